"""Lightning callbacks of the platform."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
from lightning.pytorch.callbacks import Checkpoint
from lightning.pytorch.loggers import WandbLogger
from PIL import Image

from fusion_depth.resume import LAST_CHECKPOINT, LAST_CHECKPOINT_STATE


class ValidationPanels(L.Callback):
    """Each validation epoch, show a few predictions beside their image, sparse input and GT.

    With W&B the panels go to the dashboard; otherwise they are saved as PNGs under
    ``save_dir`` so people without W&B can look at them too.
    """

    def __init__(self, save_dir: str | None = None) -> None:
        self.save_dir = Path(save_dir) if save_dir else None

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        panels = getattr(pl_module, "val_panels", [])
        if trainer.sanity_checking or not panels or not trainer.is_global_zero:
            return
        captions = ["image | sparse input | prediction | ground truth"] * len(panels)
        wandb = [lg for lg in trainer.loggers if isinstance(lg, WandbLogger)]
        for logger in wandb:
            logger.log_image(
                "val/panels", images=list(panels), caption=captions, step=trainer.global_step
            )
        if not wandb and self.save_dir is not None:
            self.save_dir.mkdir(parents=True, exist_ok=True)
            Image.fromarray(np.concatenate(panels, axis=0)).save(
                self.save_dir / f"epoch{trainer.current_epoch:03d}.png"
            )


def validation_follows(trainer: L.Trainer, batch_idx: int) -> bool:
    """Whether Lightning validates right after training batch ``batch_idx`` of this epoch: after
    the epoch's last batch, and every ``val_check_interval`` batches (counted as Lightning
    counts them). Time-based intervals (``val_check_interval`` as a duration) cannot be told in
    advance: every batch counts as possibly followed by validation."""
    if getattr(trainer, "_val_check_time_interval", None) is not None:
        return True
    if batch_idx + 1 >= trainer.num_training_batches:
        return True
    every = trainer.val_check_batch
    if not isinstance(every, int) or every <= 0:
        return False
    loop = trainer.fit_loop.epoch_loop
    current = loop.total_batch_idx if trainer.check_val_every_n_epoch is None else batch_idx
    return (current + 1) % every == 0


def pending_log_row(trainer: L.Trainer, epoch_end: bool) -> dict[str, Any] | None:
    """The row Lightning's loggers receive right after the hook that is running now: a training
    batch's step metrics (logged after ``on_train_batch_end``) or, with ``epoch_end``, the
    epoch's (logged after ``on_train_epoch_end``). None when nothing will be logged.

    Follows ``_LoggerConnector.update_train_step_metrics``/``update_train_epoch_metrics`` and
    ``log_metrics`` (Lightning 2.6): the logged metrics, ``epoch`` and the step they log at.
    """
    connector = trainer._logger_connector
    if not trainer.loggers or trainer._results is None:
        return None
    if not epoch_end and not (connector.should_update_logs or trainer.fast_dev_run):
        return None
    metrics = {k: float(v) for k, v in connector.metrics["log"].items()}
    if not metrics:
        return None
    step = trainer.fit_loop.epoch_loop._batches_that_stepped - (1 if epoch_end else 0)
    return {**metrics, "epoch": trainer.current_epoch, "step": step}


class LastCheckpoint(Checkpoint):
    """Writes ``<dirpath>/last.ckpt``, the full training state a re-run resumes from
    (``resume=auto``): every ``every_n_epochs`` training epochs, and every
    ``every_n_train_steps`` optimizer steps if set (0 / None: never).

    As a :class:`~lightning.pytorch.callbacks.Checkpoint` it runs after the other callbacks
    and after the best-model checkpoint listed before it, so the file records that epoch's
    validation and best model too. Step saves happen only after a batch that stepped the
    optimizer (never inside a gradient-accumulation window, whose gradients a checkpoint does
    not hold) and skip the batches that validation follows (see :func:`validation_follows`), so
    every saved state lies either between two optimizer steps of an epoch's training or after
    its validation: a resumed run redoes whatever was in progress, never skips it.

    Each save flushes the loggers first and records the log row Lightning writes right after the
    save (:func:`pending_log_row`), so a resumed CSV log can add it if the kill came first.
    Writes are atomic (``AtomicCheckpointIO``).
    """

    def __init__(
        self, dirpath: str, every_n_epochs: int = 1, every_n_train_steps: int | None = None
    ) -> None:
        for name, value in (
            ("every_n_epochs", every_n_epochs),
            ("every_n_train_steps", every_n_train_steps or 0),
        ):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(
                    f"callbacks.last_checkpoint.{name}={value!r}: expected an integer ≥ 0"
                )
        self.path = Path(dirpath) / LAST_CHECKPOINT
        self.every_n_epochs = every_n_epochs
        self.every_n_train_steps = every_n_train_steps or 0
        self._saved_at_step = -1
        self._pending_log_row: dict[str, Any] | None = None

    @property
    def state_key(self) -> str:
        return LAST_CHECKPOINT_STATE

    def state_dict(self) -> dict[str, Any]:
        return {"saved_at_step": self._saved_at_step, "pending_log_row": self._pending_log_row}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._saved_at_step = int(state_dict.get("saved_at_step", -1))

    def _save(self, trainer: L.Trainer, epoch_end: bool) -> None:
        for logger in trainer.loggers:  # what was logged so far is on disk with the state
            logger.save()
        self._saved_at_step = trainer.global_step
        self._pending_log_row = pending_log_row(trainer, epoch_end)
        trainer.save_checkpoint(self.path, weights_only=False)  # the full state, to resume from

    def on_train_batch_end(
        self,
        trainer: L.Trainer,
        pl_module: L.LightningModule,
        outputs: Any,
        batch: Any,
        batch_idx: int,
    ) -> None:
        n, step = self.every_n_train_steps, trainer.global_step
        if not n or step <= 0 or step % n or step == self._saved_at_step:
            return
        if (batch_idx + 1) % trainer.accumulate_grad_batches:
            return  # inside an accumulation window: its summed gradients are in no checkpoint
        if validation_follows(trainer, batch_idx):
            # A state saved here would resume past the validation that follows: a run killed
            # during it would never validate that epoch. The epoch-end save (after validation)
            # covers this batch, and a kill before it resumes from the previous step save.
            return
        self._save(trainer, epoch_end=False)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # Always written when due, also right after a step save: this one holds the epoch's
        # validation and best model.
        n = self.every_n_epochs
        if n and (trainer.current_epoch + 1) % n == 0:
            self._save(trainer, epoch_end=True)
