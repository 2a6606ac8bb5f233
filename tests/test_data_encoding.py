"""Samples cross the DataLoader as uint8 images and uint16 depth maps (1/256 m) and become floats
on the device (issue 17): the floats are the ones the readers served before, bit for bit; the
prepared caches store ``.npy`` arrays (version 3) that refuse depths they cannot hold, name a
damaged file, and replace older (PNG) caches by preparing again."""

from __future__ import annotations

import functools
import json
import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader, Dataset

import fusion_depth.data.cache as prepared
from fusion_depth.data import RADAR_POINT_FIELDS
from fusion_depth.data.base import FrameList, PreparedDataset
from fusion_depth.data.cache import PreparedFrame, PreparedSplit, SkippedFramesError, prepare_split
from fusion_depth.data.depth_io import (
    MAX_ENCODED_DEPTH,
    DataFileError,
    read_depth_png,
    read_npy,
    read_rgb,
    write_depth_png,
    write_npy,
    write_rgb_png,
)
from fusion_depth.data.encoding import decode_sample
from fusion_depth.data.procedural import DEPTH_SCALE, ProceduralDepth
from fusion_depth.data.radar_points import point_rows
from fusion_depth.models import DepthNet
from fusion_depth.runner.datamodule import DepthDataModule, IndexedDataset
from fusion_depth.runner.module import DepthModule

H, W = 32, 64


def _frame(frame_id: str) -> PreparedFrame:
    """Random maps over the whole range the cache holds: 0 (none), the 3.9 mm step, 255.99 m,
    and values between steps (stored rounded)."""
    rng = np.random.default_rng(sum(map(ord, frame_id)))
    sparse = np.where(rng.random((H, W)) < 0.1, rng.uniform(0.5, 120.0, (H, W)), 0.0)
    depth = rng.uniform(0.0, MAX_ENCODED_DEPTH, (H, W))
    depth[0, :3] = (0.0, 1 / 256, MAX_ENCODED_DEPTH)
    depth[1, :3] = (np.nan, -1.0, np.inf)  # stored as 0 (no value), as before
    return PreparedFrame(
        image=rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
        sparse=sparse,
        depth=depth,
        filled=np.where(depth > 0, depth, 7.25),
        condition="night",
        frame_box=(0, 0, H - 2, W - 4),
        radar_points=point_rows([1.5, 10.25], [2.5, 3.0], [4.0, 9.0]),
    )


def _old_float_sample(frame: PreparedFrame, folder: Path, use_filled: bool) -> dict:
    """What PreparedSplit served before version 3: the frame through the cache's PNG files,
    read back and converted to floats in the worker."""
    folder.mkdir(parents=True, exist_ok=True)
    write_rgb_png(folder / "image.png", frame.image)
    write_depth_png(folder / "sparse.png", frame.sparse)
    write_depth_png(folder / "depth.png", frame.filled if use_filled else frame.depth)
    image = read_rgb(folder / "image.png", verify=False)
    return {
        "image": torch.from_numpy(image.transpose(2, 0, 1).copy()).float().div_(255.0),
        "sparse": torch.from_numpy(read_depth_png(folder / "sparse.png", verify=False))[None],
        "depth": torch.from_numpy(read_depth_png(folder / "depth.png", verify=False))[None],
    }


def _assert_bits_equal(got: torch.Tensor, want: torch.Tensor) -> None:
    assert got.dtype == want.dtype == torch.float32 and got.shape == want.shape
    assert torch.equal(got.contiguous().view(torch.int32), want.contiguous().view(torch.int32))


class Frames(PreparedDataset):
    """A dataset of :func:`_frame` frames (no files of its own), through the real base class."""

    name = "frames"
    layout = "any folder"

    def __init__(self, split: str, root: Path, cache_root: Path, filled: bool = False) -> None:
        self.filled = filled
        super().__init__(split, root, cache_root, H, W)

    def list_frames(self) -> FrameList:
        ids = {split: {f"{split}/{i}": i for i in range(3)} for split in ("train", "val", "test")}
        return FrameList(ids, "fixed")

    def load_frame(self, split: str, frame: int) -> PreparedFrame:
        return _frame(f"{split}/{frame}")

    def serves_filled(self) -> bool:
        return self.filled


