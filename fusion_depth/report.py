"""The paper-style table of a sweep: ``python -m fusion_depth.report multirun/<sweep>``.

Reads every ``metrics.json`` below a directory, averages runs that differ only in their seed
(mean ± sample std), marks the best value of each column, and prints Markdown, LaTeX or CSV.

Options:
  --format {markdown,latex,csv}  how to print the table (default markdown).
  --by {condition,distance,cap}  one metric (``--metric``) per condition, distance bin or depth
                                 cap: columns ``all`` then each of them, mean ± std over seeds.
  --metric KEY                   the metric of --by, --compare and a --by plot (default rmse;
                                 any key of the metrics: abs_rel, delta1, mae, ...).
  --compare KEY=VALUE            e.g. ``fusion=rgb``: every group that differs from a VALUE group
                                 only in KEY (fusion, loss or backbone) is compared with it image
                                 by image: mean of the per-image differences (other − baseline,
                                 so negative is better for errors) with a paired bootstrap CI,
                                 pairing runs by seed. ``Significant`` says whether the CI
                                 excludes 0 (such cells are bold). With ``--by condition``, also
                                 per condition. Needs each run's ``per_image.csv``.
  --resamples N                  bootstrap resamples of --compare (default 10000).
  --level L                      confidence level of --compare's intervals (default 0.95).
  --plot OUT.png                 also save a bar chart (any Matplotlib format: .png, .pdf, .svg):
                                 one subplot per metric (RMSE, ARD, δ1, or --metric) with a bar
                                 per fusion mode over each loss; with --by, --metric per column;
                                 with --compare, the differences with their CIs. Error bars are
                                 the std over seeds (none for a single seed).
  --wandb                        also log the table as a W&B Table (project fusion-depth, job
                                 type report, named after the directory, written below it);
                                 offline unless you are logged in (``wandb sync`` uploads it).

How to read --compare: the interval covers the variation from sampling test images and, when
the two groups share ≥ 2 seeds, from retraining with another seed; with one shared seed (or
none: each side is then averaged over its seeds) it covers the test images only.
"""

from __future__ import annotations

import argparse
import csv
import io
import os
import statistics
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import reduce
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fusion_depth.runs import PER_IMAGE_FILE, load_runs, write_atomic
from fusion_depth.stats import BootstrapResult, paired_bootstrap
from fusion_depth.tables import format_table

if TYPE_CHECKING:  # Matplotlib is imported by the plots only: a table should print at once.
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

# (metric key, column header, LaTeX header, better) in the paper's order.
COLUMNS = (
    ("rmse", "RMSE", "RMSE", min),
    ("abs_rel", "ARD", "ARD", min),
    ("sq_rel", "SRD", "SRD", min),
    ("delta1", "δ1", r"$\delta_1$", max),
    ("delta2", "δ2", r"$\delta_2$", max),
    ("delta3", "δ3", r"$\delta_3$", max),
)
MODALITY = {"rgb": "RGB", "concat": "RGB-Fusion", "add": "RGB-Add"}
LOSS = {"l1": "L1", "l2": "L2", "berhu": "BerHu"}
# Overrides that already have a column or are averaged over.
_IDENTITY_KEYS = {"dataset", "backbone", "fusion", "loss", "seed"}


def _setting(run: dict) -> str:
    """Overrides other than the identity columns and the seed, e.g. ``optimizer.lr=0.001``."""
    keys = [
        o
        for o in run["run"].get("overrides", [])
        if o.split("=", 1)[0].lstrip("+~") not in _IDENTITY_KEYS
    ]
    return " ".join(sorted(keys))


