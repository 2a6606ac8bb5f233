"""Simulated automotive radar and 64-beam lidar for :mod:`fusion_depth.data.procedural`.

Both return a sparse depth map aligned with the camera: camera-frame z in metres at the pixel a
return projects to, 0 elsewhere, the nearer return winning where two share a pixel.
"""

from __future__ import annotations

import numpy as np

from fusion_depth.data._procedural_render import Weather
from fusion_depth.data._procedural_scene import (
    BUILDING,
    CAR,
    NEAR,
    POLE,
    SIGN,
    TRUNK,
    Camera,
    Scene,
)

RADAR_HEIGHT = 0.5  # metres; nuScenes-like front radar below the camera
RADAR_RANGE = 100.0
RADAR_FOV_DEG = 50.0  # half-angle in azimuth
LIDAR_ELEVATIONS_DEG = np.linspace(2.0, -24.9, 64)  # HDL-64-like beam layout
LIDAR_AZIMUTH_STEP_DEG = 0.3
LIDAR_RANGE = 120.0
# A pixel gets a lidar return when its ray lies within this angle of a beam/azimuth grid point,
# i.e. the full-resolution projection subsampled to the output size: the density (~2-3 % of
# pixels) does not grow as the image shrinks, as with strided KITTI sparse depth.
LIDAR_TOLERANCE_DEG = 0.04


def _splat(points: np.ndarray, camera: Camera) -> np.ndarray:
    """Sparse depth map of world points; the nearer point wins a shared pixel."""
    out = np.full((camera.height, camera.width), np.inf, dtype=np.float32)
    u, v, z = camera.project(points)
    ok = (z > NEAR) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    np.minimum.at(out, (v[ok].astype(np.int64), u[ok].astype(np.int64)), z[ok])
    out[np.isinf(out)] = 0.0
    return out


def _occluded(origin: np.ndarray, targets: np.ndarray, lo: np.ndarray, hi: np.ndarray
              ) -> np.ndarray:
    """Whether the horizontal segment origin -> target (X, Z) crosses any box footprint before
    the last 5 cm (so the box a target lies on does not hide it)."""
    d = targets - origin
    d[np.abs(d) < 1e-6] = 1e-6
    inv = 1.0 / d[:, None, :]
    t1 = (lo[None] - origin) * inv
    t2 = (hi[None] - origin) * inv
    t_near = np.minimum(t1, t2).max(-1)
    t_far = np.maximum(t1, t2).min(-1)
    end = 1.0 - 0.05 / np.linalg.norm(d, axis=1, keepdims=True)
    return ((t_near <= t_far) & (t_far > 0) & (t_near < end)).any(1)


def _visible_edge_points(origin: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                         rng: np.random.Generator) -> np.ndarray:
    """A random point on a footprint edge (X, Z rectangle) that faces the radar."""
    edges = []
    if origin[0] < lo[0]:
        edges.append(((lo[0], lo[1]), (lo[0], hi[1])))
    if origin[0] > hi[0]:
        edges.append(((hi[0], lo[1]), (hi[0], hi[1])))
    if origin[1] < lo[1]:
        edges.append(((lo[0], lo[1]), (hi[0], lo[1])))
    if origin[1] > hi[1]:
        edges.append(((lo[0], hi[1]), (hi[0], hi[1])))
    a, b = (np.asarray(e) for e in edges[rng.integers(len(edges))])
    return a + (b - a) * rng.random()


