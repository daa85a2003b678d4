"""``radiomap reconstruct``: track, correct and fuse an RGB-D sequence into a coloured map."""

from __future__ import annotations

from pathlib import Path

import click

from mapping.cli._common import (RadiomapCommand, check_formats, config_option, deprecated_alias, drop_replayed,
                                 evaluation_options, formats_option, fusion_options, Number, pose_arguments,
                                 pose_options, replay_manifest, replayed_sequence, sequence_options, settings_line,
                                 warn_far_depth, written_text)
from mapping.validation import EXPOSURE_FACTOR
from mapping.factory import TRACKERS

EPILOG = """\b
Examples:
  radiomap reconstruct room_seq -o run_raw --poses gt
      fuse raw intensities (no correction) with the ground-truth poses
  radiomap reconstruct room_seq --response crf.npz --vignetting vignetting.npz -o run_corrected
      fuse irradiance f^-1(I)/V/k with ICP tracking, k the exposure and white balance estimated per frame
      (on by default with --response; --no-exposure-compensation fuses f^-1(I)/V); compare histogram.json
  radiomap reconstruct redkitchen/seq-01 --frames 0:300:2 --voxel-size 0.01 -o kitchen
      a 7-Scenes sequence, every second of the first 300 frames
  radiomap reconstruct rgbd_dataset_freiburg1_desk --depth-scale 5000 --intrinsics 517.3,516.5,318.6,255.3 -o desk
  radiomap reconstruct --config run_corrected/config.json -o run_again
      replay a run with the options it recorded (options given here override them)
\b
The results folder holds mesh.ply (--formats adds GLB, OBJ, npz; colours through the response at
--display-exposure, or with exposure compensation at --mesh-exposure; with --backend surfel surfels.ply,
and surfels_mesh.ply with --surfel-mesh), trajectory.txt (TUM), histogram.json/.npz/.png (colour
disagreement before fusion, Fig. 9 of Alexandrov et al.), metrics.json, frames.csv, config.json (replayable with --config) and summary.txt;
with exposure compensation exposures.txt/.json (per-frame k_r k_g k_b relative to the first frame, source
map|frame|fallback). A RUNNING file marks a run that has not finished. With --force over a complete run,
that run stays in OUT until the new one is complete and replaces it (never neither).
"""


