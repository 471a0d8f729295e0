"""What every navigation filter shares: estimate records, update outcomes, checks.

Each filter form (:mod:`~opnav.filters.ekf`, :mod:`~opnav.filters.ukf`,
:mod:`~opnav.filters.sr_ukf`, :mod:`~opnav.filters.augmented_ukf`,
:mod:`~opnav.filters.particle`) has a pure-function core,
``<form>_predict(estimate, t, *, models) -> estimate`` and
``<form>_update(estimate, record, *, models) -> UpdateOutcome`` (the particle
filters carry a :class:`~opnav.filters.particle.ParticleCloud` and also return
it), and a thin class that holds the models and the current :class:`Estimate`:
``predict(t)`` moves the estimate to epoch ``t``; ``update(record)`` folds in
one :class:`opnav.records.Measurement` and returns an :class:`UpdateOutcome`
(residual, its covariance, NIS, accepted or the reason it was refused).
Refusals are logged, never silent.

What the forms share lives here, once: the epoch check (:func:`check_epoch`),
the record screen (:func:`record_problem`, :func:`screen_record`), the
measurement noise (:func:`measurement_covariance`), the process noise over a
step (:func:`discrete_noise`, :func:`psd_sqrt`), the chi-square gate
(:func:`chi2_gate`, :func:`gate_refusal`; the cached quantile is
:func:`opnav.consistency.chi2_quantile`, imported here) and the
refused outcomes (:func:`rejected`, :func:`refused`).

Vectors: the state is ``[r (km), v (km/s)]`` in ICRF relative to the filter's
central body (named by the dynamics model), possibly augmented by the filter.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..consistency import chi2_quantile
from ..errors import CovarianceError, InputError
from ..records import Measurement
from .noise import ProcessNoise

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Estimate:
    """State estimate at an epoch.

    Attributes
    ----------
    t_tdb_s : float
        TDB seconds past J2000.
    x : (n,) array
        State; the first six entries are position (km) and velocity (km/s), ICRF,
        relative to the dynamics model's central body.
    P : (n, n) array
        Covariance in the same units.
    """

    t_tdb_s: float
    x: np.ndarray
    P: np.ndarray


@dataclass(frozen=True)
class UpdateOutcome:
    """Result of one measurement update.

    ``estimate`` is the posterior, or the prior unchanged when ``accepted`` is
    False; ``reason`` then says why (NaN, non-PD covariance, time reversal,
    chi-square gate). ``residual``/``residual_cov``/``nis`` are NaN-filled when
    the record was rejected before they could be formed.
    """

    estimate: Estimate
    residual: np.ndarray
    residual_cov: np.ndarray
    nis: float
    accepted: bool
    reason: str = ""


class MeasurementModel(Protocol):
    """Predicts measurements from states (implemented in :mod:`opnav.measurements`)."""

    def predict(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        """Predicted value(s): ``x`` (n,) -> (m,), or (K, n) -> (K, m)."""
        ...

    def jacobian(self, record: Measurement, x: np.ndarray) -> np.ndarray:
        """d predict / d x at ``x`` (n,), shape (m, n)."""
        ...

    def residual(self, record: Measurement, predicted: np.ndarray) -> np.ndarray:
        """``record.value - predicted`` with angles wrapped to (-pi, pi]; (m,) or (K, m)."""
        ...


class NavigationFilter(Protocol):
    """The interface every filter in :mod:`opnav.filters` offers."""

    @property
    def estimate(self) -> Estimate: ...

    def predict(self, t_tdb_s: float) -> Estimate: ...

    def update(self, record: Measurement) -> UpdateOutcome: ...


class GaussianFilter:
    """What the Gaussian filters' classes share: hold the current estimate, predict it, take records.

    A subclass holds its models and supplies the pure steps ``_predict(estimate, t) -> Estimate``
    and ``_update(prior, record) -> UpdateOutcome`` (its module's ``*_predict`` / ``*_update``);
    ``reset`` checks an estimate before it is held (subclasses may tighten or factor it).
    """

    _estimate: Estimate

    @property
    def estimate(self) -> Estimate:
        return self._estimate

    def reset(self, estimate: Estimate) -> None:
        """Replace the current estimate (checked: finite state, SPD covariance of matching size)."""
        self._estimate = check_estimate(estimate)

    def predict(self, t_tdb_s: float) -> Estimate:
        """Move the estimate to ``t_tdb_s`` (TDB s past J2000); a no-op at the current epoch."""
        self._estimate = self._predict(self._estimate, t_tdb_s)
        return self._estimate

    def update(self, record: Measurement) -> UpdateOutcome:
        """Predict to the record's epoch, then fold it in (or refuse it with a logged reason,
        :func:`refuse_unusable`)."""
        refusal = refuse_unusable(record, self._estimate, self.predict)
        if refusal is not None:
            return refusal
        outcome = self._update(self.predict(record.t_tdb_s), record)
        self._estimate = outcome.estimate
        return outcome

    def _predict(self, estimate: Estimate, t_tdb_s: float) -> Estimate:
        raise NotImplementedError

    def _update(self, prior: Estimate, record: Measurement) -> UpdateOutcome:
        raise NotImplementedError


def check_epoch(t_current_tdb_s: float, t_tdb_s: float) -> None:
    """Refuse a prediction epoch that is not finite or lies before the filter epoch.

    Parameters
    ----------
    t_current_tdb_s : float
        The filter's epoch, TDB seconds past J2000.
    t_tdb_s : float
        The epoch to predict to; up to 1 ns before ``t_current_tdb_s`` counts as the same epoch.

    Raises
    ------
    InputError
        If ``t_tdb_s`` is not finite or lies more than 1 ns before ``t_current_tdb_s``.
    """
    if not np.isfinite(t_tdb_s):
        raise InputError("predict epoch t_tdb_s is not finite")
    if t_tdb_s < t_current_tdb_s - 1e-9:
        raise InputError(f"cannot predict backwards: t_tdb_s={t_tdb_s:.3f} is before the filter epoch {t_current_tdb_s:.3f}")


def record_problem(record: Measurement, t_current_tdb_s: float) -> str | None:
    """Reason a record cannot be processed now (bad values, or it lies in the filter's past)."""
    reason = record.problem()
    if reason is not None:
        return reason
    if record.t_tdb_s < t_current_tdb_s - 1e-9:
        return f"time goes backwards: record at {record.t_tdb_s:.3f} s is before the filter epoch {t_current_tdb_s:.3f} s"
    return None


def refuse_unusable(record: Measurement, current: Estimate, predict) -> UpdateOutcome | None:
    """The refusal of a record a filter cannot use (:func:`record_problem`), or ``None`` if it can.

    A record with bad values at a usable epoch (finite, not in the filter's past) still moves the
    filter to its epoch first (``predict(t) -> Estimate``): the refused row then carries the
    estimate at the record's time tag, never the old state under the new tag. A record in the
    filter's past (or at a non-finite epoch) leaves the filter where it is.
    """
    reason = record_problem(record, current.t_tdb_s)
    if reason is None:
        return None
    t = record.t_tdb_s
    estimate = predict(t) if np.isfinite(t) and t >= current.t_tdb_s - 1e-9 else current
    return rejected(estimate, record.size, reason, record)


def screen_record(estimate: Estimate, record: Measurement) -> UpdateOutcome | None:
    """The refused outcome for a record that cannot be folded into ``estimate`` as it is, else ``None``.

    A record is refused for bad values (:meth:`opnav.records.Measurement.problem`) or an
    epoch more than 1 us from the estimate's: the pure ``*_update`` functions fold in
    records at the estimate's epoch only (predict first).
    """
    reason = record.problem()
    if reason is None and abs(record.t_tdb_s - estimate.t_tdb_s) > 1e-6:
        reason = f"record epoch {record.t_tdb_s:.3f} differs from the estimate epoch {estimate.t_tdb_s:.3f}; predict first"
    return None if reason is None else rejected(estimate, record.size, reason, record)


def measurement_covariance(model: MeasurementModel, record: Measurement, x: np.ndarray) -> np.ndarray:
    """R for ``record`` at ``x``: the model's ``noise_covariance`` if it has one, else the record's.

    Parameters
    ----------
    model : MeasurementModel
        A model with ``noise_covariance(record, x)`` adds its own terms (e.g. the target's
        ephemeris error, which depends on the range and so on ``x``).
    record : Measurement
    x : (n,) or (K, n) array
        State(s) at which the model term is evaluated.

    Returns
    -------
    (m, m) array, or (K, m, m) for K states
        Measurement-noise covariance in record units.
    """
    noise = getattr(model, "noise_covariance", None)
    if noise is not None:
        return noise(record, x)
    return record.covariance if np.ndim(x) == 1 else np.broadcast_to(
        record.covariance, (np.shape(x)[0], record.size, record.size))


def discrete_noise(process_noise: ProcessNoise | None, t0_tdb_s: float, t1_tdb_s: float, x: np.ndarray) -> np.ndarray:
    """Process-noise covariance (n, n) over ``[t0, t1]`` at state ``x`` (n,); zero beyond the first six entries.

    ``process_noise`` is an :mod:`opnav.filters.noise` model (``None`` means none); epochs are
    TDB seconds past J2000; the result is in km and km/s.
    """
    n = x.shape[-1]
    Q = np.zeros((n, n))
    if process_noise is not None and t1_tdb_s != t0_tdb_s:
        Q[:6, :6] = np.asarray(process_noise.discrete(t1_tdb_s - t0_tdb_s, x[:6]), dtype=float)
    return Q


def psd_sqrt(Q: np.ndarray, name: str) -> np.ndarray:
    """A square root ``A`` (n, n) with ``A A^T = Q`` of a symmetric positive semi-definite ``Q`` (n, n).

    Unlike a Cholesky factor it exists for a singular ``Q`` (process noise that is zero
    outside the first six entries of an augmented state).

    Raises
    ------
    CovarianceError
        If ``Q`` has an eigenvalue below ``-1e-12`` times its largest magnitude; ``name`` says which matrix.
    """
    values, vectors = np.linalg.eigh(0.5 * (Q + np.swapaxes(Q, -1, -2)))
    if np.any(values < -1e-12 * max(1.0, float(np.max(np.abs(values))))):
        raise CovarianceError(f"{name} is not positive semi-definite")
    return vectors * np.sqrt(np.clip(values, 0.0, None))


def chi2_gate(nis: float, dof: int, probability: float) -> bool:
    """True if ``nis`` lies inside the ``probability`` quantile of chi-square(dof)."""
    return bool(nis <= chi2_quantile(probability, dof))


def gate_refusal(
    estimate: Estimate,
    record: Measurement,
    *,
    residual: np.ndarray,
    residual_cov: np.ndarray,
    nis: float,
    probability: float | None,
) -> UpdateOutcome | None:
    """The refused outcome (logged) if ``nis`` fails the chi-square gate, else ``None``.

    Parameters
    ----------
    estimate : Estimate
        The prior, kept by the refusal.
    record : Measurement
    residual : (m,) array
        Innovation in record units.
    residual_cov : (m, m) array
        Its covariance.
    nis : float
        ``residual^T residual_cov^-1 residual``.
    probability : float or None
        Gate at this quantile of chi-square(m); ``None`` lets every record through.
    """
    if probability is None or chi2_gate(nis, record.size, probability):
        return None
    return refused(estimate, record, gate_message(nis, probability, record.size), residual=residual,
                   residual_cov=residual_cov, nis=nis)


def gate_message(nis: float, probability: float, size: int) -> str:
    """Why a record of ``size`` with ``nis`` was refused by the chi-square gate at ``probability``."""
    return f"chi-square gate: NIS {nis:.3g} above the {probability} quantile of chi2({size})"


def refused(
    estimate: Estimate, record: Measurement, reason: str, *, residual: np.ndarray, residual_cov: np.ndarray, nis: float
) -> UpdateOutcome:
    """An :class:`UpdateOutcome` that keeps ``estimate`` and refuses ``record`` for ``reason``; logs why."""
    log.warning("rejected %s measurement at t=%.3f s (%s): %s", record.kind, record.t_tdb_s, record.sensor or "-", reason)
    return UpdateOutcome(estimate, residual, residual_cov, nis, False, reason)


def check_covariance(P: np.ndarray, name: str = "covariance") -> np.ndarray:
    """Return ``P`` symmetrised; raise :class:`CovarianceError` if it is not finite SPD."""
    P = np.asarray(P, dtype=float)
    if P.ndim != 2 or P.shape[0] != P.shape[1]:
        raise CovarianceError(f"{name} must be square, got shape {P.shape}")
    if not np.all(np.isfinite(P)):
        raise CovarianceError(f"{name} contains NaN or infinity")
    P = 0.5 * (P + P.T)
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        raise CovarianceError(f"{name} is not positive definite") from None
    return P


def check_estimate(estimate: Estimate, *, min_size: int = 1) -> Estimate:
    """A validated copy of ``estimate``: finite 1-D state of at least ``min_size`` entries,
    finite symmetric positive-definite covariance of matching size; raise otherwise."""
    x = np.asarray(estimate.x, dtype=float)
    if x.ndim != 1 or x.size < min_size or not np.all(np.isfinite(x)):
        raise InputError(f"estimate.x must be a finite 1-D state with >= {min_size} entries, got shape {x.shape}")
    P = check_covariance(estimate.P, "estimate.P")
    if P.shape != (x.size, x.size):
        raise InputError(f"estimate.P must be {x.size}x{x.size}, got {P.shape}")
    return Estimate(float(estimate.t_tdb_s), x, P)


def rejected(estimate: Estimate, size: int, reason: str, record: Measurement) -> UpdateOutcome:
    """An :class:`UpdateOutcome` for a record refused before an innovation existed; logs why.

    ``size`` is the record's ``m``; residual, its covariance and NIS are NaN-filled.
    """
    nan = np.full(size, np.nan)
    return refused(estimate, record, reason, residual=nan, residual_cov=np.full((size, size), np.nan), nis=float("nan"))
