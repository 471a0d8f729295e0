"""Federated filter: with fusion-reset at every epoch it is the centralised Kalman filter
(Carlson 1990), no-reset locals are stand-alone filters, options are validated."""

import numpy as np
import pytest
from test_ukf import FixedNoise, PositionModel, assert_gaussians_close, cv_transition

from opnav.errors import InputError
from opnav.filters.base import Estimate
from opnav.filters.federated import (
    FederatedFilter,
    FederatedOptions,
    ScaledNoise,
    fuse,
    run_federated,
)
from opnav.filters.ukf import UKFOptions, UnscentedKalmanFilter
from opnav.records import Measurement

Q = np.diag([1e-3, 1e-3, 1e-3, 1e-7, 1e-7, 1e-7])
X0 = np.array([100.0, -50.0, 20.0, 0.1, 0.2, -0.05])
P0 = np.diag([25.0, 25.0, 25.0, 1e-4, 1e-4, 1e-4])
BETAS = {"a": 0.3, "b": 0.7}


def make_ukf(noise=Q):
    return UnscentedKalmanFilter(Estimate(0.0, X0, P0), transition=cv_transition, process_noise=FixedNoise(noise),
                                 model=PositionModel(), options=UKFOptions(alpha=0.5))


def sensor_records(rng, steps=20):
    """Sensor 'a' (noisy, 3 km) and 'b' (1 km, every other epoch) position records, same epochs."""
    records = []
    for k in range(1, steps + 1):
        t = 60.0 * k
        records.append(Measurement(t, "position", X0[:3] + 3 * rng.standard_normal(3), 9 * np.eye(3), sensor="a"))
        if k % 2 == 0:
            records.append(Measurement(t, "position", X0[:3] + rng.standard_normal(3), np.eye(3), sensor="b"))
    return records


def test_fusion_reset_equals_centralised_filter():
    rng = np.random.default_rng(1)
    records = sensor_records(rng)
    options = FederatedOptions(betas=BETAS, routes={"a": "a", "b": "b"}, mode="fusion-reset")
    federated = FederatedFilter({"a": make_ukf(), "b": make_ukf()}, initial=Estimate(0.0, X0, P0), options=options)
    central = make_ukf()
    epochs = 60.0 * np.arange(1, 21)
    fused, outcomes = run_federated(federated, records, epochs)
    assert all(o.accepted for o in outcomes)
    i = 0
    for t, estimate in zip(epochs, fused):
        while i < len(records) and records[i].t_tdb_s <= t:
            central.update(records[i])
            i += 1
        assert_gaussians_close(estimate.x, estimate.P, central.estimate.x, central.estimate.P, 1e-9)
    # after the reset every local holds the global state with P_g / beta_i
    for name, local in federated.locals.items():
        np.testing.assert_allclose(local.estimate.P, federated.estimate.P / BETAS[name], rtol=1e-12)


def test_no_reset_locals_are_stand_alone_filters():
    rng = np.random.default_rng(2)
    records = sensor_records(rng)
    options = FederatedOptions(betas=BETAS, routes={"a": "a", "b": "b"}, mode="no-reset")
    federated = FederatedFilter({"a": make_ukf(), "b": make_ukf()}, initial=Estimate(0.0, X0, P0), options=options)
    fused, _ = run_federated(federated, records, 60.0 * np.arange(1, 21))
    for name in ("a", "b"):
        alone = UnscentedKalmanFilter(Estimate(0.0, X0, P0 / BETAS[name]), transition=cv_transition,
                                      process_noise=FixedNoise(Q / BETAS[name]), model=PositionModel(),
                                      options=UKFOptions(alpha=0.5))
        for t in 60.0 * np.arange(1, 21):  # same steps as the federated run (Q is per step)
            for rec in records:
                if rec.sensor == name and rec.t_tdb_s == t:
                    alone.update(rec)
            alone.predict(t)
        assert_gaussians_close(federated.locals[name].estimate.x, federated.locals[name].estimate.P,
                               alone.estimate.x, alone.estimate.P, 1e-9)
    # the fused estimate is the information sum of the two, tighter than either local
    assert np.all(np.diag(fused[-1].P) < np.diag(federated.locals["b"].estimate.P))


def test_scaled_noise_and_fuse():
    noise = ScaledNoise(FixedNoise(Q), 1 / 0.25)
    np.testing.assert_allclose(noise.discrete(60.0, X0), 4 * Q)
    a = Estimate(5.0, np.array([1.0, 0, 0, 0, 0, 0]), np.eye(6))
    b = Estimate(5.0, np.array([3.0, 0, 0, 0, 0, 0]), np.eye(6))
    g = fuse([a, b])
    np.testing.assert_allclose(g.x[0], 2.0)
    np.testing.assert_allclose(g.P, 0.5 * np.eye(6))
    with pytest.raises(InputError, match="one epoch"):
        fuse([a, Estimate(6.0, b.x, b.P)])


def test_bad_options_and_unrouted_sensor():
    with pytest.raises(InputError, match="sum to 1"):
        FederatedOptions(betas={"a": 0.5, "b": 0.6}, routes={})
    with pytest.raises(InputError, match="positive"):
        FederatedOptions(betas={"a": 1.5, "b": -0.5}, routes={})
    with pytest.raises(InputError, match="mode"):
        FederatedOptions(betas={"a": 1.0}, routes={}, mode="sometimes")
    with pytest.raises(InputError, match="without a beta"):
        FederatedOptions(betas={"a": 1.0}, routes={"x": "c"})
    with pytest.raises(InputError, match="factor"):
        ScaledNoise(FixedNoise(Q), 0.0)
    options = FederatedOptions(betas={"a": 1.0}, routes={"a": "a"})
    federated = FederatedFilter({"a": make_ukf()}, initial=Estimate(0.0, X0, P0), options=options)
    out = federated.update(Measurement(60.0, "position", X0[:3], np.eye(3), sensor="star-tracker"))
    assert not out.accepted and "star-tracker" in out.reason


def test_duplicated_records_are_refused_not_counted_twice():
    rng = np.random.default_rng(3)
    records = sensor_records(rng, steps=6)
    options = FederatedOptions(betas=BETAS, routes={"a": "a", "b": "b"}, mode="fusion-reset")
    epochs = 60.0 * np.arange(1, 7)
    once = FederatedFilter({"a": make_ukf(), "b": make_ukf()}, initial=Estimate(0.0, X0, P0), options=options)
    twice = FederatedFilter({"a": make_ukf(), "b": make_ukf()}, initial=Estimate(0.0, X0, P0), options=options)
    fused_once, _ = run_federated(once, records, epochs)
    fused_twice, outcomes = run_federated(twice, records + records, epochs)
    assert sum(not o.accepted for o in outcomes) == len(records)
    assert all("duplicate" in o.reason for o in outcomes if not o.accepted)
    np.testing.assert_array_equal(fused_twice[-1].P, fused_once[-1].P)
