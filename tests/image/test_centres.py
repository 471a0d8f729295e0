"""Centre finding for resolved bodies on rendered frames: the closed-form horizon solution, the limb
fit and the cross-correlation against the renderer's truth, the terminator never taken for the
limb, and the choice of method by size and phase."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from centre_scene import camera_1mp, render_scene
from opnav.errors import InputError, NoSolutionError
from opnav.image.centres import CentreOptions, apparent_diameter_px, body_pose, choose_method
from opnav.image.correlate import DetectorNoise, correlate_centre
from opnav.image.ellipsoid import (
    EllipsoidPose,
    horizon_cone,
    horizon_position,
    ideal_xy,
    line_crossings,
    outline_points,
)
from opnav.image.limb import LimbOptions, fit_limb_ellipsoid, scan_lines, usable_lines

#: a centre error beyond this Mahalanobis distance squared (chi-square, 2 dof) fails: 3 sigma's 99.73 %
GATE_2D = chi2.ppf(0.9973, 2)


def _tri_axial_pose():
    return EllipsoidPose(radii_km=np.array([13.0, 11.4, 9.1]), R_cam_body=Rotation.from_euler("zyx", [0.4, -0.7, 1.2]).as_matrix(),
                         r_cam_km=np.array([3.0, -2.0, 4000.0]), sun_cam=np.array([0.6, 0.2, -0.3]))


def test_closed_form_horizon_solution_recovers_a_tri_axial_body_exactly():
    pose = _tri_axial_pose()
    from opnav.camera import Camera

    cam = Camera(width_px=1024, height_px=1024, focal_length_mm=500.0, pixel_pitch_um=10.0)
    u = cam.unproject(outline_points(cam, pose))
    r = horizon_position(pose.at(np.array([0.0, 0.0, 1.0e4])), u)  # the prior position is not used
    np.testing.assert_allclose(r, pose.r_cam_km, rtol=1e-9)


def test_line_crossings_lie_on_the_outline():
    pose = _tri_axial_pose()
    from opnav.camera import Camera

    cam = Camera(width_px=1024, height_px=1024, focal_length_mm=500.0, pixel_pitch_um=10.0)
    cone = horizon_cone(pose)
    centre = ideal_xy(cam, cam.project(pose.r_cam_km))
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    dirs = np.stack([np.cos(angles), np.sin(angles)], 1)
    starts = np.repeat(centre[None], 12, 0)
    a = line_crossings(cone, cam.focal_length_px, starts, dirs)
    hits = starts + a[:, None] * dirs
    m = np.concatenate([hits, np.full((12, 1), cam.focal_length_px)], 1)
    grad = 2.0 * np.hypot(*(m @ cone.T)[:, :2].T)
    assert np.all(a > 0)
    assert np.max(np.abs(np.einsum("ni,ij,nj->n", m, cone, m)) / grad) < 1e-9  # px from the conic


def _prior(pose, camera, rng, px=1.0, rel_range=0.01):
    f = camera.focal_length_px
    turn = Rotation.from_rotvec([rng.normal(0, px) / f, rng.normal(0, px) / f, 0.0])
    return pose.at(turn.apply(pose.r_cam_km) * (1.0 + rng.normal(0, rel_range)))


def _noise(camera):
    return DetectorNoise(camera.read_noise_e, camera.gain_e_per_adu, camera.bias_adu)


@pytest.mark.parametrize("name, diameter, phase, seed", [("mars", 60, 40, 1), ("moon", 80, 80, 2), ("phobos", 50, 30, 3)])
def test_limb_fit_centre_and_range_within_three_sigma_of_truth(name, diameter, phase, seed):
    """A noisy, blurred frame with a prior 1 px and 1 % off: the centre inside its 3-sigma ellipse,
    the range inside 3 sigma. The body is made faint enough (peak 3000 e-) that the noise, not
    the model's pixel integral, sets the error."""
    rng = np.random.default_rng(seed)
    scene = render_scene(name, diameter, phase, rng=rng, peak_e=3000.0, supersample=4)
    pose = body_pose(scene.body, scene.R_icrf_cam, scene.observer, scene.ephemeris)
    fit = fit_limb_ellipsoid(scene.image, scene.camera, _prior(pose, scene.camera, rng),
                             psf_sigma_px=scene.psf_sigma_px, noise=_noise(scene.camera))
    err = fit.xy_px - scene.xy_true_px
    assert err @ np.linalg.solve(fit.cov_xy_px2, err) < GATE_2D, (err, np.sqrt(np.diag(fit.cov_xy_px2)))
    assert abs(fit.range_km - scene.range_true_km) < 3.0 * fit.sigma_range_km
    # an honest sigma: a 60-80 px limb at this brightness is good to a few hundredths of a pixel
    assert 0.003 < math.sqrt(np.trace(fit.cov_xy_px2)) < 0.1


