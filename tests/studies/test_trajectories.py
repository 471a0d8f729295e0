"""Capture trajectory: Lambert arcs, the capture hyperbola, the S2 arc and body visibility."""

import numpy as np
import pytest

from opnav.constants import DEG_RAD, GM_KM3_S2, RADIUS_KM
from opnav.dynamics import change_center, propagate, two_body_model
from opnav.ephemeris import default_ephemeris
from opnav.errors import InputError
from opnav.studies.trajectories import (
    MARS_POLE_ICRF,
    MARS_SOI_KM,
    body_visibility,
    hyperbola_periapsis_state,
    lambert,
    mars_capture_trajectory,
)

MU_EARTH = 398_600.0


@pytest.fixture(scope="module")
def capture():
    return mars_capture_trajectory(step_s=7200.0, days_before_soi=1.0)


def test_lambert_matches_curtis_example_5_2():
    # Curtis, Orbital Mechanics for Engineering Students, Example 5.2 (mu = 398600 km^3/s^2).
    v1, v2 = lambert(np.array([5000.0, 10000.0, 2100.0]), np.array([-14600.0, 2500.0, 7000.0]), 3600.0,
                     mu_km3_s2=MU_EARTH, pole=np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(v1, [-5.9925, 1.9254, 3.2456], atol=2e-4)
    np.testing.assert_allclose(v2, [-3.3125, -4.1966, -0.38529], atol=2e-4)


@pytest.mark.parametrize("pole_z", [1.0, -1.0])
def test_lambert_arc_reaches_its_target_under_two_body_propagation(pole_z):
    # Both the short (prograde) and long way: the propagated departure state must hit r2 at tof.
    r1 = np.array([1.0e8, 5.0e7, 1.0e6])
    r2 = np.array([-1.5e8, 1.2e8, 4.0e6])
    tof = 250.0 * 86_400.0
    v1, v2 = lambert(r1, r2, tof, mu_km3_s2=GM_KM3_S2["sun"], pole=np.array([0.0, 0.0, pole_z]))
    arrival = propagate(two_body_model("sun"), 0.0, np.r_[r1, v1], tof).states[0]
    np.testing.assert_allclose(arrival[:3], r2, atol=1e-2)
    np.testing.assert_allclose(arrival[3:], v2, atol=1e-8)
    assert np.sign(np.cross(r1, v1)[2]) == pole_z


def test_lambert_rejects_bad_time_of_flight():
    with pytest.raises(InputError, match="tof_s"):
        lambert(np.ones(3), np.array([1.0, -1.0, 0.0]), -5.0, mu_km3_s2=1.0, pole=np.array([0.0, 0.0, 1.0]))


def test_hyperbola_has_requested_periapsis_energy_and_inclination():
    v_inf = np.array([-2.0, 1.5, 0.8])
    r_p = RADIUS_KM["mars"] + 380.0
    mu = GM_KM3_S2["mars"]
    state = hyperbola_periapsis_state(v_inf, periapsis_radius_km=r_p, inclination_rad=75.0 * DEG_RAD, mu_km3_s2=mu)
    r, v = state[:3], state[3:]
    np.testing.assert_allclose(np.linalg.norm(r), r_p, rtol=1e-14)
    assert abs(r @ v) < 1e-9 * np.linalg.norm(r) * np.linalg.norm(v)
    np.testing.assert_allclose(0.5 * v @ v - mu / r_p, 0.5 * v_inf @ v_inf, rtol=1e-12)
    h = np.cross(r, v)
    np.testing.assert_allclose(np.degrees(np.arccos(h @ MARS_POLE_ICRF / np.linalg.norm(h))), 75.0, atol=1e-9)


def test_hyperbola_asymptote_is_the_requested_v_inf():
    # Far from Mars (30 days before periapsis, ~8e6 km) the two-body velocity tends to v_inf; the
    # remaining deflection is ~ mu / (r v_inf^2) ~ 5e-4 rad, i.e. < 2 m/s on 3.3 km/s.
    v_inf = np.array([-2.0, 1.5, 0.8])
    state = hyperbola_periapsis_state(v_inf, periapsis_radius_km=4000.0, inclination_rad=100.0 * DEG_RAD,
                                      mu_km3_s2=GM_KM3_S2["mars"])
    past = propagate(two_body_model("mars"), 0.0, state, -30.0 * 86_400.0).states[0]
    np.testing.assert_allclose(past[3:], v_inf, atol=3e-3)


def test_unreachable_inclination_names_the_parameter():
    # An asymptote along the pole allows only polar orbits.
    with pytest.raises(InputError, match="inclination_rad"):
        hyperbola_periapsis_state(3.0 * MARS_POLE_ICRF + 1e-3 * np.array([1.0, 0.0, 0.0]),
                                  periapsis_radius_km=4000.0, inclination_rad=0.1, mu_km3_s2=GM_KM3_S2["mars"])


def test_capture_arc_switches_models_at_the_sphere_of_influence(capture):
    dist = np.linalg.norm(capture.states_mars[:, :3], axis=1)
    soi = capture.t_tdb_s == capture.t_soi_tdb_s
    np.testing.assert_allclose(dist[soi], MARS_SOI_KM, atol=0.05)
    assert np.all(dist[~capture.inside_soi] > MARS_SOI_KM)
    assert np.all(dist[capture.inside_soi & ~soi] < MARS_SOI_KM)
    assert np.all(np.diff(dist) < 0.0), "the arc must approach Mars monotonically"
    np.testing.assert_allclose(dist[-1], RADIUS_KM["mars"] + 380.0, atol=1e-6)
    assert capture.t_tdb_s[-1] == capture.t_periapsis_tdb_s


def test_capture_arc_frames_are_consistent_and_energy_matches_v_inf(capture):
    shifted = change_center(capture.states_sun, capture.t_tdb_s, "sun", "mars")
    np.testing.assert_allclose(shifted, capture.states_mars, atol=1e-6)
    # Mars-relative energy at the SOI against the Lambert v_inf: the Sun's tide over two days and the
    # patched-conic seed differ by a few percent at most.
    x = capture.state_at(capture.t_soi_tdb_s, "mars")
    energy = 0.5 * x[3:] @ x[3:] - GM_KM3_S2["mars"] / np.linalg.norm(x[:3])
    np.testing.assert_allclose(energy, 0.5 * capture.v_inf_km_s @ capture.v_inf_km_s, rtol=0.05)


def test_capture_arc_rejects_bad_options():
    with pytest.raises(InputError, match="step_s"):
        mars_capture_trajectory(step_s=0.0)
    with pytest.raises(InputError, match="days_before_soi"):
        mars_capture_trajectory(days_before_soi=-1.0)


def test_moon_behind_mars_is_occulted_and_in_front_is_not():
    t = 4.6e8
    r_phobos = default_ephemeris().position("phobos", t, center="mars")
    behind = body_visibility(np.array([t]), -3.0 * r_phobos[None, :], "phobos")
    front = body_visibility(np.array([t]), 3.0 * r_phobos[None, :], "phobos")
    assert behind.occulted[0] and not behind.visible[0]
    assert not front.occulted[0]
    np.testing.assert_allclose(behind.mars_separation_rad, 0.0, atol=1e-12)
    sun = body_visibility(np.array([t]), 3.0 * r_phobos[None, :], "sun")
    assert sun.sun_separation_rad[0] == 0.0 and not sun.eclipsed[0]
