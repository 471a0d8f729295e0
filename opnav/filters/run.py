"""Run a filter over a record set and keep its history; NEES/NIS consistency checks.

:func:`run_filter` sorts the records by epoch (stable, so records sharing an
epoch keep their order), refuses exact duplicates (same epoch, kind, target,
sensor, star and value: a copy carries no new information), calls
``filter.update(record)`` for each other one and
stores the posterior, residual, NIS and accept/refuse reason after every
record in a frozen :class:`FilterHistory`.

Consistency (Bar-Shalom, Li & Kirubarajan 2001, Sec. 5.4): for a consistent
filter the normalised estimation error squared ``NEES = e^T P^-1 e`` is
chi-square(n) and the normalised innovation squared ``NIS`` is chi-square(m).
The mean of ``N`` independent values times ``N`` is chi-square(N n), which gives
the two-sided bounds of :func:`chi2_mean_bounds`. :func:`ensemble_nees` is the Monte Carlo
test built on them (Sec. 5.4.2): the NEES of N runs averaged at each epoch against that band.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

import numpy as np
from scipy import stats
from tqdm import tqdm

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


def run_filter(filter: NavigationFilter, records: Iterable[Measurement], *, progress: bool = True,
               checked: bool = False) -> FilterHistory:
    """Process ``records`` in epoch order with ``filter`` and return the history.

    Parameters
    ----------
    filter : NavigationFilter
        Any opnav filter (``update(record) -> UpdateOutcome``); it is advanced in place.
    records : iterable of Measurement
    progress : bool
        Show a tqdm progress bar (on stderr).
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
    nis = np.empty(count)
    accepted = np.empty(count, dtype=bool)
    reasons = []
    # particle filters expose their cloud; its N_eff after each record feeds the consistency monitor
    ess = np.full(count, np.nan) if hasattr(filter, "cloud") else None
    update = without_duplicates(filter)
    worst_asymmetry, worst_conditioning = 0.0, np.inf
    for i, record in enumerate(tqdm(ordered, disable=not progress, desc="filter", unit="rec")):
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
        nis[i] = outcome.nis
        accepted[i] = outcome.accepted
        reasons.append(outcome.reason)
    return FilterHistory(
        epochs=epochs, states=states, covariances=covs, residuals=residuals, nis=nis,
        dof=np.array([r.size for r in ordered]), accepted=accepted, reasons=tuple(reasons),
        kinds=tuple(r.kind for r in ordered), targets=tuple(r.target for r in ordered), ess=ess,
        health={"records_checked": count, "max_asymmetry": worst_asymmetry,
                "min_scaled_eigenvalue_ratio": worst_conditioning} if checked else None,
    )


