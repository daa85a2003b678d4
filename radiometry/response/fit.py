"""Recover the inverse camera response ``f^-1`` from bracketed exposures.

Methods (one function each, plus the :func:`fit_response` dispatcher):

- ``"debevec"`` (:func:`fit_response_debevec`): Debevec & Malik (SIGGRAPH 1997) on a sparse least-squares
  solve. Per channel, unknowns ``g(z) = ln f^-1(z)`` for z = 0..255 and ``ln E_i`` per sampled pixel;
  data rows ``w(z_ij) (g(z_ij) - ln E_i - ln t_j) = 0``, smoothness rows ``lam' w(z) g''(z) = 0``,
  hat weights ``w(z) = min(z, 255 - z)`` (levels 0 and 255 carry no data), gauge ``g(128) = 0``. Unlike
  Debevec's ``lambda``, ``lam`` is per level of data (``lam' = lam sqrt(observations / 254)``), so it
  keeps its meaning whatever the number of samples. Pixels are sampled stratified over intensity like
  radical does: level by level in the longest exposure until every level has ``samples`` observations,
  then from the shorter exposures for the levels still short (:func:`select_samples`). Levels never
  observed are extrapolated by the smoothness term (linearly in ``g``). The normal equations are
  factorised with the ``ln E`` block eliminated first, so time and memory grow linearly with samples.
  Noise biases any such fit towards the radiances that fill many pixels (errors in the regressor);
  averaging several frames per exposure, as radical does, reduces it.
  ``lam="auto"`` chooses the smoothness weight by cross-validation on held-out pixels
  (:mod:`radiometry.response.smoothness`).
- ``"engel"`` (:func:`radiometry.response.engel.fit_response_engel`): maximum likelihood over all
  (subsampled) pixels without a smoothness prior, alternating closed-form updates of irradiance and response
  as TUM's ``mono_dataset_code`` and radical do. It keeps a knee, but needs exposure ratios that are not all
  equal: with brackets at exactly 2x steps ``f^-1`` is determined only up to a factor periodic in ``ln E``
  (period ``ln 2``) that nothing but noise and quantisation constrain.
- ``"loglog"`` (:func:`radiometry.response.loglog.fit_response_loglog`): Debevec's data term over all (subsampled)
  pixels with a prior on the log-log curvature of ``f^-1`` (zero for every gamma curve), which picks the member of
  the equal-ratio ambiguity closest to real curves and keeps knees. The default (``"auto"``): the most accurate
  over the test set of curves, equal ratios or not (figures in :func:`fit_response_auto`).
- ``"opencv-debevec"``, ``"robertson"``: OpenCV's ``CalibrateDebevec`` / ``CalibrateRobertson``, for
  comparison.

Every method returns a :class:`~radiometry.response.CameraResponse` (``f^-1(255) = 1``) whose ``meta``
records the method, its parameters and fit statistics. Images are uint8 RGB ``(H, W, 3)`` or grayscale
``(H, W)``; times are in seconds. :func:`load_brackets` reads a folder of brackets and its times file;
:func:`merge_radiance` and :func:`prediction_rms` check a response against the images.
"""

from __future__ import annotations

import logging
import math
import os
import time
import unicodedata
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.errors import CalibrationError, DatasetError
from radiometry.registry import Registry
from radiometry.response.debevec import (_LEVELS, DEFAULT_LAMBDA, DEFAULT_SAMPLES, HAT_WEIGHTS, _finish, _solve_debevec_channel,
                                         select_samples)
from radiometry.response.inputs import _as_stack, _check_brightness_order, _check_levels, _check_mask, equal_ratios
from radiometry.response.levels import declared
from radiometry.response.model import LEVELS, CameraResponse

log = logging.getLogger(__name__)

TIMES_FILE_NAMES = ("times.txt", "image_list.txt")


