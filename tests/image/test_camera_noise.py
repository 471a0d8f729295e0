"""A calibrated camera's covariance carried into the moons' RA/Dec records (opnav.image.camera_noise).

Frames are rendered with a distorted true camera and measured by the tracking stage (which knows
the stars its attitude used) with a camera drawn from a calibration covariance around the truth (a camera "inside its covariance"). The
camera's error then moves each moon relative to the frame's stars by far more than its centroid
noise: the records' chi-square against the truth is consistent only with the option on.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from opnav.camera import Camera, CameraCovariance
from opnav.catalog import synthetic_catalog
from opnav.ephemeris import default_ephemeris
from opnav.epochs import parse_epoch
from opnav.image.calibration import corner_radius, corner_scale, parameter_values, with_parameters
from opnav.image.camera_noise import radec_camera_jacobian
from opnav.image.pipeline import PipelineOptions, frame_input
from opnav.image.tracking import TrackingOptions, track_frame
from opnav.light import apparent_direction
from opnav.render import Observer, render_frame, write_frame

NOMINAL = Camera(512, 512, 762.7, 13.0, aperture_mm=150.0, exposure_s=1.0, read_noise_e=8.0, gain_e_per_adu=2.0,
                 full_well_e=1e5)
NAMES = ("f", "cx", "cy", "k1", "p1", "p2")
#: 1-sigma of each parameter as a displacement at the detector corner, px: a calibration of a few frames
CORNER_SIGMA_PX = np.array([0.1, 1.0, 1.0, 0.2, 0.05, 0.05])


def _truth() -> Camera:
    f, rc = NOMINAL.focal_length_px, corner_radius(NOMINAL)
    return NOMINAL.replace(cx_px=NOMINAL.cx_px + 1.5, cy_px=NOMINAL.cy_px - 2.0, k1=3.0 / (f * rc**3),
                           p1=0.4 / (f * rc**2), p2=-0.3 / (f * rc**2))


def _frame(rng, ephemeris, camera: Camera, tmp_path, k: int):
    """A frame of Phobos 15 million km from Mars (phase 50 degrees) rendered with ``camera``; stars around it."""
    t = float(parse_epoch("2014-07-15T00:00:00", "utc")) + rng.uniform(0, 86400.0)
    r_mars, v_mars = ephemeris.state("mars", t)
    to_sun = ephemeris.position("sun", t) - r_mars
    to_sun /= np.linalg.norm(to_sun)
    side = np.cross(to_sun, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    r_obs = r_mars + 15e6 * (math.cos(math.radians(50.0)) * to_sun + math.sin(math.radians(50.0)) * side)
    observer = Observer(t, r_obs, v_mars)
    z = apparent_direction(lambda tt: ephemeris.position("phobos", tt), t, r_obs, v_mars)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    # Phobos off the centre (a third of the half-field), where the distortion's errors are not a turn
    pointing = Rotation.from_matrix(np.column_stack([x, np.cross(z, x), z])) * Rotation.from_rotvec(
        np.r_[rng.uniform(-1.2e-3, 1.2e-3, 2), rng.uniform(-np.pi, np.pi)])
    catalog = synthetic_catalog(150, rng=rng, vmag_range=(6.0, 11.0), centre_icrf=pointing.apply([0.0, 0.0, 1.0]),
                                radius_rad=math.radians(0.6))
    result = render_frame(camera, pointing, observer, catalog=catalog, targets=("phobos",), ephemeris=ephemeris, rng=rng)
    path, _ = write_frame(tmp_path / f"frame_{k}.fits", result.image, result.header, result.truth)
    return path, catalog, result.truth.target("phobos")


def test_radec_jacobian_matches_the_tangent_plane_one_rotated():
    """d(RA, Dec) from the tangent-plane Jacobian: a small step of each parameter moves (RA, Dec) as predicted."""
    from opnav.image.attitude import wahba_rotation

    camera = _truth()
    rng = np.random.default_rng(3)
    stars = rng.uniform([0, 0], [511, 511], (12, 2))
    target = np.array([380.0, 140.0])
    R = Rotation.from_rotvec([0.3, -1.1, 0.4])
    jac = radec_camera_jacobian(camera, NAMES, stars, target, R)
    values = parameter_values(camera, NAMES)

    def radec(vals):
        moved = with_parameters(camera, NAMES, vals)
        turn = wahba_rotation(moved.unproject(stars), camera.unproject(stars), np.ones(len(stars)))
        u = R.apply(turn.apply(moved.unproject(target)))
        return np.array([math.atan2(u[1], u[0]), math.asin(u[2])])

    steps = 0.05 / corner_scale(camera, NAMES)  # 0.05 px at the corner: linear to well below the tolerance
    for j, h in enumerate(steps):
        up, down = values.copy(), values.copy()
        up[j] += h
        down[j] -= h
        numeric = (radec(up) - radec(down)) / (2 * h)
        np.testing.assert_allclose(jac[:, j], numeric, rtol=1e-3, atol=1e-6 * np.abs(jac[:, j]).max())


def test_consider_keeps_the_jacobian_and_the_covariance_white_adds_its_term():
    """camera_error = "consider": each radec record keeps d(RA, Dec)/d(parameters) relative to the stars (the
    record's pixel moved by the crop's offset) and its covariance; "white" adds J C J^T instead. A record of
    another kind passes unchanged; an unknown mode is refused by name."""
    from opnav.errors import InputError
    from opnav.image.camera_noise import with_camera_covariance
    from opnav.records import CAMERA_JACOBIAN, CAMERA_PARAMETERS, Measurement, camera_jacobian

    camera = _truth()
    rng = np.random.default_rng(8)
    stars = rng.uniform([0, 0], [511, 511], (5, 2))
    R = Rotation.from_rotvec([0.2, 0.9, -0.3])
    calibration = CameraCovariance(NAMES, np.diag((CORNER_SIGMA_PX / corner_scale(camera, NAMES)) ** 2), {})
    cov = np.diag([0.03, 0.04]) ** 2 * (math.pi / 648_000.0) ** 2
    records = [Measurement(0.0, "radec", [1.0, 0.2], cov, target="phobos", extra={"xy_px": [30.0, 20.0]}),
               Measurement(0.0, "position", [1.0, 2.0, 3.0], np.eye(3))]
    offset = (250.0, 180.0)  # the crop's origin in the frame
    jac = radec_camera_jacobian(camera, NAMES, stars, np.array([280.0, 200.0]), R)
    kept, other = with_camera_covariance(records, camera=camera, calibration=calibration, star_xy=stars, R_icrf_cam=R,
                                         xy_offset_px=offset, camera_error="consider")
    assert other is records[1] and CAMERA_JACOBIAN not in other.extra
    np.testing.assert_array_equal(kept.covariance, cov)
    assert camera_jacobian(kept)[0] == NAMES == kept.extra[CAMERA_PARAMETERS]
    np.testing.assert_allclose(camera_jacobian(kept)[1], jac, rtol=1e-12)
    white, _ = with_camera_covariance(records, camera=camera, calibration=calibration, star_xy=stars, R_icrf_cam=R,
                                      xy_offset_px=offset)
    np.testing.assert_allclose(white.covariance, cov + jac @ calibration.covariance @ jac.T, rtol=1e-12)
    assert CAMERA_JACOBIAN not in white.extra
    with pytest.raises(InputError, match=r"^camera_error must be one of white, consider, got 'bias'$"):
        with_camera_covariance(records, camera=camera, calibration=calibration, star_xy=stars, R_icrf_cam=R,
                               camera_error="bias")
    with pytest.raises(InputError, match=r"^camera_error must be one of white, consider"):
        TrackingOptions(camera_error="bias")


@pytest.mark.slow
def test_records_chi_square_is_consistent_only_with_the_camera_covariance(tmp_path):
    """The tracking stage (which knows the stars its attitude used) on frames of the true camera measured with
    cameras drawn from the calibration's covariance: records with and without ``camera_covariance``."""
    ephemeris = default_ephemeris()
    rng = np.random.default_rng(39)
    truth = _truth()
    sigma = CORNER_SIGMA_PX / corner_scale(truth, NAMES)
    calibration = CameraCovariance(NAMES, np.diag(sigma**2), {})
    options = PipelineOptions(targets=("phobos",))
    z2_without, z2_with, added = [], [], []
    for k in range(16):
        if len(z2_with) == 12:
            break
        path, catalog, target = _frame(rng, ephemeris, truth, tmp_path, k)
        # the camera the stage assumes: drawn from the calibration's covariance around the truth
        assumed = with_parameters(truth, NAMES, parameter_values(truth, NAMES) + rng.normal(0.0, sigma))
        frame = frame_input(path, assumed)  # a-priori attitude: the header's WCS (the true pointing)
        plain, inflated = (track_frame(frame, catalog=catalog, ephemeris=ephemeris, options=options, rng=k,
                                       tracking=TrackingOptions(camera_covariance=c)) for c in (None, calibration))
        assert plain.result is not None and plain.used.sum() >= 10
        if not plain.result.records:  # Phobos behind Mars at this epoch
            continue
        (without,), (with_,) = plain.result.records, inflated.result.records
        assert np.array_equal(without.value, with_.value)  # the option changes covariances only
        err = np.array([math.remainder(without.value[0] - target.ra_rad, 2 * math.pi), without.value[1] - target.dec_rad])
        z2_without.append(err @ np.linalg.solve(without.covariance, err))
        z2_with.append(err @ np.linalg.solve(with_.covariance, err))
        added.append(np.trace(with_.covariance - without.covariance) / np.trace(without.covariance))
    n = len(z2_with)
    assert n == 12
    low, high = chi2.ppf(0.001, 2 * n), chi2.ppf(0.999, 2 * n)
    # the camera's error dominates the centroid noise: the records alone are far too confident
    assert np.median(added) > 3.0
    assert sum(z2_without) > high
    assert low < sum(z2_with) < high


