"""Unscented Kalman filters: additive-noise, square-root and augmented (S3) forms.

Algorithm (scaled unscented transform, van der Merwe 2004, ch. 3):

1. Sigma points ``X_0 = x``, ``X_i = x +/- gamma * S[:, i]`` with ``S S^T = P``
   (lower Cholesky factor), ``gamma = sqrt(n + lambda)``,
   ``lambda = alpha^2 (n + kappa) - n``; weights from filterpy's
   :class:`~filterpy.kalman.MerweScaledSigmaPoints`.
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
:func:`_cross`) because with ``alpha = 1e-3`` the central weight is about
-1e6: summing raw heliocentric positions (1e8 km) with such weights would lose
metres to cancellation.

The square-root form (van der Merwe & Wan 2001) carries the Cholesky factor
through QR decompositions and rank-one updates, so the covariance stays
positive definite over long arcs. The augmented form (Wan & van der Merwe
2000, Algorithm 3.1; used by S3) draws one set of ``2L+1`` points over
state, process noise and measurement noise (``L = n + q + m``) and carries it
through both the dynamics and the measurement model.

Vectors: states are ``[r (km), v (km/s)]``, ICRF, relative to the central body
of whatever ``transition`` integrates (see :mod:`opnav.filters.base`); other
state sizes work the same way.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints
from scipy import linalg

from ..errors import CovarianceError, InputError
from ..records import Measurement
from .base import (
    Estimate,
    MeasurementModel,
    UpdateOutcome,
    check_covariance,
    check_estimate,
    chi2_gate,
    record_problem,
    rejected,
)
from .ekf import measurement_covariance
from .noise import ProcessNoise

log = logging.getLogger(__name__)

#: ``transition(t0_tdb_s, X (K, n), t1_tdb_s) -> (K, n)``: states moved from t0 to t1.
Transition = Callable[[float, np.ndarray, float], np.ndarray]
#: ``noisy_transition(t0, X (K, n), W (K, q), t1) -> (K, n)`` for the augmented filter.
NoisyTransition = Callable[[float, np.ndarray, np.ndarray, float], np.ndarray]


@dataclass(frozen=True)
class UKFOptions:
    """Scaled-sigma-point parameters and gating of the unscented filters.

    Attributes
    ----------
    alpha : float
        Spread of the points, 0 < alpha <= 1. The default 1 puts them at
        ``sqrt(n + kappa)`` sigma with non-negative weights. Van der Merwe's
        1e-3 makes the weights ~1/(alpha^2 n) ~ 1e5, which multiplies every
        per-point error: a DOP853 propagation at rtol 1e-11 is off by ~2 m at
        1.5 au, and the S1 mean then jitters by tens to hundreds of km
        (``benchmarks/filters.py``).
    beta : float
        Prior-knowledge weight on the central point (2 is optimal for Gaussians).
    kappa : float
        Secondary scaling; ``n + kappa`` must be positive.
    gate_probability : float or None
        Reject a record whose NIS exceeds this chi-square quantile; ``None`` disables gating.
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0
    gate_probability: float | None = None

    def __post_init__(self) -> None:
        if not (np.isfinite(self.alpha) and 0.0 < self.alpha <= 1.0):
            raise InputError(f"UKFOptions.alpha must be in (0, 1], got {self.alpha}")
        if not (np.isfinite(self.beta) and self.beta >= 0.0):
            raise InputError(f"UKFOptions.beta must be >= 0, got {self.beta}")
        if not np.isfinite(self.kappa):
            raise InputError(f"UKFOptions.kappa must be finite, got {self.kappa}")
        if self.gate_probability is not None and not 0.0 < self.gate_probability < 1.0:
            raise InputError(f"UKFOptions.gate_probability must be in (0, 1), got {self.gate_probability}")


@dataclass(frozen=True)
class SigmaWeights:
    """Weights of the scaled unscented transform for dimension ``n``."""

    n: int
    gamma: float
    Wm: np.ndarray
    Wc: np.ndarray


def force_model_transition(model) -> Transition:
    """Wrap an :mod:`opnav.dynamics` force model as a :data:`Transition` for K states in ONE integration.

    States are ``[r (km), v (km/s)]`` ICRF relative to ``model.center``; entries
    beyond the first six (augmented parameters) are held constant.
    """
    from ..dynamics import propagate

    def step(t0_tdb_s: float, X: np.ndarray, t1_tdb_s: float) -> np.ndarray:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        moved = X.copy()
        moved[:, :6] = propagate(model, t0_tdb_s, X[:, :6], np.array([t1_tdb_s])).states[-1]
        return moved

    return step


