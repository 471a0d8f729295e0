"""Centre of a mesh-shaped body (:class:`opnav.shape.Mesh`): cross-correlation with a template the
renderer draws from the mesh at the a-priori pose, or, far out, a point-source centroid moved by the
mesh's own photocentre offset.

An irregular body has no limb an ellipsoid describes, so it is measured as
:mod:`opnav.image.correlate` measures a small body, with the mesh as the model:

1. **Pose** (:func:`mesh_pose`): the body's orientation, position (apparent direction times the
   light-time range) and Sun direction in the camera frame, from the ephemeris with the renderer's
   light time and aberration (:func:`opnav.image.centres.body_pose`, whose steps do not depend on
   the shape).
2. **Template** (:func:`render_mesh_model`): each pixel's mean I/F on its own rays
   (:func:`opnav.shape.mesh_pixel_means`: the renderer's integral of a mesh body, self-shadowing
   included) convolved with the pixel-integrated Gaussian PSF, over the box of the mesh's bounding
   sphere plus a PSF's reach.
3. **Fit** (:func:`correlate_mesh_centre`): :func:`opnav.image.correlate.correlate_centre` with that
   template (whole-pixel search, then the Gauss-Newton fit of shift, scale, gain and background with
   its covariance), in two passes: the second template is drawn at the first pass's centre and
   range, so the interpolated shift and scale are hundredths of a pixel.
4. **Far out** (:func:`point_centre`): below ``point_max_diameter_px`` the body is a point source;
   the centroid of its light is its photocentre, and the centre of figure is that plus the
   predicted offset (centre of figure minus photocentre of the mesh's view,
   :func:`opnav.bodies.view_body`), with ``phase_sigma_fraction`` of the offset as its 1-sigma error.
   The source is found by :func:`find_point_source`: among the local peaks within ``search_px`` of
   the predicted photocentre, the nearest one whose light is within a factor ``flux_factor`` of the
   predicted (a star of another brightness beside the body is not taken for it).

:func:`measure_mesh_centre` chooses between them by apparent size (:func:`opnav.image.centres.choose_method`
with ``ellipsoid=False``: never a limb fit) and returns the same records as
:func:`opnav.image.centres.measure_body_centre`, a point-like body's too (method ``"point"``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from ..bodies import Body, view_body
from ..camera import Camera
from ..errors import InputError, NoSolutionError
from ..observer import Corrections, Observer
from ..shape import Mesh, mesh_pixel_means, reflectance_weights
from .centres import BodyCentre, CentreOptions, body_pose, centre_records, choose_method
from .correlate import CorrelationCentre, CorrelationOptions, DetectorNoise, correlate_centre
from .ellipsoid import pixel_gaussian_kernel


@dataclass(frozen=True)
class MeshPose:
    """A mesh body's shape, orientation, position and lighting in the camera frame.

    Attributes
    ----------
    mesh : Mesh
    R_cam_body : (3, 3) array
        Body -> camera rotation (columns: the body axes in the camera frame).
    r_cam_km : (3,) array
        Camera -> body centre, camera frame, km.
    sun_cam : (3,) array
        Unit vector body -> Sun, camera frame.
    weights : (w_L, w_LS)
        Reflectance mix (:func:`opnav.shape.reflectance_weights`).
    """

    mesh: Mesh
    R_cam_body: np.ndarray
    r_cam_km: np.ndarray
    sun_cam: np.ndarray
    weights: tuple[float, float]

    def at(self, r_cam_km: np.ndarray) -> "MeshPose":
        """The same body moved to ``r_cam_km`` (camera frame, km)."""
        return replace(self, r_cam_km=np.asarray(r_cam_km, float))

    @property
    def range_km(self) -> float:
        return float(np.linalg.norm(self.r_cam_km))

    @property
    def phase_rad(self) -> float:
        """Sun-body-camera angle, rad."""
        return float(np.arccos(np.clip(-self.sun_cam @ self.r_cam_km / self.range_km, -1.0, 1.0)))

    def diameter_px(self, camera: Camera) -> float:
        """Apparent diameter of the bounding sphere, px (at the boresight's pixel scale)."""
        return 2.0 * math.asin(min(self.mesh.bounding_radius_km / self.range_km, 1.0)) * camera.focal_length_px


def mesh_pose(body: Body, R_icrf_cam: Rotation, observer: Observer, ephemeris, *, light_time: bool = True,
              aberration: bool = True) -> MeshPose:
    """Step 1 of the module notes for a ``body`` with a mesh ``shape`` (``R_icrf_cam``: camera -> ICRF)."""
    if body.shape is None:
        raise InputError(f"body {body.name!r} has no mesh shape: measure it with opnav.image.centres")
    # body_pose's light time, aberration, axes and Sun do not depend on the shading or the shape
    pose = body_pose(replace(body, shading="lambert"), R_icrf_cam, observer, ephemeris, light_time=light_time,
                     aberration=aberration)
    return MeshPose(body.shape, pose.R_cam_body, pose.r_cam_km, pose.sun_cam,
                    reflectance_weights(body.shading, body.lunar_lambert_l))


def mesh_box(camera: Camera, pose: MeshPose, margin_px: float) -> tuple[int, int, int, int]:
    """``(x0, y0, width, height)`` of the detector pixels within ``margin_px`` of the bounding sphere's
    outline (clipped to the detector); ``NoSolutionError`` when it is off the detector."""
    centre = camera.project(pose.r_cam_km)
    if not np.all(np.isfinite(centre)):
        raise NoSolutionError("the body is behind the camera")
    reach = 0.5 * pose.diameter_px(camera) * 1.05 + margin_px
    lo = np.maximum(np.floor(centre - reach).astype(int), 0)
    hi = np.minimum(np.ceil(centre + reach).astype(int), [camera.width_px - 1, camera.height_px - 1])
    if np.any(hi < lo):
        raise NoSolutionError("the body's outline is off the detector")
    return int(lo[0]), int(lo[1]), int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)


