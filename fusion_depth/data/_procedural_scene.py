"""Street-scene layout and analytic ray casting for :mod:`fusion_depth.data.procedural`.

World frame: X right, Y up, Z forward along the road, ground plane Y = 0, camera near the origin.
A scene is the ground plane plus axis-aligned boxes, which keeps exact depth cheap: each box is
intersected with the slab method, vectorised over the pixels its projection can cover.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

MAX_DEPTH = 250.0  # the world ends here, so depth fits the cache's uint16 1/256 m format
NEAR = 0.05
SKY_ID = -2  # per-pixel hit ids: a box index, or one of these two
GROUND_ID = -1

# Box materials.
SIDEWALK, BUILDING, CAR, GLASS, POLE, LAMP, SIGN, TRUNK, FOLIAGE = range(9)
N_MATERIALS = 9

# Meaning of the per-box ``param`` columns, by material.
# BUILDING: floor height, window width, window spacing, window height, shop front (0/1),
#           share of windows lit at night, building id, window phase.
# CAR (body) and GLASS (cabin): facing (+1 drives away from the camera, -1 towards it),
#           lights on (0/1), front axle z, rear axle z, glass band low, glass band high (0: a
#           car, whose glass is the cabin box), wheel radius.
N_PARAM = 8

_BUILDING_COLOURS = np.array(
    [
        [0.76, 0.68, 0.55],
        [0.56, 0.31, 0.23],
        [0.60, 0.60, 0.62],
        [0.85, 0.84, 0.80],
        [0.36, 0.37, 0.40],
        [0.82, 0.76, 0.60],
        [0.46, 0.51, 0.58],
        [0.70, 0.46, 0.31],
        [0.66, 0.58, 0.50],
        [0.52, 0.48, 0.44],
    ],
    dtype=np.float32,
)
_CAR_COLOURS = np.array(
    [
        [0.88, 0.88, 0.88],
        [0.08, 0.08, 0.09],
        [0.62, 0.63, 0.65],
        [0.35, 0.36, 0.38],
        [0.62, 0.08, 0.07],
        [0.12, 0.22, 0.50],
        [0.10, 0.13, 0.25],
        [0.18, 0.35, 0.22],
        [0.85, 0.68, 0.12],
        [0.45, 0.30, 0.20],
    ],
    dtype=np.float32,
)
_CAR_COLOUR_CDF = np.cumsum([0.2, 0.18, 0.17, 0.12, 0.08, 0.08, 0.06, 0.04, 0.03, 0.04])[:-1]
_SIGN_COLOURS = np.array(
    [[0.10, 0.25, 0.65], [0.75, 0.10, 0.10], [0.90, 0.90, 0.88], [0.90, 0.70, 0.10]],
    dtype=np.float32,
)
_WHITE_PAINT = (0.86, 0.86, 0.82)
_YELLOW_PAINT = (0.86, 0.70, 0.22)


@dataclass(frozen=True)
class Camera:
    """Pinhole camera; ``rotation`` maps camera axes (x right, y down, z forward) to world."""

    height: int
    width: int
    focal: float
    position: np.ndarray
    rotation: np.ndarray
    yaw: float

    def _grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame x/z and y/z of the pixel centres: columns (W,) and rows (H,)."""
        cols = (np.arange(self.width, dtype=np.float32) + 0.5 - self.width / 2) / self.focal
        rows = (np.arange(self.height, dtype=np.float32) + 0.5 - self.height / 2) / self.focal
        return cols, rows

    def rays(self) -> np.ndarray:
        """World ray directions (3, H, W) scaled so that the ray parameter is camera z."""
        cols, rows = self._grid()
        cam = np.empty((3, self.height, self.width), dtype=np.float32)
        cam[0] = cols[None, :]
        cam[1] = rows[:, None]
        cam[2] = 1.0
        d = np.einsum("ij,jhw->ihw", self.rotation.astype(np.float32), cam)
        d[np.abs(d) < 1e-6] = 1e-6  # the slab method divides by every component
        return d

    def ray_lengths(self) -> np.ndarray:
        """Length (H, W) of the ``rays()`` directions: range = depth * length."""
        cols, rows = self._grid()
        return np.sqrt(1 + cols[None, :] ** 2 + rows[:, None] ** 2)

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) in camera coordinates."""
        return (points - self.position) @ self.rotation

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Continuous pixel coordinates (u, v) and camera z of world points (pixel i spans
        [i, i+1)); points behind the camera get z <= 0 and meaningless u, v."""
        pc = self.to_camera(points)
        z = pc[..., 2]
        safe = np.where(z > NEAR, z, 1.0)
        u = self.focal * pc[..., 0] / safe + self.width / 2
        v = self.focal * pc[..., 1] / safe + self.height / 2
        return u, v, z


