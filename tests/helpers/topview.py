"""A Top-View folder of images and depth files (PNG and JPEG; 16-bit PNG and float NPY depth),
for ``test_topview`` and ``test_fuzz_readers``."""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
from PIL import Image

CACHE_STEP = 1 / 256  # the prepared cache stores depth in 1/256 m
H, W = 64, 96
SPLIT_FRAMES = {"train": ["a00", "a01", "a02", "a03"], "val": ["b00", "b01"], "test": ["c00"]}


def crane_depth_cm(seed: int) -> np.ndarray:
    """Ground 30-45 m below the boom and a load hanging 6-8 m below it, in centimetres."""
    rng = np.random.default_rng(seed)
    depth = 3000.0 + np.add.outer(np.arange(H) * 12.0, np.arange(W) * 7.0) + rng.uniform(0, 50)
    depth[20:30, 40:52] = 600.0 + rng.uniform(0, 200)
    return depth


def write_folder(root: Path) -> Path:
    """Images as PNG and JPEG; depth as 16-bit PNG (cm) and float NPY (cm), matched by name."""
    for split, names in SPLIT_FRAMES.items():
        (root / split / "rgb").mkdir(parents=True)
        (root / split / "depth").mkdir(parents=True)
        for i, name in enumerate(names):
            seed = zlib.crc32(name.encode()) % 1000
            rgb = np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)
            depth = crane_depth_cm(seed)
            if i % 2 == 0:
                Image.fromarray(rgb).save(root / split / "rgb" / f"{name}.png")
                Image.fromarray(np.round(depth).astype(np.uint16)).save(
                    root / split / "depth" / f"{name}.png"
                )
            else:
                Image.fromarray(rgb).save(root / split / "rgb" / f"{name}.jpg", quality=95)
                np.save(root / split / "depth" / f"{name}.npy", depth.astype(np.float32))
    return root