def group_runs(runs: Sequence[dict]) -> list[dict]:
    """Groups of runs that differ only in seed, in the paper's order (loss, then modality)."""
    groups: dict[tuple, list[dict]] = {}
    for run in runs:
        r = run["run"]
        key = (
            r["dataset"],
            r.get("sensor") or "",
            r["backbone"],
            r["loss"],
            r["fusion"],
            _setting(run),
        )
        groups.setdefault(key, []).append(run)

    def order(key: tuple) -> tuple:
        dataset, sensor, backbone, loss, fusion, setting = key
        return (
            dataset,
            sensor,
            backbone,
            list(LOSS).index(loss) if loss in LOSS else 99,
            loss,
            list(MODALITY).index(fusion) if fusion in MODALITY else 99,
            fusion,
            setting,
        )

    result = []
    for key in sorted(groups, key=order):
        members = groups[key]
        stats = {}
        for metric, *_ in COLUMNS:
            values = [m["test"][metric] for m in members]
            stats[metric] = (
                statistics.fmean(values),
                statistics.stdev(values) if len(values) > 1 else None,
            )
        dataset, sensor, backbone, loss, fusion, setting = key
        result.append(
            {
                "dataset": dataset,
                "sensor": sensor,
                "backbone": backbone,
                "loss": loss,
                "fusion": fusion,
                "setting": setting,
                "n": len(members),
                "seeds": sorted(m["run"].get("seed") for m in members),
                "stats": stats,
                "runs": members,
            }
        )
    return result


def _identity_columns(groups: Sequence[dict]) -> list[tuple[str, str]]:
    """(header, key) of the identity fields that vary, so a uniform grid keeps a narrow table."""
    return [
        (name, key)
        for name, key in (
            ("Dataset", "dataset"),
            ("Sensor", "sensor"),
            ("Backbone", "backbone"),
            ("Setting", "setting"),
        )
        if len({g[key] for g in groups}) > 1
    ]


def _identity_cells(group: dict, extra: Sequence[tuple[str, str]]) -> list[str]:
    """The cells naming a group: the varying identity fields, then Modality and Loss."""
    return [group[key] for _, key in extra] + [
        MODALITY.get(group["fusion"], group["fusion"]),
        LOSS.get(group["loss"], group["loss"]),
    ]


def build_table(groups: Sequence[dict], fmt: str = "markdown") -> str:
    """The paper's table (Modality, Loss, RMSE, ARD, SRD, δ1–δ3) for grouped runs."""
    if not groups:
        raise ValueError("no runs to tabulate")
    extra = _identity_columns(groups)
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
        row = _identity_cells(g, extra)
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
BY_SECTIONS = {
    "condition": "test_by_condition",
    "distance": "test_by_distance",
    "cap": "test_by_cap",
}
ALL = "all"


def _higher_is_better(metric: str) -> bool:
    """Only the δ thresholds go up; every error metric goes down."""
    return metric.startswith("delta")


def _metric_label(metric: str, latex: bool = False) -> str:
    """The paper's name of a metric (RMSE, ARD, δ1...), or its key when the paper has none."""
    for key, name, tex, _ in COLUMNS:
        if key == metric:
            return tex if latex else name
    return _tex_escape(metric) if latex else metric


def _tex_escape(text: str) -> str:
    return text.replace("_", r"\_")


def _lower_bound(key: str) -> float | None:
    """10.0 for a distance bin ``"10-20"``; None when the key does not start with a number."""
    try:
        return float(key.split("-", 1)[0])
    except ValueError:
        return None


def _column_keys(runs: Sequence[dict], by: str) -> list[str]:
    """``all``, then every key of the ``--by`` section in file order (distance bins by range)."""
    section = BY_SECTIONS[by]
    keys: dict[str, None] = {}
    for run in runs:
        if section not in run:
            raise ValueError(
                f"{run['path']}: no {section!r} (written by an older version); "
                f"--by {by} needs the run evaluated again"
            )
        keys.update(dict.fromkeys(run[section]))
    ordered = list(keys)
    bounds = [_lower_bound(k) for k in ordered]
    if by != "condition" and all(b is not None for b in bounds):
        ordered = [k for _, k in sorted(zip(bounds, ordered, strict=True), key=lambda t: t[0])]
    return [ALL, *ordered]


