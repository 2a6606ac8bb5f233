"""Running exported model files: a table of engines, each loading a model file by its sidecar.

``evaluate model_file=`` and ``predict model_file=`` run an exported file where they would run a
checkpoint's network. :func:`load_exported` reads ``<model file>.json`` (the sidecar
:mod:`fusion_depth.export.sidecar` writes; plain JSON, checked key by key), looks its engine
up by name in :data:`ENGINES` and wraps the running file in an :class:`ExportedModel`, a
:class:`~fusion_depth.models.DepthModel` whose output is depth in metres. The evaluation loop
(:class:`~fusion_depth.runner.module.DepthModule`), the metrics, tables and ``per_image.csv``
are then the checkpoint's, unchanged.

Engines (one entry of :data:`ENGINES` each):

* ``onnxruntime``: ``.onnx`` files, ONNX Runtime's CPU provider;
* ``torchscript``: ``.pt`` files, ``torch.jit.load``. A TorchScript file is a program (TorchScript
  code, not arbitrary Python): load only files you exported, as with any model file;
* ``openvino``: ``.xml`` + ``.bin`` IR, compiled for the CPU with the sidecar's ``precision``
  as ``INFERENCE_PRECISION_HINT`` (bf16 falls back to fp32, with a warning, on a CPU without
  it; the engine identity says which ran);
* ``tensorrt``: ``.pt2`` files, Torch-TensorRT programs (``torch.export.load(...).module()``) run
  on the CUDA GPU, in the precision they were built for. Loading one unpickles it
  (``torch.export.load`` warns so itself): load only files you exported, as with TorchScript.
  Needs a CUDA GPU and ``pip install -e ".[tensorrt]"``.

Nothing read from disk becomes code: the sidecar is parsed as JSON and its values are checked
(types, ranges, known names); the engine and the dataset reader are chosen by name from the
package's own tables, and the model file is the path given, never one the sidecar names.
"""

from __future__ import annotations

import functools
import logging
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from fusion_depth.errors import ConfigError, UserError
from fusion_depth.export.contract import QUANTIZATIONS, require_cuda, require_modules
from fusion_depth.export.sidecar import sidecar_path
from fusion_depth.export.torchscript import quiet_jit
from fusion_depth.models import DepthModel
from fusion_depth.models.fusion import FUSION_MODES, InputMode
from fusion_depth.runner.checkpoints import LoadedModel, check_expected
from fusion_depth.utils.checkpoint_file import check_no_code
from fusion_depth.utils.json_file import read_json

log = logging.getLogger(__name__)

OPENVINO_EXTRA = 'pip install -e ".[openvino]"'
ONNX_EXTRA = 'pip install -e ".[onnx]"'
TENSORRT_EXTRA = 'pip install -e ".[tensorrt]"'
# What ran the network of a checkpoint (the run record's ``engine`` of ``evaluate ckpt_path=``).
TORCH_ENGINE = "torch"


_REQUIRED = object()  # get()'s default: the key must be there


class ModelFileError(ValueError, UserError):
    """A model file its engine cannot load (truncated, or its weights missing), or whose
    inputs differ from what its sidecar says; the one-line message names the file."""


class SidecarError(ValueError, UserError):
    """A model file's sidecar that is missing, not JSON, or has a missing or wrong key; the
    one-line message names the file and the key."""


# --------------------------------------------------------------------------- the sidecar


