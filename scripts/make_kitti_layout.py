"""A KITTI depth-completion layout of generated 375x1242 frames, for timing ``prepare``.

2 train drives x 2 cameras x 4 frames (16 train frames) and 1 val drive x 2 cameras x 2 frames,
drawn by the built-in generator; the lidar map serves as both ground truth and Velodyne input.
Run from the repository root: ``python scripts/make_kitti_layout.py
OUT [N [DENSITY]]``, N train frames per drive and camera (default 4). With DENSITY (e.g. 0.07),
the ground truth is instead the frame's exact depth at that share of the pixels below the top
third, drawn at random (4-5 % of the frame at 0.07, as one real Velodyne scan projected into a
KITTI frame), and the Velodyne input a fifth of those: the 24-frame benchmark of the prepare
page is ``OUT 6 0.07``.
"""

import sys
from pathlib import Path

import numpy as np
from PIL import Image

from fusion_depth.data.procedural import render_frame

DRIVES = {
    "train": ["2011_09_26_drive_0001_sync", "2011_09_28_drive_0002_sync"],
    "val": ["2011_09_26_drive_0002_sync"],
}


def save_depth(path: Path, metres: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.round(metres * 256).astype(np.uint16)).save(path)


def main(out: Path, per_camera: int = 4, density: float | None = None) -> None:
    root, raw, k = out / "kitti_depth", out / "kitti_raw", 0
    rng = np.random.default_rng(0)
    for subset, drives in DRIVES.items():
        for drive in drives:
            for camera in ("image_02", "image_03"):
                for frame in range(per_camera if subset == "train" else 2):
                    image, depth, lidar = render_frame(
                        11, "train", k, 375, 1242, 82.0, "day", "lidar"
                    )
                    k += 1
                    velodyne_depth = lidar
                    if density is not None:
                        below = np.arange(375)[:, None] >= 125
                        keep = below & (rng.random(depth.shape) < density) & (depth < 80)
                        lidar = np.where(keep, depth, 0.0)
                        velodyne_depth = np.where(rng.random(depth.shape) < 0.2, lidar, 0.0)
                    name = f"{frame:010d}.png"
                    proj = Path(subset, drive, "proj_depth")
                    annotated = root / "data_depth_annotated" / proj / "groundtruth" / camera
                    velodyne = root / "data_depth_velodyne" / proj / "velodyne_raw" / camera
                    save_depth(annotated / name, lidar)
                    save_depth(velodyne / name, velodyne_depth)
                    rgb = raw / drive[:10] / drive / camera / "data" / name
                    rgb.parent.mkdir(parents=True, exist_ok=True)
                    Image.fromarray(image).save(rgb)
    print(k, "frames")


if __name__ == "__main__":
    main(
        Path(sys.argv[1]),
        *(int(n) for n in sys.argv[2:3]),
        *(float(d) for d in sys.argv[3:4]),
    )
