"""Extended Kalman filter: STM prediction, Joseph-form update, chi-square gating.

Algorithm, for each record (epochs TDB s past J2000; state ``[r km, v km/s]``
ICRF relative to the dynamics' central body, optionally augmented):

1. Refuse the record, with a logged reason, if its value or covariance has NaN,
   its covariance is not symmetric positive definite, or it lies before the
   filter epoch (:func:`opnav.filters.base.record_problem`).
2. Predict: integrate the state and the variational equations from the
   filter epoch to the record's (``propagator`` returns ``x(t1)`` and the state
   transition matrix ``Phi(t1, t0)``); ``P = Phi P Phi^T + Q(dt)``.
3. Innovation ``nu = z - h(x)`` (angles wrapped by the model), ``H = dh/dx``,
   ``S = H P H^T + R`` with ``R`` the record covariance plus any model term
   (target-ephemeris error); ``NIS = nu^T S^-1 nu``.
4. Gate: refuse the record if ``NIS`` exceeds the ``gate_probability`` quantile
   of chi-square(m) -- this catches 100-sigma outliers -- keeping the prior.
5. Joseph-form update ``P+ = (I - K H) P (I - K H)^T + K R K^T`` (symmetric PD
   for any gain, Bucy & Joseph 1968), then symmetrised and checked. States named
   in ``EKFOptions.consider`` get no gain (Schmidt's consider filter, Schmidt
   1966): they are never corrected, and because the Joseph form is the exact
   covariance of any gain, their uncertainty still flows into ``P`` of the rest.

:func:`ekf_predict` and :func:`ekf_update` are pure functions (the source of
truth); :class:`ExtendedKalmanFilter` only holds the models and the estimate.
With the default models -- fast propagation (:func:`force_model_propagator`),
a :class:`~opnav.measurements.ProbeMeasurementModel` on the ephemeris cache
(white ephemeris error), a 6-element state -- it takes ``radec`` and
``radec_pair`` records in one compiled step (:mod:`opnav.filters.compiled`,
the same formulas, ~15 us a record instead of ~150 on S1) and gives every
other record, and every one that step does not accept, to the pure functions.
:func:`ekf_predict_batch` and :func:`ekf_update_batch` apply the same steps to K
independent runs at once (Monte Carlo in lockstep, :func:`opnav.filters.lockstep.run_ekf_lockstep`);
both forms share :func:`joseph_update`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Callable

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
    check_estimate,
    chi2_quantile,
    discrete_noise,
    gate_refusal,
    measurement_covariance,
    refused,
    rejected,
    screen_record,
)
from .noise import ProcessNoise, WhiteAcceleration

log = logging.getLogger(__name__)

#: ``propagator(t0_tdb_s, x0 (n,), t1_tdb_s) -> (x1 (n,), Phi (n, n))``.
StmPropagator = Callable[[float, np.ndarray, float], tuple[np.ndarray, np.ndarray]]
#: ``propagator(t0_tdb_s, X0 (K, 6), t1_tdb_s) -> (X1 (K, 6), Phi (K, 6, 6))``.
BatchStmPropagator = Callable[[float, np.ndarray, float], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class EKFOptions:
    """Gating of the EKF.

    Attributes
    ----------
    gate_probability : float or None
        Refuse a record whose NIS exceeds this chi-square(m) quantile; ``None`` turns
        gating off. The default 1 - 1e-6 refuses ~1 good record in a million and any
        residual beyond ~5.5 sigma (m = 2), so a 100-sigma outlier never gets in.
    consider : tuple of int
        Indices of augmented states (>= 6) treated as consider parameters: no gain, so
        their estimate and covariance stay as they started while their uncertainty enters
        the others' covariance (module notes, step 5).
    """

    gate_probability: float | None = 1.0 - 1e-6
    consider: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.gate_probability is not None and not 0.0 < self.gate_probability < 1.0:
            raise InputError(f"EKFOptions.gate_probability must be in (0, 1), got {self.gate_probability}")
        consider = tuple(int(i) for i in self.consider)
        if any(i < 6 for i in consider) or len(set(consider)) != len(consider):
            raise InputError(f"EKFOptions.consider must name distinct augmented states (index >= 6), got {self.consider}")
        object.__setattr__(self, "consider", consider)


def force_model_propagator(model, *, exact: bool = False) -> StmPropagator:
    """Wrap an :mod:`opnav.dynamics` force model as an :data:`StmPropagator` (state and variational equations).

    ``exact=False`` (default) integrates with the compiled fixed-step propagator
    (:class:`opnav.dynamics.fast.FastPropagator`); ``exact=True`` with DOP853 at
    rtol 1e-11 (:func:`opnav.dynamics.propagate`). States are ``(n,)`` or, for runs in
    lockstep, ``(K, n)`` (both propagators take either); augmented entries beyond the first
    six are held constant (identity STM block).
    """
    if exact:
        from ..dynamics import propagate

        def six(t0: float, x0: np.ndarray, t1: float) -> tuple[np.ndarray, np.ndarray]:
            traj = propagate(model, t0, x0, np.array([t1]), stm=True)
            return traj.states[-1], traj.stm[-1]
        fast = None
    else:
        from ..dynamics.fast import FastPropagator

        fast = FastPropagator(model)
        six = fast.step

    def step(t0: float, x0: np.ndarray, t1: float) -> tuple[np.ndarray, np.ndarray]:
        n = x0.shape[-1]
        if n == 6:
            return six(t0, x0, t1)
        x6, phi6 = six(t0, x0[..., :6], t1)
        x1 = np.array(x0, dtype=float)
        x1[..., :6] = x6
        phi = np.array(np.broadcast_to(np.eye(n), x0.shape[:-1] + (n, n)))
        phi[..., :6, :6] = phi6
        return x1, phi

    # the compiled single-run step (opnav.filters.compiled) propagates with the same FastPropagator
    step.fast_propagator = fast
    return step


def force_model_batch_propagator(model, *, exact: bool = False) -> "BatchStmPropagator":
    """:func:`force_model_propagator` for K states (K, n) in one call (runs in lockstep): the same
    stepper, named for the batch signature."""
    return force_model_propagator(model, exact=exact)


def ekf_predict(
    estimate: Estimate,
    t_tdb_s: float,
    *,
    propagator: StmPropagator,
    process_noise: ProcessNoise | None = None,
) -> Estimate:
    """Propagate ``estimate`` to ``t_tdb_s`` (TDB s past J2000): ``x = f(x)``, ``P = Phi P Phi^T + Q``.

    Raises
    ------
    InputError
        If ``t_tdb_s`` is not finite or lies before the estimate's epoch.
    CovarianceError
        If the predicted covariance is not finite SPD.
    """
    check_epoch(estimate.t_tdb_s, t_tdb_s)
    if not t_tdb_s > estimate.t_tdb_s:
        return estimate
    x, phi = propagator(estimate.t_tdb_s, estimate.x, float(t_tdb_s))
    P = phi @ estimate.P @ phi.T + discrete_noise(process_noise, estimate.t_tdb_s, float(t_tdb_s), estimate.x)
    return Estimate(float(t_tdb_s), np.asarray(x, dtype=float), check_covariance(P, "predicted covariance"))


def ekf_update(
    estimate: Estimate,
    record: Measurement,
    *,
    model: MeasurementModel,
    options: EKFOptions = EKFOptions(),
) -> UpdateOutcome:
    """Fold ``record`` (at the estimate's epoch) into ``estimate``; refusals keep the prior.

    Returns
    -------
    UpdateOutcome
        Posterior (or prior), residual ``nu`` (m,), ``S`` (m, m), NIS, accepted flag and reason.
    """
    screened = screen_record(estimate, record)
    if screened is not None:
        return screened
    x, P = estimate.x, estimate.P
    predicted, H = predict_with_jacobian(model, record, x)
    nu = model.residual(record, predicted)
    R = measurement_covariance(model, record, x)
    x_post, P_post, S, nis = joseph_update(x[None], P[None], nu[None], H[None], R, consider=options.consider)
    S, nis = S[0], float(nis[0])
    if not np.isfinite(nis):
        return rejected(estimate, record.size, "innovation covariance is not positive definite or innovation not finite", record)
    refusal = gate_refusal(estimate, record, residual=nu, residual_cov=S, nis=nis, probability=options.gate_probability)
    if refusal is not None:
        return refusal
    try:
        P_post = check_covariance(P_post[0], "posterior covariance")
    except CovarianceError as exc:
        return refused(estimate, record, str(exc), residual=nu, residual_cov=S, nis=nis)
    return UpdateOutcome(Estimate(estimate.t_tdb_s, x_post[0], P_post), nu, S, nis, True)


def predict_with_jacobian(model: MeasurementModel, record: Measurement, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``h(x)`` (m,) and ``dh/dx`` (m, n) at one state ``x`` (n,), from one geometry pass when the
    model offers ``predict_and_jacobians`` (light time and aberration are then solved once, not twice)."""
    both = getattr(model, "predict_and_jacobians", None)
    if both is None:
        return model.predict(record, x), model.jacobian(record, x)
    predicted, H = both(record, x[None])
    return predicted[0], H[0]


def joseph_update(
    x: np.ndarray, P: np.ndarray, nu: np.ndarray, H: np.ndarray, R: np.ndarray, *, consider: tuple[int, ...] = ()
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Kalman update of K states at once, Joseph form.

    Parameters
    ----------
    x : (K, n)  P : (K, n, n)  nu : (K, m) innovations  H : (K, m, n)  R : (m, m) or (K, m, m)
    consider : tuple of int
        State indices given no gain (consider parameters).

    Returns
    -------
    x_post (K, n), P_post (K, n, n) symmetrised, S (K, m, m), nis (K,).
    A run whose ``S`` is not positive definite gets NIS = NaN and its prior back.
    """
    HP = H @ P
    S = HP @ np.swapaxes(H, -1, -2) + R
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    eigmin = np.linalg.eigvalsh(S)[:, 0]
    good = np.isfinite(eigmin) & (eigmin > 0.0) & np.all(np.isfinite(nu), axis=-1)
    safe_S = np.where(good[:, None, None], S, np.eye(S.shape[-1]))
    chol = np.linalg.cholesky(safe_S)
    white = np.linalg.solve(chol, nu[..., None])[..., 0]
    nis = np.where(good, np.sum(white * white, axis=-1), np.nan)
    # K = P H^T S^-1, from S K^T = H P through the Cholesky factor
    gain = np.swapaxes(np.linalg.solve(np.swapaxes(chol, -1, -2), np.linalg.solve(chol, HP)), -1, -2)
    gain = np.where(good[:, None, None], gain, 0.0)
    if consider:
        gain[:, list(consider), :] = 0.0
    a = np.eye(x.shape[-1]) - gain @ H
    P_post = a @ P @ np.swapaxes(a, -1, -2) + gain @ R @ np.swapaxes(gain, -1, -2)
    P_post = 0.5 * (P_post + np.swapaxes(P_post, -1, -2))
    x_post = x + (gain @ np.where(good[:, None], nu, 0.0)[..., None])[..., 0]
    return x_post, P_post, S, nis


@dataclass(frozen=True)
class BatchUpdate:
    """Result of :func:`ekf_update_batch` for K runs.

    ``x`` (K, n) and ``P`` (K, n, n) posteriors (priors where refused), ``residual`` (K, m),
    ``nis`` (K,), ``accepted`` (K,) bool, ``H`` (K, m, n) Jacobians at the priors, ``R`` (K, m, m), each run's own.
    """

    x: np.ndarray
    P: np.ndarray
    residual: np.ndarray
    nis: np.ndarray
    accepted: np.ndarray
    H: np.ndarray
    R: np.ndarray


def ekf_predict_batch(
    t0_tdb_s: float,
    x: np.ndarray,
    P: np.ndarray,
    t1_tdb_s: float,
    *,
    propagator: BatchStmPropagator,
    process_noise: ProcessNoise | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`ekf_predict` for K independent runs sharing epochs: ``x`` (K, n), ``P`` (K, n, n).

    Returns the predicted states, covariances and the STMs (K, n, n).
    """
    dt = float(t1_tdb_s) - float(t0_tdb_s)
    if not dt >= 0.0:
        raise InputError(f"cannot predict backwards or to a non-finite epoch: {t0_tdb_s} -> {t1_tdb_s}")
    x1, phi = propagator(t0_tdb_s, x, t1_tdb_s)
    P1 = phi @ P @ np.swapaxes(phi, -1, -2)
    Q = batch_process_noise(process_noise, dt, x[:, :6])
    if x.shape[-1] == 6:
        P1 = P1 + Q
    else:
        P1[..., :6, :6] += Q
    return x1, 0.5 * (P1 + np.swapaxes(P1, -1, -2)), phi


def batch_process_noise(process_noise: ProcessNoise | None, dt_s: float, x: np.ndarray) -> np.ndarray | float:
    """Process noise over ``dt_s`` for K states ``x`` (K, 6): (K, 6, 6), one (6, 6) for all when the
    model does not depend on the state (:class:`~opnav.filters.noise.WhiteAcceleration`), 0 for none."""
    if process_noise is None or dt_s == 0.0:
        return 0.0
    if isinstance(process_noise, WhiteAcceleration):
        return process_noise.discrete(dt_s)
    return np.stack([process_noise.discrete(dt_s, xi) for xi in x])


def ekf_update_batch(
    x: np.ndarray,
    P: np.ndarray,
    record: Measurement,
    values: np.ndarray,
    *,
    model,
    options: EKFOptions = EKFOptions(),
) -> "BatchUpdate":
    """:func:`ekf_update` for K independent runs that observed the same kind/target/epoch.

    Parameters
    ----------
    x : (K, n)  P : (K, n, n)
    record : Measurement
        Kind, target, epoch and covariance shared by the runs (its value is not used).
    values : (K, m)
        Each run's measured value.
    model : measurement model with ``predict_and_jacobians(record, x) -> ((K, m), (K, m, n))``.

    Returns
    -------
    BatchUpdate
        Refused runs (non-finite NIS, e.g. a NaN value, or outside the gate) keep their prior.
        ``R`` is each run's own, evaluated at its state (it depends on the state through the
        target range), so a run's figures do not depend on the other runs of its batch.
    """
    predicted, H = model.predict_and_jacobians(record, x)
    # residual(record with zero value, predicted - values) = values - predicted, wrapped like the model's
    zero = replace(record, value=np.zeros(record.size))
    nu = model.residual(zero, predicted - values)
    R = measurement_covariance(model, record, x)
    x_post, P_post, _, nis = joseph_update(x, P, nu, H, R, consider=options.consider)
    accepted = np.isfinite(nis)
    if options.gate_probability is not None:
        accepted &= nis <= chi2_quantile(options.gate_probability, record.size)
    x_post = np.where(accepted[:, None], x_post, x)
    P_post = np.where(accepted[:, None, None], P_post, P)
    return BatchUpdate(x_post, P_post, nu, nis, accepted, H, R)


class ExtendedKalmanFilter(GaussianFilter):
    """EKF holding its models; see the module docstring for the algorithm.

    Parameters
    ----------
    estimate : Estimate
        Initial state (n,) and covariance (n, n) at the initial epoch.
    propagator : StmPropagator
        State and STM propagation, e.g. :func:`force_model_propagator` of a dynamics model.
    model : MeasurementModel
        e.g. :class:`opnav.measurements.ProbeMeasurementModel` for the same central body.
    process_noise : ProcessNoise, optional
        :mod:`opnav.filters.noise` model applied to the first six states.
    options : EKFOptions
    """

    def __init__(
        self,
        estimate: Estimate,
        *,
        propagator: StmPropagator,
        model: MeasurementModel,
        process_noise: ProcessNoise | None = None,
        options: EKFOptions = EKFOptions(),
    ) -> None:
        self.propagator = propagator
        self.model = model
        self.process_noise = process_noise
        self.options = options
        self.reset(estimate)

    def reset(self, estimate: Estimate) -> None:
        """Replace the current estimate (checked: finite state of at least 6, SPD covariance of matching size)."""
        self._estimate = check_estimate(estimate, min_size=6)

    def hold(self, estimate: Estimate) -> None:
        """Replace the current estimate with one whose covariance this filter computed (the bound's
        recursion, :func:`opnav.filters.crb.pcrb_along`, puts the state back on the truth): not
        checked again, where :meth:`reset` checks an estimate from elsewhere (a Cholesky a call)."""
        self._estimate = estimate

    def update(self, record: Measurement) -> UpdateOutcome:
        """Predict to the record's epoch and fold it in (or refuse it with a logged reason).

        RA/Dec records with the default models (fast propagation, white ephemeris error, no consider
        parameters) take one compiled step (:mod:`opnav.filters.compiled`); the rest, and every
        record that step does not accept, go through :func:`ekf_predict` and :func:`ekf_update`.
        """
        steps = self._compiled_steps()
        if steps is not None:
            outcome = steps.ekf(self._estimate, record, process_noise=self.process_noise,
                                gate_probability=self.options.gate_probability)
            if outcome is not None:
                self._estimate = outcome.estimate
                return outcome
        return super().update(record)

    def _compiled_steps(self):
        """The :class:`~opnav.filters.compiled.RadecSteps` of the current models, or None."""
        from .compiled import filter_steps

        steps = filter_steps(self, ExtendedKalmanFilter, self.propagator, self.model)
        return steps if not self.options.consider else None

    def _predict(self, estimate: Estimate, t_tdb_s: float) -> Estimate:
        return ekf_predict(estimate, t_tdb_s, propagator=self.propagator, process_noise=self.process_noise)

    def _update(self, prior: Estimate, record: Measurement) -> UpdateOutcome:
        return ekf_update(prior, record, model=self.model, options=self.options)
