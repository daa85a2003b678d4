"""The mapping pipeline: ``loader[i] -> RGBDFrame -> radiometric correction -> tracking -> fusion ->
(disagreement histogram) -> results folder``.

:func:`reconstruct` is the core: plain keyword arguments (a dataset, a colour model, a fusion backend, a
tracker or ground-truth poses), one loop over frames, a :class:`RunResult`. :func:`build_run` is the small
factory that turns a :class:`ReconstructConfig` (what the CLI collects) into those arguments.

Per frame (ICP mode)::

    frame   = dataset[i]                                   # lazy load
    pose    = tracker.track(frame.depth, K, view_prev, pose_prev)  # frame-to-model ICP; failure -> skip
    view    = backend.render_for_frame(depth, K, pose)     # the map at this pose, BEFORE fusing this frame
    colour  = colour_model.to_map(frame, view)             # uint8 RGB -> map units (may use the view)
    pairs   = backend.integrate(depth, colour, K, pose, view=view)   # fuse; (map, sample) colour pairs
    histogram.add(to_display(pairs.map), to_display(pairs.sample))
    view_prev, pose_prev = view, pose                      # the tracker's target for frame i + 1

One ray cast per frame serves both the histogram (the map before this frame) and the tracking of the next
frame (the map at the last pose, lacking only the last frame), like Open3D's dense SLAM loop which also
casts once per frame. When that view covers less than ``refresh_coverage`` of the frame's valid depth (the
first frame; the camera entering unmapped space) the map is cast again after fusion for the tracker.
"""

from __future__ import annotations

import inspect
import logging
import math
import resource
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from mapping.colour import ColourModel, RawIntensity, display_l1, make_colour_model
from mapping.datasets.base import RGBDDataset
from mapping.fusion.base import FusionBackend
from mapping.histogram import DisagreementHistogram
from radiometry.tables import format_table
from mapping.metrics import ATEResult, absolute_trajectory_error, format_tum_trajectory
from radiometry.errors import ModelMismatchError, RadiomapError, TrackingError

log = logging.getLogger(__name__)

POSE_SOURCES = ("icp", "gt")
BACKENDS = {"tsdf": ("mapping.fusion.tsdf", "TSDFBackend"), "surfel": ("mapping.fusion.surfel", "SurfelBackend")}
STAGES = ("load", "track", "render", "colour", "fuse", "histogram")


# --------------------------------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------------------------------
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

    @property
    def frames(self) -> int:
        return len(self.records)

    @property
    def fused(self) -> int:
        return sum(r.fused for r in self.records)

    @property
    def skipped(self) -> int:
        return self.frames - self.fused

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else math.nan

    def skip_reasons(self) -> dict[str, int]:
        """Skipped frames counted by the kind of reason (the text before the first number)."""
        return dict(Counter(_reason_kind(r.reason) for r in self.records if not r.fused))

    def metrics(self) -> dict:
        """The content of ``metrics.json``."""
        return {
            "status": self.status,
            "frames": {"total": self.frames, "fused": self.fused, "skipped": self.skipped,
                       "skip_reasons": self.skip_reasons(),
                       "skipped_frames": [{"index": r.index, "timestamp": r.timestamp, "reason": r.reason}
                                          for r in self.records if not r.fused]},
            "timing": {"seconds": self.seconds, "frames_per_second": self.frames_per_second,
                       "ms_per_frame": 1000.0 * self.seconds / max(self.frames, 1),
                       "stage_ms_per_frame": {k: 1000.0 * v / max(self.frames, 1)
                                              for k, v in self.stage_seconds.items()}},
            "histogram": self.histogram.stats(),
            "ate": None if self.ate is None else self.ate.to_dict(),
            "depth_beyond_range": self.depth_beyond_range,
            "map": self.map_stats,
            "memory": {"peak_rss_mb": self.peak_rss_mb},
        }

    def summary_row(self) -> dict:
        s = self.histogram.stats()
        return {"frames": self.frames, "fused": self.fused, "skipped": self.skipped,
                "fps": round(self.frames_per_second, 2), "L1 mean": s["mean"], "L1 median": s["median"],
                "L1 p90": s["p90"], "pairs": s["count"],
                "ATE cm": "-" if self.ate is None else round(100 * self.ate.rmse, 2),
                "peak MB": round(self.peak_rss_mb)}


def _reason_kind(reason: str) -> str:
    for i, ch in enumerate(reason):
        if ch.isdigit():
            return reason[:i].strip() or reason
    return reason


