"""Time: float TDB seconds past J2000 inside, astropy ``Time`` at the edges.

J2000 is 2000-01-01 12:00:00 TDB (JD 2451545.0 TDB). Strings from files and the
CLI are parsed with an explicit scale (utc, tt, tdb, tai); calendar output is
produced only for files, the CLI and reports.

A fast exact path
-----------------
One date of the common kind (ISO ``YYYY-MM-DDTHH:MM:SS[.fff]`` text, or a modified Julian date)
is converted by :func:`parse_epoch` and :func:`mjd_tdb_seconds` with the pyerfa calls astropy's
``Time`` makes, in its order and with its two-part arithmetic (:func:`day_frac`), so the seconds
are the same bits; a one-frame ``opnav solve`` then never imports ``astropy.time`` nor reads
astropy's leap-second file (~80 ms of its start-up, to check that a header's epoch keywords
agree). The path is taken only where its answer cannot differ from astropy's: a valid calendar
date (no leap second written as ``:60``), no pyerfa warning (a "dubious year"), and a UTC (or a
TT/TAI whose TDB needs UT) date before the expiry of the leap-second table pyerfa holds (its own,
mid-2017, until astropy replaces it by a newer one in this process; both list the same leap seconds
up to then: ``tests/test_epochs_frames.py``). Every other input goes through astropy as before,
with its errors.
"""

from __future__ import annotations

import contextlib
import re
import warnings
from typing import TYPE_CHECKING

import numpy as np

from .constants import TIME_SCALES
from .errors import InputError

if TYPE_CHECKING:  # astropy.time is imported where a Time is made or read
    from astropy.time import Time

J2000_JD = 2_451_545.0
#: Julian date of MJD 0 (erfa.DJM0).
MJD0_JD = 2_400_000.5

#: The ISO 8601 text the fast path reads (astropy's ``isot`` in full, seconds with or without a fraction).
_ISO_TEXT = re.compile(r"(\d{4})-(\d{2})-(\d{2})T(\d{2}):(\d{2}):(\d{2})(?:\.(\d+))?")
_MONTH_DAYS = (31, 28, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31)


def tdb_seconds(time: Time) -> np.ndarray | float:
    """Convert an astropy ``Time`` (any scale) to TDB seconds past J2000.

    The two-part Julian date is differenced before scaling so that a
    microsecond survives at any epoch.
    """
    tdb = time.tdb
    seconds = ((tdb.jd1 - J2000_JD) + tdb.jd2) * 86_400.0
    return float(seconds) if np.ndim(seconds) == 0 else np.asarray(seconds)


def to_time(t_tdb_s: float | np.ndarray) -> Time:
    """TDB seconds past J2000 -> astropy ``Time`` in the TDB scale."""
    from astropy.time import Time

    t = np.asarray(t_tdb_s, dtype=float)
    days = np.floor(t / 86_400.0)
    return Time(J2000_JD + days, (t - days * 86_400.0) / 86_400.0, format="jd", scale="tdb")


def _two_sum(a, b):
    """``a + b`` and its rounding error (Shewchuk 1997), as ``astropy.time.utils.two_sum``."""
    x = a + b
    eb = x - a
    ea = x - eb
    eb = b - eb
    ea = a - ea
    return x, ea + eb


def day_frac(val1, val2):
    """``val1 + val2`` as a whole number and a fraction in [-0.5, 0.5]: ``astropy.time.utils.day_frac``
    without a factor or divisor, the same operations (so the same bits), without importing astropy."""
    sum12, err12 = _two_sum(np.float64(val1), np.float64(val2))
    day = np.round(sum12)
    frac, check = _two_sum(sum12 - day, err12)
    excess = np.where(frac * np.sign(check) != 0.5, np.round(frac), np.round(frac + 2 * check))
    day += excess
    frac = sum12 - day
    frac += err12
    return day, frac


