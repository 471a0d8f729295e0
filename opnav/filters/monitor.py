"""Consistency monitor: says when a filter's answer cannot be trusted.

A filter that is wrong rarely says so by itself: a collapsed particle cloud
reports a tiny covariance, gates out every record that disagrees and exits
cleanly. :func:`check_history` reads a :class:`~opnav.filters.run.FilterHistory`
(and, when the truth is known, its NEES) and returns a :class:`Consistency`
with named flags:

``refused``
    more than ``max_refused_fraction`` of the records were refused;
``nis_out_of_band``
    the mean NIS of ``window`` consecutive accepted records left its two-sided
    ``probability`` chi-square band (:func:`opnav.consistency.window_test`)
    for ``persistence`` windows in a row (Bar-Shalom, Li & Kirubarajan 2001,
    sec. 5.4: a consistent filter's NIS is chi-square with the record size);
``nees_out_of_band``
    the same test on NEES over epochs (only with a truth);
``final_error_outside_covariance``
    with a truth: the final NEES exceeds the ``probability`` quantile of chi-square(6)
    (one value, so the test does not assume time-independent NEES: a single run's NEES is
    one slowly varying draw);
``particles_degenerate``
    a particle filter's effective sample size fell below ``min_ess`` (the cloud
    stands for too few distinct states for its covariance to mean anything).

The answer is ``usable`` unless more than half of the records were refused,
the last NIS (or NEES) window is out of band, the final error lies outside the
covariance, or the particle cloud was ever
degenerate (a cloud that stood for a handful of states has lost the spread it
reports, and resampling hides that: N_eff is back to N right after). Other flags
are warnings: the states in between may be wrong, the final one may be used.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..consistency import WindowTest, chi2_quantile
from ..consistency import window_test as consistency_window_test
from ..errors import InputError
from .run import FilterHistory


@dataclass(frozen=True)
class MonitorOptions:
    """Thresholds of :func:`check_history`.

    Attributes
    ----------
    window : int
        Accepted records (or epochs, for NEES) per window.
    probability : float
        Two-sided probability of the chi-square band of a window's mean (0.999: a
        consistent filter leaves it once in a thousand windows).
    persistence : int
        Consecutive out-of-band windows that raise a flag.
    max_refused_fraction : float
        Largest share of refused records before ``refused`` is flagged.
    min_ess : float
        Smallest effective sample size of a particle cloud before ``particles_degenerate``.
    """

    window: int = 50
    probability: float = 0.999
    persistence: int = 3
    max_refused_fraction: float = 0.05
    min_ess: float = 10.0

    def __post_init__(self) -> None:
        if int(self.window) != self.window or self.window < 2:
            raise InputError(f"MonitorOptions.window must be an integer >= 2, got {self.window}")
        if not 0.0 < self.probability < 1.0:
            raise InputError(f"MonitorOptions.probability must be in (0, 1), got {self.probability}")
        if int(self.persistence) != self.persistence or self.persistence < 1:
            raise InputError(f"MonitorOptions.persistence must be an integer >= 1, got {self.persistence}")
        if not 0.0 <= self.max_refused_fraction <= 1.0:
            raise InputError(f"MonitorOptions.max_refused_fraction must be in [0, 1], got {self.max_refused_fraction}")
        if not self.min_ess >= 1.0:
            raise InputError(f"MonitorOptions.min_ess must be >= 1, got {self.min_ess}")


@dataclass(frozen=True)
class Consistency:
    """What :func:`check_history` found; ``flags`` empty means nothing to report."""

    flags: tuple[str, ...]
    usable: bool
    refused_fraction: float
    nis: WindowTest
    nees: WindowTest | None = None
    min_ess: float | None = None
    final_ess: float | None = None
    messages: tuple[str, ...] = field(default=())

    def to_dict(self) -> dict:
        """JSON-ready summary (``summary.json`` ``consistency``)."""
        out = {"flags": list(self.flags), "usable": self.usable, "refused_fraction": self.refused_fraction,
               "nis": self.nis.to_dict(), "messages": list(self.messages)}
        if self.nees is not None:
            out["nees"] = self.nees.to_dict()
        if self.min_ess is not None:
            out["particles"] = {"min_ess": self.min_ess, "final_ess": self.final_ess}
        return out


def window_test(values: np.ndarray, dof: np.ndarray, options: MonitorOptions) -> WindowTest:
    """Means of consecutive windows of chi-square values (``dof`` each) against their bands
    (:func:`opnav.consistency.window_test` with the window and probability of ``options``)."""
    return consistency_window_test(values, dof, window=options.window, probability=options.probability)


def check_history(history: FilterHistory, *, nees: np.ndarray | None = None, final_nees: float | None = None,
                  options: MonitorOptions = MonitorOptions()) -> Consistency:
    """Flag refusals, NIS (and NEES) out of band and a degenerate particle cloud.

    Parameters
    ----------
    history : FilterHistory
        One filter run (:func:`opnav.filters.run.run_filter`); ``history.ess`` is read when present.
    nees : (N,) array, optional
        NEES of the states at the history's epochs against a truth (state size 6); tested in
        windows, for NEES values that are independent (e.g. across Monte Carlo runs).
    final_nees : float, optional
        NEES of the final estimate against the truth (6 states).
    options : MonitorOptions
    """
    return check_records(history.accepted, history.nis, history.dof, history.ess, nees=nees, final_nees=final_nees,
                         options=options)


def check_records(accepted: np.ndarray, nis: np.ndarray, dof: np.ndarray, ess: np.ndarray | None = None, *,
                  nees: np.ndarray | None = None, final_nees: float | None = None,
                  options: MonitorOptions = MonitorOptions()) -> Consistency:
    """:func:`check_history` from per-record arrays (accepted flags, NIS, record sizes, N_eff or None)."""
    flags, messages = [], []
    count = int(np.size(accepted))
    refused_fraction = float(np.mean(~accepted)) if count else 0.0
    if refused_fraction > options.max_refused_fraction:
        flags.append("refused")
        messages.append(f"{refused_fraction:.0%} of the records were refused")
    used = accepted & np.isfinite(nis)
    nis = window_test(nis[used], dof[used], options)
    ends_outside = bool(nis.outside[-1]) if nis.outside.size else False
    if nis.longest_run >= options.persistence or ends_outside:
        flags.append("nis_out_of_band")
        messages.append(f"NIS left its {options.probability:.1%} band for {nis.longest_run} consecutive windows of "
                        f"{options.window} records" + (" and is outside it at the end" if ends_outside else ""))
    nees_test = None
    if nees is not None:
        nees = np.asarray(nees, dtype=float)
        nees_test = window_test(nees, np.full(nees.size, 6), options)
        if nees_test.longest_run >= options.persistence or (nees_test.outside.size and nees_test.outside[-1]):
            flags.append("nees_out_of_band")
            ends_outside = ends_outside or bool(nees_test.outside[-1])
            messages.append(f"NEES left its band for {nees_test.longest_run} consecutive windows")
    if final_nees is not None and not final_nees <= chi2_quantile(options.probability, 6):
        flags.append("final_error_outside_covariance")
        ends_outside = True
        messages.append(f"the final error is outside the reported covariance: NEES {final_nees:.1f} above the "
                        f"{options.probability:.1%} quantile of chi-square(6), {chi2_quantile(options.probability, 6):.1f}")
    min_ess = final_ess = None
    degenerate = False
    if ess is not None and np.any(np.isfinite(ess)):
        ess = ess[np.isfinite(ess)]
        min_ess, final_ess = float(ess.min()), float(ess[-1])
        degenerate = min_ess < options.min_ess
        if degenerate:
            flags.append("particles_degenerate")
            messages.append(f"the particle cloud's effective sample size fell to {min_ess:.1f} "
                            f"(threshold {options.min_ess:g}); use more particles")
    usable = refused_fraction <= 0.5 and not ends_outside and not degenerate
    return Consistency(tuple(flags), usable, refused_fraction, nis, nees_test, min_ess, final_ess, tuple(messages))
