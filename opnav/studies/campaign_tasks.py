"""What a campaign's workers run (:mod:`opnav.studies.campaign`): tasks of seeds, the posterior bound.

- :func:`run_batch`: seeds of the run file, as quick runs (:mod:`opnav.studies.campaign_runs`) or
  through the runner; finished runs are read back.
- The posterior Cramér-Rao bound along the truth (the runs share it, so the first seed's simulation
  stands for all), saved in ``DIR/posterior_bound.json`` with the hash of the run it follows, and read
  back when a resumed campaign finds it: :func:`runs_and_bound` makes it inside the first seed's run
  (one process: the campaign's own, or a dask worker); :func:`runs_keeping_simulation` keeps that
  simulation in the worker's memory for :func:`bound_from_kept`, sent to the same local worker once
  the runs are handed out, so that the bound fills the end of the campaign beside the page's figures
  instead of lengthening one worker's share of the runs; :func:`bound_task` simulates the first seed
  again (a campaign whose first run was finished before).
- :func:`timed`: a task with where and when it ran (``campaign.json``'s ``timeline``).

A task's figures do not depend on where it runs or with which others: the same on any number of
workers and with any batch.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from .. import __version__
from ..files import atomic_write_text
from .campaign_runs import finished, posterior_bound, quick_key, run_quick, run_quick_filter, write_quick_summary
from .campaign_workers import keep, kept
from .runner import RunOptions, run_study
from .settings import check_filters, load_run_file

#: The campaign folder's file of the posterior Cramér-Rao bound (with the hash of the run it was made for).
BOUND_FILE = "posterior_bound.json"


def replay_command(path: str, overrides: dict, seed: int, filters, mode) -> str:
    """The ``opnav run`` command line that replays one campaign run alone."""
    parts = ["opnav run", str(path), "--seed", str(seed), *(f"--set {k}={v}" for k, v in overrides.items())]
    if filters:
        parts += ["--filters", ",".join(filters)]
    if mode:
        parts += ["--mode", mode]
    return " ".join(parts + ["--out DIR"])


def run_batch(path: str, overrides: dict, seeds: list[int], folders: list[str], filters, mode: str | None,
              quick: bool, single_thread: bool = False, simulated=None) -> list[dict]:
    """Worker task: seeds of the run file, quietly, as quick runs when ``quick``
    (:mod:`opnav.studies.campaign_runs`, which calls ``simulated(k, sim)`` with each simulation it makes),
    else through the runner with all their files; returns their summaries. Finished runs are read back.

    ``single_thread``: the compiled kernels run on one thread (:func:`opnav.compiled.use_one_thread`;
    a worker process shares the machine with the other workers).
    """
    if single_thread:
        _one_thread()
    runs = [load_run_file(path, {**overrides, "seed": str(seed)}) for seed in seeds]
    if quick:
        names = check_filters(filters or runs[0].filters, runs[0].path)
        replay = [replay_command(path, overrides, seed, filters, mode) for seed in seeds]
        return run_quick(runs, [Path(f) for f in folders], names, replay, simulated)
    return [run_study(run, RunOptions(out=Path(folder), filters=filters, mode=mode, workers=1))
            for run, folder in zip(runs, folders)]


def _one_thread() -> None:
    """The compiled kernels on one thread (:func:`opnav.compiled.use_one_thread`): a worker shares the
    machine with the other workers."""
    from ..compiled import use_one_thread

    use_one_thread()


def bound_file(path: str, overrides: dict, seed: int, out: str) -> tuple[str, Path]:
    """(hash, file) of the campaign's posterior bound: the run of ``seed`` it follows, where it is kept."""
    from .runner import digest

    run = load_run_file(path, {**overrides, "seed": str(seed)})
    return digest({"run": run.describe(), "opnav": __version__, "stage": "posterior bound"}), Path(out) / BOUND_FILE


def saved_bound(key: str, target: Path) -> tuple[bool, dict | None]:
    """(True, bound) when ``target`` holds the bound of hash ``key`` (a resumed campaign), else (False, None)."""
    try:
        saved = json.loads(target.read_text())
        if saved.get("hash") == key:
            return True, saved["bound"]
    except (OSError, ValueError, AttributeError, KeyError):
        pass
    return False, None


def make_bound(sim, key: str, target: Path) -> dict | None:
    """The posterior bound along ``sim``'s truth (:func:`opnav.studies.campaign_runs.posterior_bound`), saved
    with its hash; None when the study has no truth start or the navigation takes consider parameters."""
    bound = posterior_bound(sim) if sim.start_truth is not None else None
    atomic_write_text(target, json.dumps({"hash": key, "bound": bound}, indent=2))
    return bound


def bound_task(path: str, overrides: dict, seed: int, out: str, single_thread: bool = False) -> dict | None:
    """Worker task: the posterior bound from a simulation of its own of the first seed, ``seed`` (module
    notes), or the saved one when it was made for the same run (:func:`make_bound`)."""
    if single_thread:
        _one_thread()
    from . import STUDIES

    key, target = bound_file(path, overrides, seed, out)
    found, bound = saved_bound(key, target)
    if found:
        return bound
    run = load_run_file(path, {**overrides, "seed": str(seed)})
    return make_bound(STUDIES[run.study].simulate(run.settings, run.seed), key, target)


