"""Low-degree Earth geopotential (J2, J3, J4, C/S22, C/S31, C/S33) with analytic Hessian.

Algorithm
---------
1. Rotate the ICRF position into the Earth-fixed frame by a z-rotation of the
   Earth rotation angle (IAU 2000 ERA of UT1). Precession, nutation and polar
   motion are neglected, so the body-fixed frame is off by up to the
   accumulated precession since J2000 (about 50"/yr) -- adequate for the
   low-degree field of S3, and stated wherever the term is used.
2. Evaluate Cunningham's functions ``V_nm``, ``W_nm`` (Montenbruck & Gill 2000,
   eqs. 3.29-3.31) by their recursions, vectorised over K positions.
3. The potential is ``U = GM/R sum (C_nm V_nm + S_nm W_nm)``. M&G eq. 3.33
   writes each Cartesian derivative of ``C V + S W`` at degree n as a linear
   combination of ``V``/``W`` at degree n + 1. That map is linear in the
   coefficients, so applying it once gives the acceleration and applying it
   twice gives the Hessian, each as a fixed coefficient table contracted with
   ``V``/``W`` up to degree n_max + 2. The tables are built once per term.
4. Rotate the gradient and Hessian back to ICRF.

The monopole is left out (``C_00 = 0``): :class:`~opnav.dynamics.forces.CentralGravity`
carries it. Coefficients are unnormalised with ``J_n = -C_n0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..constants import DAY_S
from ..errors import InputError

#: Highest degree this term carries (J4); the recursion runs to _DEGREE + 2 (LEGENDRE_SIZE rows).
_DEGREE = 4
LEGENDRE_SIZE = _DEGREE + 3
#: (2m - 1)!! for m = 0, 1, ... (with (-1)!! = 1).
DOUBLE_FACTORIAL = np.array([float(math.prod(range(2 * m - 1, 0, -2))) for m in range(16)])
#: Zonal-recursion factors (2n-1)/(n-m) and (n+m-1)/(n-m) for m < n, precomputed as floats
#: because building them per call dominated the cost of a single evaluation.
LEGENDRE_ROW_A = [(2 * n - 1) / (n - np.arange(n)) for n in range(16)]
LEGENDRE_ROW_B = [(n + np.arange(n) - 1) / (n - np.arange(n)) for n in range(16)]


def earth_rotation_angle(t_tdb_s: float, tdb_minus_ut1_s: float) -> float:
    """IAU 2000 Earth rotation angle (rad, in [0, 2pi)) at TDB seconds past J2000.

    ``UT1 = TDB - tdb_minus_ut1_s`` (the small TDB - TT periodic terms, < 2 ms,
    are absorbed in that constant). Fractional days are split off before
    scaling to keep full precision (IERS Conventions 2010, eq. 5.15).
    """
    days = (t_tdb_s - tdb_minus_ut1_s) / DAY_S
    whole = math.floor(days)
    fraction = days - whole
    turns = 0.7790572732640 + 0.00273781191135448 * days + fraction
    return 2.0 * math.pi * (turns - math.floor(turns))


def _rotation_z(angle: float) -> np.ndarray:
    """ICRF -> Earth-fixed for an Earth rotation angle (rad): ``r_bf = R @ r_icrf``."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def _derivative_tables(C: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients of d/dx, d/dy, d/dz of ``sum C V + S W`` (per unit 1/R), shape (3, SIZE, SIZE).

    Montenbruck & Gill (2000), eq. 3.33, applied term by term; the result
    lives one degree higher than the input.
    """
    Cd = np.zeros((3,) + C.shape)
    Sd = np.zeros((3,) + C.shape)
    for n in range(C.shape[0] - 1):
        for m in range(n + 1):
            c, s = C[n, m], S[n, m]
            if c == 0.0 and s == 0.0:
                continue
            if m == 0:
                Cd[0, n + 1, 1] -= c
                Sd[1, n + 1, 1] -= c
            else:
                f = math.factorial(n - m + 2) / math.factorial(n - m)
                Cd[0, n + 1, m + 1] -= 0.5 * c
                Sd[0, n + 1, m + 1] -= 0.5 * s
                Cd[0, n + 1, m - 1] += 0.5 * f * c
                Sd[0, n + 1, m - 1] += 0.5 * f * s
                Sd[1, n + 1, m + 1] -= 0.5 * c
                Cd[1, n + 1, m + 1] += 0.5 * s
                Sd[1, n + 1, m - 1] -= 0.5 * f * c
                Cd[1, n + 1, m - 1] += 0.5 * f * s
            Cd[2, n + 1, m] -= (n - m + 1) * c
            Sd[2, n + 1, m] -= (n - m + 1) * s
    # W_n0 is identically zero, so S_n0 entries carry nothing.
    Sd[:, :, 0] = 0.0
    return Cd, Sd


def cunningham_vw(r_bf_km: np.ndarray, radius_km: float, size: int = LEGENDRE_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """Cunningham's ``V_nm``, ``W_nm`` for n, m < ``size``, shape (K, size, size).

    ``r_bf_km`` (K, 3) km in the body-fixed frame. ``V_nm = (R/r)^(n+1)
    P_nm(sin phi) cos(m lambda)``, ``W_nm`` likewise with sin; ``P_nm`` without
    the Condon-Shortley phase (Montenbruck & Gill 2000, eqs. 3.29-3.31). Both
    recursions are run at once on ``Z = V + i W``: the sectorial step is then a
    complex product by ``(x + i y) R / r^2`` and the zonal step is real.
    ``Z_(n-2, n-1)`` is zero, so the row update needs no special case.
    """
    if not 2 <= size <= len(LEGENDRE_ROW_A):
        raise InputError(f"size must lie in [2, {len(LEGENDRE_ROW_A)}], got {size!r}")
    x, y, z = r_bf_km[:, 0], r_bf_km[:, 1], r_bf_km[:, 2]
    r2 = x * x + y * y + z * z
    rho = (radius_km * radius_km / r2)[:, None]
    z0 = (z * radius_km / r2)[:, None]
    Z = np.zeros((len(x), size, size), dtype=complex)
    # Sectorials in closed form: Z_mm = (2m-1)!! ((x + i y) R/r^2)^m R/r.
    orders = np.arange(size)
    xy0 = (x + 1j * y) * radius_km / r2
    Z[:, orders, orders] = DOUBLE_FACTORIAL[:size] * xy0[:, None] ** orders * (radius_km / np.sqrt(r2))[:, None]
    # Then row by row in n, all orders m < n at once.
    Z[:, 1, 0] = z0[:, 0] * Z[:, 0, 0]
    for n in range(2, size):
        Z[:, n, :n] = LEGENDRE_ROW_A[n] * z0 * Z[:, n - 1, :n] - LEGENDRE_ROW_B[n] * rho * Z[:, n - 2, :n]
    return Z.real, Z.imag


@dataclass(frozen=True)
class Geopotential:
    """Non-spherical Earth gravity: zonals J2..J4 and tesserals C/S22, C/S31, C/S33.

    Parameters
    ----------
    gm_km3_s2, radius_km : float
        Reference GM (km^3/s^2) and radius (km) of the coefficients.
    j2, j3, j4 : float
        Unnormalised zonal coefficients, ``J_n = -C_n0`` (J2 ~ +1.0826e-3).
    c22, s22, c31, s31, c33, s33 : float
        Unnormalised tesseral/sectorial coefficients.
    tdb_minus_ut1_s : float
        TDB - UT1 in seconds, used for the Earth rotation angle (UT1 ~ UTC, so
        TT - UTC = 32.184 s + TAI - UTC; 64.184 s in 1999-2005).
    center : str
        Always ``"earth"`` (checked by :class:`~opnav.dynamics.forces.ForceModel`).

    Notes
    -----
    Acceleration and Hessian come from the Cunningham recursion (module
    docstring). ICRF <-> Earth-fixed is a z-rotation by the Earth rotation
    angle only: no precession, nutation or polar motion.
    """

    gm_km3_s2: float
    radius_km: float
    j2: float = 0.0
    j3: float = 0.0
    j4: float = 0.0
    c22: float = 0.0
    s22: float = 0.0
    c31: float = 0.0
    s31: float = 0.0
    c33: float = 0.0
    s33: float = 0.0
    tdb_minus_ut1_s: float = 64.184
    center: str = "earth"
    _tables: tuple[np.ndarray, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("gm_km3_s2", "radius_km"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise InputError(f"{name} must be positive and finite, got {value!r}")
        for name in ("j2", "j3", "j4", "c22", "s22", "c31", "s31", "c33", "s33", "tdb_minus_ut1_s"):
            if not np.isfinite(getattr(self, name)):
                raise InputError(f"geopotential coefficient {name} must be finite, got {getattr(self, name)!r}")
        if self.center != "earth":
            raise InputError(f"the geopotential is the Earth's; center must be 'earth', got {self.center!r}")
        C, S = self.coefficients()
        C1, S1 = _derivative_tables(C, S)
        C2 = np.empty((3, 3, LEGENDRE_SIZE, LEGENDRE_SIZE))
        S2 = np.empty((3, 3, LEGENDRE_SIZE, LEGENDRE_SIZE))
        for i in range(3):
            C2[i], S2[i] = _derivative_tables(C1[i], S1[i])
        # Flattened so that evaluation is one matrix product with [V, W] per state.
        gradient = np.concatenate([C1.reshape(3, -1), S1.reshape(3, -1)], axis=1)
        hessian = np.concatenate([C2.reshape(9, -1), S2.reshape(9, -1)], axis=1)
        object.__setattr__(self, "_tables", (gradient.T.copy(), hessian.T.copy()))

    def coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """Unnormalised (C, S), each (SIZE, SIZE) indexed [n, m], monopole excluded."""
        C = np.zeros((LEGENDRE_SIZE, LEGENDRE_SIZE))
        S = np.zeros((LEGENDRE_SIZE, LEGENDRE_SIZE))
        C[2, 0], C[3, 0], C[4, 0] = -self.j2, -self.j3, -self.j4
        C[2, 2], S[2, 2] = self.c22, self.s22
        C[3, 1], S[3, 1] = self.c31, self.s31
        C[3, 3], S[3, 3] = self.c33, self.s33
        return C, S

    @property
    def evaluation_tables(self) -> tuple[np.ndarray, np.ndarray]:
        """Gradient (98, 3) and Hessian (98, 9) tables contracted with the flattened ``[V, W]``
        of :func:`cunningham_vw` (size 7); used by the compiled kernels of :mod:`opnav.dynamics.fast`."""
        return self._tables

    def rotation(self, t_tdb_s: float) -> np.ndarray:
        """``R_bf_icrf`` (3, 3): ICRF -> Earth-fixed at ``t_tdb_s``."""
        return _rotation_z(earth_rotation_angle(t_tdb_s, self.tdb_minus_ut1_s))

    def _features(self, r_bf_km: np.ndarray) -> np.ndarray:
        V, W = cunningham_vw(r_bf_km, self.radius_km)
        return np.concatenate([V.reshape(len(V), -1), W.reshape(len(W), -1)], axis=1)

    def acceleration(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> np.ndarray:
        """(K, 3) km/s^2, ICRF; ``r_km`` (K, 3) geocentric ICRF."""
        R_bf_icrf = self.rotation(t_tdb_s)
        a_bf = self._features(r_km @ R_bf_icrf.T) @ self._tables[0]
        return (self.gm_km3_s2 / self.radius_km**2) * a_bf @ R_bf_icrf

    def partials(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(da/dr (K, 3, 3) 1/s^2 -- the potential's Hessian, ICRF --, da/dv = 0)."""
        R_bf_icrf = self.rotation(t_tdb_s)
        hessian_bf = (self._features(r_km @ R_bf_icrf.T) @ self._tables[1]).reshape(-1, 3, 3)
        hessian = R_bf_icrf.T @ hessian_bf @ R_bf_icrf * (self.gm_km3_s2 / self.radius_km**3)
        return hessian, np.zeros((len(r_km), 3, 3))