def _run_metric(run: dict, by: str | None, column: str, metric: str) -> float | None:
    """One run's ``metric`` for a column (``all`` = the whole test set); None when absent."""
    values = run["test"] if column == ALL else run[BY_SECTIONS[by]].get(column)
    if values is None:
        return None
    if metric not in values:
        known = ", ".join(k for k, v in values.items() if isinstance(v, int | float))
        raise ValueError(f"{run['path']}: no metric {metric!r}; expected one of {known}")
    return float(values[metric])


def _mean_std(values: Sequence[float]) -> tuple[float, float | None]:
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else None


def by_column_stats(
    groups: Sequence[dict], by: str, metric: str = "rmse"
) -> tuple[list[str], list[dict[str, tuple[float, float | None] | None]]]:
    """Columns (``all`` + the ``--by`` keys) and, per group, column → (mean, std over seeds).

    A column a group never saw (e.g. a condition missing from its test set) maps to None.
    """
    if by not in BY_SECTIONS:
        raise ValueError(f"--by {by}: expected one of {', '.join(BY_SECTIONS)}")
    columns = _column_keys([r for g in groups for r in g["runs"]], by)
    stats = []
    for g in groups:
        cells: dict[str, tuple[float, float | None] | None] = {}
        for column in columns:
            values = [_run_metric(r, by, column, metric) for r in g["runs"]]
            present = [v for v in values if v is not None]
            cells[column] = _mean_std(present) if present else None
        stats.append(cells)
    return columns, stats


def build_by_table(
    groups: Sequence[dict], by: str, metric: str = "rmse", fmt: str = "markdown"
) -> str:
    """One metric per condition (distance bin, depth cap): where does a fusion mode help?"""
    if not groups:
        raise ValueError("no runs to tabulate")
    columns, stats = by_column_stats(groups, by, metric)
    extra = _identity_columns(groups)
    show_n = any(g["n"] > 1 for g in groups)
    header = [name for name, _ in extra] + ["Modality", "Loss"] + (["Seeds"] if show_n else [])
    first = len(header)
    if fmt == "csv":
        header += [f"{metric}_{c}_{s}" for c in columns for s in ("mean", "std")]
    else:
        latex = fmt == "latex"
        label = _metric_label(metric, latex)
        header += [f"{label} ({_tex_escape(c) if latex else c})" for c in columns]
    rows = []
    for g, cells in zip(groups, stats, strict=True):
        row = _identity_cells(g, extra) + ([str(g["n"])] if show_n else [])
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
        better = max if _higher_is_better(metric) else min
        for j, column in enumerate(columns):
            means = [(i, s[column][0]) for i, s in enumerate(stats) if s[column] is not None]
            if means:
                target = round(better(m for _, m in means), 3)
                bold |= {(i, first + j) for i, m in means if round(m, 3) == target}
    return format_table(header, rows, fmt, bold)


def _fmt_std(std: float | None) -> str:
    return "" if std is None else f"{std:.6g}"


# --- Paired comparisons: --compare KEY=VALUE -------------------------------------------------

COMPARE_KEYS = ("fusion", "loss", "backbone")
# Protocol fields that change how per-image results are aggregated, not the results themselves.
_AGGREGATION_ONLY = {"distance_bins", "bin_width", "averaging"}


@dataclass(frozen=True)
class PerImage:
    """One metric of one run for each scored test image, sorted by the image's index."""

    path: Path
    index: np.ndarray  # int64, sorted, unique
    condition: np.ndarray  # str, aligned with index
    values: np.ndarray  # float64, aligned with index


def per_image_path(run: dict) -> Path:
    """Where a run's ``per_image.csv`` is (``per_image_file`` is relative to metrics.json)."""
    return Path(run["path"]).parent / run.get("per_image_file", PER_IMAGE_FILE)


