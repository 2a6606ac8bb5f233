"""Each evaluation preset (``eval=<name>``) scores as its reference code does: which pixels count,
clamping, units, averaging, crop, what ARD divides by. Small frames hit every convention; the
expected values are worked out by hand from the pixel lists below, not by the library."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers import compose_config

from fusion_depth.config import validate_config
from fusion_depth.runner.protocol import EvalProtocol, EvaluationResult, results_tables

H, W = 375, 1242  # a KITTI frame: the Garg crop keeps rows 153..370, columns 44..1196
ROW, GARG_TOP = 200, 153

# Image A: (row, col, ground truth m, prediction m). Image B has no ground truth at all.
# Image C: one pixel. The dataset (procedural) scores 0.5 < gt < 80 by default.
BEYOND_CAP = (ROW, 600, 45.0, 70.0)  # predicts 70 m where the truth is 45 m (under a 50 m cap)
AT_CAP = (ROW, 601, 50.0, 40.0)  # truth exactly at the 50 m cap: not scored under it
NO_GT = (ROW, 602, 0.0, 10.0)  # 0 = no measurement, never scored
NAN_GT = (ROW, 603, math.nan, 10.0)  # NaN, never scored
ABOVE_CROP = (GARG_TOP - 1, 600, 20.0, 22.0)  # one row above the Garg crop
CROP_EDGE = (GARG_TOP, 600, 10.0, 8.0)  # the crop's first row
FAR = (ROW, 604, 85.0, 90.0)  # beyond 80 m
NEAR = (ROW, 605, 0.5, 0.3)  # at procedural's min_depth 0.5 (not above it), above 1e-3 and 0
OVERSHOOT = (ROW, 606, 60.0, 100.0)  # a prediction above 80 m: clamped to 80 where clamping
UNDERSHOOT = (ROW, 607, 10.0, 1e-4)  # below every clamp's floor (1e-3 m, 0.5 m)
TINY_GT = (ROW, 608, 5e-4, 0.01)  # ground truth below eigen's 1e-3 m, above 0
VERY_FAR = (ROW, 609, 200.0, 70.0)  # beyond every cap but kitti_dc's
# The Garg crop's other edges, where int() and round() of the fractions differ: rows 153..370
# (371.96 → 371 out) and columns 44..1196 (44.65 → 44 in, 1196.99 → 1197 out).
BOTTOM_IN, BOTTOM_OUT = (370, 610, 12.0, 11.0), (371, 611, 12.0, 14.0)
LEFT_OUT, LEFT_IN = (ROW, 43, 15.0, 16.0), (ROW, 44, 15.0, 13.0)
RIGHT_IN, RIGHT_OUT = (ROW, 1196, 25.0, 24.0), (ROW, 1197, 25.0, 27.0)
ONLY = (ROW, 600, 30.0, 33.0)  # image C

IMAGE_A = [
    BEYOND_CAP,
    AT_CAP,
    NO_GT,
    NAN_GT,
    ABOVE_CROP,
    CROP_EDGE,
    FAR,
    NEAR,
    OVERSHOOT,
    UNDERSHOOT,
    TINY_GT,
    VERY_FAR,
    BOTTOM_IN,
    BOTTOM_OUT,
    LEFT_OUT,
    LEFT_IN,
    RIGHT_IN,
    RIGHT_OUT,
]
# The pixels no crop, cap below 85 m or floor above 5e-4 m leaves out, as (gt, prediction).
UNCROPPED = [(12.0, 11.0), (12.0, 14.0), (15.0, 16.0), (15.0, 13.0), (25.0, 24.0), (25.0, 27.0)]


def _frames() -> tuple[torch.Tensor, torch.Tensor]:
    pred = torch.full((3, 1, H, W), 5.0, dtype=torch.float64)
    target = torch.zeros((3, 1, H, W), dtype=torch.float64)
    for image, pixels in ((0, IMAGE_A), (2, [ONLY])):
        for row, col, gt, d in pixels:
            target[image, 0, row, col] = gt
            pred[image, 0, row, col] = d
    return pred, target


def _score(preset: str, tmp_path, *overrides: str) -> EvaluationResult:
    cfg = compose_config([f"eval={preset}", *overrides], tmp_path)
    validate_config(cfg)
    protocol = EvalProtocol.from_config(cfg.eval, cfg.dataset.min_depth, cfg.dataset.max_depth)
    metrics = protocol.scorer()
    pred, target = _frames()
    metrics.update(pred, target, index=torch.arange(3))
    return EvaluationResult.from_metrics(protocol, metrics, latency={})


def _image_errors(pairs: list[tuple[float, float]]) -> dict[str, float]:
    """One image's metrics from its scored (gt, prediction) pairs, written out directly."""
    gt = np.array([g for g, _ in pairs])
    d = np.array([p for _, p in pairs])
    ratio = np.maximum(d / gt, gt / d)
    return {
        "mae": np.mean(np.abs(d - gt)),
        "rmse": np.sqrt(np.mean((d - gt) ** 2)),
        "imae": np.mean(np.abs(1000 / d - 1000 / gt)),
        "irmse": np.sqrt(np.mean((1000 / d - 1000 / gt) ** 2)),
        "abs_rel": np.mean(np.abs(d - gt) / gt),
        "sq_rel": np.mean((d - gt) ** 2 / gt),
        "rmse_log": np.sqrt(np.mean((np.log(d) - np.log(gt)) ** 2)),
        "delta1": np.mean(ratio < 1.25),
        "delta2": np.mean(ratio < 1.25**2),
        "delta3": np.mean(ratio < 1.25**3),
        "log10": np.mean(np.abs(np.log10(d) - np.log10(gt))),
    }


