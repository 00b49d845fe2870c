"""Cheap PNG figures for stage outputs (residual, Allan, segmentation and drift plots).

A pipeline run draws a few dozen figures; drawn the usual way (``pyplot`` figures, ``tight_layout`` or
``bbox_inches="tight"``, log axes with labelled minor ticks, ``legend(loc="best")``) they cost more CPU than the
science they show. Here: an Agg canvas without ``pyplot`` (no figure manager to create and close), margins fixed
in inches instead of a layout pass that draws the figure twice, log axes with unlabelled minor ticks and no minor
grid (the minor-tick locator and its mathtext labels were most of an Allan plot's time), and legends at a fixed
place. Figures show the same data as before.
"""

from __future__ import annotations

import io

#: margins in inches (left, right, bottom, top) around the axes grid; room for tick labels, axis labels and a title
MARGINS_IN = (0.85, 0.2, 0.55, 0.45)


def figure(nrows: int = 1, ncols: int = 1, figsize=(8.0, 4.0), dpi: float = 90, sharex: bool = False,
           margins_in=MARGINS_IN, hspace: float = 0.35, wspace: float = 0.28, squeeze: bool = False):
    """(figure, axes) on an Agg canvas with fixed margins; ``axes`` is a 2-D array unless ``squeeze``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, sharex=sharex, squeeze=squeeze)
    w, h = figsize
    left, right, bottom, top = margins_in
    fig.subplots_adjust(left=min(0.4, left / w), right=max(0.6, 1 - right / w), bottom=min(0.4, bottom / h),
                        top=max(0.6, 1 - top / h), hspace=hspace, wspace=wspace)
    return fig, axes


def log_axes(ax, x: bool = True, y: bool = True) -> None:
    """Log scale without the minor-tick locator (major decades only, labelled as usual)."""
    from matplotlib.ticker import NullLocator

    for on, axis, setter in ((x, ax.xaxis, ax.set_xscale), (y, ax.yaxis, ax.set_yscale)):
        if on:
            setter("log")
            axis.set_minor_locator(NullLocator())


def envelope(t, y, max_points: int = 4000):
    """(t, y) reduced to at most ``max_points`` by keeping each bin's minimum and maximum (in time order), so
    spikes and the trace's envelope stay visible at screen resolution; short series are returned unchanged."""
    import numpy as np

    t, y = np.asarray(t, dtype=float), np.asarray(y, dtype=float)
    nbins = max(1, max_points // 2)
    if t.size <= max_points:
        return t, y
    step = int(np.ceil(t.size / nbins))
    n = (t.size // step) * step
    tb, yb = t[:n].reshape(-1, step), y[:n].reshape(-1, step)
    finite = np.isfinite(yb)
    lo = np.argmin(np.where(finite, yb, np.inf), axis=1)
    hi = np.argmax(np.where(finite, yb, -np.inf), axis=1)
    first, second = np.minimum(lo, hi), np.maximum(lo, hi)
    rows = np.arange(tb.shape[0])
    tt = np.column_stack([tb[rows, first], tb[rows, second]]).ravel()
    yy = np.column_stack([yb[rows, first], yb[rows, second]]).ravel()
    if n < t.size:
        tt, yy = np.concatenate([tt, t[n:][[0, -1]]]), np.concatenate([yy, y[n:][[0, -1]]])
    return tt, yy


def png(fig, dpi: float | None = None) -> bytes:
    """The figure as PNG bytes (its own dpi unless given)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi or fig.dpi)
    return buf.getvalue()
