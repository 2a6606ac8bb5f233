"""Hydra launchers (conf/hydra/launcher/): the SLURM job a sweep submits, and sweeps of two smoke
jobs on this machine, run by submitit (one process per job) and by joblib (worker processes)."""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import pytest
import submitit
from helpers import run_module
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from fusion_depth.config import CONF_DIR


def compose_with_hydra(overrides: list[str]) -> DictConfig:
    """The sweep-level config, hydra node included, as ``python -m fusion_depth.train -m``
    composes it; no config of ours may shadow a plugin's (Hydra's deprecated schema matching)."""
    GlobalHydra.instance().clear()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with initialize_config_dir(CONF_DIR, version_base="1.3"):
                cfg = compose("train", overrides=overrides, return_hydra_config=True)
    finally:
        GlobalHydra.instance().clear()
    shadowing = [str(w.message) for w in caught if "ConfigStore schema" in str(w.message)]
    assert not shadowing, shadowing
    return cfg


def sbatch_script(cfg: DictConfig, monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> str:
    """The job script the SLURM launcher would hand to sbatch, built by the plugin's own launch()
    with submission stubbed out (submitit only checks that ``srun`` exists)."""
    fake_bin = tmp_path / "bin"
    fake_bin.mkdir(exist_ok=True)
    (fake_bin / "srun").write_text("#!/bin/sh\nexit 1\n")
    (fake_bin / "srun").chmod(0o755)
    monkeypatch.setenv("PATH", f"{fake_bin}{os.pathsep}{os.environ['PATH']}")
    executors = []

    def map_array(self, fn, *args):  # submitit.AutoExecutor.map_array: record, submit nothing
        executors.append(self)
        return []

    monkeypatch.setattr(submitit.AutoExecutor, "map_array", map_array)
    launcher = instantiate(cfg.hydra.launcher)
    launcher.setup(hydra_context=None, task_function=None, config=cfg)
    assert launcher.launch([["fusion=rgb"]], initial_job_idx=0) == []
    (executor,) = executors
    return executor._executor._make_submission_file_text("python -m submitit.core._submit", "x")


def test_slurm_launcher_runs_one_task_per_device(tmp_path, monkeypatch) -> None:
    sweep = tmp_path / "sweep"
    cfg = compose_with_hydra(
        [
            "hydra/launcher=slurm",
            "trainer.devices=4",
            "hydra.launcher.partition=gpu",
            f"hydra.sweep.dir={sweep}",
        ]
    )
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("SlurmLauncher")
    assert launcher.tasks_per_node == launcher.gpus_per_node == cfg.trainer.devices == 4
    assert launcher.partition == "gpu"
    assert launcher.nodes == 1
    assert launcher.submitit_folder == f"{sweep}/.submitit/%j"
    assert launcher.setup is None and launcher.additional_parameters == {}
    script = sbatch_script(cfg, monkeypatch, tmp_path)
    for line in (
        "--ntasks-per-node=4",
        "--gpus-per-node=4",
        "--nodes=1",
        "--partition=gpu",
        "--time=1440",
        "--cpus-per-task=8",
        "--mem=64GB",
    ):
        assert f"#SBATCH {line}\n" in script, script
    assert f"srun --unbuffered --output {sweep}/.submitit/%j/%j_%t_log.out" in script


def test_slurm_launcher_with_ddp_on_several_nodes(tmp_path, monkeypatch) -> None:
    cfg = compose_with_hydra(
        [
            "hydra/launcher=slurm",
            "trainer=ddp",
            "trainer.devices=2",
            "trainer.num_nodes=3",
            f"hydra.sweep.dir={tmp_path / 'sweep'}",
        ]
    )
    script = sbatch_script(cfg, monkeypatch, tmp_path)
    for line in ("--nodes=3", "--ntasks-per-node=2", "--gpus-per-node=2"):
        assert f"#SBATCH {line}\n" in script, script
    assert "--partition" not in script  # null: the cluster's default partition


def test_slurm_launcher_on_a_cpu_partition(tmp_path, monkeypatch) -> None:
    cfg = compose_with_hydra(
        [
            "hydra/launcher=slurm",
            "trainer.accelerator=cpu",
            "hydra.launcher.gpus_per_node=null",
            "hydra.launcher.partition=cpu",
            f"hydra.sweep.dir={tmp_path / 'sweep'}",
        ]
    )
    script = sbatch_script(cfg, monkeypatch, tmp_path)
    assert "--gpus" not in script and "#SBATCH --ntasks-per-node=1\n" in script


def test_one_machine_launchers_and_plain_plugin_names_compose() -> None:
    local = compose_with_hydra(["hydra/launcher=local", "trainer.devices=2"]).hydra.launcher
    assert local._target_.endswith("LocalLauncher")
    assert local.tasks_per_node == 1 and local.gpus_per_node == 2
    parallel = compose_with_hydra(["hydra/launcher=parallel"]).hydra.launcher
    assert parallel._target_.endswith("JoblibLauncher") and parallel.n_jobs == 2
    # The plugins' own configs stay reachable, with the plugins' defaults.
    for name, target in (
        ("submitit_slurm", "SlurmLauncher"),
        ("submitit_local", "LocalLauncher"),
        ("joblib", "JoblibLauncher"),
    ):
        plain = compose_with_hydra([f"hydra/launcher={name}"]).hydra.launcher
        assert plain._target_.endswith(target)


def launch_smoke_sweep(launcher: list[str], sweep: Path) -> None:
    """``fusion=rgb,concat`` under ``experiment=smoke`` with the given launcher; both jobs
    finish, each with the metrics of its own fusion, and the sweep summary counts them."""
    result = run_module(
        [
            "fusion_depth.train",
            "-m",
            *launcher,
            "experiment=smoke",
            "logger=none",
            "fusion=rgb,concat",
            f"hydra.sweep.dir={sweep}",
        ],
        cwd=sweep.parent,
        timeout=900,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]
    assert "2 ok, 0 failed" in result.stdout, result.stdout[-3000:]
    fusions = {}
    for metrics_file in sweep.glob("*/metrics.json"):
        job = metrics_file.parent
        overrides = list(OmegaConf.load(job / ".hydra" / "overrides.yaml"))
        (fusion,) = [o.split("=", 1)[1] for o in overrides if o.startswith("fusion=")]
        metrics = json.loads(metrics_file.read_text())
        assert metrics["status"] == "ok" and metrics["run"]["fusion"] == fusion, job
        fusions[fusion] = job
    assert set(fusions) == {"rgb", "concat"}
    summary = json.loads((sweep / "sweep_summary.json").read_text())
    assert [job["status"] for job in summary] == ["ok", "ok"]


@pytest.mark.slow
def test_submitit_local_sweep_of_two_smoke_jobs(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # both jobs start at once: one thread each
    sweep = tmp_path / "sweep"
    launch_smoke_sweep(["hydra/launcher=local", "hydra.launcher.timeout_min=10"], sweep)
    launched = OmegaConf.load(sweep / "multirun.yaml").hydra.launcher
    assert launched._target_.endswith("LocalLauncher")
    # One submitit folder per job: its stdout/stderr logs and the pickled result.
    jobs = sorted(p for p in (sweep / ".submitit").iterdir() if p.name != "%j")
    assert len(jobs) == 2
    for job in jobs:
        assert (job / f"{job.name}_0_log.out").stat().st_size > 0
        assert (job / f"{job.name}_0_log.err").is_file()
        assert (job / f"{job.name}_0_result.pkl").is_file()


@pytest.mark.slow
def test_joblib_sweep_of_two_smoke_jobs(tmp_path) -> None:
    sweep = tmp_path / "sweep"
    launch_smoke_sweep(["hydra/launcher=parallel"], sweep)
    launched = OmegaConf.load(sweep / "multirun.yaml").hydra.launcher
    assert launched._target_.endswith("JoblibLauncher") and launched.n_jobs == 2
