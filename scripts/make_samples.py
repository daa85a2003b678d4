#!/usr/bin/env python3
"""Regenerate the embedded sample data in ``data_samples/`` (deterministic, NumPy only).

``data_samples/brackets/``: five 8-bit exposures (160 x 120, RGB PNG) of a synthetic high-dynamic-range
scene - a smooth radiance gradient spanning 12 stops plus a chart of 24 coloured patches - rendered
through a known per-channel camera response with photon and read noise and 8-bit quantisation, plus
``times.txt`` (exposure times in seconds) and ``ground_truth_response.npz`` (the true ``f^-1``, radiomap
format) so that a calibration of the sample can be checked.

    python scripts/make_samples.py            # rewrite data_samples/
    python scripts/make_samples.py --check    # exit 1 if data_samples/ differs from what it would write
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from a checkout
    sys.path.insert(0, str(REPO))

SEED = 20240607
WIDTH, HEIGHT = 160, 120
TIMES = (0.001, 0.004, 0.016, 0.064, 0.256)  # seconds, two stops apart
FULL_WELL = 40000.0  # electrons at saturation: photon noise
READ_NOISE = 4.0  # electrons RMS
GAMMAS = (2.0, 2.2, 2.4)  # R, G, B
S_AMOUNT = 0.35  # strength of the toe/shoulder


def true_inverse(u: np.ndarray, channel: int) -> np.ndarray:
    """The sample camera's ``f^-1`` on normalised intensity u in [0, 1] (f^-1(1) = 1).

    An S-shaped film-like curve (toe and shoulder) raised to a per-channel gamma: strictly increasing,
    ``(u + a sin(2 pi u) / (2 pi)) ** gamma_c``.
    """
    v = u + S_AMOUNT * np.sin(2 * np.pi * u) / (2 * np.pi)
    return np.clip(v, 0.0, 1.0) ** GAMMAS[channel]


def true_table() -> np.ndarray:
    """The true inverse response as a ``(256, 3)`` table."""
    u = np.arange(256) / 255.0
    return np.stack([true_inverse(u, c) for c in range(3)], axis=1)


def scene_radiance() -> np.ndarray:
    """Scene radiance ``(H, W, 3)``; an exposure saturates where radiance * time >= 1."""
    rng = np.random.default_rng(SEED)
    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    # smooth background: 12 stops left to right, a gentle vertical ramp and a colour cast
    stops = -9.0 + 12.0 * xx / (WIDTH - 1)
    base = np.exp2(stops) * (0.7 + 0.3 * yy / (HEIGHT - 1))
    cast = np.stack([1.0 + 0.15 * np.sin(yy / 17.0), np.ones_like(yy), 0.85 + 0.15 * np.cos(xx / 23.0)], axis=-1)
    radiance = base[..., None] * cast
    # a 6 x 4 chart of patches from 2^-9 to 2^3, random hues (in the lower 2/3 of the image)
    levels = np.linspace(-9.0, 3.0, 24)
    rng.shuffle(levels)
    ph, pw, top = 16, 20, 44
    for k, lv in enumerate(levels):
        r, c = divmod(k, 6)
        y0, x0 = top + r * (ph + 3), 8 + c * (pw + 5)
        hue = rng.uniform(0.35, 1.0, 3)
        radiance[y0:y0 + ph, x0:x0 + pw] = np.exp2(lv) * hue / hue.max()
    # the brightest radiance (2^3) reaches half the saturation of the shortest exposure
    return radiance * (0.5 / TIMES[0] / 8.0)


def render(radiance: np.ndarray) -> list[np.ndarray]:
    """Expose, add photon and read noise, apply the camera response and quantise to 8 bits."""
    rng = np.random.default_rng(SEED + 1)
    grid_u = np.linspace(0.0, 1.0, 8193)
    grids = [true_inverse(grid_u, c) for c in range(3)]
    images = []
    for t in TIMES:
        electrons = rng.poisson(np.clip(radiance * t, 0.0, 4.0) * FULL_WELL).astype(np.float64)
        electrons += rng.normal(0.0, READ_NOISE, electrons.shape)
        exposure = np.clip(electrons / FULL_WELL, 0.0, 1.0)
        u = np.stack([np.interp(exposure[..., c], grids[c], grid_u) for c in range(3)], axis=-1)
        images.append(np.clip(np.rint(255.0 * u), 0, 255).astype(np.uint8))
    return images


def brackets() -> tuple[list[np.ndarray], list[str]]:
    images = render(scene_radiance())
    return images, [f"exposure_{k}.png" for k in range(len(images))]


def times_text(names: list[str]) -> str:
    lines = ["# radiomap sample brackets (scripts/make_samples.py): image  exposure time [s]"]
    lines += [f"{name} {t:g}" for name, t in zip(names, TIMES)]
    return "\n".join(lines) + "\n"


README = """\
# Sample brackets (synthetic, made by `scripts/make_samples.py`)

Five exposures (`times.txt`, seconds, two stops apart) of a synthetic high-dynamic-range scene - a smooth
radiance gradient over 12 stops and a chart of 24 coloured patches - rendered through a known S-shaped,
per-channel camera response (gamma 2.0 / 2.2 / 2.4 for R / G / B) with photon noise (40000 e- full well),
read noise (4 e-) and 8-bit quantisation. `ground_truth_response.npz` is the true inverse response
(`radiometry.CameraResponse.load`). Regenerate with `python scripts/make_samples.py`.

    radiomap response data_samples/brackets -o out/crf.npz
"""


def write(out: Path) -> None:
    from radiometry.fileio import atomic_write_text, ensure_dir
    from radiometry.images import write_image
    from radiometry.response import CameraResponse

    folder = ensure_dir(out / "brackets")
    images, names = brackets()
    for name, image in zip(names, images):
        write_image(folder / name, image)
    atomic_write_text(folder / "times.txt", times_text(names))
    atomic_write_text(folder / "README.md", README)
    CameraResponse(true_table(), {"method": "ground truth", "source": "scripts/make_samples.py"}).save(
        folder / "ground_truth_response.npz")


def check(out: Path) -> list[str]:
    """Names of sample files that differ from what :func:`write` would produce (pixels, text, table)."""
    from radiometry.errors import RadiomapError
    from radiometry.images import read_rgb
    from radiometry.response import CameraResponse

    folder = out / "brackets"
    images, names = brackets()
    stale = []
    for name, image in zip(names, images):
        try:
            if not np.array_equal(read_rgb(folder / name), image):
                stale.append(name)
        except RadiomapError:
            stale.append(name)
    for name, text in (("times.txt", times_text(names)), ("README.md", README)):
        path = folder / name
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            stale.append(name)
    try:
        if not np.allclose(CameraResponse.load(folder / "ground_truth_response.npz").inverse_table, true_table()):
            stale.append("ground_truth_response.npz")
    except RadiomapError:
        stale.append("ground_truth_response.npz")
    return stale


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=REPO / "data_samples", help="output folder (data_samples/)")
    parser.add_argument("--check", action="store_true", help="only check that the files are up to date")
    args = parser.parse_args(argv)
    if args.check:
        stale = check(args.out)
        if stale:
            print(f"{args.out}: out of date: {', '.join(stale)}; run python scripts/make_samples.py")
            return 1
        print(f"{args.out}: up to date")
        return 0
    write(args.out)
    print(f"wrote {args.out / 'brackets'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
