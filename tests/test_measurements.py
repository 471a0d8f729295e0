"""Measurement models: analytic Jacobians vs central differences, physics checks, S4 eq. 1."""

import numpy as np
import pytest

from opnav.constants import ARCSEC_RAD, C_KM_S
from opnav.ephemeris import Ephemeris, default_planets
from opnav.epochs import parse_epoch
from opnav.errors import InputError
from opnav.frames import unit
from opnav.light import aberrate, aberration_velocity_jacobian
from opnav.measurements import ProbeMeasurementModel, position_from_los, position_measurement, radec_partials
from opnav.records import Measurement

T0 = parse_epoch("2014-07-15T00:00:00", scale="tdb")


class CircularMoons:
    """Phobos/Deimos on circular equatorial orbits (enough for Jacobian checks)."""

    PERIOD_S = {"phobos": 27_554.0, "deimos": 109_075.0}
    RADIUS_KM = {"phobos": 9_377.0, "deimos": 23_460.0}

    def state(self, name, t):
        t = np.asarray(t, dtype=float)
        n = 2.0 * np.pi / self.PERIOD_S[name]
        a = self.RADIUS_KM[name]
        c, s = np.cos(n * t), np.sin(n * t)
        r = np.stack([a * c, a * s, 0.1 * a * s], axis=-1)
        v = np.stack([-a * n * s, a * n * c, 0.1 * a * n * c], axis=-1)
        return r, v


EPH = Ephemeris(default_planets(), CircularMoons())


def cruise_state() -> np.ndarray:
    """A heliocentric probe state ~20e6 km from Mars (km, km/s, ICRF, Sun-centred)."""
    r_mars, v_mars = EPH.state("mars", T0, center="sun")
    return np.concatenate([r_mars + np.array([-1.5e7, 1.0e7, 0.6e7]), v_mars + np.array([2.0, -1.5, 0.7])])


def numeric_jacobian(f, x, steps):
    cols = []
    for i, h in enumerate(steps):
        dx = np.zeros_like(x)
        dx[i] = h
        cols.append((f(x + dx) - f(x - dx)) / (2.0 * h))
    return np.stack(cols, axis=-1)


# central-difference steps: 1 km in position, 1e-3 km/s in velocity. Truncation error is
# O(h^2 |f'''|) ~ (h/|rho|)^2 relative, far below the rtol used.
STEPS = np.array([1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])


def records():
    star = unit(np.array([0.3, -0.8, 0.2]))
    return [
        Measurement(T0, "radec", [1.0, 0.1], np.eye(2) * 1e-12, target="phobos"),
        Measurement(T0, "radec", [1.0, 0.1], np.eye(2) * 1e-12, target="deimos"),
        Measurement(T0, "los", unit(np.array([1.0, 1.0, 1.0])), np.eye(3) * 1e-12, target="mars"),
        Measurement(T0, "starlight_angle", [1.0], [[1e-12]], target="mars", star_unit_icrf=star),
        Measurement(T0, "starlight_angle", [1.0], [[1e-12]], target="sun", star_unit_icrf=star),
        Measurement(T0, "starlight_elevation", [1.0], [[1e-12]], target="mars", star_unit_icrf=star),
        Measurement(T0, "position", [0.0, 0.0, 0.0], np.eye(3), target="mars"),
        Measurement(T0, "radial_velocity", [0.0], [[1e-6]], target="sun", star_unit_icrf=star),
        Measurement(T0, "radial_velocity", [0.0], [[1e-6]], target="vega", star_id=91262, star_unit_icrf=star),
    ]


