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


def describe_epoch(t_tdb_s: float) -> str:
    """``t_tdb_s`` for a message: the TDB calendar date with the seconds past J2000 beside it."""
    try:
        return f"{format_epoch(float(t_tdb_s), 'tdb', precision=0)} TDB ({float(t_tdb_s):.0f} s past J2000)"
    except (ValueError, OverflowError):
        return f"{float(t_tdb_s):.6g} TDB s past J2000"
