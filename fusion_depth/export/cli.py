"""``python -m fusion_depth.export``: a trained checkpoint as a deployable model file.

python -m fusion_depth.export ckpt_path=best.ckpt                       # ONNX, training resolution
python -m fusion_depth.export ckpt_path=best.ckpt format=torchscript height=384 width=1248
python -m fusion_depth.export ckpt_path=best.ckpt format=openvino    # IR, bf16 where the CPU has it
python -m fusion_depth.export ckpt_path=best.ckpt format=openvino quantize=int8   # NNCF int8
python -m fusion_depth.export ckpt_path=best.ckpt format=tensorrt precision=fp16  # a CUDA GPU

The model takes ``image`` (B, 3, H, W) float32 RGB in [0, 1] and, for checkpoints trained with
``fusion=concat`` or ``add``, ``sparse`` (B, 1, H, W) float32 metres (0 = no return), and returns
``depth`` (B, 1, H, W) float32 metres in ``[min_depth, max_depth]``, computed as ``predict`` and
``evaluate`` compute it (:func:`fusion_depth.models.inference.predict_depth`).

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
* ``format=openvino`` converts it with ``openvino.convert_model`` to an IR (``.xml`` + ``.bin``,
  fp32 weights) that runs in ``precision`` (``auto``: bf16 where the CPU has it, else fp32),
  recorded in the sidecar and used by the runtime (``INFERENCE_PRECISION_HINT``).
  ``quantize=int8`` quantizes it with NNCF, calibrated on ``calibration_frames`` frames of the
  checkpoint's training split. Needs ``pip install -e ".[openvino]"``.
* ``format=tensorrt`` compiles it with Torch-TensorRT's dynamo path into TensorRT engines for
  this machine's GPU (``precision``: ``auto``/``fp16`` or ``fp32``; batch fixed, 1 by default),
  saved as an ExportedProgram (``.pt2``) and verified on the GPU. Needs a CUDA GPU and ``pip
  install -e ".[tensorrt]"``; without either it is refused in one line before anything is done.
* ``verify`` compares the file's depth on a random input with PyTorch's, within ``tolerance``
  (null: the precision's, :data:`fusion_depth.export.TOLERANCES`).
* ``measure_accuracy`` (``auto``: on for ``quantize`` and ``max_rmse_increase``) scores the file
  and the checkpoint (PyTorch fp32) on the validation split and records the paired per-image
  differences of RMSE and δ1 with 95 % bootstrap intervals in the sidecar's ``accuracy``;
  ``max_rmse_increase=<m>`` refuses an export whose mean RMSE increase is larger.

``output`` (default ``<run dir>/<checkpoint stem>.onnx``, ``.pt``, ``.xml`` or ``.pt2``) is
written under a temporary name in its folder (with its ``.bin`` for OpenVINO) and renamed into
place only after it was verified (and its accuracy accepted), so a failed export leaves any
earlier file untouched. Next to it, ``<output>.json`` records what deployment code must feed
and gets back: input/output names, shapes and units, the depth range, fusion mode, backbone,
checkpoint, format, engine, precision, quantization and opset, and the dataset and run identity
that ``evaluate``/``predict model_file=`` use.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from fusion_depth.config.hydra_main import hydra_main
from fusion_depth.export.exporter import check_export_options, default_output, export_model
from fusion_depth.export.sidecar import sidecar_path
from fusion_depth.runner.checkpoints import load_model
from fusion_depth.utils.console import quiet_known_noise

log = logging.getLogger(__name__)
quiet_known_noise()


def export(cfg: DictConfig) -> Path:
    """Run a ``conf/export.yaml`` config; returns the model file written."""
    # Option errors before the (slow) checkpoint load; export_model checks them all again.
    fmt = check_export_options(
        cfg.format,
        cfg.height,
        cfg.width,
        cfg.batch_size,
        bool(cfg.verify),
        cfg.precision,
        cfg.quantize,
        cfg.measure_accuracy,
        cfg.max_rmse_increase,
    )
    output = cfg.output
    if output is None:
        output = default_output(cfg.ckpt_path, fmt, cfg.paths.output_dir)
    # Resolved here: once detached from the root config its ${...} references could not be.
    chosen = OmegaConf.to_container(cfg.dataset, resolve=True) if cfg.get("dataset") else None
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
        precision=cfg.precision,
        quantize=cfg.quantize,
        calibration_frames=cfg.calibration_frames,
        measure_accuracy=cfg.measure_accuracy,
        max_rmse_increase=cfg.max_rmse_increase,
        dataset=chosen,
        eval_batch_size=cfg.eval_batch_size,
    )
    _log_export(loaded.path, fmt, path)
    return path


def _log_export(ckpt_path: Path, fmt: str, path: Path) -> None:
    """Log what the model file ``path`` takes and gives, as its sidecar records it."""
    # The sidecar, not the arguments: it is what deployment code will read.
    info = json.loads(sidecar_path(path).read_text())
    shapes = ", ".join(f"{i['name']} {tuple(i['shape'])}" for i in info["inputs"])
    computes = (info["quantization"] or {}).get("mode") or info["precision"]
    log.info(
        "exported %s (fusion=%s, backbone=%s) as %s to %s: %s → depth %s in metres, computed in %s",
        ckpt_path,
        info["fusion"],
        info["backbone"],
        fmt,
        path,
        shapes,
        tuple(info["outputs"][0]["shape"]),
        computes,
    )
    checked = info["verified"]
    if checked:
        _log_verification(checked)
    accuracy = info["accuracy"]
    if accuracy:
        _log_accuracy(accuracy)
    log.info("inputs, outputs and depth range described in %s", sidecar_path(path))


def _log_verification(checked: dict[str, Any]) -> None:
    """Log how close the file's depth came to PyTorch's (the sidecar's ``verified``)."""
    log.info(
        "verified with %s: depth within %.2g m of PyTorch's (relative: max %.2g, mean %.2g; "
        "tolerance %g on the %s)",
        checked["runtime"],
        checked["max_abs_diff_m"],
        checked["max_rel_diff"],
        checked["mean_rel_diff"],
        checked["tolerance"],
        "mean" if checked["checked"] == "mean_rel_diff" else "max",
    )


def _log_accuracy(accuracy: dict[str, Any]) -> None:
    """Log the RMSE and δ1 the file costs against PyTorch fp32 (the sidecar's ``accuracy``)."""
    for metric, unit in (("rmse", " m"), ("delta1", "")):
        values = accuracy[metric]
        diff = values["diff"]
        log.info(
            "%s on %d %s images of %s: %.4g%s exported vs %.4g%s in PyTorch fp32, per-image "
            "difference %+.3g [%+.3g, %+.3g] (95 %% CI)",
            metric,
            accuracy["images"],
            accuracy["split"],
            accuracy["dataset"],
            values["exported"],
            unit,
            values["reference"],
            unit,
            diff["mean"],
            diff["low"],
            diff["high"],
        )


@hydra_main("export")
def main(cfg: DictConfig) -> None:
    export(cfg)
