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
from dataclasses import dataclass

from fusion_depth.losses.depth_loss import PIXEL_LOSS_LABELS
from fusion_depth.metrics.depth import (
    HIGHER_IS_BETTER,
    METRIC_KEYS,
    TABLE_METRICS,
    metric_header,
    metric_in_units,
)
from fusion_depth.models._registry import DEFAULT_MODEL, MODELS
from fusion_depth.models.fusion import FUSION_LABELS
from fusion_depth.models.prior_alignment import LABEL as ALIGNMENT_LABEL
from fusion_depth.models.prior_alignment import MODEL_NAME as ALIGNMENT_MODEL
from fusion_depth.models.released import released_entry
from fusion_depth.runner.protocol import BEFORE_PRESETS, protocol_differences
from fusion_depth.runner.record import BREAKDOWNS, RunRecord
from fusion_depth.utils.tables import format_table


@dataclass(frozen=True)
class Preset:
    """How the runs were scored, as a table prints them: the evaluation preset (``eval=``), its
    columns in order and its units. ``metrics.json`` records them under ``protocol``; a record
    written before presets existed is ``paper``'s. See :func:`runs_preset`."""

    name: str = "paper"
    metrics: tuple[str, ...] = TABLE_METRICS
    units: str = "m"

    def value(self, metric: str, value: float) -> float:
        """``value`` (metres, 1/km, as recorded) in this preset's units."""
        return metric_in_units(metric, value, self.units)

    def label(self, metric: str, latex: bool = False) -> str:
        """The column header of ``metric``: its table name with this preset's unit."""
        return metric_header(metric, self.units, latex)

    def decimals(self, metric: str) -> int:
        """The decimals a cell of ``metric`` is printed with: a length in millimetres to the
        millimetre (0), everything else to 3 (metres to the millimetre, ratios, 1/km)."""
        return 0 if self.value(metric, 1.0) == 1000.0 else 3

    def cell(
        self, metric: str, cell: tuple[float, float | None] | None
    ) -> tuple[float, float | None] | None:
        """A (mean, std over seeds) cell in this preset's units; None stays None."""
        if cell is None:
            return None
        mean, std = cell
        return self.value(metric, mean), None if std is None else self.value(metric, std)


def runs_preset(runs: Sequence[RunRecord]) -> Preset:
    """The :class:`Preset` every run was scored with.

    Raises:
        ValueError: the runs were scored under different presets (a table would put numbers
            that mean different things side by side); names a run of each.
    """
    found: dict[Preset, RunRecord] = {}
    for run in runs:
        protocol = run.protocol or {}
        preset = Preset(
            name=str(protocol.get("preset", BEFORE_PRESETS["preset"])),
            metrics=tuple(protocol.get("metrics") or BEFORE_PRESETS["metrics"]),
            units=str(protocol.get("units", BEFORE_PRESETS["units"])),
        )
        found.setdefault(preset, run)
    if len(found) > 1:
        named = "; ".join(f"eval={p.name} ({r.path})" for p, r in found.items())
        raise ValueError(
            f"the runs were scored under different evaluation presets: {named}. Report one "
            "preset at a time, or score them again with one (python -m fusion_depth.evaluate "
            "ckpt_path=<folder> eval=<preset>)"
        )
    return next(iter(found), Preset())


def _format_name(version: object) -> str:
    return "unknown (a record from before records named it)" if version is None else str(version)


def check_format_versions(runs: Sequence[RunRecord], mixed: bool = False) -> str | None:
    """Refuse runs of one dataset whose frames were prepared by different format versions
    (:func:`fusion_depth.runner.record.format_version`; a record that names none is unknown):
    their scores are not comparable (nuScenes' placement change moved RMSE by up to 3.5 %).

    Args:
        mixed: report them anyway (``--mixed-formats``): return the note to print instead.

    Returns:
        None where every dataset's runs share one version; with ``mixed``, a line naming the
        versions and a record of each.

    Raises:
        ValueError: (without ``mixed``) the versions of a dataset differ; names each version,
            a record of each, and what to do.
    """
    found: dict[object, dict[object, RunRecord]] = {}
    for run in runs:
        found.setdefault(run.run.dataset, {}).setdefault(run.run.format_version, run)
    mixes = {dataset: versions for dataset, versions in found.items() if len(versions) > 1}
    if not mixes:
        return None
    named = "; ".join(
        f"{dataset}: " + ", ".join(f"{_format_name(v)} ({r.path})" for v, r in versions.items())
        for dataset, versions in mixes.items()
    )
    if mixed:
        return f"note: --mixed-formats: runs of different data format versions together: {named}"
    raise ValueError(
        f"the runs read frames of different data format versions ({named}), whose scores "
        "are not comparable: score them again on this version (python -m fusion_depth.evaluate "
        "ckpt_path=<folder>), keep one version (move the others out), or pass --mixed-formats"
    )


