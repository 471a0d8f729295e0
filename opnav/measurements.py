"""Measurement models with analytic Jacobians, for every kind in :mod:`opnav.records`.

:class:`ProbeMeasurementModel` implements the
:class:`opnav.filters.base.MeasurementModel` protocol. Given a record and a
state ``x = [r, v]`` (km, km/s, ICRF, relative to the model's central body;
extra augmented entries are ignored and get zero partials) it predicts the
measurement the camera/spectrometer would make, applying the same light-time
and aberration code (:mod:`opnav.light`) that the renderer uses:

1. probe SSB state = central body's SSB state (ephemeris) + ``x``;
2. light time: astrometric vector ``rho`` from the probe at reception to the
   target at emission (:func:`opnav.light.light_time_vector`);
3. aberration from the probe's SSB velocity (:func:`opnav.light.aberrate`) on the
   unit vector ``rho/|rho|``;
4. the kind's function of the apparent direction (RA/Dec, unit vector,
   starlight angle, starlight elevation).

Partials (all analytic; ``tests/test_measurements.py`` checks each against
central differences of the full model with light time and aberration on):

- d rho / d r_probe = -(I + v_T rho_hat^T / c)^-1 (Sherman-Morrison form), which is
  exact to first order: it carries the change of light time with the probe
  position through the target's velocity ``v_T`` at emission. Only the change
  of ``v_T`` itself over the light-time change (second order, ~|a_T| tau / c)
  is neglected.
- Aberration partials are those of the exact relativistic formula, for both
  the direction (:func:`opnav.light.aberration_jacobian`) and the probe velocity
  (:func:`opnav.light.aberration_velocity_jacobian`); so d/dv of RA/Dec is the
  aberration term (~1/c per km/s) and zero when aberration is off.
- ``target_vector`` = ``|rho| u_app``: the direction partials above times the range plus the
  apparent direction times d|rho|/dr = rho_hat^T drho/dr (the light-time range).
- Position and radial-velocity partials are exact. The radial-velocity model
  is the classical (first-order in v/c) Doppler of S4 and ignores light time.

Starlight kinds: ``record.star_unit_icrf`` is the star's astrometric direction
from the probe (catalog position with proper motion and parallax for the probe's
position applied by the catalog stage, *not* aberrated); with aberration on, the
model aberrates it with the probe velocity, exactly as it does the body direction, so the angle predicted
is the one measured between the two *apparent* directions in the image.

Radial velocity (S4): for a star, ``v_rad = (v_star - v_probe) . l_star`` with
``v_star . l_star`` the catalog radial velocity of ``record.star_id`` (given to
the model) and ``l_star = record.star_unit_icrf``; for ``target == "sun"``,
``v_rad = v . r / |r|`` with ``r, v`` the probe's heliocentric state. Both are
positive when the source and probe separate (l points probe -> source, and for
the Sun l = -r/|r|), so one sign convention covers both.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from .constants import C_KM_S, RADIUS_KM
from .ephemeris import default_ephemeris
from .ephemeris.cache import EphemerisCache
from .ephemeris.tables import ArcTables
from .errors import ConvergenceError, InputError
from .frames import angle_between, unit_to_radec
from .light import aberrate, aberration_jacobian, aberration_velocity_jacobian, light_time_vector
from .light_compiled import compiled_directions
from .records import KIND_SIZE, Measurement, pair_targets

#: Kinds whose value is a function of the apparent direction to ``record.target``.
DIRECTION_KINDS = ("radec", "los", "starlight_angle", "starlight_elevation", "starlight", "target_vector")
#: Positions of right ascensions in the value of each kind that holds them (wrapped in residuals).
RA_SLOTS = {"radec": [0], "radec_pair": [0, 2]}


@dataclass(frozen=True)
class _Sight:
    """What :meth:`ProbeMeasurementModel._direction` reads of a record: its epoch and one target."""

    t_tdb_s: float
    target: str


def _outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...j->...ij", a, b)


def radec_partials(vector: np.ndarray) -> np.ndarray:
    """d(ra, dec)/d(vector) for vector(s) (..., 3) of any length, shape (..., 2, 3), rad per unit length.

    Notes
    -----
    With rho_xy^2 = x^2 + y^2: d ra = [-y, x, 0] / rho_xy^2 and
    d dec = [-x z, -y z, rho_xy^2] / (|w|^2 rho_xy). These are the S1 partials with
    respect to the *target-relative* vector; with respect to the probe position
    they change sign (S1 writes [y, -x, 0] / rho_xy^2).
    """
    w = np.asarray(vector, dtype=float)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    rxy2 = x * x + y * y
    rxy = np.sqrt(rxy2)
    r2 = rxy2 + z * z
    zero = np.zeros_like(x)
    d_ra = np.stack([-y / rxy2, x / rxy2, zero], axis=-1)
    d_dec = np.stack([-x * z / (r2 * rxy), -y * z / (r2 * rxy), rxy / r2], axis=-1)
    return np.stack([d_ra, d_dec], axis=-2)


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Wrap angle(s) (rad) to (-pi, pi]."""
    wrapped = np.mod(np.asarray(angle, dtype=float) + np.pi, 2.0 * np.pi) - np.pi
    return np.where(wrapped == -np.pi, np.pi, wrapped)


