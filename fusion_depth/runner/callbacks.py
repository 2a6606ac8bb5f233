"""Lightning callbacks of the platform."""

from __future__ import annotations

import logging
import math
import os
import time
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Checkpoint, ModelCheckpoint, ModelSummary
from lightning.pytorch.loggers import WandbLogger
from lightning.pytorch.utilities.exceptions import MisconfigurationException
from torch import Tensor

from fusion_depth.data.visualize import PANEL_CAPTION, panel_figure, write_panel_figure
from fusion_depth.runner.resume import LAST_CHECKPOINT, LAST_CHECKPOINT_STATE
from fusion_depth.utils.progress import format_duration
from fusion_depth.utils.schema import POSITIVE, Rule, Schema

log = logging.getLogger(__name__)


class ValidationPanels(L.Callback):
    """Each validation epoch, draw the module's ``val_panels`` frames with
    :func:`~fusion_depth.data.visualize.panel_figure`: image, sparse input, prediction, ground truth
    and error, with labelled colour bars in metres.

    With W&B the figure goes to the dashboard; otherwise it is saved as
    ``save_dir/epoch<NNN>.png`` so people without W&B can look at it too.
    """

    def __init__(self, save_dir: str | None = None) -> None:
        self.save_dir = Path(save_dir) if save_dir else None

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        frames = getattr(pl_module, "val_panels", [])
        if trainer.sanity_checking or not frames or not trainer.is_global_zero:
            return
        net = pl_module.net
        wandb = [lg for lg in trainer.loggers if isinstance(lg, WandbLogger)]
        for logger in wandb:
            figure = panel_figure(frames, net.min_depth, net.max_depth)
            logger.log_image(
                "val/panels", images=[figure], caption=[PANEL_CAPTION], step=trainer.global_step
            )
        if not wandb and self.save_dir is not None:
            path = self.save_dir / f"epoch{trainer.current_epoch:03d}.png"
            write_panel_figure(path, frames, net.min_depth, net.max_depth)


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


