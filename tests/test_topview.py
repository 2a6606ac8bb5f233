"""dataset=topview: Unreal depth exports decoded exactly, RGB only enforced at config time, bad
input named, prepare idempotent, and one training run."""

from __future__ import annotations

import json
import logging
import math
import zlib
from pathlib import Path

import numpy as np
import pytest
from helpers import REPO, run_module, run_sweep
from helpers.topview import CACHE_STEP, SPLIT_FRAMES, H, W, crane_depth_cm, write_folder
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from PIL import Image

from fusion_depth.config import validate_config
from fusion_depth.data import topview
from fusion_depth.data.cache import SkippedFramesError
from fusion_depth.data.topview import TopViewDepth, read_depth_file
from fusion_depth.prepare.cli import prepare


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    return write_folder(tmp_path_factory.mktemp("topview") / "data")


def _expected_metres(name: str, png: bool) -> np.ndarray:
    depth = crane_depth_cm(zlib.crc32(name.encode()) % 1000)
    return (np.round(depth) if png else depth.astype(np.float32).astype(np.float64)) * 0.01


def test_png_and_npy_depth_decode_to_metres(folder, tmp_path) -> None:
    train = TopViewDepth("train", folder, tmp_path / "cache", height=H, width=W)
    assert len(train) == 4 and train.conditions == ["day"] * 4
    for index, png in ((0, True), (1, False)):
        sample = train[index]
        assert sample["image"].shape == (3, H, W) and sample["condition"] == "day"
        assert not sample["sparse"].any()  # camera only
        expected = _expected_metres(SPLIT_FRAMES["train"][index], png)
        got = sample["depth"][0].numpy()
        assert np.abs(got - expected).max() <= CACHE_STEP / 2 + 1e-4
    image = (train[0]["image"].numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8)
    expected_rgb = np.asarray(Image.open(folder / "train/rgb/a00.png").convert("RGB"))
    np.testing.assert_array_equal(image, expected_rgb)


def test_depth_unit_applies_to_npy_in_metres(tmp_path) -> None:
    metres = np.full((4, 5, 1), 42.5, np.float64)
    metres[0, 0] = np.nan
    metres[1, 1] = -3.0
    np.save(tmp_path / "m.npy", metres)
    depth = read_depth_file(tmp_path / "m.npy", depth_unit=1.0)
    assert depth.shape == (4, 5) and depth[0, 0] == 0 and depth[1, 1] == 0
    assert depth[2, 2] == pytest.approx(42.5)


def test_exr_is_refused_naming_the_file_and_the_alternatives(tmp_path) -> None:
    (tmp_path / "frame.exr").write_bytes(b"v/1\x01")
    with pytest.raises(ValueError, match="frame.exr: EXR.*not supported.*\\.npy.*16-bit PNG"):
        read_depth_file(tmp_path / "frame.exr", depth_unit=0.01)


def test_resizing_keeps_rendered_depths(folder, tmp_path) -> None:
    val = TopViewDepth("val", folder, tmp_path / "cache", height=32, width=64)
    sample = val[0]
    assert sample["image"].shape == (3, 32, 64) and sample["depth"].shape == (1, 32, 64)
    rendered = np.unique(_expected_metres("b00", png=True))
    got = sample["depth"][0].numpy().ravel()
    nearest = np.abs(got[:, None] - rendered[None, :]).min(axis=1)
    assert nearest.max() <= CACHE_STEP / 2 + 1e-4


def _make(make_config, root, *overrides):
    return make_config(
        "dataset=topview",
        f"dataset.root={root}",
        "dataset.height=64",
        "dataset.width=96",
        *overrides,
    )


def test_only_rgb_fusion_is_allowed(folder, make_config) -> None:
    cfg = _make(make_config, folder)
    assert cfg.dataset.sensor == "none" and cfg.fusion.mode == "rgb"
    assert cfg.dataset.reader.condition == "day"
    validate_config(cfg)
    for fusion in ("concat", "add"):
        with pytest.raises(ValueError, match=f"fusion={fusion}: dataset=topview .*fusion=rgb"):
            validate_config(_make(make_config, folder, f"fusion={fusion}"))


def test_prepare_is_idempotent_and_never_writes_into_the_folder(folder, make_config) -> None:
    before = sorted((p, p.stat().st_mtime_ns) for p in folder.rglob("*"))
    cfg = _make(make_config, folder)
    assert prepare(cfg) == {"train": 4, "val": 2, "test": 1}
    cache = Path(cfg.paths.cache_dir) / "topview"
    files = sorted((p, p.stat().st_mtime_ns) for p in cache.rglob("*"))
    assert prepare(cfg) == {"train": 4, "val": 2, "test": 1}
    assert sorted((p, p.stat().st_mtime_ns) for p in cache.rglob("*")) == files
    assert sorted((p, p.stat().st_mtime_ns) for p in folder.rglob("*")) == before


