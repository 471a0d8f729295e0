"""Square-root unscented Kalman filter (van der Merwe & Wan 2001).

Same sigma points, weights and results (to rounding) as the additive UKF of
:mod:`opnav.filters.ukf`, but the state carries the lower Cholesky factor
``S`` (``S S^T = P``), a :class:`SqrtEstimate`, and ``P`` is never factored
again, so it stays symmetric positive definite over long arcs. Per step:

1. Time update: sigma points from ``(x, S)`` through the transition in one
   call; ``S^- = qr([sqrt(Wc_i) (X_i - X_0)]_{i>0}, sqrt(Q)])`` (:func:`qr_factor`)
   then a rank-one update with ``sqrt(beta - alpha^2) (x - X_0)``. This is
   the form of :func:`opnav.filters.ukf.cross_covariance`, which replaces van
   der Merwe's downdate by ``Wc_0 (X_0 - x)`` (a weight of about -1e6 at
   ``alpha = 1e-3``) by an update with weight ``beta - alpha^2``.
2. Measurement update: ``S_z`` likewise from the innovations and ``sqrt(R)``;
   ``K = Pxz S_z^-T S_z^-1`` and the whitened innovation come from triangular
   solves; the NIS is gated (:func:`opnav.filters.base.gate_refusal`).
3. ``S^+ = cholupdate(S^-, K S_z[:, j], -1)`` for each column ``j``
   (:func:`cholupdate`); a downdate that loses positive definiteness refuses
   the record.

:func:`sr_ukf_predict` and :func:`sr_ukf_update` are the pure core;
:class:`SquareRootUKF` only holds the models and the current :class:`SqrtEstimate`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import linalg

from ..compiled import kernel
from ..errors import CovarianceError
from ..records import Measurement
from .base import (
    Estimate,
    MeasurementModel,
    UpdateOutcome,
    check_epoch,
    check_estimate,
    discrete_noise,
    gate_refusal,
    measurement_covariance,
    psd_sqrt,
    refused,
    rejected,
    screen_record,
)
from .noise import ProcessNoise
from .ukf import (
    SigmaSpread,
    SigmaWeights,
    Transition,
    UKFOptions,
    cross_covariance,
    sigma_moments,
    sigma_points,
    UnscentedKalmanFilter,
)


@dataclass(frozen=True)
class SqrtEstimate(Estimate):
    """An :class:`~opnav.filters.base.Estimate` that carries the square root of its covariance.

    Built from ``(t_tdb_s, x, S)``; ``P = S S^T`` is formed once, on construction,
    so the pair cannot disagree.

    Attributes
    ----------
    t_tdb_s : float
        TDB seconds past J2000.
    x : (n,) array
        State (units and frame as in :class:`~opnav.filters.base.Estimate`).
    S : (n, n) array
        Lower-triangular factor with ``S S^T = P``.
    P : (n, n) array
        Covariance ``S S^T`` (not an argument).
    """

    P: np.ndarray = field(init=False, repr=False)
    S: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "P", self.S @ self.S.T)


def as_sqrt(estimate: Estimate) -> SqrtEstimate:
    """``estimate`` itself if it is a :class:`SqrtEstimate`, else one with the Cholesky factor of its ``P``.

    Raises
    ------
    numpy.linalg.LinAlgError
        If ``estimate.P`` is not positive definite.
    """
    if isinstance(estimate, SqrtEstimate):
        return estimate
    return SqrtEstimate(estimate.t_tdb_s, estimate.x, np.linalg.cholesky(estimate.P))


def cholupdate(L: np.ndarray, v: np.ndarray, sign: float) -> np.ndarray:
    """Rank-one update of a lower Cholesky factor: returns ``L'`` with ``L' L'^T = L L^T + sign v v^T``.

    Raises
    ------
    CovarianceError
        If a downdate (``sign < 0``) would leave the matrix not positive definite.
    """
    L = np.array(L, dtype=float)
    v = np.array(v, dtype=float)
    if not _cholupdate(L, v, float(sign)):
        raise CovarianceError("Cholesky downdate lost positive definiteness (square-root UKF covariance)")
    return L


@kernel
def _cholupdate(L, v, sign):
    """In-place rank-one update of ``L`` by ``sign v v^T`` (``v`` is overwritten); False if it breaks down.

    Compiled: the column loop of small numpy slices cost ~30 us a call in Python, and the
    square-root UKF makes several per record.
    """
    n = L.shape[0]
    for k in range(n):
        r2 = L[k, k] ** 2 + sign * v[k] ** 2
        if not r2 > 0.0:
            return False
        r = np.sqrt(r2)
        c = r / L[k, k]
        s = v[k] / L[k, k]
        L[k, k] = r
        for i in range(k + 1, n):
            L[i, k] = (L[i, k] + sign * s * v[i]) / c
            v[i] = c * v[i] - s * L[i, k]
    return True


def qr_factor(columns: np.ndarray) -> np.ndarray:
    """Lower-triangular ``S`` (k, k) with ``S S^T = columns @ columns.T`` for ``columns`` (k, p), p >= k.

    From the QR decomposition of ``columns.T``, with the signs of ``R``'s rows made positive.
    """
    R = linalg.qr(columns.T, mode="r")[0][: columns.shape[0]]
    R = R * np.where(np.diag(R) < 0.0, -1.0, 1.0)[:, None]
    return R.T


def spread_factor(spread: SigmaSpread, extra_sqrt: np.ndarray, weights: SigmaWeights) -> np.ndarray:
    """Square root of ``cross_covariance(spread, spread) + extra_sqrt extra_sqrt^T`` (QR, then a rank-one fix).

    Parameters
    ----------
    spread : SigmaSpread
        Points (2L+1, k) about their central point.
    extra_sqrt : (k, p) array
        Square root of the additive noise (``Q`` or ``R``).
    weights : SigmaWeights

    Raises
    ------
    CovarianceError
        If the rank-one correction is a downdate (``beta < alpha^2``) that loses positive definiteness.
    """
    Wc = weights.Wc
    c = float(np.sum(Wc)) - 2.0
    columns = np.concatenate([np.sqrt(Wc[1:])[:, None] * spread.offsets, extra_sqrt.T], axis=0).T
    if c == 0.0:
        return qr_factor(columns)
    return cholupdate(qr_factor(columns), np.sqrt(abs(c)) * spread.shift, float(np.sign(c)))


def sr_ukf_predict(
    estimate: Estimate,
    t_tdb_s: float,
    *,
    transition: Transition,
    process_noise: ProcessNoise | None,
    weights: SigmaWeights,
) -> SqrtEstimate:
    """Move ``estimate`` and its square root to ``t_tdb_s`` (TDB s past J2000).

    Parameters
    ----------
    estimate : Estimate
        A :class:`SqrtEstimate`, or an estimate whose ``P`` is factored first (:func:`as_sqrt`).
    t_tdb_s : float
        Target epoch; at the current epoch the (square-root) estimate is returned unchanged.
    transition : Transition
        Called once with all ``2n+1`` points.
    process_noise : ProcessNoise or None
        :mod:`opnav.filters.noise` model for the first six states, evaluated at ``estimate.x``.
    weights : SigmaWeights

    Raises
    ------
    InputError
        If ``t_tdb_s`` is not finite or lies before the estimate's epoch.
    CovarianceError
        If the process noise is not positive semi-definite.
    """
    check_epoch(estimate.t_tdb_s, t_tdb_s)
    e = as_sqrt(estimate)
    if not t_tdb_s > e.t_tdb_s:
        return e
    points = sigma_points(e.x, e.S, weights.gamma)
    moved = np.asarray(transition(e.t_tdb_s, points, t_tdb_s), dtype=float).reshape(points.shape)
    mean, spread = sigma_moments(moved, weights)
    Q = discrete_noise(process_noise, e.t_tdb_s, t_tdb_s, e.x)
    return SqrtEstimate(float(t_tdb_s), mean, spread_factor(spread, psd_sqrt(Q, "process noise Q"), weights))


def sr_ukf_update(
    estimate: Estimate,
    record: Measurement,
    *,
    model: MeasurementModel,
    weights: SigmaWeights,
    options: UKFOptions,
) -> UpdateOutcome:
    """Fold ``record`` (at the estimate's epoch) into ``estimate`` through the square roots.

    Parameters
    ----------
    estimate : Estimate
        Prior at ``record.t_tdb_s``; a :class:`SqrtEstimate`, or factored first (:func:`as_sqrt`).
    record : Measurement
    model : MeasurementModel
        Vectorised measurement model.
    weights : SigmaWeights
    options : UKFOptions
        Only ``gate_probability`` is used here.

    Returns
    -------
    UpdateOutcome
        Its ``estimate`` is a :class:`SqrtEstimate`: the posterior, or the prior when the
        record is refused (bad values, another epoch, non-PD innovation covariance,
        chi-square gate, or a downdate that loses positive definiteness).
    """
    prior = as_sqrt(estimate)
    refusal = screen_record(prior, record)
    if refusal is not None:
        return refusal
    points = sigma_points(prior.x, prior.S, weights.gamma)
    nu = model.residual(record, model.predict(record, points))
    nu_mean, nu_spread = sigma_moments(nu, weights)
    _, x_spread = sigma_moments(points, weights)
    try:
        Sz = spread_factor(nu_spread, np.linalg.cholesky(measurement_covariance(model, record, prior.x)), weights)
    except CovarianceError:
        return rejected(prior, record.size, "innovation covariance is not positive definite", record)
    Pxz = -cross_covariance(x_spread, nu_spread, weights)
    # K = Pxz Sz^-T Sz^-1 and the whitened innovation, both from the triangular factor
    half = np.linalg.solve(Sz, np.concatenate([Pxz.T, nu_mean[:, None]], axis=1))
    gain = np.linalg.solve(Sz.T, half[:, :-1]).T
    nis = float(half[:, -1] @ half[:, -1])
    S_cov = Sz @ Sz.T
    refusal = gate_refusal(prior, record, residual=nu_mean, residual_cov=S_cov, nis=nis,
                           probability=options.gate_probability)
    if refusal is not None:
        return refusal
    S_post = prior.S
    try:
        for column in (gain @ Sz).T:
            S_post = cholupdate(S_post, column, -1.0)
    except CovarianceError as exc:
        return refused(prior, record, str(exc), residual=nu_mean, residual_cov=S_cov, nis=nis)
    return UpdateOutcome(SqrtEstimate(record.t_tdb_s, prior.x + gain @ nu_mean, S_post), nu_mean, S_cov, nis, True)


class SquareRootUKF(UnscentedKalmanFilter):
    """Square-root UKF holding its models and a :class:`SqrtEstimate`; see the module docstring.

    Same parameters and results as :class:`opnav.filters.ukf.UnscentedKalmanFilter` (to rounding).

    Parameters
    ----------
    estimate : Estimate
        Initial state and covariance (state units; frame/origin of ``transition``).
    transition : Transition
        ``transition(t0, X (K, n), t1) -> (K, n)``; called once per prediction with all points.
    process_noise : ProcessNoise or None
        :mod:`opnav.filters.noise` model for the first six states.
    model : MeasurementModel
        Vectorised measurement model.
    options : UKFOptions
    """

    def reset(self, estimate: Estimate) -> None:
        """Replace the current estimate (checked, then factored; used by the federated filter after fusion)."""
        self._estimate = as_sqrt(check_estimate(estimate))

    def _predict(self, estimate: SqrtEstimate, t_tdb_s: float) -> SqrtEstimate:
        return sr_ukf_predict(estimate, t_tdb_s, transition=self.transition, process_noise=self.process_noise,
                              weights=self.weights)

    def _update(self, prior: SqrtEstimate, record: Measurement) -> UpdateOutcome:
        return sr_ukf_update(prior, record, model=self.model, weights=self.weights, options=self.options)
