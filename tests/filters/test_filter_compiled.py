"""The compiled single-run EKF and UKF steps (opnav.filters.compiled) against the pure cores they replace.

The reference is the same filter class on the general path (``ekf_predict``/``ekf_update``,
``ukf_predict_estimate``/``ukf_update_estimate``), with the same compiled propagator and ephemeris
cache, so the two differ only in how the formulas are evaluated (loops against BLAS/LAPACK): every
record is taken from the reference's prior by both, and the outcomes must agree to rounding.
"""

import logging
from dataclasses import replace

import numpy as np
import pytest

from opnav.dynamics import capture_model_2, cruise_model
from opnav.dynamics.fast import FastPropagator
from opnav.ephemeris.cache import default_cached_ephemeris
from opnav.epochs import parse_epoch
from opnav.filters.base import Estimate
from opnav.filters.ekf import EKFOptions, ExtendedKalmanFilter, force_model_propagator
from opnav.filters.noise import StateNoiseCompensation, WhiteAcceleration
from opnav.filters.run import run_filter
from opnav.filters.ukf import UKFOptions, UnscentedKalmanFilter, force_model_transition
from opnav.measurements import ProbeMeasurementModel, TargetOffsetModel
from opnav.records import Measurement

T0 = parse_epoch("2014-07-15T00:00:00", scale="tdb")
ARCSEC = np.pi / 648_000.0
SIGMA = 0.1 * ARCSEC
STEP_S = 60.0
#: Agreement of one step with the pure core (relative, see _differences): rounding of the same formulas.
RTOL = 1e-12


def probe_state(model):
    """A probe 20 million km from Mars (heliocentric ICRF, km and km/s), as in S1's July arc."""
    r_sun, v_sun = model.ephemeris.state("sun", T0, center="ssb")
    r_mars, v_mars = model.ephemeris.state("mars", T0, center="ssb")
    return np.concatenate([r_mars - r_sun + np.array([1.5e7, 1.2e7, 5e6]), v_mars - v_sun + np.array([-3.0, 1.0, 0.5])])


def make_records(model, truth, epochs, rng, *, pair=False, sigma=SIGMA):
    """Phobos and Deimos RA/Dec (rad) at every epoch: two records, or one ``radec_pair`` with a cross term."""
    records = []
    for t, x in zip(epochs, truth):
        values = []
        for name in ("phobos", "deimos"):
            stub = Measurement(t, "radec", [0.0, 0.0], np.eye(2), target=name)
            values.append(model.predict(stub, x) + sigma * rng.standard_normal(2))
        if pair:
            cov = sigma**2 * (np.eye(4) + 0.5 * np.kron([[0.0, 1.0], [1.0, 0.0]], np.eye(2)))
            records.append(Measurement(t, "radec_pair", np.concatenate(values), cov, target="phobos+deimos"))
        else:
            records += [Measurement(t, "radec", v, sigma**2 * np.eye(2), target=name)
                        for v, name in zip(values, ("phobos", "deimos"))]
    return records


@pytest.fixture(scope="module")
def arc():
    """S1-like cruise arc: truth every minute for 150 minutes, model, records, a 5000-km prior."""
    model = ProbeMeasurementModel("sun", ephemeris=default_cached_ephemeris(), target_position_sigma_km=1.0)
    dynamics = cruise_model()
    epochs = T0 + STEP_S * np.arange(1, 151)
    truth = FastPropagator(dynamics).trajectory(T0, probe_state(model), epochs).states
    rng = np.random.default_rng(35)
    P0 = np.diag([(5000.0 / np.sqrt(3.0)) ** 2] * 3 + [(0.005 / np.sqrt(3.0)) ** 2] * 3)
    x0 = probe_state(model) + np.sqrt(np.diag(P0)) * rng.standard_normal(6)
    return dict(model=model, dynamics=dynamics, epochs=epochs, truth=truth, prior=Estimate(T0, x0, P0),
                records=make_records(model, truth, epochs, rng),
                pairs=make_records(model, truth, epochs, rng, pair=True))


def hidden(function):
    """``function`` without its ``fast_propagator``: the filter then takes the general path."""
    return lambda *args: function(*args)


def ekf_pair(arc, *, model=None, process_noise=None, options=EKFOptions(), dynamics=None, prior=None):
    """(compiled, reference) EKFs on the same models."""
    dynamics = arc["dynamics"] if dynamics is None else dynamics
    propagator = force_model_propagator(dynamics)
    kwargs = dict(model=arc["model"] if model is None else model, process_noise=process_noise, options=options)
    prior = arc["prior"] if prior is None else prior
    return (ExtendedKalmanFilter(prior, propagator=propagator, **kwargs),
            ExtendedKalmanFilter(prior, propagator=hidden(propagator), **kwargs))


