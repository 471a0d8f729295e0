"""Augmented unscented Kalman filter of S3 (Wan & van der Merwe 2000, Algorithm 3.1).

One sigma set is drawn over state, process noise and measurement noise and
carried through both the dynamics and the measurement model, so neither ``Q``
nor ``R`` is added to a covariance afterwards. Per measured step, from the last
posterior ``(x, P)`` at ``t0`` to a record at ``t``:

1. Augmented mean ``[x, 0_q, 0_m]`` and square root ``blkdiag(chol(P),
   sqrt(Q), chol(R))`` (``L = n + q + m``; ``sqrt(Q)`` from
   :func:`opnav.filters.base.psd_sqrt`, since ``Q`` is zero outside the first
   six entries) give ``2L+1`` points (:func:`opnav.filters.ukf.sigma_points`).
2. Their state parts go through ``f(t0, X, W, t)`` with their process-noise
   parts ``W``; the weighted moments are the prior at ``t``.
3. The measurement of point ``i`` is ``h(X_i) + V_i``: innovations
   ``residual(z, h(X_i)) - V_i`` enter :func:`opnav.filters.ukf.innovate` with
   ``R = 0``; the NIS is gated as in the additive UKF.

``augmented_ukf_predict(t)`` reports the prediction from an ``[x, w]`` set (the
record size ``m`` is not known yet) as an :class:`AugmentedPrediction`, which
remembers the posterior it came from; the next update at ``t`` redraws the
joint set from that posterior, so each measured step uses exactly one ``2L+1``
set. Further records at the same epoch use ``[x, v]`` sets drawn from the new
posterior.

:func:`augmented_ukf_predict` and :func:`augmented_ukf_update` are the pure
core; :class:`AugmentedUKF` only holds the models and the current estimate.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Callable

import numpy as np
from scipy import linalg

from ..records import Measurement
from .base import (
    Estimate,
    GaussianFilter,
    MeasurementModel,
    UpdateOutcome,
    check_epoch,
    discrete_noise,
    measurement_covariance,
    psd_sqrt,
    rejected,
    screen_record,
)
from .noise import ProcessNoise
from .ukf import (
    SigmaWeights,
    Transition,
    UKFOptions,
    cross_covariance,
    innovate,
    innovation_outcome,
    sigma_moments,
    sigma_points,
    sigma_weights,
    symmetrized,
)

#: ``noisy_transition(t0_tdb_s, X (K, n), W (K, q), t1_tdb_s) -> (K, n)``: states moved with noise samples ``W``.
NoisyTransition = Callable[[float, np.ndarray, np.ndarray, float], np.ndarray]


def additive_noise(transition: Transition) -> NoisyTransition:
    """Wrap a transition so process noise enters additively after it: ``f(X) + W`` (W is (K, n))."""

    def noisy(t0_tdb_s: float, X: np.ndarray, W: np.ndarray, t1_tdb_s: float) -> np.ndarray:
        return np.asarray(transition(t0_tdb_s, X, t1_tdb_s), dtype=float) + W

    return noisy


@dataclass(frozen=True)
class AugmentedPrediction(Estimate):
    """Predicted moments at ``t_tdb_s`` and the posterior they were predicted from.

    A plain :class:`~opnav.filters.base.Estimate` is its own posterior; an update
    at ``t_tdb_s`` draws its joint sigma set from ``posterior``.

    Attributes
    ----------
    t_tdb_s, x, P
        As in :class:`~opnav.filters.base.Estimate`.
    posterior : Estimate
        The last posterior, at or before ``t_tdb_s``.
    """

    posterior: Estimate


def _posterior(estimate: Estimate) -> Estimate:
    return estimate.posterior if isinstance(estimate, AugmentedPrediction) else estimate


@lru_cache(maxsize=32)
def _weights(L: int, options: UKFOptions) -> SigmaWeights:
    # one weight set per joint dimension L = n + q + m; filterpy rebuilds them on every call
    return sigma_weights(L, options)


def _joint_points(base: Estimate, roots: list[np.ndarray], options: UKFOptions) -> tuple[np.ndarray, SigmaWeights]:
    """Sigma points (2L+1, L) of ``[x, 0, ...]`` with square root ``blkdiag(chol(P), *roots)``, and their weights."""
    S_a = linalg.block_diag(np.linalg.cholesky(base.P), *roots)
    x_a = np.concatenate([base.x, np.zeros(S_a.shape[0] - base.x.size)])
    w = _weights(x_a.size, options)
    return sigma_points(x_a, S_a, w.gamma), w


def _propagate(transition: NoisyTransition, base: Estimate, points: np.ndarray, t1_tdb_s: float, q: int) -> np.ndarray:
    """State parts of joint points moved from ``base``'s epoch to ``t1_tdb_s`` with their ``q`` noise parts."""
    n = base.x.size
    return np.asarray(transition(base.t_tdb_s, points[:, :n], points[:, n : n + q], t1_tdb_s), dtype=float)