# Overrides that already have a column or are averaged over (``model=`` chooses the network,
# as does ``model.net.name=``; other ``model.*`` keys are settings).
_IDENTITY_KEYS = {"dataset", "model", "model.net.name", "backbone", "fusion", "loss", "seed"}
# The engine of runs that record none: training runs and checkpoints run by PyTorch.
DEFAULT_ENGINE = "torch"


def key_label(key: str, value: str) -> str:
    """How the tables name an identity value: a model by its label in the model table
    (:data:`fusion_depth.models.MODELS`), a fusion mode or pixel loss by the paper's name
    (RGB-Fusion, L1, ...); any other value, or one the tables do not know, as it is; none ("–")
    where a record has none (the global alignment, scored by evaluate, trains with no loss)."""
    if value is None:
        return "–"
    if key == "model":
        if value == ALIGNMENT_MODEL:  # scored by evaluate, never trained: not in the table
            return ALIGNMENT_LABEL
        entry = MODELS.get(value) if isinstance(value, str) else None
        entry = entry if entry is not None else released_entry(value)
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


def short_settings(settings: Collection[str]) -> tuple[dict[str, str], tuple[str, ...]]:
    """Short labels for the ``setting`` of a table's groups (space-separated overrides), and the
    overrides they leave out.

    An override whose key has one value in every setting that names it is left out (a prior's
    weights, a fit's threshold that only RANSAC rows give): it tells none of those rows apart.
    Where that would give two settings one label, such overrides are kept again, the shortest
    first, until the labels differ. A dotted key is cut to its last part where no other key
    of the table ends so (``alignment.target=sparse`` → ``target=sparse``).

    Returns:
        setting → label, and the overrides left out (sorted; empty when none was).
    """
    parsed = {s: s.split() for s in settings}
    values: dict[str, set[str]] = {}
    for overrides in parsed.values():
        for override in overrides:
            key, _, value = override.partition("=")
            values.setdefault(key, set()).add(value)
    uniform = {key for key, found in values.items() if len(found) == 1}
    # Kept again in this order where labels would collide: the shortest overrides first.
    restore = sorted(uniform, key=lambda key: (len(key) + len(next(iter(values[key]))), key))

    # A key's last part names it where no other key of the table, shown or not, ends so.
    ends = [key.lstrip("+~").rsplit(".", 1)[-1] for key in values]

    def labels_without(left_out: set[str]) -> dict[str, str]:

        def short(override: str) -> str:
            key, sep, value = override.partition("=")
            name = key.lstrip("+~")
            end = name.rsplit(".", 1)[-1]
            shown = end if ends.count(end) == 1 else name
            return f"{key[: len(key) - len(name)]}{shown}{sep}{value}"

        return {
            s: " ".join(short(o) for o in overrides if o.partition("=")[0] not in left_out)
            for s, overrides in parsed.items()
        }

    left_out = set(uniform)
    labels = labels_without(left_out)
    while len(set(labels.values())) < len(labels):
        left_out.discard(restore.pop(0))
        labels = labels_without(left_out)
    every = {o for overrides in parsed.values() for o in overrides}
    return labels, tuple(sorted(o for o in every if o.partition("=")[0] in left_out))


def settings_note(groups: Sequence[dict]) -> str:
    """A Markdown line under a table whose Setting column is shown short
    (:func:`short_settings`) naming the overrides it leaves out; "" when none."""
    shared = groups[0].get("setting_shared", ()) if groups else ()
    if not shared:
        return ""
    named = ", ".join(f"`{o}`" for o in shared)
    return f"\n\nLeft out of Setting, the same in every row that sets them: {named}."


