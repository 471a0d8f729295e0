"""The tracking stage's compiled and reorganised paths give the numbers of the array paths they replaced.

Each replaced computation is checked against its reference (the array-level function kept in the
module, or a copy of the replaced code here), and ``Tracker.step`` on rendered S1 frames against
the stage with every reference put back.
"""

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.special import ndtr
from scipy.spatial.transform import Rotation
from scipy.stats import chi2, norm

import opnav.image.centroid as centroid_mod
import opnav.image.moon_fit as moon_fit_mod
import opnav.image.pipeline as pipeline_mod
import opnav.image.targets as targets_mod
import opnav.image.tracking as tracking_mod
from opnav.image import camera_scatter
from opnav.image.attitude import wahba_gated
from opnav.bodies import BodyRays, BodyView, body_axes_icrf, body_model, cross3, reproject_view
from opnav.camera import Camera
from opnav.frames import radec_to_unit, unit, unit_to_radec
from opnav.image.centroid import centroid, chi2_sf

READ_NOISE_E = 5.0
BACKGROUND_E = 20.0


# ---- Gaussian-fit centroids ------------------------------------------------------------------

def _stars(rng, shape, xy, flux, sigma):
    """Expected electrons of point sources (exact pixel integrals) over a flat background."""
    expected = np.full(shape, BACKGROUND_E)
    cols, rows = np.arange(shape[1]), np.arange(shape[0])
    for (x, y), f, s in zip(xy, flux, sigma):
        ex = ndtr((cols + 0.5 - x) / s) - ndtr((cols - 0.5 - x) / s)
        ey = ndtr((rows + 0.5 - y) / s) - ndtr((rows - 0.5 - y) / s)
        expected += f * np.outer(ey, ex)
    return expected


def _frame(rng, n=24, saturated=False):
    """Stars of mixed flux and width, one on the edge (and one saturated), one seed on a flat patch
    (no signal: its fit never starts) and one on nothing but noise."""
    shape = (160, 200)
    xy = np.column_stack([rng.uniform(8, shape[1] - 8, n), rng.uniform(8, shape[0] - 8, n)])
    xy[0] = [1.2, 80.3]  # on the edge
    flux = rng.uniform(500.0, 40000.0, n)
    if saturated:
        flux[1] = 4e6  # its core clipped
    sigma = rng.uniform(0.8, 1.6, n)
    image = rng.poisson(_stars(rng, shape, xy, flux, sigma)) + rng.normal(0.0, READ_NOISE_E, shape)
    image = np.minimum(image, 60000.0)
    image[100:115, 20:35] = 100.0  # a flat patch
    seeds = np.vstack([xy + rng.uniform(-0.4, 0.4, xy.shape), [[27.0, 107.0], [150.0, 20.0]]])
    return image, seeds


def _reference_centroid(monkeypatch, *args, **kwargs):
    with monkeypatch.context() as patch:
        patch.setattr(centroid_mod, "_gauss", centroid_mod._gauss_reference)
        return centroid(*args, **kwargs)


def _assert_same_fits(fast, ref, xy_px=1e-9, rtol=1e-9, iterate_rtol=1e-6, cov_rtol=None):
    """Same flags; centroids to ``xy_px``; their covariances (to the largest element; ``cov_rtol``,
    default ``rtol``), fluxes, widths, backgrounds to ``rtol``. The chi-square and the flux's variance (in the SNR) are those of the
    last evaluated iterate, a step before the converged one, where the rounding of a step (its
    condition, 1e7-1e10, times eps, when the batch solves by least squares) is not yet contracted
    away: ``iterate_rtol``."""
    np.testing.assert_array_equal(fast.ok, ref.ok)
    ok = ref.ok
    assert ok.sum() > 5
    np.testing.assert_allclose(fast.xy[ok], ref.xy[ok], rtol=0.0, atol=xy_px)
    scale = np.abs(ref.cov[ok]).max(axis=(1, 2))[:, None, None]
    np.testing.assert_allclose(fast.cov[ok] / scale, ref.cov[ok] / scale, rtol=0.0,
                               atol=rtol if cov_rtol is None else cov_rtol)
    for name in ("flux", "sigma_px", "background", "dof"):
        np.testing.assert_allclose(getattr(fast, name)[ok], getattr(ref, name)[ok], rtol=rtol, err_msg=name)
    for name in ("snr", "chi2"):
        np.testing.assert_allclose(getattr(fast, name)[ok], getattr(ref, name)[ok], rtol=iterate_rtol, err_msg=name)
    np.testing.assert_allclose(fast.gradient_adu_px, ref.gradient_adu_px, rtol=rtol, atol=0.0)


