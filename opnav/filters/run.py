"""Run a filter over a record set and keep its history; NEES/NIS consistency checks.

:func:`run_filter` sorts the records by epoch (stable, so records sharing an
epoch keep their order), calls ``filter.update(record)`` for each one and
stores the posterior, residual, NIS and accept/refuse reason after every
record in a frozen :class:`FilterHistory`.

Consistency (Bar-Shalom, Li & Kirubarajan 2001, Sec. 5.4): for a consistent
filter the normalised estimation error squared ``NEES = e^T P^-1 e`` is
chi-square(n) and the normalised innovation squared ``NIS`` is chi-square(m).
The mean of ``N`` independent values times ``N`` is chi-square(N n), which gives
the two-sided bounds of :func:`chi2_mean_bounds`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Iterable

import numpy as np
from scipy import stats
from tqdm import tqdm

from ..errors import InputError
from ..records import Measurement
from .base import NavigationFilter
from .crb import pcrb_predict, pcrb_update
from .ekf import BatchStmPropagator, EKFOptions, ekf_predict_batch, ekf_update_batch
from .noise import ProcessNoise


@dataclass(frozen=True)
class FilterHistory:
    """What a filter did with each record, in processing order.

    Attributes
    ----------
    epochs : (N,) array
        Record epochs, TDB seconds past J2000.
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

    def __len__(self) -> int:
        return int(self.epochs.size)


