"""Global alignment of a relative depth prior to sparse metric depth: the least-squares scale and
shift that make a monocular foundation model's affine-invariant inverse depth metric, frame by
frame, from the radar or lidar returns of the same frame.

Follows the global scale-and-shift alignment stage of RadarCam-Depth (Li et al., ICRA 2024),
which fits the relative inverse depth to the radar depth. The fit has a closed form
(ordinary least squares of one regressor); the RANSAC option (Fischler & Bolles 1981) fits
minimal two-point samples and refits on the best sample's inliers, for returns that miss the
object the pixel shows (radar multipath, lidar through glass).

Two spaces are offered:

* ``inverse`` (the default): ``s · prior + t ≈ 1 / depth``. The prior is an inverse depth up to
  an affine map (Depth Anything V2's relative output), so this is the model's own space.
* ``depth``: ``s / prior + t ≈ depth``: the prior inverted first, the fit in metres, weighting
  far returns as the metric errors (MAE, RMSE) do.

A frame with too few returns for a fit (fewer than two, or all at one prior value) takes its
batch's median fit; a batch without any takes ``fallback`` (each such frame counted in
:attr:`Alignment.fallback`): never NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from fusion_depth.errors import ArgumentError, check_choice

ALIGNMENT_SPACES = ("inverse", "depth")
_TINY = 1e-12  # a variance below this is no spread of prior values to fit a shift on


@dataclass(frozen=True)
class Alignment:
    """Per-frame fits of :func:`fit_scale_shift`.

    Attributes:
        scale: (B,) the fitted scale ``s`` (float64).
        shift: (B,) the fitted shift ``t`` (float64; in 1/m for ``inverse``, m for ``depth``).
        points: (B,) the returns each fit used (RANSAC: its inliers).
        fallback: (B,) True where the frame had too few returns and took the batch's median fit
            or ``fallback``.
    """

    scale: torch.Tensor
    shift: torch.Tensor
    points: torch.Tensor
    fallback: torch.Tensor


def _regressor(prior: torch.Tensor, space: str) -> torch.Tensor:
    """What the fit scales: the prior itself (``inverse``) or its reciprocal (``depth``)."""
    return prior if space == "inverse" else 1.0 / prior.clamp_min(_TINY)


def least_squares_fit(
    x: torch.Tensor, y: torch.Tensor, valid: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per frame, ``(s, t)`` minimising ``Σ (s x + t − y)²`` over its ``valid`` pixels, in
    closed form (no loop over frames, so a network that calls it exports).

    Args:
        x: (B, 1, H, W) the regressor.
        y: (B, 1, H, W) the target; any finite value where ``valid`` is False.
        valid: (B, 1, H, W) bool.

    Returns:
        ``scale`` (B,), ``shift`` (B,) and ``fitted`` (B,) bool: False for a frame with fewer
        than two valid pixels, no spread of ``x`` among them, or a best scale ≤ 0, which would
        reverse the order of depths (its scale is 0 and its shift the mean of ``y``, or 0), in
        ``x``'s dtype.
    """
    count = valid.sum(dim=(1, 2, 3))
    weight = count.clamp_min(1).to(x.dtype)

    def mean(values: torch.Tensor) -> torch.Tensor:
        return torch.where(valid, values, 0.0).sum(dim=(1, 2, 3)) / weight

    x_mean, y_mean = mean(x), mean(y)
    x_offset = x - x_mean.view(-1, 1, 1, 1)
    variance = mean(x_offset * x_offset)
    covariance = mean(x_offset * (y - y_mean.view(-1, 1, 1, 1)))
    fitted = (count >= 2) & (variance > _TINY * x_mean.square().clamp_min(1.0))
    scale = torch.where(fitted, covariance / variance.clamp_min(_TINY), 0.0)
    fitted = fitted & (scale > 0)  # a prior of inverse depth, or of depth, grows with it
    scale = torch.where(fitted, scale, 0.0)
    return scale, y_mean - scale * x_mean, fitted


def _ransac(
    x: torch.Tensor, y: torch.Tensor, iterations: int, threshold: float, generator: torch.Generator
) -> torch.Tensor:
    """The inlier mask of the best of ``iterations`` two-point fits: a point is an inlier when
    ``|s x + t − y| ≤ threshold · |y|`` (a relative error, so near and far returns count alike).
    Ties go to the first sample drawn, so the fit is reproducible for a given generator."""
    count = x.numel()
    first = torch.randint(count, (iterations,), generator=generator)
    second = (first + torch.randint(1, count, (iterations,), generator=generator)) % count
    dx = x[second] - x[first]
    ok = dx.abs() > _TINY
    scale = torch.where(ok, (y[second] - y[first]) / torch.where(ok, dx, 1.0), 0.0)
    shift = y[first] - scale * x[first]
    residual = (scale[:, None] * x[None] + shift[:, None] - y[None]).abs()
    inliers = (residual <= threshold * y.abs()[None]) & ok[:, None]
    return inliers[int(inliers.sum(dim=1).argmax())]


def check_alignment_arguments(space: str, ransac_iterations: int, ransac_threshold: float) -> None:
    """Fail on settings :func:`fit_scale_shift` cannot take, before any frame is read.

    Raises:
        ArgumentError: an unknown ``space``, ``ransac_iterations`` not an integer ≥ 0, or
            ``ransac_threshold ≤ 0``.
    """
    check_choice(space, ALIGNMENT_SPACES, "space", owner=fit_scale_shift)
    whole = isinstance(ransac_iterations, int) and not isinstance(ransac_iterations, bool)
    if not whole or ransac_iterations < 0:
        raise ArgumentError(
            f"{{ransac_iterations}}={ransac_iterations}: expected an integer ≥ 0",
            "ransac_iterations",
            owner=fit_scale_shift,
        )
    if isinstance(ransac_threshold, bool) or not (
        isinstance(ransac_threshold, int | float) and ransac_threshold > 0
    ):
        raise ArgumentError(
            f"{{ransac_threshold}}={ransac_threshold}: expected a number > 0",
            "ransac_threshold",
            owner=fit_scale_shift,
        )