def discrete_noise(process_noise: ProcessNoise | None, t0_tdb_s: float, t1_tdb_s: float, x: np.ndarray) -> np.ndarray:
    """Process-noise covariance (n, n) over ``[t0, t1]`` at state ``x`` (n,); zero beyond the first six entries."""
    n = x.shape[-1]
    Q = np.zeros((n, n))
    if process_noise is not None and t1_tdb_s != t0_tdb_s:
        Q[:6, :6] = np.asarray(process_noise.discrete(t1_tdb_s - t0_tdb_s, x[:6]), dtype=float)
    return Q


def sigma_weights(n: int, options: UKFOptions) -> SigmaWeights:
    """Mean/covariance weights (from filterpy) and the point scale ``gamma = sqrt(n + lambda)``."""
    if n + options.kappa <= 0.0:
        raise InputError(f"UKFOptions.kappa={options.kappa} makes n + kappa <= 0 for n={n}")
    points = MerweScaledSigmaPoints(n, options.alpha, options.beta, options.kappa)
    lam = options.alpha**2 * (n + options.kappa) - n
    return SigmaWeights(n, float(np.sqrt(n + lam)), points.Wm.copy(), points.Wc.copy())


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


class _Spread(NamedTuple):
    """Points relative to the central one: ``offsets`` (..., 2L, k) for i >= 1, ``shift`` = mean - X_0."""

    offsets: np.ndarray
    shift: np.ndarray


def _moments(points: np.ndarray, w: SigmaWeights) -> tuple[np.ndarray, _Spread]:
    """Weighted mean (..., k) of points (..., 2L+1, k) and their spread about the central point."""
    offsets = points[..., 1:, :] - points[..., :1, :]
    shift = np.einsum("i,...ik->...k", w.Wm[1:], offsets)
    return points[..., 0, :] + shift, _Spread(offsets, shift)


def _cross(a: _Spread, b: _Spread, w: SigmaWeights) -> np.ndarray:
    """Weighted cross-covariance ``sum_i Wc_i (A_i - a)(B_i - b)^T``.

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


def _symmetric(P: np.ndarray) -> np.ndarray:
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
    mean, spread = _moments(moved, weights)
    P1 = _cross(spread, spread, weights) + Q
    return mean, _symmetric(P1), moved[..., 0, :]


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
        else ``record.covariance`` (:func:`opnav.filters.ekf.measurement_covariance`).
    model : MeasurementModel
        Vectorised predictor ``predict(record, X (K, n)) -> (K, m)``.

    Notes
    -----
    Innovations of the individual points are ``nu_i = residual(z, h(X_i))`` so
    angle wrapping is the model's business, and
    ``S = sum Wc (nu_i - nu)(nu_i - nu)^T + R``,
    ``Pxz = sum Wc (X_i - x)(h_i - z_hat)^T = -sum Wc (X_i - x)(nu_i - nu)^T``.
    """
    points = sigma_points(x, np.linalg.cholesky(P), weights.gamma)
    R = measurement_covariance(model, record, np.reshape(x, (-1, x.shape[-1]))[0])
    return _innovate(x, P, points, record, model, weights, R, np.zeros(0))


def _innovate(
    x: np.ndarray,
    P: np.ndarray,
    points: np.ndarray,
    record: Measurement,
    model: MeasurementModel,
    weights: SigmaWeights,
    R: np.ndarray,
    noise: np.ndarray,
) -> Innovation:
    """Kalman update from state points ``(..., 2L+1, n)``; ``noise`` adds measurement-noise points (augmented form)."""
    n = x.shape[-1]
    flat = points.reshape(-1, n)
    nu = model.residual(record, model.predict(record, flat)).reshape(points.shape[:-1] + (record.size,))
    if noise.size:
        nu = nu - noise
    nu_mean, nu_spread = _moments(nu, weights)
    _, x_spread = _moments(points, weights)
    S = _symmetric(_cross(nu_spread, nu_spread, weights) + R)
    Pxz = -_cross(x_spread, nu_spread, weights)
    np.linalg.cholesky(S)  # raises LinAlgError for a non-PD innovation covariance
    # one solve gives the gain (K^T = S^-1 Pxz^T) and S^-1 nu; m is small, so LU beats
    # triangular solves whose per-call overhead dominated the update
    solved = np.linalg.solve(S, np.concatenate([np.swapaxes(Pxz, -1, -2), nu_mean[..., None]], axis=-1))
    gain = np.swapaxes(solved[..., :-1], -1, -2)
    nis = np.einsum("...i,...i->...", nu_mean, solved[..., -1])
    x_post = x + np.einsum("...ij,...j->...i", gain, nu_mean)
    P_post = _symmetric(P - gain @ S @ np.swapaxes(gain, -1, -2))
    return Innovation(x_post, P_post, nu_mean, S, nis)


