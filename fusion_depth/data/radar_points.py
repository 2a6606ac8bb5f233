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


def pixel_index(x: np.ndarray) -> np.ndarray:
    """The pixel (int64, same shape) each continuous coordinate lies in: ``round(x)``, halves to
    even as numpy rounds them.

    The coordinates put pixel centres at integers (pixel ``i`` spans ``[i - 0.5, i + 0.5]``), the
    OpenCV and nuScenes devkit convention (``view_points``); RadarNet's setup places a projected
    point on ``np.round`` of it (``setup/setup_dataset_nuscenes.py`` of
    github.com/nesl/radar-camera-fusion-depth), and so does every reader here.
    """
    return np.rint(np.asarray(x)).astype(np.int64)


def in_image(u: np.ndarray, v: np.ndarray, height: int, width: int) -> np.ndarray:
    """Whether each point (M,) lies in a pixel of a ``height x width`` image: its
    :func:`pixel_index` column in ``[0, width)`` and row in ``[0, height)``. False for NaN and
    for values too large to round to int64."""
    u, v = np.asarray(u), np.asarray(v)
    with np.errstate(invalid="ignore"):
        near = (u > -1) & (u < width) & (v > -1) & (v < height)  # NaN compares false
    out = near.copy()
    col, row = pixel_index(u[near]), pixel_index(v[near])
    out[near] = (col >= 0) & (col < width) & (row >= 0) & (row < height)
    return out


# How far inside its pixel a stored coordinate stays from the pixel's border: mirrored
# (``W - 1 - u``) in float32 at up to 8192 columns, it stays in the mirrored pixel.
_BORDER_MARGIN = 1 / 512


def same_pixel_float32(x: np.ndarray) -> np.ndarray:
    """Pixel coordinates (M,) as float32 in the same pixel, clear of its border:
    :func:`pixel_index` of the result equals that of ``x``. A value within 1/512 pixel of a
    half is moved 1/512 pixel inside its pixel: on a half it would round to even, so its mirror
    ``W - 1 - u`` would not land in the mirrored pixel, and rounding to float32 alone can carry a
    value a few millionths off a half into the neighbouring pixel. Coordinates beyond 2^22,
    where float32 holds no value inside a pixel, are left as the cast gives them."""
    x = np.asarray(x).reshape(-1)
    held = np.isfinite(x) & (np.abs(x) < 2**22)  # NaN, inf and huge values: as cast
    cell = pixel_index(np.where(held, x, 0.0))
    offset = np.where(held, x, 0.0) - cell  # in [-0.5, 0.5]
    near = held & (np.abs(np.abs(offset) - 0.5) < _BORDER_MARGIN)
    inside = np.where(near, cell + np.sign(offset) * (0.5 - _BORDER_MARGIN), x)
    out = inside.astype(np.float32)
    off = held & (pixel_index(np.where(held, out, 0.0)) != cell)
    out[off] = np.nextafter(out[off], cell[off].astype(np.float32))  # at most one step
    return out


def pad_points(rows: np.ndarray, max_points: int) -> np.ndarray:
    """The first ``max_points`` of ``rows`` (M, K) (the nearest, as :func:`point_rows` sorts
    them), padded with rows of zeros to float32 (max_points, K)."""
    out = np.zeros((max_points, NUM_FIELDS), dtype=np.float32)
    kept = rows[:max_points]
    out[: len(kept)] = kept
    return out


def inside_image(rows: np.ndarray, height: int, width: int) -> bool:
    """Whether every row (M, K) lies in a pixel of a ``height x width`` image (:func:`in_image`)."""
    return bool(in_image(rows[:, U], rows[:, V], height, width).all())


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
