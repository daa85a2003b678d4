"""The work of ``radiomap reconstruct`` and ``radiomap compare`` on one sequence, as library functions of the
command's checked options (plain values: paths, numbers, text), and :data:`COMMANDS`, the registry of the commands
a batch runs: one entry per command.

The commands parse and check their options (``mapping/cli/<name>.py``, ``task_arguments``), then call these
functions; a batch task calls the same function in a worker process with the same arguments, so each results
folder is the one the single command writes. Open3D is imported inside the functions (by the pipeline), never
when this module is imported.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from mapping.self_calibration import (MARKER, run_self_calibration, self_calibration_complete,
                                      self_calibration_rows)
from radiometry.registry import Registry

log = logging.getLogger(__name__)


# ------------------------------------------------------------------ radiomap reconstruct
def reconstruct_command(*, manifest: dict, settings: str, replayed: dict | None = None, **options: Any):
    """Reconstruct one sequence into its results folder as ``radiomap reconstruct`` does; returns the run
    (:class:`mapping.results.RunResult`) and the summary it wrote to ``summary.txt``.

    options:  the fields of :class:`mapping.factory.ReconstructConfig` (``sequence``, ``output``, ``response``, ...),
              already checked by the command.
    manifest: config.json's record of the options (the command's replay manifest); ``started`` is set when the
              run starts and the dataset, the colour model and the pipeline's configuration are added.
    settings: the summary's settings line (which value came from where).
    replayed: with ``--config``, what the replayed run recorded of its frames (:func:`mapping.replay.check_frames`
              refuses the run, before anything is written, when the sequence now gives other frames)."""
    from mapping.datasets import describe_dataset, intrinsics_text
    from mapping.replay import check_frames, selection_record
    from mapping.results import colour_model_setup
    from mapping.export import plain_value
    from mapping.publication import ReconstructionFolder
    from mapping.factory import ReconstructConfig, build_run
    from mapping.pipeline import reconstruct
    from radiometry.tables import format_table

    config = ReconstructConfig(**options)
    kwargs = build_run(config)   # opens the dataset and loads the models: fails before anything is written
    check_frames(replayed, kwargs["dataset"])
    settings += ", " + intrinsics_text(kwargs["dataset"])
    folder = ReconstructionFolder(config.output, force=config.force)   # --force keeps a complete run until replaced
    record = {**manifest, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
              "dataset": {**describe_dataset(kwargs["dataset"]),
                          "selected_with": selection_record(config.sequence, config.frames, config.format)},
              "colour_model": colour_model_setup(kwargs["colour_model"]),
              "pipeline": {k: plain_value(v) for k, v in asdict(config).items() if k not in ("force", "progress")}}
    folder.write_json("config.json", record)
    from mapping.pipeline import TrackingLostError

    lost = None
    try:
        # with --colour-map the optimised mesh beside the plain one, before the folder is complete (mapping.colour_map)
        try:
            run = reconstruct(**kwargs, output=folder)
        except TrackingLostError as exc:   # the map of the frames before the loss is written: summarise it, then fail
            run, lost = exc.run, exc
        summary = "\n".join([format_table([run.summary_row()]), *run.notes(), settings])
        if run.colour_map is not None:
            summary += "\n" + run.colour_map.summary_line()
        if lost is not None:
            summary += f"\nPARTIAL: {run.partial_reason}"
        folder.write_text("summary.txt", summary + "\n")   # the pipeline's table plus the settings used
        if lost is not None:
            raise lost
    finally:
        folder.release()  # unlock the folder (locked while this run writes it: a second run is refused)
    return run, summary


def reconstruct_rows(folder: Path) -> list[dict]:
    """The batch summary's row of a complete reconstruct folder (from its metrics.json)."""
    metrics = json.loads((folder / "metrics.json").read_text(encoding="utf-8"))
    return [_row(metrics["frames"]["total"], metrics["frames"]["fused"], metrics["timing"]["seconds"],
                 metrics["histogram"], metrics.get("ate"), metrics.get("holdout"))]


# ------------------------------------------------------------------ radiomap compare
class MethodChoiceError(ValueError):
    """The methods asked for cannot be made from the models given (a usage error of ``radiomap compare``)."""


