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
