"""A config value as it is written on the command line, for the one-line config errors."""

from __future__ import annotations

from typing import Any

from omegaconf import ListConfig


def show(value: Any) -> str:
    """A value as it is written on the command line (``null``, ``true``, ``[1, 2]``, ``x``)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, list | tuple | ListConfig):
        return "[" + ", ".join(show(v) for v in value) + "]"
    return str(value)
