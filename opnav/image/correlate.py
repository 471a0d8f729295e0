"""Centre of a small or irregularly lit body by cross-correlation with a model image.

Steps (:func:`correlate_centre`):

1. Model image of the body at its predicted pose (:func:`opnav.image.ellipsoid.render_ellipsoid`:
   the renderer's shading, pixel integral and PSF), over the outline's box plus a PSF's reach.
2. Whole-pixel search: normalised cross-correlation (OpenCV ``matchTemplate``, ``TM_CCOEFF_NORMED``)
   of the model against the frame within ``search_px`` of the prediction; the best peak.
3. Sub-pixel peak: Gauss-Newton fit of ``gain * model(c + (x - c - d) / k) + background`` to the
   frame's pixels under the model's box, weighted by the pixels' shot and read noise: ``d`` the
   shift, ``k`` the scale about the predicted centre ``c`` (a range error of the prediction makes
   the body bigger or smaller, and a phased body's light is off its centre, so an unfitted scale
   would move the centre: 0.3 px for a 1 % range error on a 100 px Mars at 30 deg phase). The
   model is moved by cubic-spline interpolation (exact to ~1e-3 px for a PSF of >= 1 px sigma).
   Fitting the whole model, rather than a paraboloid through the correlation peak, has no
   pixel-locking bias.
4. Covariance of ``d`` from the fit, ``(J^T W J)^-1`` scaled by the reduced chi-square of the
   residuals when it exceeds one (a model that is not quite the body: shape, albedo marks).

5. A second pass renders the model at the first pass's centre and scale and fits again: the
   interpolated shift and scale are then hundredths of a pixel, where interpolating a model
   made a pixel or a percent away leaves ~0.01-0.03 px that depend on the prior.

The centre is the predicted centre's pixel moved by ``d``: the model's centre of figure is known,
so the phase's offset of the light from the centre is in the model, not in the answer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy import ndimage

from ..camera import Camera
from ..errors import InputError, NoSolutionError
from .ellipsoid import EllipsoidPose, outline_box, render_ellipsoid


@dataclass(frozen=True)
class DetectorNoise:
    """Pixel noise model: ``var_ADU = (read_noise_e^2 + max(signal_e, 0)) / gain^2``, with
    ``signal_e = (value_ADU - bias_adu) * gain``."""

    read_noise_e: float
    gain_e_per_adu: float
    bias_adu: float

    def variance_adu2(self, image: np.ndarray) -> np.ndarray:
        signal = np.maximum((np.asarray(image, float) - self.bias_adu) * self.gain_e_per_adu, 0.0)
        return (self.read_noise_e**2 + signal) / self.gain_e_per_adu**2


@dataclass(frozen=True)
class CorrelationOptions:
    """``search_px``: how far from the prediction the peak may lie; ``supersample``: rays per pixel
    per axis of the model where its shading is smooth (None: 2, a midpoint rule good to ~1e-4 of the
    peak there; the pixels the limb or the terminator
    crosses get :data:`opnav.bodies.EDGE_SUPERSAMPLE`); ``iterations``: Gauss-Newton steps of
    the sub-pixel fit; ``passes``: model renders (each after the first at the previous fit)."""

    search_px: int = 10
    supersample: int | None = None
    iterations: int = 8
    passes: int = 2

    def __post_init__(self) -> None:
        if not (isinstance(self.search_px, int) and self.search_px >= 1):
            raise InputError(f"CorrelationOptions.search_px must be a positive integer, got {self.search_px!r}")
        if (self.supersample is not None and self.supersample < 1) or self.iterations < 1 or self.passes < 1:
            raise InputError("CorrelationOptions.supersample, iterations and passes must be >= 1")


@dataclass(frozen=True)
class CorrelationCentre:
    """``xy_px`` (2,) centre of figure, detector px, with ``cov_xy_px2`` (2, 2); ``shift_px`` (2,)
    from the prediction; ``scale`` the body's size over the model's (the predicted range over the
    range the frame shows); ``peak`` the normalised correlation at the whole-pixel peak; ``chi2``
    and ``dof`` of the sub-pixel fit."""

    xy_px: np.ndarray
    cov_xy_px2: np.ndarray
    shift_px: np.ndarray
    scale: float
    peak: float
    chi2: float
    dof: int


def model_template(camera: Camera, pose: EllipsoidPose, *, psf_sigma_px: float,
                   supersample: int | None = None) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """The model image (step 1) and its box ``(x0, y0, width, height)``, detector px; ``supersample``
    None: 2 (:class:`CorrelationOptions`)."""
    box = outline_box(camera, pose, 4.0 * psf_sigma_px + 3.0)
    ss = supersample if supersample is not None else 2
    return render_ellipsoid(camera, pose, box, psf_sigma_px=psf_sigma_px, supersample=ss), box


def correlate_centre(image: np.ndarray, camera: Camera, pose: EllipsoidPose, *, psf_sigma_px: float,
                     noise: DetectorNoise, options: CorrelationOptions = CorrelationOptions(),
                     template: tuple[np.ndarray, tuple[int, int, int, int]] | None = None) -> CorrelationCentre:
    """Centre of the body by cross-correlation with its model image (module docstring), in
    ``options.passes`` passes: each after the first renders the model at the previous pass's
    centre and scale (range), so the interpolated shift and scale of the model are small."""
    start = camera.project(pose.r_cam_km)
    range0 = float(np.linalg.norm(pose.r_cam_km))
    fit = _correlate_once(image, camera, pose, psf_sigma_px=psf_sigma_px, noise=noise, options=options,
                          template=template)
    scale = fit.scale
    for _ in range(options.passes - 1):
        pose = pose.at(camera.unproject(fit.xy_px) * range0 / scale)
        fit = _correlate_once(image, camera, pose, psf_sigma_px=psf_sigma_px, noise=noise,
                              options=replace(options, search_px=2))
        scale *= fit.scale
    return replace(fit, shift_px=fit.xy_px - start, scale=float(scale))


def _correlate_once(image: np.ndarray, camera: Camera, pose: EllipsoidPose, *, psf_sigma_px: float,
                    noise: DetectorNoise, options: CorrelationOptions,
                    template: tuple[np.ndarray, tuple[int, int, int, int]] | None = None) -> CorrelationCentre:
    """One pass of :func:`correlate_centre` (module docstring, steps 1-4).

    Parameters
    ----------
    image : (H, W) array
        Frame, ADU.
    camera : Camera
    pose : EllipsoidPose
        Predicted pose (camera frame, km).
    psf_sigma_px : float
        Gaussian PSF sigma, px.
    noise : DetectorNoise
    options : CorrelationOptions
    template : (model, box), optional
        A model image already made for ``pose`` (:func:`model_template`).

    Raises
    ------
    NoSolutionError
        The model's box and search area leave the frame, or the fit fails.
    """
    image = np.asarray(image, float)
    if image.shape != camera.shape:
        raise InputError(f"image shape {image.shape} does not match the camera {camera.shape}")
    model, (x0, y0, w, h) = template if template is not None else model_template(
        camera, pose, psf_sigma_px=psf_sigma_px, supersample=options.supersample)
    s = options.search_px
    rows, cols = image.shape
    if x0 - s < 0 or y0 - s < 0 or x0 + w + s > cols or y0 + h + s > rows:
        raise NoSolutionError("the body's model and search area reach beyond the frame")
    region = image[y0 - s:y0 + h + s, x0 - s:x0 + w + s].astype(np.float32)
    score = cv2.matchTemplate(region, model.astype(np.float32), cv2.TM_CCOEFF_NORMED)
    iy, ix = np.unravel_index(int(np.argmax(score)), score.shape)
    peak = float(score[iy, ix])
    if not np.isfinite(peak) or peak <= 0:
        raise NoSolutionError("no correlation peak of the body's model")
    ix, iy = ix - s, iy - s
    data = image[y0 + iy:y0 + iy + h, x0 + ix:x0 + ix + w]
    weight = 1.0 / noise.variance_adu2(data)
    coeffs = ndimage.spline_filter(model, order=3, mode="constant")
    # the prediction's centre in the model image's pixels: the point the scale acts about
    centre_t = camera.project(pose.r_cam_km) - np.array([x0, y0], float)
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    frac = np.zeros(2)  # (dx, dy) beyond the whole-pixel shift
    scale = 1.0
    # gain and background by linear least squares on the model as predicted (a body filling its box
    # makes the box's median the body's brightness, not the sky's)
    (gain, back), *_ = np.linalg.lstsq(np.column_stack([model.ravel(), np.ones(model.size)]), data.ravel(), rcond=None)
    gain, back = float(gain), float(back)
    wflat = weight.ravel()

    def moved_model(frac, scale):
        # output pixel p shows the model at centre + (p - centre - d) / scale
        src_x = centre_t[0] + (xx - centre_t[0] - frac[0]) / scale
        src_y = centre_t[1] + (yy - centre_t[1] - frac[1]) / scale
        return ndimage.map_coordinates(coeffs, [src_y, src_x], order=3, mode="constant", prefilter=False)

    for _ in range(options.iterations):
        moved = moved_model(frac, scale)
        gy, gx = np.gradient(moved)
        d_scale = -((xx - centre_t[0] - frac[0]) * gx + (yy - centre_t[1] - frac[1]) * gy) / scale
        jac = np.stack([-gain * gx.ravel(), -gain * gy.ravel(), gain * d_scale.ravel(), moved.ravel(),
                        np.ones(moved.size)], 1)
        resid = (data - gain * moved - back).ravel()
        wj = jac * wflat[:, None]
        normal = jac.T @ wj
        try:
            step = np.linalg.solve(normal, wj.T @ resid)
        except np.linalg.LinAlgError:
            raise NoSolutionError("the correlation fit's normal matrix is singular (a flat model or frame)") from None
        frac += step[:2]
        scale += step[2]
        gain += step[3]
        back += step[4]
        if np.max(np.abs(frac)) > 2.0 or not gain > 0 or not 0.8 < scale < 1.25:
            raise NoSolutionError("the correlation fit left its peak")
        if np.max(np.abs(step[:2])) < 1e-6:
            break
    moved = moved_model(frac, scale)
    resid = data - gain * moved - back
    chi2 = float(np.sum(resid * resid * weight))
    dof = int(data.size - 5)
    try:
        cov = np.linalg.inv(normal)[:2, :2] * max(chi2 / dof, 1.0)
    except np.linalg.LinAlgError:
        raise NoSolutionError("the correlation fit's normal matrix is singular (a flat model or frame)") from None
    shift = np.array([ix, iy], float) + frac
    centre = camera.project(pose.r_cam_km) + shift
    if not math.isfinite(float(centre.sum())):
        raise NoSolutionError("the correlation centre is not finite")
    return CorrelationCentre(xy_px=centre, cov_xy_px2=0.5 * (cov + cov.T), shift_px=shift, scale=float(scale), peak=peak, chi2=chi2,
                             dof=dof)
