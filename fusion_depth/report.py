"""The paper-style table of a sweep: ``python -m fusion_depth.report multirun/<date>/<time>``.

Reads every ``metrics.json`` below a directory, averages runs that differ only in their seed
(mean ± sample std), marks the best value of each column, and prints Markdown, LaTeX or CSV.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections.abc import Sequence

from fusion_depth.runs import load_runs

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
            }
        )
    return result


def format_table(
    header: Sequence[str],
    rows: Sequence[Sequence[str]],
    fmt: str = "markdown",
    bold: set[tuple[int, int]] | frozenset = frozenset(),
) -> str:
    """Render string cells as Markdown, LaTeX or CSV; ``bold`` holds (row, column) indices."""
    if fmt == "csv":
        import csv
        import io

        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow(header)
        writer.writerows(rows)
        return out.getvalue().rstrip("\n")
    if fmt == "markdown":
        cells = [
            [f"**{c}**" if (i, j) in bold else c for j, c in enumerate(row)]
            for i, row in enumerate(rows)
        ]
        widths = [max(len(x) for x in col) for col in zip(header, *cells, strict=True)]

        def line(row: Sequence[str]) -> str:
            return "| " + " | ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)) + " |"

        sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
        return "\n".join([line(header), sep, *(line(r) for r in cells)])
    if fmt == "latex":

        def tex(cell: str) -> str:
            return cell.replace("±", r"$\pm$").replace("_", r"\_")

        cells = [
            [rf"\textbf{{{tex(c)}}}" if (i, j) in bold else tex(c) for j, c in enumerate(row)]
            for i, row in enumerate(rows)
        ]
        body = [
            " & ".join(header) + r" \\",
            r"\hline \hline",
            *(" & ".join(r) + r" \\" for r in cells),
        ]
        return "\n".join(
            [r"\begin{tabular}{" + "l" * len(header) + "}", *body, r"\hline", r"\end{tabular}"]
        )
    raise ValueError(f"format={fmt!r}: expected one of markdown, latex, csv")


def build_table(groups: Sequence[dict], fmt: str = "markdown") -> str:
    """The paper's table (Modality, Loss, RMSE, ARD, SRD, δ1–δ3) for grouped runs."""
    if not groups:
        raise ValueError("no runs to tabulate")
    extra = [
        (name, key)
        for name, key in (
            ("Dataset", "dataset"),
            ("Sensor", "sensor"),
            ("Backbone", "backbone"),
            ("Setting", "setting"),
        )
        if len({g[key] for g in groups}) > 1
    ]
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
        row = [g[key] for _, key in extra]
        row += [MODALITY.get(g["fusion"], g["fusion"]), LOSS.get(g["loss"], g["loss"])]
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


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m fusion_depth.report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("directory", help="a sweep (or any) directory holding metrics.json files")
    parser.add_argument("--format", choices=("markdown", "latex", "csv"), default="markdown")
    args = parser.parse_args(argv)
    try:
        runs = load_runs(args.directory)
        if not runs:
            raise ValueError(f"{args.directory}: no metrics.json found below it")
        print(build_table(group_runs(runs), args.format))
    except (FileNotFoundError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
