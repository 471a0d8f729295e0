"""Monte Carlo in lockstep: K independent runs of one filter advanced through one time loop.

The runs observe the same record epochs and kinds (one template per kind and
target), each with its own measured values (its own noise draws, so any run
replays alone with its seed). Every step does ONE propagation of all K states
(:class:`opnav.dynamics.fast.FastPropagator` takes (K, 6) arrays) and ONE
measurement-model call for all K states or sigma points, then the filter's own
update arithmetic batched over K. Each run is exactly what the single-run
filter computes (``tests/test_lockstep.py`` checks it run by run):

- :func:`run_ekf_lockstep`: :func:`opnav.filters.ekf.ekf_predict_batch` /
  :func:`~opnav.filters.ekf.ekf_update_batch` (Joseph update, chi-square gate),
  with the posterior Cramer-Rao bound along the truth riding along as an extra row;
- :func:`run_ukf_lockstep`: :func:`opnav.filters.ukf.ukf_predict` /
  :func:`~opnav.filters.ukf.ukf_update` on (K, n) means and (K, n, n) covariances.

A run whose record is refused (gate) or missing (NaN value: the target was not
observed in that run at that epoch) keeps its prior for that record.
States: ``[r km, v km/s]``, ICRF, relative to the dynamics' central body; epochs
TDB seconds past J2000.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from tqdm import tqdm

from ..errors import InputError
from ..records import Measurement
from .base import chi2_quantile
from .crb import pcrb_predict, pcrb_update
from .ekf import BatchStmPropagator, EKFOptions, batch_process_noise, ekf_predict_batch, ekf_update_batch
from .noise import ProcessNoise


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
    progress: bool = False,
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
    x0 : (K, n)
        Initial estimates, km and km/s, ICRF, dynamics centre (runs differ by their draws);
        entries beyond six are constant parameters (e.g. target-ephemeris offsets,
        :class:`opnav.measurements.TargetOffsetModel`), held by the propagator.
    P0 : (n, n)
        Initial covariance (shared).
    epochs : (N,)
        Measurement epochs, increasing, after ``t0_tdb_s``.
    templates : list of T Measurement
        Kind, target, covariance of each record taken at every epoch (value and epoch unused).
    values : (T, N, K, m) array
        Measured values of each run.
    propagator : BatchStmPropagator
    model : measurement model with vectorised ``predict`` and ``jacobians``.
    truth : (N + 1, n) array, optional
        True states at ``t0_tdb_s`` then at ``epochs``; when given, the PCRB is run along it
        (:mod:`opnav.filters.crb`, starting from ``J0 = P0^-1``).
    keep_every : int
        Keep states/covariances every this many steps (memory).
    progress : bool
        Show a progress bar (tqdm, on stderr), one tick per epoch; off by default.
    """
    epochs, x, values = _check_inputs(t0_tdb_s, x0, epochs, templates, values)
    k_runs, n_steps = x.shape[0], epochs.size
    P = np.repeat(np.asarray(P0, dtype=float)[None], k_runs, axis=0)
    n = x.shape[1]
    with_truth = truth is not None
    if with_truth and np.shape(truth) != (n_steps + 1, n):
        raise InputError(f"truth must have shape ({n_steps + 1}, {n}) (t0 then each epoch), got {np.shape(truth)}")
    J = np.linalg.inv(P0) if with_truth else None
    kept = _kept_steps(n_steps, keep_every)
    out_x = np.empty((len(kept), k_runs, n))
    out_P = np.empty((len(kept), k_runs, n, n))
    out_crb = np.empty((len(kept), n, n)) if with_truth else None
    nis = np.empty((n_steps, len(templates), k_runs))
    accepted = np.empty((n_steps, len(templates), k_runs), dtype=bool)
    t_prev = float(t0_tdb_s)
    row = 0
    for i in tqdm(range(n_steps), disable=not progress, desc="lockstep EKF", unit="step"):
        t = float(epochs[i])
        # the truth rides along as an extra row so its STM (for the PCRB) costs no extra integration
        stack = np.vstack([x, truth[i]]) if with_truth else x
        P_stack = np.concatenate([P, np.eye(n)[None]]) if with_truth else P
        x, P, phi = ekf_predict_batch(t_prev, stack, P_stack, t, propagator=propagator, process_noise=process_noise)
        if with_truth:
            Q = None
            if process_noise is not None:
                Q = np.zeros((n, n))
                Q[:6, :6] = process_noise.discrete(t - t_prev, truth[i, :6])
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
                J = pcrb_update(J, result.H[-1], result.R[-1])  # H and R at the truth
        if with_truth:
            x, P = x[:-1], P[:-1]
        if row < len(kept) and kept[row] == i:
            out_x[row], out_P[row] = x, P
            if with_truth:
                out_crb[row] = np.linalg.inv(J)
            row += 1
        t_prev = t
    return LockstepHistory(epochs[kept], out_x, out_P, nis, accepted, out_crb)


