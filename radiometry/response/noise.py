"""The noise a bracketed stack carries, in levels: the yardstick of the truth-free quality figure.

Two estimates, each blind where the other sees:

- **in one image** (:func:`image_noise`): a robust standard deviation of the 3x3 Laplacian over the declared levels,
  exact for white noise on a locally flat or linear image. Texture at the pixel scale (fine fabric, foliage, gravel,
  a printed random-dot target) is read as noise: on a stack of random pixels with 0.5 levels of noise it reads
  65 levels. Motion between exposures does not reach it.
- **between exposures** (:func:`between_exposure_noise`): the stack is one static scene at several exposure times,
  so texture is the same in every image and noise is not. For an exposure ``k`` and the two exposures ``a``, ``b``
  nearest to it in time, each of ``a``'s levels is mapped to the mean level the same pixels read in ``k`` (the
  brightness transfer function, measured, no response needed), and likewise ``b``'s. The two differences
  ``d_a = z_k - m_a(z_a)`` and ``d_b = z_k - m_b(z_b)`` share only ``k``'s own noise, so their covariance is
  its variance (computed robustly: ``(var(d_a + d_b) - var(d_a - d_b)) / 4`` with MAD variances). Texture cancels
  in both differences; a camera or scene that moved between exposures does not, and is counted as noise.

:func:`stack_noise` uses the Laplacian's figure (what the quality thresholds were set on) unless it is more than
:data:`TEXTURE_RATIO` times the figure between exposures: the images then have texture at the pixel scale, the
Laplacian has not measured their noise, and the figure between exposures is used instead, with a flag that the
verdict turns into a sentence and stricter rules (:mod:`radiometry.response.quality`: good only within 3 levels RMS,
broken only above 10x). The figure between exposures misses errors that neighbouring exposures share: JPEG's (smooth
q75 stacks read 0.68-0.91 against the Laplacian's 1.50-1.99 and a truth of about 1.6), so on a stack called JPEG
texture is not looked for.

Measured (``python scripts/study_image_noise.py``, 2026-11-28; gamma 2.2 through ``tests/camera_pipelines.py``,
320x240, twelve 2x exposures; the truth from a second render with other noise draws; docs/calibration_pipelines.md):

- smooth scene (a log gradient, flat patches), Gaussian noise 0.5 / 1 / 2 levels after the response: truth 0.58 /
  1.03 / 1.99, Laplacian 0.66 / 1.33 / 2.33, between exposures 0.62 / 1.10 / 2.12; photon and read noise: 1.55,
  1.83, 1.57;
- random pixels (radiance log-uniform over 10 stops per pixel), the same noise: truth 0.57 / 1.03 / 1.99, Laplacian
  65.0 / 65.0 / 64.9, between exposures 0.58 / 1.04 / 2.07; photon and read noise: 1.61, 65.0, 1.58;
- the real stacks: taipei Laplacian 2.07, between exposures 2.51; memorial (blue fill masked) 2.55 and 1.81;
- the smooth stack with the camera moved 1-2 px: Laplacian 1.33, between exposures 3.60 (motion counts as noise there,
  which is why the Laplacian's figure is kept where it is not flagged); moved over random pixels: 65.0 and 30.3, both
  inflated (a known limit: the held-out RMS, 40.8 levels, keeps such a stack from being good).

Laplacian over the figure between exposures: smooth synthetic stacks 1.06-1.21 (1.35-1.51 at 160x120, 2.0-2.3 at 80x60,
where the patches' edges are dense: flagged there, harmlessly, the figure between exposures being the more accurate),
the real stacks 0.82 (taipei) and 1.41 (memorial), random pixels 7.6 (JPEG q92) to 112.
"""

from __future__ import annotations

import math

import numpy as np

#: Laplacian figure over the figure between exposures above which the images are taken to have texture at the pixel
#: scale (measured: smooth synthetic stacks 1.06-1.51 from 160x120 up, the real stacks taipei 0.82 and memorial 1.41,
#: random pixels 7.6-112)
TEXTURE_RATIO = 1.6
#: pixels a level of the neighbouring exposure needs to be mapped (fewer: its pixels are left out)
BIN_PIXELS = 20
#: pixels per channel that an exposure and its two neighbours must share for a figure between exposures
MIN_SHARED = 500
#: the least noise an 8-bit level carries (its rounding, 1 / sqrt 12)
ROUNDING = 0.29


