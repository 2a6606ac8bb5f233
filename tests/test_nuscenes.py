"""``dataset=nuscenes`` on a tiny database in the real nuScenes schema, read by the real devkit.

The fixture writes the 13 JSON tables, a map mask, radar ``.pcd`` files in the nuScenes binary PCD
format (18 fields), lidar ``.pcd.bin`` files and JPEG images. Points are placed by choosing the
pixel and depth they must end up at, then taking them back through the camera calibration, the
ego pose at the camera's timestamp, the ego pose at the sweep's timestamp and the sensor's
calibration, with rotation matrices written out here (not the devkit's), so a convention error
on either side fails the comparison.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import command_message
from PIL import Image

pytest.importorskip("nuscenes")

from nuscenes.nuscenes import NuScenes, NuScenesExplorer  # noqa: E402
from nuscenes.utils.data_classes import LidarPointCloud, RadarPointCloud  # noqa: E402
from nuscenes.utils.geometry_utils import BoxVisibility, view_points  # noqa: E402
from pyquaternion import Quaternion  # noqa: E402

import fusion_depth.data.nuscenes as nus  # noqa: E402
from fusion_depth.data import RADAR_POINT_FIELDS  # noqa: E402
from fusion_depth.data.nuscenes import NuScenesDepth  # noqa: E402

# --- geometry -----------------------------------------------------------------------------

CAM_W, CAM_H = 128, 72  # the fixture's "1600x900": 16:9
INTRINSIC = [[100.0, 0.0, 64.0], [0.0, 100.0, 36.0], [0.0, 0.0, 1.0]]
# The prepared size in most tests: scale 0.5 (64x36), then 4 rows cropped from the top, so the
# intrinsics become f = 50, c = (0.5 (64 + 0.5) - 0.5, 0.5 (36 + 0.5) - 0.5 - 4): pixel centres
# at integers, as the devkit's.
HEIGHT, WIDTH = 32, 64
F_OUT, CX_OUT, CY_OUT = 50.0, 31.75, 13.75


def yaw_matrix(degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_quaternion(degrees: float) -> list[float]:
    half = math.radians(degrees) / 2
    return [math.cos(half), 0.0, 0.0, math.sin(half)]


@dataclass(frozen=True)
class Rigid:
    """A frame inside its parent: ``parent = R @ child + t``; ``quaternion`` is R as nuScenes
    stores it (w, x, y, z)."""

    rotation: np.ndarray
    translation: tuple[float, float, float]
    quaternion: list[float]

    @classmethod
    def yaw(cls, degrees: float, translation: tuple[float, float, float]) -> Rigid:
        return cls(yaw_matrix(degrees), translation, yaw_quaternion(degrees))

    def to_parent(self, p: np.ndarray) -> np.ndarray:
        return self.rotation @ p + np.asarray(self.translation)[:, None]

    def from_parent(self, p: np.ndarray) -> np.ndarray:
        return self.rotation.T @ (p - np.asarray(self.translation)[:, None])


# Camera axes (x right, y down, z forward) in the ego frame (x forward, y left, z up).
CAMERA = Rigid(
    np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
    (1.0, 0.0, 1.5),
    [0.5, -0.5, 0.5, -0.5],
)
SENSORS = {
    "CAM_FRONT": ("camera", CAMERA),
    "RADAR_FRONT": ("radar", Rigid.yaw(10.0, (3.5, 0.2, 0.6))),
    "RADAR_FRONT_LEFT": ("radar", Rigid.yaw(80.0, (3.4, 0.6, 0.5))),
    "LIDAR_TOP": ("lidar", Rigid.yaw(-90.0, (0.95, 0.0, 1.85))),
}


def ego_poses(i: int) -> dict[str, Rigid]:
    """Ego poses of sample ``i``'s sweeps: each timestamp its own, all different."""
    x = 20.0 * i
    return {
        "CAM_FRONT": Rigid.yaw(30.0, (100.0 + x, 50.0, 0.0)),
        "RADAR_FRONT": Rigid.yaw(31.0, (100.5 + x, 50.2, 0.0)),
        "RADAR_FRONT/prev": Rigid.yaw(28.0, (99.0 + x, 49.5, 0.0)),
        "RADAR_FRONT_LEFT": Rigid.yaw(30.8, (100.4 + x, 50.15, 0.0)),
        "LIDAR_TOP": Rigid.yaw(30.5, (100.2 + x, 50.1, 0.05)),
        "LIDAR_TOP/prev": Rigid.yaw(29.0, (99.5 + x, 49.8, 0.0)),
    }


def camera_point(row: float, col: float, depth: float) -> np.ndarray:
    """The camera-frame point seen at the centre of prepared pixel (row, col) at ``depth``."""
    return np.array(
        [
            (col - CX_OUT) * depth / F_OUT,
            (row - CY_OUT) * depth / F_OUT,
            depth,
        ]
    )


def in_sensor(points_cam: np.ndarray, i: int, sweep: str) -> np.ndarray:
    """Camera-frame points (3, N) of sample ``i`` as ``sweep``'s sensor recorded them."""
    poses = ego_poses(i)
    world = poses["CAM_FRONT"].to_parent(CAMERA.to_parent(points_cam))
    sensor = SENSORS[sweep.split("/")[0]][1]
    return sensor.from_parent(poses[sweep].from_parent(world))


VALID = {"dyn_prop": 1, "ambig_state": 3, "invalid_state": 0}
# sweep -> [(row, col, depth, radar states)]; what each prepared pixel must hold.
RADAR_POINTS = {
    "RADAR_FRONT": [
        (20, 10, 12.0, VALID),
        (22, 40, 30.0, {**VALID, "invalid_state": 1}),  # low RCS: default filters drop it
        (25, 50, 8.0, {**VALID, "dyn_prop": 0, "ambig_state": 1}),  # ambiguous Doppler
        (18, 30, 20.0, {**VALID, "dyn_prop": 7}),  # "stopped": not in default dynprop_states
    ],
    "RADAR_FRONT/prev": [(15, 20, 25.0, VALID)],
    "RADAR_FRONT_LEFT": [(12, 5, 15.0, VALID)],
}
LIDAR_POINTS = {
    "LIDAR_TOP": [
        camera_point(10, 10, 15.0),
        camera_point(16, 32, 20.0),  # a shared pixel, farther point first ...
        camera_point(16, 32, 10.0),  # ... the nearer one wins
        camera_point(16, 33, 9.0),  # a shared pixel, nearer point first
        camera_point(16, 33, 11.0),
        np.array([0.5, 0.2, -5.0]),  # behind the camera
        camera_point(20, 20, 0.5),  # closer than min_distance
        camera_point(10, 70, 10.0),  # right of the image
        camera_point(-2, 10, 10.0),  # in the rows cropped away at the top
    ],
    "LIDAR_TOP/prev": [camera_point(28, 60, 40.0)],
}
LIDAR_EXPECTED = {(10, 10): 15.0, (16, 32): 10.0, (16, 33): 9.0}
# Annotated 1 m boxes, (scene, keyframe) -> [(category, where)]: ``where`` is the lidar point of
# LIDAR_POINTS (camera_point's row, col, depth) as keyframe ``seen_in`` recorded it, so a box
# covers that point in the world. RadarNet's merged target clears vehicle and human boxes.
ANNOTATIONS = {
    ("scene-0061", 1): [
        ("vehicle.car", 1, (10, 10, 15.0)),  # keyframe 1's point: not merged into keyframe 0
        ("static_object.bicycle_rack", 1, (16, 33, 9.0)),  # not a moving category: kept
    ],
    ("scene-0061", 0): [
        # where keyframe 1's nearer point at (16, 32) lands in keyframe 0: not merged there
        ("human.pedestrian.adult", 1, (16, 32, 10.0)),
    ],
}
RADAR_DEFAULT = {(20, 10): 12.0}

# --- the database ---------------------------------------------------------------------------

RADAR_FIELDS = (
    "x y z dyn_prop id rcs vx vy vx_comp vy_comp is_quality_valid ambig_state x_rms y_rms "
    "invalid_state pdh0 vx_rms vy_rms"
).split()
RADAR_SIZES = [4, 4, 4, 1, 2, 4, 4, 4, 4, 4, 1, 1, 1, 1, 1, 1, 1, 1]
RADAR_TYPES = "F F F I I F F F F F I I I I I I I I".split()
_PACK = {("F", 4): "<f", ("I", 1): "<b", ("I", 2): "<h"}


