"""Tests of the built-in procedural dataset (tiny frames, so the module runs in seconds)."""

from __future__ import annotations

import json
import logging
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from fusion_depth.data import procedural
from fusion_depth.data.procedural import CONDITIONS, ProceduralDepth, render_frame
from fusion_depth.utils.atomic import host_tag

H, W = 64, 96
SMALL = {"height": H, "width": W, "num_train": 10, "num_val": 5, "num_test": 5}


def _arrays(ds: ProceduralDepth) -> dict[str, np.ndarray]:
    return {name: np.load(ds.split_dir / f"{name}.npy") for name in ("image", "depth", "sparse")}


def _stack(ds: ProceduralDepth, key: str) -> np.ndarray:
    return np.stack([ds[i][key][0].numpy() for i in range(len(ds))])


@pytest.fixture(scope="module")
def radar_train(tmp_path_factory) -> ProceduralDepth:
    return ProceduralDepth("train", tmp_path_factory.mktemp("radar"), **SMALL)


@pytest.fixture(scope="module")
def lidar_train(tmp_path_factory) -> ProceduralDepth:
    return ProceduralDepth("train", tmp_path_factory.mktemp("lidar"), sparse="lidar", **SMALL)


def test_same_seed_same_arrays_different_seed_differs(tmp_path, radar_train):
    again = _arrays(ProceduralDepth("train", tmp_path / "b", **SMALL))
    for name, array in _arrays(radar_train).items():
        assert np.array_equal(array, again[name]), name
    other = _arrays(ProceduralDepth("train", tmp_path / "c", seed=1, **SMALL))
    assert not np.array_equal(other["image"], again["image"])
    assert not np.array_equal(other["depth"], again["depth"])


def test_splits_use_different_streams(tmp_path, radar_train):
    val = ProceduralDepth("val", radar_train.cache_dir.parent, **SMALL)
    assert val.cache_dir == radar_train.cache_dir
    assert not torch.equal(val[0]["depth"], radar_train[0]["depth"])


def test_sample_format(radar_train):
    assert len(radar_train) == SMALL["num_train"]
    sample = radar_train[0]
    # A radar split adds its returns as points (issue 16; tests/test_radar_points.py).
    assert set(sample) == {"image", "sparse", "depth", "condition", "radar_points"}
    assert sample["image"].shape == (3, H, W) and sample["image"].dtype == torch.float32
    for key in ("sparse", "depth"):
        assert sample[key].shape == (1, H, W) and sample[key].dtype == torch.float32
        assert sample[key].min() >= 0
    assert 0 <= sample["image"].min() and sample["image"].max() <= 1
    assert sample["image"].std() > 0.02  # a picture, not a blank frame
    assert sample["depth"].max() > 20  # the street recedes into the distance
    assert sample["condition"] in CONDITIONS
    assert torch.equal(radar_train[-1]["depth"], radar_train[len(radar_train) - 1]["depth"])
    with pytest.raises(IndexError):
        radar_train[len(radar_train)]


def test_radar_is_sparse_and_near_the_true_depth(radar_train):
    sparse, depth = _stack(radar_train, "sparse"), _stack(radar_train, "depth")
    counts = (sparse > 0).sum(axis=(1, 2))
    assert counts.min() >= 5 and counts.max() <= 100, counts
    hit = sparse > 0
    err = np.abs(sparse[hit] - depth[hit])
    # Range/azimuth noise, clutter and multipath: most, not all, returns match the surface.
    assert np.mean(err <= np.maximum(1.0, 0.1 * depth[hit])) > 0.5


def test_lidar_is_sparse_denser_than_radar_and_accurate(lidar_train, radar_train):
    sparse, depth = _stack(lidar_train, "sparse"), _stack(lidar_train, "depth")
    counts = (sparse > 0).sum(axis=(1, 2))
    assert counts.max() < 0.05 * H * W, counts
    radar_counts = (_stack(radar_train, "sparse") > 0).sum(axis=(1, 2))
    assert counts.mean() > 2 * radar_counts.mean()
    hit = sparse > 0
    assert np.all(depth[hit] > 0)  # lidar returns only where there is a surface
    assert np.mean(np.abs(sparse[hit] - depth[hit]) < 0.1 + 0.01 * depth[hit]) > 0.95
    # The same frames with radar show the same street: only the sparse input differs.
    assert torch.equal(lidar_train[3]["image"], radar_train[3]["image"])


