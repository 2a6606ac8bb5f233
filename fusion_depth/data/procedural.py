"""``dataset=procedural``: street scenes rendered by the package itself, so training and CI need
no download or sign-up.

Each frame is a street (road with lane paint, kerbs and sidewalks, facades with windows and
varying setbacks, parked and moving cars, street lights, signs, trees, sky) seen by a pinhole
dash camera, ray-cast analytically against a ground plane and axis-aligned boxes in numpy. Depth is
exact camera-frame z in metres (0 = sky); the world ends at 250 m. Five weather conditions change
only the image (fog extinction, night lighting and noise, rain streaks and wet road, overcast), and
the sparse input is a simulated automotive radar (default) or 64-beam lidar.

Frames are generated once per parameter set into ``root/<hash>/<split>/`` as uncompressed ``.npy``
files that ``__getitem__`` memory-maps:

* ``image.npy``  uint8  (N, H, W, 3)
* ``depth.npy``  uint16 (N, H, W), depth in 1/256 m (KITTI convention: 3.9 mm steps, so <= 2 mm
  rounding error up to the 250 m horizon; 0 = invalid)
* ``sparse.npy`` uint16 (N, H, W), same encoding (0 = no return)
* ``radar_points.npy`` float32 (N, P, K), radar only: each frame's returns as points, the
  ``radar_points`` of a :class:`~fusion_depth.data.Sample` (columns
  :data:`~fusion_depth.data.RADAR_POINT_FIELDS`; ``P = max_radar_points``, the nearest kept,
  zero rows after). ``u, v, depth`` are where the return projects before
  ``radar_height_extension`` draws it as a line, i.e. the pixel of ``sparse`` it lands on with
  the extension off; ``rcs`` and ``velocity`` are 0 (the simulated scene is static, and the
  simulation draws no cross-section).
* ``conditions.json`` the condition of every frame

The DataLoader's workers pass frames on in this stored form
(:meth:`ProceduralDepth.encoded_sample`), converted to floats on the device
(:mod:`fusion_depth.data.encoding`); ``dataset[i]`` gives the float form.

``<hash>`` covers every parameter and ``GENERATOR_VERSION``, so a change renders into a new
folder and leaves the old one alone; ``root/<hash>/meta.json`` records the parameters. Only the
requested split is rendered. It is written into a temporary sibling folder and renamed into place
when complete, so an interrupted run leaves nothing a later run would read, and of two processes
rendering the same split the first rename wins (both produce identical frames). A split renders in
one process per core this process may use, at most one per ``_FRAMES_PER_PROCESS`` frames
(:func:`render_processes`), each writing its frames into the same memory-mapped arrays; a frame is
a pure function of its index, so the arrays are the same for any number of processes.

Run ``python -m fusion_depth.data.procedural --out preview.png`` to look at one frame per
condition, and ``python -m fusion_depth.data.procedural --frames DIR`` for the first test frames
as files a program reads (:func:`write_test_frames`).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import multiprocessing
import os
import shutil
import time
import uuid
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import ClassVar, Literal, overload

import numpy as np
import torch
from torch.utils.data import Dataset

from fusion_depth.data import CONDITIONS, RADAR_POINT_FIELDS, SPLITS, EncodedSample, Sample
from fusion_depth.data._procedural_render import sample_weather, shade
from fusion_depth.data._procedural_scene import SKY_ID, cast_primary, sample_scene
from fusion_depth.data._procedural_sensors import lidar_map, radar_returns
from fusion_depth.data.base import check_conditions, check_size, check_split
from fusion_depth.data.cache import check_settings_file
from fusion_depth.data.depth_io import DEPTH_PNG_SCALE, DataFileError, check_npy, short_reason
from fusion_depth.data.encoding import decode_sample, encode_sample
from fusion_depth.data.radar_points import check_max_points, pad_points, point_rows
from fusion_depth.errors import ArgumentError
from fusion_depth.utils.atomic import fsync_file, owner_tag, remove_orphaned_temporaries
from fusion_depth.utils.processes import die_with_parent
from fusion_depth.utils.schema import NON_NEGATIVE_INT, POSITIVE_INT, Rule, Schema, is_number

# Bump whenever rendering changes, so old caches are not reused. 3: radar_points' u, v put pixel
# centres at integers (the same pixels as 2, which put their corners there).
GENERATOR_VERSION = 3
SENSORS = ("radar", "lidar")
DEPTH_SCALE = DEPTH_PNG_SCALE  # cache stores uint16 depth * 256, as the prepared caches
_ARRAYS = ("image", "depth", "sparse")  # every split's; a radar split adds RADAR_ARRAY
RADAR_ARRAY = "radar_points"
DEFAULT_MAX_RADAR_POINTS = 64  # the simulated radar has tens of returns in view
DEFAULT_CAMERA_HEIGHT = (1.4, 1.7)  # metres: a car's dash camera


def _is_range(low: float, high: float):
    """A rule's test: two numbers ``low ≤ a ≤ b ≤ high``."""

    def ok(value: object) -> bool:
        try:
            a, b = value  # type: ignore[misc]
        except (TypeError, ValueError):
            return False
        return is_number(a) and is_number(b) and low <= a <= b <= high

    return ok


