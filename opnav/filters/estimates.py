"""Writers of a filter's estimates, the one place both ``opnav navigate`` and the study runner use.

- :class:`Track`: epochs, states and covariances of an estimate sequence (after each record,
  the smoothed trajectory of batch least squares, or the fused estimates of a federated run);
- :func:`write_estimates_csv`, :func:`write_covariances_csv`, :func:`write_residuals_csv`: the
  CSV tables of ``opnav navigate`` (numbers as Python ``repr``, so they read back exactly);
- :func:`write_oem`: the track as a CCSDS OEM with covariance (:mod:`opnav.ccsds`, the last
  estimate of each epoch, the spacecraft as ``OBJECT_NAME``); :func:`write_records_tdm`: the RA/Dec
  records (single and paired) as a CCSDS TDM with its covariance sidecar;
- :func:`write_json` (``summary.json``, stage records) and :func:`save_npz` (array files);
- :func:`write_navigation_outputs`: the full set ``opnav navigate`` writes into its folder.

Every file is written atomically (a temporary file beside it, then a rename). States are
``[r km, v km/s]`` (then any augmented parameters), ICRF, relative to the dynamics' central
body; epochs TDB seconds past J2000. :mod:`opnav.ccsds` is imported only when an OEM or TDM is
written.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..epochs import format_epoch
from ..files import atomic_output, atomic_write_text
from ..records import Measurement
from .run import FilterHistory

#: Columns of the state in ``estimates.csv`` (km, km/s, ICRF, about the dynamics' centre).
STATE_COLUMNS = ("x_km", "y_km", "z_km", "vx_km_s", "vy_km_s", "vz_km_s")


@dataclass(frozen=True)
class Track:
    """A sequence of estimates.

    Attributes
    ----------
    epochs : (N,) array
        TDB seconds past J2000.
    states : (N, n) array
        ``[r km, v km/s, ...]``, ICRF, relative to the dynamics' central body.
    covariances : (N, n, n) array
        Their covariances (km^2, km^2/s, km^2/s^2 blocks).
    """

    epochs: np.ndarray
    states: np.ndarray
    covariances: np.ndarray

    @classmethod
    def from_history(cls, history: FilterHistory) -> "Track":
        """The estimate after each record of ``history``."""
        return cls(history.epochs, history.states, history.covariances)


def _csv(rows: list[list], header: Sequence[str]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue()


def write_estimates_csv(path: str | Path, track: Track) -> None:
    """``t_tdb_s, epoch_utc``, the six states and their 1-sigmas (``sigma_<column>``) per estimate."""
    epochs_utc = format_epoch(track.epochs, "utc")
    sig = np.sqrt(np.diagonal(track.covariances, axis1=1, axis2=2))
    rows = [[repr(t), utc, *map(repr, x), *map(repr, s)]
            for t, utc, x, s in zip(_floats(track.epochs), epochs_utc, _floats(track.states[:, :6]),
                                    _floats(sig[:, :6]))]
    atomic_write_text(path, _csv(rows, ["t_tdb_s", "epoch_utc", *STATE_COLUMNS,
                                        *(f"sigma_{c}" for c in STATE_COLUMNS)]))


def write_covariances_csv(path: str | Path, track: Track) -> None:
    """``t_tdb_s`` and the upper triangle of each covariance (``p<i><j>``, row-major)."""
    iu = np.triu_indices(track.states.shape[1])
    upper = np.asarray(track.covariances, dtype=float)[:, iu[0], iu[1]]
    rows = [[repr(t), *map(repr, P)] for t, P in zip(_floats(track.epochs), _floats(upper))]
    atomic_write_text(path, _csv(rows, ["t_tdb_s", *(f"p{i}{j}" for i, j in zip(*iu))]))


def write_residuals_csv(path: str | Path, history: FilterHistory, records: Sequence[Measurement]) -> None:
    """Per record (in epoch order, as the filter took them): epoch, kind, target, sensor, accepted,
    NIS, refusal reason and the residual (record units, space-separated)."""
    ordered = sorted(records, key=lambda r: r.t_tdb_s)
    rows = [[repr(r.t_tdb_s), r.kind, r.target, r.sensor, int(ok), repr(nis), reason,
             " ".join(map(repr, res[: r.size]))]
            for r, ok, nis, reason, res in zip(ordered, history.accepted, _floats(history.nis), history.reasons,
                                                _floats(history.residuals))]
    atomic_write_text(path, _csv(rows, ["t_tdb_s", "kind", "target", "sensor", "accepted", "nis", "reason",
                                        "residual"]))


def _floats(array) -> list:
    """``array`` as nested lists of Python floats (their repr is the shortest that reads back exactly),
    converted in one call instead of one ``float()`` a number."""
    return np.asarray(array, dtype=float).tolist()


def write_oem(path: str | Path, track: Track, *, center: str, object_name: str, comment: str,
              object_id: str | None = None) -> None:
    """The track as a CCSDS OEM with covariance (:func:`opnav.ccsds.write_estimates_oem`):
    ``object_name`` is the spacecraft (``OBJECT_NAME``, and ``OBJECT_ID`` unless ``object_id`` is
    given), ``center`` the origin of the states, ``comment`` says what the estimates are (filter, run)."""
    from ..ccsds import write_estimates_oem

    write_estimates_oem(path, track.epochs, track.states, track.covariances, center=center,
                        object_name=object_name, object_id=object_id, comment=comment)


def write_records_tdm(path: str | Path, records: Sequence[Measurement], *, spacecraft: str = "opnav") -> bool:
    """The ``radec`` and ``radec_pair`` records a filter can use as a CCSDS TDM with its covariance sidecar
    ``<path>.cov.csv`` (:func:`opnav.ccsds.write_tdm`; ``spacecraft`` is ``PARTICIPANT_1``); False
    (nothing written) when there are none."""
    from ..ccsds import tdm_ready, write_tdm

    radec = tdm_ready(records)
    if not radec:
        return False
    write_tdm(path, radec, participant=spacecraft)
    return True


def write_json(path: str | Path, data: dict) -> None:
    """``data`` as indented JSON (numpy scalars as floats)."""
    atomic_write_text(path, json.dumps(data, indent=2, default=float))


def save_npz(path: Path, **arrays) -> None:
    """``np.savez`` of ``arrays`` to ``path`` durably and atomically (:func:`opnav.files.atomic_output`)."""
    with atomic_output(path) as handle:
        np.savez(handle, **arrays)


def write_navigation_outputs(out: str | Path, track: Track, history: FilterHistory, records: Sequence[Measurement],
                             summary: dict, *, spacecraft: str = "opnav") -> None:
    """What ``opnav navigate`` writes into folder ``out``: ``estimates.csv``, ``covariances.csv``
    (of ``track``), ``residuals.csv`` (of ``history``), ``estimates.oem`` (object ``spacecraft``),
    ``measurements.tdm`` and its sidecar ``measurements.tdm.cov.csv`` (when there are RA/Dec records;
    ``spacecraft`` is their observer) and ``summary.json`` (``summary``; its ``center`` and ``filter``
    give the OEM's centre and comment)."""
    out = Path(out)
    write_estimates_csv(out / "estimates.csv", track)
    write_covariances_csv(out / "covariances.csv", track)
    write_residuals_csv(out / "residuals.csv", history, records)
    write_oem(out / "estimates.oem", track, center=summary["center"], object_name=spacecraft,
              comment=f"opnav navigate, filter {summary['filter']}")
    write_records_tdm(out / "measurements.tdm", records, spacecraft=spacecraft)
    write_json(out / "summary.json", summary)
