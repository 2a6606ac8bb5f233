"""Training losses on reciprocal depth (paper, "Loss Functions").

The network predicts reciprocal depth ``d_net = depth_scale / depth`` and every loss here is
computed on that reciprocal map at the network's output resolution:

``loss = w_ssim * L_ssim + w_edge * L_edge + w_pixel * L_pixel``

All functions take ``pred`` and ``target`` of shape ``(B, 1, h, w)`` and an optional bool ``mask``
of the same shape that is True where the target is valid. Ground truth is usually incomplete (sparse
lidar, sky, reprojection holes), so every term only looks at valid target pixels, and a mask without
a single valid pixel yields a loss of exactly 0 (finite, with a zero gradient) instead of NaN.

The functional forms follow Kornia's naming (``*_loss``); :class:`DepthLoss` is the module used by
the training step and returns every term so that each one can be logged.
"""

from __future__ import annotations

import math

import torch
from kornia.filters import spatial_gradient
from kornia.losses import ssim_loss
from kornia.morphology import erosion
from torch import Tensor, nn

from fusion_depth.utils.schema import NON_NEGATIVE, POSITIVE, Schema, one_of

__all__ = [
    "NONFINITE_ACTIONS",
    "PIXEL_LOSSES",
    "PIXEL_LOSS_LABELS",
    "DepthLoss",
    "berhu_loss",
    "edge_loss",
    "log_l1_loss",
    "masked_ssim_loss",
    "pixel_loss",
    "ssi_loss",
]

PIXEL_LOSSES: tuple[str, ...] = ("l1", "l2", "berhu", "log_l1", "ssi")
"""Allowed values of ``pixel_loss(kind=...)`` and ``DepthLoss(pixel=...)``."""
PIXEL_LOSS_LABELS: dict[str, str] = {
    "l1": "L1",
    "l2": "L2",
    "berhu": "BerHu",
    "log_l1": "log-L1",
    "ssi": "SSI",
}
"""How tables and plots name each pixel loss."""
NONFINITE_ACTIONS: tuple[str, ...] = ("stop", "skip")
"""What training does with a batch whose loss is NaN or infinite (``model.on_nonfinite_loss``)."""


def _check_inputs(pred: Tensor, target: Tensor, mask: Tensor | None) -> Tensor:
    """Validate shapes and return a bool mask (all True when ``mask`` is None)."""
    if pred.dim() != 4:
        raise ValueError(f"pred must have shape (B, C, h, w), got {tuple(pred.shape)}")
    if pred.shape != target.shape:
        raise ValueError(
            f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}"
        )
    if mask is None:
        return torch.ones_like(target, dtype=torch.bool)
    if mask.shape != target.shape:
        raise ValueError(
            f"mask shape {tuple(mask.shape)} differs from target shape {tuple(target.shape)}"
        )
    return mask.bool()


def _masked_mean(values: Tensor, mask: Tensor) -> Tensor:
    """Mean of ``values`` over True entries of ``mask``; 0 when there are none.

    ``torch.where`` (not multiplication) keeps NaN/inf at masked-out positions from leaking in.
    """
    total = torch.where(mask, values, torch.zeros_like(values)).sum()
    return total / mask.sum().clamp_min(1).to(values.dtype)


def _check_kind(kind: str) -> None:
    if kind not in PIXEL_LOSSES:
        raise ValueError(f"unknown pixel loss {kind!r}; expected one of {', '.join(PIXEL_LOSSES)}")