def ukf_pair(arc, *, model=None, process_noise=None, options=UKFOptions(gate_probability=1.0 - 1e-6), dynamics=None,
             prior=None):
    dynamics = arc["dynamics"] if dynamics is None else dynamics
    transition = force_model_transition(dynamics)
    kwargs = dict(model=arc["model"] if model is None else model, process_noise=process_noise, options=options)
    prior = arc["prior"] if prior is None else prior
    return (UnscentedKalmanFilter(prior, transition=transition, **kwargs),
            UnscentedKalmanFilter(prior, transition=hidden(transition), **kwargs))


def differences(a, b, predicted, H, *, unscented=False):
    """Largest differences of outcome ``a`` from the reference ``b``, each relative to what bounds its
    rounding: the state to ``|x|``, the covariance to ``sigma_i sigma_j``, the innovation to the
    measured value (it is ``z - h(x)``: one rounding of an angle of ~3 rad is 4e-16 rad, ~1e-9 of
    its 0.1" sigma), ``S`` to the rounding bound of ``H P H^T + R`` (``|H| |P| |H|^T + |R|``,
    elementwise) and the NIS, beyond its first-order change with the innovation's and ``S``'s
    (``2 sqrt(NIS q) + q + NIS |S^-1/2 dS S^-T/2|``, ``q = dnu^T S^-1 dnu``), to its own size.
    ``predicted`` is the prior at the record epoch, ``H`` (m, 6) the model's Jacobian there.

    ``unscented``: the sigma points come from the Cholesky factor of the prior, which rounding fixes
    only to ``eps cond(C)`` (``C`` its correlation matrix; S1's reaches 4e6), and their predicted
    angles are rounded to ``spacing(pi)`` (4e-16 rad; numpy's vectorised arctan2 and libm's differ by
    that in one call of 14) against a spread of ``sigma_h = sqrt(diag(H P H^T))``: the posterior
    covariance is compared in units of ``max(RTOL, 4 eps cond(C))``, ``S`` (the points' spread) of
    ``max(RTOL, 4 eps cond(C) + 4 spacing(pi) / sigma_h)``, times RTOL.
    """
    Pa, Pb = a.estimate.P, b.estimate.P
    sigma = np.sqrt(np.diag(Pb))
    P_scale = S_scale = 1.0
    if unscented:
        s = np.sqrt(np.diag(predicted.P))
        cholesky_floor = 4.0 * np.finfo(float).eps * np.linalg.cond(predicted.P / np.outer(s, s))
        angle_floor = 4.0 * np.spacing(np.pi) / np.min(np.sqrt(np.diag(H @ predicted.P @ H.T)))
        P_scale = max(1.0, cholesky_floor / RTOL)
        S_scale = max(1.0, (cholesky_floor + angle_floor) / RTOL)
    dnu = a.residual - b.residual
    q = float(dnu @ np.linalg.solve(b.residual_cov, dnu))
    root = np.linalg.inv(np.linalg.cholesky(b.residual_cov))
    dS = np.linalg.norm(root @ (a.residual_cov - b.residual_cov) @ root.T, 2)
    bound_S = np.abs(H) @ np.abs(predicted.P) @ np.abs(H).T + np.abs(b.residual_cov - H @ predicted.P @ H.T)
    return {
        "x": np.max(np.abs(a.estimate.x - b.estimate.x)) / np.max(np.abs(b.estimate.x)),
        "P": np.max(np.abs(Pa - Pb) / np.outer(sigma, sigma)) / P_scale,
        "nu": np.max(np.abs(dnu)) / np.pi,
        "S": np.max(np.abs(a.residual_cov - b.residual_cov) / bound_S) / S_scale,
        "nis": max(0.0, abs(a.nis - b.nis) - 2.0 * np.sqrt(b.nis * q) - q - b.nis * dS) / max(1.0, b.nis),
    }


