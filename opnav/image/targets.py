"""Targets: moon photocentre -> centre of figure -> RA/Dec; planet limbs -> centre and radius.

Conventions: docs/conventions.md. Camera frame +z boresight; attitude
``R_icrf_cam`` (camera -> ICRF); attitude covariance is that of the small
rotation vector in the camera frame (as :mod:`opnav.image.attitude` returns it).

Phase correction (unresolved or marginally resolved moons)
-----------------------------------------------------------
A lit body's brightness-weighted centre (photocentre), which the centroider
measures, is displaced from its centre of figure towards the Sun. In a view
frame with z' along the line of sight (camera -> target) and the target far
away (orthographic view), a ray through (x', y') meets the ellipsoid
q^T A q = 1 (A = R diag(a^-2, b^-2, c^-2) R^T) at its nearest point q; with
the outward normal n = A q / |A q|, the emission and incidence cosines are
mu = -n.z' and mu0 = n.s (s: unit vector target -> Sun). The radiance is

    Lambert:          I = mu0
    Lommel–Seeliger:  I = mu0 / (mu0 + mu)

on the lit and visible part (mu0 > 0, mu > 0), and the offset is the first
moment  d = integral(I (x', y') dA) / integral(I dA)  over the projected disk,
evaluated on an ``n_grid`` x ``n_grid`` grid over the outline
(:func:`photocentre_offset`). For a Lambert sphere of radius R at phase
angle alpha this gives the classical closed form (checked in the tests)

    |d| = R (3 pi / 16) sin(alpha) (1 + cos(alpha)) / ((pi - alpha) cos(alpha) + sin(alpha)),

directed along the Sun's direction projected on the image. The centre of
figure is the photocentre direction minus d / range. The model error of the
correction (shape, albedo variegation, shading law) is carried in the
covariance as ``phase_sigma_fraction`` of |d| per axis.

Limbs (resolved Mars, the Earth from GEO)
-----------------------------------------
1. :func:`limb_points`: from a first centre and radius, ``n_rays`` radial scan
   lines (optionally only within ``arc_half_width_rad`` of the Sun's azimuth in
   the image, so the terminator is never taken for a limb) are sampled with
   bilinear interpolation every 0.25 px; the edge is where the profile
   (smoothed by a Gaussian of ``smooth_px``) falls fastest, refined by a
   parabola through the three samples around the extreme gradient. Weak edges
   (gradient below ``min_contrast`` of the strongest) are dropped.
2. :func:`fit_limb`: the edge pixels become unit directions (the camera model,
   distortion included). The limb of a sphere is a cone: u_i . c = cos(rho)
   for its centre direction c and apparent radius rho, i.e. the linear system
   u_i . w = 1 with w = c / cos(rho). RANSAC over 3-point solutions of that
   system rejects outliers (stars, craters, terminator points); Gauss–Newton on
   the angular residuals angle(u_i, c) - rho of the inliers refines (c, rho),
   and its covariance is s^2 (J^T J)^-1 with s^2 the residual variance. The
   cone model is exact for a sphere under any projection, so no ellipse
   approximation of the projected outline is needed.
3. :func:`starlight_measurements`: with the centre direction in ICRF and a
   star direction S, the starlight angle is alpha = angle(c, S) and the
   starlight elevation beta = alpha - arcsin(R / |r|) (scenario S3). The fitted
   rho belongs to the visible limb at altitude h (a UV limb sits in the
   atmosphere), so the distance is |r| = (R + h) / sin(rho) and the geometric
   radius arcsin(R / |r|) = arcsin(sin(rho) R / (R + h)). For a radiance that
   is flat up to h0 and falls as exp(-(h - h0)/H) above, seen with a blur much
   wider than H (a GEO UV sensor's pixel spans ~40 km at the limb), the
   steepest edge is that of the equivalent step, at h = h0 + H (the area
   under the tail moved into a step); the renderer's UV Earth (h0 = 40 km,
   H = 8 km) thus has h = 48 km; fits to its frames from GEO found 47.3-48.4 km
   (the equivalent step is exact only for an infinitely wide blur), so 1 km is
   a fair 1-sigma. The uncertainty enters the variance of beta through
   ``limb_altitude_sigma_km``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from ..bodies import cross3
from ..compiled import kernel
from ..camera import Camera
from ..errors import InputError, NoSolutionError
from ..frames import unit_to_radec
from ..light import aberrate

SHADING_LAWS = ("lommel-seeliger", "lambert")
#: Samples per axis of the photocentre model over a moon's projected outline (:func:`photocentre_offset`).
PHOTOCENTRE_GRID = 200
#: A pixel flagged as a possible cosmic-ray hit is put back into :func:`fit_point_source` when the
#: fitted model explains it within this many noise sigmas (Gaussian noise passes it but for a 3e-7
#: share, so putting back cuts no tail; a hit deposits hundreds of sigmas).
SUSPECT_SIGMAS = 5.0


def _view_basis(los_cam: np.ndarray) -> np.ndarray:
    """Rows x', y', z' of a view frame with z' along ``los_cam`` and x' closest to camera +x."""
    z = np.asarray(los_cam, float) / np.linalg.norm(los_cam)
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ z) * z
    x /= np.linalg.norm(x)
    return np.stack([x, cross3(z, x), z])


