"""Camera calibration from identified stars (opnav.image.calibration) and camera files (opnav.camera).

The synthetic frames put stars at random pixels of a *true* camera, take their directions through
that camera and a random attitude, and add Gaussian centroid noise of a known sigma; the fit starts
from the nominal camera. A correct fit with honest covariances then has every parameter within
the chi-square bound of the truth and a chi-square per degree of freedom inside its distribution's
interval.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from opnav.camera import Camera, CameraCovariance, read_camera_file, write_camera_file
from opnav.errors import InputError
from opnav.image.calibration import (
    FrameStars,
    calibrate,
    corner_radius,
    corner_scale,
    parameter_values,
    residual_jacobian,
    with_parameters,
)

SIGMA_PX = 0.1


def true_camera(nominal: Camera, rng: np.random.Generator) -> Camera:
    """The nominal camera with focal length off by 0.2-0.5 %, principal point by 2-5 px and Brown
    distortion of a few px at the corner (the issue's ranges)."""
    f, rc = nominal.focal_length_px, corner_radius(nominal)
    angle, offset = rng.uniform(0, 2 * np.pi), rng.uniform(2, 5)
    radial_px = rng.choice([-1, 1]) * rng.uniform(1.5, 4.0)
    return nominal.replace(
        focal_length_mm=nominal.focal_length_mm * (1 + rng.choice([-1, 1]) * rng.uniform(0.002, 0.005)),
        cx_px=nominal.cx_px + offset * math.cos(angle), cy_px=nominal.cy_px + offset * math.sin(angle),
        k1=radial_px / (f * rc**3), k2=rng.uniform(-0.5, 0.5) / (f * rc**5), k3=rng.uniform(-0.2, 0.2) / (f * rc**7),
        p1=rng.uniform(-1, 1) / (f * rc**2), p2=rng.uniform(-1, 1) / (f * rc**2))


def synthetic_frames(camera: Camera, n_frames: int, n_stars: int, rng: np.random.Generator, *, sigma_px=SIGMA_PX):
    frames = []
    for k in range(n_frames):
        attitude = Rotation.random(random_state=rng)
        xy = rng.uniform([-0.5, -0.5], [camera.width_px - 0.5, camera.height_px - 0.5], (n_stars, 2))
        v_icrf = attitude.apply(camera.unproject(xy))
        measured = xy + rng.normal(0.0, sigma_px, xy.shape)
        cov = np.broadcast_to(np.eye(2) * sigma_px**2, (n_stars, 2, 2))
        prior = attitude * Rotation.from_rotvec(rng.normal(0.0, 3.0 / camera.focal_length_px, 3))
        frames.append(FrameStars(measured, cov, v_icrf, prior, f"frame{k}"))
    return frames


def test_jacobians_match_central_differences():
    rng = np.random.default_rng(11)
    camera = true_camera(Camera.from_fov(12.0, 1024, 768), rng)
    names = ("f", "cx", "cy", "k1", "k2", "k3", "p1", "p2")
    v_cam = camera.unproject(rng.uniform([0, 0], [1023, 767], (25, 2)))
    theta = np.array([2e-3, -1e-3, 4e-3])
    _, d_params, d_theta = residual_jacobian(camera, names, v_cam, theta)
    values = parameter_values(camera, names)
    # steps move the corner by 1e-3 px: pixels are linear in f, cx, cy and each Brown coefficient,
    # so central differences are exact up to rounding (~1e-13 of ~1e3 px over 1e-3 px)
    steps = 1e-3 / corner_scale(camera, names)
    for j, name in enumerate(names):
        h = steps[j]
        up = with_parameters(camera, (name,), [values[j] + h])
        down = with_parameters(camera, (name,), [values[j] - h])
        numeric = (residual_jacobian(up, (), v_cam, theta)[0] - residual_jacobian(down, (), v_cam, theta)[0]) / (2 * h)
        np.testing.assert_allclose(d_params[:, :, j] * h, numeric * h, rtol=0, atol=1e-8, err_msg=name)
    # rotations of 1e-7 rad (a few thousandths of a px): truncation ~ f h^3 ~ 1e-18 px, rounding ~ 1e-10 px
    for j in range(3):
        h = np.zeros(3)
        h[j] = 1e-7
        numeric = (residual_jacobian(camera, (), v_cam, theta + h)[0] - residual_jacobian(camera, (), v_cam, theta - h)[0]) / 2e-7
        np.testing.assert_allclose(d_theta[:, :, j] * 1e-7, numeric * 1e-7, rtol=0, atol=1e-8)
        assert np.abs(d_theta[:, :, j]).max() > 1e2  # the check is not vacuous: px per rad ~ f


def test_noise_free_stars_give_the_true_camera():
    rng = np.random.default_rng(3)
    nominal = Camera.from_fov(12.0, 1024, 1024)
    truth = true_camera(nominal, rng)
    frames = synthetic_frames(truth, 3, 60, rng, sigma_px=1e-9)
    fitted = calibrate(frames, nominal)
    # a pixel's worth of a parameter at the corner is its scale; noise-free it must come back to far below that
    np.testing.assert_allclose(fitted.values, parameter_values(truth, fitted.names),
                               rtol=0, atol=1e-6 * np.abs(parameter_values(truth, fitted.names)).max())
    assert fitted.rms_px < 1e-6


@pytest.mark.parametrize("fov_deg, n_frames, n_stars", [(12.0, 1, 300), (12.0, 20, 15), (6.0, 1, 300), (6.0, 20, 15)])
def test_recovers_truth_within_its_sigma(fov_deg, n_frames, n_stars):
    rng = np.random.default_rng(int(fov_deg) * 100 + n_frames)
    nominal = Camera.from_fov(fov_deg, 1024, 1024)
    cases = 4
    z2 = []
    chi2_values, dofs = [], []
    for _ in range(cases):
        truth = true_camera(nominal, rng)
        fitted = calibrate(synthetic_frames(truth, n_frames, n_stars, rng), nominal)
        error = fitted.values - parameter_values(truth, fitted.names)
        z2.append(error @ np.linalg.solve(fitted.covariance, error))
        chi2_values.append(fitted.chi2)
        dofs.append(fitted.dof)
        # the post-fit RMS is the noise less what the unknowns absorb: rms^2 * 2N / sigma^2 ~ chi-square(dof)
        rows = 2 * fitted.n_stars
        assert chi2.ppf(1e-4, fitted.dof) < fitted.rms_px**2 * rows / SIGMA_PX**2 < chi2.ppf(1 - 1e-4, fitted.dof)
    p = len(fitted.names)
    # the parameters' joint error, normalised by their covariance, is chi-square with p dof per case
    assert sum(z2) < chi2.ppf(0.999, p * cases)
    # the residuals' chi-square: the sum over cases is chi-square with the summed dof (no outliers injected)
    total, dof = sum(chi2_values), sum(dofs)
    assert chi2.ppf(0.0005, dof) < total < chi2.ppf(0.9995, dof)


def test_outliers_are_rejected_and_do_not_bias_the_fit():
    rng = np.random.default_rng(5)
    nominal = Camera.from_fov(12.0, 1024, 1024)
    truth = true_camera(nominal, rng)
    frames = synthetic_frames(truth, 4, 40, rng)
    bad = frames[1]
    xy = bad.xy.copy()
    xy[:3] += np.array([[5.0, 0.0], [0.0, -8.0], [3.0, 3.0]])  # a misidentified star, a blend, a hot pixel
    frames[1] = FrameStars(xy, bad.cov, bad.v_icrf, bad.R_icrf_cam, bad.name)
    fitted = calibrate(frames, nominal)
    assert not fitted.frames[1].kept[:3].any()
    assert fitted.n_rejected == 3
    error = fitted.values - parameter_values(truth, fitted.names)
    assert error @ np.linalg.solve(fitted.covariance, error) < chi2.ppf(0.999, len(error))


def test_before_residuals_show_the_uncalibrated_camera():
    rng = np.random.default_rng(8)
    nominal = Camera.from_fov(12.0, 1024, 1024)
    truth = true_camera(nominal, rng)
    fitted = calibrate(synthetic_frames(truth, 1, 200, rng), nominal)
    frame = fitted.frames[0]
    # the true camera is off by pixels at the corner: the nominal camera leaves far more than the noise
    assert frame.rms_before_px > 5 * SIGMA_PX
    assert frame.rms_px < 1.2 * SIGMA_PX


def test_unobservable_parameters_are_refused_by_name():
    rng = np.random.default_rng(2)
    nominal = Camera.from_fov(1.0, 1024, 1024)
    # a distortion-free narrow camera: the principal point is a rotation of the attitude to within
    # (field / 2)^2, thousands of px of sigma
    frames = synthetic_frames(nominal, 2, 30, rng)
    with pytest.raises(InputError, match=r"do not constrain cx \([0-9.e+]+ px\), cy") as info:
        calibrate(frames, nominal, model="pinhole", fit=("f", "cx", "cy"))
    assert "\n" not in str(info.value)
    fitted = calibrate(frames, nominal, model="pinhole", fit=("f",))
    assert fitted.names == ("f",)


def test_auto_fit_answers_a_narrow_field_with_the_principal_point_at_its_prior():
    """A 1-degree camera: the stars hardly constrain the principal point (a turn of the attitude), so
    ``fit="auto"`` estimates it with its prior, which its sigma and the other parameters' carry."""
    rng = np.random.default_rng(12)
    nominal = Camera.from_fov(1.0, 1024, 1024)
    truth = true_camera(nominal, rng)
    frames = synthetic_frames(truth, 1, 20, rng)  # 20 stars: 15 px of principal-point sigma from the stars alone
    with pytest.raises(InputError, match=r"do not constrain cx"):
        calibrate(frames, nominal, fit=("f", "cx", "cy", "k1", "k2", "k3", "p1", "p2"))
    fitted = calibrate(frames, nominal, principal_point_sigma_px=5.0)
    assert fitted.names == ("f", "cx", "cy", "k1", "k2", "k3", "p1", "p2") and fitted.held == ()
    share = dict(zip(fitted.names, fitted.stars_share))
    sigma = dict(zip(fitted.names, fitted.sigma))
    # the prior, not the stars, bounds the principal point; the stars alone bound the focal length
    assert share["cx"] < 0.5 and share["cy"] < 0.5 and share["f"] == 1.0
    assert sigma["cx"] <= 5.0 and sigma["cy"] <= 5.0
    z = (fitted.values - parameter_values(truth, fitted.names)) / fitted.sigma
    assert np.all(np.abs(z) < np.sqrt(chi2.ppf(0.999, len(z))))
    # the stars cannot tell: a prior far narrower than the truth's offset holds the estimate at the
    # nominal point, beyond 3 of its sigmas from the truth, with no sign of it in the fit's chi-square
    offset = math.hypot(truth.cx_px - nominal.cx_px, truth.cy_px - nominal.cy_px)
    tight = calibrate(frames, nominal, principal_point_sigma_px=offset / 30.0)
    moved = math.hypot(tight.value("cx") - nominal.cx_px, tight.value("cy") - nominal.cy_px)
    assert moved < 0.1 * offset
    assert tight.chi2_per_dof < chi2.ppf(0.999, tight.dof) / tight.dof


def test_bad_input_ends_in_one_clear_line():
    rng = np.random.default_rng(4)
    nominal = Camera.from_fov(12.0, 1024, 1024)
    frames = synthetic_frames(nominal, 2, 30, rng)
    with pytest.raises(InputError, match="3 identified stars; calibration needs at least 4"):
        calibrate([FrameStars(f.xy[:3], f.cov[:3], f.v_icrf[:3], f.R_icrf_cam, "few.fits") for f in frames[:1]], nominal)
    small = Camera.from_fov(12.0, 640, 480)
    with pytest.raises(InputError, match="outside the 640 x 480 px detector.*another camera"):
        calibrate(frames, small)
    with pytest.raises(InputError, match="--model 'fisheye' is not a camera model; accepted: pinhole"):
        calibrate(frames, nominal, model="fisheye")
    with pytest.raises(InputError, match="--fit p1: not in --model radial2"):
        calibrate(frames, nominal, model="radial2", fit=("f", "p1"))
    with pytest.raises(InputError, match="unknown parameter k4"):
        calibrate(frames, nominal, fit=("k4",))
    with pytest.raises(InputError, match="residuals for"):
        calibrate([FrameStars(f.xy[:4], f.cov[:4], f.v_icrf[:4], f.R_icrf_cam, f.name) for f in frames[:1]], nominal)


def test_camera_file_round_trip(tmp_path):
    rng = np.random.default_rng(9)
    nominal = Camera.from_fov(12.0, 1024, 1024, camera_id="navcam")
    truth = true_camera(nominal, rng)
    fitted = calibrate(synthetic_frames(truth, 2, 80, rng), nominal)
    path = tmp_path / "camera.toml"
    write_camera_file(path, fitted.camera, CameraCovariance(fitted.names, fitted.covariance, {"model": fitted.model}),
                      comment="opnav calibrate test")
    read = read_camera_file(path)
    assert read.camera == fitted.camera  # every float back to the bit
    assert read.calibration.names == fitted.names
    np.testing.assert_allclose(read.calibration.covariance, fitted.covariance, rtol=1e-12)
    assert read.calibration.summary == {"model": "brown"}


@pytest.mark.parametrize("text, message", [
    ("[camera]\nwidth_px = 1024\n", r"\[camera\] needs height_px"),
    ("[camera]\nwidth_px = 10\nheight_px = 10\nfocal_length_mm = 50.0\npixel_pitch_um = 5.0\nk9 = 1.0\n",
     r"'k9'\] in \[camera\].*known keys: width_px"),
    ("[lens]\nf = 1\n", r"unknown \[lens\]"),
    ("[camera]\nwidth_px = 10\nheight_px = 10\nfocal_length_mm = 50.0\npixel_pitch_um = 5.0\n"
     "[calibration]\nparameters = [\"f\"]\nsigma = [-1.0]\ncorrelation = [[1.0]]\n", r"\[calibration\] sigma must hold 1 positive"),
])
def test_bad_camera_files_are_refused_in_one_line(tmp_path, text, message):
    path = tmp_path / "camera.toml"
    path.write_text(text)
    with pytest.raises(InputError, match=message) as info:
        read_camera_file(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_target_direction_covariance_matches_cameras_drawn_from_the_calibration():
    """The linearised covariance of a target's direction relative to the stars' attitude against the
    direction errors of 400 cameras drawn from the calibration's covariance (Wahba on the same stars)."""
    from opnav.image.attitude import wahba_rotation
    from opnav.image.calibration import target_direction_covariance

    rng = np.random.default_rng(21)
    nominal = Camera.from_fov(6.0, 1024, 1024)
    truth = true_camera(nominal, rng)
    fitted = calibrate(synthetic_frames(truth, 3, 60, rng, sigma_px=0.3), nominal, max_sigma_px=50.0)
    camera = fitted.camera
    star_xy = rng.uniform([0, 0], [1023, 1023], (8, 2))
    target_xy = np.array([700.0, 300.0])
    cov = target_direction_covariance(camera, fitted.names, fitted.covariance, star_xy, target_xy)
    reference = camera.unproject(target_xy)
    x_axis = np.array([1.0, 0.0, 0.0]) - reference[0] * reference
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(reference, x_axis)
    errors = []
    for values in rng.multivariate_normal(fitted.values, fitted.covariance, 400):
        drawn = with_parameters(camera, fitted.names, values)
        rotation = wahba_rotation(drawn.unproject(star_xy), camera.unproject(star_xy), np.ones(len(star_xy)))
        direction = rotation.apply(drawn.unproject(target_xy))
        errors.append([direction @ x_axis, direction @ y_axis])
    errors = np.array(errors) - [reference @ x_axis, reference @ y_axis]
    # each draw's error normalised by the predicted covariance: chi-square(2), mean 2 over 400 draws
    z2 = np.einsum("ni,ij,nj->n", errors, np.linalg.inv(cov), errors)
    assert chi2.ppf(0.001, 800) / 400 < z2.mean() < chi2.ppf(0.999, 800) / 400
    assert np.sqrt(np.trace(cov)) * camera.focal_length_px > 1e-3  # not vacuous: thousandths of a px or more


def test_a_frame_whose_stars_do_not_fit_is_left_out_and_named():
    """A frame matched to the wrong stars (its catalog directions shuffled) cannot keep 3 stars within the
    gate: it is left out with its name and the others give the camera; alone it is refused in one line."""
    rng = np.random.default_rng(14)
    nominal = Camera.from_fov(12.0, 1024, 1024)
    truth = true_camera(nominal, rng)
    frames = synthetic_frames(truth, 4, 40, rng)
    bad = frames[2]
    wrong = FrameStars(bad.xy, bad.cov, bad.v_icrf[rng.permutation(len(bad.xy))], bad.R_icrf_cam, "wrong.fits")
    fitted = calibrate([*frames[:2], wrong, frames[3]], nominal)
    assert len(fitted.dropped) == 1 and fitted.dropped[0].startswith("wrong.fits: only")
    assert [f.name for f in fitted.frames] == ["frame0", "frame1", "frame3"]
    z = (fitted.values - parameter_values(truth, fitted.names)) / fitted.sigma
    assert np.all(np.abs(z) < np.sqrt(chi2.ppf(0.999, len(z))))
    with pytest.raises(InputError, match=r"^wrong.fits: only \d stars fit the camera within the gate") as info:
        calibrate([wrong], nominal, fit=("f",))
    assert "\n" not in str(info.value)


def test_brown1_fits_a_narrow_field_and_knows_its_centre_better():
    """A 1-degree camera whose lens has k2 and k3 of the size of k1 in normalised units (their corner
    displacement 1e-4 and 1e-8 of k1's): the ``brown1`` model (k1 p1 p2) recovers the truth within its
    covariance, and the direction of a target at the field centre relative to the stars of a sparse frame
    is known better than with ``brown``, whose k2 and k3 take values no lens has (the sums over 4 cases of
    both cameras' noise-free target errors, normalised by each one's own covariance, are chi-square(2 x 4))."""
    from opnav.image.calibration import target_direction_covariance

    rng = np.random.default_rng(41)
    nominal = Camera.from_fov(1.0, 1024, 1024)
    f, rc = nominal.focal_length_px, corner_radius(nominal)
    z2, z2_target, sigma_ratio = [], {"brown": [], "brown1": []}, []
    for _ in range(4):
        k1 = rng.choice([-1, 1]) * rng.uniform(1.5, 4.0) / (f * rc**3)
        truth = nominal.replace(focal_length_mm=nominal.focal_length_mm * 1.003, cx_px=nominal.cx_px + 3.0,
                                cy_px=nominal.cy_px - 2.0, k1=k1, k2=k1, k3=k1,
                                p1=rng.uniform(-1, 1) / (f * rc**2), p2=rng.uniform(-1, 1) / (f * rc**2))
        frames = synthetic_frames(truth, 40, 6, rng, sigma_px=0.02)
        stars = rng.uniform(50.0, 974.0, (4, 2))
        centre = np.array([nominal.cx_px, nominal.cy_px])
        sigmas = {}
        for model in ("brown", "brown1"):
            fitted = calibrate(frames, nominal, model=model)
            if model == "brown1":
                error = fitted.values - parameter_values(truth, fitted.names)
                z2.append(error @ np.linalg.solve(fitted.covariance, error))
            cov = target_direction_covariance(fitted.camera, fitted.names, fitted.covariance, stars, centre)
            miss = _target_error(fitted.camera, truth, stars, centre)
            z2_target[model].append(miss @ np.linalg.solve(cov, miss))
            sigmas[model] = math.sqrt(np.trace(cov))
        sigma_ratio.append(sigmas["brown1"] / sigmas["brown"])
    assert sum(z2) < chi2.ppf(0.999, 6 * 4)
    for model, values in z2_target.items():
        assert sum(values) < chi2.ppf(0.999, 2 * 4), model
    assert max(sigma_ratio) < 1.0


def _target_error(camera: Camera, truth: Camera, star_xy: np.ndarray, target_xy: np.ndarray) -> np.ndarray:
    """The direction error (rad, on ``camera``'s x and y axes at the target) ``camera`` makes for a target at
    ``target_xy`` relative to stars at ``star_xy`` of a frame ``truth`` took (Wahba, equal weights)."""
    from opnav.image.attitude import wahba_rotation

    true_directions = truth.unproject(star_xy)  # the frame's stars in the true camera frame
    rotation = wahba_rotation(camera.unproject(star_xy), true_directions, np.ones(len(star_xy)))
    direction = rotation.apply(camera.unproject(target_xy))
    reference = truth.unproject(target_xy)
    x_axis = np.array([1.0, 0.0, 0.0]) - reference[0] * reference
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(reference, x_axis)
    return np.array([direction @ x_axis, direction @ y_axis])


@pytest.mark.parametrize("floor_px", [0.0, 0.03])
def test_auto_floor_recovers_the_error_the_covariances_leave_out(floor_px):
    """Stars whose covariances say 0.01-0.1 px a axis but whose errors carry ``floor_px`` more in quadrature
    (a PSF model's error): ``sigma_floor_px="auto"`` finds it within 15 % (0 when there is none: below a
    tenth of the smallest sigma), and the fit's chi-square per dof and parameters are then honest."""
    rng = np.random.default_rng(23)
    nominal = Camera.from_fov(12.0, 1024, 1024)
    truth = true_camera(nominal, rng)
    frames = []
    for k in range(4):
        attitude = Rotation.random(random_state=rng)
        xy = rng.uniform(-0.5, 1023.5, (150, 2))
        sigma = rng.uniform(0.01, 0.1, 150)
        error = rng.normal(size=(150, 2)) * np.sqrt(sigma**2 + floor_px**2)[:, None]
        cov = sigma[:, None, None] ** 2 * np.eye(2)
        prior = attitude * Rotation.from_rotvec(rng.normal(0.0, 3.0 / truth.focal_length_px, 3))
        frames.append(FrameStars(xy + error, cov, attitude.apply(truth.unproject(xy)), prior, f"frame{k}"))
    fit = calibrate(frames, nominal, sigma_floor_px="auto")
    if floor_px:
        assert abs(fit.sigma_floor_px / floor_px - 1.0) < 0.15
    else:
        assert fit.sigma_floor_px < 0.001
    assert chi2.ppf(0.0005, fit.dof) / fit.dof < fit.chi2_per_dof < chi2.ppf(0.9995, fit.dof) / fit.dof
    error = fit.values - parameter_values(truth, fit.names)
    assert error @ np.linalg.solve(fit.covariance, error) < chi2.ppf(0.999, len(error))
    with pytest.raises(InputError, match="--sigma-floor-px must be a number >= 0 or auto"):
        calibrate(frames, nominal, sigma_floor_px="some")
