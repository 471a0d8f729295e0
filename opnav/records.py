"""Time-tagged measurement records: the one object between image stage and filters.

A :class:`Measurement` carries a value in internal units with its covariance,
the epoch, what was observed and by which sensor. Records are written as plain
CSV (one row each, vectors as space-separated numbers, units named in the
``unit`` column) beside a JSON metadata file, and read back unchanged.

Kinds and the layout of ``value`` (internal units):

==================== ====== =========================================================
kind                 size   value
==================== ====== =========================================================
radec                2      [ra, dec] of the target as seen from the probe, rad
radec_pair           4      [ra_1, dec_1, ra_2, dec_2] of two targets in one frame (``target``
                            ``"name_1+name_2"``), with the cross-covariance of the attitude
                            error they share (:func:`join_frame_radec`)
los                  3      unit line of sight probe -> target, ICRF
starlight_angle      1      angle between the target-centre direction and a star, rad
starlight_elevation  1      starlight angle minus the target's apparent radius, rad
starlight            2      [starlight angle, starlight elevation] of one star, rad, with their
                            cross-covariance (both share the target-centre error)
position             3      probe position pseudo-measurement, km, ICRF (origin in ``target``)
target_vector        3      probe -> ``target`` centre, km, ICRF: the apparent line of sight (light
                            time, aberration) times the light-time range, as a limb fit of the
                            body's known shape gives it (:mod:`opnav.image.centres`)
radial_velocity      1      Doppler radial velocity of a source seen by the probe, km/s
==================== ====== =========================================================

Two targets measured in one frame share that frame's attitude error: a star-identified attitude
from a few stars can be as uncertain as a moon's own centroid (S1: 15 mas of a moon's 30-50 mas),
and a filter that takes the two records as independent believes the pair's common part better
known than it is (S1, one EKF update over 300 draws: NEES 7.06 against 5.94 for the pair, whose
chi-square(6) band reaches 6.68; on twins of a July arc the 30-day NEES went from 3-5 to 5-13).
:func:`join_frame_radec` makes such records one ``radec_pair`` with their cross-covariance;
:func:`split_radec_pairs` undoes it for per-target statistics and formats that hold one target
a record.

A target's RA/Dec measured against its frame's stars moves with an error of the camera model's
parameters (focal length, principal point, distortion) by ``J dc``, ``J`` = d(RA, Dec)/d(parameters)
relative to the stars: the same error in every frame, a bias over an arc. The image stage can keep
``J`` in a record (:data:`CAMERA_JACOBIAN`, rows as the value's, one column a parameter of
:data:`CAMERA_PARAMETERS`) for a filter that holds the parameters' errors as consider states
(:class:`opnav.measurements.CameraOffsetModel`); the CSV carries both in two optional columns,
:func:`join_frame_radec` stacks a pair's and :func:`split_radec_pairs` splits them.

Starlight kinds carry the star direction ``star_unit_icrf``; ``radial_velocity``
carries the source direction there too (``star_id`` 0 and target ``sun`` for the Sun).
"""

from __future__ import annotations

import csv
import hashlib
import math
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError
from .files import MAX_TEXT_BYTES, atomic_write_text, check_input_file

KIND_SIZE = {
    "radec": 2,
    "radec_pair": 4,
    "los": 3,
    "starlight_angle": 1,
    "starlight_elevation": 1,
    "starlight": 2,
    "position": 3,
    "radial_velocity": 1,
    "target_vector": 3,
}
KIND_UNIT = {
    "radec": "rad",
    "radec_pair": "rad",
    "los": "1",
    "starlight_angle": "rad",
    "starlight_elevation": "rad",
    "starlight": "rad",
    "position": "km",
    "radial_velocity": "km/s",
    "target_vector": "km",
}

#: Quality flags (bit mask).
FLAG_SATURATED = 1
FLAG_EDGE = 2
FLAG_LOW_SNR = 4
FLAG_PHASE_CORRECTED = 8
FLAG_REGISTERED = 16  # value interpolated to this epoch by time registration

