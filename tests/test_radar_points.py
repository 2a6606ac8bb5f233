"""Radar returns as points (issue 16, for RadarNet): ``radar_points`` of every radar dataset lie
on the pixels of the ``sparse`` map they were drawn into, with its depth; padding, ``P``, the
datasets without radar, batching, and damaged files. nuScenes: tests/test_nuscenes.py."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.carla import H as CARLA_H
from helpers.carla import W as CARLA_W
from helpers.carla import record_fixture

from fusion_depth.data import RADAR_POINT_FIELDS
from fusion_depth.data.cache import PreparedFrame, PreparedSplit, prepare_split
from fusion_depth.data.carla import CarlaDepth
from fusion_depth.data.depth_io import DataFileError
from fusion_depth.data.encoding import decode_sample
from fusion_depth.data.procedural import ProceduralDepth
from fusion_depth.data.radar_points import (
    DEPTH,
    NUM_FIELDS,
    RCS,
    VALID,
    VELOCITY,
    U,
    V,
    pad_points,
    point_rows,
    read_points,
    same_pixel_float32,
    write_points,
)
from fusion_depth.runner.datamodule import DepthDataModule

H, W = 64, 96
SMALL = {"height": H, "width": W, "num_train": 12, "num_val": 4, "num_test": 4}
CACHE_STEP = 1 / 256  # the caches store depth maps in 1/256 m


def assert_short(err: DataFileError, path: Path) -> None:
    """``err`` names ``path`` first and says what is wrong in one short line."""
    text = str(err)
    assert text.startswith(f"{path}: ") and err.path == path, text
    assert "\n" not in text and len(text.replace(str(path.parent), "")) < 300, text


def _valid(points: torch.Tensor) -> np.ndarray:
    rows = points.numpy()
    return rows[rows[:, VALID] == 1]


def check_points_on_map(points: torch.Tensor, sparse: torch.Tensor, max_points: int) -> int:
    """The contract of ``radar_points`` against a map drawn one pixel per return: shape and
    dtype, valid rows first and nearest first, zero padding, each valid point inside the image
    at a pixel of ``sparse`` holding the nearest depth of the points there. Returns how many
    points are valid."""
    height, width = sparse.shape[-2:]
    assert points.shape == (max_points, len(RADAR_POINT_FIELDS)) and points.dtype == torch.float32
    rows = points.numpy()
    flags = rows[:, VALID]
    assert set(np.unique(flags)) <= {0.0, 1.0}
    count = int(flags.sum())
    assert (flags[:count] == 1).all(), "valid rows come first"
    assert (rows[count:] == 0).all(), "padding rows are all zeros"
    valid = rows[:count]
    assert (np.diff(valid[:, DEPTH]) >= 0).all(), "nearest first"
    u, v, depth = valid[:, U], valid[:, V], valid[:, DEPTH]
    # Pixel centres at integers: a return lies in pixel (round(v), round(u)), as RadarNet's.
    cols, rows_ = np.round(u).astype(int), np.round(v).astype(int)
    assert ((cols >= 0) & (cols < width) & (rows_ >= 0) & (rows_ < height)).all()
    assert (depth > 0).all()
    sparse_map = sparse.numpy().reshape(height, width)
    cells = list(zip(rows_, cols, strict=True))
    for (r, c), z in zip(cells, depth, strict=True):
        nearest = min(d for cell, d in zip(cells, depth, strict=True) if cell == (r, c))
        assert sparse_map[r, c] > 0
        assert abs(sparse_map[r, c] - nearest) <= CACHE_STEP / 2 + 1e-4, (r, c, z)
    return count


# --- the built-in dataset -------------------------------------------------------------------


@pytest.fixture(scope="module")
def procedural_root(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("procedural")


@pytest.fixture(scope="module")
def single_pixels(procedural_root) -> ProceduralDepth:
    return ProceduralDepth("train", procedural_root, radar_height_extension=0.0, **SMALL)


def test_procedural_points_are_the_returns_of_the_sparse_map(single_pixels) -> None:
    assert single_pixels.params["max_radar_points"] == 64
    for i in range(len(single_pixels)):
        sample = single_pixels[i]
        count = check_points_on_map(sample["radar_points"], sample["sparse"], 64)
        assert 0 < count < 64  # nothing cut: every return of the map is a point
        sparse = sample["sparse"][0].numpy()
        rows = _valid(sample["radar_points"])
        cells = set(
            zip(np.round(rows[:, V]).astype(int), np.round(rows[:, U]).astype(int), strict=True)
        )
        assert cells == {(int(r), int(c)) for r, c in zip(*np.nonzero(sparse), strict=True)}
        assert (rows[:, [RCS, VELOCITY]] == 0).all()  # a static scene without cross-sections


def test_procedural_points_sit_on_the_vertical_lines(procedural_root, single_pixels) -> None:
    lines = ProceduralDepth("train", procedural_root, radar_height_extension=2.0, **SMALL)
    for i in range(len(lines)):
        sample = lines[i]
        # One point per return where it projects, whatever the drawing: the same rows.
        assert torch.equal(sample["radar_points"], single_pixels[i]["radar_points"])
        sparse = sample["sparse"][0].numpy()
        assert (sparse > 0).sum() > (single_pixels[i]["sparse"][0].numpy() > 0).sum()
        for u, v, z, *_ in _valid(sample["radar_points"]):
            row, col = round(v), round(u)
            # The line through the point crosses its row at its column (the camera's roll of
            # up to 1 degree may move the drawn pixel by one column), no farther than it (the
            # pitch changes z by a few mm along the metre or so of the line one row covers).
            near = sparse[row, max(col - 1, 0) : col + 2]
            assert (near > 0).any() and near[near > 0].min() <= z * 1.001 + CACHE_STEP


def test_procedural_keeps_the_nearest_p(procedural_root, single_pixels) -> None:
    few = ProceduralDepth(
        "train", procedural_root, radar_height_extension=0.0, max_radar_points=8, **SMALL
    )
    assert few.cache_dir != single_pixels.cache_dir  # P is part of the generated arrays
    assert np.load(few.split_dir / "radar_points.npy").shape == (12, 8, NUM_FIELDS)
    for i in range(len(few)):
        points, every = few[i]["radar_points"], single_pixels[i]["radar_points"]
        assert points.shape == (8, NUM_FIELDS)
        assert torch.equal(points, every[:8])  # the nearest 8 of all
        assert torch.equal(few[i]["sparse"], single_pixels[i]["sparse"])  # the map keeps all
    with pytest.raises(ValueError, match="max_radar_points=0"):
        ProceduralDepth("train", procedural_root, max_radar_points=0, **SMALL)


def test_lidar_datasets_have_no_radar_points(procedural_root) -> None:
    lidar = ProceduralDepth("val", procedural_root, sparse="lidar", **SMALL)
    assert "radar_points" not in lidar[0]
    assert not (lidar.split_dir / "radar_points.npy").exists()
    assert "max_radar_points" not in lidar.params  # old lidar caches stay valid


def _datamodule(root: Path, **options) -> DepthDataModule:
    reader = functools.partial(ProceduralDepth, root=root, **SMALL, **options)
    return DepthDataModule(reader, batch_size=4, num_workers=0, pin_memory=False)


def test_a_batch_carries_the_points(procedural_root) -> None:
    batch = next(iter(_datamodule(procedural_root, max_radar_points=16).train_dataloader()))
    assert batch["radar_points"].shape == (4, 16, NUM_FIELDS)
    assert batch["radar_points"].dtype == torch.float32  # points cross the loader as floats
    assert batch["sparse"].shape == (4, 1, H, W) and batch["index"].shape == (4,)
    assert batch["sparse"].dtype == torch.uint16  # maps in 1/256 m, decoded on the device
    batch = decode_sample(batch)
    for points, sparse in zip(batch["radar_points"], batch["sparse"], strict=True):
        assert (points[:, VALID] == 1).any() and (sparse > 0).any()
    lidar = next(iter(_datamodule(procedural_root, sparse="lidar").val_dataloader()))
    assert "radar_points" not in lidar and lidar["sparse"].shape == (4, 1, H, W)


@pytest.mark.parametrize(
    "damage",
    ["truncated", "garbage", "float64", "other P", "pickled"],
)
def test_a_damaged_procedural_points_array_is_named(tmp_path, damage) -> None:
    first = ProceduralDepth("val", tmp_path, **SMALL)
    path = first.split_dir / "radar_points.npy"
    good = np.load(path)
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif damage == "garbage":
        path.write_bytes(np.random.default_rng(0).bytes(300))
    elif damage == "float64":
        np.save(path, good.astype(np.float64))
    elif damage == "other P":
        np.save(path, good[:, :10])
    else:
        np.save(path, np.array([{"u": 1}], dtype=object), allow_pickle=True)
    # Damaged after the split was checked (a reader built before): reading names the file.
    with pytest.raises(DataFileError) as info:
        first[0]
    assert_short(info.value, path)
    # A reader built now finds the damage and renders the split again.
    again = ProceduralDepth("val", tmp_path, **SMALL)
    assert np.array_equal(np.load(path), good) and again[0]["radar_points"].shape[1] == NUM_FIELDS


# --- the prepared cache ---------------------------------------------------------------------


def test_point_rows_sort_nearest_first_and_stay_in_their_pixel() -> None:
    u = np.array([5.25, 52.49999999, 0.0, 95.49999999])
    v = np.array([1.0, 2.0, 3.0, 63.49999999])
    rows = point_rows(u, v, [9.0, 3.0, 3.0, 1.0], rcs=[1, 2, 3, 4], velocity=[-1, -2, -3, -4])
    assert rows.dtype == np.float32 and rows.shape == (4, NUM_FIELDS)
    assert rows[:, DEPTH].tolist() == [1.0, 3.0, 3.0, 9.0]  # a stable sort: ties keep order
    assert rows[:, RCS].tolist() == [4, 2, 3, 1] and rows[:, VELOCITY].tolist() == [-4, -2, -3, -1]
    # float32 never rounds into the next pixel (95.49999999 is 95.5 in float32, which is 96)
    assert np.round(rows[:, U]).tolist() == [95, 52, 0, 5]
    assert np.round(rows[:, V]).tolist() == [63, 2, 3, 1]
    assert (rows[:, VALID] == 1).all()
    near_halves = np.array([1.5 - 1e-9, 2.5 + 1e-9, 2.5, 7.25, -0.5 + 1e-9])
    assert np.round(same_pixel_float32(near_halves)).tolist() == [1, 3, 2, 7, 0]
    # A half (which rounds to even) is stored inside its pixel, so its mirror W - 1 - u lands
    # in the mirrored pixel, as the flipped map's does; float32 holds no pixel beyond 2^22.
    halves = np.arange(800) + 0.5
    stored = same_pixel_float32(halves)
    assert (np.round(stored) == np.round(halves)).all()
    assert (np.round(np.float32(799) - stored) == 799 - np.round(halves)).all()
    assert same_pixel_float32(np.array([2.0**25 + 1]))[0] == np.float32(2.0**25)
    padded = pad_points(rows, 6)
    assert padded.shape == (6, NUM_FIELDS) and (padded[4:] == 0).all()
    assert np.array_equal(pad_points(rows, 2), rows[:2])
    assert pad_points(point_rows([], [], []), 3).tolist() == [[0.0] * NUM_FIELDS] * 3


def _radar_frame(frame_id: str) -> PreparedFrame:
    rng = np.random.default_rng(len(frame_id) + ord(frame_id[0]))
    h, w = 8, 12
    count = {"a": 5, "b": 0, "c": 2}[frame_id]
    # Pixel centres at integers: pixel i spans [i - 0.5, i + 0.5].
    u, v = rng.uniform(-0.5, w - 0.5, count), rng.uniform(-0.5, h - 0.5, count)
    depth = rng.uniform(1, 60, count)
    sparse = np.zeros((h, w), np.float32)
    for col, row, z in sorted(zip(u, v, depth, strict=True), key=lambda p: -p[2]):
        sparse[round(row), round(col)] = z
    return PreparedFrame(
        image=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        sparse=sparse,
        depth=rng.uniform(0.5, 80, (h, w)),
        condition="day",
        radar_points=point_rows(u, v, depth, velocity=np.full(count, 2.5)),
    )


@pytest.fixture
def radar_split(tmp_path) -> Path:
    return prepare_split(tmp_path, "val", ["a", "b", "c"], _radar_frame, {})


def test_a_prepared_split_serves_every_point_padded_to_p(radar_split) -> None:
    assert sorted(p.name for p in radar_split.glob("*.radar.npy")) == [
        "000000.radar.npy",
        "000001.radar.npy",
        "000002.radar.npy",
    ]
    split = PreparedSplit(radar_split, max_radar_points=4)
    counts = [
        check_points_on_map(split[i]["radar_points"], split[i]["sparse"], 4)
        for i in range(len(split))
    ]
    assert counts == [4, 0, 2]  # frame a has 5 returns: the nearest 4 kept
    assert (_valid(split[0]["radar_points"])[:, VELOCITY] == 2.5).all()
    every = PreparedSplit(radar_split, max_radar_points=64)[0]["radar_points"]
    assert int(every[:, VALID].sum()) == 5 and torch.equal(every[:4], split[0]["radar_points"])


def test_datasets_without_radar_have_no_points_and_mixed_splits_are_refused(tmp_path) -> None:
    def lidar_frame(frame_id: str) -> PreparedFrame:
        frame = _radar_frame(frame_id)
        frame.radar_points = None
        return frame

    plain = prepare_split(tmp_path / "plain", "val", ["a", "b"], lidar_frame, {})
    assert "radar_points" not in PreparedSplit(plain)[0] and not list(plain.glob("*.radar.npy"))
    mixed = prepare_split(
        tmp_path / "mixed",
        "val",
        ["a", "c"],
        lambda f: (lidar_frame if f == "a" else _radar_frame)(f),
        {},
    )
    with pytest.raises(DataFileError, match="some frames have radar points"):
        PreparedSplit(mixed)


def test_points_off_the_image_or_malformed_are_refused_when_prepared(tmp_path) -> None:
    def off_image(frame_id: str) -> PreparedFrame:
        frame = _radar_frame(frame_id)
        frame.radar_points = point_rows([12.0], [1.0], [5.0])  # u = width: outside
        return frame

    with pytest.raises(ValueError, match="radar_points"):
        prepare_split(tmp_path, "val", ["a"], off_image, {})


def _damage(path: Path, how: str, rng: np.random.Generator) -> None:
    data = path.read_bytes()
    if how == "truncated":
        path.write_bytes(data[: int(rng.integers(0, len(data)))])
    elif how == "flipped":
        buffer = bytearray(data)
        for at in rng.integers(0, len(buffer), 4):
            buffer[at] ^= int(rng.integers(1, 256))
        path.write_bytes(bytes(buffer))
    elif how == "garbage":
        path.write_bytes(rng.bytes(int(rng.integers(0, 400))))
    elif how == "float64":
        np.save(path, np.load(path).astype(np.float64))
    elif how == "one column less":
        np.save(path, np.load(path)[:, :-1])
    elif how == "1-d":
        np.save(path, np.load(path).ravel())
    elif how == "nan":
        rows = np.load(path)
        rows[0, DEPTH] = np.nan
        np.save(path, rows)
    elif how == "pickled":
        np.save(path, np.array([{"u": 1}], dtype=object), allow_pickle=True)
    elif how == "npz":
        rows = np.load(path)
        with path.open("wb") as f:
            np.savez(f, rows=rows)
    elif how == "huge header":
        header = "{'descr': '<f4', 'fortran_order': False, 'shape': (100000000, 6), }"
        header += " " * (118 - len(header) - 1) + "\n"
        path.write_bytes(b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode())


DAMAGE = ["truncated", "flipped", "garbage", "float64", "one column less", "1-d", "nan"]
DAMAGE += ["pickled", "npz", "huge header"]


@pytest.mark.parametrize("how", DAMAGE)
@pytest.mark.parametrize("seed", range(4))
def test_a_damaged_points_file_loads_checked_or_fails_naming_it(radar_split, how, seed) -> None:
    path = radar_split / "000000.radar.npy"
    _damage(path, how, np.random.default_rng(seed))
    for read in (lambda: read_points(path), lambda: PreparedSplit(radar_split)[0]["radar_points"]):
        try:
            rows = read()
        except DataFileError as err:
            assert_short(err, path)
            continue
        # Damage numpy cannot see (a flipped bit in a value) still gives well-formed rows.
        rows = np.asarray(rows)
        assert rows.dtype == np.float32 and rows.ndim == 2 and rows.shape[1] == NUM_FIELDS
        assert np.isfinite(rows).all()


def test_write_points_refuses_rows_of_another_shape(tmp_path) -> None:
    with pytest.raises(ValueError, match="expected"):
        write_points(tmp_path / "x.radar.npy", np.zeros((3, NUM_FIELDS - 1)))
    with pytest.raises(FileNotFoundError):
        read_points(tmp_path / "missing.radar.npy")


# --- CARLA ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return record_fixture(tmp_path_factory.mktemp("carla") / "recording")


def test_carla_points_are_the_detections_of_the_sparse_map(recording, tmp_path) -> None:
    train = CarlaDepth("train", recording, tmp_path / "cache", height=CARLA_H, width=CARLA_W)
    assert train.max_radar_points == 128
    for i in range(len(train)):
        sample = train[i]
        count = check_points_on_map(sample["radar_points"], sample["sparse"], 128)
        assert count == (3 if i == 0 else 1)  # behind the camera, outside the image: dropped
        rows = _valid(sample["radar_points"])
        assert (rows[:, VELOCITY] == np.float32(-1.5)).all() and (rows[:, RCS] == 0).all()
    # (20, 2, -1) lands at u = 47.5 + 48 * 2/20 = 52.3, v = 31.5 + 48 * 1/20 = 33.9 (test_carla;
    # pixel centres at integers, so the image centre of 96x64 is (47.5, 31.5)); the pair on one
    # pixel keeps both points, 24 m and 30 m, nearest first.
    rows = _valid(train[0]["radar_points"])
    np.testing.assert_allclose(
        rows[:, :3], [[52.3, 33.9, 20], [37.9, 26.7, 24], [37.9, 26.7, 30]], atol=1e-4
    )


def test_carla_p_is_applied_when_serving(recording, tmp_path) -> None:
    cache = tmp_path / "cache"
    every = CarlaDepth("train", recording, cache, height=CARLA_H, width=CARLA_W)
    files = sorted(p.relative_to(cache) for p in cache.rglob("*"))
    two = CarlaDepth("train", recording, cache, height=CARLA_H, width=CARLA_W, max_radar_points=2)
    assert sorted(p.relative_to(cache) for p in cache.rglob("*")) == files  # nothing prepared
    assert two[0]["radar_points"].shape == (2, NUM_FIELDS)
    assert torch.equal(two[0]["radar_points"], every[0]["radar_points"][:2])
    assert torch.equal(two[0]["sparse"], every[0]["sparse"])  # the map keeps all
    resized = CarlaDepth("val", recording, tmp_path / "small", height=32, width=64)
    check_points_on_map(resized[0]["radar_points"], resized[0]["sparse"], 128)
    with pytest.raises(ValueError, match="max_radar_points=-1"):
        CarlaDepth("val", recording, cache, height=CARLA_H, width=CARLA_W, max_radar_points=-1)
