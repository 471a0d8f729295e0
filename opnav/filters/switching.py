"""One filter run across changes of dynamics model and state origin (S2: model 1 -> model 2 at Mars' SOI).

S2 navigates the Mars capture with two models: outside Mars' sphere of
influence a heliocentric four-body model (state relative to the Sun), inside it
a Mars-centred perturbed two-body model, each with its own measurement set
(MPD outside, MPS inside). :class:`SwitchingFilter` chains one filter per
:class:`Phase`: records before a phase's start go to the previous filter; the
first record at or after it makes the filter predict to the switch epoch, moves
the estimate to the next phase's origin and hands it over.

Moving the origin is a translation by the ephemeris state of one centre
relative to the other at the switch epoch, ``x_mars = x_sun - x_mars/sun(t)``:
with the ephemeris taken as exact (the filters treat it so throughout) its
Jacobian is the identity and the covariance carries over unchanged.

States: ``[r km, v km/s]`` (augmented entries carried over unchanged), ICRF,
relative to each phase's ``center``; epochs TDB seconds past J2000.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..records import Measurement
from .base import Estimate, NavigationFilter, UpdateOutcome


@dataclass(frozen=True)
class Phase:
    """One leg of a switching run.

    Attributes
    ----------
    start_tdb_s : float
        First epoch of the leg, TDB s past J2000 (ignored for the first phase).
    center : str
        Origin of the leg's states (an ephemeris body, e.g. ``"sun"``, ``"mars"``).
    filter : NavigationFilter
        The leg's filter (its own dynamics and measurement model for ``center``); from the
        second phase on it must offer ``reset(estimate)``, its initial estimate is replaced.
    """

    start_tdb_s: float
    center: str
    filter: NavigationFilter


@dataclass(frozen=True)
class Switch:
    """A hand-over: epoch, the two origins, and the estimate before and after the change of origin."""

    t_tdb_s: float
    from_center: str
    to_center: str
    before: Estimate
    after: Estimate


class SwitchingFilter:
    """Run :class:`Phase` filters in turn, mapping the estimate across each switch (module notes).

    Parameters
    ----------
    phases : sequence of Phase
        In time order; the first phase's filter holds the initial estimate.
    ephemeris : Ephemeris, optional
        For the change of origin; default :func:`opnav.ephemeris.default_ephemeris`.

    Raises
    ------
    InputError
        For no phases, starts out of order, or a later filter without ``reset``.
    """

    def __init__(self, phases: Sequence[Phase], *, ephemeris=None) -> None:
        self.phases = tuple(phases)
        if not self.phases:
            raise InputError("SwitchingFilter needs at least one phase")
        starts = [p.start_tdb_s for p in self.phases[1:]]
        if any(not np.isfinite(s) for s in starts) or np.any(np.diff(starts) <= 0.0):
            raise InputError(f"phase starts must be finite and increasing, got {starts}")
        if starts and not starts[0] > self.phases[0].filter.estimate.t_tdb_s:
            raise InputError("the second phase must start after the initial estimate's epoch")
        for phase in self.phases[1:]:
            if not hasattr(phase.filter, "reset"):
                raise InputError(f"the filter of the phase starting at {phase.start_tdb_s} cannot be reset")
        if ephemeris is None:
            from ..ephemeris import default_ephemeris

            ephemeris = default_ephemeris()
        self.ephemeris = ephemeris
        self.current = 0
        self.switches: list[Switch] = []

    @property
    def estimate(self) -> Estimate:
        """The current phase's estimate (relative to :attr:`center`)."""
        return self.phases[self.current].filter.estimate

    @property
    def center(self) -> str:
        return self.phases[self.current].center

    def _phase_of(self, t_tdb_s: float) -> int:
        index = 0
        for i, phase in enumerate(self.phases[1:], start=1):
            if t_tdb_s >= phase.start_tdb_s:
                index = i
        return index

    def _advance(self, index: int) -> None:
        from ..dynamics import change_center

        while self.current < index:
            old, new = self.phases[self.current], self.phases[self.current + 1]
            before = old.filter.predict(new.start_tdb_s)
            x = np.array(before.x, dtype=float)
            x[:6] = change_center(x[:6], new.start_tdb_s, old.center, new.center, ephemeris=self.ephemeris)
            after = Estimate(new.start_tdb_s, x, before.P)
            new.filter.reset(after)
            self.switches.append(Switch(new.start_tdb_s, old.center, new.center, before, after))
            self.current += 1

    def predict(self, t_tdb_s: float) -> Estimate:
        """Move to ``t_tdb_s``, switching phases on the way; the estimate is relative to the new :attr:`center`."""
        self._advance(self._phase_of(t_tdb_s))
        return self.phases[self.current].filter.predict(t_tdb_s)

    def update(self, record: Measurement) -> UpdateOutcome:
        """Switch to the record's phase if it has begun, then let that phase's filter take the record."""
        index = self._phase_of(record.t_tdb_s)
        if index > self.current and np.isfinite(record.t_tdb_s):
            self._advance(index)
        return self.phases[self.current].filter.update(record)
