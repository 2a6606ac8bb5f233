"""Depth evaluation metrics in metres (paper, "Evaluation Metrics", plus the usual KITTI set).

Conventions (those of Eigen et al., the KITTI benchmark and monodepth2, so that numbers are
comparable with published ones):

* A pixel is scored iff ``min_depth < target < max_depth`` (NaN targets are never valid).
* Predictions are clamped to ``[min_depth, max_depth]`` before scoring, as monodepth2 and the KITTI
  evaluation scripts do; this bounds the relative/log/inverse errors of degenerate predictions.
* Averaging is per image: each metric is averaged over the valid pixels of one image, then over
  images. Images without any valid pixel are skipped (they would be 0/0).

Metrics, with ``d`` the prediction and ``d*`` the ground truth, means over valid pixels:

* ``abs_rel`` (the paper's ARD) = mean(|d - d*| / d*)
* ``sq_rel`` (the paper's SRD) = mean((d - d*)² / d*)
* ``rmse`` = sqrt(mean((d - d*)²)); ``mae`` = mean(|d - d*|)
* ``rmse_log`` = sqrt(mean((ln d - ln d*)²)); ``log10`` = mean(|log10 d - log10 d*|)
* ``delta{k}`` = fraction of pixels with max(d/d*, d*/d) < 1.25**k, k = 1, 2, 3
* ``irmse`` / ``imae`` = RMSE / MAE of inverse depth in 1/km (1000/d), the KITTI depth-completion
  convention.

Note on ARD/SRD: the paper's formulas divide by the *prediction*; that is a typo. Eigen et al., whom
the paper cites, and every public evaluation code divide by the ground truth, which is what is done
here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor
from torchmetrics import Metric

__all__ = [
    "HIGHER_IS_BETTER",
    "METRIC_KEYS",
    "DepthMetrics",
    "compute_depth_metrics",
    "per_image_depth_metrics",
]

METRIC_KEYS: tuple[str, ...] = (
    "abs_rel",
    "sq_rel",
    "rmse",
    "rmse_log",
    "mae",
    "log10",
    "delta1",
    "delta2",
    "delta3",
    "irmse",
    "imae",
)

HIGHER_IS_BETTER: dict[str, bool] = {k: k.startswith("delta") for k in METRIC_KEYS}
"""Per-metric optimisation direction (e.g. for checkpoint ``mode``): only the deltas go up."""


def _check_range(min_depth: float, max_depth: float) -> None:
    if not 0 < min_depth < max_depth:
        raise ValueError(
            f"need 0 < min_depth < max_depth, got min_depth={min_depth}, max_depth={max_depth}"
        )


def _flatten(pred: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
    """Check shapes and return both maps as float64 ``(B, H*W)`` (float64: sums over megapixels)."""
    if pred.shape != target.shape:
        raise ValueError(
            f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}"
        )
    if not (pred.dim() == 3 or (pred.dim() == 4 and pred.shape[1] == 1)):
        raise ValueError(
            f"expected depth maps of shape (B, 1, H, W) or (B, H, W), got {tuple(pred.shape)}"
        )
    b = pred.shape[0]
    return (
        pred.detach().reshape(b, -1).to(torch.float64),
        target.detach().reshape(b, -1).to(torch.float64),
    )


def per_image_depth_metrics(
    pred: Tensor, target: Tensor, min_depth: float, max_depth: float
) -> tuple[dict[str, Tensor], Tensor]:
    """Every metric for each image of a batch, vectorised with masked sums.

    Args:
        pred: predicted depth in metres, ``(B, 1, H, W)`` or ``(B, H, W)``.
        target: ground-truth depth, same shape; invalid pixels are those outside
            ``(min_depth, max_depth)`` (0 or NaN placeholders included).
        min_depth, max_depth: the evaluation range (see module docstring).

    Returns:
        ``(values, has_valid)``: ``values[key]`` is a float64 ``(B,)`` tensor for each key of
        :data:`METRIC_KEYS`; ``has_valid`` is a bool ``(B,)`` tensor telling which images had at
        least one valid pixel. Images without one get 0 for every metric (never NaN) and must be
        skipped using ``has_valid``.
    """
    _check_range(min_depth, max_depth)
    d, gt = _flatten(pred, target)
    valid = (gt > min_depth) & (gt < max_depth)
    n = valid.sum(dim=1)
    has_valid = n > 0
    n = n.clamp_min(1).to(torch.float64)

    # Replace invalid pixels by a harmless value so that log/divisions stay finite; masked sums use
    # torch.where, so these placeholders never reach a result.
    d = d.clamp(min_depth, max_depth)
    gt = torch.where(valid, gt, d)

    def mean(x: Tensor) -> Tensor:
        return torch.where(valid, x, torch.zeros_like(x)).sum(dim=1) / n

    err = d - gt
    sq = err * err
    ratio = torch.maximum(d / gt, gt / d)
    log_err = torch.log(d) - torch.log(gt)
    inv_err = 1000.0 / d - 1000.0 / gt
    values = {
        "abs_rel": mean(err.abs() / gt),
        "sq_rel": mean(sq / gt),
        "rmse": mean(sq).sqrt(),
        "rmse_log": mean(log_err * log_err).sqrt(),
        "mae": mean(err.abs()),
        "log10": mean(log_err.abs()) / math.log(10.0),
        "delta1": mean((ratio < 1.25).to(torch.float64)),
        "delta2": mean((ratio < 1.25**2).to(torch.float64)),
        "delta3": mean((ratio < 1.25**3).to(torch.float64)),
        "irmse": mean(inv_err * inv_err).sqrt(),
        "imae": mean(inv_err.abs()),
    }
    return values, has_valid


def compute_depth_metrics(
    pred: Tensor, target: Tensor, min_depth: float = 1e-3, max_depth: float = 80.0
) -> dict[str, float]:
    """Per-image-averaged metrics of one batch as Python floats (functional twin of DepthMetrics).

    Raises:
        ValueError: if shapes differ, or if no image has a pixel inside ``(min_depth, max_depth)``.
    """
    values, has_valid = per_image_depth_metrics(pred, target, min_depth, max_depth)
    count = int(has_valid.sum())
    if count == 0:
        raise ValueError(f"no image has a valid ground-truth pixel in ({min_depth}, {max_depth})")
    return {k: float(v[has_valid].sum() / count) for k, v in values.items()}


class DepthMetrics(Metric):
    """Accumulates per-image depth metrics across batches (and processes), optionally per condition.

    States (all summed across processes): ``sums`` ``(K,)`` float64, the sum over scored images of
    each per-image metric in :data:`METRIC_KEYS` order, and ``count`` the number of scored images;
    with ``conditions`` (e.g. ``["day", "night", "rain", "fog"]``) also ``cond_sums`` ``(G, K)`` and
    ``cond_count`` ``(G,)`` for the breakdown the paper reports per weather/lighting condition.
    Storing sums of per-image values, not per-pixel sums, is what makes the average per image.

    ``compute()`` returns a flat dict of 0-d float64 tensors: ``"abs_rel"``, ... and, with
    conditions, ``"<condition>/abs_rel"``, ... for each condition with at least one scored image.
    The metrics do not share a direction, so ``higher_is_better`` is None; see
    :data:`HIGHER_IS_BETTER` for each key.
    """

    is_differentiable = False
    higher_is_better = None
    full_state_update = False

    sums: Tensor
    count: Tensor
    cond_sums: Tensor
    cond_count: Tensor

    def __init__(
        self,
        min_depth: float = 1e-3,
        max_depth: float = 80.0,
        conditions: Sequence[str] | None = None,
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        _check_range(min_depth, max_depth)
        self.min_depth = float(min_depth)
        self.max_depth = float(max_depth)
        if isinstance(conditions, str):
            raise ValueError(
                f"conditions must be a sequence of names, got the string {conditions!r}"
            )
        self.conditions: tuple[str, ...] | None = None
        if conditions is not None:
            names = tuple(conditions)
            if not names or len(set(names)) != len(names):
                raise ValueError(f"conditions must be non-empty and unique, got {list(names)}")
            self.conditions = names
            self._cond_index = {name: i for i, name in enumerate(names)}

        k = len(METRIC_KEYS)
        self.add_state("sums", torch.zeros(k, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("count", torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")
        if self.conditions is not None:
            g = len(self.conditions)
            self.add_state(
                "cond_sums", torch.zeros(g, k, dtype=torch.float64), dist_reduce_fx="sum"
            )
            self.add_state("cond_count", torch.zeros(g, dtype=torch.float64), dist_reduce_fx="sum")

    def _condition_indices(self, condition: Sequence[str] | str, batch: int) -> Tensor:
        """Map one condition name per image (a single string applies to the whole batch)."""
        if self.conditions is None:
            raise ValueError("a condition was passed but DepthMetrics was built without conditions")
        names = [condition] * batch if isinstance(condition, str) else list(condition)
        if len(names) != batch:
            raise ValueError(f"got {len(names)} condition names for a batch of {batch} images")
        unknown = sorted({name for name in names if name not in self._cond_index})
        if unknown:
            raise ValueError(
                f"unknown condition(s) {unknown}; known conditions: {list(self.conditions)}"
            )
        return torch.tensor(
            [self._cond_index[name] for name in names], dtype=torch.long, device=self.sums.device
        )

    def update(self, pred: Tensor, target: Tensor, condition: Sequence[str] | None = None) -> None:
        """Score a batch of depth maps in metres, ``(B, 1, H, W)`` or ``(B, H, W)``.

        ``condition`` gives one known condition name per image (or one string for the whole batch);
        without it the images only count towards the overall metrics.
        """
        idx = None
        if condition is not None:
            # Validate before touching any state, so a bad batch leaves the metric unchanged.
            idx = self._condition_indices(condition, pred.shape[0])
        values, has_valid = per_image_depth_metrics(pred, target, self.min_depth, self.max_depth)
        per_image = torch.stack([values[k] for k in METRIC_KEYS], dim=1)  # (B, K)
        per_image = torch.where(has_valid[:, None], per_image, torch.zeros_like(per_image))
        weight = has_valid.to(torch.float64)
        self.sums += per_image.sum(dim=0)
        self.count += weight.sum()
        if idx is not None:
            self.cond_sums.index_add_(0, idx, per_image)
            self.cond_count.index_add_(0, idx, weight)

    def compute(self) -> dict[str, Tensor]:
        """Mean over scored images; raises ValueError if none was scored."""
        if self.count <= 0:
            raise ValueError(
                "DepthMetrics has not scored any image: no ground-truth pixel in "
                f"({self.min_depth}, {self.max_depth}) was seen"
            )
        out = {k: v for k, v in zip(METRIC_KEYS, self.sums / self.count, strict=True)}
        if self.conditions is not None:
            for g, name in enumerate(self.conditions):
                if self.cond_count[g] > 0:
                    means = self.cond_sums[g] / self.cond_count[g]
                    out.update({f"{name}/{k}": v for k, v in zip(METRIC_KEYS, means, strict=True)})
        return out
