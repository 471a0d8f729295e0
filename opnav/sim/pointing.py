"""Pointing laws: where a camera looks and how fast it turns (guidance, not rendering).

Camera +z = boresight; +x toward celestial east, +y toward celestial north at the boresight,
then turned by ``roll_rad`` about +z. Laws:

* ``target``: boresight on the apparent direction of ``target`` (light time and
  aberration through :func:`opnav.light.apparent_direction`);
* ``earth``: the same with the Earth's centre (Earth-pointing satellite);
* ``inertial``: fixed boresight ``ra_rad``, ``dec_rad``.

:func:`trajectory_to_ssb` moves a trajectory's states to the solar-system barycentre, the
origin every law and the renderer take.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ..frames import radec_to_unit
from ..light import apparent_direction
from ..observer import Corrections, Observer

POINTING_LAWS = ("target", "earth", "inertial")


@dataclass(frozen=True)
class PointingLaw:
    """How the camera is pointed (see module notes); angles rad."""

    law: str = "inertial"
    target: str | None = None
    ra_rad: float = 0.0
    dec_rad: float = 0.0
    roll_rad: float = 0.0

    def __post_init__(self) -> None:
        if self.law not in POINTING_LAWS:
            raise InputError(f"pointing law must be one of {', '.join(POINTING_LAWS)}, got {self.law!r}")
        if self.law == "target" and not self.target:
            raise InputError("pointing law 'target' needs a target name")
        for name in ("ra_rad", "dec_rad", "roll_rad"):
            if not math.isfinite(getattr(self, name)):
                raise InputError(f"pointing {name} must be finite")


def attitude_from_boresight(boresight_icrf: np.ndarray, roll_rad: float = 0.0) -> Rotation:
    """Camera -> ICRF rotation with +z on ``boresight_icrf``, +x east, +y north, then rolled about +z."""
    z = np.asarray(boresight_icrf, dtype=float)
    z = z / np.linalg.norm(z)
    ra = math.atan2(z[1], z[0])
    east = np.array([-math.sin(ra), math.cos(ra), 0.0])
    north = np.cross(z, east)
    base = Rotation.from_matrix(np.column_stack([east, north, z]))
    return base * Rotation.from_rotvec([0.0, 0.0, roll_rad])


def pointing_attitude(law: PointingLaw, observer: Observer, ephemeris, corrections: Corrections) -> Rotation:
    """Attitude (camera -> ICRF) of ``law`` at ``observer``'s epoch and state."""
    if law.law == "inertial":
        boresight = radec_to_unit(law.ra_rad, law.dec_rad)
    else:
        name = law.target if law.law == "target" else "earth"
        boresight = apparent_direction(
            lambda t: ephemeris.position(name, t), observer.t_tdb_s, observer.r_ssb_km, observer.v_ssb_km_s,
            light_time=corrections.light_time, aberration=corrections.aberration,
        )
    return attitude_from_boresight(boresight, law.roll_rad)


def body_rate(law: PointingLaw, observer: Observer, ephemeris, corrections: Corrections, *, dt_s: float = 1.0) -> np.ndarray:
    """Camera body rate (camera frame, rad/s) of ``law``, central difference over ``dt_s``."""
    if law.law == "inertial":
        return np.zeros(3)
    shifted = []
    for sign in (-0.5, 0.5):
        obs = Observer(observer.t_tdb_s + sign * dt_s, observer.r_ssb_km + sign * dt_s * observer.v_ssb_km_s, observer.v_ssb_km_s)
        shifted.append(pointing_attitude(law, obs, ephemeris, corrections))
    return (shifted[0].inv() * shifted[1]).as_rotvec() / dt_s


def trajectory_to_ssb(trajectory, ephemeris) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t (M,), r_ssb_km (M, 3), v_ssb_km_s (M, 3)) from an ``opnav.dynamics.Trajectory``."""
    states = np.asarray(trajectory.states, dtype=float)
    if states.ndim != 2 or states.shape[1] != 6:
        raise InputError(f"trajectory states must have shape (M, 6), got {states.shape}")
    t = np.asarray(trajectory.t_tdb_s, dtype=float)
    r_c, v_c = ephemeris.state(trajectory.center, t) if trajectory.center != "ssb" else (0.0, 0.0)
    return t, states[:, :3] + r_c, states[:, 3:] + v_c
