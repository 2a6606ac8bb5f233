"""``python -m fusion_depth.predict``: depth maps for new images from a trained checkpoint, or
from a model file exported from one.

python -m fusion_depth.predict ckpt_path=best.ckpt input=photos/ sparse=radar_pngs/
python -m fusion_depth.predict ckpt_path=best.ckpt input=frame.jpg sparse=frame_radar.png npy=true
python -m fusion_depth.predict ckpt_path=best.ckpt input=split:test limit=20   # a dataset split
python -m fusion_depth.predict model_file=best.xml input=split:test   # an exported model file

``model_file`` (instead of ``ckpt_path``) is a file written by ``python -m fusion_depth.export``,
run on the CPU by the engine its sidecar names (:mod:`fusion_depth.export.runtime`), in the
precision it was exported for (``device``, ``precision`` and ``channels_last`` are for
checkpoints). It takes images of the size it was exported at only (other sizes are skipped,
naming the size it takes); splits come from the dataset its sidecar records (or ``dataset=``).

``input`` is a folder of images (``.png``, ``.jpg``, ``.jpeg``, sorted by name), one image file, or
``split:<train|val|test>``: that split of the checkpoint's dataset (or of ``dataset=<name>``).
``sparse`` (and ``ground_truth``, shown in the visualisation only) is a folder of depth PNGs named
``<image stem>.png`` or, for one image, a single PNG; a checkpoint trained with sparse input
needs it for file and folder inputs. For every input ``<stem>`` (``<split>_<index:06d>`` for
splits), ``output_dir`` receives ``<stem>.png`` (uint16 depth in 1/256 m), ``<stem>.npy``
(float32 metres) with ``npy=true`` and ``<stem>.viz.png`` with ``visualize=true`` (the default);
:mod:`fusion_depth.predict.files` describes the files.

An image of more than ``max_pixels`` pixels (default 4096 × 4096; null: any) is refused from its
header, before it is decoded: the network's memory grows with the pixels. No output replaces
another output or an input of the same run: in a folder, an input whose outputs an input before
it would write (``x.viz.png`` after ``x.png``, whose visualisation is ``x.viz.png``) is skipped.

In a folder or split run an input that fails is skipped (``skipped <path>: <reason>``), the others
are still written, the run ends with the summary line ``predicted N of M inputs into <dir>;
skipped K: <paths>`` and the command exits with status 1 if anything was skipped. Failures that
are not about one input (an ``output_dir`` that takes no files, a full disk, the network failing
on 3 inputs in a row) stop the run at once (:mod:`fusion_depth.predict.files`, "Failures"). A single
file input raises instead of skipping.
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from fusion_depth.config.hydra_main import hydra_main
from fusion_depth.data import SPLITS
from fusion_depth.errors import ConfigError
from fusion_depth.export.runtime import check_source, load_exported
from fusion_depth.predict.files import (
    MAX_PIXELS,
    SPLIT_PREFIX,
    PredictSummary,
    predict_file,
    predict_folder,
    predict_split,
)
from fusion_depth.runner.checkpoints import load_model
from fusion_depth.runner.speed import autocast, resolve_device, resolve_precision, speed_up
from fusion_depth.utils.console import quiet_known_noise

quiet_known_noise()


def predict(cfg: DictConfig) -> PredictSummary | np.ndarray:
    """Run a ``conf/predict.yaml`` config.

    Returns the summary for a folder or split input, the depth (H, W) for a single file.
    """
    source = str(cfg.input)
    sparse, ground_truth = cfg.get("sparse"), cfg.get("ground_truth")
    options = {"npy": cfg.npy, "visualize": cfg.visualize, "flip_tta": cfg.flip_tta}
    files = {"max_pixels": cfg.get("max_pixels", MAX_PIXELS)}  # image files only: splits are sized
    if source.startswith(SPLIT_PREFIX):
        for key, value in (("sparse", sparse), ("ground_truth", ground_truth)):
            if value is not None:
                raise ValueError(
                    f"{key}={value}: input={source} reads it from the dataset; drop {key}="
                )
    else:
        path = Path(source).expanduser()
        if not path.exists():
            raise FileNotFoundError(
                f"input={source}: no such file or folder (expected a folder of images, an "
                f"image file, or {SPLIT_PREFIX}<{'|'.join(SPLITS)}>)"
            )
    check_source(cfg.get("ckpt_path"), cfg.get("model_file"))
    if cfg.get("model_file") is not None:
        if cfg.get("prior") is not None:
            raise ConfigError(
                f"prior={cfg.prior.name} with model_file={cfg.model_file}: an exported file "
                "holds its prior; prior= goes with ckpt_path="
            )
        # Run by its engine on the CPU, in the precision recorded at export.
        loaded = load_exported(cfg.model_file)
        running = contextlib.nullcontext()
    else:
        prior = cfg.get("prior")
        prior = None if prior is None else OmegaConf.to_container(prior, resolve=True)
        loaded = load_model(cfg.ckpt_path, prior=prior)
        device = resolve_device(str(cfg.device))
        precision = resolve_precision(cfg.precision, device, key="precision")
        speed_up(loaded.net.to(device), cfg.channels_last, False, device)
        running = autocast(precision, device)
    output_dir = Path(cfg.output_dir)
    batching = {"batch_size": cfg.batch_size, "limit": cfg.limit, "progress": cfg.progress}
    with running:
        if source.startswith(SPLIT_PREFIX):
            split = source[len(SPLIT_PREFIX) :]
            return predict_split(
                loaded, split, output_dir, cfg.get("dataset"), **options, **batching
            )
        if path.is_dir():
            return predict_folder(
                loaded, path, output_dir, sparse, ground_truth, **options, **batching, **files
            )
        return predict_file(loaded, path, output_dir, sparse, ground_truth, **options, **files)


@hydra_main("predict")
def main(cfg: DictConfig) -> None:
    """Hydra entry point; exits with status 1 when any input was skipped."""
    result = predict(cfg)
    if isinstance(result, PredictSummary) and not result.ok:
        sys.exit(1)
