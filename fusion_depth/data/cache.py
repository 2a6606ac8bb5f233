"""Prepared caches: a dataset's slow per-frame work (projection, filling, resizing) done once.

A real dataset module turns its raw files into :class:`PreparedFrame` objects; :func:`prepare_split`
writes them under ``<cache root>/<dataset>/<hash of the settings>/<split>/`` as uncompressed
``.npy`` arrays (:func:`~fusion_depth.data.depth_io.write_npy`; ``np.load`` reads them):

* ``000123.image.npy``  RGB uint8 (H, W, 3)
* ``000123.sparse.npy`` the sparse sensor input, uint16 (H, W) metres × 256 (KITTI's depth PNG
  encoding, :data:`~fusion_depth.data.depth_io.DEPTH_PNG_SCALE`; 0 = no return)
* ``000123.depth.npy``  the measured ground truth, same encoding (what evaluation scores)
* ``000123.filled.npy`` the densified ground truth, only when a filling method is set
* ``000123.radar.npy``  the radar returns as points, only for a radar dataset: float32 (M, K)
  rows, columns :data:`~fusion_depth.data.RADAR_POINT_FIELDS`, nearest first, every return of
  the frame (:mod:`fusion_depth.data.radar_points`); served cut or padded to
  ``max_radar_points`` rows, so that setting changes nothing in the cache
* ``000123.fullres.npy`` ground truth kept at the dataset's full resolution, only where a reader
  resamples its frames and keeps it (nuScenes' val and test: RadarNet's): float32 (N, 3) rows
  ``y, x, depth``, each pixel's centre in the prepared frame's coordinates; served as
  ``depth_points``, padded with zero rows to the split's largest N
* ``000123.json``       the frame's source id and condition, written last
* ``index.json``        every frame of the split, written when all are done

The arrays hold what the cache's PNGs held up to version 2 (the same uint16 values), but decode
about 40 times faster (0.5 ms against 19.6 ms for a 384x1248 frame) at about 4 times the disk
space (7 bytes a pixel, 9 with ``filled``). :class:`PreparedSplit` passes them on as they are
(:meth:`PreparedSplit.encoded_sample`, what the datamodule's loaders read), to be converted to
floats on the device (:mod:`fusion_depth.data.encoding`). A depth that uint16 × 1/256 m cannot
hold (beyond :data:`~fusion_depth.data.depth_io.MAX_ENCODED_DEPTH`, 255.996 m) is refused when
the frame is prepared, naming it, never clipped. Caches of an older :data:`PREPARED_VERSION` hash
to another folder, so they are prepared again (and the old folder is left alone: delete it).

Several processes may prepare one split: workers (``prepare.workers``), shards across machines
(``prepare.shard``/``prepare.num_shards``) or two commands. Each claims a frame before making it
(a file in ``.claims/``), so a frame is made once; a dead process's claim is taken over by one
process at a time (under ``.claims/.lock``); the process that finds every frame present writes
``index.json`` (:func:`prepare_split`, :class:`PrepareOptions`). Workers die with their parent
and ignore Ctrl-C: the parent stops them, and removes the claims and temporary files no live
process holds.

Each file goes through a temporary name (which names its writer, so the next run removes a
killed writer's), is flushed to disk and renamed, and a frame counts as done only once its
``.json`` exists, so an interrupted prepare (or a power loss) restarts where it stopped and never
leaves a file a later run would read as valid (a ``.json`` that does not parse, names another
frame, or whose arrays are not the sizes it records, is prepared again). Other settings hash to
another folder, leaving this one alone. The user's dataset folder is only ever read.

A split with ``index.json`` is complete, and verified each time it is loaded
(:func:`is_prepared`): the index must list the frames the dataset lists, each frame's arrays the
sizes written, each frame's source files (``000123.json``'s ``sources``: path, size, time and
SHA-256, when the dataset names them) their recorded size and time or, where those changed, their
content. A changed frame is prepared again, a damaged index rebuilt from the frames' records;
``meta.json`` recording other settings than the folder's name stands for is refused
(:func:`check_meta`). A damaged file found while reading (a truncated array, one of another dtype,
maps of different sizes, a radar points file truncated or of another dtype or shape) raises
:class:`~fusion_depth.data.depth_io.DataFileError` naming it; deleting the cache folder prepares
it again.

Broken frames. A frame whose files cannot be read (``make_frame`` raises a ``ValueError``, e.g.
:class:`~fusion_depth.data.depth_io.DataFileError`, or an ``OSError``, e.g. FileNotFoundError)
is handled by ``on_error``:

* ``"raise"`` (what training and evaluation use): the error propagates at the first such frame,
  naming its file; nothing after it is prepared.
* ``"skip"`` (what ``python -m fusion_depth.prepare`` uses): the frame is logged as
  ``skipped <frame id>: <reason>`` and every other frame of every split is still prepared; the
  split gets no ``index.json``, so training still refuses it (preparing it again, and failing on
  the same frame), and at the end :class:`SkippedFramesError` lists every skipped frame. A later
  run prepares only the frames still missing.

Errors writing the cache (a full disk, no permission) are not about one frame and always raise.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import multiprocessing
import os
import shutil
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from multiprocessing.connection import wait
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
from threadpoolctl import threadpool_limits

from fusion_depth.data import RADAR_POINT_FIELDS, EncodedSample, Sample
from fusion_depth.data.depth_io import (
    MAX_ENCODED_DEPTH,
    DataFileError,
    check_npy,
    depth_beyond_encoding,
    encode_depth,
    read_npy,
    write_npy,
)
from fusion_depth.data.radar_points import (
    DEFAULT_MAX_RADAR_POINTS,
    VALID,
    check_max_points,
    in_image,
    inside_image,
    pad_points,
    read_points,
    write_points,
)
from fusion_depth.errors import ArgumentError
from fusion_depth.utils.atomic import remove_orphaned_temporaries, write_json_atomic
from fusion_depth.utils.processes import die_with_parent, pid_alive
from fusion_depth.utils.progress import Progress

try:  # takeovers of a dead process's claim are serialised by a lock file (not on Windows)
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

# Bump when the cache layout changes, so old caches are not reused (3: .npy arrays, were PNGs).
PREPARED_VERSION = 3
INDEX_FILE = "index.json"
META_FILE = "meta.json"
ON_ERROR = ("raise", "skip")  # what prepare_split does with a frame it cannot read
OnError = Literal["raise", "skip"]
# What make_frame raises for a frame's bad or missing files (DataFileError is a ValueError).
FRAME_ERRORS = (ValueError, OSError)
CLAIMS_DIR = ".claims"  # a split's frames being prepared right now, one file each
CLAIMS_LOCK = ".lock"  # in CLAIMS_DIR: held while a dead process's claim is taken over
SHARDED_FILE = ".sharded.json"  # a split a sharded prepare has started and not finished
# A claim older than this is taken over (its process died on another machine; on this one a
# claim is taken over as soon as its process is gone). A frame takes seconds.
CLAIM_STALE_S = 600.0
# How long stopped workers get to end their writes before they are killed (an interrupt must
# end prepare within a second or two, even with a worker deep in a long C call).
STOP_GRACE_S = 1.0
# The index.json of each split this process verified, by its (mtime, size, frame list):
# training builds a reader per split, and each would verify every split again.
_VERIFIED: dict[str, tuple] = {}

log = logging.getLogger(__name__)


@dataclass
class PreparedFrame:
    """One frame as a dataset's prepare step produces it (arrays at the cached resolution)."""

    # Depth maps hold metres up to MAX_ENCODED_DEPTH (255.996 m, what the cache's uint16 in
    # 1/256 m holds; a frame with a farther one is refused); NaN, inf and < 0 are stored as 0.
    image: np.ndarray  # uint8 (H, W, 3)
    sparse: np.ndarray  # float (H, W) metres, 0 = no return
    depth: np.ndarray  # float (H, W) metres, 0 = invalid: measured points only
    condition: str
    filled: np.ndarray | None = None  # float (H, W) metres: densified ground truth for training
    # (top, left, height, width) of the original frame in the arrays when a reader cropped or
    # padded it: evaluation crops (eval.crop) are fractions of the original frame.
    frame_box: tuple[int, int, int, int] | None = None
    # float32 (M, K) radar returns, columns RADAR_POINT_FIELDS, nearest first (radar_points.
    # point_rows), every return drawn in ``sparse``; None for a dataset without a radar. A radar
    # dataset gives every frame an array, (0, K) when it has no return.
    radar_points: np.ndarray | None = None
    # float32 (N, 3) ground truth at the dataset's full resolution (rows y, x, depth: each
    # pixel's centre in the arrays' coordinates, metres), for eval.resolution=full; None where
    # the reader keeps none. A split gives every frame an array or none.
    full_points: np.ndarray | None = None


