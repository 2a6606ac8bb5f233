"""Tests for fusion_depth.metrics.depth: hand-computed values and the averaging/validity
conventions."""

from __future__ import annotations

import math

import pytest
import torch

from fusion_depth.metrics.depth import (
    HIGHER_IS_BETTER,
    METRIC_KEYS,
    DepthMetrics,
    compute_depth_metrics,
    crop_mask,
    per_image_depth_metrics,
)

# 2x2 image, every pixel valid. Per pixel (pred d, target g):
#   (1.5, 1)  (2, 2)
#   (2, 4)    (8, 8)
# |d-g| = .5, 0, 2, 0         -> mae = 2.5/4 = 0.625
# |d-g|/g = .5, 0, .5, 0      -> abs_rel = 1/4 = 0.25
# (d-g)^2/g = .25, 0, 1, 0    -> sq_rel = 1.25/4 = 0.3125
# (d-g)^2 = .25, 0, 4, 0      -> rmse = sqrt(4.25/4) = 1.0307764064
# ratios max(d/g, g/d) = 1.5, 1, 2, 1 -> delta1 = 2/4, delta2 (< 1.5625) = 3/4,
#                                        delta3 (< 1.953125) = 3/4
# |log10 d/g| = log10 1.5 + log10 2 = log10 3 -> log10 = 0.4771212547/4 = 0.1192803137
# ln-errors ln 1.5, ln .5     -> rmse_log = sqrt((0.164402 + 0.480453)/4) = 0.4015143110
# 1000/d - 1000/g = -1000/3, 0, 250, 0 -> irmse = sqrt((1e6/9 + 62500)/4) = 208.3333333,
#                                          imae = (333.333 + 250)/4 = 145.8333333
PRED_2X2 = [[1.5, 2.0], [2.0, 8.0]]
TARGET_2X2 = [[1.0, 2.0], [4.0, 8.0]]
EXPECTED_2X2 = {
    "abs_rel": 0.25,
    "sq_rel": 0.3125,
    "rmse": 1.0307764064,
    "rmse_log": 0.4015143110,
    "mae": 0.625,
    "log10": 0.1192803137,
    "delta1": 0.5,
    "delta2": 0.75,
    "delta3": 0.75,
    "irmse": 208.3333333,
    "imae": 145.8333333,
}


def _img(rows: list[list[float]]) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float32)[None, None]


def _random_batch(b: int = 4, h: int = 6, w: int = 7, seed: int = 0) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    target = torch.rand(b, 1, h, w, generator=g) * 90.0  # some above max_depth=80
    target[torch.rand(b, 1, h, w, generator=g) < 0.3] = 0.0  # missing ground truth
    pred = target * (0.7 + 0.6 * torch.rand(b, 1, h, w, generator=g)) + 0.5
    return pred, target


def test_keys_and_directions() -> None:
    assert METRIC_KEYS == (
        "abs_rel", "sq_rel", "rmse", "rmse_log", "mae", "log10",
        "delta1", "delta2", "delta3", "irmse", "imae",
    )  # fmt: skip
    assert {k for k, v in HIGHER_IS_BETTER.items() if v} == {"delta1", "delta2", "delta3"}


def test_hand_computed_2x2() -> None:
    out = compute_depth_metrics(_img(PRED_2X2), _img(TARGET_2X2), min_depth=1e-3, max_depth=80.0)
    assert set(out) == set(METRIC_KEYS)
    for key, expected in EXPECTED_2X2.items():
        assert out[key] == pytest.approx(expected, rel=1e-6), key


def test_relative_errors_divide_by_ground_truth() -> None:
    # pred 3, target 2: |d-g|/g = 0.5 (dividing by the prediction would give 1/3).
    out = compute_depth_metrics(_img([[3.0]]), _img([[2.0]]))
    assert out["abs_rel"] == pytest.approx(0.5)
    assert out["sq_rel"] == pytest.approx(0.5)  # 1 / 2


def test_per_image_averaging_not_pooled() -> None:
    # Image A: one valid pixel, abs_rel 0.5. Image B: four exact pixels, abs_rel 0.
    # Per image: (0.5 + 0) / 2 = 0.25. Pooled over the 5 pixels it would be 0.5 / 5 = 0.1.
    pred = torch.cat([_img([[3.0, 9.0], [9.0, 9.0]]), _img([[1.0, 2.0], [3.0, 4.0]])])
    target = torch.cat([_img([[2.0, 0.0], [0.0, 0.0]]), _img([[1.0, 2.0], [3.0, 4.0]])])
    out = compute_depth_metrics(pred, target)
    assert out["abs_rel"] == pytest.approx(0.25)
    assert out["mae"] == pytest.approx(0.5)  # (1 + 0)/2, pooled would be 0.2
    assert out["delta1"] == pytest.approx(0.5)  # (0 + 1)/2, pooled would be 0.8


