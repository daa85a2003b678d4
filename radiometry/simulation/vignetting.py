"""Vignetting of the simulated camera: per-channel polynomial fields with their own centres, a smooth
non-radial field, a DSO ``vignette.png`` resampled to any size, lensfun's ``pa`` model; named presets.

:class:`VignettingSpec` is resolution independent (centres are fractions of the image size, ``x = cx * W -
0.5``; the radius is normalised by the half-diagonal as in :mod:`radiometry.vignetting` and lensfun) and
renders ``V`` for any image size; :func:`vignetting_preset` names the simulator's fields.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.formats.dso_vignette import read_dso_vignette
from radiometry.simulation._checks import check_size, per_channel
from radiometry.simulation.lensfun import LensfunVignetting


def pixel_grid(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Column and row pixel-centre coordinates, float64 ``(W,)`` and ``(H,)``."""
    return np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64)


def polynomial_for_corner(corner: float) -> tuple[float, float, float]:
    """Coefficients ``(b1, b2, b3)`` of a monotone cos^4-like fall-off that reaches ``corner`` at r = 1."""
    if not 0.05 <= corner <= 1.0:
        raise ValueError(f"corner must be within [0.05, 1] (V at the image corner), got {corner}")
    d = 1.0 - corner
    return (-1.1 * d, 0.15 * d, -0.05 * d)


def polynomial_vignetting(width: int, height: int, coeffs: Any, centres: Any) -> np.ndarray:
    """``1 + b1 r^2 + b2 r^4 + b3 r^6`` per channel, not normalised, float64 ``(H, W, C)``.

    ``coeffs`` is ``(C, 3)``; ``centres`` ``(C, 2)`` fractions of the image size (0.5 = centre).
    """
    b = np.array(coeffs, dtype=np.float64, ndmin=2)
    c = np.array(centres, dtype=np.float64, ndmin=2)
    if b.ndim != 2 or b.shape[1] != 3:
        raise ValueError(f"coeffs must have shape (C, 3), got {np.shape(coeffs)}")
    if c.shape != (b.shape[0], 2):
        raise ValueError(f"centres must have shape ({b.shape[0]}, 2) to match coeffs, got {np.shape(centres)}")
    xs, ys = pixel_grid(width, height)
    radius = 0.5 * math.hypot(width, height)
    out = np.empty((height, width, b.shape[0]), dtype=np.float64)
    for ch in range(b.shape[0]):
        cx, cy = c[ch, 0] * width - 0.5, c[ch, 1] * height - 0.5
        r2 = ((xs[None, :] - cx) ** 2 + (ys[:, None] - cy) ** 2) / radius**2
        out[:, :, ch] = 1.0 + r2 * (b[ch, 0] + r2 * (b[ch, 1] + r2 * b[ch, 2]))
    return out


def nonradial_field(width: int, height: int, terms: Sequence[Sequence[float]]) -> np.ndarray:
    """A smooth multiplicative field ``1 + sum_k a_k cos(pi (fx_k u + px_k)) cos(pi (fy_k v + py_k))``.

    ``u = (x + 0.5) / W`` and ``v = (y + 0.5) / H`` run over (0, 1); each term is ``(a, fx, fy, px,
    py)``. Low orders (``fx, fy`` <= 2) and amplitudes of a few percent give the gentle asymmetric
    shading of a real lens/sensor stack that no radial polynomial can fit. float64 ``(H, W)``.
    """
    u = (np.arange(width, dtype=np.float64) + 0.5) / width
    v = (np.arange(height, dtype=np.float64) + 0.5) / height
    out = np.ones((height, width), dtype=np.float64)
    for term in terms:
        if len(term) != 5:
            raise ValueError(f"a non-radial term is (amplitude, fx, fy, phase_x, phase_y), got {term!r}")
        a, fx, fy, px, py = (float(t) for t in term)
        out += a * np.cos(np.pi * (fy * v + py))[:, None] * np.cos(np.pi * (fx * u + px))[None, :]
    return out


