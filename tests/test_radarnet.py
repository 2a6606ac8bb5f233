"""model=radarnet (Singh et al., CVPR 2023; github.com/nesl/radar-camera-fusion-depth): the tall
association window, the shapes at each stage, the quasi-dense map and the association ground
truth built by hand, the config-time refusals, a checkpoint rebuilt by name, and the two-stage
training (association, then fusion on the stage-1 checkpoint) evaluated by name."""

from __future__ import annotations

import pytest
import torch
from helpers import REPO, run_module

from fusion_depth.config import validate_config
from fusion_depth.errors import ConfigError
from fusion_depth.models import MODELS, create_model
from fusion_depth.models.inference import predict_depth
from fusion_depth.models.radarnet import (
    RadarNet,
    association_labels,
    crop_windows,
    default_window_width,
    paste_windows,
    points_from_sparse,
    quasi_dense_depth,
)
from fusion_depth.runner.checkpoints import load_model
from fusion_depth.utils.checkpoint_file import CheckpointError, plain_config


def _points(rows: list[tuple[float, float, float]], pad_to: int = 0) -> torch.Tensor:
    """(1, P, 6) points from (u, v, depth) rows, valid, then zero rows up to ``pad_to``."""
    points = torch.zeros(1, max(len(rows), pad_to), 6)
    for i, (u, v, d) in enumerate(rows):
        points[0, i, [0, 1, 2, 5]] = torch.tensor([u, v, d, 1.0])
    return points


def test_the_window_is_tall_and_scaled_from_the_papers_patch() -> None:
    """900 × 288 on 900 × 1600 images: the full height, 18 % of the width (multiple of 32)."""
    assert default_window_width(1600) == 288
    assert default_window_width(1248) == 224
    assert default_window_width(96) == 32
    assert RadarNet(stage="association", window_width=64).window(1248) == 64
    with pytest.raises(ValueError, match="window_width=40"):
        RadarNet(window_width=40)


@pytest.mark.parametrize(
    ("u", "first", "last"),
    [(50.0, 34, 65), (3.0, 0, 18), (94.0, 78, 95)],  # centre, clipped left, clipped right
)
def test_the_crop_spans_full_height_and_the_width_clipped_at_the_borders(u, first, last):
    """Pixel values = column + 1, so each crop column tells where it came from (0 = outside)."""
    h, w, width = 64, 96, 32
    columns = torch.arange(1.0, w + 1).expand(1, 1, h, w)
    crop = crop_windows(columns, torch.tensor([[u]]), width)
    assert crop.shape == (1, 1, 1, h, width)  # every row of the image, the window's width
    assert torch.equal(crop[..., 0, :], crop[..., -1, :])  # full height: each row the same
    inside = crop[0, 0, 0, 0][crop[0, 0, 0, 0] > 0].long() - 1
    assert torch.equal(inside, torch.arange(first, last + 1))
    # Pasting back puts every window pixel where it was cropped from.
    pasted = paste_windows(crop[:, :, 0], torch.tensor([[u]]), w)
    expected = torch.zeros(1, 1, h, w)
    expected[..., first : last + 1] = columns[..., first : last + 1]
    assert torch.equal(pasted, expected)


def test_stages_have_the_published_shapes() -> None:
    """Association: one logit per window pixel per point; quasi-dense depth and confidence at
    the input size; fusion: image and depth pyramids fused at strides 2-32, depth out."""
    torch.manual_seed(0)
    net = RadarNet(stage="end_to_end").eval()
    image = torch.rand(2, 3, 64, 96)
    points = torch.cat([_points([(10, 40, 5.0), (60, 30, 12.0), (90, 20, 30.0)])] * 2)
    with torch.no_grad():
        logits, depth, confidence = net.quasi_dense(image, points)
        pyramid = net.fusion_net.image_encoder(image)
        out = net(image, None, points)
    assert logits.shape == (2, 3, 64, 32)
    assert depth.shape == confidence.shape == (2, 1, 64, 96)
    assert [tuple(f.shape[-2:]) for f in pyramid] == [(32, 48), (16, 24), (8, 12), (4, 6), (2, 3)]
    assert [f.shape[1] for f in pyramid] == [64, 64, 128, 256, 512]
    assert net.fusion_net.decoder.head.in_channels == 32
    assert out.shape == (2, 1, 64, 96) and out.min() >= net.min_depth
    assert out.max() <= net.max_depth
    assert net.output_space == "depth"


