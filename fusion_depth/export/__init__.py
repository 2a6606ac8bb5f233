"""Trained networks as deployable model files, one module per back end, and the engines that
run them.

Every format exports the same :class:`DepthExportModel` (:mod:`.contract`): ``image``
(B, 3, H, W) float32 RGB in [0, 1] and, for ``fusion=concat``/``add`` checkpoints, ``sparse``
(B, 1, H, W) float32 metres (0 = no return), to ``depth`` (B, 1, H, W) float32 metres in
``[min_depth, max_depth]``, by the code path of ``predict`` and ``evaluate``, so exported and
PyTorch predictions agree. H × W is fixed when exporting; the batch axis is dynamic unless fixed
(TensorRT engines always fix it, at 1 by default).

* :mod:`.exporter`: :func:`export_model`, the options, the atomic write, the format registry;
* :mod:`.onnx`, :mod:`.torchscript`, :mod:`.openvino`, :mod:`.tensorrt`: the back ends (each a
  :class:`Backend`);
* :mod:`.verification`: :class:`ExportError`, the tolerances per precision and the comparison
  with PyTorch;
* :mod:`.data`: calibration frames (``quantize=int8``) and the accuracy an export costs;
* :mod:`.sidecar`: ``<model file>.json``, what deployment code feeds the model and gets back;
* :mod:`.runtime`: the engines that run a model file by its sidecar (``evaluate``/``predict
  model_file=``).
"""

from fusion_depth.export.cli import main  # noqa: E402 - the command, after its library
from fusion_depth.export.contract import Backend, DepthExportModel, ExportSpec
from fusion_depth.export.exporter import (
    BACKENDS,
    FORMATS,
    check_export_options,
    check_format,
    default_output,
    export_model,
)
from fusion_depth.export.onnx import require_onnx
from fusion_depth.export.runtime import (
    ENGINES,
    ExportedModel,
    ModelFileError,
    SidecarError,
    load_exported,
    read_sidecar,
)
from fusion_depth.export.sidecar import sidecar_path
from fusion_depth.export.verification import TOLERANCE, TOLERANCES, ExportError

__all__ = [
    "main",
    "BACKENDS",
    "ENGINES",
    "FORMATS",
    "TOLERANCE",
    "TOLERANCES",
    "Backend",
    "DepthExportModel",
    "ExportError",
    "ExportSpec",
    "ExportedModel",
    "ModelFileError",
    "SidecarError",
    "check_export_options",
    "check_format",
    "default_output",
    "export_model",
    "load_exported",
    "read_sidecar",
    "require_onnx",
    "sidecar_path",
]