def blue_fill_mask(images: Sequence[np.ndarray], *, tolerance: int = 8, dilate: int = 2) -> np.ndarray:
    """Usable-pixel mask for registered stacks whose borders are filled with pure blue (memorial).

    A pixel is excluded when it is pure blue (R <= tolerance, G <= tolerance, B >= 255 - tolerance) in
    any image; the excluded region is grown by ``dilate`` pixels to drop resampled border blends.
    Returns a boolean ``(H, W)`` array, True = usable.
    """
    arrays = [np.asarray(im) for im in images]
    if not arrays:
        raise ValueError("images must hold at least one RGB image")
    for k, arr in enumerate(arrays):
        if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape != arrays[0].shape:
            raise ValueError(f"images must be RGB (H, W, 3) of one size to find blue fill; images[{k}] has "
                             f"shape {arr.shape}")
    stack = np.stack(arrays)
    if tolerance < 0 or dilate < 0:
        raise ValueError(f"tolerance and dilate must be >= 0, got {tolerance} and {dilate}")
    r, g, b = stack[..., 0], stack[..., 1], stack[..., 2]
    blue = ((r <= tolerance) & (g <= tolerance) & (b >= 255 - tolerance)).any(axis=0)
    if dilate and blue.any():
        from scipy.ndimage import binary_dilation

        blue = binary_dilation(blue, structure=np.ones((3, 3), bool), iterations=int(dilate))
    return ~blue


# --------------------------------------------------------------------------------------------------
# sampling
# --------------------------------------------------------------------------------------------------
# --------------------------------------------------------------------------------------------------
# Debevec & Malik, sparse
# --------------------------------------------------------------------------------------------------
def fit_response_debevec(images: Sequence[np.ndarray], times: Sequence[float], *, lam: float | str = DEFAULT_LAMBDA,
                         samples: int = DEFAULT_SAMPLES, mask: np.ndarray | None = None,
                         levels: tuple[int, int] | str = "auto", edges: bool | str = "auto",
                         seed: int = 0) -> CameraResponse:
    """Debevec & Malik on a sparse least-squares solve (see the module docstring).

    ``lam``: smoothness weight per level of data (> 0), or ``"auto"``: chosen by cross-validation on held-out
    pixels among :data:`radiometry.response.smoothness.LAMBDA_GRID` (``meta["lambda_scores"]`` records every
    candidate's held-out error). ``samples``: target number of observations per
    intensity level. ``mask``: boolean ``(H, W)``, True = usable pixel (see :func:`blue_fill_mask`).
    ``levels``: the valid intensity range (inclusive, like radical's ``--valid-min/--valid-max``):
    observations outside it are ignored, e.g. a black-level floor or a clip below 255; the response is
    still estimated (extrapolated) there; ``"auto"`` (default): per channel from the data, with the saturated
    observations below the cut left out too, and ``edges`` drops the pixels near strong edges
    (:mod:`radiometry.response.levels`, as :func:`radiometry.response.loglog.fit_response_loglog`). ``seed``:
    sampling order. The result is repaired to strictly increasing only if the solve is not (``meta["repaired"]``,
    ``meta["repaired_levels"]``). ``meta``
    also records the sampled pixels and observations per channel, the levels never observed, those outside the
    observed span (``extrapolated_levels``: their values come from the smoothness term alone), ``inverse_stderr``
    (per level and channel, the relative standard error of ``f^-1`` from the fit's covariance, see
    :func:`~radiometry.response.debevec._log_stderr`: noise only, not the prior's bias) and ``fit_rms_levels`` (observed level minus
    ``f(E_i t_j)`` over the samples, 8-bit levels).
    """
    auto = isinstance(lam, str) and lam == "auto"
    if not auto and (isinstance(lam, str) or not (np.isfinite(lam) and lam > 0)):
        raise ValueError(f"lam must be a positive number (smoothness weight, e.g. {DEFAULT_LAMBDA}) or 'auto', "
                         f"got {lam!r}")
    if int(samples) != samples or samples < 1:
        raise ValueError(f"samples must be a positive whole number of observations per level, got {samples}")
    from radiometry.response.levels import _pile, prepare, stalled_observations

    if not isinstance(levels, str):
        levels = _check_levels(levels)
    start = time.perf_counter()
    stack, t = _as_stack(images, times)
    _check_brightness_order(stack, t)
    n_img, h, w, n_ch = stack.shape
    valid = _check_mask(mask, (h, w))
    valid_flat = None if valid is None else valid.ravel()
    channel_levels, valid_flat, level_meta = prepare(stack, t, valid_flat, levels, edges=edges, seed=seed)
    flat = stack.reshape(n_img, h * w, n_ch)
    log_t = np.log(t)
    g = np.empty((LEVELS, n_ch))
    sampled, stalls = [], []
    for c in range(n_ch):
        values = np.ascontiguousarray(flat[:, :, c])
        lo, hi = channel_levels[c]
        idx = select_samples(values, t, samples=int(samples), valid=valid_flat, levels=(lo, hi), seed=seed + c)
        if idx.size == 0:
            raise CalibrationError(f"channel {c}: every pixel is saturated, empty or masked in every image (no "
                                   f"level in {lo}..{hi}); use shorter or longer exposures or check the mask")
        sampled.append(values[:, idx])
        stalls.append(stalled_observations(values[:, idx], t, _pile(level_meta, c)) if levels == "auto" else None)
    scores = None
    if auto:
        from radiometry.response.smoothness import cross_validate_lambda

        lam, scores = cross_validate_lambda(sampled, log_t, (max(lv[0] for lv in channel_levels),
                                                             min(lv[1] for lv in channel_levels)), seed=seed)
    solved = []
    for c, values in enumerate(sampled):
        sol = _solve_debevec_channel(values, log_t, float(lam), channel_levels[c], stderr=True, stalled=stalls[c])
        g[:, c] = sol["g"]
        solved.append(sol)
    unobserved, extrapolated = [], []
    for c, sol in enumerate(solved):
        seen = np.bincount(sol["z"], minlength=LEVELS)
        unobserved.append([int(v) for v in np.flatnonzero(seen[1:255] == 0) + 1])  # includes levels outside lo..hi
        span = np.flatnonzero(seen)
        extrapolated.append([k for k in range(LEVELS) if k < span[0] or k > span[-1]])
        if len(unobserved[-1]) > 16:
            log.warning("channel %d: %d intensity levels were never observed; their values are extrapolated "
                        "by the smoothness term", c, len(unobserved[-1]))
    meta: dict[str, Any] = {
        "method": "debevec", "lambda": float(lam), "samples_per_level": int(samples),
        "levels": levels if isinstance(levels, str) else list(levels),
        "seed": int(seed),
        "images": int(n_img), "times": t.tolist(), "masked": valid is not None,
        "pixels": [int(sol["ln_e"].size) for sol in solved],
        "observations": [int(sol["z"].size) for sol in solved],
        "unobserved_levels": unobserved, "extrapolated_levels": extrapolated,
        "declared_levels": [[int(np.flatnonzero(np.bincount(sol["z"], minlength=LEVELS))[0]),
                             int(np.flatnonzero(np.bincount(sol["z"], minlength=LEVELS))[-1])] for sol in solved],
        **level_meta,
        "inverse_stderr": np.stack([sol["log_stderr"] for sol in solved], axis=1).tolist(),
        "inverse_stderr_source": ("debevec: covariance of the weighted least squares (smoothness rows as a prior; "
                                  "the pixels' noise only: the bias of the smoothness prior, at bends and at the "
                                  "top levels is not in it; radiomap adds the levels' 8-bit width where it "
                                  "states the response's error: radiometry.response.relative_uncertainty)"),
    }
    if scores is not None:
        meta.update({"lambda_selection": "cross-validation", "lambda_scores": scores})
    response = _finish(g, meta)
    # fit residual in 8-bit levels: observed level vs f(E_i t_j) on the sampled pixels
    sq, n = [], 0
    for c, sol in enumerate(solved):
        x = np.exp(sol["ln_e"][sol["pix"]] + log_t[sol["img"]] - g[-1, c])
        pred = np.interp(x, response.inverse_table[:, c], _LEVELS)
        err = pred - sol["z"]
        sq.append(float(np.sum(err ** 2)))
        n += err.size
        response.meta.setdefault("fit_rms_levels_per_channel", []).append(math.sqrt(sq[-1] / err.size))
    response.meta["fit_rms_levels"] = math.sqrt(sum(sq) / n)
    response.meta["fit_seconds"] = time.perf_counter() - start
    return response


