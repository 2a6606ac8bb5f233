"""Depth in metres from a trained network, at the resolution of the ground truth or the input.

Shared by evaluation (test stage, ``evaluate``) and ``predict``, so every entry point turns the
network's output (DenseDepth: reciprocal depth at half resolution) into metres the same way.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from fusion_depth.errors import check_choice
from fusion_depth.models import DepthModel

UPSAMPLING = ("bilinear", "nearest", "bilinear_reflect")
"""How a depth map is resized to the ground truth's size: bilinear (pixel areas aligned, edges
replicated: ``F.interpolate(align_corners=False)``), nearest, or bilinear with mirrored edges
(``bilinear_reflect``: scikit-image's ``resize(order=1, mode="reflect")``, which DenseDepth's
``utils.py`` ``scale_up`` calls)."""


def _check_upsample(mode: str) -> None:
    check_choice(mode, UPSAMPLING, "upsample", owner=predict_depth)


def resize_depth(
    depth: torch.Tensor, size: tuple[int, int], mode: str = "bilinear"
) -> torch.Tensor:
    """Depth ``(B, 1, h, w)`` → ``(B, 1, *size)`` by one of :data:`UPSAMPLING`.

    Raises:
        ArgumentError: ``mode`` is not one of :data:`UPSAMPLING` (naming ``upsample``).
    """
    _check_upsample(mode)
    if tuple(depth.shape[-2:]) == tuple(size):
        return depth
    if mode == "nearest":
        return F.interpolate(depth, size=size, mode="nearest")
    if mode == "bilinear_reflect":
        return _linear_mirrored(_linear_mirrored(depth, size[0], -2), size[1], -1)
    return F.interpolate(depth, size=size, mode="bilinear", align_corners=False)


def depth_at_points(depth: torch.Tensor, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A depth map read at ground-truth points, as the metrics take maps.

    Reads ``depth`` bilinearly at each point's ``(y, x)``, pixel areas aligned and edges
    replicated: the value ``resize_depth(depth, full_size, "bilinear")`` holds at that point's
    full-resolution pixel, when ``(y, x)`` is that pixel's centre in ``depth``'s coordinates
    (:func:`fusion_depth.data.nuscenes.full_resolution_points`).

    Shape:
        - depth: (B, 1, H, W) metres.
        - points: (B, Q, 3) rows ``y, x, depth`` (pixel centres at integers; depth 0: a padding
          row, never scored), a batch's ``depth_points``.
        - output: ``(prediction, target)``, each (B, 1, 1, Q) metres, float32 or wider (read
          with autocast off).
    """
    height, width = depth.shape[-2:]
    # At least fp32, autocast off: bf16 would move a column near 800 by a whole pixel.
    dtype = torch.promote_types(depth.dtype, torch.float32)
    y, x, target = points.to(dtype).unbind(-1)
    grid = torch.stack([(2 * x + 1) / width - 1, (2 * y + 1) / height - 1], dim=-1)
    with torch.autocast(depth.device.type, enabled=False):
        read = F.grid_sample(
            depth.to(dtype),
            grid.unsqueeze(1),
            mode="bilinear",
            padding_mode="border",
            align_corners=False,
        )
    return read, target[:, None, None, :]


def _linear_mirrored(x: torch.Tensor, size: int, dim: int) -> torch.Tensor:
    """Linear resampling of ``x`` along ``dim`` to ``size`` samples, pixel areas aligned (output
    ``i`` reads input ``(i + 0.5) n / size - 0.5``), samples past an edge mirrored about the edge
    pixel (``x[-1]`` reads ``x[1]``: SciPy's ``mode="mirror"``, scikit-image's ``"reflect"``)."""
    n = x.shape[dim]
    position = (torch.arange(size, dtype=torch.float64, device=x.device) + 0.5) * n / size - 0.5
    low = torch.floor(position)
    weight = (position - low).to(x.dtype)
    low = low.long()

    def mirrored(index: torch.Tensor) -> torch.Tensor:
        if n == 1:
            return torch.zeros_like(index)
        period = 2 * (n - 1)
        index = index.remainder(period)
        return torch.where(index > n - 1, period - index, index)

    shape = [1] * x.dim()
    shape[dim] = size
    weight = weight.view(shape)
    a = x.index_select(dim, mirrored(low))
    b = x.index_select(dim, mirrored(low + 1))
    return a * (1 - weight) + b * weight


