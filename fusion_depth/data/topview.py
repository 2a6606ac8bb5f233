"""``dataset=topview``: top-view images from a crane's boom camera with depth exported from
Unreal Engine (the paper's Top-View set). Camera only: ``sparse`` is all zeros, and the dataset
config allows ``fusion=rgb`` alone (``dataset.fusions``).

Folder format
-------------
::

    <root>/
      train/  val/  test/          the three splits, each laid out as
        rgb/<name>.png|.jpg|.jpeg  the camera image (RGB; alpha ignored)
        depth/<name>.png|.npy      its depth map, pixel-aligned, same size, matched by name

* **16-bit PNG** (single channel): metres = value x ``depth_unit``. Unreal's native unit is the
  centimetre, hence the default ``depth_unit: 0.01`` (1 cm steps, up to 655 m).
* **NPY**: a (H, W) (or (H, W, 1)) float or integer array; metres = value x ``depth_unit``, so
  set ``depth_unit: 1.0`` for maps saved in metres.
* **EXR** is not read: no EXR reader is among the dependencies (OpenEXR/imageio are not
  installed), and a ``.exr`` depth file fails naming the file; convert it to NPY (float) or
  16-bit PNG first.

Zero, negative or non-finite depths (and NPY values too large for a float32) are invalid, and so
is anything at or beyond ``max_range`` (default 250 m: the cache stores 1/256 m in uint16). Every
frame gets the condition ``condition`` (default ``day``: the renders are daylight scenes). Files
starting with ``.`` are ignored; a depth map in two formats is an error naming the files.
A corrupt or truncated file, a depth PNG that is not 16-bit single-channel, an NPY that is not a
numeric (H, W) array, or a depth map of another size than its image is a
:class:`~fusion_depth.data.depth_io.DataFileError` naming the file.

Broken frames. Every name in ``rgb/`` is a frame, whatever stands there, so nothing is dropped
quietly. An image without a depth map is a FileNotFoundError; a directory (or a dangling link)
where a frame's image or depth map should be is an IsADirectoryError (FileNotFoundError); each
names the path and what was expected. These are found while listing the folder, so for training
(``on_error="raise"``) the first one fails before anything is prepared; ``python -m
fusion_depth.prepare`` (``on_error="skip"``) counts such a frame as skipped, like one whose file
is corrupt, and prepares the others (:mod:`fusion_depth.data.cache`). Depth maps without an
image are ignored with a warning.

Preparing
---------
As :mod:`fusion_depth.data.carla`: every split is prepared once into the shared cache
(:mod:`fusion_depth.data.cache`) under ``<cache_root>/topview/<hash>/`` at ``height x width``,
the image resized bilinearly (area averaging when shrinking), the depth sampled at the nearest
source pixel so every value is one Unreal rendered. The hash covers the settings and every file's
name, size and modification time. The first split built prepares all three, so a bad file
anywhere fails before training; the dataset folder is only ever read.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion_depth.data import CONDITIONS, SPLITS
from fusion_depth.data.base import FrameList, PreparedDataset
from fusion_depth.data.cache import OnError, PreparedFrame, check_on_error, not_a_file
from fusion_depth.data.depth_io import DataFileError, read_depth_png, read_rgb
from fusion_depth.data.folders import (
    check_max_range,
    entries_not_files,
    fingerprint,
    list_files,
    require_dir,
    resize_depth_nearest,
    resize_rgb,
)
from fusion_depth.errors import ArgumentError

FORMAT_VERSION = 1  # bump when decoding changes, so old caches are not reused
RGB_SUFFIXES = (".png", ".jpg", ".jpeg")
DEPTH_SUFFIXES = (".png", ".npy", ".exr")
_FLOAT32_MAX = float(np.finfo(np.float32).max)
LAYOUT = "a Top-View dataset laid out as <root>/{train,val,test}/{rgb,depth}/<name>.*"

log = logging.getLogger(__name__)


def read_depth_file(path: str | os.PathLike, depth_unit: float) -> np.ndarray:
    """A depth map (16-bit PNG or NPY) as float32 (H, W) metres; invalid values (zero,
    negative, NaN, inf, beyond float32) become 0, so the result is finite and >= 0.

    A missing file raises FileNotFoundError; an unsupported, corrupt or truncated one, or an NPY
    that is not a non-empty numeric (H, W) or (H, W, 1) array, raises DataFileError naming it.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        raise DataFileError(
            path,
            "EXR depth maps are not supported (no EXR reader is installed); export or convert "
            "them to .npy (float array, metres = value x the reader's depth_unit) or 16-bit PNG",
        )
    if suffix == ".png":
        depth = read_depth_png(path, scale=1.0).astype(np.float64) * depth_unit
    elif suffix == ".npy":
        depth = _read_npy(path).astype(np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            depth *= depth_unit
    else:
        raise DataFileError(path, f"expected a depth map ending in {', '.join(DEPTH_SUFFIXES)}")
    valid = np.isfinite(depth) & (depth > 0) & (depth <= _FLOAT32_MAX)
    return np.where(valid, depth, 0.0).astype(np.float32)


def _read_npy(path: Path) -> np.ndarray:
    """The (H, W) array of an NPY file. Its header is checked first, against the file's size (by
    a memory map that is never read): a header promising more data than the file holds fails
    without allocating it; pickled objects are refused."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing depth map")
    expected = "a non-empty (H, W) numeric depth array saved with numpy.save"
    try:
        header = np.load(path, mmap_mode="r", allow_pickle=False)
        if not isinstance(header, np.ndarray):  # a .npz archive under a .npy name
            header.close()
            raise DataFileError(path, f"a {type(header).__name__}, expected {expected}")
        shape, dtype = header.shape, header.dtype
        del header
        if len(shape) == 3 and shape[2] == 1:
            shape = shape[:2]
        if len(shape) != 2 or dtype.kind not in "fiu" or 0 in shape:
            raise DataFileError(path, f"expected {expected}, got {dtype} {shape}")
        return np.load(path, allow_pickle=False).reshape(shape)
    except DataFileError:
        raise
    except Exception as err:  # numpy raises ValueError, OSError, EOFError, ... for bad bytes
        raise DataFileError(
            path, f"unreadable NPY depth map ({type(err).__name__}: {err}); expected {expected}"
        ) from err


@dataclass(frozen=True)
class TopViewFrame:
    """One frame's files; ``problem`` is what the scan found wrong with them (None: nothing)."""

    id: str  # "<split>/<name>"
    rgb: Path
    depth: Path | None
    problem: OSError | None = None


def scan_folder(root: Path, on_error: OnError = "raise") -> FrameList:
    """Every split's frames (image and depth matched by name) and a fingerprint of the files.

    A frame's breakage (module docstring, "Broken frames") raises here with ``on_error="raise"``;
    with ``"skip"`` the frame is kept with its ``problem``, which :func:`load_frame` raises, so
    ``prepare_split`` skips it by id. A missing folder, a split without images, or two files for
    one name concern the whole split and always raise.
    """
    check_on_error(on_error)
    frames: dict[str, dict[str, TopViewFrame]] = {}
    entries: list[os.DirEntry] = []
    for split in SPLITS:
        split_dir = require_dir(root / split, f"the {split} split of {LAYOUT}")
        rgb_dir = require_dir(split_dir / "rgb", f"the camera images {split_dir}/rgb/<name>.png")
        depth_dir = require_dir(split_dir / "depth", f"the depth maps {split_dir}/depth/<name>.*")
        images = list_files(rgb_dir, RGB_SUFFIXES)
        depths = list_files(depth_dir, DEPTH_SUFFIXES)
        not_images = entries_not_files(rgb_dir, RGB_SUFFIXES)
        not_depths = entries_not_files(depth_dir, DEPTH_SUFFIXES)
        if not images and not not_images:
            raise ValueError(
                f"{rgb_dir}: no images, the {split} split is empty; expected "
                f"<name>{'|'.join(RGB_SUFFIXES)} files"
            )
        kept = []
        for name in sorted(set(images) | set(not_images)):
            frame_id = f"{split}/{name}"
            problem: OSError | None = None
            if name in not_images:
                image = not_images[name]
                problem = not_a_file(image, f"the camera image file of frame {frame_id}")
            else:
                image = Path(images[name].path)
                if name in not_depths:
                    problem = not_a_file(not_depths[name], f"the depth map file of {image}")
                elif name not in depths:
                    problem = FileNotFoundError(
                        f"{depth_dir / name}.png: missing depth map of {image} (expected "
                        f"{name} with one of {', '.join(DEPTH_SUFFIXES)} in {depth_dir})"
                    )
            if problem is not None and on_error == "raise":
                raise problem
            entries += [e for e in (images.get(name), depths.get(name)) if e is not None]
            depth = Path(depths[name].path) if name in depths and problem is None else None
            kept.append(TopViewFrame(frame_id, image, depth, problem))
        orphans = sorted(set(depths) - set(images) - set(not_images))
        if orphans:
            log.warning(
                "topview %s: %d depth maps without an image are ignored (e.g. %s)",
                split,
                len(orphans),
                orphans[0],
            )
        frames[split] = {frame.id: frame for frame in kept}
    return FrameList(frames, fingerprint(entries))


def load_frame(
    frame: TopViewFrame,
    height: int,
    width: int,
    depth_unit: float,
    max_range: float,
    condition: str,
) -> PreparedFrame:
    """Reads and resizes one image and its depth map; the sparse input is empty.

    Raises the frame's ``problem`` when the scan found one, else what the readers raise for a
    bad file (DataFileError, FileNotFoundError), naming it.
    """
    if frame.problem is not None:
        raise frame.problem
    assert frame.depth is not None  # the scan sets it for every frame without a problem
    image = read_rgb(frame.rgb)
    depth = read_depth_file(frame.depth, depth_unit)
    if depth.shape != image.shape[:2]:
        raise DataFileError(
            frame.depth,
            f"depth map is {depth.shape[1]}x{depth.shape[0]}, expected the image's "
            f"{image.shape[1]}x{image.shape[0]} ({frame.rgb})",
        )
    depth = np.where(depth < max_range, depth, 0.0).astype(np.float32)
    return PreparedFrame(
        image=resize_rgb(image, height, width),
        sparse=np.zeros((height, width), np.float32),
        depth=resize_depth_nearest(depth, height, width),
        condition=condition,
    )


class TopViewDepth(PreparedDataset):
    """One split of a Top-View folder (format: the module docstring), served from the prepared
    cache as :class:`~fusion_depth.data.Sample` dicts with an all-zero ``sparse``.

    ``depth_unit`` is metres per stored unit, ``condition`` the one every frame gets, and
    ``max_range`` the metres at and beyond which depth is invalid; the other arguments are
    :class:`~fusion_depth.data.base.PreparedDataset`'s.
    """

    name = "topview"
    layout = LAYOUT
    format_version = FORMAT_VERSION

    def __init__(
        self,
        split: str,
        root: str | os.PathLike,
        cache_root: str | os.PathLike,
        height: int = 480,
        width: int = 640,
        depth_unit: float = 0.01,
        condition: str = "day",
        max_range: float = 250.0,
        on_error: OnError = "raise",
    ) -> None:
        if not depth_unit > 0:
            raise ArgumentError(
                f"{{depth_unit}}={depth_unit}: expected metres per stored unit > 0 "
                "(0.01 for Unreal's centimetres, 1.0 for metres)",
                "depth_unit",
                owner=TopViewDepth,
            )
        if condition not in CONDITIONS:
            raise ArgumentError(
                f"{{condition}}={condition!r}: expected one of {list(CONDITIONS)}",
                "condition",
                owner=TopViewDepth,
            )
        self.depth_unit = float(depth_unit)
        self.condition = condition
        self.max_range = check_max_range(max_range)
        super().__init__(split, root, cache_root, height, width, on_error)

    def list_frames(self) -> FrameList:
        return scan_folder(self.root, self.on_error)

    def settings(self) -> dict:
        return {
            "depth_unit": self.depth_unit,
            "condition": self.condition,
            "max_range": self.max_range,
        }

    def frame_files(self, split: str, frame: TopViewFrame) -> list[Path]:
        return [frame.rgb] if frame.depth is None else [frame.rgb, frame.depth]

    def load_frame(self, split: str, frame: TopViewFrame) -> PreparedFrame:
        return load_frame(
            frame, self.height, self.width, self.depth_unit, self.max_range, self.condition
        )
