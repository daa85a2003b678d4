"""Procedural albedo textures: edges and fine detail for tracking, fusion and colour-consistency tests.

Every generator takes a ``numpy.random.Generator`` and a texel grid ``(h, w)`` with the texel size in
metres, and returns float32 ``(h, w, 3)`` RGB albedo within ``[ALBEDO_MIN, ALBEDO_MAX]``. Row 0 is the
top of the surface (highest ``t``), column 0 its left edge (lowest ``s``), as an image is drawn.

Generated images (posters, printed pages, photographs of blobs) are drawn with OpenCV at the texel
resolution and can be pasted into another texture (:func:`paste`) or cover a whole face.

Image textures: :func:`picture` turns a user's 8-bit sRGB picture into albedo on a texel grid (decoded
to linear light with the sRGB transfer function, resampled, then mapped affinely onto the albedo range,
so black is ``ALBEDO_MIN`` and white ``ALBEDO_MAX``); :func:`make_room` pastes them on its walls.
"""

from __future__ import annotations

import string

import numpy as np

from radiometry.response import srgb_to_linear  # noqa: F401 (also this module's name for it)

ALBEDO_MIN = 0.03
ALBEDO_MAX = 0.92


def _cv2():
    import cv2

    return cv2


def finish(tex: np.ndarray) -> np.ndarray:
    """Clip to the physical albedo range and make float32 C-contiguous."""
    return np.ascontiguousarray(np.clip(tex, ALBEDO_MIN, ALBEDO_MAX), dtype=np.float32)