log = logging.getLogger(__name__)


Frame3 = tuple[np.ndarray, np.ndarray, np.ndarray]
Frame4 = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]


@overload
def render_frame(
    seed: int,
    split: str,
    index: int,
    height: int,
    width: int,
    fov_deg: float,
    condition: str,
    sparse: str,
    radar_height_extension: float = ...,
    *,
    with_points: Literal[False] = ...,
    camera_height: tuple[float, float] = ...,
    fov_range: tuple[float, float] | None = ...,
) -> Frame3: ...


@overload
def render_frame(
    seed: int,
    split: str,
    index: int,
    height: int,
    width: int,
    fov_deg: float,
    condition: str,
    sparse: str,
    radar_height_extension: float = ...,
    *,
    with_points: Literal[True],
    camera_height: tuple[float, float] = ...,
    fov_range: tuple[float, float] | None = ...,
) -> Frame4: ...


def render_frame(
    seed: int,
    split: str,
    index: int,
    height: int,
    width: int,
    fov_deg: float,
    condition: str,
    sparse: str,
    radar_height_extension: float = 0.0,
    *,
    with_points: bool = False,
    camera_height: tuple[float, float] = DEFAULT_CAMERA_HEIGHT,
    fov_range: tuple[float, float] | None = None,
) -> Frame3 | Frame4:
    """Frame ``index`` of ``split``: image uint8 (H, W, 3), depth and sparse float32 (H, W).

    A pure function of its arguments. Scene, weather and sensor draw from separate streams, so
    the same frame with lidar instead of radar shows the same street. ``with_points`` adds a
    fourth item: the radar's returns in the image as float32 (M, K) rows
    (:func:`~fusion_depth.data.radar_points.point_rows`, nearest first; ``rcs``, ``velocity``
    0), None for lidar; the other three are the same either way.

    ``camera_height`` is the range (metres) the camera's height is drawn from; ``fov_range``, a
    range of horizontal fields of view (degrees) drawn per frame from a fourth stream in place
    of ``fov_deg``. At their defaults the frames are those of earlier versions.
    """
    stream = np.random.SeedSequence(seed, spawn_key=(SPLITS.index(split), index))
    children = stream.spawn(4)  # the first three as before: the camera's stream is new
    scene_rng, weather_rng, sensor_rng = (np.random.default_rng(s) for s in children[:3])
    if fov_range is not None:
        fov_deg = float(np.random.default_rng(children[3]).uniform(*fov_range))
    scene = sample_scene(scene_rng, height, width, fov_deg, tuple(camera_height))
    dirs = scene.camera.rays()
    t, ids = cast_primary(scene, dirs)
    depth = np.where(ids == SKY_ID, 0.0, t).astype(np.float32)
    weather = sample_weather(condition, weather_rng)
    image = shade(scene, dirs, t, ids, weather, weather_rng)
    points = None
    if sparse == "radar":
        sparse_map, returns = radar_returns(scene, sensor_rng, weather, radar_height_extension)
        points = point_rows(returns[:, 0], returns[:, 1], returns[:, 2])
    else:
        sparse_map = lidar_map(scene.camera, dirs, depth, sensor_rng, weather)
    image_u8 = (image * 255 + 0.5).astype(np.uint8)
    if with_points:
        return image_u8, depth, sparse_map, points
    return image_u8, depth, sparse_map