def step_by_step(fast, reference, records, *, skip=0):
    """Both filters take every record from the reference's prior; the worst differences after ``skip``."""
    worst = {}
    for i, record in enumerate(records):
        fast.reset(reference.estimate)
        a = fast.update(record)
        predicted = reference.predict(record.t_tdb_s)  # what update does first
        H = reference.model.predict_and_jacobians(record, predicted.x[None])[1][0]
        b = reference.update(record)
        assert (a.accepted, a.reason, a.estimate.t_tdb_s) == (b.accepted, b.reason, b.estimate.t_tdb_s)
        if i >= skip and b.accepted:
            unscented = isinstance(fast, UnscentedKalmanFilter)
            for key, value in differences(a, b, predicted, H, unscented=unscented).items():
                worst[key] = max(worst.get(key, 0.0), value)
    return worst


def test_the_default_models_take_the_compiled_step_and_others_do_not(arc):
    fast, reference = ekf_pair(arc)
    assert fast._compiled_steps() is not None and reference._compiled_steps() is None
    assert ukf_pair(arc)[0]._compiled_steps() is not None
    exact = ExtendedKalmanFilter(arc["prior"], propagator=force_model_propagator(arc["dynamics"], exact=True),
                                 model=arc["model"])
    assert exact._compiled_steps() is None
    numpy_model = ProbeMeasurementModel("sun")  # the exact ephemeris: no compiled tables
    assert ekf_pair(arc, model=numpy_model)[0]._compiled_steps() is None
    offsets = TargetOffsetModel(ProbeMeasurementModel("sun", ephemeris=default_cached_ephemeris()), ["phobos"])
    prior = Estimate(T0, np.r_[arc["prior"].x, 0.0, 0.0, 0.0], np.diag(np.r_[np.diag(arc["prior"].P), 1.0, 1.0, 1.0]))
    augmented = ExtendedKalmanFilter(prior, propagator=force_model_propagator(arc["dynamics"]), model=offsets)
    assert augmented._compiled_steps() is None


@pytest.mark.parametrize("form", ["ekf", "ukf"])
@pytest.mark.parametrize("records", ["records", "pairs"])
def test_each_compiled_step_equals_the_pure_core(arc, form, records):
    fast, reference = (ekf_pair if form == "ekf" else ukf_pair)(arc)
    # the first records shrink a 5000-km prior by 1e4: the pure core's own rounding there is ~1e-11
    worst = step_by_step(fast, reference, arc[records], skip=20)
    assert max(worst.values()) < RTOL, worst


@pytest.mark.parametrize("form", ["ekf", "ukf"])
def test_whole_arc_agrees(arc, form):
    """Run on their own, the two paths are the same filter: estimates, covariances and NIS agree to a
    millionth of the filter's uncertainty over the arc (measured: 4e-8 sigma, 1e-8, 3e-7)."""
    fast, reference = (ekf_pair if form == "ekf" else ukf_pair)(arc)
    a, b = run_filter(fast, arc["records"]), run_filter(reference, arc["records"])
    assert a.accepted.all() and b.accepted.all()
    sigma = np.sqrt(np.diagonal(b.covariances, axis1=1, axis2=2))
    assert np.max(np.abs(a.states - b.states) / sigma) < 1e-6
    assert np.max(np.abs(a.covariances - b.covariances) / (sigma[:, :, None] * sigma[:, None, :])) < 1e-6
    assert np.max(np.abs(a.nis - b.nis)) < 1e-5
    np.testing.assert_array_equal(a.epochs, b.epochs)
    error = np.linalg.norm(a.states[-1, :3] - arc["truth"][-1, :3])
    assert error < 3.0 * np.sqrt(np.trace(a.covariances[-1, :3, :3]))


@pytest.mark.parametrize("noise", [WhiteAcceleration(1e-12), StateNoiseCompensation((1e-12, 2e-12, 3e-12))])
@pytest.mark.parametrize("form", ["ekf", "ukf"])
def test_process_noise_is_the_pure_cores(arc, form, noise):
    fast, reference = (ekf_pair if form == "ekf" else ukf_pair)(arc, process_noise=noise)
    worst = step_by_step(fast, reference, arc["records"][:80], skip=20)
    assert max(worst.values()) < RTOL, worst


@pytest.mark.parametrize("light_time, aberration, sigma_km", [(False, True, 1.0), (True, False, 0.0),
                                                              (False, False, 5.0)])
@pytest.mark.parametrize("form", ["ekf", "ukf"])
def test_model_switches_are_the_models(arc, form, light_time, aberration, sigma_km):
    model = ProbeMeasurementModel("sun", ephemeris=default_cached_ephemeris(), light_time=light_time,
                                  aberration=aberration, target_position_sigma_km=sigma_km)
    fast, reference = (ekf_pair if form == "ekf" else ukf_pair)(arc, model=model, options=(
        EKFOptions(gate_probability=None) if form == "ekf" else UKFOptions()))
    assert fast._compiled_steps() is not None
    worst = step_by_step(fast, reference, arc["records"][:60], skip=20)
    assert max(worst.values()) < RTOL, worst


