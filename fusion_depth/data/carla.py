"""``dataset=carla``: CARLA recordings, the paper's synthetic camera + radar set.

Folder format
-------------
Written as-is by a CARLA client (``scripts/record_carla.py`` does exactly this); one folder per
split, one file per sensor and frame, all named by the frame's name (CARLA's frame number,
zero-padded, e.g. ``00012345``)::

    <root>/
      train/  val/  test/               the three splits, each laid out as
        rgb/<frame>.png                 camera image, 8-bit RGB or RGBA PNG
        depth/<frame>.png               depth camera, CARLA's raw encoding (see below)
        radar/<frame>.csv               radar detections, header ``depth,azimuth,altitude,velocity``
        meta/<frame>.json               field of view, radar pose, weather; written last

* **rgb**: what ``carla.Image.save_to_disk(path)`` writes for ``sensor.camera.rgb``. The sensor's
  ``raw_data`` is BGRA; ``save_to_disk`` (and the recorder) store it as a PNG in the usual RGB
  channel order. Alpha, if present, is ignored.
* **depth**: ``sensor.camera.depth`` at the RGB camera's pose, resolution and field of view, saved
  *without* a colour converter (``save_to_disk(path)`` or ``carla.ColorConverter.Raw``; the
  ``Depth``/``LogarithmicDepth`` converters produce lossy grey images and are rejected). Metres
  are ``1000 * (R + G*256 + B*256**2) / (256**3 - 1)``: planar depth along the camera's forward
  axis, 1000 m at the far plane (the sky).
* **radar**: one row per ``carla.RadarDetection``, values as CARLA gives them: ``depth`` (m,
  range from the sensor), ``azimuth`` and ``altitude`` (radians), ``velocity`` (m/s, as CARLA
  reports it; kept, not used by the network). A header-only file is a frame without detections.
  A row holding NaN or an infinity (``nan``, ``inf``, or a number too large for a float) is not
  a measurement: it is dropped, with a warning naming the file. A negative depth, a row that is
  not four numbers, or another header is an error naming the file and line.
* **meta**: ``{"fov": 90.0, "condition": "ClearNoon", "radar_to_camera": {"location": {"x", "y",
  "z"}, "rotation": {"pitch", "yaw", "roll"}}}``: ``fov`` is the camera's horizontal field of
  view in degrees (its ``fov`` attribute); ``condition`` is the weather preset's name (or a plain
  condition name, see :func:`condition_of`); ``radar_to_camera`` is the radar's pose in the
  camera's frame as a ``carla.Transform`` (metres and degrees), i.e. the transform whose matrix
  maps radar-frame points to camera-frame points. Other keys are ignored.

Frames are the names in ``meta/`` (``<frame>.json``); a frame whose image, depth or radar file is
missing is an error naming it (FileNotFoundError), and one whose file is corrupt, truncated, in
the wrong format or bit depth, or of another size than the camera image is a
:class:`~fusion_depth.data.depth_io.DataFileError` naming it. A directory (or a dangling link)
where a frame's file should be, its ``.json`` included, is an IsADirectoryError
(FileNotFoundError) naming the path, never a frame dropped quietly. Missing files, directories
and metadata are checked while listing the recording, so for training (``on_error="raise"``) the
first one fails before anything is prepared; ``python -m fusion_depth.prepare``
(``on_error="skip"``) counts such a frame as skipped, like one with a corrupt file, and prepares
the others (:mod:`fusion_depth.data.cache`). Files starting with ``.`` (temporary files) are
ignored.

Geometry
--------
CARLA (Unreal Engine 4) is left-handed: x forward, y right, z up, in metres. A detection at
``(depth d, azimuth az, altitude alt)`` sits at ``x = d cos(alt) cos(az)``, ``y = d cos(alt)
sin(az)``, ``z = d sin(alt)`` in the radar frame (positive azimuth: to the right; positive
altitude: up). ``radar_to_camera`` maps it to the camera frame with the matrix of
``carla.Transform.get_matrix()`` (:func:`transform_matrix`; pitch about y, nose up positive; yaw
about z, to the right positive; roll about x; degrees). The camera is a pinhole with square
pixels: focal ``f = W / (2 tan(fov / 2))`` and the principal point at the image centre. With pixel
centres at integers (every reader's convention,
:func:`~fusion_depth.data.radar_points.pixel_index`) the centre is ``((W - 1) / 2, (H - 1) / 2)``,
and a camera-frame point lands at
``u = (W - 1) / 2 + f y / x`` (right), ``v = (H - 1) / 2 - f z / x`` (down), in pixel
``(round(v), round(u))``, with depth ``x``: the same forward distance the depth camera encodes.
Points behind the camera, at or beyond ``max_range``, or outside the image are dropped; where two
detections land on one pixel the nearer wins. The detections that land in the image are also
served as ``radar_points`` (:data:`~fusion_depth.data.RADAR_POINT_FIELDS`: ``u, v`` as above,
``depth`` = x, ``velocity`` from the CSV, ``rcs`` 0), the nearest ``max_radar_points``.

Conditions
----------
:func:`condition_of` maps CARLA's weather presets onto the platform's five conditions by the words
in their names, first match wins:

* ``Night`` -> night (``ClearNight``, ``HardRainNight``: darkness changes the image most)
* ``Fog``, ``Foggy``, ``Dust``, ``Mist`` -> fog (``FoggyNoon``, the recorder's; ``DustStorm``)
* ``Rain``, ``Rainy`` -> rain (``HardRainNoon``, ``MidRainyNoon``, ``SoftRainSunset``)
* ``Cloudy``, ``Overcast`` -> cloudy (``CloudyNoon``, ``WetCloudySunset``)
* ``Clear``, ``Wet``, ``Noon``, ``Sunset``, ``Morning``, ``Day`` -> day (``ClearNoon``,
  ``WetSunset``: a wet road in daylight is still day)

The plain names ``day``, ``night``, ``fog``, ``rain``, ``cloudy`` are accepted too, in any case.
Only frames whose condition is in ``conditions`` are used.

Preparing
---------
Every split is turned once into the shared prepared cache (:mod:`fusion_depth.data.cache`)
under ``<cache_root>/carla/<hash>/``, at ``height x width``: the image resized bilinearly (area
averaging when shrinking), the depth map sampled at the nearest source pixel (exact rendered
depths, never a blend across an edge), and the radar projected with the intrinsics scaled to the
new size (``f_x = f W'/W``, ``f_y = f H'/H``), so sparse depths stay exact. Ground truth at or
beyond ``max_range`` (default 250 m: the sky at 1000 m, and the cache's 256 m ceiling) is
invalid (0). The hash covers these settings and every file's name, size and modification time,
so a changed recording gets a new cache. The first split built prepares all three, so a bad file
anywhere fails before training starts; the recording itself is only ever read.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import re
import reprlib
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fusion_depth.data import CONDITIONS, SPLITS
from fusion_depth.data.base import FrameList, PreparedDataset, check_conditions
from fusion_depth.data.cache import FRAME_ERRORS, OnError, PreparedFrame, check_on_error, not_a_file
from fusion_depth.data.depth_io import DataFileError, open_image, png_bit_depth, read_rgb
from fusion_depth.data.folders import (
    check_max_range,
    entries_not_files,
    fingerprint,
    list_files,
    require_dir,
    resize_depth_nearest,
    resize_rgb,
)
from fusion_depth.data.radar_points import (
    DEFAULT_MAX_RADAR_POINTS,
    in_image,
    pixel_index,
    point_rows,
)
from fusion_depth.errors import ArgumentError

# Bump when decoding or projection changes, so old caches are not reused. 2: radar_points' u, v
# put pixel centres at integers (1 put their corners there; the same pixels but for a detection
# exactly on a pixel border, which rounds to even now).
FORMAT_VERSION = 2
SENSOR_DIRS = {"rgb": ".png", "depth": ".png", "radar": ".csv", "meta": ".json"}
RADAR_COLUMNS = ("depth", "azimuth", "altitude", "velocity")
DEPTH_FAR = 1000.0  # metres at CARLA's depth code 256**3 - 1
DEPTH_CODES = 256**3 - 1
DEPTH_STEP = DEPTH_FAR / DEPTH_CODES  # metres per code: about 0.06 mm
_FLOAT32_MAX = float(np.finfo(np.float32).max)
LAYOUT = "a CARLA recording laid out as <root>/{train,val,test}/{rgb,depth,radar,meta}/<frame>.*"

# First match wins: darkness and fog change the image most, then precipitation, then cloud.
_CONDITION_WORDS: tuple[tuple[str, frozenset[str]], ...] = (
    ("night", frozenset({"night"})),
    ("fog", frozenset({"fog", "foggy", "dust", "mist", "misty"})),
    ("rain", frozenset({"rain", "rainy"})),
    ("cloudy", frozenset({"cloudy", "overcast"})),
    ("day", frozenset({"clear", "wet", "noon", "sunset", "morning", "day"})),
)

log = logging.getLogger(__name__)


def condition_of(name: str) -> str:
    """The platform condition of a CARLA weather preset name (see the module docstring)."""
    text = str(name).strip()
    if text.lower() in CONDITIONS:
        return text.lower()
    words = {w.lower() for w in re.findall(r"[A-Z]+(?![a-z])|[A-Z]?[a-z]+|\d+", text)}
    for condition, keys in _CONDITION_WORDS:
        if words & keys:
            return condition
    raise ValueError(
        f"condition {name!r}: expected a CARLA weather preset name (e.g. ClearNoon, "
        f"WetCloudySunset, HardRainNoon, ClearNight) or one of {list(CONDITIONS)}"
    )


def decode_carla_depth(rgb: np.ndarray) -> np.ndarray:
    """CARLA's raw depth encoding, uint8 (H, W, 3) in R, G, B order, to float64 metres."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] < 3 or rgb.dtype != np.uint8:
        raise ValueError(f"expected uint8 (H, W, 3) R, G, B codes, got {rgb.dtype} {rgb.shape}")
    code = (
        rgb[..., 0].astype(np.int64)
        + rgb[..., 1].astype(np.int64) * 256
        + rgb[..., 2].astype(np.int64) * 65536
    )
    return code * DEPTH_STEP


