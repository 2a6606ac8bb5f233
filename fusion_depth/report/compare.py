"""Paired per-image comparisons between groups of runs (``report --compare KEY=VALUE[,...]``):
the mean per-image difference with a hierarchical paired bootstrap interval, pairing runs by
seed.

The baseline is the group(s) with every ``KEY=VALUE`` given; every other group that differs from
a baseline only in those keys is compared with it. A model brings its own encoder and loss
(``model=<name>`` selects them), so when ``model`` is among the keys the groups may differ in
``backbone`` and ``loss`` too (``--compare model=densedepth,fusion=rgb``: every model and fusion
mode against DenseDepth RGB).
"""

from __future__ import annotations

import csv
import os
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from functools import reduce
from pathlib import Path

import numpy as np

from fusion_depth.metrics.bootstrap import BootstrapResult, paired_bootstrap
from fusion_depth.report.groups import (
    ALL,
    Parts,
    Preset,
    identity_cells,
    identity_columns,
    key_label,
    lay_out,
    put_first,
    tex_escape,
)
from fusion_depth.runner.protocol import protocol_differences
from fusion_depth.runner.record import RunRecord
from fusion_depth.runner.run_folder import PER_IMAGE_FILE

# --- Paired comparisons: --compare KEY=VALUE[,KEY=VALUE...] -----------------------------------

COMPARE_KEYS = ("fusion", "loss", "backbone", "model", "engine")
# Every identity field of a group, in the tables' order (a comparison holds all but its keys).
_GROUP_KEYS = ("dataset", "sensor", "model", "backbone", "fusion", "loss", "setting", "engine")
# What a model brings with it (its Recipe: fusion_depth.models.register_model).
_MODEL_PARTS = ("backbone", "loss")
# Settings a model brings as well: its prior (prior=, prior.*) and its fit (alignment.*), so that
# a model with a prior compares with DenseDepth without one under --compare model=...
_MODEL_SETTINGS = ("prior", "alignment")
# Protocol fields that change how per-image results are aggregated, not the results themselves.
_AGGREGATION_ONLY = {"distance_bins", "bin_width", "averaging"}


@dataclass(frozen=True)
class PerImage:
    """One metric of one run for each scored test image, sorted by the image's index."""

    path: Path
    index: np.ndarray  # int64, sorted, unique
    condition: np.ndarray  # str, aligned with index
    values: np.ndarray  # float64, aligned with index


def per_image_path(run: RunRecord) -> Path:
    """Where a run's ``per_image.csv`` is (``per_image_file`` is relative to metrics.json)."""
    return Path(run.path).parent / (run.per_image_file or PER_IMAGE_FILE)


_EXTRA = "\0extra"  # DictReader's key for fields beyond the header's


def _ends_with_newline(path: Path) -> bool:
    with path.open("rb") as f:
        f.seek(0, os.SEEK_END)
        if f.tell() == 0:
            return False
        f.seek(-1, os.SEEK_END)
        return f.read(1) == b"\n"