@dataclass(frozen=True)
class Scene:
    """One frame's geometry and the layout facts the renderer and sensors need."""

    camera: Camera
    lo: np.ndarray  # (N, 3) box minimum corners
    hi: np.ndarray  # (N, 3) box maximum corners
    material: np.ndarray  # (N,)
    color: np.ndarray  # (N, 3) base albedo
    param: np.ndarray  # (N, N_PARAM), see the table above
    road: tuple[float, float]  # kerb-to-kerb X extent
    asphalt: float  # base grey of the road
    markings: np.ndarray  # (M, 5): x centre, half width, dash length, period, phase
    marking_color: np.ndarray  # (M, 3)
    verge_color: np.ndarray  # (2, 3): ground colour left / right of the sidewalks
    lamps: np.ndarray  # (L, 3) street-light positions
    sun: np.ndarray  # (3,) unit vector towards the sun


class _Boxes:
    """Accumulates boxes while a layout is sampled."""

    def __init__(self) -> None:
        self.lo: list[tuple[float, float, float]] = []
        self.hi: list[tuple[float, float, float]] = []
        self.material: list[int] = []
        self.color: list[np.ndarray] = []
        self.param: list[list[float]] = []

    def add(
        self,
        lo: tuple[float, float, float],
        hi: tuple[float, float, float],
        material: int,
        color: Sequence[float] | np.ndarray,
        param: Sequence[float] = (),
    ) -> None:
        self.lo.append(lo)
        self.hi.append(hi)
        self.material.append(material)
        self.color.append(np.asarray(color, dtype=np.float32))
        self.param.append(list(param) + [0.0] * (N_PARAM - len(param)))


def _camera(
    rng: np.random.Generator,
    height: int,
    width: int,
    fov_deg: float,
    camera_height: tuple[float, float] = (1.4, 1.7),
) -> Camera:
    """A dash camera ``camera_height`` metres up (drawn uniformly; a car's 1.4-1.7 m by
    default) with a little random pitch, yaw and roll."""
    pitch, yaw, roll = np.radians(
        [rng.uniform(-1.0, 2.5), rng.uniform(-4.0, 4.0), rng.uniform(-1.0, 1.0)]
    )
    c, s = np.cos(yaw), np.sin(yaw)
    r_yaw = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    c, s = np.cos(pitch), np.sin(pitch)
    r_pitch = np.array([[1, 0, 0], [0, c, s], [0, -s, c]])  # positive looks down
    c, s = np.cos(roll), np.sin(roll)
    r_roll = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    flip = np.diag([1.0, -1.0, 1.0])  # camera y points down, world Y up
    rotation = (r_yaw @ flip @ r_pitch @ r_roll).astype(np.float32)
    focal = width / 2 / np.tan(np.radians(fov_deg) / 2)
    position = np.array([0.0, rng.uniform(*camera_height), 0.0], dtype=np.float32)
    return Camera(height, width, float(focal), position, rotation, float(yaw))


