"""``<model file>.json``: what deployment code feeds an exported model and gets back.

It records the input and output names, shapes, dtypes and units, the depth range, the fusion
mode, model, backbone, dataset and sensor, the checkpoint, format, engine, precision,
quantization and opset, how the file was verified and, where measured, the accuracy it costs
(:func:`fusion_depth.export.data.compare_accuracy`). For ``evaluate``/``predict
model_file=`` it also holds the checkpoint's dataset block (``dataset_config``) and the training
run's identity (``run``), as plain data; :mod:`fusion_depth.export.runtime` reads it back.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from fusion_depth.export.contract import Backend, DepthExportModel, ExportSpec
from fusion_depth.models import DEFAULT_MODEL
from fusion_depth.runner.checkpoints import LoadedModel
from fusion_depth.runner.record import training_identity


def sidecar_path(path: str | os.PathLike) -> Path:
    """``<model file>.json``: what deployment code feeds the model and gets back."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def sidecar_contents(
    model: DepthExportModel,
    loaded: LoadedModel | None,
    backend: Backend,
    output: Path,
    spec: ExportSpec,
    result: dict[str, Any],
) -> dict[str, Any]:
    """The sidecar JSON: everything deployment code needs to feed the model and read it.

    ``loaded``: the checkpoint exported (None for a bare network); ``spec``: what was exported
    (size, batch axis, precision, quantization); ``result``: the back end's ``verify`` result
    (opset, verification), with the exporter's ``quantization`` and ``accuracy`` blocks where
    it made them.
    """
    net = model.net
    batch: int | str = spec.batch_size or "batch"
    height, width = spec.height, spec.width
    inputs = _inputs(model.uses_sparse, batch, height, width)
    dataset = (loaded.config.get("dataset") or {}) if loaded is not None else {}
    block = (
        {k: v for k, v in dataset.items() if k != "requires"} if isinstance(dataset, dict) else {}
    )
    net_config = ((loaded.config.get("model") or {}).get("net") or {}) if loaded else {}
    return {
        "format": backend.name,
        "file": output.name,
        "checkpoint": str(loaded.path.resolve()) if loaded is not None else None,
        "fusion": net.fusion.mode,
        "model": net_config.get("name", DEFAULT_MODEL) if loaded is not None else None,
        # The run config's encoder; a bare network's own (not every model has one ``encoder``).
        "backbone": (
            loaded.backbone
            if loaded is not None
            else getattr(getattr(net, "encoder", None), "name", None)
        ),
        "dataset": dataset.get("name"),
        "sensor": dataset.get("sensor"),
        "inputs": inputs,
        "outputs": [
            {
                "name": "depth",
                "shape": [batch, 1, height, width],
                "dtype": "float32",
                "unit": "m",
                "description": f"depth in metres, clipped to [{net.min_depth}, {net.max_depth}]",
            }
        ],
        "min_depth": net.min_depth,
        "max_depth": net.max_depth,
        "dynamic_batch": spec.batch_size is None,
        "engine": backend.engine,
        "precision": spec.precision,
        "quantization": result.get("quantization"),
        "opset": result["opset"],
        "verified": result["verified"],
        "accuracy": result.get("accuracy"),
        "torch": torch.__version__,
        # What evaluate/predict model_file= need: the dataset and the run, as plain data.
        "dataset_config": block or None,
        "run": (
            training_identity(loaded.run, loaded.config).to_json() if loaded is not None else None
        ),
    }


def _inputs(uses_sparse: bool, batch: int | str, height: int, width: int) -> list[dict[str, Any]]:
    """The sidecar's ``inputs``: ``image`` and, with ``uses_sparse``, ``sparse``."""
    inputs = [
        {
            "name": "image",
            "shape": [batch, 3, height, width],
            "dtype": "float32",
            "description": "RGB in [0, 1] (not ImageNet-normalised; the model does that)",
        }
    ]
    if uses_sparse:
        inputs.append(
            {
                "name": "sparse",
                "shape": [batch, 1, height, width],
                "dtype": "float32",
                "unit": "m",
                "description": "sparse depth in metres, 0 = no return",
            }
        )
    return inputs