#: Separator of the two target names of a ``radec_pair`` record.
PAIR_SEPARATOR = "+"
#: ``Measurement.extra`` keys of a ``radec`` record from an image (in memory, not written to files):
#: d(ra, dec)/d(camera-frame small rotation) (2, 3), and that rotation's covariance (3, 3), rad^2.
ATTITUDE_JACOBIAN = "attitude_jacobian"
ATTITUDE_COVARIANCE = "attitude_cov_rad2"
#: ``Measurement.extra`` keys of a record measured against its frame's stars with a calibrated camera
#: (written to files): d(value)/d(camera parameters) relative to the stars, (m, P) nested lists, rad per
#: parameter unit (``f``, ``cx``, ``cy`` px; Brown coefficients dimensionless), and the parameters' names
#: (:data:`opnav.camera.CALIBRATION_PARAMETERS`), a tuple of P.
CAMERA_JACOBIAN = "camera_jacobian"
CAMERA_PARAMETERS = "camera_parameters"
#: ``Measurement.extra`` key of a ``radec`` record whose covariance holds its camera's calibration error as
#: white noise (in memory; :func:`opnav.image.camera_noise.with_camera_covariance`): ``L`` (2, P), rad, with
#: ``L L^T`` the term added. The records of one frame share the camera's one error: a pair's
#: cross-covariance gains ``L_1 L_2^T`` (:func:`join_frame_radec`).
CAMERA_WHITE_FACTOR = "camera_white_factor"

CSV_COLUMNS = (
    "t_tdb_s", "kind", "unit", "sensor", "target", "star_id",
    "star_x", "star_y", "star_z", "frame_id", "flags", "value", "covariance",
)
#: Columns a file may add (written only when a record carries them; empty cells for the others):
#: the record's :data:`CAMERA_PARAMETERS` (names, space-separated) and :data:`CAMERA_JACOBIAN`
#: (row-major, space-separated, rad per parameter unit, in the ``unit`` column's angle unit per unit).
CAMERA_COLUMNS = ("camera_parameters", "camera_jacobian")


@dataclass(frozen=True)
class Measurement:
    """One time-tagged measurement with its covariance.

    Construction checks shapes only; :meth:`problem` reports NaNs or a covariance
    that is not symmetric positive definite, so a filter can reject the record
    with a logged reason instead of the reader failing.
    """

    t_tdb_s: float
    kind: str
    value: np.ndarray
    covariance: np.ndarray
    target: str = ""
    sensor: str = ""
    star_id: int = 0
    star_unit_icrf: np.ndarray | None = None
    frame_id: str = ""
    flags: int = 0
    extra: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        if self.kind not in KIND_SIZE:
            raise InputError(f"unknown measurement kind {self.kind!r}; known: {', '.join(KIND_SIZE)}")
        size = KIND_SIZE[self.kind]
        value = np.atleast_1d(np.asarray(self.value, dtype=float))
        cov = np.atleast_2d(np.asarray(self.covariance, dtype=float))
        if value.shape != (size,):
            raise InputError(f"{self.kind} measurement needs {size} values, got shape {value.shape}")
        if cov.shape != (size, size):
            raise InputError(f"{self.kind} covariance must be {size}x{size}, got {cov.shape}")
        # read-only copies, so a record cannot change after problem() has judged it
        value = value.copy()
        cov = cov.copy()
        value.flags.writeable = False
        cov.flags.writeable = False
        object.__setattr__(self, "value", value)
        object.__setattr__(self, "covariance", cov)
        object.__setattr__(self, "t_tdb_s", float(self.t_tdb_s))
        if not math.isfinite(self.t_tdb_s):
            raise InputError(f"measurement time must be finite TDB seconds, got {self.t_tdb_s!r}")
        if self.star_unit_icrf is not None:
            star = np.asarray(self.star_unit_icrf, dtype=float)
            if star.shape != (3,):
                raise InputError(f"star_unit_icrf must have shape (3,), got {star.shape}")
            object.__setattr__(self, "star_unit_icrf", star)
        elif self.kind in ("starlight_angle", "starlight_elevation", "starlight", "radial_velocity"):
            raise InputError(f"{self.kind} measurement needs star_unit_icrf")
        if self.kind == "radec_pair" and len(pair_targets(self)) != 2:
            raise InputError(f"radec_pair target must name two bodies as 'a{PAIR_SEPARATOR}b', got {self.target!r}")

    @property
    def size(self) -> int:
        return KIND_SIZE[self.kind]

    def problem(self) -> str | None:
        """Why this record cannot be used (NaN, non-PD covariance), or ``None`` if it can.

        Computed once per record (filters ask at every step of a prediction and an update);
        the value and covariance arrays are read-only, so the answer cannot go stale.
        """
        memo = self.__dict__.get("_problem", False)
        if memo is not False:
            return memo
        reason = self._find_problem()
        self.__dict__["_problem"] = reason
        return reason

    def _find_problem(self) -> str | None:
        if not np.isfinite(self.t_tdb_s):
            return "epoch is not finite"
        if not np.all(np.isfinite(self.value)):
            return "value contains NaN or infinity"
        if not np.all(np.isfinite(self.covariance)):
            return "covariance contains NaN or infinity"
        if not np.allclose(self.covariance, self.covariance.T, rtol=1e-9, atol=0.0):
            return "covariance is not symmetric"
        try:
            np.linalg.cholesky(self.covariance)
        except np.linalg.LinAlgError:
            return "covariance is not positive definite"
        return None


