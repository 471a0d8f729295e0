"""Camera calibration from identified stars: focal length, principal point, Brown distortion and each frame's attitude.

The camera of :mod:`opnav.camera` (pinhole + Brown radial ``k1, k2, k3`` and tangential ``p1, p2``)
is fitted to stars whose catalog directions are known (identified by the plate solver or a WCS
prior), in one or many frames of one camera, together with each frame's attitude:

1. **Model and free parameters.** ``model`` (:data:`MODELS`) says which distortion coefficients the
   camera has (the others are held at 0); ``fit`` which of the model's parameters (:data:`PARAMETERS`)
   are estimated (the others keep the starting camera's values).
2. **Unknowns in pixels at the corner.** Each camera parameter is scaled by the displacement a unit
   change makes at the detector corner (``f``: the corner's normalised radius ``r_c``; ``cx, cy``: 1;
   ``k_n``: ``f r_c^(2n+1)``; ``p_n``: ``f r_c^2``) and each frame's attitude correction (a rotation
   vector in the camera frame, ``R = R0 exp(theta)``) by ``f``, so the normal matrix is well
   conditioned whatever the field of view.
3. **Residuals.** ``project(R^T v) - xy`` for every star, whitened by its centroid covariance, with
   analytic Jacobians (:func:`residual_jacobian`; a test checks them against central differences).
4. **Observability.** The Fisher information of the stars given (their covariances) gives each
   parameter's 1-sigma as a displacement at the corner, the frames' attitudes marginalised. Before
   the fit (at the starting camera) a parameter without any bound is refused; after it (at the
   solution: how well the principal point is known depends on the distortion, whose centre it is)
   a parameter above ``max_sigma_px`` is not observable from these stars and the model is refused,
   naming it (:class:`opnav.errors.InputError`).
5. **Robust fit.** Levenberg-Marquardt with the ``soft_l1`` loss (scale: 3 sigma; iteratively reweighted), then
   stars whose whitened residual exceeds the chi-square(2) ``gate_probability`` quantile are
   rejected and the model refitted by plain least squares on the rest (repeated until no star
   changes side), so the covariance is the Gaussian one of the kept stars. A frame left with fewer
   than 3 stars within the gate (its identification is wrong) is left out and named
   (:attr:`Calibration.dropped`), and the others fitted again. When the gate would
   reject more than ``MAX_REJECTED_FRACTION`` of the stars the model is refused: it is the model
   (too few distortion terms) or the centroid covariances that are wrong, not the stars.
6. **Covariance.** The inverse normal matrix at the solution with the centroid covariances as given
   (not scaled by the fit's chi-square: its ``chi2_per_dof`` says whether they were honest).
7. **Centroid floor.** ``sigma_floor_px`` adds a per-axis error in quadrature to every star's
   covariance: what a centroider's covariance leaves out, chiefly the error of fitting a Gaussian
   to a PSF that is not one, which depends on where the star falls on its pixel (on rendered
   12-degree frames of an Airy PSF with its first dark ring at 1.5 px the stars' chi-square per dof
   against the truth is 3.5, 8.8 for the brightest quarter). ``"auto"`` estimates it from the
   stars (:func:`estimate_floor_px`): after a robust fit with the covariances as given, the floor at
   which the median of the stars' whitened squared residuals is chi-square(2)'s median (a median:
   outliers do not move it), scaled by the residuals' degrees of freedom; 0 when they are within
   their covariances already.

The "before" residuals of :class:`Calibration` are those of the starting camera with each frame's
attitude fitted alone, so they show what the uncalibrated camera leaves across the field.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import gammaincinv

from ..camera import CALIBRATION_PARAMETERS, Camera
from ..errors import ConvergenceError, InputError

#: Every camera parameter a calibration can fit: focal length and principal point in px, then the
#: Brown coefficients (dimensionless, on the normalised image plane; docs/conventions.md).
PARAMETERS = CALIBRATION_PARAMETERS
#: Which distortion coefficients each model has (the others are 0).
MODELS = {
    "pinhole": (),
    "radial1": ("k1",),
    "radial2": ("k1", "k2"),
    "radial3": ("k1", "k2", "k3"),
    "brown": ("k1", "k2", "k3", "p1", "p2"),
    # a narrow field's Brown model: k2 and k3 move the corner by (k2 / k1) r_c^2 and (k3 / k1) r_c^4 of
    # k1's displacement (r_c the corner's normalised radius: 0.012 on a 1-degree camera), nothing for any
    # real lens, while fitted they take values no lens has and carry the stars' noise to the field centre
    "brown1": ("k1", "p1", "p2"),
}
#: Units of each parameter, for files and reports.
UNITS = {"f": "px", "cx": "px", "cy": "px", "k1": "", "k2": "", "k3": "", "p1": "", "p2": ""}
#: Default bound on a parameter's 1-sigma displacement at the detector corner, px (module step 4).
MAX_SIGMA_PX = 10.0
#: ``fit`` value (the default) that fits what the stars constrain: the principal point with a prior.
AUTO = "auto"
#: Default per-axis 1-sigma of a starting camera's principal point in ``fit="auto"``, px (module step 4).
PRINCIPAL_POINT_SIGMA_PX = 5.0
#: Stars a frame needs: 3 for its attitude and one to spare for the camera.
MIN_STARS_PER_FRAME = 4
#: Largest share of the stars the gate may reject: beyond it the model, not the stars, is wrong.
MAX_REJECTED_FRACTION = 1.0 / 3.0


@dataclass(frozen=True)
class FrameStars:
    """The identified stars of one frame.

    Attributes
    ----------
    xy : ndarray, shape (N, 2)
        Measured centroids, px (docs/conventions.md: x column, y row, (0, 0) the first pixel's centre).
    cov : ndarray, shape (N, 2, 2)
        Their covariances, px^2.
    v_icrf : ndarray, shape (N, 3)
        Apparent catalog directions of the same stars (proper motion, parallax and the observer's
        aberration applied), unit vectors, ICRF.
    R_icrf_cam : Rotation
        Starting attitude, camera frame -> ICRF.
    name : str
        The frame (file name), for messages and reports.
    """

    xy: np.ndarray
    cov: np.ndarray
    v_icrf: np.ndarray
    R_icrf_cam: Rotation
    name: str = "frame"

    def __post_init__(self) -> None:
        xy = np.asarray(self.xy, dtype=float).reshape(-1, 2)
        cov = np.asarray(self.cov, dtype=float).reshape(-1, 2, 2)
        v = np.asarray(self.v_icrf, dtype=float).reshape(-1, 3)
        if not (len(xy) == len(cov) == len(v)):
            raise InputError(f"{self.name}: xy ({len(xy)}), cov ({len(cov)}) and v_icrf ({len(v)}) need one row per star")
        if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(cov)) and np.all(np.isfinite(v))):
            raise InputError(f"{self.name}: star positions, covariances and directions must be finite")
        det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0]
        if np.any(cov[:, 0, 0] <= 0) or np.any(det <= 0):
            raise InputError(f"{self.name}: every centroid covariance must be positive definite (px^2)")
        object.__setattr__(self, "xy", xy)
        object.__setattr__(self, "cov", cov)
        object.__setattr__(self, "v_icrf", v / np.linalg.norm(v, axis=1, keepdims=True))


@dataclass(frozen=True)
class FrameFit:
    """One frame after the calibration.

    Attributes
    ----------
    name : str
    xy : ndarray, shape (N, 2)
        Measured centroids, px.
    residual_before_px : ndarray, shape (N, 2)
        Predicted minus measured position with the starting camera and the frame's attitude fitted alone, px.
    residual_after_px : ndarray, shape (N, 2)
        The same with the calibrated camera and attitude, px.
    kept : ndarray of bool, shape (N,)
        Stars the fit used (False: rejected as outliers, module step 5).
    R_icrf_cam : Rotation
        Fitted attitude, camera frame -> ICRF.
    attitude_cov_rad2 : ndarray, shape (3, 3)
        Covariance of the camera-frame rotation vector, rad^2 (the camera parameters marginalised).
    """

    name: str
    xy: np.ndarray
    residual_before_px: np.ndarray
    residual_after_px: np.ndarray
    kept: np.ndarray
    R_icrf_cam: Rotation
    attitude_cov_rad2: np.ndarray

    @property
    def rms_px(self) -> float:
        """Post-fit RMS per axis of the kept stars, px."""
        r = self.residual_after_px[self.kept]
        return float(np.sqrt(np.mean(r**2))) if len(r) else math.nan

    @property
    def rms_before_px(self) -> float:
        """RMS per axis of the kept stars with the starting camera, px."""
        r = self.residual_before_px[self.kept]
        return float(np.sqrt(np.mean(r**2))) if len(r) else math.nan


@dataclass(frozen=True)
class Calibration:
    """Result of :func:`calibrate`.

    Attributes
    ----------
    camera : Camera
        The calibrated camera (the starting camera with the fitted parameters).
    start : Camera
        The starting camera (coefficients outside the model set to 0).
    model : str
        :data:`MODELS` key.
    names : tuple of str
        Fitted parameters, in :data:`PARAMETERS` order.
    values : ndarray, shape (P,)
        Their values (``f``, ``cx``, ``cy`` in px; Brown coefficients dimensionless).
    covariance : ndarray, shape (P, P)
        Their covariance (units of ``values`` squared), frames' attitudes marginalised.
    frames : tuple of FrameFit
    chi2 : float
        Sum of the kept stars' whitened squared residuals.
    dof : int
        Residuals (2 per kept star, 1 per prior) less unknowns.
    elapsed_s : float
        Wall-clock time of the fit, s.
    prior_sigma : ndarray, shape (P,)
        1-sigma of each fitted parameter's Gaussian prior (centred on the starting camera's value),
        units of ``values``; inf: none (the stars alone).
    held : tuple of str
        The model's parameters ``fit="auto"`` left at the starting camera's values because the stars
        do not constrain them.
    dropped : tuple of str
        Frames left out because fewer than 3 of their stars fit the camera within the gate (a wrong
        identification), each with the reason; ``frames`` holds the others.
    sigma_floor_px : float
        The centroid floor the fit used (given, or estimated with ``"auto"``), px (module step 7).
    """

    camera: Camera
    start: Camera
    model: str
    names: tuple[str, ...]
    values: np.ndarray
    covariance: np.ndarray
    frames: tuple[FrameFit, ...]
    chi2: float
    dof: int
    elapsed_s: float
    prior_sigma: np.ndarray | None = None
    held: tuple[str, ...] = ()
    dropped: tuple[str, ...] = ()
    sigma_floor_px: float = 0.0

    def __post_init__(self) -> None:
        if self.prior_sigma is None:
            object.__setattr__(self, "prior_sigma", np.full(len(self.names), np.inf))

    @property
    def stars_share(self) -> np.ndarray:
        """Share of each parameter's information from the stars, ``1 - var / var_prior``, (P,):
        1 for a parameter without a prior, near 0 for one the stars hardly constrain."""
        return 1.0 - np.diag(self.covariance) / self.prior_sigma**2

    @property
    def sigma(self) -> np.ndarray:
        """1-sigma of each fitted parameter (units of ``values``)."""
        return np.sqrt(np.diag(self.covariance))

    @property
    def correlation(self) -> np.ndarray:
        """Correlation matrix of the fitted parameters, (P, P)."""
        s = self.sigma
        return self.covariance / np.outer(s, s)

    @property
    def chi2_per_dof(self) -> float:
        return self.chi2 / self.dof

    @property
    def n_stars(self) -> int:
        """Stars the fit kept, all frames."""
        return int(sum(int(f.kept.sum()) for f in self.frames))

    @property
    def n_rejected(self) -> int:
        return int(sum(int((~f.kept).sum()) for f in self.frames))

    @property
    def rms_px(self) -> float:
        """Post-fit RMS per axis over the kept stars of all frames, px."""
        r = np.concatenate([f.residual_after_px[f.kept] for f in self.frames])
        return float(np.sqrt(np.mean(r**2)))

    def value(self, name: str) -> float:
        """The calibrated camera's value of parameter ``name`` (fitted or held)."""
        return parameter_values(self.camera, (name,))[0]


