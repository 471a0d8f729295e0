"""Piecewise Chebyshev cache of body states, evaluated vectorised.

A jplephem evaluation costs about 0.25 ms and the analytic moon model rebuilds
rotation matrices on every call, so filters and integrators that ask for the
same bodies thousands of times a simulated day spend most of their time in the
ephemeris. :class:`EphemerisCache` fits each (body, centre) pair once per
segment and answers every later question from the series.

Algorithm
---------
1. Time is cut into segments ``[i L, (i + 1) L)`` of ``L`` seconds (TDB past
   J2000); ``L`` is ``segment_s`` for the planets and the Sun and
   ``moon_segment_s`` when Phobos or Deimos is involved (their 7.7 h and 30 h
   periods need shorter segments than a planet's year).
2. On first use of a segment the exact ephemeris is evaluated once, vectorised,
   at the ``degree + 1`` Chebyshev nodes of the segment, and position and
   velocity (6 columns) are fitted by ``numpy.polynomial.chebyshev.chebfit``.
   Interpolation at Chebyshev nodes is near-minimax, so the error is the
   truncation of the series: with the defaults below (1 day for planets, 2 h
   for the Martian moons, degree 15) it is below 1 cm for every body
   (``tests/test_ephemeris_cache.py``; 6-h moon segments left 8 cm), far under
   any measurement noise and at the level of the exact evaluation's own
   rounding of the epoch (float64 seconds near 4.6e8 s times ~25 km/s).
3. Evaluation maps ``t`` to ``x = 2 (t/L - i) - 1`` in [-1, 1] and sums
   ``c_k T_k(x)`` with ``T_k(x) = cos(k arccos x)``, for any number of epochs in
   one array operation.
4. :meth:`EphemerisCache.table` hands the dense coefficients of an arc to
   compiled kernels (:mod:`opnav.dynamics.fast`), which evaluate the same
   series by the Chebyshev recurrence.
5. With a ``store`` (:class:`opnav.ephemeris.segment_store.SegmentStore`; the
   process-wide :func:`default_cached_ephemeris` has one in opnav's cache
   folder) a (body, centre) pair's segments fitted by earlier processes are
   read on its first use, checked against the source, instead of fitted
   again (0.7 s of CPU in each process of a 30-day S1 run); the segments this
   process fits are added to the store by :meth:`EphemerisCache.save`, at the
   end of the process or when its owner calls it.

Vectors are ICRF, km and km/s; epochs TDB seconds past J2000.
"""

from __future__ import annotations

import atexit
import functools
import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from . import MOONS, Ephemeris, default_ephemeris


@dataclass(frozen=True)
class ChebyshevTable:
    """Dense Chebyshev coefficients of one (body, centre) pair over an arc.

    Attributes
    ----------
    first_segment : int
        Index ``i`` of the first segment (segment ``i`` starts at ``i * segment_s``).
    segment_s : float
        Segment length, s.
    coefficients : (S, D + 1, 6) array
        Coefficients of position (km) and velocity (km/s), ICRF, per segment.
    """

    first_segment: int
    segment_s: float
    coefficients: np.ndarray

    @property
    def start_tdb_s(self) -> float:
        return self.first_segment * self.segment_s

    @property
    def end_tdb_s(self) -> float:
        return (self.first_segment + len(self.coefficients)) * self.segment_s


