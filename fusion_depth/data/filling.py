"""Ground-truth depth filling: sparse lidar maps made dense for training.

The paper fills the missing pixels of its lidar ground truth with the colorization method of
Levin, Lischinski & Weiss (2004), as the NYU Depth v2 toolbox does (``fill_depth_colorization.m``):
every missing pixel's depth is a weighted average of its 3x3 neighbours, with weights that are
large where the image intensity is similar, so depth spreads along surfaces and stops at image
edges. The measured pixels are fixed, and the resulting sparse linear system is solved once per
frame. ``linear`` is the cheap alternative (piecewise-linear over a Delaunay triangulation of the
measured points, nearest measurement outside their convex hull); ``none`` leaves the map as it is.

Every method returns every measured value exactly, so evaluation against the measured points of a
filled map is the same as against the unfilled one.
"""

from __future__ import annotations

import numpy as np

FILL_METHODS: tuple[str, ...] = ("none", "linear", "colorization")

# Levin et al.'s weight bandwidth as the NYU toolbox sets it: 0.6 x the window's intensity
# variance, at least enough for the most similar neighbour to weigh exp(log 0.01) = 1 %
# relative to an identical one, and never below 2e-6 (flat regions).
_VARIANCE_FACTOR = 0.6
_MIN_NEIGHBOUR_WEIGHT = 0.01
_MIN_SIGMA = 2e-6
_OFFSETS = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0))


def fill_depth(depth: np.ndarray, image: np.ndarray, method: str) -> np.ndarray:
    """A dense float32 (H, W) depth map from ``depth`` (metres, 0 = missing) and its RGB image.

    ``method`` is one of :data:`FILL_METHODS`. Measured pixels (``depth > 0``) keep their value
    exactly; a map without any measured pixel comes back unchanged (there is nothing to spread).
    """
    if method not in FILL_METHODS:
        raise ValueError(f"fill method {method!r}: expected one of {list(FILL_METHODS)}")
    depth = np.asarray(depth, dtype=np.float32)
    image = np.asarray(image)
    if depth.ndim != 2:
        raise ValueError(f"depth: expected a (H, W) map, got shape {depth.shape}")
    if image.shape != (*depth.shape, 3):
        raise ValueError(
            f"image: expected shape {(*depth.shape, 3)} to match the depth map, got {image.shape}"
        )
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
    known = depth > 0
    if method == "none" or known.all() or not known.any():
        return depth.copy()
    if method == "linear":
        filled = _fill_linear(depth, known)
    else:
        filled = _fill_colorization(depth, known, _intensity(image))
    filled = filled.astype(np.float32)
    filled[known] = depth[known]  # exact, whatever the interpolation's rounding
    return filled


def _intensity(image: np.ndarray) -> np.ndarray:
    """ITU-R BT.601 luma in [0, 1], what MATLAB's rgb2gray gives the NYU toolbox."""
    rgb = image.astype(np.float64)
    if image.dtype == np.uint8:
        rgb /= 255.0
    return rgb @ np.array([0.2989, 0.5870, 0.1140])


def _fill_linear(depth: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Barycentric interpolation inside the measured points' convex hull, nearest outside."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
    from scipy.spatial import QhullError

    points = np.argwhere(known).astype(np.float64)
    values = depth[known].astype(np.float64)
    missing = np.argwhere(~known).astype(np.float64)
    filled = depth.astype(np.float64)
    guess = np.full(len(missing), np.nan)
    if len(points) >= 3:
        try:
            guess = LinearNDInterpolator(points, values)(missing)
        except QhullError:  # all points on one line: no triangle to interpolate in
            pass
    outside = np.isnan(guess)
    if outside.any():
        guess[outside] = NearestNDInterpolator(points, values)(missing[outside])
    filled[~known] = guess
    return filled


def _fill_colorization(depth: np.ndarray, known: np.ndarray, gray: np.ndarray) -> np.ndarray:
    """Levin et al.'s optimisation with the measured pixels fixed.

    Each missing pixel ``i`` must equal the weighted mean of its 3x3 neighbours,
    ``x_i - sum_j w_ij x_j = 0`` with ``w_ij ~ exp(-(I_i - I_j)^2 / sigma_i)`` summing to 1.
    Known neighbours move to the right-hand side, which leaves a sparse, diagonally dominant
    system in the missing pixels only. (The NYU toolbox keeps every pixel as an unknown and
    pulls the measured ones to their value with a penalty weight; fixing them is that weight's
    limit, gives a smaller system, and keeps the measurements exactly.)
    """
    from scipy.sparse import csr_matrix
    from scipy.sparse.linalg import spsolve

    h, w = depth.shape
    weights, valid = _neighbour_weights(gray)  # (8, H, W) each
    scale = float(depth[known].max())  # solve in [0, 1], as the toolbox does
    values = depth.astype(np.float64) / scale

    missing = ~known
    n = int(missing.sum())
    index = np.full((h, w), -1, dtype=np.int64)  # unknown number of each missing pixel
    index[missing] = np.arange(n)
    rows, cols = np.nonzero(missing)
    entry_rows, entry_cols, entry_vals = [index[missing]], [index[missing]], [np.ones(n)]
    rhs = np.zeros(n)
    for k, (dy, dx) in enumerate(_OFFSETS):
        has = valid[k][rows, cols]  # this neighbour lies inside the image
        r, c = rows[has], cols[has]
        nr, nc, wk = r + dy, c + dx, weights[k][r, c]
        fixed = known[nr, nc]  # a measured neighbour contributes to the right-hand side
        rhs += np.bincount(index[r[fixed], c[fixed]], wk[fixed] * values[nr, nc][fixed], n)
        entry_rows.append(index[r[~fixed], c[~fixed]])
        entry_cols.append(index[nr[~fixed], nc[~fixed]])
        entry_vals.append(-wk[~fixed])
    matrix = csr_matrix(
        (np.concatenate(entry_vals), (np.concatenate(entry_rows), np.concatenate(entry_cols))),
        shape=(n, n),
    )
    solution = spsolve(matrix, rhs)
    filled = values.copy()
    filled[missing] = solution
    return filled * scale


def _neighbour_weights(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised affinities of every pixel to its 8 neighbours and which neighbours exist."""
    h, w = gray.shape
    padded = np.pad(gray, 1, mode="constant", constant_values=np.nan)
    shifted = np.stack([padded[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] for dy, dx in _OFFSETS])
    valid = ~np.isnan(shifted)
    window = np.concatenate([shifted, gray[None]])  # the 3x3 window including the pixel itself
    count = (~np.isnan(window)).sum(0)
    mean = np.nansum(window, 0) / count
    variance = np.nansum((window - mean) ** 2, 0) / count
    diff2 = np.where(valid, (shifted - gray) ** 2, np.inf)
    sigma = np.maximum(_VARIANCE_FACTOR * variance, diff2.min(0) / -np.log(_MIN_NEIGHBOUR_WEIGHT))
    sigma = np.maximum(sigma, _MIN_SIGMA)
    weights = np.where(valid, np.exp(-np.where(valid, diff2, 0.0) / sigma), 0.0)
    weights /= weights.sum(0)
    return weights, valid