def radar_points(scene: Scene, rng: np.random.Generator, weather: Weather) -> np.ndarray:
    """World points (N, 3) of one radar scan.

    Returns come mostly from cars (strong reflectors, several points each), some from poles,
    trunks, signs and facades, plus clutter; each is measured as (range, azimuth) with noise and
    placed at the radar's mounting height, because the radar has no elevation resolution.
    """
    cam = scene.camera
    origin = np.array([cam.position[0], cam.position[2]])
    heading = cam.yaw
    lo2, hi2 = scene.lo[:, [0, 2]], scene.hi[:, [0, 2]]
    blocking = (scene.lo[:, 1] <= RADAR_HEIGHT) & (scene.hi[:, 1] >= RADAR_HEIGHT)

    cand: list[np.ndarray] = []
    p_det: list[float] = []
    for k in np.flatnonzero(blocking & np.isin(scene.material, (CAR, POLE, TRUNK, SIGN,
                                                                BUILDING))):
        nearest = np.clip(origin, lo2[k], hi2[k])
        rng_k = float(np.hypot(*(nearest - origin)))
        if rng_k < 1.0 or rng_k > RADAR_RANGE:
            continue
        fall = (rng_k / RADAR_RANGE) ** 2
        mat = scene.material[k]
        if mat == CAR:
            cand.append(nearest)
            p_det.append(0.97 - 0.35 * fall)
            for _ in range(min(3, rng.poisson(1.6 if rng_k < 40 else 0.8))):
                cand.append(_visible_edge_points(origin, lo2[k], hi2[k], rng))
                p_det.append(0.8 - 0.4 * fall)
        elif mat == BUILDING:
            for _ in range(rng.poisson(1.2)):
                cand.append(_visible_edge_points(origin, lo2[k], hi2[k], rng))
                p_det.append(0.45 - 0.35 * fall)
        else:
            cand.append(nearest)
            p_det.append({POLE: 0.6, SIGN: 0.5, TRUNK: 0.3}[int(mat)] - 0.3 * fall)
    points = np.asarray(cand, dtype=np.float64).reshape(-1, 2)
    offset = points - origin
    azimuth = np.degrees(np.arctan2(offset[:, 0], offset[:, 1]) - heading)
    in_view = (np.hypot(offset[:, 0], offset[:, 1]) <= RADAR_RANGE) & (
        np.abs((azimuth + 180) % 360 - 180) <= RADAR_FOV_DEG)
    points, prob = points[in_view], np.asarray(p_det)[in_view]
    if len(points):
        blocked = _occluded(origin, points, lo2[blocking], hi2[blocking])
        prob = np.where(blocked, 0.15 * prob, prob)  # multipath still sees some hidden cars
        points = points[rng.random(len(points)) < prob]

    offset = points - origin
    ranges = np.hypot(offset[:, 0], offset[:, 1])
    azimuth = np.arctan2(offset[:, 0], offset[:, 1]) - heading
    n_clutter = rng.poisson(3.5 if weather.condition == "rain" else 2.0)
    ranges = np.concatenate([ranges, rng.uniform(2.0, RADAR_RANGE, n_clutter)])
    azimuth = np.concatenate(
        [azimuth, np.radians(rng.uniform(-RADAR_FOV_DEG, RADAR_FOV_DEG, n_clutter))]
    )
    ranges = ranges + rng.normal(0.0, 1.0, len(ranges)) * (0.1 + 0.002 * ranges)
    azimuth = azimuth + np.radians(rng.normal(0.0, 0.7, len(azimuth))) + heading
    world = np.stack(
        [
            origin[0] + ranges * np.sin(azimuth),
            np.full(len(ranges), RADAR_HEIGHT),
            origin[1] + ranges * np.cos(azimuth),
        ],
        1,
    )
    return world.astype(np.float32)


def radar_map(scene: Scene, rng: np.random.Generator, weather: Weather) -> np.ndarray:
    """Sparse radar depth (H, W) in the camera frame."""
    return _splat(radar_points(scene, rng, weather), scene.camera)


def lidar_map(camera: Camera, dirs: np.ndarray, depth: np.ndarray, rng: np.random.Generator,
              weather: Weather) -> np.ndarray:
    """Sparse lidar depth (H, W): exact depth plus small range noise at the pixels whose rays
    fall on the beam/azimuth grid of a level lidar at the camera; fog drops far returns."""
    c, s = np.cos(camera.yaw), np.sin(camera.yaw)
    x_h = c * dirs[..., 0] - s * dirs[..., 2]
    z_h = s * dirs[..., 0] + c * dirs[..., 2]
    azimuth = np.degrees(np.arctan2(x_h, z_h))
    elevation = np.degrees(np.arctan2(dirs[..., 1], np.hypot(x_h, z_h)))
    tol = min(LIDAR_TOLERANCE_DEG, 0.5 * np.degrees(1.0 / camera.focal))
    top, spacing = LIDAR_ELEVATIONS_DEG[0], LIDAR_ELEVATIONS_DEG[0] - LIDAR_ELEVATIONS_DEG[1]
    beam = np.round((top - elevation) / spacing)
    on_beam = (beam >= 0) & (beam < len(LIDAR_ELEVATIONS_DEG)) & (
        np.abs(top - beam * spacing - elevation) < tol)
    step = LIDAR_AZIMUTH_STEP_DEG
    on_column = np.abs(azimuth - np.round(azimuth / step) * step) < tol
    ranges = depth * camera.ray_lengths()
    keep = on_beam & on_column & (depth > 0) & (ranges < LIDAR_RANGE)
    rows, cols = np.nonzero(keep)
    r = ranges[rows, cols]
    drop = 0.1 if weather.condition == "rain" else 0.03
    if weather.condition == "fog":
        vis = weather.visibility
        drop = np.where(r > vis, 0.95, 0.3 * (r / vis) ** 2)
    alive = rng.random(len(r)) >= drop
    rows, cols, r = rows[alive], cols[alive], r[alive]
    noise = rng.normal(0.0, 0.03 if weather.condition == "rain" else 0.02, len(r))
    out = np.zeros_like(depth, dtype=np.float32)
    z = depth[rows, cols]
    out[rows, cols] = z * (1 + noise / r)
    return out