def _per_image_mean(images: list[list[tuple[float, float]]]) -> dict[str, float]:
    each = [_image_errors(pairs) for pairs in images]
    return {k: float(np.mean([e[k] for e in each])) for k in each[0]}


def _columns(table: str) -> list[str]:
    """The metric columns of a printed table's first header (between Condition and Images)."""
    cells = [c.strip() for c in table.splitlines()[0].strip("|").split("|")]
    return cells[1 : cells.index("Images")]


def _check(result: dict, expected: dict, keys) -> None:
    for key in keys:
        assert result[key] == pytest.approx(expected[key], rel=1e-9), key


def test_radarnet_scores_the_raw_prediction_per_cap_in_mm(tmp_path) -> None:
    """nesl/radar-camera-fusion-depth: 0 < gt < cap (strict), no clamp, per image, mm and 1/km,
    caps 50, 70 and 80 in one pass; the empty image is skipped."""
    result = _score("radarnet", tmp_path)
    assert result.protocol.clamp is False and result.protocol.min_depth == 0.0
    # 50 m is not < 50; 1e-4 m and 5e-4 m ground truth are scored as they are.
    at_50 = [(45.0, 70.0), (20.0, 22.0), (10.0, 8.0), (0.5, 0.3), (10.0, 1e-4), (5e-4, 0.01)]
    at_50 += UNCROPPED
    at_80 = [*at_50, (50.0, 40.0), (60.0, 100.0)]  # 100 m is scored as it is (no clamp)
    c = [(30.0, 33.0)]
    _check(result.by_cap["50"], _per_image_mean([at_50, c]), ["mae", "rmse", "imae", "irmse"])
    _check(result.by_cap["70"], _per_image_mean([at_80, c]), ["mae"])
    overall = _per_image_mean([at_80, c])
    _check(result.overall, overall, ["mae", "rmse", "imae", "irmse"])
    assert result.overall["num_images"] == 2  # image B (no ground truth) is skipped
    # The example: 70 m predicted where the truth is 45 m costs 25 m here, not 5 m.
    only = _score("radarnet", tmp_path, "eval.max_depth=[50]")
    errors = [abs(d - gt) for gt, d in at_50]
    assert only.per_image[0]["mae"] == pytest.approx(np.mean(errors)) and errors[0] == 25.0
    # The printed table: its columns, order and units (mm; 1/km as recorded).
    table = results_tables(result)
    assert _columns(table) == ["MAE (mm)", "RMSE (mm)", "iMAE (1/km)", "iRMSE (1/km)"]
    row = [c.strip() for c in table.splitlines()[2].strip("|").split("|")]
    assert row[0] == "all"
    assert row[1:5] == [
        f"{1000 * overall['mae']:.3f}",
        f"{1000 * overall['rmse']:.3f}",
        f"{overall['imae']:.3f}",
        f"{overall['irmse']:.3f}",
    ]


