"""Is a recorded exposure list (``--exposures FILE``) aligned with the frames? The images' own evidence says.

:func:`mapping.exposure_files.match_exposure_file` gives each frame the row nearest in time. When the list's clock
is off by a frame period or a few (a constant offset that still lands within the window of a neighbouring frame,
rows dropped so that the order slips), every frame silently gets a neighbour's exposure. This module checks the
matched exposures against the images before anything is fused:

- for pairs of selected frames 1 and 4 apart (:data:`BASELINES`), the images give the log exposure ratio
  ``log(k_b / k_a)``: ORB features matched between the frames (at most 320 pixels wide), a homography fitted by
  RANSAC, frame b warped onto frame a, and the median of ``f^-1(I_a) V(x_b) / (f^-1(I_b) V(x_a))`` over the smooth,
  unclipped pixels (:func:`radiometry.exposure.exposure_ratio`, the paper's step 4) -- correspondences, not mean
  brightness (auto exposure keeps the mean brightness steady while the exposure changes);
- the file gives ``log(k_b / k_a)`` from the rows matched to the two frames, and from the rows ``s`` further for
  every shift ``s`` in -3..+3 (and +-4, only to tell a trend from a minimum);
- the *disagreement* of a shift is the mean over pairs of ``min(|image - file|, 0.2)`` (log units, averaged over
  the channels; truncated so that a pair the homography got wrong counts once, not as much as it is wrong).

Verdicts (:class:`AlignmentCheck`), per baseline: ``constant`` (the file's exposures never change by 1 %: the check
cannot tell, nothing is said and no image is read), ``unchecked`` (fewer than :data:`MIN_PAIRS` pairs with
evidence), ``ok``, ``warn`` (a shift of -3..+3 explains the images better: its disagreement at most
:data:`WARN_RATIO` of the alignment's, :data:`WARN_GAIN` lower, and below the file's own mean change) and
``refuse`` (at most :data:`REFUSE_RATIO`, :data:`REFUSE_GAIN` lower and below half the file's mean change). A best
shift of +-4 is a trend (vignetting not given biases the ratios as the camera pans), never a verdict. Consecutive
frames decide; the 4-frame baseline (4 times as sensitive to a slow exposure swing, and to a bias) raises their
verdict one step: warn to refuse when it names the same shift, ok to warn when it alone refuses (:func:`combine`).
``mismatch`` (a warning): no shift helps, yet the file disagrees with the images by at least
:data:`MISMATCH_LEVEL` and twice the images' own mean change (a list of another sequence or frame rate).
``refuse`` stops the run in one line naming the file, the shift in frames and seconds and the fix; ``warn`` and
``mismatch`` are logged and recorded (``exposures.json``'s settings, ``self_calibration.json``, compare's summary).

Measured (``python scripts/study_exposure_alignment.py``, 60 frames per sequence, docs/exposure_alignment.md): real
frames with exposures imposed on purpose (irradiance scaled by a random walk of 12 % steps or a slow swing of
+-0.4 in log, the frames rewritten through a gamma 2.2 response), the list written with the frames' timestamps,
correct, shifted by +1, -1, +2 rows, and with its clock one frame + 0.01 s late.

Disagreement of the correct list (consecutive frames d1(0), the best shifted d1(+-1), 4 apart d4(0)) and verdicts
on the shifted lists (4 per seed, 2 seeds):

    sequence            exposures  correct: d1(0)  d1(+-1)  d4(0)   correct  shifted lists
    kitchen (Kinect)    walk       0.006-0.007  0.096-0.100  0.011-0.012  ok   8 of 8 refused, right shift
    kitchen             swing      0.005-0.006  0.013        0.012        ok   8 of 8 refused, right shift
    office (RealSense)  walk       0.016-0.018  0.100-0.101  0.064-0.066  ok   8 of 8 refused, right shift
    office              swing      0.015-0.017  0.018-0.022  0.063-0.065  ok   3 warned (right shift), 5 not seen
    lampshade           walk       0.021-0.022  0.092-0.095  0.020-0.030  ok   8 of 8 refused, right shift
    lampshade           swing      0.021-0.026  0.020-0.026  0.022-0.028  ok   4 warned (3 right shift), 4 not seen
    room, V not given   walk       0.027-0.030  0.090-0.117  0.133-0.164  ok   8 of 8 refused, right shift
    room, V not given   swing      0.031-0.039  0.032-0.033  0.158        ok   3 warned (wrong shift), 5 not seen

No correct list is warned about (16 of 16 ok), no constant list is checked; every list off by a frame or more is
refused when the exposure changes by ~12 % a frame; a slow swing (at most 8 % a frame) shifted by one frame moves the
consecutive ratios by at most 1.3 %, near the images' noise on the RealSense and the lamp shade: warned about or not
seen. Strong vignetting not given (the room) biases the 4-frame ratios: warnings there may name the wrong shift.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

log = logging.getLogger(__name__)

#: the shifts (rows of the file) tried on each side of the alignment used
MAX_SHIFT = 3
#: fewest frame pairs with image evidence for a verdict
MIN_PAIRS = 6
#: the file's exposures "never change" when their log spread is below this (1 %)
CONSTANT_SPREAD = 0.01
#: a pair's residual counts at most this much (log units)
TRUNCATE = 0.2
#: refuse: a shift's disagreement is at most this fraction of the alignment's, and lower by at least REFUSE_GAIN
REFUSE_RATIO = 0.5
REFUSE_GAIN = 0.01
#: warn: at most this fraction, and lower by at least WARN_GAIN
WARN_RATIO = 0.75
WARN_GAIN = 0.005
#: mismatch (a warning): no shift helps, yet the file's changes disagree with the images' by at least this much
#: and by more than MISMATCH_RATIO times the images' own mean change (a list of another sequence or frame rate)
MISMATCH_LEVEL = 0.03
MISMATCH_RATIO = 2.0
#: most frame pairs measured (spread evenly over the sequence)
MAX_PAIRS = 80
#: frame distances of the pairs compared: 1 (consecutive frames) and 4 (a slow exposure swing shifted by a frame
#: changes a 4-frame ratio about 4 times as much as a consecutive one)
BASELINES = (1, 4)
#: width of the images the evidence is measured on
WIDTH = 320


@dataclass(frozen=True)
class AlignmentCheck:
    """The verdict on a list's alignment: ``disagreement`` by shift (rows of the file), ``shift`` the best one,
    ``seconds`` what that shift is in the file's clock, ``pairs`` the frame pairs with image evidence, ``signal``
    the file's mean exposure change between them (log units; a shift is believed only when it leaves less
    disagreement than that), ``baseline`` the frame distance of the pairs that decided, ``others`` the other
    baselines' disagreements."""

    verdict: str
    pairs: int = 0
    disagreement: dict[int, float] = field(default_factory=dict)
    shift: int = 0
    seconds: float = 0.0
    signal: float = float("nan")
    baseline: int = 1
    flat: float = float("nan")
    others: dict[int, dict[int, float]] = field(default_factory=dict)

    def text(self) -> str:
        if self.verdict == "constant":
            return "not checked: the file's exposures never change"
        if self.verdict == "mismatch":
            return (f"the file's exposure changes do not match the images' (disagreement {self.disagreement[0]:.3f} "
                    f"log units at best; the images' own changes {self.flat:.3f})")
        if self.verdict == "unchecked":
            return f"not checked: {self.pairs} frame pairs with image evidence (needs {MIN_PAIRS})"
        d = self.disagreement
        line = f"disagreement with the images {d[0]:.3f} (log units, {self.pairs} frame pairs {self.baseline} apart)"
        if self.shift:
            line += f", {d[self.shift]:.3f} with the list shifted by {self.shift:+d} row(s) ({self.seconds:+.3f} s)"
        return line

    def to_json(self) -> dict:
        return {"verdict": self.verdict, "pairs": self.pairs, "shift_rows": self.shift,
                "shift_seconds": round(self.seconds, 6),
                "file_change": None if not np.isfinite(self.signal) else round(self.signal, 5),
                "image_change": None if not np.isfinite(self.flat) else round(self.flat, 5),
                "baseline_frames": self.baseline,
                "disagreement": {str(s): round(v, 5) for s, v in sorted(self.disagreement.items())},
                "other_baselines": {str(m): {str(s): round(v, 5) for s, v in sorted(d.items())}
                                    for m, d in self.others.items()},
                "text": self.text()}


