"""A sun sensor: the Sun's direction measured in a sensor fixed on the spacecraft body.

The model (:class:`SunSensor`, stated in a run file's settings and built by :func:`sun_sensor`):

1. **Truth.** The Sun's apparent direction from the observer (:func:`apparent_sun`): light time and
   stellar aberration as the renderer applies them to a solar-system body
   (:func:`opnav.light.apparent_direction`; each switchable, ``light_time`` / ``aberration``).
2. **Field.** The direction in the sensor frame through the true body attitude and the mounting
   (sensor -> body); a Sun more than ``half_angle_rad`` off the sensor's boresight (+z) gives no
   measurement, and the reading says why.
3. **Noise.** The measured direction is the true one moved in its tangent plane by the sensor's
   ``bias_rad`` plus Gaussian noise of ``sigma_rad`` per axis. The tangent axes are
   ``e1 = unit(y x u)`` and ``e2 = u x e1`` in the sensor frame (at the boresight, the sensor's +x
   and +y), so the bias is a fixed error of the sensor's two angles. Epoch ``k``'s draws come from
   ``numpy.random.default_rng([seed, *stream, k])``: the sensor's own stream, the same for any
   chunking of an arc.
4. **Record.** The measured direction is taken to ICRF with the *estimated* body attitude (the star
   tracker's or camera's solution; the truth when none is given), and becomes one ``los`` record
   (:mod:`opnav.records`; target ``sun``, apparent unit vector probe -> Sun, ICRF) whose
   covariance is the sensor's transverse noise ``sigma^2 (I - u u^T)`` plus the attitude
   solution's error mapped through ``-R_icrf_body [u_body]x`` (the attitude's covariance is of a
   small rotation in the body frame, rad^2), plus a radial variance of 1e-6 of the trace so the
   3 x 3 matrix is positive definite (a unit vector has no error along itself; the same
   convention as :func:`opnav.image.pipeline.limb_records`). The bias is not in the covariance:
   it is an error the filter does not know of.

Frames: ICRF for everything inertial; the body frame is whatever the caller's attitude
``R_icrf_body`` (body -> ICRF) says; the sensor frame has +z along the boresight. Units: km,
km/s, TDB seconds past J2000, radians; :func:`sun_sensor` takes the run file's degrees and
arcseconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..constants import ARCSEC_RAD, DEG_RAD
from ..errors import InputError
from ..light import aberrate, apparent_direction
from ..records import Measurement

#: Radial variance added to a ``los`` covariance, as a fraction of its trace (module notes, step 4).
RADIAL_VARIANCE_FRACTION = 1e-6


@dataclass(frozen=True, eq=False)
class SunSensor:
    """A sun sensor fixed on the body (module notes).

    Attributes
    ----------
    mounting : Rotation
        Sensor -> body rotation; the sensor's boresight is its +z axis.
    half_angle_rad : float
        Field of view half-angle about the boresight, rad, in (0, pi/2).
    sigma_rad : float
        Noise, 1-sigma per transverse axis, rad (> 0).
    bias_rad : (2,) tuple of float
        Fixed error along the tangent axes ``e1``, ``e2`` (module notes), rad.
    light_time, aberration : bool
        The truth's corrections (as the renderer's ``[corrections]``).
    stream : tuple of int
        The sensor's random stream: epoch ``k`` draws from ``default_rng([seed, *stream, k])``.
    name : str
        The records' ``sensor`` and the prefix of the reasons a reading is refused.
    """

    mounting: Rotation
    half_angle_rad: float
    sigma_rad: float
    bias_rad: tuple[float, float] = (0.0, 0.0)
    light_time: bool = True
    aberration: bool = True
    stream: tuple[int, ...] = (41,)
    name: str = "sun sensor"

    def __post_init__(self) -> None:
        if not isinstance(self.mounting, Rotation) or not self.mounting.single:
            raise InputError("sun sensor mounting must be one scipy Rotation (sensor -> body)")
        if not (np.isfinite(self.half_angle_rad) and 0.0 < self.half_angle_rad < np.pi / 2):
            raise InputError(f"sun sensor field half-angle must be in (0, 90) deg, got "
                             f"{self.half_angle_rad / DEG_RAD!r} deg")
        if not (np.isfinite(self.sigma_rad) and self.sigma_rad > 0.0):
            raise InputError(f"sun sensor noise must be a positive number of arcsec, got "
                             f"{self.sigma_rad / ARCSEC_RAD!r} arcsec")
        bias = tuple(float(b) for b in self.bias_rad)
        if len(bias) != 2 or not all(np.isfinite(bias)):
            raise InputError(f"sun sensor bias must be two finite angles (arcsec), got {self.bias_rad!r}")
        object.__setattr__(self, "bias_rad", bias)
        object.__setattr__(self, "stream", tuple(int(s) for s in self.stream))

    def rng(self, seed: int, k: int) -> np.random.Generator:
        """Epoch ``k``'s generator (module notes, step 3)."""
        return np.random.default_rng([seed, *self.stream, k])


