"""Centre finding for resolved bodies: which method, the predicted pose, and the records.

A body's centre is found by one of three methods, chosen by :func:`choose_method` from its
predicted apparent size and shape, never by its name:

- ``"point"``: a near-point source (apparent diameter below ``point_max_diameter_px``): today's
  photocentre-corrected centroid (:func:`opnav.image.targets.moon_direction`);
- ``"correlation"``: cross-correlation with a model image (:mod:`opnav.image.correlate`): small
  bodies, a body whose shape is not an ellipsoid, or a lit limb too short for a limb fit (fewer
  than ``min_limb_lines`` scan lines on it: a thin crescent of a small body);
- ``"limb"``: the lit-limb ellipsoid fit (:mod:`opnav.image.limb`), which also gives the range.

:func:`body_pose` predicts the pose (shape, orientation, position and Sun direction in the camera
frame) from the ephemeris with the renderer's own light time and aberration; :func:`centre_records`
turns a result into records: the centre's ``radec`` (the same kind, model and Jacobian as a moon's)
and, from a limb fit, a ``target_vector`` (the probe -> body vector, ICRF, km: the line of sight
times the range the apparent size gives) with its 3x3 covariance; both include the attitude error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..bodies import Body, body_axes_icrf
from ..camera import Camera
from ..errors import InputError
from ..frames import unit, unit_to_radec
from ..light import aberrate, light_time_vector
from ..observer import Observer
from ..records import Measurement
from .ellipsoid import EllipsoidPose

METHODS = ("auto", "point", "correlation", "limb")


@dataclass(frozen=True)
class CentreOptions:
    """How :func:`choose_method` picks a method.

    ``method``: ``"auto"`` (by size and shape) or one of ``"point"``, ``"correlation"``, ``"limb"``
    forced; ``point_max_diameter_px``: largest apparent diameter measured as a point source;
    ``limb_min_diameter_px``: smallest diameter fitted by its limb; ``min_limb_lines``: fewest scan
    lines (``line_spacing_px`` apart) the lit limb must span for a limb fit; ``glare_margin_px``:
    two bodies whose predicted outlines come closer than this (px) are not measured, nor are
    overlapping ones (:mod:`opnav.image.occultation`).
    """

    method: str = "auto"
    point_max_diameter_px: float = 3.0
    limb_min_diameter_px: float = 20.0
    min_limb_lines: int = 8
    line_spacing_px: float = 3.0
    glare_margin_px: float = 10.0

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"centre method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if not 0.0 < self.point_max_diameter_px < self.limb_min_diameter_px:
            raise InputError("CentreOptions: need 0 < point_max_diameter_px < limb_min_diameter_px, got "
                             f"{self.point_max_diameter_px!r} and {self.limb_min_diameter_px!r}")
        if self.min_limb_lines < 4 or not self.line_spacing_px > 0:
            raise InputError("CentreOptions: min_limb_lines >= 4 and line_spacing_px > 0 are required")
        if not (math.isfinite(self.glare_margin_px) and self.glare_margin_px >= 0.0):
            raise InputError(f"CentreOptions.glare_margin_px must be >= 0 px, got {self.glare_margin_px!r}")


def choose_method(diameter_px: float, phase_rad: float, *, ellipsoid: bool = True,
                  options: CentreOptions = CentreOptions()) -> str:
    """``"point"``, ``"correlation"`` or ``"limb"`` for a body of apparent diameter ``diameter_px``
    (px) at phase angle ``phase_rad`` (module docstring); ``ellipsoid`` False for a shape model the
    ellipsoid fit cannot describe.

    The lit limb spans the outline's full width across the illumination direction at any phase
    below 180 deg (it is the half outline facing the Sun), so the lines on it number about
    ``diameter / spacing``; the cusps' ends are dark, the more so the higher the phase, hence
    the factor ``cos(phase / 2)`` of the lines kept.
    """
    if not (math.isfinite(diameter_px) and diameter_px > 0):
        raise InputError(f"apparent diameter must be positive, got {diameter_px!r}")
    if options.method != "auto":
        return options.method
    if diameter_px < options.point_max_diameter_px:
        return "point"
    lines = diameter_px / options.line_spacing_px * math.cos(0.5 * min(max(phase_rad, 0.0), math.pi))
    if not ellipsoid or diameter_px < options.limb_min_diameter_px or lines < options.min_limb_lines:
        return "correlation"
    return "limb"


def body_pose(body: Body, R_icrf_cam: Rotation, observer: Observer, ephemeris, *,
              light_time: bool = True, aberration: bool = True) -> EllipsoidPose:
    """The pose of ``body`` as ``observer`` sees it (:class:`~opnav.image.ellipsoid.EllipsoidPose`):
    position = apparent direction (light time, aberration: :func:`opnav.bodies.view_body`'s
    steps) times the light-time range, orientation and Sun direction at the emission epoch; all
    rotated into the camera frame by ``R_icrf_cam`` (camera -> ICRF)."""
    if body.shading not in ("lambert", "lommel-seeliger"):
        raise InputError(f"body {body.name!r}: centre finding needs a sunlit body, not shading {body.shading!r}")
    t = observer.t_tdb_s

    def target_ssb(epoch):
        return ephemeris.position(body.name, epoch)

    if light_time:
        r_rel, tau = light_time_vector(target_ssb, t, observer.r_ssb_km)
    else:
        r_rel, tau = np.asarray(target_ssb(t), float).reshape(3) - observer.r_ssb_km, 0.0
    t_emit = t - float(tau)
    direction = unit(r_rel)
    if aberration:
        direction = aberrate(direction, observer.v_ssb_km_s)
    R_cam_icrf = R_icrf_cam.inv().as_matrix()
    sun = np.asarray(ephemeris.position("sun", t_emit), float) - np.asarray(ephemeris.position(body.name, t_emit), float)
    return EllipsoidPose(radii_km=np.asarray(body.radii_km), R_cam_body=R_cam_icrf @ body_axes_icrf(body, t_emit, ephemeris),
                         r_cam_km=R_cam_icrf @ (direction * float(np.linalg.norm(r_rel))), sun_cam=R_cam_icrf @ unit(sun),
                         shading=body.shading)


def apparent_diameter_px(camera: Camera, pose: EllipsoidPose) -> float:
    """Apparent diameter of the body's largest axis, px (at the boresight's pixel scale)."""
    return 2.0 * math.asin(min(float(np.max(pose.radii_km)) / float(np.linalg.norm(pose.r_cam_km)), 1.0)) \
        * camera.focal_length_px


def _cross(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def centre_records(*, t_tdb_s: float, target: str, sensor: str, frame_id: str, camera: Camera,
                   R_icrf_cam: Rotation, cov_att_rad2: np.ndarray, xy_px: np.ndarray | None = None,
                   cov_xy_px2: np.ndarray | None = None, r_cam_km: np.ndarray | None = None,
                   cov_cam_km2: np.ndarray | None = None, method: str = "", flags: int = 0) -> list[Measurement]:
    """Records of a body's centre (module docstring).

    Either ``xy_px`` (2,) with ``cov_xy_px2`` (a correlation centre: one ``radec`` record) or
    ``r_cam_km`` (3,) with ``cov_cam_km2`` (a limb fit, camera frame, km: a ``radec`` and a
    ``target_vector`` record). ``R_icrf_cam`` (camera -> ICRF) with ``cov_att_rad2`` (3, 3: small
    camera-frame rotation, rad^2) is the frame's attitude; its error is added to both (the two
    records share it: keep them from the same frame together or take one).
    """
    rot = R_icrf_cam.as_matrix()
    cov_att = np.asarray(cov_att_rad2, float)
    if r_cam_km is not None:
        r_cam = np.asarray(r_cam_km, float)
        cov_cam = np.asarray(cov_cam_km2, float)
    elif xy_px is not None:
        r_cam = camera.unproject(np.asarray(xy_px, float))
        # d(unit direction)/d(pixel) by central differences of the camera's own unprojection
        step = 1e-3
        jac = np.stack([(camera.unproject(xy_px + d) - camera.unproject(xy_px - d)) / (2 * step)
                        for d in (np.array([step, 0.0]), np.array([0.0, step]))], 1)
        cov_cam = jac @ np.asarray(cov_xy_px2, float) @ jac.T
    else:
        raise InputError("centre_records needs xy_px or r_cam_km")
    r_icrf = rot @ r_cam
    # a small camera rotation e moves the ICRF vector by R [r]x e (its sign convention aside: the covariance is the same)
    j_att = rot @ _cross(r_cam)
    cov_icrf = rot @ cov_cam @ rot.T + j_att @ cov_att @ j_att.T
    u = r_icrf / np.linalg.norm(r_icrf)
    ra, dec = unit_to_radec(u)
    x, y, z = u
    rxy2 = x * x + y * y
    j_radec = np.array([[-y / rxy2, x / rxy2, 0.0],
                        [-x * z / math.sqrt(rxy2), -y * z / math.sqrt(rxy2), math.sqrt(rxy2)]]) / np.linalg.norm(r_icrf)
    cov_radec = j_radec @ cov_icrf @ j_radec.T
    extra = {"method": method} if method else {}
    common = dict(t_tdb_s=t_tdb_s, target=target, sensor=sensor, frame_id=frame_id, flags=flags, extra=extra)
    records = [Measurement(kind="radec", value=[float(ra), float(dec)], covariance=0.5 * (cov_radec + cov_radec.T),
                           **common)]
    if r_cam_km is not None:
        records.append(Measurement(kind="target_vector", value=r_icrf, covariance=0.5 * (cov_icrf + cov_icrf.T),
                                   **common))
    return records


@dataclass(frozen=True)
class BodyCentre:
    """What :func:`measure_body_centre` gave: the ``records``, the ``method`` used and its ``fit``
    (:class:`~opnav.image.limb.LimbCentre` or :class:`~opnav.image.correlate.CorrelationCentre`)."""

    records: tuple
    method: str
    fit: object


def measure_body_centre(image: np.ndarray, camera: Camera, body: Body, *, R_icrf_cam: Rotation,
                        cov_att_rad2: np.ndarray, observer: Observer, ephemeris, psf_sigma_px: float,
                        noise, t_tdb_s: float, sensor: str = "camera", frame_id: str = "frame",
                        options: CentreOptions = CentreOptions(), prior_R_icrf_cam: Rotation | None = None,
                        light_time: bool = True, aberration: bool = True) -> BodyCentre:
    """A resolved body's centre records from one frame: the pose predicted from ``observer`` and
    ``ephemeris`` (:func:`body_pose`, with ``prior_R_icrf_cam`` or else ``R_icrf_cam``), the method
    chosen by size and phase (:func:`choose_method`), the fit, and :func:`centre_records` with the
    frame's attitude ``R_icrf_cam`` and its covariance. ``noise``: the detector's
    :class:`~opnav.image.correlate.DetectorNoise`.

    A limb fit that fails (too few usable lines) falls back to cross-correlation unless
    ``options.method`` forced the limb. Raises ``NoSolutionError`` when the fit fails or the body
    is point-like (``"point"``: measured by the point-source path,
    :func:`opnav.image.targets.moon_direction`).
    """
    from ..errors import NoSolutionError
    from .correlate import correlate_centre
    from .limb import fit_limb_ellipsoid

    pose = body_pose(body, prior_R_icrf_cam or R_icrf_cam, observer, ephemeris, light_time=light_time,
                     aberration=aberration)
    method = choose_method(apparent_diameter_px(camera, pose), pose.phase_rad, options=options)
    common = dict(t_tdb_s=t_tdb_s, target=body.name, sensor=sensor, frame_id=frame_id, camera=camera,
                  R_icrf_cam=R_icrf_cam, cov_att_rad2=cov_att_rad2, method=method)
    if method == "limb":
        try:
            fit = fit_limb_ellipsoid(image, camera, pose, psf_sigma_px=psf_sigma_px, noise=noise)
            return BodyCentre(records=tuple(centre_records(r_cam_km=fit.r_cam_km, cov_cam_km2=fit.cov_cam_km2,
                                                           **common)), method=method, fit=fit)
        except NoSolutionError:
            if options.method == "limb":
                raise
            # too few usable lines (a crescent, a limb across the frame's edge): the whole model
            method = common["method"] = "correlation"
    if method == "correlation":
        fit = correlate_centre(image, camera, pose, psf_sigma_px=psf_sigma_px, noise=noise)
        records = centre_records(xy_px=fit.xy_px, cov_xy_px2=fit.cov_xy_px2, **common)
    else:
        raise NoSolutionError(f"{body.name} is point-like ({apparent_diameter_px(camera, pose):.1f} px): "
                              "measure it as a point source")
    return BodyCentre(records=tuple(records), method=method, fit=fit)
