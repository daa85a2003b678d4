"""A truth-free quality figure for a response calibration: whether to trust the file.

A user with a real camera has no true curve to compare with. Two figures need none:

- **held-out prediction** (levels RMS, and its ratio to the images' own noise): each exposure in turn (at most six,
  spread over the stack; with five exposures or more) is left out, the response is fitted on the others
  (or, for a response given rather than fitted, used as it is), the others are merged into radiance and the
  left-out exposure is predicted through the response. A response that is right predicts an image it has not
  seen to the image's noise; a wrong curve, wrong exposure times or a camera that moved between exposures do
  not.
- **split-half uncertainty** (% of the range): the response fitted on two spatially disjoint halves of the pixels (a
  checkerboard of 32-pixel blocks), compared over the declared levels after the same per-channel scale alignment
  the accuracy figures use; half their largest difference (each half has twice the full fit's variance, so the
  difference has twice its standard deviation) estimates what the pixels leave uncertain in the full fit;
  scene-dependent errors (a region that does not follow the model) make the halves disagree more.

The noise is the Laplacian's in one image, or, when texture at the pixel scale inflates that, the noise measured
between exposures (:mod:`radiometry.response.noise`); the sentence then says the images' noise could not be measured in
one image, and a response is good only within :data:`TEXTURE_GOOD_LEVELS` levels RMS and broken above
:data:`TEXTURE_BROKEN` times that noise.

Both are computed over the levels the fit declares constrained and without the observations it found saturated
(:mod:`radiometry.response.levels`). :func:`verdict` turns them into a sentence with the thresholds that
separated good from broken fits in ``scripts/bench_calibration.py --quality`` (docs/calibration_pipelines.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from radiometry.errors import RadiomapError
from radiometry.response.levels import declared
from radiometry.response.model import LEVELS, CameraResponse
from radiometry.response.noise import image_noise, stack_noise

#: held-out RMS over the images' own noise (x 1.2 for the merge's) up to which a response is trusted, and beyond which
#: it is called broken. Measured: good fits 0.92-1.52 (clean, JPEG q92, noise after the response), a camera moved
#: 1-2 px 8.4, the wrong curve 18.6; the real stacks memorial (film, reciprocity failure) 3.02 and taipei 2.83
#: (2026-11-28, with refits)
HOLDOUT_GOOD = 2.0
HOLDOUT_BROKEN = 4.0
#: on JPEG stacks (radiometry.response.levels.blockiness) both thresholds are this many times larger: the Laplacian
#: misses JPEG's block noise (flat inside a block), which the prediction sees (EuRoC curve through JPEG q75/q92:
#: 6.7-8.3x with a response within 0.5-2.4 %)
JPEG_FACTOR = 2.5
#: held-out RMS (levels) above which a response is never graded good, whatever its ratio to the noise: on small or
#: textured images the noise estimate (the Laplacian) picks up texture, so a large error can look like noise (a JPEG
#: q75 64x48 stack predicted at 21.96 levels, "1.48x", with a curve 9 % off); good fits measured 1.2-2.9 levels
HOLDOUT_ABSOLUTE = 8.0
#: held-out RMS (levels) up to which a response is good when texture at the pixel scale kept the images' noise from
#: being measured in one image (radiometry.response.noise): the noise between exposures cannot tell noise from a
#: camera that moved, so the error itself must be small too (good fits measured 1.2-2.9 levels; on a random-pixel
#: stack with 0.5 levels of noise the right curve 0.66, gamma 2.0 given for 2.2 3.58)
TEXTURE_GOOD_LEVELS = 3.0
#: held-out RMS over the noise between exposures above which such a response is broken: that figure misses errors
#: that neighbouring exposures share (JPEG's on random pixels, which the blockiness test misses: the right curve read
#: 2.0-4.6x there), so the JPEG stacks' limit (JPEG_FACTOR x HOLDOUT_BROKEN) applies. Measured on random pixels
#: (320x240): the right curves 0.98-3.45x; gamma 2.0 given for 2.2 3.2-10.7x (doubtful or broken, never good); the
#: kink curve 18-64x (broken)
TEXTURE_BROKEN = 10.0
#: the in-sample prediction RMS (levels, radiometry.api) above which a response is said to predict the images badly;
#: a response is never graded good beside that warning
FIT_RMS_WARNING = 10.0
#: shares of the levels tied by a fit's monotone constraint (``meta["pooled_levels"]``) above which a response is not
#: good, and broken: the data did not determine ``f^-1`` there (Engel's fit on the real 2x stacks: memorial 14 %,
#: taipei 27 % and 14-16 % off the default fit; the default and Debevec tie none on them)
TIED_DOUBTFUL, TIED_BROKEN = 0.10, 0.25
#: split-half uncertainty (% of the range) up to which a response is trusted (more makes it doubtful, not broken)
SPLIT_GOOD = 1.5
#: pixels per channel in the held-out and split-half fits (fewer than the fit itself: they are many)
QUALITY_PIXELS = 20_000
#: refits need this many exposures (with fewer, leaving one out can leave a gap the rest cannot bridge: the response
#: is then used as it is); at most HELD_OUT exposures, spread over the stack, are held out
MIN_REFIT_EXPOSURES = 5
HELD_OUT = 6
#: the held-out prediction's expected RMS over the image noise (the merged radiance adds its own)
MERGE_FACTOR = 1.2
BLOCK = 32
#: a bend: the slope of ``f^-1`` over BEND_WIDTH levels, BEND_GAP levels above a level, this many times its slope as
#: far below, at a level from BEND_FROM up (below it every gamma-like curve bends that much by itself: gamma 2.2's
#: ratio is 2.5 at level 11, 1.2 at 50). Measured on fits (2x and varied designs, 320x240, 75 stacks through the
#: five pipelines; docs/calibration_pipelines.md): smooth curves (gamma 2.2, EuRoC, s-curve) 1.18-1.79 from level 32
#: up; a x4 kink at 180 fits as 1.7-3.9 per channel (2.2-3.9 in its sharpest channel), a x50 knee at 200 as 2.2-10000
BEND_RATIO = 2.0
BEND_FROM = 32
BEND_WIDTH = 4
BEND_GAP = 2
_HAT = np.maximum(np.minimum(np.arange(LEVELS, dtype=np.float64), 255.0 - np.arange(LEVELS)), 1.0)


def _usable(stack: np.ndarray, times: np.ndarray, levels: list[tuple[int, int]]) -> np.ndarray:
    """``(P, N, C)`` boolean: observations within the declared levels and not stalled (saturated)."""
    from radiometry.response.levels import stalled_observations

    n_img, n_pix, n_ch = stack.shape
    out = np.zeros(stack.shape, bool)
    for c in range(n_ch):
        lo, hi = levels[c]
        values = stack[:, :, c]
        out[:, :, c] = (values >= lo) & (values <= hi) & ~stalled_observations(values, times)
    return out


def _predict_rms(stack: np.ndarray, times: np.ndarray, usable: np.ndarray, response: CameraResponse, j: int,
                 pixels: np.ndarray) -> tuple[float, int]:
    """Squared-error sum and count of predicting exposure ``j`` from the others merged, over ``pixels``."""
    n_img, _, n_ch = stack.shape
    tables = response.channel_tables(n_ch).astype(np.float64)
    sq, count = 0.0, 0
    others = [k for k in range(n_img) if k != j]
    for c in range(n_ch):
        with np.errstate(divide="ignore"):
            g = np.log(tables[:, c])
        num = np.zeros(pixels.size)
        den = np.zeros(pixels.size)
        for k in others:
            z = stack[k, pixels, c]
            w = np.where(usable[k, pixels, c], _HAT[z], 0.0)
            num += w * (np.where(w > 0, g[z], 0.0) - math.log(times[k]))
            den += w
        sel = (den > 0) & usable[j, pixels, c]
        if not sel.any():
            continue
        radiance = np.exp(num[sel] / den[sel]) * times[j]
        pred = np.interp(radiance, tables[:, c], np.arange(LEVELS, dtype=np.float64))
        err = pred - stack[j, pixels[sel], c]
        sq += float(np.sum(err ** 2))
        count += int(err.size)
    return sq, count


def holdout_rms(images: Sequence[np.ndarray], times: Sequence[float], response: CameraResponse, *,
                refit: Callable[[list[np.ndarray], np.ndarray], CameraResponse] | None = None,
                mask: np.ndarray | None = None, max_pixels: int = 200_000, seed: int = 0) -> dict[str, Any]:
    """Each exposure predicted from the others (``refit``: a function ``(images, times) -> response`` that fits
    without it; None: ``response`` for every exposure). Returns ``{"rms": overall, "per_exposure": [...]}``,
    levels, and the noise it is compared with (:func:`radiometry.response.noise.stack_noise`): ``"noise"`` (the one
    used), ``"noise_in_images"`` (the Laplacian's), ``"noise_between"`` and ``"texture"``; ``"ratio"`` is ``rms`` over
    :data:`MERGE_FACTOR` times ``"noise"``."""
    from radiometry.response.inputs import _as_stack

    from radiometry.response.levels import BLOCKY, blockiness, edge_mask

    stack, t = _as_stack(images, times)
    n_img, h, w, n_ch = stack.shape
    flat = stack.reshape(n_img, h * w, n_ch)
    valid = None if mask is None else np.asarray(mask, bool).ravel()
    compressed = blockiness(stack) > BLOCKY
    keep = edge_mask(stack, valid)[0] if compressed else None  # the pixels the fit itself uses
    if keep is not None:
        valid = keep.ravel() if valid is None else valid & keep.ravel()
    pixels = np.arange(h * w) if valid is None else np.flatnonzero(valid)
    if pixels.size > max_pixels:
        pixels = np.sort(np.random.default_rng(seed).choice(pixels, max_pixels, replace=False))
    usable = _usable(flat, t, declared(response, n_ch))
    per, sq_all, n_all = [], 0.0, 0
    in_sample = None  # why the prediction is in-sample (None: held out, or a response given rather than fitted)
    if refit is not None and n_img < MIN_REFIT_EXPOSURES:
        refit = None
        in_sample = "too few exposures to hold one out"
    order = np.argsort(t)
    held = sorted(int(order[k]) for k in np.unique(np.linspace(0, n_img - 1, min(n_img, HELD_OUT)).round()
                                                   .astype(int)))
    refitted = 0
    for j in held:
        model = response
        if refit is not None:
            keep = [k for k in range(n_img) if k != j]
            try:
                model = refit([stack[k] if n_ch == 3 else stack[k, :, :, 0] for k in keep], t[keep])
                refitted += 1
            except (ValueError, RadiomapError):  # the others alone do not calibrate: judge the response as it is
                model = response
        sq, count = _predict_rms(flat, t, usable, model, j, pixels)
        per.append(math.sqrt(sq / count) if count else float("nan"))
        sq_all += sq
        n_all += count
    rms = math.sqrt(sq_all / n_all) if n_all else float("nan")
    if refit is not None and refitted == 0:
        in_sample = "no fit without an exposure succeeded"
    noise = stack_noise(stack, flat[:, pixels], t, usable[:, pixels], declared(response, n_ch), compressed=compressed)
    used = noise["noise"]
    return {"rms": rms, "compressed": compressed, "per_exposure": per, "held_out": [float(t[j]) for j in held],
            "refit": refitted, "in_sample": in_sample,
            "noise": used, "noise_in_images": noise["in_images"], "noise_between": noise["between_exposures"],
            "texture": noise["texture"],
            "ratio": rms / (MERGE_FACTOR * used) if used and math.isfinite(used) else float("nan")}


def _aligned_difference(a: np.ndarray, b: np.ndarray, levels: list[tuple[int, int]]) -> np.ndarray:
    """Max ``|a - b|`` per channel over the declared levels, % of the range, ``a`` scaled to ``b`` by least squares
    in ``ln`` over the declared levels from 32 up."""
    out = []
    for c, (lo, hi) in enumerate(levels):
        sel = slice(max(lo, 32), hi + 1)
        scale = float(np.exp(np.mean(np.log(b[sel, c]) - np.log(a[sel, c]))))
        out.append(100 * float(np.abs(a[lo:hi + 1, c] * scale - b[lo:hi + 1, c]).max()))
    return np.array(out)


def split_half(images: Sequence[np.ndarray], times: Sequence[float], fit: Callable[..., CameraResponse],
               levels: list[tuple[int, int]], *, mask: np.ndarray | None = None) -> np.ndarray:
    """Per channel, half the largest disagreement (% of the range) of two fits on a checkerboard of 32-pixel blocks
    and its complement (an estimate of the full fit's error from its pixels); ``fit(images, times, mask=...)`` fits
    one half."""
    shape = np.asarray(images[0]).shape[:2]
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    board = ((yy // BLOCK + xx // BLOCK) % 2).astype(bool)
    base = np.ones(shape, bool) if mask is None else np.asarray(mask, bool)
    a = fit(images, times, mask=base & board).inverse_table
    b = fit(images, times, mask=base & ~board).inverse_table
    return _aligned_difference(a, b, levels) / 2.0


def bends(response: CameraResponse, levels: list[tuple[int, int]]) -> list[dict[str, Any]]:
    """Per channel, the sharpest bend of ``f^-1`` within its declared levels (from :data:`BEND_FROM`) whose slope
    ratio (above / below, :data:`BEND_WIDTH` levels each, :data:`BEND_GAP` levels from it) exceeds
    :data:`BEND_RATIO`: ``{"channel", "level", "ratio"}``. Only bends where ``f^-1`` grows steeper (a knee, a
    highlight shoulder) are looked for, not where it flattens. Noise on the levels (JPEG, a camera's processing) makes the
    fit round such a bend, by 0.8-2.6 % of the range near it on the curves measured, and the held-out prediction
    (in levels, where a steep ``f^-1`` is flat) does not see it."""
    table = response.inverse_table
    out = []
    reach = BEND_GAP + BEND_WIDTH
    for c, (lo, hi) in enumerate(levels):
        column = table[:, min(c, table.shape[1] - 1)]
        t = column / column[-1]
        at = np.arange(max(lo, BEND_FROM) + reach, hi - reach + 1)
        if at.size == 0:
            continue
        below = (t[at - BEND_GAP] - t[at - reach]) / BEND_WIDTH
        above = (t[at + reach] - t[at + BEND_GAP]) / BEND_WIDTH
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(below > 0, above / below, 0.0)
        k = int(np.argmax(ratio))
        if ratio[k] > BEND_RATIO:
            out.append({"channel": c, "level": int(at[k]), "ratio": round(float(ratio[k]), 2)})
    return out


def bend_text(found: list[dict[str, Any]], channels: str = "RGB") -> str:
    """The sentence for :func:`bends`' findings ('' when none)."""
    if not found:
        return ""
    names = channels if len(channels) >= 1 + max(b["channel"] for b in found) else "RGB"
    where = ", ".join(f"{names[b['channel']]} at level {b['level']} (slope x{b['ratio']:.1f})" for b in found)
    return (f"f^-1 bends sharply: {where}; noise on the levels (JPEG, the camera's processing) makes a fit round such "
            f"a bend, by 0.8-2.6 % of the range near it on the curves measured, which the held-out prediction does "
            f"not see: check the plot there, and fit from PNG or raw brackets where the bend matters")


#: the grades, best first
GRADES = ("good", "doubtful", "broken")


def worse_grade(a: str, b: str) -> str:
    """The worse of two grades of :data:`GRADES`."""
    return a if GRADES.index(a) > GRADES.index(b) else b


def tied_share(response: CameraResponse) -> float:
    """The share of a response's levels (all channels) that its fit tied to one value to keep ``f^-1`` increasing
    (``meta["pooled_levels"]``: lists of blocks per channel); 0 when it records none."""
    pooled = response.meta.get("pooled_levels") or []
    try:
        tied = sum(len(block) for channel in pooled for block in channel)
    except TypeError:       # another layout: nothing to count
        return 0.0
    return tied / float(256 * max(response.channels, 1))


def verdict(holdout: float, split: Sequence[float] | None, ratio: float, *,
            compressed: bool = False, in_sample: str | None = None,
            fit_rms: float | None = None, kind: str = "held-out prediction",
            texture: tuple[float, float] | None = None) -> tuple[str, str]:
    """``(grade, sentence)``: ``good``, ``doubtful`` or ``broken``, with what to do. ``ratio``: the held-out RMS
    over the noise the images themselves carry (:func:`image_noise`, times :data:`MERGE_FACTOR`); ``compressed``:
    a JPEG stack (the thresholds times :data:`JPEG_FACTOR`); ``in_sample``: why no exposure could be held out (the
    prediction then includes the exposure it predicts: never good); ``fit_rms``: the in-sample prediction RMS of the
    whole stack (above :data:`FIT_RMS_WARNING` never good); ``kind``: what the figure is called in the sentence. A
    held-out RMS above :data:`HOLDOUT_ABSOLUTE` levels is doubtful at best. ``texture``: ``(Laplacian, between
    exposures)`` when texture at the pixel scale kept the images' noise from being measured in one image
    (:func:`radiometry.response.noise.stack_noise`): ``ratio`` is then over the noise between exposures (which a
    camera that moved would inflate too), the sentence says so, a response is good only up to
    :data:`TEXTURE_GOOD_LEVELS` levels RMS and broken above :data:`TEXTURE_BROKEN` times that noise."""
    scale = JPEG_FACTOR if compressed else 1.0
    worst_split = None if split is None else float(np.max(split))
    if not (math.isfinite(holdout) and math.isfinite(ratio)):
        return "unknown", ("quality not computed: too few pixels within the declared levels to predict an exposure or "
                           "measure the images' noise; check the plot")
    broken = ratio > (TEXTURE_BROKEN if texture is not None else scale * HOLDOUT_BROKEN)
    good = ratio <= scale * HOLDOUT_GOOD and (worst_split is None or worst_split <= SPLIT_GOOD)
    kind = kind if in_sample is None else f"in-sample prediction ({in_sample})"
    noise = "the images' noise" if texture is None else "the noise measured between exposures"
    figures = (f"{kind} {holdout:.2f} levels RMS, {ratio:.2f}x {noise}" +
               ("" if worst_split is None else f", split-half uncertainty {worst_split:.2f} %"))
    if texture is not None:
        figures += (f" (the images' noise could not be measured in one image: texture at the pixel scale, whose "
                    f"Laplacian reads {texture[0]:.2f} levels against {texture[1]:.2f} between exposures; a camera or "
                    "scene that moved between exposures would count as noise there)")
    limits = f"trusted up to {scale * HOLDOUT_GOOD:g}x{' for JPEG' if compressed else ''} and {SPLIT_GOOD:g} %"
    if texture is not None:
        limits = (f"trusted up to {HOLDOUT_GOOD:g}x, {TEXTURE_GOOD_LEVELS:g} levels RMS and {SPLIT_GOOD:g} %, "
                  f"broken above {TEXTURE_BROKEN:g}x")
    why = []  # what keeps a response whose ratio looks good from being graded good
    if holdout > HOLDOUT_ABSOLUTE:
        why.append(f"{holdout:.1f} levels RMS is more than the {HOLDOUT_ABSOLUTE:g} levels a good fit predicts to "
                   "(good fits: 1.2-2.9), whatever its ratio to the noise (whose estimate takes texture for noise on "
                   "small or textured images)")
    if texture is not None and holdout > TEXTURE_GOOD_LEVELS:
        why.append(f"with the noise measured only between exposures a response is trusted up to "
                   f"{TEXTURE_GOOD_LEVELS:g} levels RMS (good fits: 1.2-2.9)")
    if fit_rms is not None and not (fit_rms <= FIT_RMS_WARNING):
        why.append(f"the response predicts the images with an RMS error of {fit_rms:.1f} levels (above "
                   f"{FIT_RMS_WARNING:g})")
    if in_sample is not None:
        why.append("an in-sample prediction cannot show a wrong curve: record 5 exposures or more for a held-out one")
    if good and not why:
        return "good", f"quality good: {figures}"
    if broken:
        causes = ("the camera moved between exposures, the exposure times are wrong, auto exposure or white balance "
                  "was on, " + ("JPEG compression is too strong (fit from PNG or raw brackets), " if compressed
                                else "") + "or the curve does not fit these images")
        return "broken", (f"quality BROKEN: {figures} ({limits}); do not use this response: {causes}")
    reason = ("; ".join(why) + "; ") if why else ""
    return "doubtful", (f"quality doubtful: {figures} ({limits}); {reason}check the plot and the per-exposure errors "
                        "(one bad exposure: leave it out), or record more pixels or exposures")


def assess(images: Sequence[np.ndarray], times: Sequence[float], response: CameraResponse, *,
           method: str | None = None, fit_options: dict | None = None, mask: np.ndarray | None = None,
           seed: int = 0, fit_rms: float | None = None, fitted: bool = False) -> dict[str, Any]:
    """The quality record of ``response`` on the stack: held-out prediction (refitting without each exposure with
    ``method`` when given, else the response as it is), split-half agreement (when ``method`` is given) and the
    verdict (``fit_rms``: the in-sample prediction RMS of the whole stack, see :func:`verdict`). ``fitted``: the
    response was fitted on this stack; without ``method`` the figure is then not called held-out (each exposure is
    left out of the merge but not of the fit: ``--quality fast``). Saved in the response's meta as ``quality``."""
    from radiometry.response.fit import fit_response

    first = np.asarray(images[0])
    n_ch = 3 if first.ndim == 3 and first.shape[2] == 3 else 1
    levels = declared(response, n_ch)
    refit = None
    split = None
    if method is not None:
        options = dict(fit_options or {})
        options.pop("mask", None)
        takes_mask = method in ("auto", "loglog", "debevec", "engel")
        if method in ("loglog", "engel") or (method == "auto" and "samples" not in options
                                              and options.get("lam") != "auto"):
            options.setdefault("pixels", QUALITY_PIXELS)

        def refit(imgs, ts, *, mask=mask):  # noqa: ANN001 - the fit on a part of the data
            return fit_response(imgs, ts, method=method, **({"mask": mask} if takes_mask else {}), **options)

        split_error = "the method takes no mask (OpenCV's)" if not takes_mask else None
        if takes_mask:
            try:
                split = split_half(images, times, refit, levels, mask=mask).tolist()
            except (ValueError, ArithmeticError, RadiomapError) as exc:  # a half too small to fit
                split, split_error = None, str(exc)
    hold = holdout_rms(images, times, response, refit=refit, mask=mask, seed=seed)
    kind = "held-out prediction"
    if fitted and refit is None:
        kind = "prediction of each exposure from the others through the response fitted on all (no refits)"
    texture = (hold["noise_in_images"], hold["noise_between"]) if hold["texture"] else None
    grade, sentence = verdict(hold["rms"], split, hold["ratio"], compressed=hold["compressed"],
                              in_sample=hold["in_sample"], fit_rms=fit_rms, kind=kind, texture=texture)
    tied = tied_share(response)
    if tied > TIED_DOUBTFUL and grade in GRADES:
        worse = worse_grade("broken" if tied > TIED_BROKEN else "doubtful", grade)
        sentence = sentence.replace(f"quality {grade}", f"quality {'BROKEN' if worse == 'broken' else worse}", 1)
        grade = worse
        # the default method (loglog, what "auto" fits) tied none on the real stacks: suggest it only after another
        default = response.meta.get("method") == "loglog"
        sentence += (f"; the fit tied {100 * tied:.0f} % of the levels to keep f^-1 increasing: the data did not "
                     "determine the curve there " + ("" if default else "with this method")
                     + ("; do not use this response" if grade == "broken" and "do not use" not in sentence else "")
                     + (": check the exposure times (two exposures listed at one time, or times that do not match "
                        "the images) and that the exposures overlap; the default method, used here, tied none on "
                        "the real stacks measured" if default else
                        ": fit with the default method (it tied none on the real stacks measured)"))
    found = bends(response, levels)
    if found:       # what the figures above cannot see; on a JPEG stack such a fit was off by more than 0.8 %
        sentence += "; " + bend_text(found, "L" if n_ch == 1 else "RGB")
        if grade == "good" and hold["compressed"]:
            grade = "doubtful"
            sentence = sentence.replace("quality good", "quality doubtful", 1)
    out = {"holdout_rms_levels": hold["rms"], "holdout_per_exposure": hold["per_exposure"],
           "image_noise_levels": None if hold["texture"] else hold["noise"],
           "noise_measured": "between exposures (texture at the pixel scale)" if hold["texture"] else "in the images",
           "laplacian_noise_levels": hold["noise_in_images"], "noise_between_exposures_levels": hold["noise_between"],
           "holdout_over_noise": hold["ratio"], "jpeg": hold["compressed"],
           "holdout_refit": hold["refit"], "prediction": (f"in-sample ({hold['in_sample']})" if hold["in_sample"]
                                                          else "held-out" if kind == "held-out prediction" else
                                                          "from the other exposures, response fitted on all"),
           "holdout_exposures": hold["held_out"], "split_half_percent": split,
           "grade": grade, "summary": sentence, "bends": found,
           "thresholds": {"holdout_over_noise_good": HOLDOUT_GOOD, "holdout_over_noise_broken": HOLDOUT_BROKEN,
                          "split_good": SPLIT_GOOD,
                          "holdout_levels_good": HOLDOUT_ABSOLUTE}}
    if method is not None and split is None:
        out["split_half_error"] = split_error
    return out


__all__ = ["assess", "bends", "bend_text", "holdout_rms", "split_half", "verdict", "declared"]
