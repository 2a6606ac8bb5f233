"""Resume is exact wherever the kill lands: SIGKILLs inside validation, inside the test stage,
and at random moments (some timed to land while a checkpoint is written), each followed by the
same command, end with the same steps, validation record, best checkpoint, test metrics and CSV
log as an uninterrupted run of the same seed."""

from __future__ import annotations

import csv
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from helpers import compose_config
from helpers.probe import PROBE, RESUMABLE, probe_env

from fusion_depth.metrics.depth import METRIC_KEYS
from fusion_depth.train.fit import train

# RESUMABLE (3 batches per epoch, last.ckpt after every step and epoch) for 4 epochs, with a
# CSV log and a learning rate that changes every epoch, so a lost or repeated scheduler step
# shows too.
KILLABLE = [
    *(o for o in RESUMABLE if o not in ("logger=none", "trainer.max_epochs=3")),
    "trainer.max_epochs=4",
    "logger=csv",
    "scheduler.step_size=1",
]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The reference: the same run, never interrupted (metrics.json, its run folder)."""
    run_dir = tmp_path_factory.mktemp("uninterrupted") / "run"
    results = train(compose_config(KILLABLE, run_dir))
    assert results["resumed_from"] is None
    return {"results": results, "dir": run_dir}


def command(run_dir: Path) -> list[str]:
    return [
        sys.executable,
        "-m",
        "fusion_depth.train",
        *KILLABLE,
        PROBE,
        f"hydra.run.dir={run_dir}",
    ]


def csv_rows(run_dir: Path) -> list[dict]:
    with (run_dir / "csv" / "metrics.csv").open() as f:
        return list(csv.DictReader(f))


def assert_same_as_uninterrupted(run_dir: Path, reference: dict) -> dict:
    """The run in ``run_dir`` finished as the reference did: steps, every validation epoch,
    the best checkpoint, the test metrics (to the printed digit), the checkpoint folder and
    the CSV log."""
    expected = reference["results"]
    results = json.loads((run_dir / "metrics.json").read_text())
    assert results["status"] == "ok"
    assert (results["global_step"], results["epochs"]) == (
        expected["global_step"],
        expected["epochs"],
    )
    assert [(v["epoch"], v["step"]) for v in results["validation"]] == [
        (v["epoch"], v["step"]) for v in expected["validation"]
    ]
    for got, want in zip(results["validation"], expected["validation"], strict=True):
        for key in METRIC_KEYS:
            assert got[key] == pytest.approx(want[key], rel=1e-6), (got["epoch"], key)
    assert Path(results["best_checkpoint"]).name == Path(expected["best_checkpoint"]).name
    assert results["best_val_rmse"] == pytest.approx(expected["best_val_rmse"], rel=1e-6)
    for key in METRIC_KEYS:
        assert f"{results['test'][key]:.3f}" == f"{expected['test'][key]:.3f}", key
    # Nothing left over from the interrupted attempts: no orphaned best, no temporary file.
    names = sorted(p.name for p in (run_dir / "checkpoints").iterdir())
    assert names == sorted(p.name for p in (reference["dir"] / "checkpoints").iterdir())
    assert not list(run_dir.glob(".*.tmp"))
    # The CSV log continues the interrupted one: the same rows as the uninterrupted run's.
    rows, want_rows = csv_rows(run_dir), csv_rows(reference["dir"])
    assert [(r["step"], r["epoch"]) for r in rows] == [(r["step"], r["epoch"]) for r in want_rows]
    for got, want in zip(rows, want_rows, strict=True):
        for key, value in want.items():
            if key.startswith(("train/", "val/", "lr-")) and value:
                assert float(got[key]) == pytest.approx(float(value), rel=1e-5), (key, got)
    return results


def wait_for(path: Path, process: subprocess.Popen, timeout: float = 600) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert process.poll() is None, process.stderr.read().decode()[-3000:]
        assert time.monotonic() < deadline, f"{path} never appeared"
        time.sleep(0.1)


def kill(process: subprocess.Popen) -> None:
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=60)
    process.stderr.close()


@pytest.mark.slow
def test_kills_in_validation_and_in_the_test_stage_are_redone(tmp_path, uninterrupted) -> None:
    run_dir = tmp_path / "run"
    # 1: killed inside epoch 1's validation, after that epoch's last training step.
    env = probe_env(tmp_path, at_step=None, action="stall", val_epoch=1)
    first = subprocess.Popen(command(run_dir), cwd=tmp_path, env=env, stderr=subprocess.PIPE)
    wait_for(tmp_path / "probe.val", first)
    kill(first)
    assert not (run_dir / "metrics.json").exists()
    # 2: the same command, killed this time inside the test stage.
    env = probe_env(tmp_path, at_step=None, action="stall", val_epoch=1, in_test=True)
    second = subprocess.Popen(command(run_dir), cwd=tmp_path, env=env, stderr=subprocess.PIPE)
    wait_for(tmp_path / "probe.test", second)
    kill(second)
    assert not (run_dir / "metrics.json").exists()
    # 3: the same command again, to the end.
    third = subprocess.run(
        command(run_dir), cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900
    )
    assert third.returncode == 0, third.stderr[-3000:]

    lines = (tmp_path / "probe.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    pids = list(dict.fromkeys(r["pid"] for r in records))
    assert len(pids) == 2  # the third process trained and validated nothing: it only tested
    by_pid = [[r for r in records if r["pid"] == pid] for pid in pids]
    # The interrupted epoch-1 validation was run again by the second process, after redoing
    # the epoch's last step (its step save was skipped: validation followed it).
    assert [r["val_epoch"] for r in by_pid[0] if "val_epoch" in r] == [0]
    second_run = [(r.get("val_epoch"), r.get("step")) for r in by_pid[1]]
    assert second_run[:2] == [(None, 6), (1, 6)]
    assert [r["val_epoch"] for r in by_pid[1] if "val_epoch" in r] == [1, 2, 3]
    results = assert_same_as_uninterrupted(run_dir, uninterrupted)
    assert results["resumed_from"] == str(run_dir / "checkpoints" / "last.ckpt")


@pytest.mark.slow
def test_random_kills_never_change_the_result(tmp_path, uninterrupted) -> None:
    """At least 10 SIGKILLs at random moments, a third of them while a checkpoint is being
    written, each followed by the same command; then the run is let finish."""
    seed = int(os.environ.get("FUSION_DEPTH_KILL_SEED", "20261130"))
    rng = random.Random(seed)
    run_dir = tmp_path / "run"
    checkpoints = run_dir / "checkpoints"
    env = probe_env(tmp_path, at_step=None, action="stall")
    log = tmp_path / "probe.jsonl"
    kills: list[str] = []

    def records() -> int:
        return len(log.read_text().splitlines()) if log.exists() else 0

    while len(kills) < 10:
        assert len(kills) < 40
        before = records()
        process = subprocess.Popen(command(run_dir), cwd=tmp_path, env=env, stderr=subprocess.PIPE)
        mode = ("checkpoint write", "after a record", "any time")[len(kills) % 3]
        wanted = rng.randint(1, 2)  # the how-many-th checkpoint write / new record to wait for
        if mode == "any time":  # after a random delay or a few more records, whichever is first,
            # so that a fast machine does not finish before the kill
            delay = time.monotonic() + rng.uniform(2, 11)
            enough_records = before + rng.randint(2, 4)
        writes, writing = 0, False
        deadline = time.monotonic() + 300
        while process.poll() is None and time.monotonic() < deadline:
            if mode == "checkpoint write":
                now_writing = bool(list(checkpoints.glob(".*.tmp")))  # a write under way
                writes += now_writing and not writing
                writing = now_writing
                if writes >= wanted:
                    break
                time.sleep(0.005)
            elif mode == "after a record":  # inside a step, validation, or between epochs
                if records() >= before + wanted:
                    time.sleep(rng.uniform(0, 0.6))
                    break
                time.sleep(0.02)
            else:  # start-up, training or checkpointing
                if time.monotonic() >= delay or records() >= enough_records:
                    break
                time.sleep(0.02)
        if process.poll() is not None:  # finished first: nothing was interrupted
            assert process.returncode == 0, process.stderr.read().decode()[-3000:]
            process.stderr.close()
            break
        kill(process)
        kills.append(mode)
        last = checkpoints / "last.ckpt"
        step = None
        if last.exists():  # never half-written
            step = torch.load(last, weights_only=True, mmap=True)["global_step"]
        print(f"kill {len(kills)} ({mode}): last.ckpt at step {step}")  # shown on failure
    assert len(kills) >= 10, f"seed {seed}: the run finished after {len(kills)} kills"
    assert kills.count("checkpoint write") >= 3
    final = subprocess.run(
        command(run_dir), cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900
    )
    assert final.returncode == 0, final.stderr[-3000:]
    assert_same_as_uninterrupted(run_dir, uninterrupted)


def _kill_at_each(tmp_path: Path, run_dir: Path, overrides: list[str], points: list) -> None:
    """Run the command once per break point (``[epoch, batch]``, the probe stalls there once,
    in order), SIGKILL it there, then run it to the end."""
    env = probe_env(tmp_path, at_step=None, action="stall", at_batches=points)
    args = [sys.executable, "-m", "fusion_depth.train", *overrides, f"hydra.run.dir={run_dir}"]
    for i in range(len(points)):
        process = subprocess.Popen(args, cwd=tmp_path, env=env, stderr=subprocess.PIPE)
        wait_for(tmp_path / f"probe.batch{i}", process)
        kill(process)
    final = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    assert final.returncode == 0, final.stderr[-3000:]


@pytest.mark.slow
def test_a_kill_right_after_a_step_save_loses_no_log_row(tmp_path, uninterrupted) -> None:
    """Killed after the step save of a batch, before Lightning logged that batch: the resumed
    CSV log still has its row (recorded in the checkpoint)."""
    run_dir = tmp_path / "run"
    after_save = "+callbacks.probe._target_=resume_probe.ProbeAfterSave"
    _kill_at_each(tmp_path, run_dir, [*KILLABLE, after_save], [[0, 0], [1, 1]])
    assert_same_as_uninterrupted(run_dir, uninterrupted)


@pytest.mark.slow
def test_resume_is_exact_with_gradient_accumulation(tmp_path) -> None:
    """Two successive kills in the same accumulation window: no state is saved inside a window
    (its summed gradients are in no checkpoint), so the window is redone whole."""
    accumulating = [*KILLABLE, "trainer.accumulate_grad_batches=2"]
    reference_dir = tmp_path / "reference"
    reference = {
        "results": train(compose_config(accumulating, reference_dir)),
        "dir": reference_dir,
    }
    run_dir = tmp_path / "run"
    _kill_at_each(tmp_path, run_dir, [*accumulating, PROBE], [[1, 1], [1, 1]])
    assert_same_as_uninterrupted(run_dir, reference)
