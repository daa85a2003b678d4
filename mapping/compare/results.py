"""What a comparison yields: per method a :class:`MethodResult`, together a :class:`CompareResult` (the table,
the ranking), and the folder they are written to, :class:`ComparisonFolder`.

Layout (``OUT``)::

    OUT/compare.json, compare.csv, compare.txt   the table (and everything else, in JSON)
    OUT/histograms.png                           normalised histograms of all methods (Fig. 9), linear + log
    OUT/renders.jpg                              the meshes side by side from 2-3 trajectory viewpoints (their
                                                 poses and camera: "renders" in compare.json)
    OUT/report.html                              everything above in one self-contained page
    OUT/<method>/                                a reconstruct results folder per method (histogram,
                                                 trajectory, metrics, mesh.ply, mesh_colours.npz)
    OUT/holdout.csv                              with ``holdout_every``: every method's figures per withheld frame
                                                 (:mod:`mapping.holdout`; its pooled PSNR and L1 are table columns)
    OUT/<method>/colour_map.json, mesh_colourmap.*   with ``colour_map``: the colour-map stage of each method
                                                 (:mod:`mapping.colour_map`); its check and choice are table columns
                                                 (:data:`COLOUR_MAP_COLUMNS`) and a section of the report
    OUT/config.json, summary.txt                 the CLI's options and printed summary (``config``, ``summary``)
    OUT/.radiomap-files.json                     the files and method folders the comparison wrote: the next
                                                 ``force`` run removes them (:class:`ComparisonFolder`)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mapping.compare.colour_error import ColourError
from mapping.compare.geometry import MapGeometry
from mapping.compare.methods import METHOD_NAMES, Method
from mapping.export import MANIFEST, RUNNING_MARKER, ResultsFolder
from mapping.publication import StagedResultsFolder
from radiometry.tables import format_table

TABLE_COLUMNS = ["method", "description", "frames fused", "pairs", "L1 mean", "L1 median", "L1 p90",
                 "colour err", "colour err p90", "seconds"]
HOLDOUT_COLUMNS = ["holdout frames", "holdout PSNR", "holdout L1"]   # with held-out frames, before "seconds"
#: with the colour-map stage, before "seconds" (after the held-out columns): its check's held-out PSNR (dB) and L1
#: (levels) of the plain and the optimised mesh, the mesh kept (``optimised`` or ``plain``) and why in brief
#: (:attr:`mapping.colour_map.ColourMapOutcome.brief`) and the stage's seconds ("seconds" then excludes them)
COLOUR_MAP_COLUMNS = ["cm plain PSNR", "cm plain L1", "cm opt PSNR", "cm opt L1", "cm kept", "cm why", "cm seconds"]
MARKER = "compare.json"


@dataclass
class MethodResult:
    """One method's run."""

    method: Method
    run: Any                        # mapping.results.RunResult
    folder: Path
    colour_model: Any
    geometry: MapGeometry
    colour_error: ColourError | None
    files: dict[str, Path] = field(default_factory=dict)
    seconds: float = math.nan

    def row(self) -> dict[str, Any]:
        s = self.run.histogram.stats()
        err = self.colour_error
        holdout = self.run.holdout
        return {"method": self.method.name, "description": self.method.label, "frames fused": self.run.fused,
                "pairs": s["count"], "L1 mean": s["mean"], "L1 median": s["median"], "L1 p90": s["p90"],
                "colour err": math.nan if err is None else err.mean,
                "colour err p90": math.nan if err is None else err.p90,
                **({} if holdout is None else {"holdout frames": len(holdout.evaluated), "holdout PSNR": holdout.psnr,
                                               "holdout L1": holdout.l1}),
                **({} if self.run.colour_map is None else colour_map_row(self.run.colour_map)),
                "seconds": self.seconds}


