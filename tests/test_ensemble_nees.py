"""The Monte Carlo NEES test (`opnav.consistency.ensemble_nees`) and the campaign's reading of run files."""

import numpy as np
import pytest
from scipy import stats

from opnav.errors import InputError
from opnav.consistency import chi2_mean_bounds, ensemble_nees
from opnav.studies.campaign import monte_carlo_line, run_nees_arrays

T0 = 4.5e8  # TDB s past J2000, mid-2014


def chi2_runs(runs: int, epochs: int, seed: int, scale: float = 1.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """``runs`` runs of chi-square(6) NEES draws at 60 s epochs, each with its own float noise on the epochs."""
    rng = np.random.default_rng(seed)
    t = T0 + 60.0 * np.arange(epochs)
    return [(t + rng.uniform(-1e-4, 1e-4, epochs), scale * rng.chisquare(6, epochs)) for _ in range(runs)]


def test_consistent_draws_put_about_95_percent_of_epochs_inside():
    runs = chi2_runs(20, 4000, seed=3)
    window = T0 + 60.0 * 1000  # the first 1000 epochs are not judged
    result = ensemble_nees(runs, 6, window)
    assert result.runs == 20 and result.epochs == 3000 and result.dof == 6
    assert result.band == chi2_mean_bounds(6, 20, 0.95)
    # the epochs' run means are independent here, so the count inside is binomial(E, 0.95)
    low, high = stats.binom.interval(0.999, result.epochs, 0.95)
    assert low <= result.share_inside * result.epochs <= high
    assert result.mean == pytest.approx(6.0, abs=0.1)


def test_an_overconfident_filter_falls_out_of_the_band():
    """NEES 1.5 times too large (covariance 1.5 times too small): most epochs' run means above the band."""
    result = ensemble_nees(chi2_runs(20, 4000, seed=3, scale=1.5), 6, T0)
    assert result.share_inside < 0.5
    assert result.mean > result.band[1]


def test_mean_and_share_by_hand():
    """Epochs matched to the second, the window judged on the rounded epochs, bounds per epoch."""
    a = (np.array([0.0, 59.6, 120.0]), np.array([1.0, 2.0, 3.0]))
    b = (np.array([60.0000001, 120.0, 180.0]), np.array([5.0, 30.0, 11.0]))
    result = ensemble_nees([a, b], 6, 60.0)
    # shared in the window: 60 s (a's 59.6 rounds to it) and 120 s; run means 3.5 and 16.5
    low, high = chi2_mean_bounds(6, 2, 0.95)
    assert low < 3.5 < high < 16.5
    assert (result.runs, result.epochs, result.mean, result.share_inside) == (2, 2, 10.0, 0.5)
    assert result.to_dict()["band"] == [low, high]


def test_nan_before_the_window_is_not_judged():
    a = (np.array([0.0, 60.0]), np.array([np.nan, 6.0]))
    assert ensemble_nees([a, a], 6, 60.0).mean == 6.0


@pytest.mark.parametrize("runs, match", [
    ([], "no runs"),
    ([(np.arange(3.0), np.ones(2))], "one length"),
    ([(np.arange(3.0), np.array([1.0, np.nan, 1.0]))], "NaN or infinite NEES"),
    ([(np.array([0.0, np.nan]), np.ones(2))], "not finite"),
    ([(np.array([0.0, 0.2]), np.ones(2))], "within one second"),
    ([(np.arange(3.0), np.ones(3)), (np.arange(3.0) + 10.0, np.ones(3))], "share no epoch"),
])
def test_bad_inputs_raise(runs, match):
    with pytest.raises(InputError, match=match):
        ensemble_nees(runs, 6, 0.0)


def test_bad_probability_and_dof_raise():
    runs = chi2_runs(2, 5, seed=1)
    with pytest.raises(InputError, match="probability"):
        ensemble_nees(runs, 6, T0, probability=1.0)
    with pytest.raises(InputError, match="dof >= 1"):
        ensemble_nees(runs, 0, T0)


def test_campaign_reads_or_explains_a_runs_file(tmp_path):
    """A run through the runner: ``filters/<name>.npz``; a quick run: ``nees/<name>.npz`` with its hash."""
    ordinary = tmp_path / "run_000"
    (ordinary / "filters").mkdir(parents=True)
    np.savez(ordinary / "filters" / "ekf.npz", t_tdb_s=np.arange(3.0), nees=np.ones(3), error=np.zeros((3, 6)))
    epochs, values = run_nees_arrays(ordinary, "ekf", {})
    assert epochs.tolist() == [0.0, 1.0, 2.0] and values.tolist() == [1.0, 1.0, 1.0]
    (ordinary / "filters" / "ekf.npz").write_bytes(b"PK\x03\x04 cut short")
    with pytest.raises(InputError, match=r"ekf\.npz cannot be read.*resume the campaign"):
        run_nees_arrays(ordinary, "ekf", {})
    with pytest.raises(InputError, match=r"ukf\.npz is missing"):
        run_nees_arrays(ordinary, "ukf", {})
    quick = tmp_path / "run_001"
    (quick / "nees").mkdir(parents=True)
    np.savez(quick / "nees" / "ekf.npz", t_tdb_s=np.arange(3.0), nees=np.ones(3), hash=np.str_("abc"))
    assert run_nees_arrays(quick, "ekf", {"quick": {"hash": "abc"}})[1].size == 3
    with pytest.raises(InputError, match="written by another run"):
        run_nees_arrays(quick, "ekf", {"quick": {"hash": "def"}})
    with pytest.raises(InputError, match=r"nees/ukf\.npz is missing.*summary\.json"):
        run_nees_arrays(quick, "ukf", {"quick": {"hash": "abc"}})


def test_campaign_line():
    test = {"available": True, **ensemble_nees(chi2_runs(4, 50, seed=2), 6, T0).to_dict()}
    line = monte_carlo_line("ekf", test)
    assert line.startswith("ekf: Monte Carlo NEES: mean over 4 runs at each of 50 epochs of the window: ")
    assert "(95 % band [" in line and "share of epochs inside: " in line
    assert monte_carlo_line("ukf", {"available": False, "reason": "x is missing"}) == \
        "ukf: Monte Carlo NEES: not available (x is missing)"
