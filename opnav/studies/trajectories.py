"""Reference trajectories built from physics (S2: the MAVEN-like Mars capture arc).

S2 (docs/studies.md#s2-mars-capture) studies "a NASA 2013 Mars probe" (MAVEN: launched
2013-11-18 18:28 UTC, Mars orbit insertion 2014-09-22 ~02:24 UTC) but gives no
state, so :func:`mars_capture_trajectory` builds one, step by step:

1. **Interplanetary arc.** A single-revolution Lambert arc (Sun point mass,
   DE421 GM) from the Earth's centre at departure to the Mars centre at
   arrival (:func:`lambert`), prograde with respect to the Earth's orbit.
   Its arrival velocity minus Mars' gives the incoming hyperbolic excess
   velocity ``v_inf`` (ICRF).
2. **Capture hyperbola at periapsis.** A Mars-centred hyperbola with that
   ``v_inf``, periapsis radius ``R_mars + altitude`` and an orbit inclination
   to Mars' equator (IAU pole) chosen in the B-plane, placed so that the
   probe is at periapsis at the arrival epoch (:func:`hyperbola_periapsis_state`).
3. **Back-propagation with the S2 models.** From periapsis backwards with
   ``capture_model_2`` (Mars + Sun + Earth, Mars-centred) to the sphere of
   influence ``|r_mars_probe| = 5.773e5 km`` (S2; the paper's "5.773e6 m" is a
   typo), then with ``capture_model_1`` (Sun + Mars + Earth, heliocentric) for
   the requested days before the crossing.

The patched-conic steps 1-2 only *seed* the state; the returned arc is one
continuous solution of the S2 force models, so its states at the SOI
crossing and at periapsis are consistent with the dynamics a filter uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from ..constants import DAY_S, DEG_RAD, GM_KM3_S2, RADIUS_KM
from ..dynamics import capture_model_1, capture_model_2, change_center, propagate, shadow_factor
from ..ephemeris import Ephemeris, default_ephemeris
from ..epochs import parse_epoch
from ..errors import ConvergenceError, InputError
from ..frames import angle_between, radec_to_unit

#: Mars' sphere-of-influence radius used by S2 to switch models, km.
MARS_SOI_KM = 5.773e5
#: Mars' north pole, ICRF, IAU WGCCRE 2009 (Archinal et al. 2011) at J2000: RA 317.68143 deg, Dec 52.88650 deg
#: (century rates, < 0.02 deg over 2014, are ignored: the pole only orients the capture plane).
MARS_POLE_ICRF = radec_to_unit(317.68143 * DEG_RAD, 52.88650 * DEG_RAD)
#: MAVEN launch (UTC) and the S2 periapsis epoch (TDB).
MAVEN_LAUNCH_UTC = "2013-11-18T18:28:00"
S2_PERIAPSIS_TDB = "2014-09-22T02:00:00"


def _stumpff(z: float) -> tuple[float, float]:
    """Stumpff functions C(z), S(z) (Curtis 2014, eqs. 3.50-3.51)."""
    if z > 1e-8:
        sz = np.sqrt(z)
        return (1.0 - np.cos(sz)) / z, (sz - np.sin(sz)) / sz**3
    if z < -1e-8:
        sz = np.sqrt(-z)
        return (np.cosh(sz) - 1.0) / -z, (np.sinh(sz) - sz) / sz**3
    return 0.5 - z / 24.0, 1.0 / 6.0 - z / 120.0


def lambert(r1_km: np.ndarray, r2_km: np.ndarray, tof_s: float, *, mu_km3_s2: float,
            pole: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Single-revolution Lambert arc (universal variables).

    Parameters
    ----------
    r1_km, r2_km : (3,) arrays
        Positions at departure and arrival relative to the attracting body, km, ICRF.
    tof_s : float
        Time of flight, s (> 0).
    mu_km3_s2 : float
        Gravitational parameter of the attracting body, km^3/s^2.
    pole : (3,) array
        Direction (ICRF) defining "prograde": the transfer's angular momentum has a
        positive component along it (e.g. the Earth's orbital angular momentum).

    Returns
    -------
    v1_km_s, v2_km_s : (3,) arrays
        Velocities at departure and arrival, km/s, ICRF, same origin as the positions.

    Notes
    -----
    Curtis, *Orbital Mechanics for Engineering Students* (3rd ed. 2014), Algorithm 5.2:
    ``A = sin(dtheta) sqrt(r1 r2 / (1 - cos dtheta))``,
    ``y(z) = r1 + r2 + A (z S(z) - 1) / sqrt(C(z))`` and the time of flight
    ``sqrt(mu) t(z) = (y/C)^1.5 S + A sqrt(y)``, monotonic in z on one revolution,
    solved here with Brent's method instead of Curtis' Newton iteration; then the
    Lagrange coefficients ``f = 1 - y/r1``, ``g = A sqrt(y/mu)``, ``gdot = 1 - y/r2``.
    """
    r1 = np.asarray(r1_km, dtype=float)
    r2 = np.asarray(r2_km, dtype=float)
    if r1.shape != (3,) or r2.shape != (3,):
        raise InputError(f"r1_km and r2_km must be (3,) vectors, got {r1.shape} and {r2.shape}")
    if not (np.isfinite(tof_s) and tof_s > 0.0):
        raise InputError(f"tof_s must be positive, got {tof_s!r}")
    if not (np.isfinite(mu_km3_s2) and mu_km3_s2 > 0.0):
        raise InputError(f"mu_km3_s2 must be positive, got {mu_km3_s2!r}")
    n1, n2 = np.linalg.norm(r1), np.linalg.norm(r2)
    cos_dtheta = float(np.clip(r1 @ r2 / (n1 * n2), -1.0, 1.0))
    dtheta = np.arccos(cos_dtheta)
    if np.cross(r1, r2) @ np.asarray(pole, dtype=float) < 0.0:
        dtheta = 2.0 * np.pi - dtheta
    if abs(np.sin(dtheta)) < 1e-10:
        raise InputError("Lambert endpoints are collinear with the attracting body: the transfer plane is undefined")
    a_coef = np.sin(dtheta) * np.sqrt(n1 * n2 / (1.0 - cos_dtheta))

    def y_of(z: float) -> float:
        c, s = _stumpff(z)
        return n1 + n2 + a_coef * (z * s - 1.0) / np.sqrt(c)

    def tof_residual(z: float) -> float:
        c, s = _stumpff(z)
        y = y_of(z)
        return ((y / c) ** 1.5 * s + a_coef * np.sqrt(y)) / np.sqrt(mu_km3_s2) - tof_s

    z_hi = 4.0 * np.pi**2 * (1.0 - 1e-6)
    z_lo = -4.0 * np.pi**2
    if y_of(z_lo) < 0.0:
        # y(z) < 0 has no physical solution (A > 0): the time of flight is smallest where y turns positive.
        root = brentq(y_of, z_lo, z_hi, xtol=1e-14)
        z_lo = root + 1e-9 * (z_hi - root)
    else:
        while tof_residual(z_lo) > 0.0:
            z_lo *= 2.0
            if z_lo < -1e6:
                raise ConvergenceError(f"Lambert: no single-revolution solution bracketed for tof {tof_s:.0f} s")
    if tof_residual(z_lo) > 0.0:
        raise ConvergenceError(f"Lambert: tof {tof_s:.0f} s is shorter than the fastest transfer bracketed")
    if tof_residual(z_hi) < 0.0:
        raise ConvergenceError(f"Lambert: tof {tof_s:.0f} s needs more than one revolution")
    z = brentq(tof_residual, z_lo, z_hi, xtol=1e-14, rtol=1e-14, maxiter=200)
    y = y_of(z)
    f = 1.0 - y / n1
    g = a_coef * np.sqrt(y / mu_km3_s2)
    g_dot = 1.0 - y / n2
    v1 = (r2 - f * r1) / g
    v2 = (g_dot * r2 - r1) / g
    return v1, v2


