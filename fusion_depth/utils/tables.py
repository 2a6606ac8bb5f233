"""Tables as text: Markdown, LaTeX or CSV, for the metric tables every command prints and for
``report``."""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence


def format_table(
    header: Sequence[str],
    rows: Sequence[Sequence[str]],
    fmt: str = "markdown",
    bold: set[tuple[int, int]] | frozenset = frozenset(),
) -> str:
    """Render string cells as Markdown, LaTeX or CSV; ``bold`` holds (row, column) indices."""
    if fmt == "csv":
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
