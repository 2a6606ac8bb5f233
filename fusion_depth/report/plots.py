"""Bar charts of a sweep (``report --plot``): Matplotlib, imported only when a plot is drawn."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fusion_depth.report.compare import Comparison, comparison_identity_columns
from fusion_depth.report.groups import (
    ALL,
    by_column_stats,
    higher_is_better,
    identity_cells,
    identity_columns,
    key_label,
    mean_std,
    metric_label,
    run_metric,
)
from fusion_depth.utils.atomic import write_atomic

if TYPE_CHECKING:  # Matplotlib is imported by the plots only: a table should print at once.
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

# --- Plots: --plot out.png --------------------------------------------------------------------

PLOT_METRICS = ("rmse", "abs_rel", "delta1")


def _save_figure_atomic(fig: Figure, out: str | os.PathLike) -> Path:
    """Save next to ``out`` then rename, so a viewer or sync never picks up half a PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    out = Path(out)
    canvas = FigureCanvasAgg(fig)
    formats = canvas.get_supported_filetypes()
    fmt = out.suffix.lstrip(".").lower()
    if fmt not in formats:
        raise ValueError(
            f"--plot {out}: expected a file name ending in one of "
            f"{', '.join('.' + f for f in sorted(formats))}"
        )
    write_atomic(
        out,
        lambda tmp: canvas.print_figure(tmp, format=fmt, dpi=150, bbox_inches="tight"),
        suffix=f".{fmt}",
    )
    return out


def _grouped_bars(
    ax: Axes,
    categories: Sequence[str],
    series: Sequence[tuple[str, Sequence[float], Any]],
) -> None:
    """Bars of each series side by side over each category; ``yerr`` None draws no error bar."""
    width = 0.8 / max(len(series), 1)
    x = np.arange(len(categories))
    for k, (name, heights, yerr) in enumerate(series):
        offset = (k - (len(series) - 1) / 2) * width
        ax.bar(x + offset, heights, width, yerr=yerr, capsize=3, label=name)
    ax.set_xticks(x, categories, rotation=30 if len(categories) > 4 else 0)
    ax.grid(axis="y", alpha=0.3)


def _std_errors(cells: Sequence[tuple[float, float | None] | None]) -> np.ndarray | None:
    stds = [c[1] if c is not None and c[1] is not None else np.nan for c in cells]
    return None if np.isnan(stds).all() else np.nan_to_num(stds)


def _direction(metric: str) -> str:
    return "higher is better" if higher_is_better(metric) else "lower is better"


def plot_groups(
    groups: Sequence[dict], out: str | os.PathLike, metrics: Sequence[str] = PLOT_METRICS
) -> Path:
    """One subplot per metric: bars per fusion mode over each loss, error bars = seed std."""
    from matplotlib.figure import Figure

    if not groups:
        raise ValueError("no runs to plot")
    extra = [key for _, key in identity_columns(groups)]

    def category(g: dict) -> str:
        return " / ".join([*(key_label(k, g[k]) for k in extra), key_label("loss", g["loss"])])

    categories = list(dict.fromkeys(category(g) for g in groups))
    fusions = list(dict.fromkeys(g["fusion"] for g in groups))
    fig = Figure(figsize=(1.2 + 3.6 * len(metrics), 3.6), layout="constrained")
    for n, metric in enumerate(metrics):
        ax = fig.add_subplot(1, len(metrics), n + 1)
        series = []
        for fusion in fusions:
            cells: list[tuple[float, float | None] | None] = []
            for cat in categories:
                g = next((g for g in groups if g["fusion"] == fusion and category(g) == cat), None)
                if g is None:
                    cells.append(None)
                else:
                    values = [run_metric(r, None, ALL, metric) for r in g["runs"]]
                    cells.append(mean_std(values))
            heights = [np.nan if c is None else c[0] for c in cells]
            series.append((key_label("fusion", fusion), heights, _std_errors(cells)))
        _grouped_bars(ax, categories, series)
        ax.set_title(f"{metric_label(metric)} ({_direction(metric)})")
        if n == 0:
            ax.legend(fontsize="small")
    return _save_figure_atomic(fig, out)


def plot_by(
    groups: Sequence[dict],
    out: str | os.PathLike,
    by: str,
    metric: str = "rmse",
    first: Sequence[str] = (),
) -> Path:
    """``metric`` per condition (or bin; ``first`` first): one bar per group, error bars = seed
    std."""
    from matplotlib.figure import Figure

    columns, stats = by_column_stats(groups, by, metric, first)
    extra = identity_columns(groups)
    fig = Figure(figsize=(min(16.0, 2.5 + 0.4 * len(columns) * max(1, len(groups))), 3.8))
    ax = fig.add_subplot()
    series = []
    for g, cells in zip(groups, stats, strict=True):
        row = [cells[c] for c in columns]
        heights = [np.nan if c is None else c[0] for c in row]
        series.append((" / ".join(identity_cells(g, extra)), heights, _std_errors(row)))
    _grouped_bars(ax, columns, series)
    ax.set_title(f"{metric_label(metric)} by {by} ({_direction(metric)})")
    ax.legend(fontsize="small")
    fig.set_layout_engine("constrained")
    return _save_figure_atomic(fig, out)


def plot_comparisons(comparisons: Sequence[Comparison], out: str | os.PathLike) -> Path:
    """Mean differences against the baseline with their bootstrap intervals as error bars."""
    from matplotlib.figure import Figure

    if not comparisons:
        raise ValueError("no comparisons to plot")
    columns = list(dict.fromkeys(col for c in comparisons for col in c.results))
    extra = comparison_identity_columns(comparisons)
    fig = Figure(figsize=(min(16.0, 2.5 + 0.4 * len(columns) * max(1, len(comparisons))), 3.8))
    ax = fig.add_subplot()
    series = []
    for c in comparisons:
        results = [c.results.get(col) for col in columns]
        heights = [np.nan if r is None else r.mean for r in results]
        low = [0.0 if r is None else r.mean - r.low for r in results]
        high = [0.0 if r is None else r.high - r.mean for r in results]
        name = " / ".join(identity_cells(c.group, extra))
        name += f" vs {c.baseline_label}"
        series.append((name, heights, np.array([low, high])))
    _grouped_bars(ax, columns, series)
    ax.axhline(0.0, color="black", linewidth=0.8)
    c0 = comparisons[0]
    ax.set_title(
        f"Δ{metric_label(c0.metric)} vs baseline, {100 * c0.level:g}% CI ({_direction(c0.metric)})"
    )
    ax.legend(fontsize="small")
    fig.set_layout_engine("constrained")
    return _save_figure_atomic(fig, out)
