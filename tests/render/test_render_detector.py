"""Detector model: noise statistics, cosmic rays, blooming (acceptance: variance within 2 %)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from opnav.camera import Camera
from opnav.errors import InputError
from opnav.render import DetectorOptions, read_out
from opnav.render.detector import MIP_ELECTRONS_PER_UM, bloom, flat_variance_adu2

QUIET = DetectorOptions(cosmic_ray_rate_cm2_s=0.0, hot_pixel_fraction=0.0)


@pytest.mark.parametrize("signal_e, gain", [(50.0, 1.0), (2000.0, 2.5), (20_000.0, 4.0)])
def test_flat_field_variance_matches_model(signal_e, gain):
    camera = Camera.from_fov(5.0, 512, 512, gain_e_per_adu=gain, read_noise_e=6.0, dark_current_e_s=3.0)
    rng = np.random.default_rng(7)
    frame = read_out(np.full(camera.shape, signal_e), camera, options=QUIET, rng=rng).astype(float)
    model = flat_variance_adu2(signal_e, camera)
    measured = frame.var(ddof=1)
    # Relative standard error of a variance from N samples is sqrt(2/N) = 0.3 % here.
    assert measured == pytest.approx(model, rel=0.02)
    n = frame.size
    lo, hi = chi2.ppf([0.0005, 0.9995], n - 1) / (n - 1)
    # Pure Poisson + Gaussian + rounding: the sample variance also passes a chi-square bound
    # (loosened by the small non-Gaussian excess kurtosis of Poisson noise).
    assert lo * 0.99 < measured / model < hi * 1.01
    mean_expected = (signal_e + camera.dark_current_e_s * camera.exposure_s) / gain + camera.bias_adu
    assert frame.mean() == pytest.approx(mean_expected, abs=5 * np.sqrt(model / n) + 0.01)


def test_cosmic_ray_charge_matches_rate_and_track_model():
    camera = Camera.from_fov(5.0, 512, 512, exposure_s=20.0, read_noise_e=0.0, dark_current_e_s=0.0)
    options = DetectorOptions(cosmic_ray_rate_cm2_s=5.0, hot_pixel_fraction=0.0, depletion_um=10.0)
    rng = np.random.default_rng(11)
    totals = []
    for _ in range(20):
        totals.append(read_out(np.zeros(camera.shape), camera, options=options, rng=rng).astype(float).sum() - camera.bias_adu * camera.width_px * camera.height_px)
    area_cm2 = (512 * camera.pixel_pitch_um * 1e-4) ** 2
    events = 5.0 * area_cm2 * camera.exposure_s
    # Isotropic incidence: mean path = depletion * E[1/cos] = 2 * depletion.
    expected = events * MIP_ELECTRONS_PER_UM * 2.0 * options.depletion_um
    # Edge losses are small (tracks are a few pixels long); compound-Poisson scatter per frame
    # ~ sqrt(events) * ~2 x mean charge; 20 frames.
    assert np.mean(totals) == pytest.approx(expected, rel=0.15)


def test_cosmic_ray_storm_changes_only_the_pixels_it_hits():
    # Faults compare a storm with the clean run of the same seed: the photon and read noise
    # must be the same draws, or the comparison is one between two noise realisations.
    camera = Camera.from_fov(5.0, 256, 256, exposure_s=20.0)
    signal = np.full(camera.shape, 300.0)
    frames = [read_out(signal, camera, options=DetectorOptions(cosmic_ray_rate_cm2_s=rate, hot_pixel_fraction=0.0,
                                                               blooming=False),
                       rng=np.random.default_rng([4, 2])).astype(float) for rate in (0.0, 5.0, 50.0)]
    for stormy in frames[1:]:
        hit = stormy != frames[0]
        assert 0 < hit.sum() < 0.2 * hit.size
        assert np.all(stormy[hit] > frames[0][hit])  # charge only added


def test_an_exposure_whose_cosmic_rays_would_cross_every_pixel_many_times_is_refused_in_one_line():
    # 1e9 s on a 1 MP detector is ~1e9 tracks: the track list alone would need tens of TiB.
    camera = Camera.from_fov(1.0, 64, 64, exposure_s=1.0e9)
    with pytest.raises(InputError, match=r"exposure_s = 1e\+09 s.*cosmic_ray_rate_cm2_s = 0"):
        read_out(np.zeros(camera.shape), camera, rng=np.random.default_rng(1))
    # the same exposure without cosmic rays is read out (and saturates on dark current)
    quiet = DetectorOptions(cosmic_ray_rate_cm2_s=0.0, hot_pixel_fraction=0.0)
    frame = read_out(np.zeros(camera.shape), camera, options=quiet, rng=np.random.default_rng(1))
    assert frame.shape == camera.shape


def test_blooming_conserves_charge_along_columns():
    charge = np.zeros((50, 7))
    charge[25, 3] = 10 * 1000.0
    charge[10, 1] = 900.0
    out = bloom(charge, 1000.0)
    assert out.max() <= 1000.0
    assert out.sum() == pytest.approx(charge.sum())
    np.testing.assert_array_equal(out[:, [0, 2, 4, 5, 6]], 0.0)
    # 9000 e- of excess, 4500 each way: 4 full pixels and a 500 e- tail on each side.
    np.testing.assert_allclose(out[20:31, 3], [500] + [1000] * 9 + [500])
    # Spill off the column end is lost, never wrapped.
    edge = np.zeros((5, 1))
    edge[0, 0] = 4000.0
    out_edge = bloom(edge, 1000.0)
    # 3000 e- excess: the 1500 e- sent up leave the column, the 1500 sent down stay.
    np.testing.assert_allclose(out_edge[:, 0], [1000, 1000, 500, 0, 0])


def test_saturation_and_adc_clipping():
    camera = Camera.from_fov(5.0, 32, 32, full_well_e=30_000.0, bit_depth=12, gain_e_per_adu=5.0)
    frame = read_out(np.full(camera.shape, 1e6), camera, options=QUIET, rng=np.random.default_rng(1))
    assert frame.max() <= 2**12 - 1
    assert frame.dtype == np.uint16


def test_read_out_rejects_bad_input():
    camera = Camera.from_fov(5.0, 16, 16)
    with pytest.raises(InputError, match="rng"):
        read_out(np.zeros(camera.shape), camera)
    with pytest.raises(InputError, match="finite"):
        read_out(np.full(camera.shape, np.nan), camera, rng=np.random.default_rng(0))
    with pytest.raises(InputError, match="hot_pixel_fraction"):
        DetectorOptions(hot_pixel_fraction=-1.0)


def test_saturate_keyword_is_below_every_full_pixel_reading():
    # Full pixels read full_well/gain + bias plus read noise (noise is added after the
    # clipping), so SATURATE must lie below all of them, yet above the readings of a pixel
    # whose signal is 5 total-noise sigmas under the full well.
    from opnav.render.frames_io import saturation_level_adu

    camera = Camera.from_fov(5.0, 256, 256, full_well_e=50_000.0, gain_e_per_adu=1.0, read_noise_e=8.0)
    level = saturation_level_adu(camera)
    full = read_out(np.full(camera.shape, 1e7), camera, options=QUIET, rng=np.random.default_rng(3)).astype(float)
    assert full.min() >= level
    signal = 50_000.0 - 5.0 * np.sqrt(50_000.0 + 8.0**2)
    below = read_out(np.full(camera.shape, signal), camera, options=QUIET, rng=np.random.default_rng(4)).astype(float)
    assert np.mean(below >= level) < 1e-3
    adc_limited = Camera.from_fov(5.0, 16, 16, full_well_e=30_000.0, bit_depth=12, gain_e_per_adu=5.0)
    assert saturation_level_adu(adc_limited) == 2**12 - 1


def test_hot_pixel_clusters_are_3x3_blocks_added_to_the_same_single_hot_pixels():
    from opnav.render.detector import hot_pixels

    camera = Camera(width_px=256, height_px=200, focal_length_mm=50.0, pixel_pitch_um=10.0)
    single = hot_pixels(camera, DetectorOptions(hot_pixel_fraction=1e-3, hot_pixel_seed=3))
    both = hot_pixels(camera, DetectorOptions(hot_pixel_fraction=1e-3, hot_pixel_seed=3, hot_pixel_clusters=4))
    n = single[0].size
    assert np.array_equal(both[0][:n], single[0]) and np.array_equal(both[1][:n], single[1])
    rows, cols = both[0][n:].reshape(4, 9), both[1][n:].reshape(4, 9)
    for r, c in zip(rows, cols):  # each cluster: a 3 x 3 block (clipped at the edges)
        assert r.max() - r.min() <= 2 and c.max() - c.min() <= 2
        assert len(set(zip(r.tolist(), c.tolist()))) == 9 or r.min() == 0 or c.min() == 0 \
            or r.max() == camera.height_px - 1 or c.max() == camera.width_px - 1
    with pytest.raises(InputError, match="hot_pixel_clusters"):
        DetectorOptions(hot_pixel_clusters=-1)
