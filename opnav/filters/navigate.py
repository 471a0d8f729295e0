"""Run any filter by name over a record set: the sequential filters, batch least squares and the federated filter.

:func:`navigate` builds the dynamics (:func:`opnav.dynamics.get_model` of ``nav.dynamics``,
unless a force model is given), the measurement model
(:func:`opnav.filters.factory.measurement_model`) and the filter named (``nav.filter`` by
default), runs it and returns a :class:`NavigationResult`:

- ``ekf``, ``ukf``, ``sr-ukf``, ``pf``, ``upf``, ``mcmc-upf``: :func:`opnav.filters.factory.build_filter`
  and :func:`opnav.filters.run.run_filter`; the track is the estimate after each record;
- ``wls``: :func:`opnav.filters.batch.batch_least_squares` from the initial estimate; the track is
  the smoothed trajectory at the record epochs, the history has no NIS;
- ``federated``: :func:`opnav.filters.factory.run_federated_filter` (one local filter per sensor);
  the track is the fused estimates, the history the local filters' outcomes.

:func:`read_measurements` reads a measurement file (CSV or CCSDS TDM) and
:func:`navigation_summary` reduces a result to the ``summary.json`` of ``opnav navigate``
(counts, final estimate, NIS statistics of :func:`opnav.consistency.nis_summary` and the
consistency flags of :mod:`opnav.filters.monitor`). Writing is :mod:`opnav.filters.estimates`.

States ``[r km, v km/s]``, ICRF, relative to the force model's centre; epochs TDB s past J2000.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ..consistency import nis_summary
from ..epochs import format_epoch
from ..errors import InputError
from ..records import Measurement
from .base import Estimate
from .estimates import Track
from .options import NavigationConfig
from .run import FilterHistory

#: Filters that run only on white ephemeris error and have no per-record covariance check.
WHOLE_SET_FILTERS = ("wls", "federated")


@dataclass(frozen=True)
class NavigationResult:
    """One filter run over a record set (:func:`navigate`).

    Attributes
    ----------
    filter : str
        The filter's name.
    dynamics : str
        Force-model name (``nav.dynamics``).
    center : str
        Origin of every state (the force model's centre).
    track : Track
        The estimates: after each record (sequential filters), the smoothed trajectory at the
        record epochs (``wls``) or the fused estimates (``federated``).
    history : FilterHistory
        Per record, in epoch order: estimate, residual, NIS, accepted, reason.
    wall_s : float
        Wall time of building and running the filter, s.
    extra : dict
        ``wls``: ``iterations`` and ``cost``; ``federated``: ``fusions``; else empty.
    """

    filter: str
    dynamics: str
    center: str
    track: Track
    history: FilterHistory
    wall_s: float
    extra: dict = field(default_factory=dict)


def _history_from_batch(result) -> FilterHistory:
    n = len(result.epochs)
    return FilterHistory(
        epochs=result.epochs, states=result.states, covariances=result.covariances, residuals=result.residuals,
        nis=np.full(n, np.nan), dof=np.sum(np.isfinite(result.residuals), axis=1), accepted=result.used,
        reasons=tuple("" if used else "left out (bad record)" for used in result.used),
        kinds=("",) * n, targets=("",) * n,
    )


#: Longest time the filters propagate from the navigation epoch to the first record (20 years, s): a
#: longer one is a wrong epoch (e.g. a year typed wrong), which would propagate for hours first.
MAX_LEAD_S = 20 * 365.25 * 86400.0


def check_epoch_span(records: Sequence[Measurement], t0_tdb_s: float, source: str = "[navigation]") -> None:
    """Refuse records that begin more than :data:`MAX_LEAD_S` after the navigation epoch ``t0_tdb_s`` (TDB s
    past J2000), naming both epochs, instead of propagating for hours before the first record."""
    if not records:
        return
    first = min(record.t_tdb_s for record in records)
    if first - t0_tdb_s > MAX_LEAD_S:
        from ..epochs import format_epoch

        years = (first - t0_tdb_s) / (365.25 * 86400.0)
        # TDB: UTC is not defined for the years such a mistake can name (ERFA would warn)
        raise InputError(f"{source}: the navigation epoch {format_epoch(t0_tdb_s, 'tdb')} TDB is {years:.0f} years "
                         f"before the first record ({format_epoch(first, 'tdb')} TDB); the filters would propagate "
                         f"that long first (at most {MAX_LEAD_S / (365.25 * 86400.0):.0f} years): set the "
                         "epoch near the data")


def check_camera_records(records: Sequence[Measurement], nav: NavigationConfig, name: str,
                         source: str = "[navigation]") -> None:
    """Refuse ``camera_error = "consider"`` (one line naming it) with a filter other than the EKF, over records
    of which none carries a camera Jacobian (the image stage keeps them with the camera's error as
    ``consider``), or with a record naming a parameter that ``nav.camera_parameters`` lacks."""
    from ..records import camera_jacobian

    if name != "ekf":
        raise InputError(f"{source}: camera_error = 'consider' works with filter 'ekf' only, not {name!r}")
    names = {found[0] for found in map(camera_jacobian, records) if found is not None}
    if not names:
        raise InputError(f"{source}: camera_error = 'consider' needs records that carry their camera Jacobian "
                         "(camera_parameters and camera_jacobian columns: the image stage writes them with the "
                         "camera's error as 'consider'); these records have none")
    missing = sorted({n for group in names for n in group} - set(nav.camera_parameters))
    if missing:
        raise InputError(f"{source}: camera_error = 'consider': the records carry camera Jacobians of "
                         f"{', '.join(missing)}, which the camera file's [calibration] "
                         f"({', '.join(nav.camera_parameters)}) does not have")


def navigate(records: Sequence[Measurement], nav: NavigationConfig, *, filter_name: str | None = None,
             exact: bool = False, force_model=None, center: str | None = None, progress: bool = False,
             checked: bool = False, source: str = "[navigation]") -> NavigationResult:
    """Run filter ``filter_name`` (default ``nav.filter``) over ``records`` (module notes).

    Parameters
    ----------
    records : sequence of Measurement
    nav : NavigationConfig
        Initial estimate, dynamics, noise, gate and per-filter options.
    filter_name : str, optional
        One of :data:`opnav.filters.options.FILTERS`.
    exact : bool
        Propagate with DOP853 and the exact ephemeris (as ``nav.exact``; either one turns it on).
    force_model : optional
        :mod:`opnav.dynamics` force model to filter with (default: ``get_model(nav.dynamics)``).
    center : str, optional
        Origin of the states the measurement model takes (default: the force model's centre).
    progress : bool
        Show a progress bar (sequential filters only).
    checked : bool
        Check the covariance after every record (:func:`opnav.filters.run.run_filter`; sequential
        filters only).
    source : str
        Where ``nav`` came from (a scenario file), named in errors.

    Raises
    ------
    InputError
        ``wls`` or ``federated`` with ``ephemeris_error`` or ``camera_error`` other than ``white``, or
        ``checked``; ``camera_error = "consider"`` over records of which none carries a camera Jacobian
        (:data:`opnav.records.CAMERA_JACOBIAN`) or one names a parameter the camera's calibration does
        not have; an unknown or unavailable filter; bad filter options.
    """
    name = filter_name or nav.filter
    check_epoch_span(records, nav.t0_tdb_s, source)
    if exact and not nav.exact:
        nav = dataclasses.replace(nav, exact=True)
    if name in WHOLE_SET_FILTERS and nav.ephemeris_error != "white":
        raise InputError(f"{source}: filter {name!r} takes ephemeris_error = 'white' only, "
                         f"not {nav.ephemeris_error!r}")
    if nav.camera_error == "consider":
        check_camera_records(records, nav, name, source)
    if name in WHOLE_SET_FILTERS and checked:
        raise InputError(f"filter {name!r} has no per-record covariance check; checked runs take a sequential filter")
    from .factory import build_filter, measurement_model, run_federated_filter

    if force_model is None:
        from ..dynamics import get_model

        force_model = get_model(nav.dynamics)
    center = force_model.center if center is None else center
    model = measurement_model(nav, center, ephemeris=getattr(force_model, "ephemeris", None))
    tic = time.perf_counter()
    if name == "wls":
        from .batch import batch_least_squares, force_model_trajectory

        result = batch_least_squares(list(records), Estimate(nav.t0_tdb_s, nav.x0, nav.P0),
                                     propagator=force_model_trajectory(force_model), model=model, options=nav.batch)
        history = _history_from_batch(result)
        track = Track.from_history(history)
        extra = {"iterations": result.iterations, "cost": result.cost}
    elif name == "federated":
        fused, history = run_federated_filter(nav, list(records), model, force_model)
        track = Track(*fused)
        extra = {"fusions": int(track.epochs.size)}
    else:
        from .run import run_filter

        history = run_filter(build_filter(name, nav, model, force_model), records, progress=progress,
                             checked=checked)
        track = Track.from_history(history)
        extra = {}
    return NavigationResult(name, nav.dynamics, center, track, history, time.perf_counter() - tic, extra)


def read_measurements(path: str | Path, *, tdm_sigma_rad: float | None = None) -> list[Measurement]:
    """Records of a measurement CSV (:func:`opnav.records.read_csv`), or of a CCSDS TDM (by suffix
    ``.tdm``/``.xml`` or its first keyword; :func:`opnav.ccsds.read_tdm`, ``tdm_sigma_rad`` the 1-sigma
    of each angle, rad, for TDMs without opnav's covariance comments).

    Raises
    ------
    InputError
        When the file cannot be read or holds no records (naming the file).
    """
    source = Path(path)
    head = b""
    if source.is_file():
        with source.open("rb") as handle:
            head = handle.read(64).lstrip()
    if source.suffix.lower() in (".tdm", ".xml") or head.startswith(b"CCSDS_TDM_VERS"):
        from ..ccsds import read_tdm

        records = read_tdm(source, sigma_rad=tdm_sigma_rad)
    else:
        from ..records import read_csv

        records = read_csv(source)
    if not records:
        raise InputError(f"{path}: no measurement records")
    return records


def navigation_summary(result: NavigationResult, records: Sequence[Measurement], *, measurements: str,
                       scenario: str) -> dict:
    """The ``summary.json`` of ``opnav navigate``: filter, dynamics, centre, the input files
    (``measurements``, ``scenario``), record counts and refusal reasons, the final estimate and its
    1-sigmas, wall time, the filter's ``extra`` figures, the NIS statistics
    (:func:`opnav.consistency.nis_summary`, when any record has a NIS) and, except for ``wls``,
    ``consistency`` (:func:`opnav.filters.monitor.check_history`: flags, ``usable``, ``messages``)."""
    from .monitor import check_history

    history, track = result.history, result.track
    accepted = history.accepted
    t_final = float(track.epochs[-1])
    summary = {
        "filter": result.filter, "dynamics": result.dynamics, "center": result.center,
        "measurements": measurements, "scenario": scenario,
        "records": len(records), "accepted": int(accepted.sum()), "rejected": int((~accepted).sum()),
        "rejection_reasons": sorted({r for r in history.reasons if r}),
        "final": {"t_tdb_s": t_final, "epoch_utc": format_epoch(t_final, "utc"),
                  "state": track.states[-1, :6].tolist(), "state_units": "km, km/s (ICRF)",
                  "sigma": np.sqrt(np.diag(track.covariances[-1])[:6]).tolist()},
        "wall_s": result.wall_s, **result.extra,
    }
    nis = nis_summary(history.nis, history.dof, accepted)
    if nis is not None:
        summary["nis"] = nis
    if result.filter != "wls":
        summary["consistency"] = check_history(history).to_dict()
    return summary