def berhu_loss(
    pred: Tensor, target: Tensor, mask: Tensor | None = None, threshold: float = 0.2
) -> Tensor:
    """Reverse Huber (BerHu) loss averaged over valid pixels (paper, eq. B(x)).

    ``B(x) = |x|`` if ``|x| <= c`` else ``(x**2 + c**2) / (2 c)``, with ``x = pred - target`` and
    ``c = threshold * max|x|`` over the valid pixels of the whole batch. ``c`` is detached: it is a
    data-dependent switch point (Laina et al.), not something to optimise. L1 for small residuals
    keeps their gradients alive, L2 for large ones penalises outliers more. When every residual is
    zero (``c = 0``), ``c`` is replaced by 1 so the quadratic branch never divides by zero (the loss
    is 0 either way, and the gradient stays finite).
    """
    mask = _check_inputs(pred, target, mask)
    diff = torch.where(mask, pred - target, torch.zeros_like(pred))
    abs_diff = diff.abs()
    c = threshold * abs_diff.detach().max()
    c = torch.where(c > 0, c, torch.ones_like(c))
    per_pixel = torch.where(abs_diff <= c, abs_diff, (diff * diff + c * c) / (2 * c))
    return _masked_mean(per_pixel, mask)


LOG_FLOOR = 1e-2
"""Reciprocal depth below which :func:`log_l1_loss` extends the log linearly: a depth of
``100 × depth_scale`` metres (1 km at the built-in dataset's 10), far beyond any ``max_depth``."""


def log_l1_loss(
    pred: Tensor, target: Tensor, mask: Tensor | None = None, floor: float = LOG_FLOOR
) -> Tensor:
    """Mean ``|log pred − log target|`` over valid pixels: L1 on log depth.

    ``log(s / d̂) − log(s / d) = log d − log d̂``, so on reciprocal depth this is exactly the L1
    error of log depth, whatever ``depth_scale`` is: a 10 % error costs the same at 5 m and at
    50 m, where L1 on reciprocal depth weighs the 50 m pixel ten times less. δ1 and abs_rel are
    relative errors, and this is the pixel term that matches them. Not in the paper; log-space
    losses are the usual choice for monocular depth (Eigen et al., 2014, whose scale-invariant
    loss with λ = 0 is L2 on log depth).

    The network's reciprocal output is not constrained to be positive, so below ``floor`` the log
    is continued by its tangent, ``log floor + (pred − floor) / floor``: a prediction ≤ 0 keeps a
    finite loss and a gradient back towards the target. Targets must be > 0 at valid pixels.

    Args:
        pred: predicted reciprocal depth ``(B, 1, h, w)``.
        target: true reciprocal depth, same shape; any value where ``mask`` is False.
        mask: bool, same shape, True where ``target`` is valid (all True when None).
        floor: reciprocal depth (> 0) where the tangent takes over.

    Returns:
        A scalar; 0 when no pixel is valid.
    """
    mask = _check_inputs(pred, target, mask)
    # clamp_min keeps the unused branch finite, so that torch.where passes no NaN gradient.
    tangent = (pred - floor) / floor + math.log(floor)
    log_pred = torch.where(pred > floor, pred.clamp_min(floor).log(), tangent)
    log_target = torch.where(mask, target, torch.ones_like(target)).clamp_min(floor).log()
    return _masked_mean((log_pred - log_target).abs(), mask)


SSI_EPS = 1e-6
"""Added to each image's prediction variance in :func:`ssi_loss`: a flat prediction (a network
at its first step) gets a finite scale and a gradient, not a division by 0."""


def ssi_loss(pred: Tensor, target: Tensor, mask: Tensor | None = None) -> Tensor:
    """Scale-and-shift-invariant L1: each image's prediction is first mapped onto its target by
    the least-squares scale and shift over its valid pixels, then the mean absolute error is
    taken. The loss of MiDaS (Ranftl et al., "Towards Robust Monocular Depth Estimation", TPAMI
    2022) that trains a network to predict inverse depth up to an affine map, as monocular
    foundation models do: the least-squares alignment is theirs (their ``L_ssimse``), the error
    after it is L1 rather than squared, and their gradient-matching term is left out. Not in the
    seed paper; it trains the built-in dataset's stand-in for a foundation prior.

    Each (image, channel) slice is aligned on its own, so the batch-as-channels fold of
    :class:`DepthLoss` gives the same value. The scale and shift are functions of ``pred``, and
    the gradient flows through them (as in MiDaS).

    Args:
        pred: (B, C, h, w) prediction, any affine map of the target's space.
        target: (B, C, h, w) target (the platform's reciprocal depth); any value where ``mask``
            is False.
        mask: bool, same shape, True where ``target`` is valid (all True when None).

    Returns:
        A scalar; 0 when no pixel is valid.
    """
    mask = _check_inputs(pred, target, mask)
    count = mask.sum(dim=(-2, -1), keepdim=True).clamp_min(1).to(pred.dtype)

    def mean(values: Tensor) -> Tensor:
        return torch.where(mask, values, torch.zeros_like(values)).sum((-2, -1), True) / count

    target = torch.where(mask, target, torch.zeros_like(target))
    pred_offset = pred - mean(pred)
    target_offset = target - mean(target)
    scale = mean(pred_offset * target_offset) / (mean(pred_offset * pred_offset) + SSI_EPS)
    aligned = scale * pred_offset + mean(target)
    return _masked_mean((aligned - target).abs(), mask)


