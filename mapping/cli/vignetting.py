"""``radiomap vignetting``: calibrate vignetting from a white-paper sweep."""

from __future__ import annotations

from pathlib import Path

import click

from mapping.cli._common import Number
from mapping.validation import SMOOTH_SIGMA_PX
from radiometry.vignetting_calibration import MODELS

EPILOG = """\b
Record the sweep with exposure and white balance FIXED: move the camera over an evenly lit
white sheet (on a darker background) so that every part of the image sees the sheet many times,
corners included. The sheet must not be clipped: keep its brightest part below 244 (levels
within 6 of 250 count as clipped).

\b
Examples:
  radiomap vignetting paper_seq/rgb --response crf.npz -o vignetting.npz
  radiomap vignetting sweep.mp4 --response crf.npz -o xtion.vgn --model poly
  radiomap vignetting 0 --response crf.npz -o vignette.png --min-samples 30 --stop-when-covered
      (camera index 0; '.vgn' writes radical's format, '.png' DSO's 16-bit vignette.png)
"""


# the library default of fit_vignetting_lut(smooth_sigma=...); tests check that they agree
DEFAULT_SMOOTH_SIGMA = 1.0


@click.command("vignetting", epilog=EPILOG)
@click.argument("frames", metavar="FRAMES")
@click.option("-r", "--response", "response_path", required=True, type=click.Path(dir_okay=False),
              help="Camera response: radiomap .npz, radical .crf or DSO pcalib.txt.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Model file: .npz (radiomap), .vgn (radical) or .png (DSO 16-bit vignette, channel mean).")
@click.option("--model", "model_name", type=click.Choice(list(MODELS)), default="lut", show_default=True,
              help="LUT per pixel, or polynomial with free / fixed centre.")
@click.option("--min-samples", type=click.IntRange(min=1), default=20, show_default=True,
              help="Samples per pixel wanted; coverage below it is reported.")
@click.option("--stop-when-covered", is_flag=True, help="Stop reading frames once every pixel has --min-samples.")
@click.option("--max-frames", type=click.IntRange(min=1), default=None, help="Read at most this many frames.")
@click.option("--no-drift-correction", is_flag=True,
              help="Do not estimate per-frame brightness drift (plain average as in radical).")
@click.option("--smooth-sigma", type=Number(SMOOTH_SIGMA_PX, "px", "0 disables the smoothing, 2-3 suits thin sweeps"),
              default=DEFAULT_SMOOTH_SIGMA, show_default=True,
              help="LUT only: denoise the per-pixel residual to the radial fit with a Gaussian of this many "
                   "pixels (0 = off). Raise it (2-3) for short or noisy sweeps with few samples per pixel; "
                   "lower it to keep fine non-radial detail when every pixel has many samples.")
@click.option("--save-accumulation", type=click.Path(dir_okay=False), default=None,
              help="Also save the fused data (.npz) for later fits or repeatability studies.")
@click.option("--allow-exposure-changes", is_flag=True,
              help="Calibrate even when the sheet's brightness varied by more than 25% between frames (auto "
                   "exposure left on); the drift correction then leaves up to ~0.7 levels of error.")
