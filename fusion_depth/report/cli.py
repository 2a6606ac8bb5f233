"""The paper-style table of a sweep: ``python -m fusion_depth.report multirun/<sweep>``.

Reads every ``metrics.json`` below a directory, averages runs that differ only in their seed
(mean ± sample std), marks the best value of each column, and prints Markdown, LaTeX or CSV.

Runs are grouped by dataset, sensor, model, backbone, loss, fusion mode and other overrides;
a Model column (the model table's labels: DenseDepth, Sparse-to-Dense, ...) appears when the
runs hold several models.

Options:
  --format {markdown,latex,csv}  how to print the table (default markdown).
  --by {condition,distance,cap}  one metric (``--metric``) per condition, distance bin or depth
                                 cap: columns ``all`` then each of them, mean ± std over seeds.
  --by model                     per model: the ``--by condition`` table with a Model column
                                 (night and fog first), then the paired differences (as
                                 --compare, per condition) of each model against DenseDepth
                                 (the runs' first model if none is DenseDepth) with the same
                                 fusion mode and loss, or against the --compare baseline (e.g.
                                 model=densedepth,fusion=rgb). As CSV, one table (see
                                 :mod:`fusion_depth.report.by_model`).
  --metric KEY                   the metric of --by, --compare and a --by plot (default rmse;
                                 any key of the metrics: abs_rel, delta1, mae, ...).
  --compare KEY=VALUE[,...]      e.g. ``fusion=rgb``: every group that differs from a VALUE group
                                 only in KEY (fusion, loss, backbone, model or engine: an
                                 exported model's, ``engine=torch`` pairs each with its
                                 checkpoint) is compared with it image by image: mean of
                                 the per-image differences (other − baseline, so negative
                                 is better for errors) with a paired bootstrap CI, pairing
                                 runs by seed. ``Significant`` says whether
                                 the CI excludes 0 (such cells are bold). With ``--by
                                 condition``, also per condition. Several pairs
                                 (``model=densedepth,fusion=rgb``): the baseline has them all, and
                                 groups may differ from it in all those keys. With ``model``, a
                                 group may differ in backbone and loss too (each model has its
                                 own). Needs each run's ``per_image.csv``.
  --where KEY=VALUE[,...]        keep only the runs with these values (same KEYs as --compare),
                                 e.g. ``fusion=rgb,model=densedepth``: one configuration of a
                                 sweep, its seeds. A value no run has is refused, naming those
                                 the runs have.
  --first COL[,COL...]           put these --by columns first, after ``all`` (e.g. night,fog;
                                 --by model's default); each must be a column of the runs.
  --resamples N                  bootstrap resamples of --compare (default 10000).
  --level L                      confidence level of --compare's intervals (default 0.95).
  --plot OUT.png                 also save a bar chart (any Matplotlib format: .png, .pdf, .svg):
                                 one subplot per metric (RMSE, ARD, δ1, or --metric) with a bar
                                 per fusion mode over each loss; with --by, --metric per column;
                                 with --compare (and --by model), the differences with their
                                 CIs. Error bars are the std over seeds (none for a single seed).
                                 An SVG, PNG or PDF carries the command and the plotted values
                                 in its metadata, and repeats byte for byte on the same
                                 Matplotlib.
  --output FILE                  also write the table to FILE (atomically), headed by a comment
                                 that names the command (Markdown ``<!-- -->``, LaTeX ``%``;
                                 CSV has no header line): a table a docs page includes, made
                                 from run records rather than typed.
  --bench {speed,engines,prepare}
                                 tabulate the ``bench.json`` files below the directory (what
                                 ``python -m fusion_depth.bench --json`` writes) instead of the
                                 metrics: ``speed``, a row per record's run (and its eager fp32
                                 baseline and speed-ups); ``engines``, a row per engine of each
                                 record run with ``--engines``; ``prepare``, a row per fill
                                 method of each record run with ``--only prepare``. Rows are
                                 led by the record's folder and what it measured. ``--plot``
                                 draws latency and samples/s (speed) or latency per engine,
                                 median to p95 (engines); prepare has no figure. Not with --by,
                                 --compare, --metric, --first or --wandb.
  --panels OUT.png               instead of a table, draw the test panels of the one run recorded
                                 below the directory (its ``test_panels.npz``: image, sparse
                                 input, prediction, ground truth and error per test frame) as a
                                 PNG that carries the command in its metadata: the docs'
                                 pictures. Alone, with no other option.
  --mixed-formats                report runs of one dataset whose frames were prepared by
                                 different format versions (the dataset reader's
                                 format_version, recorded in metrics.json's run; a record
                                 without it is unknown), with a note naming them on stderr.
                                 Refused by default: nuScenes' placement change (format 3) moved
                                 RMSE by up to 3.5 %.
  --published                    a released model's records (evaluate released=<name>) beside
                                 the numbers its paper prints, per depth cap: MAE and RMSE in
                                 mm, ours, published and the difference, with the source
                                 (:mod:`fusion_depth.report.published`).
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
import shlex
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from fusion_depth.report.bench import BENCH_TABLES, build_bench_table
from fusion_depth.report.by_model import (
    BY_MODEL,
    SECTION,
    build_model_report,
    default_baseline,
)
from fusion_depth.report.compare import (
    COMPARE_KEYS,
    build_comparison_table,
    compare_to_baseline,
    group_matches,
)
from fusion_depth.report.groups import (
    BY_SECTIONS,
    HARD_CONDITIONS,
    build_by_table,
    build_table,
    check_format_versions,
    column_keys,
    group_runs,
    runs_preset,
)
from fusion_depth.report.output import (
    check_plot_target,
    check_target,
    generated_table_file,
    naming_a_full_disk,
    write_output,
)
from fusion_depth.report.panels import draw_recorded_panels
from fusion_depth.report.plots import (
    PLOT_METRICS,
    plot_by,
    plot_comparisons,
    plot_engine_latency,
    plot_groups,
    plot_speed,
)
from fusion_depth.report.published import build_published_table
from fusion_depth.runner.bench_record import BENCH_FILE, load_bench_records
from fusion_depth.runner.record import METRICS_FILE, load_runs

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

    from fusion_depth.runner.loggers import wandb_logged_in

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


def _compare_option(text: str) -> dict[str, str]:
    """``fusion=rgb`` or ``model=densedepth,fusion=rgb`` → key → value (of ``--compare``'s
    baseline, or of the runs ``--where`` keeps)."""
    baseline: dict[str, str] = {}
    for pair in text.split(","):
        key, sep, value = pair.partition("=")
        if not sep or key not in COMPARE_KEYS or not value:
            raise argparse.ArgumentTypeError(
                f"{text!r}: expected KEY=VALUE with KEY one of {', '.join(COMPARE_KEYS)}, "
                "e.g. fusion=rgb (several separated by commas: model=densedepth,fusion=rgb)"
            )
        if key in baseline:
            raise argparse.ArgumentTypeError(f"{text!r}: {key} given twice")
        baseline[key] = value
    return baseline


def _first_option(text: str) -> tuple[str, ...]:
    """``night,fog`` → the column names."""
    names = tuple(n for n in text.split(",") if n)
    if not names:
        raise argparse.ArgumentTypeError(f"{text!r}: expected column names, e.g. night,fog")
    return names


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
        choices=(*BY_SECTIONS, BY_MODEL),
        help="columns: all, then each condition / distance bin / depth cap (one --metric); "
        "model: per model and condition, with paired differences against DenseDepth",
    )
    parser.add_argument(
        "--metric",
        help="metric of --by, --compare and plots (default rmse; plots: rmse, abs_rel, delta1)",
    )
    parser.add_argument(
        "--compare",
        type=_compare_option,
        metavar="KEY=VALUE[,...]",
        help="paired per-image comparison against the KEY=VALUE groups (KEY: fusion, loss, "
        "backbone, model; several separated by commas), with bootstrap CIs",
    )
    parser.add_argument(
        "--where",
        type=_compare_option,
        metavar="KEY=VALUE[,...]",
        help="keep only the runs with these values (KEY as --compare), e.g. fusion=rgb",
    )
    parser.add_argument(
        "--first",
        type=_first_option,
        metavar="COL[,...]",
        help="put these --by columns first (after all), e.g. night,fog (--by model's default)",
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
    parser.add_argument(
        "--bench",
        choices=BENCH_TABLES,
        help="tabulate the bench.json records below the directory (bench --json) instead: "
        "speed (latency, samples/s, speed-ups), engines (latency per engine) or prepare (fill "
        "time per frame and hours per split)",
    )
    parser.add_argument(
        "--time",
        action="store_true",
        help="the plain table (no --by or --compare) with each group's training wall time",
    )
    parser.add_argument("--plot", metavar="OUT.png", help="also save the grid as a bar chart")
    parser.add_argument(
        "--output",
        metavar="FILE",
        help="also write the table to FILE, headed by the command that made it",
    )
    parser.add_argument(
        "--panels",
        metavar="OUT.png",
        help="instead of a table, draw the recorded test panels of the run below the directory",
    )
    parser.add_argument(
        "--mixed-formats",
        action="store_true",
        help="report runs of one dataset whose frames were prepared by different format "
        "versions (refused by default), with a note naming them",
    )
    parser.add_argument("--wandb", action="store_true", help="also log the table to W&B")
    return _add_tables(parser)


def _add_tables(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options that choose another table than the grid of the runs."""
    parser.add_argument(
        "--published",
        action="store_true",
        help="a released model's scores beside its paper's, per depth cap, with the difference "
        "(fusion_depth/report/published.py)",
    )
    return parser


