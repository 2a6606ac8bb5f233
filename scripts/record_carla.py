#!/usr/bin/env python
"""Record a CARLA dataset for ``dataset=carla``, in exactly the folder format that
:mod:`fusion_depth.data.carla` reads (see its docstring).

An ego vehicle on autopilot carries an RGB camera, a depth camera at the same pose with the same
resolution and field of view, and a radar on the front bumper. The world runs in synchronous
mode, so the three measurements of a recorded frame belong to the same simulation step. The
weather cycles through the platform's conditions (day, night, fog, rain, cloudy), a block of
frames each. Run it once per split, e.g. on different towns for the test set::

    python scripts/record_carla.py --out /data/carla --split train --frames 6000 --town Town03
    python scripts/record_carla.py --out /data/carla --split val --frames 800 --town Town05
    python scripts/record_carla.py --out /data/carla --split test --frames 600 --town Town10HD

Needs a running CARLA server (0.9.x) and its Python client (``pip install carla==<the server's
version>``). The writing functions take duck-typed measurements (anything with the attributes of
``carla.Image``, ``carla.RadarDetection``, ``carla.Transform``), so they work and are tested
without CARLA.
"""

from __future__ import annotations

import argparse
import csv
import io
import logging
import queue
import random
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from fusion_depth.data.carla import RADAR_COLUMNS, SENSOR_DIRS, relative_transform
from fusion_depth.data.depth_io import write_rgb_png
from fusion_depth.utils.atomic import write_json_atomic, write_text_atomic

log = logging.getLogger("record_carla")

# condition -> (name written to meta.json, CARLA preset it starts from, parameters changed).
# CARLA has no fog preset, and night presets only from 0.9.12 on: both are derived from ClearNoon.
WEATHERS: dict[str, tuple[str, str, dict[str, float]]] = {
    "day": ("ClearNoon", "ClearNoon", {}),
    "night": ("ClearNight", "ClearNoon", {"sun_altitude_angle": -90.0}),
    "fog": ("FoggyNoon", "ClearNoon", {"fog_density": 60.0, "fog_distance": 3.0, "wetness": 20.0}),
    "rain": ("HardRainNoon", "HardRainNoon", {}),
    "cloudy": ("CloudyNoon", "CloudyNoon", {}),
}

# Sensor poses on the vehicle (UE4 axes: x forward, y right, z up; metres, degrees).
CAMERA_POSE = {
    "location": {"x": 1.5, "y": 0.0, "z": 1.6},
    "rotation": {"pitch": 0.0, "yaw": 0.0, "roll": 0.0},
}
RADAR_POSE = {  # front bumper
    "location": {"x": 2.3, "y": 0.0, "z": 0.7},
    "rotation": {"pitch": 0.0, "yaw": 0.0, "roll": 0.0},
}
SYNC_DELTA_S = 0.05  # simulation step in synchronous mode: 20 Hz


def frame_name(frame: int) -> str:
    """File name stem of a frame: CARLA's frame number, zero-padded so names sort in order."""
    return f"{int(frame):08d}"


def image_to_rgb(image: Any) -> np.ndarray:
    """A ``carla.Image``'s ``raw_data`` (BGRA bytes, row-major) as uint8 (H, W, 3) R, G, B."""
    height, width = int(image.height), int(image.width)
    raw = np.frombuffer(bytes(image.raw_data), dtype=np.uint8)
    if raw.size != height * width * 4:
        raise ValueError(f"image raw_data has {raw.size} bytes, expected {height}x{width}x4 (BGRA)")
    return raw.reshape(height, width, 4)[..., 2::-1].copy()


def write_image(image: Any, path: str | Path) -> None:
    """A camera or depth camera image as an RGB PNG: the same channels ``save_to_disk`` writes
    without a colour converter, so depth keeps CARLA's exact 24-bit encoding."""
    write_rgb_png(path, image_to_rgb(image))


