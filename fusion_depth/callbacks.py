"""Lightning callbacks of the platform."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import numpy as np
from lightning.pytorch.loggers import WandbLogger
from PIL import Image


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
