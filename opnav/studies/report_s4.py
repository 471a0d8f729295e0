"""The S4 report page (docs/studies.md#s4-mars-approach): the exact, registered and unregistered
federated runs against their own sigmas, showing the divergence the study is about.

:func:`report_blocks` turns a run's summary and the arrays :func:`opnav.studies.s4.evaluate` saved
(``evaluation.npz``: fusion epochs, and per case the fused estimate's error and 1-sigma) into the
page (:func:`opnav.studies.report_page.write_page` writes it):

- ``s4_errors``: position and velocity error magnitudes of the three runs with each run's own
  3-sigma (RSS of the three axes), log scale;
- ``s4_error_in_sigma``: the worst axis's error in units of that axis's 1-sigma at every fusion epoch,
  with the 3-sigma line: a run above it is overconfident, i.e. diverged in the sense of S4;
- ``s4_position_axes``: the position error per ICRF axis with +-3-sigma, one row per run.

Tables: the paper's finding beside opnav's per case, the final figures, the arc's facts and the OEMs.
Times are calendar UTC.
"""

from __future__ import annotations

import numpy as np

from ..epochs import format_epoch
from .report_page import Figure, Table
from .report_plots import envelope_indices, figure_png, new_figure, utc_axis


def _utc(t_tdb_s: float) -> str:
    """Epoch ``t_tdb_s`` (TDB s past J2000) as ``YYYY-MM-DD hh:mm:ss`` UTC (without the unit)."""
    return format_epoch(float(t_tdb_s), "utc")[:19].replace("T", " ")


#: The paper, as docs/studies.md cites it.
CITATION = ("Zhang Heng, Zhang Wei, Chen Xiao: Study on deep space time registration method of integrated "
            "navigation system based on celestial angle and velocity measurements. Journal of Deep Space "
            "Exploration 4(4):373-378, 2017, doi:10.15982/j.issn.2095-7777.2017.04.010")
#: Figure ids of an S4 report.
FIGURES = ("s4_errors", "s4_error_in_sigma", "s4_position_axes")
#: The three runs, their colours and the paper's finding on each (None: opnav's own reference run).
CASES = {"exact": ("tab:green", None), "registered": ("tab:blue", "converges"),
         "unregistered": ("tab:red", "diverges")}
#: Dash patterns of the 3-sigma lines: the exact and unregistered runs take the same records with the same
#: covariances (only their time tags differ), so their 3-sigmas agree to a fraction of a percent and their
#: dashes interleave to show both.
DASHES = {"exact": (0, (3, 6)), "registered": "--", "unregistered": (4.5, (3, 6))}
#: Share of the arc left out when counting epochs outside 3-sigma (the filters start 1000 km off).
SETTLING_SHARE = 0.1


def report_blocks(summary: dict, arrays) -> list:
    """The S4 page: paragraphs, :class:`~opnav.studies.report_page.Table` and
    :class:`~opnav.studies.report_page.Figure` blocks from ``summary`` (``summary.json``) and ``arrays``
    (``evaluation.npz``)."""
    settings = summary["run"]["settings"]
    t = arrays["t_tdb_s"]
    cases = [name for name in CASES if f"{name}_error" in arrays]
    return [
        f"S4 Mars approach ({CITATION}): a federated UKF fuses an angle sensor (lines of sight to the Sun and "
        f"Mars, every 60 s, turned into a position pseudo-measurement) and a velocity sensor (Doppler of the Sun, "
        f"Canopus and Vega, every 600 s) from {_utc(float(t[0]))} to "
        f"{_utc(float(t[-1]))} UTC. The angle data lead the velocity clock by "
        f"{settings.get('lead_s', 30.0):g} s; the three runs use the same records differently: exact (each at "
        "its own time tag), registered (Lagrange extrapolation to the fusion epochs) and unregistered (the "
        "latest angle sample taken as if it were at the fusion epoch).",
        "Settings: " + ", ".join(f"{key} = {value}" for key, value in settings.items()) + ".",
        _paper_table(summary, arrays, cases),
        _errors_figure(arrays, cases),
        _sigma_figure(arrays, cases),
        _axes_figure(arrays, cases),
        _final_table(summary, cases),
        _facts_table(summary),
        *_estimates(summary),
    ]