def write_radar(detections: Iterable[Any], path: str | Path) -> int:
    """A ``carla.RadarMeasurement`` (or any iterable of objects with ``depth``, ``azimuth``,
    ``altitude``, ``velocity``) as the radar CSV; returns the number of detections."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(RADAR_COLUMNS)
    count = 0
    for detection in detections:
        writer.writerow([repr(float(getattr(detection, name))) for name in RADAR_COLUMNS])
        count += 1
    write_text_atomic(path, buffer.getvalue())
    return count


def transform_to_dict(transform: Any) -> dict[str, dict[str, float]]:
    """A ``carla.Transform`` (``location.x/y/z``, ``rotation.pitch/yaw/roll``) as JSON data."""
    if isinstance(transform, dict):
        loc, rot = transform["location"], transform["rotation"]
        return {
            "location": {k: float(loc.get(k, 0.0)) for k in ("x", "y", "z")},
            "rotation": {k: float(rot.get(k, 0.0)) for k in ("pitch", "yaw", "roll")},
        }
    loc, rot = transform.location, transform.rotation
    return {
        "location": {k: float(getattr(loc, k)) for k in ("x", "y", "z")},
        "rotation": {k: float(getattr(rot, k)) for k in ("pitch", "yaw", "roll")},
    }


def write_meta(
    path: str | Path,
    fov: float,
    weather: str,
    radar_to_camera: Any,
    **extra: Any,
) -> None:
    """The frame's metadata: camera field of view (degrees), weather preset name, and the
    radar's pose in the camera frame (a ``carla.Transform`` or its JSON form)."""
    meta = {
        "fov": float(fov),
        "condition": str(weather),
        "radar_to_camera": transform_to_dict(radar_to_camera),
        **extra,
    }
    write_json_atomic(path, meta)


def write_frame(
    out: str | Path,
    split: str,
    frame: int,
    rgb: Any,
    depth: Any,
    radar: Iterable[Any],
    radar_to_camera: Any,
    weather: str,
    **extra: Any,
) -> str:
    """One frame's four files under ``out/split``; the metadata last, since the reader treats a
    frame as recorded once its ``meta/<frame>.json`` exists. Returns the frame's name."""
    if (rgb.width, rgb.height) != (depth.width, depth.height) or float(rgb.fov) != float(depth.fov):
        raise ValueError(
            f"frame {frame}: the depth camera ({depth.width}x{depth.height}, fov {depth.fov}) "
            f"must match the RGB camera ({rgb.width}x{rgb.height}, fov {rgb.fov})"
        )
    name = frame_name(frame)
    split_dir = Path(out) / split
    files = {
        sensor: split_dir / sensor / f"{name}{suffix}" for sensor, suffix in SENSOR_DIRS.items()
    }
    write_image(rgb, files["rgb"])
    write_image(depth, files["depth"])
    write_radar(radar, files["radar"])
    write_meta(files["meta"], rgb.fov, weather, radar_to_camera, frame=int(frame), **extra)
    return name


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--host", default="127.0.0.1", help="CARLA server host")
    parser.add_argument("--port", type=int, default=2000, help="CARLA server port")
    parser.add_argument("--tm-port", type=int, default=8000, help="traffic manager port")
    parser.add_argument("--out", required=True, help="dataset root; frames go to OUT/SPLIT/")
    parser.add_argument("--split", choices=("train", "val", "test"), default="train")
    parser.add_argument("--frames", type=int, default=1000, help="frames to record")
    parser.add_argument(
        "--resolution", default="640x480", help="camera WIDTHxHEIGHT (default 640x480)"
    )
    parser.add_argument("--fov", type=float, default=90.0, help="horizontal field of view (°)")
    parser.add_argument(
        "--conditions",
        default="day,night,fog,rain,cloudy",
        help=f"weathers to cycle through, a comma-separated subset of {list(WEATHERS)}",
    )
    parser.add_argument(
        "--frames-per-weather", type=int, default=50, help="frames recorded per weather block"
    )
    parser.add_argument(
        "--every", type=int, default=10, help="simulation steps (of 0.05 s) between frames"
    )
    parser.add_argument("--town", default=None, help="load this map first (e.g. Town03)")
    parser.add_argument("--vehicle", default="vehicle.tesla.model3", help="ego blueprint")
    parser.add_argument("--radar-range", type=float, default=100.0, help="metres")
    parser.add_argument("--radar-vertical-fov", type=float, default=10.0, help="degrees")
    parser.add_argument("--radar-points", type=int, default=15000, help="points per second")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    try:
        width, height = (int(v) for v in args.resolution.lower().split("x"))
    except ValueError:
        parser.error(f"--resolution {args.resolution!r}: expected WIDTHxHEIGHT, e.g. 640x480")
    args.width, args.height = width, height
    args.conditions = [c.strip() for c in args.conditions.split(",") if c.strip()]
    unknown = [c for c in args.conditions if c not in WEATHERS]
    if unknown or not args.conditions:
        parser.error(f"--conditions {unknown}: expected a subset of {list(WEATHERS)}")
    if args.frames < 1 or args.frames_per_weather < 1 or args.every < 1:
        parser.error("--frames, --frames-per-weather and --every must be at least 1")
    return args


