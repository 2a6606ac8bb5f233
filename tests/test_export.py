"""``python -m fusion_depth.export``: ONNX and TorchScript models that give PyTorch's depth.

Checkpoints are untrained DepthNets saved the way training saves them (``conftest``), at the
smoke size 64×96; no test trains. Each ONNX export takes a while, so the fusion model is
exported once per module and the RGB one once, through the entry point.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from helpers import REPO, compose_config, run_module
from hydra.core.global_hydra import GlobalHydra

import fusion_depth.export.torchscript as export_module
from fusion_depth.export import DepthExportModel, ExportError, export_model, sidecar_path
from fusion_depth.export.cli import export
from fusion_depth.models import DepthNet
from fusion_depth.models.inference import predict_depth
from fusion_depth.runner.checkpoints import load_model

pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.load` is deprecated:FutureWarning")

H, W = 64, 96  # the smoke dataset's size, which the checkpoints record
RTOL = 1e-3


@pytest.fixture(scope="module")
def fusion_model(checkpoints: dict[str, Path]):
    return load_model(checkpoints["concat"])


@pytest.fixture(scope="module")
def fusion_onnx(fusion_model, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The concat checkpoint exported to ONNX at its training size, dynamic batch."""
    return export_model(fusion_model, "onnx", tmp_path_factory.mktemp("onnx") / "concat.onnx")


def _inputs(batch: int, height: int = H, width: int = W, seed: int = 0):
    """A random image and a sparse map with ~5 % returns in [1, 70] m (zeros elsewhere)."""
    rng = np.random.default_rng(seed)
    image = rng.random((batch, 3, height, width), dtype=np.float32)
    sparse = rng.uniform(1.0, 70.0, (batch, 1, height, width)).astype(np.float32)
    sparse[rng.random(sparse.shape) > 0.05] = 0.0
    return image, sparse


def _assert_matches_pytorch(depth: np.ndarray, net: DepthNet, image, sparse=None) -> None:
    expected = predict_depth(
        net, torch.from_numpy(image), None if sparse is None else torch.from_numpy(sparse)
    ).numpy()
    assert depth.shape == expected.shape == (image.shape[0], 1, *image.shape[-2:])
    assert depth.dtype == np.float32
    np.testing.assert_allclose(depth, expected, rtol=RTOL, atol=0)
    assert depth.min() >= net.min_depth and depth.max() <= net.max_depth
    # Not a trivial agreement on a map clipped to one end of the range.
    inside = (expected > net.min_depth) & (expected < net.max_depth)
    assert inside.mean() > 0.3 and expected[inside].std() > 0.05 * expected[inside].mean()


def _session(path: Path) -> ort.InferenceSession:
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


# --------------------------------------------------------------------------- ONNX


@pytest.mark.slow
def test_fusion_onnx_matches_pytorch_at_any_batch(fusion_onnx: Path, fusion_model) -> None:
    onnx.checker.check_model(str(fusion_onnx))
    session = _session(fusion_onnx)
    assert [i.name for i in session.get_inputs()] == ["image", "sparse"]
    assert [o.name for o in session.get_outputs()] == ["depth"]
    assert [i.shape for i in session.get_inputs()] == [["batch", 3, H, W], ["batch", 1, H, W]]
    for batch in (1, 3):  # exported from a batch of 2: the batch axis is dynamic
        image, sparse = _inputs(batch, seed=batch)
        (depth,) = session.run(["depth"], {"image": image, "sparse": sparse})
        _assert_matches_pytorch(depth, fusion_model.net, image, sparse)


@pytest.mark.slow
def test_the_sparse_input_is_used(fusion_onnx: Path) -> None:
    session = _session(fusion_onnx)
    image, sparse = _inputs(1)
    with_returns = session.run(["depth"], {"image": image, "sparse": sparse})[0]
    without = session.run(["depth"], {"image": image, "sparse": np.zeros_like(sparse)})[0]
    assert np.abs(with_returns - without).max() > 0.1


@pytest.mark.slow
def test_sidecar_tells_deployment_what_to_feed(fusion_onnx: Path, fusion_model) -> None:
    info = json.loads(sidecar_path(fusion_onnx).read_text())
    assert sidecar_path(fusion_onnx) == fusion_onnx.with_name("concat.onnx.json")
    assert info["format"] == "onnx" and info["file"] == "concat.onnx"
    assert info["checkpoint"] == str(fusion_model.path.resolve())
    assert (info["fusion"], info["backbone"]) == ("concat", "densenet169")
    assert [(i["name"], i["shape"], i["dtype"]) for i in info["inputs"]] == [
        ("image", ["batch", 3, H, W], "float32"),
        ("sparse", ["batch", 1, H, W], "float32"),
    ]
    assert info["inputs"][1]["unit"] == "m"
    assert [(o["name"], o["shape"], o["unit"]) for o in info["outputs"]] == [
        ("depth", ["batch", 1, H, W], "m")
    ]
    assert (info["min_depth"], info["max_depth"]) == (0.5, 80.0)
    assert info["dynamic_batch"] is True
    model_opset = [o.version for o in onnx.load(str(fusion_onnx)).opset_import if o.domain == ""]
    assert info["opset"] == model_opset[0] and info["opset"] >= 17
    assert info["verified"]["max_rel_diff"] <= 1e-3 and info["verified"]["batch"] == 1
    # The mode of a plainly created file (readable by other users unless the umask says no),
    # not mkstemp's 0600.
    umask = os.umask(0o022)
    os.umask(umask)
    for path in (fusion_onnx, sidecar_path(fusion_onnx)):
        assert path.stat().st_mode & 0o777 == 0o666 & ~umask