def _copy(src: Path, dst: Path) -> Path:
    for path in src.rglob("*"):
        if path.is_file():
            target = dst / path.relative_to(src)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(path.read_bytes())
    return dst


def _break(root: Path, change: str) -> Path:
    if change == "root":
        return root / "nowhere"
    if change == "layout":
        (root / "val/depth").rename(root / "val/depths")
    elif change == "missing":
        (root / "train/depth/a02.png").unlink()
    elif change == "empty":
        for path in (root / "test/rgb").iterdir():
            path.unlink()
    elif change == "8bit":
        Image.fromarray(np.zeros((H, W), np.uint8)).save(root / "test/depth/c00.png")
    elif change == "size":
        np.save(root / "val/depth/b01.npy", np.ones((H, W + 1), np.float32))
    elif change == "corrupt":
        (root / "val/rgb/b00.png").write_bytes(b"not an image")
    elif change == "twice":
        np.save(root / "train/depth/a00.npy", np.ones((H, W), np.float32))
    elif change in ("image-dir", "depth-dir"):
        path = root / ("train/rgb/a02.png" if change == "image-dir" else "train/depth/a02.png")
        path.unlink()
        path.mkdir()
    elif change == "dangling":
        (root / "train/rgb/a02.png").unlink()
        (root / "train/rgb/a02.png").symlink_to(root / "nowhere.png")
    return root


@pytest.mark.parametrize(
    "change,error,match",
    [
        ("root", FileNotFoundError, "nowhere: no such folder.*\\{rgb,depth\\}"),
        ("layout", FileNotFoundError, "val/depth: missing folder.*found.*depths"),
        ("missing", FileNotFoundError, "train/depth/a02.png: missing depth map of .*a02.png"),
        ("empty", ValueError, "test/rgb: no images, the test split is empty"),
        ("8bit", ValueError, "c00.png: expected a single-channel 16-bit depth PNG"),
        ("size", ValueError, "b01.npy: depth map is 97x64, expected the image's 96x64"),
        ("corrupt", ValueError, "b00.png: unreadable image"),
        ("twice", ValueError, "a00.npy and a00.png|a00.png and a00.npy"),
        (
            "image-dir",
            IsADirectoryError,
            "train/rgb/a02.png: a directory, expected the camera image file of frame train/a02",
        ),
        (
            "depth-dir",
            IsADirectoryError,
            "train/depth/a02.png: a directory, expected the depth map file of .*train/rgb/a02.png",
        ),
        ("dangling", FileNotFoundError, "train/rgb/a02.png: not a readable file"),
    ],
)
def test_bad_input_fails_before_training_naming_the_path(
    folder, tmp_path, change, error, match
) -> None:
    root = _break(_copy(folder, tmp_path / "copy"), change)
    with pytest.raises(error, match=match):
        TopViewDepth("train", root, tmp_path / "cache", height=H, width=W)


def _break_two_frames(folder: Path, copy: Path) -> Path:
    """A copy whose train frame a02 has a directory for its image and whose val image b00 is
    not an image."""
    root = _break(_copy(folder, copy), "image-dir")
    (root / "val/rgb/b00.png").write_bytes(b"not an image")
    return root


def _cache_of(cfg, root: Path) -> Path:
    """The prepared cache folder of ``root`` (the session cache holds other tests' too)."""
    for cache in (Path(cfg.paths.cache_dir) / "topview").iterdir():
        if json.loads((cache / "meta.json").read_text())["root"] == str(root.resolve()):
            return cache
    raise AssertionError(f"no cache of {root}")