def _small(rgb: np.ndarray) -> np.ndarray:
    import cv2

    h, w = rgb.shape[:2]
    if w <= WIDTH:
        return np.ascontiguousarray(rgb)
    return cv2.resize(rgb, (WIDTH, max(8, round(h * WIDTH / w))), interpolation=cv2.INTER_AREA)


def _smooth(gray: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood varies by under 6 levels: a small misregistration does not change them."""
    import cv2

    kernel = np.ones((3, 3), np.uint8)
    return (cv2.dilate(gray, kernel).astype(np.int16) - cv2.erode(gray, kernel)) < 6


def pair_log_ratio(rgb_a: np.ndarray, rgb_b: np.ndarray, response, vmap: np.ndarray | None = None,
                   *, min_pixels: int = 300) -> np.ndarray:
    """``log(k_b / k_a)`` per channel ``(3,)`` of two uint8 RGB images of the same size (already small), from
    pixels registered by a homography of matched ORB features; NaN where the images give no evidence."""
    import cv2

    from radiometry.exposure import exposure_ratio

    nan = np.full(3, np.nan)
    ga, gb = (cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in (rgb_a, rgb_b))
    orb = cv2.ORB_create(nfeatures=1000, fastThreshold=7)
    ka, da = orb.detectAndCompute(ga, None)
    kb, db = orb.detectAndCompute(gb, None)
    if da is None or db is None or len(ka) < 12 or len(kb) < 12:
        return nan
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(da, db)
    if len(matches) < 12:
        return nan
    pa = np.float32([ka[m.queryIdx].pt for m in matches])
    pb = np.float32([kb[m.trainIdx].pt for m in matches])
    H, inliers = cv2.findHomography(pb, pa, cv2.RANSAC, 2.0)
    if H is None or int(inliers.sum()) < 20:
        return nan
    h, w = ga.shape
    warped = cv2.warpPerspective(rgb_b, H, (w, h), flags=cv2.INTER_LINEAR)
    valid = cv2.warpPerspective(np.ones((h, w), np.uint8), H, (w, h), flags=cv2.INTER_NEAREST) > 0
    valid = cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    keep = valid & _smooth(ga) & _smooth(cv2.cvtColor(warped, cv2.COLOR_RGB2GRAY))
    if np.count_nonzero(keep) < min_pixels:
        return nan
    va = vb = None
    if vmap is not None:
        va = vmap[keep]
        vb = cv2.warpPerspective(np.ascontiguousarray(vmap, dtype=np.float32), H, (w, h),
                                 flags=cv2.INTER_LINEAR)
        vb = vb.reshape(h, w, -1)[keep]
    ratio, used = exposure_ratio(rgb_a[keep], warped[keep], va, vb, response, low=12, high=245,
                                 min_count=min_pixels)
    return -np.log(ratio)          # exposure_ratio gives k_a / k_b


def image_log_ratios(dataset, pairs: list[tuple[int, int]], response, vignetting=None) -> np.ndarray:
    """``(P, 3)`` image log ratios ``log(k_b / k_a)`` of the pairs of positions ``(a, b)`` of ``dataset``."""
    import cv2

    cv2.setRNGSeed(0)       # RANSAC: the same verdict on every run
    out = np.full((len(pairs), 3), np.nan)
    cache: dict[int, np.ndarray] = {}
    vmap = None
    for p, (a, b) in enumerate(pairs):
        for i in (a, b):
            if i not in cache:
                cache[i] = _small(np.asarray(dataset[i].rgb))
        if vignetting is not None and vmap is None:
            h, w = cache[a].shape[:2]
            vmap = np.asarray(vignetting.evaluate(h, w), dtype=np.float32)
            vmap = vmap if vmap.ndim == 3 else vmap[:, :, None]
        out[p] = pair_log_ratio(cache[a], cache[b], response, vmap)
        for i in list(cache):
            if i <= a:          # pairs come in the order of a: frames before it are not needed again
                del cache[i]
    return out


def _pairs(n: int, max_pairs: int = MAX_PAIRS) -> list[tuple[int, int]]:
    """Frame pairs ``(a, a + m)`` for every baseline ``m`` of :data:`BASELINES`, at most ``max_pairs`` of each
    (spread evenly), in the order of ``a`` (each frame read once or twice)."""
    out = set()
    for m in BASELINES:
        starts = np.arange(max(n - m, 0))
        if len(starts) > max_pairs:
            starts = np.unique(np.linspace(0, n - 1 - m, max_pairs).round().astype(int))
        out.update((int(a), int(a) + m) for a in starts)
    return sorted(out)


def disagreements(image: np.ndarray, table, pairs: list[tuple[int, int]],
                  max_shift: int = MAX_SHIFT + 1) -> tuple[dict[int, float], dict, int]:
    """``({shift: disagreement}, {shift: seconds, "signal": the file's mean change}, pairs used)``: the image log
    ratios ``(P, 3)`` against the file's with its rows shifted; only pairs every shift can be compared on count
    (the same pairs for all); the signal is the mean of ``min(|file's log ratio|, TRUNCATE)`` as matched."""
    rows, values, stamps = table.rows, table.file_values, table.file_stamps
    n = len(values)
    a = np.array([p[0] for p in pairs])
    b = np.array([p[1] for p in pairs])
    img = image if table.per_channel else np.repeat(np.nanmean(image, axis=1, keepdims=True), 3, axis=1)
    ok = np.all(np.isfinite(img), axis=1) & (rows[a] >= 0) & (rows[b] >= 0)
    for s in (-max_shift, max_shift):
        ok &= (rows[a] + s >= 0) & (rows[b] + s >= 0) & (rows[a] + s < n) & (rows[b] + s < n)
    out, seconds = {}, {}
    logv = np.log(values)
    ra, rb = rows[a[ok]], rows[b[ok]]
    change = np.minimum(np.abs(logv[rb] - logv[ra]), TRUNCATE)
    seconds["signal"] = float(change.mean(axis=1).mean()) if change.size else 0.0
    seconds["flat"] = float(np.minimum(np.abs(img[ok]), TRUNCATE).mean()) if change.size else 0.0
    for s in range(-max_shift, max_shift + 1):
        ra, rb = rows[a[ok]] + s, rows[b[ok]] + s
        res = np.minimum(np.abs(img[ok] - (logv[rb] - logv[ra])), TRUNCATE)
        out[s] = float(res.mean()) if res.size else float("nan")
        base = rows[a[ok]]
        seconds[s] = float(np.median(stamps[base + s] - stamps[base])) if res.size and stamps is not None else 0.0
    return out, seconds, int(np.count_nonzero(ok))


def verdict_of(d: dict[int, float], seconds: dict, pairs: int, *, baseline: int = 1) -> AlignmentCheck:
    """The verdict on the disagreements by shift (module doc); ``seconds["signal"]``: the file's mean change."""
    signal = float(seconds.get("signal", np.inf))
    if pairs < MIN_PAIRS:
        return AlignmentCheck("unchecked", pairs, signal=signal, baseline=baseline)
    best = min(d, key=lambda s: (d[s], abs(s)))
    verdict = "ok"
    if 0 < abs(best) <= MAX_SHIFT:     # a best beyond the shifts tried is a trend (a bias), not a minimum
        if d[best] <= REFUSE_RATIO * d[0] and d[0] - d[best] >= REFUSE_GAIN and d[best] <= REFUSE_RATIO * signal:
            verdict = "refuse"
        elif d[best] <= WARN_RATIO * d[0] and d[0] - d[best] >= WARN_GAIN and d[best] <= signal:
            verdict = "warn"
    flat = float(seconds.get("flat", np.inf))
    if verdict == "ok" and d[0] >= MISMATCH_LEVEL and d[0] > MISMATCH_RATIO * flat:
        return AlignmentCheck("mismatch", pairs, d, 0, 0.0, signal, baseline, flat=flat)
    return AlignmentCheck(verdict, pairs, d, best if verdict != "ok" else 0, seconds[best] if verdict != "ok" else 0.0,
                          signal, baseline, flat=flat)


def check_alignment(dataset, table, response, vignetting=None) -> AlignmentCheck:
    """The verdict on the exposures ``table`` (:class:`mapping.exposure_files.KnownExposures`) gives ``dataset``'s
    frames, from the images themselves (module doc); no image is read when the file's exposures never change."""
    known = table.values[table.known]
    if table.rows is None or len(known) < 2:
        return AlignmentCheck("unchecked")
    logk = np.log(known)
    if float(np.max(logk.max(axis=0) - logk.min(axis=0))) < CONSTANT_SPREAD:
        return AlignmentCheck("constant")
    pairs = _pairs(len(dataset))
    image = image_log_ratios(dataset, pairs, response, vignetting)
    gap = np.array([b - a for a, b in pairs])
    by_baseline = {m: verdict_of(*disagreements(image[gap == m], table, [p for p, g in zip(pairs, gap) if g == m]),
                                 baseline=m) for m in BASELINES}
    return combine(by_baseline)


_SEVERITY = {"unchecked": -1, "ok": 0, "mismatch": 1, "warn": 1, "refuse": 2}


def combine(by_baseline: dict[int, AlignmentCheck]) -> AlignmentCheck:
    """One verdict from the baselines' (module doc): consecutive frames (the first baseline) decide; a longer
    baseline raises their verdict by one step (ok to warn at most, warn to refuse) when it names the same shift (or
    consecutive frames see none and it refuses); the others' disagreements are kept in ``others``."""
    first, *rest = by_baseline.values()
    out = first
    for other in rest:
        if _SEVERITY[other.verdict] <= _SEVERITY[out.verdict] or other.verdict == "unchecked":
            continue
        if out.verdict == "warn" and other.shift == out.shift:
            out = replace(other, verdict="refuse" if other.verdict == "refuse" else out.verdict)
        elif out.verdict in ("ok", "unchecked") and other.verdict == "refuse":
            out = replace(other, verdict="warn")
    others = {m: c.disagreement for m, c in by_baseline.items() if m != out.baseline}
    return replace(out, others=others)


def enforce(check: AlignmentCheck, path) -> None:
    """Stop (:class:`mapping.exposure_files.ExposureFileError`) on ``refuse``, log a warning on ``warn``."""
    from mapping.exposure_files import ExposureFileError

    if check.verdict == "mismatch":
        log.warning("%s: the file's exposure changes do not match the images' (disagreement %.3f log units as "
                    "matched and no better at any shift of -3..+3; the images' own changes average %.3f); check that "
                    "the list belongs to this sequence and its clock and frame rate; used as matched", path,
                    check.disagreement[0], check.flat)
        return
    if check.verdict not in ("refuse", "warn"):
        if check.verdict in ("ok", "unchecked"):
            log.info("%s: %s", path, check.text())
        return
    d, s = check.disagreement, check.shift
    what = (f"{path}: the exposures are off by {s:+d} frame(s) ({check.seconds:+.3f} s in the file's clock): "
            f"shifted so, they agree with the images' exposure changes (disagreement {d[s]:.3f} log units) better "
            f"than as matched ({d[0]:.3f}; {check.pairs} pairs of frames {check.baseline} apart)")
    if check.verdict == "refuse":
        raise ExposureFileError(f"{what}; correct the file's clock offset (or give one row per frame, in order)")
    log.warning("%s; check the file's clock offset (or give one row per frame); used as matched", what)


__all__ = ["AlignmentCheck", "check_alignment", "disagreements", "enforce", "image_log_ratios", "pair_log_ratio",
           "verdict_of"]
