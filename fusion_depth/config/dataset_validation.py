"""The checks of :func:`~fusion_depth.config.validate_config` that concern the dataset alone,
for ``prepare``, which reads nothing else (and its own ``prepare`` node); and the one-line form
both give OmegaConf's errors.

This module imports only the data layer, so ``python -m fusion_depth.prepare`` starts without
the models (timm) and the trainer (Lightning): with several workers, their seconds of import
were a fixed cost that no number of workers shortens.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

from fusion_depth.config.arguments import config_message, where_set
from fusion_depth.config.keys import check_known_keys
from fusion_depth.data.base import (
    SIZE_MULTIPLE,
    check_depth_range,
    check_size,
    check_size_multiple,
)
from fusion_depth.errors import ArgumentError, ConfigError, MissingDependencyError
from fusion_depth.utils.config_values import ABSENT, config_value
from fusion_depth.utils.overrides import show
from fusion_depth.utils.schema import Schema, is_number


class MissingValueError(MissingMandatoryValue, ConfigError):
    """A ``???`` value that must be set (still an OmegaConf MissingMandatoryValue)."""


@contextmanager
def one_line_errors() -> Iterator[None]:
    """OmegaConf's errors inside, as one-line errors naming the key: a ``???`` value as
    :class:`MissingValueError` (saying how to set it), any other as
    :class:`~fusion_depth.errors.ConfigError`."""
    try:
        yield
    except MissingValueError:
        raise
    except MissingMandatoryValue as err:
        key = err.full_key or "?"
        raise MissingValueError(
            f"{key}: missing value (???); set it on the command line: {key}=..."
        ) from None
    except OmegaConfBaseException as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"{err.full_key or 'config'}: {first}") from None


def reader_rules(ds: Any) -> Schema:
    """What the arguments of ``ds.reader``'s target accept: its ``ARGUMENT_RULES`` (argument →
    :class:`~fusion_depth.utils.schema.Rule`, declared on the reader class); empty when it
    declares none, or when the target cannot be imported (an unknown target is
    :func:`~fusion_depth.config.keys.check_known_keys`' to name)."""
    from hydra.utils import get_object

    reader = ds.get("reader") if isinstance(ds, DictConfig) else None
    target = reader.get("_target_") if isinstance(reader, DictConfig) else None
    if not isinstance(target, str):
        return {}
    try:
        built = get_object(target)
    except Exception:  # noqa: BLE001 - named by check_known_keys, with the reason
        return {}
    rules = getattr(built, "ARGUMENT_RULES", None)
    return rules if isinstance(rules, dict) else {}


def check_reader(ds: Any) -> None:
    """Every ``dataset.reader.<argument>`` its reader declares a rule for (:func:`reader_rules`),
    checked before any work: a null, infinite, non-numeric or listed count would otherwise fail
    inside the reader, or deep in the preparation.

    Raises:
        ConfigError: ``<key>=<value>: expected <what it accepts>``, naming where the value is set
            (``dataset.fill`` for ``dataset.reader.fill: ${dataset.fill}``).
    """
    for argument, rule in reader_rules(ds).items():
        value = config_value(ds, f"reader.{argument}")
        if value is ABSENT or rule.ok(value):
            continue
        key = where_set(ds._get_root(), f"dataset.reader.{argument}")
        raise ConfigError(f"{key}={show(value)}: expected {rule.expected}")


def check_dataset(ds: Any, fusion: str) -> None:
    """A dataset block the network can take, with ``fusion`` (its input mode) allowed on it.
    ``ds`` is the ``dataset`` node (a DictConfig, or any object with its keys as attributes).

    Raises:
        ConfigError: a size, depth range, reader value (:func:`check_reader`) or fusion mode the
            dataset cannot take, naming the key.
        MissingDependencyError: the dataset's optional package is not installed (with the
            command that installs it).
    """
    try:
        multiple = check_size_multiple((ds.get("reader") or {}).get("size_multiple", SIZE_MULTIPLE))
        check_size(ds.height, ds.width, multiple)
    except ArgumentError as err:
        raise ConfigError(
            config_message(
                err,
                {
                    "height": "dataset.height",
                    "width": "dataset.width",
                    "size_multiple": "dataset.reader.size_multiple",
                },
            )
        ) from None
    for key in ("min_depth", "max_depth", "depth_scale"):
        if not is_number(ds[key]) or not ds[key] > 0:
            raise ConfigError(f"dataset.{key}={show(ds[key])}: expected a positive number")
    try:
        check_depth_range(ds.min_depth, ds.max_depth)
    except ArgumentError as err:
        keys = {"min_depth": "dataset.min_depth", "max_depth": "dataset.max_depth"}
        raise ConfigError(config_message(err, keys)) from None
    check_reader(ds)  # before the package check: a bad value is named without it
    needs = ds.get("requires")
    if needs is not None and importlib.util.find_spec(needs.module) is None:
        raise MissingDependencyError(
            f"dataset={ds.name} needs {needs.package} (module {needs.module!r}), which is not "
            f"installed: {needs.install}"
        )
    allowed = ds.get("fusions")
    if allowed is not None and fusion not in allowed:
        raise ConfigError(
            f"fusion={fusion}: dataset={ds.name} has no sparse sensor input, so only "
            f"fusion={'/'.join(allowed)} is possible (dataset.fusions)"
        )


def validate_dataset_config(cfg: DictConfig) -> dict:
    """Fail before touching data, as :func:`~fusion_depth.config.validate_config` does, for the
    ``dataset`` node alone: missing values, the dataset's values
    (:func:`check_dataset`, against ``fusion.mode``), and unknown keys of
    ``dataset`` and ``prepare`` (:func:`~fusion_depth.config.keys.check_known_keys`). The rest of
    the config is training's; ``train`` checks it.

    Returns:
        The resolved ``dataset`` node as plain data.

    Raises:
        MissingValueError: a ``???`` value under ``dataset`` (e.g. ``dataset.root``).
        ConfigError: a bad value or an unknown key, in one line naming it.
        MissingDependencyError: the dataset needs a package that is not installed.
    """
    with one_line_errors():
        OmegaConf.to_container(cfg.dataset, resolve=False, throw_on_missing=True)
        check_dataset(cfg.dataset, cfg.fusion.mode)
        check_known_keys(cfg, only=("dataset", "prepare"))
        return OmegaConf.to_container(cfg.dataset, resolve=True, throw_on_missing=True)