def parameter_values(camera: Camera, names) -> np.ndarray:
    """Values of ``names`` (:data:`PARAMETERS`) of ``camera``: ``f`` is the focal length in px."""
    table = {"f": camera.focal_length_px, "cx": camera.cx_px, "cy": camera.cy_px}
    return np.array([table[n] if n in table else getattr(camera, n) for n in names], dtype=float)


def with_parameters(camera: Camera, names, values) -> Camera:
    """``camera`` with parameters ``names`` set to ``values`` (``f`` in px: the pixel pitch is kept)."""
    changes = {}
    for name, value in zip(names, values):
        if name == "f":
            changes["focal_length_mm"] = float(value) * camera.pixel_pitch_um / 1000.0
        elif name in ("cx", "cy"):
            changes[f"{name}_px"] = float(value)
        else:
            changes[name] = float(value)
    return camera.replace(**changes)


def corner_radius(camera: Camera) -> float:
    """Normalised radius (pinhole) of the detector corner farthest from the principal point."""
    dx = max(camera.cx_px + 0.5, camera.width_px - 0.5 - camera.cx_px)
    dy = max(camera.cy_px + 0.5, camera.height_px - 0.5 - camera.cy_px)
    return math.hypot(dx, dy) / camera.focal_length_px


def corner_scale(camera: Camera, names) -> np.ndarray:
    """Displacement at the detector corner, px, of a unit change of each parameter (module step 2)."""
    f, rc = camera.focal_length_px, corner_radius(camera)
    table = {"f": rc, "cx": 1.0, "cy": 1.0, "k1": f * rc**3, "k2": f * rc**5, "k3": f * rc**7,
             "p1": f * rc**2, "p2": f * rc**2}
    return np.array([table[n] for n in names])