@pytest.mark.slow
def test_fixed_batch_for_a_bare_network(tmp_path: Path) -> None:
    """What the benchmark does: a DepthNet without checkpoint, static shapes (``add`` fusion)."""
    torch.manual_seed(0)
    net = DepthNet(backbone="resnet18", fusion="add").eval()
    with torch.no_grad():
        # About 10 m, away from the clipping at max_depth, and varying across the image.
        net.decoder.head.bias.fill_(1.0)
        net.decoder.head.weight.mul_(30.0)
    out = export_model(net, "onnx", tmp_path / "add.onnx", 64, 64, batch_size=2)
    session = _session(out)
    assert [i.shape for i in session.get_inputs()] == [[2, 3, 64, 64], [2, 1, 64, 64]]
    image, sparse = _inputs(2, 64, 64)
    (depth,) = session.run(["depth"], {"image": image, "sparse": sparse})
    _assert_matches_pytorch(depth, net, image, sparse)
    info = json.loads(sidecar_path(out).read_text())
    assert info["checkpoint"] is None and info["dynamic_batch"] is False
    assert info["inputs"][0]["shape"] == [2, 3, 64, 64]
    assert (info["fusion"], info["backbone"]) == ("add", "resnet18")
    with pytest.raises(ValueError, match=r"height=null: a bare network .* pass height="):
        export_model(net, "onnx", tmp_path / "other.onnx")


