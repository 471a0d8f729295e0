"""The stars' scatter about their attitude that the camera model leaves, and the attitude fit that allows for it.

A camera known only to a fraction of a percent in focal length, a few pixels in principal point and
without its distortion (a user's nominal model before calibration) puts every star up to a few pixels
from where any attitude predicts it: 0.2 % of focal length alone is 1.4 px at the corner of a
1024-px detector. Against centroid sigmas of hundredths of a pixel that is 50 sigmas and more, so an
attitude fit gated in centroid sigmas (:func:`opnav.image.attitude.wahba_gated`) drops star after
star, and its covariance is far too small for the error the camera model leaves in the attitude and
in every target's direction relative to the stars.

:func:`model_scatter_px` measures that error from the residuals themselves; :func:`gated_attitude`
refits with each star's sigma widened by it when the plain gate cannot explain the stars (it drops
too many, or it stops at ``min_stars`` with stars still outside it), so the attitude covariance, and
the records whose covariance takes it in, carry the camera's error to first order. A well-known
camera's frames, whose stars fit within their noise, are fitted as before. Both stages use it: the
tracking stage on every tracked frame (:mod:`opnav.image.tracking`), the full-frame stage after star
identification (:func:`opnav.image.pipeline.measure_frame`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..consistency import chi2_quantile
from .attitude import AttitudeSolution, wahba, wahba_gated

#: Model scatter is taken into the gate when the residuals' median per-axis variance exceeds the
#: centroid variance by this factor (25: five times the centroid sigma; noise, or a few bad stars among
#: good ones, does not get there: a nominal camera 1 px off at the corner is 50 centroid sigmas out).
MODEL_SCATTER_FACTOR = 25.0
#: Median of chi-square with 2 degrees of freedom: a 2-D residual's median square is this many per-axis variances.
_CHI2_2_MEDIAN = 2.0 * math.log(2.0)
#: wahba_gated's default gate: the 1 - 1e-4 quantile of chi-square(2).
_GATE_PROBABILITY = 1.0 - 1e-4


@dataclass(frozen=True)
class GatedAttitude:
    """What :func:`gated_attitude` gives.

    Attributes
    ----------
    solution : opnav.image.attitude.AttitudeSolution
        The fit on the kept stars (attitude camera -> ICRF, covariance rad^2).
    kept : (N,) bool array
        The stars the solution uses.
    sigma_px : (N,) array
        Each star's per-axis sigma in the fit, px (its weight is the inverse square): the centroid
        sigma, or that and ``scatter_px`` in quadrature.
    scatter_px : float
        The camera model's per-axis scatter taken into the fit, px (0: the plain fit).
    """

    solution: AttitudeSolution
    kept: np.ndarray
    sigma_px: np.ndarray
    scatter_px: float


def model_scatter_px(b_cam: np.ndarray, v_icrf: np.ndarray, sigma_px: np.ndarray, camera) -> float:
    """Per-axis scatter of the stars about the attitude beyond their centroid noise, px (0: none to speak of).

    The residuals of a Wahba fit to every star: their median square over ``ln 4`` (the median of
    chi-square(2)) estimates the per-axis variance whatever a few outliers do; what exceeds the stars'
    median centroid variance is the camera model's error across the field (a nominal camera's missing
    distortion, a calibration's residual error). Below ``MODEL_SCATTER_FACTOR`` times the centroid
    variance it is taken as noise (0), so a well-known camera's gate is unchanged.

    Parameters
    ----------
    b_cam : (N, 3) array
        The stars' measured unit directions, camera frame.
    v_icrf : (N, 3) array
        Their apparent catalog unit directions, ICRF.
    sigma_px : (N,) array
        Their centroid sigmas per axis, px.
    camera : opnav.camera.Camera
        Sets the pixel scale.
    """
    if len(b_cam) < 3:
        return 0.0
    fit = wahba(b_cam, v_icrf, sigma_rad=sigma_px * camera.pixel_scale_rad)
    variance = float(np.median((fit.residuals_rad / camera.pixel_scale_rad) ** 2)) / _CHI2_2_MEDIAN
    centroid = float(np.median(sigma_px**2))
    if variance <= MODEL_SCATTER_FACTOR * centroid:
        return 0.0
    return math.sqrt(variance - centroid)


def gated_attitude(b_cam: np.ndarray, v_icrf: np.ndarray, sigma_px: np.ndarray, camera, *, min_stars: int,
                   max_dropped_fraction: float = 0.5) -> GatedAttitude:
    """The gated Wahba fit of identified stars, the gate widened by the camera model's scatter (module docstring).

    The plain fit is :func:`opnav.image.attitude.wahba_gated`'s in centroid sigmas. When it drops more
    than ``max_dropped_fraction`` of the stars, or stops at ``min_stars`` stars with one still outside
    its gate (a frame of 3 or 4 stars whose camera model is off cannot drop enough to say so), and
    :func:`model_scatter_px` finds a scatter, each star's sigma in the gate and the weights is its
    centroid sigma and that scatter in quadrature, and the attitude covariance carries the scatter
    too. Otherwise (every frame whose stars a well-known camera explains) the fit is the plain one.

    Parameters
    ----------
    b_cam, v_icrf, sigma_px, camera
        As :func:`model_scatter_px`.
    min_stars : int
        The gate keeps at least this many stars.
    max_dropped_fraction : float
        See above.
    """
    sigma_px = np.asarray(sigma_px, dtype=float)
    solution, kept = wahba_gated(b_cam, v_icrf, sigma_rad=sigma_px * camera.pixel_scale_rad, min_stars=min_stars,
                                 gate_probability=_GATE_PROBABILITY)
    z2 = (solution.residuals_rad / (sigma_px[kept] * camera.pixel_scale_rad)) ** 2
    exhausted = z2.size > 0 and float(z2.max()) > chi2_quantile(_GATE_PROBABILITY, 2)
    if 1.0 - kept.mean() <= max_dropped_fraction and not exhausted:
        return GatedAttitude(solution, kept, sigma_px, 0.0)
    scatter = model_scatter_px(b_cam, v_icrf, sigma_px, camera)
    if scatter == 0.0:
        return GatedAttitude(solution, kept, sigma_px, 0.0)
    widened = np.sqrt(sigma_px**2 + scatter**2)
    solution, kept = wahba_gated(b_cam, v_icrf, sigma_rad=widened * camera.pixel_scale_rad, min_stars=min_stars,
                                 gate_probability=_GATE_PROBABILITY)
    return GatedAttitude(solution, kept, widened, scatter)
