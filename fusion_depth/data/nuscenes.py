"""``dataset=nuscenes``: the paper's real camera + radar set, read with the official devkit.

Needs the optional extra ``pip install -e ".[nuscenes]"`` (the ``nuscenes-devkit`` package; it pins
numpy < 2, so it is not a core dependency). Without it, choosing this dataset fails at once with
that command.

Layout
------
The folder as nuScenes publishes it (https://www.nuscenes.org/nuscenes#download: the metadata
archive plus the sensor blobs, unpacked into one folder)::

    <root>/
      maps/*.png                  map masks (the devkit checks they exist)
      samples/CAM_FRONT/*.jpg     keyframe images, 1600x900
      samples/RADAR_FRONT/*.pcd   keyframe radar returns (also RADAR_FRONT_LEFT, ...)
      samples/LIDAR_TOP/*.pcd.bin keyframe lidar sweeps
      sweeps/<CHANNEL>/...        the non-keyframe sweeps (needed when accumulating sweeps)
      v1.0-trainval/*.json        the 13 tables (or v1.0-mini/, v1.0-test/)

Frames
------
One frame per keyframe ``sample`` of the chosen scenes (in scene-name order, then time order):

* **image**: ``CAM_FRONT``.
* **sparse**: the radar returns of ``radar_channels`` (default ``RADAR_FRONT``; ``RADAR_FRONT_LEFT``
  and ``RADAR_FRONT_RIGHT`` can be added), each accumulated over ``radar_nsweeps`` sweeps (the
  keyframe's and the ones before it) and filtered by the devkit's ``RadarPointCloud`` states:
  ``radar_filters=default`` (``RadarPointCloud.default_filters()``: valid clusters, unambiguous
  Doppler, not ``stopped``), ``off`` (``disable_filters()``: every return), or ``custom`` with the
  three lists ``radar_invalid_states``, ``radar_dynprop_states``, ``radar_ambig_states``.
* **depth** (ground truth): ``LIDAR_TOP``, accumulated over ``lidar_nsweeps`` sweeps (default 1:
  accumulating smears moving objects).
* **filled** (training ground truth, ``fill=colorization|linear|none``): the lidar map densified by
  :func:`fusion_depth.data.filling.fill_depth`, as the paper does with Levin et al.'s colorization.
  Only the train split has it; validation and test always score the measured lidar points.

Geometry
--------
The devkit does it: ``from_file_multisweep(nusc, sample, channel, "CAM_FRONT", nsweeps,
min_distance)`` takes every sweep from its sensor through the ego pose at the sweep's timestamp
into the global frame and back through the ego pose at the camera's timestamp into the camera
(the chain of ``NuScenesExplorer.map_pointcloud_to_image``), and ``view_points`` projects with the
intrinsics. ``u, v`` put pixel centres at integers (the devkit's and OpenCV's convention), and a
point lands in pixel ``(round(v), round(u))`` with its camera-frame ``z`` as depth, as RadarNet's
setup places it (:func:`~fusion_depth.data.radar_points.pixel_index`).
Points with ``z < min_distance`` (default 1 m; the devkit also drops points within that distance
of their own sensor), outside the image, or beyond the cache's 255.99 m ceiling are dropped; where
two points land on one pixel the nearer wins.

Radar points. The radar returns that land in the image are also served as ``radar_points``
(:data:`~fusion_depth.data.RADAR_POINT_FIELDS`, the nearest ``max_radar_points``): ``u, v`` the
projected position in the output image, ``depth`` the camera-frame ``z`` (both as ``sparse``),
``rcs`` the devkit's ``rcs`` field (dBsm), and ``velocity`` the radial velocity, the
ego-motion-compensated ``vx_comp, vy_comp`` projected on the line of sight from the radar in the
frame of the sweep that measured it, positive moving away (m/s).

Resolution: the image is scaled uniformly (bilinear; area-averaging when shrinking) until it covers
``height x width``, then cropped: centred horizontally, from the top vertically (sky, where lidar
never returns). The default 448x800 is 1600x900 halved with 2 rows cut from the top. Sparse maps
are never resampled: points are projected with the intrinsics scaled and shifted the same way,
centre-aware (``u' = s (u + 0.5) - 0.5 - left``: ``f_x`` times ``s``, ``c_x`` to
``s (c_x + 0.5) - 0.5 - left``), so every depth stays a measured one and a point lands where the
resized image shows it.

Splits and conditions
---------------------
``train``/``val`` are the devkit's official scene splits (``create_splits_scenes()``:
``train``/``val`` for v1.0-trainval, ``mini_train``/``mini_val`` for v1.0-mini). nuScenes' test
scenes have no public annotations, but their lidar is public, so depth ground truth exists:
``test_split=val`` (default) tests on the val scenes, as nuScenes depth papers do (the val
frames are prepared once and shared); ``test_split=test`` tests on the official test scenes read
from ``<root>/v1.0-test``, so model selection and testing use disjoint scenes. ``stride=n`` keeps
every n-th keyframe of each scene (e.g. 8 gives about 3.5k train frames of v1.0-trainval, the
size of the paper's set). A frame's ``condition`` comes from its scene description: ``night``
if it mentions night (night wins over rain), else ``rain`` if it mentions rain, else ``day``;
``conditions`` keeps only frames of the listed ones.

Preparing
---------
The first split requested prepares all three into the shared cache
(:mod:`fusion_depth.data.cache`), each under ``<cache_root>/nuscenes/<hash>/`` (train's hash
also covers ``fill``, so val and test share another folder), so a bad file anywhere fails
before training. The hash covers every setting above plus the tables' names,
sizes and modification times; val/test do not depend on ``fill``, so changing it re-prepares
only the train split. Every file a frame needs is checked before the first frame is written;
the dataset folder is only ever read. Loading the v1.0-trainval tables takes the devkit about a
minute and a few GB of memory, once per prepare.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from PIL import Image

from fusion_depth.data import SPLITS
from fusion_depth.data.base import SIZE_MULTIPLE, PreparedDataset, check_conditions
from fusion_depth.data.cache import (
    OnError,
    PreparedFrame,
    SplitJob,
    cache_dir,
    is_prepared,
    prepare_splits,
)
from fusion_depth.data.depth_io import MAX_ENCODED_DEPTH, read_rgb
from fusion_depth.data.filling import FILL_METHODS, fill_depth
from fusion_depth.data.radar_points import (
    DEFAULT_MAX_RADAR_POINTS,
    in_image,
    pixel_index,
    point_rows,
)
from fusion_depth.errors import ArgumentError, check_choice
from fusion_depth.utils.schema import (
    NON_NEGATIVE_INT,
    POSITIVE_INT,
    Rule,
    Schema,
    is_number,
    one_of,
)

# Bump when projection or resizing changes, so old caches are not reused. 3: points placed at
# round() of centre-aware coordinates, as the devkit and RadarNet (1 put them half a pixel off),
# and val/test keep RadarNet's full-resolution ground truth as points (2 did not yet).
FORMAT_VERSION = 3
INSTALL = 'pip install -e ".[nuscenes]"'
CAMERA = "CAM_FRONT"
LIDAR = "LIDAR_TOP"
RADAR_CHANNELS = (
    "RADAR_FRONT",
    "RADAR_FRONT_LEFT",
    "RADAR_FRONT_RIGHT",
    "RADAR_BACK_LEFT",
    "RADAR_BACK_RIGHT",
)
# version -> the devkit's split names (create_splits_scenes) of its train and val scenes
VERSIONS = {"v1.0-trainval": ("train", "val"), "v1.0-mini": ("mini_train", "mini_val")}
TEST_VERSION = "v1.0-test"
TEST_SPLITS = ("val", "test")
TABLES = (
    "category",
    "attribute",
    "visibility",
    "instance",
    "sensor",
    "calibrated_sensor",
    "ego_pose",
    "log",
    "scene",
    "sample",
    "sample_data",
    "sample_annotation",
    "map",
)
NUSCENES_CONDITIONS = ("day", "night", "rain")  # of CONDITIONS: nuScenes' scene descriptions
RADAR_FILTERS = ("default", "off", "custom")
# The state values each RadarPointCloud filter can take (what disable_filters() allows).
RADAR_STATE_RANGES = {"invalid_states": 18, "dynprop_states": 8, "ambig_states": 5}
CACHE_MAX_DEPTH = MAX_ENCODED_DEPTH  # 255.99 m, the cache's ceiling
LIDAR_POINT_BYTES = 5 * 4  # float32 x, y, z, intensity, ring index
# Rows of the devkit's RadarPointCloud.points (its FIELDS order): rcs, the velocities, and the
# row this module's radar class (_radar_class) overwrites with the radial velocity. Row 6 is
# ``vx``, the velocity before ego-motion compensation, which nothing here reads.
RADAR_RCS_ROW, RADAR_RADIAL_ROW, RADAR_VX_COMP_ROW, RADAR_VY_COMP_ROW = 5, 6, 8, 9
LAYOUT = (
    "the nuScenes folder as published: samples/, sweeps/, maps/ and the table folder "
    "<version>/ (v1.0-trainval, v1.0-mini or v1.0-test) side by side"
)
_FORMATS = {
    "radar": "a nuScenes radar PCD file (v0.7 header, 18 binary fields per return) as the "
    "devkit's RadarPointCloud.from_file reads it",
    "lidar": "a nuScenes lidar .pcd.bin file (float32 x, y, z, intensity, ring index per point)",
}
_NIGHT = re.compile(r"\bnight", re.IGNORECASE)
_RAIN = re.compile(r"\brain", re.IGNORECASE)  # rain, rainy, raining; not train, drain, terrain

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Devkit:
    """The parts of ``nuscenes-devkit`` this module uses."""

    NuScenes: type
    RadarPointCloud: type
    LidarPointCloud: type
    view_points: Callable[..., np.ndarray]
    create_splits_scenes: Callable[..., dict]
    NuScenesExplorer: type
    BoxVisibility: Any
    Quaternion: type


def require_devkit() -> Devkit:
    """Imports the devkit, or fails with the install command (it is an optional extra)."""
    try:
        from nuscenes.nuscenes import NuScenes, NuScenesExplorer
        from nuscenes.utils.data_classes import LidarPointCloud, RadarPointCloud
        from nuscenes.utils.geometry_utils import BoxVisibility, view_points
        from nuscenes.utils.splits import create_splits_scenes
        from pyquaternion import Quaternion  # the devkit's own dependency
    except ImportError as err:
        raise ImportError(
            "dataset=nuscenes reads nuScenes with the official nuscenes-devkit, which could not "
            f"be imported ({err}). Install the optional extra: {INSTALL} in the fusion-depth "
            "checkout (or pip install nuscenes-devkit). It pins numpy<2, which is why it is not "
            "a core dependency."
        ) from err
    return Devkit(
        NuScenes,
        RadarPointCloud,
        LidarPointCloud,
        view_points,
        create_splits_scenes,
        NuScenesExplorer,
        BoxVisibility,
        Quaternion,
    )


def condition_from_description(description: str) -> str:
    """``night`` / ``rain`` / ``day`` from a scene description (night wins over rain)."""
    if _NIGHT.search(description):
        return "night"
    if _RAIN.search(description):
        return "rain"
    return "day"


def resize_geometry(h0: int, w0: int, height: int, width: int) -> tuple[int, int, int, int]:
    """``(new_h, new_w, top, left)``: the size an ``h0 x w0`` image is scaled to, uniformly, to
    cover ``height x width`` (rounded per axis), and the crop offset (centred horizontally, from
    the top vertically) that cuts it to that size. :func:`resize_and_crop` applies it."""
    scale = max(width / w0, height / h0)
    new_w = max(width, round(w0 * scale))
    new_h = max(height, round(h0 * scale))
    return new_h, new_w, new_h - height, (new_w - width) // 2


def resize_and_crop(
    image: np.ndarray, intrinsic: np.ndarray, height: int, width: int
) -> tuple[np.ndarray, np.ndarray]:
    """Scales ``image`` uniformly to cover ``height x width`` and crops it (centred horizontally,
    from the top vertically); returns it with the intrinsics that project into the result.

    Pixel centres sit at integers (the devkit's ``view_points`` convention), so scaling by ``s``
    maps ``u`` to ``s (u + 0.5) - 0.5`` (PIL's resampling aligns pixel areas the same way): the
    intrinsics' rows scale by the factors (per axis, after rounding the resized size), and the
    principal point also moves by ``0.5 s - 0.5`` and the crop offset.

    Args:
        image: (H0, W0, 3) uint8 RGB.
        intrinsic: (3, 3) camera matrix of ``image`` in pixels.
        height: output rows; width: output columns.

    Returns:
        The (height, width, 3) image and the float64 (3, 3) matrix projecting into it.
    """
    h0, w0 = image.shape[:2]
    new_h, new_w, top, left = resize_geometry(h0, w0, height, width)
    if (new_w, new_h) != (w0, h0):
        resized = Image.fromarray(image).resize((new_w, new_h), Image.Resampling.BILINEAR)
        image = np.asarray(resized)
    k = np.asarray(intrinsic, dtype=np.float64).copy()
    for axis, scale_axis, offset in ((0, new_w / w0, left), (1, new_h / h0, top)):
        k[axis] *= scale_axis
        k[axis, 2] += 0.5 * scale_axis - 0.5 - offset
    return np.ascontiguousarray(image[top : top + height, left : left + width]), k


def image_points(
    points: np.ndarray,
    intrinsic: np.ndarray,
    height: int,
    width: int,
    min_distance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The camera-frame points ``(>=3, N)`` (rows x, y, z first) that land in the image: float64
    ``(M,)`` arrays ``u, v`` (continuous pixel position: column, row; pixel centres at
    integers) and ``z`` (depth, metres),
    and the int64 ``(M,)`` indices of those points among the N, in their order.

    Drops points with depth ``z < min_distance`` (behind the camera included), beyond the cache's
    ceiling, or outside the image.
    """
    points = np.asarray(points, dtype=np.float64)[:3]
    z = points[2]
    keep = np.flatnonzero(np.isfinite(points).all(0) & (z >= min_distance) & (z <= CACHE_MAX_DEPTH))
    if not len(keep):
        return np.zeros(0), np.zeros(0), np.zeros(0), keep
    uv = require_devkit().view_points(
        points[:, keep], np.asarray(intrinsic, np.float64), normalize=True
    )
    inside = in_image(uv[0], uv[1], height, width)
    index = keep[inside]
    return uv[0, inside], uv[1, inside], points[2, index], index


def splat_nearest(
    u: np.ndarray, v: np.ndarray, z: np.ndarray, height: int, width: int
) -> np.ndarray:
    """Points inside the image (:func:`image_points`) to a float32 ``(height, width)`` depth map
    (0 = none): each at pixel ``(round(v), round(u))`` (:func:`pixel_index`), the nearest
    winning a shared pixel."""
    depth_map = np.zeros((height, width), dtype=np.float32)
    if not len(z):
        return depth_map
    flat = pixel_index(v) * width + pixel_index(u)
    order = np.lexsort((z, flat))  # by pixel, nearest first within a pixel
    _, first = np.unique(flat[order], return_index=True)
    depth_map.flat[flat[order][first]] = z[order][first]
    return depth_map


def project_points(
    points: np.ndarray,
    intrinsic: np.ndarray,
    height: int,
    width: int,
    min_distance: float,
) -> np.ndarray:
    """Camera-frame points ``(3, N)`` to a float32 ``(height, width)`` depth map (0 = none).

    Drops points with depth ``z < min_distance`` (behind the camera included), beyond the cache's
    ceiling, or outside the image; a point lands in pixel ``(round(v), round(u))`` of its
    projection (pixel centres at integers, as the devkit's ``view_points`` and RadarNet), and the
    nearest point wins a shared pixel.
    """
    u, v, z, _ = image_points(points, intrinsic, height, width, min_distance)
    return splat_nearest(u, v, z, height, width)


def _keyframe_lidar_pixels(
    explorer: Any, sample: dict
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A keyframe's single lidar sweep on its own camera's full-resolution pixels, RadarNet's
    way: the devkit's ``NuScenesExplorer.map_pointcloud_to_image`` (depth > 1 m,
    ``1 < u < W - 1``, ``1 < v < H - 1``), each point on pixel ``np.round`` of its ``(v, u)``.
    int64 ``rows`` and ``cols`` and float64 ``depth``, one per point, in the devkit's order."""
    points, depth, _ = explorer.map_pointcloud_to_image(
        _channel_token(sample, LIDAR), _channel_token(sample, CAMERA)
    )
    cols, rows = np.round(points[0]).astype(np.int64), np.round(points[1]).astype(np.int64)
    return rows, cols, np.asarray(depth, dtype=np.float64)


def _last_written(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The index of each pixel's last point, in writing order: the point a Python loop of
    ``map[y, x] = z`` leaves on the pixel."""
    flat = rows * (int(cols.max(initial=0)) + 1) + cols
    _, last_reversed = np.unique(flat[::-1], return_index=True)
    return np.sort(len(flat) - 1 - last_reversed)


def radarnet_ground_truth(
    devkit: Devkit, nusc: Any, sample: dict
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RadarNet's evaluation ground truth of one keyframe, at the camera's full resolution:
    int64 ``(N,)`` pixel ``rows`` and ``cols`` and float64 ``depth`` in metres, one per pixel.

    Its rule (``lidar_depth_map_from_token`` and ``save_depth`` in ``setup/`` and ``src/`` of
    github.com/nesl/radar-camera-fusion-depth): the keyframe's single lidar sweep through the
    devkit's ``NuScenesExplorer.map_pointcloud_to_image`` (depth > 1 m, ``1 < u < W - 1``,
    ``1 < v < H - 1``), each point on pixel ``np.round`` of its ``(v, u)``, the last point
    written winning a shared pixel, stored as a PNG of ``uint32(256 z)``, so the depth is
    truncated to 1/256 m.
    """
    rows, cols, depth = _keyframe_lidar_pixels(devkit.NuScenesExplorer(nusc), sample)
    stored = np.floor(depth * 256.0)  # uint32(z * 256), z > 1
    last = _last_written(rows, cols)
    return rows[last], cols[last], stored[last] / 256.0


# RadarNet's merged training target (setup/setup_dataset_nuscenes.py, merge_lidar_point_clouds):
# the annotation categories whose boxes' image rectangles are cleared ("moving objects").
RADARNET_REMOVED_CATEGORIES = ("vehicle", "human")


def _last_wins(rows: np.ndarray, cols: np.ndarray, depth: np.ndarray, shape: tuple[int, int]):
    """A float64 ``shape`` map with each point on its pixel, the last point written winning."""
    image = np.zeros(shape, dtype=np.float64)
    last = _last_written(rows, cols)
    image[rows[last], cols[last]] = depth[last]
    return image


def _clear_boxes(
    devkit: Devkit, nusc: Any, sample: dict, image: np.ndarray, removed: Sequence[str]
) -> None:
    """Zeroes, in place, the image rectangle of each of the keyframe's annotated boxes whose
    category starts with one of ``removed``: ``int`` of the projected corners' extremes, as
    RadarNet slices (numpy's negative-index semantics included)."""
    _, boxes, intrinsic = nusc.get_sample_data(
        _channel_token(sample, CAMERA),
        box_vis_level=devkit.BoxVisibility.ANY,
        use_flat_vehicle_coordinates=False,
    )
    for box in boxes:
        if any(box.name.startswith(prefix) for prefix in removed):
            corners = devkit.view_points(box.corners(), view=intrinsic, normalize=True)[:2, :]
            min_x, min_y = int(np.min(corners[0])), int(np.min(corners[1]))
            max_x, max_y = int(np.max(corners[0])), int(np.max(corners[1]))
            image[min_y:max_y, min_x:max_x] = 0


def _pose(record: dict, quaternion: type) -> tuple[np.ndarray, np.ndarray]:
    return quaternion(record["rotation"]).rotation_matrix, np.asarray(record["translation"])


def _into_keyframe(
    devkit: Devkit, nusc: Any, other: dict, main: dict, image: np.ndarray, intrinsic: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixels of ``other``'s lidar image lifted to 3-D with its camera, carried through its
    lidar's frame into ``main``'s camera and projected there (RadarNet's
    ``camera_to_lidar_frame`` then ``point_cloud_to_image``): float ``(u, v)`` and depth of the
    points deeper than 1 m strictly inside the 1-pixel margin."""
    q = devkit.Quaternion
    ys, xs = np.nonzero(image)
    z = image[ys, xs]
    xyz = np.linalg.inv(intrinsic) @ np.stack([xs, ys, np.ones_like(xs)]).astype(np.float64) * z
    camera = nusc.get("sample_data", _channel_token(other, CAMERA))
    lidar = nusc.get("sample_data", _channel_token(other, LIDAR))
    main_camera = nusc.get("sample_data", _channel_token(main, CAMERA))
    # (pose record, inverse?) in RadarNet's order; the lidar's four steps cancel out, but are
    # kept so that the float arithmetic is RadarNet's
    steps = [
        (nusc.get("calibrated_sensor", camera["calibrated_sensor_token"]), False),
        (nusc.get("ego_pose", camera["ego_pose_token"]), False),
        (nusc.get("ego_pose", lidar["ego_pose_token"]), True),
        (nusc.get("calibrated_sensor", lidar["calibrated_sensor_token"]), True),
        (nusc.get("calibrated_sensor", lidar["calibrated_sensor_token"]), False),
        (nusc.get("ego_pose", lidar["ego_pose_token"]), False),
        (nusc.get("ego_pose", main_camera["ego_pose_token"]), True),
        (nusc.get("calibrated_sensor", main_camera["calibrated_sensor_token"]), True),
    ]
    for record, inverse in steps:
        rotation, translation = _pose(record, q)
        if inverse:
            xyz = rotation.T @ (xyz - translation[:, None])
        else:
            xyz = rotation @ xyz + translation[:, None]
    main_calibration = nusc.get("calibrated_sensor", main_camera["calibrated_sensor_token"])
    points = devkit.view_points(xyz, np.asarray(main_calibration["camera_intrinsic"]), True)
    height, width = image.shape
    keep = (
        (xyz[2] > 1.0)
        & (points[0] > 1)
        & (points[0] < width - 1)
        & (points[1] > 1)
        & (points[1] < height - 1)
    )
    return points[0, keep], points[1, keep], xyz[2, keep]


def merged_lidar_ground_truth(
    devkit: Devkit,
    nusc: Any,
    sample: dict,
    keyframes: int,
    removed: Sequence[str] = RADARNET_REMOVED_CATEGORIES,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RadarNet's merged training target of one keyframe at the camera's full resolution:
    int64 ``(N,)`` pixel ``rows`` and ``cols`` and float64 ``depth`` in metres, one per pixel.

    Its rule (``merge_lidar_point_clouds`` in ``setup/setup_dataset_nuscenes.py`` of
    github.com/nesl/radar-camera-fusion-depth, ``--n_forward/backward_frames_to_reproject``, 12
    by default): the keyframe's own lidar image (:func:`radarnet_ground_truth`'s, untruncated);
    then each of up to ``keyframes`` keyframes after it, then before it: its lidar image on its
    own camera with its annotated ``removed`` boxes' rectangles cleared, lifted to 3-D, carried
    into this keyframe's camera (depth > 1 m, inside the 1-pixel margin), placed with
    ``np.round`` (last wins), this keyframe's ``removed`` rectangles cleared, and merged: a pixel
    without depth takes it, one with depth takes a nearer one. Stored by RadarNet as a uint16
    PNG (truncated to 1/256 m), which the caller does.

    Its published setup (``setup_dataset_nuscenes_with_denseGT.py``, ±80 keyframes) clears
    moving objects with panoptic segmentation masks instead of boxes; that one is not built here.

    Shape:
        - out: three ``(N,)`` arrays, rows then columns then depth.
    """
    explorer = devkit.NuScenesExplorer(nusc)
    camera = nusc.get("sample_data", _channel_token(sample, CAMERA))
    shape = (int(camera["height"]), int(camera["width"]))
    main = _last_wins(*_keyframe_lidar_pixels(explorer, sample), shape)
    for other in _neighbour_keyframes(nusc, sample, keyframes):
        image = _last_wins(*_keyframe_lidar_pixels(explorer, other), shape)
        _clear_boxes(devkit, nusc, other, image, removed)
        other_camera = nusc.get("sample_data", _channel_token(other, CAMERA))
        calibration = nusc.get("calibrated_sensor", other_camera["calibrated_sensor_token"])
        intrinsic = np.asarray(calibration["camera_intrinsic"], dtype=np.float64)
        u, v, z = _into_keyframe(devkit, nusc, other, sample, image, intrinsic)
        cols, rows = np.round(u).astype(np.int64), np.round(v).astype(np.int64)
        moved = _last_wins(rows, cols, z, shape)
        _clear_boxes(devkit, nusc, sample, moved, removed)
        take = (moved > 0) & ((main == 0) | (moved < main))
        main[take] = moved[take]
    rows, cols = np.nonzero(main)
    return rows, cols, main[rows, cols]


def full_resolution_points(
    rows: np.ndarray,
    cols: np.ndarray,
    depth: np.ndarray,
    source_size: tuple[int, int],
    size: tuple[int, int],
) -> np.ndarray:
    """Full-resolution ground-truth pixels as float32 ``(M, 3)`` rows ``y, x, depth``: each
    pixel's centre in the coordinates of the resized and cropped frame (:func:`resize_geometry`;
    pixel centres at integers, ``y = s (row + 0.5) - 0.5 - top``), the pixels that fall outside
    that frame (the rows the crop cut) left out. What ``eval.resolution=full`` reads the
    prediction at (:func:`fusion_depth.models.inference.depth_at_points`)."""
    (h0, w0), (height, width) = source_size, size
    new_h, new_w, top, left = resize_geometry(h0, w0, height, width)
    y = new_h / h0 * (rows + 0.5) - 0.5 - top
    x = new_w / w0 * (cols + 0.5) - 0.5 - left
    inside = in_image(x, y, height, width)
    return np.stack([y[inside], x[inside], depth[inside]], axis=1).astype(np.float32)


def radar_filter_states(
    mode: str,
    invalid_states: Sequence[int] = (0,),
    dynprop_states: Sequence[int] = tuple(range(7)),
    ambig_states: Sequence[int] = (3,),
) -> dict[str, list[int]]:
    """The states a radar return must have to be kept, as the devkit's filter attributes.

    ``default`` and ``off`` are the devkit's own ``RadarPointCloud.default_filters()`` and
    ``disable_filters()``; ``custom`` takes the three lists.

    Raises:
        ArgumentError: naming the reader's argument (``radar_filters``, ``radar_<name>``).
    """
    if mode not in RADAR_FILTERS:
        raise ArgumentError(
            f"{{radar_filters}}={mode!r}: expected one of {RADAR_FILTERS}",
            "radar_filters",
            owner=radar_filter_states,
        )
    if mode == "custom":
        states = {
            "invalid_states": invalid_states,
            "dynprop_states": dynprop_states,
            "ambig_states": ambig_states,
        }
        for name, values in states.items():
            limit = RADAR_STATE_RANGES[name]
            values = list(values) if values is not None else []
            if not values or any(int(v) != v or not 0 <= v < limit for v in values):
                raise ArgumentError(
                    f"{{radar_{name}}}={values}: expected a non-empty list of integers "
                    f"in [0, {limit - 1}] (or {{radar_filters}}=off to keep every return)",
                    f"radar_{name}",
                    "radar_filters",
                    owner=radar_filter_states,
                )
        return {name: sorted({int(v) for v in values}) for name, values in states.items()}
    filters = type("RadarFilters", (require_devkit().RadarPointCloud,), {})
    if mode == "default":
        filters.default_filters()
    else:
        filters.disable_filters()
    return {name: sorted(int(v) for v in getattr(filters, name)) for name in RADAR_STATE_RANGES}


def radial_velocity(points: np.ndarray) -> np.ndarray:
    """The radial velocity (N,) in m/s, positive moving away, of radar returns ``(18, N)`` in
    their sensor's frame: ``(vx_comp, vy_comp)`` projected on the direction from the sensor to
    ``(x, y)``; 0 for a return at the sensor or with a non-finite value."""
    x, y = points[0], points[1]
    vx, vy = points[RADAR_VX_COMP_ROW], points[RADAR_VY_COMP_ROW]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        radial = (x * vx + y * vy) / np.hypot(x, y)
    return np.where(np.isfinite(radial), radial, 0.0)


def _radar_class(devkit: Devkit, states: dict[str, list[int]]) -> type:
    """A ``RadarPointCloud`` with these filter states as its class attributes: the devkit's
    ``from_file_multisweep`` applies them, and the devkit's global defaults stay untouched.

    Its ``from_file`` also writes each return's :func:`radial_velocity` into row
    :data:`RADAR_RADIAL_ROW` (``vx``, unused here) while the points are still in the sensor's
    frame: ``from_file_multisweep`` moves only x, y, z into the camera frame, after which the
    line of sight from the radar is no longer known.
    """

    class FilteredRadarPointCloud(devkit.RadarPointCloud):
        @classmethod
        def from_file(cls, file_name: str, *args: Any, **kwargs: Any) -> Any:
            cloud = super().from_file(file_name, *args, **kwargs)
            if cloud.points.shape[1]:
                cloud.points[RADAR_RADIAL_ROW] = radial_velocity(cloud.points)
            return cloud

    for name, values in states.items():
        setattr(FilteredRadarPointCloud, name, values)
    return FilteredRadarPointCloud


@dataclass(frozen=True)
class FrameSettings:
    """What turns one keyframe into a prepared frame."""

    height: int
    width: int
    radar_channels: tuple[str, ...]
    radar_nsweeps: int
    radar_states: dict
    lidar_nsweeps: int
    min_distance: float
    fill: str  # "none" for val/test
    full_ground_truth: bool = False  # val/test: RadarNet's full-resolution ground truth too
    lidar_keyframes: int = 0  # train: RadarNet's merged target from this many keyframes each way
    lidar_removed: tuple[str, ...] = RADARNET_REMOVED_CATEGORIES


def _channel_token(sample: dict, channel: str) -> str:
    try:
        return sample["data"][channel]
    except KeyError:
        raise ValueError(
            f"sample {sample['token']}: no {channel} sample_data among its keyframe data "
            f"{sorted(sample['data'])}; expected every nuScenes sensor channel"
        ) from None


def _sweep_chain(nusc: Any, sample: dict, channel: str, nsweeps: int) -> list[dict]:
    """The sample_data records ``from_file_multisweep`` reads: the keyframe and those before."""
    record = nusc.get("sample_data", _channel_token(sample, channel))
    chain = [record]
    while len(chain) < nsweeps and record["prev"]:
        record = nusc.get("sample_data", record["prev"])
        chain.append(record)
    return chain


def frame_files(nusc: Any, sample: dict, settings: FrameSettings) -> list[tuple[Path, str]]:
    """Every file one frame reads, with what it should be."""
    root = Path(nusc.dataroot)
    cam = nusc.get("sample_data", _channel_token(sample, CAMERA))
    files = [(root / cam["filename"], f"{CAMERA} image")]
    for channel in settings.radar_channels:
        for record in _sweep_chain(nusc, sample, channel, settings.radar_nsweeps):
            files.append((root / record["filename"], f"{channel} radar point cloud"))
    for record in _sweep_chain(nusc, sample, LIDAR, settings.lidar_nsweeps):
        files.append((root / record["filename"], f"{LIDAR} lidar point cloud"))
    for other in _neighbour_keyframes(nusc, sample, settings.lidar_keyframes):
        for channel, what in ((LIDAR, "lidar point cloud"), (CAMERA, "image")):
            record = nusc.get("sample_data", _channel_token(other, channel))
            files.append((root / record["filename"], f"{channel} {what} of a merged keyframe"))
    return files


def _neighbour_keyframes(nusc: Any, sample: dict, keyframes: int) -> list[dict]:
    """Up to ``keyframes`` keyframes after ``sample``, then up to as many before it."""
    found = []
    for direction in ("next", "prev"):
        other = sample
        for _ in range(keyframes):
            if not other[direction]:
                break
            other = nusc.get("sample", other[direction])
            found.append(other)
    return found


def check_files(nusc: Any, tokens: Sequence[str], settings: FrameSettings) -> None:
    """Fails before any frame is prepared if a file is missing (or a lidar file is cut short)."""
    missing: list[tuple[Path, str, str]] = []
    total = 0
    for token in tokens:
        for path, what in frame_files(nusc, nusc.get("sample", token), settings):
            total += 1
            try:
                size = path.stat().st_size
            except OSError:
                missing.append((path, what, token))
                continue
            if path.name.endswith(".bin") and size % LIDAR_POINT_BYTES:
                raise ValueError(
                    f"{path}: {size} bytes, not a whole number of {LIDAR_POINT_BYTES}-byte points; "
                    f"expected {_FORMATS['lidar']}"
                )
    if missing:
        path, what, token = missing[0]
        raise FileNotFoundError(
            f"{path}: missing {what} of sample {token}; {len(missing)} of the {total} files these "
            f"frames need are missing under {nusc.dataroot} (expected every samples/ and sweeps/ "
            f"blob of {nusc.version} unpacked there)"
        )


def _camera_points(
    cloud: type, nusc: Any, sample: dict, channel: str, nsweeps: int, min_distance: float, what: str
) -> np.ndarray:
    """Camera-frame points of ``channel``'s last ``nsweeps`` sweeps, via the devkit: the point
    cloud's rows (x, y, z moved into the camera frame, the others as read), ``(rows, N)``."""
    try:
        pc, _ = cloud.from_file_multisweep(
            nusc, sample, channel, CAMERA, nsweeps=nsweeps, min_distance=min_distance
        )
    except Exception as err:  # the devkit's readers fail with assertions, struct or numpy errors
        paths = [
            Path(nusc.dataroot) / r["filename"]
            for r in _sweep_chain(nusc, sample, channel, nsweeps)
        ]
        for path in paths:  # find the culprit; only on this error path
            try:
                cloud.from_file(str(path))
            except Exception as file_err:
                raise ValueError(
                    f"{path}: unreadable {channel} {what} point cloud "
                    f"({type(file_err).__name__}: {file_err}); expected {_FORMATS[what]}"
                ) from err
        raise ValueError(
            f"sample {sample['token']}: the devkit could not accumulate {channel} from "
            f"{[str(p) for p in paths]} ({type(err).__name__}: {err})"
        ) from err
    return np.asarray(pc.points, dtype=np.float64)


def _intrinsic(calibration: dict, image_path: Path) -> np.ndarray:
    k = np.asarray(calibration.get("camera_intrinsic") or [], dtype=np.float64)
    if k.shape != (3, 3) or not np.isfinite(k).all() or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise ValueError(
            f"calibrated_sensor {calibration['token']} ({image_path.name}): camera_intrinsic "
            f"{calibration.get('camera_intrinsic')!r}; expected a 3x3 pinhole matrix"
        )
    return k


def load_frame(devkit: Devkit, nusc: Any, token: str, settings: FrameSettings) -> PreparedFrame:
    """One keyframe sample: image, projected radar (as a map and as points) and lidar, and the
    filled lidar map."""
    sample = nusc.get("sample", token)
    cam = nusc.get("sample_data", _channel_token(sample, CAMERA))
    image_path = Path(nusc.dataroot) / cam["filename"]
    image = read_rgb(image_path)
    h0, w0 = image.shape[:2]
    if cam.get("width") and cam.get("height") and (cam["width"], cam["height"]) != (w0, h0):
        raise ValueError(
            f"{image_path}: image is {w0}x{h0}, expected {cam['width']}x{cam['height']} as "
            "sample_data.json records it (the camera intrinsics are for that size)"
        )
    intrinsic = _intrinsic(
        nusc.get("calibrated_sensor", cam["calibrated_sensor_token"]), image_path
    )
    image, intrinsic = resize_and_crop(image, intrinsic, settings.height, settings.width)
    size = (settings.height, settings.width)

    radar_cloud = _radar_class(devkit, settings.radar_states)
    radar = [
        _camera_points(
            radar_cloud,
            nusc,
            sample,
            channel,
            settings.radar_nsweeps,
            settings.min_distance,
            "radar",
        )
        for channel in settings.radar_channels
    ]
    radar_all = np.concatenate(radar, 1)
    u, v, z, index = image_points(radar_all, intrinsic, *size, settings.min_distance)
    features = np.nan_to_num(
        radar_all[[RADAR_RCS_ROW, RADAR_RADIAL_ROW]][:, index], nan=0.0, posinf=0.0, neginf=0.0
    )
    lidar = _camera_points(
        devkit.LidarPointCloud,
        nusc,
        sample,
        LIDAR,
        settings.lidar_nsweeps,
        settings.min_distance,
        "lidar",
    )
    depth = project_points(lidar[:3], intrinsic, *size, settings.min_distance)
    if settings.lidar_keyframes:  # RadarNet's merged target, stored as its PNG (1/256 m)
        rows, cols, merged = merged_lidar_ground_truth(
            devkit, nusc, sample, settings.lidar_keyframes, settings.lidar_removed
        )
        merged = np.floor(merged * 256.0) / 256.0
        y, x, merged = full_resolution_points(rows, cols, merged, (h0, w0), size).T
        kept = merged <= CACHE_MAX_DEPTH
        depth = splat_nearest(x[kept], y[kept], merged[kept], *size)
    full_points = None
    if settings.full_ground_truth:
        full_points = full_resolution_points(
            *radarnet_ground_truth(devkit, nusc, sample), (h0, w0), size
        )
    scene = nusc.get("scene", sample["scene_token"])
    return PreparedFrame(
        image=image,
        sparse=splat_nearest(u, v, z, *size),
        depth=depth,
        condition=condition_from_description(scene.get("description", "")),
        filled=None if settings.fill == "none" else fill_depth(depth, image, settings.fill),
        radar_points=point_rows(u, v, z, rcs=features[0], velocity=features[1]),
        full_points=full_points,
    )


def split_frames(
    nusc: Any, scene_names: Sequence[str], conditions: Sequence[str], stride: int, what: str
) -> list[str]:
    """Sample tokens of the named scenes (scene-name order, then time order), every
    ``stride``-th keyframe of each, only scenes whose condition is in ``conditions``."""
    by_name = {scene["name"]: scene for scene in nusc.scene}
    present = sorted(set(scene_names) & set(by_name))
    table = Path(nusc.dataroot) / nusc.version / "scene.json"
    if not present:
        raise ArgumentError(
            f"{table}: none of the {len(scene_names)} scenes of {what} "
            f"({', '.join(sorted(scene_names)[:4])}, ...) is listed; expected the {nusc.version} "
            "tables as published, or another {version}",
            "version",
            owner=split_frames,
        )
    tokens: list[str] = []
    skipped: dict[str, int] = {}
    for name in present:
        scene = by_name[name]
        condition = condition_from_description(scene.get("description", ""))
        if condition not in conditions:
            skipped[condition] = skipped.get(condition, 0) + 1
            continue
        token, index = scene["first_sample_token"], 0
        while token:
            if index > len(nusc.sample):
                raise ValueError(f"{table}: scene {name}'s samples form a loop (sample {token})")
            sample = nusc.get("sample", token)
            if index % stride == 0:
                tokens.append(token)
            token, index = sample["next"], index + 1
    if not tokens:
        raise ArgumentError(
            f"{table}: {what} has no keyframe left: {{conditions}}={list(conditions)} "
            f"excludes all its {len(present)} scenes (conditions: {skipped}); expected at least "
            "one scene with a keyframe",
            "conditions",
            owner=split_frames,
        )
    return tokens


def check_tables(root: Path, version: str) -> str:
    """Checks ``<root>/<version>/`` holds the 13 tables; returns a digest of their names, sizes
    and modification times (a changed download gets a new cache)."""
    table_dir = root / version
    if not table_dir.is_dir():
        found = sorted(p.name for p in root.iterdir() if p.is_dir())
        raise FileNotFoundError(
            f"{table_dir}: missing folder; expected the nuScenes {version} tables "
            f"(<root>/{version}/*.json, from the {version} metadata archive) next to samples/, "
            f"sweeps/ and maps/ (found in {root}: {found or 'nothing'})"
        )
    digest = hashlib.sha256()
    for table in TABLES:
        path = table_dir / f"{table}.json"
        if not path.is_file():
            raise FileNotFoundError(
                f"{path}: missing table; expected the {len(TABLES)} nuScenes tables "
                f"({', '.join(TABLES)}) in {table_dir}"
            )
        stat = path.stat()
        digest.update(json.dumps([table, stat.st_size, stat.st_mtime_ns]).encode())
    return digest.hexdigest()[:16]


def load_tables(devkit: Devkit, root: Path, version: str) -> Any:
    """The devkit's database of one version; a layout it rejects fails naming the folder."""
    log.info(
        "loading the nuScenes %s tables from %s (v1.0-trainval: about a minute)", version, root
    )
    try:
        return devkit.NuScenes(version=version, dataroot=str(root), verbose=False)
    except (AssertionError, KeyError, IndexError, TypeError, ValueError, OSError) as err:
        raise ValueError(
            f"{root / version}: the nuScenes devkit could not load the {version} tables "
            f"({type(err).__name__}: {err}); expected {LAYOUT}"
        ) from err


# What NuScenesDepth's arguments accept (fusion_depth.utils.schema), checked with the config
# before any work (dataset.reader.<argument>: fusion_depth.config.dataset_validation), and here
# for a caller from Python. The others (channels, filter states) are lists checked in __init__.
READER_RULES: Schema = {
    "version": one_of(*VERSIONS),
    "fill": one_of(*FILL_METHODS),
    "radar_nsweeps": Rule(POSITIVE_INT.ok, "an integer ≥ 1 (radar sweeps per frame)"),
    "lidar_nsweeps": Rule(POSITIVE_INT.ok, "an integer ≥ 1 (lidar sweeps per frame)"),
    "lidar_keyframes": Rule(NON_NEGATIVE_INT.ok, "an integer ≥ 0 (keyframes each way; 0: none)"),
    "min_distance": Rule(lambda v: is_number(v) and math.isfinite(v) and v > 0, "metres > 0"),
    "stride": Rule(POSITIVE_INT.ok, "an integer ≥ 1 (every n-th keyframe)"),
    "test_split": one_of(*TEST_SPLITS),
}
_NUMBERS = ("radar_nsweeps", "lidar_nsweeps", "lidar_keyframes", "min_distance", "stride")


def _reader_error(message: str, argument: str) -> ArgumentError:
    """An :class:`ArgumentError` about :class:`NuScenesDepth`'s ``argument``."""
    return ArgumentError(message, argument, owner=NuScenesDepth)


class NuScenesDepth(PreparedDataset):
    """One split of nuScenes (see the module docstring), served from the prepared cache as
    :class:`~fusion_depth.data.Sample` dicts; the train split serves the filled lidar map as
    ``depth`` when ``fill`` is not ``none``. Samples carry ``radar_points`` (the nearest
    ``max_radar_points`` returns in the image; module docstring).

    Missing files fail before anything is prepared, whatever ``on_error``; a file that cannot
    be read is handled by ``on_error`` (:class:`~fusion_depth.data.base.PreparedDataset`). The
    test split is prepared from another table version (``test_split="test"``), so each split
    may have its own cache folder: this class prepares them itself (:meth:`prepare`).
    """

    name = "nuscenes"
    layout = LAYOUT
    conditions_allowed = NUSCENES_CONDITIONS
    ARGUMENT_RULES: ClassVar[Schema] = READER_RULES  # what dataset.reader's keys may hold
    format_version = FORMAT_VERSION

    def __init__(
        self,
        split: str,
        root: str | os.PathLike,
        cache_root: str | os.PathLike,
        version: str = "v1.0-trainval",
        height: int = 448,
        width: int = 800,
        fill: str = "colorization",
        conditions: Sequence[str] = NUSCENES_CONDITIONS,
        radar_channels: Sequence[str] = ("RADAR_FRONT",),
        radar_nsweeps: int = 1,
        radar_filters: str = "default",
        radar_invalid_states: Sequence[int] = (0,),
        radar_dynprop_states: Sequence[int] = tuple(range(7)),
        radar_ambig_states: Sequence[int] = (3,),
        lidar_nsweeps: int = 1,
        lidar_keyframes: int = 0,
        lidar_removed: Sequence[str] = RADARNET_REMOVED_CATEGORIES,
        min_distance: float = 1.0,
        stride: int = 1,
        test_split: str = "val",
        on_error: OnError = "raise",
        max_radar_points: int = DEFAULT_MAX_RADAR_POINTS,
        size_multiple: int = SIZE_MULTIPLE,
    ) -> None:
        require_devkit()  # first: without it nothing else can work
        for name, value, allowed in (
            ("version", version, list(VERSIONS)),
            ("fill", fill, FILL_METHODS),
            ("test_split", test_split, TEST_SPLITS),
        ):
            check_choice(value, allowed, name, owner=NuScenesDepth)
        self.conditions_kept = check_conditions(conditions, NUSCENES_CONDITIONS)
        self.radar_channels = check_conditions(radar_channels, RADAR_CHANNELS, "radar_channels")
        given = (radar_nsweeps, lidar_nsweeps, lidar_keyframes, min_distance, stride)
        for name, value in zip(_NUMBERS, given, strict=True):
            if not READER_RULES[name].ok(value):  # null, inf, nan, a list or a string too
                expected = READER_RULES[name].expected
                raise _reader_error(f"{{{name}}}={value!r}: expected {expected}", name)
        if lidar_keyframes and lidar_nsweeps != 1:
            raise ArgumentError(
                f"{{lidar_keyframes}}={lidar_keyframes} with {{lidar_nsweeps}}={lidar_nsweeps}: "
                "the merged target starts from the keyframe's single sweep; use lidar_nsweeps=1",
                "lidar_keyframes",
                "lidar_nsweeps",
                owner=NuScenesDepth,
            )
        if isinstance(lidar_removed, str) or not all(isinstance(c, str) for c in lidar_removed):
            raise _reader_error(
                f"{{lidar_removed}}={lidar_removed!r}: expected a list of category prefixes "
                "(vehicle, human)",
                "lidar_removed",
            )
        self.radar_states = radar_filter_states(
            radar_filters, radar_invalid_states, radar_dynprop_states, radar_ambig_states
        )
        self.version = version
        self.fill = fill
        self.radar_nsweeps = int(radar_nsweeps)
        self.lidar_nsweeps = int(lidar_nsweeps)
        self.lidar_keyframes = int(lidar_keyframes)
        self.lidar_removed = tuple(lidar_removed)
        self.min_distance = float(min_distance)
        self.stride = int(stride)
        self.test_split = test_split
        super().__init__(
            split, root, cache_root, height, width, on_error, max_radar_points, size_multiple
        )

    def split_folder(self, split: str) -> str:
        # test_split=val: the test split is the val split, the same frames prepared once.
        return "val" if split == "test" and self.test_split == "val" else split

    def serves_filled(self) -> bool:
        return self.split == "train" and self.fill != "none"

    def prepare(self, cache_root: Path) -> Path:
        """Prepares every split not yet in its cache folder; returns this split's folder."""
        base = {
            "format_version": self.format_version,
            "root": str(self.root),
            "version": self.version,
            "tables": check_tables(self.root, self.version),
            "height": self.height,
            "width": self.width,
            "conditions": self.conditions_kept,
            "radar_channels": self.radar_channels,
            "radar_nsweeps": self.radar_nsweeps,
            "radar_states": self.radar_states,
            "lidar_nsweeps": self.lidar_nsweeps,
            "min_distance": self.min_distance,
            "stride": self.stride,
        }
        train_key, val_key = VERSIONS[self.version]
        # split -> (cache params, table version, the devkit's split name, fill)
        merged = (  # only when asked for: earlier caches keep their folders
            {"lidar_keyframes": self.lidar_keyframes, "lidar_removed": list(self.lidar_removed)}
            if self.lidar_keyframes
            else {}
        )
        sources = {
            "train": ({**base, "fill": self.fill, **merged}, self.version, train_key, self.fill),
            "val": (base, self.version, val_key, "none"),
            "test": (base, self.version, val_key, "none"),  # test_split=val: the same frames
        }
        if self.test_split == "test":
            test_params = {
                **base,
                "test_version": TEST_VERSION,
                "test_tables": check_tables(self.root, TEST_VERSION),
            }
            sources["test"] = (test_params, TEST_VERSION, "test", "none")
        folders = {
            name: (
                cache_dir(cache_root, self.name, params, read_only=self.read_only()),
                self.split_folder(name),
            )
            for name, (params, *_) in sources.items()
        }
        todo = [
            name
            for i, name in enumerate(SPLITS)
            if folders[name] not in [folders[s] for s in SPLITS[:i]]
            and not is_prepared(*folders[name], params=sources[name][0])
        ]
        if todo:
            settings = FrameSettings(
                height=self.height,
                width=self.width,
                radar_channels=tuple(self.radar_channels),
                radar_nsweeps=self.radar_nsweeps,
                radar_states=self.radar_states,
                lidar_nsweeps=self.lidar_nsweeps,
                min_distance=self.min_distance,
                fill="none",
                lidar_keyframes=self.lidar_keyframes,
                lidar_removed=self.lidar_removed,
            )
            _prepare(
                require_devkit(),
                self.root,
                sources,
                folders,
                todo,
                self.conditions_kept,
                self.stride,
                settings,
                self.on_error,
            )
        return folders[self.split][0]


def _prepare(
    devkit: Devkit,
    root: Path,
    sources: dict[str, tuple],
    folders: dict[str, tuple[Path, str]],
    todo: Sequence[str],
    conditions: Sequence[str],
    stride: int,
    settings: FrameSettings,
    on_error: OnError = "raise",
) -> None:
    """Lists the frames of every split still to prepare and checks all their files before the
    first frame is written; the devkit's tables are loaded once per version, dropped after.
    ``on_error``: see :class:`NuScenesDepth`."""
    scene_splits = devkit.create_splits_scenes()
    databases: dict[str, Any] = {}
    plans = []
    for name in todo:
        params, version, key, fill = sources[name]
        if version not in databases:
            databases[version] = load_tables(devkit, root, version)
        nusc = databases[version]
        tokens = split_frames(
            nusc, scene_splits[key], conditions, stride, f"the {key} split of {version}"
        )
        split_settings = replace(
            settings,
            fill=fill,
            full_ground_truth=name != "train",
            lidar_keyframes=settings.lidar_keyframes if name == "train" else 0,
        )
        check_files(nusc, tokens, split_settings)
        plans.append((name, params, nusc, tokens, split_settings))
    jobs = []
    for name, params, nusc, tokens, split_settings in plans:
        cache, folder = folders[name]
        jobs.append(
            SplitJob(
                cache,
                folder,
                tokens,
                lambda token, nusc=nusc, s=split_settings: load_frame(devkit, nusc, token, s),
                params,
                lambda token, nusc=nusc, s=split_settings: [
                    path for path, _ in frame_files(nusc, nusc.get("sample", token), s)
                ],
            )
        )
    prepare_splits(jobs, on_error=on_error)
