"""Plots of mapping results (matplotlib, axis first, no radiometry imports).

>>> fig, ax = plt.subplots()                                              # doctest: +SKIP
>>> plot_histograms(ax, {"no correction": h0, "LUT vignetting": h1}, log_y=True)
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from mapping.histogram import BINS, DisagreementHistogram


def _counts(h) -> np.ndarray:
    if isinstance(h, DisagreementHistogram):
        return h.counts
    arr = np.asarray(h)
    if arr.ndim != 1:
        raise ValueError(f"a histogram must be a DisagreementHistogram or 1-D counts, got shape {arr.shape}")
    return arr


def plot_histograms(ax, histograms: Mapping[str, DisagreementHistogram | np.ndarray], *, normalise: bool = True,
                    log_y: bool = False, max_distance: int | None = None, show_mean: bool = True,
                    cumulative: bool = False, title: str | None = None, colors=None):
    """Overlay colour-disagreement histograms like the paper's Fig. 9.

    ax:           a matplotlib axis.
    histograms:   ``{label: DisagreementHistogram or counts}``; drawn as steps in the given order.
    normalise:    divide each by its total (fractions), so runs with different numbers of samples compare.
    log_y:        logarithmic y axis (the tails differ most).
    max_distance: right end of the x axis (default: the 99.9th percentile of all histograms, at least 30).
    show_mean:    dashed vertical line and legend entry with each histogram's mean.
    cumulative:   plot the cumulative distribution instead.
    Returns the axis.
    """
    if not histograms:
        raise ValueError("histograms must name at least one histogram")
    colors = colors or [None] * len(histograms)
    upper = 30
    x = np.arange(BINS)
    for (label, h), color in zip(histograms.items(), colors):
        counts = _counts(h).astype(np.float64)
        total = counts.sum()
        y = counts / total if (normalise and total > 0) else counts
        if cumulative:
            y = np.cumsum(y)
        mean = float(np.dot(np.arange(len(counts)), counts) / total) if total > 0 else float("nan")
        text = f"{label} (mean {mean:.1f})" if show_mean and total > 0 else str(label)
        (line,) = ax.step(x[:len(y)], y, where="mid", label=text, color=color, linewidth=1.2)
        if show_mean and total > 0:
            ax.axvline(mean, color=line.get_color(), linestyle="--", linewidth=0.8)
        if total > 0:
            cdf = np.cumsum(counts) / total
            upper = max(upper, int(np.searchsorted(cdf, 0.999)) + 1)
    ax.set_xlim(0, max_distance if max_distance is not None else min(upper, BINS - 1))
    ax.set_xlabel("L1 colour distance, map vs new sample (8-bit display levels, R+G+B)")
    ylabel = "fraction of samples" if normalise else "samples"
    ax.set_ylabel(("cumulative " if cumulative else "") + ylabel)
    if log_y and not cumulative:
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper right", fontsize="small")
    if title:
        ax.set_title(title)
    return ax


def save_histogram_figure(path, histograms: Mapping[str, DisagreementHistogram | np.ndarray], *,
                          log_y: bool = True, title: str | None = None) -> None:
    """Write a figure with linear and log panels of :func:`plot_histograms` (atomic, format by suffix)."""
    from matplotlib.figure import Figure

    from radiometry.fileio import atomic_path

    fig = Figure(figsize=(11 if log_y else 6, 4))
    axes = fig.subplots(1, 2 if log_y else 1, squeeze=False)
    plot_histograms(axes[0, 0], histograms, title=title)
    if log_y:
        plot_histograms(axes[0, 1], histograms, log_y=True, title="log scale")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
