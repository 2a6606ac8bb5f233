"""Data-parallel training: a 2-process CPU DDP run (gloo) inside a Hydra sweep, started by
train itself from the composed config, so nothing re-runs the command line."""

from __future__ import annotations

import json

import pytest
from helpers import compose_config, run_module
from hydra.core.global_hydra import GlobalHydra

from fusion_depth.runner.distributed import local_world_size


@pytest.mark.slow
def test_a_two_process_cpu_ddp_run_trains_and_tests_without_relaunching(tmp_path) -> None:
    sweep = tmp_path / "sweep"
    args = [
        "fusion_depth.train",
        "-m",
        "experiment=smoke",
        "logger=none",
        "trainer=ddp",
        "trainer.accelerator=cpu",
        "trainer.devices=2",
        f"hydra.sweep.dir={sweep}",
    ]
    result = run_module(args, cwd=tmp_path, timeout=900)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-3000:]
    assert "1 ok, 0 failed" in result.stdout
    # One sweep, one job: the ranks were started from the composed config, not from argv.
    assert output.count("Launching 1 jobs locally") == 1
    assert "started 2 data-parallel processes" in output
    (job,) = [p for p in sweep.iterdir() if (p / ".hydra").is_dir()]
    assert not list(tmp_path.rglob("*train_ddp_process*"))
    saved = json.loads((job / "metrics.json").read_text())
    # 8 training frames split over 2 ranks of batch 2: 2 optimizer steps per epoch, 2 epochs.
    assert saved["global_step"] == 4 and saved["epochs"] == 2
    # The test stage ran on rank 0 alone, over the whole test split, each image once.
    assert saved["test"]["num_images"] == 5
    rows = (job / "per_image.csv").read_text().splitlines()[1:]
    assert sorted(int(r.split(",")[0]) for r in rows) == list(range(5))
    assert saved["best_checkpoint"] and (job / "checkpoints").is_dir()


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        ([], 0),  # one device: Lightning runs in this process
        (["trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2"], 2),
        (["trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=1"], 0),
        (["trainer.accelerator=cpu", "trainer.devices=2", "trainer.strategy=ddp_spawn"], 0),
    ],
)
def test_local_world_size_is_what_lightning_would_launch(tmp_path, overrides, expected) -> None:
    cfg = compose_config(overrides, tmp_path)
    GlobalHydra.instance().clear()
    assert local_world_size(cfg.trainer) == expected


def test_several_nodes_need_a_cluster_launcher(tmp_path, monkeypatch) -> None:
    for var in ("SLURM_NTASKS", "LOCAL_RANK", "TORCHELASTIC_RUN_ID"):
        monkeypatch.delenv(var, raising=False)
    overrides = ["trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2"]
    cfg = compose_config([*overrides, "trainer.num_nodes=2"], tmp_path)
    GlobalHydra.instance().clear()
    with pytest.raises(ValueError, match="trainer.num_nodes=2: .*hydra/launcher=slurm"):
        local_world_size(cfg.trainer)


def test_the_trainer_groups_compose(tmp_path) -> None:
    gpu = compose_config(["trainer=gpu", "experiment=paper"], tmp_path).trainer
    assert (gpu.accelerator, gpu.devices, gpu.max_epochs) == ("gpu", 1, 20)  # the paper's 20
    ddp = compose_config(["trainer=ddp"], tmp_path).trainer
    GlobalHydra.instance().clear()
    assert (ddp.strategy, ddp.devices, ddp.sync_batchnorm) == ("ddp", "auto", False)
