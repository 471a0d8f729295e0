"""DE421 planets: agreement with astropy reading the same kernel, chains, errors."""

from __future__ import annotations

import numpy as np
import pytest
from astropy import units as u
from astropy.coordinates import get_body_barycentric, get_body_barycentric_posvel

from opnav.constants import AU_KM, GM_KM3_S2
from opnav.ephemeris import Ephemeris, default_ephemeris
from opnav.ephemeris.planets import NAIF_ID, PlanetEphemeris, default_kernel_path, default_planets
from opnav.epochs import parse_epoch, to_time
from opnav.errors import EphemerisError

BODIES = ["sun", "mercury", "venus", "earth", "moon", "mars", "jupiter", "saturn"]
EPOCHS = parse_epoch(
    ["1950-01-01T00:00:00", "2000-01-01T12:00:00", "2013-12-12T12:00:00", "2014-08-31T00:00:00", "2049-06-30T00:00:00"],
    scale="tdb",
)


@pytest.mark.parametrize("body", BODIES)
def test_positions_match_astropy_with_the_same_kernel(body):
    r, _ = default_planets().state(body, EPOCHS)
    reference = get_body_barycentric(body, to_time(EPOCHS), ephemeris=str(default_kernel_path()))
    r_astropy = reference.xyz.to_value(u.km).T
    assert r.shape == (len(EPOCHS), 3)
    assert np.max(np.linalg.norm(r - r_astropy, axis=-1)) < 1e-3  # 1 m


@pytest.mark.parametrize("body", BODIES)
def test_velocities_match_astropy_with_the_same_kernel(body):
    _, v = default_planets().state(body, EPOCHS)
    _, reference = get_body_barycentric_posvel(body, to_time(EPOCHS), ephemeris=str(default_kernel_path()))
    v_astropy = reference.xyz.to_value(u.km / u.s).T
    assert np.max(np.linalg.norm(v - v_astropy, axis=-1)) < 1e-6  # 1 mm/s


def test_velocity_is_the_derivative_of_position():
    planets = default_planets()
    t = EPOCHS[1:4]
    step = 60.0
    for body in ("moon", "mars"):
        _, v = planets.state(body, t)
        v_numeric = (planets.position(body, t + step) - planets.position(body, t - step)) / (2 * step)
        # truncation step^2/6 |jerk|: Moon's ~1e-11 km/s^3 gives ~6e-9 km/s
        np.testing.assert_allclose(v, v_numeric, rtol=0, atol=1e-7)


def test_relative_states_and_scalar_shape():
    planets = default_planets()
    t = float(EPOCHS[2])
    r_earth_moon, v_earth_moon = planets.state("moon", t, center="earth")
    assert r_earth_moon.shape == v_earth_moon.shape == (3,)
    assert 356_000.0 < np.linalg.norm(r_earth_moon) < 407_000.0
    np.testing.assert_allclose(r_earth_moon, planets.position(301, t) - planets.position(399, t), atol=1e-8)
    # vis-viva around the Sun: Mars' heliocentric orbit energy matches an ellipse of a = 1.524 au
    r, v = planets.state("mars", t, center="sun")
    a_km = 1.0 / (2.0 / np.linalg.norm(r) - np.dot(v, v) / GM_KM3_S2["sun"])
    assert a_km / AU_KM == pytest.approx(1.5237, abs=0.003)


def test_ephemeris_facade_matches_planets_and_knows_the_moons():
    ephemeris = default_ephemeris()
    t = EPOCHS[2:4]
    np.testing.assert_allclose(
        ephemeris.position("mars", t, center="earth"), default_planets().position("mars", t, center="earth")
    )
    r_phobos, _ = ephemeris.state("phobos", t, center="sun")
    r_mars_phobos, _ = ephemeris.state("phobos", t, center="mars")
    np.testing.assert_allclose(r_phobos - default_planets().position("mars", t, center="sun"), r_mars_phobos, atol=1e-6)
    assert set(Ephemeris.known_bodies()) == set(NAIF_ID) | {"phobos", "deimos"}
    assert Ephemeris.check_body(" Phobos ") == "phobos"
    with pytest.raises(EphemerisError, match="unknown body 'vulcan'"):
        Ephemeris.check_body("vulcan")


def test_unknown_body_raises():
    with pytest.raises(EphemerisError, match="unknown body 'pluto_moon'"):
        default_planets().state("pluto_moon", 0.0)
    with pytest.raises(EphemerisError, match="NAIF 402"):
        default_planets().state(402, 0.0)
    with pytest.raises(EphemerisError, match="unknown body"):
        default_planets().state("mars", 0.0, center="vulcan")


@pytest.mark.parametrize("t", [-3.2e9, 1.75e9, np.nan])
def test_epoch_outside_coverage_raises(t):
    # DE421 covers 1899-07-29 .. 2053-10-09
    with pytest.raises(EphemerisError, match="epoch"):
        default_planets().state("earth", np.array([0.0, t]))


def test_missing_or_corrupt_kernel_raises(tmp_path):
    with pytest.raises(EphemerisError, match="not found"):
        PlanetEphemeris(tmp_path / "de999.bsp")
    corrupt = tmp_path / "corrupt.bsp"
    corrupt.write_bytes(b"\0" * 3000)
    with pytest.raises(EphemerisError, match="cannot read"):
        PlanetEphemeris(corrupt)
