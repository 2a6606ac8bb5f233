"""Target preparation and augmentation of the LightningModule."""

from __future__ import annotations

import torch

from fusion_depth.data.transforms import TrainAugmentation
from fusion_depth.module import downsample_depth


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
