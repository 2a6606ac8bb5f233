"""Train one configuration, test its best checkpoint, write ``metrics.json`` and
``per_image.csv``.

python -m fusion_depth.train                                   # the default run
python -m fusion_depth.train -m loss=l1,l2,berhu fusion=rgb,concat,add   # a sweep
"""

from __future__ import annotations

import contextlib
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import CompactHydraException
from hydra.types import RunMode
from hydra.utils import instantiate
from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint
from lightning.pytorch.plugins.environments import LightningEnvironment
from omegaconf import DictConfig, OmegaConf

from fusion_depth.checkpoint import AtomicCheckpointIO, plain_config
from fusion_depth.cli import hydra_main, user_message
from fusion_depth.config import check_output_dir, checkpoint_bytes, validate_config
from fusion_depth.console import quiet_known_noise
from fusion_depth.data.datamodule import DepthDataModule, check_batches, check_scorable
from fusion_depth.distributed import launch_local_ranks, local_world_size
from fusion_depth.loggers import closing
from fusion_depth.redaction import redact_overrides, redact_secrets
from fusion_depth.resume import (
    RunLock,
    RunLockedError,
    RunStart,
    identity_overrides,
    is_lead_process,
    plan_start,
)
from fusion_depth.run_record import (
    METRICS_FILE,
    RunIdentity,
    RunRecord,
    publish_results,
    read_run_record,
    run_identity,
)
from fusion_depth.runs import RESOLVED_CONFIG_FILE, record_failure, write_text_atomic
from fusion_depth.search import DEFAULT_METRIC, metric_key, objective
from fusion_depth.speed import accelerator_device, resolve_precision
from fusion_depth.visualize import PANEL_CAPTION, write_panel_figure

log = logging.getLogger(__name__)

TEST_PANELS_FILE = "test_panels.png"  # a few test frames drawn by the best checkpoint

