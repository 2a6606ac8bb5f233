"""The TensorRT back end: Torch-TensorRT's dynamo path compiles the model into TensorRT engines
for this machine's NVIDIA GPU, saved as an ExportedProgram (``.pt2``) and verified by loading it
back and running it on the GPU.

The file is a PT2 archive, named ``.pt2`` as ``torch.export.save`` expects (Torch-TensorRT's
guides write ``.ep``; torch warns on any name but ``.pt2`` and loads one only through a
deprecated path, so the runtime opens the file itself and hands ``torch.export.load`` the file
object, which takes any name).

``torch_tensorrt.compile(model, ir="dynamo", arg_inputs=...)`` traces the model with
``torch.export`` and builds the engines; ``torch_tensorrt.save`` writes the program, engines
inside, and ``torch.export.load(path).module()`` runs it
(:func:`fusion_depth.export.runtime.load_tensorrt_program`). ``precision=fp16`` (``auto``)
builds with Torch-TensorRT's rule-based autocast to fp16 (``enable_autocast``,
``autocast_low_precision_type``: the dynamo path's way to fp16 since Torch-TensorRT 2.10; from
2.13 on it ignores ``enabled_precisions``), which leaves the operations its rules exclude (such
as those with large-valued outputs) in fp32; ``precision=fp32`` builds with TF32 off, so fp32
means fp32. The input size and the batch are fixed in the engine
(``batch_size``, 1 by default); ``model_file=`` runs any batch in chunks of it. An engine runs
on the GPU model (and TensorRT version) it was built for. No INT8: Torch-TensorRT's INT8 path
needs NVIDIA ModelOpt to calibrate, which this package does not depend on.

Needs a CUDA GPU and ``pip install -e ".[tensorrt]"``; on a machine without either,
``format=tensorrt`` is refused in one line before anything is loaded or written. Untested in
CI (no GPU there); ``tests/gpu/check_tensorrt.py`` is the check to run on a GPU machine.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import torch

from fusion_depth.export.contract import Backend, DepthExportModel, ExportSpec, example_inputs
from fusion_depth.export.runtime import load_tensorrt_program, require_tensorrt
from fusion_depth.export.verification import CHECKED, compare_depth, unreadable

# precision → torch_tensorrt.compile's options for it
_PRECISION_OPTIONS: dict[str, dict[str, Any]] = {
    "fp16": {"enable_autocast": True, "autocast_low_precision_type": torch.float16},
    "fp32": {"disable_tf32": True},
}


def require_trt(verify: bool = True) -> None:
    """Fail with one line when there is no CUDA GPU or no ``torch_tensorrt``.

    Raises:
        MissingDependencyError: naming what is missing.
    """
    require_tensorrt("format=tensorrt")


def export_tensorrt(model: DepthExportModel, path: Path, spec: ExportSpec) -> None:
    """Compile ``model`` into TensorRT engines for ``spec.batch_size`` × ``spec.height`` ×
    ``spec.width`` inputs in ``spec.precision`` on the current CUDA device and save the
    program to ``path`` (``torch_tensorrt.save``, an ExportedProgram)."""
    import torch_tensorrt

    gpu_model = copy.deepcopy(model).cuda().eval()
    inputs = example_inputs(model, spec.batch_size or 1, spec.height, spec.width, seed=1)
    example = [x.cuda() for x in inputs]
    with torch.no_grad():
        compiled = torch_tensorrt.compile(
            gpu_model,
            ir="dynamo",
            arg_inputs=example,
            **_PRECISION_OPTIONS[spec.precision],
        )
        torch_tensorrt.save(
            compiled, str(path), output_format="exported_program", arg_inputs=example
        )


def verify_tensorrt(
    path: Path,
    model: DepthExportModel,
    spec: ExportSpec,
    batch: int,
    verify: bool,
    tolerance: float,
) -> dict[str, Any]:
    """Load the program back and, with ``verify``, compare its depth (run on the GPU) for a
    random batch of ``batch`` with ``model``'s (PyTorch fp32 on the CPU).

    Returns:
        ``{"opset": None, "verified": None, or the runtime, batch and differences}``.

    Raises:
        ExportError: it cannot be loaded back, or its depth is not within ``tolerance``.
    """
    import torch_tensorrt

    try:
        program = load_tensorrt_program(path)
    except (RuntimeError, ValueError) as err:
        raise unreadable("the TensorRT program cannot be loaded back", err) from err
    result: dict[str, Any] = {"opset": None, "verified": None}
    if verify:
        inputs = example_inputs(model, batch, spec.height, spec.width, seed=2)
        depth = program(*(x.cuda() for x in inputs)).float().cpu().numpy()
        what = f"TensorRT ({spec.precision})"
        result["verified"] = {
            "runtime": (
                f"Torch-TensorRT {torch_tensorrt.__version__} {torch.cuda.get_device_name()}, "
                f"{spec.precision}"
            ),
            "batch": batch,
            **compare_depth(depth, model(*inputs), tolerance, what, CHECKED[spec.precision]),
        }
    return result


TENSORRT = Backend(
    name="tensorrt",
    suffix=".pt2",
    fixed_batch=True,
    dynamic_batch=False,
    export=export_tensorrt,
    verify=verify_tensorrt,
    engine="tensorrt",
    require=require_trt,
    precisions=("fp16", "fp32"),
    quantize_hint=(
        "TensorRT INT8 needs NVIDIA ModelOpt, which this package does not use: export "
        "format=tensorrt precision=fp16, or format=openvino quantize=int8 for a CPU"
    ),
)
