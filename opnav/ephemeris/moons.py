"""Phobos and Deimos: a precessing-ellipse mean-element model and a user-SPK reader.

Both classes answer ``state(name, t) -> (r, v)``: the **Mars-centred** ICRF
position (km) and velocity (km/s) of ``"phobos"`` or ``"deimos"`` at TDB
seconds past J2000 (scalar -> (3,), (N,) -> (N, 3)).

Mean-element model (:class:`MeanElementMoons`), step by step
----------------------------------------------------------
1. Elements are JPL's mean elements of solution MAR080 (Jacobson 2010, AJ 139,
   668), referred to each moon's Laplace plane, epoch 1950-01-01.0 TT.
2. Rates, as read from the table (periods in Julian years):

   - the argument of periapsis advances (prograde): ``dw/dt = +2 pi / P_w``;
   - the node regresses: ``dnode/dt = -2 pi / P_node``;
   - ``n`` is the rate of the mean longitude ``lambda = node + w + M`` (it
     equals 2 pi over the sidereal period), so the mean anomaly advances at
     ``dM/dt = n - dw/dt - dnode/dt``. ``lambda`` and the longitude of
     periapsis ``varpi = node + w`` are propagated linearly and ``M = lambda - varpi``:
     an error in the (4-digit) precession periods then only turns the small
     ellipse and never moves the moon along its orbit.
3. Kepler's equation ``M = E - e sin E`` is solved by vectorised Newton
   iteration; the perifocal position is ``a (cos E - e, sqrt(1 - e^2) sin E, 0)``.
   The size comes from the tabulated ``a`` and the angle from the tabulated ``n``
   (they differ from Kepler's third law with GM_Mars by the J2 term, ~4e-4).
4. Perifocal -> Laplace frame by ``Rz(node) Rx(i) Rz(w)``; Laplace frame ->
   ICRF by ``Rz(ra_pole + 90 deg) Rx(90 deg - dec_pole)``: the Laplace frame's
   x axis is the ascending node of the Laplace plane on the ICRF equator, its z
   axis the Laplace pole.
5. Velocity is the exact time derivative of that position, element rates
   included: ``v = R (dr_pf/dM) dM/dt + dnode/dt (p x r) + dw/dt (h x r)``,
   with ``p`` the Laplace pole and ``h`` the orbit normal (both ICRF).

The model neglects Phobos' tidal secular acceleration and the short-period
perturbations, which is why it agrees with full ephemerides (e.g. the BDL
theory behind PyEphem) only at the ~100 km level.

User SPK (:class:`SpkMoons`): a kernel such as JPL ``mar099.bsp`` holding
segments Mars barycentre (4) -> Phobos (401), Deimos (402) and Mars (499);
the Mars-centred state is ``(4 -> 40x) - (4 -> 499)``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from erfa import ErfaWarning
from jplephem.spk import SPK

from ..constants import DAY_S, DEG_RAD, JULIAN_YEAR_S
from ..epochs import J2000_JD, describe_epoch, parse_epoch
from ..errors import ConvergenceError, EphemerisError, InputError

# ERFA calls 1950 a "dubious year" because UTC had no leap-second table then; the
# UT1 it feeds into TDB - TT changes that difference by microseconds only.
with warnings.catch_warnings():
    warnings.simplefilter("ignore", ErfaWarning)
    #: Epoch of the MAR080 mean elements, 1950-01-01T00:00:00 TT, in TDB seconds past J2000.
    MAR080_EPOCH_TDB_S = parse_epoch("1950-01-01T00:00:00", scale="tt")

#: NAIF ids in a Mars-system SPK.
MARS_BARYCENTER_ID = 4
MARS_ID = 499
MOON_NAIF_ID = {"phobos": 401, "deimos": 402}


def _moon_key(name: str) -> str:
    key = str(name).strip().lower()
    if key not in MOON_NAIF_ID:
        raise EphemerisError(f"unknown moon {name!r}; expected one of {', '.join(MOON_NAIF_ID)}")
    return key


@dataclass(frozen=True)
class MeanElements:
    """Mean elements of one moon on its Laplace plane, internal units.

    Attributes
    ----------
    a_km : float
        Semi-major axis, km.
    e : float
        Eccentricity, 0 <= e < 1.
    w_rad, mean_anomaly_rad, i_rad, node_rad : float
        Argument of periapsis, mean anomaly, inclination to the Laplace plane and
        node (measured on the Laplace plane from its ascending node on the ICRF
        equator) at ``epoch_tdb_s``, rad.
    n_rad_s : float
        Rate of the mean longitude node + w + M, rad/s.
    w_rate_rad_s, node_rate_rad_s : float
        Rates of w (apsidal advance, > 0) and of the node (regression, < 0), rad/s.
    pole_ra_rad, pole_dec_rad : float
        ICRF right ascension and declination of the Laplace-plane pole, rad.
    epoch_tdb_s : float
        Epoch of the elements, TDB seconds past J2000.
    """

    a_km: float
    e: float
    w_rad: float
    mean_anomaly_rad: float
    i_rad: float
    node_rad: float
    n_rad_s: float
    w_rate_rad_s: float
    node_rate_rad_s: float
    pole_ra_rad: float
    pole_dec_rad: float
    epoch_tdb_s: float

    def __post_init__(self) -> None:
        values = {name: getattr(self, name) for name in self.__dataclass_fields__}
        for name, value in values.items():
            if not np.isfinite(value):
                raise InputError(f"mean element {name} must be finite, got {value!r}")
        if self.a_km <= 0.0:
            raise InputError(f"mean element a_km must be positive, got {self.a_km!r}")
        if not 0.0 <= self.e < 1.0:
            raise InputError(f"mean element e must be in [0, 1), got {self.e!r}")
        if self.n_rad_s <= 0.0:
            raise InputError(f"mean element n_rad_s must be positive, got {self.n_rad_s!r}")
        if abs(self.pole_dec_rad) > np.pi / 2:
            raise InputError(f"mean element pole_dec_rad must be within +-pi/2, got {self.pole_dec_rad!r}")

    @classmethod
    def from_jpl_table(
        cls,
        *,
        a_km: float,
        e: float,
        w_deg: float,
        mean_anomaly_deg: float,
        i_deg: float,
        node_deg: float,
        n_deg_day: float,
        apsidal_period_yr: float,
        node_period_yr: float,
        pole_ra_deg: float,
        pole_dec_deg: float,
        epoch_tdb_s: float,
    ) -> "MeanElements":
        """Build from the units of JPL's mean-element tables (deg, deg/day, Julian years).

        The node period is that of its regression: the node rate is ``-360 deg / P_node``.
        """
        for name, period in (("apsidal_period_yr", apsidal_period_yr), ("node_period_yr", node_period_yr)):
            if not period > 0.0:
                raise InputError(f"{name} must be positive, got {period!r}")
        return cls(
            a_km=a_km,
            e=e,
            w_rad=w_deg * DEG_RAD,
            mean_anomaly_rad=mean_anomaly_deg * DEG_RAD,
            i_rad=i_deg * DEG_RAD,
            node_rad=node_deg * DEG_RAD,
            n_rad_s=n_deg_day * DEG_RAD / DAY_S,
            w_rate_rad_s=2.0 * np.pi / (apsidal_period_yr * JULIAN_YEAR_S),
            node_rate_rad_s=-2.0 * np.pi / (node_period_yr * JULIAN_YEAR_S),
            pole_ra_rad=pole_ra_deg * DEG_RAD,
            pole_dec_rad=pole_dec_deg * DEG_RAD,
            epoch_tdb_s=epoch_tdb_s,
        )

    @property
    def mean_anomaly_rate_rad_s(self) -> float:
        """dM/dt = n - dw/dt - dnode/dt, rad/s."""
        return self.n_rad_s - self.w_rate_rad_s - self.node_rate_rad_s

    @property
    def R_icrf_laplace(self) -> np.ndarray:
        """Rotation Laplace frame -> ICRF, (3, 3): x = ascending node on the ICRF equator, z = pole."""
        return _rotation_z(self.pole_ra_rad + np.pi / 2) @ _rotation_x(np.pi / 2 - self.pole_dec_rad)


#: JPL mean elements of solution MAR080 (Jacobson 2010), epoch 1950-01-01.0 TT.
MAR080 = {
    "phobos": MeanElements.from_jpl_table(
        a_km=9376.0, e=0.0151, w_deg=150.057, mean_anomaly_deg=91.059, i_deg=1.075, node_deg=207.784,
        n_deg_day=1128.8447569, apsidal_period_yr=1.1316, node_period_yr=2.2617,
        pole_ra_deg=317.671, pole_dec_deg=52.893, epoch_tdb_s=MAR080_EPOCH_TDB_S,
    ),
    "deimos": MeanElements.from_jpl_table(
        a_km=23458.0, e=0.0002, w_deg=260.729, mean_anomaly_deg=325.329, i_deg=1.788, node_deg=24.525,
        n_deg_day=285.1618790, apsidal_period_yr=27.3703, node_period_yr=54.5367,
        pole_ra_deg=316.657, pole_dec_deg=53.529, epoch_tdb_s=MAR080_EPOCH_TDB_S,
    ),
}


def _rotation_x(angle: np.ndarray | float) -> np.ndarray:
    """Active rotation by ``angle`` about x, (..., 3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    zero, one = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([one, zero, zero], -1), np.stack([zero, c, -s], -1), np.stack([zero, s, c], -1)], -2)


