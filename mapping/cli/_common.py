"""Shared pieces of the subcommands: option types, result folders, summary tables."""

from __future__ import annotations

import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import click

from radiometry import __version__
from radiometry.fileio import atomic_write_json, atomic_write_text, ensure_dir


class FrameRange(click.ParamType):
    """``A:B:S`` (Python slice syntax, each part optional) -> ``slice``."""

    name = "A:B:S"

    def convert(self, value, param, ctx):
        if isinstance(value, slice):
            return value
        parts = str(value).split(":")
        if len(parts) > 3:
            self.fail(f"{value!r} is not A:B:S (e.g. 0:100:2)", param, ctx)
        try:
            nums = [int(p) if p.strip() else None for p in parts]
        except ValueError:
            self.fail(f"{value!r} is not A:B:S with whole numbers (e.g. 0:100:2)", param, ctx)
        while len(nums) < 3:
            nums.append(None)
        if len(parts) == 1 and nums[0] is not None:  # a single number N means the first N frames
            nums = [0, nums[0], None]
        if nums[2] is not None and nums[2] <= 0:
            self.fail(f"the step in {value!r} must be positive", param, ctx)
        return slice(*nums)


def run_manifest(command: str, params: dict[str, Any]) -> dict[str, Any]:
    """What a results folder records about the run that made it."""
    return {
        "command": command,
        "argv": sys.argv,
        "parameters": {k: (str(v) if isinstance(v, (Path, slice)) else v) for k, v in params.items()},
        "radiomap_version": __version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


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


def warn_far_depth(fraction: float, depth_max: float, *, threshold: float = 0.2) -> None:
    """Warn on stderr when more than ``threshold`` of the valid depth lay beyond ``--depth-max`` (ICP then
    sees fewer surfaces and may slide along what is left)."""
    if fraction > threshold:
        click.echo(f"warning: {100 * fraction:.0f} % of the valid depth lies beyond --depth-max {depth_max:g} m and "
                   "was neither fused nor tracked; raise --depth-max if the scene is deeper", err=True)


__all__ = ["FrameRange", "run_manifest", "format_table", "warn_far_depth", "atomic_write_json",
           "atomic_write_text", "ensure_dir", "json"]
