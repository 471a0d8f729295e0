"""A moon beside its bright, saturated primary: the local PSF fit with the primary's pixels left out.

A saturated Mars bleeds charge up and down its columns (blooming) and its PSF halo
spreads a few PSF widths beyond the limb; both join a nearby moon to Mars' connected
component, so :func:`~opnav.image.detect.detect` gives it no point seed, and a moon in a
bloomed column is physically lost. When no clean point source is found near the
prediction, :func:`local_moon_fit` searches ``association_radius_px`` around it for a
PSF-shaped local maximum of the frame with the *blocked* pixels left out:

- pixels within 5 read-noise sigmas of saturation (read noise is added after the
  clipping, so half of a bloomed column reads just below ``SATURATE``), grown by one
  pixel along the column (the partly filled end of a bloom run);
- the primary's disk and halo: pixels closer to its centre than ``R + sigma_psf z``,
  where ``z`` makes the halo of a uniform disk of the predicted surface brightness
  ``S`` (e-/px) fall to one read-noise sigma, ``S Q(z) = read_noise``, plus
  ``HALO_MARGIN_PX`` for the error of the predicted disk centre.

Each candidate is fitted with a Gaussian PSF of the stars' width over a plane
(:func:`opnav.image.targets.fit_point_source`) and kept only if at least
``min_psf_fraction`` of its PSF lies on usable pixels (judged at the predicted position when
the fit is within a pixel of it: a gate on the fitted centre is a selection on the noise that
keeps the fits pushed away from the primary and drops those pushed toward it, a bias of ~0.3
sigma radial from Mars on the kept records near the gate) and the fit's chi-square is
acceptable (p >= 0.001; the covariance is scaled by the reduced chi-square above 1).
Pixels the detector rejected as cosmic-ray hits or hot pixels seed no candidate, but the fit
takes back those its model explains (``suspect``): a rejection test that fails on bright noise
more often than on faint, as it can on the primary's slope, would otherwise take upward
fluctuations away from one side of the moon (``tests/image/test_fit_suspect_pixels.py``). In
the S1 July arc this changes 20 of 41,600 records: such rejections inside the fit are rare.
Otherwise no record is written: the frame is flagged ``no_<moon>`` and, when the
prediction lies on blocked pixels, ``<moon>_hidden``, with the reason logged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.special import ndtri

from ..errors import NoSolutionError
from . import detect as detect_mod
from .centroid import chi2_sf
from .targets import PointFit, fit_point_source, psf_fraction

#: Margin added to the primary's masked disk + halo for the error of its predicted position, px.
HALO_MARGIN_PX = 2.0


class MoonHiddenError(NoSolutionError):
    """The moon's predicted position lies on saturated, bloomed or halo pixels of its primary."""


@dataclass(frozen=True)
class MoonContext:
    """What the local moon fit needs from the frame (module section "Moons next to a saturated primary")."""

    image: np.ndarray
    background: np.ndarray
    noise: np.ndarray
    blocked: np.ndarray
    invalid: np.ndarray
    rejected: np.ndarray
    psf_sigma_px: float | None
    read_noise_e: float
    gain: float
    bias_adu: float
    exposure_s: float
    primary: object | None


