"""``python -m fusion_depth.export format=openvino``: IRs that give PyTorch's depth in fp32 and
bf16, int8 files whose accuracy cost is measured on data, and exports that fail leave nothing.

Checkpoints are untrained ResNet-18 DepthNets (``conftest``, ``spread=True``: depths around 10 m
that vary across the image, not clipped to one end) at the smoke size 64×96; no test trains.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import openvino as ov
import pytest
import torch
from helpers import save_untrained_checkpoint

from fusion_depth.config.hydra_main import user_message
from fusion_depth.export import BACKENDS, ExportError, export_model, sidecar_path
from fusion_depth.export.exporter import check_export_options, resolve_export_precision
from fusion_depth.export.runtime import compile_openvino, cpu_has_bf16
from fusion_depth.models.inference import predict_depth
from fusion_depth.runner.checkpoints import load_model

H, W = 64, 96


@pytest.fixture(scope="module")
def fusion_model(tmp_path_factory: pytest.TempPathFactory, smoke_dataset: dict):
    root = tmp_path_factory.mktemp("ckpt18")
    path = save_untrained_checkpoint(
        root / "concat.ckpt", "concat", smoke_dataset, backbone="resnet18", spread=True
    )
    return load_model(path)


@pytest.fixture(scope="module")
def fp32_ir(fusion_model, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ov") / "concat.xml"
    return export_model(fusion_model, "openvino", out, precision="fp32")


def _inputs(batch: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    image = rng.random((batch, 3, H, W), dtype=np.float32)
    sparse = rng.uniform(1.0, 70.0, (batch, 1, H, W)).astype(np.float32)
    sparse[rng.random(sparse.shape) > 0.05] = 0.0
    return image, sparse


def _pytorch(net, image: np.ndarray, sparse: np.ndarray) -> np.ndarray:
    return predict_depth(net, torch.from_numpy(image), torch.from_numpy(sparse)).numpy()


def _run(path: Path, precision: str, image: np.ndarray, sparse: np.ndarray) -> np.ndarray:
    compiled, _ = compile_openvino(path, precision)
    return compiled([image, sparse])[compiled.outputs[0]]


@pytest.mark.slow
def test_fp32_ir_gives_pytorchs_depth_at_any_batch(fp32_ir: Path, fusion_model) -> None:
    bin_file = fp32_ir.with_suffix(".bin")
    assert bin_file.is_file() and bin_file.stat().st_size > 1_000_000  # fp32 weights: 4 B each
    assert sorted(p.name for p in fp32_ir.parent.iterdir()) == [
        "concat.bin",
        "concat.xml",
        "concat.xml.json",
    ]
    model = ov.Core().read_model(str(fp32_ir))
    assert [i.get_any_name() for i in model.inputs] == ["image", "sparse"]
    assert model.outputs[0].get_any_name() == "depth"
    assert str(model.inputs[0].get_partial_shape()) == f"[?,3,{H},{W}]"
    for batch in (1, 3):
        image, sparse = _inputs(batch, seed=batch)
        depth = _run(fp32_ir, "fp32", image, sparse)
        expected = _pytorch(fusion_model.net, image, sparse)
        np.testing.assert_allclose(depth, expected, rtol=1e-3, atol=0)
        inside = (expected > 0.5) & (expected < 80.0)
        assert inside.mean() > 0.3 and expected[inside].std() > 1.0  # not a constant map
    info = json.loads(sidecar_path(fp32_ir).read_text())
    assert (info["format"], info["engine"], info["precision"]) == ("openvino", "openvino", "fp32")
    assert info["quantization"] is None and info["accuracy"] is None
    assert info["verified"]["checked"] == "max_rel_diff"
    assert info["verified"]["max_rel_diff"] <= info["verified"]["tolerance"] == 1e-3
    # What evaluate/predict model_file= need, as plain data.
    assert info["dataset_config"]["name"] == "procedural" and "reader" in info["dataset_config"]
    assert (info["run"]["fusion"], info["run"]["backbone"]) == ("concat", "resnet18")
    assert info["model"] == "densedepth"


@pytest.mark.slow
def test_bf16_is_recorded_and_run_in_bf16(fusion_model, fp32_ir: Path, tmp_path: Path) -> None:
    out = export_model(fusion_model, "openvino", tmp_path / "bf16.xml", precision="bf16")
    info = json.loads(sidecar_path(out).read_text())
    assert info["precision"] == "bf16"
    # The weights stay fp32: the same .bin as the fp32 export; bf16 is chosen when compiling.
    assert out.with_suffix(".bin").read_bytes() == fp32_ir.with_suffix(".bin").read_bytes()
    assert info["verified"]["tolerance"] == 0.1 and info["verified"]["max_rel_diff"] <= 0.1
    image, sparse = _inputs(2, seed=5)
    bf16 = _run(out, "bf16", image, sparse)
    fp32 = _run(out, "fp32", image, sparse)
    expected = _pytorch(fusion_model.net, image, sparse)
    assert np.abs(bf16 / expected - 1).max() <= 0.1
    if cpu_has_bf16():
        assert info["verified"]["runtime"].endswith("CPU, bf16")
        assert np.abs(bf16 - fp32).max() > 1e-3  # the hint took effect: bf16 rounds
        assert resolve_export_precision("auto", "openvino") == "bf16"
    else:
        assert resolve_export_precision("auto", "openvino") == "fp32"
    assert resolve_export_precision("auto", "onnx") == "fp32"


@pytest.mark.slow
def test_a_failed_export_leaves_the_earlier_files_untouched(
    fusion_model, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "m.xml"
    earlier = {"m.xml": b"<earlier xml/>", "m.bin": b"earlier weights", "m.xml.json": b"{}\n"}
    for name, data in earlier.items():
        (tmp_path / name).write_bytes(data)
    seen: list[Path] = []
    real = BACKENDS["openvino"]

    def verify_then_fail(path, *args):
        real.verify(path, *args)  # the IR and its .bin were written and check out
        seen.extend([path, path.with_suffix(".bin")])
        raise ExportError("forced verification failure")

    monkeypatch.setitem(BACKENDS, "openvino", dataclasses.replace(real, verify=verify_then_fail))
    with pytest.raises(ExportError, match="forced verification failure"):
        export_model(fusion_model, "openvino", out, precision="fp32")
    assert all(p.parent == tmp_path and p.name.startswith(".m.xml.") for p in seen)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == earlier  # no temp files


@pytest.mark.slow
def test_int8_records_its_calibration_and_measured_accuracy(
    fusion_model, smoke_dataset: dict, tmp_path: Path
) -> None:
    out = export_model(
        fusion_model, "openvino", tmp_path / "int8.xml", quantize="int8", max_rmse_increase=100.0
    )
    info = json.loads(sidecar_path(out).read_text())
    assert info["quantization"] == {
        "mode": "int8",
        # calibration_frames=300 by default: all 8 frames of the smoke training split.
        "calibration": {"dataset": "procedural", "split": "train", "frames": 8},
    }
    assert info["verified"]["checked"] == "mean_rel_diff"
    assert info["verified"]["runtime"].endswith("CPU, int8")
    assert b"FakeQuantize" in out.read_bytes()  # NNCF's quantization nodes are in the graph
    # Every convolution's weights are int8 (dequantized by a Multiply) but the first's, which
    # takes the sparse metres, and the last's, which gives the depth: those stay fp32 Constants.
    convolutions = [
        op
        for op in ov.Core().read_model(out).get_ordered_ops()
        if op.get_type_name() == "Convolution"
    ]
    float_weights = [
        op.input_value(1).get_node().get_type_name() == "Constant" for op in convolutions
    ]
    assert len(float_weights) > 2 and float_weights[0] and float_weights[-1]
    assert not any(float_weights[1:-1])
    accuracy = info["accuracy"]
    assert (accuracy["split"], accuracy["dataset"]) == ("val", "procedural")
    assert accuracy["images"] == smoke_dataset["reader"]["num_val"] == 4
    assert accuracy["max_rmse_increase"] == 100.0 and accuracy["level"] == 0.95
    for metric in ("rmse", "delta1"):
        block = accuracy[metric]
        diff = block["diff"]
        assert diff["low"] <= diff["mean"] <= diff["high"], metric
        # Per-image averaging: the headline is the mean over images, so the mean paired
        # difference is the difference of the headlines.
        assert diff["mean"] == pytest.approx(block["exported"] - block["reference"], abs=1e-9)
    assert accuracy["rmse"]["diff"]["mean"] != 0.0  # int8 is not the fp32 model


@pytest.mark.slow
def test_int8_calibrates_on_frames_it_is_given(fusion_model, tmp_path: Path) -> None:
    """``calibration=``: frames of the caller's (``bench`` quantizes its random-weight network on
    synthetic frames), no dataset read; wrong shapes, or frames without quantize, are refused."""
    frames = [tuple(torch.from_numpy(x[:1]) for x in _inputs(1, seed=s)) for s in range(2)]
    out = export_model(
        fusion_model,
        "openvino",
        tmp_path / "given.xml",
        quantize="int8",
        calibration=frames,
        measure_accuracy=False,
    )
    info = json.loads(sidecar_path(out).read_text())
    assert info["quantization"]["calibration"] == {"dataset": None, "split": None, "frames": 2}
    assert info["accuracy"] is None
    with pytest.raises(ValueError, match=r"calibration frame 0 has shapes \[\(1, 3, 64, 96\)\]"):
        export_model(
            fusion_model,
            "openvino",
            tmp_path / "bad.xml",
            quantize="int8",
            calibration=[frames[0][:1]],
        )
    with pytest.raises(ValueError, match="calibration frames were given without quantize=int8"):
        export_model(fusion_model, "openvino", tmp_path / "bad.xml", calibration=frames)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "given.bin",
        "given.xml",
        "given.xml.json",
    ]


@pytest.mark.slow
def test_max_rmse_increase_refuses_and_writes_nothing(fusion_model, tmp_path: Path) -> None:
    out = tmp_path / "deploy" / "m.xml"
    # An fp32 IR costs ~0 m of RMSE: any negative bound must refuse it.
    with pytest.raises(
        ExportError,
        match=r"max_rmse_increase=-0.5: the export raises RMSE by [-+]\d.* m per val image "
        r"\(95 % CI .*4 images of procedural\); refused, nothing was written",
    ) as err:
        export_model(fusion_model, "openvino", out, precision="fp32", max_rmse_increase=-0.5)
    assert list(out.parent.iterdir()) == []
    assert user_message(err.value) == str(err.value)  # the command prints this line alone


@pytest.mark.parametrize(
    "options,message",
    [
        ({"fmt": "onnx", "quantize": "int8"}, "quantize=int8: format=onnx offers no quantization"),
        ({"fmt": "openvino", "quantize": "int4"}, r"quantize=int4: expected null or one of"),
        ({"fmt": "onnx", "precision": "bf16"}, "precision=bf16: format=onnx runs in fp32 only"),
        ({"fmt": "openvino", "precision": "fp8"}, r"precision=fp8: expected one of \['auto'"),
        (
            {"fmt": "openvino", "precision": "fp16"},
            "precision=fp16: format=openvino runs in fp32, bf16 only; precision=fp16 is for "
            "format=tensorrt",
        ),
        (
            {"fmt": "openvino", "measure_accuracy": False, "max_rmse_increase": 0.1},
            "max_rmse_increase=0.1 needs the accuracy measured",
        ),
        ({"fmt": "openvino", "measure_accuracy": "yes"}, "measure_accuracy=yes: expected auto"),
    ],
)
def test_option_errors_name_the_key(options: dict, message: str) -> None:
    fmt = options.pop("fmt")
    with pytest.raises(ValueError, match=message):
        check_export_options(fmt, None, None, None, True, **options)


def test_an_openvino_output_must_end_in_xml(fusion_model, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"output=.*model.ir: a format=openvino model file ends"):
        export_model(fusion_model, "openvino", tmp_path / "model.ir")
    assert list(tmp_path.iterdir()) == []
