"""Plot helpers every report shares: calendar UTC time axes, figures without pyplot, long series thinned.

- :func:`utc_axis` puts calendar UTC on a time axis (matplotlib's concise date labels) and returns the
  x values of TDB epochs; :func:`utc_dates` converts without an axis.
- :func:`new_figure` makes a matplotlib figure outside pyplot (no global state, no GUI backend, nothing
  left open) with opnav's report style; :func:`figure_png` turns it into PNG bytes.
- :func:`envelope_indices` thins a long series to what a panel a few hundred pixels wide can show: the
  extremes of each run of samples, so the drawing looks the same as the full line at a fraction of the
  cost (a 30-day run at one record a minute has 86,400 records); :func:`sample_indices` thins a
  scatter (every n-th point plus the points that matter).

The figures of one filter run (from its ``filters/<name>.npz``, :func:`opnav.studies.common.track`):
:func:`error_figure` (errors and 3-sigma in RTN or ICRF, whole arc and RMS window),
:func:`residual_figure` (innovations per target against their 3-sigma), :func:`nis_figure` and
:func:`nees_figure` (each against its chi-square band). Each returns a matplotlib figure for
:func:`figure_png`.
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
    # steps between matplotlib's own, so every span finds one with 3-6 ticks (its lists leave gaps: 2.4 h
    # found none and it warned)
    locator.intervald.update({mdates.SECONDLY: [1, 2, 5, 10, 15, 20, 30, 45, 60, 90, 120],
                              mdates.MINUTELY: [1, 2, 5, 10, 15, 20, 30, 45, 60, 90, 120],
                              mdates.HOURLY: [1, 2, 3, 4, 6, 8, 12, 18, 24, 36, 48],
                              mdates.DAILY: [1, 2, 3, 4, 5, 7, 10, 14, 21, 28, 42, 56]})
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


def plain_log_labels(ax) -> None:
    """Label ``ax``'s log y axis (call after plotting) with plain numbers (``0.5``, ``2``, ``10`` rather
    than ``5x10^-1``): at 1, 2 and 5 times the powers of ten over up to three decades, else at the
    powers of ten only, so the labels never crowd; no minor ticks."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter, NullLocator

    low, high = ax.get_ylim()
    decades = np.log10(high / low) if low > 0 and high > low else 1.0
    ax.yaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0) if decades <= 3 else (1.0,),
                                          numticks=12))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())
    # a log axis's minor ticks are dozens of artists each, a third of a figure's drawing time
    ax.yaxis.set_minor_locator(NullLocator())


def under_panel_legend(fig, ax) -> None:
    """``ax``'s legend in one row under the figure (two when it has more than four entries), so its long
    lines do not take the panel's width."""
    handles, labels = ax.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=min(4, len(handles)) if len(handles) <= 4 else 3,
               fontsize=8, frameon=False)


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


def sample_indices(n: int, always: np.ndarray | None = None, points: int = PLOT_POINTS) -> tuple[np.ndarray, int]:
    """(indices, stride) of a scatter of ``n`` points: every ``stride``-th point, at most ``points`` of
    them, plus every index where ``always`` (n,) is True (the points outside a band). A scatter thinned
    to its extremes (:func:`envelope_indices`) would show only the band's edges; a regular subsample
    keeps the density, and the points that matter are all drawn."""
    stride = max(1, int(np.ceil(n / points)))
    picks = np.arange(0, n, stride)
    if always is not None:
        picks = np.union1d(picks, np.flatnonzero(always))
    return picks, stride


def _drawn(stride: int, also: str) -> str:
    """Legend text of a thinned scatter: which points are drawn (nothing when all are)."""
    return "" if stride == 1 else f"; 1 in {stride} drawn and all {also}"


# --- the figures of one filter run (S1, S3 and any study with the generic filters) -------------------

#: Component names of the error figures per frame, position then velocity.
FRAME_AXES = {"rtn": ("radial", "along-track", "cross-track"), "icrf": ("x", "y", "z")}
FRAME_NAMES = {"rtn": "RTN (radial, along-track, cross-track of the true orbit about the centre body)",
               "icrf": "ICRF axes"}
_WINDOW_COLOR = "#fff2cc"
_BAND_COLOR = "tab:blue"


def _mark_window(ax, x_window: float, label: bool = False) -> None:
    """Shade the RMS window (from ``x_window`` to the axis end) on ``ax``."""
    ax.axvspan(x_window, ax.get_xlim()[1], color=_WINDOW_COLOR, zorder=0, lw=0,
               label="RMS window" if label else None)