def nees(states: np.ndarray, covariances: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared ``(x - x_true)^T P^-1 (x - x_true)``, shape (N,).

    Parameters
    ----------
    states : (N, n) array
    covariances : (N, n, n) array
    truth : (N, n) array
        True states at the same epochs, same frame, origin and units.
    """
    states = np.asarray(states, dtype=float)
    truth = np.asarray(truth, dtype=float)
    if truth.shape != states.shape or np.shape(covariances) != states.shape + states.shape[-1:]:
        raise InputError(f"nees: states {np.shape(states)}, covariances {np.shape(covariances)} and truth "
                         f"{np.shape(truth)} do not match")
    err = states - truth
    chol = np.linalg.cholesky(covariances)
    white = np.linalg.solve(chol, err[..., None])[..., 0]
    return np.sum(white * white, axis=-1)


def history_nees(history: FilterHistory, truth: Callable[[np.ndarray], np.ndarray], *, size: int = 6) -> np.ndarray:
    """NEES of the first ``size`` states of ``history`` against ``truth(epochs) -> (N, >=size)``."""
    true_states = np.asarray(truth(history.epochs), dtype=float)[:, :size]
    return nees(history.states[:, :size], history.covariances[:, :size, :size], true_states)


def chi2_mean_bounds(dof: int, count: int, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided ``probability`` interval of the mean of ``count`` independent chi-square(dof) values."""
    if dof < 1 or count < 1:
        raise InputError(f"chi2_mean_bounds needs dof >= 1 and count >= 1, got {dof}, {count}")
    tail = 0.5 * (1.0 - probability)
    total = dof * count
    return float(stats.chi2.ppf(tail, total) / count), float(stats.chi2.ppf(1.0 - tail, total) / count)



@dataclass(frozen=True)
class EnsembleNEES:
    """Result of the Monte Carlo NEES test (:func:`ensemble_nees`).

    Attributes
    ----------
    runs : int
        Runs averaged at each epoch (N).
    epochs : int
        Epochs, matched to the second, that every run has inside the judged window (E).
    mean : float
        Mean over those epochs of the run-averaged NEES.
    band : (float, float)
        Two-sided ``probability`` interval of the mean of N chi-square(``dof``) values.
    share_inside : float
        Share of the E epochs whose run-averaged NEES lies inside ``band`` (bounds included).
    dof : int
        Degrees of freedom of one NEES value (the states it is taken over).
    probability : float
    """

    runs: int
    epochs: int
    mean: float
    band: tuple[float, float]
    share_inside: float
    dof: int
    probability: float

    def to_dict(self) -> dict:
        return {"runs": self.runs, "epochs": self.epochs, "mean": self.mean, "band": list(self.band),
                "share_inside": self.share_inside, "dof": self.dof, "probability": self.probability}


def ensemble_nees(runs: Sequence[tuple[np.ndarray, np.ndarray]], dof: int, window_start_tdb_s: float,
                  probability: float = 0.95) -> EnsembleNEES:
    """Monte Carlo NEES test (Bar-Shalom, Li & Kirubarajan 2001, Sec. 5.4.2) over N runs of one filter.

    One run cannot test consistency: its epochs share one estimation error, so a run whose error
    sits 3 sigma out along a weak axis is out of any band at every epoch. Across independent runs
    the NEES at one epoch are independent, and for a consistent filter their mean is distributed
    as chi-square(N dof) / N. So the NEES is averaged over the runs at each epoch they share in the
    judged window and compared with the two-sided ``probability`` interval of that mean
    (:func:`chi2_mean_bounds`); a consistent filter has about ``probability`` of the epochs inside,
    an overconfident one (covariance too small) falls above the band, a pessimistic one below.
    The epochs of one run are correlated (the error changes slowly), so the share scatters far
    more than a binomial count: a few runs of a consistent filter can give a share near 0 or 1.

    Parameters
    ----------
    runs : sequence of (epochs, nees)
        Per run: epochs (TDB s past J2000) and the NEES at them, 1-D arrays of one length.
        Epochs are matched across runs to the nearest second.
    dof : int
        Degrees of freedom of one NEES value: the number of states it is taken over (6 for
        position and velocity, whatever parameters the filter's state carries beside them).
    window_start_tdb_s : float
        Start of the judged window, TDB s past J2000: epochs (rounded to the second) from it on count.
    probability : float
        Coverage of the band, in (0, 1).

    Returns
    -------
    EnsembleNEES

    Raises
    ------
    InputError
        No runs; a run whose epoch and NEES arrays differ in length, are not 1-D, or whose epochs
        are not finite; a NaN or infinite NEES in the window; two epochs of one run within the
        same second; no epoch in the window that every run has; ``probability`` outside (0, 1).
    """
    if not len(runs):
        raise InputError("ensemble_nees: no runs")
    if not 0.0 < probability < 1.0:
        raise InputError(f"ensemble_nees: probability must be in (0, 1), got {probability}")
    judged = [_judged_epochs(i, t, values, window_start_tdb_s) for i, (t, values) in enumerate(runs)]
    shared = judged[0][0]
    for seconds, _ in judged[1:]:
        shared = np.intersect1d(shared, seconds, assume_unique=True)
    if not shared.size:
        raise InputError(f"ensemble_nees: the {len(runs)} runs share no epoch (to the second) from "
                         f"{window_start_tdb_s} s TDB on")
    per_epoch = np.mean([values[np.searchsorted(seconds, shared)] for seconds, values in judged], axis=0)
    low, high = chi2_mean_bounds(dof, len(runs), probability)
    return EnsembleNEES(runs=len(runs), epochs=int(shared.size), mean=float(per_epoch.mean()), band=(low, high),
                        share_inside=float(np.mean((per_epoch >= low) & (per_epoch <= high))), dof=int(dof),
                        probability=float(probability))


def _judged_epochs(index: int, epochs, values, window_start_tdb_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Run ``index``'s epochs in the window, rounded to whole seconds and sorted, and its NEES at them."""
    epochs = np.asarray(epochs, dtype=float)
    values = np.asarray(values, dtype=float)
    if epochs.ndim != 1 or epochs.shape != values.shape:
        raise InputError(f"ensemble_nees: run {index} has epochs of shape {epochs.shape} and NEES of shape "
                         f"{values.shape}; both must be 1-D of one length")
    if not np.all(np.isfinite(epochs)):
        raise InputError(f"ensemble_nees: run {index} has epochs that are not finite")
    # runs simulated alike carry their epochs with different float noise: match them to the second
    seconds = np.round(epochs).astype(np.int64)
    inside = seconds >= window_start_tdb_s
    order = np.argsort(seconds[inside], kind="stable")
    seconds, values = seconds[inside][order], values[inside][order]
    if np.any(np.diff(seconds) == 0):
        raise InputError(f"ensemble_nees: run {index} has two epochs within one second; they cannot be matched "
                         "across runs to the second")
    bad = int(np.count_nonzero(~np.isfinite(values)))
    if bad:
        raise InputError(f"ensemble_nees: run {index} has {bad} NaN or infinite NEES value(s) in the window")
    return seconds, values
