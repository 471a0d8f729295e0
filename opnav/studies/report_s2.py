"""The S2 report page (docs/studies.md#s2-mars-capture): observability per measurement set over the
capture arc, and the switching EKF's errors with the sphere-of-influence crossing marked.

:func:`report_blocks` turns a run's summary and the arrays :func:`opnav.studies.s2.evaluate` saved
(``evaluation.npz``) into the page's paragraphs, tables and figures
(:func:`opnav.studies.report_page.write_page` writes it):

- ``s2_switching_position_errors``, ``s2_switching_velocity_errors``: estimate minus truth per axis
  (km, m/s; each phase about its own origin) with the filter's +-3-sigma, one column per phase on its
  own linear scale, the SOI crossing a dashed line;
- ``s2_switching_nees``: the NEES (6 states) per epoch against the per-epoch 95 % chi-square(6) band;
- ``s2_observability_crb`` (with ``observability = true``): per model and set, the position Cramer-Rao
  bound at the arc start from the measurements up to each epoch;
- ``s2_singular_values``: per model and set, the six singular values of the stripped observability
  matrix (km and m/s units) with the rank threshold.

Tables: the switching filter per phase beside S2 Table 3, Tables 1-2 beside ours, the arc's facts and
the OEMs written. Times are calendar UTC.

From pixels (``--mode images``, :func:`opnav.studies.s2.evaluate_images`): the switching EKF's figures are
those of the angles measured on the frames; a section adds the angle noise each body achieved against
the truth, the errors per phase beside the measurement-mode twin at that noise, the wrong-body check and
``s2_sample_mars`` / ``s2_sample_phobos``: the first frame of each with its true and fitted centre.
"""

from __future__ import annotations

import numpy as np

from ..consistency import chi2_interval
from ..epochs import format_epoch
from .report_campaign import nice_log_ticks
from .report_page import Figure, Table
from .report_plots import figure_png, new_figure, utc_axis, utc_dates


def _utc(t_tdb_s: float) -> str:
    """Epoch ``t_tdb_s`` (TDB s past J2000) as ``YYYY-MM-DD hh:mm:ss`` UTC (without the unit)."""
    return format_epoch(float(t_tdb_s), "utc")[:19].replace("T", " ")


#: The paper, as docs/studies.md cites it.
CITATION = ("Zhu Jiafang, Wang Xinlong, Li Qunsheng, Che Huan: Autonomous navigation model design and analysis "
            "for Mars probe in capture stage. Aero Weaponry 2017(5):18-24")
#: Figure ids of an S2 report: always, and with the observability tables.
FIGURES = ("s2_switching_position_errors", "s2_switching_velocity_errors", "s2_switching_nees")
OBSERVABILITY_FIGURES = ("s2_observability_crb", "s2_singular_values")
#: Relative singular-value threshold of the rank (:func:`opnav.studies.s2_observability.s2_observability`).
RANK_RTOL = 1e-9
_SETS_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red")


def report_blocks(summary: dict, arrays) -> list:
    """The S2 page: paragraphs, :class:`~opnav.studies.report_page.Table` and
    :class:`~opnav.studies.report_page.Figure` blocks from ``summary`` (``summary.json``) and ``arrays``
    (``evaluation.npz``)."""
    facts = summary["facts"]
    settings = summary["run"]["settings"]
    images = "images" in summary
    soi = float(facts["soi_crossing_tdb_s"])
    blocks: list = [
        f"S2 Mars capture ({CITATION}): starlight angles of Mars, Phobos, Deimos and the Sun against three "
        f"stars; one EKF switches from model 1 (heliocentric, set MPD) to model 2 (Mars-centred, set MPS) at "
        f"Mars' sphere of influence, crossed at {_utc(soi)} UTC."
        + (" From pixels: the angles are measured on rendered frames (navigation camera, star tracker, sun "
           "sensor)." if images else ""),
        "Settings: " + ", ".join(f"{key} = {value}" for key, value in settings.items()) + ".",
        "## Switching EKF",
        _table3(summary),
        _switching_errors(arrays, soi, velocity=False),
        _switching_errors(arrays, soi, velocity=True),
        _switching_nees(arrays, soi),
    ]
    if images:
        blocks += ["## From pixels", *_image_blocks(summary, arrays)]
    if "observability" in summary:
        blocks += ["## Observability (S2 Tables 1-2)", *_observability_tables(summary)]
        blocks += [_crb_figure(arrays), _singular_value_figure(arrays)]
    blocks += ["## Arc and outputs", _facts_table(summary), *_estimates(summary)]
    return blocks


