"""dataset=carla: CARLA's encodings and geometry checked numerically, the recorder's writers
round-tripped through the reader with stand-in measurements, bad input, and one training run."""

from __future__ import annotations

import importlib.util
import json
import logging
import math
import os
import re
from pathlib import Path

import numpy as np
import pytest
from helpers import REPO, command_message, run_module, run_sweep
from helpers.carla import (
    CACHE_STEP,
    FOV,
    RADAR_POSE,
    H,
    Location,
    Rotation,
    Transform,
    W,
    detection_at,
    pixels,
    record_fixture,
    recorder,
    scene_depth,
    scene_rgb,
)
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from PIL import Image

from fusion_depth.data.cache import SkippedFramesError
from fusion_depth.data.carla import (
    DEPTH_STEP,
    CarlaDepth,
    condition_of,
    decode_carla_depth,
    encode_carla_depth,
    matrix_to_transform,
    project_radar,
    read_carla_depth,
    relative_transform,
    transform_matrix,
)
from fusion_depth.prepare.cli import prepare


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return record_fixture(tmp_path_factory.mktemp("carla") / "recording")


@pytest.mark.parametrize(
    "name,condition",
    [
        ("ClearNoon", "day"),
        ("ClearSunset", "day"),
        ("WetNoon", "day"),
        ("CloudyNoon", "cloudy"),
        ("WetCloudySunset", "cloudy"),
        ("MidRainyNoon", "rain"),
        ("HardRainNoon", "rain"),
        ("SoftRainSunset", "rain"),
        ("ClearNight", "night"),
        ("HardRainNight", "night"),
        ("FoggyNoon", "fog"),
        ("DustStorm", "fog"),
        ("fog", "fog"),
        ("Night", "night"),
        ("cloudy", "cloudy"),
    ],
)
def test_weather_presets_map_to_conditions(name, condition) -> None:
    assert condition_of(name) == condition


def test_unknown_weather_is_named() -> None:
    with pytest.raises(ValueError, match="'Default'.*ClearNoon"):
        condition_of("Default")


def test_depth_png_decodes_to_the_encoded_metres(tmp_path) -> None:
    # CARLA's formula on hand-picked codes: metres = 1000 (R + 256 G + 65536 B) / (256^3 - 1).
    codes = np.array([[[255, 255, 255], [1, 0, 0], [92, 143, 2], [0, 0, 0]]], np.uint8)
    expected = [1000.0, 1000 / 16777215, 1000 * (92 + 143 * 256 + 2 * 65536) / 16777215, 0.0]
    np.testing.assert_allclose(decode_carla_depth(codes)[0], expected, rtol=0, atol=1e-9)
    depth = np.random.default_rng(0).uniform(0, 1000, (40, 50))
    depth[0, :3] = [0.0, 1000.0, 12.345678]
    path = tmp_path / "depth.png"
    Image.fromarray(encode_carla_depth(depth), "RGB").save(path)
    decoded = read_carla_depth(path)
    assert np.abs(decoded - depth).max() <= DEPTH_STEP / 2 + 1e-9


def test_grey_converted_depth_png_is_rejected(tmp_path) -> None:
    grey = np.repeat(np.arange(40, dtype=np.uint8).reshape(5, 8, 1), 3, axis=2)
    Image.fromarray(grey, "RGB").save(tmp_path / "grey.png")
    with pytest.raises(ValueError, match="grey.png.*ColorConverter"):
        read_carla_depth(tmp_path / "grey.png")
    Image.fromarray(np.zeros((4, 4), np.uint16)).save(tmp_path / "u16.png")
    with pytest.raises(ValueError, match="u16.png.*8-bit RGB"):
        read_carla_depth(tmp_path / "u16.png")


