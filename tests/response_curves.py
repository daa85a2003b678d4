"""A test set of camera response curves and a small bracket renderer, independent of radiomap's own code.

Used by the response tests and by ``scripts/bench_calibration.py``. Nothing here imports ``radiometry``:
the curves, the scene, the noise and the quantisation are written out below, so that a fault in the
simulator or the fitting code cannot cancel itself out.

Curves are inverse responses ``f^-1`` given as 256 relative irradiances per level, strictly increasing,
``f^-1(255) = 1`` (radiomap's normalisation):

- ``gamma-2.2``: ``(z/255)^2.2``.
- ``s-curve``: a toe and a shoulder (slope 1.6 of the mean at both ends, 0.4 in the middle) under a gamma 1.6.
- ``euroc``: the real measured inverse response of the EuRoC MT9V034 (DSO ``pcalib.txt`` in
  ``../shared/data/vignetting/euroc_mt9v034_752x480``), nearly linear with small wiggles; ``None`` when absent.
- ``kink-4x``: linear up to level 180, four times steeper above (a knee: one level above 180 covers four times
  the irradiance of one below).
- ``flat-then-steep``: gamma 1.5 up to 180, steeper to 185, a near-flat stretch 185..200 (slope 0.1 of the
  gamma's), then five times steeper: the shape of the machine-vision pcalib of issue 15.

:func:`render_brackets` exposes a scene through a curve: ``x = L t`` (L relative radiance per channel), photon
(Poisson) and read (Gaussian) noise in electrons, clipping at the full well (saturation), ``f`` by inverting the
table piecewise linearly, 8-bit rounding.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

LEVELS = np.arange(256)
U = LEVELS / 255.0
REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("RADIOMAP_SHARED_DATA", REPO.parent / "shared" / "data"))
EUROC_PCALIB = SHARED_DATA / "vignetting" / "euroc_mt9v034_752x480" / "pcalib.txt"

#: 12 exposures at 2x steps (seconds)
TIMES = 2.0 ** np.arange(-11, 1)


def _from_slopes(slopes: np.ndarray) -> np.ndarray:
    """An inverse response whose step from level z-1 to z is ``slopes[z]`` (z = 1..255), 0 at level 0."""
    table = np.concatenate([[0.0], np.cumsum(slopes[1:])])
    return table / table[-1]


def gamma_curve(gamma: float = 2.2) -> np.ndarray:
    return U ** gamma


def s_curve() -> np.ndarray:
    toe_shoulder = U + 0.6 * np.sin(2 * np.pi * U) / (2 * np.pi)
    return np.clip(toe_shoulder, 0, 1) ** 1.6


def kink_curve(knee: int = 180, factor: float = 4.0) -> np.ndarray:
    slopes = np.where(LEVELS > knee, factor, 1.0)
    return _from_slopes(slopes)


def flat_then_steep_curve() -> np.ndarray:
    base = np.diff(U ** 1.5, prepend=0.0)
    factor = np.select([LEVELS <= 180, LEVELS <= 185, LEVELS <= 200], [1.0, 3.0, 0.1], default=5.0)
    return _from_slopes(base * factor)


def read_pcalib(path: Path) -> np.ndarray:
    """The first 256 numbers of a DSO/TUM ``pcalib.txt``, normalised to 1 at level 255 (own parser)."""
    values = []
    for token in path.read_text().split():
        try:
            values.append(float(token))
        except ValueError:
            break
        if len(values) == 256:
            break
    table = np.asarray(values, dtype=np.float64)
    assert table.size == 256, f"{path}: expected 256 values, got {table.size}"
    table = table - table[0]
    return table / table[-1]


def euroc_curve() -> np.ndarray | None:
    return read_pcalib(EUROC_PCALIB) if EUROC_PCALIB.is_file() else None


def dark_flat_curve() -> np.ndarray:
    """Near-flat (a tenth of the slope) over levels 40..55 of a 1.5 power curve: a flat stretch where an octave
    spans few levels."""
    base = np.diff(U ** 1.5, prepend=0.0)
    return _from_slopes(base * np.where((LEVELS >= 40) & (LEVELS <= 55), 0.1, 1.0))


def srgb_curve() -> np.ndarray:
    """The sRGB decoding (IEC 61966-2-1): linear below level ~10, then a 2.4 power."""
    return np.where(U <= 0.04045, U / 12.92, ((U + 0.055) / 1.055) ** 2.4)


def break_curves() -> dict[str, np.ndarray]:
    """Curves built to break the response fits' priors (not tuned on): knees in the dark octaves, where the
    equal-ratio ambiguity's period spans few levels, a flat dark stretch, a shoulder, a linear and a steep
    gamma curve, sRGB."""
    out = {"dark-kink-4x@60": kink_curve(knee=60, factor=4.0), "dark-flat-40-55": dark_flat_curve(),
           "shoulder-0.25x@200": kink_curve(knee=200, factor=0.25), "mid-kink-3x@120": kink_curve(120, 3.0),
           "linear": U.copy(), "gamma-3": gamma_curve(3.0), "srgb": srgb_curve()}
    for name, table in out.items():
        assert table.shape == (256,) and np.all(np.diff(table) > 0) and table[-1] == 1.0, name
    return out


def curves(include_euroc: bool = True) -> dict[str, np.ndarray]:
    """The test set: name -> ``(256,)`` inverse response (EuRoC only when ../shared/data is present)."""
    out = {"gamma-2.2": gamma_curve(2.2), "s-curve": s_curve(), "kink-4x": kink_curve(),
           "flat-then-steep": flat_then_steep_curve()}
    if include_euroc:
        euroc = euroc_curve()
        if euroc is not None:
            out["euroc"] = euroc
    for name, table in out.items():
        assert table.shape == (256,) and np.all(np.diff(table) > 0) and table[-1] == 1.0, name
    return out


def scene(height: int, width: int, *, seed: int = 0, channels: int = 3) -> np.ndarray:
    """Relative radiance ``(H, W, C)``: a horizontal log gradient over 16 stops, a vertical ramp, 80 flat
    patches spread over the same range, and one light source that saturates every exposure."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width]
    lo, hi = np.log(2.0 ** -5), np.log(2.0 ** 11)
    base = np.exp(lo + (hi - lo) * xx / (width - 1)) * (0.7 + 0.3 * yy / max(height - 1, 1))
    radiance = base[..., None] * np.array([1.0, 0.8, 0.6])[:channels]
    size = max(4, min(height, width) // 10)
    for _ in range(80):
        y0, x0 = rng.integers(0, height - size), rng.integers(0, width - size)
        radiance[y0:y0 + size, x0:x0 + size] = np.exp(rng.uniform(lo, hi, channels))
    radiance[:size, :size] = 2.0 ** 14  # a lamp: 255 in every exposure
    return radiance


def render_brackets(table: np.ndarray, radiance: np.ndarray, times: np.ndarray = TIMES, *, seed: int = 0,
                    full_well: float = 10000.0, read_noise: float = 3.0) -> list[np.ndarray]:
    """Expose ``radiance`` for each time through the inverse response ``table`` (``(256,)`` or ``(256, C)``).

    Irradiance 1 fills the well (level 255 from there up). Returns uint8 ``(H, W, C)`` images, or ``(H, W)``
    for one channel.
    """
    rng = np.random.default_rng(seed)
    channels = radiance.shape[-1]
    tables = np.asarray(table, dtype=np.float64).reshape(256, -1)
    tables = np.repeat(tables, channels, axis=1) if tables.shape[1] == 1 else tables
    images = []
    for t in times:
        electrons = rng.poisson(np.minimum(radiance * t, 4.0) * full_well) + rng.normal(0, read_noise,
                                                                                       radiance.shape)
        x = np.clip(electrons / full_well, 0.0, 1.0)
        level = np.stack([np.interp(x[..., c], tables[:, c], LEVELS) for c in range(channels)], axis=-1)
        img = np.clip(np.rint(level), 0, 255).astype(np.uint8)
        images.append(img[..., 0] if channels == 1 else img)
    return images


def gamma_stack(times, shape=(48, 64), seed=0, *, darkest: float = -4.0) -> list[np.ndarray]:
    """A small gamma-2.2 bracket, uint8 RGB: radiance log-uniform over ``exp(darkest)..1`` per value, 0.5 levels of
    noise after the response (the short-stack and times-order tests)."""
    rng = np.random.default_rng(seed)
    radiance = np.exp(rng.uniform(darkest, 0.0, tuple(shape) + (3,)))
    return [np.clip(np.round(255 * np.clip(radiance * t, 0, 1) ** (1 / 2.2) + rng.normal(0, 0.5, radiance.shape)),
                    0, 255).astype(np.uint8) for t in times]


def max_error_percent(fitted: np.ndarray, truth: np.ndarray, levels: tuple[int, int] = (5, 250)) -> np.ndarray:
    """Largest ``|f^-1 - truth|`` over ``levels`` (inclusive), % of the range, per channel (both 1 at 255)."""
    fitted = np.asarray(fitted, dtype=np.float64).reshape(256, -1)
    truth = np.asarray(truth, dtype=np.float64).reshape(256, -1)
    sel = slice(levels[0], levels[1] + 1)
    return 100 * np.abs(fitted[sel] - truth[sel]).max(axis=0)
