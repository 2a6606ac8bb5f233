"""Ground-truth depth filling: sparse lidar maps made dense for training.

The paper fills the missing pixels of its lidar ground truth with the colorization method of
Levin, Lischinski & Weiss (2004), as the NYU Depth v2 toolbox does (``fill_depth_colorization.m``):
every missing pixel's depth is a weighted average of its 3x3 neighbours, with weights that are
large where the image intensity is similar, so depth spreads along surfaces and stops at image
edges. The measured pixels are fixed, and the resulting sparse linear system is solved once per
frame by a direct solver for 3x3-stencil systems on the pixel grid
(:class:`~fusion_depth.data.stencil_lu.StencilLU`: geometric nested dissection, multifrontal,
float32 factors), refined in float64 until a bound proves every pixel within 1 mm of the exact
solution (:func:`colorization_error_bound`; the promise is :data:`FILL_TOLERANCE_M`, 1 cm).
Measured by ``python -m fusion_depth.bench --only prepare`` on 2 cores of an Intel Xeon with
AMX, one thread, against SciPy's default ``spsolve`` of the same system: 6.8-7.1x on real
375x1242 KITTI frames (a Velodyne scan projected into its image), 6.3-7.7x on generated ones
of that size and 8.2-8.6x at nuScenes' 448x800; a first fill in a fresh process, which also
maps its memory, 4.2-4.5x (``docs/results/prepare.md``). The command prints the ratio on your
machine.
``linear`` is the cheap alternative (piecewise-linear over a Delaunay triangulation of the
measured points, nearest measurement outside their convex hull); ``linear_hull`` the same
inside the hull and nothing outside it (the rule of RadarNet's ``interpolate_depth``,
``setup/data_utils.py``: ``LinearNDInterpolator`` with ``fill_value=0``); ``none`` leaves the
map as it is.

Every method returns every measured value exactly, so evaluation against the measured points of a
filled map is the same as against the unfilled one.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from threadpoolctl import ThreadpoolController

from fusion_depth.data.stencil_lu import CENTRE, StencilLU, stencil_apply

if TYPE_CHECKING:
    from scipy.sparse import csc_matrix
    from scipy.sparse.linalg import SuperLU

log = logging.getLogger(__name__)

FILL_METHODS: tuple[str, ...] = ("none", "linear", "colorization", "linear_hull")

# Levin et al.'s weight bandwidth as the NYU toolbox sets it: 0.6 x the window's intensity
# variance, at least enough for the most similar neighbour to weigh exp(log 0.01) = 1 %
# relative to an identical one, and never below 2e-6 (flat regions).
_VARIANCE_FACTOR = 0.6
_MIN_NEIGHBOUR_WEIGHT = 0.01
_MIN_SIGMA = 2e-6
_OFFSETS = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0))
# Nested dissection stops cutting at boxes this small: below it a cut saves less than it costs.
_LEAF_PIXELS = 16
# What the colorization fill promises: every pixel within this of the exact solution of its
# system; the refinement stops once it has proved a tenth of it (colorization_error_bound).
FILL_TOLERANCE_M = 0.01
_MAX_REFINEMENTS = 6
# Above the float64 rounding of a residual or of A z for values in [0, 1] with 9 terms a row.
_ROUNDING = 1e-14
# Where the 8 neighbours of _OFFSETS sit among the 9 of stencil_lu.STENCIL (the centre is 4).
_NEIGHBOUR_SLOTS = [0, 1, 2, 3, 5, 6, 7, 8]


@functools.cache
def _blas() -> ThreadpoolController:
    """The BLAS libraries of this process once the fills' SciPy, and the OpenBLAS it links, is
    loaded (a controller's ``limit`` costs 15 µs, ``threadpool_limits`` 0.7 ms: it looks the
    libraries up each time)."""
    import scipy.interpolate  # noqa: F401
    import scipy.spatial  # noqa: F401

    return ThreadpoolController()


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
    depth = _measured(depth)
    known = depth > 0
    if method == "none" or known.all() or not known.any():
        return depth.copy()
    if method in ("linear", "linear_hull"):
        # One BLAS thread: the triangulation's LAPACK calls are 2×2 solves, which a second
        # thread only slows (13 % of the wall time, 40 % of the CPU time on a 2-core Xeon).
        with _blas().limit(limits=1, user_api="blas"):
            filled = _fill_linear(depth, known, outside=method == "linear")
    else:
        filled = _fill_colorization(depth, known, _intensity(image))
    filled = filled.astype(np.float32)
    filled[known] = depth[known]  # exact, whatever the interpolation's rounding
    return filled


def colorization_reference(depth: np.ndarray, image: np.ndarray) -> np.ndarray:
    """The colorization fill of ``depth`` solved by SciPy's default ``spsolve`` (SuperLU, COLAMD
    order, partial pivoting) of the same system (:func:`colorization_system`): what
    :func:`fill_depth` is held to (within 1 cm at every pixel) and timed against
    (``python -m fusion_depth.bench --only prepare``). Slow: 8-13 s at KITTI's size.

    Args:
        depth: float (H, W) metres, 0 = missing (at least one measured pixel).
        image: (H, W, 3) RGB, uint8 or float in [0, 1].

    Returns:
        float64 (H, W) metres, the measured pixels as given.
    """
    from scipy.sparse.linalg import spsolve

    depth = _measured(depth)
    known = depth > 0
    transposed, rhs, scale, unknowns = colorization_system(depth, known, _intensity(image))
    filled = depth.astype(np.float64).ravel()
    filled[unknowns] = spsolve(transposed.T.tocsc(), rhs) * scale
    return filled.reshape(depth.shape)


def _measured(depth: np.ndarray) -> np.ndarray:
    """float32 ``depth`` with every pixel that is not a finite depth > 0 set to 0 (missing)."""
    return np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)


def _intensity(image: np.ndarray) -> np.ndarray:
    """ITU-R BT.601 luma in [0, 1], what MATLAB's rgb2gray gives the NYU toolbox."""
    rgb = image.astype(np.float64)
    if image.dtype == np.uint8:
        rgb /= 255.0
    return rgb @ np.array([0.2989, 0.5870, 0.1140])


