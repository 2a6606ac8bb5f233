"""Datasets: one module per dataset, plus the shared datamodule and transforms."""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, NotRequired, TypedDict

if TYPE_CHECKING:
    from torch import Tensor

SPLITS: tuple[str, ...] = ("train", "val", "test")
"""The split names every dataset reader accepts (their order also keys the procedural seed
streams)."""

CONDITIONS: tuple[str, ...] = ("day", "night", "fog", "rain", "cloudy")
"""The capture conditions a frame can have; metrics are broken down by them (the paper, Sec. 4:
day, night, rain on nuScenes; the synthetic sets add fog and cloud). A dataset may use a
subset."""

RADAR_POINT_FIELDS: tuple[str, ...] = ("u", "v", "depth", "rcs", "velocity", "valid")
"""The columns of a sample's ``radar_points`` (see :class:`Sample`), in order:

- u, v: the return's continuous pixel position in the sample's image (column, row), pixel
  centres at integers (pixel i spans [i - 0.5, i + 0.5], the OpenCV and nuScenes devkit
  convention), so it lies in pixel (round(v), round(u)) of ``image`` and ``sparse``, as
  RadarNet places its points (radar_points.pixel_index);
- depth: metres, camera-frame z (the forward distance), the quantity ``sparse`` holds;
- rcs: radar cross-section in dBsm, where the dataset records it (nuScenes), else 0;
- velocity: radial velocity in m/s, as the dataset's radar reports it (nuScenes: ego-motion
  compensated, positive moving away; CARLA: RadarDetection.velocity), else 0;
- valid: 1 for a return, 0 for a padding row (all of whose columns are 0).
"""


class _SampleKeys(TypedDict):
    """The keys of :class:`Sample` and :class:`EncodedSample` (see those for the dtypes)."""

    image: Tensor
    sparse: Tensor
    depth: Tensor
    condition: str
    frame_box: NotRequired[Tensor]
    radar_points: NotRequired[Tensor]
    depth_points: NotRequired[Tensor]


class Sample(_SampleKeys):
    """One frame as every dataset serves it (``dataset[i]``), and as models, losses and metrics
    see a batch (a batch adds a leading batch dimension ``B`` to each tensor and makes
    ``condition`` a list). The datamodule's loaders carry the same keys in the
    :class:`EncodedSample` form, which :func:`fusion_depth.data.encoding.decode_sample` turns
    into this one on the device.

    Shape:
        - image: (3, H, W) float32 RGB in [0, 1].
        - sparse: (1, H, W) float32 metres from the sparse sensor (radar or lidar), 0 = no
          return; all zeros for a camera-only dataset.
        - depth: (1, H, W) float32 ground-truth metres, 0 = invalid (not scored).
        - condition: one of :data:`CONDITIONS`.
        - frame_box: optional (4,) int64 ``(top, left, height, width)`` of the original frame in
          the arrays, when the reader cropped or padded it (evaluation crops are fractions of the
          original frame).
        - radar_points: (P, K) float32, only from a dataset whose sparse sensor is a radar
          (procedural with ``sparse=radar``, CARLA, nuScenes): the returns that ``sparse`` was
          projected from, one row per return with the columns :data:`RADAR_POINT_FIELDS`
          (``K = len(RADAR_POINT_FIELDS)``), nearest first. ``P`` is fixed per dataset config
          (``dataset.max_radar_points``): a frame with more returns keeps the nearest ``P``
          (the others stay in ``sparse``), one with fewer is padded with rows of zeros
          (``valid`` = 0). Every valid row's return is drawn in ``sparse`` at pixel
          ``(round(v), round(u))`` (with its depth unless a nearer return shares the pixel);
          the procedural radar's ``radar_height_extension`` draws it as a vertical line through
          that pixel.
        - depth_points: optional (Q, 3) float32, only from a reader that resamples its frames
          and keeps ground truth at the dataset's full resolution (nuScenes' val and test:
          RadarNet's): rows ``y, x, depth``, each full-resolution pixel's centre in the
          sample's coordinates (pixel centres at integers) and its depth in metres, padded with
          rows of zeros (depth 0: not scored) to the split's largest count. ``eval.resolution=
          full`` scores the prediction read at these points.
    """


class EncodedSample(_SampleKeys):
    """A :class:`Sample` as it crosses the DataLoader's process boundary: the stored integers,
    converted to the float form only on the device
    (:mod:`fusion_depth.data.encoding`). A reader that stores frames this way (the prepared
    caches, the built-in dataset) serves it from ``encoded_sample(index)``, and the datamodule's
    loaders use that method where a reader has it.

    Shape:
        - image: (3, H, W) uint8 RGB (the float form is ``image / 255``).
        - sparse, depth: (1, H, W) uint16, metres × 256 (KITTI's convention,
          :data:`fusion_depth.data.depth_io.DEPTH_PNG_SCALE`: 3.9 mm steps, at most 255.996 m),
          0 = no value (the float form is ``value / 256``, exactly).
        - condition, frame_box, radar_points: as in :class:`Sample`.
    """


READERS: dict[str, tuple[str, str]] = {
    "procedural": ("fusion_depth.data.procedural", "ProceduralDepth"),
    "kitti": ("fusion_depth.data.kitti", "KittiDepth"),
    "carla": ("fusion_depth.data.carla", "CarlaDepth"),
    "topview": ("fusion_depth.data.topview", "TopViewDepth"),
    "nuscenes": ("fusion_depth.data.nuscenes", "NuScenesDepth"),
    "radarnet_layout": ("fusion_depth.data.radarnet_layout", "RadarNetLayout"),
}
"""The package's own table of dataset readers, by the name a dataset config and a checkpoint
record (``dataset.name``): module and class. A checkpoint names its dataset; its reader is looked
up here, never imported from a path stored in the file. Modules are imported on first use, since
some need optional packages (nuScenes: the devkit)."""


def cache_dir() -> str:
    """Where generated/prepared datasets live: $FUSION_DEPTH_CACHE or ~/.cache/fusion_depth."""
    return str(Path(os.environ.get("FUSION_DEPTH_CACHE", "~/.cache/fusion_depth")).expanduser())


def reader_class(name: str) -> Any:
    """The reader class of dataset ``name`` (a key of :data:`READERS`).

    Raises:
        KeyError: ``name`` is not a dataset of this package.
    """
    if name not in READERS:
        raise KeyError(f"dataset {name!r} is not one of {sorted(READERS)}")
    module, cls = READERS[name]
    return getattr(importlib.import_module(module), cls)