def error_figure(data, frame: str, window_start_tdb_s: float, center: str, title: str):
    """Errors and 3-sigma of one filter: ``data`` is the filter's npz (:func:`opnav.studies.common.track`),
    ``frame`` ``rtn`` or ``icrf``.

    Rows: position over the whole arc (log scale: |error| and 3-sigma, the RMS window shaded), position
    over the RMS window (linear: error and the +-3-sigma band), then the same for velocity. The zoomed
    panels' y-limits hold every error and the band, so nothing is clipped. Returns the matplotlib figure.
    """
    t = np.asarray(data["t_tdb_s"], dtype=float)
    error = np.asarray(data["error_rtn" if frame == "rtn" else "error"], dtype=float)
    sigma = np.asarray(data["sigma_rtn" if frame == "rtn" else "sigma"], dtype=float)
    window = t >= window_start_tdb_s
    if not window.any():
        window = np.ones(t.size, dtype=bool)
    fig, axes = new_figure(4, 3, height_in=11.5)
    names = FRAME_AXES[frame]
    for block, (scale, unit, what) in enumerate(((1.0, "km", "position"), (1e3, "m/s", "velocity"))):
        for col in range(3):
            err = scale * error[:, 3 * block + col]
            sig3 = 3.0 * scale * sigma[:, 3 * block + col]
            whole, zoom = axes[2 * block, col], axes[2 * block + 1, col]
            x = utc_axis(whole, t, label=False)
            keep = envelope_indices(np.abs(err))
            whole.semilogy(x[keep], np.abs(err)[keep], color="tab:red", lw=0.8, label="|error|")
            keep = envelope_indices(sig3)
            whole.semilogy(x[keep], sig3[keep], color=_BAND_COLOR, lw=1.0, label="3-sigma")
            positive = sig3[np.isfinite(sig3) & (sig3 > 0)]
            top = np.nanmax(np.concatenate([np.abs(err), sig3]))
            if positive.size and np.isfinite(top) and top > 0:
                whole.set_ylim(0.01 * positive.min(), 2.0 * top)
            whole.set_xlim(x[0], x[-1])
            plain_log_labels(whole)
            _mark_window(whole, x[window][0], label=(block == 0 and col == 0))
            whole.set_title(f"{what} {names[col]} ({unit}), whole arc, log scale", fontsize=10)
            xz = utc_axis(zoom, t[window], label=(block == 1))
            ez, sz = err[window], sig3[window]
            keep = envelope_indices(sz)
            zoom.fill_between(xz[keep], -sz[keep], sz[keep], color=_BAND_COLOR, alpha=0.2, lw=0, label="+-3-sigma")
            keep = envelope_indices(ez)
            zoom.plot(xz[keep], ez[keep], color="tab:red", lw=0.8, label="error")
            lim = np.nanmax(np.abs(np.concatenate([ez, sz])))
            lim = 1.1 * lim if np.isfinite(lim) and lim > 0 else 1.0
            zoom.set_ylim(-lim, lim)
            zoom.set_xlim(xz[0], xz[-1])
            zoom.axhline(0.0, color="0.5", lw=0.5)
            zoom.set_title(f"{what} {names[col]} ({unit}), RMS window", fontsize=10)
    axes[0, 0].legend(fontsize=8, loc="upper right")
    axes[1, 0].legend(fontsize=8, loc="upper right")
    fig.suptitle(f"{title}: estimate minus truth, {FRAME_NAMES[frame]}, origin {center}", fontsize=11)
    return fig


def nees_figure(data, window_start_tdb_s: float, dof: int, title: str):
    """NEES per epoch over the whole arc (log scale) with the 95 % interval of one chi-square(``dof``)
    value, the RMS window shaded; the legend gives the share of the window's epochs inside the band."""
    from ..consistency import chi2_interval, nees_band_share

    t = np.asarray(data["t_tdb_s"], dtype=float)
    values = np.asarray(data["nees"], dtype=float)
    window = t >= window_start_tdb_s
    low, high = chi2_interval(dof, 0.95)
    fig, axes = new_figure(1, 1, height_in=3.6)
    ax = axes[0, 0]
    x = utc_axis(ax, t)
    shown = np.maximum(values, 1e-3)
    keep = envelope_indices(shown)
    ax.semilogy(x[keep], shown[keep], lw=0.7, color="tab:purple", label="NEES")
    for bound in (low, high):
        ax.axhline(bound, color="tab:green", ls="--", lw=1.2)
    ax.plot([], [], color="tab:green", ls="--", label=f"95 % interval of chi2({dof}): {low:.2f} to {high:.2f}")
    ax.set_xlim(x[0], x[-1])
    if window.any():
        share = nees_band_share(values[window], dof, 0.95)
        _mark_window(ax, x[window][0], label=True)
        ax.plot([], [], " ", label=f"inside over the RMS window: {100 * share:.0f} % of its epochs")
    plain_log_labels(ax)
    under_panel_legend(fig, ax)
    ax.set_ylabel(f"NEES ({dof} states)")
    ax.set_title(f"{title}: NEES per epoch", fontsize=11)
    return fig