def hyperbola_periapsis_state(v_inf_km_s: np.ndarray, *, periapsis_radius_km: float, inclination_rad: float,
                              mu_km3_s2: float, pole: np.ndarray = MARS_POLE_ICRF) -> np.ndarray:
    """Periapsis state of the hyperbola with incoming excess velocity ``v_inf_km_s``.

    Parameters
    ----------
    v_inf_km_s : (3,) array
        Incoming hyperbolic excess velocity (probe relative to the planet, far before
        periapsis), km/s, ICRF.
    periapsis_radius_km : float
        Periapsis distance from the planet's centre, km.
    inclination_rad : float
        Inclination of the orbit plane to the planet's equator (``pole``), rad, in
        [|pi/2 - angle(S, pole)| ... pi - that] reachable for the asymptote S.
    mu_km3_s2 : float
        Planet's gravitational parameter, km^3/s^2.
    pole : (3,) array
        Planet's north pole, ICRF unit vector.

    Returns
    -------
    (6,) array
        ``[r (km), v (km/s)]`` at periapsis, ICRF, planet-centred.

    Notes
    -----
    B-plane frame: ``S = v_inf/|v_inf|``, ``T = S x K/|S x K|`` (K the pole),
    ``R = S x T``. With the B vector at angle theta from T, the orbit normal is
    ``h = cos(theta) K_perp + sin(theta) T`` (``K_perp`` the unit component of K
    normal to S), so ``cos i = cos(theta) |K_perp|``; theta >= 0 is taken.
    With ``e = 1 + r_p v_inf^2/mu`` and ``k = sqrt(e^2 - 1)``, the incoming
    asymptote is ``S = (p + k q)/e`` (p periapsis direction, q = h x p), hence
    ``p = (S + k B_hat)/e`` and ``q = (k S - B_hat)/e``, and ``|v_p| = sqrt(v_inf^2 + 2 mu/r_p)``
    (Vallado 2013, sec. 12.2).
    """
    v_inf = np.asarray(v_inf_km_s, dtype=float)
    speed = float(np.linalg.norm(v_inf))
    if v_inf.shape != (3,) or not speed > 0.0:
        raise InputError(f"v_inf_km_s must be a non-zero (3,) vector, got {v_inf!r}")
    if not periapsis_radius_km > 0.0:
        raise InputError(f"periapsis_radius_km must be positive, got {periapsis_radius_km!r}")
    s = v_inf / speed
    k_pole = np.asarray(pole, dtype=float) / np.linalg.norm(pole)
    k_perp = k_pole - (k_pole @ s) * s
    k_perp_norm = float(np.linalg.norm(k_perp))
    cos_theta = np.cos(inclination_rad) / k_perp_norm
    if not (np.isfinite(cos_theta) and abs(cos_theta) <= 1.0):
        lowest = np.degrees(np.arccos(k_perp_norm))
        raise InputError(f"inclination_rad {inclination_rad!r} is not reachable with this asymptote: "
                         f"inclination must lie in [{lowest:.2f}, {180.0 - lowest:.2f}] deg")
    theta = np.arccos(cos_theta)
    t_axis = np.cross(s, k_pole) / k_perp_norm
    r_axis = np.cross(s, t_axis)
    b_hat = np.cos(theta) * t_axis + np.sin(theta) * r_axis
    e = 1.0 + periapsis_radius_km * speed**2 / mu_km3_s2
    k = np.sqrt(e * e - 1.0)
    p_hat = (s + k * b_hat) / e
    q_hat = (k * s - b_hat) / e
    v_p = np.sqrt(speed**2 + 2.0 * mu_km3_s2 / periapsis_radius_km)
    return np.concatenate([periapsis_radius_km * p_hat, v_p * q_hat])


