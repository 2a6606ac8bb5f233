"""Simulated automotive radar and 64-beam lidar for :mod:`fusion_depth.data.procedural`.

Both return a sparse depth map aligned with the camera: camera-frame z in metres at the pixel a
return projects to, 0 elsewhere, the nearer return winning where two share a pixel. The radar's
returns are also available as image points (:func:`radar_returns`).
"""

from __future__ import annotations

import numpy as np

from fusion_depth.data._procedural_render import Weather
from fusion_depth.data._procedural_scene import (
    BUILDING,
    CAR,
    NEAR,
    POLE,
    TRUNK,
    Camera,
    Scene,
)
from fusion_depth.data.radar_points import pixel_index, same_pixel_float32

RADAR_HEIGHT = 0.5  # metres; nuScenes-like front radar below the camera
RADAR_RANGE = 100.0
RADAR_FOV_DEG = 50.0  # half-angle in azimuth
LIDAR_ELEVATIONS_DEG = np.linspace(2.0, -24.9, 64)  # HDL-64-like beam layout
LIDAR_AZIMUTH_STEP_DEG = 0.3
LIDAR_RANGE = 120.0
# A pixel gets a lidar return when its ray lies within this angle of a beam/azimuth grid point,
# i.e. the full-resolution projection subsampled to the output size: the density (~1.5-2 % of
# pixels) does not grow as the image shrinks, as with strided KITTI sparse depth.
LIDAR_TOLERANCE_DEG = 0.03


