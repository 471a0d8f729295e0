"""What every study hands the runner (:class:`Simulation`) and the figures taken from a filter run.

A study module (``s1.py``, ``s3.py``) turns its settings and a seed into a
:class:`Simulation`: the true states at the measurement epochs, the measurement
records, the navigation set-up (initial estimate, dynamics, noise) and the
window over which the study takes its RMS. :func:`filter_metrics` reduces a
filter's history to the figures of ``summary.json``.

States: ``[r km, v km/s]``, ICRF, relative to ``Simulation.center``; epochs TDB
seconds past J2000.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..consistency import chi2_interval, chi2_mean_bounds, nees, nees_band_share
from ..errors import CovarianceError
from ..filters.run import FilterHistory
from ..filters.options import NavigationConfig
from ..records import Measurement, split_radec_pairs

#: States the NEES is taken over, and so its degrees of freedom: position and velocity. Parameters a
#: filter augments its state with (ephemeris offsets) have no truth to be judged against.
NEES_STATES = 6


def measurements_summary(sim: Simulation) -> dict:
    """The ``measurements`` entry of a run's ``summary.json``: record count, epochs, kinds, the
    bodies observed (each of a ``radec_pair``'s two) and the first and last epoch (TDB s)."""
    return {"records": len(sim.records), "epochs": int(sim.epochs.size),
            "kinds": sorted({r.kind for r in sim.records}),
            "targets": sorted({r.target for r in split_radec_pairs(sim.records)}),
            "first_epoch_tdb_s": float(sim.epochs[0]), "last_epoch_tdb_s": float(sim.epochs[-1])}


#: Tracking events (acquisitions, losses of lock) listed in a run's facts; the counts cover all.
MAX_EVENTS_LISTED = 100


def tracking_facts(events: list[dict]) -> dict:
    """What the image stage's tracker did over a run (:class:`opnav.image.tracking.Tracker` ``events``):
    the counts of acquisitions, losses of lock and failed acquisitions, and the first events."""
    kinds = [event["event"] for event in events]
    return {"acquisitions": kinds.count("acquired"), "losses_of_lock": kinds.count("lost"),
            "failed_acquisitions": kinds.count("acquisition failed"), "events": events[:MAX_EVENTS_LISTED]}


@dataclass(frozen=True)
class Simulation:
    """One study run's truth, records and navigation set-up.

    Attributes
    ----------
    center : str
        Origin of every state.
    epochs : (N,) array
        Measurement epochs, increasing.
    truth : (N, 6) array
        True states at ``epochs``.
    records : list of Measurement
    navigation : NavigationConfig
        Initial estimate (truth plus a draw from P0), dynamics name, noise, gate, options.
    force_model : ForceModel
        The filters' dynamics (also the truth's, unless the study says otherwise).
    window_start_tdb_s : float
        Start of the window the study takes its RMS over (to the last epoch).
    paper : dict
        The study's published figures for this case (reports show them beside ours).
    facts : dict
        Anything else worth reporting (e.g. the star schedule).
    start_truth : (6,) array or None
        True state at ``navigation.t0_tdb_s`` when the study has it (the posterior Cramer-Rao
        bound of a lockstep campaign starts there).
    """

    center: str
    epochs: np.ndarray
    truth: np.ndarray
    records: list[Measurement]
    navigation: NavigationConfig
    force_model: object
    window_start_tdb_s: float
    paper: dict = field(default_factory=dict)
    facts: dict = field(default_factory=dict)
    start_truth: np.ndarray | None = None


def epoch_posteriors(history: FilterHistory, epochs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The estimate after the last record of each epoch: (index into ``epochs``, states, covariances)."""
    last = np.r_[history.epochs[1:] != history.epochs[:-1], True]
    index = np.searchsorted(epochs, history.epochs[last])
    if np.any(index >= epochs.size) or np.any(epochs[np.minimum(index, epochs.size - 1)] != history.epochs[last]):
        raise ValueError("history epochs are not measurement epochs of the simulation")
    return index, history.states[last], history.covariances[last]


def filter_metrics(history: FilterHistory, sim: Simulation) -> dict:
    """Figures of one filter run over ``sim``.

    ``position_rms_km`` / ``velocity_rms_m_s``: RMS of the error magnitude over the study
    window, and ``position_rms_rtn_km`` the RMS of each component in the true state's radial,
    along-track (transverse) and cross-track (orbit normal) directions, which shows the weak
    axis; ``converged_after_s``: time from the first epoch after which the position
    error stays within twice the window RMS; ``nees_mean``: mean NEES (6 states) over the
    window with the share of epochs inside the per-epoch chi-square(6) 95 % interval
    (``nees_fraction_in_95``), and the same over the whole arc (:func:`nees_figures`);
    ``nis_mean_per_dof``: the accepted records' NIS summed over their degrees of freedom,
    with the 95 % band of that ratio; ``final``: the last error and 1-sigma.
    """
    index, states, covs = epoch_posteriors(history, sim.epochs)
    return posterior_metrics(index, states, covs, sim, history.accepted, history.nis, history.dof)


def posterior_metrics(index: np.ndarray, states: np.ndarray, covs: np.ndarray, sim: Simulation,
                      accepted: np.ndarray, nis: np.ndarray, dof: np.ndarray) -> dict:
    """The figures of :func:`filter_metrics` from each epoch's posterior and the per-record NIS.

    ``index`` (M,) indexes ``sim.epochs`` for the posteriors ``states`` (M, n) and ``covs``
    (M, n, n); ``accepted``, ``nis`` and ``dof`` have one entry per record, in processing
    order (a lockstep campaign run has no per-record history but has these).
    """
    truth = sim.truth[index]
    t = sim.epochs[index]
    err = states[:, :6] - truth
    pos = np.linalg.norm(err[:, :3], axis=1)
    vel = np.linalg.norm(err[:, 3:6], axis=1)
    window = t >= sim.window_start_tdb_s
    pos_rms = float(np.sqrt(np.mean(pos[window] ** 2)))
    rtn = np.einsum("nij,nj->ni", rtn_axes(truth[window]), err[window, :3])
    values = epoch_nees(states, covs, truth, t)
    beyond = np.flatnonzero(pos > 2.0 * pos_rms)
    converged = float(t[beyond[-1] + 1] - t[0]) if beyond.size and beyond[-1] + 1 < t.size else (
        0.0 if not beyond.size else None)
    used = accepted & np.isfinite(nis)
    dof = dof[used]
    nis = nis[used]
    return {
        "position_rms_km": pos_rms,
        "position_rms_rtn_km": np.sqrt(np.mean(rtn**2, axis=0)).tolist(),
        "velocity_rms_m_s": float(1e3 * np.sqrt(np.mean(vel[window] ** 2))),
        "converged_after_s": converged,
        "nees_mean": float(values[window].mean()),
        "nees_fraction_in_95": nees_band_share(values[window], NEES_STATES, 0.95),
        **nees_figures(values, window),
        "nis_mean_per_dof": float(np.sum(nis) / np.sum(dof)) if nis.size else None,
        "nis_band95_per_dof": list(chi2_mean_bounds(1, int(np.sum(dof)), 0.95)) if nis.size else None,
        "accepted": int(accepted.sum()), "records": int(accepted.size),
        "final": {"position_error_km": float(pos[-1]), "position_sigma_km": float(np.sqrt(np.trace(covs[-1, :3, :3]))),
                  "velocity_error_m_s": float(1e3 * vel[-1]),
                  "velocity_sigma_m_s": float(1e3 * np.sqrt(np.trace(covs[-1, 3:6, 3:6])))},
    }


def epoch_nees(states: np.ndarray, covs: np.ndarray, truth: np.ndarray, t: np.ndarray) -> np.ndarray:
    """NEES of the first :data:`NEES_STATES` states at each epoch (``t`` TDB s past J2000, for the message).

    Raises
    ------
    CovarianceError
        A covariance that is not positive definite (a filter that diverged, e.g. under a process
        noise of 1e30 km^2/s^3): named by its first epoch instead of numpy's traceback.
    """
    block = covs[:, :NEES_STATES, :NEES_STATES]
    try:
        return nees(states[:, :NEES_STATES], block, truth)
    except np.linalg.LinAlgError:
        from ..epochs import describe_epoch

        bad = next(k for k in range(len(block)) if not _positive_definite(block[k]))
        raise CovarianceError(f"the filter's covariance at {describe_epoch(t[bad])} (epoch {bad + 1} of {len(block)}) "
                              "is not positive definite: the filter diverged, and its NEES has no meaning") from None


def _positive_definite(matrix: np.ndarray) -> bool:
    try:
        np.linalg.cholesky(matrix)
    except np.linalg.LinAlgError:
        return False
    return bool(np.all(np.isfinite(matrix)))


def nees_figures(values: np.ndarray, window: np.ndarray) -> dict:
    """NEES over the whole arc and over the RMS window, each with its bands.

    Parameters
    ----------
    values : (M,) array
        NEES of :data:`NEES_STATES` states at each epoch of the arc.
    window : (M,) bool array
        The epochs of the RMS window.

    Returns
    -------
    dict
        ``nees_band95``: the 95 % interval of one epoch's chi-square(6), the band the shares count
        against; for ``arc`` and ``window`` (``nees_mean_arc``, ``nees_fraction_in_95_arc`` and
        ``nees_epochs_arc``, the window's mean and share being ``nees_mean`` and
        ``nees_fraction_in_95``), the epochs and ``nees_band95_mean_<part>``: the 95 % band of the
        mean of that many *independent* chi-square(6) values. Successive epochs of one run are
        correlated, so the mean of a consistent filter spreads wider than that band: it bounds the
        mean only over independent runs; the share in the per-epoch band holds for any one run.
    """
    out = {"nees_band95": list(chi2_interval(NEES_STATES, 0.95)),
           "nees_mean_arc": float(values.mean()), "nees_fraction_in_95_arc": nees_band_share(values, NEES_STATES, 0.95)}
    for part, keep in (("arc", np.ones(values.size, bool)), ("window", window)):
        count = int(np.count_nonzero(keep))
        out[f"nees_epochs_{part}"] = count
        out[f"nees_band95_mean_{part}"] = list(chi2_mean_bounds(NEES_STATES, count, 0.95)) if count else None
    return out


def rtn_axes(states: np.ndarray) -> np.ndarray:
    """Rows radial, transverse, normal (N, 3, 3) of states ``[r km, v km/s]`` (N, 6), in their frame."""
    radial = states[:, :3] / np.linalg.norm(states[:, :3], axis=1, keepdims=True)
    normal = np.cross(states[:, :3], states[:, 3:6])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return np.stack([radial, np.cross(normal, radial), normal], axis=1)


def track(history: FilterHistory, sim: Simulation) -> dict[str, np.ndarray]:
    """Arrays for plots and the stage file.

    Per epoch (N): ``t_tdb_s``; ``error`` and ``sigma`` (N, 6), estimate minus truth and the filter's
    1-sigma, km and km/s, ICRF axes, origin ``sim.center``; ``error_rtn`` and ``sigma_rtn`` (N, 6) the
    same along the true state's radial, transverse and normal axes (:func:`rtn_axes`; the velocity
    error's components on those axes, not its rate in the rotating frame); ``nees``. Per record (K),
    in processing order: ``nis``, ``dof``, ``accepted``, ``record_t_tdb_s`` (the estimate's epoch),
    ``residual`` (K, m_max; innovations in record units, NaN-padded), ``residual_sigma`` (the square
    roots of the innovation covariance's diagonal, when the filter gives them), ``record_kind`` and
    ``record_target`` (indices into ``kind_names`` and ``target_names``).
    """
    index, states, covs = epoch_posteriors(history, sim.epochs)
    err = states[:, :6] - sim.truth[index]
    axes = rtn_axes(sim.truth[index])
    rtn_cov = [np.einsum("nij,njk,nlk->nil", axes, covs[:, b:b + 3, b:b + 3], axes) for b in (0, 3)]
    arrays = {
        "t_tdb_s": sim.epochs[index], "error": err, "sigma": np.sqrt(np.diagonal(covs, axis1=1, axis2=2))[:, :6],
        "nees": epoch_nees(states, covs, sim.truth[index], sim.epochs[index]),
        "error_rtn": np.concatenate([np.einsum("nij,nj->ni", axes, err[:, b:b + 3]) for b in (0, 3)], axis=1),
        "sigma_rtn": np.sqrt(np.concatenate([np.diagonal(c, axis1=1, axis2=2) for c in rtn_cov], axis=1)),
        "nis": history.nis, "dof": history.dof, "accepted": history.accepted, "record_t_tdb_s": history.epochs,
        "residual": history.residuals,
    }
    # kinds and targets as indices into their names: as text (4-byte characters) they took 3 MB of the
    # 17.7 MB of a 30-day S1 filter file
    for key, names in (("kind", history.kinds), ("target", history.targets)):
        unique, index = np.unique(np.asarray(names, dtype=str), return_inverse=True)
        arrays[f"{key}_names"], arrays[f"record_{key}"] = unique, index.astype(np.int32)
    if history.residual_sigmas is not None:
        arrays["residual_sigma"] = history.residual_sigmas
    return arrays
