"""Target preparation, augmentation and the non-finite loss guard of the LightningModule."""

from __future__ import annotations

from functools import partial

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader

from fusion_depth.data.transforms import TrainAugmentation
from fusion_depth.losses.depth_loss import DepthLoss
from fusion_depth.models import DepthNet
from fusion_depth.runner.module import DepthModule, NonFiniteLossError, downsample_depth


def test_downsample_dense_depth_is_area_average() -> None:
    depth = torch.arange(1.0, 17.0).view(1, 1, 4, 4)
    out, mask = downsample_depth(depth, (2, 2))
    torch.testing.assert_close(out, torch.tensor([[[[3.5, 5.5], [11.5, 13.5]]]]))
    assert mask.all()


def test_downsample_keeps_sparse_points_undiluted() -> None:
    depth = torch.zeros(1, 1, 4, 4)
    depth[0, 0, 0, 1] = 20.0  # one valid pixel in the top-left cell
    depth[0, 0, 3, 3] = 8.0
    depth[0, 0, 2, 2] = 4.0  # two valid pixels in the bottom-right cell
    out, mask = downsample_depth(depth, (2, 2))
    torch.testing.assert_close(out, torch.tensor([[[[20.0, 0.0], [0.0, 6.0]]]]))
    assert mask.tolist() == [[[[True, False], [False, True]]]]


def test_non_finite_ground_truth_is_invalid_at_every_size() -> None:
    depth = torch.full((1, 1, 4, 4), 10.0)
    depth[0, 0, 0, 0] = float("nan")  # one NaN in the top-left cell, next to valid pixels
    depth[0, 0, 2:, 2:] = float("inf")  # a whole cell of inf
    depth[0, 0, 3, 0] = -float("inf")
    out, mask = downsample_depth(depth, (2, 2))
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, torch.tensor([[[[10.0, 10.0], [10.0, 0.0]]]]))
    assert mask.tolist() == [[[[True, True], [True, False]]]]
    same, valid = downsample_depth(depth, (4, 4))
    assert torch.isfinite(same).all() and valid.sum() == 16 - 1 - 4 - 1


def test_a_nan_in_the_ground_truth_leaves_the_training_loss_finite() -> None:
    module = DepthModule(DepthNet("resnet18", "concat", pretrained=False), loss=DepthLoss())
    torch.manual_seed(0)
    batch = {
        "image": torch.rand(2, 3, 64, 64),
        "sparse": torch.rand(2, 1, 64, 64) * 10,
        "depth": torch.rand(2, 1, 64, 64) * 50 + 1,
    }
    batch["depth"][0, 0, :9, :13] = float("nan")  # not aligned with the 2×2 pooling cells
    batch["depth"][1, 0, 40:, 30:] = float("inf")
    losses = module.step_losses(batch)
    assert all(torch.isfinite(v) for v in losses.values()), losses


def _batch() -> dict:
    torch.manual_seed(0)
    return {
        "image": torch.rand(2, 3, 8, 12) * 0.5 + 0.25,
        "sparse": torch.rand(2, 1, 8, 12) * 10,
        "depth": torch.rand(2, 1, 8, 12) * 50,
        "condition": ["day", "fog"],
    }


def test_flip_moves_image_sparse_and_depth_together() -> None:
    batch = _batch()
    out = TrainAugmentation(flip_p=1.0, color_p=0.0)(batch)
    for key in ("image", "sparse", "depth"):
        torch.testing.assert_close(out[key], batch[key].flip(-1))
    assert out["condition"] == batch["condition"]


def test_colour_jitter_touches_the_image_only() -> None:
    batch = _batch()
    out = TrainAugmentation(flip_p=0.0, color_p=1.0, brightness=(1.2, 1.2), contrast=(1, 1))(batch)
    torch.testing.assert_close(out["image"], (batch["image"] * 1.2).clamp(0, 1))
    torch.testing.assert_close(out["sparse"], batch["sparse"])
    torch.testing.assert_close(out["depth"], batch["depth"])


def test_no_augmentation_at_zero_probability() -> None:
    batch = _batch()
    out = TrainAugmentation(flip_p=0.0, color_p=0.0)(batch)
    for key in ("image", "sparse", "depth"):
        torch.testing.assert_close(out[key], batch[key])


# --- a NaN or infinite training loss --------------------------------------------------------


def _fit_with_nan_batches(nan_batches: set[int], **options) -> DepthModule:
    """One epoch over 4 batches of one frame; the images of ``nan_batches`` are NaN."""
    torch.manual_seed(0)
    samples = [
        {
            "image": torch.full((3, 64, 64), torch.nan)
            if i in nan_batches
            else torch.rand(3, 64, 64),
            "sparse": torch.zeros(1, 64, 64),
            "depth": 5 + torch.rand(1, 64, 64),
        }
        for i in range(4)
    ]
    module = DepthModule(
        DepthNet("resnet18"),
        loss=DepthLoss(max_val=20.0),
        optimizer=partial(torch.optim.Adam, lr=1e-4),
        **options,
    )
    trainer = L.Trainer(
        max_epochs=1,
        accelerator="cpu",
        precision="32-true",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=0,
    )
    trainer.fit(module, train_dataloaders=DataLoader(samples, batch_size=1))
    return module


def test_a_nan_loss_stops_the_run_saying_where_and_what() -> None:
    with pytest.raises(NonFiniteLossError) as error:
        _fit_with_nan_batches({2})
    message = str(error.value)
    assert "non-finite training loss at epoch 0, step 2, batch 2 (loss=nan" in message
    assert "model.on_nonfinite_loss=skip" in message


