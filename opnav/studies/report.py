"""Reports of a study run: ``report.md`` and a self-contained ``report.html`` (figures embedded).

For each filter: the figures of ``summary.json`` beside the paper's, the position
and velocity errors per axis with the filter's 3-sigma envelope, NEES with its
per-epoch 95 % interval, and the NIS of the records (a running mean over 50
records per degree of freedom with its band). Figures are PNG files in
``DIR/figures`` and inlined (base64) in the HTML; long series are drawn from their
extremes in :data:`PLOT_POINTS` runs (:func:`envelope_indices`), which look the same.
"""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path

import numpy as np

from ..consistency import chi2_mean_bounds
from ..records import atomic_write_text
from .common import NEES_STATES

HOUR_S = 3600.0
#: Samples a plotted series keeps at most (its extremes are kept: :func:`envelope_indices`); a panel is a
#: few hundred pixels wide, and a 30-day run at one record a minute has 43,200 epochs and 86,400 records.
PLOT_POINTS = 4000


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


def _figure_png(fig) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    return buffer.getvalue()


def _error_figure(name: str, data, t0: float) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hours = (data["t_tdb_s"] - t0) / HOUR_S
    fig, axes = plt.subplots(2, 3, figsize=(12, 5.5), sharex=True, constrained_layout=True)
    labels = ("x", "y", "z")
    for row, (scale, unit, offset) in enumerate(((1.0, "km", 0), (1e3, "m/s", 3))):
        for col in range(3):
            ax = axes[row, col]
            err = scale * data["error"][:, offset + col]
            sig = 3.0 * scale * data["sigma"][:, offset + col]
            keep = envelope_indices(sig)
            ax.fill_between(hours[keep], -sig[keep], sig[keep], color="tab:blue", alpha=0.2, lw=0, label="3-sigma")
            keep = envelope_indices(err)
            ax.plot(hours[keep], err[keep], color="tab:red", lw=0.8, label="error")
            lim = np.nanpercentile(np.abs(np.concatenate([err, sig])[len(err) // 10:]), 99) * 1.3 or 1.0
            ax.set_ylim(-lim, lim)
            ax.set_title(f"{'position' if row == 0 else 'velocity'} {labels[col]} ({unit})", fontsize=9)
            ax.tick_params(labelsize=8)
            ax.locator_params(axis="x", nbins=5)
            if row == 1:
                ax.set_xlabel("hours from start", fontsize=8)
    axes[0, 0].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{name}: estimate minus truth with the filter's 3-sigma", fontsize=10)
    png = _figure_png(fig)
    plt.close(fig)
    return png


def _consistency_figure(name: str, data, t0: float) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 3.2), constrained_layout=True)
    hours = (data["t_tdb_s"] - t0) / HOUR_S
    lo, hi = chi2_mean_bounds(NEES_STATES, 1, 0.95)
    shown = np.maximum(data["nees"], 1e-3)
    keep = envelope_indices(shown)
    ax1.semilogy(hours[keep], shown[keep], lw=0.7, color="tab:purple")
    ax1.axhspan(lo, hi, color="tab:green", alpha=0.2, label=f"95 % of chi2({NEES_STATES})")
    ax1.set_title(f"NEES ({NEES_STATES} states)", fontsize=9)
    ax1.set_xlabel("hours from start", fontsize=8)
    ax1.legend(fontsize=7)
    used = data["accepted"] & np.isfinite(data["nis"])
    nis, dof, t = data["nis"][used], data["dof"][used], data["record_t_tdb_s"][used]
    window = min(50, max(1, nis.size))
    if nis.size:
        kernel = np.ones(window)
        running = np.convolve(nis, kernel, "valid") / np.convolve(dof, kernel, "valid")
        total = int(round(np.mean(dof) * window))
        band = chi2_mean_bounds(1, total, 0.95)
        keep = envelope_indices(running)
        ax2.plot((t[window - 1:][keep] - t0) / HOUR_S, running[keep], lw=0.7, color="tab:orange")
        ax2.axhspan(*band, color="tab:green", alpha=0.2, label=f"95 % band ({window} records)")
        ax2.legend(fontsize=7)
    ax2.set_title("NIS per degree of freedom, running mean", fontsize=9)
    ax2.set_xlabel("hours from start", fontsize=8)
    for ax in (ax1, ax2):
        ax.tick_params(labelsize=8)
        ax.locator_params(axis="x", nbins=6)
    fig.suptitle(name, fontsize=10)
    png = _figure_png(fig)
    plt.close(fig)
    return png


def _fmt(value, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}" if abs(value) < 1e5 else f"{value:.3e}"
    return str(value)


def _table(summary: dict) -> list[list[str]]:
    rows = [["filter", "position RMS (km)", "R / T / N RMS (km)", "velocity RMS (m/s)", "converged after (h)", "NEES mean",
             "NEES in 95 % (share)", "NIS/dof", "NIS band", "accepted", "flags", "wall (s)"]]
    for name, f in summary["filters"].items():
        band = f.get("nis_band95_per_dof")
        converged = f.get("converged_after_s")
        rtn = f.get("position_rms_rtn_km")
        rows.append([name, _fmt(f["position_rms_km"]), "-" if rtn is None else " / ".join(_fmt(v) for v in rtn),
                     _fmt(f["velocity_rms_m_s"], 4),
                     _fmt(None if converged is None else converged / HOUR_S, 1), _fmt(f["nees_mean"], 2),
                     _fmt(f["nees_fraction_in_95"], 2), _fmt(f["nis_mean_per_dof"], 3),
                     "-" if band is None else f"{band[0]:.3f}-{band[1]:.3f}", f"{f['accepted']}/{f['records']}",
                     ", ".join(f["consistency"]["flags"]) or "none", _fmt(f["wall_s"], 1)])
    return rows


def _tracking_lines(summary: dict) -> list[str]:
    """Image mode with tracking: acquisitions and losses of lock, each loss with its frame and reason."""
    tracking = summary.get("facts", {}).get("tracking")
    if not tracking:
        return []
    lines = ["## Image stage: tracking", "",
             f"{tracking['acquisitions']} full-frame acquisition(s), {tracking['losses_of_lock']} loss(es) of lock, "
             f"{tracking['failed_acquisitions']} failed acquisition(s).", ""]
    losses = [e for e in tracking["events"] if e["event"] != "acquired"]
    if losses:
        lines += ["| frame | event | reason |", "|---|---|---|"]
        lines += [f"| {e['frame']} | {e['event']} | {e.get('reason', '')} |" for e in losses]
        lines.append("")
    return lines


def write_report(out: Path, summary: dict) -> None:
    """Write ``report.md``, ``report.html`` and ``figures/*.png`` for ``summary`` (and ``out/filters/*.npz``)."""
    out = Path(out)
    figures = {}
    t0 = summary["measurements"]["first_epoch_tdb_s"]
    for name in summary["filters"]:
        data = np.load(out / "filters" / f"{name}.npz")
        figures[f"{name}_errors"] = _error_figure(name, data, t0)
        figures[f"{name}_consistency"] = _consistency_figure(name, data, t0)
    sample = summary["facts"].get("sample_frame")
    if sample and Path(sample).exists():
        figures["sample_frame"] = sample_frame_png(sample, f"sample frame {Path(sample).name}: detections (cyan), "
                                                           "true target centres (green), measured moons (red)")
    (out / "figures").mkdir(exist_ok=True)
    for key, png in figures.items():
        path = out / "figures" / f"{key}.png"
        tmp = path.with_suffix(".tmp")
        tmp.write_bytes(png)
        tmp.replace(path)
    run = summary["run"]
    rows = _table(summary)
    settings = ", ".join(f"{k} = {v}" for k, v in run["settings"].items())
    paper = summary.get("paper", {})
    md = [f"# {run['name']} ({run['study'].upper()}, seed {run['seed']})", "", f"Settings: {settings}.", "",
          f"Measurements: {summary['measurements']['records']} records at {summary['measurements']['epochs']} epochs "
          f"({', '.join(summary['measurements']['kinds'])}; {', '.join(summary['measurements']['targets'])}); "
          f"RMS window: {summary['facts'].get('window', 'study window')}.", "",
          "| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0])]
    md += ["| " + " | ".join(r) + " |" for r in rows[1:]]
    md += ["", f"Paper: `{paper}`", ""]
    facts = {k: v for k, v in summary["facts"].items() if k not in ("window", "frames_skipped")}
    if facts:
        md += [f"Facts: `{facts}`", ""]
    refused = _skipped_frame_lines(summary) + _tracking_lines(summary) + _refused_lines(summary)
    md += refused
    for key in figures:
        md.append(f"![{key}](figures/{key}.png)")
    atomic_write_text(out / "report.md", "\n".join(md) + "\n")
    cells = "".join("<tr>" + "".join(f"<{'th' if i == 0 else 'td'}>{html.escape(c)}</{'th' if i == 0 else 'td'}>"
                                     for c in row) + "</tr>" for i, row in enumerate(rows))
    images = "".join(f'<h3>{html.escape(key)}</h3><img alt="{html.escape(key)}" style="max-width:100%" '
                     f'src="data:image/png;base64,{base64.b64encode(png).decode()}">' for key, png in figures.items())
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(run['name'])}</title>"
            "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}"
            "td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px}</style></head><body>"
            f"<h1>{html.escape(run['name'])} ({run['study'].upper()}, seed {run['seed']})</h1>"
            f"<p>Settings: {html.escape(settings)}.</p><table>{cells}</table>"
            f"<p>Paper: <code>{html.escape(str(paper))}</code></p>"
            + (f"<p>Facts: <code>{html.escape(str(facts))}</code></p>" if facts else "")
            + markdown_body(refused) + f"{images}</body></html>")
    atomic_write_text(out / "report.html", page)


