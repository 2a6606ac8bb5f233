"""A trained network and its dataset rebuilt from a checkpoint's record, never from code in the
file (the file itself is read by :mod:`fusion_depth.utils.checkpoint_file`).

The network is rebuilt from the known ``model.net`` keys, and the dataset from its name in the
package's own table (:data:`fusion_depth.data.READERS`), with the stored reader arguments
checked against that reader's constructor.
"""

from __future__ import annotations

import functools
import inspect
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.utils import instantiate

from fusion_depth.data import READERS, cache_dir, reader_class
from fusion_depth.errors import ArgumentError
from fusion_depth.models import DepthModel, network_from_checkpoint, network_state
from fusion_depth.models.depth_prior import NO_PRIOR, PRIOR_KEY, check_prior_record
from fusion_depth.utils.checkpoint_file import (
    CONFIG_KEY,
    RUN_KEY,
    CheckpointError,
    not_plain,
    read_checkpoint,
)

# What records a model's dataset, by the option that names the file (LoadedModel.key).
_RECORD = {"ckpt_path": "run config", "model_file": "sidecar"}


@dataclass
class LoadedModel:
    """A network rebuilt from a checkpoint, with the run config it was trained with (or an
    exported model file run by an engine, :func:`fusion_depth.export.runtime.load_exported`:
    then ``key`` is ``model_file`` and ``config`` holds what its sidecar records)."""

    net: DepthModel
    config: dict[str, Any]
    path: Path
    run: dict[str, Any] | None = None  # the training run's identity, when train recorded it
    key: str = "ckpt_path"  # the option that named ``path``, for messages

    @property
    def fusion(self) -> str:
        """The fusion mode it was trained with (``fusion=``): ``rgb`` (the image alone),
        ``concat`` or ``add`` (the image and sparse depth)."""
        return self.config["fusion"]["mode"]

    @property
    def backbone(self) -> str:
        """The encoder it was trained with (``backbone.name``), e.g. ``resnet10t``."""
        return self.config["backbone"]["name"]


def check_expected(
    config: dict[str, Any],
    path: Path,
    fusion: str | None = None,
    backbone: str | None = None,
    option: str = "ckpt_path",
) -> None:
    """Fail when the caller asked for another fusion mode or backbone than the checkpoint
    (``option``: the key that named ``path``) has."""
    trained = {"fusion": config["fusion"]["mode"], "backbone": config["backbone"]["name"]}
    for key, wanted in (("fusion", fusion), ("backbone", backbone)):
        if wanted is not None and wanted != trained[key]:
            raise CheckpointError(
                f"{option}={path} was trained with {key}={trained[key]}, but {key}={wanted} "
                f"was asked for: drop the {key}= override or pick a {key}={wanted} checkpoint"
            )


def _with_prior_file(net_config: Any, path: Path, prior: dict[str, Any]) -> dict[str, Any]:
    """``net_config`` with its prior read from ``prior["weights"]``: the same prior as trained
    with (``prior["name"]``), from another file (weights moved, another machine's copy); or,
    for ``prior["name"] == "none"``, served without the prior it was trained with (its channel
    given zeros, as ``prior.dropout`` trained it to take)."""
    recorded = net_config.get("prior") if isinstance(net_config, dict) else None
    trained = (recorded or {}).get("name", NO_PRIOR)
    if prior["name"] == NO_PRIOR:
        return (
            net_config
            if trained == NO_PRIOR
            else {**net_config, "prior": {**recorded, "enabled": False}}
        )
    if trained != prior["name"]:
        raise CheckpointError(
            f"prior={prior['name']}: ckpt_path={path} was trained with prior={trained}; give "
            f"that prior's file{'' if trained == NO_PRIOR else f' as prior={trained}'} or leave "
            "prior= out"
        )
    return {**net_config, "prior": {**recorded, "weights": prior["weights"]}}


