"""``radiomap response``: recover the camera response from bracketed exposures."""

from __future__ import annotations

import time
from pathlib import Path

import click

from mapping.cli._common import Number
from mapping.validation import GAMMA, SMOOTHNESS

FORMATS = {".npz": "radiomap", ".crf": "radical", ".txt": "DSO/TUM pcalib"}
#: the names of radiometry.response.fit.FITTERS (listed here so that --help imports no NumPy)
#: share of the pixels pure blue in some exposure (radiometry.response.fit.blue_fill_mask, dilated) above which a
#: stack fitted without --mask-blue is warned about: memorial's registration fill covers 9.1 %, taipei 0.0 %
BLUE_FILL_SHARE = 0.01
RESPONSE_METHODS = ("auto", "debevec", "engel", "loglog", "opencv-debevec", "robertson")


class LambdaType(Number):
    """A positive number (:data:`mapping.validation.SMOOTHNESS`) or ``auto``."""

    name = "LAMBDA|auto"

    def __init__(self) -> None:
        super().__init__(SMOOTHNESS, "", "Debevec's default 10, the log-log prior's 0.1")

    def convert(self, value, param, ctx):
        if isinstance(value, str) and value.strip().lower() == "auto":
            return "auto"
        return super().convert(value, param, ctx)

EPILOG = """\b
Examples:
  radiomap response data_samples/brackets -o out/crf.npz
      the default fit (log-log curvature prior) on the embedded sample (times from
      data_samples/brackets/times.txt)
  radiomap response ../shared/data/brackets/memorial_debevec1997 --mask-blue -o memorial.crf
      the memorial stack without its blue border fill, saved for radical
  radiomap response brackets/ --times times.txt --method robertson -o pcalib.txt
      OpenCV's Robertson, saved as a DSO pcalib.txt (mean of R, G, B; or --channel G)
  radiomap response brackets/ --method engel -o crf.npz
      Engel's maximum likelihood: no smoothness prior, keeps a knee; needs exposure ratios that are not
      all equal (brackets at exactly 2x steps leave f^-1 undetermined up to an octave-periodic factor)
  radiomap response brackets/ --lambda auto -o crf.npz
      Debevec with the smoothness weight chosen by cross-validation on held-out pixels
  radiomap response --gamma 2.2 -o gamma.npz
      no calibration: the standard response f^-1(I) = (I/255)^2.2, the documented assumption for a camera
      whose response is unknown (sRGB is close to it); --linear writes f^-1(I) = I/255

\b
The times file has one 'image_name seconds' line per image ('#' comments; further columns, such as
the 1/t column of image_list.txt, are ignored). Beside OUT the command writes OUT's name with .png
(plot of the curves) and .json (the run's parameters and summary).
"""


@click.command("response", epilog=EPILOG, short_help="Recover the camera response from bracketed exposures.")
@click.argument("folder", type=click.Path(file_okay=False, path_type=Path), required=False)
@click.option("--times", "times_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Exposure times file ('name seconds' per line). Default: FOLDER/times.txt or image_list.txt.")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Response file: .npz (radiomap), .crf (radical) or .txt (DSO/TUM pcalib, one channel).")
@click.option("--method", type=click.Choice(list(RESPONSE_METHODS)), default="auto",
              show_default=True, help="auto: loglog (Debevec's data term over all pixels with a log-log curvature "
                                      "prior: the most accurate on our test set of curves), or debevec when "
                                      "--samples or --lambda auto is given; or debevec, engel, loglog, or "
                                      "OpenCV's Debevec / Robertson.")
@click.option("--lambda", "lam", type=LambdaType(), default=None,
              help="Smoothness weight (debevec: per level of data, default 10, or 'auto': chosen by "
                   "cross-validation on held-out pixels, also with --method auto; loglog: the prior's weight, "
                   "default 0.1; opencv-debevec: OpenCV's lambda, default 10). A number needs --method.")
@click.option("--samples", type=click.IntRange(min=1), default=None,
              help="debevec: observations per intensity level (default 50); opencv-debevec: pixel locations (70).")
@click.option("--mask-blue", is_flag=True,
              help="Ignore pure-blue fill (registered stacks such as memorial); auto, debevec, engel and loglog.")
