"""What every navigation filter shares: estimate records, update outcomes, checks.

A filter holds its models (dynamics, measurement model, process noise) and a
current :class:`Estimate`. ``predict(t)`` moves the estimate to epoch ``t``;
``update(record)`` folds in one :class:`opnav.records.Measurement` and returns
an :class:`UpdateOutcome` (residual, its covariance, NIS, accepted or the
reason it was rejected). Rejections are logged, never silent.

Vectors: the state is ``[r (km), v (km/s)]`` in ICRF relative to the filter's
central body (named by the dynamics model), possibly augmented by the filter.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy import stats

from ..errors import CovarianceError, InputError
from ..records import Measurement

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


def record_problem(record: Measurement, t_current_tdb_s: float) -> str | None:
    """Reason a record cannot be processed now (bad values, or it lies in the filter's past)."""
    reason = record.problem()
    if reason is not None:
        return reason
    if record.t_tdb_s < t_current_tdb_s - 1e-9:
        return f"time goes backwards: record at {record.t_tdb_s:.3f} s is before the filter epoch {t_current_tdb_s:.3f} s"
    return None


def chi2_gate(nis: float, dof: int, probability: float) -> bool:
    """True if ``nis`` lies inside the ``probability`` quantile of chi-square(dof)."""
    return bool(nis <= stats.chi2.ppf(probability, dof))


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
    """An :class:`UpdateOutcome` for a record refused before an innovation existed; logs why."""
    log.warning("rejected %s measurement at t=%.3f s (%s): %s", record.kind, record.t_tdb_s, record.sensor or "-", reason)
    nan = np.full(size, np.nan)
    return UpdateOutcome(estimate, nan, np.full((size, size), np.nan), float("nan"), False, reason)
