"""A calibrated camera's uncertainty carried into the targets' RA/Dec records (issue 39, an option).

A target's RA/Dec is its direction in the attitude its frame's stars give, and both pass through the
camera model: an error of the camera's parameters (focal length, principal point, distortion) moves
the target relative to the stars. The centroid covariances of the records leave that out. With the
option on (``[measurement] camera_covariance`` of a scene, S1's ``camera_covariance`` setting,
``opnav process --camera-covariance``), :func:`with_camera_covariance` adds it to each ``radec``
record of a frame:

1. ``J_t``: the derivative of the target's direction, relative to the attitude of the frame's stars
   (Wahba, equal weights), by the camera's parameters, on the tangent plane at the target in the
   camera frame (:func:`opnav.image.calibration.target_direction_jacobian`);
2. ``M``: that tangent plane rotated to ICRF with the frame's attitude and projected on the RA/Dec
   directions at the record (``dRA = east . du / cos(Dec)``, ``dDec = north . du``);
3. the record's covariance gains ``(M J_t) C (M J_t)^T``, ``C`` the camera file's parameter
   covariance; ``L = M J_t C^(1/2)`` (the term is ``L L^T``) is kept in ``extra``
   (:data:`opnav.records.CAMERA_WHITE_FACTOR`): two moons of one frame joined into a pair share the
   camera's one error, cross-covariance ``L_1 L_2^T``.

The term is the same in every frame of a similar star field: over an arc it is a bias of the camera,
not white noise, so a filter that takes it as white noise is still optimistic over many frames; per
record the chi-square against the truth is honest (tests/image/test_camera_noise.py). With
``camera_error = "consider"`` the record keeps ``M J_t`` instead (:data:`opnav.records.CAMERA_JACOBIAN`,
with the parameters' names, :data:`opnav.records.CAMERA_PARAMETERS`) and its covariance as it was: a
filter then holds the camera's parameter errors as consider states, one error shared by every record
(:class:`opnav.measurements.CameraOffsetModel`, ``[navigation] camera_error``).

:func:`frame_with_camera_covariance` does it for a full-frame result (the sources at catalog stars'
places under its attitude as the stars, :func:`identified_stars`); the tracking stage (:class:`opnav.image.tracking.TrackingOptions`
``camera_covariance``) for the stars its attitude used.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera, CameraCovariance
from ..errors import InputError
from ..records import CAMERA_JACOBIAN, CAMERA_PARAMETERS, CAMERA_WHITE_FACTOR, Measurement
from .calibration import target_direction_jacobian

#: How a record carries the camera's error: ``white`` (added to its covariance) or ``consider`` (its
#: Jacobian kept for a filter's consider states).
CAMERA_ERROR = ("white", "consider")
#: A source this close to a catalog star's place under the solved attitude is that star, px.
MATCH_RADIUS_PX = 2.0


def radec_camera_jacobian(camera: Camera, names, star_xy: np.ndarray, target_xy: np.ndarray,
                          R_icrf_cam: Rotation, star_weights: np.ndarray | None = None) -> np.ndarray:
    """d(RA, Dec)/d(camera parameters) of a target measured against the frame's stars (module steps 1-2).

    Parameters
    ----------
    camera : Camera
        The camera the frame was measured with.
    names : sequence of str
        Its calibrated parameters (:data:`opnav.camera.CALIBRATION_PARAMETERS`).
    star_xy : ndarray, shape (N, 2)
        The stars the frame's attitude was fitted to, px (N >= 2).
    target_xy : ndarray, shape (2,)
        The target's pixel, px.
    R_icrf_cam : Rotation
        The frame's attitude, camera frame -> ICRF.
    star_weights : ndarray, shape (N,), optional
        The stars' weights in the attitude fit (inverse centroid variances); default equal.

    Returns
    -------
    ndarray, shape (2, P)
        rad (of RA and of Dec) per parameter unit (``f``, ``cx``, ``cy`` px; Brown dimensionless).
    """
    jac, x_axis, y_axis = target_direction_jacobian(camera, names, star_xy, target_xy, star_weights)
    u = R_icrf_cam.apply(camera.unproject(np.asarray(target_xy, dtype=float)))
    ra, dec = math.atan2(u[1], u[0]), math.asin(max(-1.0, min(1.0, u[2])))
    east = np.array([-math.sin(ra), math.cos(ra), 0.0])
    north = np.array([-math.sin(dec) * math.cos(ra), -math.sin(dec) * math.sin(ra), math.cos(dec)])
    plane = np.column_stack([R_icrf_cam.apply(x_axis), R_icrf_cam.apply(y_axis)])  # (3, 2), ICRF
    to_radec = np.vstack([east @ plane / math.cos(dec), north @ plane])
    return to_radec @ jac


def check_camera_error(camera_error: str) -> str:
    """``camera_error`` if it is one of :data:`CAMERA_ERROR`, else :class:`InputError` naming them."""
    if camera_error not in CAMERA_ERROR:
        raise InputError(f"camera_error must be one of {', '.join(CAMERA_ERROR)}, got {camera_error!r}")
    return camera_error


def with_camera_covariance(records, *, camera: Camera, calibration: CameraCovariance, star_xy: np.ndarray,
                           R_icrf_cam: Rotation, star_weights: np.ndarray | None = None,
                           xy_offset_px=(0.0, 0.0), camera_error: str = "white") -> list[Measurement]:
    """The frame's records with the camera's covariance added to each ``radec`` record, or with its Jacobian
    kept (module docstring).

    Parameters
    ----------
    records : sequence of Measurement
        One frame's records; a ``radec`` record needs ``extra["xy_px"]`` (the image stage writes it),
        the others are passed on unchanged.
    camera : Camera
        The camera the frame was measured with (the camera file's).
    calibration : CameraCovariance
        The camera file's ``[calibration]``: parameter names and covariance.
    star_xy : ndarray, shape (N, 2)
        The stars the frame's attitude was fitted to, px. Fewer than 2: records unchanged (no
        attitude from stars, nothing relative to them).
    R_icrf_cam : Rotation
        The frame's attitude, camera frame -> ICRF.
    star_weights : ndarray, shape (N,), optional
        Their weights in the attitude fit (inverse centroid variances, as the image stage's); default equal.
    xy_offset_px : (float, float)
        Added to each record's ``xy_px`` to make it a pixel of ``camera`` (the records of a crop, whose
        origin is this pixel of the frame), px.
    camera_error : str
        ``white``: ``J C J^T`` added to the record's covariance (``L = J C^(1/2)`` kept in ``extra`` under
        :data:`opnav.records.CAMERA_WHITE_FACTOR`); ``consider``: the covariance unchanged, ``J`` (2, P), rad per
        parameter unit, and the parameters' names kept in ``extra``
        (:data:`opnav.records.CAMERA_JACOBIAN`, :data:`opnav.records.CAMERA_PARAMETERS`).

    Returns
    -------
    list of Measurement
    """
    consider = check_camera_error(camera_error) == "consider"
    star_xy = np.asarray(star_xy, dtype=float).reshape(-1, 2)
    if len(star_xy) < 2:
        return list(records)
    # white: L = J C^(1/2) kept beside J C J^T = L L^T, so that two moons of the frame, joined into a pair,
    # share the camera's one error (opnav.records.join_frame_radec)
    root = None if consider else _covariance_root(np.asarray(calibration.covariance, float))
    out = []
    for record in records:
        if record.kind != "radec" or "xy_px" not in record.extra:
            out.append(record)
            continue
        target_xy = np.asarray(record.extra["xy_px"], float) + np.asarray(xy_offset_px, float)
        jac = radec_camera_jacobian(camera, calibration.names, star_xy, target_xy, R_icrf_cam, star_weights)
        if consider:
            out.append(replace(record, extra={**record.extra, CAMERA_JACOBIAN: jac.tolist(),
                                              CAMERA_PARAMETERS: tuple(calibration.names)}))
            continue
        factor = jac @ root
        added = factor @ factor.T
        out.append(replace(record, covariance=np.asarray(record.covariance) + added,
                           extra={**record.extra, CAMERA_WHITE_FACTOR: factor.tolist()}))
    return out


def _covariance_root(covariance: np.ndarray) -> np.ndarray:
    """The symmetric square root of a covariance (P, P) (eigenvalues below zero, from rounding, taken as 0)."""
    values, vectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
    return (vectors * np.sqrt(np.clip(values, 0.0, None))) @ vectors.T


def star_weights(cov_px2: np.ndarray) -> np.ndarray:
    """Attitude-fit weights of stars with centroid covariances ``cov_px2`` (N, 2, 2): the inverse mean
    variance per axis, as the image stage's Wahba fit weighs them."""
    return 1.0 / np.asarray(cov_px2, dtype=float)[:, [0, 1], [0, 1]].mean(axis=1)