def _mesh_exposure(ctx, param, value):
    if value is None:
        return None
    from mapping.exposure_compensation import parse_reference

    try:
        parse_reference(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    return value


@click.command("reconstruct", cls=RadiomapCommand, epilog=EPILOG)
@click.argument("sequence", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Results folder (created).")
@click.option("-r", "--response", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Camera response (radiomap .npz, radical .crf, DSO pcalib.txt). Without it the map "
                   "averages raw intensities (no correction).")
@click.option("--vignetting", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Vignetting model (radiomap .npz, radical .vgn, DSO vignette.png) or a V array (.npy, "
                   "H x W x C). Needs --response.")
@pose_options("icp", "icp: track (--tracker); gt: the sequence's ground-truth poses (compare's default); or a "
                     "trajectory: a TUM file (e.g. an earlier run's trajectory.txt, ORB-SLAM's, evo's), a Redwood "
                     ".log or a folder of 7-Scenes pose files (frames without a pose are skipped).")
@click.option("--tracker", type=click.Choice(list(TRACKERS)), default="auto", show_default=True,
              help="With --poses icp: auto (point-to-plane ICP, and Open3D's coloured ICP for the frames where its "
                   "system is ill-conditioned or it fails: a wall, a floor; docs/tracking.md), point-to-plane ICP "
                   "alone (depth), hybrid RGB-D odometry or coloured ICP (depth and the colour the map holds: raw "
                   "levels, or irradiance at the map's exposure).")
@sequence_options
@fusion_options
@click.option("--surfel-mesh", is_flag=True,
              help="With --backend surfel: also write surfels_mesh.ply, a Poisson mesh of the stable surfels "
                   "(Open3D; beside surfels.ply).")
@click.option("--display-exposure", type=Number(EXPOSURE_FACTOR, "", "an exposure factor: 13 stops either way"),
              default=1.0, show_default=True, metavar="K",
              help="Exposure k at which map irradiance becomes display levels: the histogram's units and, without "
                   "exposure compensation, the mesh colours (with it, k relative to the first frame; the mesh "
                   "then follows --mesh-exposure).")
@click.option("--exposure-compensation/--no-exposure-compensation", default=None,
              help="Estimate every frame's exposure and white balance against the map and fuse f^-1(I)/V/k; "
                   "writes exposures.txt/.json [default: on with --response, off without; compare's: off].")
@click.option("--exposures", "exposures", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="With exposure compensation: the camera's recorded per-frame exposures (exposure x gain; "
                   "exposures.txt, 'timestamp k' or 'timestamp k_r k_g k_b' lines, TUM monoVO times.txt) instead "
                   "of estimating them; one per frame. Checked against the images' exposure changes: a list off by "
                   "a frame or more is refused.")
@click.option("--mesh-exposure", default=None, callback=_mesh_exposure, metavar="median|first|K|R,G,B",
              help="With exposure compensation: the exposure of the mesh colours relative to the first frame: "
                   "median (of the sequence's estimates; the default), first, a number or r,g,b.")
@evaluation_options
@formats_option
@config_option
@click.option("--force", is_flag=True, help="Overwrite the results of a previous run in OUTPUT.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
@deprecated_alias("-v", "vignetting", "--vignetting", "-v is radiomap's --verbose: radiomap -v reconstruct ...")
@deprecated_alias("--reference-exposure", "display_exposure", "--display-exposure")
@deprecated_alias("--exposure-reference", "mesh_exposure", "--mesh-exposure")
def command(sequence: Path, output: Path, response: Path | None, vignetting: Path | None, poses, tracker: str,
            poses_max_difference: float | None,
            voxel_size: float, frames: slice | None, depth_scale: float | None, intrinsics: str | None,
            backend: str, surfel_mesh: bool, format: str | None, depth_max: float, display_exposure: float,
            exposure_compensation: bool | None, exposures: Path | None, mesh_exposure: str | None,
            holdout_every: int | None, colour_map: str | None, formats: tuple[str, ...], force: bool,
            no_progress: bool) -> None:
    """Reconstruct SEQUENCE (TUM, 7-Scenes, Redwood or a radiomap simulation) into a TSDF or surfel map of
    irradiance (or raw intensities), recording the colour disagreement of every fused sample.

    With --config RUN/config.json, SEQUENCE and every option default to the recorded run's."""
    from mapping.batch.commands import reconstruct_command

    run, summary = reconstruct_command(**task_arguments(click.get_current_context()))
    click.echo(summary)
    if run.skipped:   # the frames --holdout-every withheld are not skipped (they were asked for)
        reasons = ", ".join(f"{k}: {v}" for k, v in run.skip_reasons().items())
        click.echo(f"warning: skipped {run.skipped} of {run.frames} frames ({reasons}); see {output / 'frames.csv'}",
                   err=True)
    warn_far_depth(run.depth_beyond_range, depth_max)
    click.echo(written_text(output), err=True)
    click.echo(f"results in {output}")


def task_arguments(ctx: click.Context) -> dict:
    """The options of ``ctx`` (a parsed reconstruct command) checked, as the keyword arguments of
    :func:`mapping.batch.commands.reconstruct_command`: plain values, the replay manifest and the settings line
    (what ``radiomap reconstruct`` runs, and what each task of ``radiomap batch reconstruct`` runs)."""
    p = ctx.params
    from mapping.cli._common import refuse_sequence_as_output

    refuse_sequence_as_output(p["sequence"], p["output"])
    poses, max_difference = pose_arguments(ctx)   # a trajectory file of the sequence resolved
    response, backend = p["response"], p["backend"]
    if p["vignetting"] is not None and response is None:
        raise click.UsageError("--vignetting needs --response (vignetting acts on irradiance, not on intensities)")
    if p["exposure_compensation"] and response is None:
        raise click.UsageError("--exposure-compensation needs --response (exposure acts on irradiance)")
    compensate = p["exposure_compensation"] if p["exposure_compensation"] is not None else response is not None
    if p["exposures"] is not None and not compensate:
        raise click.BadParameter("applies with exposure compensation only (it replaces the estimates); add --response"
                                 " (and drop --no-exposure-compensation)", param_hint="--exposures")
    if p["exposures"] is not None:
        from mapping.exposure_files import read_exposure_file

        read_exposure_file(p["exposures"])     # a bad file fails here, before anything is written
    if p["mesh_exposure"] is not None and not compensate and \
            not drop_replayed(ctx, "mesh_exposure", None, "no exposure compensation"):
        raise click.BadParameter("applies with exposure compensation only; without it the mesh colours are at "
                                 "--display-exposure", param_hint="--mesh-exposure")
    if p["surfel_mesh"] and backend != "surfel" and \
            not drop_replayed(ctx, "surfel_mesh", False, f"--backend {backend}"):
        raise click.BadParameter(f"applies to --backend surfel only, got --backend {backend} (the TSDF backend "
                                 "always writes mesh.ply); drop --surfel-mesh or add --backend surfel",
                                 param_hint="--surfel-mesh")
    if p["tracker"] != "auto" and p["poses"] != "icp" and \
            not drop_replayed(ctx, "tracker", "auto", f"--poses {p['poses']}"):
        raise click.BadParameter(f"applies with --poses icp only (got --poses {p['poses']}: no frame is tracked); "
                                 "drop --tracker or add --poses icp", param_hint="--tracker")
    from mapping.validation import check_colour_map

    try:   # the library's check (mapping.validation), shown as a usage error before anything is read
        check_colour_map(p["colour_map"], backend)
    except ValueError as exc:
        raise click.BadParameter(str(exc).removeprefix("--colour-map "), param_hint="--colour-map") from None
    formats = check_formats(ctx, p["formats"], backend)
    options = dict(sequence=p["sequence"], output=p["output"], response=response, vignetting=p["vignetting"],
                   poses=p["poses"], poses_max_difference=max_difference, tracker=p["tracker"],
                   voxel_size=p["voxel_size"],
                   frames=p["frames"] or slice(None), depth_scale=p["depth_scale"], intrinsics=p["intrinsics"],
                   backend=backend, surfel_mesh=p["surfel_mesh"], format=p["format"], depth_max=p["depth_max"],
                   reference_exposure=p["display_exposure"], exposure_compensation=p["exposure_compensation"],
                   exposure_reference=p["mesh_exposure"] or "median", holdout_every=p["holdout_every"],
                   exposures=None if p["exposures"] is None else str(p["exposures"]),
                   colour_map=p["colour_map"], mesh_formats=formats, force=p["force"],
                   progress=not p["no_progress"])
    settings = [("poses", "poses", p["poses"]), ("tracker", "tracker", p["tracker"]),
                ("exposure compensation", "exposure_compensation", "on" if compensate else "off",
                 f"reconstruct's default {'with' if response is not None else 'without'} --response")]
    if backend == "tsdf":
        settings.append(("formats", "formats", ",".join(formats)))
    manifest = replay_manifest(ctx, files=("intrinsics", "poses", "exposures"),
                               inputs=("response", "vignetting", "poses", "intrinsics", "exposures"))
    return {**options, "manifest": manifest, "settings": settings_line(ctx, settings),
            "replayed": replayed_sequence(ctx)}
