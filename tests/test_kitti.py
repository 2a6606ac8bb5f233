"""``dataset=kitti`` on fixtures in KITTI's published depth completion layout.

Frames are 40x100 (real ones ~375x1242): uint16 PNGs of metres x 256 with known values in
``data_depth_annotated``/``data_depth_velodyne`` and RGB PNGs in the raw drives' folders.
"""

from __future__ import annotations

import json
import logging
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import command_message, file_bytes, run_module, run_sweep
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate
from omegaconf.errors import MissingMandatoryValue
from PIL import Image

import fusion_depth.data.kitti as kitti
from fusion_depth.config import validate_config
from fusion_depth.data.cache import SkippedFramesError
from fusion_depth.data.kitti import KittiDepth, parse_split_file
from fusion_depth.errors import ConfigError
from fusion_depth.metrics.depth import crop_mask
from fusion_depth.prepare.cli import prepare
from fusion_depth.runner.datamodule import DepthDataModule, check_scorable
from fusion_depth.runner.protocol import EvalProtocol
from fusion_depth.train.fit import train

REPO = Path(__file__).resolve().parents[1]
H, W = 40, 100
DRIVES = {
    "train": ["2011_09_26_drive_0001_sync", "2011_09_28_drive_0002_sync"],
    "val": ["2011_09_26_drive_0002_sync"],
}
FRAMES = {"2011_09_28_drive_0002_sync": ["0000000005"]}  # the other drives: 5 and 6
CAMERAS = ("image_02", "image_03")


def _frames_of(drive: str) -> list[str]:
    return FRAMES.get(drive, ["0000000005", "0000000006"])


