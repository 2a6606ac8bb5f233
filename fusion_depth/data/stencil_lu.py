"""A direct solver for 3x3-stencil linear systems on a pixel grid.

Every row of the system belongs to a pixel and couples it to its 3x3 neighbourhood, as Levin et
al.'s colorization fill does (:mod:`fusion_depth.data.filling`). The grid is cut by geometric
nested dissection (George 1973, "Nested dissection of a regular finite element mesh"): one row
or column of pixels, which no 3x3 neighbourhood crosses, splits a box into two halves, and each
half is cut the same way. The LU factors are computed by the multifrontal method (Duff & Reid
1983, "The multifrontal solution of indefinite sparse symmetric linear equations"; Liu 1992,
"The multifrontal method for sparse matrix solution: theory and practice"): each box's cut is
eliminated in a small dense matrix, its *front*, which holds the cut and the ring of pixels
around the box, and passes the Schur complement on that ring to its parent's front.

The grid is padded (with identity rows that touch nothing) to a size whose halves are equal at
every cut (:func:`padded_size`), so that all boxes of one level have the same shape and,
grouped by which sides touch the grid's border, the same front layout: each level is then a
few batched dense operations (NumPy's ``inv`` and ``matmul`` over stacks of fronts) instead of
one sparse operation per pixel. The top fronts, which hold most of the arithmetic, run as
dense matrix products at BLAS speed.

Pivoting is not needed, nor done, for the systems this is for: nonsingular M-matrices, whose
every principal submatrix is a nonsingular M-matrix, so each front's cut block is invertible and
its inverse is nonnegative.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

# The 3x3 neighbourhood, row-major: offset k of pixel (y, x) is (y + dy, x + dx); the centre is
# k = 4 and the opposite of k is 8 - k.
STENCIL: tuple[tuple[int, int], ...] = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1))
CENTRE = 4
# A box of at most this many pixels is not cut: its front eliminates it whole.
_LEAF_PIXELS = 24
# Fronts are eliminated in chunks of about this many floats (512 kB), which stay in cache.
_CHUNK_FLOATS = 1 << 17
# Entries of the operator, of the cut blocks' inverses and of the updates smaller than this are
# dropped: far below float32's precision next to the operator's O(1) entries (refinement
# against the exact operator makes up the difference). Products of three of the rest are
# normal floats, never subnormal ones, which x86 multiplies 10-100x slower.
_NEGLIGIBLE = 1e-10


# The padding ends its halving on a side of at most this many pixels (see padded_size).
_MAX_LEAF_SIDE = 15


def padded_size(n: int) -> int:
    """The smallest ``m >= n`` of the form ``(a + 1) 2^k - 1`` with ``1 <= a <= 15``: a side
    that halves around one-pixel cuts, the cheapest, down to ``a`` pixels (an even ``a`` is
    then cut by two). The grid is padded to it with rows that touch nothing: 5 % more pixels
    at KITTI's 375x1242 (383x1279), 11 % at nuScenes' 448x800 (479x831); two-pixel cuts at
    every level instead took about 20 % longer at KITTI's size."""
    if n < 1:
        raise ValueError(f"grid side: expected at least 1 pixel, got {n}")
    best = n if n <= _MAX_LEAF_SIDE else None
    for side in range(1, _MAX_LEAF_SIDE + 1):
        m = side
        while m < n:
            m = 2 * m + 1
        best = m if best is None else min(best, m)
    return best


def _cut_width(side: int) -> int:
    """The width of the cut across a box side: 1 pixel for an odd side, 2 for an even one,
    so that the two halves are always equal (0: the side is too short to cut)."""
    return 0 if side < 3 else 1 if side % 2 else 2


@dataclass(frozen=True)
class _Group:
    """The boxes of one level whose sides touch the same borders of the grid: one front
    layout, ``s`` pixels eliminated (the cut, or the whole box at a leaf) and ``g`` ring
    pixels left for the ancestors."""

    cut: np.ndarray  # (nb, s) flat grid index of each eliminated pixel
    ring: np.ndarray  # (nb, g) flat grid index of each ring pixel
    entry_at: np.ndarray  # (e,) flat position in the (s + g)^2 front of each original entry
    entry_from: np.ndarray  # (nb, e) flat index into the (9, H * W) coefficients
    # For each half: its group on the level below, its positions in that group (None: all
    # of it, in order) and where its ring lies in this front, as runs (_runs).
    children: tuple[tuple[int, np.ndarray | None, tuple[tuple[slice, slice], ...]], ...]