def run_filter(filter: NavigationFilter, records: Iterable[Measurement], *, progress: bool = True) -> FilterHistory:
    """Process ``records`` in epoch order with ``filter`` and return the history.

    Parameters
    ----------
    filter : NavigationFilter
        Any opnav filter (``update(record) -> UpdateOutcome``); it is advanced in place.
    records : iterable of Measurement
    progress : bool
        Show a tqdm progress bar (on stderr).
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
    for i, record in enumerate(tqdm(ordered, disable=not progress, desc="filter", unit="rec")):
        outcome = filter.update(record)
        epochs[i] = record.t_tdb_s
        states[i] = outcome.estimate.x
        covs[i] = outcome.estimate.P
        residuals[i, : record.size] = outcome.residual
        nis[i] = outcome.nis
        accepted[i] = outcome.accepted
        reasons.append(outcome.reason)
    return FilterHistory(
        epochs=epochs, states=states, covariances=covs, residuals=residuals, nis=nis,
        dof=np.array([r.size for r in ordered]), accepted=accepted, reasons=tuple(reasons),
        kinds=tuple(r.kind for r in ordered), targets=tuple(r.target for r in ordered),
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
class LockstepHistory:
    """K Monte Carlo EKF runs advanced together (see :func:`run_ekf_lockstep`).

    Attributes
    ----------
    epochs : (M,) array
        Kept epochs (every ``keep_every``-th step and the last), TDB s past J2000.
    states : (M, K, 6) array
        Posterior states at the kept epochs; km, km/s, ICRF, dynamics centre.
    covariances : (M, K, 6, 6) array
    nis : (N, T, K) array
        NIS of every run for each of the T record templates at every step (NaN if refused early).
    accepted : (N, T, K) bool array
    pcrb : (M, 6, 6) array or None
        Posterior Cramér-Rao bound covariance at the kept epochs (when a truth was given).
    """

    epochs: np.ndarray
    states: np.ndarray
    covariances: np.ndarray
    nis: np.ndarray
    accepted: np.ndarray
    pcrb: np.ndarray | None


def run_ekf_lockstep(
    t0_tdb_s: float,
    x0: np.ndarray,
    P0: np.ndarray,
    epochs: np.ndarray,
    templates: list[Measurement],
    values: np.ndarray,
    *,
    propagator: BatchStmPropagator,
    model,
    process_noise: ProcessNoise | None = None,
    options: EKFOptions = EKFOptions(),
    truth: np.ndarray | None = None,
    keep_every: int = 1,
    progress: bool = True,
) -> LockstepHistory:
    """Run K independent EKFs that observe the same record epochs, in one vectorised pass.

    Each run is exactly :func:`opnav.filters.ekf.ekf_predict` / ``ekf_update`` (same
    Joseph update, same gate), but the K states share one integration and one
    measurement-model call per record, which is what makes a 50-run, 43,200-step
    Monte Carlo affordable.

    Parameters
    ----------
    t0_tdb_s : float
        Epoch of the initial estimates.
    x0 : (K, 6)
        Initial estimates, km and km/s, ICRF, dynamics centre.
    P0 : (6, 6)
        Initial covariance (shared).
    epochs : (N,)
        Measurement epochs, increasing, after ``t0_tdb_s``.
    templates : list of T Measurement
        Kind, target, covariance of each record taken at every epoch (value and epoch unused).
    values : (T, N, K, m) array
        Measured values of each run.
    propagator : BatchStmPropagator
    model : measurement model with vectorised ``predict`` and ``jacobians``.
    truth : (N + 1, 6) array, optional
        True states at ``t0_tdb_s`` then at ``epochs``; when given, the PCRB is run along it
        (:mod:`opnav.filters.crb`, starting from ``J0 = P0^-1``).
    keep_every : int
        Keep states/covariances every this many steps (memory).
    """
    epochs = np.asarray(epochs, dtype=float)
    x = np.array(x0, dtype=float)
    if x.ndim != 2 or x.shape[1] != 6:
        raise InputError(f"x0 must have shape (K, 6), got {x.shape}")
    k_runs, n_steps = x.shape[0], epochs.size
    values = np.asarray(values, dtype=float)
    if values.shape[:3] != (len(templates), n_steps, k_runs):
        raise InputError(f"values must have shape (T, N, K, m) = ({len(templates)}, {n_steps}, {k_runs}, m), got {values.shape}")
    if np.any(np.diff(np.concatenate([[t0_tdb_s], epochs])) <= 0.0):
        raise InputError("epochs must increase strictly from t0_tdb_s")
    P = np.repeat(np.asarray(P0, dtype=float)[None], k_runs, axis=0)
    with_truth = truth is not None
    if with_truth and np.shape(truth) != (n_steps + 1, 6):
        raise InputError(f"truth must have shape ({n_steps + 1}, 6) (t0 then each epoch), got {np.shape(truth)}")
    J = np.linalg.inv(P0) if with_truth else None
    kept = [i for i in range(n_steps) if i % keep_every == keep_every - 1 or i == n_steps - 1]
    out_x = np.empty((len(kept), k_runs, 6))
    out_P = np.empty((len(kept), k_runs, 6, 6))
    out_crb = np.empty((len(kept), 6, 6)) if with_truth else None
    nis = np.empty((n_steps, len(templates), k_runs))
    accepted = np.empty((n_steps, len(templates), k_runs), dtype=bool)
    t_prev = float(t0_tdb_s)
    row = 0
    for i in tqdm(range(n_steps), disable=not progress, desc="lockstep EKF", unit="step"):
        t = float(epochs[i])
        # the truth rides along as an extra row so its STM (for the PCRB) costs no extra integration
        stack = np.vstack([x, truth[i]]) if with_truth else x
        P_stack = np.concatenate([P, np.eye(6)[None]]) if with_truth else P
        x, P, phi = ekf_predict_batch(t_prev, stack, P_stack, t, propagator=propagator, process_noise=process_noise)
        if with_truth:
            Q = None if process_noise is None else process_noise.discrete(t - t_prev, truth[i])
            J = pcrb_predict(J, phi[-1], Q)
            # the truth row gets a NaN value, so the update refuses it but still returns H at the truth
            x[-1] = truth[i + 1]
        for j, template in enumerate(templates):
            record = replace(template, t_tdb_s=t)
            step_values = np.vstack([values[j, i], np.full((1, record.size), np.nan)]) if with_truth else values[j, i]
            result = ekf_update_batch(x, P, record, step_values, model=model, options=options)
            x, P = result.x, result.P
            nis[i, j], accepted[i, j] = result.nis[:k_runs], result.accepted[:k_runs]
            if with_truth:
                J = pcrb_update(J, result.H[-1], result.R)
        if with_truth:
            x, P = x[:-1], P[:-1]
        if row < len(kept) and kept[row] == i:
            out_x[row], out_P[row] = x, P
            if with_truth:
                out_crb[row] = np.linalg.inv(J)
            row += 1
        t_prev = t
    return LockstepHistory(epochs[kept], out_x, out_P, nis, accepted, out_crb)
