"""Light time and stellar aberration: equation residuals, closed forms, Jacobian, astropy agreement."""

from __future__ import annotations

import numpy as np
import pytest

from opnav.constants import ARCSEC_RAD, C_KM_S, DAY_S
from opnav.ephemeris import default_ephemeris
from opnav.ephemeris.planets import default_kernel_path, default_planets
from opnav.epochs import parse_epoch, to_time
from opnav.errors import ConvergenceError, InputError
from opnav.frames import angle_between, unit
from opnav.light import aberrate, aberration_jacobian, apparent_direction, light_time_vector

T_2014 = parse_epoch("2014-06-01T00:00:00", scale="tdb")


def _mars_ssb(t: np.ndarray) -> np.ndarray:
    return default_planets().position("mars", t)


@pytest.mark.parametrize("body", ["mars", "sun", "jupiter", "moon"])
def test_light_time_solves_its_equation_to_a_metre(body):
    planets = default_planets()
    t = T_2014 + np.linspace(0.0, 300.0 * DAY_S, 7)
    r_earth, _ = planets.state("earth", t)
    r_rel, tau = light_time_vector(lambda tt: planets.position(body, tt), t, r_earth)
    residual_km = np.linalg.norm(planets.position(body, t - tau) - r_earth, axis=-1) - C_KM_S * tau
    assert np.all(np.abs(residual_km) < 1e-3)
    np.testing.assert_allclose(r_rel, planets.position(body, t - tau) - r_earth, rtol=0, atol=1e-6)


def test_light_time_shapes_and_non_convergence():
    planets = default_planets()
    r_earth = planets.position("earth", T_2014)
    r_rel, tau = light_time_vector(_mars_ssb, T_2014, r_earth)
    assert r_rel.shape == (3,) and np.ndim(tau) == 0
    assert tau == pytest.approx(np.linalg.norm(r_rel) / C_KM_S, abs=1e-9)
    with pytest.raises(ConvergenceError, match="light-time"):
        light_time_vector(_mars_ssb, T_2014, r_earth, max_iterations=1)


@pytest.mark.parametrize(
    ("speed_km_s", "expected_arcsec"),
    # perpendicular incidence: cos(theta') = beta, so sin(deflection) = v / c exactly
    [(30.0, np.degrees(np.arcsin(30.0 / C_KM_S)) * 3600), (29.78, 20.49)],
)
def test_aberration_perpendicular_to_velocity(speed_km_s, expected_arcsec):
    direction = np.array([1.0, 0.0, 0.0])
    apparent = aberrate(direction, np.array([0.0, speed_km_s, 0.0]))
    deflection_arcsec = angle_between(direction, apparent) / ARCSEC_RAD
    assert deflection_arcsec == pytest.approx(expected_arcsec, abs=0.005)
    assert apparent[1] > 0  # toward the velocity
    assert np.linalg.norm(apparent) == pytest.approx(1.0, abs=1e-15)


def test_aberration_vanishes_along_the_velocity():
    v = np.array([3.0, -20.0, 10.0])
    along = unit(v)
    np.testing.assert_allclose(aberrate(np.stack([along, -along]), v), np.stack([along, -along]), rtol=0, atol=1e-15)


def test_aberration_matches_the_relativistic_angle_formula():
    rng = np.random.default_rng(20140601)
    directions = unit(rng.normal(size=(500, 3)))
    v = np.array([-12.0, 25.0, 8.0])
    beta = np.linalg.norm(v) / C_KM_S
    cos_theta = directions @ unit(v)
    expected = np.arccos(np.clip((cos_theta + beta) / (1 + beta * cos_theta), -1, 1))
    apparent = aberrate(directions, v)
    np.testing.assert_allclose(angle_between(apparent, v), expected, rtol=0, atol=1e-12)
    # the deflection lies in the plane of the direction and the velocity
    normal = np.cross(directions, v)
    np.testing.assert_allclose(np.sum(apparent * normal, -1) / np.linalg.norm(normal, axis=-1), 0.0, atol=1e-15)


def test_aberration_rejects_superluminal_observers():
    with pytest.raises(InputError, match="speed of light"):
        aberrate(np.array([1.0, 0.0, 0.0]), np.array([0.0, C_KM_S, 0.0]))


def test_aberration_jacobian_matches_central_differences():
    rng = np.random.default_rng(7)
    directions = unit(rng.normal(size=(20, 3)))
    v = np.array([5.0, 28.0, -3.0])
    jacobian = aberration_jacobian(directions, v)
    step = 1e-6
    numeric = np.empty_like(jacobian)
    for j in range(3):
        delta = np.zeros(3)
        delta[j] = step
        numeric[:, :, j] = (aberrate(directions + delta, v) - aberrate(directions - delta, v)) / (2 * step)
    # truncation ~ step^2 ~ 1e-12, rounding ~ 1e-16 / step ~ 1e-10
    np.testing.assert_allclose(jacobian, numeric, rtol=0, atol=1e-9)


