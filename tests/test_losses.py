"""Tests for fusion_depth.losses.depth_loss: hand-computed values, masking and gradient
behaviour."""

from __future__ import annotations

import math

import pytest
import torch

from fusion_depth.losses.depth_loss import (
    PIXEL_LOSSES,
    DepthLoss,
    berhu_loss,
    edge_loss,
    log_l1_loss,
    masked_ssim_loss,
    pixel_loss,
    ssi_loss,
)

# Residuals pred - target of a 2x2 map: 0.1, 0.5, 1.0, -2.0.
TARGET = torch.tensor([[[[1.0, 1.0], [1.0, 3.0]]]])
PRED = torch.tensor([[[[1.1, 1.5], [2.0, 1.0]]]])
MASK_LAST_OUT = torch.tensor([[[[True, True], [True, False]]]])


def _random_case(seed: int = 0, size: int = 16) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    pred = torch.rand(2, 1, size, size, generator=g)
    target = torch.rand(2, 1, size, size, generator=g)
    mask = torch.rand(2, 1, size, size, generator=g) < 0.8
    return pred, target, mask


def test_ssim_identical_is_zero_and_different_is_positive() -> None:
    pred, target, _ = _random_case()
    assert masked_ssim_loss(pred, pred.clone()).item() == pytest.approx(0.0, abs=1e-6)
    assert masked_ssim_loss(pred, target).item() > 0.05


def test_berhu_matches_formula_on_both_sides_of_c() -> None:
    # max|x| = 2 -> c = 0.4. |0.1| <= c: 0.1; others (x^2 + c^2) / (2c):
    # 0.5 -> 0.41/0.8 = 0.5125, 1.0 -> 1.16/0.8 = 1.45, -2.0 -> 4.16/0.8 = 5.2. Mean 7.2625/4.
    assert berhu_loss(PRED, TARGET).item() == pytest.approx(1.815625, rel=1e-6)
    # With the -2.0 pixel masked out, c = 0.2 * 1.0 = 0.2 over the valid pixels only:
    # 0.1 -> 0.1, 0.5 -> 0.29/0.4 = 0.725, 1.0 -> 1.04/0.4 = 2.6. Mean 3.425/3.
    assert berhu_loss(PRED, TARGET, MASK_LAST_OUT).item() == pytest.approx(3.425 / 3, rel=1e-6)
    # The threshold is a parameter: 0.5 -> c = 1: 0.1, 0.5, 1.0 (|x| <= c), 5/2 = 2.5. Mean 4.1/4.
    assert berhu_loss(PRED, TARGET, threshold=0.5).item() == pytest.approx(1.025, rel=1e-6)


def test_berhu_zero_residual_is_zero_with_finite_gradient() -> None:
    pred = TARGET.clone().requires_grad_(True)
    loss = berhu_loss(pred, TARGET)
    loss.backward()
    assert loss.item() == 0.0
    assert torch.isfinite(pred.grad).all()


def test_l1_l2_by_hand() -> None:
    assert pixel_loss(PRED, TARGET, kind="l1").item() == pytest.approx(3.6 / 4, rel=1e-6)
    assert pixel_loss(PRED, TARGET, kind="l2").item() == pytest.approx(5.26 / 4, rel=1e-6)
    assert pixel_loss(PRED, TARGET, MASK_LAST_OUT, "l1").item() == pytest.approx(1.6 / 3, rel=1e-6)
    assert pixel_loss(PRED, TARGET, MASK_LAST_OUT, "l2").item() == pytest.approx(1.26 / 3, rel=1e-6)
    assert pixel_loss(PRED, TARGET, kind="berhu").item() == pytest.approx(1.815625, rel=1e-6)


def test_log_l1_by_hand_weighs_relative_error_alike_at_every_depth() -> None:
    # Reciprocal depth 2 vs 1 and 0.2 vs 0.1: both a factor of 2 (5 m vs 10 m, 50 m vs 100 m at
    # depth_scale 10), both cost log 2; L1 on reciprocal depth weighs the far pixel 10× less.
    pred = torch.tensor([[[[2.0, 0.2]]]])
    target = torch.tensor([[[[1.0, 0.1]]]])
    assert log_l1_loss(pred, target).item() == pytest.approx(math.log(2), rel=1e-6)
    assert pixel_loss(pred, target, kind="log_l1").item() == pytest.approx(math.log(2), rel=1e-6)
    assert pixel_loss(pred, target, kind="l1").item() == pytest.approx(1.1 / 2, rel=1e-6)
    # On the 2x2 case with the last pixel masked out: log 1.1, log 1.5, log 2 averaged.
    expected = (math.log(1.1) + math.log(1.5) + math.log(2.0)) / 3
    assert log_l1_loss(PRED, TARGET, MASK_LAST_OUT).item() == pytest.approx(expected, rel=1e-6)


