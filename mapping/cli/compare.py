"""``radiomap compare``: fuse one sequence with several radiometric corrections at identical poses."""

from __future__ import annotations

from pathlib import Path

import click

from mapping.cli._common import (RadiomapCommand, config_option, drop_replayed, fusion_options, replay_manifest,
                                 sequence_options, settings_line, warn_far_depth)

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
side; OUT/<method>/ one results folder per method (mesh.ply and .glb [not with --no-glb],
mesh_colours.npz with the map-unit colours, histogram, trajectory, metrics); OUT/summary.txt what was
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
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Folder for the comparison (created).")
@fusion_options
@click.option("--exposure-compensation", is_flag=True,
              help="Also run every corrected method with exposure compensation (reconstruct's default with "
                   "--response is on; here it adds methods).")
@click.option("--methods", callback=_methods, default=None, metavar="LIST",
              help="Comma-separated methods instead of the default (none,poly,lut[,poly+ec,lut+ec]): none, "
                   "response, poly, lut, and response+ec, poly+ec, lut+ec.")
@click.option("--poses", type=click.Choice(["gt", "icp"]), default="gt", show_default=True,
              help="Ground-truth poses, or ICP tracked once and reused by every method (reconstruct's default).")
@sequence_options
@click.option("--brightness", type=click.Choice(["mean", "calibrated"]), default="mean", show_default=True,
              help="mean: compare the corrections at equal brightness (each V rescaled to an image mean of 1); "
                   "calibrated: V = 1 at the optical centre as calibrated.")
@click.option("--views", type=click.IntRange(0, 6), default=3, show_default=True,
              help="Viewpoints of the side-by-side renders (0: none).")
@click.option("--render-width", type=click.IntRange(32, 1920), default=320, show_default=True,
              help="Width of each render in pixels.")
@click.option("--glb/--no-glb", default=True, show_default=True,
              help="Also write each mesh as binary glTF (mesh.glb) for web viewers, as reconstruct does.")
@config_option
@click.option("--force", is_flag=True, help="Overwrite an earlier comparison in OUTPUT.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def command(sequence: Path, response: Path, vignetting_lut: Path | None, vignetting_poly: Path | None, output: Path,
            backend: str, exposure_compensation: bool, methods: list[str] | None, poses: str, frames: slice | None,
            voxel_size: float, depth_max: float, brightness: str, depth_scale: float | None, intrinsics: str | None,
            format: str | None, views: int, render_width: int, glb: bool, force: bool, no_progress: bool) -> None:
    """Reconstruct SEQUENCE once per radiometric correction (no correction, polynomial and LUT vignetting,
    optionally with exposure compensation) at identical poses, and compare the colour disagreement
    histograms, the meshes and (for simulated sequences) the colours against the true radiance.

    With --config RUN/config.json, SEQUENCE and every option default to the recorded comparison's."""
    from mapping.compare import compare, load_method_vignetting, make_methods
    from mapping.datasets import open_dataset
    from radiometry.formats import load_response

    ctx = click.get_current_context()
    if methods is not None and exposure_compensation and \
            not drop_replayed(ctx, "exposure_compensation", False, "--methods lists the methods"):
        raise click.UsageError("--methods lists the methods itself (add e.g. lut+ec); drop --exposure-compensation")
    dataset = open_dataset(sequence, format=format, depth_scale=depth_scale, intrinsics=intrinsics,
                           frames=frames or slice(None))
    resp = load_response(response)
    lut = load_method_vignetting(vignetting_lut, "lut") if vignetting_lut is not None else None
    poly = load_method_vignetting(vignetting_poly, "poly") if vignetting_poly is not None else None
    exposure_compensation = ctx.params["exposure_compensation"]
    try:
        method_list = make_methods(resp, vignetting_poly=poly, vignetting_lut=lut,
                                   exposure_compensation=exposure_compensation, names=methods)
    except ValueError as exc:
        raise click.UsageError(str(exc)) from None
    scene = _scene_of(dataset)
    ec = "on (+ec methods)" if any(m.exposure_compensation for m in method_list) else "off"
    settings = settings_line(ctx, [("poses", "poses", poses),
                                   ("exposure compensation", "exposure_compensation", ec) if methods is None
                                   else ("exposure compensation", None, f"{ec}, as --methods lists"),
                                   ("glb", "glb", "on" if glb else "off")])

    def summary(result) -> str:
        lines = [result.table_text()]
        if result.ate is not None:
            lines.append(f"ATE of the shared trajectory: {100 * result.ate.rmse:.2f} cm RMSE")
        if scene is None:
            lines.append("(no ground truth: colour error not measured)")
        lines.append(f"ranking by L1 mean (best first): {', '.join(result.ranking())}")
        return "\n".join(lines + [settings]) + "\n"

    # config.json and summary.txt are written by compare() in its locked folder: they belong to the run
    result = compare(dataset, method_list, output=output, backend=backend, poses=poses, voxel_size=voxel_size,
                     depth_max=depth_max, brightness=brightness, scene=scene, views=views,
                     render_width=render_width, progress=not no_progress, force=force,
                     title=f"radiomap compare: {sequence.name}", mesh_formats=("ply", "glb") if glb else ("ply",),
                     config=replay_manifest(ctx, files=("intrinsics",), methods_run=[m.name for m in method_list]),
                     summary=summary)
    click.echo(summary(result), nl=False)
    click.echo(f"report: {result.files['report']}")
    warn_far_depth(max((r.run.depth_beyond_range for r in result.results), default=0.0), depth_max)


def _scene_of(dataset):
    """The simulated room of a simulated sequence (for the colour error), else None; a note when its light changes
    (the colour error then also counts the change)."""
    from mapping.datasets import SimulatedDataset

    room = dataset.true_room() if isinstance(dataset, SimulatedDataset) else None
    scales = dataset.true_light_scales() if room is not None else None
    if scales is not None and scales.size and scales.max() - scales.min() > 1e-6:
        click.echo(f"note: the light changes during {dataset.name} ({scales.min():.2f}..{scales.max():.2f}); the "
                   "colour error compares with the radiance at the nominal light, so it also counts the change",
                   err=True)
    return room
