"""White-paper sweeps rendered independently of radiomap's camera code, with a known vignetting and response.

Used by the end-to-end vignetting tests and ``scripts/bench_vignetting.py``. The radiometry is written out here
(nothing from ``radiometry`` touches a pixel): a white sheet of known radiance on a darker textured desk, placed
at random positions, sizes and angles so that over the sweep it covers the whole image; irradiance ``L V(x) t``;
photon (Poisson) and read (Gaussian) noise in electrons; the camera response by inverting a table ``f^-1``
piecewise linearly; 8-bit rounding. The only piece borrowed from the library is the *truth* field of the
``asymmetric`` preset (:func:`vignette_field`), never the rendering.

Vignettes (:func:`vignette_field`), each float64 ``(H, W, 3)`` with maximum 1 per channel:

- ``euroc``: the real measured DSO ``vignette.png`` of the EuRoC MT9V034 (``../shared/data``), area-resampled
  to the sweep's size; the blue channel shifted by (+13, +8) pixels at 376x240 (the shift of a lateral colour
  error; the issue's camera had 26 px at 640x480), so that the channels differ as in a colour camera.
- ``lensfun-tamron`` and ``lensfun-sony``: lensfun's measured ``pa`` model (``1 + k1 r^2 + k2 r^4 + k3 r^6``,
  ``r = 1`` at the half-diagonal) of the Tamron SP 15-30mm at 20 mm f/5.6 (corners 0.49) and the Sony RX10 at
  10.3 mm f/8 (corners 0.60), parsed from ``../shared/data/lensfun/db`` here.
- ``asymmetric``: radiomap's simulator preset (a strong non-radial field).

Curves come from ``tests/response_curves.py`` (the response test set).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from response_curves import SHARED_DATA

EUROC_VIGNETTE = SHARED_DATA / "vignetting" / "euroc_mt9v034_752x480" / "vignette.png"
LENSFUN_DB = SHARED_DATA / "lensfun" / "db"
#: name -> (database file, lens model, focal, aperture, distance)
LENSFUN_PROFILES = {
    "lensfun-tamron": ("slr-tamron.xml", "Tamron SP 15-30mm f/2.8 Di VC USD (A012)", "20", "5.6", "1000"),
    "lensfun-sony": ("compact-sony.xml", "Sony RX10 &amp; compatibles", "10.3", "8", "10"),
}
VIGNETTES = ("euroc", "lensfun-tamron", "lensfun-sony", "asymmetric")
#: the sheet's radiance per channel (a slightly warm white) and the desk's
SHEET = np.array([1.0, 0.96, 0.88])
DESK = 0.22


def shared_available() -> bool:
    return EUROC_VIGNETTE.is_file() and LENSFUN_DB.is_dir()


def default_size(vignette: str, scale: int = 1) -> tuple[int, int]:
    """``(width, height)``: the EuRoC camera's 752x480 halved (376x240), else 320x240; times ``scale``."""
    return (376 * scale, 240 * scale) if vignette == "euroc" else (320 * scale, 240 * scale)


def _normalised(field: np.ndarray) -> np.ndarray:
    return field / field.reshape(-1, field.shape[-1]).max(axis=0)