@pytest.mark.parametrize("light_time,aberration", [(True, True), (False, False), (True, False)])
@pytest.mark.parametrize("index", range(9))
def test_jacobian_matches_central_differences(index, light_time, aberration):
    record = records()[index]
    model = ProbeMeasurementModel("sun", ephemeris=EPH, light_time=light_time, aberration=aberration,
                                  star_radial_velocity_km_s={91262: -13.9})
    x = cruise_state()
    analytic = model.jacobian(record, x)
    numeric = numeric_jacobian(lambda s: model.predict(record, s), x, STEPS)
    # Position partials (~1/range) and velocity partials (aberration ~1/c, or Doppler ~1)
    # differ by orders of magnitude, so each block is held to 1e-6 of its own largest entry
    # (FD truncation ~(h/range)^2 and light-time iteration noise are far below that).
    for block in (slice(0, 3), slice(3, 6)):
        scale = np.abs(numeric[:, block]).max()
        np.testing.assert_allclose(analytic[:, block], numeric[:, block], rtol=0, atol=1e-6 * scale + 1e-300)
    if aberration and record.kind in ("radec", "los", "starlight_angle", "starlight_elevation"):
        assert np.abs(analytic[:, 3:]).max() > 1e-7 * np.abs(analytic[:, :3]).max()


def test_light_time_partial_is_not_negligible_for_fast_moon():
    """The light-time term of d rho/d r changes RA partials by ~v_T/c: check it is the one FD sees."""
    record = records()[0]
    x = cruise_state()
    model = ProbeMeasurementModel("sun", ephemeris=EPH, aberration=False)
    numeric = numeric_jacobian(lambda s: model.predict(record, s), x, STEPS)[:, :3]
    analytic = model.jacobian(record, x)[:, :3]
    naive = -radec_partials(model._direction(record, x[None])[0][0]) * 1.0
    err_exact = np.abs(analytic - numeric).max()
    err_naive = np.abs(naive - numeric).max()
    assert err_exact < 0.05 * err_naive


def test_augmented_state_gets_zero_partials():
    model = ProbeMeasurementModel("sun", ephemeris=EPH)
    x = np.concatenate([cruise_state(), [1.0, 2.0]])
    jac = model.jacobian(records()[0], x)
    assert jac.shape == (2, 8)
    assert np.all(jac[:, 6:] == 0.0)


def test_predict_vectorised_equals_loop():
    model = ProbeMeasurementModel("sun", ephemeris=EPH)
    rng = np.random.default_rng(1)
    xs = cruise_state() + rng.normal(size=(5, 6)) * np.array([1e3] * 3 + [1e-3] * 3)
    for record in records()[:6]:
        batch = model.predict(record, xs)
        loop = np.array([model.predict(record, s) for s in xs])
        np.testing.assert_allclose(batch, loop, rtol=0, atol=1e-13)


def test_light_time_shift_matches_target_motion():
    """Switching light time off moves the apparent moon by ~ v_moon_perp * tau / range."""
    record = records()[0]
    x = cruise_state()
    on = ProbeMeasurementModel("sun", ephemeris=EPH, aberration=False).predict(record, x)
    off = ProbeMeasurementModel("sun", ephemeris=EPH, aberration=False, light_time=False).predict(record, x)
    r_probe = EPH.position("sun", T0) + x[:3]
    rho = EPH.position("phobos", T0) - r_probe
    tau = np.linalg.norm(rho) / C_KM_S
    u = rho / np.linalg.norm(rho)
    # secant displacement of the moon during the light time (Phobos turns ~0.014 rad in it)
    moved = EPH.position("phobos", T0) - EPH.position("phobos", T0 - tau)
    expected = np.linalg.norm(moved - (moved @ u) * u) / np.linalg.norm(rho)
    shift = np.hypot((on[0] - off[0]) * np.cos(on[1]), on[1] - off[1])
    np.testing.assert_allclose(shift, expected, rtol=1e-3)


def test_aberration_of_order_v_over_c():
    record = records()[2]
    x = cruise_state()
    on = ProbeMeasurementModel("sun", ephemeris=EPH).predict(record, x)
    off = ProbeMeasurementModel("sun", ephemeris=EPH, aberration=False).predict(record, x)
    v_ssb = EPH.state("sun", T0)[1] + x[3:]
    v_perp = v_ssb - (v_ssb @ off) * off
    np.testing.assert_allclose(np.linalg.norm(on - off), np.linalg.norm(v_perp) / C_KM_S, rtol=1e-3)


