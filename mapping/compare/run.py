"""The comparison run: every method fuses the same frames at identical poses (:func:`compare`).

Identical poses. With ``poses="gt"`` every run takes the dataset's ground truth. With ``poses="icp"`` the
first method's run tracks and every later run fuses at exactly the poses it estimated, skipping exactly the
frames it skipped (:class:`FixedPoses`). Point-to-plane ICP (the default tracker) uses depth only, so the choice
of method does not matter; the photometric trackers (``tracker_options={"name": "hybrid"}`` or
``"coloured-icp"``) track on the FIRST method's colour, so the shared poses depend on it (the summary names it).
``CompareResult.poses_identical`` checks it after the fact.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mapping.colour import IrradianceColour, RawIntensity
from mapping.compare.colour_error import colour_error
from mapping.compare.geometry import map_geometry
from mapping.compare.methods import BRIGHTNESS, Method, equal_brightness
from mapping.compare.outputs import write_compare_json, write_outputs
from mapping.compare.results import CompareResult, ComparisonFolder, MethodResult
from radiometry.errors import RadiomapError
from radiometry.response import CameraResponse


class FixedPoses:
    """A dataset view whose frames carry given poses instead of their own (``None``: the frame has no pose,
    so :func:`mapping.pipeline.reconstruct` with ``poses="gt"`` skips it); ``on_frame`` is called once per
    frame read (the shared progress bar)."""

    def __init__(self, dataset, poses: Sequence[np.ndarray | None] | None = None, *,
                 on_frame: Callable[[], None] | None = None) -> None:
        if poses is not None and len(poses) != len(dataset):
            raise ValueError(f"poses must have one entry per frame ({len(dataset)}), got {len(poses)}")
        self.dataset = dataset
        self.poses = None if poses is None else list(poses)
        self.on_frame = on_frame
        self.name = getattr(dataset, "name", "")
        self.K = dataset.K
        self.width = dataset.width
        self.height = dataset.height

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int):
        frame = self.dataset[index]
        if self.on_frame is not None:
            self.on_frame()
        if self.poses is None:
            return frame
        pose = self.poses[index]
        return dataclasses.replace(frame, pose=None if pose is None else np.array(pose, dtype=np.float64))

    def ground_truth(self):
        return self.dataset.ground_truth()


def compare(dataset, methods: Sequence[Method], *, output: str | Path, backend: str = "tsdf", poses: str = "gt",
            voxel_size: float = 0.01, depth_max: float = 3.0, backend_options: Mapping[str, Any] | None = None,
            tracker_options: Mapping[str, Any] | None = None, brightness: str = "mean", scene=None,
            display_response: CameraResponse | None = None, views: int = 3, render_width: int = 320,
            progress: bool = True, force: bool = False, title: str | None = None,
            report_sections: Sequence[Any] | Callable[[CompareResult], Sequence[Any]] = (),
            parameters: Mapping[str, Any] | None = None, mesh_formats: Sequence[str] = ("ply",),
            config: Mapping[str, Any] | None = None,
            summary: Callable[[CompareResult], str] | None = None, holdout_every: int | None = None,
            colour_map: str | None = None, mesh_methods: Collection[str] | None = None,
            given_exposures: Mapping[int, np.ndarray] | None = None) -> CompareResult:
    """Fuse ``dataset`` once per method with identical poses; write the table, figures, meshes and report. The
    folder ``output`` and each method's folder in it are locked against a second run
    (:class:`mapping.export.FolderLock`) from their creation until the comparison ends.

    dataset:          an :class:`~mapping.datasets.base.RGBDDataset` (range and stride applied).
    methods:          :class:`~mapping.compare.methods.Method` list (:func:`~mapping.compare.methods.make_methods`),
                      in table order.
    output:           the comparison's folder (refused if it holds one, unless ``force``: then the previous
                      comparison's files and method folders are removed first, :class:`ComparisonFolder`).
    backend:          ``tsdf`` or ``surfel`` (:func:`mapping.factory.make_backend`), ``backend_options`` to it.
    poses:            ``gt`` (ground truth) or ``icp`` (tracked once by the first method, reused).
    brightness:       ``mean`` (equal brightness, the default) or ``calibrated`` (:mod:`mapping.compare.methods`).
    scene:            the true scene (a :class:`mapping.simulation.room.Room`) for the colour error and the
                      "truth" column of the renders; None for real data.
    display_response: linearises raw intensities for the colour error (default: the first method's response).
    views:            viewpoints of the side-by-side renders (0 for none); ``render_width`` pixels wide each.
    report_sections:  extra :class:`mapping.report.ReportSection` s placed before the results (e.g. the demo's
                      calibration accuracy), or a function of the (unfinished) :class:`CompareResult` returning them.
    mesh_formats:     files of each method's mesh (:func:`mapping.export.write_mesh`: ply, glb, obj, npz; PLY only
                      by default, as :func:`mapping.pipeline.reconstruct` writes; ``npz`` adds ``mesh_colours.npz``
                      with the map-unit colours).
    mesh_methods:     the names of the methods whose mesh files are written (None: every method's); the others'
                      maps are still measured and rendered (the geometry is the same for all methods, only the
                      colours differ), e.g. the demo writes two of five.
    config, summary:  written as ``config.json`` (a JSON document, e.g. the CLI's replay manifest) and
                      ``summary.txt`` (the text ``summary(result)`` returns) when the comparison has finished, in
                      the locked folder before it is marked complete: they belong to this run (its MANIFEST).
    holdout_every:    None, or N: every method withholds the same frames (every N-th) from fusion and its final map is
                      judged by them (:mod:`mapping.holdout`: PSNR and L1 columns, ``holdout.csv``); with ICP poses
                      the first method tracks the withheld frames too and every method judges at those poses.
    colour_map:       None, ``rigid`` or ``non-rigid``: each method's mesh also colour-map optimised, a variant of
                      the method (:func:`mapping.colour_map.colour_map_for_run`, run by
                      :func:`mapping.pipeline.reconstruct` before the method's folder is complete: ``mesh_colourmap.*``
                      and ``colour_map.json`` in it, judged by the withheld frames when there are any); its outcome
                      in the table (:data:`~mapping.compare.results.COLOUR_MAP_COLUMNS`) and the report.
    """
    from mapping._open3d import o3d
    from mapping.factory import make_backend, make_tracker
    from mapping.holdout import check_holdout_every
    from mapping.pipeline import POSE_SOURCES, reconstruct
    from mapping.validation import check_colour_map, check_run
    from radiometry.fileio import atomic_write_json, atomic_write_text
    from radiometry.progress import progress_bar

    methods = list(methods)
    if not methods:
        raise ValueError("methods must hold at least one Method")
    names = [m.name for m in methods]
    if len(set(names)) != len(names):
        raise ValueError(f"method names must be unique, got {names}")
    from mapping.pose_files import PoseTable

    from_file = isinstance(poses, PoseTable)
    if not from_file and poses not in POSE_SOURCES:
        raise ValueError(f"poses must be one of {', '.join(POSE_SOURCES)} or a PoseTable, got {poses!r}")
    check_colour_map(colour_map, backend)
    if brightness not in BRIGHTNESS:
        raise ValueError(f"brightness must be one of {', '.join(BRIGHTNESS)}, got {brightness!r}")
    if not (isinstance(voxel_size, (int, float)) and math.isfinite(voxel_size) and voxel_size > 0):
        raise ValueError(f"voxel_size must be a positive number of metres, got {voxel_size!r}")
    if not (isinstance(views, (int, np.integer)) and views >= 0):
        raise ValueError(f"views must be a whole number >= 0 (0: no renders), got {views!r}")
    if views and not (isinstance(render_width, (int, np.integer)) and 16 <= render_width <= 4096):
        raise ValueError(f"render_width must be a whole number of pixels in 16..4096, got {render_width!r}")
    if len(dataset) == 0:
        raise RadiomapError(f"{getattr(dataset, 'name', 'the sequence')}: no frames to compare; check --frames")
    if display_response is None:
        display_response = next((m.response for m in methods if m.response is not None), None)
    check_run(dataset, backend=backend, voxel_size=voxel_size, depth_max=depth_max, poses=poses,
              **{k: v for k, v in dict(backend_options or {}).items()
                 if k in ("block_resolution", "trunc_voxel_multiplier", "depth_min")})
    output = Path(output)
    height, width = dataset.height, dataset.width
    n = len(dataset)
    if holdout_every is not None:
        holdout_every = check_holdout_every(holdout_every, n)

    # the comparison's folder, then each method's: released (their files listed) in reverse when it ends
    with contextlib.ExitStack() as folders:
        # the previous comparison removed, or (complete) kept until this one is published: written to top.path
        top = folders.enter_context(ComparisonFolder(output, force=force))
        start = time.perf_counter()
        reads = n + (n // holdout_every if holdout_every else 0)   # the withheld frames are read again to judge
        bar = progress_bar(total=reads * len(methods), desc="compare", enabled=progress)
        results: list[MethodResult] = []
        fixed: list[np.ndarray | None] | None = None
        ate = None
        try:
            with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
                for method in methods:
                    bar.set_postfix_str(method.name, refresh=True)
                    colour_model = _colour_model(method, height, width, brightness, given_exposures)
                    fusion = make_backend(backend, voxel_size=voxel_size, depth_max=depth_max,
                                          **dict(backend_options or {}))
                    track = poses == "icp" and fixed is None
                    view = FixedPoses(dataset, None if (poses == "gt" or track or from_file) else fixed,
                                      on_frame=_ticks(bar, reads))
                    folder = folders.enter_context(top.subfolder(method.name))
                    tracker = make_tracker(depth_max=depth_max, **dict(tracker_options or {})) if track else None
                    folder.write_json("config.json", _method_config(
                        method, dataset, colour_model, top.published(top.path / "config.json") if config else None,
                        fusion, tracker, backend=backend, poses=poses, voxel_size=voxel_size, depth_max=depth_max,
                        brightness=brightness))
                    t0 = time.perf_counter()
                    run = reconstruct(view, colour_model=colour_model, backend=fusion, tracker=tracker,
                                      poses="icp" if track else poses if from_file else "gt", output=folder,
                                      progress=False,
                                      histogram_label=method.label, write_mesh=False, holdout_every=holdout_every,
                                      colour_map=colour_map, colour_map_options={"formats": tuple(mesh_formats)})
                    # the method's time without the colour-map stage's (a column of its own)
                    seconds = time.perf_counter() - t0 - (0.0 if run.colour_map is None else run.colour_map.seconds)
                    if track:
                        fixed = _poses_by_frame(run, n)
                    if track or (from_file and ate is None):   # the shared trajectory against the ground truth
                        ate = run.ate
                    results.append(_method_result(method, run, folder.path, fusion, colour_model, seconds,
                                                  backend=backend, scene=scene, display_response=display_response,
                                                  max_distance=max(3 * voxel_size, 0.03),
                                                  mesh_formats=mesh_formats if mesh_methods is None or
                                                  method.name in mesh_methods else ()))
                    del fusion
        finally:
            bar.close()

        first = results[0].run
        result = CompareResult(results=results, stamps=first.stamps, poses=first.poses,
                               pose_source="ground truth" if poses == "gt" else f"the trajectory {poses}" if from_file
                               else
                               f"{_tracker_label(tracker_options)} (tracked with '{methods[0].name}')",
                               output=top.path, files={}, seconds=0.0, ate=ate,
                               parameters={"backend": backend, "poses": str(poses), "voxel_size": voxel_size,
                                           "depth_max": depth_max, "brightness": brightness, "frames": n,
                                           "width": width, "height": height, "holdout_every": holdout_every,
                                           **dict(parameters or {})})
        if not result.poses_identical:  # cannot happen by construction; never report a comparison that breaks it
            raise RadiomapError("the methods were fused at different poses; this is a bug, please report it")
        write_outputs(result, dataset, scene, views=views, render_width=render_width, title=title,
                      report_sections=report_sections)
        if config is not None:
            result.files["config"] = atomic_write_json(top.path / "config.json", config)
        if summary is not None:
            result.files["summary"] = atomic_write_text(top.path / "summary.txt", summary(result))
        result.seconds = time.perf_counter() - start
        write_compare_json(result)
        top.complete()
        _published(result, top)
    return result


def _published(result: CompareResult, top: ComparisonFolder) -> None:
    """The paths of ``result`` under their published names (a staged comparison was written elsewhere)."""
    result.output = top.published(result.output)
    result.files = {k: top.published(v) for k, v in result.files.items()}
    for r in result.results:
        r.folder = top.published(r.folder)
        r.files = {k: top.published(v) for k, v in r.files.items()}


def _method_result(method: Method, run, folder: Path, fusion, colour_model, seconds: float, *, backend: str,
                   scene, display_response: CameraResponse | None, max_distance: float,
                   mesh_formats: Sequence[str]) -> MethodResult:
    """A method's fused map as a mesh (and surfels) in its folder, its colour error against ``scene`` and its
    ``compare_method.json``."""
    from mapping.export import write_mesh
    from radiometry.fileio import atomic_write_json

    geometry = map_geometry(fusion)
    files = dict(run.files)
    if backend == "surfel" and hasattr(fusion, "export"):
        files.update(fusion.export(folder, colour_model.to_display))
    if mesh_formats:
        files.update(write_mesh(folder, geometry.vertices, geometry.triangles, geometry.colours,
                                colour_model.to_display, normals=geometry.normals, formats=mesh_formats))
    err = None
    if scene is not None:
        err = colour_error(geometry, colour_model, scene, display_response=display_response, max_distance=max_distance)
    result = MethodResult(method, run, folder, colour_model, geometry, err, files, seconds)
    atomic_write_json(folder / "compare_method.json",
                      {"method": method.describe(), "row": result.row(),
                       "colour_error": None if err is None else err.to_dict(),
                       "geometry": {"kind": geometry.kind, "vertices": len(geometry),
                                    "triangles": int(geometry.triangles.shape[0])}})
    return result


def _method_config(method: Method, dataset, colour_model, part_of: Path | None, fusion, tracker,
                   **settings: Any) -> dict[str, Any]:
    """A method folder's config.json: the method, the sequence, its colour model before the run, the fusion backend
    and the tracker (their classes and parameters, as a run's config.json records them) and the comparison's
    settings, and ``part_of``, the comparison's config.json (None when the caller wrote none): a method is replayed
    by replaying its comparison (``radiomap compare --config PART_OF --methods NAME``), which ``--config`` says when
    given this file."""
    from mapping.results import colour_model_setup, describe_run

    run = describe_run(dataset, colour_model, fusion, tracker)
    return {"command": "compare", "part_of": None if part_of is None else str(Path(part_of).absolute()),
            "method": method.describe(), "dataset": run["dataset"], "colour_model": colour_model_setup(colour_model),
            "backend": run["backend"], "tracker": run["tracker"],
            "settings": {k: str(v) if k == "poses" else v for k, v in settings.items()}}


def _ticks(bar, reads: int) -> Callable[[], None]:
    """``bar.update`` for a method's first ``reads`` frame reads (its share of the comparison's bar): the frames the
    colour-map stage reads again are not counted."""
    left = [reads]

    def tick() -> None:
        if left[0] > 0:
            left[0] -= 1
            bar.update()
    return tick


def _colour_model(method: Method, height: int, width: int, brightness: str,
                  given: Mapping[int, np.ndarray] | None = None):
    if method.response is None:
        return RawIntensity()
    vig = method.vignetting
    if vig is not None and brightness == "mean":
        vig = equal_brightness(vig, height, width)
    base = IrradianceColour(method.response, vig, name=method.name)
    if not method.exposure_compensation:
        return base
    from mapping.exposure_compensation import CompensatedColour

    if given is not None:     # the camera's recorded exposures (compare --exposures), one table per method's run
        from mapping.exposure_compensation.given import GivenExposures

        return CompensatedColour(base, GivenExposures(method.response, vig, known=dict(given), source="--exposures"))
    return CompensatedColour(base, compensate=True)


def _tracker_label(tracker_options: Mapping[str, Any] | None) -> str:
    """How the shared poses were tracked, for the table's pose line: ``ICP``, ``auto tracking`` (the default),
    ``hybrid tracking`` or ``coloured-icp tracking`` (:data:`mapping.factory.TRACKERS`)."""
    name = dict(tracker_options or {}).get("name", "auto")
    return "ICP" if name == "icp" else f"{name} tracking"


def _poses_by_frame(run, n: int) -> list[np.ndarray | None]:
    """Per dataset position: the pose the run fused (or withheld) that frame at, or None if it skipped it."""
    out: list[np.ndarray | None] = [None] * n
    k = 0
    for i, record in enumerate(run.records):
        if record.fused:
            out[i] = run.poses[k]
            k += 1
        else:
            out[i] = run.held_out_poses.get(i)
    return out
