"""A trained checkpoint as a deployable model file: ONNX or TorchScript.

python -m fusion_depth.export ckpt_path=best.ckpt                       # ONNX, training resolution
python -m fusion_depth.export ckpt_path=best.ckpt format=torchscript height=384 width=1248

The exported model (:class:`DepthExportModel`) takes ``image`` (B, 3, H, W) float32 RGB in [0, 1]
and, for checkpoints trained with ``fusion=concat`` or ``add``, ``sparse`` (B, 1, H, W) float32
metres (0 = no return), and returns ``depth`` (B, 1, H, W) float32 metres in
``[min_depth, max_depth]``: the network's half-resolution reciprocal output turned into metres
and resized to the input by :func:`fusion_depth.inference.predict_depth`, the code path of
``predict`` and ``evaluate``, so exported and PyTorch predictions agree.

* ``H`` × ``W`` is fixed when exporting: the checkpoint's training resolution, or ``height``/
  ``width`` (multiples of 32). The batch axis is dynamic (ONNX: named ``batch``; TorchScript
  accepts any batch), unless ``batch_size=N`` fixes it in the ONNX graph for runtimes that
  want static shapes.
* ``format=onnx`` uses the ``torch.export``-based exporter of ``torch.onnx.export`` (the default
  since torch 2.9; it needs ``onnxscript``; the TorchScript-based one is deprecated). The file
  is checked with ``onnx.checker`` and, with ``verify=true`` (the default), ONNX Runtime's
  depth for a random input is compared with PyTorch's. Needs ``pip install -e ".[onnx]"``.
* ``format=torchscript`` saves ``torch.jit.trace`` of the model (``torch.jit`` is deprecated
  upstream but still what C++/libtorch deployments load); verified by loading it back.

``output`` (default ``<run dir>/<checkpoint stem>.onnx`` or ``.pt``) is written under a temporary
name in its folder and renamed into place only after it was verified, so a failed export leaves
any earlier file untouched. Next to it, ``<output>.json`` records what deployment code must feed
and gets back: input/output names, shapes and units, the depth range, fusion mode, backbone,
checkpoint, format and opset.
"""

from __future__ import annotations

import contextlib
import copy
import importlib
import json
import logging
import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from torch import nn

from fusion_depth.checkpoint import LoadedModel, load_model
from fusion_depth.cli import hydra_main
from fusion_depth.console import quiet_known_noise
from fusion_depth.inference import predict_depth
from fusion_depth.models import DepthNet
from fusion_depth.runs import write_atomic, write_text_atomic

log = logging.getLogger("fusion_depth.export")  # not "__main__" under python -m
quiet_known_noise()

FORMATS = {"onnx": ".onnx", "torchscript": ".pt"}
ONNX_EXTRA = 'pip install -e ".[onnx]"'
TOLERANCE = 1e-3  # largest relative difference |exported - PyTorch| / PyTorch accepted by verify
SIZE_MULTIPLE = 32


class ExportError(RuntimeError):
    """The export ran but its result is not usable (e.g. it disagrees with PyTorch)."""


class DepthExportModel(nn.Module):
    """``forward(image[, sparse]) -> depth`` in metres at the input resolution, fp32, eval mode.

    Holds its own CPU fp32 copy of the network, so exporting never changes the caller's model.
    """

    def __init__(self, net: DepthNet) -> None:
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


# --------------------------------------------------------------------------- checks


def check_format(fmt: Any) -> str:
    if fmt not in FORMATS:
        raise ValueError(f"format={fmt}: expected one of {list(FORMATS)}")
    return fmt


def _check_size(key: str, value: Any) -> int:
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


def _resolve_size(
    model: LoadedModel | DepthNet, height: int | None, width: int | None
) -> tuple[int, int]:
    """``height``/``width``, or the checkpoint's training resolution where not given."""
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
        size.append(_check_size(key, value))
    return size[0], size[1]


def _check_batch_size(batch_size: Any, fmt: str) -> int | None:
    if batch_size is None:
        return None
    if fmt != "onnx":
        raise ValueError(
            f"batch_size={batch_size}: fixes the batch axis of format=onnx only; a "
            f"format={fmt} model accepts any batch size, drop batch_size="
        )
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(
            f"batch_size={batch_size}: expected null (dynamic batch) or an integer ≥ 1"
        )
    return batch_size


def require_onnx(verify: bool = True) -> None:
    """Fail with one line naming the extra when the ONNX packages are missing."""
    modules = ["onnx", "onnxscript"] + (["onnxruntime"] if verify else [])
    missing = []
    for name in modules:
        try:
            importlib.import_module(name)
        except ImportError:
            missing.append(name)
    if missing:
        raise ImportError(
            f"format=onnx needs {', '.join(missing)}, which {'is' if len(missing) == 1 else 'are'} "
            f"not installed: {ONNX_EXTRA}"
        )