def cholupdate(L: np.ndarray, v: np.ndarray, sign: float) -> np.ndarray:
    """Rank-one update of a lower Cholesky factor: returns ``L'`` with ``L' L'^T = L L^T + sign v v^T``.

    Raises
    ------
    CovarianceError
        If a downdate (``sign < 0``) would leave the matrix not positive definite.
    """
    L = np.array(L, dtype=float)
    v = np.array(v, dtype=float)
    n = L.shape[0]
    for k in range(n):
        r2 = L[k, k] ** 2 + sign * v[k] ** 2
        if not r2 > 0.0:
            raise CovarianceError("Cholesky downdate lost positive definiteness (square-root UKF covariance)")
        r = np.sqrt(r2)
        c = r / L[k, k]
        s = v[k] / L[k, k]
        L[k, k] = r
        L[k + 1 :, k] = (L[k + 1 :, k] + sign * s * v[k + 1 :]) / c
        v[k + 1 :] = c * v[k + 1 :] - s * L[k + 1 :, k]
    return L


def _qr_factor(columns: np.ndarray) -> np.ndarray:
    """Lower-triangular ``S`` with ``S S^T = columns @ columns.T`` (QR of the transpose)."""
    R = linalg.qr(columns.T, mode="r")[0][: columns.shape[0]]
    R = R * np.where(np.diag(R) < 0.0, -1.0, 1.0)[:, None]
    return R.T


def _psd_sqrt(Q: np.ndarray, name: str) -> np.ndarray:
    """A square root ``A`` with ``A A^T = Q`` for a symmetric positive semi-definite ``Q``."""
    values, vectors = np.linalg.eigh(_symmetric(Q))
    if np.any(values < -1e-12 * max(1.0, float(np.max(np.abs(values))))):
        raise CovarianceError(f"{name} is not positive semi-definite")
    return vectors * np.sqrt(np.clip(values, 0.0, None))


class _UnscentedBase:
    """State keeping, record checks and gating shared by the unscented filters."""

    def __init__(
        self,
        estimate: Estimate,
        *,
        transition: Transition | NoisyTransition,
        process_noise: ProcessNoise | None,
        model: MeasurementModel,
        options: UKFOptions = UKFOptions(),
    ) -> None:
        self.transition = transition
        self.process_noise = process_noise
        self.model = model
        self.options = options
        self.reset(estimate)
        self._init_weights()

    def _init_weights(self) -> None:
        self.weights = sigma_weights(self._estimate.x.size, self.options)

    @property
    def estimate(self) -> Estimate:
        return self._estimate

    def reset(self, estimate: Estimate) -> None:
        """Replace the current estimate (used by the federated filter after fusion)."""
        self._estimate = check_estimate(estimate)

    def _check_epoch(self, t_tdb_s: float) -> None:
        if not np.isfinite(t_tdb_s):
            raise InputError("predict epoch t_tdb_s is not finite")
        if t_tdb_s < self._estimate.t_tdb_s - 1e-9:
            raise InputError(
                f"cannot predict backwards: t_tdb_s={t_tdb_s:.3f} is before the filter epoch {self._estimate.t_tdb_s:.3f}"
            )

    def _finish(self, record: Measurement, prior: Estimate, post: Innovation | None, reason: str) -> UpdateOutcome:
        """Gate and package an update; keeps ``prior`` when the record is refused."""
        if post is None:
            return rejected(prior, record.size, reason, record)
        nis = float(post.nis)
        if self.options.gate_probability is not None and not chi2_gate(nis, record.size, self.options.gate_probability):
            reason = f"chi-square gate: NIS {nis:.3g} above the {self.options.gate_probability} quantile of chi2({record.size})"
            log.warning("rejected %s measurement at t=%.3f s (%s): %s", record.kind, record.t_tdb_s, record.sensor or "-", reason)
            return UpdateOutcome(prior, post.residual, post.S, nis, False, reason)
        try:
            P = check_covariance(post.P, "posterior covariance")
        except CovarianceError as exc:
            log.warning("rejected %s measurement at t=%.3f s: %s", record.kind, record.t_tdb_s, exc)
            return UpdateOutcome(prior, post.residual, post.S, nis, False, str(exc))
        self._accept(Estimate(record.t_tdb_s, post.x, P))
        return UpdateOutcome(self._estimate, post.residual, post.S, nis, True)

    def _accept(self, estimate: Estimate) -> None:
        self._estimate = estimate


