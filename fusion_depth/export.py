"""``python -m fusion_depth.export``: a trained checkpoint as a deployable model file.

python -m fusion_depth.export ckpt_path=best.ckpt                       # ONNX, training resolution
python -m fusion_depth.export ckpt_path=best.ckpt format=torchscript height=384 width=1248

The model takes ``image`` (B, 3, H, W) float32 RGB in [0, 1] and, for checkpoints trained with
``fusion=concat`` or ``add``, ``sparse`` (B, 1, H, W) float32 metres (0 = no return), and returns
``depth`` (B, 1, H, W) float32 metres in ``[min_depth, max_depth]``, computed as ``predict`` and
``evaluate`` compute it (:mod:`fusion_depth.exporting`).

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

import json
import logging
from pathlib import Path

from omegaconf import DictConfig

from fusion_depth.checkpoint import load_model
from fusion_depth.cli import hydra_main
from fusion_depth.console import quiet_known_noise
from fusion_depth.exporting import check_export_options, default_output, export_model, sidecar_path

log = logging.getLogger("fusion_depth.export")  # not "__main__" under python -m
quiet_known_noise()


def export(cfg: DictConfig) -> Path:
    """Run a ``conf/export.yaml`` config; returns the model file written."""
    # Option errors before the (slow) checkpoint load; export_model checks them all again.
    fmt = check_export_options(cfg.format, cfg.height, cfg.width, cfg.batch_size, bool(cfg.verify))
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
