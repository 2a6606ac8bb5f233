"""Ground-truth filling: every measured value survives; holes fill as each method says."""

from __future__ import annotations

import numpy as np
import pytest

from fusion_depth.data.filling import FILL_METHODS, fill_depth

H, W = 30, 40


def _plane(h: int = H, w: int = W) -> np.ndarray:
    rows, cols = np.mgrid[0:h, 0:w]
    return (4.0 + 0.25 * rows + 0.125 * cols).astype(np.float32)


def _random_sparse(seed: int, density: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    depth = np.where(rng.random((H, W)) < density, rng.uniform(2, 60, (H, W)), 0.0)
    image = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    return depth.astype(np.float32), image


@pytest.mark.parametrize("method", FILL_METHODS)
def test_every_method_keeps_every_measured_value_exactly(method) -> None:
    depth, image = _random_sparse(0)
    filled = fill_depth(depth, image, method)
    assert filled.dtype == np.float32 and filled.shape == (H, W)
    measured = depth > 0
    np.testing.assert_array_equal(filled[measured], depth[measured])
    if method == "none":
        np.testing.assert_array_equal(filled, depth)
    else:  # every hole filled (linear_hull: inside the hull), within the measured range
        assert (filled > 0).all() or method == "linear_hull"
        assert depth[measured].min() - 1e-4 <= filled[filled > 0].min()
        assert filled.max() <= depth[measured].max() + 1e-4


def test_linear_on_a_plane_gives_the_plane() -> None:
    plane = _plane()
    rng = np.random.default_rng(1)
    keep = rng.random((H, W)) < 0.05
    keep[[0, 0, -1, -1], [0, -1, 0, -1]] = True  # the corners: the hull covers the frame
    depth = np.where(keep, plane, 0)
    filled = fill_depth(depth, np.zeros((H, W, 3), np.uint8), "linear")
    np.testing.assert_allclose(filled, plane, atol=1e-4)


def test_linear_fills_outside_the_hull_with_the_nearest_measurement() -> None:
    depth = np.zeros((H, W), np.float32)
    depth[10, 10], depth[10, 20], depth[20, 10] = 5.0, 7.0, 9.0
    filled = fill_depth(depth, np.zeros((H, W, 3), np.uint8), "linear")
    assert filled[0, 0] == 5.0 and filled[0, W - 1] == 7.0 and filled[H - 1, 0] == 9.0
    assert filled[12, 12] == pytest.approx(5.0 + 0.2 * 2 + 0.4 * 2, abs=1e-5)  # inside: plane


def test_linear_with_collinear_points_falls_back_to_nearest() -> None:
    depth = np.zeros((H, W), np.float32)
    depth[5, 5:30:10] = [3.0, 4.0, 5.0]  # one row: no triangle to interpolate in
    filled = fill_depth(depth, np.zeros((H, W, 3), np.uint8), "linear")
    assert filled[20, 5] == 3.0 and filled[20, 25] == 5.0 and (filled > 0).all()


def test_colorization_reproduces_a_plane_under_a_flat_image() -> None:
    """Uniform intensity makes every weight equal: the fill is the discrete harmonic
    interpolant of the measurements, which a plane is when the border is measured."""
    plane = _plane()
    keep = np.zeros((H, W), bool)
    keep[[0, -1], :] = keep[:, [0, -1]] = True
    keep[15, 20] = True
    filled = fill_depth(np.where(keep, plane, 0), np.full((H, W, 3), 128, np.uint8), "colorization")
    np.testing.assert_allclose(filled, plane, atol=1e-4)


def test_colorization_follows_image_edges_and_linear_does_not() -> None:
    """Depth spreads along uniform image regions and stops at an intensity edge."""
    image = np.zeros((H, W, 3), np.uint8)
    image[:, W // 2 :] = 255
    depth = np.zeros((H, W), np.float32)
    depth[::6, 2] = 10.0  # measured only near the left border ...
    depth[::6, W - 3] = 30.0  # ... and near the right border
    color = fill_depth(depth, image, "colorization")
    linear = fill_depth(depth, image, "linear")
    left, right = color[:, 5 : W // 2 - 1], color[:, W // 2 + 1 : W - 5]
    assert np.abs(left - 10.0).max() < 0.5 and np.abs(right - 30.0).max() < 0.5
    assert linear[:, W // 2 - 2].mean() > 15.0  # a blend across the edge


def test_a_map_without_measurements_stays_empty() -> None:
    empty = np.zeros((H, W), np.float32)
    for method in FILL_METHODS:
        assert not fill_depth(empty, np.zeros((H, W, 3), np.uint8), method).any()


def test_a_bad_method_names_the_value_and_the_choices() -> None:
    depth, image = _random_sparse(2)
    with pytest.raises(
        ValueError, match=r"'cubic'.*\['none', 'linear', 'colorization', 'linear_hull'\]"
    ):
        fill_depth(depth, image, "cubic")


def test_an_image_of_another_size_is_refused() -> None:
    depth, _ = _random_sparse(3)
    with pytest.raises(ValueError, match=r"image: expected shape \(30, 40, 3\)"):
        fill_depth(depth, np.zeros((H + 1, W, 3), np.uint8), "linear")


def _reference_colorization(depth: np.ndarray, image: np.ndarray) -> np.ndarray:
    """Levin et al.'s system built pixel by pixel, as the NYU toolbox's loop reads, and solved
    densely: what the vectorised, reordered build and the sparse LU must reproduce."""
    from fusion_depth.data.filling import _OFFSETS, _intensity, _neighbour_weights

    h, w = depth.shape
    weights, valid = _neighbour_weights(_intensity(image))
    known = depth > 0
    scale = float(depth[known].max())
    missing = [(r, c) for r in range(h) for c in range(w) if not known[r, c]]
    number = {pixel: i for i, pixel in enumerate(missing)}
    matrix, rhs = np.eye(len(missing)), np.zeros(len(missing))
    for i, (r, c) in enumerate(missing):
        for k, (dy, dx) in enumerate(_OFFSETS):
            if not valid[k, r, c]:
                continue
            if known[r + dy, c + dx]:
                rhs[i] += weights[k, r, c] * depth[r + dy, c + dx] / scale
            else:
                matrix[i, number[(r + dy, c + dx)]] -= weights[k, r, c]
    filled = depth.astype(np.float64)
    filled[~known] = np.linalg.solve(matrix, rhs) * scale
    return filled


@pytest.mark.parametrize("seed", [4, 5])
def test_colorization_solves_the_system_a_pixel_by_pixel_build_gives(seed) -> None:
    """The grid operator the solver factorises is the toolbox's system (the pixel-by-pixel
    solution leaves no residual in it), and the fill is within its proven millimetre."""
    from fusion_depth.data.filling import _grid_coefficients, _intensity
    from fusion_depth.data.stencil_lu import stencil_apply

    depth, image = _random_sparse(seed, density=0.05)
    reference = _reference_colorization(depth, image)
    known = depth > 0
    scale = float(depth[known].max())
    coefficients = _grid_coefficients(known, _intensity(image))
    rhs = np.where(known, depth.astype(np.float64) / scale, 0.0)
    assert np.abs(stencil_apply(coefficients, reference / scale) - rhs).max() < 1e-12
    np.testing.assert_allclose(fill_depth(depth, image, "colorization"), reference, atol=1e-3)


def test_colorization_agrees_with_a_pivoting_solve_on_a_lidar_frame_within_1_cm() -> None:
    """The promise: the same filled depth as SciPy's default solve (COLAMD order, partial
    pivoting) of the same system, on a generated lidar frame (scan lines, 1.5 % measured)."""
    from fusion_depth.data.filling import colorization_reference
    from fusion_depth.data.procedural import render_frame

    image, _, sparse = render_frame(7, "train", 0, 94, 310, 82.0, "night", "lidar")
    known = sparse > 0
    assert 0.005 < known.mean() < 0.05
    exact = colorization_reference(sparse, image)
    assert np.array_equal(exact[known], sparse[known])
    error = np.abs(fill_depth(sparse, image, "colorization") - exact)
    assert error.max() < 1e-4, f"{error.max() * 100:.2g} cm"  # 1 cm promised; LU gives ~1e-9


@pytest.mark.parametrize("shape", [(1, 7), (3, 3), (40, 60), (61, 47), (9, 300), (2, 300)])
def test_nested_dissection_visits_every_pixel_once_cut_last(shape) -> None:
    from fusion_depth.data.filling import nested_dissection_order

    h, w = shape
    order = nested_dissection_order(h, w)
    np.testing.assert_array_equal(np.sort(order), np.arange(h * w))
    if (h, w) == (40, 60):  # wider than tall: the first cut is column 30, numbered last
        np.testing.assert_array_equal(order[-h:], np.arange(h) * w + 30)
    if (h, w) == (2, 300):  # too thin to cut: numbered along its length, a band
        np.testing.assert_array_equal(order[:4], [0, 300, 1, 301])
    with pytest.raises(ValueError):  # cached, so callers must not change it
        order[0] = 1


def test_colorization_proves_its_tolerance_without_falling_back(monkeypatch) -> None:
    """The float32 grid factors refined in float64 prove the 1 cm on a lidar frame without
    SuperLU's float64 factorisation; where refinement is cut short, the fallback gives the
    same map."""
    from fusion_depth.data import filling
    from fusion_depth.data.procedural import render_frame

    image, _, sparse = render_frame(3, "train", 1, 64, 192, 82.0, "fog", "lidar")
    fallbacks = []
    real = filling._fill_colorization_float64
    monkeypatch.setattr(
        filling, "_fill_colorization_float64", lambda *a: fallbacks.append(1) or real(*a)
    )
    refined = fill_depth(sparse, image, "colorization")
    assert fallbacks == []
    monkeypatch.setattr(filling, "_MAX_REFINEMENTS", 0)
    exact = fill_depth(sparse, image, "colorization")
    assert fallbacks == [1]
    np.testing.assert_allclose(refined, exact, rtol=0, atol=1e-3)


def test_a_grid_factorisation_that_fails_falls_back_to_superlu(monkeypatch) -> None:
    """A front that is singular in float32 (a nearly cut-off region) falls back to SuperLU's
    float64 factors instead of failing the frame."""
    from fusion_depth.data import filling
    from fusion_depth.data.procedural import render_frame

    image, _, sparse = render_frame(3, "train", 1, 64, 192, 82.0, "fog", "lidar")
    expected = fill_depth(sparse, image, "colorization")

    def singular(coefficients):
        raise ValueError("coefficients: a front is singular")

    monkeypatch.setattr(filling, "StencilLU", singular)
    np.testing.assert_allclose(fill_depth(sparse, image, "colorization"), expected, atol=1e-3)


@pytest.mark.parametrize("weather", ["night", "day"])
def test_the_proven_bound_holds_against_the_float64_solve(weather) -> None:
    """The refinement stops on a proof, not a count: the error it bounds from the residual
    (colorization_error_bound) is at least the true error against SciPy's float64 solve, and
    within a tenth of the 1 cm promise."""
    from scipy.sparse.linalg import spsolve

    from fusion_depth.data import filling
    from fusion_depth.data.procedural import render_frame
    from fusion_depth.data.stencil_lu import StencilLU, stencil_apply

    image, _, sparse = render_frame(5, "train", 2, 94, 310, 82.0, weather, "lidar")
    known = sparse > 0
    gray = filling._intensity(image)
    transposed, rhs, scale, unknowns = filling.colorization_system(sparse, known, gray)
    exact = spsolve(transposed.T.tocsc(), rhs)
    coefficients = filling._grid_coefficients(known, gray)
    factors = StencilLU(coefficients)
    bound = filling.colorization_error_bound(factors, coefficients, known)
    grid_rhs = np.where(known, sparse.astype(np.float64) / scale, 0.0)
    solution = factors.solve(grid_rhs)  # one float32 solve: an error worth bounding
    solution[known] = grid_rhs[known]
    residual = np.abs(grid_rhs - stencil_apply(coefficients, solution)).max()
    error = np.abs(solution.ravel()[unknowns] - exact).max()
    assert 1e-9 < error <= bound(residual, 1.0)
    filled = filling._fill_colorization(sparse, known, gray).ravel()[unknowns] / scale
    assert np.abs(filled - exact).max() * scale <= filling.FILL_TOLERANCE_M / 10


def test_the_bound_is_refused_where_no_positive_vector_is_found(monkeypatch) -> None:
    """Factors too poor to give A z >= 1/2 prove nothing: the bound is infinite, so the fill
    falls back to SuperLU rather than trust an unproven map."""
    from fusion_depth.data import filling
    from fusion_depth.data.procedural import render_frame

    image, _, sparse = render_frame(3, "train", 1, 40, 60, 82.0, "fog", "lidar")
    known = sparse > 0
    coefficients = filling._grid_coefficients(known, filling._intensity(image))

    class Useless:
        def solve(self, rhs):
            return np.zeros_like(rhs)

    assert filling.colorization_error_bound(Useless(), coefficients, known)(0.0, 1.0) == np.inf
    monkeypatch.setattr(filling, "colorization_error_bound", lambda *a: lambda *s: np.inf)
    fallbacks = []
    real = filling._fill_colorization_float64
    monkeypatch.setattr(
        filling, "_fill_colorization_float64", lambda *a: fallbacks.append(1) or real(*a)
    )
    fill_depth(sparse, image, "colorization")
    assert fallbacks == [1]


def test_the_bound_proves_nothing_for_a_matrix_that_is_not_an_m_matrix() -> None:
    """The bound does not assume A^-1 >= 0, it proves it: rows x1 - 2 x2 and x2 - 2 x1 have
    no positive entry off the diagonal, but their inverse has negative entries, so the z that
    solves A z = 1 is negative and no bound is claimed (it would be 0: wrong)."""
    from fusion_depth.data import filling
    from fusion_depth.data.stencil_lu import CENTRE, StencilLU

    known = np.array([[True, False, False]])
    coefficients = np.zeros((9, 1, 3))
    coefficients[CENTRE] = 1.0
    coefficients[5, 0, 1] = -2.0  # (0, 1): pixel 1's right neighbour
    coefficients[3, 0, 2] = -2.0  # (0, -1): pixel 2's left neighbour
    bound = filling.colorization_error_bound(StencilLU(coefficients), coefficients, known)
    assert bound(1e-3, 1.0) == np.inf


def test_the_superlu_fallback_is_bounded_too_and_warns_when_it_cannot_be(
    monkeypatch, caplog
) -> None:
    """The fallback solves the same grid system (the same map as the grid solver, within the
    millimetre), bounds its own error the same way, and says so when it cannot prove 1 cm."""
    from fusion_depth.data import filling
    from fusion_depth.data.procedural import render_frame

    image, _, sparse = render_frame(3, "train", 1, 64, 192, 82.0, "fog", "lidar")
    known = sparse > 0
    gray = filling._intensity(image)
    scale = float(sparse[known].max())
    coefficients = filling._grid_coefficients(known, gray)
    rhs = np.where(known, sparse.astype(np.float64) / scale, 0.0)
    with caplog.at_level("WARNING", logger="fusion_depth.data.filling"):
        fallback = filling._fill_colorization_float64(sparse, known, gray, coefficients, rhs)
    assert caplog.records == []  # proved: no warning
    np.testing.assert_allclose(fallback, filling._fill_colorization(sparse, known, gray), atol=1e-3)
    monkeypatch.setattr(filling, "colorization_error_bound", lambda *a: lambda *s: 0.5)
    with caplog.at_level("WARNING", logger="fusion_depth.data.filling"):
        again = filling._fill_colorization_float64(sparse, known, gray, coefficients, rhs)
    assert "could not be proven within 0.01 m" in caplog.text
    assert f"(bound {0.5 * scale:.3g} m)" in caplog.text
    np.testing.assert_array_equal(again, fallback)


def test_linear_hull_is_radarnets_interpolation() -> None:
    """RadarNet's interpolate_depth (setup/data_utils.py): scipy's LinearNDInterpolator over the
    measured pixels' (row, column), 0 outside their convex hull."""
    from scipy.interpolate import LinearNDInterpolator

    depth, image = _random_sparse(3)
    rows, cols = np.nonzero(depth)
    reference = LinearNDInterpolator(np.stack([rows, cols], 1), depth[rows, cols], fill_value=0)
    grid = np.stack(np.meshgrid(np.arange(H), np.arange(W), indexing="ij"), -1).reshape(-1, 2)
    expected = reference(grid).reshape(H, W).astype(np.float32)
    filled = fill_depth(depth, image, "linear_hull")
    np.testing.assert_allclose(filled, expected, rtol=1e-6, atol=1e-6)
    assert (filled == 0).any()  # outside the hull: still missing, unlike linear
    assert (fill_depth(depth, image, "linear") > 0).all()
