"""Data-parallel training on one machine without re-running the command line.

Lightning's ``ddp`` strategy starts the other ranks by running ``sys.argv`` again. Under a
Hydra multirun that launches the whole sweep again in every rank. Here ``train`` starts the
ranks itself instead, as processes that are handed the already composed config, each with the
environment Lightning reads for an externally launched process (``LOCAL_RANK``, ``RANK``,
``WORLD_SIZE``, ``MASTER_ADDR``, ``MASTER_PORT``). When a cluster launcher already started one
process per device (SLURM tasks, torchrun), Lightning sees that and nothing is launched.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import socket
from collections.abc import Callable
from multiprocessing.connection import wait
from typing import Any

import lightning as L
from hydra.core.hydra_config import HydraConfig
from hydra.core.utils import setup_globals
from lightning.pytorch.strategies.launchers.subprocess_script import _SubprocessScriptLauncher
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)


def local_world_size(trainer_cfg: DictConfig) -> int:
    """How many processes this machine must start for ``trainer_cfg`` (0: none; Lightning
    runs in this process, or a cluster launcher started the processes).

    Decided by Lightning itself, from a Trainer built with only the device and strategy
    settings: its ``ddp`` launcher is the one that would re-run the command line.
    """
    keys = ("accelerator", "devices", "num_nodes", "strategy")
    settings = {k: trainer_cfg[k] for k in keys if k in trainer_cfg}
    quiet = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    level = quiet.level
    quiet.setLevel(logging.WARNING)  # no second "GPU available: ..." banner
    try:
        trainer = L.Trainer(
            **settings,
            logger=False,
            enable_checkpointing=False,
            enable_progress_bar=False,
            enable_model_summary=False,
        )
    finally:
        quiet.setLevel(level)
    launches = isinstance(trainer.strategy.launcher, _SubprocessScriptLauncher)
    if not launches or trainer.num_devices * trainer.num_nodes == 1:
        return 0
    if trainer.num_nodes > 1:
        raise ValueError(
            f"trainer.num_nodes={trainer.num_nodes}: several nodes need a cluster launcher that "
            "starts one process per device on each node, e.g. -m hydra/launcher=slurm "
            "(see docs/guides/scale.md)"
        )
    return trainer.num_devices


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run_rank(fn: Callable[[Any], Any], job: Any, env: dict[str, str], hydra: Any) -> None:
    os.environ.update(env)
    if hydra is not None:  # ${hydra:...} interpolations of the job's config resolve as in the job
        setup_globals()
        HydraConfig.instance().cfg = hydra
    fn(job)


def launch_local_ranks(fn: Callable[[Any], Any], job: Any, world_size: int) -> None:
    """Run ``fn(job)`` in ``world_size`` new processes of this machine, as ranks 0..n-1 of one
    process group; return when all succeeded. If one fails, the others are stopped and a
    RuntimeError names it (its traceback is on stderr), so one failed run never hangs a sweep
    in a collective operation."""
    hydra = None
    if HydraConfig.initialized():  # as plain data: a launcher's typed config may not pickle
        hydra = OmegaConf.create(OmegaConf.to_container(HydraConfig.instance().cfg))
    common = {
        "MASTER_ADDR": "127.0.0.1",
        "MASTER_PORT": str(_free_port()),
        "WORLD_SIZE": str(world_size),
        "NODE_RANK": "0",
    }
    context = mp.get_context("spawn")  # safe with CUDA; the ranks import the package afresh
    # A spawned process re-selects its parent's default start method; inside a joblib worker
    # that is "loky", which a fresh interpreter does not know, so it is "spawn" while starting.
    default = mp.get_start_method(allow_none=True)
    foreign = default is not None and default not in mp.get_all_start_methods()
    ranks = []
    try:
        if foreign:
            mp.set_start_method("spawn", force=True)
        try:
            for rank in range(world_size):
                env = {**common, "LOCAL_RANK": str(rank), "RANK": str(rank)}
                process = context.Process(
                    target=_run_rank, args=(fn, job, env, hydra), name=f"fusion-depth-rank{rank}"
                )
                process.start()
                ranks.append(process)
        finally:
            if foreign:
                mp.set_start_method(default, force=True)
        log.info("started %d data-parallel processes on this machine", world_size)
        running = list(ranks)
        while running:
            wait([p.sentinel for p in running])
            for process in [p for p in running if p.exitcode is not None]:
                running.remove(process)
                if process.exitcode != 0:
                    raise RuntimeError(
                        f"rank {ranks.index(process)} of {world_size} exited with code "
                        f"{process.exitcode} (its error is printed above); the other ranks "
                        "were stopped"
                    )
    finally:
        for process in ranks:
            if process.is_alive():
                process.terminate()
        for process in ranks:
            process.join(timeout=30)
            if process.is_alive():
                process.kill()
                process.join()
