"""Federated filter (Carlson 1990) for S4: local filters per sensor, master fusion, reset.

Each sensor feeds its own local filter (e.g. the angle sensor's position
pseudo-measurements one, the spectrometer's Doppler velocities another); all
locals estimate the same full state. Algorithm:

1. Information sharing: with factors ``beta_i > 0``, ``sum beta_i = 1``, local
   ``i`` starts from ``P_i = P_0 / beta_i`` and runs with process noise
   ``Q / beta_i`` (the federated filter wraps the local's ``process_noise``), so
   the common prior and process noise are counted once in total.
2. Each record is routed by ``record.sensor`` to its local filter, which
   predicts to the record's epoch and updates.
3. Fusion at an epoch ``t``: every local is predicted to ``t`` and
   ``P_g = (sum_i P_i^-1)^-1``, ``x_g = P_g sum_i P_i^-1 x_i``.
4. Modes:

   - ``"fusion-reset"``: after each fusion the locals restart from the global
     solution, ``x_i = x_g``, ``P_i = P_g / beta_i``. Each local then benefits
     from the others' data; the best accuracy.
   - ``"no-reset"``: the locals never hear from the master; the fused estimate
     is formed for output only. Each local is then a stand-alone filter on its
     own sensor (more robust to a failing sensor, less accurate).

The local filters are taken over by the federated filter (it resets them and
scales their process noise); any filter with ``estimate``, ``predict``,
``update``, ``reset`` and a ``process_noise`` attribute (the unscented filters,
:class:`opnav.filters.ekf.ExtendedKalmanFilter`) will do.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..errors import InputError
from ..records import Measurement
from .base import Estimate, UpdateOutcome, check_covariance, rejected
from .noise import ProcessNoise
from .option_types import MODES, FederatedSetup  # FederatedSetup: importable from here too
from .run import without_duplicates


class LocalFilter(Protocol):
    """What the federated filter needs from a local filter."""

    process_noise: ProcessNoise | None

    @property
    def estimate(self) -> Estimate: ...

    def predict(self, t_tdb_s: float) -> Estimate: ...

    def update(self, record: Measurement) -> UpdateOutcome: ...

    def reset(self, estimate: Estimate) -> None: ...


@dataclass(frozen=True)
class ScaledNoise:
    """A process-noise model multiplied by ``factor`` (``1/beta_i`` for a local filter)."""

    base: ProcessNoise
    factor: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.factor) and self.factor > 0.0):
            raise InputError(f"ScaledNoise.factor must be finite and > 0, got {self.factor}")

    def discrete(self, dt_s: float, x: np.ndarray) -> np.ndarray:
        """``factor * base.discrete(dt_s, x)`` (6, 6), km and km/s."""
        return self.factor * np.asarray(self.base.discrete(dt_s, x), dtype=float)


@dataclass(frozen=True)
class FederatedOptions:
    """Information-sharing factors and mode.

    Attributes
    ----------
    betas : mapping of local name to float
        ``beta_i > 0`` summing to 1 (the master keeps no share of its own).
    mode : {"fusion-reset", "no-reset"}
    routes : mapping of sensor name to local name
        Which local filter takes records of each ``record.sensor``.
    """

    betas: Mapping[str, float]
    routes: Mapping[str, str]
    mode: str = "fusion-reset"

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise InputError(f"FederatedOptions.mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        values = np.array(list(self.betas.values()), dtype=float)
        if values.size == 0 or np.any(~np.isfinite(values)) or np.any(values <= 0.0):
            raise InputError(f"FederatedOptions.betas must be positive, got {dict(self.betas)}")
        if abs(values.sum() - 1.0) > 1e-9:
            raise InputError(f"FederatedOptions.betas must sum to 1, got {values.sum():.12g}")
        unknown = set(self.routes.values()) - set(self.betas)
        if unknown:
            raise InputError(f"FederatedOptions.routes point to locals without a beta: {', '.join(sorted(unknown))}")


def fuse(estimates: list[Estimate]) -> Estimate:
    """Information-weighted fusion of estimates at one epoch.

    ``P_g = (sum P_i^-1)^-1``, ``x_g = P_g sum P_i^-1 x_i``; all states share
    units, frame and origin.
    """
    if not estimates:
        raise InputError("fuse needs at least one estimate")
    t = estimates[0].t_tdb_s
    if any(abs(e.t_tdb_s - t) > 1e-9 for e in estimates):
        raise InputError(f"fuse needs estimates at one epoch, got {[e.t_tdb_s for e in estimates]}")
    info = sum(np.linalg.inv(e.P) for e in estimates)
    vector = sum(np.linalg.solve(e.P, e.x) for e in estimates)
    P = check_covariance(np.linalg.inv(info), "fused covariance")
    return Estimate(t, P @ vector, P)


class FederatedFilter:
    """Federated filter over named local filters; see the module docstring.

    Parameters
    ----------
    locals_ : mapping of name to LocalFilter
        The local filters (taken over: reset to ``P_0 / beta_i``, noise scaled by ``1 / beta_i``).
    initial : Estimate
        Common initial estimate ``(x_0, P_0)``.
    options : FederatedOptions
    """

    def __init__(self, locals_: Mapping[str, LocalFilter], *, initial: Estimate, options: FederatedOptions) -> None:
        if set(locals_) != set(options.betas):
            raise InputError(f"locals {sorted(locals_)} and betas {sorted(options.betas)} must name the same filters")
        self.locals = dict(locals_)
        self.options = options
        P0 = check_covariance(initial.P, "initial.P")
        for name, local in self.locals.items():
            beta = float(options.betas[name])
            if local.process_noise is not None:
                local.process_noise = ScaledNoise(local.process_noise, 1.0 / beta)
            local.reset(Estimate(initial.t_tdb_s, np.asarray(initial.x, dtype=float), P0 / beta))
        self._estimate = Estimate(float(initial.t_tdb_s), np.asarray(initial.x, dtype=float), P0)

    @property
    def estimate(self) -> Estimate:
        """The last fused (global) estimate."""
        return self._estimate

    def predict(self, t_tdb_s: float) -> Estimate:
        """Predict every local to ``t_tdb_s`` and return their fusion (locals are not reset)."""
        return fuse([local.predict(t_tdb_s) for local in self.locals.values()])

    def update(self, record: Measurement) -> UpdateOutcome:
        """Route ``record`` to the local filter of ``record.sensor``; returns that local's outcome."""
        name = self.options.routes.get(record.sensor)
        if name is None:
            return rejected(self._estimate, record.size, f"no local filter for sensor {record.sensor!r}", record)
        return self.locals[name].update(record)

    def fuse(self, t_tdb_s: float) -> Estimate:
        """Master fusion at ``t_tdb_s``; in ``fusion-reset`` mode the locals restart from the result."""
        self._estimate = self.predict(t_tdb_s)
        if self.options.mode == "fusion-reset":
            for name, local in self.locals.items():
                local.reset(Estimate(self._estimate.t_tdb_s, self._estimate.x, self._estimate.P / self.options.betas[name]))
        return self._estimate


def run_federated(
    federated: FederatedFilter, records: list[Measurement], fusion_epochs_tdb_s: np.ndarray
) -> tuple[list[Estimate], list[UpdateOutcome]]:
    """Feed ``records`` in time order and fuse at each epoch once every record up to it is in.

    Returns the fused estimates (one per fusion epoch) and the update outcomes (one per record).
    """
    epochs = np.asarray(fusion_epochs_tdb_s, dtype=float)
    ordered = sorted(records, key=lambda r: r.t_tdb_s)
    fused: list[Estimate] = []
    outcomes: list[UpdateOutcome] = []
    update = without_duplicates(federated)
    i = 0
    for t in epochs:
        while i < len(ordered) and ordered[i].t_tdb_s <= t + 1e-9:
            outcomes.append(update(ordered[i]))
            i += 1
        fused.append(federated.fuse(float(t)))
    return fused, outcomes
