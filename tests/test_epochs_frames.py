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


# --- the fast exact path (one ISO date or MJD without astropy.time) --------------------------------

_FAST_SCRIPT = r"""
import json, sys
import numpy as np
from opnav.epochs import mjd_tdb_seconds, parse_epoch
rng = np.random.default_rng(int(sys.argv[1]))
out = []
for k in range(int(sys.argv[2])):
    fields = (int(rng.integers(1958, 2040)), int(rng.integers(1, 13)), int(rng.integers(1, 29)),
              int(rng.integers(0, 24)), int(rng.integers(0, 60)), int(rng.integers(0, 60)))
    digits = "".join(str(d) for d in rng.integers(0, 10, int(rng.integers(0, 12))))
    text = "%04d-%02d-%02dT%02d:%02d:%02d" % fields + ("." + digits if digits else "")
    mjd = float(rng.uniform(36115.0, 88069.0))
    for scale in ("utc", "tt", "tai", "tdb"):
        out.append(["text", text, scale, parse_epoch(text, scale)])
        out.append(["mjd", mjd, scale, mjd_tdb_seconds(mjd, scale)])
print(json.dumps({"astropy_time": "astropy.time" in sys.modules, "values": out}))
"""


def _astropy_seconds(kind, value, scale) -> float:
    import warnings

    from astropy.time import Time

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "dubious year" past the leap-second tables
        time = Time([value], format="isot", scale=scale) if kind == "text" else Time(value, format="mjd", scale=scale)
        return float(np.ravel(tdb_seconds(time))[0])


@pytest.mark.filterwarnings("ignore:ERFA function")
def test_fast_epoch_path_gives_astropys_bits_in_a_fresh_process():
    # a process that has not loaded astropy (opnav solve): pyerfa's own leap-second table, no astropy.time
    # imported for dates before its expiry; every value (fast or astropy's where the fast path does not
    # apply) the same float as astropy's Time gives, here with astropy's newer table
    import json
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", _FAST_SCRIPT, "11", "120"], capture_output=True, text=True,
                          check=True)
    found = json.loads(done.stdout)
    for kind, value, scale, seconds in found["values"]:
        assert seconds == _astropy_seconds(kind, value, scale), (kind, value, scale)
    early = subprocess.run([sys.executable, "-c", _FAST_SCRIPT.replace("(1958, 2040)", "(1973, 2016)")
                            .replace("(36115.0, 88069.0)", "(41700.0, 57700.0)"), "12", "40"],
                           capture_output=True, text=True, check=True)
    assert json.loads(early.stdout)["astropy_time"] is False  # 1973-2016: the fast path throughout


def test_pyerfa_leap_seconds_are_astropys_up_to_their_expiry():
    # the fast path's premise: before its expiry, pyerfa's built-in table lists astropy's leap seconds
    import subprocess
    import sys

    script = "import erfa; print(erfa.leap_seconds.expires.isoformat()); print(erfa.leap_seconds.get().tolist())"
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    expires, table = done.stdout.splitlines()
    import datetime

    import erfa
    from astropy.time import Time

    Time("2020-01-01T00:00:00", scale="utc").tdb  # astropy's first UTC conversion sets its own table in pyerfa
    assert erfa.leap_seconds.expires > datetime.datetime.fromisoformat(expires)
    limit = datetime.datetime.fromisoformat(expires)
    before = [(int(y), int(m), float(s)) for y, m, s in eval(table)]  # noqa: S307 - pyerfa's own printout
    listed = [(int(y), int(m), float(s)) for y, m, s in erfa.leap_seconds.get().tolist()
              if datetime.datetime(int(y), int(m), 1) < limit]
    assert len(listed) >= 40 and before == listed


def _outcome(parse, *args):
    try:
        return float(np.ravel(parse(*args))[0])
    except InputError as exc:
        return str(exc)


@pytest.mark.filterwarnings("ignore:ERFA function")
@pytest.mark.parametrize("text", ["2014-07-15", "2014-07-15T00:58", "2014-07-15 00:58:52.5", "2016-12-31T23:59:60.5",
                                  "2014-07-15T00:58:52.", " 2014-07-15T00:58:52.816274Z ", "2014-7-15T00:58:52",
                                  "2014-07-15T12:00:61", "2060-01-01T00:00:00", "1959-06-01T00:00:00"])
def test_one_date_parses_as_a_list_of_it_does(text):
    # a list goes through astropy's Time whole: one text, fast or not, must give its value or its error
    for scale in ("utc", "tt", "tai", "tdb"):
        single, listed = _outcome(parse_epoch, text, scale), _outcome(parse_epoch, [text], scale)
        if isinstance(listed, str):  # the same error, which names the text as given
            listed = listed.replace(repr([text]), repr(text))
        assert single == listed, (text, scale)


@pytest.mark.parametrize("bad", ["2014-02-29T00:00:00", "2014-07-15T24:00:00", "2014-07-15T23:61:00",
                                 "2014-00-10T00:00:00"])
def test_invalid_fields_are_refused_as_before(bad):
    with pytest.raises(InputError, match="cannot parse epoch"):
        parse_epoch(bad, scale="utc")


def test_dates_past_the_leap_second_table_convert_without_a_warning():
    """A UTC date beyond pyerfa's leap-second table takes its last offset with no "dubious year"
    lines (they stood before `opnav propagate --at 2200-...`'s one-line error); the same seconds as
    the TDB text, which needs no table, give back."""
    import warnings

    from opnav.epochs import format_epoch, mjd_tdb_seconds, parse_epoch, utc_text

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        t = parse_epoch("2200-01-01T00:00:00")
        assert parse_epoch(["2200-01-01T00:00:00"])[0] == t
        assert abs(mjd_tdb_seconds(124_593.0, "utc") - t) < 1e-5  # MJD of 2200-01-01
        assert format_epoch(t, "utc", precision=0) == "2200-01-01T00:00:00" == utc_text(t, precision=0)
        # 37 s TAI - UTC since 2017, and TT - TAI 32.184 s: TDB within 2 ms of TT
        assert abs(t - parse_epoch("2200-01-01T00:01:09.184", "tdb")) < 2e-3
