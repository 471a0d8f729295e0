"""The calibrated camera's parameter errors as consider parameters of the EKF (Schmidt; issue 39).

A camera calibrated from a few stars leaves an error ``dc`` of its parameters that moves every moon
record, relative to its frame's stars, by ``J dc``: one bias over the whole arc. The records keep
``J`` (the image stage); ``[navigation] camera_error = "consider"`` appends ``dc`` to the state with
the calibration's covariance and gives it no gain (:class:`opnav.measurements.CameraOffsetModel`).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2
from test_measurements import numeric_jacobian

from opnav.camera import Camera, CameraCovariance, write_camera_file
from opnav.consistency import nees
from opnav.constants import ARCSEC_RAD
from opnav.dynamics import cruise_model, propagate
from opnav.epochs import parse_epoch
from opnav.errors import InputError
from opnav.filters.factory import build_filter, measurement_model
from opnav.filters.navigate import navigate
from opnav.filters.options import NavigationConfig, navigation_from_dict
from opnav.image.calibration import corner_scale
from opnav.image.camera_noise import radec_camera_jacobian
from opnav.measurements import CameraOffsetModel, ProbeMeasurementModel
from opnav.records import (
    ATTITUDE_COVARIANCE,
    ATTITUDE_JACOBIAN,
    CAMERA_JACOBIAN,
    CAMERA_PARAMETERS,
    Measurement,
    camera_jacobian,
    join_frame_radec,
    read_csv,
    split_radec_pairs,
    write_csv,
)

T0 = parse_epoch("2014-07-10T00:00:00", scale="tdb")
BASE = ProbeMeasurementModel("sun")
#: The S1 demo camera's geometry (1024 px, 1 degree).
CAMERA = Camera(1024, 1024, 764.0, 13.0)
NAMES = ("f", "cx", "cy", "k1", "p1", "p2")
#: 1-sigma of each parameter as a displacement at the detector corner, px (a calibration from a few stars)
CORNER_SIGMA_PX = 0.015 * np.array([1.0, 10.0, 10.0, 2.0, 0.5, 0.5])
CALIBRATION = np.diag((CORNER_SIGMA_PX / corner_scale(CAMERA, NAMES)) ** 2)
#: A frame's three stars and its attitude (camera -> ICRF).
STARS_PX = np.array([[150.0, 200.0], [820.0, 300.0], [400.0, 900.0]])
ATTITUDE = Rotation.from_rotvec([0.3, -1.1, 0.4])
NOISE_RAD = 0.05 * ARCSEC_RAD


def probe_state() -> np.ndarray:
    """A heliocentric probe ~20 million km from Mars, km and km/s, ICRF, Sun-centred (S1's July geometry)."""
    r_mars, v_mars = BASE.ephemeris.state("mars", T0, center="sun")
    return np.concatenate([r_mars + np.array([-1.5e7, 1.0e7, 0.6e7]), v_mars + np.array([2.0, -1.5, 0.7])])


def moon_jacobian(k: int, n: int) -> np.ndarray:
    """d(RA, Dec)/d(camera parameters) of the moon at record ``k`` of ``n`` (it drifts over ~100 px near the
    field centre, as S1's moons do), relative to the frame's stars: rad per parameter unit, (2, 6)."""
    target = np.array([500.0 + 60.0 * math.sin(3.0 * k / n), 480.0 + 40.0 * math.cos(2.0 * k / n)])
    return radec_camera_jacobian(CAMERA, NAMES, STARS_PX, target, ATTITUDE)


def nav_config(x0: np.ndarray, P0: np.ndarray, camera_error: str) -> NavigationConfig:
    consider = camera_error == "consider"
    return NavigationConfig(t0_tdb_s=T0, dynamics="cruise", x0=x0, P0=P0, camera_error=camera_error,
                            camera_parameters=NAMES if consider else (),
                            camera_covariance=CALIBRATION if consider else None)


def test_consider_ekf_is_consistent_under_a_constant_camera_error_where_the_plain_ekf_is_not():
    """Runs of 150 Deimos records, 10 min apart, each with its own camera error drawn from the calibration's
    covariance (0.4 of the records' 0.05" noise at the moon) injected through the records' Jacobians: the
    final NEES averaged over the runs is inside chi-square(6 K)/K for the consider EKF and far above it for
    the EKF that takes the records as they are; the consider states keep their prior (no gain)."""
    n, runs = 150, 6
    epochs = T0 + 600.0 * np.arange(1, n + 1)
    x_true0 = probe_state()
    truth = propagate(cruise_model(), T0, x_true0, np.concatenate([[T0], epochs])).states
    jacobians = np.array([moon_jacobian(k, n) for k in range(n)])
    camera_sigma = np.sqrt(np.einsum("kij,jl,kil->ki", jacobians, CALIBRATION, jacobians)).mean()
    assert 0.25 < camera_sigma / NOISE_RAD < 0.6  # small per record: a bias only over the arc
    P0 = np.diag([300.0**2] * 3 + [3e-4**2] * 3)
    force = cruise_model()
    final = {"white": [], "consider": []}
    for run in range(runs):
        rng = np.random.default_rng([39, run])
        dc = rng.multivariate_normal(np.zeros(len(NAMES)), CALIBRATION)
        x0 = x_true0 + rng.multivariate_normal(np.zeros(6), P0)
        records = []
        for k, t in enumerate(epochs):
            stub = Measurement(t, "radec", [0.0, 0.0], np.eye(2), target="deimos")
            value = BASE.predict(stub, truth[k + 1]) + jacobians[k] @ dc + NOISE_RAD * rng.standard_normal(2)
            records.append(Measurement(t, "radec", value, NOISE_RAD**2 * np.eye(2), target="deimos",
                                       extra={CAMERA_JACOBIAN: jacobians[k].tolist(), CAMERA_PARAMETERS: NAMES}))
        for mode in final:
            result = navigate(records, nav_config(x0, P0, mode), force_model=force)
            x, P = result.track.states[-1], result.track.covariances[-1]
            final[mode].append(float(nees(x[None, :6], P[None, :6, :6], truth[-1][None])[0]))
            if mode == "consider":
                assert result.history.accepted.all()
                np.testing.assert_array_equal(x[6:], 0.0)
                np.testing.assert_allclose(P[6:, 6:], CALIBRATION, rtol=1e-9, atol=0.0)
    low, high = chi2.ppf([0.001, 0.999], 6 * runs) / runs
    assert low < np.mean(final["consider"]) < high
    assert np.mean(final["white"]) > 2.0 * high


def _records_with_jacobians(x: np.ndarray, rng) -> list[Measurement]:
    """Both moons of one frame with attitude and camera Jacobians (the camera's columns in another order
    than the model's, Deimos' without ``f``)."""
    cov_att = np.diag([0.02, 0.02, 0.4]) ** 2 * ARCSEC_RAD**2
    records = []
    for name, names in (("phobos", ("cx", "cy", "f", "k1", "p1", "p2")), ("deimos", ("k1", "cx", "cy", "p1", "p2"))):
        value = BASE.predict(Measurement(T0, "radec", [0.0, 0.0], np.eye(2), target=name), x)
        jac = rng.normal(size=(2, 3))
        records.append(Measurement(T0, "radec", value, jac @ cov_att @ jac.T + NOISE_RAD**2 * np.eye(2), target=name,
                                   frame_id="frame_00001", extra={
                                       ATTITUDE_JACOBIAN: jac, ATTITUDE_COVARIANCE: cov_att,
                                       CAMERA_PARAMETERS: names,
                                       CAMERA_JACOBIAN: (rng.normal(size=(2, len(names))) * 1e-6).tolist()}))
    return records


def test_wrapper_prediction_and_jacobian_against_differences():
    """h(x, dc) = h(x) + J dc with J's columns placed by name; the analytic Jacobian of the augmented state
    matches central differences, for a radec record, a radec_pair (stacked Jacobians, a missing parameter
    a zero column) and a record without a camera Jacobian (zero block)."""
    model = CameraOffsetModel(BASE, NAMES)
    rng = np.random.default_rng(5)
    dc = rng.normal(size=len(NAMES)) * np.sqrt(np.diag(CALIBRATION))
    x = np.concatenate([probe_state(), dc])
    phobos, deimos = _records_with_jacobians(probe_state(), rng)
    (pair,) = join_frame_radec([phobos, deimos])
    plain = Measurement(T0, "radec", phobos.value, phobos.covariance, target="phobos")
    # h is linear in dc: steps of 1000 sigma (a move of ~1e-5 rad) keep the differences above rounding
    steps = np.concatenate([[1.0] * 3, [1e-3] * 3, 1e3 * np.sqrt(np.diag(CALIBRATION))])
    for record in (phobos, pair, plain):
        names, jac = camera_jacobian(record) or (NAMES, np.zeros((record.size, len(NAMES))))
        placed = np.zeros((record.size, len(NAMES)))
        for j, name in enumerate(names):
            placed[:, NAMES.index(name)] = jac[:, j]
        np.testing.assert_allclose(model.predict(record, x), BASE.predict(record, x[:6]) + placed @ dc, rtol=0, atol=1e-15)
        analytic = model.jacobian(record, x)
        numeric = numeric_jacobian(lambda s: model.predict(record, s), x, steps)
        np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-6 * np.abs(analytic[:, :6]).max())
        np.testing.assert_array_equal(analytic[:, 6:], placed)
    assert np.all(model.jacobian(pair, x)[2:, 6] == 0.0)  # Deimos' record has no f column
    np.testing.assert_allclose(model.noise_covariance(pair, x), pair.covariance)
    with pytest.raises(InputError, match=r"carries a camera Jacobian of k2, which the camera's calibration"):
        CameraOffsetModel(BASE, NAMES).predict(
            Measurement(T0, "radec", [0, 0], np.eye(2), target="phobos",
                        extra={CAMERA_PARAMETERS: ("k2",), CAMERA_JACOBIAN: [[1.0], [0.0]]}),
            x)
    with pytest.raises(InputError, match="12 entries"):
        model.predict(phobos, probe_state())