def photocentre_offset(
    radii_km: tuple[float, float, float],
    R_view_body: Rotation,
    sun_view: np.ndarray,
    *,
    law: str = "lommel-seeliger",
    n_grid: int = PHOTOCENTRE_GRID,
) -> np.ndarray:
    """Photocentre minus centre of figure of a lit ellipsoid, in the view plane.

    Parameters
    ----------
    radii_km : (a, b, c)
        Semi-axes along the body axes, km.
    R_view_body : Rotation
        Body axes -> view frame (z' along the line of sight, camera towards target).
    sun_view : (3,) array
        Unit vector target -> Sun in the view frame.
    law : {"lommel-seeliger", "lambert"}
        Shading law (module docstring).
    n_grid : int
        Samples per axis over the projected outline.

    Returns
    -------
    (2,) array
        Offset (x', y') in km, in the view frame. Zero vector if no lit part is visible.
    """
    return _photocentre_offset(radii_km, R_view_body.as_matrix(), sun_view, law, n_grid)


def _photocentre_offset(radii_km, rot: np.ndarray, sun_view: np.ndarray, law: str, n_grid: int) -> np.ndarray:
    """:func:`photocentre_offset` with the body -> view rotation as a matrix (3, 3)."""
    if law not in SHADING_LAWS:
        raise InputError(f"unknown shading law {law!r}; expected one of {', '.join(SHADING_LAWS)}")
    radii = np.asarray(radii_km, float)
    if radii.shape != (3,) or np.any(radii <= 0):
        raise InputError(f"radii_km must be three positive semi-axes, got {radii_km!r}")
    sun = np.asarray(sun_view, float) / np.linalg.norm(sun_view)
    quad = rot @ np.diag(radii**-2.0) @ rot.T
    inv = rot @ np.diag(radii**2.0) @ rot.T
    half = np.sqrt(np.diag(inv))[:2]
    offset = _photocentre_moment(quad, half, sun, int(n_grid), law == "lambert")
    return offset if np.all(np.isfinite(offset)) else np.zeros(2)


@kernel
def _photocentre_moment(quad, half, sun, n_grid, lambert):  # pragma: no cover - compiled
    """First moment of the radiance over the ``n_grid`` x ``n_grid`` grid (:func:`photocentre_offset`);
    NaNs when no lit part is visible.

    With the outward normal n = A q unnormalised, mu = -n_z / |n| and mu0 = n.s / |n|: whether a
    cell is lit and visible follows from the signs of -n_z and n.s, and the Lommel–Seeliger
    radiance mu0 / (mu0 + mu) is n.s / (n.s - n_z), |n| cancelling (the same numbers to rounding).
    Each row's radiances are computed first without branches (the compiler runs that loop on
    vector registers, ~4x faster than a branch per cell), then summed in grid order."""
    step_x = 2.0 * half[0] / n_grid
    step_y = 2.0 * half[1] / n_grid
    a = quad[2, 2]
    xs = np.empty(n_grid)
    for i in range(n_grid):
        xs[i] = -half[0] + step_x * (i + 0.5)
    radiance = np.empty(n_grid)
    total = 0.0
    moment_x = 0.0
    moment_y = 0.0
    for j in range(n_grid):
        y = -half[1] + step_y * (j + 0.5)
        for i in range(n_grid):
            x = xs[i]
            # the ray (x, y, z) along +z' meets q^T A q = 1 at its nearest root
            b = x * quad[0, 2] + y * quad[1, 2]
            c = x * x * quad[0, 0] + 2.0 * x * y * quad[0, 1] + y * y * quad[1, 1] - 1.0
            disc = b * b - a * c
            z = (-b - np.sqrt(max(disc, 0.0))) / a
            nx = x * quad[0, 0] + y * quad[1, 0] + z * quad[2, 0]
            ny = x * quad[0, 1] + y * quad[1, 1] + z * quad[2, 1]
            nz = x * quad[0, 2] + y * quad[1, 2] + z * quad[2, 2]
            lit = nx * sun[0] + ny * sun[1] + nz * sun[2]  # mu0 |n|
            if lambert:
                value = lit / np.sqrt(nx * nx + ny * ny + nz * nz)
            else:
                value = lit / (lit - nz)
            # the ray hits, the surface faces the Sun and the camera (mu |n| = -n_z)
            radiance[i] = value if (disc > 0.0) & (lit > 0.0) & (nz < 0.0) else 0.0
        for i in range(n_grid):
            if radiance[i] > 0.0:
                total += radiance[i]
                moment_x += radiance[i] * xs[i]
                moment_y += radiance[i] * y
    out = np.empty(2)
    out[0] = moment_x / total if total > 0.0 else np.nan
    out[1] = moment_y / total if total > 0.0 else np.nan
    return out


@dataclass(frozen=True)
class MoonDirection:
    """Apparent direction of a moon's centre of figure.

    Attributes
    ----------
    ra_rad, dec_rad : float
        Apparent right ascension and declination, ICRF, rad.
    cov_rad2 : (2, 2) array
        Covariance of (ra, dec), rad^2 (centroid + attitude + phase-model terms).
    unit_icrf : (3,) array
        The same direction as a unit vector, ICRF.
    xy_cof_px : (2,) array
        Centre of figure on the detector, px.
    offset_km : (3,) array
        Photocentre minus centre of figure, camera frame, km (zero if not corrected).
    attitude_jacobian : (2, 3) array
        d(ra, dec) / d(camera-frame small rotation), rad/rad: the attitude term of ``cov_rad2`` is
        ``J C J^T``, and two targets measured with one attitude share ``J_1 C J_2^T``.
    """

    ra_rad: float
    dec_rad: float
    cov_rad2: np.ndarray
    unit_icrf: np.ndarray
    xy_cof_px: np.ndarray
    offset_km: np.ndarray
    attitude_jacobian: np.ndarray


