"""Runs with a probe: training commands that load ``tests/resume_probe.py``'s callback, which
records each trained batch and breaks the run at a chosen moment (``test_resume``,
``test_kills``)."""

from __future__ import annotations

import json
import os
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
# Three epochs of three batches; last.ckpt after every optimizer step and epoch.
RESUMABLE = [
    "experiment=smoke",
    "logger=none",
    "trainer.max_epochs=3",
    "callbacks.last_checkpoint.every_n_epochs=1",
    "callbacks.last_checkpoint.every_n_train_steps=1",
]


PROBE = "+callbacks.probe._target_=resume_probe.Probe"  # tests/resume_probe.py


def probe_env(tmp_path: Path, at_step: int, action: str, **extra: str) -> dict[str, str]:
    """The environment of a training command with PROBE: tests/ importable, and the probe's
    settings (it breaks the run at ``at_step`` once: ``stall`` or ``fail``)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(TESTS), env.get("PYTHONPATH")]))
    settings = {
        "log": str(tmp_path / "probe.jsonl"),
        "marker": str(tmp_path / "probe.marker"),
        "at_step": at_step,
        "action": action,
        **extra,
    }
    env["FUSION_DEPTH_TEST_PROBE"] = json.dumps(settings)
    return env


def probe_records(tmp_path: Path) -> list[dict]:
    """The trained batches the probe recorded (its validation records left out)."""
    lines = (tmp_path / "probe.jsonl").read_text().splitlines()
    return [r for r in map(json.loads, lines) if "batch" in r]