def identified_stars(result, camera: Camera, catalog, observer=None, *, vmag_limit: float | None = None,
                     radius_px: float = MATCH_RADIUS_PX) -> np.ndarray:
    """Which sources of a full-frame result are catalog stars where its attitude puts them (bool, one a source).

    The full-frame stage's result does not say which sources its attitude used; they are found again:
    the catalog stars (to ``vmag_limit``, at their apparent directions for ``observer`` when given)
    projected with the result's attitude and ``camera``, and each converged source within
    ``radius_px`` of one (the nearest, one source a star).
    """
    from scipy.spatial import cKDTree

    sources = result.sources
    ok = np.asarray(sources.ok, bool) & np.all(np.isfinite(sources.xy), axis=1)
    R = result.R_icrf_cam
    rows = np.asarray(catalog.cone(R.apply([0.0, 0.0, 1.0]), camera.half_diagonal_fov_rad * 1.05,
                                   vmag_limit=vmag_limit))
    if not rows.size or not ok.any():
        return np.zeros(len(ok), bool)
    if observer is not None:
        directions = catalog.apparent_directions(rows, t_tdb_s=observer.t_tdb_s, r_observer_ssb_km=observer.r_ssb_km,
                                                 v_observer_ssb_km_s=observer.v_ssb_km_s)
    else:
        directions = np.asarray(catalog.unit_vectors(), float)[rows]
    in_front = R.inv().apply(directions)[:, 2] > 0.0
    predicted = camera.project(R.inv().apply(directions[in_front]))
    distance, nearest = cKDTree(predicted).query(np.where(ok[:, None], sources.xy, 0.0))
    near = ok & (distance <= radius_px)
    # one source a star: of two sources near the same star, the nearer
    order = np.argsort(distance)
    taken, out = set(), np.zeros(len(ok), bool)
    for k in order[near[order]]:
        if nearest[k] not in taken:
            taken.add(nearest[k])
            out[k] = True
    return out


def frame_with_camera_covariance(result, camera: Camera, calibration: CameraCovariance, *, catalog, observer=None,
                                 vmag_limit: float | None = None, camera_error: str = "white"):
    """A full-frame stage's result (:class:`opnav.image.pipeline.FrameResult`) with the camera's covariance
    added to its ``radec`` records (or their Jacobians kept, ``camera_error = "consider"``,
    :func:`with_camera_covariance`), the stars those :func:`identified_stars` finds, weighted by their
    centroid covariances. A result without a star-identified attitude (flag ``attitude_prior``) is
    returned as it is."""
    if "attitude_prior" in result.flags:
        return result
    stars = identified_stars(result, camera, catalog, observer, vmag_limit=vmag_limit)
    records = with_camera_covariance(result.records, camera=camera, calibration=calibration,
                                     star_xy=result.sources.xy[stars], R_icrf_cam=result.R_icrf_cam,
                                     star_weights=star_weights(result.sources.cov[stars]), camera_error=camera_error)
    return replace(result, records=tuple(records))
