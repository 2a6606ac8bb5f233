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
        haze = np.array([0.72, 0.80, 0.90] if condition == "day" else [0.75, 0.76, 0.78],
                        dtype=F32)
    return Weather(condition, 3.0 / visibility, haze, float(rng.uniform(0.9, 1.1)),
                   float(visibility))


_SKY_PALETTE = {  # horizon, zenith, cloud colour, cloud cover range
    "day": ((0.78, 0.86, 0.95), (0.30, 0.52, 0.88), (0.95, 0.95, 0.96), (0.0, 0.5)),
    "cloudy": ((0.78, 0.79, 0.80), (0.58, 0.60, 0.64), (0.50, 0.51, 0.54), (0.5, 0.9)),
    "rain": ((0.60, 0.62, 0.65), (0.40, 0.42, 0.46), (0.30, 0.31, 0.34), (0.6, 1.0)),
    "night": ((0.06, 0.05, 0.05), (0.01, 0.015, 0.035), (0.04, 0.04, 0.05), (0.0, 0.6)),
}


def _horizon(weather: Weather) -> np.ndarray:
    """Sky colour at the horizon: what wet roads and windows reflect."""
    if weather.condition == "fog":
        return weather.haze
    return np.asarray(_SKY_PALETTE[weather.condition][0], dtype=F32)


def _sky(dirs: np.ndarray, weather: Weather, rng: np.random.Generator) -> np.ndarray:
    """Sky colour (N, 3) of rays (N, 3) from their elevation, with clouds on a plane overhead."""
    up = np.clip(dirs[:, 1] / np.linalg.norm(dirs, axis=-1), 0.0, 1.0)
    if weather.condition == "fog":
        return weather.haze * (1 + 0.06 * up[:, None])
    horizon, zenith, cloud_col, cover_range = (
        np.asarray(c, dtype=F32) for c in _SKY_PALETTE[weather.condition])
    s = (np.clip(up / 0.45, 0, 1) ** 0.7)[:, None]
    sky = horizon * (1 - s) + zenith * s
    cover = rng.uniform(*cover_range)
    h = np.maximum(dirs[:, 1], 1e-3)
    shift = rng.uniform(0, 256, 2)
    cloud = _tex(_NOISE, dirs[:, 0] / h * 6 + shift[0], dirs[:, 2] / h * 6 + shift[1])
    cloud = (np.clip((cloud + cover - 0.5) * 2.5, 0, 1) * np.clip(up * 8, 0, 1))[:, None]
    return sky * (1 - cloud) + cloud_col * cloud


