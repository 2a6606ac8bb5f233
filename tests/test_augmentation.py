"""Training augmentation: each model's own (RadarNet's, Sparse-to-Dense's) as its recipe composes
it, checked against the reference formulas (torchvision's, which both reference repositories
call) and against the geometry it promises."""

from __future__ import annotations

import re

import kornia.augmentation as K
import pytest
import torch
import torchvision.transforms.functional as TF
from helpers import command_message, compose_config

from fusion_depth.config import validate_config
from fusion_depth.data.radar_points import DEPTH, NUM_FIELDS, VALID, U, V
from fusion_depth.data.transforms import TrainAugmentation
from fusion_depth.errors import ArgumentError, ConfigError


def _batch(n: int = 2, height: int = 64, width: int = 96) -> dict:
    torch.manual_seed(0)
    return {
        "image": torch.rand(n, 3, height, width) * 0.6 + 0.2,
        "sparse": torch.zeros(n, 1, height, width),
        "depth": torch.rand(n, 1, height, width) * 50 + 1,
        "condition": ["day"] * n,
    }


def _with_point(batch: dict, row: int, col: int, depth: float) -> dict:
    """One radar return on pixel (row, col) of every frame, drawn in the sparse map."""
    n = len(batch["image"])
    points = torch.zeros(n, 3, NUM_FIELDS)
    points[:, 0, U], points[:, 0, V], points[:, 0, DEPTH], points[:, 0, VALID] = col, row, depth, 1
    batch["sparse"][:, 0, row, col] = depth
    return {**batch, "radar_points": points}


def test_the_defaults_draw_what_the_paper_augmentation_drew() -> None:
    """No geometry asked for: the same random numbers, so earlier runs' batches are unchanged."""
    batch = _batch(8)
    torch.manual_seed(3)
    out = TrainAugmentation()(batch)
    torch.manual_seed(3)
    flip, color = K.RandomHorizontalFlip(p=0.5), K.ColorJitter((0.75, 1.25), (0.9, 1.1), p=0.5)
    stacked = flip(torch.cat([batch["image"], batch["sparse"], batch["depth"]], 1))
    torch.testing.assert_close(out["image"], color(stacked[:, :3].contiguous()))
    torch.testing.assert_close(out["depth"], stacked[:, 4:])


def test_radarnets_colour_operations_follow_its_order_and_formulas() -> None:
    """Brightness, then contrast, then saturation, each torchvision's (RadarNet's
    fusionnet_transforms.py calls torchvision.transforms.functional)."""
    batch = _batch()
    augment = TrainAugmentation(
        flip_p=0.0,
        color_p=1.0,
        brightness=(1.1, 1.1),
        contrast=(0.8, 0.8),
        saturation=(1.2, 1.2),
        color_each=True,
    )
    expected = TF.adjust_saturation(
        TF.adjust_contrast(TF.adjust_brightness(batch["image"], 1.1), 0.8), 1.2
    )
    torch.testing.assert_close(augment(batch)["image"], expected, atol=1e-5, rtol=0)


def test_radarnets_colour_operations_are_drawn_each_on_its_own() -> None:
    """p = 0.5 each, independently: all four combinations of brightness and saturation occur,
    about a quarter each (a joint jitter would apply both or neither)."""
    n = 4000
    torch.manual_seed(0)
    grey = torch.full((n, 3, 2, 2), 0.25)
    grey[:, 0] = 0.5  # a red tint: saturation 0 makes it grey, brightness 2 doubles it
    batch = {"image": grey, "sparse": torch.zeros(n, 1, 2, 2), "depth": torch.ones(n, 1, 2, 2)}
    augment = TrainAugmentation(
        flip_p=0.0,
        color_p=0.5,
        brightness=(2.0, 2.0),
        contrast=(1.0, 1.0),
        saturation=(0.0, 0.0),
        color_each=True,
    )
    image = augment(batch)["image"]
    brighter = image[:, 1, 0, 0] > 0.4  # green: 0.25 → 0.5 when brightened
    desaturated = (image[:, 0, 0, 0] - image[:, 2, 0, 0]).abs() < 1e-4
    for b in (False, True):
        for s in (False, True):
            share = ((brighter == b) & (desaturated == s)).float().mean().item()
            assert 0.22 < share < 0.28, (b, s, share)


