"""``backbone=timm``: any timm model's own feature pyramid feeds the DenseDepth decoder (issue 16).

All models at random initialisation (no network): ConvNeXt (first level at stride 4, so a learned
stride-2 stem), EfficientNet and RegNet (their stem is the stride-2 level).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import safetensors.torch
import timm
import torch

from fusion_depth.config.validation import validate_config
from fusion_depth.errors import ConfigError
from fusion_depth.models import DepthNet, Encoder
from fusion_depth.models import encoder as encoder_module
from fusion_depth.models.encoder import ENCODER_SPECS
from fusion_depth.runner.checkpoints import load_model
from fusion_depth.utils.checkpoint_file import plain_config

TESTED = ("convnext_atto", "efficientnet_b0", "regnety_002")
# Strides 2, 4, 8, 16, 32 of a 64×96 input.
SIZES = [(32, 48), (16, 24), (8, 12), (4, 6), (2, 3)]


@pytest.mark.parametrize("name", TESTED)
def test_pyramid_gives_the_five_strides_and_a_finite_half_resolution_depth(name: str) -> None:
    torch.manual_seed(0)
    net = DepthNet(name, "concat", backbone_taps="pyramid").eval()
    image, sparse = torch.rand(2, 3, 64, 96), torch.rand(2, 1, 64, 96) * 50
    with torch.no_grad():
        feats = net.encoder(net.fusion(image, sparse))
        reciprocal = net(image, sparse)
    assert [tuple(f.shape[-2:]) for f in feats] == SIZES
    assert tuple(f.shape[1] for f in feats) == net.encoder.channels
    assert reciprocal.shape == (2, 1, 32, 48) and torch.isfinite(reciprocal).all()
    # ConvNeXt's patchify stem has nothing at stride 2: the learned stem gives that skip.
    assert (net.encoder.stem is not None) == (name == "convnext_atto")
    first = {
        "convnext_atto": "stem (learned)",
        "efficientnet_b0": "blocks.0",
        "regnety_002": "stem",
    }
    assert net.encoder.taps[0] == first[name]


@pytest.mark.parametrize("name", TESTED)
def test_channels_last_and_bf16_autocast(name: str) -> None:
    net = DepthNet(name, "add", backbone_taps="pyramid").eval()
    net = net.to(memory_format=torch.channels_last)
    image = torch.rand(1, 3, 64, 96).contiguous(memory_format=torch.channels_last)
    sparse = torch.rand(1, 1, 64, 96) * 50
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = net(image, sparse)
    assert out.dtype == torch.float32 and out.shape == (1, 1, 32, 48)
    assert torch.isfinite(out).all()


def test_paper_taps_are_unchanged() -> None:
    # The paper's backbones keep their hand-listed taps (tests/test_models.py checks the maps).
    assert ENCODER_SPECS["densenet169"].taps == (
        "norm0",
        "pool0",
        "transition1",
        "transition2",
        "norm5",
    )
    assert ENCODER_SPECS["resnet50"].taps == ("act1", "layer1", "layer2", "layer3", "layer4")
    assert Encoder("resnet50").taps == ENCODER_SPECS["resnet50"].taps
    with pytest.raises(ValueError, match="^name=convnext_atto: expected one of .*timm"):
        Encoder("convnext_atto")  # taps="paper" is the default


@pytest.mark.parametrize(
    "name,why",
    [
        ("vit_tiny_patch16_224", "strides 16; expected levels at strides 4, 8, 16 and 32"),
        ("swin_tiny_patch4_window7_224", "cannot run on a 64×64 image"),
    ],
)
def test_a_model_without_strides_4_to_32_is_refused(name: str, why: str) -> None:
    with pytest.raises(ValueError, match=f"^name={name}: .*{why}"):
        Encoder(name, taps="pyramid")


def _write_state(name: str, path: Path) -> dict[str, torch.Tensor]:
    """A random-init ImageNet-format checkpoint of ``name``, classifier included."""
    torch.manual_seed(1)
    state = timm.create_model(name, pretrained=False, num_classes=1000).state_dict()
    if path.suffix == ".safetensors":
        safetensors.torch.save_file({k: v.contiguous() for k, v in state.items()}, path)
    else:
        torch.save(state, path)
    return state


def _assert_body_holds(encoder: Encoder, state: dict[str, torch.Tensor]) -> None:
    # timm's FeatureListNet renames "stages.0" to "stages_0"; compare with "." and "_" alike.
    source = {k.replace(".", "_"): v for k, v in state.items()}
    body = encoder.body.state_dict()
    assert len(body) > 20
    for key, value in body.items():
        torch.testing.assert_close(value, source[key.replace(".", "_")], msg=key)


@pytest.mark.parametrize(
    "name,suffix",
    [("convnext_atto", ".safetensors"), ("efficientnet_b0", ".pth"), ("regnety_002", ".pt")],
)
def test_weights_from_a_local_file(tmp_path: Path, name: str, suffix: str) -> None:
    path = tmp_path / f"{name}{suffix}"
    state = _write_state(name, path)
    torch.manual_seed(7)  # anything not loaded would differ from the file
    _assert_body_holds(Encoder(name, weights=str(path), taps="pyramid"), state)


def test_a_file_of_another_architecture_is_refused(tmp_path: Path) -> None:
    wrong = tmp_path / "resnet.pth"
    torch.save(timm.create_model("resnet18", num_classes=0).state_dict(), wrong)
    with pytest.raises(ValueError, match="^weights=.*resnet.pth: not a state dict"):
        Encoder("convnext_atto", weights=str(wrong), taps="pyramid")


def test_pretrained_uses_the_local_hub_cache(tmp_path: Path, monkeypatch) -> None:
    import huggingface_hub.constants

    hub_id = timm.models.get_pretrained_cfg("convnext_atto").hf_hub_id
    repo = tmp_path / "hub" / f"models--{hub_id.replace('/', '--')}"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text("abc123")
    (repo / "snapshots" / "abc123").mkdir(parents=True)
    state = _write_state("convnext_atto", repo / "snapshots" / "abc123" / "model.safetensors")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.setattr(encoder_module, "_hub_reachable", lambda timeout=3.0: False)
    _assert_body_holds(Encoder("convnext_atto", pretrained=True, taps="pyramid"), state)


def test_config_composes_and_names_the_taps(make_config) -> None:
    cfg = make_config("experiment=smoke", "backbone=timm", "backbone.name=convnext_atto")
    validate_config(cfg)
    assert (cfg.model.net.backbone, cfg.model.net.backbone_taps) == ("convnext_atto", "pyramid")
    cfg = make_config("experiment=paper")
    validate_config(cfg)
    assert (cfg.model.net.backbone, cfg.model.net.backbone_taps) == ("densenet169", "paper")


@pytest.mark.parametrize(
    "overrides,match",
    [
        (
            ["backbone=timm", "backbone.name=convnxt_atto"],
            r"^backbone.name=convnxt_atto: not a timm model \(did you mean convnext_atto\?\)",
        ),
        (
            ["backbone=timm", "backbone.name=convnext_tiny.fb_in99k"],
            r"^backbone.name=convnext_tiny.fb_in99k: no pretrained tag 'fb_in99k'",
        ),
        (["backbone=timm", "backbone.taps=dense"], r"^backbone.taps=dense: expected one of"),
        (["backbone.name=convnext_atto"], r"^backbone.name=convnext_atto: expected one of"),
    ],
)
def test_an_unknown_name_fails_at_config_time(make_config, overrides, match) -> None:
    with pytest.raises(ConfigError, match=match) as err:
        validate_config(make_config("experiment=smoke", *overrides))
    assert "\n" not in str(err.value) and len(str(err.value)) < 200


def test_a_checkpoint_rebuilds(tmp_path: Path, smoke_dataset: dict) -> None:
    torch.manual_seed(0)
    kwargs = {
        "backbone": "convnext_atto",
        "backbone_taps": "pyramid",
        "fusion": "concat",
        "min_depth": smoke_dataset["min_depth"],
        "max_depth": smoke_dataset["max_depth"],
        "depth_scale": smoke_dataset["depth_scale"],
        "sparse_encoding": "log",
    }
    net = DepthNet(**kwargs).eval()
    config = {
        "model": {"net": {"name": "densedepth", **kwargs}},
        "fusion": {"mode": "concat"},
        "backbone": {"name": "convnext_atto", "taps": "pyramid"},
        "dataset": smoke_dataset,
    }
    path = tmp_path / "timm.ckpt"
    state = {f"net.{k}": v for k, v in net.state_dict().items()}
    torch.save({"state_dict": state, "fusion_depth_config": plain_config(config)}, path)
    loaded = load_model(path)
    assert loaded.net.encoder.taps == net.encoder.taps and loaded.net.encoder.stem is not None
    image, sparse = torch.rand(1, 3, 64, 96), torch.rand(1, 1, 64, 96) * 50
    with torch.no_grad():
        torch.testing.assert_close(loaded.net(image, sparse), net(image, sparse))


@pytest.mark.slow
def test_one_training_step_and_the_checkpoint_evaluates(make_config) -> None:
    from fusion_depth.train.fit import train

    cfg = make_config(
        "experiment=smoke",
        "backbone=timm",
        "backbone.name=convnext_atto",
        "fusion=concat",
        "logger=none",
        "trainer.max_epochs=1",
        "trainer.limit_train_batches=1",
        "trainer.limit_test_batches=1",
    )
    results = train(cfg)
    assert results["global_step"] == 1 and results["run"]["backbone"] == "convnext_atto"
    assert all(torch.isfinite(torch.tensor(v)) for v in results["test"].values())
    saved = json.loads((Path(cfg.paths.output_dir) / "metrics.json").read_text())
    loaded = load_model(saved["best_checkpoint"])
    assert loaded.backbone == "convnext_atto" and loaded.net.encoder.stem is not None


@pytest.mark.slow
def test_onnx_export_matches_pytorch(tmp_path: Path) -> None:
    import numpy as np
    import onnxruntime as ort

    from fusion_depth.export import export_model
    from fusion_depth.models.inference import predict_depth

    torch.manual_seed(0)
    net = DepthNet("convnext_atto", "concat", backbone_taps="pyramid").eval()
    out = export_model(net, "onnx", tmp_path / "timm.onnx", 64, 64, batch_size=1)
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    image, sparse = torch.rand(1, 3, 64, 64), torch.rand(1, 1, 64, 64) * 50
    (depth,) = session.run(["depth"], {"image": image.numpy(), "sparse": sparse.numpy()})
    with torch.no_grad():
        expected = predict_depth(net, image, sparse).numpy()
    np.testing.assert_allclose(depth, expected, rtol=1e-4, atol=1e-3)


def _train_checkpoint(path: Path, net: DepthNet) -> Path:
    """A file as train writes it, as far as the encoder's reader looks: the run config and the
    module's state dict (``net.*``)."""
    from fusion_depth.utils.checkpoint_file import CONFIG_KEY

    state = {f"net.{k}": v for k, v in net.state_dict().items()}
    config = {"model": {"net": {"name": "densedepth", "fusion": "rgb"}}}
    torch.save({"state_dict": state, CONFIG_KEY: config}, path)
    return path