def render_mesh_model(camera: Camera, pose: MeshPose, box: tuple[int, int, int, int], *, psf_sigma_px: float,
                      supersample: int = 4) -> np.ndarray:
    """Noise-free model image of the lit mesh over ``box = (x0, y0, width, height)`` (px), in I/F per unit
    albedo (step 2 of the module notes: :func:`opnav.image.ellipsoid.render_ellipsoid` for a mesh)."""
    x0, y0, w, h = box
    if w <= 0 or h <= 0:
        raise InputError(f"render_mesh_model: empty box {box!r}")
    cx, cy = np.meshgrid(np.arange(x0, x0 + w + 1) - 0.5, np.arange(y0, y0 + h + 1) - 0.5)
    corners = camera.unproject(np.column_stack([cx.ravel(), cy.ravel()])).reshape(h + 1, w + 1, 3)
    rot = pose.R_cam_body  # a camera-frame row vector v is v @ rot in the body's axes
    image = mesh_pixel_means((corners / corners[..., 2:3]) @ rot, -pose.r_cam_km @ rot, pose.mesh, pose.sun_cam @ rot,
                             weights=pose.weights, supersample=supersample, size_px=pose.diameter_px(camera))
    kernel = pixel_gaussian_kernel(psf_sigma_px)
    image = ndimage.convolve1d(image, kernel, axis=0, mode="constant")
    return ndimage.convolve1d(image, kernel, axis=1, mode="constant")


@dataclass(frozen=True)
class MeshTemplates:
    """Model images of a mesh body for :func:`opnav.image.correlate.correlate_centre` (its
    ``Templates``): :func:`render_mesh_model` over :func:`mesh_box` with a PSF's reach."""

    psf_sigma_px: float
    supersample: int = 4

    def box(self, camera: Camera, pose: MeshPose) -> tuple[int, int, int, int]:
        return mesh_box(camera, pose, 4.0 * self.psf_sigma_px + 3.0)

    def render(self, camera: Camera, pose: MeshPose, box: tuple[int, int, int, int]) -> np.ndarray:
        return render_mesh_model(camera, pose, box, psf_sigma_px=self.psf_sigma_px, supersample=self.supersample)