def laplacian_noise(stack: np.ndarray, levels: list[tuple[int, int]]) -> np.ndarray:
    """Per exposure of ``stack`` (``(N, H, W, C)``), the mean over channels of a robust standard deviation of the
    3x3 Laplacian (``1.4826 MAD / sqrt 20``) over the declared ``levels``, at least :data:`ROUNDING`; NaN for an
    exposure where no channel has 100 such pixels."""
    import cv2

    out = np.full(stack.shape[0], np.nan)
    for k, img in enumerate(stack):
        per = []
        for c in range(stack.shape[3]):
            z = np.ascontiguousarray(img[:, :, c]).astype(np.float32)
            lap = np.abs(cv2.Laplacian(z, cv2.CV_32F, ksize=1))
            sel = (z >= levels[c][0]) & (z <= levels[c][1])
            if sel.sum() >= 100:
                per.append(1.4826 * float(np.median(lap[sel])) / math.sqrt(20.0))
        if per:
            out[k] = max(float(np.mean(per)), ROUNDING)
    return out


def _rms(values: np.ndarray) -> float:
    values = values[np.isfinite(values)]
    return math.sqrt(float(np.mean(np.square(values)))) if values.size else float("nan")


def image_noise(stack: np.ndarray, levels: list[tuple[int, int]]) -> float:
    """The images' own noise in levels as one image shows it (RMS over exposures of :func:`laplacian_noise`)."""
    return _rms(laplacian_noise(stack, levels))


def _robust_var(x: np.ndarray) -> float:
    return (1.4826 * float(np.median(np.abs(x - np.median(x))))) ** 2


def _mapped(zk: np.ndarray, zj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``zj``'s levels mapped to the mean level their pixels read in ``zk``, and which pixels have a mapping (a
    level of ``zj`` with at least :data:`BIN_PIXELS` pixels)."""
    count = np.bincount(zj, minlength=256)
    total = np.bincount(zj, weights=zk, minlength=256)
    with np.errstate(invalid="ignore", divide="ignore"):
        table = total / count
    return table[zj], count[zj] >= BIN_PIXELS


def between_exposure_noise(flat: np.ndarray, times: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Per exposure of ``flat`` (``(N, P, C)`` levels, exposure times ``times``), the noise in levels measured
    against the two exposures nearest in time (module docstring), mean over channels; NaN where the three share
    fewer than :data:`MIN_SHARED` ``usable`` (``(N, P, C)``) pixels in every channel."""
    n_img, _, n_ch = flat.shape
    log_t = np.log(np.asarray(times, dtype=np.float64))
    out = np.full(n_img, np.nan)
    if n_img < 3:
        return out
    for k in range(n_img):
        order = np.argsort(np.abs(log_t - log_t[k]), kind="stable")
        a, b = [int(j) for j in order if j != k][:2]
        per = []
        for c in range(n_ch):
            sel = usable[k, :, c] & usable[a, :, c] & usable[b, :, c]
            zk = flat[k, sel, c].astype(np.float64)
            if zk.size < MIN_SHARED:
                continue
            m_a, ok_a = _mapped(zk, flat[a, sel, c].astype(np.intp))
            m_b, ok_b = _mapped(zk, flat[b, sel, c].astype(np.intp))
            ok = ok_a & ok_b
            if ok.sum() < MIN_SHARED:
                continue
            d_a, d_b = zk[ok] - m_a[ok], zk[ok] - m_b[ok]
            var = (_robust_var(d_a + d_b) - _robust_var(d_a - d_b)) / 4.0
            per.append(max(math.sqrt(max(var, 0.0)), ROUNDING))
        if per:
            out[k] = float(np.mean(per))
    return out


def stack_noise(stack: np.ndarray, flat: np.ndarray, times: np.ndarray, usable: np.ndarray,
                levels: list[tuple[int, int]], *, compressed: bool = False) -> dict:
    """The noise the quality figure compares with: ``{"noise", "in_images", "between_exposures", "texture"}``.
    ``stack``: ``(N, H, W, C)`` (the Laplacian's); ``flat``, ``usable``: ``(N, P, C)`` over the pixels the prediction
    uses. ``noise`` is ``in_images`` (:func:`image_noise`) unless ``texture`` (the Laplacian read more than
    :data:`TEXTURE_RATIO` times the noise between exposures over the same exposures): then ``between_exposures``.
    ``compressed`` (a JPEG stack, :func:`radiometry.response.levels.blockiness`): texture is not looked for, the
    figure between exposures missing JPEG's error, which neighbouring exposures share (smooth q75 stacks: 0.69-0.91
    between exposures against the Laplacian's 1.50-1.99, and the true EuRoC curve read 11.4x, broken)."""
    lap = laplacian_noise(stack, levels)
    between = between_exposure_noise(flat, times, usable)
    both = np.isfinite(lap) & np.isfinite(between)
    in_images = _rms(lap)
    across = _rms(between[both])
    texture = bool(not compressed and both.any() and _rms(lap[both]) > TEXTURE_RATIO * across)
    return {"noise": across if texture else in_images, "in_images": in_images,
            "between_exposures": across, "texture": texture}


__all__ = ["between_exposure_noise", "image_noise", "laplacian_noise", "stack_noise", "TEXTURE_RATIO"]