def compare_command(sequence: Path, *, output: Path, response: Path, vignetting_lut: Path | None,
                    vignetting_poly: Path | None, vignetting_self: Path | None = None, methods: list[str] | None,
                    exposure_compensation: bool, backend: str, poses: str, frames: slice | None, voxel_size: float,
                    depth_max: float, brightness: str, depth_scale: float | None, intrinsics: str | None,
                    format: str | None, views: int, render_width: int, force: bool, progress: bool,
                    manifest: dict, settings: str, notify: Callable[[str], None] = log.warning,
                    holdout_every: int | None = None, tracker: str = "auto", colour_map: str | None = None,
                    poses_max_difference: float = 0.02, mesh_formats: tuple[str, ...] = ("ply",),
                    exposures: str | None = None, replayed: dict | None = None):
    """Compare the radiometric corrections on one sequence as ``radiomap compare`` does; returns the
    :class:`mapping.compare.CompareResult` and the summary it wrote to ``summary.txt``.

    The keywords are the command's options (``methods`` None: the default list, with ``+ec`` methods when
    ``exposure_compensation``); :class:`MethodChoiceError` when a method's model is missing.
    manifest: config.json's record of the options (``methods_run`` is added).
    settings: the summary's settings line (which value came from where).
    notify:   receives a note on the sequence before the run (a light that changes during a simulation).
    holdout_every: withhold every N-th frame from fusion and judge each map by them (:mod:`mapping.holdout`).
    replayed: with ``--config``, what the replayed comparison recorded of its frames
              (:func:`mapping.replay.check_frames`)."""
    from mapping.compare import compare
    from mapping.datasets import describe_dataset, intrinsics_text, open_dataset
    from mapping.replay import check_frames, selection_record

    dataset = open_dataset(sequence, format=format, depth_scale=depth_scale, intrinsics=intrinsics,
                           frames=frames or slice(None))
    check_frames(replayed, dataset)
    settings += ", " + intrinsics_text(dataset)
    from mapping.pose_files import resolve_poses

    poses = resolve_poses(poses, dataset, max_difference=poses_max_difference)   # a file read and matched
    method_list = compare_methods(response, vignetting_lut=vignetting_lut, vignetting_poly=vignetting_poly,
                                  vignetting_self=vignetting_self, exposure_compensation=exposure_compensation,
                                  methods=methods)
    scene = _scene_of(dataset, notify)
    given = None
    if exposures is not None:       # the +ec methods take the camera's recorded exposures instead of estimates
        from mapping.factory import _given_exposures

        given = _given_exposures(exposures, dataset, method_list[0].response, None, poses_max_difference,
                                 "compare")
        if given.check is not None and given.check["verdict"] in ("warn", "mismatch"):    # said in the summary, not only logged
            settings += f"; exposures {exposures}: {given.check['text']}"

    def summary(result) -> str:
        lines = [result.table_text()]
        if result.ate is not None:
            lines.append(f"ATE of the shared trajectory: {100 * result.ate.rmse:.2f} cm RMSE")
        if scene is None:
            lines.append("(no true radiance: colour error not measured; only a simulated sequence knows it)")
        lines.append(f"ranking by L1 mean (best first): {', '.join(result.ranking())}")
        if holdout_every is not None:
            lines.append(f"holdout: 1 frame in {holdout_every} withheld from fusion; PSNR (dB) and L1 (levels, summed "
                         "over R, G, B) of each final map rendered at them, exposure fitted per frame (holdout.csv)")
        lines += [f"{r.method.name}: " + r.run.colour_map.summary_line() for r in result.results
                  if r.run.colour_map is not None]
        return "\n".join(lines + [settings]) + "\n"

    # config.json and summary.txt are written by compare() in its locked folder: they belong to the run
    result = compare(dataset, method_list, output=output, backend=backend, poses=poses, voxel_size=voxel_size,
                     depth_max=depth_max, brightness=brightness, scene=scene, views=views,
                     render_width=render_width, progress=progress, force=force,
                     title=f"radiomap compare: {Path(sequence).name}",
                     mesh_formats=mesh_formats,
                     config={**manifest, "dataset": {**describe_dataset(dataset),
                                                     "selected_with": selection_record(sequence, frames, format)},
                             "methods_run": [m.name for m in method_list]}, summary=summary,
                     holdout_every=holdout_every, tracker_options={"name": tracker}, colour_map=colour_map,
                     given_exposures=None if given is None else given.known)
    return result, summary(result)


def compare_methods(response: Path, *, vignetting_lut: Path | None, vignetting_poly: Path | None,
                    exposure_compensation: bool, methods: list[str] | None,
                    vignetting_self: Path | None = None) -> list:
    """The :class:`mapping.compare.Method` list of a comparison from the model files (MethodChoiceError when a
    method's model is missing or of the wrong kind)."""
    from mapping.compare import load_method_vignetting, make_methods
    from radiometry.formats import load_response

    resp = load_response(response)
    lut = load_method_vignetting(vignetting_lut, "lut") if vignetting_lut is not None else None
    poly = load_method_vignetting(vignetting_poly, "poly") if vignetting_poly is not None else None
    own = load_method_vignetting(vignetting_self, "self") if vignetting_self is not None else None
    try:
        return make_methods(resp, vignetting_poly=poly, vignetting_lut=lut, vignetting_self=own,
                            exposure_compensation=exposure_compensation, names=methods)
    except ValueError as exc:
        raise MethodChoiceError(str(exc)) from None


def _scene_of(dataset, notify: Callable[[str], None]):
    """The simulated room of a simulated sequence (for the colour error), else None; a note when its light changes
    (the colour error then also counts the change)."""
    from mapping.datasets import SimulatedDataset

    room = dataset.true_room() if isinstance(dataset, SimulatedDataset) else None
    scales = dataset.true_light_scales() if room is not None else None
    if scales is not None and scales.size and scales.max() - scales.min() > 1e-6:
        notify(f"note: the light changes during {dataset.name} ({scales.min():.2f}..{scales.max():.2f}); the "
               "colour error compares with the radiance at the nominal light, so it also counts the change")
    return room


