"""Time registration: bring measurements of different sensors to common fusion epochs (S4).

Sensors on different clocks and rates do not sample at the fusion epochs of a
federated filter. Three ways of handing their data to it are offered, so their
effect can be compared:

- :func:`register` — three-point Lagrange interpolation/extrapolation (S4 eq. 12)
  of each measurement stream to each fusion epoch. For nodes ``t_0, t_1, t_2``
  with values ``z_j``, ``z(t) = sum_j L_j(t) z_j`` with
  ``L_j(t) = prod_{i != j} (t - t_i) / (t_j - t_i)``. Registered records carry
  :data:`opnav.records.FLAG_REGISTERED`.
- :func:`hold_latest` — what a fusion without registration does: the latest
  sample at or before each epoch is used as if it had been taken at the epoch
  (zero-order hold). A sensor whose data lead the fusion clock by ``dt`` then
  injects an error ``dz/dt * dt`` (for a position pseudo-measurement, the
  probe's velocity times the lead: ~25 km per second of lead at Mars approach).
- Processing every record at its own time tag (the exact reference): give the
  raw records to the filters, no function needed.

Registered covariance (documented inflation). The noise of the registered
value is ``sum_j L_j^2 R_j`` for independent node errors; extrapolation makes
``sum L_j^2 > 1`` (5.2 for nodes at -0.5, -1.5, -2.5 sample intervals). When the
epochs are denser than the samples, one raw sample is a node of several
registered records whose errors are then correlated; a filter that treats
them as independent would count that sample's information several times. The
covariance is therefore multiplied by ``u``, the largest number of registered
records any of its nodes enters: splitting each sample's information ``u`` ways
keeps the fused information at most that of the raw data (the covariance-
intersection argument). The interpolation truncation error
``z'''(xi)/6 prod (t - t_j)`` is not added; for a heliocentric position
pseudo-measurement sampled every 60 s it is below 1e-8 km.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from ..errors import InputError
from ..records import FLAG_REGISTERED, Measurement

log = logging.getLogger(__name__)


def lagrange_weights(t_nodes_tdb_s: np.ndarray, t_tdb_s: float) -> np.ndarray:
    """Weights ``L_j(t)`` (3,) of three-point Lagrange interpolation (S4 eq. 12).

    Parameters
    ----------
    t_nodes_tdb_s : (3,) array
        Distinct node epochs, TDB seconds past J2000.
    t_tdb_s : float
        Epoch to interpolate or extrapolate to.
    """
    t_nodes = np.asarray(t_nodes_tdb_s, dtype=float)
    if t_nodes.shape != (3,) or not np.all(np.isfinite(t_nodes)):
        raise InputError(f"t_nodes_tdb_s must be three finite epochs, got {t_nodes_tdb_s!r}")
    if len(np.unique(t_nodes)) != 3:
        raise InputError(f"t_nodes_tdb_s must be distinct, got {t_nodes.tolist()}")
    weights = np.ones(3)
    for j in range(3):
        for i in range(3):
            if i != j:
                weights[j] *= (t_tdb_s - t_nodes[i]) / (t_nodes[j] - t_nodes[i])
    return weights


def lagrange3(t_nodes_tdb_s: np.ndarray, values: np.ndarray, t_tdb_s: float) -> np.ndarray:
    """Three-point Lagrange value at ``t_tdb_s`` of ``values`` (3, m) given at ``t_nodes_tdb_s`` (3,)."""
    values = np.asarray(values, dtype=float)
    if values.shape[0] != 3:
        raise InputError(f"values must have three rows (one per node), got shape {values.shape}")
    return lagrange_weights(t_nodes_tdb_s, t_tdb_s) @ values.reshape(3, -1)


def _streams(records: Sequence[Measurement]) -> dict[tuple, list[Measurement]]:
    """Records grouped by what they measure (kind, target, sensor, star), sorted by epoch."""
    groups: dict[tuple, list[Measurement]] = defaultdict(list)
    for rec in records:
        groups[(rec.kind, rec.target, rec.sensor, rec.star_id)].append(rec)
    for key, group in groups.items():
        group.sort(key=lambda r: r.t_tdb_s)
        times = np.array([r.t_tdb_s for r in group])
        if np.any(np.diff(times) <= 0.0):
            raise InputError(f"stream {key}: two records share the epoch {times[np.argmin(np.diff(times))]:.3f} s")
    return groups


def _check_epochs(epochs_tdb_s: np.ndarray) -> np.ndarray:
    epochs = np.asarray(epochs_tdb_s, dtype=float)
    if epochs.ndim != 1 or not np.all(np.isfinite(epochs)) or np.any(np.diff(epochs) <= 0.0):
        raise InputError("epochs_tdb_s must be a 1-D, finite, strictly increasing array")
    return epochs


def _nodes(times: np.ndarray, t: float, causal: bool) -> np.ndarray | None:
    """Indices of the three nodes for epoch ``t`` (or ``None`` if the stream cannot supply them)."""
    if causal:
        last = np.searchsorted(times, t + 1e-9, side="right")  # samples at or before t
        return np.arange(last - 3, last) if last >= 3 else None
    if times.size < 3:
        return None
    nearest = np.argsort(np.abs(times - t), kind="stable")[:3]
    return np.sort(nearest)


def register(
    records: Sequence[Measurement],
    epochs_tdb_s: np.ndarray,
    *,
    causal: bool = True,
    max_extrapolation_s: float = np.inf,
) -> list[Measurement]:
    """Register each measurement stream to the fusion epochs by three-point Lagrange (S4 eq. 12).

    Parameters
    ----------
    records : sequence of Measurement
        Raw records; streams are told apart by (kind, target, sensor, star_id).
    epochs_tdb_s : (E,) array
        Increasing fusion epochs, TDB seconds past J2000.
    causal : bool
        True (real time): use the three latest samples at or before each epoch
        (extrapolation). False (post-processing): the three nearest (interpolation).
    max_extrapolation_s : float
        Skip an epoch that lies farther than this from the nearest node (logged).

    Returns
    -------
    list of Measurement
        Sorted by epoch. A sample whose epoch equals a fusion epoch is passed
        through unchanged; every other record has ``flags | FLAG_REGISTERED``,
        ``extra["lagrange_weights"]``, ``extra["node_epochs_tdb_s"]`` and the
        covariance ``u * sum_j L_j^2 R_j`` explained in the module notes. Angles
        are interpolated as numbers: streams must not wrap (RA near 0/2 pi)
        within three samples.
    """
    epochs = _check_epochs(epochs_tdb_s)
    if not max_extrapolation_s > 0.0:
        raise InputError(f"max_extrapolation_s must be positive, got {max_extrapolation_s}")
    out: list[Measurement] = []
    for key, stream in _streams(records).items():
        times = np.array([r.t_tdb_s for r in stream])
        plans = []
        for t in epochs:
            exact = np.flatnonzero(np.abs(times - t) <= 1e-9)
            if exact.size:
                plans.append((t, exact[:1], None))
                continue
            nodes = _nodes(times, t, causal)
            if nodes is None:
                continue
            if np.min(np.abs(times[nodes] - t)) > max_extrapolation_s:
                log.warning("stream %s: no sample within %.1f s of epoch %.3f s; not registered", key,
                            max_extrapolation_s, t)
                continue
            plans.append((t, nodes, lagrange_weights(times[nodes], t)))
        use = np.zeros(times.size, dtype=int)
        for _, nodes, _ in plans:
            use[nodes] += 1
        for t, nodes, weights in plans:
            if weights is None:
                out.append(stream[nodes[0]])
                continue
            value = weights @ np.stack([stream[i].value for i in nodes])
            cov = np.einsum("j,jab->ab", weights**2, np.stack([stream[i].covariance for i in nodes]))
            template = stream[nodes[-1]]
            out.append(replace(
                template,
                t_tdb_s=float(t),
                value=value,
                covariance=cov * int(np.max(use[nodes])),
                flags=template.flags | FLAG_REGISTERED,
                extra={**template.extra, "lagrange_weights": weights, "node_epochs_tdb_s": times[nodes]},
            ))
    out.sort(key=lambda r: r.t_tdb_s)
    return out


def hold_latest(records: Sequence[Measurement], epochs_tdb_s: np.ndarray) -> list[Measurement]:
    """Fusion without registration: the latest sample at or before each epoch, re-stamped to the epoch.

    Values and covariances are unchanged and no flag is set — this is the
    mistake registration corrects, kept for comparison. Each sample is used at
    most once (an epoch with no new sample gets nothing from that stream).
    """
    epochs = _check_epochs(epochs_tdb_s)
    out: list[Measurement] = []
    for stream in _streams(records).values():
        times = np.array([r.t_tdb_s for r in stream])
        latest = np.searchsorted(times, epochs + 1e-9, side="right") - 1
        taken = -1
        for t, index in zip(epochs, latest):
            if index > taken:
                out.append(replace(stream[index], t_tdb_s=float(t)))
                taken = index
    out.sort(key=lambda r: r.t_tdb_s)
    return out
