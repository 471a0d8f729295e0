"""CCSDS Tracking Data Messages of RA/Dec angles (TDM 2.0 written, 1.0 and 2.0 read), KVN or NDM/XML.

``radec`` and ``radec_pair`` records (:mod:`opnav.records`): [ra, dec] rad, ICRF, of a target as
seen from the spacecraft, epochs TDB; covariances rad**2, in ``COMMENT`` lines and in the
sidecar (:mod:`opnav.ccsds.sidecar`). The format and its keywords are described in
:mod:`opnav.ccsds` and docs/formats/ccsds.md.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
from collections import Counter, defaultdict, deque
from collections.abc import Iterable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import erfa
import numpy as np
from ccsds_ndm.models import ndmxml4 as _tdm  # TDM 2.0 lives in the NDM/XML 4.0.0 models

from ..epochs import J2000_JD, describe_epoch
from ..errors import InputError
from ..frames import radec_to_unit, unit_to_radec
from ..records import Measurement, pair_targets
from .common import (KEY_WIDTH, creation_time_utc, enum_text, epoch_text, first_true, format_shared_epochs,
                     is_keyword_value, is_xml, keyword_value, load_message, message_segments, number_of, parse_epochs,
                     required_field, time_scale, write_kvn, write_message)
from .sidecar import records_from_sidecar, tdm_sidecar, write_sidecar

log = logging.getLogger(__name__)

_OPNAV_TAG = re.compile(r"\s*opnav\s+(\w+)\s*=\s*(.*?)\s*")

_TDM_HEADER_COMMENT = (
    "opnav optical navigation angles: ANGLE_1 = right ascension, ANGLE_2 = declination (deg, ICRF) "
    "of PARTICIPANT_2 (target) as seen from PARTICIPANT_1 (spacecraft); 'opnav covariance_rad2' "
    "in a segment is the [ra, dec] covariance of all its records, row-major, rad**2; every record's "
    "covariance (two targets of one frame: 4x4, with their cross-covariance) is in the sidecar "
    "<this file>.cov.csv"
)

#: The record kinds a TDM holds: one RA/Dec direction, or two sharing a frame's attitude.
_TDM_KINDS = ("radec", "radec_pair")


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
    originator = keyword_value("originator", originator)
    participant = keyword_value("participant", participant)
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
    epochs = format_shared_epochs(np.array([rec.t_tdb_s for rec in kept]), "records' t_tdb_s")
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
    xml = is_xml(path)
    angles = []
    for rows in groups.values():
        rows.sort(key=lambda row: row[0])  # stable: records of one epoch keep their order
        angles.append(([row[1] for row in rows], [row[2] for row in rows], [row[3] for row in rows]))
    # KVN: ccsds-ndm writes the header and each segment's metadata, the observations are formatted here
    segments = [_tdm_segment(key, {row[4] for row in rows}, ep, participant, path,
                             _tdm_observations(ep, ra, dec) if xml else [])
                for (key, rows), (ep, ra, dec) in zip(groups.items(), angles)]
    tdm = _tdm.Tdm(
        header=_tdm.TdmHeader(comment=[_TDM_HEADER_COMMENT], creation_date=creation_time_utc(), originator=originator),
        body=_tdm.TdmBody(segment=segments),
    )
    if xml:
        write_message(path, tdm, "TDM")
    else:
        write_kvn(path, tdm, [_tdm_kvn_rows(*segment) for segment in angles])
    write_sidecar(tdm_sidecar(path), kept, epochs)
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
    tdm = load_message(path, "TDM", kvn_data=kvn_data)
    sidecar = tdm_sidecar(path)
    skipped: Counter[str] = Counter()
    parsed = message_segments(tdm, path, "TDM")
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
        return records_from_sidecar(sidecar, [s for s in segments if s is not None])
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
    names = {name: bool(name.strip()) and is_keyword_value(name)
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
    if (rec.problem() is None and all(t.strip() and is_keyword_value(t) for t in targets)
            and np.all(np.abs(decs) <= 0.5 * math.pi) and (not rec.sensor or is_keyword_value(rec.sensor))):
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
        keyword_value("target", target)
    if rec.sensor:
        keyword_value("sensor", rec.sensor)


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
    one, two = f"{'ANGLE_1':<{KEY_WIDTH}} = ", f"{'ANGLE_2':<{KEY_WIDTH}} = "
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
    meta, data = required_field(segment, "metadata", where), required_field(segment, "data", where)
    if angles is not None:
        return _segment_angles(where, meta, angles, skipped)
    angles = []
    for obs in getattr(data, "observation", None) or []:
        for f in dataclasses.fields(obs):
            item = getattr(obs, f.name)
            if f.name in ("epoch", "comment") or item is None:
                continue
            if f.name in ("angle_1", "angle_2"):
                epoch = epoch_text(getattr(obs, "epoch", None), f"{where} {f.name.upper()}")
                angles.append((epoch, f.name, number_of(item, f"{where} {f.name.upper()} at {epoch}")))
            else:
                skipped[f.name.upper()] += 1
    return _segment_angles(where, meta, angles, skipped)


def _segment_angles(where: str, meta, angles: list, skipped: Counter) -> _TdmAngles | None:
    if not angles:
        return None
    scale = time_scale(meta, where)
    angle_type = enum_text(getattr(meta, "angle_type", None))
    if angle_type != "RADEC":
        raise InputError(f"{where}: ANGLE_TYPE {angle_type or '(missing)'} is not supported; opnav reads RADEC only")
    frame = enum_text(getattr(meta, "reference_frame", None))
    if frame not in ("ICRF", "EME2000"):
        raise InputError(f"{where}: REFERENCE_FRAME {frame or '(missing)'} is not supported for RADEC; "
                         "expected ICRF or EME2000")
    tags = _opnav_tags(getattr(meta, "comment", None) or [])
    pairs = _pair_angles(angles, skipped)
    if not pairs:
        return None
    t = np.atleast_1d(parse_epochs([epoch for epoch, _, _ in pairs], scale, where))
    ra = np.radians([a1 for _, a1, _ in pairs])
    dec = np.radians([a2 for _, _, a2 in pairs])
    bad = np.abs(dec) > 0.5 * math.pi
    if np.any(bad):
        k = first_true(bad)
        raise InputError(f"{where}: ANGLE_2 {pairs[k][2]!r} deg at {pairs[k][0]} is not a declination (beyond +-90)")
    if frame == "EME2000":
        rb = erfa.bp00(J2000_JD, 0.0)[0]  # frame bias: v_EME2000 = rb @ v_ICRF
        ra, dec = unit_to_radec(radec_to_unit(ra, dec) @ rb)
    return _TdmAngles(where, [epoch for epoch, _, _ in pairs], t, np.atleast_1d(ra), np.atleast_1d(dec),
                      tags.get("target") or _path_source(meta), tags.get("sensor", ""), tags,
                      enum_text(getattr(meta, "time_system", None)))


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
