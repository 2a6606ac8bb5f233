"""The checks a config must pass before any work, together: :func:`validate_config`.

What each key may hold is declared beside the code that reads it (an ``ARGUMENT_RULES`` table
by argument name, placed here at the node that sets them, or a runner module's
``CONFIG_SCHEMA`` by key; see :mod:`fusion_depth.utils.schema`), or is a check of values that
depend on each other;
:data:`VALUE_CHECKS` lists them in the order they run."""

from __future__ import annotations

from collections.abc import Callable

from omegaconf import DictConfig, OmegaConf

from fusion_depth.config.checks import (
    check_backbone,
    check_bottleneck,
    check_model,
    check_scheduler,
)
from fusion_depth.config.dataset_validation import check_dataset, one_line_errors
from fusion_depth.config.keys import check_known_keys
from fusion_depth.data import transforms
from fusion_depth.losses import depth_loss
from fusion_depth.models import depth_prior, encoder, fusion
from fusion_depth.optim import optimizers
from fusion_depth.runner import callbacks, datamodule, module, protocol, resume, speed
from fusion_depth.utils.config_values import check_schema
from fusion_depth.utils.schema import Schema


def _schema(schema: Schema) -> Callable[[DictConfig], None]:
    return lambda cfg: check_schema(cfg, schema)


def _arguments(node: str, rules: Schema) -> Callable[[DictConfig], None]:
    """The rules of a science function's arguments (by name), at the keys of ``node``."""
    return _schema({f"{node}.{argument}": rule for argument, rule in rules.items()})


# Every value check, in order: the fusion mode first (a mode no model takes is named alone), then
# the model against the encoder and dataset it is given, before the dataset's own checks (so a
# model that needs a sensor the dataset lacks is refused naming both), then the rest.
VALUE_CHECKS: tuple[Callable[[DictConfig], None], ...] = (
    _schema({"fusion.mode": fusion.ARGUMENT_RULES["fusion"]}),
    _arguments("model.net", fusion.ARGUMENT_RULES),
    _arguments("loss", depth_loss.ARGUMENT_RULES),
    check_backbone,
    _arguments("backbone", encoder.ARGUMENT_RULES),
    _arguments("prior", depth_prior.ARGUMENT_RULES),
    check_model,
    lambda cfg: check_dataset(cfg.dataset, cfg.fusion.mode),
    _schema(datamodule.CONFIG_SCHEMA),
    check_bottleneck,
    _arguments("augment", transforms.ARGUMENT_RULES),
    _schema(module.TRAINER_SCHEMA),
    _arguments("optimizer", optimizers.ARGUMENT_RULES),
    check_scheduler,
    _schema(callbacks.CONFIG_SCHEMA),
    _schema(speed.CONFIG_SCHEMA),
    _schema(module.CONFIG_SCHEMA),
    lambda cfg: check_schema(cfg, protocol.config_schema(cfg)),
    _schema(resume.CONFIG_SCHEMA),
)


def check_config_values(cfg: DictConfig) -> None:
    """Every value of ``cfg`` that the network, the trainer and the data pipeline read, checked
    (when the key is present) before anything is built (:data:`VALUE_CHECKS`).

    Raises:
        ConfigError: the first value that fails, in one line naming the key and what it accepts.
        MissingDependencyError: the dataset needs a package that is not installed.
    """
    for check in VALUE_CHECKS:
        check(cfg)


def validate_config(cfg: DictConfig) -> dict:
    """Fail before touching data: unknown keys, missing values, and values the network cannot
    take, each a one-line error naming the key (Hydra prints it without a traceback).

    Hydra already rejects unknown group choices with the list of options. Returns the resolved
    config as plain data.
    """
    with one_line_errors():
        OmegaConf.to_container(cfg, resolve=False, throw_on_missing=True)  # ??? values first
        check_config_values(cfg)  # before importing targets: a missing optional package is named
        check_known_keys(cfg)
        return OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