@dataclass(frozen=True)
class CaptureTrajectory:
    """The S2 capture arc: states on an epoch grid, with the model switch.

    Attributes
    ----------
    t_tdb_s : (M,) array
        Epochs, TDB seconds past J2000, increasing; includes ``t_soi_tdb_s`` and
        ``t_periapsis_tdb_s`` (the last epoch).
    states_sun : (M, 6) array
        Probe ``[r (km), v (km/s)]`` relative to the Sun, ICRF.
    states_mars : (M, 6) array
        Probe ``[r (km), v (km/s)]`` relative to Mars, ICRF.
    t_soi_tdb_s : float
        Epoch of the inbound crossing of ``|r_mars_probe| = soi_radius_km``.
    t_periapsis_tdb_s : float
        Periapsis epoch.
    t_departure_tdb_s : float
        Earth departure epoch of the seeding Lambert arc.
    v_inf_km_s : (3,) array
        Incoming excess velocity of the seeding Lambert arc, km/s, ICRF (relative to Mars).
    soi_radius_km : float
        Sphere-of-influence radius that switches model 1 -> model 2, km.
    """

    t_tdb_s: np.ndarray
    states_sun: np.ndarray
    states_mars: np.ndarray
    t_soi_tdb_s: float
    t_periapsis_tdb_s: float
    t_departure_tdb_s: float
    v_inf_km_s: np.ndarray
    soi_radius_km: float

    @property
    def inside_soi(self) -> np.ndarray:
        """(M,) bool: epochs governed by model 2 (at or after the SOI crossing)."""
        return self.t_tdb_s >= self.t_soi_tdb_s

    def state_at(self, t_tdb_s: float, center: str) -> np.ndarray:
        """Grid state ``[r km, v km/s]`` (ICRF, relative to ``center`` "sun" or "mars") at a grid epoch."""
        index = np.flatnonzero(self.t_tdb_s == t_tdb_s)
        if index.size == 0:
            raise InputError(f"t_tdb_s {t_tdb_s!r} is not an epoch of the capture trajectory grid")
        if center == "sun":
            return self.states_sun[index[0]].copy()
        if center == "mars":
            return self.states_mars[index[0]].copy()
        raise InputError(f"center must be 'sun' or 'mars', got {center!r}")


