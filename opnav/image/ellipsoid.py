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

Model image (:func:`render_ellipsoid`): the renderer's own pixel integral
(:func:`opnav.bodies.ellipsoid_pixel_means`: each pixel's rays, finer on the pixels the limb or
the terminator crosses, shaded Lambert or Lommel-Seeliger) convolved with the pixel-integrated
Gaussian PSF, so a template differs from a rendered body only by noise and by the pose it was
made at. No shadowing (an ellipsoid casts none on itself). Unless the caller names the pixels,
only those near the lit part of the body's face are integrated (:func:`lit_mask`: its outline's
lit arc and the terminator's visible arc, both circles on the unit sphere of the whitened frame),
which leaves the image the same to the last bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy import ndimage
from scipy.special import erf

from ..bodies import ellipsoid_pixel_means
from ..camera import Camera
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


def pixel_gaussian_kernel(sigma_px: float) -> np.ndarray:
    """1-D pixel-integrated Gaussian (the renderer's PSF, :mod:`opnav.render.psf`), unit sum."""
    half = int(math.ceil(6.0 * sigma_px)) + 1
    edges = (np.arange(-half, half + 2) - 0.5) / (math.sqrt(2.0) * sigma_px)
    k = np.diff(erf(edges)) / 2.0
    return k / k.sum()


def render_ellipsoid(camera: Camera, pose: EllipsoidPose, box: tuple[int, int, int, int], *, psf_sigma_px: float,
                     supersample: int = 2, pixels: np.ndarray | None = None) -> np.ndarray:
    """Noise-free model image of the lit body over ``box = (x0, y0, width, height)`` (px), in units of
    I/F per unit albedo (module docstring).

    Each pixel's mean I/F on its own rays, as the renderer integrates a frame
    (:func:`opnav.bodies.ellipsoid_pixel_means`: ``supersample`` rays per axis where the shading
    is smooth, :data:`opnav.bodies.EDGE_SUPERSAMPLE` on the pixels the limb or the terminator
    crosses and their neighbours), then the pixel-integrated Gaussian PSF. ``pixels`` (height,
    width) bool: integrate only these (e.g. a band around the limb; the others stay dark, so keep a
    PSF's reach of margin around what is read). Without ``pixels``, only those within
    :data:`LIT_REACH_PX` of the lit part of the body's face are integrated (:func:`lit_mask`): the
    rest hold no light, yet a body under ``_SMALL_BODY_PX`` across is integrated on the edge grid
    everywhere (its box's dark margin cost three times its own pixels) and the pixels the night
    side's limb crosses are too (half a crescent's cost). A caller's ``pixels`` (the limb fit's
    bands along the lit limb) are taken as they are: the mask would leave out little of them and
    cost its outline's polygon per tile (24 tiles of an 800 px body: 12 ms).
    """
    x0, y0, w, h = box
    if w <= 0 or h <= 0:
        raise InputError(f"render_ellipsoid: empty box {box!r}")
    if pixels is None:
        pixels = lit_mask(camera, pose, box)
    cx, cy = np.meshgrid(np.arange(x0, x0 + w + 1) - 0.5, np.arange(y0, y0 + h + 1) - 0.5)
    corners = camera.unproject(np.column_stack([cx.ravel(), cy.ravel()])).reshape(h + 1, w + 1, 3)
    rot = pose.R_cam_body  # body -> camera: a camera-frame row vector v is v @ rot in the body's axes
    r = pose.r_cam_km
    size_px = 2.0 * math.asin(min(float(np.max(pose.radii_km)) / float(np.linalg.norm(r)), 1.0)) * camera.focal_length_px
    image = ellipsoid_pixel_means((corners / corners[..., 2:3]) @ rot, -r @ rot, pose.radii_km, pose.sun_cam @ rot,
                                  lambert=pose.shading == "lambert", supersample=supersample, size_px=size_px,
                                  wanted=pixels)
    kernel = pixel_gaussian_kernel(psf_sigma_px)
    image = ndimage.convolve1d(image, kernel, axis=0, mode="constant")
    return ndimage.convolve1d(image, kernel, axis=1, mode="constant")


#: Pixels (px) around the lit part's polygon that :func:`lit_mask` keeps: a pixel the lit part
#: enters has its centre within 0.71 px of it (or of the pixels the polygon's edges are drawn
#: on), and the polygon's 0.5 px chords and a distortion's bend across a pixel are hundredths of a
#: pixel.
LIT_REACH_PX = 2