def _fill_linear(depth: np.ndarray, known: np.ndarray, outside: bool = True) -> np.ndarray:
    """Barycentric interpolation inside the measured points' convex hull; outside it the
    nearest measurement, or 0 (missing) without ``outside``."""
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
    beyond = np.isnan(guess)
    if beyond.any():
        guess[beyond] = NearestNDInterpolator(points, values)(missing[beyond]) if outside else 0.0
    filled[~known] = guess
    return filled


def _fill_colorization(depth: np.ndarray, known: np.ndarray, gray: np.ndarray) -> np.ndarray:
    """Levin et al.'s optimisation with the measured pixels fixed (:func:`colorization_system`),
    solved directly on the pixel grid (:class:`~fusion_depth.data.stencil_lu.StencilLU`, float32
    factors) and refined in float64 until :func:`colorization_error_bound` proves every pixel
    within a tenth of :data:`FILL_TOLERANCE_M` of the exact solution; where it cannot, by
    SuperLU's float64 factorisation of the system (:func:`_fill_colorization_float64`)."""
    scale = float(depth[known].max())
    coefficients = _grid_coefficients(known, gray)
    rhs = np.where(known, depth.astype(np.float64) / scale, 0.0)
    try:
        factors = StencilLU(coefficients)
    except ValueError:  # a front singular in float32: a nearly cut-off region
        return _fill_colorization_float64(depth, known, gray, coefficients, rhs)
    bound = colorization_error_bound(factors, coefficients, known)
    solution = np.zeros(depth.shape)
    residual, previous = rhs, np.inf
    for _ in range(_MAX_REFINEMENTS):
        solution += factors.solve(residual)
        solution[known] = rhs[known]
        residual = rhs - stencil_apply(coefficients, solution)
        size = float(np.abs(residual).max())
        if bound(size, float(np.abs(solution).max())) * scale <= FILL_TOLERANCE_M / 10:
            return solution * scale
        if not size < 0.5 * previous:  # stalled at rounding, or diverging
            break
        previous = size
    return _fill_colorization_float64(depth, known, gray, coefficients, rhs)


