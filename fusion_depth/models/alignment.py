"""Global alignment of a depth prior to sparse metric depth: per frame, the scale (and shift)
that make a monocular foundation model's output metric, from the radar or lidar returns of the
same frame.

Follows the global alignment stage of RadarCam-Depth (Li et al., ICRA 2024, Sec. III-B): a
least-squares fit of the relative inverse depth to the sparse metric inverse depth. The model
fitted depends on what the prior gives (its ``kind``, :mod:`fusion_depth.models.depth_prior`):

* ``relative`` (Depth Anything V2's relative models, MiDaS): an inverse depth up to an unknown
  scale *and shift*, so ``s · prior + t ≈ 1 / depth``, fitted in inverse depth. This is the
  only space where that model is exact: a shifted inverse depth ``a / d + b`` has no scale and
  shift in metres that map it onto ``d``.
* ``metric`` (Depth Anything V2's metric models): metres already, off by a scale at most (a
  camera other than the training one), so ``s · prior ≈ depth``, scale only, in metres.

Radar returns are noisy: multipath, a wide vertical beam drawn as a line of pixels, returns
that miss the object the pixel shows. So the default fit is RANSAC (Fischler & Bolles 1981):
``ransac_iterations`` minimal samples (two returns for a scale and shift, one for a scale), the
hypotheses that would reverse the order of depths (a scale ≤ 0) rejected, the one with the most
inliers kept, and a least-squares refit on its inliers. Samples are drawn **per return**: given
the batch's ``radar_points``, each return is one sample, at the pixel it projects to; a return
drawn as a vertical line of pixels counts once, so two pixels of one line (one depth, two prior
values: scale 0) are never a sample. Without points (lidar), each pixel with a return is one.

The hypotheses are a fixed, evenly spread sequence of draws (a Kronecker sequence started at
``seed``), not a random stream: the fit of a frame depends on its samples alone, is the same on
every call and every device, and the whole fit is tensor operations with no loop over frames,
so a network that fits exports. An exported network takes the image and the sparse map, not
the radar's points: it samples each pixel with a return, where ``evaluate`` and training
sample each return once (the same where a return is one pixel, as on nuScenes).

A frame whose fit cannot be made falls back to its batch's median fit, or in a batch
without any to ``fallback`` (its caller's running fit), and :class:`Alignment` says why: too
few samples (fewer than two, one for a scale), or no hypothesis and no fit that keeps the
order of depths (``reversed``). Never NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from fusion_depth.errors import ArgumentError, check_choice

PRIOR_KINDS = ("relative", "metric")  # what a prior gives: fusion_depth.models.depth_prior
DEFAULT_RANSAC_ITERATIONS = 100
DEFAULT_RANSAC_THRESHOLD = 0.1
_TINY = 1e-12  # a difference of prior values below this is no spread to fit a scale on
_CHUNK = 10  # RANSAC hypotheses whose inliers are counted at once
_U, _V, _DEPTH, _VALID = 0, 1, 2, 5  # columns of fusion_depth.data.RADAR_POINT_FIELDS


@dataclass(frozen=True)
class Alignment:
    """Per-frame fits of :func:`fit_scale_shift`.

    Attributes:
        scale: (B,) the fitted scale ``s`` (float64).
        shift: (B,) the fitted shift ``t`` (float64, 1/m; 0 for a metric prior's fit).
        points: (B,) the samples each fit used (RANSAC: its best hypothesis's inliers).
        fallback: (B,) True where the frame took its batch's median fit (or ``fallback``)
            instead of a fit of its own.
        reversed: (B,) True where it did so although it had samples enough: every RANSAC
            hypothesis (or, with ``ransac_iterations=0``, the least-squares fit) had a scale ≤ 0
            (it would reverse the depth order) or no spread of prior values to fit on.
    """

    scale: torch.Tensor
    shift: torch.Tensor
    points: torch.Tensor
    fallback: torch.Tensor
    reversed: torch.Tensor


def prior_kind(prior: object) -> str:
    """What ``prior`` gives: its ``kind`` attribute (``relative`` or ``metric``,
    :mod:`fusion_depth.models.depth_prior`), ``relative`` for a prior that declares none.

    Raises:
        ArgumentError: a ``kind`` that is neither.
    """
    kind = getattr(prior, "kind", "relative")
    check_choice(kind, PRIOR_KINDS, "kind", owner=prior_kind)
    return kind


def check_alignment_arguments(
    ransac_iterations: int, ransac_threshold: float, owner: object = None
) -> None:
    """Fail on settings :func:`fit_scale_shift` cannot take, before any frame is read;
    ``owner`` (default :func:`fit_scale_shift`) is what the config layer names the keys of.

    Raises:
        ArgumentError: ``ransac_iterations`` not an integer ≥ 0, or ``ransac_threshold ≤ 0``.
    """
    whole = isinstance(ransac_iterations, int) and not isinstance(ransac_iterations, bool)
    if not whole or ransac_iterations < 0:
        raise ArgumentError(
            f"{{ransac_iterations}}={ransac_iterations}: expected an integer ≥ 0 (0: least "
            "squares on every return)",
            "ransac_iterations",
            owner=owner or fit_scale_shift,
        )
    if isinstance(ransac_threshold, bool) or not (
        isinstance(ransac_threshold, int | float) and ransac_threshold > 0
    ):
        raise ArgumentError(
            f"{{ransac_threshold}}={ransac_threshold}: expected a relative error > 0",
            "ransac_threshold",
            owner=owner or fit_scale_shift,
        )


def alignment_samples(
    prior: torch.Tensor, sparse: torch.Tensor, points: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each frame's samples for the fit: the prior's value and the metric depth, one per radar
    return where ``points`` are given (at the pixel the return projects to, rounded and kept in
    the image), else one per pixel with a return.

    Args:
        prior: (B, 1, H, W) the prior at the frame's resolution.
        sparse: (B, 1, H, W) metres, 0 = no return.
        points: (B, P, 6) the batch's ``radar_points`` (columns
            :data:`~fusion_depth.data.RADAR_POINT_FIELDS`, ``u, v`` in pixels of this frame),
            or None.

    Returns:
        ``x`` (B, N) prior values, ``depth`` (B, N) metres and ``valid`` (B, N) bool, float64;
        N is P, or the most pixels with a return of any frame.
    """
    batch, _, height, width = prior.shape
    flat = prior.double().reshape(batch, -1)
    if points is not None:
        u = points[..., _U].round().long().clamp(0, width - 1)
        v = points[..., _V].round().long().clamp(0, height - 1)
        depth = points[..., _DEPTH].double()
        valid = (points[..., _VALID] > 0) & (depth > 0)
        return flat.gather(1, v * width + u), torch.where(valid, depth, 0.0), valid
    depth = sparse.double().reshape(batch, -1)
    valid = depth > 0
    if _tracing():  # every pixel: a shape that depends on no value (an exported network)
        return flat, depth, valid
    # The pixels with a return first, then as many columns as the frame with most of them needs.
    order = _valid_first(valid)
    keep = max(int(valid.sum(dim=1).max()) if valid.numel() else 0, 1)
    order = order[:, :keep]
    return flat.gather(1, order), depth.gather(1, order), valid.gather(1, order)


def _valid_first(valid: torch.Tensor) -> torch.Tensor:
    """(B, N) indices that put each row's True entries first, each part in its own order: a
    stable sort, as a top-k of ``N · valid + (N - 1 - index)`` (which ONNX has)."""
    n = valid.shape[1]
    index = torch.arange(n, device=valid.device, dtype=torch.float64)
    score = valid.double() * n + (n - 1 - index)
    return torch.topk(score, n, dim=1).indices


def _masked_median(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The lower median of ``values`` (B,) where ``mask`` (as :func:`torch.median`), 0 where
    none is: each value's rank among the others, with no sort and no shape that depends on the
    mask or on the batch (an exported network's batch is dynamic)."""
    v = torch.where(mask, values, torch.inf)
    index = torch.arange(v.shape[0], device=v.device)
    before = (v[None, :] < v[:, None]) | (
        (v[None, :] == v[:, None]) & (index[None, :] < index[:, None])
    )
    middle = (mask.sum() - 1).clamp_min(0) // 2
    return torch.where(mask & (before.sum(dim=1) == middle), v, 0.0).sum()


def _tracing() -> bool:
    """Whether the fit is being exported, traced or compiled: shapes may then not depend on
    values."""
    return (
        torch.compiler.is_compiling()
        or torch.compiler.is_exporting()
        or torch.jit.is_tracing()
    )


# A 2-D Kronecker sequence (the fractional parts of i·α for two irrationals): evenly spread
# draws in [0, 1)², the same on every call and device, computed in the graph (an exported
# network holds no table) rather than drawn from a random stream.
_KRONECKER = (0.6180339887498949, 0.41421356237309515)  # (√5 − 1) / 2, √2 − 1


def _hypothesis_table(iterations: int, seed: int, device: torch.device) -> torch.Tensor:
    """(iterations, 2) draws in [0, 1): which samples each hypothesis takes; ``seed`` starts
    the sequence elsewhere."""
    i = torch.arange(iterations, dtype=torch.float64, device=device) + seed * iterations + 1
    return torch.stack([torch.frac(i * a) for a in _KRONECKER], dim=1)


def _least_squares(
    x: torch.Tensor, y: torch.Tensor, weight: torch.Tensor, with_shift: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per frame, ``(s, t)`` minimising ``Σ w (s x + t − y)²`` (``t = 0`` without shift), and
    whether a fit with ``s > 0`` was made (two samples with spread, one for a scale)."""
    count = weight.sum(dim=1)
    if not with_shift:
        xx = (weight * x * x).sum(dim=1)
        scale = (weight * x * y).sum(dim=1) / xx.clamp_min(_TINY)
        made = (count >= 1) & (xx > _TINY)
        return torch.where(made, scale, 0.0), torch.zeros_like(scale), made
    n = count.clamp_min(1.0)
    x_mean, y_mean = (weight * x).sum(dim=1) / n, (weight * y).sum(dim=1) / n
    x_offset = x - x_mean[:, None]
    variance = (weight * x_offset * x_offset).sum(dim=1) / n
    covariance = (weight * x_offset * (y - y_mean[:, None])).sum(dim=1) / n
    made = (count >= 2) & (variance > _TINY * x_mean.square().clamp_min(1.0))
    scale = torch.where(made, covariance / variance.clamp_min(_TINY), 0.0)
    return scale, y_mean - scale * x_mean, made


def _ransac(
    x: torch.Tensor,
    y: torch.Tensor,
    valid: torch.Tensor,
    iterations: int,
    threshold: float,
    seed: int,
    with_shift: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The best order-keeping hypothesis of each frame: its ``(s, t)``, its inliers (B, N) and
    whether it exists. A sample is an inlier when ``|s x + t − y| ≤ threshold · |y|`` (a
    relative error: near and far returns count alike); ties go to the first hypothesis."""
    count = valid.sum(dim=1)
    # The frame's valid samples first, so that a draw in [0, count) picks one of them.
    order = _valid_first(valid)
    table = _hypothesis_table(iterations, seed, x.device)
    first = (table[None, :, 0] * count[:, None]).long()
    second = (table[None, :, 1] * (count[:, None] - 1).clamp_min(1)).long()
    second = second + (second >= first).long()  # another sample than the first
    first, second = order.gather(1, first), order.gather(1, second.clamp_max(x.shape[1] - 1))
    x1, y1 = x.gather(1, first), y.gather(1, first)
    if with_shift:
        x2, y2 = x.gather(1, second), y.gather(1, second)
        dx = x2 - x1
        usable = (count[:, None] >= 2) & (dx.abs() > _TINY)
        scale = (y2 - y1) / torch.where(usable, dx, 1.0)
        shift = y1 - scale * x1
    else:
        usable = (count[:, None] >= 1) & (x1.abs() > _TINY)
        scale = y1 / torch.where(usable, x1, 1.0)
        shift = torch.zeros_like(scale)
    usable = usable & (scale > 0) & torch.isfinite(scale) & torch.isfinite(shift)
    bound = threshold * y.abs()

    def inliers_of(s: torch.Tensor, t: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
        """(B, K, N) inliers of K hypotheses per frame."""
        residual = (s[..., None] * x[:, None] + t[..., None] - y[:, None]).abs()
        return (residual <= bound[:, None]) & valid[:, None] & ok[..., None]

    # Counted a few hypotheses at a time: (B, K, N) at once is gigabytes for every pixel of a
    # large frame (an exported network fits on all of them).
    chunks = [slice(i, i + _CHUNK) for i in range(0, iterations, _CHUNK)]
    counts = torch.cat(
        [inliers_of(scale[:, c], shift[:, c], usable[:, c]).sum(dim=2) for c in chunks], dim=1
    )
    pick = counts.argmax(dim=1, keepdim=True)  # the first of the most
    best = [scale.gather(1, pick), shift.gather(1, pick), usable.gather(1, pick)]
    return best[0][:, 0], best[1][:, 0], inliers_of(*best)[:, 0], best[2][:, 0]


def fit_scale_shift(
    prior: torch.Tensor,
    sparse: torch.Tensor,
    kind: str = "relative",
    ransac_iterations: int = DEFAULT_RANSAC_ITERATIONS,
    ransac_threshold: float = DEFAULT_RANSAC_THRESHOLD,
    fallback: tuple[float, float] | torch.Tensor = (1.0, 0.0),
    seed: int = 0,
    points: torch.Tensor | None = None,
) -> Alignment:
    """The scale (and shift) that map each frame's ``prior`` onto its sparse metric depth.

    Args:
        prior: (B, 1, H, W) a ``relative`` prior's inverse depth (larger is nearer, any scale
            and shift) or a ``metric`` prior's depth in metres.
        sparse: (B, 1, H, W) metres, 0 = no return (the batch's ``sparse``).
        kind: ``relative`` (fit ``s · prior + t ≈ 1/depth``) or ``metric`` (fit ``s · prior ≈
            depth``); see the module docstring.
        ransac_iterations: N > 0: RANSAC with N minimal samples and a least-squares refit on
            the best one's inliers; 0: least squares on every sample.
        ransac_threshold: a sample is an inlier of a hypothesis when its relative error (in
            inverse depth, or in metres for a metric prior) is at most this.
        fallback: ``(s, t)`` (or a tensor of the two) for a frame without a fit of its own in
            a batch without any (else it takes the batch's median fit).
        seed: where RANSAC's fixed sequence of draws starts.
        points: (B, P, 6) the batch's ``radar_points``: one sample per return
            (:func:`alignment_samples`); None: one per pixel with a return.

    Returns:
        :class:`Alignment`, one fit per frame.

    Raises:
        ArgumentError: an unknown ``kind``, ``ransac_iterations < 0`` or ``ransac_threshold ≤
            0``.
        ValueError: ``prior`` and ``sparse`` differ in shape.
    """
    check_choice(kind, PRIOR_KINDS, "kind", owner=fit_scale_shift)
    check_alignment_arguments(ransac_iterations, ransac_threshold)
    if prior.shape != sparse.shape:
        raise ValueError(f"prior {tuple(prior.shape)} and sparse {tuple(sparse.shape)} differ")
    x, depth, valid = alignment_samples(prior, sparse, points)
    with_shift = kind == "relative"
    if with_shift:
        y = torch.where(valid, 1.0 / torch.where(valid, depth, 1.0), 0.0)
    else:  # a metric prior of 0 (a ReLU's sky) has no scale to fit on
        valid = valid & (x > _TINY)
        y = torch.where(valid, depth, 0.0)
    enough = valid.sum(dim=1) >= (2 if with_shift else 1)
    scale, shift, made = _least_squares(x, y, valid.double(), with_shift)
    inliers = valid
    if ransac_iterations:
        h_scale, h_shift, h_inliers, found = _ransac(
            x, y, valid, ransac_iterations, ransac_threshold, seed, with_shift
        )
        r_scale, r_shift, r_made = _least_squares(x, y, h_inliers.double(), with_shift)
        refit = r_made & (r_scale > 0)
        # The refit on the inliers; the hypothesis itself where the refit reverses the order.
        scale = torch.where(refit, r_scale, h_scale)
        shift = torch.where(refit, r_shift, h_shift)
        made, inliers = found, h_inliers
    fitted = made & (scale > 0)
    # The batch's median fit (the lower median, as torch.median), else ``fallback``: without a
    # shape that depends on which frames fitted.
    given = torch.as_tensor(fallback, dtype=torch.float64).to(scale.device)
    median = torch.stack([_masked_median(v, fitted) for v in (scale, shift)])
    default = torch.where(fitted.any(), median, given)
    return Alignment(
        scale=torch.where(fitted, scale, default[0]),
        shift=torch.where(fitted, shift, default[1] if with_shift else 0.0),
        points=torch.where(fitted, (inliers & valid).sum(dim=1), 0),
        fallback=~fitted,
        reversed=enough & ~fitted,
    )


def apply_alignment(
    prior: torch.Tensor,
    alignment: Alignment,
    kind: str,
    min_depth: float,
    max_depth: float,
) -> torch.Tensor:
    """Metric depth from ``prior`` and its per-frame fits, clipped to the depth range.

    Args:
        prior: (B, 1, H, W) the prior, as given to :func:`fit_scale_shift`.
        alignment: its fits.
        kind: the prior's kind, as given to :func:`fit_scale_shift`.
        min_depth: the range's lower end in metres (> 0).
        max_depth: its upper end in metres.

    Returns:
        (B, 1, H, W) metres in ``[min_depth, max_depth]``, in ``prior``'s dtype. A relative
        prior's fitted inverse depth at or below ``1 / max_depth`` (beyond the range, or
        beyond infinity) maps to ``max_depth``.
    """
    check_choice(kind, PRIOR_KINDS, "kind", owner=apply_alignment)
    scale = alignment.scale.to(prior.device, torch.float64)[:, None, None, None]
    shift = alignment.shift.to(prior.device, torch.float64)[:, None, None, None]
    fitted = scale * prior.double() + shift
    if kind == "relative":
        fitted = 1.0 / fitted.clamp_min(1.0 / max_depth)
    return fitted.clamp(min_depth, max_depth).to(prior.dtype)


class FallbackCount:
    """Counts a network's per-frame fits and those that fell back, for the run's log and
    record (``alignment`` in ``metrics.json``): :meth:`reset_fits` before a stage,
    :meth:`count_fits` per batch, :meth:`fit_summary` after it."""

    def reset_fits(self) -> None:
        """Start counting again (at the test stage's start)."""
        self._fits, self._fallbacks, self._reversed = 0, 0, 0

    @torch.compiler.disable  # counted under torch.compile too, outside the compiled graph
    def count_fits(self, fit: Alignment) -> None:
        """Count a batch's fits (:class:`Alignment`); nothing while exported or traced."""
        if torch.compiler.is_exporting() or torch.jit.is_tracing():
            return
        self._fits = getattr(self, "_fits", 0) + int(fit.fallback.numel())
        self._fallbacks = getattr(self, "_fallbacks", 0) + int(fit.fallback.sum())
        self._reversed = getattr(self, "_reversed", 0) + int(fit.reversed.sum())

    def fit_summary(self) -> dict[str, int]:
        """``{"fits": n, "fallbacks": k, "reversed": r}`` since :meth:`reset_fits`: one fit per
        frame and forward pass (two per frame with ``eval.flip_tta``); ``reversed`` counts the
        fallbacks of frames that had samples enough but no fit keeping the depth order."""
        return {
            "fits": getattr(self, "_fits", 0),
            "fallbacks": getattr(self, "_fallbacks", 0),
            "reversed": getattr(self, "_reversed", 0),
        }
