"""Materials, lighting and weather for :mod:`fusion_depth.data.procedural` street scenes.

Colours are computed per pixel from the ray-cast hits: albedo with procedural texture (asphalt,
lane paint, paving, facades with windows, cars with wheels and lights), then a lighting model per
condition, then the weather's effect on the image (fog and rain extinction, glare, rain streaks,
sensor noise). The weather never touches the geometry, so depth is exact in every condition.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fusion_depth.data._procedural_scene import (
    BUILDING,
    CAR,
    FOLIAGE,
    GLASS,
    GROUND_ID,
    LAMP,
    N_MATERIALS,
    SIDEWALK,
    SKY_ID,
    TRUNK,
    Scene,
    box_corners,
    cast_shadows,
    pixel_windows,
)

F32 = np.float32


def _value_noise(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Tileable fractal value noise in [-1, 1] used as the texture source for every material."""
    out = np.zeros((size, size), dtype=F32)
    amp = 1.0
    for cells in (4, 8, 16, 32, 64):
        grid = rng.standard_normal((cells, cells)).astype(F32)
        x = np.arange(size) * cells / size
        i0 = np.floor(x).astype(np.int64)
        f = (x - i0).astype(F32)
        f = f * f * (3 - 2 * f)
        i1 = (i0 + 1) % cells
        rows = grid[i0] * (1 - f)[:, None] + grid[i1] * f[:, None]
        out += amp * (rows[:, i0] * (1 - f)[None] + rows[:, i1] * f[None])
        amp *= 0.55
    return out / np.abs(out).max()


_TEXTURE_RNG = np.random.default_rng(20240607)  # fixed: textures are part of the generator
_NOISE = _value_noise(_TEXTURE_RNG).ravel()
_GRAIN = _TEXTURE_RNG.uniform(-1.0, 1.0, 256 * 256).astype(F32)


