"""Bar charts of a sweep (``report --plot``): Matplotlib, imported only when a plot is drawn.

A figure carries what it shows as text: its metadata (``Description`` in SVG and PNG,
``Subject`` in PDF) holds the command that drew it and the plotted values as JSON
(:func:`figure_description`). A docs page's figure can so be checked against the run records
it was drawn from on any Matplotlib version; on the same version the bytes repeat too (no date
is written, and SVG ids are salted with a constant).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fusion_depth.report.compare import Comparison, comparison_identity_columns
from fusion_depth.report.groups import (
    ALL,
    Preset,
    by_column_stats,
    higher_is_better,
    identity_cells,
    identity_columns,
    key_label,
    mean_std,
    run_metric,
)
from fusion_depth.runner.bench_record import NamedRecord, run_label
from fusion_depth.utils.atomic import write_atomic

if TYPE_CHECKING:  # Matplotlib is imported by the plots only: a table should print at once.
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

# --- Plots: --plot out.png --------------------------------------------------------------------

PLOT_METRICS = ("rmse", "abs_rel", "delta1")

# The metadata key that holds figure_description(), per format (PDF has no Description).
_DESCRIPTION_KEY = {"svg": "Description", "png": "Description", "pdf": "Subject"}
# No creation date, so that drawing the same values again writes the same bytes.
_NO_DATE = {"svg": {"Date": None}, "pdf": {"CreationDate": None}}


def _value(x: Any) -> float | None:
    """A plotted number as the description stores it: 6 significant digits, None for a gap."""
    x = float(x)
    return None if np.isnan(x) else float(f"{x:.6g}")


def figure_description(command: str | None, panels: Sequence[dict]) -> str:
    """The text a figure carries in its metadata: ``command`` (None: not drawn by the CLI) and
    each panel's title, categories and series (name, bar heights, error bars), as JSON."""
    return json.dumps({"command": command, "panels": list(panels)}, ensure_ascii=False)


def read_figure_description(path: str | os.PathLike) -> dict:
    """The :func:`figure_description` an SVG or PNG made by ``report --plot`` carries, parsed.

    Raises:
        ValueError: ``path`` is not an SVG or PNG, or carries no such description.
    """
    path = Path(path)
    text = None
    if path.suffix.lower() == ".svg":
        from xml.etree import ElementTree

        node = ElementTree.parse(path).find(".//{http://purl.org/dc/elements/1.1/}description")
        text = None if node is None else node.text
    elif path.suffix.lower() == ".png":
        from PIL import Image

        with Image.open(path) as image:
            text = image.info.get("Description")
    else:
        raise ValueError(f"{path}: expected an .svg or .png figure")
    try:
        description = json.loads(text or "")
    except json.JSONDecodeError:
        description = None
    if not isinstance(description, dict) or "panels" not in description:
        raise ValueError(f"{path}: no description written by report --plot in its metadata")
    return description


def _save_figure_atomic(
    fig: Figure, out: str | os.PathLike, panels: Sequence[dict], command: str | None
) -> Path:
    """Save next to ``out`` then rename, so a viewer or sync never picks up half a PNG. The
    figure's metadata gets :func:`figure_description` where the format has a field for it."""
    from matplotlib import rc_context
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
    metadata = dict(_NO_DATE.get(fmt, {}))
    if fmt in _DESCRIPTION_KEY:
        metadata[_DESCRIPTION_KEY[fmt]] = figure_description(command, panels)

    def write(tmp: Path) -> None:
        with rc_context({"svg.hashsalt": "fusion-depth"}):
            canvas.print_figure(
                tmp, format=fmt, dpi=150, bbox_inches="tight", metadata=metadata or None
            )

    write_atomic(out, write, suffix=f".{fmt}")
    return out


# Bars whose positive heights span more than this factor get a log axis (a ResNet-10-T beside a
# DenseNet-169: the small bars would otherwise vanish).
LOG_AXIS_SPAN = 20.0
# Category labels are wrapped to lines of this many characters, so that neighbours never overlap.
LABEL_WIDTH = 18


