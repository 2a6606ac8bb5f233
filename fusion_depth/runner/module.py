"""The LightningModule: one depth network (model.net), its loss, and the depth metrics per stage."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import lightning as L
import torch
import torch.nn.functional as F
from torch import nn

from fusion_depth.data.encoding import decode_sample
from fusion_depth.data.visualize import PanelFrame
from fusion_depth.losses.depth_loss import NONFINITE_ACTIONS, DepthLoss
from fusion_depth.metrics.depth import DepthMetrics
from fusion_depth.models import DepthModel
from fusion_depth.models.depth_prior import PRIOR_KEY, check_prior_record, prior_record
from fusion_depth.models.inference import depth_at_points, predict_depth, resize_depth
from fusion_depth.optim.schedules import schedule_interval
from fusion_depth.runner.protocol import EvalProtocol, EvaluationResult, latency_summary
from fusion_depth.runner.record import RunIdentity
from fusion_depth.runner.speed import speed_up
from fusion_depth.utils.checkpoint_file import CONFIG_KEY, RUN_KEY
from fusion_depth.utils.schema import (
    NON_NEGATIVE,
    NON_NEGATIVE_INT,
    POSITIVE_INT,
    Rule,
    Schema,
    is_int,
    one_of,
)

log = logging.getLogger(__name__)

TRAINING_STATE_KEY = "fusion_depth_training_state"  # what a resumed run needs beyond Lightning's


class NonFiniteLossError(FloatingPointError):
    """The training loss became NaN or infinite (``model.on_nonfinite_loss``)."""


def downsample_depth(
    depth: torch.Tensor, size: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth (B,1,H,W) in metres → (depth, valid mask) at ``size`` by masked average pooling.

    A pixel is valid iff its depth is finite and > 0: 0 marks "no ground truth", and a NaN or
    infinite value (a custom reader's hole) is invalid too, never averaged into a valid cell.
    Invalid cells come back as 0. Averaging only the valid pixels of each cell keeps sparse
    ground truth (lidar) sparse instead of diluting it with zeros, and a dense map is simply
    area-averaged.
    """
    valid = torch.isfinite(depth) & (depth > 0)
    depth = torch.where(valid, depth, torch.zeros_like(depth))  # NaN * 0 would still be NaN
    if tuple(depth.shape[-2:]) == tuple(size):
        return depth, valid
    weight_full = valid.to(depth.dtype)
    total = F.adaptive_avg_pool2d(depth, size)
    weight = F.adaptive_avg_pool2d(weight_full, size)
    mask = weight > 0
    return torch.where(mask, total / weight.clamp_min(1e-12), torch.zeros_like(total)), mask


def _panel_frame(batch: dict, i: int, depth: torch.Tensor, label: str = "") -> PanelFrame:
    """Frame ``i`` of ``batch`` with its predicted ``depth`` (metres), on the CPU."""
    return PanelFrame(
        image=batch["image"][i].detach().float().cpu(),
        sparse=batch["sparse"][i].detach().float().cpu(),
        prediction=depth.detach().float().reshape(depth.shape[-2:]).cpu(),
        target=batch["depth"][i].detach().float().reshape(batch["depth"].shape[-2:]).cpu(),
        label=label,
    )


