"""A bench record: the JSON ``python -m fusion_depth.bench --json bench.json`` writes, read back
as plain data, and the table rows both ``bench`` (one record) and ``report --bench`` (every
record below a folder) print from it.

Two tables come from a record:

* **speed** (:data:`SPEED_HEADER`): batch-1 inference latency (median and p95, s), the GFLOP/s
  that latency achieves and its share of the measured matrix-product peak, training samples/s
  and GFLOP/s, and peak memory (MB); one row for the run's settings, and with ``--baseline`` one
  for eager fp32 and one of speed-ups.
* **engines** (:data:`ENGINE_HEADER`): with ``--engines``, one row per engine: what it computes
  in, its batch-1 latency (median, p95), that latency over the frame's FLOP floor, its speed-up
  over PyTorch, and the seconds its export took.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from fusion_depth.utils.json_file import read_json
from fusion_depth.utils.schema import is_int, is_number

BENCH_FILE = "bench.json"
# A record as load_bench_records gives it: (its folder below the root, the record).
NamedRecord = tuple[str, Mapping[str, Any]]

SPEED_HEADER = (
    "run",
    "infer median (s)",
    "infer p95 (s)",
    "infer GFLOP/s",
    "of matmul peak",
    "train samples/s",
    "train GFLOP/s",
    "peak memory (MB)",
)
ENGINE_HEADER = (
    "engine",
    "computes in",
    "batch-1 latency, median (p95)",
    "latency / FLOP floor",
    "speed-up over torch",
    "export (s)",
)
BASELINE_RUN = "32-true, eager, contiguous (baseline)"

# The fields the tables read: dotted key → (may be null, what it must be).
_SETTINGS = {
    "backbone": str,
    "fusion": str,
    "height": int,
    "width": int,
    "batch_size": int,
    "precision": str,
    "channels_last": bool,
    "compile": bool,
    "device": str,
}
_TIMINGS = {  # each stage's timings: a missing stage is left out of the record
    "infer": ("latency_s_median", "latency_s_p95"),
    "baseline_infer": ("latency_s_median", "latency_s_p95"),
    "train": ("samples_per_s", "step_s_median"),
    "baseline_train": ("samples_per_s", "step_s_median"),
}
_OPTIONAL_NUMBERS = (
    "peak_gflops",
    "baseline_peak_gflops",
    "infer_gflop_per_frame",
    "train_gflop_per_step",
    "infer_speedup",
    "train_speedup",
    "infer_floor_s",
)
_ENGINE_NUMBERS = ("latency_s_median", "latency_s_p95", "speedup")
_ENGINE_OPTIONAL = ("latency_over_floor", "export_s")


def _fmt(value: float | None, digits: int = 3) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def _ratio(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}×"


def _where(result: Mapping[str, Any]) -> str:
    machine = result["machine"]
    return machine.get("gpu") or f"{machine['cpu']}, {machine['torch_threads']} threads"


def settings_line(result: Mapping[str, Any]) -> str:
    """What was measured, in a line: backbone, fusion, resolution, training batch and device."""
    s = result["settings"]
    return (
        f"{s['backbone']} · fusion={s['fusion']} · {s['height']}×{s['width']} · "
        f"train batch {s['batch_size']} · {s['device']} ({_where(result)})"
    )


def run_label(settings: Mapping[str, Any]) -> str:
    """The speed settings of a run as the tables name them: ``bf16-mixed, channels-last, eager``."""
    label = f"{settings['precision']}{', channels-last' if settings['channels_last'] else ''}"
    return label + (
        f", compiled ({settings['compile_mode']})" if settings["compile"] else ", eager"
    )


def speed_rows(result: Mapping[str, Any]) -> list[list[str]]:
    """The speed table's rows (:data:`SPEED_HEADER`) of one record: its settings, then with a
    baseline the eager fp32 row and the speed-ups."""
    infer_flops = result.get("infer_gflop_per_frame")
    train_flops = result.get("train_gflop_per_step")

    def row(name: str, infer: Mapping | None, train: Mapping | None, peak: float | None) -> list:
        latency = infer["latency_s_median"] if infer else None
        gflops = infer_flops / latency if infer_flops and latency else None
        share = f"{100 * gflops / peak:.0f} %" if gflops and peak else "–"
        train_gflops = train_flops / train["step_s_median"] if train and train_flops else None
        memory = max(
            (d["peak_memory_mb"] for d in (infer, train) if d and d.get("peak_memory_mb")),
            default=None,
        )
        return [
            name,
            _fmt(latency),
            _fmt(infer and infer["latency_s_p95"]),
            _fmt(gflops, 1),
            share,
            _fmt(train and train["samples_per_s"], 2),
            _fmt(train_gflops, 1),
            _fmt(memory, 0),
        ]

    rows = [
        row(
            run_label(result["settings"]),
            result.get("infer"),
            result.get("train"),
            result.get("peak_gflops"),
        )
    ]
    if result.get("baseline_infer") or result.get("baseline_train"):
        rows.append(
            row(
                BASELINE_RUN,
                result.get("baseline_infer"),
                result.get("baseline_train"),
                result.get("baseline_peak_gflops"),
            )
        )
        speedups = [_ratio(result.get("infer_speedup")), _ratio(result.get("train_speedup"))]
        rows.append(["speed-up", speedups[0], "", "", "", speedups[1], "", ""])
    return rows


def speed_notes(result: Mapping[str, Any]) -> str:
    """The line under the speed table: matrix-product peaks, FLOPs per frame and per step, and
    the data stage's samples/s, where they were measured."""
    s, notes = result["settings"], []
    if result.get("peak_gflops"):
        notes.append(f"matrix-product peak {result['peak_gflops']:.0f} GFLOP/s ({s['precision']})")
    if result.get("baseline_peak_gflops"):
        notes.append(f"{result['baseline_peak_gflops']:.0f} GFLOP/s (fp32)")
    infer = result.get("infer") or {}
    if infer.get("prior_latency_s_median") is not None:
        notes.append(
            f"of the batch-1 latency, the prior alone {_fmt(infer['prior_latency_s_median'])} s "
            f"and the network on top of it {_fmt(infer['head_latency_s_median'])} s"
        )
    if result.get("infer_gflop_per_frame"):
        notes.append(f"{result['infer_gflop_per_frame']:.1f} GFLOP per frame")
    if result.get("train_gflop_per_step"):
        notes.append(f"{result['train_gflop_per_step']:.1f} GFLOP per training step")
    if "data" in result:
        d = result["data"]
        notes.append(
            f"data ({d['dataset']} {d['split']}): {d['samples_per_s_per_worker']:.1f} samples/s "
            f"per loader worker ({d['workers']}), to floats + augmentation on "
            f"{d['augment_device']} {d['augment_samples_per_s']:.1f} samples/s, together "
            f"{d['pipeline_samples_per_s']:.1f} samples/s"
        )
    return "; ".join(notes)


