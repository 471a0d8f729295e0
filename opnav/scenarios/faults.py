"""Faults injected into a run's measurement records, by name in the run file's ``[faults]`` table
or with ``opnav run --set faults.NAME=VALUE``.

Each fault acts on the records a study simulated (measurement or image mode), after the
simulation and before the filters, drawn from its own generator (the run's seed and a fixed
stream), so the same run file and seed give the same faults. What was done is counted in the
summary's ``facts.faults``, and the records each filter refused are listed with their reasons in
``filters/<name>.json`` and the report: a fault either shows up there or in the consistency
flags, never silently in the answer.

Time-tag faults (``clock_offset_s``, ``time_jitter_s``) move each record's epoch tag and leave
its value as measured at the true time, which is what a wrong clock does; the run then takes the
truth at the tags (:func:`truth_at_tags`), so its errors are those of the estimates at the epochs
the filter believes.

Not here yet: the frame-level faults (hot-pixel clusters, cosmic-ray storms, stray light,
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
    clock_offset_s : float
        Added to every record's epoch tag, s (a clock offset).
    time_jitter_s : float
        1-sigma of a Gaussian error added to the epoch tag, one draw per measurement epoch (the
        records of one frame share it), s.
    """

    outlier_fraction: float = 0.0
    outlier_sigma: float = 100.0
    dropped_fraction: float = 0.0
    clock_offset_s: float = 0.0
    time_jitter_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("outlier_fraction", "dropped_fraction"):
            value = getattr(self, name)
            if not (np.isfinite(value) and 0.0 <= value < 1.0):
                raise InputError(f"faults.{name} must be in [0, 1), got {value!r}")
        if not (np.isfinite(self.outlier_sigma) and self.outlier_sigma > 0.0):
            raise InputError(f"faults.outlier_sigma must be positive, got {self.outlier_sigma!r}")
        if not np.isfinite(self.clock_offset_s):
            raise InputError(f"faults.clock_offset_s must be finite, got {self.clock_offset_s!r}")
        if not (np.isfinite(self.time_jitter_s) and self.time_jitter_s >= 0.0):
            raise InputError(f"faults.time_jitter_s must be >= 0, got {self.time_jitter_s!r}")

    @property
    def retags(self) -> bool:
        """Whether the faults move epoch tags."""
        return self.clock_offset_s != 0.0 or self.time_jitter_s > 0.0

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
    epochs = np.unique([r.t_tdb_s for r in records])
    shift = faults.clock_offset_s + faults.time_jitter_s * np.random.default_rng([seed, 78]).standard_normal(epochs.size)
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
        tag = record.t_tdb_s + float(shift[np.searchsorted(epochs, record.t_tdb_s)]) if faults.retags else record.t_tdb_s
        out.append(replace(record, value=value, t_tdb_s=tag))
    out.sort(key=lambda r: r.t_tdb_s)
    facts = {"records_dropped": int(np.sum(~keep)), "outliers": int(np.sum(outlier)),
             "outliers_at": [{"t_tdb_s": records[i].t_tdb_s, "kind": records[i].kind, "target": records[i].target}
                             for i in np.flatnonzero(outlier)][:1000]}
    if faults.retags:
        facts["time_tag_error_s"] = {"mean": float(shift.mean()), "rms": float(np.sqrt(np.mean(shift**2))),
                                     "max_abs": float(np.max(np.abs(shift)))}
    return out, facts


def truth_at_tags(epochs: np.ndarray, truth: np.ndarray, tags: np.ndarray) -> np.ndarray:
    """True states ``[r km, v km/s]`` (M, 6) at ``tags`` (TDB s) from states (N, 6) at ``epochs``,
    in the same frame and about the same origin as ``truth`` (the study's centre, ICRF).

    Cubic Hermite in position with the velocity as its derivative (the velocity is that
    spline's derivative): for the studies' steps (10-60 s) far below a kilometre-level error.
    Tags up to one step outside the arc are extrapolated; further out is an error.
    """
    from scipy.interpolate import CubicHermiteSpline

    epochs = np.asarray(epochs, dtype=float)
    tags = np.asarray(tags, dtype=float)
    step = float(np.min(np.diff(epochs))) if epochs.size > 1 else 0.0
    if epochs.size < 2 or tags.min() < epochs[0] - step or tags.max() > epochs[-1] + step:
        raise InputError("faulted time tags fall more than one step outside the simulated arc; "
                         "use a clock offset or jitter smaller than the measurement step")
    spline = CubicHermiteSpline(epochs, truth[:, :3], truth[:, 3:6])
    return np.hstack([spline(tags), spline.derivative()(tags)])


def faults_from_values(values: dict, source: str) -> Faults:
    """A :class:`Faults` from a ``[faults]`` table and ``faults.NAME`` overrides, each key checked."""
    from .settings import build_settings

    fields = {f.name for f in dataclasses.fields(Faults)}
    unknown = sorted(set(values) - fields)
    if unknown:
        raise InputError(f"{source}: unknown fault(s) {unknown}; known: {sorted(fields)}")
    return build_settings(Faults, values, source)
