"""model=sparse_to_dense (Ma & Karaman 2018) and the model table: the published architecture
stage by stage, the up-projection block against its definition (Laina et al. 2016), the
config-time refusals, and a checkpoint rebuilt by name."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from helpers import REPO, run_module, run_sweep

from fusion_depth.config import validate_config
from fusion_depth.errors import ConfigError
from fusion_depth.models import MODELS, create_model
from fusion_depth.models.sparse_to_dense import SparseToDense, Unpool, UpProjection
from fusion_depth.runner.checkpoints import load_model
from fusion_depth.runner.record import load_runs
from fusion_depth.utils.checkpoint_file import plain_config


def _stage_shapes(net: SparseToDense, image: torch.Tensor, sparse: torch.Tensor) -> list:
    shapes = []
    parts = [net.encoder, net.bottleneck, *net.decoder, net.head]
    hooks = [p.register_forward_hook(lambda m, i, o: shapes.append(tuple(o.shape))) for p in parts]
    out = net(image, sparse)
    for hook in hooks:
        hook.remove()
    return [*shapes, tuple(out.shape)]


@pytest.mark.parametrize(("backbone", "width"), [("resnet18", 512), ("resnet50", 2048)])
def test_stages_have_the_published_shapes(backbone: str, width: int) -> None:
    """Encoder at stride 32 with the ResNet's width, a 1×1 conv halving it, four up-projections
    each doubling the size and halving the channels, one channel, then the input's size."""
    net = SparseToDense(backbone=backbone, fusion="concat").eval()
    image, sparse = torch.rand(2, 3, 64, 96), torch.rand(2, 1, 64, 96) * 30
    assert _stage_shapes(net, image, sparse) == [
        (2, width, 2, 3),
        (2, width // 2, 2, 3),
        (2, width // 4, 4, 6),
        (2, width // 8, 8, 12),
        (2, width // 16, 16, 24),
        (2, width // 32, 32, 48),
        (2, 1, 32, 48),
        (2, 1, 64, 96),
    ]
    assert net.encoder[0].in_channels == 4  # RGBd: the first convolution takes the sparse channel


def test_rgb_variant_takes_three_channels_and_ignores_sparse() -> None:
    torch.manual_seed(0)
    net = SparseToDense(fusion="rgb").eval()
    assert net.encoder[0].in_channels == 3 and not net.fusion.uses_sparse
    image = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        assert torch.equal(net(image, torch.rand(1, 1, 64, 64)), net(image, None))


def test_unpool_puts_each_value_top_left_of_its_block() -> None:
    x = torch.arange(12.0).view(1, 2, 2, 3)
    y = Unpool(2)(x)
    assert y.shape == (1, 2, 4, 6)
    assert torch.equal(y[..., ::2, ::2], x)
    mask = torch.ones_like(y, dtype=torch.bool)
    mask[..., ::2, ::2] = False
    assert not y[mask].any()


def test_up_projection_matches_its_definition() -> None:
    """unpool → (5×5 conv, BN, ReLU, 3×3 conv, BN) + (5×5 conv, BN) → ReLU, written out here
    with the block's own weights and batch-norm statistics."""
    torch.manual_seed(0)
    block = UpProjection(8)
    for bn in (m for m in block.modules() if isinstance(m, torch.nn.BatchNorm2d)):
        bn.running_mean.uniform_(-0.5, 0.5)
        bn.running_var.uniform_(0.5, 2.0)
        bn.weight.data.uniform_(0.5, 1.5)
        bn.bias.data.uniform_(-0.2, 0.2)
    block.eval()
    x = torch.randn(2, 8, 5, 7)
    up = torch.zeros(2, 8, 10, 14)
    up[..., ::2, ::2] = x

    def bn(t: torch.Tensor, m: torch.nn.BatchNorm2d) -> torch.Tensor:
        return F.batch_norm(t, m.running_mean, m.running_var, m.weight, m.bias, eps=m.eps)

    conv5, bn1, _, conv3, bn2 = block.upper
    hidden = F.relu(bn(F.conv2d(up, conv5.weight, padding=2), bn1))
    upper = bn(F.conv2d(hidden, conv3.weight, padding=1), bn2)
    proj_conv, proj_bn = block.projection
    projection = bn(F.conv2d(up, proj_conv.weight, padding=2), proj_bn)
    expected = F.relu(upper + projection)
    with torch.no_grad():
        got = block(x)
    assert got.shape == (2, 4, 10, 14)
    torch.testing.assert_close(got, expected)
    assert all(c.bias is None for c in (conv5, conv3, proj_conv))


def test_it_predicts_metres_and_trains_in_metres() -> None:
    net = create_model("sparse_to_dense", fusion="concat", min_depth=0.5, max_depth=80.0)
    assert net.output_space == "depth"
    depth = torch.tensor([0.1, 5.0, 200.0])
    assert torch.equal(net.to_output(depth), torch.tensor([0.5, 5.0, 80.0]))
    out = net.predict_depth(torch.rand(1, 3, 32, 64), torch.rand(1, 1, 32, 64) * 10)
    assert out.shape == (1, 1, 32, 64) and out.min() >= 0.5 and out.max() <= 80.0


def test_the_default_encoder_and_loss_follow_the_model(make_config) -> None:
    """Each model brings its published encoder and loss; backbone=/loss= still choose."""
    s2d = make_config("model=sparse_to_dense")
    paper = make_config("model=densedepth", "experiment=paper")  # not the built-in recipe's
    assert (s2d.backbone.name, s2d.loss.name, s2d.loss.w_ssim) == ("resnet18", "l1_only", 0.0)
    assert (paper.backbone.name, paper.loss.pixel, paper.loss.w_ssim) == ("densenet169", "l1", 1.0)
    assert make_config("model=sparse_to_dense", "loss=berhu").loss.pixel == "berhu"
    assert (
        make_config("model=sparse_to_dense", "backbone=resnet50").model.net.backbone == "resnet50"
    )


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["fusion=add"], "model=sparse_to_dense cannot take fusion=add"),
        (["backbone=densenet169"], "model=sparse_to_dense cannot take backbone=densenet169"),
        (["model.net.name=nope"], "model.net.name='nope': expected one of"),
        (["+model.net.sparse_encoding=log"], "model.net.sparse_encoding: unknown key"),
    ],
)
def test_a_model_refuses_what_it_cannot_take_at_config_time(make_config, overrides, message):
    cfg = make_config("model=sparse_to_dense", *overrides)
    with pytest.raises(ConfigError, match=message):
        validate_config(cfg)


@pytest.mark.slow
def test_every_model_config_composes_and_builds(make_config, tmp_path) -> None:
    from helpers import save_untrained_checkpoint

    dataset = {"name": "procedural", "min_depth": 0.5, "max_depth": 80.0, "depth_scale": 10.0}
    prior = save_untrained_checkpoint(tmp_path / "prior.ckpt", "rgb", dataset, backbone="resnet10t")
    for name, entry in MODELS.items():
        # a model that works on a prior gets one: a checkpoint of this platform
        given = ["prior=checkpoint", f"prior.weights={prior}"] if entry.needs_prior else []
        cfg = make_config(
            f"model={name}", f"fusion={entry.fusions[-1]}", "experiment=smoke", *given
        )
        validate_config(cfg)
        net = create_model(**{k: v for k, v in cfg.model.net.items() if k != "_target_"})
        assert type(net).__name__ == entry.cls


def test_a_checkpoint_is_rebuilt_by_the_model_name(tmp_path, smoke_dataset) -> None:
    kwargs = {"backbone": "resnet18", "fusion": "concat", "min_depth": 0.5, "max_depth": 80.0}
    torch.manual_seed(0)
    net = create_model("sparse_to_dense", **kwargs)
    config = {
        "model": {"net": {"name": "sparse_to_dense", **kwargs, "depth_scale": 10.0}},
        "fusion": {"mode": "concat"},
        "backbone": {"name": "resnet18"},
        "loss": {"pixel": "l1"},
        "dataset": smoke_dataset,
    }
    path = tmp_path / "s2d.ckpt"
    state = {f"net.{k}": v for k, v in net.state_dict().items()}
    torch.save({"state_dict": state, "fusion_depth_config": plain_config(config)}, path)
    loaded = load_model(path)
    assert isinstance(loaded.net, SparseToDense)
    image, sparse = torch.rand(1, 3, 64, 96), torch.rand(1, 1, 64, 96) * 20
    with torch.no_grad():
        torch.testing.assert_close(loaded.net(image, sparse), net.eval()(image, sparse))


@pytest.mark.slow
def test_sparse_to_dense_trains_evaluates_and_predicts(tmp_path) -> None:
    """The model through the same machinery as the paper's: train (its L1 loss), then the
    printed best checkpoint scored by evaluate, which rebuilds it by name."""
    trained = run_module(
        [
            "fusion_depth.train",
            "model=sparse_to_dense",
            "fusion=concat",
            "loss=l1_only",
            "experiment=smoke",
            "trainer.max_epochs=1",
            "logger=none",
            f"hydra.run.dir={tmp_path / 'run'}",
        ],
        REPO,
    )
    assert trained.returncode == 0, trained.stderr[-3000:]
    (best,) = (tmp_path / "run" / "checkpoints").glob("epoch*.ckpt")
    scored = run_module(
        ["fusion_depth.evaluate", f"ckpt_path={best}", f"hydra.run.dir={tmp_path / 'eval'}"],
        REPO,
    )
    assert scored.returncode == 0, scored.stderr[-3000:]
    assert (tmp_path / "eval" / "metrics.json").is_file()


@pytest.mark.slow
def test_the_methods_sweep_runs_each_model_with_its_own_encoder_and_loss(tmp_path) -> None:
    """sweeps/methods.yaml under the smoke experiment, one seed: one run per model."""
    result = run_sweep("methods", ["seed=42", "trainer.max_epochs=1"], tmp_path / "sweep")
    assert result.returncode == 0, result.stderr[-3000:]
    runs = load_runs(tmp_path / "sweep")
    assert sorted((r.run.model, r.run.backbone, r.run.loss) for r in runs) == [
        ("densedepth", "resnet10t", "l1"),  # experiment=smoke's encoder for DenseDepth
        ("radarnet", "resnet18", "l1_only"),
        ("sparse_to_dense", "resnet18", "l1_only"),
    ]
    assert all(r.run.fusion == "concat" and r.status == "ok" for r in runs)
