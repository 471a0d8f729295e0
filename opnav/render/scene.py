"""What is in view: the observer, the stars in the field and the Sun keep-out test.

Steps for the stars of one frame:

1. Cone search of the catalog around the boresight with the radius of the
   detector's half-diagonal plus 10 % (distortion) plus the PSF stamp.
2. Apparent directions from the catalog itself (proper motion to the epoch,
   parallax from the observer's SSB position, aberration from its SSB
   velocity), each switchable through :class:`Corrections`.
3. ICRF -> camera frame with the attitude, projection with the camera model,
   and a cut to sources whose stamps touch the detector.

The Sun is never drawn: a frame whose boresight is within ``sun_keepout_rad``
of the Sun's apparent direction is flagged (or rejected, by option).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..light import apparent_direction
from ..observer import Corrections, Observer


class StarSource(Protocol):
    """The part of :class:`opnav.catalog.StarCatalog` the renderer uses."""

    vmag: np.ndarray
    star_id: np.ndarray

    def cone(self, center_icrf: np.ndarray, radius_rad: float, *, vmag_limit: float | None = None) -> np.ndarray:
        """Indices of stars within ``radius_rad`` of ``center_icrf``."""
        ...

    def apparent_directions(
        self,
        index: np.ndarray,
        *,
        t_tdb_s: float,
        r_observer_ssb_km: np.ndarray,
        v_observer_ssb_km_s: np.ndarray,
        proper_motion: bool = True,
        parallax: bool = True,
        aberration: bool = True,
    ) -> np.ndarray:
        """(M, 3) apparent unit vectors, ICRF."""
        ...


@dataclass(frozen=True)
class StarsInView:
    """Stars whose stamps touch the detector.

    ``direction_icrf`` (N, 3) apparent unit vectors; ``xy_px`` (N, 2) pixel positions
    at mid-exposure; ``vmag`` (N,); ``star_id`` (N,) int.
    """

    star_id: np.ndarray
    vmag: np.ndarray
    direction_icrf: np.ndarray
    xy_px: np.ndarray


def boresight_icrf(R_icrf_cam: Rotation) -> np.ndarray:
    """Camera +z axis in ICRF (unit vector)."""
    return R_icrf_cam.apply([0.0, 0.0, 1.0])


def stars_in_view(
    catalog: StarSource,
    camera: Camera,
    R_icrf_cam: Rotation,
    observer: Observer,
    *,
    corrections: Corrections = Corrections(),
    vmag_limit: float | None = None,
    margin_px: float = 0.0,
) -> StarsInView:
    """Select and project the catalog stars seen by ``camera``.

    Parameters
    ----------
    catalog : StarSource
    camera : Camera
    R_icrf_cam : Rotation
        Attitude, camera frame -> ICRF.
    observer : Observer
    corrections : Corrections
    vmag_limit : float, optional
        Faintest magnitude rendered.
    margin_px : float
        Keep stars up to this far outside the detector (their stamps reach in).
    """
    centre = boresight_icrf(R_icrf_cam)
    radius = 1.1 * camera.half_diagonal_fov_rad + margin_px * camera.pixel_scale_rad
    index = np.asarray(catalog.cone(centre, min(radius, math.pi), vmag_limit=vmag_limit), dtype=int)
    empty = StarsInView(np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 2)))
    if index.size == 0:
        return empty
    directions = np.asarray(
        catalog.apparent_directions(
            index,
            t_tdb_s=observer.t_tdb_s,
            r_observer_ssb_km=observer.r_ssb_km,
            v_observer_ssb_km_s=observer.v_ssb_km_s,
            proper_motion=corrections.proper_motion,
            parallax=corrections.parallax,
            aberration=corrections.aberration,
        ),
        dtype=float,
    ).reshape(-1, 3)
    xy = camera.project(R_icrf_cam.inv().apply(directions))
    keep = camera.in_frame(xy, margin_px=-margin_px)
    return StarsInView(
        star_id=np.asarray(catalog.star_id)[index][keep].astype(np.int64),
        vmag=np.asarray(catalog.vmag, dtype=float)[index][keep],
        direction_icrf=directions[keep],
        xy_px=xy[keep],
    )


def smear_path_px(
    direction_icrf: np.ndarray,
    camera: Camera,
    R_icrf_cam: Rotation,
    omega_cam_rad_s: np.ndarray,
    *,
    n_steps: int = 9,
    max_step_px: float = 0.1,
) -> np.ndarray:
    """Pixel positions (N, K, 2) of fixed ICRF directions across the exposure.

    The camera turns at the constant body rate ``omega_cam_rad_s`` (camera frame,
    rad/s) about its mid-exposure attitude ``R_icrf_cam``: ``R(s) = R_icrf_cam *
    exp(s omega)`` for s in [-T/2, T/2]. The path is sampled at the mid-points of
    K equal time slices, K >= ``n_steps`` and large enough that consecutive samples
    are at most ``max_step_px`` apart, so the mean of the samples is the
    time-average of the moving PSF.
    """
    direction_icrf = np.asarray(direction_icrf, dtype=float).reshape(-1, 3)
    omega = np.asarray(omega_cam_rad_s, dtype=float)

    in_camera = R_icrf_cam.inv().apply(direction_icrf)  # (N, 3) at mid-exposure

    def positions(steps_s: np.ndarray) -> np.ndarray:
        """(N, K, 2): the camera at ``R_icrf_cam * exp(s omega)`` sees ICRF d at exp(-s omega) R^-1 d."""
        turns = Rotation.from_rotvec(np.asarray(steps_s, float)[:, None] * omega).as_matrix()  # (K, 3, 3)
        seen = np.einsum("kji,nj->nki", turns, in_camera)
        return camera.project(seen.reshape(-1, 3)).reshape(len(in_camera), len(steps_s), 2)

    half = 0.5 * camera.exposure_s
    ends = positions(np.array([half, -half]))
    length = np.nanmax(np.linalg.norm(ends[:, 0] - ends[:, 1], axis=-1), initial=0.0)
    count = max(n_steps, int(math.ceil(length / max_step_px)))
    times = ((np.arange(count) + 0.5) / count - 0.5) * camera.exposure_s
    return positions(times)


def sun_direction(observer: Observer, ephemeris, corrections: Corrections) -> np.ndarray:
    """Apparent unit vector observer -> Sun, ICRF, through :func:`opnav.light.apparent_direction`."""
    return apparent_direction(
        lambda t: ephemeris.position("sun", t),
        observer.t_tdb_s,
        observer.r_ssb_km,
        observer.v_ssb_km_s,
        light_time=corrections.light_time,
        aberration=corrections.aberration,
    )