def runs_and_bound(task: tuple, bound: tuple, single_thread: bool = False) -> tuple[list[dict], dict | None]:
    """Worker task: a task of runs (:func:`run_batch` arguments) whose first seed is the bound's
    (:func:`bound_task` arguments), and the bound made from that seed's own simulation (it follows the
    truth, which the run simulates anyway: a second simulation of it was a third of a run's time).
    Returns (summaries, bound)."""
    key, target = bound_file(*bound)
    found, made = saved_bound(key, target)
    made = {"bound": made} if found else {}

    def simulated(k: int, sim) -> None:
        if k == 0 and not made:
            made["bound"] = make_bound(sim, key, target)

    summaries = run_batch(*task[:7], single_thread, simulated)
    if not made:  # its first run was finished before: the bound from a simulation of its own
        made["bound"] = bound_task(*bound, single_thread)
    return summaries, made["bound"]


#: :func:`runs_keeping_simulation`'s word that this worker keeps the first seed's simulation for
#: :func:`bound_from_kept`, and that it has none (its first run was finished before).
KEPT, NOT_KEPT = "kept", "not kept"


def runs_keeping_simulation(task: tuple, bound: tuple, single_thread: bool = False) -> tuple[list[dict], object]:
    """Worker task: a task of runs (:func:`run_batch` arguments) whose first seed is the bound's
    (:func:`bound_task` arguments), keeping that seed's simulation in this process for
    :func:`bound_from_kept`. Returns (summaries, what of the bound): ``{"bound": ...}`` when it was saved
    before, :data:`KEPT`, or :data:`NOT_KEPT` when the first run was finished before (no simulation)."""
    key, target = bound_file(*bound)
    found, made = saved_bound(key, target)
    if found:
        return run_batch(*task[:7], single_thread), {"bound": made}
    held = []

    def simulated(k: int, sim) -> None:
        if k == 0:
            keep(key, sim)
            held.append(key)

    summaries = run_batch(*task[:7], single_thread, simulated)
    return summaries, KEPT if held else NOT_KEPT


def bound_from_kept(path: str, overrides: dict, seed: int, out: str, single_thread: bool = False) -> dict | None:
    """Worker task: the posterior bound from the simulation :func:`runs_keeping_simulation` kept in this
    process (then forgotten), else from a simulation of its own (:func:`bound_task`)."""
    key, target = bound_file(path, overrides, seed, out)
    sim = kept(key)
    if sim is None:
        return bound_task(path, overrides, seed, out, single_thread)
    return make_bound(sim, key, target)


def task_filters(task: tuple) -> tuple[str, ...]:
    """The names of the filters a task (:func:`run_batch` arguments) runs."""
    path, overrides, seeds, _, filters, _, _ = task
    run = load_run_file(path, {**overrides, "seed": str(seeds[0])})
    return check_filters(filters or run.filters, run.path)


def filter_part(task: tuple, name: str, single_thread: bool = False) -> dict:
    """Worker task: filter ``name`` of a quick task of one seed (:func:`run_batch` arguments), its other
    filters on other workers (:func:`opnav.studies.campaign_runs.run_quick_filter`); :func:`join_filter_parts`
    writes the run's summary once every filter is done."""
    if single_thread:
        _one_thread()
    path, overrides, seeds, folders, _, _, _ = task
    run = load_run_file(path, {**overrides, "seed": str(seeds[0])})
    return run_quick_filter(run, Path(folders[0]), task_filters(task), name)


def join_filter_parts(task: tuple, parts: dict[str, dict]) -> list[dict]:
    """The summaries of a quick task of one seed whose filters ran apart (:func:`filter_part`, ``parts`` by
    filter): its ``summary.json`` written as :func:`run_batch` writes it (the simulation's wall, the first
    filter's)."""
    path, overrides, seeds, folders, filters, mode, _ = task
    run = load_run_file(path, {**overrides, "seed": str(seeds[0])})
    names = task_filters(task)
    stages = {"simulate": parts[names[0]]["simulate_s"],
              **{f"filter {name}": parts[name]["figures"]["wall_s"] for name in names}}
    return [write_quick_summary(run, Path(folders[0]), parts[names[0]]["facts"],
                                {name: parts[name]["figures"] for name in names}, stages, quick_key(run, names),
                                replay_command(path, overrides, seeds[0], filters, mode))]


def timed(function, *arguments):
    """Worker task: ``function(*arguments)`` and when and where it ran: (result, {"worker": process id,
    "start", "end": Unix time, s, "cpu_s": the process's CPU seconds in it}). Then the ephemeris segments
    it fitted go to the store (:func:`opnav.ephemeris.cache.save_default_cache`: a worker process ends
    without running ``atexit``), so that the next process reads them."""
    from ..ephemeris.cache import save_default_cache

    start, cpu = time.time(), time.process_time()
    result = function(*arguments)
    save_default_cache()
    return result, {"worker": os.getpid(), "start": start, "end": time.time(), "cpu_s": time.process_time() - cpu}


def finished_batch(task: tuple) -> list[dict] | None:
    """The summaries of a quick task whose runs are all finished (a resumed campaign), else None."""
    path, overrides, seeds, folders, filters, _, quick = task
    if not quick:
        return None
    runs = [load_run_file(path, {**overrides, "seed": str(seed)}) for seed in seeds]
    names = check_filters(filters or runs[0].filters, runs[0].path)
    done = [finished(Path(folder), quick_key(run, names)) for run, folder in zip(runs, folders)]
    return done if all(summary is not None for summary in done) else None
