"""Self-calibration from an RGB-D sequence: vignetting, per-frame exposure and white balance without a white sheet.

Surface points are sampled from the depth of every ``anchor_every``-th frame (a grid of pixels, in world
coordinates through the poses) and projected into every frame (pinhole ``K``). A sighting is kept when

- the projected depth agrees with that frame's depth (``depth_tolerance``: absolute + relative; occlusion),
- it lies away from depth edges (:func:`mapping.exposure_compensation.masks.depth_edges`),
- the surface is not seen at a grazing angle (``min_cos`` between the point's normal, from the anchor's depth,
  and the viewing ray),
- no channel in the pixel's window is saturated (``>= high``) or dark (``<= low``),

and its colour is the irradiance ``f^-1(I)`` (the given response; gamma 2.2 by default) averaged over a small
window (``window`` pixels, which forgives sub-pixel pose and depth error; by default an odd ~0.8 % of the image
width, at least 3: 5 at 640, 3 at 320 and 160). Points on strong texture are not sampled (``max_texture``: the
window's relative standard deviation in the anchor), for the same reason. (A fixed 5 px window at 160x120 covers
four times the surface it covers at 320x240, and on the demo's room its texture test rejected every point in the
top third of the image.)
The sightings go to :func:`radiometry.self_calibration.self_calibrate`.

:func:`run_self_calibration` is ``radiomap self-calibrate`` (and each task of ``radiomap batch self-calibrate``):
sequence -> poses (ground truth or ICP through :func:`mapping.pipeline.reconstruct`) -> sightings -> solver -> a
:class:`SelfCalibrationFolder` holding ``vignetting.npz`` (a LUT model with its standard error, readable by
``radiomap reconstruct --vignetting``), ``exposures.txt`` (``reconstruct``'s format), the figures and the summary.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from mapping.export import MANIFEST, RUNNING_MARKER, ResultsFolder
from radiometry.response import CameraResponse
from mapping.exposure_files import KnownExposures, match_exposure_file
from radiometry.self_calibration import Observations, SelfCalibration, SelfCalibrationError

log = logging.getLogger(__name__)

MARKER = "self_calibration.json"
FIGURES = ("vignetting.png", "stderr.png", "coverage.png", "exposures.png", "residuals.png")


class SelfCalibrationFolder(ResultsFolder):
    """The folder ``radiomap self-calibrate`` writes (OUT): refused without ``--force`` when it holds an earlier
    self-calibration; ``--force`` replaces that run's files only.

    Published as one set (:func:`radiometry.fileio.publish_set`): every file is written to a staging folder inside
    OUT (:meth:`file`) and renamed into place by :meth:`complete`, ``self_calibration.json`` last. Until then the
    previous self-calibration stands untouched, complete (no ``RUNNING`` marker is written over it): a run that is
    interrupted (Ctrl-C, SIGKILL, a failure) at any moment leaves the previous result or the new one, never
    neither (a SIGKILL during the renames leaves a journal that the next run rolls back). The previous run's files
    that the new set does not replace (figures of a run without ``--no-plots``) are removed after the commit."""

    what = "self-calibration"
    markers = (MARKER, RUNNING_MARKER, MANIFEST)
    refusal = "already holds a self-calibration; pass --force to overwrite it or choose another output folder"
    result_names = frozenset({MARKER, RUNNING_MARKER, MANIFEST, "vignetting.npz", "exposures.txt", "summary.txt",
                              "trajectory.txt", "groundtruth_tum.txt", *FIGURES})
    status_file = None

    def __init__(self, path, *, force: bool = False) -> None:
        self._publication = None     # the open publish_set context
        self._set = None             # its FileSet
        self._completed = False
        self._existed = Path(path).exists()
        self._wrote_running = False
        super().__init__(path, force=force)

    def _remove_previous_run(self) -> None:
        """Nothing is removed before the new set is published (:meth:`complete`)."""

    def _mark_running(self) -> None:
        if not self_calibration_complete(self.path):   # a complete previous result stays complete until replaced
            super()._mark_running()
            self._wrote_running = True

    def refuse(self) -> None:
        """End the run without a result and without a trace (a refusal, e.g. ``--strict``): the staged files go,
        the RUNNING marker this run wrote goes, the folder goes if this run created it and it is empty; a previous
        self-calibration stands untouched."""
        self.release()
        if self._wrote_running:
            (self.path / RUNNING_MARKER).unlink(missing_ok=True)
        if not self._existed:
            try:
                self.path.rmdir()
            except OSError:
                pass

    def file(self, name: str) -> Path:
        """Where to write ``name``: in the staging folder of the set (published by :meth:`complete`)."""
        from radiometry.fileio import publish_set

        if self._set is None:
            self._publication = publish_set(self.path / MARKER)
            self._set = self._publication.__enter__()
        return self._set.path(self.path / name)

    def staging(self) -> Path:
        """The staging folder (for writers that take a folder)."""
        return self.file(MARKER).parent

    def final(self, path) -> Path:
        """The published name of a staged path."""
        return self._set.final(path) if self._set is not None else Path(path)

    def complete(self) -> None:
        from mapping.export import _manifest_entries

        published: set[str] = set()
        if self._publication is not None:
            published = {p.name for p in self.staging().iterdir() if p.is_file()}
            previous = (set(self.result_names) | _manifest_entries(self.path)[0]) - published - {
                RUNNING_MARKER, MANIFEST}
            publication, self._publication, self._set = self._publication, None, None
            publication.__exit__(None, None, None)        # the commit: the new set replaces the old one
            for name in sorted(previous):                  # the old run's files the new set did not replace
                try:
                    (self.path / name).unlink()
                except FileNotFoundError:
                    pass
                except OSError as exc:
                    log.warning("could not remove %s of the previous self-calibration: %s", self.path / name, exc)
        self._completed = True
        super().complete()

    def __exit__(self, exc_type, exc, tb) -> None:
        from radiometry.errors import RadiomapError

        if exc_type is not None and issubclass(exc_type, RadiomapError):
            self.refuse()   # a refusal (data that cannot constrain V, too few poses, ...): no trace, no --force next
        else:
            super().__exit__(exc_type, exc, tb)

    def release(self) -> None:
        if self._publication is not None:   # not completed: the staged files go, the previous set stands
            publication, self._publication, self._set = self._publication, None, None
            try:
                publication.__exit__(RuntimeError, RuntimeError("self-calibration not completed"), None)
            except RuntimeError:
                pass
        if not self._completed:
            self.lock.release()     # the previous run's file list stays: its files are the ones in place
            return
        super().release()


@dataclass(frozen=True)
class SamplingOptions:
    """How surface points are sampled and sightings kept (see the module doc)."""

    anchor_every: int = 5
    points_per_row: int = 53      # sampling grid: one point every width // points_per_row pixels
    window: int | None = None     # None: odd, ~0.8 % of the image width, at least 3 (:func:`sampling_window`)
    depth_tolerance: tuple[float, float] = (0.02, 0.02)    # metres + fraction of the depth
    min_cos: float = 0.35
    max_texture: float = 0.08
    high: int = 250
    low: int = 5
    depth_min: float = 0.3
    depth_max: float = 4.0


@dataclass
class SelfCalibrationRun:
    """What :func:`run_self_calibration` returns: the solver's result, the frames' indices and timestamps in the
    sequence, the sightings' statistics, timings (wall seconds per stage and in total; ``cpu``: CPU seconds of
    the whole run, ``cpu_per_100_frames`` the same per 100 frames used), peak memory (MiB, the process's peak
    resident size) and the files."""

    result: SelfCalibration
    indices: np.ndarray
    timestamps: np.ndarray
    sampling: dict[str, Any]
    seconds: dict[str, float]
    peak_rss_mb: float
    files: dict[str, Path] = field(default_factory=dict)
    summary: str = ""
    checks: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------------
# sightings
# --------------------------------------------------------------------------------------------------
def sampling_window(width: int) -> int:
    """The default sampling window for images ``width`` pixels wide: odd, ~0.8 % of the width, at least 3."""
    return max(3, 2 * int(round(0.0035 * width)) + 1)


def _irradiance(rgb: np.ndarray, tables: np.ndarray, window: int) -> np.ndarray:
    """``f^-1(I)`` per channel, box-averaged over ``window`` pixels, float32 ``(H, W, 3)``."""
    import cv2

    e = np.stack([tables[:, c][rgb[:, :, c]] for c in range(3)], axis=2).astype(np.float32)
    return cv2.blur(e, (window, window)) if window > 1 else e


def _usable(frame, opts: SamplingOptions) -> np.ndarray:
    """Pixels whose window is neither clipped nor dark, with depth in range and away from depth edges."""
    import cv2

    from mapping.exposure_compensation.masks import depth_edges

    kernel = np.ones((opts.window, opts.window), np.uint8)
    hi = cv2.dilate(frame.rgb.max(axis=2), kernel) >= opts.high
    lo = cv2.erode(frame.rgb.min(axis=2), kernel) <= opts.low
    d = frame.depth
    ok = (d > opts.depth_min) & (d < opts.depth_max) & np.isfinite(d)
    return ok & ~hi & ~lo & ~depth_edges(d, dilation=max(2, opts.window // 2 + 1))


def _anchor_points(frame, pose: np.ndarray, tables: np.ndarray, opts: SamplingOptions
                   ) -> tuple[np.ndarray, np.ndarray]:
    """World points and normals ``(M, 3)`` sampled on a pixel grid of one frame's depth."""
    import cv2

    K = frame.K
    h, w = frame.depth.shape
    d = frame.depth.astype(np.float64)
    ys, xs = np.mgrid[0:h, 0:w]
    cam = np.stack([(xs - K[0, 2]) / K[0, 0] * d, (ys - K[1, 2]) / K[1, 1] * d, d], axis=2)
    s = 2
    gx = np.zeros_like(cam)
    gy = np.zeros_like(cam)
    gx[:, s:-s] = cam[:, 2 * s:] - cam[:, :-2 * s]
    gy[s:-s] = cam[2 * s:] - cam[:-2 * s]
    n = np.cross(gx, gy)
    n /= np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-12)
    ray = cam / np.maximum(np.linalg.norm(cam, axis=2, keepdims=True), 1e-12)
    cos = np.abs(np.sum(n * ray, axis=2))
    grey = _irradiance(frame.rgb, tables, 1).mean(axis=2)
    mean = cv2.blur(grey, (opts.window, opts.window))
    sq = cv2.blur(grey * grey, (opts.window, opts.window))
    texture = np.sqrt(np.maximum(sq - mean * mean, 0)) / np.maximum(mean, 1e-6)
    ok = _usable(frame, opts) & (cos > opts.min_cos) & (texture < opts.max_texture)
    ok[:s + 1], ok[-s - 1:], ok[:, :s + 1], ok[:, -s - 1:] = False, False, False, False
    grid = np.zeros_like(ok)
    stride = max(2, w // opts.points_per_row)
    off = stride // 2
    grid[off::stride, off::stride] = True
    sel = ok & grid
    pts, nrm = cam[sel], n[sel]
    R, t = pose[:3, :3], pose[:3, 3]
    return pts @ R.T + t, nrm @ R.T


def collect_observations(frames: list, poses: list[np.ndarray], response: CameraResponse, *,
                         options: SamplingOptions = SamplingOptions(), progress: bool = True
                         ) -> tuple[Observations, dict[str, Any]]:
    """Sightings of surface points in ``frames`` (RGB-D frames of one size and ``K``) at ``poses`` (camera to
    world), as the module doc describes; returns them and counts (points, sightings, per frame)."""
    from radiometry.progress import progress_bar

    tables = response.channel_tables(3).astype(np.float32)
    first = frames[0]
    h, w = first.depth.shape
    K = first.K
    opts = options if options.window is not None else replace(options, window=sampling_window(w))
    anchors = list(range(0, len(frames), opts.anchor_every))
    world, normals = [], []
    for a in anchors:
        p, n = _anchor_points(frames[a], poses[a], tables, opts)
        world.append(p)
        normals.append(n)
    world = np.concatenate(world) if world else np.zeros((0, 3))
    normals = np.concatenate(normals) if normals else np.zeros((0, 3))
    point_ids, frame_ids, us, vs, irr = [], [], [], [], []
    abs_tol, rel_tol = opts.depth_tolerance
    bar = progress_bar(total=len(frames), desc="sightings", unit="frame", enabled=progress)
    for j, frame in enumerate(frames):
        R, t = poses[j][:3, :3], poses[j][:3, 3]
        cam = (world - t) @ R
        z = cam[:, 2]
        front = z > opts.depth_min
        u = np.full(len(z), -1.0)
        v = np.full(len(z), -1.0)
        u[front] = K[0, 0] * cam[front, 0] / z[front] + K[0, 2]
        v[front] = K[1, 1] * cam[front, 1] / z[front] + K[1, 2]
        ui, vi = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
        inside = front & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
        idx = np.flatnonzero(inside)
        ui, vi = ui[idx], vi[idx]
        usable = _usable(frame, opts)[vi, ui]
        dz = frame.depth[vi, ui].astype(np.float64)
        agree = np.abs(dz - z[idx]) < abs_tol + rel_tol * z[idx]
        ray = cam[idx] / np.linalg.norm(cam[idx], axis=1, keepdims=True)
        cos = np.abs(np.sum((normals[idx] @ R) * ray, axis=1))
        keep = usable & agree & (cos > opts.min_cos)
        idx, ui, vi = idx[keep], ui[keep], vi[keep]
        e = _irradiance(frame.rgb, tables, opts.window)[vi, ui]
        good = np.all(e > 0, axis=1)
        point_ids.append(idx[good])
        frame_ids.append(np.full(int(good.sum()), j, np.int64))
        us.append(u[idx[good]])
        vs.append(v[idx[good]])
        irr.append(e[good].astype(np.float64))
        bar.update(1)
    bar.close()
    point = np.concatenate(point_ids) if point_ids else np.zeros(0, np.int64)
    # points seen once say nothing; renumber the rest densely
    counts = np.bincount(point, minlength=len(world))
    keep = counts[point] >= 2
    used, dense = np.unique(point[keep], return_inverse=True)
    obs = Observations(point=dense.astype(np.int64), frame=np.concatenate(frame_ids)[keep],
                       x=np.concatenate(us)[keep], y=np.concatenate(vs)[keep],
                       irradiance=np.concatenate(irr)[keep] if irr else np.zeros((0, 3)), resolution=(w, h),
                       n_frames=len(frames))
    stats = {"window": opts.window, "anchors": len(anchors), "points_sampled": int(len(world)),
             "points_used": int(len(used)), "sightings": int(len(obs.point)),
             "sightings_per_point": round(float(len(obs.point)) / max(len(used), 1), 2)}
    return obs, stats


# --------------------------------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------------------------------
def _poses(dataset, frames: list, source, *, depth_max: float, progress: bool, tracker: str = "auto"
           ) -> tuple[list, np.ndarray]:
    """Camera-to-world pose per frame (ground truth, a :class:`mapping.pose_files.PoseTable` or tracked by
    ``tracker``) and a bool array of the frames that have one."""
    from mapping.pose_files import PoseTable

    if source == "gt" or isinstance(source, PoseTable):
        poses = [f.pose for f in frames] if source == "gt" else list(source)
        have = np.array([p is not None for p in poses])
        if source == "gt" and have.any():
            from mapping.pose_convention import refuse_inverted_poses

            refuse_inverted_poses(frames, name=str(dataset.name),      # camera-to-world expected
                                  quaternion_file=getattr(dataset, "ground_truth_file", None))
        return [p if p is not None else np.eye(4) for p in poses], have
    if source != "icp":
        raise ValueError(f"poses must be 'gt', 'icp' or a PoseTable, got {source!r}")
    from mapping.factory import make_backend, make_tracker
    from mapping.pipeline import TrackingLostError, reconstruct

    backend = make_backend("tsdf", voxel_size=0.01, depth_max=depth_max)
    try:
        run = reconstruct(dataset, backend=backend, tracker=make_tracker(tracker, depth_max=depth_max),
                          poses="icp", output=None, progress=progress, write_mesh=False)
    except TrackingLostError as exc:   # the frames tracked before the loss still calibrate
        log.warning("%s; self-calibrating from those frames", exc)
        run = exc.run
    poses = [np.eye(4)] * len(frames)
    have = np.zeros(len(frames), bool)
    position = {f.index: k for k, f in enumerate(frames)}   # frame numbers of the sequence -> places in `frames`
    fused = [r for r in run.records if r.fused]
    for rec, pose in zip(fused, run.poses):
        poses[position[rec.index]] = pose
        have[position[rec.index]] = True
    return poses, have


def _peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _cpu_seconds() -> float:
    """CPU time (user + system) of this process so far: unlike the wall clock, hardly changed by other load."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run_self_calibration(sequence: str | Path, output: str | Path, *, response: CameraResponse | str | Path | None
                         = None, poses="gt", frames: slice | None = None, format: str | None = None,
                         depth_scale: float | None = None, intrinsics=None, options: SamplingOptions =
                         SamplingOptions(), solver: dict[str, Any] | None = None, plots: bool = True,
                         force: bool = False, progress: bool = True, manifest: dict | None = None,
                         tracker: str = "auto", poses_max_difference: float = 0.02, exposures=None,
                         holdout: str = "every:5", strict: bool = False) -> SelfCalibrationRun:
    """``radiomap self-calibrate``: self-calibrate ``sequence`` into the folder ``output`` (module doc).

    response: a model or file (default ``CameraResponse.gamma(2.2)``, recorded in the summary as an assumption);
    poses: ``"gt"``, ``"icp"`` (tracked by ``tracker``) or a trajectory file (:mod:`mapping.pose_files`, matched
    within ``poses_max_difference`` seconds); frames: a slice of the sequence; solver: keyword arguments of
    :func:`radiometry.self_calibration.self_calibrate`; manifest: the command's options, saved in the summary;
    exposures: known exposures (a file, :mod:`mapping.exposure_files`, or a :class:`KnownExposures`): only the
    frames without one get a fitted exposure; holdout: the frames withheld for the validation
    (:mod:`radiometry.self_calibration_validation`: ``every:N``, ``last:P%``, ``none``); strict: refuse (write
    nothing) unless the validation's verdict is that V helps (not when it does not help, nor when it is mixed).
    """
    from radiometry.api import as_response
    from radiometry.fileio import atomic_write_json, atomic_write_text
    from radiometry.self_calibration import coverage_text

    from mapping.datasets import describe_dataset, intrinsics_text, open_dataset
    from mapping.metrics import format_tum_trajectory

    seconds: dict[str, float] = {}
    t0, cpu0 = time.perf_counter(), _cpu_seconds()
    response_given = response is not None
    response = as_response(response) if response_given else CameraResponse.gamma(2.2)
    dataset = open_dataset(sequence, format=format, depth_scale=depth_scale, intrinsics=intrinsics,
                           frames=frames if frames is not None else slice(None))
    # everything that can refuse the run before any work, before the folder (and its RUNNING marker) exists
    from mapping.pose_files import resolve_poses

    poses = resolve_poses(poses, dataset, max_difference=poses_max_difference)
    from radiometry.self_calibration_validation import holdout_frames, parse_holdout

    parse_holdout(holdout)                    # a ValueError naming the accepted forms
    alignment = None
    if exposures is not None and not isinstance(exposures, KnownExposures):
        from mapping.exposure_alignment import check_alignment, enforce

        exposures = match_exposure_file(dataset, exposures, max_difference=poses_max_difference)
        alignment = check_alignment(dataset, exposures, response)   # a list off by a frame or more: refused
        enforce(alignment, exposures.source)
    if poses == "gt" and dataset.ground_truth() is None:
        raise SelfCalibrationError(f"{dataset.name}: the sequence has no ground-truth poses (--poses gt); use "
                                   "--poses icp or --poses FILE (a trajectory)")
    if poses != "icp":
        have = len(dataset.ground_truth()[0]) if poses == "gt" else poses.matched
        if have < 3:
            raise SelfCalibrationError(f"{dataset.name}: only {have} frame(s) have a pose (need 3); use more "
                                       "frames (--frames) or --poses icp")
    from mapping.factory import TRACKERS
    from radiometry.registry import validate_name

    validate_name(tracker, TRACKERS, "tracker")   # a ValueError naming the valid trackers
    with SelfCalibrationFolder(output, force=force) as folder:
        loaded = [dataset[i] for i in range(len(dataset))]
        seconds["read"] = time.perf_counter() - t0
        t = time.perf_counter()
        pose_list, have = _poses(dataset, loaded, poses, depth_max=options.depth_max, progress=progress,
                                 tracker=tracker)
        seconds["poses"] = time.perf_counter() - t
        use = np.flatnonzero(have)
        if len(use) < 3:
            raise SelfCalibrationError(f"{dataset.name}: only {len(use)} frame(s) have a pose (need 3); use more "
                                       "frames (--frames) or --poses icp")
        t = time.perf_counter()
        obs, stats = collect_observations([loaded[i] for i in use], [pose_list[i] for i in use], response,
                                          options=options, progress=progress)
        seconds["sightings"] = time.perf_counter() - t
        t = time.perf_counter()
        K = loaded[use[0]].K
        known = None if exposures is None else exposures.values[use]
        held = holdout_frames(len(use), holdout)
        result, checks = _solve_and_check(obs, held, response, known, holdout, {
            "centre": (float(K[0, 2]), float(K[1, 2])), **(solver or {})})
        seconds["solve"] = time.perf_counter() - t
        for line in checks["warnings"]:
            log.warning("%s", line)
        if strict and checks["refuse"]:
            folder.refuse()
            raise SelfCalibrationError(f"--strict: {checks['refuse']}; nothing written")
        indices = np.array([loaded[i].index for i in use])
        stamps = np.array([loaded[i].timestamp for i in use])
        cov_line, thin = coverage_text(result.coverage)
        truth = dataset.ground_truth()
        files = {"vignetting": result.vignetting.save(folder.file("vignetting.npz")),
                 "exposures": atomic_write_text(folder.file("exposures.txt"),
                                                exposures_text(result, indices, stamps)),
                 "trajectory": atomic_write_text(folder.file("trajectory.txt"), format_tum_trajectory(
                     stamps, np.stack([pose_list[i] for i in use])))}
        if truth is not None:   # the ground truth beside the trajectory, as a TUM file (evo)
            files["groundtruth"] = atomic_write_text(folder.file("groundtruth_tum.txt"), format_tum_trajectory(*truth))
        if plots:
            from mapping.self_calibration_plots import save_figures

            files.update(save_figures(folder.staging(), result, indices))
        files = {k: folder.final(v) for k, v in files.items()}    # the names they are published under
        seconds["total"] = time.perf_counter() - t0
        seconds["cpu"] = _cpu_seconds() - cpu0
        seconds["cpu_per_100_frames"] = 100.0 * seconds["cpu"] / len(use)
        run = SelfCalibrationRun(result=result, indices=indices, timestamps=stamps, sampling=stats,
                                 seconds={k: round(v, 2) for k, v in seconds.items()}, peak_rss_mb=_peak_rss_mb(),
                                 files=files)
        run.checks = checks
        run.summary = summary_text(run, dataset.name, response_given, str(poses), cov_line) + "\n" + \
            "\n".join(checks["lines"] + [intrinsics_text(dataset)])   # which intrinsics, from where
        files["summary"] = folder.final(atomic_write_text(folder.file("summary.txt"), run.summary + "\n"))
        atomic_write_json(folder.file(MARKER), {
            "sequence": describe_dataset(dataset), "poses": str(poses),
            "response": "given" if response_given else "assumed gamma 2.2 (CameraResponse.gamma(2.2))",
            "frames_used": int(len(use)), "sampling": stats, "options": options.__dict__,
            "solver": result.info, "coverage": cov_line, "thin_regions": thin,
            "residual_log_scale_before": [_mad(r) for r in result.residuals_before],
            "residual_log_scale_after": [_mad(r) for r in result.residuals_after],
            "exposures_given": None if exposures is None else exposures.describe(),
            "exposures_alignment": None if alignment is None else alignment.to_json(),
            "validation": checks["validation"], "ambiguity": result.info.get("ambiguity"),
            "plausibility": checks["plausibility"], "warnings": checks["warnings"],
            "seconds": run.seconds, "peak_rss_mb": round(run.peak_rss_mb, 1),
            "files": {k: str(v) for k, v in files.items()}, "run": manifest or {}})
        folder.complete()
    return run


def _solve_and_check(obs: Observations, held: np.ndarray, response: CameraResponse, known: np.ndarray | None,
                     holdout: str, solver: dict[str, Any]) -> tuple[SelfCalibration, dict[str, Any]]:
    """Solve on the frames not ``held``, validate on the held ones, check V's plausibility: ``(result, checks)``
    with ``checks``: ``validation`` (a dict or None), ``plausibility`` (sentences), ``lines`` (for the summary),
    ``warnings`` (what the user must hear) and ``refuse`` (why ``--strict`` refuses, or None)."""
    from radiometry.self_calibration import self_calibrate
    from radiometry.self_calibration_checks import plausibility
    from radiometry.self_calibration_validation import subset, validate

    held_sighting = held[obs.frame]
    train = subset(obs, ~held_sighting) if held.any() else obs
    result = self_calibrate(train, exposures=known, **solver)
    lines, warnings, refuse = [], [], None
    validation = None
    if held.any():
        found = validate(result, train, subset(obs, held_sighting), response.channel_tables(obs.channels),
                         holdout)
        if found is None:
            lines.append(f"validation: no withheld frame ({holdout}) sees points of the fitted frames; not validated")
            warnings.append("V could not be validated (no withheld frame shares points with the fitted ones)")
        else:
            validation = found.as_dict()
            lines.append(found.text())
            fill = np.isnan(result.exposures) & np.isfinite(found.exposures)
            result.exposures[fill] = found.exposures[fill]          # withheld frames: k predicted with V
            if not found.helps:
                figures = (f"L1 {np.mean(found.l1_without):.2f} -> {np.mean(found.l1_with):.2f} levels, PSNR "
                           f"{np.mean(found.psnr_without):.2f} -> {np.mean(found.psnr_with):.2f} dB")
                refuse = (f"V's held-out figures disagree ({found.verdict_text()}; {figures})"
                          if found.verdict == "mixed" else
                          f"V does not predict withheld frames better than no V ({figures})")
                warnings.append(f"{refuse}: do not use this vignetting.npz (usual causes: too little motion, a wrong "
                                "response, surfaces that are not matte, poses or depth that do not fit the colour)")
                lines.append(f"WARNING: {warnings[-1]}")
    else:
        lines.append("validation: none (--holdout none): nothing tells whether V helps")
    ambiguity = result.info.get("ambiguity")
    if ambiguity:
        lines.append(ambiguity)
        warnings.append(ambiguity)
    if result.info.get("weak_tilt"):        # said, not a warning: the stated error covers it
        lines.append(result.info["weak_tilt"])
    notes = plausibility(result.vignetting.evaluate(), result.vignetting.stderr, result.info["centre"])
    if notes:
        lines.extend(f"implausible: {n}" for n in notes)
        warnings.append("implausible V: " + "; ".join(notes))
    return result, {"validation": validation, "plausibility": notes, "lines": lines, "warnings": warnings,
                    "refuse": refuse}


def self_calibration_complete(folder: Path) -> bool:
    """A self-calibration folder is complete when its record (``self_calibration.json``) is there and no RUNNING
    marker (a batch skips it)."""
    return (Path(folder) / MARKER).is_file() and not (Path(folder) / RUNNING_MARKER).exists()


def self_calibration_rows(folder: Path) -> list[dict]:
    """The batch summary's row of a complete self-calibration folder (from its ``self_calibration.json``)."""
    import json

    doc = json.loads((Path(folder) / MARKER).read_text(encoding="utf-8"))
    seconds = doc["seconds"]
    return [{"frames": doc["frames_used"], "sightings": doc["sampling"]["sightings"],
             "total s": seconds.get("total"), "cpu s/100 frames": seconds.get("cpu_per_100_frames"),
             "resid after %": round(100 * max(doc["residual_log_scale_after"]), 2),
             "thin regions": ", ".join(doc["thin_regions"]) or "-", "peak MiB": doc["peak_rss_mb"]}]


def _mad(res: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(res - np.median(res))))


