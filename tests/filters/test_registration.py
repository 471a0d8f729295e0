"""Time registration: Lagrange accuracy, registered covariance, and a shortened S4 run in which
fusion without registration is biased while registered fusion stays inside its 3 sigma."""

import numpy as np
import pytest
from scipy import stats

from opnav.dynamics import propagate
from opnav.dynamics.models import two_body_model
from opnav.ephemeris import default_ephemeris
from opnav.epochs import parse_epoch
from opnav.errors import InputError
from opnav.filters.base import Estimate
from opnav.filters.federated import FederatedFilter, FederatedOptions, run_federated
from opnav.filters.noise import WhiteAcceleration
from opnav.filters.registration import (
    hold_latest,
    lagrange3,
    lagrange_weights,
    register,
)
from opnav.filters.ukf import UKFOptions, UnscentedKalmanFilter, force_model_transition
from opnav.measurements import ProbeMeasurementModel
from opnav.records import FLAG_REGISTERED, Measurement


@pytest.mark.parametrize("t", [0.3, 1.5, 2.0, 3.7, -1.0])
def test_lagrange_is_exact_for_quadratics_and_has_the_cubic_remainder(t):
    nodes = np.array([0.0, 1.0, 2.5])
    quad = lambda s: np.stack([2.0 - 3.0 * s + 0.5 * s**2, 4.0 * s], -1)
    np.testing.assert_allclose(lagrange3(nodes, quad(nodes), t), quad(t), rtol=0, atol=1e-12)
    assert lagrange_weights(nodes, t).sum() == pytest.approx(1.0, abs=1e-14)
    # remainder of a cubic: f'''/6 * prod (t - t_j), with f''' = 6 for s^3
    cubic = nodes**3
    np.testing.assert_allclose(lagrange3(nodes, cubic[:, None], t)[0], t**3 - np.prod(t - nodes), atol=1e-12)


def test_lagrange_rejects_bad_nodes():
    with pytest.raises(InputError, match="distinct"):
        lagrange_weights(np.array([0.0, 1.0, 1.0]), 0.5)
    with pytest.raises(InputError, match="three"):
        lagrange_weights(np.array([0.0, 1.0]), 0.5)


def line_stream(rng, times, sigma, velocity=np.array([25.0, -3.0, 1.0])):
    """Position records of a probe in uniform motion (km, km/s) with noise ``sigma`` (km)."""
    truth = lambda t: np.array([1.0e8, 2.0e7, -5.0e6]) + velocity * t
    return truth, [Measurement(t, "position", truth(t) + sigma * rng.standard_normal(3), sigma**2 * np.eye(3),
                               target="sun", sensor="angle") for t in times]


@pytest.mark.parametrize("causal", [True, False])
def test_registered_values_are_unbiased_with_honest_covariance(causal):
    """NEES of registered values against the truth at the epochs ~ chi2(3) (sparse epochs: no shared nodes)."""
    rng = np.random.default_rng(1)
    times = 60.0 * np.arange(2000) - 30.0
    truth, records = line_stream(rng, times, 2.0)
    epochs = 60.0 * 5 * np.arange(1, 390)  # every fifth sample interval: no node is used twice
    registered = register(records, epochs, causal=causal)
    assert len(registered) == epochs.size
    nees = [(r.value - truth(r.t_tdb_s)) @ np.linalg.solve(r.covariance, r.value - truth(r.t_tdb_s)) for r in registered]
    lo, hi = stats.chi2.ppf([0.005, 0.995], 3 * len(nees)) / len(nees)
    assert lo < np.mean(nees) < hi
    assert all(r.flags & FLAG_REGISTERED for r in registered)
    expected_weights = (1.875, -1.25, 0.375) if causal else (-0.125, 0.75, 0.375)  # ties go to the earlier sample
    order = np.argsort(-np.asarray(registered[0].extra["node_epochs_tdb_s"])) if causal else np.arange(3)
    np.testing.assert_allclose(np.asarray(registered[0].extra["lagrange_weights"])[order], expected_weights)


def test_shared_nodes_inflate_covariance_and_exact_epochs_pass_through():
    rng = np.random.default_rng(2)
    times = 60.0 * np.arange(20) - 30.0
    _, records = line_stream(rng, times, 2.0)
    dense = register(records, 60.0 * np.arange(3, 18), causal=True)
    weights = np.asarray(dense[5].extra["lagrange_weights"])
    # each sample is a node of three registered records: covariance x3
    np.testing.assert_allclose(dense[5].covariance, 3 * np.sum(weights**2) * 4.0 * np.eye(3))
    exact = register(records, np.array([times[7]]), causal=True)
    assert exact[0] is records[7]


