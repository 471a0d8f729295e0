"""Reports of a study run: ``report.md``, a self-contained ``report.html`` and ``figures/*.png``.

:func:`write_report` writes the report of a study run with the generic filters (S1, S3, the demo)
through :func:`opnav.studies.report_page.write_page`:

1. what was run: the settings, the records, the arc and the RMS window in calendar UTC;
2. per filter the figures of ``summary.json`` in a table (the NEES share in its band is over the
   RMS window, and the column says so), then the paper's figures beside opnav's in a table with the
   study's citation (:data:`CITATIONS`), and the study's other facts as tables and sentences;
3. per filter the plots (:mod:`opnav.studies.report_plots`), ids ``<filter>_errors`` (errors with
   3-sigma in RTN or, on request, ICRF: whole arc on a log scale and the RMS window zoomed),
   ``<filter>_residuals`` (per target, arcsec, +-3-sigma of the innovation), ``<filter>_nis`` (per
   record with its chi-square band) and ``<filter>_nees`` (per epoch, band, window marked); in
   image mode a sample frame per sensor (:mod:`opnav.studies.report_frames`);
4. the image stage's skipped frames and tracking events, and every filter's refused records;
5. the provenance block (command line, run file hash, opnav version, git revision, date, machine).

Long series are drawn from their extremes (:func:`opnav.studies.report_plots.envelope_indices`), so a
30-day run at one record a minute draws in about the time of a short one.
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from ..consistency import chi2_interval
from .common import NEES_STATES
from .report_page import Figure, Provenance, Table, figure_id, markdown_html, provenance, write_page

HOUR_S = 3600.0
#: Frames the error plots of a run report can use (``RunOptions.report_frame``).
REPORT_FRAMES = ("rtn", "icrf")
#: The papers the studies reproduce, as docs/studies.md cites them.
CITATIONS = {
    "s1": "Ma Pengbin, Baoyin Hexi, Mu Junshan: \"Autonomous navigation of Mars probe based on optical observation "
          "of Martian moon\". Optics and Precision Engineering 22(4):863-869, 2014, doi:10.3788/OPE.20142204.0863.",
    "s2": "Zhu Jiafang, Wang Xinlong, Li Qunsheng, Che Huan: \"Autonomous navigation model design and analysis for "
          "Mars probe in capture stage\". Aero Weaponry 2017(5):18-24.",
    "s3": "Wang Changhong, Wang Cunlian, Li Baohua: \"A method to realize GEO satellite autonomous navigation\". "
          "Navigation Positioning and Timing 2014(2):12-19.",
    "s4": "Zhang Heng, Zhang Wei, Chen Xiao: \"Study on deep space time registration method of integrated navigation "
          "system based on celestial angle and velocity measurements\". Journal of Deep Space Exploration "
          "4(4):373-378, 2017, doi:10.15982/j.issn.2095-7777.2017.04.010.",
}


def fmt(value, digits: int = 3) -> str:
    """A figure as report text: ``-`` for None, floats to ``digits`` decimals (two significant digits when
    that would show none, scientific at 1e5 and above or below 1e-3, but not zero), lists joined with commas."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if not np.isfinite(value):
            return str(value)
        if value != 0.0 and (abs(value) >= 1e5 or abs(value) < 1e-3):
            return f"{value:.3e}"
        if value != 0.0 and abs(value) < 10.0 ** -digits:  # a small figure keeps two significant digits
            return f"{value:.2g}"
        return f"{value:.{digits}f}"
    if isinstance(value, (list, tuple)):
        return ", ".join(fmt(v, digits) for v in value)
    return str(value)


def utc(t_tdb_s: float) -> str:
    """``t_tdb_s`` (TDB s past J2000) as calendar UTC to the second, for a report."""
    from ..epochs import format_epoch

    return format_epoch(float(t_tdb_s), "utc", precision=0).replace("T", " ") + " UTC"