def _module() -> DepthModule:
    return DepthModule(DepthNet("resnet18", "concat", pretrained=False))


@pytest.mark.parametrize("filled", [False, True])
def test_prepared_frames_cross_the_loader_as_integers_and_decode_to_the_old_floats(
    tmp_path, filled
) -> None:
    (tmp_path / "data").mkdir()
    root, cache = tmp_path / "data", tmp_path / "cache"
    reader = functools.partial(Frames, root=root, cache_root=cache, filled=filled)
    datamodule = DepthDataModule(reader, batch_size=3, num_workers=1, pin_memory=False)
    batch = next(iter(datamodule.loader("train", shuffle=False, batch_size=3)))
    assert batch["image"].dtype == torch.uint8 and batch["image"].shape == (3, 3, H, W)
    assert batch["sparse"].dtype == batch["depth"].dtype == torch.uint16
    assert batch["radar_points"].dtype == torch.float32 and batch["frame_box"].shape == (3, 4)
    decoded = _module().on_after_batch_transfer(batch, 0)  # what every Lightning stage runs
    split = reader(split="train")
    for i in range(3):
        old = _old_float_sample(_frame(f"train/{i}"), tmp_path / "old" / str(i), filled)
        for key in ("image", "sparse", "depth"):
            _assert_bits_equal(decoded[key][i], old[key])
            _assert_bits_equal(split[i][key], old[key])  # dataset[i]: the same floats
    assert decoded["condition"] == ["night"] * 3 and torch.equal(decoded["index"], batch["index"])
    assert torch.equal(decoded["radar_points"], batch["radar_points"])


def test_the_built_in_dataset_decodes_to_the_floats_it_served_before(tmp_path) -> None:
    options = {"height": H, "width": W, "num_train": 4, "num_val": 2, "num_test": 2}
    reader = functools.partial(ProceduralDepth, root=tmp_path, **options)
    datamodule = DepthDataModule(reader, batch_size=4, num_workers=0, pin_memory=False)
    batch = next(iter(datamodule.loader("train", shuffle=False, batch_size=4)))
    assert (batch["image"].dtype, batch["depth"].dtype) == (torch.uint8, torch.uint16)
    decoded = _module().on_after_batch_transfer(batch, 0)
    split = reader(split="train")
    arrays = split._open()
    for i in range(4):  # the float path before issue 17, from the stored arrays
        image = torch.from_numpy(np.ascontiguousarray(arrays["image"][i].transpose(2, 0, 1)))
        old = {"image": image.float().div_(255.0)}
        for key in ("sparse", "depth"):
            value = torch.from_numpy(arrays[key][i].astype(np.float32))
            old[key] = value.div_(DEPTH_SCALE).unsqueeze(0)
        for key in ("image", "sparse", "depth"):
            _assert_bits_equal(decoded[key][i], old[key])
            _assert_bits_equal(split[i][key], old[key])
    assert batch["radar_points"].shape[-1] == len(RADAR_POINT_FIELDS)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_decoding_on_the_gpu_gives_the_cpu_floats_bit_for_bit() -> None:
    generator = torch.Generator().manual_seed(0)
    batch = {
        "image": torch.randint(0, 256, (2, 3, H, W), dtype=torch.uint8, generator=generator),
        "sparse": torch.randint(0, 65536, (2, 1, H, W), generator=generator).to(torch.uint16),
        "depth": torch.randint(0, 65536, (2, 1, H, W), generator=generator).to(torch.uint16),
    }
    on_cpu = decode_sample(batch)
    on_gpu = decode_sample({k: v.pin_memory().cuda(non_blocking=True) for k, v in batch.items()})
    for key in batch:
        _assert_bits_equal(on_gpu[key].cpu(), on_cpu[key])


def test_floats_pass_through_and_other_integer_dtypes_are_refused() -> None:
    floats = {"image": torch.rand(1, 3, 2, 2), "depth": torch.rand(1, 1, 2, 2), "index": 3}
    decoded = decode_sample(floats)
    assert all(decoded[k] is floats[k] for k in floats)
    with pytest.raises(ValueError, match=r"sample\['image'\] is torch.int16: expected torch.uint8"):
        decode_sample({"image": torch.zeros(1, 3, 2, 2, dtype=torch.int16)})
    with pytest.raises(ValueError, match=r"sample\['sparse'\] is torch.int32"):
        decode_sample({"image": torch.rand(3, 2, 2), "sparse": torch.zeros(1, 2, 2).int()})


