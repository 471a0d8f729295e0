"""Campaign runs in lockstep: K seeds of one run file through one vectorised pass of each filter.

A Monte Carlo campaign of a study whose runs all take the same record epochs and kinds
(S1: one RA/Dec of each moon every step) does not need K separate filter loops: each
seed is simulated exactly as ``opnav run --seed`` simulates it, its measured values go
into one ``(T, N, K, m)`` grid, and :func:`opnav.filters.lockstep.run_ekf_lockstep` /
:func:`~opnav.filters.lockstep.run_ukf_lockstep` advance the K filters together (one
integration and one measurement-model call per step). Each run's figures are those of
:func:`opnav.studies.common.posterior_metrics` and :func:`opnav.filters.monitor.check_records`,
the same functions the single-run stage uses on the same posteriors, so a campaign run
and its replay give the same numbers (``tests/test_montecarlo.py`` checks it).

What a lockstep run keeps is its ``summary.json`` (figures, seed, the command that
replays it) and, per filter, ``nees/<name>.npz``: the epochs (``t_tdb_s``, TDB s) and the
NEES at each (``nees``, the runner's :func:`opnav.studies.common.track` values) with the
run's lockstep hash (``hash``), which the campaign's Monte Carlo NEES test reads. It is not
``filters/<name>.npz``: that is the runner's file, whose errors, sigmas and NIS the report
plots. The per-run measurement files, OEM and report come from the replay. The lockstep
EKF also runs the posterior Cramer-Rao bound along the truth (one more row).

Runs that do not fit (image mode, faults, particle filters, a UKF over an augmented
state, records that differ from epoch to epoch or seed to seed) go through
:func:`opnav.studies.runner.run_study` one by one; :func:`lockstep_filters` says which.
States are ``[r km, v km/s]``, ICRF, about ``Simulation.center``; epochs TDB s past J2000.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .. import __version__
from ..consistency import nees
from ..filters.base import gate_message
from ..filters.ekf import EKFOptions, force_model_batch_propagator
from ..filters.estimates import save_npz
from ..filters.factory import measurement_model
from ..filters.lockstep import run_ekf_lockstep, run_ukf_lockstep
from ..filters.monitor import check_records
from ..filters.noise import process_noise_from_config
from ..records import atomic_write_text
from .common import NEES_STATES, Simulation, measurements_summary, posterior_metrics
from .runner import MAX_LISTED, digest
from .settings import RunFile

#: Filters with a lockstep implementation.
LOCKSTEP_FILTERS = ("ekf", "ukf")


def lockstep_filters(run: RunFile, filters: tuple[str, ...], mode: str) -> bool:
    """Whether the runs of ``run`` with ``filters`` in ``mode`` can go in lockstep (before simulating).

    Measurement mode, no injected faults, a study that simulates records (not S2/S4's own
    evaluation) and only filters of :data:`LOCKSTEP_FILTERS`. The records' layout is checked
    again on the simulations (:func:`record_grid`).
    """
    from . import STUDIES

    return (mode == "measurements" and STUDIES[run.study].generic_filters
            and (run.faults is None or not run.faults.active) and all(f in LOCKSTEP_FILTERS for f in filters))


def record_grid(sim: Simulation):
    """The records of ``sim`` as ``(templates, values)`` if every epoch has the same records, else None.

    ``templates`` are the T records of the first epoch (kind, target, sensor, star, covariance);
    ``values`` (T, N, m) the measured values at each of the N epochs of ``sim.epochs``.
    """
    records = sorted(sim.records, key=lambda r: r.t_tdb_s)
    n_epochs = sim.epochs.size
    if not records or len(records) % n_epochs:
        return None
    per_epoch = len(records) // n_epochs
    templates = records[:per_epoch]
    sizes = {r.size for r in templates}
    if len(sizes) != 1:
        return None
    values = np.empty((per_epoch, n_epochs, sizes.pop()))
    for i in range(n_epochs):
        group = records[i * per_epoch:(i + 1) * per_epoch]
        for j, (record, template) in enumerate(zip(group, templates)):
            if (record.t_tdb_s != sim.epochs[i] or record.kind != template.kind or record.target != template.target
                    or record.sensor != template.sensor or record.star_id != template.star_id
                    or not np.array_equal(record.covariance, template.covariance)):
                return None
            values[j, i] = record.value
    return templates, values


def _same_layout(sims: list[Simulation], grids) -> bool:
    """Every simulation has a record grid with the first one's epochs, templates and navigation set-up
    (all but the initial estimate and the seed)."""
    from .runner import navigation_json

    def setup(sim: Simulation) -> dict:
        return {k: v for k, v in navigation_json(sim.navigation).items() if k not in ("x0", "seed")}

    def layout(templates) -> list:
        return [(t.kind, t.target, t.sensor, t.star_id, t.covariance.tobytes()) for t in templates]

    first = sims[0]
    if grids[0] is None:
        return False
    reference = layout(grids[0][0])
    for sim, grid in zip(sims, grids):
        if grid is None or not np.array_equal(sim.epochs, first.epochs) or setup(sim) != setup(first):
            return False
        if layout(grid[0]) != reference:
            return False
    return True


def _run_filter_lockstep(name: str, sims: list[Simulation], templates, values: np.ndarray):
    """One filter over every simulation in lockstep: (history, wall_s)."""
    first = sims[0]
    nav = first.navigation
    model = measurement_model(nav, first.center)
    x0 = np.stack([sim.navigation.augmented[0] for sim in sims])
    P0 = nav.augmented[1]
    noise = process_noise_from_config(nav.process_noise)
    begin = time.perf_counter()
    if name == "ekf":
        consider = tuple(range(6, x0.shape[1])) if nav.ephemeris_error == "consider" else ()
        truth = None
        if first.start_truth is not None:
            # the bound rides along the true trajectory, augmented parameters (offsets) at zero
            truth = np.zeros((first.epochs.size + 1, x0.shape[1]))
            truth[0, :6], truth[1:, :6] = first.start_truth, first.truth
        history = run_ekf_lockstep(
            nav.t0_tdb_s, x0, P0, first.epochs, templates, values,
            propagator=force_model_batch_propagator(first.force_model, exact=nav.exact), model=model,
            process_noise=noise, options=EKFOptions(gate_probability=nav.gate_probability, consider=consider),
            truth=truth)
    else:
        from ..filters.ukf import force_model_transition

        history = run_ukf_lockstep(
            nav.t0_tdb_s, x0, P0, first.epochs, templates, values,
            transition=force_model_transition(first.force_model, exact=nav.exact), model=model,
            process_noise=noise, options=replace(nav.ukf, gate_probability=nav.gate_probability))
    return history, time.perf_counter() - begin


def _run_figures(name: str, k: int, history, sim: Simulation, templates, wall_s: float) -> dict:
    """Run ``k``'s record for filter ``name``: what :func:`opnav.studies.runner.filter_stage` records."""
    states, covs = history.states[:, k], history.covariances[:, k]
    index = np.arange(sim.epochs.size)
    accepted = history.accepted[:, :, k].reshape(-1)
    nis = history.nis[:, :, k].reshape(-1)
    dof = np.tile([t.size for t in templates], sim.epochs.size)
    metrics = posterior_metrics(index, states, covs, sim, accepted, nis, dof)
    final_nees = float(run_nees(history, k, sim)[-1])
    consistency = check_records(accepted, nis, dof, None, final_nees=final_nees)
    probability = sim.navigation.gate_probability
    refused = []
    for flat in np.flatnonzero(~accepted)[:MAX_LISTED]:
        i, j = divmod(int(flat), len(templates))
        reason = (gate_message(float(nis[flat]), probability, templates[j].size) if np.isfinite(nis[flat])
                  else "innovation covariance is not positive definite or innovation not finite")
        refused.append({"t_tdb_s": float(sim.epochs[i]), "kind": templates[j].kind, "target": templates[j].target,
                        "reason": reason})
    return {"filter": name, "wall_s": wall_s, **metrics, "consistency": consistency.to_dict(),
            "refused": refused, "refused_count": int((~accepted).sum())}


