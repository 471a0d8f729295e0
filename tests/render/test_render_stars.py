"""Stars, PSF, photometry and WCS of rendered frames (acceptance items of issue 3)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import j0, j1
from scipy.spatial.transform import Rotation

from opnav.camera import Camera
from opnav.errors import InputError
from opnav.frames import radec_to_unit
from opnav.render import PSF, DetectorOptions, Observer, RenderOptions, electron_rate, render_frame
from opnav.render.frames_io import header_wcs
from opnav.photometry import JOHNSON_V, collecting_area_m2

NOISE_FREE = DetectorOptions(noise_free=True, hot_pixel_fraction=0.0)
OBSERVER = Observer(1.5e8, np.array([1.2e8, 8.0e7, 3.0e7]), np.array([-15.0, 20.0, 8.0]))
ATTITUDE = Rotation.from_euler("zyx", [1.1, -0.4, 0.25])
DISTORTED = dict(k1=-0.08, k2=0.01, p1=2e-4, p2=-1e-4)


def _isolated(truth, camera, half):
    xy = truth.stars.xy_px
    inside = camera.in_frame(xy, margin_px=half + 1)
    d = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + np.eye(len(xy)) * 1e9
    return np.nonzero(inside & (d.min(1) > 2 * half + 2))[0]


def _window_moments(image, xy, half):
    cx, cy = np.rint(xy).astype(int)
    win = image[cy - half : cy + half + 1, cx - half : cx + half + 1]
    yy, xx = np.mgrid[cy - half : cy + half + 1, cx - half : cx + half + 1]
    total = win.sum()
    return np.array([(win * xx).sum() / total, (win * yy).sum() / total]), total


@pytest.mark.parametrize("distortion", [{}, DISTORTED])
def test_camera_round_trip_over_whole_detector(distortion):
    camera = Camera.from_fov(8.0, 1024, 768, **distortion)
    xs, ys = np.meshgrid(np.linspace(-0.5, 1023.5, 60), np.linspace(-0.5, 767.5, 50))
    xy = np.stack([xs.ravel(), ys.ravel()], -1)
    back = camera.project(camera.unproject(xy))
    assert np.max(np.abs(back - xy)) < 1e-6


def test_zero_point_matches_the_photon_rate_of_a_v0_star():
    # Classic figure: a V = 0 star gives ~1000 photons s^-1 cm^-2 A^-1 near 5500 A.
    per_cm2_per_a = JOHNSON_V.photon_flux_zero_m2_s / 1e4 / JOHNSON_V.width_a
    assert 950 < per_cm2_per_a < 1050
    camera = Camera.from_fov(2.0, 64, 64, aperture_mm=100.0, throughput=0.5, qe=0.8)
    expected = JOHNSON_V.photon_flux_zero_m2_s * math.pi * 0.05**2 * 0.5 * 0.8 * 10 ** (-0.4 * 7.5)
    assert electron_rate(7.5, camera) == pytest.approx(expected, rel=1e-12)
    assert collecting_area_m2(camera) == pytest.approx(math.pi * 0.05**2)


@pytest.mark.parametrize("sigma", [0.7, 1.3])
def test_noise_free_star_centroid_and_flux(star_catalog, sigma):
    camera = Camera.from_fov(6.0, 512, 512)
    options = RenderOptions(psf=PSF(sigma_px=sigma), detector=NOISE_FREE)
    result = render_frame(camera, ATTITUDE, OBSERVER, catalog=star_catalog, options=options)
    truth = result.truth
    half = options.psf.half_width_px
    isolated = _isolated(truth, camera, half)
    assert len(isolated) >= 10
    for i in isolated:
        centroid, total = _window_moments(result.signal_e, truth.stars.xy_px[i], half)
        assert np.all(np.abs(centroid - truth.stars.xy_px[i]) < 1e-3)
        predicted = electron_rate(truth.stars.vmag[i], camera) * camera.exposure_s
        assert total == pytest.approx(predicted, rel=5e-3)
    # The ADU image is the same electrons through gain and bias.
    expected_adu = (result.signal_e + camera.dark_current_e_s * camera.exposure_s) / camera.gain_e_per_adu + camera.bias_adu
    np.testing.assert_allclose(result.image, expected_adu, rtol=1e-12)


def test_airy_psf_flux_follows_encircled_energy_and_centroid_is_true():
    r0 = 1.8
    psf = PSF(kind="airy", airy_first_zero_px=r0, subsample=7, radius_px=25)
    from opnav.render.psf import render_stamps

    xy = np.array([[40.3, 41.7]])
    stamps = render_stamps(xy, np.array([1.0]), psf)
    values = stamps.values[0]
    yy, xx = np.mgrid[0:values.shape[0], 0:values.shape[1]]
    xx, yy = xx + stamps.x0[0], yy + stamps.y0[0]
    within = np.hypot(xx - xy[0, 0], yy - xy[0, 1]) <= 20.0
    v = 3.831705970207512 * 20.0 / r0
    assert values[within].sum() == pytest.approx(1.0 - j0(v) ** 2 - j1(v) ** 2, abs=2e-3)
    centroid = np.array([(values * xx)[within].sum(), (values * yy)[within].sum()]) / values[within].sum()
    assert np.all(np.abs(centroid - xy[0]) < 5e-3)


def test_smeared_star_centroid_is_mid_exposure_position(star_catalog):
    camera = Camera.from_fov(6.0, 512, 512, exposure_s=1.0)
    omega = np.array([0.0, 1.5, 0.0]) / camera.focal_length_px  # 1.5 px/s about camera y
    options = RenderOptions(detector=NOISE_FREE)
    result = render_frame(camera, ATTITUDE, OBSERVER, catalog=star_catalog, options=options, omega_cam_rad_s=omega)
    still = render_frame(camera, ATTITUDE, OBSERVER, catalog=star_catalog, options=options)
    half = options.psf.half_width_px + 2
    isolated = _isolated(result.truth, camera, half)
    assert len(isolated) >= 5
    for i in isolated:
        centroid, total = _window_moments(result.signal_e, result.truth.stars.xy_px[i], half)
        assert np.all(np.abs(centroid - result.truth.stars.xy_px[i]) < 2e-3)
        assert total == pytest.approx(result.truth.stars.electrons[i], rel=5e-3)
        # The smear widens the image along x by the 1.5 px path: variance grows by L^2/12.
        win_s = _second_moment_x(result.signal_e, result.truth.stars.xy_px[i], half)
        win_0 = _second_moment_x(still.signal_e, still.truth.stars.xy_px[i], half)
        assert win_s - win_0 == pytest.approx(1.5**2 / 12.0, rel=0.05)


def _second_moment_x(image, xy, half):
    cx, cy = np.rint(xy).astype(int)
    win = image[cy - half : cy + half + 1, cx - half : cx + half + 1]
    xx = np.arange(cx - half, cx + half + 1)[None, :]
    mean = (win * xx).sum() / win.sum()
    return (win * (xx - mean) ** 2).sum() / win.sum()


@pytest.mark.parametrize("distortion", [{}, DISTORTED])
def test_wcs_maps_truth_stars_to_apparent_radec(star_catalog, distortion):
    camera = Camera.from_fov(10.0, 800, 600, **distortion)
    result = render_frame(camera, ATTITUDE, OBSERVER, catalog=star_catalog, options=RenderOptions(detector=NOISE_FREE))
    wcs = header_wcs(result.header)
    xy = result.truth.stars.xy_px
    on_chip = camera.in_frame(xy)
    assert on_chip.sum() > 20
    ra, dec = wcs.all_pix2world(xy[on_chip, 0], xy[on_chip, 1], 0)
    world = radec_to_unit(np.radians(ra), np.radians(dec))
    err = np.arccos(np.clip(np.sum(world * result.truth.stars.direction_icrf[on_chip], -1), -1, 1))
    assert np.max(err) / camera.pixel_scale_rad < 0.01
    # Inverse direction through the fitted AP/BP (or exact TAN) as well.
    ra_t, dec_t = np.degrees(np.stack(_radec(result.truth.stars.direction_icrf[on_chip])))
    px, py = wcs.all_world2pix(ra_t, dec_t, 0)
    assert np.max(np.hypot(px - xy[on_chip, 0], py - xy[on_chip, 1])) < 0.01


def _radec(vectors):
    from opnav.frames import unit_to_radec

    return unit_to_radec(vectors)


def test_bad_inputs_raise_clear_errors(star_catalog):
    camera = Camera.from_fov(6.0, 64, 64)
    with pytest.raises(InputError, match="not finite"):
        Observer(0.0, np.array([np.nan, 0.0, 0.0]), np.zeros(3))
    with pytest.raises(InputError, match="exposure_s"):
        camera.replace(exposure_s=0.0)
    with pytest.raises(InputError, match="rng"):
        render_frame(camera, ATTITUDE, OBSERVER, catalog=star_catalog)
    with pytest.raises(InputError, match="psf kind"):
        PSF(kind="moffat")