def test_aberration_velocity_jacobian_central_differences():
    u = unit(np.array([0.2, -0.5, 0.8]))
    v = np.array([25.0, -10.0, 5.0])
    numeric = numeric_jacobian(lambda w: aberrate(u, w), v, np.full(3, 1e-2))
    np.testing.assert_allclose(aberration_velocity_jacobian(u, v), numeric, rtol=0, atol=1e-10)


def test_starlight_angle_is_angle_between_body_and_star():
    """theta = arccos(-l_body_to_probe . s) on a geometry with no corrections."""
    x = cruise_state()
    record = records()[3]
    model = ProbeMeasurementModel("sun", ephemeris=EPH, light_time=False, aberration=False)
    r_mars_probe = x[:3] - EPH.position("mars", T0, center="sun")
    expected = np.arccos(-unit(r_mars_probe) @ record.star_unit_icrf)
    np.testing.assert_allclose(model.predict(record, x)[0], expected, rtol=0, atol=1e-12)


def test_starlight_elevation_s3_definition():
    """S3: beta = arccos(-r.S/|r|) - arcsin(R_e/|r|) for an Earth-centred GEO state."""
    star = unit(np.array([0.1, 0.9, -0.3]))
    rec = Measurement(T0, "starlight_elevation", [0.0], [[1e-10]], target="earth", star_unit_icrf=star)
    x = np.array([42_164.0 * np.cos(1.0), 42_164.0 * np.sin(1.0), 0.0, -3.07 * np.sin(1.0), 3.07 * np.cos(1.0), 0.0])
    model = ProbeMeasurementModel("earth", ephemeris=EPH, light_time=False, aberration=False)
    r = x[:3]
    expected = np.arccos(-r @ star / np.linalg.norm(r)) - np.arcsin(6378.1363 / np.linalg.norm(r))
    np.testing.assert_allclose(model.predict(rec, x)[0], expected, rtol=0, atol=1e-12)


def test_radial_velocity_sign_conventions():
    """Sun: v.r/|r| (receding positive); star: (v_star - v).l, same sense."""
    model = ProbeMeasurementModel("sun", ephemeris=EPH, star_radial_velocity_km_s={7: 10.0})
    x = np.array([1.5e8, 0.0, 0.0, 3.0, 29.0, 0.0])
    sun = Measurement(T0, "radial_velocity", [0.0], [[1e-6]], target="sun", star_unit_icrf=[1.0, 0.0, 0.0])
    np.testing.assert_allclose(model.predict(sun, x)[0], 3.0, atol=1e-12)
    star = Measurement(T0, "radial_velocity", [0.0], [[1e-6]], target="x", star_id=7, star_unit_icrf=[0.0, 1.0, 0.0])
    v_ssb = EPH.state("sun", T0)[1] + x[3:]
    np.testing.assert_allclose(model.predict(star, x)[0], 10.0 - v_ssb[1], atol=1e-12)
    with pytest.raises(InputError, match="radial velocity for star 8"):
        bad = Measurement(T0, "radial_velocity", [0.0], [[1e-6]], target="x", star_id=8, star_unit_icrf=[0, 1, 0])
        model.predict(bad, x)


def test_residual_wraps_right_ascension():
    model = ProbeMeasurementModel("sun", ephemeris=EPH)
    rec = Measurement(T0, "radec", [0.001, 0.2], np.eye(2), target="phobos")
    res = model.residual(rec, np.array([[2.0 * np.pi - 0.001, 0.1], [0.0, 0.2]]))
    np.testing.assert_allclose(res, [[0.002, 0.1], [0.001, 0.0]], atol=1e-15)


