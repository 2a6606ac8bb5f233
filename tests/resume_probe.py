"""A test-only Lightning callback, added to real training commands with
``+callbacks.probe._target_=resume_probe.Probe`` (``tests/`` on PYTHONPATH, its settings as JSON
in $FUSION_DEPTH_TEST_PROBE so they stay out of the run's folder name): it records every
trained batch and validation, and breaks the run once, on purpose, so tests can check what a
re-run does."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import lightning as L
from lightning.pytorch.callbacks import Checkpoint


class Probe(L.Callback):
    """Appends ``{"pid", "epoch", "batch", "step", "lr"}`` per trained batch and ``{"pid",
    "val_epoch"}`` per validation epoch to ``log``.

    Breaks the run once per break point, each while its marker file does not exist (it is
    created): at global step ``at_step`` it stalls forever (``action=stall``, for a test to
    SIGKILL the process) or raises (``action=fail``); at each ``[epoch, batch]`` of
    ``at_batches`` likewise (each once, in order); with ``val_epoch`` it stalls inside the
    validation of that epoch; with ``in_test`` inside the test stage. ``only_fusion``: break
    only a run of this fusion mode.
    """

    def __init__(self) -> None:
        settings = json.loads(os.environ["FUSION_DEPTH_TEST_PROBE"])
        self.log_file = Path(settings["log"])
        self.marker = Path(settings["marker"])
        self.at_step = settings.get("at_step")
        self.action = settings.get("action", "stall")
        self.val_epoch = settings.get("val_epoch")
        self.in_test = settings.get("in_test", False)
        self.only_fusion = settings.get("only_fusion")
        self.at_batches = [tuple(b) for b in settings.get("at_batches", [])]

    def _write(self, record: dict) -> None:
        self.log_file.parent.mkdir(parents=True, exist_ok=True)
        with self.log_file.open("a") as f:
            f.write(json.dumps({"pid": os.getpid(), **record}) + "\n")

    def _break_once(self, marker: Path, action: str, where: str) -> None:
        if marker.exists():
            return
        marker.touch()
        if action == "fail":
            raise RuntimeError(f"probe: failing on purpose at {where}")
        while True:  # until the test kills this process
            time.sleep(1)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module, outputs, batch, batch_idx) -> None:
        step = trainer.global_step
        lr = trainer.optimizers[0].param_groups[0]["lr"]  # the rate the next step will use
        self._write({"epoch": trainer.current_epoch, "batch": batch_idx, "step": step, "lr": lr})
        armed = self.only_fusion in (None, pl_module.net.fusion.mode)
        if armed and self.at_step is not None and step == self.at_step:
            self._break_once(self.marker, self.action, f"step {self.at_step}")
        for i, point in enumerate(self.at_batches):
            marker = self.marker.with_suffix(f".batch{i}")
            if marker.exists():
                continue
            if point == (trainer.current_epoch, batch_idx):
                self._break_once(marker, self.action, f"epoch {point[0]}, batch {point[1]}")
            break  # the break points are taken in order

    def on_validation_batch_end(self, trainer: L.Trainer, *args: object, **kwargs: object) -> None:
        if not trainer.sanity_checking and trainer.current_epoch == self.val_epoch:
            self._break_once(self.marker.with_suffix(".val"), self.action, "validation")

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module) -> None:
        if not trainer.sanity_checking:
            self._write({"val_epoch": trainer.current_epoch, "step": trainer.global_step})

    def on_test_batch_end(self, trainer: L.Trainer, *args: object, **kwargs: object) -> None:
        if self.in_test:
            self._break_once(self.marker.with_suffix(".test"), self.action, "test")


class ProbeAfterSave(Checkpoint, Probe):
    """The Probe, run after ``LastCheckpoint`` (Lightning runs checkpoint callbacks last, in
    their order): its breaks land after that batch's step save, before Lightning logs the
    batch."""
