"""CKs (type 3) and linear SCLKs written with spiceypy: an attitude history as SPICE kernels.

:func:`write_ck` writes a known attitude history (a pointing law's, a simulated spin) as one type 3
segment; :func:`write_linear_sclk` writes the simplest spacecraft clock a CK can be indexed by
(docs/formats/ck.md). :func:`opnav.ephemeris.ck.ck_attitude` reads them back.

A type 3 segment holds the pointing records (quaternions of the C-matrix, ``ICRF -> frame``) and
the starts of its interpolation intervals; between two records of an interval SPICE turns at a
constant rate about one axis (exact for a uniform spin about a fixed axis; for any other motion the
error at mid-interval is ``h^2 / 8 |dw/dt|`` to leading order, ``h`` the records' spacing, ``w``
the angular velocity).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from .spice import ICRF, KernelSet, spiceypy_module

#: Ticks per second of :func:`write_linear_sclk`'s clock: its fine field counts 1/65536 s.
TICKS_PER_S = 65536


def write_linear_sclk(path: str | Path, *, clock_id: int, start_tdb_s: float) -> Path:
    """Write a text SCLK kernel (type 1) of a clock that counts TDB seconds from ``start_tdb_s``.

    Two fields, ``SECONDS.FRACTION`` (``FRACTION`` in 1/65536 s): tick 0 is ``start_tdb_s``, and the
    clock runs at exactly one second per TDB second for 2^32 s (136 years), in one partition.

    Parameters
    ----------
    path : str or Path
        The file written (``.tsc``).
    clock_id : int, keyword-only
        The spacecraft clock's NAIF id (negative: the spacecraft's id, ``-77``).
    start_tdb_s : float, keyword-only
        TDB seconds past J2000 at which the clock reads 0.

    Returns
    -------
    Path
    """
    if not isinstance(clock_id, (int, np.integer)) or clock_id >= 0:
        raise InputError(f"clock_id must be a negative integer (a spacecraft's NAIF id), got {clock_id!r}")
    if not np.isfinite(start_tdb_s):
        raise InputError(f"start_tdb_s must be finite, got {start_tdb_s!r}")
    n = -int(clock_id)
    path = Path(path)
    # SCLK01_COEFFICIENTS: (encoded ticks, parallel time = TDB s past J2000, rate = parallel seconds
    # per count of the first field); TIME_SYSTEM 1 makes the parallel time TDB.
    path.write_text(
        "KPL/SCLK\n\nA linear clock written by opnav.ephemeris.ck_writer.write_linear_sclk: "
        f"tick 0 at TDB {start_tdb_s!r} s past J2000, one clock second per TDB second.\n\n"
        "\\begindata\n"
        "SCLK_KERNEL_ID                = ( @2000-01-01/12:00 )\n"
        f"SCLK_DATA_TYPE_{n}            = ( 1 )\n"
        f"SCLK01_TIME_SYSTEM_{n}        = ( 1 )\n"
        f"SCLK01_N_FIELDS_{n}           = ( 2 )\n"
        f"SCLK01_MODULI_{n}             = ( 4294967296 {TICKS_PER_S} )\n"
        f"SCLK01_OFFSETS_{n}            = ( 0 0 )\n"
        f"SCLK01_OUTPUT_DELIM_{n}       = ( 1 )\n"
        f"SCLK_PARTITION_START_{n}      = ( 0 )\n"
        f"SCLK_PARTITION_END_{n}        = ( {4294967296 * TICKS_PER_S - 1} )\n"
        f"SCLK01_COEFFICIENTS_{n}       = ( 0 {float(start_tdb_s)!r} 1.0 )\n"
        "\\begintext\n")
    return path


def write_ck(path: str | Path, t: np.ndarray, attitudes: Rotation, *, ck_id: int, sclk: str | Path,
             segment_id: str = "opnav attitude") -> Path:
    """Write the attitude history ``attitudes`` at ``t`` as a CK of one type 3 segment, one interval.

    Parameters
    ----------
    path : str or Path
        The file written (``.bc``); an existing file is replaced.
    t : (N,) array
        TDB seconds past J2000, increasing, N >= 2.
    attitudes : Rotation of N
        ``R_icrf_frame`` (frame -> ICRF, docs/conventions.md) at ``t``.
    ck_id : int, keyword-only
        The CK structure's id, <= -1000 (``-77000``); its clock is ``ck_id / 1000`` truncated (``-77``),
        the clock an SCLK of :func:`write_linear_sclk` with that ``clock_id`` gives.
    sclk : str or Path, keyword-only
        The SCLK kernel of that clock (:func:`write_linear_sclk`), used to encode ``t``.
    segment_id : str, keyword-only
        The segment's name (at most 40 characters).

    Returns
    -------
    Path
    """
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.size < 2 or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0.0):
        raise InputError("t must be a 1-D array of at least 2 increasing, finite TDB epochs")
    if len(attitudes) != t.size:
        raise InputError(f"attitudes has {len(attitudes)} rotations for {t.size} epochs")
    sp = spiceypy_module()
    path = Path(path)
    path.unlink(missing_ok=True)  # ckopn refuses an existing file
    # SPICE's quaternion of a C-matrix (ICRF -> frame), scalar first
    quaternions = np.array([sp.m2q(m) for m in attitudes.inv().as_matrix()])
    if not isinstance(ck_id, (int, np.integer)) or ck_id > -1000:
        raise InputError(f"ck_id must be an integer <= -1000 (its clock is ck_id / 1000), got {ck_id!r}")
    with KernelSet([sclk]).loaded():
        clock = sp.ckmeta(int(ck_id), "SCLK")  # ck_id / 1000, truncated towards zero
        ticks = np.array([sp.sce2c(clock, float(x)) for x in t])
        handle = sp.ckopn(str(path), segment_id[:40], 0)
        try:
            sp.ckw03(handle, ticks[0], ticks[-1], int(ck_id), ICRF, False, segment_id[:40], t.size, ticks,
                     quaternions, np.zeros((t.size, 3)), 1, [ticks[0]])
        finally:
            sp.ckcls(handle)
    return path


__all__ = ["TICKS_PER_S", "write_ck", "write_linear_sclk"]
