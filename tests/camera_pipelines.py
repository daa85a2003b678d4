"""Camera pipelines as real cameras have them, written independently of radiomap's code (issue 28).

Nothing here imports ``radiometry`` or ``mapping``: a fault in the fitting code cannot cancel itself out. JPEG
goes through OpenCV's encoder (libjpeg, 4:2:0 chroma subsampling by default), the codec real files come from.

The pipeline, per exposure ``t`` (:func:`expose`):

1. sensor: ``electrons = Poisson(min(L t, 4) * full_well) + Normal(0, read_noise)``; linear value
   ``x = clip(electrons / full_well, 0, 1)`` (clipping at the full well);
2. white balance on the linear value, after the clip: ``x_c * gain_c``; with a gain below 1 the channel can never
   reach level 255 (gain 0.88 on gamma 2.2: red saturates at level 240, not 255), with a gain above 1 it
   clips again at 1;
3. the response ``f``: the level whose inverse response (a ``(256,)`` table, ``f^-1(255) = 1``) is ``x``,
   interpolated;
4. optional noise after the response, in levels (ISP noise, dithering): saturated pixels then read a spread of
   levels below the ceiling instead of one;
5. rounding to 8 bits; optional JPEG (quality 75..95) through OpenCV in BGR order, decoded back.

``true_inverse`` gives what a fit can be compared with: the table restricted to the levels a channel can reach,
and ``ceiling_level`` the level where a channel saturates (the truth for "declared levels never above a channel's
true saturation").
"""

from __future__ import annotations

import numpy as np

LEVELS = np.arange(256)


