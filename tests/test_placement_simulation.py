"""The placement simulation (scripts/simulate_placement.py) and the results page made from it."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "simulate_placement.py"
RECORD = REPO / "results" / "records" / "placement" / "simulation.json"
PAGE = REPO / "docs" / "results" / "placement.md"


def _script():
    spec = importlib.util.spec_from_file_location("simulate_placement", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_page_shows_the_tables_of_the_committed_record() -> None:
    record = json.loads(RECORD.read_text())
    assert record["frames"] == 40 and record["script"] == "scripts/simulate_placement.py"
    assert _script().tables(record) in PAGE.read_text()


def test_a_simulated_frame_scored_four_ways() -> None:
    """On one ray-cast frame: the full-resolution pipeline agrees with RadarNet's own steps to
    0.1 % at every cap, and the old placement is off by far more."""
    record = _script().simulate(frames=1, seed=1)
    mean = record["mean_mm"]
    for cap, (mae, rmse) in mean["radarnet"].items():
        full_mae, full_rmse = mean["full"][cap]
        old_rmse = mean["old"][cap][1]
        assert abs(full_mae / mae - 1) < 1e-3 and abs(full_rmse / rmse - 1) < 1e-3, cap
        assert abs(old_rmse / rmse - 1) > 10 * abs(full_rmse / rmse - 1), cap
    other = record["other_presets"]
    assert other["kitti_dc/kitti_png"] != other["kitti_dc/none"]  # the PNG's 1/256 m moves them