def colour_map_row(outcome) -> dict[str, Any]:
    """The :data:`COLOUR_MAP_COLUMNS` of a method's colour-map stage (a
    :class:`mapping.colour_map.ColourMapOutcome`; NaN figures when it did not run)."""
    def figure(h, name: str) -> float:
        return math.nan if h is None else float(getattr(h, name))
    return {"cm plain PSNR": figure(outcome.plain, "psnr"), "cm plain L1": figure(outcome.plain, "l1"),
            "cm opt PSNR": figure(outcome.optimised, "psnr"), "cm opt L1": figure(outcome.optimised, "l1"),
            "cm kept": outcome.kept, "cm why": outcome.brief, "cm seconds": outcome.seconds}


@dataclass
class CompareResult:
    """The outcome of :func:`compare`."""

    results: list[MethodResult]
    stamps: np.ndarray
    poses: np.ndarray
    pose_source: str
    output: Path
    files: dict[str, Path]
    seconds: float
    ate: Any = None
    parameters: dict[str, Any] = field(default_factory=dict)
    renders: dict[str, Any] | None = None   # the side-by-side renders' camera and viewpoints (compare.json)

    def __getitem__(self, name: str) -> MethodResult:
        for r in self.results:
            if r.method.name == name:
                return r
        raise KeyError(f"no method {name!r}; the comparison ran {', '.join(self.names)}")

    @property
    def names(self) -> list[str]:
        return [r.method.name for r in self.results]

    def table(self) -> list[dict[str, Any]]:
        return [r.row() for r in self.results]

    @property
    def columns(self) -> list[str]:
        """The table's columns: :data:`TABLE_COLUMNS`, with :data:`HOLDOUT_COLUMNS` before "seconds" when the runs
        withheld frames and :data:`COLOUR_MAP_COLUMNS` after them when the colour-map stage ran."""
        extra = []
        if any(r.run.holdout is not None for r in self.results):
            extra += HOLDOUT_COLUMNS
        if any(r.run.colour_map is not None for r in self.results):
            extra += COLOUR_MAP_COLUMNS
        return TABLE_COLUMNS[:-1] + extra + TABLE_COLUMNS[-1:]

    def table_text(self) -> str:
        rows = []
        for row in self.table():
            rows.append({k: ("-" if isinstance(v, float) and not math.isfinite(v) else
                             round(v, 2) if isinstance(v, float) else v) for k, v in row.items()})
        return format_table(rows, self.columns)

    @property
    def poses_identical(self) -> bool:
        """Every method fused the same frames at bit-identical poses."""
        first = self.results[0].run
        return all(np.array_equal(r.run.poses, first.poses) and np.array_equal(r.run.stamps, first.stamps)
                   for r in self.results[1:])

    def ranking(self, column: str = "L1 mean") -> list[str]:
        """Method names from best (smallest ``column``) to worst."""
        rows = self.table()
        return [r["method"] for r in sorted(rows, key=lambda r: (not math.isfinite(r[column]), r[column]))]



class ComparisonFolder(StagedResultsFolder):
    """The comparison's folder (``OUT``): a :class:`~mapping.export.ResultsFolder` whose results are the files of
    the module doc's layout and one results folder per method (:meth:`subfolder`). ``force`` over a complete
    comparison stages the new one and publishes it as one set, ``compare.json`` last
    (:class:`mapping.publication.StagedResultsFolder`: the previous comparison stands until then); over anything else
    it removes the previous comparison's files and method folders (those its ``.radiomap-files.json`` lists, and
    folders named like a method) before the new one starts. The user's other files are left alone."""

    what = "comparison"
    markers = (MARKER, *ResultsFolder.markers)
    refusal = ("already holds a comparison or the results of a run; pass --force to overwrite them or choose another "
               "output folder")
    result_names = frozenset({MARKER, "compare.csv", "compare.txt", "histograms.png", "colour_error.png",
                              "renders.jpg", "report.html", "exposures.png", "trajectory.png", "config.json",
                              "summary.txt", "holdout.csv", RUNNING_MARKER, MANIFEST})
    result_folders = frozenset(METHOD_NAMES)
    status_file = None
    primary = MARKER

    def _previous_complete(self) -> bool:
        return (self.path / MARKER).is_file() and not (self.path / RUNNING_MARKER).exists()
