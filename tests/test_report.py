"""The paper-style table: grouping over seeds, best marks, formats, errors; per-condition
columns, paired comparisons with bootstrap intervals, plots and the W&B table."""

from __future__ import annotations

import csv
import io
import json
import shlex
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from fusion_depth.metrics.depth import METRIC_KEYS
from fusion_depth.report import (
    build_table,
    group_runs,
    main,
    paired_differences,
    read_figure_description,
)
from fusion_depth.runner.protocol import BEFORE_PRESETS
from fusion_depth.runner.record import load_runs
from fusion_depth.utils.atomic import write_json_atomic


def _write_run(root, name, fusion, loss, seed, rmse, delta1=0.8, extra=()):
    test = {k: 0.1 for k in METRIC_KEYS} | {"rmse": rmse, "delta1": delta1, "num_images": 10}
    overrides = [f"fusion={fusion}", f"loss={loss}", f"seed={seed}", *extra]
    write_json_atomic(
        root / name / "metrics.json",
        {
            "status": "ok",
            "test": test,
            "test_by_condition": {},
            "run": {
                "dataset": "procedural",
                "sensor": "radar",
                "backbone": "densenet169",
                "fusion": fusion,
                "loss": loss,
                "seed": seed,
                "overrides": overrides,
            },
        },
    )


def test_seeds_are_averaged_and_best_is_marked(tmp_path, capsys) -> None:
    _write_run(tmp_path, "a", "rgb", "l1", 1, rmse=1.0)
    _write_run(tmp_path, "b", "rgb", "l1", 2, rmse=2.0)
    _write_run(tmp_path, "c", "concat", "l1", 1, rmse=0.5, delta1=0.9)
    assert main([str(tmp_path)]) == 0
    table, note = capsys.readouterr().out.strip().split("\n\n")
    lines = table.splitlines()
    assert len(lines) == 4  # header, separator, two groups
    assert note == "The same in every row, so not a column: Loss L1."
    rgb = next(line for line in lines if "| RGB " in line)
    assert "1.500 ± 0.707" in rgb and "| 2 " in rgb  # mean ± sample std over 2 seeds
    fusion = next(line for line in lines if "RGB-Fusion" in line)
    assert "**0.500**" in fusion and "**0.900**" in fusion
    rmse = [c.strip() for c in lines[0].split("|")].index("RMSE")
    assert "**" not in rgb.split("|")[rmse]  # rgb's RMSE is not the best