@functools.lru_cache(maxsize=8)
def _box_shapes(height: int, width: int) -> list[tuple]:
    """The levels of :func:`_plan`'s tree, top-down: for each, its boxes' (height, width),
    how they are cut (``"rows"``, ``"cols"``, or None for the leaves), the cut's width in
    pixels, and the row and column origins of the level's boxes."""
    shapes = []
    h, w = height, width
    row_origins, col_origins = np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64)
    while True:
        rows_cut, cols_cut = _cut_width(h), _cut_width(w)
        if h * w <= _LEAF_PIXELS or not (rows_cut or cols_cut):
            shapes.append((h, w, None, 0, row_origins, col_origins))
            return shapes
        split = "rows" if rows_cut and (h >= w or not cols_cut) else "cols"
        width_of_cut = rows_cut if split == "rows" else cols_cut
        shapes.append((h, w, split, width_of_cut, row_origins, col_origins))
        if split == "rows":
            h = (h - width_of_cut) // 2
            row_origins = np.concatenate([row_origins, row_origins + h + width_of_cut])
            row_origins.sort()
        else:
            w = (w - width_of_cut) // 2
            col_origins = np.concatenate([col_origins, col_origins + w + width_of_cut])
            col_origins.sort()


def _plan(height: int, width: int) -> tuple[tuple[_Group, ...], ...]:
    """The nested-dissection tree of a (height, width) grid, leaves first: for each level,
    its groups of boxes with the same front layout.

    Every box of a level has the same shape: a box is cut across its longer side (if it can
    be) through the middle, by one row or column of pixels if that side is odd, two if it is
    even, so both halves are equal. Boxes of at most :data:`_LEAF_PIXELS` pixels, or too thin
    to cut, are leaves."""
    levels: list[tuple[_Group, ...]] = []
    below: dict | None = None  # the level below: each lattice cell's group and position
    for h, w, split, width_of_cut, row_origins, col_origins in reversed(_box_shapes(height, width)):
        i, j = np.meshgrid(np.arange(len(row_origins)), np.arange(len(col_origins)), indexing="ij")
        # Which borders of the grid each box touches: top, bottom, left, right.
        sides = np.stack([i == 0, i == i.max(), j == 0, j == j.max()])
        code = (sides * np.array([8, 4, 2, 1])[:, None, None]).sum(0)
        group_of = np.zeros_like(code)
        position = np.zeros_like(code)
        groups, rings = [], {}
        for number, value in enumerate(np.unique(code)):
            chosen = code == value
            group_of[chosen] = number
            position[chosen] = np.arange(chosen.sum())
            key = tuple(bool(side) for side in sides[:, chosen][:, 0])
            cells = np.argwhere(chosen)  # row-major
            cut_local, ring_local = _layout(h, w, split, width_of_cut, key)
            front = {pixel: k for k, pixel in enumerate(cut_local + ring_local)}
            size = len(front)
            at, offset, source = [], [], []
            cut_set = set(cut_local)
            for y, x in cut_local:
                for k, (dy, dx) in enumerate(STENCIL):
                    q = (y + dy, x + dx)
                    if q not in front:
                        continue  # inside a child box: assembled in that child's front
                    at.append(front[(y, x)] * size + front[q])
                    offset.append(k)
                    source.append((y, x))
                    if q not in cut_set:  # a ring pixel's row, its column on the cut
                        at.append(front[q] * size + front[(y, x)])
                        offset.append(8 - k)
                        source.append(q)
            origin = row_origins[cells[:, 0]] * width + col_origins[cells[:, 1]]
            local = np.array([y * width + x for y, x in source], dtype=np.int64)
            entry_from = (np.array(offset, dtype=np.int64) * height * width + local)[
                None, :
            ] + origin[:, None]
            cut = origin[:, None] + np.array([y * width + x for y, x in cut_local])[None, :]
            ring = origin[:, None] + np.array(
                [y * width + x for y, x in ring_local], dtype=np.int64
            ).reshape(1, -1)
            children = ()
            if split is not None:
                children = _children(h, w, split, width_of_cut, key, cells, front, below)
            groups.append(
                _Group(cut, ring.reshape(len(cells), -1), np.array(at), entry_from, children)
            )
            rings[key] = ring_local
        levels.append(tuple(groups))
        sizes = np.bincount(group_of.ravel())
        below = {"group": group_of, "position": position, "rings": rings, "sizes": sizes}
    return tuple(levels)


