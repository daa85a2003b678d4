"""Calibration targets: a white sheet on a desk (vignetting) and an HDR chart (response).

The paper scene follows Alexandrov et al.: a white sheet (A4, albedo ~0.85, a faint paper texture)
on a darker desk (albedo ~0.25, mild wood-like texture) under even light (ambient only, so the
radiance of the sheet is the same everywhere up to its texture). The chart is a radiance image with
log-spaced patches covering a wide dynamic range, for bracketed-exposure response calibration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapping.simulation import textures as tx
from mapping.simulation.scene import Face, Lighting, TexturedScene

_STREAM_PAPER_SCENE = 404
_STREAM_CHART = 505
SHEET_HEIGHT = 0.0005   # the sheet lies 0.5 mm above the desk


@dataclass(frozen=True)
class PaperParams:
    """The white-paper scene: sheet size (m), albedos, the paper texture's relative amplitude, the
    (uniform) irradiance, and the desk size (m)."""

    sheet_size: tuple[float, float] = (0.297, 0.210)
    sheet_albedo: float = 0.85
    paper_texture: float = 0.01
    desk_albedo: float = 0.25
    desk_texture: float = 0.08
    irradiance: float = 100.0
    desk_size: tuple[float, float] = (3.0, 3.0)

    def __post_init__(self) -> None:
        if min(self.sheet_size) <= 0 or min(self.desk_size) <= max(self.sheet_size):
            raise ValueError("sheet_size must be positive and smaller than desk_size")
        if not (0.05 <= self.desk_albedo < self.sheet_albedo <= 0.95):
            raise ValueError(f"need 0.05 <= desk_albedo < sheet_albedo <= 0.95, got {self.desk_albedo}, "
                             f"{self.sheet_albedo}")
        if not (0 <= self.paper_texture <= 0.1 and 0 <= self.desk_texture <= 0.5):
            raise ValueError("paper_texture must be within [0, 0.1] and desk_texture within [0, 0.5]")
        if not self.irradiance > 0:
            raise ValueError(f"irradiance must be positive, got {self.irradiance!r}")


class PaperScene(TexturedScene):
    """Desk (face 0) and sheet (face 1), centred at the origin, z up; :attr:`sheet_face` is 1."""

    sheet_face = 1

    def __init__(self, faces, lighting, *, seed: int, params: PaperParams) -> None:
        super().__init__(faces, lighting, name=f"paper-{seed}")
        self.seed = seed
        self.params = params

    @property
    def sheet_corners(self) -> np.ndarray:
        return self.faces[self.sheet_face].corners()

    @property
    def sheet_radiance(self) -> float:
        """Radiance of the sheet without its texture (albedo * E / pi, grey)."""
        return self.params.sheet_albedo * self.params.irradiance / np.pi

    def to_dict(self) -> dict:
        p = self.params
        return {"seed": self.seed, "sheet_size": list(p.sheet_size), "sheet_albedo": p.sheet_albedo,
                "paper_texture": p.paper_texture, "desk_albedo": p.desk_albedo, "desk_texture": p.desk_texture,
                "irradiance": p.irradiance, "desk_size": list(p.desk_size),
                "sheet_corners": self.sheet_corners.tolist(), "sheet_radiance": self.sheet_radiance,
                "lighting": self.lighting.to_dict()}


def make_paper_scene(seed: int = 0, **params) -> PaperScene:
    """A sheet of paper on a desk, deterministic for ``seed`` (see :class:`PaperParams`)."""
    p = PaperParams(**params)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _STREAM_PAPER_SCENE]))
    dw, dh = p.desk_size
    texel_desk = 0.003
    h, w = int(np.ceil(dh / texel_desk)), int(np.ceil(dw / texel_desk))
    grain = tx.fractal_noise(rng, h, w, (40.0, 8.0, 1.5))
    streaks = tx.value_noise(rng, h, max(2, w // 25), 3.0)
    import cv2

    streaks = cv2.resize(streaks, (w, h), interpolation=cv2.INTER_LINEAR)
    desk_colour = p.desk_albedo * np.array([1.12, 0.98, 0.85])
    desk = desk_colour[None, None, :] * (1 + p.desk_texture * (0.6 * grain + 0.8 * streaks))[:, :, None]
    desk = tx.finish(desk)
    sw, sh = p.sheet_size
    texel_sheet = 0.001
    h2, w2 = int(np.ceil(sh / texel_sheet)), int(np.ceil(sw / texel_sheet))
    fibres = tx.fractal_noise(rng, h2, w2, (20.0, 4.0, 1.2))
    sheet = np.full((h2, w2, 3), p.sheet_albedo, np.float32) * (1 + p.paper_texture * fibres)[:, :, None]
    sheet = np.clip(sheet, tx.ALBEDO_MIN, 0.98).astype(np.float32)
    yaw = rng.uniform(-0.3, 0.3)
    c, s = np.cos(yaw), np.sin(yaw)
    ax, ay = np.array([c, s, 0.0]), np.array([-s, c, 0.0])
    faces = [
        Face("desk", [-dw / 2, -dh / 2, 0.0], [1, 0, 0], [0, 1, 0], (dw, dh), desk),
        Face("sheet", np.array([0, 0, SHEET_HEIGHT]) - ax * sw / 2 - ay * sh / 2, ax, ay, (sw, sh), sheet),
    ]
    e = p.irradiance
    return PaperScene(faces, Lighting((e, e, e), 0.0, ()), seed=int(seed), params=p)


def hdr_chart(width: int, height: int, *, seed: int = 0, radiance_range: tuple[float, float] = (1.0, 2000.0),
              rows: int = 6, cols: int = 8) -> np.ndarray:
    """A radiance image float32 ``(H, W, 3)``: ``rows x cols`` patches whose radiances are log-spaced
    over ``radiance_range`` (shuffled), each with a smooth +-35 % gradient and a mild colour tint, on a
    background at the lowest radiance with a slow gradient. Every 8-bit level of every exposure of a
    doubling bracket series over that range is populated."""
    lo, hi = radiance_range
    if not (0 < lo < hi and np.isfinite(hi)):
        raise ValueError(f"radiance_range must be (low, high) with 0 < low < high, got {radiance_range!r}")
    if not (isinstance(width, int) and isinstance(height, int) and width >= cols * 4 and height >= rows * 4):
        raise ValueError(f"width x height must be whole numbers of at least {cols * 4} x {rows * 4}, "
                         f"got {width!r} x {height!r}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _STREAM_CHART]))
    levels = np.exp(np.linspace(np.log(lo), np.log(hi), rows * cols))
    rng.shuffle(levels)
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    img = (lo * (0.6 + 0.4 * xs / width))[:, :, None] * np.ones(3, np.float32)
    ph, pw = height / rows, width / cols
    border = 0.08
    for i in range(rows):
        for j in range(cols):
            y0, y1 = int(round((i + border) * ph)), int(round((i + 1 - border) * ph))
            x0, x1 = int(round((j + border) * pw)), int(round((j + 1 - border) * pw))
            if y1 <= y0 or x1 <= x0:
                continue
            a = rng.uniform(0, 2 * np.pi)
            gx = (xs[y0:y1, x0:x1] - (x0 + x1) / 2) / max(x1 - x0, 1)
            gy = (ys[y0:y1, x0:x1] - (y0 + y1) / 2) / max(y1 - y0, 1)
            grad = 1.0 + 0.7 * (np.cos(a) * gx + np.sin(a) * gy)
            tint = np.clip(1.0 + 0.25 * rng.uniform(-1, 1, 3), 0.6, 1.4).astype(np.float32)
            img[y0:y1, x0:x1] = levels[i * cols + j] * grad[:, :, None] * tint[None, None, :]
    return img.astype(np.float32)