def test_paper_clamps_to_the_dataset_range(tmp_path) -> None:
    """The platform's own scoring: dataset.min_depth 0.5 < gt < 80, clamped to [0.5, 80], per
    image."""
    result = _score("paper", tmp_path)
    a = [(45.0, 70.0), (50.0, 40.0), (20.0, 22.0), (10.0, 8.0), (60.0, 80.0), (10.0, 0.5)]
    a += UNCROPPED  # 100 → 80 and 1e-4 → 0.5 above
    _check(result.overall, _per_image_mean([a, [(30.0, 33.0)]]), ["rmse", "abs_rel", "delta1"])
    # The same 70 m prediction under a 50 m cap, clamped: a 5 m error, as the issue says.
    capped = _score("paper", tmp_path, "eval.max_depth=50")
    a50 = [(45.0, 50.0), (20.0, 22.0), (10.0, 8.0), (10.0, 0.5), *UNCROPPED]
    _check(capped.overall, _per_image_mean([a50, [(30.0, 33.0)]]), ["mae", "rmse"])
    assert _columns(results_tables(result)) == ["RMSE", "ARD", "SRD", "MAE", "δ1", "δ2", "δ3"]


def test_eigen_is_monodepth2s(tmp_path) -> None:
    """monodepth2 on the Eigen split: 1e-3 < gt < 80, clamped to [1e-3, 80], the Garg crop
    (rows 153..370, columns 44..1196: each edge in and out), per image, abs_rel sq_rel rmse
    rmse_log a1 a2 a3."""
    result = _score("eigen", tmp_path)
    a = [(45.0, 70.0), (50.0, 40.0), (10.0, 8.0), (0.5, 0.3), (60.0, 80.0), (10.0, 1e-3)]
    a += [(12.0, 11.0), (15.0, 13.0), (25.0, 24.0)]  # inside the crop's bottom, left, right
    keys = ["abs_rel", "sq_rel", "rmse", "rmse_log", "delta1", "delta2", "delta3"]
    _check(result.overall, _per_image_mean([a, [(30.0, 33.0)]]), keys)
    columns = ["ARD", "SRD", "RMSE", "RMSE_LOG", "δ1", "δ2", "δ3"]
    assert _columns(results_tables(result)) == columns


def _devkit_fill(depth: np.ndarray) -> np.ndarray:
    """``DepthImage::interpolateBackground`` of the KITTI devkit (cpp/io_depth.h), line by line."""
    d = depth.copy()
    height, width = d.shape
    for v in range(height):
        count = 0
        for u in range(width):
            if d[v, u] >= 0:
                if count >= 1:
                    u1, u2 = u - count, u - 1
                    if u1 > 0 and u2 < width - 1:
                        d[v, u1 : u2 + 1] = min(d[v, u1 - 1], d[v, u2 + 1])
                count = 0
            else:
                count += 1
        for u in range(width):
            if d[v, u] >= 0:
                d[v, :u] = d[v, u]
                break
        for u in range(width - 1, -1, -1):
            if d[v, u] >= 0:
                d[v, u + 1 :] = d[v, u]
                break
    for u in range(width):
        for v in range(height):
            if d[v, u] >= 0:
                d[:v, u] = d[v, u]
                break
        for v in range(height - 1, -1, -1):
            if d[v, u] >= 0:
                d[v + 1 :, u] = d[v, u]
                break
    return d


def _devkit_reads(pred: np.ndarray, tmp_path) -> np.ndarray:
    """A prediction (H, W) written as a submission's uint16 PNG (256·d truncated, the largest
    value 65535), then read as the devkit reads it: 0 is invalid (-1), else value / 256, and
    the invalid pixels interpolated."""
    from PIL import Image

    stored = np.clip(np.floor(pred * 256), 0, 65535).astype(np.uint16)
    path = tmp_path / "prediction.png"
    Image.fromarray(stored).save(path)
    read = np.asarray(Image.open(path)).astype(np.float64)
    assert read.max() == stored.max()  # a real 16-bit PNG
    return _devkit_fill(np.where(read > 0, read / 256, -1.0))


def test_kitti_dc_scores_the_prediction_as_the_devkit_reads_its_png(tmp_path) -> None:
    """The KITTI devkit: every gt > 0 counts with no cap (85 m and 200 m included), no clamp,
    per image, printed as MAE RMSE iMAE iRMSE in mm and 1/km; the prediction is scored as the
    devkit reads it back from a uint16 PNG (0.3 m reads 76/256 m; 1e-4 m stores 0, which the
    devkit fills with the smaller of its row neighbours, 0.01 m's 2/256 m)."""
    result = _score("kitti_dc", tmp_path)
    assert result.protocol.quantize == "kitti_png"
    pred, target = _frames()
    expected = []
    for image in (0, 2):
        read = _devkit_reads(pred[image, 0].numpy(), tmp_path)
        gt = target[image, 0].numpy()
        scored = np.isfinite(gt) & (gt > 0)
        expected.append(list(zip(gt[scored], read[scored], strict=True)))
    assert (10.0, 2 / 256) in expected[0] and (0.5, 76 / 256) in expected[0]
    _check(result.overall, _per_image_mean(expected), ["mae", "rmse", "imae", "irmse"])
    # Scored as floats instead, the numbers move.
    floats = _score("kitti_dc", tmp_path, "eval.quantize=none")
    assert floats.overall["imae"] != pytest.approx(result.overall["imae"], rel=1e-3)
    assert _columns(results_tables(result)) == [
        "MAE (mm)",
        "RMSE (mm)",
        "iMAE (1/km)",
        "iRMSE (1/km)",
    ]