@pytest.mark.parametrize("form", ["ekf", "ukf"])
def test_a_mars_centred_state(arc, form):
    """Centre other than the Sun (the model adds Mars' SSB state; the propagator integrates about Mars).

    Without the ephemeris term: it takes the difference of SSB positions (2e8 km, rounded to 3e-8 km)
    over a 3e4-km line of sight, so either path has it only to ~2e-12."""
    model = ProbeMeasurementModel("mars", ephemeris=default_cached_ephemeris())
    dynamics = capture_model_2()
    x0 = np.array([30_000.0, -8000.0, 4000.0, 0.5, 1.2, -0.3])
    epochs = T0 + STEP_S * np.arange(1, 41)
    truth = FastPropagator(dynamics).trajectory(T0, x0, epochs).states
    records = make_records(model, truth, epochs, np.random.default_rng(8), sigma=10.0 * ARCSEC)
    P0 = np.diag([1.0**2] * 3 + [1e-5**2] * 3)
    prior = Estimate(T0, x0 + np.sqrt(np.diag(P0)) * np.random.default_rng(9).standard_normal(6), P0)
    fast, reference = (ekf_pair if form == "ekf" else ukf_pair)(arc, model=model, dynamics=dynamics, prior=prior)
    worst = step_by_step(fast, reference, records, skip=10)
    assert max(worst.values()) < RTOL, worst


def bad_records(arc):
    """Good records with, after some, a bad one of the same epoch: every refusal the general path
    gives (bad values, non-PD or asymmetric covariance, the gate, the filter's past) and a record it
    cannot even model (no target: it raises)."""
    good = arc["records"][:40]
    bad = {
        11: replace(good[11], value=np.array([np.nan, 0.1])),
        15: replace(good[15], covariance=np.array([[1.0, 2.0], [2.0, 1.0]]) * SIGMA**2),
        17: replace(good[17], covariance=np.array([[1.0, 0.5], [0.4, 1.0]]) * SIGMA**2),
        21: replace(good[21], value=good[21].value + 100.0 * SIGMA),
        25: replace(good[25], t_tdb_s=good[25].t_tdb_s - 600.0),
        27: replace(good[27], target=" "),
    }
    return [r for i, record in enumerate(good) for r in ((record, bad[i]) if i in bad else (record,))]


@pytest.mark.parametrize("form", ["ekf", "ukf"])
def test_refusals_are_the_general_paths(arc, form, caplog):
    fast, reference = (ekf_pair if form == "ekf" else ukf_pair)(arc)
    records = bad_records(arc)
    with caplog.at_level(logging.WARNING, logger="opnav.filters.base"):
        outcomes = []
        for record in records:
            fast.reset(reference.estimate)
            try:
                b = reference.update(record)
            except Exception as exc:  # the general path raises (no target): so must the compiled filter
                with pytest.raises(type(exc)):
                    fast.update(record)
                continue
            a = fast.update(record)
            outcomes.append(b)
            assert (a.accepted, a.reason, a.estimate.t_tdb_s) == (b.accepted, b.reason, b.estimate.t_tdb_s)
            if not a.accepted:
                np.testing.assert_array_equal(a.estimate.x, b.estimate.x)
    reasons = [o.reason for o in outcomes if not o.accepted]
    assert len(reasons) == 5 and any("chi-square gate" in r for r in reasons), reasons
    assert any("time goes backwards" in r for r in reasons) and any("NaN" in r for r in reasons)


@pytest.mark.parametrize("form", ["ekf", "ukf"])
def test_checked_run_on_the_compiled_path(arc, form):
    fast, _ = (ekf_pair if form == "ekf" else ukf_pair)(arc)
    history = run_filter(fast, arc["pairs"][:30], checked=True)
    assert history.accepted.all() and history.health["records_checked"] == 30
    assert history.health["max_asymmetry"] == 0.0


def test_the_square_root_ukf_keeps_its_own_steps(arc):
    from opnav.filters.sr_ukf import SquareRootUKF

    sr = SquareRootUKF(arc["prior"], transition=force_model_transition(arc["dynamics"]), process_noise=None,
                       model=arc["model"])
    assert sr._compiled_steps() is None
