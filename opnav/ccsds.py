"""CCSDS Orbit Ephemeris Messages (OEM) and Tracking Data Messages (TDM), through ccsds-ndm.

Messages are read by the ``ccsds-ndm`` package (its xsdata object models, its KVN
parser) and written by it (its KVN writer and XML serializer), except the KVN data
lines, which this module formats in that writer's layout (see :func:`_write_kvn`) and,
for a TDM, reads (``KEYWORD = EPOCH VALUE``; ccsds-ndm takes about 1 ms a line);
the TDM's covariance sidecar is plain CSV. The format follows the file name: a name ending in
``.xml`` is NDM/XML, anything else (``.oem``, ``.tdm``, ``.kvn``, ``.txt``) is KVN.
Files are written atomically (temporary file in the same folder, then rename).

OEM (CCSDS 502.0-B-2, ``CCSDS_OEM_VERS = 2.0``, NDM/XML schema 2.0.0)
    One segment. ``TIME_SYSTEM = TDB``; epochs are ISO calendar dates in TDB
    with microseconds. States are ``X Y Z`` in km and ``X_DOT Y_DOT Z_DOT`` in
    km/s, in ``REF_FRAME`` (default ICRF) with origin ``CENTER_NAME`` (default
    MARS), each number written with Python's shortest round-trip repr (17
    significant digits at most), so a read gives back the same doubles.
    Covariances, when given, are OEM covariance blocks (lower triangle, km**2,
    km**2/s, km**2/s**2) with an ``EPOCH`` each and ``COV_REF_FRAME`` equal to
    ``REF_FRAME``. ``OBJECT_NAME``/``OBJECT_ID`` name the spacecraft (a run's
    :attr:`opnav.studies.settings.RunFile.spacecraft`); ``INTERPOLATION = HERMITE``
    with ``INTERPOLATION_DEGREE = 3`` (:data:`OEM_INTERPOLATION`). OEM 2.0 rather
    than 3.0 because every OEM reader in use accepts 2.0; :func:`read_oem` reads both.

TDM (CCSDS 503.0-B-2, ``CCSDS_TDM_VERS = 2.0``, NDM/XML schema 4.0.0)
    ``radec`` and ``radec_pair`` records (:mod:`opnav.records`): the right
    ascension and declination of a target as seen from the spacecraft, ICRF.
    Keywords: ``ANGLE_TYPE = RADEC``, ``REFERENCE_FRAME = ICRF`` (allowed by TDM
    2.0), ``TIME_SYSTEM = TDB``, ``MODE = SEQUENTIAL``, ``PATH = 2,1`` with
    ``PARTICIPANT_1`` = the spacecraft (the observer, where the light is
    received) and ``PARTICIPANT_2`` = the target in upper case (where it comes
    from): in a TDM the path lists participants in the order the signal
    travels, as in the standard's own optical example (E-16). ``ANGLE_1`` is the
    right ascension in degrees in [0, 360), ``ANGLE_2`` the declination in
    degrees; they share an epoch, one pair per direction. One segment per
    (sensor, target); a ``radec_pair`` (two moons in one frame) gives one
    direction to each of its targets' segments, at the same epoch. KVN files
    have no blank line between ``META_STOP`` and ``DATA_START`` (``ccsds-ndm-py``
    refuses one there).

    TDM 2.0 has no keyword for an observation's uncertainty (``DATA_QUALITY`` is
    RAW/VALIDATED/DEGRADED, ``CORRECTION_ANGLE_n`` a bias applied or to apply), so
    the noise goes where the standard leaves room, in ``COMMENT`` lines of the
    segment metadata, which :func:`read_tdm` reads back exactly::

        COMMENT opnav target = phobos
        COMMENT opnav sensor = nac
        COMMENT opnav covariance_rad2 = 1e-10 0.0 0.0 2.5e-10

    (the 2x2 covariance of [ra, dec], row-major, rad**2, each number a Python
    repr; written when every record of the segment has that covariance, as in
    measurement mode). Nothing in a TDM ties two directions together, so every
    record's covariance is also written to a sidecar CSV beside the TDM,
    ``<tdm name>.cov.csv`` (:func:`tdm_sidecar`), one row per record in the
    records' order: ``epoch_tdb`` (the epoch text of its observations),
    ``t_tdb_s`` (exact), ``sensor``, ``target`` (``phobos+deimos`` for a pair),
    ``frame_id``, ``flags`` and ``covariance_rad2`` (row-major; 4x4 for a pair,
    [ra_1, dec_1, ra_2, dec_2], with the moon-moon cross-covariance their shared
    attitude error gives). :func:`read_tdm` reads the sidecar when it is there:
    the records come back as written, pairs included; a sidecar whose rows and
    the TDM's observations do not match one to one is refused.

Inside opnav time is TDB seconds past J2000 (2000-01-01T12:00:00 TDB, see
:mod:`opnav.epochs`), angles are radians, positions km, velocities km/s.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import logging
import math
import re
import warnings
from collections import Counter, defaultdict, deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from enum import Enum
from functools import lru_cache
from pathlib import Path

import erfa
import numpy as np
from ccsds_ndm.mapping import NDMFileFormats
from ccsds_ndm.models import ndmxml2 as _odm  # OEM 2.0 lives in the NDM/XML 2.0.0 models
from ccsds_ndm.models import ndmxml4 as _tdm  # TDM 2.0 lives in the NDM/XML 4.0.0 models
from ccsds_ndm.ndm_io import NdmIo
from xsdata.exceptions import ConverterWarning

from .epochs import J2000_JD, describe_epoch, format_epoch, parse_epoch
from .errors import InputError
from .frames import radec_to_unit, unit_to_radec
from .records import PAIR_SEPARATOR, Measurement, atomic_write_text, pair_targets

__all__ = ["OemData", "read_oem", "read_tdm", "tdm_sidecar", "write_oem", "write_tdm"]

log = logging.getLogger(__name__)

#: Decimal digits of the seconds in written epochs. Microseconds, not more: Python's
#: ``datetime.strptime('%f')`` and many other readers stop at six digits.
EPOCH_DIGITS = 6
_EPOCH_RESOLUTION_S = 10.0 ** -EPOCH_DIGITS
_WRITTEN_EPOCH = re.compile(r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}\.\d+")
_DAY_OF_YEAR_EPOCH = re.compile(r"\s*(-?\d{4})-(\d{3})T(.*)")

#: TIME_SYSTEM values read (as opnav.epochs scales); anything else is refused.
_TIME_SCALES = {"TDB": "tdb", "TT": "tt", "UTC": "utc", "TAI": "tai"}

_STATE_KEYS = ("x", "y", "z", "x_dot", "y_dot", "z_dot")
#: (row, column, model field) of the 21 lower-triangle covariance entries, in file order.
_COV_KEYS = tuple((i, j, f"c{_STATE_KEYS[i]}_{_STATE_KEYS[j]}") for i in range(6) for j in range(i + 1))

_XML_SCHEMA = {
    "OEM": "https://sanaregistry.org/r/ndmxml_unqualified/ndmxml-2.0.0-master-2.0.xsd",
    "TDM": "https://sanaregistry.org/r/ndmxml_unqualified/ndmxml-4.0.0-master-4.0.xsd",
}

_OPNAV_TAG = re.compile(r"\s*opnav\s+(\w+)\s*=\s*(.*?)\s*")
_TDM_HEADER_COMMENT = (
    "opnav optical navigation angles: ANGLE_1 = right ascension, ANGLE_2 = declination (deg, ICRF) "
    "of PARTICIPANT_2 (target) as seen from PARTICIPANT_1 (spacecraft); 'opnav covariance_rad2' "
    "in a segment is the [ra, dec] covariance of all its records, row-major, rad**2; every record's "
    "covariance (two targets of one frame: 4x4, with their cross-covariance) is in the sidecar "
    "<this file>.cov.csv"
)
#: The interpolation an OEM of opnav recommends: cubic Hermite (positions and velocities at the two
#: bracketing epochs). A filter's estimates jump at each update; two nodes keep a jump to its interval.
OEM_INTERPOLATION = ("HERMITE", 3)
_INTERPOLATIONS = ("HERMITE", "LAGRANGE", "LINEAR")

#: Symmetry tolerance, relative to sqrt(C_ii C_jj): rounding noise passes, a transposed entry does not.
_SYMMETRY_RTOL = 1e-9


@dataclass(frozen=True, eq=False)
class OemData:
    """States read from an OEM.

    Attributes
    ----------
    t_tdb_s : ndarray, shape (N,)
        Epochs, TDB seconds past J2000, strictly increasing.
    states : ndarray, shape (N, 6)
        [x, y, z] km and [vx, vy, vz] km/s of the object relative to ``center``,
        axes of ``ref_frame``.
    covariances : ndarray, shape (N, 6, 6), or None
        State covariances (km**2, km**2/s, km**2/s**2), same frame; ``None`` when
        the file has no covariance block, NaN at epochs that have none.
    center : str
        ``CENTER_NAME`` (origin of the states), as in the file.
    ref_frame : str
        ``REF_FRAME`` (axes of the states), as in the file.
    object_name : str
        ``OBJECT_NAME``.
    object_id : str
        ``OBJECT_ID``.
    interpolation : str
        ``INTERPOLATION`` of the first segment (``HERMITE``, ``LAGRANGE``, ``LINEAR``), "" when absent.
    interpolation_degree : int or None
        ``INTERPOLATION_DEGREE`` of the first segment.
    """

    t_tdb_s: np.ndarray
    states: np.ndarray
    covariances: np.ndarray | None
    center: str
    ref_frame: str
    object_name: str
    object_id: str = ""
    interpolation: str = ""
    interpolation_degree: int | None = None


# --- OEM ----------------------------------------------------------------------------------------


def write_oem(
    path: str | Path,
    t_tdb_s: Sequence[float] | np.ndarray,
    states: np.ndarray,
    covariances: np.ndarray | None = None,
    *,
    object_name: str = "opnav",
    object_id: str = "opnav",
    center: str = "MARS",
    ref_frame: str = "ICRF",
    originator: str = "opnav",
    comment: str | Sequence[str] | None = None,
    interpolation: tuple[str, int] | None = OEM_INTERPOLATION,
) -> None:
    """Write states (and covariances) as a one-segment CCSDS OEM 2.0, TIME_SYSTEM TDB.

    Parameters
    ----------
    path : str or Path
        Output file; ``.xml`` gives NDM/XML, any other name KVN. Replaced atomically.
    t_tdb_s : array_like, shape (N,)
        Epochs, TDB seconds past J2000, strictly increasing and at least 1 us apart
        (the file keeps microseconds).
    states : array_like, shape (N, 6)
        [x, y, z] km, [vx, vy, vz] km/s of the object relative to ``center``, axes
        of ``ref_frame`` (opnav's states are ICRF).
    covariances : array_like, shape (N, 6, 6), optional
        Symmetric state covariances, km**2, km**2/s, km**2/s**2, same frame.
        Written as OEM covariance blocks (lower triangle) at each epoch.
    object_name, object_id : str
        ``OBJECT_NAME`` and ``OBJECT_ID``.
    center : str
        ``CENTER_NAME``, the origin of the states (e.g. ``"MARS"``).
    ref_frame : str
        ``REF_FRAME`` and ``COV_REF_FRAME`` (e.g. ``"ICRF"``, ``"EME2000"``).
    originator : str
        ``ORIGINATOR`` in the header.
    comment : str or sequence of str, optional
        Metadata ``COMMENT`` lines (a string is split at line breaks).
    interpolation : (str, int) or None
        ``INTERPOLATION`` and ``INTERPOLATION_DEGREE``, the interpolation recommended between the
        epochs (default :data:`OEM_INTERPOLATION`, cubic Hermite); None leaves both out.

    Raises
    ------
    InputError
        For wrong shapes, NaN or infinity, epochs that do not increase, an
        asymmetric covariance, a name that cannot be a keyword value or an
        interpolation other than HERMITE, LAGRANGE or LINEAR with a degree >= 1.
    """
    path = Path(path)
    t, x, cov = _check_ephemeris(t_tdb_s, states, covariances)
    object_name = _keyword_value("object_name", object_name)
    object_id = _keyword_value("object_id", object_id)
    center = _keyword_value("center", center)
    ref_frame = _keyword_value("ref_frame", ref_frame)
    originator = _keyword_value("originator", originator)
    method, degree = _check_interpolation(interpolation)
    epochs = _format_epochs(t, "t_tdb_s")
    xml = _is_xml(path)
    metadata = _odm.OemMetadata(
        comment=_comment_lines(comment),
        object_name=object_name,
        object_id=object_id,
        center_name=center,
        ref_frame=ref_frame,
        time_system="TDB",
        start_time=epochs[0],
        stop_time=epochs[-1],
        interpolation=method,
        interpolation_degree=degree,
    )
    # KVN: ccsds-ndm writes the header and metadata, the rows are formatted here as its writer formats them
    vectors = _state_vectors(epochs, x) if xml else []
    blocks = _covariance_blocks(epochs, cov, ref_frame) if xml and cov is not None else []
    oem = _odm.Oem(
        header=_odm.NdmHeader(creation_date=_creation_date(), originator=originator),
        body=_odm.OemBody(segment=[_odm.OemSegment(
            metadata=metadata, data=_odm.OemData(state_vector=vectors, covariance_matrix=blocks))]),
    )
    if xml:
        _write_message(path, oem, "OEM")
    else:
        _write_kvn(path, oem, [_oem_kvn_rows(epochs, x, cov, ref_frame)])


def write_estimates_oem(path: str | Path, t_tdb_s: np.ndarray, states: np.ndarray, covariances: np.ndarray, *,
                        center: str, object_name: str = "opnav", object_id: str | None = None,
                        comment=None) -> int:
    """:func:`write_oem` of a filter's estimates after each record: the last estimate of each epoch
    (several records share a frame's epoch), probe states only (the first 6 of augmented states).

    ``t_tdb_s`` (N,) TDB s past J2000, non-decreasing; ``states`` (N, n >= 6) [r km, v km/s] and
    ``covariances`` (N, n, n), ICRF, relative to ``center``. ``object_name`` is the spacecraft
    (``OBJECT_NAME``; ``OBJECT_ID`` too unless ``object_id`` is given). Returns the number of epochs
    written.
    """
    t = np.asarray(t_tdb_s, dtype=float)
    last = np.r_[t[1:] > t[:-1], True] if t.size else np.zeros(0, bool)
    write_oem(path, t[last], np.asarray(states)[last, :6], np.asarray(covariances)[last, :6, :6],
              object_name=object_name, object_id=object_id or object_name, center=center.upper(), comment=comment)
    return int(last.sum())


def read_oem(path: str | Path) -> OemData:
    """Read a CCSDS OEM (2.0 or 3.0, KVN or XML) into TDB seconds, km and km/s.

    Segments are joined into one arc; they must share ``CENTER_NAME``,
    ``REF_FRAME`` and ``OBJECT_NAME`` and their epochs must increase across
    segment boundaries (a repeated boundary epoch is refused, not guessed at).
    ``TIME_SYSTEM`` may be TDB, TT, UTC or TAI; epochs are converted to TDB.
    Accelerations, if present, are ignored.

    Parameters
    ----------
    path : str or Path
        KVN or XML file; the format is recognised from the content.

    Returns
    -------
    OemData
        States in the file's ``REF_FRAME`` relative to its ``CENTER_NAME``.
        ``covariances`` is ``None`` without covariance blocks; epochs without a
        block get NaN, blocks at an epoch with no state are dropped with a warning.

    Raises
    ------
    InputError
        Missing, empty, binary or malformed file, a message that is not an OEM,
        an unsupported time system, a covariance in another frame; the message
        names the file.
    """
    path = Path(path)
    oem = _load(path, "OEM")
    times, rows, cov_epochs, cov_mats = [], [], [], []
    first = None
    for k, segment in enumerate(_segments(oem, path, "OEM"), start=1):
        where = f"{path}: OEM segment {k}"
        meta, data = _field(segment, "metadata", where), _field(segment, "data", where)
        names = tuple(_text(_field(meta, key, where), f"{where} {key.upper()}")
                      for key in ("object_name", "center_name", "ref_frame"))
        object_id = _text(getattr(meta, "object_id", None) or "", f"{where} OBJECT_ID", required=False)
        if first is None:
            first = (*names, object_id)
            interpolation = (_enum_text(getattr(meta, "interpolation", None)),
                             getattr(meta, "interpolation_degree", None))
        elif tuple(n.upper() for n in names) != tuple(n.upper() for n in first[:3]):
            raise InputError(f"{where}: OBJECT_NAME, CENTER_NAME or REF_FRAME {names} differ from segment 1's "
                             f"{first[:3]}; opnav reads one object, origin and frame per file")
        scale = _time_scale(meta, where)
        vectors = list(getattr(data, "state_vector", None) or [])
        if not vectors:
            raise InputError(f"{where}: no state vectors")
        epochs = [_epoch_text(getattr(v, "epoch", None), f"{where} state vector {i + 1}")
                  for i, v in enumerate(vectors)]
        times.append(_parse_epochs(epochs, scale, where))
        rows.extend(
            [_number(getattr(v, key, None), f"{where} {key.upper()} at {epoch}") for key in _STATE_KEYS]
            for v, epoch in zip(vectors, epochs)
        )
        blocks = list(getattr(data, "covariance_matrix", None) or [])
        if blocks:
            cov_epochs.append(_parse_epochs(
                [_epoch_text(getattr(b, "epoch", None), f"{where} covariance {i + 1}") for i, b in enumerate(blocks)],
                scale, where))
            cov_mats.extend(_covariance_matrix(b, names[2], where) for b in blocks)

    t = np.concatenate(times)
    steps = np.diff(t)
    if np.any(steps <= 0.0):
        k = int(np.argmax(steps <= 0.0))
        raise InputError(f"{path}: OEM epochs do not increase at {describe_epoch(t[k + 1])} "
                         "(overlapping or repeated segment boundary); opnav reads one continuous arc")
    covariances = None
    if cov_mats:
        covariances = _match_covariances(path, t, np.concatenate(cov_epochs), cov_mats)
    states = np.array(rows, dtype=float)
    for array in (t, states, covariances):
        if array is not None:
            array.flags.writeable = False
    object_name, center, ref_frame, object_id = first
    return OemData(t, states, covariances, center, ref_frame, object_name, object_id, *interpolation)


def _check_interpolation(interpolation) -> tuple[str | None, int | None]:
    if interpolation is None:
        return None, None
    try:
        method, degree = interpolation
    except (TypeError, ValueError):
        method, degree = None, None
    if (method not in _INTERPOLATIONS or isinstance(degree, bool) or not isinstance(degree, int)
            or degree < 1):
        raise InputError(f"interpolation must be (method, degree) with method one of {', '.join(_INTERPOLATIONS)} "
                         f"and degree an integer >= 1, got {interpolation!r}")
    return method, degree


def _check_ephemeris(t_tdb_s, states, covariances) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    try:
        t = np.array(t_tdb_s, dtype=float)
        x = np.array(states, dtype=float)
        cov = None if covariances is None else np.array(covariances, dtype=float)
    except (TypeError, ValueError):
        raise InputError("t_tdb_s, states and covariances must be arrays of numbers") from None
    if t.ndim != 1 or t.size == 0:
        raise InputError(f"t_tdb_s must have shape (N,) with N >= 1, got shape {t.shape}")
    n = t.size
    if x.shape != (n, 6):
        raise InputError(f"states must have shape ({n}, 6) to match t_tdb_s, got {x.shape}")
    if not np.all(np.isfinite(t)):
        raise InputError(f"t_tdb_s[{_first(~np.isfinite(t))}] is not a finite number")
    if not np.all(np.isfinite(x)):
        raise InputError(f"states[{_first(~np.all(np.isfinite(x), axis=1))}] contains NaN or infinity")
    if n > 1 and np.any(np.diff(t) <= 0.0):
        k = _first(np.diff(t) <= 0.0) + 1
        raise InputError(f"t_tdb_s must increase strictly; t_tdb_s[{k}] = {describe_epoch(t[k])} "
                         f"is not after t_tdb_s[{k - 1}] = {describe_epoch(t[k - 1])}")
    if cov is not None:
        if cov.shape != (n, 6, 6):
            raise InputError(f"covariances must have shape ({n}, 6, 6) to match t_tdb_s, got {cov.shape}")
        if not np.all(np.isfinite(cov)):
            raise InputError(f"covariances[{_first(~np.all(np.isfinite(cov), axis=(1, 2)))}] "
                             "contains NaN or infinity")
        diag = np.diagonal(cov, axis1=1, axis2=2)
        if np.any(diag < 0.0):
            raise InputError(f"covariances[{_first(np.any(diag < 0.0, axis=1))}] has a negative variance")
        scale = np.sqrt(diag[:, :, None] * diag[:, None, :])
        asymmetric = np.abs(cov - np.swapaxes(cov, 1, 2)) > _SYMMETRY_RTOL * scale
        if np.any(asymmetric):
            raise InputError(f"covariances[{_first(np.any(asymmetric, axis=(1, 2)))}] is not symmetric")
        # the file keeps one triangle; average so that a round trip of a symmetric matrix is exact
        cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    return t, x, cov


@lru_cache(maxsize=1)
def _covariance_entry_types() -> tuple:
    """``(model field, value type, units)`` of the 21 lower-triangle entries of an OEM covariance block, in
    ``_COV_KEYS`` order (found once: a 10-day arc at 10 s writes 86,400 blocks)."""
    units = {
        _odm.PositionCovarianceType: _odm.PositionCovarianceUnits.KM_2,
        _odm.PositionVelocityCovarianceType: _odm.PositionVelocityCovarianceUnits.KM_2_S,
        _odm.VelocityCovarianceType: _odm.VelocityCovarianceUnits.KM_2_S_2,
    }
    entries = []
    for i, j, name in _COV_KEYS:
        kind = (_odm.PositionCovarianceType if i < 3 else
                _odm.PositionVelocityCovarianceType if j < 3 else _odm.VelocityCovarianceType)
        entries.append((name, kind, units[kind]))
    return tuple(entries)


#: Flat positions (row-major in a 6x6 matrix) of the ``_COV_KEYS`` entries.
_COV_FLAT = np.array([6 * i + j for i, j, _ in _COV_KEYS])
#: (start, stop) in the 21 ``_COV_KEYS`` values of each lower-triangle row (1, 2, ..., 6 values).
_COV_ROWS = tuple((i * (i + 1) // 2, (i + 1) * (i + 2) // 2) for i in range(6))


def _state_vectors(epochs: list[str], x: np.ndarray) -> list:
    """OEM state vectors (the NDM/XML path; KVN rows are :func:`_oem_kvn_rows`)."""
    km, km_s = _odm.PositionUnits.KM, _odm.VelocityUnits.KM_S
    return [
        _odm.StateVectorAccType(
            epoch=epoch,
            x=_odm.PositionType(value=row[0], units=km),
            y=_odm.PositionType(value=row[1], units=km),
            z=_odm.PositionType(value=row[2], units=km),
            x_dot=_odm.VelocityType(value=row[3], units=km_s),
            y_dot=_odm.VelocityType(value=row[4], units=km_s),
            z_dot=_odm.VelocityType(value=row[5], units=km_s),
        )
        for epoch, row in zip(epochs, x.tolist())  # Python floats, as float() gives
    ]


def _oem_kvn_rows(epochs: list[str], x: np.ndarray, cov: np.ndarray | None, frame: str) -> str:
    """The data section of a one-segment KVN OEM as ccsds-ndm's KVN writer lays it out: each state
    vector on a line (epoch and six numbers, two blanks apart, a blank line between vectors), then
    the covariance blocks (``EPOCH``, ``COV_REF_FRAME``, the lower triangle row by row). Numbers are
    Python's shortest repr, as the writer's ``str(float)``; each line or block is one ``%`` format."""
    line = "  ".join(["%s"] + ["%r"] * 6)
    text = "\n\n".join([line % (epoch, *row) for epoch, row in zip(epochs, x.tolist())])
    if cov is None:
        return text
    block = "\n".join([f"{'EPOCH':<{_KEY_WIDTH}} = %s", f"{'COV_REF_FRAME':<{_KEY_WIDTH}} = {_percent(frame)}",
                       *("  ".join(["%r"] * (stop - start)) for start, stop in _COV_ROWS)])
    values = cov.reshape(len(cov), 36)[:, _COV_FLAT].tolist()
    return "\n".join([text, "", "COVARIANCE_START", *[block % (epoch, *row) for epoch, row in zip(epochs, values)],
                      "COVARIANCE_STOP"])


def _percent(text: str) -> str:
    """``text`` for a ``%`` format string (its ``%`` doubled)."""
    return text.replace("%", "%%")


def _covariance_blocks(epochs: list[str], cov: np.ndarray, frame: str) -> list:
    """OEM covariance blocks (lower triangle) of ``cov`` (N, 6, 6) at ``epochs``."""
    entry_types = _covariance_entry_types()
    values = cov.reshape(len(cov), 36)[:, _COV_FLAT].tolist()  # Python floats, as float() gives
    return [_odm.OemCovarianceMatrixType(epoch=epoch, cov_ref_frame=frame, **{
        name: kind(value=value, units=unit) for (name, kind, unit), value in zip(entry_types, row)})
        for epoch, row in zip(epochs, values)]


def _covariance_matrix(block, ref_frame: str, where: str) -> np.ndarray:
    epoch = getattr(block, "epoch", "?")
    frame = getattr(block, "cov_ref_frame", None)
    frame = ref_frame if frame is None else _text(frame, f"{where} COV_REF_FRAME at {epoch}")
    if frame.upper() != ref_frame.upper():
        raise InputError(f"{where}: covariance at {epoch} is in COV_REF_FRAME {frame}, not the state frame "
                         f"{ref_frame}; opnav does not rotate covariances")
    cov = np.empty((6, 6))
    for i, j, name in _COV_KEYS:
        cov[i, j] = cov[j, i] = _number(getattr(block, name, None), f"{where} {name.upper()} at {epoch}")
    return cov


def _match_covariances(path: Path, t: np.ndarray, t_cov: np.ndarray, mats: list[np.ndarray]) -> np.ndarray:
    out = np.full((t.size, 6, 6), np.nan)
    filled = np.zeros(t.size, dtype=bool)
    dropped = 0
    for tc, cov in zip(t_cov, mats):
        k = int(np.argmin(np.abs(t - tc)))
        # half the written resolution: the same epoch text parses to the same instant, a different one does not
        if abs(t[k] - tc) > 0.5 * _EPOCH_RESOLUTION_S:
            dropped += 1
            continue
        if filled[k]:
            raise InputError(f"{path}: two covariance blocks at {describe_epoch(t[k])}")
        out[k], filled[k] = cov, True
    if dropped:
        log.warning("%s: %d covariance block(s) at epochs with no state vector ignored", path, dropped)
    if not filled.all():
        log.warning("%s: %d of %d epochs have no covariance block; their covariances are NaN",
                    path, int((~filled).sum()), t.size)
    return out


# --- TDM ----------------------------------------------------------------------------------------

#: Suffix of a TDM's covariance sidecar (``measurements.tdm`` -> ``measurements.tdm.cov.csv``).
SIDECAR_SUFFIX = ".cov.csv"
_SIDECAR_COLUMNS = ("epoch_tdb", "t_tdb_s", "sensor", "target", "frame_id", "flags", "covariance_rad2")
#: The record kinds a TDM holds: one RA/Dec direction, or two sharing a frame's attitude.
_TDM_KINDS = ("radec", "radec_pair")


def tdm_sidecar(path: str | Path) -> Path:
    """The covariance sidecar of TDM ``path``: the same name with :data:`SIDECAR_SUFFIX` appended."""
    path = Path(path)
    return path.with_name(path.name + SIDECAR_SUFFIX)


def write_tdm(
    path: str | Path,
    records: Iterable[Measurement],
    *,
    originator: str = "opnav",
    participant: str = "opnav",
) -> int:
    """Write the ``radec`` and ``radec_pair`` records as a CCSDS TDM 2.0 of RADEC angles, TIME_SYSTEM
    TDB, and their covariances in a sidecar CSV beside it (:func:`tdm_sidecar`).

    Parameters
    ----------
    path : str or Path
        Output file; ``.xml`` gives NDM/XML, any other name KVN. Replaced atomically, as is
        its sidecar ``<path>.cov.csv``.
    records : iterable of Measurement
        ``radec`` records (value [ra, dec] rad of the target as seen from the spacecraft, ICRF,
        covariance 2x2 rad**2) and ``radec_pair`` records (two such directions in one frame, 4x4
        covariance with their cross-covariance). Other kinds are skipped.
    originator : str
        ``ORIGINATOR`` in the header.
    participant : str
        The spacecraft's name, ``PARTICIPANT_1`` of every segment.

    Returns
    -------
    int
        Number of records written (a ``radec_pair`` counts once).

    Raises
    ------
    InputError
        When there is no radec or radec_pair record (a TDM needs one observation), a record is
        unusable (NaN, covariance not symmetric positive definite, declination beyond +-90 deg,
        no target) or a name cannot be a keyword value.

    Notes
    -----
    One segment per (sensor, target); a pair's two directions go to their targets' segments at
    the pair's epoch. A TDM has no per-observation uncertainty: a segment whose records share
    one [ra, dec] covariance carries it in ``COMMENT opnav covariance_rad2``, and the sidecar
    holds every record's covariance (a pair's 4x4 one), exact epoch, frame and flags, in the
    records' order (module notes).
    """
    path = Path(path)
    originator = _keyword_value("originator", originator)
    participant = _keyword_value("participant", participant)
    records = list(records)
    for rec in records:
        if not isinstance(rec, Measurement):
            raise InputError(f"records must be opnav.records.Measurement, got {type(rec).__name__}")
    kept = [rec for rec in records if rec.kind in _TDM_KINDS]
    if not kept:
        raise InputError(f"none of the {len(records)} records is of kind radec or radec_pair; a TDM needs at "
                         f"least one angle observation, nothing written to {path}")
    if len(kept) < len(records):
        skipped = Counter(rec.kind for rec in records if rec.kind not in _TDM_KINDS)
        log.info("%s: %d records that are not radec skipped (%s)", path, sum(skipped.values()),
                 ", ".join(f"{kind}: {count}" for kind, count in sorted(skipped.items())))
    for rec, ok in zip(kept, _tdm_usable(kept).tolist()):
        if not ok:
            _check_tdm_record(rec)
    epochs = _format_epochs_any(np.array([rec.t_tdb_s for rec in kept]), "records' t_tdb_s")
    groups: dict[tuple[str, str], list[tuple[float, str, float, float, tuple]]] = {}
    for rec, epoch in zip(kept, epochs):
        targets = pair_targets(rec) if rec.kind == "radec_pair" else (rec.target,)
        for k, target in enumerate(targets):
            ra_deg = math.degrees(rec.value[2 * k]) % 360.0
            block = rec.covariance[2 * k:2 * k + 2, 2 * k:2 * k + 2]
            groups.setdefault((rec.sensor, target), []).append(
                # a tiny negative angle wraps to exactly 360, outside the schema's [-360, 360)
                (rec.t_tdb_s, epoch, 0.0 if ra_deg >= 360.0 else ra_deg, math.degrees(rec.value[2 * k + 1]),
                 tuple(block.ravel().tolist())))
    xml = _is_xml(path)
    angles = []
    for rows in groups.values():
        rows.sort(key=lambda row: row[0])  # stable: records of one epoch keep their order
        angles.append(([row[1] for row in rows], [row[2] for row in rows], [row[3] for row in rows]))
    # KVN: ccsds-ndm writes the header and each segment's metadata, the observations are formatted here
    segments = [_tdm_segment(key, {row[4] for row in rows}, ep, participant, path,
                             _tdm_observations(ep, ra, dec) if xml else [])
                for (key, rows), (ep, ra, dec) in zip(groups.items(), angles)]
    tdm = _tdm.Tdm(
        header=_tdm.TdmHeader(comment=[_TDM_HEADER_COMMENT], creation_date=_creation_date(), originator=originator),
        body=_tdm.TdmBody(segment=segments),
    )
    if xml:
        _write_message(path, tdm, "TDM")
    else:
        _write_kvn(path, tdm, [_tdm_kvn_rows(*segment) for segment in angles])
    _write_sidecar(tdm_sidecar(path), kept, epochs)
    return len(kept)


def read_tdm(path: str | Path, *, sigma_rad: float | None = None) -> list[Measurement]:
    """Read the RADEC angles of a CCSDS TDM (1.0 or 2.0, KVN or XML) as ``radec`` and ``radec_pair`` records.

    Parameters
    ----------
    path : str or Path
        KVN or XML file; the format is recognised from the content. When its sidecar
        ``<path>.cov.csv`` (:func:`tdm_sidecar`, written by :func:`write_tdm`) is beside it, every
        record's covariance, exact epoch, frame and flags come from there, and the two directions
        of a ``radec_pair`` become that pair again.
    sigma_rad : float, optional
        Angle noise (rad) for segments without an ``opnav covariance_rad2`` comment when there is
        no sidecar: their covariance is ``sigma_rad**2 * I``.

    Returns
    -------
    list of Measurement
        ``radec`` records (value [ra, dec] rad, ICRF, of the target as seen from the spacecraft;
        covariance rad**2) and, with a sidecar, ``radec_pair`` records: in the sidecar's order
        (the order they were written in), else in time order. The target is the ``opnav target``
        comment, else the participant that starts the PATH (lower case); the sensor is the
        ``opnav sensor`` comment, else "".

    Raises
    ------
    InputError
        Missing, empty, binary or malformed file; a segment with angles whose TIME_SYSTEM is not
        TDB/TT/UTC/TAI, whose ANGLE_TYPE is not RADEC or whose REFERENCE_FRAME is not ICRF or
        EME2000; a segment without covariance comment when there is no sidecar and ``sigma_rad``
        is not given; a sidecar that does not match the TDM's observations. The message names the
        file.

    Notes
    -----
    Observations other than ANGLE_1/ANGLE_2 (RANGE, MAG, ...) and angles without their partner
    at the same epoch are skipped and counted in a logged warning. EME2000 angles are rotated to
    ICRF by the IAU 2000 frame bias (about 23 mas); their covariance is kept as it is (the
    rotation changes it by ~1e-7 relative).
    """
    path = Path(path)
    if sigma_rad is not None and not (isinstance(sigma_rad, (int, float)) and math.isfinite(sigma_rad)
                                      and sigma_rad > 0.0):
        raise InputError(f"sigma_rad must be a positive number of radians, got {sigma_rad!r}")
    kvn_data: list[list[tuple[int, str]]] = []
    tdm = _load(path, "TDM", kvn_data=kvn_data)
    sidecar = tdm_sidecar(path)
    skipped: Counter[str] = Counter()
    parsed = _segments(tdm, path, "TDM")
    if kvn_data and len(kvn_data) != len(parsed):
        raise InputError(f"{path}: {len(kvn_data)} DATA_START lines for {len(parsed)} segments")
    segments = []
    for k, segment in enumerate(parsed, start=1):
        where = f"{path}: TDM segment {k}"
        angles = _kvn_observations(kvn_data[k - 1], where, path, skipped) if kvn_data else None
        segments.append(_read_tdm_segment(where, segment, skipped, angles))
    if skipped:
        log.warning("%s: %d observations that are not RADEC angle pairs skipped (%s)", path,
                    sum(skipped.values()), ", ".join(f"{key}: {n}" for key, n in sorted(skipped.items())))
    if sidecar.is_file():
        return _records_from_sidecar(sidecar, [s for s in segments if s is not None])
    records: list[Measurement] = []
    for segment in segments:
        if segment is None:
            continue
        cov = _tdm_covariance(segment.tags, sigma_rad, segment.where, sidecar)
        records.extend(Measurement(float(ti), "radec", [a, d], cov, target=segment.target, sensor=segment.sensor)
                       for ti, a, d in zip(segment.t, segment.ra, segment.dec))
    records.sort(key=lambda rec: rec.t_tdb_s)
    return records


def tdm_ready(records: Iterable[Measurement]) -> list[Measurement]:
    """The ``radec`` and ``radec_pair`` records :func:`write_tdm` accepts (usable values and covariance,
    targets, declinations within +-90 deg): a run's TDM of what it measured, leaving out what a filter
    would refuse anyway (the CSV keeps every record)."""
    kept = [rec for rec in records if rec.kind in _TDM_KINDS]
    return [rec for rec, ok in zip(kept, _tdm_usable(kept).tolist()) if ok or _tdm_fits(rec)]


def _tdm_fits(rec: Measurement) -> bool:
    try:
        _check_tdm_record(rec)
    except InputError:
        return False
    return True


def _tdm_usable(recs: list[Measurement]) -> np.ndarray:
    """Which ``radec``/``radec_pair`` records certainly pass :func:`_check_tdm_record`, judged per kind for
    all at once (True: it passes; False: ask :func:`_check_tdm_record`, which says why or lets it pass).

    The same tests as :meth:`opnav.records.Measurement.problem` (finite epoch, value and covariance,
    ``allclose`` symmetry at rtol 1e-9, a Cholesky factor) on arrays of every record: 86,400
    records one by one took seconds.
    """
    ok = np.zeros(len(recs), dtype=bool)
    for kind in _TDM_KINDS:
        rows = [k for k, rec in enumerate(recs) if rec.kind == kind]
        if rows:
            ok[rows] = _usable_of_kind([recs[k] for k in rows])
    return ok


def _usable_of_kind(recs: list[Measurement]) -> np.ndarray:
    t = np.array([rec.t_tdb_s for rec in recs])
    value = np.array([rec.value for rec in recs])
    cov = np.array([rec.covariance for rec in recs])
    transposed = np.swapaxes(cov, 1, 2)
    with np.errstate(invalid="ignore"):  # NaN and infinity fail the tests, quietly
        ok = (np.isfinite(t) & np.all(np.isfinite(value), axis=1) & np.all(np.isfinite(cov), axis=(1, 2))
              & np.all(np.abs(value[:, 1::2]) <= 0.5 * math.pi, axis=1)
              & np.all(np.abs(cov - transposed) <= 1e-9 * np.abs(transposed), axis=(1, 2)))
    try:
        np.linalg.cholesky(cov[ok])
    except np.linalg.LinAlgError:  # one of them is not positive definite: each is asked on its own
        return np.zeros(len(recs), dtype=bool)
    targets = [_tdm_targets(rec) for rec in recs]
    names = {name: bool(name.strip()) and _is_keyword_value(name)
             for name in {n for names in targets for n in names} | {rec.sensor for rec in recs}}
    names[""] = True  # no sensor is fine; no target is not, and is caught by the test of targets
    return ok & np.array([all(name.strip() and names[name] for name in names_) and names[rec.sensor]
                          for rec, names_ in zip(recs, targets)])


def _tdm_targets(rec: Measurement) -> tuple[str, ...]:
    return pair_targets(rec) if rec.kind == "radec_pair" else (rec.target,)


def _check_tdm_record(rec: Measurement) -> None:
    """Refuse a record a TDM cannot hold (InputError naming it); the message, whose epoch costs an
    astropy ``Time``, is built only for a record that fails."""
    targets = _tdm_targets(rec)
    decs = rec.value[1::2]
    if (rec.problem() is None and all(t.strip() and _is_keyword_value(t) for t in targets)
            and np.all(np.abs(decs) <= 0.5 * math.pi) and (not rec.sensor or _is_keyword_value(rec.sensor))):
        return
    what = f"{rec.kind} record at {describe_epoch(rec.t_tdb_s)} (target {rec.target!r}, sensor {rec.sensor!r})"
    problem = rec.problem()
    if problem is not None:
        raise InputError(f"{what}: {problem}; nothing written")
    if not all(t.strip() for t in targets):
        raise InputError(f"{what}: no target; the TDM names it as PARTICIPANT_2")
    beyond = [d for d in decs if abs(d) > 0.5 * math.pi]
    if beyond:
        raise InputError(f"{what}: declination {math.degrees(beyond[0]):.6f} deg is beyond +-90 deg")
    for target in targets:
        _keyword_value("target", target)
    if rec.sensor:
        _keyword_value("sensor", rec.sensor)


def _format_epochs_any(t: np.ndarray, what: str) -> list[str]:
    """Epoch texts of ``t`` (TDB, microseconds), repeated epochs allowed (records of one frame share one)."""
    if t.size == 0:
        return []
    unique, inverse = np.unique(t, return_inverse=True)
    texts = [str(text) for text in format_epoch(unique, "tdb", precision=EPOCH_DIGITS)]
    for k, text in enumerate(texts):
        if not _WRITTEN_EPOCH.fullmatch(text):
            raise InputError(f"{what} {unique[k]!r} s is outside the years 0000-9999 a CCSDS date can hold")
    return [texts[k] for k in inverse.ravel().tolist()]


def _tdm_observations(epochs: list[str], ra: list[float], dec: list[float]) -> list:
    """The ANGLE_1 and ANGLE_2 observations of a segment (the NDM/XML path; KVN: :func:`_tdm_kvn_rows`)."""
    deg = _tdm.AngleUnits.DEG
    observations = []
    for epoch, ra_deg, dec_deg in zip(epochs, ra, dec):
        observations.append(_tdm.TrackingDataObservationType(
            epoch=epoch, angle_1=_tdm.AngleType(value=ra_deg, units=deg)))
        observations.append(_tdm.TrackingDataObservationType(
            epoch=epoch, angle_2=_tdm.AngleType(value=dec_deg, units=deg)))
    return observations


def _tdm_kvn_rows(epochs: list[str], ra: list[float], dec: list[float]) -> str:
    """A segment's observation lines as ccsds-ndm's KVN writer lays them out (``ANGLE_1 = EPOCH  value``)."""
    one, two = f"{'ANGLE_1':<{_KEY_WIDTH}} = ", f"{'ANGLE_2':<{_KEY_WIDTH}} = "
    return "\n".join(f"{one}{epoch}  {a!r}\n{two}{epoch}  {d!r}" for epoch, a, d in zip(epochs, ra, dec))


def _tdm_segment(key: tuple, covariances: set, epochs: list[str], participant: str, path: Path, observations: list):
    sensor, target = key
    comments = [f"opnav target = {target}"]
    if sensor:
        comments.append(f"opnav sensor = {sensor}")
    if len(covariances) == 1:
        comments.append("opnav covariance_rad2 = " + " ".join(repr(v) for v in next(iter(covariances))))
    else:
        comments.append(f"opnav covariances in {tdm_sidecar(path).name} (one per record)")
    metadata = _tdm.TdmMetadata(
        comment=comments,
        time_system="TDB",
        start_time=epochs[0],
        stop_time=epochs[-1],
        participant_1=participant,
        participant_2=target.upper(),
        mode=_tdm.ModeType.SEQUENTIAL,
        path="2,1",
        angle_type=_tdm.AngleTypeType.RADEC,
        reference_frame=_tdm.RefFrameType.ICRF,
    )
    return _tdm.TdmSegment(metadata=metadata, data=_tdm.TdmData(observation=observations))


@dataclass(frozen=True, eq=False)
class _TdmAngles:
    """The RA/Dec observations of one TDM segment: epoch texts and TDB seconds, [ra, dec] rad ICRF,
    the target and sensor it names and its ``opnav`` comments."""

    where: str
    epochs: list[str]
    t: np.ndarray
    ra: np.ndarray
    dec: np.ndarray
    target: str
    sensor: str
    tags: dict
    time_system: str


def _read_tdm_segment(where: str, segment, skipped: Counter, angles: list | None = None) -> _TdmAngles | None:
    """A segment's RA/Dec observations; ``angles`` (``(epoch, "angle_1" | "angle_2", value)``) when its
    KVN lines were read apart (:func:`_kvn_observations`), else from ccsds-ndm's objects."""
    meta, data = _field(segment, "metadata", where), _field(segment, "data", where)
    if angles is not None:
        return _segment_angles(where, meta, angles, skipped)
    angles = []
    for obs in getattr(data, "observation", None) or []:
        for f in dataclasses.fields(obs):
            item = getattr(obs, f.name)
            if f.name in ("epoch", "comment") or item is None:
                continue
            if f.name in ("angle_1", "angle_2"):
                epoch = _epoch_text(getattr(obs, "epoch", None), f"{where} {f.name.upper()}")
                angles.append((epoch, f.name, _number(item, f"{where} {f.name.upper()} at {epoch}")))
            else:
                skipped[f.name.upper()] += 1
    return _segment_angles(where, meta, angles, skipped)


def _segment_angles(where: str, meta, angles: list, skipped: Counter) -> _TdmAngles | None:
    if not angles:
        return None
    scale = _time_scale(meta, where)
    angle_type = _enum_text(getattr(meta, "angle_type", None))
    if angle_type != "RADEC":
        raise InputError(f"{where}: ANGLE_TYPE {angle_type or '(missing)'} is not supported; opnav reads RADEC only")
    frame = _enum_text(getattr(meta, "reference_frame", None))
    if frame not in ("ICRF", "EME2000"):
        raise InputError(f"{where}: REFERENCE_FRAME {frame or '(missing)'} is not supported for RADEC; "
                         "expected ICRF or EME2000")
    tags = _opnav_tags(getattr(meta, "comment", None) or [])
    pairs = _pair_angles(angles, skipped)
    if not pairs:
        return None
    t = np.atleast_1d(_parse_epochs([epoch for epoch, _, _ in pairs], scale, where))
    ra = np.radians([a1 for _, a1, _ in pairs])
    dec = np.radians([a2 for _, _, a2 in pairs])
    bad = np.abs(dec) > 0.5 * math.pi
    if np.any(bad):
        k = _first(bad)
        raise InputError(f"{where}: ANGLE_2 {pairs[k][2]!r} deg at {pairs[k][0]} is not a declination (beyond +-90)")
    if frame == "EME2000":
        rb = erfa.bp00(J2000_JD, 0.0)[0]  # frame bias: v_EME2000 = rb @ v_ICRF
        ra, dec = unit_to_radec(radec_to_unit(ra, dec) @ rb)
    return _TdmAngles(where, [epoch for epoch, _, _ in pairs], t, np.atleast_1d(ra), np.atleast_1d(dec),
                      tags.get("target") or _path_source(meta), tags.get("sensor", ""), tags,
                      _enum_text(getattr(meta, "time_system", None)))


def _pair_angles(angles: list[tuple[str, str, float]], skipped: Counter) -> list[tuple[str, float, float]]:
    """Pair each ANGLE_1 with the ANGLE_2 of the same epoch text, in file order."""
    waiting: dict[str, dict[str, deque]] = defaultdict(lambda: {"angle_1": deque(), "angle_2": deque()})
    pairs = []
    for epoch, name, value in angles:
        other = "angle_2" if name == "angle_1" else "angle_1"
        queue = waiting[epoch]
        if queue[other]:
            partner = queue[other].popleft()
            pairs.append((epoch, value, partner) if name == "angle_1" else (epoch, partner, value))
        else:
            queue[name].append(value)
    for queue in waiting.values():
        for name, values in queue.items():
            if values:
                skipped[f"{name.upper()} without its pair"] += len(values)
    return pairs


def _opnav_tags(comments: Iterable[str]) -> dict[str, str]:
    tags = {}
    for line in comments:
        match = _OPNAV_TAG.fullmatch(str(line))
        if match:
            tags[match.group(1).lower()] = match.group(2)
    return tags


def _tdm_covariance(tags: dict[str, str], sigma_rad: float | None, where: str, sidecar: Path) -> np.ndarray:
    text = tags.get("covariance_rad2")
    if text is None:
        if sigma_rad is None:
            raise InputError(f"{where}: the TDM carries no 'opnav covariance_rad2' comment and there is no "
                             f"covariance sidecar {sidecar}; pass sigma_rad (angle noise, rad) to read it")
        return float(sigma_rad) ** 2 * np.eye(2)
    try:
        values = [float(v) for v in text.split()]
    except ValueError:
        values = []
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise InputError(f"{where}: 'opnav covariance_rad2 = {text}' is not four finite numbers")
    return np.array(values).reshape(2, 2)


def _path_source(meta) -> str:
    """The participant where the signal starts (the observed target), lower case."""
    path = str(getattr(meta, "path", None) or "")
    first = path.split(",")[0].strip()
    name = getattr(meta, f"participant_{first}", None) if first.isdigit() else None
    return str(name or "").strip().lower()


# --- the TDM's covariance sidecar ----------------------------------------------------------------


def _write_sidecar(path: Path, records: list[Measurement], epochs: list[str]) -> None:
    """One CSV row per record, in the records' order: the epoch text the TDM gives it, its exact
    t_tdb_s, sensor, target (``a+b`` for a pair), frame, flags and covariance (row-major, rad**2;
    4x4 for a pair: [ra_a, dec_a, ra_b, dec_b]). Numbers are Python reprs, read back exactly."""
    t = [rec.t_tdb_s for rec in records]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(_SIDECAR_COLUMNS)
    writer.writerows([epoch, repr(ti), rec.sensor, rec.target, rec.frame_id, rec.flags,
                      " ".join(map(repr, rec.covariance.ravel().tolist()))]
                     for epoch, ti, rec in zip(epochs, t, records))
    atomic_write_text(path, buffer.getvalue())


def _records_from_sidecar(sidecar: Path, segments: list[_TdmAngles]) -> list[Measurement]:
    """The records of a TDM whose covariances, exact epochs, frames and flags are in ``sidecar``: every
    sidecar row takes the observation(s) of its target(s) at its epoch text and sensor, and every
    observation must be taken exactly once (a sidecar of another TDM is refused)."""
    waiting: dict[tuple[str, str, str], deque] = defaultdict(deque)
    for segment in segments:
        if segment.time_system != "TDB":
            raise InputError(f"{segment.where}: TIME_SYSTEM {segment.time_system}, but its covariance sidecar "
                             f"{sidecar} gives TDB epochs; a TDM written with a sidecar is in TDB")
        for epoch, a, d in zip(segment.epochs, segment.ra.tolist(), segment.dec.tolist()):
            waiting[(epoch, segment.sensor, segment.target)].append((a, d))
    rows = _read_sidecar_rows(sidecar)
    records = []
    for line, row in rows:
        where = f"{sidecar}: line {line}"
        names = [name.strip() for name in row["target"].split(PAIR_SEPARATOR)]
        value = []
        for name in names:
            queue = waiting.get((row["epoch_tdb"], row["sensor"], name))
            if not queue:
                raise InputError(f"{where}: the TDM has no observation of {name!r} (sensor {row['sensor']!r}) at "
                                 f"{row['epoch_tdb']}; the sidecar belongs to another TDM")
            value.extend(queue.popleft())
        kind = "radec_pair" if len(names) == 2 else "radec"
        cov = _sidecar_covariance(row["covariance_rad2"], 2 * len(names), where)
        t = _sidecar_number(row["t_tdb_s"], "t_tdb_s", where)
        try:
            flags = int(row["flags"] or 0)
        except ValueError:
            raise InputError(f"{where}: flags {row['flags']!r} is not an integer") from None
        records.append(Measurement(t, kind, value, cov, target=row["target"], sensor=row["sensor"],
                                   frame_id=row["frame_id"], flags=flags))
    left = sum(len(queue) for queue in waiting.values())
    if left:
        raise InputError(f"{sidecar}: {left} observation(s) of the TDM have no row in its covariance sidecar; "
                         "the sidecar belongs to another TDM")
    # each row's exact epoch must be the one the TDM gives it (to its microsecond)
    texts = _format_epochs_any(np.array([rec.t_tdb_s for rec in records]), f"{sidecar} t_tdb_s")
    for (line, row), text in zip(rows, texts):
        if text != row["epoch_tdb"]:
            raise InputError(f"{sidecar}: line {line}: t_tdb_s {row['t_tdb_s']} is {text} TDB, not its epoch_tdb "
                             f"{row['epoch_tdb']}")
    return records


def _read_sidecar_rows(sidecar: Path) -> list[tuple[int, dict]]:
    try:
        text = sidecar.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{sidecar}: cannot read the TDM's covariance sidecar ({_one_line(exc)})") from None
    reader = csv.DictReader(io.StringIO(text))
    missing = [c for c in _SIDECAR_COLUMNS if c not in (reader.fieldnames or [])]
    if missing:
        raise InputError(f"{sidecar}: not a TDM covariance sidecar; columns {', '.join(missing)} are missing "
                         f"(expected {', '.join(_SIDECAR_COLUMNS)})")
    rows = []
    for line, row in enumerate(reader, start=2):
        if None in row or any(row[c] is None for c in _SIDECAR_COLUMNS):
            raise InputError(f"{sidecar}: line {line}: expected {len(_SIDECAR_COLUMNS)} columns")
        rows.append((line, row))
    return rows


def _sidecar_number(text: str, column: str, where: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise InputError(f"{where}: {column} {text!r} is not a finite number")
    return value


def _sidecar_covariance(text: str, size: int, where: str) -> np.ndarray:
    try:
        values = [float(v) for v in text.split()]
    except ValueError:
        values = []
    if len(values) != size * size or not all(math.isfinite(v) for v in values):
        raise InputError(f"{where}: covariance_rad2 must be {size * size} finite numbers ({size}x{size}, "
                         f"row-major, rad**2), got {text!r}")
    return np.array(values).reshape(size, size)


# --- shared -------------------------------------------------------------------------------------


#: Width of a KVN keyword column (``KEY<blanks> = value``), as ccsds-ndm writes it.
_KEY_WIDTH = 24


def _is_xml(path: Path) -> bool:
    """Whether ``path`` names NDM/XML (else KVN)."""
    return path.name.lower().endswith(".xml")


def _write_kvn(path: Path, message, data: list[str]) -> None:
    """Write a KVN message whose segments were built without data rows, segment ``k``'s rows (``data[k]``,
    text as ccsds-ndm's writer lays them out) where that writer puts them: an OEM's after the blank line
    that follows ``META_STOP``, a TDM's after ``DATA_START``.

    ccsds-ndm writes every other line (header, metadata, markers); building 86,400 state vectors,
    covariance blocks or observations as its objects, only to have them written one field at a time,
    took most of a 30-day run's output time. ``tests/test_ccsds_golden.py`` pins the bytes.
    """
    from ccsds_ndm.kvn_tokenizer import SectionMarkerLine
    from ccsds_ndm.kvn_writer import write_kvn_lines

    marker, offset = ("DATA_START", 0) if type(message).__name__ == "Tdm" else ("META_STOP", 1)
    out: list[str] = []
    insert_at, k = -1, 0
    tdm = marker == "DATA_START"
    for i, line in enumerate(write_kvn_lines(message)):
        if tdm and out and out[-1] == "META_STOP" and not line.to_str().strip():
            # ccsds-ndm puts a blank line between META_STOP and DATA_START, where ccsds-ndm-py stops
            # with 'Expected DATA'; the standard allows the layout without it, which both read
            continue
        out.append(line.to_str())
        if isinstance(line, SectionMarkerLine) and line.key == marker:
            insert_at = i + offset
        if i == insert_at:
            out.append(data[k])
            k += 1
    if k != len(data):
        raise RuntimeError(f"ccsds-ndm laid out {k} data sections for {len(data)} segments")
    text = "\n".join(out)
    atomic_write_text(path, text if text.endswith("\n") else text + "\n")


def _write_message(path: Path, message, kind: str) -> None:
    if _is_xml(path):
        text = NdmIo().to_string(message, NDMFileFormats.XML, no_namespace_schema_location=_XML_SCHEMA[kind])
    else:
        text = NdmIo().to_string(message, NDMFileFormats.KVN)
    atomic_write_text(path, text if text.endswith("\n") else text + "\n")


def _load(path: Path, kind: str, *, kvn_data: list | None = None):
    """Parse ``path`` with ccsds-ndm; every failure becomes a one-line InputError naming the file.

    With ``kvn_data`` (a list) and a KVN TDM, the observation lines of each segment are taken out of
    the text before ccsds-ndm parses it and appended to ``kvn_data`` as ``[(line number, line), ...]``
    per segment (:func:`_kvn_observations` reads them): ccsds-ndm builds each observation through
    ``typing.get_type_hints``, about 1 ms a line, 6 minutes for a 30-day S1 TDM.
    """
    if not path.exists():
        raise InputError(f"{kind} file not found: {path}")
    if not path.is_file():
        raise InputError(f"{path}: not a file, expected a CCSDS {kind}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text {kind} file (bytes that are not UTF-8)") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the {kind} file ({exc.strerror or exc})") from None
    if not text.strip():
        raise InputError(f"{path}: empty file, expected a CCSDS {kind}")
    if kvn_data is not None and not text.lstrip().startswith("<"):
        text = _strip_kvn_data(text, kvn_data)
    try:
        with warnings.catch_warnings():
            # xsdata keeps a number it cannot parse as text and only warns; make that an error
            warnings.simplefilter("error", ConverterWarning)
            message = NdmIo().from_string(text)
    except Exception as exc:  # noqa: BLE001 - ValueError, KeyError, lxml and xsdata errors all mean "malformed"
        raise InputError(f"{path}: not a readable CCSDS {kind} ({_one_line(exc)})") from None
    found = str(getattr(message, "id", "") or "")
    if found != f"CCSDS_{kind}_VERS":
        name = found.removeprefix("CCSDS_").removesuffix("_VERS") or type(message).__name__
        raise InputError(f"{path}: a CCSDS {name} message, not a{'n' if kind[0] in 'AEIOU' else ''} {kind}")
    return message


def _strip_kvn_data(text: str, data: list) -> str:
    """``text`` without the lines between each ``DATA_START`` and ``DATA_STOP`` other than blanks and
    ``COMMENT`` lines; those lines, with their line numbers, appended to ``data``, one list a segment."""
    kept, inside = [], False
    for number, line in enumerate(text.splitlines(), start=1):
        word = line.strip()
        if word == "DATA_STOP":
            inside = False
        elif inside and word and not word.startswith("COMMENT"):
            data[-1].append((number, word))
            continue
        elif word == "DATA_START":
            inside = True
            data.append([])
        kept.append(line)
    return "\n".join(kept) + "\n"


_KVN_OBSERVATION = re.compile(r"([A-Za-z0-9_]+)\s*=\s*(\S+)\s+(\S+)")


@lru_cache(maxsize=1)
def _observation_keywords() -> frozenset:
    """The data keywords of TDM 2.0 (ccsds-ndm's observation fields, upper case)."""
    return frozenset(f.name.upper() for f in dataclasses.fields(_tdm.TrackingDataObservationType)
                     if f.name not in ("epoch", "comment"))


def _kvn_observations(lines: list[tuple[int, str]], where: str, path: Path, skipped: Counter) -> list:
    """``(epoch, "angle_1" | "angle_2", value)`` of a segment's KVN observation lines (``KEYWORD = EPOCH
    VALUE``), in file order; other known keywords are counted in ``skipped``, anything else refused
    naming the line."""
    angles = []
    known = _observation_keywords()
    for number, line in lines:
        match = _KVN_OBSERVATION.fullmatch(line)
        keyword = match.group(1).upper() if match else ""
        if keyword not in known:
            raise InputError(f"{path}: line {number}: not a TDM observation ('KEYWORD = EPOCH VALUE' with a TDM "
                             f"data keyword): {line[:80]!r}")
        if keyword not in ("ANGLE_1", "ANGLE_2"):
            skipped[keyword] += 1
            continue
        try:
            value = float(match.group(3))
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise InputError(f"{where}: {keyword} at {match.group(2)} (line {number}) is not a finite number: "
                             f"{match.group(3)!r}")
        angles.append((match.group(2), keyword.lower(), value))
    return angles


def _segments(message, path: Path, kind: str) -> list:
    segments = getattr(getattr(message, "body", None), "segment", None)
    if not isinstance(segments, list) or not segments:
        raise InputError(f"{path}: the {kind} has no segment")
    return segments


def _field(obj, name: str, where: str):
    value = getattr(obj, name, None)
    if value is None:
        raise InputError(f"{where}: {name} is missing")
    return value


def _time_scale(meta, where: str) -> str:
    system = _enum_text(getattr(meta, "time_system", None))
    if system not in _TIME_SCALES:
        raise InputError(f"{where}: TIME_SYSTEM {system or '(missing)'} is not supported; "
                         f"expected one of {', '.join(_TIME_SCALES)}")
    return _TIME_SCALES[system]


def _enum_text(value) -> str:
    if isinstance(value, Enum):
        value = value.value
    return "" if value is None else str(value).strip().upper()


def _text(value, what: str, required: bool = True) -> str:
    if not isinstance(value, str) or (required and not value.strip()):
        raise InputError(f"{what} is missing or not text")
    return value.strip()


def _epoch_text(value, what: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"{what}: EPOCH is missing")
    return value.strip()


def _number(item, what: str) -> float:
    """The float of a model value (a ``value``/``units`` wrapper or a bare float)."""
    if item is None:
        raise InputError(f"{what} is missing")
    value = getattr(item, "value", item)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{what} is not a finite number: {value!r}")
    return float(value)


def _parse_epochs(texts: list[str], scale: str, where: str) -> np.ndarray:
    # astropy reads day-of-year dates as 'YYYY:DDD:hh:mm:ss', the CCSDS form is 'YYYY-DDDThh:mm:ss'
    cleaned = [_DAY_OF_YEAR_EPOCH.sub(r"\1:\2:\3", text) for text in texts]
    try:
        return np.atleast_1d(np.asarray(parse_epoch(cleaned, scale), dtype=float))
    except InputError:
        pass
    # one by one: astropy wants one form for a whole list (a file may mix calendar and
    # day-of-year dates), and a message should name the one bad date, not the list
    out = np.empty(len(texts))
    for k, (text, clean) in enumerate(zip(texts, cleaned)):
        try:
            out[k] = parse_epoch(clean, scale)
        except InputError:
            raise InputError(f"{where}: cannot read epoch {text!r} as a {scale.upper()} date") from None
    return out


def _format_epochs(t: np.ndarray, what: str) -> list[str]:
    texts = [str(text) for text in format_epoch(np.atleast_1d(np.asarray(t, dtype=float)), "tdb",
                                                 precision=EPOCH_DIGITS)]
    for k, text in enumerate(texts):
        if not _WRITTEN_EPOCH.fullmatch(text):
            raise InputError(f"{what}[{k}] = {t[k]!r} s is outside the years 0000-9999 a CCSDS date can hold")
    repeated = [k for k in range(1, len(texts)) if texts[k] == texts[k - 1]]
    if repeated:
        k = repeated[0]
        raise InputError(f"{what}[{k - 1}] and [{k}] are less than 1 us apart ({texts[k]} TDB); "
                         "the file keeps microseconds")
    return texts


@lru_cache(maxsize=1024)
def _is_keyword_value(value: str) -> bool:
    """Whether :func:`_keyword_value` accepts ``value`` (cached: a TDM names a few targets and sensors
    in every record)."""
    try:
        _keyword_value("value", value)
    except InputError:
        return False
    return True


def _keyword_value(name: str, value) -> str:
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"{name} must be a non-empty string, got {value!r}")
    if any(ord(c) < 32 or ord(c) == 127 for c in value) or value != value.strip():
        raise InputError(f"{name} {value!r} has line breaks, control characters or surrounding blanks; "
                         "a CCSDS keyword value cannot keep them")
    return value


def _comment_lines(comment: str | Sequence[str] | None) -> list[str]:
    if comment is None:
        return []
    lines = comment.splitlines() if isinstance(comment, str) else list(comment)
    out = []
    for line in lines:
        if not isinstance(line, str) or "\n" in line or "\r" in line:
            raise InputError(f"comment lines must be strings without line breaks, got {line!r}")
        out.append(line.strip())
    return out


def _creation_date() -> str:
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S")


def _first(mask: np.ndarray) -> int:
    return int(np.argmax(mask))


def _one_line(exc: BaseException) -> str:
    # xsdata puts the offending text on a second line; keep it, on one line
    text = "; ".join(line.strip() for line in str(exc).strip().splitlines() if line.strip()) or type(exc).__name__
    return text if len(text) <= 160 else text[:157] + "..."