def value_noise(rng: np.random.Generator, h: int, w: int, cell: float) -> np.ndarray:
    """Smooth noise with feature size ``cell`` texels, zero mean, roughly unit range, float32 ``(h, w)``."""
    cv2 = _cv2()
    cell = max(float(cell), 1.0)
    gh, gw = int(np.ceil(h / cell)) + 3, int(np.ceil(w / cell)) + 3
    grid = rng.uniform(-1.0, 1.0, size=(gh, gw)).astype(np.float32)
    big = cv2.resize(grid, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
    oy = int(rng.integers(0, max(1, big.shape[0] - h)))
    ox = int(rng.integers(0, max(1, big.shape[1] - w)))
    return np.ascontiguousarray(big[oy:oy + h, ox:ox + w])


def fractal_noise(rng: np.random.Generator, h: int, w: int, cells: tuple[float, ...],
                  weights: tuple[float, ...] | None = None) -> np.ndarray:
    """A sum of :func:`value_noise` octaves (coarse to fine), float32 ``(h, w)``."""
    weights = weights or tuple(0.6 ** i for i in range(len(cells)))
    out = np.zeros((h, w), dtype=np.float32)
    for c, wt in zip(cells, weights):
        out += np.float32(wt) * value_noise(rng, h, w, c)
    return out / np.float32(sum(weights))


def random_colour(rng: np.random.Generator, lo: float = 0.15, hi: float = 0.8, saturation: float = 0.5) -> np.ndarray:
    """A random RGB albedo: grey level in ``[lo, hi]`` tinted by ``saturation``."""
    grey = rng.uniform(lo, hi)
    tint = rng.uniform(-1.0, 1.0, size=3)
    return np.clip(grey * (1.0 + saturation * tint), ALBEDO_MIN, ALBEDO_MAX)


def _m(texel: float, metres: float) -> float:
    """A length in metres as texels."""
    return metres / texel


# ------------------------------------------------------------------------------------ generators
def paint(rng: np.random.Generator, h: int, w: int, texel: float, colour: np.ndarray,
          variation: float = 0.04) -> np.ndarray:
    """Painted plaster: a colour with a few percent of blotchy and fine noise."""
    n = fractal_noise(rng, h, w, (_m(texel, 0.6), _m(texel, 0.12), _m(texel, 0.02), 1.5))
    return finish(np.asarray(colour, np.float32)[None, None, :] * (1.0 + variation * n)[:, :, None])


def checker(rng: np.random.Generator, h: int, w: int, texel: float, colours: np.ndarray,
            square: float) -> np.ndarray:
    """A checkerboard of two colours with ``square`` metres squares and a little noise."""
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    k = ((np.floor(xs * texel / square) + np.floor(ys * texel / square)) % 2).astype(np.int64)
    base = np.asarray(colours, np.float32)[k]
    n = fractal_noise(rng, h, w, (_m(texel, 0.05), 1.5))
    return finish(base * (1.0 + 0.03 * n)[:, :, None])


def stripes(rng: np.random.Generator, h: int, w: int, texel: float, colours: np.ndarray,
            period: float, angle: float, duty: float = 0.5) -> np.ndarray:
    """Stripes of ``period`` metres at ``angle`` radians, hard edges."""
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    phase = (xs * np.cos(angle) + ys * np.sin(angle)) * texel / period
    k = ((phase - np.floor(phase)) < duty).astype(np.int64)
    base = np.asarray(colours, np.float32)[k]
    n = fractal_noise(rng, h, w, (_m(texel, 0.3), 2.0))
    return finish(base * (1.0 + 0.03 * n)[:, :, None])


def planks(rng: np.random.Generator, h: int, w: int, texel: float, colour: np.ndarray,
           width: float = 0.14, length: float = 1.2) -> np.ndarray:
    """A wooden floor: planks of ``width`` x ``length`` metres (rows along the image width), each with
    its own tint, grain stretched along the plank and dark gaps between them."""
    cv2 = _cv2()
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    row = np.floor(ys * texel / width).astype(np.int64)
    n_rows = int(row.max()) + 1
    offsets = rng.uniform(0, length, size=n_rows).astype(np.float32)
    col = np.floor((xs * texel + offsets[row]) / length).astype(np.int64)
    tints = rng.uniform(0.75, 1.2, size=(n_rows, int(col.max()) + 1)).astype(np.float32)
    tint = tints[row, col]
    grain_small = rng.uniform(-1, 1, size=(max(2, h // 2), max(2, w // 40))).astype(np.float32)
    grain = cv2.resize(grain_small, (w, h), interpolation=cv2.INTER_CUBIC)
    fine = fractal_noise(rng, h, w, (_m(texel, 0.05), 1.5))
    gap_y = ((ys * texel) % width) < max(texel * 1.2, 0.003)
    gap_x = ((xs * texel + offsets[row]) % length) < max(texel * 1.2, 0.003)
    shade = tint * (1.0 + 0.12 * grain + 0.04 * fine)
    shade = np.where(gap_y | gap_x, 0.35, shade)
    return finish(np.asarray(colour, np.float32)[None, None, :] * shade[:, :, None])


def tiles(rng: np.random.Generator, h: int, w: int, texel: float, colour: np.ndarray,
          grout: np.ndarray, size: float = 0.3, joint: float = 0.006) -> np.ndarray:
    """Square tiles of ``size`` metres with ``joint`` metres of grout and a per-tile tint."""
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    ty, tx = np.floor(ys * texel / size).astype(np.int64), np.floor(xs * texel / size).astype(np.int64)
    tint = rng.uniform(0.9, 1.1, size=(int(ty.max()) + 1, int(tx.max()) + 1)).astype(np.float32)[ty, tx]
    speck = fractal_noise(rng, h, w, (_m(texel, 0.08), 1.2))
    base = np.asarray(colour, np.float32)[None, None, :] * (tint * (1.0 + 0.06 * speck))[:, :, None]
    jm = ((xs * texel) % size < joint) | ((ys * texel) % size < joint)
    base[jm] = np.asarray(grout, np.float32)
    return finish(base)


def granite(rng: np.random.Generator, h: int, w: int, texel: float, colour: np.ndarray) -> np.ndarray:
    """Speckled stone/laminate: coloured multi-scale noise with sharp dark and light grains."""
    n = fractal_noise(rng, h, w, (_m(texel, 0.2), _m(texel, 0.04), 1.2))
    grains = rng.random((h, w)).astype(np.float32)
    shade = 1.0 + 0.25 * n
    shade = np.where(grains < 0.04, 0.45, np.where(grains > 0.97, 1.35, shade))
    tint = 1.0 + 0.08 * np.stack([value_noise(rng, h, w, _m(texel, 0.1)) for _ in range(3)], axis=2)
    return finish(np.asarray(colour, np.float32)[None, None, :] * shade[:, :, None] * tint)


def _random_words(rng: np.random.Generator, n: int) -> str:
    letters = string.ascii_letters + string.digits
    return " ".join("".join(rng.choice(list(letters), size=int(rng.integers(2, 9)))) for _ in range(n))


def printed_page(rng: np.random.Generator, h: int, w: int, texel: float, *,
                 paper: float = 0.85, ink: float = 0.08, line_height: float = 0.025) -> np.ndarray:
    """A sheet of text: rows of random words in dark ink on paper (fine, high-contrast detail)."""
    cv2 = _cv2()
    img = np.full((h, w, 3), int(paper * 255), np.uint8)
    lh = max(4, int(round(line_height / texel)))
    scale = max(lh / 30.0, 0.12)
    thick = 1 if lh < 20 else 2
    ink_rgb = tuple(int(v) for v in np.clip(255 * ink * (1 + 0.3 * rng.uniform(-1, 1, 3)), 0, 255))
    margin = max(2, w // 12)
    y = margin + lh
    while y < h - margin // 2:
        words = _random_words(rng, int(rng.integers(3, 14)))
        cv2.putText(img, words, (margin, y), cv2.FONT_HERSHEY_SIMPLEX, scale, ink_rgb, thick, cv2.LINE_AA)
        y += int(lh * rng.uniform(1.4, 1.9))
    return finish(img.astype(np.float32) / 255.0)


def poster(rng: np.random.Generator, h: int, w: int, texel: float) -> np.ndarray:
    """A generated picture: a colour gradient, overlapping discs and rectangles, a title and a
    thin frame; strong edges of every orientation and saturated colours."""
    cv2 = _cv2()
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    c0, c1 = random_colour(rng, 0.2, 0.8, 0.9), random_colour(rng, 0.2, 0.8, 0.9)
    a = rng.uniform(0, np.pi)
    t = (xs * np.cos(a) + ys * np.sin(a))
    t = (t - t.min()) / max(float(np.ptp(t)), 1.0)
    img = ((1 - t)[:, :, None] * c0 + t[:, :, None] * c1) * 255.0
    img = np.ascontiguousarray(img.astype(np.uint8))
    for _ in range(int(rng.integers(4, 10))):
        colour = tuple(int(v) for v in random_colour(rng, 0.1, 0.9, 1.0) * 255)
        if rng.random() < 0.5:
            centre = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            cv2.circle(img, centre, int(rng.uniform(0.05, 0.3) * min(h, w)), colour, -1, cv2.LINE_AA)
        else:
            p0 = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            p1 = (p0[0] + int(rng.uniform(0.1, 0.5) * w), p0[1] + int(rng.uniform(0.05, 0.3) * h))
            cv2.rectangle(img, p0, p1, colour, -1, cv2.LINE_AA)
    lh = max(6, h // 10)
    cv2.putText(img, _random_words(rng, 2).upper(), (max(2, w // 15), h - lh), cv2.FONT_HERSHEY_DUPLEX,
                max(lh / 28.0, 0.2), (245, 245, 240), max(1, lh // 12), cv2.LINE_AA)
    frame = max(1, int(round(0.01 / texel)))
    cv2.rectangle(img, (0, 0), (w - 1, h - 1), (20, 20, 20), frame)
    return finish(img.astype(np.float32) / 255.0)


# 8-bit sRGB code -> linear light in 1/65535 steps: resampling a photograph in uint16 keeps 1.5e-5
# precision at half the memory of float32
_SRGB8_TO_LINEAR16 = np.round(srgb_to_linear(np.arange(256) / 255.0) * 65535.0).astype(np.uint16)


def picture(rgb: np.ndarray, h: int, w: int) -> np.ndarray:
    """An 8-bit sRGB picture (``(H, W, 3)`` RGB or ``(H, W)`` grey uint8) as albedo on an ``(h, w)``
    texel grid, float32 ``(h, w, 3)``.

    The codes are decoded to linear light (:func:`srgb_to_linear`), resampled in linear light
    (``cv2.INTER_AREA``, an area average, when shrinking; bilinear when enlarging, where INTER_AREA
    would repeat pixels) and mapped onto ``[ALBEDO_MIN, ALBEDO_MAX]``: ``ALBEDO_MIN + (ALBEDO_MAX -
    ALBEDO_MIN) * linear``, so that ratios of albedo differences are the picture's."""
    cv2 = _cv2()
    img = np.asarray(rgb)
    if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)) \
            or min(img.shape[:2]) < 1:
        raise ValueError(f"rgb must be uint8 (H, W, 3) or (H, W), got {img.dtype} {img.shape}")
    if not (int(h) >= 1 and int(w) >= 1):
        raise ValueError(f"h and w must be at least 1 texel, got ({h}, {w})")
    h, w = int(h), int(w)
    linear = _SRGB8_TO_LINEAR16[img]
    if linear.ndim == 2:
        linear = np.repeat(linear[:, :, None], 3, axis=2)
    if linear.shape[:2] != (h, w):
        shrink = h <= linear.shape[0] and w <= linear.shape[1]
        linear = cv2.resize(linear, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    albedo = linear.astype(np.float32) * np.float32((ALBEDO_MAX - ALBEDO_MIN) / 65535.0) + np.float32(ALBEDO_MIN)
    return finish(albedo)


def paste(base: np.ndarray, patch: np.ndarray, top: int, left: int) -> np.ndarray:
    """Copy ``patch`` into ``base`` (in place) at row ``top``, column ``left``, cropped to fit."""
    h, w = base.shape[:2]
    ph, pw = patch.shape[:2]
    y0, x0 = max(0, top), max(0, left)
    y1, x1 = min(h, top + ph), min(w, left + pw)
    if y1 > y0 and x1 > x0:
        base[y0:y1, x0:x1] = patch[y0 - top:y1 - top, x0 - left:x1 - left]
    return base


def material(rng: np.random.Generator, h: int, w: int, texel: float, kind: str) -> np.ndarray:
    """A texture of a named kind with random parameters: ``paint``, ``checker``, ``stripes``,
    ``planks``, ``tiles``, ``granite``, ``page``, ``poster``."""
    if kind == "paint":
        return paint(rng, h, w, texel, random_colour(rng, 0.45, 0.85, 0.25))
    if kind == "checker":
        c = random_colour(rng, 0.3, 0.7, 0.6)
        return checker(rng, h, w, texel, np.stack([c * 1.25, c * 0.35]), rng.uniform(0.04, 0.12))
    if kind == "stripes":
        c = random_colour(rng, 0.3, 0.7, 0.7)
        return stripes(rng, h, w, texel, np.stack([c * 1.2, random_colour(rng, 0.1, 0.4, 0.5)]),
                       rng.uniform(0.03, 0.15), rng.uniform(0, np.pi), rng.uniform(0.3, 0.7))
    if kind == "planks":
        return planks(rng, h, w, texel, np.array([0.55, 0.36, 0.2]) * rng.uniform(0.8, 1.2))
    if kind == "tiles":
        return tiles(rng, h, w, texel, random_colour(rng, 0.5, 0.8, 0.2), np.array([0.25, 0.25, 0.24]),
                     rng.choice([0.2, 0.3, 0.4]))
    if kind == "granite":
        return granite(rng, h, w, texel, random_colour(rng, 0.25, 0.6, 0.3))
    if kind == "page":
        return printed_page(rng, h, w, texel)
    if kind == "poster":
        return poster(rng, h, w, texel)
    raise ValueError(f"unknown texture kind {kind!r}; valid names: {', '.join(MATERIALS)}")


MATERIALS = ("paint", "checker", "stripes", "planks", "tiles", "granite", "page", "poster")