@pytest.mark.parametrize("psf_sigma_px", [None, 1.2])
@pytest.mark.parametrize("read_noise_e", [READ_NOISE_E, None])  # None: the noise is fitted, then the fit repeated
def test_compiled_gauss_fit_equals_the_batched_reference(monkeypatch, psf_sigma_px, read_noise_e):
    image, seeds = _frame(np.random.default_rng(21))
    kwargs = dict(window=7, psf_sigma_px=psf_sigma_px, read_noise_e=read_noise_e, gain_e_per_adu=1.0,
                  saturation_adu=60000.0, frame_gradient=True)
    fast = centroid(image, seeds, **kwargs)
    ref = _reference_centroid(monkeypatch, image, seeds, **kwargs)
    if psf_sigma_px is None:  # the flat patch's seed has no width to start from: its matrix stays zero
        assert not fast.ok[-2]
    # A fitted noise model is a function of the first pass's residuals and stamp chi-squares, those of
    # its last evaluated iterate (see _assert_same_fits): the covariances built on it agree to that
    # iterate's precision, not the converged centroids' (seed 21: 1.1e-9 of the largest element).
    _assert_same_fits(fast, ref, cov_rtol=None if read_noise_e is not None else 1e-6)


def test_compiled_gauss_fit_equals_the_reference_without_a_failing_source(monkeypatch):
    # every matrix regular: the batch is solved directly throughout, in both
    image, seeds = _frame(np.random.default_rng(22))
    seeds = seeds[1:-2]
    kwargs = dict(window=7, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0, saturation_adu=60000.0)
    fast = centroid(image, seeds, **kwargs)
    ref = _reference_centroid(monkeypatch, image, seeds, **kwargs)
    assert fast.ok.all()
    _assert_same_fits(fast, ref, xy_px=1e-11, rtol=1e-11, iterate_rtol=1e-11)


def test_a_clipped_core_fits_as_the_reference_to_its_conditioning(monkeypatch):
    # A star whose core is clipped leaves flux and width degenerate (its normal matrix's condition is
    # ~2e15, where least squares truncates): the batched reference's own result for it moves by a
    # quarter of its sigma with the rest of the batch (least squares for every star once one fit
    # has no start), and rounding (the two LAPACK builds, the order of the sums) is amplified to
    # ~1e-5 px. The other stars stay at 1e-9 px.
    image, seeds = _frame(np.random.default_rng(21), saturated=True)
    kwargs = dict(window=7, read_noise_e=READ_NOISE_E, gain_e_per_adu=1.0, saturation_adu=60000.0)
    fast = centroid(image, seeds, **kwargs)
    ref = _reference_centroid(monkeypatch, image, seeds, **kwargs)
    np.testing.assert_array_equal(fast.ok, ref.ok)
    assert fast.ok[1]
    sigma = np.sqrt(np.diagonal(ref.cov[1]))
    assert np.all(np.abs(fast.xy[1] - ref.xy[1]) < 0.01 * sigma)
    keep = np.arange(len(seeds)) != 1
    _assert_same_fits(replace(fast, **{f: getattr(fast, f)[keep] for f in _ROW_FIELDS}),
                      replace(ref, **{f: getattr(ref, f)[keep] for f in _ROW_FIELDS}))


