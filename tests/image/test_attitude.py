"""Wahba solution, Shuster covariance consistency, camera refinement."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from opnav.camera import Camera
from opnav.errors import CovarianceError, InputError
from opnav.image.attitude import _condition_bound, _information, refine_camera, shuster_covariance, wahba, wahba_gated


def _field_directions(rng, n, half_angle_rad):
    """n camera-frame unit vectors uniform in a cone about +z."""
    cos_theta = rng.uniform(np.cos(half_angle_rad), 1.0, n)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    sin_theta = np.sqrt(1.0 - cos_theta**2)
    return np.column_stack([sin_theta * np.cos(phi), sin_theta * np.sin(phi), cos_theta])


def _perturb(rng, b, sigma_rad):
    """Add isotropic tangent-plane noise of sigma_rad per axis to unit vectors b."""
    noise = rng.normal(0.0, sigma_rad, b.shape)
    noise -= np.sum(noise * b, axis=1, keepdims=True) * b
    noisy = b + noise
    return noisy / np.linalg.norm(noisy, axis=1, keepdims=True)


def test_noise_free_vectors_give_the_exact_rotation():
    rng = np.random.default_rng(11)
    truth = Rotation.random(random_state=12)
    b = _field_directions(rng, 6, np.radians(8.0))
    solution = wahba(b, truth.apply(b), sigma_rad=1e-5)
    assert (solution.R_icrf_cam * truth.inv()).magnitude() < 1e-12
    assert np.all(solution.residuals_rad < 1e-12)


def test_quarter_turn_about_z():
    # Closed form: x -> y, y -> -x under +90 deg about z.
    b = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    v = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    solution = wahba(b, v, sigma_rad=1e-4)
    np.testing.assert_allclose(solution.R_icrf_cam.as_rotvec(), [0.0, 0.0, np.pi / 2], atol=1e-12)


def test_nees_is_chi_square_consistent():
    """Mean NEES of the camera-frame attitude error over seeded runs lies in the 95% chi2(3) band."""
    rng = np.random.default_rng(2024)
    runs, sigma = 400, 5e-5
    nees = np.empty(runs)
    for k in range(runs):
        truth = Rotation.random(random_state=rng.integers(2**31))
        b_true = _field_directions(rng, int(rng.integers(4, 15)), np.radians(7.0))
        b = _perturb(rng, b_true, sigma)
        solution = wahba(b, truth.apply(b_true), sigma_rad=sigma)
        error = (solution.R_icrf_cam.inv() * truth).as_rotvec()  # truth = estimate * exp(error)
        nees[k] = error @ np.linalg.solve(solution.cov_rad2, error)
    low, high = chi2.ppf([0.025, 0.975], 3 * runs) / runs
    assert low < nees.mean() < high


def test_collinear_stars_have_no_attitude():
    b = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    with pytest.raises(CovarianceError, match="collinear"):
        wahba(b, b, sigma_rad=1e-5)


def test_the_covariance_refuses_what_the_condition_number_refuses():
    """shuster_covariance skips the SVD's condition number when a cheap bound settles it: over fields from
    a thousandth of an arcsecond to a radian, nearly collinear ones included, the bound is never below
    the SVD's figure, and the covariance is refused exactly when that figure exceeds 1e12."""
    rng = np.random.default_rng(7)
    for _ in range(3000):
        n = int(rng.integers(2, 12))
        spread = 10.0 ** rng.uniform(-8.5, 0.0)
        b = np.column_stack([rng.normal(size=(n, 2)) * spread, np.ones(n)])
        if rng.random() < 0.3:  # stars along a line (a degenerate, nearly collinear field)
            b[:, 1] = b[:, 0] * rng.normal() + rng.normal(size=n) * spread * 10.0 ** rng.uniform(-9, -3)
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        sigma = rng.uniform(1e-7, 1e-5, n)
        weights = 1.0 / sigma**2
        information = np.einsum("n,nij->ij", weights, np.eye(3)[None] - b[:, :, None] * b[:, None, :])
        condition = np.linalg.cond(information)
        assert _condition_bound(information) >= condition
        if condition > 1e12:
            with pytest.raises(CovarianceError):
                shuster_covariance(b, sigma)
        else:
            np.testing.assert_allclose(shuster_covariance(b, sigma) @ information, np.eye(3), atol=1e-12 * condition)


def test_the_compiled_information_matrix_is_numpys():
    """shuster_covariance's information matrix, compiled, is the einsum it replaced to the bit (2 to 60 stars,
    equal and unequal weights, fields from 1e-4 to 1 rad)."""
    rng = np.random.default_rng(8)
    for _ in range(500):
        n = int(rng.integers(2, 60))
        b = rng.normal(size=(n, 3)) * 10.0 ** rng.uniform(-4, 0) + [0.0, 0.0, 1.0]
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        weights = 1.0 / rng.uniform(1e-7, 1e-5, n) ** 2
        if rng.random() < 0.5:
            weights = np.full(n, weights[0])
        expected = np.einsum("n,nij->ij", weights, np.eye(3)[None] - b[:, :, None] * b[:, None, :])
        np.testing.assert_array_equal(_information(b, weights), expected)