class FloatReader(Dataset):
    """A custom reader of the float form only (no ``encoded_sample``)."""

    def __len__(self) -> int:
        return 2

    def __getitem__(self, index: int) -> dict:
        return {
            "image": torch.full((3, H, W), 0.5),
            "sparse": torch.zeros(1, H, W),
            "depth": torch.full((1, H, W), 3.0 + index),
            "condition": "day",
        }


def test_a_reader_of_floats_still_trains_unchanged() -> None:
    batch = next(iter(DataLoader(IndexedDataset(FloatReader()), batch_size=2)))
    decoded = _module().on_after_batch_transfer(batch, 0)
    assert decoded["depth"].dtype == torch.float32 and decoded["depth"][1].max() == 4.0
    assert torch.equal(decoded["image"], batch["image"])


# --- the cache: range, damage, version --------------------------------------------------------


@pytest.mark.parametrize("name", ["sparse", "depth", "filled"])
def test_a_depth_the_cache_cannot_hold_is_refused_naming_the_frame(tmp_path, name) -> None:
    def frames(frame_id: str) -> PreparedFrame:
        frame = _frame(frame_id)
        if frame_id == "b":
            getattr(frame, name)[5, 7] = 300.0
        return frame

    with pytest.raises(ValueError) as info:
        prepare_split(tmp_path / "raise", "val", ["a", "b"], frames, {})
    message = str(info.value)
    assert message.startswith(f"frame b: {name} holds depths up to 300 m, beyond the 255.996 m")
    assert "\n" not in message and len(message) < 200
    with pytest.raises(SkippedFramesError, match="frame b: "):  # the others are prepared
        prepare_split(tmp_path / "skip", "val", ["a", "b", "c"], frames, {}, on_error="skip")
    assert sorted(p.name for p in (tmp_path / "skip/val").glob("*.json")) == [
        "000000.json",
        "000002.json",
    ]


def test_the_deepest_depth_the_cache_holds_round_trips(tmp_path) -> None:
    def frame(frame_id: str) -> PreparedFrame:
        depth = np.full((H, W), MAX_ENCODED_DEPTH)
        depth[0, 0] = MAX_ENCODED_DEPTH + 0.5 / 256 - 1e-6  # still rounds to 65535
        return PreparedFrame(np.zeros((H, W, 3), np.uint8), depth, depth, "day")

    split = PreparedSplit(prepare_split(tmp_path, "val", ["a"], frame, {}))
    assert (split.encoded_sample(0)["depth"].numpy() == 65535).all()
    assert (split[0]["depth"] == 65535 / 256).all()