@dataclass(frozen=True)
class SkippedFrame:
    """A frame ``prepare_split(..., on_error="skip")`` could not prepare, and why (one line)."""

    frame_id: str
    reason: str


@dataclass(frozen=True)
class SplitReport:
    """How one split folder fared in an ``on_error="skip"`` prepare: ``total`` frames, of which
    ``skipped`` could not be prepared (the rest are in the cache)."""

    split: str
    total: int
    skipped: tuple[SkippedFrame, ...] = ()

    @property
    def prepared(self) -> int:
        return self.total - len(self.skipped)

    def line(self) -> str:
        """``train: 3 of 4 frames prepared; skipped 1: train/a02``."""
        text = f"{self.split}: {self.prepared} of {self.total} frames prepared"
        if self.skipped:
            text += f"; skipped {len(self.skipped)}: " + ", ".join(s.frame_id for s in self.skipped)
        return text


class SkippedFramesError(ValueError):
    """Some frames could not be prepared (``on_error="skip"``); every other frame was.

    Raised once every split was tried. ``reports`` holds one :class:`SplitReport` per split
    folder tried, complete ones included; the splits with skipped frames have no ``index.json``.
    """

    def __init__(self, reports: Sequence[SplitReport]) -> None:
        self.reports = list(reports)
        skipped = [frame for report in self.reports for frame in report.skipped]
        shown = "; ".join(f"{frame.frame_id} ({frame.reason})" for frame in skipped[:3])
        more = f"; and {len(skipped) - 3} more" if len(skipped) > 3 else ""
        super().__init__(
            f"{len(skipped)} frame(s) could not be prepared: {shown}{more}. Their splits are not "
            "marked prepared; fix or remove those files and prepare again (frames already "
            "prepared are kept)"
        )

    def __reduce__(self):
        return type(self), (self.reports,)


class IncompleteSplitError(ValueError):
    """A split a sharded prepare started is not complete yet: ``done`` of ``total`` frames are
    in the cache. Raised by a shard once its own frames are done while others are still
    missing, and by training on such a split (it does not prepare frames other shards own).
    ``hint``: one line when another sharded prepare of the dataset runs with other settings
    (the shards were started differently, so each waits for frames the others never make)."""

    def __init__(
        self,
        split_dir: Path,
        done: int,
        total: int,
        num_shards: int | None,
        hint: str | None = None,
    ) -> None:
        self.split_dir, self.done, self.total, self.num_shards = split_dir, done, total, num_shards
        self.hint = hint
        self.splits: list[IncompleteSplitError] = [self]  # prepare_splits: every such split
        shards = f" by {num_shards} shards" if num_shards else ""
        super().__init__(
            f"{split_dir}: {done} of {total} frames prepared, {total - done} missing: the split "
            f"is being prepared{shards} and is usable once every shard has finished (run the "
            "missing shards, or python -m fusion_depth.prepare without shards to finish it here)"
            + (f"; {hint}" if hint else "")
        )

    def __reduce__(self):
        return type(self), (self.split_dir, self.done, self.total, self.num_shards, self.hint)


class CacheFullError(OSError):
    """The disk holding the cache is full: one line naming the cache folder. The frames written
    before are whole (each went through a temporary name), so prepare resumes once there is
    room."""


@dataclass(frozen=True)
class PrepareOptions:
    """How :func:`prepare_split` spreads its frames (``python -m fusion_depth.prepare`` sets
    them from ``prepare.*``; training prepares with the defaults).

    Args:
        workers: processes preparing frames at once (forked: each takes the next unclaimed
            frame). The cache is the same file for file, whatever the number.
        shard: this process prepares the frames at positions ``shard, shard + num_shards, ...``
            of each split.
        num_shards: how many processes (machines, SLURM jobs) share the splits.
        finish_sharded: prepare a split that a sharded prepare left unfinished (``prepare``
            does); False (training) raises :class:`IncompleteSplitError` instead.
    """

    workers: int = 1
    shard: int = 0
    num_shards: int = 1
    finish_sharded: bool = False

    def __post_init__(self) -> None:
        for name, value, minimum in (
            ("workers", self.workers, 1),
            ("num_shards", self.num_shards, 1),
        ):
            if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
                raise ArgumentError(
                    f"{{{name}}}={value!r}: expected an integer >= {minimum}",
                    name,
                    owner=PrepareOptions,
                )
        shard_ok = isinstance(self.shard, int) and not isinstance(self.shard, bool)
        if not shard_ok or not 0 <= self.shard < self.num_shards:
            raise ArgumentError(
                f"{{shard}}={self.shard!r}: expected an integer in [0, {self.num_shards}) "
                f"({{num_shards}}={self.num_shards})",
                "shard",
                "num_shards",
                owner=PrepareOptions,
            )


_OPTIONS: ContextVar[PrepareOptions | None] = ContextVar("prepare_options", default=None)


def current_prepare_options() -> PrepareOptions:
    """The options of the innermost :func:`prepare_options` block (the defaults outside one)."""
    return _OPTIONS.get() or PrepareOptions()


@contextmanager
def prepare_options(options: PrepareOptions) -> Iterator[PrepareOptions]:
    """Every :func:`prepare_split` inside the block uses ``options`` (readers build their caches
    deep inside their constructors; ``python -m fusion_depth.prepare`` wraps them in this)."""
    token = _OPTIONS.set(options)
    try:
        yield options
    finally:
        _OPTIONS.reset(token)


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity mask, e.g. a SLURM allocation)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


@dataclass(frozen=True)
class SplitJob:
    """The arguments of one :func:`prepare_split` call, for :func:`prepare_splits`."""

    cache: Path
    split: str
    frame_ids: Sequence[str]
    make_frame: Callable[[str], PreparedFrame]
    params: dict[str, Any]
    # The files frame ``id`` is made from (PreparedDataset.frame_files), whose sizes, times
    # and content digests its record keeps, so that a changed file prepares the frame again.
    sources: Callable[[str], Sequence[Path]] | None = None


def check_on_error(on_error: str) -> OnError:
    """``on_error`` itself, or a ValueError naming the choices."""
    if on_error not in ON_ERROR:
        raise ValueError(f"on_error={on_error!r}: expected one of {list(ON_ERROR)}")
    return cast(OnError, on_error)


def not_a_file(path: Path, expected: str) -> OSError:
    """The error for something at ``path`` that stands where a frame's file should be but is not
    a file: IsADirectoryError for a directory, FileNotFoundError for anything else (a dangling
    link). The message names ``path`` and what was ``expected``."""
    if path.is_dir():
        return IsADirectoryError(f"{path}: a directory, expected {expected}")
    return FileNotFoundError(f"{path}: not a readable file (a broken link?), expected {expected}")


def cache_dir(
    root: str | os.PathLike,
    dataset: str,
    params: dict[str, Any],
    read_only: dict[str, Path] | None = None,
) -> Path:
    """``root/dataset/<12 hex digits>``: one folder per distinct set of settings.

    ``read_only`` names the user's dataset folders (``{"root": path}``); a cache that would land
    inside one of them is refused, because those folders are only ever read.
    """
    text = json.dumps({"prepared_version": PREPARED_VERSION, **params}, sort_keys=True)
    cache = Path(root).expanduser() / dataset / hashlib.sha256(text.encode()).hexdigest()[:12]
    if read_only:
        cache = cache.resolve()
        for name, folder in read_only.items():
            if cache.is_relative_to(folder):
                raise ArgumentError(
                    f"cache {cache} is inside {{{name}}}={folder}; the dataset folder is only "
                    "ever read: point FUSION_DEPTH_CACHE ({cache_root}) elsewhere",
                    name,
                    "cache_root",
                    owner=cache_dir,
                )
    return cache


def frames_digest(frame_ids: Sequence[str]) -> str:
    """16 hex digits naming the frame list, in order (``index.json``'s ``frames_digest``)."""
    return hashlib.sha256(json.dumps(list(frame_ids)).encode()).hexdigest()[:16]


