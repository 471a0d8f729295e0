"""render_windows reads every window out in one pass: it must give what reading each window out on
its own gives (noise-free: the same image to 1e-12; noisy: the same pixel statistics)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from opnav.camera import Camera
from opnav.catalog import synthetic_catalog
from opnav.errors import InputError
from opnav.render import Body, Corrections, DetectorOptions, Observer, RenderOptions, render_windows
from opnav.render.detector import MIP_ELECTRONS_PER_UM, WindowLayout, bloom, hot_pixels, read_out_windows
from opnav.render.frame import _build_scene, _resolve_bodies, merge_boxes, roi_boxes
from opnav.render.psf import add_stamps
from opnav.studies.s1 import load_demo

GEOMETRIC = Corrections(light_time=False, aberration=False)
BALL = np.array([1.496e8, 0.0, 0.0])  # km from the Sun (at the SSB): the resolved body's place
OBSERVER = Observer(0.0, BALL + 1.0e6 * np.array([-0.6, 0.8, 0.0]), np.zeros(3))
OMEGA = np.array([2e-3, -1e-3, 4e-3])  # rad/s: every source smeared over a few pixels


class _StaticEphemeris:
    """The Sun at the SSB, the body "ball" at ``BALL``; nothing moves."""

    def position(self, body, t, *, center="ssb"):
        r = {"sun": np.zeros(3), "ball": BALL}[body]
        return np.broadcast_to(r, (np.size(t), 3)).copy() if np.ndim(t) else r.copy()

    def state(self, body, t, *, center="ssb"):
        r = self.position(body, t, center=center)
        return r, np.zeros_like(r)


@pytest.fixture(scope="module")
def scene():
    """A camera pointed at a resolved, saturating body in a star field, with hot pixels,
    stray light and smear: every term of the read-out shows in some window."""
    camera = Camera.from_fov(8.0, 300, 240, exposure_s=2.0, full_well_e=40_000.0, gain_e_per_adu=2.0)
    z = (BALL - OBSERVER.r_ssb_km) / np.linalg.norm(BALL - OBSERVER.r_ssb_km)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    attitude = Rotation.from_matrix(np.column_stack([x, np.cross(z, x), z])) * Rotation.from_rotvec([0.01, -0.02, 0.3])
    catalog = synthetic_catalog(60_000, rng=np.random.default_rng(5), vmag_range=(3.0, 9.0))
    detector = DetectorOptions(noise_free=True, hot_pixel_fraction=3e-3, hot_pixel_clusters=30, hot_pixel_seed=2)
    options = RenderOptions(detector=detector, corrections=GEOMETRIC, stray_light_e=400.0, supersample=2)
    kwargs = dict(catalog=catalog, targets=(Body("ball", (4000.0,) * 3, 0.3),), ephemeris=_StaticEphemeris(),
                  omega_cam_rad_s=OMEGA)
    return camera, attitude, options, kwargs


def _reference_windows(camera, attitude, options, kwargs, regions):
    """Noise-free windows the straightforward way: each window drawn and read out on its own."""
    scene = _build_scene(camera, attitude, OBSERVER, kwargs["catalog"], _resolve_bodies(kwargs["targets"]),
                         kwargs["ephemeris"], options, kwargs["omega_cam_rad_s"])
    detector = options.detector
    images = []
    for x0, y0, x1, y1 in regions:
        signal = np.zeros((y1 - y0 + 1, x1 - x0 + 1))
        for stamps in scene.sources:
            add_stamps(signal, stamps, origin_xy=(x0, y0))
        signal += options.stray_light_e * (x0 + np.arange(signal.shape[1])) / (camera.width_px - 1)
        dark = np.full(signal.shape, camera.dark_current_e_s)
        rows, cols = hot_pixels(camera, detector)
        rows, cols = rows - y0, cols - x0
        inside = (rows >= 0) & (rows < signal.shape[0]) & (cols >= 0) & (cols < signal.shape[1])
        dark[rows[inside], cols[inside]] *= detector.hot_pixel_factor
        charge = signal + dark * camera.exposure_s
        charge = bloom(charge, camera.full_well_e) if detector.blooming else np.minimum(charge, camera.full_well_e)
        images.append(charge / camera.gain_e_per_adu + camera.bias_adu)
    return scene, images


def _grid_boxes(camera, x_range, y_range, size):
    """Boxes of ``size`` px one pixel apart (so never merged): stamps straddle several of them."""
    return [(x, y, x + size - 1, y + size - 1) for x in range(*x_range, size + 1) for y in range(*y_range, size + 1)]


@pytest.mark.parametrize("placement", ["around sources", "grid"])
@pytest.mark.parametrize("blooming", [True, False])
def test_noise_free_windows_equal_the_per_window_reference(scene, placement, blooming):
    camera, attitude, options, kwargs = scene
    options = replace(options, detector=replace(options.detector, blooming=blooming))
    boxes = None if placement == "around sources" else _grid_boxes(camera, (0, 300), (0, 240), 9)
    rendered = render_windows(camera, attitude, OBSERVER, options=options, window_half_px=6, boxes=boxes, **kwargs)
    regions = roi_boxes(rendered.truth, camera, half_px=6) if boxes is None else merge_boxes(boxes, camera)
    assert len(regions) > 40
    reference, images = _reference_windows(camera, attitude, options, kwargs, regions)
    assert [(w.x0, w.y0, w.image.shape) for w in rendered.windows] == [
        (x0, y0, image.shape) for (x0, y0, _, _), image in zip(regions, images)]
    for window, image in zip(rendered.windows, images):
        np.testing.assert_allclose(window.image, image, rtol=1e-12, atol=0.0)
    # The scene exercises what the batched read-out must keep per window or per pixel.
    full_adu = camera.full_well_e / camera.gain_e_per_adu + camera.bias_adu
    saturated = [w for w in rendered.windows if np.isclose(w.image.max(), full_adu, rtol=1e-12)]
    assert saturated, "no window reaches the full well"
    assert len(rendered.truth.stars) > 20 and rendered.truth.targets[0].resolved
    layout = WindowLayout.from_boxes(regions)
    assert layout.flat_index(*hot_pixels(camera, options.detector)).size > 10  # hot pixels inside windows
    if blooming:  # bloom trails run off a window's top or bottom row (that charge is lost, as for the window alone)
        assert any(np.any(np.isclose(w.image[[0, -1]], full_adu, rtol=1e-12)) for w in saturated)
    stamps, box = reference.sources[0], np.array(regions)
    size_y, size_x = stamps.values.shape[1:]
    windows_hit = np.sum((stamps.x0[:, None] <= box[:, 2]) & (stamps.x0[:, None] + size_x > box[:, 0])
                         & (stamps.y0[:, None] <= box[:, 3]) & (stamps.y0[:, None] + size_y > box[:, 1]), axis=1)
    assert np.sum(windows_hit >= (2 if boxes is not None else 1)) > 10  # on the grid, stamps straddle windows


def check_noisy_window_pixels(scene, n_draws: int):
    """Per-pixel mean and variance over ``n_draws`` draws: expected ADU and (charge + read noise^2) / gain^2
    + 1/12 (rounding), the Poisson + Gaussian model, with hot pixels; no cosmic rays, no saturation.
    The variance bounds were set for 1500 draws; a sample variance scatters as sqrt(2 / n_draws),
    so with fewer draws they widen by sqrt(1500 / n_draws): the same number of its sigmas."""
    widen = np.sqrt(1500 / n_draws)
    camera, attitude, options, kwargs = scene
    camera = camera.replace(exposure_s=0.2)
    kwargs = {**kwargs, "targets": ()}
    quiet = DetectorOptions(cosmic_ray_rate_cm2_s=0.0, hot_pixel_fraction=3e-3, hot_pixel_seed=2)
    noisy = replace(options, detector=quiet)
    expected_options = replace(options, detector=replace(quiet, noise_free=True))
    expected = render_windows(camera, attitude, OBSERVER, options=expected_options, window_half_px=6, **kwargs)
    mean_adu = np.concatenate([w.image.ravel() for w in expected.windows])
    charge_e = (mean_adu - camera.bias_adu) * camera.gain_e_per_adu
    assert charge_e.max() < 0.5 * camera.full_well_e and len(expected.windows) > 20
    model_var = (charge_e + camera.read_noise_e**2) / camera.gain_e_per_adu**2 + 1.0 / 12.0
    sum_d, sum_d2 = np.zeros_like(mean_adu), np.zeros_like(mean_adu)  # of the draws less the expected value
    for k in range(n_draws):
        rendered = render_windows(camera, attitude, OBSERVER, options=noisy, window_half_px=6,
                                  rng=np.random.default_rng(k), **kwargs)
        d = np.concatenate([w.image.ravel() for w in rendered.windows]) - mean_adu
        sum_d += d
        sum_d2 += d * d
    z = sum_d / n_draws / np.sqrt(model_var / n_draws)
    assert np.max(np.abs(z)) < 5.5
    assert np.mean(z**2) == pytest.approx(1.0, abs=5 * np.sqrt(2.0 / z.size))
    ratio = (sum_d2 - sum_d**2 / n_draws) / (n_draws - 1) / model_var
    # Relative scatter of one pixel's sample variance ~ sqrt(2 / n_draws) = 3.7 %, more for the
    # few-electron pixels (Poisson excess kurtosis); averaged over the pixels well under 1 %.
    assert np.mean(ratio) == pytest.approx(1.0, abs=0.01 * widen)
    assert np.max(np.abs(ratio - 1.0)) < 0.25 * widen
    bright = charge_e > 2000.0  # where shot noise dominates the read noise
    assert bright.sum() > 30 and np.mean(ratio[bright]) == pytest.approx(1.0, abs=0.03 * widen)


@pytest.mark.slow
def test_noisy_window_pixels_have_the_expected_mean_and_variance(scene):
    check_noisy_window_pixels(scene, n_draws=1500)


def test_noisy_window_pixels_have_the_expected_mean_and_variance_over_400_draws(scene):
    """Fast sibling of the test above: 400 draws, the variance bounds for 400 draws."""
    check_noisy_window_pixels(scene, n_draws=400)


def test_noisy_windows_are_deterministic_for_a_seed(scene):
    camera, attitude, options, kwargs = scene
    noisy = replace(options, detector=DetectorOptions(cosmic_ray_rate_cm2_s=50.0))
    first, again, other = (render_windows(camera, attitude, OBSERVER, options=noisy, rng=np.random.default_rng(seed),
                                          **kwargs) for seed in (3, 3, 4))
    assert all(np.array_equal(a.image, b.image) for a, b in zip(first.windows, again.windows))
    assert not all(np.array_equal(a.image, b.image) for a, b in zip(first.windows, other.windows))


def test_cosmic_rays_hit_each_window_as_a_detector_of_its_area():
    """Windows of different sizes read out together: each collects the cosmic-ray charge of its own
    area (tracks a fraction of a pixel long, so hardly any charge runs off the edges)."""
    camera = Camera.from_fov(5.0, 400, 400, pixel_pitch_um=10.0, exposure_s=20.0, read_noise_e=0.0,
                             dark_current_e_s=0.0, gain_e_per_adu=1.0)
    options = DetectorOptions(cosmic_ray_rate_cm2_s=1.0e5, hot_pixel_fraction=0.0, depletion_um=0.1, blooming=False)
    boxes = [(0, 0, 19, 19), (30, 0, 59, 29), (100, 100, 199, 139), (300, 300, 329, 399)]
    layout = WindowLayout.from_boxes(boxes)
    rng = np.random.default_rng(8)
    charge = np.zeros(len(boxes))
    n_frames = 25
    for _ in range(n_frames):
        adu = read_out_windows(np.zeros(layout.size), layout, camera, options=options, rng=rng).astype(float)
        charge += [view.sum() for view in layout.views(adu - camera.bias_adu)]
    area_cm2 = layout.rows * layout.cols * (camera.pixel_pitch_um * 1e-4) ** 2
    events = options.cosmic_ray_rate_cm2_s * area_cm2 * camera.exposure_s * n_frames
    # Isotropic incidence, cos(theta) = sqrt(u) with u in [1e-6, 1): mean path = depletion * E[1/cos]
    # = 2 depletion (1 - 1e-3) / (1 - 1e-6); compound-Poisson scatter of the sum: E[1/cos^2] = 13.8,
    # relative sigma sqrt(13.8 / events) / 2.
    expected = events * MIP_ELECTRONS_PER_UM * options.depletion_um * 2.0 * (1.0 - 1e-3) / (1.0 - 1e-6)
    assert events.min() > 15_000
    np.testing.assert_allclose(charge, expected, rtol=4.0 * np.sqrt(13.8 / events.min()) / 2.0 + 0.005)


def test_no_windows_reads_out_nothing(scene):
    camera, attitude, options, kwargs = scene
    rendered = render_windows(camera, attitude, OBSERVER, options=options, boxes=[(-20, -20, -5, -5)], **kwargs)
    assert rendered.windows == () and len(rendered.truth.stars) > 0
    noisy = replace(options, detector=DetectorOptions())
    assert render_windows(camera, attitude, OBSERVER, options=noisy, boxes=[], rng=np.random.default_rng(0),
                          **kwargs).windows == ()


@pytest.mark.parametrize("boxes", [[(0, 0, float("nan"), 3)], [(0, 0, 3)], [("a", 0, 1, 1)], [(0, 0, 1, 2, 3)]])
def test_boxes_that_are_not_four_finite_numbers_are_a_clear_error(boxes):
    camera = load_demo()[0].camera
    with pytest.raises(InputError, match="boxes must be"):
        merge_boxes(boxes, camera)
