"""What a reconstruction produces: per-frame records, the run's result, and the files written into its results
folder (``trajectory.txt``, ``frames.csv``, ``histogram.*``, the mesh, ``metrics.json``, ``summary.txt``)."""

from __future__ import annotations

import logging
import math
import re
import resource
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mapping.histogram import DisagreementHistogram
from mapping.holdout import HoldoutResult
from mapping.metrics import ATEResult, format_tum_trajectory
from radiometry.tables import format_table

log = logging.getLogger(__name__)

#: the sequence's ground truth beside the estimated trajectory, as a TUM file (when the sequence has one)
GROUND_TRUTH_FILE = "groundtruth_tum.txt"


@dataclass
class FrameRecord:
    """What happened to one frame (one row of ``frames.csv``)."""

    index: int
    timestamp: float
    fused: bool
    reason: str = ""
    fitness: float = math.nan
    inlier_rmse: float = math.nan
    pairs: int = 0
    mean_l1: float = math.nan


@dataclass
class RunResult:
    """The outcome of :func:`reconstruct`."""

    stamps: np.ndarray                  # (N,) timestamps of the fused frames
    poses: np.ndarray                   # (N, 4, 4) camera-to-world poses of the fused frames
    histogram: DisagreementHistogram
    records: list[FrameRecord]
    seconds: float
    stage_seconds: dict[str, float]
    ate: ATEResult | None
    map_stats: dict
    peak_rss_mb: float
    status: str = "complete"
    files: dict[str, Path] = field(default_factory=dict)
    depth_beyond_range: float = 0.0     # fraction of the valid depth pixels at or beyond the backend's depth_max
    held_out_poses: dict[int, np.ndarray | None] = field(default_factory=dict)  # position -> pose, withheld frames
    holdout: HoldoutResult | None = None  # the final map judged by the withheld frames (mapping.holdout)
    colour_map: Any = None              # mapping.colour_map.ColourMapOutcome of the colour-map stage, if it ran
    partial_reason: str = ""            # status "partial": why the run stopped early (tracking lost)
    requested: int | None = None        # the frames the run was asked for (None: those it processed, ``frames``)
    ate_note: str = ""                  # why there is no ATE though the sequence has ground truth (too few poses)

    @property
    def frames(self) -> int:
        return len(self.records)

    @property
    def fused(self) -> int:
        return sum(r.fused for r in self.records)

    @property
    def held_out(self) -> int:
        """Frames withheld from fusion by ``holdout_every`` (asked for: neither fused nor skipped)."""
        return len(self.held_out_poses)

    @property
    def skipped(self) -> int:
        """Frames neither fused nor withheld (``frames = fused + skipped + held_out``)."""
        return self.frames - self.fused - self.held_out

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else math.nan

    def skipped_records(self) -> list[FrameRecord]:
        """The records of the skipped frames (records are in the run's frame order: position = list index)."""
        return [r for i, r in enumerate(self.records) if not r.fused and i not in self.held_out_poses]

    def skip_reasons(self) -> dict[str, int]:
        """Skipped frames counted by the kind of reason (the text before the first number)."""
        return dict(Counter(reason_kind(r.reason) for r in self.skipped_records()))

    def metrics(self) -> dict:
        """The content of ``metrics.json``."""
        return {
            "status": self.status,
            **({"partial_reason": self.partial_reason} if self.partial_reason else {}),
            # total: the run's frames; processed = fused + skipped (+ held_out): fewer when it stopped early
            "frames": {"total": self.frames if self.requested is None else self.requested, "processed": self.frames,
                       "fused": self.fused, "skipped": self.skipped,
                       **({"held_out": self.held_out} if self.held_out_poses else {}),
                       "skip_reasons": self.skip_reasons(),
                       "skipped_frames": [{"index": r.index, "timestamp": r.timestamp, "reason": r.reason}
                                          for r in self.skipped_records()]},
            "timing": {"seconds": self.seconds, "frames_per_second": self.frames_per_second,
                       "ms_per_frame": 1000.0 * self.seconds / max(self.frames, 1),
                       "stage_ms_per_frame": {k: 1000.0 * v / max(self.frames, 1)
                                              for k, v in self.stage_seconds.items()}},
            "histogram": self.histogram.stats(),
            "ate": None if self.ate is None else self.ate.to_dict(),
            "depth_beyond_range": self.depth_beyond_range,
            "map": self.map_stats,
            "memory": {"peak_rss_mb": self.peak_rss_mb},
            **({} if self.holdout is None else {"holdout": self.holdout.to_dict()}),
        }

    def notes(self) -> list[str]:
        """Lines saying why a figure of the summary is missing (L1 ``nan``, ATE ``-``) when the run itself says why."""
        out = []
        if self.histogram.total == 0 and self.fused < 2:
            out.append(f"note: no L1: {self.fused} frame fused (L1 compares each frame with the map the frames before "
                       "it made: it needs at least 2)")
        if self.ate_note:
            out.append(f"note: no ATE: {self.ate_note}")
        return out

    def summary_row(self) -> dict:
        s = self.histogram.stats()
        return {"frames": self.frames, "fused": self.fused, "skipped": self.skipped,
                **({"held out": self.held_out} if self.held_out_poses else {}),
                "fps": round(self.frames_per_second, 2), "L1 mean": s["mean"], "L1 median": s["median"],
                "L1 p90": s["p90"], "pairs": s["count"],
                "ATE cm": "-" if self.ate is None else round(100 * self.ate.rmse, 2),
                **({} if self.holdout is None else {"holdout PSNR": round(self.holdout.psnr, 2),
                                                    "holdout L1": round(self.holdout.l1, 2)}),
                "peak MB": round(self.peak_rss_mb)}