def test_sky_has_zero_depth_and_ground_is_valid(radar_train):
    depth = _stack(radar_train, "depth")
    images = np.stack([radar_train[i]["image"].numpy() for i in range(len(radar_train))])
    assert np.mean(depth[:, H // 2 + 8 :] > 0) > 0.99  # below the horizon: road and objects
    assert np.mean(depth > 0) > 0.7
    day = [i for i in range(len(radar_train)) if radar_train.conditions[i] == "day"]
    sky = depth[day] == 0
    assert sky.sum() > 20
    rows = np.nonzero(sky)[1]
    assert np.all(rows < H // 2 + 8)  # no invalid depth down on the road
    rgb = images[day].transpose(0, 2, 3, 1)[sky]
    assert rgb[:, 2].mean() > rgb[:, 0].mean() + 0.05  # and those pixels are blue sky


def test_depth_is_camera_z_of_the_first_surface_hit():
    from fusion_depth.data._procedural_scene import GROUND_ID, SKY_ID, cast_primary, sample_scene

    scene = sample_scene(np.random.default_rng(3), H, W, 70.0)
    rays = scene.camera.rays()
    t, ids = cast_primary(scene, rays)
    hit = ids != SKY_ID
    points = scene.camera.position[:, None, None] + rays * np.where(hit, t, 0)
    z = scene.camera.to_camera(points.reshape(3, -1).T)[:, 2].reshape(t.shape)
    np.testing.assert_allclose(z[hit], t[hit], atol=1e-3)  # z, not Euclidean range
    np.testing.assert_allclose(points[1][ids == GROUND_ID], 0.0, atol=1e-3)  # on the road
    boxes = ids >= 0
    p = points[:, boxes].T
    lo, hi = scene.lo[ids[boxes]], scene.hi[ids[boxes]]
    assert np.all((p > lo - 1e-3) & (p < hi + 1e-3))  # on the box it reports
    assert np.all(np.minimum(np.abs(p - lo), np.abs(p - hi)).min(1) < 1e-3)  # on its surface


def test_every_condition_in_every_split(radar_train, tmp_path):
    assert sorted(set(radar_train.conditions)) == sorted(CONDITIONS)
    assert {radar_train.conditions.count(c) for c in CONDITIONS} == {2}
    assert [radar_train[i]["condition"] for i in range(5)] == list(CONDITIONS)
    val = ProceduralDepth("val", tmp_path, conditions=("fog", "night"), **SMALL)
    assert set(val.conditions) == {"fog", "night"}


def test_fog_hides_far_contrast():
    for index in range(3):
        clear, depth, _ = render_frame(0, "test", index, H, W, 70.0, "day", "radar")
        foggy, same_depth, _ = render_frame(0, "test", index, H, W, 70.0, "fog", "radar")
        assert np.array_equal(depth, same_depth)  # weather never moves the geometry
        far = depth > 40
        assert far.sum() > 20
        assert foggy[far].std() < 0.5 * clear[far].std()
        assert foggy[far].std() < 10  # nearly uniform fog colour (uint8 levels)


def test_radar_sees_cars_through_fog():
    counts = [
        (render_frame(0, "test", i, H, W, 70.0, "fog", "radar")[2] > 0).sum() for i in range(3)
    ]
    assert min(counts) >= 5


def test_radar_height_extension_draws_each_return_as_a_vertical_line():
    focal = W / 2 / np.tan(np.radians(70.0) / 2)
    checked = 0
    for i in range(4):
        raw = render_frame(0, "test", i, H, W, 70.0, "day", "radar")[2]
        lines = render_frame(0, "test", i, H, W, 70.0, "day", "radar", 2.0)[2]
        assert (lines[raw > 0] > 0).all(), "every return keeps its pixel"
        assert (lines > 0).sum() > 3 * (raw > 0).sum()
        for col in np.flatnonzero((raw > 0).sum(0) == 1)[1:-1]:
            # The line spans the rows between the ground and 2 m at the return's depth (the
            # camera's roll may move part of it into a neighbouring column).
            z = raw[:, col].max()
            near_z = np.abs(lines[:, col - 1 : col + 2] - z) < 0.1
            rows = np.flatnonzero(near_z.any(1))
            if rows.max() == H - 1 or rows.min() == 0:
                continue  # cut by the image border
            assert len(rows) == rows.max() - rows.min() + 1, "one unbroken line"
            assert abs(len(rows) - focal * 2.0 / z) <= 2.5
            checked += 1
    assert checked >= 5
    with pytest.raises(ValueError, match="radar_height_extension=-1"):
        ProceduralDepth("train", "unused", radar_height_extension=-1, **SMALL)


def test_changing_a_parameter_makes_a_new_cache_and_keeps_the_old(tmp_path):
    first = ProceduralDepth("val", tmp_path, **SMALL)
    before = {p: p.stat().st_mtime_ns for p in first.split_dir.iterdir()}
    second = ProceduralDepth("val", tmp_path, **{**SMALL, "num_val": 6})
    third = ProceduralDepth("val", tmp_path, sparse="lidar", **SMALL)
    assert len({first.cache_dir, second.cache_dir, third.cache_dir}) == 3
    assert len(second) == 6
    assert {p: p.stat().st_mtime_ns for p in first.split_dir.iterdir()} == before
    meta = json.loads((second.cache_dir / "meta.json").read_text())
    assert meta["num_val"] == 6 and meta["generator_version"] == procedural.GENERATOR_VERSION


def test_cache_is_reused_and_only_the_requested_split_is_built(tmp_path, monkeypatch, caplog):
    with caplog.at_level(logging.INFO, logger="fusion_depth.data.procedural"):
        first = ProceduralDepth("val", tmp_path, **SMALL)
    lines = [r.getMessage() for r in caplog.records if "generated" in r.getMessage()]
    assert len(lines) == 1 and "5 procedural val frames" in lines[0]
    assert not (first.cache_dir / "train").exists()
    assert not (first.cache_dir / "test").exists()
    mtime = (first.split_dir / "image.npy").stat().st_mtime_ns

    def fail(*args, **kwargs):
        raise AssertionError("the cache should have been reused")

    monkeypatch.setattr(procedural, "render_frame", fail)
    again = ProceduralDepth("val", tmp_path, **SMALL)
    assert (again.split_dir / "image.npy").stat().st_mtime_ns == mtime
    assert torch.equal(again[2]["image"], first[2]["image"])


def test_interrupted_generation_leaves_nothing_to_read(tmp_path, monkeypatch):
    real = procedural.render_frame
    calls = []

    def crash_after_two(*args, **kwargs):
        calls.append(1)
        if len(calls) > 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(procedural, "render_frame", crash_after_two)
    with pytest.raises(KeyboardInterrupt):
        ProceduralDepth("test", tmp_path, **SMALL)
    (cache,) = tmp_path.iterdir()
    assert [p.name for p in cache.iterdir()] == ["meta.json"]  # no split, no temporary folder
    monkeypatch.setattr(procedural, "render_frame", real)
    assert len(ProceduralDepth("test", tmp_path, **SMALL)) == SMALL["num_test"]


def test_rendering_in_several_processes_gives_the_same_arrays(tmp_path, monkeypatch):
    serial = ProceduralDepth("train", tmp_path / "serial", **SMALL)
    assert procedural.render_processes(SMALL["num_train"]) == 1  # a small split stays in-process
    monkeypatch.setattr(procedural, "render_processes", lambda num_frames: 2)
    monkeypatch.setattr(procedural, "_FRAMES_PER_TASK", 3)  # 4 tasks, the last one short
    renderers = tmp_path / "renderers.txt"
    real = procedural.render_frame

    def render_and_record_the_process(*args, **kwargs):
        with renderers.open("a") as f:  # one short append per frame: whole lines
            f.write(f"{os.getpid()}\n")
        return real(*args, **kwargs)

    monkeypatch.setattr(procedural, "render_frame", render_and_record_the_process)
    parallel = ProceduralDepth("train", tmp_path / "parallel", **SMALL)
    pids = renderers.read_text().split()
    assert len(pids) == SMALL["num_train"]  # every frame rendered once
    assert str(os.getpid()) not in pids  # all by the pool's processes
    names = ("image", "depth", "sparse", procedural.RADAR_ARRAY)
    for name in names:
        a, b = (np.load(ds.split_dir / f"{name}.npy") for ds in (serial, parallel))
        assert a.shape[0] == SMALL["num_train"] and np.array_equal(a, b), name
    assert parallel.conditions == serial.conditions
    assert np.load(parallel.split_dir / "image.npy")[-1].any()  # the last task's frame is drawn


def test_a_renderer_error_in_another_process_leaves_nothing_to_read(tmp_path, monkeypatch):
    monkeypatch.setattr(procedural, "render_processes", lambda num_frames: 2)
    monkeypatch.setattr(procedural, "_FRAMES_PER_TASK", 2)
    parent = os.getpid()

    def fail_in_another_process(*args, **kwargs):
        if os.getpid() == parent:  # rendering here would not be the path under test
            raise AssertionError("rendered in the parent process")
        return 1 / 0

    monkeypatch.setattr(procedural, "render_frame", fail_in_another_process)
    with pytest.raises(ZeroDivisionError):  # raised here, from the process that failed
        ProceduralDepth("test", tmp_path, **SMALL)
    (cache,) = tmp_path.iterdir()
    assert [p.name for p in cache.iterdir()] == ["meta.json"]


def test_losing_a_generation_race_is_harmless(tmp_path):
    first = ProceduralDepth("val", tmp_path, **SMALL)
    before = _arrays(first)
    late = ProceduralDepth("val", tmp_path, **SMALL)
    late._generate()  # a second process that finishes after the first has published
    for name, array in _arrays(late).items():
        assert np.array_equal(array, before[name]), name
    assert sorted(p.name for p in first.cache_dir.iterdir()) == ["meta.json", "val"]


def test_pickles_without_the_arrays(radar_train):
    radar_train[0]  # open the memory maps
    clone = pickle.loads(pickle.dumps(radar_train))
    assert len(pickle.dumps(radar_train)) < 10_000
    assert torch.equal(clone[1]["sparse"], radar_train[1]["sparse"])


@pytest.mark.parametrize(
    ("kwargs", "value"),
    [
        ({"split": "training"}, "training"),
        ({"sparse": "sonar"}, "sonar"),
        ({"height": 100}, "100"),
        ({"width": 0}, "0"),
        ({"conditions": ("day", "snow")}, "snow"),
    ],
)
def test_invalid_arguments_name_the_value(tmp_path, kwargs, value):
    args = {"split": "train", "root": tmp_path, **SMALL, **kwargs}
    with pytest.raises(ValueError, match=value):
        ProceduralDepth(**args)
    assert not any(tmp_path.iterdir())  # rejected before anything is written


def test_height_error_explains_the_multiple_of_32(tmp_path):
    with pytest.raises(ValueError, match="multiple of 32"):
        ProceduralDepth("train", tmp_path, **{**SMALL, "height": 48})


def test_preview_cli_writes_a_grid(tmp_path):
    from PIL import Image

    out = tmp_path / "preview.png"
    procedural.main(["--out", str(out), "--height", "64", "--width", "96"])
    with Image.open(out) as image:
        assert image.size[1] == 5 * 64 + 4 * 4  # one row per condition
        assert image.size[0] == 3 * 96 + 2 * 4  # image | depth | sparse


# --- a damaged or leftover cache mends itself ----------------------------------------------------


def _delete_image(split_dir):
    (split_dir / "image.npy").unlink()


def _truncate_depth(split_dir):
    path = split_dir / "depth.npy"
    os.truncate(path, path.stat().st_size // 2)


def _cut_conditions(split_dir):
    path = split_dir / "conditions.json"
    path.write_text(path.read_text()[:7])


def _empty_sparse(split_dir):
    (split_dir / "sparse.npy").write_bytes(b"")


@pytest.mark.parametrize("damage", [_delete_image, _truncate_depth, _cut_conditions, _empty_sparse])
def test_a_damaged_split_is_generated_again_without_hand_work(tmp_path, damage, caplog):
    first = ProceduralDepth("val", tmp_path, **SMALL)
    before = _arrays(first)
    damage(first.split_dir)
    with caplog.at_level(logging.WARNING, logger="fusion_depth.data.procedural"):
        again = ProceduralDepth("val", tmp_path, **SMALL)
    assert f"{again.split_dir}: " in caplog.text and "generating the split again" in caplog.text
    for name, array in _arrays(again).items():
        assert np.array_equal(array, before[name]), name
    assert again.conditions == first.conditions
    assert sorted(p.name for p in again.cache_dir.iterdir()) == ["meta.json", "val"]


def test_an_edited_meta_json_is_refused_in_one_line(tmp_path):
    first = ProceduralDepth("val", tmp_path, **SMALL)
    meta = first.cache_dir / "meta.json"
    meta.write_text(json.dumps({**json.loads(meta.read_text()), "height": 32}))
    with pytest.raises(ValueError, match=r"meta.json: records height=32, but the folder") as info:
        ProceduralDepth("val", tmp_path, **SMALL)
    assert "\n" not in str(info.value)


def test_a_killed_runs_temporary_folder_goes_and_a_live_ones_stays(tmp_path):
    first = ProceduralDepth("val", tmp_path, **SMALL)
    script = "import os; print(os.getpid())"
    dead = subprocess.run([sys.executable, "-c", script], capture_output=True)
    tag = host_tag()
    orphan = first.cache_dir / f".train.tmp.p{int(dead.stdout)}h{tag}.0e737453"
    live = first.cache_dir / f".train.tmp.p{os.getpid()}h{tag}.1f848564"
    older = first.cache_dir / ".train.tmp-926-0e737453"  # as 0.2.0 named them
    stale_meta = first.cache_dir / ".meta.json.tmp-926-5a5a5a5a"
    for folder in (orphan, live, older):
        folder.mkdir()
        (folder / "image.npy").write_bytes(b"\x93NUMPY half")
    stale_meta.write_text("{")
    hour_ago = time.time() - 3600
    for path in (older, stale_meta):
        os.utime(path, (hour_ago, hour_ago))
    ProceduralDepth("val", tmp_path, **SMALL)
    assert sorted(p.name for p in first.cache_dir.iterdir()) == sorted(
        ["meta.json", "val", live.name]
    )


def test_renderers_die_with_their_parent(tmp_path):
    """A kill -9 of the process rendering a split in a pool leaves no renderer running."""
    script = f"""
import sys
from fusion_depth.data import procedural
procedural.render_processes = lambda num_frames: 2
procedural._FRAMES_PER_TASK = 1
real = procedural.render_frame
procedural.render_frame = lambda *a, **k: (sum(range(400_000_000)), real(*a, **k))[1]
procedural.ProceduralDepth("val", {str(tmp_path)!r}, **{SMALL!r})
"""
    process = subprocess.Popen([sys.executable, "-c", script])
    children = Path(f"/proc/{process.pid}/task/{process.pid}/children")
    deadline = time.monotonic() + 60
    while len(children.read_text().split()) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    renderers = [int(pid) for pid in children.read_text().split()]
    process.kill()
    process.wait(timeout=10)
    time.sleep(2.0)
    running = []
    for pid in renderers:
        stat = Path(f"/proc/{pid}/stat")
        if stat.exists() and stat.read_text().rsplit(")", 1)[1].split()[0] not in "ZX":
            running.append(pid)
    for pid in running:
        os.kill(pid, 9)
    assert len(renderers) == 2 and running == []


# What the command line makes of null, inf, nan, abc, [1], -1, 1.5 and true.
BAD_COUNTS = [None, float("inf"), float("nan"), "abc", [1], -1, 1.5, True]


@pytest.mark.parametrize("key", ["num_train", "num_val", "num_test"])
def test_a_bad_frame_count_is_one_line_naming_the_key_before_any_work(
    make_config, tmp_path, key: str
) -> None:
    """Before: null, inf or a list ended in a TypeError or OverflowError inside the reader, and
    abc got "invalid literal for int()" naming nothing. Now the config check names the key the
    user sets (dataset.num_train, which the reader's argument interpolates), and so does the
    reader for a caller from Python."""
    import copy

    from omegaconf import OmegaConf

    from fusion_depth.config import validate_config
    from fusion_depth.errors import ArgumentError, ConfigError

    composed = make_config("experiment=smoke")
    for value in BAD_COUNTS:
        cfg = copy.deepcopy(composed)
        OmegaConf.update(cfg, f"dataset.{key}", value)
        with pytest.raises(ConfigError) as err:
            validate_config(cfg)
        message = str(err.value)
        assert "\n" not in message and message.startswith(f"dataset.{key}="), message
        assert "expected an integer ≥ 1" in message
        with pytest.raises(ArgumentError, match=rf"^{key}=.*: expected an integer ≥ 1"):
            ProceduralDepth("train", tmp_path / "cache", **{key: value})
    assert not (tmp_path / "cache").exists()


def test_other_cameras_change_the_view_and_the_defaults_keep_the_built_in_frames(tmp_path):
    """``camera_height`` and ``fov_range`` (a source pool of other cameras): at their defaults
    the frames and the cache folder are the built-in ones; a higher camera sees the road nearer
    the bottom of the image farther away, a wider field of view shows more of the street."""
    default = render_frame(0, "test", 3, H, W, 70.0, "day", "radar")
    stated = render_frame(
        0, "test", 3, H, W, 70.0, "day", "radar", camera_height=(1.4, 1.7), fov_range=None
    )
    for a, b in zip(default, stated, strict=True):
        np.testing.assert_array_equal(a, b)
    high = render_frame(0, "test", 3, H, W, 70.0, "day", "radar", camera_height=(3.0, 3.0))
    low = render_frame(0, "test", 3, H, W, 70.0, "day", "radar", camera_height=(1.2, 1.2))
    bottom = slice(H - 4, H)  # the road just ahead: twice as far from a camera 2.5 times higher
    ratio = np.median(high[1][bottom] / np.maximum(low[1][bottom], 1e-3))
    assert 2.0 < ratio < 3.0, ratio
    narrow = render_frame(0, "test", 3, H, W, 70.0, "day", "radar", fov_range=(30.0, 30.0))
    wide = render_frame(0, "test", 3, H, W, 70.0, "day", "radar", fov_range=(110.0, 110.0))
    assert np.median(narrow[1][bottom]) > 1.5 * np.median(wide[1][bottom])
    drawn = {
        float(np.median(render_frame(0, "test", i, H, W, 70.0, "day", "radar",
                                     fov_range=(40.0, 110.0))[1][bottom]))
        for i in range(4)
    }  # fmt: skip
    assert len(drawn) == 4  # a field of view per frame
    base = ProceduralDepth("test", tmp_path, **SMALL)
    same = ProceduralDepth("test", tmp_path, **SMALL, camera_height=[1.4, 1.7], fov_range=None)
    assert same.cache_dir == base.cache_dir
    other = ProceduralDepth("test", tmp_path, **SMALL, camera_height=[1.2, 3.0])
    assert other.cache_dir != base.cache_dir and other.params["camera_height"] == [1.2, 3.0]


@pytest.mark.parametrize(
    ("kwargs", "named"),
    [
        ({"camera_height": [3.0, 1.2]}, "camera_height"),
        ({"camera_height": 1.5}, "camera_height"),
        ({"fov_range": [5.0, 90.0]}, "fov_range"),
    ],
)
def test_camera_ranges_out_of_bounds_are_refused_naming_the_key(tmp_path, kwargs, named):
    with pytest.raises(ValueError, match=rf"^{named}=.*: expected"):
        ProceduralDepth("train", tmp_path, **SMALL, **kwargs)
    assert not any(tmp_path.iterdir())
