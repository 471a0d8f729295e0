"""One filter core: every form's pure predict/update functions, called step by step, give the
estimates of its class (the procedural and OO forms agree, as in filterpy's ``test_procedure_form``),
and the checks shared in :mod:`opnav.filters.base` raise and refuse as documented."""

import logging

import numpy as np
import pytest
from scipy import stats
from test_ukf import (
    BEACONS,
    P0_ORBIT,
    Q_ORBIT,
    SIGMA_RADEC,
    X0_ORBIT,
    BeaconRadec,
    FixedNoise,
    PositionModel,
    cv_matrix,
    cv_transition,
    gravity_transition,
    radec_record,
    simulate_orbit,
)

from opnav.errors import CovarianceError, InputError
from opnav.filters.augmented_ukf import AugmentedUKF, additive_noise, augmented_ukf_predict, augmented_ukf_update
from opnav.filters.base import (
    Estimate,
    check_epoch,
    chi2_quantile,
    gate_refusal,
    measurement_covariance,
    psd_sqrt,
    screen_record,
)
from opnav.filters.ekf import EKFOptions, ExtendedKalmanFilter, ekf_predict, ekf_update
from opnav.filters.particle import (
    ParticleFilter,
    ParticleOptions,
    UnscentedParticleFilter,
    sample_cloud,
    sample_mixture,
    sir_predict,
    sir_update,
    upf_predict,
    upf_update,
)
from opnav.filters.sr_ukf import SqrtEstimate, SquareRootUKF, as_sqrt, sr_ukf_predict, sr_ukf_update
from opnav.filters.ukf import (
    UKFOptions,
    UnscentedKalmanFilter,
    sigma_weights,
    ukf_predict_estimate,
    ukf_update_estimate,
)
from opnav.records import Measurement

GATE = 0.999
Q_LINEAR = np.diag([1e-3, 1e-3, 1e-3, 1e-7, 1e-7, 1e-7])
X0_LINEAR = np.array([100.0, -50.0, 20.0, 0.1, 0.2, -0.05])
P0_LINEAR = np.diag([25.0, 25.0, 25.0, 1e-4, 1e-4, 1e-4])
Q_PF = np.diag([0.04, 0.04, 0.04, 1e-6, 1e-6, 1e-6])


def orbit_records(Q=Q_ORBIT, steps=10):
    """Beacon RA/Dec records of the toy orbit, ending with a 100-sigma outlier that the gate refuses."""
    _, records = simulate_orbit(np.random.default_rng(5), steps, Q=Q)
    last = records[-1]
    return records + [radec_record(last.t_tdb_s + 60.0, last.value + np.array([100 * SIGMA_RADEC, 0.0]), "a")]


def linear_records(steps=10):
    """Position records of constant-velocity motion from X0_LINEAR, ending with a 1000-sigma outlier."""
    rng = np.random.default_rng(6)
    R = np.diag([0.5, 0.8, 0.3])
    truth = [(cv_matrix(60.0 * k) @ X0_LINEAR)[:3] for k in range(1, steps + 2)]
    records = [Measurement(60.0 * k, "position", truth[k - 1] + rng.standard_normal(3), R) for k in range(1, steps + 1)]
    return records + [Measurement(60.0 * (steps + 1), "position", truth[-1] + 1e3, R)]


def cv_propagator(t0, x, t1):
    F = cv_matrix(t1 - t0)
    return F @ x, F


