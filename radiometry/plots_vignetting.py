"""Plots of vignetting calibrations (matplotlib; every function takes the axis first).

- :func:`plot_vignetting_map`: ``V`` of one channel as an image with iso-lines.
- :func:`plot_radial_profiles`: the samples (drift-corrected mean flat, normalised) against the radius
  from each channel's centre, with the model's profile.
- :func:`plot_residuals`: the flat divided by the model, minus 1, in percent.
- :func:`plot_coverage`: samples per pixel, with the pixels below ``min_samples`` hatched.
- :func:`plot_repeatability`: the paper's Fig. 6 box plots (error per model per channel).
- :func:`save_calibration_figures`: all of the above into PNG files.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from radiometry.fileio import atomic_path
from radiometry.vignetting import PolynomialVignetting, VignettingModel, half_diagonal

if TYPE_CHECKING:  # pragma: no cover
    from radiometry.vignetting_calibration import VignettingAccumulation

CHANNEL_NAMES = ("R", "G", "B")
CHANNEL_COLOURS = ("tab:red", "tab:green", "tab:blue")


def _image_panel(ax, im, title: str, colorbar: bool):
    """Finish an image panel: its title, no ticks, a colour bar if asked; returns the image artist."""
    ax.set_title(title)
    ax.set_xticks([])
    ax.set_yticks([])
    if colorbar:
        ax.figure.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
    return im


def _channel_label(c: int, channels: int) -> str:
    return "grey" if channels == 1 else CHANNEL_NAMES[c]


def _normalised_flat(accumulation: "VignettingAccumulation", model: VignettingModel) -> np.ndarray:
    """The session's flat scaled so that it matches the model in the median (``NaN`` where unobserved)."""
    h, w, ch = accumulation.shape
    flat = accumulation.flat()
    v = np.broadcast_to(model.evaluate(h, w), (h, w, ch))
    out = np.empty_like(flat)
    for c in range(ch):
        ratio = flat[:, :, c] / v[:, :, c]
        a = np.nanmedian(ratio) if np.isfinite(ratio).any() else 1.0
        out[:, :, c] = flat[:, :, c] / a
    return out


def plot_vignetting_map(ax, model: VignettingModel | np.ndarray, channel: int = 0, *, levels: int = 8,
                        vmin: float | None = None, vmax: float = 1.0, colorbar: bool = True):
    """``V`` of ``channel`` as an image (``viridis``) with ``levels`` iso-lines; returns the image artist."""
    v = model.evaluate() if isinstance(model, VignettingModel) else np.asarray(model)
    if v.ndim == 3:
        v = v[:, :, min(channel, v.shape[2] - 1)]
    im = ax.imshow(v, cmap="viridis", vmin=vmin if vmin is not None else float(np.min(v)), vmax=vmax,
                   interpolation="nearest")
    if levels and float(v.max() - v.min()) > 1e-6:
        cs = ax.contour(v, levels=levels, colors="white", linewidths=0.6, alpha=0.7)
        ax.clabel(cs, fmt="%.2f", fontsize=6)
    if isinstance(model, PolynomialVignetting):
        cx, cy = model.centres[min(channel, model.channels - 1)]
        ax.plot([cx], [cy], marker="+", color="red", markersize=10)
    channels = 3 if v.ndim == 2 else v.shape[2]
    return _image_panel(ax, im, f"V, channel {_channel_label(channel, channels)}", colorbar)


def plot_stderr_map(ax, stderr: np.ndarray, channel: int = 0, *, vmax: float | None = None,
                    colorbar: bool = True):
    """The relative standard error of ``V`` (``LUTVignetting.stderr``) of ``channel`` in percent (``magma``,
    capped at ``vmax`` %, default the 99th percentile so that filled corners do not wash the rest out);
    returns the image artist."""
    se = np.asarray(stderr, dtype=np.float64)
    channels = se.shape[2] if se.ndim == 3 else 1
    if se.ndim == 3:
        se = se[:, :, min(channel, se.shape[2] - 1)]
    pct = 100.0 * se
    top = float(np.percentile(pct, 99)) if vmax is None else float(vmax)
    im = ax.imshow(pct, cmap="magma", vmin=0.0, vmax=max(top, 1e-6), interpolation="nearest")
    return _image_panel(ax, im, f"stderr of V [%], channel {_channel_label(channel, channels)}", colorbar)