def write_radar_pcd(path: Path, xyz: np.ndarray, states: list[dict]) -> None:
    """A radar sweep in the nuScenes PCD v0.7 binary format (18 fields, little-endian)."""
    n = xyz.shape[1]
    header = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS " + " ".join(RADAR_FIELDS),
        "SIZE " + " ".join(map(str, RADAR_SIZES)),
        "TYPE " + " ".join(RADAR_TYPES),
        "COUNT " + " ".join(["1"] * len(RADAR_FIELDS)),
        f"WIDTH {n}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {n}",
        "DATA binary",
    ]
    body = bytearray()
    for k in range(n):
        values = {name: 0 for name in RADAR_FIELDS}
        values.update({"x": xyz[0, k], "y": xyz[1, k], "z": xyz[2, k], "id": k, "rcs": 5.0})
        values.update({"is_quality_valid": 1, "pdh0": 1, "x_rms": 3, "y_rms": 3})
        values.update(states[k])
        for name, size, kind in zip(RADAR_FIELDS, RADAR_SIZES, RADAR_TYPES, strict=True):
            body += struct.pack(_PACK[(kind, size)], values[name])
    # The devkit asserts that data follows every field it reads (end < len), so the published
    # files end with a byte after the last point.
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(("\n".join(header) + "\n").encode() + bytes(body) + b"\n")


def write_lidar_bin(path: Path, xyz: np.ndarray) -> None:
    """A lidar sweep as nuScenes stores it: float32 (x, y, z, intensity, ring index) rows."""
    n = xyz.shape[1]
    rows = np.zeros((n, 5), dtype=np.float32)
    rows[:, :3] = xyz.T
    rows[:, 3] = 10.0
    rows[:, 4] = np.arange(n) % 32
    path.parent.mkdir(parents=True, exist_ok=True)
    rows.tofile(path)


def write_jpeg(path: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:CAM_H, 0:CAM_W]
    image = np.stack([xx * 2, yy * 3, (xx + yy) % 256], -1) + rng.integers(0, 30, (CAM_H, CAM_W, 3))
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.clip(image, 0, 255).astype(np.uint8)).save(path, quality=95)


def token(*parts: object) -> str:
    return hashlib.md5("/".join(map(str, parts)).encode()).hexdigest()


def _describe_sensors(tables: dict[str, list]) -> None:
    """Fills the tables every version shares: categories, attributes, visibilities, sensors."""
    tables["category"] = [
        {"token": token("cat"), "name": "vehicle.car", "description": "Vehicle designed for 4 ppl"}
    ]
    tables["attribute"] = [
        {"token": token("attr"), "name": "vehicle.parked", "description": "Vehicle is stationary"}
    ]
    tables["visibility"] = [
        {"token": str(i + 1), "level": level, "description": f"visibility of whole object {level}"}
        for i, level in enumerate(["v0-40", "v40-60", "v60-80", "v80-100"])
    ]
    for channel, (modality, rigid) in SENSORS.items():
        tables["sensor"].append({"token": token(channel), "channel": channel, "modality": modality})
        tables["calibrated_sensor"].append(
            {
                "token": token("calib", channel),
                "sensor_token": token(channel),
                "translation": list(rigid.translation),
                "rotation": rigid.quaternion,
                "camera_intrinsic": INTRINSIC if modality == "camera" else [],
            }
        )


def _add_log_and_map(root: Path, version: str, tables: dict[str, list]) -> str:
    """Adds the log and its map, a blank mask written under ``maps/``; returns the log token."""
    log_token = token(version, "log")
    tables["log"].append(
        {
            "token": log_token,
            "logfile": "n015-2018-07-24-11-22-45+0800",
            "vehicle": "n015",
            "date_captured": "2018-07-24",
            "location": "singapore-onenorth",
        }
    )
    map_file = f"maps/{token(version, 'map')}.png"
    (root / "maps").mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(root / map_file)
    tables["map"].append(
        {
            "token": token(version, "map"),
            "log_tokens": [log_token],
            "category": "semantic_prior",
            "filename": map_file,
        }
    )
    return log_token


def _write_sweep_file(root: Path, sweep: str, i: int, stamp: int, key: bool) -> tuple[str, str]:
    """Writes sample ``i``'s file of ``sweep``; returns its filename and ``fileformat``."""
    channel = sweep.split("/")[0]
    folder = "samples" if key else "sweeps"
    stem = f"n015-2018-07-24-11-22-45+0800__{channel}__{stamp}"
    if channel == "CAM_FRONT":
        filename, fmt = f"{folder}/{channel}/{stem}.jpg", "jpg"
        write_jpeg(root / filename, seed=stamp % 1000)
    elif channel.startswith("RADAR"):
        filename, fmt = f"{folder}/{channel}/{stem}.pcd", "pcd"
        points = RADAR_POINTS[sweep]
        xyz = in_sensor(np.stack([camera_point(*p[:3]) for p in points], 1), i, sweep)
        write_radar_pcd(root / filename, xyz, [p[3] for p in points])
    else:
        filename, fmt = f"{folder}/{channel}/{stem}.pcd.bin", "pcd"
        xyz = in_sensor(np.stack(LIDAR_POINTS[sweep], 1), i, sweep)
        write_lidar_bin(root / filename, xyz)
    return filename, fmt


def _add_sweeps(
    root: Path,
    version: str,
    tables: dict[str, list],
    scene: str,
    i: int,
    sample_token: str,
    clock: int,
    last_sd: dict[str, dict],
) -> None:
    """Writes sample ``i``'s sweeps; adds their ego poses and sample_data, chained by channel."""
    sweeps = [
        ("RADAR_FRONT/prev", -90000, False),
        ("RADAR_FRONT", -20000, True),
        ("RADAR_FRONT_LEFT", -15000, True),
        ("LIDAR_TOP/prev", -40000, False),
        ("LIDAR_TOP", 10000, True),
        ("CAM_FRONT", 0, True),
    ]
    for sweep, offset, key in sweeps:
        channel = sweep.split("/")[0]
        stamp = clock + offset
        filename, fmt = _write_sweep_file(root, sweep, i, stamp, key)
        pose = ego_poses(i)[sweep]
        pose_token = token(version, scene, i, sweep, "pose")
        tables["ego_pose"].append(
            {
                "token": pose_token,
                "timestamp": stamp,
                "rotation": pose.quaternion,
                "translation": list(pose.translation),
            }
        )
        record = {
            "token": token(version, scene, i, sweep),
            "sample_token": sample_token,
            "ego_pose_token": pose_token,
            "calibrated_sensor_token": token("calib", channel),
            "timestamp": stamp,
            "fileformat": fmt,
            "is_key_frame": key,
            "height": CAM_H if channel == "CAM_FRONT" else 0,
            "width": CAM_W if channel == "CAM_FRONT" else 0,
            "filename": filename,
            "prev": last_sd[channel]["token"] if channel in last_sd else "",
            "next": "",
        }
        if channel in last_sd:
            last_sd[channel]["next"] = record["token"]
        last_sd[channel] = record
        tables["sample_data"].append(record)


def _add_annotations(tables: dict[str, list], version: str, samples: dict[str, list]) -> None:
    """The :data:`ANNOTATIONS` boxes as sample_annotation records, one instance each."""
    categories = {row["name"]: row["token"] for row in tables["category"]}
    for (scene, i), boxes in ANNOTATIONS.items():
        if scene not in samples:
            continue
        for category, seen_in, (row, col, depth) in boxes:
            if category not in categories:
                categories[category] = token("cat", category)
                tables["category"].append(
                    {"token": categories[category], "name": category, "description": category}
                )
            centre = ego_poses(seen_in)["CAM_FRONT"].to_parent(
                CAMERA.to_parent(camera_point(row, col, depth)[:, None])
            )[:, 0]
            ann, instance = token(version, scene, i, category), token(version, scene, category)
            tables["instance"].append(
                {
                    "token": instance,
                    "category_token": categories[category],
                    "nbr_annotations": 1,
                    "first_annotation_token": ann,
                    "last_annotation_token": ann,
                }
            )
            tables["sample_annotation"].append(
                {
                    "token": ann,
                    "sample_token": samples[scene][i],
                    "instance_token": instance,
                    "visibility_token": "4",
                    "attribute_tokens": [],
                    "translation": centre.tolist(),
                    "size": [1.0, 1.0, 1.0],
                    "rotation": [1.0, 0.0, 0.0, 0.0],
                    "prev": "",
                    "next": "",
                    "num_lidar_pts": 1,
                    "num_radar_pts": 0,
                }
            )