def camera_jacobian(record: Measurement) -> tuple[tuple[str, ...], np.ndarray] | None:
    """The record's camera parameters and d(value)/d(parameters) (m, P), rad per parameter unit, or None
    when it carries none (:data:`CAMERA_JACOBIAN`)."""
    if CAMERA_JACOBIAN not in record.extra:
        return None
    names = tuple(record.extra[CAMERA_PARAMETERS])
    return names, np.asarray(record.extra[CAMERA_JACOBIAN], dtype=float).reshape(record.size, len(names))


def _with_camera_jacobian(names: tuple[str, ...], jac: np.ndarray) -> dict:
    return {CAMERA_PARAMETERS: tuple(names), CAMERA_JACOBIAN: np.asarray(jac, dtype=float).tolist()}


def _stacked_camera_jacobian(first: Measurement, second: Measurement) -> dict:
    """The ``extra`` of a pair: the two records' camera Jacobians stacked (4, P) over the union of their
    parameters (the first's order, then the second's others), a parameter or a record without one giving
    zeros; nothing when neither has one."""
    found = [camera_jacobian(r) for r in (first, second)]
    if found == [None, None]:
        return {}
    names = tuple(dict.fromkeys(n for f in found if f is not None for n in f[0]))
    stacked = np.zeros((4, len(names)))
    for i, f in enumerate(found):
        if f is not None:
            stacked[2 * i:2 * i + 2, [names.index(n) for n in f[0]]] = f[1]
    return _with_camera_jacobian(names, stacked)


def pair_targets(record: Measurement) -> tuple[str, ...]:
    """The target names of a ``radec_pair`` record (empty names dropped)."""
    return tuple(name.strip() for name in record.target.split(PAIR_SEPARATOR) if name.strip())


def join_frame_radec(records: list[Measurement]) -> list[Measurement]:
    """Records with the two ``radec`` records of each frame measured with one attitude made one
    ``radec_pair`` (module docstring); every other record is passed on unchanged, in order.

    Two ``radec`` records are joined when they share ``frame_id`` (not empty) and epoch, are the
    only two of their frame, and both carry :data:`ATTITUDE_JACOBIAN` ``J_i`` and the same
    :data:`ATTITUDE_COVARIANCE` ``C`` in ``extra`` (as the image stage writes them). The pair's
    covariance is ``[[C_1, X], [X^T, C_2]]`` with ``X = J_1 C J_2^T``: each record's own
    covariance already holds its attitude term ``J_i C J_i^T``, so the marginals are unchanged.
    When both carry :data:`CAMERA_WHITE_FACTOR` ``L_i`` (the camera's calibration error in their
    covariances), ``X`` gains ``L_1 L_2^T``: the one camera error moves both moons.
    The pair keeps the first record's sensor and the union of the flags, and the records' camera
    Jacobians stacked (:data:`CAMERA_JACOBIAN`; a record, or a parameter, without one gives zeros).
    """
    by_frame: dict = {}
    for k, record in enumerate(records):
        if record.kind == "radec" and record.frame_id and ATTITUDE_JACOBIAN in record.extra:
            by_frame.setdefault((record.frame_id, record.t_tdb_s), []).append(k)
    joined: dict = {}
    for rows in by_frame.values():
        if len(rows) != 2:
            continue
        first, second = records[rows[0]], records[rows[1]]
        cov_att = np.asarray(first.extra[ATTITUDE_COVARIANCE], float)
        if not np.array_equal(cov_att, np.asarray(second.extra.get(ATTITUDE_COVARIANCE), float)):
            continue
        cross = np.asarray(first.extra[ATTITUDE_JACOBIAN], float) @ cov_att @ np.asarray(
            second.extra[ATTITUDE_JACOBIAN], float).T
        if CAMERA_WHITE_FACTOR in first.extra and CAMERA_WHITE_FACTOR in second.extra:
            cross = cross + np.asarray(first.extra[CAMERA_WHITE_FACTOR], float) @ np.asarray(
                second.extra[CAMERA_WHITE_FACTOR], float).T
        covariance = np.block([[first.covariance, cross], [cross.T, second.covariance]])
        joined[rows[0]] = Measurement(
            t_tdb_s=first.t_tdb_s, kind="radec_pair", value=np.concatenate([first.value, second.value]),
            covariance=0.5 * (covariance + covariance.T), target=f"{first.target}{PAIR_SEPARATOR}{second.target}",
            sensor=first.sensor, frame_id=first.frame_id, flags=first.flags | second.flags,
            extra=_stacked_camera_jacobian(first, second))
        joined[rows[1]] = None
    merged = (joined.get(k, record) for k, record in enumerate(records))
    return [record for record in merged if record is not None]


