"""Time: float TDB seconds past J2000 inside, astropy ``Time`` at the edges.

J2000 is 2000-01-01 12:00:00 TDB (JD 2451545.0 TDB). Strings from files and the
CLI are parsed with an explicit scale (utc, tt, tdb, tai); calendar output is
produced only for files, the CLI and reports.
"""

from __future__ import annotations

import numpy as np
from astropy.time import Time

from .constants import TIME_SCALES
from .errors import InputError

J2000_JD = 2_451_545.0


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
    t = np.asarray(t_tdb_s, dtype=float)
    days = np.floor(t / 86_400.0)
    return Time(J2000_JD + days, (t - days * 86_400.0) / 86_400.0, format="jd", scale="tdb")


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


def format_epoch(t_tdb_s: float | np.ndarray, scale: str = "utc", precision: int = 3) -> str | list[str]:
    """TDB seconds past J2000 -> ISO-8601 text in ``scale`` (for files and reports)."""
    scale = scale.lower()
    if scale not in TIME_SCALES:
        raise InputError(f"unknown time scale {scale!r}; expected one of {', '.join(TIME_SCALES)}")
    time = getattr(to_time(t_tdb_s), scale)
    time.precision = precision
    return time.isot if np.ndim(t_tdb_s) == 0 else list(time.isot)


def utc_text(t_tdb_s: float, precision: int = 3) -> str:
    """``format_epoch(t_tdb_s, "utc", precision)`` of one epoch without a UTC conversion of astropy's.

    The same pyerfa calls in astropy's order (TDB -> TT with TDB - TT at the geocentre, TT -> TAI ->
    UTC, then ``d2dtf``), with pyerfa's built-in leap-second table: astropy's first UTC conversion in
    a process reads its leap-second file, ~60 ms of a one-frame ``opnav solve``. The two tables hold
    the same leap seconds (none has been added since 2017); for dates beyond its table pyerfa warns of
    a "dubious year", as it does inside ``format_epoch``.
    """
    import erfa
    from astropy.time.utils import day_frac  # astropy's two-part date, as to_time builds it

    t = float(t_tdb_s)
    days = np.floor(t / 86_400.0)
    jd1, jd2 = day_frac(J2000_JD + days, (t - days * 86_400.0) / 86_400.0)
    # UT for TDB - TT from the date read as TT, as astropy does without an observer location
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
