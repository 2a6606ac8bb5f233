"""Runs that survive: a SIGKILLed run resumes where its last checkpoint left it and ends where an
uninterrupted run ends; a sweep re-run skips finished jobs and resumes the broken one."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml
from helpers import compose_config, run_module
from helpers.probe import PROBE, RESUMABLE, probe_env, probe_records

from fusion_depth.config.run_dirs import run_dirname
from fusion_depth.metrics.depth import METRIC_KEYS
from fusion_depth.runner.checkpoint_io import AtomicCheckpointIO, CheckpointWriteError
from fusion_depth.runner.datamodule import EpochSampler, ResumableLoader
from fusion_depth.runner.resume import OtherRunError, config_changes, plan_start
from fusion_depth.train.fit import train
from fusion_depth.utils.atomic import host_tag
from fusion_depth.utils.checkpoint_file import CONFIG_KEY, RUN_KEY, CheckpointError

# The built-in recipe's per-step schedule (warm-up + cosine), so that a learning rate restored
# one step off would change the resumed run's metrics (test_kills covers the per-epoch StepLR).
PER_STEP_SCHEDULE = ["scheduler=cosine", "scheduler.warmup_fraction=0.2"]


@pytest.mark.slow
def test_a_killed_run_resumes_mid_epoch_and_ends_like_an_uninterrupted_one(tmp_path) -> None:
    run_dir = tmp_path / "run"
    command = [
        sys.executable,
        "-m",
        "fusion_depth.train",
        *RESUMABLE,
        *PER_STEP_SCHEDULE,
        PROBE,
        f"hydra.run.dir={run_dir}",
    ]
    env = probe_env(tmp_path, at_step=5, action="stall")
    first = subprocess.Popen(
        command, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    deadline = time.monotonic() + 900
    while not (tmp_path / "probe.marker").exists():
        assert first.poll() is None, first.stderr.read().decode()[-3000:]
        assert time.monotonic() < deadline, "the first run never reached step 5"
        time.sleep(0.5)
    # Step 5 (epoch 1, batch 2) was trained; its checkpoint was not written yet: kill -9.
    first.send_signal(signal.SIGKILL)
    first.wait(timeout=60)
    first.stderr.close()
    assert first.returncode == -signal.SIGKILL
    assert not (run_dir / "metrics.json").exists()
    assert not list((run_dir / "checkpoints").glob(".*tmp")), "no half-written checkpoint"
    saved = torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True, mmap=True)
    assert saved["global_step"] == 4 and saved["epoch"] == 1  # mid-epoch: 1 of 3 batches done

    second = subprocess.run(
        command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900
    )
    assert second.returncode == 0, second.stderr[-3000:]
    records = probe_records(tmp_path)
    pids = list(dict.fromkeys(r["pid"] for r in records))
    assert len(pids) == 2
    before = [(r["epoch"], r["batch"], r["step"]) for r in records if r["pid"] == pids[0]]
    after = [(r["epoch"], r["batch"], r["step"]) for r in records if r["pid"] == pids[1]]
    assert before == [(0, 0, 1), (0, 1, 2), (0, 2, 3), (1, 0, 4), (1, 1, 5)]
    # Continued from step 4's checkpoint: step 5 again (its update was lost), no epoch twice.
    assert after == [(1, 1, 5), (1, 2, 6), (2, 0, 7), (2, 1, 8), (2, 2, 9)]
    # ... on the learning rate the killed run had reached, not a restarted warm-up.
    lr_at_5 = [r["lr"] for r in records if r.get("step") == 5]
    assert len(lr_at_5) == 2 and lr_at_5[0] == pytest.approx(lr_at_5[1], rel=1e-9), lr_at_5
    resumed = json.loads((run_dir / "metrics.json").read_text())
    assert resumed["resumed_from"] == str(run_dir / "checkpoints" / "last.ckpt")
    assert resumed["global_step"] == 9 and resumed["epochs"] == 3

    # The same run without the kill: the same metrics, to the printed precision.
    uninterrupted = train(
        compose_config([*RESUMABLE, *PER_STEP_SCHEDULE], tmp_path / "uninterrupted")
    )
    assert uninterrupted["resumed_from"] is None
    for key in METRIC_KEYS:
        assert f"{resumed['test'][key]:.3f}" == f"{uninterrupted['test'][key]:.3f}", key
    assert resumed["best_val_rmse"] == pytest.approx(uninterrupted["best_val_rmse"], rel=1e-6)


SWEEP = [
    "fusion_depth.train",
    "-m",
    "experiment=smoke",
    "logger=none",
    "fusion=rgb,concat",
    "callbacks.last_checkpoint.every_n_epochs=1",
    PROBE,
]


@pytest.mark.slow
def test_a_sweep_rerun_skips_finished_jobs_and_resumes_the_failed_one(tmp_path) -> None:
    env = probe_env(tmp_path, at_step=4, action="fail", only_fusion="concat")
    first = run_module(SWEEP, cwd=tmp_path, env=env)
    assert first.returncode == 1, first.stderr[-3000:]
    assert "1 ok, 1 failed" in first.stdout
    # Folders named after the overrides, not the time: the same command finds them again.
    (sweep,) = (tmp_path / "multirun").iterdir()
    assert sweep.name == run_dirname(f"{PROBE},experiment=smoke,fusion=rgb,concat")
    jobs = {
        m: sweep / run_dirname(f"{PROBE},experiment=smoke,fusion={m}") for m in ("rgb", "concat")
    }
    assert sorted(p for p in sweep.iterdir() if p.is_dir()) == sorted(jobs.values())
    failure = json.loads((jobs["concat"] / "failure.json").read_text())
    assert "failing on purpose at step 4" in failure["error"]
    done = jobs["rgb"] / "metrics.json"
    done_before = (done.stat().st_mtime_ns, done.read_text())

    second = run_module(SWEEP, cwd=tmp_path, env=env)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "2 ok, 0 failed" in second.stdout
    assert f"Already finished: {done}" in second.stdout
    assert (done.stat().st_mtime_ns, done.read_text()) == done_before  # not trained again
    resumed = json.loads((jobs["concat"] / "metrics.json").read_text())
    assert resumed["resumed_from"] == str(jobs["concat"] / "checkpoints" / "last.ckpt")
    assert resumed["global_step"] == 6
    assert not (jobs["concat"] / "failure.json").exists()
    # The second attempt trained only epoch 1 of the concat job (epoch 0 was checkpointed).
    pids = list(dict.fromkeys(r["pid"] for r in probe_records(tmp_path)))
    assert len(pids) == 2
    second_steps = [r["step"] for r in probe_records(tmp_path) if r["pid"] == pids[1]]
    assert second_steps == [4, 5, 6]


def fake_checkpoint(path: Path, overrides: list[str], wandb_id: str = "abcd1234") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": {}, RUN_KEY: {"overrides": overrides, "wandb_id": wandb_id}}, path)
    return path


def test_plan_start_resumes_skips_refuses_and_starts_over(tmp_path) -> None:
    run, ckpts = tmp_path / "run", tmp_path / "run" / "checkpoints"
    ours = ["experiment=smoke", "fusion=concat"]
    assert plan_start(run, ckpts, "auto", True, ours).checkpoint is None  # nothing there yet
    last = fake_checkpoint(ckpts / "last.ckpt", [*ours, "resume=auto"])
    (run / "failure.json").write_text("{}")
    start = plan_start(run, ckpts, "auto", True, ours, excluded=["resume"])
    assert (start.checkpoint, start.wandb_id, start.finished) == (last, "abcd1234", None)
    assert not (run / "failure.json").exists()  # an earlier attempt's failure is no longer true
    # Another configuration's checkpoint in the same folder (a shared hydra.run.dir) is refused.
    with pytest.raises(ValueError, match="belongs to another run.*fusion=rgb"):
        plan_start(run, ckpts, "auto", True, ["experiment=smoke", "fusion=rgb"])
    (ckpts / "last.ckpt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match=r"last\.ckpt.*resume=never"):
        plan_start(run, ckpts, "auto", True, ours)
    # A finished run is skipped, or with skip_done=false continued from its last checkpoint.
    fake_checkpoint(last, ours)
    metrics = {"status": "ok", "run": {"overrides": ours}, "test": {"rmse": 1.5}, "global_step": 3}
    (run / "metrics.json").write_text(json.dumps(metrics))
    assert plan_start(run, ckpts, "auto", True, ours).finished == metrics
    assert plan_start(run, ckpts, "auto", False, ours).checkpoint == last
    # resume=never removes the previous run's results and checkpoints before starting over.
    (ckpts / "epoch001-rmse1.5.ckpt").write_bytes(b"x")
    start = plan_start(run, ckpts, "never", False, ours)
    assert start.checkpoint is None and start.wandb_id != "abcd1234"
    assert not list(ckpts.glob("*.ckpt")) and not (run / "metrics.json").exists()
    with pytest.raises(ValueError, match="resume='sometimes'.*auto"):
        plan_start(run, ckpts, "sometimes", True, ours)


def test_config_changes_ignore_where_the_run_and_the_cache_are_and_excluded_keys() -> None:
    stored = {
        "paths": {"output_dir": "/old/runs/a", "cache_dir": "/old/cache"},
        "trainer": {"default_root_dir": "/old/runs/a", "max_epochs": 18},
        "dataset": {"reader": {"_target_": "x.Reader", "root": "/old/cache/procedural"}},
        "optimizer": {"lr": 1.5e-3},
        "logger": {"save_dir": "/old/runs/a", "project": "p"},
        "data": {"num_workers": 2},
    }
    moved = {
        "paths": {"output_dir": "/new/b", "cache_dir": "/home/u/.cache/fd"},
        "trainer": {"default_root_dir": "/new/b", "max_epochs": 18},
        "dataset": {"reader": {"_target_": "x.Reader", "root": "/home/u/.cache/fd/procedural"}},
        "optimizer": {"lr": 1.5e-3},
        "logger": {"save_dir": "/new/b", "project": "other"},
        "data": {"num_workers": 0},
    }
    excluded = ["logger", "data.num_workers"]
    assert config_changes(stored, moved, excluded) == []
    moved["optimizer"]["lr"] = 1e-4
    moved["trainer"]["max_epochs"] = 20
    moved["trainer"]["precision"] = "32-true"
    del moved["dataset"]["reader"]["root"]
    assert config_changes(stored, moved, excluded) == [
        "dataset.reader.root: '<cache>/procedural' → absent",
        "optimizer.lr: 0.0015 → 0.0001",
        "trainer.max_epochs: 18 → 20",
        "trainer.precision: absent → '32-true'",
    ]
    assert config_changes(stored, moved, []) != config_changes(stored, moved, excluded)


def test_a_run_folder_of_another_configuration_is_neither_skipped_nor_resumed(tmp_path) -> None:
    run, ckpts = tmp_path / "run", tmp_path / "run" / "checkpoints"
    ours = ["experiment=smoke"]
    config = {"paths": {"output_dir": str(run)}, "optimizer": {"lr": 1.5e-3}, "seed": 42}
    older = {"paths": {"output_dir": "/elsewhere"}, "optimizer": {"lr": 1e-4}, "seed": 42}
    # A checkpoint whose run config differs is refused, naming the difference; the same
    # config recorded in a folder that has moved since resumes.
    ckpts.mkdir(parents=True)
    torch.save(
        {"state_dict": {}, RUN_KEY: {"overrides": ours}, CONFIG_KEY: older}, ckpts / "last.ckpt"
    )
    with pytest.raises(
        OtherRunError, match=r"another configuration \(optimizer.lr: 0.0001 → 0.0015\)"
    ):
        plan_start(run, ckpts, "auto", True, ours, config=config)
    same = {**config, "paths": {"output_dir": "/elsewhere"}}
    torch.save(
        {"state_dict": {}, RUN_KEY: {"overrides": ours}, CONFIG_KEY: same}, ckpts / "last.ckpt"
    )
    assert (
        plan_start(run, ckpts, "auto", True, ours, config=config).checkpoint == ckpts / "last.ckpt"
    )
    # A finished run is compared with the config it wrote beside its metrics.
    metrics = {"status": "ok", "run": {"overrides": ours}, "test": {"rmse": 1.5}, "global_step": 3}
    (run / "metrics.json").write_text(json.dumps(metrics))
    (run / "config_resolved.yaml").write_text(yaml.safe_dump(older))
    with pytest.raises(OtherRunError, match=r"metrics\.json holds a run .*resume=never replaces"):
        plan_start(run, ckpts, "auto", True, ours, config=config)
    (run / "config_resolved.yaml").write_text(yaml.safe_dump(same))
    assert plan_start(run, ckpts, "auto", True, ours, config=config).finished == metrics
    # A recorded config that cannot be read leaves the decision to the overrides.
    (run / "config_resolved.yaml").write_text("optimizer: [unclosed")
    assert plan_start(run, ckpts, "auto", True, ours, config=config).finished == metrics
    # resume=never starts a finished run over, as it says, also with sweep.skip_done=true.
    start = plan_start(run, ckpts, "never", True, ours, config=config)
    assert start.finished is None and start.checkpoint is None
    assert not (run / "metrics.json").exists() and not list(ckpts.glob("*.ckpt"))


class _FullDisk:
    """A binary file that takes ``room`` bytes, then fails as a full disk does."""

    def __init__(self, file, room: int) -> None:
        self.file, self.room = file, room

    def write(self, data) -> int:
        size = len(memoryview(data).cast("B"))
        if size > self.room:
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= size
        return self.file.write(data)

    def __getattr__(self, name: str):
        return getattr(self.file, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.file.close()


def test_a_full_disk_shows_the_platforms_message_and_keeps_the_previous_checkpoint(
    tmp_path, monkeypatch
) -> None:
    path = tmp_path / "last.ckpt"
    io = AtomicCheckpointIO()
    io.save_checkpoint({"step": torch.tensor(1)}, path)
    real_open = Path.open

    def full_disk_open(self, mode="r", *args, **kwargs):
        file = real_open(self, mode, *args, **kwargs)
        return _FullDisk(file, room=100_000) if "w" in mode else file

    # The disk fills up in the middle of torch's own writer (its inline_container error).
    monkeypatch.setattr(Path, "open", full_disk_open)
    with pytest.raises(CheckpointWriteError) as failure:
        io.save_checkpoint({"step": torch.tensor(2), "weights": torch.randn(200_000)}, path)
    monkeypatch.undo()
    message = str(failure.value)
    assert message.startswith(f"could not write the checkpoint {path} (No space left on device;")
    assert "MB free there" in message and "previous checkpoint there, if any, is intact" in message
    assert "inline_container" not in message
    assert io.load_checkpoint(path)["step"].item() == 1
    assert [p.name for p in tmp_path.iterdir()] == ["last.ckpt"]  # no temporary file left


def test_checkpoints_are_loaded_weights_only(tmp_path) -> None:
    path = tmp_path / "evil.ckpt"
    torch.save({"state_dict": {}, "payload": subprocess.Popen}, path)  # needs unpickling code
    with pytest.raises(CheckpointError, match=r"evil.ckpt: refused to load.*subprocess\.Popen"):
        AtomicCheckpointIO().load_checkpoint(path, weights_only=False)


def test_a_restored_loader_hands_out_the_rest_of_its_epoch(tmp_path) -> None:
    data = list(range(10))

    def loader() -> ResumableLoader:
        return ResumableLoader(data, batch_size=2, sampler=EpochSampler(10, seed=3), drop_last=True)

    full = loader()
    full.sampler.set_epoch(4)
    epoch4 = [b.tolist() for b in full]
    assert sorted(sum(epoch4, [])) == data and epoch4 != [[0, 1], [2, 3], [4, 5], [6, 7], [8, 9]]
    full.sampler.set_epoch(5)
    assert [b.tolist() for b in full] != epoch4  # another order each epoch

    interrupted = loader()
    interrupted.sampler.set_epoch(4)
    it = iter(interrupted)
    assert [next(it).tolist() for _ in range(2)] == epoch4[:2]
    state = interrupted.state_dict()
    assert state == {"epoch": 4, "batches": 2}
    restored = loader()
    restored.load_state_dict(state)
    restored.sampler.set_epoch(4)
    assert [b.tolist() for b in restored] == epoch4[2:]
    assert [b.tolist() for b in restored] == epoch4  # the skip applies once
    restored.load_state_dict(state)
    restored.sampler.set_epoch(5)  # an epoch-end checkpoint: the next epoch starts in full
    assert len(list(restored)) == 5


def test_run_dirname_is_stable_and_safe() -> None:
    assert run_dirname("") == "default"
    assert (
        run_dirname("dataset.root=/data/kitti,fusion=add") == "dataset.root-_data_kitti+fusion-add"
    )
    long = "x=" + "a" * 400
    name = run_dirname(long)
    assert len(name.encode()) <= 200 and name == run_dirname(long) != run_dirname(long + "b")


def test_the_disk_check_asks_for_room_for_the_checkpoints_the_run_writes(tmp_path) -> None:
    from torch import nn

    from fusion_depth.config import checkpoint_bytes
    from fusion_depth.train.fit import checkpoint_room

    model = nn.Linear(100, 10)
    full, weights = checkpoint_bytes(model), checkpoint_bytes(model, 0)
    assert full == 3 * weights  # weights + Adam's two moments
    default = compose_config([], tmp_path).callbacks
    assert checkpoint_room(default, model) == 4 * full  # last + best, each written beside the old
    smoke = compose_config(["experiment=smoke"], tmp_path).callbacks
    assert checkpoint_room(smoke, model) == 2 * weights  # no last.ckpt, weights-only best


def test_a_new_start_removes_what_interrupted_attempts_left(tmp_path) -> None:
    run, ckpts = tmp_path / "run", tmp_path / "run" / "checkpoints"
    ckpts.mkdir(parents=True)
    tmp_files = [ckpts / ".last.ckpt.k2j4.ckpt.tmp", run / ".metrics.json.x8.tmp"]
    for path in tmp_files:
        path.write_bytes(b"half written")
    orphan = ckpts / "epoch002-rmse9.0000.ckpt"  # a best written after last.ckpt, then killed
    orphan.write_bytes(b"x")
    best = ckpts / "epoch001-rmse9.5000.ckpt"
    best.write_bytes(b"x")
    last = fake_checkpoint(ckpts / "last.ckpt", ["experiment=smoke"])
    checkpoint = torch.load(last, weights_only=True)
    checkpoint["callbacks"] = {
        "ModelCheckpoint{'monitor': 'val/rmse'}": {
            "dirpath": str(ckpts),
            "best_model_path": str(best),
            "best_k_models": {str(best): torch.tensor(9.5)},
        }
    }
    checkpoint["global_step"] = 4
    torch.save(checkpoint, last)
    start = plan_start(run, ckpts, "auto", True, ["experiment=smoke"])
    assert (start.checkpoint, start.global_step) == (last, 4)
    assert sorted(p.name for p in ckpts.iterdir()) == sorted([last.name, best.name])
    assert not (run / ".metrics.json.x8.tmp").exists()
    # Starting afresh (no last.ckpt), every checkpoint of the abandoned attempt goes too.
    last.unlink()
    tmp_files[0].write_bytes(b"half written")
    assert plan_start(run, ckpts, "auto", True, ["experiment=smoke"]).checkpoint is None
    assert list(ckpts.iterdir()) == []


def test_a_run_that_trained_no_step_is_never_done(tmp_path) -> None:
    from fusion_depth.runner.resume import finished_results
    from fusion_depth.runner.sweep_summary import summarize_sweep

    job = tmp_path / "sweep" / "job"
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("- fusion=rgb\n")
    for steps, done in ((0, False), (None, False), (3, True)):
        record = {"status": "ok", "run": {}, "test": {"rmse": 1.0}, "global_step": steps}
        (job / "metrics.json").write_text(json.dumps(record))
        assert (finished_results(job) is not None) == done
        assert summarize_sweep(tmp_path / "sweep")[0]["status"] == ("ok" if done else "incomplete")


_KILLED_WRITE = """
import os, sys
from pathlib import Path
from fusion_depth.utils.atomic import write_atomic
def killed(tmp):
    tmp.write_bytes(b"half written")
    os._exit(9)  # killed between the write and the rename
