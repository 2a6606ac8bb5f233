"""Runs grouped by their setting (seeds averaged, mean ± sample std) and the tables of a
sweep: the paper-style table, and one metric per condition, distance bin or depth cap.

A group is the runs that share dataset, sensor, model, backbone, loss, fusion mode, other
overrides (``setting``) and the engine that ran the network (``engine``: ``torch`` for
checkpoints and training runs, an exported model's engine such as ``openvino-int8``, recorded
by ``evaluate model_file=``); the tables name a model by its label in the model table
(:data:`fusion_depth.models.MODELS`), and runs recorded before models had names
(``model`` None) are :data:`~fusion_depth.models.DEFAULT_MODEL`'s.
"""

from __future__ import annotations

import statistics
from collections.abc import Collection, Sequence

from fusion_depth.losses.depth_loss import PIXEL_LOSS_LABELS
from fusion_depth.metrics.depth import HIGHER_IS_BETTER, METRIC_LABELS, METRIC_LATEX, TABLE_METRICS
from fusion_depth.models._registry import DEFAULT_MODEL, MODELS
from fusion_depth.models.fusion import FUSION_LABELS
from fusion_depth.runner.record import BREAKDOWNS, RunRecord
from fusion_depth.utils.tables import format_table

# (metric key, column header, LaTeX header, better) of the tables, from the metrics' own tables.
COLUMNS = tuple(
    (k, METRIC_LABELS[k], METRIC_LATEX[k], max if HIGHER_IS_BETTER[k] else min)
    for k in TABLE_METRICS
)
# Overrides that already have a column or are averaged over (``model=`` chooses the network,
# as does ``model.net.name=``; other ``model.*`` keys are settings).
_IDENTITY_KEYS = {"dataset", "model", "model.net.name", "backbone", "fusion", "loss", "seed"}
# The engine of runs that record none: training runs and checkpoints run by PyTorch.
DEFAULT_ENGINE = "torch"


def key_label(key: str, value: str) -> str:
    """How the tables name an identity value: a model by its label in the model table
    (:data:`fusion_depth.models.MODELS`), a fusion mode or pixel loss by the paper's name
    (RGB-Fusion, L1, ...); any other value, or one the tables do not know, as it is."""
    if key == "model":
        entry = MODELS.get(value) if isinstance(value, str) else None
        return entry.label if entry is not None else value
    return {"fusion": FUSION_LABELS, "loss": PIXEL_LOSS_LABELS}.get(key, {}).get(value, value)


def _rank(value: object, order: Collection[str]) -> tuple[int, str]:
    """Sort key putting ``value`` at its place in ``order`` (a table's keys), unknown ones last."""
    known = list(order)
    return (known.index(value) if value in known else len(known), str(value))


def _setting(run: RunRecord) -> str:
    """Overrides other than the identity columns and the seed, e.g. ``optimizer.lr=0.001``."""
    keys = [
        o for o in run.run.overrides or [] if o.split("=", 1)[0].lstrip("+~") not in _IDENTITY_KEYS
    ]
    return " ".join(sorted(keys))


def group_runs(runs: Sequence[RunRecord]) -> list[dict]:
    """Groups of runs (:func:`fusion_depth.runner.record.load_runs`) that differ only in seed,
    in the paper's order (models in the model table's order, then loss, then modality). Each
    group: its identity (``dataset``, ``sensor``, ``model``, ``backbone``, ``loss``,
    ``fusion``, ``setting``, ``engine``), ``n``, ``seeds``, ``stats`` (metric → mean, std over
    seeds) and its ``runs``. A run recorded without a model (before models had names) is
    :data:`~fusion_depth.models.DEFAULT_MODEL`'s."""
    groups: dict[tuple, list[RunRecord]] = {}
    for run in runs:
        r = run.run
        key = (
            r.dataset,
            r.sensor or "",
            r.model if r.model is not None else DEFAULT_MODEL,
            r.backbone,
            r.loss,
            r.fusion,
            _setting(run),
            r.engine or DEFAULT_ENGINE,
        )
        groups.setdefault(key, []).append(run)

    def order(key: tuple) -> tuple:
        dataset, sensor, model, backbone, loss, fusion, setting, engine = key
        return (
            dataset,
            sensor,
            _rank(model, MODELS),
            backbone,
            _rank(loss, PIXEL_LOSS_LABELS),
            _rank(fusion, FUSION_LABELS),
            setting,
            engine != DEFAULT_ENGINE,
            engine,
        )

    result = []
    for key in sorted(groups, key=order):
        members = groups[key]
        stats = {}
        for metric, *_ in COLUMNS:
            values = [m.test[metric] for m in members]
            stats[metric] = (
                statistics.fmean(values),
                statistics.stdev(values) if len(values) > 1 else None,
            )
        dataset, sensor, model, backbone, loss, fusion, setting, engine = key
        result.append(
            {
                "dataset": dataset,
                "sensor": sensor,
                "model": model,
                "backbone": backbone,
                "loss": loss,
                "fusion": fusion,
                "setting": setting,
                "engine": engine,
                "n": len(members),
                "seeds": sorted(m.run.seed for m in members),
                "stats": stats,
                "runs": members,
            }
        )
    return result


