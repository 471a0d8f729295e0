"""Force terms and force models: accelerations and their analytic partials.

Every term is a frozen dataclass with two methods, vectorised over K states
that share one epoch:

- ``acceleration(t, r, v) -> a``: ``r`` (K, 3) km and ``v`` (K, 3) km/s, ICRF,
  relative to the model's central body; ``a`` (K, 3) km/s^2, ICRF.
- ``partials(t, r, v) -> (da/dr, da/dv)``: (K, 3, 3) in 1/s^2 and 1/s.

A :class:`ForceModel` names the central body (the origin of its states) and
sums its terms. Positions of perturbing bodies come from an *ephemeris*: any
object with ``position(body, t, *, center) -> (3,)`` km, ICRF (an
:class:`opnav.ephemeris.Ephemeris`, or the faster
:class:`opnav.ephemeris.cache.EphemerisCache` that the model factories use).

Epochs are TDB seconds past J2000; see ``docs/conventions.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..constants import AU_KM, RADIUS_KM, SOLAR_PRESSURE_1AU_N_M2
from ..ephemeris import Ephemeris
from ..ephemeris.cache import default_cached_ephemeris
from ..errors import InputError

_EYE3 = np.eye(3)


class PositionSource(Protocol):
    """Anything that gives body positions: km, ICRF, relative to ``center``."""

    def position(self, body: str, t: float | np.ndarray, *, center: str = "ssb") -> np.ndarray: ...


class ForceTerm(Protocol):
    """One contribution to the acceleration of a state relative to a central body."""

    def acceleration(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> np.ndarray:
        """(K, 3) km/s^2, ICRF, for (K, 3) positions (km) and velocities (km/s)."""
        ...

    def partials(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(da/dr (K, 3, 3) in 1/s^2, da/dv (K, 3, 3) in 1/s)."""
        ...


def _check_gm(gm_km3_s2: float, name: str = "gm_km3_s2") -> None:
    if not (np.isfinite(gm_km3_s2) and gm_km3_s2 > 0.0):
        raise InputError(f"{name} must be positive and finite, got {gm_km3_s2!r}")


def _point_mass_gradient(d: np.ndarray, gm: float) -> np.ndarray:
    """d/dd of ``-gm d/|d|^3`` for (K, 3) ``d``: ``-gm (I/|d|^3 - 3 d d^T/|d|^5)``, (K, 3, 3)."""
    dist = np.linalg.norm(d, axis=-1)
    inv3 = 1.0 / dist**3
    outer = d[:, :, None] * d[:, None, :]
    return -gm * (inv3[:, None, None] * _EYE3 - 3.0 * (inv3 / dist**2)[:, None, None] * outer)


