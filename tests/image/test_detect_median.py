"""The correlation sample's median (detection's threshold) by bracketing: the number of the median it replaced
(numba's ``np.median``, numpy's for values without NaN), whatever the values."""

import numpy as np
import pytest

from opnav.compiled import kernel
from opnav.image.detect import _exact_median


@kernel
def _numba_median(values):
    return np.median(values)


def _cases(rng, n):
    yield rng.normal(size=n)
    yield np.round(rng.normal(size=n) * 3)  # an 8-bit frame's few distinct ratios: ties at the median
    yield np.concatenate([rng.normal(size=n), rng.uniform(100.0, 1e4, n // 50)])  # stars in the sample
    yield np.full(n, 2.5)
    yield np.sort(rng.normal(size=n))  # ordered values: the subsample's stride meets a pattern
    yield rng.integers(0, 3, n).astype(float)
    yield np.abs(rng.standard_cauchy(n))
    with_nan = rng.normal(size=n)
    with_nan[n // 3] = np.nan
    yield with_nan


@pytest.mark.parametrize("n", [1, 2, 3, 4095, 4096, 4097, 65535, 65536, 313_001])
def test_the_median_is_numpy_s(n):
    rng = np.random.default_rng(n)
    for values in _cases(rng, n):
        got = _exact_median(values)
        if not np.isnan(values).any():
            assert got == np.median(values)
        expected = _numba_median(values)
        assert got == expected or (np.isnan(got) and np.isnan(expected))