def kalman_form(name, problem):
    """(class instance, start, pure predict, pure update, records) of one Kalman form on one problem."""
    if problem == "linear":
        estimate, noise, records = Estimate(0.0, X0_LINEAR, P0_LINEAR), FixedNoise(Q_LINEAR), linear_records()
        transition, model = cv_transition, PositionModel()
    else:
        estimate, noise, records = Estimate(0.0, X0_ORBIT, P0_ORBIT), FixedNoise(Q_ORBIT), orbit_records()
        transition, model = gravity_transition, BeaconRadec(BEACONS)
    options = UKFOptions(alpha=0.5, gate_probability=GATE)
    weights = sigma_weights(6, options)
    if name == "ekf":
        ekf_options = EKFOptions(gate_probability=GATE)
        filt = ExtendedKalmanFilter(estimate, propagator=cv_propagator, model=model, process_noise=noise,
                                    options=ekf_options)
        return (filt, estimate,
                lambda e, t: ekf_predict(e, t, propagator=cv_propagator, process_noise=noise),
                lambda e, r: ekf_update(e, r, model=model, options=ekf_options), records)
    if name == "ukf":
        filt = UnscentedKalmanFilter(estimate, transition=transition, process_noise=noise, model=model, options=options)
        return (filt, estimate,
                lambda e, t: ukf_predict_estimate(e, t, transition=transition, process_noise=noise, weights=weights),
                lambda e, r: ukf_update_estimate(e, r, model=model, weights=weights, options=options), records)
    if name == "sr-ukf":
        filt = SquareRootUKF(estimate, transition=transition, process_noise=noise, model=model, options=options)
        return (filt, as_sqrt(estimate),
                lambda e, t: sr_ukf_predict(e, t, transition=transition, process_noise=noise, weights=weights),
                lambda e, r: sr_ukf_update(e, r, model=model, weights=weights, options=options), records)
    noisy = additive_noise(transition)
    filt = AugmentedUKF(estimate, transition=noisy, process_noise=noise, model=model, options=options)
    return (filt, estimate,
            lambda e, t: augmented_ukf_predict(e, t, transition=noisy, process_noise=noise, options=options),
            lambda e, r: augmented_ukf_update(e, r, transition=noisy, process_noise=noise, model=model, options=options),
            records)


def assert_same_estimate(a, b):
    assert a.t_tdb_s == b.t_tdb_s
    np.testing.assert_allclose(a.x, b.x, rtol=1e-12, atol=0)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-12, atol=1e-300)


def assert_same_outcome(a, b):
    assert_same_estimate(a.estimate, b.estimate)
    np.testing.assert_allclose(a.residual, b.residual, rtol=1e-12, atol=0)
    np.testing.assert_allclose(a.residual_cov, b.residual_cov, rtol=1e-12, atol=0)
    np.testing.assert_allclose(a.nis, b.nis, rtol=1e-12)
    assert (a.accepted, a.reason) == (b.accepted, b.reason)


@pytest.mark.parametrize("name,problem", [
    ("ekf", "linear"), ("ukf", "linear"), ("sr-ukf", "linear"), ("augmented", "linear"),
    ("ukf", "orbit"), ("sr-ukf", "orbit"), ("augmented", "orbit"),
])
def test_kalman_pure_functions_reproduce_the_class(name, problem):
    filt, estimate, predict, update, records = kalman_form(name, problem)
    accepted = 0
    for i, record in enumerate(records):
        estimate = predict(estimate, record.t_tdb_s)
        outcome = update(estimate, record)
        estimate = outcome.estimate
        assert_same_outcome(outcome, filt.update(record))
        assert_same_estimate(estimate, filt.estimate)
        accepted += outcome.accepted
        if i == 3:  # a prediction between records, then on from it
            estimate = predict(estimate, record.t_tdb_s + 20.0)
            assert_same_estimate(estimate, filt.predict(record.t_tdb_s + 20.0))
    assert accepted >= len(records) - 2  # a good record may fall outside the 0.999 gate
    assert not outcome.accepted and "chi-square gate" in outcome.reason  # the outlier


def test_square_root_estimate_carries_its_factor():
    _, start, predict, update, records = kalman_form("sr-ukf", "orbit")
    predicted = predict(start, records[0].t_tdb_s)
    posterior = update(predicted, records[0]).estimate
    for e in (start, predicted, posterior):
        assert isinstance(e, SqrtEstimate)
        np.testing.assert_array_equal(e.S, np.tril(e.S))
        np.testing.assert_array_equal(e.P, e.S @ e.S.T)