def test_on_a_cpu_the_association_runs_in_fp32_under_bf16_autocast() -> None:
    """oneDNN's bf16 convolutions gave NaN at random on the window's 1-pixel-wide deepest
    features (AMX CPUs), stopping training; on a CPU the association network is kept in fp32."""
    torch.manual_seed(0)
    net = RadarNet(stage="end_to_end").eval()
    image = torch.rand(2, 3, 64, 96)
    points = torch.cat([_points([(10, 40, 5.0), (60, 30, 12.0), (90, 20, 30.0)])] * 2)
    with torch.no_grad():
        reference = net.association_logits(image, points)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            logits = net.association_logits(image, points)
    assert logits.dtype == torch.float32 and torch.isfinite(logits).all()
    assert torch.equal(logits, reference)


def test_padded_rows_skip_the_association_network_and_change_no_valid_logit() -> None:
    """Only valid points' windows go through the association network: a batch padded to 5 rows
    per image gives the valid rows' logits of the unpadded batch (eval mode, so batch norm does
    not see the batch), 0 for the padding rows, and the network sees 3 windows, not 10."""
    torch.manual_seed(0)
    net = RadarNet(stage="end_to_end").eval()
    image = torch.rand(2, 3, 64, 96)
    rows = [[(10, 40, 5.0), (60, 30, 12.0)], [(90, 20, 30.0)]]
    padded = torch.cat([_points(r, pad_to=5) for r in rows])
    seen = []
    hook = net.association.register_forward_hook(lambda m, args, out: seen.append(len(args[0])))
    with torch.no_grad():
        logits = net.association_logits(image, padded)
        hook.remove()
        alone = [net.association_logits(image[i : i + 1], _points(r)) for i, r in enumerate(rows)]
    assert seen == [3]
    torch.testing.assert_close(logits[0, :2], alone[0][0])
    torch.testing.assert_close(logits[1, :1], alone[1][0])
    assert not logits[0, 2:].any() and not logits[1, 1:].any()
    # A batch with no valid point runs nothing and still has the shape.
    empty = net.association_logits(image, torch.zeros(2, 4, 6))
    assert empty.shape == (2, 4, 64, 32) and not empty.any()


def test_the_quasi_dense_map_keeps_each_point_where_it_passes_the_threshold() -> None:
    """Two points, confidences written by hand: a pixel takes the depth of the most confident
    point at or above 0.5; nothing where neither passes."""
    confidence = torch.zeros(1, 2, 2, 4)
    confidence[0, 0] = torch.tensor([[0.9, 0.6, 0.4, 0.0], [0.5, 0.2, 0.0, 0.0]])
    confidence[0, 1] = torch.tensor([[0.7, 0.8, 0.45, 0.0], [0.49, 0.0, 0.0, 0.99]])
    depth, best = quasi_dense_depth(confidence, torch.tensor([[10.0, 20.0]]), threshold=0.5)
    assert torch.equal(depth[0, 0], torch.tensor([[10.0, 20.0, 0.0, 0.0], [10.0, 0.0, 0.0, 20.0]]))
    assert torch.equal(best[0, 0], torch.tensor([[0.9, 0.8, 0.0, 0.0], [0.5, 0.0, 0.0, 0.99]]))


def test_the_association_ground_truth_comes_from_the_depth_map() -> None:
    """Window pixels within 0.4 m of the point's depth (and with ground truth) are positive."""
    gt = torch.tensor([[10.0, 10.3, 10.45, 9.7], [0.0, 9.59, 20.0, 10.39]]).view(1, 1, 1, 2, 4)
    labels = association_labels(gt, torch.tensor([[10.0]]), max_distance=0.4)
    assert torch.equal(labels[0, 0, 0], torch.tensor([[1.0, 1, 0, 1], [0, 0, 0, 1]]))