def mounting_from_boresight(boresight_body) -> Rotation:
    """Sensor -> body rotation whose +z is ``boresight_body`` (3,), body frame, any length > 0.

    The sensor's +x is the body's +x made perpendicular to the boresight (the body's +y when the
    boresight is within 25 deg of the body's x axis); +y completes the right-handed frame.
    """
    b = np.asarray(boresight_body, dtype=float)
    if b.shape != (3,) or not np.all(np.isfinite(b)) or np.linalg.norm(b) == 0.0:
        raise InputError(f"sun sensor boresight must be a non-zero body-frame vector [x, y, z], got {boresight_body!r}")
    z = b / np.linalg.norm(b)
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ z) * z
    x /= np.linalg.norm(x)
    return Rotation.from_matrix(np.column_stack([x, np.cross(z, x), z]))


def sun_sensor(*, boresight_body, half_angle_deg: float, sigma_arcsec: float, bias_arcsec=(0.0, 0.0),
               light_time: bool = True, aberration: bool = True, stream: tuple[int, ...] = (41,),
               name: str = "sun sensor") -> SunSensor:
    """A :class:`SunSensor` from a run file's units: the boresight as a body-frame vector
    (:func:`mounting_from_boresight`), the field half-angle in degrees, the noise per transverse axis
    and the bias (two tangent-axis angles) in arcsec."""
    return SunSensor(mounting_from_boresight(boresight_body), float(half_angle_deg) * DEG_RAD,
                     float(sigma_arcsec) * ARCSEC_RAD, tuple(float(b) * ARCSEC_RAD for b in bias_arcsec),
                     light_time, aberration, tuple(stream), name)


@dataclass(frozen=True)
class SunReading:
    """One epoch of a sun sensor.

    Attributes
    ----------
    t_tdb_s : float
        Epoch, TDB seconds past J2000.
    record : Measurement or None
        The ``los`` record (module notes, step 4); None when the Sun is out of the field.
    reason : str or None
        Why there is no record ("sun sensor: ..."), else None.
    true_icrf : (3,) array
        The truth's apparent Sun direction, ICRF unit vector.
    off_boresight_rad : float
        The true Sun's angle from the sensor's boresight, rad.
    """

    t_tdb_s: float
    record: Measurement | None
    reason: str | None
    true_icrf: np.ndarray
    off_boresight_rad: float


def apparent_sun(t_tdb_s, r_ssb_km, v_ssb_km_s, *, ephemeris, light_time: bool = True,
                 aberration: bool = True) -> np.ndarray:
    """Apparent unit vector(s) observer -> Sun, ICRF, shape (3,) or (N, 3).

    Parameters
    ----------
    t_tdb_s : float or (N,) array
        Reception epochs, TDB seconds past J2000.
    r_ssb_km, v_ssb_km_s : (3,) or (N, 3) arrays
        Observer position (km) and velocity (km/s) relative to the SSB, ICRF.
    ephemeris
        Gives ``position("sun", t)`` relative to the SSB, km, ICRF.
    """
    return apparent_direction(lambda t: ephemeris.position("sun", t), t_tdb_s, r_ssb_km, v_ssb_km_s,
                              light_time=light_time, aberration=aberration)


