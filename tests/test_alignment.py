"""The global alignment of a prior to sparse returns (fusion_depth.models.alignment): exact priors
fit exactly, RANSAC survives gross outliers, hypotheses that reverse the depth order are never
kept, and radar returns drawn as lines are sampled once each."""

from __future__ import annotations

import pytest
import torch

from fusion_depth.errors import ArgumentError
from fusion_depth.models.alignment import apply_alignment, fit_scale_shift

H, W = 32, 48


def _scene(frames: int = 3, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return 2.0 + 60.0 * torch.rand(frames, 1, H, W, generator=generator)


def _returns(depth: torch.Tensor, count: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` returns per frame at distinct random pixels: the sparse map and the points
    (columns u, v, depth, rcs, velocity, valid)."""
    generator = torch.Generator().manual_seed(seed)
    frames = len(depth)
    sparse = torch.zeros_like(depth)
    points = torch.zeros(frames, count, 6)
    for f in range(frames):
        pixels = torch.randperm(H * W, generator=generator)[:count]
        v, u = pixels // W, pixels % W
        points[f, :, 0], points[f, :, 1] = u.float(), v.float()
        points[f, :, 2], points[f, :, 5] = depth[f, 0, v, u], 1.0
        sparse[f, 0, v, u] = depth[f, 0, v, u]
    return sparse, points


@pytest.mark.parametrize("iterations", [0, 100])
@pytest.mark.parametrize("with_points", [False, True])
def test_an_exact_relative_prior_with_a_shift_is_recovered_exactly(iterations, with_points):
    depth = _scene()
    prior = 3.0 / depth + 0.2  # Depth Anything's kind of output: inverse depth, scaled, shifted
    sparse, points = _returns(depth, 40)
    fit = fit_scale_shift(
        prior, sparse, "relative", iterations, points=points if with_points else None
    )
    torch.testing.assert_close(fit.scale, torch.full((3,), 1 / 3, dtype=torch.float64))
    torch.testing.assert_close(fit.shift, torch.full((3,), -0.2 / 3, dtype=torch.float64))
    aligned = apply_alignment(prior, fit, "relative", 0.5, 80.0)
    torch.testing.assert_close(aligned, depth, rtol=1e-5, atol=0)
    assert not fit.fallback.any() and not fit.reversed.any()


def test_ransac_stays_within_one_percent_with_thirty_percent_gross_outliers():
    depth = _scene(frames=4)
    prior = 3.0 / depth + 0.2
    sparse, points = _returns(depth, 60)
    generator = torch.Generator().manual_seed(5)
    wrong = torch.rand(points.shape[:2], generator=generator) < 0.3  # multipath: far too far/near
    factor = torch.where(torch.rand(wrong.shape, generator=generator) < 0.5, 0.3, 2.5)
    points[..., 2] = torch.where(wrong, points[..., 2] * factor, points[..., 2])
    assert 0.2 < wrong.float().mean() < 0.4
    robust = fit_scale_shift(prior, sparse, "relative", 100, points=points)
    plain = fit_scale_shift(prior, sparse, "relative", 0, points=points)
    for fit, within in ((robust, True), (plain, False)):
        aligned = apply_alignment(prior, fit, "relative", 0.5, 80.0)
        error = ((aligned - depth).abs() / depth).amax()
        assert (error <= 0.01) == within, float(error)


def test_only_order_reversing_hypotheses_fall_back_and_say_so():
    depth = _scene(frames=2)
    prior = 3.0 / depth + 0.2
    sparse, points = _returns(depth, 8)
    # Frame 0's returns say far where the prior says near: every pair has a negative scale.
    order = torch.argsort(points[0, :, 2])
    points[0, order, 2] = points[0, order.flip(0), 2]
    fit = fit_scale_shift(prior, sparse, "relative", 50, fallback=(0.5, 0.01), points=points)
    assert fit.fallback.tolist() == [True, False]
    assert fit.reversed.tolist() == [True, False]
    # The batch's median fit (frame 1's), not a reversed one; alone, the caller's.
    assert fit.scale[0] == fit.scale[1] and fit.shift[0] == fit.shift[1]
    alone = fit_scale_shift(
        prior[:1], sparse[:1], "relative", 50, fallback=(0.5, 0.01), points=points[:1]
    )
    assert alone.reversed.tolist() == [True]
    assert alone.scale[0] == 0.5 and alone.shift[0] == 0.01
    plain = fit_scale_shift(prior, sparse, "relative", 0, points=points)
    assert plain.reversed.tolist() == [True, False] and plain.scale[0] == plain.scale[1]
    # Too few returns is a fallback, not a reversal.
    few = fit_scale_shift(prior, torch.zeros_like(sparse), "relative", 50)
    assert few.fallback.all() and not few.reversed.any()


def test_returns_drawn_as_vertical_lines_are_sampled_once_each():
    """A return drawn down a column of pixels has one depth and many prior values: any two of
    its pixels give scale 0. Sampled per return, each return is one sample at its own pixel."""
    depth = _scene(frames=1)
    prior = 3.0 / depth + 0.2
    _, points = _returns(depth, 12)
    sparse = torch.zeros_like(depth)
    for u, v, d in points[0, :, :3].tolist():  # each return down 12 rows of its column
        sparse[0, 0, int(v) : int(v) + 12, int(u)] = d
    per_return = fit_scale_shift(prior, sparse, "relative", 100, points=points)
    torch.testing.assert_close(per_return.scale, torch.tensor([1 / 3], dtype=torch.float64))
    assert int(per_return.points[0]) == 12
    per_pixel = fit_scale_shift(prior, sparse, "relative", 100)
    assert int(per_pixel.points[0]) > 12  # the lines' pixels, and a fit that is not the truth
    assert abs(float(per_pixel.scale[0]) - 1 / 3) > 1e-3


def test_a_frames_fit_does_not_depend_on_the_other_frames_of_its_batch():
    depth = _scene(frames=3, seed=2)
    prior = 3.0 / depth + 0.2
    sparse, points = _returns(depth, 30)
    points[..., 2] *= torch.where(torch.rand(points.shape[:2]) < 0.3, 2.0, 1.0)
    together = fit_scale_shift(prior, sparse, "relative", 100, points=points)
    for f in range(3):
        alone = fit_scale_shift(
            prior[f : f + 1], sparse[f : f + 1], "relative", 100, points=points[f : f + 1]
        )
        assert alone.scale.item() == together.scale[f].item()
        assert alone.shift.item() == together.shift[f].item()


def test_a_metric_prior_is_fitted_by_a_scale_alone_and_robustly():
    depth = _scene(frames=2)
    prior = depth / 1.3  # metres from another camera: off by a scale
    sparse, points = _returns(depth, 50)
    exact = fit_scale_shift(prior, sparse, "metric", 0, points=points)
    torch.testing.assert_close(exact.scale, torch.full((2,), 1.3, dtype=torch.float64))
    assert exact.shift.eq(0).all()
    torch.testing.assert_close(apply_alignment(prior, exact, "metric", 0.5, 80.0), depth)
    wrong = torch.arange(50) % 3 == 0  # a third of the returns 2.5 times too far
    points[:, wrong, 2] *= 2.5
    robust = fit_scale_shift(prior, sparse, "metric", 100, points=points)
    plain = fit_scale_shift(prior, sparse, "metric", 0, points=points)
    assert (robust.scale / 1.3 - 1).abs().max() < 0.01
    assert (plain.scale / 1.3 - 1).abs().min() > 0.1


def test_settings_it_cannot_take_are_refused_in_one_line():
    prior = sparse = torch.ones(1, 1, 4, 4)
    with pytest.raises(ArgumentError, match=r"^kind='inverse': expected one of"):
        fit_scale_shift(prior, sparse, "inverse")
    with pytest.raises(ArgumentError, match=r"^ransac_iterations=-1: expected an integer ≥ 0"):
        fit_scale_shift(prior, sparse, ransac_iterations=-1)
    with pytest.raises(ArgumentError, match=r"^ransac_threshold=0: expected a relative error"):
        fit_scale_shift(prior, sparse, ransac_threshold=0)
