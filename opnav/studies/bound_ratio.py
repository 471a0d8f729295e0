"""A campaign's error beside its posterior Cramér-Rao bound, and its NEES beside its band, with intervals.

S1's tables (:mod:`opnav.studies.s1`) compare each setting's position RMS over the window with the
bound along the truth (:func:`opnav.studies.campaign_runs.posterior_bound`). Both are root mean squares
over the same window of the same quantity: per seed ``r_i = sqrt(mean_t |e_i(t)|^2)`` (km, the
seed's ``position_rms_km``) and for the bound ``B = sqrt(mean_t tr P_B(t)[:3, :3])``. For any
estimator, ``E |e(t)|^2 >= tr P_B(t)``, so over seeds the mean square ``mean_i r_i^2`` estimates a
number at least ``B^2``: the figure to hold against the bound is the RMS over seeds of the seeds'
RMS, ``sqrt(mean_i r_i^2)``, not the mean of the ``r_i`` (smaller by Jensen's inequality, by a
lot when the seeds spread as widely as S1's do).

Its interval: the seeds' ``r_i^2`` are independent draws (a campaign gives each seed its own random
numbers) of an unknown, skewed distribution (S1's window error lies almost along one weak direction,
so ``r_i^2`` is close to a one-degree-of-freedom chi-square), so the interval of their mean is a
bias-corrected and accelerated (BCa) bootstrap over the seeds (:func:`scipy.stats.bootstrap`), which
assumes no shape; the square root and the division by ``B`` carry it over to the ratio. A filter
that reaches the bound has ratio 1 inside its interval; an interval above 1 is a filter short of the
bound, one below 1 a bound that is wrong (no estimator beats it).

NEES (6 states): a run's mean NEES over an interval of epochs has expectation 6 for a consistent
filter, whatever the correlation of its epochs; the variance of that mean is at most that of one
epoch's chi-square(6) (12, reached when the error does not change over the interval). The mean over
``N`` independent runs is therefore judged against the 95 % interval of a chi-square(6 N) / N
(:func:`opnav.consistency.chi2_mean_bounds`): the exact band when each run's error holds still over
the interval, and one a less correlated mean (of smaller variance) falls in at least as often in
practice (``tests/studies/test_bound_ratio.py`` draws both).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from ..consistency import chi2_mean_bounds
from ..errors import InputError


@dataclass(frozen=True)
class BoundRatio:
    """RMS over seeds of the seeds' window RMS, and its ratio to the bound with an interval.

    Attributes
    ----------
    seeds : int
        Number of seeds.
    rms_km : float
        ``sqrt(mean_i r_i^2)``, km.
    bound_km : float
        The bound ``B`` (RMS over the same window), km.
    ratio : float
        ``rms_km / bound_km``.
    low, high : float
        The ratio's interval (``probability``, BCa bootstrap over the seeds).
    probability : float
        Coverage of the interval.
    """

    seeds: int
    rms_km: float
    bound_km: float
    ratio: float
    low: float
    high: float
    probability: float

    @property
    def verdict(self) -> str:
        """``"reaches the bound"`` (1 inside the interval), ``"above the bound"`` or ``"below the bound"``."""
        if self.low > 1.0:
            return "above the bound"
        if self.high < 1.0:
            return "below the bound"
        return "reaches the bound"


def rms_over_bound(rms_km, bound_km: float, *, probability: float = 0.95, resamples: int = 10_000,
                   rng: np.random.Generator | int | None = 0) -> BoundRatio:
    """The seeds' RMS over the bound (module notes).

    Parameters
    ----------
    rms_km : (N,) array_like
        Each seed's position RMS over the window, km (N >= 3, finite, not all equal).
    bound_km : float
        The bound's position RMS over the same window, km (> 0).
    probability : float
        Coverage of the interval, in (0, 1).
    resamples : int
        Bootstrap resamples.
    rng : numpy Generator, int or None
        The bootstrap's random numbers (default 0: the same interval for the same seeds).
    """
    values = np.asarray(rms_km, dtype=float)
    if values.ndim != 1 or values.size < 3 or not np.all(np.isfinite(values)):
        raise InputError(f"rms_over_bound needs at least 3 finite per-seed RMS values, got {values.shape}")
    if not (np.isfinite(bound_km) and bound_km > 0.0):
        raise InputError(f"rms_over_bound needs a positive bound, got {bound_km}")
    if not 0.0 < probability < 1.0:
        raise InputError(f"probability must be in (0, 1), got {probability}")
    squares = values**2
    mean_square = float(squares.mean())
    if np.ptp(squares) == 0.0:  # every seed alike: no spread to resample
        low = high = mean_square
    else:
        interval = stats.bootstrap((squares,), np.mean, confidence_level=probability, n_resamples=resamples,
                                   method="BCa", random_state=np.random.default_rng(rng)).confidence_interval
        low, high = float(interval.low), float(interval.high)
    rms = np.sqrt(mean_square)
    return BoundRatio(int(values.size), float(rms), float(bound_km), float(rms / bound_km),
                      float(np.sqrt(low) / bound_km), float(np.sqrt(high) / bound_km), probability)


@dataclass(frozen=True)
class MeanNEES:
    """Mean over runs of each run's mean NEES over an interval of epochs, with its band.

    Attributes
    ----------
    runs : int
    mean : float
    low, high : float
        The band a consistent filter's mean falls in with ``probability`` or more (module notes).
    probability : float
    """

    runs: int
    mean: float
    low: float
    high: float
    probability: float

    @property
    def inside(self) -> bool:
        return self.low <= self.mean <= self.high


def mean_nees(run_means, *, dof: int = 6, probability: float = 0.95) -> MeanNEES:
    """Mean of the runs' mean NEES (each over the same interval of epochs) and its band (module notes).

    Parameters
    ----------
    run_means : (N,) array_like
        Each independent run's mean NEES over the interval.
    dof : int
        States the NEES is taken over.
    probability : float
        Coverage of the band.
    """
    values = np.asarray(run_means, dtype=float)
    if values.ndim != 1 or values.size < 1 or not np.all(np.isfinite(values)):
        raise InputError(f"mean_nees needs finite per-run NEES means, got {values.shape}")
    low, high = chi2_mean_bounds(dof, int(values.size), probability)
    return MeanNEES(int(values.size), float(values.mean()), float(low), float(high), probability)