def settings_table(settings: dict, pairs: int = 3) -> Table:
    """The run's settings, ``pairs`` (setting, value) pairs a row, so a page shows them in a few lines."""
    items = [(key, value if isinstance(value, str) else (f"{value:g}" if isinstance(value, float) else fmt(value)))
             for key, value in settings.items()]
    items += [("", "")] * (-len(items) % pairs)
    rows = tuple(tuple(cell for item in items[i:i + pairs] for cell in item) for i in range(0, len(items), pairs))
    return Table("Settings", ("setting", "value") * pairs, rows)


def results_table(summary: dict) -> Table:
    """Each filter's figures over the RMS window (and its NIS over every accepted record)."""
    header = ("filter", "position RMS (km)", "radial / along / cross RMS (km)", "velocity RMS (m/s)",
              "converged after (h)", "NEES mean: window / whole arc",
              "share of epochs with NEES in its 95 % band: window / whole arc",
              "NIS per dof (accepted records)", "NIS per dof 95 % band", "accepted / records", "flags", "wall (s)")
    rows = []
    for name, f in summary["filters"].items():
        band = f.get("nis_band95_per_dof")
        converged = f.get("converged_after_s")
        rtn = f.get("position_rms_rtn_km")
        rows.append((name, fmt(f["position_rms_km"]), "-" if rtn is None else " / ".join(fmt(v) for v in rtn),
                     fmt(f["velocity_rms_m_s"], 4), fmt(None if converged is None else converged / HOUR_S, 1),
                     f"{fmt(f['nees_mean'], 2)} / {fmt(f.get('nees_mean_arc'), 2)}",
                     f"{fmt(f['nees_fraction_in_95'], 2)} / {fmt(f.get('nees_fraction_in_95_arc'), 2)}",
                     fmt(f["nis_mean_per_dof"], 3),
                     "-" if band is None else f"{band[0]:.3f} to {band[1]:.3f}", f"{f['accepted']} / {f['records']}",
                     ", ".join(f["consistency"]["flags"]) or "none", fmt(f["wall_s"], 1)))
    return Table("Results", header, tuple(rows),
                 note=f"RMS over the RMS window; NEES of {NEES_STATES} states over the window and over the whole "
                      "arc, each epoch against the 95 % interval of chi-square(6) "
                      f"({'%.2f to %.2f' % chi2_interval(NEES_STATES, 0.95)}): a consistent filter has about 0.95 "
                      "of its epochs inside and a mean near 6 (successive epochs are correlated, so one run's mean "
                      "strays further than independent draws would); NIS summed over every accepted record and "
                      "divided by its degrees of freedom, against the 95 % band of that ratio.")


def _window_errors(out: Path, name: str, start: float) -> dict:
    """Smallest and largest position (km) and velocity (m/s) error per ICRF axis over the RMS window."""
    data = np.load(out / "filters" / f"{name}.npz")
    err = np.asarray(data["error"])[np.asarray(data["t_tdb_s"]) >= start]
    return {"position_km": (float(err[:, :3].min()), float(err[:, :3].max())),
            "velocity_m_s": (float(1e3 * err[:, 3:].min()), float(1e3 * err[:, 3:].max()))}


def paper_table(out: Path, summary: dict) -> Table | None:
    """The paper's figures beside opnav's (S1: the RMS over the last 15 days; S3: Table 4's converged
    error ranges per axis), with the study's citation; a generic listing for other shapes."""
    paper = summary.get("paper") or {}
    if not paper:
        return None
    study = summary["run"]["study"]
    filters = list(summary["filters"])
    note = f"Paper: {CITATIONS.get(study, study.upper())}" + (f" {paper['note']}." if paper.get("note") else "")
    if "position_rms_km" in paper:
        header = ("quantity", "paper", *(f"opnav {f}" for f in filters))
        rows = [("position RMS over the RMS window (km)", fmt(paper["position_rms_km"]),
                 *(fmt(summary["filters"][f]["position_rms_km"]) for f in filters)),
                ("velocity RMS over the RMS window (m/s)", fmt(paper.get("velocity_rms_m_s"), 4),
                 *(fmt(summary["filters"][f]["velocity_rms_m_s"], 4) for f in filters))]
        return Table("Paper beside opnav", header, tuple(rows), note=note)
    if "table4" in paper:
        rows = []
        for name, ranges in paper["table4"].items():
            ours = _window_errors(out, name, summary["window_start_tdb_s"]) if name in filters else None
            for key, label in (("position_km", "position error range per axis (km)"),
                               ("velocity_m_s", "velocity error range per axis (m/s)")):
                low, high = ranges[key]
                mine = "not run" if ours is None else f"{ours[key][0]:.3f} to {ours[key][1]:.3f}"
                rows.append((name, label, f"{low:g} to {high:g}", mine))
        return Table("Paper beside opnav", ("filter", "quantity", "paper (converged)", "opnav (RMS window, ICRF axes)"),
                     tuple(rows), note=note)
    rows = tuple((label, fmt(value)) for label, value in readable_items(paper) if label != "note")
    return Table("Paper", ("quantity", "paper"), rows, note=note)


