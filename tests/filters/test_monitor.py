"""Consistency monitor: windowed chi-square tests of NIS/NEES, refusals, degenerate clouds."""

import numpy as np
import pytest
from scipy import stats

from opnav.errors import InputError
from opnav.filters.monitor import MonitorOptions, check_history, window_test
from opnav.filters.run import FilterHistory


def history(nis, dof=2, accepted=None, ess=None):
    n = len(nis)
    accepted = np.ones(n, bool) if accepted is None else accepted
    return FilterHistory(
        epochs=np.arange(n, dtype=float), states=np.zeros((n, 6)), covariances=np.repeat(np.eye(6)[None], n, 0),
        residuals=np.zeros((n, dof)), nis=np.asarray(nis, float), dof=np.full(n, dof), accepted=accepted,
        reasons=tuple("" if a else "gate" for a in accepted), kinds=("radec",) * n, targets=("a",) * n, ess=ess)


def test_consistent_nis_raises_no_flag():
    rng = np.random.default_rng(0)
    report = check_history(history(rng.chisquare(2, 5000)))
    assert report.flags == () and report.usable
    # 100 windows at 99.9 %: at most a stray one outside, never three in a row
    assert report.nis.outside.sum() <= 2 and report.nis.longest_run < 3


def test_overconfident_filter_is_flagged_and_unusable():
    rng = np.random.default_rng(1)
    # a covariance half the truth doubles every NIS
    report = check_history(history(2.0 * rng.chisquare(2, 1000)))
    assert "nis_out_of_band" in report.flags and not report.usable
    assert report.nis.outside.all()


def test_recovered_filter_warns_but_stays_usable():
    rng = np.random.default_rng(2)
    nis = rng.chisquare(2, 2000)
    nis[:300] *= 5.0  # a bad start, then consistent
    report = check_history(history(nis))
    assert "nis_out_of_band" in report.flags and report.usable


def test_refusals_and_degenerate_clouds():
    rng = np.random.default_rng(3)
    nis = rng.chisquare(2, 400)
    accepted = np.arange(400) % 3 == 0  # two thirds refused
    report = check_history(history(nis, accepted=accepted))
    assert "refused" in report.flags and not report.usable
    ess = np.full(400, 120.0)
    ess[10] = 1.5
    report = check_history(history(nis, ess=ess))
    assert report.flags == ("particles_degenerate",) and not report.usable and report.min_ess == 1.5


def test_window_test_bands_are_those_of_the_window_sum():
    values = np.full(100, 2.0)
    test = window_test(values, np.full(100, 2), MonitorOptions(window=50))
    assert test.means.tolist() == [2.0, 2.0] and not test.outside.any()
    np.testing.assert_allclose(test.bounds[0], stats.chi2.ppf([0.0005, 0.9995], 100) / 50)


def test_bad_options():
    for kwargs in ({"window": 1}, {"probability": 1.0}, {"persistence": 0}, {"max_refused_fraction": 2.0},
                   {"min_ess": 0.5}):
        with pytest.raises(InputError):
            MonitorOptions(**kwargs)


def test_final_error_outside_the_covariance_is_unusable():
    rng = np.random.default_rng(4)
    consistent = check_history(history(rng.chisquare(2, 200)), final_nees=7.0)
    assert consistent.usable and not consistent.flags
    report = check_history(history(rng.chisquare(2, 200)), final_nees=stats.chi2.ppf(0.9999, 6))
    assert report.flags == ("final_error_outside_covariance",) and not report.usable