@click.option("--channel", type=click.Choice(["mean", "R", "G", "B"], case_sensitive=False), default=None,
              help="For a .txt (pcalib, one channel) OUTPUT of colour images: the channel to write [default: "
                   "mean, with a warning].")
@click.option("--gamma", type=Number(GAMMA, "", "sRGB is about 2.2"), default=None,
              help="Instead of calibrating, write the standard response f^-1(I) = (I/255)^GAMMA (2.2: the "
                   "assumption for a camera whose response is unknown). No FOLDER.")
@click.option("--linear", is_flag=True, help="Instead of calibrating, write the linear response f^-1(I) = I/255. "
                                             "No FOLDER.")
@click.option("--quality", type=click.Choice(["full", "fast", "none"]), default="full", show_default=True,
              help="The truth-free quality figure: full (each exposure predicted by a fit without it, and the "
                   "agreement of fits on two disjoint pixel halves), fast (each exposure predicted through this "
                   "response, no refits), none.")
@click.option("--force", is_flag=True, help="Overwrite OUTPUT if it exists.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def command(folder: Path | None, times_file: Path | None, output: Path, method: str, lam: float | None,
            samples: int | None, mask_blue: bool, channel: str | None, gamma: float | None, linear: bool,
            quality: str, force: bool, no_progress: bool) -> None:
    """Recover the inverse camera response f^-1 from bracketed exposures of a static scene.

    FOLDER holds the images (same size, 8-bit, fixed white balance) and usually their times file.
    Prints a summary and writes the response, a plot of the curves and a JSON record of the run.
    With --gamma or --linear (and no FOLDER) it writes that standard response instead.
    """
    import numpy as np

    from mapping.cli._common import run_manifest
    from radiometry.tables import format_table
    from radiometry.errors import CalibrationError, DatasetError, OutputError
    from radiometry.fileio import atomic_write_json, check_overwrite, ensure_dir, publish_set, refuse_inputs
    from radiometry.api import calibrate_response
    from radiometry.response.fit import blue_fill_mask, find_times_file, load_brackets, own_outputs
    from radiometry.response.inputs import TimesOrderError

    params = {"folder": folder, "times": times_file, "output": output, "method": method, "lambda": lam,
              "samples": samples, "mask_blue": mask_blue, "channel": channel, "gamma": gamma, "linear": linear,
              "quality": quality, "force": force}
    suffix = output.suffix.lower()
    if suffix not in FORMATS:
        raise OutputError(f"{output}: unknown response format {output.suffix!r}; use .npz (radiomap), "
                          ".crf (radical) or .txt (DSO pcalib)")
    standard = gamma is not None or linear
    if standard:
        if gamma is not None and linear:
            raise click.UsageError("give --gamma or --linear, not both")
        if folder is not None or times_file is not None or lam is not None or samples is not None or mask_blue \
                or channel is not None:
            raise click.UsageError("--gamma and --linear write a standard response: they take no FOLDER, --times, "
                                   "--lambda, --samples, --mask-blue or --channel (every channel is the same)")
        check_overwrite(output, *_companions(output), force=force)
        _write_standard(output, suffix, gamma, params)
        return
    if folder is None:
        raise click.UsageError("give the FOLDER of bracketed images to calibrate, or --gamma G / --linear to write "
                               "a standard response")
    kwargs = {}
    if method in ("robertson", "engel") and (lam is not None or samples is not None):
        raise click.UsageError(f"--lambda and --samples apply to debevec, loglog (--lambda only) and opencv-debevec, "
                               f"not {method}")
    if method == "auto" and lam is not None and lam != "auto":
        raise click.UsageError("--lambda N with --method auto is ambiguous: give --method loglog (the prior's weight, "
                               "default 0.1) or --method debevec (the smoothness, default 10); --lambda auto picks "
                               "Debevec's by cross-validation")
    if method == "loglog" and samples is not None:
        raise click.UsageError("--samples applies to debevec and opencv-debevec; loglog uses all pixels")
    if lam == "auto" and method not in ("debevec", "auto"):
        raise click.UsageError("--lambda auto (cross-validation) needs --method debevec")
    if channel is not None and suffix != ".txt":
        raise click.UsageError("--channel applies to a .txt (pcalib) output only")
    if mask_blue and method not in ("auto", "debevec", "engel", "loglog"):
        raise click.UsageError("--mask-blue needs --method debevec, engel or loglog (OpenCV's methods take no "
                               "mask)")
    if lam is not None:
        kwargs["lam"] = lam
    if samples is not None:
        kwargs["samples"] = samples
    check_overwrite(output, force=force)
    ensure_dir(output.parent)  # an unwritable output fails now, not after the fit

    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such folder; pass the folder that holds the bracketed images")
    used_times = times_file if times_file is not None else find_times_file(folder)
    own = own_outputs(folder)   # an earlier run's response, plot and record in the folder: not inputs
    refuse_inputs([output, *_companions(output)],
                  [used_times, *(p for p in folder.iterdir() if p.is_file() and p.name not in own)])
    check_overwrite(output, *_companions(output), force=force)  # the files beside it: inputs are named above
    images, times, names = load_brackets(folder, used_times, progress=not no_progress)
    if channel is not None and images[0].ndim == 2:
        raise click.BadParameter(f"picks R, G or B of a colour stack, but the images of {folder} are grey (one "
                                 "channel, written as it is); drop --channel", param_hint="--channel")
    fill = None   # the share of a registration's pure-blue fill found in a stack fitted without --mask-blue
    if mask_blue:
        mask = blue_fill_mask(images)
        kwargs["mask"] = mask
        click.echo(f"masked {100 * (1 - mask.mean()):.1f}% of the pixels (pure-blue fill)")
    elif images[0].ndim == 3 and images[0].shape[2] == 3:
        fill = 1.0 - float(blue_fill_mask(images).mean())
        if fill > BLUE_FILL_SHARE:
            click.echo(f"warning: {100 * fill:.1f}% of the pixels are pure blue in some exposure (a registration's "
                       "fill, as in memorial): they bias the B curve and its levels; fit with --mask-blue"
                       + ("" if method in ("auto", "debevec", "engel", "loglog") else " (and --method loglog)"),
                       err=True)
    import scipy.sparse.linalg  # noqa: F401  (imported before the clock starts: the time is the fit's)

    start = time.perf_counter()
    try:  # the fit and its prediction error, as radiometry.calibrate_response does them
        response = calibrate_response(images, times, method=method, quality=quality, **kwargs)
    except TimesOrderError as exc:  # the times file's fault: name it and the images that disagree
        raise DatasetError(f"{used_times}: {exc.message(names)}") from None
    except ValueError as exc:  # the images or times of this folder are unusable
        raise DatasetError(f"{folder} ({used_times.name}): {exc}") from None
    except CalibrationError as exc:  # e.g. every pixel saturated: name the folder that holds such images
        from radiometry.images import with_sixteen_bit_note

        # too few levels may be the reduction of 16-bit images to 8 bits: then say that rather than add exposures
        raise CalibrationError(f"{folder}: {with_sixteen_bit_note(exc, [folder / n for n in names])}") from None
    meta = response.meta
    if fill is not None and fill > BLUE_FILL_SHARE and (meta.get("quality") or {}).get("grade") == "good":
        meta["quality"]["grade"] = "doubtful"   # the figures judge the fill's pixels too: not good beside them
        meta["quality"]["summary"] = (meta["quality"]["summary"].replace("quality good", "quality doubtful", 1)
                                      + f"; {100 * fill:.1f}% of the pixels are a pure-blue fill: fit with --mask-blue")
        click.echo(f"warning: {meta['quality']['summary']}", err=True)
    fit_seconds = meta.get("fit_seconds", time.perf_counter() - start)  # the fit's own time, not the quality's
    rms = meta["prediction_rms_levels"]
    meta.update({"folder": str(folder), "times_file": str(used_times), "images_used": names})

    method = meta.get("method", method)  # what "auto" chose
    if "chosen_by" in meta:
        click.echo(f"method {method} ({meta['chosen_by']})")
    plot_path = output.with_suffix(".png")
    repaired = meta.get("repaired_levels")
    tied = sum(len(block) for channel in meta.get("pooled_levels") or [] for block in channel)
    if meta.get("repaired"):
        monotone = f"repaired ({sum(map(len, repaired or [[]]))} levels)"
    else:
        monotone = f"yes ({tied} levels tied by the constraint)" if tied else "yes"
    if method in ("debevec", "engel", "loglog"):
        sampled = "/".join(str(p) for p in meta["pixels"]) + " px"
    elif method == "opencv-debevec":
        sampled = f"{meta['samples']} px"
    else:
        sampled = "all px"
    row = {"method": method, "channels": response.channels, "images": len(images),
           "exposures [s]": f"{times.min():.4g}..{times.max():.4g}", "samples": sampled,
           "fit RMS [levels]": rms, "monotone": monotone, "time [s]": fit_seconds}
    summary = format_table([row])
    record = run_manifest("response", params)
    record.update({"summary": row, "response": {k: v for k, v in meta.items()}, "outputs": {
        "response": str(output), "plot": str(plot_path)}})
    with publish_set(output) as files:  # the response, its plot and record: all three or none (the old set stays)
        _save(files.path(output), response, suffix, channel)
        _plot(files.path(plot_path), response, f"{method}: {folder.name}")
        atomic_write_json(files.path(output.with_suffix(".json")), record)
    click.echo(summary)
    click.echo("fit RMS: error of predicting every unsaturated pixel of every exposure from the merged radiance")
    if meta.get("lambda_selection") == "cross-validation":
        click.echo(f"lambda {meta['lambda']:g}, chosen by cross-validation on held-out pixels")
    if "levels_summary" in meta:
        click.echo(meta["levels_summary"])
    elif "observed_range" in meta:
        spans = ", ".join(f"{lo}..{hi}" for lo, hi in meta["observed_range"])
        click.echo(f"levels constrained by data: {spans} (per channel); the others are extrapolated "
                   "(meta 'extrapolated_levels')")
    if "quality" in meta:
        q = meta["quality"]
        if q["grade"] == "good":  # otherwise radiometry.api has said it as a warning (stderr)
            click.echo(q["summary"])
    click.echo(f"wrote {output} ({FORMATS[suffix]}), {plot_path}, {output.with_suffix('.json')}")
    if not np.isfinite(rms) or rms > 10:
        click.echo("warning: a fit RMS above 10 levels suggests motion, misregistration, wrong exposure times "
                   "or auto exposure/white balance; check the plot", err=True)