def test_prepare_skips_broken_frames_by_name_and_training_still_refuses_them(
    folder, tmp_path, make_config, caplog, monkeypatch
) -> None:
    root = _break_two_frames(folder, tmp_path / "copy")
    cfg = _make(make_config, root)
    with caplog.at_level(logging.INFO), pytest.raises(SkippedFramesError) as info:
        prepare(cfg)

    assert [report.line() for report in info.value.reports] == [
        "train: 3 of 4 frames prepared; skipped 1: train/a02",
        "val: 1 of 2 frames prepared; skipped 1: val/b00",
        "test: 1 of 1 frames prepared",
    ]
    image_dir = root / "train/rgb/a02.png"
    reasons = {s.frame_id: s.reason for r in info.value.reports for s in r.skipped}
    assert reasons["train/a02"].startswith(
        f"{image_dir}: a directory, expected the camera image file"
    )
    assert reasons["val/b00"].startswith(f"{root / 'val/rgb/b00.png'}: unreadable image")
    assert f"skipped train/a02: {image_dir}: a directory" in caplog.text
    assert f"skipped val/b00: {root / 'val/rgb/b00.png'}: unreadable image" in caplog.text
    # Every good frame is in the cache; only the complete split is marked prepared.
    cache = _cache_of(cfg, root)
    records = {s: sorted(p.name for p in (cache / s).glob("0*.json")) for s in SPLIT_FRAMES}
    assert records == {
        "train": ["000000.json", "000001.json", "000003.json"],
        "val": ["000001.json"],
        "test": ["000000.json"],
    }
    assert [(cache / s / "index.json").is_file() for s in SPLIT_FRAMES] == [False, False, True]

    # Preparing again reads only the two broken frames, and skips them again.
    calls = []
    real_load = topview.load_frame
    monkeypatch.setattr(
        topview, "load_frame", lambda frame, *a: calls.append(frame.id) or real_load(frame, *a)
    )
    with pytest.raises(SkippedFramesError):
        prepare(cfg)
    assert calls == ["train/a02", "val/b00"]

    # Training's reader still fails at the first broken frame, naming it: the directory before
    # anything is prepared, and once it is a file again, the corrupt image.
    with pytest.raises(IsADirectoryError, match="train/rgb/a02.png: a directory"):
        TopViewDepth("val", root, cfg.paths.cache_dir, height=H, width=W)
    image_dir.rmdir()
    image_dir.write_bytes((folder / "train/rgb/a02.png").read_bytes())
    with pytest.raises(ValueError, match="val/rgb/b00.png: unreadable image"):
        TopViewDepth("test", root, cfg.paths.cache_dir, height=H, width=W)


@pytest.mark.slow
def test_prepare_command_names_skipped_frames_and_exits_1(folder, tmp_path) -> None:
    root = _break_two_frames(folder, tmp_path / "copy")
    result = run_module(
        [
            "fusion_depth.prepare",
            "dataset=topview",
            f"dataset.root={root}",
            "dataset.height=64",
            "dataset.width=96",
            f"hydra.run.dir={tmp_path / 'run'}",
        ],
        cwd=REPO,
        timeout=300,
    )
    text = result.stdout + result.stderr
    assert result.returncode == 1, text
    assert f"skipped train/a02: {root / 'train/rgb/a02.png'}: a directory" in text
    assert f"skipped val/b00: {root / 'val/rgb/b00.png'}: unreadable image" in text
    for line in (
        "train: 3 of 4 frames prepared; skipped 1: train/a02",
        "val: 1 of 2 frames prepared; skipped 1: val/b00",
        "test: 1 of 1 frames prepared",
    ):
        assert line in result.stdout.splitlines(), text


def test_sweep_config_reproduces_the_papers_topview_table(tmp_path) -> None:
    GlobalHydra.instance().clear()
    with initialize_config_dir(str(REPO / "sweeps"), version_base="1.3"):
        cfg = compose(
            "topview_loss_grid",
            overrides=[f"hydra.searchpath=[file://{REPO / 'conf'}]", f"dataset.root={tmp_path}"],
            return_hydra_config=True,
        )
    GlobalHydra.instance().clear()
    assert cfg.dataset.name == "topview" and cfg.fusion.mode == "rgb"
    assert set(cfg.hydra.sweeper.params.loss.split(",")) == {"l1", "l2", "berhu"}
    assert "fusion" not in cfg.hydra.sweeper.params
    assert cfg.trainer.max_epochs == 30 and cfg.backbone.pretrained is True


@pytest.mark.slow
def test_training_and_testing_on_a_folder(folder, make_config) -> None:
    from fusion_depth.train.fit import train

    cfg = _make(
        make_config,
        folder,
        "backbone=resnet50",
        "backbone.pretrained=false",
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
    )
    results = train(cfg)
    saved = json.loads((Path(cfg.paths.output_dir) / "metrics.json").read_text())
    assert saved["test"] == results["test"] and results["test"]["num_images"] == 1
    assert results["run"]["dataset"] == "topview" and results["run"]["sensor"] == "none"
    assert set(results["test_by_condition"]) == {"day"}
    assert all(math.isfinite(v) for v in results["test"].values())


@pytest.mark.slow
def test_the_topview_sweep_runs_under_the_smoke_experiment(folder, tmp_path) -> None:
    sweep = tmp_path / "sweep"
    overrides = [f"dataset.root={folder}", "seed=42,43", "loss=l1"]
    result = run_sweep("topview_loss_grid", overrides, sweep)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "2 ok, 0 failed" in result.stdout
    report = run_module(["fusion_depth.report", str(sweep)], cwd=tmp_path, timeout=120)
    assert report.returncode == 0, report.stderr
    rows = [line for line in report.stdout.splitlines() if line.startswith("| RGB")]
    assert len(rows) == 1 and "±" in rows[0]  # mean ± std over the two seeds