def _layout(
    h: int, w: int, split: str | None, width_of_cut: int, key: tuple[bool, bool, bool, bool]
) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """A box's eliminated pixels and ring pixels (box coordinates), the ring without the
    sides that lie on the grid's border (``key``: top, bottom, left, right)."""
    if split is None:
        cut = [(y, x) for y in range(h) for x in range(w)]
    elif split == "rows":
        first = (h - width_of_cut) // 2
        cut = [(y, x) for y in range(first, first + width_of_cut) for x in range(w)]
    else:
        first = (w - width_of_cut) // 2  # column by column: each half's ring meets one
        cut = [(y, x) for x in range(first, first + width_of_cut) for y in range(h)]
    top, bottom, left, right = key
    # Around the box, counter-clockwise from the top-left corner: each half of a cut box then
    # meets its parent's front in a few runs of consecutive pixels (see _runs).
    loop = (
        [(y, -1) for y in range(-1, h + 1)]
        + [(h, x) for x in range(w)]
        + [(y, w) for y in range(h, -2, -1)]
        + [(-1, x) for x in range(w - 1, -1, -1)]
    )
    ring = [
        (y, x)
        for y, x in loop
        if not (y == -1 and top or y == h and bottom or x == -1 and left or x == w and right)
    ]
    return cut, ring


