"""Where the config sets each argument of the science code, so that an error naming an argument
(:class:`~fusion_depth.errors.ArgumentError`, raised by ``models/``, ``losses/``, ``metrics/``,
``data/``, ``optim/``, which know no config) is reported naming the key the user sets:
``weights=/x.pth: no such file`` becomes ``backbone.weights=/x.pth: no such file``.

:data:`ARGUMENT_KEYS` maps the function or class that raised it (by dotted name, or the module or
package it lies in) to the node whose keys are its arguments, or to a table argument → key. With
the run's config at hand, a key whose value is an interpolation names where that is set
(``dataset.reader.root: ${dataset.root}`` → ``dataset.root``), so a dataset of one's own is
named right too.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping

from omegaconf import DictConfig, OmegaConf

from fusion_depth.errors import ArgumentError, UserError

_ENCODER = {
    "name": "backbone.name",
    "taps": "backbone.taps",
    "weights": "backbone.weights",
    "pretrained": "backbone.pretrained",
}
ARGUMENT_KEYS: dict[str, str | Mapping[str, str]] = {
    "fusion_depth.models._registry.model_entry": {"name": "model.net.name"},
    "fusion_depth.models._registry.check_model_takes": {
        "fusion": "fusion",
        "backbone": "backbone",
        "sensor": "dataset.sensor",
        "prior": "prior",
    },
    "fusion_depth.models.depth_prior": {
        "weights": "prior.weights",
        "input_size": "prior.input_size",
        "kind": "prior.kind",
        "max_depth": "prior.max_depth",
        "name": "prior.name",
    },
    "fusion_depth.models.alignment": "alignment",  # evaluate's prior alignment settings
    "fusion_depth.models.encoder": _ENCODER,
    "fusion_depth.models.fusion.InputFusion": {"mode": "fusion.mode"},
    "fusion_depth.models.inference": {"upsample": "eval.upsample"},
    # evaluate's released=<name>: the authors' files and settings (conf/released/)
    "fusion_depth.models.radarnet_released.load_released": {
        "association_weights": "released.association_weights",
        "fusion_weights": "released.fusion_weights",
    },
    "fusion_depth.models.released": "released",
    "fusion_depth.models": "model.net",  # a network's own arguments (model.net.<argument>)
    "fusion_depth.metrics.depth": "eval",
    "fusion_depth.optim.schedules": "scheduler",
    "fusion_depth.data.cache.PrepareOptions": "prepare",
    "fusion_depth.data.transforms": "augment",  # the training augmentation's arguments
    "fusion_depth.data": "dataset.reader",  # every reader's arguments: the dataset's reader node
}
_INTERPOLATION = re.compile(r"^\$\{([A-Za-z_][\w.]*)\}$")


def _where(owner: str) -> str | Mapping[str, str] | None:
    """The entry of :data:`ARGUMENT_KEYS` for ``owner`` or the nearest module or package above."""
    while owner:
        if owner in ARGUMENT_KEYS:
            return ARGUMENT_KEYS[owner]
        owner = owner.rpartition(".")[0]
    return None


def where_set(cfg: DictConfig, key: str) -> str:
    """The key whose value ``key`` holds: itself, or where its ``${...}`` interpolation points,
    followed to the end (``dataset.reader.root`` → ``dataset.root``)."""
    for _ in range(8):  # a chain of interpolations; a cycle is OmegaConf's to report
        parent, _, leaf = key.rpartition(".")
        node = OmegaConf.select(cfg, parent) if parent else cfg
        if not isinstance(node, DictConfig) or leaf not in node:
            return key
        match = _INTERPOLATION.match(str(node._get_node(leaf)._value()))
        if match is None:
            return key
        key = match.group(1)
    return key


def argument_key(owner: str, cfg: DictConfig | None = None) -> Callable[[str], str]:
    """The config key of each argument ``owner`` (a dotted name) takes, followed to where it is
    set when ``cfg`` is given; an argument whose key is not known keeps its name."""
    where = _where(owner)
    if isinstance(where, str):
        node = where

        def key(argument: str) -> str:
            return f"{node}.{argument}"
    else:
        table = dict(where or {})

        def key(argument: str) -> str:
            return table.get(argument, argument)

    if cfg is None:
        return key
    return lambda argument: where_set(cfg, key(argument))


def argument_error(err: BaseException | None) -> ArgumentError | None:
    """The :class:`ArgumentError` ``err`` is, or was raised from (Hydra's instantiate wraps what
    a target raises); None when there is none, or when a user error of its own (one that already
    says what to change, such as a message the commands made) stands between."""
    while err is not None and not isinstance(err, ArgumentError):
        if isinstance(err, UserError):
            return None
        err = err.__cause__
    return err


def config_message(
    err: ArgumentError, keys: Mapping[str, str] | None = None, cfg: DictConfig | None = None
) -> str:
    """``err``'s message naming config keys: ``keys`` (argument → key) where given, else where
    :data:`ARGUMENT_KEYS` says ``err.owner`` takes its arguments from (followed to where they
    are set in ``cfg``, when given)."""
    if keys is not None:
        return err.naming(lambda argument: keys.get(argument, argument))
    return err.naming(argument_key(err.owner, cfg))