def _damage(path: Path, how: str) -> None:
    array = np.load(path)
    if how == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size - 7])
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "garbage":
        path.write_bytes(np.random.default_rng(0).bytes(300))
    elif how == "another dtype":
        np.save(path, array.astype(np.float32))
    elif how == "another size":
        np.save(path, array[:-1])
    elif how == "fortran order":
        np.save(path, np.asfortranarray(array))
    elif how == "pickled":
        np.save(path, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    elif how == "npz":
        with path.open("wb") as f:
            np.savez(f, array=array)
    elif how == "huge header":  # promises far more than the file holds: nothing is allocated
        header = "{'descr': '|u1', 'fortran_order': False, 'shape': (100000, 100000, 3), }"
        header += " " * (118 - len(header) - 1) + "\n"
        path.write_bytes(b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode())


DAMAGE = ["truncated", "empty", "garbage", "another dtype", "another size", "fortran order"]
DAMAGE += ["pickled", "npz", "huge header"]


@pytest.mark.parametrize("which", ["image", "sparse", "depth", "filled"])
@pytest.mark.parametrize("how", DAMAGE)
def test_a_damaged_cache_file_is_a_short_error_naming_it(tmp_path, which, how) -> None:
    folder = prepare_split(tmp_path, "val", ["a"], _frame, {})
    path = folder / f"000000.{which}.npy"
    _damage(path, how)
    split = PreparedSplit(folder, use_filled=which == "filled")
    if (which, how) == ("image", "another size"):  # told by the maps, which name the image
        path = folder / "000000.sparse.npy"
    for read in (lambda: split[0], lambda: split.encoded_sample(0)):
        with pytest.raises(DataFileError) as info:
            read()
        text = str(info.value)
        assert text.startswith(f"{path}: ") and info.value.path == path, text
        if path.name != f"000000.{which}.npy":
            assert f"the size of {folder}/000000.image.npy" in text, text
        assert "\n" not in text and len(text.replace(str(folder), "")) < 300, text
        assert f"delete {folder} to prepare the split again" in text


def test_a_missing_cache_file_is_named(tmp_path) -> None:
    folder = prepare_split(tmp_path, "val", ["a"], _frame, {})
    (folder / "000000.sparse.npy").unlink()
    with pytest.raises(FileNotFoundError, match=f"^{folder}/000000.sparse.npy: missing"):
        PreparedSplit(folder)[0]


def test_npy_files_round_trip_exactly_and_are_written_atomically(tmp_path) -> None:
    array = np.arange(2 * 3 * 3, dtype=np.uint16).reshape(2, 3, 3) * 3000
    write_npy(tmp_path / "a.npy", array)
    got = read_npy(tmp_path / "a.npy", np.uint16, (2, None, 3), "test array")
    assert got.dtype == np.uint16 and np.array_equal(got, array) and got.flags.writeable
    assert np.array_equal(np.load(tmp_path / "a.npy"), array)  # any numpy reads it
    assert [p.name for p in tmp_path.iterdir()] == ["a.npy"]  # no temporary file left
    with pytest.raises(DataFileError, match="test array of uint16 .2, 3, 3., expected uint16 .3"):
        read_npy(tmp_path / "a.npy", np.uint16, (3, None, 3), "test array")


def _old_cache(cache_root: Path, reader: type[Frames], root: Path) -> Path:
    """A version-2 cache of ``reader`` as the code before issue 17 wrote it: PNG files."""
    dataset = object.__new__(reader)
    dataset.root, dataset.height, dataset.width, dataset.filled = root.resolve(), H, W, False
    params = dataset.cache_key(dataset.list_frames())
    version = prepared.PREPARED_VERSION
    prepared.PREPARED_VERSION = 2
    try:
        cache = prepared.cache_dir(cache_root, reader.name, params)
    finally:
        prepared.PREPARED_VERSION = version
    (cache / "meta.json").parent.mkdir(parents=True)
    (cache / "meta.json").write_text(json.dumps({"prepared_version": 2, **params}))
    for split in ("train", "val", "test"):
        records = []
        for i in range(3):
            frame, stem = _frame(f"{split}/{i}"), cache / split / f"{i:06d}"
            write_rgb_png(f"{stem}.image.png", frame.image)
            write_depth_png(f"{stem}.sparse.png", frame.sparse)
            write_depth_png(f"{stem}.depth.png", frame.depth)
            records.append({"id": f"{split}/{i}", "file": f"{i:06d}", "condition": "night"})
            records[-1]["filled"] = False
        (cache / split / "index.json").write_text(json.dumps({"split": split, "frames": records}))
    return cache


def test_an_older_png_cache_is_prepared_again_and_left_alone(tmp_path, caplog) -> None:
    (tmp_path / "data").mkdir()
    old = _old_cache(tmp_path / "cache", Frames, tmp_path / "data")
    before = {p: p.stat().st_mtime_ns for p in old.rglob("*")}
    with caplog.at_level(logging.INFO, logger="fusion_depth.data.cache"):
        split = Frames("val", tmp_path / "data", tmp_path / "cache")
    assert split.cache != old and split.cache.parent == old.parent
    assert sorted(p.name for p in (split.cache / "val").glob("000000.*")) == [
        "000000.depth.npy",
        "000000.filled.npy",
        "000000.image.npy",
        "000000.json",
        "000000.radar.npy",
        "000000.sparse.npy",
    ]
    assert json.loads((split.cache / "meta.json").read_text())["prepared_version"] == 3
    assert {p: p.stat().st_mtime_ns for p in old.rglob("*")} == before  # never touched
    assert f"are no longer read ({old})" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="fusion_depth.data.cache"):
        Frames("train", tmp_path / "data", tmp_path / "cache")  # nothing to prepare, no notice
    assert "no longer read" not in caplog.text
