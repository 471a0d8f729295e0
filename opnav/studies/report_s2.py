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
    soi = float(facts["soi_crossing_tdb_s"])
    blocks: list = [
        f"S2 Mars capture ({CITATION}): starlight angles of Mars, Phobos, Deimos and the Sun against three "
        f"stars; one EKF switches from model 1 (heliocentric, set MPD) to model 2 (Mars-centred, set MPS) at "
        f"Mars' sphere of influence, crossed at {_utc(soi)} UTC.",
        "Settings: " + ", ".join(f"{key} = {value}" for key, value in settings.items()) + ".",
        "## Switching EKF",
        _table3(summary),
        _switching_errors(arrays, soi, velocity=False),
        _switching_errors(arrays, soi, velocity=True),
        _switching_nees(arrays, soi),
    ]
    if "observability" in summary:
        blocks += ["## Observability (S2 Tables 1-2)", *_observability_tables(summary)]
        blocks += [_crb_figure(arrays), _singular_value_figure(arrays)]
    blocks += ["## Arc and outputs", _facts_table(summary), *_estimates(summary)]
    return blocks


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
    run = summary["filters"]["ekf-switching"]
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
    run = summary["filters"]["ekf-switching"]
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
