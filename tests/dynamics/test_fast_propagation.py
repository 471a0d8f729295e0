"""The compiled fixed-step propagator against the numpy force models and DOP853."""

import numpy as np
import pytest

from opnav.constants import GM_KM3_S2
from opnav.dynamics import (
    CentralGravity,
    ForceModel,
    approach_model,
    capture_model_1,
    capture_model_2,
    cruise_model,
    geo_model,
    propagate,
)
from opnav.dynamics.fast import AT_A_CENTRE, OUTSIDE_TABLES, FastPropagator, propagate_states
from opnav.epochs import parse_epoch
from opnav.errors import InputError
from opnav.studies.s3 import geo_state

S1_STATE0 = np.array([24_306_991.2893, 132_523_850.2219, 58_427_884.5328, -32.455391, 3.658828, 3.362343])
T_S1_EPOCH = parse_epoch("2013-12-12T12:00:00", scale="tt")
T_JUL = parse_epoch("2014-07-01T00:00:00", scale="tdb")
T_S3 = parse_epoch("2001-01-01T00:00:00", scale="utc")


def s1_july_state() -> np.ndarray:
    return propagate(cruise_model(), T_S1_EPOCH, S1_STATE0, [T_JUL]).states[0]


def chained(fast: FastPropagator, t0: float, x0: np.ndarray, step_s: float, steps: int):
    x, total = x0.copy(), np.eye(6)
    for i in range(steps):
        x, phi = fast.step(t0 + i * step_s, x, t0 + (i + 1) * step_s)
        total = phi @ total
    return x, total


@pytest.mark.parametrize("name, build, center_state", [
    ("cruise", lambda: cruise_model(srp_area_to_mass_m2_kg=0.01, shadow_bodies=("earth", "mars")), "s1"),
    ("capture1", capture_model_1, "s1"),
    ("approach", approach_model, "s1"),
    ("geo", lambda: geo_model(epoch_tdb_s=T_S3), "geo"),
    ("capture2", capture_model_2, "mars"),
])
def test_compiled_right_hand_side_equals_the_force_model(name, build, center_state):
    model = build()
    rng = np.random.default_rng(11)
    t = T_S3 if center_state == "geo" else T_JUL
    base = {"s1": s1_july_state()[:3], "geo": geo_state()[:3], "mars": np.array([5000.0, 3000.0, 1000.0])}[center_state]
    r = base + rng.normal(scale=0.01 * np.linalg.norm(base), size=(6, 3))
    acc, grad = FastPropagator(model).acceleration(t, r)
    np.testing.assert_allclose(acc, model.acceleration(t, r, np.zeros_like(r)), rtol=1e-9, atol=1e-22)
    np.testing.assert_allclose(grad, model.partials(t, r, np.zeros_like(r))[0], rtol=1e-8,
                               atol=1e-12 * np.abs(grad).max())


