"""What several test files share: the repository's root, configs composed as a command would
receive them, checkpoints saved without training, commands run as a user runs them, and the
files of a folder to compare two caches by.

Fixtures that use these live in ``conftest.py``; test files import these by name."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, open_dict

from fusion_depth.config import CONF_DIR

REPO = Path(__file__).resolve().parents[2]


def file_bytes(folder: Path) -> dict[str, bytes]:
    """Every file below ``folder`` (hidden ones too), by its path relative to it, with its
    bytes."""
    return {
        str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()
    }


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


def command_message(err: BaseException, *overrides: str) -> str:
    """What a command run with ``overrides`` prints for ``err``: an
    :class:`~fusion_depth.errors.ArgumentError` of the science code (naming its argument) names
    the config key where it is set (:func:`fusion_depth.config.arguments.config_message`)."""
    from fusion_depth.config.arguments import config_message
    from fusion_depth.errors import ArgumentError

    if not isinstance(err, ArgumentError):
        return str(err)
    import tempfile

    with tempfile.TemporaryDirectory() as run:
        cfg = compose_config(list(overrides), Path(run))
    GlobalHydra.instance().clear()
    return config_message(err, cfg=cfg)


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
    from fusion_depth.models import DepthNet
    from fusion_depth.utils.checkpoint_file import plain_config

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