#: Refused records shown one per row in a report (every one is in filters/<name>.json, up to 1000).
REPORT_REFUSED_ROWS = 200


def _skipped_frame_lines(summary: dict) -> list[str]:
    """Markdown: every frame the image stage did not measure, with its reason (the first REPORT_REFUSED_ROWS)."""
    skipped = summary.get("facts", {}).get("frames_skipped") or {}
    if not isinstance(skipped, dict) or not skipped:
        return []
    lines = [f"## Image stage: {len(skipped)} frame(s) not measured", "", "| frame | reason |", "|---|---|"]
    lines += [f"| {frame} | {reason} |" for frame, reason in list(skipped.items())[:REPORT_REFUSED_ROWS]]
    if len(skipped) > REPORT_REFUSED_ROWS:
        lines.append(f"| ... | {len(skipped) - REPORT_REFUSED_ROWS} more in summary.json (facts.frames_skipped) |")
    return lines + [""]


def _refused_lines(summary: dict) -> list[str]:
    """Markdown: every refused record of each filter with its reason (the first REPORT_REFUSED_ROWS)."""
    from ..epochs import format_epoch

    lines: list[str] = []
    for name, figures in summary["filters"].items():
        refused = figures.get("refused") or []
        if not refused:
            continue
        count = figures.get("refused_count", len(refused))
        lines += [f"## {name}: {count} records refused", "", "| epoch (UTC) | kind | target | reason |",
                  "|---|---|---|---|"]
        lines += [f"| {format_epoch(r['t_tdb_s'], 'utc')} | {r['kind']} | {r['target']} | {r['reason']} |"
                  for r in refused[:REPORT_REFUSED_ROWS]]
        if count > REPORT_REFUSED_ROWS:
            lines.append(f"| ... | | | {count - REPORT_REFUSED_ROWS} more in filters/{name}.json |")
        lines.append("")
    return lines