def _tex(table: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Lookup of a tiling 256x256 table at texel coordinates (a, b), truncated to integers."""
    index = ((a.astype(np.int32) & 255) << 8) | (b.astype(np.int32) & 255)
    return np.take(table, index)


def _hash01(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """A deterministic pseudo-random number in [0, 1) per integer triple (e.g. which window)."""
    h = (a.astype(np.int64) * 73856093) ^ (b.astype(np.int64) * 19349663)
    h = (h ^ (c.astype(np.int64) * 83492791)) & 0xFFFFFFFF
    h = (h * 2654435761) & 0xFFFFFFFF
    return (h >> 8).astype(F32) / F32(1 << 24)


@dataclass(frozen=True)
class Weather:
    """Per-frame weather: the condition plus the randomised strength of its effects."""

    condition: str
    beta: float  # extinction coefficient of fog / rain / haze, 1/m
    haze: np.ndarray  # colour the extinction blends towards
    exposure: float
    visibility: float  # metres where contrast falls to 5 % (3 / beta)


def sample_weather(condition: str, rng: np.random.Generator) -> Weather:
    """Randomises how strong the condition is in this frame."""
    if condition == "fog":
        visibility = rng.uniform(25.0, 45.0)  # beyond ~30-40 m nearly invisible
        haze = np.array([0.74, 0.76, 0.78], dtype=F32) * rng.uniform(0.85, 1.05)
    elif condition == "rain":
        visibility = rng.uniform(250.0, 450.0)
        haze = np.array([0.55, 0.57, 0.60], dtype=F32) * rng.uniform(0.9, 1.1)
    elif condition == "night":
        visibility = 2000.0
        haze = np.array([0.02, 0.02, 0.03], dtype=F32)
    else:
        visibility = rng.uniform(1000.0, 2500.0)
        haze = np.array([0.72, 0.80, 0.90] if condition == "day" else [0.75, 0.76, 0.78], dtype=F32)
    return Weather(
        condition, 3.0 / visibility, haze, float(rng.uniform(0.9, 1.1)), float(visibility)
    )


_SKY_PALETTE = {  # horizon, zenith, cloud colour, cloud cover range
    "day": ((0.78, 0.86, 0.95), (0.30, 0.52, 0.88), (0.95, 0.95, 0.96), (0.0, 0.5)),
    "cloudy": ((0.78, 0.79, 0.80), (0.58, 0.60, 0.64), (0.50, 0.51, 0.54), (0.5, 0.9)),
    "rain": ((0.60, 0.62, 0.65), (0.40, 0.42, 0.46), (0.30, 0.31, 0.34), (0.6, 1.0)),
    "night": ((0.06, 0.05, 0.05), (0.01, 0.015, 0.035), (0.04, 0.04, 0.05), (0.0, 0.6)),
}

# Per-pixel arrays are channel-first, (3, N) or (3, H, W): numpy broadcasts a length-3 last
# axis an order of magnitude slower than long rows.


def _rgb(*values: float) -> np.ndarray:
    """A colour shaped (3, 1), to broadcast over (3, N) pixel arrays."""
    return np.array(values, dtype=F32)[:, None]


def _horizon(weather: Weather) -> np.ndarray:
    """Sky colour at the horizon (3, 1): what wet roads and windows reflect."""
    if weather.condition == "fog":
        return weather.haze[:, None]
    return _rgb(*_SKY_PALETTE[weather.condition][0])


def _sky(d: np.ndarray, weather: Weather, rng: np.random.Generator) -> np.ndarray:
    """Sky colour (3, N) of rays (3, N) from their elevation, with clouds on a plane overhead."""
    up = np.clip(d[1] / np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2), 0.0, 1.0)
    if weather.condition == "fog":
        return weather.haze[:, None] * (1 + 0.06 * up)
    horizon, zenith, cloud_col = (_rgb(*c) for c in _SKY_PALETTE[weather.condition][:3])
    s = np.clip(up / 0.45, 0, 1) ** 0.7
    cover = rng.uniform(*_SKY_PALETTE[weather.condition][3])
    h = np.maximum(d[1], 1e-3)
    shift = rng.uniform(0, 256, 2)
    cloud = _tex(_NOISE, d[0] / h * 6 + shift[0], d[2] / h * 6 + shift[1])
    cloud = np.clip((cloud + cover - 0.5) * 2.5, 0, 1) * np.clip(up * 8, 0, 1)
    return horizon + (zenith - horizon) * s + (cloud_col - horizon - (zenith - horizon) * s) * cloud


def _face_normals(
    p: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Axis (0, 1, 2) and sign (+-1) of the box face each ray (direction ``d``) hit at ``p``
    (all (3, N)): the nearest of the three faces turned towards the ray, whose normal opposes
    the ray."""
    dist = np.abs(p - np.where(d > 0, lo, hi))
    axis = np.where(
        (dist[0] <= dist[1]) & (dist[0] <= dist[2]), 0, np.where(dist[1] <= dist[2], 1, 2)
    )
    sign = np.where(np.take_along_axis(d, axis[None], 0)[0] > 0, -1, 1)
    return axis, sign


def _ground(scene: Scene, p: np.ndarray, wet: bool) -> np.ndarray:
    """Asphalt with lane paint on the road, grass or paving beyond the sidewalks."""
    x, z = p[0], p[2]
    grey = scene.asphalt * (
        1 + 0.12 * _tex(_NOISE, x * 3, z * 3) + 0.08 * _tex(_GRAIN, x * 25, z * 25)
    )
    albedo = _rgb(1.0, 1.0, 1.03) * grey
    wear = 0.75 + 0.25 * _tex(_NOISE, x * 7 + 91, z * 2)
    for (xc, half, dash, period, phase), color in zip(
        scene.markings, scene.marking_color, strict=True
    ):
        on = (np.abs(x - xc) < half) & (np.mod(z - phase, period) < dash)
        albedo[:, on] = color[:, None] * wear[on]
    if wet:
        albedo *= 0.55
    verge = 1 + 0.25 * _tex(_NOISE, x * 2, z * 2)
    for side, outside in enumerate((x < scene.road[0], x > scene.road[1])):
        albedo[:, outside] = scene.verge_color[side][:, None] * verge[outside]
    return albedo


def _sidewalk(base: np.ndarray, p: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Paving slabs with joints on top, a lighter kerb stone on the side."""
    x, z = p[0], p[2]
    joint = (np.mod(z, 1.5) < 0.05) | (np.mod(x, 1.5) < 0.05)
    shade = 1 + 0.1 * _tex(_NOISE, x * 4, z * 4) - 0.25 * joint
    return base * np.where(axis == 1, shade, 1.15)


def _building(
    base: np.ndarray,
    param: np.ndarray,
    top: np.ndarray,
    p: np.ndarray,
    axis: np.ndarray,
    edge_lo: np.ndarray,
    edge_hi: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Facade texture with a grid of windows and an optional shop front.

    Returns albedo, a glass mask (reflective) and a per-window random number that decides which
    windows are lit at night.
    """
    floor_h, win_w, spacing, win_h, shop, _, bid, phase = param
    along = np.where(axis == 0, p[2], p[0])
    y = p[1]
    floor_i = np.floor(y / floor_h)
    in_floor = y - floor_i * floor_h
    col_i = np.floor((along - phase) / spacing)
    in_col = np.abs(along - phase - col_i * spacing - spacing / 2)
    inside = (np.minimum(along - edge_lo, edge_hi - along) > 0.6) & (axis != 1)
    window = (
        inside
        & (floor_i >= 1)
        & (y < top - 0.8)
        & (in_floor > 0.3 * floor_h)
        & (in_floor < 0.3 * floor_h + win_h)
        & (in_col < win_w / 2)
    )
    shop_front = (
        inside & (shop > 0) & (floor_i == 0) & (y > 0.4) & (y < 2.6) & (in_col < spacing / 2 - 0.2)
    )
    shade = (
        1
        + 0.08 * _tex(_NOISE, along * 2 + bid * 37, y * 2)
        + 0.04 * _tex(_GRAIN, along * 10, y * 10)
    )
    albedo = base * np.where(y > top - 0.5, 0.8, shade)  # darker cornice
    glass = window | shop_front
    albedo[:, glass] = _rgb(0.10, 0.12, 0.15)
    return albedo, glass, _hash01(bid, floor_i, col_i)


def _car(
    base: np.ndarray,
    param: np.ndarray,
    p: np.ndarray,
    axis: np.ndarray,
    sign: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Car body: wheels on the sides, lights, grille, bumper and plate at the ends, glass band
    for vans and buses. Returns albedo, glass mask, headlight mask, tail-light mask."""
    facing, _, front_z, rear_z, glass_lo, glass_hi, wheel, _ = param
    x, y, z = p
    albedo = base.copy()
    tyre = (axis == 0) & (
        np.minimum((z - front_z) ** 2, (z - rear_z) ** 2) + (y - wheel) ** 2 < wheel**2
    )
    albedo[:, tyre] = 0.05
    end = axis == 2
    is_front = end & (sign == facing)
    is_rear = end & (sign != facing)
    lateral = np.minimum(x - lo[0], hi[0] - x)
    centre = np.abs(x - (lo[0] + hi[0]) / 2)
    head = is_front & (y > 0.58) & (y < 0.76) & (lateral > 0.1) & (lateral < 0.42)
    tail = is_rear & (y > 0.7) & (y < 0.86) & (lateral > 0.06) & (lateral < 0.32)
    grille = is_front & (y > 0.4) & (y < 0.56) & (centre < 0.45)
    albedo[:, (end & (y < 0.32)) | grille] = 0.12  # bumper and grille
    albedo[:, end & (y > 0.36) & (y < 0.48) & (centre < 0.26)] = 0.85  # number plate
    albedo[:, head] = _rgb(0.85, 0.85, 0.80)
    albedo[:, tail] = _rgb(0.55, 0.04, 0.03)
    glass = (glass_hi > 0) & (axis != 1) & (y > glass_lo) & (y < glass_hi)
    glass |= is_front & (glass_hi > 0) & (y > glass_lo - 0.4) & (y < glass_hi)  # windscreen
    albedo[:, glass] = _rgb(0.08, 0.10, 0.12)
    return albedo, glass, head, tail


def _surfaces(
    scene: Scene,
    p: np.ndarray,
    d: np.ndarray,
    ids: np.ndarray,
    blocks: dict[int, slice],
    weather: Weather,
) -> tuple[np.ndarray, ...]:
    """Albedo, normal, emission (3, N) and glossiness (N,) of hit pixels (points ``p`` and ray
    directions ``d``, (3, N)) sorted by material: ``blocks`` gives each material's contiguous
    range, ground first, so that every material works on slices, not scattered pixels."""
    n = len(ids)
    cond = weather.condition
    night = cond == "night"
    albedo = np.empty((3, n), dtype=F32)
    normal = np.zeros((3, n), dtype=F32)
    gloss = np.zeros(n, dtype=F32)
    emit = np.zeros((3, n), dtype=F32)
    g = blocks[GROUND_ID]
    normal[1, g] = 1.0
    albedo[:, g] = _ground(scene, p[:, g], cond == "rain")
    if cond == "rain":  # wet asphalt mirrors the sky at grazing angles (Fresnel), puddles more
        x, z = p[0, g], p[2, g]
        puddle = np.clip(_tex(_NOISE, x * 1.5 + 50, z * 0.8) * 2 + 0.5, 0, 1)
        cos_i = -d[1, g] / np.sqrt(d[0, g] ** 2 + d[1, g] ** 2 + d[2, g] ** 2)
        fresnel = 0.05 + 0.95 * (1 - cos_i) ** 5
        on_road = (x >= scene.road[0]) & (x <= scene.road[1])
        gloss[g] = np.where(on_road, (0.3 + 0.6 * puddle) * fresnel, 0)

    off = g.stop  # box pixels follow the ground; their arrays are views from here on
    bid = ids[off:]
    pb = p[:, off:]
    lo, hi = np.take(scene.lo.T, bid, 1), np.take(scene.hi.T, bid, 1)
    axis, sign = _face_normals(pb, d[:, off:], lo, hi)
    normal[axis, np.arange(off, n)] = sign
    base = np.take(scene.color.T, bid, 1)
    alb, glo, emi = albedo[:, off:], gloss[off:], emit[:, off:]
    alb[:] = base * (1 + 0.06 * _tex(_GRAIN, pb[0] * 9 + pb[2] * 9, pb[1] * 9))

    def block(material: int) -> slice:
        s = blocks[material]
        return slice(s.start - off, s.stop - off)

    s = block(SIDEWALK)
    alb[:, s] = _sidewalk(base[:, s], pb[:, s], axis[s])
    s = block(BUILDING)
    if s.stop > s.start:
        param = np.take(scene.param.T, bid[s], 1)
        along_lo = np.where(axis[s] == 0, lo[2, s], lo[0, s])
        along_hi = np.where(axis[s] == 0, hi[2, s], hi[0, s])
        alb[:, s], glass, rand = _building(
            base[:, s], param, hi[1, s], pb[:, s], axis[s], along_lo, along_hi
        )
        glo[s][glass] = 0.22
        if night:
            lit = glass & (rand < param[5])
            emi[:, s][:, lit] = _rgb(1.0, 0.78, 0.45) * (0.35 + 0.5 * rand[lit] / param[5, lit])
    s = block(CAR)
    if s.stop > s.start:
        param = np.take(scene.param.T, bid[s], 1)
        alb[:, s], glass, head, tail = _car(
            base[:, s], param, pb[:, s], axis[s], sign[s], lo[:, s], hi[:, s]
        )
        glo[s] = np.where(glass, 0.15, 0.05)
        lights_on = param[1] > 0
        strength = {"night": 3.0, "fog": 1.2, "rain": 1.0}.get(cond, 0.0)
        emi[:, s][:, head & lights_on] = _rgb(1.0, 0.97, 0.9) * strength
        emi[:, s][:, tail & lights_on] = _rgb(1.0, 0.08, 0.04) * strength * 0.6
    s = block(GLASS)
    side = axis[s] != 1  # the cabin roof keeps the body colour
    alb[:, s][:, side] = _rgb(0.07, 0.09, 0.11)
    glo[s][side] = 0.15
    if night:
        emi[:, block(LAMP)] = _rgb(2.5, 2.2, 1.6)
    for material in (FOLIAGE, TRUNK):
        s = block(material)
        alb[:, s] *= 0.75 + 0.45 * _tex(_NOISE, pb[0, s] * 6 + pb[2, s] * 6, pb[1, s] * 6)
    return albedo, normal, gloss, emit


def _night_lights(scene: Scene, pts: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Irradiance (H, W) at points with normals (3, H, W) from street lamps (shining down), the
    headlights of moving cars and the camera car's own headlights (narrow spots), each evaluated
    only within its reach."""
    cars = np.flatnonzero((scene.material == CAR) & (scene.param[:, 1] > 0))
    facing = scene.param[cars, 0]
    front = np.stack(
        [
            (scene.lo[cars, 0] + scene.hi[cars, 0]) / 2,
            np.full(len(cars), 0.7),
            np.where(facing > 0, scene.hi[cars, 2] + 0.1, scene.lo[cars, 2] - 0.1),
        ],
        1,
    )
    cam = scene.camera
    ego = np.array([[cam.position[0], 0.7, cam.position[2] + 1.5]])
    pos = np.concatenate([scene.lamps, front, ego]).astype(F32)
    n_lamps = len(scene.lamps)
    axis = np.zeros_like(pos)
    axis[:n_lamps, 1] = -1.0
    axis[n_lamps:-1, 2] = facing
    axis[-1] = (np.sin(cam.yaw), 0.0, np.cos(cam.yaw))
    axis[n_lamps:, 1] = -0.08  # headlights dip to the road
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    power = np.r_[np.full(n_lamps, 28.0), np.full(len(cars), 60.0), 80.0]
    reach = np.r_[np.full(n_lamps, 16.0), np.full(len(cars), 35.0), 50.0]
    cut = np.r_[np.full(n_lamps, -0.2), np.full(len(cars) + 1, 0.9)]  # cone cosine
    # Boxes bounding what each light reaches: a lamp's pool below it, a headlight's beam ahead.
    lo = pos - reach[:, None]
    hi = pos + reach[:, None]
    lo[:, 1], hi[:, 1] = 0.0, np.maximum(pos[:, 1], 2.5)
    beam = axis[n_lamps:, [0, 2]] * reach[n_lamps:, None]
    lo[n_lamps:, [0, 2]] = pos[n_lamps:, [0, 2]] + np.minimum(beam, 0) - 0.4 * reach[n_lamps:, None]
    hi[n_lamps:, [0, 2]] = pos[n_lamps:, [0, 2]] + np.maximum(beam, 0) + 0.4 * reach[n_lamps:, None]
    win = pixel_windows(box_corners(lo, hi), cam)
    total = np.zeros(pts.shape[1:], dtype=F32)
    for light, direction, watts, radius, cos_cut, (r0, r1, c0, c1) in zip(
        pos, axis, power, reach, cut, win, strict=True
    ):
        if r1 <= r0 or c1 <= c0:
            continue
        window = (slice(r0, r1), slice(c0, c1))
        px, py, pz = pts[(slice(None), *window)]
        nx, ny, nz = normal[(slice(None), *window)]
        vx, vy, vz = light[0] - px, light[1] - py, light[2] - pz
        d2 = vx * vx + vy * vy + vz * vz + 1.0
        inv_d = 1 / np.sqrt(d2)
        gain = np.maximum(nx * vx + ny * vy + nz * vz, 0) * inv_d
        gain *= np.maximum(1 - d2 / radius**2, 0) ** 2 / d2
        cos_a = -(vx * direction[0] + vy * direction[1] + vz * direction[2]) * inv_d
        gain *= np.clip((cos_a - cos_cut) / (1 - cos_cut), 0, 1) ** 2
        total[window] += watts * gain
    return total


def _glare_sources(scene: Scene, weather: Weather) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World position, colour and size (m) of light sources that bloom in the camera."""
    cond = weather.condition
    pos, col, size = [], [], []
    if cond in ("night", "fog", "rain"):
        cars = np.flatnonzero((scene.material == CAR) & (scene.param[:, 1] > 0))
        lo, hi, facing = scene.lo[cars], scene.hi[cars], scene.param[cars, 0]
        strength = {"night": 1.0, "fog": 0.5, "rain": 0.4}[cond]
        oncoming = facing < 0
        white = np.array([1.0, 0.97, 0.9], dtype=F32) * strength
        red = np.array([1.0, 0.1, 0.05], dtype=F32) * strength * 0.5
        for x in (lo[:, 0] + 0.26, hi[:, 0] - 0.26):
            pos.append(np.stack([x, np.where(oncoming, 0.67, 0.78), lo[:, 2] - 0.02], 1))
            col.append(np.where(oncoming[:, None], white, red))
            size.append(np.where(oncoming, 0.25, 0.12))
    if cond == "night":
        pos.append(scene.lamps)
        col.append(np.tile(np.array([1.0, 0.85, 0.6], dtype=F32), (len(scene.lamps), 1)))
        size.append(np.full(len(scene.lamps), 0.35))
    if not pos:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(pos), np.concatenate(col), np.concatenate(size)


def _add_glare(image: np.ndarray, depth: np.ndarray, scene: Scene, weather: Weather) -> None:
    """Blooms around visible lights facing the camera (headlights, tail lights, lamps)."""
    pos, col, size = _glare_sources(scene, weather)
    if not len(pos):
        return
    cam = scene.camera
    u, v, z = cam.project(pos)
    h, w = depth.shape
    spread = 3.0 if weather.condition == "fog" else 1.0
    for uu, vv, zz, cc, ss in zip(u, v, z, col, size, strict=True):
        if zz < 0.5 or not (0 <= uu < w and 0 <= vv < h):
            continue
        seen = depth[int(vv), int(uu)]
        if 0 < seen < zz - 0.4:  # occluded
            continue
        sigma = max(0.6, ss * cam.focal / zz)
        reach = int(min(max(h, w) / 3, 8 * sigma * spread + 4))
        r0, r1 = max(0, int(vv) - reach), min(h, int(vv) + reach + 1)
        c0, c1 = max(0, int(uu) - reach), min(w, int(uu) + reach + 1)
        yy, xx = np.mgrid[r0:r1, c0:c1]
        r2 = ((yy + 0.5 - vv) ** 2 + (xx + 0.5 - uu) ** 2).astype(F32)
        glow = np.exp(-r2 / (2 * sigma**2)) + 0.25 * spread * sigma**2 / (r2 + 4 * sigma**2)
        fade = np.exp(-weather.beta * zz * 0.5)
        image[:, r0:r1, c0:c1] += (cc * fade)[:, None, None] * glow


def _rain_streaks(image: np.ndarray, rng: np.random.Generator) -> None:
    """Bright, slanted motion-blurred drops in front of the camera."""
    h, w = image.shape[1:]
    count = h * w // 300
    length = rng.uniform(0.05, 0.15, count) * h
    angle = np.radians(rng.uniform(-15, 15)) + rng.normal(0, 0.03, count)
    steps = np.linspace(0, 1, max(4, int(0.15 * h)), dtype=F32)
    r = rng.uniform(-0.1 * h, h, count)[:, None] + (length * np.cos(angle))[:, None] * steps
    c = rng.uniform(0, w, count)[:, None] + (length * np.sin(angle))[:, None] * steps
    keep = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    layer = np.zeros((h, w), dtype=F32)
    weight = np.broadcast_to(rng.uniform(0.05, 0.12, count)[:, None], r.shape)
    np.add.at(layer, (r[keep].astype(np.int64), c[keep].astype(np.int64)), weight[keep])
    alpha = np.clip(layer, 0, 0.35)
    image *= 1 - alpha
    image += alpha * 0.85


def _noise(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Zero-mean, unit-variance sensor noise: uniform, five times cheaper to draw than Gaussian
    and indistinguishable from it once quantised to 8 bits at these amplitudes."""
    return (rng.random(shape, dtype=F32) - F32(0.5)) * F32(12**0.5)


def _contact_shadows(scene: Scene, pts: np.ndarray, ground: np.ndarray) -> np.ndarray:
    """Darkening (H, W) of the ground under cars (ambient occlusion)."""
    occlusion = np.ones(ground.shape, dtype=F32)
    cars = np.flatnonzero(scene.material == CAR)
    lo, hi = scene.lo[cars] - (0.3, 0, 0.3), scene.hi[cars] + (0.3, 0, 0.3)
    lo[:, 1] = hi[:, 1] = 0.0
    corners = np.stack([lo, hi, lo, hi], 1)
    corners[:, 2, 0], corners[:, 3, 0] = hi[:, 0], lo[:, 0]
    win = pixel_windows(corners, scene.camera)
    for (r0, r1, c0, c1), a, b in zip(win, lo, hi, strict=True):
        if (r1 - r0) * (c1 - c0) < 30:  # too far away to show
            continue
        x, z = pts[0, r0:r1, c0:c1], pts[2, r0:r1, c0:c1]
        inside = np.minimum(np.minimum(x - a[0], b[0] - x), np.minimum(z - a[2], b[2] - z))
        inside = np.clip(inside / 0.4, 0, 1) * ground[r0:r1, c0:c1]
        occlusion[r0:r1, c0:c1] *= 1 - 0.6 * inside
    return occlusion


def shade(
    scene: Scene,
    dirs: np.ndarray,
    t: np.ndarray,
    ids: np.ndarray,
    weather: Weather,
    rng: np.random.Generator,
) -> np.ndarray:
    """RGB image (H, W, 3) in [0, 1] of a ray-cast scene (rays (3, H, W), hits ``t``, ``ids``)
    under the given weather."""
    cam = scene.camera
    cond = weather.condition
    h, w = ids.shape
    hit = ids != SKY_ID
    depth = np.where(hit, t, 0).astype(F32)
    pts = cam.position[:, None, None] + dirs * depth

    # Hit pixels sorted by material: ``pix`` are their flat indices.
    hit_idx = np.flatnonzero(hit)
    flat_ids = ids.reshape(-1)[hit_idx]
    key = np.where(flat_ids >= 0, scene.material[np.maximum(flat_ids, 0)], GROUND_ID)
    order = np.argsort(key, kind="stable")
    pix, key = hit_idx[order], key[order]
    edges = np.searchsorted(key, np.arange(GROUND_ID, N_MATERIALS + 1))
    blocks = {m: slice(edges[i], edges[i + 1]) for i, m in enumerate(range(GROUND_ID, N_MATERIALS))}
    flat_dirs = dirs.reshape(3, -1)
    albedo, normal, gloss, emit = _surfaces(
        scene, pts.reshape(3, -1)[:, pix], flat_dirs[:, pix], flat_ids[order], blocks, weather
    )

    ambient, sun_power = {
        "day": ((0.50, 0.55, 0.65), 0.9),
        "cloudy": ((0.80, 0.80, 0.83), 0.18),
        "fog": ((0.82, 0.83, 0.85), 0.10),
        "rain": ((0.60, 0.62, 0.66), 0.06),
        "night": ((0.025, 0.028, 0.045), 0.0),
    }[cond]
    light = _rgb(*ambient) * (0.65 + 0.35 * normal[1])
    if sun_power:
        sun_dot = np.clip(scene.sun @ normal, 0, None)
        if cond == "day":
            sun_dot *= ~cast_shadows(scene, pts, hit).reshape(-1)[pix]
        light += (sun_power * _rgb(1.05, 1.0, 0.92)) * sun_dot
    light *= _contact_shadows(scene, pts, ids == GROUND_ID).reshape(-1)[pix]
    if cond == "night":
        normal_img = np.zeros_like(pts)
        normal_img.reshape(3, -1)[:, pix] = normal
        light += _rgb(1.0, 0.85, 0.62) * _night_lights(scene, pts, normal_img).reshape(-1)[pix]
    color = albedo * light + emit
    color += (_horizon(weather) * (0.3 if cond == "night" else 1.0)) * gloss
    transmit = np.exp(-weather.beta * (depth * cam.ray_lengths()).reshape(-1)[pix])

    image = np.empty((3, h * w), dtype=F32)
    sky = np.flatnonzero(~hit)
    image[:, sky] = _sky(flat_dirs[:, sky], weather, rng)
    image[:, pix] = weather.haze[:, None] + (color - weather.haze[:, None]) * transmit
    image = image.reshape(3, h, w)
    _add_glare(image, depth, scene, weather)
    if cond == "rain":
        _rain_streaks(image, rng)
    image *= weather.exposure
    if cond == "night":
        image *= rng.uniform(1.1, 1.5)  # auto exposure lifts the dark frame, and its noise
        sigma = 0.012 + 0.035 * np.sqrt(np.clip(image, 0, 1))  # read + shot noise
        image += _noise(rng, image.shape) * sigma
        image += _noise(rng, (1, h, w)) * 0.01  # luminance noise shared by the channels
    else:
        image += _noise(rng, image.shape) * 0.006
    if cond == "cloudy":
        image = 0.8 * image + 0.2 * image.mean(0)
    return np.clip(image, 0.0, 1.0).transpose(1, 2, 0)
