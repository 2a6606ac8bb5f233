"""Prepared caches: a dataset's slow per-frame work (projection, filling, resizing) done once.

A real dataset module turns its raw files into :class:`PreparedFrame` objects; :func:`prepare_split`
writes them under ``<cache root>/<dataset>/<hash of the settings>/<split>/`` as

* ``000123.image.png``  RGB uint8
* ``000123.sparse.png`` the sparse sensor input, uint16 depth PNG (1/256 m, 0 = no return)
* ``000123.depth.png``  the measured ground truth, same encoding (what evaluation scores)
* ``000123.filled.png`` the densified ground truth, only when a filling method is set
* ``000123.json``       the frame's source id and condition, written last
* ``index.json``        every frame of the split, written when all are done

Each file goes through a temporary name and a rename, and a frame counts as done only once its
``.json`` exists, so an interrupted prepare restarts where it stopped and never leaves a file a
later run would read as valid. A split with ``index.json`` is complete: preparing it again does
nothing. Other settings hash to another folder, leaving this one alone. The user's dataset
folder is only ever read.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from rich.progress import track
from torch.utils.data import Dataset

from fusion_depth.data.depth_io import read_depth_png, read_rgb, write_depth_png, write_rgb_png
from fusion_depth.runs import write_json_atomic

PREPARED_VERSION = 1  # bump when the cache layout changes, so old caches are not reused
INDEX_FILE = "index.json"
META_FILE = "meta.json"

log = logging.getLogger(__name__)


@dataclass
class PreparedFrame:
    """One frame as a dataset's prepare step produces it (arrays at the cached resolution)."""

    image: np.ndarray  # uint8 (H, W, 3)
    sparse: np.ndarray  # float (H, W) metres, 0 = no return
    depth: np.ndarray  # float (H, W) metres, 0 = invalid: measured points only
    condition: str
    filled: np.ndarray | None = None  # float (H, W) metres: densified ground truth for training
    # (top, left, height, width) of the original frame in the arrays when a reader cropped or
    # padded it: evaluation crops (eval.crop) are fractions of the original frame.
    frame_box: tuple[int, int, int, int] | None = None


def cache_dir(
    root: str | os.PathLike,
    dataset: str,
    params: dict[str, Any],
    read_only: dict[str, Path] | None = None,
) -> Path:
    """``root/dataset/<12 hex digits>``: one folder per distinct set of settings.

    ``read_only`` names the user's dataset folders (``{"root": path}``); a cache that would land
    inside one of them is refused, because those folders are only ever read.
    """
    text = json.dumps({"prepared_version": PREPARED_VERSION, **params}, sort_keys=True)
    cache = Path(root).expanduser() / dataset / hashlib.sha256(text.encode()).hexdigest()[:12]
    if read_only:
        cache = cache.resolve()
        for name, folder in read_only.items():
            if cache.is_relative_to(folder):
                raise ValueError(
                    f"cache {cache} is inside dataset.{name}={folder}; the dataset folder is only "
                    "ever read: point FUSION_DEPTH_CACHE (paths.cache_dir) elsewhere"
                )
    return cache


def is_prepared(cache: Path, split: str) -> bool:
    return (cache / split / INDEX_FILE).is_file()


def prepare_split(
    cache: Path,
    split: str,
    frame_ids: Sequence[str],
    make_frame: Callable[[str], PreparedFrame],
    params: dict[str, Any],
) -> Path:
    """Writes every frame of ``split`` that is not there yet; returns the split folder.

    ``frame_ids`` must come in the same order every time (they name the files by position);
    ``params`` are recorded in ``meta.json`` for a person to see what the cache holds.
    """
    split_dir = cache / split
    if (split_dir / INDEX_FILE).is_file():
        log.info("using the prepared %s split in %s", split, split_dir)
        return split_dir
    if not frame_ids:
        raise ValueError(f"split {split!r}: no frames to prepare (settings: {params})")
    write_json_atomic(cache / META_FILE, {"prepared_version": PREPARED_VERSION, **params})
    split_dir.mkdir(parents=True, exist_ok=True)
    records = []
    done = 0
    for i, frame_id in enumerate(
        track(frame_ids, description=f"preparing {cache.parent.name} {split}", transient=True)
    ):
        stem = f"{i:06d}"
        record_path = split_dir / f"{stem}.json"
        if record_path.is_file():
            record = json.loads(record_path.read_text())
            if record.get("id") == frame_id:
                records.append(record)
                done += 1
                continue
        frame = make_frame(frame_id)
        _check_frame(frame, frame_id)
        write_rgb_png(split_dir / f"{stem}.image.png", frame.image)
        write_depth_png(split_dir / f"{stem}.sparse.png", frame.sparse)
        write_depth_png(split_dir / f"{stem}.depth.png", frame.depth)
        if frame.filled is not None:
            write_depth_png(split_dir / f"{stem}.filled.png", frame.filled)
        record = {
            "id": frame_id,
            "file": stem,
            "condition": frame.condition,
            "filled": frame.filled is not None,
        }
        if frame.frame_box is not None:
            record["frame_box"] = [int(v) for v in frame.frame_box]
        write_json_atomic(record_path, record)
        records.append(record)
    write_json_atomic(split_dir / INDEX_FILE, {"split": split, "frames": records})
    log.info(
        "prepared %d %s frames into %s (%d already there from an earlier run)",
        len(records),
        split,
        split_dir,
        done,
    )
    return split_dir


def _check_frame(frame: PreparedFrame, frame_id: str) -> None:
    h, w = frame.image.shape[:2]
    maps = {"sparse": frame.sparse, "depth": frame.depth, "filled": frame.filled}
    for name, array in maps.items():
        if array is not None and array.shape != (h, w):
            raise ValueError(
                f"frame {frame_id}: {name} has shape {array.shape}, expected the image's {(h, w)}"
            )


class PreparedSplit(Dataset):
    """Reads one prepared split; samples are the platform's ``{"image", "sparse", "depth",
    "condition"}`` dict. ``use_filled`` serves the filled ground truth as ``depth`` where it
    exists (training); evaluation leaves it off and scores the measured points."""

    def __init__(self, split_dir: str | os.PathLike, use_filled: bool = False) -> None:
        self.split_dir = Path(split_dir)
        index = self.split_dir / INDEX_FILE
        if not index.is_file():
            raise FileNotFoundError(f"{index}: not a prepared split (run fusion_depth.prepare)")
        self.frames: list[dict] = json.loads(index.read_text())["frames"]
        if not self.frames:
            raise ValueError(f"{index}: the split has no frames")
        self.use_filled = use_filled
        self.conditions = [frame["condition"] for frame in self.frames]

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> dict:
        frame = self.frames[index]
        stem = self.split_dir / frame["file"]
        depth_file = "filled" if self.use_filled and frame["filled"] else "depth"
        image = read_rgb(f"{stem}.image.png")
        sample = {
            "image": torch.from_numpy(image.transpose(2, 0, 1).copy()).float().div_(255.0),
            "sparse": torch.from_numpy(read_depth_png(f"{stem}.sparse.png"))[None],
            "depth": torch.from_numpy(read_depth_png(f"{stem}.{depth_file}.png"))[None],
            "condition": frame["condition"],
        }
        if "frame_box" in frame:
            sample["frame_box"] = torch.tensor(frame["frame_box"], dtype=torch.long)
        return sample
