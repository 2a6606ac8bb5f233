"""``report --by model``: per model, one metric per condition (mean ± std over seeds) and the paired
differences between models on the same test images.

It is the ``--by condition`` table with a Model column (models in the model table's order,
named by their labels; conditions in :data:`~fusion_depth.report.groups.HARD_CONDITIONS` first),
followed by the ``--compare`` table of every group against its baseline: by default
``model=densedepth`` (:data:`~fusion_depth.models.DEFAULT_MODEL`; the sweep's first model when
it has none), i.e. each other model (with its own encoder and loss) against DenseDepth with the
same fusion mode and settings; ``--compare`` picks another baseline
(``model=densedepth,fusion=rgb``: every model and fusion mode against DenseDepth RGB). As CSV
(and in W&B) the two are one table: a row per group and baseline, with the group's mean and std
and its differences to that baseline (empty for the baselines themselves).
"""

from __future__ import annotations

from collections.abc import Sequence

from fusion_depth.models._registry import DEFAULT_MODEL
from fusion_depth.report.compare import Comparison, build_comparison_table, csv_cells
from fusion_depth.report.groups import (
    HARD_CONDITIONS,
    Preset,
    build_by_table,
    by_column_stats,
    identity_cells,
    identity_columns,
)
from fusion_depth.utils.tables import format_table

BY_MODEL = "model"  # the --by choice
SECTION = "condition"  # the breakdown whose columns --by model shows
_SHOW = ("model",)  # the identity column --by model always shows


def default_baseline(groups: Sequence[dict]) -> dict[str, str] | None:
    """The baseline of ``--by model`` without ``--compare``: ``{"model": "densedepth"}``, or
    the first model of the sweep (in the model table's order) when it has no DenseDepth runs;
    None when the runs hold a single model (nothing to compare)."""
    models = list(dict.fromkeys(g["model"] for g in groups))
    if len(models) < 2:
        return None
    return {"model": DEFAULT_MODEL if DEFAULT_MODEL in models else models[0]}


def build_model_report(
    groups: Sequence[dict],
    comparisons: Sequence[Comparison] | None,
    metric: str = "rmse",
    fmt: str = "markdown",
    first: Sequence[str] = HARD_CONDITIONS,
    preset: Preset | None = None,
) -> str:
    """The ``--by model`` report of grouped runs and their ``comparisons`` (None or empty: the
    first table only), in the units of ``preset`` (CSV: the recorded units).

    Markdown and LaTeX: the per-condition table (``metric`` mean ± std over seeds, a Model
    column, the columns in ``first`` first), a blank line, then the comparison table. CSV: one
    table (:func:`_merged_csv`), so that scripts and W&B read a single header.
    """
    if fmt == "csv":
        return _merged_csv(groups, comparisons or (), metric, first)
    parts = [build_by_table(groups, SECTION, metric, fmt, first=first, show=_SHOW, preset=preset)]
    if comparisons:
        parts.append(build_comparison_table(comparisons, fmt, show=_SHOW, preset=preset))
    return "\n\n".join(parts)


def _merged_csv(
    groups: Sequence[dict], comparisons: Sequence[Comparison], metric: str, first: Sequence[str]
) -> str:
    """One CSV row per group and baseline: identity, ``Seeds``, ``<metric>_<column>_mean|std``,
    then ``Baseline``, ``Pairing``, ``Images``, ``<metric>_<column>_diff|low|high|significant``
    and ``level`` (empty for a group compared with nothing, such as a baseline)."""
    if not groups:
        raise ValueError("no runs to tabulate")
    columns, stats = by_column_stats(groups, SECTION, metric, first)
    compared = list(dict.fromkeys(col for c in comparisons for col in c.results))
    extra = identity_columns(groups, _SHOW)
    header = [name for name, _ in extra] + ["Modality", "Loss", "Seeds"]
    header += [f"{metric}_{col}_{s}" for col in columns for s in ("mean", "std")]
    header += ["Baseline", "Pairing", "Images"]
    header += [
        f"{metric}_{col}_{part}"
        for col in compared
        for part in ("diff", "low", "high", "significant")
    ]
    header.append("level")
    rows = []
    for g, cells in zip(groups, stats, strict=True):
        row = identity_cells(g, extra, full=True) + [str(g["n"])]
        for col in columns:
            cell = cells[col]
            row += (
                ["", ""]
                if cell is None
                else [f"{cell[0]:.6g}", "" if cell[1] is None else f"{cell[1]:.6g}"]
            )
        against = [c for c in comparisons if c.group is g]
        if not against:
            rows.append(row + [""] * (3 + 4 * len(compared) + 1))
        for c in against:
            diffs = [c.baseline_label, c.pairing, str(c.num_images)]
            for col in compared:
                diffs += csv_cells(c.results.get(col))
            rows.append(row + diffs + [f"{c.level:g}"])
    return format_table(header, rows, "csv")