def _tdb_seconds_fast(jd1, jd2, scale: str) -> float | None:
    """TDB seconds past J2000 of the two-part Julian date ``(jd1, jd2)`` in ``scale``, as astropy's
    ``Time(...).tdb`` computes them (its hops utc -> tai -> tt -> tdb, TDB - TT at the geocentre from
    UT taken as UTC), or None where astropy's answer may differ (module docstring: a warning from pyerfa,
    a date past the expiry of pyerfa's leap-second table)."""
    import erfa

    # a day's margin: the date is in its own scale, up to a minute from UTC
    if scale != "tdb" and jd1 + jd2 - MJD0_JD >= _leap_table_expiry_mjd() - 1.0:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a "dubious year" and the like: astropy's path decides
        try:
            if scale == "utc":
                jd1, jd2 = erfa.utctai(jd1, jd2)
                scale = "tai"
            if scale == "tai":
                jd1, jd2 = erfa.taitt(jd1, jd2)
                scale = "tt"
            if scale == "tt":
                utc1, utc2 = erfa.taiutc(*erfa.tttai(jd1, jd2))
                ut = day_frac(utc1 - 0.5, utc2)[1]
                jd1, jd2 = erfa.tttdb(jd1, jd2, erfa.dtdb(jd1, jd2, ut, 0.0, 0.0, 0.0))
        except (Warning, erfa.ErfaError, ValueError):
            return None
    jd1, jd2 = day_frac(jd1, jd2)
    return float(((jd1 - J2000_JD) + jd2) * 86_400.0)


def _leap_table_expiry_mjd() -> float:
    """MJD (UTC) at which the leap-second table pyerfa holds now expires (its own, or the newer one
    astropy set in this process)."""
    import datetime

    import erfa

    return float((erfa.leap_seconds.expires - datetime.datetime(1858, 11, 17)).days)


def _iso_fields(text: str) -> tuple[int, int, int, int, int, float] | None:
    """(year, month, day, hour, minute, second) of ISO text ``YYYY-MM-DDTHH:MM:SS[.fff]`` naming a valid
    moment (no leap second), the seconds summed digit by digit as astropy's fast parser does; None otherwise."""
    match = _ISO_TEXT.fullmatch(text)
    if match is None:
        return None
    year, month, day, hour, minute, whole = (int(v) for v in match.groups()[:6])
    if not (1 <= month <= 12 and hour <= 23 and minute <= 59 and whole <= 59):
        return None
    leap = year % 4 == 0 and (year % 100 != 0 or year % 400 == 0)
    if not 1 <= day <= _MONTH_DAYS[month - 1] + (1 if month == 2 and leap else 0):
        return None
    fraction, scale = 0.0, 0.1
    for digit in match.group(7) or "":  # astropy's parse_frac_from_char_array, operation for operation
        fraction += int(digit) * scale
        scale /= 10.0
    return year, month, day, hour, minute, float(whole) + fraction


def _parse_one_fast(text: str, scale: str) -> float | None:
    """:func:`parse_epoch` of one text by the fast path, or None where it does not apply."""
    fields = _iso_fields(text)
    if fields is None:
        return None
    import erfa

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            jd1, jd2 = erfa.dtf2d(scale.upper(), *fields)
        except (Warning, erfa.ErfaError, ValueError):
            return None
    return _tdb_seconds_fast(*day_frac(jd1, jd2), scale)


@contextlib.contextmanager
def _without_dubious_year():
    """A context in which pyerfa's "dubious year" warnings are not shown: a UTC date outside its
    leap-second table (before 1960, or past the table's expiry) is converted with the nearest known
    offset, as astropy and SPICE do; the warning's lines would stand before a command's one-line
    answer or error and say nothing the user can act on."""
    import erfa

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", erfa.ErfaWarning)
        yield


def parse_epoch(text: str | list[str], scale: str = "utc") -> float | np.ndarray:
    """Parse ISO-8601 calendar text in ``scale`` to TDB seconds past J2000.

    Parameters
    ----------
    text : str or list of str
        e.g. ``"2013-12-12T12:00:00"``. A trailing ``Z`` is accepted for UTC.
    scale : {"utc", "tt", "tdb", "tai"}
        Time scale the text is written in.

    Raises
    ------
    InputError
        For an unknown scale or text that is not a date.
    """
    if not isinstance(scale, str) or scale.lower() not in TIME_SCALES:
        raise InputError(f"unknown time scale {scale!r}; expected one of {', '.join(TIME_SCALES)}")
    scale = scale.lower()
    items = [text] if isinstance(text, str) else list(text) if isinstance(text, (list, tuple)) else [text]
    if not items or not all(isinstance(s, str) for s in items):
        raise InputError(f"an epoch is calendar text such as '2014-07-15T00:00:00', got {text!r}")
    cleaned = [s.strip().removesuffix("Z") for s in items]
    if isinstance(text, str):
        seconds = _parse_one_fast(cleaned[0], scale)
        if seconds is not None:
            return seconds
    from astropy.time import Time

    with _without_dubious_year():
        try:
            time = Time(cleaned, format="isot", scale=scale)
        except ValueError:
            try:
                time = Time(cleaned, scale=scale)
            except ValueError:
                # astropy lists every format it tried, ten lines that do not say what was wrong
                raise InputError(f"cannot parse epoch {text!r} as a {scale.upper()} date; expected ISO 8601 "
                                 "such as '2014-07-15T00:00:00' with a valid month, day and time") from None
        seconds = tdb_seconds(time)
    return float(seconds[0]) if isinstance(text, str) else seconds


