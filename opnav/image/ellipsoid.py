"""A tri-axial ellipsoid seen by a camera: its horizon conic, the closed-form horizon solution and a
noise-free model image.

The camera is at the origin of the camera frame (+z boresight, +x along columns, +y along rows);
the body's centre is at ``r`` (km, camera frame), its semi-axes ``(a, b, c)`` (km) lie along the
columns of ``R_cam_body``. A point ``x`` is on the surface when ``(x - r)^T A (x - r) = 1`` with
``A = R_cam_body diag(a^-2, b^-2, c^-2) R_cam_body^T``.

Horizon cone. The rays ``u`` from the camera that graze the surface satisfy ``u^T C u = 0`` with
``C = A r r^T A - (r^T A r - 1) A`` (positive inside the body's outline, negative outside). In
*ideal* image coordinates (pinhole, no distortion, origin at the principal point, px) a point
``(x, y)`` is the direction ``m = (x, y, f)``, so ``C`` is also the outline's conic there.

Closed-form horizon solution (Christian, "A Tutorial on Horizon-Based Optical Navigation and
Attitude Determination With Space Imaging Systems", IEEE Access 9, 2021, sect. IV; after
Christian and Robinson, J. Astronaut. Sci. 2017). With ``B = diag(a^-1, b^-1, c^-1) R_cam_body^T``
(``B^T B = A``) the ellipsoid is the unit sphere centred on ``B r``; each horizon direction
``s_i = B u_i / |B u_i|`` then satisfies ``s_i . n = 1`` with ``n = B r / sqrt(|B r|^2 - 1)``. The
least-squares ``n`` of the stacked equations gives ``B r = n / sqrt(n.n - 1)`` and ``r`` itself,
range included: the body's known size sets the range.

Model image (:func:`render_ellipsoid`): rays on a ``supersample x supersample`` grid per pixel (a
finer one on the pixels the outline crosses) are intersected with the ellipsoid, shaded with :func:`opnav.bodies.reflectance` (Lambert or
Lommel-Seeliger at the hit point's incidence and emission cosines), averaged per pixel (the pixel
integral) and convolved with the pixel-integrated Gaussian PSF: the renderer's own steps
(:mod:`opnav.render.frame`), so a template differs from a rendered body only by noise and by the
pose it was made at. No shadowing (an ellipsoid casts none on itself).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy import ndimage
from scipy.special import erf

from ..bodies import reflectance
from ..camera import Camera
from ..compiled import kernel
from ..errors import InputError, NoSolutionError


@dataclass(frozen=True)
class EllipsoidPose:
    """A body's shape, orientation, position and lighting in the camera frame.

    Attributes
    ----------
    radii_km : (3,) array
        Semi-axes along the body's x, y, z, km.
    R_cam_body : (3, 3) array
        Body -> camera rotation (its columns are the body axes in the camera frame).
    r_cam_km : (3,) array
        Camera -> body centre, camera frame, km.
    sun_cam : (3,) array
        Unit vector body -> Sun, camera frame.
    shading : {"lambert", "lommel-seeliger"}
    """

    radii_km: np.ndarray
    R_cam_body: np.ndarray
    r_cam_km: np.ndarray
    sun_cam: np.ndarray
    shading: str = "lambert"

    def __post_init__(self) -> None:
        radii = np.asarray(self.radii_km, float).reshape(-1)
        if radii.shape != (3,) or not np.all(np.isfinite(radii) & (radii > 0)):
            raise InputError(f"EllipsoidPose.radii_km must be three positive numbers, got {self.radii_km!r}")
        rot = np.asarray(self.R_cam_body, float)
        if rot.shape != (3, 3) or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-9):
            raise InputError("EllipsoidPose.R_cam_body must be a 3x3 rotation matrix")
        r = np.asarray(self.r_cam_km, float).reshape(-1)
        sun = np.asarray(self.sun_cam, float).reshape(-1)
        if r.shape != (3,) or sun.shape != (3,) or not (np.all(np.isfinite(r)) and np.all(np.isfinite(sun))):
            raise InputError("EllipsoidPose.r_cam_km and sun_cam must be finite 3-vectors")
        if self.shading not in ("lambert", "lommel-seeliger"):
            raise InputError(f"EllipsoidPose.shading must be lambert or lommel-seeliger, got {self.shading!r}")
        object.__setattr__(self, "radii_km", radii)
        object.__setattr__(self, "R_cam_body", rot)
        object.__setattr__(self, "r_cam_km", r)
        object.__setattr__(self, "sun_cam", sun / np.linalg.norm(sun))
        if float(r @ shape_matrix(self) @ r) <= 1.0:
            raise InputError("EllipsoidPose: the camera is inside the body")

    def at(self, r_cam_km: np.ndarray) -> "EllipsoidPose":
        """The same body moved to ``r_cam_km`` (camera frame, km)."""
        return replace(self, r_cam_km=np.asarray(r_cam_km, float))

    @property
    def phase_rad(self) -> float:
        """Sun-body-camera angle, rad."""
        to_camera = -self.r_cam_km / np.linalg.norm(self.r_cam_km)
        return float(np.arccos(np.clip(self.sun_cam @ to_camera, -1.0, 1.0)))


def shape_matrix(pose: EllipsoidPose) -> np.ndarray:
    """``A`` of the module docstring, camera frame, km^-2."""
    rot = pose.R_cam_body
    return rot @ np.diag(pose.radii_km**-2.0) @ rot.T


def whitening(pose: EllipsoidPose) -> np.ndarray:
    """``B`` with ``B^T B = A``: camera-frame km -> the frame where the body is the unit sphere."""
    return np.diag(1.0 / pose.radii_km) @ pose.R_cam_body.T


def horizon_cone(pose: EllipsoidPose) -> np.ndarray:
    """``C`` of the module docstring (3, 3): ``u^T C u`` > 0 inside the outline, 0 on it."""
    a = shape_matrix(pose)
    ar = a @ pose.r_cam_km
    return np.outer(ar, ar) - (float(pose.r_cam_km @ ar) - 1.0) * a


def horizon_cones(a: np.ndarray, r_cam_km: np.ndarray) -> np.ndarray:
    """:func:`horizon_cone` of a body of shape matrix ``a`` (3, 3) at positions ``r_cam_km`` (K, 3):
    (K, 3, 3)."""
    ar = np.asarray(r_cam_km, float) @ a
    return ar[:, :, None] * ar[:, None, :] - (np.sum(ar * r_cam_km, 1) - 1.0)[:, None, None] * a


def ideal_xy(camera: Camera, xy: np.ndarray) -> np.ndarray:
    """Detector pixels (..., 2) -> ideal image coordinates (..., 2), px (distortion removed,
    origin at the principal point)."""
    u = camera.unproject(xy)
    return camera.focal_length_px * u[..., :2] / u[..., 2:3]


def centre_pixel(camera: Camera, r_cam_km: np.ndarray) -> np.ndarray:
    """Detector pixel (x, y) of the direction of ``r_cam_km`` (camera frame)."""
    return camera.project(np.asarray(r_cam_km, float))


def line_crossings(cone: np.ndarray, focal_px: float, start_xy: np.ndarray, dir_xy: np.ndarray) -> np.ndarray:
    """Distance (px) along each ideal-coordinate line ``start + a dir`` to its far crossing of the
    outline (the larger root: with ``dir`` pointing to the Sun, the lit limb); NaN where it misses.

    ``start_xy`` (L, 2) and unit ``dir_xy`` (L, 2) in ideal coordinates; ``cone`` from
    :func:`horizon_cone` (or a stack (K, 3, 3) broadcast against the lines).
    """
    m0 = np.concatenate([start_xy, np.full(start_xy.shape[:-1] + (1,), focal_px)], -1)
    s = np.concatenate([dir_xy, np.zeros(dir_xy.shape[:-1] + (1,))], -1)
    cs = np.einsum("...ij,...j->...i", cone, s)
    alpha = np.sum(s * cs, -1)
    beta = np.sum(m0 * cs, -1)
    gamma = np.einsum("...i,...ij,...j->...", m0, cone, m0)
    disc = beta * beta - alpha * gamma
    with np.errstate(invalid="ignore", divide="ignore"):
        # alpha < 0 (far along any line is outside): the larger root takes the minus sign
        return np.where((disc >= 0) & (alpha < 0), (-beta - np.sqrt(np.maximum(disc, 0.0))) / alpha, np.nan)


def horizon_position(pose: EllipsoidPose, u_cam: np.ndarray) -> np.ndarray:
    """Closed-form body position (camera frame, km) from horizon directions (module docstring).

    ``u_cam`` (N, 3): camera-frame directions of points on the body's outline, N >= 3; ``pose``
    supplies the shape and orientation (its position is not used). Raises ``NoSolutionError`` when
    the points do not define a cone around the body.
    """
    u = np.asarray(u_cam, float)
    if u.ndim != 2 or u.shape[1] != 3 or len(u) < 3:
        raise NoSolutionError(f"horizon solution needs at least 3 outline directions, got {len(u)}")
    b = whitening(pose)
    s = u @ b.T
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    n, *_ = np.linalg.lstsq(s, np.ones(len(s)), rcond=None)
    nn = float(n @ n)
    if not np.isfinite(nn) or nn <= 1.0:
        raise NoSolutionError("horizon solution: the outline points do not enclose a body")
    return np.linalg.solve(b, n / math.sqrt(nn - 1.0))


def edge_supersample(camera: Camera, pose: EllipsoidPose) -> int:
    """Rays per pixel per axis on the pixels the outline crosses, by apparent size: a small body's
    centre rests on few edge pixels, each of whose lit fraction a coarse grid quantises (an 8 x 8
    grid moved a 10 px Phobos' correlation centre by ~0.008 px with the model's sub-pixel phase,
    32 x 32 by ~0.002 px); a large one has thousands of them, whose errors average out."""
    size = 2.0 * float(np.max(pose.radii_km)) / float(np.linalg.norm(pose.r_cam_km)) * camera.focal_length_px
    return 32 if size < 60.0 else 16 if size < 300.0 else 8


def pixel_gaussian_kernel(sigma_px: float) -> np.ndarray:
    """1-D pixel-integrated Gaussian (the renderer's PSF, :mod:`opnav.render.psf`), unit sum."""
    half = int(math.ceil(6.0 * sigma_px)) + 1
    edges = (np.arange(-half, half + 2) - 0.5) / (math.sqrt(2.0) * sigma_px)
    k = np.diff(erf(edges)) / 2.0
    return k / k.sum()


def _shade(camera: Camera, pose: EllipsoidPose, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """I/F per unit albedo of the rays through detector points (xs, ys); 0 off the lit body."""
    u = camera.unproject(np.stack([xs, ys], -1))
    a = shape_matrix(pose)
    r = pose.r_cam_km
    au = u @ a
    qa = np.sum(au * u, 1)
    qb = au @ r
    qc = float(r @ a @ r) - 1.0
    disc = qb * qb - qa * qc
    hit = disc > 0
    t = (qb[hit] - np.sqrt(disc[hit])) / qa[hit]
    point = t[:, None] * u[hit]
    normal = (point - r) @ a
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    mu = -np.sum(normal * u[hit], 1)
    mu0 = normal @ pose.sun_cam
    lit = (mu0 > 0) & (mu > 0)
    value = np.zeros(len(u))
    value[np.flatnonzero(hit)[lit]] = reflectance(mu0[lit], mu[lit], pose.shading, 1.0)
    return value


def _pixel_means(camera: Camera, pose: EllipsoidPose, cols: np.ndarray, rows: np.ndarray, supersample: int) -> np.ndarray:
    """Mean I/F over a ``supersample x supersample`` grid in each pixel (the pixel integral); a
    pinhole camera's in one compiled pass (:func:`_pinhole_pixel_means`), a distorted one's through
    :meth:`Camera.unproject`."""
    if not camera.has_distortion:
        return _pinhole_pixel_means(np.ascontiguousarray(cols, np.float64), np.ascontiguousarray(rows, np.float64),
                                    int(supersample), float(camera.cx_px), float(camera.cy_px),
                                    float(camera.focal_length_px), shape_matrix(pose), pose.r_cam_km, pose.sun_cam,
                                    pose.shading == "lambert")
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    ox, oy = np.meshgrid(offsets, offsets)
    xs = (cols[:, None] + ox.ravel()[None, :]).ravel()
    ys = (rows[:, None] + oy.ravel()[None, :]).ravel()
    return _shade(camera, pose, xs, ys).reshape(-1, supersample * supersample).mean(1)


@kernel
def _pinhole_pixel_means(cols, rows, ss, cx, cy, f, a, r, sun, lambert):  # pragma: no cover - compiled
    """:func:`_shade` averaged over each pixel's grid for a pinhole camera, without the arrays of
    every ray (a 20 px body's edge pixels on a 32 x 32 grid are 2e5 rays: 0.2 s in numpy). The I/F
    is :func:`opnav.bodies.reflectance`'s at unit albedo."""
    ar0 = a[0, 0] * r[0] + a[0, 1] * r[1] + a[0, 2] * r[2]
    ar1 = a[1, 0] * r[0] + a[1, 1] * r[1] + a[1, 2] * r[2]
    ar2 = a[2, 0] * r[0] + a[2, 1] * r[1] + a[2, 2] * r[2]
    qc = r[0] * ar0 + r[1] * ar1 + r[2] * ar2 - 1.0
    out = np.zeros(cols.size)
    for i in range(cols.size):
        acc = 0.0
        for jy in range(ss):
            y = rows[i] + (jy + 0.5) / ss - 0.5
            for jx in range(ss):
                x = cols[i] + (jx + 0.5) / ss - 0.5
                u0 = (x - cx) / f
                u1 = (y - cy) / f
                norm = math.sqrt(u0 * u0 + u1 * u1 + 1.0)
                u0 /= norm
                u1 /= norm
                u2 = 1.0 / norm
                au0 = a[0, 0] * u0 + a[0, 1] * u1 + a[0, 2] * u2
                au1 = a[1, 0] * u0 + a[1, 1] * u1 + a[1, 2] * u2
                au2 = a[2, 0] * u0 + a[2, 1] * u1 + a[2, 2] * u2
                qa = u0 * au0 + u1 * au1 + u2 * au2
                qb = u0 * ar0 + u1 * ar1 + u2 * ar2
                disc = qb * qb - qa * qc
                if disc <= 0.0:
                    continue
                t = (qb - math.sqrt(disc)) / qa
                p0, p1, p2 = t * u0 - r[0], t * u1 - r[1], t * u2 - r[2]
                n0 = a[0, 0] * p0 + a[0, 1] * p1 + a[0, 2] * p2
                n1 = a[1, 0] * p0 + a[1, 1] * p1 + a[1, 2] * p2
                n2 = a[2, 0] * p0 + a[2, 1] * p1 + a[2, 2] * p2
                nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
                mu = -(n0 * u0 + n1 * u1 + n2 * u2) / nn
                mu0 = (n0 * sun[0] + n1 * sun[1] + n2 * sun[2]) / nn
                if mu > 0.0 and mu0 > 0.0:
                    acc += 1.5 * mu0 if lambert else 2.0 * mu0 / (mu0 + mu)
        out[i] = acc / (ss * ss)
    return out


def render_ellipsoid(camera: Camera, pose: EllipsoidPose, box: tuple[int, int, int, int], *, psf_sigma_px: float,
                     supersample: int = 8, inner_supersample: int = 2, pixels: np.ndarray | None = None) -> np.ndarray:
    """Noise-free model image of the lit body over ``box = (x0, y0, width, height)`` (px), in units of
    I/F per unit albedo (module docstring).

    Pixels within 1.5 px of the outline (where the light stops) are integrated on a
    ``supersample``-square grid, the others (smooth shading: the terminator of a Lambert or
    Lommel-Seeliger body fades continuously to zero) on an ``inner_supersample`` one.
    ``pixels`` (height, width) bool: ray-cast only these (e.g. a band around the limb; the others
    stay dark, so keep a PSF's reach of margin around what is read).
    """
    x0, y0, w, h = box
    if w <= 0 or h <= 0:
        raise InputError(f"render_ellipsoid: empty box {box!r}")
    wanted = np.ones((h, w), bool) if pixels is None else np.asarray(pixels, bool)
    edge = outline_mask(camera, pose, box, half_width_px=1.5) & wanted
    image = np.zeros((h, w))
    for mask, ss in ((edge, supersample), (wanted & ~edge, inner_supersample)):
        rows, cols = np.nonzero(mask)
        if rows.size:
            image[rows, cols] = _pixel_means(camera, pose, cols + x0, rows + y0, ss)
    kernel = pixel_gaussian_kernel(psf_sigma_px)
    image = ndimage.convolve1d(image, kernel, axis=0, mode="constant")
    return ndimage.convolve1d(image, kernel, axis=1, mode="constant")


def outline_points(camera: Camera, pose: EllipsoidPose, spacing_px: float = 0.5) -> np.ndarray:
    """Detector pixels (N, 2) along the body's outline, about ``spacing_px`` apart (closed)."""
    centre = pose.r_cam_km
    b = whitening(pose)
    c_unit = b @ centre
    d = float(np.linalg.norm(c_unit))
    axis = c_unit / d
    ref = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(axis, ref)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    rho = math.sqrt(max(1.0 - 1.0 / d**2, 0.0))
    # the horizon circle on the unit sphere: 1/d from its centre toward the camera, radius rho
    size_px = 2.0 * math.asin(min(float(np.max(pose.radii_km)) / float(np.linalg.norm(centre)), 1.0)) * camera.focal_length_px
    n = int(max(64, math.ceil(math.pi * size_px / spacing_px)))
    phi = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    pts_unit = -axis[None, :] / d + rho * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    xy = camera.project(centre[None, :] + pts_unit @ np.linalg.inv(b).T)
    if not np.all(np.isfinite(xy)):
        raise NoSolutionError("the body's outline reaches behind the camera")
    return xy


def outline_mask(camera: Camera, pose: EllipsoidPose, box: tuple[int, int, int, int], *,
                 half_width_px: float) -> np.ndarray:
    """(height, width) bool over ``box``: pixels within about ``half_width_px`` of the outline
    (the outline drawn as a polyline of that half-width; a pixel's centre counts)."""
    x0, y0, w, h = box
    pts = outline_points(camera, pose) - np.array([x0, y0], float)
    mask = np.zeros((h, w), np.uint8)
    shift = 4  # OpenCV's fixed-point sub-pixel vertices (1/16 px)
    poly = np.round(pts * (1 << shift)).astype(np.int32)[None]
    cv2.polylines(mask, poly, True, 1, thickness=max(int(round(2.0 * half_width_px)), 1), lineType=cv2.LINE_8,
                  shift=shift)
    return mask.astype(bool)


def outline_box(camera: Camera, pose: EllipsoidPose, margin_px: float) -> tuple[int, int, int, int]:
    """``(x0, y0, width, height)`` of the detector pixels within ``margin_px`` of the outline's
    bounding box (clipped to the detector)."""
    xy = outline_points(camera, pose, spacing_px=2.0)
    lo = np.maximum(np.floor(xy.min(0) - margin_px).astype(int), 0)
    hi = np.minimum(np.ceil(xy.max(0) + margin_px).astype(int), [camera.width_px - 1, camera.height_px - 1])
    if np.any(hi < lo):
        raise NoSolutionError("the body's outline is off the detector")
    return int(lo[0]), int(lo[1]), int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)