def test_pixels_outside_range_are_ignored() -> None:
    # Only the top-left pixel (target 2) is inside (min, max) = (1e-3, 80); the others are
    # missing (0), too far (100) and NaN, with wild predictions that must not count.
    pred = _img([[3.0, 50.0], [1.0, 7.0]])
    target = _img([[2.0, 0.0], [100.0, float("nan")]])
    out = compute_depth_metrics(pred, target, min_depth=1e-3, max_depth=80.0)
    assert out["abs_rel"] == pytest.approx(0.5)
    assert out["rmse"] == pytest.approx(1.0)
    assert out["delta1"] == pytest.approx(0.0)  # 1.5 >= 1.25
    assert out["delta2"] == pytest.approx(1.0)  # 1.5 < 1.5625
    assert all(math.isfinite(v) for v in out.values())
    # Both bounds are exclusive: targets equal to min_depth or max_depth are not scored.
    out = compute_depth_metrics(_img([[3.0, 9.0]]), _img([[2.0, 1.0]]), min_depth=1.0)
    assert out["abs_rel"] == pytest.approx(0.5)
    out = compute_depth_metrics(_img([[3.0, 9.0]]), _img([[2.0, 80.0]]), max_depth=80.0)
    assert out["abs_rel"] == pytest.approx(0.5)


def test_predictions_are_clamped_to_range() -> None:
    # pred 100 is clamped to max_depth 80: |80 - 40| / 40 = 1 (unclamped: 1.5).
    out = compute_depth_metrics(_img([[100.0]]), _img([[40.0]]), max_depth=80.0)
    assert out["abs_rel"] == pytest.approx(1.0)
    # pred 0 is clamped to min_depth 0.5: |0.5 - 1| / 1 = 0.5, and log/inverse metrics stay finite.
    out = compute_depth_metrics(_img([[0.0]]), _img([[1.0]]), min_depth=0.5)
    assert out["abs_rel"] == pytest.approx(0.5)
    assert out["irmse"] == pytest.approx(1000.0)  # 1000/0.5 - 1000/1
    assert all(math.isfinite(v) for v in out.values())


def test_image_without_valid_pixel_is_skipped() -> None:
    good_pred, good_target = _img(PRED_2X2), _img(TARGET_2X2)
    empty_pred, empty_target = _img([[5.0, 5.0], [5.0, 5.0]]), _img([[0.0, 0.0], [0.0, 90.0]])
    pred = torch.cat([empty_pred, good_pred, empty_pred])
    target = torch.cat([empty_target, good_target, empty_target])

    values, has_valid = per_image_depth_metrics(pred, target, 1e-3, 80.0)
    assert has_valid.tolist() == [False, True, False]
    for key in METRIC_KEYS:
        assert values[key].shape == (3,)
        assert torch.isfinite(values[key]).all(), key

    out = compute_depth_metrics(pred, target)
    for key, expected in EXPECTED_2X2.items():
        assert out[key] == pytest.approx(expected, rel=1e-6), key


def test_all_invalid_raises() -> None:
    with pytest.raises(ValueError, match=r"\(0.001, 80.0\)"):
        compute_depth_metrics(torch.ones(2, 1, 3, 3), torch.zeros(2, 1, 3, 3))


def test_shape_mismatch_raises() -> None:
    with pytest.raises(ValueError, match=r"\(2, 1, 3, 3\).*\(2, 3, 3\)"):
        compute_depth_metrics(torch.ones(2, 1, 3, 3), torch.ones(2, 3, 3))


def test_bhw_and_b1hw_agree() -> None:
    pred, target = _random_batch()
    a = compute_depth_metrics(pred, target)
    b = compute_depth_metrics(pred[:, 0], target[:, 0])
    assert a == pytest.approx(b, rel=1e-12)


def test_metric_class_matches_functional_over_concatenated_batch() -> None:
    pred, target = _random_batch(b=7)
    target[3] = 0.0  # one image without ground truth
    metric = DepthMetrics(min_depth=1e-3, max_depth=80.0)
    for chunk in ((0, 2), (2, 5), (5, 7)):
        metric.update(pred[slice(*chunk)], target[slice(*chunk)])
    out = metric.compute()
    expected = compute_depth_metrics(pred, target)
    assert set(out) == set(METRIC_KEYS)
    for key in METRIC_KEYS:
        assert out[key].dim() == 0
        assert out[key].item() == pytest.approx(expected[key], rel=1e-9), key
    assert metric.results()["overall"]["num_images"] == 6
    assert len(metric.per_image()) == 6  # the image without ground truth has no record

    metric.reset()
    with pytest.raises(ValueError), pytest.warns(UserWarning, match="before the ``update``"):
        metric.compute()