class ProgressLog(L.Callback):
    """Progress as log lines where no progress bar is drawn (stdout not a terminal: SLURM
    ``.out`` files, ``nohup``, CI), on the lead process only:

    * after each epoch's validation: ``epoch 3/20: train loss 0.1234, val RMSE 8.123 m,
      δ1 0.456, 41 s, ETA 11 min`` (the ETA from the mean epoch time so far);
    * inside an epoch or a test stage, at most every ``every_s`` seconds:
      ``epoch 3/20: batch 40/80, loss 0.1234, 1.9 batches/s`` or ``test: batch 12/63``.

    With a progress bar (``trainer.enable_progress_bar=true``, or a terminal) it stays silent.

    Args:
        every_s: the shortest time between two lines inside an epoch or a test stage.
        clock: seconds, monotonic (replaceable in tests).
    """

    def __init__(self, every_s: float = 120.0, clock: Callable[[], float] = time.monotonic):
        if not every_s > 0:
            raise ValueError(f"callbacks.progress_log.every_s={every_s}: expected seconds > 0")
        self.every_s = float(every_s)
        self.clock = clock
        self._epoch_times: list[float] = []
        self._epoch_start = self._last_line = 0.0
        self._loss_sum, self._loss_count = 0.0, 0

    @staticmethod
    def _active(trainer: L.Trainer) -> bool:
        return trainer.progress_bar_callback is None and trainer.is_global_zero

    def _epochs(self, trainer: L.Trainer) -> str:
        total = trainer.max_epochs
        return (
            f"{trainer.current_epoch + 1}/{total}"
            if total and total > 0
            else str(trainer.current_epoch + 1)
        )

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._epoch_start = self._last_line = self.clock()
        self._loss_sum, self._loss_count = 0.0, 0

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any, **kwargs: Any
    ) -> None:
        loss = trainer.callback_metrics.get("train/loss")
        if loss is not None and math.isfinite(float(loss)):
            self._loss_sum += float(loss)
            self._loss_count += 1
        now = self.clock()
        if not self._active(trainer) or now - self._last_line < self.every_s:
            return
        self._last_line = now
        done = trainer.fit_loop.epoch_loop.batch_progress.current.processed
        total = trainer.num_training_batches
        rate = done / max(now - self._epoch_start, 1e-9)
        parts = [f"epoch {self._epochs(trainer)}: batch {done}/{total}"]
        if self._loss_count:
            parts.append(f"loss {self._loss_sum / self._loss_count:.4f}")
        parts.append(f"{rate:.2g} batches/s")
        log.info("%s", ", ".join(parts))

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        took = self.clock() - self._epoch_start
        self._epoch_times.append(took)
        if not self._active(trainer):
            return
        metrics = trainer.callback_metrics
        parts = [f"epoch {self._epochs(trainer)}"]
        if self._loss_count:
            parts.append(f"train loss {self._loss_sum / self._loss_count:.4f}")
        if "val/rmse" in metrics:
            parts.append(f"val RMSE {float(metrics['val/rmse']):.3f} m")
        if "val/delta1" in metrics:
            parts.append(f"δ1 {float(metrics['val/delta1']):.3f}")
        parts.append(format_duration(took))
        left = (trainer.max_epochs or 0) - trainer.current_epoch - 1
        if left > 0:
            mean = sum(self._epoch_times) / len(self._epoch_times)
            parts.append(f"ETA {format_duration(left * mean)}")
        log.info("%s: %s", parts[0], ", ".join(parts[1:]))

    def on_test_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._epoch_start = self._last_line = self.clock()

    def on_test_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any, **kwargs: Any
    ) -> None:
        now = self.clock()
        if not self._active(trainer) or now - self._last_line < self.every_s:
            return
        self._last_line = now
        done = trainer.test_loop.batch_progress.current.processed
        total = sum(trainer.num_test_batches)
        left = (total - done) * (now - self._epoch_start) / max(done, 1)
        log.info("test: batch %d/%d, ETA %s", done, total, format_duration(left))


# The callbacks' values (fusion_depth.utils.schema).
CONFIG_SCHEMA: Schema = {"callbacks.progress_log.every_s": Rule(POSITIVE.ok, "seconds > 0")}