def _check_first(runs: Sequence[Any], section: str | None, first: Sequence[str]) -> None:
    """Refuse a ``--first`` column the runs do not have (or ``--first`` without ``--by``)."""
    if section is None:
        raise ValueError("--first orders the --by columns; give --by too")
    have = column_keys(runs, section)
    unknown = [c for c in first if c not in have]
    if unknown:
        raise ValueError(
            f"--first {','.join(first)}: no {section} {unknown[0]!r} (have: {', '.join(have[1:])})"
        )


def select_groups(groups: Sequence[dict], where: Mapping[str, str]) -> list[dict]:
    """The groups (:func:`group_runs`) whose identity has every ``key=value`` of ``where``.

    Raises:
        ValueError: no group has them; names the values the groups have for each key.
    """
    kept = [g for g in groups if group_matches(g, where)]
    if not kept:
        have = "; ".join(f"{k}: {', '.join(sorted({str(g[k]) for g in groups}))}" for k in where)
        spec = ",".join(f"{k}={v}" for k, v in where.items())
        raise ValueError(f"--where {spec}: no run has it (the runs have {have})")
    return kept


def command_line(argv: Sequence[str]) -> str:
    """The command a generated table or figure names: ``python -m fusion_depth.report ...``,
    quoted so that it pastes back into a shell."""
    return shlex.join(["python", "-m", "fusion_depth.report", *argv])