def choose_parameters(model: str, fit) -> tuple[str, ...]:
    """The parameters to fit: ``fit`` (names of :data:`PARAMETERS`) checked against ``model``, or all of the model's.

    Raises
    ------
    InputError
        An unknown model or parameter, or one the model does not have (``--model``/``--fit``).
    """
    if model not in MODELS:
        raise InputError(f"--model {model!r} is not a camera model; accepted: {', '.join(MODELS)}")
    has = ("f", "cx", "cy") + MODELS[model]
    if fit is None:
        return has
    names = tuple(dict.fromkeys(str(n).strip().lower() for n in fit if str(n).strip()))
    unknown = [n for n in names if n not in PARAMETERS]
    if unknown:
        raise InputError(f"--fit: unknown parameter {', '.join(unknown)}; accepted: {', '.join(PARAMETERS)}")
    outside = [n for n in names if n not in has]
    if outside:
        raise InputError(f"--fit {', '.join(outside)}: not in --model {model} (its parameters: {', '.join(has)})")
    if not names:
        raise InputError(f"--fit names no parameter; accepted: {', '.join(has)}")
    return tuple(n for n in PARAMETERS if n in names)


def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices ``[v]x``."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian ``J_l(phi)``: d(exp(phi) u)/d(phi) = -[exp(phi) u]x J_l(phi)."""
    angle = float(np.linalg.norm(phi))
    k = _skew(phi)
    if angle < 1e-6:  # series to second order: the closed form loses digits near 0
        return np.eye(3) + 0.5 * k + k @ k / 6.0
    return (np.eye(3) + (1.0 - math.cos(angle)) / angle**2 * k
            + (angle - math.sin(angle)) / angle**3 * k @ k)