def test_srp_shadow_matches_in_penumbra_and_umbra():
    # states behind the Earth (GEO in eclipse season geometry): the compiled shadow factor equals the numpy one
    model = geo_model(epoch_tdb_s=T_S3)
    from opnav.ephemeris import default_ephemeris

    r_sun = default_ephemeris().position("sun", T_S3, center="earth")
    anti = -r_sun / np.linalg.norm(r_sun)
    side = np.cross(anti, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    offsets = np.linspace(0.0, 7500.0, 12)  # from the axis of the shadow cone out past the penumbra
    r = 42_164.0 * anti + offsets[:, None] * side
    acc, _ = FastPropagator(model).acceleration(T_S3, r)
    np.testing.assert_allclose(acc, model.acceleration(T_S3, r, np.zeros_like(r)), rtol=1e-9, atol=1e-22)


def test_s1_thirty_days_against_dop853():
    x0 = s1_july_state()
    model = cruise_model()
    x, stm = chained(FastPropagator(model), T_JUL, x0, 60.0, 43_200)
    ref = propagate(model, T_JUL, x0, [T_JUL + 43_200 * 60.0], stm=True, rtol=1e-12)
    assert np.linalg.norm(x[:3] - ref.states[-1, :3]) < 1e-3  # < 1 m
    assert np.max(np.abs(stm - ref.stm[-1])) < 1e-6 * np.max(np.abs(ref.stm[-1]))
    big = np.abs(ref.stm[-1]) > 1e-3 * np.abs(ref.stm[-1]).max()
    assert np.max(np.abs(stm - ref.stm[-1])[big] / np.abs(ref.stm[-1])[big]) < 1e-6


def test_s3_geo_day_with_geopotential_sun_moon_srp_against_dop853():
    model = geo_model(epoch_tdb_s=T_S3)
    x, stm = chained(FastPropagator(model), T_S3, geo_state(), 10.0, 8640)
    ref = propagate(model, T_S3, geo_state(), [T_S3 + 86_400.0], stm=True, rtol=1e-12)
    assert np.linalg.norm(x[:3] - ref.states[-1, :3]) < 1e-3
    assert np.max(np.abs(stm - ref.stm[-1])) < 1e-6 * np.max(np.abs(ref.stm[-1]))


def test_close_mars_periapsis_is_cut_into_substeps():
    # 4000 km from Mars' centre the dynamical time is ~20 min: one 600-s step must be subdivided
    model = capture_model_2()
    r = 4000.0
    v = np.sqrt(GM_KM3_S2["mars"] / r)
    x0 = np.array([r, 0.0, 0.0, 0.0, v, 0.0])
    x, _ = FastPropagator(model).step(T_JUL, x0, T_JUL + 3600.0)
    ref = propagate(model, T_JUL, x0, [T_JUL + 3600.0], rtol=1e-12).states[-1]
    assert np.linalg.norm(x[:3] - ref[:3]) < 1e-4


def test_batch_equals_single_and_parallel_equals_serial_and_input_is_kept():
    model = cruise_model()
    fast = FastPropagator(model)
    x0 = s1_july_state()
    rng = np.random.default_rng(3)
    batch = x0 + rng.normal(size=(80, 6)) * np.r_[1e3, 1e3, 1e3, 1e-3, 1e-3, 1e-3]  # above the parallel threshold
    kept = batch.copy()
    X, Phi = fast.step(T_JUL, batch, T_JUL + 600.0)
    np.testing.assert_array_equal(batch, kept)
    for k in (0, 41, 79):
        x, phi = fast.step(T_JUL, batch[k], T_JUL + 600.0)
        np.testing.assert_allclose(X[k], x, rtol=1e-15, atol=0)
        np.testing.assert_allclose(Phi[k], phi, rtol=1e-13, atol=1e-16)


def test_backwards_then_forwards_returns_to_start():
    fast = FastPropagator(cruise_model())
    x0 = s1_july_state()
    back, _ = fast.step(T_JUL, x0, T_JUL - 86_400.0, stm=False)
    again, _ = fast.step(T_JUL - 86_400.0, back, T_JUL, stm=False)
    assert np.linalg.norm(again[:3] - x0[:3]) < 1e-6


def test_trajectory_chains_steps_and_composes_stms():
    fast = FastPropagator(cruise_model())
    x0 = s1_july_state()
    epochs = T_JUL + np.array([3600.0, 7200.0, 10_800.0])
    traj = fast.trajectory(T_JUL, x0, epochs, stm=True)
    x, phi = fast.step(T_JUL, x0, epochs[0])
    x, phi2 = fast.step(epochs[0], x, epochs[1])
    np.testing.assert_allclose(traj.states[1], x, rtol=1e-15)
    np.testing.assert_allclose(traj.stm[1], phi2 @ phi, rtol=1e-12)


def test_bad_inputs_and_unsupported_terms_raise():
    fast = FastPropagator(cruise_model())
    with pytest.raises(InputError, match="NaN"):
        fast.step(T_JUL, np.full(6, np.nan), T_JUL + 60.0)
    with pytest.raises(InputError, match="shape"):
        fast.step(T_JUL, np.zeros(5), T_JUL + 60.0)
    with pytest.raises(InputError, match="finite"):
        fast.step(float("nan"), s1_july_state(), T_JUL)

    class Drag:
        def acceleration(self, t, r, v):
            return np.zeros_like(r)

        def partials(self, t, r, v):
            return np.zeros((len(r), 3, 3)), np.zeros((len(r), 3, 3))

    with pytest.raises(InputError, match="no compiled form"):
        FastPropagator(ForceModel("sun", (CentralGravity(GM_KM3_S2["sun"]), Drag()), "with drag"))
    with pytest.raises(InputError, match="step_fraction"):
        FastPropagator(cruise_model(), step_fraction=0.0)


SETUPS = {  # name -> (force model, start epoch, state, step): every term the compiled form has
    "cruise+srp+shadows": (lambda: cruise_model(srp_area_to_mass_m2_kg=0.01, shadow_bodies=("earth", "mars")), T_JUL,
                           lambda: s1_july_state(), 600.0),
    "geo": (lambda: geo_model(epoch_tdb_s=T_S3), T_S3, geo_state, 10.0),
    "mars periapsis (sub-steps)": (capture_model_2, T_JUL,
                                   lambda: np.array([4000.0, 0.0, 0.0, 0.0, np.sqrt(GM_KM3_S2["mars"] / 4000.0), 0.0]),
                                   3600.0),
}


@pytest.mark.parametrize("name", sorted(SETUPS))
def test_states_alone_are_the_states_of_the_stm_run_to_the_bit(name):
    """Without STMs every state goes through one vectorised loop (_integrate_points): the same
    operations as the per-state loop that also carries the STM, so the same bits, for a lone state,
    a UKF's 13 sigma points and a batch run in parallel."""
    build, t0, state, step = SETUPS[name]
    fast = FastPropagator(build())
    x0 = state()
    scale = np.r_[np.full(3, 1e-4 * np.linalg.norm(x0[:3])), np.full(3, 1e-4 * np.linalg.norm(x0[3:]))]
    for k in (1, 13, 40):
        X = x0 + np.random.default_rng(k).normal(size=(k, 6)) * scale
        alone, none = fast.step(t0, X, t0 + step, stm=False)
        with_stm, _ = fast.step(t0, X, t0 + step, stm=True)
        assert none is None
        np.testing.assert_array_equal(alone, with_stm)


@pytest.mark.parametrize("name", sorted(SETUPS))
def test_kernel_propagation_is_the_step_to_the_bit(name):
    """propagate_states (what the compiled filter steps call) chooses the steps and does the arithmetic
    of FastPropagator.step, forwards and backwards, with and without STMs."""
    build, t0, state, step = SETUPS[name]
    fast = FastPropagator(build())
    x0 = state()
    X = x0 + np.random.default_rng(4).normal(size=(13, 6)) * np.r_[1.0, 1.0, 1.0, 1e-4, 1e-4, 1e-4]
    for t1 in (t0 + step, t0 - step):
        expected, _ = fast.step(t0, X, t1, stm=False)
        moved = X.copy()
        assert propagate_states(t0, t1, moved, np.empty((1, 6, 6)), False, fast.step_fraction, fast.tables(t0, t1),
                                fast.kernel_force()) == 0
        np.testing.assert_array_equal(moved, expected)
        expected, expected_stm = fast.step(t0, X[0], t1)
        moved, stm = X[:1].copy(), np.eye(6)[None].copy()
        assert propagate_states(t0, t1, moved, stm, True, fast.step_fraction, fast.tables(t0, t1),
                                fast.kernel_force()) == 0
        np.testing.assert_array_equal(moved[0], expected)
        np.testing.assert_array_equal(stm[0], expected_stm)
    unchanged = X.copy()
    assert propagate_states(t0, t0, unchanged, np.empty((1, 6, 6)), False, fast.step_fraction, fast.tables(t0, t0),
                            fast.kernel_force()) == 0
    np.testing.assert_array_equal(unchanged, X)


def test_kernel_propagation_reports_what_the_step_raises_for():
    fast = FastPropagator(cruise_model())
    force = fast.kernel_force()
    at_sun = np.zeros((1, 6))
    assert propagate_states(T_JUL, T_JUL + 60.0, at_sun, np.empty((1, 6, 6)), False, 0.05,
                            fast.tables(T_JUL, T_JUL + 60.0), force) == AT_A_CENTRE
    coef, first, seg, count = fast.tables(T_JUL, T_JUL + 60.0)
    outside = (coef, first + 10**6, seg, count)  # the tables now start long after the epoch
    state = s1_july_state()[None].copy()
    assert propagate_states(T_JUL, T_JUL + 60.0, state, np.empty((1, 6, 6)), False, 0.05, outside,
                            force) == OUTSIDE_TABLES