def test_the_association_loss_is_weighted_bce_inside_the_image() -> None:
    """pos_weight 2 on positives; window columns outside the image do not count."""
    net = RadarNet(stage="association", window_width=32)
    gt = torch.zeros(1, 1, 32, 64)
    gt[..., :8] = 10.0  # positives in the first 8 columns, negatives elsewhere
    points = _points([(0.0, 10.0, 10.0)])  # the window covers columns -16 … 15
    logits = torch.zeros(1, 1, 32, 32)
    # logit 0: BCE = log 2 per pixel; positives weigh 2 → mean over 16 columns (8 pos, 8 neg)
    expected = torch.log(torch.tensor(2.0)) * (8 * 2 + 8) / 16
    torch.testing.assert_close(net.association_loss(logits, points, gt), expected)


def test_points_from_a_sparse_map_are_its_returns_nearest_first() -> None:
    sparse = torch.zeros(1, 1, 4, 5)
    sparse[0, 0, 1, 3], sparse[0, 0, 2, 0], sparse[0, 0, 3, 4] = 20.0, 5.0, 12.0
    points = points_from_sparse(sparse, max_points=4)
    assert points.shape == (1, 4, 6)
    assert points[0, :, [0, 1, 2, 5]].tolist() == [
        [0, 2, 5, 1],
        [4, 3, 12, 1],
        [3, 1, 20, 1],
        [0, 0, 0, 0],
    ]


def test_points_from_the_batch_or_from_the_sparse_map_give_the_same_depth() -> None:
    """predict/export have only the sparse map: the derived points are the batch's."""
    torch.manual_seed(0)
    net = RadarNet(stage="end_to_end").eval()
    image, sparse = torch.rand(1, 3, 64, 96), torch.zeros(1, 1, 64, 96)
    rows = [(10, 40, 5.0), (60, 30, 12.0)]
    for u, v, d in rows:
        sparse[0, 0, v, u] = d
    with torch.no_grad():
        from_batch = predict_depth(net, image, sparse, points=_points(rows, pad_to=8))
        from_map = predict_depth(net, image, sparse)
    torch.testing.assert_close(from_batch, from_map)


def test_the_default_encoder_and_loss_follow_the_model(make_config) -> None:
    cfg = make_config("model=radarnet", "fusion=concat")
    assert (cfg.backbone.name, cfg.loss.name, cfg.model.net.stage) == (
        "resnet18",
        "l1_only",
        "end_to_end",
    )
    assert MODELS["radarnet"].sensors == ("radar",)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["fusion=rgb"], "model=radarnet cannot take fusion=rgb"),
        (["fusion=concat", "backbone=resnet50"], "model=radarnet cannot take backbone=resnet50"),
        (
            ["fusion=concat", "dataset.reader.sparse=lidar"],
            r"model=radarnet cannot take dataset.sensor=lidar \(dataset=procedural\)",
        ),
        (
            ["fusion=concat", "dataset=topview", "dataset.root=/nonexistent"],
            r"model=radarnet cannot take dataset.sensor=none \(dataset=topview\)",
        ),
    ],
)
def test_radarnet_refuses_what_it_cannot_take_at_config_time(make_config, overrides, message):
    cfg = make_config("model=radarnet", *overrides)
    with pytest.raises(ConfigError, match=message):
        validate_config(cfg)


def test_a_checkpoint_is_rebuilt_by_the_model_name(tmp_path, smoke_dataset) -> None:
    """A fusion-stage checkpoint: rebuilt without re-reading its stage-1 file, its association
    network (and the flag that it is trained) from its own weights."""
    kwargs = {"backbone": "resnet18", "fusion": "concat", "min_depth": 0.5, "max_depth": 80.0}
    torch.manual_seed(0)
    net = create_model("radarnet", stage="fusion", **kwargs)
    net.association_trained.fill_(True)
    config = {
        "model": {
            "net": {
                "name": "radarnet",
                **kwargs,
                "stage": "fusion",
                "association_weights": str(tmp_path / "gone.ckpt"),
                "depth_scale": 10.0,
            }
        },
        "fusion": {"mode": "concat"},
        "backbone": {"name": "resnet18"},
        "loss": {"pixel": "l1"},
        "dataset": smoke_dataset,
    }
    path = tmp_path / "radarnet.ckpt"
    state = {f"net.{k}": v for k, v in net.state_dict().items()}
    torch.save({"state_dict": state, "fusion_depth_config": plain_config(config)}, path)
    loaded = load_model(path)
    assert isinstance(loaded.net, RadarNet) and loaded.net.stage == "fusion"
    assert bool(loaded.net.association_trained)
    image, points = torch.rand(1, 3, 64, 96), _points([(20, 30, 8.0)])
    with torch.no_grad():
        torch.testing.assert_close(loaded.net(image, None, points), net.eval()(image, None, points))
    # A checkpoint of another model is no association checkpoint.
    other = tmp_path / "other.ckpt"
    config["model"]["net"] = {"name": "sparse_to_dense", **kwargs}
    torch.save({"state_dict": {}, "fusion_depth_config": plain_config(config)}, other)
    with pytest.raises(CheckpointError, match=f"association_weights={other}: not a radarnet"):
        RadarNet(stage="fusion", association_weights=str(other))
    with pytest.raises(CheckpointError, match=f"association_weights={tmp_path}/gone.ckpt: no such"):
        RadarNet(stage="fusion", association_weights=str(tmp_path / "gone.ckpt"))