def identity_columns(groups: Sequence[dict], show: Collection[str] = ()) -> list[tuple[str, str]]:
    """(header, key) of the identity fields that vary (and those in ``show``, e.g. ``model``
    for ``--by model``), so a uniform grid keeps a narrow table."""
    return [
        (name, key)
        for name, key in (
            ("Dataset", "dataset"),
            ("Sensor", "sensor"),
            ("Model", "model"),
            ("Backbone", "backbone"),
            ("Setting", "setting"),
            ("Engine", "engine"),
        )
        if key in show or len({g[key] for g in groups}) > 1
    ]


def identity_cells(group: dict, extra: Sequence[tuple[str, str]]) -> list[str]:
    """The cells naming a group: the varying identity fields, then Modality and Loss (models,
    fusion modes and losses by their labels, :func:`key_label`)."""
    return [key_label(key, group[key]) for _, key in extra] + [
        key_label("fusion", group["fusion"]),
        key_label("loss", group["loss"]),
    ]


def build_table(groups: Sequence[dict], fmt: str = "markdown") -> str:
    """The paper's table (Modality, Loss, RMSE, ARD, SRD, δ1–δ3) for grouped runs."""
    if not groups:
        raise ValueError("no runs to tabulate")
    extra = identity_columns(groups)
    show_n = any(g["n"] > 1 for g in groups)
    latex = fmt == "latex"
    header = [name for name, _ in extra] + ["Modality", "Loss"]
    if show_n:
        header.append("Seeds")
    first_metric = len(header)
    header += [tex if latex else name for _, name, tex, _ in COLUMNS]
    if fmt == "csv":
        header = header[:first_metric] + [f"{k}_{s}" for k, *_ in COLUMNS for s in ("mean", "std")]
    rows, bold = [], set()
    for g in groups:
        row = identity_cells(g, extra)
        if show_n:
            row.append(str(g["n"]))
        for metric, *_ in COLUMNS:
            mean, std = g["stats"][metric]
            if fmt == "csv":
                row += [f"{mean:.6g}", "" if std is None else f"{std:.6g}"]
            else:
                row.append(f"{mean:.3f}" if std is None else f"{mean:.3f} ± {std:.3f}")
        rows.append(row)
    if fmt != "csv":
        for j, (metric, _, _, better) in enumerate(COLUMNS):
            target = better(g["stats"][metric][0] for g in groups)
            bold |= {
                (i, first_metric + j)
                for i, g in enumerate(groups)
                if round(g["stats"][metric][0], 3) == round(target, 3)
            }
    return format_table(header, rows, fmt, bold)


# --- Per-column tables: --by condition / distance / cap ---------------------------------------

# --by choice → the metrics.json section holding one metrics dict per column.
BY_SECTIONS = BREAKDOWNS
ALL = "all"
# The conditions ``--by model`` puts first (after ``all``) when a sweep has them: where a camera
# struggles, the question radar fusion is asked.
HARD_CONDITIONS = ("night", "fog")


def put_first(columns: Sequence[str], first: Sequence[str] = ()) -> list[str]:
    """``columns`` with ``all`` first, then those named in ``first`` (in that order, where
    present), then the others in their own order."""
    lead = [c for c in columns if c == ALL]
    lead += [c for c in dict.fromkeys(first) if c in columns and c != ALL]
    return lead + [c for c in columns if c not in lead]


def higher_is_better(metric: str) -> bool:
    """Only the δ thresholds go up; every error metric goes down (:data:`HIGHER_IS_BETTER`)."""
    return HIGHER_IS_BETTER.get(metric, False)


def metric_label(metric: str, latex: bool = False) -> str:
    """The paper's name of a metric (RMSE, ARD, δ1...), or its key when the paper has none."""
    for key, name, tex, _ in COLUMNS:
        if key == metric:
            return tex if latex else name
    return tex_escape(metric) if latex else metric


def tex_escape(text: str) -> str:
    return text.replace("_", r"\_")