# --------------------------------------------------------------------------------------------------
# dispatcher
# --------------------------------------------------------------------------------------------------
def fit_response_auto(images: Sequence[np.ndarray], times: Sequence[float], **kwargs: Any) -> CameraResponse:
    """The log-log fit (:func:`radiometry.response.loglog.fit_response_loglog`), the most accurate over the test set
    of curves (``scripts/bench_calibration.py``, 640x480, max ``|f^-1 - truth|`` over levels 5..250, worst channel:
    at most 0.82 % of the range with exactly 2x brackets and 0.73 % with varied ratios, against Debevec's 1.59 % /
    1.67 % and Engel's 6.15 % / 0.82 %); Debevec & Malik when Debevec's own options are given (``samples``, or
    ``lam="auto"``: its cross-validation). A numeric ``lam`` is refused: it means the smoothness for Debevec
    (default 10) and the prior's weight for loglog (0.1), so name the method. ``meta["chosen_by"]`` says why."""
    kwargs = {k: v for k, v in kwargs.items() if not (k in ("lam", "samples") and v is None)}
    ratio = equal_ratios(np.asarray(times, dtype=np.float64))
    if "samples" in kwargs or kwargs.get("lam") == "auto":
        method, why = "debevec", "auto: Debevec's samples or lambda 'auto' given"
    elif "lam" in kwargs:
        raise ValueError(f"lam={kwargs['lam']!r} with method 'auto' is ambiguous: give method='loglog' (the "
                         "prior's weight, default 0.1) or method='debevec' (the smoothness, default 10), or "
                         "lam='auto' for Debevec with cross-validation")
    elif ratio is not None:
        method, why = "loglog", (f"auto: the log-log fit; every exposure ratio is {ratio:.3g}x, which leaves a "
                                 "factor periodic in ln E that its prior chooses")
    else:
        method, why = "loglog", "auto: the log-log fit"
    response = FITTERS[method](images, times, **kwargs)
    response.meta["chosen_by"] = why
    return response