def test_a_crop_moves_pixels_and_points_without_resampling() -> None:
    batch = _with_point(_batch(4), row=40, col=70, depth=12.5)
    torch.manual_seed(1)
    out = TrainAugmentation(flip_p=0.0, color_p=0.0, crop=(32, 64))(batch)
    assert out["image"].shape == (4, 3, 32, 64)
    for i in range(4):
        # the crop is a window of the frame: find it by its values
        windows = batch["depth"][i, 0].unfold(0, 32, 1).unfold(1, 64, 1)
        match = (windows == out["depth"][i, 0]).all(-1).all(-1).nonzero()
        assert len(match) == 1
        top, left = match[0].tolist()
        torch.testing.assert_close(
            out["image"][i], batch["image"][i, :, top : top + 32, left : left + 64], rtol=0, atol=0
        )
        point = out["radar_points"][i, 0]
        inside = 0 <= 40 - top < 32 and 0 <= 70 - left < 64
        assert bool(point[VALID]) == inside
        if inside:
            assert (point[V].item(), point[U].item()) == (40 - top, 70 - left)
            assert out["sparse"][i, 0, 40 - top, 70 - left] == 12.5
        else:
            assert not point.any()


def test_a_zoom_divides_depth_and_keeps_each_point_on_its_pixel() -> None:
    """Sparse-to-Dense: an object s times larger is s times nearer (depth ÷ s)."""
    batch = _with_point(_batch(2), row=20, col=30, depth=15.0)
    centre = (31.5, 47.5)  # the frame's centre: the zoom magnifies about it
    augment = TrainAugmentation(
        flip_p=0.0, color_p=0.0, crop_center=centre, scale=(1.5, 1.5), resample="nearest"
    )
    out = augment(batch)
    assert out["image"].shape == batch["image"].shape
    point = out["radar_points"][0, 0]
    torch.testing.assert_close(point[V].item(), centre[0] + 1.5 * (20 - centre[0]))
    torch.testing.assert_close(point[U].item(), centre[1] + 1.5 * (30 - centre[1]))
    assert point[DEPTH].item() == pytest.approx(10.0)
    row, col = round(point[V].item()), round(point[U].item())
    assert out["sparse"][0, 0, row, col].item() == pytest.approx(10.0)
    # the return is moved, not resampled: one pixel still (nearest sampling would draw ~1.5²)
    assert int((out["sparse"][0] > 0).sum()) == 1
    # nearest-neighbour: every depth is one of the frame's, divided by the zoom
    values = set((batch["depth"][0] / 1.5).flatten().tolist())
    assert set(out["depth"][0].flatten().tolist()) <= values


def test_a_rotation_turns_about_the_crop_centre() -> None:
    batch = _with_point(_batch(64, 64, 64), row=31, col=50, depth=8.0)
    out = TrainAugmentation(flip_p=0.0, color_p=0.0, crop_center=(31.5, 31.5), rotation=5.0)(batch)
    moved = out["radar_points"][:, 0]
    radius = torch.hypot(moved[:, V] - 31.5, moved[:, U] - 31.5)
    torch.testing.assert_close(
        radius, torch.full_like(radius, float(torch.hypot(torch.tensor(-0.5), torch.tensor(18.5))))
    )
    turned = torch.atan2(moved[:, V] - 31.5, moved[:, U] - 31.5) - torch.atan2(
        torch.tensor(-0.5), torch.tensor(18.5)
    )
    assert turned.abs().max() <= torch.deg2rad(torch.tensor(5.0)) + 1e-6
    assert turned.abs().max() > torch.deg2rad(torch.tensor(3.0))  # it does turn
    assert torch.equal(moved[:, DEPTH], torch.full((64,), 8.0))  # no zoom: depth unchanged


def test_a_crop_larger_than_the_frames_is_refused() -> None:
    with pytest.raises(ArgumentError, match=r"crop=\[96, 64\]: larger than the frames") as err:
        TrainAugmentation(crop=(96, 64))(_batch())
    # a command names the config key (fusion_depth.config.arguments)
    assert command_message(err.value).startswith("augment.crop=[96, 64]: larger")


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        (
            "augment.crop=[48,64]",
            "augment.crop=[48, 64]: expected [height, width], positive multiples of 32",
        ),
        ("augment.resample=cubic", "augment.resample=cubic: expected one of"),
        ("augment.crop_placement=top", "augment.crop_placement=top: expected one of"),
        (
            "augment.crop=[96,64]",
            "augment.crop=[96, 64]: larger than the frames (dataset.height=64, dataset.width=192)",
        ),
        ("augment.saturation=[1.2,0.8]", "augment.saturation=[1.2, 0.8]: expected [low, high]"),
    ],
)
def test_bad_augmentation_values_get_a_short_error(tmp_path, override, expected) -> None:
    cfg = compose_config([override], tmp_path)
    with pytest.raises(ConfigError, match=re.escape(expected)):
        validate_config(cfg)