@click.option("--no-plots", is_flag=True, help="Skip the PNG figures (the coverage map is always written).")
@click.option("--force", is_flag=True, help="Overwrite existing output files.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def command(frames: str, response_path: str, output: str, model_name: str, min_samples: int,
            stop_when_covered: bool, max_frames: int | None, no_drift_correction: bool, smooth_sigma: float,
            save_accumulation: str | None, allow_exposure_changes: bool, no_plots: bool, force: bool,
            no_progress: bool) -> None:
    """Calibrate vignetting from a white-paper sweep FRAMES (folder, video file or camera index).

    Writes the model, a coverage map (<OUT stem>_coverage.png), figures (V per channel, radial
    profiles with samples, residuals) and a summary (<OUT stem>_summary.txt/.json).
    """
    from radiometry.errors import CalibrationError, ModelMismatchError, OutputError
    from radiometry.fileio import (atomic_write_json, atomic_write_text, check_overwrite, ensure_dir, publish_set,
                                   refuse_inputs)
    from radiometry.formats import VIGNETTING_WRITERS, load_response, save_vignetting
    from radiometry.plots_vignetting import save_calibration_figures, save_coverage_png
    from radiometry.vignetting_calibration import calibration_summary, collect_vignetting, fit_vignetting
    from radiometry.vignetting_calibration.evaluate import budget_text
    from mapping.cli._common import run_manifest
    from radiometry.tables import format_table

    source = click.get_current_context().get_parameter_source("smooth_sigma")
    if model_name != "lut" and source is not click.core.ParameterSource.DEFAULT:
        raise click.BadParameter(f"applies to --model lut only, got --model {model_name}; drop --smooth-sigma "
                                 "or use --model lut", param_hint="--smooth-sigma")
    out = Path(output)
    if out.suffix.lower() not in VIGNETTING_WRITERS:
        raise OutputError(f"{out}: unknown model format {out.suffix!r}; use .npz (radiomap), .vgn (radical) "
                          "or .png (DSO vignette)")
    prefix = out.with_name(out.stem)
    outputs = [out, *(prefix.with_name(f"{prefix.name}_{name}") for name in (
        "coverage.png", "vignetting.png", "stderr.png", "profiles.png", "residuals.png", "summary.txt",
        "summary.json"))] + ([Path(save_accumulation)] if save_accumulation else [])
    source = Path(frames)
    inputs = [response_path] + ([p for p in source.iterdir() if p.is_file()] if source.is_dir() else [source])
    refuse_inputs(outputs, inputs)   # with or without --force: never over a frame of the sweep or the response
    written = [p for p in outputs[1:] if not (no_plots and p.name.endswith(("_vignetting.png", "_stderr.png",
                                                                          "_profiles.png", "_residuals.png")))]
    check_overwrite(out, *written, force=force)   # the model and every file written beside it
    ensure_dir(out.parent)  # an unwritable output fails now, not after reading every frame
    response = load_response(response_path)
    try:
        acc = collect_vignetting(frames, response, min_samples=min_samples, stop_when_covered=stop_when_covered,
                                 max_frames=max_frames, progress=not no_progress)
    except ModelMismatchError as exc:   # a grey sweep through an RGB response: name both files
        raise ModelMismatchError(f"{frames} through {response_path}: {exc}") from None
    spread = frame_scale_spread(acc)
    if spread > SCALE_SPREAD_REFUSED and not allow_exposure_changes:
        raise CalibrationError(f"{frames}: the sheet's brightness varied by {100 * spread:.0f}% between frames: auto "
                               "exposure (or the light) changed during the sweep; record it with a fixed exposure, "
                               "or pass --allow-exposure-changes to accept up to ~0.7 levels of error")
    fit_options = {"joint_scale": not no_drift_correction}
    if model_name == "lut":
        fit_options["smooth_sigma"] = smooth_sigma
        fit_options["thin_samples"] = min_samples
    try:
        model = fit_vignetting(acc, model=model_name, **fit_options)
    except CalibrationError as exc:   # too little of the image seen: the response's levels may be the cause
        blame = response_levels_excluded(acc, response, response_path)
        if blame is None:
            raise
        finding = getattr(exc, "finding", None)   # the fit's advice gives way to the cause found here
        raise CalibrationError(f"{finding}, because {blame}" if finding else f"{exc}; the cause: {blame}") from None
    rows, facts = calibration_summary(model, acc, response, min_samples)
    skipped = ", ".join(f"{k}: {v}" for k, v in sorted(acc.skipped.items())) or "none"
    lines = [
        f"vignetting model ({model_name}) -> {out}",
        f"frames used: {acc.frames_used}, skipped: {acc.frames_skipped} ({skipped})",
        str(acc.coverage_report(min_samples)),
        format_table(rows),
    ]
    if "error_budget" in facts:
        lines.append(budget_text(facts["error_budget"], model.channels))
    lines.extend(_truth_free_lines(acc, response, model_name, fit_options, facts, not no_drift_correction))
    text = "\n".join(lines)
    # the model, its figures, summaries and the accumulation: all published together or none (the old set stays)
    with publish_set(out) as files:
        save_vignetting(model, files.path(out))
        if save_accumulation:
            acc.save(files.path(save_accumulation))
        staged = files.path(prefix)
        if no_plots:
            figures = {"coverage": save_coverage_png(staged.with_name(staged.name + "_coverage.png"),
                                                     acc.coverage(), min_samples)}
        else:
            figures = save_calibration_figures(staged, acc, model, min_samples=min_samples)
        figures = {name: files.final(path) for name, path in figures.items()}
        for side in outputs[1:6]:  # an earlier run's figure this run does not write (--no-plots, a model without
            if not files.path(side).exists():  # a standard error) would describe another model: removed with it
                files.retire(side)
        atomic_write_text(staged.with_name(staged.name + "_summary.txt"), text + "\n")
        atomic_write_json(staged.with_name(staged.name + "_summary.json"),
                          {**facts, "model": model_name, "output": str(out), "figures": figures,
                           "run": run_manifest("vignetting", {"frames": frames, "response": response_path,
                                                              "output": output, "model": model_name,
                                                              "min_samples": min_samples,
                                                              "stop_when_covered": stop_when_covered,
                                                              "max_frames": max_frames,
                                                              "drift_correction": not no_drift_correction,
                                                              "allow_exposure_changes": allow_exposure_changes,
                                                              "smooth_sigma": smooth_sigma if model_name == "lut"
                                                              else None})})
    click.echo(text)
    from mapping.cli._common import written_files_text

    click.echo(written_files_text([out, save_accumulation, *figures.values(), Path(prefix).with_name(
        Path(prefix).name + "_summary.txt"), Path(prefix).with_name(Path(prefix).name + "_summary.json")]), err=True)