@torch.no_grad()
def predict_depth(
    net: DepthModel,
    image: torch.Tensor,
    sparse: torch.Tensor | None = None,
    flip_tta: bool = False,
    size: tuple[int, int] | None = None,
    upsample: str = "bilinear",
    points: torch.Tensor | None = None,
    prior: torch.Tensor | None = None,
) -> torch.Tensor:
    """Depth in metres ``(B, 1, *size)`` for images ``(B, 3, H, W)`` in [0, 1]. Sides that are
    not multiples of 32 (the network's :attr:`~fusion_depth.models.DepthModel.input_multiple`)
    are padded at the bottom/right (edges replicated; sparse maps with 0) and cut back, so any
    image size works.

    Args:
        net: a checkpoint's network (:func:`~fusion_depth.runner.checkpoints.load_model`) or an
            exported model's (:func:`~fusion_depth.export.runtime.load_exported`), in eval mode;
            call this under ``torch.no_grad()``.
        image: float ``(B, 3, H, W)``, RGB in [0, 1]; an exported model takes only its size.
        sparse: float ``(B, 1, H, W)`` depth in metres, 0 = no return; a fusion model needs it,
            an RGB one (``fusion=rgb``) ignores it.
        flip_tta: average with the mirrored prediction of the mirrored input (DenseDepth's
            test-time augmentation).
        size: ``(height, width)`` of the output; None: the input's.
        upsample: how the output is resized, one of :data:`UPSAMPLING`.
        points: float ``(B, P, 6)``, the batch's ``radar_points`` (columns
            :data:`~fusion_depth.data.RADAR_POINT_FIELDS`), for a network that takes them
            (``model=radarnet``); mirrored with the image under ``flip_tta``.
        prior: float ``(B, 1, H, W)``, the batch's cached prior, for a network built with one,
            in place of running it (padded and mirrored as the image); None: it runs its prior.

    Raises:
        ArgumentError: ``upsample`` is not one of :data:`UPSAMPLING`.
    """
    _check_upsample(upsample)
    sparse = sparse if net.fusion.uses_sparse else None
    height, width = image.shape[-2:]
    multiple = getattr(net, "input_multiple", 32)  # an exported model's wrapper: 32
    pad_h, pad_w = -height % multiple, -width % multiple
    if pad_h or pad_w:
        image = F.pad(image, (0, pad_w, 0, pad_h), mode="replicate")
        if sparse is not None:
            sparse = F.pad(sparse, (0, pad_w, 0, pad_h))
        if prior is not None:
            prior = F.pad(prior, (0, pad_w, 0, pad_h), mode="replicate")
    points = points if getattr(net, "takes_points", False) else None

    def run(image: torch.Tensor, sparse: torch.Tensor | None, points, prior) -> torch.Tensor:
        # Only what is given is passed: a network without a prior need not accept one.
        given = {} if prior is None else {"prior": prior}
        if points is not None:
            return net.predict_depth(image, sparse, points, **given)
        return net.predict_depth(image, sparse, **given)

    depth = run(image, sparse, points, prior)
    if flip_tta:
        flipped = None
        if points is not None:  # column u of a W-wide image mirrors to W - 1 - u
            flipped = points.clone()
            flipped[..., 0] = torch.where(
                points[..., 5] > 0, image.shape[-1] - 1 - points[..., 0], points[..., 0]
            )
        mirrored_sparse = None if sparse is None else sparse.flip(-1)
        mirrored_prior = None if prior is None else prior.flip(-1)
        mirrored = run(image.flip(-1), mirrored_sparse, flipped, mirrored_prior).flip(-1)
        # The mean of the two; where one is 0 (no prediction: model=radarnet's association
        # stage), the other alone. Other networks never predict 0.
        both = (depth > 0) & (mirrored > 0)
        depth = torch.where(both, (depth + mirrored) / 2, depth + mirrored)
    if pad_h or pad_w:
        # Back to the padded input's frame (the output may be at a lower resolution), then cut.
        depth = resize_depth(depth, (height + pad_h, width + pad_w), upsample)[..., :height, :width]
    return resize_depth(depth, size or (height, width), upsample)
