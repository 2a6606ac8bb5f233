"""Batch-level training augmentation (Kornia), run on the device after transfer.

The default is the paper's (Siddiqui et al., Sec. 4.1: horizontal flip, brightness and contrast
jitter). A model's recipe may bring its authors' own (:class:`~fusion_depth.models.Recipe`'s
``augment``, and a dataset's recipe ``conf/experiment/<dataset>_<model>.yaml``):

- RadarNet (Singh et al. 2023; ``nesl/radar-camera-fusion-depth``, ``src/fusionnet_transforms.py``
  and ``bash/train_fusionnet_nuscenes.sh``): brightness, contrast and saturation in [0.8, 1.2],
  each on its own with probability 0.5 and in that order (``color_each``), a flip with
  probability 0.5, and random 448×448 crops (``crop``, in the dataset's recipe);
- Sparse-to-Dense (Ma & Karaman 2018; ``fangchangma/sparse-to-dense.pytorch``,
  ``dataloaders/kitti_dataloader.py``): a rotation in ±5°, a zoom ``s`` in [1, 1.5] with depth
  divided by ``s`` (``scale``), nearest-neighbour resampling of image and depth, a crop centred on
  a fixed point, a flip, and ColorJitter 0.4/0.4/0.4 (factors in [0.6, 1.4], random order).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import kornia.augmentation as K
import torch
import torch.nn.functional as F
from torch import nn

from fusion_depth.data.radar_points import DEPTH, VALID, U, V
from fusion_depth.errors import ArgumentError
from fusion_depth.utils.schema import (
    BOOLEAN,
    NON_NEGATIVE,
    PROBABILITY,
    Rule,
    Schema,
    is_int,
    is_number,
    one_of,
)

# Batch keys that hold metres, divided by the zoom. The target is resampled nearest-neighbour (a
# mean of two depths across an edge is a depth that is nowhere), as Sparse-to-Dense resamples
# its; the sparse input's returns are moved, each to one pixel, so a zoom neither duplicates nor
# drops measurements (Sparse-to-Dense samples its input after the transform, at a fixed count).
_DEPTH_MAPS = ("sparse", "depth", "depth_measured")
# The training targets: moved and resampled alike (depth_measured: a filled target's measured
# pixels, which the outlier filter leaves as they are, as RadarNet's lidar map).
_TARGETS = ("depth", "depth_measured")


class TrainAugmentation(nn.Module):
    """A training batch's augmentation: geometry (crop, zoom, rotation), flip, colour.

    The geometry and the flip move image, sparse map, depth, a cached prior (``prior``) and
    radar points (``radar_points``) together; the colour jitter touches the image only. Kornia's
    ``ColorJitter`` uses the torchvision formulas (multiplicative brightness, contrast blended
    with the grey mean, saturation blended with grey), which the paper's and the peers' ranges
    refer to. With the defaults the batch keeps its size and only flip and colour apply, drawing
    the same random numbers as before the geometry existed.

    Args:
        flip_p: probability of a horizontal flip.
        color_p: probability of the colour jitter (``color_each``: of each of its operations).
        brightness: ``[low, high]`` brightness factors.
        contrast: ``[low, high]`` contrast factors.
        saturation: ``[low, high]`` saturation factors; None: saturation is not changed.
        color_each: brightness, contrast and saturation each drawn on its own with ``color_p``,
            in that order (RadarNet); false: one jitter, its operations in random order.
        crop: ``[height, width]`` in pixels of the served frame, multiples of 32; None: the
            whole frame.
        crop_center: ``[row, column]`` of the crop's centre in the frame (pixel centres at
            integers), about which zoom and rotation turn; the frame reads as empty outside.
            None: a random position with the crop inside the frame (whole pixels, so a crop
            alone resamples nothing), placed by ``crop_placement``.
        crop_placement: how a random crop is placed: ``uniform`` (every offset alike) or
            ``radarnet`` (its ``random_crop`` with ``horizontal vertical``: the column offset
            uniform in ``[0, W - w)``; the row offset uniform in ``[0, H - h)`` with
            probability 0.3, else ``(H - h) // 2``).
        scale: ``[low, high]`` zoom factors ``s`` (≥ 1 magnifies); depth and sparse depth are
            divided by ``s``, as an object ``s`` times nearer looks ``s`` times larger. None: no
            zoom.
        rotation: the largest rotation in degrees (uniform in ±``rotation``); 0: none.
        resample: how the image is resampled under zoom or rotation, ``bilinear`` or ``nearest``
            (Sparse-to-Dense's; depth maps are always nearest).
        outlier_filter: ``[kernel, threshold]``: the target's pixels more than ``threshold``
            metres deeper than the nearest in their ``kernel``×``kernel`` neighbourhood are
            dropped after the geometry (:func:`remove_outliers`; RadarNet's ``[7, 1.5]``); None:
            none.

    Shape:
        - batch["image"]: (B, 3, H, W); "sparse", "depth": (B, 1, H, W) metres; "prior":
          (B, 1, H, W); "radar_points": (B, P, K). Out: the same with ``H, W`` = ``crop``;
          a radar point moved outside the crop becomes a zero row (``valid`` 0).

    Raises:
        ArgumentError: an ``outlier_filter`` it cannot apply (a kernel that is not an odd
            integer ≥ 1, a threshold that is not finite metres > 0); in :meth:`forward`, a
            ``crop`` larger than the batch's frames.
    """

    def __init__(
        self,
        flip_p: float = 0.5,
        color_p: float = 0.5,
        brightness: Sequence[float] = (0.75, 1.25),
        contrast: Sequence[float] = (0.9, 1.1),
        saturation: Sequence[float] | None = None,
        color_each: bool = False,
        crop: Sequence[int] | None = None,
        crop_center: Sequence[float] | None = None,
        crop_placement: str = "uniform",
        scale: Sequence[float] | None = None,
        rotation: float = 0.0,
        resample: str = "bilinear",
        outlier_filter: Sequence[float] | None = None,
    ) -> None:
        super().__init__()
        self.flip = K.RandomHorizontalFlip(p=flip_p)
        factors = {"brightness": brightness, "contrast": contrast}
        if saturation is not None:
            factors["saturation"] = saturation
        if color_each:  # RadarNet: each operation on its own draw, in this order
            self.color = nn.Sequential(
                *(K.ColorJitter(**{name: tuple(f)}, p=color_p) for name, f in factors.items())
            )
        else:
            self.color = K.ColorJitter(**{k: tuple(f) for k, f in factors.items()}, p=color_p)
        self.crop = tuple(crop) if crop is not None else None
        self.crop_center = tuple(crop_center) if crop_center is not None else None
        self.crop_placement = crop_placement
        self.scale = tuple(scale) if scale is not None else None
        self.rotation = float(rotation)
        self.resample = resample
        if outlier_filter is not None:
            given = list(outlier_filter) if isinstance(outlier_filter, Sequence) else outlier_filter
            if not ARGUMENT_RULES["outlier_filter"].ok(given):
                raise ArgumentError(
                    f"{{outlier_filter}}={given!r}: expected "
                    f"{ARGUMENT_RULES['outlier_filter'].expected}",
                    "outlier_filter",
                    owner=TrainAugmentation,
                )
        self.outlier_filter = tuple(outlier_filter) if outlier_filter is not None else None

    @torch.no_grad()
    def forward(self, batch: dict) -> dict:
        out = self._geometry(dict(batch))
        if self.outlier_filter is not None:
            kernel, threshold = self.outlier_filter
            out["depth"] = remove_outliers(out["depth"], int(kernel), float(threshold))
        image = out["image"]
        keys = ["image", "sparse", "depth", *(k for k in ("prior", "depth_measured") if k in out)]
        keys = [k for k in keys if out.get(k) is not None]
        maps = [out[k].to(image.dtype) for k in keys]
        stacked = self.flip(torch.cat(maps, dim=1))
        moved = dict(zip(keys, stacked.split([m.shape[1] for m in maps], dim=1), strict=True))
        for key in keys[3:]:
            out[key] = moved[key].contiguous()
        image, sparse, depth = moved["image"], moved["sparse"], moved["depth"]
        points = out.get("radar_points")
        if points is not None:  # the flipped images' returns mirror too: u → W - 1 - u
            flipped = self.flip._params["batch_prob"].to(points.device) > 0.5
            mirror = flipped[:, None] & (points[..., VALID] > 0)
            points = points.clone()
            points[..., U] = torch.where(
                mirror, image.shape[-1] - 1 - points[..., U], points[..., U]
            )
            out["radar_points"] = points
        return {
            **out,
            "image": self.color(image.contiguous()),
            "sparse": sparse.contiguous(),
            "depth": depth.contiguous(),
        }

    def _geometry(self, batch: dict) -> dict:
        """Crop, zoom and rotation (none drawn when none is asked for)."""
        if self.crop is None and self.scale is None and self.rotation == 0:
            return batch
        image = batch["image"]
        n, _, height, width = image.shape
        out_h, out_w = self.crop or (height, width)
        if out_h > height or out_w > width:
            raise ArgumentError(
                f"{{crop}}={[out_h, out_w]}: larger than the frames ({height}×{width})",
                "crop",
                owner=TrainAugmentation,
            )
        if self.crop_center is not None:
            centre = torch.tensor(self.crop_center, dtype=torch.float64).expand(n, 2)
        else:  # whole-pixel offsets: a crop alone moves pixels, it does not resample them
            top, left = _crop_offsets(n, height - out_h, width - out_w, self.crop_placement)
            centre = torch.stack([top + (out_h - 1) / 2, left + (out_w - 1) / 2], 1).double()
        zoom = torch.ones(n, dtype=torch.float64)
        if self.scale is not None:
            low, high = self.scale
            zoom = low + (high - low) * torch.rand(n, dtype=torch.float64)
        angle = torch.zeros(n, dtype=torch.float64)
        if self.rotation:
            angle = (2 * torch.rand(n, dtype=torch.float64) - 1) * math.radians(self.rotation)
        # output pixel p (row, col) reads input c + R(angle) (p - c_out) / zoom
        cos, sin = torch.cos(angle) / zoom, torch.sin(angle) / zoom
        to_input = torch.stack([torch.stack([cos, -sin], 1), torch.stack([sin, cos], 1)], 1)
        out_centre = torch.tensor([(out_h - 1) / 2, (out_w - 1) / 2], dtype=torch.float64)
        if self.scale is None and self.rotation == 0 and self.crop_center is None:
            batch = self._slice(batch, centre - out_centre, out_h, out_w)
        else:
            batch = self._warp(batch, to_input, centre, out_centre, out_h, out_w, zoom)
        points = batch.get("radar_points")
        if points is not None:
            batch["radar_points"] = _move_points(
                points, to_input, centre, out_centre, zoom, out_h, out_w
            )
        return batch

    @staticmethod
    def _slice(batch: dict, corner: torch.Tensor, out_h: int, out_w: int) -> dict:
        corner = corner.round().long().tolist()
        for key in ("image", *_DEPTH_MAPS, "prior"):
            if batch.get(key) is not None:
                maps = batch[key]
                batch[key] = torch.stack(
                    [
                        m[:, t : t + out_h, c : c + out_w]
                        for m, (t, c) in zip(maps, corner, strict=True)
                    ]
                )
        return batch

    def _warp(
        self,
        batch: dict,
        to_input: torch.Tensor,
        centre: torch.Tensor,
        out_centre: torch.Tensor,
        out_h: int,
        out_w: int,
        zoom: torch.Tensor,
    ) -> dict:
        image = batch["image"]
        height, width = image.shape[-2:]
        rows, cols = torch.meshgrid(
            torch.arange(out_h, dtype=torch.float64),
            torch.arange(out_w, dtype=torch.float64),
            indexing="ij",
        )
        offset = torch.stack([rows, cols], -1).reshape(-1, 2) - out_centre  # (HW, 2)
        source = centre[:, None, :] + torch.einsum("nij,pj->npi", to_input, offset)
        # grid_sample's (x, y) in [-1, 1] with corner pixels' centres at ±1 (align_corners)
        grid = torch.stack(
            [2 * source[..., 1] / (width - 1) - 1, 2 * source[..., 0] / (height - 1) - 1], -1
        )
        grid = grid.reshape(len(image), out_h, out_w, 2).to(image.device, torch.float32)
        modes = {"image": self.resample, "prior": "bilinear", **dict.fromkeys(_TARGETS, "nearest")}
        divide = zoom.to(image.device, torch.float32)[:, None, None, None]
        for key, mode in modes.items():
            maps = batch.get(key)
            if maps is None:
                continue
            warped = F.grid_sample(
                maps.float(), grid, mode=mode, padding_mode="zeros", align_corners=True
            ).to(maps.dtype)
            batch[key] = warped / divide if key in _DEPTH_MAPS else warped
        if batch.get("sparse") is not None:
            batch["sparse"] = _move_sparse(
                batch["sparse"], to_input, centre, out_centre, zoom, out_h, out_w
            )
        return batch


def _crop_offsets(n: int, rows: int, cols: int, placement: str) -> tuple[torch.Tensor, ...]:
    """``n`` random (top, left) offsets of a crop ``rows`` and ``cols`` pixels smaller than the
    frame (:class:`TrainAugmentation`'s ``crop_placement``)."""
    if placement == "uniform":
        return torch.randint(0, rows + 1, (n,)), torch.randint(0, cols + 1, (n,))
    # RadarNet's random_crop: np.random.randint(0, d) excludes d itself (0 when d is 0)
    left = torch.randint(0, max(cols, 1), (n,))
    random_row = torch.rand(n) <= 0.30
    top = torch.where(random_row, torch.randint(0, max(rows, 1), (n,)), rows // 2)
    return top, left


def remove_outliers(depth: torch.Tensor, kernel: int, threshold: float) -> torch.Tensor:
    """``depth`` with each valid pixel set to 0 (invalid) where the nearest valid depth in its
    ``kernel``×``kernel`` neighbourhood is more than ``threshold`` metres nearer: a background
    point seen through a foreground object (RadarNet's ``OutlierRemoval.remove_outliers``,
    ``src/net_utils.py``, which its fusion network applies to its target at each step).

    Args:
        depth: (B, 1, H, W) metres, 0 = invalid.
        kernel: the neighbourhood's side, odd.
        threshold: metres.

    Returns:
        (B, 1, H, W) the same depths, the outliers 0.
    """
    far = 10 * depth.max()  # invalid pixels and the border never count as nearer
    filled = torch.where(depth > 0, depth, far)
    pad = kernel // 2
    nearest = -F.max_pool2d(-F.pad(filled, (pad, pad, pad, pad), value=float(far)), kernel, 1)
    return torch.where(nearest < depth - threshold, torch.zeros_like(depth), depth)


def _output_place(
    rows_cols: torch.Tensor, to_input: torch.Tensor, centre: torch.Tensor, out_centre: torch.Tensor
) -> torch.Tensor:
    """Where input positions (row, column) land in the output: the inverse of ``to_input``
    about ``centre``, in float64 on the CPU (a GPU may have no float64).

    Shape:
        - rows_cols: (B, M, 2); to_input: (B, 2, 2); centre: (B, 2). Out: (B, M, 2) float64.
    """
    place = rows_cols.cpu().double() - centre[:, None, :]
    return out_centre + torch.einsum("nij,npj->npi", torch.linalg.inv(to_input), place)


def _move_sparse(
    sparse: torch.Tensor,
    to_input: torch.Tensor,
    centre: torch.Tensor,
    out_centre: torch.Tensor,
    zoom: torch.Tensor,
    out_h: int,
    out_w: int,
) -> torch.Tensor:
    """Each return of a sparse map moved to the output pixel its centre maps to (the inverse of
    ``to_input``), depth ÷ zoom; the nearest wins a shared pixel, one that leaves is dropped."""
    out = torch.zeros(*sparse.shape[:2], out_h, out_w, dtype=sparse.dtype, device=sparse.device)
    for i in range(len(sparse)):
        rows, cols = torch.nonzero(sparse[i, 0] > 0, as_tuple=True)
        if not len(rows):
            continue
        where = torch.stack([rows, cols], 1)[None]
        moved = _output_place(where, to_input[i : i + 1], centre[i : i + 1], out_centre)[0]
        moved = moved.round().long().to(sparse.device)
        depth = sparse[i, 0, rows, cols] / float(zoom[i])
        inside = (moved[:, 0] >= 0) & (moved[:, 0] < out_h) & (moved[:, 1] >= 0)
        inside &= moved[:, 1] < out_w
        index = moved[inside, 0] * out_w + moved[inside, 1]
        nearest = torch.full((out_h * out_w,), math.inf, dtype=depth.dtype, device=depth.device)
        nearest = nearest.scatter_reduce(0, index, depth[inside], reduce="amin")
        out[i, 0] = torch.where(nearest.isinf(), 0.0, nearest).view(out_h, out_w)
    return out


def _move_points(
    points: torch.Tensor,
    to_input: torch.Tensor,
    centre: torch.Tensor,
    out_centre: torch.Tensor,
    zoom: torch.Tensor,
    out_h: int,
    out_w: int,
) -> torch.Tensor:
    """Radar rows at their place in the output (the inverse of ``to_input``), depth ÷ zoom; a
    row whose point leaves the output's pixels becomes a zero row."""
    moved = _output_place(points[..., [V, U]], to_input, centre, out_centre)
    moved = moved.to(points.device, torch.float32)
    inside = (
        (moved[..., 0] >= -0.5)
        & (moved[..., 0] < out_h - 0.5)
        & (moved[..., 1] >= -0.5)
        & (moved[..., 1] < out_w - 0.5)
    )
    out = points.clone()
    out[..., V], out[..., U] = moved[..., 0].to(points.dtype), moved[..., 1].to(points.dtype)
    out[..., DEPTH] = points[..., DEPTH] / zoom.to(points.device, points.dtype)[:, None]
    keep = inside & (points[..., VALID] > 0)
    return out * keep[..., None].to(points.dtype)


_FACTOR_RANGE = Rule(
    lambda v: (
        isinstance(v, list) and len(v) == 2 and all(is_number(x) for x in v) and 0 < v[0] <= v[1]
    ),
    "[low, high] factors with 0 < low ≤ high",
)
_CROP = Rule(
    lambda v: (
        isinstance(v, list)
        and len(v) == 2
        and all(is_int(x) and x % 32 == 0 for x in v)
        and min(v) > 0
    ),
    "[height, width], positive multiples of 32",
)
_POINT = Rule(
    lambda v: isinstance(v, list) and len(v) == 2 and all(is_number(x) for x in v),
    "[row, column] in pixels",
)
# What :class:`TrainAugmentation`'s arguments accept (fusion_depth.utils.schema).
ARGUMENT_RULES: Schema = {
    "flip_p": PROBABILITY,
    "color_p": PROBABILITY,
    "brightness": _FACTOR_RANGE,
    "contrast": _FACTOR_RANGE,
    "saturation": _FACTOR_RANGE.or_null("saturation unchanged"),
    "color_each": BOOLEAN,
    "crop": _CROP.or_null("the whole frame"),
    "crop_center": _POINT.or_null("a random position"),
    "scale": _FACTOR_RANGE.or_null("no zoom"),
    "rotation": NON_NEGATIVE,
    "resample": one_of("bilinear", "nearest"),
    "crop_placement": one_of("uniform", "radarnet"),
    "outlier_filter": Rule(
        lambda v: (
            isinstance(v, list)
            and len(v) == 2
            and is_int(v[0])
            and v[0] >= 1  # -1 % 2 is 1 too
            and v[0] % 2 == 1
            and is_number(v[1])
            and math.isfinite(v[1])
            and v[1] > 0
        ),
        "[kernel, threshold]: an odd side ≥ 1 in pixels and finite metres > 0",
    ).or_null("no filter"),
}
