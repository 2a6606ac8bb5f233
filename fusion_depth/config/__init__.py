"""Where the Hydra configs are (:data:`CONF_DIR`, :data:`SWEEPS_DIR`), and what a config goes
through before any work, one module per concern:

- :mod:`.resolvers`: the ``fd.*`` OmegaConf resolvers that ``conf/`` uses.
- :mod:`.keys`: unknown keys (every key must be read by something).
- :mod:`.validation`: :func:`validate_config`: the values each reader declares it takes
  (:mod:`fusion_depth.utils.schema`) and the keys, as one-line errors;
  :func:`validate_dataset_config` (:mod:`.dataset_validation`): the same for the dataset alone,
  for ``prepare``, which reads nothing else.
- :mod:`.output_dir`: the output directory (writable, room for the checkpoints).
- :mod:`.run_dirs`: run and sweep folder names.
- :mod:`.hydra_main`: what every command line of the package shares.

The errors they raise are in :mod:`fusion_depth.errors`; the redaction of secrets from what a run
writes is :mod:`fusion_depth.runner.redaction`. Every public name is importable from here.

:mod:`.validation` imports every layer whose values it checks (the models with timm, the trainer
with Lightning: seconds), so its names are imported on first use: ``import fusion_depth``, and
``prepare``, which validates only the dataset, start without them.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from fusion_depth.config.dataset_validation import validate_dataset_config
from fusion_depth.config.keys import (
    PASSED_BY_CODE,
    PLAIN_CONSUMERS,
    READ_BY_CODE,
    check_known_keys,
    target_accepts,
    unknown_key_error,
)
from fusion_depth.config.output_dir import MB, check_output_dir, checkpoint_bytes
from fusion_depth.config.resolvers import register_resolvers

__all__ = [
    "CONF_DIR",
    "MB",
    "PASSED_BY_CODE",
    "PLAIN_CONSUMERS",
    "READ_BY_CODE",
    "SWEEPS_DIR",
    "VALUE_CHECKS",
    "check_known_keys",
    "check_output_dir",
    "check_config_values",
    "checkpoint_bytes",
    "register_resolvers",
    "target_accepts",
    "unknown_key_error",
    "validate_config",
    "validate_dataset_config",
]

# Names imported on first use (PEP 562), by module.
_ON_FIRST_USE = {
    name: "fusion_depth.config.validation"
    for name in ("VALUE_CHECKS", "check_config_values", "validate_config")
}


def __getattr__(name: str) -> Any:
    if name in _ON_FIRST_USE:
        return getattr(importlib.import_module(_ON_FIRST_USE[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _shipped(name: str) -> str:
    """A folder that sits at the repository's top level and ships inside the package: the
    installed copy (``fusion_depth/<name>``) or, in a checkout, the repository's own."""
    package = Path(__file__).resolve().parents[1]  # fusion_depth/, above this config/ package
    installed = package / name
    return str(installed if installed.is_dir() else package.parent / name)


# The Hydra configs every entry point composes, and the ready-made sweep configs.
CONF_DIR = _shipped("conf")
SWEEPS_DIR = _shipped("sweeps")