@dataclass(frozen=True)
class ModelInfo:
    """What a sidecar says about its model file, checked.

    Attributes:
        path: the model file (the path given, not the sidecar's ``file``).
        sidecar: the sidecar's path.
        format: the export format (``onnx``, ``torchscript``, ``openvino``, ``tensorrt``).
        engine: the name of the engine in :data:`ENGINES` that runs it.
        fusion: the fusion mode; ``input_names`` says whether ``sparse`` is fed.
        input_names: ``["image"]`` or ``["image", "sparse"]``, in the file's order.
        height, width: the input size in pixels, fixed in the file.
        batch_size: None = any batch; N = the file takes batches of exactly N.
        min_depth, max_depth: the depth range in metres the output is clipped to.
        precision: the inference precision it is meant to run in (``fp32``, ``bf16``,
            ``fp16``: one its engine runs).
        quantization: None or ``int8``.
        backbone, model: the network's encoder and model name (None where not recorded).
        checkpoint: the checkpoint exported (None: a bare network).
        dataset_config: the checkpoint's dataset block (plain data), None where not recorded.
        run: the training run's identity (plain data), None where not recorded.
    """

    path: Path
    sidecar: Path
    format: str
    engine: str
    fusion: str
    input_names: tuple[str, ...]
    height: int
    width: int
    batch_size: int | None
    min_depth: float
    max_depth: float
    precision: str = "fp32"
    quantization: str | None = None
    backbone: str | None = None
    model: str | None = None
    checkpoint: str | None = None
    dataset_config: dict[str, Any] | None = field(default=None, repr=False)
    run: dict[str, Any] | None = field(default=None, repr=False)

    @property
    def uses_sparse(self) -> bool:
        return "sparse" in self.input_names

    @classmethod
    def from_sidecar(cls, data: Any, path: Path, sidecar: Path) -> ModelInfo:
        """The info in ``data`` (the parsed sidecar ``sidecar`` of model file ``path``).

        Raises:
            SidecarError: a key is missing or has a value of the wrong type or range, or the
                format or engine is not one of the package's; the message names the file and
                the key.
        """
        where = str(sidecar)
        if not isinstance(data, dict):
            raise SidecarError(f"{where}: expected a JSON object, got a {type(data).__name__}")
        check_no_code(data, sidecar, "", "a sidecar", "fusion_depth.export")
        get = _sidecar_getter(data, where)
        fmt, engine = _read_engine(get, where)
        fusion = get("fusion", (str,), f"one of {list(FUSION_MODES)}")
        if fusion not in FUSION_MODES:
            raise SidecarError(
                f"{where}: key 'fusion' is {fusion!r}; expected one of {list(FUSION_MODES)}"
            )
        min_depth, max_depth = _read_depth_range(get, where)
        names, batch, height, width = _read_inputs(get, where, fusion)
        can_run = ENGINES[engine].precisions
        precision = get("precision", (str,), f"one of {list(can_run)}", "fp32")
        if precision not in can_run:
            raise SidecarError(
                f"{where}: key 'precision' is {precision!r}; engine {engine!r} runs {list(can_run)}"
            )
        quantization = _read_quantization(get, where)
        optional_text = "a string or null"
        return cls(
            path=path,
            sidecar=sidecar,
            format=fmt,
            engine=engine,
            fusion=fusion,
            input_names=tuple(names),
            height=height,
            width=width,
            batch_size=batch if isinstance(batch, int) else None,
            min_depth=min_depth,
            max_depth=max_depth,
            precision=precision,
            quantization=quantization,
            backbone=get("backbone", (str, type(None)), optional_text, None),
            model=get("model", (str, type(None)), optional_text, None),
            checkpoint=get("checkpoint", (str, type(None)), optional_text, None),
            dataset_config=get("dataset_config", (dict, type(None)), "an object or null", None),
            run=get("run", (dict, type(None)), "an object or null", None),
        )


# ``get(key, kinds, expected, default)`` of :func:`_sidecar_getter`: a sidecar's checked value.
_Getter = Callable[..., Any]


def _sidecar_getter(data: dict[str, Any], where: str) -> _Getter:
    """``get(key, kinds, expected, default)``: a key of sidecar ``where``'s ``data``, checked."""

    def get(key: str, kinds: tuple[type, ...], expected: str, default: Any = _REQUIRED) -> Any:
        """``data[key]`` if it is one of ``kinds`` (JSON's true is no number), else
        ``default``, or a SidecarError naming the key."""
        if key not in data:
            if default is not _REQUIRED:
                return default
            raise SidecarError(
                f"{where}: no key {key!r} (expected {expected}); export the model again "
                "with python -m fusion_depth.export"
            )
        value = data[key]
        if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
            raise SidecarError(f"{where}: key {key!r} is {value!r}; expected {expected}")
        return value

    return get