def _write_u16(path: Path, value: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(value.astype(np.uint16)).save(path)


def _frame_arrays(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame ``k``'s RGB image and its ground truth and Velodyne maps as stored (uint16)."""
    rows, cols = np.mgrid[0:H, 0:W]
    plane = np.round((5.0 + 0.1 * rows + 0.05 * cols + k) * 256).astype(np.uint16)
    gt = np.where(((rows + cols) % 3 == 0) & (rows >= 10), plane, 0).astype(np.uint16)
    velodyne = np.where(((rows + 2 * cols) % 7 == 0) & (rows >= 12), plane + 128, 0)
    image = np.stack([rows * 6, cols * 2, np.full_like(rows, 40 * k)], -1) % 256
    return image.astype(np.uint8), gt, velodyne.astype(np.uint16)


@pytest.fixture
def kitti_data(tmp_path) -> dict:
    """A depth completion root and a raw root; ``truth[frame id]`` = (image, gt, velodyne)."""
    root, raw = tmp_path / "kitti_depth", tmp_path / "kitti_raw"
    truth, k = {}, 0
    for subset, drives in DRIVES.items():
        for drive in drives:
            for camera in CAMERAS:
                for frame in _frames_of(drive):
                    image, gt, velo = _frame_arrays(k)
                    k += 1
                    proj = Path(subset, drive, "proj_depth")
                    name = Path(camera, f"{frame}.png")
                    _write_u16(root / "data_depth_annotated" / proj / "groundtruth" / name, gt)
                    _write_u16(root / "data_depth_velodyne" / proj / "velodyne_raw" / name, velo)
                    rgb = raw / drive[:10] / drive / camera / "data" / f"{frame}.png"
                    rgb.parent.mkdir(parents=True, exist_ok=True)
                    Image.fromarray(image).save(rgb)
                    truth[f"{subset}/{drive}/{camera}/{frame}"] = (image, gt, velo)
    return {"root": root, "raw_root": raw, "truth": truth, "cache": tmp_path / "cache"}


def _dataset(data: dict, split: str, **options) -> KittiDepth:
    options = {
        "root": data["root"],
        "raw_root": data["raw_root"],
        "cache_root": data["cache"],
        "height": 64,
        "width": 128,
        **options,
    }
    return KittiDepth(split, **options)


def _tree(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file below ``folder`` with its size and modification time."""
    return {
        str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _dataset_files(data: dict) -> list[dict]:
    """What a run must never change: the depth completion and raw data folders."""
    return [_tree(data["root"]), _tree(data["raw_root"])]


def _ids(dataset: KittiDepth) -> list[str]:
    return [frame["id"] for frame in dataset.frames]


# --- reading, crop/pad, subsampling, filling -----------------------------------------------


def test_decoded_depths_match_the_encoded_ones_and_padding_is_invalid(kitti_data) -> None:
    before = _dataset_files(kitti_data)
    val = _dataset(kitti_data, "val")  # 64x128: 24 rows and 28 columns of padding
    assert len(val) == 4 and val.conditions == ["day"] * 4
    for i, frame_id in enumerate(_ids(val)):
        image, gt, velodyne = kitti_data["truth"][frame_id]
        sample = val[i]
        assert sample["condition"] == "day"
        assert sample["depth"].shape == sample["sparse"].shape == (1, 64, 128)
        np.testing.assert_array_equal(sample["depth"][0, :H, :W].numpy(), gt / 256.0)
        np.testing.assert_array_equal(sample["sparse"][0, :H, :W].numpy(), velodyne / 256.0)
        for name in ("depth", "sparse"):
            assert not sample[name][0, H:].any() and not sample[name][0, :, W:].any()
        rgb = np.round(sample["image"].numpy().transpose(1, 2, 0) * 255).astype(np.uint8)
        np.testing.assert_array_equal(rgb[:H, :W], image)
        np.testing.assert_array_equal(rgb[H:, :W], np.repeat(image[-1:], 64 - H, 0))  # edge
    assert _dataset_files(kitti_data) == before, "the dataset folders were written to"


def test_a_larger_frame_keeps_its_bottom_rows_and_horizontal_centre(kitti_data) -> None:
    val = _dataset(kitti_data, "val", height=32, width=96)
    _, gt, velodyne = kitti_data["truth"][_ids(val)[0]]
    np.testing.assert_array_equal(val[0]["depth"][0].numpy(), gt[8:40, 2:98] / 256.0)
    np.testing.assert_array_equal(val[0]["sparse"][0].numpy(), velodyne[8:40, 2:98] / 256.0)


def test_splits_are_kittis_train_and_val_and_test_is_val_prepared_once(kitti_data) -> None:
    train, val, test = (_dataset(kitti_data, s) for s in ("train", "val", "test"))
    assert _ids(train) == [f for f in kitti_data["truth"] if f.startswith("train/")]
    assert _ids(val) == _ids(test) == [f for f in kitti_data["truth"] if f.startswith("val/")]
    assert test.split_dir == val.split_dir
    assert sorted(p.name for p in train.cache.iterdir() if p.is_dir()) == ["train", "val"]
    assert train.cache.parent == kitti_data["cache"] / "kitti"


def test_sparse_points_keeps_exactly_n_velodyne_returns_the_same_each_time(kitti_data) -> None:
    n = 7
    first = _dataset(kitti_data, "train", sparse_points=n)
    again = _dataset(kitti_data, "train", sparse_points=n, cache_root=kitti_data["cache"] / "b")
    assert again.split_dir != first.split_dir
    masks = []
    for i, frame_id in enumerate(_ids(first)):
        sparse = first[i]["sparse"][0, :H, :W].numpy()
        source = kitti_data["truth"][frame_id][2] / 256.0
        assert (sparse > 0).sum() == n
        np.testing.assert_array_equal(sparse[sparse > 0], source[sparse > 0])
        np.testing.assert_array_equal(again[i]["sparse"][0].numpy(), first[i]["sparse"][0].numpy())
        masks.append(sparse > 0)
    assert any((m != masks[0]).any() for m in masks[1:]), "every frame kept the same pixels"
    everything = _dataset(kitti_data, "train", sparse_points=10**6)
    np.testing.assert_array_equal(
        everything[0]["sparse"][0, :H, :W].numpy(), kitti_data["truth"][_ids(first)[0]][2] / 256.0
    )


@pytest.mark.parametrize("method", ["linear", "colorization"])
def test_filled_ground_truth_trains_and_evaluation_scores_measured_points(
    kitti_data, method
) -> None:
    train = _dataset(kitti_data, "train", fill=method, height=32, width=96)
    val = _dataset(kitti_data, "val", fill=method, height=32, width=96)
    assert train.use_filled and not val.use_filled
    for i, frame_id in enumerate(_ids(train)):
        gt = kitti_data["truth"][frame_id][1][8:40, 2:98] / 256.0
        depth = train[i]["depth"][0].numpy()
        assert (depth > 0).all(), "holes left in the filled ground truth"
        np.testing.assert_array_equal(depth[gt > 0], gt[gt > 0])
        if method == "linear":  # the measured points lie on a plane: so does the fill
            k = list(kitti_data["truth"]).index(frame_id)
            rows, cols = np.mgrid[8:40, 2:98]
            plane = 5.0 + 0.1 * rows + 0.05 * cols + k
            np.testing.assert_allclose(depth[3:-1, 1:-1], plane[3:-1, 1:-1], atol=2 / 256)
    _, gt, _ = kitti_data["truth"][_ids(val)[0]]
    np.testing.assert_array_equal(val[0]["depth"][0].numpy(), gt[8:40, 2:98] / 256.0)


def test_eval_crop_is_taken_on_the_original_frame(kitti_data) -> None:
    """Samples keep every measured point and say where the 40x100 frame lies, so eval.crop=garg
    scores Garg's fractions of the full frame: rows 16..38 and columns 3..95 of it, whether the
    sample padded the frame or cut rows off."""
    val = _dataset(kitti_data, "val")
    _, gt, _ = kitti_data["truth"][_ids(val)[0]]
    sample = val[0]
    np.testing.assert_array_equal(sample["depth"][0, :H, :W].numpy(), gt / 256.0)
    assert sample["frame_box"].tolist() == [0, 0, H, W]  # padded to 64x128 at the bottom/right
    inside = np.zeros((64, 128), bool)
    inside[16:39, 3:96] = True
    mask = crop_mask((64, 128), "garg", sample["frame_box"][None])[0]
    np.testing.assert_array_equal(mask.numpy(), inside)
    # Cut to 32 rows (bottom kept, 8 cut at the top) and 96 columns (2 cut on each side).
    cut = _dataset(kitti_data, "val", height=32, width=96)[0]
    assert cut["frame_box"].tolist() == [-8, -2, H, W]
    mask = crop_mask((32, 96), "garg", cut["frame_box"][None])[0]
    assert mask.any(dim=1).nonzero().flatten().tolist() == list(range(16 - 8, 39 - 8))
    assert mask.any(dim=0).nonzero().flatten().tolist() == list(range(3 - 2, 96 - 2))


# --- split files --------------------------------------------------------------------------------


def test_a_split_file_selects_the_test_frames_and_their_drives_leave_train(kitti_data) -> None:
    split_file = kitti_data["root"].parent / "eigen_test_files.txt"
    split_file.write_text(
        "# Eigen/monodepth2 style, then a relative path\n"
        "2011_09_26/2011_09_26_drive_0002_sync 5 l\n"
        "\n"
        "2011_09_26/2011_09_26_drive_0002_sync 0000000006 r\n"
        "2011_09_26/2011_09_26_drive_0002_sync 5 l\n"  # a duplicate counts once
        "2011_09_28_drive_0002_sync/proj_depth/groundtruth/image_03/0000000005.png\n"
    )
    test = _dataset(kitti_data, "test", split_file=split_file)
    assert _ids(test) == [
        "val/2011_09_26_drive_0002_sync/image_02/0000000005",
        "val/2011_09_26_drive_0002_sync/image_03/0000000006",
        "train/2011_09_28_drive_0002_sync/image_03/0000000005",
    ]
    _, gt, _ = kitti_data["truth"][_ids(test)[2]]
    np.testing.assert_array_equal(test[2]["depth"][0, :H, :W].numpy(), gt / 256.0)
    train = _dataset(kitti_data, "train", split_file=split_file)
    assert {f.split("/")[1] for f in _ids(train)} == {"2011_09_26_drive_0001_sync"}
    assert len(_dataset(kitti_data, "val", split_file=split_file)) == 4
    kept = _dataset(kitti_data, "train", split_file=split_file, exclude_test_drives=False)
    assert len(kept) == 6


def _write_selection(root: Path) -> dict[str, tuple]:
    """The depth-completion benchmark's val_selection_cropped layout, as KITTI's
    data_depth_selection.zip unpacks it, with two frames; returns id → (image, gt, velodyne)."""
    folder = root / "depth_selection" / "val_selection_cropped"
    truth = {}
    for k, (camera, frame) in enumerate((("image_02", "0000000005"), ("image_03", "0000000177"))):
        image, gt, velo = _frame_arrays(20 + k)
        drive = "2011_09_26_drive_0002_sync"
        _write_u16(
            folder / "groundtruth_depth" / f"{drive}_groundtruth_depth_{frame}_{camera}.png", gt
        )
        _write_u16(folder / "velodyne_raw" / f"{drive}_velodyne_raw_{frame}_{camera}.png", velo)
        (folder / "image").mkdir(parents=True, exist_ok=True)
        Image.fromarray(image).save(folder / "image" / f"{drive}_image_{frame}_{camera}.png")
        truth[f"val_selection_cropped/{drive}/{camera}/{frame}"] = (image, gt, velo)
    return truth


def test_the_selected_validation_set_is_the_test_split(kitti_data) -> None:
    """dataset.test_split=val_selection_cropped tests on the benchmark's selected frames, read
    from depth_selection/ (images included, no raw drive needed); train and val stay KITTI's."""
    truth = _write_selection(kitti_data["root"])
    before = _dataset_files(kitti_data)
    test = _dataset(kitti_data, "test", test_split="val_selection_cropped")
    assert _ids(test) == list(truth)
    for i, frame_id in enumerate(_ids(test)):
        image, gt, velodyne = truth[frame_id]
        sample = test[i]
        np.testing.assert_array_equal(sample["depth"][0, :H, :W].numpy(), gt / 256.0)
        np.testing.assert_array_equal(sample["sparse"][0, :H, :W].numpy(), velodyne / 256.0)
        rgb = np.round(sample["image"].numpy().transpose(1, 2, 0) * 255).astype(np.uint8)
        np.testing.assert_array_equal(rgb[:H, :W], image)
        assert sample["frame_box"].tolist() == [0, 0, H, W]  # the cropped frame itself
    val = _dataset(kitti_data, "val", test_split="val_selection_cropped")
    assert _ids(val) == [f for f in kitti_data["truth"] if f.startswith("val/")]
    assert test.split_dir != val.split_dir
    assert _dataset_files(kitti_data) == before, "the dataset folders were written to"
    # The plain test split is still KITTI's val, in a cache of its own.
    assert _ids(_dataset(kitti_data, "test")) == _ids(val)


def test_the_selected_set_is_refused_by_name_when_missing_or_doubly_given(kitti_data) -> None:
    with pytest.raises(FileNotFoundError, match=r"depth_selection/val_selection_cropped/"):
        _dataset(kitti_data, "test", test_split="val_selection_cropped")
    with pytest.raises(ValueError) as err:
        _dataset(kitti_data, "test", test_split="val_selected")
    assert "dataset.test_split='val_selected'" in command_message(err.value, "dataset=kitti")
    with pytest.raises(ValueError, match=r"both name the test frames"):
        _dataset(kitti_data, "test", test_split="val_selection_cropped", split_file="x.txt")
    truth = _write_selection(kitti_data["root"])
    stray = kitti_data["root"] / "depth_selection" / "val_selection_cropped" / "groundtruth_depth"
    (stray / "notes.png").write_bytes(b"")
    with pytest.raises(ValueError, match=r"notes.png: not a selected-frame name"):
        _dataset(kitti_data, "test", test_split="val_selection_cropped")
    assert truth


def test_train_stride_keeps_every_nth_frame_of_each_drive_and_camera(kitti_data) -> None:
    train = _dataset(kitti_data, "train", train_stride=2)
    assert [f.split("/", 1)[1] for f in _ids(train)] == [
        f"{drive}/{camera}/0000000005" for drive in DRIVES["train"] for camera in CAMERAS
    ]
    assert len(_dataset(kitti_data, "val", train_stride=2)) == 4  # evaluation keeps every frame


def test_split_file_line_formats(tmp_path) -> None:
    path = tmp_path / "files.txt"
    path.write_text(
        "2011_09_26/2011_09_26_drive_0002_sync 0000000069 r\n"
        "2011_09_26/2011_09_26_drive_0002_sync/image_02/data/0000000070.png "
        "2011_09_26/2011_09_26_drive_0002_sync/image_03/data/0000000070.png\n"
        "val\\2011_09_26_drive_0005_sync\\proj_depth\\velodyne_raw\\image_02\\0000000071.png\n"
    )
    assert parse_split_file(path) == [
        ("2011_09_26_drive_0002_sync", "image_03", "0000000069"),
        ("2011_09_26_drive_0002_sync", "image_02", "0000000070"),
        ("2011_09_26_drive_0005_sync", "image_02", "0000000071"),
    ]


# --- bad input --------------------------------------------------------------------------------


def _break(data: dict, how: str) -> tuple[dict, type, str]:
    """Damages the fixture one way; returns the KittiDepth options, error type and message."""
    root, raw = data["root"], data["raw_root"]
    frame = "2011_09_26_drive_0001_sync/proj_depth/{}/image_02/0000000005.png"
    gt = root / "data_depth_annotated" / "train" / frame.format("groundtruth")
    velodyne = root / "data_depth_velodyne" / "train" / frame.format("velodyne_raw")
    image = raw / "2011_09_26/2011_09_26_drive_0001_sync/image_02/data/0000000005.png"
    split_file = root.parent / "split.txt"
    if how == "missing root":
        return {"root": root.parent / "nowhere"}, FileNotFoundError, r"dataset.root=.*nowhere"
    if how == "annotated folder as root":
        return {"root": root / "data_depth_annotated"}, ValueError, "pass its parent"
    if how == "missing velodyne folder":
        (root / "data_depth_velodyne").rename(root.parent / "moved")
        return {}, FileNotFoundError, r"data_depth_velodyne: missing; expected .*velodyne_raw"
    if how == "missing raw root":
        return {"raw_root": raw.parent / "no_raw"}, FileNotFoundError, r"raw_root=.*no_raw"
    if how == "missing image":
        image.unlink()
        return {}, FileNotFoundError, rf"1 of 6 frames have no RGB image.*\n  {image}"
    if how == "missing velodyne frame":
        velodyne.unlink()
        return {}, FileNotFoundError, rf"no velodyne_raw depth PNG.*\n  {velodyne}"
    if how == "corrupt ground truth":
        gt.write_bytes(b"\x89PNG\r\n\x1a\n not really")
        return {}, ValueError, rf"{gt}: unreadable depth PNG"
    if how == "8-bit ground truth":
        Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(gt)
        return {}, ValueError, rf"{gt}: expected a single-channel 16-bit depth PNG"
    if how == "ground truth is a directory":
        gt.unlink()
        gt.mkdir()
        return (
            {},
            FileNotFoundError,
            rf"1 of 6 frames have no annotated depth PNG.*\n  {gt} \(a dir",
        )
    if how == "wrong size":
        _write_u16(velodyne, np.zeros((H, W - 1)))
        return {}, ValueError, rf"{velodyne}: 40x99 depth map, expected the size of its image"
    if how == "no drives":
        for drive in (root / "data_depth_annotated" / "val").iterdir():
            drive.rename(root.parent / drive.name)
        return {}, ValueError, r"data_depth_annotated/val: no drive folders like"
    if how == "drive without frames":
        for png in (root / "data_depth_annotated" / "val").rglob("*.png"):
            png.unlink()
        return {}, ValueError, r"val: no annotated depth PNGs"
    if how == "unlisted frame":
        split_file.write_text("2011_09_26/2011_09_26_drive_0002_sync 7 l\n")
        expected = r"(?s)1 of 1 listed frames have no annotated depth.*0000000007.png.*652"
        return {"split_file": split_file}, FileNotFoundError, expected
    if how == "bad split line":
        split_file.write_text("# header\n2011_09_26_drive_0002_sync five l\n")
        return {"split_file": split_file}, ValueError, r"split.txt, line 2: .*expected"
    if how == "empty split file":
        split_file.write_text("# nothing\n\n")
        return {"split_file": split_file}, ValueError, "lists no frames"
    if how == "every train drive tested":
        split_file.write_text(
            "2011_09_26/2011_09_26_drive_0001_sync 5 l\n2011_09_28/2011_09_28_drive_0002_sync 5 l\n"
        )
        return {"split_file": split_file}, ValueError, "nothing is left to train on"
    if how == "cache inside the dataset":
        return {"cache_root": root / "cache"}, ValueError, r"inside dataset.root=.*only ever read"
    raise AssertionError(how)


BAD_INPUTS = [
    "missing root",
    "annotated folder as root",
    "missing velodyne folder",
    "missing raw root",
    "missing image",
    "missing velodyne frame",
    "corrupt ground truth",
    "8-bit ground truth",
    "ground truth is a directory",
    "wrong size",
    "no drives",
    "drive without frames",
    "unlisted frame",
    "bad split line",
    "empty split file",
    "every train drive tested",
    "cache inside the dataset",
]


@pytest.mark.parametrize("how", BAD_INPUTS)
def test_bad_input_fails_before_training_naming_the_path(kitti_data, how) -> None:
    options, error, message = _break(kitti_data, how)
    before = _dataset_files(kitti_data)
    with pytest.raises(error) as err:
        _dataset(kitti_data, "val", **options)
    assert re.search(message, command_message(err.value, "dataset=kitti")), str(err.value)
    assert _dataset_files(kitti_data) == before, "the dataset folders were written to"
    assert not list(kitti_data["cache"].rglob("index.json")), "a split was marked prepared"


@pytest.mark.parametrize(
    ("option", "message"),
    [
        ({"fill": "cubic"}, r"dataset.fill='cubic': expected one of \['none', 'linear'"),
        ({"sparse_points": 0}, "dataset.sparse_points=0: expected null"),
        ({"height": 40}, "dataset.height=40: expected a positive multiple of 32"),
        ({"train_stride": 0}, "dataset.train_stride=0: expected an integer >= 1"),
    ],
)
def test_bad_options_are_named(kitti_data, option, message) -> None:
    with pytest.raises(ValueError) as err:  # the reader names its argument, a command the key
        _dataset(kitti_data, "train", **option)
    assert re.search(message, command_message(err.value, "dataset=kitti")), str(err.value)


def test_the_config_needs_both_roots_before_touching_data(make_config, kitti_data) -> None:
    with pytest.raises(MissingMandatoryValue, match="dataset.root"):
        validate_config(make_config("dataset=kitti"))
    with pytest.raises(MissingMandatoryValue, match="dataset.raw_root"):
        validate_config(make_config("dataset=kitti", f"dataset.root={kitti_data['root']}"))


# --- prepare --------------------------------------------------------------------------------


class Interrupted(Exception):
    pass


def test_prepare_is_idempotent_and_resumes_after_an_interruption(
    make_config, kitti_data, monkeypatch
) -> None:
    overrides = [
        "dataset=kitti",
        f"dataset.root={kitti_data['root']}",
        f"dataset.raw_root={kitti_data['raw_root']}",
        "dataset.height=32",
        "dataset.width=96",
        "dataset.fill=linear",
    ]
    real_load = kitti.load_frame
    calls = []

    def counting_load(*args, **kwargs):
        calls.append(args[0].id)
        if len(calls) == 4 and interrupt:
            raise Interrupted
        return real_load(*args, **kwargs)

    monkeypatch.setattr(kitti, "load_frame", counting_load)
    interrupt = False
    monkeypatch.setenv("FUSION_DEPTH_CACHE", str(kitti_data["cache"] / "whole"))
    assert prepare(make_config(*overrides)) == {"train": 6, "val": 4, "test": 4}
    assert len(calls) == 10
    whole = next((kitti_data["cache"] / "whole" / "kitti").iterdir())
    snapshot = _tree(whole)
    assert prepare(make_config(*overrides)) == {"train": 6, "val": 4, "test": 4}
    assert len(calls) == 10 and _tree(whole) == snapshot, "a second prepare wrote something"

    calls.clear()
    interrupt = True
    monkeypatch.setenv("FUSION_DEPTH_CACHE", str(kitti_data["cache"] / "resumed"))
    with pytest.raises(Interrupted):
        prepare(make_config(*overrides))
    resumed = next((kitti_data["cache"] / "resumed" / "kitti").iterdir())
    assert len(list((resumed / "train").glob("*.json"))) == 3  # three frames done, no index
    assert not (resumed / "train" / "index.json").exists()
    assert not [p for p in resumed.rglob("*") if p.name.endswith(".tmp")]
    done = _tree(resumed)
    calls.clear()
    interrupt = False
    assert prepare(make_config(*overrides)) == {"train": 6, "val": 4, "test": 4}
    assert len(calls) == 7, "frames prepared before the interruption were prepared again"
    after = _tree(resumed)
    assert all(after[name] == stat for name, stat in done.items() if name != "meta.json")
    for name in snapshot:  # the same files with the same contents as an uninterrupted run
        assert (resumed / name).read_bytes() == (whole / name).read_bytes(), name
    assert set(after) == set(snapshot)


def test_prepare_skips_broken_frames_by_name_and_training_still_refuses_them(
    make_config, kitti_data, monkeypatch, caplog
) -> None:
    root, raw = kitti_data["root"], kitti_data["raw_root"]
    velodyne = (
        root / "data_depth_velodyne/train/2011_09_26_drive_0001_sync/proj_depth/velodyne_raw"
        "/image_02/0000000005.png"
    )
    velodyne.unlink()
    gt = (
        root / "data_depth_annotated/val/2011_09_26_drive_0002_sync/proj_depth/groundtruth"
        "/image_03/0000000006.png"
    )
    gt.unlink()
    gt.mkdir()
    monkeypatch.setenv("FUSION_DEPTH_CACHE", str(kitti_data["cache"]))
    cfg = make_config(
        "dataset=kitti",
        f"dataset.root={root}",
        f"dataset.raw_root={raw}",
        "dataset.height=32",
        "dataset.width=96",
    )
    with caplog.at_level(logging.WARNING), pytest.raises(SkippedFramesError) as info:
        prepare(cfg)

    bad_train = "train/2011_09_26_drive_0001_sync/image_02/0000000005"
    bad_val = "val/2011_09_26_drive_0002_sync/image_03/0000000006"
    # test is val's folder: one report for both.
    assert [report.line() for report in info.value.reports] == [
        f"train: 5 of 6 frames prepared; skipped 1: {bad_train}",
        f"val: 3 of 4 frames prepared; skipped 1: {bad_val}",
    ]
    assert f"skipped {bad_train}: {velodyne}: missing depth PNG" in caplog.text
    assert (
        f"skipped {bad_val}: {gt}: a directory, expected the groundtruth PNG file of frame "
        f"{bad_val}" in caplog.text
    )
    (cache,) = (kitti_data["cache"] / "kitti").iterdir()
    assert len(list(cache.glob("*/0*.json"))) == 8 and not list(cache.glob("*/index.json"))
    # Training's reader checks every frame's files first and names the first broken ones.
    with pytest.raises(FileNotFoundError, match=rf"train split: 1 of 6 .*velodyne.*\n  {velodyne}"):
        _dataset(kitti_data, "train")


def assert_same_caches(first: Path, second: Path) -> None:
    """The KITTI caches below two ``$FUSION_DEPTH_CACHE`` folders hold the same files, byte for
    byte (hidden ones too)."""
    first, second = (next((root / "kitti").iterdir()) for root in (first, second))
    assert file_bytes(first) == file_bytes(second)


def test_prepare_in_shards_with_workers_gives_the_serial_cache(
    kitti_data, tmp_path, monkeypatch
) -> None:
    from helpers import compose_config

    from fusion_depth.data.cache import IncompleteSplitError

    def config(cache: str, *extra: str):
        monkeypatch.setenv("FUSION_DEPTH_CACHE", str(kitti_data["cache"] / cache))
        overrides = [
            "dataset=kitti",
            f"dataset.root={kitti_data['root']}",
            f"dataset.raw_root={kitti_data['raw_root']}",
            "dataset.height=32",
            "dataset.width=96",
            "dataset.fill=colorization",
            *extra,
        ]
        return compose_config(overrides, tmp_path / "run", config_name="prepare")

    assert prepare(config("serial", "prepare.workers=1")) == {"train": 6, "val": 4, "test": 4}
    with pytest.raises(IncompleteSplitError) as info:
        prepare(config("sharded", "prepare.workers=2", "prepare.num_shards=3", "prepare.shard=1"))
    assert [(s.split_dir.name, s.done, s.total) for s in info.value.splits] == [
        ("train", 2, 6),
        ("val", 1, 4),
    ]
    # Training does not prepare what the other shards own: it names what is missing.
    with pytest.raises(IncompleteSplitError, match="2 of 6 frames prepared, 4 missing"):
        sharded_data = kitti_data | {"cache": kitti_data["cache"] / "sharded"}
        _dataset(sharded_data, "train", height=32, width=96, fill="colorization")
    for shard in (0, 2):
        try:
            prepare(
                config(
                    "sharded",
                    "prepare.workers=2",
                    "prepare.num_shards=3",
                    f"prepare.shard={shard}",
                )
            )
        except IncompleteSplitError:
            assert shard == 0
    assert_same_caches(kitti_data["cache"] / "serial", kitti_data["cache"] / "sharded")


@pytest.mark.slow
def test_two_shards_as_a_joblib_multirun_give_the_serial_cache_and_training_reads_it(
    kitti_data, tmp_path, monkeypatch
) -> None:
    """The documented multirun of shards, on the joblib launcher: exit 0 (training's sweep
    summary, which wants a metrics.json per job, is not prepare's), the serial cache file for
    file, and a split training reads."""
    from helpers import compose_config

    size = [
        "dataset=kitti",
        f"dataset.root={kitti_data['root']}",
        f"dataset.raw_root={kitti_data['raw_root']}",
        "dataset.height=32",
        "dataset.width=96",
    ]
    monkeypatch.setenv("FUSION_DEPTH_CACHE", str(kitti_data["cache"] / "serial"))
    prepare(compose_config([*size, "prepare.workers=1"], tmp_path / "run", config_name="prepare"))
    env = {**os.environ, "FUSION_DEPTH_CACHE": str(kitti_data["cache"] / "sharded")}
    shards = ["prepare.workers=1", "prepare.num_shards=2", "prepare.shard=range(2)"]
    sweep_dir = f"hydra.sweep.dir={tmp_path / 'sweep'}"
    command = ["fusion_depth.prepare", "-m", *size, *shards, "hydra/launcher=parallel", sweep_dir]
    done = run_module(command, cwd=tmp_path, env=env, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "failed" not in done.stdout + done.stderr
    assert_same_caches(kitti_data["cache"] / "serial", kitti_data["cache"] / "sharded")
    sharded_data = kitti_data | {"cache": kitti_data["cache"] / "sharded"}
    train_split = _dataset(sharded_data, "train", height=32, width=96)
    assert len(train_split) == 6 and train_split[5]["image"].shape == (3, 32, 96)


# Run in a fresh interpreter: prepare's own command line, then which heavy packages it imported.
_PREPARE_AND_LIST_IMPORTS = """
import runpy, sys
sys.argv = ["fusion_depth.prepare", *sys.argv[1:]]
try:
    runpy.run_module("fusion_depth.prepare", run_name="__main__")
finally:
    print("imported:", sorted(m for m in ("lightning", "timm", "torch") if m in sys.modules))
"""


@pytest.mark.slow
def test_prepare_runs_without_torch_and_checks_its_keys(kitti_data, tmp_path) -> None:
    """prepare checks only ``dataset`` and ``prepare``, so it imports neither timm (the models)
    nor Lightning (the trainer), and a prepared split imports torch only when read: seconds of
    start-up that no number of workers shortens. Its own keys are still checked, a ``+key`` as
    well."""
    env = {**os.environ, "FUSION_DEPTH_CACHE": str(kitti_data["cache"])}
    base = [
        "dataset=kitti",
        f"dataset.root={kitti_data['root']}",
        f"dataset.raw_root={kitti_data['raw_root']}",
        "dataset.height=32",
        "dataset.width=96",
        "prepare.workers=2",
        f"hydra.run.dir={tmp_path / 'run'}",
    ]

    def run(*extra: str) -> subprocess.CompletedProcess:
        command = [sys.executable, "-c", _PREPARE_AND_LIST_IMPORTS, *base, *extra]
        return subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)

    done = run()
    assert done.returncode == 0, done.stderr
    assert "imported: []" in done.stdout
    assert len(list((kitti_data["cache"] / "kitti").glob("*/*/index.json"))) == 2  # train, val
    for extra, message in [
        ("+dataset.reader.fill_iters=3", "dataset.reader.fill_iters: unknown key"),
        ("+prepare.worker=3", "prepare.worker: unknown key (nothing reads it"),
        ("dataset.fill=colorisation", "dataset.fill='colorisation': expected one of"),
    ]:
        refused = run(extra)
        assert refused.returncode == 1 and message in refused.stderr, (extra, refused.stderr)


# --- configs end to end --------------------------------------------------------------------------


@pytest.mark.slow
def test_training_and_testing_through_the_real_configs(make_config, kitti_data) -> None:
    from fusion_depth.train.fit import train

    cfg = make_config(
        "dataset=kitti",
        f"dataset.root={kitti_data['root']}",
        f"dataset.raw_root={kitti_data['raw_root']}",
        "dataset.height=32",
        "dataset.width=96",
        "dataset.sparse_points=50",
        "backbone=resnet50",
        "backbone.pretrained=false",
        "fusion=concat",
        "logger=none",
        "trainer.max_epochs=1",
        "trainer.limit_train_batches=2",
        "trainer.limit_val_batches=1",
        "trainer.num_sanity_val_steps=0",
        "trainer.enable_model_summary=false",
        "callbacks.model_checkpoint.save_last=false",
        "+callbacks.model_checkpoint.save_weights_only=true",
        "data.eval_batch_size=2",
        "model.num_val_panels=1",
    )
    results = train(cfg)
    saved = json.loads((Path(cfg.paths.output_dir) / "metrics.json").read_text())
    assert saved["test"] == results["test"]
    assert saved["run"]["dataset"] == "kitti" and saved["run"]["sensor"] == "lidar"
    assert saved["test"]["num_images"] == 4  # test = KITTI's val here
    assert set(saved["test_by_condition"]) <= {"day"}
    assert np.isfinite(saved["test"]["rmse"]) and saved["global_step"] == 2


def test_the_sweep_config_reproduces_the_papers_kitti_table(tmp_path) -> None:
    GlobalHydra.instance().clear()
    with initialize_config_dir(str(REPO / "sweeps"), version_base="1.3"):
        cfg = compose(
            "kitti_fusion",
            overrides=[
                f"hydra.searchpath=[file://{REPO / 'conf'}]",
                f"dataset.root={tmp_path}",
                f"dataset.raw_root={tmp_path}",
            ],
            return_hydra_config=True,
        )
    GlobalHydra.instance().clear()
    assert cfg.dataset.name == "kitti" and cfg.dataset.sensor == "lidar"
    assert (cfg.dataset.height, cfg.dataset.width) == (384, 1248)
    assert cfg.dataset.fill == "colorization" and cfg.eval.crop == "garg"
    assert cfg.hydra.sweeper.params.seed == "42,43,44"
    assert cfg.dataset.reader.train_stride == 10
    assert set(cfg.hydra.sweeper.params.fusion.split(",")) == {"rgb", "concat", "add"}
    assert cfg.loss.pixel == "l1" and cfg.trainer.max_epochs == 20
    assert cfg.backbone.pretrained is True and cfg.dataset.max_depth == 80.0


@pytest.mark.slow
def test_the_kitti_sweep_runs_under_smoke_and_scores_inside_the_garg_crop(
    kitti_data, tmp_path
) -> None:
    sweep = tmp_path / "sweep"
    result = run_sweep(
        "kitti_fusion",
        [
            f"dataset.root={kitti_data['root']}",
            f"dataset.raw_root={kitti_data['raw_root']}",
            "dataset.train_stride=1",
            "seed=42",
            "fusion=concat",  # one job of the grid: the config and the crop are what is tested
            "trainer.limit_test_batches=null",
        ],
        sweep,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "1 ok, 0 failed" in result.stdout
    (saved,) = [json.loads(p.read_text()) for p in sweep.glob("*/metrics.json")]
    assert saved["run"]["fusion"] == "concat" and saved["protocol"]["crop"] == "garg"
    # The scored pixels are exactly the measured ones inside Garg's crop of each full frame.
    test = KittiDepth(
        "test",
        kitti_data["root"],
        kitti_data["raw_root"],
        os.environ["FUSION_DEPTH_CACHE"],
        height=64,
        width=96,
        fill="colorization",
        train_stride=1,
    )
    expected = 0
    for i in range(len(test)):
        sample = test[i]
        depth = sample["depth"][0]
        inside = crop_mask(tuple(depth.shape), "garg", sample["frame_box"][None])[0]
        expected += int(((depth > 1.0) & (depth < 80.0) & inside).sum())
    assert saved["test"]["num_pixels"] == expected
    assert saved["test"]["num_images"] == len(test)


def test_a_val_split_whose_lidar_lies_outside_the_crop_is_refused_before_training(
    make_config, kitti_data, monkeypatch
) -> None:
    """The issue's case: at a small dataset.height the bottom-centre crop of each frame drops
    the rows where the val frames' ground truth lies (here rows 0-7 of 40), so the first
    validation would score nothing. Training refuses it up front, naming split, frames, size."""
    for gt in (kitti_data["root"] / "data_depth_annotated" / "val").rglob("*.png"):
        stored = np.zeros_like(np.array(Image.open(gt)))
        stored[:8, ::3] = 10 * 256  # 10 m lidar returns in the top 8 rows only
        _write_u16(gt, stored)
    monkeypatch.setenv("FUSION_DEPTH_CACHE", str(kitti_data["cache"]))
    overrides = [
        "dataset=kitti",
        f"dataset.root={kitti_data['root']}",
        f"dataset.raw_root={kitti_data['raw_root']}",
        "dataset.width=96",
        "backbone.pretrained=false",
        "experiment=smoke",
        "logger=none",
    ]
    cfg = make_config(*overrides, "dataset.height=32")
    with pytest.raises(ConfigError) as err:
        train(cfg)
    message = str(err.value)
    assert message.startswith(
        "dataset=kitti: the val split cannot be scored: none of the 2 frames its val stage reads"
    )
    assert "32×96 sample" in message and "Raise dataset.height" in message
    assert not list(Path(cfg.paths.output_dir).rglob("*.ckpt"))
    # At a height that keeps those rows (the 40-row frames are padded to 64) they are scored.
    cfg = make_config(*overrides, "dataset.height=64")
    datamodule = DepthDataModule(reader=instantiate(cfg.dataset.reader), batch_size=2)
    protocol = EvalProtocol.from_config(cfg.eval, cfg.dataset.min_depth, cfg.dataset.max_depth)
    check_scorable(datamodule, protocol, cfg.trainer, "kitti")
