"""Plot helpers every report shares: calendar UTC time axes, figures without pyplot, long series thinned.

- :func:`utc_axis` puts calendar UTC on a time axis (matplotlib's concise date labels) and returns the
  x values of TDB epochs; :func:`utc_dates` converts without an axis.
- :func:`new_figure` makes a matplotlib figure outside pyplot (no global state, no GUI backend, nothing
  left open) with opnav's report style; :func:`figure_png` turns it into PNG bytes.
- :func:`envelope_indices` thins a long series to what a panel a few hundred pixels wide can show: the
  extremes of each run of samples, so the drawing looks the same as the full line at a fraction of the
  cost (a 30-day run at one record a minute has 86,400 records).
"""

from __future__ import annotations

import io

import numpy as np

#: Samples a plotted series keeps at most (its extremes are kept: :func:`envelope_indices`).
PLOT_POINTS = 4000
#: Spacing of the nodes between which UTC - TDB is interpolated (:func:`utc_dates`), s.
_UTC_NODE_S = 6 * 3600.0
#: Resolution of report PNGs; a 13-inch figure is 1300 pixels wide, readable at 100 % in a browser.
DPI = 100


def utc_dates(t_tdb_s: np.ndarray) -> np.ndarray:
    """Matplotlib date numbers of UTC for epochs ``t_tdb_s`` (TDB seconds past J2000), same shape.

    UTC - TDB is taken exactly (astropy) at nodes at most 6 h apart and interpolated between them: it
    changes by 1.7 ms over a year (TDB - TT) and by a leap second at most, which a plot cannot show,
    while converting 86,400 epochs one by one takes a second.
    """
    from ..epochs import to_time

    t = np.asarray(t_tdb_s, dtype=float)
    finite = t[np.isfinite(t)]
    if finite.size == 0:
        return np.full(t.shape, np.nan)
    low, high = float(finite.min()), float(finite.max())
    nodes = np.linspace(low, high, max(2, int(np.ceil((high - low) / _UTC_NODE_S)) + 1))
    dates = np.asarray(to_time(nodes).utc.plot_date, dtype=float)
    days = (nodes - low) / 86_400.0
    offset = dates - days  # the date number of each node less its TDB days since the first
    return offset[0] + (t - low) / 86_400.0 + np.interp(t, nodes, offset - offset[0])


def utc_axis(ax, t_tdb_s: np.ndarray, *, label: bool = True) -> np.ndarray:
    """Format ``ax``'s x axis as calendar UTC and return the x values (matplotlib dates) of ``t_tdb_s``.

    Concise date labels (days, then hours, the month and year once at the axis end) keep the ticks
    short enough not to overlap on a panel a third of a page wide; ``label`` writes "UTC" under it.
    """
    import matplotlib.dates as mdates

    x = utc_dates(t_tdb_s)
    locator = mdates.AutoDateLocator(minticks=3, maxticks=6)
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator))
    if label:
        ax.set_xlabel("UTC")
    return x


def new_figure(rows: int = 1, cols: int = 1, *, width_in: float = 13.0, height_in: float = 4.0,
               sharex: bool | str = False, sharey: bool | str = False, squeeze: bool = False):
    """(figure, axes) outside pyplot with constrained layout and report font sizes; ``axes`` is a
    (rows, cols) array unless ``squeeze``."""
    from matplotlib.figure import Figure as MplFigure

    fig = MplFigure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")
    axes = fig.subplots(rows, cols, sharex=sharex, sharey=sharey, squeeze=squeeze)
    for ax in np.ravel(axes):
        ax.tick_params(labelsize=9)
        ax.grid(True, color="0.9", lw=0.6)
        ax.set_axisbelow(True)
    return fig, axes


def figure_png(fig) -> bytes:
    """PNG bytes of matplotlib figure ``fig`` at :data:`DPI`."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=DPI)
    return buffer.getvalue()


def envelope_indices(values: np.ndarray, points: int = PLOT_POINTS) -> np.ndarray:
    """Indices (increasing) that draw ``values`` (N,) as its full line would look: every index when N is at
    most ``points``, else the first and last and, in each of ``points // 2`` runs of consecutive samples,
    the smallest and the largest (NaN are skipped; a run of only NaN keeps its first sample)."""
    n = values.size
    if n <= points:
        return np.arange(n)
    bins = points // 2
    edges = np.linspace(0, n, bins + 1).astype(int)
    width = int(np.max(np.diff(edges)))
    # the runs padded to one width with their own first sample, so each row's extremes are its own
    index = np.minimum(edges[:-1, None] + np.arange(width), edges[1:, None] - 1)
    rows = np.asarray(values, dtype=float)[index]
    low = np.where(np.isnan(rows), np.inf, rows).argmin(axis=1)
    high = np.where(np.isnan(rows), -np.inf, rows).argmax(axis=1)
    picks = np.concatenate([[0, n - 1], index[np.arange(bins), low], index[np.arange(bins), high]])
    return np.unique(picks)
