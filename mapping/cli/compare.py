"""``radiomap compare``: fuse one sequence with several radiometric corrections at identical poses."""

from __future__ import annotations

from pathlib import Path

import click

from mapping.cli._common import (RadiomapCommand, config_option, drop_replayed, evaluation_options, formats_option,
                                 fusion_options,
                                 pose_arguments, pose_options, replay_manifest, replayed_sequence, sequence_options,
                                 settings_line,
                                 warn_far_depth, written_text)
from mapping.factory import TRACKERS

EPILOG = """\b
Examples:
  radiomap compare room_seq --response crf.npz --vignetting-lut lut.npz --vignetting-poly poly.npz \\
      --poses gt -o cmp
      no correction vs polynomial vs LUT vignetting on a simulated room (the colour error against the true
      radiance is added because the sequence has ground truth)
  radiomap compare room_seq -r crf.npz --vignetting-lut lut.npz --vignetting-poly poly.npz \\
      --exposure-compensation -o cmp_ec
      the same, each corrected method also with exposure compensation
  radiomap response --gamma 2.2 -o gamma.npz
  radiomap compare redkitchen/seq-01 -r gamma.npz --methods none,response,response+ec \\
      --poses icp --frames 0:200:2 -o kitchen_cmp
      real data of a camera whose response is unknown (the gamma 2.2 assumption) and not calibrated for
      vignetting: tracked once (ICP), raw colours vs response vs response with exposure compensation
  radiomap compare --config cmp/config.json -o cmp_surfel --backend surfel
      replay a comparison with the options it recorded, here with another backend
\b
OUT/report.html holds everything (figures embedded); OUT/compare.csv/.json/.txt the table;
OUT/histograms.png the histograms (Fig. 9 of Alexandrov et al.); OUT/renders.jpg the meshes side by
side; OUT/<method>/ one results folder per method (mesh.ply, other mesh files with --formats,
histogram, trajectory, metrics); OUT/summary.txt what was
printed, with the settings used; OUT/config.json the options (replayable with --config).
"""


def _methods(ctx, param, value):
    if value is None:
        return None
    from mapping.compare import METHOD_NAMES

    names = [v.strip() for v in value.split(",") if v.strip()]
    bad = [n for n in names if n not in METHOD_NAMES]
    if bad or not names:
        raise click.BadParameter(f"unknown method(s) {', '.join(bad) or '(none given)'}; choose among "
                                 f"{', '.join(METHOD_NAMES)}")
    return names