_UNITS = (("_arcsec", "arcsec"), ("_km_s", "km/s"), ("_m_s", "m/s"), ("_km", "km"), ("_deg", "deg"),
          ("_tdb_s", "TDB s"), ("_s", "s"))


def readable_key(key: str) -> str:
    """``rms_arcsec`` -> ``rms (arcsec)``: a summary key as a label with its unit."""
    for suffix, unit in _UNITS:
        if key.endswith(suffix):
            return f"{key[: -len(suffix)].replace('_', ' ')} ({unit})"
    return key.replace("_", " ")


def readable_items(value, prefix: str = ""):
    """(label, leaf) of nested tables with readable labels (``a, b: c (km)``); a list of tables counts
    as a leaf described by its length."""
    if isinstance(value, dict):
        for key, item in value.items():
            label = readable_key(str(key))
            yield from readable_items(item, f"{prefix}, {label}" if prefix else label)
    elif isinstance(value, (list, tuple)) and value and isinstance(value[0], dict):
        yield prefix, f"{len(value)} entries (summary.json)"
    else:
        yield prefix, value


#: Facts the report shows in their own place (sentence, figure, section), not in the facts table.
_OWN_PLACE = ("window", "frames_skipped", "tracking", "sample_frame", "sample_frames", "measurement_errors")


def facts_blocks(summary: dict) -> list:
    """The study's facts: per-target measurement errors as a table, the rest as a two-column table."""
    facts = summary.get("facts") or {}
    blocks: list = []
    errors = facts.get("measurement_errors")
    if isinstance(errors, dict) and errors and all(isinstance(v, dict) and "rms_arcsec" in v for v in errors.values()):
        rows = tuple((target, str(e["count"]), fmt(e["rms_arcsec"], 4), fmt(e["mean_arcsec"], 4),
                      fmt(e["median_sigma_arcsec"], 4), fmt(e["chi2_mean"], 2), fmt(e.get("chi2_mean_interval_99"), 2),
                      fmt(e.get("chi2_max"), 1)) for target, e in errors.items())
        blocks.append(Table("Image stage: measured RA/Dec against the truth", (
            "target", "records", "RMS RA, Dec (arcsec)", "mean RA, Dec (arcsec)", "median reported 1-sigma (arcsec)",
            "chi-square mean", "99 % interval of that mean", "chi-square max"), rows,
            note="Each record's error against the truth's apparent direction, with the covariance the image stage "
                 "reported; a chi-square mean inside its interval says the reported sigmas are right."))
    elif isinstance(errors, dict) and errors:
        blocks.append(Table("Image stage: measured records against the truth", ("quantity", "value"),
                            tuple((label, fmt(v, 4)) for label, v in readable_items(errors))))
    rows = tuple((label, fmt(v, 4)) for label, v in readable_items({k: v for k, v in facts.items()
                                                                   if k not in _OWN_PLACE}))
    if rows:
        blocks.append(Table("Facts of this run", ("fact", "value"), rows))
    return blocks