def residual_jacobian(camera: Camera, names, v_cam: np.ndarray, theta: np.ndarray):
    """Predicted pixels of stars and their derivatives (module step 3).

    Parameters
    ----------
    camera : Camera
        The camera at the current parameters.
    names : tuple of str
        Fitted camera parameters (:data:`PARAMETERS`).
    v_cam : ndarray, shape (N, 3)
        ``R0^T v``: the catalog directions in the frame's *starting* camera frame, unit vectors.
    theta : ndarray, shape (3,)
        Attitude correction, rad: the attitude is ``R0 exp(theta)`` (camera frame -> ICRF).

    Returns
    -------
    xy : ndarray, shape (N, 2)
        Predicted pixels, px.
    d_params : ndarray, shape (N, 2, P)
        d(xy)/d(parameters), in the parameters' units (``f``, ``cx``, ``cy`` px; Brown dimensionless).
    d_theta : ndarray, shape (N, 2, 3)
        d(xy)/d(theta), px per rad.
    """
    d = Rotation.from_rotvec(-np.asarray(theta, dtype=float)).apply(v_cam)
    xy = camera.project(d)
    xn, yn = d[:, 0] / d[:, 2], d[:, 1] / d[:, 2]
    r2 = xn * xn + yn * yn
    f = camera.focal_length_px
    radial = 1.0 + r2 * (camera.k1 + r2 * (camera.k2 + r2 * camera.k3))
    xd = xn * radial + 2.0 * camera.p1 * xn * yn + camera.p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + camera.p1 * (r2 + 2.0 * yn * yn) + 2.0 * camera.p2 * xn * yn
    columns = {
        "f": (xd, yd),
        "cx": (np.ones_like(xn), np.zeros_like(xn)),
        "cy": (np.zeros_like(xn), np.ones_like(xn)),
        "k1": (f * xn * r2, f * yn * r2),
        "k2": (f * xn * r2**2, f * yn * r2**2),
        "k3": (f * xn * r2**3, f * yn * r2**3),
        "p1": (f * 2.0 * xn * yn, f * (r2 + 2.0 * yn * yn)),
        "p2": (f * (r2 + 2.0 * xn * xn), f * 2.0 * xn * yn),
    }
    d_params = np.zeros((len(d), 2, len(names)))
    for j, name in enumerate(names):
        d_params[:, 0, j], d_params[:, 1, j] = columns[name]
    # d = exp(phi) v_cam with phi = -theta: dd/dtheta = [d]x J_l(-theta)
    dd_dtheta = _skew(d) @ _left_jacobian(-np.asarray(theta, dtype=float))
    d_theta = camera.projection_jacobian(d) @ dd_dtheta
    return xy, d_params, d_theta


def _whiteners(cov: np.ndarray) -> np.ndarray:
    """(N, 2, 2) ``U^T`` with ``U U^T = cov^-1`` (lower Cholesky factor of the information)."""
    return np.swapaxes(np.linalg.cholesky(np.linalg.inv(cov)), -1, -2)