def run_nees(history, k: int, sim: Simulation) -> np.ndarray:
    """NEES of run ``k`` at each of ``sim.epochs``, as :func:`opnav.studies.common.track` takes it
    (the first :data:`~opnav.studies.common.NEES_STATES` states against ``sim.truth``)."""
    n = NEES_STATES
    return nees(history.states[:, k, :n], history.covariances[:, k, :n, :n], sim.truth)


def nees_path(folder: Path, name: str) -> Path:
    """A lockstep run's per-epoch NEES file for filter ``name`` (module notes)."""
    return Path(folder) / "nees" / f"{name}.npz"


def _save_run_nees(folder: Path, name: str, history, k: int, sim: Simulation, key: str) -> None:
    # written before summary.json, so a run the campaign finds finished has its file (or lost it since)
    save_npz(nees_path(folder, name), t_tdb_s=sim.epochs, nees=run_nees(history, k, sim), hash=np.str_(key))


def _bound(history, sim: Simulation) -> dict:
    """Posterior Cramer-Rao bound (1-sigma, RMS over the study window) from the lockstep EKF."""
    window = sim.epochs >= sim.window_start_tdb_s
    position = np.sqrt(np.trace(history.pcrb[window, :3, :3], axis1=1, axis2=2))
    velocity = np.sqrt(np.trace(history.pcrb[window, 3:6, 3:6], axis1=1, axis2=2))
    return {"pcrb_position_km": float(np.sqrt(np.mean(position**2))),
            "pcrb_velocity_m_s": float(1e3 * np.sqrt(np.mean(velocity**2)))}


