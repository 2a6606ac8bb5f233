"""A prepared split is verified against what made it: an edited index or meta.json, a replaced
source file, a truncated or emptied array and a write cut by a power loss are caught (re-prepared
or refused in one line), and the leftovers of a killed prepare go on the next run."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import file_bytes
from test_kitti import _dataset, _frame_arrays, _write_u16, kitti_data  # noqa: F401

from fusion_depth.data import cache as cache_module
from fusion_depth.data.cache import (
    CLAIMS_DIR,
    INDEX_FILE,
    META_FILE,
    SHARDED_FILE,
    IncompleteSplitError,
    PreparedFrame,
    PreparedSplit,
    PrepareOptions,
    is_prepared,
    prepare_options,
    prepare_split,
)
from fusion_depth.data.depth_io import DataFileError
from fusion_depth.utils import atomic
from fusion_depth.utils.atomic import host_tag

FRAMES = [f"{k:03d}" for k in range(6)]
PARAMS = {"dataset": "toy", "size": [8, 12]}


def _source(k: int, variant: int = 0) -> np.ndarray:
    return np.random.default_rng(100 * variant + k).uniform(1, 80, (8, 12)).astype(np.float32)


@pytest.fixture
def data(tmp_path) -> Path:
    """A dataset folder: one float32 depth map per frame, ``<id>.npy``."""
    root = tmp_path / "data"
    root.mkdir()
    for k, frame_id in enumerate(FRAMES):
        np.save(root / f"{frame_id}.npy", _source(k))
    return root


class Toy:
    """Makes a frame from its source file and counts the frames it made."""

    def __init__(self, root: Path) -> None:
        self.root, self.made = root, []

    def make(self, frame_id: str) -> PreparedFrame:
        self.made.append(frame_id)
        depth = np.load(self.root / f"{frame_id}.npy").astype(np.float64)
        image = (np.stack([depth] * 3, -1) * 3 % 256).astype(np.uint8)
        return PreparedFrame(image, depth * (depth > 40), depth, "day", filled=depth)

    def sources(self, frame_id: str) -> list[Path]:
        return [self.root / f"{frame_id}.npy"]

    def prepare(self, cache: Path, options: PrepareOptions | None = None, **kwargs) -> Path:
        cache_module._VERIFIED.clear()  # as a new process would: it has verified nothing
        with prepare_options(options or PrepareOptions()):
            return prepare_split(
                cache, "train", FRAMES, self.make, PARAMS, sources=self.sources, **kwargs
            )


def _replace(path: Path, array: np.ndarray) -> None:
    """As ``rm path; cp other path``: a new file with a new time."""
    path.unlink()
    np.save(path, array)


def _depth_of(split_dir: Path, k: int) -> np.ndarray:
    return PreparedSplit(split_dir)[k]["depth"][0].numpy()


# --- sources -------------------------------------------------------------------------------------


def test_a_replaced_source_prepares_that_frame_again_and_only_it(tmp_path, data) -> None:
    toy = Toy(data)
    split = toy.prepare(tmp_path / "cache")
    assert toy.made == FRAMES
    old = _depth_of(split, 2)
    # The same size and another content: only its digest tells.
    _replace(data / "002.npy", _source(2, variant=1))
    toy.made.clear()
    toy.prepare(tmp_path / "cache")
    assert toy.made == ["002"]
    new = _depth_of(split, 2)
    assert not np.allclose(new, old)
    assert np.allclose(new, _source(2, variant=1), atol=1 / 256)
    fresh = Toy(data)
    fresh.prepare(tmp_path / "fresh")
    assert file_bytes(split) == file_bytes(tmp_path / "fresh" / "train")


def test_a_source_touched_but_unchanged_is_read_once_and_kept(tmp_path, data, monkeypatch) -> None:
    toy = Toy(data)
    split = toy.prepare(tmp_path / "cache")
    stat = (data / "004.npy").stat()
    os.utime(data / "004.npy", ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    hashed = []
    real = cache_module._file_digest
    monkeypatch.setattr(cache_module, "_file_digest", lambda p: hashed.append(p) or real(p))
    toy.made.clear()
    toy.prepare(tmp_path / "cache")
    assert toy.made == [] and [Path(p).name for p in hashed] == ["004.npy"]
    record = json.loads((split / "000004.json").read_text())
    assert record["sources"][0][2] == stat.st_mtime_ns + 10**9  # the new time is kept
    assert json.loads((split / INDEX_FILE).read_text())["frames"][4] == record
    hashed.clear()
    toy.prepare(tmp_path / "cache")
    assert toy.made == [] and hashed == []  # the next load trusts it again


def test_a_deleted_source_makes_its_frame_fail_naming_the_file(tmp_path, data) -> None:
    toy = Toy(data)
    toy.prepare(tmp_path / "cache")
    (data / "001.npy").unlink()
    with pytest.raises(FileNotFoundError, match="001.npy"):
        toy.prepare(tmp_path / "cache")
    assert not (tmp_path / "cache" / "train" / INDEX_FILE).exists()


# --- the index and meta.json ---------------------------------------------------------------------


def _listed_five_times(frames: list) -> list:
    return [frames[0]] * 5


def _cut_to_three(frames: list) -> list:
    return frames[:3]


def _every_entry_at_frame_zero(frames: list) -> list:
    return [{**frame, "file": frames[0]["file"]} for frame in frames]


def _ids_swapped(frames: list) -> list:
    return [frames[1], frames[0], *frames[2:]]


@pytest.mark.parametrize(
    "edit", [_listed_five_times, _cut_to_three, _every_entry_at_frame_zero, _ids_swapped]
)
def test_an_edited_index_is_refused_by_the_reader_and_rebuilt_by_prepare(
    tmp_path, data, edit
) -> None:
    toy = Toy(data)
    split = toy.prepare(tmp_path / "cache")
    before = file_bytes(split)
    index = split / INDEX_FILE
    content = json.loads(index.read_text())
    index.write_text(json.dumps({**content, "frames": edit(content["frames"])}))
    with pytest.raises(DataFileError) as info:
        PreparedSplit(split)
    assert str(info.value).startswith(f"{index}: ") and "\n" not in str(info.value)
    toy.made.clear()
    toy.prepare(tmp_path / "cache")
    assert toy.made == []  # every frame's record and arrays were still whole
    assert file_bytes(split) == before
    assert len(PreparedSplit(split)) == len(FRAMES)


def test_an_index_that_lists_other_frames_than_the_datasets_is_rebuilt(tmp_path, data) -> None:
    """An index edited consistently (its digest recomputed) still has to list the frames the
    dataset lists now."""
    toy = Toy(data)
    split = toy.prepare(tmp_path / "cache")
    index = split / INDEX_FILE
    content = json.loads(index.read_text())
    frames = content["frames"][:3]
    digest = cache_module.frames_digest([f["id"] for f in frames])
    index.write_text(json.dumps({**content, "frames": frames, "frames_digest": digest}))
    assert len(PreparedSplit(split)) == 3  # a reader alone cannot tell
    cache_module._VERIFIED.clear()
    assert not is_prepared(tmp_path / "cache", "train", FRAMES)
    toy.prepare(tmp_path / "cache")
    assert len(PreparedSplit(split)) == len(FRAMES)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda meta: {**meta, "size": [16, 24]}, r"records size=\[16, 24\], but the folder"),
        (lambda meta: {**meta, "frames": 5}, r"records frames=5, but the folder's name stands"),
        (lambda meta: [meta], r"expected the folder's settings as a JSON object"),
    ],
)
def test_an_edited_meta_is_refused_in_one_line_and_the_cache_kept(
    tmp_path, data, edit, message
) -> None:
    toy = Toy(data)
    toy.prepare(tmp_path / "cache")
    meta = tmp_path / "cache" / META_FILE
    meta.write_text(json.dumps(edit(json.loads(meta.read_text()))))
    before = file_bytes(tmp_path / "cache")
    with pytest.raises(DataFileError, match=message) as info:
        toy.prepare(tmp_path / "cache")
    text = str(info.value)
    assert text.startswith(f"{meta}: ") and "\n" not in text and "delete" in text
    assert file_bytes(tmp_path / "cache") == before


def test_a_meta_json_cut_short_is_refused_in_one_line(tmp_path, data) -> None:
    toy = Toy(data)
    toy.prepare(tmp_path / "cache")
    meta = tmp_path / "cache" / META_FILE
    meta.write_text(meta.read_text()[:20])
    with pytest.raises(DataFileError, match=r"meta.json: unreadable \(") as info:
        toy.prepare(tmp_path / "cache")
    assert "\n" not in str(info.value)


# --- arrays --------------------------------------------------------------------------------------


def _empty(path: Path) -> None:
    path.write_bytes(b"")


def _truncate(path: Path) -> None:
    os.truncate(path, path.stat().st_size - 7)


def _delete(path: Path) -> None:
    path.unlink()


@pytest.mark.parametrize("damage", [_empty, _truncate, _delete])
@pytest.mark.parametrize("resumed", [False, True], ids=["loaded", "resumed"])
def test_a_damaged_array_behind_an_intact_record_is_made_again(
    tmp_path, data, damage, resumed
) -> None:
    toy = Toy(data)
    split = toy.prepare(tmp_path / "cache")
    before = file_bytes(split)
    damage(split / "000003.depth.npy")
    if resumed:  # as a prepare killed before its index, then run again
        (split / INDEX_FILE).unlink()
    toy.made.clear()
    toy.prepare(tmp_path / "cache")
    assert toy.made == ["003"]
    assert file_bytes(split) == before


def test_an_older_record_without_sizes_has_its_arrays_headers_checked_on_resume(
    tmp_path, data
) -> None:
    """A frame record of version 0.2.0 keeps no array sizes: a resumed prepare reads each
    array's header against its size."""
    toy = Toy(data)
    split = toy.prepare(tmp_path / "cache")
    for path in split.glob("0*.json"):
        record = json.loads(path.read_text())
        del record["arrays"], record["sources"]
        path.write_text(json.dumps(record))
    (split / INDEX_FILE).unlink()
    _truncate(split / "000005.filled.npy")
    toy.made.clear()
    toy.prepare(tmp_path / "cache")
    assert toy.made == ["005"]
    np.testing.assert_allclose(_depth_of(split, 5), _source(5), atol=1 / 256)