FITTERS = Registry("method", {
    "auto": fit_response_auto,
    "debevec": fit_response_debevec,
    "engel": "radiometry.response.engel:fit_response_engel",
    "loglog": "radiometry.response.loglog:fit_response_loglog",
    "opencv-debevec": "radiometry.response.opencv:fit_response_opencv_debevec",
    "robertson": "radiometry.response.opencv:fit_response_robertson",
})
#: the method names, in the order the CLI lists them
METHODS = FITTERS.names()


def fit_response(images: Sequence[np.ndarray], times: Sequence[float], *, method: str = "auto",
                 **kwargs: Any) -> CameraResponse:
    """Fit ``f^-1`` with ``method`` in :data:`METHODS` (default ``auto``: :func:`fit_response_auto`); ``kwargs`` go
    to that method's function (keyword-only: a keyword the method does not take is a TypeError naming it)."""
    return FITTERS[method](images, times, **kwargs)


# --------------------------------------------------------------------------------------------------
# checking a response against the images
# --------------------------------------------------------------------------------------------------
def _declared_weights(response: CameraResponse, channels: int) -> np.ndarray:
    """Hat weight per level and channel ``(256, C)``, 0 outside the response's declared levels (else 1..254)."""
    out = np.zeros((LEVELS, channels))
    for c, (lo, hi) in enumerate(declared(response, channels) if response.meta.get("declared_levels")
                                 else [(1, 254)] * channels):
        out[lo:hi + 1, c] = np.maximum(HAT_WEIGHTS[lo:hi + 1], 1.0)
    return out


def merge_radiance(images: Sequence[np.ndarray], times: Sequence[float], response: CameraResponse, *,
                   mask: np.ndarray | None = None) -> np.ndarray:
    """HDR merge: per pixel, the hat-weighted mean of ``ln f^-1(z_j) - ln t_j`` over the exposures.

    Only the levels the response declares constrained count (``meta["declared_levels"]``, else 1..254).
    Returns float32 ``(H, W, C)`` relative radiance; NaN where no exposure has such a level or the mask is False.
    """
    stack, t = _as_stack(images, times)
    n_img, h, w, n_ch = stack.shape
    valid = _check_mask(mask, (h, w))
    tables = response.channel_tables(n_ch).astype(np.float64)
    with np.errstate(divide="ignore"):
        g = np.log(tables)
    g = np.where(np.isfinite(g), g, 0.0)  # level 0 may map to 0; it has weight 0 anyway
    weights = _declared_weights(response, n_ch)
    num = np.zeros((h, w, n_ch))
    den = np.zeros((h, w, n_ch))
    log_t = np.log(t)
    for j in range(n_img):
        z = stack[j]
        wj = np.stack([weights[:, c][z[..., c]] for c in range(n_ch)], axis=-1)
        gz = np.stack([g[:, c][z[..., c]] for c in range(n_ch)], axis=-1)
        num += wj * (gz - log_t[j])
        den += wj
    with np.errstate(invalid="ignore", divide="ignore"):
        radiance = np.exp(num / den)
    radiance[den == 0] = np.nan
    if valid is not None:
        radiance[~valid] = np.nan
    return radiance.astype(np.float32)