@pytest.mark.parametrize(
    "b, v, sigma, message",
    [
        (np.ones((3, 2)), np.ones((3, 2)), 1e-5, "shape"),
        (np.eye(3), np.eye(3)[:2], 1e-5, "same shape"),
        (np.eye(3)[:1], np.eye(3)[:1], 1e-5, "at least 2"),
        (np.eye(3), np.eye(3), -1.0, "sigma_rad"),
        (np.full((3, 3), np.nan), np.eye(3), 1e-5, "NaN"),
    ],
)
def test_bad_input_is_rejected(b, v, sigma, message):
    with pytest.raises(InputError, match=message):
        wahba(b, v, sigma_rad=sigma)


@pytest.mark.parametrize("sigma_px", [0.0, 0.1])
def test_refine_camera_recovers_focal_length_and_k1(sigma_px):
    rng = np.random.default_rng(5)
    true_camera = Camera.from_fov(12.0, 1024, 768, k1=-0.05)
    truth = Rotation.random(random_state=6)
    xy_true = rng.uniform([20.0, 20.0], [1003.0, 747.0], (40, 2))
    v_icrf = truth.apply(true_camera.unproject(xy_true))
    xy = xy_true + rng.normal(0.0, sigma_px, xy_true.shape)
    start_camera = true_camera.replace(focal_length_mm=true_camera.focal_length_mm * 1.02, k1=0.0)
    start = truth * Rotation.from_rotvec([2e-4, -1e-4, 3e-4])
    fit = refine_camera(xy, v_icrf, start_camera, start, fit_k1=True)
    if sigma_px == 0.0:
        assert abs(fit.camera.focal_length_mm / true_camera.focal_length_mm - 1.0) < 1e-9
        assert abs(fit.camera.k1 - true_camera.k1) < 1e-7
        assert (fit.R_icrf_cam * truth.inv()).magnitude() < 1e-10
    else:
        # The residual sum of squares of a linearised fit is sigma^2 chi2(2N - 5).
        dof = 2 * len(xy) - 5
        rss = fit.rms_px**2 * len(xy) / sigma_px**2
        assert chi2.ppf(0.001, dof) < rss < chi2.ppf(0.999, dof)
        assert abs(fit.camera.focal_length_mm / true_camera.focal_length_mm - 1.0) < 1e-3


def test_gated_wahba_drops_a_blend_and_stays_consistent():
    # One bright star (small sigma) displaced by 0.5 px-equivalent, as an unresolved double
    # is: the plain fit is dragged far outside its covariance, the gated fit drops that star
    # and its attitude error is consistent with its covariance over seeded runs.
    rng = np.random.default_rng(21)
    sigma = np.full(40, 2e-6)
    sigma[0] = 2e-7
    nees_plain, nees_gated, dropped = [], [], []
    for _ in range(200):
        truth = Rotation.random(random_state=rng.integers(2**31))
        b = _field_directions(rng, 40, np.radians(0.15))
        v = truth.apply(b)
        measured = np.array([_perturb(rng, bi[None], s)[0] for bi, s in zip(b, sigma)])
        measured[0] = _perturb(rng, measured[0][None], 5e-5)[0]
        gated, kept = wahba_gated(measured, v, sigma_rad=sigma)  # one call: its solution and its mask
        for solution, store in ((wahba(measured, v, sigma_rad=sigma), nees_plain), (gated, nees_gated)):
            err = (truth.inv() * solution.R_icrf_cam).as_rotvec()
            store.append(err @ np.linalg.solve(solution.cov_rad2, err))
        dropped.append(~kept)
    lo, hi = chi2.ppf([0.025, 0.975], 3 * 200) / 200
    assert lo < np.mean(nees_gated) < hi
    assert np.mean(nees_plain) > hi
    assert np.mean([d[0] for d in dropped]) > 0.99
    # clean stars are dropped only at the gate's false-alarm rate (1e-4 each)
    assert np.mean([d[1:].sum() for d in dropped]) < 0.05


def test_gated_wahba_drops_a_bright_wrong_star_among_few_faint_ones():
    # Six stars; the brightest (sigma 10x smaller) is displaced, as a star blended with a
    # hot-pixel cluster is: the plain fit follows it and leaves its largest residuals on the
    # good stars. The gate must drop the bright star, not the good ones.
    rng = np.random.default_rng(4)
    sigma = np.full(6, 2e-6)
    sigma[0] = 2e-7
    for _ in range(50):
        truth = Rotation.random(random_state=rng.integers(2**31))
        b = _field_directions(rng, 6, np.radians(0.5))
        v = truth.apply(b)
        measured = np.array([_perturb(rng, bi[None], s)[0] for bi, s in zip(b, sigma)])
        tangent = np.cross(measured[0], rng.normal(size=3))
        measured[0] += 3e-5 * tangent / np.linalg.norm(tangent)  # 150 of its sigmas, 15 of the others'
        solution, kept = wahba_gated(measured, v, sigma_rad=sigma)
        assert not kept[0] and kept[1:].all()
        err = (truth.inv() * solution.R_icrf_cam).as_rotvec()
        assert err @ np.linalg.solve(solution.cov_rad2, err) < chi2.ppf(0.9999, 3)
