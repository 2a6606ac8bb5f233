"""Reading a JSON file someone else wrote: it is plain data, and anything wrong with it is one
line naming the file."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any


def read_json(path: str | os.PathLike, what: str, error: type[Exception] = ValueError) -> Any:
    """The data in the JSON file ``path`` (dicts, lists, strings, numbers, booleans, None).

    Args:
        path: the file.
        what: what the file should be, for the message ("a bench record", "a sidecar").
        error: the exception type raised when the file is not JSON.

    Raises:
        OSError: the file cannot be read.
        error: it is not UTF-8 JSON, or nests too deeply for the parser (which recurses once
            per level); the message names the file.
    """
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise error(f"{path}: not valid JSON ({err})") from err
    except RecursionError as err:
        raise error(f"{path}: nested too deeply to be {what}") from err
