"""Filter consistency statistics, the one copy: NEES, NIS, chi-square bands and the Monte Carlo NEES test.

Consistency (Bar-Shalom, Li & Kirubarajan 2001, Sec. 5.4): for a consistent filter the
normalised estimation error squared ``NEES = e^T P^-1 e`` of an ``n``-state estimate is
chi-square(n), and the normalised innovation squared ``NIS`` of an ``m``-value record is
chi-square(m). The mean of ``N`` independent chi-square(d) values times ``N`` is chi-square(N d),
which gives the two-sided bounds of :func:`chi2_mean_bounds` (and, for one value,
:func:`chi2_interval`). On top of these:

- :func:`window_test`: the means of consecutive windows of chi-square values (NIS per record, or
  NEES per epoch) against their bands, the test of :mod:`opnav.filters.monitor`;
- :func:`ensemble_nees`: the Monte Carlo test (Sec. 5.4.2), the NEES of N runs averaged at each
  epoch against the band of the mean of N values;
- :func:`nis_summary` and :func:`nees_band_share`: the figures reports quote.

Only numpy, scipy and opnav's foundation modules are imported, and not ``scipy.stats`` (a second or
more to import): chi-square quantiles come from ``scipy.special.gammaincinv``, its own formula.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

import numpy as np

from .errors import InputError


def nees(states: np.ndarray, covariances: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared ``(x - x_true)^T P^-1 (x - x_true)``, shape (N,).

    Parameters
    ----------
    states : (N, n) array
        Estimates (any frame, origin and units).
    covariances : (N, n, n) array
        Their covariances, in the same units squared.
    truth : (N, n) array
        True states at the same epochs, same frame, origin and units.

    Raises
    ------
    InputError
        When the shapes do not match.
    """
    states = np.asarray(states, dtype=float)
    truth = np.asarray(truth, dtype=float)
    if truth.shape != states.shape or np.shape(covariances) != states.shape + states.shape[-1:]:
        raise InputError(f"nees: states {np.shape(states)}, covariances {np.shape(covariances)} and truth "
                         f"{np.shape(truth)} do not match")
    err = states - truth
    chol = np.linalg.cholesky(covariances)
    white = np.linalg.solve(chol, err[..., None])[..., 0]
    return np.sum(white * white, axis=-1)


@lru_cache(maxsize=256)
def chi2_quantile(probability: float, dof: float) -> float:
    """The ``probability`` quantile of chi-square(``dof``), cached: ``scipy.stats.chi2.ppf``'s own formula
    (the same bits) without importing ``scipy.stats`` (over a second on a busy machine)."""
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(0.5 * dof, probability))