def write_nuscenes(root: Path, version: str, scenes: list[tuple[str, str, int]]) -> dict:
    """Writes ``<root>/<version>/`` (the 13 tables), ``maps/`` and the sensor files of
    ``scenes`` = [(name, description, number of keyframes)]; returns scene -> sample tokens."""
    tables: dict[str, list] = {name: [] for name in nus.TABLES}
    _describe_sensors(tables)
    log_token = _add_log_and_map(root, version, tables)
    samples: dict[str, list[str]] = {}
    last_sd: dict[str, dict] = {}  # channel -> the previous sample_data record of its chain
    clock = 1532402927000000
    for name, description, count in scenes:
        last_sd.clear()
        tokens = [token(version, name, "sample", i) for i in range(count)]
        samples[name] = tokens
        tables["scene"].append(
            {
                "token": token(version, name),
                "log_token": log_token,
                "nbr_samples": count,
                "first_sample_token": tokens[0],
                "last_sample_token": tokens[-1],
                "name": name,
                "description": description,
            }
        )
        for i, sample_token in enumerate(tokens):
            clock += 500000
            tables["sample"].append(
                {
                    "token": sample_token,
                    "timestamp": clock,
                    "prev": tokens[i - 1] if i else "",
                    "next": tokens[i + 1] if i + 1 < count else "",
                    "scene_token": token(version, name),
                }
            )
            _add_sweeps(root, version, tables, name, i, sample_token, clock, last_sd)
    _add_annotations(tables, version, samples)
    (root / version).mkdir(parents=True, exist_ok=True)
    for name, rows in tables.items():
        (root / version / f"{name}.json").write_text(json.dumps(rows, indent=0))
    return samples


MINI_SCENES = [
    ("scene-0061", "Parked truck, construction, intersection, turn left, following a van", 2),
    ("scene-0553", "Night, wait at intersection, bicycle, rain", 2),  # night wins over rain
    ("scene-0103", "Rain, peds, big street", 2),
    ("scene-0916", "Parking lot, bicycle rack, parked bicycles, bus, many peds, ped crossing", 2),
]
TEST_SCENES = [("scene-0077", "Night, big street, bus stop", 1)]