def _lower_bound(key: str) -> float | None:
    """10.0 for a distance bin ``"10-20"``; None when the key does not start with a number."""
    try:
        return float(key.split("-", 1)[0])
    except ValueError:
        return None


def column_keys(runs: Sequence[RunRecord], by: str, first: Sequence[str] = ()) -> list[str]:
    """``all``, then every key of the ``--by`` section: those named in ``first``, then the
    others in file order (distance bins by range)."""
    keys: dict[str, None] = {}
    for run in runs:
        section = run.breakdown(by)
        if section is None:
            raise ValueError(
                f"{run.path}: no {BY_SECTIONS[by]!r} (written by an older version); "
                f"--by {by} needs the run evaluated again"
            )
        keys.update(dict.fromkeys(section))
    ordered = list(keys)
    bounds = [_lower_bound(k) for k in ordered]
    if by != "condition" and all(b is not None for b in bounds):
        ordered = [k for _, k in sorted(zip(bounds, ordered, strict=True), key=lambda t: t[0])]
    return put_first([ALL, *ordered], first)


def run_metric(run: RunRecord, by: str | None, column: str, metric: str) -> float | None:
    """One run's ``metric`` for a column (``all`` = the whole test set); None when absent."""
    values = run.test if column == ALL else run.breakdown(by).get(column)
    if values is None:
        return None
    if metric not in values:
        known = ", ".join(k for k, v in values.items() if isinstance(v, int | float))
        raise ValueError(f"{run.path}: no metric {metric!r}; expected one of {known}")
    return float(values[metric])


def mean_std(values: Sequence[float]) -> tuple[float, float | None]:
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else None


def by_column_stats(
    groups: Sequence[dict], by: str, metric: str = "rmse", first: Sequence[str] = ()
) -> tuple[list[str], list[dict[str, tuple[float, float | None] | None]]]:
    """Columns (``all`` + the ``--by`` keys, those in ``first`` first) and, per group,
    column → (mean, std over seeds).

    A column a group never saw (e.g. a condition missing from its test set) maps to None.
    """
    if by not in BY_SECTIONS:
        raise ValueError(f"--by {by}: expected one of {', '.join(BY_SECTIONS)}")
    columns = column_keys([r for g in groups for r in g["runs"]], by, first)
    stats = []
    for g in groups:
        cells: dict[str, tuple[float, float | None] | None] = {}
        for column in columns:
            values = [run_metric(r, by, column, metric) for r in g["runs"]]
            present = [v for v in values if v is not None]
            cells[column] = mean_std(present) if present else None
        stats.append(cells)
    return columns, stats


def build_by_table(
    groups: Sequence[dict],
    by: str,
    metric: str = "rmse",
    fmt: str = "markdown",
    *,
    first: Sequence[str] = (),
    show: Collection[str] = (),
) -> str:
    """One metric per condition (distance bin, depth cap): where does a fusion mode help?

    ``first``: columns to put first (after ``all``); ``show``: identity columns to show even
    when every group has the same value (``("model",)`` for ``--by model``).
    """
    if not groups:
        raise ValueError("no runs to tabulate")
    columns, stats = by_column_stats(groups, by, metric, first)
    extra = identity_columns(groups, show)
    show_n = any(g["n"] > 1 for g in groups)
    header = [name for name, _ in extra] + ["Modality", "Loss"] + (["Seeds"] if show_n else [])
    first = len(header)
    if fmt == "csv":
        header += [f"{metric}_{c}_{s}" for c in columns for s in ("mean", "std")]
    else:
        latex = fmt == "latex"
        label = metric_label(metric, latex)
        header += [f"{label} ({tex_escape(c) if latex else c})" for c in columns]
    rows = []
    for g, cells in zip(groups, stats, strict=True):
        row = identity_cells(g, extra) + ([str(g["n"])] if show_n else [])
        for column in columns:
            cell = cells[column]
            if fmt == "csv":
                row += ["", ""] if cell is None else [f"{cell[0]:.6g}", _fmt_std(cell[1])]
            elif cell is None:
                row.append("–")
            else:
                mean, std = cell
                row.append(f"{mean:.3f}" if std is None else f"{mean:.3f} ± {std:.3f}")
        rows.append(row)
    bold = set()
    if fmt != "csv":
        better = max if higher_is_better(metric) else min
        for j, column in enumerate(columns):
            means = [(i, s[column][0]) for i, s in enumerate(stats) if s[column] is not None]
            if means:
                target = round(better(m for _, m in means), 3)
                bold |= {(i, first + j) for i, m in means if round(m, 3) == target}
    return format_table(header, rows, fmt, bold)


def _fmt_std(std: float | None) -> str:
    return "" if std is None else f"{std:.6g}"
