"""Batch least squares: linear exactness, chi-square consistency, nonlinear convergence; PCRB."""

import numpy as np
import pytest
from scipy import stats

from opnav.dynamics import propagate, two_body_model
from opnav.ephemeris import default_planets, Ephemeris
from opnav.epochs import parse_epoch
from opnav.errors import InputError
from opnav.filters.base import Estimate
from opnav.filters.batch import BatchOptions, batch_least_squares, force_model_trajectory
from opnav.filters.crb import pcrb
from opnav.filters.ekf import EKFOptions, ExtendedKalmanFilter, force_model_propagator
from opnav.filters.run import run_filter
from opnav.measurements import ProbeMeasurementModel
from opnav.records import Measurement

H_POS = np.hstack([np.eye(3), np.zeros((3, 3))])
R_POS = np.diag([4.0, 9.0, 1.0])


class LinearPositionModel:
    def predict(self, record, x):
        return np.asarray(x)[..., :3].copy()

    def jacobian(self, record, x):
        return H_POS

    def residual(self, record, predicted):
        return record.value - predicted


def cv_stm(dt):
    return np.block([[np.eye(3), dt * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])


def linear_trajectory(t0, x0, t):
    phis = np.stack([cv_stm(ti - t0) for ti in t])
    return phis @ x0, phis


def linear_records(rng, x_true, count=30):
    return [Measurement(10.0 * k, "position", x_true[:3] + 10.0 * k * x_true[3:] + rng.multivariate_normal(np.zeros(3), R_POS), R_POS)
            for k in range(count)]


def test_linear_batch_equals_closed_form_least_squares():
    rng = np.random.default_rng(0)
    x_true = np.array([1.0, 2.0, 3.0, 0.1, -0.2, 0.3])
    records = linear_records(rng, x_true)
    apriori = Estimate(0.0, np.zeros(6), np.eye(6) * 1e8)
    result = batch_least_squares(records, apriori, propagator=linear_trajectory, model=LinearPositionModel())
    A = np.vstack([H_POS @ cv_stm(r.t_tdb_s) for r in records])
    W = np.kron(np.eye(len(records)), np.linalg.inv(R_POS))
    z = np.concatenate([r.value for r in records])
    normal = A.T @ W @ A + np.eye(6) * 1e-8
    x_ls = np.linalg.solve(normal, A.T @ W @ z)
    np.testing.assert_allclose(result.estimate.x, x_ls, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(result.estimate.P, np.linalg.inv(normal), rtol=1e-8)
    assert result.iterations <= 2  # linear: one step then a zero step


def test_linear_batch_error_and_cost_are_chi_square():
    errs, costs = [], []
    for seed in range(40):
        rng = np.random.default_rng(100 + seed)
        x_true = rng.normal(size=6)
        records = linear_records(rng, x_true)
        result = batch_least_squares(records, Estimate(0.0, np.zeros(6), np.eye(6) * 1e8),
                                     propagator=linear_trajectory, model=LinearPositionModel())
        e = result.estimate.x - x_true
        errs.append(e @ np.linalg.solve(result.estimate.P, e))
        costs.append(result.cost)
    # mean of 40 chi2(6) and of 40 chi2(90 - 6), two-sided 99%
    lo, hi = stats.chi2.ppf([0.005, 0.995], 6 * 40) / 40
    assert lo < np.mean(errs) < hi
    lo, hi = stats.chi2.ppf([0.005, 0.995], 84 * 40) / 40
    assert lo < np.mean(costs) < hi


def test_batch_bad_records_left_out_and_errors():
    rng = np.random.default_rng(1)
    x_true = np.array([1.0, 2.0, 3.0, 0.1, -0.2, 0.3])
    records = linear_records(rng, x_true)
    records.append(Measurement(50.0, "position", [np.nan, 0.0, 0.0], R_POS))
    result = batch_least_squares(records, Estimate(0.0, np.zeros(6), np.eye(6) * 1e8),
                                 propagator=linear_trajectory, model=LinearPositionModel())
    assert result.used.sum() == len(records) - 1
    with pytest.raises(InputError, match="before the a-priori epoch"):
        batch_least_squares(records, Estimate(100.0, np.zeros(6), np.eye(6)), propagator=linear_trajectory,
                            model=LinearPositionModel())
    with pytest.raises(InputError, match="max_iterations"):
        BatchOptions(max_iterations=0)


T0 = parse_epoch("2014-07-01T00:00:00", scale="tdb")
EPH = Ephemeris(default_planets(), moons=object())  # Mars/Sun only: moons never asked


def two_body_case(rng, hours=48, step_s=1800.0):
    """Heliocentric two-body probe observing Mars (RA/Dec, 1 arcsec)."""
    model = two_body_model("sun")
    r_mars, v_mars = EPH.state("mars", T0, center="sun")
    x_true0 = np.concatenate([r_mars + np.array([-8e6, 5e6, 3e6]), v_mars + np.array([1.5, -1.0, 0.4])])
    epochs = T0 + np.arange(1, int(hours * 3600 / step_s) + 1) * step_s
    truth = propagate(model, T0, x_true0, epochs).states
    meas = ProbeMeasurementModel("sun", ephemeris=EPH)
    sigma = 4.8481e-6
    records = []
    for t, x in zip(epochs, truth):
        template = Measurement(t, "radec", [0.0, 0.0], np.eye(2) * sigma**2, target="mars")
        value = meas.predict(template, x) + rng.normal(0.0, sigma, 2)
        records.append(Measurement(t, "radec", value, np.eye(2) * sigma**2, target="mars"))
    return model, meas, x_true0, records, epochs, truth


def test_nonlinear_batch_converges_to_truth_within_its_covariance():
    rng = np.random.default_rng(7)
    model, meas, x_true0, records, _, _ = two_body_case(rng)
    P0 = np.diag([1e3**2] * 3 + [1e-3**2] * 3)
    guess = x_true0 + rng.multivariate_normal(np.zeros(6), P0)
    result = batch_least_squares(records, Estimate(T0, guess, P0), propagator=force_model_trajectory(model), model=meas)
    e = result.estimate.x - x_true0
    assert e @ np.linalg.solve(result.estimate.P, e) < stats.chi2.ppf(0.999, 6)
    assert result.cost < stats.chi2.ppf(0.999, 2 * len(records))
    assert 2 <= result.iterations <= 10


def test_ekf_on_two_body_arc_respects_pcrb_and_stays_pd():
    """At the truth, the EKF covariance equals the PCRB recursion (Q = 0) to linearisation accuracy."""
    rng = np.random.default_rng(11)
    model, meas, x_true0, records, epochs, truth = two_body_case(rng, hours=24, step_s=3600.0)
    P0 = np.diag([1e3**2] * 3 + [1e-3**2] * 3)
    ekf = ExtendedKalmanFilter(Estimate(T0, x_true0 + rng.multivariate_normal(np.zeros(6), P0), P0),
                               propagator=force_model_propagator(model), model=meas, options=EKFOptions())
    hist = run_filter(ekf, records, progress=False)
    assert hist.accepted.all()
    assert np.all(np.linalg.eigvalsh(hist.covariances) > 0)
    phis = propagate(model, T0, x_true0, epochs, stm=True).stm
    transitions = np.concatenate([phis[:1], phis[1:] @ np.linalg.inv(phis[:-1])])
    H = [meas.jacobian(r, x) for r, x in zip(records, truth)]
    bound = pcrb(P0, transitions, H, [r.covariance for r in records])
    # EKF linearises at its estimate (~1e3 km off on a 1e7 km range): agreement to ~(1e3/1e7) = 1e-4 relative; 1e-3 allowed
    np.testing.assert_allclose(np.sqrt(np.trace(hist.covariances[:, :3, :3], axis1=1, axis2=2)),
                               np.sqrt(np.trace(bound[:, :3, :3], axis1=1, axis2=2)), rtol=1e-3)
