"""Faults injected into a run's measurement records, by name in the run file's ``[faults]`` table
or with ``opnav run --set faults.NAME=VALUE``.

Each fault acts on the records a study simulated (measurement or image mode), after the
simulation and before the filters, drawn from its own generator (the run's seed and a fixed
stream), so the same run file and seed give the same faults. What was done is counted in the
summary's ``facts.faults``, and the records each filter refused are listed with their reasons in
``filters/<name>.json`` and the report: a fault either shows up there or in the consistency
flags, never silently in the answer.

Not here yet: time-tag faults (a clock offset, jitter: the truth must then be evaluated at the
wrong tags) and the frame-level faults (hot-pixel clusters, cosmic-ray storms, stray light,
false stars, a wrong a-priori attitude, a flipped camera axis), which act on rendered frames.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from ..records import Measurement


@dataclass(frozen=True)
class Faults:
    """Record faults (all off by default).

    Attributes
    ----------
    outlier_fraction : float
        Share of records whose value is moved by ``outlier_sigma`` standard deviations of their
        own covariance, in a random direction (a false match, a cosmic ray on a centroid).
    outlier_sigma : float
        Size of an outlier, in sigmas (default 100).
    dropped_fraction : float
        Share of records removed (lost frames or telemetry).
    """

    outlier_fraction: float = 0.0
    outlier_sigma: float = 100.0
    dropped_fraction: float = 0.0

    def __post_init__(self) -> None:
        for name in ("outlier_fraction", "dropped_fraction"):
            value = getattr(self, name)
            if not (np.isfinite(value) and 0.0 <= value < 1.0):
                raise InputError(f"faults.{name} must be in [0, 1), got {value!r}")
        if not (np.isfinite(self.outlier_sigma) and self.outlier_sigma > 0.0):
            raise InputError(f"faults.outlier_sigma must be positive, got {self.outlier_sigma!r}")

    @property
    def active(self) -> bool:
        return self != Faults()


def apply_faults(records: list[Measurement], faults: Faults, seed: int) -> tuple[list[Measurement], dict]:
    """``records`` with ``faults`` applied (time order kept), and what was done."""
    if not faults.active:
        return records, {}
    rng = np.random.default_rng([seed, 77])
    count = len(records)
    keep = rng.random(count) >= faults.dropped_fraction
    outlier = (rng.random(count) < faults.outlier_fraction) & keep
    out = []
    for i, record in enumerate(records):
        if not keep[i]:
            continue
        value = np.array(record.value, dtype=float)
        if outlier[i]:
            direction = rng.standard_normal(record.size)
            direction /= np.linalg.norm(direction)
            # along a unit direction in the whitened space: exactly outlier_sigma sigmas
            value = value + faults.outlier_sigma * np.linalg.cholesky(record.covariance) @ direction
        out.append(replace(record, value=value))
    facts = {"records_dropped": int(np.sum(~keep)), "outliers": int(np.sum(outlier)),
             "outliers_at": [{"t_tdb_s": records[i].t_tdb_s, "kind": records[i].kind, "target": records[i].target}
                             for i in np.flatnonzero(outlier)][:1000]}
    return out, facts


def faults_from_values(values: dict, source: str) -> Faults:
    """A :class:`Faults` from a ``[faults]`` table and ``faults.NAME`` overrides, each key checked."""
    from .settings import build_settings

    fields = {f.name for f in dataclasses.fields(Faults)}
    unknown = sorted(set(values) - fields)
    if unknown:
        raise InputError(f"{source}: unknown fault(s) {unknown}; known: {sorted(fields)}")
    return build_settings(Faults, values, source)
