"""Helpers for datasets read from folders of files (``carla``, ``topview``, and yours: see the
docs/guides/datasets/own-dataset.md).

Resizing keeps the depth values exact: images are resampled, depth maps only ever sampled, so
evaluation scores depths that really were rendered and never a blend across an object edge.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from fusion_depth.data.depth_io import MAX_ENCODED_DEPTH
from fusion_depth.errors import ArgumentError, ArgumentFileError

# The prepared cache stores uint16 depth × 256, so nothing beyond this fits.
CACHE_MAX_DEPTH = MAX_ENCODED_DEPTH


def check_max_range(max_range: float) -> float:
    """Depths are cached as uint16 1/256 m, so a valid range must stay below 256 m."""
    if not 0 < max_range <= CACHE_MAX_DEPTH:
        raise ArgumentError(
            f"{{max_range}}={max_range}: expected metres in (0, {CACHE_MAX_DEPTH:.2f}] "
            "(the prepared cache stores depth as uint16 in 1/256 m)",
            "max_range",
            owner=check_max_range,
        )
    return float(max_range)


def require_root(root: str | os.PathLike, layout: str) -> Path:
    """The dataset folder, resolved; a missing one fails naming it and the layout expected."""
    if str(root) in ("", "???", "None"):
        raise ArgumentError(f"{{root}} is not set: expected {layout}", "root", owner=require_root)
    path = Path(root).expanduser().resolve()
    if not path.is_dir():
        raise ArgumentFileError(
            f"{{root}}={path}: no such folder; expected {layout}", "root", owner=require_root
        )
    return path


def require_dir(path: Path, what: str) -> Path:
    if not path.is_dir():
        parent = path.parent
        found = sorted(p.name for p in parent.iterdir()) if parent.is_dir() else []
        raise FileNotFoundError(
            f"{path}: missing folder, expected {what} (found in {parent}: {found or 'nothing'})"
        )
    return path


def list_files(folder: Path, suffixes: Sequence[str]) -> dict[str, os.DirEntry]:
    """``stem -> entry`` of the plain files in ``folder`` whose suffix (lower case) is in
    ``suffixes``; hidden files (e.g. temporary ``.name.tmp``) are skipped."""
    files: dict[str, os.DirEntry] = {}
    with os.scandir(folder) as entries:
        for entry in entries:
            if entry.name.startswith(".") or not entry.is_file():
                continue
            stem, suffix = os.path.splitext(entry.name)
            if suffix.lower() in suffixes:
                if stem in files:
                    raise ValueError(
                        f"{folder}: {files[stem].name} and {entry.name} share the frame name "
                        f"{stem!r}; expected one file per frame"
                    )
                files[stem] = entry
    return files


def entries_not_files(folder: Path, suffixes: Sequence[str]) -> dict[str, Path]:
    """``stem -> path`` of the entries of ``folder`` named like frame files (``<stem><suffix>``,
    suffix in ``suffixes`` in any case, not hidden) that are not files: directories, dangling
    links. :func:`list_files` leaves them out, yet each stands where a frame's file should
    be, so a reader reports it instead of dropping the frame."""
    found: dict[str, Path] = {}
    with os.scandir(folder) as entries:
        for entry in entries:
            stem, suffix = os.path.splitext(entry.name)
            if not entry.name.startswith(".") and suffix.lower() in suffixes:
                if not entry.is_file():
                    found[stem] = Path(entry.path)
    return found


def fingerprint(entries: Iterable[os.DirEntry | Path]) -> str:
    """A digest of the files' paths, sizes and modification times (16 hex digits), for a
    dataset's cache key: a changed dataset gets a new cache.

    Raises:
        OSError: a file cannot be stat'ed (e.g. FileNotFoundError).
    """
    digest = hashlib.sha256()
    for entry in entries:
        stat = entry.stat()
        digest.update(json.dumps([os.fspath(entry), stat.st_size, stat.st_mtime_ns]).encode())
    return digest.hexdigest()[:16]


def resize_rgb(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """uint8 (H, W, 3) to (height, width, 3). Pillow's bilinear filter widens with the scale
    factor, so shrinking averages over each target pixel's area instead of aliasing."""
    if image.shape[:2] == (height, width):
        return image
    resized = Image.fromarray(image).resize((width, height), Image.Resampling.BILINEAR)
    return np.asarray(resized)


def resize_depth_nearest(depth: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W) to (height, width) by taking the source pixel under each target pixel's centre:
    every value is one that was rendered (no blending of foreground and background)."""
    h, w = depth.shape
    if (h, w) == (height, width):
        return depth
    rows = ((np.arange(height) + 0.5) * h / height).astype(np.int64)
    cols = ((np.arange(width) + 0.5) * w / width).astype(np.int64)
    return depth[rows[:, None], cols[None, :]]
