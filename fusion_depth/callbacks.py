"""Lightning callbacks of the platform."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import numpy as np
from lightning.pytorch.callbacks import Checkpoint
from lightning.pytorch.loggers import WandbLogger
from PIL import Image

from fusion_depth.resume import LAST_CHECKPOINT


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


class LastCheckpoint(Checkpoint):
    """Writes ``<dirpath>/last.ckpt``, the full training state a re-run resumes from
    (``resume=auto``): every ``every_n_epochs`` training epochs, and every
    ``every_n_train_steps`` optimizer steps if set (0 / None: never).

    As a :class:`~lightning.pytorch.callbacks.Checkpoint` it runs after the other callbacks
    and after the best-model checkpoint listed before it, so the file records that epoch's
    validation and best model too. Writes are atomic (``AtomicCheckpointIO``).
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

    def _save(self, trainer: L.Trainer) -> None:
        trainer.save_checkpoint(self.path, weights_only=False)  # the full state, to resume from
        self._saved_at_step = trainer.global_step

    def on_train_batch_end(self, trainer: L.Trainer, *args: object) -> None:
        # global_step counts optimizer steps: with gradient accumulation it stays put for a
        # few batches, and only the batch that stepped is saved.
        n, step = self.every_n_train_steps, trainer.global_step
        if n and step > 0 and step % n == 0 and step != self._saved_at_step:
            self._save(trainer)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # Always written when due, also right after a step save: this one holds the epoch's
        # validation and best model.
        n = self.every_n_epochs
        if n and (trainer.current_epoch + 1) % n == 0:
            self._save(trainer)
