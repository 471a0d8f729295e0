"""The NEES/NIS statistics and chi-square bands (opnav.consistency), the one copy."""

import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

from opnav import consistency
from opnav.errors import InputError


def test_nees_is_the_mahalanobis_distance():
    rng = np.random.default_rng(11)
    A = rng.normal(size=(5, 4, 4))
    P = A @ A.transpose(0, 2, 1) + 4 * np.eye(4)
    x, truth = rng.normal(size=(5, 4)), rng.normal(size=(5, 4))
    expected = [e @ np.linalg.solve(Pk, e) for e, Pk in zip(x - truth, P)]
    np.testing.assert_allclose(consistency.nees(x, P, truth), expected, rtol=1e-12)
    with pytest.raises(InputError, match="do not match"):
        consistency.nees(x, P, truth[:-1])


def test_chi2_bands_are_scipys():
    low, high = consistency.chi2_mean_bounds(6, 20, 0.95)
    np.testing.assert_allclose([low, high], stats.chi2.ppf([0.025, 0.975], 120) / 20, rtol=1e-14)
    assert consistency.chi2_interval(3, 0.9) == consistency.chi2_mean_bounds(3, 1, 0.9)
    assert consistency.chi2_quantile(0.999, 2) == stats.chi2.ppf(0.999, 2)
    with pytest.raises(InputError, match="dof >= 1"):
        consistency.chi2_mean_bounds(0, 3)


def test_nis_summary_takes_the_accepted_finite_values():
    nis = np.array([1.0, 3.0, np.nan, 100.0])
    summary = consistency.nis_summary(nis, np.array([2, 2, 2, 3]), np.array([True, True, True, False]))
    assert summary["mean"] == 2.0 and summary["mean_dof"] == 2
    assert summary["bounds95_for_mean"] == list(consistency.chi2_mean_bounds(2, 2, 0.95))
    assert consistency.nis_summary(nis, np.full(4, 2), np.zeros(4, bool)) is None


def test_nees_band_share_counts_the_bounds_inside():
    low, high = consistency.chi2_interval(6)
    assert consistency.nees_band_share(np.array([low, high, 0.0, 1e3]), 6) == 0.5


def test_consistent_draws_stay_inside_their_window_bands():
    """Windows of 50 chi-square(2) draws at 99.9 %: at most a stray window of 100 outside."""
    rng = np.random.default_rng(0)
    test = consistency.window_test(rng.chisquare(2, 5000), np.full(5000, 2), window=50, probability=0.999)
    assert test.means.size == 100 and test.outside.sum() <= 2 and test.longest_run < 3


def test_importing_consistency_leaves_scipy_stats_alone():
    code = "import sys, opnav.consistency; print('scipy.stats' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True).stdout.strip() == "False"


def test_the_statistics_have_one_home():
    """The old homes re-export them no more: one copy, in opnav.consistency (the filters' run loop
    uses its NEES, the same object)."""
    from opnav import filters
    from opnav.filters import run

    assert run.nees is consistency.nees and not hasattr(run, "chi2_mean_bounds")
    assert not hasattr(run, "ensemble_nees") and filters.ensemble_nees is consistency.ensemble_nees
