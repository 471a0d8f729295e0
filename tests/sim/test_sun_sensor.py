"""The sun-sensor model (opnav.sim.sun_sensor): noise against its stated sigma, the field, the frames."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from opnav.constants import ARCSEC_RAD, C_KM_S, DEG_RAD
from opnav.ephemeris import default_ephemeris
from opnav.errors import InputError
from opnav.light import light_time_vector
from opnav.sim.sun_sensor import (apparent_sun, geometric_los, mounting_from_boresight, read_arc, read_sun,
                                  sun_sensor)

T0 = 664_000_000.0  # 2021-01-15, TDB s past J2000


def _observer():
    eph = default_ephemeris()
    r_sun = eph.position("sun", T0)
    return eph, r_sun + np.array([1.5e8, 0.8e8, 0.3e8]), np.array([-12.0, 20.0, 8.0])


def _body_pointing_sensor_at(sensor, u_icrf, roll_rad=0.3):
    """Body -> ICRF attitude that puts ``u_icrf`` on the sensor's boresight (roll about it: ``roll_rad``)."""
    z = u_icrf / np.linalg.norm(u_icrf)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    R_icrf_sensor = Rotation.from_matrix(np.column_stack([x, np.cross(z, x), z])) * Rotation.from_rotvec([0, 0, roll_rad])
    return R_icrf_sensor * sensor.mounting.inv()


