"""The files of a run folder: their names, ``failure.json`` on error, and where the code that
produced a run came from. ``metrics.json``, the record of a finished run, is
:mod:`fusion_depth.runner.record`'s; the folder's name, :mod:`fusion_depth.config.run_dirs`'s.
"""

from __future__ import annotations

import os
import subprocess
import traceback
from pathlib import Path
from typing import Any

from fusion_depth.utils.atomic import write_json_atomic
from fusion_depth.version import __version__

FAILURE_FILE = "failure.json"


RESOLVED_CONFIG_FILE = "config_resolved.yaml"


PER_IMAGE_FILE = "per_image.csv"

# The test panels' frames as arrays (data.visualize.write_panel_frames): `report RUN --panels
# OUT.png` draws the run's figure again without its checkpoint.
TEST_PANEL_FRAMES_FILE = "test_panels.npz"


TRACEBACK_FILE = "traceback.txt"


def provenance() -> dict[str, Any]:
    """Package versions and, when the package runs from a git checkout, its commit and whether
    the working tree had uncommitted changes (``git_dirty``); None where unknown."""
    import lightning
    import torch

    source = Path(__file__).resolve().parents[1]  # fusion_depth/
    commit = dirty = None
    try:
        git = ["git", "-C", str(source)]
        commit = subprocess.run(
            [*git, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()
        status = subprocess.run(
            [*git, "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout
        dirty = bool(status.strip())
    except (OSError, subprocess.SubprocessError):
        pass  # not a git checkout (an installed wheel) or no git: the versions still say enough
    return {
        "fusion_depth": __version__,
        "torch": torch.__version__,
        "lightning": lightning.__version__,
        "git_commit": commit or None,
        "git_dirty": dirty,
    }


def record_failure(
    output_dir: str | os.PathLike,
    overrides: list[str],
    error: BaseException,
    message: str | None = None,
) -> Path:
    """Save what failed (overrides, error, traceback) next to the run's other outputs;
    ``message``: the line the command shows for it, where it has one."""
    output_dir = Path(output_dir)
    trace = output_dir / TRACEBACK_FILE
    output_dir.mkdir(parents=True, exist_ok=True)
    trace.write_text("".join(traceback.format_exception(error)))
    path = output_dir / FAILURE_FILE
    write_json_atomic(
        path,
        {
            "status": "failed",
            "overrides": overrides,
            "error": f"{type(error).__name__}: {message or error}",
            "traceback": str(trace),
        },
    )
    return path
