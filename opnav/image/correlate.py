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
   model is moved by cubic-spline interpolation (exact to ~1e-3 px for a PSF of >= 1 px sigma);
   magnifying it would widen its blur too, which a nearer body's image does not, so a Laplacian
   term takes that back out (:func:`_fit_model`). Fitting the whole model, rather than a
   paraboloid through the correlation peak, has no pixel-locking bias. Saturated pixels (the
   camera's full well or converter top) and their neighbours are left out.
4. Covariance of ``d`` from the fit, ``(J^T W J)^-1`` (the spline's own slopes) scaled by the
   reduced chi-square of the residuals when it exceeds one (a model that is not quite the body:
   shape, albedo marks).
5. A second pass renders the model at the first pass's centre and scale and fits again: the
   interpolated shift and scale are then hundredths of a pixel.
6. The model image's own error (:func:`template_error_cov`): a renderer's light moves with the
   body's place within its pixels (its rays and facets alias), by up to 0.1 px on a 5 px crescent;
   that error is a shift, which no residual shows, so it is measured by drawing the model a quarter
   pixel over and fitting it to itself, and added to the covariance.

The centre is the predicted centre's pixel moved by ``d``: the model's centre of figure is known,
so the phase's offset of the light from the centre is in the model, not in the answer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Protocol

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
    the sub-pixel fit; ``passes``: model renders (each after the first at the previous fit);
    ``template_error``: add the model image's own error to the covariance (step 6; two more renders:
    a caller that reads only the centre may leave it out)."""

    search_px: int = 10
    supersample: int | None = None
    iterations: int = 8
    passes: int = 2
    template_error: bool = True

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
    templates = EllipsoidTemplates(psf_sigma_px, supersample)
    box = templates.box(camera, pose)
    return templates.render(camera, pose, box), box


class Templates(Protocol):
    """How a body's model image is drawn: :class:`EllipsoidTemplates`, or
    :class:`opnav.image.mesh_centre.MeshTemplates` for a shape model."""

    def box(self, camera: Camera, pose) -> tuple[int, int, int, int]:
        """``(x0, y0, width, height)``, detector px, of the model image of ``pose``."""

    def render(self, camera: Camera, pose, box: tuple[int, int, int, int]) -> np.ndarray:
        """The noise-free model image of ``pose`` over ``box`` (any units: the fit scales it)."""


@dataclass(frozen=True)
class EllipsoidTemplates:
    """Model images of an ellipsoid (:func:`opnav.image.ellipsoid.render_ellipsoid`) with a Gaussian PSF of
    ``psf_sigma_px`` px, ``supersample`` rays per pixel per axis where the shading is smooth (None: 2)."""

    psf_sigma_px: float
    supersample: int | None = None

    def box(self, camera: Camera, pose: EllipsoidPose) -> tuple[int, int, int, int]:
        return outline_box(camera, pose, 4.0 * self.psf_sigma_px + 3.0)

    def render(self, camera: Camera, pose: EllipsoidPose, box: tuple[int, int, int, int]) -> np.ndarray:
        ss = self.supersample if self.supersample is not None else 2
        return render_ellipsoid(camera, pose, box, psf_sigma_px=self.psf_sigma_px, supersample=ss)


def correlate_centre(image: np.ndarray, camera: Camera, pose, *, psf_sigma_px: float,
                     noise: DetectorNoise, options: CorrelationOptions = CorrelationOptions(),
                     template: tuple[np.ndarray, tuple[int, int, int, int]] | None = None,
                     templates: Templates | None = None) -> CorrelationCentre:
    """Centre of the body by cross-correlation with its model image (module docstring), in
    ``options.passes`` passes: each after the first renders the model at the previous pass's
    centre and scale (range), so the interpolated shift and scale of the model are small.

    Parameters
    ----------
    image : (H, W) array
        Frame, ADU.
    camera : Camera
    pose : EllipsoidPose or MeshPose
        Predicted pose (camera frame, km): what ``templates`` draws; only its ``r_cam_km`` and
        ``at`` are read here.
    psf_sigma_px : float
        Gaussian PSF sigma, px.
    noise : DetectorNoise
    options : CorrelationOptions
    template : (model, box), optional
        The first pass's model image, already drawn for ``pose``.
    templates : Templates, optional
        How model images are drawn; default :class:`EllipsoidTemplates` (``psf_sigma_px``,
        ``options.supersample``).

    Returns
    -------
    CorrelationCentre
        ``xy_px`` and ``cov_xy_px2`` in detector px; ``shift_px`` from ``pose``'s projection.

    Raises
    ------
    NoSolutionError
        The model's box and search area leave the frame, or the fit fails.
    """
    image = np.asarray(image, float)
    if image.shape != camera.shape:
        raise InputError(f"image shape {image.shape} does not match the camera {camera.shape}")
    templates = templates or EllipsoidTemplates(psf_sigma_px, options.supersample)
    start = camera.project(pose.r_cam_km)
    range0 = float(np.linalg.norm(pose.r_cam_km))
    scale = 1.0
    for k in range(options.passes):
        if template is None:
            box = templates.box(camera, pose)
            template = (templates.render(camera, pose, box), box)
        fit, window = _correlate_once(image, camera, pose, template, psf_sigma_px=psf_sigma_px, noise=noise,
                                      options=options, search_px=options.search_px if k == 0 else 2,
                                      last=k + 1 == options.passes)
        scale *= fit.scale
        if k + 1 < options.passes:
            pose, template = pose.at(camera.unproject(fit.xy_px) * range0 / scale), None
    cov = fit.cov_xy_px2
    if options.template_error:
        cov = cov + template_error_cov(camera, pose, template, window, templates, psf_sigma_px=psf_sigma_px,
                                       iterations=options.iterations)
    return replace(fit, xy_px=fit.xy_px, cov_xy_px2=cov, shift_px=fit.xy_px - start, scale=float(scale))


@dataclass(frozen=True)
class _Fit:
    """The sub-pixel fit's parameters (``frac`` (2,) px beyond the whole-pixel shift, ``scale``, ``gain``,
    ``back``), its normal matrix (5, 5) and residuals (the window's shape); these two None when not
    asked for."""

    frac: np.ndarray
    scale: float
    gain: float
    back: float
    normal: np.ndarray | None
    resid: np.ndarray | None


def _fit_model(data: np.ndarray, weight: np.ndarray, model: np.ndarray, centre_t: np.ndarray, blur2: float,
               frac: np.ndarray, scale: float, gain: float, back: float, iterations: int, *,
               with_normal: bool = True) -> _Fit:
    """Step 3: Gauss-Newton fit of ``gain * model(c + (x - c - d) / k) + back`` to ``data`` with
    ``weight`` (1 / variance), ``c = centre_t`` (model px), from the given start.

    Magnifying the model also widens its blur by the scale, which a body nearer by that much does
    not: the Laplacian term takes the widening (``blur2``, px^2, the blur that does not grow with the
    body) back out, to first order in ``scale - 1``. Without it a 10 px crescent's fitted scale went
    56 % of the way to a 1 % range error and its centre moved 0.02 px (6 sigma at 2e4 e-) along the
    phase direction; passes recovered half of that each. The normal matrix is from the spline's own
    slopes (for a covariance); ``with_normal`` False: neither it nor the residuals (the parameters
    alone, for a centre alone)."""
    h, w = model.shape
    coeffs = ndimage.spline_filter(model, order=3, mode="constant")
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    frac = np.array(frac, float)
    wflat = weight.ravel()

    def moved_model(frac, scale):
        # output pixel p shows the model at centre + (p - centre - d) / scale
        src_x = centre_t[0] + (xx - centre_t[0] - frac[0]) / scale
        src_y = centre_t[1] + (yy - centre_t[1] - frac[1]) / scale
        moved = ndimage.map_coordinates(coeffs, [src_y, src_x], order=3, mode="constant", prefilter=False)
        laplace = ndimage.laplace(moved, mode="constant")
        return moved - (scale - 1.0) * blur2 * laplace, src_x, src_y, laplace

    def jacobian(moved, src_x, src_y, laplace, scale, exact):
        if exact:
            # the final covariance: the spline's own slope (a central difference across whole pixels
            # reads a 1.2 px PSF's edges ~5 % too shallow, the covariance as much too small)
            h_px = 0.01
            gx = (ndimage.map_coordinates(coeffs, [src_y, src_x + h_px], order=3, mode="constant", prefilter=False)
                  - ndimage.map_coordinates(coeffs, [src_y, src_x - h_px], order=3, mode="constant",
                                            prefilter=False)) / (2.0 * h_px * scale)
            gy = (ndimage.map_coordinates(coeffs, [src_y + h_px, src_x], order=3, mode="constant", prefilter=False)
                  - ndimage.map_coordinates(coeffs, [src_y - h_px, src_x], order=3, mode="constant",
                                            prefilter=False)) / (2.0 * h_px * scale)
        else:
            gy, gx = np.gradient(moved)
        d_scale = -((xx - centre_t[0] - frac[0]) * gx + (yy - centre_t[1] - frac[1]) * gy) / scale - blur2 * laplace
        return np.stack([-gain * gx.ravel(), -gain * gy.ravel(), gain * d_scale.ravel(), moved.ravel(),
                         np.ones(moved.size)], 1)

    for _ in range(iterations):
        moved, src_x, src_y, laplace = moved_model(frac, scale)
        jac = jacobian(moved, src_x, src_y, laplace, scale, exact=False)
        resid = (data - gain * moved - back).ravel()
        wj = jac * wflat[:, None]
        try:
            step = np.linalg.solve(jac.T @ wj, wj.T @ resid)
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
    if not with_normal:
        return _Fit(frac, float(scale), float(gain), float(back), None, None)
    moved, src_x, src_y, laplace = moved_model(frac, scale)
    jac = jacobian(moved, src_x, src_y, laplace, scale, exact=True)
    normal = jac.T @ (jac * wflat[:, None])
    return _Fit(frac, float(scale), float(gain), float(back), normal, data - gain * moved - back)


def _blur2(psf_sigma_px: float) -> float:
    """The blur that does not grow with the body, variance px^2 per axis: the PSF plus the pixel's box
    twice (the scene's pixel mean and the pixel-integrated kernel)."""
    return psf_sigma_px**2 + 1.0 / 6.0


def _correlate_once(image: np.ndarray, camera: Camera, pose, template: tuple[np.ndarray, tuple[int, int, int, int]],
                    *, psf_sigma_px: float, noise: DetectorNoise, options: CorrelationOptions,
                    search_px: int, last: bool = True) -> tuple[CorrelationCentre, np.ndarray]:
    """One pass of :func:`correlate_centre` (module docstring, steps 2-4) with the model image
    ``template`` drawn for ``pose``: the centre, and the weights (1 / variance) of the window of
    the frame it fitted; ``last`` False for a pass whose covariance is not kept (its centre and scale
    alone: the covariance and chi-square NaN)."""
    model, (x0, y0, w, h) = template
    s = search_px
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
    # a saturated pixel says only that the light there was more than its well held, and blooming
    # moves the excess along its column into the next: neither is the model's light (a 38 px body at
    # a fixed exposure filled its wells, chi-square per dof 4,600 and its centre 3 sigma off), so
    # they and their neighbours carry no weight
    saturated = data >= saturation_adu(camera, noise)
    if saturated.any():
        weight[ndimage.binary_dilation(saturated, np.ones((3, 3), bool))] = 0.0
        if np.count_nonzero(weight) < 20:
            raise NoSolutionError("the body's pixels are saturated")
    # the prediction's centre in the model image's pixels: the point the scale acts about
    centre_t = camera.project(pose.r_cam_km) - np.array([x0, y0], float)
    # gain and background by linear least squares on the model as predicted (a body filling its box
    # makes the box's median the body's brightness, not the sky's)
    used = weight.ravel() > 0.0
    (gain, back), *_ = np.linalg.lstsq(np.column_stack([model.ravel()[used], np.ones(int(used.sum()))]),
                                       data.ravel()[used], rcond=None)
    fit = _fit_model(data, weight, model, centre_t, _blur2(psf_sigma_px), np.zeros(2), 1.0, float(gain), float(back),
                     options.iterations, with_normal=last)
    dof = int(np.count_nonzero(weight) - 5)
    if last:
        chi2 = float(np.sum(fit.resid * fit.resid * weight))
        try:
            cov = np.linalg.inv(fit.normal)[:2, :2] * max(chi2 / dof, 1.0)
        except np.linalg.LinAlgError:
            raise NoSolutionError("the correlation fit's normal matrix is singular (a flat model or frame)") from None
    else:
        chi2, cov = math.nan, np.full((2, 2), math.nan)
    shift = np.array([ix, iy], float) + fit.frac
    centre = camera.project(pose.r_cam_km) + shift
    if not math.isfinite(float(centre.sum())):
        raise NoSolutionError("the correlation centre is not finite")
    return CorrelationCentre(xy_px=centre, cov_xy_px2=0.5 * (cov + cov.T), shift_px=shift, scale=fit.scale, peak=peak,
                             chi2=chi2, dof=dof), weight


def saturation_adu(camera: Camera, noise: DetectorNoise) -> float:
    """The value (ADU) from which a pixel of ``camera`` counts as saturated: its full well (or the
    converter's top) less five read-noise sigmas (a saturated pixel is read with its read noise)."""
    top = min(noise.bias_adu + camera.full_well_e / noise.gain_e_per_adu, 2.0**camera.bit_depth - 1.0)
    return top - 5.0 * noise.read_noise_e / noise.gain_e_per_adu


#: Sub-pixel moves (px) of the model at which :func:`template_error_cov` draws it again.
TEMPLATE_MOVES_PX = ((0.25, 0.0), (0.0, 0.25))


def template_error_cov(camera: Camera, pose, template: tuple[np.ndarray, tuple[int, int, int, int]],
                       weight: np.ndarray, templates: Templates, *, psf_sigma_px: float,
                       iterations: int = 8) -> np.ndarray:
    """Covariance (2, 2), px^2, of the centre's error that the model image's own drawing makes (step 6).

    A rendered model's light is right only to the renderer's pixel-phase error (its pixels' light is
    convolved with the PSF as if it sat at their centres, and rays and facets alias; it moves with the
    body's position within its pixels: 0.004-0.017 px on a 10 px
    shape model, up to 0.1 px on a 5 px crescent), and the fit moves it by whatever that error is
    at the pose it was drawn for: an error no residual shows, since it is a shift. It is measured
    by drawing the model again at the pose moved by each of :data:`TEMPLATE_MOVES_PX` and fitting
    the first model to it (``weight`` the frame's, 1 / variance, over the model's box): each fit's
    shift minus the move is the difference of two draws' errors, whose covariance is twice the
    error's, at a quarter pixel apart (a pixel-periodic error's two draws then uncorrelated).

    Parameters
    ----------
    camera : Camera
    pose : EllipsoidPose or MeshPose
        The pose ``template`` was drawn for (camera frame, km).
    template : (model, box)
    weight : array, the model's shape
    templates : Templates
    psf_sigma_px : float

    Returns
    -------
    (2, 2) array, detector px^2
    """
    model, box = template
    centre = camera.project(pose.r_cam_km)
    centre_t = centre - np.array(box[:2], float)
    range_km = float(np.linalg.norm(pose.r_cam_km))
    cov = np.zeros((2, 2))
    for move in TEMPLATE_MOVES_PX:
        moved = pose.at(camera.unproject(centre + np.array(move)) * range_km)
        truth = camera.project(moved.r_cam_km) - centre
        try:
            fit = _fit_model(templates.render(camera, moved, box), weight, model, centre_t, _blur2(psf_sigma_px), truth,
                             1.0, 1.0, 0.0, iterations, with_normal=False)
        except NoSolutionError:
            raise NoSolutionError("the body's model image does not fit itself a quarter pixel over") from None
        error = fit.frac - truth
        cov += np.outer(error, error)
    return cov / (2.0 * len(TEMPLATE_MOVES_PX))
