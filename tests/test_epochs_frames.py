"""Time scales (opnav.epochs) and directions/frames (opnav.frames)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from opnav.constants import ARCSEC_RAD
from opnav.epochs import format_epoch, parse_epoch, tdb_seconds, to_time
from opnav.errors import InputError
from opnav.frames import (
    R_ECLIPTIC_ICRF,
    angle_between,
    ecliptic_to_icrf,
    icrf_to_ecliptic,
    radec_to_unit,
    unit,
    unit_to_radec,
)

MICROSECOND = 1e-6

# --- epochs ---------------------------------------------------------------------------------------


def test_j2000_is_zero():
    assert parse_epoch("2000-01-01T12:00:00", scale="tdb") == 0.0
    # TT and TDB differ by < 2 ms (periodic terms); UTC = TT - 64.184 s at J2000
    assert abs(parse_epoch("2000-01-01T12:00:00", scale="tt")) < 2e-3
    assert abs(parse_epoch("2000-01-01T11:58:55.816", scale="utc")) < 2e-3


def test_scale_offsets_are_the_defined_ones():
    text = "2014-06-01T00:00:00"
    tai = parse_epoch(text, scale="tai")
    assert parse_epoch(text, scale="tt") - tai == pytest.approx(-32.184, abs=MICROSECOND)
    assert parse_epoch(text, scale="utc") - tai == pytest.approx(35.0, abs=MICROSECOND)  # TAI - UTC in 2014


# ERFA flags UTC years without a known leap-second table ("dubious year"); harmless here
@pytest.mark.filterwarnings("ignore:.*dubious year")
@pytest.mark.parametrize("scale", ["utc", "tt", "tdb", "tai"])
@pytest.mark.parametrize(
    "text",
    [
        "2013-12-12T12:00:00.000000",
        "1999-03-04T05:06:07.891234",
        "2039-12-31T23:59:59.999999",
        "2016-12-31T12:00:00.000001",
    ],
)
def test_string_round_trip_to_the_microsecond(text, scale):
    assert format_epoch(parse_epoch(text, scale=scale), scale=scale, precision=6) == text


def test_leap_second_is_kept_in_utc():
    t = parse_epoch("2016-12-31T23:59:60.500000", scale="utc")
    assert parse_epoch("2017-01-01T00:00:00", scale="utc") - t == pytest.approx(0.5, abs=MICROSECOND)
    assert format_epoch(t, scale="utc", precision=6) == "2016-12-31T23:59:60.500000"


def test_list_input_and_trailing_z():
    t = parse_epoch(["2014-01-01T00:00:00Z", "2014-01-02T00:00:00Z"], scale="utc")
    assert isinstance(t, np.ndarray) and t.shape == (2,)
    assert t[1] == parse_epoch("2014-01-02T00:00:00", scale="utc")
    # a UTC day is 86400 SI s; TDB - TT drifts by up to 30 us a day
    assert t[1] - t[0] == pytest.approx(86_400.0, abs=35 * MICROSECOND)
    assert format_epoch(t, scale="utc", precision=0) == ["2014-01-01T00:00:00", "2014-01-02T00:00:00"]


@given(st.floats(min_value=-3.2e9, max_value=3.2e9, allow_nan=False))
@example(0.0)
@example(-0.5)
@example(86_399.9999995)
def test_time_object_round_trip_to_the_microsecond(t):
    assert tdb_seconds(to_time(t)) == pytest.approx(t, abs=MICROSECOND)


@pytest.mark.filterwarnings("ignore:.*dubious year")
@given(st.floats(min_value=-3.1e9, max_value=3.1e9, allow_nan=False))
@example(0.0)
def test_text_round_trip_of_seconds_to_the_microsecond(t):
    text = format_epoch(t, scale="tt", precision=6)
    # six decimals round to half a microsecond; the two-part JD keeps the rest
    assert parse_epoch(text, scale="tt") == pytest.approx(t, abs=MICROSECOND)


@pytest.mark.parametrize("bad", ["2014-13-01T00:00:00", "yesterday", "2014-02-30T00:00:00", ""])
def test_malformed_date_raises_input_error(bad):
    with pytest.raises(InputError, match="cannot parse epoch"):
        parse_epoch(bad, scale="utc")


def test_unknown_scale_raises_input_error():
    with pytest.raises(InputError, match="unknown time scale 'ut2'"):
        parse_epoch("2014-01-01T00:00:00", scale="ut2")
    with pytest.raises(InputError, match="unknown time scale 'gps'"):
        format_epoch(0.0, scale="gps")


# --- frames ---------------------------------------------------------------------------------------

@given(
    st.floats(min_value=-10.0, max_value=10.0, allow_nan=False),
    st.floats(min_value=-np.pi / 2, max_value=np.pi / 2, allow_nan=False),
)
@example(0.0, np.pi / 2)
@example(1.0, -np.pi / 2)
@example(2 * np.pi, 0.0)
@example(-1e-300, 0.3)
def test_radec_unit_round_trip(ra, dec):
    u = radec_to_unit(ra, dec)
    assert np.linalg.norm(u) == pytest.approx(1.0, abs=1e-15)
    ra_back, dec_back = unit_to_radec(u)
    assert 0.0 <= ra_back < 2 * np.pi
    assert dec_back == pytest.approx(dec, abs=1e-15)
    # at the poles RA is undefined, so compare directions, not RA
    assert angle_between(radec_to_unit(ra_back, dec_back), u) < 1e-15
    if abs(dec) < np.pi / 2 - 1e-6:
        assert np.cos(ra_back - ra) == pytest.approx(1.0, abs=1e-15)
        assert np.sin(ra_back - ra) == pytest.approx(0.0, abs=1e-14)


@given(st.tuples(*(st.floats(min_value=-1e6, max_value=1e6, allow_nan=False) for _ in range(3))))
@example((0.0, 0.0, 5.0))
@example((0.0, 0.0, -1e-12))
@example((-3.0, -0.0, 0.0))
def test_unit_to_radec_of_any_vector_recovers_its_direction(vector):
    v = np.array(vector)
    if np.linalg.norm(v) < 1e-100:
        return
    ra, dec = unit_to_radec(v)
    assert angle_between(radec_to_unit(ra, dec), v) < 2e-15


def test_radec_is_vectorised():
    ra = np.linspace(0.0, 6.0, 12).reshape(3, 4)
    dec = np.linspace(-1.5, 1.5, 12).reshape(3, 4)
    u = radec_to_unit(ra, dec)
    assert u.shape == (3, 4, 3)
    ra_back, dec_back = unit_to_radec(u)
    np.testing.assert_allclose(ra_back, ra, atol=1e-14)
    np.testing.assert_allclose(dec_back, dec, atol=1e-15)


def test_ecliptic_pole_and_equinox():
    pole_icrf = ecliptic_to_icrf(np.array([0.0, 0.0, 1.0]))
    ra, dec = unit_to_radec(pole_icrf)
    obliquity_deg = 23 + 26 / 60 + 21.448 / 3600  # 84381.448", J2000
    assert np.degrees(dec) == pytest.approx(90.0 - obliquity_deg, abs=1e-10)
    assert np.degrees(ra) == pytest.approx(270.0, abs=1e-10)
    # the equinox (x axis) is common to both frames
    np.testing.assert_allclose(icrf_to_ecliptic(np.array([1.0, 0.0, 0.0])), [1.0, 0.0, 0.0], atol=1e-16)
    # the ICRF north pole has ecliptic latitude 90 - obliquity, longitude 90 deg
    lon, lat = unit_to_radec(icrf_to_ecliptic(np.array([0.0, 0.0, 1.0])))
    assert np.degrees(lat) == pytest.approx(90.0 - obliquity_deg, abs=1e-10)
    assert np.degrees(lon) == pytest.approx(90.0, abs=1e-10)


def test_ecliptic_rotation_is_orthonormal_and_inverts():
    np.testing.assert_allclose(R_ECLIPTIC_ICRF @ R_ECLIPTIC_ICRF.T, np.eye(3), atol=1e-16)
    assert np.linalg.det(R_ECLIPTIC_ICRF) == pytest.approx(1.0, abs=1e-15)
    rng = np.random.default_rng(3)
    v = rng.normal(size=(10, 3)) * 1e8
    np.testing.assert_allclose(ecliptic_to_icrf(icrf_to_ecliptic(v)), v, rtol=0, atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(icrf_to_ecliptic(v), axis=-1), np.linalg.norm(v, axis=-1), rtol=1e-15)


def test_angle_between_closed_forms_and_precision():
    x, y = np.array([1.0, 0.0, 0.0]), np.array([0.0, 2.0, 0.0])
    assert angle_between(x, y) == pytest.approx(np.pi / 2, abs=1e-16)
    assert angle_between(x, -3 * x) == pytest.approx(np.pi, abs=1e-16)
    assert angle_between(x, 7 * x) == 0.0
    # 1 micro-arcsec: arccos of a dot product would return 0 or 1e-8 here
    tiny = 1e-6 * ARCSEC_RAD
    assert angle_between(x, np.array([np.cos(tiny), np.sin(tiny), 0.0])) == pytest.approx(tiny, rel=1e-9)
    near_pi = np.pi - tiny
    assert angle_between(x, np.array([np.cos(near_pi), np.sin(near_pi), 0.0])) == pytest.approx(near_pi, rel=1e-15)
    a = np.array([[1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(angle_between(a, x), [np.pi / 4, np.pi / 2], atol=1e-15)


def test_unit_rejects_zero_and_non_finite():
    np.testing.assert_allclose(unit(np.array([3.0, 0.0, 4.0])), [0.6, 0.0, 0.8])
    with pytest.raises(InputError, match="zero-length"):
        unit(np.zeros(3))
    with pytest.raises(InputError, match="non-finite"):
        unit(np.array([[1.0, 0.0, 0.0], [np.nan, 0.0, 0.0]]))


@pytest.mark.filterwarnings("ignore:ERFA function")  # dates past pyerfa's leap-second table: "dubious year"
def test_utc_text_is_format_epoch_without_astropys_utc_conversion():
    # opnav solve prints its frames' dates with utc_text (no leap-second file read); the text must be
    # format_epoch's, leap seconds and every precision included
    from opnav.epochs import utc_text

    rng = np.random.default_rng(7)
    epochs = list(rng.uniform(-3e8, 1.3e9, 300))  # 1990-2041
    for leap in ("2015-06-30T23:59:59", "2016-12-31T23:59:59", "2008-12-31T23:59:59"):
        epochs += list(parse_epoch(leap, "utc") + np.linspace(-1.5, 2.5, 41))  # across the leap second
    for t in epochs:
        for precision in (0, 3, 6):
            assert utc_text(float(t), precision) == format_epoch(float(t), "utc", precision)
