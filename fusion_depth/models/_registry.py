"""The package's table of depth networks, created by name (as timm's ``_registry.py`` and
``_factory.py`` do). A config names its network with ``model.net.name``; a checkpoint's network
is rebuilt from that name and its stored arguments, never from a path stored in the file."""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from fusion_depth.errors import ArgumentError
from fusion_depth.models.base import DepthModel
from fusion_depth.utils.overrides import show


@dataclass(frozen=True)
class Recipe:
    """A model's published training recipe: what ``model=<name>`` trains with unless the command
    line (``backbone=``, ``loss=``, ``optimizer=``, ``scheduler=``, or a key) or a dataset's own
    recipe (``conf/experiment/<dataset>_<model>.yaml``) says otherwise. Names are options of the
    config groups (``conf/<group>/<name>.yaml``); the arguments replace that option's values.

    Attributes:
        backbone: the encoder (``densenet169``, ``resnet18``, ...).
        loss: the loss (``l1``: SSIM + edge + L1 on reciprocal depth; ``l1_only``: L1 alone).
        optimizer: the optimizer (``adam``, ``adamw``, ``sgd``) and ``optimizer_args`` its values.
        schedule: the schedule (``step``, ``cosine``, ``constant``:
            :func:`fusion_depth.optim.schedules.create_schedule`'s table) and ``schedule_args``.
        batch_size: the training batch; None keeps ``conf/train.yaml``'s (2, the paper's).
        max_epochs: the epochs; None keeps the trainer's (20, the paper's).
        augment: the training augmentation's values that differ from the paper's
            (``conf/train.yaml``'s ``augment``: :class:`~fusion_depth.data.transforms.
            TrainAugmentation`'s arguments); what depends on a dataset's frames (``crop``,
            ``crop_center``) belongs in that dataset's recipe.
    """

    backbone: str
    loss: str
    optimizer: str
    schedule: str
    optimizer_args: Mapping[str, Any] = field(default_factory=dict)
    schedule_args: Mapping[str, Any] = field(default_factory=dict)
    batch_size: int | None = None
    max_epochs: int | None = None
    augment: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ModelEntry:
    """One network of the table: where its class lives, what it can take, how it trains."""

    module: str
    cls: str
    label: str  # how tables and plots name it
    paper: str  # the publication it follows
    fusions: tuple[str, ...]  # the fusion modes it takes
    recipe: Recipe  # its authors' training recipe
    backbones: tuple[str, ...] | None = None  # the encoders it takes (None: any the platform has)
    sensors: tuple[str, ...] | None = None  # the sparse sensors it needs (None: any)
    needs_prior: bool = False  # a monocular prior (prior=...) is what it works on


# The built-in models' modules, in the order tables list them; any other module of this package
# that registers a model follows, by name.
_BUILT_IN = ("depth_net", "sparse_to_dense", "radarnet")


class _ModelTable(Mapping[str, ModelEntry]):
    """``name → ModelEntry``, filled by :func:`register_model` as the package's model modules
    are imported; the first look-up imports every module of ``fusion_depth.models`` (the
    package's own code, found by listing its folder), so that each registers its model."""

    def __init__(self) -> None:
        self.entries: dict[str, ModelEntry] = {}  # as registered, before any discovery
        self._discovered = False

    def _discover(self) -> None:
        if self._discovered:
            return
        self._discovered = True
        package = importlib.import_module("fusion_depth.models")
        found = sorted(m.name for m in pkgutil.iter_modules(package.__path__))
        for name in (*_BUILT_IN, *(n for n in found if n not in _BUILT_IN)):
            if not name.startswith("_"):
                importlib.import_module(f"fusion_depth.models.{name}")

    def __getitem__(self, name: str) -> ModelEntry:
        self._discover()
        return self.entries[name]

    def __iter__(self) -> Iterator[str]:
        self._discover()
        return iter(self.entries)

    def __len__(self) -> int:
        self._discover()
        return len(self.entries)


MODELS = _ModelTable()
DEFAULT_MODEL = "densedepth"  # what a checkpoint written before models had names holds


def register_model(
    name: str,
    *,
    label: str,
    paper: str,
    fusions: tuple[str, ...],
    recipe: Recipe,
    backbones: tuple[str, ...] | None = None,
    sensors: tuple[str, ...] | None = None,
    needs_prior: bool = False,
) -> Callable[[type[DepthModel]], type[DepthModel]]:
    """Put the decorated network in the table as ``name`` (what ``model=`` and
    ``model.net.name`` say), as timm's ``@register_model`` does: the class, what it takes and
    its recipe are declared in one place, beside the network.

    Args:
        name: the model's name; a Python identifier.
        label: how tables and plots name it.
        paper: the publication it follows (named in errors about what it cannot take).
        fusions: the ``fusion=`` modes it takes.
        recipe: its authors' training recipe (:class:`Recipe`).
        backbones: the encoders it takes; None: any the platform has.
        sensors: the sparse sensors it needs (``("radar",)``); None: any.
        needs_prior: it works on a monocular prior, so ``prior=none`` is refused.

    Raises:
        ValueError: ``name`` is not an identifier, or another class has it.
    """

    def register(cls: type[DepthModel]) -> type[DepthModel]:
        known = MODELS.entries.get(name)
        if not name.isidentifier() or (known is not None and known.cls != cls.__name__):
            raise ValueError(f"register_model: name={name!r} is taken or not an identifier")
        entry = ModelEntry(
            cls.__module__,
            cls.__name__,
            label,
            paper,
            tuple(fusions),
            recipe,
            backbones,
            sensors,
            needs_prior,
        )
        MODELS.entries[name] = entry
        return cls

    return register


