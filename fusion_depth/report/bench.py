"""Tables and a figure of bench records (``report <folder> --bench speed|engines|prepare``): every
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
    prepare_table,
    settings_line,
    speed_rows,
)
from fusion_depth.utils.tables import format_table

BENCH_TABLES = ("speed", "engines", "prepare")


def build_bench_table(records: Sequence[NamedRecord], table: str, fmt: str = "markdown") -> str:
    """One ``table`` (``speed``, ``engines`` or ``prepare``) of every record: each record's rows,
    the first led by its name and what it measured
    (:func:`~fusion_depth.runner.bench_record.settings_line`; for ``prepare``, the frames filled
    and the cores of the estimate).

    Raises:
        ValueError: ``table`` is not one of :data:`BENCH_TABLES`, or no record has the table
            (``engines``: no record was run with ``--engines``; ``prepare``: none with
            ``--only prepare``).
    """
    if table not in BENCH_TABLES:
        raise ValueError(f"--bench {table}: expected one of {', '.join(BENCH_TABLES)}")
    if table == "prepare":
        return _prepare_table(records, fmt)
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


def _prepare_table(records: Sequence[NamedRecord], fmt: str) -> str:
    """The ``prepare`` table of every record run with ``--only prepare``: a row per fill method,
    the first led by the record's name and the frames it filled. Records must estimate the same
    named splits (one header)."""
    header: list[str] | None = None
    rows = []
    for name, result in records:
        if "prepare" not in result:
            continue
        own_header, own_rows, note = prepare_table(result)
        if header is not None and own_header != header:
            raise ValueError(
                f"--bench prepare: {name} estimates other splits than the first record"
            )
        header = own_header
        rows += [[name, note, *row] if n == 0 else ["", "", *row] for n, row in enumerate(own_rows)]
    if header is None:
        raise ValueError("--bench prepare: no record holds it (run bench with --only prepare)")
    return format_table(["record", "measured", *header], rows, fmt)
