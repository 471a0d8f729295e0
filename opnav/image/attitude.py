"""Attitude from matched star directions: Wahba's problem, its covariance, camera refinement.

Algorithm
---------
1. :func:`wahba` solves Wahba's problem ``min sum w_i |v_icrf_i - R b_i|^2`` with the SVD method
   (Markley 1988): ``B = sum w_i v_i b_i^T = U S V^T``, ``R = U diag(1, 1, det U det V) V^T``.
   The weights are ``w_i = 1 / sigma_i^2`` with ``sigma_i`` the per-axis angular noise of
   the measured camera-frame direction ``b_i``.
2. The covariance is Shuster's QUEST covariance, expressed for the small rotation vector
   ``dtheta`` in the *camera* frame defined by ``R_icrf_cam_true = R_icrf_cam * exp(dtheta)``
   (scipy ``Rotation.from_rotvec(dtheta)`` applied first)::

       P = [ sum_i w_i (I - b_i b_i^T) ]^-1

   (Shuster & Oh 1981, eq. 84; Markley & Crassidis 2014, eq. 5.142, camera = body frame).
3. :func:`refine_camera` fits the attitude together with the focal length and optionally
   the radial distortion ``k1`` to matched stars by least squares on the pixel residuals,
   starting from a solved attitude.
"""

from __future__ import annotations

import math

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..compiled import kernel
from ..consistency import chi2_quantile
from ..errors import ConvergenceError, CovarianceError, InputError


@dataclass(frozen=True)
class AttitudeSolution:
    """Result of :func:`wahba`.

    Attributes
    ----------
    R_icrf_cam : scipy.spatial.transform.Rotation
        Camera frame -> ICRF.
    cov_rad2 : ndarray, shape (3, 3)
        Covariance of the camera-frame small rotation vector (see module Notes), rad^2.
    residuals_rad : ndarray, shape (N,)
        Angle between each measured direction and its catalog direction rotated into the camera
        frame, rad.
    """

    R_icrf_cam: Rotation
    cov_rad2: np.ndarray
    residuals_rad: np.ndarray


def _as_directions(name: str, value: np.ndarray) -> np.ndarray:
    array = np.asarray(value, dtype=float)
    if array.ndim != 2 or array.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InputError(f"{name} contains NaN or infinite values")
    norm = np.linalg.norm(array, axis=1, keepdims=True)
    if np.any(norm == 0.0):
        raise InputError(f"{name} contains a zero vector")
    return array / norm


def _sigma_per_star(sigma_rad: float | np.ndarray, n: int) -> np.ndarray:
    sigma = np.broadcast_to(np.asarray(sigma_rad, dtype=float), (n,)).copy()
    if not np.all(np.isfinite(sigma) & (sigma > 0.0)):
        raise InputError("sigma_rad must be positive and finite for every star")
    return sigma


