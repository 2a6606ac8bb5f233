"""Reading a composed config's values for the schema checks: :func:`config_value` and
:func:`check_schema`, over the plain :class:`~fusion_depth.utils.schema.Rule` tables. Kept apart
from :mod:`fusion_depth.utils.schema`, which the science packages import, because it reads
OmegaConf nodes."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from fusion_depth.errors import ConfigError
from fusion_depth.utils.overrides import show
from fusion_depth.utils.schema import Schema

ABSENT = object()  # what :func:`config_value` returns for a key the config does not have


def config_value(cfg: DictConfig, key: str) -> Any:
    """The resolved value at ``key`` (containers as plain lists and dicts), or :data:`ABSENT`; a
    ``???`` value raises OmegaConf's MissingMandatoryValue (one line from
    :func:`~fusion_depth.config.validate_config`)."""
    value = OmegaConf.select(cfg, key, default=ABSENT, throw_on_missing=True)
    if isinstance(value, DictConfig | ListConfig):
        return OmegaConf.to_container(value, resolve=True)
    return value


def check_schema(cfg: DictConfig, schema: Schema) -> None:
    """Check every key of ``schema`` that ``cfg`` has, in the schema's order.

    Raises:
        ConfigError: ``<key>=<value>: expected <what the rule accepts>``, for the first value
            that fails.
    """
    for key, rule in schema.items():
        value = config_value(cfg, key)
        if value is not ABSENT and not rule.ok(value):
            raise ConfigError(f"{key}={show(value)}: expected {rule.expected}")
