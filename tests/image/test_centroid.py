"""Centroiding: accuracy against the Cramér–Rao bound, bias, equivariance, covariance, failures."""

import numpy as np
import pytest
from scipy.special import ndtr
from scipy.stats import chi2

from opnav.errors import InputError
from opnav.image.centroid import centroid, centroid_crb

READ_NOISE_E = 5.0
BACKGROUND_E = 20.0


def _field(rng, n, *, sigma, flux, cell=16, background=BACKGROUND_E, read_noise=READ_NOISE_E, noise=True, phase=None):
    """Stars on a grid of cells, sub-pixel phase uniform (or ``phase``); exact pixel integrals; gain 1, bias 0."""
    side = int(np.ceil(np.sqrt(n)))
    idx = np.arange(n)
    offset = rng.uniform(-0.5, 0.5, (n, 2)) if phase is None else np.broadcast_to(phase, (n, 2))
    xy = np.column_stack([(idx % side) * cell + cell // 2, (idx // side) * cell + cell // 2]) + offset
    shape = (side * cell, side * cell)
    expected = np.full(shape, background)
    cols, rows = np.arange(shape[1]), np.arange(shape[0])
    for (x, y), f in zip(xy, np.broadcast_to(flux, (n,))):
        lo_c, lo_r = int(x) - 8, int(y) - 8
        c, r = cols[max(lo_c, 0):lo_c + 17], rows[max(lo_r, 0):lo_r + 17]
        ex = ndtr((c + 0.5 - x) / sigma) - ndtr((c - 0.5 - x) / sigma)
        ey = ndtr((r + 0.5 - y) / sigma) - ndtr((r - 0.5 - y) / sigma)
        expected[r[0]:r[-1] + 1, c[0]:c[-1] + 1] += f * np.outer(ey, ex)
    if not noise:
        return xy, expected
    return xy, rng.poisson(expected) + rng.normal(0.0, read_noise, shape)


@pytest.mark.parametrize("sigma, flux", [(0.7, 3000.0), (1.0, 20000.0), (1.5, 8000.0)])
def test_gauss_fit_attains_cramer_rao_bound(sigma, flux):
    rng = np.random.default_rng(11)
    n = 400
    window = 2 * int(np.ceil(3 * sigma)) + 1
    xy, image = _field(rng, n, sigma=sigma, flux=flux)
    res = centroid(image, xy + rng.uniform(-0.5, 0.5, xy.shape), window=window, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0)
    assert res.ok.all()
    crb = centroid_crb(xy, flux, sigma, background_e=BACKGROUND_E, read_noise_e=READ_NOISE_E, window=window)
    z2 = (res.xy - xy) ** 2 / np.stack([crb[:, 0, 0], crb[:, 1, 1]], -1)
    # An efficient estimator makes sum(z2) ~ chi2(2n). Allow RMS up to 1.1x the bound beyond the
    # 0.1% sampling quantile, and require the bound not to be beaten (which would mean a wrong CRB).
    dof = 2 * n
    assert z2.sum() <= 1.1**2 * chi2.ppf(0.999, dof)
    assert z2.sum() >= chi2.ppf(0.001, dof) / 1.1**2


def test_covariance_is_consistent_nees_chi2():
    rng = np.random.default_rng(12)
    n = 400
    xy, image = _field(rng, n, sigma=1.0, flux=rng.uniform(2000, 50000, 400))
    res = centroid(image, xy + rng.uniform(-0.5, 0.5, xy.shape), window=7, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0)
    err = res.xy - xy
    nees = np.einsum("ni,nij,nj->n", err, np.linalg.inv(res.cov), err)
    # mean NEES of n independent 2-D errors: n * mean ~ chi2(2n)
    assert chi2.ppf(0.001, 2 * n) <= nees.sum() <= chi2.ppf(0.999, 2 * n)


def test_covariance_without_known_noise_is_consistent():
    rng = np.random.default_rng(13)
    n = 400
    xy, image = _field(rng, n, sigma=1.0, flux=20000.0)
    res = centroid(image, xy, window=7)
    err = res.xy - xy
    nees = np.einsum("ni,nij,nj->n", err, np.linalg.inv(res.cov), err)
    # The sandwich covariance estimates the noise from 49 residuals per star: allow 20% on its mean.
    assert 0.8 * 2 <= nees.mean() <= 1.2 * 2


@pytest.mark.parametrize("sigma", [0.5, 0.7, 1.0, 1.5])
def test_no_pixel_phase_bias_noise_free(sigma):
    rng = np.random.default_rng(14)
    xy, image = _field(rng, 100, sigma=sigma, flux=1e4, noise=False)
    window = 2 * int(np.ceil(3 * sigma)) + 1
    res = centroid(image, np.rint(xy), window=window, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0)
    assert np.max(np.abs(res.xy - xy)) < 1e-4
    assert np.allclose(res.sigma_px, sigma, atol=1e-3)


def test_no_pixel_phase_bias_with_noise():
    rng = np.random.default_rng(15)
    n = 900
    # (0.3, -0.3) is near the worst phase for a centre-of-gravity estimator
    xy, image = _field(rng, n, sigma=0.7, flux=5000.0, phase=(0.3, -0.3))
    res = centroid(image, np.rint(xy), window=5, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0)
    err = res.xy - xy
    sem = err.std(axis=0, ddof=1) / np.sqrt(n)
    # Bias below 4 standard errors of the mean (~0.0006 px here) on both axes.
    assert np.all(np.abs(err.mean(axis=0)) < 4 * sem)


def test_integer_shift_equivariance():
    rng = np.random.default_rng(16)
    xy, image = _field(rng, 16, sigma=1.0, flux=10000.0)
    padded = np.pad(image, 10, mode="constant", constant_values=BACKGROUND_E)
    base = centroid(padded, xy + 10, window=7, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0)
    for dx, dy in [(3, 0), (0, -2), (5, 7)]:
        shifted = np.roll(padded, (dy, dx), axis=(0, 1))
        res = centroid(shifted, xy + 10 + [dx, dy], window=7, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0)
        np.testing.assert_allclose(res.xy, base.xy + [dx, dy], atol=1e-9)
        np.testing.assert_allclose(res.cov, base.cov, rtol=1e-9)


@pytest.mark.parametrize("method, tol", [("iwc", 0.01), ("cog", 0.06)])
def test_moment_methods_noise_free(method, tol):
    rng = np.random.default_rng(17)
    xy, image = _field(rng, 50, sigma=1.0, flux=1e4, noise=False)
    res = centroid(image, np.rint(xy), method=method, window=9, psf_sigma_px=1.0, read_noise_e=5.0, gain_e_per_adu=1.0)
    assert res.ok.all()
    assert np.max(np.abs(res.xy - xy)) < tol


def test_crb_matches_continuous_limit():
    # Well-sampled Gaussian, Poisson only, known width: var(x) -> sigma^2 / F.
    sigma, flux = 4.0, 1e5
    crb = centroid_crb(np.array([[50.0, 50.0]]), flux, sigma, background_e=0.0, read_noise_e=0.0, window=41, fit_width=False)
    assert crb[0, 0, 0] == pytest.approx(sigma**2 / flux, rel=0.01)
    assert abs(crb[0, 0, 1]) < 1e-3 * crb[0, 0, 0]


def test_saturated_core_is_left_out():
    rng = np.random.default_rng(18)
    xy, image = _field(rng, 9, sigma=1.5, flux=2e5)
    level = 8000.0
    clipped = np.minimum(image, level)
    assert (image > level).sum() > 9
    res = centroid(clipped, xy, window=11, saturation_adu=level, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0)
    assert res.ok.all()
    assert np.max(np.abs(res.xy - xy)) < 0.05


def test_failed_seeds_are_flagged_not_dropped():
    rng = np.random.default_rng(19)
    xy, image = _field(rng, 4, sigma=1.0, flux=1e4)
    seeds = np.vstack([xy, [[1e6, 1e6], [np.nan, 3.0]]])
    res = centroid(image, seeds, window=7, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0)
    assert len(res) == 6
    assert res.ok[:4].all() and not res.ok[4:].any()
    assert np.isnan(res.xy[4:]).all()


def test_bad_arguments():
    image = np.zeros((20, 20))
    with pytest.raises(InputError, match="window"):
        centroid(image, np.array([[10.0, 10.0]]), window=6)
    with pytest.raises(InputError, match="seeds"):
        centroid(image, np.array([10.0, 10.0]))
    with pytest.raises(InputError, match="method"):
        centroid(image, np.array([[10.0, 10.0]]), method="magic")
    with pytest.raises(InputError, match="gain"):
        centroid(image, np.array([[10.0, 10.0]]), gain_e_per_adu=-1.0)


def _with_ramp(rng, gradient_e_px, *, n=400, flux=3000.0):
    """A star field with a stray-light ramp ``gradient_e_px`` (electrons per px along x, y) over it."""
    xy, expected = _field(rng, n, sigma=1.0, flux=flux, noise=False)
    rows, cols = np.indices(expected.shape)
    expected = expected + 1000.0 + gradient_e_px[0] * cols + gradient_e_px[1] * rows
    return xy, rng.poisson(expected) + rng.normal(0.0, READ_NOISE_E, expected.shape)


def test_frame_gradient_removes_the_stray_light_bias():
    # A ramp of 4 e/px per px leans every 3000 e star ~0.03-0.05 px toward the bright side
    # (about 8 pi s^4 g / F): a bias the same in every frame, many sigma over a long arc.
    rng = np.random.default_rng(21)
    gradient = np.array([4.0, -3.0])
    xy, image = _with_ramp(rng, gradient)
    seeds = xy + rng.uniform(-0.5, 0.5, xy.shape)
    plain = centroid(image, seeds, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0)
    fixed = centroid(image, seeds, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0, frame_gradient=True)
    assert plain.ok.all() and fixed.ok.all()
    sigma = np.sqrt(np.mean(fixed.cov[:, [0, 1], [0, 1]], axis=0)) / np.sqrt(len(xy))  # of the mean error
    plain_bias = (plain.xy - xy).mean(axis=0)
    fixed_bias = (fixed.xy - xy).mean(axis=0)
    assert np.all(np.abs(plain_bias) > 5 * sigma)
    assert np.all(np.sign(plain_bias) == np.sign(gradient))
    assert np.all(np.abs(fixed_bias) < 3.5 * sigma)
    np.testing.assert_allclose(fixed.gradient_adu_px, gradient, rtol=0.05)
    # the known gradient (a crop gets its frame's) gives the same centroids
    given = centroid(image, seeds, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0, gradient_adu_px=fixed.gradient_adu_px)
    np.testing.assert_allclose(given.xy, fixed.xy, atol=1e-6)


def test_frame_gradient_leaves_a_flat_frame_alone():
    rng = np.random.default_rng(22)
    xy, image = _with_ramp(rng, (0.0, 0.0))
    seeds = xy + rng.uniform(-0.5, 0.5, xy.shape)
    plain = centroid(image, seeds, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0)
    checked = centroid(image, seeds, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0, frame_gradient=True)
    assert checked.gradient_adu_px == (0.0, 0.0)
    np.testing.assert_array_equal(checked.xy, plain.xy)


def test_frame_gradient_ignores_a_halo_it_cannot_call_a_plane():
    # One corner's sources on a bright halo: clipped, the flat rest shows no gradient.
    from opnav.image.centroid import background_gradient

    rng = np.random.default_rng(23)
    xy = rng.uniform(0, 1000, (12, 2))
    background = 100.0 + rng.normal(0.0, 1.0, 12)
    background[:2] += 500.0
    assert background_gradient(xy, background, np.ones(12)) is None
    assert background_gradient(xy[:3], background[:3], np.ones(3)) is None  # too few


def test_gradient_must_be_two_finite_numbers():
    with pytest.raises(InputError, match="gradient_adu_px"):
        centroid(np.zeros((20, 20)), np.array([[10.0, 10.0]]), gradient_adu_px=(np.nan, 0.0))


def test_a_track_through_the_stamp_fails_the_psf_test():
    # uniform p-values on clean stars; a cosmic-ray track across a star's stamp leaves residuals
    # far beyond chi-square(dof), and only that star is refused
    from opnav.image.centroid import psf_like

    rng = np.random.default_rng(24)
    xy, image = _field(rng, 100, sigma=1.0, flux=5000.0)
    image[int(xy[7, 1]) - 1, int(xy[7, 0]) - 3:int(xy[7, 0]) + 4] += 400.0  # a track 7 px long
    res = centroid(image, xy + rng.uniform(-0.3, 0.3, xy.shape), read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0)
    assert res.ok.all()
    passed = psf_like(res)
    assert not passed[7]
    assert passed.sum() == 99
    p_values = chi2.sf(np.delete(res.chi2, 7), np.delete(res.dof, 7))
    assert 0.01 < np.mean(p_values < 0.1) < 0.25  # calibrated, not merely permissive


def test_stamps_cut_as_fancy_indexing_cuts_them():
    """The compiled stamp cutter against numpy's gather of the same pixels: off-frame, ``bad``, NaN and
    saturated pixels unusable and 0, the rest the frame's values; for a C-ordered frame and a view."""
    from opnav.image.centroid import _cut_stamps, _stamp_grid

    rng = np.random.default_rng(7)
    full = rng.normal(100.0, 10.0, (60, 90))
    full[rng.random(full.shape) < 0.02] = np.nan
    full[rng.random(full.shape) < 0.02] = 200.0
    bad = rng.random(full.shape) < 0.05
    seeds = np.column_stack([rng.uniform(-6, 96, 40), rng.uniform(-6, 66, 40)])
    for image, mask in ((full, bad), (full[:, ::2], np.ascontiguousarray(bad[:, ::2]))):
        h, w = image.shape
        _, u, v = _stamp_grid(seeds, 9)
        for has_bad in (False, True):
            stamps, usable = _cut_stamps(image, mask, has_bad, u, v, 150.0)
            inside = (v[:, :, None] >= 0) & (v[:, :, None] < h) & (u[:, None, :] >= 0) & (u[:, None, :] < w)
            values = image[np.clip(v, 0, h - 1)[:, :, None], np.clip(u, 0, w - 1)[:, None, :]]
            expected = inside & np.isfinite(values) & (values < 150.0)
            if has_bad:
                expected &= ~mask[np.clip(v, 0, h - 1)[:, :, None], np.clip(u, 0, w - 1)[:, None, :]]
            assert expected.any() and not expected.all()
            np.testing.assert_array_equal(usable, expected)
            np.testing.assert_array_equal(stamps, np.where(expected, values, 0.0))


def test_invalid_mask_of_another_shape_is_refused():
    image = np.random.default_rng(1).normal(100.0, 5.0, (40, 50))
    with pytest.raises(InputError, match="invalid mask"):
        centroid(image, np.array([[20.0, 20.0]]), invalid=np.zeros((40, 49), bool))
