"""The files of a run folder: their names, atomic writes, ``failure.json`` on error, the
folder names, and where the code that produced a run came from. ``metrics.json``, the record
of a finished run, is :mod:`fusion_depth.run_record`'s."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import tempfile
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from fusion_depth.version import __version__

FAILURE_FILE = "failure.json"
RESOLVED_CONFIG_FILE = "config_resolved.yaml"
PER_IMAGE_FILE = "per_image.csv"
TRACEBACK_FILE = "traceback.txt"


_MAX_DIRNAME = 200  # bytes; file systems allow 255


def run_dirname(override_dirname: str) -> str:
    """A folder name for a run from Hydra's ``override_dirname`` (``fusion=concat,loss=l1``):
    the same overrides give the same folder, so re-running a command finds its run again.
    ``default`` when there are none; ``/`` in values becomes ``_``; overly long names are cut
    and end in a hash of the whole."""
    name = override_dirname.replace(os.sep, "_") or "default"
    if len(name.encode()) > _MAX_DIRNAME:
        digest = hashlib.sha1(name.encode()).hexdigest()[:10]
        name = f"{name.encode()[: _MAX_DIRNAME - 11].decode(errors='ignore')}-{digest}"
    return name


def sweep_dirname(config_name: str, override_dirname: str) -> str:
    """A sweep's folder: the sweep config's name (``--config-name``, unless it is ``train``)
    and the sweep's own overrides, e.g. ``loss=l1,l2,berhu``.

    Registered with ``use_cache``: OmegaConf caches by the interpolation's text, and Hydra
    copies the sweep's cache into every job's config, so all jobs share the sweep's folder
    although each job's ``override_dirname`` is its own.
    """
    parts = [config_name] if config_name not in ("", "None", "train") else []
    if override_dirname or not parts:
        parts.append(run_dirname(override_dirname))
    return "/".join(parts)


def provenance() -> dict[str, Any]:
    """Package versions and, when the package runs from a git checkout, its commit and whether
    the working tree had uncommitted changes (``git_dirty``); None where unknown."""
    import lightning
    import torch

    source = Path(__file__).resolve().parent
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


def _file_mode() -> int:
    """The mode a plainly created file gets (0o666 less the umask); mkstemp's is 0o600."""
    umask = os.umask(0o022)
    os.umask(umask)
    return 0o666 & ~umask


def write_atomic(
    path: str | os.PathLike,
    write: Callable[[Path], None],
    check: Callable[[Path], Any] = lambda tmp: None,
    suffix: str = ".tmp",
    companions: Sequence[str] = (),
) -> Any:
    """``write(tmp)`` then ``check(tmp)`` on a temporary sibling, renamed to ``path`` only if
    both succeed: readers never see a half-written file, and an existing one survives a
    failure. ``suffix`` is the temporary name's (for writers that go by the extension).

    ``companions``: suffixes of files that ``write`` writes next to ``tmp`` with its stem
    (``tmp.with_suffix(".bin")``, as OpenVINO writes an IR's weights beside its ``.xml``); each
    is renamed to ``path.with_suffix(<suffix>)`` with it (companions first, ``path`` last), and
    removed on failure. Returns what ``check`` returned.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    # (temporary file, final file), the main file last: it appears once its companions have.
    moves = [(tmp.with_suffix(c), path.with_suffix(c)) for c in companions] + [(tmp, path)]
    try:
        write(tmp)
        result = check(tmp)
        for source, target in moves:
            os.chmod(source, _file_mode())
            os.replace(source, target)
    except BaseException:
        for source, _ in moves:
            source.unlink(missing_ok=True)
        raise
    return result


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """``text`` written atomically (see :func:`write_atomic`)."""
    write_atomic(path, lambda tmp: tmp.write_text(text))


def write_json_atomic(path: str | os.PathLike, data: Any) -> None:
    """``data`` as indented JSON, written atomically."""
    write_text_atomic(path, json.dumps(data, indent=2) + "\n")


def record_failure(
    output_dir: str | os.PathLike, overrides: list[str], error: BaseException
) -> Path:
    """Save what failed (overrides, error, traceback) next to the run's other outputs."""
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
            "error": f"{type(error).__name__}: {error}",
            "traceback": str(trace),
        },
    )
    return path