def test_an_outlier_filter_it_cannot_apply_is_refused_before_training(tmp_path) -> None:
    """Before: ``[-1, 1]`` passed (``-1 % 2 == 1``) and training died at its first batch with a
    torch traceback. Every kernel that is not an odd integer ≥ 1, and every threshold that is
    not finite metres > 0, is one line naming the key, before anything is built; and from
    Python, naming the argument."""
    composed = compose_config([], tmp_path)
    inf, nan = float("inf"), float("nan")
    bad = [[-1, 1], [0, 1], [-3, 1.5], [2, 1], [7, 0], [7, -1], [7, inf], [7, nan]]
    for value in [*bad, [7], [True, 1], "7"]:
        cfg = composed.copy()
        cfg.augment.outlier_filter = value
        with pytest.raises(ConfigError) as err:
            validate_config(cfg)
        assert str(err.value).startswith("augment.outlier_filter=") and "\n" not in str(err.value)
        assert "expected [kernel, threshold]: an odd side ≥ 1" in str(err.value)
    for value in bad:
        with pytest.raises(ArgumentError, match=r"^outlier_filter=.*expected \[kernel"):
            TrainAugmentation(outlier_filter=value)
    cfg = composed.copy()
    cfg.augment.outlier_filter = [1, 0.5]  # the smallest filter: no neighbour but itself
    validate_config(cfg)


_KITTI = ["dataset=kitti", "dataset.root=DATA", "dataset.raw_root=RAW"]


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        # RadarNet on nuScenes: its full-resolution frames, 448×448 crops, its colour operations
        (
            ["dataset=nuscenes", "dataset.root=DATA", "model=radarnet"],
            {"crop": [448, 448], "saturation": [0.8, 1.2], "color_each": True, "scale": None},
        ),
        # Sparse-to-Dense on KITTI: rotation, zoom, nearest resampling, its crop
        (
            [*_KITTI, "model=sparse_to_dense"],
            {
                "crop": [224, 896],
                "crop_center": [249.5, 609.5],
                "scale": [1.0, 1.5],
                "rotation": 5.0,
                "resample": "nearest",
                "color_p": 1.0,
            },
        ),
        # the model's own without a dataset's crop (recipe_from=model)
        (
            [*_KITTI, "model=sparse_to_dense", "recipe_from=model"],
            {"crop": None, "scale": [1.0, 1.5], "rotation": 5.0},
        ),
        # the built-in dataset keeps the augmentation its recipes were searched with
        (["model=radarnet"], {"crop": None, "saturation": None, "color_each": False}),
        (["model=sparse_to_dense"], {"scale": None, "rotation": 0.0, "color_p": 0.5}),
        # experiment=paper: the paper's augmentation, whatever the model
        (["model=radarnet", "experiment=paper"], {"saturation": None, "color_each": False}),
        (["model=densedepth", "dataset=nuscenes", "dataset.root=DATA"], {"crop": None}),
    ],
)
def test_each_recipe_composes_its_authors_augmentation(tmp_path, overrides, expected) -> None:
    cfg = compose_config(overrides, tmp_path)
    augment = {k: cfg.augment[k] for k in expected}
    assert {
        k: (list(v) if hasattr(v, "__len__") and not isinstance(v, str) else v)
        for k, v in augment.items()
    } == expected
    # and the module's augmentation receives them
    for key, value in expected.items():
        got = cfg.model.augmentation[key]
        assert (list(got) if hasattr(got, "__len__") and not isinstance(got, str) else got) == value


def test_radarnets_nuscenes_recipe_trains_at_its_resolution(tmp_path) -> None:
    cfg = compose_config(["dataset=nuscenes", "dataset.root=DATA", "model=radarnet"], tmp_path)
    assert (cfg.dataset.height, cfg.dataset.width) == (896, 1600)
    assert cfg.model.net.window_width == 288  # the reference's windows on a 448-wide crop
    # its training target: 12 keyframes each way merged, boxes cleared, interpolated inside the
    # hull, outliers filtered at each step; its association stage's fake points
    assert cfg.dataset.reader.lidar_keyframes == 12
    assert list(cfg.dataset.reader.lidar_removed) == ["vehicle", "human"]
    assert cfg.dataset.reader.fill == "linear_hull"
    assert list(cfg.model.augmentation.outlier_filter) == [7, 1.5]
    assert cfg.model.net.fake_point_probability == 0.1
    assert cfg.callbacks.model_checkpoint.at_least == 3


