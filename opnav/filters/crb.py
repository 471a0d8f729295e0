"""Posterior Cramér-Rao bound (PCRB) for nonlinear filtering, Tichavsky et al. (1998).

For dynamics ``x_{k+1} = f(x_k) + w_k`` (``w ~ N(0, Q_k)``) and measurements
``z_k = h(x_k) + v_k`` (``v ~ N(0, R_k)``) with additive Gaussian noise, the
information matrix ``J_k`` (inverse of the bound on the estimation-error
covariance) obeys (Tichavsky, Muravchik & Nehorai 1998, IEEE TSP 46(5), eq. 21,
in the form of their Sec. IV for additive Gaussian noise):

    J_{k+1} = (Q_k + F_k J_k^-1 F_k^T)^-1 + H_{k+1}^T R_{k+1}^-1 H_{k+1},

with ``F_k = df/dx`` and ``H = dh/dx`` averaged over the true-state
distribution. Along one known truth trajectory (the Monte Carlo set-up of S1,
whose runs share the truth and differ in noise) the expectations collapse to
the Jacobians *at the truth*, and the recursion is that of a Kalman filter's
covariance linearised at the truth: the bound any unbiased estimator must
respect, against which the EKF's RMS error is compared.

Vectors: state ``[r km, v km/s]`` (ICRF, relative to the dynamics' centre);
``J`` is in the inverse units.
"""

from __future__ import annotations

import numpy as np
from scipy import linalg

from ..errors import CovarianceError, InputError


def _spd_inverse(matrix: np.ndarray, name: str) -> np.ndarray:
    try:
        factor = linalg.cho_factor(0.5 * (matrix + matrix.T))
    except linalg.LinAlgError:
        raise CovarianceError(f"{name} is not positive definite") from None
    inverse = linalg.cho_solve(factor, np.eye(matrix.shape[0]))
    return 0.5 * (inverse + inverse.T)


def pcrb_predict(J: np.ndarray, F: np.ndarray, Q: np.ndarray | None = None) -> np.ndarray:
    """Information after the dynamics step: ``(Q + F J^-1 F^T)^-1`` (n, n)."""
    prior_cov = F @ _spd_inverse(J, "information matrix J") @ F.T
    if Q is not None:
        prior_cov = prior_cov + Q
    return _spd_inverse(prior_cov, "predicted bound covariance Q + F J^-1 F^T")


def pcrb_update(J: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Information after a measurement: ``J + H^T R^-1 H``; ``H`` (m, n), ``R`` (m, m)."""
    info = H.T @ _spd_inverse(np.atleast_2d(R), "measurement covariance R") @ H
    out = J + info
    return 0.5 * (out + out.T)


def pcrb(
    P0: np.ndarray,
    transitions: np.ndarray,
    jacobians: list[np.ndarray],
    noises: list[np.ndarray],
    process_noise: np.ndarray | None = None,
) -> np.ndarray:
    """Bound covariances ``J_k^-1`` after each step of the recursion, shape (N, n, n).

    Parameters
    ----------
    P0 : (n, n)
        Prior covariance at the first epoch (``J_0 = P0^-1``).
    transitions : (N, n, n)
        ``F_k`` from epoch k-1 to k at the truth (identity for records sharing an epoch).
    jacobians : list of N (m_k, n) arrays
        Measurement Jacobians at the truth at epoch k.
    noises : list of N (m_k, m_k) arrays
        Measurement covariances.
    process_noise : (N, n, n), optional
        ``Q`` over each transition.
    """
    transitions = np.asarray(transitions, dtype=float)
    if not (len(transitions) == len(jacobians) == len(noises)):
        raise InputError("pcrb: transitions, jacobians and noises must have the same length")
    J = _spd_inverse(np.asarray(P0, dtype=float), "P0")
    out = np.empty((len(transitions),) + J.shape)
    for k, F in enumerate(transitions):
        Q = None if process_noise is None else process_noise[k]
        J = pcrb_update(pcrb_predict(J, F, Q), jacobians[k], noises[k])
        out[k] = _spd_inverse(J, "information matrix J")
    return out


def pcrb_along(ekf, records, t0_tdb_s: float, start_truth: np.ndarray, P0: np.ndarray, epochs: np.ndarray,
               truth: np.ndarray) -> np.ndarray:
    """The bound along a truth, by an EKF's own steps held on the truth: covariances at ``epochs``, (N, n, n).

    Along a known truth the recursion above is a Kalman filter's covariance linearised at the
    truth (module notes), so the bound is what ``ekf`` (an :class:`~opnav.filters.ekf.ExtendedKalmanFilter`
    with no gate) computes for its covariance when its state is put back on the truth before every
    record: ``P = F P F^T + Q`` over the step, then the update with ``H`` and ``R`` there (for the
    first record of an epoch, at the truth of the previous epoch propagated by the filter's
    dynamics, which differs from the truth by the propagators' difference over one step). Whatever
    the filter's path (compiled or general), the state it estimates is ignored.

    Parameters
    ----------
    ekf : ExtendedKalmanFilter
        Built for the records' measurement model and the truth's dynamics; its gate off.
    records : sequence of Measurement
        At epochs of ``epochs`` (records of one epoch in any order).
    t0_tdb_s : float
        Epoch of ``start_truth`` and ``P0`` (TDB s past J2000).
    start_truth : (6,) array
        True ``[r km, v km/s]`` at ``t0_tdb_s``, ICRF, relative to the filter's centre.
    P0 : (n, n) array
        Prior covariance (``J_0 = P0^-1``); states beyond the first six (augmented
        parameters) have a true value of zero.
    epochs : (N,) array  truth : (N, 6) array
        Truth epochs (TDB s past J2000, increasing) and states, as ``start_truth``.

    Returns
    -------
    (N, n, n) array
        The bound after the last record at each epoch (the prediction alone at an epoch with none).
    """
    from .base import Estimate

    n = P0.shape[0]
    states = np.zeros((epochs.size, n))
    states[:, :6] = truth
    start = np.zeros(n)
    start[:6] = start_truth
    ordered = sorted(records, key=lambda record: record.t_tdb_s)
    index = np.searchsorted(epochs, [record.t_tdb_s for record in ordered])
    if np.any(index >= epochs.size) or np.any(epochs[np.minimum(index, epochs.size - 1)]
                                              != [record.t_tdb_s for record in ordered]):
        raise InputError("pcrb_along: every record must be at an epoch of the truth")
    out = np.empty((epochs.size, n, n))
    t_prev, x_prev, P = float(t0_tdb_s), start, np.asarray(P0, dtype=float)
    ekf.reset(Estimate(t_prev, x_prev, P))  # the prior is checked once; later covariances are the filter's own
    done = 0
    for i, t in enumerate(epochs):
        while done < len(ordered) and index[done] == i:
            ekf.hold(Estimate(t_prev, x_prev, P))
            P = ekf.update(ordered[done]).estimate.P
            t_prev, x_prev = float(t), states[i]
            done += 1
        if t_prev != t:  # no record at this epoch: the prediction alone
            ekf.hold(Estimate(t_prev, x_prev, P))
            P = ekf.predict(float(t)).P
            t_prev, x_prev = float(t), states[i]
        out[i] = P
    return out
