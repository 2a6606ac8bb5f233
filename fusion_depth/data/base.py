"""The base class of every dataset read from files: it holds the ceremony, a dataset fills in
what is its own (in the manner of monodepth2's ``datasets/mono_dataset.py``).

A dataset module subclasses :class:`PreparedDataset`, checks and stores its own options in
``__init__``, then calls ``super().__init__(split, root, cache_root, height, width, on_error)``,
and fills in two methods:

* :meth:`~PreparedDataset.list_frames`: every split's frames, ``{frame id: what
  load_frame needs}``, in the same order every time, and a digest of their files
  (:class:`FrameList`);
* :meth:`~PreparedDataset.load_frame`: one frame's arrays at the network's input size;

and may fill in a third, :meth:`~PreparedDataset.frame_files`: the files one frame is made from.
Their sizes, times and content digests go into the frame's record, so a file replaced later
prepares that frame again; without it the frames' files are trusted once prepared.

The base class checks the split, ``on_error`` and the input size, resolves the dataset folder,
prepares every split once into the shared cache (:mod:`fusion_depth.data.cache`: atomic,
resumable, the dataset folder only ever read) and then serves the requested split as
:class:`~fusion_depth.data.Sample` dicts. The guide docs/guides/datasets/own-dataset.md walks
through one.
"""

from __future__ import annotations

import numbers
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from fusion_depth.data import CONDITIONS, SPLITS
from fusion_depth.data.cache import (
    OnError,
    PreparedFrame,
    PreparedSplit,
    SplitJob,
    cache_dir,
    check_on_error,
    is_prepared,
    prepare_splits,
)
from fusion_depth.data.folders import require_root
from fusion_depth.data.radar_points import DEFAULT_MAX_RADAR_POINTS, check_max_points
from fusion_depth.errors import ArgumentError

# The encoder halves the resolution five times, and the decoder's skips must line up.
SIZE_MULTIPLE = 32


def check_split(split: str) -> str:
    """``split`` itself, or a ValueError naming the choices (:data:`~fusion_depth.data.SPLITS`)."""
    if split not in SPLITS:
        raise ValueError(f"split={split!r}: expected one of {list(SPLITS)}")
    return split


def check_size(height: int, width: int, multiple: int = SIZE_MULTIPLE) -> tuple[int, int]:
    """``(height, width)`` as ints, or an ArgumentError naming ``height`` or ``width`` when one is
    not a positive multiple of ``multiple`` (:data:`SIZE_MULTIPLE`: the encoder downsamples by
    32; 1 for frames served at any size, as a released network that is not padded takes them:
    ``dataset.reader.size_multiple``)."""
    for name, size in (("height", height), ("width", width)):
        whole = isinstance(size, numbers.Integral) and not isinstance(size, bool)
        if not whole or size <= 0 or size % multiple:
            expected = (
                f"a positive multiple of {multiple} (the encoder downsamples by {multiple})"
                if multiple > 1
                else "a positive integer"
            )
            raise ArgumentError(f"{{{name}}}={size!r}: expected {expected}", name, owner=check_size)
    return int(height), int(width)


def check_size_multiple(value: int) -> int:
    """``value`` as an int: the multiple of 32 (the default) or 1 (any size) that a dataset's
    ``height`` and ``width`` must be."""
    if value not in (1, SIZE_MULTIPLE) or isinstance(value, bool):
        raise ArgumentError(
            f"{{size_multiple}}={value!r}: expected {SIZE_MULTIPLE} (what the encoders need) or "
            "1 (frames at any size, for a network that takes them unpadded: released=radarnet)",
            "size_multiple",
            owner=check_size_multiple,
        )
    return int(value)


def check_depth_range(min_depth: float, max_depth: float, owner: object = None) -> None:
    """The depth range a dataset, a network and its input fusion share: ``0 < min_depth <
    max_depth`` (metres). The one place it is checked.

    Raises:
        ArgumentError: naming ``min_depth`` and ``max_depth``, as arguments of ``owner`` (the
            caller that takes them; this function's when None).
    """
    if not 0 < min_depth < max_depth:
        raise ArgumentError(
            f"{{min_depth}}={min_depth}, {{max_depth}}={max_depth}: "
            "expected 0 < min_depth < max_depth",
            "min_depth",
            "max_depth",
            owner=owner or check_depth_range,
        )