def generated_table(table: str, fmt: str, argv: Sequence[str]) -> str:
    """``table`` headed by a comment naming the command that made it (``--output``): a Markdown
    or LaTeX file a page includes says how to make it again. CSV gets no header line."""
    command = command_line(argv)
    if fmt == "markdown":
        return f"<!-- generated by: {command} -->\n\n{table}\n"
    if fmt == "latex":
        return f"% generated by: {command}\n{table}\n"
    return f"{table}\n"


def _bench_report(args: argparse.Namespace, argv: Sequence[str]) -> None:
    """``--bench``: the table (and figure) of the bench records below ``args.directory``."""
    if args.plot and args.bench == "prepare":
        raise ValueError("--plot: the prepare table has no figure")
    records = load_bench_records(args.directory)
    if not records:
        raise ValueError(f"{args.directory}: no {BENCH_FILE} found below it")
    table = build_bench_table(records, args.bench, args.format)
    print(table)
    if args.output:
        write_output(args.output, generated_table(table, args.format, argv))
    if args.plot:
        plot = plot_speed if args.bench == "speed" else plot_engine_latency
        with naming_a_full_disk(args.plot):
            plot(records, args.plot, command_line(argv))


def _check_targets(args: argparse.Namespace) -> None:
    """Refuses an ``--output`` or ``--plot`` target report may not write (:mod:`.output`)
    before any work is done; a CSV's header row is checked when the table exists."""
    if args.output:
        check_target(
            args.output, "--output", None if args.format == "csv" else generated_table_file
        )
    if args.plot:
        check_plot_target(args.plot)


