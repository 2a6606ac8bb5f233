"""Reading and writing the image and depth files every dataset shares.

Depth maps on disk follow KITTI's convention: single-channel uint16 PNG holding metres × 256
(3.9 mm steps, up to 255.99 m), 0 meaning "no measurement". Every reader raises an error that
names the file and what was expected, so a corrupt frame is never turned into a black image;
every writer goes through a temporary sibling and a rename, so a reader never sees half a file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from fusion_depth.runs import write_atomic

DEPTH_PNG_SCALE = 256.0
_UINT16_MAX = np.iinfo(np.uint16).max


def _open(path: str | os.PathLike, what: str) -> Image.Image:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing {what}")
    try:
        image = Image.open(path)
        image.load()  # decode now, so truncated files fail here and not in a worker later
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
        raise ValueError(f"{path}: unreadable {what} ({err})") from err
    return image


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """An image file as uint8 (H, W, 3) RGB."""
    return np.asarray(_open(path, "image").convert("RGB"))


def read_depth_png(path: str | os.PathLike, scale: float = DEPTH_PNG_SCALE) -> np.ndarray:
    """A uint16 depth PNG as float32 (H, W) metres (``value / scale``; 0 stays 0 = invalid)."""
    image = _open(path, "depth PNG")
    array = np.asarray(image)
    if array.ndim != 2 or array.dtype.kind not in "iu" or image.mode not in ("I", "I;16", "I;16B"):
        raise ValueError(
            f"{Path(path)}: expected a single-channel 16-bit depth PNG, got mode {image.mode!r} "
            f"with shape {array.shape}"
        )
    return (array.astype(np.float32) / scale).astype(np.float32)


def encode_depth(depth: np.ndarray, scale: float = DEPTH_PNG_SCALE) -> np.ndarray:
    """Metres to uint16 ``round(depth * scale)``; non-finite or negative values become 0."""
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    return np.clip(np.round(depth * scale), 0, _UINT16_MAX).astype(np.uint16)


def _save_atomic(image: Image.Image, path: Path) -> None:
    write_atomic(path, lambda tmp: image.save(tmp, format="PNG"))


def write_depth_png(
    path: str | os.PathLike, depth: np.ndarray, scale: float = DEPTH_PNG_SCALE
) -> None:
    """Float (H, W) metres to a uint16 PNG, written atomically."""
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"{path}: expected a (H, W) depth map, got shape {depth.shape}")
    _save_atomic(Image.fromarray(encode_depth(depth, scale)), Path(path))


def write_rgb_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """uint8 (H, W, 3) to an RGB PNG, written atomically."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(
            f"{path}: expected a uint8 (H, W, 3) image, got {image.dtype} {image.shape}"
        )
    _save_atomic(Image.fromarray(image, "RGB"), Path(path))
