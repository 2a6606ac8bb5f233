"""The errors the package raises about a user's input. Each is a line naming the key, file or
value and what it may be; the commands print it as its message alone (no traceback, unless
``HYDRA_FULL_ERROR=1``; :mod:`fusion_depth.config.hydra_main`). They still are the built-in
error types, so callers can catch ValueError / OSError / ImportError. This module imports
nothing: the science packages raise these without knowing of Hydra."""

from __future__ import annotations


class UserError(Exception):
    """An error about the user's input (data, config value, file), shown as its message alone."""


class ConfigError(ValueError, UserError):
    """A config value or key that cannot work; the one-line message names the key and what is
    allowed."""


class MissingDependencyError(ImportError, UserError):
    """The chosen dataset, export format or engine needs a package that is not installed, or a
    device that is not there (a CUDA GPU for TensorRT)."""


class OutputDirError(OSError, UserError):
    """The output directory cannot be written, or has too little free space."""


class CommandError(RuntimeError, UserError):
    """A user-facing error (bad data, config value or file) shown as its message alone; the
    original exception is its ``__cause__`` (shown with ``HYDRA_FULL_ERROR=1``)."""