def check_conditions(
    conditions: Sequence[str], allowed: Sequence[str] = CONDITIONS, argument: str = "conditions"
) -> list[str]:
    """``conditions`` as a list of str, or an ArgumentError naming ``argument`` (the caller's
    argument that holds them) when it is empty or holds a name not in ``allowed`` (a dataset's
    subset of :data:`~fusion_depth.data.CONDITIONS`)."""
    conditions = [str(c) for c in conditions]
    if not conditions or any(c not in allowed for c in conditions):
        raise ArgumentError(
            f"{{{argument}}}={conditions}: expected a non-empty subset of {list(allowed)}",
            argument,
            owner=check_conditions,
        )
    return conditions


@dataclass(frozen=True)
class FrameList:
    """What :meth:`PreparedDataset.list_frames` found."""

    frames: dict[str, dict[str, Any]]  # split -> {frame id: what load_frame needs}, in order
    files: str  # a digest of the frames' files (names, sizes, times): a change re-prepares


class PreparedDataset(PreparedSplit):
    """One split of a dataset read from files, prepared once into the cache (module docstring).

    Subclasses set :attr:`name` and :attr:`layout` and fill in :meth:`list_frames` and
    :meth:`load_frame`; they may override :meth:`settings` (their options that change the
    prepared files), :meth:`cache_key`, :meth:`read_only`, :meth:`resolve_root`,
    :meth:`split_folder`, :meth:`check_frames` and :meth:`serves_filled`.

    Args:
        split: one of :data:`~fusion_depth.data.SPLITS`.
        root: the dataset folder (only ever read).
        cache_root: where prepared splits go, ``<cache_root>/<name>/<hash of cache_key()>/``.
        height: the network's input height in pixels, a multiple of 32.
        width: the network's input width in pixels, a multiple of 32.
        on_error: ``"raise"`` fails at the first broken frame, naming its file; ``"skip"``
            prepares every other frame of every split, then raises
            :class:`~fusion_depth.data.cache.SkippedFramesError` listing the broken ones
            (what ``python -m fusion_depth.prepare`` uses).
        max_radar_points: ``P``, the rows of ``radar_points`` each sample serves (the nearest
            returns, zero rows after) when :meth:`load_frame` gives radar points (a radar
            dataset); it changes nothing in the cache.
        size_multiple: what ``height`` and ``width`` must be multiples of
            (:func:`check_size_multiple`): 32, or 1 for frames at any size.

    Raises:
        ValueError: a bad split, ``on_error``, size or ``max_radar_points`` (naming the key), or
            what the subclass's hooks raise for its files.
        FileNotFoundError: ``root`` is not a folder.
    """

    name: ClassVar[str]  # the dataset's name: its config's ``name`` and its cache folder
    layout: ClassVar[str]  # the folder layout expected, for error messages
    conditions_allowed: ClassVar[tuple[str, ...]] = CONDITIONS  # those its frames can have
    format_version: ClassVar[int] = 1  # bump when reading changes, so old caches are not reused
    # Where it writes (the argument, a folder below it): a reader rebuilt from a checkpoint
    # writes into this machine's cache, wherever the checkpoint says.
    writes_into: ClassVar[tuple[str, str]] = ("cache_root", "")

    def __init__(
        self,
        split: str,
        root: str | os.PathLike,
        cache_root: str | os.PathLike,
        height: int,
        width: int,
        on_error: OnError = "raise",
        max_radar_points: int = DEFAULT_MAX_RADAR_POINTS,
        size_multiple: int = SIZE_MULTIPLE,
    ) -> None:
        self.split = check_split(split)
        self.on_error = check_on_error(on_error)
        self.height, self.width = check_size(height, width, check_size_multiple(size_multiple))
        max_radar_points = check_max_points(max_radar_points)
        self.root = self.resolve_root(root)
        self.cache = self.prepare(Path(cache_root).expanduser())
        super().__init__(
            self.cache / self.split_folder(split),
            use_filled=self.serves_filled(),
            max_radar_points=max_radar_points,
        )

    # --- what a dataset fills in ----------------------------------------------------------------

    def list_frames(self) -> FrameList:
        """Every split's frames, ``{split: {frame id: what load_frame needs}}`` in a fixed order
        (ids name the cached files by position), and a digest of their files (e.g.
        :func:`~fusion_depth.data.folders.fingerprint`). Cheap: lists folders, reads no image.

        With ``self.on_error == "raise"`` a frame whose files are missing may raise here; with
        ``"skip"`` keep it, and let :meth:`load_frame` raise, so it is skipped by id.
        """
        raise NotImplementedError

    def frame_files(self, split: str, frame: Any) -> list[Path] | None:
        """The files :meth:`load_frame` reads for ``frame`` (a value of :meth:`list_frames`), or
        None (the default): the frames' files are then trusted once prepared. Each frame's
        record keeps their sizes, modification times and SHA-256 digests; on every load a file
        whose size or time changed is read again, and a frame whose file's content changed is
        prepared again (:func:`~fusion_depth.data.cache.is_prepared`). Cheap: builds paths,
        reads nothing."""
        return None

    def load_frame(self, split: str, frame: Any) -> PreparedFrame:
        """One frame of ``split`` (a value of :meth:`list_frames`) at ``height x width``; a radar
        dataset adds its returns as ``radar_points``
        (:func:`~fusion_depth.data.radar_points.point_rows`, from the projection that draws
        ``sparse``), for every frame.

        Raises:
            ValueError, OSError: a file of the frame is missing, corrupt or of the wrong size
                (e.g. :class:`~fusion_depth.data.depth_io.DataFileError`), naming it.
        """
        raise NotImplementedError

    # --- what a dataset may change ---------------------------------------------------------------

    def settings(self) -> dict[str, Any]:
        """The dataset's own options that change the prepared files (plain data), for
        :meth:`cache_key`."""
        return {}

    def cache_key(self, listed: FrameList) -> dict[str, Any]:
        """Plain data naming everything the prepared files depend on: :attr:`format_version`,
        the folder, the size, :meth:`settings` and ``listed.files``. A change of any of them
        prepares a new cache folder."""
        return {
            "format_version": self.format_version,
            "root": str(self.root),
            "height": self.height,
            "width": self.width,
            **self.settings(),
            "files": listed.files,
        }

    def resolve_root(self, root: str | os.PathLike) -> Path:
        """The dataset folder, resolved; missing or unset fails naming it and :attr:`layout`."""
        return require_root(root, self.layout)

    def read_only(self) -> dict[str, Path]:
        """The user's folders, by config key: no cache may land inside them."""
        return {"root": self.root}

    def split_folder(self, split: str) -> str:
        """The cache folder serving ``split``; splits that share their frames share a folder."""
        return split

    def check_frames(self, split: str, frames: dict[str, Any]) -> None:
        """Before anything is prepared with ``on_error="raise"``: fail early on a split's
        missing files (optional; by default the first bad frame fails as it is prepared)."""

    def serves_filled(self) -> bool:
        """Whether this split serves the densified ground truth as ``depth`` (training)."""
        return False

    # --- the ceremony ----------------------------------------------------------------------------

    def prepare(self, cache_root: Path) -> Path:
        """Prepares every split not yet in the cache (once for all three, so a bad file anywhere
        fails before training starts); returns the cache folder."""
        listed = self.list_frames()
        frames = listed.frames
        params = self.cache_key(listed)
        cache = cache_dir(cache_root, self.name, params, read_only=self.read_only())
        folders = {split: self.split_folder(split) for split in SPLITS}
        needed = list(dict.fromkeys(folders.values()))  # in SPLITS order, each folder once
        first = {folder: next(s for s in SPLITS if folders[s] == folder) for folder in needed}
        ready = [
            is_prepared(cache, folder, list(frames[first[folder]]), params) for folder in needed
        ]
        if all(ready):
            return cache
        if self.on_error == "raise":
            for folder in needed:
                self.check_frames(first[folder], frames[first[folder]])
        jobs = []
        for folder in needed:
            split = first[folder]
            by_id = frames[split]
            jobs.append(
                SplitJob(
                    cache,
                    folder,
                    list(by_id),
                    lambda frame_id, split=split, by_id=by_id: self.load_frame(
                        split, by_id[frame_id]
                    ),
                    params,
                    self._sources(split, by_id),
                )
            )
        prepare_splits(jobs, on_error=self.on_error)
        return cache

    def _sources(self, split: str, by_id: dict[str, Any]) -> Callable[[str], list[Path]] | None:
        """``frame id -> its files`` for the split's job, or None when the dataset names none."""
        if type(self).frame_files is PreparedDataset.frame_files:
            return None

        def files(frame_id: str) -> list[Path]:
            return self.frame_files(split, by_id[frame_id]) or []

        return files