@pytest.mark.slow
def test_skip_drops_nan_batches_up_to_the_limit() -> None:
    module = _fit_with_nan_batches({1, 3}, on_nonfinite_loss="skip", max_nonfinite_skips=2)
    assert module.nonfinite_skips == 2
    optimizer = module.trainer.optimizers[0]
    weight = module.net.decoder.head.weight
    assert optimizer.state[weight]["step"] == 2  # only the two finite batches updated it
    assert all(torch.isfinite(p).all() for p in module.parameters())
    with pytest.raises(NonFiniteLossError, match="batch 3 .* after 1 skipped batches"):
        _fit_with_nan_batches({1, 3}, on_nonfinite_loss="skip", max_nonfinite_skips=1)


def test_bad_nonfinite_options_are_refused_naming_the_key() -> None:
    net = DepthNet("resnet18")
    with pytest.raises(ValueError, match="model.on_nonfinite_loss='ignore'"):
        DepthModule(net, on_nonfinite_loss="ignore")
    with pytest.raises(ValueError, match="model.max_nonfinite_skips=-1"):
        DepthModule(net, max_nonfinite_skips=-1)


def test_a_zero_prediction_is_scored_unless_the_network_declares_partial_output(
    monkeypatch,
) -> None:
    # Only a network whose 0 means "no prediction" (RadarNet's association stage) has those
    # pixels left out; any other network's 0 is an error the metrics must show.
    net = DepthNet("resnet18", "concat", pretrained=False)
    module = DepthModule(net, loss=DepthLoss())
    depth = torch.full((1, 1, 4, 4), 10.0)
    pred = depth.clone()
    pred[..., :2, :] = 0.0
    batch = {"depth": depth, "condition": ["day"]}
    module._update(module.val_metrics, pred, batch)
    scored = module.val_metrics.compute()
    module.val_metrics.reset()
    monkeypatch.setattr(type(net), "partial_output", property(lambda self: True))
    module._update(module.val_metrics, pred, batch)
    filled_only = module.val_metrics.compute()
    assert scored["rmse"] > 5.0
    assert filled_only["rmse"] == pytest.approx(0.0, abs=1e-6)


def test_at_full_resolution_a_point_read_partly_from_no_prediction_is_not_scored(
    monkeypatch,
) -> None:
    # eval.resolution=full reads bilinearly: next to a pixel without a prediction (0), the read
    # would blend in that 0. Such a point has no prediction, as the pixel itself has none.
    net = DepthNet("resnet18", "concat", pretrained=False)
    module = DepthModule(net, loss=DepthLoss())
    monkeypatch.setattr(type(net), "partial_output", property(lambda self: True))
    pred = torch.full((1, 1, 4, 8), 10.0)
    pred[..., :4] = 0.0  # columns 0-3: no prediction
    points = torch.tensor([[[1.0, 3.25, 10.0], [1.0, 5.0, 10.0], [2.0, 6.5, 10.0]]])
    batch = {"depth_points": points, "condition": ["day"], "depth": torch.zeros(1, 1, 4, 8)}
    module._update_at_points(module.val_metrics, pred, batch)
    result = module.val_metrics.results()["overall"]
    module.val_metrics.reset()
    assert result["rmse"] == pytest.approx(0.0, abs=1e-6) and result["num_pixels"] == 2
    monkeypatch.setattr(type(net), "partial_output", property(lambda self: False))
    module._update_at_points(module.val_metrics, pred, batch)
    assert module.val_metrics.compute()["rmse"] > 1.0  # 3.25 reads 2.5 m: scored as a miss


def test_the_evaluation_range_comes_from_the_config_not_the_network(make_config) -> None:
    """A run scores by its eval block, and null limits take the dataset's, whatever range the
    network was given (it is not read back from the network)."""
    from fusion_depth.runner.module import module_from_config

    cfg = make_config(
        "experiment=smoke", "dataset.max_depth=50", "model.net.max_depth=60", "eval.min_depth=1"
    )
    module = module_from_config(cfg)
    assert module.net.max_depth == 60
    assert (module.protocol.min_depth, module.protocol.max_depth) == (1.0, (50.0,))
    capped = module_from_config(make_config("experiment=smoke", "eval.max_depth=[40,50]"))
    assert capped.protocol.max_depth == (40.0, 50.0)


def test_the_model_summary_has_no_flops_column_and_no_precision_warning(caplog) -> None:
    """Lightning's summary shows a FLOPs column of zeros (no example input) and warns that
    bf16-mixed "is not supported by the model summary"; the platform's leaves both out."""
    import warnings

    from fusion_depth.runner.callbacks import ParameterSummary

    module = DepthModule(DepthNet("resnet18", "concat", pretrained=False), loss=DepthLoss())
    trainer = L.Trainer(precision="bf16-mixed", accelerator="cpu", logger=False)
    module.trainer = trainer
    summary = ParameterSummary()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model_summary = summary._summary(trainer, module)
    assert not [w for w in caught if "model summary" in str(w.message)]
    with caplog.at_level("INFO", logger="fusion_depth.runner.callbacks"):
        ParameterSummary.summarize(
            model_summary._get_summary_data(),
            model_summary.total_parameters,
            model_summary.trainable_parameters,
            model_summary.model_size,
            model_summary.total_training_modes,
            model_summary.total_flops,
        )
    text = caplog.text
    assert "Total params" in text and "Params" in text
    assert "FLOPs" not in text and "Flops" not in text