@pytest.mark.slow
def test_entry_point_exports_rgb_onnx_into_the_run_dir(checkpoints, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    result = run_module(
        [
            "fusion_depth.export",
            f"ckpt_path={checkpoints['rgb']}",
            f"hydra.run.dir={run_dir}",
        ],
        cwd=REPO,
        timeout=600,
    )
    text = result.stdout + result.stderr
    assert result.returncode == 0, text
    out = run_dir / "rgb.onnx"  # default output: <run dir>/<checkpoint stem>.onnx
    assert f"as onnx to {out}: image ('batch', 3, {H}, {W}) → depth" in text
    assert "verified with onnxruntime" in text
    assert "[onnx_ir" not in text and "[onnxscript" not in text  # the optimiser's pass log
    assert f"described in {sidecar_path(out)}" in text
    assert (run_dir / "export.log").is_file()
    session = _session(out)
    assert [i.name for i in session.get_inputs()] == ["image"]
    image, _ = _inputs(2)
    (depth,) = session.run(["depth"], {"image": image})
    _assert_matches_pytorch(depth, load_model(checkpoints["rgb"]).net, image)
    info = json.loads(sidecar_path(out).read_text())
    assert info["fusion"] == "rgb" and [i["name"] for i in info["inputs"]] == ["image"]
    assert sorted(p.name for p in run_dir.iterdir() if not p.name.startswith(".hydra")) == [
        "export.log",
        "rgb.onnx",
        "rgb.onnx.json",
    ]


def test_missing_onnx_packages_name_the_extra(
    fusion_model, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import fails as if not installed
    with pytest.raises(ImportError) as err:
        export_model(fusion_model, "onnx", tmp_path / "m.onnx")
    assert str(err.value) == (
        'format=onnx needs onnxruntime, which is not installed: pip install -e ".[onnx]"'
    )
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- TorchScript


@pytest.mark.slow
def test_torchscript_round_trip_equals_pytorch(fusion_model, tmp_path: Path) -> None:
    out = export_model(fusion_model, "torchscript", tmp_path / "deploy" / "concat.pt")
    scripted = torch.jit.load(str(out))
    for batch in (1, 2):
        image, sparse = _inputs(batch, seed=10 + batch)
        with torch.no_grad():
            depth = scripted(torch.from_numpy(image), torch.from_numpy(sparse)).numpy()
        _assert_matches_pytorch(depth, fusion_model.net, image, sparse)
        expected = predict_depth(
            fusion_model.net, torch.from_numpy(image), torch.from_numpy(sparse)
        )
        np.testing.assert_array_equal(depth, expected.numpy())  # the very same computation
    info = json.loads(sidecar_path(out).read_text())
    assert info["format"] == "torchscript" and info["opset"] is None
    assert info["verified"]["max_abs_diff_m"] == 0.0


@pytest.mark.slow
def test_height_and_width_override_the_training_size(fusion_model, tmp_path: Path) -> None:
    out = export_model(fusion_model, "torchscript", tmp_path / "m.pt", height=96, width=128)
    image, sparse = _inputs(1, 96, 128)
    with torch.no_grad():
        depth = torch.jit.load(str(out))(torch.from_numpy(image), torch.from_numpy(sparse))
    _assert_matches_pytorch(depth.numpy(), fusion_model.net, image, sparse)
    info = json.loads(sidecar_path(out).read_text())
    assert info["inputs"][0]["shape"] == ["batch", 3, 96, 128]
    assert info["outputs"][0]["shape"] == ["batch", 1, 96, 128]


@pytest.mark.slow
def test_exporting_does_not_change_the_callers_model(fusion_model, tmp_path: Path) -> None:
    before = {k: v.clone() for k, v in fusion_model.net.state_dict().items()}
    wrapper = DepthExportModel(fusion_model.net)
    assert wrapper.net is not fusion_model.net and wrapper.input_names == ["image", "sparse"]
    export_model(fusion_model, "torchscript", tmp_path / "m.pt")
    assert not fusion_model.net.training
    assert all(p.requires_grad for p in fusion_model.net.parameters())
    after = fusion_model.net.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)


# --------------------------------------------------------------------------- errors


def test_bad_options_name_the_key(fusion_model, tmp_path: Path) -> None:
    out = tmp_path / "m.onnx"
    with pytest.raises(
        ValueError,
        match=r"format=tflite: expected one of \['onnx', 'torchscript', 'openvino', 'tensorrt'\]",
    ):
        export_model(fusion_model, "tflite", out)
    with pytest.raises(
        ValueError, match=r"height=70: expected a multiple of 32 .* height=64 or 96"
    ):
        export_model(fusion_model, "onnx", out, height=70)
    with pytest.raises(ValueError, match=r"width=0: expected a positive multiple of 32"):
        export_model(fusion_model, "torchscript", out, width=0)
    with pytest.raises(ValueError, match=r"batch_size=2: fixes the batch axis of format=onnx"):
        export_model(fusion_model, "torchscript", out, batch_size=2)
    with pytest.raises(ValueError, match=r"batch_size=0: expected null"):
        export_model(fusion_model, "onnx", out, batch_size=0)
    with pytest.raises(ValueError, match=r"output=.*that is ckpt_path"):
        export_model(fusion_model, "torchscript", fusion_model.path)
    assert list(tmp_path.iterdir()) == []


def test_config_errors_come_before_loading_the_checkpoint(tmp_path: Path) -> None:
    cfg = compose_config(
        ["ckpt_path=/nonexistent.ckpt", "format=coreml"], tmp_path / "run", "export"
    )
    try:
        with pytest.raises(ValueError, match=r"format=coreml: expected one of"):
            export(cfg)
    finally:
        GlobalHydra.instance().clear()
    cfg = compose_config(["ckpt_path=/nonexistent.ckpt", "height=33"], tmp_path / "run", "export")
    try:
        with pytest.raises(ValueError, match=r"height=33: expected a multiple of 32"):
            export(cfg)
    finally:
        GlobalHydra.instance().clear()
    cfg = compose_config(["ckpt_path=/nonexistent.ckpt"], tmp_path / "run", "export")
    try:
        assert cfg.format == "onnx" and cfg.verify is True and cfg.output is None
        with pytest.raises(FileNotFoundError, match=r"ckpt_path=/nonexistent.ckpt: no such file"):
            export(cfg)
    finally:
        GlobalHydra.instance().clear()


@pytest.mark.slow
def test_a_failed_write_leaves_the_previous_file_untouched(
    fusion_model, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "m.pt"
    out.write_bytes(b"the previous model")
    sidecar_path(out).write_text('{"previous": true}\n')

    def disk_full(module, path) -> None:
        Path(path).write_bytes(b"half a mod")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch.jit, "save", disk_full)
    with pytest.raises(OSError, match="No space left"):
        export_model(fusion_model, "torchscript", out)
    assert out.read_bytes() == b"the previous model"
    assert sidecar_path(out).read_text() == '{"previous": true}\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pt", "m.pt.json"]  # no temp files


@pytest.mark.slow
def test_a_model_that_disagrees_with_pytorch_is_not_written(
    fusion_model, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "m.pt"
    out.write_bytes(b"the previous model")
    real_load = torch.jit.load

    class OffByOneCentimetre(torch.nn.Module):
        def __init__(self, inner) -> None:
            super().__init__()
            self.inner = inner

        def forward(self, *inputs):
            return self.inner(*inputs) + 0.01

    monkeypatch.setattr(
        export_module.torch.jit, "load", lambda *a, **k: OffByOneCentimetre(real_load(*a, **k))
    )
    # 1 cm off: over tolerance=1e-5 (relative), within the default 1e-3 for this model, whose
    # depths are all beyond 10 m.
    with pytest.raises(
        ExportError, match=r"differs from PyTorch's by up to 0.01 m .*tolerance=1e-05"
    ):
        export_model(fusion_model, "torchscript", out, tolerance=1e-5)
    assert out.read_bytes() == b"the previous model"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pt"]
    export_model(fusion_model, "torchscript", out, tolerance=1e-3)
    assert out.read_bytes() != b"the previous model"
    assert json.loads(sidecar_path(out).read_text())["verified"]["max_abs_diff_m"] > 0.009