def reason_kind(reason: str) -> str:
    """The kind of a skip reason, for counting: the text before its first number or parenthesis ("fitness",
    "too few valid depth pixels"), so that frames skipped for one cause count together."""
    match = re.search(r"\d| \(", reason)
    kind = reason[:match.start()] if match else reason
    return kind.rstrip(" :") or reason


def peak_rss_mb() -> float:
    """Peak resident memory of this process (MB; includes Open3D's C++ allocations)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def backend_stats(backend) -> dict:
    """The backend's size figures for metrics.json (empty, with a warning, if it fails)."""
    try:
        return dict(backend.stats())
    except Exception as exc:  # a statistic must never lose a finished run
        log.warning("the backend's stats() failed: %s", exc)
        return {}


def frames_csv(records: list[FrameRecord]) -> str:
    lines = ["index,timestamp,fused,fitness,inlier_rmse_m,pairs,mean_l1,reason"]
    for r in records:
        reason = r.reason.replace('"', "'")
        lines.append(f"{r.index},{r.timestamp:.6f},{int(r.fused)},{r.fitness:.4f},{r.inlier_rmse:.5f},{r.pairs},"
                     f"{r.mean_l1:.3f},\"{reason}\"")
    return "\n".join(lines) + "\n"


def write_partial(run: RunResult, backend, output) -> None:
    """On Ctrl-C or a failure: the trajectory and metrics so far, the RUNNING marker stays."""
    try:
        output.write_text("trajectory.txt", format_tum_trajectory(run.stamps, run.poses))
        output.write_text("frames.csv", frames_csv(run.records))
        run.map_stats = backend_stats(backend)
        output.write_json("metrics.json", run.metrics())
    except Exception as exc:  # never mask the original exception
        log.warning("could not save the partial results: %s", exc)


