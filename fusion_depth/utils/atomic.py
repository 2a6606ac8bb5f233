"""Atomic writes: a file is written to a temporary sibling, flushed to disk and renamed over its
name, so a kill, a power loss or a full disk never leaves a half-written file where a reader
looks.

A temporary name says which process made it (``.<name>.p<pid>h<host>.<random><suffix>``, where
``<host>`` is a digest of the machine's name), so that a later run can tell the leftovers of a
killed writer (:func:`remove_orphaned_temporaries`) from a file another process is writing now.
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
import re
import shutil
import socket
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from fusion_depth.utils.processes import pid_alive

# A temporary file on another machine (a shared cache) counts as orphaned once this old: its
# writer cannot be asked whether it is alive, and a write takes seconds, not minutes.
FOREIGN_STALE_S = 600.0
_OWNER = re.compile(r"\.p(\d+)h([0-9a-f]{8})\.")


def host_tag() -> str:
    """8 hex digits naming this machine (a digest of its host name)."""
    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]


def owner_tag() -> str:
    """``p<pid>h<host_tag()>``: the writer a temporary name carries."""
    return f"p{os.getpid()}h{host_tag()}"


def temporary_orphaned(path: Path, max_age_s: float = FOREIGN_STALE_S) -> bool:
    """Whether the temporary file ``path`` is a killed writer's: its owner tag names a process
    of this machine that is gone, or it is older than ``max_age_s`` (another machine's, or a
    name without a tag, as versions up to 0.2.0 wrote them)."""
    match = _OWNER.search(path.name)
    if match and match.group(2) == host_tag():
        return not pid_alive(int(match.group(1)))
    try:
        return time.time() - path.lstat().st_mtime > max_age_s
    except FileNotFoundError:
        return False


def is_temporary(path: Path) -> bool:
    """Whether ``path`` is named as :func:`write_atomic` names its temporary files
    (``.<name>.p<pid>h<host>.<random><suffix>``, or ``.<name>.tmp-<pid>-<random>`` and
    ``.<name>.<random>.tmp`` as versions up to 0.2.0 wrote them): the one rule every sweep of
    the platform's leftovers goes by."""
    name = path.name
    return name.startswith(".") and (_OWNER.search(name) is not None or ".tmp" in name)


def remove_orphaned_temporaries(
    folder: Path,
    names: Sequence[str] | None = None,
    recursive: bool = False,
    folder_locked: bool = False,
) -> list[Path]:
    """Removes the temporary files (or folders, :func:`is_temporary`) in ``folder`` whose
    writer is gone (:func:`temporary_orphaned`); returns them. One another live process is
    writing stays.

    Args:
        folder: where to look; nothing happens if it does not exist.
        names: only the temporaries of ``folder/<name>`` for each name (``.<name>.*``); None:
            every temporary.
        recursive: also in every folder below ``folder``.
        folder_locked: the caller holds ``folder``'s lock (a run folder's), so no other
            process writes there: every temporary but this process's own is a leftover, even
            where its owner's process id now names another process.
    """
    if not folder.is_dir():
        return []
    if names is None:
        found = folder.rglob(".*") if recursive else folder.glob(".*")
    else:
        patterns = [f".{glob.escape(name)}.*" for name in names]
        search = folder.rglob if recursive else folder.glob
        found = (path for pattern in patterns for path in search(pattern))
    removed = []
    for path in sorted(set(found)):
        if not is_temporary(path) or not _left_over(path, folder_locked):
            continue
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
        removed.append(path)
    return removed


def _left_over(path: Path, folder_locked: bool) -> bool:
    if folder_locked:
        return f".{owner_tag()}." not in path.name
    return temporary_orphaned(path)


def _file_mode() -> int:
    """The mode a plainly created file gets (0o666 less the umask); mkstemp's is 0o600."""
    umask = os.umask(0o022)
    os.umask(umask)
    return 0o666 & ~umask


def fsync_file(path: Path) -> None:
    """Flushes ``path``'s data to the disk (a rename after it publishes whole data even across
    a power loss)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(
    path: str | os.PathLike,
    write: Callable[[Path], None],
    check: Callable[[Path], Any] = lambda tmp: None,
    suffix: str = ".tmp",
    companions: Sequence[str] = (),
) -> Any:
    """``write(tmp)`` then ``check(tmp)`` on a temporary sibling, flushed to disk and renamed to
    ``path`` only if both succeed: readers never see a half-written file, and an existing one
    survives a failure. ``suffix`` is the temporary name's (for writers that go by the
    extension).

    ``companions``: suffixes of files that ``write`` writes next to ``tmp`` with its stem
    (``tmp.with_suffix(".bin")``, as OpenVINO writes an IR's weights beside its ``.xml``); each
    is renamed to ``path.with_suffix(<suffix>)`` with it (companions first, ``path`` last), and
    removed on failure. Returns what ``check`` returned.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    prefix = f".{path.name}.{owner_tag()}."
    fd, name = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    # (temporary file, final file), the main file last: it appears once its companions have.
    moves = [(tmp.with_suffix(c), path.with_suffix(c)) for c in companions] + [(tmp, path)]
    try:
        write(tmp)
        result = check(tmp)
        for source, _ in moves:
            fsync_file(source)
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