_ROW_FIELDS = ("xy", "cov", "flux", "snr", "ok", "sigma_px", "background", "chi2", "dof")


def test_chi2_sf_is_scipys():
    x = np.array([-np.inf, -1.0, -0.0, 0.0, 1e-300, 0.5, 3.0, 80.0, 7e4, np.inf, np.nan])
    dof = np.array([1.0, 2.0, 44.0, 0.5, 1e-300, 0.0, -1.0, np.inf, np.nan])
    np.testing.assert_array_equal(chi2_sf(x[:, None], dof[None, :]), chi2.sf(x[:, None], dof[None, :]))
    for value in x:
        for k in dof:
            fast, ref = chi2_sf(value, k), chi2.sf(value, k)
            assert (fast == ref or (np.isnan(fast) and np.isnan(ref))) and type(fast) is type(ref)


def test_cached_gate_and_halo_quantiles_are_scipys():
    from opnav.consistency import chi2_quantile  # the attitude gate's

    assert chi2_quantile(1.0 - 1e-4, 2) == chi2.ppf(1.0 - 1e-4, 2)
    q = np.geomspace(1e-300, 0.999999, 500)
    np.testing.assert_array_equal(-moon_fit_mod.ndtri(q), norm.isf(q))


# ---- moon photocentre and direction ----------------------------------------------------------

def _photocentre_reference(quad, half, sun, n_grid, lambert):
    """The photocentre moment of the replaced kernel, as arrays: mu and mu0 from the unit normal."""
    x = -half[0] + 2.0 * half[0] / n_grid * (np.arange(n_grid) + 0.5)
    y = -half[1] + 2.0 * half[1] / n_grid * (np.arange(n_grid) + 0.5)
    xx, yy = np.meshgrid(x, y)
    a = quad[2, 2]
    b = xx * quad[0, 2] + yy * quad[1, 2]
    c = xx * xx * quad[0, 0] + 2.0 * xx * yy * quad[0, 1] + yy * yy * quad[1, 1] - 1.0
    disc = b * b - a * c
    with np.errstate(invalid="ignore"):
        z = (-b - np.sqrt(disc)) / a
        normal = xx[..., None] * quad[0] + yy[..., None] * quad[1] + z[..., None] * quad[2]
        length = np.linalg.norm(normal, axis=-1)
        mu, mu0 = -normal[..., 2] / length, normal @ sun / length
        lit = (disc > 0.0) & (mu0 > 0.0) & (mu > 0.0)
        radiance = np.where(lit, mu0 if lambert else mu0 / (mu0 + mu), 0.0)
    total = radiance.sum()
    if not total > 0.0:
        return np.full(2, np.nan)
    return np.array([(radiance * xx).sum() / total, (radiance * yy).sum() / total])