def _radec_jacobian(u: np.ndarray) -> np.ndarray:
    """d(ra, dec)/d(u) for a unit vector u (2, 3)."""
    x, y, z = u
    rho2 = x * x + y * y
    rho = math.sqrt(rho2)
    return np.array([[-y / rho2, x / rho2, 0.0], [-x * z / rho, -y * z / rho, rho]])


def _cross_matrix(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _unproject_with_jacobian(camera: Camera, xy: np.ndarray, step_px: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction (3,) of pixel ``xy`` in the camera frame and its derivative by (x, y), (3, 2), by
    central differences: the five pixels unprojected in one call."""
    d = np.eye(2) * step_px
    u = camera.unproject(np.stack([xy, xy + d[0], xy - d[0], xy + d[1], xy - d[1]]))
    return u[0], np.stack([(u[1] - u[2]) / (2 * step_px), (u[3] - u[4]) / (2 * step_px)], axis=-1)


def moon_direction(
    xy_px: np.ndarray,
    cov_xy_px2: np.ndarray,
    camera: Camera,
    R_icrf_cam: Rotation,
    cov_attitude_rad2: np.ndarray,
    *,
    radii_km: tuple[float, float, float] | None = None,
    R_icrf_body: Rotation | None = None,
    sun_icrf: np.ndarray | None = None,
    range_km: float | None = None,
    law: str = "lommel-seeliger",
    phase_sigma_fraction: float = 0.1,
) -> MoonDirection:
    """Centre-of-figure direction (RA/Dec with covariance) from a measured photocentre.

    Parameters
    ----------
    xy_px : (2,) array
        Measured photocentre (e.g. :func:`opnav.image.centroid.centroid`), px.
    cov_xy_px2 : (2, 2) array
        Its covariance, px^2.
    camera : Camera
    R_icrf_cam : Rotation
        Attitude, camera -> ICRF.
    cov_attitude_rad2 : (3, 3) array
        Covariance of the camera-frame small rotation vector, rad^2.
    radii_km, R_icrf_body, sun_icrf, range_km : optional
        Body semi-axes (km), body axes -> ICRF, unit vector target -> Sun (ICRF) and
        observer-target range (km), from a-priori ephemerides. Give all four to apply the
        phase correction; give none to skip it.
    law : {"lommel-seeliger", "lambert"}
    phase_sigma_fraction : float
        1-sigma model error of the correction per axis, as a fraction of its size.

    Returns
    -------
    MoonDirection
    """
    xy = np.asarray(xy_px, float)
    cov_xy = np.asarray(cov_xy_px2, float)
    cov_att = np.asarray(cov_attitude_rad2, float)
    if xy.shape != (2,) or cov_xy.shape != (2, 2) or cov_att.shape != (3, 3):
        raise InputError("moon_direction needs xy (2,), cov_xy (2, 2) and cov_attitude (3, 3)")
    if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(cov_xy)) and np.all(np.isfinite(cov_att))):
        raise InputError("moon_direction: non-finite centroid or covariance")
    phase_args = (radii_km, R_icrf_body, sun_icrf, range_km)
    if any(a is not None for a in phase_args) and not all(a is not None for a in phase_args):
        raise InputError("phase correction needs radii_km, R_icrf_body, sun_icrf and range_km together")
    u_pc, d_u_d_xy = _unproject_with_jacobian(camera, xy)
    # rotations as matrices: composing and applying scipy rotations costs tens of us each
    rot = R_icrf_cam.as_matrix()
    offset_cam = np.zeros(3)
    cov_offset_cam = np.zeros((3, 3))
    if radii_km is not None:
        if not (range_km > 0):
            raise InputError(f"range_km must be positive, got {range_km!r}")
        basis = _view_basis(u_pc)  # rows: view axes in the camera frame
        view_body = basis @ rot.T @ R_icrf_body.as_matrix()
        sun_view = basis @ (rot.T @ np.asarray(sun_icrf, float))
        d_view = _photocentre_offset(radii_km, view_body, sun_view, law, PHOTOCENTRE_GRID)
        offset_cam = basis[:2].T @ d_view
        sigma_km = phase_sigma_fraction * float(np.linalg.norm(d_view))
        cov_offset_cam = sigma_km**2 * basis[:2].T @ basis[:2]
    u_cof = u_pc - offset_cam / range_km if radii_km is not None else u_pc
    u_cof = u_cof / np.linalg.norm(u_cof)
    u_icrf = rot @ u_cof
    ra, dec = unit_to_radec(u_icrf)
    j_radec = _radec_jacobian(u_icrf)
    j_xy = j_radec @ rot @ d_u_d_xy
    j_att = j_radec @ rot @ (-_cross_matrix(u_cof))
    cov = j_xy @ cov_xy @ j_xy.T + j_att @ cov_att @ j_att.T
    if radii_km is not None:
        j_off = j_radec @ rot / range_km
        cov = cov + j_off @ cov_offset_cam @ j_off.T
    return MoonDirection(
        ra_rad=float(ra), dec_rad=float(dec), cov_rad2=0.5 * (cov + cov.T), unit_icrf=u_icrf,
        xy_cof_px=camera.project(u_cof), offset_km=offset_cam, attitude_jacobian=j_att,
    )


# ---- limbs -----------------------------------------------------------------------------------

def limb_points(
    image: np.ndarray,
    centre_xy: np.ndarray,
    radius_px: float,
    *,
    n_rays: int = 360,
    sun_azimuth_rad: float | None = None,
    arc_half_width_rad: float = math.radians(80.0),
    smooth_px: float = 1.0,
    min_contrast: float = 0.3,
    radial_half_width_px: float | None = None,
) -> np.ndarray:
    """Sub-pixel limb points along radial scan lines (module docstring, Limbs step 1).

    Parameters
    ----------
    image : (H, W) array
        Frame, ADU.
    centre_xy : (2,) array
        First guess of the disk centre, px (e.g. the extended detection's flux centre).
    radius_px : float
        First guess of the apparent radius, px.
    n_rays : int
        Scan lines over the full circle (those outside the Sun-side arc are skipped).
    sun_azimuth_rad : float, optional
        Direction of the Sun in the image, atan2(dy, dx); only rays within
        ``arc_half_width_rad`` of it are used. None uses every ray (a fully lit disk).
    smooth_px, min_contrast : float
        Profile smoothing (px) and the weakest edge kept, as a fraction of the strongest.
    radial_half_width_px : float, optional
        Scan only ``radius_px`` plus or minus this, px (a limb predicted to a pixel, read from an
        annulus window: :func:`limb_read_width_px` gives the pixels that reads); None scans 0.6 to
        1.4 times ``radius_px`` (a first guess from the detection).

    Returns
    -------
    (M, 2) array
        Edge points (x, y), px.
    """
    if not (radius_px > 2):
        raise InputError(f"limb_points needs radius_px > 2, got {radius_px!r}")
    angles = np.linspace(0.0, 2.0 * np.pi, n_rays, endpoint=False)
    if sun_azimuth_rad is not None:
        diff = np.angle(np.exp(1j * (angles - sun_azimuth_rad)))
        angles = angles[np.abs(diff) <= arc_half_width_rad]
    step = 0.25
    if radial_half_width_px is None:
        radii = np.arange(0.6 * radius_px, 1.4 * radius_px, step)
    else:
        if not (2.0 * smooth_px <= radial_half_width_px < radius_px):
            raise InputError(f"radial_half_width_px must be in [{2.0 * smooth_px:g}, radius_px), got {radial_half_width_px!r}")
        radii = np.arange(radius_px - radial_half_width_px, radius_px + radial_half_width_px, step)
    dirs = np.stack([np.cos(angles), np.sin(angles)], -1)
    profile = _ray_profiles(np.ascontiguousarray(image, dtype=float), np.asarray(centre_xy, float), dirs, radii)
    # ndimage.gaussian_filter1d(profile, smooth_px / step, axis=1, order=1) through OpenCV (2x faster):
    # the same kernel, the same reflected edges
    sigma = smooth_px / step
    kernel = ndimage._filters._gaussian_kernel1d(sigma, 1, int(4.0 * sigma + 0.5))[::-1]
    grad = cv2.filter2D(profile, cv2.CV_64F, kernel[None, :], anchor=(-1, -1), borderType=cv2.BORDER_REFLECT)
    k = np.argmin(grad, axis=1)  # brightness falls outwards
    k = np.clip(k, 1, len(radii) - 2)
    rows = np.arange(len(angles))
    g0, g1, g2 = grad[rows, k - 1], grad[rows, k], grad[rows, k + 1]
    curvature = g0 - 2 * g1 + g2
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(curvature > 0, 0.5 * (g0 - g2) / curvature, 0.0)
    r_edge = radii[k] + np.clip(frac, -0.5, 0.5) * step
    strength = -g1
    keep = strength >= min_contrast * np.max(strength)
    return np.asarray(centre_xy, float)[None, :] + r_edge[keep, None] * dirs[keep]


def limb_read_width_px(radial_half_width_px: float) -> float:
    """How far from the guessed radius :func:`limb_points` with ``radial_half_width_px`` reads
    pixels, px: the scanned radii plus the bilinear sample's neighbour."""
    return radial_half_width_px + 1.0


@kernel
def _ray_profiles(image, centre, dirs, radii):  # pragma: no cover - compiled
    """(rays, radii) bilinear samples of ``image`` at ``centre + radius * dir`` (x = column, y = row),
    the edge pixels extended outwards (scipy's ``map_coordinates`` with order 1, mode "nearest")."""
    rows, cols = image.shape
    out = np.empty((dirs.shape[0], radii.size))
    for i in range(dirs.shape[0]):
        for j in range(radii.size):
            x = centre[0] + radii[j] * dirs[i, 0]
            y = centre[1] + radii[j] * dirs[i, 1]
            x0 = math.floor(x)
            y0 = math.floor(y)
            fx = x - x0
            fy = y - y0
            c0 = min(max(x0, 0), cols - 1)
            c1 = min(max(x0 + 1, 0), cols - 1)
            r0 = min(max(y0, 0), rows - 1)
            r1 = min(max(y0 + 1, 0), rows - 1)
            top = image[r0, c0] * (1.0 - fx) + image[r0, c1] * fx
            bottom = image[r1, c0] * (1.0 - fx) + image[r1, c1] * fx
            out[i, j] = top * (1.0 - fy) + bottom * fy
    return out


@dataclass(frozen=True)
class LimbFit:
    """A fitted limb cone.

    Attributes
    ----------
    centre_cam : (3,) array
        Unit direction to the disk centre, camera frame.
    radius_rad : float
        Apparent angular radius of the fitted limb, rad.
    cov : (3, 3) array
        Covariance of (e1, e2, radius) in rad^2, where (e1, e2) are small rotations of
        ``centre_cam`` along ``tangent_cam`` rows.
    tangent_cam : (2, 3) array
        Orthonormal tangent basis at ``centre_cam``.
    inliers : (M,) bool
        Edge points kept by RANSAC.
    rms_rad : float
        RMS angular residual of the inliers, rad.
    """

    centre_cam: np.ndarray
    radius_rad: float
    cov: np.ndarray
    tangent_cam: np.ndarray
    inliers: np.ndarray
    rms_rad: float


def _cone_from_points(u: np.ndarray) -> tuple[np.ndarray, float] | None:
    w, *_ = np.linalg.lstsq(u, np.ones(len(u)), rcond=None)
    norm = np.linalg.norm(w)
    if not np.isfinite(norm) or norm <= 1.0:
        return None
    return w / norm, math.acos(1.0 / norm)


def _distinct_triples(rng: np.random.Generator, count: int, size: int) -> np.ndarray:
    """``size`` random triples of distinct indices below ``count`` (rows with a repeat drawn again)."""
    triples = rng.integers(0, count, (size, 3))
    while True:
        repeated = (triples[:, 0] == triples[:, 1]) | (triples[:, 0] == triples[:, 2]) | (triples[:, 1] == triples[:, 2])
        if not repeated.any():
            return triples
        triples[repeated] = rng.integers(0, count, (int(repeated.sum()), 3))


def _tangent_basis(c: np.ndarray) -> np.ndarray:
    ref = np.array([1.0, 0.0, 0.0]) if abs(c[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ c) * c
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(c, e1)])


def fit_limb(
    points_xy: np.ndarray,
    camera: Camera,
    *,
    rng: np.random.Generator | int | None = None,
    ransac_threshold_px: float = 1.0,
    ransac_iterations: int = 300,
    velocity_cam_km_s: np.ndarray | None = None,
) -> LimbFit:
    """Outlier-robust cone fit to limb points (module docstring, Limbs step 2).

    Parameters
    ----------
    points_xy : (M, 2) array
        Edge points, px (:func:`limb_points`).
    camera : Camera
        Converts pixels to directions (distortion included).
    rng : Generator, int or None
        Source of the RANSAC samples.
    ransac_threshold_px : float
        Inlier threshold, px (converted with the boresight pixel scale).
    ransac_iterations : int
    velocity_cam_km_s : (3,) array, optional
        Observer velocity relative to the SSB in the camera frame, km/s: the points' lines of
        sight are de-aberrated before the fit, so the cone is the geometric one (aberration maps
        the limb to a circle whose centre is not the aberrated direction of the body's centre:
        ~0.2" for the Earth from GEO, with the apparent radius changed by as much). None fits the
        apparent points.

    Returns
    -------
    LimbFit
        With ``velocity_cam_km_s``, the geometric cone (camera axes).

    Raises
    ------
    NoSolutionError
        Fewer than 5 points, or no consensus.
    """
    pts = np.asarray(points_xy, float)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 5:
        raise NoSolutionError(f"limb fit needs at least 5 edge points, got {len(pts) if pts.ndim == 2 else 0}")
    rng = np.random.default_rng(rng)
    u = camera.unproject(pts)
    if velocity_cam_km_s is not None:
        u = aberrate(u, -np.asarray(velocity_cam_km_s, float))  # the inverse Lorentz aberration
    threshold = ransac_threshold_px * camera.pixel_scale_rad
    # every RANSAC sample at once: the cone through 3 points solves u_i . w = 1 (w = c / cos(rho))
    samples = u[_distinct_triples(rng, len(u), ransac_iterations)]
    usable = np.abs(np.linalg.det(samples)) > 1e-12
    w = np.linalg.solve(samples[usable], np.ones((int(usable.sum()), 3, 1)))[..., 0]
    norm = np.linalg.norm(w, axis=1)
    cones = np.isfinite(norm) & (norm > 1.0)
    if not cones.any():
        raise NoSolutionError("limb fit: no consensus among the edge points")
    axes, rhos = w[cones] / norm[cones, None], np.arccos(1.0 / norm[cones])
    counts = np.sum(np.abs(np.arccos(np.clip(u @ axes.T, -1, 1)) - rhos) < threshold, axis=0)
    best = int(np.argmax(counts))  # the first of the largest consensus sets
    inliers = np.abs(np.arccos(np.clip(u @ axes[best], -1, 1)) - rhos[best]) < threshold
    if inliers.sum() < 5:
        raise NoSolutionError("limb fit: no consensus among the edge points")
    cone = _cone_from_points(u[inliers])
    if cone is None:
        raise NoSolutionError("limb fit: the inlier points do not define a cone")
    c, rho = cone
    for _ in range(20):
        basis = _tangent_basis(c)
        ui = u[inliers]
        cos_t = np.clip(ui @ c, -1, 1)
        theta = np.arccos(cos_t)
        sin_t = np.maximum(np.sin(theta), 1e-12)
        resid = theta - rho
        # d theta / d e_k = -(u . e_k) / sin(theta) for c -> c + e_k delta
        jac = np.column_stack([-(ui @ basis[0]) / sin_t, -(ui @ basis[1]) / sin_t, -np.ones(len(ui))])
        step, *_ = np.linalg.lstsq(jac, -resid, rcond=None)
        c = c + basis.T @ step[:2]
        c /= np.linalg.norm(c)
        rho += step[2]
        if np.max(np.abs(step)) < 1e-13:
            break
        # refresh the inliers around the refined cone
        full = np.abs(np.arccos(np.clip(u @ c, -1, 1)) - rho)
        inliers = full < threshold
    basis = _tangent_basis(c)
    ui = u[inliers]
    theta = np.arccos(np.clip(ui @ c, -1, 1))
    resid = theta - rho
    sin_t = np.maximum(np.sin(theta), 1e-12)
    jac = np.column_stack([-(ui @ basis[0]) / sin_t, -(ui @ basis[1]) / sin_t, -np.ones(len(ui))])
    dof = max(len(ui) - 3, 1)
    s2 = float(resid @ resid) / dof
    cov = s2 * np.linalg.inv(jac.T @ jac)
    return LimbFit(centre_cam=c, radius_rad=float(rho), cov=cov, tangent_cam=basis, inliers=inliers,
                   rms_rad=math.sqrt(float(resid @ resid) / len(ui)))


@dataclass(frozen=True)
class StarlightResult:
    """Starlight angle and elevation of one star against a limb-fitted body (S3).

    ``angle_rad``/``elevation_rad`` with variances ``var_angle_rad2``/``var_elevation_rad2``
    and their covariance ``cov_angle_elevation_rad2`` (they share the limb-centre and attitude
    errors); ``star_icrf`` the star's unit vector (ICRF); ``centre_icrf`` the body-centre direction.
    """

    angle_rad: float
    elevation_rad: float
    var_angle_rad2: float
    var_elevation_rad2: float
    star_icrf: np.ndarray
    centre_icrf: np.ndarray
    cov_angle_elevation_rad2: float = 0.0

    @property
    def covariance(self) -> np.ndarray:
        """Covariance (2, 2) rad^2 of [angle, elevation] (the ``starlight`` record's)."""
        return np.array([[self.var_angle_rad2, self.cov_angle_elevation_rad2],
                         [self.cov_angle_elevation_rad2, self.var_elevation_rad2]])


def starlight_measurements(
    fit: LimbFit,
    R_icrf_cam: Rotation,
    cov_attitude_rad2: np.ndarray,
    star_icrf: np.ndarray,
    *,
    body_radius_km: float,
    limb_altitude_km: float = 0.0,
    limb_altitude_sigma_km: float = 0.0,
    v_observer_km_s: np.ndarray | None = None,
) -> StarlightResult:
    """Starlight angle alpha and elevation beta = alpha - arcsin(R/|r|) with variances.

    Parameters
    ----------
    fit : LimbFit
        Limb cone in the camera frame.
    R_icrf_cam : Rotation
        Attitude of the limb camera, camera -> ICRF (e.g. from a star sensor).
    cov_attitude_rad2 : (3, 3) array
        Its covariance (camera-frame small rotation vector), rad^2.
    star_icrf : (3,) array
        Unit vector to the star, ICRF (apparent, as the filter's model uses).
    body_radius_km : float
        Body radius R of the measurement model, km.
    limb_altitude_km : float
        Altitude of the visible limb above R (module docstring, step 3), km.
    limb_altitude_sigma_km : float
        1-sigma uncertainty of that altitude (a model error common to all points), km.
    v_observer_km_s : (3,) array, optional
        Observer velocity relative to the SSB, ICRF, km/s, when ``fit`` is the geometric cone
        (:func:`fit_limb` ``velocity_cam_km_s``): its axis is aberrated to the apparent centre the
        angle is measured to (``star_icrf`` apparent too), its radius is the geometric one.

    Returns
    -------
    StarlightResult
    """
    star = np.asarray(star_icrf, float)
    star = star / np.linalg.norm(star)
    cov_att = np.asarray(cov_attitude_rad2, float)
    if cov_att.shape != (3, 3):
        raise InputError(f"cov_attitude_rad2 must be 3x3, got {cov_att.shape}")
    if not (body_radius_km > 0 and limb_altitude_km > -body_radius_km):
        raise InputError("body_radius_km must be positive and limb_altitude_km above -radius")
    rot = R_icrf_cam.as_matrix()
    c_icrf = rot @ fit.centre_cam
    if v_observer_km_s is not None:  # the aberration's Jacobian differs from the identity by 1e-4: kept out
        c_icrf = aberrate(c_icrf, np.asarray(v_observer_km_s, float))
    alpha = math.atan2(np.linalg.norm(np.cross(c_icrf, star)), float(c_icrf @ star))
    sin_alpha = max(math.sin(alpha), 1e-12)
    # d alpha / d c = -(S_perp) / sin(alpha), with c moved along the fit's tangent basis
    d_alpha_d_c = -(star - (star @ c_icrf) * c_icrf) / sin_alpha
    tangent_icrf = fit.tangent_cam @ rot.T  # rows: tangent directions in ICRF
    g_fit = np.array([d_alpha_d_c @ tangent_icrf[0], d_alpha_d_c @ tangent_icrf[1], 0.0])
    g_att = d_alpha_d_c @ rot @ (-_cross_matrix(fit.centre_cam))
    var_alpha = float(g_fit @ fit.cov @ g_fit + g_att @ cov_att @ g_att)
    ratio = body_radius_km / (body_radius_km + limb_altitude_km)
    sin_geo = math.sin(fit.radius_rad) * ratio
    rho_geo = math.asin(sin_geo)
    d_rho = ratio * math.cos(fit.radius_rad) / math.sqrt(1.0 - sin_geo**2)
    g_beta = g_fit - np.array([0.0, 0.0, d_rho])
    d_beta_d_h = math.sin(fit.radius_rad) * body_radius_km / (body_radius_km + limb_altitude_km) ** 2 / math.cos(rho_geo)
    var_beta = float(g_beta @ fit.cov @ g_beta + g_att @ cov_att @ g_att) + (d_beta_d_h * limb_altitude_sigma_km) ** 2
    cov_alpha_beta = float(g_fit @ fit.cov @ g_beta + g_att @ cov_att @ g_att)
    return StarlightResult(
        angle_rad=alpha, elevation_rad=alpha - rho_geo, var_angle_rad2=var_alpha,
        var_elevation_rad2=var_beta, star_icrf=star, centre_icrf=c_icrf, cov_angle_elevation_rad2=cov_alpha_beta,
    )


# ---- point sources on a bright neighbour's halo ----------------------------------------------

@dataclass(frozen=True)
class PointFit:
    """A point source fitted with a fixed-width Gaussian PSF over a sloping background.

    Attributes
    ----------
    xy : (2,) array
        Centre (x = column, y = row), px.
    cov : (2, 2) array
        Its covariance, px^2, scaled by the reduced chi-square when that exceeds 1.
    flux : float
        Source flux, ADU.
    snr : float
        Flux over its 1-sigma uncertainty.
    chi2, dof : float, int
        Weighted residual sum of squares of the fit and its degrees of freedom.
    psf_fraction : float
        Fraction of the source's PSF that falls on usable pixels of the stamp.
    """

    xy: np.ndarray
    cov: np.ndarray
    flux: float
    snr: float
    chi2: float
    dof: int
    psf_fraction: float


def _pixel_gaussian(u: np.ndarray, v: np.ndarray, x0: float, y0: float, s: float) -> tuple[np.ndarray, ...]:
    """Unit-flux pixel-integrated Gaussian on the grid (v rows, u cols) and its d/dx0, d/dy0."""
    from scipy.special import ndtr

    def axis(c, c0):
        lo, hi = (c - 0.5 - c0) / s, (c + 0.5 - c0) / s
        dens = (np.exp(-0.5 * lo * lo) - np.exp(-0.5 * hi * hi)) / (s * math.sqrt(2.0 * math.pi))
        return ndtr(hi) - ndtr(lo), dens

    ex, dex = axis(u, x0)
    ey, dey = axis(v, y0)
    return np.outer(ey, ex), np.outer(ey, dex), np.outer(dey, ex)


def psf_fraction(usable: np.ndarray, xy: np.ndarray, psf_sigma_px: float, window: int = 9) -> float:
    """Fraction of a point source's PSF at ``xy`` that falls on ``usable`` pixels.

    The PSF is the pixel-integrated Gaussian of :func:`fit_point_source`, over the same
    ``window`` stamp (centred on the pixel nearest ``xy``); pixels outside the frame count as
    not usable. It is :attr:`PointFit.psf_fraction` (whose stamp is centred on the fit's start
    pixel) for a position given beforehand, a prediction, instead of a fitted one.
    """
    usable = np.asarray(usable, bool)
    h, w = usable.shape
    cx, cy = (int(round(c)) for c in xy)
    half = window // 2
    u = np.arange(cx - half, cx + half + 1)
    v = np.arange(cy - half, cy + half + 1)
    psf = _pixel_gaussian(u.astype(float), v.astype(float), float(xy[0]), float(xy[1]), psf_sigma_px)[0]
    rows, cols = np.meshgrid(v, u, indexing="ij")
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    good = np.zeros(psf.shape, bool)
    good[inside] = usable[rows[inside], cols[inside]]
    return float(psf[good].sum() / max(psf.sum(), 1e-300))


def fit_point_source(
    image: np.ndarray,
    xy0: np.ndarray,
    *,
    usable: np.ndarray,
    psf_sigma_px: float,
    read_noise_e: float,
    gain_e_per_adu: float,
    bias_adu: float = 0.0,
    window: int = 9,
    max_iter: int = 30,
    suspect: np.ndarray | None = None,
) -> PointFit:
    """Weighted least-squares fit of ``F * PSF(x - x0, y - y0) + b0 + b1 dx + b2 dy`` to a stamp.

    The PSF is the pixel-integrated Gaussian of known width (the frame's stars give it); the
    plane absorbs the smooth part of a bright neighbour's halo. Pixels where ``usable`` is
    False (saturated, bloomed, too close to a bright limb) are left out, not modelled, so a
    partly hidden source is measured without bias from what it shares with the neighbour,
    at the cost of a larger covariance. Pixel variances follow the shifted-Poisson model
    ``read_noise^2/gain^2 + (model - bias)/gain`` (ADU^2) at the current model (iterated
    reweighting; Gauss–Newton steps on the linear parameters and the centre).

    Parameters
    ----------
    image : (H, W) array
        Frame, ADU.
    xy0 : (2,) array
        Starting centre, px, within ~1 px of the source.
    usable : (H, W) bool array
        Pixels the fit may use.
    psf_sigma_px : float
        Gaussian PSF sigma, px.
    read_noise_e, gain_e_per_adu, bias_adu : float
        Detector read noise (e-), gain (e-/ADU) and bias (ADU).
    window : int
        Odd stamp side, px.
    max_iter : int
        Gauss–Newton iteration limit.
    suspect : (H, W) bool array, optional
        Pixels a detector flagged as possible cosmic-ray hits or hot pixels
        (:attr:`opnav.image.detect.Detections.rejected`). The source is first fitted without
        them; then those of them the fit's model explains within :data:`SUSPECT_SIGMAS` noise
        sigmas are put back and the fit repeated (a pixel the new fit leaves beyond that is
        dropped again). Leaving every flagged pixel out would bias the centre: the flags depend
        on each pixel's own noise (a bright fluctuation on a halo's slope fails a sharpness
        test more often than a faint one), so the flagged set takes upward fluctuations away
        from one side of the source. A real hit is far beyond the model and stays out.

    Returns
    -------
    PointFit

    Raises
    ------
    NoSolutionError
        Too few usable pixels, no convergence, a non-positive flux or a centre that leaves
        the stamp.
    """
    image = np.asarray(image, float)
    if window < 5 or window % 2 == 0:
        raise InputError(f"fit_point_source window must be odd and >= 5, got {window}")
    if not (psf_sigma_px > 0 and gain_e_per_adu > 0 and read_noise_e >= 0):
        raise InputError("fit_point_source needs psf_sigma_px > 0, gain_e_per_adu > 0 and read_noise_e >= 0")
    h, w = image.shape
    for name, mask in (("usable", usable), ("suspect", suspect)):
        if mask is not None and np.shape(mask) != image.shape:
            raise InputError(f"fit_point_source: {name} has shape {np.shape(mask)}, the image {image.shape}")
    cx, cy = (int(round(c)) for c in xy0)
    half = window // 2
    if not (half <= cx < w - half and half <= cy < h - half):
        raise NoSolutionError("fit_point_source: the stamp leaves the frame")
    u = np.arange(cx - half, cx + half + 1, dtype=float)
    v = np.arange(cy - half, cy + half + 1, dtype=float)
    stamp = (slice(cy - half, cy + half + 1), slice(cx - half, cx + half + 1))
    data = image[stamp]
    allowed = np.asarray(usable, bool)[stamp]
    flagged = np.zeros_like(allowed) if suspect is None else allowed & np.asarray(suspect, bool)[stamp]
    good = allowed & ~flagged
    n_par = 6  # x0, y0, F and the plane
    if good.sum() < 2 * n_par:
        raise NoSolutionError(f"fit_point_source: only {int(good.sum())} usable pixels in the stamp")
    du, dv = np.meshgrid(u - cx, v - cy)
    b0 = float(np.median(data[good]))
    params = np.array([float(xy0[0]), float(xy0[1]), max(float(np.sum(np.clip(data[good] - b0, 0, None))), 1.0),
                       b0, 0.0, 0.0])
    read_var = (read_noise_e / gain_e_per_adu) ** 2

    def model_and_variance(params):
        psf, dpx, dpy = _pixel_gaussian(u, v, params[0], params[1], psf_sigma_px)
        model = params[2] * psf + params[3] + params[4] * du + params[5] * dv
        return psf, dpx, dpy, model, read_var + np.clip(model - bias_adu, 0.0, None) / gain_e_per_adu

    def weighted_system(params, good):
        """PSF, model, and the Jacobian and weights of the ``good`` pixels at ``params``."""
        psf, dpx, dpy, model, var = model_and_variance(params)
        jac = np.stack([params[2] * dpx, params[2] * dpy, psf, np.ones_like(psf), du, dv], -1)[good]
        return psf, model, jac, 1.0 / var[good]

    def iterate(params, good):
        for _ in range(max_iter):
            _, model, jac, wts = weighted_system(params, good)
            normal = jac.T @ (jac * wts[:, None])
            step = np.linalg.lstsq(normal, jac.T @ (wts * (data[good] - model[good])), rcond=None)[0]
            params = params + step
            if not (np.all(np.isfinite(step)) and abs(params[0] - cx) < half and abs(params[1] - cy) < half
                    and params[2] > 0):
                raise NoSolutionError("fit_point_source: the fit left the stamp or lost the source")
            if max(abs(step[0]), abs(step[1])) < 1e-5:
                return params
        raise NoSolutionError("fit_point_source: no convergence")

    params = iterate(params, good)
    for _ in range(3):  # flagged pixels the model explains go back in (parameter ``suspect``)
        *_, model, var = model_and_variance(params)
        unexplained = flagged & (data - model > SUSPECT_SIGMAS * np.sqrt(var))
        if np.array_equal(good, allowed & ~unexplained):
            break
        good = allowed & ~unexplained
        params = iterate(params, good)
    x0, y0, flux = params[:3]
    psf, model, jac, wts = weighted_system(params, good)
    cov = np.linalg.inv(jac.T @ (jac * wts[:, None]))
    chi2 = float(np.sum(wts * (data[good] - model[good]) ** 2))
    dof = int(good.sum()) - jac.shape[1]
    scale = max(1.0, chi2 / dof)
    return PointFit(
        xy=np.array([x0, y0]), cov=cov[:2, :2] * scale, flux=float(flux), snr=float(flux / math.sqrt(cov[2, 2] * scale)),
        chi2=chi2, dof=dof, psf_fraction=float(psf[good].sum() / max(psf.sum(), 1e-300)),
    )
