"""Detection on clipped, quantised frames: 8-bit cameras whose sky sits a few ADU above zero (issue 40 item 2)."""

import math
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from opnav.camera import Camera
from opnav.catalog import synthetic_catalog
from opnav.errors import FrameError
from opnav.image.detect import MAX_REJECTED_FRACTION, detect, estimate_background
from opnav.image.extract import extract_sources
from opnav.image.starid import solve_image
from opnav.image.starid_index import build_index


def clipped_sky(rng, shape, *, level, sigma, step=1.0, top=255.0):
    """A normal sky read out in whole steps of ``step`` ADU and clipped to [0, top], as an ADC does."""
    return np.clip(np.rint(rng.normal(level, sigma, shape) / step) * step, 0.0, top)


@pytest.mark.parametrize(
    "level, sigma, step",
    [
        (1.0, 0.75, 1.0),  # the public 8-bit tracker frames: ~25 % of the pixels at 0
        (0.3, 1.5, 1.0),  # clipped harder: ~45 % at 0
        (2.0, 1.0, 1.0),  # barely clipped
        (4.0, 3.0, 4.0),  # a 12-bit ADC stored in a 16-bit file (steps of 4 ADU)
        (0.5, 0.8, 1e-6),  # floating-point data clipped at zero (not quantised)
    ],
)
def test_noise_of_a_clipped_quantised_sky_is_within_ten_percent(level, sigma, step):
    rng = np.random.default_rng(40)
    image = clipped_sky(rng, (256, 320), level=level, sigma=sigma, step=step)
    assert np.mean(image == 0.0) > 0.02  # the sky is clipped
    background = estimate_background(image)
    noise = np.median(background.noise_tiles)
    assert abs(noise / sigma - 1.0) < 0.1, noise
    # the level is the sky's (the mean of the unclipped distribution), not the clipped frame's median
    assert abs(np.median(background.level_tiles) - level) < 0.1 * sigma


def test_noise_never_below_the_rounding_noise_of_the_value_step():
    # a sky quantised far more coarsely than its noise: nearly every value is the same integer
    rng = np.random.default_rng(41)
    image = np.rint(rng.normal(20.0, 0.2, (128, 128)))
    background = estimate_background(image)
    assert background.noise.min() >= 1.0 / math.sqrt(12.0) - 1e-12


@pytest.mark.parametrize("value", [0.0, 255.0, 17.0])
def test_a_constant_frame_is_refused_in_one_line(value):
    image = np.full((64, 96), value)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(FrameError, match="blank") as caught:
            extract_sources(image, saturation_adu=255.0)
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize("fill", [0.0, 3.0])
def test_no_division_by_zero_on_a_nearly_flat_frame(fill):
    # all one value but a star and a saturated hot pixel: every tile's noise is unmeasurable
    image = np.full((128, 160), fill)
    yy, xx = np.mgrid[0:128, 0:160]
    image += np.rint(200.0 * np.exp(-0.5 * ((xx - 70.3) ** 2 + (yy - 60.6) ** 2) / 1.2**2))
    image[20, 30] = 255.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's divide-by-zero and invalid-value warnings fail the test
        found = extract_sources(np.clip(image, 0.0, 255.0), saturation_adu=255.0)
    assert np.all(np.isfinite(found.snr)) and np.all(np.isfinite(found.xy))
    assert np.min(np.hypot(*(found.xy - [70.3, 60.6]).T)) < 0.2


def test_hot_pixel_rejection_never_takes_a_large_fraction_of_the_frame():
    # a frame whose every other pixel is a lone spike: the sharpness test flags them all
    rng = np.random.default_rng(42)
    image = rng.normal(100.0, 2.0, (128, 128))
    spikes = rng.random(image.shape) < 0.05
    image[spikes] += rng.uniform(50.0, 500.0, spikes.sum())
    found = detect(image)
    assert found.rejected.sum() <= MAX_REJECTED_FRACTION * image.size
    # the pixels kept as rejected are the most significant ones
    assert image[found.rejected].min() >= np.percentile(image[spikes & ~found.rejected], 50)


