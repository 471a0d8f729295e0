"""The Chebyshev ephemeris cache and its dense tables against the exact ephemeris."""

import numpy as np
import pytest

from opnav.ephemeris import default_ephemeris
from opnav.ephemeris.cache import EphemerisCache
from opnav.ephemeris.tables import ArcTables, chebyshev_states
from opnav.epochs import parse_epoch
from opnav.errors import EphemerisError, InputError

T0 = parse_epoch("2014-07-01T00:00:00", scale="tdb")
PAIRS = [("phobos", "ssb"), ("deimos", "mars"), ("mars", "ssb"), ("sun", "earth"), ("moon", "earth"),
         ("earth", "sun"), ("jupiter", "sun")]


@pytest.mark.parametrize("body, center", PAIRS)
def test_cache_states_match_the_exact_ephemeris_to_a_centimetre(body, center):
    exact = default_ephemeris()
    cache = EphemerisCache(exact)
    t = T0 + np.random.default_rng(7).uniform(0.0, 10 * 86_400.0, 200)
    r, v = cache.state(body, t, center=center)
    r_ref, v_ref = exact.state(body, t, center=center)
    assert np.abs(r - r_ref).max() < 1e-5  # km: 1 cm
    assert np.abs(v - v_ref).max() < 1e-9  # km/s
    # scalar path agrees with the array path
    r0, v0 = cache.state(body, float(t[3]), center=center)
    np.testing.assert_allclose(r0, r[3], rtol=1e-15, atol=1e-9)
    np.testing.assert_allclose(v0, v[3], rtol=0, atol=1e-12)


def test_tables_evaluated_by_the_compiled_recurrence_equal_the_cache():
    cache = EphemerisCache()
    tables = ArcTables([(body, center, cache) for body, center in PAIRS])
    coef, first, seg, count = tables.cover(T0, T0 + 3 * 86_400.0)
    out = np.empty((len(PAIRS), 6))
    for t in T0 + np.array([0.0, 1234.5, 86_400.0, 2.9 * 86_400.0]):
        assert chebyshev_states(t, coef, first, seg, count, 6, out)
        for j, (body, center) in enumerate(PAIRS):
            r, v = cache.state(body, t, center=center)
            np.testing.assert_allclose(out[j], np.r_[r, v], rtol=1e-13, atol=1e-9)
    # outside the covered span the kernel refuses instead of extrapolating
    assert not chebyshev_states(tables.span[1] + 1.0, coef, first, seg, count, 6, out)
    grown = tables.cover(T0 + 40 * 86_400.0, T0 + 41 * 86_400.0)
    assert chebyshev_states(T0 + 40.5 * 86_400.0, *grown, 6, out)


def test_cache_errors_are_named():
    with pytest.raises(InputError, match="segment_s"):
        EphemerisCache(segment_s=0.0)
    with pytest.raises(InputError, match="NaN"):
        EphemerisCache().state("mars", np.array([T0, np.nan]))
    with pytest.raises(EphemerisError, match="vulcan"):
        EphemerisCache().state("vulcan", T0)
    with pytest.raises(EphemerisError):
        EphemerisCache().state("mars", 1e12)  # far outside DE421