def lockstep_key(run: RunFile, filters: tuple[str, ...]) -> str:
    """Content hash of one lockstep run's result (run identity, filters, opnav version)."""
    return digest({"run": run.describe(), "filters": list(filters), "opnav": __version__, "stage": "lockstep"})


def finished(folder: Path, key: str) -> dict | None:
    """The lockstep summary in ``folder`` if it was made from ``key``."""
    try:
        summary = json.loads((Path(folder) / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    return summary if summary.get("lockstep", {}).get("hash") == key else None


def run_lockstep(runs: list[RunFile], folders: list[Path], filters: tuple[str, ...], replay: list[str]) -> list[dict] | None:
    """Simulate each run, then run ``filters`` over all of them in lockstep; write each ``summary.json``.

    Returns the summaries in order, or None when the simulations do not share one record layout
    (the caller then runs them one by one). ``replay[k]`` is the command line that replays run k.
    The steps (:func:`simulate_batch`, :func:`filter_batch` per filter, :func:`write_batch`) are
    what a campaign on several workers runs as separate tasks, with the same figures.
    """
    batch = simulate_batch(runs, slim=False)
    if not lockstep_ready(batch, filters):
        return None
    results = {name: filter_batch(name, batch, runs, folders, filters) for name in filters}
    return write_batch(runs, folders, filters, batch, results, replay)


@dataclass(frozen=True)
class SimulatedBatch:
    """Simulations of consecutive seeds of one run file, as a lockstep batch's filters take them.

    Attributes
    ----------
    sims : list of Simulation
        One a seed; without their records and force model when made ``slim`` (:func:`simulate_batch`),
        to go to another process (:func:`filter_batch` makes the force model again).
    grids : list
        :func:`record_grid` of each simulation (None for one that has none).
    measurements : list of dict
        :func:`opnav.studies.common.measurements_summary` of each.
    wall_s : float
        Wall time of the simulations, s.
    """

    sims: list
    grids: list
    measurements: list
    wall_s: float


def simulate_batch(runs: list[RunFile], slim: bool = True) -> SimulatedBatch:
    """Simulate each run as ``opnav run --seed`` does (measurement mode); ``slim``: drop the records and
    the force model once the record grids are taken, so the batch pickles small."""
    from . import STUDIES

    study = STUDIES[runs[0].study]
    begin = time.perf_counter()
    sims = [study.simulate(run.settings, run.seed) for run in runs]
    wall = time.perf_counter() - begin
    grids = [record_grid(sim) for sim in sims]
    measurements = [measurements_summary(sim) for sim in sims]
    if slim:
        sims = [replace(sim, records=[], force_model=None) for sim in sims]
    return SimulatedBatch(sims, grids, measurements, wall)


def join_batches(parts: list[SimulatedBatch]) -> SimulatedBatch:
    """One batch of the seeds of ``parts``, in order (simulated in several tasks)."""
    return SimulatedBatch([sim for part in parts for sim in part.sims], [grid for part in parts for grid in part.grids],
                          [m for part in parts for m in part.measurements], sum(part.wall_s for part in parts))


def lockstep_ready(batch: SimulatedBatch, filters: tuple[str, ...]) -> bool:
    """Whether the batch's runs share one record layout and set-up (:func:`_same_layout`) and ``filters``
    have a lockstep form for their state (the lockstep UKF takes the six probe states only)."""
    if not _same_layout(batch.sims, batch.grids):
        return False
    return not ("ukf" in filters and batch.sims[0].navigation.augmented[0].size != 6)


def filter_batch(name: str, batch: SimulatedBatch, runs: list[RunFile], folders: list[Path],
                 filters: tuple[str, ...]) -> dict:
    """Filter ``name`` over every run of ``batch`` in lockstep: each run's figures (what
    :func:`opnav.studies.runner.filter_stage` records) and ``nees/<name>.npz`` written; returns
    ``{"figures": [per run], "wall_s": per run, "bound": posterior CRB or None}``."""
    from . import STUDIES

    sims = batch.sims
    if sims[0].force_model is None:  # a slim batch: the study's force model, as the simulation made it
        sims = [replace(sims[0], force_model=STUDIES[runs[0].study].dynamics(runs[0].settings)), *sims[1:]]
    templates = batch.grids[0][0]
    values = np.stack([grid[1] for grid in batch.grids], axis=2)  # (T, N, K, m)
    history, wall = _run_filter_lockstep(name, sims, templates, values)
    figures = []
    for k, sim in enumerate(sims):
        figures.append(_run_figures(name, k, history, sim, templates, wall / len(sims)))
        _save_run_nees(folders[k], name, history, k, sim, lockstep_key(runs[k], filters))
    bound = _bound(history, sims[0]) if history.pcrb is not None else None
    return {"figures": figures, "wall_s": wall / len(sims), "bound": bound}


def write_batch(runs: list[RunFile], folders: list[Path], filters: tuple[str, ...], batch: SimulatedBatch,
                results: dict[str, dict], replay: list[str]) -> list[dict]:
    """Each run's ``summary.json`` from its simulation and the :func:`filter_batch` result of every
    filter (in ``filters`` order); returns the summaries in order."""
    simulate_wall = batch.wall_s / len(runs)
    bound = None
    for name in filters:
        bound = results[name]["bound"] or bound
    summaries = []
    for k, (run, sim, folder) in enumerate(zip(runs, batch.sims, folders)):
        stages = {"simulate": simulate_wall}
        stages.update({f"filter {name} (lockstep)": results[name]["wall_s"] for name in filters})
        summary = {
            "run": run.describe(), "mode": "measurements", "opnav": __version__,
            "measurements": batch.measurements[k],
            "window_start_tdb_s": sim.window_start_tdb_s, "paper": sim.paper, "facts": sim.facts,
            "filters": {name: results[name]["figures"][k] for name in filters}, "stages_wall_s": stages,
            "lockstep": {"hash": lockstep_key(run, filters), "runs_together": len(runs), "replay": replay[k],
                         **({"bound": bound} if bound else {})},
        }
        Path(folder).mkdir(parents=True, exist_ok=True)
        atomic_write_text(Path(folder) / "summary.json", json.dumps(summary, indent=2, default=float))
        summaries.append(summary)
    return summaries