def _read_engine(get: _Getter, where: str) -> tuple[str, str]:
    """The sidecar's format and engine: known, and the engine runs the format."""
    fmt = get("format", (str,), f"one of {sorted(FORMAT_ENGINES)}")
    if fmt not in FORMAT_ENGINES:
        raise SidecarError(
            f"{where}: key 'format' is {fmt!r}; expected one of {sorted(FORMAT_ENGINES)}"
        )
    # A sidecar written before engines had names: its format's engine.
    engine = get("engine", (str,), f"one of {sorted(ENGINES)}", FORMAT_ENGINES[fmt])
    if engine not in ENGINES:
        raise SidecarError(
            f"{where}: key 'engine' is {engine!r}; expected one of {sorted(ENGINES)}"
        )
    if fmt not in ENGINES[engine].formats:
        raise SidecarError(
            f"{where}: key 'engine' is {engine!r}, which runs "
            f"{', '.join(ENGINES[engine].formats)} files, not format {fmt!r}"
        )
    return fmt, engine


def _read_depth_range(get: _Getter, where: str) -> tuple[float, float]:
    """The sidecar's ``min_depth`` and ``max_depth`` in metres: finite, 0 < min < max."""
    number = "a number (metres)"
    min_depth = float(get("min_depth", (int, float), number))
    max_depth = float(get("max_depth", (int, float), number))
    if not (math.isfinite(min_depth) and math.isfinite(max_depth) and 0 < min_depth < max_depth):
        raise SidecarError(
            f"{where}: keys 'min_depth', 'max_depth' are {min_depth}, {max_depth}; expected "
            "0 < min_depth < max_depth"
        )
    return min_depth, max_depth


def _read_inputs(get: _Getter, where: str, fusion: str) -> tuple[list[str], int | str, int, int]:
    """The sidecar's input names (those of ``fusion``) and the image's batch, height and width."""
    inputs = get("inputs", (list,), "a list of the inputs, image first")
    names, shapes = [], []
    for i, item in enumerate(inputs):
        key = f"inputs[{i}]"
        if not isinstance(item, dict) or not isinstance(item.get("name"), str):
            raise SidecarError(f"{where}: key {key!r} has no 'name'; expected a name and shape")
        shape = item.get("shape")
        if not isinstance(shape, list) or len(shape) != 4:
            raise SidecarError(
                f"{where}: key '{key}.shape' is {shape!r}; expected [batch, C, H, W]"
            )
        names.append(item["name"])
        shapes.append(shape)
    expected_names = ["image", "sparse"] if fusion != "rgb" else ["image"]
    if names != expected_names:
        raise SidecarError(
            f"{where}: key 'inputs' names {names}; a fusion={fusion} model takes {expected_names}"
        )
    batch, _, height, width = shapes[0]
    for key, value in (("height", height), ("width", width)):
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0 or value % 32:
            raise SidecarError(
                f"{where}: key 'inputs[0].shape' has {key} {value!r}; expected a positive "
                "multiple of 32"
            )
    # A name (``batch``) is a dynamic axis; an integer, the batch the file was exported at.
    if isinstance(batch, bool) or not (
        isinstance(batch, str) or (isinstance(batch, int) and batch > 0)
    ):
        raise SidecarError(
            f"{where}: key 'inputs[0].shape' has batch {batch!r}; expected a name (any "
            "batch) or a positive integer"
        )
    return names, batch, height, width