def _in_image(points: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``u, v, z`` (M,) of the world points (N, 3) in front of the camera and inside its image
    (pixel ``(int(v), int(u))``), in their order; float32 for float32 points."""
    u, v, z = camera.project(points)
    ok = (z > NEAR) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    return u[ok], v[ok], z[ok]


def _splat(points: np.ndarray, camera: Camera) -> np.ndarray:
    """Sparse depth map of world points; the nearer point wins a shared pixel."""
    out = np.full((camera.height, camera.width), np.inf, dtype=np.float32)
    u, v, z = _in_image(points, camera)
    np.minimum.at(out, (v.astype(np.int64), u.astype(np.int64)), z)
    out[np.isinf(out)] = 0.0
    return out


def _occluded(
    origin: np.ndarray, targets: np.ndarray, lo: np.ndarray, hi: np.ndarray
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


def _surface_points(
    origin: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    counts: np.ndarray,
    margin: np.ndarray,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Random points on the footprint edges (X, Z rectangles) that face the radar: ``counts[k]``
    on footprint k, favouring long edges seen head-on and keeping ``margin[k]`` (a fraction)
    off the corners. Returns the points (M, 2) and the footprint each belongs to."""
    (x0, z0), (x1, z1) = lo.T, hi.T
    start = np.stack([np.c_[x0, z0], np.c_[x1, z0], np.c_[x0, z0], np.c_[x0, z1]], 1)
    end = np.stack([np.c_[x0, z1], np.c_[x1, z1], np.c_[x1, z0], np.c_[x1, z1]], 1)
    # How far the radar is in front of each edge (x0, x1, z0, z1); > 0: the edge faces it.
    front = np.c_[x0 - origin[0], origin[0] - x1, z0 - origin[1], origin[1] - z1]
    length = np.linalg.norm(end - start, axis=-1)
    distance = np.linalg.norm((start + end) / 2 - origin, axis=-1)
    weight = np.where(front > 0, (length + 1e-3) * front / distance, 0.0)
    owner = np.repeat(np.arange(len(lo)), counts)
    cumulative = np.cumsum(weight, 1)[owner]
    draw = rng.random(len(owner)) * cumulative[:, -1]
    edge = np.minimum((draw[:, None] > cumulative).sum(1), 3)
    where = margin[owner] + (1 - 2 * margin[owner]) * rng.random(len(owner))
    a, b = start[owner, edge], end[owner, edge]
    return a + (b - a) * where[:, None], owner


def radar_points(scene: Scene, rng: np.random.Generator, weather: Weather) -> np.ndarray:
    """World points (N, 3) of one radar scan.

    Returns come mostly from cars (strong reflectors, several points each), some from facades,
    lamp and sign posts and tree trunks (whatever stands at the radar's height), plus clutter.
    Each is measured as (range, azimuth) with noise and placed at the radar's mounting height,
    because the radar has no elevation resolution.
    """
    cam = scene.camera
    origin = np.array([cam.position[0], cam.position[2]])
    heading = cam.yaw
    lo2, hi2 = scene.lo[:, [0, 2]], scene.hi[:, [0, 2]]
    blocking = (scene.lo[:, 1] <= RADAR_HEIGHT) & (scene.hi[:, 1] >= RADAR_HEIGHT)

    # Reflectors within range, with how many returns each may give and how likely each is.
    dist = np.linalg.norm(np.clip(origin, lo2, hi2) - origin, axis=1)
    strength = {CAR: 0.95, BUILDING: 0.6, POLE: 0.35, TRUNK: 0.2}
    keys = np.array(list(strength))
    objs = np.flatnonzero(
        blocking & np.isin(scene.material, keys) & (dist >= 1.0) & (dist <= RADAR_RANGE)
    )
    mat, fall = scene.material[objs], (dist[objs] / RADAR_RANGE) ** 2
    car, building = mat == CAR, mat == BUILDING
    counts = np.where(car, 1 + np.minimum(6, rng.poisson(np.where(dist[objs] < 40, 4.0, 2.0))), 1)
    counts = np.where(building, rng.poisson(3.0, len(objs)), counts)
    base = np.array([strength[m] for m in mat.tolist()])
    prob_first = np.where(car | building, base - 0.35 * fall, base * (1 - fall))
    prob_more = np.where(car, 0.8 - 0.4 * fall, prob_first)
    margin = np.select([car, building], [0.15, 0.05], 0.5)
    points, owner = _surface_points(origin, lo2[objs], hi2[objs], counts, margin, rng)
    first = np.r_[True, owner[1:] != owner[:-1]] if len(owner) else np.zeros(0, bool)
    prob = np.where(first, prob_first[owner], prob_more[owner])

    offset = points - origin
    azimuth = np.degrees(np.arctan2(offset[:, 0], offset[:, 1]) - heading)
    in_view = (np.hypot(offset[:, 0], offset[:, 1]) <= RADAR_RANGE) & (
        np.abs((azimuth + 180) % 360 - 180) <= RADAR_FOV_DEG
    )
    points, prob = points[in_view], prob[in_view]
    if len(points):
        blocked = _occluded(origin, points, lo2[blocking], hi2[blocking])
        prob = np.where(blocked, 0.04 * prob, prob)  # multipath sees a few hidden objects
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


def extend_height(points: np.ndarray, camera: Camera, height: float) -> np.ndarray:
    """Each radar point (N, 3) as a vertical line of world points from the ground to ``height``
    metres at its (X, Z), sampled at least twice per image row it covers.

    A radar without elevation resolution cannot say where on an object a return came from; the
    radar-camera depth literature (e.g. Nobis et al. 2019, Lin et al. 2020) draws each return as
    such a line, which gives the network a few pixels per return instead of one.
    """
    if height <= 0 or not len(points):
        return points
    z = np.maximum(camera.to_camera(points)[:, 2], NEAR)
    samples = np.clip(np.ceil(2 * camera.focal * height / z), 2, 4 * camera.height).astype(int)
    owner = np.repeat(np.arange(len(points)), samples)
    start = np.cumsum(samples) - samples
    fraction = (np.arange(len(owner)) - start[owner]) / (samples[owner] - 1)
    lines = points[owner].copy()
    lines[:, 1] = fraction * height
    return lines


def radar_returns(
    scene: Scene, rng: np.random.Generator, weather: Weather, height_extension: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """One radar scan: the sparse depth map (H, W) float32 in the camera frame, and its returns
    in the image as float32 (M, 3) ``u, v, z`` rows (continuous pixel position, column and row,
    pixel centres at integers, and camera-frame z in metres), in scan order.

    Each return is a point at the radar's mounting height, drawn at pixel ``(round(v), round(u))``
    with depth ``z`` (the nearer winning a shared pixel); ``height_extension`` > 0 draws it as a
    vertical line up to that height instead (see :func:`extend_height`), which passes through
    that point, whose row stays the one returned. Returns whose point lies outside the image
    are left out of the rows (with an extension, part of their line may still be drawn).
    """
    points = radar_points(scene, rng, weather)
    u, v, z = _in_image(points, scene.camera)
    sparse = _splat(extend_height(points, scene.camera, height_extension), scene.camera)
    return sparse, np.stack([_centred(u), _centred(v), z], 1).astype(np.float32)


def _centred(x: np.ndarray) -> np.ndarray:
    """Coordinates with pixel corners at integers (the camera's, drawn at ``int(x)``) as the
    rows give them, with pixel centres at integers (:func:`~fusion_depth.data.radar_points.
    pixel_index`), in the same pixel: ``x - 0.5``, a half stepped towards its pixel."""
    cell = np.floor(x.astype(np.float64))
    centred = x.astype(np.float64) - 0.5
    tie = pixel_index(centred) != cell
    centred[tie] = np.nextafter(centred[tie], cell[tie])
    return same_pixel_float32(centred)


def radar_map(
    scene: Scene, rng: np.random.Generator, weather: Weather, height_extension: float = 0.0
) -> np.ndarray:
    """Sparse radar depth (H, W) in the camera frame; ``height_extension`` > 0 draws every
    return as a vertical line up to that height (see :func:`extend_height`)."""
    return radar_returns(scene, rng, weather, height_extension)[0]


def lidar_map(
    camera: Camera, dirs: np.ndarray, depth: np.ndarray, rng: np.random.Generator, weather: Weather
) -> np.ndarray:
    """Sparse lidar depth (H, W): exact depth plus small range noise at the pixels whose rays
    fall on the beam/azimuth grid of a level lidar at the camera; fog drops far returns."""
    c, s = np.cos(camera.yaw), np.sin(camera.yaw)
    x_h = c * dirs[0] - s * dirs[2]
    z_h = s * dirs[0] + c * dirs[2]
    azimuth = np.degrees(np.arctan2(x_h, z_h))
    elevation = np.degrees(np.arctan2(dirs[1], np.hypot(x_h, z_h)))
    tol = min(LIDAR_TOLERANCE_DEG, 0.5 * np.degrees(1.0 / camera.focal))
    top, spacing = LIDAR_ELEVATIONS_DEG[0], LIDAR_ELEVATIONS_DEG[0] - LIDAR_ELEVATIONS_DEG[1]
    beam = np.round((top - elevation) / spacing)
    on_beam = (
        (beam >= 0)
        & (beam < len(LIDAR_ELEVATIONS_DEG))
        & (np.abs(top - beam * spacing - elevation) < tol)
    )
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