def _add_car(
    boxes: _Boxes,
    rng: np.random.Generator,
    x: float,
    z0: float,
    facing: int,
    moving: bool,
    allow_large: bool,
) -> float:
    """Adds a car, van or bus whose rear-most edge (smallest Z) is at ``z0``; returns its length.

    Cars are a body box and a glass cabin box; vans and buses a single tall box whose glass band
    is drawn by the renderer.
    """
    kind_draw, color_draw = rng.random(2)
    kind = int(kind_draw > 0.8) + int(allow_large and kind_draw > 0.95)  # car, van, bus
    color = _CAR_COLOURS[np.searchsorted(_CAR_COLOUR_CDF, color_draw)]
    color = color * rng.uniform(0.9, 1.1)  # palette and jitter keep it within [0, 1]
    if kind == 0:
        length, width = rng.uniform(3.8, 4.9), rng.uniform(1.7, 1.95)
        top, wheel = rng.uniform(0.95, 1.15), 0.32
        glass = (0.0, 0.0)
    elif kind == 1:
        length, width = rng.uniform(4.8, 6.0), rng.uniform(1.9, 2.1)
        top, wheel = rng.uniform(1.9, 2.5), 0.35
        glass = (top - 0.8, top - 0.2)
    else:
        length, width = rng.uniform(9.0, 12.0), 2.5
        top, wheel = rng.uniform(2.9, 3.3), 0.5
        glass = (1.3, top - 0.35)
    axle = 0.8 if kind < 2 else 2.2
    x0, x1, z1 = x - width / 2, x + width / 2, z0 + length
    front, rear = (z1 - axle, z0 + axle) if facing > 0 else (z0 + axle, z1 - axle)
    param = (facing, float(moving), front, rear, glass[0], glass[1], wheel)
    boxes.add((x0, 0.18, z0), (x1, top, z1), CAR, color, param)
    if kind == 0:
        cabin_len = length * rng.uniform(0.45, 0.58)
        offset = length * rng.uniform(0.15, 0.25)  # cabin sits towards the rear
        c0 = z0 + offset if facing > 0 else z1 - offset - cabin_len
        inset = rng.uniform(0.08, 0.15)
        cabin_top = top + rng.uniform(0.38, 0.55)
        boxes.add(
            (x0 + inset, top, c0), (x1 - inset, cabin_top, c0 + cabin_len), GLASS, color, param
        )
    return float(length)


def _buildings(
    boxes: _Boxes,
    rng: np.random.Generator,
    side: int,
    edge: float,
    z_end: float,
    first_id: int,
) -> int:
    """A row of facades with varying setback, length, height and gaps along one side of the
    street; returns the next free building id."""
    street_height = rng.uniform(6.0, 28.0)
    setback_scale = rng.uniform(0.0, 8.0)
    z = rng.uniform(-40.0, -10.0)
    bid = first_id
    while z < z_end:
        length = rng.uniform(6.0, 28.0)
        if rng.random() < 0.15:  # alley or side street
            z += rng.uniform(4.0, 16.0)
            continue
        setback = 0.0 if rng.random() < 0.4 else rng.uniform(0.3, 1.0) * setback_scale
        depth = rng.uniform(8.0, 20.0)
        height = min(max(street_height * rng.uniform(0.5, 1.5), 3.5), 45.0)
        face = edge + side * setback
        x0, x1 = (face - depth, face) if side < 0 else (face, face + depth)
        z1 = min(z + length, z_end)
        _add_building(boxes, rng, (x0, 0.0, z), (x1, height, z1), bid)
        bid += 1
        z = z1 + (0.0 if rng.random() < 0.6 else rng.uniform(0.5, 3.0))
    return bid


def _add_building(
    boxes: _Boxes,
    rng: np.random.Generator,
    lo: tuple[float, float, float],
    hi: tuple[float, float, float],
    bid: int,
) -> None:
    """A facade box with its colour and window layout."""
    color = _BUILDING_COLOURS[rng.integers(len(_BUILDING_COLOURS))]
    color = color * rng.uniform(0.85, 1.1) + rng.uniform(-0.04, 0.04, 3)  # stays in (0, 1)
    floor = rng.uniform(2.9, 3.6)
    win_w = rng.uniform(0.7, 1.5)
    spacing = rng.uniform(max(win_w + 0.6, 1.8), 3.8)
    win_h = rng.uniform(1.0, min(1.8, floor - 0.9))
    param = (
        floor,
        win_w,
        spacing,
        win_h,
        float(rng.random() < 0.5),
        rng.uniform(0.15, 0.6),
        bid,
        rng.uniform(0.0, spacing),
    )
    boxes.add(lo, hi, BUILDING, color, param)