quiet_known_noise()


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
    (:meth:`RunRecord.to_json <fusion_depth.run_record.RunRecord.to_json>`; None on the ranks
    other than 0 of a data-parallel run that a cluster launcher started).

    A run whose ``metrics.json`` is complete is not trained again, and one with a
    ``last.ckpt`` continues from it (see :mod:`fusion_depth.resume`)."""
    record = train_record(cfg)
    return record.to_json() if record is not None else None


def train_record(cfg: DictConfig) -> RunRecord | None:
    """:func:`train`, returning the run's record (None on the ranks other than 0 of a
    data-parallel run that a cluster launcher started)."""
    run_config = validate_config(cfg)
    precision = resolve_precision(
        cfg.trainer.precision, accelerator_device(cfg.trainer.accelerator)
    )
    run_config["trainer"]["precision"] = precision  # what ran, not "auto"
    output_dir = Path(cfg.paths.output_dir)
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
        launch_local_ranks(fit_and_test, job, world_size)
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


class NoTrainingError(RuntimeError, CompactHydraException):
    """Fit ended without training a single batch: there is nothing to test or report."""


@dataclass
class RankJob:
    """What every process of a run needs: the config, the resolved config, the run's identity
    and where it starts (decided once, before any process starts)."""

    cfg: DictConfig
    run_config: dict
    identity: RunIdentity
    start: RunStart


def fit_and_test(job: RankJob) -> RunRecord | None:
    """Fit, test the best checkpoint on rank 0 alone, write ``metrics.json``; its record
    (None on the other ranks of a data-parallel run)."""
    cfg, run_config, start = job.cfg, job.run_config, job.start
    precision = run_config["trainer"]["precision"]
    output_dir = Path(cfg.paths.output_dir)
    L.seed_everything(cfg.seed, workers=True)
    datamodule = DepthDataModule(reader=instantiate(cfg.dataset.reader), seed=cfg.seed, **cfg.data)
    model = instantiate(cfg.model, _convert_="all")
    check_output_dir(output_dir, checkpoint_room(cfg.callbacks, model))
    model.run_config = plain_config(run_config)  # checkpoints hold data, never code to call
    model.run_identity = job.identity
    logger = False
    if cfg.logger.get("_target_"):
        resuming = {}  # the interrupted run's W&B run; its CSV log, continued
        if "id" in cfg.logger and cfg.logger.id is None:
            resuming["id"] = start.wandb_id
        if "resume_step" in cfg.logger and cfg.logger.resume_step is None:
            resuming["resume_step"] = start.global_step
            resuming["resume_row"] = start.pending_log_row
        logger = instantiate(cfg.logger, **resuming)
    with closing(logger):
        callbacks = [instantiate(c) for c in cfg.callbacks.values() if c]
        if logger:
            logger.log_hyperparams(run_config)
        else:  # Lightning refuses a learning-rate monitor with nothing to log to
            callbacks = [c for c in callbacks if not isinstance(c, LearningRateMonitor)]
        progress = cfg.trainer.enable_progress_bar
        settings = {
            "logger": logger,
            "precision": precision,
            "enable_progress_bar": sys.stdout.isatty() if progress is None else progress,
            "plugins": [AtomicCheckpointIO()],
        }
        trainer = instantiate(cfg.trainer, callbacks=callbacks, **settings)
        # Zero work is a failure: refused here, not reported as a run that trained nothing.
        check_batches(datamodule, cfg.trainer, cfg.dataset.name, trainer.world_size)
        check_scorable(datamodule, model.protocol, cfg.trainer, cfg.dataset.name)

        started = time.perf_counter()
        trainer.fit(model, datamodule=datamodule, ckpt_path=start.checkpoint, weights_only=True)
        best_callback = next(
            (c for c in trainer.checkpoint_callbacks if isinstance(c, ModelCheckpoint)), None
        )
        best = best_callback.best_model_path if best_callback else ""
        best_score = best_callback.best_model_score if best_callback else None
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
            # The test stage on one process sees every test image exactly once (a distributed
            # sampler pads the split to a multiple of the world size).
            torch.distributed.destroy_process_group()
            trainer = instantiate(
                cfg.trainer,
                devices=1,
                num_nodes=1,
                strategy="auto",
                **{**settings, "plugins": [AtomicCheckpointIO(), LightningEnvironment()]},
            )
        result = model.run_test(
            trainer, datamodule, ckpt_path=best or None, verbose=False, weights_only=True
        )
        record = RunRecord.from_result(
            job.identity,
            result,
            "test",
            best_checkpoint=best or None,
            best_val_rmse=float(best_score) if best and best_score is not None else None,
            epochs=epochs,
            resumed_from=str(start.checkpoint) if start.checkpoint else None,
            global_step=global_step,
            validation=validation,
            wall_time_s=round(time.perf_counter() - started, 2),
        )
        title = (
            f"Test metrics ({result.overall['num_images']} images, best checkpoint "
            f"{best or 'last weights'})"
        )
        panel = None  # written before metrics.json, whose presence means the run is complete
        if model.test_panels:
            net = model.net
            panel = write_panel_figure(
                output_dir / TEST_PANELS_FILE, model.test_panels, net.min_depth, net.max_depth
            )
        publish_results(output_dir, record, result, trainer.loggers, title)
        if panel is not None:
            print(f"Test frames ({PANEL_CAPTION}): {panel}", flush=True)
    return record


@hydra_main("train")
def main(cfg: DictConfig) -> float | None:
    """Hydra entry point. Returns the run's ``optimized_metric`` (a validation metric,
    :func:`fusion_depth.search.objective`), what a sweeper such as ``hparams_search=optuna``
    optimises; None on the ranks that do not test. In a sweep a failing job is recorded, returns
    None (a failed trial to the Optuna sweeper) and the sweep goes on."""
    metric = cfg.get("optimized_metric", DEFAULT_METRIC)
    if HydraConfig.get().mode != RunMode.MULTIRUN:
        metric_key(metric)  # a bad name fails before training
        return objective(train_record(cfg), metric)
    try:
        metric_key(metric)
        return objective(train_record(cfg), metric)
    except RunLockedError as err:  # the folder is another live process's: write nothing there
        log.error("job not run: %s", err)
        return None
    except Exception as err:  # noqa: BLE001 - one job's failure must not end the sweep
        overrides = redact_overrides(list(HydraConfig.get().overrides.task))
        path = record_failure(cfg.paths.output_dir, overrides, err)
        message = user_message(err)  # bad config, data or files: its line says it all
        if message is not None:
            log.error("job failed: %s; recorded in %s", message, path)
        else:
            log.exception("job failed; recorded in %s", path)
        return None


if __name__ == "__main__":
    # Through the module, not as __main__: launchers that pickle the task function (submitit,
    # joblib) and the data-parallel ranks then find it by name.
    from fusion_depth.train import main as _main

    _main()
