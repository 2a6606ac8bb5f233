"""End to end: one training run, the 9-run smoke grid with its report, a failing job."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import compose_config, run_module, run_sweep
from omegaconf import OmegaConf
from PIL import Image

from fusion_depth.data.visualize import MIN_TILE_HEIGHT, panel_figure, read_panel_frames
from fusion_depth.metrics.depth import METRIC_KEYS
from fusion_depth.train.fit import train


@pytest.mark.slow
def test_one_training_run_writes_metrics_checkpoint_and_wandb(
    make_config, tmp_path, capsys
) -> None:
    cfg = make_config("experiment=smoke", "fusion=concat")
    results = train(cfg)
    out = Path(cfg.paths.output_dir)
    # The run ends with a picture of test frames, one per condition, and says where it is.
    panel = np.asarray(Image.open(out / "test_panels.png"))
    assert str(out / "test_panels.png") in capsys.readouterr().out.splitlines()[-1]
    tile = -(-MIN_TILE_HEIGHT // cfg.dataset.height) * cfg.dataset.height
    assert (
        len(cfg.dataset.conditions) * tile
        < panel.shape[0]
        < (len(cfg.dataset.conditions) + 1) * tile
    )
    # The same frames as arrays draw the same figure again, with no checkpoint (the docs'
    # pictures are drawn so from a record).
    frames, low, high = read_panel_frames(out / "test_panels.npz")
    assert [f.label for f in frames] == list(cfg.dataset.conditions)
    assert np.array_equal(panel_figure(frames, low, high), panel[..., :3])
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["test"] == results["test"]
    assert set(saved["test"]) == set(METRIC_KEYS) | {"num_images", "num_pixels"}
    assert saved["test"]["num_images"] == cfg.dataset.reader.num_test
    # Per-image records line up with the test split and add up to the overall numbers.
    rows = list(csv.DictReader((out / "per_image.csv").open()))
    assert [int(r["index"]) for r in rows] == list(range(cfg.dataset.reader.num_test))
    assert sum(int(r["num_pixels"]) for r in rows) == saved["test"]["num_pixels"]
    mean_rmse = sum(float(r["rmse"]) for r in rows) / len(rows)
    assert mean_rmse == pytest.approx(saved["test"]["rmse"], rel=1e-9)
    assert saved["protocol"]["averaging"] == "per_image" and saved["protocol"]["max_depth"] == [80]
    assert (
        sum(g["num_pixels"] for g in saved["test_by_distance"].values())
        == (saved["test"]["num_pixels"])
    )
    assert saved["latency"]["mean_s"] > 0 and saved["latency"]["device"].startswith("cpu")
    assert saved["versions"]["git_commit"] is None or len(saved["versions"]["git_commit"]) == 40
    assert saved["run"] | {"overrides": None, "wandb_id": None} == {
        "dataset": "procedural",
        "sensor": "radar",
        "model": "densedepth",
        "backbone": "resnet10t",  # experiment=smoke's encoder for DenseDepth
        "fusion": "concat",
        "loss": "l1",
        "seed": 42,
        "overrides": None,
        "wandb_id": None,
    }
    assert set(saved["test_by_condition"]) <= set(cfg.dataset.conditions)
    assert saved["global_step"] == cfg.trainer.max_epochs * cfg.trainer.limit_train_batches
    # The best checkpoint loads without unpickling code and describes its run.
    ckpt = torch.load(saved["best_checkpoint"], map_location="cpu", weights_only=True)
    assert ckpt["fusion_depth_config"]["fusion"]["mode"] == "concat"
    assert any(k.startswith("net.fusion.mix") for k in ckpt["state_dict"])
    assert ckpt["fusion_depth_run"]["fusion"] == "concat"
    wandb_runs = list((out / "wandb").glob("offline-run-*"))
    assert wandb_runs, "W&B must log offline by default"
    # The W&B run's id is recorded, so a resumed run continues that W&B run.
    assert wandb_runs[0].name.endswith(f"-{saved['run']['wandb_id']}")
    tables = {p.name.rsplit("_", 2)[0] for p in wandb_runs[0].rglob("*.table.json")}
    assert {"by_condition", "by_distance", "by_cap"} <= tables, tables
    # The run was finished, so the next job of a sweep (same process) gets a W&B run of its own.
    import wandb

    assert wandb.run is None
    resolved = OmegaConf.load(out / "config_resolved.yaml")
    assert resolved.model.loss.max_val == cfg.dataset.depth_scale / cfg.dataset.min_depth


@pytest.mark.slow
def test_smoke_grid_then_report_has_nine_rows(tmp_path) -> None:
    sweep = tmp_path / "sweep"
    result = run_sweep("loss_fusion_grid", ["seed=42"], sweep)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "9 ok, 0 failed" in result.stdout
    assert len(list(sweep.glob("*/metrics.json"))) == 9
    report = run_module(["fusion_depth.report", str(sweep)], cwd=tmp_path, timeout=120)
    assert report.returncode == 0, report.stderr
    rows = [line for line in report.stdout.splitlines() if line.startswith("| RGB")]
    assert len(rows) == 9
    combos = {tuple(c.strip() for c in row.split("|")[1:3]) for row in rows}
    assert combos == {
        (m, loss) for m in ("RGB", "RGB-Fusion", "RGB-Add") for loss in ("L1", "L2", "BerHu")
    }


@pytest.mark.slow
def test_the_weather_sweep_runs_and_report_compares_per_condition(tmp_path) -> None:
    """sweeps/procedural_weather.yaml under the smoke experiment (two seeds, two modes), then
    the table the weather results page shows: each fusion mode against rgb, image by image, per
    condition."""
    sweep = tmp_path / "weather"
    result = run_sweep("procedural_weather", ["seed=42,43", "fusion=rgb,concat"], sweep)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "4 ok, 0 failed" in result.stdout
    # Job folders are named after their overrides, so a re-run lands in the same place.
    (job,) = sweep.glob("*fusion-concat*seed-43*")
    assert (job / "per_image.csv").is_file()
    args = ["fusion_depth.report", str(sweep), "--by", "condition", "--compare", "fusion=rgb"]
    report = run_module([*args, "--resamples", "500"], cwd=tmp_path, timeout=120)
    assert report.returncode == 0, report.stderr
    assert "RGB-Fusion" in report.stdout
    assert "night" in report.stdout and "fog" in report.stdout


@pytest.mark.slow
def test_failing_job_is_recorded_and_the_sweep_goes_on(tmp_path) -> None:
    sweep = tmp_path / "sweep"
    result = run_module(
        [
            "fusion_depth.train",
            "-m",
            "experiment=smoke",
            "logger=none",
            "dataset.width=48,96",
            f"hydra.sweep.dir={sweep}",
        ],
        cwd=tmp_path,
    )
    assert result.returncode == 1
    assert "1 ok, 1 failed" in result.stdout
    failed = next(line for line in result.stdout.splitlines() if line.strip().startswith("failed"))
    assert "dataset.width=48" in failed and "multiple of 32" in failed
    # Job folders are named after their overrides (less logger=, which does not change a run).
    failure = json.loads((sweep / "dataset.width-48+experiment-smoke" / "failure.json").read_text())
    assert Path(failure["traceback"]).is_file()
    assert (sweep / "dataset.width-96+experiment-smoke" / "metrics.json").is_file()
    summary = json.loads((sweep / "sweep_summary.json").read_text())
    assert sorted(job["status"] for job in summary) == ["failed", "ok"]


@pytest.mark.slow
def test_the_same_seed_gives_the_same_metrics(make_config, tmp_path) -> None:
    """Reproducibility: seed_everything(seed, workers=True) covers init, shuffling and
    augmentation, so a second run with the same seed prints the same numbers."""
    first = train(make_config("experiment=smoke", "logger=none", "seed=7"))
    second = train(compose_config(["experiment=smoke", "logger=none", "seed=7"], tmp_path / "b"))
    for key in METRIC_KEYS:
        assert f"{first['test'][key]:.3f}" == f"{second['test'][key]:.3f}", key
        assert first["test"][key] == pytest.approx(second["test"][key], rel=1e-9), key