def axis_label(metric: str, preset: Preset) -> str:
    """The y-axis label of ``metric`` with its unit: ``RMSE (m)``, ``ARD (fraction of depth)``,
    ``δ1 (share of pixels)``, ``iRMSE (1/km)``."""
    label = preset.label(metric)
    if "(" in label:
        return label
    if metric in ("rmse", "mae", "sq_rel"):
        return f"{label} ({preset.units})"
    if metric.startswith("delta"):
        return f"{label} (share of pixels)"
    if metric == "abs_rel":
        return f"{label} (fraction of depth)"
    return label


def _wrapped(label: str) -> str:
    import textwrap

    lines = textwrap.wrap(label, LABEL_WIDTH, break_on_hyphens=False, break_long_words=False)
    return "\n".join(lines) or label


def _grouped_bars(
    ax: Axes,
    title: str,
    categories: Sequence[str],
    series: Sequence[tuple[str, Sequence[float], Any]],
    ylabel: str,
    xlabel: str | None = None,
    legend: bool = True,
    log_axis: bool = True,
) -> dict:
    """Bars of each series side by side over each category; ``yerr`` None draws no error bar.
    The y axis is labelled ``ylabel`` (with its unit) and, with ``log_axis``, turns logarithmic
    where every bar and error bar is positive and the bars span more than
    :data:`LOG_AXIS_SPAN`. With ``legend``, a legend of several series sits beside the axes
    (below them when its labels are long), never over the bars. Returns the panel as
    :func:`figure_description` stores it."""
    width = 0.8 / max(len(series), 1)
    x = np.arange(len(categories))
    for k, (name, heights, yerr) in enumerate(series):
        offset = (k - (len(series) - 1) / 2) * width
        ax.bar(x + offset, heights, width, yerr=yerr, capsize=3, label=name)
    ax.set_xticks(x, [_wrapped(c) for c in categories], fontsize="small")
    heights = np.asarray([h for _, hs, _ in series for h in hs], dtype=float)
    # Where each bar's error bar reaches down to (a (2, n) yerr: its first row).
    lowest = np.concatenate(
        [
            np.asarray(hs, dtype=float)
            - (0.0 if yerr is None else np.atleast_2d(np.asarray(yerr, dtype=float))[0])
            for _, hs, yerr in series
        ]
    )
    shown = np.isfinite(heights)
    positive = heights[shown & (heights > 0)]
    log = (
        log_axis
        and len(positive) == shown.sum() > 1
        and bool((lowest[shown] > 0).all())
        and positive.max() / positive.min() > LOG_AXIS_SPAN
    )
    if log:
        ax.set_yscale("log")
    ax.grid(axis="y", alpha=0.3, which="both" if log else "major")
    ax.set_title(title)
    ax.set_ylabel(ylabel + (", log scale" if log else ""))
    if xlabel:
        ax.set_xlabel(xlabel)
    if legend and len(series) > 1:
        if max(len(name) for name, _, _ in series) > 30:
            ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(0.0, -0.22))
        else:
            ax.legend(
                fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0
            )
    return {
        "title": title,
        "ylabel": ylabel,
        "log_scale": bool(log),
        "categories": list(categories),
        "series": [
            {
                "name": name,
                "heights": [_value(h) for h in heights],
                "errors": None if yerr is None else np.vectorize(_value)(yerr).tolist(),
            }
            for name, heights, yerr in series
        ],
    }


def _std_errors(cells: Sequence[tuple[float, float | None] | None]) -> np.ndarray | None:
    stds = [c[1] if c is not None and c[1] is not None else np.nan for c in cells]
    return None if np.isnan(stds).all() else np.nan_to_num(stds)


def _direction(metric: str) -> str:
    return "higher is better" if higher_is_better(metric) else "lower is better"