def test_compute_without_scored_image_raises() -> None:
    metric = DepthMetrics()
    metric.update(torch.ones(1, 1, 2, 2), torch.zeros(1, 1, 2, 2))
    with pytest.raises(ValueError):
        metric.compute()


def test_condition_breakdown() -> None:
    pred, target = _random_batch(b=6, seed=1)
    target[4] = 0.0  # a "night" image without ground truth: skipped in both night and overall
    conds = ["day", "night", "day", "day", "night", "night"]
    metric = DepthMetrics(conditions=["day", "night", "fog"])
    metric.update(pred[:3], target[:3], condition=conds[:3])
    metric.update(pred[3:], target[3:], condition=conds[3:])
    out = metric.compute()

    day = [0, 2, 3]
    night = [1, 5]
    exp_day = compute_depth_metrics(pred[day], target[day])
    exp_night = compute_depth_metrics(pred[night], target[night])
    exp_all = compute_depth_metrics(pred, target)
    assert not any(k.startswith("fog/") for k in out)  # no fog image was seen
    assert set(out) == set(METRIC_KEYS) | {
        f"{c}/{k}" for c in ("day", "night") for k in METRIC_KEYS
    }
    counts = {c: g["num_images"] for c, g in metric.results()["by_condition"].items()}
    assert counts == {"day": 3, "night": 2}
    for key in METRIC_KEYS:
        assert out[f"day/{key}"].item() == pytest.approx(exp_day[key], rel=1e-9)
        assert out[f"night/{key}"].item() == pytest.approx(exp_night[key], rel=1e-9)
        # The groups partition the scored images, so their count-weighted mean is the overall one.
        pooled = (3 * out[f"day/{key}"] + 2 * out[f"night/{key}"]) / 5
        assert pooled.item() == pytest.approx(exp_all[key], rel=1e-9)
        assert out[key].item() == pytest.approx(exp_all[key], rel=1e-9)


def test_unknown_condition_raises_and_leaves_state() -> None:
    metric = DepthMetrics(conditions=["day", "night"])
    pred, target = _random_batch(b=2)
    with pytest.raises(ValueError, match=r"snow.*day.*night"):
        metric.update(pred, target, condition=["day", "snow"])
    assert metric.image_sums == [] and metric.image_condition == []
    with pytest.raises(ValueError, match="2 images"):
        metric.update(pred, target, condition=["day"])
    with pytest.raises(ValueError):
        DepthMetrics().update(pred, target, condition=["day", "day"])


# --- evaluation protocols: caps, crops, averaging, breakdowns ----------------------------------


def test_pooled_weighs_pixels_per_image_weighs_images() -> None:
    # Image A: one pixel, error 2 m. Image B: three pixels, error 0. Per image: RMSE mean of
    # (2, 0) = 1; pooled: sqrt(4 / 4) = 1 as well, so use MAE to tell them apart: per image
    # (2 + 0) / 2 = 1, pooled 2 / 4 = 0.5.
    pred = torch.tensor([[[[4.0, 0.0], [0.0, 0.0]]], [[[5.0, 5.0], [5.0, 0.0]]]])
    target = torch.tensor([[[[2.0, 0.0], [0.0, 0.0]]], [[[5.0, 5.0], [5.0, 0.0]]]])
    per_image = compute_depth_metrics(pred, target, averaging="per_image")
    pooled = compute_depth_metrics(pred, target, averaging="pooled")
    assert per_image["mae"] == pytest.approx(1.0)
    assert pooled["mae"] == pytest.approx(0.5)
    assert per_image["rmse"] == pytest.approx(1.0)  # mean of sqrt(4) and 0
    assert pooled["rmse"] == pytest.approx(1.0)  # sqrt(4 / 4)
    assert pooled["abs_rel"] == pytest.approx(1.0 / 4)
    assert per_image["abs_rel"] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="^averaging='mean'"):
        compute_depth_metrics(pred, target, averaging="mean")


def test_caps_score_only_closer_ground_truth_and_clamp_predictions() -> None:
    # Ground truth 10, 45, 60, 75 m; predictions 12, 45, 90, 75. Cap 50: pixels 10 and 45,
    # cap 70 adds 60 (prediction clamped to 70), cap 80 adds 75 and clamps 90 to 80.
    target = _img([[10.0, 45.0], [60.0, 75.0]])
    pred = _img([[12.0, 45.0], [90.0, 75.0]])
    metric = DepthMetrics(min_depth=1.0, max_depth=[80, 50, 70])
    metric.update(pred, target)
    by_cap = metric.results()["by_cap"]
    assert list(by_cap) == ["50", "70", "80"]
    assert by_cap["50"]["mae"] == pytest.approx(2.0 / 2)
    assert by_cap["70"]["mae"] == pytest.approx((2.0 + 10.0) / 3)
    assert by_cap["80"]["mae"] == pytest.approx((2.0 + 20.0) / 4)
    assert [by_cap[c]["num_pixels"] for c in by_cap] == [2, 3, 4]
    # The headline (compute, overall) is the largest cap.
    assert metric.compute()["mae"].item() == pytest.approx(by_cap["80"]["mae"])
    assert metric.results()["overall"] == by_cap["80"]


