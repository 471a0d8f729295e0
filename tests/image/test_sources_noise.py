"""opnav centroid's noise model from a FITS header (opnav.image.sources.image_sources)."""

import numpy as np

from opnav.image.io import ImageMeta
from opnav.image.sources import image_sources

BIAS_ADU, GAIN, READ_E = 500.0, 2.0, 5.0


def _frame(rng):
    """A 256 px frame of 40 Gaussian stars (sigma 1.2 px) on a bias of 500 ADU, gain 2 e-/ADU."""
    shape = (256, 256)
    xy = rng.uniform(20, 236, (40, 2))
    electrons = rng.uniform(3e3, 3e4, 40)
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    signal = np.zeros(shape)
    for (x, y), e in zip(xy, electrons):
        signal += e / (2 * np.pi * 1.44) * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.44))
    electrons_px = rng.poisson(signal + 20.0) + rng.normal(0.0, READ_E, shape)
    return BIAS_ADU + electrons_px / GAIN


def _sigmas(image, header):
    meta = ImageMeta("frame.fits", "fits", header, 1, None, None, False)
    found = image_sources(image, meta)
    ok = found.centroids.ok
    return found.detections.xy[ok], np.sqrt(found.centroids.cov[ok, 0, 0])


def test_a_header_without_biaslvl_does_not_count_the_bias_as_shot_noise():
    """RDNOISE and GAIN without BIASLVL: the stars' sigmas are those of the full header's model within
    15 % (with the bias taken for 0, the 500 ADU pedestal's 'shot noise' made them 1.7x larger)."""
    image = _frame(np.random.default_rng(3))
    full_xy, full = _sigmas(image, {"RDNOISE": READ_E, "GAIN": GAIN, "BIASLVL": BIAS_ADU})
    part_xy, part = _sigmas(image, {"RDNOISE": READ_E, "GAIN": GAIN})
    assert len(full) >= 30 and np.array_equal(full_xy, part_xy)
    ratio = np.median(part / full)
    assert 0.85 < ratio < 1.15, ratio