def prediction_rms(images: Sequence[np.ndarray], times: Sequence[float], response: CameraResponse, *,
                   mask: np.ndarray | None = None, per_image: bool = False) -> float | list[float]:
    """RMS error (8-bit levels) of predicting every exposure from the merged radiance map.

    Each image is predicted as ``f(E * t_j)`` (``response.forward``, interpolated) from
    :func:`merge_radiance`; the error is taken over unmasked pixels whose observed level is within the
    response's declared levels (1..254 when it declares none: not empty, not saturated). ``per_image=True``
    returns one RMS per image.
    """
    stack, t = _as_stack(images, times)
    radiance = merge_radiance(stack, t, response, mask=mask)
    defined = np.isfinite(radiance)
    sq_sum, count, per = 0.0, 0, []
    weights = _declared_weights(response, stack.shape[3])
    for j in range(stack.shape[0]):
        z = stack[j]
        sel = defined & np.stack([weights[:, c][z[..., c]] > 0 for c in range(stack.shape[3])], axis=-1)
        pred = response.forward(np.where(defined, radiance, 0.0) * np.float32(t[j]))
        err = (pred - z.astype(np.float32))[sel].astype(np.float64)
        sq_sum += float(np.sum(err ** 2))
        count += err.size
        per.append(math.sqrt(float(np.mean(err ** 2))) if err.size else float("nan"))
    if per_image:
        return per
    if count == 0:
        raise CalibrationError("no pixel has an unsaturated, non-empty observation to compare with")
    return math.sqrt(sq_sum / count)


# --------------------------------------------------------------------------------------------------
# bracket folders
# --------------------------------------------------------------------------------------------------
def _parse_seconds(token: str) -> float:
    if "/" in token:
        num, den = token.split("/", 1)
        return float(num) / float(den)
    return float(token)


