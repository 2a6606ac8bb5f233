"""The grid solver: its nested-dissection plan, and its solves of random M-matrices against
their known solutions (the operator itself checked against a dense matrix)."""

from __future__ import annotations

import numpy as np
import pytest

from fusion_depth.data.stencil_lu import (
    CENTRE,
    STENCIL,
    StencilLU,
    _plan,
    stencil_apply,
)


def _m_matrix(h: int, w: int, seed: int, leak: float = 0.05) -> np.ndarray:
    """A random 3x3-stencil M-matrix: nonnegative neighbour weights summing to 1 - leak."""
    rng = np.random.default_rng(seed)
    weights = rng.random((9, h, w))
    weights[CENTRE] = 0.0
    rows, cols = np.mgrid[0:h, 0:w]
    for k, (dy, dx) in enumerate(STENCIL):
        outside = (rows + dy < 0) | (rows + dy >= h) | (cols + dx < 0) | (cols + dx >= w)
        weights[k][outside] = 0.0
    total = weights.sum(0)
    weights = np.divide(weights, total, out=np.zeros_like(weights), where=total > 0)
    coefficients = -(1.0 - leak) * weights
    coefficients[CENTRE] = 1.0
    return coefficients


def _dense(coefficients: np.ndarray) -> np.ndarray:
    _, h, w = coefficients.shape
    matrix = np.zeros((h * w, h * w))
    for k, (dy, dx) in enumerate(STENCIL):
        for y in range(h):
            for x in range(w):
                if 0 <= y + dy < h and 0 <= x + dx < w:
                    matrix[y * w + x, (y + dy) * w + x + dx] += coefficients[k, y, x]
    return matrix


@pytest.mark.parametrize(
    "shape",
    [(1, 1), (1, 9), (9, 1), (2, 2), (3, 5), (4, 4), (7, 9), (16, 17), (30, 40), (2, 70), (26, 18)],
)
def test_a_solve_matches_dense_lapack_to_float32_and_refines_to_float64(shape) -> None:
    coefficients = _m_matrix(*shape, seed=sum(shape))
    truth = np.random.default_rng(1).random(shape)
    rhs = stencil_apply(coefficients, truth)
    np.testing.assert_allclose(
        _dense(coefficients) @ truth.ravel(), rhs.ravel(), rtol=0, atol=1e-12
    )  # stencil_apply is the operator
    factors = StencilLU(coefficients)
    solution = factors.solve(rhs)
    assert solution.dtype == np.float64 and solution.shape == shape
    assert np.abs(solution - truth).max() < 1e-5
    for _ in range(3):
        solution += factors.solve(rhs - stencil_apply(coefficients, solution))
    assert np.abs(solution - truth).max() < 1e-12


@pytest.mark.parametrize("shape", [(1, 1), (5, 31), (31, 5), (63, 95), (64, 96), (375, 1242)])
def test_every_pixel_is_eliminated_once_in_the_plan(shape) -> None:
    """Odd sides are cut by one row or column, even ones by two: every pixel is eliminated
    exactly once, with no padding, whatever the sides."""
    h, w = shape
    levels = _plan(h, w)
    eliminated = np.concatenate([group.cut.ravel() for level in levels for group in level])
    np.testing.assert_array_equal(np.sort(eliminated), np.arange(h * w))
    assert len(levels[-1]) == 1 and levels[-1][0].ring.shape[1] == 0  # the root: no ring
    for level in levels:
        for group in level:  # a ring pixel is eliminated later: never in its own box's cut
            assert not np.intersect1d(group.cut, group.ring).size


def test_a_singular_operator_is_refused_by_name() -> None:
    coefficients = _m_matrix(6, 7, seed=3)
    coefficients[:, 2, 3] = 0.0  # a pixel whose row is all zero
    with pytest.raises(ValueError, match="singular"):
        StencilLU(coefficients)


def test_coefficients_of_the_wrong_shape_are_refused() -> None:
    with pytest.raises(ValueError, match=r"expected \(9, H, W\), got \(8, 4, 4\)"):
        StencilLU(np.zeros((8, 4, 4)))


def test_negligible_entries_do_not_change_the_refined_solution() -> None:
    """Weights of about 1e-26 (dropped from the factors, as subnormal-prone) still count in the
    operator the refinement uses: the refined solution solves the exact system."""
    coefficients = _m_matrix(20, 24, seed=5)
    coefficients[1, 5:15, :] *= 1e-25  # vertical links nearly cut in a band
    coefficients[7, 5:15, :] *= 1e-25
    coefficients[CENTRE] = 1.0
    truth = np.random.default_rng(2).random((20, 24))
    rhs = stencil_apply(coefficients, truth)
    factors = StencilLU(coefficients)
    solution = factors.solve(rhs)
    for _ in range(3):
        solution += factors.solve(rhs - stencil_apply(coefficients, solution))
    assert np.abs(solution - truth).max() < 1e-12