def plot_radial_profiles(ax, accumulation: "VignettingAccumulation", model: VignettingModel, *,
                         max_points: int = 4000, seed: int = 0):
    """Samples of the normalised flat against the radius ``r`` (1 = half-diagonal) from each channel's
    centre (the polynomial's centre, or the image centre for a LUT), with the model's profile along the
    same radii (a band for a non-radial LUT)."""
    h, w, ch = accumulation.shape
    flat = _normalised_flat(accumulation, model)
    v = np.broadcast_to(model.evaluate(h, w), (h, w, ch))
    rng = np.random.default_rng(seed)
    radius = half_diagonal((w, h))
    yy, xx = np.mgrid[0:h, 0:w]
    for c in range(ch):
        if isinstance(model, PolynomialVignetting):
            cx, cy = model.centres[min(c, model.channels - 1)] * np.array([w / model.resolution[0],
                                                                           h / model.resolution[1]])
        else:
            cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
        r = np.hypot(xx - cx, yy - cy) / radius
        sel = np.flatnonzero(np.isfinite(flat[:, :, c]).ravel())
        if sel.size > max_points:
            sel = rng.choice(sel, max_points, replace=False)
        colour = CHANNEL_COLOURS[c] if ch == 3 else "black"
        ax.scatter(r.ravel()[sel], flat[:, :, c].ravel()[sel], s=1, alpha=0.25, color=colour, rasterized=True)
        order = np.argsort(r.ravel())
        rr, vv = r.ravel()[order], v[:, :, c].ravel()[order]
        if isinstance(model, PolynomialVignetting):
            ax.plot(rr, vv, color=colour, lw=1.5, label=f"{_channel_label(c, ch)} model")
        else:
            bins = np.linspace(0, rr.max(), 60)
            idx = np.digitize(rr, bins)
            lo = [vv[idx == i].min() if np.any(idx == i) else np.nan for i in range(1, len(bins))]
            hi = [vv[idx == i].max() if np.any(idx == i) else np.nan for i in range(1, len(bins))]
            ax.fill_between(bins[1:], lo, hi, color=colour, alpha=0.35, label=f"{_channel_label(c, ch)} LUT range")
    ax.set_xlabel("r (1 = half-diagonal)")
    ax.set_ylabel("V")
    ax.set_title("radial profiles: samples and model")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, markerscale=4)
    return ax


def plot_residuals(ax, accumulation: "VignettingAccumulation", model: VignettingModel, channel: int = 1, *,
                   limit: float | None = None, colorbar: bool = True):
    """``flat / V - 1`` in percent for one channel (diverging colours, unobserved pixels blank)."""
    h, w, ch = accumulation.shape
    c = min(channel, ch - 1)
    flat = _normalised_flat(accumulation, model)[:, :, c]
    v = np.broadcast_to(model.evaluate(h, w), (h, w, ch))[:, :, c]
    res = 100.0 * (flat / v - 1.0)
    if limit is None:
        finite = res[np.isfinite(res)]
        limit = float(np.percentile(np.abs(finite), 99)) if finite.size else 1.0
        limit = max(limit, 0.1)
    im = ax.imshow(res, cmap="RdBu_r", vmin=-limit, vmax=limit, interpolation="nearest")
    return _image_panel(ax, im, f"residual flat/V - 1 (%), channel {_channel_label(c, ch)}", colorbar)


def plot_coverage(ax, count: np.ndarray, min_samples: int, *, colorbar: bool = True):
    """Samples per pixel (``(H, W)``), capped at ``2 * min_samples``; pixels below ``min_samples`` hatched
    in red."""
    count = np.asarray(count)
    im = ax.imshow(np.minimum(count, 2 * min_samples), cmap="magma", vmin=0, vmax=2 * min_samples,
                   interpolation="nearest")
    below = count < min_samples
    if below.any():
        overlay = np.zeros((*count.shape, 4))
        overlay[below] = (1.0, 0.0, 0.0, 0.45)
        ax.imshow(overlay, interpolation="nearest")
    title = f"coverage: samples per pixel ({100 * below.mean():.1f}% below {min_samples}, red)"
    return _image_panel(ax, im, title, colorbar)