def particle_form(kind):
    """(class instance, start cloud, pure predict, pure update) sharing models and generator seeds."""
    noise, model = FixedNoise(Q_PF), BeaconRadec(BEACONS)
    options = ParticleOptions(n_particles=60, resample_fraction=0.9, mcmc_move=kind == "mcmc-upf", gate_probability=GATE)
    estimate = Estimate(0.0, X0_ORBIT, P0_ORBIT)
    rng = np.random.default_rng(11)
    start = (sample_cloud(estimate, n_particles=options.n_particles, rng=rng) if kind == "sir" else
             sample_mixture(estimate, n_particles=options.n_particles, fraction=options.component_fraction, rng=rng))
    common = dict(transition=gravity_transition, process_noise=noise, model=model, rng=np.random.default_rng(11),
                  options=options)
    if kind == "sir":
        return (ParticleFilter(estimate, **common), start,
                lambda c, t: sir_predict(c, t, transition=gravity_transition, process_noise=noise, options=options, rng=rng),
                lambda c, r: sir_update(c, r, model=model, options=options, rng=rng))
    weights = sigma_weights(6, options.ukf)
    return (UnscentedParticleFilter(estimate, **common), start,
            lambda c, t: upf_predict(c, t, transition=gravity_transition, process_noise=noise, model=model,
                                     options=options, weights=weights, rng=rng),
            lambda c, r: upf_update(c, r, model=model, options=options, weights=weights))


@pytest.mark.parametrize("kind", ["sir", "upf", "mcmc-upf"])
def test_particle_pure_functions_reproduce_the_class(kind):
    filt, cloud, predict, update = particle_form(kind)
    records = orbit_records(Q=Q_PF, steps=6)
    np.testing.assert_array_equal(cloud.particles, filt.cloud.particles)
    resampled = 0
    for record in records:
        cloud, outcome = update(predict(cloud, record.t_tdb_s), record)
        assert_same_outcome(outcome, filt.update(record))
        np.testing.assert_allclose(cloud.particles, filt.cloud.particles, rtol=1e-12, atol=0)
        np.testing.assert_allclose(cloud.weights, filt.weights, rtol=1e-12, atol=0)
        assert_same_estimate(cloud.estimate, filt.estimate)
        resampled += bool(cloud.last_epoch and cloud.last_epoch.resampled)
    assert resampled > 0
    assert not outcome.accepted and "chi-square gate" in outcome.reason


# --------------------------------------------------------------------------- shared checks
def test_check_epoch_refuses_non_finite_and_backwards_epochs():
    check_epoch(100.0, 100.0)
    check_epoch(100.0, 100.0 - 1e-10)  # within 1 ns: the same epoch
    check_epoch(100.0, 160.0)
    with pytest.raises(InputError, match="backwards"):
        check_epoch(100.0, 99.0)
    for bad in (np.nan, np.inf):
        with pytest.raises(InputError, match="not finite"):
            check_epoch(100.0, bad)


@pytest.mark.parametrize("name", ["ukf", "sr-ukf", "augmented"])
def test_every_unscented_form_uses_the_shared_epoch_check(name):
    _, estimate, predict, _, _ = kalman_form(name, "orbit")
    later = predict(estimate, 60.0)
    with pytest.raises(InputError, match="cannot predict backwards"):
        predict(later, 0.0)
    with pytest.raises(InputError, match="not finite"):
        predict(later, np.nan)


@pytest.mark.parametrize("kind", ["sir", "upf"])
def test_every_particle_form_uses_the_shared_epoch_check(kind):
    _, cloud, predict, _ = particle_form(kind)
    with pytest.raises(InputError, match="cannot predict backwards"):
        predict(predict(cloud, 60.0), 0.0)