def _euroc(width: int, height: int) -> np.ndarray:
    import cv2

    raw = cv2.imread(str(EUROC_VIGNETTE), cv2.IMREAD_UNCHANGED)
    assert raw is not None and raw.ndim == 2, f"{EUROC_VIGNETTE}: expected a one-channel 16-bit image"
    src = raw.astype(np.float64) / float(raw.max())
    grey = cv2.resize(src, (width, height), interpolation=cv2.INTER_AREA)
    dx, dy = 13 * width / 376, 8 * height / 240
    shift = np.float64([[1, 0, dx], [0, 1, dy]])
    blue = cv2.warpAffine(grey, shift, (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return _normalised(np.stack([grey, grey, blue], axis=-1))


def lensfun_coefficients(name: str) -> tuple[float, float, float]:
    """``k1, k2, k3`` of a profile in :data:`LENSFUN_PROFILES`, read from the lensfun XML (own parser)."""
    filename, model, focal, aperture, distance = LENSFUN_PROFILES[name]
    text = (LENSFUN_DB / filename).read_text(encoding="utf-8")
    for lens in re.finditer(r"<lens>(.*?)</lens>", text, re.S):
        body = lens.group(1)
        if f"<model>{model}</model>" not in body:
            continue
        entry = re.search(rf'<vignetting model="pa" focal="{re.escape(focal)}" aperture="{re.escape(aperture)}" '
                          rf'distance="{re.escape(distance)}" k1="([^"]+)" k2="([^"]+)" k3="([^"]+)"', body)
        if entry:
            return tuple(float(v) for v in entry.groups())  # type: ignore[return-value]
    raise AssertionError(f"{filename}: no pa entry for {model} at {focal} mm f/{aperture} distance {distance}")


def _lensfun(name: str, width: int, height: int) -> np.ndarray:
    k1, k2, k3 = lensfun_coefficients(name)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    r2 = ((xx - (width - 1) / 2) ** 2 + (yy - (height - 1) / 2) ** 2) / (0.25 * (width ** 2 + height ** 2))
    v = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return _normalised(np.repeat(v[:, :, None], 3, axis=2))


def vignette_field(name: str, width: int, height: int) -> np.ndarray:
    """The true ``V`` of a vignette in :data:`VIGNETTES`, float64 ``(H, W, 3)``, maximum 1 per channel."""
    if name == "euroc":
        return _euroc(width, height)
    if name in LENSFUN_PROFILES:
        return _lensfun(name, width, height)
    if name == "asymmetric":
        from radiometry.simulation.vignetting import vignetting_preset

        return _normalised(vignetting_preset("asymmetric").render(width, height).astype(np.float64))
    raise ValueError(f"unknown vignette {name!r}; valid: {', '.join(VIGNETTES)}")


def _desk(height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """A darker desk with a smooth texture (a few percent), the same in every frame's coordinates."""
    import cv2

    noise = cv2.GaussianBlur(rng.normal(0.0, 1.0, (height, width)), (0, 0), 6.0)
    return DESK * (1.0 + 0.08 * noise / max(noise.std(), 1e-9))


def sheet_masks(height: int, width: int, frames: int, *, seed: int = 0) -> list[np.ndarray]:
    """Where the sheet is in each frame: a rectangle of 45-70 % of the image height, rotated by up to 25
    degrees, its centre on a grid of positions (shuffled, jittered) that covers the whole image and its edges."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    side = int(np.ceil(np.sqrt(frames)))
    grid = [((i + 0.5) / side, (j + 0.5) / side) for i in range(side) for j in range(side)]
    order = rng.permutation(len(grid))[:frames]
    masks = []
    for k in order:
        gx, gy = grid[k]
        cx = (-0.05 + 1.1 * gx + rng.uniform(-0.3, 0.3) / side) * width
        cy = (-0.05 + 1.1 * gy + rng.uniform(-0.3, 0.3) / side) * height
        half_h = 0.5 * rng.uniform(0.45, 0.7) * height
        half_w = half_h * rng.uniform(1.2, 1.5)
        angle = np.deg2rad(rng.uniform(-25, 25))
        u = (xx - cx) * np.cos(angle) + (yy - cy) * np.sin(angle)
        v = -(xx - cx) * np.sin(angle) + (yy - cy) * np.cos(angle)
        masks.append((np.abs(u) <= half_w) & (np.abs(v) <= half_h))
    return masks


def render_sweep(table: np.ndarray, vignette: np.ndarray, *, frames: int = 64, top_level: float = 225.0,
                 seed: int = 0, full_well: float = 10000.0, read_noise: float = 3.0,
                 masks: list[np.ndarray] | None = None) -> list[np.ndarray]:
    """Film a white sheet swept over the image through ``vignette`` (``(H, W, 3)``) and the inverse response
    ``table`` (``(256,)`` or ``(256, 3)``): uint8 RGB frames.

    The exposure puts the sheet's brightest channel at ``top_level`` where ``V = 1`` (irradiance 1 fills
    the well); noise as :func:`response_curves.render_brackets`.
    """
    rng = np.random.default_rng(seed + 1000)
    height, width = vignette.shape[:2]
    tables = np.asarray(table, dtype=np.float64).reshape(256, -1)
    tables = np.repeat(tables, 3, axis=1) if tables.shape[1] == 1 else tables
    exposure = float(np.interp(top_level, np.arange(256.0), tables[:, 0])) / float(SHEET.max())
    desk = _desk(height, width, np.random.default_rng(seed + 7))
    masks = sheet_masks(height, width, frames, seed=seed) if masks is None else masks
    out = []
    for mask in masks:
        radiance = np.where(mask[:, :, None], SHEET[None, None, :], desk[:, :, None] * SHEET[None, None, :])
        x = radiance * vignette * exposure
        electrons = rng.poisson(np.minimum(x, 4.0) * full_well) + rng.normal(0.0, read_noise, x.shape)
        x = np.clip(electrons / full_well, 0.0, 1.0)
        level = np.stack([np.interp(x[..., c], tables[:, c], np.arange(256.0)) for c in range(3)], axis=-1)
        out.append(np.clip(np.rint(level), 0, 255).astype(np.uint8))
    return out


def flat_rms_vs_truth(estimate: np.ndarray, truth: np.ndarray, table: np.ndarray, *, level: float = 200.0,
                      absorb_scale: bool = False) -> np.ndarray:
    """RMS in 8-bit levels, per channel, of a flat field imaged at ``level`` where ``V = 1``, predicted through
    the estimated ``V`` vs through the true one, both through the TRUE response ``table``: ``f(E V_est)`` vs
    ``f(E V_true)``. ``absorb_scale=False`` (the issue's measure): a uniform error of the normalisation counts;
    ``True``: the estimate is first rescaled by the median of ``V_true / V_est``."""
    tables = np.asarray(table, dtype=np.float64).reshape(256, -1)
    tables = np.repeat(tables, truth.shape[2], axis=1) if tables.shape[1] == 1 else tables
    out = np.empty(truth.shape[2])
    for c in range(truth.shape[2]):
        t, e = truth[:, :, c].astype(np.float64), estimate[:, :, c].astype(np.float64)
        a = float(np.median(t / e)) if absorb_scale else 1.0
        base = float(np.interp(level, np.arange(256.0), tables[:, c]))
        obs = np.interp(base * t, tables[:, c], np.arange(256.0))
        pred = np.interp(a * base * e, tables[:, c], np.arange(256.0))
        out[c] = float(np.sqrt(np.mean((pred - obs) ** 2)))
    return out


def bracket_times(seed: int = 5) -> np.ndarray:
    """12 exposure times at 2x steps each moved by 2^u, u uniform in +-0.35 (the response bench's ``varied``)."""
    from response_curves import TIMES

    return TIMES * 2.0 ** np.random.default_rng(seed).uniform(-0.35, 0.35, TIMES.size)