def test_hold_latest_has_the_lead_bias():
    rng = np.random.default_rng(3)
    lead = 30.0
    velocity = np.array([25.0, -3.0, 1.0])
    truth, records = line_stream(rng, 60.0 * np.arange(50) - lead, 1e-9, velocity)
    held = hold_latest(records, 60.0 * np.arange(1, 49))
    assert len(held) == 48 and not any(r.flags & FLAG_REGISTERED for r in held)
    for r in held:
        np.testing.assert_allclose(r.value - truth(r.t_tdb_s), -velocity * lead, atol=1e-6)


def test_registration_input_errors():
    rng = np.random.default_rng(4)
    _, records = line_stream(rng, np.array([0.0, 60.0, 120.0]), 1.0)
    with pytest.raises(InputError, match="increasing"):
        register(records, np.array([100.0, 50.0]))
    with pytest.raises(InputError, match="share the epoch"):
        register(records + [records[0]], np.array([100.0]))
    assert register(records, np.array([1000.0]), max_extrapolation_s=120.0) == []


# ---------------------------------------------------------------- shortened S4
STARS = {1: (np.array([-0.0653, 0.6034, -0.7948]), 20.3), 2: (np.array([0.1257, -0.7695, 0.6261]), -13.5)}


def s4_short_run(registered: bool, hours: float = 4.0, lead_s: float = 30.0):
    """Sun two-body approach arc; position pseudo-measurements (1000 km) lead the Doppler clock by ``lead_s``."""
    rng = np.random.default_rng(5)
    eph = default_ephemeris()
    t0 = parse_epoch("2021-01-15T05:46:07", scale="utc")
    r_mars, v_mars = eph.state("mars", t0, center="sun")
    x0 = np.concatenate([r_mars + np.array([3.0e6, -2.0e6, 1.0e6]), v_mars + np.array([0.8, -0.5, 0.3])])
    model = two_body_model("sun")
    epochs = t0 + 60.0 * np.arange(1, int(hours * 60) + 1)
    angle_times = epochs - lead_s
    truth = propagate(model, t0, x0, np.concatenate([angle_times, epochs[-1:]])).states
    sigma_r = 1000.0
    positions = [Measurement(t, "position", x[:3] + sigma_r * rng.standard_normal(3), sigma_r**2 * np.eye(3),
                             target="sun", sensor="angle") for t, x in zip(angle_times, truth[:-1])]
    meas_model = ProbeMeasurementModel("sun", light_time=False, aberration=False,
                                       star_radial_velocity_km_s={k: v for k, (_, v) in STARS.items()})
    truth_at = dict(zip(epochs, propagate(model, t0, x0, epochs).states))
    dopplers = []
    for t in epochs[9::10]:
        for star_id, target, direction in [(0, "sun", np.array([1.0, 0.0, 0.0]))] + [
            (k, f"HIP{k}", d / np.linalg.norm(d)) for k, (d, _) in STARS.items()
        ]:
            rec = Measurement(t, "radial_velocity", [0.0], [[1e-6]], target=target, sensor="velocity",
                              star_id=star_id, star_unit_icrf=direction)
            value = meas_model.predict(rec, truth_at[t]) + 1e-3 * rng.standard_normal(1)
            dopplers.append(Measurement(t, "radial_velocity", value, [[1e-6]], target=target, sensor="velocity",
                                        star_id=star_id, star_unit_icrf=direction))
    angle = register(positions, epochs, causal=True) if registered else hold_latest(positions, epochs)
    P0 = np.diag([1000.0**2] * 3 + [0.1**2] * 3)
    x_start = x0 + np.array([1000.0, 1000.0, 1000.0, 0.1, 0.1, 0.1])
    transition = force_model_transition(model)
    noise = WhiteAcceleration(1e-18)
    locals_ = {name: UnscentedKalmanFilter(Estimate(t0, x_start, P0), transition=transition, process_noise=noise,
                                           model=meas_model, options=UKFOptions(alpha=1e-3))
               for name in ("angle", "velocity")}
    federated = FederatedFilter(locals_, initial=Estimate(t0, x_start, P0),
                                options=FederatedOptions(betas={"angle": 0.5, "velocity": 0.5},
                                                         routes={"angle": "angle", "velocity": "velocity"}))
    fused, _ = run_federated(federated, angle + dopplers, epochs)
    error = fused[-1].x[:3] - truth[-1][:3]
    return error, np.sqrt(np.diag(fused[-1].P)[:3])


def test_s4_short_registered_fusion_converges_unregistered_is_biased():
    error_reg, sigma_reg = s4_short_run(registered=True)
    error_raw, sigma_raw = s4_short_run(registered=False)
    assert np.all(np.abs(error_reg) < 3.0 * sigma_reg), (error_reg, sigma_reg)
    assert np.linalg.norm(error_raw) > 2.0 * np.linalg.norm(error_reg)
    assert np.any(np.abs(error_raw) > 3.0 * sigma_raw), (error_raw, sigma_raw)