def flat_items(value, prefix: str = ""):
    """(dotted key, leaf) of every value in nested tables: ``{"a": {"b": 1}}`` gives ``("a.b", 1)``."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield from flat_items(item, f"{prefix}.{key}" if prefix else str(key))
    else:
        yield prefix, value


def write_table_report(out: Path, summary: dict) -> None:
    """``report.md`` and ``report.html`` of a study with its own evaluation: every figure as a table row."""
    run = summary["run"]
    rows = [(key, _fmt(value, 4) if isinstance(value, float) else str(value))
            for section in ("filters", "observability", "facts", "paper") if section in summary
            for key, value in flat_items(summary[section], section)]
    settings = ", ".join(f"{k} = {v}" for k, v in run["settings"].items())
    md = [f"# {run['name']} ({run['study'].upper()}, seed {run['seed']})", "", f"Settings: {settings}.", "",
          "| figure | value |", "|---|---|"] + [f"| {k} | {v} |" for k, v in rows]
    atomic_write_text(Path(out) / "report.md", "\n".join(md) + "\n")
    atomic_write_text(Path(out) / "report.html", markdown_page(run["name"], md))


def sample_frame_png(path: str, title: str) -> bytes:
    """A rendered frame (log stretch) with the image stage's detections, the targets' true centres and
    the measured moon positions overlaid."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..catalog import load_catalog
    from ..ephemeris import default_ephemeris
    from ..image.pipeline import PipelineOptions, process_frame
    from ..render.frames_io import read_frame

    stored = read_frame(path)
    result = process_frame(path, catalog=load_catalog(), ephemeris=default_ephemeris(),
                           options=PipelineOptions(targets=("phobos", "deimos")), rng=np.random.default_rng(0))
    image = np.asarray(stored.image, dtype=float)
    low, high = np.percentile(image, [5.0, 99.9])
    fig, ax = plt.subplots(figsize=(7, 7), constrained_layout=True)
    ax.imshow(np.log1p(np.clip(image - low, 0.0, None)), cmap="gray", origin="lower",
              vmax=np.log1p(max(high - low, 1.0)))
    xy = np.asarray(result.sources.xy, dtype=float).reshape(-1, 2)[np.asarray(result.sources.ok, dtype=bool)]
    ax.scatter(xy[:, 0], xy[:, 1], s=60, facecolors="none", edgecolors="tab:cyan", lw=0.8,
               label=f"detections ({len(xy)}; {result.n_stars_matched} stars identified)")
    placed: list = []
    line_px = 0.022 * image.shape[0]  # one 8-point text line on the 7-inch figure, in frame pixels

    def label(text: str, xy, color: str, up: bool) -> None:
        # a moon beside Mars puts several labels on one spot: move each one a line further until it
        # clears those already placed, instead of overprinting them
        x, y = float(xy[0]) + 0.01 * image.shape[1], float(xy[1]) + (1.0 if up else -1.5) * line_px
        while any(abs(y - py) < line_px and abs(x - px) < 0.15 * image.shape[1] for px, py in placed):
            y += line_px if up else -line_px
        placed.append((x, y))
        ax.annotate(text, xy, xytext=(x, y), color=color, fontsize=8)

    for target in stored.truth.targets:
        if np.all(np.isfinite(target.xy_cof_px)):
            ax.plot(*target.xy_cof_px, "+", color="tab:green", ms=14, mew=1.2)
            label(f"{target.name} (true)", target.xy_cof_px, "tab:green", up=True)
    for record in result.records:
        if record.kind == "radec" and "xy_px" in record.extra:
            ax.plot(*record.extra["xy_px"], "x", color="tab:red", ms=10, mew=1.2)
            label(f"{record.target} (measured)", record.extra["xy_px"], "tab:red", up=False)
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    ax.tick_params(labelsize=7)
    png = _figure_png(fig)
    plt.close(fig)
    return png


