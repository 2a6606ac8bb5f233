"""Train one configuration, test its best checkpoint and write ``metrics.json``.

python -m fusion_depth.train                                   # the default run
python -m fusion_depth.train -m loss=l1,l2,berhu fusion=rgb,concat,add   # a sweep
"""

from __future__ import annotations

import logging
import sys
import time
import warnings
from pathlib import Path

import hydra
import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from hydra.utils import instantiate
from lightning.pytorch.callbacks import LearningRateMonitor
from omegaconf import DictConfig, OmegaConf

import fusion_depth
from fusion_depth.config import validate_config
from fusion_depth.data.datamodule import DepthDataModule
from fusion_depth.report import format_table
from fusion_depth.runs import (
    METRICS_FILE,
    RESOLVED_CONFIG_FILE,
    record_failure,
    write_json_atomic,
    write_text_atomic,
)

log = logging.getLogger(__name__)

# Not actionable for users: the augmentation hook is meant to live on the module, and the
# pytree notice is Lightning's own use of a deprecated torch API.
warnings.filterwarnings("ignore", message=".*overridden `on_after_batch_transfer`.*")
warnings.filterwarnings("ignore", message=".*isinstance\\(treespec, LeafSpec\\)` is deprecated.*")

TABLE_COLUMNS = (
    ("rmse", "RMSE"),
    ("abs_rel", "ARD"),
    ("sq_rel", "SRD"),
    ("mae", "MAE"),
    ("delta1", "δ1"),
    ("delta2", "δ2"),
    ("delta3", "δ3"),
)


def _run_identity(cfg: DictConfig) -> dict:
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


def _split_by_condition(flat: dict[str, float]) -> tuple[dict, dict]:
    overall = {k: v for k, v in flat.items() if "/" not in k}
    by_condition: dict[str, dict] = {}
    for key, value in flat.items():
        if "/" in key:
            condition, metric = key.split("/", 1)
            by_condition.setdefault(condition, {})[metric] = value
    return overall, by_condition


def metric_table(overall: dict, by_condition: dict) -> str:
    """Markdown table of the test metrics, overall and per condition."""
    rows = [["all", *(f"{overall[k]:.3f}" for k, _ in TABLE_COLUMNS)]]
    rows += [[c, *(f"{m[k]:.3f}" for k, _ in TABLE_COLUMNS)] for c, m in by_condition.items()]
    return format_table(["Condition", *(name for _, name in TABLE_COLUMNS)], rows, "markdown")


def train(cfg: DictConfig) -> dict:
    """Fit, test the best checkpoint, write ``metrics.json``; returns its contents."""
    run_config = validate_config(cfg)
    L.seed_everything(cfg.seed, workers=True)
    output_dir = Path(cfg.paths.output_dir)
    datamodule = DepthDataModule(reader=instantiate(cfg.dataset.reader), **cfg.data)
    model = instantiate(cfg.model, _convert_="all")
    write_text_atomic(output_dir / RESOLVED_CONFIG_FILE, OmegaConf.to_yaml(run_config))
    model.run_config = run_config
    logger = instantiate(cfg.logger) if cfg.logger.get("_target_") else False
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
        enable_progress_bar=sys.stdout.isatty() if progress is None else progress,
    )

    start = time.perf_counter()
    trainer.fit(model, datamodule=datamodule)
    best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
    trainer.test(model, datamodule=datamodule, ckpt_path=best or None, verbose=False)
    overall, by_condition = _split_by_condition(model.test_results)
    results = {
        "status": "ok",
        "run": _run_identity(cfg),
        "test": overall,
        "test_by_condition": by_condition,
        "best_checkpoint": best or None,
        "best_val_rmse": (
            float(trainer.checkpoint_callback.best_model_score)
            if best and trainer.checkpoint_callback.best_model_score is not None
            else None
        ),
        "epochs": trainer.current_epoch,
        "global_step": trainer.global_step,
        "wall_time_s": round(time.perf_counter() - start, 2),
        "versions": {
            "fusion_depth": fusion_depth.__version__,
            "torch": torch.__version__,
            "lightning": L.__version__,
        },
    }
    write_json_atomic(output_dir / METRICS_FILE, results)
    print(
        f"\nTest metrics ({results['test']['num_images']} images, best checkpoint "
        f"{best or 'last weights'}):\n{metric_table(overall, by_condition)}\n"
        f"Written to {output_dir / METRICS_FILE}",
        flush=True,
    )
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