def test_ssi_is_blind_to_each_image_scale_and_shift_and_by_hand() -> None:
    # Per image, any positive affine map of the target costs nothing; image 2's own map differs.
    g = torch.Generator().manual_seed(7)
    target = torch.rand(2, 1, 6, 8, generator=g) + 0.1
    mask = torch.rand(2, 1, 6, 8, generator=g) < 0.8
    pred = target * torch.tensor([3.0, 0.2]).view(2, 1, 1, 1) + torch.tensor([-1.0, 5.0]).view(
        2, 1, 1, 1
    )
    # 0 up to SSI_EPS's pull on the scale (1e-6 against image 2's prediction variance of 3e-3)
    assert ssi_loss(pred, target, mask).item() == pytest.approx(0.0, abs=1e-4)
    # By hand: pred (0, 1, 2, 3) onto target (0, 1, 1, 3): least squares s = 1.125 / 1.25 = 0.9,
    # t = 1.25 - 0.9 · 1.5 = -0.1, so aligned (-0.1, 0.8, 1.7, 2.6): errors 0.1 + 0.2 + 0.7 + 0.4.
    pred = torch.tensor([[[[0.0, 1.0], [2.0, 3.0]]]])
    target = torch.tensor([[[[0.0, 1.0], [1.0, 3.0]]]])
    assert ssi_loss(pred, target).item() == pytest.approx(1.4 / 4, rel=1e-4)
    assert pixel_loss(pred * 7 - 2, target, kind="ssi").item() == pytest.approx(1.4 / 4, rel=1e-4)


def test_log_l1_continues_by_the_tangent_below_the_floor() -> None:
    # At and below the floor the log becomes log(floor) + (p - floor) / floor: continuous, and a
    # prediction <= 0 keeps a finite loss and a gradient of -1/floor (towards the target).
    target = torch.ones(1, 1, 1, 3)
    pred = torch.tensor([[[[0.01, 0.0, -0.5]]]], requires_grad=True)
    per_pixel = [log_l1_loss(pred[..., i : i + 1], target[..., :1]) for i in range(3)]
    log_floor = math.log(0.01)
    assert per_pixel[0].item() == pytest.approx(-log_floor, rel=1e-6)
    assert per_pixel[1].item() == pytest.approx(1.0 - log_floor, rel=1e-6)
    assert per_pixel[2].item() == pytest.approx(51.0 - log_floor, rel=1e-6)
    log_l1_loss(pred, target).backward()
    torch.testing.assert_close(pred.grad, torch.full_like(pred, -100.0 / 3))


def test_edge_loss_by_hand_with_eroded_mask() -> None:
    # Target is an x-ramp of slope 2, pred is flat. Column 0 is invalid (and holds junk), so the
    # eroded mask keeps columns 2..4 only. Normalised Sobel dx of the target: 2 inside, 1 on the
    # replicated right border; dy = 0. Mean over both components: (2 + 2 + 1) / 3 / 2 = 5/6.
    target = (2.0 * torch.arange(5.0)).expand(5, 5).clone()[None, None]
    target[..., 0] = 1000.0
    mask = torch.ones_like(target, dtype=torch.bool)
    mask[..., 0] = False
    pred = torch.zeros_like(target)
    assert edge_loss(pred, target, mask).item() == pytest.approx(5 / 6, rel=1e-6)
    assert edge_loss(target, target).item() == pytest.approx(0.0, abs=1e-7)


@pytest.mark.parametrize("kind", PIXEL_LOSSES)
def test_masked_target_pixels_do_not_affect_any_term(kind: str) -> None:
    pred, target, mask = _random_case(seed=1)
    crit = DepthLoss(pixel=kind)
    pred_a = pred.clone().requires_grad_(True)
    pred_b = pred.clone().requires_grad_(True)
    out_a = crit(pred_a, target, mask)
    changed = target.clone()
    changed[~mask] = torch.rand(int((~mask).sum())) * 100.0
    changed[~mask & (torch.arange(16) % 2 == 0)] = float("nan")
    out_b = crit(pred_b, changed, mask)
    for key in ("loss", "ssim", "edge", "pixel"):
        assert torch.isfinite(out_b[key]), key
        assert out_b[key].item() == pytest.approx(out_a[key].item(), rel=1e-6, abs=1e-9), key
    out_a["loss"].backward()
    out_b["loss"].backward()
    torch.testing.assert_close(pred_a.grad, pred_b.grad)


@pytest.mark.parametrize("kind", PIXEL_LOSSES)
def test_empty_mask_is_finite_zero(kind: str) -> None:
    pred, target, _ = _random_case(seed=2)
    pred.requires_grad_(True)
    out = DepthLoss(pixel=kind)(pred, target, torch.zeros_like(target, dtype=torch.bool))
    for key, value in out.items():
        assert torch.isfinite(value), key
        assert value.item() == pytest.approx(0.0, abs=1e-6), key
    out["loss"].backward()
    assert torch.isfinite(pred.grad).all()


