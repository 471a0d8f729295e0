"""The correlation sample's median (detection's threshold) by bracketing: the number of the median it replaced
(numba's ``np.median``, numpy's for values without NaN), whatever the values."""

import numpy as np
import pytest

from opnav.compiled import kernel
from opnav.image.detect import _exact_median, _median_bracket


@kernel
def _numba_median(values):
    return np.median(values)


def _cases(rng, n):
    yield rng.normal(size=n)
    yield np.round(rng.normal(size=n) * 3)  # an 8-bit frame's few distinct ratios: ties at the median
    yield np.concatenate([rng.normal(size=n), rng.uniform(100.0, 1e4, n // 50)])  # stars in the sample
    yield np.full(n, 2.5)
    yield np.sort(rng.normal(size=n))  # ordered values: the subsample's stride meets a pattern
    yield _with_bright_columns(rng, n)
    yield rng.integers(0, 3, n).astype(float)
    yield np.abs(rng.standard_cauchy(n))
    with_nan = rng.normal(size=n)
    with_nan[n // 3] = np.nan
    yield with_nan


def _with_bright_columns(rng, n):
    """A correlation sample of 256-value rows whose every 64th column is bright (a bloom trail's columns)."""
    values = rng.normal(size=n)
    values[np.arange(n) % 64 == 0] += 50.0
    return values


@pytest.mark.parametrize("n", [1, 2, 3, 4095, 4096, 4097, 65535, 65536, 313_001])
def test_the_median_is_numpy_s(n):
    rng = np.random.default_rng(n)
    for values in _cases(rng, n):
        got = _exact_median(values)
        if not np.isnan(values).any():
            assert got == np.median(values)
        expected = _numba_median(values)
        assert got == expected or (np.isnan(got) and np.isnan(expected))


@pytest.mark.parametrize("n", [4096, 65536, 62001, 313_001])
def test_the_bracket_holds_the_middle_ranks_of_a_sample_with_a_period(n):
    """The bracket's subsample follows no period of the array: a sample whose values repeat a pattern every
    64 (or 249) values is bracketed as a shuffled one is, so the exact median needs no full selection."""
    rng = np.random.default_rng(n)
    period = 249 if n == 62001 else 64
    for values in (rng.normal(size=n), _with_bright_columns(rng, n),
                   rng.normal(size=n) + 40.0 * (np.arange(n) % period < 4)):
        half = n >> 1
        first = half - 1 if n % 2 == 0 else half
        low, high = _median_bracket(values, first, half)
        ordered = np.sort(values)
        assert low <= ordered[first] and ordered[half] <= high
        assert np.mean((values >= low) & (values <= high)) < 0.25  # a bracket, not the whole array


def test_the_tile_sort_is_numpy_s():
    # the background's tile values sorted as uint16 where they are whole numbers from 0 to 65535, as floats
    # elsewhere: numpy's sorted rows, bit for bit (NaNs last, -0.0 kept, 65535 and 65536 at the edge)
    from opnav.image.detect import _sort_rows

    rng = np.random.default_rng(7)
    rows = [np.round(rng.normal(1000.0, 30.0, 257)), rng.integers(0, 256, 257).astype(float),
            np.full(257, 65535.0), np.round(rng.normal(1000.0, 30.0, 257)) + 0.5, rng.normal(0.0, 1.0, 257)]
    for special in (np.nan, -0.0, 0.0, -1.0, 65536.0, 65535.0, np.inf):
        row = rng.integers(0, 65536, 257).astype(float)
        row[rng.integers(0, 257, 3)] = special
        rows.append(row)
    values = np.array(rows)
    for order in (np.arange(len(rows)), rng.permutation(len(rows)), [0, 1, 2]):
        block = np.ascontiguousarray(values[order])
        expected = np.sort(block, axis=-1)
        _sort_rows(block)
        np.testing.assert_array_equal(block, expected)
        assert np.array_equal(np.signbit(block), np.signbit(expected))