@pytest.mark.parametrize("lambert", [False, True])
def test_photocentre_kernel_equals_the_array_model(lambert):
    rng = np.random.default_rng(5)
    for k in range(40):
        radii = np.array([13.0, 11.4, 9.1]) * rng.uniform(0.5, 1.5, 3)
        rot = Rotation.random(random_state=k).as_matrix()
        sun = unit(rng.normal(size=3))
        quad = rot @ np.diag(radii**-2.0) @ rot.T
        half = np.sqrt(np.diag(rot @ np.diag(radii**2.0) @ rot.T))[:2]
        fast = targets_mod._photocentre_moment(quad, half, sun, 200, lambert)
        ref = _photocentre_reference(quad, half, sun, 200, lambert)
        np.testing.assert_array_equal(np.isnan(fast), np.isnan(ref))
        np.testing.assert_allclose(fast[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=0.0, atol=1e-12 * radii.max())


def _moon_direction_reference(xy_px, cov_xy_px2, camera, R_icrf_cam, cov_attitude_rad2, *, radii_km=None,
                              R_icrf_body=None, sun_icrf=None, range_km=None, law="lommel-seeliger",
                              phase_sigma_fraction=0.1):
    """The replaced :func:`opnav.image.targets.moon_direction`: scipy rotations, one unprojection a pixel."""
    xy = np.asarray(xy_px, float)
    u_pc = camera.unproject(xy)
    step = 1e-3
    d_u_d_xy = np.stack([(camera.unproject(xy + d) - camera.unproject(xy - d)) / (2 * step)
                         for d in np.eye(2) * step], axis=-1)
    offset_cam, cov_offset_cam = np.zeros(3), np.zeros((3, 3))
    if radii_km is not None:
        R_cam_icrf = R_icrf_cam.inv()
        basis = targets_mod._view_basis(u_pc)
        R_view_body = Rotation.from_matrix(basis) * R_cam_icrf * R_icrf_body
        sun_view = basis @ R_cam_icrf.apply(np.asarray(sun_icrf, float))
        d_view = targets_mod.photocentre_offset(radii_km, R_view_body, sun_view, law=law)
        offset_cam = basis[:2].T @ d_view
        cov_offset_cam = (phase_sigma_fraction * float(np.linalg.norm(d_view))) ** 2 * basis[:2].T @ basis[:2]
    u_cof = u_pc - offset_cam / range_km if radii_km is not None else u_pc
    u_cof = u_cof / np.linalg.norm(u_cof)
    u_icrf = R_icrf_cam.apply(u_cof)
    ra, dec = unit_to_radec(u_icrf)
    j_radec = targets_mod._radec_jacobian(u_icrf)
    rot = R_icrf_cam.as_matrix()
    j_xy = j_radec @ rot @ d_u_d_xy
    j_att = j_radec @ rot @ (-targets_mod._cross_matrix(u_cof))
    cov = j_xy @ np.asarray(cov_xy_px2) @ j_xy.T + j_att @ np.asarray(cov_attitude_rad2) @ j_att.T
    if radii_km is not None:
        j_off = j_radec @ rot / range_km
        cov = cov + j_off @ cov_offset_cam @ j_off.T
    return targets_mod.MoonDirection(ra_rad=float(ra), dec_rad=float(dec), cov_rad2=0.5 * (cov + cov.T),
                                     unit_icrf=u_icrf, xy_cof_px=camera.project(u_cof), offset_km=offset_cam,
                                     attitude_jacobian=j_att)


@pytest.mark.parametrize("k1", [0.0, -0.3])
def test_moon_direction_equals_the_rotation_reference(k1):
    rng = np.random.default_rng(6)
    camera = Camera.from_fov(1.0, 1024, 1024, k1=k1)
    for k in range(20):
        R = Rotation.random(random_state=100 + k)
        kwargs = dict(radii_km=(13.0, 11.4, 9.1), R_icrf_body=Rotation.random(random_state=200 + k),
                      sun_icrf=unit(rng.normal(size=3)), range_km=rng.uniform(5e3, 5e4),
                      law=("lommel-seeliger", "lambert")[k % 2]) if k % 4 else {}
        args = (rng.uniform(0, 1023, 2), np.diag(rng.uniform(1e-4, 1e-2, 2)), camera, R, np.eye(3) * 1e-12)
        fast, ref = targets_mod.moon_direction(*args, **kwargs), _moon_direction_reference(*args, **kwargs)
        assert abs(fast.ra_rad - ref.ra_rad) < 1e-13 and abs(fast.dec_rad - ref.dec_rad) < 1e-13
        np.testing.assert_allclose(fast.cov_rad2, ref.cov_rad2, rtol=0.0, atol=1e-9 * np.abs(ref.cov_rad2).max())
        np.testing.assert_allclose(fast.xy_cof_px, ref.xy_cof_px, rtol=0.0, atol=1e-9)
        np.testing.assert_allclose(fast.offset_km, ref.offset_km, rtol=0.0, atol=1e-12)
        np.testing.assert_allclose(fast.attitude_jacobian, ref.attitude_jacobian, rtol=0.0, atol=1e-12)


# ---- predicted views -------------------------------------------------------------------------

def _reproject_view_reference(view, camera, R_icrf_cam, new_camera, new_R_icrf_cam):
    """The replaced :func:`opnav.bodies.reproject_view`, with scipy's rotation composition."""
    xy = np.concatenate([np.reshape(view.xy_cof_px, (1, 2)), np.reshape(view.xy_photocentre_px, (1, 2)),
                         np.reshape(view.rays.xy_px, (-1, 2))]).astype(float)
    moved = new_camera.project((new_R_icrf_cam.inv() * R_icrf_cam).apply(camera.unproject(xy)))
    return replace(view, xy_cof_px=moved[0], xy_photocentre_px=moved[1],
                   rays=BodyRays(xy_px=moved[2:], electrons_s=view.rays.electrons_s))


def test_reprojected_views_equal_the_rotation_reference():
    rng = np.random.default_rng(7)
    camera = Camera.from_fov(1.0, 1024, 1024, k1=-0.2)
    crop = camera.replace(width_px=64, height_px=64, cx_px=camera.cx_px - 480, cy_px=camera.cy_px - 500)
    view = BodyView("phobos", np.array([511.3, 530.2]), np.array([511.9, 530.0]), np.zeros(3), 0.0, 0.0, 1e4, 0.5,
                    1e-4, 10.0, 1e3, BodyRays(rng.uniform(400, 600, (50, 2)), np.ones(50)))
    for k in range(20):
        R = Rotation.random(random_state=k)
        moved_R = R * Rotation.from_rotvec(rng.normal(0.0, 3e-5, 3))
        for new_camera in (camera, crop):
            fast = reproject_view(view, camera, R, new_camera, moved_R)
            ref = _reproject_view_reference(view, camera, R, new_camera, moved_R)
            for name in ("xy_cof_px", "xy_photocentre_px"):
                np.testing.assert_allclose(getattr(fast, name), getattr(ref, name), rtol=0.0, atol=1e-9)
            np.testing.assert_allclose(fast.rays.xy_px, ref.rays.xy_px, rtol=0.0, atol=1e-9)


def test_view_geometry_helpers_give_numpys_numbers():
    rng = np.random.default_rng(8)
    for _ in range(2000):
        a, b = rng.normal(size=3) * 10 ** rng.uniform(-6, 9), rng.normal(size=3) * 10 ** rng.uniform(-6, 9)
        np.testing.assert_array_equal(cross3(a, b), np.cross(a, b))
    mars = body_model("mars")  # a fixed pole: its axes are made once
    z = radec_to_unit(mars.pole_ra_rad, mars.pole_dec_rad)
    x = unit(np.cross(np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0]), z))
    axes = body_axes_icrf(mars, 0.0, None)
    np.testing.assert_array_equal(axes, np.column_stack([x, np.cross(z, x), z]))
    axes[:] = 0.0  # a caller's copy
    np.testing.assert_array_equal(body_axes_icrf(mars, 1e6, None), np.column_stack([x, np.cross(z, x), z]))