def colorization_error_bound(
    factors: StencilLU, coefficients: np.ndarray, known: np.ndarray
) -> Callable[[float, float], float]:
    """A proven bound on the colorization fill's error, from the largest residual.

    For a matrix ``A`` with no positive entry off its diagonal (the system in the missing
    pixels: each row ``x_i - sum_j w_ij x_j``, ``w >= 0``), a vector ``z > 0`` with
    ``A z >= c > 0`` in every row proves ``A`` a nonsingular M-matrix, so ``A^-1 >= 0`` entrywise
    and ``A^-1 1 <= z / c`` (Berman & Plemmons, "Nonnegative Matrices in the Mathematical
    Sciences", 1994, ch. 6, condition I27; Varga, "Matrix Iterative Analysis", 2000, sec. 3.5).
    The error of an approximate solution with residual ``r = b - A x`` is ``A^-1 r``, so no
    pixel is off by more than ``max|r| * max(z) / c``. ``z`` is the factors' solve of ``A z = 1``,
    refined until ``c >= 1/2``; ``A z`` and ``r`` are computed in float64, and their rounding
    (under 1e-14 of the largest value in a row's terms) is added to both.

    Args:
        factors: the factorised operator of :func:`_grid_coefficients` (or any object with
            the same ``solve``, as the SuperLU fallback's).
        coefficients: (9, H, W), that operator.
        known: bool (H, W), the measured pixels (identity rows; at least one missing pixel).

    Returns:
        ``bound(max|r|, max|x|)``: the largest possible error of any pixel, in units of the
        largest measured depth (``inf`` where no such ``z`` is found: nothing is proved).
    """
    ones = np.where(known, 0.0, 1.0)
    z = np.zeros(known.shape)
    residual = ones
    for _ in range(3):
        z += factors.solve(residual)
        z[known] = 0.0
        image = stencil_apply(coefficients, z)
        residual = ones - image
        largest, lowest = float(z[~known].max()), float(z[~known].min())
        smallest = float(image[~known].min()) - _ROUNDING * max(1.0, largest)
        if lowest > 0 and smallest >= 0.5:
            return lambda size, magnitude: (
                (size + _ROUNDING * max(1.0, magnitude)) * largest / smallest
            )
    return lambda size, magnitude: np.inf


class _SuperLUOnGrid:
    """SuperLU's float64 factors of :func:`colorization_system`, solving the whole grid's system
    as :meth:`StencilLU.solve` does (measured pixels: identity rows)."""

    def __init__(self, coefficients: np.ndarray, depth: np.ndarray, known: np.ndarray, gray):
        transposed, _, _, self.unknowns = colorization_system(depth, known, gray)
        self.factors = _factorise(transposed)
        self.coefficients, self.known = coefficients, known

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        fixed = np.where(self.known, rhs, 0.0)
        moved = (rhs - stencil_apply(self.coefficients, fixed)).ravel()  # b_u - A_uk x_k
        solution = fixed.ravel()
        solution[self.unknowns] = self.factors.solve(moved[self.unknowns], trans="T")
        return solution.reshape(rhs.shape)


def _fill_colorization_float64(
    depth: np.ndarray,
    known: np.ndarray,
    gray: np.ndarray,
    coefficients: np.ndarray,
    rhs: np.ndarray,
) -> np.ndarray:
    """The fill by SuperLU's float64 factorisation of :func:`colorization_system`, for systems
    the float32 grid factors cannot solve to the tolerance (3-4x their time). Its error is
    bounded the same way (:func:`colorization_error_bound`); a frame whose system is too
    ill-conditioned for even that to prove :data:`FILL_TOLERANCE_M` is filled all the same,
    with a warning naming the bound."""
    scale = float(depth[known].max())
    factors = _SuperLUOnGrid(coefficients, depth, known, gray)
    solution = factors.solve(rhs)
    residual = rhs - stencil_apply(coefficients, solution)
    proven = colorization_error_bound(factors, coefficients, known)(
        float(np.abs(residual).max()), float(np.abs(solution).max())
    )
    if not proven * scale <= FILL_TOLERANCE_M:
        log.warning(
            "colorization: the fill could not be proven within %g m of the exact solution "
            "(bound %.3g m): the frame's system is too ill-conditioned",
            FILL_TOLERANCE_M,
            proven * scale,
        )
    return solution * scale