class _Problem:
    """The stacked least-squares problem of :func:`calibrate` over the stars ``use`` of each frame."""

    def __init__(self, start: Camera, names, frames, use, prior_sigma=None) -> None:
        self.start, self.names = start, tuple(names)
        self.scale = corner_scale(start, self.names)
        # a Gaussian prior on a parameter (centred on the starting camera's value) is one more row
        # (p - p0) / sigma_prior, after the stars' rows; inf: no prior
        self.prior_sigma = (np.full(len(self.names), np.inf) if prior_sigma is None
                            else np.asarray(prior_sigma, dtype=float))
        self.prior = np.flatnonzero(np.isfinite(self.prior_sigma))
        self.p0 = parameter_values(start, self.names)
        self.f0 = start.focal_length_px
        self.frames = frames
        self.use = use
        self.v_cam = [f.R_icrf_cam.inv().apply(f.v_icrf[u]) for f, u in zip(frames, use)]
        self.xy = [f.xy[u] for f, u in zip(frames, use)]
        self.white = [_whiteners(f.cov[u]) for f, u in zip(frames, use)]
        self.n_params = len(self.names)
        self.n = self.n_params + 3 * len(frames)
        self.rows = 2 * sum(len(x) for x in self.xy)  # the stars' rows (the prior's follow them)
        self.rows_all = self.rows + len(self.prior)

    def unpack(self, x: np.ndarray) -> tuple[Camera, np.ndarray]:
        params = self.p0 + x[: self.n_params] / self.scale
        camera = with_parameters(self.start, self.names, params) if self.n_params else self.start
        thetas = x[self.n_params:].reshape(-1, 3) / self.f0
        return camera, thetas

    def evaluate(self, x: np.ndarray, *, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        camera, thetas = self.unpack(x)
        residuals = np.empty(self.rows_all)
        jac = np.zeros((self.rows_all, self.n)) if jacobian else None
        row = 0
        for k, (v_cam, xy, white) in enumerate(zip(self.v_cam, self.xy, self.white)):
            predicted, d_params, d_theta = residual_jacobian(camera, self.names, v_cam, thetas[k])
            m = 2 * len(xy)
            residuals[row: row + m] = np.einsum("nij,nj->ni", white, predicted - xy).ravel()
            if jacobian:
                jac[row: row + m, : self.n_params] = (white @ (d_params / self.scale)).reshape(m, -1)
                cols = slice(self.n_params + 3 * k, self.n_params + 3 * k + 3)
                jac[row: row + m, cols] = (white @ (d_theta / self.f0)).reshape(m, 3)
            row += m
        weight = 1.0 / (self.scale[self.prior] * self.prior_sigma[self.prior])
        residuals[self.rows:] = x[self.prior] * weight
        if jacobian:
            jac[self.rows + np.arange(len(self.prior)), self.prior] = weight
        return residuals, jac

    def fun(self, x: np.ndarray) -> np.ndarray:
        return self.evaluate(x, jacobian=False)[0]

    def jac(self, x: np.ndarray) -> np.ndarray:
        return self.evaluate(x, jacobian=True)[1]


def _inverse_normal(jac: np.ndarray) -> np.ndarray:
    """``(J^T J)^-1``, infinite on the diagonal of parameters the rows do not constrain.

    Through the eigen-decomposition of the (unknowns x unknowns) normal matrix rather than an SVD of
    ``J`` (hundreds of rows): the unknowns are scaled to corner pixels (module step 2), so squaring
    the condition number costs nothing that matters, and it is 100 times faster for 20 frames.
    """
    normal = jac.T @ jac
    values, vectors = np.linalg.eigh(normal)
    tiny = values <= max(values.max(initial=0.0), 1e-300) * 1e-13
    inv = np.where(tiny, 0.0, 1.0 / np.where(tiny, 1.0, values))
    cov = (vectors * inv) @ vectors.T
    if np.any(tiny):  # a direction without information: every parameter in it has no bound
        null = np.any(np.abs(vectors[:, tiny]) > 1e-9, axis=1)
        cov[null, null] = np.inf
    return cov


def corner_sigmas(problem: _Problem, jac: np.ndarray) -> np.ndarray:
    """Corner-pixel 1-sigma of each camera parameter of ``problem`` (module step 4), attitudes free."""
    return np.sqrt(np.diag(_inverse_normal(jac))[: problem.n_params])


def unobservable(names, sigma_px: np.ndarray, max_sigma_px: float) -> list[str]:
    """The parameters whose corner-pixel 1-sigma exceeds ``max_sigma_px`` (inf: only those without any bound)."""
    return [n for n, s in zip(names, sigma_px) if not (s <= max_sigma_px or max_sigma_px == math.inf and s < math.inf)]


def refuse_unobservable(names, sigma_px: np.ndarray, max_sigma_px: float) -> None:
    """InputError naming the parameters above ``max_sigma_px`` (module step 4); nothing when there are none."""
    bad = [(n, s) for n, s in zip(names, sigma_px) if n in unobservable(names, sigma_px, max_sigma_px)]
    if bad:
        listed = ", ".join(f"{n} ({'no bound' if not math.isfinite(s) else f'{s:.3g} px'})" for n, s in bad)
        raise InputError(
            f"the stars given do not constrain {listed} to {max_sigma_px:g} px at the detector corner "
            f"(1 sigma, attitudes free): fit fewer parameters (--fit/--model, or --fit auto), add frames or stars, "
            f"or raise --max-sigma-px")


def _chi2_quantile(probability: float, dof: int) -> float:
    return float(2.0 * gammaincinv(0.5 * dof, probability))


#: A Levenberg-Marquardt iteration that lowers chi-square by less than this ends the fit.
CHI2_TOLERANCE = 1e-5


def _solve(problem: _Problem, x0: np.ndarray, robust: bool, max_iterations: int = 500) -> np.ndarray:
    """Levenberg-Marquardt on the normal equations (the unknowns are scaled to corner pixels, module
    step 2, so ``J^T J`` is well conditioned); ``robust`` reweights each star by the ``soft_l1`` loss
    ``rho(z) = 2 (sqrt(1 + z) - 1)``, ``z = chi2_star / 3^2`` (iteratively reweighted least squares)."""

    def weighted(x: np.ndarray, jacobian: bool):
        r, jac = problem.evaluate(x, jacobian=jacobian)
        if not robust:
            return r, jac, float(r @ r)
        stars = problem.rows  # the prior's rows (after the stars') keep their weight
        chi2_star = (r[0:stars:2] ** 2 + r[1:stars:2] ** 2) / 9.0
        cost = float(np.sum(2.0 * (np.sqrt(1.0 + chi2_star) - 1.0))) * 9.0 + float(r[stars:] @ r[stars:])
        w = np.r_[np.repeat((1.0 + chi2_star) ** -0.25, 2), np.ones(len(r) - stars)]
        return r * w, (jac * w[:, None] if jacobian else None), cost

    x = np.array(x0, dtype=float)
    r, jac, cost = weighted(x, True)
    damping = 1e-6
    for _ in range(max_iterations):
        normal = jac.T @ jac
        gradient = jac.T @ r
        diag = np.maximum(np.diag(normal), 1e-12)
        while True:
            try:
                step = -np.linalg.solve(normal + damping * np.diag(diag), gradient)
            except np.linalg.LinAlgError:
                step = np.full_like(x, np.nan)
            trial = x + step
            if np.all(np.isfinite(step)):
                r_new, _, cost_new = weighted(trial, False)
                if np.isfinite(cost_new) and cost_new <= cost:
                    break
            damping *= 10.0
            if damping > 1e12:
                raise ConvergenceError("camera calibration did not converge (no step lowers the residuals)")
        x = trial
        # Done when an undamped step lowers chi-square by less than CHI2_TOLERANCE: along a direction the
        # stars hardly constrain (the principal point of a narrow field) Gauss-Newton converges only
        # linearly, and the estimate is then within about a hundredth of its sigma of the minimum.
        # (A heavily damped step is small because of the damping, not because the fit is done.)
        converged = np.max(np.abs(step)) < 1e-9 or (damping <= 1e-2 and cost - cost_new <= CHI2_TOLERANCE)
        damping = max(damping / 10.0, 1e-12)
        r, jac, cost = weighted(x, True)
        if converged:
            return x
    raise ConvergenceError(f"camera calibration did not converge in {max_iterations} iterations")


def _per_star_chi2(problem: _Problem, frames, x: np.ndarray) -> list[np.ndarray]:
    """Whitened squared residual of every star of every frame (kept or not) at ``x``."""
    camera, thetas = problem.unpack(x)
    out = []
    for frame, theta in zip(frames, thetas):
        v_cam = frame.R_icrf_cam.inv().apply(frame.v_icrf)
        predicted, _, _ = residual_jacobian(camera, (), v_cam, theta)
        w = np.einsum("nij,nj->ni", _whiteners(frame.cov), predicted - frame.xy)
        out.append(np.sum(w**2, axis=1))
    return out


#: ``sigma_floor_px`` value that estimates the centroid floor from the stars (module step 7).
FLOOR_AUTO = "auto"
#: Median of chi-square with 2 degrees of freedom.
_CHI2_2_MEDIAN = 2.0 * math.log(2.0)


def estimate_floor_px(problem: _Problem, frames, x: np.ndarray) -> float:
    """Per-axis centroid error beyond the stars' covariances, px, from a fit's residuals (module step 7).

    The ``s >= 0`` at which the median over the stars of ``r^T (C + s^2 I)^-1 r`` (``r`` a star's
    residual at ``x``, ``C`` its covariance) is ``2 ln 2`` (chi-square(2)'s median) times
    ``dof / residuals`` (the fit absorbs the unknowns' share); 0 when it is below that already.
    """
    camera, thetas = problem.unpack(x)
    r = np.concatenate([residual_jacobian(camera, (), f.R_icrf_cam.inv().apply(f.v_icrf), theta)[0] - f.xy
                        for f, theta in zip(frames, thetas)])
    cov = np.concatenate([f.cov for f in frames])
    target = _CHI2_2_MEDIAN * max(problem.rows_all - problem.n, 1) / problem.rows_all

    def median_z2(s2: float) -> float:
        a, b, d = cov[:, 0, 0] + s2, cov[:, 0, 1], cov[:, 1, 1] + s2
        det = a * d - b * b
        return float(np.median((d * r[:, 0] ** 2 - 2.0 * b * r[:, 0] * r[:, 1] + a * r[:, 1] ** 2) / det))

    if median_z2(0.0) <= target:
        return 0.0
    lo, hi = 0.0, float(np.median(np.sum(r**2, axis=1)))  # a floor of the residuals' own size explains them
    while median_z2(hi) > target:
        hi *= 4.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if median_z2(mid) > target else (lo, mid)
    return math.sqrt(0.5 * (lo + hi))


def _check_frames(frames, camera: Camera, n_params: int) -> None:
    if not frames:
        raise InputError("calibration needs at least one frame of identified stars")
    for frame in frames:
        if len(frame.xy) < MIN_STARS_PER_FRAME:
            raise InputError(f"{frame.name}: {len(frame.xy)} identified stars; calibration needs at least "
                             f"{MIN_STARS_PER_FRAME} a frame (3 for its attitude)")
        outside = ~camera.in_frame(frame.xy, margin_px=-2.0)
        if np.any(outside):
            raise InputError(f"{frame.name}: {int(outside.sum())} stars lie outside the {camera.width_px} x "
                             f"{camera.height_px} px detector of the camera given: frames of another camera?")
    stars = sum(len(f.xy) for f in frames)
    unknowns = n_params + 3 * len(frames)
    if 2 * stars <= unknowns:
        raise InputError(f"{stars} identified stars in {len(frames)} frames give {2 * stars} residuals for "
                         f"{unknowns} unknowns ({n_params} camera parameters, 3 a frame); need more stars")


def calibrate(
    frames,
    camera: Camera,
    *,
    model: str = "brown",
    fit=None,
    gate_probability: float = 1.0 - 1e-4,
    max_sigma_px: float = MAX_SIGMA_PX,
    sigma_floor_px: float | str = 0.0,
    principal_point_sigma_px: float = PRINCIPAL_POINT_SIGMA_PX,
) -> Calibration:
    """Fit a camera and each frame's attitude to identified stars (module docstring).

    Parameters
    ----------
    frames : sequence of FrameStars
        Identified stars of one camera's frames.
    camera : Camera
        Starting camera (a nominal or pre-flight model); its detector fields are kept.
    model : str
        :data:`MODELS` key: the distortion coefficients the camera has.
    fit : sequence of str or "auto", optional
        Parameters to fit (:data:`PARAMETERS`, all in ``model``), each from the stars alone; a parameter
        they do not constrain is refused. Default (None or ``"auto"``): all of the model's, the
        principal point with a Gaussian prior on the starting camera's (``principal_point_sigma_px``),
        and any other parameter the stars do not constrain held at the starting camera's value
        (:attr:`Calibration.held`), so an answer comes whatever the field of view.
    gate_probability : float
        A star whose whitened residual exceeds this chi-square(2) quantile is rejected.
    max_sigma_px : float
        Largest 1-sigma displacement at the detector corner a fitted parameter may have (module step 4), px.
    sigma_floor_px : float or "auto"
        Per-axis centroid error added in quadrature to every star's covariance, px: what a
        centroider's covariance leaves out (PSF model error, pixel phase), so bright stars do not
        weigh more than their real accuracy; ``"auto"``: estimated from the stars (module step 7).
    principal_point_sigma_px : float
        ``fit="auto"``: per-axis 1-sigma of the starting camera's principal point, px (a pre-flight
        camera is known to a few px). In a narrow field the principal point is mostly a turn of the
        attitude, so the stars hardly constrain it and its estimate and sigma stay near this prior;
        the covariance carries it into the other parameters.

    Returns
    -------
    Calibration

    Raises
    ------
    InputError
        Unknown model or parameter; a frame with fewer than :data:`MIN_STARS_PER_FRAME` stars or stars
        off the detector; fewer residuals than unknowns; a parameter the stars do not constrain
        named in ``fit``.
    ConvergenceError
        The least-squares iterations failed.
    """
    started = time.perf_counter()
    auto = fit is None or (isinstance(fit, str) and fit.strip().lower() == AUTO)
    names = choose_parameters(model, None if auto else ((fit,) if isinstance(fit, str) else fit))
    if not 0.0 < gate_probability < 1.0:
        raise InputError(f"gate_probability must be in (0, 1), got {gate_probability}")
    if not max_sigma_px > 0.0:
        raise InputError(f"--max-sigma-px must be positive, got {max_sigma_px}")
    auto_floor = isinstance(sigma_floor_px, str)
    if auto_floor and sigma_floor_px.strip().lower() != FLOOR_AUTO:
        raise InputError(f"--sigma-floor-px must be a number >= 0 or {FLOOR_AUTO}, got {sigma_floor_px!r}")
    if not auto_floor and not (math.isfinite(sigma_floor_px) and sigma_floor_px >= 0.0):
        raise InputError(f"--sigma-floor-px must be a number >= 0 or {FLOOR_AUTO}, got {sigma_floor_px}")
    if not (math.isfinite(principal_point_sigma_px) and principal_point_sigma_px > 0.0):
        raise InputError(f"--principal-point-sigma-px must be a positive number of px, got {principal_point_sigma_px}")
    frames = tuple(frames)
    if auto_floor:
        _check_frames(frames, camera, len(names))
        start0 = camera.replace(**{k: 0.0 for k in ("k1", "k2", "k3", "p1", "p2") if k not in MODELS[model]})
        prior0 = (np.array([principal_point_sigma_px if n in ("cx", "cy") else np.inf for n in names])
                  if auto else None)
        probe = _Problem(start0, names, frames, [np.ones(len(f.xy), bool) for f in frames], prior0)
        sigma_floor_px = estimate_floor_px(probe, frames, _solve(probe, np.zeros(probe.n), robust=True))
    if sigma_floor_px > 0.0:
        floor = np.eye(2) * sigma_floor_px**2
        frames = tuple(FrameStars(f.xy, f.cov + floor, f.v_icrf, f.R_icrf_cam, f.name) for f in frames)
    start = camera.replace(**{k: 0.0 for k in ("k1", "k2", "k3", "p1", "p2") if k not in MODELS[model]})
    _check_frames(frames, start, len(names))
    held: tuple[str, ...] = ()
    dropped: list[str] = []
    while True:
        prior = (np.array([principal_point_sigma_px if n in ("cx", "cy") else np.inf for n in names])
                 if auto else None)
        problem = _Problem(start, names, frames, [np.ones(len(f.xy), bool) for f in frames], prior)
        # before the fit only a parameter without any bound is refused: how well the principal point is
        # known depends on the distortion (its centre), which the starting camera may lack
        threshold = math.inf
        sigma_px = corner_sigmas(problem, problem.jac(np.zeros(problem.n)))
        bad = unobservable(names, sigma_px, threshold)
        if not bad:
            try:
                x, problem = _robust_fit(problem, frames, gate_probability, model)
            except _FrameBeyondGate as exc:
                # one frame's wrong identification does not sink the others: it is left out, named
                if len(frames) == 1:
                    raise InputError(exc.reason) from None
                dropped.append(exc.reason)
                frames = frames[: exc.index] + frames[exc.index + 1:]
                _check_frames(frames, start, len(names))
                continue
            residuals, jac = problem.evaluate(x, jacobian=True)
            threshold = max_sigma_px
            sigma_px = corner_sigmas(problem, jac)
            bad = unobservable(names, sigma_px, threshold)
            if not bad:
                break
        if not auto or len(bad) == len(names):
            refuse_unobservable(names, sigma_px, threshold)
        # --fit auto: the parameters the stars do not constrain keep the starting camera's values
        held += tuple(bad)
        names = tuple(n for n in names if n not in bad)
    cov_scaled = _inverse_normal(jac)
    fitted, thetas = problem.unpack(x)
    scale = np.r_[problem.scale, np.full(3 * len(frames), problem.f0)]
    cov = cov_scaled / np.outer(scale, scale)
    before = _attitude_only(start, frames, problem.use)
    fits = []
    for k, frame in enumerate(frames):
        v_cam = frame.R_icrf_cam.inv().apply(frame.v_icrf)
        after = residual_jacobian(fitted, (), v_cam, thetas[k])[0] - frame.xy
        block = slice(len(names) + 3 * k, len(names) + 3 * k + 3)
        fits.append(FrameFit(frame.name, frame.xy, before[k], after, problem.use[k],
                             frame.R_icrf_cam * Rotation.from_rotvec(thetas[k]), cov[block, block]))
    dof = problem.rows_all - problem.n
    return Calibration(camera=fitted, start=start, model=model, names=names,
                       values=parameter_values(fitted, names), covariance=cov[: len(names), : len(names)],
                       frames=tuple(fits), chi2=float(residuals @ residuals), dof=dof,
                       elapsed_s=time.perf_counter() - started, prior_sigma=problem.prior_sigma.copy(), held=held,
                       dropped=tuple(dropped), sigma_floor_px=float(sigma_floor_px))


class _FrameBeyondGate(Exception):
    """A frame keeps fewer than 3 stars within the gate (:func:`_robust_fit`): ``index`` and why."""

    def __init__(self, index: int, reason: str) -> None:
        super().__init__(reason)
        self.index, self.reason = index, reason


def _robust_fit(problem: _Problem, frames, gate_probability: float, model: str) -> tuple[np.ndarray, _Problem]:
    """Module step 5: the robust fit, then the chi-square(2) gate and plain refits until no star changes side."""
    x = _solve(problem, np.zeros(problem.n), robust=True)
    gate = _chi2_quantile(gate_probability, 2)
    for _ in range(10):
        new_use = [c <= gate for c in _per_star_chi2(problem, frames, x)]
        for k, (frame, u) in enumerate(zip(frames, new_use)):
            if u.sum() < 3:
                raise _FrameBeyondGate(k, f"{frame.name}: only {int(u.sum())} stars fit the camera within the gate; "
                                          f"the frame's identification or the starting camera is wrong")
        rejected = sum(int((~u).sum()) for u in new_use)
        total = sum(len(u) for u in new_use)
        if rejected > MAX_REJECTED_FRACTION * total:
            raise InputError(f"the fitted camera leaves {rejected} of {total} stars beyond the "
                             f"{gate_probability:.6g} gate: the camera has more distortion than --model {model} "
                             f"--fit {','.join(problem.names)} describe, or the centroids are worse than their "
                             f"covariances (--sigma-floor-px)")
        changed = any(np.any(a != b) for a, b in zip(new_use, problem.use))
        if changed:
            problem = _Problem(problem.start, problem.names, frames, new_use, problem.prior_sigma)
        x = _solve(problem, x, robust=False)
        if not changed:
            break
    return x, problem


def _attitude_only(camera: Camera, frames, use) -> list[np.ndarray]:
    """Residuals (predicted - measured, px) of every star with ``camera`` held and each frame's attitude fitted alone."""
    out = []
    for frame, u in zip(frames, use):
        problem = _Problem(camera, (), (frame,), (u,))
        x = _solve(problem, np.zeros(3), robust=False)
        v_cam = frame.R_icrf_cam.inv().apply(frame.v_icrf)
        out.append(residual_jacobian(camera, (), v_cam, x / problem.f0)[0] - frame.xy)
    return out


def target_direction_covariance(camera: Camera, names, covariance: np.ndarray, star_xy: np.ndarray,
                                target_xy: np.ndarray) -> np.ndarray:
    """Covariance of a target's direction relative to the attitude its frame's stars give, from the camera's.

    A measurement of a target (a moon's RA/Dec) is its direction in the attitude the frame's stars give,
    and both come through the camera: an error of the camera's parameters moves the target relative to
    the stars. This is the part of the measurement noise a calibration's covariance adds (the part the
    records' centroid covariances leave out); it is common to every frame of a similar star field, so
    it is a bias rather than white noise over an arc.

    Parameters
    ----------
    camera : Camera
        The calibrated camera.
    names : sequence of str
        Its fitted parameters (:data:`PARAMETERS`), as :class:`opnav.camera.CameraCovariance` names them.
    covariance : ndarray, shape (P, P)
        Their covariance (``f``, ``cx``, ``cy`` in px; Brown coefficients dimensionless).
    star_xy : ndarray, shape (N, 2)
        The stars the attitude is fitted to (N >= 2), px.
    target_xy : ndarray, shape (2,)
        The target's pixel, px.

    Returns
    -------
    ndarray, shape (2, 2)
        Covariance of the target's direction error, rad^2, on the camera's x and y axes at the target
        (the tangent plane; ICRF once rotated by the attitude).

    Notes
    -----
    Linearised: ``J C J^T`` with ``J`` from :func:`target_direction_jacobian`.
    """
    names = tuple(names)
    covariance = np.asarray(covariance, dtype=float)
    if covariance.shape != (len(names), len(names)):
        raise InputError(f"covariance must be {len(names)} x {len(names)} for parameters {', '.join(names)}")
    jac = target_direction_jacobian(camera, names, star_xy, target_xy)[0]
    return jac @ covariance @ jac.T


def target_direction_jacobian(camera: Camera, names, star_xy: np.ndarray, target_xy: np.ndarray,
                              star_weights: np.ndarray | None = None):
    """Derivative of a target's direction, relative to the attitude its frame's stars give, by the camera's parameters.

    Parameters
    ----------
    camera, names, star_xy, target_xy
        As :func:`target_direction_covariance`.
    star_weights : ndarray, shape (N,), optional
        The stars' weights in the attitude fit (e.g. inverse centroid variances); default equal.

    Returns
    -------
    jac : ndarray, shape (2, P)
        d(direction)/d(parameter), rad per parameter unit, on ``x_axis`` and ``y_axis``.
    x_axis, y_axis : ndarray, shape (3,)
        The tangent plane at the target, camera frame (the camera's x axis made perpendicular to the
        target's direction, then ``direction x x_axis``), unit vectors.

    Notes
    -----
    Central differences of the target's direction in the frame the stars define (Wahba with
    ``star_weights``, :func:`opnav.image.attitude.wahba_rotation`) per parameter, steps moving the detector
    corner by 1e-3 px (the direction is linear in each parameter to far below that).
    """
    from .attitude import wahba_rotation

    names = tuple(names)
    star_xy = np.asarray(star_xy, dtype=float).reshape(-1, 2)
    if len(star_xy) < 2:
        raise InputError(f"an attitude needs at least 2 stars, got {len(star_xy)}")
    unknown = [n for n in names if n not in PARAMETERS]
    if unknown:
        raise InputError(f"unknown camera parameter {', '.join(unknown)}; accepted: {', '.join(PARAMETERS)}")
    target_xy = np.asarray(target_xy, dtype=float)
    weights = np.ones(len(star_xy)) if star_weights is None else np.asarray(star_weights, dtype=float).reshape(-1)
    if weights.shape != (len(star_xy),) or not np.all(np.isfinite(weights) & (weights > 0)):
        raise InputError(f"star_weights must be {len(star_xy)} positive numbers, one a star")
    stars_ref = camera.unproject(star_xy)  # the stars' directions in the frame of the camera as fitted
    target_ref = camera.unproject(target_xy)
    x_axis = np.array([1.0, 0.0, 0.0]) - target_ref[0] * target_ref
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(target_ref, x_axis)

    def moved(values: np.ndarray) -> np.ndarray:
        changed = with_parameters(camera, names, values)
        rotation = wahba_rotation(changed.unproject(star_xy), stars_ref, weights)
        direction = rotation.apply(changed.unproject(target_xy))
        return np.array([direction @ x_axis, direction @ y_axis])

    values = parameter_values(camera, names)
    steps = 1e-3 / corner_scale(camera, names)
    jac = np.empty((2, len(names)))
    for j, h in enumerate(steps):
        up, down = values.copy(), values.copy()
        up[j] += h
        down[j] -= h
        jac[:, j] = (moved(up) - moved(down)) / (2.0 * h)
    return jac, x_axis, y_axis
