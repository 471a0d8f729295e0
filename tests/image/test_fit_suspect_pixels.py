"""fit_point_source with pixels flagged as possible cosmic-ray hits (``suspect``).

Flags that depend on each pixel's own noise (a sharpness test fails on bright fluctuations more
often than on faint ones, and more often on a halo's bright side) take upward fluctuations away
from one side of the source when the flagged pixels are simply left out: the centre moves away
from that side. Putting back the flagged pixels the model explains removes that bias; a real hit
stays out.
"""

import numpy as np
import pytest

from opnav.image.targets import _pixel_gaussian, fit_point_source

SIDE = 15
TRUE_XY = np.array([7.3, 7.1])
FLUX_E = 20000.0
READ_NOISE_E = 5.0


def _scene():
    u = np.arange(SIDE, dtype=float)
    psf, _, _ = _pixel_gaussian(u, u, TRUE_XY[0], TRUE_XY[1], 1.0)
    xx, _ = np.meshgrid(u, u)
    halo = 2000.0 + 300.0 * xx  # a bright neighbour's slope rising toward +x, e- per pixel
    return FLUX_E * psf + halo, halo


def _fit(image, usable, suspect=None):
    return fit_point_source(image, TRUE_XY.round(), usable=usable, psf_sigma_px=1.0, read_noise_e=READ_NOISE_E,
                            gain_e_per_adu=1.0, window=11, suspect=suspect)


def test_noise_dependent_flags_bias_only_when_dropped():
    expected, _ = _scene()
    rng = np.random.default_rng(4)
    sigma = np.sqrt(expected + READ_NOISE_E**2)
    dropped, judged, scatter = [], [], []
    everything = np.ones(expected.shape, bool)
    for _ in range(1500):
        image = rng.poisson(expected) + rng.normal(0.0, READ_NOISE_E, expected.shape)
        # flagged: bright fluctuations on the slope's bright side only
        flags = ((image - expected) > 1.0 * sigma) & (np.arange(SIDE)[None, :] >= 8)
        dropped.append(_fit(image, ~flags).xy[0] - TRUE_XY[0])
        fit = _fit(image, everything, suspect=flags)
        judged.append(fit.xy[0] - TRUE_XY[0])
        scatter.append(np.sqrt(fit.cov[0, 0]))
    dropped, judged = np.array(dropped), np.array(judged)
    se = judged.std() / np.sqrt(judged.size)
    assert judged.std() == pytest.approx(np.mean(scatter), rel=0.1)  # the covariance is the scatter's
    assert abs(judged.mean()) < 3.0 * se  # put back: no bias
    assert dropped.mean() < -6.0 * se  # left out: pushed away from the bright side


def test_a_real_hit_stays_out():
    expected, _ = _scene()
    rng = np.random.default_rng(9)
    image = rng.poisson(expected) + rng.normal(0.0, READ_NOISE_E, expected.shape)
    image[7, 9] += 50000.0  # a cosmic ray on the source's wing
    flags = np.zeros(expected.shape, bool)
    flags[7, 9] = True
    everything = np.ones(expected.shape, bool)
    fit = _fit(image, everything, suspect=flags)
    error = np.hypot(*(fit.xy - TRUE_XY))
    assert error < 4.0 * np.sqrt(np.trace(fit.cov))
    assert np.hypot(*(_fit(image, everything).xy - TRUE_XY)) > 10.0 * error  # taken in, it drags the centre


def test_no_suspects_is_the_plain_fit():
    expected, _ = _scene()
    image = np.random.default_rng(2).poisson(expected).astype(float)
    usable = np.ones(expected.shape, bool)
    plain = _fit(image, usable)
    none_flagged = _fit(image, usable, suspect=np.zeros(expected.shape, bool))
    assert np.array_equal(plain.xy, none_flagged.xy) and np.array_equal(plain.cov, none_flagged.cov)


@pytest.mark.parametrize("name", ["usable", "suspect"])
def test_a_mask_of_another_shape_is_a_clear_error(name):
    from opnav.errors import InputError

    expected, _ = _scene()
    masks = {"usable": np.ones(expected.shape, bool), "suspect": np.zeros(expected.shape, bool)}
    masks[name] = np.ones((SIDE - 1, SIDE), bool)
    with pytest.raises(InputError, match=name):
        fit_point_source(expected, TRUE_XY.round(), psf_sigma_px=1.0, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0,
                         window=11, **masks)