def _street_furniture(
    boxes: _Boxes,
    rng: np.random.Generator,
    side: int,
    kerb: float,
    sidewalk: float,
    curb: float,
    lamps: list[tuple[float, float, float]],
) -> None:
    """Street lights, signs and trees on one sidewalk (``side`` -1 left, +1 right)."""
    if rng.random() < 0.85:
        spacing = rng.uniform(18.0, 35.0)
        height, arm = rng.uniform(5.5, 8.5), rng.uniform(1.0, 2.5)
        x = kerb + side * 0.5
        z = rng.uniform(-5.0, spacing)
        grey = np.full(3, rng.uniform(0.3, 0.5), dtype=np.float32)
        while z < 170.0:
            boxes.add((x - 0.08, 0.0, z - 0.08), (x + 0.08, height, z + 0.08), POLE, grey)
            tip = x - side * arm
            ax0, ax1 = sorted((x, tip))
            boxes.add((ax0, height - 0.12, z - 0.05), (ax1, height, z + 0.05), POLE, grey)
            boxes.add(
                (tip - 0.3, height - 0.3, z - 0.18),
                (tip + 0.3, height - 0.05, z + 0.18),
                LAMP,
                grey,
            )
            lamps.append((tip, height - 0.35, z))
            z += spacing * rng.uniform(0.9, 1.1)
    for _ in range(rng.poisson(1.2)):
        x, z = kerb + side * rng.uniform(0.3, 0.8), rng.uniform(3.0, 80.0)
        color = _SIGN_COLOURS[rng.integers(len(_SIGN_COLOURS))]
        boxes.add((x - 0.04, 0.0, z - 0.04), (x + 0.04, 2.7, z + 0.04), POLE, (0.5, 0.5, 0.5))
        boxes.add((x - 0.32, 2.05, z - 0.06), (x + 0.32, 2.7, z - 0.03), SIGN, color)
    if sidewalk > 2.5 and rng.random() < 0.5:
        x = kerb + side * sidewalk * rng.uniform(0.55, 0.7)
        z = rng.uniform(-5.0, 10.0)
        green = np.array([0.17, 0.32, 0.12]) * rng.uniform(0.8, 1.25, 3)
        while z < 130.0:
            trunk = rng.uniform(2.0, 3.2)
            boxes.add(
                (x - 0.15, curb, z - 0.15), (x + 0.15, trunk, z + 0.15), TRUNK, (0.30, 0.22, 0.15)
            )
            half = rng.uniform(1.0, min(1.8, sidewalk * 0.8))
            boxes.add(
                (x - half, trunk, z - half),
                (x + half, trunk + rng.uniform(2.0, 4.0), z + half),
                FOLIAGE,
                green,
            )
            z += rng.uniform(7.0, 15.0)


@dataclass(frozen=True)
class _Lanes:
    """The street's cross-section: lanes, parking strips and the road's kerb-to-kerb extent."""

    lane: float  # lane width
    n_same: int  # lanes in the camera's direction
    n_opp: int  # lanes in the opposite direction (0: one-way)
    park: np.ndarray  # (2,) bool: a parking strip on the left / right
    ego: int  # the camera's lane among the n_same
    centre: float  # X of the line between the two directions
    travel: tuple[float, float]  # X extent of the travel lanes
    road: tuple[float, float]  # X extent of travel lanes and parking strips


