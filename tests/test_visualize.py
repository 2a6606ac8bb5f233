"""The panel figure the main job ends with (``test_panels.png``) and validation draws: shared,
labelled colour scales in metres, an error column, one frame per condition."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from fusion_depth.data.visualize import (
    MIN_TILE_HEIGHT,
    PanelFrame,
    colorize_depth,
    depth_colorbar,
    display_near,
    error_colorbar,
    error_scale,
    panel_figure,
    read_panel_frames,
    write_panel_frames,
)

MIN_DEPTH, MAX_DEPTH = 0.5, 80.0
H, W = 32, 48


def _frame(depth: float, predicted: float, label: str = "", target: bool = True) -> PanelFrame:
    """A flat grey image with ground truth ``depth`` m in its lower half (0 = none above) and a
    prediction of ``predicted`` m everywhere, at half resolution as the networks give it."""
    gt = torch.zeros(H, W)
    gt[H // 2 :] = depth
    return PanelFrame(
        image=torch.full((3, H, W), 0.6),
        sparse=torch.zeros(1, H, W),
        prediction=torch.full((H // 2, W // 2), predicted),
        target=gt if target else None,
        label=label,
    )


SCALE = -(-MIN_TILE_HEIGHT // H)  # tiles this small are enlarged by a whole factor
TILE_H, TILE_W = H * SCALE, W * SCALE


def _bars_width(height: int, near: float, max_error: float | None) -> int:
    """Columns of the depth colour bar plus, with ``max_error``, the error colour bar."""
    width = depth_colorbar(height, near, MAX_DEPTH).shape[1]
    return width + (error_colorbar(height, max_error).shape[1] if max_error else 0)


def test_error_tiles_share_one_scale_and_depth_tiles_the_depth_scale() -> None:
    frames = [_frame(10.0, 12.0, "day"), _frame(20.0, 21.0, "night")]
    figure = panel_figure(frames, MIN_DEPTH, MAX_DEPTH)
    # Errors are 2 m and 1 m; the 95th percentile 2 m is a 1-2-5 value: the top of the scale.
    assert error_scale([np.full(5, 2.0), np.full(5, 1.0)]) == 2.0
    near = display_near([f.target.numpy() for f in frames], MIN_DEPTH, MAX_DEPTH)
    assert near == 10.0  # the nearest ground truth shown, so 10-80 m get all the colours
    header = figure.shape[0] - 2 * TILE_H
    label_cols = figure.shape[1] - 5 * TILE_W - _bars_width(2 * TILE_H, near, 2.0)
    assert header > 0 and label_cols > 0  # column titles on top, condition names at the left
    assert figure[:header].max() > 200 and figure[header:, :label_cols].max() > 200

    def pixel(row: int, column: int, y: int) -> np.ndarray:
        """Pixel at ``y`` of tile ``column`` in figure row ``row`` (x at a quarter width)."""
        return figure[header + row * TILE_H + y, label_cols + column * TILE_W + TILE_W // 4]

    lower = TILE_H * 3 // 4  # inside the half with ground truth
    bar = error_colorbar(2 * TILE_H, 2.0)
    top, middle = bar[0, 2], bar[(len(bar) - 1) // 2, 2]
    assert np.abs(pixel(0, 4, lower).astype(int) - top).max() <= 2  # 2 m: the top colour
    assert np.abs(pixel(1, 4, lower).astype(int) - middle).max() <= 3  # 1 m: half-way up
    assert (pixel(0, 4, 2) == 153 // 3).all()  # no ground truth: the dimmed image
    for row, (gt, pred) in enumerate([(10.0, 12.0), (20.0, 21.0)]):
        for column, depth in ((2, pred), (3, gt)):
            expected = colorize_depth(np.array([[depth]], np.float32), near, MAX_DEPTH)[0, 0]
            assert (pixel(row, column, lower) == expected).all()


def test_frames_without_ground_truth_drop_the_ground_truth_and_error_columns() -> None:
    with_gt = panel_figure([_frame(10.0, 12.0)], MIN_DEPTH, MAX_DEPTH)
    without = panel_figure([_frame(10.0, 12.0, target=False)], MIN_DEPTH, MAX_DEPTH)
    assert with_gt.shape[0] == without.shape[0]
    # Two tiles fewer, no error colour bar, and the depth scale starts at min_depth (no GT).
    assert without.shape[1] == with_gt.shape[1] - 2 * TILE_W - _bars_width(
        TILE_H, 10.0, 2.0
    ) + _bars_width(TILE_H, MIN_DEPTH, None)


def test_bad_frames_are_refused() -> None:
    with pytest.raises(ValueError, match="no frames"):
        panel_figure([], MIN_DEPTH, MAX_DEPTH)
    small = PanelFrame(torch.zeros(3, 8, 8), torch.zeros(1, 8, 8), torch.ones(4, 4), None)
    with pytest.raises(ValueError, match="different sizes"):
        panel_figure([_frame(10.0, 12.0), small], MIN_DEPTH, MAX_DEPTH)


def _test_stage(module, conditions: list[list[str]]) -> list[str]:
    """Run ``module``'s test stage on batches with these conditions; the drawn frames' labels."""
    module.eval().on_test_epoch_start()
    with torch.no_grad():
        for batch_idx, names in enumerate(conditions):
            size = len(names)
            batch = {
                "image": torch.rand(size, 3, 64, 96),
                "sparse": torch.zeros(size, 1, 64, 96),
                "depth": torch.full((size, 1, 64, 96), 10.0),
                "condition": names,
                "index": torch.arange(size) + size * batch_idx,
            }
            module.test_step(batch, batch_idx)
    assert all(f.prediction.shape == (64, 96) for f in module.test_panels)
    return [f.label for f in module.test_panels]


def test_test_stage_draws_the_first_frame_of_each_condition(make_config) -> None:
    cfg = make_config("experiment=smoke", "fusion=concat", "model.num_test_panels=3")
    module = instantiate(cfg.model, _convert_="all")
    conditions = [["day", "day"], ["night", "day"], ["fog", "rain"]]
    assert _test_stage(module, conditions) == ["day", "night", "fog"]  # at most 3
    module.on_test_epoch_start()  # a new test stage starts a new figure
    assert module.test_panels == []


def test_a_dataset_with_one_condition_shows_its_first_test_frames(make_config) -> None:
    cfg = make_config("experiment=smoke", "dataset.conditions=[day]", "model.num_test_panels=3")
    module = instantiate(cfg.model, _convert_="all")
    assert _test_stage(module, [["day", "day"]] * 3) == ["day"] * 3


# --- panel frames as a record: test_panels.npz ------------------------------------------------


def test_panel_frames_read_back_draw_the_same_figure(tmp_path) -> None:
    frames = [_frame(10.0, 12.0, "day"), _frame(30.0, 25.0, "fog"), _frame(5.0, 5.5, "night")]
    frames[1] = PanelFrame(  # a frame with radar returns and a non-grey image
        image=torch.rand(3, H, W, generator=torch.Generator().manual_seed(0)),
        sparse=torch.where(torch.rand(1, H, W) > 0.9, 20.0, 0.0),
        prediction=frames[1].prediction,
        target=frames[1].target,
        label="fog",
    )
    path = write_panel_frames(tmp_path / "test_panels.npz", frames, MIN_DEPTH, MAX_DEPTH)
    read, low, high = read_panel_frames(path)
    assert (low, high) == (MIN_DEPTH, MAX_DEPTH)
    assert [f.label for f in read] == ["day", "fog", "night"]
    assert np.array_equal(panel_figure(read, low, high), panel_figure(frames, MIN_DEPTH, MAX_DEPTH))
    # Without ground truth a frame reads back as having none, and the figure has no error column.
    bare = [_frame(10.0, 12.0, "a", target=False)]
    again, *_ = read_panel_frames(write_panel_frames(tmp_path / "b.npz", bare, 1.0, 80.0))
    assert again[0].target is None


@pytest.mark.parametrize(
    "hostile,message",
    [
        (b"not a zip at all", "not a panel-frames file"),
        ("missing", "no array 'target'"),
        ("pickled", "not a panel-frames file"),
        ("mismatched", "arrays of mismatched shapes"),
    ],
)
def test_a_hostile_panel_frames_file_is_refused_naming_it(tmp_path, hostile, message) -> None:
    path = tmp_path / "test_panels.npz"
    good = dict(
        image=np.zeros((2, 3, H, W), np.uint8),
        sparse=np.zeros((2, H, W), np.float32),
        prediction=np.zeros((2, H // 2, W // 2), np.float32),
        target=np.zeros((2, H, W), np.float32),
        label=np.array(["a", "b"]),
        depth_range=np.array([0.5, 80.0]),
    )
    if isinstance(hostile, bytes):
        path.write_bytes(hostile)
    else:
        if hostile == "missing":
            del good["target"]
        elif hostile == "pickled":  # an object array would need pickle: it is never loaded
            good["label"] = np.array([{"a": 1}, None], dtype=object)
        else:
            good["sparse"] = np.zeros((2, H, W + 1), np.float32)
        np.savez(path, **good)
    with pytest.raises(ValueError, match=message) as err:
        read_panel_frames(path)
    assert str(path) in str(err.value)