# Columns naming a row that a Markdown table leaves out where every row holds one value (named
# under the table instead): they tell no row apart. The varying identity columns
# (:func:`identity_columns`) are shown only where they vary already.
SAME_LEFT_OUT = ("Modality", "Loss", "Baseline")

# A table's header and each of its rows in three parts: the cells naming the row (identity,
# Modality, Loss; a compared group's Baseline), its bookkeeping (Seeds, Training (min), Images)
# and what it measured (a Cap, the metrics, Significant).
Parts = tuple[Sequence[str], Sequence[str], Sequence[str]]


def _note_value(value: str) -> str:
    return "none" if value == "–" else value


def lay_out(
    fmt: str,
    header: Parts,
    rows: Sequence[Parts],
    bold: Collection[tuple[int, int]] = (),
    note: str = "",
) -> str:
    """A table from its parts (:data:`Parts`), metrics first.

    Markdown and LaTeX: the cells naming a row, then what it measured, then its bookkeeping, so
    the numbers start right after what a row is. Markdown leaves out a column of
    :data:`SAME_LEFT_OUT` holding one value in every row of a table of several rows, and names
    it in the note under the table, after ``note`` (:func:`settings_note`). CSV is data, read by
    name: naming, bookkeeping, then what was measured, every column, no note.

    Args:
        bold: (row, index among the measured cells) of the cells to mark.
    """
    naming, book, measured = header
    if fmt == "csv":
        return format_table([*naming, *book, *measured], [[*n, *b, *m] for n, b, m in rows], fmt)
    keep = list(range(len(naming)))
    same = []
    if fmt == "markdown" and len(rows) > 1:
        for j, name in enumerate(naming):
            values = {row[0][j] for row in rows}
            if name in SAME_LEFT_OUT and len(values) == 1:
                same.append(f"{name} {_note_value(values.pop())}")
                keep.remove(j)
    cells = [[*(n[j] for j in keep), *m, *b] for n, b, m in rows]
    marked = {(i, len(keep) + j) for i, j in bold}
    table = format_table([*(naming[j] for j in keep), *measured, *book], cells, fmt, marked)
    if fmt != "markdown":
        return table
    notes = [note.strip()] if note.strip() else []
    if same:
        notes.append(f"The same in every row, so not a column: {', '.join(same)}.")
    return table + ("\n\n" + " ".join(notes) if notes else "")


# Protocol keys that only shape the breakdowns, not the headline scores a row averages.
_BREAKDOWN_ONLY = frozenset({"distance_bins", "bin_width"})


def _check_same_scoring(members: Sequence[RunRecord]) -> None:
    """Runs averaged into one row must have been scored alike: a key of ``eval`` given on one
    run's command line (``evaluate ... eval.clamp=true``) is not among its overrides, so the
    recorded protocol is compared instead.

    Raises:
        ValueError: two runs of the row differ in a protocol key, naming both and the key.
    """
    first = members[0]
    for run in members[1:]:
        differences = protocol_differences(first.protocol, run.protocol, _BREAKDOWN_ONLY)
        if differences:
            key, x, y = differences[0]
            raise ValueError(
                f"{first.path} and {run.path} differ only in their seed but were scored "
                f"differently (protocol {key} {x!r} vs {y!r}); a row averages runs scored "
                "alike: score them again with one protocol"
            )


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
    labels, shared = short_settings({key[6] for key in groups})
    for key in sorted(groups, key=order):
        members = groups[key]
        _check_same_scoring(members)
        stats = _metric_stats([m.test for m in members])
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
                "setting_label": labels[setting],  # the Setting column's short form
                "setting_shared": shared,  # what the short forms leave out
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


def identity_cells(group: dict, extra: Sequence[tuple[str, str]], full: bool = False) -> list[str]:
    """The cells naming a group: the varying identity fields, then Modality and Loss (models,
    fusion modes and losses by their labels, :func:`key_label`). The setting is its short label
    (:func:`short_settings`) unless ``full`` (CSV and LaTeX: every override)."""

    def cell(key: str) -> str:
        if key == "setting" and not full:
            return group.get("setting_label", group["setting"])
        return key_label(key, group[key])

    return [cell(key) for _, key in extra] + [
        key_label("fusion", group["fusion"]),
        key_label("loss", group["loss"]),
    ]