def _children(
    h: int,
    w: int,
    split: str,
    width_of_cut: int,
    key: tuple[bool, bool, bool, bool],
    cells: np.ndarray,
    front: dict,
    below: dict,
) -> tuple[tuple[int, np.ndarray | None, tuple[tuple[slice, slice], ...]], ...]:
    """For a group of boxes cut along ``split``: each half's group on the level below, the
    halves' positions in it, and where each of its ring pixels sits in this front."""
    top, bottom, left, right = key
    out = []
    for half in (0, 1):
        if split == "rows":
            shift = (half * ((h - width_of_cut) // 2 + width_of_cut), 0)
            child_key = (top and half == 0, bottom and half == 1, left, right)
            rows, cols = 2 * cells[:, 0] + half, cells[:, 1]
        else:
            shift = (0, half * ((w - width_of_cut) // 2 + width_of_cut))
            child_key = (top, bottom, left and half == 0, right and half == 1)
            rows, cols = cells[:, 0], 2 * cells[:, 1] + half
        group = int(below["group"][rows[0], cols[0]])
        positions = below["position"][rows, cols]
        into = [front[(y + shift[0], x + shift[1])] for y, x in below["rings"][child_key]]
        same = below["sizes"][group] == len(positions) and np.array_equal(
            positions, np.arange(len(positions))
        )
        out.append((group, None if same else positions, _runs(into)))
    return tuple(out)


def _runs(into: list[int]) -> tuple[tuple[slice, slice], ...]:
    """``into`` (where each child ring pixel sits in the parent's front) as runs of pixels
    that are consecutive in both: (child slice, parent slice) pairs, the parent's possibly
    reversed. Adding the child's update run by run is a few block copies instead of a
    scatter of every entry."""
    runs, start = [], 0
    for end in range(1, len(into) + 1):
        step = into[start + 1] - into[start] if end - start >= 2 else 0
        if end < len(into) and end - start == 1 and abs(into[end] - into[start]) == 1:
            continue
        if end < len(into) and step and into[end] - into[end - 1] == step:
            continue
        first, last, step = into[start], into[end - 1], step or 1
        stop = last + step if last + step >= 0 else None
        runs.append((slice(start, end), slice(first, stop, step)))
        start = end
    return tuple(runs)


class StencilLU:
    """LU factors of a 3x3-stencil operator on an (H, W) grid, in float32.

    Args:
        coefficients: (9, H, W) float: ``coefficients[k, y, x]`` is row (y, x)'s coefficient
            of pixel ``(y, x) + STENCIL[k]`` (0 where that pixel is outside the grid). The
            operator must be a nonsingular M-matrix (positive diagonal, nonpositive
            neighbours, every pixel linked to a row with a positive row sum).

    Raises:
        ValueError: ``coefficients`` is not (9, H, W), or a front's cut block is singular
            (the operator is not a nonsingular M-matrix).
    """

    def __init__(self, coefficients: np.ndarray) -> None:
        coefficients = np.asarray(coefficients)
        if coefficients.ndim != 3 or coefficients.shape[0] != 9:
            raise ValueError(f"coefficients: expected (9, H, W), got {coefficients.shape}")
        _, self.height, self.width = coefficients.shape
        hp, wp = padded_size(self.height), padded_size(self.width)
        self._padded = (hp, wp)
        grid = np.zeros((9, hp, wp), dtype=np.float32)
        grid[CENTRE] = 1.0  # padding: identity rows that touch nothing
        grid[:, : self.height, : self.width] = coefficients
        flat = _drop_negligible(grid.reshape(-1))
        # Per level, leaves first, per group: (group, the cut block's inverse, the ring's rows
        # on the cut, the inverse times the cut's rows on the ring).
        self._levels: list[list[tuple[_Group, np.ndarray, np.ndarray, np.ndarray]]] = []
        updates: list[np.ndarray] = []
        for groups in _plan(hp, wp):
            factors, level_updates = [], []
            for group in groups:
                factors.append(_eliminate(group, flat, updates))
                level_updates.append(factors[-1][-1])
            self._levels.append([factor[:4] for factor in factors])
            updates = level_updates

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``x`` with ``A x = rhs`` to float32 precision (refine in float64 for more).

        Args:
            rhs: (H, W) float.

        Returns:
            (H, W) float64.
        """
        hp, wp = self._padded
        values = np.zeros((hp, wp), dtype=np.float32)
        values[: self.height, : self.width] = rhs
        values = values.reshape(-1)
        for level in self._levels:  # forward, leaves first
            for group, inverse, ring_rows, _ in level:
                cut = np.matmul(inverse, values[group.cut][:, :, None])
                values[group.cut] = cut[:, :, 0]
                if group.ring.shape[1]:
                    np.subtract.at(values, group.ring, np.matmul(ring_rows, cut)[:, :, 0])
        for level in reversed(self._levels):  # backward, root first
            for group, _, _, solved in level:
                if group.ring.shape[1]:
                    ring = values[group.ring][:, :, None]
                    values[group.cut] -= np.matmul(solved, ring)[:, :, 0]
        return values.reshape(hp, wp)[: self.height, : self.width].astype(np.float64)


def _eliminate(
    group: _Group, flat: np.ndarray, updates: list[np.ndarray]
) -> tuple[_Group, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eliminates the cuts of ``group``'s boxes: their fronts assembled from the operator
    (``flat``) and the children's ``updates`` (the level below's, one array per group).

    The boxes are taken a chunk at a time (:data:`_CHUNK_FLOATS` of fronts), so that each
    chunk's fronts stay in the CPU's cache through the assembly, the inverse and the
    products, and the memory for them is reused, not mapped afresh for every level.

    Returns:
        (group, the cut blocks' inverses (nb, s, s), the ring's rows on the cut (nb, g, s),
        the inverses times the cut's rows on the ring (nb, s, g), the Schur complements on the
        rings (nb, g, g)), float32.

    Raises:
        ValueError: a cut block is singular.
    """
    nb, s = group.cut.shape
    g = group.ring.shape[1]
    size = s + g
    inverse = np.empty((nb, s, s), dtype=np.float32)
    ring_rows = np.empty((nb, g, s), dtype=np.float32)
    solved = np.empty((nb, s, g), dtype=np.float32)
    update = np.empty((nb, g, g), dtype=np.float32)
    step = max(1, min(nb, _CHUNK_FLOATS // (size * size)))
    buffer = np.empty((step, size * size), dtype=np.float32)
    for first in range(0, nb, step):
        boxes = slice(first, min(first + step, nb))
        count = boxes.stop - first
        front = buffer[:count]
        front.fill(0.0)
        front[:, group.entry_at] = flat[group.entry_from[boxes]]
        front3 = front.reshape(count, size, size)
        for child, positions, runs in group.children:
            picked = updates[child][boxes if positions is None else positions[boxes]]
            for rows_from, rows_to in runs:
                for cols_from, cols_to in runs:
                    front3[:, rows_to, cols_to] += picked[:, rows_from, cols_from]
        try:
            inverse[boxes] = _drop_negligible(np.linalg.inv(front3[:, :s, :s]))
        except np.linalg.LinAlgError:
            raise ValueError(
                "coefficients: a front is singular; expected a nonsingular M-matrix"
            ) from None
        np.matmul(inverse[boxes], front3[:, :s, s:], out=solved[boxes])
        ring_rows[boxes] = front3[:, s:, :s]
        schur = front3[:, s:, s:]  # the Schur complement on the ring, in place
        schur -= ring_rows[boxes] @ solved[boxes]
        update[boxes] = _drop_negligible(schur)
    return group, inverse, ring_rows, solved, update


def _drop_negligible(array: np.ndarray) -> np.ndarray:
    """``array`` with its entries of magnitude below :data:`_NEGLIGIBLE` set to 0, in place."""
    array[np.abs(array) < _NEGLIGIBLE] = 0.0
    return array


def stencil_apply(coefficients: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``A x`` for the operator of :class:`StencilLU`, in float64.

    Args:
        coefficients: (9, H, W), as :class:`StencilLU` takes them.
        values: (H, W).

    Returns:
        (H, W) float64.
    """
    h, w = values.shape
    padded = np.pad(np.asarray(values, dtype=np.float64), 1)
    out = np.zeros((h, w))
    for k, (dy, dx) in enumerate(STENCIL):
        out += coefficients[k] * padded[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
    return out
