"""The LightningModule: one DepthNet, the paper's loss, and the depth metrics per stage."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from fusion_depth.losses import DepthLoss
from fusion_depth.metrics import DepthMetrics
from fusion_depth.models import DepthNet
from fusion_depth.visualize import depth_panel


def downsample_depth(
    depth: torch.Tensor, size: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth (B,1,H,W), 0 = invalid → (depth, valid mask) at ``size`` by masked average pooling.

    Averaging only the valid pixels of each cell keeps sparse ground truth (lidar) sparse instead
    of diluting it with zeros, and a dense map is simply area-averaged.
    """
    if tuple(depth.shape[-2:]) == tuple(size):
        return depth, depth > 0
    valid = (depth > 0).to(depth.dtype)
    total = F.adaptive_avg_pool2d(depth * valid, size)
    weight = F.adaptive_avg_pool2d(valid, size)
    mask = weight > 0
    return torch.where(mask, total / weight.clamp_min(1e-12), torch.zeros_like(total)), mask


class DepthModule(L.LightningModule):
    """Trains ``net`` on reciprocal depth; validates and tests in metres.

    Predictions are upsampled bilinearly from the network's half resolution to the ground
    truth's before scoring. ``run_config`` (the resolved run config, plain data) is saved in
    every checkpoint so evaluation can rebuild the run without unpickling code.
    """

    def __init__(
        self,
        net: DepthNet,
        loss: DepthLoss,
        optimizer: Callable[..., torch.optim.Optimizer],
        scheduler: Callable[..., Any] | None = None,
        augmentation: nn.Module | None = None,
        conditions: Sequence[str] = (),
        num_val_panels: int = 4,
    ) -> None:
        super().__init__()
        self.save_hyperparameters(ignore=["net", "loss", "optimizer", "scheduler", "augmentation"])
        self.net = net
        self.loss = loss
        self.optimizer_factory = optimizer
        self.scheduler_factory = scheduler
        self.augmentation = augmentation
        metric_args = {
            "min_depth": net.min_depth,
            "max_depth": net.max_depth,
            "conditions": list(conditions) or None,
        }
        self.val_metrics = DepthMetrics(**metric_args)
        self.test_metrics = DepthMetrics(**metric_args)
        self.test_results: dict[str, float] = {}
        self.val_panels: list[np.ndarray] = []
        self.run_config: dict | None = None

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        if self.run_config is not None:
            checkpoint["fusion_depth_config"] = self.run_config

    def forward(self, image: torch.Tensor, sparse: torch.Tensor | None = None) -> torch.Tensor:
        """Depth in metres at half the input resolution."""
        return self.net.predict_depth(image, sparse)

    def _reciprocal(self, batch: dict) -> torch.Tensor:
        sparse = batch["sparse"] if self.net.fusion.uses_sparse else None
        return self.net(batch["image"], sparse)

    def on_after_batch_transfer(self, batch: dict, dataloader_idx: int) -> dict:
        if self.augmentation is not None and self.trainer is not None and self.trainer.training:
            batch = self.augmentation(batch)
        return batch

    def _loss(self, reciprocal: torch.Tensor, depth: torch.Tensor) -> dict[str, torch.Tensor]:
        target, mask = downsample_depth(depth, tuple(reciprocal.shape[-2:]))
        return self.loss(reciprocal, self.net.to_reciprocal(target), mask)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        losses = self._loss(self._reciprocal(batch), batch["depth"])
        self.log("train/loss", losses["loss"], prog_bar=True, batch_size=len(batch["image"]))
        self.log_dict(
            {f"train/{k}": v for k, v in losses.items() if k != "loss"},
            batch_size=len(batch["image"]),
        )
        return losses["loss"]

    def _evaluate(self, batch: dict, metrics: DepthMetrics) -> torch.Tensor:
        reciprocal = self._reciprocal(batch)
        depth = batch["depth"]
        pred = F.interpolate(
            self.net.to_depth(reciprocal),
            size=depth.shape[-2:],
            mode="bilinear",
            align_corners=False,
        )
        metrics.update(pred, depth, batch["condition"] if metrics.conditions else None)
        return reciprocal

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        reciprocal = self._evaluate(batch, self.val_metrics)
        self.log(
            "val/loss",
            self._loss(reciprocal, batch["depth"])["loss"],
            batch_size=len(batch["image"]),
        )
        self._collect_panels(batch, reciprocal)

    def _collect_panels(self, batch: dict, reciprocal: torch.Tensor) -> None:
        wanted = self.hparams.num_val_panels - len(self.val_panels)
        for i in range(min(wanted, len(batch["image"]))):
            self.val_panels.append(
                depth_panel(
                    batch["image"][i],
                    batch["sparse"][i],
                    self.net.to_depth(reciprocal[i]),
                    batch["depth"][i],
                    self.net.min_depth,
                    self.net.max_depth,
                )
            )

    def on_validation_epoch_start(self) -> None:
        self.val_panels = []

    def on_validation_epoch_end(self) -> None:
        self.log_dict({f"val/{k}": v for k, v in self.val_metrics.compute().items()})
        self.val_metrics.reset()

    def test_step(self, batch: dict, batch_idx: int) -> None:
        self._evaluate(batch, self.test_metrics)

    def on_test_epoch_end(self) -> None:
        results = self.test_metrics.compute()
        self.log_dict({f"test/{k}": v for k, v in results.items()})
        self.test_results = {k: float(v) for k, v in results.items()}
        self.test_results["num_images"] = int(self.test_metrics.count)
        self.test_metrics.reset()

    def configure_optimizers(self) -> dict:
        optimizer = self.optimizer_factory(params=self.parameters())
        if self.scheduler_factory is None:
            return {"optimizer": optimizer}
        scheduler = self.scheduler_factory(optimizer=optimizer)
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"},
        }