# ---- the stage on rendered frames --------------------------------------------------------------

@pytest.fixture(scope="module")
def s1_frames(s1_demo_frames):
    """Six S1 demo frames a minute apart (both moons, Mars near; 16 July as in test_tracking): the
    first six of the session's (tests/conftest.py)."""
    frames, catalog, ephemeris, options = s1_demo_frames
    return replace(frames, paths=frames.paths[:6], truths=frames.truths[:6]), catalog, ephemeris, options


def _track(frames, catalog, ephemeris, options):
    tracker = tracking_mod.Tracker(catalog, ephemeris, options)
    results, tracked = [], []
    for k, path in enumerate(frames.paths):
        results.append(tracker.step(pipeline_mod.frame_input(path), rng=k))
        tracked.append(tracker.last_tracked)
        tracker.last_tracked = None
    return results, tracked, tracker.events


def test_tracker_records_equal_the_reference_paths(s1_frames, monkeypatch):
    frames, catalog, ephemeris, options = s1_frames
    fast, fast_tracked, fast_events = _track(frames, catalog, ephemeris, options)
    with monkeypatch.context() as patch:
        patch.setattr(centroid_mod, "_gauss", centroid_mod._gauss_reference)
        patch.setattr(centroid_mod, "chi2_sf", chi2.sf)
        patch.setattr(moon_fit_mod, "chi2_sf", chi2.sf)
        patch.setattr(targets_mod, "_photocentre_moment", _photocentre_reference)
        patch.setattr(pipeline_mod, "moon_direction", _moon_direction_reference)
        patch.setattr(tracking_mod, "reproject_view", _reproject_view_reference)
        ref, ref_tracked, ref_events = _track(frames, catalog, ephemeris, options)
    assert fast_events == ref_events and sum(t is not None for t in fast_tracked) == len(frames.paths) - 1
    records = 0
    for a, b, ta, tb in zip(fast, ref, fast_tracked, ref_tracked):
        assert a.flags == b.flags and a.n_stars_matched == b.n_stars_matched
        assert [(r.target, r.kind, r.flags) for r in a.records] == [(r.target, r.kind, r.flags) for r in b.records]
        # 1e-12 rad: 6e-8 px on the 1-degree camera
        np.testing.assert_allclose(a.R_icrf_cam.as_matrix(), b.R_icrf_cam.as_matrix(), rtol=0.0, atol=1e-12)
        for x, y in zip(a.records, b.records):
            sigma = np.sqrt(np.diag(y.covariance))
            np.testing.assert_allclose(x.value, y.value, rtol=0.0, atol=1e-6 * sigma.min())
            np.testing.assert_allclose(x.covariance, y.covariance, rtol=0.0, atol=1e-9 * np.abs(y.covariance).max())
            np.testing.assert_allclose(x.extra["xy_px"], y.extra["xy_px"], rtol=0.0, atol=1e-9)
            records += 1
        if ta is not None:
            np.testing.assert_array_equal(ta.found, tb.found)
            np.testing.assert_array_equal(ta.used, tb.used)
            ok = tb.centroids.ok
            np.testing.assert_allclose(ta.centroids.xy[ok], tb.centroids.xy[ok], rtol=0.0, atol=1e-9)
    assert records >= len(frames.paths)


