"""EKF: agreement with filterpy's KalmanFilter, refusals with reasons, covariance health; process noise."""

import logging

import numpy as np
import pytest
from filterpy.common import Q_continuous_white_noise, van_loan_discretization
from filterpy.kalman import KalmanFilter
from scipy import stats

from opnav.consistency import chi2_mean_bounds, nees
from opnav.errors import InputError
from opnav.filters.base import Estimate
from opnav.filters.ekf import EKFOptions, ExtendedKalmanFilter, ekf_predict, ekf_update
from opnav.filters.noise import StateNoiseCompensation, WhiteAcceleration, process_noise_from_config, ric_rotation
from opnav.filters.run import run_filter
from opnav.records import Measurement


# --------------------------------------------------------------------------- process noise
def test_white_acceleration_matches_filterpy_and_van_loan():
    q, dt = 3e-12, 60.0
    Q = WhiteAcceleration(q).discrete(dt)
    one_axis = Q_continuous_white_noise(dim=2, dt=dt, spectral_density=q)
    for axis in range(3):
        idx = [axis, axis + 3]
        np.testing.assert_allclose(Q[np.ix_(idx, idx)], one_axis, rtol=1e-12)
    # van Loan on the constant-velocity system is exact for this model
    F = np.block([[np.zeros((3, 3)), np.eye(3)], [np.zeros((3, 3)), np.zeros((3, 3))]])
    G = np.vstack([np.zeros((3, 3)), np.eye(3)])
    _, Q_vl = van_loan_discretization(F, G * np.sqrt(q), dt)
    np.testing.assert_allclose(Q, Q_vl, rtol=1e-9, atol=1e-30)


def test_snc_rotates_ric_densities_into_icrf():
    x = np.array([7000.0, 1000.0, 500.0, -1.0, 7.0, 0.5])
    rot = ric_rotation(x)
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-14)
    Q = StateNoiseCompensation((1e-10, 0.0, 0.0)).discrete(10.0, x)
    radial = x[:3] / np.linalg.norm(x[:3])
    # radial-only noise puts all position variance along r
    np.testing.assert_allclose(Q[:3, :3], 1e-10 * 1000.0 / 3.0 * np.outer(radial, radial), rtol=1e-12, atol=1e-25)
    iso = StateNoiseCompensation((2e-10, 2e-10, 2e-10)).discrete(10.0, x)
    np.testing.assert_allclose(iso, WhiteAcceleration(2e-10).discrete(10.0), rtol=0, atol=1e-12 * np.abs(iso).max())
    np.testing.assert_array_equal(Q, Q.T)


def test_process_noise_validation():
    with pytest.raises(InputError, match="q_km2_s3"):
        WhiteAcceleration(-1.0)
    with pytest.raises(InputError, match="q_ric_km2_s3"):
        StateNoiseCompensation((1.0, 2.0))
    with pytest.raises(InputError, match="unknown process_noise model"):
        process_noise_from_config({"model": "pink"})
    assert process_noise_from_config({"model": "none"}) is None
    assert process_noise_from_config({"model": "white", "q_km2_s3": 1e-15}) == WhiteAcceleration(1e-15)


