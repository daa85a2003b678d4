"""Plain-text and CSV tables of result rows (the summaries printed by commands, scripts and benchmarks)."""

from __future__ import annotations

import csv
import io
import math
from typing import Any


def format_table(rows: list[dict[str, Any]], columns: list[str] | None = None) -> str:
    """A plain-text table (the summary printed at the end of a run and saved beside its results)."""
    if not rows:
        return "(no rows)"
    columns = columns or list(rows[0].keys())

    def cell(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    cells = [[cell(r.get(c, "")) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    line = "  ".join(c.ljust(w) for c, w in zip(columns, widths))
    sep = "  ".join("-" * w for w in widths)
    body = ["  ".join(v.ljust(w) for v, w in zip(row, widths)) for row in cells]
    return "\n".join([line, sep, *body])


def csv_text(rows: list[dict[str, Any]], columns: list[str]) -> str:
    """The rows as CSV text with a header line (missing cells, NaN and infinities empty; floats 4 decimals)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for r in rows:
        writer.writerow([_csv_cell(r.get(c, "")) for c in columns])
    return buf.getvalue()


def _csv_cell(value: Any) -> Any:
    """Floats with 4 decimals, NaN and infinities empty."""
    if isinstance(value, float):
        return f"{value:.4f}" if math.isfinite(value) else ""
    return value


__all__ = ["csv_text", "format_table"]