def _grid_coefficients(known: np.ndarray, gray: np.ndarray) -> np.ndarray:
    """The colorization operator on the whole grid as :class:`StencilLU` takes it: (9, H, W),
    each missing pixel's row ``x_i - sum_j w_ij x_j`` (:func:`_neighbour_weights`), each
    measured pixel's row the identity, so ``A x = b`` with ``b`` the measured depths (0
    elsewhere) is :func:`colorization_system` with the measured pixels kept as unknowns."""
    weights, _ = _neighbour_weights(gray)
    coefficients = np.empty((9, *known.shape))
    coefficients[CENTRE] = 1.0
    coefficients[_NEIGHBOUR_SLOTS] = np.where(known, 0.0, -weights)
    return coefficients


def _factorise(transposed: csc_matrix) -> SuperLU:
    """SuperLU of ``transposed`` (``A`` transposed, solve with ``trans="T"``) in its own order.

    The system is a nonsingular M-matrix (every weight is positive, each pixel's neighbour
    weights sum to 1, and each region of missing pixels borders a measured one), so LU needs
    no pivoting: every pivot of every symmetric reordering is positive and the factors cannot
    grow. That lets SuperLU keep the nested-dissection order, which is what makes it fast.
    """
    from scipy.sparse.linalg import splu

    return splu(
        transposed,
        permc_spec="NATURAL",
        diag_pivot_thresh=0.0,
        options={"SymmetricMode": True},
    )


def colorization_system(
    depth: np.ndarray, known: np.ndarray, gray: np.ndarray
) -> tuple[csc_matrix, np.ndarray, float, np.ndarray]:
    """Levin et al.'s linear system in the missing pixels, in nested-dissection order.

    Each missing pixel ``i`` must equal the weighted mean of its 3x3 neighbours,
    ``x_i - sum_j w_ij x_j = 0`` with ``w_ij ~ exp(-(I_i - I_j)^2 / sigma_i)`` summing to 1
    (Levin, Lischinski & Weiss 2004, eq. 1-2; the NYU toolbox's ``fill_depth_colorization.m``).
    Known neighbours move to the right-hand side, which leaves a sparse system ``A x = b`` in
    the missing pixels only. (The toolbox keeps every pixel as an unknown and pulls the
    measured ones to their value with a penalty weight; fixing them is that weight's limit,
    gives a smaller system, and keeps the measurements exactly.)

    The unknowns are numbered in :func:`nested_dissection_order`, so a factorisation in that
    order fills in little.

    Args:
        depth: float (H, W) metres, 0 where ``known`` is False.
        known: bool (H, W), the measured pixels (at least one).
        gray: float (H, W) intensity in [0, 1] (:func:`_intensity`).

    Returns:
        ``A`` transposed, as an (N, N) CSC matrix (the same arrays as ``A`` in CSR, so nothing
        is converted; solve with ``trans="T"``), N the number of missing pixels, at most 9
        entries a column; ``b`` (N,), the depths over their maximum, so the system is solved
        in [0, 1] as the toolbox does; that maximum, the scale of the solution; and the flat
        (row-major) pixel index of each unknown, (N,) int64.
    """
    from scipy.sparse import csc_matrix

    h, w = depth.shape
    n = h * w
    weights, valid = _neighbour_weights(gray)  # (8, H, W) each
    scale = float(depth[known].max())
    values = np.where(known, depth.astype(np.float64) / scale, 0.0).ravel()
    known_flat = known.ravel()
    order = nested_dissection_order(h, w)
    unknowns = order[~known_flat[order]]
    count = len(unknowns)
    number = np.full(n, -1, dtype=np.int64)  # the unknown's number of each missing pixel
    number[unknowns] = np.arange(count)
    exists = valid.reshape(8, n).T[unknowns]  # (N, 8): the neighbour lies inside the image
    neighbour = np.where(exists, unknowns[:, None] + _flat_offsets(w), 0)
    weight = np.where(exists, weights.reshape(8, n).T[unknowns], 0.0)
    fixed = exists & known_flat[neighbour]
    rhs = (weight * np.where(fixed, values[neighbour], 0.0)).sum(1)
    # Each row: the pixel itself (1), then its missing neighbours (-w).
    keep = np.concatenate([np.ones((count, 1), dtype=bool), exists & ~fixed], axis=1)
    columns = np.concatenate([np.arange(count)[:, None], number[neighbour]], axis=1)
    entries = np.concatenate([np.ones((count, 1)), -weight], axis=1)
    indptr = np.zeros(count + 1, dtype=np.int64)
    np.cumsum(keep.sum(1), out=indptr[1:])
    transposed = csc_matrix((entries[keep], columns[keep], indptr), shape=(count, count))
    return transposed, rhs, scale, unknowns