def _read_quantization(get: _Getter, where: str) -> str | None:
    """The sidecar's quantization mode: None, or one of :data:`QUANTIZATIONS`."""
    quantization = get("quantization", (dict, type(None)), "null or an object", None)
    if quantization is None:
        return None
    mode = quantization.get("mode")
    if mode not in QUANTIZATIONS:
        raise SidecarError(
            f"{where}: key 'quantization.mode' is {mode!r}; expected one of {list(QUANTIZATIONS)}"
        )
    return mode


def read_sidecar(model_file: str | os.PathLike) -> ModelInfo:
    """The checked sidecar of ``model_file`` (``<model file>.json``).

    Raises:
        FileNotFoundError: ``model_file`` does not exist.
        SidecarError: the sidecar is missing, not JSON, or a key is missing or wrong (the
            message names the file and key).
    """
    path = Path(model_file).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"model_file={path}: no such file")
    sidecar = sidecar_path(path)
    if not sidecar.is_file():
        raise SidecarError(
            f"model_file={path}: no sidecar {sidecar.name} next to it; python -m "
            "fusion_depth.export writes one (what the model takes and gives), export it again"
        )
    data = read_json(sidecar, "a sidecar", error=SidecarError)
    return ModelInfo.from_sidecar(data, path, sidecar)


# --------------------------------------------------------------------------- engines


@dataclass(frozen=True)
class Runner:
    """A model file ready to run: ``run(inputs) -> depth``, ``inputs`` the arrays of
    :attr:`ModelInfo.input_names` ((B, C, H, W) float32), ``depth`` (B, 1, H, W) float32 m."""

    run: Callable[[Sequence[np.ndarray]], np.ndarray]
    identity: str  # what ran it, as the run record's ``engine``: ``openvino-bf16``
    description: str  # for logs: ``OpenVINO 2026.4 CPU, bf16``
    computes: str = "fp32"  # what it computes in: ``bf16``, ``int8, other operations bf16``


@dataclass(frozen=True)
class Engine:
    """One engine of :data:`ENGINES`: how files of some formats are run.

    Attributes:
        name: the sidecar's ``engine`` value.
        formats: the export formats whose files it runs.
        load: ``load(info)`` returns the :class:`Runner` of the file ``info`` describes.
        require: ``require()`` raises ImportError naming the extra when a package is missing
            (or the device it needs).
        precisions: the sidecar ``precision`` values it runs (of
            :data:`~fusion_depth.export.contract.PRECISIONS`).
    """

    name: str
    formats: tuple[str, ...]
    load: Callable[[ModelInfo], Runner]
    require: Callable[[], None]
    precisions: tuple[str, ...] = ("fp32",)


def _load_onnxruntime(info: ModelInfo) -> Runner:
    import onnxruntime as ort

    session = ort.InferenceSession(str(info.path), providers=["CPUExecutionProvider"])
    check_declared_inputs(info, [(i.name, i.shape) for i in session.get_inputs()])

    def run(inputs: Sequence[np.ndarray]) -> np.ndarray:
        feeds = dict(zip(info.input_names, inputs, strict=True))
        return session.run(["depth"], feeds)[0]

    return Runner(run, "onnxruntime", f"ONNX Runtime {ort.__version__} CPU, fp32", "fp32")


def _load_torchscript(info: ModelInfo) -> Runner:
    # The package's own export format: a TorchScript program, never unpickled Python.
    with quiet_jit():
        module = torch.jit.load(str(info.path), map_location="cpu").eval()

    def run(inputs: Sequence[np.ndarray]) -> np.ndarray:
        with torch.no_grad(), quiet_jit():
            return module(*(torch.from_numpy(x) for x in inputs)).numpy()

    return Runner(run, "torchscript", f"torch.jit {torch.__version__} CPU, fp32", "fp32")


@functools.cache
def openvino_core() -> Any:
    """The process's one ``openvino.Core`` (creating one scans the devices)."""
    import openvino as ov

    return ov.Core()


def cpu_has_bf16() -> bool:
    """Whether OpenVINO computes bf16 natively on this CPU (``OPTIMIZATION_CAPABILITIES``)."""
    return "BF16" in openvino_core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")