def _check_inputs(t0_tdb_s: float, x0: np.ndarray, epochs: np.ndarray, templates: list[Measurement],
                  values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    epochs = np.asarray(epochs, dtype=float)
    x = np.array(x0, dtype=float)
    if x.ndim != 2 or x.shape[1] < 6:
        raise InputError(f"x0 must have shape (K, n >= 6), got {x.shape}")
    k_runs, n_steps = x.shape[0], epochs.size
    values = np.asarray(values, dtype=float)
    if values.shape[:3] != (len(templates), n_steps, k_runs):
        raise InputError(f"values must have shape (T, N, K, m) = ({len(templates)}, {n_steps}, {k_runs}, m), "
                         f"got {values.shape}")
    if n_steps == 0 or np.any(np.diff(np.concatenate([[t0_tdb_s], epochs])) <= 0.0):
        raise InputError("epochs must be non-empty and increase strictly from t0_tdb_s")
    return epochs, x, values


def _kept_steps(n_steps: int, keep_every: int) -> list[int]:
    if keep_every < 1:
        raise InputError(f"keep_every must be >= 1, got {keep_every}")
    return [i for i in range(n_steps) if i % keep_every == keep_every - 1 or i == n_steps - 1]


class _RunValues:
    """A measurement model whose residuals take each run's own measured value.

    ``predict`` is the wrapped model's; ``residual(record, predicted)`` for predicted
    values of K runs x P points (K * P, m) returns ``values_k - predicted`` wrapped like
    the model's own residual (RA to (-pi, pi]); ``zero`` is the record with a zero value.
    """

    def __init__(self, model, values: np.ndarray, points_per_run: int, zero: Measurement):
        self.model = model
        self.values = np.repeat(values, points_per_run, axis=0)
        self.zero = zero
        noise = getattr(model, "noise_covariance", None)
        if noise is not None:
            self.noise_covariance = noise

    def predict(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        return self.model.predict(record, x)

    def residual(self, record: Measurement, predicted: np.ndarray) -> np.ndarray:
        return self.model.residual(self.zero, predicted - self.values)


def run_ukf_lockstep(
    t0_tdb_s: float,
    x0: np.ndarray,
    P0: np.ndarray,
    epochs: np.ndarray,
    templates: list[Measurement],
    values: np.ndarray,
    *,
    transition,
    model,
    process_noise: ProcessNoise | None = None,
    options=None,
    keep_every: int = 1,
    progress: bool = False,
) -> LockstepHistory:
    """Run K independent additive-noise UKFs that observe the same record epochs, in one pass.

    Each run is :func:`opnav.filters.ukf.ukf_predict` then, per record,
    :func:`~opnav.filters.ukf.ukf_update` with the UKF's chi-square gate, exactly as
    :class:`~opnav.filters.ukf.UnscentedKalmanFilter` computes it; all ``K (2n + 1)``
    sigma points go through ``transition`` and the measurement model in one call each.

    Parameters
    ----------
    t0_tdb_s, x0 (K, n), P0 (n, n), epochs (N,), templates, values (T, N, K, m)
        As :func:`run_ekf_lockstep`.
    transition : Transition
        ``transition(t0, X (M, 6), t1) -> (M, 6)``, e.g. :func:`opnav.filters.ukf.force_model_transition`.
    model : measurement model with a vectorised ``predict``.
    process_noise : ProcessNoise, optional
    options : UKFOptions, optional
        Sigma-point scaling and gate (default ``UKFOptions()``).
    keep_every, progress
        As :func:`run_ekf_lockstep`.

    Returns
    -------
    LockstepHistory
        ``pcrb`` is None (run :func:`run_ekf_lockstep` with the truth for the bound).
    """
    from .ukf import UKFOptions, sigma_weights, ukf_predict, ukf_update

    options = options if options is not None else UKFOptions()
    epochs, x, values = _check_inputs(t0_tdb_s, x0, epochs, templates, values)
    k_runs, n_steps = x.shape[0], epochs.size
    P = np.repeat(np.asarray(P0, dtype=float)[None], k_runs, axis=0)
    weights = sigma_weights(6, options)
    points = 2 * weights.n + 1
    kept = _kept_steps(n_steps, keep_every)
    out_x = np.empty((len(kept), k_runs, 6))
    out_P = np.empty((len(kept), k_runs, 6, 6))
    nis = np.empty((n_steps, len(templates), k_runs))
    accepted = np.empty((n_steps, len(templates), k_runs), dtype=bool)
    zeros = [replace(template, value=np.zeros(template.size)) for template in templates]
    t_prev = float(t0_tdb_s)
    row = 0
    for i in tqdm(range(n_steps), disable=not progress, desc="lockstep UKF", unit="step"):
        t = float(epochs[i])
        Q = batch_process_noise(process_noise, t - t_prev, x)
        x, P, _ = ukf_predict(x, P, t_prev, t, transition=transition, Q=Q, weights=weights)
        for j, template in enumerate(templates):
            # runs without a value at this epoch (NaN: no record, e.g. a target out of view) skip it
            has = np.all(np.isfinite(values[j, i]), axis=-1)
            nis[i, j], accepted[i, j] = np.nan, False
            if not has.any():
                continue
            record = replace(template, t_tdb_s=t)
            post = ukf_update(x[has], P[has], record, model=_RunValues(model, values[j, i][has], points, zeros[j]),
                              weights=weights)
            ok = np.isfinite(post.nis)
            if options.gate_probability is not None:
                ok &= post.nis <= chi2_quantile(options.gate_probability, record.size)
            x[has] = np.where(ok[:, None], post.x, x[has])
            P[has] = np.where(ok[:, None, None], post.P, P[has])
            nis[i, j, has], accepted[i, j, has] = post.nis, ok
        if row < len(kept) and kept[row] == i:
            out_x[row], out_P[row] = x, P
            row += 1
        t_prev = t
    return LockstepHistory(epochs[kept], out_x, out_P, nis, accepted, None)