#: The switching run's name in a summary: measurement mode, from pixels; and the twin beside the latter.
RUN_NAMES = ("ekf-switching", "ekf-switching from pixels")
TWIN_NAME = "ekf-switching measurement mode at the achieved noise"


def _run(summary: dict) -> dict:
    """The switching run's figures (measurement mode or from pixels)."""
    return next(summary["filters"][name] for name in RUN_NAMES if name in summary["filters"])


def _image_blocks(summary: dict, arrays) -> list:
    """From pixels: achieved angle noise per body, errors per phase beside the twin, wrong-body check, frames."""
    images = summary["images"]
    noise = images["achieved_angle_noise"]
    blocks: list = [
        "Each measured direction (Mars through the star tracker's attitude, each moon through its own frame's "
        "stars, the Sun through the sun sensor and the tracker) becomes two starlight angles against the two "
        "nearby catalog stars whose errors are the least correlated (largest residual correlation "
        f"{images['angle_pair_correlation_max']:.3f}). The twin runs the same epochs and stars in measurement mode "
        "with each body's achieved noise, from the same initial estimate.",
        Table("Starlight-angle noise the frames achieved (against the truth; the angles the filter took)",
              ("body", "angles", "RMS (arcsec)", "mean (arcsec)", "median reported sigma (arcsec)",
               "mean chi-square (1 expected)"),
              tuple((name, str(row["count"]), _fmt(row["rms_arcsec"]), _fmt(row["mean_arcsec"]),
                     _fmt(row["median_sigma_arcsec"]), _fmt(row["chi2_mean"], 2)) for name, row in noise.items())),
    ]
    twin = summary["filters"].get(TWIN_NAME) or {}
    run = _run(summary)
    rows = []
    for phase, figures in run.items():
        if not isinstance(figures, dict) or phase not in twin:
            continue
        other = twin[phase]
        rows.append((phase, _fmt(figures["position_error_mean_km"]), _fmt(other["position_error_mean_km"]),
                     _fmt(figures["position_error_mean_km"] / other["position_error_mean_km"], 2),
                     _fmt(figures["nees_mean"], 2), _fmt(other["nees_mean"], 2)))
    blocks.append(Table("Errors after convergence from pixels beside measurement mode at the achieved noise",
                        ("phase (model, set)", "position error from pixels (km)", "measurement mode (km)",
                         "ratio", "NEES from pixels", "NEES measurement mode"), tuple(rows)))
    wrong = images["wrong_body"]
    blocks.append(Table("Wrong-body check: direction records nearer another body's true centre than their own's",
                        ("body", "records", "wrong body", "gross errors (chi-square(2) > 27.6)",
                         "largest error (arcsec)"),
                        tuple((name, str(row["records"]), str(row["wrong_body"]), str(row.get("gross_errors", "-")),
                               _fmt(row["max_error_arcsec"])) for name, row in wrong.items())))
    refused = images.get("refused_by_the_filter") or {}
    if refused:
        blocks.append(Table("Angles the filter's chi-square gate refused (left out of the achieved noise and the twin)",
                            ("body", "angles", "RMS error (arcsec)", "median reported sigma (arcsec)"),
                            tuple((name, str(row["count"]), _fmt(row["rms_arcsec"]), _fmt(row["median_sigma_arcsec"]))
                                  for name, row in refused.items())))
    blocks.append(f"Frames skipped, with their reasons in summary.json: {len(images['skipped'])}; moons not "
                  f"measured in their frames (hidden by Mars' glare or not found): {len(images['missed'])}; "
                  f"star tracker: {images.get('tracker_stars_misidentified', '-')} misidentified of "
                  f"{images.get('tracker_stars_used', '-')} tracked star uses.")
    for body in ("mars", "phobos"):
        if f"sample_{body}_image" in arrays:
            blocks.append(_sample_figure(arrays, body))
    return blocks