def load_per_image(run: dict, metric: str) -> PerImage:
    """Read ``metric`` of every image from the run's per-image file, checking it on the way."""
    path = per_image_path(run)
    if not path.is_file():
        raise FileNotFoundError(
            f"{run['path']}: its per-image results {path} are missing; --compare needs "
            f"{PER_IMAGE_FILE}, which runs of older versions did not write: re-score them with "
            f"python -m fusion_depth.evaluate ckpt_path=<sweep folder> and compare the output"
        )
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = {"index", "condition", metric} - set(reader.fieldnames or ())
        if missing:
            raise ValueError(
                f"{path}: no column(s) {', '.join(sorted(missing))}; expected a header with "
                f"index, condition and the metric (have: {', '.join(reader.fieldnames or ())})"
            )
        try:
            rows = [(int(r["index"]), r["condition"], float(r[metric])) for r in reader]
        except (TypeError, ValueError) as err:
            raise ValueError(f"{path}: line {reader.line_num}: {err}") from err
    if len(rows) == 0:
        raise ValueError(f"{path}: no images")
    rows.sort()
    index = np.array([r[0] for r in rows], dtype=np.int64)
    values = np.array([r[2] for r in rows], dtype=np.float64)
    if (np.diff(index) == 0).any():
        dup = int(index[1:][np.diff(index) == 0][0])
        raise ValueError(f"{path}: image index {dup} appears more than once")
    if not np.isfinite(values).all():
        bad = int(index[~np.isfinite(values)][0])
        raise ValueError(f"{path}: {metric} of image {bad} is not finite")
    return PerImage(path, index, np.array([r[1] for r in rows], dtype=object), values)


def _check_same_images(ref: dict, ref_pi: PerImage, run: dict, pi: PerImage) -> None:
    """Refuse to pair runs scored on different images: their differences would mean nothing."""

    def refuse(reason: str) -> ValueError:
        return ValueError(
            f"{ref['path']} and {run['path']}: not scored on the same test images ({reason}); "
            "--compare pairs images by index, so both runs must use the same dataset, split "
            "and protocol"
        )

    for what, a, b in (
        ("dataset", ref["run"].get("dataset"), run["run"].get("dataset")),
        ("split", ref.get("split"), run.get("split")),
    ):
        if a != b:
            raise refuse(f"{what} {a!r} vs {b!r}")
    if "protocol" in ref and "protocol" in run:
        keys = (set(ref["protocol"]) | set(run["protocol"])) - _AGGREGATION_ONLY
        for key in sorted(keys):
            a, b = ref["protocol"].get(key), run["protocol"].get(key)
            if a != b:
                raise refuse(f"protocol {key} {a!r} vs {b!r}")
    _, i, j = np.intersect1d(ref_pi.index, pi.index, assume_unique=True, return_indices=True)
    differ = ref_pi.condition[i] != pi.condition[j]
    if differ.any():
        k = int(np.argmax(differ))
        raise refuse(
            f"image {int(ref_pi.index[i[k]])} is {ref_pi.condition[i[k]]!r} in one and "
            f"{pi.condition[j[k]]!r} in the other"
        )


@dataclass(frozen=True)
class Comparison:
    """A group against its baseline, image by image: results per column (``all``, conditions)."""

    group: dict
    baseline: dict
    key: str
    metric: str
    seeds: tuple  # the paired seeds; empty when each side was averaged over its seeds
    num_images: int
    level: float
    results: dict[str, BootstrapResult | None] = field(default_factory=dict)

    @property
    def pairing(self) -> str:
        """How the runs were paired, for the table: by seed, or seed means against each other."""
        if self.seeds:
            return f"{len(self.seeds)} paired"
        return f"means {self.baseline['n']} vs {self.group['n']}"