def read_times_file(path: str | os.PathLike) -> list[tuple[str, float]]:
    """Read ``name seconds [more columns]`` lines (``#`` comments and blank lines ignored).

    ``seconds`` may be a fraction such as ``1/250``. Extra columns (``image_list.txt`` has ``1/t``) are
    ignored. Raises :class:`DatasetError` naming the file and line for anything else.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: no such times file; pass --times FILE with lines 'image_name seconds'")
    from radiometry.textlists import read_list_text  # byte-order marks, CRLF, non-UTF-8 file names

    try:
        text = read_list_text(path)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read the times file ({exc}); it must be a text file") from None
    entries: list[tuple[str, float]] = []
    seen: dict[str, int] = {}
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = _name_and_columns(line)
        if len(parts) < 2:
            raise DatasetError(f"{path}:{lineno}: expected 'image_name seconds', got {raw.strip()!r}")
        name, token = unicodedata.normalize("NFC", parts[0]), parts[1]
        try:
            seconds = _parse_seconds(token)
        except (ValueError, ZeroDivisionError):
            spaced = " a file name with spaces must be quoted ('\"my image.png\" 0.004') or end with a tab;" \
                if any(_is_number(t) for t in parts[2:]) else ""
            raise DatasetError(f"{path}:{lineno}: exposure time {token!r} is not a number of seconds;{spaced} "
                               "write e.g. 'img.png 0.004' or 'img.png 1/250' (comment headers with #)") from None
        if not (math.isfinite(seconds) and seconds > 0):
            raise DatasetError(f"{path}:{lineno}: exposure time must be positive seconds, got {token!r}; write "
                               f"{name}'s exposure time in seconds, e.g. '{name} 0.004' or '{name} 1/250'")
        if name in seen:
            raise DatasetError(f"{path}:{lineno}: {name} is listed twice (first on line {seen[name]}); "
                               "keep one line per image")
        seen[name] = lineno
        entries.append((name, seconds))
    if not entries:
        raise DatasetError(f"{path}: no 'image_name seconds' lines; list every bracket image with its exposure")
    return entries


def _name_and_columns(line: str) -> list[str]:
    """A times file line's name and columns: ``"my image.png" 0.004`` (quoted, double or single), ``my image.png<TAB>
    0.004`` (the name ends at the first tab), else whitespace-separated."""
    if line[0] in "\"'":
        end = line.find(line[0], 1)
        if end > 1:
            return [line[1:end], *line[end + 1:].split()]
    if "\t" in line:
        name, rest = line.split("\t", 1)
        if name.strip() and rest.split() and _is_number(rest.split()[0]):
            return [name.strip(), *rest.split()]
    return line.split()


def _is_number(token: str) -> bool:
    try:
        _parse_seconds(token)
    except (ValueError, ZeroDivisionError):
        return False
    return True


def find_times_file(folder: str | os.PathLike) -> Path:
    """The default times file of a bracket folder: ``times.txt`` or ``image_list.txt``."""
    folder = Path(folder)
    for name in TIMES_FILE_NAMES:
        if (folder / name).is_file():
            return folder / name
    raise DatasetError(f"{folder}: no {' or '.join(TIMES_FILE_NAMES)}; write one with lines "
                       "'image_name seconds' or pass --times FILE")


def own_outputs(folder: str | os.PathLike) -> set[str]:
    """Names of the files in ``folder`` that a radiomap run record there (``crf.json`` of ``radiomap response -o
    folder/crf.npz``, a vignetting ``*_summary.json``) lists as its outputs: not exposures of the bracket."""
    import json

    folder = Path(folder)
    names: set[str] = set()
    for record in folder.glob("*.json"):
        try:
            if record.stat().st_size > 4_000_000:
                continue
            data = json.loads(record.read_text(encoding="utf-8"))
        except (OSError, ValueError, UnicodeDecodeError):
            continue
        if not isinstance(data, dict) or "radiomap_version" not in (data.get("run") or data):
            continue
        for key in ("outputs", "figures"):
            listed = data.get(key)
            for value in (listed.values() if isinstance(listed, dict) else ()):
                if isinstance(value, str):    # written beside the record (its path may be relative to another cwd)
                    names.add(Path(value).name)
        if names:
            names.add(record.name)
    return names


def _is_file(path: Path) -> bool:
    try:
        return path.is_file()
    except OSError:  # a name too long for the file system, or one it cannot represent
        return False


def load_brackets(folder: str | os.PathLike, times_file: str | os.PathLike | None = None, *,
                  progress: bool = True) -> tuple[list[np.ndarray], np.ndarray, list[str]]:
    """Read a bracket folder: ``(images, times, names)`` in the order of the times file.

    Images are RGB uint8 (or grayscale). The times file defaults to ``times.txt`` / ``image_list.txt``
    in the folder. Every listed image must exist and every image in the folder must be listed.
    ``progress``: a progress bar on stderr when it is a terminal (:func:`radiometry.progress.progress_bar`).
    """
    from radiometry.images import list_images, read_rgb
    from radiometry.progress import progress_bar

    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such folder; pass the folder that holds the bracketed images")
    tfile = Path(times_file) if times_file is not None else find_times_file(folder)
    entries = read_times_file(tfile)
    # names compared in Unicode's composed form (NFC): a times file typed on one system and images named on another
    # spell an accented letter differently, and print the same
    own = {unicodedata.normalize("NFC", n) for n in own_outputs(folder)}   # an earlier run's plot is not an exposure
    present = {name: p for p in list_images(folder) if (name := unicodedata.normalize("NFC", p.name)) not in own}
    missing = [name for name, _ in entries if name not in present and not _is_file(folder / name)]
    if missing:
        raise DatasetError(f"{tfile}: lists {', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''} "
                           f"but {folder} has no such image; fix the names or remove those lines")
    listed = {Path(name).name for name, _ in entries}
    unlisted = sorted(set(present) - listed)
    if unlisted:
        more = " ..." if len(unlisted) > 3 else ""
        raise DatasetError(f"{tfile}: does not list {', '.join(unlisted[:3])}{more} found in {folder}; "
                           "add a line 'name seconds' for each or move them out")
    images = [read_rgb(present.get(name, folder / name))
              for name, _ in progress_bar(entries, desc="reading brackets", unit="image", enabled=progress,
                                          leave=False)]
    shapes = {im.shape for im in images}
    if len(shapes) > 1:
        first = images[0].shape
        odd, shape = next((name, im.shape) for (name, _), im in zip(entries, images) if im.shape != first)
        if shape[:2] == first[:2]:  # the same size, grayscale among colour images (or the other way round)
            def kind(s):
                return "colour (3 channels)" if len(s) == 3 else "grayscale (1 channel)"

            raise DatasetError(f"{folder / odd}: {kind(shape)} but {entries[0][0]} is {kind(first)}: channel "
                               "mismatch; save every bracket in the same colour mode")
        raise DatasetError(f"{folder / odd}: shape {shape} differs from {entries[0][0]} {first}; "
                           "all brackets must have the same size")
    times = np.array([s for _, s in entries], dtype=np.float64)
    return images, times, [name for name, _ in entries]


__all__ = ["METHODS", "FITTERS", "DEFAULT_LAMBDA", "DEFAULT_SAMPLES", "HAT_WEIGHTS", "fit_response",
           "fit_response_debevec", "select_samples", "blue_fill_mask",
           "merge_radiance", "prediction_rms", "read_times_file", "find_times_file", "load_brackets", "own_outputs"]
