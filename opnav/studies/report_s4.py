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

From pixels (``summary["image_mode"]``, :mod:`opnav.studies.s4_images`) the page adds:

- a table of what the frames gave: the achieved noise of each line of sight per axis against the
  true geometric one beside the covariances' mean chi-square, the Mars centre method, the samples
  skipped and why, the star tracker's stars and the wrong-body check;
- ``s4_los_errors``: the Sun's and Mars' line-of-sight errors per axis at every sample;
- ``s4_sample_frame``: the first measured camera frame around Mars with the fitted and the true
  centre (the fitted one drawn through the true attitude, so their offset is the whole error).

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
#: Figure ids a from-pixels report adds.
IMAGE_FIGURES = ("s4_los_errors", "s4_sample_frame")
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
    image = summary.get("image_mode")
    step = image["image_step_s"] if image else settings.get("angle_step_s", 60.0)
    source = ("measured from rendered frames of Mars and a sun-sensor model (image mode)" if image else
              "simulated with the study's noise")
    return [
        f"S4 Mars approach ({CITATION}): a federated UKF fuses an angle sensor (lines of sight to the Sun and "
        f"Mars, every {step:g} s, {source}, turned into a position pseudo-measurement) and a velocity sensor (Doppler of the Sun, "
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
        *(_image_blocks(image, arrays) if image else []),
        *_estimates(summary),
    ]


def _image_blocks(image: dict, arrays) -> list:
    """The from-pixels table and figures (module notes)."""
    noise, wrong = image["achieved_noise"], image["wrong_body"]
    rows = [(f"{name} line of sight, per axis (RMS against the true geometric one)",
             f"{noise[key]['rms_per_axis_arcsec']:.3f}\" over {noise[key]['count']} samples; mean "
             f"({noise[key]['mean_arcsec'][0]:+.3f}, {noise[key]['mean_arcsec'][1]:+.3f})\"; chi-square/dof of the "
             f"reported covariances {noise[key]['chi2_per_dof']:.2f}")
            for name, key in (("Mars (navigation camera + star tracker)", "mars"), ("Sun (sun sensor + star tracker)", "sun"))]
    rows += [("samples (one tracker frame, one camera frame, one sun-sensor reading each)",
              f"{image['samples']} every {image['image_step_s']:g} s; {image['position_records']} eq. 1 records"),
             ("samples skipped", f"{image['samples_skipped']}" + (": " + "; ".join(
                 f"{reason} ({count})" for reason, count in image["skipped_reasons"].items()) if image["skipped_reasons"] else "")),
             ("Mars centre method", ", ".join(
                 f"{'not known: records read back from saved chunks' if method == 'unknown' else method} ({count})"
                 for method, count in image["mars_methods"].items())),
             ("star tracker", f"{image['tracking']['stars_used']} star measurements, "
                              f"{image['tracking']['stars_misidentified']} misidentified (checked against the truth)"),
             ("wrong-body check", f"{wrong['count']} of {wrong['checked']} Mars records more than "
                                  f"{wrong['threshold_sigma']:g} sigma from the true centre or off the true disk "
                                  f"(worst {wrong['worst_sigma']:.2f} sigma, {wrong['worst_disk_radii']:.4f} disk radii)")]
    blocks = [Table("From pixels: what the frames gave against the truth", ("item", "value"), tuple(rows),
                    note="Measurement mode at the same cadence and noise: --set angle_step_s="
                         f"{image['image_step_s']:g} --set sun_sigma_arcsec={noise['sun']['rms_per_axis_arcsec']:.3f} "
                         f"--set mars_sigma_arcsec={noise['mars']['rms_per_axis_arcsec']:.3f}.")]
    if "sun_error_arcsec" in arrays and len(arrays["sun_error_arcsec"]):
        blocks.append(_los_figure(arrays))
    if "sample_image_adu" in arrays:
        blocks.append(_sample_figure(arrays))
    return blocks


def _los_figure(arrays) -> Figure:
    fig, axes = new_figure(1, 2, height_in=3.6)
    x_t = arrays["position_t_tdb_s"]
    for col, (key, name) in enumerate((("mars_error_arcsec", "Mars"), ("sun_error_arcsec", "Sun"))):
        ax = axes[0, col]
        x = utc_axis(ax, x_t)
        for axis, color in ((0, "tab:blue"), (1, "tab:orange")):
            ax.plot(x, arrays[key][:, axis], ".", ms=2, color=color, label=f"axis {axis + 1}")
        ax.set_ylabel("error (arcsec)")
        ax.set_title(f"{name}: measured - true geometric line of sight", fontsize=10)
        ax.legend(fontsize=8, loc="upper right")
    return Figure("s4_los_errors", "Line-of-sight errors at every sample, two axes perpendicular to the true "
                  "direction: Mars from the camera's limb fit and the tracker's attitude, the Sun from the sun "
                  "sensor and the same attitude.", figure_png(fig))


def _sample_figure(arrays) -> Figure:
    fig, axes = new_figure(1, 1, height_in=4.4)
    ax = axes[0, 0]
    image = arrays["sample_image_adu"]
    ax.imshow(image, origin="lower", cmap="gray", vmin=float(np.percentile(image, 1)),
              vmax=float(np.percentile(image, 99.9)))
    fit, true = arrays["sample_fit_xy_px"], arrays["sample_true_xy_px"]
    ax.plot(*true, "+", color="tab:green", ms=14, mew=1.2, label="true centre")
    ax.plot(*fit, "x", color="tab:red", ms=10, mew=1.2, label="fitted centre")
    ax.set_xlabel("column in the cut-out (px)")
    ax.set_ylabel("row (px)")
    ax.legend(fontsize=8, loc="upper right")
    offset = float(np.hypot(*(np.asarray(fit) - np.asarray(true))))
    return Figure("s4_sample_frame", f"Sample {int(arrays['sample_index'])}: the navigation camera's frame around "
                  f"Mars with the limb-fitted centre (x) and the true one (+), {offset:.3f} px apart.", figure_png(fig))


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
