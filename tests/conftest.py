"""Shared fixtures: compose the real configs (Hydra compose API) into an isolated run."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from helpers import compose_config, save_untrained_checkpoint
from hydra.core.config_store import ConfigStore
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

from fusion_depth.config import SWEEPS_DIR
from fusion_depth.config.hydra_main import register_sweeps
from fusion_depth.config.recipes import register_model_recipes

# conf/train.yaml's defaults pick each model's recipe options, which its commands store first.
register_model_recipes()

# Under pytest-xdist (pyproject's addopts) every worker trains at once: each gets its share of
# the cores, and the runs it starts as subprocesses inherit that share, so that the workers do
# not oversubscribe the CPU (which slows everything several times over).
if "PYTEST_XDIST_WORKER_COUNT" in os.environ:
    _threads = max(1, len(os.sched_getaffinity(0)) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"]))
    os.environ["OMP_NUM_THREADS"] = str(_threads)
    torch.set_num_threads(_threads)

# The files that take longest (training in subprocesses: kills, resumes, sweeps), longest first,
# from `pytest --durations`. pytest-xdist hands each worker whole files in collection order, so
# these go first: a long file started last would keep one worker busy while the others idle.
LONGEST_FILES = (
    "test_kills.py",
    "test_resume.py",
    "test_train.py",
    "test_export.py",
    "test_cli.py",
    "test_launchers.py",
    "test_hostile_checkpoints.py",
    "test_sparse_to_dense.py",
    "test_hparams_search.py",
    "test_radarnet.py",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    rank = {name: i for i, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: order within a file


@pytest.fixture
def packaged_sweeps():
    """The sweeps registered in Hydra's config store as the commands do, removed afterwards
    (the store is process-wide: other tests compose the sweep files by path)."""
    register_sweeps()
    yield
    for path in Path(SWEEPS_DIR).glob("*.yaml"):
        ConfigStore.instance().repo.pop(path.name, None)


@pytest.fixture(scope="session", autouse=True)
def isolated_environment(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Generated datasets go to a per-session cache; W&B never leaves the machine."""
    cache = tmp_path_factory.mktemp("fusion_depth_cache")
    os.environ["FUSION_DEPTH_CACHE"] = str(cache)
    os.environ["WANDB_MODE"] = "offline"
    os.environ["WANDB_SILENT"] = "true"
    os.environ.pop("WANDB_API_KEY", None)
    return cache


@pytest.fixture
def make_config(tmp_path: Path) -> Callable[..., DictConfig]:
    def _make(*overrides: str) -> DictConfig:
        return compose_config(list(overrides), tmp_path / "run")

    yield _make
    GlobalHydra.instance().clear()


@pytest.fixture(scope="session")
def smoke_dataset(tmp_path_factory: pytest.TempPathFactory, isolated_environment: Path) -> dict:
    """The smoke experiment's procedural block (64×96, 5 test frames), as plain data."""
    cfg = compose_config(["experiment=smoke"], tmp_path_factory.mktemp("compose"))
    GlobalHydra.instance().clear()
    return OmegaConf.to_container(cfg.dataset, resolve=True)


@pytest.fixture(scope="session")
def checkpoints(tmp_path_factory: pytest.TempPathFactory, smoke_dataset: dict) -> dict[str, Path]:
    """Untrained concat and rgb checkpoints on the smoke dataset."""
    root = tmp_path_factory.mktemp("ckpt")
    return {
        fusion: save_untrained_checkpoint(root / f"{fusion}.ckpt", fusion, smoke_dataset)
        for fusion in ("concat", "rgb")
    }