def _error_in_sigma(arrays, name: str) -> np.ndarray:
    """The worst position axis's |error| / 1-sigma at each fusion epoch (M,)."""
    return np.max(np.abs(arrays[f"{name}_error"][:, :3]) / arrays[f"{name}_sigma"][:, :3], axis=1)


def _paper_table(summary: dict, arrays, cases: list[str]) -> Table:
    settled = slice(int(SETTLING_SHARE * arrays["t_tdb_s"].size), None)
    rows = []
    for name in cases:
        ratio = _error_in_sigma(arrays, name)
        figures = summary["filters"][name]
        outside = float(np.mean(ratio[settled] > 3.0))
        verdict = ("inside its 3-sigma" if figures["max_axis_error_in_sigma"] <= 3.0 else
                   "outside its 3-sigma: the filter's covariance no longer covers its error")
        rows.append((name, CASES[name][1] or "- (opnav's reference)",
                     f"final position error {figures['final_position_error_km']:.1f} km, worst axis "
                     f"{figures['max_axis_error_in_sigma']:.2f} sigma: {verdict}",
                     f"{100 * outside:.1f} %"))
    return Table("The paper's finding beside opnav's",
                 ("run", "paper's finding", "opnav at the last fusion epoch",
                  f"epochs with an axis beyond 3-sigma (after the first {100 * SETTLING_SHARE:g} % of the arc)"),
                 tuple(rows),
                 note=f"Paper: {CITATION}. The paper plots the errors; it gives the outcome (divergence without "
                      "registration, convergence with it), not a table of figures.")


def _errors_figure(arrays, cases: list[str]) -> Figure:
    fig, axes = new_figure(1, 2, height_in=4.6)
    t = arrays["t_tdb_s"]
    for col, (offset, scale, what, unit) in enumerate(((0, 1.0, "position", "km"), (3, 1e3, "velocity", "m/s"))):
        ax = axes[0, col]
        x = utc_axis(ax, t)
        for name in cases:
            color = CASES[name][0]
            err = scale * np.linalg.norm(arrays[f"{name}_error"][:, offset:offset + 3], axis=1)
            band = 3.0 * scale * np.linalg.norm(arrays[f"{name}_sigma"][:, offset:offset + 3], axis=1)
            keep = envelope_indices(err)
            ax.semilogy(x[keep], err[keep], color=color, lw=1.0, label=f"{name}: error")
            keep = envelope_indices(band)
            ax.semilogy(x[keep], band[keep], color=color, lw=1.4, ls=DASHES[name], label=f"{name}: 3-sigma")
        ax.set_ylabel(f"{what} error magnitude ({unit})")
        ax.set_title(f"{what}: |estimate - truth| and the run's own 3-sigma (RSS of the axes)", fontsize=10)
    fig.legend(*axes[0, 0].get_legend_handles_labels(), loc="outside lower center", ncol=6, fontsize=9)
    return Figure("s4_errors", "Error magnitude of each run (solid) against its own 3-sigma (dashed, same colour): "
                  "a run whose solid line stays above its dashed one has diverged from what its covariance claims (the "
                  "exact and unregistered runs take the same records with the same covariances, so their 3-sigmas "
                  "nearly coincide and their dashes interleave).",
                  figure_png(fig))


def _sigma_figure(arrays, cases: list[str]) -> Figure:
    fig, axes = new_figure(1, 1, height_in=3.6)
    ax = axes[0, 0]
    x = utc_axis(ax, arrays["t_tdb_s"])
    for name in cases:
        ratio = _error_in_sigma(arrays, name)
        keep = envelope_indices(ratio)
        ax.semilogy(x[keep], ratio[keep], color=CASES[name][0], lw=1.0, label=name)
    ax.axhline(3.0, color="k", ls="--", lw=1.0, label="3 sigma")
    ax.set_ylabel("worst position axis |error| / 1-sigma")
    ax.legend(fontsize=8, ncol=4, loc="lower right")
    return Figure("s4_error_in_sigma", "The worst ICRF position axis's error in units of its own 1-sigma at each "
                  "fusion epoch: a consistent run stays mostly below the dashed 3-sigma line; the unregistered run's "
                  "lag puts it far above.", figure_png(fig))


