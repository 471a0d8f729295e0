"""Plane-background PSF fit of a moon next to a bright primary: unbiased, honest covariance."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ndtr
from scipy.stats import chi2

from opnav.errors import InputError, NoSolutionError
from opnav.image.targets import fit_point_source

SIGMA_PX = 1.0
READ_NOISE_E = 6.0
GAIN = 2.0
BIAS = 100.0


def _stamp(rng, xy, flux_e, *, shape=(25, 25), slope_e=(40.0, 15.0), level_e=300.0):
    """Pixel-integrated Gaussian + sloping background, Poisson + read noise, ADU."""
    rows, cols = np.indices(shape, dtype=float)

    def axis_integral(coord, centre):
        return ndtr((coord + 0.5 - centre) / SIGMA_PX) - ndtr((coord - 0.5 - centre) / SIGMA_PX)

    source = flux_e * axis_integral(cols, xy[0]) * axis_integral(rows, xy[1])
    background = level_e + slope_e[0] * (cols - xy[0]) / 10.0 + slope_e[1] * (rows - xy[1]) / 10.0
    electrons = rng.poisson(np.clip(source + background, 0.0, None)) + rng.normal(0.0, READ_NOISE_E, shape)
    return electrons / GAIN + BIAS


@pytest.mark.parametrize("masked", [False, True])
def test_fit_is_unbiased_and_its_covariance_honest(masked):
    rng = np.random.default_rng(11)
    trials = 300
    nees, errors = [], []
    for _ in range(trials):
        truth = np.array([12.0, 12.0]) + rng.uniform(-0.5, 0.5, 2)
        image = _stamp(rng, truth, 20_000.0)
        usable = np.ones(image.shape, bool)
        if masked:
            # a bloomed column two pixels right of the source, left out of the fit
            usable[:, int(round(truth[0])) + 2] = False
        fit = fit_point_source(image, np.rint(truth), usable=usable, psf_sigma_px=SIGMA_PX,
                               read_noise_e=READ_NOISE_E, gain_e_per_adu=GAIN, bias_adu=BIAS)
        error = fit.xy - truth
        errors.append(error)
        nees.append(error @ np.linalg.solve(fit.cov, error))
    errors = np.array(errors)
    lo, hi = chi2.ppf([0.001, 0.999], 2 * trials) / trials
    assert lo < np.mean(nees) < hi
    standard_error = errors.std(axis=0, ddof=1) / np.sqrt(trials)
    assert np.all(np.abs(errors.mean(axis=0)) < 4.0 * standard_error)


def test_masked_column_costs_precision_not_accuracy():
    rng = np.random.default_rng(5)
    truth = np.array([12.2, 11.7])
    image = _stamp(rng, truth, 20_000.0)
    usable = np.ones(image.shape, bool)
    full = fit_point_source(image, np.rint(truth), usable=usable, psf_sigma_px=SIGMA_PX,
                            read_noise_e=READ_NOISE_E, gain_e_per_adu=GAIN, bias_adu=BIAS)
    usable[:, 13] = False
    masked = fit_point_source(image, np.rint(truth), usable=usable, psf_sigma_px=SIGMA_PX,
                              read_noise_e=READ_NOISE_E, gain_e_per_adu=GAIN, bias_adu=BIAS)
    assert masked.psf_fraction < full.psf_fraction
    assert masked.cov[0, 0] > full.cov[0, 0]


def test_bad_input_is_refused():
    image = np.zeros((25, 25))
    usable = np.ones(image.shape, bool)
    with pytest.raises(InputError, match="window"):
        fit_point_source(image, np.array([12.0, 12.0]), usable=usable, psf_sigma_px=1.0,
                         read_noise_e=5.0, gain_e_per_adu=1.0, window=4)
    with pytest.raises(NoSolutionError, match="leaves the frame"):
        fit_point_source(image, np.array([1.0, 12.0]), usable=usable, psf_sigma_px=1.0,
                         read_noise_e=5.0, gain_e_per_adu=1.0)
