"""Targets: phase correction, moon RA/Dec with covariance, limb fits and starlight elevation."""

import math

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from opnav.camera import Camera
from opnav.constants import ARCSEC_RAD, RADIUS_KM
from opnav.errors import InputError, NoSolutionError
from opnav.frames import radec_to_unit, unit_to_radec
from opnav.image.targets import (
    fit_limb,
    limb_points,
    moon_direction,
    photocentre_offset,
    starlight_measurements,
)


def _lambert_law(a):
    return 3 * math.pi / 16 * math.sin(a) * (1 + math.cos(a)) / (math.sin(a) + (math.pi - a) * math.cos(a))


@pytest.mark.parametrize("phase", [0.3, 0.8, 1.3, 1.8, 2.3])
def test_lambert_sphere_offset_matches_closed_form(phase):
    # View frame: z' from camera to target, so the Sun at phase angle a is (sin a, 0, -cos a).
    sun = np.array([math.sin(phase), 0.0, -math.cos(phase)])
    d = photocentre_offset((1.0, 1.0, 1.0), Rotation.identity(), sun, law="lambert", n_grid=300)
    assert d[0] == pytest.approx(_lambert_law(phase), rel=2e-3)
    assert abs(d[1]) < 1e-9


def test_offset_rotates_with_the_scene_and_vanishes_at_zero_phase():
    radii = (13.4, 11.2, 9.2)
    body = Rotation.from_euler("xyz", [0.3, -0.2, 0.5])
    sun = np.array([0.6, 0.3, -0.74])
    sun /= np.linalg.norm(sun)
    d = photocentre_offset(radii, body, sun)
    turn = Rotation.from_euler("z", 0.7)
    d_turned = photocentre_offset(radii, turn * body, turn.apply(sun))
    np.testing.assert_allclose(d_turned, turn.as_matrix()[:2, :2] @ d, atol=2e-3 * np.linalg.norm(d))
    sphere = photocentre_offset((5.0, 5.0, 5.0), body, np.array([0.0, 0.0, -1.0]))
    np.testing.assert_allclose(sphere, 0.0, atol=1e-9)


def _narrow_camera():
    # S1 design used in the tests: 1.0 deg across 1024 px (3.5"/px), f = 762.7 mm, 13 um pixels.
    return Camera(1024, 1024, 762.7, 13.0)


def test_moon_direction_without_correction_and_its_covariance():
    rng = np.random.default_rng(1)
    camera = _narrow_camera()
    attitude = Rotation.from_euler("zyx", [40.0, -20.0, 10.0], degrees=True)
    xy = np.array([612.3, 401.7])
    cov_xy = np.array([[0.02**2, 0.3e-4], [0.3e-4, 0.03**2]])
    cov_att = np.diag([0.2, 0.3, 2.0]) ** 2 * ARCSEC_RAD**2
    res = moon_direction(xy, cov_xy, camera, attitude, cov_att)
    ra0, dec0 = unit_to_radec(attitude.apply(camera.unproject(xy)))
    assert res.ra_rad == pytest.approx(float(ra0), abs=1e-12) and res.dec_rad == pytest.approx(float(dec0), abs=1e-12)
    # Monte Carlo: perturb centroid and attitude, check the predicted covariance (NEES ~ chi2(2)).
    n = 500
    nees = []
    for dxy, dth in zip(rng.multivariate_normal(np.zeros(2), cov_xy, n), rng.multivariate_normal(np.zeros(3), cov_att, n)):
        u = (attitude * Rotation.from_rotvec(dth)).apply(camera.unproject(xy + dxy))
        ra, dec = unit_to_radec(u)
        e = np.array([(ra - res.ra_rad) * 1.0, dec - res.dec_rad])
        nees.append(e @ np.linalg.solve(res.cov_rad2, e))
    assert chi2.ppf(0.001, 2 * n) <= np.sum(nees) <= chi2.ppf(0.999, 2 * n)