write_atomic(Path(sys.argv[1]), killed, suffix=sys.argv[2])
"""


def test_a_new_start_removes_every_temporary_a_killed_writer_left(tmp_path) -> None:
    """Writers killed mid-write (test_panels.npz, a panel, a map in a folder of the run) leave
    their real temporary names, whatever their suffix, in the run folder and the folders right
    inside it: a new start removes them all, and leaves the files a run keeps."""
    run = tmp_path / "run"
    targets = [
        (run / "test_panels.npz", ".npz"),
        (run / "prior" / "0123abcd.npy", ".npy"),
        (run / "predictions" / "x.png", ".png"),
        (run / "metrics.json", ".tmp"),
    ]
    for target, suffix in targets:
        killed = subprocess.run([sys.executable, "-c", _KILLED_WRITE, str(target), suffix])
        assert killed.returncode == 9
    left = [p for p in run.rglob(".*") if p.is_file()]
    assert len(left) == len(targets), left
    kept = run / "predictions" / "x.png"
    kept.write_bytes(b"a finished output")
    # Deeper than the folders right inside the run folder is not the run's (W&B's, a user's).
    deep = run / "wandb" / "offline-run" / f".x.p1h{host_tag()}.tmp"
    deep.parent.mkdir(parents=True)
    deep.write_bytes(b"not the run's")
    assert plan_start(run, None, "auto", True, ["experiment=smoke"]).checkpoint is None
    assert [p for p in run.rglob(".*") if p.is_file()] == [deep]
    assert kept.read_bytes() == b"a finished output"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ["data.batch_size=16"],
            r"data.batch_size=16: the train split of dataset=procedural has "
            r"8 frames, fewer than one batch \(the last partial batch is dropped\)",
        ),
        (["dataset.num_train=1"], r"data.batch_size=2: the train split .* has 1 frame, fewer"),
        (
            ["trainer.limit_train_batches=0"],
            r"trainer.limit_train_batches=0: leaves no batch of "
            r"the train split of dataset=procedural \(8 frames, data.batch_size=2, 4 batches\)",
        ),
        (["trainer.limit_val_batches=0.1"], r"trainer.limit_val_batches=0.1: leaves no batch"),
        (["trainer.max_steps=0"], r"trainer.max_steps=0: leaves nothing to train"),
    ],
)
def test_a_run_that_would_train_or_score_nothing_is_refused(tmp_path, overrides, message) -> None:
    from fusion_depth.errors import ConfigError

    run_dir = tmp_path / "run"
    with pytest.raises(ConfigError, match=message):
        train(compose_config(["experiment=smoke", "logger=none", *overrides], run_dir))
    assert not (run_dir / "checkpoints").exists() and not (run_dir / "metrics.json").exists()


def test_a_split_without_frames_is_refused() -> None:
    from fusion_depth.errors import ConfigError
    from fusion_depth.runner.datamodule import DepthDataModule, check_batches

    frames = {"train": 4, "val": 0, "test": 3}
    datamodule = DepthDataModule(reader=lambda split: [{}] * frames[split], num_workers=0)
    with pytest.raises(ConfigError, match=r"^dataset=mine: the val split has no frames$"):
        check_batches(datamodule, {}, "mine")
    frames["val"] = 1
    datamodule = DepthDataModule(reader=lambda split: [{}] * frames[split], num_workers=0)
    check_batches(datamodule, {}, "mine")  # 2 training batches, 1 validation, 2 test
    datamodule = DepthDataModule(
        reader=lambda split: [{}] * frames[split], batch_size=4, num_workers=0
    )
    check_batches(datamodule, {}, "mine")
    with pytest.raises(ConfigError, match=r"has 2 frames per process of 2, fewer than one"):
        check_batches(datamodule, {}, "mine", world_size=2)  # a DDP share of the 4 frames


def test_a_run_whose_every_batch_was_skipped_reports_no_result(tmp_path, monkeypatch) -> None:
    from fusion_depth.runner.module import DepthModule
    from fusion_depth.train.fit import NoTrainingError

    def nan_loss(self, batch):
        return {"loss": torch.tensor(float("nan"), requires_grad=True)}

    monkeypatch.setattr(DepthModule, "step_losses", nan_loss)
    run_dir = tmp_path / "run"
    skip_all = ["model.on_nonfinite_loss=skip", "model.max_nonfinite_skips=100"]
    with pytest.raises(NoTrainingError, match=r"trained no batch .*6 batches skipped"):
        train(compose_config(["experiment=smoke", "logger=none", *skip_all], run_dir))
    assert not (run_dir / "metrics.json").exists()


@pytest.mark.slow
def test_two_commands_on_one_run_folder_train_it_once(tmp_path) -> None:
    run_dir = tmp_path / "run"
    command = ["fusion_depth.train", *RESUMABLE, PROBE, f"hydra.run.dir={run_dir}"]
    env = probe_env(tmp_path, at_step=2, action="stall")  # whoever trains stalls at step 2
    started = [
        subprocess.Popen(
            [sys.executable, "-m", *command],
            cwd=tmp_path,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    deadline = time.monotonic() + 600
    while not (tmp_path / "probe.marker").exists() or all(p.poll() is None for p in started):
        assert time.monotonic() < deadline, "neither trained, or neither was refused"
        time.sleep(0.2)
    refused = next(p for p in started if p.poll() is not None)
    training = next(p for p in started if p is not refused)
    assert training.poll() is None
    stderr = refused.stderr.read()
    assert refused.returncode == 1, stderr[-3000:]
    assert f"{run_dir} is in use by process {training.pid} on host " in stderr, stderr[-3000:]
    assert "Traceback" not in stderr
    training.kill()
    training.wait(timeout=60)
    for p in started:
        p.stderr.close()
    assert {r["pid"] for r in probe_records(tmp_path)} == {training.pid}  # only one trained
    # The killed holder's lock is taken over by the next command, which resumes the run.
    again = run_module(command, cwd=tmp_path, env=env)
    assert again.returncode == 0, again.stderr[-3000:]
    metrics = (run_dir / "metrics.json").read_text()
    assert json.loads(metrics)["global_step"] == 9
    # The same command after the defaults changed (a new version, an edited conf/) does not
    # pass the old run off as its own: here the folder's recorded config says the run trained
    # with another learning rate than the one this command composes. One line names what
    # changed, and the finished run is left as it was.
    recorded = yaml.safe_load((run_dir / "config_resolved.yaml").read_text())
    recorded["optimizer"]["lr"] = recorded["model"]["optimizer"]["lr"] = 0.0123
    (run_dir / "config_resolved.yaml").write_text(yaml.safe_dump(recorded))
    changed = run_module(command, cwd=tmp_path, env=env)
    assert changed.returncode == 1, changed.stderr[-3000:]
    assert "holds a run of the same command with another configuration" in changed.stderr
    assert "model.optimizer.lr: 0.0123 → 0.0001; optimizer.lr: 0.0123 → 0.0001" in changed.stderr
    assert "resume=never replaces it" in changed.stderr and "Traceback" not in changed.stderr
    assert (run_dir / "metrics.json").read_text() == metrics


@pytest.mark.slow
def test_a_sweep_job_whose_folder_is_in_use_writes_nothing_there(tmp_path) -> None:
    from fusion_depth.runner.resume import RunLock

    sweep_dir = tmp_path / "sweep"
    job_dir = sweep_dir / run_dirname("experiment=smoke")
    with RunLock(job_dir):  # a live process (this one) is using the job's folder
        done = run_module(
            [
                "fusion_depth.train",
                "-m",
                "experiment=smoke",
                "logger=none",
                f"hydra.sweep.dir={sweep_dir}",
            ],
            cwd=tmp_path,
        )
    assert done.returncode == 1, done.stderr[-3000:]
    assert (
        f"job not run: {job_dir} is in use by process {os.getpid()} on host"
        in done.stdout + done.stderr
    )
    assert "0 ok, 1 failed or incomplete" in done.stdout
    assert not (job_dir / "failure.json").exists() and not (job_dir / "checkpoints").exists()


def test_a_lock_file_that_is_a_link_or_a_folder_is_refused(tmp_path) -> None:
    from fusion_depth.runner.resume import RunLock, RunLockedError

    target = tmp_path / "target.txt"
    target.write_text("keep me")
    linked = tmp_path / "linked"
    linked.mkdir()
    (linked / ".run.lock").symlink_to(target)
    with pytest.raises(RunLockedError, match=r"\.run\.lock: cannot be used as the run's lock"):
        RunLock(linked).__enter__()
    assert target.read_text() == "keep me"
    folder = tmp_path / "folder"
    (folder / ".run.lock").mkdir(parents=True)
    with pytest.raises(RunLockedError, match=r"\.run\.lock: cannot be used as the run's lock"):
        RunLock(folder).__enter__()


def test_a_key_added_since_at_the_value_that_computes_as_before_is_no_change() -> None:
    """A run folder from before the evaluation presets lacks eval.preset, eval.clamp, ...: at
    eval=paper's values they score as that run did, so it resumes; at another value it is
    another run."""
    stored = {"eval": {"crop": "none"}, "model": {"evaluation": {"crop": "none"}}}
    now = {
        "eval": {"crop": "none", "preset": "paper", "clamp": True, "units": "m"},
        "model": {"evaluation": {"crop": "none", "relative_to": "ground_truth"}},
    }
    assert config_changes(stored, now) == []
    now["eval"]["clamp"] = False
    now["model"]["evaluation"]["relative_to"] = "prediction"
    assert config_changes(stored, now) == [
        "eval.clamp: absent → False",
        "model.evaluation.relative_to: absent → 'prediction'",
    ]