def encode_carla_depth(depth: np.ndarray) -> np.ndarray:
    """Metres to CARLA's raw encoding, uint8 (H, W, 3) R, G, B (the inverse of the decoder,
    for writing test fixtures and synthetic frames; clipped to [0, 1000] m)."""
    code = np.round(np.clip(np.asarray(depth, dtype=np.float64), 0, DEPTH_FAR) / DEPTH_STEP)
    code = code.astype(np.int64)
    return np.stack([code & 255, (code >> 8) & 255, code >> 16], axis=-1).astype(np.uint8)


def read_carla_depth(path: str | os.PathLike) -> np.ndarray:
    """A depth camera PNG saved without a colour converter, as float64 (H, W) metres.

    Only CARLA's exact encoding is read: an 8-bit-per-channel RGB(A) PNG. Another format (a JPEG
    is lossy), another mode or bit depth (a 16-bit PNG, which Pillow would quietly cut to its
    high bytes), a grey image (a converter's lossy output) or an unreadable file raises
    DataFileError naming the file.
    """
    path = Path(path)
    image = open_image(path, "CARLA depth PNG")
    bits = png_bit_depth(path)
    if image.format != "PNG" or image.mode not in ("RGB", "RGBA") or bits != 8:
        got = f"{image.format or 'unknown'} of mode {image.mode!r}" + (
            f", {bits} bits per channel" if bits is not None else ""
        )
        raise DataFileError(
            path,
            f"expected CARLA's raw depth encoding, an 8-bit RGB(A) PNG, got a {got} (save the "
            "depth camera without a ColorConverter)",
        )
    rgb = np.asarray(image)[..., :3]
    grey = (rgb[..., 0] == rgb[..., 1]).all() and (rgb[..., 1] == rgb[..., 2]).all()
    if grey and np.unique(rgb[..., 0]).size > 1:
        raise DataFileError(
            path,
            "a grey image, i.e. saved with ColorConverter.Depth or LogarithmicDepth, which loses "
            "precision; expected the raw encoding (save_to_disk without a converter)",
        )
    return decode_carla_depth(rgb)