def chi2_mean_bounds(dof: int, count: int, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided ``probability`` interval of the mean of ``count`` independent chi-square(dof) values."""
    if dof < 1 or count < 1:
        raise InputError(f"chi2_mean_bounds needs dof >= 1 and count >= 1, got {dof}, {count}")
    tail = 0.5 * (1.0 - probability)
    total = dof * count
    return chi2_quantile(tail, total) / count, chi2_quantile(1.0 - tail, total) / count


def chi2_interval(dof: int, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided ``probability`` interval of one chi-square(``dof``) value."""
    return chi2_mean_bounds(dof, 1, probability)


def nees_band_share(values: np.ndarray, dof: int, probability: float = 0.95) -> float:
    """Share of the NEES ``values`` (each chi-square(``dof``) for a consistent filter) inside the
    two-sided ``probability`` interval of one value (bounds included)."""
    low, high = chi2_interval(dof, probability)
    values = np.asarray(values, dtype=float)
    return float(np.mean((values >= low) & (values <= high)))


def nis_summary(nis: np.ndarray, dof: np.ndarray, accepted: np.ndarray, probability: float = 0.95) -> dict | None:
    """Mean NIS of the accepted records with a finite NIS, their mean record size (rounded) and the
    two-sided ``probability`` band of that mean: ``{"mean", "mean_dof", "bounds95_for_mean"}``, or
    None when no record qualifies. (The key names the 95 % band, the default ``probability``.)"""
    used = np.asarray(accepted, dtype=bool) & np.isfinite(nis)
    values = np.asarray(nis, dtype=float)[used]
    if not values.size:
        return None
    mean_dof = int(round(np.mean(np.asarray(dof)[used])))
    return {"mean": float(values.mean()), "mean_dof": mean_dof,
            "bounds95_for_mean": list(chi2_mean_bounds(mean_dof, values.size, probability))}


@dataclass(frozen=True)
class WindowTest:
    """Windowed chi-square test of one statistic (NIS or NEES).

    ``means`` are the window means, ``bounds`` their (lower, upper) bands (one per window),
    ``outside`` which windows left the band, ``longest_run`` the longest run of windows out of band.
    """

    means: np.ndarray
    bounds: np.ndarray
    outside: np.ndarray
    longest_run: int

    def to_dict(self) -> dict:
        return {"windows": int(self.means.size), "windows_outside": int(self.outside.sum()),
                "longest_run_outside": self.longest_run,
                "last_window_mean": float(self.means[-1]) if self.means.size else None,
                "last_window_bounds": self.bounds[-1].tolist() if self.means.size else None}


def window_test(values: np.ndarray, dof: np.ndarray, *, window: int, probability: float) -> WindowTest:
    """Means of consecutive windows of ``window`` chi-square values (``dof`` each) against their
    two-sided ``probability`` bands (the band of the window's sum, scaled to its mean per value).

    A trailing partial window of at least half the length is tested too, so the end of a run
    is always looked at.
    """
    values = np.asarray(values, dtype=float)
    dof = np.asarray(dof, dtype=int)
    w = int(window)
    starts = list(range(0, values.size - w + 1, w))
    if values.size % w >= w // 2 or (not starts and values.size):
        starts.append(max(0, values.size - w))
    means, bounds = [], []
    for s in starts:
        chunk, chunk_dof = values[s: s + w], dof[s: s + w]
        total = int(chunk_dof.sum())
        lo, hi = chi2_mean_bounds(total, 1, probability)
        means.append(chunk.mean())
        bounds.append((lo / chunk.size, hi / chunk.size))
    means_arr = np.array(means)
    bounds_arr = np.array(bounds).reshape(-1, 2)
    outside = (means_arr < bounds_arr[:, 0]) | (means_arr > bounds_arr[:, 1])
    longest = run = 0
    for out in outside:
        run = run + 1 if out else 0
        longest = max(longest, run)
    return WindowTest(means_arr, bounds_arr, outside, longest)


@dataclass(frozen=True)
class EnsembleNEES:
    """Result of the Monte Carlo NEES test (:func:`ensemble_nees`).

    Attributes
    ----------
    runs : int
        Runs averaged at each epoch (N).
    epochs : int
        Epochs, matched to the second, that every run has inside the judged window (E).
    mean : float
        Mean over those epochs of the run-averaged NEES.
    band : (float, float)
        Two-sided ``probability`` interval of the mean of N chi-square(``dof``) values.
    share_inside : float
        Share of the E epochs whose run-averaged NEES lies inside ``band`` (bounds included).
    dof : int
        Degrees of freedom of one NEES value (the states it is taken over).
    probability : float
    """

    runs: int
    epochs: int
    mean: float
    band: tuple[float, float]
    share_inside: float
    dof: int
    probability: float

    def to_dict(self) -> dict:
        return {"runs": self.runs, "epochs": self.epochs, "mean": self.mean, "band": list(self.band),
                "share_inside": self.share_inside, "dof": self.dof, "probability": self.probability}


def ensemble_nees(runs: Sequence[tuple[np.ndarray, np.ndarray]], dof: int, window_start_tdb_s: float,
                  probability: float = 0.95) -> EnsembleNEES:
    """Monte Carlo NEES test (Bar-Shalom, Li & Kirubarajan 2001, Sec. 5.4.2) over N runs of one filter.

    One run cannot test consistency: its epochs share one estimation error, so a run whose error
    sits 3 sigma out along a weak axis is out of any band at every epoch. Across independent runs
    the NEES at one epoch are independent, and for a consistent filter their mean is distributed
    as chi-square(N dof) / N. So the NEES is averaged over the runs at each epoch they share in the
    judged window and compared with the two-sided ``probability`` interval of that mean
    (:func:`chi2_mean_bounds`); a consistent filter has about ``probability`` of the epochs inside,
    an overconfident one (covariance too small) falls above the band, a pessimistic one below.
    The epochs of one run are correlated (the error changes slowly), so the share scatters far
    more than a binomial count: a few runs of a consistent filter can give a share near 0 or 1.

    Parameters
    ----------
    runs : sequence of (epochs, nees)
        Per run: epochs (TDB s past J2000) and the NEES at them, 1-D arrays of one length.
        Epochs are matched across runs to the nearest second.
    dof : int
        Degrees of freedom of one NEES value: the number of states it is taken over (6 for
        position and velocity, whatever parameters the filter's state carries beside them).
    window_start_tdb_s : float
        Start of the judged window, TDB s past J2000: epochs (rounded to the second) from it on count.
    probability : float
        Coverage of the band, in (0, 1).

    Returns
    -------
    EnsembleNEES

    Raises
    ------
    InputError
        No runs; a run whose epoch and NEES arrays differ in length, are not 1-D, or whose epochs
        are not finite; a NaN or infinite NEES in the window; two epochs of one run within the
        same second; no epoch in the window that every run has; ``probability`` outside (0, 1).
    """
    if not len(runs):
        raise InputError("ensemble_nees: no runs")
    if not 0.0 < probability < 1.0:
        raise InputError(f"ensemble_nees: probability must be in (0, 1), got {probability}")
    judged = [_judged_epochs(i, t, values, window_start_tdb_s) for i, (t, values) in enumerate(runs)]
    shared = judged[0][0]
    for seconds, _ in judged[1:]:
        shared = np.intersect1d(shared, seconds, assume_unique=True)
    if not shared.size:
        raise InputError(f"ensemble_nees: the {len(runs)} runs share no epoch (to the second) from "
                         f"{window_start_tdb_s} s TDB on")
    per_epoch = np.mean([values[np.searchsorted(seconds, shared)] for seconds, values in judged], axis=0)
    low, high = chi2_mean_bounds(dof, len(runs), probability)
    return EnsembleNEES(runs=len(runs), epochs=int(shared.size), mean=float(per_epoch.mean()), band=(low, high),
                        share_inside=float(np.mean((per_epoch >= low) & (per_epoch <= high))), dof=int(dof),
                        probability=float(probability))


def _judged_epochs(index: int, epochs, values, window_start_tdb_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Run ``index``'s epochs in the window, rounded to whole seconds and sorted, and its NEES at them."""
    epochs = np.asarray(epochs, dtype=float)
    values = np.asarray(values, dtype=float)
    if epochs.ndim != 1 or epochs.shape != values.shape:
        raise InputError(f"ensemble_nees: run {index} has epochs of shape {epochs.shape} and NEES of shape "
                         f"{values.shape}; both must be 1-D of one length")
    if not np.all(np.isfinite(epochs)):
        raise InputError(f"ensemble_nees: run {index} has epochs that are not finite")
    # runs simulated alike carry their epochs with different float noise: match them to the second
    seconds = np.round(epochs).astype(np.int64)
    inside = seconds >= window_start_tdb_s
    order = np.argsort(seconds[inside], kind="stable")
    seconds, values = seconds[inside][order], values[inside][order]
    if np.any(np.diff(seconds) == 0):
        raise InputError(f"ensemble_nees: run {index} has two epochs within one second; they cannot be matched "
                         "across runs to the second")
    bad = int(np.count_nonzero(~np.isfinite(values)))
    if bad:
        raise InputError(f"ensemble_nees: run {index} has {bad} NaN or infinite NEES value(s) in the window")
    return seconds, values
