"""Plots of calibration results (matplotlib, axis first, so that they compose into figures).

Figures are created with :func:`new_figure` on matplotlib's Agg canvas directly (no pyplot, no global
backend switch), so plotting works headless and never disturbs an interactive session;
:func:`save_figure` writes a PNG atomically.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.fileio import atomic_path

#: line colours of the channels of a 3-channel (RGB) and a 1-channel response
CHANNEL_COLOURS = {3: ("#d62728", "#2ca02c", "#1f77b4"), 1: ("#333333",)}
CHANNEL_NAMES = {3: ("R", "G", "B"), 1: ("gray",)}


def new_figure(nrows: int = 1, ncols: int = 1, *, size: tuple[float, float] = (6.4, 4.8), **subplot_kw: Any):
    """A ``(figure, axes)`` pair on the Agg canvas (``axes`` as ``Figure.subplots`` returns it)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=True, subplot_kw=subplot_kw or None)
    return fig, axes


def save_figure(fig, path: str | os.PathLike, *, dpi: int = 100) -> Path:
    """Write a figure (format from the suffix, PNG recommended) atomically."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    return Path(path)


def _channel_lists(meta: dict, key: str, channels: int) -> list[np.ndarray] | None:
    """``meta[key]`` as one integer array of levels per channel (a 1-list serves every channel); None if absent or
    malformed (a plot never fails on a hand-edited file)."""
    lists = meta.get(key)
    if not isinstance(lists, (list, tuple)) or not lists or not all(isinstance(v, (list, tuple)) for v in lists):
        return None
    out = []
    for c in range(channels):
        levels = [int(v) for v in lists[min(c, len(lists) - 1)] if isinstance(v, (int, np.integer)) and 0 <= v < 256]
        out.append(np.asarray(levels, dtype=np.intp))
    return out


def plot_response(ax, response, *, log: bool = False, label: str | None = None, band: bool = True,
                  **line_kw: Any) -> list:
    """Plot ``f^-1`` (relative irradiance) against intensity 0..255, one line per channel in RGB colours.

    ``log=True`` uses a logarithmic irradiance axis (Debevec's ``g = ln f^-1`` up to the axis scale), which
    shows the dark levels. ``label`` prefixes the legend entries (e.g. a method name, to overlay several
    responses); ``line_kw`` go to ``ax.plot`` (e.g. ``linestyle="--"``). When the response carries its standard
    error (``meta["inverse_stderr"]``) and ``band`` is True, a band of +-1 standard uncertainty (that error and the
    levels' 8-bit width: :func:`radiometry.response.relative_uncertainty`) is shaded around each line; levels the fit extrapolated rather than estimated from data (``meta["extrapolated_levels"]``) are marked
    with open circles. Returns the lines.
    """
    table = np.asarray(response.inverse_table)
    n_ch = table.shape[1]
    levels = np.arange(table.shape[0])
    from radiometry.response import relative_uncertainty

    se = relative_uncertainty(response) if band else None
    extrapolated = _channel_lists(response.meta, "extrapolated_levels", n_ch)
    lines = []
    for c in range(n_ch):
        name = CHANNEL_NAMES[n_ch][c]
        kw = {"color": CHANNEL_COLOURS[n_ch][c], "linewidth": 1.5, **line_kw}
        y = table[:, c]
        if log:
            y = np.where(y > 0, y, np.nan)  # level 0 may map to 0, which a log axis cannot show
        lines += ax.plot(levels, y, label=f"{label} {name}" if label else name, **kw)
        if se is not None:
            ax.fill_between(levels, y * np.exp(-se[:, c]), y * np.exp(se[:, c]), color=kw["color"], alpha=0.25,
                            linewidth=0, label="$\\pm$1 standard uncertainty" if c == 0 else None)
        if extrapolated is not None and extrapolated[c].size:
            k = extrapolated[c]
            ax.plot(k, y[k], linestyle="none", marker="o", markersize=4, markerfacecolor="none",
                    markeredgecolor=kw["color"], label="extrapolated (no data)" if c == 0 else None)
    if log:
        ax.set_yscale("log")
    ax.set_xlim(0, 255)
    ax.set_xlabel("intensity I (8-bit level)")
    ax.set_ylabel("relative irradiance f$^{-1}$(I)" + (" (log scale)" if log else ""))
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(loc="upper left", fontsize="small")
    return lines


def response_figure(response, *, title: str | None = None):
    """A two-panel figure of a response: ``f^-1`` on linear (left) and logarithmic (right) axes."""
    fig, (lin, logax) = new_figure(1, 2, size=(10.0, 4.0))
    plot_response(lin, response)
    plot_response(logax, response, log=True)
    lin.set_title("inverse response f$^{-1}$")
    logax.set_title("log scale (g = ln f$^{-1}$)")
    if title:
        fig.suptitle(title)
    return fig


__all__ = ["new_figure", "save_figure", "plot_response", "response_figure", "CHANNEL_COLOURS"]