def test_transform_matrix_follows_carla_axes() -> None:
    def rotate(pitch=0.0, yaw=0.0, roll=0.0):
        return transform_matrix(Transform(Location(), Rotation(pitch, yaw, roll)))[:3, :3]

    np.testing.assert_allclose(rotate(yaw=90) @ [1, 0, 0], [0, 1, 0], atol=1e-12)  # turns right
    np.testing.assert_allclose(rotate(pitch=90) @ [1, 0, 0], [0, 0, 1], atol=1e-12)  # nose up
    np.testing.assert_allclose(rotate(roll=90) @ [0, 1, 0], [0, 0, -1], atol=1e-12)
    m = transform_matrix(Transform(Location(1, 2, 3), Rotation(10.0, -35.0, 20.0)))
    np.testing.assert_allclose(m @ [0, 0, 0, 1], [1, 2, 3, 1])
    np.testing.assert_allclose(transform_matrix(matrix_to_transform(m)), m, atol=1e-12)


def test_relative_transform_puts_the_radar_in_camera_coordinates() -> None:
    # Both sensors look to the vehicle's right; the radar sits 2 m further right: 2 m ahead.
    camera = Transform(Location(1.0, 0.0, 1.0), Rotation(yaw=90.0))
    radar = Transform(Location(1.0, 2.0, 1.0), Rotation(yaw=90.0))
    rel = relative_transform(camera, radar)
    np.testing.assert_allclose(list(rel["location"].values()), [2.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(list(rel["rotation"].values()), [0.0, 0.0, 0.0], atol=1e-12)


def test_detection_lands_on_the_expected_pixel_with_its_depth() -> None:
    pose = transform_matrix(RADAR_POSE)
    det = detection_at((20.0, 2.0, -1.0))
    row = [[det.depth, det.azimuth, det.altitude, det.velocity]]
    sparse = project_radar(row, pose, FOV, (H, W), (H, W))
    # u = 48 + 48 * 2/20 = 52.8, v = 32 + 48 * 1/20 = 34.4, depth = forward distance 20 m.
    assert pixels(sparse) == [(34, 52)]
    assert sparse[34, 52] == pytest.approx(20.0, abs=1e-4)
    # Scaled to 32x64 the intrinsics scale per axis: fx = 48 * 64/96 = 32, fy = 48 * 32/64 = 24.
    small = project_radar(row, pose, FOV, (H, W), (32, 64))
    assert pixels(small) == [(17, 35)]  # v 17.2, u 35.2
    assert small[17, 35] == pytest.approx(20.0, abs=1e-4)
    # A radar turned 90° right, 10 m ahead and 4.9 m left, sees 0.1 m right of straight ahead.
    turned = transform_matrix(Transform(Location(10.0, -4.9, -0.1), Rotation(yaw=90.0)))
    ahead = project_radar([[5.0, 0.0, 0.0, 0.0]], turned, FOV, (H, W), (H, W))
    assert pixels(ahead) == [(32, 48)]  # u = 48 + 48 * 0.1/10, v = 32 + 48 * 0.1/10
    assert ahead[32, 48] == pytest.approx(10.0)
    # Positive azimuth is to the right, positive altitude up (identity pose).
    identity = np.eye(4)
    az = math.atan(0.51)  # u = 48 + 48 * 0.51 = 72.48
    right = project_radar([[10.0, az, 0.0, 0.0]], identity, FOV, (H, W), (H, W))
    assert pixels(right) == [(32, 72)]
    assert right[32, 72] == pytest.approx(10.0 * math.cos(az))
    up = project_radar([[10.0, 0.0, math.radians(10.0), 0.0]], identity, FOV, (H, W), (H, W))
    assert pixels(up)[0][0] < 32


def test_nearer_detection_wins_and_points_behind_or_outside_are_dropped() -> None:
    rows = [
        [20.0, 0.0, 0.0, 0.0],
        [20.001, 0.0, 0.0, 0.0],  # same pixel, farther
        [19.999, 1e-5, 0.0, 0.0],  # same pixel, nearer
        [5.0, math.pi, 0.0, 0.0],  # behind
        [5.0, math.radians(60), 0.0, 0.0],  # outside the 90° field of view
        [300.0, 0.0, 0.0, 0.0],  # beyond max_range
    ]
    sparse = project_radar(rows, np.eye(4), FOV, (H, W), (H, W), max_range=250.0)
    assert np.count_nonzero(sparse) == 1
    assert sparse[32, 48] == pytest.approx(19.999, abs=1e-4)


def test_recorder_output_round_trips_through_the_reader(recording, tmp_path) -> None:
    meta = json.loads((recording / "train/meta/00000100.json").read_text())
    assert meta["fov"] == FOV and meta["condition"] == "ClearNoon" and meta["frame"] == 100
    header = (recording / "train/radar/00000100.csv").read_text().splitlines()[0]
    assert header == "depth,azimuth,altitude,velocity"

    train = CarlaDepth("train", recording, tmp_path / "cache", height=H, width=W)
    assert len(train) == 4
    assert train.conditions == ["day", "rain", "night", "cloudy"]
    sample = train[0]
    assert sample["image"].shape == (3, H, W) and sample["condition"] == "day"
    # BGRA raw_data came back as the original RGB.
    np.testing.assert_array_equal(
        (sample["image"].numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8), scene_rgb(100)
    )
    # Ground truth: the encoded metres (cache step 1/256 m); the sky (1000 m) invalid.
    depth = sample["depth"][0].numpy()
    expected = scene_depth(100)
    assert (depth[:6] == 0).all()
    assert np.abs(depth[6:] - expected[6:]).max() <= CACHE_STEP / 2 + DEPTH_STEP
    # Radar: (20, 2, -1) at u = 48 + 48 * 2/20 = 52.8, v = 32 + 48 * 1/20 = 34.4; the pair at
    # u = 48 - 48 * 6/30 = 38.4, v = 32 - 48 * 3/30 = 27.2, where the nearer (24 m) wins.
    sparse = sample["sparse"][0].numpy()
    points = {(r, c): float(sparse[r, c]) for r, c in pixels(sparse)}
    assert points == {
        (34, 52): pytest.approx(20.0, abs=CACHE_STEP),
        (27, 38): pytest.approx(24.0, abs=CACHE_STEP),
    }
    assert pixels(train[1]["sparse"][0].numpy()) == [(34, 52)]


def test_resized_frames_keep_exact_depths(recording, tmp_path) -> None:
    val = CarlaDepth("val", recording, tmp_path / "cache", height=32, width=64)
    assert val.conditions == ["fog", "cloudy"]
    sample = val[0]
    assert sample["image"].shape == (3, 32, 64)
    sparse = sample["sparse"][0].numpy()
    assert pixels(sparse) == [(17, 35)]
    assert sparse[17, 35] == pytest.approx(20.0, abs=CACHE_STEP)
    # Nearest sampling: every ground-truth value is one the depth camera rendered.
    depth = sample["depth"][0].numpy()
    rendered = scene_depth(200)
    valid = depth > 0
    nearest = np.abs(depth[valid][:, None] - rendered[6:].ravel()[None, :]).min(axis=1)
    assert nearest.max() <= CACHE_STEP / 2 + DEPTH_STEP


def test_conditions_select_frames(recording, tmp_path) -> None:
    train = CarlaDepth(
        "train", recording, tmp_path / "c", height=H, width=W, conditions=["rain", "fog"]
    )
    assert train.conditions == ["rain"]
    with pytest.raises(ValueError) as err:
        CarlaDepth("train", recording, tmp_path / "c", height=H, width=W, conditions=["night"])
    shown = command_message(err.value, "dataset=carla")  # the reader names its argument
    assert re.search(r"val.*dataset.conditions=\['night'\]", shown), shown


def test_prepare_is_idempotent_and_never_writes_into_the_recording(
    recording, make_config, tmp_path
) -> None:
    before = sorted((p, p.stat().st_mtime_ns) for p in recording.rglob("*"))
    cfg = make_config(
        "dataset=carla", f"dataset.root={recording}", "dataset.height=64", "dataset.width=96"
    )
    assert prepare(cfg) == {"train": 4, "val": 2, "test": 2}
    cache = Path(cfg.paths.cache_dir) / "carla"
    files = sorted((p, p.stat().st_mtime_ns) for p in cache.rglob("*"))
    assert prepare(cfg) == {"train": 4, "val": 2, "test": 2}
    assert sorted((p, p.stat().st_mtime_ns) for p in cache.rglob("*")) == files
    assert sorted((p, p.stat().st_mtime_ns) for p in recording.rglob("*")) == before


def _copy(src: Path, dst: Path) -> Path:
    for path in src.rglob("*"):
        if path.is_file():
            target = dst / path.relative_to(src)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(path.read_bytes())
    return dst


def _break(root: Path, change: str) -> Path:
    """A copy of the recording with one thing wrong; returns the root to read."""
    if change == "root":
        return root / "nowhere"
    if change == "split":
        (root / "test").rename(root / "testing")
    elif change == "sensor-dir":
        (root / "val/rgb").rename(root / "val/images")
    elif change == "file":
        (root / "train/rgb/00000110.png").unlink()
    elif change == "corrupt":
        (root / "test/depth/00000310.png").write_bytes(b"\x89PNG broken")
    elif change == "empty":
        for path in (root / "val/meta").iterdir():
            path.unlink()
    elif change == "meta":
        (root / "train/meta/00000120.json").write_text('{"fov": 90}')
    elif change == "radar":
        (root / "test/radar/00000300.csv").write_text("x,y,z\n1,2,3\n")
    elif change in ("meta-dir", "rgb-dir"):
        path = root / (
            "train/meta/00000120.json" if change == "meta-dir" else "val/rgb/00000210.png"
        )
        path.unlink()
        path.mkdir()
    return root


@pytest.mark.parametrize(
    "change,error,match",
    [
        ("root", FileNotFoundError, "nowhere: no such folder.*train,val,test"),
        ("split", FileNotFoundError, "copy/test: missing folder, expected the test split"),
        ("sensor-dir", FileNotFoundError, "val/rgb: missing folder.*found.*images"),
        ("file", FileNotFoundError, "train/rgb/00000110.png: missing rgb file of frame 00000110"),
        ("corrupt", ValueError, "test/depth/00000310.png: unreadable CARLA depth PNG"),
        ("empty", ValueError, "val/meta: no frames, the val split is empty"),
        ("meta", ValueError, "00000120.json: missing key 'condition'"),
        ("radar", ValueError, "00000300.csv: expected the header depth,azimuth,altitude,velocity"),
        (
            "meta-dir",
            IsADirectoryError,
            "train/meta/00000120.json: a directory, expected the meta file of frame 00000120",
        ),
        (
            "rgb-dir",
            IsADirectoryError,
            "val/rgb/00000210.png: a directory, expected the rgb file of frame 00000210",
        ),
    ],
)
def test_bad_input_fails_before_training_naming_the_path(
    recording, tmp_path, change, error, match
) -> None:
    # Building the train split checks (and prepares) all three, so a bad test frame fails now.
    root = _break(_copy(recording, tmp_path / "copy"), change)
    with pytest.raises(error, match=match):
        CarlaDepth("train", root, tmp_path / "cache", height=H, width=W)


def test_prepare_skips_broken_frames_by_name_and_training_still_refuses_them(
    recording, tmp_path, make_config, caplog
) -> None:
    root = _break(_break(_copy(recording, tmp_path / "copy"), "meta-dir"), "corrupt")
    (root / "val/radar/00000200.csv").write_text("depth,azimuth,altitude,velocity\n-3,0,0,0\n")
    cfg = make_config(
        "dataset=carla", f"dataset.root={root}", "dataset.height=64", "dataset.width=96"
    )
    with caplog.at_level(logging.WARNING), pytest.raises(SkippedFramesError) as info:
        prepare(cfg)

    assert [report.line() for report in info.value.reports] == [
        "train: 3 of 4 frames prepared; skipped 1: train/00000120",
        "val: 1 of 2 frames prepared; skipped 1: val/00000200",
        "test: 1 of 2 frames prepared; skipped 1: test/00000310",
    ]
    for frame_id, problem in (
        ("train/00000120", f"{root / 'train/meta/00000120.json'}: a directory"),
        ("val/00000200", f"{root / 'val/radar/00000200.csv'}: line 2: depth -3.0 is negative"),
        ("test/00000310", f"{root / 'test/depth/00000310.png'}: unreadable CARLA depth PNG"),
    ):
        assert f"skipped {frame_id}: {problem}" in caplog.text
    caches = [
        c
        for c in (Path(cfg.paths.cache_dir) / "carla").iterdir()
        if json.loads((c / "meta.json").read_text())["root"] == str(root.resolve())
    ]
    assert len(caches) == 1
    assert len(list(caches[0].glob("*/0*.json"))) == 5  # every good frame is prepared
    assert not list(caches[0].glob("*/index.json"))  # but no split is marked prepared

    # Training's reader fails at the first broken frame, naming it.
    with pytest.raises(IsADirectoryError, match="train/meta/00000120.json: a directory"):
        CarlaDepth("train", root, cfg.paths.cache_dir, height=H, width=W)


def test_missing_root_fails_at_config_time(make_config) -> None:
    from omegaconf.errors import MissingMandatoryValue

    from fusion_depth.config import validate_config

    with pytest.raises(MissingMandatoryValue, match="dataset.root"):
        validate_config(make_config("dataset=carla"))


def test_recorder_needs_the_carla_client() -> None:
    if importlib.util.find_spec("carla") is not None:
        pytest.skip("the carla client is installed here")
    with pytest.raises(SystemExit, match="pip install carla"):
        recorder.import_carla()
    args = recorder.parse_args(["--out", "x", "--resolution", "800x600", "--conditions", "fog"])
    assert (args.width, args.height, args.conditions) == (800, 600, ["fog"])


def compose_sweep(name: str, *overrides: str):
    """A sweep config of ``sweeps/`` composed as ``--config-dir sweeps --config-name`` does."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(str(REPO / "sweeps"), version_base="1.3"):
        return compose(
            name,
            overrides=[f"hydra.searchpath=[file://{REPO / 'conf'}]", *overrides],
            return_hydra_config=True,
        )


def test_sweep_config_reproduces_the_papers_carla_table(tmp_path) -> None:
    cfg = compose_sweep("carla_loss_fusion_grid", f"dataset.root={tmp_path}")
    GlobalHydra.instance().clear()
    assert cfg.dataset.name == "carla" and cfg.dataset.root == str(tmp_path)
    params = cfg.hydra.sweeper.params
    assert set(params.loss.split(",")) == {"l1", "l2", "berhu"}
    assert set(params.fusion.split(",")) == {"rgb", "concat", "add"}
    assert cfg.trainer.max_epochs == 20 and cfg.backbone.pretrained is True


@pytest.mark.slow
def test_training_and_testing_on_a_recording(recording, make_config) -> None:
    from fusion_depth.train.fit import train

    cfg = make_config(
        "dataset=carla",
        f"dataset.root={recording}",
        "dataset.height=64",
        "dataset.width=96",
        "backbone=resnet50",
        "backbone.pretrained=false",
        "fusion=concat",
        "loss=berhu",
        "logger=none",
        "trainer.max_epochs=1",
        "trainer.limit_train_batches=2",
        "trainer.limit_val_batches=1",
        "trainer.num_sanity_val_steps=0",
        "trainer.enable_model_summary=false",
        "callbacks.model_checkpoint.save_last=false",
        "+callbacks.model_checkpoint.save_weights_only=true",
        "model.num_val_panels=1",
        "data.eval_batch_size=2",
    )
    results = train(cfg)
    saved = json.loads((Path(cfg.paths.output_dir) / "metrics.json").read_text())
    assert saved["test"] == results["test"] and results["test"]["num_images"] == 2
    assert results["run"]["dataset"] == "carla" and results["run"]["sensor"] == "radar"
    assert set(results["test_by_condition"]) <= {"day", "rain"}
    assert all(math.isfinite(v) for v in results["test"].values())
    assert os.path.isfile(results["best_checkpoint"])


@pytest.mark.slow
def test_the_carla_sweep_runs_under_the_smoke_experiment(recording, tmp_path) -> None:
    sweep = tmp_path / "sweep"
    result = run_sweep(
        "carla_loss_fusion_grid",
        [f"dataset.root={recording}", "seed=42", "loss=l1", "fusion=rgb,concat"],
        sweep,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "2 ok, 0 failed" in result.stdout
    args = ["fusion_depth.report", str(sweep), "--compare", "fusion=rgb", "--resamples", "200"]
    report = run_module(args, cwd=tmp_path, timeout=120)
    assert report.returncode == 0, report.stderr
    assert "RGB-Fusion" in report.stdout