def _sample_figure(arrays, body: str) -> Figure:
    """The sample frame's crop (log stretch above the sky) with the true and fitted centres, and a
    magnified inset around them (their difference is a fraction of a pixel)."""
    image = np.asarray(arrays[f"sample_{body}_image"], float)
    true_xy, measured_xy = arrays[f"sample_{body}_true_xy"], arrays[f"sample_{body}_measured_xy"]
    sky = float(np.median(image))
    shown = np.log1p(np.clip(image - sky, 0.0, None))
    fig, axes = new_figure(1, 1, width_in=6.0, height_in=6.0)
    ax = axes[0, 0]
    ax.grid(False)
    inset = ax.inset_axes([0.62, 0.62, 0.36, 0.36])
    for target in (ax, inset):
        target.imshow(shown, cmap="gray", origin="lower", interpolation="nearest")
        target.plot(*true_xy, "+", color="tab:green", ms=16, mew=1.4, label="true centre")
        if np.all(np.isfinite(measured_xy)):
            target.plot(*measured_xy, "x", color="tab:red", ms=11, mew=1.4, label="fitted centre")
    inset.set_xlim(true_xy[0] - 2.0, true_xy[0] + 2.0)
    inset.set_ylim(true_xy[1] - 2.0, true_xy[1] + 2.0)
    inset.set_xticks([])
    inset.set_yticks([])
    inset.set_title("4 x 4 px", fontsize=8, color="white", pad=2)
    ax.set_xlabel("column in the crop (px)")
    ax.set_ylabel("row in the crop (px)")
    ax.set_title(str(arrays[f"sample_{body}_title"]), fontsize=10)
    ax.legend(loc="lower left", fontsize=8, framealpha=0.8)
    return Figure(f"s2_sample_{body}", f"The first {body} frame around {body} (log stretch above the sky): its true "
                  "centre and the centre the image stage fitted; the inset magnifies 4 x 4 px around them.",
                  figure_png(fig))


def _fmt(value, digits: int = 3) -> str:
    """A figure for a table cell: fixed decimals, or 4 significant digits when very large or small."""
    if value is None:
        return "-"
    value = float(value)
    if not np.isfinite(value):
        return "unbounded" if value > 0 else "-"
    return f"{value:.{digits}f}" if 1e-3 <= abs(value) < 1e5 or value == 0 else f"{value:.4g}"


def _table3(summary: dict) -> Table:
    """The switching filter per phase beside S2 Table 3 (errors after convergence: second half of each phase)."""
    run = _run(summary)
    paper = (summary.get("paper") or {}).get("table3") or {}
    rows = []
    for phase, figures in run.items():
        if not isinstance(figures, dict):
            continue
        printed = paper.get(phase.split()[0])
        rows.append((phase, _fmt(figures["position_error_mean_km"]), _fmt(printed[0]) if printed else "-",
                     _fmt(figures["position_error_var_km2"]), _fmt(printed[1]) if printed else "-",
                     _fmt(1e3 * figures["velocity_error_mean_km_s"], 4), _fmt(1e3 * printed[2], 1) if printed else "-",
                     _fmt(figures["nees_mean"], 2), _fmt(figures["sigma_position_km_at_end"])))
    accepted = run.get("accepted_fraction")
    return Table("Switching EKF after convergence (second half of each phase) beside S2 Table 3",
                 ("phase (model, set)", "position error mean (km)", "paper (km)", "position error variance (km²)",
                  "paper (km²)", "velocity error mean (m/s)", "paper (m/s)", "NEES mean (6 states; 6 expected)",
                  "position 1-sigma at the end (km)"),
                 tuple(rows),
                 note=f"Paper: {CITATION}, Table 3 (its velocity figures read as km/s). "
                      + (f"{100 * accepted:.1f} % of the records accepted. " if isinstance(accepted, float) else "")
                      + "The paper gives neither the angle noise nor the initial error: they are the settings above.")


