"""The paper-style table: grouping over seeds, best marks, formats, errors."""

from __future__ import annotations

import csv
import io

import pytest

from fusion_depth.metrics import METRIC_KEYS
from fusion_depth.report import build_table, group_runs, main
from fusion_depth.runs import write_json_atomic


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
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 4  # header, separator, two groups
    rgb = next(line for line in lines if "| RGB " in line)
    assert "1.500 ± 0.707" in rgb and "| 2 " in rgb  # mean ± sample std over 2 seeds
    fusion = next(line for line in lines if "RGB-Fusion" in line)
    assert "**0.500**" in fusion and "**0.900**" in fusion
    assert "**" not in rgb.split("|")[4]  # rgb's RMSE is not the best


def test_paper_order_loss_then_modality(tmp_path) -> None:
    for i, (fusion, loss) in enumerate(
        [("add", "berhu"), ("rgb", "l2"), ("concat", "l1"), ("rgb", "l1")]
    ):
        _write_run(tmp_path, str(i), fusion, loss, 0, rmse=1.0 + i)
    from fusion_depth.runs import load_runs

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
    from fusion_depth.runs import load_runs

    table = build_table(group_runs(load_runs(tmp_path)))
    assert "Setting" in table and "optimizer.lr=0.001" in table and "±" not in table


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


def test_unknown_format_is_rejected() -> None:
    with pytest.raises(SystemExit):
        main(["x", "--format", "html"])