def import_carla() -> Any:
    """The ``carla`` client module, or exit with how to get it."""
    try:
        import carla
    except ImportError:
        sys.exit(
            "record_carla.py needs the CARLA Python client, which is not installed: "
            "pip install carla==<your CARLA server's version> (or put the server's "
            "PythonAPI/carla/dist/carla-*.egg or .whl on PYTHONPATH), then start the server "
            "(./CarlaUE4.sh) and run this again."
        )
    return carla


def _set_weather(carla: Any, world: Any, condition: str) -> str:
    name, preset, changes = WEATHERS[condition]
    preset = name if hasattr(carla.WeatherParameters, name) else preset
    world.set_weather(getattr(carla.WeatherParameters, preset))
    if changes and preset != name:
        weather = world.get_weather()  # a copy: the preset itself stays untouched
        for key, value in changes.items():
            setattr(weather, key, value)
        world.set_weather(weather)
    return name


def _carla_transform(carla: Any, pose: dict) -> Any:
    loc, rot = pose["location"], pose["rotation"]
    return carla.Transform(
        carla.Location(x=loc["x"], y=loc["y"], z=loc["z"]),
        carla.Rotation(pitch=rot["pitch"], yaw=rot["yaw"], roll=rot["roll"]),
    )


def _next_of(q: queue.Queue, frame: int, what: str, timeout: float = 10.0) -> Any:
    """The measurement of simulation step ``frame`` (older ones are dropped)."""
    while True:
        try:
            data = q.get(timeout=timeout)
        except queue.Empty:
            raise RuntimeError(
                f"no {what} measurement for frame {frame} within {timeout} s"
            ) from None
        if data.frame == frame:
            return data
        if data.frame > frame:
            raise RuntimeError(f"{what}: got frame {data.frame} while waiting for {frame}")


def _enter_synchronous_mode(client: Any, world: Any, args: argparse.Namespace) -> tuple[Any, Any]:
    """Fixes the world's step and syncs the traffic manager; returns original settings, manager."""
    original = world.get_settings()
    settings = world.get_settings()
    settings.synchronous_mode = True
    settings.fixed_delta_seconds = SYNC_DELTA_S
    world.apply_settings(settings)
    traffic = client.get_trafficmanager(args.tm_port)
    traffic.set_synchronous_mode(True)
    traffic.set_random_device_seed(args.seed)
    return original, traffic


def _spawn_ego(
    world: Any, library: Any, traffic: Any, args: argparse.Namespace, actors: list[Any]
) -> Any:
    """Spawns the ego vehicle at the first free spawn point, on autopilot, and returns it."""
    spawn_points = world.get_map().get_spawn_points()
    random.shuffle(spawn_points)
    blueprint = library.find(args.vehicle)
    vehicle = next(
        (v for p in spawn_points if (v := world.try_spawn_actor(blueprint, p)) is not None),
        None,
    )
    if vehicle is None:
        raise RuntimeError("could not spawn the ego vehicle at any spawn point")
    actors.append(vehicle)  # listed at once, so that it is destroyed whatever fails next
    vehicle.set_autopilot(True, traffic.get_port())
    return vehicle