@pytest.mark.parametrize(
    "overrides",
    [
        # RadarNet's own augmentation and a crop, with its radar points moved along
        ["model=radarnet", "fusion=concat", "augment.crop=[32,64]"],
        # Sparse-to-Dense's own: zoom, rotation, nearest resampling, a crop about a fixed centre
        [
            "model=sparse_to_dense",
            "fusion=concat",
            "augment.crop=[32,64]",
            "augment.crop_center=[40,50]",
        ],
    ],
)
def test_a_run_trains_on_its_recipes_crops_and_scores_whole_frames(
    make_config, monkeypatch, overrides
) -> None:
    from fusion_depth.runner.module import DepthModule
    from fusion_depth.train.fit import train

    seen: dict[str, set] = {"train": set(), "test": set()}
    original_train, original_test = DepthModule.training_step, DepthModule.test_step

    def training_step(self, batch, batch_idx):
        seen["train"].add(tuple(batch["image"].shape[-2:]))
        return original_train(self, batch, batch_idx)

    def test_step(self, batch, batch_idx):
        seen["test"].add(tuple(batch["image"].shape[-2:]))
        return original_test(self, batch, batch_idx)

    monkeypatch.setattr(DepthModule, "training_step", training_step)
    monkeypatch.setattr(DepthModule, "test_step", test_step)
    cfg = make_config("experiment=smoke", "recipe_from=smoke", "logger=none", *overrides)
    results = train(cfg)
    assert seen == {"train": {(32, 64)}, "test": {(cfg.dataset.height, cfg.dataset.width)}}
    assert results["test"]["num_images"] == cfg.dataset.reader.num_test


def _radarnets_outlier_removal(depth: torch.Tensor, kernel: int, threshold: float):
    """RadarNet's OutlierRemoval.remove_outliers (src/net_utils.py), rewritten with loops: a
    valid pixel goes when the smallest valid depth in its window (the border and invalid pixels
    count as 10 × the largest depth) is below its own minus the threshold."""
    out = depth.clone()
    big = 10 * depth.max().item()
    _, _, h, w = depth.shape
    r = kernel // 2
    for b in range(depth.shape[0]):
        for y in range(h):
            for x in range(w):
                window = [
                    depth[b, 0, j, i].item()
                    if 0 <= j < h and 0 <= i < w and depth[b, 0, j, i] > 0
                    else big
                    for j in range(y - r, y + r + 1)
                    for i in range(x - r, x + r + 1)
                ]
                if min(window) < depth[b, 0, y, x].item() - threshold:
                    out[b, 0, y, x] = 0
    return out


def test_the_outlier_filter_is_radarnets() -> None:
    from fusion_depth.data.transforms import remove_outliers

    torch.manual_seed(0)
    depth = torch.rand(2, 1, 12, 16) * 30 + 1
    depth[torch.rand_like(depth) < 0.4] = 0  # missing pixels
    depth[0, 0, 5, 5] = 40.0  # a background point between nearer ones
    expected = _radarnets_outlier_removal(depth, 7, 1.5)
    torch.testing.assert_close(remove_outliers(depth, 7, 1.5), expected, rtol=0, atol=0)
    assert expected[0, 0, 5, 5] == 0 and (expected > 0).sum() < (depth > 0).sum()
    # in the augmentation, after the geometry, on the target only
    batch = {"image": torch.rand(2, 3, 12, 16), "sparse": depth.clone(), "depth": depth}
    batch["depth_measured"] = depth.clone()  # RadarNet's lidar map: not filtered
    out = TrainAugmentation(flip_p=0.0, color_p=0.0, outlier_filter=(7, 1.5))(batch)
    torch.testing.assert_close(out["depth"], expected, rtol=0, atol=0)
    torch.testing.assert_close(out["sparse"], depth, rtol=0, atol=0)
    torch.testing.assert_close(out["depth_measured"], depth, rtol=0, atol=0)
    # but moved with the frame, as the target is
    torch.manual_seed(2)
    out = TrainAugmentation(flip_p=1.0, color_p=0.0, crop=(8, 8))(batch)
    torch.testing.assert_close(out["depth_measured"], out["depth"], rtol=0, atol=0)


