"""Lockstep Monte Carlo equals single runs; the fast filter path equals the DOP853 path."""

import numpy as np
import pytest

from opnav.constants import ARCSEC_RAD
from opnav.dynamics import cruise_model, propagate
from opnav.dynamics.fast import FastPropagator
from opnav.ephemeris.cache import EphemerisCache
from opnav.epochs import parse_epoch
from opnav.filters.base import Estimate
from opnav.filters.ekf import ExtendedKalmanFilter, force_model_propagator
from opnav.filters.lockstep import run_ukf_lockstep
from opnav.filters.noise import WhiteAcceleration
from opnav.filters.run import run_filter
from opnav.filters.ukf import UKFOptions, UnscentedKalmanFilter
from opnav.measurements import ProbeMeasurementModel, simulate_radec
from opnav.records import Measurement

S1_STATE0 = np.array([24_306_991.2893, 132_523_850.2219, 58_427_884.5328, -32.455391, 3.658828, 3.362343])
T_EPOCH = parse_epoch("2013-12-12T12:00:00", scale="tt")
T_JUL = parse_epoch("2014-07-01T00:00:00", scale="tdb")
SIGMA = 0.1 * ARCSEC_RAD
P0 = np.diag([(5000.0 / np.sqrt(3.0)) ** 2] * 3 + [(0.005 / np.sqrt(3.0)) ** 2] * 3)


def s1_arc(steps: int, runs: int, seed: int):
    """Truth, epochs, Deimos RA/Dec values (1, N, K, 2) and K initial estimates drawn from P0."""
    rng = np.random.default_rng(seed)
    epochs = T_JUL + 60.0 * np.arange(1, steps + 1)
    truth = propagate(cruise_model(), T_EPOCH, S1_STATE0, np.concatenate([[T_JUL], epochs])).states
    model = ProbeMeasurementModel("sun")
    values = np.stack([simulate_radec(model, "deimos", epochs, truth[1:], sigma_rad=SIGMA, rng=rng)
                       for _ in range(runs)], axis=1)[None]
    x0 = truth[0] + rng.standard_normal((runs, 6)) * np.sqrt(np.diag(P0))
    return truth, epochs, values, x0


def records_of(epochs, values_one_run):
    return [Measurement(t, "radec", v, SIGMA**2 * np.eye(2), target="deimos") for t, v in zip(epochs, values_one_run)]


def test_fast_ekf_equals_the_dop853_ekf_to_a_percent_of_its_sigma():
    truth, epochs, values, x0 = s1_arc(240, 1, seed=4)
    records = records_of(epochs, values[0, :, 0])
    noise = WhiteAcceleration(1e-22)
    histories = []
    for exact in (True, False):
        ephemeris = EphemerisCache().ephemeris if exact else EphemerisCache()
        model = ProbeMeasurementModel("sun", ephemeris=ephemeris)
        ekf = ExtendedKalmanFilter(Estimate(T_JUL, x0[0], P0), model=model, process_noise=noise,
                                   propagator=force_model_propagator(cruise_model(), exact=exact))
        histories.append(run_filter(ekf, records, progress=False))
    slow, fast = histories
    assert fast.accepted.all() and slow.accepted.all()
    sigma = np.sqrt(np.einsum("nii->ni", slow.covariances))
    assert np.max(np.abs(fast.states - slow.states) / sigma) < 0.01
    np.testing.assert_allclose(fast.covariances, slow.covariances, rtol=1e-6)


def test_ukf_lockstep_equals_single_runs():
    truth, epochs, values, x0 = s1_arc(30, 3, seed=9)
    model = ProbeMeasurementModel("sun", ephemeris=EphemerisCache())
    fast = FastPropagator(cruise_model())

    def transition(t0, X, t1):
        return fast.step(t0, X, t1, stm=False)[0]

    noise = WhiteAcceleration(1e-20)
    options = UKFOptions()
    template = Measurement(T_JUL, "radec", np.zeros(2), SIGMA**2 * np.eye(2), target="deimos")
    hist = run_ukf_lockstep(T_JUL, x0, P0, epochs, [template], values, transition=transition, model=model,
                            process_noise=noise, options=options, progress=False)
    assert hist.accepted.all()
    for k in range(3):
        ukf = UnscentedKalmanFilter(Estimate(T_JUL, x0[k], P0), transition=transition, process_noise=noise,
                                    model=model, options=options)
        single = run_filter(ukf, records_of(epochs, values[0, :, k]), progress=False)
        np.testing.assert_allclose(hist.states[:, k], single.states, rtol=1e-10, atol=1e-9)
        # covariances compared in units of their own sigmas (the velocity block loses digits to the
        # -1e6 central weight of alpha = 1e-3, differently in batched and single arithmetic)
        scale = np.sqrt(np.einsum("nii->ni", single.covariances))
        scaled = (hist.covariances[:, k] - single.covariances) / (scale[:, :, None] * scale[:, None, :])
        assert np.abs(scaled).max() < 1e-6
        np.testing.assert_allclose(hist.nis[:, 0, k], single.nis, rtol=1e-6)


def test_lockstep_refuses_bad_shapes():
    from opnav.errors import InputError

    truth, epochs, values, x0 = s1_arc(3, 2, seed=1)
    template = Measurement(T_JUL, "radec", np.zeros(2), SIGMA**2 * np.eye(2), target="deimos")
    with pytest.raises(InputError, match="values must have shape"):
        run_ukf_lockstep(T_JUL, x0, P0, epochs, [template], values[:, :, :1], transition=None, model=None)
    with pytest.raises(InputError, match="increase strictly"):
        run_ukf_lockstep(T_JUL, x0, P0, epochs[::-1], [template], values, transition=None, model=None)
