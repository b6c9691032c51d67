"""Result tables: results.csv (every column) and a Markdown table (chosen columns)."""

from __future__ import annotations

import csv
import math
from pathlib import Path


def columns_of(rows: list[dict], first: list[str] | None = None) -> list[str]:
    """`first` (those present), then every other key in order of appearance."""
    keys: list[str] = []
    for row in rows:
        keys += [k for k in row if k not in keys]
    head = [k for k in (first or []) if k in keys]
    return head + [k for k in keys if k not in head]


def write_csv(path: Path, rows: list[dict], first: list[str] | None = None) -> None:
    """One line per row; missing values are empty."""
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns_of(rows, first), restval="")
        writer.writeheader()
        writer.writerows(rows)


def fmt(value, digits: int = 3) -> str:
    """A table cell: floats to `digits` significant digits, NaN and None as '-'."""
    if value is None or value == "":
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if math.isnan(value):
            return "-"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return f"{value:.{digits}g}"
    return str(value).replace("|", "/").replace("\n", " ")


def markdown_table(rows: list[dict], columns: list[str], headers: dict[str, str] | None = None) -> str:
    """A GitHub Markdown table of `columns` (renamed by `headers`)."""
    headers = headers or {}
    lines = ["| " + " | ".join(headers.get(c, c) for c in columns) + " |",
             "|" + "|".join("---" for _ in columns) + "|"]
    for row in rows:
        lines.append("| " + " | ".join(fmt(row.get(c)) for c in columns) + " |")
    return "\n".join(lines)