def _spawn_sensors(
    carla: Any, world: Any, library: Any, vehicle: Any, args: argparse.Namespace, actors: list[Any]
) -> dict[str, Any]:
    """Attaches the RGB camera, the depth camera and the radar to the vehicle, by name."""
    sensors: dict[str, Any] = {}
    for name, blueprint, pose in (
        ("rgb", "sensor.camera.rgb", CAMERA_POSE),
        ("depth", "sensor.camera.depth", CAMERA_POSE),
        ("radar", "sensor.other.radar", RADAR_POSE),
    ):
        bp = library.find(blueprint)
        if name == "radar":
            bp.set_attribute("horizontal_fov", str(args.fov))
            bp.set_attribute("vertical_fov", str(args.radar_vertical_fov))
            bp.set_attribute("range", str(args.radar_range))
            bp.set_attribute("points_per_second", str(args.radar_points))
        else:
            bp.set_attribute("image_size_x", str(args.width))
            bp.set_attribute("image_size_y", str(args.height))
            bp.set_attribute("fov", str(args.fov))
        sensor = world.spawn_actor(bp, _carla_transform(carla, pose), attach_to=vehicle)
        actors.append(sensor)  # destroyed even if a later sensor fails to spawn
        sensors[name] = sensor
    return sensors


def _record_frames(
    carla: Any, world: Any, queues: dict[str, queue.Queue], args: argparse.Namespace
) -> int:
    """Steps the world, cycling the weather, and writes every ``args.every``-th step's frame."""
    radar_to_camera = relative_transform(CAMERA_POSE, RADAR_POSE)
    written = 0
    condition = None
    weather = ""
    for i in range(args.frames):
        wanted = args.conditions[(i // args.frames_per_weather) % len(args.conditions)]
        if wanted != condition:
            condition, weather = wanted, _set_weather(carla, world, wanted)
            log.info("weather %s (%s) from frame %d", weather, condition, i)
        for _ in range(args.every - 1):
            world.tick()
        frame = world.tick()
        data = {name: _next_of(q, frame, name) for name, q in queues.items()}
        write_frame(
            args.out,
            args.split,
            frame,
            data["rgb"],
            data["depth"],
            data["radar"],
            radar_to_camera,
            weather,
            town=world.get_map().name,
            radar_range=args.radar_range,
        )
        written += 1
        if written % 100 == 0:
            log.info("%d / %d frames written to %s", written, args.frames, args.out)
    return written


def _tear_down(world: Any, traffic: Any, original: Any, actors: list[Any]) -> None:
    """Destroys the actors, newest first, and gives the world back its asynchronous settings."""
    for actor in reversed(actors):
        if hasattr(actor, "stop"):
            actor.stop()
        actor.destroy()
    traffic.set_synchronous_mode(False)
    world.apply_settings(original)


def record(args: argparse.Namespace) -> int:
    """Drives the simulator and writes ``args.frames`` frames; returns how many were written."""
    carla = import_carla()
    random.seed(args.seed)
    client = carla.Client(args.host, args.port)
    client.set_timeout(30.0)
    world = client.load_world(args.town) if args.town else client.get_world()
    original, traffic = _enter_synchronous_mode(client, world, args)
    actors: list[Any] = []
    try:
        library = world.get_blueprint_library()
        vehicle = _spawn_ego(world, library, traffic, args, actors)
        sensors = _spawn_sensors(carla, world, library, vehicle, args, actors)
        queues: dict[str, queue.Queue] = {name: queue.Queue() for name in sensors}
        for name, sensor in sensors.items():
            sensor.listen(queues[name].put)
        return _record_frames(carla, world, queues, args)
    finally:
        _tear_down(world, traffic, original, actors)


def main(argv: Sequence[str] | None = None) -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    args = parse_args(argv)
    import_carla()  # fail before anything else when the client is missing
    written = record(args)
    print(f"wrote {written} frames to {Path(args.out) / args.split}")


if __name__ == "__main__":
    main()