def plot_groups(
    groups: Sequence[dict],
    out: str | os.PathLike,
    metrics: Sequence[str] = PLOT_METRICS,
    command: str | None = None,
    preset: Preset | None = None,
) -> Path:
    """One subplot per metric: bars per fusion mode over each loss, error bars = seed std.
    ``command``: the command line the figure's metadata names (:func:`figure_description`);
    ``preset``: the units of the bars (:func:`~fusion_depth.report.groups.runs_preset`)."""
    preset = preset or Preset()
    from matplotlib.figure import Figure

    if not groups:
        raise ValueError("no runs to plot")
    extra = [key for _, key in identity_columns(groups)]

    def category(g: dict) -> str:
        return " / ".join([*(key_label(k, g[k]) for k in extra), key_label("loss", g["loss"])])

    categories = list(dict.fromkeys(category(g) for g in groups))
    fusions = list(dict.fromkeys(g["fusion"] for g in groups))
    fig = Figure(figsize=(1.2 + 3.6 * len(metrics), 3.6), layout="constrained")
    panels = []
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
                    cells.append(preset.cell(metric, mean_std(values)))
            heights = [np.nan if c is None else c[0] for c in cells]
            series.append((key_label("fusion", fusion), heights, _std_errors(cells)))
        title = f"{preset.label(metric)} ({_direction(metric)})"
        panels.append(
            _grouped_bars(
                ax,
                title,
                categories,
                series,
                axis_label(metric, preset),
                " / ".join([*extra, "loss"]),
                legend=n == len(metrics) - 1,  # one legend, right of the last panel
            )
        )
    return _save_figure_atomic(fig, out, panels, command)


def _series_name(cells: Sequence[str]) -> str:
    """A legend entry: a group's identity cells (its setting short,
    :func:`~fusion_depth.report.groups.short_settings`), the empty ones and "–" left out."""
    return " / ".join(cell for cell in cells if cell and cell != "–")


def plot_by(
    groups: Sequence[dict],
    out: str | os.PathLike,
    by: str,
    metric: str = "rmse",
    first: Sequence[str] = (),
    command: str | None = None,
    preset: Preset | None = None,
) -> Path:
    """``metric`` per condition (or bin; ``first`` first): one bar per group, error bars = seed
    std. ``command``, ``preset``: as :func:`plot_groups`'s."""
    preset = preset or Preset()
    from matplotlib.figure import Figure

    columns, stats = by_column_stats(groups, by, metric, first)
    extra = identity_columns(groups)
    fig = Figure(figsize=(min(16.0, 2.5 + 0.4 * len(columns) * max(1, len(groups))), 3.8))
    ax = fig.add_subplot()
    series = []
    for g, cells in zip(groups, stats, strict=True):
        row = [preset.cell(metric, cells[c]) for c in columns]
        heights = [np.nan if c is None else c[0] for c in row]
        series.append((_series_name(identity_cells(g, extra)), heights, _std_errors(row)))
    title = f"{preset.label(metric)} by {by} ({_direction(metric)})"
    xlabel = {"distance": "ground-truth distance (m)", "cap": "depth cap (m)"}.get(by, by)
    panel = _grouped_bars(ax, title, columns, series, axis_label(metric, preset), xlabel)
    fig.set_layout_engine("constrained")
    return _save_figure_atomic(fig, out, [panel], command)


def plot_comparisons(
    comparisons: Sequence[Comparison],
    out: str | os.PathLike,
    command: str | None = None,
    preset: Preset | None = None,
) -> Path:
    """Mean differences against the baseline with their bootstrap intervals as error bars.
    ``command``, ``preset``: as :func:`plot_groups`'s."""
    preset = preset or Preset()
    from matplotlib.figure import Figure

    if not comparisons:
        raise ValueError("no comparisons to plot")
    columns = list(dict.fromkeys(col for c in comparisons for col in c.results))
    extra = comparison_identity_columns(comparisons)
    # One baseline for all (--by model): the title names it, not each legend entry.
    one_baseline = len({id(c.baseline) for c in comparisons}) == 1
    fig = Figure(figsize=(min(16.0, 2.5 + 0.4 * len(columns) * max(1, len(comparisons))), 3.8))
    ax = fig.add_subplot()
    series = []
    for c in comparisons:
        results = [c.results.get(col) for col in columns]
        m = c.metric
        heights = [np.nan if r is None else preset.value(m, r.mean) for r in results]
        low = [0.0 if r is None else preset.value(m, r.mean - r.low) for r in results]
        high = [0.0 if r is None else preset.value(m, r.high - r.mean) for r in results]
        name = _series_name(identity_cells(c.group, extra))
        if not one_baseline:
            name += f" vs {c.baseline_label}"
        series.append((name, heights, np.array([low, high])))
    c0 = comparisons[0]
    # Its shortest name: the compared keys' values alone.
    against = min((c.baseline_label for c in comparisons), key=len) if one_baseline else "baseline"
    title = (
        f"Δ{preset.label(c0.metric)} vs {against}, {100 * c0.level:g}% CI ({_direction(c0.metric)})"
    )
    ylabel = f"Δ{axis_label(c0.metric, preset)}, other − baseline"
    # A difference is read against 0: a linear axis always.
    panel = _grouped_bars(ax, title, columns, series, ylabel, log_axis=False)
    ax.axhline(0.0, color="black", linewidth=0.8)
    fig.set_layout_engine("constrained")
    return _save_figure_atomic(fig, out, [panel], command)