def _face_normals(p: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Axis (0, 1, 2) and sign (+-1) of the box face each ray (direction ``d``) hit at ``p``:
    the nearest of the three faces turned towards the ray, whose normal opposes the ray."""
    dist = np.abs(p - np.where(d > 0, lo, hi))
    axis = np.where((dist[:, 0] <= dist[:, 1]) & (dist[:, 0] <= dist[:, 2]), 0,
                    np.where(dist[:, 1] <= dist[:, 2], 1, 2))
    sign = np.where(np.take_along_axis(d, axis[:, None], 1)[:, 0] > 0, -1, 1)
    return axis, sign


def _ground(scene: Scene, p: np.ndarray, wet: bool) -> np.ndarray:
    """Asphalt with lane paint on the road, grass or paving beyond the sidewalks."""
    x, z = p[:, 0], p[:, 2]
    grey = scene.asphalt * (1 + 0.12 * _tex(_NOISE, x * 3, z * 3) + 0.08 * _tex(_GRAIN, x * 25,
                                                                            z * 25))
    albedo = np.repeat(grey[:, None], 3, 1) * np.array([1.0, 1.0, 1.03], dtype=F32)
    wear = 0.75 + 0.25 * _tex(_NOISE, x * 7 + 91, z * 2)
    for (xc, half, dash, period, phase), color in zip(scene.markings, scene.marking_color,
                                                      strict=True):
        on = (np.abs(x - xc) < half) & (np.mod(z - phase, period) < dash)
        albedo[on] = color * wear[on, None]
    if wet:
        albedo *= 0.55
    left, right = x < scene.road[0], x > scene.road[1]
    verge_tex = (1 + 0.25 * _tex(_NOISE, x * 2, z * 2))[:, None]
    albedo[left] = scene.verge_color[0] * verge_tex[left]
    albedo[right] = scene.verge_color[1] * verge_tex[right]
    return albedo


def _sidewalk(base: np.ndarray, p: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Paving slabs with joints on top, a lighter kerb stone on the side."""
    x, z = p[:, 0], p[:, 2]
    joint = (np.mod(z, 1.5) < 0.05) | (np.mod(x, 1.5) < 0.05)
    shade = 1 + 0.1 * _tex(_NOISE, x * 4, z * 4) - 0.25 * joint
    shade = np.where(axis == 1, shade, 1.15)
    return base * shade[:, None]


def _building(
    base: np.ndarray, param: np.ndarray, top: np.ndarray, p: np.ndarray, axis: np.ndarray,
    edge_lo: np.ndarray, edge_hi: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Facade texture with a grid of windows and an optional shop front.

    Returns albedo, a glass mask (reflective) and a per-window random number that decides which
    windows are lit at night.
    """
    floor_h, win_w, spacing, win_h, shop, _, bid, phase = param.T
    along = np.where(axis == 0, p[:, 2], p[:, 0])
    y = p[:, 1]
    floor_i = np.floor(y / floor_h)
    in_floor = y - floor_i * floor_h
    col_i = np.floor((along - phase) / spacing)
    in_col = along - phase - col_i * spacing
    inside = (np.minimum(along - edge_lo, edge_hi - along) > 0.6) & (axis != 1)
    window = (
        inside & (floor_i >= 1) & (y < top - 0.8)
        & (in_floor > 0.3 * floor_h) & (in_floor < 0.3 * floor_h + win_h)
        & (np.abs(in_col - spacing / 2) < win_w / 2)
    )
    shop_front = inside & (shop > 0) & (floor_i == 0) & (y > 0.4) & (y < 2.6) & (
        np.abs(in_col - spacing / 2) < spacing / 2 - 0.2)
    shade = 1 + 0.08 * _tex(_NOISE, along * 2 + bid * 37, y * 2) + 0.04 * _tex(
        _GRAIN, along * 10, y * 10)
    shade = np.where(y > top - 0.5, 0.8, shade)  # cornice
    albedo = base * shade[:, None]
    glass = window | shop_front
    albedo[glass] = np.array([0.10, 0.12, 0.15], dtype=F32)
    rand = _hash01(bid, floor_i, col_i)
    return albedo, glass, rand


def _car(
    base: np.ndarray, param: np.ndarray, p: np.ndarray, axis: np.ndarray, sign: np.ndarray,
    lo: np.ndarray, hi: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Car body: wheels on the sides, lights, grille, bumper and plate at the ends, glass band
    for vans and buses. Returns albedo, glass mask, headlight mask, tail-light mask."""
    facing, _, front_z, rear_z, glass_lo, glass_hi, _, wheel = param.T
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    albedo = base.copy()
    side = axis == 0
    tyre = side & (np.minimum((z - front_z) ** 2, (z - rear_z) ** 2) + (y - wheel) ** 2
                   < wheel**2)
    albedo[tyre] = 0.05
    end = axis == 2
    is_front = end & (sign == facing)
    is_rear = end & (sign != facing)
    lateral = np.minimum(x - lo[:, 0], hi[:, 0] - x)
    centre = np.abs(x - (lo[:, 0] + hi[:, 0]) / 2)
    head = is_front & (y > 0.58) & (y < 0.76) & (lateral > 0.1) & (lateral < 0.42)
    tail = is_rear & (y > 0.7) & (y < 0.86) & (lateral > 0.06) & (lateral < 0.32)
    bumper = end & (y < 0.32)
    grille = is_front & (y > 0.4) & (y < 0.56) & (centre < 0.45)
    plate = end & (y > 0.36) & (y < 0.48) & (centre < 0.26)
    albedo[bumper | grille] = 0.12
    albedo[plate] = 0.85
    albedo[head] = (0.85, 0.85, 0.80)
    albedo[tail] = (0.55, 0.04, 0.03)
    glass = (glass_hi > 0) & (axis != 1) & (y > glass_lo) & (y < glass_hi)
    glass |= is_front & (glass_hi > 0) & (y > glass_lo - 0.4) & (y < glass_hi)  # windscreen
    albedo[glass] = (0.08, 0.10, 0.12)
    return albedo, glass, head, tail


def _surfaces(scene: Scene, p: np.ndarray, d: np.ndarray, ids: np.ndarray,
              blocks: dict[int, slice], weather: Weather) -> tuple[np.ndarray, ...]:
    """Albedo, normal, glossiness and emission of hit pixels sorted by material (``blocks``
    gives each material's contiguous range; ground first), so that every material works on
    slices instead of scattered pixels."""
    n = len(ids)
    cond = weather.condition
    night = cond == "night"
    albedo = np.empty((n, 3), dtype=F32)
    normal = np.zeros((n, 3), dtype=F32)
    gloss = np.zeros(n, dtype=F32)
    emit = np.zeros((n, 3), dtype=F32)
    g = blocks[GROUND_ID]
    normal[g, 1] = 1.0
    albedo[g] = _ground(scene, p[g], cond == "rain")
    if cond == "rain":  # wet asphalt mirrors the sky, puddles more so
        x, z = p[g, 0], p[g, 2]
        puddle = np.clip(_tex(_NOISE, x * 1.5 + 50, z * 0.8) * 2 + 0.5, 0, 1)
        gloss[g] = np.where((x >= scene.road[0]) & (x <= scene.road[1]), 0.25 + 0.5 * puddle, 0)

    off = g.stop  # box pixels follow the ground; their arrays are views from here on
    bid = ids[off:]
    pb, lo, hi = p[off:], np.take(scene.lo, bid, 0), np.take(scene.hi, bid, 0)
    axis, sign = _face_normals(pb, d[off:], lo, hi)
    normal[np.arange(off, n), axis] = sign
    base = np.take(scene.color, bid, 0)
    alb, glo, emi = albedo[off:], gloss[off:], emit[off:]
    alb[:] = base * (1 + 0.06 * _tex(_GRAIN, pb[:, 0] * 9 + pb[:, 2] * 9, pb[:, 1] * 9))[:, None]

    def block(material: int) -> slice:
        s = blocks[material]
        return slice(s.start - off, s.stop - off)

    s = block(SIDEWALK)
    alb[s] = _sidewalk(base[s], pb[s], axis[s])
    s = block(BUILDING)
    if s.stop > s.start:
        param = np.take(scene.param, bid[s], 0)
        along_lo = np.where(axis[s] == 0, lo[s, 2], lo[s, 0])
        along_hi = np.where(axis[s] == 0, hi[s, 2], hi[s, 0])
        alb[s], glass, rand = _building(base[s], param, hi[s, 1], pb[s], axis[s], along_lo,
                                        along_hi)
        glo[s][glass] = 0.35
        if night:
            lit = glass & (rand < param[:, 5])
            emi[s][lit] = np.array([1.0, 0.78, 0.45], dtype=F32) * (
                0.35 + 0.5 * rand[lit] / param[lit, 5])[:, None]
    s = block(CAR)
    if s.stop > s.start:
        param = np.take(scene.param, bid[s], 0)
        alb[s], glass, head, tail = _car(base[s], param, pb[s], axis[s], sign[s], lo[s], hi[s])
        glo[s] = np.where(glass, 0.3, 0.06)
        lights_on = param[:, 1] > 0
        strength = {"night": 3.0, "fog": 1.2, "rain": 1.0}.get(cond, 0.0)
        emi[s][head & lights_on] = np.array([1.0, 0.97, 0.9], dtype=F32) * strength
        emi[s][tail & lights_on] = np.array([1.0, 0.08, 0.04], dtype=F32) * strength * 0.6
    s = block(GLASS)
    side = axis[s] != 1  # the cabin roof keeps the body colour
    alb[s][side] = (0.07, 0.09, 0.11)
    glo[s][side] = 0.3
    if night:
        emi[block(LAMP)] = (2.5, 2.2, 1.6)
    for material in (FOLIAGE, TRUNK):
        s = block(material)
        leaf = 0.75 + 0.45 * _tex(_NOISE, pb[s, 0] * 6 + pb[s, 2] * 6, pb[s, 1] * 6)
        alb[s] = base[s] * leaf[:, None]
    return albedo, normal, gloss, emit


def _night_lights(scene: Scene, pts: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Irradiance (H, W) from street lamps, the headlights of moving cars and the camera car's
    own headlights (spot lights), each evaluated only within its reach."""
    cars = np.flatnonzero((scene.material == CAR) & (scene.param[:, 1] > 0))
    facing = scene.param[cars, 0]
    front = np.stack([(scene.lo[cars, 0] + scene.hi[cars, 0]) / 2, np.full(len(cars), 0.7),
                      np.where(facing > 0, scene.hi[cars, 2] + 0.1, scene.lo[cars, 2] - 0.1)], 1)
    cam = scene.camera
    ego = np.array([[cam.position[0], 0.7, cam.position[2] + 1.5]])
    pos = np.concatenate([scene.lamps, front, ego]).astype(F32)
    axis = np.zeros_like(pos)  # zero: an omnidirectional lamp
    axis[len(scene.lamps):-1, 2] = facing
    axis[-1] = (np.sin(cam.yaw), 0.0, np.cos(cam.yaw))
    axis[len(scene.lamps):, 1] = -0.08  # headlights dip to the road
    axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-6)
    power = np.r_[np.full(len(scene.lamps), 28.0), np.full(len(cars), 60.0), 90.0]
    reach = np.r_[np.full(len(scene.lamps), 22.0), np.full(len(cars), 35.0), 50.0]
    centre = pos + axis * reach[:, None] / 2
    half = np.where(np.abs(axis) > 0.5, reach[:, None] / 2 + 1, reach[:, None])
    half[len(scene.lamps):, :2] *= 0.4
    lo, hi = centre - half, centre + half
    lo[:, 1] = np.minimum(lo[:, 1], 0.0)
    win = pixel_windows(box_corners(lo, hi), cam)
    px, py, pz = (pts[..., a] for a in range(3))
    nx, ny, nz = (normal[..., a] for a in range(3))
    total = np.zeros(pts.shape[:2], dtype=F32)
    for light, direction, watts, radius, (r0, r1, c0, c1) in zip(pos, axis, power, reach, win,
                                                                 strict=True):
        if r1 <= r0 or c1 <= c0:
            continue
        window = (slice(r0, r1), slice(c0, c1))
        vx, vy, vz = light[0] - px[window], light[1] - py[window], light[2] - pz[window]
        d2 = vx * vx + vy * vy + vz * vz + 0.3
        inv_d = 1 / np.sqrt(d2)
        gain = np.maximum(nx[window] * vx + ny[window] * vy + nz[window] * vz, 0) * inv_d
        gain *= np.maximum(1 - d2 / radius**2, 0) ** 2 / d2
        if direction.any():
            cos_a = -(vx * direction[0] + vy * direction[1] + vz * direction[2]) * inv_d
            gain *= np.clip((cos_a - 0.9) / 0.1, 0, 1) ** 2
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
        for offset in (0.26, -0.26):
            x = np.where(offset > 0, lo[:, 0] + offset, hi[:, 0] + offset)
            oncoming = facing < 0
            y = np.where(oncoming, 0.67, 0.78)
            pos.append(np.stack([x, y, lo[:, 2] - 0.02], 1))
            white = np.array([1.0, 0.97, 0.9], dtype=F32) * strength
            red = np.array([1.0, 0.1, 0.05], dtype=F32) * strength * 0.5
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
        image[r0:r1, c0:c1] += glow[..., None] * cc * fade


def _rain_streaks(image: np.ndarray, rng: np.random.Generator) -> None:
    """Bright, slanted motion-blurred drops in front of the camera."""
    h, w = image.shape[:2]
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
    alpha = np.clip(layer, 0, 0.35)[..., None]
    image *= 1 - alpha
    image += alpha * 0.85


def _contact_shadows(scene: Scene, pts: np.ndarray, ground: np.ndarray) -> np.ndarray:
    """Darkening of the ground under cars (ambient occlusion), per pixel (H, W)."""
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
        p = pts[r0:r1, c0:c1]
        dx = np.minimum(p[..., 0] - a[0], b[0] - p[..., 0])
        dz = np.minimum(p[..., 2] - a[2], b[2] - p[..., 2])
        inside = np.clip(np.minimum(dx, dz) / 0.4, 0, 1) * ground[r0:r1, c0:c1]
        occlusion[r0:r1, c0:c1] *= 1 - 0.6 * inside
    return occlusion


def shade(scene: Scene, dirs: np.ndarray, t: np.ndarray, ids: np.ndarray, weather: Weather,
          rng: np.random.Generator) -> np.ndarray:
    """RGB image (H, W, 3) in [0, 1] of a ray-cast scene under the given weather."""
    cam = scene.camera
    cond = weather.condition
    hit = ids != SKY_ID
    depth = np.where(hit, t, 0).astype(F32)
    pts = cam.position + dirs * depth[..., None]

    # Hit pixels sorted by material: ``pix`` are their flat indices.
    hit_idx = np.flatnonzero(hit)
    flat_ids = ids.reshape(-1)[hit_idx]
    key = np.where(flat_ids >= 0, scene.material[np.maximum(flat_ids, 0)], GROUND_ID)
    order = np.argsort(key, kind="stable")
    pix, key = hit_idx[order], key[order]
    edges = np.searchsorted(key, np.arange(GROUND_ID, N_MATERIALS + 1))
    blocks = {m: slice(edges[i], edges[i + 1]) for i, m in enumerate(range(GROUND_ID,
                                                                          N_MATERIALS))}
    p = pts.reshape(-1, 3)[pix]
    albedo, normal, gloss, emit = _surfaces(scene, p, dirs.reshape(-1, 3)[pix], flat_ids[order],
                                            blocks, weather)

    ambient, sun_power = {
        "day": ((0.40, 0.45, 0.55), 1.0),
        "cloudy": ((0.80, 0.80, 0.83), 0.18),
        "fog": ((0.82, 0.83, 0.85), 0.10),
        "rain": ((0.60, 0.62, 0.66), 0.06),
        "night": ((0.025, 0.028, 0.045), 0.0),
    }[cond]
    light = np.asarray(ambient, dtype=F32) * (0.65 + 0.35 * normal[:, 1:2])
    if sun_power:
        sun_dot = np.clip(normal @ scene.sun, 0, None)
        if cond == "day":
            sun_dot *= ~cast_shadows(scene, pts, hit).reshape(-1)[pix]
        light += (sun_power * np.array([1.05, 1.0, 0.92], dtype=F32)) * sun_dot[:, None]
    light *= _contact_shadows(scene, pts, ids == GROUND_ID).reshape(-1)[pix, None]
    if cond == "night":
        normal_img = np.zeros_like(pts)
        normal_img.reshape(-1, 3)[pix] = normal
        lamps = _night_lights(scene, pts, normal_img).reshape(-1)[pix]
        light += lamps[:, None] * np.array([1.0, 0.85, 0.62], dtype=F32)
    color = albedo * light + emit
    color += gloss[:, None] * (_horizon(weather) * (0.3 if cond == "night" else 1.0))
    transmit = np.exp(-weather.beta * (depth * cam.ray_lengths()).reshape(-1)[pix])[:, None]

    image = np.empty(pts.shape, dtype=F32)
    image[~hit] = _sky(dirs[~hit], weather, rng)
    image.reshape(-1, 3)[pix] = color * transmit + weather.haze * (1 - transmit)
    _add_glare(image, depth, scene, weather)
    if cond == "rain":
        _rain_streaks(image, rng)
    image *= weather.exposure
    if cond == "night":
        image *= rng.uniform(1.1, 1.5)  # auto exposure lifts the dark frame, and its noise
        sigma = 0.012 + 0.035 * np.sqrt(np.clip(image, 0, 1))
        image += rng.standard_normal(image.shape, dtype=F32) * sigma
        image += rng.standard_normal(image.shape[:2] + (1,), dtype=F32) * 0.01
    else:
        image += rng.standard_normal(image.shape, dtype=F32) * 0.006
    if cond == "cloudy":
        image = 0.8 * image + 0.2 * image.mean(-1, keepdims=True)
    return np.clip(image, 0.0, 1.0)
