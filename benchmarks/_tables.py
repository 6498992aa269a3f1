"""What the grid benchmarks share (imported by them, not run): one row per run as a rich
table and as CSV."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console
from rich.table import Table


def format_value(value: object) -> str:
    """A float to 3 significant digits (NaN: a dash); anything else as it prints."""
    if isinstance(value, float):
        return "—" if math.isnan(value) else f"{value:.3g}"
    return str(value)


def print_table(
    console: Console, rows: list[dict], columns: Sequence[str], title: str, left: Sequence[str] = ()
) -> None:
    """One line per row; the ``left`` columns left-aligned, the others right-aligned."""
    table = Table(title=title)
    for column in columns:
        table.add_column(column, justify="left" if column in left else "right")
    for row in rows:
        table.add_row(*(format_value(row[c]) for c in columns))
    console.print(table)


def write_csv(path: Path, rows: list[dict], columns: Sequence[str]) -> None:
    """One line per row, the table's columns."""
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(columns))
        writer.writeheader()
        writer.writerows(rows)