def _companions(output: Path) -> list[Path]:
    """The files written beside the response: its plot and its record."""
    return [output.with_suffix(".png"), output.with_suffix(".json")]


def _write_standard(output: Path, suffix: str, gamma: float | None, params: dict) -> None:
    """Write the gamma or linear response (1 channel for a pcalib .txt, else 3) with its plot and record."""
    from mapping.cli._common import run_manifest
    from radiometry.fileio import atomic_write_json, publish_set
    from radiometry.response import CameraResponse

    channels = 1 if suffix == ".txt" else 3
    response = CameraResponse.linear(channels) if gamma is None else CameraResponse.gamma(gamma, channels)
    plot_path = output.with_suffix(".png")
    name = "linear" if gamma is None else f"gamma {gamma:g}"
    record = run_manifest("response", params)
    record.update({"summary": {"method": response.meta["method"], "gamma": gamma, "channels": channels},
                   "response": dict(response.meta), "outputs": {"response": str(output), "plot": str(plot_path)}})
    with publish_set(output) as files:
        _save(files.path(output), response, suffix, None)
        _plot(files.path(plot_path), response, f"standard response: {name}")
        atomic_write_json(files.path(output.with_suffix(".json")), record)
    click.echo(f"wrote {output} ({FORMATS[suffix]}, {name}: f^-1(I) = "
               f"{'I/255' if gamma is None else f'(I/255)^{gamma:g}'}), {plot_path}, {output.with_suffix('.json')}")


def _save(output: Path, response, suffix: str, channel: str | None) -> None:
    if suffix == ".crf":
        from radiometry.formats.crf import write_radical_crf

        write_radical_crf(output, response)
    elif suffix == ".txt":
        from radiometry.formats.pcalib import write_pcalib

        if response.channels == 3 and channel is None:
            click.echo("warning: pcalib.txt holds one channel: writing the mean of R, G and B "
                       "(choose one with --channel R|G|B)", err=True)
            channel = "mean"
        index = {"mean": "mean", "r": 0, "g": 1, "b": 2}[channel.lower()] if channel else None
        write_pcalib(output, response, channel=index if response.channels == 3 else None)
    else:
        response.save(output)


def _plot(path: Path, response, title: str) -> None:
    from radiometry.plots import response_figure, save_figure

    save_figure(response_figure(response, title=title), path)