class DepthModule(L.LightningModule):
    """Trains ``net`` in its output space (the paper's DenseDepth: reciprocal depth; see
    :class:`~fusion_depth.models.DepthModel`); validates and tests in metres.

    Scoring follows one protocol, fixed at construction (see :class:`EvalProtocol`): either
    ``evaluation``, the ``eval`` config block (null depth limits take the network's range), or
    ``protocol``, a ready one (``evaluate``'s, whose limits come from the dataset it scores);
    not both. Predictions are resized from the network's resolution to the ground truth's,
    and the test stage may add flip test-time augmentation. Validation scores the same way
    without it. :meth:`run_test` runs the test stage and returns what it measured.
    ``channels_last``, ``compile`` (true/false/auto) and ``compile_mode`` are applied once the
    device is known (:func:`fusion_depth.runner.speed.speed_up`); the precision is the
    Trainer's. ``run_config`` (the resolved run config, plain data) is saved in every checkpoint so
    evaluation can rebuild the run without unpickling code. ``loss`` and ``optimizer`` may be
    None for a module that only evaluates.
    """

    def __init__(
        self,
        net: DepthModel,
        loss: DepthLoss | None = None,
        optimizer: Callable[..., torch.optim.Optimizer] | None = None,
        scheduler: Callable[..., Any] | None = None,
        augmentation: nn.Module | None = None,
        conditions: Sequence[str] = (),
        num_val_panels: int = 4,
        num_test_panels: int = 5,
        evaluation: Mapping[str, Any] | None = None,
        channels_last: bool = False,
        compile: bool | str = False,
        compile_mode: str = "default",
        on_nonfinite_loss: str = "stop",
        max_nonfinite_skips: int = 3,
        protocol: EvalProtocol | None = None,
    ) -> None:
        super().__init__()
        if protocol is not None and evaluation is not None:
            raise ValueError("DepthModule: give the evaluation config or a protocol, not both")
        if on_nonfinite_loss not in NONFINITE_ACTIONS:
            raise ValueError(
                f"model.on_nonfinite_loss={on_nonfinite_loss!r}: expected one of "
                f"{list(NONFINITE_ACTIONS)}"
            )
        if isinstance(max_nonfinite_skips, bool) or not (
            isinstance(max_nonfinite_skips, int) and max_nonfinite_skips >= 0
        ):
            raise ValueError(
                f"model.max_nonfinite_skips={max_nonfinite_skips!r}: expected an integer ≥ 0"
            )
        self.save_hyperparameters(
            ignore=["net", "loss", "optimizer", "scheduler", "augmentation", "protocol"]
        )
        self.net = net
        self.loss = loss
        self.optimizer_factory = optimizer
        self.scheduler_factory = scheduler
        self.augmentation = augmentation
        self.conditions = list(conditions) or None
        if protocol is None:  # built in Python without a config: the network's own range
            protocol = EvalProtocol.from_config(evaluation, net.min_depth, net.max_depth)
        self.protocol = protocol
        self.val_metrics = self.protocol.scorer(self.conditions)
        self.test_metrics = self.protocol.scorer(self.conditions)
        self._test_result: EvaluationResult | None = None  # the last test stage's, see run_test
        self._latencies: list[float] = []
        self._test_input: tuple[int, tuple[int, ...]] = (0, (0, 0))  # batch size, image size
        # Frames drawn by panel_figure: the first validation batches' each epoch (ValidationPanels)
        # and, in the test stage, the first test frame of each condition (the run's test panel).
        self.val_panels: list[PanelFrame] = []
        self.test_panels: list[PanelFrame] = []
        self.run_config: dict | None = None
        self.run_identity: RunIdentity | None = None
        self.nonfinite_skips = 0  # batches skipped for a NaN/inf loss in this run
        self.trained_batches = 0  # batches whose loss was back-propagated, in this run
        # One record per validation epoch of the run ({"epoch", "step", metric: value}),
        # carried through resumes in the checkpoint; metrics.json's "validation".
        self.val_history: list[dict[str, float | int]] = []
        self._rng_to_restore: dict[str, Any] | None = None

    def setup(self, stage: str) -> None:
        device = self.trainer.strategy.root_device if self._trainer is not None else self.device
        hp = self.hparams
        speed_up(self.net, hp.channels_last, hp.compile, device, hp.compile_mode)

    def run_test(
        self, trainer: L.Trainer, datamodule: L.LightningDataModule, **test_options: Any
    ) -> EvaluationResult:
        """Run ``trainer``'s test stage on ``datamodule`` and return what it measured (metric
        tables, per-image records and latency, by :attr:`protocol`). ``test_options`` go to
        ``trainer.test`` (``ckpt_path``, ``verbose``, ``weights_only``).

        Raises:
            RuntimeError: the test stage scored no batch (it never reached its end).
        """
        self._test_result = None
        trainer.test(self, datamodule=datamodule, **test_options)
        if self._test_result is None:
            raise RuntimeError("the test stage ended without scoring a batch: no results")
        return self._test_result

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        if self.run_config is not None:
            checkpoint[CONFIG_KEY] = self.run_config
        if self.run_identity is not None:
            checkpoint[RUN_KEY] = self.run_identity.to_json()
        prior = prior_record(self.net)  # which prior it trains with: its digest, checked on load
        if prior is not None:
            checkpoint[PRIOR_KEY] = prior
        # The augmentation draws from torch's global generators: a resumed run continues their
        # streams, so it trains on the same augmented batches as an uninterrupted one.
        rng = {"cpu": torch.get_rng_state()}
        if torch.cuda.is_available() and torch.cuda.is_initialized():
            rng["cuda"] = torch.cuda.get_rng_state_all()
        checkpoint[TRAINING_STATE_KEY] = {
            "rng": rng,
            "nonfinite_skips": self.nonfinite_skips,
            "trained_batches": self.trained_batches,
            "val_history": [dict(r) for r in self.val_history],
        }

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        # A resumed run, or the test stage's best checkpoint, goes on with the prior it had.
        path = getattr(self._trainer, "ckpt_path", None) if self._trainer is not None else None
        where = f"ckpt_path={path}" if path else "the checkpoint loaded"
        check_prior_record(self.net, checkpoint.get(PRIOR_KEY), where)
        state = checkpoint.get(TRAINING_STATE_KEY)
        if state is not None:
            self.nonfinite_skips = state["nonfinite_skips"]
            self.trained_batches = state.get("trained_batches", 0)
            self._rng_to_restore = state["rng"]
            self.val_history = [dict(r) for r in state.get("val_history", [])]

    def on_train_start(self) -> None:
        # Restored here, not on load: after the setup and sanity checks that follow loading,
        # right before the first batch, where the uninterrupted run's stream stood.
        rng, self._rng_to_restore = self._rng_to_restore, None
        if rng is not None:
            torch.set_rng_state(rng["cpu"])
            if "cuda" in rng and torch.cuda.is_available():
                torch.cuda.set_rng_state_all(rng["cuda"])

    def forward(self, image: torch.Tensor, sparse: torch.Tensor | None = None) -> torch.Tensor:
        """Depth in metres at half the input resolution."""
        return self.net.predict_depth(image, sparse)

    def _network_output(self, batch: dict) -> torch.Tensor:
        sparse = batch["sparse"] if self.net.fusion.uses_sparse else None
        # The cached prior (fusion_depth.runner.prior_cache) where the batch has one.
        given = {} if batch.get("prior") is None else {"prior": batch["prior"]}
        if getattr(self.net, "takes_points", False):  # radar points from the batch when it has them
            return self.net(batch["image"], sparse, batch.get("radar_points"), **given)
        return self.net(batch["image"], sparse, **given)

    def on_after_batch_transfer(self, batch: dict, dataloader_idx: int) -> dict:
        """Every stage's batch on the device: the loaders' encoded form (uint8 image, uint16
        depth maps) to floats (:func:`~fusion_depth.data.encoding.decode_sample`), then, when
        training, the augmentation."""
        batch = decode_sample(batch)
        if self.augmentation is not None and self.trainer is not None and self.trainer.training:
            batch = self.augmentation(batch)
        return batch

    def _loss(self, output: torch.Tensor, depth: torch.Tensor) -> dict[str, torch.Tensor]:
        # In fp32 under mixed precision too: SSIM's local variances lose too much in bf16.
        with torch.autocast(output.device.type, enabled=False):
            target, mask = downsample_depth(depth, tuple(output.shape[-2:]))
            return self.loss(output, self.net.to_output(target), mask)

    def step_losses(self, batch: dict) -> dict[str, torch.Tensor]:
        """The training loss of a batch (``"loss"``) and its terms; what ``bench`` times. A
        network with its own ``training_loss(batch, depth_loss)`` (several outputs or stages,
        e.g. ``model=radarnet``) computes it, given this module's depth loss."""
        hook = getattr(self.net, "training_loss", None)
        if hook is not None:
            return hook(batch, self._loss)
        return self._loss(self._network_output(batch), batch["depth"])

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor | None:
        losses = self.step_losses(batch)
        if not torch.isfinite(losses["loss"]):
            self._nonfinite_loss(losses, batch_idx)
            return None  # Lightning skips the backward pass (its step counter still counts)
        self.trained_batches += 1
        self.log("train/loss", losses["loss"], prog_bar=True, batch_size=len(batch["image"]))
        self.log_dict(
            {f"train/{k}": v for k, v in losses.items() if k != "loss"},
            batch_size=len(batch["image"]),
        )
        return losses["loss"]

    def _nonfinite_loss(self, losses: Mapping[str, torch.Tensor], batch_idx: int) -> None:
        """Skip the batch while ``on_nonfinite_loss=skip`` has skips left, else stop the run
        with the loss terms and the last checkpoint (written before the loss broke)."""
        terms = ", ".join(f"{k}={v.item():.4g}" for k, v in losses.items())
        where = f"epoch {self.current_epoch}, step {self.global_step}, batch {batch_idx}"
        self.nonfinite_skips += 1
        limit = self.hparams.max_nonfinite_skips
        if self.hparams.on_nonfinite_loss == "skip" and self.nonfinite_skips <= limit:
            log.warning(
                "non-finite training loss at %s (%s): batch skipped (%d of at most %d)",
                where,
                terms,
                self.nonfinite_skips,
                limit,
            )
            return
        callback = self._trainer.checkpoint_callback if self._trainer is not None else None
        kept = (callback.last_model_path or callback.best_model_path) if callback else ""
        skipped = (
            f" after {limit} skipped batches" if self.hparams.on_nonfinite_loss == "skip" else ""
        )
        raise NonFiniteLossError(
            f"non-finite training loss at {where} ({terms}){skipped}; the run stops here. "
            f"Last checkpoint: {kept or 'none yet'}. Lower the learning rate, check the inputs "
            "of that batch, or set model.on_nonfinite_loss=skip (model.max_nonfinite_skips=N)"
        )

    def _update(self, metrics: DepthMetrics, pred: torch.Tensor, batch: dict) -> None:
        depth = batch["depth"]
        if self.net.partial_output:  # 0 = no prediction: only the pixels it fills are scored
            depth = torch.where(pred > 0, depth, torch.zeros_like(depth))
        metrics.update(
            pred,
            depth,
            batch["condition"] if metrics.conditions else None,
            index=batch.get("index"),
            frame_box=batch.get("frame_box"),
        )

    def _update_at_points(self, metrics: DepthMetrics, pred: torch.Tensor, batch: dict) -> None:
        """Score ``pred`` against the batch's full-resolution ground truth, ``depth_points``
        (``eval.resolution=full``): read where each point lies
        (:func:`~fusion_depth.models.inference.depth_at_points`). For a network whose 0 means
        no prediction, a point read partly from such a pixel has none either."""
        points = batch["depth_points"]
        at_points, target = depth_at_points(pred, points)
        if self.net.partial_output:
            covered, _ = depth_at_points((pred > 0).to(pred.dtype), points)
            at_points = torch.where(covered >= 1.0, at_points, torch.zeros_like(at_points))
        scored = {k: v for k, v in batch.items() if k != "frame_box"}
        self._update(metrics, at_points, {**scored, "depth": target})

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        output = self._network_output(batch)
        depth = batch["depth"]
        pred = resize_depth(self.net.to_depth(output), depth.shape[-2:], self.protocol.upsample)
        self._update(self.val_metrics, pred, batch)
        hook = getattr(self.net, "training_loss", None)
        losses = hook(batch, self._loss) if hook is not None else self._loss(output, depth)
        self.log("val/loss", losses["loss"], batch_size=len(batch["image"]))
        self._collect_panels(batch, output)

    def _collect_panels(self, batch: dict, output: torch.Tensor) -> None:
        wanted = self.hparams.num_val_panels - len(self.val_panels)
        for i in range(min(wanted, len(batch["image"]))):
            self.val_panels.append(_panel_frame(batch, i, self.net.to_depth(output[i])))

    def _collect_test_panels(self, batch: dict, pred: torch.Tensor) -> None:
        """Up to ``num_test_panels`` frames, in test order, spread over the conditions: each
        condition gets at most its share (``num_test_panels`` / conditions, rounded up), so the
        built-in dataset's five conditions give one frame each and a one-condition dataset its
        first frames."""
        wanted = self.hparams.num_test_panels
        share = -(-wanted // max(1, len(self.conditions or ())))
        conditions = batch.get("condition")
        for i in range(len(batch["image"])):
            if len(self.test_panels) >= wanted:
                return
            label = str(conditions[i]) if conditions is not None else ""
            if sum(frame.label == label for frame in self.test_panels) < share:
                self.test_panels.append(_panel_frame(batch, i, pred[i], label))

    def on_validation_epoch_start(self) -> None:
        self.val_panels = []

    def on_validation_epoch_end(self) -> None:
        values = self.val_metrics.compute()
        self.log_dict({f"val/{k}": v for k, v in values.items()})
        self.val_metrics.reset()
        if self._trainer is not None and not self.trainer.sanity_checking:
            record = {"epoch": self.current_epoch, "step": self.global_step}
            self.val_history.append({**record, **{k: float(v) for k, v in values.items()}})

    def on_test_epoch_start(self) -> None:
        self._latencies = []
        self._scored_full = False  # whether the batches brought full-resolution points
        self._test_result = None
        self.test_panels = []

    def test_step(self, batch: dict, batch_idx: int) -> None:
        image, depth = batch["image"], batch["depth"]
        if image.device.type == "cuda":
            torch.cuda.synchronize(image.device)
        start = time.perf_counter()
        pred = predict_depth(
            self.net,
            image,
            batch["sparse"],
            points=batch.get("radar_points"),
            prior=batch.get("prior"),  # only where the frames bring one (evaluate prior=oracle)
            flip_tta=self.protocol.flip_tta,
            size=tuple(depth.shape[-2:]),
            upsample=self.protocol.upsample,
        )
        if image.device.type == "cuda":
            torch.cuda.synchronize(image.device)
        self._latencies.append((time.perf_counter() - start) / len(image))
        if self.protocol.resolution == "full" and batch.get("depth_points") is not None:
            self._update_at_points(self.test_metrics, pred, batch)
            self._scored_full = True
        else:
            self._update(self.test_metrics, pred, batch)
        self._collect_test_panels(batch, pred)
        if batch_idx == 0:
            self._test_input = (len(image), tuple(image.shape[-2:]))

    def on_test_epoch_end(self) -> None:
        flat = self.test_metrics.compute()
        self.log_dict({f"test/{k}": v for k, v in flat.items()})
        batch_size, size = self._test_input
        latency = latency_summary(self._latencies, self.device, batch_size, size)
        protocol = self.protocol
        if protocol.resolution == "full" and not getattr(self, "_scored_full", False):
            # A dataset without full-resolution points was scored on its frames: say so.
            protocol = replace(protocol, resolution="network")
        self._test_result = EvaluationResult.from_metrics(protocol, self.test_metrics, latency)
        self.test_metrics.reset()

    def build_optimizer(self) -> torch.optim.Optimizer:
        """The optimizer over this module's parameters (what ``bench`` steps, without a
        Trainer or a schedule).

        Raises:
            ValueError: the module was built for evaluation only.
        """
        if self.optimizer_factory is None:
            raise ValueError("this DepthModule was built for evaluation only (no optimizer)")
        return self.optimizer_factory(params=self.parameters())

    def configure_optimizers(self) -> dict:
        optimizer = self.build_optimizer()
        if self.scheduler_factory is None:
            return {"optimizer": optimizer}
        # A per-step schedule (fusion_depth.optim.schedules) declares interval = "step" and is given
        # the run's optimizer steps; torch's (the paper's StepLR) step per epoch.
        interval = schedule_interval(self.scheduler_factory)
        if interval == "step":
            total_steps = int(self.trainer.estimated_stepping_batches)
            scheduler = self.scheduler_factory(optimizer=optimizer, total_steps=total_steps)
        else:
            scheduler = self.scheduler_factory(optimizer=optimizer)
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": interval},
        }