def _switching_errors(arrays, soi: float, *, velocity: bool) -> Figure:
    """Estimate minus truth per axis with +-3-sigma: one column per phase, each on its own linear scale
    (the Mars-centred phase's errors are a hundred times smaller than the first hours')."""
    t = arrays["switching_t_tdb_s"]
    inside = arrays["switching_inside_soi"].astype(bool)
    scale, unit, offset = (1e3, "m/s", 3) if velocity else (1.0, "km", 0)
    error = scale * arrays["switching_error"][:, offset:offset + 3]
    band = 3.0 * scale * arrays["switching_sigma"][:, offset:offset + 3]
    fig, axes = new_figure(3, 2, height_in=7.2, sharex="col")
    soi_x = utc_dates(np.array([soi]))[0]
    titles = ("phase 1: model 1 (heliocentric), set MPD", "phase 2: model 2 (Mars-centred), set MPS")
    for col, keep in enumerate((~inside, inside)):
        if not np.any(keep):
            continue
        for row, axis in enumerate("xyz"):
            ax = axes[row, col]
            x = utc_axis(ax, t[keep], label=row == 2)
            err, sig = error[keep, row], band[keep, row]
            ax.fill_between(x, -sig, sig, color="tab:blue", alpha=0.2, lw=0, label="±3-sigma")
            ax.plot(x, err, color="tab:red", lw=0.9, label="error")
            ax.axvline(soi_x, color="k", ls="--", lw=1.0, label="SOI crossing")
            lim = 1.05 * float(np.max(np.abs(np.concatenate([err, sig]))))
            ax.set_ylim(-lim, lim)
            ax.set_ylabel(f"{axis} ({unit})")
            if row == 0:
                ax.set_title(titles[col], fontsize=10)
    axes[0, 0].legend(fontsize=8, loc="upper right")
    kind = "velocity" if velocity else "position"
    fig.suptitle(f"S2 switching EKF: {kind} error (estimate minus truth, ICRF; about the Sun in phase 1, about "
                 "Mars in phase 2) with the filter's ±3-sigma", fontsize=11)
    return Figure(f"s2_switching_{kind}_errors",
                  f"{kind.capitalize()} error per ICRF axis with the filter's ±3-sigma, phase 1 (left) and phase 2 "
                  "(right) each on its own scale; the SOI crossing, where the filter changes model, origin and "
                  "measurement set, is dashed. The error should stay inside the band.", figure_png(fig))


def _switching_nees(arrays, soi: float) -> Figure:
    t, values = arrays["switching_t_tdb_s"], arrays["switching_nees"]
    low, high = chi2_interval(6, 0.95)
    fig, axes = new_figure(1, 1, height_in=3.4)
    ax = axes[0, 0]
    x = utc_axis(ax, t)
    ax.axhspan(low, high, color="tab:green", alpha=0.2, label="95 % interval of chi-square(6)")
    ax.semilogy(x, np.maximum(values, 1e-3), ".", ms=2.5, color="tab:purple", label="NEES per epoch")
    ax.axvline(utc_dates(np.array([soi]))[0], color="k", ls="--", lw=1.0, label="SOI crossing (model 1 → 2)")
    ax.set_ylim(0.5 * min(low, float(np.min(values))), 3.0 * max(high, float(np.max(values))))
    nice_log_ticks(ax)
    ax.set_ylabel("NEES (6 states)")
    ax.legend(fontsize=8, loc="upper right", ncol=3)
    inside = float(np.mean((values >= low) & (values <= high)))
    return Figure("s2_switching_nees", f"NEES of the switching EKF at each epoch (6 states; {100 * inside:.0f} % of "
                  "the epochs inside the 95 % chi-square interval, about 95 % for a consistent filter); the SOI "
                  "crossing is dashed.", figure_png(fig))


def _observability_tables(summary: dict) -> list[Table]:
    paper_tables = (summary.get("paper") or {}).get("table1_2") or {}
    tables = []
    for model in (1, 2):
        ours = summary["observability"].get(f"model{model}")
        if not ours:
            continue
        paper = paper_tables.get(str(model)) or {}
        rows = []
        for name, figures in ours.items():
            printed = paper.get(name)
            crb = np.linalg.norm(figures["crb_sigma_position_km"])
            rows.append((name, str(figures["rank"]), str(printed[0]) if printed else "-",
                         f"{figures['max_singular_value']:.4g}", f"{printed[1]:.5g}" if printed else "-",
                         f"{figures['eta']:.4g}" if "eta" in figures else "-", f"{printed[2]:.5g}" if printed else "-",
                         f"{figures['condition_number']:.4g}", f"{printed[3]:.5g}" if printed else "-",
                         _fmt(crb, 2)))
        where = "outside the SOI, heliocentric" if model == 1 else "inside the SOI, Mars-centred"
        tables.append(Table(
            f"Model {model} ({where}) beside S2 Table {model}",
            ("set", "rank", "paper rank", "max singular value", "paper", "eta", "paper eta", "condition number",
             "paper", "position CRB at the arc start (km)"),
            tuple(rows),
            note=f"Paper: {CITATION}, Table {model}. opnav's singular values, eta and condition numbers are for "
                 "states in km and m/s on an hourly grid; the paper states neither its units nor its scaling, so "
                 "those columns compare orderings, not digits. The CRB (RSS of the three axes) does not depend "
                 "on the scaling."))
    return tables


