"""The errors the package raises about a user's input. Hydra prints a CompactHydraException as
its message alone (no traceback, unless ``HYDRA_FULL_ERROR=1``): each of these is a line naming
the key, file or value and what it may be. They still are the built-in error types, so callers
can catch ValueError / OSError / ImportError."""

from __future__ import annotations

from hydra.errors import CompactHydraException
from omegaconf.errors import MissingMandatoryValue


class ConfigError(ValueError, CompactHydraException):
    """A config value or key that cannot work; the one-line message names the key and what is
    allowed."""


class MissingValueError(MissingMandatoryValue, ConfigError):
    """A ``???`` value that must be set (still an OmegaConf MissingMandatoryValue)."""


class MissingDependencyError(ImportError, CompactHydraException):
    """The chosen dataset, export format or engine needs a package that is not installed, or a
    device that is not there (a CUDA GPU for TensorRT)."""


class OutputDirError(OSError, CompactHydraException):
    """The output directory cannot be written, or has too little free space."""


class CommandError(RuntimeError, CompactHydraException):
    """A user-facing error (bad data, config value or file) shown as its message alone; the
    original exception is its ``__cause__`` (shown with ``HYDRA_FULL_ERROR=1``)."""