def is_prepared(
    cache: Path,
    split: str,
    frame_ids: Sequence[str] | None = None,
    params: dict[str, Any] | None = None,
) -> bool:
    """Whether ``split`` is prepared in ``cache`` and still what made it: its ``index.json``
    lists ``frame_ids`` (when given; else the frames its digest names), each frame's arrays
    have the sizes they were written with, and each source file its size and time (or, where
    they changed, its content digest). ``meta.json`` must record ``params`` (when given).

    A split that fails is made ready to prepare again, keeping what is still valid: a changed
    frame's record is removed (the frame is made again), a damaged index is removed (it is
    written again from the frames' records); a warning names what changed. The leftovers of a
    prepare killed after its index was written (claims, shard marker, temporary files) are
    removed. A split verified once stays verified in this process while its index is unchanged.

    Raises:
        DataFileError: ``meta.json`` records other settings than ``params`` (it was edited, or
            the folder copied from another one), naming the first that differs.
    """
    split_dir = cache / split
    index = split_dir / INDEX_FILE
    if params is not None and index.is_file():
        check_meta(cache, params)
    try:
        stat = index.stat()
    except FileNotFoundError:
        return False
    wanted = None if frame_ids is None else frames_digest(frame_ids)
    if _VERIFIED.get(str(split_dir)) == (stat.st_mtime_ns, stat.st_size, wanted):
        return True
    problem = _verify_split(split_dir, frame_ids)
    if problem is not None:
        log.warning("%s: %s; preparing what changed again", split_dir, problem)
        index.unlink(missing_ok=True)
        return False
    _remove_leftovers(split_dir)
    stat = index.stat()
    _VERIFIED[str(split_dir)] = (stat.st_mtime_ns, stat.st_size, wanted)
    return True


def check_meta(cache: Path, params: dict[str, Any]) -> None:
    """Writes ``cache/meta.json`` (the settings the folder's name is a digest of, with
    :data:`PREPARED_VERSION`) where it is missing; one that records others is refused
    (:func:`check_settings_file`)."""
    check_settings_file(cache / META_FILE, {"prepared_version": PREPARED_VERSION, **params}, cache)


def check_settings_file(path: Path, settings: dict[str, Any], folder: Path) -> None:
    """Writes ``settings`` to ``path`` (``meta.json``: what made the cache ``folder``, whose
    name is a digest of them) where it is missing; one that records other settings is refused.

    The temporary files a killed write of ``path`` left are removed.

    Raises:
        DataFileError: naming ``path`` and the first setting that differs (or saying it is
            unreadable), and what to do: delete ``folder``.
    """
    expected = json.loads(json.dumps(settings))
    again = f"delete {folder} to prepare it again"
    remove_orphaned_temporaries(path.parent, [path.name])  # a killed write's
    try:
        found = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        write_json_atomic(path, expected)
        return
    except (OSError, ValueError, RecursionError) as err:
        raise DataFileError(path, f"unreadable ({one_line(err, 80)}); {again}") from err
    if found == expected:
        return
    if not isinstance(found, dict):
        raise DataFileError(path, f"expected the folder's settings as a JSON object; {again}")
    key = next(k for k in sorted({*found, *expected}) if found.get(k) != expected.get(k))
    raise DataFileError(
        path,
        f"records {key}={json.dumps(found.get(key))}, but the folder's name stands for "
        f"{key}={json.dumps(expected.get(key))} (the file was edited, or the folder copied); "
        f"{again}",
    )


def prepare_split(
    cache: Path,
    split: str,
    frame_ids: Sequence[str],
    make_frame: Callable[[str], PreparedFrame],
    params: dict[str, Any],
    *,
    on_error: OnError = "raise",
    sources: Callable[[str], Sequence[Path]] | None = None,
) -> Path:
    """Writes every frame of ``split`` that is not there yet; returns the split folder.

    ``frame_ids`` must come in the same order every time (they name the files by position);
    ``params`` are recorded in ``meta.json`` for a person to see what the cache holds (one that
    records others is refused: :func:`check_meta`). ``sources(frame_id)``: the files the frame
    is made from; each frame's record keeps their sizes, times and content digests, and a
    frame whose files changed is made again (:func:`is_prepared`). A split with an index is
    verified before it is used (:func:`is_prepared`). The
    current :class:`PrepareOptions` (:func:`prepare_options`) say which frames this process
    prepares and with how many workers. Each frame is claimed before it is made (a file in
    ``.claims/``), so workers, shards and separate processes on one cache each make a frame
    once; a claim whose process is gone is taken over, and the temporary files a killed write
    left are removed with it. Whichever process finds every frame present writes
    ``index.json``, once.

    Raises:
        ValueError: ``frame_ids`` is empty, or ``on_error`` is not one of :data:`ON_ERROR`.
        ValueError, OSError: with ``on_error="raise"``, the first frame whose ``make_frame``
            fails (see the module docstring).
        SkippedFramesError: with ``on_error="skip"``, after the whole split, when frames were
            skipped; the split then has no ``index.json``.
        IncompleteSplitError: frames other shards own are still missing.
        CacheFullError: the cache's disk is full.
        DataFileError: ``meta.json`` records other settings (:func:`check_meta`).
    """
    _prepare_jobs([SplitJob(cache, split, frame_ids, make_frame, params, sources)], on_error)
    return cache / split


@dataclass
class _SplitWork:
    """One split being prepared: its job, the positions this process still has to make, and
    the frames skipped so far."""

    cache: Path
    split: str
    job: _FrameJob
    pending: list[int]
    skipped: list[SkippedFrame] = field(default_factory=list)
    started_with: int | None = None  # the num_shards of the shards this one joined, if other


def _start_split(job: SplitJob, on_error: OnError, options: PrepareOptions) -> _SplitWork | None:
    """Checks ``job``'s split and lists the frames this process has to make; None when the
    split is prepared. Raises what :func:`prepare_split` names, but for skipped frames."""
    cache, split, frame_ids = job.cache, job.split, job.frame_ids
    split_dir = cache / split
    if is_prepared(cache, split, frame_ids, job.params):
        log.info("using the prepared %s split in %s", split, split_dir)
        return None
    if not frame_ids:
        raise ValueError(f"split {split!r}: no frames to prepare (settings: {job.params})")
    with _disk_full_names(cache):
        cache.mkdir(parents=True, exist_ok=True)
        check_meta(cache, job.params)
        split_dir.mkdir(parents=True, exist_ok=True)
        remove_orphaned_temporaries(split_dir, [INDEX_FILE, SHARDED_FILE])
        sharded = _read_sharded(split_dir)
        joined = None  # the count of the shards this one joins, where it is another
        if options.num_shards > 1:
            if _other_num_shards(sharded, options.num_shards):
                joined = sharded
                log.warning(_num_shards_hint(split_dir, sharded, options.num_shards))
            write_json_atomic(split_dir / SHARDED_FILE, {"num_shards": options.num_shards})
        elif sharded is not None and not options.finish_sharded:
            done = len(frame_ids) - len(_missing(split_dir, frame_ids))
            raise IncompleteSplitError(split_dir, done, len(frame_ids), sharded)
        positions = range(options.shard, len(frame_ids), options.num_shards)
        pending = [i for i in positions if _done_record(split_dir, i, frame_ids[i]) is None]
    log.info(
        "%s %s: %d of this process's %d frames to prepare, with %d worker(s)",
        cache.parent.name,
        split,
        len(pending),
        len(positions),
        min(options.workers, max(len(pending), 1)),
    )
    frame_job = _FrameJob(split_dir, tuple(frame_ids), job.make_frame, on_error, job.sources)
    return _SplitWork(cache, split, frame_job, pending, started_with=joined)


def _make_pending(works: Sequence[_SplitWork], workers: int) -> None:
    """Makes every split's pending frames, in one set of workers (a worker that finds no
    frame of a split left goes on to the next, so none waits for another to end a split);
    then waits for the frames another live process claimed."""
    names = ", ".join(work.split for work in works)
    description = f"preparing {works[0].cache.parent.name} {names}" if works else ""
    while active := [work for work in works if work.pending]:
        skipped = _prepare_frames(
            [work.job for work in active], [work.pending for work in active], workers, description
        )
        for work, split_skipped in zip(active, skipped, strict=True):
            work.skipped += split_skipped
            bad = {frame.frame_id for frame in work.skipped}
            ids = work.job.frame_ids
            work.pending = [
                i
                for i in work.pending
                if ids[i] not in bad
                and _done_record(work.job.split_dir, i, ids[i], warn=False) is None
            ]
        waiting = sum(len(work.pending) for work in works)
        if waiting:  # claimed by another live process: wait for it, or for its claim to lapse
            log.info("waiting for %d frame(s) another process is preparing", waiting)
            time.sleep(1.0)