def _crb_figure(arrays) -> Figure:
    fig, axes = new_figure(1, 2, height_in=4.0, sharey=True)
    for col, model in enumerate((1, 2)):
        ax = axes[0, col]
        t = arrays[f"model{model}_t_tdb_s"]
        x = utc_axis(ax, t)
        for name, curve, color in zip(arrays[f"model{model}_sets"], arrays[f"model{model}_crb_position_km"],
                                      _SETS_COLORS):
            shown = np.where(np.isfinite(curve), curve, np.nan)
            ax.semilogy(x, shown, lw=1.4, color=color, label=str(name))
        ax.set_title(f"model {model}: {'heliocentric, before' if model == 1 else 'Mars-centred, after'} the SOI "
                     "crossing", fontsize=10)
        ax.legend(fontsize=8, title="set", title_fontsize=8)
    axes[0, 0].set_ylabel("position CRB at the arc start (km)")
    return Figure("s2_observability_crb", "Position Cramér-Rao bound at each arc's first epoch (RSS of the three "
                  "axes, 1-sigma) from the measurements up to each epoch, per measurement set: the lower and the "
                  "sooner a set's curve falls, the better it pins the state down.", figure_png(fig))


def _singular_value_figure(arrays) -> Figure:
    fig, axes = new_figure(1, 2, height_in=3.8, sharey=True)
    for col, model in enumerate((1, 2)):
        ax = axes[0, col]
        names = [str(n) for n in arrays[f"model{model}_sets"]]
        values = arrays[f"model{model}_singular_values"]
        width = 0.8 / len(names)
        for k, (name, row, color) in enumerate(zip(names, values, _SETS_COLORS)):
            shown = np.where(row > 0, row, np.nan)
            ax.bar(np.arange(1, row.size + 1) + (k - (len(names) - 1) / 2) * width, shown, width, color=color,
                   label=name)
        ax.axhline(RANK_RTOL * float(np.max(values)), color="k", ls=":", lw=1.0, label="rank threshold")
        ax.set_yscale("log")
        ax.set_ylim(top=1e3 * float(np.max(values)))  # room for the legend above the bars
        ax.set_xticks(np.arange(1, values.shape[1] + 1))
        ax.set_xlabel("singular value index")
        ax.set_title(f"model {model}", fontsize=10)
        ax.legend(fontsize=8, ncol=5, loc="upper center")
    axes[0, 0].set_ylabel("singular value (states in km, m/s)")
    return Figure("s2_singular_values", "Singular values of each set's stripped observability matrix (states in km "
                  "and m/s): the ones above the dotted threshold count towards the rank, and the smallest one says "
                  "how weakly the worst direction is seen.", figure_png(fig))


def _facts_table(summary: dict) -> Table:
    facts = summary["facts"]
    run = _run(summary)
    rows = [("SOI crossing (Mars' sphere of influence, 5.773e5 km)", _utc(facts["soi_crossing_tdb_s"])
             + " UTC"),
            ("periapsis (380 km altitude)", _utc(facts["periapsis_tdb_s"]) + " UTC"),
            ("hyperbolic excess speed", f"{facts['v_inf_km_s']:.4f} km/s")]
    if run.get("switch_tdb_s") is not None:
        rows.append(("filter switched model and set", _utc(run["switch_tdb_s"]) + " UTC"))
    if isinstance(run.get("wall_s"), float):
        rows.append(("switching run wall time", f"{run['wall_s']:.1f} s"))
    return Table("The capture arc", ("item", "value"), tuple(rows))


def _estimates(summary: dict) -> list:
    estimates = summary.get("estimates") or {}
    if not estimates:
        return []
    return [Table("Estimated trajectories (CCSDS OEM with covariance)", ("file", "centre", "what"),
                  tuple((e["file"], e["center"].capitalize(),
                         "phase 1, model 1 (MPD)" if name.endswith("model1") else "phase 2, model 2 (MPS)")
                        for name, e in estimates.items()))]