def test_phase_correction_recovers_centre_of_figure():
    camera = _narrow_camera()
    attitude = Rotation.from_euler("zyx", [100.0, 30.0, -50.0], degrees=True)
    radius, range_km, phase = 11.0, 2.0e4, math.radians(70.0)
    u_cof_cam = camera.unproject(np.array([500.0, 530.0]))
    # Sun: phase angle 70 deg from the observer direction, towards camera +x in the image.
    to_observer = -u_cof_cam
    side = np.cross(u_cof_cam, np.cross(np.array([1.0, 0.0, 0.0]), u_cof_cam))
    side /= np.linalg.norm(side)
    sun_cam = math.cos(phase) * to_observer + math.sin(phase) * side
    # Independent photocentre from the closed-form Lambert law.
    u_pc = u_cof_cam + _lambert_law(phase) * radius / range_km * side
    xy_pc = camera.project(u_pc / np.linalg.norm(u_pc))
    res = moon_direction(
        xy_pc, np.eye(2) * 1e-6, camera, attitude, np.eye(3) * 1e-16,
        radii_km=(radius,) * 3, R_icrf_body=Rotation.identity(), sun_icrf=attitude.apply(sun_cam),
        range_km=range_km, law="lambert",
    )
    truth = attitude.apply(u_cof_cam)
    offset_rad = _lambert_law(phase) * radius / range_km
    err = math.acos(min(1.0, float(res.unit_icrf @ truth)))
    assert err < 5e-3 * offset_rad
    # and the correction's model uncertainty (10% of the offset) is in the covariance
    assert math.sqrt(np.trace(res.cov_rad2)) > 0.05 * offset_rad


def test_moon_direction_rejects_partial_phase_inputs():
    camera = _narrow_camera()
    with pytest.raises(InputError, match="together"):
        moon_direction(np.array([5.0, 5.0]), np.eye(2), camera, Rotation.identity(), np.eye(3), radii_km=(1, 1, 1))


# ---- limbs -----------------------------------------------------------------------------------

R_GEO_KM = 42_164.0


def _earth_frame(rng, camera, c_cam, rho, *, signal=3000.0, psf_sigma=1.0, supersample=4, clutter=True):
    """Own renderer (the project renderer's UV limb is soft): a uniform disk, hard edge at rho."""
    h, w = camera.shape
    ys, xs = np.mgrid[:h, :w]
    angle = np.arccos(np.clip(camera.unproject(np.stack([xs, ys], -1)) @ c_cam, -1, 1))
    frac = (angle < rho).astype(float)
    # supersample only the pixels the edge can cross
    band = np.abs(angle - rho) < 1.5 * camera.pixel_scale_rad * 1.2
    by, bx = ys[band], xs[band]
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    inside = np.zeros(band.sum())
    for dy in sub:
        for dx in sub:
            inside += (camera.unproject(np.stack([bx + dx, by + dy], -1)) @ c_cam) > math.cos(rho)
    frac[band] = inside / supersample**2
    expected = ndimage.gaussian_filter(signal * frac, psf_sigma) + 50.0
    if clutter:
        for x, y in rng.uniform(20, 490, (6, 2)):
            expected[int(y), int(x)] += 5000.0
    return rng.poisson(expected) + rng.normal(0.0, 5.0, expected.shape)


def _wide_camera():
    # S3 UV Earth sensor used in the tests: 30 deg across 512 px (3.5'/px) with mild distortion.
    return Camera.from_fov(30.0, 512, 512, k1=-0.02)


def test_earth_limb_fit_and_starlight_elevation_s3_accuracy():
    rng = np.random.default_rng(5)
    camera = _wide_camera()
    rho = math.asin(RADIUS_KM["earth"] / R_GEO_KM)
    errors, sigmas = [], []
    for trial in range(4):
        c_cam = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), 1.0])
        c_cam /= np.linalg.norm(c_cam)
        image = _earth_frame(rng, camera, c_cam, rho)
        guess = camera.project(c_cam) + rng.uniform(-5, 5, 2)
        pts = limb_points(image, guess, rho * camera.focal_length_px * 1.05)
        fit = fit_limb(pts, camera, rng=trial)
        attitude = Rotation.from_rotvec(rng.normal(0, 1, 3))
        star = attitude.apply(radec_to_unit(rng.uniform(0, 2 * np.pi), rng.uniform(-1, 1)))
        res = starlight_measurements(fit, attitude, np.zeros((3, 3)), star, body_radius_km=RADIUS_KM["earth"])
        c_icrf = attitude.apply(c_cam)
        alpha = math.acos(float(c_icrf @ star))
        errors.append(res.elevation_rad - (alpha - rho))
        sigmas.append(math.sqrt(res.var_elevation_rad2))
    errors, sigmas = np.array(errors), np.array(sigmas)
    # S3: UV Earth sensor 20" (3 sigma); the fit's own sigma must be honest too.
    assert np.all(np.abs(errors) <= 20.0 * ARCSEC_RAD)
    assert np.all(3 * sigmas <= 20.0 * ARCSEC_RAD)
    assert np.sum((errors / sigmas) ** 2) <= chi2.ppf(0.999, len(errors))