def tangent_axes(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tangent axes ``e1 = unit(y x u)``, ``e2 = u x e1`` of a sensor-frame unit vector ``u`` (3,)
    (module notes, step 3): the sensor's +x and +y at the boresight."""
    e1 = np.cross([0.0, 1.0, 0.0], u)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def los_covariance(u_icrf: np.ndarray, sigma_rad: float, R_icrf_body: Rotation, u_body: np.ndarray,
                   cov_att_body_rad2: np.ndarray | None) -> np.ndarray:
    """Covariance (3, 3) of a measured ICRF unit vector ``u_icrf`` (module notes, step 4).

    ``sigma_rad`` per transverse axis; ``u_body`` the same direction in the body frame, whose
    attitude ``R_icrf_body`` (body -> ICRF) has the small-rotation covariance ``cov_att_body_rad2``
    (body frame, rad^2; None: a perfectly known attitude).
    """
    cov = sigma_rad**2 * (np.eye(3) - np.outer(u_icrf, u_icrf))
    if cov_att_body_rad2 is not None:
        # R exp([d]x) u_body = u + R (d x u_body) = u - R [u_body]x d
        j_att = -R_icrf_body.as_matrix() @ _skew(u_body)
        cov = cov + j_att @ np.asarray(cov_att_body_rad2, dtype=float) @ j_att.T
    cov = 0.5 * (cov + cov.T)
    return cov + np.outer(u_icrf, u_icrf) * float(np.trace(cov)) * RADIAL_VARIANCE_FRACTION


def read_sun(sensor: SunSensor, t_tdb_s: float, r_ssb_km, v_ssb_km_s, R_icrf_body: Rotation, *,
             rng: np.random.Generator, ephemeris, R_icrf_body_est: Rotation | None = None,
             cov_att_body_rad2: np.ndarray | None = None, frame_id: str = "") -> SunReading:
    """One sun-sensor reading at ``t_tdb_s`` (module notes).

    Parameters
    ----------
    sensor : SunSensor
    t_tdb_s : float
        Epoch, TDB seconds past J2000.
    r_ssb_km, v_ssb_km_s : (3,) arrays
        True observer position (km) and velocity (km/s) relative to the SSB, ICRF.
    R_icrf_body : Rotation
        True body -> ICRF attitude (what the sensor sees the Sun through).
    rng : Generator
        The epoch's draws (:meth:`SunSensor.rng`).
    ephemeris
        Gives the Sun's SSB position (:func:`apparent_sun`).
    R_icrf_body_est : Rotation, optional
        The estimated attitude (star tracker or camera solution) the record is taken to ICRF with;
        None: the truth.
    cov_att_body_rad2 : (3, 3) array, optional
        Covariance of that estimate's small-rotation error, body frame, rad^2; None: none.
    frame_id : str
        The record's ``frame_id``.
    """
    t = float(t_tdb_s)
    u_true = apparent_sun(t, np.asarray(r_ssb_km, float), np.asarray(v_ssb_km_s, float), ephemeris=ephemeris,
                          light_time=sensor.light_time, aberration=sensor.aberration)
    R_icrf_sensor = R_icrf_body * sensor.mounting
    u_sensor = R_icrf_sensor.inv().apply(u_true)
    off = float(np.arccos(np.clip(u_sensor[2], -1.0, 1.0)))
    if off > sensor.half_angle_rad:
        reason = (f"{sensor.name}: the Sun is {off / DEG_RAD:.2f} deg off the boresight, outside the "
                  f"{sensor.half_angle_rad / DEG_RAD:.2f} deg half-angle field")
        return SunReading(t, None, reason, u_true, off)
    e1, e2 = tangent_axes(u_sensor)
    d1, d2 = np.asarray(sensor.bias_rad) + sensor.sigma_rad * rng.standard_normal(2)
    measured = u_sensor + d1 * e1 + d2 * e2
    measured /= np.linalg.norm(measured)
    R_est = R_icrf_body if R_icrf_body_est is None else R_icrf_body_est
    u_body = sensor.mounting.apply(measured)
    u_icrf = R_est.apply(u_body)
    cov = los_covariance(u_icrf, sensor.sigma_rad, R_est, u_body, cov_att_body_rad2)
    record = Measurement(t, "los", u_icrf, cov, target="sun", sensor=sensor.name, frame_id=frame_id)
    return SunReading(t, record, None, u_true, off)


def geometric_los(record: Measurement, v_ssb_km_s) -> np.ndarray:
    """The geometric (aberration removed) unit line of sight of an apparent ``los`` record, ICRF, for an
    observer moving at ``v_ssb_km_s`` (3,), km/s, relative to the SSB (the inverse Lorentz aberration)."""
    return aberrate(np.asarray(record.value, float), -np.asarray(v_ssb_km_s, float))


def read_arc(sensor: SunSensor, seed: int, t_tdb_s, r_ssb_km, v_ssb_km_s, R_icrf_body: Rotation, *, ephemeris,
             R_icrf_body_est: Rotation | None = None, cov_att_body_rad2=None, first: int = 0) -> list[SunReading]:
    """:func:`read_sun` at every epoch of an arc, epoch ``first + k`` drawing from :meth:`SunSensor.rng`.

    ``t_tdb_s`` (M,), ``r_ssb_km`` / ``v_ssb_km_s`` (M, 3) true SSB states (km, km/s, ICRF),
    ``R_icrf_body`` true attitudes (M rotations); ``R_icrf_body_est`` and ``cov_att_body_rad2``
    (M, 3, 3) the attitude solutions, per epoch, or None.
    """
    t = np.atleast_1d(np.asarray(t_tdb_s, float))
    r = np.asarray(r_ssb_km, float).reshape(-1, 3)
    v = np.asarray(v_ssb_km_s, float).reshape(-1, 3)
    if not (len(t) == len(r) == len(v) == len(R_icrf_body)):
        raise InputError(f"sun sensor arc: epochs, positions, velocities and attitudes disagree in length "
                         f"({len(t)}, {len(r)}, {len(v)}, {len(R_icrf_body)})")
    readings = []
    for k in range(len(t)):
        est = None if R_icrf_body_est is None else R_icrf_body_est[k]
        cov = None if cov_att_body_rad2 is None else np.asarray(cov_att_body_rad2[k], float)
        readings.append(read_sun(sensor, t[k], r[k], v[k], R_icrf_body[k], rng=sensor.rng(seed, first + k),
                                 ephemeris=ephemeris, R_icrf_body_est=est, cov_att_body_rad2=cov))
    return readings