def plot_repeatability(ax, errors: dict[str, np.ndarray], *, channel_names: Sequence[str] = CHANNEL_NAMES):
    """Box plots of repeatability errors (8-bit levels): one group per model, one box per channel."""
    models = list(errors)
    channels = max(np.asarray(e).shape[1] for e in errors.values())
    width = 0.8 / channels
    for c in range(channels):
        data = [np.asarray(errors[m])[:, min(c, np.asarray(errors[m]).shape[1] - 1)] for m in models]
        pos = np.arange(len(models)) + (c - (channels - 1) / 2) * width
        bp = ax.boxplot(data, positions=pos, widths=width * 0.9, patch_artist=True, showfliers=True)
        colour = CHANNEL_COLOURS[c] if channels == 3 else "grey"
        for box in bp["boxes"]:
            box.set_facecolor(colour)
            box.set_alpha(0.5)
        ax.plot([], [], color=colour, lw=6, alpha=0.5, label=channel_names[c] if channels == 3 else "grey")
    ax.set_xticks(np.arange(len(models)))
    ax.set_xticklabels(models)
    ax.set_ylabel("RMS error (8-bit levels)")
    ax.set_title("vignetting repeatability: model of one session vs the others")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    return ax


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format=path.suffix.lstrip(".") or "png")
    plt.close(fig)
    return path


def save_coverage_png(path: str | os.PathLike, count: np.ndarray, min_samples: int) -> Path:
    """The coverage map as a PNG figure."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 5.2))
    plot_coverage(ax, count, min_samples)
    return _save(fig, Path(path))


def save_calibration_figures(prefix: str | os.PathLike, accumulation: "VignettingAccumulation",
                             model: VignettingModel, *, min_samples: int = 20) -> dict[str, Path]:
    """Write ``<prefix>_coverage.png``, ``_vignetting.png`` (V per channel), ``_stderr.png`` (its standard
    error, when the model carries one), ``_profiles.png`` and ``_residuals.png``; returns ``{name: path}``."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    prefix = Path(prefix)
    out = {"coverage": save_coverage_png(prefix.with_name(prefix.name + "_coverage.png"),
                                         accumulation.coverage(), min_samples)}
    ch = model.channels
    v_all = model.evaluate()
    vmin = float(v_all.min())
    fig, axes = plt.subplots(1, ch, figsize=(4.6 * ch, 3.6), squeeze=False)
    for c in range(ch):
        plot_vignetting_map(axes[0, c], model, c, vmin=vmin)
    out["vignetting"] = _save(fig, prefix.with_name(prefix.name + "_vignetting.png"))
    stderr = getattr(model, "stderr", None)
    if stderr is not None:
        top = float(np.percentile(100.0 * stderr, 99))
        fig, axes = plt.subplots(1, ch, figsize=(4.6 * ch, 3.6), squeeze=False)
        for c in range(ch):
            plot_stderr_map(axes[0, c], stderr, c, vmax=top)
        out["stderr"] = _save(fig, prefix.with_name(prefix.name + "_stderr.png"))
    fig, ax = plt.subplots(figsize=(7, 4.5))
    plot_radial_profiles(ax, accumulation, model)
    out["profiles"] = _save(fig, prefix.with_name(prefix.name + "_profiles.png"))
    chs = accumulation.channels
    fig, axes = plt.subplots(1, chs, figsize=(4.6 * chs, 3.6), squeeze=False)
    for c in range(chs):
        plot_residuals(axes[0, c], accumulation, model, c)
    out["residuals"] = _save(fig, prefix.with_name(prefix.name + "_residuals.png"))
    return out


__all__ = ["plot_vignetting_map", "plot_stderr_map", "plot_radial_profiles", "plot_residuals", "plot_coverage", "plot_repeatability",
           "save_coverage_png", "save_calibration_figures"]
