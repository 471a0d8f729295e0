"""opnav.studies.bound_ratio: the seeds' RMS over the bound and the runs' NEES, each held against draws
whose truth is known (a filter at the bound, short of it, below it; consistent and overconfident runs)."""

import numpy as np
import pytest

from opnav.errors import InputError
from opnav.studies.bound_ratio import mean_nees, rms_over_bound

BOUND_KM = 44.0
SEEDS = 50
CAMPAIGNS = 200


def _campaign_rms(rng, scale: float, dof: int) -> np.ndarray:
    """Each seed's window RMS when its error is Gaussian with ``scale``^2 times the bound's covariance,
    spread over ``dof`` directions that hold still over the window (S1's weak direction: dof 1)."""
    return np.sqrt(scale**2 * BOUND_KM**2 * rng.chisquare(dof, SEEDS) / dof)


@pytest.mark.parametrize("dof", [1, 3])
def test_a_filter_at_the_bound_has_1_inside_its_interval_about_95_percent_of_the_time(dof):
    rng = np.random.default_rng(11)
    verdicts = [rms_over_bound(_campaign_rms(rng, 1.0, dof), BOUND_KM, resamples=2000, rng=k).verdict
                for k in range(CAMPAIGNS)]
    covered = verdicts.count("reaches the bound") / CAMPAIGNS
    # 95 % nominal; the bootstrap of a 1-dof chi-square mean from 50 seeds covers about 92 %
    # (200 campaigns: +-1.9 % binomial); 88 % is 2 binomial sigmas under that
    assert covered >= 0.88
    assert verdicts.count("below the bound") > 0 and verdicts.count("above the bound") > 0  # both tails


@pytest.mark.parametrize(("scale", "verdict"), [(0.7, "below the bound"), (1.4, "above the bound")])
def test_a_filter_off_the_bound_by_30_to_40_percent_is_found_out(scale, verdict):
    rng = np.random.default_rng(12)
    verdicts = [rms_over_bound(_campaign_rms(rng, scale, 1), BOUND_KM, resamples=2000, rng=k).verdict
                for k in range(CAMPAIGNS)]
    assert verdicts.count(verdict) / CAMPAIGNS >= 0.7
    assert verdicts.count("reaches the bound") / CAMPAIGNS <= 0.3


def test_the_ratio_is_the_rms_over_seeds_of_the_seeds_rms_not_their_mean():
    rms = np.array([10.0, 20.0, 70.0])
    result = rms_over_bound(rms, 40.0)
    assert result.rms_km == pytest.approx(np.sqrt((100.0 + 400.0 + 4900.0) / 3.0))
    assert result.ratio == pytest.approx(result.rms_km / 40.0)
    assert result.low <= result.ratio <= result.high
    assert rms_over_bound(rms, 40.0).high == result.high  # the same interval for the same seeds


def test_bad_input_is_refused_with_a_clear_message():
    with pytest.raises(InputError, match="at least 3"):
        rms_over_bound([1.0, 2.0], 1.0)
    with pytest.raises(InputError, match="positive bound"):
        rms_over_bound([1.0, 2.0, 3.0], 0.0)
    with pytest.raises(InputError, match="finite"):
        mean_nees([6.0, np.nan])


def _run_nees(rng, epochs: int, rho: float, variance: float) -> float:
    """One run's mean NEES over ``epochs`` of an AR(1) error (correlation ``rho`` per epoch) of 6 states
    whose true covariance is ``variance`` times the filter's."""
    e = np.empty((epochs, 6))
    e[0] = rng.standard_normal(6)
    for k in range(1, epochs):
        e[k] = rho * e[k - 1] + np.sqrt(1.0 - rho**2) * rng.standard_normal(6)
    return float(np.mean(variance * np.sum(e**2, axis=1)))


@pytest.mark.parametrize("rho", [0.0, 0.9, 1.0])
def test_consistent_runs_fall_in_the_nees_band_whatever_their_correlation(rho):
    rng = np.random.default_rng(13)
    inside = [mean_nees([_run_nees(rng, 50, rho, 1.0) for _ in range(SEEDS)]).inside for _ in range(CAMPAIGNS)]
    assert np.mean(inside) >= 0.9


def test_overconfident_runs_fall_above_the_nees_band():
    rng = np.random.default_rng(14)
    results = [mean_nees([_run_nees(rng, 50, 0.9, 1.4) for _ in range(SEEDS)]) for _ in range(50)]
    assert all(r.mean > r.high for r in results)
