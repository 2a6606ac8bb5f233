"""Datasets: one module per dataset, plus the shared datamodule and transforms."""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from typing import Any

# The split names every dataset reader accepts (their order also keys the procedural seed streams).
SPLITS: tuple[str, ...] = ("train", "val", "test")

# The package's own table of dataset readers, by the name a dataset config and a checkpoint
# record (``dataset.name``): module and class. A checkpoint names its dataset; its reader is
# looked up here, never imported from a path stored in the file. Modules are imported on first
# use, since some need optional packages (nuScenes: the devkit).
READERS: dict[str, tuple[str, str]] = {
    "procedural": ("fusion_depth.data.procedural", "ProceduralDepth"),
    "kitti": ("fusion_depth.data.kitti", "KittiDepth"),
    "carla": ("fusion_depth.data.carla", "CarlaDepth"),
    "topview": ("fusion_depth.data.topview", "TopViewDepth"),
    "nuscenes": ("fusion_depth.data.nuscenes", "NuScenesDepth"),
}


def cache_dir() -> str:
    """Where generated/prepared datasets live: $FUSION_DEPTH_CACHE or ~/.cache/fusion_depth."""
    return str(Path(os.environ.get("FUSION_DEPTH_CACHE", "~/.cache/fusion_depth")).expanduser())


def reader_class(name: str) -> Any:
    """The reader class of dataset ``name`` (a key of :data:`READERS`).

    Raises:
        KeyError: ``name`` is not a dataset of this package.
    """
    if name not in READERS:
        raise KeyError(f"dataset {name!r} is not one of {sorted(READERS)}")
    module, cls = READERS[name]
    return getattr(importlib.import_module(module), cls)


# Where each reader writes what it generates or prepares: (argument, folder in the cache). A
# reader built from a checkpoint writes into this machine's cache, wherever the file says.
WRITES_INTO: dict[str, tuple[str, str]] = {
    "procedural": ("root", "procedural"),
    "kitti": ("cache_root", ""),
    "carla": ("cache_root", ""),
    "topview": ("cache_root", ""),
    "nuscenes": ("cache_root", ""),
}