def _soi_crossing(model, t_peri: float, x_peri: np.ndarray, soi_km: float, v_inf: float) -> tuple[float, np.ndarray]:
    """Inbound SOI crossing epoch and Mars-centred state, by bracketing on a grid and Hermite-root refinement."""
    # Straight-line estimate of the crossing time; the grid extends 50 % beyond it for safety.
    guess_s = soi_km / v_inf
    grid = t_peri - np.linspace(0.0, 1.5 * guess_s, 400)[1:]
    traj = propagate(model, t_peri, x_peri, grid)
    dist = np.linalg.norm(traj.states[:, :3], axis=1)
    outside = np.flatnonzero(dist > soi_km)
    if outside.size == 0:
        raise ConvergenceError(f"capture arc never leaves the sphere of influence ({soi_km:.0f} km) "
                               f"within {1.5 * guess_s / DAY_S:.1f} days before periapsis")
    j = outside[0]
    x_in = traj.states[j - 1] if j > 0 else x_peri
    t_in = grid[j - 1] if j > 0 else t_peri
    t_out = grid[j]

    def radius_at(t: float) -> float:
        state = propagate(model, t_in, x_in, t).states[0]
        return float(np.linalg.norm(state[:3])) - soi_km

    t_cross = brentq(radius_at, t_out, t_in, xtol=1e-3)
    return t_cross, propagate(model, t_in, x_in, t_cross).states[0]