def nis_figure(data, title: str):
    """NIS of each record (log scale), one colour per record size, with each size's 95 % chi-square
    interval as dashed lines of its colour; refused records as crosses at their NIS."""
    from ..consistency import chi2_interval, chi2_quantile

    t = np.asarray(data["record_t_tdb_s"], dtype=float)
    nis = np.asarray(data["nis"], dtype=float)
    dof = np.asarray(data["dof"], dtype=int)
    accepted = np.asarray(data["accepted"], dtype=bool)
    fig, axes = new_figure(1, 1, height_in=3.6)
    ax = axes[0, 0]
    x = utc_axis(ax, t)
    colors = ("tab:orange", "tab:blue", "tab:green", "tab:purple")
    finite = np.isfinite(nis) & (nis > 0)
    for k, size in enumerate(np.unique(dof)):
        color = colors[k % len(colors)]
        used = np.flatnonzero(accepted & finite & (dof == size))
        if not used.size:
            continue
        low, high = chi2_interval(int(size), 0.95)
        outside = (nis[used] < low) | (nis[used] > high)
        # forcing in all the 5 % outside the band would make its edges look crowded; the rare large ones
        # (above the 99.9 % quantile) are the records worth seeing one by one
        rare = chi2_quantile(0.999, int(size))
        picks, stride = sample_indices(used.size, nis[used] > rare)
        keep = used[picks]
        ax.scatter(x[keep], nis[keep], s=4, color=color, lw=0, alpha=0.7,
                   label=f"{size}-value records ({used.size}; {100 * (1 - outside.mean()):.0f} % in their band"
                         f"{_drawn(stride, f'above {rare:.3g}, its 99.9 % quantile')})")
        for bound in (low, high):
            ax.axhline(bound, color=color, ls="--", lw=1.0)
    refused = np.flatnonzero(~accepted & finite)
    if refused.size:
        ax.scatter(x[refused], nis[refused], s=18, marker="x", color="tab:red", lw=0.8,
                   label=f"refused ({refused.size})")
    ax.set_yscale("log")
    ax.set_xlim(np.nanmin(x), np.nanmax(x))
    ax.set_ylabel("NIS")
    ax.plot([], [], color="0.3", ls="--", label="95 % interval of chi2(record size)")
    plain_log_labels(ax)
    under_panel_legend(fig, ax)
    ax.set_title(f"{title}: NIS per record", fontsize=11)
    return fig


#: Names of a record's values by kind (a ``radec_pair``'s four are two targets' RA and Dec).
_COMPONENTS = {"radec": ("RA", "Dec"), "starlight": ("starlight angle", "starlight elevation"),
               "starlight_angle": ("starlight angle",), "starlight_elevation": ("starlight elevation",)}


def residual_panels(kinds: np.ndarray, targets: np.ndarray) -> dict[tuple[str, str], list[tuple[np.ndarray, int]]]:
    """Which record rows and value columns make each residual panel: ``(target, component)`` ->
    ``[(row indices, column), ...]`` in first-seen order (a ``radec_pair``'s columns 0-1 belong to
    its first target, 2-3 to its second)."""
    from ..records import KIND_SIZE

    panels: dict[tuple[str, str], list[tuple[np.ndarray, int]]] = {}
    kinds, targets = np.asarray(kinds, dtype=str), np.asarray(targets, dtype=str)
    for kind in dict.fromkeys(kinds.tolist()):
        for target in dict.fromkeys(targets[kinds == kind].tolist()):
            rows = np.flatnonzero((kinds == kind) & (targets == target))
            if kind == "radec_pair" and "+" in target:
                first, second = target.split("+", 1)
                parts = [(first, "RA", 0), (first, "Dec", 1), (second, "RA", 2), (second, "Dec", 3)]
            else:
                names = _COMPONENTS.get(kind) or tuple(f"{kind} {i}" for i in range(KIND_SIZE.get(kind, 1)))
                parts = [(target, name, i) for i, name in enumerate(names)]
            for owner, name, column in parts:
                panels.setdefault((owner, name), []).append((rows, column))
    return panels


def record_names(data, key: str) -> np.ndarray:
    """Each record's ``kind`` or ``target`` (K,) text from a filter npz: ``record_<key>`` indexes
    ``<key>_names``."""
    return np.asarray(data[f"{key}_names"], dtype=str)[np.asarray(data[f"record_{key}"], dtype=int)]