def test_target_ephemeris_error_inflates_covariance():
    x = cruise_state()
    rec = records()[0]
    model = ProbeMeasurementModel("sun", ephemeris=EPH, target_position_sigma_km=1.0)
    dist = np.linalg.norm(EPH.position("phobos", T0) - EPH.position("sun", T0) - x[:3])
    R = model.noise_covariance(rec, x)
    # the model uses the light-time range, ~|v| tau longer than the geometric one (~1e-4)
    np.testing.assert_allclose(R[1, 1] - rec.covariance[1, 1], (1.0 / dist) ** 2, rtol=1e-3)
    assert R[0, 0] - rec.covariance[0, 0] >= (1.0 / dist) ** 2


def test_position_from_two_lines_of_sight_recovers_truth_and_partials():
    t = parse_epoch("2021-01-20T00:00:00", scale="tdb")
    r_sun, r_mars = EPH.position("sun", t), EPH.position("mars", t)
    r_probe = r_mars + np.array([3e6, -2e6, 1e6])
    l_ps, l_pm = unit(r_sun - r_probe), unit(r_mars - r_probe)
    r, d_ps, d_pm = position_from_los(l_ps, l_pm, r_mars - r_sun)
    np.testing.assert_allclose(r, r_probe - r_sun, rtol=1e-12)
    # step 1e-7 (unitless) on a unit vector; rtol 1e-5 of the largest partial
    num_ps = numeric_jacobian(lambda l: position_from_los(l, l_pm, r_mars - r_sun)[0], l_ps, np.full(3, 1e-7))
    num_pm = numeric_jacobian(lambda l: position_from_los(l_ps, l, r_mars - r_sun)[0], l_pm, np.full(3, 1e-7))
    np.testing.assert_allclose(d_ps, num_ps, rtol=0, atol=1e-5 * np.abs(num_ps).max())
    np.testing.assert_allclose(d_pm, num_pm, rtol=0, atol=1e-5 * np.abs(num_pm).max())


def test_position_measurement_with_light_time_is_unbiased_and_covariance_matches_scatter():
    t = parse_epoch("2021-01-20T00:00:00", scale="tdb")
    r_probe = EPH.position("mars", t) + np.array([3e6, -2e6, 1e6])
    model = ProbeMeasurementModel("ssb", ephemeris=EPH, aberration=False)
    state = np.concatenate([r_probe, np.zeros(3)])
    l_ps = model.predict(Measurement(t, "los", [1, 0, 0], np.eye(3), target="sun"), state)
    l_pm = model.predict(Measurement(t, "los", [1, 0, 0], np.eye(3), target="mars"), state)
    sigma = 2.0 * ARCSEC_RAD
    cov_ps = sigma**2 * (np.eye(3) - np.outer(l_ps, l_ps))
    cov_pm = sigma**2 * (np.eye(3) - np.outer(l_pm, l_pm))
    exact = position_measurement(t, l_ps, cov_ps, l_pm, cov_pm, ephemeris=EPH)
    np.testing.assert_allclose(exact.value, r_probe - EPH.position("sun", t), rtol=0, atol=1e-3)
    rng = np.random.default_rng(4)
    draws = []
    for _ in range(300):
        noisy_ps = unit(l_ps + rng.multivariate_normal(np.zeros(3), cov_ps))
        noisy_pm = unit(l_pm + rng.multivariate_normal(np.zeros(3), cov_pm))
        draws.append(position_measurement(t, noisy_ps, cov_ps, noisy_pm, cov_pm, ephemeris=EPH).value - exact.value)
    draws = np.array(draws)
    # Mahalanobis mean of the draws ~ chi2(3)/3: 99.9% bounds for 300 draws
    cinv = np.linalg.inv(exact.covariance)
    mean_nees = np.mean(np.einsum("ni,ij,nj->n", draws, cinv, draws))
    assert 2.55 < mean_nees < 3.5


def test_bad_state_is_rejected_with_named_parameter():
    model = ProbeMeasurementModel("sun", ephemeris=EPH)
    with pytest.raises(InputError, match="state"):
        model.predict(records()[0], np.array([1.0, 2.0, np.nan, 0, 0, 0]))
    with pytest.raises(InputError, match="target_position_sigma_km"):
        ProbeMeasurementModel("sun", ephemeris=EPH, target_position_sigma_km=-1.0)
