"""Exporting a network to a model file in any format: the options, the file and its sidecar.

:func:`export_model` checks the options (the input size, a multiple of 32, defaults to the
checkpoint's training resolution; the batch axis is dynamic unless ``batch_size`` fixes it in a
format that can; the precision and quantization the format offers), wraps the network in a
:class:`DepthExportModel`, reads calibration frames for ``quantize=int8``
(:mod:`fusion_depth.export.data`), has the format's :class:`Backend` (:data:`BACKENDS`)
write the file and its companions under temporary names in its folder, check and verify them
(within the precision's tolerance, :data:`TOLERANCES`), measures the accuracy it costs where
asked (refusing it above ``max_rmse_increase``), and renames them into place only then, so a
failed export leaves any earlier file untouched. Next to it, ``<output>.json``
(:mod:`fusion_depth.export.sidecar`) records what deployment code must feed and gets back.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch

from fusion_depth.export.contract import PRECISIONS, Backend, DepthExportModel, ExportSpec
from fusion_depth.export.data import ExportData, calibration_inputs, compare_accuracy, export_data
from fusion_depth.export.onnx import ONNX
from fusion_depth.export.openvino import OPENVINO, require_nncf
from fusion_depth.export.runtime import ModelInfo, cpu_has_bf16, open_exported
from fusion_depth.export.sidecar import sidecar_contents, sidecar_path
from fusion_depth.export.tensorrt import TENSORRT
from fusion_depth.export.torchscript import TORCHSCRIPT
from fusion_depth.export.verification import TOLERANCES, ExportError
from fusion_depth.models import DepthModel
from fusion_depth.runner.checkpoints import LoadedModel
from fusion_depth.utils.atomic import write_atomic, write_text_atomic

log = logging.getLogger(__name__)

# The formats, by their format= value; a new back end is a module with a Backend and a line here.
BACKENDS: dict[str, Backend] = {
    backend.name: backend for backend in (ONNX, TORCHSCRIPT, OPENVINO, TENSORRT)
}
FORMATS = {name: backend.suffix for name, backend in BACKENDS.items()}
SIZE_MULTIPLE = 32
PRECISION_CHOICES = ("auto", *PRECISIONS)
MEASURE_CHOICES = ("auto", True, False)
CALIBRATION_FRAMES = 300  # NNCF's default subset size


def check_format(fmt: Any) -> str:
    """``fmt`` when it names a format of :data:`FORMATS`.

    Raises:
        ValueError: it does not.
    """
    if fmt not in FORMATS:
        raise ValueError(f"format={fmt}: expected one of {list(FORMATS)}")
    return fmt


def check_size(key: str, value: Any) -> int:
    """``value`` of ``height``/``width`` (``key``) when it is a positive multiple of 32 pixels.

    Raises:
        ValueError: it is not; the message suggests the nearest multiples.
    """
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{key}={value}: expected a positive multiple of {SIZE_MULTIPLE}")
    if value % SIZE_MULTIPLE:
        low = value // SIZE_MULTIPLE * SIZE_MULTIPLE
        hint = f"{low} or {low + SIZE_MULTIPLE}" if low else str(SIZE_MULTIPLE)
        raise ValueError(
            f"{key}={value}: expected a multiple of {SIZE_MULTIPLE} (the encoder's stride), "
            f"e.g. {key}={hint}"
        )
    return value


def resolve_size(
    model: LoadedModel | DepthModel, height: int | None, width: int | None
) -> tuple[int, int]:
    """``height``/``width`` in pixels, or the checkpoint's training resolution where not given.

    Raises:
        ValueError: a size is not a positive multiple of 32, or is None and ``model`` records
            none (a bare :class:`DepthModel` never does).
    """
    dataset = (model.config.get("dataset") or {}) if isinstance(model, LoadedModel) else {}
    size = []
    for key, value in (("height", height), ("width", width)):
        if value is None:
            value = dataset.get(key)
            if value is None:
                where = (
                    f"ckpt_path={model.path} records no dataset.{key}"
                    if isinstance(model, LoadedModel)
                    else "a bare network has no training resolution"
                )
                raise ValueError(f"{key}=null: {where}; pass {key}=<multiple of 32>")
        size.append(check_size(key, value))
    return size[0], size[1]


def check_batch_size(batch_size: Any, fmt: str) -> int | None:
    """``batch_size``: None (a dynamic batch axis) or an integer ≥ 1 for a format that can fix
    its batch axis.

    Raises:
        ValueError: it is neither, or ``fmt`` accepts any batch size anyway.
    """
    if batch_size is None:
        return None
    if not BACKENDS[fmt].fixed_batch:
        fixed = ", ".join(f"format={name}" for name, b in BACKENDS.items() if b.fixed_batch)
        raise ValueError(
            f"batch_size={batch_size}: fixes the batch axis of {fixed} only; a "
            f"format={fmt} model accepts any batch size, drop batch_size="
        )
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(
            f"batch_size={batch_size}: expected null (dynamic batch) or an integer ≥ 1"
        )
    return batch_size


def resolve_export_precision(precision: Any, fmt: str) -> str:
    """``precision`` (``auto``, ``fp32``, ``bf16``, ``fp16``) of a ``fmt`` file, resolved:
    ``auto`` is fp16 for a GPU format (TensorRT: every GPU it runs on computes fp16), bf16
    where the format can run in it and this CPU computes it natively (OpenVINO's
    ``OPTIMIZATION_CAPABILITIES``), else fp32.

    Raises:
        ValueError: not a choice, or a precision the format cannot run in.
    """
    if precision not in PRECISION_CHOICES:
        raise ValueError(f"precision={precision}: expected one of {list(PRECISION_CHOICES)}")
    backend = BACKENDS[fmt]
    if precision == "auto":
        if "fp16" in backend.precisions:
            return "fp16"
        return "bf16" if "bf16" in backend.precisions and cpu_has_bf16() else "fp32"
    if precision not in backend.precisions:
        can = [name for name, b in BACKENDS.items() if precision in b.precisions]
        raise ValueError(
            f"precision={precision}: format={fmt} runs in {', '.join(backend.precisions)} only; "
            f"precision={precision} is for format={' or '.join(can)}"
        )
    return precision


def check_quantize(quantize: Any, fmt: str) -> str | None:
    """``quantize``: None, or a quantization ``fmt`` offers (``int8`` for OpenVINO).

    Raises:
        ValueError: it is neither.
        ImportError: the package it needs (NNCF) is missing.
    """
    if quantize is None:
        return None
    backend = BACKENDS[fmt]
    if quantize not in backend.quantizations:
        offer = [name for name, b in BACKENDS.items() if quantize in b.quantizations]
        known = sorted({q for b in BACKENDS.values() for q in b.quantizations})
        instead = backend.quantize_hint or f"use format={' or '.join(offer)}"
        raise ValueError(
            f"quantize={quantize}: format={fmt} offers no quantization; {instead}"
            if offer
            else f"quantize={quantize}: expected null or one of {known}"
        )
    require_nncf()
    return quantize


def check_accuracy_options(measure: Any, max_rmse_increase: Any, quantize: str | None) -> bool:
    """Whether to measure the accuracy the export costs: ``measure`` true/false, or ``auto``
    (on for a quantized export); ``max_rmse_increase`` (metres, or None) needs it measured.

    Raises:
        ValueError: ``measure`` is not a choice, ``max_rmse_increase`` is not a number, or
            it is given with ``measure_accuracy=false``.
    """
    if measure not in MEASURE_CHOICES or (measure in (0, 1) and not isinstance(measure, bool)):
        raise ValueError(f"measure_accuracy={measure}: expected auto, true or false")
    if max_rmse_increase is not None and (
        isinstance(max_rmse_increase, bool) or not isinstance(max_rmse_increase, int | float)
    ):
        raise ValueError(f"max_rmse_increase={max_rmse_increase}: expected metres or null")
    if max_rmse_increase is not None and measure is False:
        raise ValueError(
            f"max_rmse_increase={max_rmse_increase} needs the accuracy measured; drop "
            "measure_accuracy=false"
        )
    return measure is True or (
        measure == "auto" and (quantize is not None or max_rmse_increase is not None)
    )


def check_export_options(
    fmt: Any,
    height: Any,
    width: Any,
    batch_size: Any,
    verify: bool,
    precision: Any = "auto",
    quantize: Any = None,
    measure_accuracy: Any = "auto",
    max_rmse_increase: Any = None,
) -> str:
    """The options :func:`export_model` checks that need no checkpoint, so they fail before a
    (slow) checkpoint load; returns the format.

    Raises:
        ValueError: the format, a size (None = the checkpoint's), the batch size, precision,
            quantization or accuracy options are invalid.
        ImportError: a package the format needs (with ``verify``, to run it) is missing.
    """
    fmt = check_format(fmt)
    for key, value in (("height", height), ("width", width)):
        if value is not None:
            check_size(key, value)
    check_batch_size(batch_size, fmt)
    BACKENDS[fmt].require(verify)
    resolve_export_precision(precision, fmt)
    quantize = check_quantize(quantize, fmt)
    check_accuracy_options(measure_accuracy, max_rmse_increase, quantize)
    return fmt


def check_tolerance(tolerance: Any, computes_in: str) -> float:
    """``tolerance`` (relative), or the default of the precision the file computes in
    (:data:`TOLERANCES`) where None.

    Raises:
        ValueError: not a number ≥ 0.
    """
    if tolerance is None:
        return TOLERANCES[computes_in]
    if not isinstance(tolerance, int | float) or isinstance(tolerance, bool) or tolerance < 0:
        raise ValueError(f"tolerance={tolerance}: expected a number ≥ 0 (or null: the default)")
    return float(tolerance)


def check_calibration(
    calibration: Sequence[tuple[torch.Tensor, ...]],
    quantize: str | None,
    model: DepthExportModel,
    height: int,
    width: int,
) -> list[tuple[torch.Tensor, ...]]:
    """Calibration frames given to :func:`export_model`, checked: ``quantize`` is set, and each
    frame holds ``model``'s inputs, batch 1, at ``height`` × ``width``.

    Raises:
        ValueError: naming what is wrong.
    """
    if quantize is None:
        raise ValueError("calibration frames were given without quantize=int8; drop them")
    frames = [tuple(frame) for frame in calibration]
    expected = [(1, 3, height, width), (1, 1, height, width)][: len(model.input_names)]
    if not frames:
        raise ValueError(f"quantize={quantize}: no calibration frames")
    for i, frame in enumerate(frames):
        shapes = [tuple(x.shape) for x in frame]
        if shapes != expected:
            raise ValueError(
                f"quantize={quantize}: calibration frame {i} has shapes {shapes}; the model "
                f"takes {model.input_names} of shapes {expected}"
            )
    return frames


def export_model(
    model: LoadedModel | DepthModel,
    fmt: str,
    output: str | os.PathLike,
    height: int | None = None,
    width: int | None = None,
    *,
    batch_size: int | None = None,
    opset: int | None = None,
    verify: bool = True,
    tolerance: float | None = None,
    sidecar: bool = True,
    precision: str = "auto",
    quantize: str | None = None,
    calibration_frames: int = CALIBRATION_FRAMES,
    measure_accuracy: bool | str = "auto",
    max_rmse_increase: float | None = None,
    dataset: Mapping[str, Any] | None = None,
    eval_batch_size: int = 4,
    calibration: Sequence[tuple[torch.Tensor, ...]] | None = None,
) -> Path:
    """Export ``model`` (a checkpoint's :class:`LoadedModel`, or a bare :class:`DepthModel`, which
    then needs ``height``/``width``) to ``output``; returns ``output``.

    ``fmt``: ``onnx``, ``torchscript``, ``openvino`` (``output`` then ends in ``.xml``; its
    weights go to the ``.bin`` beside it) or ``tensorrt`` (``.pt2``; needs a CUDA GPU).
    ``height``/``width``: the input size (multiples of 32), default the checkpoint's training
    resolution. ``batch_size``: None = dynamic batch axis (TensorRT: 1); N fixes it (ONNX,
    OpenVINO, TensorRT). ``opset``: the ONNX opset, None = the exporter's default.
    ``precision``: what the file runs in, ``auto`` (TensorRT: fp16; else bf16 where the format
    and this CPU can, else fp32), ``fp32``, ``bf16`` (OpenVINO) or ``fp16`` (TensorRT).
    ``quantize``: None or ``int8`` (OpenVINO, NNCF), calibrated on ``calibration_frames``
    frames of the training split (all of them when it has fewer), or on ``calibration`` where
    given: the frames themselves, each a tuple of the model's inputs (``image`` (1, 3, H, W)
    in [0, 1] and, for fusion, ``sparse`` (1, 1, H, W) metres); the sidecar then records no
    dataset. ``verify``: compare the exported model's depth with PyTorch's on a random input
    (batch 1, so a dynamic batch is exercised at another size than the one traced) and fail
    above ``tolerance`` (relative; None = the precision's, :data:`TOLERANCES`).
    ``measure_accuracy``: score the exported file and the PyTorch fp32 network on the
    validation split and record the paired per-image differences of RMSE and δ1 with 95 %
    bootstrap intervals in the sidecar (``auto``: when quantizing or with
    ``max_rmse_increase``). ``max_rmse_increase`` (metres): refuse the export when the mean
    per-image RMSE increase (the point estimate) exceeds it. ``dataset``: the dataset block to
    calibrate and measure on (a resolved ``dataset=`` choice), None = the checkpoint's.
    ``eval_batch_size``: the batch size of the accuracy measurement. ``sidecar``: also write
    ``<output>.json``. Nothing is written unless the export, the checks, the verification and
    the accuracy bound all pass.

    Raises:
        ValueError: an option is invalid, or ``output`` is a folder, the checkpoint itself, or
            (for a format with companion files) does not end in the format's suffix.
        ImportError: a package the format needs is missing.
        ExportError: the file fails its checker, its depth is not within ``tolerance``, or it
            costs more than ``max_rmse_increase`` of RMSE.
        OSError: writing the file failed (any earlier file is left untouched).
    """
    spec = _check_spec(model, fmt, height, width, batch_size, opset, verify, precision, quantize)
    backend = BACKENDS[fmt]
    measuring = check_accuracy_options(measure_accuracy, max_rmse_increase, spec.quantize)
    tolerance = check_tolerance(tolerance, spec.computes_in)
    loaded = model if isinstance(model, LoadedModel) else None
    output = _check_output(output, loaded, backend)
    wrapper = DepthExportModel(loaded.net if loaded is not None else model)
    spec, extra, measure_on = _prepare_data(
        model, wrapper, spec, calibration, calibration_frames, measuring, dataset, eval_batch_size
    )
    target = _Target(wrapper, loaded, backend, output, spec)

    def check(tmp: Path) -> dict[str, Any]:
        """The checks the file must pass before it is renamed into place."""
        return _check_file(tmp, target, verify, tolerance, extra, measure_on, max_rmse_increase)

    result = write_atomic(
        output, target.write, check, suffix=backend.suffix, companions=backend.companions
    )
    if sidecar:
        text = json.dumps(target.sidecar(result), indent=2)
        write_text_atomic(sidecar_path(output), text + "\n")
    return output


@dataclass(frozen=True)
class _Target:
    """What an export writes where: the network, its checkpoint, back end, file and spec."""

    wrapper: DepthExportModel
    loaded: LoadedModel | None
    backend: Backend
    output: Path
    spec: ExportSpec

    def write(self, tmp: Path) -> None:
        """Write the model file (and its companions) at the temporary path ``tmp``."""
        self.backend.export(self.wrapper, tmp, self.spec)

    def sidecar(self, result: dict[str, Any]) -> dict[str, Any]:
        """The sidecar JSON of the file, given what :func:`_check_file` returned."""
        return sidecar_contents(
            self.wrapper, self.loaded, self.backend, self.output, self.spec, result
        )


def _check_spec(
    model: LoadedModel | DepthModel,
    fmt: Any,
    height: Any,
    width: Any,
    batch_size: Any,
    opset: int | None,
    verify: bool,
    precision: Any,
    quantize: Any,
) -> ExportSpec:
    """The format, size, batch axis, precision and quantization, checked, as what to export."""
    fmt = check_format(fmt)
    height, width = resolve_size(model, height, width)
    batch_size = check_batch_size(batch_size, fmt)
    backend = BACKENDS[fmt]
    backend.require(verify)
    if batch_size is None and not backend.dynamic_batch:
        batch_size = 1  # its files fix the batch axis; model_file= runs any batch in chunks
    precision = resolve_export_precision(precision, fmt)
    quantize = check_quantize(quantize, fmt)
    return ExportSpec(height, width, batch_size, opset, precision, quantize)


def _check_output(output: str | os.PathLike, loaded: LoadedModel | None, backend: Backend) -> Path:
    """``output`` as a path, checked: not the checkpoint, not a folder, the format's suffix."""
    output = Path(output).expanduser()
    if loaded is not None and output.resolve() == loaded.path.resolve():
        raise ValueError(f"output={output}: that is ckpt_path; choose another file")
    if output.is_dir():
        raise ValueError(f"output={output}: is a folder; expected a file path")
    # A companion goes beside the file with the file's stem, so the suffix must be the format's.
    if backend.companions and output.suffix != backend.suffix:
        raise ValueError(
            f"output={output}: a format={backend.name} model file ends in {backend.suffix} (its "
            f"{', '.join(backend.companions)} goes beside it), e.g. "
            f"output={output.with_suffix(backend.suffix)}"
        )
    return output


def _prepare_data(
    model: LoadedModel | DepthModel,
    wrapper: DepthExportModel,
    spec: ExportSpec,
    calibration: Sequence[tuple[torch.Tensor, ...]] | None,
    calibration_frames: int,
    measuring: bool,
    dataset: Mapping[str, Any] | None,
    eval_batch_size: int,
) -> tuple[ExportSpec, dict[str, Any], ExportData | None]:
    """The spec with its calibration frames, its quantization block, and the data to measure."""
    quantize, height, width = spec.quantize, spec.height, spec.width
    if calibration is not None:
        calibration = check_calibration(calibration, quantize, wrapper, height, width)
    extra: dict[str, Any] = {}
    data = None
    # Given frames need no dataset to calibrate on; measuring still needs its validation split.
    if (quantize is not None and calibration is None) or measuring:
        data = export_data(model, dataset, eval_batch_size)
    if quantize is not None:
        if calibration is not None:
            frames, source = calibration, {"dataset": None, "split": None}
        else:
            frames, _ = calibration_inputs(
                data, calibration_frames, height, width, wrapper.uses_sparse
            )
            source = {"dataset": data.name, "split": "train"}
        spec = replace(spec, calibration=frames)
        extra["quantization"] = {
            "mode": quantize,
            "calibration": {**source, "frames": len(frames)},
        }
        log.info(
            "quantize=%s: calibrating on %d %s frames",
            quantize,
            len(frames),
            f"{data.name} train" if calibration is None else "given",
        )
    return spec, extra, data if measuring else None


def _check_file(
    tmp: Path,
    target: _Target,
    verify: bool,
    tolerance: float,
    extra: dict[str, Any],
    measure_on: ExportData | None,
    max_rmse_increase: float | None,
) -> dict[str, Any]:
    """The file's verification (with ``extra``) and, on ``measure_on``, the accuracy it costs."""
    backend, wrapper, spec = target.backend, target.wrapper, target.spec
    # Batch 1 where the axis is dynamic: a size other than the one traced.
    verified = backend.verify(tmp, wrapper, spec, spec.batch_size or 1, verify, tolerance)
    result = {**verified, **extra}
    if measure_on is not None:
        result["accuracy"] = _measure_accuracy(tmp, target, result, measure_on, max_rmse_increase)
    return result


def _measure_accuracy(
    tmp: Path,
    target: _Target,
    result: dict[str, Any],
    data: ExportData,
    max_rmse_increase: float | None,
) -> dict[str, Any]:
    """The file's accuracy against the network's on ``data``; ExportError above the bound."""
    # Run by the engine deployment code would use, as its sidecar describes it.
    contents = target.sidecar(result)
    exported = open_exported(ModelInfo.from_sidecar(contents, tmp, sidecar_path(target.output)))
    accuracy = compare_accuracy(target.wrapper.net, exported, data)
    accuracy["max_rmse_increase"] = max_rmse_increase
    increase = accuracy["rmse"]["diff"]
    if max_rmse_increase is not None and not increase["mean"] <= max_rmse_increase:
        raise ExportError(
            f"max_rmse_increase={max_rmse_increase:g}: the export raises RMSE by "
            f"{increase['mean']:+.3g} m per {accuracy['split']} image "
            f"(95 % CI {increase['low']:+.3g} to {increase['high']:+.3g}, "
            f"{accuracy['images']} images of {accuracy['dataset']}); refused, nothing "
            "was written"
        )
    return accuracy


def default_output(ckpt_path: str | os.PathLike, fmt: str, output_dir: str | os.PathLike) -> Path:
    """``<output_dir>/<checkpoint stem><the format's suffix>`` (``.onnx``, ``.pt``, ``.xml``,
    ``.pt2``)."""
    return Path(output_dir) / f"{Path(ckpt_path).stem}{FORMATS[check_format(fmt)]}"