def _metric_stats(sections: Sequence[dict]) -> dict[str, tuple[float, float | None]]:
    """Metric → (mean, std over seeds) of one metrics dict per run, for every metric all of
    them hold."""
    return {
        metric: mean_std([s[metric] for s in sections])
        for metric in METRIC_KEYS
        if all(metric in s for s in sections)
    }


def _cell_text(preset: Preset, metric: str, cell: tuple[float, float | None]) -> str:
    """``mean ± std`` (or the mean of a single seed) in the preset's units and decimals
    (:meth:`Preset.decimals`)."""
    mean, std = preset.cell(metric, cell)
    places = preset.decimals(metric)
    return f"{mean:.{places}f}" if std is None else f"{mean:.{places}f} ± {std:.{places}f}"


def _best_rows(metric: str, values: Sequence[tuple[int, float]], places: int = 3) -> set[int]:
    """The rows holding the best of ``(row, value)`` pairs at the ``places`` decimals printed;
    none when fewer than two values compete (a best needs something to beat)."""
    if len(values) < 2:
        return set()
    better = max if higher_is_better(metric) else min
    target = round(better(v for _, v in values), places)
    return {i for i, v in values if round(v, places) == target}


def _table_caps(groups: Sequence[dict]) -> list[str]:
    """The depth caps a table gives rows to: every cap of ``test_by_cap`` (by value) when some
    run scored several in one pass (``eval=radarnet``); none otherwise."""
    runs = [r for g in groups for r in g["runs"]]
    if not any(len(r.test_by_cap or {}) > 1 for r in runs):
        return []
    caps = {cap for r in runs for cap in r.test_by_cap or {}}
    return sorted(caps, key=float)


def _cap_stats(group: dict, cap: str | None) -> dict[str, tuple[float, float | None]]:
    """A group's metric → (mean, std over seeds) at ``cap`` (None: the headline); a metric some
    run lacks at that cap is left out."""
    if cap is None:
        return group["stats"]
    sections = [(r.test_by_cap or {}).get(cap) for r in group["runs"]]
    return {} if any(s is None for s in sections) else _metric_stats(sections)


def training_minutes(group: dict) -> tuple[float, float | None] | None:
    """Mean and std over seeds of a group's training wall time in minutes (``wall_time_s``:
    fit and test), None where a run records none (``evaluate``'s records)."""
    times = [run.wall_time_s for run in group["runs"]]
    if not times or any(not isinstance(t, int | float) for t in times):
        return None
    return mean_std([t / 60 for t in times])


def _metric_cells(
    preset: Preset, metric: str, cell: tuple[float, float | None] | None, fmt: str
) -> list[str]:
    """A metric's cells: CSV its mean and std in the recorded units (empty where it is
    missing), else ``mean ± std`` in the preset's units (:func:`_cell_text`; "–" if missing)."""
    if fmt == "csv":
        return ["", ""] if cell is None else [f"{cell[0]:.6g}", _fmt_std(cell[1])]
    return ["–" if cell is None else _cell_text(preset, metric, cell)]


def _minutes_cells(group: dict, fmt: str) -> list[str]:
    """The training-time cells of a group (:func:`training_minutes`): CSV its mean and std
    (empty where a run records none), else ``mean ± std`` to a tenth of a minute ("–")."""
    minutes = training_minutes(group)
    if fmt == "csv":
        return ["", ""] if minutes is None else [f"{minutes[0]:.4g}", _fmt_std(minutes[1])]
    if minutes is None:
        return ["–"]
    spread = "" if minutes[1] is None else f" ± {minutes[1]:.1f}"
    return [f"{minutes[0]:.1f}{spread}"]


