"""CCSDS Orbit Ephemeris Messages (OEM 2.0 written, 2.0 and 3.0 read), KVN or NDM/XML.

States ``[x, y, z]`` km and ``[x_dot, y_dot, z_dot]`` km/s in ``REF_FRAME`` about ``CENTER_NAME``,
epochs TDB; covariances km**2, km**2/s, km**2/s**2 (lower triangle in the file). The format and
its keywords are described in :mod:`opnav.ccsds` and docs/formats/ccsds.md.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from ccsds_ndm.models import ndmxml2 as _odm  # OEM 2.0 lives in the NDM/XML 2.0.0 models

from ..epochs import describe_epoch
from ..errors import InputError
from .common import (EPOCH_RESOLUTION_S, KEY_WIDTH, comment_lines, creation_time_utc, enum_text, epoch_text, first_true,
                     format_epochs, is_xml, keyword_value, load_message, message_segments, number_of, parse_epochs,
                     percent_escaped, required_field, text_value, time_scale, write_kvn, write_message)

log = logging.getLogger(__name__)

_STATE_KEYS = ("x", "y", "z", "x_dot", "y_dot", "z_dot")

#: (row, column, model field) of the 21 lower-triangle covariance entries, in file order.
_COV_KEYS = tuple((i, j, f"c{_STATE_KEYS[i]}_{_STATE_KEYS[j]}") for i in range(6) for j in range(i + 1))

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
    object_name = keyword_value("object_name", object_name)
    object_id = keyword_value("object_id", object_id)
    center = keyword_value("center", center)
    ref_frame = keyword_value("ref_frame", ref_frame)
    originator = keyword_value("originator", originator)
    method, degree = _check_interpolation(interpolation)
    epochs = format_epochs(t, "t_tdb_s")
    xml = is_xml(path)
    metadata = _odm.OemMetadata(
        comment=comment_lines(comment),
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
        header=_odm.NdmHeader(creation_date=creation_time_utc(), originator=originator),
        body=_odm.OemBody(segment=[_odm.OemSegment(
            metadata=metadata, data=_odm.OemData(state_vector=vectors, covariance_matrix=blocks))]),
    )
    if xml:
        write_message(path, oem, "OEM")
    else:
        write_kvn(path, oem, [_oem_kvn_rows(epochs, x, cov, ref_frame)])


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
    oem = load_message(path, "OEM")
    times, rows, cov_epochs, cov_mats = [], [], [], []
    first = None
    for k, segment in enumerate(message_segments(oem, path, "OEM"), start=1):
        where = f"{path}: OEM segment {k}"
        meta, data = required_field(segment, "metadata", where), required_field(segment, "data", where)
        names = tuple(text_value(required_field(meta, key, where), f"{where} {key.upper()}")
                      for key in ("object_name", "center_name", "ref_frame"))
        object_id = text_value(getattr(meta, "object_id", None) or "", f"{where} OBJECT_ID", required=False)
        if first is None:
            first = (*names, object_id)
            interpolation = (enum_text(getattr(meta, "interpolation", None)),
                             getattr(meta, "interpolation_degree", None))
        elif tuple(n.upper() for n in names) != tuple(n.upper() for n in first[:3]):
            raise InputError(f"{where}: OBJECT_NAME, CENTER_NAME or REF_FRAME {names} differ from segment 1's "
                             f"{first[:3]}; opnav reads one object, origin and frame per file")
        scale = time_scale(meta, where)
        vectors = list(getattr(data, "state_vector", None) or [])
        if not vectors:
            raise InputError(f"{where}: no state vectors")
        epochs = [epoch_text(getattr(v, "epoch", None), f"{where} state vector {i + 1}")
                  for i, v in enumerate(vectors)]
        times.append(parse_epochs(epochs, scale, where))
        rows.extend(
            [number_of(getattr(v, key, None), f"{where} {key.upper()} at {epoch}") for key in _STATE_KEYS]
            for v, epoch in zip(vectors, epochs)
        )
        blocks = list(getattr(data, "covariance_matrix", None) or [])
        if blocks:
            cov_epochs.append(parse_epochs(
                [epoch_text(getattr(b, "epoch", None), f"{where} covariance {i + 1}") for i, b in enumerate(blocks)],
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
        raise InputError(f"t_tdb_s[{first_true(~np.isfinite(t))}] is not a finite number")
    if not np.all(np.isfinite(x)):
        raise InputError(f"states[{first_true(~np.all(np.isfinite(x), axis=1))}] contains NaN or infinity")
    if n > 1 and np.any(np.diff(t) <= 0.0):
        k = first_true(np.diff(t) <= 0.0) + 1
        raise InputError(f"t_tdb_s must increase strictly; t_tdb_s[{k}] = {describe_epoch(t[k])} "
                         f"is not after t_tdb_s[{k - 1}] = {describe_epoch(t[k - 1])}")
    if cov is not None:
        if cov.shape != (n, 6, 6):
            raise InputError(f"covariances must have shape ({n}, 6, 6) to match t_tdb_s, got {cov.shape}")
        if not np.all(np.isfinite(cov)):
            raise InputError(f"covariances[{first_true(~np.all(np.isfinite(cov), axis=(1, 2)))}] "
                             "contains NaN or infinity")
        diag = np.diagonal(cov, axis1=1, axis2=2)
        if np.any(diag < 0.0):
            raise InputError(f"covariances[{first_true(np.any(diag < 0.0, axis=1))}] has a negative variance")
        scale = np.sqrt(diag[:, :, None] * diag[:, None, :])
        asymmetric = np.abs(cov - np.swapaxes(cov, 1, 2)) > _SYMMETRY_RTOL * scale
        if np.any(asymmetric):
            raise InputError(f"covariances[{first_true(np.any(asymmetric, axis=(1, 2)))}] is not symmetric")
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
    block = "\n".join([f"{'EPOCH':<{KEY_WIDTH}} = %s", f"{'COV_REF_FRAME':<{KEY_WIDTH}} = {percent_escaped(frame)}",
                       *("  ".join(["%r"] * (stop - start)) for start, stop in _COV_ROWS)])
    values = cov.reshape(len(cov), 36)[:, _COV_FLAT].tolist()
    return "\n".join([text, "", "COVARIANCE_START", *[block % (epoch, *row) for epoch, row in zip(epochs, values)],
                      "COVARIANCE_STOP"])


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
    frame = ref_frame if frame is None else text_value(frame, f"{where} COV_REF_FRAME at {epoch}")
    if frame.upper() != ref_frame.upper():
        raise InputError(f"{where}: covariance at {epoch} is in COV_REF_FRAME {frame}, not the state frame "
                         f"{ref_frame}; opnav does not rotate covariances")
    cov = np.empty((6, 6))
    for i, j, name in _COV_KEYS:
        cov[i, j] = cov[j, i] = number_of(getattr(block, name, None), f"{where} {name.upper()} at {epoch}")
    return cov


def _match_covariances(path: Path, t: np.ndarray, t_cov: np.ndarray, mats: list[np.ndarray]) -> np.ndarray:
    out = np.full((t.size, 6, 6), np.nan)
    filled = np.zeros(t.size, dtype=bool)
    dropped = 0
    for tc, cov in zip(t_cov, mats):
        k = int(np.argmin(np.abs(t - tc)))
        # half the written resolution: the same epoch text parses to the same instant, a different one does not
        if abs(t[k] - tc) > 0.5 * EPOCH_RESOLUTION_S:
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