def peak_rss_mb() -> float:
    """Peak resident memory of this process (MB; includes Open3D's C++ allocations)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# --------------------------------------------------------------------------------------------------
# the core loop
# --------------------------------------------------------------------------------------------------
def reconstruct(dataset: RGBDDataset, *, colour_model: ColourModel | None = None,
                backend: FusionBackend, tracker=None, poses: str = "icp", initial_pose: np.ndarray | None = None,
                output=None, refresh_coverage: float = 0.5, max_consecutive_failures: int = 30,
                progress: bool = True, histogram_label: str | None = None,
                write_mesh: bool = True) -> RunResult:
    """Track (or take ground-truth poses), correct, fuse and measure colour disagreement over a sequence.

    dataset:       an :class:`~mapping.datasets.base.RGBDDataset` (frame range and stride applied).
    colour_model:  a :class:`~mapping.colour.ColourModel` (default: raw intensities, no correction).
    backend:       a :class:`~mapping.fusion.base.FusionBackend` (TSDF or surfel).
    tracker:       a :class:`~mapping.tracking.FrameToModelTracker` for ``poses="icp"``.
    poses:         ``"icp"`` (track) or ``"gt"`` (the dataset's ground truth; frames without it are skipped).
    initial_pose:  the first frame's pose in ICP mode (default: its ground truth when known, else identity).
    output:        None, or a :class:`~mapping.export.ResultsFolder` to write the results into.
    refresh_coverage: re-cast the map after fusion for the tracker when the pre-fusion view covers less than
                   this fraction of the frame's valid depth.
    max_consecutive_failures: raise :class:`TrackingError` when tracking fails this many frames in a row.
    progress:      a progress bar on stderr when it is a terminal (:func:`radiometry.progress.progress_bar`).
    write_mesh:    export the map's mesh into ``output``.
    """
    if poses not in POSE_SOURCES:
        raise ValueError(f"poses must be one of {', '.join(POSE_SOURCES)}, got {poses!r}")
    if poses == "icp" and tracker is None:
        raise ValueError("poses='icp' needs a tracker (mapping.tracking.FrameToModelTracker)")
    if not 0 <= refresh_coverage <= 1:
        raise ValueError(f"refresh_coverage must be in [0, 1], got {refresh_coverage}")
    colour_model = colour_model or RawIntensity()
    loop = _Loop(dataset, colour_model, backend, tracker, poses, initial_pose, refresh_coverage,
                 max_consecutive_failures, histogram_label or getattr(colour_model, "name", "run"))
    bar = _progress_bar(len(dataset), progress, getattr(dataset, "name", ""))
    status = "failed"
    try:
        for i in range(len(dataset)):
            loop.step(i)
            loop.advance(bar)
        loop.check_fused()  # a run that fused nothing (or too little) fails: mapping/validation.py
        status = "complete"
    except KeyboardInterrupt:
        status = "interrupted"
        loop.drop_unfinished()
        raise
    finally:
        bar.close()
        run = loop.result(status)
        if status != "complete" and output is not None:
            _write_partial(run, backend, output)
    run.map_stats = _backend_stats(backend)
    run.ate = _ate(run, dataset, poses)
    if output is not None:
        _write_results(run, dataset, colour_model, backend, tracker, output, write_mesh=write_mesh)
    return run


class _Loop:
    """The per-frame steps of :func:`reconstruct` and the state they share."""

    def __init__(self, dataset, colour_model, backend, tracker, poses, initial_pose, refresh_coverage,
                 max_failures, label) -> None:
        self.dataset, self.colour_model, self.backend, self.tracker = dataset, colour_model, backend, tracker
        self.poses, self.initial_pose = poses, initial_pose
        self.refresh_coverage, self.max_failures = refresh_coverage, max_failures
        self.histogram = DisagreementHistogram(label=label)
        self.records: list[FrameRecord] = []
        self.stamps: list[float] = []
        self.est: list[np.ndarray] = []
        self.timer = {k: 0.0 for k in STAGES}
        self.render_for_frame = getattr(backend, "render_for_frame", None)
        self.track_view = None          # the map as the tracker sees it: (view, pose it was rendered at)
        self.failures = 0
        self.depth_valid = 0            # valid depth pixels seen, and those at or beyond the depth range
        self.depth_far = 0
        self.skipped = 0   # frames done and not fused (the bar's postfix)
        # the backend's fusion range (TSDF: depth_min/depth_max; surfels: max_depth)
        self.depth_low = getattr(backend, "depth_min", 0.0)
        self.depth_high = getattr(backend, "depth_max", getattr(backend, "max_depth", np.inf))
        self.started = time.perf_counter()

    def _timed(self, stage: str, fn, *args, **kwargs):
        t = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            self.timer[stage] += time.perf_counter() - t

    # ---------------------------------------------------------------- one frame
    def step(self, i: int) -> None:
        frame = self._timed("load", self.dataset.__getitem__, i)
        record = FrameRecord(frame.index, float(frame.timestamp), False)
        self.records.append(record)
        self._count_far_depth(frame)
        pose = self._pose(frame, record)
        if pose is None:
            return
        view = self._timed("render", self._render, frame, pose)
        if view is not None:
            view.pose = pose  # the pose the view was rendered at (exposure compensation re-projects with it)
        colour = self._timed("colour", self.colour_model.to_map, frame, view)
        depth = self._colour_valid_depth(frame, record)
        if depth is None:
            return
        pairs = self._timed("fuse", self.backend.integrate, depth, colour, frame.K, pose, view=view,
                            frame_index=frame.index)
        self._timed("histogram", self._measure, pairs, record)
        record.fused = True
        self.stamps.append(float(frame.timestamp))
        self.est.append(np.asarray(pose, dtype=np.float64))
        if self.poses == "icp":
            self._timed("render", self._keep_for_tracking, frame, pose, view)

    def _pose(self, frame, record: FrameRecord) -> np.ndarray | None:
        """The frame's pose, or None (with the reason recorded) when it must not be fused."""
        if self.poses == "gt":
            if frame.pose is None:
                record.reason = "no ground-truth pose"
            elif self._fusable_depth(frame) == 0:  # nothing to fuse (Open3D would abort the integration)
                record.reason = "no depth within the fusion range"
                return None
            return frame.pose
        if self.tracker.last_pose is None:  # the first frame with depth founds the map
            if self._fusable_depth(frame) < 1000:
                record.reason = "no depth to start the map"
                return None
            pose = _initial_pose(frame, self.initial_pose)
            self.tracker.start(pose)
            return pose
        view, view_pose = self.track_view
        result = self._timed("track", self.tracker.track, frame.depth, frame.K, view, view_pose)
        record.fitness, record.inlier_rmse = result.fitness, result.inlier_rmse
        if result.ok:
            self.failures = 0
            return result.pose
        record.reason = result.reason
        self.failures += 1
        log.info("frame %d skipped: %s", frame.index, result.reason)
        if self.failures >= self.max_failures:
            raise TrackingError(
                f"tracking failed on {self.failures} consecutive frames (last at frame {frame.index}: "
                f"{result.reason}); check --depth-scale and --intrinsics, use a smaller --frames stride, or fuse "
                "with --poses gt")
        return None

    def _count_far_depth(self, frame) -> None:
        """Count the depth the range cuts away: a scene deeper than depth_max leaves ICP fewer surfaces (two
        walls and a floor can become one wall and a floor, along which it slides)."""
        valid = frame.depth > 0
        self.depth_valid += int(np.count_nonzero(valid))
        self.depth_far += int(np.count_nonzero(valid & (frame.depth >= self.depth_high)))

    def _fusable_depth(self, frame) -> int:
        """Depth pixels within the backend's range (a frame of only far or no depth has nothing to fuse)."""
        return int(np.count_nonzero((frame.depth > self.depth_low) & (frame.depth < self.depth_high)))

    def _colour_valid_depth(self, frame, record: FrameRecord) -> np.ndarray | None:
        """The frame's depth without the pixels whose colour the model rejects (``last_valid_mask``, e.g.
        clipped pixels or a frame whose exposure estimate fell back): zero depth fuses neither colour nor
        geometry there. None (the frame skipped, with the model's reason) when nothing is left to fuse."""
        valid = getattr(self.colour_model, "last_valid_mask", None)
        if valid is None:
            return frame.depth
        depth = np.where(valid, frame.depth, np.float32(0))
        if self._fusable_depth(replace(frame, depth=depth)) == 0:
            record.reason = getattr(self.colour_model, "last_reject_reason", None) or "colour rejected"
            return None
        return depth

    def _render(self, frame, pose: np.ndarray):
        """The map before this frame, at its pose (one ray cast, reused by fusion and by the next tracking)."""
        if self.render_for_frame is not None:
            return self.render_for_frame(frame.depth, frame.K, pose)
        return self.backend.render(pose, frame.K, frame.height, frame.width)

    def _measure(self, pairs, record: FrameRecord) -> None:
        """Add the frame's colour pairs to the histogram, in display units."""
        if pairs is None or not len(pairs):
            return
        d = display_l1(self.colour_model, pairs.map_colour, pairs.sample_colour)
        record.pairs = self.histogram.add_distances(d)
        record.mean_l1 = float(d.mean())

    def _keep_for_tracking(self, frame, pose: np.ndarray, view) -> None:
        """The next frame is tracked against this frame's pre-fusion view, unless it shows too little of the
        scene (the first frame, the camera entering unmapped space): then the map is cast again."""
        valid = np.count_nonzero(frame.depth > 0)
        if view is None or np.count_nonzero(view.depth > 0) < self.refresh_coverage * valid:
            view = self.backend.render(pose, frame.K, frame.height, frame.width)
        self.track_view = (view, pose)

    def advance(self, bar) -> None:
        """One frame done: the bar advances, and a DEBUG line says so ("frame 3 of 5: fused"; ``-vv``)."""
        record = self.records[-1]
        log.debug("frame %d of %d: %s", len(self.records), len(self.dataset),
                  "fused" if record.fused else f"skipped ({record.reason or 'no reason'})")
        if not record.fused:
            self.skipped += 1
            bar.set_postfix(skipped=self.skipped, refresh=False)
        bar.update(1)

    def check_fused(self) -> None:
        from mapping.validation import check_fused

        fused = sum(r.fused for r in self.records)
        reasons = Counter(_reason_kind(r.reason) for r in self.records if not r.fused)
        check_fused(fused, len(self.records), dict(reasons),
                    str(getattr(self.dataset, "root", None) or getattr(self.dataset, "name", "the sequence")))

    def drop_unfinished(self) -> None:
        """Forget the frame an interruption cut short (neither fused nor skipped for a reason): it was not
        processed, so it is not counted as skipped."""
        if self.records and not self.records[-1].fused and not self.records[-1].reason:
            self.records.pop()

    def result(self, status: str) -> RunResult:
        return RunResult(stamps=np.asarray(self.stamps), poses=np.asarray(self.est).reshape(-1, 4, 4),
                         histogram=self.histogram, records=self.records, seconds=time.perf_counter() - self.started,
                         stage_seconds=dict(self.timer), ate=None, map_stats={}, peak_rss_mb=peak_rss_mb(),
                         status=status, depth_beyond_range=self.depth_far / max(self.depth_valid, 1))


def _initial_pose(frame, initial_pose):
    if initial_pose is not None:
        return np.asarray(initial_pose, dtype=np.float64)
    if frame.pose is not None:
        return np.asarray(frame.pose, dtype=np.float64)
    return np.eye(4)


def _progress_bar(n: int, enabled: bool, name: str):
    from radiometry.progress import progress_bar

    return progress_bar(total=n, desc=f"reconstruct {name}".strip(), enabled=enabled, leave=False)


def _backend_stats(backend) -> dict:
    try:
        return dict(backend.stats())
    except Exception as exc:  # a statistic must never lose a finished run
        log.warning("the backend's stats() failed: %s", exc)
        return {}


def _ate(run: RunResult, dataset, poses: str) -> ATEResult | None:
    if poses != "icp" or len(run.stamps) < 3:
        return None
    gt = dataset.ground_truth()
    if gt is None:
        return None
    try:
        return absolute_trajectory_error(run.stamps, run.poses, gt[0], gt[1])
    except ValueError as exc:
        log.warning("no ATE: %s", exc)
        return None


# --------------------------------------------------------------------------------------------------
# writing results
# --------------------------------------------------------------------------------------------------
def _frames_csv(records: list[FrameRecord]) -> str:
    lines = ["index,timestamp,fused,fitness,inlier_rmse_m,pairs,mean_l1,reason"]
    for r in records:
        reason = r.reason.replace('"', "'")
        lines.append(f"{r.index},{r.timestamp:.6f},{int(r.fused)},{r.fitness:.4f},{r.inlier_rmse:.5f},{r.pairs},"
                     f"{r.mean_l1:.3f},\"{reason}\"")
    return "\n".join(lines) + "\n"


def _write_partial(run: RunResult, backend, output) -> None:
    """On Ctrl-C or a failure: the trajectory and metrics so far, the RUNNING marker stays."""
    try:
        output.write_text("trajectory.txt", format_tum_trajectory(run.stamps, run.poses))
        output.write_text("frames.csv", _frames_csv(run.records))
        run.map_stats = _backend_stats(backend)
        output.write_json("metrics.json", run.metrics())
    except Exception as exc:  # never mask the original exception
        log.warning("could not save the partial results: %s", exc)


def _describe_run(dataset, colour_model, backend, tracker) -> dict:
    """What config.json records when the caller has not written one (the CLI writes its own)."""
    def params(obj):
        if obj is None:
            return None
        return {k: v for k, v in vars(obj).items() if not k.startswith("_") and isinstance(v, (int, float, str, bool,
                                                                                             tuple, type(None)))}
    return {"dataset": repr(dataset), "colour_model": colour_model.describe(),
            "backend": {"class": type(backend).__name__, **(params(backend) or {})},
            "tracker": None if tracker is None else {"class": type(tracker).__name__, **params(tracker)}}


def _write_results(run: RunResult, dataset, colour_model, backend, tracker, output, *, write_mesh: bool) -> None:
    from mapping.plots import save_histogram_figure

    files = {}
    if not output.file("config.json").exists():
        files["config"] = output.write_json("config.json", _describe_run(dataset, colour_model, backend, tracker))
    files["trajectory"] = output.write_text("trajectory.txt", format_tum_trajectory(run.stamps, run.poses))
    files["frames"] = output.write_text("frames.csv", _frames_csv(run.records))
    files["histogram_json"] = run.histogram.save(output.file("histogram.json"))
    files["histogram_npz"] = run.histogram.save(output.file("histogram.npz"))
    if run.histogram.total:
        save_histogram_figure(output.file("histogram.png"), {run.histogram.label: run.histogram},
                              title="colour disagreement before fusion")
        files["histogram_png"] = output.file("histogram.png")
    if write_mesh:
        export_display = getattr(colour_model, "export_display", None)  # e.g. the sequence's median exposure
        files.update(backend.export(output.path, export_display() if export_display else colour_model.to_display))
    save_results = getattr(colour_model, "save_results", None)      # e.g. per-frame exposure estimates
    if save_results is not None:
        files.update(save_results(output.path))
    run.files = files
    metrics = run.metrics()
    metrics["colour_model"] = colour_model.describe()
    metrics["files"] = {k: Path(v).name for k, v in files.items()}
    output.write_text("summary.txt", format_table([run.summary_row()]) + "\n")
    output.write_json("metrics.json", metrics)
    output.complete()


# --------------------------------------------------------------------------------------------------
# factory: configuration -> keyword arguments of reconstruct()
# --------------------------------------------------------------------------------------------------
@dataclass
class ReconstructConfig:
    """Everything ``radiomap reconstruct`` collects; :func:`build_run` turns it into :func:`reconstruct`'s
    arguments."""

    sequence: Path
    output: Path | None = None
    response: Path | None = None
    vignetting: Path | None = None
    poses: str = "icp"
    voxel_size: float = 0.01
    frames: slice = field(default_factory=lambda: slice(None))
    depth_scale: float | None = None
    intrinsics: Any = None
    backend: str = "tsdf"
    surfel_mesh: bool = False                   # surfel backend: also write a Poisson mesh (surfels_mesh.ply)
    format: str | None = None
    depth_max: float = 3.0
    block_resolution: int = 16
    trunc_voxel_multiplier: float = 8.0
    motion_model: str = "constant_velocity"
    reference_exposure: float = 1.0
    exposure_compensation: bool | None = None   # None: on when a response is given
    exposure_reference: str = "median"          # mesh colours: median | first | k | r,g,b (first frame = 1)
    force: bool = False
    progress: bool = True


def make_backend(name: str, *, voxel_size: float = 0.01, depth_max: float = 3.0, block_resolution: int = 16,
                 trunc_voxel_multiplier: float = 8.0, surfel_mesh: bool = False, **kwargs) -> FusionBackend:
    """A fusion backend by name (:data:`BACKENDS`), imported lazily; options it does not take are ignored,
    except ``surfel_mesh`` (the surfel backend's Poisson mesh, ``mesh=True``), which only the surfel backend
    accepts."""
    if name not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {name!r}")
    if surfel_mesh:
        if name != "surfel":
            raise ValueError(f"surfel_mesh applies to the surfel backend only, got backend {name!r} (the TSDF "
                             "backend always writes mesh.ply); pass backend='surfel' or surfel_mesh=False")
        kwargs["mesh"] = True
    from mapping.validation import check_fusion

    check_fusion(backend=name, voxel_size=voxel_size, depth_max=depth_max, block_resolution=block_resolution,
                 trunc_voxel_multiplier=trunc_voxel_multiplier, depth_min=kwargs.get("depth_min", 0.1))
    module_name, class_name = BACKENDS[name]
    try:
        import importlib

        cls = getattr(importlib.import_module(module_name), class_name)
    except (ImportError, AttributeError) as exc:
        raise RadiomapError(f"the {name} backend ({module_name.replace('.', '/')}.py: {class_name}) is not "
                            f"available in this installation ({exc}); use --backend tsdf") from None
    options = {"voxel_size": voxel_size, "depth_max": depth_max, "max_depth": depth_max,
               "block_resolution": block_resolution, "trunc_voxel_multiplier": trunc_voxel_multiplier, **kwargs}
    accepted = inspect.signature(cls).parameters
    if any(p.kind == p.VAR_KEYWORD for p in accepted.values()):
        return cls(**options)
    return cls(**{k: v for k, v in options.items() if k in accepted})


def make_tracker(*, depth_max: float = 3.0, motion_model: str = "constant_velocity", **kwargs):
    from mapping.tracking import FrameToModelTracker

    return FrameToModelTracker(depth_max=depth_max, motion_model=motion_model, **kwargs)


def load_vignetting_option(path: Path):
    """``--vignetting``: radiomap/radical/DSO files via :func:`radiometry.formats.load_vignetting`, or a
    ``.npy`` array V (H, W[, C]) such as a simulator's ``truth/vignetting.npy``."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        from radiometry.errors import CalibrationFileError
        from radiometry.arrays import load_array_file
        from radiometry.vignetting import LUTVignetting

        fix = "pass a float (H, W[, C]) .npy with finite V > 0"
        array = load_array_file(path, fix=fix)  # refuses complex, object, text and structured arrays
        try:
            return LUTVignetting(array, info={"source": str(path)})
        except (ValueError, TypeError) as exc:
            raise CalibrationFileError(f"{path}: not a usable vignetting array ({exc}); {fix}") from None
    from radiometry.formats import load_vignetting

    return load_vignetting(path)


def build_run(config: ReconstructConfig) -> dict[str, Any]:
    """The keyword arguments of :func:`reconstruct` for a configuration (the dataset opened, the models
    loaded, backend and tracker built)."""
    from mapping.datasets import open_dataset
    from mapping.validation import check_config, check_run, config_options
    from radiometry.formats import load_response

    check_config(config)  # the option ranges (mapping/validation.py), before anything is read
    dataset = open_dataset(config.sequence, format=config.format, depth_scale=config.depth_scale,
                           intrinsics=config.intrinsics, frames=config.frames)
    check_run(dataset, poses=config.poses, **config_options(config))  # intrinsics, ground truth, memory
    # a file is loaded; a model object (mapping.reconstruct_sequence) is used as it is
    response = load_response(config.response) if isinstance(config.response, (str, Path)) else config.response
    vignetting = load_vignetting_option(config.vignetting) if isinstance(config.vignetting, (str, Path)) \
        else config.vignetting
    if vignetting is not None:  # refuse a model of another aspect ratio now, before any result is written
        try:
            vignetting.check_size(dataset.height, dataset.width)
        except ModelMismatchError as exc:
            raise ModelMismatchError(f"{config.vignetting}: {exc}") from None
    colour_model = make_colour_model(response, vignetting, reference_exposure=config.reference_exposure)
    if config.exposure_compensation or (config.exposure_compensation is None and response is not None):
        if response is None:
            raise ValueError("exposure compensation needs a response (it acts on irradiance); pass --response, "
                             "or --no-exposure-compensation")
        from mapping.exposure_compensation import CompensatedColour, parse_reference

        colour_model = CompensatedColour(colour_model, export_reference=parse_reference(config.exposure_reference))
    backend = make_backend(config.backend, voxel_size=config.voxel_size, depth_max=config.depth_max,
                           block_resolution=config.block_resolution,
                           trunc_voxel_multiplier=config.trunc_voxel_multiplier, surfel_mesh=config.surfel_mesh)
    tracker = make_tracker(depth_max=config.depth_max, motion_model=config.motion_model) \
        if config.poses == "icp" else None
    return {"dataset": dataset, "colour_model": colour_model, "backend": backend, "tracker": tracker,
            "poses": config.poses, "progress": config.progress}