def test_apparent_direction_switches_each_correction():
    ephemeris = default_ephemeris()
    t = T_2014 + np.array([0.0, 40.0 * DAY_S])
    r_earth, v_earth = ephemeris.state("earth", t)
    target = lambda tt: ephemeris.position("mars", tt)  # noqa: E731
    geometric = unit(target(t) - r_earth)
    np.testing.assert_allclose(
        apparent_direction(target, t, r_earth, v_earth, light_time=False, aberration=False), geometric, atol=1e-15
    )
    astrometric = apparent_direction(target, t, r_earth, v_earth, aberration=False)
    np.testing.assert_allclose(astrometric, unit(light_time_vector(target, t, r_earth)[0]), atol=1e-15)
    aberrated_only = apparent_direction(target, t, r_earth, v_earth, light_time=False)
    np.testing.assert_allclose(aberrated_only, aberrate(geometric, v_earth), atol=1e-15)
    full = apparent_direction(target, t, r_earth, v_earth)
    np.testing.assert_allclose(full, aberrate(astrometric, v_earth), atol=1e-15)
    # the light-time shift is the target's velocity across the line of sight times tau
    _, tau = light_time_vector(target, t, r_earth)
    v_mars = ephemeris.state("mars", t)[1]
    v_perp = v_mars - np.sum(v_mars * geometric, -1, keepdims=True) * geometric
    expected = np.linalg.norm(v_perp, axis=-1) * tau / np.linalg.norm(target(t) - r_earth, axis=-1)
    np.testing.assert_allclose(angle_between(astrometric, geometric), expected, rtol=1e-3)
    scalar = apparent_direction(target, float(t[0]), r_earth[0], v_earth[0])
    np.testing.assert_allclose(scalar, full[0], atol=1e-15)


def test_apparent_direction_of_mars_matches_astropy_gcrs():
    coordinates = pytest.importorskip("astropy.coordinates")
    t = T_2014 + np.linspace(0.0, 600.0 * DAY_S, 6)
    ephemeris = default_ephemeris()
    r_earth, v_earth = ephemeris.state("earth", t)
    ours = apparent_direction(lambda tt: ephemeris.position("mars", tt), t, r_earth, v_earth)
    gcrs = coordinates.get_body("mars", to_time(t), ephemeris=str(default_kernel_path()))
    theirs = unit(gcrs.cartesian.xyz.value.T)
    # astropy also bends light around the Sun (a few mas away from the Sun); we do not
    sun_elongation = angle_between(ephemeris.position("sun", t) - r_earth, ours)
    deflection_rad = 4.07e-3 * ARCSEC_RAD / np.tan(sun_elongation / 2)
    assert np.all(angle_between(ours, theirs) < deflection_rad + 1e-3 * ARCSEC_RAD)


def test_phobos_light_time_shift_is_moon_speed_times_light_time():
    ephemeris = default_ephemeris()
    r_mars, _ = ephemeris.state("mars", T_2014)
    r_phobos_mars, v_phobos_mars = ephemeris.state("phobos", T_2014, center="mars")
    # observer 20e6 km from Mars, looking at right angles to Phobos' orbital velocity
    los = unit(np.cross(r_phobos_mars, v_phobos_mars))
    r_observer = r_mars - 20.0e6 * los
    r_rel, tau = light_time_vector(lambda tt: ephemeris.position("phobos", tt), T_2014, r_observer)
    assert tau == pytest.approx(20.0e6 / C_KM_S, rel=1e-3)
    retarded_mars_phobos = ephemeris.position("phobos", T_2014 - tau, center="mars")
    shift_km = np.linalg.norm(retarded_mars_phobos - r_phobos_mars)
    # ~2.1 km/s x 66.7 s = 140 km; orbit curvature a n^2 tau^2 / 2 adds ~1 km
    assert shift_km == pytest.approx(np.linalg.norm(v_phobos_mars) * tau, abs=2.0)
    assert 120.0 < shift_km < 160.0
    np.testing.assert_allclose(r_observer + r_rel, ephemeris.position("phobos", T_2014 - tau), rtol=0, atol=1e-6)


def test_aberration_velocity_jacobian_matches_central_differences():
    from opnav.light import aberration_velocity_jacobian

    rng = np.random.default_rng(11)
    directions = unit(rng.normal(size=(20, 3)))
    v = np.array([5.0, 28.0, -3.0])
    jacobian = aberration_velocity_jacobian(directions, v)
    step = 1e-3  # km/s
    numeric = np.empty_like(jacobian)
    for j in range(3):
        delta = np.zeros(3)
        delta[j] = step
        numeric[:, :, j] = (aberrate(directions, v + delta) - aberrate(directions, v - delta)) / (2 * step)
    # entries are ~1/c = 3e-6 per km/s; rounding 1e-16 / step ~ 1e-13
    np.testing.assert_allclose(jacobian, numeric, rtol=0, atol=1e-12)
