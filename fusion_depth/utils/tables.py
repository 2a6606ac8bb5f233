"""Tables as text: Markdown, LaTeX or CSV, for the metric tables every command prints and for
``report``."""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence

# A cell starting with one of these is a formula to a spreadsheet (OWASP, "CSV Injection").
_FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


def csv_safe(cell: str) -> str:
    """``cell`` as a spreadsheet shows it, never runs it: a cell starting with ``=``, ``+``,
    ``-``, ``@``, a tab or a carriage return gets a leading ``'`` (OWASP's advice on CSV
    injection), unless it is a number (``-0.003`` stays a number)."""
    if not cell.startswith(_FORMULA_STARTS):
        return cell
    try:
        float(cell)
    except ValueError:
        return "'" + cell
    return cell


def format_table(
    header: Sequence[str],
    rows: Sequence[Sequence[str]],
    fmt: str = "markdown",
    bold: set[tuple[int, int]] | frozenset = frozenset(),
) -> str:
    """Render string cells as Markdown, LaTeX or CSV; ``bold`` holds (row, column) indices.
    CSV cells that a spreadsheet would run as a formula are neutralised (:func:`csv_safe`)."""
    if fmt == "csv":
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow([csv_safe(c) for c in header])
        writer.writerows([csv_safe(c) for c in row] for row in rows)
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