def load_model(
    path: str | os.PathLike,
    fusion: str | None = None,
    backbone: str | None = None,
    prior: dict[str, Any] | None = None,
) -> LoadedModel:
    """Rebuild the network of a training checkpoint and load its weights (eval mode, CPU).

    Args:
        path: the checkpoint.
        fusion: when given, the fusion mode it must have been trained with.
        backbone: when given, the backbone it must have been trained with.
        prior: when given, the ``prior`` node (``name``, ``weights``) whose file replaces the
            one the checkpoint names; ``name`` must be the prior it was trained with, or
            ``none``: the network runs without its prior.

    Raises:
        CheckpointError: not a training checkpoint, another fusion, backbone or prior than
            asked for, a prior whose files now hold other weights than it was trained with
            (:func:`~fusion_depth.models.depth_prior.check_prior_record`), or weights that do
            not fit the network its config names (naming the file and key).
    """
    path = Path(path).expanduser()
    checkpoint = read_checkpoint(path)
    config = checkpoint[CONFIG_KEY]
    try:
        net_config = config["model"]["net"]
        config["fusion"]["mode"], config["backbone"]["name"]  # noqa: B018 - presence check
    except (KeyError, TypeError) as err:
        raise CheckpointError(f"ckpt_path={path}: its run config lacks {err}") from err
    check_expected(config, path, fusion, backbone)
    if prior is not None:
        net_config = config["model"]["net"] = _with_prior_file(net_config, path, prior)
    try:
        net = network_from_checkpoint(net_config)
    except (ValueError, TypeError, KeyError, AttributeError) as err:
        # A prior's arguments are under model.net.prior (fusion_depth.models.depth_prior), or
        # prior.* where the command gave its file.
        node = "model.net.prior" if "depth_prior" in getattr(err, "owner", "") else "model.net"
        if node == "model.net.prior" and prior is not None:
            node = "prior"
        why = err.naming(lambda a: f"{node}.{a}") if isinstance(err, ArgumentError) else err
        raise CheckpointError(
            f"ckpt_path={path}: its model.net config cannot be built ({why})"
        ) from err
    # the prior just built from its files must be the one it was trained with (its digest)
    check_prior_record(net, checkpoint.get(PRIOR_KEY), f"ckpt_path={path}")
    state = network_state(checkpoint["state_dict"])
    expected = net.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong_shape = sorted(
        k for k in set(state) & set(expected) if state[k].shape != expected[k].shape
    )
    if missing or unexpected or wrong_shape:
        what = ", ".join(
            f"{name}: {keys[:3]}{' …' if len(keys) > 3 else ''}"
            for name, keys in (
                ("missing", missing),
                ("unexpected", unexpected),
                ("wrong shape", wrong_shape),
            )
            if keys
        )
        raise CheckpointError(
            f"ckpt_path={path}: its weights do not fit backbone={config['backbone']['name']} "
            f"fusion={config['fusion']['mode']}, which its run config names ({what})"
        )
    net.load_state_dict(state)
    run = checkpoint.get(RUN_KEY)
    return LoadedModel(
        net=net.eval(), config=config, path=path, run=run if isinstance(run, dict) else None
    )


def dataset_config(loaded: LoadedModel, chosen: Any | None) -> dict[str, Any]:
    """The dataset block to score or predict on: ``chosen`` (a ``dataset=`` choice composed from
    ``conf/``) when given, else the one the checkpoint was trained on (see :func:`make_reader`).
    """
    if chosen is not None:
        if "reader" not in chosen:  # e.g. experiment=smoke sets dataset sizes without a dataset=
            raise ValueError(
                f"dataset settings {sorted(chosen)} were given but no dataset was chosen: add "
                "dataset=<name> (e.g. dataset=procedural) to use them, or leave them out to use "
                f"the dataset {loaded.key}={loaded.path} was trained on"
            )
        return chosen
    block = loaded.config.get("dataset")
    if not isinstance(block, dict) or not isinstance(block.get("reader"), dict):
        record = _RECORD.get(loaded.key, "record")
        raise CheckpointError(
            f"{loaded.key}={loaded.path}: its {record} records no dataset reader; pass "
            "dataset=<name> to choose the dataset"
        )
    name = block.get("name")
    if not isinstance(name, str) or name not in READERS:
        raise CheckpointError(
            f"{loaded.key}={loaded.path}: dataset.name={name!r} is not one of "
            f"{sorted(READERS)}; pass dataset=<name> to choose the dataset"
        )
    # What the reader needs installed is checked by importing it from the table (make_reader),
    # never by a module name the file gives.
    return {k: v for k, v in block.items() if k != "requires"}


def make_reader(
    block: dict[str, Any], path: Path | None = None, key: str = "ckpt_path"
) -> Callable[..., Any]:
    """The reader of a dataset block, as a callable taking ``split=``.

    With ``path`` (the block came from that checkpoint, or the model file of ``key=model_file``
    whose sidecar recorded it), the reader class is looked up by
    ``dataset.name`` in :data:`fusion_depth.data.READERS` and the stored ``dataset.reader``
    arguments must be plain data naming that constructor's parameters. Where the reader writes
    (generated or prepared data, the reader class's ``writes_into``) is this machine's cache
    folder, not the one the file names. Otherwise (a block composed from ``conf/``) Hydra
    instantiates it as configured.

    Raises:
        CheckpointError: an unknown dataset, an argument the reader does not take, or a value
            that is not plain data (naming the key).
    """
    if path is None:
        return instantiate(block["reader"])
    name = block["name"]
    try:
        cls = reader_class(name)
    except ImportError as err:
        raise CheckpointError(
            f"{key}={path}: dataset={name} needs a package that is not installed ({err})"
        ) from err
    params = inspect.signature(cls).parameters
    args = dict(block["reader"])
    for arg, value in args.items():
        if arg not in params or arg == "split":
            raise CheckpointError(
                f"{key}={path}: dataset.reader.{arg} is not an argument of the {name} "
                f"reader; expected some of {sorted(k for k in params if k != 'split')}"
            )
        if not_plain(value, arg) is not None:
            raise CheckpointError(
                f"{key}={path}: dataset.reader.{arg} holds a {type(value).__name__}; "
                "expected plain data (strings, numbers, lists)"
            )
    arg, folder = cls.writes_into
    if arg in args:
        args[arg] = str(Path(cache_dir()) / folder)
    return functools.partial(cls, **args)
