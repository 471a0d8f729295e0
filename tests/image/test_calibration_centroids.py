"""Calibration centroids: the predicted blend pull against noise draws, the header's noise model, saturation."""

from __future__ import annotations

import numpy as np
import pytest

from opnav.errors import InputError
from opnav.image.calibration_centroids import (DetectorNoise, blend_bias, calibration_centroids, header_noise)
from opnav.image.centroid import centroid
from opnav.image.io import ImageMeta
from opnav.render.psf import PSF, add_stamps, render_stamps

NOISE = DetectorNoise(read_noise_e=5.0, gain_e_per_adu=1.0, bias_adu=100.0)


def _scene(stars: np.ndarray, flux_e: np.ndarray, shape=(64, 64), sigma_px: float = 1.1) -> np.ndarray:
    """Expected ADU of point sources (pixel-integrated Gaussians) on a 1 e- dark level and the bias."""
    signal = np.full(shape, 1.0)
    add_stamps(signal, render_stamps(stars, flux_e, PSF(sigma_px=sigma_px)))
    return signal + NOISE.bias_adu


def _meta(header) -> ImageMeta:
    return ImageMeta(path="frame.fits", file_format="fits", header=header, channels=1, saturation_adu=60_000.0,
                     invalid=None, lossy=False)


@pytest.mark.parametrize("offset, ratio", [((3.0, 0.5), 0.1), ((-2.2, 2.0), 0.05), ((4.5, -1.0), 0.3)])
def test_blend_bias_is_the_mean_error_over_noise_draws(offset, ratio):
    """The predicted pull of a neighbour is the mean centroid error over 400 noise draws of the pair, within
    4 standard errors of that mean, and far from zero."""
    star = np.array([31.37, 30.81])
    flux = 8000.0
    expected = _scene(np.array([star, star + offset]), np.array([flux, ratio * flux]))
    rng = np.random.default_rng(5)
    draws = rng.poisson(np.broadcast_to(expected - NOISE.bias_adu, (400, *expected.shape))) + NOISE.bias_adu
    draws = draws + rng.normal(0.0, NOISE.read_noise_e, draws.shape)
    errors = []
    for image in draws:
        fit = centroid(image, star[None], window=7, read_noise_e=5.0, gain_e_per_adu=1.0, bias_adu=100.0)
        errors.append(fit.xy[0] - star)
    errors = np.array(errors)
    mean, standard_error = errors.mean(axis=0), errors.std(axis=0, ddof=1) / np.sqrt(len(errors))
    predicted = blend_bias(star[None], np.array([flux]), np.array([101.0]),
                           [np.array([[offset[0], offset[1], ratio * flux]])], 1.1, NOISE)[0]
    assert np.all(np.abs(predicted - mean) < 4.0 * standard_error)
    assert np.linalg.norm(predicted) > 10.0 * np.max(standard_error)


def test_a_star_without_neighbours_has_no_pull():
    assert np.all(blend_bias(np.array([[10.2, 4.7]]), np.array([5000.0]), np.array([101.0]), [np.zeros((0, 3))],
                             1.0, NOISE) == 0.0)


def test_header_noise():
    assert header_noise({"GAIN": 2.0, "RDNOISE": 4.0, "BIASLVL": 50}, "f") == DetectorNoise(4.0, 2.0, 50.0)
    assert header_noise({"GAIN": 2.0, "RDNOISE": 4.0}, "f") == DetectorNoise(4.0, 2.0, 0.0)
    assert header_noise({"GAIN": 2.0}, "f") is None and header_noise(None, "f") is None
    assert header_noise({"GAIN": 0.0, "RDNOISE": 4.0}, "f") is None
    with pytest.raises(InputError, match="f: FITS keyword GAIN must be a number"):
        header_noise({"GAIN": "x", "RDNOISE": 4.0}, "f")


def test_saturated_and_blended_stars_are_left_out_and_the_rest_refitted():
    """Three stars: alone (kept, refitted with the header's noise: its sigma that of the noise model), one
    whose core saturates, one with a neighbour 2 mag fainter 2.5 px away (its pull predicted and left out)."""
    stars = np.array([[12.3, 14.6], [40.2, 20.4], [25.7, 45.1], [28.2, 45.4]])
    flux = np.array([6000.0, 2.0e6, 6000.0, 6000.0 * 10 ** (-0.8)])
    expected = _scene(stars, flux)
    rng = np.random.default_rng(2)
    image = np.minimum(rng.poisson(expected - 100.0) + 100.0 + rng.normal(0.0, 5.0, expected.shape), 60_100.0)
    meta = _meta({"GAIN": 1.0, "RDNOISE": 5.0, "BIASLVL": 100.0})
    neighbours = [np.zeros((0, 3)), np.zeros((0, 3)), np.array([[2.5, 0.3, 2.0]]), np.array([[-2.5, -0.3, -2.0]])]
    seeds = stars[:3] + 0.2
    out = calibration_centroids(image, meta, seeds, np.broadcast_to(np.eye(2), (3, 2, 2)),
                                neighbours=neighbours[:3], frame="frame.fits")
    assert out.refitted
    assert out.keep.tolist() == [True, False, False]
    assert out.saturated.tolist() == [False, True, False] and out.blended[2]
    alone = centroid(expected, stars[:1], read_noise_e=5.0, gain_e_per_adu=1.0, bias_adu=100.0)
    assert np.allclose(np.diag(out.cov[0]), np.diag(alone.cov[0]), rtol=0.1)
    assert np.linalg.norm(out.xy[0] - stars[0]) < 4.0 * np.sqrt(out.cov[0, 0, 0])
    # without the noise keywords the extraction's centroids stay, and no blend is predicted
    bare = calibration_centroids(image, _meta(None), seeds, np.broadcast_to(np.eye(2), (3, 2, 2)),
                                 neighbours=neighbours[:3], frame="frame.fits")
    assert not bare.refitted and np.array_equal(bare.xy, seeds) and bare.keep.tolist() == [True, False, True]


def test_frame_noise_recovers_the_gain_and_the_background():
    """A frame of gain 2.5 e-/ADU, read noise 4 e-, bias 200 ADU, 12 e- of sky, 60 stars of 2,000-40,000 e- and
    600 fainter ones (100-400 e-, in many of the rings): the noise model from the stamps gives the background
    variance within 10 % and the gain within 15 % of the truth."""
    from opnav.image.calibration_centroids import frame_noise

    rng = np.random.default_rng(11)
    gain, read, bias, sky = 2.5, 4.0, 200.0, 12.0
    shape = (400, 400)
    stars = rng.uniform(10, 390, (60, 2))
    faint = rng.uniform(0, 400, (600, 2))
    signal = np.full(shape, sky)
    add_stamps(signal, render_stamps(np.r_[stars, faint], np.r_[rng.uniform(2e3, 4e4, 60), rng.uniform(100, 400, 600)],
                                     PSF(sigma_px=1.2)))
    image = (rng.poisson(signal) + rng.normal(0.0, read, shape)) / gain + bias
    noise = frame_noise(image, stars, np.ones(len(stars), bool))
    background_var_adu2 = (read**2 + sky) / gain**2
    assert abs((noise.read_noise_e / noise.gain_e_per_adu) ** 2 / background_var_adu2 - 1.0) < 0.1
    assert abs(noise.gain_e_per_adu / gain - 1.0) < 0.15
    assert abs(noise.bias_adu - (bias + sky / gain)) < 0.5 * np.sqrt(background_var_adu2)