def build_table(
    groups: Sequence[dict],
    fmt: str = "markdown",
    preset: Preset | None = None,
    time: bool = False,
) -> str:
    """The paper's table for grouped runs: Modality, Loss, then the preset's metrics in its
    order and units (``paper``: RMSE, ARD, SRD, MAE, δ1–δ3 in metres; ``radarnet``: MAE, RMSE in
    mm, iMAE, iRMSE in 1/km), then Seeds. When the runs scored several caps in one pass, a Cap
    column and one row per cap, as RadarNet's tables have; the best of each column is marked per
    cap. ``time``: a column of each group's training wall time (:func:`training_minutes`; "–"
    for records without one), where the machine and the seeds' runs compare. The columns are
    laid out by :func:`lay_out` (CSV: Seeds and the time before the cap and the metrics)."""
    if not groups:
        raise ValueError("no runs to tabulate")
    preset = preset or Preset()
    extra = identity_columns(groups)
    show_n = any(g["n"] > 1 for g in groups)
    caps = _table_caps(groups)
    book = ["Seeds"] if show_n else []
    if time:
        book += ["train_min_mean", "train_min_std"] if fmt == "csv" else ["Training (min)"]
    measured = ["Cap (m)"] if caps else []
    if fmt == "csv":  # CSV is data: recorded units (metres, 1/km), as metrics.json
        measured += [f"{k}_{s}" for k in preset.metrics for s in ("mean", "std")]
    else:
        measured += [preset.label(k, fmt == "latex") for k in preset.metrics]
    rows: list[Parts] = []
    row_stats: list[tuple[str | None, dict]] = []
    for g in groups:
        for cap in caps or [None]:
            stats = _cap_stats(g, cap)
            kept = ([str(g["n"])] if show_n else []) + (_minutes_cells(g, fmt) if time else [])
            cells = [] if cap is None else [cap]
            for metric in preset.metrics:
                cells += _metric_cells(preset, metric, stats.get(metric), fmt)
            rows.append((identity_cells(g, extra, full=fmt != "markdown"), kept, cells))
            row_stats.append((cap, stats))
    bold = set()
    if fmt != "csv":
        lead = 1 if caps else 0  # the Cap column
        for j, metric in enumerate(preset.metrics):
            for cap in caps or [None]:
                cells = [
                    (i, preset.value(metric, st[metric][0]))
                    for i, (c, st) in enumerate(row_stats)
                    if c == cap and metric in st
                ]
                best = _best_rows(metric, cells, preset.decimals(metric))
                bold |= {(i, lead + j) for i in best}
    note = settings_note(groups) if ("Setting", "setting") in extra else ""
    header = ([name for name, _ in extra] + ["Modality", "Loss"], book, measured)
    return lay_out(fmt, header, rows, bold, note)


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
    preset: Preset | None = None,
) -> str:
    """One metric per condition (distance bin, depth cap): where does a fusion mode help?

    ``first``: columns to put first (after ``all``); ``show``: identity columns to show even
    when every group has the same value (``("model",)`` for ``--by model``); ``preset``: the
    units the cells are in (:func:`runs_preset`; CSV keeps the recorded units). The columns are
    laid out by :func:`lay_out`: the metric's columns, then Seeds (CSV: Seeds first).
    """
    preset = preset or Preset()
    if not groups:
        raise ValueError("no runs to tabulate")
    columns, stats = by_column_stats(groups, by, metric, first)
    extra = identity_columns(groups, show)
    show_n = any(g["n"] > 1 for g in groups)
    if fmt == "csv":
        measured = [f"{metric}_{c}_{s}" for c in columns for s in ("mean", "std")]
    else:
        latex = fmt == "latex"
        label = preset.label(metric, latex)
        measured = [f"{label} ({tex_escape(c) if latex else c})" for c in columns]
    rows: list[Parts] = []
    for g, cells in zip(groups, stats, strict=True):
        values = [v for c in columns for v in _metric_cells(preset, metric, cells[c], fmt)]
        kept = [str(g["n"])] if show_n else []
        rows.append((identity_cells(g, extra, full=fmt != "markdown"), kept, values))
    bold = set()
    if fmt != "csv":
        for j, column in enumerate(columns):
            means = [
                (i, preset.value(metric, s[column][0]))
                for i, s in enumerate(stats)
                if s[column] is not None
            ]
            bold |= {(i, j) for i in _best_rows(metric, means, preset.decimals(metric))}
    note = settings_note(groups) if ("Setting", "setting") in extra else ""
    header = ([name for name, _ in extra] + ["Modality", "Loss"], ["Seeds"] if show_n else [])
    return lay_out(fmt, (*header, measured), rows, bold, note)


def _fmt_std(std: float | None) -> str:
    return "" if std is None else f"{std:.6g}"
