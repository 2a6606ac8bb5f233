"""A training run: fit one configuration in its run folder (or continue it there), test the
best checkpoint, write ``metrics.json`` and ``per_image.csv``. ``python -m fusion_depth.train``
(:mod:`fusion_depth.train.cli`) runs :func:`train_record` once per job."""

from __future__ import annotations

import contextlib
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint
from lightning.pytorch.plugins.environments import LightningEnvironment
from omegaconf import DictConfig, OmegaConf

from fusion_depth.config import check_output_dir, checkpoint_bytes, validate_config
from fusion_depth.config.arguments import argument_error, config_message
from fusion_depth.data.visualize import PANEL_CAPTION, write_panel_figure, write_panel_frames
from fusion_depth.errors import CommandError, UserError
from fusion_depth.models.alignment import FallbackCount
from fusion_depth.runner.callbacks import ParameterSummary
from fusion_depth.runner.checkpoint_io import AtomicCheckpointIO
from fusion_depth.runner.datamodule import DepthDataModule, check_batches, check_scorable
from fusion_depth.runner.distributed import launch_local_ranks, local_world_size
from fusion_depth.runner.loggers import closing
from fusion_depth.runner.module import DepthModule, module_from_config
from fusion_depth.runner.prior_cache import attach_prior_cache
from fusion_depth.runner.protocol import EvaluationResult
from fusion_depth.runner.record import (
    METRICS_FILE,
    RunIdentity,
    RunRecord,
    publish_results,
    read_run_record,
    run_identity,
)
from fusion_depth.runner.redaction import redact_overrides, redact_secrets
from fusion_depth.runner.resume import (
    RunLock,
    RunStart,
    identity_overrides,
    is_lead_process,
    plan_start,
    recorded_precision,
)
from fusion_depth.runner.run_folder import RESOLVED_CONFIG_FILE, TEST_PANEL_FRAMES_FILE
from fusion_depth.runner.speed import accelerator_device, resolve_precision
from fusion_depth.utils.atomic import write_text_atomic
from fusion_depth.utils.checkpoint_file import plain_config

log = logging.getLogger(__name__)

TEST_PANELS_FILE = "test_panels.png"  # a few test frames drawn by the best checkpoint


def run_overrides() -> list[str]:
    """The overrides that made this run, less those that do not change what it computes
    (``hydra.job.config.override_dirname.exclude_keys``: ``resume``, the logger, ...)."""
    if not HydraConfig.initialized():
        return []
    task = HydraConfig.get().overrides.task
    return redact_overrides(identity_overrides(task, not_identity_keys()))


def not_identity_keys() -> list[str]:
    """Override keys that do not change what a run computes (the Hydra config's
    ``hydra.job.config.override_dirname.exclude_keys``: ``resume``, the logger, ...)."""
    if not HydraConfig.initialized():
        return []
    return list(HydraConfig.get().job.config.override_dirname.exclude_keys)


def train(cfg: DictConfig) -> dict | None:
    """Fit, test the best checkpoint, write ``metrics.json``; returns its contents
    (:meth:`RunRecord.to_json <fusion_depth.runner.record.RunRecord.to_json>`; None on the ranks
    other than 0 of a data-parallel run that a cluster launcher started).

    A run whose ``metrics.json`` is complete is not trained again, and one with a
    ``last.ckpt`` continues from it (see :mod:`fusion_depth.runner.resume`)."""
    record = train_record(cfg)
    return record.to_json() if record is not None else None


def train_record(cfg: DictConfig) -> RunRecord | None:
    """:func:`train`, returning the run's record (None on the ranks other than 0 of a
    data-parallel run that a cluster launcher started)."""
    run_config = validate_config(cfg)
    device = accelerator_device(cfg.trainer.accelerator)
    precision = resolve_precision(cfg.trainer.precision, device)
    output_dir = Path(cfg.paths.output_dir)
    if cfg.trainer.precision == "auto" and cfg.resume != "never":
        # A run goes on in the precision it began in: one started where the CPU has no bf16
        # resumes in fp32 on one that has it (and the other way round).
        last = cfg.callbacks.get("last_checkpoint")
        recorded = recorded_precision(output_dir, Path(last.dirpath) if last else None)
        if recorded in ("32-true", "bf16-mixed"):
            precision = resolve_precision(recorded, device)
    run_config["trainer"]["precision"] = precision  # what ran, not "auto"
    # One process per run folder (the lead one of a cluster-launched data-parallel run).
    with RunLock(output_dir) if is_lead_process() else contextlib.nullcontext():
        return _train_locked(cfg, run_config, output_dir)


