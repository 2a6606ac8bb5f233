"""Tables and a figure of bench records (``report <folder> --bench speed|engines``): every
``bench.json`` that ``python -m fusion_depth.bench --json`` wrote below a folder, one table for
all of them, so a results page's speed and engine tables come from the records themselves.

The rows are the ones ``bench`` prints (:mod:`fusion_depth.runner.bench_record`), each led by
the record's folder and what it measured. The figures are
:func:`~fusion_depth.report.plots.plot_engine_latency` and
:func:`~fusion_depth.report.plots.plot_speed`.
"""

from __future__ import annotations

from collections.abc import Sequence

from fusion_depth.runner.bench_record import (
    ENGINE_HEADER,
    SPEED_HEADER,
    NamedRecord,
    engine_rows,
    settings_line,
    speed_rows,
)
from fusion_depth.utils.tables import format_table

BENCH_TABLES = ("speed", "engines")


def build_bench_table(records: Sequence[NamedRecord], table: str, fmt: str = "markdown") -> str:
    """One ``table`` (``speed`` or ``engines``) of every record: each record's rows, the first
    led by its name and what it measured (:func:`~fusion_depth.runner.bench_record.settings_line`).

    Raises:
        ValueError: ``table`` is not one of :data:`BENCH_TABLES`, or no record has the table
            (``engines``: no record was run with ``--engines``).
    """
    if table not in BENCH_TABLES:
        raise ValueError(f"--bench {table}: expected one of {', '.join(BENCH_TABLES)}")
    make = speed_rows if table == "speed" else engine_rows
    header = SPEED_HEADER if table == "speed" else ENGINE_HEADER
    rows = [
        [name, settings_line(result), *row] if n == 0 else ["", "", *row]
        for name, result in records
        for n, row in enumerate(make(result))
    ]
    if not rows:
        raise ValueError(
            f"--bench {table}: no record holds it (run bench with --engines for the engines table)"
        )
    return format_table(["record", "measured", *header], rows, fmt)