def split_radec_pairs(records: list[Measurement]) -> list[Measurement]:
    """Each ``radec_pair`` as its two ``radec`` records (marginal covariances; the cross-covariance
    is dropped; a camera Jacobian is split by rows), every other record unchanged, in order: for
    per-target statistics and for formats with one target a record."""
    out = []
    for record in records:
        if record.kind != "radec_pair":
            out.append(record)
            continue
        camera = camera_jacobian(record)
        for i, name in enumerate(pair_targets(record)):
            block = slice(2 * i, 2 * i + 2)
            extra = {} if camera is None else _with_camera_jacobian(camera[0], camera[1][block])
            out.append(Measurement(t_tdb_s=record.t_tdb_s, kind="radec", value=record.value[block],
                                   covariance=record.covariance[block, block], target=name, sensor=record.sensor,
                                   frame_id=record.frame_id, flags=record.flags, extra=extra))
    return out


def _floats(text: str) -> np.ndarray:
    return np.array([float(v) for v in text.split()], dtype=float)


def _fmt(values: np.ndarray) -> str:
    return " ".join(map(repr, np.ravel(values).tolist()))


def file_sha256(path: str | Path) -> str | None:
    """SHA-256 of a file's bytes, hex (None when it cannot be read): a saved stage is reused only
    while its files still have the checksums recorded when they were written."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    except OSError:
        return None
    return digest.hexdigest()


def write_csv(path: str | Path, records: list[Measurement], metadata: dict | None = None) -> None:
    """Write records to ``path`` (CSV) and ``path`` with suffix ``.json`` (metadata), atomically.

    Numbers are Python's shortest repr (they read back exactly); a covariance shared by many records
    (a study's noise model) is formatted once. When any record carries a camera Jacobian
    (:data:`CAMERA_JACOBIAN`) the file has the :data:`CAMERA_COLUMNS` too.
    """
    import io

    buffer = io.StringIO()
    writer = csv.writer(buffer)
    with_camera = any(CAMERA_JACOBIAN in rec.extra for rec in records)
    writer.writerow(CSV_COLUMNS + (CAMERA_COLUMNS if with_camera else ()))
    covariances: dict[bytes, str] = {}
    no_star = ("nan", "nan", "nan")

    def covariance(rec: Measurement) -> str:
        key = rec.covariance.tobytes()
        text = covariances.get(key)
        if text is None:
            text = covariances[key] = _fmt(rec.covariance)
        return text

    def camera(rec: Measurement) -> tuple[str, ...]:
        if not with_camera:
            return ()
        found = camera_jacobian(rec)
        return ("", "") if found is None else (" ".join(found[0]), _fmt(found[1]))

    writer.writerows([
        repr(rec.t_tdb_s), rec.kind, KIND_UNIT[rec.kind], rec.sensor, rec.target, rec.star_id,
        *(no_star if rec.star_unit_icrf is None else map(repr, rec.star_unit_icrf.tolist())),
        rec.frame_id, rec.flags, _fmt(rec.value), covariance(rec), *camera(rec),
    ] for rec in records)
    atomic_write_text(path, buffer.getvalue())
    meta = {"time": "TDB seconds past J2000", "frame": "ICRF", "count": len(records)}
    meta.update(metadata or {})
    atomic_write_text(Path(path).with_suffix(".json"), json.dumps(meta, indent=2, default=str))


#: Angle units a CSV row may give for a kind whose internal unit is rad, with their size in rad.
ANGLE_UNITS = {"rad": 1.0, "deg": np.pi / 180.0, "arcsec": np.pi / 648_000.0}


def _unit_scale(kind: str, unit: str) -> float:
    """Factor from a row's ``unit`` to the kind's internal unit; ``ValueError`` for a unit that is not it.

    Angle kinds accept rad, deg and arcsec (value and covariance are converted); every other kind
    must name its own unit (:data:`KIND_UNIT`), so a value is never read in the wrong unit.
    """
    unit = unit.strip()
    expected = KIND_UNIT.get(kind)
    if expected is None or unit == expected:
        return 1.0
    if expected == "rad" and unit in ANGLE_UNITS:
        return ANGLE_UNITS[unit]
    accepted = sorted(ANGLE_UNITS) if expected == "rad" else [expected]
    raise ValueError(f"unit {unit!r} for a {kind} record; accepted: {', '.join(accepted)}")


#: Largest accepted departure of a CSV star direction from unit length (a typo, not rounding).
STAR_UNIT_TOLERANCE = 1e-4


def _star_direction(row: dict) -> np.ndarray | None:
    """The row's star direction (``None`` when star_x/y/z are all NaN); ``ValueError`` otherwise.

    The models normalise it, so a typo (9.8 for 0.98), a zero vector or one NaN component would
    silently point the record at another star or turn it into NaN: the three cells must be a unit
    vector within :data:`STAR_UNIT_TOLERANCE`.
    """
    star = np.array([float(row["star_x"]), float(row["star_y"]), float(row["star_z"])])
    if np.all(np.isnan(star)):
        return None
    if not (np.all(np.isfinite(star)) and abs(math.hypot(*star) - 1.0) <= STAR_UNIT_TOLERANCE):
        raise ValueError(f"star_x, star_y, star_z = {star.tolist()}; expected a unit vector "
                         f"(length 1 within {STAR_UNIT_TOLERANCE:g}) or nan nan nan for no star")
    return star


def _camera_cells(row: dict, size: int | None, scale: float) -> dict:
    """The record's ``extra`` from the optional :data:`CAMERA_COLUMNS` (empty: none); ``ValueError`` for names
    that are not distinct parameter names or a Jacobian that is not (size, P) finite numbers. (Which names a
    camera has is the camera file's to say: a filter refuses a name its calibration lacks.)"""
    names = (row.get("camera_parameters") or "").split()
    numbers = (row.get("camera_jacobian") or "").strip()
    if not names and not numbers:
        return {}
    if not names or len(set(names)) != len(names) or not all(n.isidentifier() for n in names):
        raise ValueError(f"camera_parameters {' '.join(names)!r}: distinct parameter names (f cx cy k1 k2 k3 p1 p2), "
                         "with a camera_jacobian")
    jac = _floats(numbers)
    if size is None or jac.size != size * len(names) or not np.all(np.isfinite(jac)):
        raise ValueError(f"camera_jacobian must hold {size} x {len(names)} finite numbers (one row a value, one "
                         f"column a camera parameter), got {jac.size}")
    return _with_camera_jacobian(tuple(names), scale * jac.reshape(size, len(names)))


def read_csv(path: str | Path) -> list[Measurement]:
    """Read records written by :func:`write_csv`; malformed rows raise ``InputError`` naming the line.

    The ``unit`` column is honoured: angle kinds may be in rad, deg or arcsec (converted to rad);
    any other mismatch with the kind's unit is an error naming the line.
    """
    path = check_input_file(path, "measurement file", MAX_TEXT_BYTES["table"])
    try:
        return _read_csv_rows(path)
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text CSV file (bytes that are not UTF-8)") from None
    except csv.Error as exc:
        raise InputError(f"{path}: not a readable CSV file ({exc})") from None


def _read_csv_rows(path: Path) -> list[Measurement]:
    records = []
    with path.open(newline="", encoding="utf-8") as handle:
        reader = csv.DictReader(handle)
        missing = set(CSV_COLUMNS) - set(reader.fieldnames or ())
        if missing:
            raise InputError(f"{path}: missing columns {', '.join(sorted(missing))}")
        for line, row in enumerate(reader, start=2):
            try:
                # cells past the header's columns (csv.DictReader files them under None) would be dropped unread
                extra = [cell for cell in row.get(None, ()) if cell.strip()]
                if extra:
                    columns = len(reader.fieldnames)
                    raise ValueError(f"{columns + len(row[None])} cells where the header has {columns} columns")
                star = _star_direction(row)
                kind = row["kind"]
                size = KIND_SIZE.get(kind)
                scale = _unit_scale(kind, row["unit"])
                extra = _camera_cells(row, size, scale)
                records.append(Measurement(
                    t_tdb_s=float(row["t_tdb_s"]),
                    kind=kind,
                    value=scale * _floats(row["value"]),
                    covariance=scale**2 * (_floats(row["covariance"]).reshape(size, size) if size
                                           else _floats(row["covariance"])),
                    target=row["target"],
                    sensor=row["sensor"],
                    star_id=int(row["star_id"] or 0),
                    star_unit_icrf=star,
                    frame_id=row["frame_id"],
                    flags=int(row["flags"] or 0),
                    extra=extra,
                ))
            except InputError as exc:
                raise InputError(f"{path}:{line}: bad measurement row: {exc}") from None
            except (ValueError, TypeError, KeyError, AttributeError) as exc:
                raise InputError(f"{path}:{line}: bad measurement row: {exc}") from None
    return records