def test_a_train_checkpoint_as_weights_starts_the_encoder_from_its_encoder(tmp_path) -> None:
    """Transfer learning (backbone.weights=<a .ckpt train wrote>): the encoder, and nothing
    else, comes from the checkpoint's network, whatever its fusion was."""
    torch.manual_seed(1)
    source = DepthNet("resnet10t", "rgb")
    with torch.no_grad():
        for p in source.parameters():
            p.add_(0.1)  # not what a fresh init gives
    file = _train_checkpoint(tmp_path / "source.ckpt", source)
    torch.manual_seed(2)
    target = DepthNet("resnet10t", "concat", weights=str(file))
    for key, value in source.encoder.state_dict().items():
        torch.testing.assert_close(target.encoder.state_dict()[key], value)
    fresh = DepthNet("resnet10t", "concat")
    decoder = next(iter(target.decoder.state_dict()))
    assert not torch.equal(
        target.decoder.state_dict()[decoder], source.decoder.state_dict()[decoder]
    )
    assert target.fusion.mix.weight.shape == fresh.fusion.mix.weight.shape


def test_a_checkpoint_of_another_backbone_is_refused_in_one_line(tmp_path) -> None:
    from fusion_depth.errors import ArgumentError

    file = _train_checkpoint(tmp_path / "other.ckpt", DepthNet("resnet18", "rgb"))
    with pytest.raises(
        ArgumentError, match=r"^weights=.*other.ckpt: its encoder has no .*backbone=resnet10t"
    ):
        DepthNet("resnet10t", "rgb", weights=str(file))
    with pytest.raises(ArgumentError, match=r"^weights=.*missing.ckpt: no such file"):
        DepthNet("resnet10t", "rgb", weights=str(tmp_path / "missing.ckpt"))
    (tmp_path / "junk.ckpt").write_bytes(b"not a checkpoint")
    with pytest.raises(ArgumentError, match=r"^weights=.*junk.ckpt: ") as caught:
        DepthNet("resnet10t", "rgb", weights=str(tmp_path / "junk.ckpt"))
    assert "\n" not in str(caught.value)
