"""Tables `sim` prints: rich boxes on a terminal, plain aligned text anywhere else.

Piped into a file or another program (or read back by a test), a box-drawn table wraps its
cells at the console width and fills the output with box characters; plain text columns
separated by two spaces stay aligned at any width and grep well.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import IO, Any

# rich styles of cells whose whole text is one of these (on a terminal only)
CELL_STYLES = {"PASS": "green", "FAIL": "bold red", "n/a": "yellow"}


def render_plain(
    title: str, columns: Sequence[str], rows: Sequence[Sequence[str]], *, left: int = 0
) -> str:
    """The table as plain text: a title line, a header, a rule, the rows; the first ``left``
    columns flush left, the others flush right (numbers)."""
    widths = [len(c) for c in columns]
    for row in rows:
        widths = [max(w, len(cell)) for w, cell in zip(widths, row, strict=True)]

    def line(cells: Sequence[str]) -> str:
        parts = [
            cell.ljust(w) if i < left else cell.rjust(w)
            for i, (cell, w) in enumerate(zip(cells, widths, strict=True))
        ]
        return "  ".join(parts).rstrip()

    out = [title, line(columns), "  ".join("-" * w for w in widths)]
    out += [line(r) for r in rows]
    return "\n".join(out)


def print_table(
    title: str,
    columns: Sequence[str],
    rows: Sequence[Sequence[str]],
    *,
    left: int = 0,
    file: IO[str] | None = None,
    min_width: int = 0,
) -> None:
    """Rich table on a TTY (at least ``min_width`` columns wide), plain text otherwise."""
    out = file if file is not None else sys.stdout
    if not out.isatty():
        print(render_plain(title, columns, rows, left=left), file=out)
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title)
    for i, col in enumerate(columns):
        table.add_column(col, justify="left" if i < left else "right")
    for row in rows:
        cells: list[Any] = [
            f"[{CELL_STYLES[c]}]{c}[/{CELL_STYLES[c]}]" if c in CELL_STYLES else c for c in row
        ]
        table.add_row(*cells)
    console = Console(file=out)
    if min_width:
        console = Console(file=out, width=max(console.width, min_width))
    console.print(table)


def format_metric(metric: str, value: float | None) -> str:
    """A target metric in the unit people read it in: errors in cm, speeds in m/s."""
    if value is None:
        return "-"
    if metric in ("rmse_m", "max_error_m", "mean_error_m"):
        return f"{value * 100.0:.2f} cm"
    if metric == "max_speed_m_s":
        return f"{value:.2f} m/s"
    if metric == "constraint_violations":
        return f"{value:.0f}"
    return f"{value:.4g}"
