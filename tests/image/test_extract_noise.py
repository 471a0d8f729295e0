"""The frame's noise model fitted by the centroider on a frame with saturated stars, bloom trails,
blends and cosmic rays: background variance and gain against the detector's, covariances against
the scatter over noise draws."""

import numpy as np
import pytest
from scipy.special import ndtr

from opnav.camera import Camera
from opnav.image.centroid import centroid
from opnav.image.detect import detect
from opnav.image.extract import extract_sources
from opnav.render.detector import DetectorOptions, read_out
from opnav.render.frames_io import saturation_level_adu

SIDE = 512
PSF_SIGMA = 1.0
CAMERA = Camera(SIDE, SIDE, focal_length_mm=100.0, pixel_pitch_um=13.0, gain_e_per_adu=2.0, read_noise_e=5.0,
                dark_current_e_s=20.0, exposure_s=1.0)
#: Background variance of the camera, ADU^2: read noise, dark current's shot noise and rounding to ADU.
TRUE_VAR = (CAMERA.read_noise_e**2 + CAMERA.dark_current_e_s * CAMERA.exposure_s) / CAMERA.gain_e_per_adu**2 + 1.0 / 12


def _stars(rng):
    """Signal (electrons) of isolated stars on a jittered grid, 6 stars 100x over the full well (clipped
    cores, bloom trails) and 6 blends (pairs 2-3 px apart); returns the image and the isolated stars'
    true (x, y) and electrons."""
    cell = 24
    centres = np.array([(c, r) for r in range(cell, SIDE - cell, cell) for c in range(cell, SIDE - cell, cell)], float)
    centres += rng.uniform(-4.0, 4.0, centres.shape)
    rng.shuffle(centres)
    flux = np.exp(rng.uniform(np.log(800.0), np.log(40_000.0), len(centres)))
    saturated, blends, isolated = slice(0, 6), slice(6, 12), slice(12, None)
    flux[saturated] = 6e6
    xy = [centres]
    fluxes = [flux]
    angle = rng.uniform(0.0, 2.0 * np.pi, 6)
    sep = rng.uniform(2.0, 3.0, 6)
    xy.append(centres[blends] + sep[:, None] * np.column_stack([np.cos(angle), np.sin(angle)]))
    fluxes.append(flux[blends] * rng.uniform(0.3, 1.0, 6))
    signal = np.zeros((SIDE, SIDE))
    grid = np.arange(SIDE)
    for (x, y), f in zip(np.concatenate(xy), np.concatenate(fluxes)):
        c0, r0 = int(x) - 10, int(y) - 10
        c, r = grid[max(c0, 0):c0 + 21], grid[max(r0, 0):r0 + 21]
        ex = ndtr((c + 0.5 - x) / PSF_SIGMA) - ndtr((c - 0.5 - x) / PSF_SIGMA)
        ey = ndtr((r + 0.5 - y) / PSF_SIGMA) - ndtr((r - 0.5 - y) / PSF_SIGMA)
        signal[r[0]:r[-1] + 1, c[0]:c[-1] + 1] += f * np.outer(ey, ex)
    return signal, centres[isolated], flux[isolated]


@pytest.fixture(scope="module")
def frame():
    rng = np.random.default_rng(35)
    signal, xy, electrons = _stars(rng)
    # four times the default rate of cosmic rays: tracks through stamps
    options = DetectorOptions(cosmic_ray_rate_cm2_s=20.0)
    images = [read_out(signal, CAMERA, options=options, rng=rng) for _ in range(10)]
    return images, xy, electrons


def test_the_fitted_noise_model_is_the_detector_s_despite_saturated_stars_and_blends(frame):
    images, _, _ = frame
    clip = saturation_level_adu(CAMERA)
    image = images[0]
    assert (image >= clip).sum() > 100  # clipped cores and bloom trails are in the frame
    found = detect(image, saturation_adu=clip)
    # every detection is fitted, saturated stars, blends and cosmic-ray hits included
    result = centroid(image, found.xy, saturation_adu=clip)
    assert result.noise_var_adu2 == pytest.approx(TRUE_VAR, rel=0.10)
    assert result.noise_gain_e_per_adu == pytest.approx(CAMERA.gain_e_per_adu, rel=0.10)


@pytest.mark.parametrize("known", [False, True], ids=["fitted", "header"])
def test_faint_stars_scatter_as_their_covariances_say(frame, known):
    images, xy_true, electrons = frame
    noise = {"read_noise_e": CAMERA.read_noise_e, "gain_e_per_adu": CAMERA.gain_e_per_adu,
             "bias_adu": CAMERA.bias_adu} if known else {}
    faint = electrons < 5_000
    clip = saturation_level_adu(CAMERA)
    errors, variances = [], []
    for image in images:
        found = extract_sources(image, max_stars=500, saturation_adu=clip, **noise)
        dist = np.hypot(*(found.xy[None, :, :] - xy_true[faint][:, None, :]).transpose(2, 0, 1))
        nearest = np.argmin(dist, axis=1)
        hit = dist[np.arange(len(nearest)), nearest] < 1.0
        err = np.full((faint.sum(), 2), np.nan)
        var = np.full((faint.sum(), 2), np.nan)
        err[hit] = found.xy[nearest[hit]] - xy_true[faint][hit]
        var[hit] = np.diagonal(found.cov[nearest[hit]], axis1=1, axis2=2)
        errors.append(err)
        variances.append(var)
    errors, variances = np.array(errors), np.array(variances)
    every = np.all(np.isfinite(errors), axis=(0, 2))
    assert every.sum() >= 100
    # scatter about each star's own mean (its fixed bias is not noise) over the covariance's sigma
    scatter2 = np.var(errors[:, every], axis=0, ddof=1)
    sigma2 = np.mean(variances[:, every], axis=0)
    ratio = float(np.sqrt(np.mean(scatter2) / np.mean(sigma2)))
    # 10 draws of 100+ stars: the ratio's sampling error is ~2 %
    assert 0.8 <= ratio <= 1.25