def test_the_devkits_fill_of_empty_prediction_pixels() -> None:
    """Runs of empty pixels inside a row, at its ends, whole rows above, between and below the
    measured ones, and a map with nothing: each as the devkit's loops fill it."""
    from fusion_depth.metrics.depth import kitti_interpolate_background

    rng = np.random.default_rng(0)
    depth = rng.uniform(1, 80, (9, 23))
    depth[rng.random(depth.shape) < 0.4] = -1.0
    depth[[0, 4, 8]] = -1.0  # whole rows: above, between and below
    depth[2, :5] = depth[2, -3:] = -1.0  # runs at the ends of a row
    np.testing.assert_array_equal(kitti_interpolate_background(depth), _devkit_fill(depth))
    empty = np.full((3, 4), -1.0)
    np.testing.assert_array_equal(kitti_interpolate_background(empty), empty)


def test_densedepth_upsamples_with_mirrored_edges() -> None:
    """DenseDepth's scale_up (skimage resize, order=1, mode="reflect"; SciPy's zoom with
    mode="mirror" computes the same): the interior is plain bilinear, the 1-pixel border is not."""
    from scipy import ndimage

    from fusion_depth.models.inference import resize_depth

    low = torch.rand(2, 1, 6, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    ours = resize_depth(low, (12, 20), "bilinear_reflect")
    for i in range(2):
        reference = ndimage.zoom(low[i, 0].numpy(), 2, order=1, mode="mirror", grid_mode=True)
        np.testing.assert_allclose(ours[i, 0].numpy(), reference, atol=1e-12)
    plain = resize_depth(low, (12, 20), "bilinear")
    moved = (ours - plain).abs() > 1e-12
    assert not moved[..., 1:-1, 1:-1].any()
    assert moved[..., 0, :].any() and moved[..., -1, :].any() and moved[..., :, 0].any()


def test_densedepth_pools_and_divides_by_the_prediction(tmp_path) -> None:
    """DenseDepth's utils.py: clamped to the model's range, every pixel of every image pooled,
    rel divided by the prediction (its swapped compute_errors arguments), a1 a2 a3 rel rms
    log_10, with flip TTA."""
    result = _score("densedepth", tmp_path)
    assert result.protocol.flip_tta is True and result.protocol.averaging == "pooled"
    assert result.protocol.upsample == "bilinear_reflect"
    pooled = [(45.0, 70.0), (50.0, 40.0), (20.0, 22.0), (10.0, 8.0), (60.0, 80.0), (10.0, 0.5)]
    pooled += [*UNCROPPED, (30.0, 33.0)]  # both images' pixels in one set
    expected = _image_errors(pooled)
    gt, d = np.array(pooled).T
    expected["abs_rel"] = np.mean(np.abs(d - gt) / d)
    _check(result.overall, expected, ["delta1", "delta2", "delta3", "abs_rel", "rmse", "log10"])
    assert _columns(results_tables(result)) == ["δ1", "δ2", "δ3", "ARD", "RMSE", "LOG10"]


def test_a_key_overrides_the_preset_and_the_record_says_so(tmp_path) -> None:
    result = _score("radarnet", tmp_path, "eval.clamp=true", "eval.min_depth=0.1")
    record = result.protocol.as_dict()
    assert record["preset"] == "radarnet" and record["clamp"] is True
    assert record["units"] == "mm" and record["metrics"] == ["mae", "rmse", "imae", "irmse"]
    a80 = [(45.0, 70.0), (20.0, 22.0), (10.0, 8.0), (0.5, 0.3), (50.0, 40.0), (60.0, 80.0)]
    a80 += [(10.0, 0.1), *UNCROPPED]  # clamped to [0.1, 80]; 5e-4 m is below the new floor
    _check(result.overall, _per_image_mean([a80, [(30.0, 33.0)]]), ["mae"])


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("eval.units=km", "eval.units"),
        ("eval.metrics=[rmse,abs_err]", "eval.metrics"),
        ("eval.relative_to=pred", "eval.relative_to"),
        ("eval.min_depth=0", "eval.min_depth"),  # 0 needs eval.clamp=false
    ],
)
def test_bad_preset_keys_are_refused_by_name(tmp_path, override, message) -> None:
    cfg = compose_config(["eval=paper", override], tmp_path)
    with pytest.raises(ValueError, match=message):
        validate_config(cfg)