def test_the_option_without_a_calibrated_camera_ends_in_one_line(tmp_path, capsys):
    """S1's camera_covariance and opnav process --camera-covariance need a camera file with [calibration]."""
    from opnav.camera import write_camera_file
    from opnav.cli import main
    from opnav.errors import InputError
    from opnav.studies.s1 import Settings, s1_tracking_options

    bare = tmp_path / "bare.toml"
    write_camera_file(bare, NOMINAL)
    with pytest.raises(InputError, match=r"^camera_covariance = true needs camera_file .* image_stage = 'tracking'$"):
        Settings(camera_covariance=True)
    with pytest.raises(InputError, match=r"^camera_covariance = true needs camera_file"):
        Settings(camera_covariance=True, camera_file=str(bare), image_stage="full-frame")
    with pytest.raises(InputError, match=r"^camera_covariance = true: camera_file '.*bare.toml' has no \[calibration\]"):
        s1_tracking_options(Settings(camera_covariance=True, camera_file=str(bare)))
    calibrated = tmp_path / "calibrated.toml"
    write_camera_file(calibrated, NOMINAL, CameraCovariance(("f",), np.array([[0.01]]), {}))
    assert s1_tracking_options(Settings(camera_covariance=True, camera_file=str(calibrated))).camera_covariance.names == ("f",)
    assert s1_tracking_options(Settings()) is None
    (tmp_path / "frames").mkdir()
    assert main(["process", str(tmp_path / "frames"), "--targets", "phobos", "--camera", str(bare),
                 "--camera-covariance", "--out", str(tmp_path / "m.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("--camera-covariance needs --camera with a [calibration] table (docs/formats/camera.md; "
                        f"opnav calibrate writes one): {bare} has none") and "\n" not in err