def augmented_ukf_predict(
    estimate: Estimate,
    t_tdb_s: float,
    *,
    transition: NoisyTransition,
    process_noise: ProcessNoise | None,
    options: UKFOptions,
) -> Estimate:
    """Predicted estimate at ``t_tdb_s`` (TDB s past J2000) from the last posterior, with an ``[x, w]`` sigma set.

    Parameters
    ----------
    estimate : Estimate
        A posterior, or an :class:`AugmentedPrediction` (the prediction starts from its ``posterior``).
    t_tdb_s : float
        Target epoch; at the current epoch ``estimate`` is returned unchanged.
    transition : NoisyTransition
        ``f(t0, X (K, n), W (K, n), t1)``; :func:`additive_noise` builds one from an ordinary transition.
    process_noise : ProcessNoise or None
        :mod:`opnav.filters.noise` model; ``W`` has covariance
        :func:`opnav.filters.base.discrete_noise` at the posterior's state.
    options : UKFOptions
        Sigma-point parameters (weights for ``L = 2n``).

    Returns
    -------
    AugmentedPrediction
        (or ``estimate`` itself at its own epoch).

    Raises
    ------
    InputError
        If ``t_tdb_s`` is not finite or lies before the estimate's epoch.
    CovarianceError
        If the process noise is not positive semi-definite.
    """
    check_epoch(estimate.t_tdb_s, t_tdb_s)
    if not t_tdb_s > estimate.t_tdb_s:
        return estimate
    base = _posterior(estimate)
    root = psd_sqrt(discrete_noise(process_noise, base.t_tdb_s, t_tdb_s, base.x), "process noise Q")
    points, w = _joint_points(base, [root], options)
    mean, spread = sigma_moments(_propagate(transition, base, points, t_tdb_s, root.shape[0]), w)
    return AugmentedPrediction(float(t_tdb_s), mean, symmetrized(cross_covariance(spread, spread, w)), base)


def augmented_ukf_update(
    estimate: Estimate,
    record: Measurement,
    *,
    transition: NoisyTransition,
    process_noise: ProcessNoise | None,
    model: MeasurementModel,
    options: UKFOptions,
) -> UpdateOutcome:
    """Fold ``record`` into ``estimate`` with one joint sigma set drawn from the last posterior.

    Parameters
    ----------
    estimate : Estimate
        Prior at ``record.t_tdb_s`` (from :func:`augmented_ukf_predict`, or a posterior at that epoch).
    record : Measurement
    transition : NoisyTransition
    process_noise : ProcessNoise or None
        As for :func:`augmented_ukf_predict`: the joint set is redrawn from the posterior with
        ``[x, w, v]`` when the posterior is older than the record, else with ``[x, v]``.
    model : MeasurementModel
        Vectorised measurement model; ``R`` (:func:`opnav.filters.base.measurement_covariance`)
        is evaluated at ``estimate.x``.
    options : UKFOptions
        Sigma-point parameters and ``gate_probability``.

    Returns
    -------
    UpdateOutcome
        The posterior (a plain Estimate, the next sigma sets' source), or ``estimate``
        itself when the record is refused (bad values, another epoch, non-PD innovation
        covariance or posterior, chi-square gate). Residual, ``S`` and NIS are those of
        the joint sigma set.
    """
    refusal = screen_record(estimate, record)
    if refusal is not None:
        return refusal
    base = _posterior(estimate)
    n = estimate.x.size
    m = record.size
    if record.t_tdb_s > base.t_tdb_s:
        root = psd_sqrt(discrete_noise(process_noise, base.t_tdb_s, record.t_tdb_s, base.x), "process noise Q")
        q = root.shape[0]
        R_root = np.linalg.cholesky(measurement_covariance(model, record, estimate.x))
        points, w = _joint_points(base, [root, R_root], options)
        state_points = _propagate(transition, base, points, record.t_tdb_s, q)
    else:
        q = 0
        points, w = _joint_points(base, [np.linalg.cholesky(measurement_covariance(model, record, estimate.x))], options)
        state_points = points[:, :n]
    mean, spread = sigma_moments(state_points, w)
    P_prior = symmetrized(cross_covariance(spread, spread, w))
    try:
        post = innovate(mean, P_prior, state_points, record, model=model, weights=w, R=np.zeros((m, m)),
                        noise=points[:, n + q : n + q + m])
    except np.linalg.LinAlgError:
        return rejected(estimate, m, "innovation covariance is not positive definite", record)
    return innovation_outcome(estimate, record, post, gate_probability=options.gate_probability)


class AugmentedUKF(GaussianFilter):
    """Augmented UKF of S3 holding its models and the current estimate; see the module docstring.

    Parameters
    ----------
    estimate : Estimate
        Initial state and covariance.
    transition : NoisyTransition
        ``f(t0, X (K, n), W (K, n), t1) -> (K, n)`` with noise samples ``W``;
        :func:`additive_noise` builds one from an ordinary transition.
    process_noise : ProcessNoise or None
        :mod:`opnav.filters.noise` model; ``W`` has its covariance
        :func:`opnav.filters.base.discrete_noise` (zero outside the first six entries, which is
        allowed: the augmented square root is built block by block).
    model : MeasurementModel
    options : UKFOptions
    """

    def __init__(
        self,
        estimate: Estimate,
        *,
        transition: NoisyTransition,
        process_noise: ProcessNoise | None,
        model: MeasurementModel,
        options: UKFOptions = UKFOptions(),
    ) -> None:
        self.transition = transition
        self.process_noise = process_noise
        self.model = model
        self.options = options
        self.reset(estimate)

    def _predict(self, estimate: Estimate, t_tdb_s: float) -> Estimate:
        # the predicted estimate is the posterior the next [x, w] sigma set is drawn from
        return augmented_ukf_predict(estimate, t_tdb_s, transition=self.transition,
                                     process_noise=self.process_noise, options=self.options)

    def _update(self, prior: Estimate, record: Measurement) -> UpdateOutcome:
        # one joint sigma set drawn from the last posterior
        return augmented_ukf_update(prior, record, transition=self.transition, process_noise=self.process_noise,
                                    model=self.model, options=self.options)
