"""How ``report`` names a row's setting in its Markdown tables and figures: short labels
(fusion_depth.report.groups.short_settings), whole millimetres (Preset.decimals); and where
its columns go: the metrics right after what names a row (fusion_depth.report.groups.lay_out)."""

from __future__ import annotations

from pathlib import Path

from fusion_depth.metrics.depth import METRIC_KEYS, TABLE_METRICS
from fusion_depth.report.groups import (
    Preset,
    build_by_table,
    build_table,
    group_runs,
    settings_note,
    short_settings,
)
from fusion_depth.runner.record import load_runs
from fusion_depth.utils.atomic import write_json_atomic

ALIGNMENT = "alignment.ransac_iterations={n} alignment.space=inverse alignment.target={target}"
RANSAC = "alignment.ransac_iterations=100 alignment.ransac_threshold=0.1 alignment.space=inverse"
WEIGHTS = "prior.weights=multirun/study/stand-in/checkpoints/epoch021-loss0.0955.ckpt"


def test_what_every_row_that_sets_a_key_shares_is_named_once() -> None:
    """The prior study's settings: the weights every prior row shares and the fit's space are
    left out (and returned, for the line under the table); what tells rows apart stays, its
    dotted keys cut to their last part."""
    settings = [
        "",
        f"{WEIGHTS} prior=checkpoint",
        f"{WEIGHTS} prior=checkpoint prior=none",
        ALIGNMENT.format(n=0, target="sparse"),
        f"{RANSAC} alignment.target=sparse",
    ]
    labels, left_out = short_settings(settings)
    assert [labels[s] for s in settings] == [
        "",
        "prior=checkpoint",
        "prior=checkpoint prior=none",
        "ransac_iterations=0",
        "ransac_iterations=100",
    ]
    assert left_out == (
        "alignment.ransac_threshold=0.1",
        "alignment.space=inverse",
        "alignment.target=sparse",
        WEIGHTS,
    )
    note = settings_note([{"setting_shared": left_out}])
    assert note.startswith("\n\nLeft out of Setting") and f"`{WEIGHTS}`" in note


def test_a_shared_override_stays_where_rows_would_look_alike() -> None:
    """Left out, ``prior=checkpoint`` would make the prior's row read as the baseline's (both
    empty): the shortest such override is kept again; the weights still go."""
    settings = ["", f"{WEIGHTS} prior=checkpoint"]
    labels, left_out = short_settings(settings)
    assert labels == {"": "", settings[1]: "prior=checkpoint"}
    assert left_out == (WEIGHTS,)
    # One run with a setting and one without: the setting is all that tells them apart.
    labels, left_out = short_settings(["optimizer.lr=0.001", ""])
    assert labels == {"optimizer.lr=0.001": "lr=0.001", "": ""} and left_out == ()


def test_a_dotted_key_is_cut_only_where_its_last_part_names_it() -> None:
    """``a.x`` and ``b.x`` keep their full names (one ``x`` would be either), even where one
    of them is left out; ``+`` and ``~`` stay in front."""
    labels, left_out = short_settings(["a.x=1 b.x=2", "a.x=1 b.x=3"])
    assert labels == {"a.x=1 b.x=2": "b.x=2", "a.x=1 b.x=3": "b.x=3"} and left_out == ("a.x=1",)
    labels, _ = short_settings(["+model.lr=1", "+model.lr=2"])
    assert labels == {"+model.lr=1": "+lr=1", "+model.lr=2": "+lr=2"}


def test_lengths_in_millimetres_print_whole() -> None:
    """RadarNet's protocol prints MAE and RMSE in mm: to the millimetre, not to a thousandth
    of one; metres, ratios and 1/km keep three decimals."""
    radarnet = Preset(name="radarnet", metrics=("mae", "rmse", "imae", "irmse"), units="mm")
    assert [radarnet.decimals(m) for m in radarnet.metrics] == [0, 0, 3, 3]
    assert {Preset().decimals(m) for m in Preset().metrics} == {3}


# --- Metrics first: the columns naming a row, the metrics, then the bookkeeping ---------------

METRIC_HEADERS = ["RMSE", "ARD", "SRD", "MAE", "δ1", "δ2", "δ3"]
CSV_METRICS = [f"{k}_{s}" for k in TABLE_METRICS for s in ("mean", "std")]