@click.command("compare", cls=RadiomapCommand, epilog=EPILOG)
@click.argument("sequence", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("-r", "--response", type=click.Path(exists=True, dir_okay=False, path_type=Path), required=True,
              help="Camera response (radiomap .npz, radical .crf, DSO pcalib.txt).")
@click.option("--vignetting-lut", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="LUT vignetting model (radiomap .npz, radical .vgn, DSO vignette.png, or a V array .npy).")
@click.option("--vignetting-poly", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="Polynomial vignetting model (radiomap .npz, radical .vgn).")
@click.option("--vignetting-self", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="Vignetting self-calibrated from a sequence (the vignetting.npz of 'radiomap self-calibrate'): "
                   "the methods self and self+ec, beside a white-paper LUT.")
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Folder for the comparison (created).")
@fusion_options
@click.option("--exposure-compensation", is_flag=True,
              help="Also run every corrected method with exposure compensation (reconstruct's default with "
                   "--response is on; here it adds methods).")
@click.option("--exposures", type=click.Path(dir_okay=False), default=None,
              help="The +ec methods use the camera's recorded per-frame exposures (exposure x gain; exposures.txt, "
                   "'timestamp k' or 'timestamp k_r k_g k_b' lines, TUM monoVO times.txt) instead of estimates; "
                   "checked against the images: a list off by a frame or more is refused.")
@click.option("--methods", callback=_methods, default=None, metavar="LIST",
              help="Comma-separated methods instead of the default (none,poly,lut[,poly+ec,lut+ec]): none, "
                   "response, poly, lut, self, and response+ec, poly+ec, lut+ec, self+ec.")
@pose_options("gt", "gt: ground-truth poses; icp: tracked once and reused by every method (reconstruct's default); "
                    "or a trajectory (a TUM file, a Redwood .log, a folder of 7-Scenes pose files; see reconstruct "
                    "--help).")
@click.option("--tracker", type=click.Choice(list(TRACKERS)), default="auto", show_default=True,
              help="With --poses icp: auto (ICP, coloured ICP where ICP is ill-conditioned), point-to-plane ICP, "
                   "hybrid RGB-D odometry or coloured ICP, on the first method's colour (see reconstruct --help).")
@sequence_options
@click.option("--brightness", type=click.Choice(["mean", "calibrated"]), default="mean", show_default=True,
              help="mean: compare the corrections at equal brightness (each V rescaled to an image mean of 1); "
                   "calibrated: V = 1 at the optical centre as calibrated.")
@click.option("--views", type=click.IntRange(0, 6), default=3, show_default=True,
              help="Viewpoints of the side-by-side renders (0: none).")
@click.option("--render-width", type=click.IntRange(32, 1920), default=320, show_default=True,
              help="Width of each render in pixels.")
@click.option("--glb/--no-glb", default=None, hidden=True,
              help="Deprecated: --formats ply,glb (or --formats ply) says which mesh files to write.")
@formats_option
@evaluation_options
@config_option
@click.option("--force", is_flag=True, help="Overwrite an earlier comparison in OUTPUT.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def command(sequence: Path, response: Path, vignetting_lut: Path | None, vignetting_poly: Path | None,
            vignetting_self: Path | None, output: Path,
            backend: str, exposure_compensation: bool, exposures: str | None, methods: list[str] | None, poses,
            tracker: str,
            poses_max_difference: float | None,
            frames: slice | None, voxel_size: float, depth_max: float, brightness: str, depth_scale: float | None,
            intrinsics: str | None, format: str | None, views: int, render_width: int, glb: bool | None,
            formats: tuple[str, ...],
            holdout_every: int | None, colour_map: str | None, force: bool, no_progress: bool) -> None:
    """Reconstruct SEQUENCE once per radiometric correction (no correction, polynomial and LUT vignetting,
    optionally with exposure compensation) at identical poses, and compare the colour disagreement
    histograms, the meshes and (for simulated sequences) the colours against the true radiance.

    With --config RUN/config.json, SEQUENCE and every option default to the recorded comparison's."""
    from mapping.batch.commands import compare_command

    result, summary = compare_command(**task_arguments(click.get_current_context()),
                                      notify=lambda note: click.echo(note, err=True))
    click.echo(summary, nl=False)
    click.echo(written_text(output), err=True)
    click.echo(f"report: {result.files['report']}")
    warn_far_depth(max((r.run.depth_beyond_range for r in result.results), default=0.0), depth_max)


def task_arguments(ctx: click.Context) -> dict:
    """The options of ``ctx`` (a parsed compare command) checked, as the keyword arguments of
    :func:`mapping.batch.commands.compare_command`: plain values (the methods by name), the replay manifest and
    the settings line (what ``radiomap compare`` runs, and what each task of ``radiomap batch compare`` runs). The
    models are loaded here once to check that they make the methods asked for."""
    from mapping.batch.commands import MethodChoiceError, compare_methods

    p = ctx.params
    formats = p["formats"]
    if p["glb"] is not None:   # the old spelling: --glb added glb to the PLY (the default then), --no-glb left PLY only
        formats = tuple(dict.fromkeys([*formats, "glb"])) if p["glb"] else tuple(f for f in formats if f != "glb")
        new = ",".join(formats or ("ply",))
        click.echo(f"warning: --{'' if p['glb'] else 'no-'}glb is deprecated, use --formats {new}", err=True)
        formats = formats or ("ply",)
    from mapping.cli._common import check_formats, refuse_sequence_as_output

    formats = check_formats(ctx, formats, p["backend"], spelling="--glb" if p["glb"] else "--formats")

    refuse_sequence_as_output(p["sequence"], p["output"])
    poses, max_difference = pose_arguments(ctx)   # a trajectory file of the sequence resolved
    methods = p["methods"]
    if methods is not None and p["exposure_compensation"] and \
            not drop_replayed(ctx, "exposure_compensation", False, "--methods lists the methods"):
        raise click.UsageError("--methods lists the methods itself (add e.g. lut+ec); drop --exposure-compensation")
    models = {k: p[k] for k in ("response", "vignetting_lut", "vignetting_poly", "vignetting_self")}
    try:
        method_list = compare_methods(**models, exposure_compensation=p["exposure_compensation"], methods=methods)
    except MethodChoiceError as exc:
        raise click.UsageError(str(exc)) from None
    names = [m.name for m in method_list]
    for base in ("lut", "poly", "self"):     # a model no listed method uses would be ignored without a word
        option = f"vignetting_{base}"
        if models[option] is not None and not any(n.removesuffix("+ec") == base for n in names) and \
                not drop_replayed(ctx, option, None, f"--methods lists no {base} method"):
            raise click.BadParameter(f"applies to the {base} methods ({base}, {base}+ec) only and the methods "
                                     f"compared ({','.join(names)}) include neither; drop --vignetting-{base} or add "
                                     f"{base} to --methods", param_hint=f"--vignetting-{base}")
        models[option] = p[option]     # None when a replayed value was dropped
    if p["tracker"] != "auto" and p["poses"] != "icp" and \
            not drop_replayed(ctx, "tracker", "auto", f"--poses {p['poses']}"):
        raise click.BadParameter(f"applies with --poses icp only (got --poses {p['poses']}: no frame is tracked); "
                                 "drop --tracker or add --poses icp", param_hint="--tracker")
    ec = "on (+ec methods)" if any(m.exposure_compensation for m in method_list) else "off"
    if p["exposures"] is not None:
        if ec == "off":
            raise click.BadParameter("applies to the +ec methods only; add --exposure-compensation (or +ec methods "
                                     "to --methods)", param_hint="--exposures")
        from mapping.exposure_files import read_exposure_file

        read_exposure_file(p["exposures"])     # a bad file fails here, before anything is written
        ec = f"given ({p['exposures']})"
    settings = settings_line(ctx, [("poses", "poses", p["poses"]), ("tracker", "tracker", p["tracker"]),
                                   ("exposure compensation", "exposure_compensation", ec) if methods is None
                                   else ("exposure compensation", None, f"{ec}, as --methods lists"),
                                   ("formats", "formats", ",".join(formats))])
    from mapping.validation import check_colour_map

    try:   # the library's check (mapping.validation), shown as a usage error before anything is read
        check_colour_map(p["colour_map"], p["backend"])
    except ValueError as exc:
        raise click.BadParameter(str(exc).removeprefix("--colour-map "), param_hint="--colour-map") from None
    options = {k: p[k] for k in ("sequence", "output", "backend", "poses", "tracker", "frames", "voxel_size",
                                 "depth_max", "brightness", "depth_scale", "intrinsics", "format", "views",
                                 "render_width", "holdout_every", "colour_map", "force")}
    return {**options, **models, "methods": [m.name for m in method_list], "mesh_formats": formats,
            "poses_max_difference": max_difference,
            "exposure_compensation": p["exposure_compensation"], "progress": not p["no_progress"],
            "exposures": p["exposures"],
            "manifest": replay_manifest(ctx, files=("intrinsics", "poses", "exposures"),
                                        inputs=("response", "vignetting_lut", "vignetting_poly", "vignetting_self",
                                                "poses", "intrinsics", "exposures")),
            "settings": settings, "replayed": replayed_sequence(ctx)}