@pytest.mark.parametrize("name, diameter, phase, seed", [("phobos", 12, 60, 4), ("mars", 30, 100, 5)])
def test_cross_correlation_centre_within_three_sigma_of_truth(name, diameter, phase, seed):
    rng = np.random.default_rng(seed)
    scene = render_scene(name, diameter, phase, rng=rng, peak_e=3000.0, supersample=4)
    pose = body_pose(scene.body, scene.R_icrf_cam, scene.observer, scene.ephemeris)
    fit = correlate_centre(scene.image, scene.camera, _prior(pose, scene.camera, rng),
                           psf_sigma_px=scene.psf_sigma_px, noise=_noise(scene.camera))
    err = fit.xy_px - scene.xy_true_px
    assert err @ np.linalg.solve(fit.cov_xy_px2, err) < GATE_2D, (err, np.sqrt(np.diag(fit.cov_xy_px2)))
    # the light of a phased body is far from its centre: the photocentre would be off by pixels
    if phase >= 60:
        assert np.hypot(*(scene.xy_true_px - _photocentre(scene))) > 10 * np.sqrt(np.trace(fit.cov_xy_px2))


def _photocentre(scene):
    img = np.clip(scene.image - scene.camera.bias_adu, 0, None)
    c = np.rint(scene.xy_true_px).astype(int)
    half = 40
    box = img[c[1] - half:c[1] + half + 1, c[0] - half:c[0] + half + 1]
    yy, xx = np.mgrid[-half:half + 1, -half:half + 1]
    return c + np.array([(box * xx).sum(), (box * yy).sum()]) / box.sum()


def test_the_terminator_is_never_taken_for_the_limb():
    """A 120 px Moon at 110 deg phase: the terminator crosses the disk near the lit limb. Every limb
    point the fit keeps lies on the true outline (within 0.3 px), none on the terminator, and the
    lines the model shows reaching the dark side are the ones left out."""
    rng = np.random.default_rng(6)
    scene = render_scene("moon", 120, 110, rng=rng, supersample=12)
    pose = body_pose(scene.body, scene.R_icrf_cam, scene.observer, scene.ephemeris)
    prior = _prior(pose, scene.camera, rng)
    scan = scan_lines(scene.camera, prior, psf_sigma_px=scene.psf_sigma_px)
    usable = usable_lines(scan)
    assert 0 < usable.sum() < len(usable)  # some lines reach the terminator and are dropped
    fit = fit_limb_ellipsoid(scene.image, scene.camera, prior, psf_sigma_px=scene.psf_sigma_px,
                             noise=_noise(scene.camera))
    pts = fit.points_xy[fit.inliers]
    cone = horizon_cone(pose)
    m = np.concatenate([ideal_xy(scene.camera, pts), np.full((len(pts), 1), scene.camera.focal_length_px)], 1)
    dist = np.abs(np.einsum("ni,ij,nj->n", m, cone, m)) / (2.0 * np.hypot(*(m @ cone.T)[:, :2].T))
    assert len(pts) >= LimbOptions().min_lines and dist.max() < 0.3
    # and every kept point is on the Sun's side of the disk
    centre = scene.xy_true_px
    sun_img = scene.camera.project(pose.r_cam_km + 1e-3 * np.linalg.norm(pose.r_cam_km) * pose.sun_cam) - centre
    assert np.all((pts - centre) @ sun_img > 0)


