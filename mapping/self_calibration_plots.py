"""Figures of a self-calibration (``radiomap self-calibrate``, :mod:`mapping.self_calibration`): ``V`` per channel and
its standard error, the coverage of image positions, the exposure of each frame and the residuals before and after
(matplotlib, every drawing function takes the axis first)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

CHANNEL_COLOURS = ("tab:red", "tab:green", "tab:blue")


def plot_vignetting(ax, lut: np.ndarray, channel: int, *, title: str = "") -> object:
    """``V`` of one channel as an image with contours at 0.05 steps; returns the image artist."""
    v = lut[:, :, channel]
    im = ax.imshow(v, cmap="viridis", vmin=float(v.min()), vmax=1.0)
    ax.contour(v, levels=np.arange(0.3, 1.0, 0.05), colors="white", linewidths=0.5)
    ax.set_title(title or f"V ({'RGB'[channel]})")
    ax.set_axis_off()
    return im


def plot_stderr(ax, stderr: np.ndarray, channel: int, *, vmax: float | None = None) -> object:
    """The relative standard error of ``V`` (in %) of one channel as an image; returns the image artist."""
    se = 100.0 * stderr[:, :, channel]
    im = ax.imshow(se, cmap="magma", vmin=0.0, vmax=vmax if vmax is not None else float(se.max()))
    ax.set_title(f"stderr of V ({'RGB'[channel]}), %")
    ax.set_axis_off()
    return im


def plot_coverage(ax, coverage: np.ndarray, *, min_samples: int = 3) -> object:
    """Sightings per image-position bin (log colour scale), bins below ``min_samples`` hatched in red."""
    from matplotlib.colors import LogNorm

    im = ax.imshow(np.maximum(coverage, 1), cmap="magma", norm=LogNorm())
    thin = np.ma.masked_where(coverage >= min_samples, np.ones_like(coverage, dtype=float))
    ax.imshow(thin, cmap="autumn", alpha=0.6)
    ax.set_title(f"sightings per image position (red: < {min_samples})")
    ax.set_axis_off()
    return im


def plot_exposures(ax, indices: np.ndarray, exposures: np.ndarray) -> None:
    """``k_j`` per channel against the frame index (``k_0 = 1``)."""
    for c in range(exposures.shape[1]):
        ax.plot(indices, exposures[:, c], color=CHANNEL_COLOURS[c], label="k_" + "rgb"[c])
    ax.set_xlabel("frame")
    ax.set_ylabel("exposure k (first frame = 1)")
    ax.legend()
    ax.grid(alpha=0.3)


def plot_residuals(ax, before: list[np.ndarray], after: list[np.ndarray]) -> None:
    """Histograms of the log-irradiance residuals with ``V = 1`` and with the fitted ``V`` (all channels)."""
    b, a = np.concatenate(before), np.concatenate(after)
    lim = float(np.percentile(np.abs(b), 99)) or 0.1
    bins = np.linspace(-lim, lim, 81)
    ax.hist(b, bins=bins, histtype="step", color="grey", label="V = 1")
    ax.hist(a, bins=bins, histtype="step", color="black", label="fitted V")
    ax.set_xlabel("log-irradiance residual")
    ax.set_ylabel("sightings")
    ax.legend()


def save_figures(folder: Path, result, indices: np.ndarray) -> dict[str, Path]:
    """Write ``vignetting.png``, ``stderr.png`` (the standard error of ``V``), ``coverage.png``, ``exposures.png``
    and ``residuals.png`` into ``folder`` (atomically); returns name -> path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from radiometry.fileio import atomic_write_bytes

    lut = result.vignetting.evaluate()
    files = {}

    def save(fig, name):
        import io

        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
        plt.close(fig)
        files[name] = atomic_write_bytes(Path(folder) / f"{name}.png", buf.getvalue())

    fig, axes = plt.subplots(1, lut.shape[2], figsize=(4.2 * lut.shape[2], 3.2))
    for c, ax in enumerate(np.atleast_1d(axes)):
        im = plot_vignetting(ax, lut, c)
    fig.colorbar(im, ax=list(np.atleast_1d(axes)), shrink=0.8)
    save(fig, "vignetting")
    se = result.vignetting.stderr
    fig, axes = plt.subplots(1, se.shape[2], figsize=(4.2 * se.shape[2], 3.2))
    for c, ax in enumerate(np.atleast_1d(axes)):
        im = plot_stderr(ax, se, c, vmax=100.0 * float(se.max()))
    fig.colorbar(im, ax=list(np.atleast_1d(axes)), shrink=0.8)
    save(fig, "stderr")
    fig, ax = plt.subplots(figsize=(5, 4))
    plot_coverage(ax, result.coverage)
    save(fig, "coverage")
    fig, ax = plt.subplots(figsize=(7, 3.5))
    plot_exposures(ax, indices, result.exposures)
    save(fig, "exposures")
    fig, ax = plt.subplots(figsize=(6, 3.5))
    plot_residuals(ax, result.residuals_before, result.residuals_after)
    save(fig, "residuals")
    return files


__all__ = ["plot_coverage", "plot_exposures", "plot_residuals", "plot_stderr", "plot_vignetting", "save_figures"]