def test_every_write_is_flushed_to_disk_before_its_rename(tmp_path, data, monkeypatch) -> None:
    """Arrays, records, the index and meta.json reach the disk before they take their names:
    a power loss cannot leave a record whose arrays are empty."""
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(source, target) -> None:
        events.append(("rename", str(source)))
        real_replace(source, target)

    monkeypatch.setattr(atomic.os, "fsync", fsync)
    monkeypatch.setattr(atomic.os, "replace", replace)
    Toy(data).prepare(tmp_path / "cache")
    renames = [i for i, (kind, _) in enumerate(events) if kind == "rename"]
    assert len(renames) == 1 + len(FRAMES) * 5 + 1  # meta, 4 arrays and a record each, index
    for i in renames:
        assert ("fsync", events[i][1]) in events[:i], f"{events[i][1]} renamed unflushed"


# --- leftovers -----------------------------------------------------------------------------------


def _dead_pid() -> int:
    done = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True
    )
    return int(done.stdout)


def test_the_leftovers_of_a_kill_after_the_index_go_on_the_next_load(tmp_path, data) -> None:
    toy = Toy(data)
    split = toy.prepare(tmp_path / "cache")
    before = file_bytes(tmp_path / "cache")
    dead, live = _dead_pid(), os.getpid()
    (split / CLAIMS_DIR).mkdir()
    (split / CLAIMS_DIR / "000002").write_text(
        json.dumps({"host": os.uname().nodename, "pid": dead})
    )
    (split / SHARDED_FILE).write_text('{"num_shards": 2}')
    (split / f".{INDEX_FILE}.p{dead}h{host_tag()}.ab12.tmp").write_text("{")
    (tmp_path / "cache" / f".{META_FILE}.p{dead}h{host_tag()}.cd34.tmp").write_text("{")
    (split / ".000004.image.npy.x1y2z3.npy").write_bytes(b"\x93NUMPY half")
    # An index being written right now by a live process stays.
    being_written = split / f".{INDEX_FILE}.p{live}h{host_tag()}.ef56.tmp"
    being_written.write_text("{")
    toy.made.clear()
    toy.prepare(tmp_path / "cache")
    assert toy.made == []
    being_written.unlink()
    assert file_bytes(tmp_path / "cache") == before