def test_choose_method_by_size_and_phase_not_by_name():
    assert choose_method(2.0, 0.3) == "point"
    assert choose_method(10.0, 0.3) == "correlation"
    assert choose_method(60.0, math.radians(30)) == "limb"
    # a 24 px thin crescent: too few lines on its lit limb
    assert choose_method(24.0, math.radians(120)) == "correlation"
    assert choose_method(24.0, math.radians(120), options=CentreOptions(method="limb")) == "limb"
    assert choose_method(300.0, 0.1, ellipsoid=False) == "correlation"
    # the same apparent size and phase give the same method for Mars and Phobos
    rng = np.random.default_rng(7)
    picks = set()
    for name in ("mars", "phobos"):
        scene = render_scene(name, 40, 30, rng=rng, noise=False, supersample=4)
        pose = body_pose(scene.body, scene.R_icrf_cam, scene.observer, scene.ephemeris)
        picks.add(choose_method(apparent_diameter_px(scene.camera, pose), pose.phase_rad))
    assert picks == {"limb"}


def test_bad_options_name_what_is_accepted():
    with pytest.raises(InputError, match="centre method must be one of auto, point, correlation, limb"):
        CentreOptions(method="hough")
    with pytest.raises(InputError, match="line_spacing_px"):
        LimbOptions(line_spacing_px=1.0)


def test_a_body_too_small_for_a_limb_fit_is_refused():
    rng = np.random.default_rng(8)
    scene = render_scene("phobos", 8, 30, rng=rng, supersample=8)
    pose = body_pose(scene.body, scene.R_icrf_cam, scene.observer, scene.ephemeris)
    with pytest.raises(NoSolutionError, match="lines"):
        fit_limb_ellipsoid(scene.image, scene.camera, pose, psf_sigma_px=scene.psf_sigma_px, noise=_noise(scene.camera),
                           options=LimbOptions(correlate_below_px=0.0))


@pytest.mark.parametrize("name, diameter, phase, method", [("mars", 70, 50, "limb"), ("phobos", 12, 40, "correlation")])
def test_measured_records_hold_the_true_direction_and_vector(name, diameter, phase, method):
    """End to end on one frame: the records' RA/Dec (and the limb's probe -> body vector) inside
    3 sigma of the renderer's truth, through the same model the filters use."""
    from opnav.image.centres import measure_body_centre
    from opnav.measurements import ProbeMeasurementModel

    rng = np.random.default_rng(9)
    # the renderer's ray grid moves a 12 px body's light by ~0.02 px at 24 rays per pixel, ~0.005 at 48
    scene = render_scene(name, diameter, phase, rng=rng, peak_e=3000.0, supersample=4)
    got = measure_body_centre(scene.image, scene.camera, scene.body, R_icrf_cam=scene.R_icrf_cam,
                              cov_att_rad2=np.zeros((3, 3)), observer=scene.observer, ephemeris=scene.ephemeris,
                              psf_sigma_px=scene.psf_sigma_px, noise=_noise(scene.camera), t_tdb_s=0.0)
    assert got.method == method
    model = ProbeMeasurementModel("ssb", ephemeris=scene.ephemeris)
    x = np.concatenate([scene.observer.r_ssb_km, scene.observer.v_ssb_km_s])
    for rec in got.records:
        resid = model.residual(rec, model.predict(rec, x))
        assert resid @ np.linalg.solve(rec.covariance, resid) < chi2.ppf(0.9973, rec.size), (rec.kind, resid)
    assert {r.kind for r in got.records} == ({"radec", "target_vector"} if method == "limb" else {"radec"})


@pytest.mark.parametrize("name, diameter, phase", [("mars", 40, 60), ("moon", 40, 100), ("phobos", 40, 30),
                                                   ("moon", 10, 120), ("phobos", 6, 60)])
def test_the_model_image_is_the_renderer_s_pixel_integral(name, diameter, phase):
    """A model image at the true pose and a noise-free rendered frame are the same integral (the
    pixels' own rays at the renderer's 4 per axis where the shading is smooth, the same PSF): one gain
    apart to 1e-4 of the peak (5e-6 measured), where a
    model whose edge pixels had 8 x 8 rays instead of 32 x 32 is 6e-3 to 1e-2 off. The small bodies
    (under 12 px: every pixel on the edge grid) check that the model, which integrates only the
    pixels near the outline, left out none of the frame's light."""
    from opnav.image.ellipsoid import outline_box, render_ellipsoid

    scene = render_scene(name, diameter, phase, rng=None, noise=False)
    pose = body_pose(scene.body, scene.R_icrf_cam, scene.observer, scene.ephemeris)
    box = outline_box(scene.camera, pose, 10.0)
    model = render_ellipsoid(scene.camera, pose, box, psf_sigma_px=scene.psf_sigma_px, supersample=4)
    x0, y0, w, h = box
    light = scene.signal_e[y0:y0 + h, x0:x0 + w]
    gain = float(np.sum(light * model) / np.sum(model * model))
    assert model.max() > 0.05
    assert np.max(np.abs(light - gain * model)) < 1e-4 * light.max()


