"""The TorchScript back end: ``torch.jit.trace`` of the model, verified by loading it back.

``torch.jit`` is deprecated upstream but is still what C++/libtorch deployments load. The traced
model accepts any batch size; its height and width are those it was traced at.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from fusion_depth.export.contract import Backend, DepthExportModel, ExportSpec, example_inputs
from fusion_depth.export.verification import compare_depth


@contextlib.contextmanager
def quiet_jit() -> Iterator[None]:
    """Hide torch.jit's deprecation notices and the tracer's notes on predict_depth's Python
    branches: they depend on H and W only, which are fixed in the exported model."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        warnings.filterwarnings("ignore", message=r".*`torch\.jit\..*` is deprecated.*")
        yield


def export_torchscript(model: DepthExportModel, path: Path, spec: ExportSpec) -> None:
    """Write ``torch.jit.trace`` of ``model`` at ``spec.height`` × ``spec.width`` to ``path``.

    ``spec.batch_size`` and ``spec.opset`` are not used: the traced model takes any batch
    size, and TorchScript has no opset. The file computes in fp32.
    """
    example = example_inputs(model, 2, spec.height, spec.width, seed=1)
    with quiet_jit():
        traced = torch.jit.trace(model, example, check_trace=False)
        torch.jit.save(traced, str(path))


def verify_torchscript(
    path: Path,
    model: DepthExportModel,
    spec: ExportSpec,
    batch: int,
    verify: bool,
    tolerance: float,
) -> dict[str, Any]:
    """Load the file back and, with ``verify``, compare its depth for a random batch of
    ``batch`` with ``model``'s.

    Returns:
        ``{"opset": None, "verified": None, or the runtime, batch and differences}``.

    Raises:
        ExportError: its depth is not within ``tolerance`` of PyTorch's.
    """
    with quiet_jit():
        loaded = torch.jit.load(str(path), map_location="cpu")  # also checks the file reads back
        if not verify:
            return {"opset": None, "verified": None}
        inputs = example_inputs(model, batch, spec.height, spec.width, seed=2)
        with torch.no_grad():
            depth = loaded(*inputs).numpy()
    reference = model(*inputs)
    return {
        "opset": None,
        "verified": {
            "runtime": f"torch.jit {torch.__version__}",
            "batch": batch,
            **compare_depth(depth, reference, tolerance, "the TorchScript model"),
        },
    }


TORCHSCRIPT = Backend(
    name="torchscript",
    suffix=".pt",
    fixed_batch=False,
    export=export_torchscript,
    verify=verify_torchscript,
    engine="torchscript",
)
