"""Summary tables of sweeps and batches as CSV and Markdown (same columns, same rows)."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from rngcam.untrusted import write_new


def format_value(value) -> str:
    """Numbers with 4 significant digits (seconds with 1 decimal), None as '-'."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else ""
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return f"{value:.4g}"
    return str(value)


def write_csv(path: Path, rows: list[dict], columns: list[str]) -> None:
    """Full-precision CSV, written atomically (never through a link planted at `path`)."""
    buf = io.StringIO(newline="")
    w = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore")
    w.writeheader()
    for row in rows:
        w.writerow({c: ("" if row.get(c) is None else row.get(c)) for c in columns})
    write_new(path, buf.getvalue())


def markdown(rows: list[dict], columns: list[str], formats: dict | None = None) -> str:
    """A GitHub Markdown table; `formats` maps a column to a function value -> str."""
    formats = formats or {}
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    for row in rows:
        cells = [formats.get(c, format_value)(row.get(c)) for c in columns]
        lines.append("| " + " | ".join(cell.replace("|", "/") for cell in cells) + " |")
    return "\n".join(lines) + "\n"


def write_text(path: Path, text: str) -> None:
    """Write a text file atomically (Markdown, JSON), never through a link planted at `path`."""
    write_new(path, text)