def test_the_fusion_stage_needs_a_trained_association() -> None:
    net = RadarNet(stage="fusion").train()
    batch = {
        "image": torch.rand(2, 3, 64, 96),
        "sparse": torch.zeros(2, 1, 64, 96),
        "depth": torch.rand(2, 1, 64, 96) * 20,
    }
    with pytest.raises(ValueError, match="association_weights"):
        net.training_loss(batch, lambda o, d: {"loss": (o - d).abs().mean()})
    assert not net.association.training  # frozen: stays in eval mode
    assert not any(p.requires_grad for p in net.association.parameters())


@pytest.mark.slow
def test_the_two_stages_train_and_the_second_evaluates_by_name(tmp_path) -> None:
    """Stage 1 (association BCE), stage 2 on its checkpoint (L1 in metres), then evaluate."""
    common = ["model=radarnet", "fusion=concat", "experiment=smoke", "trainer.max_epochs=1"]
    common.append("logger=none")
    first = run_module(
        [
            "fusion_depth.train",
            *common,
            "model.net.stage=association",
            f"hydra.run.dir={tmp_path / 'association'}",
        ],
        REPO,
    )
    assert first.returncode == 0, first.stderr[-3000:]
    (stage1,) = (tmp_path / "association" / "checkpoints").glob("epoch*.ckpt")
    second = run_module(
        [
            "fusion_depth.train",
            *common,
            "model.net.stage=fusion",
            f"model.net.association_weights={stage1}",
            f"hydra.run.dir={tmp_path / 'fusion'}",
        ],
        REPO,
    )
    assert second.returncode == 0, second.stderr[-3000:]
    (stage2,) = (tmp_path / "fusion" / "checkpoints").glob("epoch*.ckpt")
    loaded = load_model(stage2)
    assert loaded.net.stage == "fusion" and bool(loaded.net.association_trained)
    first_state = torch.load(stage1, weights_only=True)["state_dict"]
    for key, value in loaded.net.association.state_dict().items():
        torch.testing.assert_close(value, first_state[f"net.association.{key}"])  # frozen
    scored = run_module(
        ["fusion_depth.evaluate", f"ckpt_path={stage2}", f"hydra.run.dir={tmp_path / 'eval'}"],
        REPO,
    )
    assert scored.returncode == 0, scored.stderr[-3000:]
    assert (tmp_path / "eval" / "metrics.json").is_file()


def test_the_training_flip_mirrors_the_radar_points_with_the_image() -> None:
    """Augmentation flips image, maps and points together (u → W - 1 - u; padded rows stay)."""
    from fusion_depth.data.transforms import TrainAugmentation

    sparse = torch.zeros(1, 1, 8, 10)
    sparse[0, 0, 3, 2] = 7.0
    batch = {
        "image": torch.rand(1, 3, 8, 10),
        "sparse": sparse,
        "depth": torch.rand(1, 1, 8, 10),
        "radar_points": _points([(2, 3, 7.0)], pad_to=2),
    }
    flipped = TrainAugmentation(flip_p=1.0, color_p=0.0)(batch)
    u, v = flipped["radar_points"][0, 0, :2].long().tolist()
    assert (u, v) == (7, 3) and flipped["sparse"][0, 0, v, u] == 7.0
    assert not flipped["radar_points"][0, 1].any()
    kept = TrainAugmentation(flip_p=0.0, color_p=0.0)(batch)
    assert torch.equal(kept["radar_points"], batch["radar_points"])