def vignette_map_from_png(path: str | os.PathLike, width: int, height: int) -> np.ndarray:
    """A DSO ``vignette.png`` resampled to ``width x height``: centre-cropped to the target aspect
    ratio first (no stretching), then resized (area for shrinking, bilinear for enlarging); float64
    ``(H, W)`` with maximum 1. The file is read by :func:`radiometry.formats.dso_vignette.read_dso_vignette`."""
    import cv2

    src = np.asarray(read_dso_vignette(path).lut, dtype=np.float64)
    if src.ndim == 3:
        src = src[:, :, 0]
    sh, sw = src.shape
    target = width / height
    if sw / sh > target:  # too wide: crop columns
        cw = max(1, int(round(sh * target)))
        x0 = (sw - cw) // 2
        src = src[:, x0:x0 + cw]
    elif sw / sh < target:
        ch = max(1, int(round(sw / target)))
        y0 = (sh - ch) // 2
        src = src[y0:y0 + ch, :]
    interp = cv2.INTER_AREA if src.shape[1] > width else cv2.INTER_LINEAR
    out = cv2.resize(np.ascontiguousarray(src), (width, height), interpolation=interp).astype(np.float64)
    return out / out.max()


VIGNETTING_KINDS = ("polynomial", "dso", "none")


@dataclass(frozen=True)
class VignettingSpec:
    """Everything that defines a simulated vignetting field; resolution independent.

    kind:      ``polynomial`` (per-channel ``1 + b1 r^2 + b2 r^4 + b3 r^6`` about its own centre),
               ``dso`` (a ``vignette.png`` map, the same for every channel) or ``none``.
    coeffs:    ``(3, 3)`` ``b1, b2, b3`` per RGB channel; ``r`` normalised by the half-diagonal.
    centres:   ``(3, 2)`` optical centre per channel as fractions of (width, height); 0.5 = centre.
    nonradial: terms ``(a, fx, fy, px, py)`` of :func:`nonradial_field`, multiplied onto any kind.
    path:      the ``vignette.png`` for ``kind="dso"``.
    source:    provenance (preset name, lensfun lens, file), informational.

    :meth:`render` gives ``V`` float32 ``(H, W, 3)``, each channel normalised to a maximum of 1.
    """

    kind: str = "polynomial"
    coeffs: tuple = ((0.0, 0.0, 0.0),) * 3
    centres: tuple = ((0.5, 0.5),) * 3
    nonradial: tuple = ()
    path: str | None = None
    source: str = ""

    def __post_init__(self) -> None:
        if self.kind not in VIGNETTING_KINDS:
            raise ValueError(f"vignetting kind must be one of {', '.join(VIGNETTING_KINDS)}, got {self.kind!r}")
        coeffs = np.array(self.coeffs, dtype=np.float64, ndmin=2)
        if coeffs.shape == (1, 3):
            coeffs = np.repeat(coeffs, 3, axis=0)
        if coeffs.shape != (3, 3) or not np.all(np.isfinite(coeffs)):
            raise ValueError(f"coeffs must be 3 finite numbers or (3, 3) per channel, got {self.coeffs!r}")
        centres = np.array(self.centres, dtype=np.float64, ndmin=2)
        if centres.shape == (1, 2):
            centres = np.repeat(centres, 3, axis=0)
        if centres.shape != (3, 2) or not np.all(np.isfinite(centres)):
            raise ValueError(f"centres must be (cx, cy) or (3, 2) per channel, got {self.centres!r}")
        terms = tuple(tuple(float(v) for v in t) for t in self.nonradial)
        for t in terms:
            if len(t) != 5 or not all(np.isfinite(t)):
                raise ValueError(f"a non-radial term is 5 finite numbers (a, fx, fy, px, py), got {t!r}")
        if sum(abs(t[0]) for t in terms) >= 0.5:
            raise ValueError("the non-radial amplitudes must sum to less than 0.5 (a few percent is realistic)")
        if self.kind == "dso" and not self.path:
            raise ValueError("vignetting kind 'dso' needs path=<vignette.png>")
        object.__setattr__(self, "coeffs", tuple(tuple(r) for r in coeffs.tolist()))
        object.__setattr__(self, "centres", tuple(tuple(r) for r in centres.tolist()))
        object.__setattr__(self, "nonradial", terms)
        if self.path is not None:
            object.__setattr__(self, "path", str(self.path))

    def render(self, width: int, height: int) -> np.ndarray:
        """``V`` for a ``width x height`` image: float32 ``(H, W, 3)``, maximum 1 per channel."""
        width, height = check_size(width, height)
        if self.kind == "none":
            base = np.ones((height, width, 3), dtype=np.float64)
        elif self.kind == "dso":
            base = np.repeat(vignette_map_from_png(self.path, width, height)[:, :, None], 3, axis=2)
        else:
            base = polynomial_vignetting(width, height, self.coeffs, self.centres)
        if self.nonradial:
            base = base * nonradial_field(width, height, self.nonradial)[:, :, None]
        low = float(base.min())
        if low <= 0.01:
            raise ValueError(f"these vignetting parameters give V = {low:.3g} <= 0.01 inside the image "
                             f"({self.source or self.kind}); use a milder fall-off")
        base /= base.reshape(-1, 3).max(axis=0)
        return base.astype(np.float32)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "coeffs": [list(r) for r in self.coeffs],
                "centres": [list(r) for r in self.centres], "nonradial": [list(t) for t in self.nonradial],
                "path": self.path, "source": self.source}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "VignettingSpec":
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown vignetting fields {sorted(unknown)}; valid: {sorted(known)}")
        return cls(**dict(data))

    @classmethod
    def polynomial(cls, corner: float | Sequence[float] = 0.5, *, centres: Any = (0.5, 0.5),
                   nonradial: Sequence[Sequence[float]] = (), source: str = "") -> "VignettingSpec":
        """Fall-off to ``corner`` (one value or one per channel) at r = 1 (the corners of a centred
        model) with the shape of :func:`polynomial_for_corner`."""
        corners = per_channel(corner, "corner", 3)
        return cls("polynomial", tuple(polynomial_for_corner(c) for c in corners), centres,
                   tuple(nonradial), None, source)

    @classmethod
    def dso(cls, path: str | os.PathLike, *, nonradial: Sequence[Sequence[float]] = ()) -> "VignettingSpec":
        return cls("dso", path=str(path), nonradial=tuple(nonradial), source=f"DSO {Path(path).name}")

    @classmethod
    def lensfun(cls, entry: LensfunVignetting, *, centres: Any = (0.5, 0.5),
                nonradial: Sequence[Sequence[float]] = ()) -> "VignettingSpec":
        """lensfun's ``pa`` model (``r = 1`` at the half-diagonal, as here), the same for all channels."""
        return cls("polynomial", ((entry.k1, entry.k2, entry.k3),) * 3, centres, tuple(nonradial), None,
                   entry.describe())