def test_camera_jacobians_round_trip_through_csv_join_and_split(tmp_path):
    """The CSV carries each record's camera parameters and Jacobian exactly (a pair's stacked over both
    records' parameters, split back by rows; a record without one stays without); a file without the
    columns reads as before; a bad cell is refused in one line naming the file and line."""
    rng = np.random.default_rng(7)
    frame = _records_with_jacobians(probe_state(), rng)
    (pair,) = join_frame_radec(frame)
    names, stacked = camera_jacobian(pair)
    assert names == ("cx", "cy", "f", "k1", "p1", "p2")
    for i, record in enumerate(frame):
        own_names, own = camera_jacobian(record)
        np.testing.assert_array_equal(stacked[2 * i:2 * i + 2, [names.index(n) for n in own_names]], own)
    np.testing.assert_array_equal(stacked[2:, names.index("f")], 0.0)  # Deimos' record has no f
    plain = Measurement(T0 + 60.0, "radec", [0.1, 0.2], NOISE_RAD**2 * np.eye(2), target="phobos")
    records = [pair, plain, *frame]
    write_csv(tmp_path / "m.csv", records)
    back = read_csv(tmp_path / "m.csv")
    assert [camera_jacobian(r) is None for r in back] == [False, True, False, False]
    for written, read in zip(records, back):
        if camera_jacobian(written) is not None:
            assert camera_jacobian(read)[0] == camera_jacobian(written)[0]
            np.testing.assert_array_equal(camera_jacobian(read)[1], camera_jacobian(written)[1])
    for split, record in zip(split_radec_pairs([back[0]]), frame):
        np.testing.assert_array_equal(camera_jacobian(split)[1][:, [names.index(n) for n in camera_jacobian(record)[0]]],
                                      camera_jacobian(record)[1])
    # a file of records without Jacobians has the columns it always had
    write_csv(tmp_path / "plain.csv", [plain])
    assert "camera_jacobian" not in (tmp_path / "plain.csv").read_text().splitlines()[0]
    assert camera_jacobian(read_csv(tmp_path / "plain.csv")[0]) is None
    lines = (tmp_path / "m.csv").read_text().splitlines()
    for cells, message in (("f cx,1.0 2.0 3.0", r"camera_jacobian must hold 2 x 2 finite numbers"),
                           ("f f,1.0 2.0 3.0 4.0", r"camera_parameters 'f f': distinct parameter names"),
                           ("f 2x,1.0 2.0 3.0 4.0", r"camera_parameters 'f 2x': distinct parameter names"),
                           (",1.0 2.0", r"camera_parameters '': distinct parameter names")):
        head, _, _ = lines[2].rpartition(",")
        head, _, _ = head.rpartition(",")
        (tmp_path / "bad.csv").write_text("\n".join([lines[0], f"{head},{cells}"]) + "\n")
        with pytest.raises(InputError, match=rf"bad.csv:2: bad measurement row: {message}"):
            read_csv(tmp_path / "bad.csv")