def _encode_depth(depth: np.ndarray) -> np.ndarray:
    return np.clip(np.round(depth * DEPTH_SCALE), 0, np.iinfo(np.uint16).max).astype(np.uint16)


def _check_choice(name: str, value: object, allowed: Sequence[str]) -> None:
    if value not in allowed:
        raise ValueError(f"{name}={value!r}: expected one of {list(allowed)}")


class ProceduralDepth(Dataset):
    """One split of the built-in procedural dataset (see the module docstring).

    Samples are :class:`~fusion_depth.data.Sample` dicts (no ``frame_box``); with
    ``sparse="radar"`` they carry ``radar_points`` (``max_radar_points`` rows, the nearest
    returns; see the module docstring), with ``"lidar"`` not. Frame ``i`` has condition
    ``conditions[i % len(conditions)]``, so every split holds each condition in equal shares.

    ``camera_height`` (a range in metres, the car's 1.4-1.7 by default) and ``fov_range`` (a
    range of horizontal fields of view in degrees drawn per frame, replacing ``fov_deg``; null
    by default) vary the camera: a pool of other cameras for a prior to learn from
    (``conf/experiment/prior_study_source_prior.yaml``).

    Raises:
        ValueError: an option out of range, naming it.
        DataFileError: a generated array that is damaged (truncated, another dtype or shape),
            naming it, when the split is first read.
    """

    # Where it writes (the argument, a folder below the cache), as PreparedDataset.writes_into.
    writes_into = ("root", "procedural")

    # What the arguments accept (fusion_depth.utils.schema), checked with the config before any
    # work (dataset.reader.<argument>: fusion_depth.config.dataset_validation) and here for a
    # caller from Python.
    ARGUMENT_RULES: ClassVar[Schema] = {
        "num_train": Rule(POSITIVE_INT.ok, "an integer ≥ 1 (frames)"),
        "num_val": Rule(POSITIVE_INT.ok, "an integer ≥ 1 (frames)"),
        "num_test": Rule(POSITIVE_INT.ok, "an integer ≥ 1 (frames)"),
        "seed": NON_NEGATIVE_INT,
        "fov_deg": Rule(
            lambda v: is_number(v) and 10.0 <= v <= 150.0,
            "a horizontal field of view in [10, 150] degrees",
        ),
        "radar_height_extension": Rule(
            lambda v: is_number(v) and 0.0 <= v <= 10.0,
            "a height in [0, 10] metres (0 keeps each radar return a single pixel)",
        ),
        "camera_height": Rule(
            _is_range(0.5, 5.0), "a range [low, high] of heights in metres, 0.5 ≤ low ≤ high ≤ 5"
        ),
        "fov_range": Rule(
            lambda v: v is None or _is_range(10.0, 150.0)(v),
            "null, or a range [low, high] of horizontal fields of view in [10, 150] degrees",
        ),
    }

    def __init__(
        self,
        split: str,
        root: str | os.PathLike,
        height: int = 96,
        width: int = 320,
        num_train: int = 400,
        num_val: int = 50,
        num_test: int = 100,
        sparse: str = "radar",
        conditions: Sequence[str] = CONDITIONS,
        seed: int = 0,
        fov_deg: float = 70.0,
        radar_height_extension: float = 0.0,
        max_radar_points: int = DEFAULT_MAX_RADAR_POINTS,
        camera_height: Sequence[float] = DEFAULT_CAMERA_HEIGHT,
        fov_range: Sequence[float] | None = None,
    ) -> None:
        check_split(split)
        _check_choice("sparse", sparse, SENSORS)
        conditions = tuple(check_conditions(conditions))
        height, width = check_size(height, width)
        given = {
            "num_train": num_train,
            "num_val": num_val,
            "num_test": num_test,
            "seed": seed,
            "fov_deg": fov_deg,
            "radar_height_extension": radar_height_extension,
            "camera_height": camera_height,
            "fov_range": fov_range,
        }
        for name, value in given.items():  # null, inf, nan, a list or a string too
            if not self.ARGUMENT_RULES[name].ok(value):
                expected = self.ARGUMENT_RULES[name].expected
                raise ArgumentError(
                    f"{{{name}}}={value!r}: expected {expected}", name, owner=ProceduralDepth
                )
        counts = {"train": num_train, "val": num_val, "test": num_test}

        max_radar_points = check_max_points(max_radar_points)

        self.split = split
        self.params = {
            "generator_version": GENERATOR_VERSION,
            "height": int(height),
            "width": int(width),
            "num_train": int(num_train),
            "num_val": int(num_val),
            "num_test": int(num_test),
            "sparse": sparse,
            "conditions": list(conditions),
            "seed": int(seed),
            "fov_deg": float(fov_deg),
        }
        # A camera other than the car's only when asked for: the built-in frames keep their folder.
        if tuple(camera_height) != DEFAULT_CAMERA_HEIGHT:
            self.params["camera_height"] = [float(v) for v in camera_height]
        if fov_range is not None:
            self.params["fov_range"] = [float(v) for v in fov_range]
        if sparse == "radar":
            self.params["radar_height_extension"] = float(radar_height_extension)
            self.params["max_radar_points"] = max_radar_points
        self.array_names = _ARRAYS + ((RADAR_ARRAY,) if sparse == "radar" else ())
        text = json.dumps(self.params, sort_keys=True)
        self.cache_dir = Path(root) / hashlib.sha256(text.encode()).hexdigest()[:12]
        self.split_dir = self.cache_dir / split
        self._length = int(counts[split])
        if self.cache_dir.is_dir():
            check_settings_file(self.cache_dir / "meta.json", self.params, self.cache_dir)
            remove_orphaned_temporaries(self.cache_dir, SPLITS)
        problem = _split_problem(self.split_dir, self._expected())
        if problem is not None:
            if self.split_dir.exists():
                log.warning("%s: %s; generating the split again", self.split_dir, problem)
            self._generate()
        self._arrays: dict[str, np.ndarray] | None = None
        self.conditions: list[str] = json.loads((self.split_dir / "conditions.json").read_text())

    def _expected(self) -> dict[str, tuple]:
        """``name -> (dtype, shape)`` of each array of the split, and ``conditions.json``'s
        list (under ``"conditions"``)."""
        p = self.params
        n, h, w = self._length, p["height"], p["width"]
        shapes = {
            "image": (np.uint8, (n, h, w, 3)),
            "depth": (np.uint16, (n, h, w)),
            "sparse": (np.uint16, (n, h, w)),
            RADAR_ARRAY: (np.float32, (n, p.get("max_radar_points"), len(RADAR_POINT_FIELDS))),
        }
        expected: dict[str, tuple] = {name: shapes[name] for name in self.array_names}
        expected["conditions"] = tuple(p["conditions"][i % len(p["conditions"])] for i in range(n))
        return expected

    def _generate(self) -> None:
        """Renders the split into a private temporary folder, then renames it into place, so a
        reader only ever sees a complete split."""
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        check_settings_file(self.cache_dir / "meta.json", self.params, self.cache_dir)
        p = self.params
        n, h, w = self._length, p["height"], p["width"]
        # Named after this process, so that a later run removes it if this one is killed.
        tmp = self.cache_dir / f".{self.split}.tmp.{owner_tag()}.{uuid.uuid4().hex[:8]}"
        tmp.mkdir()
        start = time.perf_counter()
        try:
            out = {
                "image": np.lib.format.open_memmap(tmp / "image.npy", "w+", np.uint8, (n, h, w, 3)),
                "depth": np.lib.format.open_memmap(tmp / "depth.npy", "w+", np.uint16, (n, h, w)),
                "sparse": np.lib.format.open_memmap(tmp / "sparse.npy", "w+", np.uint16, (n, h, w)),
            }
            if p["sparse"] == "radar":
                out[RADAR_ARRAY] = np.lib.format.open_memmap(
                    tmp / f"{RADAR_ARRAY}.npy",
                    "w+",
                    np.float32,
                    (n, p["max_radar_points"], len(RADAR_POINT_FIELDS)),
                )
            del out  # created at full size; the renderers open them for writing
            conditions = list(self._expected()["conditions"])
            _render_into(tmp, self.array_names, p, self.split, conditions, render_processes(n))
            (tmp / "conditions.json").write_text(json.dumps(conditions))
            fsync_file(tmp / "conditions.json")  # the arrays' flush() wrote theirs to disk
            _publish(tmp, self.split_dir, self._expected())
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        seconds = time.perf_counter() - start
        log.info(
            "generated %d procedural %s frames (%dx%d, %s) in %.1f s (%.1f frames/s) into %s",
            n,
            self.split,
            h,
            w,
            p["sparse"],
            seconds,
            n / seconds,
            self.split_dir,
        )

    def _open(self) -> dict[str, np.ndarray]:
        """The split's arrays, memory-mapped, each checked against the dtype and shape it was
        generated with (a DataFileError naming a damaged one)."""
        if self._arrays is None:
            expected = self._expected()
            arrays = {}
            for name in self.array_names:
                path = self.split_dir / f"{name}.npy"
                dtype, shape = expected[name]
                try:
                    array = np.load(path, mmap_mode="r", allow_pickle=False)
                except Exception as err:  # numpy raises ValueError, OSError, EOFError, ...
                    raise DataFileError(
                        path,
                        f"unreadable ({short_reason(err)}); expected {np.dtype(dtype)} "
                        f"{shape}; delete {self.split_dir} to generate it again",
                    ) from err
                if (
                    not isinstance(array, np.ndarray)
                    or array.dtype != dtype
                    or array.shape != shape
                ):
                    got = f"{array.dtype} {array.shape}" if isinstance(array, np.ndarray) else "?"
                    raise DataFileError(
                        path,
                        f"{got}, expected {np.dtype(dtype)} {shape}; delete {self.split_dir} to "
                        "generate it again",
                    )
                arrays[name] = array
            self._arrays = arrays
        return self._arrays

    def __getstate__(self) -> dict:
        # Worker processes re-open the memory maps instead of receiving pickled copies.
        return {**self.__dict__, "_arrays": None}

    def __len__(self) -> int:
        return self._length

    def __getitem__(self, index: int) -> Sample:
        """Frame ``index`` in the float form (:func:`~fusion_depth.data.encoding.decode_sample`
        of :meth:`encoded_sample`)."""
        return decode_sample(self.encoded_sample(index))  # type: ignore[return-value]

    def encoded_sample(self, index: int) -> EncodedSample:
        """Frame ``index`` as stored: image uint8 (3, H, W), ``sparse`` and ``depth`` uint16
        (1, H, W) in 1/256 m (copies, not the memory maps), and ``radar_points`` for the radar.
        What the datamodule's loaders pass to the device.

        Raises:
            IndexError: ``index`` outside ``[-len, len)``.
            DataFileError: a generated array is damaged, naming it.
        """
        if not -self._length <= index < self._length:
            raise IndexError(f"index {index} out of range for {self._length} frames")
        index %= self._length
        arrays = self._open()
        sample = encode_sample(
            arrays["image"][index],
            np.array(arrays["sparse"][index]),
            np.array(arrays["depth"][index]),
            self.conditions[index],
        )
        if RADAR_ARRAY in arrays:
            sample["radar_points"] = torch.from_numpy(np.array(arrays[RADAR_ARRAY][index]))
        return sample