def _plot(
    args: argparse.Namespace,
    groups: Sequence[dict],
    comparisons: Any,
    section: str | None,
    metric: str,
    first: Sequence[str],
    preset: Any,
    argv: Sequence[str],
) -> None:
    """``--plot``: the figure of the table just printed (a full disk names the file)."""
    command = command_line(argv)
    with naming_a_full_disk(args.plot):
        if comparisons:
            plot_comparisons(comparisons, args.plot, command, preset)
        elif section:
            plot_by(groups, args.plot, section, metric, first, command, preset)
        else:
            metrics = [args.metric] if args.metric else PLOT_METRICS
            plot_groups(groups, args.plot, metrics, command, preset)


def _panels_report(
    parser: argparse.ArgumentParser, args: argparse.Namespace, argv: Sequence[str]
) -> int:
    """``--panels``: the recorded test panels drawn again; the exit status."""
    others = [a for a in argv if a.startswith("--") and a.split("=")[0] != "--panels"]
    if others:
        parser.error(f"--panels draws a recorded figure; {others[0]} is for tables")
    try:
        print(draw_recorded_panels(args.directory, args.panels, command_line(argv)))
    except (OSError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _parser()
    args = parser.parse_args(argv)
    if args.panels:
        return _panels_report(parser, args, argv)
    if args.bench:
        metrics_only = ("by", "compare", "where", "metric", "first", "mixed_formats", "wandb")
        given = [f"--{k}" for k in metrics_only if getattr(args, k)]
        if given:
            given = given[0].replace("_", "-")
            parser.error(f"--bench tabulates bench records; {given} is for metrics records")
        try:
            _check_targets(args)
            _bench_report(args, argv)
        except (OSError, ValueError) as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        return 0
    if args.time and (args.by or args.compare):
        parser.error("--time adds a column to the plain table; leave out --by and --compare")
    if args.published and (args.by or args.compare or args.time or args.plot):
        parser.error("--published is a table of its own; leave out --by, --compare, --time, --plot")
    metric = args.metric or "rmse"
    by_model = args.by == BY_MODEL
    section = SECTION if by_model else args.by  # the metrics.json breakdown of the columns
    try:
        _check_targets(args)
        runs = load_runs(args.directory)
        if not runs:
            raise ValueError(f"{args.directory}: no {METRICS_FILE} found below it")
        groups = group_runs(runs)
        if args.where:
            groups = select_groups(groups, args.where)
            runs = [run for group in groups for run in group["runs"]]
        note = check_format_versions(runs, args.mixed_formats)
        if note:
            print(note, file=sys.stderr)
        if args.first:
            _check_first(runs, section, args.first)
        first = args.first or (HARD_CONDITIONS if by_model else ())
        preset = runs_preset(runs)
        baseline = args.compare or (default_baseline(groups) if by_model else None)
        comparisons = None
        if baseline:
            comparisons = compare_to_baseline(
                groups, baseline, metric, section, args.resamples, args.level, first
            )
        elif by_model:
            print(
                "note: --by model: the runs hold one model, so there are no differences "
                "between models",
                file=sys.stderr,
            )

        def render(fmt: str) -> str:
            if args.published:
                return build_published_table(runs, fmt)
            if by_model:
                return build_model_report(groups, comparisons, metric, fmt, first, preset)
            if comparisons is not None:
                return build_comparison_table(comparisons, fmt, preset=preset)
            if args.by:
                return build_by_table(groups, args.by, metric, fmt, first=first, preset=preset)
            return build_table(groups, fmt, preset, time=args.time)

        table = render(args.format)
        print(table)
        if args.output:
            write_output(args.output, generated_table(table, args.format, argv))
        if args.plot:
            _plot(args, groups, comparisons, section, metric, first, preset, argv)
        if args.wandb:
            log_wandb(args.directory, *table_cells(render("csv")))
    except (OSError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0
