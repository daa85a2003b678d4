"""Calibration and correction in one call each: what ``radiomap response``, ``radiomap vignetting`` and
``radiomap correct`` do, for Python.

>>> import radiometry                                                                      # doctest: +SKIP
>>> response = radiometry.calibrate_response("data_samples/brackets")      # folder with times.txt
>>> vignetting = radiometry.calibrate_vignetting("paper_seq/rgb", response)       # white-paper sweep, LUT
>>> corrected = radiometry.correct("frame.png", response, vignetting)             # uint8 RGB

Models may be given as objects or as files (radiomap ``.npz``, radical ``.crf``/``.vgn``, DSO
``pcalib.txt``/``vignette.png``). Keyword names are the commands' long option names with underscores
(``--min-samples`` -> ``min_samples``; a ``--no-x`` flag is ``x=False``). Nothing here writes files: save a
model with its ``save(path)``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.errors import CalibrationError, CalibrationFileError, DatasetError
from radiometry.response import CameraResponse

log = logging.getLogger(__name__)

PathLike = str | os.PathLike


def as_response(response: CameraResponse | PathLike) -> CameraResponse:
    """A :class:`CameraResponse` given as itself or as a file (``.npz``, ``.crf``, ``pcalib.txt``)."""
    if isinstance(response, CameraResponse):
        return response
    if isinstance(response, (str, os.PathLike)):
        from radiometry.formats import load_response

        return load_response(response)
    raise TypeError(f"response must be a CameraResponse or the path of a response file, got "
                    f"{type(response).__name__}")


def as_vignetting(vignetting):
    """A vignetting model given as itself, as an array V (H, W[, C]) (a LUT) or as a file
    (:func:`read_vignetting`); None stays None."""
    from radiometry.vignetting import LUTVignetting, VignettingModel

    if vignetting is None or isinstance(vignetting, VignettingModel):
        return vignetting
    if isinstance(vignetting, np.ndarray):
        return LUTVignetting(vignetting, info={"source": "array"})
    if isinstance(vignetting, (str, os.PathLike)):
        return read_vignetting(vignetting)
    raise TypeError(f"vignetting must be a VignettingModel, an array V (H, W[, C]) or the path of a model file, "
                    f"got {type(vignetting).__name__}")


def read_vignetting(path: PathLike):
    """A vignetting model file: radiomap ``.npz``, radical ``.vgn`` and DSO ``vignette.png`` through
    :func:`radiometry.formats.load_vignetting`, or a ``.npy`` array V (H, W[, C]) such as a simulator's
    ``truth/vignetting.npy`` (taken as a LUT). The one reader behind every ``--vignetting`` option."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        from radiometry.arrays import load_array_file
        from radiometry.vignetting import LUTVignetting

        fix = "pass a float (H, W[, C]) .npy with finite V > 0"
        array = load_array_file(path, fix=fix)  # refuses complex, object, text and structured arrays
        try:
            return LUTVignetting(array, info={"source": str(path)})
        except (ValueError, TypeError) as exc:
            raise CalibrationFileError(f"{path}: not a usable vignetting array ({exc}); {fix}") from None
    from radiometry.formats import load_vignetting

    return load_vignetting(path)


def calibrate_response(brackets: PathLike | Sequence[np.ndarray], times: PathLike | Sequence[float] | None = None, *,
                       method: str = "auto", progress: bool = True, quality: str = "full",
                       **options: Any) -> CameraResponse:
    """The inverse response ``f^-1`` from bracketed exposures of a static scene (``radiomap response``).

    brackets: a folder of images with its times file (``times.txt`` / ``image_list.txt``, lines
              ``name seconds``), or a list of RGB uint8 images.
    times:    with a folder, another times file (default: the folder's); with images, their exposure times
              in seconds (required).
    method:   ``auto`` (the log-log fit; Debevec with ``samples`` or ``lam="auto"``; the default), ``loglog``,
              ``debevec`` (sparse Debevec & Malik), ``engel``, ``opencv-debevec`` or ``robertson``.
    quality:  the truth-free quality figure (:mod:`radiometry.response.quality`, in ``meta["quality"]``):
              ``"full"`` (each exposure predicted by a fit without it, and two fits on disjoint pixel halves),
              ``"fast"`` (each exposure predicted through this response, no refits) or ``"none"``.
    options:  the method's keywords (``lam``, ``samples``, ``mask``, ...; see
              :func:`radiometry.response.fit.fit_response`).

    The fit's prediction error over every unsaturated pixel is in ``response.meta["prediction_rms_levels"]``;
    a value above 10 levels is logged as a warning (motion, wrong times, auto exposure).
    """
    from radiometry.response.fit import fit_response, load_brackets, prediction_rms

    if isinstance(brackets, (str, os.PathLike)):
        folder = Path(brackets)
        images, stack_times, _ = load_brackets(folder, times, progress=progress)
        where = f"{folder}: "
    else:
        if times is None or isinstance(times, (str, os.PathLike)):
            raise ValueError("times must be the images' exposure times in seconds (one per image) when brackets "
                             "is a list of images; or pass the folder that holds them and their times file")
        images, stack_times, where = list(brackets), np.asarray(times, dtype=np.float64), ""
    try:
        response = fit_response(images, stack_times, method=method, **options)
        rms = prediction_rms(images, stack_times, response, mask=options.get("mask"))
    except ValueError as exc:
        if not where:
            raise
        raise DatasetError(f"{where}{exc}") from None
    except CalibrationError as exc:
        if not where:  # images given: the caller knows where they came from (mapping/cli/response.py)
            raise
        from radiometry.images import with_sixteen_bit_note

        # a folder: too few levels may be the reduction of its 16-bit images to 8 bits
        message = with_sixteen_bit_note(exc, [p for p in sorted(folder.iterdir()) if p.is_file()])
        raise CalibrationError(f"{where}{message}") from None
    response.meta["prediction_rms_levels"] = rms
    if quality not in ("full", "fast", "none"):
        raise ValueError(f"quality must be 'full', 'fast' or 'none', got {quality!r}")
    if quality != "none":
        from radiometry.response.quality import assess

        response.meta["quality"] = assess(images, stack_times, response, mask=options.get("mask"),
                                          method=method if quality == "full" else None,
                                          fit_options={k: v for k, v in options.items() if k != "mask"},
                                          fit_rms=rms, fitted=True)
        if response.meta["quality"]["grade"] != "good":
            log.warning("%s%s", where, response.meta["quality"]["summary"])
    from radiometry.response.quality import FIT_RMS_WARNING

    if not np.isfinite(rms) or rms > FIT_RMS_WARNING:
        log.warning("%sthe response predicts the images with an RMS error of %.1f levels: motion, misregistration, "
                    "wrong exposure times or auto exposure/white balance?", where, rms)
    return response


