"""Two moons of one frame as one radec_pair record: the attitude error they share as a cross-covariance."""

from dataclasses import replace

import numpy as np
import pytest

from opnav.epochs import parse_epoch
from opnav.ephemeris.cache import default_cached_ephemeris
from opnav.errors import InputError
from opnav.filters.base import Estimate
from opnav.filters.ekf import ekf_update
from opnav.measurements import ProbeMeasurementModel
from opnav.records import (
    ATTITUDE_COVARIANCE,
    ATTITUDE_JACOBIAN,
    Measurement,
    join_frame_radec,
    read_csv,
    split_radec_pairs,
    write_csv,
)

T = parse_epoch("2014-07-15T00:00:00", scale="tdb")
ARCSEC = np.pi / 648_000.0


def _probe_state(model):
    """A probe 20 million km from Mars (heliocentric ICRF, km and km/s), as in S1's July arc."""
    r_sun, v_sun = model.ephemeris.state("sun", T, center="ssb")
    r_mars, v_mars = model.ephemeris.state("mars", T, center="ssb")
    return np.concatenate([r_mars - r_sun + np.array([1.5e7, 1.2e7, 5e6]), v_mars - v_sun + np.array([-3.0, 1.0, 0.5])])


def _frame_records(model, x, rng, *, frame_id="frame_00001"):
    """Both moons' records of one frame with attitude Jacobians and covariance, as the image stage gives."""
    cov_att = np.diag([0.02, 0.015, 0.4]) ** 2 * ARCSEC**2 * 100
    records = []
    # the moons lie near the boresight, a small rotation moves both alike: nearly one Jacobian
    common = rng.normal(size=(2, 3))
    for name in ("phobos", "deimos"):
        stub = Measurement(T, "radec", [0.0, 0.0], np.eye(2), target=name)
        ra, dec = model.predict(stub, x)
        jac = common + 0.05 * rng.normal(size=(2, 3))
        cov = jac @ cov_att @ jac.T + np.diag([0.03, 0.03]) ** 2 * ARCSEC**2
        records.append(Measurement(T, "radec", [ra, dec], cov, target=name, sensor="nac", frame_id=frame_id, flags=8,
                                   extra={ATTITUDE_JACOBIAN: jac, ATTITUDE_COVARIANCE: cov_att}))
    return records, cov_att


@pytest.fixture(scope="module")
def model():
    return ProbeMeasurementModel("sun", ephemeris=default_cached_ephemeris(), target_position_sigma_km=1.0)


def test_join_puts_the_shared_attitude_term_off_the_diagonal_and_split_undoes_it(model):
    x = _probe_state(model)
    (phobos, deimos), cov_att = _frame_records(model, x, np.random.default_rng(1))
    lone = replace(phobos, frame_id="frame_00002")  # one moon in its frame: left as it is
    plain = replace(deimos, frame_id="frame_00003", extra={})  # no attitude terms (read from a file)
    joined = join_frame_radec([phobos, lone, deimos, plain])
    assert [r.kind for r in joined] == ["radec_pair", "radec", "radec"]
    pair = joined[0]
    assert pair.target == "phobos+deimos" and pair.frame_id == "frame_00001" and pair.flags == 8
    np.testing.assert_array_equal(pair.value, np.concatenate([phobos.value, deimos.value]))
    cross = phobos.extra[ATTITUDE_JACOBIAN] @ cov_att @ deimos.extra[ATTITUDE_JACOBIAN].T
    np.testing.assert_allclose(pair.covariance[:2, 2:], cross, rtol=1e-12)
    np.testing.assert_allclose(pair.covariance[:2, :2], phobos.covariance, rtol=1e-12)
    assert pair.problem() is None  # a joint covariance of a shared term plus independent ones is PD
    back = split_radec_pairs(joined)
    assert [(r.kind, r.target) for r in back] == [("radec", "phobos"), ("radec", "deimos"), ("radec", "phobos"),
                                                  ("radec", "deimos")]
    np.testing.assert_array_equal(back[1].value, deimos.value)
    np.testing.assert_allclose(back[1].covariance, deimos.covariance, rtol=1e-12)


def test_pair_survives_a_csv_round_trip(model, tmp_path):
    x = _probe_state(model)
    records, _ = _frame_records(model, x, np.random.default_rng(2))
    pair = join_frame_radec(records)
    write_csv(tmp_path / "m.csv", pair)
    read = read_csv(tmp_path / "m.csv")
    assert read[0].kind == "radec_pair" and read[0].target == "phobos+deimos"
    np.testing.assert_array_equal(read[0].value, pair[0].value)
    np.testing.assert_array_equal(read[0].covariance, pair[0].covariance)