# --- Bench records: report --bench speed|engines --plot ----------------------------------------


def plot_engine_latency(
    records: Sequence[NamedRecord], out: str | os.PathLike, command: str | None = None
) -> Path:
    """Batch-1 latency per engine (bars: the median; whiskers: up to the p95), a bar per
    record, in seconds; the figure's metadata names ``command`` (:func:`figure_description`).

    Raises:
        ValueError: no record holds engine timings.
    """
    from matplotlib.figure import Figure

    timed = [(name, result["engines"]) for name, result in records if result.get("engines")]
    if not timed:
        raise ValueError("--plot: no record holds engine timings (run bench with --engines)")
    engines = list(dict.fromkeys(engine for _, timings in timed for engine in timings))
    fig = Figure(figsize=(min(16.0, 2.5 + 0.9 * len(engines) * len(timed)), 3.8))
    ax = fig.add_subplot()
    series = []
    for name, timings in timed:
        cells = [timings.get(engine) for engine in engines]
        medians = [np.nan if c is None else c["latency_s_median"] for c in cells]
        above = [0.0 if c is None else c["latency_s_p95"] - c["latency_s_median"] for c in cells]
        series.append((name, medians, np.array([np.zeros(len(cells)), np.maximum(above, 0.0)])))
    title = "batch-1 latency, median to p95 (lower is better)"
    panel = _grouped_bars(ax, title, engines, series, "latency per frame (s)", "engine")
    fig.set_layout_engine("constrained")
    return _save_figure_atomic(fig, out, [panel], command)


def plot_speed(
    records: Sequence[NamedRecord], out: str | os.PathLike, command: str | None = None
) -> Path:
    """Batch-1 latency (s) and training samples/s of each record's run and, where measured, its
    eager fp32 baseline; the figure's metadata names ``command``.

    Raises:
        ValueError: no record timed inference or training.
    """
    from matplotlib.figure import Figure

    categories = [f"{name}: {run_label(result['settings'])}" for name, result in records]
    panels_spec = [
        ("batch-1 latency, median (lower is better)", "latency per frame (s)", "infer",
         "latency_s_median"),
        ("training throughput (higher is better)", "training samples/s", "train",
         "samples_per_s"),
    ]  # fmt: skip
    fig = Figure(figsize=(min(16.0, 3.0 + 1.2 * len(records)) * 2, 3.8), layout="constrained")
    panels = []
    for n, (title, ylabel, stage, key) in enumerate(panels_spec):
        ax = fig.add_subplot(1, 2, n + 1)
        series = []
        for label, prefix in (("run", ""), ("eager fp32 baseline", "baseline_")):
            heights = [(result.get(prefix + stage) or {}).get(key, np.nan) for _, result in records]
            if not np.isnan(np.asarray(heights, dtype=float)).all():
                series.append((label, heights, None))
        if not series:
            continue
        panels.append(
            _grouped_bars(ax, title, categories, series, ylabel, legend=n == len(panels_spec) - 1)
        )
    if not panels:
        raise ValueError("--plot: no record timed inference or training")
    return _save_figure_atomic(fig, out, panels, command)