def exposures_text(result: SelfCalibration, indices: np.ndarray, stamps: np.ndarray) -> str:
    """``exposures.txt`` as ``radiomap reconstruct`` writes it (:mod:`mapping.exposure_compensation.records`):
    ``index timestamp k_r k_g k_b correspondences source``; the first frame is the ``reference`` (k = 1), the
    others were estimated against the surface points (``map``); frames without sightings are left out."""
    lines = ["# radiomap per-frame exposure estimates, relative to the first fused frame (k = 1)\n",
             "# self-calibrated (radiomap self-calibrate): correspondences = sightings of surface points\n",
             "# index timestamp k_r k_g k_b correspondences source\n"]
    for j, (idx, ts) in enumerate(zip(indices, stamps)):
        k = result.exposures[j]
        if not np.all(np.isfinite(k)):
            continue
        source = "reference" if j == 0 else "map"
        lines.append(f"{int(idx)} {float(ts):.6f} {k[0]:.6f} {k[1]:.6f} {k[2]:.6f} {int(result.sightings[j])} "
                     f"{source}\n")
    return "".join(lines)


def summary_text(run: SelfCalibrationRun, name: str, response_given: bool, poses: str, coverage_line: str) -> str:
    """What ``radiomap self-calibrate`` prints and saves as ``summary.txt``."""
    from radiometry.tables import format_table

    res = run.result
    v = res.vignetting.evaluate()
    se = res.vignetting.stderr
    rows = []
    for c, ch in enumerate("RGB"[:v.shape[2]]):
        corners = float(np.mean([v[0, 0, c], v[0, -1, c], v[-1, 0, c], v[-1, -1, c]]))
        k = res.exposures[:, c]
        rows.append({"channel": ch, "centre_x": res.info["centre"][c][0], "centre_y": res.info["centre"][c][1],
                     "corner/centre": round(corners, 4), "V_min": round(float(v[:, :, c].min()), 4),
                     "stderr_median_%": round(100 * float(np.median(se[:, :, c])), 3),
                     "k_min": round(float(np.nanmin(k)), 4), "k_max": round(float(np.nanmax(k)), 4),
                     "resid_before_%": round(100 * _mad(res.residuals_before[c]), 2),
                     "resid_after_%": round(100 * _mad(res.residuals_after[c]), 2)})
    s = run.sampling
    return "\n".join([
        f"self-calibration of {name}: {len(run.indices)} frames, poses {poses}, response "
        f"{'given' if response_given else 'assumed gamma 2.2 (pass --response for a calibrated one)'}",
        f"surface points: {s['points_used']} of {s['points_sampled']} sampled in {s['anchors']} anchor frames, "
        f"{s['sightings']} sightings ({s['sightings_per_point']} per point)",
        coverage_line,
        format_table(rows),
        "resid: robust (MAD) scale of log-irradiance residuals with V = 1 (before) and with the fitted V (after)",
        f"time: {', '.join(f'{k} {v:.1f} s' for k, v in run.seconds.items())}; peak memory {run.peak_rss_mb:.0f} MiB",
    ])


__all__ = ["FIGURES", "MARKER", "SamplingOptions", "SelfCalibrationFolder", "SelfCalibrationRun",
           "collect_observations", "exposures_text", "run_self_calibration", "sampling_window",
           "self_calibration_complete", "self_calibration_rows", "summary_text"]
