"""scripts/make_kitti_layout_from_scans.py: real KITTI scans projected into a layout the KITTI
reader prepares (the prepare page's real-frame benchmarks)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
from PIL import Image

from fusion_depth.data.kitti import KittiDepth

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
F, CX, CY = 700.0, 600.5, 180.25  # focal length and principal point, pixels


def _script(monkeypatch):
    monkeypatch.syspath_prepend(str(SCRIPTS))  # it imports make_kitti_layout beside it
    spec = importlib.util.spec_from_file_location(
        "make_kitti_layout_from_scans", SCRIPTS / "make_kitti_layout_from_scans.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _object_folder(root: Path) -> Path:
    """One frame in KITTI's object layout: Velodyne x forward, y left, z up; the camera z
    forward, x right, y down; rectification the identity."""
    for name in ("image_2", "velodyne", "calib"):
        (root / name).mkdir(parents=True)
    Image.fromarray(np.full((375, 1242, 3), 90, np.uint8)).save(root / "image_2" / "000007.png")
    Image.fromarray(np.zeros((370, 1224, 3), np.uint8)).save(root / "image_2" / "000008.png")
    points = [
        (10.0, 0.0, 0.0, 0.5),  # straight ahead: the principal point, 10 m
        (20.0, 0.0, 0.0, 0.5),  # behind it on the same pixel: hidden
        (-5.0, 0.0, 0.0, 0.5),  # behind the camera: dropped
        (8.0, -2.0, -1.0, 0.5),  # right and below: x = 2 m, y = 1 m at 8 m
        (5.0, 40.0, 0.0, 0.5),  # far outside the image on the left: dropped
    ]
    np.array(points, np.float32).tofile(root / "velodyne" / "000007.bin")
    p2 = [F, 0, CX, 0, 0, F, CY, 0, 0, 0, 1, 0]
    velo_to_cam = [0, -1, 0, 0, 0, 0, -1, 0, 1, 0, 0, 0]
    (root / "calib" / "000007.txt").write_text(
        f"P2: {' '.join(map(str, p2))}\nR0_rect: 1 0 0 0 1 0 0 0 1\n"
        f"Tr_velo_to_cam: {' '.join(map(str, velo_to_cam))}\n"
    )
    return root


def test_a_scan_lands_on_its_pixels_nearest_first(tmp_path, monkeypatch) -> None:
    script = _script(monkeypatch)
    src = _object_folder(tmp_path / "object")
    depth = script.project_scan(
        src / "velodyne" / "000007.bin", src / "calib" / "000007.txt", (375, 1242)
    )
    assert depth[round(CY), round(CX)] == 10.0
    assert depth[round(CY + F / 8), round(CX + 2 * F / 8)] == 8.0
    assert np.count_nonzero(depth) == 2


def test_the_layout_is_one_the_kitti_reader_prepares(tmp_path, monkeypatch) -> None:
    script = _script(monkeypatch)
    src = _object_folder(tmp_path / "object")
    script.main(src, tmp_path / "layout", 1)  # only the 375x1242 frame is taken
    ground_truth = sorted((tmp_path / "layout").rglob("groundtruth/image_0*/*.png"))
    assert len(ground_truth) == 2 * 2 * 1 + 2 * 2  # train drives x cameras x 1, val 2 x 2
    metres = np.asarray(Image.open(ground_truth[0]), np.float64) / 256
    assert metres[round(CY), round(CX)] == 10.0
    data = KittiDepth(
        "train",
        tmp_path / "layout" / "kitti_depth",
        tmp_path / "layout" / "kitti_raw",
        tmp_path / "cache",
        height=96,
        width=320,
    )
    assert len(data) == 4
