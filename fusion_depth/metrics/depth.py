"""Depth evaluation metrics in metres (paper, "Evaluation Metrics", plus the usual KITTI set).

Conventions (those of Eigen et al., the KITTI benchmark and monodepth2, so that numbers are
comparable with published ones):

* A pixel is scored iff ``min_depth < target < max_depth`` (NaN targets are never valid).
* Predictions are clamped to ``[min_depth, max_depth]`` before scoring, as monodepth2's evaluation
  does; this bounds the relative/log/inverse errors of degenerate predictions.
  ``clamp=False`` scores the raw prediction (RadarNet's evaluation); ``min_depth`` may then be 0
  (every target above 0 counts).
* Averaging is per image by default (KITTI, monodepth2): each metric is averaged over the valid
  pixels of one image, then over images. ``averaging="pooled"`` (DenseDepth) averages over every
  valid pixel of the set at once, so large images and dense ground truth weigh more. Images
  without any valid pixel are skipped (they would be 0/0).
* ``max_depth`` may be several caps (RadarNet reports 50, 70 and 80 m): each cap is scored in the
  same pass, with predictions clamped to ``[min_depth, cap]``; the largest is the headline.
* ``quantize="kitti_png"`` first reads each prediction as the KITTI devkit reads a submission's
  uint16 PNG (truncated to 1/256 m, empty pixels filled from their neighbours).
* ``crop`` keeps only the Garg et al. or Eigen et al. region of the frame, given as fractions of the
  *original* frame (KITTI's convention); a sample's ``frame_box`` says where that frame lies when a
  reader padded or cropped it.

Metrics, with ``d`` the prediction and ``d*`` the ground truth, means over valid pixels:

* ``abs_rel`` (the paper's ARD) = mean(|d - d*| / d*)
* ``sq_rel`` (the paper's SRD) = mean((d - d*)² / d*)
* ``rmse`` = sqrt(mean((d - d*)²)); ``mae`` = mean(|d - d*|)
* ``rmse_log`` = sqrt(mean((ln d - ln d*)²)); ``log10`` = mean(|log10 d - log10 d*|)
* ``delta{k}`` = fraction of pixels with max(d/d*, d*/d) < 1.25**k, k = 1, 2, 3
* ``irmse`` / ``imae`` = RMSE / MAE of inverse depth in 1/km (1000/d), the KITTI depth-completion
  convention.

Note on ARD/SRD: the paper's formulas divide by the *prediction*; that is a typo. Eigen et al., whom
the paper cites, and the evaluation code of monodepth2 and the KITTI devkit divide by the ground
truth, which is what is done here by default. DenseDepth's ``utils.py`` passes its arguments
swapped and so divides by the prediction: ``relative_to="prediction"`` (``eval=densedepth``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from contextlib import AbstractContextManager

import numpy as np
import torch
from torch import Tensor
from torchmetrics import Metric

from fusion_depth.errors import check_choice

__all__ = [
    "AVERAGING",
    "EVAL_CROPS",
    "HIGHER_IS_BETTER",
    "METRIC_KEYS",
    "METRIC_LABELS",
    "METRIC_LATEX",
    "RELATIVE_TO",
    "TABLE_METRICS",
    "UNITS",
    "DepthMetrics",
    "compute_depth_metrics",
    "crop_mask",
    "scored_mask",
    "depth_error_sums",
    "metric_header",
    "metric_in_units",
    "metrics_from_sums",
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

# Display names: the paper's (Sec. 4.2: ARD, SRD, RMSE, δ) where it names a metric, the KITTI
# depth-completion benchmark's for the inverse ones, otherwise the key in capitals; and the same
# names for LaTeX tables.
_NAMES = {
    "abs_rel": "ARD",
    "sq_rel": "SRD",
    "delta1": "δ1",
    "delta2": "δ2",
    "delta3": "δ3",
    "irmse": "iRMSE",
    "imae": "iMAE",
}
METRIC_LABELS: dict[str, str] = {k: _NAMES.get(k, k.upper()) for k in METRIC_KEYS}
"""Column header of each metric in printed tables (``abs_rel`` → ``ARD``, ``delta1`` → ``δ1``)."""
METRIC_LATEX: dict[str, str] = {
    k: rf"$\delta_{k[-1]}$" if k.startswith("delta") else METRIC_LABELS[k] for k in METRIC_KEYS
}
"""Column header of each metric in LaTeX tables."""
TABLE_METRICS: tuple[str, ...] = ("rmse", "abs_rel", "sq_rel", "mae", "delta1", "delta2", "delta3")
"""The metrics printed tables show, in the paper's order (RMSE, ARD, SRD, δ1–δ3) with MAE after
SRD; ``metrics.json`` and ``per_image.csv`` hold all of :data:`METRIC_KEYS`."""


UNITS: tuple[str, ...] = ("m", "mm")
"""Units a table prints RMSE, MAE and SRD in (``eval.units``); metrics.json holds metres."""
# Metrics whose value is a length (SRD: squared metres over metres): scaled by the units.
_LENGTH_METRICS = frozenset({"rmse", "mae", "sq_rel"})


def metric_in_units(key: str, value: float, units: str) -> float:
    """``value`` of metric ``key`` (as metrics.json holds it: metres, 1/km) in ``units``."""
    return value * 1000.0 if units == "mm" and key in _LENGTH_METRICS else value


def metric_header(key: str, units: str = "m", latex: bool = False) -> str:
    """A table's column header of ``key`` in ``units``: ``RMSE``, ``RMSE (mm)``, ``iMAE (1/km)``
    (LaTeX: :data:`METRIC_LATEX`'s name); a key that is no metric, as it is."""
    names = METRIC_LATEX if latex else METRIC_LABELS
    if key not in names:
        return key.replace("_", r"\_") if latex else key
    if key in _LENGTH_METRICS and units == "mm":
        return f"{names[key]} (mm)"
    if key in ("irmse", "imae"):
        return f"{names[key]} (1/km)"
    return names[key]


# What δ and the log errors take an unclamped prediction of 0 or less as: 1 µm.
_SMALLEST_DEPTH = 1e-6

# Metrics that are square roots of a mean: their per-pixel sum holds the squared error.
_ROOT_KEYS = frozenset({"rmse", "rmse_log", "irmse"})
_ROOT_MASK = torch.tensor([k in _ROOT_KEYS for k in METRIC_KEYS])

AVERAGING: tuple[str, ...] = ("per_image", "pooled")
RELATIVE_TO: tuple[str, ...] = ("ground_truth", "prediction")
"""What ARD and SRD divide by: the ground truth (Eigen et al.), or the prediction (DenseDepth's
utils.py, which calls ``compute_errors(predictions, gt)`` with its arguments swapped)."""

QUANTIZATIONS: tuple[str, ...] = ("none", "kitti_png")
"""How a prediction is read before scoring: as it is, or as the KITTI devkit reads a submission
(:func:`kitti_png_prediction`)."""
KITTI_PNG_SCALE = 256.0  # a KITTI depth PNG stores 256 · metres as uint16
KITTI_PNG_MAX = 65535


def kitti_png_prediction(pred: Tensor) -> Tensor:
    """Depth maps ``(B, 1, H, W)`` or ``(B, H, W)`` in metres as the KITTI depth-completion
    devkit scores them from a submission's uint16 PNGs: ``floor(256 d)`` clipped to
    ``[0, 65535]``, divided by 256 (so at most 255.996 m, truncated to 1/256 m); a pixel that
    stores 0 (a prediction below 1/256 m) is invalid, and each image's invalid pixels are filled
    by :func:`kitti_interpolate_background`.

    Source: the devkit's ``cpp/io_depth.h`` (``readDepthMap``, ``interpolateBackground``) and
    ``cpp/evaluate_depth.cpp``, which scores ``D_ipol``, the interpolated prediction.

    Returns:
        A tensor of ``pred``'s shape, dtype and device.
    """
    stored = torch.floor(pred.clamp(0.0, KITTI_PNG_MAX / KITTI_PNG_SCALE) * KITTI_PNG_SCALE)
    depth = torch.where(stored > 0, stored / KITTI_PNG_SCALE, torch.full_like(pred, -1.0))
    if not (stored == 0).any():
        return depth
    images = depth.detach().reshape(-1, *pred.shape[-2:]).cpu().double().numpy()
    filled = np.stack([kitti_interpolate_background(image) for image in images])
    return torch.from_numpy(filled).to(pred.device, pred.dtype).reshape(pred.shape)


def kitti_interpolate_background(depth: np.ndarray) -> np.ndarray:
    """The KITTI devkit's ``DepthImage::interpolateBackground`` on one ``(H, W)`` map whose
    invalid pixels are negative: per row, a run of invalid pixels between two valid ones takes
    the smaller of the two, and the runs at the row's ends take the nearest valid value; then per
    column, the rows above the first valid one and below the last take its value (so a row with
    no valid pixel between valid rows stays invalid, as there).

    Source: ``cpp/io_depth.h`` of the KITTI depth devkit.

    Returns:
        A filled float64 copy.
    """
    out = np.array(depth, dtype=np.float64)
    for row in out:
        valid = np.flatnonzero(row >= 0)
        if not len(valid) or len(valid) == len(row):
            continue
        gaps = np.flatnonzero(row < 0)
        inner = gaps[(gaps > valid[0]) & (gaps < valid[-1])]
        right = valid[np.searchsorted(valid, inner)]
        row[inner] = np.minimum(row[right], row[valid[np.searchsorted(valid, inner) - 1]])
        row[: valid[0]] = row[valid[0]]
        row[valid[-1] + 1 :] = row[valid[-1]]
    rows = np.flatnonzero((out >= 0).any(axis=1))  # after the rows: each row all or nothing
    if len(rows):
        out[: rows[0]] = out[rows[0]]
        out[rows[-1] + 1 :] = out[rows[-1]]
    return out


# Evaluation crops as (top, bottom, left, right) fractions of the full frame: Garg et al. (ECCV
# 2016) and Eigen et al. (NIPS 2014), with the constants of the monodepth2/KITTI scripts.
EVAL_CROPS: dict[str, tuple[float, float, float, float] | None] = {
    "none": None,
    "garg": (0.40810811, 0.99189189, 0.03594771, 0.96405229),
    "eigen": (0.3324324, 0.91351351, 0.0359477, 0.96405229),
}


def _check_range(min_depth: float, max_depth: float, clamp: bool = True) -> None:
    """A clamped prediction must stay positive, so clamping needs ``min_depth > 0``."""
    if not (0 < min_depth if clamp else 0 <= min_depth) or not min_depth < max_depth:
        floor = "0 < min_depth" if clamp else "0 <= min_depth"
        raise ValueError(
            f"need {floor} < max_depth, got min_depth={min_depth}, max_depth={max_depth}"
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


def crop_mask(
    shape: tuple[int, int],
    crop: str,
    frame_box: Tensor | None = None,
    batch: int = 1,
    device: torch.device | str | None = None,
) -> Tensor:
    """Bool ``(B, H, W)``: True inside ``EVAL_CROPS[crop]`` (everywhere for ``"none"``).

    ``frame_box`` ``(B, 4)`` holds ``(top, left, height, width)`` of each original frame in the
    map's pixel coordinates (negative when a reader cut rows or columns off); without it the map
    is the frame. Rows ``top + int(f · height)`` follow the KITTI scripts' rounding.
    """
    check_choice(crop, list(EVAL_CROPS), "crop", owner=crop_mask)
    height, width = shape
    fractions = EVAL_CROPS[crop]
    if fractions is None:
        return torch.ones(batch, height, width, dtype=torch.bool, device=device)
    if frame_box is None:
        frame_box = torch.tensor([[0, 0, height, width]], device=device).expand(batch, 4)
    rows = torch.arange(height, device=device)
    cols = torch.arange(width, device=device)
    masks = []
    for top, left, h, w in frame_box.tolist():
        t, b, lft, r = (
            offset + int(f * size)
            for f, size, offset in zip(fractions, (h, h, w, w), (top, top, left, left), strict=True)
        )
        masks.append(((rows >= t) & (rows < b))[:, None] & ((cols >= lft) & (cols < r))[None, :])
    return torch.stack(masks)


def depth_error_sums(
    pred: Tensor,
    target: Tensor,
    valid: Tensor,
    min_depth: float,
    max_depth: float,
    clamp: bool = True,
    relative_to: str = "ground_truth",
) -> tuple[Tensor, Tensor]:
    """Per-image sums of each metric's per-pixel term over ``valid`` pixels, and their count.

    Returns float64 ``sums`` ``(B, K)`` in :data:`METRIC_KEYS` order (the squared error for the
    root metrics) and ``counts`` ``(B,)``. Every averaging follows from these: per image
    ``sums / counts``, pooled ``sums.sum(0) / counts.sum()`` (see :func:`metrics_from_sums`).
    Predictions are clamped to ``[min_depth, max_depth]`` first, unless ``clamp`` is False: then
    MAE, RMSE and the inverse errors score them as they are, as RadarNet's code does (a
    prediction of 0 gives an infinite inverse error there too); δ and the log errors, which
    those references do not compute, take a prediction of 0 or less as 1 µm, so it is wrong
    by every threshold and its log error stays finite. ARD and SRD divide by ``relative_to``
    (:data:`RELATIVE_TO`).
    """
    d, gt = _flatten(pred, target)
    valid = valid.reshape(d.shape) & torch.isfinite(gt) & (gt > 0)
    # Invalid pixels get a harmless value so that log/divisions stay finite; torch.where below
    # keeps these placeholders out of every sum.
    if clamp:
        d = d.clamp(min_depth, max_depth)
    gt = torch.where(valid, gt, d)
    err = d - gt
    sq = err * err
    # An unclamped prediction of 0 or less is wrong by every ratio: δ and the log errors see
    # it as 1 µm (the references that do not clamp compute neither).
    positive = d.clamp_min(_SMALLEST_DEPTH) if not clamp else d
    ratio = torch.maximum(positive / gt, gt / positive)
    log_err = torch.log(positive) - torch.log(gt)
    inv_err = 1000.0 / d - 1000.0 / gt
    base = gt if relative_to == "ground_truth" else d
    terms = {
        "abs_rel": err.abs() / base,
        "sq_rel": sq / base,
        "rmse": sq,
        "rmse_log": log_err * log_err,
        "mae": err.abs(),
        "log10": log_err.abs() / math.log(10.0),
        "delta1": (ratio < 1.25).to(torch.float64),
        "delta2": (ratio < 1.25**2).to(torch.float64),
        "delta3": (ratio < 1.25**3).to(torch.float64),
        "irmse": inv_err * inv_err,
        "imae": inv_err.abs(),
    }
    zero = torch.zeros((), dtype=torch.float64, device=d.device)
    sums = torch.stack([torch.where(valid, terms[k], zero).sum(dim=1) for k in METRIC_KEYS], 1)
    return sums, valid.sum(dim=1).to(torch.float64)


def metrics_from_sums(sums: Tensor, counts: Tensor) -> Tensor:
    """Metric values ``(..., K)`` from sums ``(..., K)`` over ``counts`` ``(...)`` pixels (> 0)."""
    means = sums / counts.unsqueeze(-1)
    return torch.where(_ROOT_MASK.to(means.device), means.sqrt(), means)


def per_image_depth_metrics(
    pred: Tensor, target: Tensor, min_depth: float, max_depth: float, clamp: bool = True
) -> tuple[dict[str, Tensor], Tensor]:
    """Every metric for each image of a batch, vectorised with masked sums.

    Args:
        pred: predicted depth in metres, ``(B, 1, H, W)`` or ``(B, H, W)``.
        target: ground-truth depth, same shape; invalid pixels are those outside
            ``(min_depth, max_depth)`` (0 or NaN placeholders included).
        min_depth: the evaluation range's lower end in metres (see module docstring).
        max_depth: its upper end (the cap) in metres.
        clamp: clamp predictions to ``[min_depth, max_depth]`` first (see module docstring).

    Returns:
        ``(values, has_valid)``: ``values[key]`` is a float64 ``(B,)`` tensor for each key of
        :data:`METRIC_KEYS`; ``has_valid`` is a bool ``(B,)`` tensor telling which images had at
        least one valid pixel. Images without one get 0 for every metric (never NaN) and must be
        skipped using ``has_valid``.
    """
    _check_range(min_depth, max_depth, clamp)
    valid = (target > min_depth) & (target < max_depth)
    sums, counts = depth_error_sums(pred, target, valid, min_depth, max_depth, clamp)
    has_valid = counts > 0
    values = metrics_from_sums(sums, counts.clamp_min(1))
    values = torch.where(has_valid[:, None], values, torch.zeros_like(values))
    return {k: values[:, i] for i, k in enumerate(METRIC_KEYS)}, has_valid


def _aggregate(sums: Tensor, counts: Tensor, averaging: str) -> dict[str, float] | None:
    """Metrics over a set of images (rows) by ``averaging``; None when no image was scored."""
    scored = counts > 0
    if not bool(scored.any()):
        return None
    if averaging == "pooled":
        values = metrics_from_sums(sums[scored].sum(0), counts[scored].sum())
    else:
        values = metrics_from_sums(sums[scored], counts[scored]).mean(0)
    out = {k: float(v) for k, v in zip(METRIC_KEYS, values, strict=True)}
    out["num_images"] = int(scored.sum())
    out["num_pixels"] = int(counts.sum())
    return out


def _check_averaging(averaging: str) -> str:
    check_choice(averaging, AVERAGING, "averaging", owner=_check_averaging)
    return averaging


def _check_relative_to(relative_to: str) -> str:
    check_choice(relative_to, RELATIVE_TO, "relative_to", owner=_check_relative_to)
    return relative_to


def scored_mask(
    target: Tensor,
    min_depth: float,
    max_depth: float,
    crop: str = "none",
    frame_box: Tensor | None = None,
) -> Tensor:
    """Bool ``(B, H·W)``: the pixels a metric scores, ground truth in ``(min_depth,
    max_depth)`` metres inside the evaluation ``crop`` (see :func:`crop_mask`).

    Shape:
        target: ``(B, 1, H, W)`` or ``(B, H, W)``; frame_box: ``(B, 4)``.
    """
    b = target.shape[0]
    valid = ((target > min_depth) & (target < max_depth)).reshape(b, -1)
    return valid & crop_mask(tuple(target.shape[-2:]), crop, frame_box, b, target.device).reshape(
        b, -1
    )


def compute_depth_metrics(
    pred: Tensor,
    target: Tensor,
    min_depth: float = 1e-3,
    max_depth: float = 80.0,
    averaging: str = "per_image",
    crop: str = "none",
    frame_box: Tensor | None = None,
    clamp: bool = True,
    relative_to: str = "ground_truth",
) -> dict[str, float]:
    """Metrics of one batch as Python floats (functional twin of DepthMetrics, one cap).

    Args:
        pred: predicted depth in metres, ``(B, 1, H, W)`` or ``(B, H, W)``.
        target: ground-truth depth in metres, same shape; 0 or NaN where there is none.
        min_depth: a pixel counts iff ``min_depth < target < max_depth`` (metres).
        max_depth: the cap, in metres.
        averaging: ``per_image`` or ``pooled`` (:data:`AVERAGING`).
        crop: a key of :data:`EVAL_CROPS`; ``frame_box`` places it (:func:`crop_mask`).
        clamp: clamp predictions to ``[min_depth, max_depth]`` first.
        relative_to: what ARD and SRD divide by (:data:`RELATIVE_TO`).

    Raises:
        ValueError: if shapes differ, an option is unknown, or no image has a pixel inside
            ``(min_depth, max_depth)``.
    """
    _check_range(min_depth, max_depth, clamp)
    _check_averaging(averaging)
    _check_relative_to(relative_to)
    valid = scored_mask(target, min_depth, max_depth, crop, frame_box)
    sums, counts = depth_error_sums(pred, target, valid, min_depth, max_depth, clamp, relative_to)
    out = _aggregate(sums, counts, averaging)
    if out is None:
        raise ValueError(f"no image has a valid ground-truth pixel in ({min_depth}, {max_depth})")
    return {k: out[k] for k in METRIC_KEYS}


def _label(value: float) -> str:
    return f"{value:g}"


class DepthMetrics(Metric):
    """Accumulates depth metrics across batches (and processes), with the evaluation breakdowns.

    Each update stores, per image, the per-pixel sums of every metric term and the pixel count
    for each scoring *region*: one per depth cap in ``max_depth`` and one per distance bin
    (``distance_bins`` edges in metres, scored within the headline cap). States are lists
    concatenated across processes (``dist_reduce_fx="cat"``): ``image_sums`` ``(N, R, K)``,
    ``image_counts`` ``(N, R)``, ``image_condition`` ``(N,)`` (index into ``conditions``, -1 for
    none) and ``image_index`` ``(N,)`` (the sample's position in its split, -1 if unknown).
    Keeping per-image sums is what lets one pass give per-image and pooled averages, every
    breakdown, and the per-image records a paired comparison between models needs.

    ``compute()`` returns a flat dict of 0-d float64 tensors for the headline cap: ``"abs_rel"``,
    ... and, with conditions, ``"<condition>/abs_rel"``, ... for each condition with a scored
    image. :meth:`results` gives every breakdown; :meth:`per_image` the per-image records. The
    metrics do not share a direction, so ``higher_is_better`` is None; see
    :data:`HIGHER_IS_BETTER` for each key. ``quantize="kitti_png"`` scores each prediction as
    the KITTI devkit reads it from a submission's PNG (:func:`kitti_png_prediction`).
    """

    is_differentiable = False
    higher_is_better = None
    full_state_update = False

    image_sums: list[Tensor]
    image_counts: list[Tensor]
    image_condition: list[Tensor]
    image_index: list[Tensor]

    def __init__(
        self,
        min_depth: float = 1e-3,
        max_depth: float | Sequence[float] = 80.0,
        conditions: Sequence[str] | None = None,
        averaging: str = "per_image",
        crop: str = "none",
        distance_bins: Sequence[float] | None = None,
        clamp: bool = True,
        relative_to: str = "ground_truth",
        quantize: str = "none",
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        check_choice(quantize, QUANTIZATIONS, "quantize", owner=DepthMetrics)
        self.quantize = quantize
        caps = [max_depth] if isinstance(max_depth, int | float) else list(max_depth)
        if not caps:
            raise ValueError("max_depth: expected a depth cap or a non-empty list of caps")
        for cap in caps:
            _check_range(min_depth, cap, clamp)
        self.clamp = bool(clamp)
        self.relative_to = _check_relative_to(relative_to)
        self.min_depth = float(min_depth)
        self.caps = sorted({float(c) for c in caps})
        self.max_depth = self.caps[-1]  # the headline cap
        self.averaging = _check_averaging(averaging)
        crop_mask((1, 1), crop)  # validates the name
        self.crop = crop
        self.bins: list[tuple[float, float]] = []
        if distance_bins is not None:
            edges = [float(e) for e in distance_bins]
            if len(edges) < 2 or any(b <= a for a, b in zip(edges, edges[1:], strict=False)):
                raise ValueError(
                    f"distance_bins={list(distance_bins)}: expected at least two increasing edges"
                )
            self.bins = list(zip(edges, edges[1:], strict=False))
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
        for name in ("image_sums", "image_counts", "image_condition", "image_index"):
            self.add_state(name, default=[], dist_reduce_fx="cat")

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
        return torch.tensor([self._cond_index[name] for name in names], dtype=torch.long)

    def update(
        self,
        pred: Tensor,
        target: Tensor,
        condition: Sequence[str] | str | None = None,
        index: Tensor | None = None,
        frame_box: Tensor | None = None,
    ) -> None:
        """Score a batch of depth maps in metres, ``(B, 1, H, W)`` or ``(B, H, W)``.

        ``condition`` gives one known condition name per image (or one string for the whole
        batch); ``index`` each image's position in its split; ``frame_box`` ``(B, 4)`` where each
        original frame lies (see :func:`crop_mask`).
        """
        b = pred.shape[0]
        # Validate before touching any state, so a bad batch leaves the metric unchanged.
        cond = (
            torch.full((b,), -1, dtype=torch.long)
            if condition is None
            else self._condition_indices(condition, b)
        )
        if pred.shape != target.shape:
            raise ValueError(
                f"pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}"
            )
        if self.quantize == "kitti_png":
            pred = kitti_png_prediction(pred)
        flat_target = target.detach().reshape(b, -1)
        base = crop_mask(tuple(target.shape[-2:]), self.crop, frame_box, b, target.device)
        base = base.reshape(b, -1) & (flat_target > self.min_depth)
        regions = [(base & (flat_target < cap), cap) for cap in self.caps]
        regions += [
            (
                base & (flat_target < self.max_depth) & (flat_target >= lo) & (flat_target < hi),
                self.max_depth,
            )
            for lo, hi in self.bins
        ]
        sums, counts = zip(
            *(
                depth_error_sums(pred, target, m, self.min_depth, cap, self.clamp, self.relative_to)
                for m, cap in regions
            ),
            strict=True,
        )
        self.image_sums.append(torch.stack(sums, dim=1))
        self.image_counts.append(torch.stack(counts, dim=1))
        self.image_condition.append(cond.to(self.device))
        idx = torch.full((b,), -1, dtype=torch.long) if index is None else index.reshape(b)
        self.image_index.append(idx.to(device=self.device, dtype=torch.long))

    def _states(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        def cat(state: list[Tensor] | Tensor) -> Tensor:
            # After a distributed sync a list state is already one concatenated tensor.
            return torch.cat(state) if isinstance(state, list) else state

        if len(self.image_sums) == 0:  # an empty list, or an empty tensor after a sync
            raise ValueError("DepthMetrics has not seen any image (update was never called)")
        return (
            cat(self.image_sums).cpu(),
            cat(self.image_counts).cpu(),
            cat(self.image_condition).cpu(),
            cat(self.image_index).cpu(),
        )

    def _headline(self, sums: Tensor, counts: Tensor) -> tuple[Tensor, Tensor]:
        r = self.caps.index(self.max_depth)
        return sums[:, r], counts[:, r]

    def compute(self) -> dict[str, Tensor]:
        """Headline-cap metrics (and per condition); raises ValueError if nothing was scored."""
        results = self._results()  # torchmetrics has already gathered the states of all processes
        groups = {"": results["overall"]}
        groups.update({f"{name}/": group for name, group in results["by_condition"].items()})
        return {
            f"{prefix}{k}": torch.tensor(group[k], dtype=torch.float64)
            for prefix, group in groups.items()
            for k in METRIC_KEYS
        }

    def results(self) -> dict[str, dict]:
        """Every breakdown as plain data: ``overall``, ``by_condition``, ``by_distance``
        (``"0-10"``, ... m, within the headline cap) and ``by_cap`` (``"50"``, ...), each with
        ``num_images`` and ``num_pixels``; groups without a scored image are left out. Under
        distributed evaluation the images of every process count."""
        with self._gathered():
            return self._results()

    def _gathered(self) -> AbstractContextManager:
        """The states of every process while inside (nothing to do when already synced)."""
        return self.sync_context(should_sync=not self._is_synced, should_unsync=not self._is_synced)

    def _results(self) -> dict[str, dict]:
        sums, counts, cond, _ = self._states()
        head_sums, head_counts = self._headline(sums, counts)
        overall = _aggregate(head_sums, head_counts, self.averaging)
        if overall is None:
            raise ValueError(
                "DepthMetrics has not scored any image: no ground-truth pixel in "
                f"({self.min_depth}, {self.max_depth}) was seen"
            )
        by_condition = {}
        for g, name in enumerate(self.conditions or ()):
            group = _aggregate(head_sums[cond == g], head_counts[cond == g], self.averaging)
            if group is not None:
                by_condition[name] = group
        by_cap = {
            _label(cap): _aggregate(sums[:, r], counts[:, r], self.averaging)
            for r, cap in enumerate(self.caps)
        }
        by_distance = {}
        for j, (lo, hi) in enumerate(self.bins):
            r = len(self.caps) + j
            group = _aggregate(sums[:, r], counts[:, r], self.averaging)
            if group is not None:
                by_distance[f"{_label(lo)}-{_label(hi)}"] = group
        return {
            "overall": overall,
            "by_condition": by_condition,
            "by_distance": by_distance,
            "by_cap": {k: v for k, v in by_cap.items() if v is not None},
        }

    def per_image(self) -> list[dict]:
        """One record per scored image (headline cap): ``index``, ``condition``, ``num_pixels``
        and every metric; ordered by ``index``; every process's images under distributed
        evaluation."""
        with self._gathered():
            sums, counts, cond, index = self._states()
        head_sums, head_counts = self._headline(sums, counts)
        scored = head_counts > 0
        values = metrics_from_sums(head_sums[scored], head_counts[scored])
        names = self.conditions or ()
        rows = [
            {
                "index": int(i),
                "condition": names[c] if c >= 0 else "",
                "num_pixels": int(n),
                **{k: float(v) for k, v in zip(METRIC_KEYS, row, strict=True)},
            }
            for i, c, n, row in zip(
                index[scored].tolist(),
                cond[scored].tolist(),
                head_counts[scored].tolist(),
                values,
                strict=True,
            )
        ]
        return sorted(rows, key=lambda r: r["index"])
