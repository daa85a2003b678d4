"""``radiomap self-calibrate``: vignetting, per-frame exposure and white balance from an RGB-D sequence itself."""

from __future__ import annotations

import os

import click

from mapping.cli._common import pose_arguments, pose_options, sequence_options
from mapping.factory import TRACKERS

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
@pose_options("gt", "gt: ground-truth poses; icp: tracked by radiomap's pipeline (--tracker); or a trajectory (a TUM "
                    "file, a Redwood .log, a folder of 7-Scenes pose files; see reconstruct --help).")
@click.option("--tracker", type=click.Choice(list(TRACKERS)), default="auto", show_default=True,
              help="With --poses icp: the tracker (see reconstruct --help).")
@sequence_options
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False),
              help="Folder for vignetting.npz, exposures.txt, figures and the summary.")
@click.option("--exposures", "exposures_path", type=click.Path(dir_okay=False), default=None,
              help="Known per-frame exposures (exposure x gain): radiomap's exposures.txt, 'timestamp k' or "
                   "'timestamp k_r k_g k_b' lines, or TUM monoVO times.txt; only frames without one are fitted. Checked "
                   "against the images' exposure changes: a list off by a frame or more is refused.")
@click.option("--holdout", default="every:5", show_default=True, metavar="every:N|last:P%|none",
              help="Frames withheld from the fit to validate V on (held-out L1 and PSNR with and without V).")
@click.option("--strict", is_flag=True, help="Refuse (write nothing) unless V predicts withheld frames better than "
                                             "no V (a mixed verdict, L1 and PSNR disagreeing, is refused too).")
@click.option("--no-plots", is_flag=True, help="Skip the PNG figures.")
@click.option("--force", is_flag=True, help="Overwrite an earlier self-calibration in OUTPUT.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def command(sequence: str, response_path: str | None, poses, poses_max_difference: float | None, tracker: str, frames,
            depth_scale, intrinsics, format, output: str, exposures_path: str | None, holdout: str, strict: bool,
            no_plots: bool, force: bool, no_progress: bool) -> None:
    """Self-calibrate vignetting and per-frame exposure and white balance from SEQUENCE (RGB-D with poses).

    Writes OUTPUT/vignetting.npz (LUT model with its standard error, for reconstruct/compare --vignetting),
    OUTPUT/exposures.txt (reconstruct's format), trajectory.txt, figures and summary.txt.
    """
    from mapping.self_calibration import run_self_calibration

    run = run_self_calibration(**task_arguments(click.get_current_context()))
    click.echo(run.summary)
    from pathlib import Path

    from mapping.cli._common import written_text

    click.echo(written_text(Path(output)), err=True)


def task_arguments(ctx: click.Context) -> dict:
    """The options of ``ctx`` (a parsed self-calibrate command) checked, as the keyword arguments of
    :func:`mapping.self_calibration.run_self_calibration`: plain values (the response as its path, loaded here
    once to check it) and the manifest; what ``radiomap self-calibrate`` runs and what each task of ``radiomap
    batch self-calibrate`` runs."""
    from mapping.cli._common import run_manifest
    from radiometry.formats import load_response

    p = ctx.params
    from mapping.cli._common import refuse_sequence_as_output

    refuse_sequence_as_output(p["sequence"], p["output"])
    if p["response_path"]:
        load_response(p["response_path"])       # a bad file fails here, before anything is written
    frames = p["frames"]
    if p["tracker"] != "auto" and p["poses"] != "icp":
        raise click.BadParameter(f"applies with --poses icp only (got --poses {p['poses']}: no frame is tracked); "
                                 "drop --tracker or add --poses icp", param_hint="--tracker")
    poses, max_difference = pose_arguments(ctx)   # a trajectory file of the sequence resolved
    from radiometry.self_calibration_validation import parse_holdout

    try:
        parse_holdout(p["holdout"])
    except ValueError as exc:
        raise click.BadParameter(str(exc).replace("holdout must be", "must be"), param_hint="--holdout") from None
    if p["exposures_path"]:
        from mapping.exposure_files import read_exposure_file

        read_exposure_file(p["exposures_path"])   # a bad file fails here, before anything is written
    from mapping.replay import INPUTS_KEY, input_records

    def absolute(value):   # a path as typed is another text from another folder (mapping.batch.resume compares them)
        return os.path.abspath(value) if isinstance(value, str) and value and os.path.exists(value) else value

    manifest = run_manifest("self-calibrate", {"sequence": absolute(p["sequence"]),
                                               "response": absolute(p["response_path"]),
                                               "poses": absolute(p["poses"]) if isinstance(p["poses"], str) and
                                               os.path.isfile(p["poses"]) else p["poses"], "tracker": p["tracker"],
                                               "frames": None if frames is None else
                                               f"{frames.start or ''}:{frames.stop or ''}:{frames.step or ''}",
                                               "output": absolute(p["output"]),
                                               "exposures": absolute(p["exposures_path"]),
                                               "holdout": p["holdout"], "strict": p["strict"],
                                               # read by a resumed batch: a complete folder made with other
                                               # values is refused (mapping.batch.resume)
                                               "format": p["format"], "depth_scale": p["depth_scale"],
                                               "intrinsics": p["intrinsics"] if not p["intrinsics"] or not
                                               os.path.isfile(p["intrinsics"]) else os.path.abspath(p["intrinsics"]),
                                               "poses_max_difference": p["poses_max_difference"],
                                               "plots": not p["no_plots"]})
    # the contents of the files it reads (sha256, mapping.replay): a resumed batch compares them
    manifest[INPUTS_KEY] = input_records({"response": p["response_path"], "exposures": p["exposures_path"],
                                          "poses": p["poses"] if isinstance(p["poses"], str) and
                                          os.path.isfile(p["poses"]) else None})
    return {"sequence": p["sequence"], "output": p["output"], "response": p["response_path"], "poses": p["poses"],
            "tracker": p["tracker"], "poses_max_difference": max_difference,
            "frames": frames, "format": p["format"], "depth_scale": p["depth_scale"], "intrinsics": p["intrinsics"],
            "exposures": p["exposures_path"], "holdout": p["holdout"], "strict": p["strict"],
            "plots": not p["no_plots"], "force": p["force"], "progress": not p["no_progress"], "manifest": manifest}