def _field(obj: Any, key: str) -> Any:
    """``obj[key]`` for the JSON form, ``obj.key`` for a ``carla.Transform``-like object."""
    return obj[key] if isinstance(obj, Mapping) else getattr(obj, key)


def transform_matrix(transform: Any) -> np.ndarray:
    """The 4x4 matrix of a ``carla.Transform`` (or its JSON form ``{"location": {x, y, z},
    "rotation": {pitch, yaw, roll}}``), as ``carla.Transform.get_matrix()`` builds it: it maps
    points in the transform's local frame to its parent's frame. Degrees; UE4 axes."""
    location, rotation = _field(transform, "location"), _field(transform, "rotation")
    x, y, z = (float(_field(location, k)) for k in ("x", "y", "z"))
    pitch, yaw, roll = (math.radians(float(_field(rotation, k))) for k in ("pitch", "yaw", "roll"))
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    cr, sr = math.cos(roll), math.sin(roll)
    return np.array(
        [
            [cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr, x],
            [cp * sy, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr, y],
            [sp, -cp * sr, cp * cr, z],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def matrix_to_transform(matrix: np.ndarray) -> dict[str, dict[str, float]]:
    """The inverse of :func:`transform_matrix`: the JSON form of a rigid 4x4 matrix."""
    m = np.asarray(matrix, dtype=np.float64)
    pitch = math.asin(max(-1.0, min(1.0, m[2, 0])))
    if abs(math.cos(pitch)) > 1e-9:
        yaw = math.atan2(m[1, 0], m[0, 0])
        roll = math.atan2(-m[2, 1], m[2, 2])
    else:  # gimbal lock: only yaw - roll (or yaw + roll) is defined, put it all in yaw
        yaw, roll = math.atan2(-m[0, 1], m[1, 1]), 0.0
    return {
        "location": {"x": float(m[0, 3]), "y": float(m[1, 3]), "z": float(m[2, 3])},
        "rotation": {
            "pitch": math.degrees(pitch),
            "yaw": math.degrees(yaw),
            "roll": math.degrees(roll),
        },
    }


def relative_transform(camera: Any, radar: Any) -> dict[str, dict[str, float]]:
    """The radar's pose in the camera frame, from both sensors' poses in a common frame (e.g.
    the vehicle's, as they were attached): ``inverse(M_camera) @ M_radar``, in JSON form."""
    return matrix_to_transform(np.linalg.inv(transform_matrix(camera)) @ transform_matrix(radar))


def detections_to_points(detections: np.ndarray) -> np.ndarray:
    """(N, >=3) rows of ``depth, azimuth, altitude`` (m, rad, rad) to (N, 3) radar-frame x, y, z."""
    d, az, alt = (np.asarray(detections, dtype=np.float64)[:, i] for i in range(3))
    return np.stack(
        [d * np.cos(alt) * np.cos(az), d * np.cos(alt) * np.sin(az), d * np.sin(alt)], axis=1
    )


def radar_image_points(
    detections: np.ndarray,
    radar_to_camera: np.ndarray,
    fov_deg: float,
    source_size: tuple[int, int],
    size: tuple[int, int],
    max_range: float = math.inf,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The detections (N, 4) that land in the output image: float64 (M,) arrays ``u, v`` (the
    continuous pixel position, column and row, in the ``size`` image), ``depth`` (metres, the
    forward distance x) and ``velocity`` (the detection's, m/s), in the detections' order.

    ``source_size`` is the recorded camera's (height, width), which with ``fov_deg`` fixes the
    intrinsics; ``size`` the output's, to which they are scaled per axis. See the module
    docstring for the conventions. Detections with a non-finite depth, azimuth or altitude are
    skipped, and so is anything whose arithmetic overflows (absurd ranges), behind the camera,
    at or beyond ``max_range``, or outside the image.
    """
    (src_h, src_w), (height, width) = source_size, size
    detections = np.asarray(detections, dtype=np.float64).reshape(-1, len(RADAR_COLUMNS))
    detections = detections[np.isfinite(detections[:, :3]).all(axis=1)]
    if not len(detections):
        return np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0)
    focal = src_w / (2.0 * math.tan(math.radians(fov_deg) / 2.0))
    fx, fy = focal * width / src_w, focal * height / src_h
    with np.errstate(over="ignore", invalid="ignore"):  # overflow gives inf/NaN: dropped
        points = detections_to_points(detections) @ radar_to_camera[:3, :3].T
        points += radar_to_camera[:3, 3]
        x, y, z = points.T
        # Tested in float32, the dtype the maps store: a forward distance just below max_range
        # in float64 can round up to it there, and a positive one below 1e-45 m down to 0.
        stored = x.astype(np.float32)
        ahead = (stored > 0) & (stored < min(max_range, _FLOAT32_MAX))
        x, y, z = x[ahead], y[ahead], z[ahead]
        u = (width - 1) / 2.0 + fx * y / x
        v = (height - 1) / 2.0 - fy * z / x
        inside = in_image(u, v, height, width)  # also drops what overflowed (NaN)
    velocity = detections[ahead, 3][inside]
    return u[inside], v[inside], x[inside], velocity


def splat_points(
    u: np.ndarray, v: np.ndarray, depth: np.ndarray, size: tuple[int, int]
) -> np.ndarray:
    """Points inside the image (:func:`radar_image_points`) to a float32 (height, width) sparse
    depth map in metres (0 = none): each at pixel ``(round(v), round(u))``
    (:func:`~fusion_depth.data.radar_points.pixel_index`), the nearer winning a shared pixel."""
    sparse = np.full(size, np.inf)
    rows, cols = pixel_index(v), pixel_index(u)
    np.minimum.at(sparse, (rows, cols), depth)
    sparse[np.isinf(sparse)] = 0.0
    return sparse.astype(np.float32)


def project_radar(
    detections: np.ndarray,
    radar_to_camera: np.ndarray,
    fov_deg: float,
    source_size: tuple[int, int],
    size: tuple[int, int],
    max_range: float = math.inf,
) -> np.ndarray:
    """Radar detections to a float32 (height, width) sparse depth map in metres (0 = none).

    The arguments are :func:`radar_image_points`'s, which drops what does not land in the
    image; the map is always finite and non-negative.
    """
    u, v, depth, _ = radar_image_points(
        detections, radar_to_camera, fov_deg, source_size, size, max_range
    )
    return splat_points(u, v, depth, size)


def read_radar_csv(path: str | os.PathLike) -> np.ndarray:
    """A radar file as float64 (N, 4): ``depth, azimuth, altitude, velocity`` per detection.

    Every value returned is finite: a row with NaN or an infinity in any column (``nan``,
    ``inf``, ``1e999``) is not a measurement and is dropped, with a warning naming the file and
    how many. Blank lines are skipped; a UTF-8 byte order mark is allowed. Undecodable text,
    another header, a row that is not four numbers, or a negative depth (a range) raises
    DataFileError naming the file and the line.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing radar file")
    expected = f"{','.join(RADAR_COLUMNS)} (one row per carla.RadarDetection)"
    try:
        with path.open(newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            header = [c.strip() for c in next(reader, [])]
            rows = [(reader.line_num, row) for row in reader if row]
    except (OSError, ValueError, csv.Error) as err:  # UnicodeDecodeError is a ValueError
        raise DataFileError(path, f"unreadable radar file ({err}); expected {expected}") from err
    if header != list(RADAR_COLUMNS):
        got = reprlib.repr(",".join(header)) if header else "an empty first line"
        raise DataFileError(path, f"expected the header {expected}, got {got}")
    values = np.zeros((len(rows), len(RADAR_COLUMNS)))
    for i, (line, row) in enumerate(rows):
        try:
            if len(row) != len(RADAR_COLUMNS):
                raise ValueError(f"{len(row)} values")
            values[i] = [float(v) for v in row]
        except ValueError as err:
            raise DataFileError(
                path,
                f"line {line}: {reprlib.repr(','.join(row))} is not a detection ({err}); "
                f"expected {len(RADAR_COLUMNS)} numbers, {','.join(RADAR_COLUMNS)}",
            ) from err
    finite = np.isfinite(values).all(axis=1)
    if not finite.all():
        log.warning(
            "%s: dropped %d of %d radar detections holding NaN or inf (not measurements)",
            path,
            int((~finite).sum()),
            len(values),
        )
        rows = [r for r, keep in zip(rows, finite, strict=True) if keep]
        values = values[finite]
    negative = np.flatnonzero(values[:, 0] < 0)
    if negative.size:
        first = negative[0]
        raise DataFileError(
            path,
            f"line {rows[first][0]}: depth {float(values[first, 0])!r} is negative "
            f"({len(negative)} such rows); expected the range from the radar in metres, >= 0",
        )
    return values


@dataclass(frozen=True)
class FrameMeta:
    """The per-frame metadata, validated."""

    fov: float  # horizontal field of view, degrees
    condition: str  # the platform condition
    weather: str  # the name as recorded
    radar_to_camera: np.ndarray  # 4x4


def read_frame_meta(path: str | os.PathLike) -> FrameMeta:
    """Reads and checks ``meta/<frame>.json``; every problem is a DataFileError naming the file
    and the key (FileNotFoundError if it is missing)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing frame metadata")
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as err:  # JSONDecodeError is a ValueError
        raise DataFileError(path, f"unreadable frame metadata ({err})") from err
    expected = (
        '{"fov": degrees, "condition": weather preset, "radar_to_camera": {"location": '
        '{"x", "y", "z"}, "rotation": {"pitch", "yaw", "roll"}}}'
    )
    if not isinstance(meta, dict):
        raise DataFileError(path, f"expected a JSON object {expected}")
    for key in ("fov", "condition", "radar_to_camera"):
        if key not in meta:
            raise DataFileError(path, f"missing key {key!r}; expected {expected}")
    fov = meta["fov"]
    if isinstance(fov, bool) or not isinstance(fov, int | float) or not 0 < fov < 180:
        raise DataFileError(
            path, f"fov={reprlib.repr(fov)}, expected a horizontal field of view in (0, 180)°"
        )
    if not isinstance(meta["condition"], str):
        raise DataFileError(
            path,
            f"condition={reprlib.repr(meta['condition'])}, expected a CARLA weather preset name "
            "(a string, e.g. ClearNoon)",
        )
    try:
        condition = condition_of(meta["condition"])
    except ValueError as err:
        raise DataFileError(path, str(err)) from err
    try:
        matrix = transform_matrix(meta["radar_to_camera"])
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as err:
        raise DataFileError(
            path,
            f"radar_to_camera={reprlib.repr(meta['radar_to_camera'])} is not a transform; "
            'expected {"location": {"x", "y", "z"} metres, "rotation": {"pitch", "yaw", "roll"} '
            "degrees}",
        ) from err
    if not np.isfinite(matrix).all():
        raise DataFileError(path, "radar_to_camera has non-finite values")
    return FrameMeta(float(fov), condition, str(meta["condition"]), matrix)


@dataclass(frozen=True)
class CarlaFrame:
    """One recorded frame: its files and metadata; ``problem`` is what the scan found wrong with
    them (then ``meta`` may be None)."""

    id: str  # "<split>/<frame>"
    rgb: Path
    depth: Path
    radar: Path
    meta: FrameMeta | None
    problem: Exception | None = None


def _file_problem(
    split_dir: Path,
    stem: str,
    listed: dict[str, dict[str, os.DirEntry]],
    not_files: dict[str, dict[str, Path]],
) -> OSError | None:
    """What is wrong with frame ``stem``'s files (a directory or dangling link where one should
    be, or a missing one), the metadata first; None when every one is a file."""
    for sensor in ("meta", *(s for s in SENSOR_DIRS if s != "meta")):
        suffix = SENSOR_DIRS[sensor]
        if stem in not_files[sensor]:
            return not_a_file(not_files[sensor][stem], f"the {sensor} file of frame {stem}")
        if stem not in listed[sensor]:
            return FileNotFoundError(
                f"{split_dir / sensor / (stem + suffix)}: missing {sensor} file of frame {stem} "
                f"(its {listed['meta'][stem].path} exists)"
            )
    return None


def scan_recording(
    root: Path, conditions: Sequence[str] = CONDITIONS, on_error: OnError = "raise"
) -> FrameList:
    """Every split's frames (checked for missing files and bad metadata, filtered by condition)
    and a fingerprint of their files. Cheap: lists folders and reads the small JSON files.

    A frame's broken file (module docstring) raises here with ``on_error="raise"``; with
    ``"skip"`` the frame is kept with its ``problem`` (before the condition filter, which needs
    its metadata), which :func:`load_frame` raises, so ``prepare_split`` skips it by id. A
    missing folder or a split without frames always raises.
    """
    check_on_error(on_error)
    frames: dict[str, dict[str, CarlaFrame]] = {}
    entries: list[os.DirEntry] = []
    for split in SPLITS:
        split_dir = require_dir(root / split, f"the {split} split of {LAYOUT}")
        listed: dict[str, dict[str, os.DirEntry]] = {}
        not_files: dict[str, dict[str, Path]] = {}
        for sensor, suffix in SENSOR_DIRS.items():
            folder = require_dir(split_dir / sensor, f"{split_dir}/{sensor}/<frame>{suffix} files")
            listed[sensor] = list_files(folder, (suffix,))
            not_files[sensor] = entries_not_files(folder, (suffix,))
        if not listed["meta"] and not not_files["meta"]:
            raise ValueError(
                f"{split_dir / 'meta'}: no frames, the {split} split is empty; expected one "
                "<frame>.json per recorded frame (written last by scripts/record_carla.py)"
            )
        kept, skipped = [], Counter()
        for stem in sorted(set(listed["meta"]) | set(not_files["meta"])):
            present = {s: listed[s][stem] for s in SENSOR_DIRS if stem in listed[s]}
            # As listed (a suffix may be upper case); where nothing is listed, the expected name.
            paths = {
                s: Path(present[s].path) if s in present else split_dir / s / f"{stem}{suffix}"
                for s, suffix in SENSOR_DIRS.items()
            }
            try:
                problem = _file_problem(split_dir, stem, listed, not_files)
                if problem is not None:
                    raise problem
                meta = read_frame_meta(paths["meta"])
            except FRAME_ERRORS as err:
                if on_error == "raise":
                    raise
                entries += present.values()
                kept.append(
                    CarlaFrame(
                        f"{split}/{stem}", paths["rgb"], paths["depth"], paths["radar"], None, err
                    )
                )
                continue
            if meta.condition not in conditions:
                skipped[meta.condition] += 1
                continue
            entries += present.values()
            kept.append(
                CarlaFrame(f"{split}/{stem}", paths["rgb"], paths["depth"], paths["radar"], meta)
            )
        if skipped:
            log.info(
                "carla %s: left out %d frames whose condition is not in %s (%s)",
                split,
                sum(skipped.values()),
                list(conditions),
                dict(skipped),
            )
        if not kept:
            raise ArgumentError(
                f"{split_dir}: none of its {sum(skipped.values())} frames has a condition in "
                f"{{conditions}}={list(conditions)} (found {dict(skipped)})",
                "conditions",
                owner=scan_recording,
            )
        frames[split] = {frame.id: frame for frame in kept}
    return FrameList(frames, fingerprint(entries))


def load_frame(frame: CarlaFrame, height: int, width: int, max_range: float) -> PreparedFrame:
    """Decodes, projects and resizes one recorded frame; its detections in the image become
    ``radar_points`` too (rcs 0: CARLA's radar does not report it).

    Raises the frame's ``problem`` when the scan found one, else what the readers raise for a
    bad file (DataFileError, FileNotFoundError), naming it.
    """
    if frame.problem is not None:
        raise frame.problem
    assert frame.meta is not None  # the scan reads it for every frame without a problem
    image = read_rgb(frame.rgb)
    depth = read_carla_depth(frame.depth)
    if depth.shape != image.shape[:2]:
        raise DataFileError(
            frame.depth,
            f"depth image is {depth.shape[1]}x{depth.shape[0]}, expected the camera image's "
            f"{image.shape[1]}x{image.shape[0]} ({frame.rgb})",
        )
    depth = np.where(depth < max_range, depth, 0.0).astype(np.float32)
    u, v, radar_depth, velocity = radar_image_points(
        read_radar_csv(frame.radar),
        frame.meta.radar_to_camera,
        frame.meta.fov,
        image.shape[:2],
        (height, width),
        max_range,
    )
    return PreparedFrame(
        image=resize_rgb(image, height, width),
        sparse=splat_points(u, v, radar_depth, (height, width)),
        depth=resize_depth_nearest(depth, height, width),
        condition=frame.meta.condition,
        radar_points=point_rows(u, v, radar_depth, velocity=velocity),
    )


class CarlaDepth(PreparedDataset):
    """One split of a CARLA recording (format: the module docstring), served from the prepared
    cache as :class:`~fusion_depth.data.Sample` dicts.

    ``conditions`` keeps the frames recorded in those conditions, and ``max_range`` is the metres
    at and beyond which depth and radar returns are invalid; the other arguments are
    :class:`~fusion_depth.data.base.PreparedDataset`'s. Samples carry ``radar_points``
    (``max_radar_points`` rows: ``u, v`` in the output image, ``depth`` the forward distance x,
    ``velocity`` the CSV's, ``rcs`` 0).
    """

    name = "carla"
    layout = LAYOUT
    format_version = FORMAT_VERSION

    def __init__(
        self,
        split: str,
        root: str | os.PathLike,
        cache_root: str | os.PathLike,
        height: int = 480,
        width: int = 640,
        conditions: Sequence[str] = CONDITIONS,
        max_range: float = 250.0,
        on_error: OnError = "raise",
        max_radar_points: int = DEFAULT_MAX_RADAR_POINTS,
    ) -> None:
        self.conditions_kept = check_conditions(conditions)
        self.max_range = check_max_range(max_range)
        super().__init__(split, root, cache_root, height, width, on_error, max_radar_points)

    def list_frames(self) -> FrameList:
        return scan_recording(self.root, self.conditions_kept, self.on_error)

    def settings(self) -> dict:
        return {"conditions": self.conditions_kept, "max_range": self.max_range}

    def frame_files(self, split: str, frame: CarlaFrame) -> list[Path]:
        return [frame.rgb, frame.depth, frame.radar]

    def load_frame(self, split: str, frame: CarlaFrame) -> PreparedFrame:
        return load_frame(frame, self.height, self.width, self.max_range)
