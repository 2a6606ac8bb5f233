"""``<model file>.json``: what deployment code feeds an exported model and gets back.

It records the input and output names, shapes, dtypes and units, the depth range, the fusion
mode, backbone, dataset and sensor, the checkpoint, format and opset, and how the file was
verified.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from fusion_depth.checkpoint import LoadedModel
from fusion_depth.exporting.contract import DepthExportModel


def sidecar_path(path: str | os.PathLike) -> Path:
    """``<model file>.json``: what deployment code feeds the model and gets back."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def sidecar_contents(
    model: DepthExportModel,
    loaded: LoadedModel | None,
    fmt: str,
    output: Path,
    height: int,
    width: int,
    batch_size: int | None,
    result: dict[str, Any],
) -> dict[str, Any]:
    """The sidecar JSON: everything deployment code needs to feed the model and read it.

    ``loaded``: the checkpoint exported (None for a bare network); ``batch_size`` None = a
    dynamic batch axis; ``result``: the back end's ``verify`` result (opset, verification).
    """
    net = model.net
    batch: int | str = batch_size or "batch"
    inputs = [
        {
            "name": "image",
            "shape": [batch, 3, height, width],
            "dtype": "float32",
            "description": "RGB in [0, 1] (not ImageNet-normalised; the model does that)",
        }
    ]
    if model.uses_sparse:
        inputs.append(
            {
                "name": "sparse",
                "shape": [batch, 1, height, width],
                "dtype": "float32",
                "unit": "m",
                "description": "sparse depth in metres, 0 = no return",
            }
        )
    dataset = (loaded.config.get("dataset") or {}) if loaded is not None else {}
    return {
        "format": fmt,
        "file": output.name,
        "checkpoint": str(loaded.path.resolve()) if loaded is not None else None,
        "fusion": net.fusion.mode,
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
        "dynamic_batch": batch_size is None,
        "opset": result["opset"],
        "verified": result["verified"],
        "torch": torch.__version__,
    }