# ---- the attitude gate and the camera model's scatter ------------------------------------------

def _stars_through(true: Camera, assumed: Camera, rng, n: int, sigma_px):
    """Bearings (through ``assumed``) of ``n`` stars imaged by ``true`` at a random attitude, centroids with
    ``sigma_px`` of noise, and their ICRF directions."""
    attitude = Rotation.random(random_state=rng)
    xy = rng.uniform([20.0, 20.0], [1003.0, 1003.0], (n, 2))
    v_icrf = attitude.apply(true.unproject(xy))
    measured = xy + rng.normal(0.0, 1.0, xy.shape) * np.reshape(sigma_px, (-1, 1))
    return tracking_mod.bearings(measured, assumed), v_icrf, attitude


def test_gate_keeps_the_stars_of_a_camera_known_to_a_fraction_of_a_pixel():
    """A camera with 0.8 px of radial distortion at the corner measured as a pinhole: centroid-sigma gating
    drops most stars; the gate widened by the residuals' scatter keeps them all, and its attitude
    covariance covers the attitude's error."""
    rng = np.random.default_rng(31)
    nominal = Camera.from_fov(1.0, 1024, 1024)
    f, rc = nominal.focal_length_px, math.hypot(512.0, 512.0) / nominal.focal_length_px
    distorted = nominal.replace(k1=0.8 / (f * rc**3))
    sigma = np.full(12, 0.01)
    b, v, attitude = _stars_through(distorted, nominal, rng, 12, 0.01)
    _, kept_plain = wahba_gated(b, v, sigma_rad=sigma * nominal.pixel_scale_rad, min_stars=3)
    fit = camera_scatter.gated_attitude(b, v, sigma, nominal, min_stars=3)
    solution, kept = fit.solution, fit.kept
    assert kept_plain.sum() <= 6 and kept.all()
    scatter = camera_scatter.model_scatter_px(b, v, sigma, nominal)
    assert fit.scatter_px == scatter
    assert 0.05 < scatter < 0.8  # the distortion left after the attitude takes its mean
    error = (attitude.inv() * solution.R_icrf_cam).as_rotvec()
    assert error @ np.linalg.solve(solution.cov_rad2, error) < chi2.ppf(0.999, 3)