def _camera_files(tmp_path):
    bare, calibrated = tmp_path / "bare.toml", tmp_path / "calibrated.toml"
    write_camera_file(bare, CAMERA)
    write_camera_file(calibrated, CAMERA, CameraCovariance(NAMES, CALIBRATION, {}))
    return bare, calibrated


def test_navigation_option_builds_the_consider_ekf_and_refuses_what_it_does_not_support(tmp_path):
    """[navigation] camera_error = "consider" with camera_file (relative to the scene file) gives the EKF a
    state augmented with the camera's parameters, their prior the [calibration] covariance, all consider
    states; combinations it does not support end in one line naming the option."""
    bare, calibrated = _camera_files(tmp_path)
    scene = tmp_path / "scene.toml"
    scene.write_text("")
    x = probe_state()
    section = {"epoch": "2014-07-10T00:00:00", "epoch_scale": "tdb", "dynamics": "cruise",
               "position_km": x[:3].tolist(), "velocity_km_s": x[3:].tolist(), "sigma_position_km": 300.0,
               "sigma_velocity_km_s": 3e-4, "camera_error": "consider", "camera_file": "calibrated.toml"}
    nav = navigation_from_dict(section, str(scene))
    assert nav.camera_parameters == NAMES
    model = measurement_model(nav, "sun")
    assert isinstance(model, CameraOffsetModel) and model.size == 12
    ekf = build_filter("ekf", nav, model, cruise_model())
    assert ekf.options.consider == tuple(range(6, 12))
    np.testing.assert_allclose(ekf.estimate.P[6:, 6:], CALIBRATION, rtol=1e-12)
    np.testing.assert_array_equal(ekf.estimate.P[:6, 6:], 0.0)
    for change, message in (({"camera_file": ""}, r"camera_error = 'consider' needs camera_file"),
                            ({"camera_file": str(bare)}, r"camera_file .*bare.toml has no \[calibration\] table"),
                            ({"filter": "ukf"}, r"camera_error = 'consider' works with filter = 'ekf' only"),
                            ({"ephemeris_error": "consider", "target_position_sigma_km": 1.0},
                             r"camera_error = 'consider' works with ephemeris_error = 'white' only"),
                            ({"camera_error": "bias"}, r"camera_error must be one of white, consider"),
                            ({"camera_error": "white"}, r"camera_file is read with camera_error = 'consider' only")):
        with pytest.raises(InputError, match=message):
            navigation_from_dict({**section, **change}, str(scene))
    record = Measurement(T0 + 600.0, "radec", [0.1, 0.2], NOISE_RAD**2 * np.eye(2), target="deimos")
    with pytest.raises(InputError, match=r"^scene.toml: camera_error = 'consider' needs records that carry their camera "
                                         r"Jacobian .* these records have none$"):
        navigate([record], nav, source="scene.toml")
    with pytest.raises(InputError, match=r"camera_error = 'consider' works with filter 'ekf' only, not 'wls'"):
        navigate([record], nav, filter_name="wls")
    k2 = Measurement(T0 + 600.0, "radec", [0.1, 0.2], NOISE_RAD**2 * np.eye(2), target="deimos",
                     extra={CAMERA_PARAMETERS: ("k2",), CAMERA_JACOBIAN: [[1e-6], [0.0]]})
    with pytest.raises(InputError, match=r"carry camera Jacobians of k2, which the camera file's \[calibration\] "
                                         r"\(f, cx, cy, k1, p1, p2\) does not have$"):
        navigate([k2], nav)


def test_s1_setting_needs_the_camera_covariance(tmp_path):
    """S1's camera_error = "consider" needs camera_covariance = true; the tracking stage then keeps the
    Jacobians (TrackingOptions.camera_error)."""
    from opnav.studies.s1 import Settings, s1_tracking_options

    _, calibrated = _camera_files(tmp_path)
    with pytest.raises(InputError, match=r"^camera_error = 'consider' needs camera_covariance = true"):
        Settings(camera_file=str(calibrated), camera_error="consider")
    with pytest.raises(InputError, match=r"^camera_error must be 'white' or 'consider', got 'bias'$"):
        Settings(camera_file=str(calibrated), camera_covariance=True, camera_error="bias")
    with pytest.raises(InputError, match=r"^camera_error = 'consider' works with ephemeris_model = 'white' only"):
        Settings(camera_file=str(calibrated), camera_covariance=True, camera_error="consider", ephemeris_model="estimate")
    tracking = s1_tracking_options(Settings(camera_file=str(calibrated), camera_covariance=True, camera_error="consider"))
    assert tracking.camera_error == "consider" and tracking.camera_covariance.names == NAMES