def test_a_pair_must_name_two_targets():
    with pytest.raises(InputError, match="two bodies"):
        Measurement(T, "radec_pair", np.zeros(4), np.eye(4), target="phobos")


def test_pair_model_is_the_two_radec_models_stacked_with_a_jacobian_that_matches_differences(model):
    x = _probe_state(model)
    pair = join_frame_radec(_frame_records(model, x, np.random.default_rng(3))[0])[0]
    parts = split_radec_pairs([pair])
    predicted, H = model.predict_and_jacobians(pair, x[None])
    np.testing.assert_array_equal(predicted[0], np.concatenate([model.predict(p, x) for p in parts]))
    np.testing.assert_array_equal(H[0], np.vstack([model.jacobian(p, x) for p in parts]))
    # central differences: 1 km in position, 1 m/s in velocity
    steps = np.array([1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])
    numeric = np.stack([(model.predict(pair, x + d) - model.predict(pair, x - d)) / (2 * h)
                        for d, h in zip(np.diag(steps), steps)], axis=-1)
    # (atol: entries below 1e-12 rad per km or per km/s are zero to the differences)
    np.testing.assert_allclose(H[0][:, :6], numeric, rtol=1e-5, atol=1e-12)
    # the ephemeris error of each moon is its own: the extra covariance has no cross block
    R = model.noise_covariance(pair, x)
    np.testing.assert_array_equal(R[:2, 2:], pair.covariance[:2, 2:])
    np.testing.assert_allclose(R[2:, 2:], model.noise_covariance(parts[1], x), rtol=1e-12)
    # right ascensions wrap in the residual
    wrapped = model.residual(replace(pair, value=pair.value + np.array([2 * np.pi, 0, -2 * np.pi, 0])), predicted[0])
    np.testing.assert_allclose(wrapped, pair.value - predicted[0], atol=1e-9)


def test_ekf_on_a_pair_without_cross_terms_equals_the_two_records_in_turn(model):
    x = _probe_state(model)
    records, _ = _frame_records(model, x, np.random.default_rng(4))
    rng = np.random.default_rng(5)
    records = [replace(r, value=r.value + 0.05 * ARCSEC * rng.standard_normal(2)) for r in records]
    prior = Estimate(T, x + np.array([200.0, -150.0, 80.0, 0.0, 0.0, 0.0]), np.diag([500.0] * 3 + [1e-3] * 3) ** 2)
    first = ekf_update(prior, records[0], model=model)
    sequential = ekf_update(first.estimate, records[1], model=model)
    pair = join_frame_radec(records)[0]
    independent = replace(pair, covariance=np.block([[records[0].covariance, np.zeros((2, 2))],
                                                     [np.zeros((2, 2)), records[1].covariance]]))
    joint = ekf_update(prior, independent, model=model)
    assert first.accepted and sequential.accepted and joint.accepted
    # the two differ only by the relinearisation after the first record: metres in 20 million km
    np.testing.assert_allclose(joint.estimate.x[:3], sequential.estimate.x[:3], rtol=0, atol=0.01)
    # (and the Jacobian by the first update's move over the range, ~1e-5)
    np.testing.assert_allclose(joint.estimate.P, sequential.estimate.P, rtol=1e-4, atol=1e-12)


def test_the_pair_keeps_the_ekf_consistent_where_two_independent_records_do_not(model):
    """Errors drawn with the shared attitude term: one update by the pair gives NEES chi-square(6);
    the same values as two independent records give an overconfident posterior."""
    from opnav.consistency import chi2_mean_bounds

    x = _probe_state(model)
    records, _ = _frame_records(model, x, np.random.default_rng(6))
    pair = join_frame_radec(records)[0]
    R = model.noise_covariance(pair, x)
    truth_value = model.predict(pair, x)
    P = np.diag([500.0] * 3 + [1e-3] * 3) ** 2
    rng = np.random.default_rng(7)
    draws = 300
    nees = {"pair": [], "independent": []}
    for _ in range(draws):
        prior = Estimate(T, x + np.linalg.cholesky(P) @ rng.standard_normal(6), P)
        measured = replace(pair, value=truth_value + np.linalg.cholesky(R) @ rng.standard_normal(4))
        joint = ekf_update(prior, measured, model=model).estimate
        first, second = split_radec_pairs([measured])
        one = ekf_update(prior, first, model=model).estimate
        both = ekf_update(one, second, model=model).estimate
        for name, post in (("pair", joint), ("independent", both)):
            error = post.x - x
            nees[name].append(float(error @ np.linalg.solve(post.P, error)))
    low, high = chi2_mean_bounds(6, draws, 0.999)
    assert low <= np.mean(nees["pair"]) <= high
    assert np.mean(nees["independent"]) > high
