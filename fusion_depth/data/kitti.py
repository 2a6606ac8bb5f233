"""``dataset=kitti``: the KITTI depth completion benchmark, camera + Velodyne lidar.

Read exactly as KITTI publishes it on the depth completion benchmark page:

* ``<root>/data_depth_annotated/{train,val}/<drive>/proj_depth/groundtruth/image_0{2,3}/``
  ``<frame>.png``: the semi-dense ground truth (11 lidar scans accumulated and cleaned),
* ``<root>/data_depth_velodyne/{train,val}/<drive>/proj_depth/velodyne_raw/image_0{2,3}/``
  ``<frame>.png``: one raw Velodyne scan projected into the camera, the sparse input,
* ``<raw_root>/<date>/<drive>/image_0{2,3}/data/<frame>.png`` the RGB frames of the raw drives,

with ``<drive>`` like ``2011_09_26_drive_0001_sync``, ``<date>`` its first 10 characters and
``<frame>`` a 10-digit index. Depth PNGs are uint16 holding metres x 256, 0 = no measurement.
``image_02`` is the left colour camera, ``image_03`` the right; both are used.

The benchmark's selected validation set, ``test_split="val_selection_cropped"``, is read from
``<root>/depth_selection/val_selection_cropped/`` as KITTI publishes it (data_depth_selection.zip):
``groundtruth_depth/``, ``velodyne_raw/`` and ``image/`` each hold one PNG per frame, named
``<drive>_<kind>_<frame>_image_0{2,3}.png``; its 1,000 frames are already cut to 1216 x 352.

Splits. ``train`` and ``val`` are KITTI's own, every frame of both cameras (``train_stride``
keeps every n-th frame of each drive and camera for training: 10 gives the paper's ~9k frames
instead of ~86k). KITTI publishes no test ground truth, so ``test`` is ``val`` (prepared once,
shared). With ``split_file`` the test split is the frames that file lists instead (e.g. the 652
Eigen et al. test frames that have annotated depth), found in either ``train`` or ``val``; with
``exclude_test_drives`` (default) their drives are dropped from ``train`` so the network never
trains on a test scene. ``val`` stays KITTI's: it only selects the checkpoint, and many of its
drives are Eigen test drives, so dropping them would leave little of it. With
``test_split="val_selection_cropped"`` the test split is the depth-completion benchmark's 1,000
selected validation frames (the devkit's, scored with ``eval=kitti_dc``); each sample's
``frame_box`` is then the cropped frame itself, as the original frame's size is not published.

A split file has one frame per line, either

* ``2011_09_26/2011_09_26_drive_0002_sync 69 l`` (Eigen/monodepth2 split files: drive, frame
  index, ``l`` = image_02 or ``r`` = image_03), or
* a relative path naming drive, camera and frame, e.g.
  ``train/2011_09_26_drive_0001_sync/proj_depth/groundtruth/image_02/0000000005.png`` or
  ``2011_09_26/2011_09_26_drive_0002_sync/image_02/data/0000000069.png`` (first token of the line);

blank lines and ``#`` comments are skipped.

Frames. The input is ``height`` x ``width`` (the paper: 384 x 1248, KITTI's ~375 x 1242 padded
to multiples of 32). A side longer than that is cropped, keeping the bottom rows (the top of a
KITTI frame is sky without lidar) and the horizontal centre; a shorter side is padded at the
bottom/right, the image by repeating its edge, depth and sparse maps with 0 (= invalid, so
padding is never scored). ``sparse_points`` keeps that many of the Velodyne returns (sparse-to-
dense's 200/500-sample experiments), chosen at random but the same every time for a frame.
``fill`` densifies the *training* ground truth (:mod:`fusion_depth.data.filling`); validation and
test always score the measured annotated points. Each sample carries ``frame_box``, where the
original frame lies in it, so ``eval.crop=garg|eigen`` takes its fractions of the full KITTI
frame exactly as the KITTI scripts do. Every frame is condition ``day``.

All of it happens once, in the prepared cache ``<cache_root>/kitti/<hash>/`` (see
:mod:`fusion_depth.data.cache`; ``python -m fusion_depth.prepare dataset=kitti ...``). Every
split is prepared on first use, before any training, so a missing or corrupt file anywhere
fails at once, naming the file: every frame's files are checked before the first is prepared,
and a missing one or a directory where a frame's PNG should be is a FileNotFoundError listing a
few. ``python -m fusion_depth.prepare`` (``on_error="skip"``) instead counts each such frame as
skipped (a directory then raising IsADirectoryError), names it, and prepares the others. The
dataset folders are only ever read.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from itertools import groupby
from pathlib import Path

import numpy as np

from fusion_depth.data.base import FrameList, PreparedDataset, check_size
from fusion_depth.data.cache import OnError, PreparedFrame, not_a_file
from fusion_depth.data.depth_io import DataFileError, read_depth_png, read_rgb
from fusion_depth.data.filling import FILL_METHODS, fill_depth
from fusion_depth.errors import ArgumentError, ArgumentFileError

SUBSETS: tuple[str, ...] = ("train", "val")  # what KITTI publishes ground truth for
CAMERAS: dict[str, str] = {"l": "image_02", "r": "image_03"}
CONDITION = "day"
ANNOTATED = "data_depth_annotated"
VELODYNE = "data_depth_velodyne"
SELECTION = "val_selection_cropped"  # the benchmark's 1,000 selected validation frames
SELECTION_FOLDER = Path("depth_selection", SELECTION)
TEST_SPLITS: tuple[str, ...] = ("val", SELECTION)  # what test is without a split file
KITTI_VERSION = 1  # bump when the frame processing changes, so old caches are not reused
# Evaluation crops as fractions of the full frame, (top, bottom, left, right), as monodepth2
# writes them: Garg et al.'s (ECCV 2016) and Eigen et al.'s (NIPS 2014).
_DRIVE = r"\d{4}_\d{2}_\d{2}_drive_\d{4}_sync"
_DRIVE_RE = re.compile(rf"^{_DRIVE}$")
_EIGEN_LINE = re.compile(rf"^(?:\d{{4}}_\d{{2}}_\d{{2}}/)?({_DRIVE})$")
_PATH_LINE = re.compile(rf"(?:^|/)({_DRIVE})/(?:.*/)?(image_0[23])/(?:.*/)?(\d+)(?:\.png)?$")
_SELECTION_NAME = re.compile(rf"^({_DRIVE})_groundtruth_depth_(\d{{10}})_(image_0[23])\.png$")
_SHOWN = 5  # how many missing files an error message lists

log = logging.getLogger(__name__)


@dataclass(frozen=True, order=True)
class KittiFrame:
    """One camera frame: where its three files are."""

    subset: str  # the data_depth_* folder holding it: train | val, or val_selection_cropped
    drive: str  # e.g. 2011_09_26_drive_0001_sync
    camera: str  # image_02 | image_03
    frame: str  # 10 digits

    @property
    def id(self) -> str:
        return f"{self.subset}/{self.drive}/{self.camera}/{self.frame}"

    @classmethod
    def from_id(cls, frame_id: str) -> KittiFrame:
        subset, drive, camera, frame = frame_id.split("/")
        return cls(subset, drive, camera, frame)

    def _selected(self, root: Path, kind: str) -> Path:
        """A file of the selected validation set: ``<kind>/<drive>_<kind>_<frame>_<camera>.png``."""
        name = f"{self.drive}_{kind}_{self.frame}_{self.camera}.png"
        return root / SELECTION_FOLDER / kind / name

    def groundtruth(self, root: Path) -> Path:
        if self.subset == SELECTION:
            return self._selected(root, "groundtruth_depth")
        folder = root / ANNOTATED / self.subset / self.drive / "proj_depth" / "groundtruth"
        return folder / self.camera / f"{self.frame}.png"

    def velodyne(self, root: Path) -> Path:
        if self.subset == SELECTION:
            return self._selected(root, "velodyne_raw")
        folder = root / VELODYNE / self.subset / self.drive / "proj_depth" / "velodyne_raw"
        return folder / self.camera / f"{self.frame}.png"

    def image(self, root: Path, raw_root: Path) -> Path:
        if self.subset == SELECTION:
            return self._selected(root, "image")
        return raw_root / self.drive[:10] / self.drive / self.camera / "data" / f"{self.frame}.png"


# --- layout -----------------------------------------------------------------------------------


def check_layout(root: Path, raw_root: Path) -> None:
    """The published top-level folders exist, or an error saying which and what was expected."""
    if not root.is_dir():
        raise ArgumentFileError(
            f"{{root}}={root}: no such folder; expected the KITTI depth completion folder "
            f"holding {ANNOTATED}/ and {VELODYNE}/",
            "root",
            owner=check_layout,
        )
    if root.name in (ANNOTATED, VELODYNE):
        raise ArgumentError(
            f"{{root}}={root}: this is the {root.name} folder itself; pass its parent, "
            f"the folder holding both {ANNOTATED}/ and {VELODYNE}/",
            "root",
            owner=check_layout,
        )
    for name, below in ((ANNOTATED, "groundtruth"), (VELODYNE, "velodyne_raw")):
        if not (root / name).is_dir():
            raise FileNotFoundError(
                f"{root / name}: missing; expected the KITTI depth completion layout "
                f"<root>/{name}/{{train,val}}/<drive>/proj_depth/{below}/image_0{{2,3}}/<frame>.png"
            )
    if not raw_root.is_dir():
        raise ArgumentFileError(
            f"{{raw_root}}={raw_root}: no such folder; expected the KITTI raw data, "
            "<raw_root>/<date>/<drive>/image_0{2,3}/data/<frame>.png",
            "raw_root",
            owner=check_layout,
        )


def list_subset(root: Path, subset: str) -> list[KittiFrame]:
    """Every annotated frame of one of KITTI's subsets, in a fixed order."""
    folder = root / ANNOTATED / subset
    expected = "<drive>/proj_depth/groundtruth/image_0{2,3}/<frame>.png"
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: missing; expected {folder}/{expected}")
    drives = sorted(p for p in folder.iterdir() if p.is_dir() and _DRIVE_RE.match(p.name))
    if not drives:
        raise ValueError(
            f"{folder}: no drive folders like 2011_09_26_drive_0001_sync; expected "
            f"{folder}/{expected}"
        )
    frames = []
    for drive in drives:
        gt = drive / "proj_depth" / "groundtruth"
        cameras = [c for c in sorted(CAMERAS.values()) if (gt / c).is_dir()]
        if not cameras:
            raise FileNotFoundError(
                f"{gt}: expected the folders image_02/ and image_03/ of annotated depth PNGs"
            )
        for camera in cameras:
            frames += [
                KittiFrame(subset, drive.name, camera, png.stem)
                for png in sorted((gt / camera).glob("*.png"))
            ]
    if not frames:
        raise ValueError(f"{folder}: no annotated depth PNGs; expected {folder}/{expected}")
    return frames