def test_time_gives_each_groups_training_minutes(tmp_path, capsys) -> None:
    for name, seed, wall in (("a", 1, 600.0), ("b", 2, 720.0)):
        _write_run(tmp_path, name, "rgb", "l1", seed, rmse=1.0)
        path = tmp_path / name / "metrics.json"
        path.write_text(json.dumps({**json.loads(path.read_text()), "wall_time_s": wall}))
    _write_run(tmp_path, "c", "concat", "l1", 1, rmse=0.5)  # no wall time: evaluate's record
    assert main([str(tmp_path), "--time"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert "| Training (min) |" in lines[0]
    rgb = next(line for line in lines if "| RGB " in line)
    cells = [[c.strip() for c in line.split("|")] for line in (lines[0], rgb)]
    column = cells[0].index("Training (min)")
    assert cells[1][column] == "11.0 ± 1.4"  # 10 and 12 minutes
    fusion = next(line for line in lines if "RGB-Fusion" in line)
    assert [c.strip() for c in fusion.split("|")][column] == "–"
    assert main([str(tmp_path), "--time", "--format", "csv"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [r["train_min_mean"] for r in rows] == ["11", ""]
    with pytest.raises(SystemExit):
        main([str(tmp_path), "--time", "--by", "condition"])
    assert "--time adds a column to the plain table" in capsys.readouterr().err


def test_paper_order_loss_then_modality(tmp_path) -> None:
    for i, (fusion, loss) in enumerate(
        [("add", "berhu"), ("rgb", "l2"), ("concat", "l1"), ("rgb", "l1")]
    ):
        _write_run(tmp_path, str(i), fusion, loss, 0, rmse=1.0 + i)
    from fusion_depth.runner.record import load_runs

    groups = group_runs(load_runs(tmp_path))
    assert [(g["loss"], g["fusion"]) for g in groups] == [
        ("l1", "rgb"),
        ("l1", "concat"),
        ("l2", "rgb"),
        ("berhu", "add"),
    ]


def test_other_overrides_are_not_averaged_together(tmp_path) -> None:
    _write_run(tmp_path, "a", "rgb", "l1", 1, rmse=1.0, extra=["optimizer.lr=0.001"])
    _write_run(tmp_path, "b", "rgb", "l1", 1, rmse=3.0)
    from fusion_depth.runner.record import load_runs

    table = build_table(group_runs(load_runs(tmp_path)))
    # The setting is kept, its key cut to its last part (the CSV has it whole).
    assert "Setting" in table and "| lr=0.001 " in table and "±" not in table
    assert "optimizer.lr=0.001" in build_table(group_runs(load_runs(tmp_path)), "csv")


def test_latex_and_csv(tmp_path, capsys) -> None:
    _write_run(tmp_path, "a", "rgb", "l1", 1, rmse=1.0)
    _write_run(tmp_path, "b", "add", "l2", 1, rmse=2.0)
    assert main([str(tmp_path), "--format", "latex"]) == 0
    latex = capsys.readouterr().out
    assert r"\begin{tabular}" in latex and r"\textbf{1.000}" in latex and "RGB-Add" in latex
    assert main([str(tmp_path), "--format", "csv"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [r["Modality"] for r in rows] == ["RGB", "RGB-Add"]
    assert float(rows[1]["rmse_mean"]) == 2.0 and rows[1]["rmse_std"] == ""


def test_errors_name_the_problem(tmp_path, capsys) -> None:
    assert main([str(tmp_path / "nope")]) == 2
    assert "nope: no such directory" in capsys.readouterr().err
    assert main([str(tmp_path)]) == 2
    assert "no metrics.json" in capsys.readouterr().err
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "metrics.json").write_text("{not json")
    assert main([str(tmp_path)]) == 2
    assert "bad/metrics.json: not valid JSON" in capsys.readouterr().err
    # Hostile files are one line too: bytes that are not UTF-8, and nesting deep enough to
    # exhaust the parser's recursion.
    (tmp_path / "bad" / "metrics.json").write_bytes(b"\xff\xfe{}")
    assert main([str(tmp_path)]) == 2
    assert "bad/metrics.json: not valid JSON" in capsys.readouterr().err
    (tmp_path / "bad" / "metrics.json").write_text("[" * 100_000 + "]" * 100_000)
    assert main([str(tmp_path)]) == 2
    assert "bad/metrics.json: nested too deeply to be a metrics file" in capsys.readouterr().err


def test_unknown_format_is_rejected() -> None:
    with pytest.raises(SystemExit):
        main(["x", "--format", "html"])


# --- Per-image results: --by, --compare, --plot, --wandb -------------------------------------

CONDITIONS = ("day", "night")
NUM_IMAGES = 40
# Per-image RMSE of the RGB baseline: image i, seed s (seeds differ a little).
BASE = np.linspace(1.0, 3.0, NUM_IMAGES)


def _condition(i: int) -> str:
    return CONDITIONS[i % 2]


def _write_image_run(
    root,
    name,
    fusion,
    seed,
    rmse,
    *,
    loss="l1",
    dataset="procedural",
    split="test",
    conditions=None,
    per_image=True,
    model=None,
    backbone="densenet169",
    protocol=None,
    overrides=(),
):
    """A run with per-image RMSE ``rmse`` (one value per image) and consistent aggregates;
    ``model`` None: a record written before runs named their model; ``protocol``: the record's
    (default: a preset-less one, i.e. ``eval=paper``'s)."""
    rmse = np.asarray(rmse, dtype=float)
    conditions = conditions or [_condition(i) for i in range(len(rmse))]
    identity = {"model": model} if model is not None else {}
    model_override = [f"model={model}"] if model is not None else []

    def metrics(mask) -> dict:
        return {k: 0.1 for k in METRIC_KEYS} | {
            "rmse": float(rmse[mask].mean()),
            "num_images": int(np.sum(mask)),
        }

    cond = np.array(conditions)
    near = np.arange(len(rmse)) < len(rmse) // 2
    write_json_atomic(
        root / name / "metrics.json",
        {
            "status": "ok",
            "run": {
                "dataset": dataset,
                "sensor": "radar",
                **identity,
                "backbone": backbone,
                "fusion": fusion,
                "loss": loss,
                "seed": seed,
                "overrides": [
                    *model_override,
                    f"fusion={fusion}",
                    f"loss={loss}",
                    f"seed={seed}",
                    *overrides,
                ],
            },
            "split": split,
            "protocol": protocol or {"min_depth": 0.5, "max_depth": [80.0], "crop": "none"},
            "test": metrics(np.ones(len(rmse), bool)),
            "test_by_condition": {c: metrics(cond == c) for c in dict.fromkeys(conditions)},
            # Distance bins listed out of order on purpose: the table sorts them by range.
            "test_by_distance": {"10-20": metrics(~near), "0-10": metrics(near)},
            "per_image_file": "per_image.csv",
        },
    )
    if per_image:
        lines = ["index,condition,num_pixels,rmse,abs_rel,delta1"]
        for i, (c, v) in enumerate(zip(conditions, rmse.tolist(), strict=True)):
            lines.append(f"{i},{c},100,{v!r},0.1,0.9")
        (root / name / "per_image.csv").write_text("\n".join(lines) + "\n")


@pytest.fixture
def grid(tmp_path):
    """3 seeds × (RGB baseline, fusion far better by 0.5 at night / 0.2 by day, add no better)."""
    noise = np.random.default_rng(0).normal(0.0, 0.05, size=(3, NUM_IMAGES))
    gain = np.where(np.arange(NUM_IMAGES) % 2 == 1, 0.5, 0.2)
    runs = {}
    for s, seed in enumerate((1, 2, 3)):
        runs["rgb", seed] = BASE + 0.1 * s
        runs["concat", seed] = BASE + 0.1 * s - gain + noise[s]
        runs["add", seed] = BASE + 0.1 * s + noise[s] - noise[s].mean()
    for (fusion, seed), rmse in runs.items():
        _write_image_run(tmp_path, f"{fusion}_{seed}", fusion, seed, rmse)
    return tmp_path, runs


def _csv(capsys) -> list[dict]:
    return list(csv.DictReader(io.StringIO(capsys.readouterr().out)))


def test_by_condition_cells_are_seed_means(grid, capsys) -> None:
    root, runs = grid
    assert main([str(root), "--by", "condition", "--format", "csv"]) == 0
    rows = {r["Modality"]: r for r in _csv(capsys)}
    assert set(rows) == {"RGB", "RGB-Fusion", "RGB-Add"}
    night = np.arange(NUM_IMAGES) % 2 == 1
    for fusion, label in (("rgb", "RGB"), ("concat", "RGB-Fusion")):
        for column, mask in (("all", slice(None)), ("night", night), ("day", ~night)):
            per_seed = [runs[fusion, s][mask].mean() for s in (1, 2, 3)]
            assert float(rows[label][f"rmse_{column}_mean"]) == pytest.approx(
                np.mean(per_seed), rel=1e-5
            )
            assert float(rows[label][f"rmse_{column}_std"]) == pytest.approx(
                np.std(per_seed, ddof=1), rel=1e-4
            )
    assert main([str(root), "--by", "condition"]) == 0
    table = capsys.readouterr().out
    header, _, *lines = table.strip().splitlines()
    assert "RMSE (all)" in header and "RMSE (day)" in header and "RMSE (night)" in header
    fusion = next(line for line in lines if "RGB-Fusion" in line)
    assert fusion.count("**") == 6  # best in every column
    assert "±" in fusion


def test_by_distance_sorts_bins_and_other_metrics(grid, capsys) -> None:
    root, _ = grid
    assert main([str(root), "--by", "distance", "--metric", "delta1", "--format", "latex"]) == 0
    header = capsys.readouterr().out.splitlines()[1]
    assert header.index("(0-10)") < header.index("(10-20)") and r"$\delta_1$" in header
    assert main([str(root), "--by", "condition", "--metric", "nope"]) == 2
    err = capsys.readouterr().err
    assert "metrics.json: no metric 'nope'; expected one of" in err and "rmse" in err


def test_compare_gives_hand_computed_differences(grid, capsys) -> None:
    root, runs = grid
    argv = [str(root), "--compare", "fusion=rgb", "--by", "condition", "--resamples", "2000"]
    assert main([*argv, "--format", "csv"]) == 0
    rows = {r["Modality"]: r for r in _csv(capsys)}
    assert set(rows) == {"RGB-Fusion", "RGB-Add"}  # the baseline is not compared with itself
    night = np.arange(NUM_IMAGES) % 2 == 1
    for fusion, label in (("concat", "RGB-Fusion"), ("add", "RGB-Add")):
        diff = np.stack([runs[fusion, s] - runs["rgb", s] for s in (1, 2, 3)])
        row = rows[label]
        assert row["Baseline"] == "RGB" and row["Seeds"] == "3 paired" and row["Images"] == "40"
        for column, mask in (("all", slice(None)), ("night", night), ("day", ~night)):
            assert float(row[f"rmse_{column}_diff"]) == pytest.approx(
                diff[:, mask].mean(), rel=1e-5
            )
            low, high = float(row[f"rmse_{column}_low"]), float(row[f"rmse_{column}_high"])
            assert low <= diff[:, mask].mean() <= high
    concat, add = rows["RGB-Fusion"], rows["RGB-Add"]
    assert float(concat["rmse_night_diff"]) == pytest.approx(-0.5, abs=0.05)
    assert float(concat["rmse_night_high"]) < 0 and concat["rmse_night_significant"] == "yes"
    assert float(add["rmse_all_low"]) < 0 < float(add["rmse_all_high"])
    assert add["rmse_all_significant"] == "no" and add["level"] == "0.95"

    assert main([*argv, "--level", "0.9"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert "ΔRMSE (all, 90% CI)" in lines[0] and "Significant" in lines[0]
    concat_line = next(line for line in lines if "RGB-Fusion" in line)
    add_line = next(line for line in lines if "RGB-Add" in line)
    assert "all, day, night" in concat_line and "**-0.3" in concat_line
    # The differences and Significant first; the bookkeeping (pairing, images) after them.
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    assert header[-3:] == ["Significant", "Seeds", "Images"]
    add_cells = [c.strip() for c in add_line.strip("|").split("|")]
    assert add_cells[header.index("Significant")] == "none" and "**" not in add_line


def test_compare_without_shared_seeds_uses_seed_means(tmp_path, capsys) -> None:
    _write_image_run(tmp_path, "rgb1", "rgb", 1, BASE)
    _write_image_run(tmp_path, "rgb2", "rgb", 2, BASE + 0.2)
    _write_image_run(tmp_path, "cat", "concat", 3, BASE - 1.0)
    assert main([str(tmp_path), "--compare", "fusion=rgb", "--format", "csv"]) == 0
    (row,) = _csv(capsys)
    assert row["Seeds"] == "means 2 vs 1"
    assert float(row["rmse_all_diff"]) == pytest.approx(-1.1)
    assert row["rmse_all_significant"] == "yes"


def test_compare_by_model_lets_a_model_bring_its_prior(tmp_path, capsys) -> None:
    """Under --compare model=..., a prior (prior=, prior.*) and a fit (alignment.*) are part of
    the model: DenseDepth with a prior and the global alignment pair with DenseDepth RGB, which
    alone is the baseline (not DenseDepth RGB with a prior); another setting still keeps a group
    apart."""
    prior = ("prior=checkpoint", "prior.weights=w.ckpt")
    dd = {"model": "densedepth"}
    _write_image_run(tmp_path, "rgb", "rgb", 1, BASE, **dd)
    _write_image_run(tmp_path, "rgb_prior", "rgb", 1, BASE - 0.5, overrides=prior, **dd)
    _write_image_run(tmp_path, "cat_prior", "concat", 1, BASE - 1.0, overrides=prior, **dd)
    _write_image_run(tmp_path, "cat_lr", "concat", 1, BASE, overrides=("optimizer.lr=1",), **dd)
    fit = ("alignment.space=inverse",)
    _write_image_run(
        tmp_path, "fit", "concat", 1, BASE + 2.0, model="prior_alignment", loss=None, overrides=fit
    )
    args = [str(tmp_path), "--by", "model", "--compare", "model=densedepth,fusion=rgb"]
    assert main([*args, "--format", "csv"]) == 0
    diffs = {
        (row["Model"], row["Modality"], row["Setting"]): float(row["rmse_all_diff"])
        for row in _csv(capsys)
        if row["rmse_all_diff"]
    }
    setting = "prior.weights=w.ckpt prior=checkpoint"
    assert diffs == pytest.approx(
        {
            ("DenseDepth", "RGB", setting): -0.5,
            ("DenseDepth", "RGB-Fusion", setting): -1.0,
            ("Prior + alignment", "RGB-Fusion", "alignment.space=inverse"): 2.0,
        }
    )


def test_compare_by_loss_pairs_only_groups_differing_in_loss(grid, capsys) -> None:
    root, runs = grid
    for seed in (1, 2, 3):
        _write_image_run(root, f"rgb_l2_{seed}", "rgb", seed, runs["rgb", seed] + 1.0, loss="l2")
    assert main([str(root), "--compare", "loss=l1", "--format", "csv", "--resamples", "500"]) == 0
    (row,) = _csv(capsys)
    assert (row["Modality"], row["Loss"], row["Baseline"]) == ("RGB", "L2", "L1")
    assert float(row["rmse_all_diff"]) == pytest.approx(1.0)
    assert main([str(root), "--compare", "loss=berhu"]) == 2
    assert "--compare loss=berhu: no runs with loss=berhu (have: l1, l2)" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({"conditions": ["night"] * NUM_IMAGES}, "image 0 is 'day' in one and 'night'"),
        ({"split": "val"}, "split 'test' vs 'val'"),
    ],
)
def test_compare_refuses_different_image_sets(tmp_path, capsys, change, reason) -> None:
    _write_image_run(tmp_path, "a", "rgb", 1, BASE)
    _write_image_run(tmp_path, "b", "concat", 1, BASE - 0.1, **change)
    assert main([str(tmp_path), "--compare", "fusion=rgb"]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'a' / 'metrics.json'} and {tmp_path / 'b' / 'metrics.json'}" in err
    assert f"not scored on the same test images ({reason}" in err


def test_paired_differences_refuses_another_dataset(tmp_path) -> None:
    _write_image_run(tmp_path, "a", "rgb", 1, BASE)
    _write_image_run(tmp_path, "b", "concat", 1, BASE - 0.1, dataset="carla")
    rgb, concat = sorted(group_runs(load_runs(tmp_path)), key=lambda g: g["fusion"] != "rgb")
    with pytest.raises(ValueError, match="dataset 'procedural' vs 'carla'"):
        paired_differences(rgb, concat, "rmse")


def test_paired_differences_uses_shared_images_only(tmp_path) -> None:
    _write_image_run(tmp_path, "a", "rgb", 1, BASE)
    _write_image_run(tmp_path, "b", "concat", 1, BASE[:30] - 0.1)  # 10 images not scored
    rgb, concat = sorted(group_runs(load_runs(tmp_path)), key=lambda g: g["fusion"] != "rgb")
    diff, conditions, seeds = paired_differences(rgb, concat, "rmse")
    assert diff.shape == (1, 30) and seeds == (1,)
    np.testing.assert_allclose(diff, -0.1)
    assert conditions.tolist() == [_condition(i) for i in range(30)]


def test_compare_needs_per_image_files(tmp_path, capsys) -> None:
    _write_image_run(tmp_path, "a", "rgb", 1, BASE)
    _write_image_run(tmp_path, "b", "concat", 1, BASE, per_image=False)
    assert main([str(tmp_path), "--compare", "fusion=rgb"]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'b' / 'metrics.json'}: its per-image results" in err
    assert "per_image.csv are missing" in err
    assert main([str(tmp_path), "--compare", "fusion=rgb", "--by", "distance"]) == 2
    assert "--by distance with --compare" in capsys.readouterr().err


def test_old_metrics_files_still_give_the_basic_table(tmp_path, capsys) -> None:
    _write_run(tmp_path, "a", "rgb", "l1", 1, rmse=1.0)
    _write_run(tmp_path, "b", "concat", "l1", 1, rmse=0.5)
    assert main([str(tmp_path)]) == 0
    assert "RGB-Fusion" in capsys.readouterr().out
    assert main([str(tmp_path), "--by", "distance"]) == 2
    assert "a/metrics.json: no 'test_by_distance'" in capsys.readouterr().err
    assert main([str(tmp_path), "--compare", "fusion=rgb"]) == 2
    assert "per_image.csv are missing" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv",
    [["--compare", "seed=1"], ["--compare", "fusion"], ["--resamples", "0"], ["--level", "95"]],
)
def test_bad_options_are_rejected(argv) -> None:
    with pytest.raises(SystemExit):
        main(["x", *argv])


@pytest.mark.parametrize(
    "extra",
    [[], ["--metric", "rmse"], ["--by", "condition"], ["--compare", "fusion=rgb"]],
)
def test_plot_writes_a_png(grid, capsys, extra) -> None:
    root, _ = grid
    out = root / "plots" / "grid.png"
    assert main([str(root), "--plot", str(out), "--resamples", "200", *extra]) == 0
    with Image.open(out) as image:
        assert image.format == "PNG" and image.size[0] > 0 and image.size[1] > 0
    assert [p.name for p in out.parent.iterdir()] == ["grid.png"]  # no temporary file left


def test_plot_of_single_seeds_and_bad_extension(tmp_path, capsys) -> None:
    _write_run(tmp_path, "a", "rgb", "l1", 1, rmse=1.0)
    _write_run(tmp_path, "b", "concat", "l2", 1, rmse=0.5)
    assert main([str(tmp_path), "--plot", str(tmp_path / "p.pdf")]) == 0
    assert (tmp_path / "p.pdf").read_bytes().startswith(b"%PDF")
    assert main([str(tmp_path), "--plot", str(tmp_path / "p.xyz")]) == 2
    assert "--plot " in capsys.readouterr().err and not (tmp_path / "p.xyz").exists()


RADARNET = {
    "preset": "radarnet",
    "min_depth": 0.0,
    "max_depth": [50.0, 70.0, 80.0],
    "clamp": False,
    "units": "mm",
    "metrics": ["mae", "rmse", "imae", "irmse"],
}


def _write_radarnet_run(root, name, fusion, seed, mae_by_cap: dict[str, float]) -> None:
    def scores(mae: float) -> dict:
        return {k: 0.1 for k in METRIC_KEYS} | {"mae": mae, "imae": 2 * mae, "num_images": 10}

    write_json_atomic(
        root / name / "metrics.json",
        {
            "status": "ok",
            "run": {
                "dataset": "nuscenes",
                "sensor": "radar",
                "backbone": "densenet169",
                "fusion": fusion,
                "loss": "l1",
                "seed": seed,
                "overrides": [f"fusion={fusion}", f"seed={seed}", "eval=radarnet"],
            },
            "protocol": RADARNET,
            "test": scores(mae_by_cap["80"]),
            "test_by_cap": {cap: scores(mae) for cap, mae in mae_by_cap.items()},
        },
    )


def test_a_preset_prints_in_its_units_and_order_one_row_per_cap(tmp_path, capsys) -> None:
    """Runs scored with eval=radarnet: MAE RMSE iMAE iRMSE, MAE and RMSE in mm, a row per cap
    (as RadarNet's tables), the best per cap in bold; CSV keeps metres."""
    _write_radarnet_run(tmp_path, "a1", "rgb", 1, {"50": 2.0, "70": 3.0, "80": 4.0})
    _write_radarnet_run(tmp_path, "a2", "rgb", 2, {"50": 2.2, "70": 3.2, "80": 4.2})
    _write_radarnet_run(tmp_path, "b1", "concat", 1, {"50": 1.5, "70": 3.5, "80": 4.5})
    assert main([str(tmp_path)]) == 0
    lines = capsys.readouterr().out.strip().split("\n\n")[0].splitlines()  # the table
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    # The cap names a row (before the metrics); Seeds follows them.
    assert header[-6:] == [
        "Cap (m)", "MAE (mm)", "RMSE (mm)", "iMAE (1/km)", "iRMSE (1/km)", "Seeds"
    ]  # fmt: skip
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in lines[2:]]
    assert [(r[0], r[header.index("Cap (m)")]) for r in rows] == [
        ("RGB", "50"), ("RGB", "70"), ("RGB", "80"),
        ("RGB-Fusion", "50"), ("RGB-Fusion", "70"), ("RGB-Fusion", "80"),
    ]  # fmt: skip
    mae = header.index("MAE (mm)")
    assert rows[0][mae] == "2100 ± 141"  # mean and std of 2.0, 2.2 m, in whole mm
    assert rows[3][mae] == "**1500**" and rows[0][mae].count("**") == 0  # best at 50 m
    assert rows[2][mae].startswith("**4100")  # best at 80 m
    assert rows[0][header.index("iMAE (1/km)")].startswith("4.200 ±")  # 1/km: not scaled
    assert main([str(tmp_path), "--by", "cap", "--metric", "mae"]) == 0
    assert "MAE (mm) (50)" in capsys.readouterr().out
    assert main([str(tmp_path), "--format", "csv"]) == 0
    csv_rows = _csv(capsys)
    assert float(csv_rows[0]["mae_mean"]) == pytest.approx(2.1)  # CSV: recorded metres


def test_seeds_scored_differently_are_not_averaged(tmp_path, capsys) -> None:
    """Two seeds under one preset name, one scored with eval.clamp=true: refused, naming the
    key (evaluate does not list eval.* among a run's overrides)."""
    _write_radarnet_run(tmp_path, "a", "rgb", 1, {"50": 2.0, "70": 3.0, "80": 4.0})
    _write_radarnet_run(tmp_path, "b", "rgb", 2, {"50": 2.0, "70": 3.0, "80": 4.0})
    record = json.loads((tmp_path / "b" / "metrics.json").read_text())
    record["protocol"] = {**record["protocol"], "clamp": True, "bin_width": 5.0}
    write_json_atomic(tmp_path / "b" / "metrics.json", record)
    assert main([str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "scored differently (protocol clamp False vs True)" in err
    record["protocol"]["clamp"] = False  # a breakdown-only key may differ
    write_json_atomic(tmp_path / "b" / "metrics.json", record)
    assert main([str(tmp_path)]) == 0


def test_a_record_from_before_the_presets_pairs_with_one_scored_by_eval_paper(
    tmp_path, capsys
) -> None:
    """A baseline written before the presets (no eval.preset, eval.clamp, ... in its protocol)
    scored as eval=paper does: --compare pairs it with a new eval=paper run, and still refuses
    one scored otherwise."""
    base = np.linspace(4.0, 6.0, NUM_IMAGES)
    _write_image_run(tmp_path, "rgb", "rgb", 1, base)  # the earlier release's protocol keys
    paper = {"min_depth": 0.5, "max_depth": [80.0], "crop": "none", **BEFORE_PRESETS}
    _write_image_run(tmp_path, "concat", "concat", 1, base - 0.25, protocol=paper)
    assert main([str(tmp_path), "--compare", "fusion=rgb", "--resamples", "200"]) == 0
    assert "-0.250 [-0.250, -0.250]" in capsys.readouterr().out
    _write_image_run(
        tmp_path, "concat", "concat", 1, base - 0.25, protocol={**paper, "clamp": False}
    )
    assert main([str(tmp_path), "--compare", "fusion=rgb", "--resamples", "200"]) == 2
    assert "protocol clamp True vs False" in capsys.readouterr().err


def test_paired_differences_print_in_the_presets_units(tmp_path, capsys) -> None:
    """Under eval=radarnet a difference in RMSE is printed in mm, as its tables are."""
    base = np.linspace(4.0, 6.0, NUM_IMAGES)
    _write_image_run(tmp_path, "rgb", "rgb", 1, base, protocol=RADARNET)
    _write_image_run(tmp_path, "concat", "concat", 1, base - 0.25, protocol=RADARNET)
    assert main([str(tmp_path), "--compare", "fusion=rgb", "--resamples", "200"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    column = header.index("ΔRMSE (mm) (all, 95% CI)")
    cell = [c.strip() for c in lines[2].strip("|").split("|")][column]
    assert cell.startswith("**-250 [-250, -250]")  # -0.25 m on every image, in whole mm


def test_runs_of_different_presets_are_not_tabulated_together(tmp_path, capsys) -> None:
    _write_radarnet_run(tmp_path, "a", "rgb", 1, {"50": 2.0, "70": 3.0, "80": 4.0})
    _write_run(tmp_path, "b", "rgb", "l1", 1, rmse=1.0)  # a record from before presets: paper
    assert main([str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "different evaluation presets" in err and "eval=radarnet" in err and "eval=paper" in err
    assert "a/metrics.json" in err and "b/metrics.json" in err


def test_plot_carries_its_command_and_values_and_repeats(grid, capsys, tmp_path) -> None:
    """An SVG or PNG figure names the command that drew it and holds the plotted values (the
    seed means and stds of the table), and drawing it again writes the same bytes."""
    root, runs = grid
    night = np.arange(NUM_IMAGES) % 2 == 1
    for suffix in ("svg", "png"):
        out = tmp_path / "figures" / f"by_condition.{suffix}"
        argv = [str(root), "--by", "condition", "--plot", str(out)]
        assert main(argv) == 0
        first = out.read_bytes()
        description = read_figure_description(out)
        assert description["command"] == shlex.join(["python", "-m", "fusion_depth.report", *argv])
        (panel,) = description["panels"]
        assert panel["categories"][:3] == ["all", "day", "night"]
        series = {s["name"]: s for s in panel["series"]}
        rgb = series["RGB / L1"]
        per_seed = [runs["rgb", seed][night].mean() for seed in (1, 2, 3)]
        night_column = panel["categories"].index("night")
        assert rgb["heights"][night_column] == pytest.approx(np.mean(per_seed), rel=1e-5)
        assert rgb["errors"][night_column] == pytest.approx(np.std(per_seed, ddof=1), rel=1e-5)
        assert main(argv) == 0
        assert out.read_bytes() == first, suffix
    capsys.readouterr()
    with pytest.raises(ValueError, match="no description written by report --plot"):
        Image.new("RGB", (4, 4)).save(tmp_path / "plain.png")
        read_figure_description(tmp_path / "plain.png")


@pytest.mark.slow
def test_wandb_logs_the_table_offline(grid, monkeypatch, capsys) -> None:
    root, _ = grid
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    monkeypatch.setenv("NETRC", str(root / "no-netrc"))
    assert main([str(root), "--wandb"]) == 0
    runs = list((root / "wandb").glob("offline-run-*"))
    assert len(runs) == 1 and list(runs[0].glob("run-*.wandb"))
    assert "RGB-Fusion" in capsys.readouterr().out


# --- Several models: the Model column, --by model, --compare model=...,fusion=... -----------

MODEL_CONDITIONS = ("day", "night", "fog", "rain")
S2D = ("sparse_to_dense", "resnet18")  # a model and its own encoder


def _model_conditions(n: int) -> list[str]:
    return [MODEL_CONDITIONS[i % len(MODEL_CONDITIONS)] for i in range(n)]


@pytest.fixture
def models_grid(tmp_path):
    """3 seeds × DenseDepth (densenet169) and Sparse-to-Dense (resnet18) × RGB and RGB-Fusion;
    Sparse-to-Dense is worse by 0.5 (1.0 at night), fusion better by 0.3."""
    noise = np.random.default_rng(1).normal(0.0, 0.05, size=(3, NUM_IMAGES))
    conditions = _model_conditions(NUM_IMAGES)
    night = np.array([c == "night" for c in conditions])
    runs = {}
    for s, seed in enumerate((1, 2, 3)):
        base = BASE + 0.1 * s
        worse = np.where(night, 1.0, 0.5)
        runs["densedepth", "rgb", seed] = base
        runs["densedepth", "concat", seed] = base - 0.3 + noise[s]
        runs["sparse_to_dense", "rgb", seed] = base + worse + noise[s]
        runs["sparse_to_dense", "concat", seed] = base + worse - 0.3 + noise[s]
    for (model, fusion, seed), rmse in runs.items():
        backbone = S2D[1] if model == S2D[0] else "densenet169"
        # Sparse-to-Dense's runs first on disk: the tables still list the model table's order.
        prefix = "a" if model == S2D[0] else "b"
        _write_image_run(
            tmp_path,
            f"{prefix}_{model}_{fusion}_{seed}",
            fusion,
            seed,
            rmse,
            conditions=conditions,
            model=model,
            backbone=backbone,
        )
    return tmp_path, runs, night


def test_model_column_appears_when_models_vary(tmp_path, capsys) -> None:
    from fusion_depth.models import MODELS
    from fusion_depth.report import key_label

    _write_image_run(tmp_path, "s2d", "rgb", 1, BASE + 1.0, model=S2D[0], backbone=S2D[1])
    _write_image_run(tmp_path, "new", "rgb", 1, BASE, model="densedepth")
    _write_image_run(tmp_path, "old", "rgb", 2, BASE + 0.2)  # no model recorded: DenseDepth
    _write_image_run(tmp_path, "other", "rgb", 1, BASE, model="zz_net", backbone="x")
    groups = group_runs(load_runs(tmp_path))
    assert [(g["model"], g["n"]) for g in groups] == [
        ("densedepth", 2),
        ("sparse_to_dense", 1),
        ("zz_net", 1),
    ]
    assert main([str(tmp_path)]) == 0
    table, note = capsys.readouterr().out.strip().split("\n\n")
    header, _, *lines = table.splitlines()
    cells = [c.strip() for c in header.strip("|").split("|")]
    # Modality and Loss are one value in every row: named under the table, not columns.
    assert cells[:3] == ["Model", "Backbone", "RMSE"]
    assert note == "The same in every row, so not a column: Modality RGB, Loss L1."
    assert [line.split("|")[1].strip() for line in lines] == [
        "DenseDepth",
        MODELS["sparse_to_dense"].label,
        "zz_net",  # a model the table does not know keeps its name
    ]
    assert key_label("model", "sparse_to_dense") == "Sparse-to-Dense"
    assert key_label("model", "zz_net") == "zz_net"
    # One model: no Model column, as before.
    assert main([str(tmp_path / "old")]) == 0
    assert "Model" not in capsys.readouterr().out


def test_by_model_gives_means_per_model_and_differences_to_densedepth(models_grid, capsys) -> None:
    root, runs, night = models_grid
    argv = [str(root), "--by", "model", "--resamples", "1000"]
    assert main(argv) == 0
    out = capsys.readouterr().out.strip()
    parts = out.split("\n\n")
    means, differences = [part for part in parts if part.startswith("|")]
    below = parts[parts.index(differences) + 1 :]  # the note under the differences
    header, _, *rows = means.splitlines()
    assert [c.strip() for c in header.strip("|").split("|")][:3] == [
        "Model",
        "Backbone",
        "Modality",
    ]
    # Night and fog first, then the others in file order.
    assert [header.index(f"({c})") for c in ("all", "night", "fog", "day", "rain")] == sorted(
        header.index(f"({c})") for c in ("all", "night", "fog", "day", "rain")
    )
    assert [r.split("|")[1].strip() for r in rows] == ["DenseDepth"] * 2 + ["Sparse-to-Dense"] * 2
    assert all("±" in r for r in rows)
    header, _, *rows = differences.splitlines()
    assert "ΔRMSE (night, 95% CI)" in header
    assert header.index("(night,") < header.index("(fog,") < header.index("(day,")
    assert len(rows) == 2 and all("Sparse-to-Dense" in r for r in rows)
    # One baseline for both rows (named with its encoder): under the table, not a column.
    assert "Baseline" not in header and "Baseline DenseDepth / densenet169" in below[0]

    assert main([*argv, "--format", "csv"]) == 0
    rows = _csv(capsys)
    assert [(r["Model"], r["Modality"]) for r in rows] == [
        ("DenseDepth", "RGB"),
        ("DenseDepth", "RGB-Fusion"),
        ("Sparse-to-Dense", "RGB"),
        ("Sparse-to-Dense", "RGB-Fusion"),
    ]
    assert rows[0]["Baseline"] == "" and rows[0]["rmse_all_diff"] == ""  # the baselines
    for row, fusion in zip(rows[2:], ("rgb", "concat"), strict=True):
        s2d = np.stack([runs["sparse_to_dense", fusion, s] for s in (1, 2, 3)])
        dd = np.stack([runs["densedepth", fusion, s] for s in (1, 2, 3)])
        assert row["Backbone"] == "resnet18" and row["Seeds"] == "3"
        assert row["Pairing"] == "3 paired" and row["Images"] == str(NUM_IMAGES)
        per_seed = s2d[:, night].mean(axis=1)
        assert float(row["rmse_night_mean"]) == pytest.approx(per_seed.mean(), rel=1e-5)
        assert float(row["rmse_night_std"]) == pytest.approx(np.std(per_seed, ddof=1), rel=1e-4)
        day = np.array(_model_conditions(NUM_IMAGES)) == "day"
        for column, mask in (("all", slice(None)), ("night", night), ("day", day)):
            assert float(row[f"rmse_{column}_diff"]) == pytest.approx(
                (s2d - dd)[:, mask].mean(), rel=1e-5
            )
        assert float(row["rmse_night_diff"]) == pytest.approx(1.0, abs=0.05)
        assert row["rmse_night_significant"] == "yes" and row["level"] == "0.95"

    out = root / "plots" / "by_model.png"
    assert main([*argv, "--plot", str(out)]) == 0
    with Image.open(out) as image:
        assert image.format == "PNG"


def test_by_model_of_one_model_prints_the_table(grid, capsys) -> None:
    root, _ = grid
    assert main([str(root), "--by", "model"]) == 0
    captured = capsys.readouterr()
    tables = [part for part in captured.out.strip().split("\n\n") if part.startswith("|")]
    assert len(tables) == 1 and "Model" in captured.out.splitlines()[0]
    assert "DenseDepth" in captured.out and "one model" in captured.err


def test_compare_model_and_fusion_pairs_on_shared_images(models_grid, capsys) -> None:
    root, runs, night = models_grid
    # Sparse-to-Dense RGB-Add (seed 1) scored on the first 30 images only; an L2 group, which
    # differs in loss, is not compared.
    add = runs["sparse_to_dense", "rgb", 1][:30] + 0.25
    _write_image_run(
        root,
        "s2d_add",
        "add",
        1,
        add,
        conditions=_model_conditions(30),
        model=S2D[0],
        backbone=S2D[1],
    )
    _write_image_run(
        root,
        "s2d_l2",
        "rgb",
        1,
        runs["sparse_to_dense", "rgb", 1],
        loss="l2",
        conditions=_model_conditions(NUM_IMAGES),
        model=S2D[0],
        backbone=S2D[1],
    )
    argv = [str(root), "--compare", "model=densedepth,fusion=rgb", "--resamples", "1000"]
    assert main([*argv, "--format", "csv"]) == 0
    rows = {(r["Model"], r["Backbone"], r["Modality"]): r for r in _csv(capsys)}
    assert set(rows) == {
        ("DenseDepth", "densenet169", "RGB-Fusion"),
        ("Sparse-to-Dense", "resnet18", "RGB"),
        ("Sparse-to-Dense", "resnet18", "RGB-Fusion"),
        ("Sparse-to-Dense", "resnet18", "RGB-Add"),
    }
    assert rows["DenseDepth", "densenet169", "RGB-Fusion"]["Baseline"] == "DenseDepth / RGB"
    row = rows["Sparse-to-Dense", "resnet18", "RGB-Add"]
    assert row["Baseline"] == "DenseDepth / densenet169 / RGB" and row["Loss"] == "L1"
    # Seed 1 only, over the 30 images both scored.
    expected = (add - runs["densedepth", "rgb", 1][:30]).mean()
    assert row["Seeds"] == "1 paired" and row["Images"] == "30"
    assert float(row["rmse_all_diff"]) == pytest.approx(expected, rel=1e-6)
    assert float(row["rmse_all_low"]) <= expected <= float(row["rmse_all_high"])
    s2d_concat = rows["Sparse-to-Dense", "resnet18", "RGB-Fusion"]
    diff = np.stack(
        [runs["sparse_to_dense", "concat", s] - runs["densedepth", "rgb", s] for s in (1, 2, 3)]
    )
    assert float(s2d_concat["rmse_all_diff"]) == pytest.approx(diff.mean(), rel=1e-5)

    # One model compared against another, fusion held fixed: backbone and loss may differ too
    # (each model brings its own); a group is paired with the baseline sharing most of them.
    assert main([str(root), "--compare", "model=densedepth", "--format", "csv"]) == 0
    pairs = {(r["Modality"], r["Loss"], r["Baseline"]) for r in _csv(capsys)}
    assert pairs == {
        ("RGB", "L1", "DenseDepth / densenet169"),
        ("RGB-Fusion", "L1", "DenseDepth / densenet169"),
        ("RGB", "L2", "DenseDepth / densenet169 / L1"),
    }


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("model=nope", "--compare model=nope: no runs with model=nope (have: densedepth, "),
        (  # each value has runs, but not together
            "model=sparse_to_dense,backbone=densenet169",
            "--compare model=sparse_to_dense,backbone=densenet169: no runs with "
            "model=sparse_to_dense and backbone=densenet169 (have: ",
        ),
    ],
)
def test_compare_unknown_value_is_one_line(models_grid, capsys, spec, message) -> None:
    root, _, _ = models_grid
    assert main([str(root), "--compare", spec]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {message}") and err.count("\n") == 1


@pytest.mark.parametrize(
    "spec", ["model=densedepth,model=x", "model=densedepth,seed=1", "model=densedepth,", "model"]
)
def test_bad_multi_key_compare_is_rejected(spec) -> None:
    with pytest.raises(SystemExit):
        main(["x", "--compare", spec])


def test_where_keeps_one_configuration_and_its_seeds(models_grid, capsys) -> None:
    root, runs, night = models_grid
    argv = [str(root), "--where", "model=densedepth,fusion=concat", "--by", "condition"]
    assert main([*argv, "--format", "csv"]) == 0
    rows = _csv(capsys)
    assert len(rows) == 1 and rows[0]["Modality"] == "RGB-Fusion"
    per_seed = [runs["densedepth", "concat", s][night].mean() for s in (1, 2, 3)]
    assert float(rows[0]["rmse_night_mean"]) == pytest.approx(np.mean(per_seed), rel=1e-5)
    # the kept runs alone are compared: Sparse-to-Dense's are gone, RGB is the baseline
    assert main([str(root), "--where", "model=densedepth", "--compare", "fusion=rgb"]) == 0
    table = capsys.readouterr().out
    assert "Sparse-to-Dense" not in table and "RGB-Fusion" in table


def test_where_without_a_matching_run_names_the_values_there(models_grid, capsys) -> None:
    root, _, _ = models_grid
    err = _refused(capsys, [str(root), "--where", "fusion=add"])
    assert err == "error: --where fusion=add: no run has it (the runs have fusion: concat, rgb)"
    with pytest.raises(SystemExit):  # a key the records do not identify runs by
        main([str(root), "--where", "seed=1"])
    assert "--where" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(root), "--bench", "speed", "--where", "fusion=rgb"])
    assert "--where is for metrics records" in capsys.readouterr().err


def test_first_puts_columns_first(grid, capsys) -> None:
    root, _ = grid
    assert main([str(root), "--by", "condition", "--first", "night"]) == 0
    header = capsys.readouterr().out.splitlines()[0]
    assert header.index("(all)") < header.index("(night)") < header.index("(day)")
    assert main([str(root), "--by", "condition"]) == 0  # without it: file order
    header = capsys.readouterr().out.splitlines()[0]
    assert header.index("(day)") < header.index("(night)")
    assert main([str(root), "--by", "condition", "--first", "nigth"]) == 2
    assert "--first nigth: no condition 'nigth' (have: day, night)" in capsys.readouterr().err
    assert main([str(root), "--first", "night"]) == 2
    assert "give --by too" in capsys.readouterr().err


def test_output_writes_the_table_headed_by_its_command(grid, capsys, tmp_path) -> None:
    """--output: the printed table, in a file whose first line says how to make it again, and
    that command, run again, writes the same bytes (the bootstrap is seeded)."""
    grid, _ = grid
    out = tmp_path / "tables" / "rmse.md"
    out.parent.mkdir()
    argv = [str(grid), "--by", "condition", "--compare", "fusion=rgb", "--output", str(out)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    text = out.read_text()
    first, _, table = text.partition("\n\n")
    assert first == f"<!-- generated by: python -m fusion_depth.report {shlex.join(argv)} -->"
    assert table == printed
    again = out.read_bytes()
    out.unlink()
    assert (
        main(shlex.split(first.removeprefix("<!-- generated by: ").removesuffix(" -->"))[3:]) == 0
    )
    assert out.read_bytes() == again
    # LaTeX gets a % comment; CSV stays plain CSV; a path below a file is a short error.
    assert main([str(grid), "--format", "latex", "--output", str(tmp_path / "t.tex")]) == 0
    assert (tmp_path / "t.tex").read_text().startswith("% generated by: python -m fusion_depth")
    assert main([str(grid), "--format", "csv", "--output", str(tmp_path / "t.csv")]) == 0
    assert (tmp_path / "t.csv").read_text().startswith("Modality")
    capsys.readouterr()
    assert main([str(grid), "--output", str(tmp_path / "t.csv" / "t.md")]) == 2
    assert "t.csv" in capsys.readouterr().err


# --- hostile inputs: each refused in one line that names the file ----------------------------


def _refused(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    return err


@pytest.mark.parametrize(
    "section,value,expected",
    [
        ("test", {"rmse": float("nan")}, "test.rmse=NaN: expected a finite number"),
        ("test", {"rmse": "abc"}, 'test.rmse="abc": expected a finite number'),
        ("test", {"rmse": True}, "test.rmse=true: expected a finite number"),
        ("test", [1, 2], "test: expected an object of metric values, got list"),
        ("test_by_condition", {"night": {"rmse": None}}, "test_by_condition.night.rmse=null"),
        ("test_by_condition", ["night"], "test_by_condition: expected an object of groups"),
    ],
)
def test_a_score_that_is_not_a_finite_number_is_refused(
    tmp_path, capsys, section, value, expected
) -> None:
    _write_run(tmp_path, "a", "rgb", "l1", 1, rmse=1.0)
    path = tmp_path / "a" / "metrics.json"
    data = json.loads(path.read_text())
    data[section] = (
        {**data[section], **value} if section == "test" and isinstance(value, dict) else value
    )
    path.write_text(json.dumps(data))  # json writes NaN as NaN, as a careless tool would
    err = _refused(capsys, [str(tmp_path)])
    assert err.startswith(f"error: {path}: ") and expected in err


def _first_run(grid) -> tuple[Path, list[str]]:
    root, _ = grid
    per_image = root / "concat_1" / "per_image.csv"
    return per_image, [str(root), "--compare", "fusion=rgb", "--resamples", "50"]


def test_a_per_image_file_cut_mid_row_is_refused(grid, capsys) -> None:
    per_image, argv = _first_run(grid)
    text = per_image.read_text()
    last = text.rstrip("\n").rsplit("\n", 1)[1]
    # cut inside the condition field: the row has too few fields
    per_image.write_text(text[: len(text) - len(last) - 1 + 4])
    assert "expected 6 fields (a cut or damaged file)" in _refused(capsys, argv)
    # cut inside the last field: as many fields, but the line is not ended
    per_image.write_text(text.rstrip("\n")[:-2])
    assert "the last row is cut short" in _refused(capsys, argv)


def test_a_per_image_file_with_more_or_fewer_rows_than_images_is_refused(grid, capsys) -> None:
    per_image, argv = _first_run(grid)
    header, *rows = per_image.read_text().splitlines()
    huge = [header, *rows, *(f"{NUM_IMAGES + i},day,1,1.0,0.1,0.9" for i in range(10**6))]
    per_image.write_text("\n".join(huge) + "\n")
    err = _refused(capsys, argv)
    assert str(per_image) in err and f"more rows than the {NUM_IMAGES} images" in err
    per_image.write_text("\n".join([header, *rows[:-1]]) + "\n")
    assert f"{NUM_IMAGES - 1} rows, but its metrics.json scored {NUM_IMAGES}" in _refused(
        capsys, argv
    )
    rows[0] = "-1" + rows[0][rows[0].index(",") :]
    per_image.write_text("\n".join([header, *rows]) + "\n")
    assert "image index -1 is not an index of the split" in _refused(capsys, argv)


def test_csv_cells_a_spreadsheet_would_run_are_neutralised(tmp_path, capsys) -> None:
    """OWASP's CSV injection: a recorded value starting with = + - @ tab or CR is written with a
    leading ' so that a spreadsheet shows it; numbers, negative ones too, stay numbers."""
    hostile = "=cmd|' /C calc'!A0"
    _write_run(tmp_path, "a", "rgb", hostile, 1, rmse=1.0)
    _write_run(tmp_path, "b", "rgb", "@SUM(A1)", 1, rmse=2.0)
    assert main([str(tmp_path), "--format", "csv"]) == 0
    rows = _csv(capsys)
    losses = {r["Loss"] for r in rows}
    assert losses == {"'" + hostile, "'@SUM(A1)"}
    for row in rows:
        for cell in row.values():
            assert not cell.startswith(("=", "+", "@", "\t", "\r")), cell
            assert not cell.startswith("-") or float(cell) < 0, cell


# --- records of frames prepared by different format versions ----------------------------------


def _set_format_version(root: Path, name: str, version: int | None) -> None:
    path = root / name / "metrics.json"
    record = json.loads(path.read_text())
    record["run"].pop("format_version", None)
    if version is not None:
        record["run"]["format_version"] = version
    write_json_atomic(path, record)


def test_records_of_different_data_format_versions_are_not_compared(tmp_path, capsys) -> None:
    """nuScenes records made before the placement change (format 2, or a record from before
    records named their format) and after it (3) are refused in one line naming both versions
    and both records; --mixed-formats reports them anyway, saying so."""
    base = np.linspace(4.0, 6.0, NUM_IMAGES)
    _write_image_run(tmp_path, "old", "rgb", 1, base, dataset="nuscenes")  # names no version
    _write_image_run(tmp_path, "new", "concat", 1, base - 0.1, dataset="nuscenes")
    _set_format_version(tmp_path, "new", 3)
    old, new = (str(tmp_path / n / "metrics.json") for n in ("old", "new"))
    compare = [str(tmp_path), "--compare", "fusion=rgb", "--resamples", "200"]
    for argv in (compare, [str(tmp_path)], [str(tmp_path), "--by", "condition"]):
        assert main(argv) == 2
        captured = capsys.readouterr()
        err = captured.err.strip()
        assert "\n" not in err and "Traceback" not in err, err
        assert "format version" in err and "unknown" in err and "3" in err, err
        assert old in err and new in err and captured.out == ""
    _set_format_version(tmp_path, "old", 2)
    assert main(compare) == 2
    err = capsys.readouterr().err
    assert "nuscenes" in err and "2 (" in err and "3 (" in err and old in err and new in err
    # Asked for, they are compared, and the mix is said on stderr in one line.
    assert main([*compare, "--mixed-formats"]) == 0
    captured = capsys.readouterr()
    assert "-0.100" in captured.out
    (note,) = captured.err.strip().splitlines()
    assert note.startswith("note: ") and "2 (" in note and "3 (" in note
    # One version, or versions of different datasets, are compared as before.
    _set_format_version(tmp_path, "old", 3)
    assert main(compare) == 0
    assert capsys.readouterr().err == ""
    _write_image_run(tmp_path, "kitti", "rgb", 1, base, dataset="kitti")
    _set_format_version(tmp_path, "kitti", 1)
    assert main([str(tmp_path)]) == 0
    with pytest.raises(SystemExit):
        main([str(tmp_path), "--bench", "speed", "--mixed-formats"])
    assert "--mixed-formats is for metrics records" in capsys.readouterr().err


def test_records_carry_the_format_version_of_the_frames_they_scored(tmp_path) -> None:
    """Training (run_identity) and evaluate (rescored_identity) record their dataset reader's
    format version; a dataset without prepared frames, or a reader the package does not hold
    and that is not loaded, records none (and nothing is imported for it)."""
    import sys

    from fusion_depth.data import kitti, nuscenes
    from fusion_depth.runner.record import (
        RunRecord,
        read_run_record,
        rescored_identity,
        run_identity,
        write_run_record,
    )

    def config(name: str, target: str) -> dict:
        return {"dataset": {"name": name, "reader": {"_target_": target}}, "seed": 1}

    nusc = config("nuscenes", "fusion_depth.data.nuscenes.NuScenesDepth")
    assert run_identity(nusc).format_version == nuscenes.FORMAT_VERSION == 3
    kitti_block = config("kitti", "fusion_depth.data.kitti.KittiDepth")["dataset"]
    assert run_identity({"dataset": kitti_block}).format_version == kitti.KittiDepth.format_version
    procedural = config("procedural", "fusion_depth.data.procedural.ProceduralDepth")
    assert run_identity(procedural).format_version is None
    foreign = config("mine", "not_a_loaded_module_of_mine.Reader")
    assert run_identity(foreign).format_version is None
    assert "not_a_loaded_module_of_mine" not in sys.modules
    # evaluate: the version of the dataset scored now, not of the one trained on.
    trained = run_identity(procedural).to_json()
    rescored = rescored_identity(trained, procedural, nusc["dataset"])
    assert (rescored.dataset, rescored.trained_on) == ("nuscenes", "procedural")
    assert rescored.format_version == 3
    # Written and read back with the record; a record of a dataset without one has none.
    record = RunRecord(status="ok", run=rescored, test={"rmse": 1.0}, checkpoint="x.ckpt")
    back = read_run_record(write_run_record(tmp_path / "a", record))
    assert back.run.format_version == 3
    plain = RunRecord(status="ok", run=run_identity(procedural), test={"rmse": 1.0})
    written = json.loads(write_run_record(tmp_path / "b", plain).read_text())
    assert "format_version" not in written["run"]