def _forward(table: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Levels (float) whose inverse response is ``x`` (piecewise-linear inversion of the table)."""
    return np.interp(x, table, LEVELS.astype(np.float64))


def ceiling_level(table: np.ndarray, gain: float) -> float:
    """The (fractional) level a channel with white-balance ``gain`` applied after the clip saturates at."""
    return float(_forward(np.asarray(table, dtype=np.float64), np.array([min(gain, 1.0)]))[0])


def jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """Encode an RGB uint8 image as JPEG at ``quality`` with OpenCV (4:2:0) and decode it back (RGB)."""
    import cv2

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(image[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    assert ok
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].copy()


def expose(radiance: np.ndarray, t: float, table: np.ndarray, *, rng: np.random.Generator,
           gains=(1.0, 1.0, 1.0), full_well: float = 10000.0, read_noise: float = 3.0,
           post_noise: float = 0.0, quality: int | None = None) -> np.ndarray:
    """One exposure of ``radiance`` (``(H, W, 3)`` relative radiance) through the pipeline above; uint8 RGB."""
    tables = np.asarray(table, dtype=np.float64).reshape(256, -1)
    if tables.shape[1] == 1:
        tables = np.repeat(tables, 3, axis=1)
    electrons = rng.poisson(np.minimum(radiance * t, 4.0) * full_well) + rng.normal(0, read_noise, radiance.shape)
    x = np.clip(electrons / full_well, 0.0, 1.0)
    x = np.minimum(x * np.asarray(gains, dtype=np.float64), 1.0)
    level = np.stack([_forward(tables[:, c], x[..., c]) for c in range(3)], axis=-1)
    if post_noise > 0:
        level = level + rng.normal(0.0, post_noise, level.shape)
    img = np.clip(np.rint(level), 0, 255).astype(np.uint8)
    if quality is not None:
        img = jpeg(img, quality)
    return img


def render(table: np.ndarray, radiance: np.ndarray, times, *, seed: int = 0, **pipeline) -> list[np.ndarray]:
    """The bracket: one :func:`expose` per time (``pipeline``: its keyword options)."""
    rng = np.random.default_rng(seed)
    return [expose(radiance, float(t), table, rng=rng, **pipeline) for t in times]


#: the pipelines of issue 28 (keyword options of :func:`expose`)
PIPELINES = {
    "clean": {},
    "wb-after-clip": {"gains": (0.88, 1.0, 0.95)},
    "wb-jpeg92": {"gains": (0.88, 1.0, 0.95), "quality": 92},
    "jpeg75": {"quality": 75},
    "post-noise": {"post_noise": 1.5},
}


def max_error_scale_free(fitted: np.ndarray, truth: np.ndarray, levels: list[tuple[int, int]]) -> np.ndarray:
    """Largest ``|f^-1 - truth|`` per channel, % of the range (truth is 1 at 255), over each channel's declared
    levels ``levels[c] = (low, high)`` inclusive, after scaling the fit to the truth by least squares in
    ``ln f^-1`` over the declared levels from 32 up (a per-channel scale of ``f^-1`` is a white-balance gain, which
    exposure absorbs: only the shape matters, and a channel that saturates below 255 fixes no value at 255)."""
    fitted = np.asarray(fitted, dtype=np.float64).reshape(256, -1)
    truth = np.asarray(truth, dtype=np.float64).reshape(256, -1)
    if truth.shape[1] == 1:
        truth = np.repeat(truth, fitted.shape[1], axis=1)
    out = []
    for c, (lo, hi) in enumerate(levels):
        sel = slice(max(lo, 32), hi + 1)
        scale = float(np.exp(np.mean(np.log(truth[sel, c]) - np.log(fitted[sel, c]))))
        f = fitted[:, c] * scale
        out.append(100 * float(np.abs(f[lo:hi + 1] - truth[lo:hi + 1, c]).max()))
    return np.array(out)


def paper_light(height: int, width: int, rng: np.random.Generator, *, gradient: float, texture: float) -> np.ndarray:
    """One frame's light on the sheet, ``(H, W)`` around 1, as a camera moved by hand over paper sees it: a linear
    falloff across the image of up to ``+-gradient`` at the edges in a random direction (the sheet's tilt and the
    room's lights change from frame to frame) and the paper's fibre texture, ``texture`` RMS at 2-3 px scale,
    which moves with the sheet and so differs at a pixel from frame to frame."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    angle = rng.uniform(0, 2 * np.pi)
    ramp = ((xx / (width - 1) - 0.5) * np.cos(angle) + (yy / (height - 1) - 0.5) * np.sin(angle)) * 2
    light = 1.0 + gradient * rng.uniform(-1, 1) * ramp
    if texture > 0:
        import cv2

        fibres = cv2.GaussianBlur(rng.standard_normal((height, width)), (0, 0), 1.2)
        light = light * (1.0 + texture * fibres / max(float(fibres.std()), 1e-12))
    return light


def sweep(table: np.ndarray, vignette: np.ndarray, *, frames: int = 64, top_level: float = 225.0, seed: int = 0,
          exposure_jitter: float = 0.0, gradient: float = 0.0, texture: float = 0.0,
          **pipeline) -> list[np.ndarray]:
    """A white-sheet sweep (the sheet placements and desk of ``tests/vignetting_sweeps.py``) through the pipeline
    above: per frame ``radiance * V * exposure``, the exposure multiplied by ``2^u``, ``u`` uniform in
    ``+-exposure_jitter`` stops (auto exposure left on). The base exposure puts the sheet's brightest channel at
    ``top_level`` where ``V = 1`` before white balance. ``gradient``, ``texture``: the light on the sheet varies as
    in a hand-held sweep (:func:`paper_light`); 0 (the default) is a static field: every frame shows the same image
    of the sheet wherever it lies, so JPEG's rounding of it is the same in every frame and does not average out."""
    from vignetting_sweeps import SHEET, _desk, sheet_masks

    rng = np.random.default_rng(seed + 1000)
    light_rng = np.random.default_rng(seed + 2000)
    height, width = vignette.shape[:2]
    tables = np.asarray(table, dtype=np.float64).reshape(256, -1)
    exposure = float(np.interp(top_level, LEVELS.astype(np.float64), tables[:, 0])) / float(SHEET.max())
    desk = _desk(height, width, np.random.default_rng(seed + 7))
    out = []
    for mask in sheet_masks(height, width, frames, seed=seed):
        radiance = np.where(mask[:, :, None], SHEET[None, None, :], desk[:, :, None] * SHEET[None, None, :]) * vignette
        if gradient > 0 or texture > 0:
            radiance = radiance * paper_light(height, width, light_rng, gradient=gradient, texture=texture)[:, :, None]
        t = exposure * 2.0 ** rng.uniform(-exposure_jitter, exposure_jitter)
        out.append(expose(radiance, t, table, rng=rng, **pipeline))
    return out