def _finish_split(work: _SplitWork, options: PrepareOptions) -> None:
    """Writes the split's index once every frame is there; raises SkippedFramesError for its
    skipped frames, IncompleteSplitError while other shards' frames are missing."""
    frame_ids = work.job.frame_ids
    with _disk_full_names(work.cache):
        if work.skipped:  # no index: the split stays unprepared until every frame is there
            raise SkippedFramesError([SplitReport(work.split, len(frame_ids), tuple(work.skipped))])
        missing = _missing(work.job.split_dir, frame_ids)
        if missing:
            hints = [
                _shard_count_hint(work, options.num_shards),
                _other_sharded_settings(work.cache, work.split),
            ]
            raise IncompleteSplitError(
                work.job.split_dir,
                len(frame_ids) - len(missing),
                len(frame_ids),
                options.num_shards,
                "; ".join(hint for hint in hints if hint) or None,
            )
        _write_index(work.job.split_dir, frame_ids)


def _other_num_shards(recorded: int | None, num_shards: int) -> bool:
    """Whether a split's shard marker records a count of shards other than ``num_shards``."""
    return bool(recorded) and recorded != num_shards


def _num_shards_hint(split_dir: Path, recorded: int, num_shards: int) -> str:
    """One line: the split was started by ``recorded`` shards, this one runs with
    ``num_shards``."""
    return (
        f"{split_dir} was started with num_shards={recorded} and this shard runs with "
        f"num_shards={num_shards}: shards of different counts split the frames differently, so "
        f"some frames fall to no shard; start every shard with num_shards={recorded}, "
        "or run prepare without shards to finish the split"
    )


def _shard_count_hint(work: _SplitWork, num_shards: int) -> str | None:
    """The hint of :func:`_num_shards_hint` when this shard joined shards of another count, or
    a shard of another count joined it since (its marker now says so); None otherwise."""
    if num_shards <= 1:
        return None
    recorded = work.started_with or _read_sharded(work.job.split_dir)
    if not _other_num_shards(recorded, num_shards):
        return None
    return _num_shards_hint(work.job.split_dir, recorded, num_shards)


def _other_sharded_settings(cache: Path, split: str) -> str | None:
    """One line naming another cache folder of the same dataset that shards are preparing with
    other settings, and the settings that differ (None: there is none)."""
    try:
        ours = json.loads((cache / META_FILE).read_text(encoding="utf-8"))
        folders = sorted(cache.parent.iterdir())
    except (OSError, ValueError, RecursionError):
        return None
    for folder in folders:
        if folder == cache or not (folder / split / SHARDED_FILE).is_file():
            continue
        try:
            theirs = json.loads((folder / META_FILE).read_text(encoding="utf-8"))
        except (OSError, ValueError, RecursionError):
            continue
        if not isinstance(ours, dict) or not isinstance(theirs, dict):
            continue
        keys = [k for k in sorted({*ours, *theirs}) if ours.get(k) != theirs.get(k)]
        if keys:
            shown = ", ".join(
                f"{k}={json.dumps(ours.get(k))} here, {json.dumps(theirs.get(k))} there"
                for k in keys[:3]
            )
            return (
                f"shards are also preparing {folder} with other settings ({shown}): every "
                "shard must be started with the same settings"
            )
    return None


@dataclass(frozen=True)
class _FrameJob:
    """What every worker of one split needs: where, which frames, how to make one, and from
    which files."""

    split_dir: Path
    frame_ids: tuple[str, ...]
    make_frame: Callable[[str], PreparedFrame]
    on_error: OnError
    sources: Callable[[str], Sequence[Path]] | None = None


def _prepare_frames(
    jobs: Sequence[_FrameJob], todos: Sequence[Sequence[int]], workers: int, description: str
) -> list[list[SkippedFrame]]:
    """Makes the frames at positions ``todos[k]`` of each ``jobs[k]`` (claimed one by one), in
    this process or in ``workers`` forked ones, with a progress bar or log lines; returns the
    skipped ones of each job. One set of workers serves every job: a worker forked once per
    split would start cold (0.1 s on a 2-core Xeon, as much as a few light frames), and the
    first to run out of a split's frames would wait for the others to end it.

    Workers ignore Ctrl-C and die with this process (:func:`~fusion_depth.utils.processes.
    die_with_parent`); a worker that dies raises ChildProcessError here. The first error a
    worker raises (with ``on_error="raise"``), an interrupt, or a worker that dies stops every
    worker: each gets SIGTERM, which ends its
    write in progress by removing the temporary file, as any exception does, and SIGKILL after
    :data:`STOP_GRACE_S`. Once every worker has stopped (a second Ctrl-C does not cut this
    short), the temporary files and claims no live process holds are removed.
    """
    todo = [(k, i) for k, positions in enumerate(todos) for i in positions]
    workers = min(workers, len(todo))
    if workers > 1 and "fork" not in multiprocessing.get_all_start_methods():
        log.warning("%d workers: this platform cannot fork; preparing in one", workers)
        workers = 1
    with Progress(len(todo), description, unit="frames", transient=True, logger=log) as progress:
        if workers <= 1:
            try:
                return _by_job(jobs, _work(jobs, todo, progress.advance))
            finally:  # an interrupt between a temporary file's creation and its write's guard
                with _interrupts_deferred():
                    for job in jobs:
                        _remove_orphans(job.split_dir)
        context = multiprocessing.get_context("fork")  # make_frame is a closure: not picklable
        counter = context.Value("i", 0)
        results = context.SimpleQueue()
        processes = [
            context.Process(
                target=_worker_main,
                args=(jobs, todos, k, workers, counter, results, os.getpid()),
                daemon=True,
            )
            for k in range(workers)
        ]
        try:
            # Forked with SIGINT blocked: a Ctrl-C before a worker ignores it stays pending.
            old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
            try:
                for process in processes:
                    process.start()
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
            skipped = _collect_reports(processes, results, counter, progress)
        finally:
            with _interrupts_deferred():
                _stop(processes)
                # A worker stopped mid-write (killed, or signalled again during its cleanup)
                # may have left a temporary file and its claim: with every worker gone, no one
                # will rename or release them.
                for job in jobs:
                    _remove_orphans(job.split_dir)
        return _by_job(jobs, skipped)


def _collect_reports(
    processes: Sequence[Any], results: Any, counter: Any, progress: Progress
) -> list[tuple[int, SkippedFrame]]:
    """The skipped frames every worker of ``processes`` reports on ``results`` once it has
    made its frames, advancing ``progress`` by the frames ``counter`` counts meanwhile. The
    first error a worker reports is raised here, and a worker that dies (or ends without
    reporting) is a ChildProcessError."""
    skipped: list[tuple[int, SkippedFrame]] = []
    reported, seen, running = 0, 0, list(processes)
    while reported < len(processes):
        while not results.empty():
            kind, value = results.get()
            reported += 1
            if kind == "error":
                raise value
            skipped += value
        dead = [p for p in processes if p.exitcode not in (None, 0)]
        if dead and results.empty():
            code = dead[0].exitcode
            how = f"killed by {signal.Signals(-code).name}" if code < 0 else f"exit {code}"
            raise ChildProcessError(
                f"a prepare worker died ({how}; out of memory?); prepare again to go on "
                "(finished frames are kept)"
            )
        now = counter.value
        progress.advance(now - seen)
        seen = now
        if not running:  # every worker has exited: its report is in the queue by now
            if results.empty() and reported < len(processes):
                raise ChildProcessError("a prepare worker ended without reporting")
            continue
        # A worker reports, then exits: waking on its exit (or every 0.1 s, for the progress)
        # ends the split as soon as the last frame is written, not up to a poll later, which
        # on a split of cheap frames was a few percent of its time. An exited worker is
        # reaped at once, so its exit code is known on the next pass (its sentinel is ready
        # before the kernel lets it be reaped).
        for sentinel in wait([p.sentinel for p in running], timeout=0.1):
            ended = next(p for p in running if p.sentinel == sentinel)
            ended.join(STOP_GRACE_S)
            running.remove(ended)
    progress.advance(counter.value - seen)
    return skipped


def _by_job(
    jobs: Sequence[_FrameJob], skipped: Sequence[tuple[int, SkippedFrame]]
) -> list[list[SkippedFrame]]:
    """Each job's skipped frames, once each (a worker that skipped a frame and exited leaves a
    stale claim, so another worker may try the frame again), in the job's frame order."""
    by_job: list[list[SkippedFrame]] = []
    for k, job in enumerate(jobs):
        order = {frame_id: i for i, frame_id in enumerate(job.frame_ids)}
        unique = {frame.frame_id: frame for j, frame in reversed(skipped) if j == k}
        by_job.append(sorted(unique.values(), key=lambda frame: order[frame.frame_id]))
    return by_job