def test_limb_on_lit_side_only_ignores_the_terminator():
    rng = np.random.default_rng(6)
    camera = _wide_camera()
    rho = math.radians(5.0)
    c_cam = np.array([0.0, 0.0, 1.0])
    image = _earth_frame(rng, camera, c_cam, rho, clutter=False)
    # darken the half away from the Sun (Sun towards -x): a straight terminator through the centre
    cx = camera.project(c_cam)[0]
    image[:, int(cx) + 1:] = rng.normal(50.0, 8.0, image[:, int(cx) + 1:].shape)
    pts = limb_points(image, camera.project(c_cam), rho * camera.focal_length_px, sun_azimuth_rad=math.pi)
    fit = fit_limb(pts, camera, rng=1)
    err = math.acos(min(1.0, float(fit.centre_cam @ c_cam)))
    assert err < 3 * math.sqrt(np.trace(fit.cov[:2, :2])) + 1e-9
    assert abs(fit.radius_rad - rho) < 3 * math.sqrt(fit.cov[2, 2])


def test_limb_fit_needs_points():
    with pytest.raises(NoSolutionError, match="at least 5"):
        fit_limb(np.zeros((3, 2)), _wide_camera())


def _scipy_limb_points(image, centre_xy, radius_px):
    """The slow path of limb_points (every ray, no Sun arc): scipy sampling and smoothing."""
    angles = np.linspace(0.0, 2.0 * np.pi, 360, endpoint=False)
    step = 0.25
    radii = np.arange(0.6 * radius_px, 1.4 * radius_px, step)
    dirs = np.stack([np.cos(angles), np.sin(angles)], -1)
    pts = np.asarray(centre_xy, float)[None, None, :] + radii[None, :, None] * dirs[:, None, :]
    profile = ndimage.map_coordinates(image, [pts[..., 1].ravel(), pts[..., 0].ravel()], order=1, mode="nearest")
    grad = ndimage.gaussian_filter1d(profile.reshape(len(angles), len(radii)), 1.0 / step, axis=1, order=1)
    k = np.clip(np.argmin(grad, axis=1), 1, len(radii) - 2)
    rows = np.arange(len(angles))
    g0, g1, g2 = grad[rows, k - 1], grad[rows, k], grad[rows, k + 1]
    curvature = g0 - 2 * g1 + g2
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(curvature > 0, 0.5 * (g0 - g2) / curvature, 0.0)
    r_edge = radii[k] + np.clip(frac, -0.5, 0.5) * step
    keep = -g1 >= 0.3 * np.max(-g1)
    return np.asarray(centre_xy, float)[None, :] + r_edge[keep, None] * dirs[keep]


def _sequential_ransac_inliers(u, threshold, rng, iterations=300):
    """The slow path of fit_limb's consensus: one 3-point cone at a time."""
    best = None
    for _ in range(iterations):
        w = np.linalg.lstsq(u[rng.choice(len(u), 3, replace=False)], np.ones(3), rcond=None)[0]
        norm = np.linalg.norm(w)
        if not np.isfinite(norm) or norm <= 1.0:
            continue
        inliers = np.abs(np.arccos(np.clip(u @ (w / norm), -1, 1)) - math.acos(1.0 / norm)) < threshold
        if best is None or inliers.sum() > best.sum():
            best = inliers
    return best


def test_compiled_limb_path_gives_the_slow_paths_numbers():
    rng = np.random.default_rng(12)
    camera = _wide_camera()
    rho = math.asin(RADIUS_KM["earth"] / R_GEO_KM)
    for trial in range(5):
        c_cam = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), 1.0])
        c_cam /= np.linalg.norm(c_cam)
        image = _earth_frame(rng, camera, c_cam, rho)
        guess = camera.project(c_cam) + rng.uniform(-5, 5, 2)
        pts = limb_points(image, guess, rho * camera.focal_length_px * 1.05)
        np.testing.assert_allclose(pts, _scipy_limb_points(image, guess, rho * camera.focal_length_px * 1.05),
                                   rtol=0, atol=1e-9)
        # the vectorised consensus draws other samples, yet finds the same limb: the same final inliers
        fit = fit_limb(pts, camera, rng=trial)
        u = camera.unproject(pts)
        reference = _sequential_ransac_inliers(u, camera.pixel_scale_rad, np.random.default_rng(trial))
        assert abs(int(reference.sum()) - int(fit.inliers.sum())) <= 2
        err = math.acos(min(1.0, float(fit.centre_cam @ c_cam))) / camera.pixel_scale_rad
        assert err < 0.02  # px: the centre accuracy of the slow path (0.001-0.005 px on these frames)