def _train_locked(cfg: DictConfig, run_config: dict, output_dir: Path) -> RunRecord | None:
    last_checkpoint = cfg.callbacks.get("last_checkpoint")
    run_config = redact_secrets(run_config)  # what gets written anywhere from here on
    start = plan_start(
        output_dir,
        Path(last_checkpoint.dirpath) if last_checkpoint else None,
        cfg.resume,
        cfg.sweep.skip_done,
        run_overrides(),
        not_identity_keys(),
        config=run_config,
    )
    if start.finished is not None:
        finished = RunRecord.from_json(start.finished, output_dir / METRICS_FILE)
        print(
            f"Already finished: {finished.path} (test rmse "
            f"{finished.test['rmse']:.4f}); sweep.skip_done=false or resume=never to "
            "train it again",
            flush=True,
        )
        return finished
    if start.checkpoint is not None:
        log.info("resuming from %s", start.checkpoint)
    write_text_atomic(output_dir / RESOLVED_CONFIG_FILE, OmegaConf.to_yaml(run_config))
    identity = run_identity(cfg, run_overrides(), wandb_id=start.wandb_id)
    job = RankJob(cfg, run_config, identity, start)
    world_size = local_world_size(cfg.trainer)
    if world_size > 1:
        launch_local_ranks(_fit_and_test_rank, job, world_size)
        return read_run_record(output_dir / METRICS_FILE)
    return fit_and_test(job)


def checkpoint_room(callbacks: DictConfig, model: torch.nn.Module) -> int:
    """Bytes the run's checkpoints need on disk, checked before training: last.ckpt (weights and
    Adam state) and the best checkpoint (weights only if so configured), each briefly twice
    while its new version is written beside the old one."""
    full = checkpoint_bytes(model)
    room = 0
    last = callbacks.get("last_checkpoint")
    if last and (last.get("every_n_epochs") or last.get("every_n_train_steps")):
        room += 2 * full
    best = callbacks.get("model_checkpoint")
    if best:
        room += 2 * (checkpoint_bytes(model, 0) if best.get("save_weights_only") else full)
    return room


class NoTrainingError(RuntimeError, UserError):
    """Fit ended without training a single batch: there is nothing to test or report."""


@dataclass
class RankJob:
    """What every process of a run needs: the config, the resolved config, the run's identity
    and where it starts (decided once, before any process starts)."""

    cfg: DictConfig
    run_config: dict
    identity: RunIdentity
    start: RunStart


def _logger(cfg: DictConfig, start: RunStart) -> Any:
    """The run's logger (False for logger=none), continuing an interrupted run's W&B run and
    CSV log."""
    if not cfg.logger.get("_target_"):
        return False
    resuming = {}
    if "id" in cfg.logger and cfg.logger.id is None:
        resuming["id"] = start.wandb_id
    if "resume_step" in cfg.logger and cfg.logger.resume_step is None:
        resuming["resume_step"] = start.global_step
        resuming["resume_row"] = start.pending_log_row
    return instantiate(cfg.logger, **resuming)


def _trainer_settings(cfg: DictConfig, logger: Any, precision: str) -> dict[str, Any]:
    """What the code sets on the Trainer besides its config group."""
    progress = cfg.trainer.enable_progress_bar
    return {
        "logger": logger,
        "precision": precision,
        "enable_progress_bar": sys.stdout.isatty() if progress is None else progress,
        "plugins": [AtomicCheckpointIO()],
    }


def _best_checkpoint(trainer: L.Trainer) -> tuple[str, float | None]:
    """The best checkpoint's path ('' if none was kept) and its validation RMSE."""
    best_callback = next(
        (c for c in trainer.checkpoint_callbacks if isinstance(c, ModelCheckpoint)), None
    )
    if best_callback is None:
        return "", None
    score = best_callback.best_model_score
    best = best_callback.best_model_path
    # Resumed in a run folder that was moved, Lightning restores the best path as it was then:
    # the file is now in this run's checkpoint folder.
    if best and not Path(best).is_file():
        moved = Path(best_callback.dirpath) / Path(best).name  # conf/callbacks sets dirpath
        best = str(moved) if moved.is_file() else best
    return best, float(score) if best and score is not None else None


def _single_process_trainer(cfg: DictConfig, settings: dict[str, Any]) -> L.Trainer:
    """A Trainer for the test stage on one process after a data-parallel fit: it sees every
    test image exactly once (a distributed sampler pads the split to a multiple of the world
    size)."""
    torch.distributed.destroy_process_group()
    return instantiate(
        cfg.trainer,
        devices=1,
        num_nodes=1,
        strategy="auto",
        **{**settings, "plugins": [AtomicCheckpointIO(), LightningEnvironment()]},
    )


