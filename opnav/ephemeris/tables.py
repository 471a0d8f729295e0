"""Dense Chebyshev tables of a few bodies over an arc, for compiled kernels.

:class:`ArcTables` stacks the :class:`~opnav.ephemeris.cache.ChebyshevTable`
of each (body, centre) pair it serves into plain arrays, grows them when a
request leaves the span, and :func:`chebyshev_states` evaluates them inside
numba kernels (:mod:`opnav.dynamics.fast`, :mod:`opnav.light_compiled`). The
series are the cache's own, so a compiled kernel and the numpy path see the
same ephemeris to rounding.

Vectors are ICRF, km and km/s; epochs TDB seconds past J2000.
"""

from __future__ import annotations

import math

import numpy as np

from ..compiled import kernel
from .cache import EphemerisCache

#: Span added on each side of a request when the tables must grow, s.
MARGIN_S = 5 * 86_400.0


@kernel(inline=True)
def chebyshev_states(t, coef, first, seg, count, columns, out):
    """Evaluate every table at ``t`` into ``out`` (NT, columns); False if ``t`` is outside a table.

    ``coef`` (NT, S, D+1, 6): position (km) then velocity (km/s) coefficients per segment;
    ``first`` (NT,) first segment index, ``seg`` (NT,) segment length s, ``count`` (NT,) segments.
    The Chebyshev recurrence ``T_k = 2 x T_(k-1) - T_(k-2)`` replaces the cosines of the numpy path.
    """
    degree1 = coef.shape[2]
    for j in range(coef.shape[0]):
        s = t / seg[j]
        i = math.floor(s)
        idx = int(i) - first[j]
        if idx < 0 or idx >= count[j]:
            return False
        x = min(1.0, max(-1.0, 2.0 * (s - i) - 1.0))
        # one recurrence for all columns; the column sums are then independent (vectorisable)
        for c in range(columns):
            out[j, c] = coef[j, idx, 0, c] + coef[j, idx, 1, c] * x
        t_prev = 1.0
        t_cur = x
        for k in range(2, degree1):
            t_next = 2.0 * x * t_cur - t_prev
            for c in range(columns):
                out[j, c] += coef[j, idx, k, c] * t_next
            t_prev = t_cur
            t_cur = t_next
    return True


class ArcTables:
    """Stacked Chebyshev tables of (body, centre, cache) triples over a growing span.

    Parameters
    ----------
    entries : sequence of (body, center, EphemerisCache)
        The pairs to serve, in the order of the table index used by kernels.
    """

    def __init__(self, entries):
        self.entries = tuple((str(body), str(center), cache) for body, center, cache in entries)
        for _, _, cache in self.entries:
            if not isinstance(cache, EphemerisCache):
                raise TypeError(f"ArcTables needs EphemerisCache sources, got {type(cache).__name__}")
        self.span = (np.inf, -np.inf)
        # with no entries the kernels loop over nothing; the shapes only keep numba's types fixed
        self.arrays = (np.zeros((0, 1, 2, 6)), np.zeros(0, dtype=np.int64), np.ones(0), np.zeros(0, dtype=np.int64))

    def cover(self, t_lo: float, t_hi: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(coef, first, seg, count)`` covering [t_lo, t_hi] (TDB s past J2000), grown if needed."""
        lo, hi = self.span
        # a table ends where its last segment ends; that epoch itself belongs to the next segment
        if lo <= t_lo and t_hi < hi:
            return self.arrays
        if not self.entries:
            self.span = (-np.inf, np.inf)
            return self.arrays
        lo, hi = min(lo, t_lo - MARGIN_S), max(hi, t_hi + MARGIN_S)
        tables = [cache.table(body, center, lo, hi) for body, center, cache in self.entries]
        segments = max(len(tab.coefficients) for tab in tables)
        degree1 = max(tab.coefficients.shape[1] for tab in tables)
        coef = np.zeros((len(tables), segments, degree1, 6))
        for j, tab in enumerate(tables):
            coef[j, : len(tab.coefficients), : tab.coefficients.shape[1]] = tab.coefficients
        first = np.array([tab.first_segment for tab in tables], dtype=np.int64)
        seg = np.array([tab.segment_s for tab in tables])
        count = np.array([len(tab.coefficients) for tab in tables], dtype=np.int64)
        self.arrays = (coef, first, seg, count)
        self.span = (max(tab.start_tdb_s for tab in tables), min(tab.end_tdb_s for tab in tables))
        return self.arrays
