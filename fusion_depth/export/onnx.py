"""The ONNX back end: ``torch.onnx.export``'s ``torch.export``-based exporter, ``onnx.checker``
and ONNX Runtime.

The ``torch.export``-based exporter is the default since torch 2.9 and needs ``onnxscript`` (the
TorchScript-based one is deprecated). The batch axis is dynamic (named ``batch``) unless
``batch_size`` fixes it for runtimes that want static shapes. Needs ``pip install -e ".[onnx]"``.
"""

from __future__ import annotations

import contextlib
import logging
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from fusion_depth.export.contract import (
    Backend,
    DepthExportModel,
    ExportSpec,
    example_inputs,
    require_modules,
)
from fusion_depth.export.verification import ExportError, compare_depth

ONNX_EXTRA = 'pip install -e ".[onnx]"'


def require_onnx(verify: bool = True) -> None:
    """Fail with one line naming the extra when the ONNX packages are missing.

    Raises:
        ImportError: ``onnx`` or ``onnxscript`` (with ``verify``, also ``onnxruntime``) cannot
            be imported.
    """
    modules = ["onnx", "onnxscript"] + (["onnxruntime"] if verify else [])
    require_modules("format=onnx", modules, ONNX_EXTRA)


@contextlib.contextmanager
def _quiet_onnx_passes() -> Iterator[None]:
    """onnxscript's optimiser logs every pass (hundreds of INFO lines under Hydra's logging)."""
    loggers = [logging.getLogger(name) for name in ("onnx_ir", "onnxscript", "torch.onnx")]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(max(logger.getEffectiveLevel(), logging.WARNING))
    try:
        yield
    finally:
        for logger, level in zip(loggers, levels, strict=True):
            logger.setLevel(level)


def export_onnx(model: DepthExportModel, path: Path, spec: ExportSpec) -> None:
    """Write ``model`` to ``path`` as one ONNX file (no external data) for ``spec.height`` ×
    ``spec.width`` inputs; ``spec.batch_size`` None = a dynamic batch axis named ``batch``;
    ``spec.opset`` None = the exporter's default. The file computes in fp32."""
    height, width, batch_size, opset = spec.height, spec.width, spec.batch_size, spec.opset
    # An example batch of 2: torch.export specialises dimensions of size 0 and 1.
    example = example_inputs(model, batch_size or 2, height, width, seed=1)
    dynamic_shapes = None
    if batch_size is None:
        batch = torch.export.Dim("batch", min=1)
        dynamic_shapes = {name: {0: batch} for name in model.input_names}
    with warnings.catch_warnings(), _quiet_onnx_passes():
        # One named dimension shared by two inputs is reported as a renaming conflict.
        warnings.filterwarnings("ignore", message=".*will not be used, since it shares.*")
        program = torch.onnx.export(
            model,
            example,
            input_names=model.input_names,
            output_names=["depth"],
            opset_version=opset,
            dynamo=True,
            dynamic_shapes=dynamic_shapes,
            external_data=False,
            verbose=False,
        )
        program.save(str(path), external_data=False)


def verify_onnx(
    path: Path,
    model: DepthExportModel,
    spec: ExportSpec,
    batch: int,
    verify: bool,
    tolerance: float,
) -> dict[str, Any]:
    """Check the ONNX file with ``onnx.checker`` and, with ``verify``, compare ONNX Runtime's
    depth (CPU) for a random batch of ``batch`` with ``model``'s.

    Returns:
        ``{"opset": the file's ai.onnx opset, "verified": None, or the runtime, batch and
        differences}``.

    Raises:
        ExportError: the checker rejects the file, or its depth is not within ``tolerance``.
    """
    import onnx

    try:
        onnx.checker.check_model(str(path), full_check=True)
    except onnx.checker.ValidationError as err:
        raise ExportError(f"the exported ONNX model fails onnx.checker: {err}") from err
    opset = next(
        (
            o.version
            for o in onnx.load(str(path), load_external_data=False).opset_import
            if o.domain in ("", "ai.onnx")
        ),
        None,
    )
    result: dict[str, Any] = {"opset": opset, "verified": None}
    if verify:
        import onnxruntime as ort

        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        inputs = example_inputs(model, batch, spec.height, spec.width, seed=2)
        feeds = {name: x.numpy() for name, x in zip(model.input_names, inputs, strict=True)}
        (depth,) = session.run(["depth"], feeds)
        reference = model(*inputs)
        result["verified"] = {
            "runtime": f"onnxruntime {ort.__version__}",
            "batch": batch,
            **compare_depth(depth, reference, tolerance, "ONNX Runtime"),
        }
    return result


ONNX = Backend(
    name="onnx",
    suffix=".onnx",
    fixed_batch=True,
    export=export_onnx,
    verify=verify_onnx,
    engine="onnxruntime",
    require=require_onnx,
)