def moon_context(frame, found, views: dict, moons, ephemeris, psf_sigma_px: float | None = None,
                 primary_view=None) -> MoonContext:
    """Blocked pixels, the stars' PSF width and the moons' primary for :func:`local_moon_fit`.

    ``frame``: the :class:`opnav.image.pipeline.FrameInput`; ``found``: its detections and
    centroids (``det``, ``sources``, ``ok``); ``views``: name -> (body, view) of the frame's
    targets, of which ``moons`` are the point-like moons; ``psf_sigma_px``: the stars' PSF width
    when known from elsewhere (a crop has too few stars); ``primary_view``: the moons' primary as
    this frame sees it, when already predicted.
    """
    from ..bodies import body_model, view_body

    image, det, sources = frame.image, found.det, found.sources
    blocked = np.zeros(image.shape, bool)
    if frame.saturation_adu is not None:
        near_full = image >= frame.saturation_adu - 5.0 * frame.read_noise_e / frame.gain_e_per_adu
        blocked |= ndimage.binary_dilation(near_full, structure=np.ones((3, 1), bool))
    stars = found.ok & ((det.flags & (detect_mod.FLAG_SATURATED | detect_mod.FLAG_BLENDED | detect_mod.FLAG_EDGE)) == 0)
    stars &= sources.snr > 20.0
    psf_sigma = psf_sigma_px
    if psf_sigma is None and stars.sum() >= 3:
        psf_sigma = float(np.median(sources.sigma_px[stars]))
    primaries = {views[name][0].primary for name in moons}
    primary = primary_view
    if primary is None and len(primaries) == 1:
        name = primaries.pop()
        primary = views[name][1] if name in views else view_body(body_model(name), frame.camera, frame.R_prior,
                                                                 frame.observer, ephemeris, supersample=1,
                                                                 keep_rays=False)
    invalid = frame.invalid
    return MoonContext(image=image, background=det.background.level, noise=det.background.noise, blocked=blocked,
                       invalid=np.zeros(image.shape, bool) if invalid is None else np.asarray(invalid, bool),
                       rejected=np.asarray(det.rejected, bool),
                       psf_sigma_px=psf_sigma, read_noise_e=frame.read_noise_e, gain=frame.gain_e_per_adu,
                       bias_adu=frame.bias_adu, exposure_s=frame.exposure_s, primary=primary)


def halo_mask(ctx: MoonContext, camera, shape_rc: tuple[slice, slice]) -> np.ndarray:
    """Pixels of ``image[shape_rc]`` on the primary's predicted disk or halo (module docstring)."""
    rows, cols = shape_rc
    yy, xx = np.mgrid[rows, cols]
    if ctx.primary is None:
        return np.zeros(yy.shape, bool)
    radius = ctx.primary.angular_radius_rad * camera.focal_length_px
    if radius < 1.0:
        return np.zeros(yy.shape, bool)
    surface_e = ctx.primary.electrons_s * ctx.exposure_s / (math.pi * radius**2)
    sigma = ctx.psf_sigma_px if ctx.psf_sigma_px is not None else 1.0
    # -ndtri(q) is scipy.stats.norm.isf(q) for q in (0, 1), without its ~70 us a call
    z = float(-ndtri(max(ctx.read_noise_e, 1.0) / surface_e)) if surface_e > max(ctx.read_noise_e, 1.0) else 0.0
    centre = ctx.primary.xy_cof_px
    return np.hypot(xx - centre[0], yy - centre[1]) < radius + sigma * max(z, 0.0) + HALO_MARGIN_PX


