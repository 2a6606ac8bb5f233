"""Build a dataset's cache once, before training: ``python -m fusion_depth.prepare dataset=...``.

Takes the same configuration as ``fusion_depth.train`` and builds every split the dataset's
reader would build on first use (projection, filling, resizing), so training epochs only read
small files. Running it again with the same settings does nothing; an interrupted run continues
where it stopped (see :mod:`fusion_depth.data.prepared`).
"""

from __future__ import annotations

import logging

import hydra
from hydra.utils import instantiate
from omegaconf import DictConfig

from fusion_depth.config import validate_config
from fusion_depth.data import SPLITS

log = logging.getLogger(__name__)


def prepare(cfg: DictConfig) -> dict[str, int]:
    """Builds (or finds) every split of ``cfg.dataset``; returns the frame count per split."""
    validate_config(cfg)
    reader = instantiate(cfg.dataset.reader)
    counts = {}
    for split in SPLITS:
        dataset = reader(split=split)
        counts[split] = len(dataset)
        log.info("%s %s: %d frames ready", cfg.dataset.name, split, counts[split])
    return counts


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def main(cfg: DictConfig) -> None:
    counts = prepare(cfg)
    print(", ".join(f"{split}: {n} frames" for split, n in counts.items()))


if __name__ == "__main__":
    main()
