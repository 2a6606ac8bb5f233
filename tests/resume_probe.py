"""A test-only Lightning callback, added to real training commands with
``+callbacks.probe._target_=resume_probe.Probe`` (``tests/`` on PYTHONPATH, its settings as JSON
in $FUSION_DEPTH_TEST_PROBE so they stay out of the run's folder name): it records every
trained batch and breaks the run once, on purpose, so tests can check what a re-run does."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import lightning as L


class Probe(L.Callback):
    """Appends ``{"pid", "epoch", "batch", "step"}`` per trained batch to ``log``. At global
    step ``at_step``, once (while ``marker`` does not exist; it is created), either stalls
    forever (``action=stall``, for a test to SIGKILL the process) or raises (``action=fail``).
    ``only_fusion``: break only a run of this fusion mode."""

    def __init__(self) -> None:
        settings = json.loads(os.environ["FUSION_DEPTH_TEST_PROBE"])
        self.log_file = Path(settings["log"])
        self.marker = Path(settings["marker"])
        self.at_step = settings["at_step"]
        self.action = settings.get("action", "stall")
        self.only_fusion = settings.get("only_fusion")

    def on_train_batch_end(self, trainer: L.Trainer, pl_module, outputs, batch, batch_idx) -> None:
        record = {
            "pid": os.getpid(),
            "epoch": trainer.current_epoch,
            "batch": batch_idx,
            "step": trainer.global_step,
        }
        self.log_file.parent.mkdir(parents=True, exist_ok=True)
        with self.log_file.open("a") as f:
            f.write(json.dumps(record) + "\n")
        armed = self.only_fusion in (None, pl_module.net.fusion.mode)
        if armed and trainer.global_step == self.at_step and not self.marker.exists():
            self.marker.touch()
            if self.action == "fail":
                raise RuntimeError(f"probe: failing on purpose at step {self.at_step}")
            while True:  # until the test kills this process
                time.sleep(1)
