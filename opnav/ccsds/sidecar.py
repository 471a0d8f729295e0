"""The covariance sidecar of a TDM (``<tdm name>.cov.csv``): what a TDM cannot hold.

A TDM has no per-observation uncertainty and nothing that ties two directions together, so
:func:`opnav.ccsds.write_tdm` writes beside it one CSV row per record, in the records' order: the
epoch text of its observations in the TDM, its exact ``t_tdb_s``, sensor, target (``a+b`` for a
``radec_pair``), frame, flags and covariance (row-major, rad**2; 4x4 for a pair, with the
cross-covariance of the attitude error both targets share). :func:`records_from_sidecar` rebuilds
the records from the TDM's observations and these rows, one to one.
"""

from __future__ import annotations

import csv
import io
import math
from collections import defaultdict, deque
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_write_text
from ..records import PAIR_SEPARATOR, Measurement
from .common import format_shared_epochs, one_line


#: Suffix of a TDM's covariance sidecar (``measurements.tdm`` -> ``measurements.tdm.cov.csv``).
SIDECAR_SUFFIX = ".cov.csv"

_SIDECAR_COLUMNS = ("epoch_tdb", "t_tdb_s", "sensor", "target", "frame_id", "flags", "covariance_rad2")


def tdm_sidecar(path: str | Path) -> Path:
    """The covariance sidecar of TDM ``path``: the same name with :data:`SIDECAR_SUFFIX` appended."""
    path = Path(path)
    return path.with_name(path.name + SIDECAR_SUFFIX)


def write_sidecar(path: Path, records: list[Measurement], epochs: list[str]) -> None:
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


def records_from_sidecar(sidecar: Path, segments: list) -> list[Measurement]:
    """The records of a TDM whose covariances, exact epochs, frames and flags are in ``sidecar``: every
    sidecar row takes the observation(s) of its target(s) at its epoch text and sensor, and every
    observation must be taken exactly once (a sidecar of another TDM is refused).

    ``segments`` are the TDM's segments with angles (``opnav.ccsds.tdm._TdmAngles``: ``where``,
    ``time_system``, ``sensor``, ``target``, epoch texts ``epochs`` and [ra, dec] rad ICRF ``ra``, ``dec``).
    """
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
    texts = format_shared_epochs(np.array([rec.t_tdb_s for rec in records]), f"{sidecar} t_tdb_s")
    for (line, row), text in zip(rows, texts):
        if text != row["epoch_tdb"]:
            raise InputError(f"{sidecar}: line {line}: t_tdb_s {row['t_tdb_s']} is {text} TDB, not its epoch_tdb "
                             f"{row['epoch_tdb']}")
    return records


def _read_sidecar_rows(sidecar: Path) -> list[tuple[int, dict]]:
    try:
        text = sidecar.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{sidecar}: cannot read the TDM's covariance sidecar ({one_line(exc)})") from None
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
