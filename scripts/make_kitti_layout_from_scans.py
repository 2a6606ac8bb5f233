"""A KITTI depth-completion layout of real frames: Velodyne scans projected into their images.

SRC is a folder in the layout of KITTI's object-detection set (``image_2/NNNNNN.png``,
``velodyne/NNNNNN.bin``, ``calib/NNNNNN.txt``: any KITTI frame with its scan and calibration).
Each scan is projected into its left colour image through the frame's own calibration
(``P2 · R0_rect · Tr_velo_to_cam``, the object devkit's ``readme.txt``), the nearest return kept
where two land on one pixel, and written as both the ground truth and the Velodyne input of a
depth-completion layout, as ``scripts/make_kitti_layout.py`` writes generated frames: 2 train
drives x 2 cameras x N frames and 1 val drive x 2 cameras x 2 frames, taking the frames of SRC
whose image is 375x1242 in turn. Run from the repository root: ``python
scripts/make_kitti_layout_from_scans.py SRC OUT [N]`` (N defaults to 6: 24 train frames, the
prepare page's benchmark).
"""

import sys
from pathlib import Path

import numpy as np
from make_kitti_layout import DRIVES, save_depth
from PIL import Image

SIZE = (375, 1242)  # (height, width): the KITTI frames the benchmark is about


def read_calibration(path: Path) -> dict[str, np.ndarray]:
    """The matrices of a KITTI object ``calib/*.txt``, by name (``P2`` 3x4, ``R0_rect`` 3x3,
    ``Tr_velo_to_cam`` 3x4)."""
    matrices = {}
    for line in path.read_text().splitlines():
        name, _, values = line.partition(":")
        if values.strip():
            matrices[name] = np.array(values.split(), dtype=np.float64)
    return {
        "P2": matrices["P2"].reshape(3, 4),
        "R0_rect": matrices["R0_rect"].reshape(3, 3),
        "Tr_velo_to_cam": matrices["Tr_velo_to_cam"].reshape(3, 4),
    }


def project_scan(scan: Path, calib: Path, size: tuple[int, int]) -> np.ndarray:
    """float (H, W) metres along the camera axis, 0 where no return landed; the nearest return
    where several land on one pixel."""
    points = np.fromfile(scan, dtype=np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
    m = read_calibration(calib)
    camera = m["R0_rect"] @ (m["Tr_velo_to_cam"] @ np.c_[points, np.ones(len(points))].T)
    pixels = m["P2"] @ np.r_[camera, np.ones((1, camera.shape[1]))]
    depth = pixels[2]
    ahead = depth > 0.1
    u = np.round(pixels[0, ahead] / depth[ahead]).astype(int)
    v = np.round(pixels[1, ahead] / depth[ahead]).astype(int)
    depth = depth[ahead]
    height, width = size
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v, depth = u[inside], v[inside], depth[inside]
    order = np.argsort(-depth)  # the farthest first, so the nearest is written last
    out = np.zeros(size)
    out[v[order], u[order]] = depth[order]
    return out


def main(src: Path, out: Path, per_camera: int = 6) -> None:
    frames = [
        name.stem
        for name in sorted((src / "image_2").glob("*.png"))
        if Image.open(name).size[::-1] == SIZE
    ]
    if not frames:
        raise SystemExit(f"{src / 'image_2'}: no {SIZE[0]}x{SIZE[1]} image")
    maps = {
        stem: project_scan(src / "velodyne" / f"{stem}.bin", src / "calib" / f"{stem}.txt", SIZE)
        for stem in frames
    }
    root, raw, k = out / "kitti_depth", out / "kitti_raw", 0
    for subset, drives in DRIVES.items():
        for drive in drives:
            for camera in ("image_02", "image_03"):
                for frame in range(per_camera if subset == "train" else 2):
                    stem = frames[k % len(frames)]
                    k += 1
                    name = f"{frame:010d}.png"
                    proj = Path(subset, drive, "proj_depth")
                    annotated = root / "data_depth_annotated" / proj / "groundtruth" / camera
                    velodyne = root / "data_depth_velodyne" / proj / "velodyne_raw" / camera
                    save_depth(annotated / name, maps[stem])
                    save_depth(velodyne / name, maps[stem])
                    rgb = raw / drive[:10] / drive / camera / "data" / name
                    rgb.parent.mkdir(parents=True, exist_ok=True)
                    Image.open(src / "image_2" / f"{stem}.png").convert("RGB").save(rgb)
    measured = np.mean([np.count_nonzero(m) / m.size for m in maps.values()])
    print(k, "frames from", len(frames), f"scans ({measured:.1%} of the pixels measured)")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), *(int(n) for n in sys.argv[3:4]))