# --------------------------------------------------------------------------- writing files


def sidecar_path(path: str | os.PathLike) -> Path:
    """``<model file>.json``: what deployment code feeds the model and gets back."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def _example_inputs(
    model: DepthExportModel, batch: int, height: int, width: int, seed: int
) -> tuple[torch.Tensor, ...]:
    """A random image in [0, 1] and, for fusion, a sparse map with ~10 % returns (else 0)."""
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


def _compare(exported: np.ndarray, reference: torch.Tensor, tolerance: float, what: str) -> dict:
    """Max absolute (m) and relative difference; raises when over ``tolerance`` (or NaN)."""
    expected = reference.numpy()
    if exported.shape != expected.shape:
        raise ExportError(
            f"{what}: output shape {tuple(exported.shape)}, PyTorch's is {tuple(expected.shape)}"
        )
    diff = np.abs(exported.astype(np.float64) - expected)
    max_abs = float(diff.max())
    max_rel = float((diff / np.abs(expected)).max())  # depth ≥ min_depth > 0
    if not max_rel <= tolerance:  # NaN fails too
        raise ExportError(
            f"{what}: depth differs from PyTorch's by up to {max_abs:.3g} m ({max_rel:.3g} "
            f"relative), more than tolerance={tolerance:g}; the exported model is not faithful "
            "(nothing was written)"
        )
    return {"max_abs_diff_m": max_abs, "max_rel_diff": max_rel}


# --------------------------------------------------------------------------- the two formats


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


def _export_onnx(
    model: DepthExportModel,
    tmp: Path,
    height: int,
    width: int,
    batch_size: int | None,
    opset: int | None,
) -> None:
    # An example batch of 2: torch.export specialises dimensions of size 0 and 1.
    example = _example_inputs(model, batch_size or 2, height, width, seed=1)
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
        program.save(str(tmp), external_data=False)


def _verify_onnx(
    tmp: Path,
    model: DepthExportModel,
    batch: int,
    height: int,
    width: int,
    verify: bool,
    tolerance: float,
) -> dict:
    import onnx

    try:
        onnx.checker.check_model(str(tmp), full_check=True)
    except onnx.checker.ValidationError as err:
        raise ExportError(f"the exported ONNX model fails onnx.checker: {err}") from err
    opset = next(
        (
            o.version
            for o in onnx.load(str(tmp), load_external_data=False).opset_import
            if o.domain in ("", "ai.onnx")
        ),
        None,
    )
    result: dict[str, Any] = {"opset": opset, "verified": None}
    if verify:
        import onnxruntime as ort

        session = ort.InferenceSession(str(tmp), providers=["CPUExecutionProvider"])
        inputs = _example_inputs(model, batch, height, width, seed=2)
        feeds = {name: x.numpy() for name, x in zip(model.input_names, inputs, strict=True)}
        (depth,) = session.run(["depth"], feeds)
        reference = model(*inputs)
        result["verified"] = {
            "runtime": f"onnxruntime {ort.__version__}",
            "batch": batch,
            **_compare(depth, reference, tolerance, "ONNX Runtime"),
        }
    return result


@contextlib.contextmanager
def _quiet_jit() -> Iterator[None]:
    """Hide torch.jit's deprecation notices and the tracer's notes on predict_depth's Python
    branches: they depend on H and W only, which are fixed in the exported model."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        warnings.filterwarnings("ignore", message=r".*`torch\.jit\..*` is deprecated.*")
        yield


def _export_torchscript(model: DepthExportModel, tmp: Path, height: int, width: int) -> None:
    example = _example_inputs(model, 2, height, width, seed=1)
    with _quiet_jit():
        traced = torch.jit.trace(model, example, check_trace=False)
        torch.jit.save(traced, str(tmp))


def _verify_torchscript(
    tmp: Path,
    model: DepthExportModel,
    batch: int,
    height: int,
    width: int,
    verify: bool,
    tolerance: float,
) -> dict:
    with _quiet_jit():
        loaded = torch.jit.load(str(tmp), map_location="cpu")  # also checks the file reads back
        if not verify:
            return {"opset": None, "verified": None}
        inputs = _example_inputs(model, batch, height, width, seed=2)
        with torch.no_grad():
            depth = loaded(*inputs).numpy()
    reference = model(*inputs)
    return {
        "opset": None,
        "verified": {
            "runtime": f"torch.jit {torch.__version__}",
            "batch": batch,
            **_compare(depth, reference, tolerance, "the TorchScript model"),
        },
    }


# --------------------------------------------------------------------------- public entry points


