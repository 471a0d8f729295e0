"""Quick campaign runs: each seed simulated and filtered as ``opnav run --seed`` does it, keeping its figures.

A Monte Carlo campaign wants each run's figures and per-epoch NEES, not its measurement
files, OEMs and report (its replay command writes those). A quick run is the runner's own
simulation and filter stages (:func:`opnav.filters.navigate.navigate`, whose single-run
EKF and UKF are compiled: a few microseconds a record) with the runner's own figures
(:func:`opnav.studies.common.filter_metrics`, :func:`opnav.filters.monitor.check_history`),
so a campaign run and its replay give the same numbers to the last bit
(``tests/studies/test_montecarlo.py`` checks it), and a run does not depend on the other runs of its
task: seeds may go to any worker in any grouping.

What a quick run keeps is its ``summary.json`` (figures, seed, the command that replays it,
under ``quick``) and, per filter, ``nees/<name>.npz``: the epochs (``t_tdb_s``, TDB s), the
NEES at each (``nees``, :func:`opnav.studies.common.track`'s values) and the run's hash
(``hash``), which the campaign's Monte Carlo NEES test reads, and the errors and 1-sigmas
(``error``, ``sigma``, (E, 6) km and km/s in single precision) the campaign page plots
(:mod:`opnav.studies.report_campaign`). The posterior Cramér-Rao bound along the truth
(:func:`posterior_bound`) is the campaign's, computed once (the runs share the truth).

Runs that need their files or the image stage (image mode, injected faults) go through
:func:`opnav.studies.runner.run_study`; :func:`quick_runs_apply` says which.
States are ``[r km, v km/s]``, ICRF, about ``Simulation.center``; epochs TDB s past J2000.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..filters.estimates import save_npz
from ..filters.monitor import check_history
from ..filters.navigate import navigate
from ..files import atomic_write_text
from .common import Simulation, filter_metrics, measurements_summary, track
from .runner import MAX_LISTED, digest
from .settings import RunFile


def quick_runs_apply(run: RunFile, mode: str) -> bool:
    """Whether the runs of ``run`` in ``mode`` can go as quick runs (before simulating): measurement
    mode, no injected faults and a study that simulates records (not S2/S4's own evaluation)."""
    from . import STUDIES

    return mode == "measurements" and STUDIES[run.study].generic_filters and (
        run.faults is None or not run.faults.active)


def quick_key(run: RunFile, filters: tuple[str, ...]) -> str:
    """Content hash of one quick run's result (run identity, filters, opnav version)."""
    return digest({"run": run.describe(), "filters": list(filters), "opnav": __version__, "stage": "quick"})


def nees_path(folder: Path, name: str) -> Path:
    """A quick run's per-epoch NEES file for filter ``name`` (module notes)."""
    return Path(folder) / "nees" / f"{name}.npz"


def finished(folder: Path, key: str) -> dict | None:
    """The quick run's summary in ``folder`` if it was made from ``key``."""
    try:
        summary = json.loads((Path(folder) / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    return summary if summary.get("quick", {}).get("hash") == key else None


def run_quick(runs: list[RunFile], folders: list[Path], filters: tuple[str, ...], replay: list[str],
              simulated: Callable[[int, Simulation], None] | None = None) -> list[dict]:
    """Each run simulated and filtered (module notes), its ``summary.json`` and NEES files written;
    finished runs are read back. ``replay[k]`` is the command line that replays run k. ``simulated(k, sim)``,
    when given, is called with run k's simulation before its filters run (a campaign computes its posterior
    bound from the first run's). Returns the summaries in order."""
    summaries = []
    for k, (run, folder, command) in enumerate(zip(runs, folders, replay)):
        key = quick_key(run, filters)
        summary = finished(folder, key)
        if summary is None:
            summary = _quick_run(run, Path(folder), filters, command, key,
                                 None if simulated is None else lambda sim, k=k: simulated(k, sim))
        summaries.append(summary)
    return summaries


def _quick_run(run: RunFile, folder: Path, filters: tuple[str, ...], replay: str, key: str,
               simulated: Callable[[Simulation], None] | None = None) -> dict:
    sim, simulate_s = _simulate(run)
    stages = {"simulate": simulate_s}
    if simulated is not None:
        simulated(sim)
    figures = {}
    for name in filters:
        figures[name] = _filter_figures(name, sim, folder, key)
        stages[f"filter {name}"] = figures[name]["wall_s"]
    return write_quick_summary(run, folder, _simulation_facts(sim), figures, stages, key, replay)


def _simulate(run: RunFile) -> tuple[Simulation, float]:
    """The run's simulation and its wall time, s."""
    from . import STUDIES

    begin = time.perf_counter()
    sim = STUDIES[run.study].simulate(run.settings, run.seed)
    return sim, time.perf_counter() - begin


def _simulation_facts(sim: Simulation) -> dict:
    """What a quick run's summary says of its simulation."""
    return {"measurements": measurements_summary(sim), "window_start_tdb_s": sim.window_start_tdb_s,
            "paper": sim.paper, "facts": sim.facts}


def write_quick_summary(run: RunFile, folder: Path, facts: dict, figures: dict, stages: dict, key: str,
                        replay: str) -> dict:
    """A quick run's ``summary.json`` (module notes): ``facts`` of its simulation, each filter's ``figures``
    (in the run's order of filters), the ``stages``' walls; returns the summary."""
    summary = {"run": run.describe(), "mode": "measurements", "opnav": __version__, **facts,
               "filters": figures, "stages_wall_s": stages, "quick": {"hash": key, "replay": replay}}
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder / "summary.json", json.dumps(summary, indent=2, default=float))
    return summary


def run_quick_filter(run: RunFile, folder: Path, filters: tuple[str, ...], name: str) -> dict:
    """One filter of a quick run (a campaign splits a run's filters over its workers): the run simulated, filter
    ``name`` run and its per-epoch file written as :func:`run_quick` does; the summary is not written
    (:func:`write_quick_summary`, once every filter is done). Returns ``{"facts", "figures", "simulate_s"}``."""
    sim, simulate_s = _simulate(run)
    figures = _filter_figures(name, sim, Path(folder), quick_key(run, filters))
    return {"facts": _simulation_facts(sim), "figures": figures, "simulate_s": simulate_s}


def _filter_figures(name: str, sim: Simulation, folder: Path, key: str) -> dict:
    """Filter ``name`` over ``sim``: what :func:`opnav.studies.runner.filter_stage` records, and the
    per-epoch NEES file (written before ``summary.json``, so a finished run has it)."""
    result = navigate(sim.records, sim.navigation, filter_name=name, force_model=sim.force_model, center=sim.center)
    history = result.history
    arrays = track(history, sim)
    consistency = check_history(history, final_nees=float(arrays["nees"][-1]))
    refused = [{"t_tdb_s": float(r.t_tdb_s), "kind": r.kind, "target": r.target, "reason": reason}
               for r, ok, reason in zip(sorted(sim.records, key=lambda r: r.t_tdb_s), history.accepted, history.reasons)
               if not ok]
    # error and sigma in single precision: the campaign page plots them (report_campaign), at half the size
    save_npz(nees_path(folder, name), t_tdb_s=arrays["t_tdb_s"], nees=arrays["nees"], hash=np.str_(key),
             error=arrays["error"].astype(np.float32), sigma=arrays["sigma"].astype(np.float32))
    record = {"filter": name, "wall_s": result.wall_s, **filter_metrics(history, sim),
              "consistency": consistency.to_dict(), "refused": refused[:MAX_LISTED], "refused_count": len(refused)}
    if history.health is not None:
        record["covariance_health"] = history.health
    return record


def posterior_bound(sim: Simulation) -> dict | None:
    """Posterior Cramér-Rao bound along ``sim``'s truth (:func:`opnav.filters.crb.pcrb_along`), with the
    navigation's own P0, R and process noise, as a root mean square over the study window: position
    ``sqrt(mean_t tr P_B(t)[:3, :3])`` km and velocity likewise in m/s, the same RMS as a run's
    ``position_rms_km`` and ``velocity_rms_m_s`` (:func:`opnav.studies.common.filter_metrics`), which
    the RMS over seeds of those figures cannot fall below on average (:mod:`opnav.studies.bound_ratio`;
    ``tests/studies/test_posterior_bound.py`` holds it against the batch information of the initial
    state). None when the navigation treats the ephemeris error as consider parameters (a bound covers
    estimated states)."""
    from ..filters.crb import pcrb_along
    from ..filters.factory import build_filter, measurement_model

    nav = sim.navigation
    if nav.ephemeris_error == "consider":
        return None
    ungated = replace(nav, gate_probability=None)
    # the bodies the filters measure come from the force model's ephemeris (a mission's kernels), as in navigate
    model = measurement_model(ungated, sim.center, ephemeris=getattr(sim.force_model, "ephemeris", None))
    ekf = build_filter("ekf", ungated, model, sim.force_model)
    covariances = pcrb_along(ekf, sim.records, nav.t0_tdb_s, sim.start_truth, nav.augmented[1], sim.epochs, sim.truth)
    window = sim.epochs >= sim.window_start_tdb_s
    position = np.sqrt(np.trace(covariances[window, :3, :3], axis1=1, axis2=2))
    velocity = np.sqrt(np.trace(covariances[window, 3:6, 3:6], axis1=1, axis2=2))
    return {"pcrb_position_km": float(np.sqrt(np.mean(position**2))),
            "pcrb_velocity_m_s": float(1e3 * np.sqrt(np.mean(velocity**2)))}
