"""Atomic writes: a file is written to a temporary sibling and renamed over its name, so a
kill or a full disk never leaves a half-written file where a reader looks.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any


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