def _write_run(root: Path, name: str, fusion: str, seed: int, rmse: float, wall=None) -> None:
    test = {k: 0.1 for k in METRIC_KEYS} | {"rmse": rmse, "num_images": 10}
    record = {
        "status": "ok",
        "test": test,
        "test_by_condition": {},
        "run": {
            "dataset": "procedural",
            "sensor": "radar",
            "backbone": "densenet169",
            "fusion": fusion,
            "loss": "l1",
            "seed": seed,
            "overrides": [f"fusion={fusion}", "loss=l1", f"seed={seed}"],
        },
    }
    write_json_atomic(
        root / name / "metrics.json", record | ({} if wall is None else {"wall_time_s": wall})
    )


def _header(table: str, fmt: str = "markdown") -> list[str]:
    first = table.splitlines()[1 if fmt == "latex" else 0]
    if fmt == "latex":
        return [c.strip() for c in first.removesuffix(r"\\").split("&")]
    if fmt == "csv":
        return first.split(",")
    return [c.strip() for c in first.strip("|").split("|")]


def test_the_metrics_come_right_after_what_names_a_row(tmp_path) -> None:
    """Markdown and LaTeX: Modality (Loss), the metrics, then Seeds and Training (min); a Loss
    that is L1 in every row is no Markdown column but named under the table (LaTeX keeps it);
    the best cell is still the metric's. CSV keeps its columns and their order."""
    _write_run(tmp_path, "a", "rgb", 1, rmse=1.0, wall=600.0)
    _write_run(tmp_path, "b", "rgb", 2, rmse=2.0, wall=720.0)
    _write_run(tmp_path, "c", "concat", 1, rmse=0.5)
    groups = group_runs(load_runs(tmp_path))
    table = build_table(groups, time=True)
    header = _header(table)
    assert header == ["Modality", *METRIC_HEADERS, "Seeds", "Training (min)"]
    assert table.endswith("\n\nThe same in every row, so not a column: Loss L1.")
    fusion = next(line for line in table.splitlines() if "RGB-Fusion" in line)
    assert [c.strip() for c in fusion.strip("|").split("|")][1] == "**0.500**"
    assert _header(build_table(groups, "latex", time=True), "latex") == [
        "Modality",
        "Loss",
        *METRIC_HEADERS[:4],
        *(rf"$\delta_{i}$" for i in (1, 2, 3)),
        "Seeds",
        "Training (min)",
    ]
    csv = build_table(groups, "csv", time=True)
    assert _header(csv, "csv") == [
        "Modality",
        "Loss",
        "Seeds",
        "train_min_mean",
        "train_min_std",
        *CSV_METRICS,
    ]
    assert "every row" not in csv
    by = build_by_table(groups, "condition")
    assert _header(by) == ["Modality", "RMSE (all)", "Seeds"] and "so not a column: Loss L1" in by
    assert _header(build_by_table(groups, "condition", fmt="csv"), "csv") == [
        "Modality",
        "Loss",
        "Seeds",
        "rmse_all_mean",
        "rmse_all_std",
    ]


def test_a_single_row_keeps_its_names_and_a_varying_column_stays(tmp_path) -> None:
    """A table of one row is named by its columns (nothing to tell apart, nothing to leave
    out); a compared group's Baseline is a naming column, left out where it is one value, and
    Images follows the differences."""
    from fusion_depth.report.groups import lay_out

    _write_run(tmp_path, "a", "rgb", 1, rmse=1.0)
    assert _header(build_table(group_runs(load_runs(tmp_path))))[:3] == ["Modality", "Loss", "RMSE"]
    header = (["Modality", "Loss", "Baseline"], ["Seeds", "Images"], ["ΔRMSE", "Significant"])
    rows = [
        (["RGB-Fusion", "–", "RGB"], ["3 paired", "250"], ["+0.1", "yes"]),
        (["RGB-Add", "–", "RGB"], ["3 paired", "250"], ["-0.1", "no"]),
    ]
    table = lay_out("markdown", header, rows, bold={(0, 0)})
    assert _header(table) == ["Modality", "ΔRMSE", "Significant", "Seeds", "Images"]
    assert "| **+0.1** |" in table
    assert table.endswith("The same in every row, so not a column: Loss none, Baseline RGB.")
    note = "\n\nLeft out of Setting, the same in every row that sets them: `x=1`."
    assert lay_out("markdown", header, rows, note=note).endswith(
        "`x=1`. The same in every row, so not a column: Loss none, Baseline RGB."
    )
    csv = lay_out("csv", header, rows)
    assert _header(csv, "csv") == [
        "Modality",
        "Loss",
        "Baseline",
        "Seeds",
        "Images",
        "ΔRMSE",
        "Significant",
    ]