def correlate_mesh_centre(image: np.ndarray, camera: Camera, pose: MeshPose, *, psf_sigma_px: float,
                          noise: DetectorNoise, options: CorrelationOptions = CorrelationOptions(),
                          supersample: int = 4) -> CorrelationCentre:
    """Centre of figure of the mesh body in ``image`` (ADU) by cross-correlation with its template (steps 2-3
    of the module notes), in ``options.passes`` passes, with the covariance of the noise and of the
    template's own pixel-phase error (:func:`opnav.image.correlate.template_error_cov`); ``supersample``
    rays per pixel per axis of the template where its pixels' rays agree: the renderer's default, 4,
    because a shape model's facets are about a pixel across on a resolved body and a coarser template
    aliases them differently from the frame (the shipped 5,120-facet body 27 px across, mean of 12 noisy
    frames at peak 2e4 e-: 2 rays biased them 0.007-0.027 px over 0.3-1.5 rad of phase, 4 rays
    0.001-0.006 px). Raises ``NoSolutionError`` when the fit fails or the box leaves the frame."""
    return correlate_centre(image, camera, pose, psf_sigma_px=psf_sigma_px, noise=noise, options=options,
                            templates=MeshTemplates(psf_sigma_px, supersample))


@dataclass(frozen=True)
class PointCentre:
    """A far body's centre of figure from its photocentre: ``xy_px`` (2,) with ``cov_xy_px2`` (2, 2);
    ``offset_px`` (2,) the predicted centre of figure minus photocentre that was added."""

    xy_px: np.ndarray
    cov_xy_px2: np.ndarray
    offset_px: np.ndarray


def point_centre(photocentre_xy_px: np.ndarray, cov_xy_px2: np.ndarray, camera: Camera, body: Body, *,
                 R_icrf_cam: Rotation, observer: Observer, ephemeris, corrections: Corrections = Corrections(),
                 phase_sigma_fraction: float = 0.1) -> PointCentre:
    """Step 4 of the module notes: the measured photocentre (px, with its covariance px^2) moved by the
    mesh view's predicted centre-of-figure offset, whose ``phase_sigma_fraction`` (1 sigma, each axis)
    is added to the covariance (the model's error: albedo marks, the pole)."""
    if not (math.isfinite(phase_sigma_fraction) and phase_sigma_fraction >= 0.0):
        raise InputError(f"phase_sigma_fraction must be >= 0, got {phase_sigma_fraction!r}")
    view = view_body(body, camera, R_icrf_cam, observer, ephemeris, corrections=corrections, keep_rays=False)
    offset = np.asarray(view.xy_cof_px, float) - np.asarray(view.xy_photocentre_px, float)
    if not np.all(np.isfinite(offset)):
        raise NoSolutionError(f"{body.name}: no light predicted (unlit or behind the camera)")
    cov = np.asarray(cov_xy_px2, float) + np.eye(2) * (phase_sigma_fraction * float(np.hypot(*offset))) ** 2
    return PointCentre(np.asarray(photocentre_xy_px, float) + offset, cov, offset)


