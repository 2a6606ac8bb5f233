"""Train one configuration, test its best checkpoint, write ``metrics.json`` and
``per_image.csv``.

python -m fusion_depth.train                                   # the default run
python -m fusion_depth.train -m loss=l1,l2,berhu fusion=rgb,concat,add   # a sweep
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

import hydra
import lightning as L
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from hydra.utils import instantiate
from lightning.pytorch.callbacks import LearningRateMonitor
from omegaconf import DictConfig, OmegaConf

from fusion_depth.config import validate_config
from fusion_depth.console import quiet_known_noise
from fusion_depth.data.datamodule import DepthDataModule
from fusion_depth.evaluation import evaluation_record, publish_results
from fusion_depth.loggers import closing
from fusion_depth.runs import (
    RESOLVED_CONFIG_FILE,
    provenance,
    record_failure,
    write_text_atomic,
)
from fusion_depth.speed import accelerator_device, resolve_precision

log = logging.getLogger(__name__)

quiet_known_noise()


def run_identity(cfg: DictConfig) -> dict:
    """What a run is: the choices ``report`` groups by, and the overrides that made it."""
    overrides = list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []
    return {
        "dataset": cfg.dataset.name,
        "sensor": cfg.dataset.get("sensor"),
        "backbone": cfg.backbone.name,
        "fusion": cfg.fusion.mode,
        "loss": cfg.loss.pixel,
        "seed": cfg.seed,
        "overrides": overrides,
    }


def train(cfg: DictConfig) -> dict:
    """Fit, test the best checkpoint, write ``metrics.json``; returns its contents."""
    run_config = validate_config(cfg)
    precision = resolve_precision(
        cfg.trainer.precision, accelerator_device(cfg.trainer.accelerator)
    )
    run_config["trainer"]["precision"] = precision  # what ran, not "auto"
    L.seed_everything(cfg.seed, workers=True)
    output_dir = Path(cfg.paths.output_dir)
    datamodule = DepthDataModule(reader=instantiate(cfg.dataset.reader), **cfg.data)
    model = instantiate(cfg.model, _convert_="all")
    write_text_atomic(output_dir / RESOLVED_CONFIG_FILE, OmegaConf.to_yaml(run_config))
    model.run_config = run_config
    model.run_identity = run_identity(cfg)
    logger = instantiate(cfg.logger) if cfg.logger.get("_target_") else False
    with closing(logger):
        callbacks = [instantiate(c) for c in cfg.callbacks.values() if c]
        if logger:
            logger.log_hyperparams(run_config)
        else:  # Lightning refuses a learning-rate monitor with nothing to log to
            callbacks = [c for c in callbacks if not isinstance(c, LearningRateMonitor)]
        progress = cfg.trainer.enable_progress_bar
        trainer = instantiate(
            cfg.trainer,
            callbacks=callbacks,
            logger=logger,
            precision=precision,
            enable_progress_bar=sys.stdout.isatty() if progress is None else progress,
        )

        start = time.perf_counter()
        trainer.fit(model, datamodule=datamodule)
        best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
        trainer.test(model, datamodule=datamodule, ckpt_path=best or None, verbose=False)
        record = evaluation_record(model.test_results, model.protocol, "test", model.test_latency)
        results = {
            "status": "ok",
            "run": model.run_identity,
            **record,
            "best_checkpoint": best or None,
            "best_val_rmse": (
                float(trainer.checkpoint_callback.best_model_score)
                if best and trainer.checkpoint_callback.best_model_score is not None
                else None
            ),
            "epochs": trainer.current_epoch,
            "global_step": trainer.global_step,
            "wall_time_s": round(time.perf_counter() - start, 2),
            "versions": provenance(),
        }
        title = (
            f"Test metrics ({results['test']['num_images']} images, best checkpoint "
            f"{best or 'last weights'})"
        )
        publish_results(output_dir, results, model.test_per_image, trainer.loggers, title)
    return results


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def main(cfg: DictConfig) -> float | None:
    """Hydra entry point; in a sweep a failing job is recorded and the sweep goes on."""
    if HydraConfig.get().mode != RunMode.MULTIRUN:
        return train(cfg)["test"]["rmse"]
    try:
        return train(cfg)["test"]["rmse"]
    except Exception as err:  # noqa: BLE001 - one job's failure must not end the sweep
        path = record_failure(cfg.paths.output_dir, list(HydraConfig.get().overrides.task), err)
        log.exception("job failed; recorded in %s", path)
        return None


if __name__ == "__main__":
    main()
