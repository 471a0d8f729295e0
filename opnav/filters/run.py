"""Run a filter over a record set and keep its history (and, when asked, check its covariance).

:func:`run_filter` sorts the records by epoch (stable, so records sharing an
epoch keep their order), refuses exact duplicates (same epoch, kind, target,
sensor, star and value: a copy carries no new information), calls
``filter.update(record)`` for each other one and
stores the posterior, residual, NIS and accept/refuse reason after every
record in a frozen :class:`FilterHistory`.

The NEES/NIS statistics and chi-square bands live in :mod:`opnav.consistency`;
:func:`history_nees` takes the NEES of a :class:`FilterHistory` against a truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from ..consistency import nees
from ..errors import CovarianceError, InputError
from ..records import Measurement
from .base import NavigationFilter, UpdateOutcome, rejected


@dataclass(frozen=True)
class FilterHistory:
    """What a filter did with each record, in processing order.

    Attributes
    ----------
    epochs : (N,) array
        Epoch of the estimate after each record, TDB seconds past J2000: the record's epoch,
        or the filter's when the record lay in its past and was refused.
    states : (N, n) array
        Estimate after each record (posterior, or the prior when refused); km, km/s, ICRF,
        relative to the dynamics' central body.
    covariances : (N, n, n) array
    residuals : (N, m_max) array
        Innovations (record units), NaN-padded to the widest record; NaN when refused early.
    nis : (N,) array
        Normalised innovation squared (NaN when refused before an innovation existed).
    dof : (N,) int array
        Record sizes m (degrees of freedom of each NIS).
    accepted : (N,) bool array
    reasons : tuple of str
        Empty for accepted records, else why the record was refused.
    kinds, targets : tuple of str
        Record kind and target, for splitting residuals by measurement type.
    ess : (N,) array or None
        Particle filters: the cloud's effective sample size after each record; None for the others.
    health : dict or None
        Checked runs (``run_filter(..., checked=True)``): records checked, the largest relative
        asymmetry and the smallest scaled eigenvalue ratio of the covariance over the run.
    residual_sigmas : (N, m_max) array or None
        Square roots of the innovation covariance's diagonal (record units), laid out as
        ``residuals`` (:func:`run_filter`; None from the batch and federated filters): the 1-sigma a
        report draws each residual against.
    """

    epochs: np.ndarray
    states: np.ndarray
    covariances: np.ndarray
    residuals: np.ndarray
    nis: np.ndarray
    dof: np.ndarray
    accepted: np.ndarray
    reasons: tuple[str, ...]
    kinds: tuple[str, ...]
    targets: tuple[str, ...]
    ess: np.ndarray | None = None
    health: dict | None = None
    residual_sigmas: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.epochs.size)


def without_duplicates(filter) -> Callable[[Measurement], UpdateOutcome]:
    """``filter.update`` that refuses a record equal to one it has seen (same epoch, kind, target,
    sensor, star and value): the same measurement twice is not twice the information."""
    seen: set = set()

    def update(record: Measurement) -> UpdateOutcome:
        key = (record.t_tdb_s, record.kind, record.target, record.sensor, record.star_id, record.value.tobytes())
        if key in seen:
            return rejected(filter.estimate, record.size, "duplicate of an earlier record", record)
        seen.add(key)
        return filter.update(record)

    return update


def covariance_health(P: np.ndarray) -> tuple[float, float]:
    """``(asymmetry, conditioning)`` of a covariance: ``max |P - P^T| / max |P|`` and the smallest
    over the largest eigenvalue of the state-scaled matrix ``D^-1/2 P D^-1/2`` (``D = diag P``;
    scaling makes km and km/s blocks comparable). NaN when ``P`` is not finite.

    Raises
    ------
    CovarianceError
        When ``P`` is not finite, not symmetric to 1e-9 of its size, or not positive definite.
    """
    P = np.asarray(P, dtype=float)
    if not np.all(np.isfinite(P)):
        raise CovarianceError("the covariance contains NaN or infinity")
    size = float(np.max(np.abs(P)))
    asymmetry = float(np.max(np.abs(P - P.T)) / size) if size > 0 else 0.0
    if asymmetry > 1e-9:
        raise CovarianceError(f"the covariance is not symmetric (max |P - P^T| / max |P| = {asymmetry:.3g})")
    scale = 1.0 / np.sqrt(np.abs(np.diag(P)))
    eigenvalues = np.linalg.eigvalsh(0.5 * (P + P.T) * scale[:, None] * scale[None, :])
    if not eigenvalues[0] > 0.0:
        raise CovarianceError(f"the covariance is not positive definite (smallest scaled eigenvalue {eigenvalues[0]:.3g})")
    return asymmetry, float(eigenvalues[0] / eigenvalues[-1])


def run_filter(filter: NavigationFilter, records: Iterable[Measurement], *, progress: bool = False,
               checked: bool = False) -> FilterHistory:
    """Process ``records`` in epoch order with ``filter`` and return the history.

    Parameters
    ----------
    filter : NavigationFilter
        Any opnav filter (``update(record) -> UpdateOutcome``); it is advanced in place.
    records : iterable of Measurement
    progress : bool
        Show a tqdm progress bar (on stderr); off by default, a library stays quiet.
    checked : bool
        Check the covariance after every record (:func:`covariance_health`: finite, symmetric,
        positive definite) and stop with :class:`~opnav.errors.CovarianceError` naming the record
        at the first failure; the worst asymmetry and conditioning go to ``history.health``.
    """
    ordered = sorted(records, key=lambda r: r.t_tdb_s)
    if not ordered:
        raise InputError("no measurement records to process")
    m_max = max(r.size for r in ordered)
    n = filter.estimate.x.size
    count = len(ordered)
    epochs = np.empty(count)
    states = np.empty((count, n))
    covs = np.empty((count, n, n))
    residuals = np.full((count, m_max), np.nan)
    residual_vars = np.full((count, m_max), np.nan)
    nis = np.empty(count)
    accepted = np.empty(count, dtype=bool)
    reasons = []
    # particle filters expose their cloud; its N_eff after each record feeds the consistency monitor
    ess = np.full(count, np.nan) if hasattr(filter, "cloud") else None
    update = without_duplicates(filter)
    worst_asymmetry, worst_conditioning = 0.0, np.inf
    if progress:
        from tqdm import tqdm

        steps = tqdm(ordered, desc="filter", unit="rec")
    else:
        steps = ordered
    for i, record in enumerate(steps):
        outcome = update(record)
        if checked:
            try:
                asymmetry, conditioning = covariance_health(outcome.estimate.P)
            except CovarianceError as exc:
                raise CovarianceError(f"checked run: after record {i} ({record.kind} at t = {record.t_tdb_s:.3f} s TDB): "
                                      f"{exc}") from None
            worst_asymmetry = max(worst_asymmetry, asymmetry)
            worst_conditioning = min(worst_conditioning, conditioning)
        if ess is not None:
            ess[i] = filter.cloud.ess
        # the estimate's own epoch: a record refused in the filter's past leaves the estimate where it
        # was, and its row must not stamp that state with the record's later-looking time tag
        epochs[i] = outcome.estimate.t_tdb_s
        states[i] = outcome.estimate.x
        covs[i] = outcome.estimate.P
        residuals[i, : record.size] = outcome.residual
        residual_vars[i, : record.size] = outcome.residual_cov.diagonal()
        nis[i] = outcome.nis
        accepted[i] = outcome.accepted
        reasons.append(outcome.reason)
    return FilterHistory(
        epochs=epochs, states=states, covariances=covs, residuals=residuals, nis=nis,
        dof=np.array([r.size for r in ordered]), accepted=accepted, reasons=tuple(reasons),
        kinds=tuple(r.kind for r in ordered), targets=tuple(r.target for r in ordered), ess=ess,
        health={"records_checked": count, "max_asymmetry": worst_asymmetry,
                "min_scaled_eigenvalue_ratio": worst_conditioning} if checked else None,
        residual_sigmas=np.sqrt(residual_vars),
    )


def history_nees(history: FilterHistory, truth: Callable[[np.ndarray], np.ndarray], *, size: int = 6) -> np.ndarray:
    """NEES of the first ``size`` states of ``history`` against ``truth(epochs) -> (N, >=size)``."""
    true_states = np.asarray(truth(history.epochs), dtype=float)[:, :size]
    return nees(history.states[:, :size], history.covariances[:, :size, :size], true_states)
