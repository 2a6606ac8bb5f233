"""Exporting a network to a model file in any format: the options, the file and its sidecar.

:func:`export_model` checks the options (the input size, a multiple of 32, defaults to the
checkpoint's training resolution; the batch axis is dynamic unless ``batch_size`` fixes it in a
format that can), wraps the network in a :class:`DepthExportModel`, has the format's
:class:`Backend` (:data:`BACKENDS`) write the file under a temporary name in its folder, check and
verify it, and renames it into place only then, so a failed export leaves any earlier file
untouched. Next to it, ``<output>.json`` (:mod:`fusion_depth.exporting.sidecar`) records what
deployment code must feed and gets back.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from fusion_depth.checkpoint import LoadedModel
from fusion_depth.exporting.contract import Backend, DepthExportModel
from fusion_depth.exporting.onnx import ONNX
from fusion_depth.exporting.sidecar import sidecar_contents, sidecar_path
from fusion_depth.exporting.torchscript import TORCHSCRIPT
from fusion_depth.exporting.verification import TOLERANCE
from fusion_depth.models import DepthModel
from fusion_depth.runs import write_atomic, write_text_atomic

# The formats, by their format= value; a new back end is a module with a Backend and a line here.
BACKENDS: dict[str, Backend] = {backend.name: backend for backend in (ONNX, TORCHSCRIPT)}
FORMATS = {name: backend.suffix for name, backend in BACKENDS.items()}
SIZE_MULTIPLE = 32


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


def check_export_options(fmt: Any, height: Any, width: Any, batch_size: Any, verify: bool) -> str:
    """The options :func:`export_model` checks that need no checkpoint, so they fail before a
    (slow) checkpoint load; returns the format.

    Raises:
        ValueError: the format, a size (None = the checkpoint's) or the batch size is invalid.
        ImportError: a package the format needs (with ``verify``, to run it) is missing.
    """
    fmt = check_format(fmt)
    for key, value in (("height", height), ("width", width)):
        if value is not None:
            check_size(key, value)
    check_batch_size(batch_size, fmt)
    BACKENDS[fmt].require(verify)
    return fmt


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
    tolerance: float = TOLERANCE,
    sidecar: bool = True,
) -> Path:
    """Export ``model`` (a checkpoint's :class:`LoadedModel`, or a bare :class:`DepthModel`, which
    then needs ``height``/``width``) to ``output``; returns ``output``.

    ``fmt``: ``onnx`` or ``torchscript``. ``height``/``width``: the input size (multiples of 32),
    default the checkpoint's training resolution. ``batch_size``: None = dynamic batch axis;
    N fixes it (ONNX only). ``opset``: the ONNX opset, None = the exporter's default.
    ``verify``: compare the exported model's depth with PyTorch's on a random input (batch 1,
    so a dynamic batch is exercised at another size than the one traced) and fail above
    ``tolerance`` (relative). ``sidecar``: also write ``<output>.json``. Nothing is written
    unless the export, the ONNX checker and the verification all succeed.

    Raises:
        ValueError: an option is invalid, or ``output`` is a folder or the checkpoint itself.
        ImportError: a package the format needs is missing.
        ExportError: the file fails its checker or its depth is not within ``tolerance``.
        OSError: writing the file failed (any earlier file is left untouched).
    """
    fmt = check_format(fmt)
    height, width = resolve_size(model, height, width)
    batch_size = check_batch_size(batch_size, fmt)
    if not isinstance(tolerance, int | float) or isinstance(tolerance, bool) or tolerance < 0:
        raise ValueError(f"tolerance={tolerance}: expected a number ≥ 0")
    backend = BACKENDS[fmt]
    backend.require(verify)
    output = Path(output).expanduser()
    loaded = model if isinstance(model, LoadedModel) else None
    if loaded is not None and output.resolve() == loaded.path.resolve():
        raise ValueError(f"output={output}: that is ckpt_path; choose another file")
    if output.is_dir():
        raise ValueError(f"output={output}: is a folder; expected a file path")
    wrapper = DepthExportModel(loaded.net if loaded is not None else model)
    verify_batch = batch_size or 1

    def write(tmp: Path) -> None:
        backend.export(wrapper, tmp, height, width, batch_size, opset)

    def check(tmp: Path) -> dict:
        return backend.verify(tmp, wrapper, verify_batch, height, width, verify, tolerance)

    result = write_atomic(output, write, check)
    if sidecar:
        text = json.dumps(
            sidecar_contents(wrapper, loaded, fmt, output, height, width, batch_size, result),
            indent=2,
        )
        write_text_atomic(sidecar_path(output), text + "\n")
    return output


def default_output(ckpt_path: str | os.PathLike, fmt: str, output_dir: str | os.PathLike) -> Path:
    """``<output_dir>/<checkpoint stem>.onnx`` (or ``.pt``)."""
    return Path(output_dir) / f"{Path(ckpt_path).stem}{FORMATS[check_format(fmt)]}"