class ProbeMeasurementModel:
    """Predicts every :mod:`opnav.records` kind from a probe state, with analytic Jacobians.

    Parameters
    ----------
    center : str
        Central body of the state vector (``"sun"``, ``"mars"``, ``"earth"``, ...):
        ``x[:3]`` is the probe position relative to it, km, ICRF.
    ephemeris : Ephemeris-like, optional
        Anything with ``state(body, t, center="ssb") -> (r km, v km/s)`` (ICRF),
        vectorised over epochs; default :func:`opnav.ephemeris.default_ephemeris`.
        An :class:`~opnav.ephemeris.cache.EphemerisCache` (what filters use) also
        switches the direction kinds to the compiled kernels of
        :mod:`opnav.light_compiled` (same answers to rounding, ~50x faster a call).
    light_time, aberration : bool
        Apply each correction (the renderer's defaults; switch off to study them).
    target_position_sigma_km : float
        1-sigma error (per axis, km) of the target's ephemeris. :meth:`noise_covariance`
        adds its projection on the measured angles to the record covariance (a white
        approximation of what is really a slowly varying bias).
    star_radial_velocity_km_s : mapping of int to float, optional
        Catalog radial velocity ``v_star . l_star`` (km/s, positive receding) by ``star_id``,
        needed for stellar ``radial_velocity`` records.
    body_radius_km : mapping of str to float, optional
        Radii for ``starlight_elevation`` (default :data:`opnav.constants.RADIUS_KM`).
    """

    def __init__(
        self,
        center: str,
        *,
        ephemeris=None,
        light_time: bool = True,
        aberration: bool = True,
        target_position_sigma_km: float = 0.0,
        star_radial_velocity_km_s: Mapping[int, float] | None = None,
        body_radius_km: Mapping[str, float] | None = None,
    ):
        if not isinstance(center, str) or not center.strip():
            raise InputError(f"center must be a body name, got {center!r}")
        if not np.isfinite(target_position_sigma_km) or target_position_sigma_km < 0.0:
            raise InputError(f"target_position_sigma_km must be finite and >= 0, got {target_position_sigma_km!r}")
        self.center = center.strip().lower()
        self.ephemeris = ephemeris if ephemeris is not None else default_ephemeris()
        self.light_time = bool(light_time)
        self.aberration = bool(aberration)
        self.target_position_sigma_km = float(target_position_sigma_km)
        self.star_radial_velocity_km_s = dict(star_radial_velocity_km_s or {})
        self.body_radius_km = {**RADIUS_KM, **dict(body_radius_km or {})}
        self._arc_tables: dict[str, ArcTables] = {}

    # ------------------------------------------------------------------ geometry
    def _states(self, t: float, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Probe SSB position (K, 3) km and velocity (K, 3) km/s, ICRF."""
        if self.center == "ssb":
            return x[:, :3], x[:, 3:6]
        r_c, v_c = self.ephemeris.state(self.center, t, center="ssb")
        return r_c + x[:, :3], v_c + x[:, 3:6]

    def _target_ssb(self, target: str):
        key = target.strip().lower()
        if not key:
            raise InputError("measurement record has no target body")
        return lambda t: self.ephemeris.state(key, t, center="ssb")[0]

    def direction_tables(self, target: str, t: float):
        """Chebyshev tables ``(coef, first, seg, count)`` of ``target`` (entry 0) and the centre (entry 1,
        absent for ``"ssb"``), both relative to the SSB, covering the light-time span before ``t``
        (TDB s past J2000), for :func:`opnav.light_compiled.directions_range`; None unless the
        ephemeris is an :class:`~opnav.ephemeris.cache.EphemerisCache`. ``target`` is a lower-case name."""
        if not isinstance(self.ephemeris, EphemerisCache):
            return None
        tables = self._arc_tables.get(target)
        if tables is None:
            entries = [(target, "ssb", self.ephemeris)]
            if self.center != "ssb":
                entries.append((self.center, "ssb", self.ephemeris))
            tables = self._arc_tables[target] = ArcTables(entries)
        # light time reaches back at most hours in the solar system
        return tables.cover(t - 86_400.0, t)

    def _direction(self, record: Measurement, x: np.ndarray, want_jacobian: bool = True):
        """Apparent direction to ``record.target`` and its partials.

        Returns rho (K, 3) km, u_app (K, 3), du_app/dr (K, 3, 3), du_app/dv (K, 3, 3),
        drho/dr (K, 3, 3), the probe SSB velocity (K, 3). With an
        :class:`~opnav.ephemeris.cache.EphemerisCache` as ephemeris the compiled twin
        (:mod:`opnav.light_compiled`) does the arithmetic; the Jacobians are then
        only filled when ``want_jacobian``.
        """
        k = x.shape[0]
        t = record.t_tdb_s
        target = record.target.strip().lower()
        tables = self.direction_tables(target, t) if target else None
        if tables is not None:
            status, *out = compiled_directions(t, x, tables, center_ssb=self.center == "ssb",
                                               light_time=self.light_time, aberration=self.aberration,
                                               want_jacobian=want_jacobian)
            if status == 2:
                raise ConvergenceError("light-time iteration did not converge in 10 steps")
            if status != 0:  # pragma: no cover - cover() spans the epoch
                raise InputError(f"epoch {t:.3f} s is outside the ephemeris tables of {target!r}")
            return tuple(out)
        r_obs, v_obs = self._states(t, x)
        target_ssb = self._target_ssb(record.target)
        eye = np.broadcast_to(np.eye(3), (k, 3, 3))
        if self.light_time:
            rho, tau = light_time_vector(target_ssb, np.full(k, t), r_obs)
            v_target = self.ephemeris.state(record.target.strip().lower(), t - tau, center="ssb")[1]
            rho_hat = rho / np.linalg.norm(rho, axis=-1, keepdims=True)
            a = v_target / C_KM_S
            denom = 1.0 + np.sum(rho_hat * a, axis=-1)[:, None, None]
            d_rho = -(eye - _outer(a, rho_hat) / denom)
        else:
            rho = np.asarray(target_ssb(np.full(k, t))).reshape(k, 3) - r_obs
            d_rho = -eye
        dist = np.linalg.norm(rho, axis=-1, keepdims=True)
        u = rho / dist
        d_u = (eye - _outer(u, u)) / dist[..., None]
        if self.aberration:
            u_app = aberrate(u, v_obs)
            du_app_dr = aberration_jacobian(u, v_obs) @ d_u @ d_rho
            du_app_dv = aberration_velocity_jacobian(u, v_obs)
        else:
            u_app = u
            du_app_dr = d_u @ d_rho
            du_app_dv = np.zeros((k, 3, 3))
        return rho, u_app, du_app_dr, du_app_dv, d_rho, v_obs

    def _star(self, record: Measurement, v_obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Apparent star direction (K, 3) and its velocity partial (K, 3, 3)."""
        s = np.broadcast_to(record.star_unit_icrf / np.linalg.norm(record.star_unit_icrf), v_obs.shape)
        if self.aberration:
            return aberrate(s, v_obs), aberration_velocity_jacobian(s, v_obs)
        return np.array(s), np.zeros(v_obs.shape + (3,))

    def _radius(self, target: str) -> float:
        key = target.strip().lower()
        if key not in self.body_radius_km:
            raise InputError(f"no radius for body {target!r} (starlight_elevation); pass body_radius_km")
        return float(self.body_radius_km[key])

    def _evaluate(self, record: Measurement, x: np.ndarray, want_jacobian: bool, kind: str | None = None):
        """Predicted values (K, m) and, if asked, d/d[r, v] (K, m, 6); ``kind`` overrides ``record.kind``."""
        kind = record.kind if kind is None else kind
        k = x.shape[0]
        if kind == "radec_pair":
            # each target's direction on its own (light time differs); stacked [ra_1, dec_1, ra_2, dec_2]
            parts = [self._evaluate(_Sight(record.t_tdb_s, name), x, want_jacobian, kind="radec")
                     for name in pair_targets(record)]
            return (np.concatenate([p[0] for p in parts], axis=-1),
                    np.concatenate([p[1] for p in parts], axis=-2) if want_jacobian else None)
        if kind in DIRECTION_KINDS:
            rho, u_app, du_dr, du_dv, d_rho, v_obs = self._direction(record, x, want_jacobian)
            du = np.concatenate([du_dr, du_dv], axis=-1)  # (K, 3, 6)
            if kind == "radec":
                ra, dec = unit_to_radec(u_app)
                value = np.stack([ra, dec], axis=-1)
                jac = radec_partials(u_app) @ du if want_jacobian else None
            elif kind == "los":
                value, jac = u_app, du
            elif kind == "target_vector":
                # |rho| u_app: d|rho|/dr = rho_hat^T drho/dr (light time included), nothing through v
                dist = np.linalg.norm(rho, axis=-1)
                value = dist[:, None] * u_app
                jac = None
                if want_jacobian:
                    d_dist = np.concatenate([(rho / dist[:, None])[:, None, :] @ d_rho, np.zeros((k, 1, 3))], axis=-1)
                    jac = dist[:, None, None] * du + u_app[:, :, None] * d_dist
            else:
                s_app, ds_dv = self._star(record, v_obs)
                theta = angle_between(u_app, s_app)
                value = theta[:, None]
                jac = None
                if want_jacobian:
                    sin_t = np.sin(theta)[:, None, None]
                    d_theta = -(s_app[:, None, :] @ du) / sin_t
                    d_theta[..., 3:] -= (u_app[:, None, :] @ ds_dv) / sin_t
                    jac = d_theta
                if kind in ("starlight_elevation", "starlight"):
                    radius = self._radius(record.target)
                    dist = np.linalg.norm(rho, axis=-1)
                    if np.any(dist <= radius):
                        raise InputError(f"probe inside {record.target} (distance {dist.min():.1f} km)")
                    elevation = value - np.arcsin(radius / dist)[:, None]
                    if want_jacobian:
                        rho_hat = rho / dist[:, None]
                        gain = radius / (dist**2 * np.sqrt(1.0 - (radius / dist) ** 2))
                        d_elevation = jac.copy()
                        d_elevation[..., :3] += gain[:, None, None] * (rho_hat[:, None, :] @ d_rho)
                    if kind == "starlight":
                        value = np.concatenate([value, elevation], axis=-1)
                        jac = np.concatenate([jac, d_elevation], axis=-2) if want_jacobian else None
                    else:
                        value, jac = elevation, (d_elevation if want_jacobian else None)
            return value, jac
        if kind == "position":
            origin = (record.target or self.center).strip().lower()
            r_obs, _ = self._states(record.t_tdb_s, x)
            if origin == "ssb":
                value = r_obs
            else:
                value = r_obs - self.ephemeris.state(origin, record.t_tdb_s, center="ssb")[0]
            jac = np.broadcast_to(np.hstack([np.eye(3), np.zeros((3, 3))]), (k, 3, 6)) if want_jacobian else None
            return value, jac
        if kind == "radial_velocity":
            return self._radial_velocity(record, x, want_jacobian)
        raise InputError(f"no model for measurement kind {kind!r}")

    def _radial_velocity(self, record: Measurement, x: np.ndarray, want_jacobian: bool):
        k = x.shape[0]
        r_obs, v_obs = self._states(record.t_tdb_s, x)
        jac = np.zeros((k, 1, 6)) if want_jacobian else None
        if record.target.strip().lower() == "sun":
            r_sun, v_sun = self.ephemeris.state("sun", record.t_tdb_s, center="ssb")
            r, v = r_obs - r_sun, v_obs - v_sun
            dist = np.linalg.norm(r, axis=-1, keepdims=True)
            r_hat = r / dist
            rate = np.sum(v * r_hat, axis=-1, keepdims=True)
            if want_jacobian:
                jac[:, 0, :3] = (v - rate * r_hat) / dist
                jac[:, 0, 3:] = r_hat
            return rate, jac
        if record.star_id not in self.star_radial_velocity_km_s:
            raise InputError(
                f"no catalog radial velocity for star {record.star_id}; pass star_radial_velocity_km_s"
            )
        l_star = record.star_unit_icrf / np.linalg.norm(record.star_unit_icrf)
        value = self.star_radial_velocity_km_s[record.star_id] - v_obs @ l_star
        if want_jacobian:
            jac[:, 0, 3:] = -l_star
        return value[:, None], jac

    # ------------------------------------------------------------------ protocol
    def predict(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        """Predicted measurement: ``x`` (n,) -> (m,), or (K, n) -> (K, m); internal units.

        ``x[..., :6]`` is [r km, v km/s], ICRF, relative to :attr:`center`.
        """
        states = _as_states(x)
        value, _ = self._evaluate(record, states, want_jacobian=False)
        return value[0] if np.ndim(x) == 1 else value

    def jacobian(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        """d predict / d x at ``x`` (n,), shape (m, n); entries beyond the first six are zero."""
        if np.ndim(x) != 1:
            raise InputError(f"jacobian takes one state (n,), got shape {np.shape(x)}; use jacobians")
        return self.jacobians(record, x)[0]

    def jacobians(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        """d predict / d x for K states ``x`` (K, n) at once, shape (K, m, n) (Monte Carlo in lockstep)."""
        return self.predict_and_jacobians(record, x)[1]

    def predict_and_jacobians(self, record: Measurement, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`predict` (K, m) and :meth:`jacobians` (K, m, n) of K states (K, n) from one geometry pass."""
        states = _as_states(x)
        value, jac = self._evaluate(record, states, want_jacobian=True)
        out = np.zeros((states.shape[0], KIND_SIZE[record.kind], states.shape[1]))
        out[..., :6] = jac
        return value, out

    def residual(self, record: Measurement, predicted: np.ndarray) -> np.ndarray:
        """``record.value - predicted`` with RA wrapped to (-pi, pi]; (m,) or (K, m)."""
        res = record.value - np.asarray(predicted, dtype=float)
        slots = RA_SLOTS.get(record.kind)
        if slots:
            res = res.copy()
            res[..., slots] = wrap_angle(res[..., slots])
        return res

    def noise_covariance(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        """Measurement covariance: the record's plus the target-ephemeris error mapped to it.

        The target position error (isotropic, ``target_position_sigma_km`` per axis)
        moves the direction by sigma/|rho| rad in each transverse axis, i.e. RA by
        sigma/(|rho| cos dec), where rho (km, ICRF) runs from the probe to the target.

        Parameters
        ----------
        record : Measurement
        x : (n,) or (K, n) array
            Probe state(s) ``[r km, v km/s, ...]``, ICRF, relative to the model's centre.

        Returns
        -------
        (m, m) array for one state, (K, m, m) for K states (each run its own range: Monte Carlo
        runs in lockstep get each its own R, so a run's figures do not depend on its batch).
        """
        sigma = self.target_position_sigma_km
        if sigma == 0.0 or record.kind not in DIRECTION_KINDS + ("radec_pair",):
            return record.covariance if np.ndim(x) == 1 else np.broadcast_to(
                record.covariance, (np.shape(x)[0], *record.covariance.shape))
        # geometric range and direction suffice: the light-time change of sigma/|rho| is ~v/c
        states = _as_states(x)
        r_obs, _ = self._states(record.t_tdb_s, states)

        def geometry(target: str) -> tuple[np.ndarray, np.ndarray]:
            """Unit vectors probe -> target (K, 3) and the angle variance sigma^2/|rho|^2 (K,), rad^2."""
            rho = self.ephemeris.state(target.strip().lower(), record.t_tdb_s, center="ssb")[0] - r_obs
            distance = np.sqrt(np.einsum("ki,ki->k", rho, rho))
            return rho / distance[:, None], (sigma / distance) ** 2

        def radec_extra(target: str) -> np.ndarray:
            u, angle_var = geometry(target)
            extra = np.zeros((len(u), 2, 2))
            extra[:, 0, 0] = angle_var / (u[:, 0] ** 2 + u[:, 1] ** 2)
            extra[:, 1, 1] = angle_var
            return extra

        if record.kind == "radec_pair":  # each moon's ephemeris error is its own: no cross term
            first, second = pair_targets(record)
            extra = np.zeros((len(states), 4, 4))
            extra[:, :2, :2], extra[:, 2:, 2:] = radec_extra(first), radec_extra(second)
        elif record.kind == "radec":
            extra = radec_extra(record.target)
        elif record.kind == "los":
            u, angle_var = geometry(record.target)
            extra = angle_var[:, None, None] * (np.eye(3) - u[:, :, None] * u[:, None, :])
        elif record.kind == "target_vector":  # the whole ephemeris error, km
            extra = np.broadcast_to(np.eye(3) * sigma**2, (len(states), 3, 3))
        else:
            extra = geometry(record.target)[1][:, None, None]
        covariance = record.covariance + extra
        return covariance[0] if np.ndim(x) == 1 else covariance


def _as_states(x: np.ndarray) -> np.ndarray:
    states = np.atleast_2d(np.asarray(x, dtype=float))
    if states.ndim != 2 or states.shape[1] < 6:
        raise InputError(f"state must have shape (n,) or (K, n) with n >= 6, got {np.shape(x)}")
    if not np.all(np.isfinite(states)):
        raise InputError("state contains NaN or infinity")
    return states


def position_from_los(
    l_ps: np.ndarray,
    l_pm: np.ndarray,
    r_sun_mars_km: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """S4 eq. 1: probe position from the probe->Sun and probe->Mars lines of sight.

    Parameters
    ----------
    l_ps, l_pm : (3,) arrays
        Geometric unit vectors probe -> Sun and probe -> Mars, ICRF.
    r_sun_mars_km : (3,) array
        Mars position relative to the Sun, km, ICRF.

    Returns
    -------
    r_sun_probe_km : (3,) array
        Probe position relative to the Sun, km, ICRF.
    d_r_d_l_ps, d_r_d_l_pm : (3, 3) arrays
        Partials of ``r_sun_probe_km`` with respect to each line of sight (km per unit).

    Notes
    -----
    Law of sines in the Sun-probe-Mars triangle: with a = l_sm . l_pm and
    b = l_ps . l_pm, ``r = -|r_sm| sqrt((1 - a^2)/(1 - b^2)) l_ps = -k l_ps``.
    Partials: dk/dl_ps = k b/(1-b^2) l_pm^T, dk/dl_pm = k (b/(1-b^2) l_ps - a/(1-a^2) l_sm)^T,
    so dr/dl_ps = -k I - l_ps dk/dl_ps and dr/dl_pm = -l_ps dk/dl_pm.
    """
    l_ps = np.asarray(l_ps, dtype=float)
    l_pm = np.asarray(l_pm, dtype=float)
    r_sm = np.asarray(r_sun_mars_km, dtype=float)
    for name, vec in (("l_ps", l_ps), ("l_pm", l_pm), ("r_sun_mars_km", r_sm)):
        if vec.shape != (3,) or not np.all(np.isfinite(vec)):
            raise InputError(f"{name} must be a finite (3,) vector, got {vec!r}")
    dist_sm = np.linalg.norm(r_sm)
    l_sm = r_sm / dist_sm
    a = float(l_sm @ l_pm)
    b = float(l_ps @ l_pm)
    if 1.0 - b * b < 1e-12:
        raise InputError("lines of sight to the Sun and Mars are parallel: position is unobservable")
    k = dist_sm * np.sqrt((1.0 - a * a) / (1.0 - b * b))
    r = -k * l_ps
    dk_dps = k * b / (1.0 - b * b) * l_pm
    dk_dpm = k * (b / (1.0 - b * b) * l_ps - a / (1.0 - a * a) * l_sm)
    d_ps = -k * np.eye(3) - np.outer(l_ps, dk_dps)
    d_pm = -np.outer(l_ps, dk_dpm)
    return r, d_ps, d_pm


def position_measurement(
    t_tdb_s: float,
    l_ps: np.ndarray,
    cov_ps: np.ndarray,
    l_pm: np.ndarray,
    cov_pm: np.ndarray,
    *,
    ephemeris=None,
    light_time: bool = True,
    sensor: str = "",
    iterations: int = 3,
) -> Measurement:
    """A ``position`` :class:`~opnav.records.Measurement` (origin Sun) from two lines of sight (S4 eq. 1).

    Parameters
    ----------
    t_tdb_s : float
        Reception epoch, TDB seconds past J2000.
    l_ps, l_pm : (3,) arrays
        Geometric (aberration removed) unit lines of sight probe -> Sun and probe -> Mars, ICRF.
    cov_ps, cov_pm : (3, 3) arrays
        Their covariances (unitless^2; rank 2, transverse to the line of sight).
    ephemeris : Ephemeris-like, optional
        Gives the Sun -> Mars vector; default :func:`opnav.ephemeris.default_ephemeris`.
    light_time : bool
        Use Sun and Mars at their emission epochs (fixed point on the solved range);
        without it the ~500 s light time moves Mars by ~10,000 km.

    Returns
    -------
    Measurement
        kind ``position``, target ``sun``; covariance ``J_ps cov_ps J_ps^T + J_pm cov_pm J_pm^T``.
    """
    eph = ephemeris if ephemeris is not None else default_ephemeris()
    cov_ps = np.asarray(cov_ps, dtype=float)
    cov_pm = np.asarray(cov_pm, dtype=float)
    if cov_ps.shape != (3, 3) or cov_pm.shape != (3, 3):
        raise InputError("cov_ps and cov_pm must be 3x3")
    l_ps = np.asarray(l_ps, dtype=float) / np.linalg.norm(l_ps)
    l_pm = np.asarray(l_pm, dtype=float) / np.linalg.norm(l_pm)
    tau_s = tau_m = 0.0
    for _ in range(iterations if light_time else 1):
        r_sun = eph.state("sun", t_tdb_s - tau_s, center="ssb")[0]
        r_mars = eph.state("mars", t_tdb_s - tau_m, center="ssb")[0]
        r, d_ps, d_pm = position_from_los(l_ps, l_pm, r_mars - r_sun)
        # r is relative to the Sun at emission; ranges give the next light times
        tau_s = np.linalg.norm(r) / C_KM_S
        tau_m = np.linalg.norm(r_mars - r_sun - r) / C_KM_S
    r_sun_now = eph.state("sun", t_tdb_s, center="ssb")[0]
    r_sun_probe = r + r_sun - r_sun_now
    cov = d_ps @ cov_ps @ d_ps.T + d_pm @ cov_pm @ d_pm.T
    return Measurement(t_tdb_s=t_tdb_s, kind="position", value=r_sun_probe, covariance=0.5 * (cov + cov.T),
                       target="sun", sensor=sensor)


def simulate_radec(
    model: ProbeMeasurementModel,
    target: str,
    t_tdb_s: np.ndarray,
    states: np.ndarray,
    *,
    sigma_rad: float,
    rng: np.random.Generator,
    target_offset_km: np.ndarray | None = None,
) -> np.ndarray:
    """Noisy apparent RA/Dec (N, 2) rad of ``target`` from true probe states, vectorised over epochs.

    Parameters
    ----------
    model : ProbeMeasurementModel
        Supplies the central body, ephemeris and the light-time/aberration switches.
    target : str
        Observed body.
    t_tdb_s : (N,) array
        Epochs, TDB s past J2000.
    states : (N, 6) array
        True probe states [r km, v km/s], ICRF, relative to ``model.center``.
    sigma_rad : float
        1-sigma Gaussian noise added to RA and to Dec (S1's noise model; the record
        covariance is ``sigma_rad^2 I``).
    rng : numpy.random.Generator
    target_offset_km : (3,) or (N, 3) array, optional
        Error of the filter's ephemeris: the truth target sits at ephemeris + offset (ICRF km);
        (3,) is a constant bias, (N, 3) one offset per epoch.

    Notes
    -----
    Uses :func:`opnav.light.apparent_direction`, the renderer's path, so the filter model
    (which calls the same light-time and aberration functions) is unbiased against it.
    """
    from .light import apparent_direction

    t = np.asarray(t_tdb_s, dtype=float)
    x = np.asarray(states, dtype=float)
    if x.shape != t.shape + (6,):
        raise InputError(f"states must have shape {t.shape + (6,)}, got {x.shape}")
    if not (np.isfinite(sigma_rad) and sigma_rad > 0.0):
        raise InputError(f"sigma_rad must be positive, got {sigma_rad!r}")
    offset = np.zeros(3) if target_offset_km is None else np.asarray(target_offset_km, dtype=float)
    key = target.strip().lower()
    if model.center == "ssb":
        r_obs, v_obs = x[:, :3], x[:, 3:]
    else:
        r_c, v_c = model.ephemeris.state(model.center, t, center="ssb")
        r_obs, v_obs = r_c + x[:, :3], v_c + x[:, 3:]
    direction = apparent_direction(lambda tt: model.ephemeris.state(key, tt, center="ssb")[0] + offset, t, r_obs, v_obs,
                                   light_time=model.light_time, aberration=model.aberration)
    ra, dec = unit_to_radec(direction)
    noise = rng.normal(0.0, sigma_rad, size=(t.size, 2))
    return np.stack([np.mod(ra + noise[:, 0], 2.0 * np.pi), dec + noise[:, 1]], axis=-1)


def starlight_covariance(sigma_star_rad: float, sigma_target_rad: float) -> np.ndarray:
    """Covariance (2, 2) rad^2 of [starlight angle, starlight elevation] from the two sensors' errors.

    The angle's error is the star-direction error plus the target-centre error along the arc
    between them (``sigma_star^2 + sigma_target^2``); the elevation subtracts the target's
    apparent radius, measured by the same target sensor with its own error ``sigma_target``,
    so it repeats the angle's error and adds ``sigma_target^2``. The two share everything
    the angle has: treating them as independent scalars counts that information twice.

    Parameters
    ----------
    sigma_star_rad : float
        1-sigma star-direction error per transverse axis (star sensor), rad.
    sigma_target_rad : float
        1-sigma target-centre (and apparent-radius) error of the target sensor, rad.
    """
    if not (np.isfinite(sigma_star_rad) and sigma_star_rad >= 0.0 and np.isfinite(sigma_target_rad)
            and sigma_target_rad > 0.0):
        raise InputError(f"sensor sigmas must be finite, star >= 0 and target > 0; got {sigma_star_rad!r}, "
                         f"{sigma_target_rad!r}")
    angle = sigma_star_rad**2 + sigma_target_rad**2
    return np.array([[angle, angle], [angle, angle + sigma_target_rad**2]])


def simulate_starlight(
    model: ProbeMeasurementModel,
    target: str,
    t_tdb_s: np.ndarray,
    states: np.ndarray,
    star_unit_icrf: np.ndarray,
    *,
    sigma_star_rad: float,
    sigma_target_rad: float,
    rng: np.random.Generator,
    vector: bool = True,
    sensor: str = "",
    covariance: np.ndarray | None = None,
) -> list[Measurement]:
    """Noisy starlight angle and elevation records of one star (S3's measurement, eq. 4).

    The noise is drawn from :func:`starlight_covariance` (correlated), or from ``covariance``
    when given. ``vector`` True gives one
    ``starlight`` record per epoch carrying that 2x2 covariance; False gives the
    ``starlight_angle`` and ``starlight_elevation`` scalar records with its diagonal, what a
    pipeline that ignores the correlation would emit (same values, same marginal noise).

    Parameters
    ----------
    model : ProbeMeasurementModel
        Truth model (centre, corrections, body radius).
    target : str
        The body whose centre and limb are measured (``"earth"`` in S3).
    t_tdb_s : (N,) array
        Epochs, TDB s past J2000.
    states : (N, 6) array
        True probe states [r km, v km/s], ICRF, relative to ``model.center``.
    star_unit_icrf : (3,) array
        Unit direction of the star, ICRF.
    sigma_star_rad, sigma_target_rad : float
        Sensor errors (:func:`starlight_covariance`), rad.
    rng : numpy.random.Generator
    vector : bool
    sensor : str
        Written into each record.
    covariance : (2, 2) array, optional
        Noise covariance of [angle, elevation], rad^2, instead of the sensors' (e.g. a study's
        own independent noises on the two).
    """
    t = np.asarray(t_tdb_s, dtype=float)
    x = np.asarray(states, dtype=float)
    if x.shape != t.shape + (6,):
        raise InputError(f"states must have shape {t.shape + (6,)}, got {x.shape}")
    if covariance is None:
        cov = starlight_covariance(sigma_star_rad, sigma_target_rad)
    else:
        cov = np.asarray(covariance, dtype=float)
        if cov.shape != (2, 2) or not np.all(np.isfinite(cov)) or not np.allclose(cov, cov.T):
            raise InputError(f"starlight covariance must be a finite symmetric 2x2 array, got {cov!r}")
    star = np.asarray(star_unit_icrf, dtype=float)
    records = []
    noise = rng.standard_normal((t.size, 2)) @ np.linalg.cholesky(cov).T
    for epoch, state, e in zip(t, x, noise):
        template = Measurement(epoch, "starlight", np.zeros(2), cov, target=target, star_unit_icrf=star,
                               sensor=sensor)
        value = model.predict(template, state) + e
        if vector:
            records.append(Measurement(epoch, "starlight", value, cov, target=target, star_unit_icrf=star,
                                       sensor=sensor))
        else:
            for j, kind in enumerate(("starlight_angle", "starlight_elevation")):
                records.append(Measurement(epoch, kind, value[j:j + 1], cov[j:j + 1, j:j + 1], target=target,
                                           star_unit_icrf=star, sensor=sensor))
    return records


class _AugmentedModel:
    """What a measurement model over an augmented state shares: the wrapped ``model``'s residual, and
    its noise covariance at the inner states (``_inner(record, x)``: (K, n0) states of ``model``);
    Jacobians from the subclass's ``predict_and_jacobians``."""

    def jacobian(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        """d(measurement)/d(state) (m, n) at one augmented state (n,)."""
        if np.ndim(x) != 1:
            raise InputError(f"jacobian takes one state (n,), got shape {np.shape(x)}; use jacobians")
        return self.predict_and_jacobians(record, x)[1][0]

    def jacobians(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        """d(measurement)/d(state) (K, m, n) of K augmented states (K, n)."""
        return self.predict_and_jacobians(record, x)[1]

    def residual(self, record: Measurement, predicted: np.ndarray) -> np.ndarray:
        return self.model.residual(record, predicted)

    def noise_covariance(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        """The wrapped model's measurement covariance at the inner state(s): x (n,) gives (m, m), x (K, n)
        gives (K, m, m)."""
        inner = self._inner(record, x)
        return self.model.noise_covariance(record, inner[0] if np.ndim(x) == 1 else inner)


class TargetOffsetModel(_AugmentedModel):
    """A :class:`ProbeMeasurementModel` over states augmented with constant target-ephemeris offsets.

    The state is ``[r (3) km, v (3) km/s, d_1 (3) km, ..., d_T (3) km]``: probe position and
    velocity (ICRF, relative to ``model.center``) then, for each of ``targets``, the offset of
    its true position from the ephemeris (ICRF km): what a moon-ephemeris error is over an arc
    (a near-constant displacement), unlike the white term of
    ``ProbeMeasurementModel.target_position_sigma_km``. A filter estimates the offsets as
    states, or holds them as consider parameters (:class:`opnav.filters.ekf.EKFOptions`).

    Moving the target by ``d`` moves its direction as moving the probe by ``-d`` does (light
    time changes by ``|d|/c``, microseconds for kilometres, and aberration depends on the
    velocity only), so predictions shift the probe position and ``dh/dd = -dh/dr``.

    Parameters
    ----------
    model : ProbeMeasurementModel
        The measurement model (its own ``target_position_sigma_km`` should be 0: the error is
        in the state now).
    targets : sequence of str
        Bodies whose offsets are appended to the state, in this order.
    """

    def __init__(self, model: ProbeMeasurementModel, targets):
        self.model = model
        self.center = model.center
        self.targets = tuple(str(t).strip().lower() for t in targets)
        if not self.targets or len(set(self.targets)) != len(self.targets):
            raise InputError(f"TargetOffsetModel needs distinct targets, got {targets!r}")
        self.size = 6 + 3 * len(self.targets)

    def _shifted(self, record: Measurement, x: np.ndarray) -> tuple[np.ndarray, int | None]:
        """Probe states (K, 6) with the record target's offset applied, and that offset's first index."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if x.shape[-1] != self.size:
            raise InputError(f"states must have {self.size} entries ([r, v] + 3 per target of {self.targets}), "
                             f"got {x.shape[-1]}")
        target = record.target.strip().lower()
        six = x[:, :6].copy()
        if target not in self.targets:
            return six, None
        first = 6 + 3 * self.targets.index(target)
        six[:, :3] -= x[:, first:first + 3]
        return six, first

    def predict(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        """Predicted measurement of (n,) or (K, n) augmented states; internal units."""
        single = np.ndim(x) == 1
        value = self.model.predict(record, self._shifted(record, x)[0])
        return value[0] if single else value

    def predict_and_jacobians(self, record: Measurement, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predictions (K, m) and Jacobians (K, m, n) of K augmented states from one geometry pass."""
        six, first = self._shifted(record, x)
        value, jac6 = self.model.predict_and_jacobians(record, six)
        jac = np.zeros(jac6.shape[:2] + (self.size,))
        jac[..., :6] = jac6[..., :6]
        if first is not None:
            jac[..., first:first + 3] = -jac6[..., :3]
        return value, jac

    def _inner(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        return self._shifted(record, x)[0]


class CameraOffsetModel(_AugmentedModel):
    """A measurement model over states augmented with the camera's parameter errors (issue 39).

    The state is ``[x_model (n0), dc (P)]``: the wrapped model's state (``[r km, v km/s, ...]``, ICRF,
    relative to ``model.center``) then ``dc``, the error of the camera the image stage measured with
    (its parameters ``names`` minus the true camera's, in their units: ``f``, ``cx``, ``cy`` px;
    Brown coefficients dimensionless). A record measured against its frame's stars moves with it by
    ``J dc``, ``J`` = d(value)/d(parameters) relative to the stars, which the image stage keeps in the
    record (:data:`opnav.records.CAMERA_JACOBIAN`): so ``h(x, dc) = h_model(x) + J dc`` and the
    Jacobian's block for ``dc`` is ``J`` (a record without one, or of another kind: zeros). ``dc`` is
    the same in every frame: a filter holds it as consider parameters (Schmidt), with the calibration's
    covariance as their prior (:class:`opnav.filters.ekf.EKFOptions`), so its error is one shared bias
    over the arc, not white noise at every record.

    Parameters
    ----------
    model : measurement model
        The wrapped model (:class:`ProbeMeasurementModel`, or :class:`TargetOffsetModel` whose ``size``
        gives its state's length; 6 otherwise).
    names : sequence of str
        The camera parameters appended to the state, in this order (the camera file's
        ``[calibration] parameters``). A record's Jacobian columns are matched by name; a record
        naming a parameter not among them raises :class:`~opnav.errors.InputError`.
    """

    def __init__(self, model, names):
        self.model = model
        self.center = model.center
        self.names = tuple(str(n) for n in names)
        if not self.names or len(set(self.names)) != len(self.names):
            raise InputError(f"CameraOffsetModel needs distinct camera parameter names, got {names!r}")
        self.first = int(getattr(model, "size", 6))
        self.size = self.first + len(self.names)
        self._columns: dict = {}

    def camera_block(self, record: Measurement) -> np.ndarray:
        """d(value)/d(dc) of ``record``, (m, P): its stored Jacobian's columns placed by name, else zeros."""
        from .records import camera_jacobian

        block = np.zeros((record.size, len(self.names)))
        found = camera_jacobian(record)
        if found is None:
            return block
        names, jac = found
        columns = self._columns.get(names)
        if columns is None:
            missing = [n for n in names if n not in self.names]
            if missing:
                raise InputError(f"a {record.kind} record at TDB {record.t_tdb_s:.3f} s carries a camera Jacobian of "
                                 f"{', '.join(missing)}, which the camera's calibration ({', '.join(self.names)}) "
                                 "does not have")
            columns = self._columns[names] = np.array([self.names.index(n) for n in names])
        block[:, columns] = jac
        return block

    def _split(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if x.shape[-1] != self.size:
            raise InputError(f"states must have {self.size} entries ({self.first} + the camera's "
                             f"{', '.join(self.names)}), got {x.shape[-1]}")
        return x[:, :self.first], x[:, self.first:]

    def predict(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        """Predicted measurement of (n,) or (K, n) augmented states; internal units."""
        inner, dc = self._split(x)
        value = self.model.predict(record, inner) + dc @ self.camera_block(record).T
        return value[0] if np.ndim(x) == 1 else value

    def predict_and_jacobians(self, record: Measurement, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predictions (K, m) and Jacobians (K, m, n) of K augmented states from one geometry pass."""
        inner, dc = self._split(x)
        value, jac_inner = self.model.predict_and_jacobians(record, inner)
        block = self.camera_block(record)
        jac = np.zeros(jac_inner.shape[:2] + (self.size,))
        jac[..., :self.first] = jac_inner[..., :self.first]
        jac[..., self.first:] = block
        return value + dc @ block.T, jac

    def _inner(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        return self._split(x)[0]
