"""What every export back end exports, and what it must provide.

:class:`DepthExportModel` is the model every format holds: ``forward(image[, sparse]) -> depth``
with ``image`` (B, 3, H, W) float32 RGB in [0, 1], for checkpoints trained with ``fusion=concat``
or ``add`` also ``sparse`` (B, 1, H, W) float32 metres (0 = no return), and ``depth``
(B, 1, H, W) float32 metres in ``[min_depth, max_depth]``, computed by
:func:`fusion_depth.models.inference.predict_depth` (the code path of ``predict`` and ``evaluate``).
:class:`Backend` is what a format's module (:mod:`fusion_depth.export.onnx`,
:mod:`fusion_depth.export.torchscript`, :mod:`fusion_depth.export.openvino`,
:mod:`fusion_depth.export.tensorrt`) hands :func:`fusion_depth.export.export_model`, and
:class:`ExportSpec` what it is asked to write.
"""

from __future__ import annotations

import copy
import importlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from fusion_depth.errors import MissingDependencyError
from fusion_depth.models import DepthModel
from fusion_depth.models.inference import predict_depth


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


def require_modules(what: str, modules: Sequence[str], extra: str) -> None:
    """Fail with one line naming ``extra`` (the install command) when any of ``modules``
    cannot be imported; ``what`` names who needs them (``format=onnx``).

    Raises:
        MissingDependencyError: an ImportError, shown in one line by the commands: ``<what>
            needs <modules>, which is/are not installed: <extra>``.
    """
    missing = []
    for name in modules:
        try:
            importlib.import_module(name)
        except ImportError:
            missing.append(name)
    if missing:
        raise MissingDependencyError(
            f"{what} needs {', '.join(missing)}, which {'is' if len(missing) == 1 else 'are'} "
            f"not installed: {extra}"
        )


def require_cuda(what: str, instead: str) -> None:
    """Fail with one line when torch sees no CUDA GPU; ``what`` names who needs one
    (``format=tensorrt``), ``instead`` what to use without one.

    Raises:
        MissingDependencyError: ``<what> needs a CUDA GPU, and torch finds none here ...``.
    """
    if not torch.cuda.is_available():
        raise MissingDependencyError(
            f"{what} needs a CUDA GPU, and torch finds none here (torch.cuda.is_available() "
            f"is False); {instead}"
        )


def _nothing_required(verify: bool) -> None:
    """A format that needs no package beyond torch."""


# The inference precisions a file can be meant to run in (the sidecar's "precision"): bf16 on
# CPUs that have it (OpenVINO), fp16 on GPUs (TensorRT).
PRECISIONS = ("fp32", "bf16", "fp16")
# The post-training quantizations a format may offer (``quantize=``).
QUANTIZATIONS = ("int8",)


@dataclass(frozen=True)
class ExportSpec:
    """What :func:`fusion_depth.export.export_model` asks a back end to write.

    Attributes:
        height, width: the input size in pixels (multiples of 32), fixed in the file.
        batch_size: None = a dynamic batch axis; N fixes it (formats with ``fixed_batch``).
        opset: the ONNX opset, None = the exporter's default (other formats ignore it).
        precision: the inference precision the file is meant to run in, one of
            :data:`PRECISIONS` (resolved: never ``auto``); weights are stored in fp32, except
            in a TensorRT engine, built for the precision it runs in.
        quantize: None, or one of the back end's ``quantizations`` (``int8``).
        calibration: with ``quantize``, the model inputs to calibrate on: one tuple per frame
            of ``image`` (1, 3, H, W) float32 in [0, 1] and, for fusion, ``sparse``
            (1, 1, H, W) float32 metres.
    """

    height: int
    width: int
    batch_size: int | None = None
    opset: int | None = None
    precision: str = "fp32"
    quantize: str | None = None
    calibration: Sequence[tuple[torch.Tensor, ...]] = ()

    @property
    def computes_in(self) -> str:
        """What the file computes in: ``int8`` for a quantized file, else :attr:`precision`
        (the key of :data:`fusion_depth.export.verification.TOLERANCES`)."""
        return self.quantize or self.precision


@dataclass(frozen=True)
class Backend:
    """One export format: how its model file is written and checked.

    Attributes:
        name: the ``format=`` value.
        suffix: the model file's default suffix (``.onnx``).
        fixed_batch: whether ``batch_size=N`` can fix the file's batch axis; a format without
            it accepts any batch size, and ``batch_size`` is refused for it.
        dynamic_batch: whether its files can have a dynamic batch axis; a format without one
            fixes it at ``batch_size``, 1 where that is None.
        export: ``export(model, path, spec)`` writes ``model`` (a :class:`DepthExportModel`) to
            ``path`` as :class:`ExportSpec` ``spec`` asks, with its companion files (below).
        verify: ``verify(path, model, spec, batch, verify, tolerance)`` checks the file written
            (raising :class:`fusion_depth.export.verification.ExportError` when it is not
            usable) and, with ``verify``, compares its depth for a random batch of ``batch``
            with ``model``'s; returns ``{"opset": int | None, "verified": dict | None}``.
        engine: the name, in :data:`fusion_depth.export.runtime.ENGINES`, of the engine
            that runs the format's files (recorded in the sidecar).
        require: ``require(verify)`` raises ImportError, naming the extra to install, when a
            package the format needs (with ``verify``, also to run the file) is missing.
        companions: suffixes of the files written beside the model file with its stem (an
            OpenVINO IR's ``.bin`` weights next to its ``.xml``); the model file then must end
            in ``suffix``. They are written, checked and renamed into place with it.
        precisions: the inference precisions (:data:`PRECISIONS`) its files can run in.
        quantizations: the ``quantize=`` values it offers (:data:`QUANTIZATIONS`).
        quantize_hint: what to do instead, said when a ``quantize=`` it lacks is asked for.
    """

    name: str
    suffix: str
    fixed_batch: bool
    export: Callable[[DepthExportModel, Path, ExportSpec], None]
    verify: Callable[[Path, DepthExportModel, ExportSpec, int, bool, float], dict[str, Any]]
    engine: str
    require: Callable[[bool], None] = _nothing_required
    companions: tuple[str, ...] = ()
    precisions: tuple[str, ...] = ("fp32",)
    quantizations: tuple[str, ...] = ()
    dynamic_batch: bool = True
    quantize_hint: str = ""
