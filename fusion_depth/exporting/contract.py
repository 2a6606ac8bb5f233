"""What every export back end exports, and what it must provide.

:class:`DepthExportModel` is the model every format holds: ``forward(image[, sparse]) -> depth``
with ``image`` (B, 3, H, W) float32 RGB in [0, 1], for checkpoints trained with ``fusion=concat``
or ``add`` also ``sparse`` (B, 1, H, W) float32 metres (0 = no return), and ``depth``
(B, 1, H, W) float32 metres in ``[min_depth, max_depth]``, computed by
:func:`fusion_depth.inference.predict_depth` (the code path of ``predict`` and ``evaluate``).
:class:`Backend` is what a format's module (:mod:`fusion_depth.exporting.onnx`,
:mod:`fusion_depth.exporting.torchscript`) hands :func:`fusion_depth.exporting.export_model`.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from fusion_depth.inference import predict_depth
from fusion_depth.models import DepthModel


class DepthExportModel(nn.Module):
    """``forward(image[, sparse]) -> depth`` in metres at the input resolution, fp32, eval mode.

    Holds its own CPU fp32 copy of the network, so exporting never changes the caller's model.
    """

    def __init__(self, net: DepthModel) -> None:
        super().__init__()
        net = copy.deepcopy(net).float().cpu().eval()
        self.net = net.to(memory_format=torch.contiguous_format)
        self.net.requires_grad_(False)
        self.eval()

    @property
    def uses_sparse(self) -> bool:
        return self.net.fusion.uses_sparse

    @property
    def input_names(self) -> list[str]:
        return ["image", "sparse"] if self.uses_sparse else ["image"]

    def forward(self, image: torch.Tensor, sparse: torch.Tensor | None = None) -> torch.Tensor:
        return predict_depth(self.net, image, sparse)


def example_inputs(
    model: DepthExportModel, batch: int, height: int, width: int, seed: int
) -> tuple[torch.Tensor, ...]:
    """Inputs for tracing or verifying ``model``: a random image (batch, 3, height, width) in
    [0, 1] and, for fusion, a sparse map (batch, 1, height, width) with ~10 % returns in
    ``[min_depth, max_depth]`` metres (else 0), drawn from ``seed``."""
    generator = torch.Generator().manual_seed(seed)
    image = torch.rand(batch, 3, height, width, generator=generator)
    if not model.uses_sparse:
        return (image,)
    net = model.net
    depth = net.min_depth + (net.max_depth - net.min_depth) * torch.rand(
        batch, 1, height, width, generator=generator
    )
    returns = torch.rand(batch, 1, height, width, generator=generator) < 0.1
    return image, torch.where(returns, depth, torch.zeros_like(depth))


def _nothing_required(verify: bool) -> None:
    """A format that needs no package beyond torch."""


@dataclass(frozen=True)
class Backend:
    """One export format: how its model file is written and checked.

    Attributes:
        name: the ``format=`` value.
        suffix: the model file's default suffix (``.onnx``).
        fixed_batch: whether ``batch_size=N`` can fix the file's batch axis; a format without
            it accepts any batch size, and ``batch_size`` is refused for it.
        export: ``export(model, path, height, width, batch_size, opset)`` writes ``model`` (a
            :class:`DepthExportModel`) to ``path`` for inputs of ``height`` × ``width`` pixels;
            ``batch_size`` None = dynamic batch axis; ``opset`` None = the exporter's default.
        verify: ``verify(path, model, batch, height, width, verify, tolerance)`` checks the file
            written (raising :class:`fusion_depth.exporting.verification.ExportError` when it is
            not usable) and, with ``verify``, compares its depth for a random batch of ``batch``
            with ``model``'s; returns ``{"opset": int | None, "verified": dict | None}``.
        require: ``require(verify)`` raises ImportError, naming the extra to install, when a
            package the format needs (with ``verify``, also to run the file) is missing.
    """

    name: str
    suffix: str
    fixed_batch: bool
    export: Callable[[DepthExportModel, Path, int, int, int | None, int | None], None]
    verify: Callable[[Path, DepthExportModel, int, int, int, bool, float], dict[str, Any]]
    require: Callable[[bool], None] = _nothing_required