def test_garg_and_eigen_crop_masks_follow_the_kitti_fractions() -> None:
    h, w = 100, 200
    garg = crop_mask((h, w), "garg")[0]
    rows = garg.any(dim=1).nonzero().flatten()
    cols = garg.any(dim=0).nonzero().flatten()
    assert (rows.min().item(), rows.max().item() + 1) == (int(0.40810811 * h), int(0.99189189 * h))
    assert (cols.min().item(), cols.max().item() + 1) == (int(0.03594771 * w), int(0.96405229 * w))
    eigen = crop_mask((h, w), "eigen")[0]
    assert eigen.any(dim=1).nonzero().min().item() == int(0.3324324 * h)
    assert crop_mask((h, w), "none").all()
    with pytest.raises(ValueError, match="^crop='tight'"):
        crop_mask((h, w), "tight")


def test_crop_follows_the_original_frame_of_a_padded_or_cut_sample() -> None:
    # A 40x100 frame padded to 48x104 (frame at the top-left) gives Garg rows 16..39 and
    # columns 3..96 of the frame; cut by 8 rows at the top instead, those rows move up by 8.
    padded = crop_mask((48, 104), "garg", torch.tensor([[0, 0, 40, 100]]))[0]
    assert padded.any(dim=1).nonzero().flatten().tolist() == list(range(16, 39))
    assert padded.any(dim=0).nonzero().flatten().tolist() == list(range(3, 96))
    cut = crop_mask((32, 100), "garg", torch.tensor([[-8, 0, 40, 100]]))[0]
    assert cut.any(dim=1).nonzero().flatten().tolist() == list(range(8, 31))


def test_crop_changes_the_numbers_exactly_as_the_mask_says() -> None:
    pred, target = _random_batch(b=3, h=40, w=60, seed=3)
    mask = crop_mask((40, 60), "garg", batch=3)[:, None]
    cropped = compute_depth_metrics(pred, target, crop="garg")
    by_hand = compute_depth_metrics(pred, torch.where(mask, target, torch.zeros_like(target)))
    assert cropped == pytest.approx(by_hand, rel=1e-12)
    assert cropped["rmse"] != pytest.approx(compute_depth_metrics(pred, target)["rmse"])


def test_breakdown_counts_add_up_to_the_total() -> None:
    pred, target = _random_batch(b=10, h=12, w=16, seed=5)
    conditions = ["day", "night", "fog", "day", "night", "fog", "day", "rain", "rain", "day"]
    metric = DepthMetrics(
        min_depth=0.5,
        max_depth=80.0,
        conditions=["day", "night", "fog", "rain"],
        distance_bins=[0, 10, 20, 40, 80],
    )
    metric.update(pred[:6], target[:6], conditions[:6], index=torch.arange(6))
    metric.update(pred[6:], target[6:], conditions[6:], index=torch.arange(6, 10))
    results = metric.results()
    overall = results["overall"]
    assert sum(g["num_images"] for g in results["by_condition"].values()) == overall["num_images"]
    assert sum(g["num_pixels"] for g in results["by_condition"].values()) == overall["num_pixels"]
    assert list(results["by_distance"]) == ["0-10", "10-20", "20-40", "40-80"]
    assert sum(g["num_pixels"] for g in results["by_distance"].values()) == overall["num_pixels"]
    # A bin's numbers are those of the pixels whose ground truth lies in it.
    in_bin = (target >= 20) & (target < 40)
    expected = compute_depth_metrics(pred, torch.where(in_bin, target, torch.zeros_like(target)))
    for key in METRIC_KEYS:
        assert results["by_distance"]["20-40"][key] == pytest.approx(expected[key], rel=1e-9)
    # Per-image records: one per scored image, in split order, matching the overall mean.
    rows = metric.per_image()
    assert [r["index"] for r in rows] == list(range(10))
    assert [r["condition"] for r in rows] == conditions
    mean_rmse = sum(r["rmse"] for r in rows) / len(rows)
    assert mean_rmse == pytest.approx(overall["rmse"], rel=1e-12)
    assert sum(r["num_pixels"] for r in rows) == overall["num_pixels"]