def _publish(
    output_dir: Path,
    model: DepthModule,
    trainer: L.Trainer,
    result: EvaluationResult,
    record: RunRecord,
    best: str,
) -> None:
    """The test panels, then ``metrics.json`` (whose presence means the run is complete) and the
    tables."""
    title = (
        f"Test metrics ({result.overall['num_images']} images, best checkpoint "
        f"{best or 'last weights'})"
    )
    panel = None
    if model.test_panels:
        net = model.net
        panel = write_panel_figure(
            output_dir / TEST_PANELS_FILE, model.test_panels, net.min_depth, net.max_depth
        )
        write_panel_frames(
            output_dir / TEST_PANEL_FRAMES_FILE, model.test_panels, net.min_depth, net.max_depth
        )
    publish_results(output_dir, record, result, trainer.loggers, title)
    if panel is not None:
        print(f"Test frames ({PANEL_CAPTION}): {panel}", flush=True)


def _fit_and_test_rank(job: RankJob) -> RunRecord | None:
    """:func:`fit_and_test` in a rank process of its own, where no command names an argument
    error's key: it is named here (the parent shows the rank's error)."""
    try:
        return fit_and_test(job)
    except Exception as err:
        argument = argument_error(err)
        if argument is None:
            raise
        raise CommandError(config_message(argument, cfg=job.cfg)) from err


def fit_and_test(job: RankJob) -> RunRecord | None:
    """Fit, test the best checkpoint on rank 0 alone, write ``metrics.json``; its record
    (None on the other ranks of a data-parallel run)."""
    cfg, run_config, start = job.cfg, job.run_config, job.start
    output_dir = Path(cfg.paths.output_dir)
    L.seed_everything(cfg.seed, workers=True)
    datamodule = DepthDataModule(reader=instantiate(cfg.dataset.reader), seed=cfg.seed, **cfg.data)
    model = module_from_config(cfg)
    datamodule.measured_depth = bool(getattr(model.net, "wants_measured_depth", False))
    check_output_dir(output_dir, checkpoint_room(cfg.callbacks, model))
    prior = OmegaConf.to_container(cfg.prior, resolve=True) if cfg.get("prior") else None
    attach_prior_cache(model.net, prior, datamodule, accelerator_device(cfg.trainer.accelerator))
    model.run_config = plain_config(run_config)  # checkpoints hold data, never code to call
    model.run_identity = job.identity
    logger = _logger(cfg, start)
    with closing(logger):
        callbacks = [instantiate(c) for c in cfg.callbacks.values() if c]
        if cfg.trainer.get("enable_model_summary") is not False:
            callbacks.append(ParameterSummary())
        if logger:
            logger.log_hyperparams(run_config)
        else:  # Lightning refuses a learning-rate monitor with nothing to log to
            callbacks = [c for c in callbacks if not isinstance(c, LearningRateMonitor)]
        settings = _trainer_settings(cfg, logger, run_config["trainer"]["precision"])
        # ParameterSummary stands in for Lightning's summary (which would also print that it
        # skips its own): the trainer adds none.
        settings["enable_model_summary"] = False
        trainer = instantiate(cfg.trainer, callbacks=callbacks, **settings)
        # Zero work is a failure: refused here, not reported as a run that trained nothing.
        check_batches(datamodule, cfg.trainer, cfg.dataset.name, trainer.world_size)
        check_scorable(datamodule, model.protocol, cfg.trainer, cfg.dataset.name)

        started = time.perf_counter()
        trainer.fit(model, datamodule=datamodule, ckpt_path=start.checkpoint, weights_only=True)
        best, best_score = _best_checkpoint(trainer)
        epochs, global_step = trainer.current_epoch, trainer.global_step
        validation = list(model.val_history)  # before test loads the best checkpoint's older one
        if global_step == 0 or model.trained_batches == 0:
            raise NoTrainingError(
                f"{output_dir}: the run trained no batch (global step {global_step}, "
                f"{model.nonfinite_skips} batches skipped for a non-finite loss), so there is no "
                "trained model to test; nothing is reported as done"
            )
        if trainer.world_size > 1:
            if not trainer.is_global_zero:
                return None
            trainer = _single_process_trainer(cfg, settings)
        counting = isinstance(model.net, FallbackCount)  # a prior aligned frame by frame
        if counting:
            model.net.reset_fits()
        result = model.run_test(
            trainer, datamodule, ckpt_path=best or None, verbose=False, weights_only=True
        )
        alignment = model.net.fit_summary() if counting else None
        if alignment is not None:
            log.info(
                "alignment: %(fallbacks)d of %(fits)d test frame fits fell back, %(reversed)d "
                "of them with returns enough but no fit that keeps the order of depths",
                alignment,
            )
        record = RunRecord.from_result(
            job.identity,
            result,
            "test",
            best_checkpoint=best or None,
            best_val_rmse=best_score,
            epochs=epochs,
            resumed_from=str(start.checkpoint) if start.checkpoint else None,
            global_step=global_step,
            validation=validation,
            wall_time_s=round(time.perf_counter() - started, 2),
            alignment=alignment,
        )
        _publish(output_dir, model, trainer, result, record, best)
    return record
