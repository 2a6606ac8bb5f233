"""A config value as it is written on the command line, for the one-line config errors."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any


def show(value: Any) -> str:
    """A value as it is written on the command line (``null``, ``true``, ``[1, 2]``, ``x``)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, Sequence) and not isinstance(value, str | bytes):  # a ListConfig too
        return "[" + ", ".join(show(v) for v in value) + "]"
    return str(value)