def model_entry(name: Any) -> ModelEntry:
    """The table's entry of ``name``.

    Raises:
        ArgumentError: ``name`` is not a model of the table (naming the choices).
    """
    if not isinstance(name, str) or name not in MODELS:
        raise ArgumentError(
            f"{{name}}={name!r}: expected one of {sorted(MODELS)}", "name", owner=model_entry
        )
    return MODELS[name]


def model_class(name: str) -> type[DepthModel]:
    """The class of model ``name`` (imported on first use)."""
    entry = model_entry(name)
    return getattr(importlib.import_module(entry.module), entry.cls)


def model_arguments(name: str) -> tuple[str, ...]:
    """The keyword arguments model ``name``'s constructor takes."""
    return tuple(inspect.signature(model_class(name)).parameters)


def check_model_takes(
    name: str, fusion: Any = None, backbone: Any = None, sensor: Any = None, prior: Any = None
) -> None:
    """Model ``name`` takes fusion mode ``fusion``, encoder ``backbone`` and a dataset whose
    sparse sensor is ``sensor``, as its registration says, and a monocular prior ``prior`` (a
    name other than ``none``) when its constructor takes a ``prior`` (None: not checked). The
    one place these are checked: :func:`create_model` and the config checks call it.

    Raises:
        ArgumentError: an unknown name, or the first argument the model does not take, naming
            what it takes and its paper.
    """
    entry = model_entry(name)
    given = (
        ("fusion", fusion, entry.fusions),
        ("backbone", backbone, entry.backbones),
        ("sensor", sensor, entry.sensors),
    )
    for argument, value, allowed in given:
        if value is not None and allowed is not None and value not in allowed:
            raise ArgumentError(
                f"model={name} cannot take {{{argument}}}={show(value)}: it takes "
                f"{{{argument}}}={'/'.join(allowed)} ({entry.paper})",
                argument,
                owner=check_model_takes,
            )
    if prior == "none" and entry.needs_prior:
        raise ArgumentError(
            f"{{prior}}=none: model={name} works on a monocular prior; choose one "
            "(prior=depth_anything_v2, or prior=checkpoint)",
            "prior",
            owner=check_model_takes,
        )
    if prior not in (None, "none") and "prior" not in model_arguments(name):
        takers = [n for n in MODELS if "prior" in model_arguments(n)]
        raise ArgumentError(
            f"model={name} cannot take {{prior}}={show(prior)}: it takes no prior (the models "
            f"that do: {', '.join(takers)})",
            "prior",
            owner=check_model_takes,
        )


# Network arguments a checkpoint never sets: files read at build time, whose weights the
# checkpoint's own replace.
NOT_FROM_CHECKPOINT = ("pretrained", "weights", "association_weights")


def network_from_checkpoint(net_config: Mapping[str, Any]) -> DepthModel:
    """The network a checkpoint's ``model.net`` config records, rebuilt by its name in the table
    (checkpoints from before models had names hold the paper's) from the stored arguments its
    constructor takes, without weights (``pretrained=False``: the checkpoint's replace
    ImageNet's, which need not be on disk); load them with :func:`network_state`.

    Raises:
        ArgumentError: an unknown name or an argument the network rejects.
        TypeError: an argument it does not take.
    """
    name = net_config.get("name", DEFAULT_MODEL)
    taken = set(model_arguments(name)) - set(NOT_FROM_CHECKPOINT)
    return create_model(
        name, **{k: v for k, v in net_config.items() if k in taken}, pretrained=False
    )


def network_state(state_dict: Mapping[str, Any]) -> dict[str, Any]:
    """The network's entries of a Lightning module's state dict (``net.*``), unprefixed."""
    return {k.removeprefix("net."): v for k, v in state_dict.items() if k.startswith("net.")}


def create_model(name: str = DEFAULT_MODEL, **kwargs: Any) -> DepthModel:
    """Model ``name`` built with ``kwargs`` (its constructor's arguments).

    Raises:
        ArgumentError: an unknown name, a fusion mode or encoder the model does not take
            (:func:`check_model_takes`), or an argument the model rejects.
        TypeError: an argument the model does not take.
    """
    check_model_takes(name, kwargs.get("fusion"), kwargs.get("backbone"))
    return model_class(name)(**kwargs)