def mjd_tdb_seconds(mjd: float, scale: str) -> float:
    """A modified Julian date in ``scale`` (utc, tt, tdb, tai) as TDB seconds past J2000:
    ``tdb_seconds(Time(mjd, format="mjd", scale=scale))``, by the fast path where it applies."""
    scale = scale.lower()
    if scale not in TIME_SCALES:
        raise InputError(f"unknown time scale {scale!r}; expected one of {', '.join(TIME_SCALES)}")
    jd1, jd2 = day_frac(float(mjd), 0.0)
    jd1 += MJD0_JD  # astropy's TimeMJD.set_jds
    seconds = _tdb_seconds_fast(*day_frac(jd1, jd2), scale) if np.isfinite(mjd) else None
    if seconds is not None:
        return seconds
    from astropy.time import Time

    with _without_dubious_year():
        return float(tdb_seconds(Time(float(mjd), format="mjd", scale=scale)))


def format_epoch(t_tdb_s: float | np.ndarray, scale: str = "utc", precision: int = 3) -> str | list[str]:
    """TDB seconds past J2000 -> ISO-8601 text in ``scale`` (for files and reports)."""
    scale = scale.lower()
    if scale not in TIME_SCALES:
        raise InputError(f"unknown time scale {scale!r}; expected one of {', '.join(TIME_SCALES)}")
    with _without_dubious_year():
        time = getattr(to_time(t_tdb_s), scale)
        time.precision = precision
        return time.isot if np.ndim(t_tdb_s) == 0 else list(time.isot)


def utc_text(t_tdb_s: float, precision: int = 3) -> str:
    """``format_epoch(t_tdb_s, "utc", precision)`` of one epoch without a UTC conversion of astropy's.

    The same pyerfa calls in astropy's order (TDB -> TT with TDB - TT at the geocentre, TT -> TAI ->
    UTC, then ``d2dtf``), with pyerfa's built-in leap-second table: astropy's first UTC conversion in
    a process reads its leap-second file, ~60 ms of a one-frame ``opnav solve`` (:func:`day_frac` is astropy's
    two-part date as ``to_time`` builds it, without importing astropy.time). The two tables hold
    the same leap seconds (none has been added since 2017); dates beyond its table take the last
    offset, pyerfa's "dubious year" warning not shown (as inside ``format_epoch``).
    """
    import erfa

    t = float(t_tdb_s)
    days = np.floor(t / 86_400.0)
    jd1, jd2 = day_frac(J2000_JD + days, (t - days * 86_400.0) / 86_400.0)
    # UT for TDB - TT from the date read as TT, as astropy does without an observer location
    with _without_dubious_year():
        utc1, utc2 = erfa.taiutc(*erfa.tttai(jd1, jd2))
        ut = day_frac(utc1 - 0.5, utc2)[1]
        tt = erfa.tdbtt(jd1, jd2, erfa.dtdb(jd1, jd2, ut, 0.0, 0.0, 0.0))
        year, month, day, hmsf = erfa.d2dtf("UTC", precision, *erfa.taiutc(*erfa.tttai(*tt)))
    hour, minute, second, fraction = (int(v) for v in hmsf)
    text = f"{int(year):04d}-{int(month):02d}-{int(day):02d}T{hour:02d}:{minute:02d}:{second:02d}"
    return text + (f".{fraction:0{precision}d}" if precision > 0 else "")


def describe_epoch(t_tdb_s: float) -> str:
    """``t_tdb_s`` for a message: the TDB calendar date with the seconds past J2000 beside it."""
    try:
        return f"{format_epoch(float(t_tdb_s), 'tdb', precision=0)} TDB ({float(t_tdb_s):.0f} s past J2000)"
    except (ValueError, OverflowError):
        return f"{float(t_tdb_s):.6g} TDB s past J2000"