def describe_run(dataset, colour_model, backend, tracker) -> dict:
    """What config.json records when the caller has not written one (the CLI writes its own)."""
    def params(obj):
        if obj is None:
            return None
        return {k: v for k, v in vars(obj).items() if not k.startswith("_") and isinstance(v, (int, float, str, bool,
                                                                                             tuple, type(None)))}
    from mapping.datasets import describe_dataset

    return {"dataset": describe_dataset(dataset), "colour_model": colour_model.describe(),
            "backend": {"class": type(backend).__name__, **(params(backend) or {})},
            "tracker": None if tracker is None else {"class": type(tracker).__name__, **params(tracker)}}


def colour_model_setup(colour_model) -> dict:
    """``colour_model.describe()`` as config.json records it before the run: without what only the run knows (the
    exposure estimates' summary, the k of a median mesh exposure), which metrics.json records when it ends."""
    doc = dict(colour_model.describe())
    if isinstance(doc.get("exposure"), dict):
        doc["exposure"] = {k: v for k, v in doc["exposure"].items() if k != "summary"}
    reference = doc.get("export_reference")
    if isinstance(reference, dict) and reference.get("kind") == "median":
        doc["export_reference"] = {k: v for k, v in reference.items() if k != "k"}
    return doc


def write_results(run: RunResult, dataset, colour_model, backend, tracker, output, *, write_mesh: bool,
                  mesh_formats: tuple[str, ...] = ("ply",)) -> None:
    """Every result file of a finished run into ``output`` (a :class:`~mapping.export.ResultsFolder`), then mark it
    complete: the last step of :func:`mapping.pipeline.reconstruct` (after the held-out evaluation and the colour-map
    stage, whose files are already in place; its line ends ``summary.txt``)."""
    from mapping.plots import save_histogram_figure

    files = {}
    if not output.file("config.json").exists():
        files["config"] = output.write_json("config.json", describe_run(dataset, colour_model, backend, tracker))
    files["trajectory"] = output.write_text("trajectory.txt", format_tum_trajectory(run.stamps, run.poses))
    truth = dataset.ground_truth() if hasattr(dataset, "ground_truth") else None
    if truth is not None:   # the ground truth as a TUM file beside the estimate (for evo and the like)
        files["groundtruth"] = output.write_text(GROUND_TRUTH_FILE, format_tum_trajectory(*truth))
    files["frames"] = output.write_text("frames.csv", frames_csv(run.records))
    files["histogram_json"] = run.histogram.save(output.file("histogram.json"))
    files["histogram_npz"] = run.histogram.save(output.file("histogram.npz"))
    if run.histogram.total:
        save_histogram_figure(output.file("histogram.png"), {run.histogram.label: run.histogram},
                              title="colour disagreement before fusion")
        files["histogram_png"] = output.file("histogram.png")
    if write_mesh:  # colours e.g. at the sequence's median exposure
        files.update(backend.export(output.path, colour_model.display_for_export(), formats=tuple(mesh_formats)))
    files.update(colour_model.save_results(output.path))  # e.g. per-frame exposure estimates
    if run.holdout is not None:
        files["holdout"] = output.write_text("holdout.csv", run.holdout.csv())
    run.files = files
    metrics = run.metrics()
    metrics["colour_model"] = colour_model.describe()
    if hasattr(tracker, "stats"):   # the auto tracker: frames tracked by each method
        metrics["tracking"] = tracker.stats()
    metrics["files"] = {k: Path(v).name for k, v in files.items()}
    summary = format_table([run.summary_row()]) + "\n" + "".join(line + "\n" for line in run.notes())
    if run.colour_map is not None:
        summary += run.colour_map.summary_line() + "\n"
    if run.status == "partial":
        summary += f"PARTIAL: {run.partial_reason}\n"
    output.write_text("summary.txt", summary)
    output.write_json("metrics.json", metrics)
    output.complete()


__all__ = ["GROUND_TRUTH_FILE", "FrameRecord", "RunResult", "backend_stats", "colour_model_setup", "describe_run",
           "frames_csv",
           "peak_rss_mb", "reason_kind", "write_partial", "write_results"]