def pixel_loss(
    pred: Tensor, target: Tensor, mask: Tensor | None = None, kind: str = "l1"
) -> Tensor:
    """Point-wise loss over valid pixels: ``"l1"`` (mean |x|), ``"l2"`` (mean x²), ``"berhu"``,
    ``"log_l1"`` (:func:`log_l1_loss`) or ``"ssi"`` (:func:`ssi_loss`, per image).

    The paper compares the first three as its ``L_pixel`` term; the default BerHu threshold (0.2)
    is used for ``"berhu"`` (call :func:`berhu_loss` directly to change it).
    """
    _check_kind(kind)
    if kind == "berhu":
        return berhu_loss(pred, target, mask)
    if kind == "log_l1":
        return log_l1_loss(pred, target, mask)
    if kind == "ssi":
        return ssi_loss(pred, target, mask)
    mask = _check_inputs(pred, target, mask)
    diff = torch.where(mask, pred - target, torch.zeros_like(pred))
    per_pixel = diff.abs() if kind == "l1" else diff * diff
    return _masked_mean(per_pixel, mask)


def edge_loss(pred: Tensor, target: Tensor, mask: Tensor | None = None) -> Tensor:
    """Mean |∇pred − ∇target| (x and y Sobel gradients) over pixels with a fully valid 3×3 window.

    Penalises blurred object boundaries (paper, ``L_edge``). A 3×3 Sobel response at a pixel next to
    a hole would mix in invalid target values, so the mask is eroded with a 3×3 structuring element
    first; the erosion is geodesic (ignores outside-image cells), which matches
    ``spatial_gradient``'s replicated border. The mean runs over both gradient components of every
    remaining pixel.
    """
    mask = _check_inputs(pred, target, mask)
    # Fill holes so that NaN/inf placeholders in the target cannot reach valid gradients.
    target = torch.where(mask, target, pred.detach())
    kernel = torch.ones(3, 3, device=pred.device, dtype=pred.dtype)
    inner = erosion(mask.to(pred.dtype), kernel) > 0.5
    grad_diff = (spatial_gradient(pred) - spatial_gradient(target)).abs()  # (B, C, 2, h, w)
    return _masked_mean(grad_diff, inner.unsqueeze(2).expand_as(grad_diff))


def masked_ssim_loss(
    pred: Tensor,
    target: Tensor,
    mask: Tensor | None = None,
    max_val: float = 1.0,
    window_size: int = 11,
) -> Tensor:
    """Kornia's SSIM loss ``mean((1 - SSIM) / 2)`` with invalid target pixels filled by ``pred``.

    SSIM is a windowed statistic and cannot simply skip pixels, so before it is computed the invalid
    target pixels are replaced by the *detached* prediction: there the two maps agree, and those
    pixels contribute (almost) nothing -- "almost" because an 11×11 window centred on a hole still
    contains valid pixels that differ. The values stored at invalid target pixels therefore never
    matter, and an empty mask gives exactly 0. The mean runs over all pixels (Kornia's reduction),
    so the term shrinks with the fraction of valid pixels. ``max_val`` is the dynamic range of the
    reciprocal-depth maps; it sets SSIM's stabilising constants ``(0.01 max_val)²`` and
    ``(0.03 max_val)²``.
    """
    mask = _check_inputs(pred, target, mask)
    target = torch.where(mask, target, pred.detach())
    return ssim_loss(pred, target, window_size=window_size, max_val=max_val)


