"""The network: DenseDepth taps and widths, fusion modes, depth conversion, weight loading."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import safetensors.torch
import timm
import torch

from fusion_depth.config.arguments import config_message
from fusion_depth.models import DenseDepthDecoder, DepthNet, Encoder, InputFusion
from fusion_depth.models import encoder as encoder_module
from fusion_depth.models.encoder import WeightsUnavailableError


@pytest.fixture(scope="module")
def densenet_encoder() -> Encoder:
    torch.manual_seed(0)
    return Encoder("densenet169").eval()


def test_densenet_taps_are_densedepth_skips(densenet_encoder: Encoder) -> None:
    # DenseDepth: conv0 ReLU (64, /2), pool0 (64, /4), transition1 (128, /8),
    # transition2 (256, /16), norm5 (1664, /32).
    assert densenet_encoder.channels == (64, 64, 128, 256, 1664)
    feats = densenet_encoder(torch.rand(1, 3, 64, 96))
    assert [tuple(f.shape[-2:]) for f in feats] == [(32, 48), (16, 24), (8, 12), (4, 6), (2, 3)]
    assert (feats[0] >= 0).all(), "first skip must be after conv0's ReLU"


def test_resnet50_taps() -> None:
    enc = Encoder("resnet50").eval()
    assert enc.channels == (64, 256, 512, 1024, 2048)
    assert "fc" not in enc.stages and "global_pool" not in enc.stages


def test_decoder_halves_channels() -> None:
    dec = DenseDepthDecoder((64, 64, 128, 256, 1664))
    assert dec.bottleneck.out_channels == 832
    assert [b.conv_b.out_channels for b in dec.up] == [416, 208, 104, 52]
    assert dec.head.in_channels == 52 and dec.head.out_channels == 1


@pytest.mark.parametrize("backbone", ["densenet169", "resnet50"])
@pytest.mark.parametrize("fusion", ["rgb", "concat", "add"])
def test_output_shape_every_fusion_and_backbone(backbone: str, fusion: str) -> None:
    net = DepthNet(backbone, fusion, min_depth=0.5, max_depth=80.0, depth_scale=10.0).eval()
    image, sparse = torch.rand(2, 3, 64, 96), torch.rand(2, 1, 64, 96) * 50
    with torch.no_grad():
        reciprocal = net(image, sparse)
        depth = net.predict_depth(image, sparse)
    assert reciprocal.shape == (2, 1, 32, 48)
    assert depth.shape == (2, 1, 32, 48)
    assert depth.min() >= 0.5 and depth.max() <= 80.0


def test_concat_starts_as_add_and_learns_from_sparse() -> None:
    image, sparse = torch.rand(2, 3, 32, 32), torch.rand(2, 1, 32, 32) * 40
    sparse[:, :, :16] = 0  # no return in the top half
    concat, add = InputFusion("concat", max_depth=80.0), InputFusion("add", max_depth=80.0)
    rgb = InputFusion("rgb", max_depth=80.0)
    torch.testing.assert_close(concat(image, sparse), add(image, sparse))
    # Where there is no return the image passes through untouched.
    torch.testing.assert_close(concat(image, sparse)[..., :16, :], rgb(image)[..., :16, :])
    concat(image, sparse).square().sum().backward()
    assert concat.mix.weight.grad[:, 3].abs().sum() > 0, "sparse channel must reach the 1x1 conv"


def test_add_adds_sparse_to_every_channel_before_normalisation() -> None:
    image, sparse = torch.rand(1, 3, 8, 8), torch.rand(1, 1, 8, 8) * 40
    fusion = InputFusion("add", max_depth=80.0)
    diff = fusion(image, sparse) - InputFusion("rgb")(image)
    torch.testing.assert_close(diff, fusion.encode_sparse(sparse) / fusion.std)


def test_sparse_encodings_keep_zero_as_no_return() -> None:
    depth = torch.tensor([0.0, 0.2, 0.5, 5.0, 80.0, 300.0])
    log = InputFusion("add", max_depth=80.0, min_depth=0.5).encode_sparse(depth)
    expected = torch.log(depth[3] / 0.5) / torch.log(torch.tensor(160.0))
    torch.testing.assert_close(log, torch.tensor([0.0, 1 / 256, 1 / 256, expected, 1.0, 1.0]))
    linear = InputFusion("add", max_depth=80.0, sparse_encoding="linear").encode_sparse(depth)
    torch.testing.assert_close(linear, torch.tensor([0.0, 0.0025, 0.00625, 0.0625, 1.0, 1.0]))
    # The log code keeps a near return clearly visible; the linear one nearly loses it.
    assert log[3] > 0.4 > 0.1 > linear[3]
    with pytest.raises(ValueError, match="sparse_encoding='sqrt'"):
        InputFusion("add", sparse_encoding="sqrt")


def test_rgb_ignores_sparse_and_fusion_needs_it() -> None:
    net = DepthNet("resnet50", "rgb").eval()
    image = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        torch.testing.assert_close(net(image, torch.rand(1, 1, 64, 64) * 50), net(image, None))
    with pytest.raises(ValueError, match="sparse"):
        InputFusion("concat")(image, None)
    with pytest.raises(ValueError, match="^mode='sum'"):
        InputFusion("sum")


def test_reciprocal_conversion_round_trip_and_clip() -> None:
    net = DepthNet("resnet50", "rgb", min_depth=1.0, max_depth=50.0, depth_scale=10.0)
    depth = torch.tensor([0.5, 1.0, 7.0, 50.0, 120.0])
    reciprocal = net.to_reciprocal(depth)
    torch.testing.assert_close(reciprocal, torch.tensor([10.0, 10.0, 10 / 7, 0.2, 0.2]))
    torch.testing.assert_close(net.to_depth(reciprocal), depth.clamp(1.0, 50.0))


def test_input_size_must_be_multiple_of_32() -> None:
    net = DepthNet("resnet50", "rgb")
    with pytest.raises(ValueError, match="multiples of 32"):
        net(torch.rand(1, 3, 50, 64))
    with pytest.raises(ValueError, match="min_depth"):
        DepthNet("resnet50", "rgb", min_depth=5.0, max_depth=1.0)


@pytest.mark.parametrize("suffix", [".safetensors", ".pth"])
def test_local_weights_file_loaded_through_timm(tmp_path: Path, suffix: str) -> None:
    # A random-init ImageNet-format checkpoint, classifier included, as timm/hub files are.
    torch.manual_seed(1)
    source = timm.create_model("densenet169", pretrained=False, num_classes=1000)
    state = source.state_dict()
    path = tmp_path / f"densenet169{suffix}"
    if suffix == ".safetensors":
        safetensors.torch.save_file({k: v.contiguous() for k, v in state.items()}, path)
    else:
        torch.save(state, path)
    enc = Encoder("densenet169", weights=str(path))
    torch.testing.assert_close(enc.stages["conv0"].weight, state["features.conv0.weight"])
    torch.testing.assert_close(enc.stages["norm5"].running_var, state["features.norm5.running_var"])


def test_weights_file_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="^weights=.*missing.pth"):
        Encoder("densenet169", weights=str(tmp_path / "missing.pth"))
    with pytest.raises(ValueError, match="safetensors"):
        Encoder("densenet169", weights=str(tmp_path / "weights.txt"))
    wrong = tmp_path / "resnet.pth"
    torch.save(timm.create_model("resnet18", num_classes=0).state_dict(), wrong)
    with pytest.raises(ValueError, match="^weights=.*resnet.pth: not a state dict"):
        Encoder("densenet169", weights=str(wrong))


def test_pretrained_offline_fails_fast_naming_both_ways_out(tmp_path, monkeypatch) -> None:
    import huggingface_hub.constants

    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "torch"))
    monkeypatch.setattr(encoder_module, "_hub_reachable", lambda timeout=3.0: False)
    start = time.perf_counter()
    with pytest.raises(WeightsUnavailableError) as err:
        Encoder("densenet169", pretrained=True)
    assert time.perf_counter() - start < 10
    # The encoder names its arguments; a command names the keys (fusion_depth.config.arguments)
    assert "with weights=" in str(err.value) and "with pretrained=false" in str(err.value)
    shown = config_message(err.value)
    assert "backbone.weights=" in shown and "backbone.pretrained=false" in shown


def test_pretrained_uses_the_local_hub_cache(tmp_path, monkeypatch) -> None:
    import huggingface_hub.constants

    repo = tmp_path / "hub" / "models--timm--resnet18.a1_in1k"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text("abc123")
    (repo / "snapshots" / "abc123").mkdir(parents=True)
    torch.manual_seed(2)
    state = timm.create_model("resnet18", num_classes=1000).state_dict()
    safetensors.torch.save_file(state, repo / "snapshots" / "abc123" / "model.safetensors")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.setattr(encoder_module, "_hub_reachable", lambda timeout=3.0: False)
    enc = Encoder("resnet18", pretrained=True)
    torch.testing.assert_close(enc.stages["conv1"].weight, state["conv1.weight"])
