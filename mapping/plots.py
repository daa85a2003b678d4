"""Plots of mapping results (matplotlib, axis first, no radiometry imports).

>>> fig, ax = plt.subplots()                                              # doctest: +SKIP
>>> plot_histograms(ax, {"no correction": h0, "LUT vignetting": h1}, log_y=True)
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from mapping.histogram import BINS, DisagreementHistogram


# colour-blind-safe colours (Okabe-Ito) with a line style and marker each, so that curves that coincide stay
# told apart (a dashed curve over a solid one shows both)
COLOURS = ("#0072B2", "#E69F00", "#009E73", "#D55E00", "#CC79A7", "#56B4E9", "#000000", "#F0E442")
LINESTYLES = ("-", "--", "-.", ":")
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")


def curve_style(i: int) -> dict:
    """Colour, line style and marker of the ``i``-th curve of a figure (matplotlib keywords)."""
    return {"color": COLOURS[i % len(COLOURS)], "linestyle": LINESTYLES[i % len(LINESTYLES)],
            "marker": MARKERS[i % len(MARKERS)]}


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
    histograms:   ``{label: DisagreementHistogram or counts}``; drawn as steps in the given order, each with
                  its own colour, line style and markers (:func:`curve_style`), so curves that coincide show.
    normalise:    divide each by its total (fractions), so runs with different numbers of samples compare.
    log_y:        logarithmic y axis (the tails differ most).
    max_distance: right end of the x axis (default: the 99.9th percentile of all histograms, at least 30).
    show_mean:    a triangle on the top edge at each histogram's mean, and the mean in its legend entry.
    cumulative:   plot the cumulative distribution instead.
    Returns the axis.
    """
    if not histograms:
        raise ValueError("histograms must name at least one histogram")
    from matplotlib.transforms import blended_transform_factory

    colors = colors or [None] * len(histograms)
    upper = 30
    x = np.arange(BINS)
    top = blended_transform_factory(ax.transData, ax.transAxes)
    curves = []
    for i, ((label, h), color) in enumerate(zip(histograms.items(), colors)):
        counts = _counts(h).astype(np.float64)
        total = counts.sum()
        y = counts / total if (normalise and total > 0) else counts
        if cumulative:
            y = np.cumsum(y)
        mean = float(np.dot(np.arange(len(counts)), counts) / total) if total > 0 else float("nan")
        text = f"{label} (mean {mean:.1f})" if show_mean and total > 0 else str(label)
        curves.append((i, x[:len(y)], y, text, color, mean if show_mean and total > 0 else None))
        if total > 0:
            cdf = np.cumsum(counts) / total
            upper = max(upper, int(np.searchsorted(cdf, 0.999)) + 1)
    right = max_distance if max_distance is not None else min(upper, BINS - 1)
    for i, xs, y, text, color, mean in curves:
        style = curve_style(i)
        if color is not None:
            style["color"] = color
        # markers spread over the visible range, at different places per curve
        every = (i * max(right // 40, 1) // max(len(curves), 1), max(right // 12, 1))
        ax.step(xs, y, where="mid", label=text, color=style["color"], linestyle=style["linestyle"],
                linewidth=1.8, marker=style["marker"], markevery=every, markersize=5, markerfacecolor="none")
        if mean is not None:
            ax.plot([mean], [1.0], transform=top, marker="v", markersize=9, color=style["color"], clip_on=False,
                    linestyle="none")
    ax.set_xlim(0, right)
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

    fig = Figure(figsize=(FULL_WIDTH_INCHES if log_y else FULL_WIDTH_INCHES / 2, 5.2))
    axes = fig.subplots(1, 2 if log_y else 1, squeeze=False)
    plot_histograms(axes[0, 0], histograms, title=title)
    if log_y:
        plot_histograms(axes[0, 1], histograms, log_y=True, title="log scale")
    _save(fig, path)


# report figures are drawn for the report's full width (1200 px at DPI) with 10-13 pt text, so that they show
# at their own size, text readable, in a browser
FULL_WIDTH_INCHES = 12.0
DPI = 100


def _save(fig, path, *, layout: bool = True) -> None:
    from mapping.figure_files import save_figure

    if layout:
        fig.tight_layout()
    save_figure(fig, path, dpi=DPI)


def plot_exposures(axes, exposures: Mapping[str, Mapping[str, np.ndarray]], *,
                   truth: tuple[np.ndarray, np.ndarray] | None = None, legend: bool = True):
    """Per-frame exposure estimates, one panel per channel (R, G, B), one curve per run.

    axes:      three matplotlib axes.
    exposures: ``{label: read_exposures(...) dict}`` (``index``, ``k`` (N, 3), ``source``); frames whose source
               is ``fallback`` are drawn as crosses.
    truth:     ``(frame indices, (N, 3) true k)`` relative to the first frame, or None.
    legend:    a legend in the first panel.
    """
    if len(axes) != 3:
        raise ValueError(f"plot_exposures draws R, G and B on three axes, got {len(axes)}")
    for c, (ax, name) in enumerate(zip(axes, ("R", "G", "B"))):
        if truth is not None:
            ax.plot(truth[0], truth[1][:, c], color="0.55", linewidth=5, alpha=0.5, label="truth")
        for i, (label, e) in enumerate(exposures.items()):
            style = curve_style(i)
            k = np.asarray(e["k"], dtype=np.float64)[:, c]
            idx = np.asarray(e["index"])
            ax.plot(idx, k, label=label, linewidth=1.6, markersize=4, markerfacecolor="none",
                    markevery=max(len(idx) // 15, 1), **style)
            fallback = np.asarray(e["source"]) == "fallback"
            if fallback.any():
                ax.plot(idx[fallback], k[fallback], "x", color=style["color"], markersize=8)
        ax.set_title(f"{name} channel", fontsize=12)
        ax.set_xlabel("frame")
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("exposure k (first frame = 1)")
    if legend:
        axes[0].legend(fontsize="small", loc="best")
    return axes


def save_exposure_figure(path, exposures: Mapping[str, Mapping[str, np.ndarray]], *,
                         truth: tuple[np.ndarray, np.ndarray] | None = None, title: str | None = None) -> None:
    """Write :func:`plot_exposures` as a full-width figure (atomic, format by suffix)."""
    from matplotlib.figure import Figure

    if not exposures:
        raise ValueError("exposures must name at least one run's estimates")
    fig = Figure(figsize=(FULL_WIDTH_INCHES, 4.8))
    axes = fig.subplots(1, 3, sharey=True)
    plot_exposures(axes, exposures, truth=truth, legend=False)
    handles, labels = axes[0].get_legend_handles_labels()
    legend_below(fig, handles, labels)   # below, off the data
    if title:
        fig.suptitle(title, fontsize=13)
    fig.tight_layout(rect=(0, fig.legends[0].get_window_extent().y1 / fig.bbox.height, 1, 1))
    _save(fig, path, layout=False)


def legend_below(fig, handles, labels, *, max_columns: int = 4):
    """A legend under the axes that fits the figure's width: as many columns as fit (at most ``max_columns``), the
    figure made taller by the legend's height so that the axes keep theirs. Measured by drawing (Agg), not guessed
    from the labels' lengths: the old fixed 4 columns ran off both sides with the demo's long method names."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    if not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    renderer = fig.canvas.get_renderer()
    margin = 0.1 * fig.dpi   # pixels kept free at the sides and below
    legend = None
    for fontsize in ("medium", "small", "x-small"):
        for ncol in range(min(len(labels), max_columns), 0, -1):
            legend = fig.legend(handles, labels, loc="lower center", ncol=ncol, frameon=False, fontsize=fontsize)
            if legend.get_window_extent(renderer).width <= fig.bbox.width - 2 * margin:
                break
            legend.remove()
            legend = None
        if legend is not None:
            break
    if legend is None:   # wider than the figure even in one column of the smallest text: widen the figure
        legend = fig.legend(handles, labels, loc="lower center", ncol=1, frameon=False, fontsize="x-small")
        fig.set_figwidth((legend.get_window_extent(renderer).width + 2 * margin) / fig.dpi)
    height = (legend.get_window_extent(renderer).height + margin) / fig.dpi
    fig.set_figheight(fig.get_figheight() + height)
    legend.set_bbox_to_anchor((0.5, margin / fig.bbox.height), transform=fig.transFigure)
    return legend


def top_view_axes(positions: np.ndarray, up: np.ndarray | None = None) -> tuple[int, int]:
    """The two world axes of a top view: all but the vertical, which is the world axis closest to ``up`` (e.g.
    the cameras' mean up direction) or, without it, the axis the positions vary least along."""
    if up is not None and np.all(np.isfinite(up)) and np.any(up):
        drop = int(np.argmax(np.abs(np.asarray(up, dtype=np.float64))))
    else:
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        drop = int(np.argmin(np.ptp(positions, axis=0))) if len(positions) else 2
    kept = [a for a in range(3) if a != drop]
    return kept[0], kept[1]


def camera_up(poses: np.ndarray) -> np.ndarray:
    """The mean up direction (world) of camera-to-world poses with OpenCV axes (y points down in the image)."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    return -poses[:, :3, 1].mean(axis=0) if len(poses) else np.zeros(3)


def plot_trajectories(ax, trajectories: Mapping[str, np.ndarray], *, ground_truth: np.ndarray | None = None,
                      up: np.ndarray | None = None):
    """Camera positions seen from above: ``{label: (N, 3) positions}``, and the ground truth (N, 3) if known;
    start (circle) and end (square) marked; equal axis scales. ``up``: the world's up direction (e.g.
    :func:`camera_up`), which picks the two axes shown (:func:`top_view_axes`)."""
    names = "xyz"
    every = [np.asarray(p, np.float64).reshape(-1, 3) for p in trajectories.values()]
    if ground_truth is not None:
        every.append(np.asarray(ground_truth, np.float64).reshape(-1, 3))
    a, b = top_view_axes(np.concatenate(every) if every else np.zeros((0, 3)), up)
    if ground_truth is not None:
        g = np.asarray(ground_truth, np.float64).reshape(-1, 3)
        ax.plot(g[:, a], g[:, b], color="0.55", linewidth=6, alpha=0.5, label="ground truth")
    for i, (label, p) in enumerate(trajectories.items()):
        p = np.asarray(p, np.float64).reshape(-1, 3)
        style = curve_style(i)
        ax.plot(p[:, a], p[:, b], label=label, linewidth=1.8, color=style["color"], linestyle=style["linestyle"])
        if len(p):
            ax.plot(p[0, a], p[0, b], "o", color=style["color"], markersize=8)
            ax.plot(p[-1, a], p[-1, b], "s", color=style["color"], markersize=8)
    ax.set_xlabel(f"{names[a]} (m)")
    ax.set_ylabel(f"{names[b]} (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="medium", loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0,
              title="circle: start, square: end", title_fontsize="medium")
    return ax


def save_trajectory_figure(path, trajectories: Mapping[str, np.ndarray], *, ground_truth: np.ndarray | None = None,
                           up: np.ndarray | None = None, title: str | None = None) -> None:
    """Write :func:`plot_trajectories` as a full-width figure, legend on the right (atomic, format by suffix)."""
    from matplotlib.figure import Figure

    if not trajectories:
        raise ValueError("trajectories must name at least one trajectory")
    fig = Figure(figsize=(FULL_WIDTH_INCHES, 6.0))
    ax = fig.subplots()
    plot_trajectories(ax, trajectories, ground_truth=ground_truth, up=up)
    if title:
        ax.set_title(title, fontsize=13)
    _save(fig, path)