class UnscentedKalmanFilter(_UnscentedBase):
    """Additive-noise UKF (process noise added to the predicted covariance, ``R`` to ``S``).

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

    def predict(self, t_tdb_s: float) -> Estimate:
        """Move the estimate to ``t_tdb_s`` (TDB s past J2000); a no-op at the current epoch."""
        self._check_epoch(t_tdb_s)
        e = self._estimate
        if t_tdb_s > e.t_tdb_s:
            Q = discrete_noise(self.process_noise, e.t_tdb_s, t_tdb_s, e.x)
            x, P, _ = ukf_predict(e.x, e.P, e.t_tdb_s, t_tdb_s, transition=self.transition, Q=Q, weights=self.weights)
            self._estimate = Estimate(float(t_tdb_s), x, P)
        return self._estimate

    def update(self, record: Measurement) -> UpdateOutcome:
        """Predict to the record's epoch if needed, then fold it in."""
        reason = record_problem(record, self._estimate.t_tdb_s)
        if reason is not None:
            return self._finish(record, self._estimate, None, reason)
        prior = self.predict(record.t_tdb_s)
        try:
            post = ukf_update(prior.x, prior.P, record, model=self.model, weights=self.weights)
        except np.linalg.LinAlgError:
            return self._finish(record, prior, None, "innovation covariance is not positive definite")
        return self._finish(record, prior, post, "")


