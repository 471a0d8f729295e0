"""The compiled direction kernel (opnav.light_compiled) gives the numpy path's numbers."""

import numpy as np
import pytest

from opnav.ephemeris.cache import EphemerisCache
from opnav.epochs import parse_epoch
from opnav.measurements import ProbeMeasurementModel
from opnav.records import KIND_SIZE, Measurement

T = parse_epoch("2014-07-01T00:00:00", scale="tdb")
STAR = np.array([0.3, 0.4, np.sqrt(0.75)])
CASES = {  # centre -> (a state near which to test, targets)
    "sun": (np.array([1.5e8, 1.0e8, 2.0e7, -20.0, 15.0, 5.0]), ("phobos", "deimos", "mars", "earth")),
    "mars": (np.array([30_000.0, -8000.0, 4000.0, 0.5, 1.2, -0.3]), ("phobos", "deimos", "sun")),
    "earth": (np.array([-7300.0, -41_500.0, 0.0, 3.03, -0.53, 0.0]), ("moon", "sun")),
    "ssb": (np.array([1.5e8, 1.0e8, 2.0e7, -20.0, 15.0, 5.0]), ("mars",)),
}


@pytest.mark.parametrize("light_time, aberration", [(True, True), (False, True), (True, False), (False, False)])
@pytest.mark.parametrize("center", sorted(CASES))
def test_compiled_directions_equal_the_numpy_model(center, light_time, aberration):
    state, targets = CASES[center]
    X = state + np.random.default_rng(5).normal(size=(4, 6)) * np.r_[100.0, 100.0, 100.0, 1e-3, 1e-3, 1e-3]
    cache = EphemerisCache()
    exact = ProbeMeasurementModel(center, ephemeris=cache.ephemeris, light_time=light_time, aberration=aberration)
    fast = ProbeMeasurementModel(center, ephemeris=cache, light_time=light_time, aberration=aberration)
    for target in targets:
        for kind in ("radec", "los", "starlight_angle"):
            m = KIND_SIZE[kind]
            record = Measurement(T, kind, np.zeros(m), np.eye(m), target=target, star_unit_icrf=STAR)
            value, jac = exact.predict_and_jacobians(record, X)
            value_fast, jac_fast = fast.predict_and_jacobians(record, X)
            # the cache differs from the exact ephemeris by < 1 mm, i.e. < 1e-10 rad at these ranges
            np.testing.assert_allclose(value_fast, value, rtol=0, atol=1e-10)
            np.testing.assert_allclose(jac_fast, jac, rtol=1e-7, atol=1e-7 * np.abs(jac).max())
            np.testing.assert_array_equal(fast.predict(record, X), value_fast)


@pytest.mark.parametrize("center", sorted(CASES))
def test_directions_without_jacobians_are_those_with_them_to_the_bit(center):
    """Skipping the partials (sigma points, particles) skips work, not arithmetic the directions need."""
    state, targets = CASES[center]
    X = state + np.random.default_rng(6).normal(size=(13, 6)) * np.r_[100.0, 100.0, 100.0, 1e-3, 1e-3, 1e-3]
    model = ProbeMeasurementModel(center, ephemeris=EphemerisCache())
    for target in targets:
        record = Measurement(T, "radec", np.zeros(2), np.eye(2), target=target)
        np.testing.assert_array_equal(model.predict(record, X), model.predict_and_jacobians(record, X)[0])