def find_point_source(image: np.ndarray, camera: Camera, predicted_xy_px: np.ndarray, predicted_e: float, *,
                      noise: DetectorNoise, psf_sigma_px: float, search_px: float = 8.0,
                      flux_factor: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Step 4's search: the centroid (x, y) px and its covariance (2, 2) px^2 of the point source nearest
    ``predicted_xy_px`` within ``search_px`` whose flux (electrons) is within ``flux_factor`` of
    ``predicted_e``; ``NoSolutionError`` when there is none (the body too faint, off its prediction,
    or only other sources there)."""
    from .centroid import centroid

    image = np.asarray(image, float)
    rows, cols = image.shape
    half = int(math.ceil(search_px)) + int(math.ceil(3.0 * psf_sigma_px)) + 1
    cx, cy = (int(round(v)) for v in predicted_xy_px)
    x0, y0, x1, y1 = max(cx - half, 0), max(cy - half, 0), min(cx + half + 1, cols), min(cy + half + 1, rows)
    if x1 - x0 < 5 or y1 - y0 < 5:
        raise NoSolutionError("the body's predicted position is off the frame")
    box = (image[y0:y1, x0:x1] - noise.bias_adu) * noise.gain_e_per_adu
    background = float(np.median(box))
    # peaks of the pixels themselves (smoothing first merges a body into a brighter neighbour's shoulder)
    sigma_e = math.sqrt(noise.read_noise_e**2 + max(background, 0.0))
    peaks = (box == ndimage.maximum_filter(box, size=3)) & (box - background > 5.0 * sigma_e)
    ys, xs = np.nonzero(peaks)
    xy = np.column_stack([xs + x0, ys + y0]).astype(float)
    near = np.hypot(*(xy - predicted_xy_px).T) <= search_px
    if not near.any():
        raise NoSolutionError("no point source within the search radius of the body's prediction")
    xy = xy[near]
    got = centroid(image, xy, psf_sigma_px=None, read_noise_e=noise.read_noise_e, gain_e_per_adu=noise.gain_e_per_adu,
                   bias_adu=noise.bias_adu, window=2 * int(math.ceil(3.0 * psf_sigma_px)) + 1)
    flux_e = got.flux * noise.gain_e_per_adu
    fits = got.ok & (flux_e > predicted_e / flux_factor) & (flux_e < predicted_e * flux_factor)
    if not fits.any():
        raise NoSolutionError(f"no point source of the body's predicted {predicted_e:.3g} e- (within x{flux_factor:g}) "
                              "near its prediction")
    pick = np.flatnonzero(fits)[np.argmin(np.hypot(*(got.xy[fits] - predicted_xy_px).T))]
    return got.xy[pick], got.cov[pick]


def measure_mesh_centre(image: np.ndarray, camera: Camera, body: Body, *, R_icrf_cam: Rotation,
                        cov_att_rad2: np.ndarray, observer: Observer, ephemeris, psf_sigma_px: float,
                        noise: DetectorNoise, t_tdb_s: float, sensor: str = "camera", frame_id: str = "frame",
                        options: CentreOptions = CentreOptions(), prior_R_icrf_cam: Rotation | None = None,
                        light_time: bool = True, aberration: bool = True) -> BodyCentre:
    """:func:`opnav.image.centres.measure_body_centre` for a mesh body: the pose from ``observer`` and
    ``ephemeris`` (with ``prior_R_icrf_cam`` or else ``R_icrf_cam``), cross-correlation with the mesh's
    template when it is resolved, and the ``radec`` record of its centre with the frame's attitude
    covariance; a point-like body by its centroid moved by the mesh's photocentre offset (step 4).
    Raises ``NoSolutionError`` when the fit fails or no source of the body's brightness lies near
    its prediction."""
    pose = mesh_pose(body, prior_R_icrf_cam or R_icrf_cam, observer, ephemeris, light_time=light_time,
                     aberration=aberration)
    diameter = pose.diameter_px(camera)
    method = choose_method(diameter, pose.phase_rad, ellipsoid=False, options=options)
    if method == "limb":
        raise InputError(f"{body.name}: a mesh body has no limb fit; its centre method is auto, point or correlation")
    if method == "point":
        corrections = Corrections(light_time=light_time, aberration=aberration)
        view = view_body(body, camera, prior_R_icrf_cam or R_icrf_cam, observer, ephemeris, corrections=corrections,
                         keep_rays=False)
        xy, cov = find_point_source(image, camera, view.xy_photocentre_px, view.electrons_s * camera.exposure_s,
                                    noise=noise, psf_sigma_px=psf_sigma_px)
        fit = point_centre(xy, cov, camera, body, R_icrf_cam=prior_R_icrf_cam or R_icrf_cam, observer=observer,
                           ephemeris=ephemeris, corrections=corrections)
    else:
        fit = correlate_mesh_centre(image, camera, pose, psf_sigma_px=psf_sigma_px, noise=noise)
    records = centre_records(t_tdb_s=t_tdb_s, target=body.name, sensor=sensor, frame_id=frame_id, camera=camera,
                             R_icrf_cam=R_icrf_cam, cov_att_rad2=cov_att_rad2, xy_px=fit.xy_px,
                             cov_xy_px2=fit.cov_xy_px2, method=method)
    return BodyCentre(records=tuple(records), method=method, fit=fit)