class DepthLoss(nn.Module):
    """``w_ssim * L_ssim + w_edge * L_edge + w_pixel * L_pixel`` on reciprocal depth.

    The paper uses weights 1, 1, 1 and compares ``pixel`` in {"l1", "l2", "berhu"}; "log_l1"
    (:func:`log_l1_loss`) and "ssi" (:func:`ssi_loss`) are this platform's additions.
    ``forward`` returns a dict with the weighted total under ``"loss"`` (to backpropagate) and the
    unweighted terms under ``"ssim"``, ``"edge"`` and ``"pixel"`` (to log).
    """

    def __init__(
        self,
        pixel: str = "l1",
        w_ssim: float = 1.0,
        w_edge: float = 1.0,
        w_pixel: float = 1.0,
        max_val: float = 1.0,
        window_size: int = 11,
        berhu_threshold: float = 0.2,
    ) -> None:
        super().__init__()
        _check_kind(pixel)
        self.pixel = pixel
        self.w_ssim = w_ssim
        self.w_edge = w_edge
        self.w_pixel = w_pixel
        self.max_val = max_val
        self.window_size = window_size
        self.berhu_threshold = berhu_threshold

    def forward(
        self, pred: Tensor, target: Tensor, mask: Tensor | None = None
    ) -> dict[str, Tensor]:
        """Compute every term.

        Args:
            pred: (B, C, h, w) predicted reciprocal depth (``depth_scale / depth``).
            target: (B, C, h, w) ground-truth reciprocal depth, likewise.
            mask: bool (B, C, h, w), True where the target is valid; None: everywhere.

        Returns:
            Scalars ``"loss"`` (the weighted total), ``"ssim"``, ``"edge"`` and ``"pixel"``.

        Raises:
            ValueError: ``pred`` is not 4-D, or ``target`` or ``mask`` has another shape.
        """
        mask = _check_inputs(pred, target, mask)
        # Every term sees the batch as one image of B·C channels. Each term is per channel, so
        # the values and gradients are the same (to the bit where oneDNN's kernels for the two
        # forms agree, as on an AVX-512 EPYC), but Kornia's SSIM then filters with one depthwise
        # convolution per pass instead of a single-channel one over the batch, whose backward
        # pass oneDNN runs slowly: SSIM 3.5× faster at batch 16 on a CPU (docs/guides/speed.md, "The
        # loss on a CPU").
        pred, target, mask = (t.reshape(1, -1, *t.shape[2:]) for t in (pred, target, mask))
        ssim = masked_ssim_loss(pred, target, mask, self.max_val, self.window_size)
        edge = edge_loss(pred, target, mask)
        if self.pixel == "berhu":
            pix = berhu_loss(pred, target, mask, self.berhu_threshold)
        else:
            pix = pixel_loss(pred, target, mask, self.pixel)
        loss = self.w_ssim * ssim + self.w_edge * edge + self.w_pixel * pix
        return {"loss": loss, "ssim": ssim, "edge": edge, "pixel": pix}

    def extra_repr(self) -> str:
        return (
            f"pixel={self.pixel!r}, w_ssim={self.w_ssim}, w_edge={self.w_edge}, "
            f"w_pixel={self.w_pixel}, max_val={self.max_val}, window_size={self.window_size}"
        )


# What :class:`DepthLoss`'s arguments accept (fusion_depth.utils.schema).
ARGUMENT_RULES: Schema = {
    "pixel": one_of(*PIXEL_LOSSES),
    "w_ssim": NON_NEGATIVE,
    "w_edge": NON_NEGATIVE,
    "w_pixel": NON_NEGATIVE,
    "berhu_threshold": POSITIVE,
}
