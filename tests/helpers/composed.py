"""The commands whose composed configs must not change when the config files are rearranged, and
the values each composes, as ``--cfg job --resolve`` prints them (tests/fixtures/composed/)."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from . import compose_config

# A real dataset's folders, which a command must be given.
_KITTI = ["dataset=kitti", "dataset.root=DATA", "dataset.raw_root=RAW"]

# The four, then a real dataset with each model (a model's published recipe, no
# dataset recipe), and each of the four groups a command line names (its choice wins).
CASES: dict[str, list[str]] = {
    "default": [],
    "sparse_to_dense": ["model=sparse_to_dense"],
    "radarnet": ["model=radarnet"],
    "paper": ["experiment=paper"],
    "paper_radarnet": ["experiment=paper", "model=radarnet"],
    "kitti": [*_KITTI],
    "kitti_sparse_to_dense": [*_KITTI, "model=sparse_to_dense"],
    "nuscenes_radarnet": ["dataset=nuscenes", "dataset.root=DATA", "model=radarnet"],
    "backbone_resnet18": ["backbone=resnet18"],
    "loss_berhu": ["loss=berhu"],
    "optimizer_sgd": ["optimizer=sgd"],
    "scheduler_step": ["scheduler=step"],
    "radarnet_scheduler_cosine": ["model=radarnet", "scheduler=cosine"],
    "smoke": ["experiment=smoke"],
    "smoke_radarnet": ["experiment=smoke", "model=radarnet"],
}

# Where the run folder and the cache are: the same stand-ins on every machine.
RUN_DIR, CACHE_DIR = "RUN", "CACHE"


def composed_values(overrides: list[str]) -> dict:
    """The job config ``python -m fusion_depth.train <overrides>`` receives, every interpolation
    resolved; FUSION_DEPTH_CACHE must be ``CACHE``. (The fixtures were written without the
    ``recipe`` node that carried values to the groups then; the values are compared where they
    landed, and a config that still has the node differs.)"""
    cfg = compose_config(overrides, Path(RUN_DIR))
    values = OmegaConf.to_container(cfg, resolve=True)
    return values