def engine_rows(result: Mapping[str, Any]) -> list[list[str]]:
    """The engines table's rows (:data:`ENGINE_HEADER`) of one record, PyTorch first."""
    return [
        [
            name,
            e["computes"],
            f"{_fmt(e['latency_s_median'])} s ({_fmt(e['latency_s_p95'])})",
            _ratio(e.get("latency_over_floor")),
            _ratio(e["speedup"]),
            _fmt(e.get("export_s"), 0),
        ]
        for name, e in (result.get("engines") or {}).items()
    ]


def floor_note(result: Mapping[str, Any]) -> str:
    """The line under the engines table: what the FLOP floor is, or that it was not measured."""
    floor_s = result.get("infer_floor_s")
    if not floor_s:
        return "no FLOP floor: the peak stage did not run (--only peak,infer)"
    return (
        f"FLOP floor {floor_s:.3f} s: {result['infer_gflop_per_frame']:.1f} GFLOP per frame at "
        f"the {result['settings']['precision']} matrix-product peak, "
        f"{result['peak_gflops']:.0f} GFLOP/s (latency / floor 1.00× = at the floor)"
    )


PREPARE_HEADER_START = ("fill", "s per frame", "frames/s per worker", "against spsolve")


def prepare_table(result: Mapping[str, Any]) -> tuple[list[str], list[list[str]], str]:
    """The ``prepare`` stage as a table: per fill method its seconds per frame, frames per
    second per worker, and the hours of each named split on the measured number of cores;
    with the line saying what frame was filled."""
    stage = result["prepare"]
    splits = list(next(iter(stage["methods"].values()))["hours"]) if stage["methods"] else []
    header = [*PREPARE_HEADER_START, *(f"h, {split}" for split in splits)]
    rows = [
        [
            method,
            _fmt(m["s_per_frame"], 3),
            _fmt(m["frames_per_s_per_worker"], 2),
            _against_spsolve(m.get("spsolve")),
            *(_fmt(m["hours"][split], 2) for split in splits),
        ]
        for method, m in stage["methods"].items()
    ]
    source = stage.get("source", "generated")
    what = (
        f"a generated {stage['height']}×{stage['width']} lidar frame"
        if source == "generated"
        else f"the median of {stage['frames']} frames of {source} "
        f"({stage['height']}×{stage['width']} the first)"
    )
    note = (
        f"{what} ({100 * stage['measured_fraction']:.1f} % of pixels measured), one worker per "
        "core; "
        f"hours on {stage['cores']} cores (prepare.workers={stage['cores']})"
    )
    return header, rows, note


def _against_spsolve(reference: Mapping[str, Any] | None) -> str:
    """The colorization row's comparison with SciPy's spsolve on the first frame: the speed-up,
    spsolve's seconds and the largest difference ("" where it was not measured)."""
    if not reference:
        return ""
    return (
        f"{_fmt(reference['speedup'], 1)}× ({reference['s_per_frame']:.2f} s), "
        f"{1000 * reference['max_difference_m']:.2g} mm"
    )