def test_gate_is_unchanged_for_a_known_camera():
    """Noise alone: the model scatter is 0, and the gated fit is wahba_gated's, star for star, in 200 draws."""
    rng = np.random.default_rng(32)
    camera = Camera.from_fov(1.0, 1024, 1024)
    scatter = []
    for _ in range(200):
        n = int(rng.integers(4, 12))
        sigma = rng.uniform(0.01, 0.05, n)
        b, v, _ = _stars_through(camera, camera, rng, n, sigma)
        scatter.append(camera_scatter.model_scatter_px(b, v, sigma, camera))
        plain, kept_plain = wahba_gated(b, v, sigma_rad=sigma * camera.pixel_scale_rad, min_stars=3)
        fit = camera_scatter.gated_attitude(b, v, sigma, camera, min_stars=3)
        solution, kept = fit.solution, fit.kept
        assert np.array_equal(kept, kept_plain)
        assert np.allclose(solution.R_icrf_cam.as_matrix(), plain.R_icrf_cam.as_matrix(), atol=0.0)
    assert not np.any(scatter)  # noise alone does not reach five times the centroid sigma


@pytest.mark.parametrize("n_stars", [3, 4])
def test_gate_allows_for_the_camera_of_a_sparse_field(n_stars):
    """3 or 4 stars through a pinhole model of a camera 0.2 % long with 1.5 px of radial distortion at the
    corner: the plain gate cannot drop enough stars to say so (it stops at 3 with stars 50 centroid sigmas
    out) and its covariance is far too small; the widened fit allows for the scatter, and its attitude
    covariance is the right size: over 300 fields the median of the error's chi-square is within the
    quartiles of chi-square(3), against hundreds for the plain fit. (The tail is heavier than a Gaussian's:
    the camera's error is one systematic pattern, estimated from 3-8 residuals.)"""
    rng = np.random.default_rng(33)
    nominal = Camera.from_fov(1.0, 1024, 1024)
    f, rc = nominal.focal_length_px, math.hypot(512.0, 512.0) / nominal.focal_length_px
    distorted = nominal.replace(focal_length_mm=nominal.focal_length_mm * 1.002, k1=1.5 / (f * rc**3))
    z2, z2_plain, widened = [], [], 0
    for _ in range(300):
        sigma = rng.uniform(0.01, 0.05, n_stars)
        b, v, attitude = _stars_through(distorted, nominal, rng, n_stars, sigma)
        fit = camera_scatter.gated_attitude(b, v, sigma, nominal, min_stars=3)
        plain, _ = wahba_gated(b, v, sigma_rad=sigma * nominal.pixel_scale_rad, min_stars=3)
        for solution, out in ((fit.solution, z2), (plain, z2_plain)):
            error = (attitude.inv() * solution.R_icrf_cam).as_rotvec()
            out.append(error @ np.linalg.solve(solution.cov_rad2, error))
        widened += fit.scatter_px > 0.0
        if fit.scatter_px > 0.0:  # the widened sigmas are the centroid's and the scatter in quadrature
            np.testing.assert_allclose(fit.sigma_px, np.hypot(sigma, fit.scatter_px))
        else:
            assert np.allclose(fit.solution.R_icrf_cam.as_matrix(), plain.R_icrf_cam.as_matrix(), atol=0.0)
    assert widened >= 270  # a field of stars near the centre can fit within its noise
    assert chi2.ppf(0.25, 3) < np.median(z2) < chi2.ppf(0.75, 3)
    assert np.median(z2_plain) > 100.0
