"""A batch's summary across sequences: the rows (frames, frames/s, L1 mean/median/p90, ATE per sequence, or per
sequence and method for comparisons), written as ``OUT/summary.csv`` and as ``OUT/index.html``, a page that links
each sequence's report (``summary.txt`` of a reconstruction, ``report.html`` of a comparison) and each failure's
log."""

from __future__ import annotations

import html
import os
from pathlib import Path

from mapping.batch.commands import COMMANDS
from mapping.batch.runner import Outcome
from radiometry.fileio import atomic_write_text
from radiometry.tables import csv_text

#: "loop s": the frame loop's seconds (metrics.json timing.seconds), of which "frames/s" is the rate; a comparison adds
#: "method s" (compare.csv's "seconds": each method's whole run), a self-calibration "total s" (all its stages)
COLUMNS = ["sequence", "status", "frames", "fused", "loop s", "frames/s", "L1 mean", "L1 median", "L1 p90",
           "ATE cm", "error"]


def summary_rows(outcomes: list[Outcome]) -> list[dict]:
    """One row per sequence (per sequence and method for a comparison); a failed sequence's row holds its error."""
    rows = []
    for o in outcomes:
        head = {"sequence": o.task.name, "status": o.status}
        if o.rows:
            rows += [{**head, **row} for row in o.rows]
        else:
            rows.append({**head, "error": o.error or ""})
    return rows


def columns_of(rows: list[dict]) -> list[str]:
    """:data:`COLUMNS`, with ``method`` after the status when a row has one (comparisons) and a command's own
    columns (self-calibrate's sightings, ...) before ``error``, in the order the rows have them."""
    columns = COLUMNS[:2] + ["method"] + COLUMNS[2:] if any("method" in r for r in rows) else list(COLUMNS)
    if rows and not any("loop s" in r for r in rows):      # a command that times no frame loop (self-calibrate)
        columns = [c for c in columns if c not in ("loop s", "frames/s")]
    extra = [k for k in dict.fromkeys(k for r in rows for k in r) if k not in columns]
    return columns[:-1] + extra + columns[-1:]


def write_summary(outcomes: list[Outcome], out: str | os.PathLike, *, title: str) -> dict[str, Path]:
    """``OUT/summary.csv`` and ``OUT/index.html`` (atomic writes); returns their paths."""
    out = Path(out)
    rows = summary_rows(outcomes)
    columns = columns_of(rows)
    csv_path = atomic_write_text(out / "summary.csv", csv_text(rows, columns))
    html_path = atomic_write_text(out / "index.html", index_html(outcomes, rows, columns, out, title=title))
    return {"csv": csv_path, "html": html_path}


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.4g}"
    return html.escape(str(value))


def index_html(outcomes: list[Outcome], rows: list[dict], columns: list[str], out: Path, *, title: str) -> str:
    """A self-contained page: the summary table, each sequence linked to its report (or its log when it failed)."""
    links = {}
    for o in outcomes:
        if o.status == "failed":
            target = o.log
        else:
            target = o.task.output / COMMANDS[o.task.command].report
        links[o.task.name] = None if target is None else Path(os.path.relpath(target, out)).as_posix()
    counts = {s: sum(o.status == s for o in outcomes) for s in ("complete", "skipped", "failed")}
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = []
    for row in rows:
        cells = []
        for c in columns:
            text = _cell(row.get(c))
            if c == "sequence" and links.get(row["sequence"]):
                text = f'<a href="{html.escape(links[row["sequence"]], quote=True)}">{text}</a>'
            cells.append(f'<td class="{html.escape(c.replace(" ", "-").replace("/", "-"))}">{text}</td>')
        body.append(f'<tr class="{html.escape(row["status"])}">{"".join(cells)}</tr>')
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font-family: sans-serif; margin: 2em; }}
table {{ border-collapse: collapse; }}
th, td {{ border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }}
td.sequence, td.status, td.method, td.error {{ text-align: left; }}
tr.failed td {{ background: #fde8e8; }}
</style></head>
<body>
<h1>{html.escape(title)}</h1>
<p>{len(outcomes)} sequences: {counts['complete']} run now, {counts['skipped']} complete before (skipped),
{counts['failed']} failed. Each name links to the sequence's report (a failed one to its log); the table is also in
<a href="summary.csv">summary.csv</a>. L1: colour disagreement of the fused samples (8-bit levels, summed over R, G,
B); ATE: absolute trajectory error (RMSE); loop s: seconds of the frame loop (read, track, render, colour, fuse,
histogram: metrics.json timing.seconds), frames/s its rate; method s (comparisons): the method's whole run,
compare.csv's seconds; total s (self-calibrations): all stages.</p>
<table><thead><tr>{head}</tr></thead>
<tbody>
{chr(10).join(body)}
</tbody></table>
</body></html>
"""


__all__ = ["COLUMNS", "columns_of", "index_html", "summary_rows", "write_summary"]