def test_a_wide_saturated_core_is_one_source_centred_from_its_wings():
    rng = np.random.default_rng(43)
    yy, xx = np.mgrid[0:120, 0:140]
    errors = []
    for x0, y0 in rng.uniform([40.0, 40.0], [100.0, 80.0], (8, 2)):
        latent = 1.0 + rng.normal(0.0, 0.75, xx.shape)
        latent += 2e5 / (2 * math.pi * 1.2**2) * np.exp(-0.5 * ((xx - x0) ** 2 + (yy - y0) ** 2) / 1.2**2)
        image = np.clip(np.rint(latent), 0.0, 255.0)
        assert (image == 255.0).sum() >= 25  # a plateau wider than the 7-px stamp's core
        found = extract_sources(image, saturation_adu=255.0)
        near = np.hypot(*(found.xy - [x0, y0]).T) < 6.0
        assert near.sum() == 1  # one source, not split, not dropped
        errors.append(found.xy[near][0] - [x0, y0])
        assert np.all(np.isfinite(found.cov[near]))
    assert np.sqrt(np.mean(np.square(errors))) < 0.05


def test_a_core_clipped_at_a_full_well_below_the_file_range_is_centred_from_its_wings():
    # a 16-bit file of a detector whose wells fill at 20,000 ADU: the plateau is found from the frame
    rng = np.random.default_rng(47)
    yy, xx = np.mgrid[0:120, 0:140]
    errors = []
    for x0, y0 in rng.uniform([40.0, 40.0], [100.0, 80.0], (6, 2)):
        latent = 100.0 + rng.normal(0.0, 5.0, xx.shape)
        latent += 8e6 / (2 * math.pi * 1.2**2) * np.exp(-0.5 * ((xx - x0) ** 2 + (yy - y0) ** 2) / 1.2**2)
        image = np.rint(np.minimum(latent, 20000.0))
        assert (image == 20000.0).sum() >= 25
        found = extract_sources(image, saturation_adu=65535.0)
        near = np.hypot(*(found.xy - [x0, y0]).T) < 6.0
        assert near.sum() == 1
        errors.append(found.xy[near][0] - [x0, y0])
    assert np.sqrt(np.mean(np.square(errors))) < 0.05


CAMERA = Camera.from_fov(20.0, 640, 480)


def render_clipped_8bit(camera, R_icrf_cam, catalog, rng, *, vmag_limit):
    """An 8-bit frame whose sky sits at ~1 ADU with 0.75 ADU of noise (a quarter of it at 0) and whose
    brightest stars clip at 255: catalog stars, a Gaussian PSF of 1.2 px, 11 e-/ADU."""
    v_cam = R_icrf_cam.inv().apply(np.array(catalog.unit_vectors()))
    xy = camera.project(v_cam)
    rows = np.flatnonzero(camera.in_frame(xy, margin_px=-3.0) & (v_cam[:, 2] > 0) & (catalog.vmag <= vmag_limit + 0.5))
    electrons = 1500.0 * 10.0 ** (-0.4 * (catalog.vmag[rows] - vmag_limit))
    signal = np.full(camera.shape, 2.0)
    yy, xx = np.mgrid[0 : camera.height_px, 0 : camera.width_px]
    for (x, y), f in zip(xy[rows], electrons):
        box = (slice(max(int(y) - 10, 0), int(y) + 11), slice(max(int(x) - 10, 0), int(x) + 11))
        r2 = (xx[box] - x) ** 2 + (yy[box] - y) ** 2
        signal[box] += f * np.exp(-0.5 * r2 / 1.2**2) / (2 * math.pi * 1.2**2)
    charge = rng.poisson(signal) + rng.normal(0.0, 8.0, signal.shape)
    return np.clip(np.rint(charge / 11.0 + 0.8), 0.0, 255.0)


def test_a_clipped_8bit_frame_solves():
    sky = synthetic_catalog(8000, rng=np.random.default_rng(1), vmag_range=(1.0, 7.0))
    index = build_index(sky, fov_min_deg=17.0, fov_max_deg=23.0, vmag_limit=6.5)
    rng = np.random.default_rng(44)
    for seed in (45, 46):
        truth = Rotation.random(random_state=seed)
        image = render_clipped_8bit(CAMERA, truth, sky, rng, vmag_limit=6.5)
        assert 0.15 < np.mean(image == 0.0) < 0.4 and (image == 255.0).any()
        solved = solve_image(image, index=index, fov_deg=20.0, fov_tolerance=0.1, saturation_adu=255.0)
        corners = np.array([[0.0, 0.0], [639.0, 0.0], [0.0, 479.0], [639.0, 479.0]])
        moved = CAMERA.project(solved.identification.R_icrf_cam.inv().apply(truth.apply(CAMERA.unproject(corners))))
        assert np.max(np.linalg.norm(moved - corners, axis=1)) < 2.0