#: the split-half uncertainty (levels) up to which a vignetting model is trusted
SPLIT_GOOD_LEVELS = 0.5
#: frame-to-frame brightness spread (max / min - 1) above which the sweep is said to have had auto exposure on, and
#: above which it is refused (without --allow-exposure-changes): the drift correction absorbs a spread of 15 % to
#: 0.30-0.44 levels and one of 45 % only to 0.72 (EuRoC vignette, docs/calibration_pipelines.md)
SCALE_SPREAD = 0.05
SCALE_SPREAD_REFUSED = 0.25


def frame_scale_spread(acc) -> float:
    """How much the sheet's brightness varied between frames: max / min of the frames' scales, minus 1."""
    import numpy as np

    scales = acc.frame_scales() if acc.frames_used > 1 else np.ones((1, acc.channels))
    return float(np.max(scales) / np.min(scales) - 1.0)


def response_levels_excluded(acc, response, response_path: str) -> str | None:
    """Why the sweep gave (almost) no samples when the response, not the sweep, is the cause: most of the sheet's
    readings in every channel are at levels the response does not declare (its ``meta["extrapolated_levels"]``, which
    the accumulation leaves out); None when the sheet's levels are mostly within them or were not recorded."""
    import numpy as np

    from radiometry.response.levels import declared
    from radiometry.vignetting_calibration.accumulate import extrapolated_mask

    hist = getattr(acc, "level_hist", None)
    if hist is None or not np.asarray(hist).sum(axis=1).all():
        return None
    hist = np.asarray(hist, dtype=np.float64)
    kept = extrapolated_mask(response, acc.channels).T            # (C, 256)
    outside = (hist * ~kept).sum(axis=1) / hist.sum(axis=1)
    if float(outside.min()) <= 0.5:
        return None
    spans = ", ".join(f"{lo}..{hi}" for lo, hi in declared(response, acc.channels))
    seen = [np.flatnonzero(h) for h in hist]
    sheet = ", ".join(f"{s.min()}..{s.max()}" for s in seen)
    return (f"the response {response_path} declares levels {spans} only (those its brackets constrained) and "
            f"{100 * float(outside.min()):.0f}% of the sheet's readings (levels {sheet}) lie outside them; calibrate "
            "the response from brackets that reach the sheet's levels, or record the sweep at an exposure within them")


#: responses radiomap did not calibrate but assumed (``radiomap response --gamma`` / ``--linear``)
ASSUMED_RESPONSES = ("gamma", "linear")


