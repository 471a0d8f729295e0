"""Propagation: orbit closure, STM vs finite differences for every model, S1 Mars ranges, API contract."""

from __future__ import annotations

import numpy as np
import pytest

from opnav.constants import GM_KM3_S2
from opnav.dynamics import (
    approach_model,
    capture_model_1,
    capture_model_2,
    change_center,
    cruise_model,
    geo_model,
    propagate,
    states_at,
    two_body_model,
)
from opnav.ephemeris import default_ephemeris
from opnav.epochs import parse_epoch
from opnav.errors import EphemerisError, InputError

T_S1 = parse_epoch("2013-12-12T12:00:00", "tt")
X_S1 = np.array([24306991.2893, 132523850.2219, 58427884.5328, -32.455391, 3.658828, 3.362343])
T_S3 = parse_epoch("2001-01-01T00:00:00", "utc")
T_CAPTURE = parse_epoch("2014-09-01T00:00:00", "tdb")
T_S4 = parse_epoch("2021-01-15T05:46:07", "utc")


def _geo_state() -> np.ndarray:
    # S3: circular equatorial, period 86164.09 s, RAAN + true anomaly = 260.702295 deg.
    angle = np.radians(260.0 + 0.702295)
    radius = (GM_KM3_S2["earth"] * (86164.09 / (2 * np.pi)) ** 2) ** (1 / 3)
    speed = np.sqrt(GM_KM3_S2["earth"] / radius)
    return np.r_[radius * np.array([np.cos(angle), np.sin(angle), 0.0]),
                 speed * np.array([-np.sin(angle), np.cos(angle), 0.0])]


def _near_mars_heliocentric(t: float, offset_km, dv_km_s) -> np.ndarray:
    r, v = default_ephemeris().state("mars", t, center="sun")
    return np.r_[r + offset_km, v + dv_km_s]


@pytest.mark.parametrize("eccentricity", [0.0, 0.7])
def test_two_body_orbit_closes_after_ten_revolutions(eccentricity):
    gm = GM_KM3_S2["earth"]
    periapsis = 7000.0
    a = periapsis / (1.0 - eccentricity)
    period = 2 * np.pi * np.sqrt(a**3 / gm)
    speed = np.sqrt(gm * (1 + eccentricity) / periapsis)
    incl = np.radians(28.5)
    x0 = np.array([periapsis, 0.0, 0.0, 0.0, speed * np.cos(incl), speed * np.sin(incl)])
    trajectory = propagate(two_body_model("earth"), T_S3, x0, T_S3 + 10 * period)
    assert np.linalg.norm(trajectory.states[-1, :3] - x0[:3]) < 1e-3  # km
    assert np.linalg.norm(trajectory.states[-1, 3:] - x0[3:]) < 1e-6  # km/s


def _stm_cases():
    return [
        ("two-body", lambda: two_body_model("earth"), T_S3, np.array([7000.0, 0, 0, 0, 7.5, 1.0]), 5800.0),
        ("cruise", lambda: cruise_model(srp_area_to_mass_m2_kg=0.02), T_S1, X_S1, 10 * 86_400.0),
        ("capture1", capture_model_1, T_CAPTURE,
         _near_mars_heliocentric(T_CAPTURE, [2e6, 1e6, 0.0], [-1.0, -0.5, 0.2]), 2 * 86_400.0),
        ("capture2", capture_model_2, T_CAPTURE, np.array([3e5, 1e5, -5e4, -2.5, -0.8, 0.3]), 86_400.0),
        ("geo", geo_model, T_S3, _geo_state(), 6 * 3600.0),
        ("approach", approach_model, T_S4,
         _near_mars_heliocentric(T_S4, [3e6, -2e6, 1e6], [-0.8, 0.5, -0.3]), 5 * 86_400.0),
    ]


@pytest.mark.parametrize("name, build, t0, x0, span_s", _stm_cases(), ids=[c[0] for c in _stm_cases()])
def test_stm_matches_central_differences(name, build, t0, x0, span_s):
    model = build()
    # Steps 1e-6 of |r| and |v|: truncation ~ (1e-6 |r| / L)^2 with L the distance to the nearest
    # attractor (>= 1e-2 |r| here). Nominal and the 12 perturbed states go in one batch, so they share
    # one step sequence and the integration error cancels in the differences.
    h = np.r_[np.full(3, 1e-6 * np.linalg.norm(x0[:3])), np.full(3, 1e-6 * np.linalg.norm(x0[3:]))]
    batch = np.vstack([x0, x0 + np.diag(h), x0 - np.diag(h)])
    trajectory = propagate(model, t0, batch, t0 + span_s, stm=True)
    phi = trajectory.stm[-1, 0]
    numeric = ((trajectory.states[-1, 1:7] - trajectory.states[-1, 7:13]) / (2 * h[:, None])).T
    for rows in (slice(0, 3), slice(3, 6)):
        for cols in (slice(0, 3), slice(3, 6)):
            block, numeric_block = phi[rows, cols], numeric[rows, cols]
            assert np.linalg.norm(block - numeric_block) < 1e-6 * np.linalg.norm(block)
    # Velocity-independent forces are Hamiltonian: the flow preserves volume (Liouville).
    assert abs(np.linalg.det(phi) - 1.0) < 1e-8


def test_single_and_batch_propagation_agree():
    model = geo_model()
    x0 = _geo_state()
    batch = np.vstack([x0, x0 + [10.0, 0, 0, 0, 0.001, 0]])
    epochs = T_S3 + np.array([600.0, 3600.0, 86_400.0])
    together = propagate(model, T_S3, batch, epochs, stm=True)
    alone = propagate(model, T_S3, batch[1], epochs, stm=True)
    assert together.states.shape == (3, 2, 6) and together.stm.shape == (3, 2, 6, 6)
    assert alone.states.shape == (3, 6) and alone.stm.shape == (3, 6, 6)
    np.testing.assert_allclose(together.states[:, 1, :3], alone.states[:, :3], rtol=0, atol=1e-5)
    np.testing.assert_allclose(together.stm[:, 1], alone.stm, rtol=0, atol=1e-7 * np.abs(alone.stm).max())