# precision → OpenVINO's INFERENCE_PRECISION_HINT
_OPENVINO_HINTS = {"fp32": "f32", "bf16": "bf16"}


def compile_openvino(path: Path, precision: str) -> tuple[Any, str]:
    """The IR at ``path`` (``.xml``, its ``.bin`` beside it) compiled for the CPU in
    ``precision`` (``fp32``/``bf16``; bf16 falls back to fp32 where the CPU lacks it).

    Returns:
        (the compiled model, the precision it runs in).
    """
    if precision == "bf16" and not cpu_has_bf16():
        log.warning("%s: recorded for bf16, which this CPU lacks; running it in fp32", path)
        precision = "fp32"
    core = openvino_core()
    compiled = core.compile_model(
        core.read_model(str(path)), "CPU", {"INFERENCE_PRECISION_HINT": _OPENVINO_HINTS[precision]}
    )
    return compiled, precision


def _load_openvino(info: ModelInfo) -> Runner:
    import openvino as ov

    compiled, precision = compile_openvino(info.path, info.precision)
    check_declared_inputs(
        info,
        [
            (
                i.get_any_name(),
                [d.get_length() if d.is_static else None for d in i.get_partial_shape()],
            )
            for i in compiled.inputs
        ],
    )
    request = compiled.create_infer_request()
    output = compiled.outputs[0]

    def run(inputs: Sequence[np.ndarray]) -> np.ndarray:
        return request.infer(list(inputs))[output].copy()

    computes = info.quantization or precision
    ran = f"{computes}, other operations {precision}" if info.quantization else computes
    return Runner(run, f"openvino-{computes}", f"OpenVINO {ov.__version__} CPU, {ran}", ran)


def require_tensorrt(what: str) -> None:
    """Fail with one line when this machine cannot build or run TensorRT engines: no CUDA GPU,
    or no ``torch_tensorrt``; ``what`` names who asks (``format=tensorrt``).

    Raises:
        MissingDependencyError: naming the GPU or the extra that is missing.
    """
    require_cuda(what, "TensorRT builds and runs engines on NVIDIA GPUs (on a CPU: OpenVINO)")
    require_modules(what, ["torch_tensorrt"], TENSORRT_EXTRA)