def residual_figure(data, window_start_tdb_s: float, title: str):
    """Innovations per target and value with the filter's +-3-sigma band (square roots of the innovation
    covariance's diagonal), angles in arcsec, over the whole arc. The y axis spans the RMS window's
    residuals and band; earlier residuals beyond it (the first records, before the filter has
    converged) are drawn as triangles on the axis edge and counted in the legend. None without
    residuals in ``data``."""
    from ..constants import ARCSEC_RAD
    from ..records import KIND_UNIT

    if any(key not in data for key in ("residual", "residual_sigma", "kind_names", "target_names")):
        return None
    t = np.asarray(data["record_t_tdb_s"], dtype=float)
    residual = np.asarray(data["residual"], dtype=float)
    sigma = np.asarray(data["residual_sigma"], dtype=float)
    accepted = np.asarray(data["accepted"], dtype=bool)
    kinds, targets = record_names(data, "kind"), record_names(data, "target")
    panels = residual_panels(kinds, targets)
    if not panels:
        return None
    owners = list(dict.fromkeys(owner for owner, _ in panels))
    cols = max(sum(1 for o, _ in panels if o == owner) for owner in owners)
    fig, axes = new_figure(len(owners), cols, height_in=1.0 + 2.9 * len(owners))
    for ax in axes.ravel():
        ax.set_visible(False)
    for r, owner in enumerate(owners):
        for c, name in enumerate(n for o, n in panels if o == owner):
            ax = axes[r, c]
            ax.set_visible(True)
            parts = panels[(owner, name)]
            rows = np.concatenate([p[0] for p in parts])
            order = np.argsort(t[rows], kind="stable")
            rows = rows[order]
            column = np.concatenate([np.full(p[0].size, p[1]) for p in parts])[order]
            unit = KIND_UNIT.get(str(kinds[rows[0]]), "")
            scale, label = (1.0 / ARCSEC_RAD, "arcsec") if unit == "rad" else (1.0, unit)
            res, sig3 = scale * residual[rows, column], 3.0 * scale * sigma[rows, column]
            x = utc_axis(ax, t[rows], label=(r == len(owners) - 1))
            used = accepted[rows] & np.isfinite(res)
            band = np.isfinite(sig3)
            late = t[rows] >= window_start_tdb_s
            late = late if (late & (used | band)).any() else np.ones(rows.size, dtype=bool)
            top = np.nanmax(np.abs(np.concatenate([res[used & late], sig3[band & late], [0.0]])))
            top = 1.25 * top if top > 0 else 1.0
            keep = np.flatnonzero(band)[envelope_indices(sig3[band])]
            ax.fill_between(x[keep], -sig3[keep], sig3[keep], color=_BAND_COLOR, alpha=0.2, lw=0, label="+-3-sigma")
            inside = used & (np.abs(res) <= top)
            rows_in = np.flatnonzero(inside)
            picks, stride = sample_indices(rows_in.size, np.abs(res[rows_in]) > sig3[rows_in])
            keep = rows_in[picks]
            ax.scatter(x[keep], res[keep], s=5, color="tab:red", lw=0,
                       label=f"accepted ({int(used.sum())}{_drawn(stride, 'beyond 3-sigma')})")
            beyond = used & ~inside
            for side, marker in ((1.0, "^"), (-1.0, "v")):
                edge = beyond & (np.sign(res) == side)
                if edge.any():
                    ax.scatter(x[edge], np.full(int(edge.sum()), side * 0.96 * top), s=22, color="tab:red",
                               marker=marker, lw=0, label=f"beyond the axis ({int(beyond.sum())})"
                               if side == 1.0 or not (beyond & (res > 0)).any() else None)
            refused = ~accepted[rows] & np.isfinite(res)
            if refused.any():
                ax.scatter(x[refused], np.clip(res[refused], -0.97 * top, 0.97 * top), s=18, marker="x", color="k",
                           lw=0.8, label=f"refused ({int(refused.sum())})")
            ax.set_ylim(-top, top)
            if np.nanmax(x) > np.nanmin(x):  # a target with records at one epoch keeps matplotlib's margins
                ax.set_xlim(np.nanmin(x), np.nanmax(x))
            ax.axhline(0.0, color="0.5", lw=0.5)
            ax.set_title(f"{owner}: {name} residual ({label})", fontsize=10)
            ax.legend(fontsize=8, loc="upper right")
    fig.suptitle(f"{title}: measurement residuals (measured minus predicted, before the update)", fontsize=11)
    return fig