def markdown_page(title: str, lines: list[str]) -> str:
    """A self-contained HTML page of simple Markdown ``lines`` (:func:`markdown_body`), so each
    ``.md`` a run or campaign writes has an ``.html`` beside it."""
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;margin:1em 0}"
            "td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px}</style></head><body>"
            + markdown_body(lines) + "</body></html>")


def markdown_body(lines: list[str]) -> str:
    """HTML of simple Markdown ``lines``: headings, pipe tables (first row as header), paragraphs."""
    body: list[str] = []
    table: list[list[str]] = []

    def flush() -> None:
        if table:
            rows = [r for r in table if not all(set(c) <= set("-: ") for c in r)]
            body.append("<table>" + "".join(
                "<tr>" + "".join(f"<{tag}>{html.escape(c)}</{tag}>" for c in r) + "</tr>"
                for r, tag in zip(rows, ["th"] + ["td"] * len(rows))) + "</table>")
            table.clear()

    for line in lines:
        text = line.strip()
        if text.startswith("|"):
            table.append([c.strip() for c in text.strip("|").split("|")])
            continue
        flush()
        if text.startswith("#"):
            level = min(len(text) - len(text.lstrip("#")), 6)
            body.append(f"<h{level}>{html.escape(text[level:].strip())}</h{level}>")
        elif text:
            body.append(f"<p>{html.escape(text)}</p>")
    flush()
    return "".join(body)


def observability_figures(study) -> dict:
    """JSON-ready figures of an S2 observability study (:class:`opnav.studies.s2_observability.S2Study`):
    per angle set its PWCS rank, singular values, eta, condition number, Cramer-Rao bound at the arc
    start (position km, velocity m/s), column scales and the paper's entries; per target its
    occultations, eclipses and smallest Sun separation (deg)."""
    from ..epochs import format_epoch
    from .s2_observability import S2_PAPER_TABLES

    return {
        "model": study.model,
        "sigma_arcsec": study.sigma_arcsec,
        "stars_hip": list(study.star_hip),
        "arc_start_tdb": format_epoch(float(study.t_tdb_s[0]), "tdb"),
        "arc_end_tdb": format_epoch(float(study.t_tdb_s[-1]), "tdb"),
        "epochs": int(study.t_tdb_s.size),
        "sets": [
            {
                "name": rep.name,
                "rank": rep.rank,
                "singular_values": rep.singular_values.tolist(),
                "eta": rep.eta,
                "condition_number": rep.condition_number,
                "crb_position_km": rep.crb_sigma[:3].tolist(),
                "crb_velocity_m_s": (rep.crb_sigma[3:6] * 1e3).tolist(),
                "column_scale_km_km_s": rep.column_scale.tolist(),
                "paper": list(S2_PAPER_TABLES[study.model].get(rep.name, ())),
            }
            for rep in study.reports
        ],
        "visibility": [
            {
                "target": vis.target,
                "occulted_epochs": int(np.count_nonzero(vis.occulted)),
                "eclipsed_epochs": int(np.count_nonzero(vis.eclipsed)),
                "min_sun_separation_deg": float(np.degrees(vis.sun_separation_rad.min())),
            }
            for vis in study.visibility
        ],
    }


def observability_paper_columns(model: int) -> dict[str, tuple[str, ...]]:
    """S2's Table 1 (``model`` 1) or 2 entries as short strings for :func:`opnav.observability.format_table`."""
    from .s2_observability import S2_PAPER_TABLES

    return {name: tuple(f"{value:.5g}" for value in row) for name, row in S2_PAPER_TABLES[model].items()}
