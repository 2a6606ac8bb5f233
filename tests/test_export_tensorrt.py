"""``format=tensorrt``: on a machine without a CUDA GPU (or without torch-tensorrt) it is refused
in one line before anything is loaded or written; its options, sidecar and engine entry are
checked here, the code around Torch-TensorRT runs with a stand-in for it on the CPU, and on a
machine with both, a small network is exported, verified and run by TensorRT itself.

CI has no GPU, so the last test skips there; ``tests/gpu/check_tensorrt.py`` is the fuller check
(DenseNet-169, fp16 and fp32, bench) to run by hand on a GPU machine.
"""

from __future__ import annotations

import importlib.util
import json
import sys
import types
from pathlib import Path

import pytest
import torch
from helpers import compose_config
from hydra.core.global_hydra import GlobalHydra

from fusion_depth.errors import MissingDependencyError
from fusion_depth.export import BACKENDS, SidecarError, export_model, load_exported, read_sidecar
from fusion_depth.export.cli import export
from fusion_depth.export.contract import DepthExportModel, ExportSpec
from fusion_depth.export.exporter import check_quantize, resolve_export_precision
from fusion_depth.export.sidecar import sidecar_contents, sidecar_path
from fusion_depth.models import DepthNet
from fusion_depth.models.inference import predict_depth

H, W = 64, 96
HAS_GPU = torch.cuda.is_available()
HAS_TRT = importlib.util.find_spec("torch_tensorrt") is not None


@pytest.fixture(scope="module")
def net() -> DepthNet:
    torch.manual_seed(0)
    return DepthNet("resnet18", "concat", pretrained=False).eval()


@pytest.mark.skipif(HAS_GPU, reason="this machine has a CUDA GPU")
def test_without_a_gpu_it_is_refused_in_one_line_and_writes_nothing(
    net: DepthNet, tmp_path: Path
) -> None:
    with pytest.raises(MissingDependencyError) as err:
        export_model(net, "tensorrt", tmp_path / "m.pt2", H, W)
    text = str(err.value)
    assert "\n" not in text
    assert text.startswith("format=tensorrt needs a CUDA GPU, and torch finds none here")
    assert list(tmp_path.iterdir()) == []
    # The command refuses before it loads the checkpoint (which does not exist here).
    cfg = compose_config(
        ["ckpt_path=/nonexistent.ckpt", "format=tensorrt"], tmp_path / "run", "export"
    )
    try:
        with pytest.raises(MissingDependencyError, match="format=tensorrt needs a CUDA GPU"):
            export(cfg)
    finally:
        GlobalHydra.instance().clear()
    assert not (tmp_path / "run").exists() or not any((tmp_path / "run").rglob("*.pt2"))