def mars_capture_trajectory(
    *,
    departure_tdb_s: float | None = None,
    periapsis_tdb_s: float | None = None,
    periapsis_altitude_km: float = 380.0,
    inclination_rad: float = 75.0 * DEG_RAD,
    days_before_soi: float = 5.0,
    step_s: float = 3600.0,
    soi_radius_km: float = MARS_SOI_KM,
    ephemeris: Ephemeris | None = None,
) -> CaptureTrajectory:
    """Build the S2 Mars capture arc (see the module docstring for the method).

    Parameters
    ----------
    departure_tdb_s : float, optional
        Earth departure of the seeding Lambert arc, TDB s past J2000; default MAVEN's
        launch, 2013-11-18T18:28:00 UTC.
    periapsis_tdb_s : float, optional
        Mars periapsis epoch (= Lambert arrival), TDB s past J2000; default
        2014-09-22T02:00:00 TDB (MAVEN's orbit insertion was ~02:24 UTC that day).
    periapsis_altitude_km : float
        Periapsis altitude above Mars' equatorial radius (3396.19 km), km; default 380
        (MAVEN's capture periapsis).
    inclination_rad : float
        Inclination of the capture hyperbola to Mars' equator, rad; default 75 deg (MAVEN).
    days_before_soi : float
        Length of the model-1 arc before the SOI crossing, days.
    step_s : float
        Grid step, s (the SOI crossing and periapsis are added to the grid).
    soi_radius_km : float
        Model-switch radius, km (S2: 5.773e5).
    ephemeris : Ephemeris, optional
        Planet/moon ephemeris (default DE421).

    Returns
    -------
    CaptureTrajectory

    Notes
    -----
    With the defaults the Lambert arc (307.3 days, Sun GM only, Earth and Mars
    centres from DE421) arrives with |v_inf| = 3.18 km/s, its asymptote 6.5 deg
    from Mars' anti-velocity and 88 deg from the Mars-Sun line; MAVEN flew about
    2.9 km/s after its correction manoeuvres, which a Lambert arc from the launch
    date cannot reproduce. The SOI crossing falls 2.04 days before periapsis
    (2014-09-20T01:06 TDB).
    """
    if not (np.isfinite(days_before_soi) and days_before_soi > 0.0):
        raise InputError(f"days_before_soi must be positive, got {days_before_soi!r}")
    if not (np.isfinite(step_s) and step_s > 0.0):
        raise InputError(f"step_s must be positive, got {step_s!r}")
    if not (np.isfinite(periapsis_altitude_km) and periapsis_altitude_km > 0.0):
        raise InputError(f"periapsis_altitude_km must be positive, got {periapsis_altitude_km!r}")
    if not (np.isfinite(soi_radius_km) and soi_radius_km > 10 * RADIUS_KM["mars"]):
        raise InputError(f"soi_radius_km must exceed ten Mars radii, got {soi_radius_km!r}")
    eph = ephemeris if ephemeris is not None else default_ephemeris()
    t_dep = parse_epoch(MAVEN_LAUNCH_UTC, "utc") if departure_tdb_s is None else float(departure_tdb_s)
    t_peri = parse_epoch(S2_PERIAPSIS_TDB, "tdb") if periapsis_tdb_s is None else float(periapsis_tdb_s)
    if not t_peri > t_dep:
        raise InputError(f"periapsis_tdb_s ({t_peri}) must follow departure_tdb_s ({t_dep})")

    r_earth, v_earth = eph.state("earth", t_dep, center="sun")
    r_mars, v_mars = eph.state("mars", t_peri, center="sun")
    _, v_arrive = lambert(r_earth, r_mars, t_peri - t_dep, mu_km3_s2=GM_KM3_S2["sun"],
                          pole=np.cross(r_earth, v_earth))
    v_inf = v_arrive - v_mars
    x_peri = hyperbola_periapsis_state(v_inf, periapsis_radius_km=RADIUS_KM["mars"] + periapsis_altitude_km,
                                       inclination_rad=inclination_rad, mu_km3_s2=GM_KM3_S2["mars"])

    model_2 = capture_model_2()
    t_soi, x_soi = _soi_crossing(model_2, t_peri, x_peri, soi_radius_km, float(np.linalg.norm(v_inf)))
    t_start = t_soi - days_before_soi * DAY_S
    grid = np.arange(t_start, t_peri, step_s)
    t_all = np.unique(np.concatenate([grid, [t_soi, t_peri]]))
    inside = t_all >= t_soi
    outside_epochs = t_all[~inside][::-1]

    inner = propagate(model_2, t_peri, x_peri, t_all[inside][::-1]).states[::-1]
    x_soi_sun = change_center(x_soi, t_soi, "mars", "sun", eph)
    outer = propagate(capture_model_1(), t_soi, x_soi_sun, outside_epochs).states[::-1]
    states_mars = np.empty((t_all.size, 6))
    states_sun = np.empty((t_all.size, 6))
    states_mars[inside] = inner
    states_sun[inside] = change_center(inner, t_all[inside], "mars", "sun", eph)
    states_sun[~inside] = outer
    states_mars[~inside] = change_center(outer, t_all[~inside], "sun", "mars", eph)
    return CaptureTrajectory(t_all, states_sun, states_mars, float(t_soi), float(t_peri), float(t_dep),
                             v_inf, float(soi_radius_km))