class SquareRootUKF(_UnscentedBase):
    """Square-root UKF (van der Merwe & Wan 2001): carries ``S`` with ``S S^T = P``.

    Same parameters and results as :class:`UnscentedKalmanFilter` (to rounding);
    the factor is propagated by QR decompositions and rank-one Cholesky
    updates, never by forming and factoring ``P``, so ``P`` stays symmetric
    positive definite over long arcs.

    Notes
    -----
    Time update: ``S^- = qr([sqrt(Wc_i) (X_i - X_0)]_{i>0}, sqrt(Q)])`` then a rank-one
    update with ``sqrt(beta - alpha^2) (x - X_0)`` (the form of :func:`_cross`,
    which replaces van der Merwe's downdate by ``Wc_0 (X_0 - x)`` — a weight of
    about -1e6 at ``alpha = 1e-3`` — by an update with weight ``beta - alpha^2``).
    Measurement update: ``S_z`` likewise from the innovations and ``sqrt(R)``,
    ``K = Pxz S_z^-T S_z^-1``, then ``S^+ = cholupdate(S^-, K S_z[:, j], -1)`` for each column j.
    """

    def reset(self, estimate: Estimate) -> None:
        super().reset(estimate)
        self._S = np.linalg.cholesky(self._estimate.P)

    def _factor(self, spread: _Spread, extra_sqrt: np.ndarray) -> np.ndarray:
        """Square root of ``_cross(spread, spread) + extra_sqrt extra_sqrt^T`` (QR, then a rank-one fix)."""
        Wc = self.weights.Wc
        c = float(np.sum(Wc)) - 2.0
        columns = np.concatenate([np.sqrt(Wc[1:])[:, None] * spread.offsets, extra_sqrt.T], axis=0).T
        if c == 0.0:
            return _qr_factor(columns)
        return cholupdate(_qr_factor(columns), np.sqrt(abs(c)) * spread.shift, float(np.sign(c)))

    def predict(self, t_tdb_s: float) -> Estimate:
        """Move the estimate and its square root to ``t_tdb_s``."""
        self._check_epoch(t_tdb_s)
        e = self._estimate
        if t_tdb_s > e.t_tdb_s:
            points = sigma_points(e.x, self._S, self.weights.gamma)
            moved = np.asarray(self.transition(e.t_tdb_s, points, t_tdb_s), dtype=float).reshape(points.shape)
            mean, spread = _moments(moved, self.weights)
            Q = discrete_noise(self.process_noise, e.t_tdb_s, t_tdb_s, e.x)
            self._S = self._factor(spread, _psd_sqrt(Q, "process noise Q"))
            self._estimate = Estimate(float(t_tdb_s), mean, self._S @ self._S.T)
        return self._estimate

    def update(self, record: Measurement) -> UpdateOutcome:
        """Predict to the record's epoch if needed, then fold it in through the square roots."""
        reason = record_problem(record, self._estimate.t_tdb_s)
        if reason is not None:
            return rejected(self._estimate, record.size, reason, record)
        prior = self.predict(record.t_tdb_s)
        points = sigma_points(prior.x, self._S, self.weights.gamma)
        nu = self.model.residual(record, self.model.predict(record, points))
        nu_mean, nu_spread = _moments(nu, self.weights)
        _, x_spread = _moments(points, self.weights)
        try:
            Sz = self._factor(nu_spread, np.linalg.cholesky(measurement_covariance(self.model, record, prior.x)))
        except CovarianceError:
            return rejected(prior, record.size, "innovation covariance is not positive definite", record)
        Pxz = -_cross(x_spread, nu_spread, self.weights)
        # K = Pxz Sz^-T Sz^-1 and the whitened innovation, both from the triangular factor
        half = np.linalg.solve(Sz, np.concatenate([Pxz.T, nu_mean[:, None]], axis=1))
        gain = np.linalg.solve(Sz.T, half[:, :-1]).T
        nis = float(half[:, -1] @ half[:, -1])
        S_cov = Sz @ Sz.T
        if self.options.gate_probability is not None and not chi2_gate(nis, record.size, self.options.gate_probability):
            reason = f"chi-square gate: NIS {nis:.3g} above the {self.options.gate_probability} quantile of chi2({record.size})"
            log.warning("rejected %s measurement at t=%.3f s (%s): %s", record.kind, record.t_tdb_s, record.sensor or "-", reason)
            return UpdateOutcome(prior, nu_mean, S_cov, nis, False, reason)
        S_post = self._S
        try:
            for column in (gain @ Sz).T:
                S_post = cholupdate(S_post, column, -1.0)
        except CovarianceError as exc:
            log.warning("rejected %s measurement at t=%.3f s: %s", record.kind, record.t_tdb_s, exc)
            return UpdateOutcome(prior, nu_mean, S_cov, nis, False, str(exc))
        self._S = S_post
        self._estimate = Estimate(record.t_tdb_s, prior.x + gain @ nu_mean, S_post @ S_post.T)
        return UpdateOutcome(self._estimate, nu_mean, S_cov, nis, True)


def additive_noise(transition: Transition) -> NoisyTransition:
    """Wrap a transition so process noise enters additively after it: ``f(X) + W`` (W is (K, n))."""

    def noisy(t0_tdb_s: float, X: np.ndarray, W: np.ndarray, t1_tdb_s: float) -> np.ndarray:
        return np.asarray(transition(t0_tdb_s, X, t1_tdb_s), dtype=float) + W

    return noisy