def _lanes(rng: np.random.Generator) -> _Lanes:
    """Samples lane counts and widths, parking strips and where the camera drives."""
    lane = rng.uniform(3.0, 3.7)
    n_same, n_opp = int(rng.integers(1, 3)), int(rng.integers(0, 3))  # n_opp 0: one-way
    park = rng.random(2) < (0.7, 0.8)
    park_w = rng.uniform(2.1, 2.6)
    ego = int(rng.integers(n_same))
    centre = -(ego + 0.5) * lane + rng.uniform(-0.4, 0.4)  # the camera drives at X ~ 0
    travel = (centre - n_opp * lane, centre + n_same * lane)
    road = (travel[0] - park[0] * park_w, travel[1] + park[1] * park_w)
    return _Lanes(lane, n_same, n_opp, park, ego, centre, travel, road)


def _markings(
    rng: np.random.Generator, lanes: _Lanes
) -> tuple[list[tuple[float, float, float, float, float]], list[tuple[float, float, float]]]:
    """Centre line, lane dividers and edge lines: rows of ``Scene.markings`` and their colours."""
    marks: list[tuple[float, float, float, float, float]] = []
    mark_colors: list[tuple[float, float, float]] = []
    centre, lane = lanes.centre, lanes.lane
    dash = rng.uniform(2.0, 4.0)
    period, phase = dash * rng.uniform(2.5, 4.0), rng.uniform(0.0, 10.0)
    if lanes.n_opp > 0:
        if rng.random() < 0.5:  # double yellow
            for off in (-0.12, 0.12):
                marks.append((centre + off, 0.05, 1.0, 1.0, 0.0))
                mark_colors.append(_YELLOW_PAINT)
        else:
            marks.append((centre, 0.07, dash, period, phase))
            mark_colors.append(_WHITE_PAINT)
    for k in [*range(1, lanes.n_same), *range(-lanes.n_opp + 1, 0)]:
        marks.append((centre + k * lane, 0.07, dash, period, phase))
        mark_colors.append(_WHITE_PAINT)
    for x in lanes.travel:
        if rng.random() < 0.7:
            marks.append((x, 0.06, 1.0, 1.0, 0.0))
            mark_colors.append(_WHITE_PAINT)
    return marks, mark_colors


def _sidewalks_and_buildings(
    boxes: _Boxes, rng: np.random.Generator, road: tuple[float, float]
) -> tuple[float, np.ndarray, float]:
    """Sidewalks, facades, maybe a T-junction; returns kerb height, walk widths, street end."""
    curb = rng.uniform(0.1, 0.2)
    walks = rng.uniform(1.8, 5.0, 2)
    concrete = np.array([1.0, 1.0, 0.97]) * rng.uniform(0.5, 0.68)
    junction = rng.random() < 0.3
    z_end = rng.uniform(45.0, 200.0) if junction else MAX_DEPTH - 15.0
    street_end = z_end - rng.uniform(10.0, 14.0) if junction else z_end
    boxes.add((road[0] - walks[0], 0.0, -30.0), (road[0], curb, street_end), SIDEWALK, concrete)
    boxes.add((road[1], 0.0, -30.0), (road[1] + walks[1], curb, street_end), SIDEWALK, concrete)
    bid = _buildings(boxes, rng, -1, road[0] - walks[0], street_end, 0)
    bid = _buildings(boxes, rng, 1, road[1] + walks[1], street_end, bid)
    if junction:  # a T-junction: the street ends at a facade across it
        boxes.add((-80.0, 0.0, z_end - 3.0), (80.0, curb, z_end), SIDEWALK, concrete)
        _add_building(
            boxes, rng, (-80.0, 0.0, z_end), (80.0, rng.uniform(8.0, 35.0), z_end + 20.0), bid
        )
    return curb, walks, street_end


