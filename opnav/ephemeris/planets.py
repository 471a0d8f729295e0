"""Planet ephemeris: JPL DE421 as a real SPK kernel, read with jplephem.

The kernel ships in the ``skyfield-data`` package (``de421.bsp``, JPL, public
domain). Positions are ICRF, km; velocities km/s; epochs TDB seconds past J2000,
scalar or 1-D array (vectorised: one jplephem call per segment for all epochs).

DE421 holds barycentre chains only: SSB -> planet barycentre (1..9), SSB -> Sun
(10), Earth-Moon barycentre -> Earth (399) / Moon (301), Mercury, Venus and Mars
barycentre -> planet (199, 299, 499). A body's SSB state is the sum along its
chain; ``state(body, t, center=...)`` differences two chains.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
from jplephem.spk import SPK

from ..epochs import J2000_JD, describe_epoch
from ..errors import EphemerisError

#: Body name -> NAIF id. Jupiter..Pluto are system barycentres (DE421 has no planet centre).
NAIF_ID = {
    "ssb": 0,
    "mercury_barycenter": 1,
    "venus_barycenter": 2,
    "earth_barycenter": 3,
    "mars_barycenter": 4,
    "jupiter": 5,
    "saturn": 6,
    "uranus": 7,
    "neptune": 8,
    "pluto": 9,
    "sun": 10,
    "mercury": 199,
    "venus": 299,
    "earth": 399,
    "moon": 301,
    "mars": 499,
}


def default_kernel_path() -> Path:
    """Path of ``de421.bsp`` inside the installed ``skyfield-data`` package."""
    try:
        import skyfield_data
    except ImportError as exc:  # pragma: no cover - declared dependency
        raise EphemerisError("package 'skyfield-data' (which ships de421.bsp) is not installed") from exc
    return Path(skyfield_data.__file__).parent / "data" / "de421.bsp"


class PlanetEphemeris:
    """Sun, planets and the Moon from a JPL SPK kernel (DE421 by default).

    Parameters
    ----------
    path : str or Path, optional
        SPK kernel; default DE421 from ``skyfield-data``.
    """

    def __init__(self, path: str | Path | None = None):
        self.path = Path(path) if path is not None else default_kernel_path()
        if not self.path.is_file():
            raise EphemerisError(f"ephemeris kernel not found: {self.path}")
        try:
            self._kernel = SPK.open(str(self.path))
        except Exception as exc:
            raise EphemerisError(f"cannot read SPK kernel {self.path}: {exc}") from exc
        self._parent = {target: center for center, target in self._kernel.pairs}
        first = next(iter(self._kernel.segments))
        self.start_tdb_s = (first.start_jd - J2000_JD) * 86_400.0
        self.end_tdb_s = (first.end_jd - J2000_JD) * 86_400.0

    def naif_id(self, body: str | int) -> int:
        """NAIF id of ``body`` (name, case-insensitive, or id); raise for unknown bodies."""
        if isinstance(body, (int, np.integer)):
            naif = int(body)
        else:
            key = str(body).strip().lower().replace(" ", "_")
            if key not in NAIF_ID:
                raise EphemerisError(
                    f"unknown body {body!r}; known: {', '.join(sorted(NAIF_ID))}"
                )
            naif = NAIF_ID[key]
        if naif != 0 and naif not in self._parent:
            raise EphemerisError(f"body {body!r} (NAIF {naif}) is not in kernel {self.path.name}")
        return naif

    def _check_epochs(self, t: np.ndarray) -> None:
        if not np.all(np.isfinite(t)):
            raise EphemerisError("epoch is NaN or infinite")
        if np.any(t < self.start_tdb_s) or np.any(t > self.end_tdb_s):
            bad = t[(t < self.start_tdb_s) | (t > self.end_tdb_s)].flat[0]
            raise EphemerisError(
                f"epoch {describe_epoch(bad)} is outside the coverage of kernel {self.path.name}: "
                f"{describe_epoch(self.start_tdb_s)} to {describe_epoch(self.end_tdb_s)}"
            )

    def _ssb_state(self, naif: int, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = np.zeros(t.shape + (3,))
        v = np.zeros(t.shape + (3,))
        day = t / 86_400.0
        while naif != 0:
            center = self._parent[naif]
            position, velocity_per_day = self._kernel[center, naif].compute_and_differentiate(J2000_JD, day)
            r += np.moveaxis(position, 0, -1)
            v += np.moveaxis(velocity_per_day, 0, -1) / 86_400.0
            naif = center
        return r, v

    def state(self, body: str | int, t: float | np.ndarray, *, center: str | int = "ssb") -> tuple[np.ndarray, np.ndarray]:
        """Position (km) and velocity (km/s) of ``body`` relative to ``center``, ICRF.

        Parameters
        ----------
        body, center : str or int
            Body names from ``NAIF_ID`` or NAIF ids.
        t : float or (N,) array
            TDB seconds past J2000.

        Returns
        -------
        r, v : (3,) or (N, 3) arrays, km and km/s, ICRF.
        """
        t_arr = np.atleast_1d(np.asarray(t, dtype=float))
        self._check_epochs(t_arr)
        r, v = self._ssb_state(self.naif_id(body), t_arr)
        if center not in ("ssb", 0):
            r_c, v_c = self._ssb_state(self.naif_id(center), t_arr)
            r, v = r - r_c, v - v_c
        if np.ndim(t) == 0:
            return r[0], v[0]
        return r, v

    def position(self, body: str | int, t: float | np.ndarray, *, center: str | int = "ssb") -> np.ndarray:
        """Position (km, ICRF) of ``body`` relative to ``center``; see :meth:`state`."""
        return self.state(body, t, center=center)[0]


@functools.lru_cache(maxsize=1)
def default_planets() -> PlanetEphemeris:
    """The process-wide DE421 reader (opened once; read-only, safe to share)."""
    return PlanetEphemeris()