def local_moon_fit(name, view, camera, ctx: MoonContext, options) -> PointFit:
    """Search around the prediction for the moon with blocked pixels left out (module docstring).

    Returns the accepted :class:`~opnav.image.targets.PointFit`; raises ``MoonHiddenError`` when
    the prediction is on blocked pixels and nothing usable is found, ``NoSolutionError`` otherwise.
    """
    if ctx.psf_sigma_px is None:
        raise NoSolutionError(f"no point source near the predicted {name} and too few stars to know the PSF")
    h, w = ctx.image.shape
    pred = np.asarray(view.xy_photocentre_px, float)
    r = options.association_radius_px
    half = options.local_window_px // 2
    # a wrong header (a WCS degrees off, a date a day off) predicts the moon off the frame or behind the camera
    if not np.all(np.isfinite(pred)) or not (-r - half < pred[0] < w + r + half and -r - half < pred[1] < h + r + half):
        raise NoSolutionError(f"{name} is predicted at {pred} px, outside the {w} x {h} frame")
    r0, r1 = max(int(pred[1] - r) - half, 0), min(int(pred[1] + r) + half + 2, h)
    c0, c1 = max(int(pred[0] - r) - half, 0), min(int(pred[0] + r) + half + 2, w)
    box = (slice(r0, r1), slice(c0, c1))
    fittable = ~(ctx.blocked[box] | ctx.invalid[box] | halo_mask(ctx, camera, box))
    # cosmic-ray hits and hot pixels seed no peak; the fit judges them itself (``suspect``)
    usable = fittable & ~ctx.rejected[box]
    pi, pj = int(round(pred[1])) - r0, int(round(pred[0])) - c0
    hidden = not (0 <= pi < fittable.shape[0] and 0 <= pj < fittable.shape[1] and fittable[pi, pj])
    resid = np.where(usable, ctx.image[box] - ctx.background[box], 0.0)
    # Normalised convolution: the matched filter over the usable pixels only.
    weight = ndimage.gaussian_filter(usable.astype(float), ctx.psf_sigma_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth = ndimage.gaussian_filter(resid, ctx.psf_sigma_px) / weight
    kernel_norm = 1.0 / (4.0 * math.pi * ctx.psf_sigma_px**2)  # sum of k^2 for a unit Gaussian kernel
    threshold = options.detect.threshold_sigma * ctx.noise[box] * math.sqrt(kernel_norm)
    yy, xx = np.mgrid[box]
    peaks = usable & (weight > 0.3) & (smooth > threshold) & (np.hypot(xx - pred[0], yy - pred[1]) < r)
    peaks &= smooth == ndimage.maximum_filter(np.where(usable, smooth, -np.inf), size=3)
    rows, cols = np.nonzero(peaks)
    order = np.argsort(-smooth[rows, cols])[:5]
    reason = "no PSF-shaped source on its usable pixels"
    best, best_dist = None, np.inf
    full_usable = ~(ctx.blocked | ctx.invalid)
    full_usable[box] &= fittable
    # Enough of the PSF on usable pixels is judged at the prediction, which the moon's own noise
    # does not move: a gate on the fitted centre would keep the fits the noise pushed off the
    # blocked pixels and drop those it pushed onto them, biasing the kept ones away from the primary.
    predicted_fraction = psf_fraction(full_usable, pred, ctx.psf_sigma_px, options.local_window_px)
    for i, j in zip(rows[order], cols[order]):
        xy0 = np.array([xx[i, j], yy[i, j]], float)
        try:
            fit = fit_point_source(ctx.image, xy0, usable=full_usable, psf_sigma_px=ctx.psf_sigma_px,
                                   read_noise_e=ctx.read_noise_e, gain_e_per_adu=ctx.gain, bias_adu=ctx.bias_adu,
                                   window=options.local_window_px, suspect=ctx.rejected)
        except NoSolutionError as exc:
            reason = str(exc)
            continue
        # the prediction stands for the moon when the fit lands within a pixel of it (the usual
        # case: the fit's noise is hundredths of a pixel); a fit farther off is judged where it is
        fraction = predicted_fraction if np.hypot(*(fit.xy - pred)) <= 1.0 else fit.psf_fraction
        if fraction < options.min_psf_fraction:
            reason = f"only {100 * fraction:.0f}% of its PSF on usable pixels"
            continue
        if chi2_sf(fit.chi2, fit.dof) < 1e-3:
            reason = f"PSF + plane fit rejected (chi2 {fit.chi2:.0f} for {fit.dof} dof)"
            continue
        if fit.snr < options.detect.threshold_sigma or np.hypot(*(fit.xy - xy0)) > 1.5:
            reason = "fit drifted from its peak or too faint"
            continue
        dist = float(np.hypot(*(fit.xy - pred)))
        if dist < min(best_dist, r):
            best, best_dist = fit, dist
    if best is not None:
        return best
    where = f"within {r} px of the predicted {name}"
    if hidden:
        raise MoonHiddenError(f"{name} predicted on saturated, bloomed or halo pixels; nothing measurable {where} ({reason})")
    raise NoSolutionError(f"no usable source {where} ({reason})")
