"""``python -m fusion_depth.train``: train one configuration, test its best checkpoint, write
``metrics.json`` and ``per_image.csv`` (:mod:`fusion_depth.train.fit`); with ``-m``, a sweep.

python -m fusion_depth.train                                   # the default run
python -m fusion_depth.train -m loss=l1,l2,berhu fusion=rgb,concat,add   # a sweep
"""

from __future__ import annotations

import logging

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from fusion_depth.config.hydra_main import hydra_main, user_message
from fusion_depth.runner.hparams_search import DEFAULT_METRIC, metric_key, objective
from fusion_depth.runner.redaction import redact_overrides
from fusion_depth.runner.resume import RunLockedError
from fusion_depth.runner.run_folder import record_failure
from fusion_depth.train.fit import train_record
from fusion_depth.utils.console import quiet_known_noise

log = logging.getLogger(__name__)
quiet_known_noise()


@hydra_main("train")
def main(cfg: DictConfig) -> float | None:
    """Hydra entry point. Returns the run's ``optimized_metric`` (a validation metric,
    :func:`fusion_depth.runner.hparams_search.objective`), what a sweeper such as
    ``hparams_search=optuna`` optimises; None on the ranks that do not test. In a sweep a
    failing job is recorded, returns None (a failed trial to the Optuna sweeper) and the sweep
    goes on."""
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
        message = user_message(err, cfg)  # bad config, data or files: its line says it all
        path = record_failure(cfg.paths.output_dir, overrides, err, message)
        if message is not None:
            log.error("job failed: %s; recorded in %s", message, path)
        else:
            log.exception("job failed; recorded in %s", path)
        return None