# --------------------------------------------------------------------------- linear problem
DT = 10.0
F_CV = np.block([[np.eye(3), DT * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
H_POS = np.hstack([np.eye(3), np.zeros((3, 3))])
R_POS = np.diag([4.0, 9.0, 1.0])
Q_MODEL = WhiteAcceleration(1e-3)


class LinearPositionModel:
    """h(x) = H x for 'position' records (a linear-Gaussian test case)."""

    def predict(self, record, x):
        return np.asarray(x)[..., :3].copy()

    def jacobian(self, record, x):
        return H_POS

    def residual(self, record, predicted):
        return record.value - predicted


def linear_propagator(t0, x0, t1):
    steps = round((t1 - t0) / DT)
    phi = np.linalg.matrix_power(F_CV, steps)
    return phi @ x0, phi


def linear_case(seed, count=60):
    rng = np.random.default_rng(seed)
    x0 = np.array([10.0, -5.0, 3.0, 1.0, 0.5, -0.2])
    P0 = np.diag([100.0, 100.0, 100.0, 1.0, 1.0, 1.0])
    x_true = x0 + rng.multivariate_normal(np.zeros(6), P0)
    truth, records = [], []
    Qd = Q_MODEL.discrete(DT)
    for k in range(1, count + 1):
        x_true = F_CV @ x_true + rng.multivariate_normal(np.zeros(6), Qd)
        truth.append(x_true)
        z = x_true[:3] + rng.multivariate_normal(np.zeros(3), R_POS)
        records.append(Measurement(k * DT, "position", z, R_POS, sensor="lin"))
    return Estimate(0.0, x0, P0), records, np.array(truth)


def make_ekf(estimate, **kw):
    return ExtendedKalmanFilter(estimate, propagator=linear_propagator, model=LinearPositionModel(),
                                process_noise=Q_MODEL, options=EKFOptions(gate_probability=None), **kw)


def test_ekf_reproduces_filterpy_kalman_filter():
    estimate, records, _ = linear_case(0)
    kf = KalmanFilter(dim_x=6, dim_z=3)
    kf.x, kf.P, kf.F, kf.H, kf.R, kf.Q = estimate.x.copy(), estimate.P.copy(), F_CV, H_POS, R_POS, Q_MODEL.discrete(DT)
    ekf = make_ekf(estimate)
    for record in records:
        kf.predict()
        kf.update(record.value)
        outcome = ekf.update(record)
        assert outcome.accepted
        np.testing.assert_allclose(ekf.estimate.x, kf.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(ekf.estimate.P, kf.P, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(outcome.residual, kf.y, rtol=1e-9, atol=1e-9)


def test_procedural_and_object_forms_agree():
    estimate, records, _ = linear_case(1, count=20)
    ekf = make_ekf(estimate)
    current = estimate
    for record in records:
        current = ekf_predict(current, record.t_tdb_s, propagator=linear_propagator, process_noise=Q_MODEL)
        current = ekf_update(current, record, model=LinearPositionModel(), options=EKFOptions(gate_probability=None)).estimate
        ekf.update(record)
    np.testing.assert_allclose(ekf.estimate.x, current.x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(ekf.estimate.P, current.P, rtol=1e-12, atol=1e-15)


def test_linear_nees_and_nis_inside_chi_square_bounds():
    """Mean NEES (6 dof) and NIS (3 dof) over 20 seeded runs x 60 steps inside 95% bounds."""
    nees_all, nis_all = [], []
    for seed in range(20):
        estimate, records, truth = linear_case(100 + seed)
        hist = run_filter(make_ekf(estimate), records, progress=False)
        nees_all.append(nees(hist.states, hist.covariances, truth))
        nis_all.append(hist.nis)
    # average across runs at each step (independent runs), then over steps
    runs = len(nees_all)
    nees_mean = np.mean(nees_all, axis=0)
    nis_mean = np.mean(nis_all, axis=0)
    lo, hi = chi2_mean_bounds(6, runs, 0.95)
    inside = np.mean((nees_mean > lo) & (nees_mean < hi))
    assert inside >= 0.85  # ~95% expected per step; 0.85 allows for step-to-step scatter over 60 steps
    # Steps within a run are correlated, so the grand mean is held to the bound of `runs`
    # independent values (a time average varies less than one sample): valid, if loose.
    lo_all, hi_all = chi2_mean_bounds(6, runs, 0.99)
    assert lo_all < np.mean(nees_all) < hi_all
    lo_n, hi_n = chi2_mean_bounds(3, runs, 0.99)
    assert lo_n < np.mean(nis_all) < hi_n
    # NIS are white for a consistent filter, so the tight bound over every value applies
    lo_w, hi_w = chi2_mean_bounds(3, nis_mean.size * runs, 0.99)
    assert lo_w < np.mean(nis_all) < hi_w


# --------------------------------------------------------------------------- refusals
def test_bad_records_are_refused_with_logged_reasons(caplog):
    estimate, records, _ = linear_case(2, count=10)
    ekf = ExtendedKalmanFilter(estimate, propagator=linear_propagator, model=LinearPositionModel(),
                               process_noise=Q_MODEL)  # default gate 1 - 1e-6
    for record in records[:5]:
        assert ekf.update(record).accepted
    t = ekf.estimate.t_tdb_s
    z = records[5].value
    nan_value = Measurement(t + DT, "position", [np.nan, 0.0, 0.0], R_POS)
    not_pd = Measurement(t + DT, "position", z, np.diag([1.0, -1.0, 1.0]))
    nan_cov = Measurement(t + DT, "position", z, np.diag([1.0, np.nan, 1.0]))
    backwards = Measurement(t - DT, "position", z, R_POS)
    sigma = np.sqrt(np.diag(R_POS + H_POS @ ekf.estimate.P @ H_POS.T))
    outlier = Measurement(records[5].t_tdb_s, "position", z + 100.0 * sigma * np.array([1.0, 0.0, 0.0]), R_POS)
    cases = [(nan_value, "NaN"), (not_pd, "not positive definite"), (nan_cov, "covariance contains NaN"),
             (backwards, "time goes backwards"), (outlier, "chi-square gate")]
    with caplog.at_level(logging.WARNING, logger="opnav.filters"):
        for record, reason in cases:
            before = ekf.estimate
            outcome = ekf.update(record)
            assert not outcome.accepted
            assert reason in outcome.reason
            assert any(reason in message for message in caplog.messages)
            if record is backwards:
                assert ekf.estimate is before  # a record in the past moves nothing
            elif record is not outlier:
                # bad values at a usable epoch: the filter is predicted to it (never the old state under
                # the new time tag) and nothing is folded in
                assert ekf.estimate.t_tdb_s == record.t_tdb_s and outcome.estimate is ekf.estimate
                expected = ekf_predict(before, record.t_tdb_s, propagator=linear_propagator, process_noise=Q_MODEL)
                np.testing.assert_array_equal(ekf.estimate.x, expected.x)
            else:
                assert outcome.nis > 1e3
                np.testing.assert_array_equal(ekf.estimate.x, outcome.estimate.x)
    # the filter still works after the refusals
    assert ekf.update(records[6]).accepted


def test_covariance_symmetric_pd_over_whole_arc():
    estimate, records, _ = linear_case(3, count=200)
    hist = run_filter(make_ekf(estimate), records, progress=False)
    np.testing.assert_array_equal(hist.covariances, np.swapaxes(hist.covariances, 1, 2))
    assert np.all(np.linalg.eigvalsh(hist.covariances) > 0.0)
    assert hist.accepted.all()


def test_predict_backwards_and_bad_initial_estimate_raise():
    estimate, _, _ = linear_case(4, count=1)
    ekf = make_ekf(estimate)
    ekf.predict(20.0)
    with pytest.raises(InputError, match="cannot predict backwards"):
        ekf.predict(10.0)
    with pytest.raises(Exception, match="estimate.P"):
        make_ekf(Estimate(0.0, estimate.x, -np.eye(6)))
    with pytest.raises(InputError, match="gate_probability"):
        EKFOptions(gate_probability=1.5)


# --------------------------------------------------------------------------- S1 Monte Carlo
def s1_monte_carlo(runs: int, hours: float, seed: int = 3):
    """EKF runs in lockstep on the S1 July arc: both moons, 0.1", 1-min data, 1-km white ephemeris error."""
    from opnav.constants import ARCSEC_RAD
    from opnav.dynamics import cruise_model, propagate
    from opnav.epochs import parse_epoch
    from opnav.filters.ekf import force_model_batch_propagator
    from opnav.filters.lockstep import run_ekf_lockstep
    from opnav.measurements import ProbeMeasurementModel, simulate_radec

    t_s1 = parse_epoch("2013-12-12T12:00:00", scale="tt")
    s1 = np.array([24_306_991.2893, 132_523_850.2219, 58_427_884.5328, -32.455391, 3.658828, 3.362343])
    t0 = parse_epoch("2014-07-01T00:00:00", scale="tdb")
    epochs = t0 + 60.0 * np.arange(1, int(hours * 60) + 1)
    truth = propagate(cruise_model(), t_s1, s1, np.concatenate([[t0], epochs])).states
    sigma = 0.1 * ARCSEC_RAD
    from opnav.ephemeris.cache import default_cached_ephemeris

    truth_model = ProbeMeasurementModel("sun")
    # the filter takes the fast path (cached ephemeris, compiled light time), the truth the exact one
    model = ProbeMeasurementModel("sun", target_position_sigma_km=1.0, ephemeris=default_cached_ephemeris())
    P0 = np.diag([(5000.0 / np.sqrt(3.0)) ** 2] * 3 + [(0.005 / np.sqrt(3.0)) ** 2] * 3)
    rng = np.random.default_rng(seed)
    x0 = truth[0] + rng.multivariate_normal(np.zeros(6), P0, size=runs)
    targets = ("phobos", "deimos")
    values = np.stack([
        np.stack([simulate_radec(truth_model, target, epochs, truth[1:], sigma_rad=sigma, rng=rng,
                                 target_offset_km=rng.normal(0.0, 1.0, (epochs.size, 3))) for _ in range(runs)], axis=1)
        for target in targets])
    templates = [Measurement(epochs[0], "radec", [0.0, 0.0], np.eye(2) * sigma**2, target=t) for t in targets]
    hist = run_ekf_lockstep(t0, x0, P0, epochs, templates, values, propagator=force_model_batch_propagator(cruise_model()),
                            model=model, truth=truth, keep_every=5, progress=False)
    kept_truth = truth[1:][4::5]
    return hist, kept_truth, runs


def check_s1_consistency(hist, kept_truth, runs):
    err_nees = np.stack([nees(hist.states[:, k], hist.covariances[:, k], kept_truth) for k in range(runs)])
    nees_t = err_nees.mean(axis=0)
    lo, hi = chi2_mean_bounds(6, runs, 0.95)
    assert np.mean((nees_t > lo) & (nees_t < hi)) >= 0.8
    lo99, hi99 = chi2_mean_bounds(6, runs, 0.99)  # time average of correlated values: loose but valid
    assert lo99 < nees_t.mean() < hi99
    # the default gate (1 - 1e-6) refuses good records at that rate: allow its 99.9% Poisson count
    refused = int((~hist.accepted).sum())
    assert refused <= stats.poisson.ppf(0.999, 1e-6 * hist.accepted.size)
    nis = hist.nis[hist.accepted]
    lo_n, hi_n = chi2_mean_bounds(2, nis.size, 0.99)  # innovations are white
    assert lo_n < nis.mean() < hi_n
    # covariance symmetric PD over the whole arc, every run
    np.testing.assert_array_equal(hist.covariances, np.swapaxes(hist.covariances, -1, -2))
    assert np.all(np.linalg.eigvalsh(hist.covariances) > 0.0)
    # at small errors the EKF covariance is the PCRB recursion linearised at its estimate
    sig = np.sqrt(np.trace(hist.covariances[..., :3, :3], axis1=-2, axis2=-1))
    bound = np.sqrt(np.trace(hist.pcrb[:, :3, :3], axis1=-2, axis2=-1))
    np.testing.assert_allclose(sig, np.broadcast_to(bound[:, None], sig.shape), rtol=0.02)
    return err_nees


def test_s1_short_arc_nees_nis_consistent():
    """10 runs x 2 h of the S1 July arc (fast version of benchmarks/s1_filters.py)."""
    hist, kept_truth, runs = s1_monte_carlo(runs=10, hours=2.0)
    check_s1_consistency(hist, kept_truth, runs)


@pytest.mark.slow
def test_s1_fifty_runs_thirty_days():
    """S1 acceptance: 50 runs x 30 days; RMS of the last 15 days matches the filter's 1-sigma."""
    hist, kept_truth, runs = s1_monte_carlo(runs=50, hours=30 * 24.0)
    check_s1_consistency(hist, kept_truth, runs)
    last = hist.epochs >= hist.epochs[-1] - 15 * 86_400.0
    err = np.linalg.norm(hist.states[last, :, :3] - kept_truth[last, None, :3], axis=-1)
    sig = np.sqrt(np.trace(hist.covariances[last][..., :3, :3], axis1=-2, axis2=-1))
    np.testing.assert_allclose(np.sqrt(np.mean(err**2)), np.sqrt(np.mean(sig**2)), rtol=0.2)


def test_pcrb_along_the_truth_by_the_filters_steps_equals_the_information_recursion():
    """opnav.filters.crb.pcrb_along (an ungated EKF's own steps, compiled here, held on the truth) against
    the lockstep EKF's bound row (the information recursion J = (Q + F J^-1 F^T)^-1 + H^T R^-1 H with F,
    H and R at the truth): the same bound to 1e-6 of itself over 2 h of S1 (both moons, 1-km ephemeris
    error in R)."""
    from opnav.dynamics import cruise_model, propagate
    from opnav.ephemeris.cache import default_cached_ephemeris
    from opnav.epochs import parse_epoch
    from opnav.filters.crb import pcrb_along
    from opnav.filters.ekf import EKFOptions, ExtendedKalmanFilter, force_model_batch_propagator, force_model_propagator
    from opnav.filters.lockstep import run_ekf_lockstep
    from opnav.measurements import ProbeMeasurementModel

    t0 = parse_epoch("2014-07-01T00:00:00", scale="tdb")
    s1 = np.array([24_306_991.2893, 132_523_850.2219, 58_427_884.5328, -32.455391, 3.658828, 3.362343])
    epochs = t0 + 60.0 * np.arange(1, 121)
    truth = propagate(cruise_model(), parse_epoch("2013-12-12T12:00:00", scale="tt"), s1,
                      np.concatenate([[t0], epochs])).states
    model = ProbeMeasurementModel("sun", target_position_sigma_km=1.0, ephemeris=default_cached_ephemeris())
    P0 = np.diag([(5000.0 / np.sqrt(3.0)) ** 2] * 3 + [(0.005 / np.sqrt(3.0)) ** 2] * 3)
    sigma2 = (0.1 / 206264.806) ** 2
    templates = [Measurement(epochs[0], "radec", [0.0, 0.0], np.eye(2) * sigma2, target=t) for t in ("phobos", "deimos")]
    values = np.zeros((2, epochs.size, 1, 2))  # the bound does not read them
    reference = run_ekf_lockstep(t0, truth[:1], P0, epochs, templates, values,
                                 propagator=force_model_batch_propagator(cruise_model()), model=model, truth=truth,
                                 options=EKFOptions(gate_probability=None)).pcrb
    ekf = ExtendedKalmanFilter(Estimate(t0, truth[0], P0), propagator=force_model_propagator(cruise_model()),
                               model=model, options=EKFOptions(gate_probability=None))
    records = [Measurement(t, "radec", [1.0, 0.5], np.eye(2) * sigma2, target=template.target)
               for t in epochs for template in templates]
    bound = pcrb_along(ekf, records, t0, truth[0], P0, epochs, truth[1:])
    assert bound.shape == reference.shape == (120, 6, 6)
    scale = np.sqrt(np.einsum("nii->ni", reference))
    assert np.abs((bound - reference) / (scale[:, :, None] * scale[:, None, :])).max() < 1e-6
    assert np.sqrt(np.trace(reference[-1, :3, :3])) < 0.5 * np.sqrt(np.trace(P0[:3, :3]))  # the bound has shrunk


def test_lockstep_update_equals_single_run_update():
    """ekf_update_batch on K runs is ekf_update on each (same gain, Joseph form, gate)."""
    from opnav.epochs import parse_epoch
    from opnav.filters.ekf import ekf_update_batch
    from opnav.measurements import ProbeMeasurementModel

    t = parse_epoch("2014-07-15T00:00:00", scale="tdb")
    model = ProbeMeasurementModel("sun", target_position_sigma_km=1.0)
    rng = np.random.default_rng(9)
    x_ref = np.array([-1.36e8, 1.9e8, 9.1e7, -20.0, -10.0, -4.0])
    P = np.diag([1e6] * 3 + [1e-5] * 3)
    xs = x_ref + rng.normal(size=(3, 6)) * np.array([1e3] * 3 + [3e-3] * 3)
    record = Measurement(t, "radec", [0.0, 0.0], np.eye(2) * (4.8e-7) ** 2, target="deimos")
    values = model.predict(record, x_ref) + rng.normal(0.0, 1e-5, size=(3, 2))
    values[2] += 1.0  # an outlier the gate must refuse
    batch = ekf_update_batch(xs, np.stack([P] * 3), record, values, model=model)
    for k in range(3):
        single = ekf_update(Estimate(t, xs[k], P), Measurement(t, "radec", values[k], record.covariance, target="deimos"),
                            model=model)
        assert single.accepted == batch.accepted[k]
        np.testing.assert_allclose(batch.x[k], single.estimate.x, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(batch.P[k], single.estimate.P, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(batch.nis[k], single.nis, rtol=1e-9)
    assert not batch.accepted[2]


def test_history_nees_uses_truth_at_history_epochs():
    from opnav.filters.run import history_nees

    estimate, records, truth = linear_case(6, count=30)
    hist = run_filter(make_ekf(estimate), records, progress=False)
    by_epoch = {r.t_tdb_s: x for r, x in zip(records, truth)}
    values = history_nees(hist, lambda t: np.array([by_epoch[float(ti)] for ti in t]))
    np.testing.assert_allclose(values, nees(hist.states, hist.covariances, truth), rtol=1e-12)
    with pytest.raises(InputError, match="do not match"):
        nees(hist.states, hist.covariances, truth[:-1])