def write_report(out: Path, summary: dict, *, frame: str = "rtn", prov: Provenance | None = None) -> None:
    """Write ``report.md``, ``report.html`` and ``figures/*.png`` of a run (module notes) from
    ``summary`` and ``out/filters/<name>.npz``; ``frame`` (:data:`REPORT_FRAMES`) is the error plots'
    frame; ``prov`` the provenance (None: taken now, without a command line or run file)."""
    from .report_frames import sample_frames
    from .report_plots import error_figure, figure_png, nees_figure, nis_figure, residual_figure

    out = Path(out)
    run = summary["run"]
    meas = summary["measurements"]
    start = summary["window_start_tdb_s"]
    window = (summary.get("facts") or {}).get("window", "the study's window")
    blocks: list = [
        settings_table(run["settings"]),
        f"**Measurements.** {meas['records']} records at {meas['epochs']} epochs ({', '.join(meas['kinds'])}; "
        f"targets {', '.join(meas['targets'])}) from {utc(meas['first_epoch_tdb_s'])} to "
        f"{utc(meas['last_epoch_tdb_s'])}, mode {summary.get('mode', 'measurements')}. RMS window: {window}, "
        f"from {utc(start)}.",
        results_table(summary)]
    paper = paper_table(out, summary)
    if paper is not None:
        blocks.append(paper)
    blocks += facts_blocks(summary)
    center = _center(out)
    for name in summary["filters"]:
        data = np.load(out / "filters" / f"{name}.npz")
        title = f"{run['name']}, {name}"
        blocks.append(f"## {name}")
        if frame == "rtn" and "error_rtn" not in data:
            frame_used = "icrf"  # a filter stage saved before RTN errors were: its ICRF errors
        else:
            frame_used = frame
        blocks.append(Figure(f"{figure_id(name)}_errors", f"Estimate minus truth ({frame_used.upper()}) with the filter's 3-sigma: "
                             "top rows the whole arc on a log scale (the RMS window shaded), below them the RMS window; "
                             "the error should stay inside the band, about 99.7 % of the time.",
                             figure_png(error_figure(data, frame_used, start, center, title))))
        residuals = residual_figure(data, start, title)
        if residuals is not None:
            blocks.append(Figure(f"{figure_id(name)}_residuals", "Innovations per target and value against the filter's "
                                 "+-3-sigma of each (its innovation covariance): they should be centred on zero, "
                                 "inside the band, with no trend.", figure_png(residuals)))
        else:
            blocks.append(f"No residual plot: filters/{name}.npz has no innovation sigmas (made by an older opnav; "
                          f"delete filters/{name}.json to run the filter again).")
        blocks.append(Figure(f"{figure_id(name)}_nis", "NIS of every record against the 95 % interval of chi-square(record "
                             "size): about 95 % of the points should lie between the dashed lines of their colour.",
                             figure_png(nis_figure(data, title))))
        blocks.append(Figure(f"{figure_id(name)}_nees",
                             f"NEES of the {NEES_STATES}-state error at every epoch against the 95 % interval of "
                             f"chi-square({NEES_STATES}); the results table counts the share inside over the RMS "
                             "window (shaded) and over the whole arc.",
                             figure_png(nees_figure(data, start, NEES_STATES, title))))
    frames = sample_frames(out, summary)
    if frames:
        blocks.append("## Image stage: sample frames")
        blocks += frames
    lines = _skipped_frame_lines(summary) + _tracking_lines(summary) + _refused_lines(summary)
    if lines:
        blocks.append("\n".join(lines))
    title = f"{run['name']} ({run['study'].upper()}, seed {run['seed']}, {summary.get('mode', 'measurements')} mode)"
    write_page(out, title, blocks, prov if prov is not None else provenance(None, None))


def _center(out: Path) -> str:
    """The origin of the run's states (``simulation.json``'s ``center``), or ``centre body``."""
    import json

    try:
        return str(json.loads((out / "simulation.json").read_text())["center"])
    except (OSError, ValueError, KeyError):
        return "centre body"


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


def markdown_page(title: str, lines: list[str]) -> str:
    """A self-contained HTML page of simple Markdown ``lines`` (:func:`~opnav.studies.report_page.markdown_html`), so each
    ``.md`` a run or campaign writes has an ``.html`` beside it."""
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;margin:1em 0}"
            "td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px}</style></head><body>"
            + markdown_html(lines) + "</body></html>")


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