@pytest.mark.parametrize("move", [(0.05, 0.0, 0.0), (0.0, 0.05, 0.0), (0.0, 0.0, 1e-3)])
def test_line_shifts_follow_their_response_not_the_outline_crossings(move):
    """Noise-free Phobos, 80 px at 60 deg phase, scanned at a pose off the truth by 0.05 px or 0.1 %
    in range (0.04 px on its radius): every usable line's fitted shift is its response to that move
    (within 0.01 px and 15 % of the shift), while the outline's crossings miss a grazing line's shift
    by more than 0.02 px, 40 % of the move (a fit to the crossings carried such shares of the pose's
    error into the next pass)."""
    from opnav.image.limb import limb_offsets
    from opnav.render.detector import DetectorOptions, read_out

    scene = render_scene("phobos", 80, 60, rng=None, noise=False)
    cam = scene.camera
    truth = body_pose(scene.body, scene.R_icrf_cam, scene.observer, scene.ephemeris)
    image = np.asarray(read_out(scene.signal_e, cam, options=DetectorOptions(noise_free=True, hot_pixel_fraction=0.0)), float)
    f = cam.focal_length_px
    dx, dy, dr = move
    pose = truth.at(Rotation.from_rotvec([-dy / f, dx / f, 0.0]).apply(truth.r_cam_km) * (1.0 + dr))
    scan = scan_lines(cam, pose, psf_sigma_px=scene.psf_sigma_px)
    use = usable_lines(scan)
    off = limb_offsets(image, scan, _noise(cam))
    predicted = off.response[use] @ (truth.r_cam_km - pose.r_cam_km)
    measured = off.delta_px[use]
    assert np.max(np.abs(measured - predicted) - 0.15 * np.abs(measured)) < 0.01, np.c_[measured, predicted]
    crossing = (line_crossings(horizon_cone(truth), f, scan.ideal_start, scan.ideal_dir) / scan.ideal_per_px
                - scan.a_pred_px)[use]
    grazing = scan.incidence[use] < 0.3
    assert grazing.any() and np.max(np.abs(crossing[grazing] - measured[grazing])) > 0.02


@pytest.mark.parametrize("offset, lit_on_frame", [((-100.0, 0.0), True), ((100.0, 0.0), False)])
def test_a_body_larger_than_the_field_is_fitted_on_its_limb_inside_or_refused(offset, lit_on_frame):
    """Mars 330 px across on a 256 px detector: the lines whose windows leave the detector are not
    read (they once reached a tile of negative size, or a line of clipped pixels); with part of the
    lit limb on the frame the fit lands inside 3 sigma of the truth, with all of it off the frame it
    is refused with its reason."""
    from opnav.camera import Camera

    base = camera_1mp()
    cam = Camera(width_px=256, height_px=256, focal_length_mm=base.focal_length_mm, pixel_pitch_um=base.pixel_pitch_um,
                 exposure_s=1.0, read_noise_e=10.0, full_well_e=200000.0, bit_depth=20)
    rng = np.random.default_rng(12)
    scene = render_scene("mars", 330, 30, rng=rng, camera=cam, offset_px=offset, clock_deg=0.0)
    pose = body_pose(scene.body, scene.R_icrf_cam, scene.observer, scene.ephemeris)
    run = lambda: fit_limb_ellipsoid(scene.image, scene.camera, _prior(pose, scene.camera, rng),  # noqa: E731
                                     psf_sigma_px=scene.psf_sigma_px, noise=_noise(scene.camera))
    if not lit_on_frame:
        with pytest.raises(NoSolutionError, match="off the frame"):
            run()
        return
    fit = run()
    err = fit.xy_px - scene.xy_true_px
    assert err @ np.linalg.solve(fit.cov_xy_px2, err) < GATE_2D, (err, np.sqrt(np.diag(fit.cov_xy_px2)))