def _by_seed(group: dict) -> dict:
    """seed → run of a group; two runs with one seed cannot be paired unambiguously."""
    runs: dict = {}
    for run in group["runs"]:
        seed = run["run"].get("seed")
        if seed in runs:
            raise ValueError(
                f"{runs[seed]['path']} and {run['path']}: two runs of one group with seed "
                f"{seed}; --compare pairs runs by seed"
            )
        runs[seed] = run
    return runs


def _seed_order(seed: object) -> tuple:
    return (seed is None, str(type(seed)), seed if seed is not None else 0)


def paired_differences(
    baseline: dict,
    group: dict,
    metric: str,
    load: Callable[[dict, str], PerImage] = load_per_image,
) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Per-image ``metric`` differences (group − baseline) over the images all runs share.

    Returns ``(differences (S, N), condition of each image (N,), paired seeds)``. Runs are paired
    by seed when the groups share seeds (S = number of shared seeds); otherwise each side is
    averaged over its seeds first (S = 1, paired seeds empty).
    """
    base, other = _by_seed(baseline), _by_seed(group)
    seeds = tuple(sorted(set(base) & set(other), key=_seed_order))
    if seeds:
        base_runs, other_runs = [base[s] for s in seeds], [other[s] for s in seeds]
    else:
        base_runs, other_runs = list(base.values()), list(other.values())
    ref = base_runs[0]
    ref_pi = load(ref, metric)
    loaded = {}
    for run in (*base_runs, *other_runs):
        loaded[run["path"]] = pi = load(run, metric)
        _check_same_images(ref, ref_pi, run, pi)
    common = reduce(np.intersect1d, (pi.index for pi in loaded.values()))
    if len(common) < 2:
        raise ValueError(
            f"{ref['path']} and {other_runs[0]['path']}: share {len(common)} scored test "
            "image(s); --compare needs at least 2"
        )

    def at_common(run: dict) -> np.ndarray:
        pi = loaded[run["path"]]
        return pi.values[np.searchsorted(pi.index, common)]

    b = np.stack([at_common(r) for r in base_runs])
    o = np.stack([at_common(r) for r in other_runs])
    diff = o - b if seeds else o.mean(axis=0, keepdims=True) - b.mean(axis=0, keepdims=True)
    conditions = ref_pi.condition[np.searchsorted(ref_pi.index, common)]
    return diff, conditions, seeds


def _condition_columns(runs: Sequence[dict], conditions: np.ndarray) -> list[str]:
    """``all``, then the conditions in the order the metrics files list them, then the rest."""
    order: dict[str, None] = {}
    for run in runs:
        order.update(dict.fromkeys(run.get("test_by_condition", {})))
    order.update(dict.fromkeys(conditions.tolist()))
    present = set(conditions.tolist())
    return [ALL, *(c for c in order if c in present)]


def compare_groups(
    groups: Sequence[dict],
    key: str,
    value: str,
    metric: str = "rmse",
    by: str | None = None,
    resamples: int = 10000,
    level: float = 0.95,
) -> list[Comparison]:
    """Every group differing from a ``key=value`` group only in ``key``, against that group.

    Each comparison holds the mean per-image difference (other − baseline) and its bootstrap
    interval (:func:`fusion_depth.stats.paired_bootstrap`), over all shared images and, with
    ``by="condition"``, over each condition's images.
    """
    if key not in COMPARE_KEYS:
        raise ValueError(f"--compare {key}={value}: expected KEY one of {', '.join(COMPARE_KEYS)}")
    if by not in (None, "condition"):
        raise ValueError(
            f"--by {by} with --compare: {PER_IMAGE_FILE} has no {by} per image; use --by condition"
        )
    baselines = [g for g in groups if g[key] == value]
    if not baselines:
        have = ", ".join(sorted({str(g[key]) for g in groups}))
        raise ValueError(f"--compare {key}={value}: no runs with {key}={value} (have: {have})")
    identity = [k for k in ("dataset", "sensor", *COMPARE_KEYS, "setting") if k != key]

    def same_but_key(a: dict, b: dict) -> bool:
        return all(a[k] == b[k] for k in identity)

    cache: dict[tuple[str, str], PerImage] = {}

    def load(run: dict, m: str) -> PerImage:
        if (run["path"], m) not in cache:
            cache[run["path"], m] = load_per_image(run, m)
        return cache[run["path"], m]

    comparisons = []
    for g in groups:
        if g[key] == value:
            continue
        baseline = next((b for b in baselines if same_but_key(b, g)), None)
        if baseline is None:
            continue
        diff, conditions, seeds = paired_differences(baseline, g, metric, load)
        columns = [ALL]
        if by == "condition":
            columns = _condition_columns([*baseline["runs"], *g["runs"]], conditions)
        results: dict[str, BootstrapResult | None] = {}
        for column in columns:
            d = diff if column == ALL else diff[:, conditions == column]
            results[column] = (
                paired_bootstrap(d, resamples=resamples, level=level) if d.shape[1] >= 2 else None
            )
        comparisons.append(
            Comparison(g, baseline, key, metric, seeds, diff.shape[1], level, results)
        )
    if not comparisons:
        raise ValueError(
            f"--compare {key}={value}: no other group differs from it only in {key} "
            f"(groups: {', '.join(_group_name(g) for g in groups)})"
        )
    return comparisons


def _group_name(group: dict) -> str:
    parts = [group["dataset"], group["backbone"], group["loss"], group["fusion"], group["setting"]]
    return "/".join(p for p in parts if p)


def _key_label(key: str, value: str) -> str:
    return {"fusion": MODALITY, "loss": LOSS}.get(key, {}).get(value, value)


def build_comparison_table(comparisons: Sequence[Comparison], fmt: str = "markdown") -> str:
    """Mean per-image difference and CI per compared group; significant cells are marked.

    A cell is significant (bold, and listed in the ``Significant`` column) when its interval
    excludes 0. The sign is other − baseline: negative is better for errors, positive for δ.
    """
    if not comparisons:
        raise ValueError("no comparisons to tabulate")
    groups = [c.group for c in comparisons]
    columns = list(dict.fromkeys(col for c in comparisons for col in c.results))
    metric, level = comparisons[0].metric, comparisons[0].level
    extra = _identity_columns(groups)
    header = [name for name, _ in extra] + ["Modality", "Loss", "Baseline", "Seeds", "Images"]
    first = len(header)
    latex = fmt == "latex"
    if fmt == "csv":
        header += [
            f"{metric}_{col}_{part}"
            for col in columns
            for part in ("diff", "low", "high", "significant")
        ]
        header.append("level")
    else:
        label = ("$\\Delta$" if latex else "Δ") + _metric_label(metric, latex)
        pct = f"{100 * level:g}\\%" if latex else f"{100 * level:g}%"
        header += [f"{label} ({_tex_escape(c) if latex else c}, {pct} CI)" for c in columns]
        header.append("Significant")
    rows, bold = [], set()
    for i, c in enumerate(comparisons):
        row = _identity_cells(c.group, extra)
        row += [_key_label(c.key, c.baseline[c.key]), c.pairing, str(c.num_images)]
        significant = []
        for j, column in enumerate(columns):
            r = c.results.get(column)
            if r is not None and r.excludes_zero:
                significant.append(column)
                bold.add((i, first + j))
            if fmt == "csv":
                row += (
                    ["", "", "", ""]
                    if r is None
                    else [
                        f"{r.mean:.6g}",
                        f"{r.low:.6g}",
                        f"{r.high:.6g}",
                        "yes" if r.excludes_zero else "no",
                    ]
                )
            else:
                row.append("–" if r is None else f"{r.mean:+.3f} [{r.low:+.3f}, {r.high:+.3f}]")
        if fmt == "csv":
            row.append(f"{level:g}")
        elif columns == [ALL]:
            row.append("yes" if significant else "no")
        else:
            row.append(", ".join(significant) or "none")
        rows.append(row)
    return format_table(header, rows, fmt, bold if fmt != "csv" else frozenset())


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
    return "higher is better" if _higher_is_better(metric) else "lower is better"


def plot_groups(
    groups: Sequence[dict], out: str | os.PathLike, metrics: Sequence[str] = PLOT_METRICS
) -> Path:
    """One subplot per metric: bars per fusion mode over each loss, error bars = seed std."""
    from matplotlib.figure import Figure

    if not groups:
        raise ValueError("no runs to plot")
    extra = [key for _, key in _identity_columns(groups)]

    def category(g: dict) -> str:
        return " / ".join([*(g[k] for k in extra), LOSS.get(g["loss"], g["loss"])])

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
                    values = [_run_metric(r, None, ALL, metric) for r in g["runs"]]
                    cells.append(_mean_std(values))
            heights = [np.nan if c is None else c[0] for c in cells]
            series.append((MODALITY.get(fusion, fusion), heights, _std_errors(cells)))
        _grouped_bars(ax, categories, series)
        ax.set_title(f"{_metric_label(metric)} ({_direction(metric)})")
        if n == 0:
            ax.legend(fontsize="small")
    return _save_figure_atomic(fig, out)


def plot_by(groups: Sequence[dict], out: str | os.PathLike, by: str, metric: str = "rmse") -> Path:
    """``metric`` per condition (or bin): one bar per group, error bars = seed std."""
    from matplotlib.figure import Figure

    columns, stats = by_column_stats(groups, by, metric)
    extra = _identity_columns(groups)
    fig = Figure(figsize=(min(16.0, 2.5 + 0.4 * len(columns) * max(1, len(groups))), 3.8))
    ax = fig.add_subplot()
    series = []
    for g, cells in zip(groups, stats, strict=True):
        row = [cells[c] for c in columns]
        heights = [np.nan if c is None else c[0] for c in row]
        series.append((" / ".join(_identity_cells(g, extra)), heights, _std_errors(row)))
    _grouped_bars(ax, columns, series)
    ax.set_title(f"{_metric_label(metric)} by {by} ({_direction(metric)})")
    ax.legend(fontsize="small")
    fig.set_layout_engine("constrained")
    return _save_figure_atomic(fig, out)


def plot_comparisons(comparisons: Sequence[Comparison], out: str | os.PathLike) -> Path:
    """Mean differences against the baseline with their bootstrap intervals as error bars."""
    from matplotlib.figure import Figure

    if not comparisons:
        raise ValueError("no comparisons to plot")
    columns = list(dict.fromkeys(col for c in comparisons for col in c.results))
    extra = _identity_columns([c.group for c in comparisons])
    fig = Figure(figsize=(min(16.0, 2.5 + 0.4 * len(columns) * max(1, len(comparisons))), 3.8))
    ax = fig.add_subplot()
    series = []
    for c in comparisons:
        results = [c.results.get(col) for col in columns]
        heights = [np.nan if r is None else r.mean for r in results]
        low = [0.0 if r is None else r.mean - r.low for r in results]
        high = [0.0 if r is None else r.high - r.mean for r in results]
        name = " / ".join(_identity_cells(c.group, extra))
        name += f" vs {_key_label(c.key, c.baseline[c.key])}"
        series.append((name, heights, np.array([low, high])))
    _grouped_bars(ax, columns, series)
    ax.axhline(0.0, color="black", linewidth=0.8)
    c0 = comparisons[0]
    ax.set_title(
        f"Δ{_metric_label(c0.metric)} vs baseline, {100 * c0.level:g}% CI ({_direction(c0.metric)})"
    )
    ax.legend(fontsize="small")
    fig.set_layout_engine("constrained")
    return _save_figure_atomic(fig, out)


# --- W&B: --wandb ------------------------------------------------------------------------------


def table_cells(csv_text: str) -> tuple[list[str], list[list[Any]]]:
    """Header and rows of a CSV table, numbers as floats, so W&B can sort and chart them."""

    def cell(text: str) -> Any:
        if text == "":
            return None
        try:
            return float(text)
        except ValueError:
            return text

    header, *rows = list(csv.reader(io.StringIO(csv_text)))
    return header, [[cell(c) for c in row] for row in rows]


def log_wandb(
    directory: str | os.PathLike, header: Sequence[str], rows: Sequence[Sequence]
) -> Path:
    """Log the table as a W&B Table in a ``report`` run named after the directory.

    Offline (synced later with ``wandb sync``) unless the user is logged in, like training runs.
    Returns the directory W&B wrote the run to.
    """
    import wandb

    from fusion_depth.loggers import wandb_logged_in

    directory = Path(directory)
    try:
        run = wandb.init(
            project="fusion-depth",
            job_type="report",
            name=directory.resolve().name,
            dir=str(directory),
            mode=None if wandb_logged_in() else "offline",
        )
        try:
            run.log({"report": wandb.Table(columns=list(header), data=[list(r) for r in rows])})
            run_dir = Path(run.dir).parent
        finally:
            run.finish()
    except wandb.errors.Error as err:
        raise ValueError(f"--wandb: could not log the table ({err})") from err
    return run_dir


def _compare_option(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or key not in COMPARE_KEYS or not value:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected KEY=VALUE with KEY one of {', '.join(COMPARE_KEYS)}, "
            "e.g. fusion=rgb"
        )
    return key, value


def _resamples_option(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a positive integer, e.g. 10000")
    return value


def _level_option(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a level in (0, 1), e.g. 0.95")
    return value


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m fusion_depth.report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("directory", help="a sweep (or any) directory holding metrics.json files")
    parser.add_argument("--format", choices=("markdown", "latex", "csv"), default="markdown")
    parser.add_argument(
        "--by",
        choices=tuple(BY_SECTIONS),
        help="columns: all, then each condition / distance bin / depth cap (one --metric)",
    )
    parser.add_argument(
        "--metric",
        help="metric of --by, --compare and plots (default rmse; plots: rmse, abs_rel, delta1)",
    )
    parser.add_argument(
        "--compare",
        type=_compare_option,
        metavar="KEY=VALUE",
        help="paired per-image comparison against the KEY=VALUE groups (KEY: fusion, loss, "
        "backbone), with bootstrap CIs",
    )
    parser.add_argument(
        "--resamples",
        type=_resamples_option,
        default=10000,
        help="bootstrap resamples of --compare (default 10000)",
    )
    parser.add_argument(
        "--level",
        type=_level_option,
        default=0.95,
        help="confidence level of --compare (default 0.95)",
    )
    parser.add_argument("--plot", metavar="OUT.png", help="also save the grid as a bar chart")
    parser.add_argument("--wandb", action="store_true", help="also log the table to W&B")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    metric = args.metric or "rmse"
    try:
        runs = load_runs(args.directory)
        if not runs:
            raise ValueError(f"{args.directory}: no metrics.json found below it")
        groups = group_runs(runs)
        comparisons = None
        if args.compare:
            key, value = args.compare
            comparisons = compare_groups(
                groups, key, value, metric, args.by, args.resamples, args.level
            )

        def render(fmt: str) -> str:
            if comparisons is not None:
                return build_comparison_table(comparisons, fmt)
            if args.by:
                return build_by_table(groups, args.by, metric, fmt)
            return build_table(groups, fmt)

        print(render(args.format))
        if args.plot:
            if comparisons is not None:
                plot_comparisons(comparisons, args.plot)
            elif args.by:
                plot_by(groups, args.plot, args.by, metric)
            else:
                plot_groups(groups, args.plot, [args.metric] if args.metric else PLOT_METRICS)
        if args.wandb:
            log_wandb(args.directory, *table_cells(render("csv")))
    except (FileNotFoundError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