def _tangent_chi2(u_measured, u_true, cov):
    """Chi-square (2 dof) of a measured unit vector against the truth under the record's covariance."""
    a = np.cross(u_true, [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    basis = np.stack([a, np.cross(u_true, a)])  # (2, 3)
    e = basis @ (u_measured - u_true)
    return float(e @ np.linalg.solve(basis @ cov @ basis.T, e))


def test_mounting_puts_the_boresight_on_sensor_z():
    for boresight in ([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.3, -2.0, 0.5]):
        m = mounting_from_boresight(boresight)
        assert np.allclose(m.apply([0.0, 0.0, 1.0]), np.asarray(boresight) / np.linalg.norm(boresight), atol=1e-15)
        assert np.isclose(np.linalg.det(m.as_matrix()), 1.0)


def test_noise_matches_the_stated_sigma_and_the_record_covariance():
    eph, r, v = _observer()
    sensor = sun_sensor(boresight_body=[0.2, 1.0, 0.1], half_angle_deg=30.0, sigma_arcsec=5.0)
    u_sun = apparent_sun(T0, r, v, ephemeris=eph)
    body = _body_pointing_sensor_at(sensor, u_sun + np.array([0.05, -0.1, 0.02]))  # Sun ~6 deg off boresight
    n = 2000
    errors, total = [], 0.0
    for k in range(n):
        reading = read_sun(sensor, T0, r, v, body, rng=sensor.rng(7, k), ephemeris=eph)
        u = reading.record.value
        assert reading.reason is None and np.isclose(np.linalg.norm(u), 1.0)
        total += _tangent_chi2(u, reading.true_icrf, reading.record.covariance)
        errors.append(np.linalg.norm(np.cross(u, reading.true_icrf)))
    # sum of 2n unit-variance squares: chi-square(2n) at 99.9 %
    assert chi2.ppf(0.0005, 2 * n) < total < chi2.ppf(0.9995, 2 * n)
    # the error angle's RMS is sqrt(2) sigma (two axes): within the chi-square bounds of the stated 5"
    rms2 = np.mean(np.square(errors)) / (5.0 * ARCSEC_RAD) ** 2 / 2.0
    assert chi2.ppf(0.0005, 2 * n) / (2 * n) < rms2 < chi2.ppf(0.9995, 2 * n) / (2 * n)


def test_bias_is_along_the_sensor_axes_at_the_boresight():
    eph, r, v = _observer()
    sensor = sun_sensor(boresight_body=[0.0, 0.0, 1.0], half_angle_deg=40.0, sigma_arcsec=0.01,
                        bias_arcsec=(30.0, -20.0))
    u_sun = apparent_sun(T0, r, v, ephemeris=eph)
    body = _body_pointing_sensor_at(sensor, u_sun)
    reading = read_sun(sensor, T0, r, v, body, rng=sensor.rng(1, 0), ephemeris=eph)
    in_sensor = (body * sensor.mounting).inv().apply(np.array(reading.record.value))
    # small angles: the sensor-frame x and y components are the two angles, rad
    assert in_sensor[0] / ARCSEC_RAD == pytest.approx(30.0, abs=0.1)
    assert in_sensor[1] / ARCSEC_RAD == pytest.approx(-20.0, abs=0.1)
    assert reading.off_boresight_rad < 1e-9


def test_out_of_field_is_refused_with_its_reason():
    eph, r, v = _observer()
    sensor = sun_sensor(boresight_body=[1.0, 0.0, 0.0], half_angle_deg=10.0, sigma_arcsec=2.0)
    u_sun = apparent_sun(T0, r, v, ephemeris=eph)
    on_axis = _body_pointing_sensor_at(sensor, u_sun)
    for off_deg, measured in ((9.5, True), (10.5, False)):
        # turn the body about an axis perpendicular to the Sun: the Sun moves off the boresight by that angle
        axis = np.cross(u_sun, [0.0, 0.0, 1.0])
        body = Rotation.from_rotvec(off_deg * DEG_RAD * axis / np.linalg.norm(axis)) * on_axis
        reading = read_sun(sensor, T0, r, v, body, rng=sensor.rng(1, 0), ephemeris=eph)
        assert reading.off_boresight_rad / DEG_RAD == pytest.approx(off_deg, abs=1e-9)
        assert (reading.record is not None) == measured
        if not measured:
            assert "sun sensor" in reading.reason and "outside the 10.00 deg half-angle field" in reading.reason


def test_truth_is_the_apparent_sun_with_light_time_and_aberration():
    eph, r, v = _observer()
    geometric, _ = light_time_vector(lambda t: eph.position("sun", t), T0, r)
    geometric /= np.linalg.norm(geometric)
    apparent = apparent_sun(T0, r, v, ephemeris=eph)
    # aberration moves the Sun by |v x u| / c, here ~20 arcsec
    shift = np.linalg.norm(np.cross(geometric, apparent))
    assert shift == pytest.approx(np.linalg.norm(np.cross(v, geometric)) / C_KM_S, rel=1e-3)
    sensor = sun_sensor(boresight_body=[0.0, 0.0, 1.0], half_angle_deg=40.0, sigma_arcsec=1e-4)
    reading = read_sun(sensor, T0, r, v, _body_pointing_sensor_at(sensor, apparent), rng=sensor.rng(1, 0),
                       ephemeris=eph)
    assert np.allclose(reading.true_icrf, apparent, atol=1e-15)
    # the record is the apparent direction (within 6 sigma of its 1e-4" noise); without aberration, the geometric one
    tolerance = 6 * 1e-4 * ARCSEC_RAD
    assert np.linalg.norm(reading.record.value - apparent) < tolerance
    assert np.linalg.norm(geometric_los(reading.record, v) - geometric) < tolerance
    off = sun_sensor(boresight_body=[0.0, 0.0, 1.0], half_angle_deg=40.0, sigma_arcsec=1e-4, aberration=False)
    plain = read_sun(off, T0, r, v, _body_pointing_sensor_at(sensor, apparent), rng=off.rng(1, 0), ephemeris=eph)
    assert np.linalg.norm(plain.true_icrf - geometric) < 1e-12


def test_attitude_error_is_in_the_covariance():
    eph, r, v = _observer()
    sensor = sun_sensor(boresight_body=[0.0, 1.0, 0.0], half_angle_deg=30.0, sigma_arcsec=1.0)
    u_sun = apparent_sun(T0, r, v, ephemeris=eph)
    body = _body_pointing_sensor_at(sensor, u_sun + np.array([0.0, 0.08, -0.05]))
    # an attitude solution 20" about body x and y, 100" about body z (a star tracker's roll): larger than the noise
    cov_att = np.diag(np.square([20.0, 20.0, 100.0]) * ARCSEC_RAD**2)
    rng = np.random.default_rng(11)
    n, total = 1500, 0.0
    for k in range(n):
        estimated = body * Rotation.from_rotvec(rng.multivariate_normal(np.zeros(3), cov_att))
        reading = read_sun(sensor, T0, r, v, body, rng=sensor.rng(3, k), ephemeris=eph, R_icrf_body_est=estimated,
                           cov_att_body_rad2=cov_att)
        total += _tangent_chi2(reading.record.value, reading.true_icrf, reading.record.covariance)
    assert chi2.ppf(0.0005, 2 * n) < total < chi2.ppf(0.9995, 2 * n)
    # without the attitude term the same errors are far too large for the record
    reading = read_sun(sensor, T0, r, v, body, rng=sensor.rng(3, 0), ephemeris=eph)
    assert np.trace(reading.record.covariance) < 0.1 * np.trace(cov_att)


def test_arc_streams_do_not_depend_on_chunking():
    eph, r, v = _observer()
    sensor = sun_sensor(boresight_body=[0.0, 0.0, 1.0], half_angle_deg=40.0, sigma_arcsec=3.0)
    t = T0 + 60.0 * np.arange(6)
    rs, vs = np.tile(r, (6, 1)) + np.outer(np.arange(6) * 60.0, v), np.tile(v, (6, 1))
    body = Rotation.concatenate([_body_pointing_sensor_at(sensor, apparent_sun(T0, r, v, ephemeris=eph))] * 6)
    whole = read_arc(sensor, 5, t, rs, vs, body, ephemeris=eph)
    parts = read_arc(sensor, 5, t[:2], rs[:2], vs[:2], body[:2], ephemeris=eph) + \
        read_arc(sensor, 5, t[2:], rs[2:], vs[2:], body[2:], ephemeris=eph, first=2)
    assert all(np.array_equal(a.record.value, b.record.value) for a, b in zip(whole, parts))
    assert len({tuple(a.record.value) for a in whole}) == 6


@pytest.mark.parametrize("kwargs, match", [
    (dict(half_angle_deg=95.0, sigma_arcsec=1.0), "half-angle"),
    (dict(half_angle_deg=20.0, sigma_arcsec=0.0), "noise"),
    (dict(half_angle_deg=20.0, sigma_arcsec=1.0, bias_arcsec=(1.0,)), "bias"),
    (dict(half_angle_deg=20.0, sigma_arcsec=1.0, boresight_body=[0.0, 0.0, 0.0]), "boresight"),
])
def test_bad_settings_are_one_line(kwargs, match):
    kwargs = {"boresight_body": [0.0, 0.0, 1.0], **kwargs}
    with pytest.raises(InputError, match=match):
        sun_sensor(**kwargs)