def compare_rows(folder: Path) -> list[dict]:
    """The batch summary's rows of a complete comparison: one per method (from each method's metrics.json)."""
    doc = json.loads((folder / "compare.json").read_text(encoding="utf-8"))
    ate = doc.get("ate")
    table = {row.get("method"): row for row in doc.get("table") or []}    # compare.csv's rows
    rows = []
    for method in doc["methods"]:
        metrics = json.loads((folder / method["folder"] / "metrics.json").read_text(encoding="utf-8"))
        row = {"method": method["name"], **_row(metrics["frames"]["total"], metrics["frames"]["fused"],
                                                metrics["timing"]["seconds"], metrics["histogram"], ate,
                                                metrics.get("holdout"))}
        seconds = table.get(method["name"], {}).get("seconds")
        # compare.csv's "seconds": the method's whole run (setup, the frame loop, its files; not its mesh)
        row["method s"] = round(seconds, 2) if isinstance(seconds, (int, float)) else None
        rows.append(row)
    return rows


def compare_complete(folder: Path) -> bool:
    """A comparison's folder is complete when compare.json is there and no RUNNING marker."""
    from mapping.export import RUNNING_MARKER

    return (folder / "compare.json").is_file() and not (folder / RUNNING_MARKER).exists()


def _row(frames: int, fused: int, seconds: float, histogram: dict, ate: dict | None,
         holdout: dict | None = None) -> dict:
    # "loop s": metrics.json's timing.seconds, the frame loop (read, track, render, colour, fuse, histogram); the
    # rate of the single command's fps; not the task's wall time nor compare.csv's "seconds" ("method s")
    row = {"frames": frames, "fused": fused, "loop s": round(seconds, 2),
           "frames/s": round(frames / seconds, 2) if seconds > 0 else None,
           "L1 mean": histogram.get("mean"), "L1 median": histogram.get("median"), "L1 p90": histogram.get("p90"),
           "ATE cm": None if ate is None else round(100 * ate["rmse"], 2)}
    if holdout is not None:  # --holdout-every: the map judged by the withheld frames (mapping.holdout)
        row.update({"holdout PSNR": holdout.get("psnr"), "holdout L1": holdout.get("l1")})
    return row


def _reconstruct_complete(folder: Path) -> bool:
    from mapping.export import is_complete

    return is_complete(folder)


def _reconstruct_outputs(folder: Path) -> list[str]:
    """The files every complete reconstruction holds (besides those its run listed in .radiomap-files.json)."""
    return ["config.json", "metrics.json", "histogram.json", "summary.txt"]


def _compare_outputs(folder: Path) -> list[str]:
    """The files every complete comparison holds: its own and each method's metrics.json (compare.json names the
    methods' folders)."""
    names = ["config.json", "compare.json", "compare.csv", "summary.txt"]
    try:
        doc = json.loads((folder / "compare.json").read_text(encoding="utf-8"))
        names += [f"{m['folder']}/metrics.json" for m in doc["methods"]]
    except (OSError, ValueError, KeyError, TypeError):
        pass    # compare.json itself is named above: resume.damage says what is wrong with it
    return names


def _self_calibration_outputs(folder: Path) -> list[str]:
    """The files a complete self-calibration holds: its record and the files the record lists."""
    names = [MARKER]
    try:
        files = json.loads((folder / MARKER).read_text(encoding="utf-8"))["files"]
        names += [Path(v).name for v in files.values()]
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        pass
    return names


# ------------------------------------------------------------------ the registry
@dataclass(frozen=True)
class BatchCommand:
    """What a batch needs of a command: the library function a task runs (with the keyword arguments the
    command's ``task_arguments`` makes), whether a results folder is finished, the summary rows of a complete
    folder, the file the HTML index links to and the files every complete folder holds (names in the folder; a
    resumed batch runs a finished folder again when one of these, or of the files its run listed, is missing,
    empty or unreadable: :func:`mapping.batch.resume.damage`)."""

    run: Callable[..., Any]
    complete: Callable[[Path], bool]
    rows: Callable[[Path], list[dict]]
    report: str
    outputs: Callable[[Path], list[str]] = lambda folder: []


#: the commands ``radiomap batch`` runs, by name (a command is one entry; its CLI module defines ``task_arguments``)
COMMANDS = Registry("batch command", {
    "reconstruct": BatchCommand(run=reconstruct_command, complete=_reconstruct_complete, rows=reconstruct_rows,
                                report="summary.txt", outputs=_reconstruct_outputs),
    "compare": BatchCommand(run=compare_command, complete=compare_complete, rows=compare_rows, report="report.html",
                            outputs=_compare_outputs),
    "self-calibrate": BatchCommand(run=run_self_calibration, complete=self_calibration_complete,
                                   rows=self_calibration_rows, report="summary.txt",
                                   outputs=_self_calibration_outputs),
})


__all__ = ["BatchCommand", "COMMANDS", "MethodChoiceError", "compare_command", "compare_methods", "compare_rows",
           "reconstruct_command", "reconstruct_rows"]