def load_tensorrt_program(path: Path) -> Callable[..., torch.Tensor]:
    """The Torch-TensorRT program saved at ``path`` (``torch_tensorrt.save``, an
    ExportedProgram), ready to run on the GPU: ``program(*inputs) -> depth``, CUDA tensors in
    and out. ``torch.export.load`` unpickles the file: load only files you exported."""
    import torch_tensorrt  # noqa: F401  (registers the TensorRT engine class the program holds)

    # As an open file: torch.export.load takes a path only when it ends in .pt2.
    with open(path, "rb") as file:
        module = torch.export.load(file).module()

    def program(*inputs: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            out = module(*inputs)
        return out[0] if isinstance(out, tuple | list) else out

    return program


def _load_tensorrt(info: ModelInfo) -> Runner:
    import torch_tensorrt

    program = load_tensorrt_program(info.path)
    device = torch.device("cuda")

    def run(inputs: Sequence[np.ndarray]) -> np.ndarray:
        depth = program(*(torch.from_numpy(x).to(device) for x in inputs))
        return depth.float().cpu().numpy()

    gpu = torch.cuda.get_device_name(device)
    return Runner(
        run,
        f"tensorrt-{info.precision}",
        f"Torch-TensorRT {torch_tensorrt.__version__} {gpu}, {info.precision}",
        info.precision,
    )


ENGINES: dict[str, Engine] = {
    engine.name: engine
    for engine in (
        Engine(
            "onnxruntime",
            ("onnx",),
            _load_onnxruntime,
            lambda: require_modules("engine onnxruntime", ["onnxruntime"], ONNX_EXTRA),
        ),
        Engine("torchscript", ("torchscript",), _load_torchscript, lambda: None),
        Engine(
            "openvino",
            ("openvino",),
            _load_openvino,
            lambda: require_modules("engine openvino", ["openvino"], OPENVINO_EXTRA),
            ("fp32", "bf16"),
        ),
        Engine(
            "tensorrt",
            ("tensorrt",),
            _load_tensorrt,
            lambda: require_tensorrt("engine tensorrt"),
            ("fp32", "fp16"),
        ),
    )
}
# A sidecar without ``engine`` (written before engines had names): its format's engine.
FORMAT_ENGINES: dict[str, str] = {fmt: e.name for e in ENGINES.values() for fmt in e.formats}


# --------------------------------------------------------------------------- the network


class ExportedModel(DepthModel):
    """An exported model file, run by its engine, in place of a checkpoint's network.

    ``forward(image, sparse)``: image (B, 3, H, W) in [0, 1], sparse (B, 1, H, W) metres (fed
    only to a fusion model) → depth (B, 1, H, W) metres on the input's device. H × W must be the
    size the file was exported at; a file exported with a fixed batch runs any batch in chunks
    of that size. Its output space is depth, so
    :func:`~fusion_depth.models.inference.predict_depth` clips to the range only. It has no
    trainable weights: one empty parameter tells callers the device (CPU).

    Raises (forward):
        ValueError: the input size is not the file's.
    """

    output_space = "depth"

    def __init__(self, info: ModelInfo, runner: Runner) -> None:
        super().__init__(info.min_depth, info.max_depth, depth_scale=1.0)
        self.info, self.runner = info, runner
        self.fusion = InputMode(info.fusion, info.uses_sparse)
        self._device_probe = nn.Parameter(torch.zeros(0), requires_grad=False)

    @property
    def engine(self) -> str:
        """What runs it, as the run record's ``engine`` (``onnxruntime``, ``openvino-int8``)."""
        return self.runner.identity

    def forward(self, image: torch.Tensor, sparse: torch.Tensor | None = None) -> torch.Tensor:
        height, width = image.shape[-2:]
        if (height, width) != (self.info.height, self.info.width):
            raise ValueError(
                f"model_file={self.info.path} takes {self.info.height}×{self.info.width} inputs "
                f"(fixed when it was exported), got {height}×{width}; export it again with "
                f"height={height} width={width}"
            )
        arrays = [image.detach().float().cpu().contiguous().numpy()]
        if self.info.uses_sparse:
            if sparse is None:
                raise ValueError(f"model_file={self.info.path}: a fusion model needs sparse depth")
            arrays.append(sparse.detach().float().cpu().contiguous().numpy())
        size = self.info.batch_size or len(image)
        depth = []
        for start in range(0, len(image), size):
            chunk = [a[start : start + size] for a in arrays]
            n = len(chunk[0])
            if n < size:  # a fixed batch axis: fill it up with copies of the last frame
                chunk = [np.concatenate([c, np.repeat(c[-1:], size - n, axis=0)]) for c in chunk]
            depth.append(np.asarray(self.runner.run(chunk), dtype=np.float32)[:n])
        return torch.from_numpy(np.concatenate(depth)).to(image.device)


def check_declared_inputs(info: ModelInfo, declared: Sequence[tuple[str, Sequence[Any]]]) -> None:
    """Refuse a model file whose own inputs (name and [batch, C, H, W], a dynamic axis as a
    name or None) differ from its sidecar's, before any data is made for it.

    Raises:
        ModelFileError: naming the file, the input and both shapes.
    """
    names = [name for name, _ in declared]
    if names != list(info.input_names):
        raise ModelFileError(
            f"model_file={info.path}: the file takes inputs {names}, its sidecar says "
            f"{list(info.input_names)}; export it again"
        )
    for name, dims in declared:
        channels = 3 if name == "image" else 1
        batch = info.batch_size  # None: any batch, so the file's batch axis is dynamic
        expected = [batch, channels, info.height, info.width]
        got = [d if isinstance(d, int) and d > 0 else None for d in dims]
        if got != expected:
            show = ["batch" if d is None else d for d in expected]
            raise ModelFileError(
                f"model_file={info.path}: input {name!r} has shape "
                f"{['batch' if d is None else d for d in got]} in the file, but its sidecar "
                f"says {show}; export it again"
            )


def open_exported(info: ModelInfo) -> ExportedModel:
    """The model file ``info`` describes, loaded by its engine.

    Raises:
        ImportError: the engine's package is missing (naming the extra).
        ModelFileError: the engine cannot load the file (truncated, its OpenVINO ``.bin``
            missing or cut), or the file's inputs differ from the sidecar's.
    """
    engine = ENGINES[info.engine]
    engine.require()
    try:
        runner = engine.load(info)
    except (ImportError, ModelFileError):
        raise
    except Exception as err:  # noqa: BLE001 - each engine raises its own types (ORT's derive
        # from Exception only); what it says goes into the one line, the rest stays the cause
        said = str(err).strip().splitlines()[0][:300] if str(err).strip() else type(err).__name__
        raise ModelFileError(
            f"model_file={info.path}: {engine.name} cannot load it ({said}); export it again"
        ) from err
    return ExportedModel(info, runner)


def load_exported(
    model_file: str | os.PathLike, fusion: str | None = None, backbone: str | None = None
) -> LoadedModel:
    """An exported model file as a :class:`~fusion_depth.runner.checkpoints.LoadedModel`
    (``key`` ``model_file``) whose network is an :class:`ExportedModel`, and whose config holds what
    the sidecar records (fusion, backbone, model name, the checkpoint's dataset block and run
    identity), so ``evaluate`` and ``predict`` use it as they use a checkpoint.

    ``fusion``/``backbone``, when given, must match the sidecar's.

    Raises:
        FileNotFoundError: no such file.
        SidecarError: the sidecar is missing or has a bad key.
        CheckpointError: ``fusion``/``backbone`` differ from the sidecar's.
        ImportError: the engine's package is missing.
    """
    info = read_sidecar(model_file)
    config: dict[str, Any] = {
        "fusion": {"mode": info.fusion},
        "backbone": {"name": info.backbone},
        "model": {"net": {"name": info.model}} if info.model else {},
    }
    if info.dataset_config is not None:
        config["dataset"] = info.dataset_config
    check_expected(config, info.path, fusion, backbone, option="model_file")
    net = open_exported(info)
    log.info("model_file=%s: run by %s", info.path, net.runner.description)
    return LoadedModel(net=net, config=config, path=info.path, run=info.run, key="model_file")


def check_source(ckpt_path: object, model_file: object, prior: bool = False) -> None:
    """Exactly one of ``ckpt_path`` and ``model_file`` must be given.

    Args:
        ckpt_path: the ``ckpt_path`` value.
        model_file: the ``model_file`` value.
        prior: the command also scores a prior's global alignment with neither (``evaluate``):
            the message names that third way.

    Raises:
        ConfigError: both or neither (one line naming both keys).
    """
    if ckpt_path is not None and model_file is not None:
        raise ConfigError(
            f"ckpt_path={ckpt_path} and model_file={model_file}: give one of them, a "
            "checkpoint or an exported model file, not both"
        )
    if ckpt_path is None and model_file is None:
        third = ", or prior=<name> prior.weights=<file> dataset=<name> (a prior's alignment)"
        raise ConfigError(
            "ckpt_path=null and model_file=null: give ckpt_path=<checkpoint, or a folder of "
            f"runs> or model_file=<a file written by python -m fusion_depth.export>"
            f"{third if prior else ''}"
        )


def engine_identity(net: DepthModel) -> str:
    """What runs ``net``: its engine identity for an :class:`ExportedModel`, else ``torch``."""
    return net.engine if isinstance(net, ExportedModel) else TORCH_ENGINE