@pytest.mark.parametrize("factor", [0.8, 1.2])
def test_radarnets_integer_colour_pipeline_differs_by_at_most_three_levels(factor) -> None:
    """RadarNet jitters uint8 frames as int tensors (torchvision 0.11: each result truncated to
    a whole level and clipped to 0..255; grey truncated too). The float pipeline here differs
    from it by at most 3 of 255 levels, about 1-1.5 darker there on average (the figure the
    models guide quotes)."""
    torch.manual_seed(0)
    levels = torch.randint(0, 256, (4, 3, 48, 64)).float()
    levels[:, :, :24] = levels[:, :, :24] // 4 + 120  # a smooth half, as images have

    def grey(t):
        return (0.2989 * t[:, 0] + 0.587 * t[:, 1] + 0.114 * t[:, 2]).trunc()[:, None]

    def blend(a, b):
        return (factor * a + (1 - factor) * b).clamp(0, 255).trunc()

    theirs = blend(levels, torch.zeros_like(levels))
    theirs = blend(theirs, grey(theirs).mean(dim=(-3, -2, -1), keepdim=True))
    theirs = blend(theirs, grey(theirs))
    augment = TrainAugmentation(
        flip_p=0.0,
        color_p=1.0,
        brightness=(factor, factor),
        contrast=(factor, factor),
        saturation=(factor, factor),
        color_each=True,
    )
    batch = {"image": levels / 255, "sparse": torch.zeros(4, 1, 48, 64)}
    ours = augment({**batch, "depth": torch.ones(4, 1, 48, 64)})["image"] * 255
    difference = theirs - ours
    assert difference.abs().max() <= 3.0
    assert -2.0 < difference.mean() < -0.5


def test_radarnets_crop_placement_follows_its_random_crop() -> None:
    """RadarNet's random_crop with 'horizontal vertical': any column offset but the last; the
    row offset random 30 % of the time, else centred."""
    torch.manual_seed(0)
    n, height, width = 4000, 64, 96
    frame = torch.arange(height * width, dtype=torch.float32).view(1, 1, height, width)
    batch = {
        "image": torch.rand(n, 3, height, width),
        "sparse": torch.zeros(n, 1, height, width),
        "depth": frame.expand(n, 1, height, width) + 1,
    }
    out = TrainAugmentation(flip_p=0.0, color_p=0.0, crop=(32, 64), crop_placement="radarnet")(
        batch
    )
    corner = out["depth"][:, 0, 0, 0] - 1
    top, left = corner // width, corner % width
    assert set(left.long().tolist()) == set(range(32))  # 0..d-1, never d = 32
    centred = (top == 16).float().mean().item()  # (64 - 32) // 2
    assert centred == pytest.approx(0.70 + 0.30 / 32, abs=0.03)
    assert set(top.long().tolist()) == set(range(32))


def test_a_crop_centre_near_the_border_reads_an_empty_frame_outside() -> None:
    batch = _with_point(_batch(2), row=3, col=4, depth=9.0)
    out = TrainAugmentation(flip_p=0.0, color_p=0.0, crop=(32, 32), crop_center=(5.5, 5.5))(batch)
    assert out["depth"].shape == (2, 1, 32, 32)
    assert (out["depth"][:, :, :10, :10] == 0).all()  # above and left of the frame
    torch.testing.assert_close(out["depth"][:, :, 10:, 10:], batch["depth"][:, :, :22, :22])
    point = out["radar_points"][0, 0]
    assert (point[V].item(), point[U].item()) == (13.0, 14.0)
    assert out["sparse"][0, 0, 13, 14] == 9.0


def test_a_rotated_point_stays_on_what_the_image_shows_there() -> None:
    """The image and the points turn the same way: a bright pixel drawn where a return is
    ends up where the moved return is."""
    torch.manual_seed(0)
    batch = _with_point(_batch(64, 64, 64), row=10, col=50, depth=8.0)
    batch["image"] = torch.zeros(64, 3, 64, 64)
    batch["image"][:, :, 9:12, 49:52] = 1.0  # a 3×3 bright patch around the return
    out = TrainAugmentation(
        flip_p=0.0, color_p=0.0, crop_center=(31.5, 31.5), rotation=5.0, resample="nearest"
    )(batch)
    for i in range(64):
        point = out["radar_points"][i, 0]
        row, col = round(point[V].item()), round(point[U].item())
        assert out["image"][i, 0, row, col] == 1.0, i