def test_gate_refusal_keeps_the_prior_and_logs_its_reason(caplog):
    prior = Estimate(0.0, X0_ORBIT, P0_ORBIT)
    record = radec_record(0.0, np.zeros(2), "a")
    residual, S = np.array([1.0, 0.0]), np.eye(2)
    bound = stats.chi2.ppf(GATE, 2)
    common = dict(residual=residual, residual_cov=S, probability=GATE)
    assert gate_refusal(prior, record, nis=0.99 * bound, **common) is None
    assert gate_refusal(prior, record, nis=1e9, residual=residual, residual_cov=S, probability=None) is None
    with caplog.at_level(logging.WARNING, logger="opnav.filters.base"):
        out = gate_refusal(prior, record, nis=1.01 * bound, **common)
    assert not out.accepted and out.estimate is prior and out.nis == 1.01 * bound
    assert out.reason.startswith("chi-square gate: NIS") and f"{GATE} quantile of chi2(2)" in out.reason
    np.testing.assert_array_equal(out.residual, residual)
    assert out.reason in caplog.text


def test_chi2_quantile_is_scipys_and_cached():
    chi2_quantile.cache_clear()
    assert chi2_quantile(GATE, 3) == stats.chi2.ppf(GATE, 3)
    chi2_quantile(GATE, 3)
    assert chi2_quantile.cache_info().hits == 1


def test_screen_record_refuses_bad_values_and_other_epochs():
    estimate = Estimate(60.0, X0_ORBIT, P0_ORBIT)
    assert screen_record(estimate, radec_record(60.0, np.zeros(2), "a")) is None
    late = screen_record(estimate, radec_record(120.0, np.zeros(2), "a"))
    assert not late.accepted and "predict first" in late.reason and late.estimate is estimate
    assert np.all(np.isnan(late.residual)) and np.isnan(late.nis)
    nan = screen_record(estimate, radec_record(60.0, np.array([np.nan, 0.0]), "a"))
    assert not nan.accepted and "NaN" in nan.reason


@pytest.mark.parametrize("name", ["ukf", "sr-ukf", "augmented"])
def test_every_unscented_update_refuses_a_record_at_another_epoch(name):
    _, estimate, _, update, _ = kalman_form(name, "orbit")
    out = update(estimate, radec_record(60.0, np.zeros(2), "a"))
    assert not out.accepted and "predict first" in out.reason


def test_measurement_covariance_prefers_the_models_own_noise():
    record = radec_record(0.0, np.zeros(2), "a")
    np.testing.assert_array_equal(measurement_covariance(BeaconRadec(BEACONS), record, X0_ORBIT), record.covariance)

    class WithEphemerisError(BeaconRadec):
        def noise_covariance(self, record, x):
            return record.covariance + 1e-8 * np.eye(2)

    np.testing.assert_array_equal(measurement_covariance(WithEphemerisError(BEACONS), record, X0_ORBIT),
                                  record.covariance + 1e-8 * np.eye(2))


def test_psd_sqrt_of_singular_noise_and_refusal_of_indefinite():
    Q = np.zeros((8, 8))
    Q[:6, :6] = Q_ORBIT
    root = psd_sqrt(Q, "Q")
    np.testing.assert_allclose(root @ root.T, Q, rtol=0, atol=1e-18)
    with pytest.raises(CovarianceError, match="Q is not positive semi-definite"):
        psd_sqrt(np.diag([1.0, -1.0]), "Q")


def test_a_navigation_epoch_decades_before_the_records_is_refused_not_propagated():
    """A year typed wrong (t0 114 years before the data) would propagate for hours before the first
    record: refused in one line naming both epochs; a day before is fine."""
    from opnav.filters.navigate import check_epoch_span
    from opnav.records import Measurement

    records = [Measurement(4.0e8, "radec", [0.1, 0.2], np.eye(2) * 1e-12, target="phobos")]
    with pytest.raises(InputError, match=r"navigation epoch 1898-.* TDB is 114 years before the first record"):
        check_epoch_span(records, 4.0e8 - 114 * 365.25 * 86400.0)
    check_epoch_span(records, 4.0e8 - 86400.0)