def load_per_image(run: RunRecord, metric: str) -> PerImage:
    """Read ``metric`` of every image from the run's per-image file, checking it on the way."""
    path = per_image_path(run)
    if not path.is_file():
        raise FileNotFoundError(
            f"{run.path}: its per-image results {path} are missing; --compare needs "
            f"{PER_IMAGE_FILE}, which runs of older versions did not write: re-score them with "
            f"python -m fusion_depth.evaluate ckpt_path=<sweep folder> and compare the output"
        )
    expected = (run.test or {}).get("num_images")  # check_scores: a finite number if there
    with path.open(newline="") as f:
        reader = csv.DictReader(f, restkey=_EXTRA, restval=None)
        missing = {"index", "condition", metric} - set(reader.fieldnames or ())
        if missing:
            raise ValueError(
                f"{path}: no column(s) {', '.join(sorted(missing))}; expected a header with "
                f"index, condition and the metric (have: {', '.join(reader.fieldnames or ())})"
            )
        rows = []
        for r in reader:
            if _EXTRA in r or None in r.values():
                raise ValueError(
                    f"{path}: line {reader.line_num}: expected {len(reader.fieldnames)} fields "
                    "(a cut or damaged file)"
                )
            try:
                rows.append((int(r["index"]), r["condition"], float(r[metric])))
            except (TypeError, ValueError) as err:
                raise ValueError(f"{path}: line {reader.line_num}: {err}") from err
            if expected is not None and len(rows) > expected:
                raise ValueError(
                    f"{path}: more rows than the {expected:g} images its {run.path.name} scored"
                )
    if not _ends_with_newline(path):
        raise ValueError(f"{path}: the last row is cut short (the file does not end a line)")
    if expected is not None and len(rows) != expected:
        raise ValueError(
            f"{path}: {len(rows)} rows, but its {run.path.name} scored {expected:g} images"
        )
    if len(rows) == 0:
        raise ValueError(f"{path}: no images")
    rows.sort()
    index = np.array([r[0] for r in rows], dtype=np.int64)
    values = np.array([r[2] for r in rows], dtype=np.float64)
    if (index < 0).any():
        raise ValueError(f"{path}: image index {int(index[0])} is not an index of the split")
    if (np.diff(index) == 0).any():
        dup = int(index[1:][np.diff(index) == 0][0])
        raise ValueError(f"{path}: image index {dup} appears more than once")
    if not np.isfinite(values).all():
        bad = int(index[~np.isfinite(values)][0])
        raise ValueError(f"{path}: {metric} of image {bad} is not finite")
    return PerImage(path, index, np.array([r[1] for r in rows], dtype=object), values)


def _check_same_images(ref: RunRecord, ref_pi: PerImage, run: RunRecord, pi: PerImage) -> None:
    """Refuse to pair runs scored on different images: their differences would mean nothing."""

    def refuse(reason: str) -> ValueError:
        return ValueError(
            f"{ref.path} and {run.path}: not scored on the same test images ({reason}); "
            "--compare pairs images by index, so both runs must use the same dataset, split "
            "and protocol"
        )

    for what, a, b in (
        ("dataset", ref.run.dataset, run.run.dataset),
        ("split", ref.split, run.split),
    ):
        if a != b:
            raise refuse(f"{what} {a!r} vs {b!r}")
    if ref.protocol is not None and run.protocol is not None:
        differences = protocol_differences(ref.protocol, run.protocol, _AGGREGATION_ONLY)
        if differences:
            key, a, b = differences[0]
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
    keys: tuple[str, ...]  # the compared identity fields, as given (``--compare``)
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

    @property
    def baseline_label(self) -> str:
        """The baseline as the tables name it: its values of the compared keys (``RGB``,
        ``DenseDepth / RGB``), with its backbone and loss where they differ from the group's."""
        parts = [
            key_label(k, self.baseline[k])
            for k in _GROUP_KEYS
            if k in self.keys
            or (k in _MODEL_PARTS and self.baseline[k] != self.group[k] and "model" in self.keys)
        ]
        return " / ".join(parts)