@contextmanager
def _interrupts_deferred() -> Iterator[None]:
    """Ctrl-C is held back inside the block (in the main thread; it arrives after it), so that
    pressing it again cannot cut a cleanup short and leave workers or files behind."""
    if not hasattr(signal, "pthread_sigmask") or (
        threading.current_thread() is not threading.main_thread()
    ):
        yield
        return
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)


def _stop(processes: Sequence[Any], grace: float = STOP_GRACE_S) -> None:
    """Ends the workers still running: SIGTERM (a clean stop), then SIGKILL after ``grace``
    seconds (a worker inside a long C call does not see SIGTERM until it returns)."""
    for process in processes:
        if process.is_alive():
            process.terminate()
    deadline = time.monotonic() + grace
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
        if process.is_alive():
            process.kill()
            process.join()


# What the BLAS and OpenMP libraries a worker loads after it started read for their thread count.
_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def _worker_main(
    jobs: Sequence[_FrameJob],
    todos: Sequence[Sequence[int]],
    start: int,
    workers: int,
    counter: Any,
    results: Any,
    parent: int,
) -> None:
    """A worker: it dies with ``parent`` and ignores Ctrl-C (the parent stops it), SIGTERM
    becomes SystemExit (so the write in progress removes its temporary file, as on any
    exception), then :func:`_work` on each split in turn; reports ``("done", skipped)`` or
    ``("error", exception)``."""
    die_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})

    def stop(signum: int, frame: Any) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, stop)

    def advance(n: int = 1) -> None:
        with counter.get_lock():
            counter.value += n

    # Each worker starts each split at its own place, so the first claims do not collide, and
    # ends the splits in order: the last (val and test: unfilled, cheap) fill the time others
    # spend on their last frame of the first.
    todo = []
    for k, positions in enumerate(todos):
        offset = start * len(positions) // workers
        todo += [(k, i) for i in [*positions[offset:], *positions[:offset]]]
    # Each worker's BLAS (the colorization solver's dense products) gets its share of the
    # cores: OpenBLAS starts a thread per core in every process, N × N threads on N cores.
    # threadpoolctl limits the libraries loaded now; one a fill loads later (SciPy's own
    # OpenBLAS) reads the environment when it starts. Unlimited, two workers' linear fills ran
    # 2-15x slower on 2 cores (docs/results/prepare.md, "Two workers against one, light fills").
    threads = max(1, usable_cores() // workers)
    for variable in _THREAD_VARIABLES:
        os.environ[variable] = str(threads)
    try:
        with threadpool_limits(limits=threads):
            results.put(("done", _work(jobs, todo, advance)))
    except SystemExit:
        raise  # stopped by the parent, which is no longer listening
    except BaseException as err:
        try:
            results.put(("error", err))
        except Exception:  # an exception that does not pickle: its message
            results.put(("error", RuntimeError(one_line(err))))
        raise SystemExit(1) from None


def _work(
    jobs: Sequence[_FrameJob], todo: Sequence[tuple[int, int]], advance: Callable[..., Any]
) -> list[tuple[int, SkippedFrame]]:
    """Claims and makes each frame ``(k, i)`` of ``todo`` (position ``i`` of ``jobs[k]``) that
    no one else has; the skipped ones, with their ``k``."""
    skipped = []
    for k, i in todo:
        # A full disk is named here, where its cache is known (the workers serve every split).
        with _disk_full_names(jobs[k].split_dir.parent):
            frame = _claim_and_make(jobs[k], i, advance)
        if frame is not None:
            skipped.append((k, frame))
    return skipped


def _claim_and_make(job: _FrameJob, i: int, advance: Callable[..., Any]) -> SkippedFrame | None:
    """Claims and makes the frame at position ``i`` unless another has it; the frame when it
    is skipped (``on_error="skip"``)."""
    stem = f"{i:06d}"
    frame_id = job.frame_ids[i]
    # Only the frames this worker makes (or skips) count: every worker walks the whole list,
    # so counting the ones others claimed would count each frame once per worker.
    if not _claim(job.split_dir, stem):
        return None  # another worker or process is making it (or found it broken)
    release, made = True, False
    try:
        if _done_record(job.split_dir, i, frame_id, warn=False) is not None:
            return None  # made by another process before this one claimed it
        made = True
        _remove_temporaries(job.split_dir, stem)
        try:
            sources, frame = _sources_and_frame(job, frame_id)
            _check_frame(frame, frame_id)
        except FRAME_ERRORS as err:
            if job.on_error == "raise":
                raise
            skipped = SkippedFrame(frame_id, one_line(err))
            log.warning("skipped %s: %s", frame_id, skipped.reason)
            release = False  # the other workers leave it; a later run tries it again
            return skipped
        _write_frame(job.split_dir, stem, frame_id, frame, sources)
        return None
    finally:
        if release:
            _release(job.split_dir, stem)
        if made:
            advance()


def _sources_and_frame(job: _FrameJob, frame_id: str) -> tuple[list | None, PreparedFrame]:
    """The frame's :func:`source_entries` (None without ``job.sources``), then the frame. The
    digests come first: a file that changes while the frame is made reads as changed later. A
    file that cannot be read lets ``make_frame`` fail first, with its own message."""
    if job.sources is None:
        return None, job.make_frame(frame_id)
    try:
        sources = source_entries(job.sources(frame_id))
    except OSError:
        job.make_frame(frame_id)  # names the file and what it should be
        raise
    return sources, job.make_frame(frame_id)


# --- claims: which process makes a frame -------------------------------------------------------


def _claim_text() -> str:
    return json.dumps({"host": socket.gethostname(), "pid": os.getpid()})


def _claim(split_dir: Path, stem: str) -> bool:
    """Whether this process now holds ``stem``'s claim: created it, or took over one whose
    process is gone (:func:`_take_over`)."""
    path = split_dir / CLAIMS_DIR / stem
    for _ in range(3):
        try:
            path.parent.mkdir(exist_ok=True)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileNotFoundError:  # the index's writer removed the claims folder just now
            continue
        except FileExistsError:
            if not _take_over(path):
                return False
            continue  # a dead claim, removed: create ours (only one creator can win)
        with os.fdopen(fd, "w") as f:
            f.write(_claim_text())
        return True
    return False


def _take_over(path: Path) -> bool:
    """Removes the claim at ``path`` if its process is gone (:func:`_stale`); whether it did (or
    found it gone). Under the claims folder's lock: without it, two processes could both judge
    one dead claim stale, and the second remove the new claim the first has just created."""
    with _claims_lock(path.parent):
        return _remove_if_stale(path)


def _remove_if_stale(path: Path) -> bool:
    """Under the claims lock: removes the claim at ``path`` if it is stale; whether it is gone
    now. A claim that appears while this runs (created without the lock, so by a live process)
    is never removed: only the file judged stale, by its inode."""
    try:
        inode = path.stat().st_ino
    except FileNotFoundError:
        return True
    if not _stale(path):
        return False
    try:
        if path.stat().st_ino == inode:
            path.unlink()
    except FileNotFoundError:
        pass
    return True


@contextmanager
def _claims_lock(folder: Path) -> Iterator[None]:
    """Holds the exclusive lock of ``folder/.lock`` (an ``flock``, freed by the kernel when its
    holder dies). The lock file may be removed by a cleanup (:func:`_remove_dead_claims`, which
    holds it then): a lock taken on a file no longer at its name is taken again. Without
    ``fcntl`` (Windows, which cannot fork workers either) there is no lock."""
    if fcntl is None:  # pragma: no cover - Windows
        yield
        return
    path = folder / CLAIMS_LOCK
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except FileNotFoundError:  # the folder is gone, and every claim with it
            yield
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            try:
                current = os.fstat(fd).st_ino == os.stat(path).st_ino
            except FileNotFoundError:
                current = False
            if current:
                yield
                return
        finally:
            os.close(fd)


def _stale(path: Path) -> bool:
    """A claim whose process is gone: on this machine, no such pid; elsewhere, older than
    :data:`CLAIM_STALE_S`. An unreadable claim (its writer was killed mid-write) is stale once
    a second old. This process's own claims are left from an earlier call (a frame it found
    broken): stale too."""
    try:
        age = time.time() - path.stat().st_mtime
        owner = json.loads(path.read_text())
    except FileNotFoundError:
        return True
    except (OSError, ValueError):
        return age > 1.0
    if not isinstance(owner, dict) or owner.get("host") != socket.gethostname():
        return age > CLAIM_STALE_S
    pid = owner.get("pid")
    return pid == os.getpid() or not pid_alive(pid)


def _release(split_dir: Path, stem: str) -> None:
    path = split_dir / CLAIMS_DIR / stem
    try:
        if json.loads(path.read_text()) == json.loads(_claim_text()):
            path.unlink()
    except (OSError, ValueError):
        pass


def _remove_dead_claims(split_dir: Path) -> None:
    """Removes the claims whose process is gone (:func:`_stale`), and the claims folder when
    none is left: a stopped or interrupted prepare leaves no claim behind."""
    folder = split_dir / CLAIMS_DIR
    if not folder.is_dir():
        return
    with _claims_lock(folder):
        try:
            claims = [p for p in folder.iterdir() if p.name != CLAIMS_LOCK]
        except FileNotFoundError:
            return
        live = [p for p in claims if not _remove_if_stale(p)]
        if not live:
            (folder / CLAIMS_LOCK).unlink(missing_ok=True)
            try:
                folder.rmdir()
            except OSError:  # another process claimed a frame just now
                pass


# The hidden temporary files of every frame's writes: .000123.image.npy.<owner>.<random>.npy
_TEMPORARIES = ".[0-9]*.*"


def _remove_temporaries(split_dir: Path, stem: str | None = None) -> None:
    """The hidden temporary files (``.000123.image.npy.<owner>.<random>.npy``) that writes
    killed before their rename left, of frame ``stem`` (None: of every frame)."""
    pattern = f".{stem}.*" if stem is not None else _TEMPORARIES
    for path in split_dir.glob(pattern):
        path.unlink(missing_ok=True)


def _remove_orphans(split_dir: Path) -> None:
    """The temporary files whose frame no live process claims (their writer is gone), then the
    dead claims (:func:`_remove_dead_claims`). Those of a frame another process is making now
    stay (it holds the claim until after its renames)."""
    for path in split_dir.glob(_TEMPORARIES):
        claim = split_dir / CLAIMS_DIR / path.name.split(".")[1]
        if not claim.exists() or _stale(claim):
            path.unlink(missing_ok=True)
    _remove_dead_claims(split_dir)


def _remove_leftovers(split_dir: Path) -> None:
    """What a prepare killed after writing the index leaves: claims, the shard marker and
    temporary files (the split is complete, so no process still writes one)."""
    if (split_dir / CLAIMS_DIR).exists():
        shutil.rmtree(split_dir / CLAIMS_DIR, ignore_errors=True)
    (split_dir / SHARDED_FILE).unlink(missing_ok=True)
    _remove_temporaries(split_dir)
    remove_orphaned_temporaries(split_dir, [INDEX_FILE, SHARDED_FILE])


# --- the split's state ---------------------------------------------------------------------------


def source_entries(paths: Sequence[Path]) -> list[list]:
    """``[path, size, mtime_ns, sha256]`` of each file (the digest's first 32 hex digits), what
    a frame's record keeps of the files it was made from.

    Raises:
        OSError: a file cannot be read (FileNotFoundError for a missing one), naming it.
    """
    entries = []
    for path in paths:
        stat = os.stat(path)
        entries.append([str(path), stat.st_size, stat.st_mtime_ns, _file_digest(path)])
    return entries


def _file_digest(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()[:32]


def _sources_problem(entries: Any) -> tuple[str | None, list | None]:
    """(why the recorded source files no longer match, or None; the entries with new sizes and
    times where only those changed and the content is the same, or None). A file whose size and
    time are as recorded is trusted without reading it."""
    if not isinstance(entries, list):
        return "its record's sources are damaged", None
    refreshed, changed = [], False
    for entry in entries:
        if not (isinstance(entry, list) and len(entry) == 4 and isinstance(entry[0], str)):
            return "its record's sources are damaged", None
        path, size, mtime, digest = entry
        try:
            stat = os.stat(path)
        except OSError:
            return f"{path} is gone", None
        if (stat.st_size, stat.st_mtime_ns) != (size, mtime):
            try:
                if stat.st_size != size or _file_digest(path) != digest:
                    return f"{path} changed", None
            except OSError:
                return f"{path} cannot be read", None
            changed = True
        refreshed.append([path, stat.st_size, stat.st_mtime_ns, digest])
    return None, refreshed if changed else None


def _arrays_problem(split_dir: Path, record: dict, headers: bool) -> str | None:
    """Why the frame's arrays are not those its record names (missing, or of another size
    than written), or None. A record from before sizes were kept (version 0.2.0) has its
    arrays' headers checked against their sizes when ``headers`` (a resumed prepare)."""
    stem = split_dir / record["file"]
    sizes = record.get("arrays")
    if isinstance(sizes, dict):
        for name, size in sizes.items():
            path = f"{stem}.{name}.npy"
            try:
                if os.stat(path).st_size != size:
                    return f"{path} is not the size it was written with"
            except OSError:
                return f"{path} is missing"
        return None
    if not headers:
        return None
    expected: list[tuple[str, Any, tuple]] = [
        ("image", np.uint8, (None, None, 3)),
        ("sparse", np.uint16, (None, None)),
        ("depth", np.uint16, (None, None)),
    ]
    if record["filled"]:
        expected.append(("filled", np.uint16, (None, None)))
    if record.get("radar_points"):
        expected.append(("radar", np.float32, (None, len(RADAR_POINT_FIELDS))))
    if "full_points" in record:
        expected.append(("fullres", np.float32, (record["full_points"], 3)))
    for name, dtype, shape in expected:
        try:
            check_npy(f"{stem}.{name}.npy", dtype, shape, "prepared array")
        except (OSError, ValueError) as err:
            return one_line(err, 200)
    return None


def _frame_problem(
    split_dir: Path, record: dict, headers: bool = False
) -> tuple[str | None, dict | None]:
    """(why the prepared frame of ``record`` is stale, or None; the record with its sources'
    new sizes and times where only those changed, or None)."""
    problem = _arrays_problem(split_dir, record, headers)
    if problem is not None or "sources" not in record:
        return problem, None
    problem, refreshed = _sources_problem(record["sources"])
    if problem is not None or refreshed is None:
        return problem, None
    return None, {**record, "sources": refreshed}


def _done_record(split_dir: Path, i: int, frame_id: str, warn: bool = True) -> dict | None:
    """Frame ``i``'s record when the frame is done and current (its arrays whole, its sources
    unchanged; a record whose sources only changed in time is rewritten), else None; ``warn``
    logs why a recorded frame is not current."""
    path = split_dir / f"{i:06d}.json"
    record = _read_record(path)
    if record is None or record.get("id") != frame_id:
        return None
    problem, refreshed = _frame_problem(split_dir, record, headers=True)
    if problem is not None:
        if warn:
            log.warning("%s: %s; preparing frame %s again", path, problem, frame_id)
        return None
    if refreshed is not None:
        write_json_atomic(path, refreshed)
        return refreshed
    return record


def _missing(split_dir: Path, frame_ids: Sequence[str]) -> list[int]:
    return [
        i for i, frame_id in enumerate(frame_ids) if _done_record(split_dir, i, frame_id) is None
    ]


def _read_sharded(split_dir: Path) -> int | None:
    """The ``num_shards`` of the sharded prepare that started this split (None: none did)."""
    try:
        data = json.loads((split_dir / SHARDED_FILE).read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError, RecursionError):
        return 0
    shards = data.get("num_shards") if isinstance(data, dict) else None
    return shards if isinstance(shards, int) and not isinstance(shards, bool) else 0


def _write_index(split_dir: Path, frame_ids: Sequence[str]) -> None:
    """``index.json`` from the frames' records, by one process (the index claim's holder), then
    the claims, the shard marker and any temporary file are removed: the split is then the same,
    file for file, as one prepared in a single uninterrupted run."""
    while not _claim(split_dir, INDEX_FILE):  # another process is writing it: wait for it
        if (split_dir / INDEX_FILE).is_file():
            return
        time.sleep(0.2)
    try:
        if (split_dir / INDEX_FILE).is_file():
            return
        records = [_done_record(split_dir, i, frame_id) for i, frame_id in enumerate(frame_ids)]
        if any(record is None for record in records):
            return  # cannot happen: every frame was there a moment ago, and frames stay
        index = {"split": split_dir.name, "frames_digest": frames_digest(frame_ids)}
        write_json_atomic(split_dir / INDEX_FILE, {**index, "frames": records})
        _remove_leftovers(split_dir)
        log.info("prepared %d frames into %s", len(records), split_dir)
    finally:
        shutil.rmtree(split_dir / CLAIMS_DIR, ignore_errors=True)


def _verify_split(split_dir: Path, frame_ids: Sequence[str] | None) -> str | None:
    """Why the prepared split in ``split_dir`` is not what made it (None: it is): its index is
    damaged or lists other frames than ``frame_ids`` (or than its digest names), or frames
    changed (:func:`_frame_problem`; their records are removed, so those frames are made
    again). Records whose sources only changed in time are rewritten, index included."""
    index = split_dir / INDEX_FILE
    try:
        data = json.loads(index.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as err:
        return f"{INDEX_FILE} is unreadable ({one_line(err, 80)})"
    problem = index_problem(data, frame_ids)
    if problem is not None:
        return f"{INDEX_FILE} {problem}"
    frames, stale, refreshed = data["frames"], [], False
    for k, record in enumerate(frames):
        problem, new = _frame_problem(split_dir, record)
        if problem is not None:
            stale.append(problem)
            (split_dir / f"{record['file']}.json").unlink(missing_ok=True)
        elif new is not None:
            frames[k], refreshed = new, True
            write_json_atomic(split_dir / f"{record['file']}.json", new)
    if stale:
        return f"{len(stale)} of {len(frames)} frames changed since they were prepared ({stale[0]})"
    if refreshed:
        write_json_atomic(index, data)
    return None


def index_problem(data: Any, frame_ids: Sequence[str] | None = None) -> str | None:
    """What is wrong with the parsed ``index.json`` ``data``, or None: it must be as
    :func:`prepare_split` writes it, each frame ``i`` in file ``i`` once, listing ``frame_ids``
    when given, and the frames its ``frames_digest`` names (an index of version 0.2.0 has none)."""
    frames = data.get("frames") if isinstance(data, dict) else None
    if not isinstance(frames, list) or not all(_valid_record(f) for f in frames):
        return (
            'is not {"split": name, "frames": [{"id", "file", "condition", "filled"}, ...]} as '
            "prepare_split writes it"
        )
    if not frames:
        return "lists no frames"
    if len({bool(frame.get("radar_points")) for frame in frames}) > 1:
        return "says some frames have radar points and others not, expected all or none"
    if len({"full_points" in frame for frame in frames}) > 1:
        return "says some frames have full-resolution points and others not, expected all or none"
    ids = [frame["id"] for frame in frames]
    if any(frame["file"] != f"{i:06d}" for i, frame in enumerate(frames)):
        return "does not list each frame once, in the order of its files"
    if len(set(ids)) != len(ids):
        return "lists a frame more than once"
    if frame_ids is not None and ids != list(frame_ids):
        return f"lists {len(ids)} frames, other than the dataset's {len(frame_ids)}"
    digest = data.get("frames_digest")
    if digest is not None and digest != frames_digest(ids):
        return "lists other frames than its frames_digest names"
    return None


@contextmanager
def _disk_full_names(cache: Path) -> Iterator[None]:
    """A write that fails for want of space becomes :class:`CacheFullError`, one line naming
    the cache (numpy reports a full disk as ``479232 requested and 133056 written``, with no
    errno: the free space tells)."""
    try:
        yield
    except CacheFullError:
        raise
    except OSError as err:
        full = err.errno in (errno.ENOSPC, errno.EDQUOT)
        if not full and err.errno is None and "requested and" in str(err):
            try:
                full = shutil.disk_usage(cache).free < 64 * 2**20
            except OSError:
                full = False
        if not full:
            raise
        raise CacheFullError(
            errno.ENOSPC,
            f"{cache}: the disk is full; free space there or point FUSION_DEPTH_CACHE (the "
            "cache folder) at another disk, then prepare again (finished frames are kept)",
        ) from err


def _write_frame(
    split_dir: Path, stem: str, frame_id: str, frame: PreparedFrame, sources: list | None = None
) -> dict:
    """Write a checked frame's arrays (each flushed to disk), then its record, with each
    array's size and, when given, the source files' :func:`source_entries`; returns the
    record."""
    arrays = {"image": frame.image}
    for name in ("sparse", "depth", "filled"):
        depth = getattr(frame, name)
        if depth is not None:
            arrays[name] = encode_depth(depth)
    for name, array in arrays.items():
        write_npy(split_dir / f"{stem}.{name}.npy", array)
    if frame.radar_points is not None:
        write_points(split_dir / f"{stem}.radar.npy", frame.radar_points)
        arrays["radar"] = frame.radar_points
    if frame.full_points is not None:
        full = np.ascontiguousarray(frame.full_points, dtype=np.float32).reshape(-1, 3)
        write_npy(split_dir / f"{stem}.fullres.npy", full)
        arrays["fullres"] = full
    record: dict[str, Any] = {
        "id": frame_id,
        "file": stem,
        "condition": frame.condition,
        "filled": frame.filled is not None,
    }
    if frame.radar_points is not None:
        record["radar_points"] = True
    if frame.full_points is not None:
        record["full_points"] = len(arrays["fullres"])
    if frame.frame_box is not None:
        record["frame_box"] = [int(v) for v in frame.frame_box]
    record["arrays"] = {name: os.stat(split_dir / f"{stem}.{name}.npy").st_size for name in arrays}
    if sources is not None:
        record["sources"] = sources
    # Last, so the frame counts as done only once every array is in place.
    write_json_atomic(split_dir / f"{stem}.json", record)
    return record


def prepare_splits(jobs: Sequence[SplitJob], *, on_error: OnError = "raise") -> None:
    """:func:`prepare_split` for each job, in order.

    With ``on_error="raise"`` the first broken frame raises. With ``"skip"``, a split with
    skipped frames does not stop the next ones: every split is tried, then one
    :class:`SkippedFramesError` reports all of them (complete splits included). A split that
    other shards have still to finish does not stop the next ones either: once every split was
    tried, :class:`IncompleteSplitError` is raised for the first, with all of them in its
    ``splits``.
    """
    older = older_caches(jobs[0].cache) if jobs else []
    if older:
        log.info(
            "%d cache folder(s) of an older format beside %s are no longer read (%s); delete "
            "them to free the space",
            len(older),
            jobs[0].cache,
            ", ".join(str(folder) for folder in older),
        )
    _prepare_jobs(jobs, on_error)


def _prepare_jobs(jobs: Sequence[SplitJob], on_error: OnError) -> None:
    """:func:`prepare_splits` without its note on older caches: every split is checked, then
    their frames made by one set of workers (:func:`_prepare_frames`), then each split's index
    written."""
    check_on_error(on_error)
    options = current_prepare_options()
    reports = [SplitReport(job.split, len(job.frame_ids)) for job in jobs]
    incomplete: dict[int, IncompleteSplitError] = {}
    works: dict[int, _SplitWork] = {}
    for k, job in enumerate(jobs):
        try:
            work = _start_split(job, on_error, options)
        except IncompleteSplitError as err:
            incomplete[k] = err
            continue
        if work is not None:
            works[k] = work
    _make_pending(list(works.values()), options.workers)
    for k, work in works.items():
        try:
            _finish_split(work, options)
        except SkippedFramesError as err:
            reports[k] = err.reports[0]
        except IncompleteSplitError as err:
            incomplete[k] = err
    if any(report.skipped for report in reports):
        raise SkippedFramesError(reports)
    if incomplete:
        first, *_ = (incomplete[k] for k in sorted(incomplete))
        first.splits = [incomplete[k] for k in sorted(incomplete)]
        raise first


def older_caches(cache: Path) -> list[Path]:
    """The folders beside ``cache`` (same dataset, other settings) whose ``meta.json`` records
    an older :data:`PREPARED_VERSION`: nothing reads them any more."""
    older = []
    for folder in sorted(cache.parent.glob("*/")) if cache.parent.is_dir() else []:
        try:
            meta = json.loads((folder / META_FILE).read_text(encoding="utf-8"))
        except (OSError, ValueError, RecursionError):
            continue
        version = meta.get("prepared_version") if isinstance(meta, dict) else None
        if isinstance(version, int) and version < PREPARED_VERSION and folder != cache:
            older.append(folder)
    return older


def one_line(err: BaseException, limit: int = 300) -> str:
    """The first line of ``err``'s message (its type's name when empty), at most ``limit``
    characters: what a ``skipped <what>: <reason>`` line shows."""
    lines = str(err).strip().splitlines()
    text = lines[0] if lines else type(err).__name__
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _read_record(path: Path) -> dict | None:
    """A finished frame's record, or None when there is none or it is damaged (redo the frame)."""
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as err:
        log.warning("%s: unreadable frame record (%s); preparing the frame again", path, err)
        return None
    return record if _valid_record(record) else None


def _valid_record(record: Any) -> bool:
    """Whether ``record`` is a frame record as :func:`prepare_split` writes it (``file`` all
    digits, so a damaged index can never point outside the split folder)."""
    if not isinstance(record, dict):
        return False
    box = record.get("frame_box")
    return (
        isinstance(record.get("id"), str)
        and isinstance(record.get("file"), str)
        and record["file"].isdigit()
        and isinstance(record.get("condition"), str)
        and isinstance(record.get("filled"), bool)
        and isinstance(record.get("radar_points", False), bool)
        and _count_or_absent(record.get("full_points"))
        and (
            box is None
            or isinstance(box, list)
            and len(box) == 4
            and all(isinstance(v, int) and not isinstance(v, bool) for v in box)
        )
    )


def _count_or_absent(value: Any) -> bool:
    """Whether ``value`` is None or a count (an int >= 0, not a bool)."""
    return value is None or (isinstance(value, int) and not isinstance(value, bool) and value >= 0)


def _check_frame(frame: PreparedFrame, frame_id: str) -> None:
    image = np.asarray(frame.image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(
            f"frame {frame_id}: image is {image.dtype} {image.shape}, expected uint8 (H, W, 3)"
        )
    h, w = image.shape[:2]
    maps = {"sparse": frame.sparse, "depth": frame.depth, "filled": frame.filled}
    for name, array in maps.items():
        if array is None:
            continue
        if np.shape(array) != (h, w):
            raise ValueError(
                f"frame {frame_id}: {name} has shape {np.shape(array)}, expected the image's "
                f"{(h, w)}"
            )
        far = depth_beyond_encoding(array)
        if far is not None:
            raise ValueError(
                f"frame {frame_id}: {name} holds depths up to {far:.6g} m, beyond the "
                f"{MAX_ENCODED_DEPTH:.3f} m the prepared cache stores (uint16 in 1/256 m); make "
                "them 0 (no value) in load_frame, e.g. with a maximum range"
            )
    points = frame.radar_points
    if points is not None and (
        points.ndim != 2
        or points.shape[1] != len(RADAR_POINT_FIELDS)
        or not np.isfinite(points).all()
        or not (points[:, VALID] == 1).all()
        or not inside_image(points, h, w)
    ):
        raise ValueError(
            f"frame {frame_id}: radar_points {points.dtype} {points.shape}, expected finite "
            f"(M, {len(RADAR_POINT_FIELDS)}) rows with valid = 1 and (u, v) inside the {h}x{w} "
            "image (radar_points.point_rows)"
        )
    full = frame.full_points
    if full is not None:
        full = np.asarray(full)
        if (
            full.ndim != 2
            or full.shape[1] != 3
            or not np.isfinite(full).all()
            or not (full[:, 2] > 0).all()
            or not in_image(full[:, 1], full[:, 0], h, w).all()
        ):
            raise ValueError(
                f"frame {frame_id}: full_points {full.dtype} {full.shape}, expected finite (N, 3) "
                f"rows y, x, depth > 0 with (x, y) inside the {h}x{w} image"
            )


class PreparedSplit:
    """Reads one prepared split: :meth:`encoded_sample` as stored (uint8 image, uint16 depth
    maps: what the datamodule's loaders pass on), ``split[i]`` as the float
    :class:`~fusion_depth.data.Sample`. ``use_filled`` serves the filled ground truth as
    ``depth`` where it exists (training); evaluation leaves it off and scores the measured
    points. A split prepared with radar points serves ``radar_points`` as float32
    (``max_radar_points``, K): the nearest returns, zero rows after. A split prepared with
    full-resolution ground truth serves it as ``depth_points``, float32 (Q, 3) rows ``y, x,
    depth``, zero rows after (Q: the split's largest count).

    A map-style dataset (``len(split)``, ``split[i]``), as torch's ``DataLoader`` takes it. Torch
    is imported on the first read, not with this module: ``prepare``, which only writes splits,
    starts without it (about 2 s, a fixed cost that no number of workers shortens).

    Raises:
        FileNotFoundError: the split has no ``index.json``.
        DataFileError: the index is damaged (when reading a frame: a damaged file of it).
        ValueError: ``max_radar_points`` is not an integer >= 1.
    """

    def __init__(
        self,
        split_dir: str | os.PathLike,
        use_filled: bool = False,
        max_radar_points: int = DEFAULT_MAX_RADAR_POINTS,
    ) -> None:
        self.max_radar_points = check_max_points(max_radar_points)
        self.split_dir = Path(split_dir)
        index = self.split_dir / INDEX_FILE
        if not index.is_file():
            raise FileNotFoundError(f"{index}: not a prepared split (run fusion_depth.prepare)")
        again = f"delete {self.split_dir} to prepare the split again"
        try:
            data = json.loads(index.read_text(encoding="utf-8"))
        except (OSError, ValueError, RecursionError) as err:
            raise DataFileError(index, f"unreadable prepared index ({err}); {again}") from err
        problem = index_problem(data)
        if problem is not None:
            raise DataFileError(index, f"{problem}; {again}")
        frames = data["frames"]
        self.frames: list[dict] = frames
        # Full-resolution points pad to the split's largest count, so a split's samples batch.
        self.max_full_points = max(frame.get("full_points") or 0 for frame in frames)
        self.use_filled = use_filled
        # Set by the datamodule for a model whose loss reads the measured ground truth beside
        # the filled one (RadarNet's): served as depth_measured where depth is the filled map.
        self.serve_measured = False
        self.conditions = [frame["condition"] for frame in self.frames]

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> Sample:
        """Frame ``index`` in the float form (:func:`~fusion_depth.data.encoding.decode_sample`
        of :meth:`encoded_sample`)."""
        from fusion_depth.data.encoding import decode_sample

        return decode_sample(self.encoded_sample(index))  # type: ignore[return-value]

    def encoded_sample(self, index: int) -> EncodedSample:
        """Frame ``index`` as stored: image uint8 (3, H, W), ``sparse`` and ``depth`` (the
        filled map with ``use_filled``) uint16 (1, H, W) in 1/256 m, plus ``frame_box`` and
        ``radar_points`` where prepared, and the measured map as ``depth_measured`` beside a
        filled ``depth`` with :attr:`serve_measured`. What the datamodule's loaders pass to the
        device.

        Raises:
            FileNotFoundError: a file of the frame is missing.
            DataFileError: a file is damaged (truncated, another dtype, a map of another size
                than the image), naming it.
        """
        import torch

        from fusion_depth.data.encoding import encode_sample

        frame = self.frames[index]
        stem = self.split_dir / frame["file"]
        depth_file = "filled" if self.use_filled and frame["filled"] else "depth"
        again = f"delete {self.split_dir} to prepare the split again"
        image = read_npy(f"{stem}.image.npy", np.uint8, (None, None, 3), "prepared image", again)
        h, w = image.shape[:2]
        size = f"maps have the size of {stem}.image.npy; {again}"
        maps = {
            key: read_npy(f"{stem}.{name}.npy", np.uint16, (h, w), "prepared depth map", size)
            for key, name in (("sparse", "sparse"), ("depth", depth_file))
        }
        sample = encode_sample(image, maps["sparse"], maps["depth"], frame["condition"])
        if self.serve_measured and depth_file == "filled":
            measured = read_npy(f"{stem}.depth.npy", np.uint16, (h, w), "prepared depth map", size)
            sample["depth_measured"] = torch.from_numpy(measured)[None]
        if "frame_box" in frame:
            sample["frame_box"] = torch.tensor(frame["frame_box"], dtype=torch.long)
        if frame.get("radar_points"):
            path = f"{stem}.radar.npy"
            rows = read_points(path)
            if not inside_image(rows, h, w):
                raise DataFileError(
                    path,
                    f"radar points outside the {h}x{w} image of {stem}.image.npy; {again}",
                )
            sample["radar_points"] = torch.from_numpy(pad_points(rows, self.max_radar_points))
        if "full_points" in frame:
            rows = read_npy(
                f"{stem}.fullres.npy",
                np.float32,
                (frame["full_points"], 3),
                "prepared full-resolution points",
                again,
            )
            padded = np.zeros((self.max_full_points, 3), dtype=np.float32)
            padded[: len(rows)] = rows
            sample["depth_points"] = torch.from_numpy(padded)
        return sample