def _axes_figure(arrays, cases: list[str]) -> Figure:
    t = arrays["t_tdb_s"]
    fig, axes = new_figure(len(cases), 3, height_in=2.4 * len(cases) + 0.6, sharex=True)
    for row, name in enumerate(cases):
        error, sigma = arrays[f"{name}_error"][:, :3], 3.0 * arrays[f"{name}_sigma"][:, :3]
        for col, axis in enumerate("xyz"):
            ax = axes[row, col]
            x = utc_axis(ax, t, label=row == len(cases) - 1)
            keep = envelope_indices(sigma[:, col])
            ax.fill_between(x[keep], -sigma[keep, col], sigma[keep, col], color="tab:blue", alpha=0.2, lw=0,
                            label="±3-sigma")
            keep = envelope_indices(error[:, col])
            ax.plot(x[keep], error[keep, col], color=CASES[name][0], lw=0.9, label="error")
            # the first hours (1000 km start) would flatten the rest: the scale is that of the settled arc,
            # and it widens to any error beyond it there
            settled = slice(int(SETTLING_SHARE * t.size), None)
            lim = 1.1 * float(np.max(np.abs(np.concatenate([error[settled, col], sigma[settled, col]]))))
            ax.set_ylim(-lim, lim)
            ax.set_title(f"{name}: position {axis} (km)", fontsize=10)
    axes[0, 0].legend(fontsize=8, loc="upper right")
    return Figure("s4_position_axes", "Position error per ICRF axis with the run's ±3-sigma, one row per run (y "
                  f"scale set by the arc after its first {100 * SETTLING_SHARE:g} %, when the 1000 km initial error "
                  "has settled): the error should stay inside the band.", figure_png(fig))


def _final_table(summary: dict, cases: list[str]) -> Table:
    rows = []
    for name in cases:
        f = summary["filters"][name]
        rows.append((name, f"{f['final_position_error_km']:.3f}", f"{f['final_position_sigma_km']:.3f}",
                     f"{f['final_velocity_error_m_s']:.4f}", f"{f['final_velocity_sigma_m_s']:.4f}",
                     f"{f['max_axis_error_in_sigma']:.2f}", f"{f['refused']}/{f['records']}", f"{f['wall_s']:.1f}"))
    return Table("Final fused estimate of each run",
                 ("run", "position error (km)", "position 1-sigma, RSS (km)", "velocity error (m/s)",
                  "velocity 1-sigma, RSS (m/s)", "worst axis error / 1-sigma", "refused / records", "wall (s)"),
                 tuple(rows))


def _facts_table(summary: dict) -> Table:
    facts = summary["facts"]
    x0 = facts["state_at_start_km_km_s"]
    stars = ", ".join(f"HIP {hip}: {value:+.1f} km/s" for hip, value in facts["star_radial_velocity_km_s"].items())
    rows = (("true state at the window start (heliocentric ICRF)",
             f"r = ({x0[0]:.6g}, {x0[1]:.6g}, {x0[2]:.6g}) km, v = ({x0[3]:.5f}, {x0[4]:.5f}, {x0[5]:.5f}) km/s"),
            ("distance to Mars at the start", f"{facts['distance_to_mars_start_km'] / 1e6:.3f} million km"),
            ("distance to Mars at the end", f"{facts['distance_to_mars_end_km'] / 1e6:.3f} million km"),
            ("position pseudo-measurement 1-sigma (median, per axis)",
             f"{facts['position_pseudo_measurement_sigma_km']:.0f} km"),
            ("star radial velocities (catalog)", stars))
    return Table("The approach arc", ("item", "value"), rows)


def _estimates(summary: dict) -> list:
    estimates = summary.get("estimates") or {}
    if not estimates:
        return []
    return [Table("Estimated trajectories (CCSDS OEM with covariance, fused estimate at each fusion epoch)",
                  ("file", "centre", "run"),
                  tuple((e["file"], e["center"].capitalize(), name) for name, e in estimates.items()))]
