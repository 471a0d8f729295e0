"""Batch weighted least squares (Gauss-Newton with the STM) for orbit determination.

Estimates the state ``x0`` at epoch ``t0`` from all records at once
(Tapley, Schutz & Born 2004, Statistical Orbit Determination, Sec. 4.6):

1. Propagate the current guess of ``x0`` and the STM ``Phi(t_i, t0)`` to every
   record epoch in one integration.
2. For each usable record, innovation ``nu_i = z_i - h(x(t_i))`` (angles
   wrapped by the model) and ``H_i = dh/dx(x(t_i)) Phi(t_i, t0)``.
3. Normal equations with the a-priori ``(x_bar, P_bar)``:
   ``N = P_bar^-1 + sum H_i^T R_i^-1 H_i``,
   ``b = P_bar^-1 (x_bar - x0) + sum H_i^T R_i^-1 nu_i``, ``dx = N^-1 b``.
4. Stop when the step is small against its own uncertainty,
   ``dx^T N dx < tolerance`` (the step moves the estimate by less than
   sqrt(tolerance) sigma); the covariance of ``x0`` is ``N^-1``.

Records with NaN, a non-PD covariance or a non-finite prediction are left out
with a logged reason. States at the record epochs with covariances
``Phi N^-1 Phi^T`` form the smoothed trajectory.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import linalg

from ..errors import ConvergenceError, CovarianceError, InputError
from ..records import Measurement
from .base import Estimate, MeasurementModel, check_covariance, measurement_covariance
from .option_types import BatchOptions

log = logging.getLogger(__name__)

#: ``propagator(t0_tdb_s, x0 (6,), t (M,)) -> (states (M, 6), Phi (M, 6, 6))``, epochs sorted from t0.
TrajectoryPropagator = Callable[[float, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def force_model_trajectory(model) -> TrajectoryPropagator:
    """Wrap an :mod:`opnav.dynamics` force model as a :data:`TrajectoryPropagator`."""
    from ..dynamics import propagate

    def run(t0: float, x0: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        traj = propagate(model, t0, x0, t, stm=True)
        return traj.states, traj.stm

    return run


@dataclass(frozen=True)
class BatchResult:
    """Solution of :func:`batch_least_squares`.

    Attributes
    ----------
    estimate : Estimate
        ``x0`` and its covariance ``N^-1`` at the solve epoch.
    iterations : int
    cost : float
        Weighted residual sum of squares ``sum nu^T R^-1 nu`` at the solution (chi-square with
        ``sum m_i - n`` degrees of freedom for a correct model).
    epochs, states, covariances : (N,), (N, n), (N, n, n)
        Smoothed trajectory at the record epochs (records sorted by epoch).
    residuals : (N, m_max)
        Post-fit residuals, NaN-padded; NaN for records left out.
    used : (N,) bool
        Records that entered the normal equations.
    """

    estimate: Estimate
    iterations: int
    cost: float
    epochs: np.ndarray
    states: np.ndarray
    covariances: np.ndarray
    residuals: np.ndarray
    used: np.ndarray


def _usable(records: list[Measurement]) -> np.ndarray:
    mask = np.ones(len(records), dtype=bool)
    for i, record in enumerate(records):
        reason = record.problem()
        if reason is not None:
            log.warning("batch: left out %s measurement at t=%.3f s: %s", record.kind, record.t_tdb_s, reason)
            mask[i] = False
    return mask


def batch_least_squares(
    records: list[Measurement],
    apriori: Estimate,
    *,
    propagator: TrajectoryPropagator,
    model: MeasurementModel,
    options: BatchOptions = BatchOptions(),
) -> BatchResult:
    """Gauss-Newton weighted least squares for the state at ``apriori.t_tdb_s``.

    Parameters
    ----------
    records : list of Measurement
        At or after the a-priori epoch (any order).
    apriori : Estimate
        First guess and a-priori covariance (a very large ``P`` means "no prior"), state
        ``[r km, v km/s]`` ICRF relative to the propagator's centre.
    propagator : TrajectoryPropagator
    model : MeasurementModel
    options : BatchOptions

    Raises
    ------
    ConvergenceError
        If the step does not fall below the tolerance within ``max_iterations``.
    InputError
        For records before the a-priori epoch or no usable records.
    """
    ordered = sorted(records, key=lambda r: r.t_tdb_s)
    if not ordered:
        raise InputError("batch_least_squares: no records")
    t0 = float(apriori.t_tdb_s)
    if ordered[0].t_tdb_s < t0 - 1e-9:
        raise InputError(f"batch_least_squares: record at {ordered[0].t_tdb_s:.3f} s is before the a-priori epoch {t0:.3f} s")
    used = _usable(ordered)
    if not used.any():
        raise InputError("batch_least_squares: no usable records")
    x_bar = np.asarray(apriori.x, dtype=float)
    n = x_bar.size
    info_bar = linalg.cho_solve(linalg.cho_factor(check_covariance(apriori.P, "apriori.P")), np.eye(n))
    epochs = np.array([r.t_tdb_s for r in ordered])
    # records sharing an epoch share one propagated state (the integrator needs distinct epochs)
    unique_epochs, which = np.unique(epochs, return_inverse=True)

    def trajectory(x_start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        states, phis = propagator(t0, x_start, unique_epochs)
        return states[which], phis[which]

    m_max = max(r.size for r in ordered)
    x0 = x_bar.copy()
    for iteration in range(1, options.max_iterations + 1):
        states, phis = trajectory(x0)
        normal = info_bar.copy()
        rhs = info_bar @ (x_bar - x0)
        residuals = np.full((len(ordered), m_max), np.nan)
        cost = 0.0
        for i, record in enumerate(ordered):
            if not used[i]:
                continue
            nu = model.residual(record, model.predict(record, states[i]))
            H = model.jacobian(record, states[i]) @ phis[i]
            R_inv = linalg.cho_solve(linalg.cho_factor(measurement_covariance(model, record, states[i])), np.eye(record.size))
            residuals[i, : record.size] = nu
            normal += H.T @ R_inv @ H
            rhs += H.T @ R_inv @ nu
            cost += float(nu @ R_inv @ nu)
        try:
            factor = linalg.cho_factor(0.5 * (normal + normal.T))
        except linalg.LinAlgError:
            raise CovarianceError("batch normal matrix is not positive definite: the state is unobservable "
                                  "from these records (add records or an a-priori covariance)") from None
        dx = linalg.cho_solve(factor, rhs)
        x0 = x0 + dx
        step = float(dx @ normal @ dx)
        log.info("batch iteration %d: cost %.6g, step %.3g sigma^2", iteration, cost, step)
        if step < options.tolerance:
            cov0 = check_covariance(linalg.cho_solve(factor, np.eye(n)), "batch covariance")
            states, phis = trajectory(x0)
            covs = phis @ cov0 @ np.swapaxes(phis, -1, -2)
            cost = 0.0
            for i, record in enumerate(ordered):
                if used[i]:
                    nu = model.residual(record, model.predict(record, states[i]))
                    residuals[i, : record.size] = nu
                    R = measurement_covariance(model, record, states[i])
                    cost += float(nu @ np.linalg.solve(R, nu))
            return BatchResult(Estimate(t0, x0, cov0), iteration, cost, epochs, states,
                               0.5 * (covs + np.swapaxes(covs, -1, -2)), residuals, used)
    raise ConvergenceError(f"batch least squares did not converge in {options.max_iterations} iterations "
                           f"(last step {step:.3g} sigma^2 > tolerance {options.tolerance:g})")
