"""Unscented Kalman filter (additive noise) and the unscented kernels its other forms share.

Algorithm (scaled unscented transform, van der Merwe 2004, ch. 3):

1. Sigma points ``X_0 = x``, ``X_i = x +/- gamma * S[:, i]`` with ``S S^T = P``
   (lower Cholesky factor), ``gamma = sqrt(n + lambda)``,
   ``lambda = alpha^2 (n + kappa) - n``; weights ``Wm_0 = lambda / (n + lambda)``,
   ``Wc_0 = Wm_0 + 1 - alpha^2 + beta``, ``Wm_i = Wc_i = 1 / (2 (n + lambda))`` (those of filterpy's
   :class:`~filterpy.kalman.MerweScaledSigmaPoints`, written out: importing filterpy.kalman
   imports scipy.stats, ~0.3 s of every process that runs a UKF).
2. Prediction: all ``2n+1`` points go through the transition in ONE call
   (``transition(t0, X (K, n), t1)``), so a vectorised propagator (and its
   ephemeris evaluations) serves every point at once. Mean and covariance are
   the weighted moments plus the process noise ``Q(t0, t1)``.
3. Update: sigma points are redrawn from the predicted ``(x, P)`` and passed
   through the measurement model in one ``predict(record, X (K, n))`` call.
   Innovations are formed per point with the model's own ``residual`` (so RA
   wraps at 2 pi), then ``S = sum Wc (nu_i - nu)(nu_i - nu)^T + R``,
   ``Pxz = -sum Wc (X_i - x)(nu_i - nu)^T``, ``K = Pxz S^-1``.

Moments are accumulated as offsets from the central point
(``x = X_0 + sum_{i>0} Wm_i (X_i - X_0)``, covariance in the form of
:func:`cross_covariance`) because with ``alpha = 1e-3`` the central weight is
about -1e6: summing raw heliocentric positions (1e8 km) with such weights would
lose metres to cancellation.

Layers: :func:`ukf_predict` and :func:`ukf_update` work on arrays, one Gaussian
or a batch of them (the particle filters and lockstep Monte Carlo use them);
:func:`ukf_predict_estimate` and :func:`ukf_update_estimate` are the pure
filter core on :class:`~opnav.filters.base.Estimate`;
:class:`UnscentedKalmanFilter` only holds the models and the estimate (with the
default models it takes ``radec`` and ``radec_pair`` records in one compiled
step of the same formulas, :mod:`opnav.filters.compiled`, and gives every other
record, and every one that step does not accept, to the pure core). The
square-root form is in :mod:`opnav.filters.sr_ukf`, the augmented form of S3 in
:mod:`opnav.filters.augmented_ukf`; both reuse the kernels here
(:func:`sigma_points`, :func:`sigma_moments`, :func:`cross_covariance`,
:func:`innovate`).

Vectors: states are ``[r (km), v (km/s)]``, ICRF, relative to the central body
of whatever ``transition`` integrates (see :mod:`opnav.filters.base`); other
state sizes work the same way.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

from ..errors import CovarianceError, InputError
from ..records import Measurement
from .base import (
    Estimate,
    GaussianFilter,
    MeasurementModel,
    UpdateOutcome,
    check_covariance,
    check_epoch,
    discrete_noise,
    gate_refusal,
    measurement_covariance,
    refused,
    rejected,
    screen_record,
)
from .noise import ProcessNoise
from .option_types import UKFOptions

#: ``transition(t0_tdb_s, X (K, n), t1_tdb_s) -> (K, n)``: states moved from t0 to t1.
Transition = Callable[[float, np.ndarray, float], np.ndarray]


@dataclass(frozen=True)
class SigmaWeights:
    """Weights of the scaled unscented transform for dimension ``n``."""

    n: int
    gamma: float
    Wm: np.ndarray
    Wc: np.ndarray


def force_model_transition(model, *, exact: bool = False) -> Transition:
    """Wrap an :mod:`opnav.dynamics` force model as a :data:`Transition` for K states in ONE call.

    States are ``[r (km), v (km/s)]`` ICRF relative to ``model.center``; entries
    beyond the first six (augmented parameters) are held constant. ``exact=False``
    (default) uses the compiled fixed-step propagator
    (:class:`opnav.dynamics.fast.FastPropagator`, no STM), ``exact=True`` DOP853.
    """
    if exact:
        from ..dynamics import propagate

        fast = None

        def six(t0_tdb_s: float, X: np.ndarray, t1_tdb_s: float) -> np.ndarray:
            return propagate(model, t0_tdb_s, X, np.array([t1_tdb_s])).states[-1]
    else:
        from ..dynamics.fast import FastPropagator

        fast = FastPropagator(model)

        def six(t0_tdb_s: float, X: np.ndarray, t1_tdb_s: float) -> np.ndarray:
            return fast.step(t0_tdb_s, X, t1_tdb_s, stm=False)[0]

    def step(t0_tdb_s: float, X: np.ndarray, t1_tdb_s: float) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        if X.shape[1] == 6:
            return six(t0_tdb_s, X, t1_tdb_s)
        moved = X.copy()
        moved[:, :6] = six(t0_tdb_s, X[:, :6], t1_tdb_s)
        return moved

    # the compiled single-run step (opnav.filters.compiled) propagates with the same FastPropagator
    step.fast_propagator = fast
    return step


def sigma_weights(n: int, options: UKFOptions) -> SigmaWeights:
    """Mean/covariance weights of the scaled unscented transform and the point scale ``gamma = sqrt(n + lambda)``.

    van der Merwe (2004), eq. 3.170-3.171: ``lambda = alpha^2 (n + kappa) - n``,
    ``Wm_0 = lambda / (n + lambda)``, ``Wc_0 = Wm_0 + (1 - alpha^2 + beta)``, every other weight
    ``1 / (2 (n + lambda))`` (the same numbers as filterpy's ``MerweScaledSigmaPoints``).
    """
    if n + options.kappa <= 0.0:
        raise InputError(f"UKFOptions.kappa={options.kappa} makes n + kappa <= 0 for n={n}")
    lam = options.alpha**2 * (n + options.kappa) - n
    Wm = np.full(2 * n + 1, 0.5 / (n + lam))
    Wc = Wm.copy()
    Wm[0] = lam / (n + lam)
    Wc[0] = lam / (n + lam) + (1.0 - options.alpha**2 + options.beta)
    return SigmaWeights(n, float(np.sqrt(n + lam)), Wm, Wc)


def sigma_points(x: np.ndarray, S: np.ndarray, gamma: float) -> np.ndarray:
    """Scaled sigma points, ordered as filterpy orders them.

    Parameters
    ----------
    x : (..., n) array
        Means (any leading batch shape; units and frame of the state).
    S : (..., n, n) array
        Lower-triangular square roots, ``S S^T = P``.
    gamma : float
        Point scale ``sqrt(n + lambda)``.

    Returns
    -------
    (..., 2n+1, n) array
        ``[x, x + gamma S[:, 0], ..., x + gamma S[:, n-1], x - gamma S[:, 0], ...]``.
    """
    spread = gamma * np.swapaxes(S, -1, -2)
    centre = x[..., None, :]
    return np.concatenate([centre, centre + spread, centre - spread], axis=-2)


class SigmaSpread(NamedTuple):
    """Points relative to the central one: ``offsets`` (..., 2L, k) for i >= 1, ``shift`` = mean - X_0 (..., k)."""

    offsets: np.ndarray
    shift: np.ndarray


def sigma_moments(points: np.ndarray, w: SigmaWeights) -> tuple[np.ndarray, SigmaSpread]:
    """Weighted mean (..., k) of points (..., 2L+1, k) and their spread about the central point."""
    offsets = points[..., 1:, :] - points[..., :1, :]
    shift = np.einsum("i,...ik->...k", w.Wm[1:], offsets)
    return points[..., 0, :] + shift, SigmaSpread(offsets, shift)


def cross_covariance(a: SigmaSpread, b: SigmaSpread, w: SigmaWeights) -> np.ndarray:
    """Weighted cross-covariance ``sum_i Wc_i (A_i - a)(B_i - b)^T`` (..., j, k).

    Notes
    -----
    With ``D_i = X_i - X_0`` and ``d = x - X_0 = sum_{i>0} Wm_i D_i`` (and
    ``Wc_i = Wm_i`` for ``i > 0``) the sum equals
    ``sum_{i>0} Wc_i D_i^A D_i^B^T + (sum Wc - 2) d^A d^B^T``, where
    ``sum Wc - 2 = beta - alpha^2``. The central weight (about -1/alpha^2) never
    multiplies anything, which keeps the moments exact to rounding and lets the
    square-root form skip its Cholesky downdate.
    """
    c = float(np.sum(w.Wc)) - 2.0
    return np.einsum("i,...ij,...ik->...jk", w.Wc[1:], a.offsets, b.offsets) + c * (
        a.shift[..., :, None] * b.shift[..., None, :]
    )


def symmetrized(P: np.ndarray) -> np.ndarray:
    """``(P + P^T) / 2`` over the last two axes."""
    return 0.5 * (P + np.swapaxes(P, -1, -2))


@dataclass(frozen=True)
class Innovation:
    """Outcome of an unscented measurement update (possibly batched over particles).

    ``x``/``P`` are the posterior, ``residual`` the mean innovation
    ``z - z_hat`` (record units), ``S`` its covariance, ``nis`` the normalised
    innovation squared.
    """

    x: np.ndarray
    P: np.ndarray
    residual: np.ndarray
    S: np.ndarray
    nis: np.ndarray


def ukf_predict(
    x: np.ndarray,
    P: np.ndarray,
    t0_tdb_s: float,
    t1_tdb_s: float,
    *,
    transition: Transition,
    Q: np.ndarray,
    weights: SigmaWeights,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unscented time update of one or a batch of Gaussians.

    Parameters
    ----------
    x : (..., n) array
        Means at ``t0_tdb_s`` (state units, frame of ``transition``).
    P : (..., n, n) array
        Covariances at ``t0_tdb_s``.
    t0_tdb_s, t1_tdb_s : float
        Epochs, TDB seconds past J2000.
    transition : Transition
        Called once with all ``(...) * (2n+1)`` points.
    Q : (n, n) array
        Process-noise covariance added over the interval.

    Returns
    -------
    x1 : (..., n) array
    P1 : (..., n, n) array
        Predicted moments at ``t1_tdb_s`` including ``Q``.
    central : (..., n) array
        The propagated central points ``f(x)`` (used by the particle filters).
    """
    n = weights.n
    points = sigma_points(x, np.linalg.cholesky(P), weights.gamma)
    moved = np.asarray(transition(t0_tdb_s, points.reshape(-1, n), t1_tdb_s), dtype=float).reshape(points.shape)
    mean, spread = sigma_moments(moved, weights)
    P1 = cross_covariance(spread, spread, weights) + Q
    return mean, symmetrized(P1), moved[..., 0, :]


def ukf_update(
    x: np.ndarray,
    P: np.ndarray,
    record: Measurement,
    *,
    model: MeasurementModel,
    weights: SigmaWeights,
) -> Innovation:
    """Unscented measurement update of one or a batch of Gaussians with one record.

    Parameters
    ----------
    x : (..., n) array
        Prior means at ``record.t_tdb_s``.
    P : (..., n, n) array
        Prior covariances.
    record : Measurement
        The measurement; the additive noise ``R`` is the model's
        ``noise_covariance(record, x)`` when it has one (target-ephemeris error),
        else ``record.covariance`` (:func:`opnav.filters.base.measurement_covariance`).
    model : MeasurementModel
        Vectorised predictor ``predict(record, X (K, n)) -> (K, m)``.

    Raises
    ------
    numpy.linalg.LinAlgError
        If a prior or innovation covariance is not positive definite.

    Notes
    -----
    Innovations of the individual points are ``nu_i = residual(z, h(X_i))`` so
    angle wrapping is the model's business, and
    ``S = sum Wc (nu_i - nu)(nu_i - nu)^T + R``,
    ``Pxz = sum Wc (X_i - x)(h_i - z_hat)^T = -sum Wc (X_i - x)(nu_i - nu)^T``.
    """
    points = sigma_points(x, np.linalg.cholesky(P), weights.gamma)
    # each mean its own R (the target range), so a Monte Carlo run's figures do not depend on its batch
    R = np.reshape(measurement_covariance(model, record, np.reshape(x, (-1, x.shape[-1]))),
                   (*np.shape(x)[:-1], record.size, record.size))
    return innovate(x, P, points, record, model=model, weights=weights, R=R)


def innovate(
    x: np.ndarray,
    P: np.ndarray,
    points: np.ndarray,
    record: Measurement,
    *,
    model: MeasurementModel,
    weights: SigmaWeights,
    R: np.ndarray,
    noise: np.ndarray | None = None,
) -> Innovation:
    """Kalman update of ``(x, P)`` from its sigma points through the measurement model.

    Parameters
    ----------
    x : (..., n) array
        Prior means.
    P : (..., n, n) array
        Prior covariances.
    points : (..., 2L+1, n) array
        State parts of the sigma points (``L = n`` unless augmented).
    record : Measurement
    model : MeasurementModel
    weights : SigmaWeights
        Weights of the ``2L+1`` points.
    R : (m, m) array
        Measurement noise added to ``S``; zero when ``noise`` carries it.
    noise : (..., 2L+1, m) array, optional
        Measurement-noise parts of augmented points: point ``i`` measures ``h(X_i) + V_i``.

    Raises
    ------
    numpy.linalg.LinAlgError
        If the innovation covariance is not positive definite.
    """
    n = x.shape[-1]
    flat = points.reshape(-1, n)
    nu = model.residual(record, model.predict(record, flat)).reshape(points.shape[:-1] + (record.size,))
    if noise is not None:
        nu = nu - noise
    nu_mean, nu_spread = sigma_moments(nu, weights)
    _, x_spread = sigma_moments(points, weights)
    S = symmetrized(cross_covariance(nu_spread, nu_spread, weights) + R)
    Pxz = -cross_covariance(x_spread, nu_spread, weights)
    np.linalg.cholesky(S)  # raises LinAlgError for a non-PD innovation covariance
    # one solve gives the gain (K^T = S^-1 Pxz^T) and S^-1 nu; m is small, so LU beats
    # triangular solves whose per-call overhead dominated the update
    solved = np.linalg.solve(S, np.concatenate([np.swapaxes(Pxz, -1, -2), nu_mean[..., None]], axis=-1))
    gain = np.swapaxes(solved[..., :-1], -1, -2)
    nis = np.einsum("...i,...i->...", nu_mean, solved[..., -1])
    x_post = x + np.einsum("...ij,...j->...i", gain, nu_mean)
    P_post = symmetrized(P - gain @ S @ np.swapaxes(gain, -1, -2))
    return Innovation(x_post, P_post, nu_mean, S, nis)


def innovation_outcome(
    prior: Estimate, record: Measurement, innovation: Innovation, *, gate_probability: float | None
) -> UpdateOutcome:
    """Gate one unscented update and package it; a refusal keeps ``prior``.

    The record is refused if its NIS fails the chi-square gate
    (:func:`opnav.filters.base.gate_refusal`) or the posterior covariance is not
    finite SPD; otherwise the posterior is dated ``record.t_tdb_s``.
    """
    nis = float(innovation.nis)
    refusal = gate_refusal(prior, record, residual=innovation.residual, residual_cov=innovation.S, nis=nis,
                           probability=gate_probability)
    if refusal is not None:
        return refusal
    try:
        P = check_covariance(innovation.P, "posterior covariance")
    except CovarianceError as exc:
        return refused(prior, record, str(exc), residual=innovation.residual, residual_cov=innovation.S, nis=nis)
    return UpdateOutcome(Estimate(record.t_tdb_s, innovation.x, P), innovation.residual, innovation.S, nis, True)


def ukf_predict_estimate(
    estimate: Estimate,
    t_tdb_s: float,
    *,
    transition: Transition,
    process_noise: ProcessNoise | None,
    weights: SigmaWeights,
) -> Estimate:
    """Move ``estimate`` to ``t_tdb_s`` (TDB s past J2000) with the additive-noise unscented time update.

    Parameters
    ----------
    estimate : Estimate
        State and covariance at the current epoch.
    t_tdb_s : float
        Target epoch; at the current epoch ``estimate`` is returned unchanged.
    transition : Transition
        Called once with all ``2n+1`` points.
    process_noise : ProcessNoise or None
        :mod:`opnav.filters.noise` model for the first six states, evaluated at ``estimate.x``.
    weights : SigmaWeights
        ``sigma_weights(n, options)`` for the state size ``n``.

    Raises
    ------
    InputError
        If ``t_tdb_s`` is not finite or lies before the estimate's epoch.
    numpy.linalg.LinAlgError
        If ``estimate.P`` is not positive definite.
    """
    check_epoch(estimate.t_tdb_s, t_tdb_s)
    if not t_tdb_s > estimate.t_tdb_s:
        return estimate
    Q = discrete_noise(process_noise, estimate.t_tdb_s, t_tdb_s, estimate.x)
    x, P, _ = ukf_predict(estimate.x, estimate.P, estimate.t_tdb_s, t_tdb_s, transition=transition, Q=Q,
                          weights=weights)
    return Estimate(float(t_tdb_s), x, P)


def ukf_update_estimate(
    estimate: Estimate,
    record: Measurement,
    *,
    model: MeasurementModel,
    weights: SigmaWeights,
    options: UKFOptions,
) -> UpdateOutcome:
    """Fold ``record`` (at the estimate's epoch) into ``estimate``; refusals keep the prior.

    Parameters
    ----------
    estimate : Estimate
        Prior at ``record.t_tdb_s`` (predict first).
    record : Measurement
    model : MeasurementModel
        Vectorised measurement model.
    weights : SigmaWeights
    options : UKFOptions
        Only ``gate_probability`` is used here; the weights carry the rest.

    Returns
    -------
    UpdateOutcome
        Posterior (or prior), mean innovation (m,), its covariance ``S`` (m, m), NIS,
        accepted flag and reason. Refused: bad record values, an epoch other than the
        estimate's, non-PD ``S`` or posterior, or the chi-square gate.
    """
    refusal = screen_record(estimate, record)
    if refusal is not None:
        return refusal
    try:
        post = ukf_update(estimate.x, estimate.P, record, model=model, weights=weights)
    except np.linalg.LinAlgError:
        return rejected(estimate, record.size, "innovation covariance is not positive definite", record)
    return innovation_outcome(estimate, record, post, gate_probability=options.gate_probability)


class UnscentedKalmanFilter(GaussianFilter):
    """Additive-noise UKF (process noise added to the predicted covariance, ``R`` to ``S``).

    Holds the models and the current estimate; the work is done by
    :func:`ukf_predict_estimate` and :func:`ukf_update_estimate`.

    Parameters
    ----------
    estimate : Estimate
        Initial state and covariance (state units; frame/origin of ``transition``).
    transition : Transition
        ``transition(t0, X (K, n), t1) -> (K, n)``; called once per prediction with all points.
    process_noise : ProcessNoise or None
        :mod:`opnav.filters.noise` model (``discrete(dt_s, x)``) for the first six states.
    model : MeasurementModel
        Vectorised measurement model.
    options : UKFOptions
    """

    def __init__(
        self,
        estimate: Estimate,
        *,
        transition: Transition,
        process_noise: ProcessNoise | None,
        model: MeasurementModel,
        options: UKFOptions = UKFOptions(),
    ) -> None:
        self.transition = transition
        self.process_noise = process_noise
        self.model = model
        self.options = options
        self.reset(estimate)
        self.weights = sigma_weights(self._estimate.x.size, options)

    def update(self, record: Measurement) -> UpdateOutcome:
        """Predict to the record's epoch and fold it in (or refuse it with a logged reason).

        RA/Dec records with the default models (fast propagation, white ephemeris error) take one
        compiled step (:mod:`opnav.filters.compiled`); the rest, and every record that step does not
        accept, go through :func:`ukf_predict_estimate` and :func:`ukf_update_estimate`.
        """
        steps = self._compiled_steps()
        if steps is not None:
            outcome = steps.ukf(self._estimate, record, process_noise=self.process_noise, weights=self.weights,
                                gate_probability=self.options.gate_probability)
            if outcome is not None:
                self._estimate = outcome.estimate
                return outcome
        return super().update(record)

    def _compiled_steps(self):
        """The :class:`~opnav.filters.compiled.RadecSteps` of the current models, or None (always for
        subclasses that change the steps, such as the square-root form)."""
        from .compiled import filter_steps

        return filter_steps(self, UnscentedKalmanFilter, self.transition, self.model)

    def _predict(self, estimate: Estimate, t_tdb_s: float) -> Estimate:
        return ukf_predict_estimate(estimate, t_tdb_s, transition=self.transition, process_noise=self.process_noise,
                                    weights=self.weights)

    def _update(self, prior: Estimate, record: Measurement) -> UpdateOutcome:
        return ukf_update_estimate(prior, record, model=self.model, weights=self.weights, options=self.options)