class AugmentedUKF(_UnscentedBase):
    """Augmented UKF of S3: one sigma set over state, process noise and measurement noise.

    Parameters
    ----------
    estimate : Estimate
        Initial state and covariance.
    transition : NoisyTransition
        ``f(t0, X (K, n), W (K, n), t1) -> (K, n)`` with noise samples ``W``;
        :func:`additive_noise` builds one from an ordinary transition.
    process_noise : ProcessNoise or None
        :mod:`opnav.filters.noise` model; ``W`` has its covariance
        :func:`discrete_noise` (zero outside the first six entries, which is
        allowed: the augmented square root is built block by block).
    model : MeasurementModel
    options : UKFOptions

    Notes
    -----
    Wan & van der Merwe (2000), Algorithm 3.1: from the last posterior
    ``(x, P)`` at ``t0`` the augmented mean ``[x, 0_q, 0_m]`` and covariance
    ``blkdiag(P, Q, R)`` (``L = n + q + m``) give ``2L+1`` points; their state
    parts go through ``f`` with their process-noise parts, and the
    measurement of each point is ``h(X_i) + V_i`` (innovation
    ``residual(z, h(X_i)) - V_i``), so neither ``Q`` nor ``R`` is added
    afterwards. ``predict(t)`` reports the prediction from a ``[x, w]`` set
    (the record's size ``m`` is not known yet); the next ``update`` at ``t``
    redraws the joint set from the last posterior, so each measured step uses
    exactly one ``2L+1`` set. Further records at the same epoch use ``[x, v]`` sets.
    """

    def _init_weights(self) -> None:
        # one weight set per joint dimension L = n + n_noise + m, made on first use
        self._weights: dict[int, SigmaWeights] = {}

    def reset(self, estimate: Estimate) -> None:
        super().reset(estimate)
        self._posterior = self._estimate

    def _accept(self, estimate: Estimate) -> None:
        self._estimate = estimate
        self._posterior = estimate

    def _w(self, L: int) -> SigmaWeights:
        if L not in self._weights:
            self._weights[L] = sigma_weights(L, self.options)
        return self._weights[L]

    def _augmented_points(self, roots: list[np.ndarray]) -> tuple[np.ndarray, SigmaWeights]:
        """Sigma points of ``[x, 0, ...]`` with square root ``blkdiag(chol(P), *roots)``."""
        base = self._posterior
        S_a = linalg.block_diag(np.linalg.cholesky(base.P), *roots)
        x_a = np.concatenate([base.x, np.zeros(S_a.shape[0] - base.x.size)])
        w = self._w(x_a.size)
        return sigma_points(x_a, S_a, w.gamma), w

    def _propagate(self, points: np.ndarray, t1_tdb_s: float, q: int) -> np.ndarray:
        n = self._posterior.x.size
        t0 = self._posterior.t_tdb_s
        return np.asarray(self.transition(t0, points[:, :n], points[:, n : n + q], t1_tdb_s), dtype=float)

    def _noise_root(self, t1_tdb_s: float) -> np.ndarray:
        base = self._posterior
        return _psd_sqrt(discrete_noise(self.process_noise, base.t_tdb_s, t1_tdb_s, base.x), "process noise Q")

    def predict(self, t_tdb_s: float) -> Estimate:
        """Predicted estimate at ``t_tdb_s`` from the last posterior (``[x, w]`` sigma set)."""
        self._check_epoch(t_tdb_s)
        if t_tdb_s > self._posterior.t_tdb_s:
            root = self._noise_root(t_tdb_s)
            points, w = self._augmented_points([root])
            mean, spread = _moments(self._propagate(points, t_tdb_s, root.shape[0]), w)
            self._estimate = Estimate(float(t_tdb_s), mean, _symmetric(_cross(spread, spread, w)))
        return self._estimate

    def update(self, record: Measurement) -> UpdateOutcome:
        """Fold in one record with a joint sigma set drawn from the last posterior."""
        reason = record_problem(record, self._estimate.t_tdb_s)
        if reason is not None:
            return rejected(self._estimate, record.size, reason, record)
        prior = self.predict(record.t_tdb_s)
        n = prior.x.size
        m = record.size
        if record.t_tdb_s > self._posterior.t_tdb_s:
            root = self._noise_root(record.t_tdb_s)
            q = root.shape[0]
            points, w = self._augmented_points([root, np.linalg.cholesky(measurement_covariance(self.model, record, prior.x))])
            state_points = self._propagate(points, record.t_tdb_s, q)
        else:
            q = 0
            points, w = self._augmented_points([np.linalg.cholesky(measurement_covariance(self.model, record, prior.x))])
            state_points = points[:, :n]
        mean, spread = _moments(state_points, w)
        P_prior = _symmetric(_cross(spread, spread, w))
        try:
            post = _innovate(mean, P_prior, state_points, record, self.model, w, np.zeros((m, m)),
                             points[:, n + q : n + q + m])
        except np.linalg.LinAlgError:
            return rejected(prior, m, "innovation covariance is not positive definite", record)
        return self._finish(record, Estimate(record.t_tdb_s, mean, P_prior), post, "")