@pytest.mark.skipif(HAS_TRT, reason="torch-tensorrt is installed")
def test_with_a_gpu_but_no_torch_tensorrt_it_names_the_extra(
    net: DepthNet, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setitem(sys.modules, "torch_tensorrt", None)  # import fails as if not installed
    with pytest.raises(MissingDependencyError) as err:
        export_model(net, "tensorrt", tmp_path / "m.pt2", H, W)
    assert str(err.value) == (
        'format=tensorrt needs torch_tensorrt, which is not installed: pip install -e ".[tensorrt]"'
    )
    assert list(tmp_path.iterdir()) == []


def test_precision_and_quantization_choices() -> None:
    assert resolve_export_precision("auto", "tensorrt") == "fp16"
    assert resolve_export_precision("fp32", "tensorrt") == "fp32"
    with pytest.raises(
        ValueError, match=r"precision=bf16: format=tensorrt runs in fp16, fp32 only"
    ):
        resolve_export_precision("bf16", "tensorrt")
    with pytest.raises(ValueError, match=r"precision=fp16 is for format=tensorrt"):
        resolve_export_precision("fp16", "openvino")
    with pytest.raises(ValueError) as err:
        check_quantize("int8", "tensorrt")
    assert str(err.value).startswith(
        "quantize=int8: format=tensorrt offers no quantization; TensorRT INT8 needs NVIDIA ModelOpt"
    )
    assert "precision=fp16" in str(err.value) and "\n" not in str(err.value)
    backend = BACKENDS["tensorrt"]
    assert (backend.suffix, backend.engine, backend.dynamic_batch) == (".pt2", "tensorrt", False)


def test_a_tensorrt_sidecar_reads_back_and_its_engine_refuses_without_a_gpu(
    net: DepthNet, tmp_path: Path
) -> None:
    """The sidecar is the same contract as every format's; loading it needs the engine."""
    path = tmp_path / "m.pt2"
    path.write_bytes(b"not an engine")  # never read: the engine refuses first
    spec = ExportSpec(H, W, batch_size=1, precision="fp16")
    result = {"opset": None, "verified": None}
    contents = sidecar_contents(
        DepthExportModel(net), None, BACKENDS["tensorrt"], path, spec, result
    )
    sidecar_path(path).write_text(json.dumps(contents))
    info = read_sidecar(path)
    assert (info.format, info.engine, info.precision, info.batch_size) == (
        "tensorrt",
        "tensorrt",
        "fp16",
        1,
    )
    assert info.input_names == ("image", "sparse")
    bad = dict(contents, precision="bf16")
    sidecar_path(path).write_text(json.dumps(bad))
    with pytest.raises(SidecarError, match=r"'precision' is 'bf16'; engine 'tensorrt' runs"):
        read_sidecar(path)
    sidecar_path(path).write_text(json.dumps(contents))
    if not HAS_GPU:
        with pytest.raises(MissingDependencyError, match=r"^engine tensorrt needs a CUDA GPU"):
            load_exported(path)


@pytest.mark.slow
def test_the_glue_around_torch_tensorrt_with_a_stand_in_on_the_cpu(
    net: DepthNet, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What this package does around Torch-TensorRT, run on the CPU: a stand-in module whose
    ``compile`` is plain ``torch.export`` (no engines) and a GPU that is the CPU. Checks the
    options passed per precision, the file written (a PT2 archive under any name) and its
    sidecar, verification, and ``model_file=`` loading and running it in chunks. TensorRT
    itself is not exercised: that needs a GPU (the test below)."""
    calls: list[tuple] = []

    def compile(module, ir, arg_inputs, **options):
        calls.append((ir, [tuple(x.shape) for x in arg_inputs], options))
        return torch.export.export(module, tuple(arg_inputs)).module()

    def save(module, path, output_format, arg_inputs):
        assert output_format == "exported_program" and path.endswith(".pt2")
        torch.export.save(torch.export.export(module, tuple(arg_inputs)), path)

    stand_in = types.ModuleType("torch_tensorrt")
    stand_in.__version__, stand_in.compile, stand_in.save = "stand-in", compile, save
    monkeypatch.setitem(sys.modules, "torch_tensorrt", stand_in)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda *args: "CPU as GPU")
    monkeypatch.setattr(torch.Tensor, "cuda", lambda self, *args, **kwargs: self)
    monkeypatch.setattr(torch.nn.Module, "cuda", lambda self, *args, **kwargs: self)
    to = torch.Tensor.to

    def to_cpu(self, *args, **kwargs):
        if args and isinstance(args[0], torch.device) and args[0].type == "cuda":
            return self
        return to(self, *args, **kwargs)

    monkeypatch.setattr(torch.Tensor, "to", to_cpu)
    options = {
        "fp16": {"enable_autocast": True, "autocast_low_precision_type": torch.float16},
        "fp32": {"disable_tf32": True},
    }
    for precision, name in (("fp16", "m.pt2"), ("fp32", "any-name.trt")):
        path = export_model(net, "tensorrt", tmp_path / name, H, W, precision=precision)
        assert calls[-1] == ("dynamo", [(1, 3, H, W), (1, 1, H, W)], options[precision])
        info = json.loads(sidecar_path(path).read_text())
        assert (info["engine"], info["precision"], info["dynamic_batch"]) == (
            "tensorrt",
            precision,
            False,
        )
        assert info["inputs"][1]["shape"] == [1, 1, H, W]
        verified = info["verified"]
        assert verified["runtime"] == f"Torch-TensorRT stand-in CPU as GPU, {precision}"
        assert verified["max_rel_diff"] <= 1e-5  # the stand-in computes in fp32
        loaded = load_exported(path)
        image, sparse = torch.rand(3, 3, H, W), torch.zeros(3, 1, H, W)
        assert loaded.net.engine == f"tensorrt-{precision}"
        depth = loaded.net(image, sparse)  # three chunks of the engine's batch, 1
        assert depth.shape == (3, 1, H, W)
        assert torch.allclose(depth, predict_depth(net, image, sparse), rtol=1e-4)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "any-name.trt",
        "any-name.trt.json",
        "m.pt2",
        "m.pt2.json",
    ]


@pytest.mark.skipif(not (HAS_GPU and HAS_TRT), reason="needs a CUDA GPU and torch-tensorrt")
@pytest.mark.parametrize("precision", ["fp16", "fp32"])
def test_on_a_gpu_the_engine_is_verified_and_runs(
    net: DepthNet, tmp_path: Path, precision: str
) -> None:
    path = export_model(net, "tensorrt", tmp_path / "m.pt2", H, W, precision=precision)
    info = json.loads(sidecar_path(path).read_text())
    assert info["precision"] == precision and info["verified"]["batch"] == 1
    loaded = load_exported(path)
    image, sparse = torch.rand(3, 3, H, W), torch.zeros(3, 1, H, W)
    depth = loaded.net(image, sparse)  # batch 3 runs in chunks of the engine's batch, 1
    assert depth.shape == (3, 1, H, W) and torch.isfinite(depth).all()
    assert loaded.net.engine == f"tensorrt-{precision}"