def list_selection(root: Path) -> list[KittiFrame]:
    """The selected validation set's frames (``val_selection_cropped``), in name order."""
    folder = root / SELECTION_FOLDER / "groundtruth_depth"
    expected = "<drive>_groundtruth_depth_<frame>_image_0{2,3}.png"
    if not folder.is_dir():
        raise ArgumentFileError(
            f"{folder}: missing; {{test_split}}={SELECTION} reads KITTI's "
            f"data_depth_selection.zip unpacked into {{root}}: {folder}/{expected}",
            "test_split",
            "root",
            owner=list_selection,
        )
    frames = []
    for png in sorted(folder.glob("*.png")):
        match = _SELECTION_NAME.match(png.name)
        if match is None:
            raise ValueError(f"{png}: not a selected-frame name; expected {expected}")
        drive, frame, camera = match.groups()
        frames.append(KittiFrame(SELECTION, drive, camera, frame))
    if not frames:
        raise ValueError(f"{folder}: no ground-truth PNGs; expected {folder}/{expected}")
    return frames


def parse_split_file(path: Path) -> list[tuple[str, str, str]]:
    """``(drive, camera, 10-digit frame)`` per listed frame, in file order, duplicates dropped."""
    if not path.is_file():
        raise ArgumentFileError(
            f"{{split_file}}={path}: no such file", "split_file", owner=parse_split_file
        )
    entries: dict[tuple[str, str, str], None] = {}
    for number, raw in enumerate(path.read_text().splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        entry = _parse_split_line(line)
        if entry is None:
            raise ValueError(
                f"{path}, line {number}: {raw.strip()!r}: expected '<date>/<drive> <frame> l|r' "
                "(e.g. '2011_09_26/2011_09_26_drive_0002_sync 69 l') or a relative path naming "
                "drive, camera and frame (e.g. '2011_09_26_drive_0002_sync/proj_depth/"
                "groundtruth/image_02/0000000069.png')"
            )
        entries[entry] = None
    if not entries:
        raise ArgumentError(
            f"{{split_file}}={path}: lists no frames", "split_file", owner=parse_split_file
        )
    return list(entries)


def _parse_split_line(line: str) -> tuple[str, str, str] | None:
    tokens = line.replace("\\", "/").split()
    eigen = _EIGEN_LINE.match(tokens[0])
    if eigen and len(tokens) == 3 and tokens[1].isdigit() and tokens[2] in CAMERAS:
        return eigen.group(1), CAMERAS[tokens[2]], f"{int(tokens[1]):010d}"
    path = _PATH_LINE.search(tokens[0])
    if path:
        return path.group(1), path.group(2), f"{int(path.group(3)):010d}"
    return None


def locate_listed(
    root: Path, listed: Iterable[tuple[str, str, str]], source: Path
) -> list[KittiFrame]:
    """The split file's frames in KITTI's train or val subset; all must have annotated depth."""
    frames, missing = [], []
    for drive, camera, frame in listed:
        subset = next((s for s in SUBSETS if (root / ANNOTATED / s / drive).is_dir()), None)
        found = KittiFrame(subset or SUBSETS[0], drive, camera, frame)
        if subset is None or not found.groundtruth(root).is_file():
            missing.append(found)
        else:
            frames.append(found)
    if missing:
        shown = "\n  ".join(str(f.groundtruth(root)) for f in missing[:_SHOWN])
        raise ArgumentFileError(
            f"{{split_file}}={source}: {len(missing)} of {len(missing) + len(frames)} listed "
            f"frames have no annotated depth in {root / ANNOTATED}/{{train,val}}, e.g.\n  {shown}\n"
            "(the 697-frame Eigen test list has 45 such frames; use the 652-frame list of those "
            "with annotated depth, monodepth2's splits/eigen_benchmark/test_files.txt)",
            "split_file",
            owner=locate_listed,
        )
    return frames


def check_files(frames: Sequence[KittiFrame], root: Path, raw_root: Path, split: str) -> None:
    """Every frame's ground truth, sparse input and RGB image is a file, before anything is
    prepared; the error lists a few that are not (missing, or a directory)."""
    for what, locate in (
        ("annotated depth PNG", lambda f: f.groundtruth(root)),
        ("velodyne_raw depth PNG", lambda f: f.velodyne(root)),
        ("RGB image", lambda f: f.image(root, raw_root)),
    ):
        missing = [locate(f) for f in frames if not locate(f).is_file()]
        if missing:
            shown = "\n  ".join(
                f"{p} (a directory)" if p.is_dir() else str(p) for p in missing[:_SHOWN]
            )
            raise FileNotFoundError(
                f"{split} split: {len(missing)} of {len(frames)} frames have no {what}, e.g.\n"
                f"  {shown}"
            )


# --- one frame --------------------------------------------------------------------------------


def crop_or_pad(array: np.ndarray, height: int, width: int, pad_mode: str) -> np.ndarray:
    """To ``height`` x ``width``: keep the bottom rows and the centre columns of a larger frame,
    pad a smaller one at the bottom/right (``pad_mode`` "edge" for images, "zero" for depth)."""
    h, w = array.shape[:2]
    top = max(h - height, 0)
    left = max((w - width) // 2, 0)
    array = array[top : top + height, left : left + width]
    pad = [(0, height - array.shape[0]), (0, width - array.shape[1])] + [(0, 0)] * (array.ndim - 2)
    if pad_mode == "edge":
        return np.pad(array, pad, mode="edge")
    return np.pad(array, pad, mode="constant")


def subsample(sparse: np.ndarray, points: int | None, seed: int, frame_id: str) -> np.ndarray:
    """Keep ``points`` of the measured pixels (all if fewer), the same ones every time for a
    frame: the choice is seeded by ``seed`` and a checksum of the frame id."""
    if points is None:
        return sparse
    measured = np.flatnonzero(sparse > 0)
    if len(measured) <= points:
        return sparse
    rng = np.random.default_rng([seed, zlib.crc32(frame_id.encode())])
    keep = rng.choice(measured, size=points, replace=False)
    out = np.zeros_like(sparse)
    out.flat[keep] = sparse.flat[keep]
    return out


@dataclass(frozen=True)
class FrameSettings:
    root: Path
    raw_root: Path
    height: int
    width: int
    sparse_points: int | None
    fill: str
    seed: int


def load_frame(frame: KittiFrame, settings: FrameSettings, training: bool) -> PreparedFrame:
    """Reads one frame's three files and turns them into the network's input size; a training
    frame gets its filled ground truth."""
    s = settings
    paths = {
        "image": frame.image(s.root, s.raw_root),
        "groundtruth": frame.groundtruth(s.root),
        "velodyne_raw": frame.velodyne(s.root),
    }
    for name, path in paths.items():
        if os.path.lexists(path) and not path.is_file():  # missing ones: the readers say so
            raise not_a_file(path, f"the {name} PNG file of frame {frame.id}")
    image = read_rgb(paths["image"])
    depth = read_depth_png(paths["groundtruth"])
    sparse = read_depth_png(paths["velodyne_raw"])
    for name in ("groundtruth", "velodyne_raw"):
        shape = depth.shape if name == "groundtruth" else sparse.shape
        if shape != image.shape[:2]:
            raise DataFileError(
                paths[name],
                f"{shape[0]}x{shape[1]} depth map, expected the size of its image "
                f"{paths['image']} ({image.shape[0]}x{image.shape[1]})",
            )
    # Where the full frame lies in the sample (crop_or_pad keeps the bottom rows and the centre
    # columns of a larger frame), for evaluation crops defined on the full frame.
    frame_h, frame_w = depth.shape
    frame_box = (-max(frame_h - s.height, 0), -max((frame_w - s.width) // 2, 0), frame_h, frame_w)
    # Crop first (filling then sees exactly the kept pixels), pad last (padding stays invalid).
    crop_h, crop_w = min(s.height, image.shape[0]), min(s.width, image.shape[1])
    image, depth, sparse = (crop_or_pad(a, crop_h, crop_w, "zero") for a in (image, depth, sparse))
    sparse = subsample(sparse, s.sparse_points, s.seed, frame.id)
    dense = fill_depth(depth, image, s.fill) if training and s.fill != "none" else None
    return PreparedFrame(
        image=crop_or_pad(image, s.height, s.width, "edge"),
        sparse=crop_or_pad(sparse, s.height, s.width, "zero"),
        depth=crop_or_pad(depth, s.height, s.width, "zero"),
        condition=CONDITION,
        filled=None if dense is None else crop_or_pad(dense, s.height, s.width, "zero"),
        frame_box=frame_box,
    )


# --- the dataset ------------------------------------------------------------------------------


def _whole(value: object, minimum: int) -> bool:
    """A whole number (``3`` or ``3.0``) of at least ``minimum``."""
    try:
        return int(value) == value and value >= minimum  # type: ignore[call-overload, operator]
    except (TypeError, ValueError, OverflowError):  # a list or null; a string or nan; inf
        return False


class KittiDepth(PreparedDataset):
    """One split of KITTI depth completion, prepared on first use (see the module docstring),
    served as :class:`~fusion_depth.data.Sample` dicts; ``depth`` is the filled ground truth in
    the train split when ``fill`` is set, the measured one otherwise.

    With ``on_error="raise"`` every frame's files are checked before the first is prepared. The
    arguments not described in the module docstring are
    :class:`~fusion_depth.data.base.PreparedDataset`'s.
    """

    name = "kitti"
    layout = f"the KITTI depth completion folder holding {ANNOTATED}/ and {VELODYNE}/"
    conditions_allowed = (CONDITION,)

    def __init__(
        self,
        split: str,
        root: str | os.PathLike,
        raw_root: str | os.PathLike,
        cache_root: str | os.PathLike,
        height: int = 384,
        width: int = 1248,
        sparse_points: int | None = None,
        fill: str = "none",
        split_file: str | os.PathLike | None = None,
        exclude_test_drives: bool = True,
        train_stride: int = 1,
        seed: int = 0,
        on_error: OnError = "raise",
        test_split: str = "val",
    ) -> None:
        check_size(height, width)  # before the options, as the other datasets do
        checks = (
            (
                "sparse_points",
                sparse_points,
                sparse_points is None or _whole(sparse_points, 1),
                "null (every Velodyne return) or a number of points >= 1",
            ),
            ("fill", repr(fill), fill in FILL_METHODS, f"one of {list(FILL_METHODS)}"),
            ("seed", seed, _whole(seed, 0), "a non-negative integer"),
            (
                "train_stride",
                train_stride,
                _whole(train_stride, 1),
                "an integer >= 1 (every n-th frame)",
            ),
            (
                "test_split",
                repr(test_split),
                test_split in TEST_SPLITS,
                f"one of {', '.join(TEST_SPLITS)}",
            ),
        )
        for argument, shown, ok, expected in checks:
            if not ok:
                raise ArgumentError(
                    f"{{{argument}}}={shown}: expected {expected}", argument, owner=KittiDepth
                )
        if test_split != "val" and split_file is not None:
            raise ArgumentError(
                f"{{test_split}}={test_split} and {{split_file}}={split_file} both name the "
                "test frames; give one",
                "test_split",
                "split_file",
                owner=KittiDepth,
            )
        self.test_split = test_split
        self.raw_root = Path(raw_root).expanduser().resolve()
        self.sparse_points = None if sparse_points is None else int(sparse_points)
        self.fill = fill
        self.seed = int(seed)
        self.split_path = None if split_file is None else Path(split_file).expanduser().resolve()
        self.exclude_test_drives = bool(exclude_test_drives)
        self.train_stride = int(train_stride)
        super().__init__(split, root, cache_root, height, width, on_error)

    def resolve_root(self, root: str | os.PathLike) -> Path:
        path = Path(root).expanduser().resolve()
        check_layout(path, self.raw_root)
        return path

    def read_only(self) -> dict[str, Path]:
        return {"root": self.root, "raw_root": self.raw_root}

    def list_frames(self) -> FrameList:
        frames = split_frames(
            self.root,
            self.split_path,
            self.exclude_test_drives,
            self.train_stride,
            self.test_split,
        )
        by_id = {name: {f.id: f for f in split} for name, split in frames.items()}
        return FrameList(by_id, _digest(frames))

    def cache_key(self, listed: FrameList) -> dict:
        return {
            "kitti_version": KITTI_VERSION,
            "root": str(self.root),
            "raw_root": str(self.raw_root),
            "height": self.height,
            "width": self.width,
            "sparse_points": self.sparse_points,
            "fill": self.fill,
            "seed": self.seed,
            "split_file": None if self.split_path is None else str(self.split_path),
            "exclude_test_drives": self.exclude_test_drives,
            "train_stride": self.train_stride,
            **({"test_split": self.test_split} if self.test_split != "val" else {}),
            "frames": listed.files,
        }

    def split_folder(self, split: str) -> str:
        # Without a split file or the selected set, the test split is the val split: the same
        # frames, prepared once.
        same = split == "test" and self.split_path is None and self.test_split == "val"
        return "val" if same else split

    def check_frames(self, split: str, frames: dict[str, KittiFrame]) -> None:
        check_files(list(frames.values()), self.root, self.raw_root, split)

    def frame_files(self, split: str, frame: KittiFrame) -> list[Path]:
        return [
            frame.image(self.root, self.raw_root),
            frame.groundtruth(self.root),
            frame.velodyne(self.root),
        ]

    def load_frame(self, split: str, frame: KittiFrame) -> PreparedFrame:
        settings = FrameSettings(
            self.root,
            self.raw_root,
            self.height,
            self.width,
            self.sparse_points,
            self.fill,
            self.seed,
        )
        return load_frame(frame, settings, training=split == "train")

    def serves_filled(self) -> bool:
        return self.split == "train" and self.fill != "none"


def split_frames(
    root: Path,
    split_file: Path | None,
    exclude_test_drives: bool = True,
    train_stride: int = 1,
    test_split: str = "val",
) -> dict[str, list[KittiFrame]]:
    """The frames of every split (see the module docstring for what each one holds)."""
    train, val = (list_subset(root, subset) for subset in SUBSETS)
    train = [
        frame
        for _, sequence in groupby(train, key=lambda f: (f.drive, f.camera))
        for frame in list(sequence)[::train_stride]
    ]
    if test_split == SELECTION:
        # The selected frames are KITTI val frames: no train drive is among them.
        return {"train": train, "val": val, "test": list_selection(root)}
    if split_file is None:
        return {"train": train, "val": val, "test": val}
    test = locate_listed(root, parse_split_file(split_file), split_file)
    if exclude_test_drives:
        drives = {f.drive for f in test}
        kept = [f for f in train if f.drive not in drives]
        if not kept:
            raise ArgumentError(
                f"train split: every drive of {root / ANNOTATED / 'train'} is a test drive of "
                f"{{split_file}}={split_file}, nothing is left to train on (set "
                "{exclude_test_drives}=false to keep them)",
                "split_file",
                "exclude_test_drives",
                owner=split_frames,
            )
        log.info(
            "kitti: %d train frames of %d test drives left out (exclude_test_drives)",
            len(train) - len(kept),
            len(drives),
        )
        train = kept
    return {"train": train, "val": val, "test": test}


def _digest(frames: dict[str, list[KittiFrame]]) -> str:
    """A checksum of every split's frame list: new or removed files give a new cache."""
    text = json.dumps({name: [f.id for f in split] for name, split in frames.items()})
    return hashlib.sha256(text.encode()).hexdigest()[:16]