def _parked_cars(boxes: _Boxes, rng: np.random.Generator, lanes: _Lanes, street_end: float) -> None:
    """Rows of parked cars along the kerbs that have a parking strip."""
    for side, kerb in ((-1, lanes.road[0]), (1, lanes.road[1])):
        if not lanes.park[(side + 1) // 2]:
            continue
        occupancy = rng.uniform(0.3, 0.95)
        z = rng.uniform(-12.0, 0.0)
        while z < min(150.0, street_end - 6.0):
            if rng.random() > occupancy:
                z += rng.uniform(3.0, 8.0)
                continue
            usual = side if lanes.n_opp > 0 else 1
            facing = usual if rng.random() < 0.85 else -usual
            x = kerb - side * (0.25 + 0.95)
            z += _add_car(boxes, rng, x, z, facing, False, False)
            z += rng.uniform(0.6, 2.5)


def _traffic(boxes: _Boxes, rng: np.random.Generator, lanes: _Lanes, street_end: float) -> None:
    """Moving cars, vans and buses in every travel lane, light or dense."""
    gap_scale = rng.uniform(10.0, 50.0)  # light or dense traffic
    for k in range(-lanes.n_opp, lanes.n_same):
        facing = 1 if k >= 0 else -1
        x_lane = lanes.centre + (k + 0.5) * lanes.lane
        z = rng.uniform(7.0, 30.0) if k == lanes.ego else rng.uniform(-4.0, 30.0)
        while z < min(180.0, street_end - 12.0):
            x = x_lane + rng.uniform(-0.25, 0.25)
            z += _add_car(boxes, rng, x, z, facing, True, True)
            z += rng.uniform(5.0, 1.0 + 2.0 * gap_scale)


def _verge_and_sun(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Ground colours beyond the two sidewalks, and the unit vector towards the sun."""
    verge = np.array(
        [[0.28, 0.40, 0.18] if rng.random() < 0.4 else [0.48, 0.46, 0.43] for _ in range(2)],
        dtype=np.float32,
    ) * rng.uniform(0.8, 1.15)
    elevation, azimuth = np.radians(rng.uniform(20.0, 65.0)), rng.uniform(0.0, 2 * np.pi)
    sun = np.array(
        [
            np.cos(elevation) * np.sin(azimuth),
            np.sin(elevation),
            np.cos(elevation) * np.cos(azimuth),
        ],
        dtype=np.float32,
    )
    sun[np.abs(sun) < 1e-4] = 1e-4  # the shadow caster divides by every component
    return verge, sun


def sample_scene(
    rng: np.random.Generator,
    height: int,
    width: int,
    fov_deg: float,
    camera_height: tuple[float, float] = (1.4, 1.7),
) -> Scene:
    """Samples one street: lanes, sidewalks, facades, parked and moving cars, furniture, sun,
    seen from a camera ``camera_height`` metres up (the range it is drawn from)."""
    # Every helper draws from ``rng`` in turn; this order fixes the built-in dataset's frames.
    boxes = _Boxes()
    lamps: list[tuple[float, float, float]] = []
    camera = _camera(rng, height, width, fov_deg, camera_height)
    lanes = _lanes(rng)
    road = lanes.road
    marks, mark_colors = _markings(rng, lanes)
    curb, walks, street_end = _sidewalks_and_buildings(boxes, rng, road)
    _parked_cars(boxes, rng, lanes, street_end)
    _traffic(boxes, rng, lanes, street_end)
    for side, kerb in ((-1, road[0]), (1, road[1])):
        _street_furniture(boxes, rng, side, kerb, walks[(side + 1) // 2], curb, lamps)
    verge, sun = _verge_and_sun(rng)
    return Scene(
        camera=camera,
        lo=np.asarray(boxes.lo, dtype=np.float32),
        hi=np.asarray(boxes.hi, dtype=np.float32),
        material=np.asarray(boxes.material, dtype=np.int16),
        color=np.asarray(boxes.color, dtype=np.float32),
        param=np.asarray(boxes.param, dtype=np.float32),
        road=(float(road[0]), float(road[1])),
        asphalt=float(rng.uniform(0.24, 0.36)),  # the last draw
        markings=np.asarray(marks, dtype=np.float32).reshape(-1, 5),
        marking_color=np.asarray(mark_colors, dtype=np.float32).reshape(-1, 3),
        verge_color=verge,
        lamps=np.asarray(lamps, dtype=np.float32).reshape(-1, 3),
        sun=sun,
    )


def box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The 8 corners (N, 8, 3) of boxes."""
    pick = ((np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1).astype(bool)
    return np.where(pick[None], hi[:, None, :], lo[:, None, :])


def pixel_windows(points: np.ndarray, camera: Camera) -> np.ndarray:
    """Pixel rectangles (N, 4: row0, row1, col0, col1) covering the projections of the convex
    hulls of point sets (N, K, 3). Hulls crossing the camera plane are clipped to the part in
    front of it (segments between the points are cut at z = NEAR)."""
    pc = camera.to_camera(points.astype(np.float64))
    z = pc[..., 2]
    front = z > NEAR
    straddle = np.flatnonzero(front.any(1) & ~front.all(1))
    if len(straddle):
        i, j = np.triu_indices(points.shape[1], 1)
        a, b = pc[straddle][:, i], pc[straddle][:, j]
        za, zb = a[..., 2], b[..., 2]
        crosses = (za > NEAR) != (zb > NEAR)
        f = np.where(crosses, (NEAR * 1.001 - za) / np.where(crosses, zb - za, 1.0), 0.0)
        cut = a + (b - a) * f[..., None]
        extra = np.zeros((len(points), len(i), 3))
        extra[straddle] = np.where(crosses[..., None], cut, (0.0, 0.0, -1.0))
        extra[np.setdiff1d(np.arange(len(points)), straddle), :, 2] = -1.0
        pc = np.concatenate([pc, extra], 1)
        z = pc[..., 2]
        front = z > NEAR
    safe = np.where(front, z, 1.0)
    u = camera.focal * pc[..., 0] / safe + camera.width / 2
    v = camera.focal * pc[..., 1] / safe + camera.height / 2
    big = 1e9
    h, w = camera.height, camera.width
    win = np.stack(
        [
            np.floor(np.where(front, v, big).min(1)) - 1,
            np.ceil(np.where(front, v, -big).max(1)) + 1,
            np.floor(np.where(front, u, big).min(1)) - 1,
            np.ceil(np.where(front, u, -big).max(1)) + 1,
        ],
        1,
    )
    return np.clip(win, 0, [h, h, w, w]).astype(np.int64)


SMALL_WINDOW = 1024  # boxes covering fewer pixels are cast together, not one by one


def cast_primary(scene: Scene, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit per pixel: camera z ``t`` (inf for sky) and hit id (box index, GROUND_ID or
    SKY_ID) of rays (3, H, W). Nothing beyond MAX_DEPTH is hit.

    Slab method with the camera outside every box. Boxes covering a large window are cast one
    at a time: along an axis where the camera lies outside the slab, the entry/exit planes are
    known without comparing (a ray going the wrong way gets a negative exit and misses); where
    it lies inside, only the exit matters. The many small, distant boxes are cast in one
    vectorised batch of (pixel, box) pairs, which saves the per-box overhead.
    """
    origin = scene.camera.position
    dy = dirs[1]
    with np.errstate(divide="ignore"):
        t_ground = -origin[1] / dy
    t = np.where((dy < 0) & (t_ground <= MAX_DEPTH), t_ground, np.inf).astype(np.float32)
    ids = np.where(np.isfinite(t), GROUND_ID, SKY_ID).astype(np.int32)
    inv = 1.0 / dirs
    rel_lo, rel_hi = scene.lo - origin, scene.hi - origin
    win = pixel_windows(box_corners(scene.lo, scene.hi), scene.camera)
    area = np.maximum(win[:, 1] - win[:, 0], 0) * np.maximum(win[:, 3] - win[:, 2], 0)
    for k in np.flatnonzero(area > SMALL_WINDOW):
        r0, r1, c0, c1 = win[k]
        t_near = t_far = None
        for a in range(3):
            lo, hi = rel_lo[k, a], rel_hi[k, a]
            iv = inv[a][r0:r1, c0:c1]
            if lo > 0 or hi < 0:
                near, far = (lo, hi) if lo > 0 else (hi, lo)
                enter, leave = near * iv, far * iv
                t_near = enter if t_near is None else np.maximum(t_near, enter)
            else:
                leave = np.maximum(lo * iv, hi * iv)
            t_far = leave if t_far is None else np.minimum(t_far, leave)
        t_box = t[r0:r1, c0:c1]
        hit = (t_near <= t_far) & (t_near > NEAR) & (t_near < t_box)
        if hit.any():
            t_box[hit] = t_near[hit]
            ids[r0:r1, c0:c1][hit] = k
    _cast_small(
        t, ids, inv, rel_lo, rel_hi, win, np.flatnonzero((area > 0) & (area <= SMALL_WINDOW))
    )
    far = t > MAX_DEPTH
    t[far], ids[far] = np.inf, SKY_ID
    return t, ids


def _cast_small(
    t: np.ndarray,
    ids: np.ndarray,
    inv: np.ndarray,
    rel_lo: np.ndarray,
    rel_hi: np.ndarray,
    win: np.ndarray,
    boxes: np.ndarray,
) -> None:
    """Casts the rays of every pixel in the windows of ``boxes`` against its box at once and
    keeps, per pixel, the nearest hit if it beats the current ``t`` (updated in place)."""
    if not len(boxes):
        return
    r0, r1, c0, c1 = win[boxes].T
    widths, areas = c1 - c0, (r1 - r0) * (c1 - c0)
    owner = np.repeat(boxes, areas)
    local = np.arange(areas.sum()) - np.repeat(np.cumsum(areas) - areas, areas)
    width = np.repeat(widths, areas)
    pix = (
        (np.repeat(r0, areas) + local // width) * t.shape[1] + np.repeat(c0, areas) + local % width
    )
    t_near, t_far = None, None
    for a in range(3):
        iv = inv[a].reshape(-1)[pix]
        t1, t2 = rel_lo[owner, a] * iv, rel_hi[owner, a] * iv
        enter, leave = np.minimum(t1, t2), np.maximum(t1, t2)
        t_near = enter if t_near is None else np.maximum(t_near, enter)
        t_far = leave if t_far is None else np.minimum(t_far, leave)
    hit = np.flatnonzero((t_near <= t_far) & (t_near > NEAR))
    order = hit[np.lexsort((t_near[hit], pix[hit]))]  # by pixel, nearest first
    first = order[np.r_[True, pix[order][1:] != pix[order][:-1]]]
    pix, t_near, owner = pix[first], t_near[first], owner[first]
    flat_t, flat_ids = t.reshape(-1), ids.reshape(-1)
    better = t_near < flat_t[pix]
    flat_t[pix[better]] = t_near[better]
    flat_ids[pix[better]] = owner[better]


def cast_shadows(scene: Scene, points: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Which surface points (3, H, W) are in a box's shadow from the sun.

    Only pixels inside the projected hull of a box and its ground shadow are tested against it,
    which bounds every point that box can shade. The sun's direction is the same for every
    pixel, so each slab's entry and exit planes are fixed.
    """
    sun = scene.sun
    corners = box_corners(scene.lo, scene.hi)
    ground = corners - sun * (corners[..., 1:2] / sun[1])
    win = pixel_windows(np.concatenate([corners, ground], 1), scene.camera)
    shadow = np.zeros(valid.shape, dtype=bool)
    for k in np.flatnonzero((win[:, 1] > win[:, 0]) & (win[:, 3] > win[:, 2])):
        r0, r1, c0, c1 = win[k]
        t_near = t_far = None
        for a in range(3):
            inv = 1.0 / sun[a]
            near, far = (
                (scene.lo[k, a], scene.hi[k, a]) if inv > 0 else (scene.hi[k, a], scene.lo[k, a])
            )
            p = points[a, r0:r1, c0:c1]
            enter, leave = (near - p) * inv, (far - p) * inv
            t_near = enter if t_near is None else np.maximum(t_near, enter)
            t_far = leave if t_far is None else np.minimum(t_far, leave)
        shadow[r0:r1, c0:c1] |= (t_near <= t_far) & (t_near > 1e-3)
    return shadow & valid