def lit_outline(camera: Camera, pose: EllipsoidPose, spacing_px: float = 0.5) -> np.ndarray | None:
    """Detector pixels (N, 2), about ``spacing_px`` apart (closed), around the lit part of the body's
    visible face: the outline's lit arc, then the terminator's visible arc back; the whole outline
    when the terminator is not in view, None when no lit part is.

    In the whitened frame (module docstring, ``B``) the surface is the unit sphere, the camera is at
    ``c = -B r``, a point ``y`` of it is in view where ``y . c > 1`` (the horizon circle its edge) and
    lit where ``y . B s > 0`` (``s`` the Sun's direction: the normal is ``B^T y``), so the terminator
    is the great circle normal to ``B s``; the two circles cross at the cusps."""
    b = whitening(pose)
    c = -(b @ pose.r_cam_km)
    d = float(np.linalg.norm(c))
    u = c / d
    sun = b @ pose.sun_cam
    sun /= np.linalg.norm(sun)
    ref = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(u, ref)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    rho = math.sqrt(max(1.0 - 1.0 / d**2, 0.0))
    size_px = 2.0 * math.asin(min(float(np.max(pose.radii_km)) / float(np.linalg.norm(pose.r_cam_km)), 1.0)) \
        * camera.focal_length_px
    n = int(max(64, math.ceil(math.pi * size_px / spacing_px)))
    # the horizon y(phi) = u / d + rho (cos phi e1 + sin phi e2) is lit where
    # y . s = (s . u) / d + rho |s_perp| cos(phi - psi) > 0
    su, s1, s2 = float(sun @ u), float(sun @ e1), float(sun @ e2)
    beta = math.hypot(s1, s2)
    if rho * beta * d <= abs(su):
        if su < 0.0:
            return None  # the visible face is all night
        phi = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
        pts = u / d + rho * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    else:
        psi, half = math.atan2(s2, s1), math.acos(-su / (d * rho * beta))
        phi = np.linspace(psi - half, psi + half, max(int(math.ceil(n * half / np.pi)), 8))
        limb = u / d + rho * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
        # the terminator z(theta) = cos theta g1 + sin theta g2 is in view about theta = 0 (g1 the
        # direction in its plane nearest the camera's): from the last cusp back to the first
        g1 = u - su * sun
        g1 /= np.linalg.norm(g1)
        g2 = np.cross(sun, g1)
        t_end, t_start = (math.atan2(float(q @ g2), float(q @ g1)) for q in (limb[0], limb[-1]))
        theta = np.linspace(t_start, t_end, max(int(math.ceil(n * abs(t_end - t_start) / (2.0 * np.pi))), 8))[1:-1]
        pts = np.concatenate([limb, np.cos(theta)[:, None] * g1 + np.sin(theta)[:, None] * g2])
    xy = camera.project(pose.r_cam_km[None, :] + pts @ np.linalg.inv(b).T)
    if not np.all(np.isfinite(xy)):
        raise NoSolutionError("the body's outline reaches behind the camera")
    return xy


def lit_mask(camera: Camera, pose: EllipsoidPose, box: tuple[int, int, int, int]) -> np.ndarray | None:
    """(height, width) bool over ``box = (x0, y0, width, height)``: the pixels within
    :data:`LIT_REACH_PX` of the lit part of the body's visible face (:func:`lit_outline`; every other
    pixel's rays miss the body or meet its night side); None when the outline reaches behind the
    camera (no polygon: every pixel may see light)."""
    x0, y0, w, h = box
    try:
        xy = lit_outline(camera, pose)
    except NoSolutionError:
        return None
    mask = np.zeros((h, w), np.uint8)
    if xy is None:
        return mask.astype(bool)
    # pixel (i, j) of the box is centred on detector (x0 + j, y0 + i); cv2 takes 1/16 px as integers
    pts = np.round((xy - np.array([x0, y0], float)) * 16.0)
    if not np.all(np.abs(pts) < 2.0**26):
        return None  # far off the box (a body beyond it): cv2's fixed point would overflow
    pts = pts.astype(np.int32)
    # the edges drawn too: a crescent thinner than a pixel may cover no pixel's centre
    cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=4)
    cv2.polylines(mask, [pts], True, 1, lineType=cv2.LINE_8, shift=4)
    side = 2 * LIT_REACH_PX + 1
    return cv2.dilate(mask, np.ones((side, side), np.uint8)).astype(bool)


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


def outline_box(camera: Camera, pose: EllipsoidPose, margin_px: float) -> tuple[int, int, int, int]:
    """``(x0, y0, width, height)`` of the detector pixels within ``margin_px`` of the outline's
    bounding box (clipped to the detector)."""
    xy = outline_points(camera, pose, spacing_px=2.0)
    lo = np.maximum(np.floor(xy.min(0) - margin_px).astype(int), 0)
    hi = np.minimum(np.ceil(xy.max(0) + margin_px).astype(int), [camera.width_px - 1, camera.height_px - 1])
    if np.any(hi < lo):
        raise NoSolutionError("the body's outline is off the detector")
    return int(lo[0]), int(lo[1]), int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)
