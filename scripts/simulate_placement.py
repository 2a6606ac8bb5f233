"""How much point placement and scoring resolution move nuScenes numbers: a ray-cast simulation.

Street scenes (a road, two facades, parked and passing cars, poles) seen by a nuScenes-like
front camera (1600x900, ``CAM_FRONT``'s intrinsics) and a 32-beam lidar sweep (HDL-32E
elevations, 1,085 azimuth steps) mounted 0.3 m above and 0.5 m behind it, ray-cast exactly. The
"network" predicts at 448x800 (the scene's depth, blurred and off by a smooth ~7 % error, area-
averaged to half resolution and cropped as the nuScenes reader crops). That one prediction is
scored under ``eval=radarnet``'s formulas four ways:

* ``old``: ground truth projected at 448x800 with the placement before 0.3.0 (``floor`` of the
  devkit's coordinates scaled as pixel corners: half a full-resolution pixel up and left);
* ``network``: projected at 448x800 with the field's placement (``eval.resolution=network``);
* ``full``: RadarNet's ground truth at 900x1600, kept as points, the output read there
  (``eval.resolution=full``, what ``eval=radarnet`` does now);
* ``radarnet``: RadarNet's own steps, a numpy copy: its ground-truth map (``np.round``, the last
  point written winning, a uint16 PNG's 1/256 m), the output upsampled to 900x1600 (the 4 cut
  rows replicated), ``eval_utils.py``'s MAE and RMSE per image, then the mean.

Run from the repository root::

    python scripts/simulate_placement.py --frames 40 \
        --record results/records/placement/simulation.json

It also measures ``kitti_dc``'s PNG reading and ``densedepth``'s mirrored border on the same
frames. ``--from-record FILE`` prints the tables of a saved record without simulating again
(the results page's tables are that output).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from fusion_depth.data.nuscenes import full_resolution_points, resize_geometry, splat_nearest
from fusion_depth.data.radar_points import in_image
from fusion_depth.metrics.depth import DepthMetrics
from fusion_depth.models.inference import depth_at_points
from fusion_depth.utils.tables import format_table

FULL = (900, 1600)
SIZE = (448, 800)  # the nuScenes reader's default
K = np.array([[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]])  # CAM_FRONT's
CAPS = (50.0, 70.0, 80.0)
LIDAR_ELEVATIONS = np.linspace(10.67, -30.67, 32)  # degrees, HDL-32E
LIDAR_AZIMUTHS = 1085
LIDAR_OFFSET = np.array([0.0, -0.3, -0.5])  # camera frame (x right, y down, z forward), metres
CAMERA_HEIGHT = 1.5
SKY = 300.0
PIPELINES = ("old", "network", "full", "radarnet")


def _boxes(rng: np.random.Generator) -> np.ndarray:
    """(N, 6) axis-aligned boxes ``x0, x1, y0, y1, z0, z1`` in the camera frame (y down)."""
    boxes = []
    for side in (-1, 1):  # facades along the street, with gaps between buildings
        offset = rng.uniform(7.0, 12.0)
        z = 3.0
        while z < 200:
            length = rng.uniform(10, 40)
            height = rng.uniform(6, 25)
            x0 = side * offset if side > 0 else -offset - 20
            boxes.append([x0, x0 + 20, CAMERA_HEIGHT - height, CAMERA_HEIGHT, z, z + length])
            z += length + rng.uniform(0, 8)
    for _ in range(rng.integers(6, 14)):  # cars, parked and in lanes
        x = rng.choice([-5.5, -2.0, 1.8, 5.0]) + rng.uniform(-0.4, 0.4)
        z = rng.uniform(5, 70)
        w, h, length = rng.uniform(1.7, 2.0), rng.uniform(1.4, 1.9), rng.uniform(3.8, 4.8)
        boxes.append([x - w / 2, x + w / 2, CAMERA_HEIGHT - h, CAMERA_HEIGHT - 0.2, z, z + length])
    for _ in range(rng.integers(4, 10)):  # poles
        x, z = rng.choice([-1, 1]) * rng.uniform(4.5, 6.5), rng.uniform(4, 80)
        boxes.append([x - 0.1, x + 0.1, CAMERA_HEIGHT - 6, CAMERA_HEIGHT, z - 0.1, z + 0.1])
    return np.array(boxes)


def _hit(origin: np.ndarray, rays: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Distance along each unit ray (M, 3) from ``origin`` to the first surface: the road
    (y = camera height) or a box; ``inf`` where nothing is hit."""
    t = np.full(len(rays), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        road = (CAMERA_HEIGHT - origin[1]) / rays[:, 1]
        t = np.where((rays[:, 1] > 1e-9) & (road > 0), road, t)
        inverse = 1.0 / rays
        for x0, x1, y0, y1, z0, z1 in boxes:
            near = np.full(len(rays), -np.inf)
            far = np.full(len(rays), np.inf)
            for axis, lo, hi in ((0, x0, x1), (1, y0, y1), (2, z0, z1)):
                a = (lo - origin[axis]) * inverse[:, axis]
                b = (hi - origin[axis]) * inverse[:, axis]
                near = np.maximum(near, np.minimum(a, b))
                far = np.minimum(far, np.maximum(a, b))
            entered = (near <= far) & (far > 0) & (near > 0)
            t = np.where(entered & (near < t), near, t)
    return t


def render(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One scene: the true depth (camera z, metres) at every full-resolution pixel centre, and
    the lidar sweep's hits as camera-frame points (3, N), in scan order."""
    boxes = _boxes(rng)
    v, u = np.mgrid[0 : FULL[0], 0 : FULL[1]].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    rays = rays.reshape(-1, 3)
    norm = np.linalg.norm(rays, axis=1)
    t = _hit(np.zeros(3), rays / norm[:, None], boxes)
    depth = np.where(np.isfinite(t), t / norm, SKY).reshape(FULL)
    elevation = np.radians(LIDAR_ELEVATIONS)[:, None]
    azimuth = np.linspace(-np.pi, np.pi, LIDAR_AZIMUTHS, endpoint=False)[None, :]
    azimuth = azimuth + rng.uniform(0, 2 * np.pi / LIDAR_AZIMUTHS)
    beams = np.stack(
        [
            np.cos(elevation) * np.sin(azimuth),
            -np.sin(elevation) * np.ones_like(azimuth),
            np.cos(elevation) * np.cos(azimuth),
        ],
        -1,
    ).reshape(-1, 3)
    hits = _hit(LIDAR_OFFSET, beams, boxes)
    keep = np.isfinite(hits) & (hits < 100.0)
    points = LIDAR_OFFSET + beams[keep] * hits[keep, None]
    points += rng.normal(0, 0.02, points.shape)  # range noise, 2 cm
    return depth, points.T


def predict(depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The network's 448x800 output: the true depth blurred (2 px), times a smooth error field of
    ~7 % (a Gaussian field, 40 px correlation), area-averaged to half resolution, the rows the
    reader crops cut."""
    noise = ndimage.gaussian_filter(rng.normal(0, 1, FULL), 40)
    noise *= 0.07 / noise.std()
    full = ndimage.gaussian_filter(np.minimum(depth, 120.0), 2) * (1 + noise)
    new_h, new_w, top, left = resize_geometry(*FULL, *SIZE)
    half = full.reshape(new_h, 2, new_w, 2).mean(axis=(1, 3))
    return half[top : top + SIZE[0], left : left + SIZE[1]]


def _project(points: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    z = points[2]
    uv = (k @ points) / z
    return uv[0], uv[1], z


def _scaled_intrinsic(old: bool) -> np.ndarray:
    new_h, new_w, top, left = resize_geometry(*FULL, *SIZE)
    k = K.copy()
    for axis, scale, offset in ((0, new_w / FULL[1], left), (1, new_h / FULL[0], top)):
        k[axis] *= scale
        # Before 0.3.0 the devkit's u was scaled as a pixel-corner coordinate.
        k[axis, 2] += (0.0 if old else 0.5 * scale - 0.5) - offset
    return k


def ground_truth_network(points: np.ndarray, old: bool) -> np.ndarray:
    """The 448x800 ground-truth map the nuScenes reader makes (z >= 1 m, the nearest winning),
    with the old placement (floor of corner coordinates) or the field's (round)."""
    u, v, z = _project(points, _scaled_intrinsic(old))
    front = z >= 1.0
    u, v, z = u[front], v[front], z[front]
    if old:
        inside = (u >= 0) & (u < SIZE[1]) & (v >= 0) & (v < SIZE[0])
        u, v = np.floor(u[inside]) + 0.25, np.floor(v[inside]) + 0.25  # lands in floor's pixel
        z = z[inside]
    else:
        inside = in_image(u, v, *SIZE)
        u, v, z = u[inside], v[inside], z[inside]
    return np.round(splat_nearest(u, v, z, *SIZE) * 256) / 256  # the cache's uint16


def ground_truth_radarnet(points: np.ndarray) -> np.ndarray:
    """RadarNet's 900x1600 ground-truth map: map_pointcloud_to_image's mask, np.round, each
    point written in turn, a uint16 PNG of 256 z."""
    u, v, z = _project(points, K)
    mask = (z > 1.0) & (u > 1) & (u < FULL[1] - 1) & (v > 1) & (v < FULL[0] - 1)
    rows, cols, z = np.round(v[mask]).astype(int), np.round(u[mask]).astype(int), z[mask]
    depth_map = np.zeros(FULL)
    for row, col, depth in zip(rows, cols, z, strict=True):  # in turn: the last written wins
        depth_map[row, col] = depth
    return np.uint32(depth_map * 256.0) / 256.0


def _radarnet_errors(prediction: np.ndarray, truth: np.ndarray, cap: float) -> tuple[float, float]:
    """eval_utils.py's mean_abs_err and root_mean_sqr_err of 1000 x depth over 0 < gt < cap."""
    mask = (truth > 0) & (truth < cap)
    error = 1000.0 * prediction[mask] - 1000.0 * truth[mask]
    return float(np.mean(np.abs(error))), float(np.sqrt(np.mean(error**2)))


def score(prediction: np.ndarray, points: np.ndarray) -> dict[str, dict[str, tuple[float, float]]]:
    """MAE and RMSE (mm) per pipeline and cap for one frame."""
    pred = torch.from_numpy(prediction)[None, None]
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for name in ("old", "network"):
        truth = torch.from_numpy(ground_truth_network(points, old=name == "old"))[None, None]
        out[name] = _metrics(pred, truth)
    radarnet_map = ground_truth_radarnet(points)
    rows, cols = np.nonzero(radarnet_map)
    kept = full_resolution_points(rows, cols, radarnet_map[rows, cols], FULL, SIZE)
    at_points, target = depth_at_points(pred, torch.from_numpy(kept).double()[None])
    out["full"] = _metrics(at_points, target)
    new_h, new_w, top, left = resize_geometry(*FULL, *SIZE)
    up = torch.nn.functional.interpolate(pred, scale_factor=2, mode="bilinear")[0, 0].numpy()
    canvas = np.concatenate([np.repeat(up[:1], 2 * top, axis=0), up])  # the cut rows: the edge
    out["radarnet"] = {f"{cap:g}": _radarnet_errors(canvas, radarnet_map, cap) for cap in CAPS}
    return out


def _metrics(pred: torch.Tensor, truth: torch.Tensor) -> dict[str, tuple[float, float]]:
    metrics = DepthMetrics(min_depth=0.0, max_depth=list(CAPS), clamp=False)
    metrics.update(pred, truth.to(pred.dtype))
    by_cap = metrics.results()["by_cap"]
    return {
        f"{cap:g}": (by_cap[f"{cap:g}"]["mae"] * 1000, by_cap[f"{cap:g}"]["rmse"] * 1000)
        for cap in CAPS
    }


def other_presets(prediction: np.ndarray, points: np.ndarray, depth: np.ndarray) -> dict:
    """The smaller differences, on the same arrays: ``kitti_dc``'s PNG reading (MAE, RMSE in mm,
    iMAE, iRMSE in 1/km, without and with ``eval.quantize=kitti_png``) and ``densedepth``'s
    mirrored border (RMSE in mm, ARD, δ1 of a 224x400 output upsampled to 448x800 by
    ``bilinear`` and by ``bilinear_reflect``, pooled over the frame's dense true depth, ARD
    divided by the prediction)."""
    from fusion_depth.models.inference import resize_depth

    pred = torch.from_numpy(prediction)[None, None]
    truth = torch.from_numpy(ground_truth_network(points, old=False))[None, None]
    out: dict[str, list[float]] = {}
    for quantize in ("none", "kitti_png"):
        metrics = DepthMetrics(min_depth=0.0, max_depth=256.0, clamp=False, quantize=quantize)
        metrics.update(pred, truth.double())
        m = metrics.results()["overall"]
        out[f"kitti_dc/{quantize}"] = [m["mae"] * 1000, m["rmse"] * 1000, m["imae"], m["irmse"]]
    new_h, new_w, top, left = resize_geometry(*FULL, *SIZE)
    dense = np.minimum(depth, SKY).reshape(new_h, 2, new_w, 2).mean(axis=(1, 3))
    dense = torch.from_numpy(dense[top : top + SIZE[0], left : left + SIZE[1]])[None, None]
    small = torch.nn.functional.avg_pool2d(pred, 2)
    for mode in ("bilinear", "bilinear_reflect"):
        metrics = DepthMetrics(
            min_depth=1.0, max_depth=80.0, averaging="pooled", relative_to="prediction"
        )
        metrics.update(resize_depth(small, SIZE, mode), dense)
        m = metrics.results()["overall"]
        out[f"densedepth/{mode}"] = [m["rmse"] * 1000, m["abs_rel"], m["delta1"]]
    return out


def simulate(frames: int, seed: int) -> dict:
    """Every frame's numbers and their means: the record."""
    rng = np.random.default_rng(seed)
    per_frame, others = [], []
    for _ in range(frames):
        depth, points = render(rng)
        prediction = predict(depth, rng)
        per_frame.append(score(prediction, points))
        others.append(other_presets(prediction, points, depth))
    mean = {
        name: {
            f"{cap:g}": [
                float(np.mean([frame[name][f"{cap:g}"][i] for frame in per_frame])) for i in (0, 1)
            ]
            for cap in CAPS
        }
        for name in PIPELINES
    }
    return {
        "script": "scripts/simulate_placement.py",
        "frames": frames,
        "seed": seed,
        "full_resolution": list(FULL),
        "network_resolution": list(SIZE),
        "mean_mm": mean,
        "other_presets": {
            key: [float(np.mean([o[key][i] for o in others])) for i in range(len(others[0][key]))]
            for key in others[0]
        },
    }


def _before_after(labels: tuple[str, str], before: list, after: list, cell: str, change: str):
    """Rows of two measurements of the same quantities and their difference, per cent."""
    return [
        [labels[0], *(format(v, cell) for v in before)],
        [labels[1], *(format(v, cell) for v in after)],
        [
            "difference, per cent",
            *(format(100 * (b / a - 1), change) for a, b in zip(before, after, strict=True)),
        ],
    ]


def tables(record: dict) -> str:
    """The results page's tables: mean MAE and RMSE (mm) per pipeline and cap, each pipeline's
    difference from RadarNet's own steps, and the other presets' measurements
    (:func:`other_presets`)."""
    mean = record["mean_mm"]
    caps = list(mean["radarnet"])
    by_cap = ["pipeline", *(f"{c} m {m}" for c in caps for m in ("MAE", "RMSE"))]

    def per_pipeline(names, cell) -> str:
        return format_table(
            by_cap, [[f"`{n}`", *(cell(n, c, i) for c in caps for i in (0, 1))] for n in names]
        )

    other = record["other_presets"]
    sections = [
        f"{record['frames']} frames, seed {record['seed']}. MAE / RMSE in mm, mean over frames:",
        per_pipeline(PIPELINES, lambda n, c, i: f"{mean[n][c][i]:,.1f}"),
        "Difference from `radarnet` (RadarNet's own steps), per cent:",
        per_pipeline(
            PIPELINES[:-1],
            lambda n, c, i: f"{100 * (mean[n][c][i] / mean['radarnet'][c][i] - 1):+.3f}",
        ),
        "`kitti_dc`, the same output as floats and as the devkit reads its PNG (every gt > 0):",
        format_table(
            ["prediction", "MAE (mm)", "RMSE (mm)", "iMAE (1/km)", "iRMSE (1/km)"],
            _before_after(
                ("floats", "read from the PNG"),
                other["kitti_dc/none"],
                other["kitti_dc/kitti_png"],
                ",.3f",
                "+.3f",
            ),
        ),
        "`densedepth`, a 224x400 output upsampled to 448x800 (pooled, dense truth 1-80 m):",
        format_table(
            ["upsampling", "RMSE (mm)", "ARD", "δ1"],
            _before_after(
                ("`bilinear` (edges replicated)", "`bilinear_reflect` (mirrored)"),
                other["densedepth/bilinear"],
                other["densedepth/bilinear_reflect"],
                ".5f",
                "+.4f",
            ),
        ),
    ]
    return "\n\n".join(sections) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--record", type=Path, help="write the record (JSON) here")
    parser.add_argument("--from-record", type=Path, help="print the tables of a saved record")
    args = parser.parse_args(argv)
    if args.from_record is not None:
        record = json.loads(args.from_record.read_text())
    else:
        record = simulate(args.frames, args.seed)
        if args.record is not None:
            args.record.parent.mkdir(parents=True, exist_ok=True)
            args.record.write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    sys.stdout.write(tables(record))
    values = [v for p in record["mean_mm"].values() for c in p.values() for v in c]
    return 0 if all(math.isfinite(v) for v in values) else 1


if __name__ == "__main__":
    raise SystemExit(main())