def _by_seed(group: dict) -> dict:
    """seed → run of a group; two runs with one seed cannot be paired unambiguously."""
    runs: dict = {}
    for run in group["runs"]:
        seed = run.run.seed
        if seed in runs:
            raise ValueError(
                f"{runs[seed].path} and {run.path}: two runs of one group with seed "
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
    load: Callable[[RunRecord, str], PerImage] = load_per_image,
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
        loaded[run.path] = pi = load(run, metric)
        _check_same_images(ref, ref_pi, run, pi)
    common = reduce(np.intersect1d, (pi.index for pi in loaded.values()))
    if len(common) < 2:
        raise ValueError(
            f"{ref.path} and {other_runs[0].path}: share {len(common)} scored test "
            "image(s); --compare needs at least 2"
        )

    def at_common(run: RunRecord) -> np.ndarray:
        pi = loaded[run.path]
        return pi.values[np.searchsorted(pi.index, common)]

    b = np.stack([at_common(r) for r in base_runs])
    o = np.stack([at_common(r) for r in other_runs])
    diff = o - b if seeds else o.mean(axis=0, keepdims=True) - b.mean(axis=0, keepdims=True)
    conditions = ref_pi.condition[np.searchsorted(ref_pi.index, common)]
    return diff, conditions, seeds


def _condition_columns(
    runs: Sequence[RunRecord], conditions: np.ndarray, first: Sequence[str] = ()
) -> list[str]:
    """``all``, then the conditions in the order the metrics files list them (those named in
    ``first`` first), then the rest."""
    order: dict[str, None] = {}
    for run in runs:
        order.update(dict.fromkeys(run.test_by_condition or {}))
    order.update(dict.fromkeys(conditions.tolist()))
    present = set(conditions.tolist())
    return put_first([ALL, *(c for c in order if c in present)], first)


def _varying_keys(keys: Sequence[str] | Mapping[str, str]) -> set[str]:
    """The identity fields a comparison over ``keys`` lets differ: the keys, and the backbone
    and loss with the model (a model brings its own encoder and loss)."""
    return {*keys, *(_MODEL_PARTS if "model" in keys else ())}


def _shared_parts(a: dict, b: dict) -> int:
    """How many of what a model brings (:data:`_MODEL_PARTS`) groups ``a`` and ``b`` share."""
    return sum(a[k] == b[k] for k in _MODEL_PARTS)


def compare_spec(baseline: Mapping[str, str]) -> str:
    """The ``--compare`` option naming ``baseline``: ``fusion=rgb``, ``model=densedepth,...``."""
    return ",".join(f"{k}={v}" for k, v in baseline.items())


def compare_groups(
    groups: Sequence[dict],
    key: str,
    value: str,
    metric: str = "rmse",
    by: str | None = None,
    resamples: int = 10000,
    level: float = 0.95,
) -> list[Comparison]:
    """Every group differing from a ``key=value`` group only in ``key``, against that group
    (:func:`compare_to_baseline` with one key)."""
    return compare_to_baseline(groups, {key: value}, metric, by, resamples, level)


def compare_to_baseline(
    groups: Sequence[dict],
    baseline: Mapping[str, str],
    metric: str = "rmse",
    by: str | None = None,
    resamples: int = 10000,
    level: float = 0.95,
    first: Sequence[str] = (),
) -> list[Comparison]:
    """Every group differing from a baseline group only in ``baseline``'s keys, against it.

    A baseline group has every ``key: value`` of ``baseline`` (e.g. ``{"model":
    "densedepth", "fusion": "rgb"}``); a group that has them all is a baseline, not compared.
    With ``model`` among the keys, ``backbone`` and ``loss`` count as part of the model (each
    model has its own encoder and loss), so a group may differ from its baseline in them too, and
    in the settings a model brings (its prior, ``prior=``, ``prior.*``, and its fit,
    ``alignment.*``; a baseline has none); a group matching several baselines is compared with
    those sharing most of its backbone and loss.

    Each comparison holds the mean per-image difference (other − baseline) and its bootstrap
    interval (:func:`fusion_depth.metrics.bootstrap.paired_bootstrap`), over all shared images and,
    with ``by="condition"``, over each condition's images (columns in ``first`` first).

    Raises:
        ValueError: a key that cannot be compared, no group with the baseline's values
            (naming the values there are), no group to compare, or runs that cannot be paired.
    """
    spec = compare_spec(baseline)
    _check_compare_request(groups, baseline, spec, by)
    by_model = "model" in baseline

    def is_baseline(g: dict) -> bool:  # under model=..., the model without a prior of its own
        plain = not by_model or _without_model_settings(g["setting"]) == g["setting"]
        return group_matches(g, baseline) and plain

    baselines = [g for g in groups if is_baseline(g)]
    if not baselines:
        have = "; ".join(sorted({",".join(f"{k}={g[k]}" for k in baseline) for g in groups}))
        raise ValueError(
            f"--compare {spec}: no runs with {' and '.join(spec.split(','))} (have: {have})"
        )
    varying = _varying_keys(baseline)
    identity = [k for k in _GROUP_KEYS if k not in varying]
    load = _cached_loader()
    keys = tuple(baseline)
    comparisons = []
    for g in groups:
        if is_baseline(g):
            continue
        for base in _closest_baselines(g, baselines, identity, by_model):
            diff, conditions, seeds = paired_differences(base, g, metric, load)
            columns = [ALL]
            if by == "condition":
                columns = _condition_columns([*base["runs"], *g["runs"]], conditions, first)
            results = _bootstrap_columns(diff, conditions, columns, resamples, level)
            comparisons.append(
                Comparison(g, base, keys, metric, seeds, diff.shape[1], level, results)
            )
    if not comparisons:
        raise ValueError(
            f"--compare {spec}: no other group differs from it only in "
            f"{' and '.join(k for k in _GROUP_KEYS if k in varying)} "
            f"(groups: {', '.join(_group_name(g) for g in groups)})"
        )
    return comparisons


def _check_compare_request(
    groups: Sequence[dict], baseline: Mapping[str, str], spec: str, by: str | None
) -> None:
    """Refuse a ``--compare`` with no or unknown keys, a bad ``--by``, or a value no group has."""
    if not baseline:
        raise ValueError("--compare: expected at least one KEY=VALUE, e.g. fusion=rgb")
    for key in baseline:
        if key not in COMPARE_KEYS:
            raise ValueError(f"--compare {spec}: expected KEY one of {', '.join(COMPARE_KEYS)}")
    if by not in (None, "condition"):
        raise ValueError(
            f"--by {by} with --compare: {PER_IMAGE_FILE} has no {by} per image; use --by condition"
        )
    for key, value in baseline.items():
        if not any(g[key] == value for g in groups):
            have = ", ".join(sorted({str(g[key]) for g in groups}))
            raise ValueError(f"--compare {spec}: no runs with {key}={value} (have: {have})")


def group_matches(group: dict, values: Mapping[str, str]) -> bool:
    """Whether ``group`` (:func:`~fusion_depth.report.groups.group_runs`) has every
    ``key: value`` of ``values`` (``--compare``'s baseline, or the runs ``--where`` keeps)."""
    return all(group[k] == v for k, v in values.items())


def _without_model_settings(setting: str) -> str:
    """A group's ``setting`` less the overrides a model brings (:data:`_MODEL_SETTINGS`)."""
    return " ".join(
        o
        for o in setting.split()
        if o.split("=", 1)[0].lstrip("+~").split(".", 1)[0] not in _MODEL_SETTINGS
    )


def _closest_baselines(
    group: dict, baselines: Sequence[dict], identity: Sequence[str], by_model: bool = False
) -> list[dict]:
    """Baselines equal to ``group`` in ``identity`` sharing most of its backbone and loss;
    ``by_model``: the settings a model brings (its prior and its fit) may differ too."""

    def value(g: dict, key: str) -> object:
        return _without_model_settings(g[key]) if by_model and key == "setting" else g[key]

    matching = [b for b in baselines if all(value(b, k) == value(group, k) for k in identity)]
    # Of the baselines a group may be paired with, those sharing most of what a model
    # brings (its encoder and loss): a model's own loss variant pairs with the same loss.
    closest = max((_shared_parts(b, group) for b in matching), default=0)
    return [b for b in matching if _shared_parts(b, group) == closest]


def _cached_loader() -> Callable[[RunRecord, str], PerImage]:
    """:func:`load_per_image`, reading each run's metric once (a baseline pairs many groups)."""
    cache: dict[tuple[Path | None, str], PerImage] = {}

    def load(run: RunRecord, metric: str) -> PerImage:
        if (run.path, metric) not in cache:
            cache[run.path, metric] = load_per_image(run, metric)
        return cache[run.path, metric]

    return load


def _bootstrap_columns(
    diff: np.ndarray,
    conditions: np.ndarray,
    columns: Sequence[str],
    resamples: int,
    level: float,
) -> dict[str, BootstrapResult | None]:
    """Each column's paired bootstrap of ``diff`` (None where it has fewer than 2 images)."""
    results: dict[str, BootstrapResult | None] = {}
    for column in columns:
        d = diff if column == ALL else diff[:, conditions == column]
        results[column] = (
            paired_bootstrap(d, resamples=resamples, level=level) if d.shape[1] >= 2 else None
        )
    return results


def _group_name(group: dict) -> str:
    parts = [
        group[k] for k in ("dataset", "model", "backbone", "loss", "fusion", "setting", "engine")
    ]
    return "/".join(str(p) for p in parts if p)


def comparison_identity_columns(
    comparisons: Sequence[Comparison], show: Collection[str] = ()
) -> list[tuple[str, str]]:
    """The identity columns naming compared groups: those that vary, those in ``show``, a
    compared model with its encoder and a compared engine (as Modality and Loss are always
    named)."""
    models = [k for c in comparisons if "model" in c.keys for k in _varying_keys(c.keys)]
    engines = ["engine" for c in comparisons if "engine" in c.keys]
    return identity_columns([c.group for c in comparisons], {*show, *models, *engines})


def csv_cells(result: BootstrapResult | None) -> list[str]:
    """A comparison's CSV cells: mean difference, interval bounds, significant (yes/no); empty
    when too few images were shared to compute it."""
    if result is None:
        return ["", "", "", ""]
    return [
        f"{result.mean:.6g}",
        f"{result.low:.6g}",
        f"{result.high:.6g}",
        "yes" if result.excludes_zero else "no",
    ]


def _interval_text(preset: Preset, metric: str, result: BootstrapResult) -> str:
    """``+mean [+low, +high]`` in the preset's units and decimals (:meth:`Preset.decimals`)."""
    mean, low, high = (preset.value(metric, v) for v in (result.mean, result.low, result.high))
    p = preset.decimals(metric)  # whole millimetres, else 3
    return f"{mean:+.{p}f} [{low:+.{p}f}, {high:+.{p}f}]"


def build_comparison_table(
    comparisons: Sequence[Comparison],
    fmt: str = "markdown",
    show: Collection[str] = (),
    preset: Preset | None = None,
) -> str:
    """Mean per-image difference and CI per compared group; significant cells are marked.

    A cell is significant (bold, and listed in the ``Significant`` column) when its interval
    excludes 0. The sign is other − baseline: negative is better for errors, positive for δ.
    The columns are laid out by :func:`~fusion_depth.report.groups.lay_out`: what a row is and
    its Baseline, the differences and Significant, then Seeds (the pairing) and Images (CSV:
    Seeds and Images before the differences).
    ``show``: identity columns to show even when every compared group has the same value;
    ``preset``: the units of the cells (:func:`~fusion_depth.report.groups.runs_preset`; CSV
    keeps the recorded units).
    """
    if not comparisons:
        raise ValueError("no comparisons to tabulate")
    preset = preset or Preset()
    columns = list(dict.fromkeys(col for c in comparisons for col in c.results))
    metric, level = comparisons[0].metric, comparisons[0].level
    extra = comparison_identity_columns(comparisons, show)
    latex = fmt == "latex"
    if fmt == "csv":
        measured = [
            f"{metric}_{col}_{part}"
            for col in columns
            for part in ("diff", "low", "high", "significant")
        ]
        measured.append("level")
    else:
        label = ("$\\Delta$" if latex else "Δ") + preset.label(metric, latex)
        pct = f"{100 * level:g}\\%" if latex else f"{100 * level:g}%"
        measured = [f"{label} ({tex_escape(c) if latex else c}, {pct} CI)" for c in columns]
        measured.append("Significant")
    rows: list[Parts] = []
    bold = set()
    for i, c in enumerate(comparisons):
        naming = identity_cells(c.group, extra, full=fmt != "markdown") + [c.baseline_label]
        cells, significant = [], []
        for j, column in enumerate(columns):
            r = c.results.get(column)
            if r is not None and r.excludes_zero:
                significant.append(column)
                bold.add((i, j))
            if fmt == "csv":
                cells += csv_cells(r)
            else:
                cells.append("–" if r is None else _interval_text(preset, metric, r))
        if fmt == "csv":
            cells.append(f"{level:g}")
        elif columns == [ALL]:
            cells.append("yes" if significant else "no")
        else:
            cells.append(", ".join(significant) or "none")
        rows.append((naming, [c.pairing, str(c.num_images)], cells))
    naming = [name for name, _ in extra] + ["Modality", "Loss", "Baseline"]
    return lay_out(fmt, (naming, ["Seeds", "Images"], measured), rows, bold)
