"""Ephemerides: planets (DE421 SPK) and the Martian moons, behind one interface.

``Ephemeris.state(body, t, center=...)`` answers for every body opnav knows:
the DE421 bodies of :mod:`opnav.ephemeris.planets` plus ``phobos`` and
``deimos`` from :mod:`opnav.ephemeris.moons` (mean-element model by default, a
user SPK such as ``mar099.bsp`` on request). Vectors are ICRF, km and km/s;
epochs TDB seconds past J2000.

:class:`SpiceEphemeris` (:mod:`opnav.ephemeris.spice`) answers the same questions from SPICE
kernels read with spiceypy, and :mod:`opnav.ephemeris.spk_writer` writes SPKs.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Protocol

import numpy as np

from ..errors import EphemerisError
from .planets import NAIF_ID, PlanetEphemeris, default_planets

MOONS = ("phobos", "deimos")


class MoonModel(Protocol):
    """Anything that gives Mars-centred ICRF states of Phobos and Deimos."""

    def state(self, name: str, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mars-centred position (km) and velocity (km/s), ICRF; shapes (3,) or (N, 3)."""
        ...


class Ephemeris:
    """Planets plus the Martian moons.

    Parameters
    ----------
    planets : PlanetEphemeris, optional
        Default: DE421 from ``skyfield-data``.
    moons : MoonModel, optional
        Default: the precessing-ellipse mean-element model (JPL MAR080).
    """

    def __init__(self, planets: PlanetEphemeris | None = None, moons: MoonModel | None = None):
        self.planets = planets if planets is not None else default_planets()
        if moons is None:
            from .moons import MeanElementMoons

            moons = MeanElementMoons()
        self.moons = moons

    @classmethod
    def from_paths(cls, planet_kernel: str | Path | None = None, moon_kernel: str | Path | None = None) -> "Ephemeris":
        """Build from kernel paths (``None`` means the defaults)."""
        planets = PlanetEphemeris(planet_kernel) if planet_kernel is not None else None
        moons = None
        if moon_kernel is not None:
            from .moons import SpkMoons

            moons = SpkMoons(moon_kernel)
        return cls(planets, moons)

    def _ssb_state(self, body: str, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = body.strip().lower() if isinstance(body, str) else body
        if key in MOONS:
            r_mars, v_mars = self.planets.state("mars", t)
            r_moon, v_moon = self.moons.state(key, t)
            return r_mars + r_moon, v_mars + v_moon
        return self.planets.state(key, t)

    def state(self, body: str, t: float | np.ndarray, *, center: str = "ssb") -> tuple[np.ndarray, np.ndarray]:
        """Position (km) and velocity (km/s) of ``body`` relative to ``center``, ICRF.

        ``t`` is TDB seconds past J2000, scalar or (N,); results are (3,) or (N, 3).
        """
        body_key = str(body).strip().lower()
        center_key = str(center).strip().lower()
        if body_key in MOONS and center_key == "mars":
            return self.moons.state(body_key, t)
        r, v = self._ssb_state(body_key, t)
        if center_key != "ssb":
            r_c, v_c = self._ssb_state(center_key, t)
            r, v = r - r_c, v - v_c
        return r, v

    def position(self, body: str, t: float | np.ndarray, *, center: str = "ssb") -> np.ndarray:
        """Position (km, ICRF) of ``body`` relative to ``center``; see :meth:`state`."""
        return self.state(body, t, center=center)[0]

    @staticmethod
    def known_bodies() -> tuple[str, ...]:
        return tuple(sorted(set(NAIF_ID) | set(MOONS)))

    @staticmethod
    def check_body(name: str) -> str:
        """Return the canonical lower-case name or raise ``EphemerisError``."""
        key = str(name).strip().lower()
        if key not in NAIF_ID and key not in MOONS:
            raise EphemerisError(f"unknown body {name!r}; known: {', '.join(Ephemeris.known_bodies())}")
        return key


@functools.lru_cache(maxsize=1)
def default_ephemeris() -> Ephemeris:
    """Process-wide DE421 + mean-element moons (read-only, safe to share)."""
    return Ephemeris()


from .spice import KernelError, SpiceEphemeris  # noqa: E402 - spiceypy itself is imported on first use

__all__ = ["Ephemeris", "KernelError", "MoonModel", "PlanetEphemeris", "SpiceEphemeris", "default_ephemeris",
           "default_planets", "MOONS"]