class MajorityCheckpoint(ModelCheckpoint):
    """Keeps a validation's checkpoint when at least ``at_least`` of ``metrics`` are no worse
    than at the one kept before, each rounded to its resolution (RadarNet's rule: its
    ``fusionnet_main.py``, ``validate``, keeps a step when 3 of MAE, RMSE, iMAE and iRMSE,
    rounded to 0.01 mm and 0.01 /km, are ≤ the best; the best then takes all four of the step's
    values). The first validation is always kept. It is Lightning's ``ModelCheckpoint`` with
    ``save_top_k=1`` otherwise: ``monitor`` (``val/rmse``) is what it names the file and records
    as the kept checkpoint's score.

    Args:
        metrics: logged validation metric (``val/<key>``) → the resolution its value is rounded
            to before comparing, in its logged unit (metres, 1/km); lower is better for each.
            None: by ``monitor`` alone, as ``ModelCheckpoint`` (to switch the rule off from the
            command line: ``callbacks.model_checkpoint.metrics=null``).
        at_least: how many of them must be no worse.
        **kwargs: :class:`~lightning.pytorch.callbacks.ModelCheckpoint`'s arguments.

    Raises:
        ValueError: no metrics, a resolution that is not > 0, or ``at_least`` outside
            1..len(metrics).
    """

    def __init__(self, metrics: Mapping[str, float] | None, at_least: int, **kwargs: Any) -> None:
        super().__init__(**{**kwargs, "save_top_k": 1})
        self.resolutions = {str(k): float(v) for k, v in dict(metrics or {}).items()}
        if metrics is not None and (not self.resolutions or min(self.resolutions.values()) <= 0):
            raise ValueError(f"metrics={dict(metrics)}: expected metric → resolution > 0")
        if metrics is not None and not 1 <= at_least <= len(self.resolutions):
            raise ValueError(f"at_least={at_least}: expected 1..{len(self.resolutions)}")
        self.at_least = at_least
        self.kept_metrics: dict[str, float] = {}

    def _rounded(self, name: str, value: float) -> int:
        return round(value / self.resolutions[name])

    def keeps(self, current: Mapping[str, float]) -> bool:
        """Whether the rule keeps a validation whose metrics are ``current`` (plain numbers)."""
        if not self.kept_metrics:
            return True
        no_worse = sum(
            self._rounded(k, current[k]) <= self._rounded(k, self.kept_metrics[k])
            for k in self.resolutions
        )
        return no_worse >= self.at_least

    def check_monitor_top_k(self, trainer: L.Trainer, current: Tensor | None = None) -> bool:
        if not self.resolutions:
            return super().check_monitor_top_k(trainer, current)
        if current is None:
            return False
        logged = trainer.callback_metrics
        missing = [k for k in self.resolutions if k not in logged]
        if missing:
            raise MisconfigurationException(
                f"MajorityCheckpoint: the validation logged no {', '.join(missing)} (its "
                f"metrics: {sorted(logged)})"
            )
        values = {k: float(logged[k]) for k in self.resolutions}
        finite = all(math.isfinite(v) for v in values.values())
        keep = trainer.strategy.reduce_boolean_decision(finite and self.keeps(values))
        if keep:
            self.kept_metrics = values
        return keep

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "kept_metrics": dict(self.kept_metrics)}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        super().load_state_dict(state_dict)
        self.kept_metrics = dict(state_dict.get("kept_metrics") or {})
        moved_from, best = state_dict.get("dirpath"), state_dict.get("best_model_path")
        if self.dirpath and moved_from and moved_from != self.dirpath and best:
            # A moved run folder (Lightning restores only the path then): the kept file is in
            # this folder now, with its score, so the next kept one replaces it.
            here = os.path.join(self.dirpath, os.path.basename(best))
            score = state_dict.get("best_model_score")
            self.best_model_path, self.best_model_score = here, score
            if score is not None:
                self.best_k_models = {here: score}
                self.kth_best_model_path, self.kth_value = here, score


class ParameterSummary(ModelSummary):
    """Lightning's model summary without what it cannot know here: its FLOPs column and total
    (0 for every layer: the module has no example input), and its warning that bf16-mixed "is
    not supported by the model summary" (the weights stay fp32 under mixed precision, so the
    size it gives is right)."""

    def _summary(self, trainer: L.Trainer, pl_module: L.LightningModule) -> Any:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r".*not supported by the model summary")
            return super()._summary(trainer, pl_module)

    @staticmethod
    def summarize(
        summary_data: list[tuple[str, list[str]]],
        total_parameters: int,
        trainable_parameters: int,
        model_size: float,
        total_training_modes: dict[str, int],
        total_flops: int,
        **summarize_kwargs: Any,
    ) -> None:
        try:  # Lightning's own table maker (private): without it, Lightning's summary as is
            from lightning.pytorch.utilities.model_summary.model_summary import (
                _format_summary_table,
            )
        except ImportError:
            ModelSummary.summarize(
                summary_data,
                total_parameters,
                trainable_parameters,
                model_size,
                total_training_modes,
                total_flops,
                **summarize_kwargs,
            )
            return
        columns = [column for column in summary_data if column[0] != "FLOPs"]
        table = _format_summary_table(
            total_parameters,
            trainable_parameters,
            model_size,
            total_training_modes,
            total_flops,
            *columns,
        )
        lines = [line for line in table.splitlines() if not line.endswith("Total Flops")]
        log.info("\n" + "\n".join(lines))
