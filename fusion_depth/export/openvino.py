"""The OpenVINO back end: ``openvino.convert_model`` of the model, an IR (``.xml`` + ``.bin``)
written by ``openvino.save_model``, optionally quantized to int8 by NNCF, verified by running
it with OpenVINO's CPU plugin.

Weights are stored in fp32 (``compress_to_fp16=False``); the precision the CPU computes in is
chosen when the IR is compiled, from the sidecar's ``precision`` (``INFERENCE_PRECISION_HINT``,
:func:`fusion_depth.export.runtime.compile_openvino`): bf16 where the CPU has it, else fp32.
``quantize=int8`` runs NNCF's post-training quantization (``nncf.quantize``) on the converted
model, calibrated on ``spec.calibration`` (frames of the checkpoint's training split,
:mod:`fusion_depth.export.data`). The batch axis is dynamic unless ``batch_size`` fixes it.
Needs ``pip install -e ".[openvino]"``.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from fusion_depth.export.contract import (
    Backend,
    DepthExportModel,
    ExportSpec,
    example_inputs,
    require_modules,
)
from fusion_depth.export.runtime import OPENVINO_EXTRA, compile_openvino
from fusion_depth.export.torchscript import quiet_jit
from fusion_depth.export.verification import CHECKED, ExportError, compare_depth, unreadable


def require_openvino(verify: bool = True) -> None:
    """Fail with one line naming the extra when ``openvino`` is missing.

    Raises:
        ImportError: ``openvino`` cannot be imported.
    """
    require_modules("format=openvino", ["openvino"], OPENVINO_EXTRA)


def _errors_only(record: logging.LogRecord) -> bool:
    return record.levelno >= logging.ERROR


@contextlib.contextmanager
def _quiet_nncf() -> Iterator[None]:
    """NNCF's info and warning lines, and torch's note on CUDA that importing and running it
    prints on a machine without CUDA, are noise here (errors pass); its progress bars
    (statistics collection, bias correction) stay. A filter, not a level: torch resets its
    loggers' levels on the way."""
    loggers = [logging.getLogger(name) for name in ("nncf", "torch.utils.cpp_extension")]
    for logger in loggers:
        logger.addFilter(_errors_only)
    try:
        yield
    finally:
        for logger in loggers:
            logger.removeFilter(_errors_only)


def require_nncf() -> None:
    """Fail with one line naming the extra when ``nncf`` (``quantize=int8``) is missing."""
    with _quiet_nncf():
        require_modules("quantize=int8", ["nncf"], OPENVINO_EXTRA)


def edge_convolutions(ov_model: Any) -> list[str]:
    """The friendly names of the first and the last convolution of ``ov_model``'s graph, in
    execution order (one name when it has one convolution, none when it has none)."""
    names = [
        op.get_friendly_name()
        for op in ov_model.get_ordered_ops()
        if op.get_type_name() in ("Convolution", "GroupConvolution")
    ]
    return list(dict.fromkeys(names[:1] + names[-1:]))


def quantize_int8(ov_model: Any, spec: ExportSpec) -> Any:
    """``ov_model`` quantized to int8 by ``nncf.quantize``, calibrated on every frame of
    ``spec.calibration`` (each a tuple of the model's inputs, batch 1).

    The first and the last convolution (:func:`edge_convolutions`) stay unquantized, in the
    file's precision: the first takes the inputs as they come (a fusion model's sparse depth in
    metres, 0 to the depth cap, beside the image), the last gives the depth. Quantizing them
    too cost the built-in DenseDepth (concat) +0.58 m validation RMSE, against +0.05 m with them
    kept (docs/results/engine-accuracy.md); keeping a network's first and last layers in higher
    precision is common practice in post-training quantization.

    Raises:
        ValueError: ``spec.calibration`` is empty.
    """
    frames = list(spec.calibration)
    if not frames:
        raise ValueError("quantize=int8: no calibration frames")
    with _quiet_nncf():
        import nncf

        dataset = nncf.Dataset(frames, lambda inputs: [x.numpy() for x in inputs])
        return nncf.quantize(
            ov_model,
            dataset,
            subset_size=len(frames),
            ignored_scope=nncf.IgnoredScope(names=edge_convolutions(ov_model)),
        )


def export_openvino(model: DepthExportModel, path: Path, spec: ExportSpec) -> None:
    """Write ``model`` as an OpenVINO IR: ``path`` (``.xml``) and ``path.with_suffix(".bin")``,
    fp32 weights, inputs named as :attr:`DepthExportModel.input_names` of ``spec.height`` ×
    ``spec.width``, batch axis dynamic unless ``spec.batch_size``; quantized to int8 first
    with ``spec.quantize``."""
    import openvino as ov

    height, width = spec.height, spec.width
    example = example_inputs(model, spec.batch_size or 2, height, width, seed=1)
    batch = spec.batch_size or -1
    channels = {"image": 3, "sparse": 1}
    shapes = [ov.PartialShape([batch, channels[n], height, width]) for n in model.input_names]
    # convert_model imports nncf.torch once nncf is loaded, which imports torch's C++-extension
    # helper, which warns that this machine has no CUDA.
    with quiet_jit(), _quiet_nncf():
        ov_model = ov.convert_model(model, example_input=example, input=shapes)
    for port, name in zip(ov_model.inputs, model.input_names, strict=True):
        port.get_tensor().set_names({name})
    ov_model.outputs[0].get_tensor().set_names({"depth"})
    if spec.quantize == "int8":
        ov_model = quantize_int8(ov_model, spec)
    ov.save_model(ov_model, str(path), compress_to_fp16=False)


def verify_openvino(
    path: Path,
    model: DepthExportModel,
    spec: ExportSpec,
    batch: int,
    verify: bool,
    tolerance: float,
) -> dict[str, Any]:
    """Read the IR back, compile it for the CPU in ``spec.precision`` and check its inputs and
    output; with ``verify``, compare its depth for a random batch of ``batch`` with ``model``'s.

    Returns:
        ``{"opset": None, "verified": None, or the runtime, batch and differences}``.

    Raises:
        ExportError: OpenVINO cannot read or compile it, its inputs or output are not the
            model's, or its depth is not within ``tolerance``.
    """
    import openvino as ov

    try:
        compiled, precision = compile_openvino(path, spec.precision)
    except RuntimeError as err:
        raise unreadable("OpenVINO cannot read the exported IR back", err) from err
    names = [port.get_any_name() for port in compiled.inputs]
    if names != model.input_names or compiled.outputs[0].get_any_name() != "depth":
        raise ExportError(
            f"the exported IR takes {names} and gives {compiled.outputs[0].get_names()}; "
            f"expected {model.input_names} → depth"
        )
    result: dict[str, Any] = {"opset": None, "verified": None}
    if verify:
        inputs = example_inputs(model, batch, spec.height, spec.width, seed=2)
        depth = compiled([x.numpy() for x in inputs])[compiled.outputs[0]]
        computes = spec.quantize or precision
        result["verified"] = {
            "runtime": f"OpenVINO {ov.__version__} CPU, {computes}",
            "batch": batch,
            **compare_depth(
                depth, model(*inputs), tolerance, f"OpenVINO ({computes})", CHECKED[computes]
            ),
        }
    return result


OPENVINO = Backend(
    name="openvino",
    suffix=".xml",
    fixed_batch=True,
    export=export_openvino,
    verify=verify_openvino,
    engine="openvino",
    require=require_openvino,
    companions=(".bin",),
    precisions=("fp32", "bf16"),
    quantizations=("int8",),
)