def module_from_config(cfg: Any) -> DepthModule:
    """The run's :class:`DepthModule`, built from ``cfg.model``, scoring by ``cfg.model.evaluation``
    (the ``eval`` group) with null depth limits taking the dataset's (``dataset.min_depth``,
    ``dataset.max_depth``): the evaluation range comes from the config, not from the network.

    Args:
        cfg: a composed run config (``conf/train.yaml``).
    """
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    evaluation = OmegaConf.to_container(cfg.model.evaluation, resolve=True)
    for key in ("min_depth", "max_depth"):
        if evaluation.get(key) is None:
            evaluation[key] = cfg.dataset[key]
    return instantiate(cfg.model, _convert_="all", evaluation=evaluation)


# The values of the :class:`DepthModule` settings (fusion_depth.utils.schema).
CONFIG_SCHEMA: Schema = {
    "model.on_nonfinite_loss": one_of(*NONFINITE_ACTIONS),
    "model.max_nonfinite_skips": NON_NEGATIVE_INT,
    "model.num_val_panels": NON_NEGATIVE_INT,
    "model.num_test_panels": NON_NEGATIVE_INT,
}
# The ``trainer`` group's values that Lightning would refuse only deep inside training.
TRAINER_SCHEMA: Schema = {
    "trainer.max_epochs": Rule(
        lambda v: v is None or (is_int(v) and v == -1) or POSITIVE_INT.ok(v),
        "an integer ≥ 1, -1 (no epoch limit: trainer.max_steps or max_time stops the run) or "
        "null (Lightning's default: 1000 unless trainer.max_steps is set)",
    ),
    "trainer.accumulate_grad_batches": POSITIVE_INT,
    "trainer.max_steps": Rule(
        lambda v: is_int(v) and v >= -1, "an integer ≥ 1, or -1 (no step limit)"
    ),
    "trainer.gradient_clip_val": NON_NEGATIVE.or_null("no clipping"),
    "trainer.val_check_interval": Rule(
        lambda v: (
            v is None
            or POSITIVE_INT.ok(v)
            or (isinstance(v, float) and 0 < v <= 1)
            or isinstance(v, str | dict)
        ),
        "null (once per epoch), a fraction of the epoch in (0, 1], or a number of batches ≥ 1",
    ),
}