class FallbackCount:
    """Counts a network's per-frame fits and those that fell back (too few returns), for the
    run's log and record (``alignment`` in ``metrics.json``): :meth:`reset_fits` before a
    stage, :meth:`count_fits` per batch, :meth:`fit_summary` after it."""

    def reset_fits(self) -> None:
        """Start counting again (at the test stage's start)."""
        self._fits, self._fallbacks = 0, 0

    def count_fits(self, fallback: torch.Tensor) -> None:
        """Count a batch's fits; ``fallback`` (B,) is True where a frame fell back."""
        self._fits = getattr(self, "_fits", 0) + int(fallback.numel())
        self._fallbacks = getattr(self, "_fallbacks", 0) + int(fallback.sum())

    def fit_summary(self) -> dict[str, int]:
        """``{"fits": n, "fallbacks": k}`` since :meth:`reset_fits`: one fit per frame and
        forward pass (two per frame with ``eval.flip_tta``)."""
        return {"fits": getattr(self, "_fits", 0), "fallbacks": getattr(self, "_fallbacks", 0)}


def fit_scale_shift(
    prior: torch.Tensor,
    sparse: torch.Tensor,
    space: str = "inverse",
    ransac_iterations: int = 0,
    ransac_threshold: float = 0.1,
    fallback: tuple[float, float] = (1.0, 0.0),
    seed: int = 0,
) -> Alignment:
    """The scale and shift that map each frame's ``prior`` onto its sparse metric depth.

    Args:
        prior: (B, 1, H, W) relative inverse depth (≥ 0, larger is nearer), e.g. Depth Anything
            V2's relative output resized to the frame.
        sparse: (B, 1, H, W) metres, 0 = no return (the batch's ``sparse``).
        space: ``inverse`` (fit ``s · prior + t`` to 1/depth) or ``depth`` (fit ``s / prior +
            t`` to metres); see the module docstring.
        ransac_iterations: 0 fits all returns; N > 0 draws N two-point samples and refits on
            the best one's inliers.
        ransac_threshold: a return is an inlier of a sample when its relative error in the
            fitted space is at most this.
        fallback: ``(s, t)`` for a frame with too few returns when no frame of its batch has
            enough.
        seed: the RANSAC samples' seed (fits are reproducible).

    Returns:
        :class:`Alignment`, one fit per frame.

    Raises:
        ArgumentError: an unknown ``space``, ``ransac_iterations < 0`` or ``ransac_threshold ≤
            0``.
        ValueError: ``prior`` and ``sparse`` differ in shape.
    """
    check_alignment_arguments(space, ransac_iterations, ransac_threshold)
    if prior.shape != sparse.shape:
        raise ValueError(f"prior {tuple(prior.shape)} and sparse {tuple(sparse.shape)} differ")
    valid = sparse.double() > 0
    if space == "depth":  # a prior of 0 (the sky, by a ReLU) has no finite reciprocal to fit
        valid = valid & (prior.double() > _TINY)
    x = _regressor(prior.double(), space)
    depth = torch.where(valid, sparse.double(), 1.0)
    y = torch.where(valid, 1.0 / depth if space == "inverse" else depth, 0.0)
    if ransac_iterations:  # keep each frame's inliers of its best two-point sample
        generator = torch.Generator().manual_seed(seed)
        inliers = torch.zeros_like(valid)
        for frame in range(len(valid)):
            where = valid[frame]
            if int(where.sum()) >= 2:
                best = _ransac(
                    x[frame][where], y[frame][where], ransac_iterations, ransac_threshold, generator
                )
                inliers[frame][where] = best
        valid = inliers
    scale, shift, fitted = least_squares_fit(x, y, valid)
    if fitted.any():
        default = (scale[fitted].median(), shift[fitted].median())
    else:
        default = tuple(torch.tensor(v, dtype=torch.float64) for v in fallback)
    return Alignment(
        scale=torch.where(fitted, scale, default[0]).cpu(),
        shift=torch.where(fitted, shift, default[1]).cpu(),
        points=torch.where(fitted, valid.sum(dim=(1, 2, 3)), 0).cpu(),
        fallback=~fitted.cpu(),
    )


def apply_alignment(
    prior: torch.Tensor,
    alignment: Alignment,
    space: str,
    min_depth: float,
    max_depth: float,
) -> torch.Tensor:
    """Metric depth from ``prior`` and its per-frame fits, clipped to the depth range.

    Args:
        prior: (B, 1, H, W) relative inverse depth, as given to :func:`fit_scale_shift`.
        alignment: its fits.
        space: the space they were fitted in.
        min_depth: the range's lower end in metres (> 0).
        max_depth: its upper end in metres.

    Returns:
        (B, 1, H, W) metres in ``[min_depth, max_depth]``, in ``prior``'s dtype. An inverse
        depth at or below 0 (a fit that puts a pixel beyond infinity) maps to ``max_depth``.
    """
    check_choice(space, ALIGNMENT_SPACES, "space", owner=apply_alignment)
    scale = alignment.scale.to(prior.device, torch.float64)[:, None, None, None]
    shift = alignment.shift.to(prior.device, torch.float64)[:, None, None, None]
    fitted = scale * _regressor(prior.double(), space) + shift
    if space == "inverse":
        fitted = 1.0 / fitted.clamp_min(1.0 / max_depth)
    return fitted.clamp(min_depth, max_depth).to(prior.dtype)
