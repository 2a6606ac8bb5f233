"""``dataset=radarnet_layout``: nuScenes as RadarNet's setup leaves it, read without the devkit.

RadarNet's setup (nesl/radar-camera-fusion-depth at c95c67d: ``setup/setup_dataset_nuscenes.py``,
``setup/setup_dataset_nuscenes_test.py``) writes derived files under ``data/nuscenes_derived``
(``data/nuscenes_derived_test`` for the test scenes) and lists them, one path per line, in text
files that RadarCam-Depth, CaFNet, GET-UP, LiRCDepth and others reuse. A user who has run it
points ``dataset.root`` at the folder it ran in, and this reader takes the frames from there,
with no devkit and no projection of its own.

Layout
------
Paths in the lists are relative to ``root`` (the authors' checkout), as their scripts write
them::

    <root>/training/nuscenes/nuscenes_train_{image,radar,lidar,ground_truth_interp}.txt
    <root>/validation/nuscenes/nuscenes_val_{image,radar,lidar}.txt
    <root>/testing/nuscenes/nuscenes_test_{image,radar,lidar}.txt
    <root>/data/nuscenes/samples/CAM_FRONT/<name>.jpg          the image (1600×900)
    <root>/data/nuscenes_derived*/radar_points/scene_<i>/CAM_FRONT/<name>.npy
    <root>/data/nuscenes_derived*/lidar/scene_<i>/CAM_FRONT/<name>.png
    <root>/data/nuscenes_derived*/ground_truth_interp/scene_<i>/CAM_FRONT/<name>.png

Frames
------
Line *i* of every list of a split is frame *i*.

* **image**: the JPEG as nuScenes ships it.
* **radar** (``*_radar.txt``): float64 ``(N, 3)`` rows ``x, y, z``: the keyframe's RADAR_FRONT
  sweep, every return (``RadarPointCloud.disable_filters()``), projected and placed on whole
  pixels, one per pixel (``merge_radar_point_clouds`` with no frames before or after). Served
  as ``radar_points`` (``u = x``, ``v = y``, ``rcs`` and ``velocity`` 0: the file has neither)
  and drawn into ``sparse`` (the nearer return winning a shared pixel: theirs has one per pixel).
* **depth** (``*_lidar.txt``): the keyframe's single lidar sweep, as a 16-bit PNG of ``256·z``
  (``lidar_depth_map_from_token``, ``data_utils.save_depth``): what their test scores.
* **filled** (train only, ``*_ground_truth_interp.txt``): lidar merged from the keyframes around
  and interpolated, their FusionNet's training target.
* **condition**: their files keep no scene description; every frame gets ``condition``.

Resolution: at ``1600×900`` (``height=900 width=1600``, with ``size_multiple=1``) the frames are
the files, pixel for pixel. At another size the image is scaled and cropped as nuScenes' reader
does (:func:`~fusion_depth.data.nuscenes.resize_and_crop`; importing that module needs no
devkit), points move centre-aware with it, the
ground truth's measured pixels are moved as points (the nearer winning), and ``filled`` is
resized by nearest neighbour. Val and test keep the files' full-resolution ground truth as
``depth_points`` for ``eval.resolution=full``.

Compared with ``dataset=nuscenes`` on the same frames (``tests/test_nuscenes.py``): the image,
the ground truth and the radar returns are the same; their setup leaves out each scene's last
keyframe, and keeps the return it wrote last where two share a pixel (here: the nearer).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import ClassVar

import numpy as np
from PIL import Image

from fusion_depth.data import CONDITIONS
from fusion_depth.data.base import SIZE_MULTIPLE, FrameList, PreparedDataset
from fusion_depth.data.cache import (
    OnError,
    PreparedFrame,
    SplitJob,
    cache_dir,
    is_prepared,
    prepare_splits,
)
from fusion_depth.data.depth_io import DataFileError, read_depth_png, read_npy, read_rgb
from fusion_depth.data.folders import fingerprint
from fusion_depth.data.nuscenes import resize_and_crop, resize_geometry, splat_nearest
from fusion_depth.data.radar_points import DEFAULT_MAX_RADAR_POINTS, in_image, point_rows
from fusion_depth.errors import check_choice

FORMAT_VERSION = 1
# split -> (the folder of its lists, their prefix): setup/setup_dataset_nuscenes(_test).py
LISTS = {
    "train": ("training/nuscenes", "nuscenes_train"),
    "val": ("validation/nuscenes", "nuscenes_val"),
    "test": ("testing/nuscenes", "nuscenes_test"),
}
# The lists each split needs: (role, file suffix).
ROLES = {
    "train": ("image", "radar", "lidar", "ground_truth_interp"),
    "val": ("image", "radar", "lidar"),
    "test": ("image", "radar", "lidar"),
}
MAX_LIST_BYTES = 64 * 2**20  # 30k frames' paths are ~4 MB; anything far larger is another file
LAYOUT = (
    "the folder RadarNet's setup ran in: training/nuscenes/, validation/nuscenes/ and "
    "testing/nuscenes/ holding nuscenes_<split>_{image,radar,lidar}.txt, with the paths they list"
)


def list_path(root: Path, split: str, role: str) -> Path:
    """The text file listing ``role``'s files of ``split`` (e.g.
    ``testing/nuscenes/nuscenes_test_radar.txt``)."""
    folder, prefix = LISTS[split]
    return root / folder / f"{prefix}_{role}.txt"


def read_list(path: Path, root: Path) -> list[Path]:
    """The paths a list names, one per non-empty line, relative to ``root`` where not absolute.

    Raises:
        FileNotFoundError: no list at ``path`` (one line naming it).
    """
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such list; expected {LAYOUT}")
    if path.stat().st_size > MAX_LIST_BYTES:
        raise ValueError(f"{path}: {path.stat().st_size} bytes, not a list of paths")
    lines = [line.strip() for line in path.read_text().splitlines()]
    return [Path(line) if Path(line).is_absolute() else root / line for line in lines if line]


class RadarNetLayout(PreparedDataset):
    """One split of RadarNet's derived nuScenes files (module docstring), served from the
    prepared cache as :class:`~fusion_depth.data.Sample` dicts with ``radar_points``.

    Args:
        split: one of :data:`~fusion_depth.data.SPLITS`.
        root: the folder RadarNet's setup ran in (its lists' paths are relative to it).
        cache_root: where prepared splits go.
        height: rows served (900: the files as they are, with ``size_multiple=1``).
        width: columns served (1600 likewise).
        condition: what every frame is labelled (their files keep no scene description).
        on_error: ``raise`` or ``skip`` (:class:`~fusion_depth.data.base.PreparedDataset`).
        max_radar_points: the returns each sample serves, nearest first.
        size_multiple: 32, or 1 for the files' own 900×1600.

    Raises:
        FileNotFoundError: a list the split needs is missing (naming it).
        ValueError: the lists of a split differ in length (naming both), a bad ``condition``.
        DataFileError: a listed file cannot be read as expected (naming it).
    """

    name = "radarnet_layout"
    layout = LAYOUT
    format_version = FORMAT_VERSION
    conditions_allowed: ClassVar[tuple[str, ...]] = CONDITIONS

    def __init__(
        self,
        split: str,
        root: str | os.PathLike,
        cache_root: str | os.PathLike,
        height: int = 900,
        width: int = 1600,
        condition: str = "day",
        on_error: OnError = "raise",
        max_radar_points: int = DEFAULT_MAX_RADAR_POINTS,
        size_multiple: int = SIZE_MULTIPLE,
    ) -> None:
        check_choice(condition, CONDITIONS, "condition", owner=RadarNetLayout)
        self.condition = condition
        super().__init__(
            split, root, cache_root, height, width, on_error, max_radar_points, size_multiple
        )

    def settings(self) -> dict:
        return {"condition": self.condition}

    def list_frames(self) -> FrameList:
        """This split's frames (their setup may have been run for some splits only: each split
        is prepared on its own, in a folder of its own)."""
        lists = {role: list_path(self.root, self.split, role) for role in ROLES[self.split]}
        paths = {role: read_list(path, self.root) for role, path in lists.items()}
        counts = {role: len(p) for role, p in paths.items()}
        if len(set(counts.values())) > 1:
            shorter = min(counts, key=counts.get)
            raise ValueError(
                f"{lists[shorter]}: {counts[shorter]} paths, but {lists['image']} has "
                f"{counts['image']}; expected one line per frame in every list"
            )
        if not counts["image"]:
            raise ValueError(f"{lists['image']}: no paths; expected one image per line")
        frames = {
            f"{i:06d}": {role: p[i] for role, p in paths.items()} for i in range(counts["image"])
        }
        return FrameList(frames={self.split: frames}, files=fingerprint(lists.values()))

    def prepare(self, cache_root: Path) -> Path:
        """Prepares this split alone (into a folder keyed by it too), unless prepared."""
        listed = self.list_frames()
        frames = listed.frames[self.split]
        params = {**self.cache_key(listed), "split": self.split}
        cache = cache_dir(cache_root, self.name, params, read_only=self.read_only())
        if is_prepared(cache, self.split, list(frames), params):
            return cache
        if self.on_error == "raise":
            self.check_frames(self.split, frames)
        job = SplitJob(
            cache,
            self.split,
            list(frames),
            lambda frame_id: self.load_frame(self.split, frames[frame_id]),
            params,
            lambda frame_id: self.frame_files(self.split, frames[frame_id]),
        )
        prepare_splits([job], on_error=self.on_error)
        return cache

    def frame_files(self, split: str, frame: dict[str, Path]) -> list[Path]:
        return list(frame.values())

    def load_frame(self, split: str, frame: dict[str, Path]) -> PreparedFrame:
        image = read_rgb(frame["image"])
        h0, w0 = image.shape[:2]
        radar = read_npy(frame["radar"], np.float64, (None, 3), "RadarNet radar points")
        lidar = read_depth_png(frame["lidar"])
        if lidar.shape != (h0, w0):
            raise DataFileError(
                frame["lidar"], f"a {lidar.shape} map for a {(h0, w0)} image ({frame['image']})"
            )
        # nuScenes' scale and crop; the matrix maps a full-resolution pixel into the frame.
        image, to_frame = resize_and_crop(image, np.eye(3), self.height, self.width)
        (sx, _, ox), (_, sy, oy) = to_frame[:2]
        u, v = sx * radar[:, 0] + ox, sy * radar[:, 1] + oy
        inside = in_image(u, v, self.height, self.width)
        u, v, z = u[inside], v[inside], radar[inside, 2]
        rows = point_rows(u, v, z)
        sparse = splat_nearest(u, v, z, self.height, self.width)
        gy, gx = np.nonzero(lidar)
        gu, gv, gz = sx * gx + ox, sy * gy + oy, lidar[gy, gx]
        kept = in_image(gu, gv, self.height, self.width)  # rows a crop cut hold no prediction
        gu, gv, gz = gu[kept], gv[kept], gz[kept]
        depth = splat_nearest(gu, gv, gz, self.height, self.width)
        filled = None
        if "ground_truth_interp" in frame:
            new_h, new_w, top, left = resize_geometry(h0, w0, self.height, self.width)
            dense = Image.fromarray(read_depth_png(frame["ground_truth_interp"]))
            dense = np.asarray(dense.resize((new_w, new_h), Image.NEAREST))
            filled = dense[top : top + self.height, left : left + self.width]
        full = np.stack([gv, gu, gz], axis=1).astype(np.float32) if split != "train" else None
        return PreparedFrame(
            image=image,
            sparse=sparse,
            depth=depth,
            condition=self.condition,
            filled=filled,
            radar_points=rows,
            full_points=full,
        )

    def serves_filled(self) -> bool:
        return self.split == "train"
