"""``report --bench``: the speed and engine tables and figures of ``bench.json`` records, with
hand-computed cells, and a one-line refusal of every record a table would print wrong."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from fusion_depth.report import main, read_figure_description
from fusion_depth.runner.bench_record import load_bench_records
from fusion_depth.utils.atomic import write_json_atomic

# A record as bench --json --baseline --engines torch,openvino writes it (the keys the tables
# read, with round numbers so that each cell can be worked out by hand).
RECORD = {
    "settings": {
        "backbone": "densenet169",
        "fusion": "rgb",
        "height": 384,
        "width": 1248,
        "batch_size": 2,
        "precision": "bf16-mixed",
        "channels_last": True,
        "compile": False,
        "compile_mode": None,
        "device": "cpu",
    },
    "machine": {"cpu": "Test CPU", "torch_threads": 2, "gpu": None},
    "peak_gflops": 400.0,
    "baseline_peak_gflops": 100.0,
    "infer_gflop_per_frame": 150.0,
    "train_gflop_per_step": 900.0,
    "infer": {"latency_s_median": 0.5, "latency_s_p95": 0.6, "peak_memory_mb": 3000.0},
    "baseline_infer": {"latency_s_median": 1.5, "latency_s_p95": 1.6, "peak_memory_mb": 5000.0},
    "train": {"samples_per_s": 0.8, "step_s_median": 2.5, "peak_memory_mb": 3900.0},
    "baseline_train": {"samples_per_s": 0.25, "step_s_median": 8.0, "peak_memory_mb": 5600.0},
    "infer_speedup": 3.0,
    "train_speedup": 3.2,
    "infer_floor_s": 0.375,
    "engines": {
        "torch": {
            "latency_s_median": 0.5,
            "latency_s_p95": 0.6,
            "computes": "bf16-mixed, channels-last",
            "speedup": 1.0,
            "latency_over_floor": 0.5 / 0.375,
        },
        "openvino": {
            "latency_s_median": 0.4,
            "latency_s_p95": 0.45,
            "computes": "bf16",
            "speedup": 1.25,
            "latency_over_floor": 0.4 / 0.375,
            "export_s": 23.4,
        },
    },
}


@pytest.fixture
def records(tmp_path: Path) -> Path:
    """Two rounds of the same command, the second 10 % slower in every engine."""
    root = tmp_path / "speed"
    write_json_atomic(root / "round-1" / "bench.json", RECORD)
    slower = copy.deepcopy(RECORD)
    for entry in slower["engines"].values():
        entry["latency_s_median"] *= 1.1
        entry["latency_s_p95"] *= 1.1
    write_json_atomic(root / "round-2" / "bench.json", slower)
    return root


def _rows(printed: str) -> list[list[str]]:
    lines = [line for line in printed.splitlines() if line.startswith("|")][2:]
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in lines]


def test_speed_table_has_a_row_per_run_baseline_and_speed_up(records, capsys) -> None:
    assert main([str(records), "--bench", "speed"]) == 0
    rows = _rows(capsys.readouterr().out)
    assert [r[0] for r in rows] == ["round-1", "", "", "round-2", "", ""]
    measured = "densenet169 · fusion=rgb · 384×1248 · train batch 2 · cpu (Test CPU, 2 threads)"
    assert [r[1] for r in rows] == [measured, "", "", measured, "", ""]
    run, baseline, speedup = rows[:3]
    # 150 GFLOP in 0.5 s = 300 GFLOP/s, 75 % of the 400 peak; 900 GFLOP per 2.5 s step = 360.
    assert run[2:] == [
        "bf16-mixed, channels-last, eager",
        "0.500",
        "0.600",
        "300.0",
        "75 %",
        "0.80",
        "360.0",
        "3900",
    ]
    # The baseline against the fp32 peak: 150 / 1.5 = 100 GFLOP/s, 100 % of 100.
    assert baseline[2:] == [
        "32-true, eager, contiguous (baseline)",
        "1.500",
        "1.600",
        "100.0",
        "100 %",
        "0.25",
        "112.5",
        "5600",
    ]
    assert speedup[2:] == ["speed-up", "3.00×", "", "", "", "3.20×", "", ""]


def test_engine_table_and_figure_give_each_engine_of_each_record(records, capsys, tmp_path) -> None:
    figure = tmp_path / "engines.svg"
    argv = [str(records), "--bench", "engines", "--plot", str(figure)]
    assert main(argv) == 0
    rows = _rows(capsys.readouterr().out)
    assert [(r[0], r[2]) for r in rows] == [
        ("round-1", "torch"),
        ("", "openvino"),
        ("round-2", "torch"),
        ("", "openvino"),
    ]
    assert rows[1][3:] == ["bf16", "0.400 s (0.450)", "1.07×", "1.25×", "23"]
    assert rows[0][-1] == "–"  # PyTorch is not exported
    (panel,) = read_figure_description(figure)["panels"]
    assert panel["categories"] == ["torch", "openvino"]
    first, second = panel["series"]
    assert first["name"] == "round-1" and first["heights"] == [0.5, 0.4]
    # Whiskers from the median up to the p95: none below, p95 − median above.
    assert first["errors"] == [[0.0, 0.0], [0.1, 0.05]]
    assert second["heights"] == [0.55, 0.44]


def test_output_is_headed_by_its_command_and_speed_plot_has_both_panels(records, tmp_path) -> None:
    out, figure = tmp_path / "speed.md", tmp_path / "speed.svg"
    argv = [str(records), "--bench", "speed", "--output", str(out), "--plot", str(figure)]
    assert main(argv) == 0
    assert out.read_text().startswith("<!-- generated by: python -m fusion_depth.report ")
    description = read_figure_description(figure)
    latency, samples = description["panels"]
    assert [s["name"] for s in latency["series"]] == ["run", "eager fp32 baseline"]
    assert latency["series"][0]["heights"] == [0.5, 0.5]
    assert samples["series"][1]["heights"] == [0.25, 0.25]


@pytest.mark.parametrize(
    "change,message",
    [
        (lambda r: r["infer"].update(latency_s_median=float("nan")), "infer.latency_s_median=NaN"),
        (lambda r: r["engines"]["openvino"].update(speedup="abc"), 'speedup="abc"'),
        (lambda r: r.update(settings=[1, 2]), "settings=list: expected an object"),
        (lambda r: r["settings"].update(height="384"), 'settings.height="384": expected a int'),
        (lambda r: r.update(machine={"cpu": None}), "machine: expected a gpu name"),
        (lambda r: r.update(engines=[]), "engines=list"),
        (lambda r: r["train"].pop("samples_per_s"), "train.samples_per_s=null"),
        (lambda r: r.pop("peak_gflops"), "infer_floor_s without"),
    ],
)
def test_a_record_a_table_would_print_wrong_is_refused_naming_file_and_key(
    records, capsys, change, message
) -> None:
    path = records / "round-2" / "bench.json"
    record = json.loads(path.read_text())
    change(record)
    path.write_text(json.dumps(record))
    assert main([str(records), "--bench", "speed"]) == 2
    (error,) = capsys.readouterr().err.strip().splitlines()
    assert error.startswith(f"error: {path}: ") and message in error


@pytest.mark.parametrize(
    "text,message",
    [
        ('{"settings": ', "not valid JSON"),
        ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
        ("[1, 2]", "expected a bench record"),
        (b"\xff\xfe{}", "not valid JSON"),
    ],
)
def test_a_file_that_is_no_record_is_refused_in_a_line(records, capsys, text, message) -> None:
    path = records / "round-1" / "bench.json"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    assert main([str(records), "--bench", "engines"]) == 2
    (error,) = capsys.readouterr().err.strip().splitlines()
    assert error.startswith(f"error: {path}: ") and message in error


def test_bench_options_that_do_not_apply_are_refused(records, tmp_path, capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main([str(records), "--bench", "speed", "--by", "condition"])
    assert exit_info.value.code == 2
    assert "--by is for metrics records" in capsys.readouterr().err
    assert main([str(tmp_path / "absent"), "--bench", "speed"]) == 2
    assert "no such directory" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty"), "--bench", "speed"]) == 2
    assert "no bench.json found" in capsys.readouterr().err
    for entry in (records / "round-1" / "bench.json", records / "round-2" / "bench.json"):
        record = json.loads(entry.read_text())
        record.pop("engines"), record.pop("infer_floor_s")
        entry.write_text(json.dumps(record))
    assert main([str(records), "--bench", "engines"]) == 2
    assert "run bench with --engines" in capsys.readouterr().err


def test_records_are_named_by_their_folder(records) -> None:
    assert [name for name, _ in load_bench_records(records)] == ["round-1", "round-2"]
    assert [name for name, _ in load_bench_records(records / "round-1")] == ["round-1"]


def test_the_prepare_table_has_a_row_per_fill_method_of_each_record(tmp_path, capsys) -> None:
    """``--bench prepare``: what ``bench --only prepare`` printed, one block per record."""
    prepare = {
        "source": "/data/cache/kitti/abc/val",
        "frames": 3,
        "height": 375,
        "width": 1242,
        "measured_fraction": 0.037,
        "cores": 32,
        "methods": {
            method: {
                "s_per_frame": seconds,
                "frames_per_s_per_worker": 1 / seconds,
                "hours": {"nuscenes train": 28_130 * seconds / 32 / 3600},
            }
            for method, seconds in (("linear", 0.5), ("colorization", 2.0))
        },
    }
    prepare["methods"]["colorization"]["spsolve"] = {
        "s_per_frame": 11.0,
        "speedup": 5.5,
        "max_difference_m": 4e-6,
    }
    record = {key: RECORD[key] for key in ("settings", "machine")} | {"prepare": prepare}
    write_json_atomic(tmp_path / "prepare" / "bench.json", record)
    write_json_atomic(tmp_path / "speed" / "bench.json", RECORD)  # no prepare: no rows
    assert main([str(tmp_path), "--bench", "prepare"]) == 0
    rows = _rows(capsys.readouterr().out)
    assert [row[2:] for row in rows] == [
        ["linear", "0.500", "2.00", "", "0.12"],
        ["colorization", "2.000", "0.50", "5.5× (11.00 s), 0.004 mm", "0.49"],
    ]
    assert rows[0][0] == "prepare" and "3 frames of /data/cache/kitti/abc/val" in rows[0][1]
    assert "3.7 % of pixels measured" in rows[0][1] and "32 cores" in rows[0][1]
    assert main([str(tmp_path / "speed"), "--bench", "prepare"]) == 2
    assert "run bench with --only prepare" in capsys.readouterr().err
    out = tmp_path / "table.md"
    argv = [str(tmp_path), "--bench", "prepare", "--output", str(out), "--plot", "x.svg"]
    assert main(argv) == 2 and not out.exists()  # refused before anything is written
    assert "--plot: the prepare table has no figure" in capsys.readouterr().err