def _rotation_z(angle: np.ndarray | float) -> np.ndarray:
    """Active rotation by ``angle`` about z, (..., 3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    zero, one = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, zero], -1), np.stack([s, c, zero], -1), np.stack([zero, zero, one], -1)], -2)


def solve_kepler(
    mean_anomaly_rad: np.ndarray | float, e: float, *, tolerance_rad: float = 1e-14, max_iterations: int = 30
) -> np.ndarray:
    """Eccentric anomaly E (rad) with ``E - e sin E = M``, elementwise (Newton's method).

    Parameters
    ----------
    mean_anomaly_rad : float or array
        Mean anomaly M, rad, any value (not reduced first).
    e : float
        Eccentricity, 0 <= e < 1.

    Raises
    ------
    InputError
        For an eccentricity outside [0, 1).
    ConvergenceError
        If Newton's method has not converged after ``max_iterations`` steps.

    Notes
    -----
    M is reduced to [-pi, pi) and Newton's method starts from E0 = M + e sin M
    (Vallado 2013, Sec. 2.2, Algorithm 2, starts from M +- e instead). The whole
    revolutions removed from M are added back, so E - M stays periodic.
    """
    if not 0.0 <= e < 1.0:
        raise InputError(f"eccentricity e must be in [0, 1), got {e!r}")
    m = np.asarray(mean_anomaly_rad, dtype=float)
    revolutions = m - (np.mod(m + np.pi, 2.0 * np.pi) - np.pi)
    m_reduced = m - revolutions
    ecc = m_reduced + e * np.sin(m_reduced)
    for _ in range(max_iterations):
        step = (ecc - e * np.sin(ecc) - m_reduced) / (1.0 - e * np.cos(ecc))
        ecc = ecc - step
        if np.all(np.abs(step) < tolerance_rad):
            return ecc + revolutions
    raise ConvergenceError(f"Kepler's equation did not converge in {max_iterations} Newton steps (e={e})")


class MeanElementMoons:
    """Phobos and Deimos from precessing mean ellipses on their Laplace planes.

    Parameters
    ----------
    elements : dict of str -> MeanElements, optional
        Per-moon elements; default :data:`MAR080`.
    """

    def __init__(self, elements: dict[str, MeanElements] | None = None):
        self.elements = dict(MAR080 if elements is None else elements)

    def state(self, name: str, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mars-centred position (km) and velocity (km/s) of a moon, ICRF.

        Parameters
        ----------
        name : {"phobos", "deimos"}
            Case-insensitive.
        t : float or (N,) array
            TDB seconds past J2000.

        Returns
        -------
        r_mars_moon_km, v_mars_moon_km_s : (3,) or (N, 3) arrays
            Relative to the centre of Mars, ICRF.

        Raises
        ------
        EphemerisError
            For an unknown moon or a non-finite epoch.
        """
        key = _moon_key(name)
        if key not in self.elements:
            raise EphemerisError(f"moon {name!r} has no mean elements in this model")
        el = self.elements[key]
        t_arr = np.asarray(t, dtype=float)
        if t_arr.ndim > 1:
            raise EphemerisError(f"epochs t must be a scalar or 1-D array, got shape {t_arr.shape}")
        if not np.all(np.isfinite(t_arr)):
            raise EphemerisError("epoch t is NaN or infinite")
        dt = t_arr - el.epoch_tdb_s
        node = el.node_rad + el.node_rate_rad_s * dt
        w = el.w_rad + el.w_rate_rad_s * dt
        mean_anomaly_rate = el.mean_anomaly_rate_rad_s
        ecc_anomaly = solve_kepler(el.mean_anomaly_rad + mean_anomaly_rate * dt, el.e)

        cos_e, sin_e = np.cos(ecc_anomaly), np.sin(ecc_anomaly)
        root = np.sqrt(1.0 - el.e**2)
        zeros = np.zeros_like(cos_e)
        r_pf = el.a_km * np.stack([cos_e - el.e, root * sin_e, zeros], axis=-1)
        e_dot = mean_anomaly_rate / (1.0 - el.e * cos_e)
        v_pf = el.a_km * e_dot[..., None] * np.stack([-sin_e, root * cos_e, zeros], axis=-1)

        R_icrf_pf = el.R_icrf_laplace @ _rotation_z(node) @ _rotation_x(el.i_rad) @ _rotation_z(w)
        r = np.einsum("...ij,...j->...i", R_icrf_pf, r_pf)
        pole = el.R_icrf_laplace[:, 2]
        normal = R_icrf_pf[..., :, 2]
        v = (
            np.einsum("...ij,...j->...i", R_icrf_pf, v_pf)
            + el.node_rate_rad_s * np.cross(pole, r)
            + el.w_rate_rad_s * np.cross(normal, r)
        )
        return r, v


class SpkMoons:
    """Phobos and Deimos from a user SPK kernel (e.g. JPL ``mar099.bsp``) via jplephem.

    Parameters
    ----------
    path : str or Path
        SPK file with segments 4 -> 401 and/or 4 -> 402, and 4 -> 499.

    Raises
    ------
    EphemerisError
        If the file is missing, unreadable, or has no 4 -> 499 segment.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise EphemerisError(f"moon SPK kernel not found: {self.path}")
        try:
            self._kernel = SPK.open(str(self.path))
        except Exception as exc:
            raise EphemerisError(f"cannot read moon SPK kernel {self.path}: {exc}") from None
        # A kernel may split one body's arc over several segments; keep them all.
        self._segments: dict[int, list] = {}
        for segment in self._kernel.segments:
            if segment.center == MARS_BARYCENTER_ID:
                self._segments.setdefault(segment.target, []).append(segment)
        if MARS_ID not in self._segments:
            raise EphemerisError(f"moon SPK kernel {self.path.name} has no Mars barycentre (4) -> Mars (499) segment")

    def _barycentric(self, naif: int, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """State of ``naif`` relative to the Mars barycentre, ICRF, km and km/s, (N, 3)."""
        r = np.full(t.shape + (3,), np.nan)
        v = np.full(t.shape + (3,), np.nan)
        jd = J2000_JD + t / DAY_S
        for segment in self._segments[naif]:
            inside = (jd >= segment.start_jd) & (jd <= segment.end_jd) & np.isnan(r[:, 0])
            if np.any(inside):
                position, velocity_per_day = segment.compute_and_differentiate(J2000_JD, t[inside] / DAY_S)
                r[inside] = np.asarray(position).T
                v[inside] = np.asarray(velocity_per_day).T / DAY_S
        if np.any(np.isnan(r[:, 0])):
            bad = t[np.isnan(r[:, 0])][0]
            raise EphemerisError(
                f"epoch {describe_epoch(bad)} is outside the coverage of NAIF {naif} in {self.path.name}"
            )
        return r, v

    def state(self, name: str, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mars-centred position (km) and velocity (km/s) of a moon, ICRF.

        Parameters
        ----------
        name : {"phobos", "deimos"}
            Case-insensitive.
        t : float or (N,) array
            TDB seconds past J2000.

        Returns
        -------
        r_mars_moon_km, v_mars_moon_km_s : (3,) or (N, 3) arrays

        Raises
        ------
        EphemerisError
            Unknown moon, moon absent from the kernel, or epoch outside its coverage.
        """
        naif = MOON_NAIF_ID[_moon_key(name)]
        if naif not in self._segments:
            raise EphemerisError(f"moon SPK kernel {self.path.name} has no segment 4 -> {naif} ({name})")
        t_arr = np.atleast_1d(np.asarray(t, dtype=float))
        if t_arr.ndim != 1:
            raise EphemerisError(f"epochs t must be a scalar or 1-D array, got shape {np.shape(t)}")
        if not np.all(np.isfinite(t_arr)):
            raise EphemerisError("epoch t is NaN or infinite")
        r_moon, v_moon = self._barycentric(naif, t_arr)
        r_mars, v_mars = self._barycentric(MARS_ID, t_arr)
        r, v = r_moon - r_mars, v_moon - v_mars
        if np.ndim(t) == 0:
            return r[0], v[0]
        return r, v
