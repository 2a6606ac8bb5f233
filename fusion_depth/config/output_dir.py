"""The output directory, checked before training: writable, with room for the checkpoints."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from fusion_depth.errors import OutputDirError

MB = 1_000_000


def check_output_dir(path: str | os.PathLike, needed_bytes: int) -> None:
    """Fail before training unless ``path`` can be created and written to and its file system
    has ``needed_bytes`` free (see :func:`checkpoint_bytes`); one-line OutputDirError."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=".write-check-", dir=path)
        try:
            os.write(fd, b"ok")
        finally:
            os.close(fd)
            os.unlink(name)
    except OSError as err:
        reason = err.strerror or type(err).__name__
        raise OutputDirError(f"output directory {path}: not writable ({reason})") from None
    free = shutil.disk_usage(path).free
    if free < needed_bytes:
        raise OutputDirError(
            f"output directory {path}: {free / MB:.0f} MB free, the run needs about "
            f"{needed_bytes / MB:.0f} MB for its checkpoints; free some space or choose another "
            "directory (hydra.run.dir=... / hydra.sweep.dir=...)"
        )


def checkpoint_bytes(model: Any, optimizer_states: int = 2) -> int:
    """The size of one full Lightning checkpoint of ``model`` (an ``nn.Module``): its
    parameters once for the weights and ``optimizer_states`` more times for the optimizer's
    per-parameter state (Adam: 2), plus its buffers. Metadata adds little."""
    params = sum(p.numel() * p.element_size() for p in model.parameters())
    buffers = sum(b.numel() * b.element_size() for b in model.buffers())
    return int(params * (1 + optimizer_states) + buffers)