def test_a_temporary_file_of_an_older_version_goes_once_it_is_old(tmp_path, data) -> None:
    """Versions up to 0.2.0 did not name the writer in a temporary file: one is taken for an
    orphan once older than any write takes."""
    toy = Toy(data)
    (tmp_path / "cache").mkdir()
    old = tmp_path / "cache" / f".{META_FILE}.k2j3h4.tmp"
    new = tmp_path / "cache" / f".{META_FILE}.m5n6b7.tmp"
    old.write_text("{")
    new.write_text("{")
    hour_ago = old.stat().st_mtime_ns - 3600 * 10**9
    os.utime(old, ns=(hour_ago, hour_ago))
    toy.prepare(tmp_path / "cache")
    assert not old.exists() and new.exists()


# --- shards --------------------------------------------------------------------------------------


def test_shards_started_with_other_settings_say_so_in_one_line(tmp_path, data) -> None:
    toy = Toy(data)
    shard = PrepareOptions(shard=0, num_shards=2, finish_sharded=True)
    root = tmp_path / "cache" / "toy"
    with prepare_options(shard), pytest.raises(IncompleteSplitError) as first:
        prepare_split(root / "aaa", "train", FRAMES, toy.make, {**PARAMS, "fill": "linear"})
    assert first.value.hint is None  # nothing else is being prepared
    other = PrepareOptions(shard=1, num_shards=2, finish_sharded=True)
    with prepare_options(other), pytest.raises(IncompleteSplitError) as second:
        prepare_split(root / "bbb", "train", FRAMES, toy.make, {**PARAMS, "fill": "none"})
    hint = second.value.hint
    assert hint is not None and "\n" not in hint
    assert str(root / "aaa") in hint and 'fill="none" here, "linear" there' in hint
    assert hint in str(second.value)


def test_kitti_a_replaced_ground_truth_png_is_prepared_again(kitti_data) -> None:  # noqa: F811
    """A ground-truth PNG replaced (rm, then cp of another image), and the dataset loaded
    again: that frame is made again from the new file."""
    data = kitti_data
    val = _dataset(data, "val")
    frame_id = val.frames[1]["id"]
    subset, drive, camera, frame = frame_id.split("/")
    png = (
        data["root"]
        / "data_depth_annotated"
        / subset
        / drive
        / "proj_depth"
        / "groundtruth"
        / camera
        / f"{frame}.png"
    )
    other = data["cache"].parent / "other.png"
    _write_u16(other, _frame_arrays(40)[1])
    png.unlink()
    shutil.copy(other, png)
    cache_module._VERIFIED.clear()
    again = _dataset(data, "val")
    gt = again[1]["depth"][0].numpy()
    stored = _frame_arrays(40)[1].astype(np.float64) / 256
    # The cached map is the new PNG's, padded into the 64x128 input (bottom rows, centre columns)
    assert np.allclose(np.sort(gt[gt > 0]), np.sort(stored[stored > 0]), atol=1 / 256)
