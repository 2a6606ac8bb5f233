"""python -m fusion_depth.score_sparse: the sparse input scored as the prediction, on its pixels."""

from __future__ import annotations

import pytest
import torch
from helpers import compose_config

from fusion_depth.runner.protocol import EvalProtocol
from fusion_depth.score_sparse.cli import score_sparse, score_sparse_input


def _frame(condition: str, depth: torch.Tensor, sparse: torch.Tensor) -> dict:
    return {"image": torch.zeros(3, *depth.shape), "depth": depth[None], "sparse": sparse[None],
            "condition": condition}  # fmt: skip


def test_only_the_covered_pixels_are_scored_and_coverage_counts_them() -> None:
    depth = torch.arange(1.0, 17.0).reshape(4, 4)  # 1 … 16 m
    exact = torch.zeros(4, 4)
    exact[0, :3] = depth[0, :3]  # three returns that are right
    doubled = torch.zeros(4, 4)
    doubled[1, :2] = 2 * depth[1, :2]  # two returns at twice the depth
    night_depth = depth.clone()
    night_depth[3, 3] = 0.0  # no ground truth: neither covered nor counted
    doubled[3, 3] = 5.0
    frames = [_frame("day", depth, exact), _frame("night", night_depth, doubled)]
    protocol = EvalProtocol.from_config({}, min_depth=0.5, max_depth=80.0)

    score = score_sparse_input(frames, protocol, ["day", "night"])

    day, night = score.result.by_condition["day"], score.result.by_condition["night"]
    assert (day["num_pixels"], day["abs_rel"], day["delta1"]) == (3, 0.0, 1.0)
    assert (night["num_pixels"], night["abs_rel"], night["delta1"]) == (2, 1.0, 0.0)
    assert score.result.overall["abs_rel"] == pytest.approx(0.5)  # per-image mean, as tested
    assert score.coverage == pytest.approx({"all": 5 / 31, "day": 3 / 16, "night": 2 / 15})
    assert score.num_frames == 2
    # Distance bins follow the ground truth: 1-3 m and 5-6 m all fall in 0-10 m.
    assert set(score.result.by_distance) == {"0-10"}


def test_a_sparse_input_that_covers_nothing_is_a_short_error() -> None:
    depth = torch.full((4, 4), 10.0)
    frames = [_frame("day", depth, torch.zeros(4, 4))]
    protocol = EvalProtocol.from_config({}, min_depth=0.5, max_depth=80.0)
    with pytest.raises(ValueError, match=r"covers no ground-truth pixel in \(0.5, 80\) m in 1"):
        score_sparse_input(frames, protocol, None)


def test_the_command_scores_the_built_in_radar_with_and_without_its_lines(
    tmp_path, monkeypatch, capsys
) -> None:
    monkeypatch.setenv("FUSION_DEPTH_CACHE", str(tmp_path / "cache"))
    sizes = ["dataset.num_train=5", "dataset.num_val=5", "dataset.num_test=10"]
    lines = score_sparse(compose_config(sizes, tmp_path / "a", config_name="score_sparse"))
    printed = capsys.readouterr().out
    assert "dataset=procedural split=test: the sparse input (radar)" in printed
    for row in ("| all ", "| day ", "| night ", "| fog ", "| rain ", "| cloudy ", "| 0-10 "):
        assert row in printed
    points = score_sparse(
        compose_config(
            [*sizes, "dataset.reader.radar_height_extension=0", "split=val"],
            tmp_path / "b",
            config_name="score_sparse",
        )
    )
    assert "split=val" in capsys.readouterr().out
    assert points.num_frames == 5 and lines.num_frames == 10
    # A return drawn as a 2 m line covers several pixels; as a point, one.
    per_frame = {
        s: x.result.overall["num_pixels"] / x.num_frames for s, x in (("l", lines), ("p", points))
    }
    assert per_frame["l"] > 3 * per_frame["p"] > 0
    assert 0 < points.coverage["all"] < lines.coverage["all"] < 0.2


def test_a_dataset_without_a_sparse_input_and_a_bad_split_are_refused(tmp_path) -> None:
    cfg = compose_config(["dataset=topview"], tmp_path / "a", config_name="score_sparse")
    with pytest.raises(ValueError, match="dataset=topview has no sparse input"):
        score_sparse(cfg)
    cfg = compose_config(["split=tset"], tmp_path / "b", config_name="score_sparse")
    with pytest.raises(ValueError, match="split=tset: expected one of train, val, test"):
        score_sparse(cfg)


def test_eval_radarnet_scores_the_sparse_input_at_full_resolution_as_evaluate_does() -> None:
    """Under eval.resolution=full (eval=radarnet) a frame that keeps its full-resolution ground
    truth as points (``depth_points``: rows y, x, depth in the frame's pixel coordinates) is
    scored there, as evaluate scores a prediction: each point against the return drawn on the
    frame's pixel that holds it (nearest; a sparse map is not interpolated)."""
    depth = torch.full((4, 4), 10.0)
    sparse = torch.zeros(4, 4)
    sparse[1, 2] = 12.0  # one return, 2 m too far
    sparse[3, 0] = 5.0  # one over a pixel whose full-resolution points have no ground truth
    # An 8x8 full resolution: four points in each frame pixel, at (i + 0.5) / 2 - 0.5.
    grid = (torch.arange(8.0) + 0.5) / 2 - 0.5
    y, x = torch.meshgrid(grid, grid, indexing="ij")
    truth = torch.full((8, 8), 11.0)
    truth[6:, :2] = 0.0  # the pixel under the second return: no ground truth there
    truth[2, 4] = 14.0  # one point under the first return differs
    points = torch.stack([y.flatten(), x.flatten(), truth.flatten()], dim=-1)
    points = torch.cat([points, torch.zeros(5, 3)])  # padding rows: never scored
    frame = {**_frame("day", depth, sparse), "depth_points": points}
    full = EvalProtocol.from_config({"resolution": "full"}, min_depth=0.5, max_depth=80.0)

    score = score_sparse_input([frame], full, ["day"])

    overall = score.result.overall
    assert overall["num_pixels"] == 4  # the four points of pixel (1, 2), not one frame pixel
    errors = torch.tensor([12.0 - 14.0, 1.0, 1.0, 1.0])
    assert overall["mae"] == pytest.approx(errors.abs().mean().item())
    assert score.coverage["all"] == pytest.approx(4 / 60)  # of the 60 points with ground truth
    assert score.result.protocol.resolution == "full"
    # Without points the frame is scored at its own resolution, and the record says so.
    plain = score_sparse_input([_frame("day", depth, sparse)], full, ["day"])
    assert plain.result.overall["num_pixels"] == 2
    assert plain.result.protocol.resolution == "network"


def test_the_command_says_at_which_resolution_it_scored(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setenv("FUSION_DEPTH_CACHE", str(tmp_path / "cache"))
    sizes = ["dataset.num_train=2", "dataset.num_val=2", "dataset.num_test=3", "eval=radarnet"]
    score_sparse(compose_config(sizes, tmp_path / "a", config_name="score_sparse"))
    printed = capsys.readouterr().out
    # The built-in dataset keeps no full-resolution points: its frames are what is scored.
    assert "at the frames' resolution" in printed and "eval.resolution=full" in printed
