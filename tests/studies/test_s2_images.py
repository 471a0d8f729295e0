"""S2 from pixels (opnav/studies/s2_images.py): angles from measured directions, a few frames end to end."""

import dataclasses

import numpy as np
import pytest
from scipy.stats import chi2

from opnav.constants import ARCSEC_RAD
from opnav.errors import InputError
from opnav.frames import radec_to_unit, unit_to_radec
from opnav.records import Measurement
from opnav.studies import s2
from opnav.studies.s2_images import angle_errors, angle_pair, measure_arc, twin_records, wrong_body_count


def _stars(u, count, rng):
    """``count`` unit vectors 1-5 deg from ``u`` at random position angles."""
    east = np.cross([0.0, 0.0, 1.0], u)
    east /= np.linalg.norm(east)
    north = np.cross(u, east)
    out = []
    for _ in range(count):
        sep, pa = np.radians(rng.uniform(1.0, 5.0)), rng.uniform(0.0, 2 * np.pi)
        out.append(np.cos(sep) * u + np.sin(sep) * (np.cos(pa) * east + np.sin(pa) * north))
    return np.array(out)


def test_angle_pair_values_and_variances_match_monte_carlo():
    # a direction with an anisotropic covariance: the two angles' values are the true ones, and the
    # reported variances and the pair's correlation are those of the angles of directions drawn from it
    rng = np.random.default_rng(5)
    ra, dec = 1.1, -0.4
    u = radec_to_unit(ra, dec)
    sigma = np.array([3.0, 1.0]) * ARCSEC_RAD  # east (RA cos dec), north
    turn = np.array([[np.cos(0.6), -np.sin(0.6)], [np.sin(0.6), np.cos(0.6)]])
    cov_tangent = turn @ np.diag(sigma**2) @ turn.T
    scale = np.diag([1.0 / np.cos(dec), 1.0])
    record = Measurement(0.0, "radec", [ra, dec], scale @ cov_tangent @ scale, target="mars")
    stars = _stars(u, 12, rng)
    pair, rho = angle_pair(record, stars, stars, np.arange(12))
    assert len(pair) == 2 and rho < 0.1
    picked = [int(p.star_id) for p in pair]
    for p, i in zip(pair, picked):
        assert p.kind == "starlight_angle" and p.target == "mars"
        assert p.value[0] == pytest.approx(np.arccos(stars[i] @ u), abs=1e-12)
    draws = rng.multivariate_normal([0.0, 0.0], cov_tangent, size=4000)
    east = np.array([-u[1], u[0], 0.0]) / np.hypot(u[0], u[1])
    north = np.cross(u, east)
    moved = u + draws[:, :1] * east + draws[:, 1:] * north
    moved /= np.linalg.norm(moved, axis=1)[:, None]
    angles = np.arccos(moved @ stars[picked].T)
    n = len(draws)
    for k, p in enumerate(pair):
        ratio = np.var(angles[:, k]) / p.covariance[0, 0]
        assert chi2.ppf(0.001, n - 1) / (n - 1) < ratio < chi2.ppf(0.999, n - 1) / (n - 1)
    assert abs(np.corrcoef(angles.T)[0, 1]) < 0.1


def test_angle_pair_needs_two_stars():
    u = radec_to_unit(0.3, 0.2)
    record = Measurement(0.0, "radec", [0.3, 0.2], np.eye(2) * 1e-12, target="phobos")
    with pytest.raises(InputError, match="fewer than two stars"):
        angle_pair(record, _stars(u, 1, np.random.default_rng(1)), _stars(u, 1, np.random.default_rng(1)), [1])


def test_a_centre_sensor_needs_a_mounting_and_an_earlier_reference():
    from scipy.spatial.transform import Rotation

    from opnav.camera import Camera
    from opnav.sim.pointing import PointingLaw
    from opnav.sim.sensors import Loop, Sensor
    from opnav.sim.stages import Centre

    camera = Camera.from_fov(10.0, 256, 256)
    with pytest.raises(InputError, match="limb or centre sensor .* mountings"):
        Sensor(camera, Centre("mars", 0, 1.0), pointing=PointingLaw(law="target", target="mars"))
    with pytest.raises(InputError, match="sensor 0: its limb or centre stage's reference"):
        Loop((Sensor(camera, Centre("mars", 0, 1.0), mounting=Rotation.identity()),), 0)
    with pytest.raises(InputError, match="psf_sigma_px"):
        Centre("mars", 0, 0.0)


def test_image_step_must_be_a_multiple_of_the_step():
    with pytest.raises(InputError, match="image_step_s must be a whole multiple of step_s"):
        s2.Settings(image_step_s=900.0)
    with pytest.raises(InputError, match="tracker_boresight_body"):
        s2.Settings(tracker_boresight_body=(0.0, 0.0, 0.0))


@pytest.fixture(scope="module")
def few_frames(tmp_path_factory):
    from opnav.studies.trajectories import mars_capture_trajectory

    # 6 hours of phase 1 and phase 2 every 6 hours: 10 epochs, 32 frames
    settings = dataclasses.replace(s2.Settings(observability=False), arc_days=0.25, image_step_s=21600.0)
    trajectory = mars_capture_trajectory(step_s=settings.step_s)
    return settings, trajectory, measure_arc(settings, 3, trajectory, tmp_path_factory.mktemp("s2"))


def test_few_frames_measure_every_body_of_each_phase_against_the_truth(few_frames):
    settings, trajectory, measured = few_frames
    targets = {d.target for d in measured.directions}
    assert targets == {"mars", "phobos", "deimos", "sun"}
    soi = trajectory.t_soi_tdb_s
    assert all(d.t_tdb_s <= soi for d in measured.directions if d.target == "deimos")  # the crossing closes phase 1
    assert all(d.t_tdb_s > soi for d in measured.directions if d.target == "sun")
    # two angles per direction, each body's errors consistent with the variances the records report
    assert len(measured.angles) == 2 * len(measured.directions)
    errors = angle_errors(measured.angles, trajectory)
    for name, figures in errors.items():
        n = figures["count"]
        assert figures["chi2_mean"] < chi2.ppf(0.999, n) / n, (name, figures)
    # the moons' angles come from their frames' own stars: sub-arcsecond; Mars' through the tracker
    assert errors["phobos"]["rms_arcsec"] < 1.0 and errors["deimos"]["rms_arcsec"] < 1.0
    wrong = wrong_body_count(measured.directions, trajectory)
    assert sum(entry["wrong_body"] for entry in wrong.values()) == 0


def test_twin_keeps_epochs_and_stars_at_the_achieved_noise(few_frames):
    _, trajectory, measured = few_frames
    sigma = {"mars": 2.0 * ARCSEC_RAD, "phobos": 0.5 * ARCSEC_RAD, "deimos": 0.5 * ARCSEC_RAD, "sun": 30 * ARCSEC_RAD}
    twin = twin_records(measured.angles, trajectory, sigma, np.random.default_rng(0))
    assert [(a.t_tdb_s, a.target, a.star_id) for a in twin] == [(a.t_tdb_s, a.target, a.star_id)
                                                                 for a in measured.angles]
    figures = angle_errors(twin, trajectory)
    for name, row in figures.items():
        assert row["median_sigma_arcsec"] == pytest.approx(sigma[name] / ARCSEC_RAD)
        n = row["count"]
        assert chi2.ppf(0.001, n) / n < row["chi2_mean"] < chi2.ppf(0.999, n) / n
