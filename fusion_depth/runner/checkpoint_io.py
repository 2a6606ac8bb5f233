"""Lightning's checkpoint writer and reader, made safe for runs that get killed or fill the disk
(:class:`AtomicCheckpointIO`).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.plugins.io import TorchCheckpointIO

from fusion_depth.errors import UserError
from fusion_depth.utils.atomic import write_atomic
from fusion_depth.utils.checkpoint_file import load_weights_only


class CheckpointWriteError(OSError, UserError):
    """A checkpoint could not be written (e.g. a full disk); the previous one is intact."""


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint writer and reader, made safe for runs that get killed.

    A checkpoint is written to a temporary sibling, flushed to disk and renamed over the old
    one, so a kill, a dead node or a full disk leaves the previous checkpoint intact rather
    than a truncated one (Lightning's own writer opens the target itself). Reading is
    weights-only, whatever the caller asks for: resuming never runs code from a file.
    """

    def save_checkpoint(
        self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None
    ) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__} takes no storage_options")

        failed: list[OSError] = []  # what the file system said, under torch's own error

        def write(tmp: Path) -> None:
            with tmp.open("wb") as f:
                torch.save(checkpoint, _ReportingFile(f, failed))
                f.flush()
                os.fsync(f.fileno())

        try:
            write_atomic(path, write, suffix=".ckpt.tmp")
        except (OSError, RuntimeError) as err:
            cause = failed[0] if failed else err
            reason = cause.strerror if isinstance(cause, OSError) and cause.strerror else cause
            failure = CheckpointWriteError(
                f"could not write the checkpoint {path} ({reason}; "
                f"{_free_space(Path(path).parent)} free there); the previous checkpoint there, "
                "if any, is intact"
            )
            failure.errno = getattr(cause, "errno", None)
            raise failure from err

    def load_checkpoint(
        self, path: Any, map_location: Any | None = None, weights_only: bool | None = None
    ) -> dict[str, Any]:
        return load_weights_only(path, map_location=map_location)


class _ReportingFile:
    """A binary file for ``torch.save`` that keeps the OSError of a failed write: torch turns
    it into its own ``RuntimeError`` (inline_container), which no longer says why."""

    def __init__(self, file: Any, failed: list[OSError]) -> None:
        self._file = file
        self._failed = failed

    def write(self, data: Any) -> int:
        try:
            return self._file.write(data)
        except OSError as err:
            self._failed.append(err)
            raise

    def __getattr__(self, name: str) -> Any:
        return getattr(self._file, name)


def _free_space(folder: Path) -> str:
    """Free space on ``folder``'s file system, e.g. ``'12.3 MB'`` (``'unknown'`` if unreadable)."""
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return "unknown space"
    return f"{free / 1e6:.1f} MB"