@pytest.fixture(scope="module")
def nusc_root(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("nuscenes")
    samples = write_nuscenes(root, "v1.0-mini", MINI_SCENES)
    samples.update(write_nuscenes(root, "v1.0-test", TEST_SCENES))
    return root, samples


def make_reader(root: Path, cache: Path, split: str = "train", **options) -> NuScenesDepth:
    settings = {"version": "v1.0-mini", "height": HEIGHT, "width": WIDTH, "fill": "none"}
    return NuScenesDepth(split=split, root=root, cache_root=cache, **{**settings, **options})


def nonzero(depth_map) -> dict[tuple[int, int], float]:
    array = np.asarray(depth_map).squeeze()
    return {(int(r), int(c)): float(array[r, c]) for r, c in zip(*np.nonzero(array), strict=True)}


# --- tests ----------------------------------------------------------------------------------


def test_fixture_is_read_by_the_real_devkit(nusc_root) -> None:
    root, samples = nusc_root
    nusc = NuScenes(version="v1.0-mini", dataroot=str(root), verbose=False)
    assert [s["name"] for s in nusc.scene] == [name for name, _, _ in MINI_SCENES]
    sample = nusc.get("sample", samples["scene-0061"][0])
    assert set(sample["data"]) == set(SENSORS)
    radar_path = nusc.get_sample_data_path(sample["data"]["RADAR_FRONT"])
    cloud = RadarPointCloud.from_file(radar_path, list(range(18)), list(range(8)), list(range(5)))
    assert cloud.points.shape == (18, 4)
    assert cloud.points[3].tolist() == [1, 1, 0, 7]  # dyn_prop
    assert cloud.points[-4].tolist() == [0, 1, 0, 0]  # invalid_state
    assert RadarPointCloud.from_file(radar_path).points.shape == (18, 1)  # default filters
    lidar = LidarPointCloud.from_file(nusc.get_sample_data_path(sample["data"]["LIDAR_TOP"]))
    assert lidar.points.shape == (4, len(LIDAR_POINTS["LIDAR_TOP"]))


def test_points_land_on_the_expected_pixels_with_the_expected_depth(nusc_root, tmp_path) -> None:
    root, samples = nusc_root
    train = make_reader(root, tmp_path)
    assert len(train) == 4  # two scenes of two keyframes, each with its own ego poses
    for index in range(len(train)):
        item = train[index]
        assert item["image"].shape == (3, HEIGHT, WIDTH)
        assert nonzero(item["depth"]) == LIDAR_EXPECTED
        assert nonzero(item["sparse"]) == RADAR_DEFAULT
    # The image is the JPEG scaled by 0.5 and cut by 4 rows at the top, like the intrinsics.
    nusc = NuScenes(version="v1.0-mini", dataroot=str(root), verbose=False)
    cam = nusc.get("sample", samples["scene-0061"][0])["data"]["CAM_FRONT"]
    jpeg = Image.open(nusc.get_sample_data_path(cam)).convert("RGB")
    expected = np.asarray(jpeg.resize((64, 36), Image.Resampling.BILINEAR))[4:]
    assert np.array_equal((train[0]["image"].numpy() * 255).round().transpose(1, 2, 0), expected)


@pytest.mark.parametrize(
    ("options", "expected"),
    [
        ({"radar_filters": "off"}, {(20, 10): 12.0, (22, 40): 30.0, (25, 50): 8.0, (18, 30): 20.0}),
        (
            {"radar_filters": "custom", "radar_invalid_states": [0, 1]},
            {(20, 10): 12.0, (22, 40): 30.0},
        ),
        (
            {"radar_filters": "custom", "radar_dynprop_states": list(range(8))},
            {(20, 10): 12.0, (18, 30): 20.0},
        ),
        ({"radar_nsweeps": 2}, {(20, 10): 12.0, (15, 20): 25.0}),
        ({"radar_channels": ["RADAR_FRONT", "RADAR_FRONT_LEFT"]}, {(20, 10): 12.0, (12, 5): 15.0}),
    ],
    ids=["filters-off", "custom-invalid", "custom-dynprop", "two-sweeps", "front-left"],
)
def test_radar_filters_sweeps_and_channels(nusc_root, tmp_path, options, expected) -> None:
    root, _ = nusc_root
    train = make_reader(root, tmp_path, **options)
    for index in range(len(train)):
        assert nonzero(train[index]["sparse"]) == expected
        assert nonzero(train[index]["depth"]) == LIDAR_EXPECTED
    # The devkit's global filter settings are left alone.
    assert RadarPointCloud.invalid_states == [0] and RadarPointCloud.ambig_states == [3]
    assert list(RadarPointCloud.dynprop_states) == list(range(7))


def test_lidar_sweeps_accumulate(nusc_root, tmp_path) -> None:
    root, _ = nusc_root
    train = make_reader(root, tmp_path, lidar_nsweeps=2)
    assert nonzero(train[1]["depth"]) == {**LIDAR_EXPECTED, (28, 60): 40.0}


def test_project_points_keeps_the_nearest_and_drops_the_rest() -> None:
    k = np.array([[10.0, 0.0, 2.0], [0.0, 10.0, 1.0], [0.0, 0.0, 1.0]])
    points = np.array(
        [
            [0.0, 0.0, 5.0],  # (1, 2) at 5 m
            [0.0, 0.0, 3.0],  # same pixel, nearer: wins
            [0.0, 0.0, 0.9],  # closer than min_distance
            [0.0, 0.0, -4.0],  # behind
            [10.0, 0.0, 5.0],  # u = 22: right of the image
            [0.1, 0.0, 1.0],  # (1, 3) at exactly min_distance: kept
            [0.0, 0.0, 300.0],  # beyond the cache's 255.99 m
            [np.nan, 0.0, 5.0],
        ]
    ).T
    depth = nus.project_points(points, k, height=3, width=4, min_distance=1.0)
    assert depth.dtype == np.float32
    assert nonzero(depth) == {(1, 2): 3.0, (1, 3): 1.0}


def _distinct_pixel_points(rng, height: int, width: int, count: int) -> np.ndarray:
    """Camera-frame points (3, count) of the intrinsics below, each in its own full-resolution
    pixel: the first at pixel centres, the rest anywhere in their pixel."""
    flat = rng.choice(height * width, count, replace=False)
    v, u = (flat // width).astype(float), (flat % width).astype(float)
    offsets = rng.uniform(-0.49, 0.49, (2, count))
    offsets[:, : count // 4] = 0.0
    u, v = u + offsets[0], v + offsets[1]
    z = rng.uniform(2.0, 80.0, count)
    f, cx, cy = NUSCENES_K[0, 0], NUSCENES_K[0, 2], NUSCENES_K[1, 2]
    return np.stack([(u - cx) * z / f, (v - cy) * z / f, z])


NUSCENES_K = np.array([[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]])


def test_points_land_where_radarnet_places_them_at_full_and_scaled_resolution() -> None:
    """RadarNet's rule (setup/setup_dataset_nuscenes.py of nesl/radar-camera-fusion-depth): the
    devkit's view_points, then np.round to a pixel. At 900x1600 every point lands there; at
    448x800 (scaled by 0.5, 2 rows cut) in the pixel whose resized image shows its
    full-resolution pixel."""
    rng = np.random.default_rng(0)
    points = _distinct_pixel_points(rng, 900, 1600, 400)
    full = nus.project_points(points, NUSCENES_K, 900, 1600, min_distance=1.0)
    uv = view_points(points, NUSCENES_K, normalize=True)
    cols, rows = np.round(uv[0]).astype(int), np.round(uv[1]).astype(int)
    expected = np.zeros((900, 1600), np.float32)
    expected[rows, cols] = points[2]  # one point per pixel: the order does not matter
    np.testing.assert_array_equal(full, expected)

    image = np.zeros((900, 1600, 3), np.uint8)
    out, k = nus.resize_and_crop(image, NUSCENES_K, 448, 800)
    scaled = nus.project_points(points, k, 448, 800, min_distance=1.0)
    expected = np.zeros((448, 800), np.float32)
    out_rows, out_cols = rows // 2 - 2, cols // 2  # the 2x2 block each full pixel falls in
    inside = out_rows >= 0
    for r, c, z in sorted(
        zip(out_rows[inside], out_cols[inside], points[2][inside], strict=True),
        key=lambda p: -p[2],
    ):
        expected[r, c] = z  # the nearest last: it wins a shared pixel
    np.testing.assert_array_equal(scaled, expected)
    # The image says the same: one lit full-resolution pixel is brightest in that pixel.
    for i in range(5):
        lit = image.copy()
        lit[rows[i], cols[i]] = 255
        shown, _ = nus.resize_and_crop(lit, NUSCENES_K, 448, 800)
        if out_rows[i] >= 0:
            assert np.unravel_index(shown[..., 0].argmax(), (448, 800)) == (
                out_rows[i],
                out_cols[i],
            )


def _radarnets_ground_truth(nusc, token: str, png: Path) -> np.ndarray:
    """RadarNet's ground truth for one keyframe, by its own steps (lidar_depth_map_from_token in
    setup/setup_dataset_nuscenes.py, save_depth and load_depth in src/data_utils.py of
    nesl/radar-camera-fusion-depth): the devkit's map_pointcloud_to_image, np.round, each point
    written in turn, a 16-bit PNG of uint32(256 z) read back / 256."""
    sample = nusc.get("sample", token)
    points, depth, image = NuScenesExplorer(nusc).map_pointcloud_to_image(
        sample["data"]["LIDAR_TOP"], sample["data"]["CAM_FRONT"]
    )
    depth_map = np.zeros((image.size[1], image.size[0]))
    quantized = np.round(points).astype(int)
    for i in range(quantized.shape[1]):
        depth_map[quantized[1, i], quantized[0, i]] = depth[i]
    # Its Pillow wrote the uint32 mode-I image as a 16-bit PNG; this one writes that directly.
    Image.fromarray(np.uint32(depth_map * 256.0).astype(np.uint16)).save(png)
    return np.array(Image.open(png), dtype=np.float32) / 256.0


def test_radarnet_ground_truth_rounds_keeps_the_last_point_and_truncates() -> None:
    """Its rule on points the fixture cannot give: halves (np.round to even), several points on
    one pixel (the last written wins, not the nearest) and depths between 1/256 m steps."""
    rng = np.random.default_rng(3)
    u = np.concatenate([rng.uniform(1.01, 126.99, 300), [20.5, 21.5, 40.2, 40.4]])
    v = np.concatenate([rng.uniform(1.01, 70.99, 300), [10.5, 10.5, 30.0, 30.1]])
    depth = np.concatenate([rng.uniform(1.01, 90.0, 300), [5.123, 6.789, 7.7777, 30.0]])
    points = np.stack([u, v, np.ones_like(u)])

    class Explorer:  # the devkit's, having projected these points
        def __init__(self, nusc) -> None:
            pass

        def map_pointcloud_to_image(self, lidar_token, camera_token):
            assert (lidar_token, camera_token) == ("lidar", "camera")
            return points, depth, None

    devkit = replace(nus.require_devkit(), NuScenesExplorer=Explorer)
    sample = {"token": "s", "data": {"LIDAR_TOP": "lidar", "CAM_FRONT": "camera"}}
    rows, cols, values = nus.radarnet_ground_truth(devkit, None, sample)
    expected = np.zeros((72, 128))
    for i in range(len(u)):  # RadarNet's loop, then its uint32 PNG
        expected[int(np.round(v[i])), int(np.round(u[i]))] = depth[i]
    expected = np.uint32(expected * 256.0) / 256.0
    ours = np.zeros_like(expected)
    ours[rows, cols] = values
    np.testing.assert_array_equal(ours, expected)
    assert ours[10, 20] == np.floor(5.123 * 256) / 256  # 20.5 rounds to 20, 21.5 to 22
    assert ours[10, 22] == np.floor(6.789 * 256) / 256
    assert ours[30, 40] == 30.0  # the last written, though farther than the 7.78 m before it


@pytest.mark.parametrize("size", [(HEIGHT, WIDTH), (64, 128)], ids=["halved", "full-width"])
def test_full_resolution_ground_truth_is_radarnets(nusc_root, tmp_path, size) -> None:
    """Val and test keep RadarNet's ground truth at the camera's resolution as points; mapped
    back to full-resolution pixels they are its PNG, pixel for pixel and value for value, but
    for the rows the crop cut."""
    root, _ = nusc_root
    nusc = NuScenes(version="v1.0-mini", dataroot=str(root), verbose=False)
    height, width = size
    new_h, new_w, top, left = nus.resize_geometry(CAM_H, CAM_W, height, width)
    scale_y, scale_x = new_h / CAM_H, new_w / CAM_W
    train = make_reader(root, tmp_path, height=height, width=width)
    assert "depth_points" not in train[0]  # training scores nothing
    checked = 0
    for split in ("val", "test"):
        reader = make_reader(root, tmp_path, split, height=height, width=width)
        for index in range(len(reader)):
            expected = _radarnets_ground_truth(nusc, reader.frames[index]["id"], tmp_path / "a.png")
            rows = reader[index]["depth_points"].numpy()
            rows = rows[rows[:, 2] > 0]
            ours = np.zeros_like(expected)
            r = np.round((rows[:, 0] + 0.5 + top) / scale_y - 0.5).astype(int)
            c = np.round((rows[:, 1] + 0.5 + left) / scale_x - 0.5).astype(int)
            ours[r, c] = rows[:, 2]
            cut = int(np.ceil(top / scale_y))  # full rows above the cropped frame
            assert (expected[cut:] > 0).sum() > 0
            np.testing.assert_array_equal(ours[cut:], expected[cut:])
            assert not ours[:cut].any()
            checked += 1
    assert checked == 8


def _pixels_last_wins(points: np.ndarray, depth: np.ndarray, shape) -> np.ndarray:
    """RadarNet's drawing loop: each point on pixel np.round of (v, u), the last one wins."""
    image = np.zeros(shape)
    for k in range(points.shape[1]):
        x, y = np.round(points[:2, k]).astype(int)
        image[y, x] = depth[k]
    return image


def _clear_moving_boxes(nusc, camera_token: str, image: np.ndarray, removed) -> None:
    _, boxes, k = nusc.get_sample_data(camera_token, box_vis_level=BoxVisibility.ANY)
    for box in boxes:
        if box.name.split(".")[0] in removed:
            corners = view_points(box.corners(), view=k, normalize=True)[:2]
            x0, y0 = int(corners[0].min()), int(corners[1].min())
            x1, y1 = int(corners[0].max()), int(corners[1].max())
            image[y0:y1, x0:x1] = 0


def _radarnets_merged_target(nusc, token_: str, keyframes: int, removed) -> np.ndarray:
    """RadarNet's merge_lidar_point_clouds (setup/setup_dataset_nuscenes.py), rewritten here
    with the devkit's own point-cloud transforms and pixel loops: the keyframe's lidar image,
    then each keyframe after it and before it lifted from its camera, carried through its lidar
    and the ego poses into this camera, its moving boxes and this frame's cleared, merged
    nearer-first into empty or farther pixels."""
    explorer = NuScenesExplorer(nusc)
    main = nusc.get("sample", token_)
    main_cam = nusc.get("sample_data", main["data"]["CAM_FRONT"])
    shape = (main_cam["height"], main_cam["width"])
    points, depth, _ = explorer.map_pointcloud_to_image(
        main["data"]["LIDAR_TOP"], main["data"]["CAM_FRONT"]
    )
    merged = _pixels_last_wins(points, depth, shape)
    main_calib = nusc.get("calibrated_sensor", main_cam["calibrated_sensor_token"])

    def pose(record):
        return Quaternion(record["rotation"]).rotation_matrix, np.array(record["translation"])

    for step in ("next", "prev"):
        other = main
        for _ in range(keyframes):
            if not other[step]:
                break
            other = nusc.get("sample", other[step])
            cam = nusc.get("sample_data", other["data"]["CAM_FRONT"])
            lidar = nusc.get("sample_data", other["data"]["LIDAR_TOP"])
            points, depth, _ = explorer.map_pointcloud_to_image(lidar["token"], cam["token"])
            image = _pixels_last_wins(points, depth, shape)
            _clear_moving_boxes(nusc, cam["token"], image, removed)
            ys, xs = np.nonzero(image)
            k = np.array(
                nusc.get("calibrated_sensor", cam["calibrated_sensor_token"])["camera_intrinsic"]
            )
            lifted = np.linalg.inv(k) @ np.stack([xs, ys, np.ones_like(xs)]) * image[ys, xs]
            cloud = LidarPointCloud(np.vstack([lifted, np.ones(len(xs))]))
            for record, forward in (
                (nusc.get("calibrated_sensor", cam["calibrated_sensor_token"]), True),
                (nusc.get("ego_pose", cam["ego_pose_token"]), True),
                (nusc.get("ego_pose", lidar["ego_pose_token"]), False),
                (nusc.get("calibrated_sensor", lidar["calibrated_sensor_token"]), False),
                (nusc.get("calibrated_sensor", lidar["calibrated_sensor_token"]), True),
                (nusc.get("ego_pose", lidar["ego_pose_token"]), True),
                (nusc.get("ego_pose", main_cam["ego_pose_token"]), False),
                (main_calib, False),
            ):
                rotation, translation = pose(record)
                if forward:
                    cloud.rotate(rotation)
                    cloud.translate(translation)
                else:
                    cloud.translate(-translation)
                    cloud.rotate(rotation.T)
            z = cloud.points[2]
            uv = view_points(cloud.points[:3], np.array(main_calib["camera_intrinsic"]), True)
            inside = (z > 1) & (uv[0] > 1) & (uv[0] < shape[1] - 1)
            inside &= (uv[1] > 1) & (uv[1] < shape[0] - 1)
            moved = _pixels_last_wins(uv[:, inside], z[inside], shape)
            _clear_moving_boxes(nusc, main_cam["token"], moved, removed)
            for y, x in zip(*np.nonzero(moved), strict=True):
                if merged[y, x] == 0 or moved[y, x] < merged[y, x]:
                    merged[y, x] = moved[y, x]
    return merged


@pytest.mark.parametrize("keyframes", [1, 3])
def test_the_merged_target_is_radarnets(nusc_root, keyframes) -> None:
    """RadarNet's merged, moving-objects-removed training target, rebuilt by its rule from the
    fixture's keyframes and boxes, pixel for pixel; and what the boxes do."""
    root, samples = nusc_root
    nusc = NuScenes(version="v1.0-mini", dataroot=str(root), verbose=False)
    devkit = nus.require_devkit()
    for scene, tokens in samples.items():
        if scene not in dict((s[0], 0) for s in MINI_SCENES):
            continue
        for token_ in tokens:
            sample = nusc.get("sample", token_)
            for removed in ((), ("vehicle", "human")):
                rows, cols, depth = nus.merged_lidar_ground_truth(
                    devkit, nusc, sample, keyframes, removed
                )
                ours = np.zeros((CAM_H, CAM_W))
                ours[rows, cols] = depth
                expected = _radarnets_merged_target(nusc, token_, keyframes, removed)
                np.testing.assert_allclose(ours, expected, rtol=1e-12, atol=0)
    first = nusc.get("sample", samples["scene-0061"][0])
    single = nus.merged_lidar_ground_truth(devkit, nusc, first, 0)
    kept = nus.merged_lidar_ground_truth(devkit, nusc, first, keyframes, ())
    cleared = nus.merged_lidar_ground_truth(devkit, nusc, first, keyframes)
    assert len(single[0]) < len(cleared[0]) < len(kept[0])  # merged; boxes clear some
    # the keyframe's own points are never cleared, even inside its own pedestrian's box
    assert set(zip(single[0], single[1], strict=True)) <= set(
        zip(cleared[0], cleared[1], strict=True)
    )


def test_the_merged_target_trains_and_the_scored_splits_keep_the_single_scan(
    nusc_root, tmp_path
) -> None:
    root, samples = nusc_root
    nusc = NuScenes(version="v1.0-mini", dataroot=str(root), verbose=False)
    devkit = nus.require_devkit()
    reader = make_reader(root, tmp_path, lidar_keyframes=1)
    plain = make_reader(root, tmp_path)
    assert reader.cache != plain.cache  # its own cache; the default's folder unchanged
    for index in range(len(reader)):
        sample = nusc.get("sample", reader.frames[index]["id"])
        rows, cols, depth = nus.merged_lidar_ground_truth(devkit, nusc, sample, 1)
        stored = np.floor(depth * 256) / 256  # RadarNet's PNG
        y, x, z = nus.full_resolution_points(rows, cols, stored, (CAM_H, CAM_W), (HEIGHT, WIDTH)).T
        expected = nus.splat_nearest(x, y, z, HEIGHT, WIDTH)
        np.testing.assert_array_equal(reader[index]["depth"].numpy()[0], expected)
    val = make_reader(root, tmp_path, "val", lidar_keyframes=1)
    val_plain = make_reader(root, tmp_path, "val")
    assert val.cache == val_plain.cache  # scored against the single scan, as RadarNet
    with pytest.raises(ValueError, match=r"lidar_keyframes=1 with lidar_nsweeps=3"):
        make_reader(root, tmp_path, lidar_keyframes=1, lidar_nsweeps=3)


def test_resize_and_crop_scales_the_intrinsics() -> None:
    image = np.zeros((900, 1600, 3), np.uint8)
    k = np.array([[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]])
    out, k2 = nus.resize_and_crop(image, k, 448, 800)
    assert out.shape == (448, 800, 3)
    # Centre-aware: c' = s (c + 0.5) - 0.5 - crop.
    np.testing.assert_allclose(k2, [[633.2, 0, 407.9], [0, 633.2, 246.0 - 0.5 - 2], [0, 0, 1]])
    out, k3 = nus.resize_and_crop(image, k, 256, 640)  # scale 0.4: 640x360, 104 rows cut
    np.testing.assert_allclose(k3, [[506.56, 0, 326.22], [0, 506.56, 196.8 - 0.5 - 104], [0, 0, 1]])


def test_splits_conditions_and_stride(nusc_root, tmp_path) -> None:
    root, samples = nusc_root
    readers = {split: make_reader(root, tmp_path, split=split) for split in ("train", "val")}
    test = make_reader(root, tmp_path, split="test")
    ids = {split: [f["id"] for f in r.frames] for split, r in readers.items()}
    assert ids["train"] == samples["scene-0061"] + samples["scene-0553"]  # mini_train
    assert ids["val"] == samples["scene-0103"] + samples["scene-0916"]  # mini_val
    assert readers["train"].conditions == ["day", "day", "night", "night"]
    assert readers["val"].conditions == ["rain", "rain", "day", "day"]
    assert test.split_dir == readers["val"].split_dir  # test_split=val: the same prepared frames

    strided = make_reader(root, tmp_path, stride=2)
    assert [f["id"] for f in strided.frames] == [samples["scene-0061"][0], samples["scene-0553"][0]]
    day_night = make_reader(root, tmp_path, split="val", conditions=["day", "night"])
    assert [f["id"] for f in day_night.frames] == samples["scene-0916"]  # rain left out
    with pytest.raises(ValueError, match="mini_val split of v1.0-mini has no keyframe left"):
        make_reader(root, tmp_path, conditions=["night"])  # an empty split fails

    official = make_reader(root, tmp_path, split="test", test_split="test")
    assert [f["id"] for f in official.frames] == samples["scene-0077"]
    assert official.conditions == ["night"]
    assert nonzero(official[0]["depth"]) == LIDAR_EXPECTED


def test_filled_ground_truth_trains_and_measured_points_evaluate(nusc_root, tmp_path) -> None:
    root, _ = nusc_root
    train = make_reader(root, tmp_path, fill="linear")
    depth = train[0]["depth"].squeeze().numpy()
    assert (depth > 0).all()  # dense: every pixel filled
    for (r, c), value in LIDAR_EXPECTED.items():
        assert depth[r, c] == value  # measured values kept
    val = make_reader(root, tmp_path, split="val", fill="linear")
    assert nonzero(val[0]["depth"]) == LIDAR_EXPECTED  # evaluation: the lidar points only
    # val does not depend on fill: another fill re-prepares only train.
    assert make_reader(root, tmp_path, split="val").split_dir == val.split_dir
    assert make_reader(root, tmp_path).split_dir.parent != train.split_dir.parent


def test_prepare_is_idempotent_and_resumable(nusc_root, tmp_path, monkeypatch) -> None:
    root, _ = nusc_root
    real_load = nus.load_frame
    calls: list[str] = []

    def interrupted(devkit, nusc, token, settings):
        if len(calls) == 3:
            raise KeyboardInterrupt
        calls.append(token)
        return real_load(devkit, nusc, token, settings)

    monkeypatch.setattr(nus, "load_frame", interrupted)
    with pytest.raises(KeyboardInterrupt):
        make_reader(root, tmp_path)
    split_dirs = list(tmp_path.glob("nuscenes/*/train"))
    assert len(split_dirs) == 1 and not (split_dirs[0] / "index.json").exists()
    assert len(list(split_dirs[0].glob("*.json"))) == 3  # three frames done

    calls.clear()
    monkeypatch.setattr(nus, "load_frame", lambda *a: calls.append(a[2]) or real_load(*a))
    train = make_reader(root, tmp_path)
    assert len(train) == 4 and len(calls) == 4 + 1  # the 4th train frame, then val's 4
    stamps = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*") if p.is_file()}

    def no_devkit_load(*args):
        raise AssertionError("a prepared cache must not load the tables again")

    monkeypatch.setattr(nus, "load_tables", no_devkit_load)
    again = make_reader(root, tmp_path)
    assert again.split_dir == train.split_dir and again.frames == train.frames
    assert {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*") if p.is_file()} == stamps
    with pytest.raises(AssertionError, match="must not load"):
        make_reader(root, tmp_path, radar_nsweeps=2)  # other settings: a new cache


def _snapshot(root: Path) -> dict:
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")}


@pytest.fixture
def fresh_root(tmp_path) -> tuple[Path, dict]:
    root = tmp_path / "data"
    samples = write_nuscenes(root, "v1.0-mini", MINI_SCENES)
    return root, samples


def test_dataset_folder_is_only_read(fresh_root, tmp_path) -> None:
    root, _ = fresh_root
    before = _snapshot(root)
    make_reader(root, tmp_path / "cache", fill="colorization")
    assert _snapshot(root) == before
    with pytest.raises(ValueError) as err:  # the reader names its argument, a command the key
        make_reader(root, root / "cache")
    shown = command_message(err.value, "dataset=nuscenes")
    assert "inside dataset.root=" in shown and "FUSION_DEPTH_CACHE (paths.cache_dir)" in shown


def _sample_file(root: Path, samples: dict, channel: str) -> Path:
    nusc = NuScenes(version="v1.0-mini", dataroot=str(root), verbose=False)
    sample = nusc.get("sample", samples["scene-0553"][1])
    return Path(nusc.get_sample_data_path(sample["data"][channel]))


def _break_lidar_missing(root, samples):
    path = _sample_file(root, samples, "LIDAR_TOP")
    path.unlink()
    return path, FileNotFoundError, "missing LIDAR_TOP lidar point cloud"


def _break_lidar_size(root, samples):
    path = _sample_file(root, samples, "LIDAR_TOP")
    path.write_bytes(path.read_bytes()[:-3])
    return path, ValueError, "not a whole number of 20-byte points"


def _break_radar(root, samples):
    path = _sample_file(root, samples, "RADAR_FRONT")
    path.write_bytes(path.read_bytes()[:300])
    return path, ValueError, "unreadable RADAR_FRONT radar point cloud.*expected a nuScenes radar"


def _break_image(root, samples):
    path = _sample_file(root, samples, "CAM_FRONT")
    path.write_bytes(b"not a jpeg")
    return path, ValueError, "unreadable image"


def _break_version(root, samples):
    (root / "v1.0-mini").rename(root / "v1.0-mini-old")
    return root / "v1.0-mini", FileNotFoundError, "missing folder; expected the nuScenes v1.0-mini"


def _break_table(root, samples):
    path = root / "v1.0-mini" / "sample_data.json"
    path.unlink()
    return path, FileNotFoundError, "missing table; expected the 13 nuScenes tables"


def _break_map(root, samples):
    next((root / "maps").glob("*.png")).unlink()
    return root / "v1.0-mini", ValueError, "devkit could not load the v1.0-mini tables"


def _break_split(root, samples):
    write_nuscenes(root, "v1.0-mini", MINI_SCENES[:2])  # no mini_val scene
    return root / "v1.0-mini" / "scene.json", ValueError, "none of the 2 scenes of the mini_val"


def _break_root(root, samples):
    return root / "elsewhere", FileNotFoundError, "no such folder; expected the nuScenes folder"


@pytest.mark.parametrize(
    "breaker",
    [
        _break_lidar_missing,
        _break_lidar_size,
        _break_radar,
        _break_image,
        _break_version,
        _break_table,
        _break_map,
        _break_split,
        _break_root,
    ],
)
def test_bad_input_fails_naming_the_path_before_training(fresh_root, tmp_path, breaker) -> None:
    root, samples = fresh_root
    path, error, message = breaker(root, samples)
    data_root = path if breaker is _break_root else root
    before = _snapshot(root)
    with pytest.raises(error, match=message) as info:
        make_reader(data_root, tmp_path / "cache", split="test")
    assert str(path) in str(info.value)
    assert not list((tmp_path / "cache").rglob("index.json"))  # nothing usable was written
    assert _snapshot(root) == before


def test_missing_and_wrong_options_fail_clearly(nusc_root, tmp_path) -> None:
    root, _ = nusc_root

    def refused(**options) -> str:  # what a command prints: the reader names its arguments
        with pytest.raises(ValueError) as err:
            make_reader(options.pop("root", root), tmp_path, **options)
        return command_message(err.value, "dataset=nuscenes")

    assert "dataset.version='v2.0'" in refused(version="v2.0")
    with pytest.raises(ValueError, match="radar_channels.*RADAR_FRONT_LEFT"):
        make_reader(root, tmp_path, radar_channels=["RADAR_TOP"])
    with pytest.raises(ValueError, match="radar_ambig_states=\\[\\]"):
        make_reader(root, tmp_path, radar_filters="custom", radar_ambig_states=[])
    assert "dataset.fill='cubic'" in refused(fill="cubic")
    assert "dataset.root is not set" in refused(root=None)
    assert not list(tmp_path.rglob("*"))


def test_train_and_test_through_the_real_configs(nusc_root, make_config) -> None:
    from fusion_depth.prepare.cli import prepare
    from fusion_depth.train.fit import train

    root, _ = nusc_root
    cfg = make_config(
        "dataset=nuscenes",
        f"dataset.root={root}",
        "dataset.version=v1.0-mini",
        "dataset.height=64",
        "dataset.width=128",
        "backbone=resnet50",
        "backbone.pretrained=false",
        "fusion=concat",
        "logger=none",
        "trainer.max_epochs=1",
        "trainer.num_sanity_val_steps=0",
        "trainer.enable_model_summary=false",
        "callbacks.model_checkpoint.save_last=false",
        "+callbacks.model_checkpoint.save_weights_only=true",
        "model.num_val_panels=1",
        "eval=radarnet",
    )
    assert cfg.dataset.fill == "colorization" and cfg.backbone.name == "resnet50"
    assert prepare(cfg) == {"train": 4, "val": 4, "test": 4}
    results = train(cfg)
    assert results["run"]["dataset"] == "nuscenes" and results["run"]["sensor"] == "radar"
    assert results["test"]["num_images"] == 4
    # Scored at the camera's resolution: every pixel of RadarNet's ground truth below the cap
    # that the 64x128 frame (72x128 with 8 rows cut) covers, not the frames' own depth maps.
    test = make_reader(root, Path(os.environ["FUSION_DEPTH_CACHE"]), "test", height=64, width=128)
    points = np.concatenate([test[i]["depth_points"].numpy() for i in range(len(test))])
    scored = int(((points[:, 2] > 0) & (points[:, 2] < 80)).sum())
    maps = sum(int((test[i]["depth"] > 0).sum()) for i in range(len(test)))
    assert results["test"]["num_pixels"] == scored != maps
    record = json.loads(Path(cfg.paths.output_dir, "metrics.json").read_text())
    assert record["protocol"]["resolution"] == "full"
    assert set(results["test_by_condition"]) == {"rain", "day"}
    assert all(math.isfinite(v) for v in results["test"].values())
    assert Path(cfg.paths.output_dir, "metrics.json").is_file()
    assert list(Path(os.environ["FUSION_DEPTH_CACHE"]).glob("nuscenes/*/train/index.json"))


def test_a_filled_training_split_serves_its_measured_map_when_the_loss_reads_it(
    nusc_root, tmp_path
) -> None:
    """RadarNet's fusion loss reads the measured pixels beside the filled target: the datamodule
    of a model that wants them serves depth_measured in training batches only."""
    from functools import partial

    from fusion_depth.data.encoding import decode_sample
    from fusion_depth.runner.datamodule import DepthDataModule

    root, _ = nusc_root
    options = {"version": "v1.0-mini", "height": HEIGHT, "width": WIDTH, "fill": "linear_hull"}
    reader = partial(NuScenesDepth, root=root, cache_root=tmp_path, **options)
    plain = DepthDataModule(reader=reader)
    assert "depth_measured" not in plain.dataset("train")[0]
    module = DepthDataModule(reader=reader)
    module.measured_depth = True
    measured = make_reader(root, tmp_path)  # fill=none: the measured map
    for index in range(len(measured)):
        sample = decode_sample(module.dataset("train")[index])  # the loaders' encoded form
        torch.testing.assert_close(sample["depth_measured"], measured[index]["depth"])
        assert (sample["depth"] > 0).sum() > (sample["depth_measured"] > 0).sum()  # filled
    assert "depth_measured" not in module.dataset("val")[0]


def test_a_merged_keyframes_missing_lidar_fails_before_anything_is_prepared(
    fresh_root, tmp_path
) -> None:
    root, samples = fresh_root
    nusc = NuScenes(version="v1.0-mini", dataroot=str(root), verbose=False)
    second = nusc.get("sample", samples["scene-0061"][1])
    lidar = root / nusc.get("sample_data", second["data"]["LIDAR_TOP"])["filename"]
    lidar.unlink()  # keyframe 1: with stride 2 not a training frame, only keyframe 0's neighbour
    with pytest.raises(FileNotFoundError, match=r"LIDAR_TOP lidar point cloud of a merged key"):
        make_reader(root, tmp_path / "cache", lidar_keyframes=1, stride=2)
    assert not list((tmp_path / "cache").rglob("*.npy"))
    assert len(make_reader(root, tmp_path / "cache", stride=2)) == 2  # unmerged: not needed


def test_radarnets_nuscenes_recipe_trains_on_its_own_data(nusc_root, make_config) -> None:
    """model=radarnet on nuScenes: its merged target, crops, outlier filter, fusion loss on the
    measured pixels and checkpoint rule, end to end (stage=end_to_end; at the fixture's size,
    with a crop that fits it)."""
    from fusion_depth.runner.callbacks import MajorityCheckpoint
    from fusion_depth.train.fit import train

    root, _ = nusc_root
    cfg = make_config(
        "dataset=nuscenes",
        f"dataset.root={root}",
        "dataset.version=v1.0-mini",
        "model=radarnet",
        "fusion=concat",
        "dataset.height=64",  # the recipe's 896x1600 is the camera's; the fixture's is 72x128
        "dataset.width=128",
        "augment.crop=[64,96]",
        "model.net.window_width=64",
        "dataset.reader.lidar_keyframes=1",
        "data.batch_size=2",  # the recipe's 16 is more than the fixture's 4 frames
        "backbone.pretrained=false",
        "logger=none",
        "trainer.max_epochs=2",
        "trainer.num_sanity_val_steps=0",
        "trainer.enable_model_summary=false",
        "model.num_val_panels=1",
        "eval=radarnet",
    )
    assert cfg.dataset.fill == "linear_hull" and list(cfg.augment.outlier_filter) == [7, 1.5]
    results = train(cfg)
    assert results["test"]["num_images"] == 4
    assert all(math.isfinite(v) for v in results["test"].values())
    state = torch.load(
        Path(cfg.paths.output_dir, "checkpoints", "last.ckpt"),
        map_location="cpu",
        weights_only=False,
    )
    (rule,) = [v for k, v in state["callbacks"].items() if k.startswith("MajorityCheckpoint")]
    assert set(rule["kept_metrics"]) == {"val/mae", "val/rmse", "val/imae", "val/irmse"}
    assert isinstance(rule["kept_metrics"]["val/rmse"], float)
    assert MajorityCheckpoint.__name__ in cfg.callbacks.model_checkpoint._target_


def test_the_nuscenes_sweep_runs_under_the_smoke_experiment(nusc_root, tmp_path) -> None:
    from helpers import run_sweep

    root, _ = nusc_root
    sweep = tmp_path / "sweep"
    overrides = [f"dataset.root={root}", "dataset.version=v1.0-mini", "seed=42", "loss=l1"]
    result = run_sweep("nuscenes_loss_fusion_grid", [*overrides, "fusion=concat"], sweep)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "1 ok, 0 failed" in result.stdout
    (metrics,) = sweep.glob("*/metrics.json")
    saved = json.loads(metrics.read_text())
    assert saved["run"]["dataset"] == "nuscenes" and saved["run"]["fusion"] == "concat"
    assert (metrics.parent / "per_image.csv").is_file()


# --- radar points (issue 16) ------------------------------------------------------------------

FILTERS_OFF = {(20, 10): 12.0, (22, 40): 30.0, (25, 50): 8.0, (18, 30): 20.0}


def radar_rows(item: dict, max_points: int) -> np.ndarray:
    """The valid rows of a sample's radar_points, checked: shape, dtype, zero padding."""
    points = item["radar_points"].numpy()
    assert points.shape == (max_points, len(RADAR_POINT_FIELDS)) and points.dtype == np.float32
    valid = points[:, -1] == 1
    count = int(valid.sum())
    assert valid[:count].all() and (points[count:] == 0).all()
    return points[:count]


def test_radar_points_are_the_returns_of_the_sparse_map(nusc_root, tmp_path) -> None:
    root, _ = nusc_root
    train = make_reader(root, tmp_path, radar_filters="off")
    assert train.max_radar_points == 128
    for index in range(len(train)):
        item = train[index]
        rows = radar_rows(item, 128)
        u, v, depth, rcs, velocity = rows[:, :5].T
        # Every return of the map, nearest first, at the pixel centre the fixture chose (the
        # devkit's chain, resized and cropped like the image), with the map's depth.
        assert depth.tolist() == sorted(depth.tolist())
        at = zip(v.round(), u.round(), depth, strict=True)
        cells = {(int(r), int(c)): float(z) for r, c, z in at}
        assert cells == pytest.approx(FILTERS_OFF, abs=1e-3)
        assert nonzero(item["sparse"]) == pytest.approx(cells, abs=1 / 256)
        np.testing.assert_allclose(u, u.round(), atol=1e-3)
        np.testing.assert_allclose(v, v.round(), atol=1e-3)
        assert (rcs == 5.0).all() and (velocity == 0).all()  # the fixture's rcs, still targets
    # P is applied when serving: the nearest two, nothing prepared again.
    files = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    two = make_reader(root, tmp_path, radar_filters="off", max_radar_points=2)
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == files
    assert radar_rows(two[0], 2)[:, 2].tolist() == pytest.approx([8.0, 12.0], abs=1e-3)
    # Sweeps and channels add their points as they add pixels to the map.
    both = make_reader(root, tmp_path, radar_channels=["RADAR_FRONT", "RADAR_FRONT_LEFT"])
    assert [round(float(z), 3) for z in radar_rows(both[0], 128)[:, 2]] == [12.0, 15.0]


def test_radial_velocity_is_the_compensated_velocity_along_the_line_of_sight(tmp_path) -> None:
    xyz = np.array([[10.0, 0.0, 0.0], [0.0, 5.0, 0.0], [3.0, 4.0, 0.0], [0.0, 0.0, 0.0]]).T
    path = tmp_path / "radar.pcd"
    write_radar_pcd(path, xyz, [{**VALID, "vx_comp": 3.0, "vy_comp": 4.0, "vx": 99.0}] * 4)
    cloud = nus._radar_class(nus.require_devkit(), nus.radar_filter_states("off"))
    points = cloud.from_file(str(path)).points
    # Row 6 (vx, uncompensated) now holds the radial velocity; rcs and the rest are untouched.
    assert points[nus.RADAR_RADIAL_ROW].tolist() == pytest.approx([3.0, 4.0, 5.0, 0.0])
    assert points[nus.RADAR_RCS_ROW].tolist() == [5.0] * 4
    assert RadarPointCloud.from_file(str(path)).points[6].tolist() == [99.0] * 4  # devkit's own


def test_radar_points_carry_the_radial_velocity(fresh_root, tmp_path) -> None:
    root, _ = fresh_root
    nusc = NuScenes(version="v1.0-mini", dataroot=str(root), verbose=False)
    expected = {}
    for record in nusc.sample_data:
        if record["channel"] != "RADAR_FRONT" or not record["is_key_frame"]:
            continue
        path = root / record["filename"]
        every = list(range(18)), list(range(8)), list(range(5))
        xyz = RadarPointCloud.from_file(str(path), *every).points[:3]
        states = [p[3] for p in RADAR_POINTS["RADAR_FRONT"]]
        velocity = [{"vx_comp": 2.0 + k, "vy_comp": -1.5} for k in range(xyz.shape[1])]
        write_radar_pcd(path, xyz, [{**s, **v} for s, v in zip(states, velocity, strict=True)])
        x, y = xyz[0, 0], xyz[1, 0]  # the return the default filters keep (12 m)
        expected[record["sample_token"]] = (x * 2.0 - y * 1.5) / math.hypot(x, y)
    train = make_reader(root, tmp_path / "cache")
    for index, frame in enumerate(train.frames):
        (row,) = radar_rows(train[index], 128)
        assert row[2] == pytest.approx(12.0, abs=1e-3)
        assert row[4] == pytest.approx(expected[frame["id"]], abs=1e-4)


# --- RadarNet's derived files (dataset=radarnet_layout) against this preparation ------------------


def _radarnets_radar_points(nusc, token: str) -> np.ndarray:
    """RadarNet's stored test radar for one keyframe, by its own steps (merge_radar_point_clouds
    with no frames before or after, setup/setup_dataset_nuscenes_test.py): the devkit's
    map_pointcloud_to_image of RADAR_FRONT with every return (its loops have called
    RadarPointCloud.disable_filters() by then), each on np.round (the last written winning),
    np.nonzero of that map as (x, y, z), float64."""
    sample = nusc.get("sample", token)
    RadarPointCloud.disable_filters()
    try:
        points, depth, image = NuScenesExplorer(nusc).map_pointcloud_to_image(
            sample["data"]["RADAR_FRONT"], sample["data"]["CAM_FRONT"]
        )
    finally:
        RadarPointCloud.default_filters()
    radar_map = _pixels_last_wins(points, depth, (image.size[1], image.size[0]))
    rows, cols = np.nonzero(radar_map)
    return np.stack([cols, rows, radar_map[rows, cols]], axis=1).astype(np.float64)


def test_radarnets_derived_files_give_this_preparations_frames(nusc_root, tmp_path) -> None:
    """The fixture's test frames written as RadarNet's setup writes them (its radar points, its
    lidar PNG, the nuScenes image; lists of relative paths), read by dataset=radarnet_layout,
    against dataset=nuscenes with the authors' radar settings at the camera's own size: the
    same image, scored ground truth (the full-resolution points eval=radarnet reads) and radar
    returns. What differs, by design: this reader keeps returns within a pixel of the border,
    which their setup drops (so the sparse maps differ on exactly those pixels), and the depth
    maps (not what eval=radarnet scores) differ on a few pixels."""
    from fusion_depth.data.radarnet_layout import RadarNetLayout
    from fusion_depth.models.released import RADARNET_MARGIN, radarnet_frame_points

    root, _ = nusc_root
    nusc = NuScenes(version="v1.0-mini", dataroot=str(root), verbose=False)
    options = {"height": CAM_H, "width": CAM_W, "size_multiple": 1, "radar_filters": "off"}
    ours = make_reader(root, tmp_path / "cache", "test", **options)
    layout = tmp_path / "radarnet"
    lists: dict[str, list[str]] = {"image": [], "radar": [], "lidar": []}
    for index in range(len(ours)):
        token = ours.frames[index]["id"]
        camera = nusc.get("sample_data", nusc.get("sample", token)["data"]["CAM_FRONT"])
        derived = layout / "data/nuscenes_derived_test"
        for role in ("radar_points", "lidar"):
            (derived / role).mkdir(parents=True, exist_ok=True)
        np.save(derived / "radar_points" / f"{token}.npy", _radarnets_radar_points(nusc, token))
        _radarnets_ground_truth(nusc, token, derived / "lidar" / f"{token}.png")
        lists["image"].append(str(root / camera["filename"]))  # an absolute path: also read
        lists["radar"].append(f"data/nuscenes_derived_test/radar_points/{token}.npy")
        lists["lidar"].append(f"data/nuscenes_derived_test/lidar/{token}.png")
    (layout / "testing/nuscenes").mkdir(parents=True)
    for role, paths in lists.items():
        (layout / f"testing/nuscenes/nuscenes_test_{role}.txt").write_text("\n".join(paths))
    theirs = RadarNetLayout("test", layout, tmp_path / "cache", CAM_H, CAM_W, size_multiple=1)
    assert len(theirs) == len(ours) == 4
    margin_points = shared_pixels = 0
    for index in range(len(ours)):
        mine, derived = ours[index], theirs[index]
        np.testing.assert_array_equal(mine["image"].numpy(), derived["image"].numpy())
        # The maps (eval.resolution=network's) are each reader's own drawing: this one projects
        # the lidar itself (nearest on a shared pixel, 1/256 m steps rounded), theirs is the PNG
        # (256·z truncated, the last point written). They are not compared: eval=radarnet
        # scores the points above, which are the same; the count is printed.
        shared_pixels += int((mine["depth"].numpy() != derived["depth"].numpy()).sum())
        a, b = (s["depth_points"].numpy() for s in (mine, derived))
        as_set = [sorted(map(tuple, p[p[:, 2] > 0].tolist())) for p in (a, b)]
        assert as_set[0] == as_set[1] and as_set[0]
        # The returns, as the released RadarNet numbers them, from each reader's rows.
        mine_pts, their_pts = (
            radarnet_frame_points(s["radar_points"], CAM_H, CAM_W) for s in (mine, derived)
        )
        assert len(their_pts) > 0
        torch_testing_equal(mine_pts, their_pts)
        # sparse: the same but on the pixels of returns their setup's margin drops
        rows = mine["radar_points"].numpy()
        rows = rows[rows[:, 5] > 0]
        u, v = rows[:, 0], rows[:, 1]
        outside = (u <= RADARNET_MARGIN) | (u >= CAM_W - RADARNET_MARGIN)
        outside |= (v <= RADARNET_MARGIN) | (v >= CAM_H - RADARNET_MARGIN)
        differ = np.argwhere(mine["sparse"][0].numpy() != derived["sparse"][0].numpy())
        dropped = {
            (int(np.rint(y)), int(np.rint(x))) for x, y in zip(u[outside], v[outside], strict=True)
        }
        assert {tuple(p) for p in differ.tolist()} <= dropped
        margin_points += int(outside.sum())
    print(f"returns within a pixel of the border (kept here, dropped by RadarNet): {margin_points}")
    print(f"depth-map pixels that differ (not the scored points): {shared_pixels}")


def torch_testing_equal(a, b) -> None:
    """Equal (K, 3) point tensors: pixels exactly, depths to float32."""
    assert a.shape == b.shape, (a, b)
    np.testing.assert_array_equal(a[:, :2].numpy(), b[:, :2].numpy())
    np.testing.assert_allclose(a[:, 2].numpy(), b[:, 2].numpy(), rtol=1e-6)