@dataclass(frozen=True)
class BodyVisibility:
    """Whether a near body can be seen from the probe along an arc.

    Attributes
    ----------
    target : str
        Body name.
    occulted : (M,) bool
        The body's centre is behind Mars' disk (sphere of the equatorial radius).
    eclipsed : (M,) bool
        The body is in Mars' umbra (unlit; only the moons can be).
    sun_separation_rad : (M,) array
        Angle between the body and the Sun seen from the probe, rad (0 for the Sun itself).
    mars_separation_rad : (M,) array
        Angle between the body and Mars' centre seen from the probe, rad.
    mars_angular_radius_rad : (M,) array
        Apparent radius of Mars' disk, rad.
    """

    target: str
    occulted: np.ndarray
    eclipsed: np.ndarray
    sun_separation_rad: np.ndarray
    mars_separation_rad: np.ndarray
    mars_angular_radius_rad: np.ndarray

    @property
    def visible(self) -> np.ndarray:
        """(M,) bool: neither occulted nor eclipsed."""
        return ~(self.occulted | self.eclipsed)


def body_visibility(t_tdb_s: np.ndarray, r_mars_probe_km: np.ndarray, target: str, *,
                    ephemeris: Ephemeris | None = None) -> BodyVisibility:
    """Occultation by Mars, eclipse in Mars' shadow and Sun separation of ``target`` seen from the probe.

    Parameters
    ----------
    t_tdb_s : (M,) array
        Epochs, TDB s past J2000.
    r_mars_probe_km : (M, 3) array
        Probe position relative to Mars, km, ICRF.
    target : str
        ``"mars"``, ``"phobos"``, ``"deimos"``, ``"sun"`` or another ephemeris body.
    ephemeris : Ephemeris, optional
        Default DE421 with the mean-element moons.

    Returns
    -------
    BodyVisibility

    Notes
    -----
    Geometric directions (no light time: it moves the moons by < 1 km here). The
    target is occulted when its direction lies within Mars' apparent radius
    ``asin(R/d)`` and it is farther than the tangent points, ``sqrt(d^2 - R^2)``.
    The eclipse test uses :func:`opnav.dynamics.shadow_factor` (umbra: factor 0).
    """
    t = np.atleast_1d(np.asarray(t_tdb_s, dtype=float))
    r_probe = np.atleast_2d(np.asarray(r_mars_probe_km, dtype=float))
    if r_probe.shape != (t.size, 3):
        raise InputError(f"r_mars_probe_km must have shape ({t.size}, 3), got {r_probe.shape}")
    eph = ephemeris if ephemeris is not None else default_ephemeris()
    key = Ephemeris.check_body(target)
    radius = RADIUS_KM["mars"]
    dist_mars = np.linalg.norm(r_probe, axis=1)
    if np.any(dist_mars <= radius):
        raise InputError(f"probe inside Mars (distance {dist_mars.min():.1f} km)")
    r_sun = eph.position("sun", t, center="mars")
    r_target = np.zeros_like(r_probe) if key == "mars" else eph.position(key, t, center="mars")
    to_target = r_target - r_probe
    to_mars = -r_probe
    mars_radius_rad = np.arcsin(radius / dist_mars)
    mars_sep = angle_between(to_target, to_mars) if key != "mars" else np.zeros(t.size)
    beyond = np.linalg.norm(to_target, axis=1) > np.sqrt(dist_mars**2 - radius**2)
    occulted = (key != "mars") & (mars_sep < mars_radius_rad) & beyond
    if key in ("mars", "sun"):
        eclipsed = np.zeros(t.size, bool)
    else:
        eclipsed = shadow_factor(r_target - r_sun, r_target, radius) == 0.0
    sun_sep = np.zeros(t.size) if key == "sun" else angle_between(to_target, r_sun - r_probe)
    return BodyVisibility(key, occulted, eclipsed, sun_sep, mars_sep, mars_radius_rad)
