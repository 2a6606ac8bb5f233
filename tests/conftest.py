"""Shared fixtures: compose the real configs (Hydra compose API) into an isolated run."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf, open_dict

from fusion_depth.config import CONF_DIR

REPO = Path(__file__).resolve().parents[1]

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


@pytest.fixture(scope="session", autouse=True)
def isolated_environment(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Generated datasets go to a per-session cache; W&B never leaves the machine."""
    cache = tmp_path_factory.mktemp("fusion_depth_cache")
    os.environ["FUSION_DEPTH_CACHE"] = str(cache)
    os.environ["WANDB_MODE"] = "offline"
    os.environ["WANDB_SILENT"] = "true"
    os.environ.pop("WANDB_API_KEY", None)
    return cache


def compose_config(
    overrides: list[str], output_dir: Path, config_name: str = "train"
) -> DictConfig:
    """The config a ``python -m fusion_depth.<config_name>`` task function would receive."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cfg = compose(config_name, overrides=overrides, return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(output_dir)
        cfg.hydra.job.num = 0
    HydraConfig.instance().set_config(cfg)
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg


@pytest.fixture
def make_config(tmp_path: Path) -> Callable[..., DictConfig]:
    def _make(*overrides: str) -> DictConfig:
        return compose_config(list(overrides), tmp_path / "run")

    yield _make
    GlobalHydra.instance().clear()


def save_untrained_checkpoint(
    path: Path,
    fusion: str,
    dataset: dict,
    seed: int = 0,
    backbone: str = "densenet169",
    spread: bool = False,
) -> Path:
    """An untrained DepthNet saved the way training saves it (weights + run config), so tests of
    evaluate/predict need no training run. ``backbone=resnet18`` is faster; an untrained one
    predicts max_depth everywhere, so ``spread=True`` scales its output layer to depths around
    10 m that vary across the image."""
    from fusion_depth.checkpoint import plain_config
    from fusion_depth.models import DepthNet

    torch.manual_seed(seed)
    kwargs = {
        "backbone": backbone,
        "fusion": fusion,
        "min_depth": dataset["min_depth"],
        "max_depth": dataset["max_depth"],
        "depth_scale": dataset["depth_scale"],
        "sparse_encoding": "log",
    }
    net = DepthNet(**kwargs, pretrained=False)
    if spread:
        with torch.no_grad():
            net.decoder.head.bias.fill_(1.0)  # reciprocal depth 1: 10 m at depth_scale 10
            net.decoder.head.weight.mul_(30.0)
    config = {
        "model": {"net": kwargs},
        "fusion": {"mode": fusion},
        "backbone": {"name": backbone},
        "loss": {"pixel": "l1"},
        "trainer": {"precision": "32-true"},  # what evaluate scores in by default
        "seed": seed,
        "dataset": dataset,
    }
    state = {f"net.{k}": v for k, v in net.state_dict().items()}
    torch.save({"state_dict": state, "fusion_depth_config": plain_config(config)}, path)
    return path


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


def run_module(
    args: list[str], cwd: Path, timeout: int = 1800, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess:
    """``python -m <args>`` in a subprocess, as a user would run it (in ``env``, by default
    this process's environment)."""
    return subprocess.run(
        [sys.executable, "-m", *args],
        cwd=cwd,
        env=dict(os.environ) if env is None else env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def run_sweep(name: str, overrides: list[str], sweep_dir: Path) -> subprocess.CompletedProcess:
    """A ``sweeps/<name>.yaml`` sweep under ``experiment=smoke``, into ``sweep_dir``."""
    return run_module(
        [
            "fusion_depth.train",
            "--config-dir",
            str(REPO / "sweeps"),
            "--config-name",
            name,
            "-m",
            "experiment=smoke",
            "logger=none",
            *overrides,
            f"hydra.sweep.dir={sweep_dir}",
        ],
        cwd=sweep_dir.parent,
    )
