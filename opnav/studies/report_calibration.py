"""The report of a camera calibration (``opnav calibrate``): Markdown and a self-contained HTML page.

What it shows (:func:`calibration_blocks`):

- the fitted parameters beside the starting camera's, each with its 1-sigma, and their correlations;
- the fit: stars kept and rejected, chi-square per degree of freedom (about 1 when the centroid
  covariances are honest), post-fit RMS beside the RMS the starting camera leaves;
- per frame: stars, rejected, RMS before (starting camera, attitude fitted alone) and after;
- residual vectors across the detector before and after (arrows magnified, the scale given);
- radial and tangential residual (about the principal point) against field radius, before and after.

Residuals are predicted minus measured position, px.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .report_page import Figure, Table, write_page
from .report_plots import figure_png, new_figure


def _fmt(value: float, digits: int = 4) -> str:
    if not math.isfinite(value):
        return "-"
    return f"{value:.{digits}g}"


def _stack(calibration):
    xy = np.concatenate([f.xy[f.kept] for f in calibration.frames])
    before = np.concatenate([f.residual_before_px[f.kept] for f in calibration.frames])
    after = np.concatenate([f.residual_after_px[f.kept] for f in calibration.frames])
    return xy, before, after


def _vector_figure(calibration) -> Figure:
    xy, before, after = _stack(calibration)
    camera = calibration.camera
    fig, axes = new_figure(1, 2, width_in=13.0, height_in=6.0)
    scales = []
    for ax, residual, title, color in ((axes[0, 0], before, "starting camera", "C0"),
                                       (axes[0, 1], after, "calibrated camera", "C2")):
        # each panel its own magnification: its largest residual draws as a tenth of the detector width
        largest = max(float(np.max(np.linalg.norm(residual, axis=1), initial=0.0)), 1e-12)
        scale = 0.1 * camera.width_px / largest
        scales.append(scale)
        ax.quiver(xy[:, 0], xy[:, 1], residual[:, 0] * scale, residual[:, 1] * scale, angles="xy",
                  scale_units="xy", scale=1.0, width=0.002, color=color)
        ax.set_xlim(-0.5, camera.width_px - 0.5)
        ax.set_ylim(camera.height_px - 0.5, -0.5)  # rows grow downwards, as the image shows them
        ax.set_aspect("equal")
        ax.set_xlabel("column x, px")
        ax.set_ylabel("row y, px")
        rms = float(np.sqrt(np.mean(residual**2)))
        ax.set_title(f"{title}: RMS {rms:.3g} px a axis, arrows x{scale:.3g}", fontsize=10)
    caption = (f"Residual (predicted - measured) of every star kept, magnified {scales[0]:.3g} times before and "
               f"{scales[1]:.3g} times after calibration (each panel's largest residual draws as a tenth of the "
               f"width): the pattern the starting camera leaves, and what is left with the calibrated one.")
    return Figure("calibration_vectors", caption, figure_png(fig))


def _radial_tangential(camera, xy: np.ndarray, residual: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    offset = xy - np.array([camera.cx_px, camera.cy_px])
    radius = np.linalg.norm(offset, axis=1)
    radial_unit = offset / np.maximum(radius, 1e-9)[:, None]
    radial = np.sum(residual * radial_unit, axis=1)
    tangential = radial_unit[:, 0] * residual[:, 1] - radial_unit[:, 1] * residual[:, 0]
    return radius, radial, tangential


def _radial_figure(calibration) -> Figure:
    xy, before, after = _stack(calibration)
    camera = calibration.camera
    fig, axes = new_figure(1, 2, width_in=13.0, height_in=4.0, sharey=True)
    for ax, residual, title in ((axes[0, 0], before, "starting camera"), (axes[0, 1], after, "calibrated camera")):
        radius, radial, tangential = _radial_tangential(camera, xy, residual)
        ax.plot(radius, radial, ".", ms=3, label="radial", color="C0")
        ax.plot(radius, tangential, ".", ms=3, label="tangential", color="C1")
        ax.axhline(0.0, color="0.5", lw=0.8)
        ax.set_xlabel("distance from the principal point, px")
        ax.set_title(title, fontsize=10)
        ax.legend(fontsize=8)
    axes[0, 0].set_ylabel("residual, px")
    caption = ("Radial (outwards) and tangential (counter-clockwise as the image shows it) residual of every star "
               "against its distance from the calibrated principal point: a focal-length or radial-distortion "
               "error is a trend in the radial residual, a principal-point or tangential error a pattern in both.")
    return Figure("calibration_radial", caption, figure_png(fig))


def calibration_blocks(calibration, *, frame_notes: dict[str, str] | None = None) -> list:
    """The report's blocks (module docstring) for :func:`opnav.studies.report_page.write_page`."""
    from ..image.calibration import UNITS, parameter_values

    cal = calibration
    start = parameter_values(cal.start, cal.names)
    def source(prior: float, share: float) -> str:  # where a parameter's information came from
        return "stars" if not np.isfinite(prior) else f"prior {_fmt(prior, 3)}, stars {100 * max(share, 0.0):.0f} %"

    held = (f" Held at the starting camera's values (the stars do not constrain them): {', '.join(cal.held)}."
            if cal.held else "")
    params = Table(
        "Fitted parameters", ("parameter", "unit", "starting camera", "calibrated", "1-sigma", "change / sigma",
                              "information from"),
        tuple((n, UNITS[n] or "-", _fmt(s, 10), _fmt(v, 10), _fmt(e, 3), _fmt((v - s) / e, 3), source(p, sh))
              for n, s, v, e, p, sh in zip(cal.names, start, cal.values, cal.sigma, cal.prior_sigma, cal.stars_share)),
        note=f"model {cal.model}; f is the focal length and cx, cy the principal point, in px; Brown coefficients "
             f"on the normalised image plane (docs/conventions.md). Covariance from the centroid covariances as "
             f"given (and a parameter's prior, centred on the starting camera's value: --fit auto), the frames' "
             f"attitudes marginalised; 'stars N %' is the share of its information the stars give.{held}")
    corr = Table("Correlations", ("",) + cal.names,
                 tuple((n,) + tuple(f"{c:+.3f}" for c in row) for n, row in zip(cal.names, cal.correlation)))
    fit = Table("Fit", ("item", "value"), (
        ("frames", str(len(cal.frames))),
        ("stars kept", str(cal.n_stars)),
        ("stars rejected (outliers)", str(cal.n_rejected)),
        ("chi-square / degrees of freedom", f"{cal.chi2:.1f} / {cal.dof} = {cal.chi2_per_dof:.3f}"),
        ("post-fit RMS a axis, px", _fmt(cal.rms_px, 4)),
        ("RMS a axis with the starting camera, px",
         _fmt(float(np.sqrt(np.mean(np.concatenate([f.residual_before_px[f.kept] for f in cal.frames]) ** 2))), 4)),
        ("fit time, s", f"{cal.elapsed_s:.2f}"),
    ), note="chi-square per degree of freedom near 1 says the centroid covariances describe the residuals; "
            "well above 1, the centroids are worse than their covariances (add --sigma-floor-px).")
    notes = frame_notes or {}
    frames = Table("Frames", ("frame", "stars kept", "rejected", "RMS before, px", "RMS after, px", "note"),
                   tuple((Path(f.name).name, str(int(f.kept.sum())), str(int((~f.kept).sum())), _fmt(f.rms_before_px, 3),
                          _fmt(f.rms_px, 3), notes.get(f.name, "")) for f in cal.frames))
    return [params, corr, fit, frames, _vector_figure(cal), _radial_figure(cal)]


def write_calibration_report(folder, name: str, calibration, prov, *, frame_notes=None) -> tuple[Path, Path]:
    """Write ``folder/<name>.md``, ``folder/<name>.html`` and their figures; returns the two page paths."""
    folder = Path(folder)
    write_page(folder, "Camera calibration", calibration_blocks(calibration, frame_notes=frame_notes), prov, name=name)
    return folder / f"{name}.md", folder / f"{name}.html"
