"""Radar returns as points: the ``radar_points`` of a :class:`~fusion_depth.data.Sample`.

A model that looks at each radar return (RadarNet, Singh et al. CVPR 2023, associates each one
with the image pixels in a tall window around its projection) needs the returns themselves, not
only the projected ``sparse`` map. A reader builds them with :func:`point_rows` from the same
projection that draws ``sparse`` (so every row lies on a pixel of the map), stores them, and
serves them padded to a fixed ``P`` rows with :func:`pad_points`, so they batch.

Rows have the columns :data:`~fusion_depth.data.RADAR_POINT_FIELDS` (``u, v, depth, rcs,
velocity, valid``) as float32, sorted nearest first, so keeping the first ``P`` rows keeps the
nearest ``P`` returns. The prepared caches store every return of a frame
(``<frame>.radar.npy``, :func:`write_points`/:func:`read_points`) and cut to ``P`` when
serving, so changing ``dataset.max_radar_points`` prepares nothing again.
"""

from __future__ import annotations

import numbers
import os

import numpy as np

from fusion_depth.data import RADAR_POINT_FIELDS
from fusion_depth.data.depth_io import DataFileError, read_npy, write_npy
from fusion_depth.errors import ArgumentError

NUM_FIELDS = len(RADAR_POINT_FIELDS)
U, V, DEPTH, RCS, VELOCITY, VALID = (RADAR_POINT_FIELDS.index(name) for name in RADAR_POINT_FIELDS)
# ``dataset.max_radar_points`` of a reader built without it (a real radar's frame: tens to a few
# hundred returns in view).
DEFAULT_MAX_RADAR_POINTS = 128


def check_max_points(value: int, argument: str = "max_radar_points") -> int:
    """``value`` as an int, or an ArgumentError naming ``argument`` when it is not an integer
    >= 1."""
    whole = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if not whole or value < 1:
        raise ArgumentError(
            f"{{{argument}}}={value!r}: expected an integer >= 1 (the radar returns each sample "
            "keeps, the nearest first)",
            argument,
            owner=check_max_points,
        )
    return int(value)


def point_rows(
    u: np.ndarray,
    v: np.ndarray,
    depth: np.ndarray,
    rcs: np.ndarray | None = None,
    velocity: np.ndarray | None = None,
) -> np.ndarray:
    """Float32 (M, K) rows of M returns, nearest first (a stable sort: ties keep their order).

    Args:
        u: (M,) continuous column of each point in the output image; it stays in its pixel
            (:func:`same_pixel_float32`).
        v: (M,) continuous row of each point, likewise.
        depth: (M,) metres, camera-frame z.
        rcs: (M,) dBsm, or None for a radar that does not report it (0).
        velocity: (M,) radial velocity in m/s, or None (0).

    Returns:
        (M, K) float32 with ``valid`` = 1, K = ``len(RADAR_POINT_FIELDS)``.
    """
    depth = np.asarray(depth, dtype=np.float64).reshape(-1)
    rows = np.zeros((len(depth), NUM_FIELDS), dtype=np.float32)
    rows[:, U] = same_pixel_float32(u)
    rows[:, V] = same_pixel_float32(v)
    rows[:, DEPTH] = depth
    if rcs is not None:
        rows[:, RCS] = np.asarray(rcs, dtype=np.float64).reshape(-1)
    if velocity is not None:
        rows[:, VELOCITY] = np.asarray(velocity, dtype=np.float64).reshape(-1)
    rows[:, VALID] = 1.0
    return rows[np.argsort(depth, kind="stable")]


def same_pixel_float32(x: np.ndarray) -> np.ndarray:
    """Pixel coordinates (M,) as float32 in the same pixel: ``floor`` of the result equals
    ``floor(x)``. Rounding to float32 alone can carry a coordinate a few millionths below an
    integer onto it, i.e. into the next pixel; such values become the largest float32 below
    that integer."""
    x = np.asarray(x).reshape(-1)
    out = x.astype(np.float32)
    if x.dtype == np.float32:
        return out
    cell = np.floor(x)
    moved = np.floor(out) != cell
    out[moved] = np.nextafter((cell[moved] + 1).astype(np.float32), np.float32(-np.inf))
    return out


def pad_points(rows: np.ndarray, max_points: int) -> np.ndarray:
    """The first ``max_points`` of ``rows`` (M, K) (the nearest, as :func:`point_rows` sorts
    them), padded with rows of zeros to float32 (max_points, K)."""
    out = np.zeros((max_points, NUM_FIELDS), dtype=np.float32)
    kept = rows[:max_points]
    out[: len(kept)] = kept
    return out


def inside_image(rows: np.ndarray, height: int, width: int) -> bool:
    """Whether every row (M, K) lies inside a ``height x width`` image: 0 <= u < width and
    0 <= v < height."""
    u, v = rows[:, U], rows[:, V]
    return bool(((u >= 0) & (u < width) & (v >= 0) & (v < height)).all())


def write_points(path: str | os.PathLike, rows: np.ndarray) -> None:
    """Saves rows (M, K) (M may be 0) as a float32 ``.npy`` file, atomically (a temporary
    sibling, then a rename)."""
    rows = np.ascontiguousarray(rows, dtype=np.float32)
    if rows.ndim != 2 or rows.shape[1] != NUM_FIELDS:
        raise ValueError(f"radar points {rows.shape}: expected (M, {NUM_FIELDS}) rows")
    write_npy(path, rows)


def read_points(path: str | os.PathLike) -> np.ndarray:
    """Rows (M, K) float32 as :func:`write_points` saved them.

    Raises:
        FileNotFoundError: there is no file.
        DataFileError: naming the file, when it is truncated or garbled, holds another dtype or
            shape than float32 (M, K), a pickled object, non-finite values, or a ``valid``
            column other than 1. The header is checked against the file's size before any data
            is read, so a header promising more than the file holds allocates nothing
            (:func:`~fusion_depth.data.depth_io.read_npy`).
    """
    hint = f"columns {','.join(RADAR_POINT_FIELDS)}; delete the cache folder to prepare it again"
    rows = read_npy(path, np.float32, (None, NUM_FIELDS), "radar points file", hint)
    if not np.isfinite(rows).all() or not (rows[:, VALID] == 1).all():
        raise DataFileError(
            path,
            f"non-finite values or a valid column other than 1; expected float32 "
            f"(M, {NUM_FIELDS}) rows {hint}",
        )
    return rows