def _truth_free_lines(acc, response, model_name: str, fit_options: dict, facts: dict, drift: bool) -> list[str]:
    """The figures a user without the truth can judge a calibration by (also recorded in ``facts``): the split-half
    uncertainty (the model on the even and the odd frames), the error budget's total, JPEG frames, the spread of the
    frames' brightness and the response's own grade; the last line is the calibration's grade (``facts["quality"]``:
    good, doubtful or broken) with every reason that lowered it."""
    import numpy as np

    from radiometry.response.levels import BLOCKY
    from radiometry.response.quality import worse_grade
    from radiometry.vignetting_calibration.evaluate import split_half_levels

    lines, reasons, grade = [], [], "good"

    def lower(to: str, reason: str) -> None:
        nonlocal grade
        grade = worse_grade(to, grade)
        reasons.append(reason)

    split = split_half_levels(acc, response, model=model_name, **fit_options)
    names = "R/G/B" if acc.channels == 3 else "grey"
    if split is None:
        facts["split_half_levels"] = None
        lines.append("split-half uncertainty: not computed (fewer than 4 frames, or a half too thin to fit)")
    else:
        facts["split_half_levels"] = [round(float(v), 4) for v in split]
        worst = float(np.max(split))
        text = "/".join(f"{v:.3f}" for v in split)
        lines.append(f"split-half uncertainty ({names}, levels of a flat field at 200; the model on the even vs the "
                     f"odd frames, halved): {text} (trusted up to {SPLIT_GOOD_LEVELS:g})")
        if worst > SPLIT_GOOD_LEVELS:
            lower("doubtful", f"the split-half uncertainty is {worst:.2f} levels: record a longer sweep that covers "
                              "every part of the image several times")
    budget = facts.get("error_budget") or {}
    total = np.nan_to_num(np.asarray(budget.get("total", [0.0]), dtype=np.float64), nan=0.0)
    if total.size and float(total.max()) > SPLIT_GOOD_LEVELS:
        lower("doubtful", f"the error budget's total is {float(total.max()):.2f} levels (its parts above)")
    blocky = getattr(acc, "blockiness", None)
    facts["blockiness"] = None if blocky is None else round(float(blocky), 3)
    if blocky is not None and blocky > BLOCKY:
        lower("doubtful", f"the frames are JPEG-compressed (blockiness {blocky:.2f}): JPEG rounds a sheet that looks "
                          "the same in every frame the same way every time, an error the split-half figure does not "
                          "see (0.4-1.9 levels on simulated JPEG sweeps with the true response, "
                          f"docs/calibration_pipelines.md); record PNG or raw frames for a LUT within "
                          f"{SPLIT_GOOD_LEVELS:g} levels")
    spread = frame_scale_spread(acc)
    facts["frame_scale_spread"] = round(spread, 4)
    if spread > SCALE_SPREAD:
        if drift:
            lines.append(f"note: the sheet's brightness varied by {100 * spread:.0f}% between frames (auto exposure "
                         "on, or the light changing); the drift correction absorbed it, but a fixed exposure is "
                         "better")
        else:
            lines.append(f"warning: the sheet's brightness varied by {100 * spread:.0f}% between frames (auto "
                         "exposure on, or the light changing) and --no-drift-correction averaged it into V; drop "
                         "that option or record with a fixed exposure")
        if spread > SCALE_SPREAD_REFUSED or not drift:
            lower("doubtful", f"the sheet's brightness varied by {100 * spread:.0f}% between frames (up to ~0.7 "
                              "levels of error after the drift correction): record with a fixed exposure")
    meta = getattr(response, "meta", {}) or {}
    given = (meta.get("quality") or {}).get("grade") if isinstance(meta.get("quality"), dict) else None
    if given in ("doubtful", "broken"):
        lower(given, f"the response was graded {given} when it was calibrated (radiomap response; its summary says "
                     "why): V is only as right as the response it was measured through"
                     + ("; calibrate the response again" if given == "broken" else ""))
    elif meta.get("method") in ASSUMED_RESPONSES:
        what = f"gamma {meta.get('gamma'):g}" if meta.get("method") == "gamma" else "linear"
        lower("doubtful", f"the response is assumed ({what}), not calibrated: V is only as right as that assumption "
                          "and no error budget can say how wrong it is (a camera whose response is not "
                          f"{what} gives a V off by levels); calibrate it from brackets (radiomap response)")
    facts["quality"] = grade
    facts["quality_reasons"] = reasons
    lines.append(f"quality: {grade}" + ("" if not reasons else ": " + "; ".join(reasons)))
    return lines