@dataclass(frozen=True)
class CentralGravity:
    """Point-mass attraction of the central body: ``a = -GM r / |r|^3``.

    Parameters
    ----------
    gm_km3_s2 : float
        Gravitational parameter of the central body, km^3/s^2.
    """

    gm_km3_s2: float

    def __post_init__(self) -> None:
        _check_gm(self.gm_km3_s2)

    def acceleration(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> np.ndarray:
        """(K, 3) km/s^2, ICRF; ``r_km`` (K, 3) relative to the central body."""
        dist = np.linalg.norm(r_km, axis=-1, keepdims=True)
        return -self.gm_km3_s2 * r_km / dist**3

    def partials(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(da/dr (K, 3, 3) 1/s^2, da/dv = 0 (K, 3, 3) 1/s)."""
        return _point_mass_gradient(r_km, self.gm_km3_s2), np.zeros((len(r_km), 3, 3))


@dataclass(frozen=True)
class ThirdBody:
    """Point-mass perturbation of a third body on a state relative to ``center``.

    Parameters
    ----------
    body : str
        Perturbing body (an ephemeris name, e.g. ``"jupiter"``).
    center : str
        The model's central body (origin of the state).
    gm_km3_s2 : float
        Gravitational parameter of ``body``, km^3/s^2.
    ephemeris : PositionSource, optional
        Source of ``body``'s position relative to ``center``; default the
        process-wide :class:`EphemerisCache`.

    Notes
    -----
    With ``r_b`` the body's position relative to the centre (Montenbruck &
    Gill 2000, eq. 3.37), direct minus indirect term::

        a = mu [(r_b - r)/|r_b - r|^3 - r_b/|r_b|^3]

    and ``da/dr = mu (3 d d^T/|d|^5 - I/|d|^3)`` with ``d = r_b - r``.
    """

    body: str
    center: str
    gm_km3_s2: float
    ephemeris: PositionSource | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.ephemeris is None:
            object.__setattr__(self, "ephemeris", default_cached_ephemeris())
        # the body as its source names it: DE421's bodies, or a kernel's (opnav.ephemeris.spice)
        check = getattr(self.ephemeris, "body_key", None) or getattr(self.ephemeris, "check_body", Ephemeris.check_body)
        object.__setattr__(self, "body", check(self.body))
        object.__setattr__(self, "center", Ephemeris.check_body(self.center))
        if self.body == self.center:
            raise InputError(f"third body {self.body!r} cannot be the central body")
        _check_gm(self.gm_km3_s2)

    def acceleration(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> np.ndarray:
        """(K, 3) km/s^2, ICRF; ``r_km`` (K, 3) relative to ``center``."""
        r_b = self.ephemeris.position(self.body, t_tdb_s, center=self.center)
        d = r_b - r_km
        dist = np.linalg.norm(d, axis=-1, keepdims=True)
        return self.gm_km3_s2 * (d / dist**3 - r_b / np.linalg.norm(r_b) ** 3)

    def partials(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(da/dr (K, 3, 3) 1/s^2, da/dv = 0 (K, 3, 3) 1/s)."""
        r_b = self.ephemeris.position(self.body, t_tdb_s, center=self.center)
        # a depends on r through d = r_b - r, so da/dr = -(d/dd)(-mu d/|d|^3) with the signs folded.
        return _point_mass_gradient(r_b - r_km, self.gm_km3_s2), np.zeros((len(r_km), 3, 3))


def shadow_factor(r_sun_probe_km: np.ndarray, r_body_probe_km: np.ndarray, body_radius_km: float) -> np.ndarray:
    """Fraction of the solar disk visible past one occulting body (conical model).

    Parameters
    ----------
    r_sun_probe_km : (K, 3) array
        Probe position relative to the Sun, km, ICRF.
    r_body_probe_km : (K, 3) array
        Probe position relative to the occulting body, km, ICRF.
    body_radius_km : float
        Radius of the occulting body (a sphere), km.

    Returns
    -------
    (K,) array in [0, 1]: 1 in sunlight, 0 in the umbra, between in the penumbra
    or an annular eclipse.

    Notes
    -----
    Montenbruck & Gill (2000), sec. 3.4.2: apparent radii ``a`` (Sun) and ``b``
    (body), their separation ``c``; the overlap of two circular disks of radii
    a and b at distance c is ``A = a^2 acos(x/a) + b^2 acos((c-x)/b) - c y``
    with ``x = (c^2 + a^2 - b^2)/(2c)``, ``y = sqrt(a^2 - x^2)``, and the
    visible fraction is ``1 - A/(pi a^2)``.
    """
    dist_sun = np.linalg.norm(r_sun_probe_km, axis=-1)
    dist_body = np.linalg.norm(r_body_probe_km, axis=-1)
    a = np.arcsin(np.clip(RADIUS_KM["sun"] / dist_sun, 0.0, 1.0))
    b = np.arcsin(np.clip(body_radius_km / dist_body, 0.0, 1.0))
    cos_c = np.sum(r_body_probe_km * r_sun_probe_km, axis=-1) / (dist_body * dist_sun)
    c = np.arccos(np.clip(cos_c, -1.0, 1.0))
    factor = np.ones_like(c)
    umbra = c <= b - a
    annular = c <= a - b
    partial = (c < a + b) & ~umbra & ~annular
    factor[umbra] = 0.0
    factor[annular] = 1.0 - (b[annular] / a[annular]) ** 2
    if np.any(partial):
        ap, bp, cp = a[partial], b[partial], c[partial]
        x = (cp**2 + ap**2 - bp**2) / (2.0 * cp)
        y = np.sqrt(np.maximum(ap**2 - x**2, 0.0))
        area = ap**2 * np.arccos(np.clip(x / ap, -1.0, 1.0)) + bp**2 * np.arccos(np.clip((cp - x) / bp, -1.0, 1.0)) - cp * y
        factor[partial] = 1.0 - area / (np.pi * ap**2)
    return factor


@dataclass(frozen=True)
class SolarRadiationPressure:
    """Cannonball solar radiation pressure with an optional conical shadow.

    Parameters
    ----------
    area_to_mass_m2_kg : float
        Cross-section over mass, m^2/kg (>= 0).
    cr : float
        Radiation pressure coefficient (1 = absorbing, 2 = mirror), in [0, 2.5].
    center : str
        The model's central body (origin of the state).
    ephemeris : PositionSource, optional
        Source of the Sun's and the occulting bodies' positions; default the
        process-wide :class:`EphemerisCache`.
    shadow_bodies : tuple of str
        Occulting spheres (names in :data:`opnav.constants.RADIUS_KM`, not the
        Sun); empty for no eclipses.
    pressure_1au_n_m2 : float
        Solar pressure at 1 au, N/m^2.

    Notes
    -----
    With ``s = r - r_sun`` the probe's position relative to the Sun
    (Montenbruck & Gill 2000, eq. 3.75, cannonball)::

        a = nu P0 Cr (A/m) (AU/|s|)^2 s/|s|

    pushing away from the Sun, where ``nu`` is the product of the
    :func:`shadow_factor` of each occulting body. The partials treat ``nu`` as
    constant: ``da/dr = nu P0 Cr (A/m) AU^2 (I/|s|^3 - 3 s s^T/|s|^5)``; the
    derivative of the shadow factor (non-zero only in the penumbra) is
    neglected. ``da/dv = 0``.
    """

    area_to_mass_m2_kg: float
    cr: float
    center: str
    ephemeris: PositionSource | None = field(default=None, repr=False, compare=False)
    shadow_bodies: tuple[str, ...] = ("earth",)
    pressure_1au_n_m2: float = SOLAR_PRESSURE_1AU_N_M2

    def __post_init__(self) -> None:
        if not (np.isfinite(self.area_to_mass_m2_kg) and self.area_to_mass_m2_kg >= 0.0):
            raise InputError(f"area_to_mass_m2_kg must be finite and >= 0, got {self.area_to_mass_m2_kg!r}")
        if not (np.isfinite(self.cr) and 0.0 <= self.cr <= 2.5):
            raise InputError(f"cr must lie in [0, 2.5], got {self.cr!r}")
        if not (np.isfinite(self.pressure_1au_n_m2) and self.pressure_1au_n_m2 >= 0.0):
            raise InputError(f"pressure_1au_n_m2 must be finite and >= 0, got {self.pressure_1au_n_m2!r}")
        object.__setattr__(self, "center", Ephemeris.check_body(self.center))
        bodies = tuple(Ephemeris.check_body(b) for b in self.shadow_bodies)
        for body in bodies:
            if body == "sun" or body not in RADIUS_KM:
                raise InputError(f"shadow body {body!r} has no radius; use one of "
                                 f"{', '.join(b for b in RADIUS_KM if b != 'sun')}")
        object.__setattr__(self, "shadow_bodies", bodies)
        if self.ephemeris is None:
            object.__setattr__(self, "ephemeris", default_cached_ephemeris())

    @property
    def _scale_km3_s2(self) -> float:
        # P0 [N/m^2] * A/m [m^2/kg] = m/s^2; /1000 -> km/s^2; times AU^2 for the 1/r^2 law.
        return self.pressure_1au_n_m2 * self.cr * self.area_to_mass_m2_kg * 1e-3 * AU_KM**2

    def _geometry(self, t_tdb_s: float, r_km: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.center == "sun":
            s = r_km
        else:
            s = r_km - self.ephemeris.position("sun", t_tdb_s, center=self.center)
        nu = np.ones(len(r_km))
        for body in self.shadow_bodies:
            r_body = r_km if body == self.center else r_km - self.ephemeris.position(body, t_tdb_s, center=self.center)
            nu = nu * shadow_factor(s, r_body, RADIUS_KM[body])
        return s, nu

    def acceleration(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> np.ndarray:
        """(K, 3) km/s^2, ICRF; ``r_km`` (K, 3) relative to ``center``."""
        s, nu = self._geometry(t_tdb_s, r_km)
        dist = np.linalg.norm(s, axis=-1, keepdims=True)
        return (self._scale_km3_s2 * nu)[:, None] * s / dist**3

    def partials(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(da/dr (K, 3, 3) 1/s^2 with the shadow factor held fixed, da/dv = 0 (K, 3, 3))."""
        s, nu = self._geometry(t_tdb_s, r_km)
        # a = +k s/|s|^3 is the negative of a point mass of "GM" k.
        gradient = -_point_mass_gradient(s, self._scale_km3_s2) * nu[:, None, None]
        return gradient, np.zeros((len(r_km), 3, 3))


@dataclass(frozen=True)
class ForceModel:
    """A central body and the force terms acting on states relative to it.

    Parameters
    ----------
    center : str
        Central body: the origin of the states (``"sun"``, ``"mars"``, ``"earth"``...).
    terms : tuple of ForceTerm
        Summed accelerations; terms with a ``center`` attribute must agree with ``center``.
    name : str
        Label for logs and reports.
    ephemeris : EphemerisCache, optional
        Where a filter using this model reads the bodies it measures (its measurement model,
        :func:`opnav.filters.factory.measurement_model`), when not opnav's DE421: a mission's SPICE
        kernels (:class:`opnav.ephemeris.spice.KernelCache`). The terms carry their own sources.
    """

    center: str
    terms: tuple[ForceTerm, ...]
    name: str = ""
    ephemeris: object = field(default=None, compare=False, repr=False)
    _fused: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", Ephemeris.check_body(self.center))
        terms = tuple(self.terms)
        if not terms:
            raise InputError(f"force model {self.name!r} needs at least one term")
        for term in terms:
            if not (callable(getattr(term, "acceleration", None)) and callable(getattr(term, "partials", None))):
                raise InputError(f"force model {self.name!r}: {term!r} is not a force term")
            term_center = getattr(term, "center", self.center)
            if term_center != self.center:
                raise InputError(f"force model {self.name!r} is centred on {self.center!r} "
                                 f"but term {type(term).__name__} is centred on {term_center!r}")
        object.__setattr__(self, "terms", terms)
        # Third bodies sharing an ephemeris are evaluated together: one (K, B, 3) computation
        # instead of B small ones, which roughly halves the cost of the cruise right-hand side.
        groups: dict[int, list[ThirdBody]] = {}
        others = []
        for term in terms:
            if type(term) is ThirdBody:
                groups.setdefault(id(term.ephemeris), []).append(term)
            else:
                others.append(term)
        fused = tuple(_ThirdBodyGroup(group) for group in groups.values())
        object.__setattr__(self, "_fused", fused + tuple(others))

    def acceleration(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> np.ndarray:
        """Total acceleration, km/s^2, ICRF; ``r_km``, ``v_km_s`` (K, 3) or (3,) relative to ``center``."""
        r2, v2 = np.atleast_2d(r_km), np.atleast_2d(v_km_s)
        total = sum(term.acceleration(t_tdb_s, r2, v2) for term in self._fused)
        return total if np.ndim(r_km) == 2 else total[0]

    def partials(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(da/dr 1/s^2, da/dv 1/s), each (K, 3, 3), or (3, 3) for (3,) inputs."""
        r2, v2 = np.atleast_2d(r_km), np.atleast_2d(v_km_s)
        da_dr = np.zeros((len(r2), 3, 3))
        da_dv = np.zeros((len(r2), 3, 3))
        for term in self._fused:
            dr, dv = term.partials(t_tdb_s, r2, v2)
            da_dr += dr
            da_dv += dv
        if np.ndim(r_km) == 2:
            return da_dr, da_dv
        return da_dr[0], da_dv[0]


class _ThirdBodyGroup:
    """Several :class:`ThirdBody` terms with one ephemeris, evaluated as one array operation."""

    def __init__(self, terms: list[ThirdBody]):
        self._ephemeris = terms[0].ephemeris
        self._center = terms[0].center
        self._bodies = tuple(term.body for term in terms)
        self._gm = np.array([term.gm_km3_s2 for term in terms])

    def _positions(self, t_tdb_s: float) -> np.ndarray:
        return np.array([self._ephemeris.position(body, t_tdb_s, center=self._center) for body in self._bodies])

    def acceleration(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> np.ndarray:
        r_b = self._positions(t_tdb_s)  # (B, 3)
        d = r_b[None, :, :] - r_km[:, None, :]  # (K, B, 3)
        w = self._gm / np.linalg.norm(d, axis=-1) ** 3  # (K, B)
        indirect = (self._gm / np.linalg.norm(r_b, axis=-1) ** 3) @ r_b
        return np.einsum("kb,kbi->ki", w, d) - indirect

    def partials(self, t_tdb_s: float, r_km: np.ndarray, v_km_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = self._positions(t_tdb_s)[None, :, :] - r_km[:, None, :]
        dist2 = np.sum(d * d, axis=-1)
        w = self._gm / dist2**1.5
        outer = np.einsum("kb,kbi,kbj->kij", 3.0 * w / dist2, d, d)
        return outer - w.sum(axis=1)[:, None, None] * _EYE3, np.zeros((len(r_km), 3, 3))
