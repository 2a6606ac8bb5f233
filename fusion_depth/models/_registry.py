"""The package's table of depth networks, created by name (as timm's ``_registry.py`` and
``_factory.py`` do). A config names its network with ``model.net.name``; a checkpoint's network
is rebuilt from that name and its stored arguments, never from a path stored in the file."""

from __future__ import annotations

import importlib
import inspect
from dataclasses import dataclass
from typing import Any

from fusion_depth.models.base import DepthModel


@dataclass(frozen=True)
class ModelEntry:
    """One network of the table: where its class lives, and what it can take."""

    module: str
    cls: str
    label: str  # how tables and plots name it
    paper: str  # the publication it follows
    fusions: tuple[str, ...]  # the fusion modes it takes
    backbones: tuple[str, ...] | None = None  # the encoders it takes (None: any the platform has)
    sensors: tuple[str, ...] | None = None  # the sparse sensors it needs (None: any)


MODELS: dict[str, ModelEntry] = {
    "densedepth": ModelEntry(
        "fusion_depth.models.depth_net",
        "DepthNet",
        "DenseDepth",
        "Alhashim & Wonka 2018, fused as in the paper (Sec. 3)",
        ("rgb", "concat", "add"),
    ),
    "sparse_to_dense": ModelEntry(
        "fusion_depth.models.sparse_to_dense",
        "SparseToDense",
        "Sparse-to-Dense",
        "Ma & Karaman, ICRA 2018",
        ("rgb", "concat"),
        ("resnet18", "resnet50"),
    ),
    "radarnet": ModelEntry(
        "fusion_depth.models.radarnet",
        "RadarNet",
        "RadarNet",
        "Singh et al., CVPR 2023 (radar-camera association, then fusion)",
        ("concat",),
        ("resnet18",),
        ("radar",),
    ),
}
DEFAULT_MODEL = "densedepth"  # what a checkpoint written before models had names holds


def model_entry(name: Any) -> ModelEntry:
    """The table's entry of ``name``.

    Raises:
        ValueError: ``name`` is not a model of the table (naming the choices).
    """
    if not isinstance(name, str) or name not in MODELS:
        raise ValueError(f"model.net.name={name!r}: expected one of {sorted(MODELS)}")
    return MODELS[name]


def model_class(name: str) -> type[DepthModel]:
    """The class of model ``name`` (imported on first use)."""
    entry = model_entry(name)
    return getattr(importlib.import_module(entry.module), entry.cls)


def model_arguments(name: str) -> tuple[str, ...]:
    """The keyword arguments model ``name``'s constructor takes."""
    return tuple(inspect.signature(model_class(name)).parameters)


def create_model(name: str = DEFAULT_MODEL, **kwargs: Any) -> DepthModel:
    """Model ``name`` built with ``kwargs`` (its constructor's arguments).

    Raises:
        ValueError: an unknown name, or an argument the model rejects.
        TypeError: an argument the model does not take.
    """
    return model_class(name)(**kwargs)
