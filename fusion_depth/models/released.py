"""Published methods' released checkpoints, run as the platform's networks, so that
``python -m fusion_depth.evaluate released=<name>`` scores them with the platform's readers and
protocols and ``report --published`` puts the scores beside the papers' (``conf/released/``).

A released model is built from its authors' files as a user downloads them, loaded with weights
only and strictly (:func:`~fusion_depth.models.radarnet_released.load_released`). It is scored,
never trained: it is not in the table of models (:data:`~fusion_depth.models.MODELS`) and has no
recipe. :data:`RELEASED` is the table of them, by the name ``released=`` takes.

What the authors' pipeline takes and this one is given differ in one place, the radar points:
:func:`radarnet_frame_points` says how they are made from the platform's ``radar_points`` and
what is not the same.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from fusion_depth.data import RADAR_POINT_FIELDS
from fusion_depth.errors import ArgumentError, check_choice
from fusion_depth.models.base import DepthModel
from fusion_depth.models.fusion import InputMode
from fusion_depth.models.radarnet_released import (
    THRESHOLD,
    FusionNet,
    RadarNetV1,
    ReleasedRadarNet,
    load_released,
)

_U, _V, _DEPTH, _VALID = (RADAR_POINT_FIELDS.index(k) for k in ("u", "v", "depth", "valid"))
# setup/setup_dataset_nuscenes_test.py keeps a projected point when 1 < x < W - 1 and
# 1 < y < H - 1 (its point_cloud_to_image, and the devkit's map_pointcloud_to_image with which
# it projects the keyframe's sweep): a margin of one pixel, "for aesthetic reasons".
RADARNET_MARGIN = 1.0
RADARNET_MIN_DEPTH = 1.0  # its min_distance_from_camera: depth > 1 m


def radarnet_frame_points(rows: Tensor, height: int, width: int) -> Tensor:
    """One frame's radar points as RadarNet's test setup stores them, from the platform's rows.

    ``setup/setup_dataset_nuscenes_test.py`` (nesl/radar-camera-fusion-depth at c95c67d,
    ``merge_radar_point_clouds`` with no sweeps before or after) writes each return's depth into
    a 900×1600 map at ``np.round`` of its projection, keeping returns with ``1 < x < W - 1`` and
    ``1 < y < H - 1`` and depth above 1 m, and stores ``np.nonzero`` of that map as ``(x, y,
    z)``: one point per pixel, whole-pixel coordinates, in row-major order (by row, then
    column). That order is the order stage 1 numbers the points in, which decides ties and the
    whole-metre rewrite chain of its quasi-dense map
    (:func:`~fusion_depth.models.radarnet_released.quasi_dense_depth`), so it is kept here.

    What differs: where two returns of the sweep land on one pixel, their map keeps the one its
    loop wrote last (the devkit's file order), this keeps the nearer (the platform's rows are
    sorted nearest first, and the file order is not kept); and the depth is the float32 the
    platform stores, theirs float64.

    Args:
        rows: (P, 6) the frame's ``radar_points`` (columns
            :data:`~fusion_depth.data.RADAR_POINT_FIELDS`; rows with ``valid`` 0 are padding),
            ``u, v`` in pixels of an image of ``height × width``.
        height: the image's rows.
        width: the image's columns.

    Returns:
        (K, 3) float32: x (column) and y (row) as whole pixels, depth in metres.
    """
    rows = rows[rows[:, _VALID] > 0]
    u, v, depth = rows[:, _U], rows[:, _V], rows[:, _DEPTH]
    kept = (
        (u > RADARNET_MARGIN)
        & (u < width - RADARNET_MARGIN)
        & (v > RADARNET_MARGIN)
        & (v < height - RADARNET_MARGIN)
        & (depth > RADARNET_MIN_DEPTH)
    )
    u, v, depth = u[kept], v[kept], depth[kept]
    col, row = torch.round(u).long(), torch.round(v).long()
    pixel = row * width + col
    # One point per pixel, the nearest (rows come nearest first: the first of each pixel).
    order = torch.argsort(pixel, stable=True)
    pixel, depth = pixel[order], depth[order]
    first = torch.ones_like(pixel, dtype=torch.bool)
    first[1:] = pixel[1:] != pixel[:-1]
    pixel, depth = pixel[first], depth[first]
    return torch.stack(
        [(pixel % width).float(), torch.div(pixel, width, rounding_mode="floor").float(), depth],
        dim=1,
    )


class ReleasedRadarNetDepth(DepthModel):
    """RadarNet's two released stages end to end (:class:`~fusion_depth.models.
    radarnet_released.ReleasedRadarNet`), as a platform network: depth in metres from the image
    and the batch's ``radar_points``.

    Args:
        association_weights: the released association network, ``model-195000.pth`` as
            downloaded (the authors' ``radarnetv1`` in its shipped configuration).
        fusion_weights: the released FusionNet, ``model-815000.pth`` as downloaded.
        threshold: the confidence a point's pixel needs (0.5 as shipped).

    Shape:
        - image: (B, 3, H, W) RGB in [0, 1], at the camera's full resolution (nuScenes:
          900×1600; any size at least 900 rows); not padded (:attr:`input_multiple` is 1).
        - points: (B, P, 6), the batch's ``radar_points`` at that resolution.
        - output: (B, 1, H, W) depth in metres, in [1, 100] (FusionNet's range).

    Raises:
        ArgumentFileError: a weights file does not exist (naming the key).
        ReleasedWeightsError: a file that is not that network as released (one line naming the
            key, the file and the first wrong key in it).
    """

    output_space = "depth"
    takes_points = True
    input_multiple: ClassVar[int] = 1
    MIN_DEPTH, MAX_DEPTH = 1.0, 100.0  # run_fusionnet_nuscenes_test.sh: --min/max_predict_depth

    def __init__(
        self,
        association_weights: str | os.PathLike,
        fusion_weights: str | os.PathLike,
        threshold: float = THRESHOLD,
    ) -> None:
        super().__init__(self.MIN_DEPTH, self.MAX_DEPTH, depth_scale=1.0)
        if not isinstance(threshold, (int, float)) or not 0.0 <= threshold <= 1.0:
            raise ArgumentError(
                f"{{threshold}}={threshold!r}: expected a confidence in [0, 1]",
                "threshold",
                owner=ReleasedRadarNetDepth,
            )
        association, fusion = RadarNetV1(), FusionNet()
        load_released(association, association_weights, argument="association_weights")
        load_released(fusion, fusion_weights, argument="fusion_weights")
        self.pipeline = ReleasedRadarNet(association, fusion, threshold=float(threshold))
        self.fusion = InputMode("concat", uses_sparse=True)  # image and radar in

    def forward(self, image: Tensor, sparse: Tensor | None, points: Tensor | None) -> Tensor:
        if points is None:
            raise ValueError(
                "the released RadarNet needs the radar returns as points (radar_points): a "
                "radar dataset's frames (dataset=nuscenes or dataset=radarnet_layout) have them"
            )
        height, width = image.shape[-2:]
        frames = [radarnet_frame_points(rows, height, width) for rows in points]
        return self.pipeline(image, frames)


@dataclass(frozen=True)
class ReleasedEntry:
    """One released model of :data:`RELEASED`: how it is built and how tables name it."""

    build: Callable[..., DepthModel]
    label: str  # how tables name it
    paper: str  # the publication whose numbers ``report --published`` gives beside it
    arguments: tuple[str, ...]  # the ``released.<key>`` settings besides ``name``; the first
    # names the file a record says it scored


RELEASED: dict[str, ReleasedEntry] = {
    "radarnet": ReleasedEntry(
        build=ReleasedRadarNetDepth,
        label="RadarNet (released)",
        paper="Singh et al., Depth Estimation from Camera Image and mmWave Radar Point Cloud, "
        "CVPR 2023",
        arguments=("association_weights", "fusion_weights", "threshold"),
    ),
}


def build_released(settings: Mapping[str, Any]) -> DepthModel:
    """The released model ``settings["name"]`` (a key of :data:`RELEASED`) built from its other
    settings (the ``released`` config node), in eval mode.

    Raises:
        ArgumentError: an unknown name or setting, or what the model's constructor raises
            (naming the setting).
    """
    name = settings.get("name")
    check_choice(name, list(RELEASED), "name", owner=build_released)
    entry = RELEASED[name]
    given = {k: v for k, v in settings.items() if k != "name"}
    unknown = sorted(set(given) - set(entry.arguments))
    if unknown:
        raise ArgumentError(
            f"{{{unknown[0]}}}: not a setting of the released {name}; it takes "
            f"{', '.join(entry.arguments)}",
            unknown[0],
            owner=build_released,
        )
    return entry.build(**given).eval()


RECORD_SUFFIX = "_released"  # a record's model name: radarnet_released (model=radarnet trains)


def record_model_name(name: str) -> str:
    """The ``model`` a record of the released ``name`` carries (``radarnet_released``), apart
    from the platform's own model of the method (``radarnet``)."""
    return f"{name}{RECORD_SUFFIX}"


def released_entry(model: object) -> ReleasedEntry | None:
    """The entry of :data:`RELEASED` a record's ``model`` names (:func:`record_model_name`), or
    None for any other model."""
    if not isinstance(model, str) or not model.endswith(RECORD_SUFFIX):
        return None
    return RELEASED.get(model.removesuffix(RECORD_SUFFIX))
