"""NEES over the whole arc and over the window, each with its band (issue 40 item 4), and a diverged
filter's covariance named in one line instead of numpy's traceback."""

import numpy as np
import pytest
from scipy import stats

from opnav.errors import CovarianceError
from opnav.studies.common import NEES_STATES, epoch_nees, nees_figures


def test_consistent_errors_fill_the_band_over_the_arc_and_the_window():
    rng = np.random.default_rng(40)
    epochs = 4000
    covs = np.stack([np.diag(rng.uniform(0.5, 2.0, NEES_STATES)) for _ in range(epochs)])
    truth = rng.normal(size=(epochs, NEES_STATES))
    states = truth + np.einsum("nij,nj->ni", np.linalg.cholesky(covs), rng.standard_normal((epochs, NEES_STATES)))
    values = epoch_nees(states, covs, truth, np.arange(epochs, dtype=float))
    window = np.arange(epochs) >= epochs // 2
    figures = nees_figures(values, window)
    np.testing.assert_allclose(figures["nees_band95"], stats.chi2.ppf([0.025, 0.975], NEES_STATES), rtol=1e-9)
    assert figures["nees_epochs_arc"] == epochs and figures["nees_epochs_window"] == epochs // 2
    # independent epochs: the arc's share inside the 95 % band within its binomial 99.9 % interval, and
    # each part's mean within the band of the mean of that many chi-square(6) values
    low, high = stats.binom.interval(0.999, epochs, 0.95)
    assert low / epochs <= figures["nees_fraction_in_95_arc"] <= high / epochs
    for part, mean in (("arc", values.mean()), ("window", values[window].mean())):
        band = figures[f"nees_band95_mean_{part}"]
        assert band[0] <= mean <= band[1]
    assert figures["nees_mean_arc"] == pytest.approx(values.mean())


def test_an_error_that_grows_before_the_window_shows_in_the_arc_figures_only():
    values = np.r_[np.full(50, 40.0), np.full(50, 6.0)]
    window = np.arange(100) >= 50
    figures = nees_figures(values, window)
    assert figures["nees_fraction_in_95_arc"] == pytest.approx(0.5) and figures["nees_mean_arc"] == pytest.approx(23.0)


def test_a_covariance_that_is_not_positive_definite_is_named_by_its_epoch():
    covs = np.stack([np.eye(6)] * 5)
    covs[3, 0, 0] = -1.0
    with pytest.raises(CovarianceError, match=r"epoch 4 of 5\) is not positive definite: the filter diverged"):
        epoch_nees(np.zeros((5, 6)), covs, np.zeros((5, 6)), 4.586e8 + np.arange(5.0))