@pytest.mark.parametrize("kind", PIXEL_LOSSES)
def test_gradients_flow_to_pred(kind: str) -> None:
    pred, target, mask = _random_case(seed=3)
    pred.requires_grad_(True)
    out = DepthLoss(pixel=kind)(pred, target, mask)
    for key in ("ssim", "edge", "pixel"):
        (grad,) = torch.autograd.grad(out[key], pred, retain_graph=True)
        assert torch.isfinite(grad).all(), key
        assert grad.abs().sum() > 0, key
    out["loss"].backward()
    assert torch.isfinite(pred.grad).all()
    assert pred.grad.abs().sum() > 0


@pytest.mark.parametrize("kind", PIXEL_LOSSES)
def test_batch_fold_gives_the_per_image_terms_and_gradient(kind: str) -> None:
    # DepthLoss hands every term the batch as one image of B channels (a faster SSIM on CPUs);
    # each term must still be the one computed on the (B, 1, h, w) batch, and so must the
    # gradient reaching the network output. Equal up to fp32 rounding: which convolution kernel
    # oneDNN picks for each form depends on the CPU (on the AMD EPYC they agree to the bit, and a
    # default run repeats its scores to the last digit; docs/guides/speed.md, "The loss on a CPU").
    g = torch.Generator().manual_seed(5)
    pred = (torch.rand(5, 1, 24, 40, generator=g) * 4 + 0.1).contiguous(
        memory_format=torch.channels_last
    )
    target = torch.rand(5, 1, 24, 40, generator=g) * 4 + 0.1
    mask = torch.rand(5, 1, 24, 40, generator=g) < 0.7
    weights = {"w_ssim": 1.87, "w_edge": 1.14, "w_pixel": 0.43}
    folded_pred = pred.clone().requires_grad_(True)
    out = DepthLoss(pixel=kind, max_val=20.0, **weights)(folded_pred, target, mask)
    out["loss"].backward()
    ref_pred = pred.clone().requires_grad_(True)
    ssim = masked_ssim_loss(ref_pred, target, mask, max_val=20.0)
    edge = edge_loss(ref_pred, target, mask)
    pix = (
        berhu_loss(ref_pred, target, mask)
        if kind == "berhu"
        else pixel_loss(ref_pred, target, mask, kind)
    )
    ref = weights["w_ssim"] * ssim + weights["w_edge"] * edge + weights["w_pixel"] * pix
    ref.backward()
    for key, value in {"ssim": ssim, "edge": edge, "pixel": pix, "loss": ref}.items():
        torch.testing.assert_close(out[key], value, rtol=1e-6, atol=0, msg=key)
    torch.testing.assert_close(folded_pred.grad, ref_pred.grad, rtol=1e-5, atol=1e-9)


def test_mismatched_shapes_are_refused_before_the_batch_fold() -> None:
    # Folded, a (2, 1, h, w) prediction and a (1, 2, h, w) target (or mask) would look alike;
    # DepthLoss must refuse them, naming both shapes, as each term does on its own.
    pred = torch.rand(2, 1, 8, 8)
    crit = DepthLoss()
    with pytest.raises(ValueError, match=r"\(2, 1, 8, 8\) vs \(1, 2, 8, 8\)"):
        crit(pred, torch.rand(1, 2, 8, 8), None)
    with pytest.raises(ValueError, match=r"mask shape \(1, 2, 8, 8\) differs"):
        crit(pred, torch.rand(2, 1, 8, 8), torch.ones(1, 2, 8, 8, dtype=torch.bool))


def test_total_is_weighted_sum() -> None:
    pred, target, mask = _random_case(seed=4)
    out = DepthLoss(pixel="berhu", w_ssim=0.5, w_edge=2.0, w_pixel=3.0)(pred, target, mask)
    expected = 0.5 * out["ssim"] + 2.0 * out["edge"] + 3.0 * out["pixel"]
    assert out["loss"].item() == pytest.approx(expected.item(), rel=1e-6)
    assert out["pixel"].item() == pytest.approx(berhu_loss(pred, target, mask).item(), rel=1e-6)
    custom = DepthLoss(pixel="berhu", berhu_threshold=0.5)(pred, target, mask)["pixel"]
    assert custom.item() == pytest.approx(berhu_loss(pred, target, mask, 0.5).item(), rel=1e-6)


def test_unknown_kind_raises() -> None:
    with pytest.raises(ValueError, match=r"'huber'.*l1.*l2.*berhu.*log_l1"):
        pixel_loss(PRED, TARGET, kind="huber")
    with pytest.raises(ValueError, match=r"'huber'.*l1.*l2.*berhu"):
        DepthLoss(pixel="huber")
