"""The mapping pipeline: ``loader[i] -> RGBDFrame -> tracking -> radiometric correction -> fusion ->
(disagreement histogram) -> results folder``.

:func:`reconstruct` is the core: plain keyword arguments (a dataset, a colour model, a fusion backend, a
tracker or ground-truth poses), one loop over frames, a :class:`~mapping.results.RunResult`.
:func:`mapping.factory.build_run` turns a :class:`~mapping.factory.ReconstructConfig` (what the CLI collects)
into those arguments; :mod:`mapping.results` writes the results folder.

Per frame (ICP mode), the contract between the parts (:class:`~mapping.fusion.base.FusionBackend`,
:class:`~mapping.colour.ColourModel`)::

    frame   = dataset[i]                                      # lazy load
    pose    = tracker.track(frame.depth, K, view_prev, pose_prev)   # frame-to-model ICP; failure -> skip
    view    = backend.render_for_frame(frame.depth, K, pose)  # the map at this pose, BEFORE fusing this frame
    colour  = colour_model.to_map(frame, view, pose)          # FrameColour: map units, valid pixels, reason
    pairs   = backend.integrate(frame.depth, colour.colour, K, pose, view=view, valid=colour.valid)
    histogram.add(colour_model.display_l1(pairs.map_colour, pairs.sample_colour))
    view_prev, pose_prev = view, pose                         # the tracker's target for frame i + 1

With ``holdout_every = N`` every N-th frame (:mod:`mapping.holdout`) is tracked (or given its ground-truth pose)
and then withheld: never rendered for, coloured, fused or measured, and not counted as skipped (one that comes
before the map exists has no pose: it cannot found the map). After the loop the final map is rendered at the
withheld frames' poses and judged against them (``RunResult.holdout``). With ``colour_map`` the colour-map stage
(:func:`mapping.colour_map.colour_map_for_run`) follows, judged by those frames when there are any
(``RunResult.colour_map``). Only then are the results written and the folder marked complete: a crash or Ctrl-C
anywhere before leaves it marked unfinished (``RUNNING``, ``metrics.json`` status ``failed`` or ``interrupted``).

One ray cast per frame serves both the histogram (the map before this frame) and the tracking of the next
frame (the map at the last pose, lacking only the last frame), like Open3D's dense SLAM loop which also
casts once per frame. When that view covers less than ``refresh_coverage`` of the frame's valid depth (the
first frame; the camera entering unmapped space) the map is cast again after fusion for the tracker.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from mapping.colour import ColourModel, RawIntensity
from mapping.datasets.base import RGBDDataset
from mapping.fusion.base import FusionBackend, masked_depth
from mapping.histogram import DisagreementHistogram
from mapping.holdout import HELD_OUT, backend_renderer, check_holdout_every, evaluate_holdout, is_held_out
from mapping.metrics import ATEResult, absolute_trajectory_error
from mapping.results import FrameRecord, RunResult, backend_stats, peak_rss_mb, write_partial, write_results
from radiometry.errors import RadiomapError

log = logging.getLogger(__name__)

POSE_SOURCES = ("icp", "gt")
STAGES = ("load", "track", "render", "colour", "fuse", "histogram")


class TrackingError(RadiomapError):
    """Tracking failed on too many consecutive frames: the run stops (skipping frames cannot recover it)."""


class TrackingLostError(TrackingError):
    """Tracking was lost for good after enough frames were fused for a map: the map of the frames fused before
    the loss was kept and written (``metrics.json`` status ``partial``, with the reason), and the run fails.
    ``run``: that partial :class:`~mapping.results.RunResult`."""

    def __init__(self, message: str, run: RunResult) -> None:
        super().__init__(message)
        self.run = run


def reconstruct(dataset: RGBDDataset, *, colour_model: ColourModel | None = None,
                backend: FusionBackend, tracker=None, poses: str = "icp", initial_pose: np.ndarray | None = None,
                output=None, refresh_coverage: float = 0.5, max_consecutive_failures: int = 30,
                progress: bool = True, histogram_label: str | None = None,
                write_mesh: bool = True, holdout_every: int | None = None, colour_map: str | None = None,
                colour_map_options: Mapping[str, Any] | None = None, mesh_formats: Sequence[str] = ("ply",),
                prefetch: int = 1) -> RunResult:
    """Track (or take ground-truth poses), correct, fuse and measure colour disagreement over a sequence.

    dataset:       an :class:`~mapping.datasets.base.RGBDDataset` (frame range and stride applied).
    colour_model:  a :class:`~mapping.colour.ColourModel` (default: raw intensities, no correction).
    backend:       a :class:`~mapping.fusion.base.FusionBackend` (TSDF or surfel).
    tracker:       a :class:`~mapping.tracking.FrameToModelTracker` for ``poses="icp"``.
    poses:         ``"icp"`` (track), ``"gt"`` (the dataset's ground truth; frames without it are skipped) or a
                   :class:`mapping.pose_files.PoseTable` (poses from a file, one per frame; frames without one are
                   skipped).
    initial_pose:  the first frame's pose in ICP mode (default: its ground truth when known, else identity).
    output:        None, or a :class:`~mapping.export.ResultsFolder` to write the results into.
    refresh_coverage: re-cast the map after fusion for the tracker when the pre-fusion view covers less than
                   this fraction of the frame's valid depth.
    max_consecutive_failures: tracking is lost when it fails this many frames in a row: the loop stops; when the
                   frames fused before make a map (:func:`mapping.validation.check_fused` over the whole sequence)
                   it is finished and written as usual with ``status: partial`` and the reason in
                   ``metrics.json``, then :class:`TrackingLostError` is raised; otherwise :class:`TrackingError`
                   (the folder stays marked unfinished).
    progress:      a progress bar on stderr when it is a terminal (:func:`radiometry.progress.progress_bar`).
    write_mesh:    export the map's mesh into ``output``.
    mesh_formats:  its files (:data:`mapping.validation.MESH_FORMATS`; PLY only by default, ``npz`` adds
                   ``mesh_colours.npz`` with the map-unit colours); also the colour-map mesh's unless
                   ``colour_map_options`` gives ``formats``.
    holdout_every: None (fuse every frame) or N in ``2 .. len(dataset) - 1``: withhold every N-th frame from fusion and
                   judge the final map by them (:func:`mapping.holdout.evaluate_holdout`; ``holdout.csv``).
    colour_map:    None, ``rigid`` or ``non-rigid``: after the loop (and the held-out evaluation) optimise the map's
                   colours (:func:`mapping.colour_map.colour_map_for_run`; ``mesh_colourmap.*`` and ``colour_map.json``
                   in ``output``, the outcome in ``RunResult.colour_map``, its line in ``summary.txt``), before the
                   folder is marked complete.
    colour_map_options: keywords of :func:`~mapping.colour_map.colour_map_for_run` (``formats``, ``iterations``, ...).
    prefetch:      frames read ahead by a background thread while the loop works on the current one, for datasets
                   that declare ``thread_safe_reads`` (:class:`mapping.datasets.base.RGBDDataset`; others are read
                   one at a time)
                   (:class:`mapping.prefetch.FramePrefetcher`; the same frames, in order, the same errors); 0 reads
                   each frame when its turn comes.
    """
    from mapping.pose_files import PoseTable

    if isinstance(poses, PoseTable):
        if len(poses) != len(dataset):
            raise ValueError(f"the pose table of {poses.source} has {len(poses)} entries for {len(dataset)} frames")
    elif poses not in POSE_SOURCES:
        raise ValueError(f"poses must be one of {', '.join(POSE_SOURCES)} or a PoseTable, got {poses!r}")
    if poses == "icp" and tracker is None:
        raise ValueError("poses='icp' needs a tracker (mapping.tracking.FrameToModelTracker)")
    if not 0 <= refresh_coverage <= 1:
        raise ValueError(f"refresh_coverage must be in [0, 1], got {refresh_coverage}")
    holdout_every = 0 if holdout_every is None else check_holdout_every(holdout_every, len(dataset))
    from mapping.prefetch import FramePrefetcher, check_ahead

    check_ahead(prefetch)
    if colour_map is not None:   # a wrong name fails before the run, not after it
        from mapping.colour_map import OPTIMISERS
        from radiometry.registry import validate_name

        colour_map = validate_name(colour_map, OPTIMISERS, "colour-map method")
    colour_model = colour_model or RawIntensity()
    loop = _Loop(dataset, colour_model, backend, tracker, poses, initial_pose, refresh_coverage,
                 max_consecutive_failures, histogram_label or colour_model.name, holdout_every)
    bar = _progress_bar(len(dataset), progress, dataset.name)
    # read ahead only where the dataset says its reads are safe in another thread (mapping.datasets.base)
    ahead = prefetch if getattr(dataset, "thread_safe_reads", False) is True else 0
    frames = FramePrefetcher(dataset, ahead)   # starts reading frame 0 in its thread (ahead > 0)
    loop.read = frames.get
    status = "failed"
    lost: TrackingError | None = None
    try:
        for i in range(len(dataset)):
            try:
                loop.step(i)
            except TrackingError as exc:   # lost for good: keep what was fused if it makes a map (below)
                loop.advance(bar)
                lost = exc
                break
            loop.advance(bar)
        try:
            loop.check_fused(whole_sequence=lost is not None)  # too little fused fails: mapping/validation.py
        except RadiomapError:
            if lost is not None:   # lost before a map existed: the loss is the error
                raise lost from None
            raise
        status = "complete" if lost is None else "partial"
    except KeyboardInterrupt:
        status = "interrupted"
        loop.drop_unfinished()
        raise
    finally:
        frames.stop()    # nothing is read after the loop ends (the thread is joined below, after the partial results)
        try:
            bar.close()
            run = loop.result(status)
            if lost is not None:
                run.partial_reason = str(lost)
            if status not in ("complete", "partial") and output is not None:
                write_partial(run, backend, output)
        finally:
            frames.close()   # joins the reading thread (it finishes at most the frame it is reading)
    try:   # the rest of the run: until write_results completes the folder, a failure leaves it unfinished
        run.map_stats = backend_stats(backend)
        run.ate = _ate(run, dataset, poses)
        if holdout_every:
            positions = sorted(run.held_out_poses)
            run.holdout = evaluate_holdout(_Frames(dataset, positions), [run.held_out_poses[i] for i in positions],
                                           backend_renderer(backend), colour_model)
            run.holdout.settings["every"] = holdout_every
        if colour_map is not None:
            from mapping.colour_map import colour_map_for_run

            run.colour_map = colour_map_for_run(run, dataset, backend, colour_model, method=colour_map,
                                                depth_max=backend.depth_max,
                                                folder=None if output is None else output.path,
                                                **{"formats": mesh_formats, **dict(colour_map_options or {})})
        if output is not None:
            write_results(run, dataset, colour_model, backend, tracker, output, write_mesh=write_mesh,
                          mesh_formats=tuple(mesh_formats))
    except BaseException as exc:
        run.status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        if output is not None:
            write_partial(run, backend, output)
        raise
    if lost is not None:
        where = "" if output is None else f"; the map of those frames is in {output.path} (metrics.json status partial)"
        raise TrackingLostError(f"{lost}; kept the {run.fused} of {len(dataset)} frames fused before the loss{where}",
                                run)
    return run


class _Loop:
    """The per-frame steps of :func:`reconstruct` and the state they share."""

    def __init__(self, dataset, colour_model: ColourModel, backend: FusionBackend, tracker, poses, initial_pose,
                 refresh_coverage, max_failures, label, holdout_every: int = 0, read=None) -> None:
        self.read = read or dataset.__getitem__   # frame i (mapping.prefetch.FramePrefetcher.get: read ahead)
        self.dataset, self.colour_model, self.backend, self.tracker = dataset, colour_model, backend, tracker
        self.poses, self.initial_pose = poses, initial_pose
        self.refresh_coverage, self.max_failures = refresh_coverage, max_failures
        self.histogram = DisagreementHistogram(label=label)
        self.records: list[FrameRecord] = []
        self.stamps: list[float] = []
        self.est: list[np.ndarray] = []
        self.stage_seconds = {k: 0.0 for k in STAGES}
        self.track_view = None          # the map as the tracker sees it: (view, pose it was rendered at)
        self.failures = 0
        self.depth_valid = 0            # valid depth pixels seen, and those at or beyond the depth range
        self.depth_far = 0
        self.skipped = 0   # frames done, neither fused nor withheld (the bar's postfix)
        self.holdout_every = holdout_every
        self.held_out: dict[int, np.ndarray | None] = {}  # position -> pose of each withheld frame (None: no pose)
        self.started = time.perf_counter()

    @contextlib.contextmanager
    def timed(self, stage: str):
        """Add the time the block takes to ``stage``'s total (:data:`STAGES`)."""
        t = time.perf_counter()
        try:
            yield
        finally:
            self.stage_seconds[stage] += time.perf_counter() - t

    # ---------------------------------------------------------------- one frame
    def step(self, i: int) -> None:
        with self.timed("load"):
            frame = self.read(i)
        record = FrameRecord(frame.index, float(frame.timestamp), False)
        self.records.append(record)
        self._count_far_depth(frame.depth)
        held_out = is_held_out(i, self.holdout_every)
        pose = self._pose(frame, record, held_out, i)
        # withheld after its pose is known (ICP tracks it); by position only, whatever the pose source, so that a
        # comparison's ground-truth runs withhold exactly the frames its tracking run withheld
        if held_out:
            self.held_out[i] = pose
            record.reason = record.reason or HELD_OUT
            return
        if pose is None:
            return
        with self.timed("render"):  # the map before this frame, at its pose (reused by fusion and tracking)
            view = self.backend.render_for_frame(frame.depth, frame.K, pose)
        with self.timed("colour"):
            colour = self.colour_model.to_map(frame, view, pose)
        if self._fusable_depth(masked_depth(frame.depth, colour.valid)) == 0:
            record.reason = colour.reason or "colour rejected"
            return
        with self.timed("fuse"):
            pairs = self.backend.integrate(frame.depth, colour.colour, frame.K, pose, view=view, valid=colour.valid,
                                           frame_index=frame.index)
        with self.timed("histogram"):
            self._measure(pairs, record)
        record.fused = True
        self.stamps.append(float(frame.timestamp))
        self.est.append(np.asarray(pose, dtype=np.float64))
        if self.poses == "icp":
            with self.timed("render"):
                self._keep_for_tracking(frame, pose, view)

    def _pose(self, frame, record: FrameRecord, held_out: bool = False, position: int = 0) -> np.ndarray | None:
        """The frame's pose, or None (with the reason recorded) when it must not be fused. Tracking needs a map:
        until a frame has been fused, each frame with depth founds it, except a withheld one (no pose)."""
        if self.poses != "icp":   # the ground truth, or a pose table (a file's poses)
            given = frame.pose if self.poses == "gt" else self.poses[position]
            if given is None:
                record.reason = "no ground-truth pose" if self.poses == "gt" else self.poses.reason
            elif self._fusable_depth(frame.depth) == 0:  # nothing to fuse (Open3D would abort the integration)
                record.reason = "no depth within the fusion range"
                return None
            return given
        if self.track_view is None:  # nothing fused yet (none had depth, or its colour was rejected)
            if held_out:
                return None
            if self._fusable_depth(frame.depth) < 1000:
                record.reason = "no depth to start the map"
                return None
            pose = _initial_pose(frame, self.initial_pose)
            self.tracker.start(pose)
            return pose
        view, view_pose = self.track_view
        with self.timed("track"):  # photometric trackers get the frame's colour in map units
            colour = _tracking_colour(self.colour_model, frame) if self.tracker.needs_colour else None
            result = self.tracker.track(frame.depth, frame.K, view, view_pose, colour=colour)
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

    def _count_far_depth(self, depth: np.ndarray) -> None:
        """Count the depth the range cuts away: a scene deeper than depth_max leaves ICP fewer surfaces (two
        walls and a floor can become one wall and a floor, along which it slides)."""
        valid = depth > 0
        self.depth_valid += int(np.count_nonzero(valid))
        self.depth_far += int(np.count_nonzero(valid & (depth >= self.backend.depth_max)))

    def _fusable_depth(self, depth: np.ndarray) -> int:
        """Depth pixels within the backend's range (a frame of only far or no depth has nothing to fuse)."""
        return int(np.count_nonzero((depth > self.backend.depth_min) & (depth < self.backend.depth_max)))

    def _measure(self, pairs, record: FrameRecord) -> None:
        """Add the frame's colour pairs to the histogram, in display units."""
        if pairs is None or not len(pairs):
            return
        d = self.colour_model.display_l1(pairs.map_colour, pairs.sample_colour)
        record.pairs = self.histogram.add_distances(d)
        record.mean_l1 = float(d.mean())

    def _keep_for_tracking(self, frame, pose: np.ndarray, view) -> None:
        """The next frame is tracked against this frame's pre-fusion view, unless it shows too little of the
        scene (the first frame, the camera entering unmapped space): then the map is cast again."""
        valid = np.count_nonzero(frame.depth > 0)
        if np.count_nonzero(view.depth > 0) < self.refresh_coverage * valid:
            view = self.backend.render(pose, frame.K, frame.height, frame.width)
        self.track_view = (view, pose)

    # ---------------------------------------------------------------- the run
    def advance(self, bar) -> None:
        """One frame done: the bar advances, and a DEBUG line says so ("frame 3 of 5: fused"; ``-vv``)."""
        record = self.records[-1]
        held_out = len(self.records) - 1 in self.held_out
        state = "fused" if record.fused else "withheld" if held_out else "skipped"
        log.debug("frame %d of %d: %s", len(self.records), len(self.dataset),
                  state if record.fused else f"{state} ({record.reason or 'no reason'})")
        if not (record.fused or held_out):
            self.skipped += 1
            bar.set_postfix(skipped=self.skipped, refresh=False)
        bar.update(1)

    def check_fused(self, whole_sequence: bool = False) -> None:
        """Fail when too little was fused (of the frames processed, or with ``whole_sequence`` of all the
        sequence's frames: a run cut short by a tracking loss)."""
        from mapping.validation import check_fused

        run = self.result("running")   # its counts: the withheld frames are neither fused nor skipped
        total = len(self.dataset) if whole_sequence else run.frames
        check_fused(run.fused, total - run.held_out, run.skip_reasons(),
                    str(getattr(self.dataset, "root", None) or self.dataset.name or "the sequence"))  # a folder, if any

    def drop_unfinished(self) -> None:
        """Forget the frame an interruption cut short (neither fused nor skipped for a reason): it was not
        processed, so it is not counted as skipped."""
        if self.records and not self.records[-1].fused and not self.records[-1].reason:
            self.records.pop()

    def result(self, status: str) -> RunResult:
        return RunResult(stamps=np.asarray(self.stamps), poses=np.asarray(self.est).reshape(-1, 4, 4),
                         histogram=self.histogram, records=self.records, seconds=time.perf_counter() - self.started,
                         stage_seconds=dict(self.stage_seconds), ate=None, map_stats={}, peak_rss_mb=peak_rss_mb(),
                         status=status, depth_beyond_range=self.depth_far / max(self.depth_valid, 1),
                         held_out_poses=dict(self.held_out), requested=len(self.dataset))


class _Frames:
    """The dataset's frames at ``positions``, read when asked for (the held-out frames, judged one at a time)."""

    def __init__(self, dataset, positions: list[int]) -> None:
        self.dataset, self.positions = dataset, positions

    def __len__(self) -> int:
        return len(self.positions)

    def __getitem__(self, k: int):
        return self.dataset[self.positions[k]]


def _tracking_colour(colour_model, frame):
    from mapping.tracking_photometric import tracking_colour  # loads Open3D: only for photometric trackers

    return tracking_colour(colour_model, frame.rgb)


def _initial_pose(frame, initial_pose):
    if initial_pose is not None:
        return np.asarray(initial_pose, dtype=np.float64)
    if frame.pose is not None:
        return np.asarray(frame.pose, dtype=np.float64)
    return np.eye(4)


def _progress_bar(n: int, enabled: bool, name: str):
    from radiometry.progress import progress_bar

    return progress_bar(total=n, desc=f"reconstruct {name}".strip(), enabled=enabled, leave=False)


def _ate(run: RunResult, dataset, poses) -> ATEResult | None:
    if poses == "gt":   # tracked or from a file: judged against the ground truth
        return None
    gt = dataset.ground_truth()
    if gt is None:
        return None
    if len(run.stamps) < 3:
        run.ate_note = f"{len(run.stamps)} pose(s) in the trajectory; the alignment to the ground truth needs 3"
        return None
    try:
        return absolute_trajectory_error(run.stamps, run.poses, gt[0], gt[1])
    except ValueError as exc:
        log.warning("no ATE: %s", exc)
        return None


__all__ = ["POSE_SOURCES", "STAGES", "TrackingError", "TrackingLostError", "reconstruct"]