def calibrate_vignetting(frames: Any, response: CameraResponse | PathLike, *, model: str = "lut",
                         min_samples: int = 20, stop_when_covered: bool = False, max_frames: int | None = None,
                         drift_correction: bool = True, smooth_sigma: float | None = None, progress: bool = True):
    """A vignetting model from a white-paper sweep (``radiomap vignetting``); returns the model.

    frames:   a folder of frames, a video file, a camera index, a list of image paths or of RGB arrays.
    response: the camera response (object or file).
    model:    ``lut`` (per pixel), ``poly`` (free centre) or ``poly-fixed-center``.
    min_samples, stop_when_covered, max_frames: as the command's options; coverage below ``min_samples``
              somewhere in the image is logged as a warning with the thin regions.
    drift_correction: estimate per-frame brightness drift (False: plain average, as radical).
    smooth_sigma: LUT only, the Gaussian (pixels) denoising the residual to the radial fit (default 1; 0 off).
    """
    from radiometry.registry import validate_name
    from radiometry.vignetting_calibration import MODELS, collect_vignetting, fit_vignetting

    validate_name(model, MODELS, "model")  # before the sweep is read
    if smooth_sigma is not None and model != "lut":
        raise ValueError(f"smooth_sigma applies to model='lut' only, got model={model!r}; drop smooth_sigma")
    response = as_response(response)
    acc = collect_vignetting(frames, response, min_samples=min_samples, stop_when_covered=stop_when_covered,
                             max_frames=max_frames, progress=progress)
    options: dict[str, Any] = {"joint_scale": bool(drift_correction)}
    if smooth_sigma is not None:
        options["smooth_sigma"] = smooth_sigma
    if model == "lut":
        options["thin_samples"] = min_samples  # the error budget's "coverage": as the command counts it
    fitted = fit_vignetting(acc, model=model, **options)
    report = acc.coverage_report(min_samples)
    if not report.complete:
        log.warning("vignetting: %s", report)
    return fitted


def correct(image: np.ndarray | PathLike, response: CameraResponse | PathLike, vignetting=None, *,
            scale: float = 1.0, irradiance: bool = False) -> np.ndarray:
    """Remove vignetting (through the response) from one image (``radiomap correct``).

    image:      RGB uint8 (H, W, 3) or (H, W), or an image file.
    response, vignetting: objects or files; vignetting None corrects nothing but the response
                (``irradiance=True`` then gives ``f^-1(I)``).
    scale:      brightness factor of the uint8 result (< 1 keeps bright corners from clipping).
    irradiance: return float32 irradiance ``f^-1(I) / V`` instead of ``f(scale f^-1(I) / V)`` as uint8.

    For many frames build one :class:`radiometry.correction.Corrector` and call it per frame (its tables
    are made once).
    """
    from radiometry.correction import Corrector

    if isinstance(image, (str, os.PathLike)):
        from radiometry.images import read_rgb

        image = read_rgb(image)
    corrector = Corrector(as_response(response), as_vignetting(vignetting))
    if irradiance:
        return corrector.irradiance(image)
    return corrector.correct(image, scale=scale)


__all__ = ["as_response", "as_vignetting", "calibrate_response", "calibrate_vignetting", "correct", "read_vignetting"]