def spsolve_note(result: Mapping[str, Any]) -> str | None:
    """The line under the ``prepare`` table: the colorization solver against SciPy's default
    ``spsolve`` of the same system on the first frame, on the machine that ran it (None in
    records made before it was measured)."""
    reference = (result["prepare"]["methods"].get("colorization") or {}).get("spsolve")
    if not reference:
        return None
    return (
        f"colorization: {reference['speedup']:.1f}× SciPy's spsolve of the same system on this "
        f"machine ({reference['s_per_frame']:.2f} s a frame), largest difference "
        f"{1000 * reference['max_difference_m']:.3g} mm (first frame)"
    )


# --- Reading records back ----------------------------------------------------------------------


def _problem(path: Path, key: str, value: Any, expected: str) -> ValueError:
    shown = json.dumps(value)[:40] if not isinstance(value, dict | list) else type(value).__name__
    return ValueError(f"{path}: {key}={shown}: expected {expected}")


def _check_number(path: Path, key: str, value: Any, optional: bool = True) -> None:
    if value is None and optional:
        return
    if not (is_number(value) and math.isfinite(value)):
        raise _problem(path, key, value, "a finite number" + (" or null" if optional else ""))


def _section(path: Path, data: Mapping[str, Any], key: str) -> Mapping[str, Any]:
    value = data.get(key)
    if not isinstance(value, dict):
        raise _problem(path, key, value, "an object")
    return value


def check_bench_record(data: Any, path: str | os.PathLike) -> dict[str, Any]:
    """``data`` if it holds what the tables read, with the types they need.

    Raises:
        ValueError: naming ``path``, the key and what it should hold.
    """
    path = Path(path)
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a bench record (the object bench --json writes)")
    settings = _section(path, data, "settings")
    for key, kind in _SETTINGS.items():
        value = settings.get(key)
        ok = is_int(value) if kind is int else isinstance(value, kind)
        if not ok:
            raise _problem(path, f"settings.{key}", value, f"a {kind.__name__}")
    if settings["compile"] and not isinstance(settings.get("compile_mode"), str):
        raise _problem(path, "settings.compile_mode", settings.get("compile_mode"), "a str")
    machine = _section(path, data, "machine")
    if not isinstance(machine.get("gpu"), str):
        if not isinstance(machine.get("cpu"), str) or not is_int(machine.get("torch_threads")):
            raise ValueError(f"{path}: machine: expected a gpu name, or cpu and torch_threads")
    for stage, keys in _TIMINGS.items():
        if data.get(stage) is None:
            continue
        timings = _section(path, data, stage)
        for key in keys:
            _check_number(path, f"{stage}.{key}", timings.get(key), optional=False)
        _check_number(path, f"{stage}.peak_memory_mb", timings.get("peak_memory_mb"))
    for key in _OPTIONAL_NUMBERS:
        _check_number(path, key, data.get(key))
    engines = {} if data.get("engines") is None else data["engines"]
    if not isinstance(engines, dict):
        raise _problem(path, "engines", engines, "an object of engines")
    for name, entry in engines.items():
        if not isinstance(entry, dict) or not isinstance(entry.get("computes"), str):
            raise _problem(path, f"engines.{name}", entry, "an object with 'computes'")
        for key in _ENGINE_NUMBERS:
            _check_number(path, f"engines.{name}.{key}", entry.get(key), optional=False)
        for key in _ENGINE_OPTIONAL:
            _check_number(path, f"engines.{name}.{key}", entry.get(key))
    if data.get("infer_floor_s") and not (
        data.get("infer_gflop_per_frame") and data.get("peak_gflops")
    ):
        raise ValueError(f"{path}: infer_floor_s without infer_gflop_per_frame and peak_gflops")
    return data


def read_bench_record(path: str | os.PathLike) -> dict[str, Any]:
    """The bench record in ``path``, checked (:func:`check_bench_record`).

    Raises:
        OSError: the file cannot be read.
        ValueError: it is not JSON or not a bench record; the message names the file.
    """
    path = Path(path)
    return check_bench_record(read_json(path, "a bench record"), path)


def load_bench_records(root: str | os.PathLike) -> list[NamedRecord]:
    """Every ``bench.json`` below ``root``, sorted by path, as (its folder relative to
    ``root``, the record); a record directly in ``root`` is named after ``root``.

    Raises:
        FileNotFoundError: ``root`` is not a directory.
        ValueError: a file is not a bench record (:func:`read_bench_record`).
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such directory")
    records = []
    for path in sorted(root.rglob(BENCH_FILE)):
        name = path.parent.relative_to(root).as_posix()
        records.append((root.name if name == "." else name, read_bench_record(path)))
    return records
