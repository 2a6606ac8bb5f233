"""``python -m fusion_depth.evaluate``: score trained checkpoints without training, or an
exported model file (:mod:`fusion_depth.evaluate.scoring`).

python -m fusion_depth.evaluate ckpt_path=<checkpoint or folder of runs>
python -m fusion_depth.evaluate model_file=<exported file>
"""

from __future__ import annotations

from omegaconf import DictConfig

from fusion_depth.config.hydra_main import hydra_main
from fusion_depth.evaluate.scoring import evaluate_records
from fusion_depth.utils.console import quiet_known_noise

quiet_known_noise()


@hydra_main("evaluate")
def main(cfg: DictConfig) -> float:
    """Hydra entry point. Returns the test RMSE of the last record written (what a sweeper
    minimises)."""
    return evaluate_records(cfg)[-1].test["rmse"]
