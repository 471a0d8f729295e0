"""Moon-ephemeris error as a constant offset: the augmented measurement model, consider EKF, scenario setting."""

import numpy as np
import pytest
from test_measurements import numeric_jacobian

from opnav.dynamics import cruise_model
from opnav.epochs import parse_epoch
from opnav.errors import InputError
from opnav.filters.base import Estimate
from opnav.filters.ekf import EKFOptions, ExtendedKalmanFilter, force_model_propagator
from opnav.filters.factory import build_filter, measurement_model
from opnav.measurements import ProbeMeasurementModel, TargetOffsetModel, simulate_radec
from opnav.filters.options import navigation_from_dict
from opnav.records import Measurement

T0 = parse_epoch("2014-07-10T00:00:00", scale="tdb")
BASE = ProbeMeasurementModel("sun")


def probe_state():
    r_mars, v_mars = BASE.ephemeris.state("mars", T0, center="sun")
    return np.concatenate([r_mars + np.array([-1.5e7, 1.0e7, 0.6e7]), v_mars + np.array([2.0, -1.5, 0.7])])


def test_offset_moves_the_target_and_its_jacobian_is_minus_the_probe_s():
    model = TargetOffsetModel(BASE, ["phobos", "deimos"])
    offset = np.array([30.0, -20.0, 10.0])
    x = np.concatenate([probe_state(), np.zeros(3), offset])
    record = Measurement(T0, "radec", [0.0, 0.0], np.eye(2) * 1e-12, target="deimos")
    # the truth path of the S1 campaign: the target itself displaced (noise-free draw)
    moved = simulate_radec(BASE, "deimos", np.array([T0]), probe_state()[None], sigma_rad=1e-300,
                           rng=np.random.default_rng(0), target_offset_km=offset)[0]
    np.testing.assert_allclose(model.predict(record, x), moved, rtol=0, atol=1e-12)
    jac = model.jacobian(record, x)
    steps = np.array([1.0] * 3 + [1e-3] * 3 + [1.0] * 6)
    numeric = numeric_jacobian(lambda s: model.predict(record, s), x, steps)
    np.testing.assert_allclose(jac, numeric, rtol=1e-6, atol=1e-6 * np.abs(jac).max())
    np.testing.assert_array_equal(jac[:, 6:9], 0.0)  # Phobos' offset does not move Deimos
    with pytest.raises(InputError, match="12 entries"):
        model.predict(record, probe_state())


def test_consider_parameters_keep_their_estimate_and_inflate_the_state_covariance():
    model = TargetOffsetModel(BASE, ["deimos"])
    truth = probe_state()
    P0 = np.diag([300.0**2] * 3 + [3e-4**2] * 3 + [1.0] * 3)
    x0 = np.concatenate([truth + np.array([200.0, -100.0, 50.0, 0, 0, 0]), np.zeros(3)])
    rng = np.random.default_rng(1)
    epochs = T0 + 600.0 * np.arange(1, 13)
    filters = {}
    for name, consider in (("estimate", ()), ("consider", (6, 7, 8))):
        ekf = ExtendedKalmanFilter(Estimate(T0, x0, P0), propagator=force_model_propagator(cruise_model()),
                                   model=model, options=EKFOptions(consider=consider))
        for t in epochs:
            state = ekf.estimate.x.copy()
            state[6:] = 0.0
            z = model.predict(Measurement(t, "radec", [0, 0], np.eye(2), target="deimos"), state)
            ekf.update(Measurement(t, "radec", z + 2e-7 * rng.standard_normal(2), np.eye(2) * 4e-14, target="deimos"))
        filters[name] = ekf.estimate
    consider = filters["consider"]
    np.testing.assert_array_equal(consider.x[6:], 0.0)
    np.testing.assert_allclose(consider.P[6:, 6:], P0[6:, 6:])
    # not learning the offsets costs information: the considered position covariance is larger
    assert np.all(np.linalg.eigvalsh(consider.P[:3, :3] - filters["estimate"].P[:3, :3]) > -1e-9)
    with pytest.raises(InputError, match="augmented"):
        EKFOptions(consider=(2,))


def test_scenario_setting_builds_the_augmented_filters():
    section = {"epoch": "2014-07-10T00:00:00", "epoch_scale": "tdb", "dynamics": "cruise",
               "position_km": probe_state()[:3].tolist(), "velocity_km_s": probe_state()[3:].tolist(),
               "sigma_position_km": 300.0, "sigma_velocity_km_s": 3e-4, "target_position_sigma_km": 1.0,
               "ephemeris_error": "consider", "ephemeris_targets": ["phobos", "deimos"]}
    nav = navigation_from_dict(section)
    model = measurement_model(nav, "sun")
    assert isinstance(model, TargetOffsetModel) and model.model.target_position_sigma_km == 0.0
    ekf = build_filter("ekf", nav, model, cruise_model())
    assert ekf.estimate.x.size == 12 and ekf.options.consider == tuple(range(6, 12))
    np.testing.assert_allclose(np.diag(ekf.estimate.P)[6:], 1.0)
    with pytest.raises(InputError, match="works with filter = .ekf. only"):
        navigation_from_dict({**section, "filter": "ukf"})
    with pytest.raises(InputError, match="ephemeris_error must be"):
        navigation_from_dict({**section, "ephemeris_error": "bias"})
    ukf = build_filter("ukf", navigation_from_dict({**section, "ephemeris_error": "estimate"}), model, cruise_model())
    assert ukf.estimate.x.size == 12


def test_navigation_values_of_the_wrong_type_are_named():
    base = {"epoch": "2014-07-10T00:00:00", "epoch_scale": "tdb", "dynamics": "cruise",
            "position_km": [1.0e8, 0.0, 0.0], "velocity_km_s": [0.0, 30.0, 0.0],
            "sigma_position_km": 300.0, "sigma_velocity_km_s": 3e-4}
    navigation_from_dict(base, "nav.toml")
    for key, value, message in (("gate_probability", "high", "gate_probability must be float"),
                                ("target_position_sigma_km", "big", "target_position_sigma_km must be float"),
                                ("seed", 1.5, "seed must be int")):
        with pytest.raises(InputError, match=message):
            navigation_from_dict({**base, key: value}, "nav.toml")
    # a TOML string "false" is not false: it must not silently turn light time on
    with pytest.raises(InputError, match="light_time must be true or false"):
        navigation_from_dict({**base, "corrections": {"light_time": "false"}}, "nav.toml")