# Frames per rendering process: below about this many, starting a process costs more than it saves.
_FRAMES_PER_PROCESS = 400
# Frames per task handed to a process (its unit of work).
_FRAMES_PER_TASK = 200


def render_processes(num_frames: int) -> int:
    """How many processes render ``num_frames``: one per core this process may run on, and at
    most one per ``_FRAMES_PER_PROCESS`` frames (small splits render in this process)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(cores or 1, num_frames // _FRAMES_PER_PROCESS))


def _render_into(
    folder: Path,
    names: Sequence[str],
    params: dict,
    split: str,
    conditions: Sequence[str],
    processes: int,
) -> None:
    """Renders every frame of ``split`` into the ``<name>.npy`` arrays in ``folder``, in
    ``processes`` processes (1: this one). Each frame is a pure function of its index
    (:func:`render_frame`), so the arrays are the same for any number of processes."""
    bounds = list(range(0, len(conditions), _FRAMES_PER_TASK)) + [len(conditions)]
    tasks = [
        (folder, tuple(names), params, split, conditions[start:stop], start)
        for start, stop in zip(bounds[:-1], bounds[1:], strict=True)
    ]
    if processes <= 1:
        for task in tasks:
            _render_range(*task)
        return
    # fork where the platform has it (as DataLoader workers): no re-import in each process.
    methods = multiprocessing.get_all_start_methods()
    context = multiprocessing.get_context("fork" if "fork" in methods else None)
    # Renderers die with this process: a kill -9 of it does not leave them rendering on.
    with ProcessPoolExecutor(
        processes, mp_context=context, initializer=die_with_parent, initargs=(os.getpid(),)
    ) as pool:
        list(pool.map(_render_range, *zip(*tasks, strict=True)))  # raises a renderer's error


def _render_range(
    folder: Path,
    names: tuple[str, ...],
    params: dict,
    split: str,
    conditions: Sequence[str],
    start: int,
) -> None:
    """Frames ``start`` … ``start + len(conditions) - 1`` of ``split``, written into the arrays."""
    out = {name: np.load(folder / f"{name}.npy", mmap_mode="r+") for name in names}
    for i, condition in enumerate(conditions, start):
        image, depth, sparse, points = render_frame(
            params["seed"],
            split,
            i,
            params["height"],
            params["width"],
            params["fov_deg"],
            condition,
            params["sparse"],
            params.get("radar_height_extension", 0.0),
            with_points=True,
            camera_height=tuple(params.get("camera_height", DEFAULT_CAMERA_HEIGHT)),
            fov_range=params.get("fov_range"),
        )
        out["image"][i] = image
        out["depth"][i] = _encode_depth(depth)
        out["sparse"][i] = _encode_depth(sparse)
        if RADAR_ARRAY in out:
            out[RADAR_ARRAY][i] = pad_points(points, params["max_radar_points"])
    for array in out.values():
        array.flush()


def _split_problem(split_dir: Path, expected: dict[str, tuple]) -> str | None:
    """Why ``split_dir`` is not a whole generated split (None: it is): a missing folder, an
    array missing or not of the dtype, shape and size ``expected``, or a ``conditions.json``
    that is not the list expected. Reads headers and the small JSON, not the arrays."""
    if not split_dir.is_dir():
        return "not generated"
    for name, spec in expected.items():
        if name == "conditions":
            continue
        dtype, shape = spec
        try:
            check_npy(split_dir / f"{name}.npy", dtype, shape, "generated array")
        except (OSError, ValueError) as err:
            return str(err).removeprefix(f"{split_dir / name}.npy: ")
    try:
        conditions = json.loads((split_dir / "conditions.json").read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as err:
        return f"conditions.json unreadable ({short_reason(err)})"
    if conditions != list(expected["conditions"]):
        return "conditions.json is not the list of the frames' conditions"
    return None


def _publish(tmp: Path, split_dir: Path, expected: dict[str, tuple]) -> None:
    """Renames a finished split into place. When another process got there first its split is
    kept (rename onto a non-empty folder fails); both rendered identical frames. A damaged
    split in the way is moved aside and removed."""
    for _ in range(3):
        try:
            os.replace(tmp, split_dir)
            return
        except OSError:
            if _split_problem(split_dir, expected) is None:
                return
            aside = split_dir.with_name(
                f".{split_dir.name}.damaged.{owner_tag()}.{uuid.uuid4().hex[:8]}"
            )
            try:
                os.replace(split_dir, aside)
            except FileNotFoundError:
                continue  # another process moved it just now
            shutil.rmtree(aside, ignore_errors=True)
    os.replace(tmp, split_dir)  # fails naming both folders


def _colorize(depth: np.ndarray, max_depth: float = 80.0) -> np.ndarray:
    """Depth (H, W) to RGB uint8: near yellow through red and purple to far blue, 0 black."""
    x = np.clip(np.log1p(depth) / np.log1p(max_depth), 0, 1)[..., None]
    stops = np.array([[1.0, 0.95, 0.3], [0.95, 0.35, 0.2], [0.55, 0.15, 0.55], [0.12, 0.15, 0.5]])
    pos = x * (len(stops) - 1)
    i = np.minimum(pos.astype(int), len(stops) - 2)[..., 0]
    f = pos - i[..., None]
    rgb = stops[i] * (1 - f) + stops[i + 1] * f
    rgb[depth <= 0] = 0
    return (rgb * 255).astype(np.uint8)


def preview(
    height: int,
    width: int,
    sparse: str,
    seed: int,
    fov_deg: float,
    radar_height_extension: float = 0.0,
) -> np.ndarray:
    """A grid with one row per condition: image | colourised depth | sparse points on the image
    (frames 0-4 of the train split, i.e. what the dataset serves first)."""
    rows = []
    # Single radar pixels are hard to see at preview size; lines and lidar are dense enough.
    radius = max(1, height // 96) if sparse == "radar" and not radar_height_extension else 0
    for i, condition in enumerate(CONDITIONS):
        image, depth, sparse_map = render_frame(
            seed, "train", i, height, width, fov_deg, condition, sparse, radar_height_extension
        )
        overlay = (image * 0.5).astype(np.uint8)
        colours = _colorize(sparse_map)
        for r, c in zip(*np.nonzero(sparse_map), strict=True):
            overlay[max(0, r - radius) : r + radius + 1, max(0, c - radius) : c + radius + 1] = (
                colours[r, c]
            )
        gap = np.full((height, 4, 3), 255, dtype=np.uint8)
        rows.append(np.concatenate([image, gap, _colorize(depth), gap, overlay], 1))
        rows.append(np.full((4, rows[-1].shape[1], 3), 255, dtype=np.uint8))
    return np.concatenate(rows[:-1], 0)


# The built-in dataset's settings (conf/dataset/procedural.yaml): the frames a default run tests
# on, which --frames writes.
DATASET_FRAMES = {"height": 64, "width": 192, "radar_height_extension": 2.0, "seed": 0}


def write_test_frames(
    folder: str | os.PathLike,
    count: int = len(CONDITIONS),
    sparse: str = "radar",
    **settings: float,
) -> list[Path]:
    """Frames ``0 … count - 1`` of the built-in dataset's test split (one per condition, in
    :data:`~fusion_depth.data.CONDITIONS`' order) as the files a program or ``predict`` reads:
    ``folder/photos/<i:06d>.png`` (RGB) and ``folder/<sparse>/<i:06d>.png`` (the sparse depth as
    a 16-bit PNG in 1/256 m, 0 = no return; :func:`~fusion_depth.data.depth_io.read_depth_png`
    reads it). ``settings`` (``height``, ``width``, ``radar_height_extension``, ``seed``,
    ``fov_deg``) default to the dataset's (:data:`DATASET_FRAMES`), so the frames are those a
    default run is tested on. Returns the photos' paths.

    Raises:
        ValueError: ``count`` below 1, or an unknown sensor.
    """
    from PIL import Image

    from fusion_depth.data.depth_io import write_depth_png

    if int(count) != count or count < 1:
        raise ValueError(f"--count {count}: expected an integer >= 1")
    _check_choice("sparse", sparse, SENSORS)
    given = {**DATASET_FRAMES, "fov_deg": 70.0, **settings}
    height, width = check_size(given["height"], given["width"])
    photos, depths = Path(folder) / "photos", Path(folder) / sparse
    photos.mkdir(parents=True, exist_ok=True)
    depths.mkdir(parents=True, exist_ok=True)
    written = []
    for i in range(int(count)):
        image, _, sparse_map = render_frame(
            int(given["seed"]),
            "test",
            i,
            height,
            width,
            float(given["fov_deg"]),
            CONDITIONS[i % len(CONDITIONS)],
            sparse,
            float(given["radar_height_extension"]) if sparse == "radar" else 0.0,
        )
        Image.fromarray(image).save(photos / f"{i:06d}.png")
        write_depth_png(depths / f"{i:06d}.png", sparse_map)
        written.append(photos / f"{i:06d}.png")
    return written


def main(argv: Sequence[str] | None = None) -> None:
    """CLI: render one frame per condition into a PNG grid for a person to look at (``--out``),
    or write the first test frames as PNG files (``--frames``, :func:`write_test_frames`)."""
    from PIL import Image

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--out", help="PNG file to write: a grid of one frame per condition")
    what.add_argument(
        "--frames",
        metavar="DIR",
        help="write the first --count test frames of the built-in dataset, as a default run "
        "tests on them, into DIR/photos/ (RGB PNGs) and DIR/radar/ (16-bit depth PNGs, 1/256 m)",
    )
    parser.add_argument("--count", type=int, default=len(CONDITIONS), help="frames of --frames")
    parser.add_argument("--height", type=int, help="default: 192 (--out), the dataset's 64")
    parser.add_argument("--width", type=int, help="default: 640 (--out), the dataset's 192")
    parser.add_argument("--sparse", choices=SENSORS, default="radar")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fov-deg", type=float, default=70.0)
    parser.add_argument(
        "--radar-height-extension",
        type=float,
        help="draw each radar return as a vertical line from the ground to this height (m); "
        "default: 0 (--out), the dataset's 2",
    )
    args = parser.parse_args(argv)
    if args.frames is not None:
        settings = {
            key: value
            for key, value in (
                ("height", args.height),
                ("width", args.width),
                ("radar_height_extension", args.radar_height_extension),
                ("seed", args.seed),
                ("fov_deg", args.fov_deg),
            )
            if value is not None
        }
        try:
            written = write_test_frames(args.frames, args.count, args.sparse, **settings)
        except ValueError as err:
            parser.error(str(err))
        folder = Path(args.frames)
        print(
            f"wrote {len(written)} test frames of the built-in dataset into {folder / 'photos'} "
            f"and their {args.sparse} depth into {folder / args.sparse}"
        )
        return
    grid = preview(
        args.height or 192,
        args.width or 640,
        args.sparse,
        args.seed,
        args.fov_deg,
        args.radar_height_extension or 0.0,
    )
    Image.fromarray(grid).save(args.out)
    print(f"wrote {args.out} ({', '.join(CONDITIONS)} from top to bottom)")


if __name__ == "__main__":
    main()
