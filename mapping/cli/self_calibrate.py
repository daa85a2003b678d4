"""``radiomap self-calibrate``: vignetting, per-frame exposure and white balance from an RGB-D sequence itself."""

from __future__ import annotations

import click

from mapping.cli._common import sequence_options

EPILOG = """\b
No white sheet: every surface point is seen at many image positions and exposures, which constrains V
(a free-centre polynomial times a smooth non-radial grid) and k per frame. The camera must pan and turn
so that surfaces cross the image; the response is given (--response; default gamma 2.2, an assumption).

\b
Examples:
  radiomap self-calibrate room_seq --response room_seq/truth/response.npz --poses gt -o selfcal
  radiomap self-calibrate redkitchen --frames 0:50 -o kitchen_selfcal
      (gamma 2.2 assumed; then: radiomap reconstruct redkitchen --response gamma.npz \\
       --vignetting kitchen_selfcal/vignetting.npz ...)
"""


@click.command("self-calibrate", epilog=EPILOG)
@click.argument("sequence", type=click.Path(exists=True, file_okay=False))
@click.option("-r", "--response", "response_path", type=click.Path(dir_okay=False), default=None,
              help="Camera response (radiomap .npz, radical .crf, DSO pcalib.txt) [default: gamma 2.2, assumed].")
@click.option("--poses", type=click.Choice(["gt", "icp"]), default="gt", show_default=True,
              help="Ground-truth poses, or ICP tracked by radiomap's pipeline.")
@sequence_options
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False),
              help="Folder for vignetting.npz, exposures.txt, figures and the summary.")
@click.option("--no-plots", is_flag=True, help="Skip the PNG figures.")
@click.option("--force", is_flag=True, help="Overwrite an earlier self-calibration in OUTPUT.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def command(sequence: str, response_path: str | None, poses: str, frames, depth_scale, intrinsics, format,
            output: str, no_plots: bool, force: bool, no_progress: bool) -> None:
    """Self-calibrate vignetting and per-frame exposure and white balance from SEQUENCE (RGB-D with poses).

    Writes OUTPUT/vignetting.npz (LUT model with its standard error, for reconstruct/compare --vignetting),
    OUTPUT/exposures.txt (reconstruct's format), trajectory.txt, figures and summary.txt.
    """
    from mapping.cli._common import run_manifest
    from mapping.self_calibration import run_self_calibration
    from radiometry.formats import load_response

    response = load_response(response_path) if response_path else None
    manifest = run_manifest("self-calibrate", {"sequence": sequence, "response": response_path, "poses": poses,
                                               "frames": None if frames is None else
                                               f"{frames.start or ''}:{frames.stop or ''}:{frames.step or ''}",
                                               "output": output})
    run = run_self_calibration(sequence, output, response=response, poses=poses, frames=frames, format=format,
                               depth_scale=depth_scale, intrinsics=intrinsics, plots=not no_plots, force=force,
                               progress=not no_progress, manifest=manifest)
    click.echo(run.summary)