def test_forward_then_backward_returns_to_start():
    model = cruise_model()
    forward = propagate(model, T_S1, X_S1, T_S1 + 30 * 86_400.0)
    back = propagate(model, T_S1 + 30 * 86_400.0, forward.states[-1], [T_S1 + 15 * 86_400.0, T_S1])
    assert np.linalg.norm(back.states[-1, :3] - X_S1[:3]) < 1e-3  # km over 1.5e8 km
    assert np.linalg.norm(back.states[-1, 3:] - X_S1[3:]) < 1e-9


def test_states_at_takes_dates_on_both_sides_in_any_order_and_changes_origin():
    model = cruise_model()
    epochs = T_S1 + np.array([20.0, -10.0, 0.0, 5.0, -30.0]) * 86_400.0
    out = states_at(model, T_S1, X_S1, epochs, output_center="mars")
    forward = propagate(model, T_S1, X_S1, np.sort(epochs[epochs >= T_S1])).states
    backward = propagate(model, T_S1, X_S1, np.sort(epochs[epochs < T_S1])[::-1]).states
    expected = change_center(np.stack([forward[2], backward[0], forward[0], forward[1], backward[1]]), epochs,
                             "sun", "mars")
    np.testing.assert_array_equal(out, expected)
    mars_centred = change_center(X_S1, T_S1, "sun", "mars")
    np.testing.assert_allclose(states_at(model, T_S1, mars_centred, [T_S1], center="mars"), mars_centred[None],
                               rtol=0, atol=1e-6)


def test_s1_table1_state_reaches_paper_mars_distances():
    epochs = parse_epoch([f"2014-{month:02d}-01T00:00:00" for month in (5, 6, 7, 8, 9)], "tt")
    trajectory = propagate(cruise_model(), T_S1, X_S1, epochs)
    mars_centred = change_center(trajectory.states, epochs, "sun", "mars")
    distance_mkm = np.linalg.norm(mars_centred[:, :3], axis=1) / 1e6
    np.testing.assert_allclose(distance_mkm, [49.0, 33.0, 23.0, 15.0, 7.0], rtol=0, atol=1.5)


def test_t0_only_returns_initial_state_and_inputs_are_not_mutated():
    x0 = X_S1.copy()
    trajectory = propagate(cruise_model(), T_S1, x0, T_S1, stm=True)
    np.testing.assert_array_equal(trajectory.states, x0[None, :])
    np.testing.assert_array_equal(trajectory.stm, np.eye(6)[None])
    epochs = np.array([T_S1, T_S1 + 60.0])
    out = propagate(cruise_model(), T_S1, x0, epochs)
    np.testing.assert_array_equal(out.states[0], X_S1)
    np.testing.assert_array_equal(x0, X_S1)
    np.testing.assert_array_equal(epochs, [T_S1, T_S1 + 60.0])
    assert out.center == "sun"


@pytest.mark.parametrize(
    "state0, epochs, match",
    [
        (np.r_[X_S1[:5], np.nan], T_S1 + 60.0, "NaN"),
        (X_S1[:5], T_S1 + 60.0, "shape"),
        (X_S1, [T_S1 + 60.0, T_S1 - 60.0], "sorted"),
        (X_S1, [T_S1 + 120.0, T_S1 + 60.0], "sorted"),
        (X_S1, np.inf, "NaN or infinity"),
    ],
)
def test_bad_inputs_raise_input_error(state0, epochs, match):
    with pytest.raises(InputError, match=match):
        propagate(cruise_model(), T_S1, state0, epochs)


def test_epoch_outside_ephemeris_raises():
    with pytest.raises(EphemerisError, match="coverage"):
        propagate(cruise_model(), T_S1, X_S1, T_S1 + 200 * 365.25 * 86_400.0)


def test_change_center_round_trip_and_origin():
    t = T_S1 + np.array([0.0, 86_400.0])
    r, v = default_ephemeris().state("mars", t, center="sun")
    mars_states = np.concatenate([r, v], axis=1)
    np.testing.assert_allclose(change_center(mars_states, t, "sun", "mars"), 0.0, atol=1e-6)
    batch = np.stack([mars_states, mars_states + 1.0], axis=1)  # (M, K, 6)
    there = change_center(batch, t, "sun", "earth")
    np.testing.assert_allclose(change_center(there, t, "earth", "sun"), batch, rtol=0, atol=1e-6)
    with pytest.raises(EphemerisError, match="vulcan"):
        change_center(mars_states, t, "sun", "vulcan")


def test_an_epoch_asked_for_twice_gets_the_same_state_twice_either_way():
    """S4 with lead_s = 0 asks for every fusion epoch twice (solve_ivp refuses repeated t_eval)."""
    model = cruise_model()
    days = T_S1 + 86_400.0 * np.array([1.0, 2.0, 2.0, 3.0])
    repeated = propagate(model, T_S1, X_S1, days, stm=True)
    once = propagate(model, T_S1, X_S1, days[[0, 1, 3]], stm=True)
    np.testing.assert_array_equal(repeated.states[1], repeated.states[2])
    np.testing.assert_allclose(repeated.states[[0, 1, 3]], once.states, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(repeated.stm[1], repeated.stm[2])
    back = propagate(model, T_S1 + 4 * 86_400.0, once.states[-1], days[::-1])
    np.testing.assert_array_equal(back.states[1], back.states[2])