def _flat_offsets(width: int) -> np.ndarray:
    """The row-major index offset of each of :data:`_OFFSETS` in an image ``width`` wide."""
    return np.array([dy * width + dx for dy, dx in _OFFSETS])


@functools.lru_cache(maxsize=8)
def nested_dissection_order(height: int, width: int) -> np.ndarray:
    """The pixels of a (height, width) grid in geometric nested-dissection order.

    The grid is cut in two across its longer side by one row or column of pixels, which no
    3x3 neighbourhood crosses; each half is ordered the same way, first one half, then the
    other, then the cut. Eliminating in this order confines fill-in to the cuts, so an LU
    factorisation of a 3x3-stencil system on N pixels costs O(N^1.5) operations and
    O(N log N) memory (George 1973, "Nested dissection of a regular finite element mesh").

    Returns:
        (height * width,) int64, read-only: flat (row-major) pixel indices, each once.
    """
    grid = np.arange(height * width, dtype=np.int64).reshape(height, width)
    parts: list[np.ndarray] = []
    boxes = [(0, height, 0, width, False)]  # (rows, cols, emitted): a stack, depth first
    while boxes:
        top, bottom, left, right, is_cut = boxes.pop()
        rows, cols = bottom - top, right - left
        if is_cut or rows * cols <= _LEAF_PIXELS or min(rows, cols) < 3:
            box = grid[top:bottom, left:right]
            # Along the longer side, so a thin strip is eliminated as a band (a 2xW image
            # numbered row by row would fill in a whole row).
            parts.append(box.T.ravel() if cols > rows else box.ravel())
        elif rows >= cols:
            middle = (top + bottom) // 2  # popped last to first: first half, second, the cut
            boxes += [
                (middle, middle + 1, left, right, True),
                (middle + 1, bottom, left, right, False),
                (top, middle, left, right, False),
            ]
        else:
            middle = (left + right) // 2
            boxes += [
                (top, bottom, middle, middle + 1, True),
                (top, bottom, middle + 1, right, False),
                (top, bottom, left, middle, False),
            ]
    order = np.concatenate(parts)
    order.flags.writeable = False
    return order


def _neighbour_weights(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised affinities of every pixel to its 8 neighbours and which neighbours exist.

    One neighbour at a time, so that no (8, H, W) temporary is made beyond the result: at
    KITTI's size each is 30 MB of memory the kernel would map afresh on a worker's first frame.
    """
    h, w = gray.shape
    padded = np.pad(gray, 1)  # outside neighbours are 0, and do not count
    inside = np.pad(np.ones((h, w), dtype=bool), 1)

    def neighbour(array: np.ndarray, k: int) -> np.ndarray:
        dy, dx = _OFFSETS[k]
        return array[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]

    valid = np.stack([neighbour(inside, k) for k in range(8)])
    # The 3x3 window's mean and variance, the pixel itself included, over the pixels that exist.
    count = valid.sum(0) + 1
    total = np.zeros((h, w))
    for k in range(8):
        total += neighbour(padded, k)
    mean = (total + gray) / count
    spread = np.zeros((h, w))
    closest = np.full((h, w), np.inf)
    for k in range(8):
        spread += (neighbour(padded, k) - mean) ** 2 * valid[k]
        squared = np.where(valid[k], (neighbour(padded, k) - gray) ** 2, np.inf)
        closest = np.minimum(closest, squared)
    variance = (spread + (gray - mean) ** 2) / count
    sigma = np.maximum(_VARIANCE_FACTOR * variance, closest / -np.log(_MIN_NEIGHBOUR_WEIGHT))
    sigma = np.maximum(sigma, _MIN_SIGMA)
    weights = np.empty((8, h, w))
    norm = np.zeros((h, w))
    for k in range(8):
        diff2 = np.where(valid[k], (neighbour(padded, k) - gray) ** 2, 0.0)
        weights[k] = np.where(valid[k], np.exp(-diff2 / sigma), 0.0)
        norm += weights[k]
    weights /= norm
    return weights, valid