def test_fake_points_come_from_the_ground_truth_as_radarnets_training_draws_them() -> None:
    """RadarNet's RadarNetTrainingDataset: with probability p an image's points become ground-
    truth pixels deeper than 1 m, the column moved by N(0, 25 px at 1600 columns) and
    truncated, the depth by U(0, 0.4) m, the radar's row kept."""
    torch.manual_seed(0)
    n, width = 3000, 320  # σ = 25 × 320 / 1600 = 5 pixels
    depth = torch.zeros(n, 1, 32, width)
    depth[:, 0, 8:24, 150] = 20.0  # the only pixels deeper than 1 m: one column
    depth[:, 0, 0, :] = 0.9  # shallower than 1 m: never a fake's origin
    radar = torch.zeros(n, 4, 6)
    radar[..., 0], radar[..., 1], radar[..., 2], radar[..., 5] = 40.0, 17.6, 7.0, 1.0
    net = RadarNet(stage="association", fake_point_probability=1.0)
    fake = net._fake_points(radar, depth)
    assert torch.equal(fake[..., 1], torch.full((n, 4), 17.0))  # the radar's row, truncated
    assert torch.equal(fake[..., 5], torch.ones(n, 4))
    assert ((fake[..., 2] >= 20.0) & (fake[..., 2] < 20.4)).all()
    assert fake[..., 2].mean().item() == pytest.approx(20.2, abs=0.01)
    u = fake[..., 0]
    assert torch.equal(u, u.trunc()) and (u >= 0).all() and (u <= width).all()
    # truncation moves the mean half a pixel down; the spread is σ
    assert u.mean().item() == pytest.approx(149.5, abs=0.1)
    assert u.std().item() == pytest.approx(5.0, rel=0.05)
    # at probability 0.1, about a tenth of the images; an image without deep pixels keeps its own
    net.fake_point_probability = 0.1
    changed = (net._fake_points(radar, depth) != radar).any(-1).any(-1).float().mean().item()
    assert changed == pytest.approx(0.1, abs=0.02)
    net.fake_point_probability = 1.0
    assert torch.equal(net._fake_points(radar, torch.zeros_like(depth)), radar)
    net.fake_point_probability = 0.0
    assert net._fake_points(radar, depth) is radar
    # validation draws none; a crop keeps the frame's noise when it is given in pixels
    net.fake_point_probability = 1.0
    assert net.eval()._fake_points(radar, depth) is radar
    net.train().fake_column_noise = 25.0
    assert net._fake_points(radar, depth)[..., 0].std().item() == pytest.approx(25.0, rel=0.05)


def test_the_fusion_loss_weighs_the_measured_pixels_as_fusionnet_does() -> None:
    """FusionNet's compute_loss with --w_lidar_loss: L1 over the filled target's pixels that
    were not measured, plus the weight times L1 over the measured ones; without a measured
    map in the batch, L1 over the target."""
    torch.manual_seed(0)
    net = RadarNet(stage="fusion", lidar_loss_weight=2.0, window_width=32).train()
    net.association_trained.fill_(True)
    assert net.wants_measured_depth
    image, depth = torch.rand(2, 3, 64, 96), torch.rand(2, 1, 64, 96) * 30 + 1
    measured = torch.where(torch.rand_like(depth) < 0.1, depth, torch.zeros_like(depth))
    sparse = torch.zeros_like(depth)
    sparse[:, :, 40, 50] = 12.0
    batch = {"image": image, "sparse": sparse, "depth": depth, "depth_measured": measured}

    def l1(output, target):
        mask = target > 0
        return {"loss": (output - target).abs()[mask].mean()}

    torch.manual_seed(1)
    losses = net.training_loss(batch, l1)
    torch.manual_seed(1)
    output = net(image, sparse)
    unmeasured = measured == 0
    expected = (output - depth).abs()[unmeasured].mean() + 2.0 * (output - measured).abs()[
        ~unmeasured
    ].mean()
    torch.testing.assert_close(losses["loss"], expected)
    torch.testing.assert_close(losses["lidar"], (output - measured).abs()[~unmeasured].mean())
    del batch["depth_measured"]
    torch.manual_seed(1)
    torch.testing.assert_close(net.training_loss(batch, l1)["loss"], (output - depth).abs().mean())
    assert not RadarNet(stage="association", lidar_loss_weight=2.0).wants_measured_depth