def test_a_prediction_of_zero_or_less_unclamped_is_wrong_not_undefined() -> None:
    """Without clamping, MAE and RMSE score a prediction ≤ 0 as it is; δ counts it wrong and
    the log errors stay finite (they see 1 µm), so a record of it can still be reported."""
    from fusion_depth.metrics.depth import compute_depth_metrics

    pred = torch.tensor([[[-1.0, 20.0]]], dtype=torch.float64)
    target = torch.tensor([[[10.0, 20.0]]], dtype=torch.float64)
    out = compute_depth_metrics(pred, target, 0.0, 80.0, clamp=False)
    assert out["mae"] == pytest.approx(11.0 / 2)
    assert out["delta1"] == 0.5  # the -1 m pixel is wrong, the 20 m one right
    assert math.isfinite(out["rmse_log"]) and math.isfinite(out["log10"])
    expected_log = math.sqrt((math.log(1e-6) - math.log(10.0)) ** 2 / 2)
    assert out["rmse_log"] == pytest.approx(expected_log)


def test_full_resolution_scoring_reads_the_upsampled_prediction_at_each_point() -> None:
    """eval.resolution=full: the network's prediction, upsampled bilinearly to the camera's
    resolution and placed with the crop offset, read at each ground-truth pixel. Here a 20x24
    camera frame served at 8x12 (halved, 2 rows cut from the top: 4 at full resolution)."""
    from fusion_depth.data.nuscenes import full_resolution_points
    from fusion_depth.models.inference import depth_at_points

    generator = torch.Generator().manual_seed(1)
    pred = torch.rand(2, 1, 8, 12, dtype=torch.float64, generator=generator) * 50 + 1
    rows, cols = np.meshgrid(np.arange(20), np.arange(24), indexing="ij")
    rows, cols = rows.ravel(), cols.ravel()
    depth = np.linspace(1.0, 70.0, len(rows))
    points = full_resolution_points(rows, cols, depth, (20, 24), (8, 12))
    assert len(points) == (20 - 4) * 24  # the 4 cut rows left out
    batch = torch.from_numpy(np.stack([points, points])).to(torch.float64)
    at_points, target = depth_at_points(pred, batch)
    assert at_points.shape == target.shape == (2, 1, 1, len(points))
    full = torch.nn.functional.interpolate(pred, size=(16, 24), mode="bilinear")
    kept = rows >= 4
    expected = full[:, 0, rows[kept] - 4, cols[kept]]
    torch.testing.assert_close(at_points[:, 0, 0], expected, rtol=0, atol=1e-6)
    assert torch.equal(target[0, 0, 0], torch.from_numpy(depth[kept]).to(torch.float32).double())


def test_full_resolution_refuses_what_it_cannot_read(tmp_path) -> None:
    for override, message in (
        ("eval.upsample=nearest", "eval.resolution=full reads the prediction bilinearly"),
        ("eval.resolution=half", "eval.resolution"),
        ("+eval.quantize=kitti_png", "eval.quantize=none"),
    ):
        cfg = compose_config(["eval=radarnet", override], tmp_path)
        with pytest.raises(ValueError, match=message):
            validate_config(cfg)
            EvalProtocol.from_config(cfg.eval, cfg.dataset.min_depth, cfg.dataset.max_depth)


def test_full_resolution_reads_bf16_outputs_at_fp32_positions() -> None:
    """A bf16 output (bf16-mixed precision) is read at its points' exact positions: bf16 holds
    no column between 796 and 800, so 798.75 would read column 799 alone."""
    from fusion_depth.models.inference import depth_at_points

    pred = torch.ones(1, 1, 2, 800)
    pred[..., 799] = 2.0  # both values exact in bf16
    points = torch.tensor([[[0.0, 798.75, 10.0], [1.0, 12.25, 20.0]]])
    with torch.autocast("cpu", dtype=torch.bfloat16):
        read, target = depth_at_points(pred.to(torch.bfloat16), points)
    assert read.dtype == torch.float32
    assert read[0, 0, 0].tolist() == [1.75, 1.0]
    assert target[0, 0, 0].tolist() == [10.0, 20.0]