class EphemerisCache:
    """Piecewise Chebyshev interpolant of body states, built lazily, evaluated vectorised.

    Offers the :class:`opnav.ephemeris.Ephemeris` interface (``state``,
    ``position``), so it can stand in for the exact ephemeris in force models
    and measurement models.

    Parameters
    ----------
    ephemeris : Ephemeris, optional
        The exact source (ICRF, km, km/s); default :func:`opnav.ephemeris.default_ephemeris`.
    segment_s : float
        Segment length for planets and the Sun, s.
    moon_segment_s : float
        Segment length when Phobos or Deimos is the body or the centre, s.
    degree : int
        Chebyshev degree per segment.
    store : SegmentStore, optional
        Where fitted segments are read from and saved to (module notes, step 5); None: this object only.

    Notes
    -----
    Segments are kept for the life of the object (a 280-day cruise with seven
    bodies holds about 2000 segments of 96 floats). The cache is safe to share
    between threads: a race only computes a segment twice.
    """

    def __init__(self, ephemeris: Ephemeris | None = None, *, segment_s: float = 86_400.0,
                 moon_segment_s: float = 7_200.0, degree: int = 15, store=None):
        for name, value in (("segment_s", segment_s), ("moon_segment_s", moon_segment_s)):
            if not (np.isfinite(value) and value > 0.0):
                raise InputError(f"{name} must be positive and finite, got {value!r}")
        if degree < 1:
            raise InputError(f"degree must be >= 1, got {degree!r}")
        self.ephemeris = ephemeris if ephemeris is not None else default_ephemeris()
        self.segment_s = float(segment_s)
        self.moon_segment_s = float(moon_segment_s)
        self.degree = int(degree)
        k = np.arange(degree + 1)
        self._nodes = np.cos(np.pi * (k + 0.5) / (degree + 1))
        self._orders = k.astype(float)
        self._segments: dict[tuple[str, str, int], np.ndarray] = {}
        self._last: dict[tuple[str, str], tuple[float, np.ndarray]] = {}
        self._store = store
        self._source: str | None = None  # the store's name of the source, found on first use
        self._read: set[tuple[str, str]] = set()  # pairs whose stored segments were read
        self._unsaved: dict[tuple[str, str, float], dict[int, np.ndarray]] = {}
        self._save_at_exit = False

    def segment_length(self, body: str, center: str) -> float:
        """Segment length (s) used for ``body`` relative to ``center``."""
        return self.moon_segment_s if (body in MOONS or center in MOONS) else self.segment_s

    def _coefficients(self, body: str, center: str, index: int, length: float) -> np.ndarray:
        key = (body, center, index)
        coeffs = self._segments.get(key)
        if coeffs is None and self._store is not None and (body, center) not in self._read:
            self._read_stored(body, center, length)
            coeffs = self._segments.get(key)
        if coeffs is None:
            t_nodes = (index + 0.5 * (self._nodes + 1.0)) * length
            r, v = self.ephemeris.state(body, t_nodes, center=center)
            # C order, as the store gives it back (segment_store): a product with another memory order may
            # round differently (numpy's chebfit returns C order today: nothing changes)
            coeffs = np.ascontiguousarray(np.polynomial.chebyshev.chebfit(self._nodes, np.hstack([r, v]), self.degree))
            self._segments[key] = coeffs
            if self._store is not None:
                self._unsaved.setdefault((body, center, length), {})[index] = coeffs
                if not self._save_at_exit:
                    self._save_at_exit = True
                    atexit.register(self.save)
        return coeffs

    def _pair_key(self, body: str, center: str, length: float) -> str | None:
        """The store's name of a pair's file (None when the store cannot name the source)."""
        from .segment_store import pair_key, source_identity

        if self._source is None:
            self._source = source_identity(self.ephemeris) or ""
        return pair_key(self._source, body, center, length, self.degree) if self._source else None

    def _read_stored(self, body: str, center: str, length: float) -> None:
        """The stored segments of ``body`` about ``center`` (each checked against the source), added."""
        self._read.add((body, center))
        key = self._pair_key(body, center, length)
        if key is None:
            return
        stored = self._store.load(key, self.degree, length,
                                  lambda t: np.hstack(self.ephemeris.state(body, t, center=center)))
        for index, coeffs in stored.items():
            self._segments.setdefault((body, center, index), coeffs)

    def save(self) -> None:
        """Add the segments fitted since the last save to the store (nothing without one)."""
        while self._unsaved:
            (body, center, length), segments = self._unsaved.popitem()
            key = self._pair_key(body, center, length)
            if key is not None:
                self._store.save(key, self.degree, segments)

    def _state_scalar(self, body: str, t: float, center: str) -> np.ndarray:
        # force terms and the measurement model ask for the same epoch back to back
        last = self._last.get((body, center))
        if last is not None and last[0] == t:
            return last[1]
        length = self.segment_length(body, center)
        index = math.floor(t / length)
        x = 2.0 * (t / length - index) - 1.0
        basis = np.cos(self._orders * math.acos(min(1.0, max(-1.0, x))))
        state = basis @ self._coefficients(body, center, index, length)
        state.flags.writeable = False
        self._last[(body, center)] = (t, state)
        return state

    def _state_array(self, body: str, t: np.ndarray, center: str) -> np.ndarray:
        length = self.segment_length(body, center)
        scaled = t / length
        index = np.floor(scaled)
        x = np.clip(2.0 * (scaled - index) - 1.0, -1.0, 1.0)
        first = math.floor(scaled.min())
        if scaled.max() < first + 1:
            # the usual case (K states at one epoch, a light-time iteration): one segment, one product
            basis = np.cos(np.arccos(x)[:, None] * self._orders)
            return basis @ self._coefficients(body, center, first, length)
        unique, inverse = np.unique(index.astype(np.int64), return_inverse=True)
        coeffs = np.stack([self._coefficients(body, center, int(i), length) for i in unique])
        basis = np.cos(np.arccos(x)[:, None] * self._orders)
        return np.einsum("nk,nkj->nj", basis, coeffs[inverse.ravel()])

    def body_key(self, name) -> str:
        """The key ``name`` is cached under: its canonical name in the source (here DE421's and the
        moon model's, :meth:`opnav.ephemeris.Ephemeris.check_body`); ``EphemerisError`` if unknown."""
        return Ephemeris.check_body(name)

    def _state(self, body: str, t, center: str) -> np.ndarray:
        body_key = self.body_key(body)
        center_key = self.body_key(center)
        if np.ndim(t) == 0:
            return self._state_scalar(body_key, float(t), center_key)
        t = np.asarray(t, dtype=float)
        if not np.all(np.isfinite(t)):
            raise InputError("ephemeris epochs contain NaN or infinity")
        return self._state_array(body_key, t.ravel(), center_key).reshape(t.shape + (6,))

    def state(self, body: str, t: float | np.ndarray, *, center: str = "ssb") -> tuple[np.ndarray, np.ndarray]:
        """Position (km) and velocity (km/s) of ``body`` relative to ``center``, ICRF.

        ``t`` is TDB seconds past J2000, scalar or array; results are (3,) or ``t.shape + (3,)``.
        """
        state = self._state(body, t, center)
        return state[..., :3], state[..., 3:]

    def position(self, body: str, t: float | np.ndarray, *, center: str = "ssb") -> np.ndarray:
        """Position of ``body`` relative to ``center``, km, ICRF; (3,) or ``t.shape + (3,)``."""
        return self._state(body, t, center)[..., :3]

    def table(self, body: str, center: str, start_tdb_s: float, end_tdb_s: float) -> ChebyshevTable:
        """Dense coefficients of ``body`` relative to ``center`` covering [start, end] (TDB s past J2000)."""
        if not (np.isfinite(start_tdb_s) and np.isfinite(end_tdb_s) and end_tdb_s >= start_tdb_s):
            raise InputError(f"table span must be finite and ordered, got [{start_tdb_s!r}, {end_tdb_s!r}]")
        body_key, center_key = self.body_key(body), self.body_key(center)
        length = self.segment_length(body_key, center_key)
        first, last = math.floor(start_tdb_s / length), math.floor(end_tdb_s / length)
        coeffs = np.stack([self._coefficients(body_key, center_key, i, length) for i in range(first, last + 1)])
        return ChebyshevTable(first, length, coeffs)


@functools.lru_cache(maxsize=1)
def default_cached_ephemeris() -> EphemerisCache:
    """Process-wide :class:`EphemerisCache` over :func:`opnav.ephemeris.default_ephemeris`, with the store in
    opnav's cache folder (:func:`opnav.ephemeris.segment_store.default_store`)."""
    from .segment_store import default_store

    return EphemerisCache(default_ephemeris(), store=default_store())


def save_default_cache() -> None:
    """Save the segments :func:`default_cached_ephemeris` fitted in this process, if it was made here (a
    worker process, which ends without running ``atexit``, calls it after each task)."""
    if default_cached_ephemeris.cache_info().currsize:
        default_cached_ephemeris().save()