def vignetting_preset(name: str) -> VignettingSpec:
    """Named vignetting fields.

    - ``xtion``: strong, like the Asus Xtion of the paper: corners at ~0.5 (R 0.52, G 0.50, B 0.45),
      the blue centre shifted by (+8, +5) pixels at 640 x 480, red/green centres off by ~2 pixels, and
      a non-radial field of ~3 % amplitude.
    - ``asymmetric``: the ``xtion`` fall-off and centres times a strong non-radial field (a horizontally
      elongated fall-off and a diagonal saddle, as mechanical vignetting or a tilted sensor give): the best
      free-centre polynomial misses it by 2.5 % RMS and 7 % at worst (``xtion``: 0.4 % and 1.3 %). The
      demo's camera: the LUT's advantage over the polynomial shows (the paper's point).
    - ``mild``: corners at ~0.8, centred, a 1 % non-radial field.
    - ``none``: ``V = 1``.
    Centres are stored as fractions of the image size, so the spec is resolution independent (the
    shifts are ~1.25 % of the width and ~1 % of the height at any resolution).
    """
    if name in ("xtion", "asymmetric"):
        sx, sy = 1.0 / 640.0, 1.0 / 480.0
        nonradial = ((0.018, 1.0, 0.0, 0.35, 0.0), (0.012, 0.0, 1.0, 0.0, 0.2), (0.010, 1.0, 1.0, 0.1, 0.6),
                     (0.006, 2.0, 1.0, 0.4, 0.3))
        if name == "asymmetric":
            nonradial += ((-0.05, 2.0, 0.0, 0.0, 0.0), (0.04, 1.0, 1.0, 0.0, 0.0))
        return VignettingSpec.polynomial(
            (0.52, 0.50, 0.45),
            centres=((0.5 + 2 * sx, 0.5 - 1 * sy), (0.5 + 1 * sx, 0.5 + 1 * sy), (0.5 + 8 * sx, 0.5 + 5 * sy)),
            nonradial=nonradial, source=f"preset {name}")
    if name == "mild":
        return VignettingSpec.polynomial(0.8, nonradial=((0.006, 1.0, 0.0, 0.3, 0.0), (0.004, 0.0, 1.0, 0.0, 0.25)),
                                         source="preset mild")
    if name == "none":
        return VignettingSpec("none", source="preset none")
    raise ValueError(f"unknown vignetting preset {name!r}; valid names: {', '.join(VIGNETTING_PRESETS)}")


VIGNETTING_PRESETS = ("xtion", "asymmetric", "mild", "none")


__all__ = ["VIGNETTING_KINDS", "VIGNETTING_PRESETS", "VignettingSpec", "nonradial_field", "pixel_grid",
           "polynomial_for_corner", "polynomial_vignetting", "vignette_map_from_png", "vignetting_preset"]