def wahba_matrix(b_cam: np.ndarray, v_icrf: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """SVD solution of Wahba's problem (Markley 1988) as a rotation matrix.

    Parameters
    ----------
    b_cam : ndarray, shape (N, 3)
        Unit directions measured in the camera frame.
    v_icrf : ndarray, shape (N, 3)
        The same stars' unit directions in ICRF.
    weights : ndarray, shape (N,)
        Non-negative weights.

    Returns
    -------
    ndarray, shape (3, 3)
        ``R_icrf_cam`` minimising ``sum w_i |v_i - R b_i|^2`` (``v = R @ b``).
    """
    attitude_profile = (v_icrf * weights[:, None]).T @ b_cam
    u, _, vt = np.linalg.svd(attitude_profile)
    d = np.linalg.det(u) * np.linalg.det(vt)
    return (u * np.array([1.0, 1.0, d])) @ vt


def wahba_rotation(b_cam: np.ndarray, v_icrf: np.ndarray, weights: np.ndarray) -> Rotation:
    """:func:`wahba_matrix` as a scipy ``Rotation`` (camera -> ICRF)."""
    return Rotation.from_matrix(wahba_matrix(b_cam, v_icrf, weights))


def shuster_covariance(b_cam: np.ndarray, sigma_rad: np.ndarray) -> np.ndarray:
    """QUEST covariance of the camera-frame rotation vector, rad^2 (module Notes, step 2).

    Parameters
    ----------
    b_cam : ndarray, shape (N, 3)
        Unit directions in the camera frame.
    sigma_rad : ndarray, shape (N,)
        Per-axis angular noise of each direction, rad.
    """
    weights = 1.0 / sigma_rad**2
    information = _information(np.ascontiguousarray(b_cam, dtype=float), np.ascontiguousarray(weights, dtype=float))
    if _condition_bound(information) > 1e11 and np.linalg.cond(information) > 1e12:
        raise CovarianceError("attitude covariance is singular: the matched stars are (nearly) collinear")
    covariance = np.linalg.inv(information)
    return 0.5 * (covariance + covariance.T)


@kernel
def _information(b_cam, weights):  # pragma: no cover - compiled
    """``sum_i w_i (I - b_i b_i^T)`` (3, 3), the sum in the order of ``numpy.einsum("n,nij->ij", w, I - b b^T)``
    (the same numbers, without its (N, 3, 3) temporaries: a solve's covariance cost ~25 us of them)."""
    out = np.zeros((3, 3))
    for n in range(b_cam.shape[0]):
        for i in range(3):
            for j in range(3):
                out[i, j] += weights[n] * ((1.0 if i == j else 0.0) - b_cam[n, i] * b_cam[n, j])
    return out


def _condition_bound(information: np.ndarray) -> float:
    """An upper bound on the 2-norm condition number of a symmetric positive semi-definite 3 x 3 matrix
    (inf when its determinant is not positive): with eigenvalues ``l1 >= l2 >= l3``, ``l1 <= tr`` and
    ``l1 l2 <= tr^2 / 4``, so ``l3 = det / (l1 l2) >= 4 det / tr^2`` and ``cond <= tr^3 / (4 det)``.

    A few float operations where ``numpy.linalg.cond`` (an SVD) cost ~50 us of a plate solve; the
    caller takes the SVD's figure when the bound is within a factor 10 (rounding of ``det``) of its
    threshold, so the test's outcome is the SVD's.
    """
    (a, b, c), (d, e, f), (g, h, i) = information.tolist()
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    trace = a + e + i
    return trace**3 / (4.0 * det) if det > 0.0 else math.inf


def wahba(b_cam: np.ndarray, v_icrf: np.ndarray, *, sigma_rad: float | np.ndarray) -> AttitudeSolution:
    """Attitude and covariance from >= 2 matched, non-parallel star directions.

    Parameters
    ----------
    b_cam : ndarray, shape (N, 3)
        Measured directions in the camera frame (normalised on entry).
    v_icrf : ndarray, shape (N, 3)
        Catalog directions of the same stars, ICRF (normalised on entry).
    sigma_rad : float or ndarray, shape (N,)
        Per-axis 1-sigma angular noise of each measured direction, rad.

    Returns
    -------
    AttitudeSolution

    Raises
    ------
    InputError
        Mismatched shapes, fewer than 2 stars, bad sigma.
    CovarianceError
        The directions are (nearly) parallel, so the attitude is not determined.

    Examples
    --------
    >>> import numpy as np
    >>> from scipy.spatial.transform import Rotation
    >>> b = np.eye(3)
    >>> truth = Rotation.from_rotvec([0.0, 0.0, np.pi / 2])
    >>> solution = wahba(b, truth.apply(b), sigma_rad=1e-5)
    >>> bool(np.allclose(solution.R_icrf_cam.as_matrix(), truth.as_matrix()))
    True
    """
    b = _as_directions("b_cam", b_cam)
    v = _as_directions("v_icrf", v_icrf)
    if b.shape != v.shape:
        raise InputError(f"b_cam {b.shape} and v_icrf {v.shape} must have the same shape")
    if len(b) < 2:
        raise InputError(f"need at least 2 matched stars for an attitude, got {len(b)}")
    sigma = _sigma_per_star(sigma_rad, len(b))
    covariance = shuster_covariance(b, sigma)
    rotation = wahba_rotation(b, v, 1.0 / sigma**2)
    predicted = rotation.inv().apply(v)
    residuals = np.arctan2(np.linalg.norm(np.cross(b, predicted), axis=1), np.sum(b * predicted, axis=1))
    return AttitudeSolution(R_icrf_cam=rotation, cov_rad2=covariance, residuals_rad=residuals)


@dataclass(frozen=True)
class CameraFit:
    """Result of :func:`refine_camera`.

    Attributes
    ----------
    camera : Camera
        The input camera with the fitted focal length (and ``k1`` if fitted).
    R_icrf_cam : Rotation
        Refined attitude, camera -> ICRF.
    rms_px : float
        Root-mean-square pixel residual after the fit.
    """

    camera: Camera
    R_icrf_cam: Rotation
    rms_px: float


def wahba_gated(
    b_cam: np.ndarray,
    v_icrf: np.ndarray,
    *,
    sigma_rad: float | np.ndarray,
    gate_probability: float = 1.0 - 1e-4,
    min_stars: int = 3,
) -> tuple[AttitudeSolution, np.ndarray]:
    """:func:`wahba` with stars whose residual its noise cannot explain removed, one at a time.

    A matched star can still be wrong for the fit: an unresolved double whose photocentre is
    not the catalog component, a star on a bright neighbour's wing or blended with a hot-pixel
    cluster. Its residual then sits many sigmas out, and with its small sigma it would drag the
    attitude. While the largest normalised residual ``(residual / sigma)^2`` of a fit exceeds
    the ``gate_probability`` quantile of chi-square with 2 degrees of freedom (the residual
    angle has two components), the star the other stars explain worst is dropped and the fit
    repeated: each star's deleted residual (its direction against the fit without it) decides,
    because a bright wrong star pulls the fit onto itself and leaves its largest residuals on
    the good, fainter stars.

    Returns
    -------
    solution : AttitudeSolution
        The fit on the kept stars (``residuals_rad`` for those stars).
    kept : ndarray of bool, shape (N,)
        Which input stars the solution uses.
    """
    if not 0.0 < gate_probability < 1.0:
        raise InputError(f"gate_probability must be in (0, 1), got {gate_probability}")
    b = np.asarray(b_cam, dtype=float)
    v = np.asarray(v_icrf, dtype=float)
    sigma = _sigma_per_star(sigma_rad, len(b))
    gate = chi2_quantile(gate_probability, 2)
    kept = np.ones(len(b), bool)
    while True:
        solution = wahba(b[kept], v[kept], sigma_rad=sigma[kept])
        z2 = (solution.residuals_rad / sigma[kept]) ** 2
        if z2.max() <= gate or kept.sum() <= min_stars:
            return solution, kept
        rows = np.flatnonzero(kept)
        deleted = np.empty(len(rows))
        for j, row in enumerate(rows):
            others = kept.copy()
            others[row] = False
            without = wahba(b[others], v[others], sigma_rad=sigma[others]).R_icrf_cam
            predicted = without.inv().apply(v[row])
            angle = math.atan2(np.linalg.norm(np.cross(b[row], predicted)), float(b[row] @ predicted))
            deleted[j] = (angle / sigma[row]) ** 2
        kept[rows[int(np.argmax(deleted))]] = False


def refine_camera(
    xy: np.ndarray,
    v_icrf: np.ndarray,
    camera: Camera,
    R_icrf_cam: Rotation,
    *,
    fit_k1: bool = False,
) -> CameraFit:
    """Least-squares refinement of attitude, focal length (and ``k1``) from matched stars.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        Measured star centroids, px (docs/conventions.md).
    v_icrf : ndarray, shape (N, 3)
        Catalog directions of the same stars, ICRF.
    camera : Camera
        Starting camera model; principal point and other distortion terms are held fixed.
    R_icrf_cam : Rotation
        Starting attitude, camera -> ICRF.
    fit_k1 : bool
        Also fit the radial distortion coefficient ``k1``.

    Returns
    -------
    CameraFit

    Notes
    -----
    Unknowns: camera-frame rotation-vector correction (3), relative focal-length change
    ``log(f / f0)`` and optionally ``k1``; residuals are ``project(R^T v) - xy`` in px,
    minimised with ``scipy.optimize.least_squares`` (trust-region reflective).
    """
    xy = np.asarray(xy, dtype=float)
    v = _as_directions("v_icrf", v_icrf)
    if xy.shape != (len(v), 2):
        raise InputError(f"xy must have shape ({len(v)}, 2), got {xy.shape}")
    n_unknowns = 5 if fit_k1 else 4
    if 2 * len(v) <= n_unknowns:
        raise InputError(f"need more than {n_unknowns // 2} matched stars to refine the camera, got {len(v)}")
    f0 = camera.focal_length_mm

    def model(params: np.ndarray) -> tuple[Camera, Rotation]:
        changes = {"focal_length_mm": f0 * np.exp(params[3])}
        if fit_k1:
            changes["k1"] = params[4]
        return camera.replace(**changes), R_icrf_cam * Rotation.from_rotvec(params[:3])

    def residuals(params: np.ndarray) -> np.ndarray:
        cam, rotation = model(params)
        return (cam.project(rotation.inv().apply(v)) - xy).ravel()

    # imported here: scipy.optimize costs ~40 ms at start-up, and a plate solve (opnav solve) never refines the camera
    from scipy.optimize import least_squares

    start = np.zeros(n_unknowns)
    if fit_k1:
        start[4] = camera.k1
    result = least_squares(residuals, start, x_scale=np.r_[np.full(3, camera.pixel_scale_rad), 1e-3, 1e-2][:n_unknowns])
    if not result.success or not np.all(np.isfinite(result.fun)):
        raise ConvergenceError(f"camera refinement did not converge: {result.message}")
    fitted_camera, rotation = model(result.x)
    return CameraFit(camera=fitted_camera, R_icrf_cam=rotation, rms_px=float(np.sqrt(np.mean(result.fun**2) * 2.0)))
