"""A CARLA recording written by ``scripts/record_carla.py``'s own writers from stand-ins of the
CARLA client's measurement classes (``test_carla``, ``test_radar_points``,
``test_fuzz_readers``)."""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion_depth.data.carla import encode_carla_depth
from helpers import REPO

CACHE_STEP = 1 / 256  # the prepared cache stores depth in 1/256 m
H, W, FOV = 64, 96, 90.0  # recorded camera: focal 48 px, principal point (48, 32)


def _load_recorder():
    spec = importlib.util.spec_from_file_location("record_carla", REPO / "scripts/record_carla.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


recorder = _load_recorder()


# Stand-ins with the attribute names of the CARLA client's measurement classes.
@dataclass
class Location:
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


@dataclass
class Rotation:
    pitch: float = 0.0
    yaw: float = 0.0
    roll: float = 0.0


@dataclass
class Transform:
    location: Location
    rotation: Rotation


@dataclass
class FakeImage:  # carla.Image
    raw_data: bytes
    width: int
    height: int
    fov: float


@dataclass
class FakeDetection:  # carla.RadarDetection
    depth: float
    azimuth: float
    altitude: float
    velocity: float


def pixels(sparse) -> list[tuple[int, int]]:
    """The (row, column) of every non-zero pixel, in row-major order."""
    return [(int(r), int(c)) for r, c in np.argwhere(np.asarray(sparse))]


def fake_image(rgb: np.ndarray, fov: float = FOV) -> FakeImage:
    """R, G, B codes as a camera's BGRA raw_data."""
    alpha = np.full(rgb.shape[:2] + (1,), 255, np.uint8)
    raw = np.concatenate([rgb[..., ::-1], alpha], axis=-1).tobytes()
    return FakeImage(raw, rgb.shape[1], rgb.shape[0], fov)


# Radar 0.8 m ahead, 0.4 m left and 0.9 m below the camera, turned 30° to the right.
RADAR_POSE = Transform(Location(0.8, -0.4, -0.9), Rotation(yaw=30.0))


def detection_at(camera_point, pose: Transform = RADAR_POSE, velocity: float = -1.5):
    """The detection CARLA would report for a camera-frame point, worked out by hand for a
    pure-yaw radar pose: radar point = Rz(-yaw) (p - t), then range, azimuth, altitude."""
    yaw = math.radians(pose.rotation.yaw)
    px = camera_point[0] - pose.location.x
    py = camera_point[1] - pose.location.y
    pz = camera_point[2] - pose.location.z
    x = math.cos(yaw) * px + math.sin(yaw) * py
    y = -math.sin(yaw) * px + math.cos(yaw) * py
    depth = math.sqrt(x * x + y * y + pz * pz)
    return FakeDetection(depth, math.atan2(y, x), math.asin(pz / depth), velocity)


def scene_depth(frame: int) -> np.ndarray:
    """Ground 4-60 m, the top rows sky (CARLA's 1000 m far plane)."""
    rows = np.arange(H, dtype=np.float64)[:, None]
    depth = np.broadcast_to(4.0 + rows * 0.9 + (frame % 50) * 0.37, (H, W)).copy()
    depth += np.arange(W)[None, :] * 0.011
    depth[:6] = 1000.0
    return depth


def scene_rgb(frame: int) -> np.ndarray:
    rng = np.random.default_rng(frame)
    return rng.integers(0, 256, (H, W, 3), dtype=np.uint8)


SPLIT_FRAMES = {
    "train": [(100, "ClearNoon"), (110, "HardRainNoon"), (120, "ClearNight"), (130, "CloudyNoon")],
    "val": [(200, "FoggyNoon"), (210, "WetCloudySunset")],
    "test": [(300, "ClearNoon"), (310, "SoftRainSunset")],
}


def record_fixture(root: Path) -> Path:
    """A recording written by the recorder's own writing functions: per frame one detection at
    camera point (20, 2, -1), one behind the camera, one outside the image; in frame 100 also
    two on one pixel, at 30 m and 24 m."""
    for split, frames in SPLIT_FRAMES.items():
        for frame, weather in frames:
            radar = [
                detection_at((20.0, 2.0, -1.0)),
                detection_at((-5.0, 0.0, 0.0)),  # behind the camera
                detection_at((10.0, 30.0, 0.0)),  # far outside the right edge
            ]
            if frame == 100:
                radar += [detection_at((30.0, -6.0, 3.0)), detection_at((24.0, -4.8, 2.4))]
            recorder.write_frame(
                root,
                split,
                frame,
                fake_image(scene_rgb(frame)),
                fake_image(encode_carla_depth(scene_depth(frame))),
                radar,
                RADAR_POSE,
                weather,
            )
    return root