def export_model(
    model: LoadedModel | DepthNet,
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
    """Export ``model`` (a checkpoint's :class:`LoadedModel`, or a bare :class:`DepthNet`, which
    then needs ``height``/``width``) to ``output``; returns ``output``.

    ``fmt``: ``onnx`` or ``torchscript``. ``height``/``width``: the input size (multiples of 32),
    default the checkpoint's training resolution. ``batch_size``: None = dynamic batch axis;
    N fixes it (ONNX only). ``opset``: the ONNX opset, None = the exporter's default.
    ``verify``: compare the exported model's depth with PyTorch's on a random input (batch 1,
    so a dynamic batch is exercised at another size than the one traced) and fail above
    ``tolerance`` (relative). ``sidecar``: also write ``<output>.json``. Nothing is written
    unless the export, the ONNX checker and the verification all succeed.
    """
    fmt = check_format(fmt)
    height, width = _resolve_size(model, height, width)
    batch_size = _check_batch_size(batch_size, fmt)
    if not isinstance(tolerance, int | float) or isinstance(tolerance, bool) or tolerance < 0:
        raise ValueError(f"tolerance={tolerance}: expected a number ≥ 0")
    if fmt == "onnx":
        require_onnx(verify)
    output = Path(output).expanduser()
    loaded = model if isinstance(model, LoadedModel) else None
    if loaded is not None and output.resolve() == loaded.path.resolve():
        raise ValueError(f"output={output}: that is ckpt_path; choose another file")
    if output.is_dir():
        raise ValueError(f"output={output}: is a folder; expected a file path")
    wrapper = DepthExportModel(loaded.net if loaded is not None else model)
    verify_batch = batch_size or 1

    if fmt == "onnx":

        def write(tmp: Path) -> None:
            _export_onnx(wrapper, tmp, height, width, batch_size, opset)

        def check(tmp: Path) -> dict:
            return _verify_onnx(tmp, wrapper, verify_batch, height, width, verify, tolerance)

    else:

        def write(tmp: Path) -> None:
            _export_torchscript(wrapper, tmp, height, width)

        def check(tmp: Path) -> dict:
            return _verify_torchscript(tmp, wrapper, verify_batch, height, width, verify, tolerance)

    result = write_atomic(output, write, check)
    if sidecar:
        text = json.dumps(
            _describe(wrapper, loaded, fmt, output, height, width, batch_size, result), indent=2
        )
        write_text_atomic(sidecar_path(output), text + "\n")
    return output


def _describe(
    model: DepthExportModel,
    loaded: LoadedModel | None,
    fmt: str,
    output: Path,
    height: int,
    width: int,
    batch_size: int | None,
    result: dict,
) -> dict:
    """The sidecar JSON: everything deployment code needs to feed the model and read it."""
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
        "backbone": net.encoder.name,
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


def default_output(ckpt_path: str | os.PathLike, fmt: str, output_dir: str | os.PathLike) -> Path:
    """``<output_dir>/<checkpoint stem>.onnx`` (or ``.pt``)."""
    return Path(output_dir) / f"{Path(ckpt_path).stem}{FORMATS[check_format(fmt)]}"


def export(cfg: DictConfig) -> Path:
    """Run a ``conf/export.yaml`` config; returns the model file written."""
    fmt = check_format(cfg.format)
    # Option errors before the (slow) checkpoint load; export_model checks them all again.
    for key in ("height", "width"):
        if cfg[key] is not None:
            _check_size(key, cfg[key])
    _check_batch_size(cfg.batch_size, fmt)
    if fmt == "onnx":
        require_onnx(bool(cfg.verify))
    output = cfg.output
    if output is None:
        output = default_output(cfg.ckpt_path, fmt, cfg.paths.output_dir)
    loaded = load_model(cfg.ckpt_path)
    path = export_model(
        loaded,
        fmt,
        output,
        cfg.height,
        cfg.width,
        batch_size=cfg.batch_size,
        opset=cfg.opset,
        verify=bool(cfg.verify),
        tolerance=cfg.tolerance,
    )
    info = json.loads(sidecar_path(path).read_text())
    shapes = ", ".join(f"{i['name']} {tuple(i['shape'])}" for i in info["inputs"])
    log.info(
        "exported %s (fusion=%s, backbone=%s) as %s to %s: %s → depth %s in metres",
        loaded.path,
        info["fusion"],
        info["backbone"],
        fmt,
        path,
        shapes,
        tuple(info["outputs"][0]["shape"]),
    )
    checked = info["verified"]
    if checked:
        log.info(
            "verified with %s: depth within %.2g m of PyTorch's (%.2g relative, tolerance %g)",
            checked["runtime"],
            checked["max_abs_diff_m"],
            checked["max_rel_diff"],
            cfg.tolerance,
        )
    log.info("inputs, outputs and depth range described in %s", sidecar_path(path))
    return path


@hydra_main("export")
def main(cfg: DictConfig) -> None:
    export(cfg)


if __name__ == "__main__":
    main()
