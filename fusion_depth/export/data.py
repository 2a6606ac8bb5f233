"""The data an export reads: calibration frames for ``quantize=int8`` (the training split) and
the accuracy an exported model costs (the validation split, against PyTorch fp32).

The dataset is chosen as ``evaluate`` chooses it: the block the checkpoint was trained on (its
reader looked up by name in the package's table,
:func:`fusion_depth.runner.checkpoints.make_reader`), or a ``dataset=`` choice composed from
``conf/``. The accuracy is scored by the evaluation
protocol and loop of ``evaluate`` (:class:`~fusion_depth.runner.module.DepthModule`,
:class:`~fusion_depth.runner.protocol.EvalProtocol`), once with the checkpoint's network in fp32
and once with the exported file, and the per-image differences get a paired bootstrap interval
(:func:`fusion_depth.metrics.bootstrap.paired_bootstrap`), as ``report --compare`` computes them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import lightning as L
import numpy as np
import torch

from fusion_depth.metrics.bootstrap import paired_bootstrap
from fusion_depth.models import DepthModel
from fusion_depth.runner.checkpoints import LoadedModel, dataset_config, make_reader
from fusion_depth.runner.datamodule import DepthDataModule
from fusion_depth.runner.module import DepthModule
from fusion_depth.runner.protocol import EvalProtocol, EvaluationResult

log = logging.getLogger(__name__)

CALIBRATION_SPLIT = "train"
ACCURACY_SPLIT = "val"
# The per-image metrics whose exported − PyTorch difference an accuracy block reports.
ACCURACY_METRICS = ("rmse", "delta1")
BOOTSTRAP_RESAMPLES = 10000
BOOTSTRAP_LEVEL = 0.95


@dataclass(frozen=True)
class ExportData:
    """The dataset an export calibrates and measures on.

    Attributes:
        block: the dataset config block (plain data).
        reader: its reader, a callable taking ``split=`` (samples in the float form).
        datamodule: its splits (built on first use) as the test stage loads them.
    """

    block: dict[str, Any]
    reader: Callable[..., Any]
    datamodule: DepthDataModule

    @property
    def name(self) -> str | None:
        return self.block.get("name")


def export_data(
    model: LoadedModel | DepthModel, chosen: Mapping[str, Any] | None, batch_size: int = 4
) -> ExportData:
    """The dataset of ``model``'s checkpoint, or ``chosen`` (a ``dataset=`` block composed from
    ``conf/``, resolved), split by split in batches of ``batch_size``.

    Raises:
        ValueError: ``model`` is a bare network (no checkpoint) and no dataset is chosen.
        CheckpointError: the checkpoint's dataset cannot be rebuilt (naming the key).
    """
    if isinstance(model, LoadedModel):
        block = dataset_config(model, dict(chosen) if chosen is not None else None)
        reader = make_reader(block, None if chosen is not None else model.path, model.key)
    elif chosen is None:
        raise ValueError(
            "a bare network records no dataset: pass dataset=<block> to calibrate or measure "
            "accuracy on"
        )
    else:
        block = dict(chosen)
        reader = make_reader(block)
    datamodule = DepthDataModule(
        reader=reader, batch_size=batch_size, num_workers=0, test_split=ACCURACY_SPLIT
    )
    return ExportData(block, reader, datamodule)


def calibration_inputs(
    data: ExportData, frames: int, height: int, width: int, uses_sparse: bool
) -> tuple[list[tuple[torch.Tensor, ...]], list[int]]:
    """Up to ``frames`` frames of the training split, spread evenly over it (all of them when
    it has fewer), as model inputs: ``image`` (1, 3, H, W) float32 in [0, 1] and, with
    ``uses_sparse``, ``sparse`` (1, 1, H, W) float32 metres.

    Returns:
        (the inputs, the indices of the frames used).

    Raises:
        ValueError: ``frames`` < 1, the split is empty, or its frames are not ``height`` ×
            ``width`` (the export's size; quantization calibrates at the size it runs at).
    """
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise ValueError(f"calibration_frames={frames}: expected an integer ≥ 1")
    split = data.reader(split=CALIBRATION_SPLIT)
    if len(split) == 0:
        raise ValueError(
            f"quantize=int8: dataset={data.name} has no {CALIBRATION_SPLIT} frames to calibrate on"
        )
    count = min(frames, len(split))
    indices = sorted({int(i) for i in np.linspace(0, len(split) - 1, count).round()})
    inputs = []
    for index in indices:
        sample = split[index]
        image = sample["image"].float()
        if tuple(image.shape[-2:]) != (height, width):
            raise ValueError(
                f"quantize=int8: dataset={data.name} frames are {image.shape[-2]}×"
                f"{image.shape[-1]}, the export {height}×{width}; calibrate at the size the "
                "model runs at (drop height=/width=, or choose a dataset of that size)"
            )
        frame = (image[None],)
        if uses_sparse:
            frame += (sample["sparse"].float()[None],)
        inputs.append(frame)
    return inputs, indices


def _score(net: DepthModel, data: ExportData, protocol: EvalProtocol) -> EvaluationResult:
    """``net`` scored on the validation split by ``protocol`` in fp32 on the CPU, by the loop
    and metrics of ``evaluate``."""
    module = DepthModule(
        net=net, conditions=list(data.block.get("conditions") or ()), protocol=protocol
    )
    trainer = L.Trainer(
        accelerator="cpu",
        devices=1,
        precision="32-true",
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        enable_checkpointing=False,
    )
    return module.run_test(trainer, data.datamodule, verbose=False)


def compare_accuracy(
    reference: DepthModel,
    exported: DepthModel,
    data: ExportData,
    *,
    resamples: int = BOOTSTRAP_RESAMPLES,
    level: float = BOOTSTRAP_LEVEL,
) -> dict[str, Any]:
    """What running ``exported`` instead of ``reference`` (the checkpoint's network, PyTorch
    fp32) costs on the validation split, image by image.

    Both are scored by the default evaluation protocol (``conf/eval/paper.yaml``: the
    dataset's depth range, per-image averaging, no crop, no flip TTA). For each metric of
    :data:`ACCURACY_METRICS` (RMSE in metres, δ1 as a fraction), the block holds both models'
    headline values and the mean per-image difference (exported − reference: positive ΔRMSE
    and negative Δδ1 are worse) with its ``level`` percentile-bootstrap interval over images.

    Returns:
        ``{"split", "dataset", "images", "reference", "level", "resamples", "rmse": {...},
        "delta1": {...}}``, each metric ``{"reference", "exported", "diff": {"mean", "low",
        "high"}}``.

    Raises:
        ValueError: fewer than 2 validation images were scored, or the two runs scored
            different images.
    """
    protocol = EvalProtocol.from_config(None, data.block["min_depth"], data.block["max_depth"])
    results = {
        name: _score(net, data, protocol) for name, net in (("ref", reference), ("exp", exported))
    }
    ref, exp = results["ref"].per_image, results["exp"].per_image
    if [r["index"] for r in ref] != [r["index"] for r in exp]:
        raise ValueError("the exported model and PyTorch were scored on different images")
    if len(ref) < 2:
        raise ValueError(
            f"dataset={data.name}: {len(ref)} {ACCURACY_SPLIT} image(s) scored; measuring "
            "accuracy needs at least 2"
        )
    block: dict[str, Any] = {
        "split": ACCURACY_SPLIT,
        "dataset": data.name,
        "images": len(ref),
        "reference": "the checkpoint in PyTorch, fp32",
        "level": level,
        "resamples": resamples,
    }
    for metric in ACCURACY_METRICS:
        diff = np.array([e[metric] - r[metric] for r, e in zip(ref, exp, strict=True)])
        interval = paired_bootstrap(diff.reshape(1, -1), resamples=resamples, level=level)
        block[metric] = {
            "reference": results["ref"].overall[metric],
            "exported": results["exp"].overall[metric],
            "diff": {"mean": interval.mean, "low": interval.low, "high": interval.high},
        }
    return block
