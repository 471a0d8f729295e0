"""Monte Carlo campaigns of a run file: N seeds through the runner, on dask.distributed, aggregated.

Run ``i`` is the run file with seed ``seed + i`` (recorded, so ``opnav run RUNFILE --seed S``
replays it alone) written by :func:`opnav.studies.runner.run_study` into ``DIR/run_NNN``.
Each run's stages are saved atomically under their content hashes, so an interrupted campaign
resumes: finished runs are read back, unfinished ones continue from their last stage.

Runs of studies that simulate records in measurement mode (S1, S3) go as quick runs
(:mod:`opnav.studies.campaign_runs`: the runner's own simulation, filters and figures, so the
same numbers as each seed's replay, keeping only ``summary.json`` and the per-epoch NEES);
the posterior Cramér-Rao bound along the truth (``DIR/posterior_bound.json``) is made from the first
seed's own simulation, inside that seed's task (the runs share the truth).
Other runs (image mode, faults, S2/S4, ``quick=False``) go through the runner with all their files.
Tasks of ``batch`` seeds (default 1) go to ``workers`` single-threaded local processes (a
``ProcessPoolExecutor`` forked from this one when that is safe: :class:`_Pool`), or to an existing
dask.distributed scheduler (``dask scheduler`` and ``dask worker ADDRESS`` on other machines sharing
the output folder); with ``workers = 1`` and no scheduler they run in this process. On workers the
task that makes the bound goes first, then the other runs, and the page's figures (a task per filter
and one for the RMS histogram) as soon as the runs are done, so that they are drawn side by side.
A run does not depend on the other runs of its task, so the figures are the same on any number of
workers and with any batch. ``campaign.json``'s ``timeline`` says where and when each task ran.

``DIR/campaign.json`` holds ``{"runs": [...], "aggregate": {...}}``: per run its seed and each
filter's figures; per filter the mean, standard deviation, minimum and maximum of the position
and velocity RMS, the mean NEES, the mean final 1-sigma, the count of runs with consistency
flags, and ``monte_carlo_nees``, the Monte Carlo NEES test. ``DIR/campaign.md`` (and
``campaign.html``) shows the aggregate beside the study's published figures, and one line per
filter: "Monte Carlo NEES: mean over N runs at each of E epochs of the window: M (95 % band
[lo, hi]); share of epochs inside: S".

That line is the consistency test of the campaign (:func:`opnav.consistency.ensemble_nees`,
Bar-Shalom et al. Sec. 5.4.2). The per-run "NEES mean" is not one: a run's epochs share one
estimation error, and a mean of run means says nothing about their spread. Instead the NEES
(6 states) of the N runs is averaged at each epoch of the study window they all have, and that
mean is compared with the 95 % interval of the mean of N chi-square(6) values: a consistent
filter has about 95 % of the E epochs inside (S near 0.95); a filter whose covariance is too
small has its mean above the band, one whose covariance is too large below it. Each run's
per-epoch NEES comes from its ``filters/<name>.npz`` (runs through the runner) or
``nees/<name>.npz`` (quick runs, :mod:`opnav.studies.campaign_runs`); when one is missing or
unreadable the entry is ``{"available": false, "reason": ...}`` and the line says why.
Studies with their own evaluation (S2, S4) have no per-epoch NEES and no such entry.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..consistency import ensemble_nees
from ..errors import InputError, OpnavError
from ..files import atomic_write_text, folder_lock
from .common import NEES_STATES
from .report import flat_items, markdown_page
from .report_campaign import DRAW_HERE, figure_calls, filter_blocks_from_files, rms_histogram, write_campaign_page
from .campaign_runs import finished, nees_path, posterior_bound, quick_key, quick_runs_apply, run_quick
from .runner import RunOptions, run_study
from .settings import check_filters, load_run_file

_log = logging.getLogger(__name__)


def replay_command(path: str, overrides: dict, seed: int, filters, mode) -> str:
    """The ``opnav run`` command line that replays one campaign run alone."""
    parts = ["opnav run", str(path), "--seed", str(seed), *(f"--set {k}={v}" for k, v in overrides.items())]
    if filters:
        parts += ["--filters", ",".join(filters)]
    if mode:
        parts += ["--mode", mode]
    return " ".join(parts + ["--out DIR"])


def _run_batch(path: str, overrides: dict, seeds: list[int], folders: list[str], filters, mode: str | None,
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
    """The compiled kernels on one thread (:func:`opnav.compiled.use_one_thread`): a dask worker shares
    the machine with the other workers."""
    from ..compiled import use_one_thread

    use_one_thread()


#: The campaign folder's file of the posterior Cramér-Rao bound (with the hash of the run it was made for).
BOUND_FILE = "posterior_bound.json"


def _bound_file(path: str, overrides: dict, seed: int, out: str) -> tuple[str, Path]:
    """(hash, file) of the campaign's posterior bound: the run of ``seed`` it follows, where it is kept."""
    from .runner import digest

    run = load_run_file(path, {**overrides, "seed": str(seed)})
    return digest({"run": run.describe(), "opnav": __version__, "stage": "posterior bound"}), Path(out) / BOUND_FILE


def _saved_bound(key: str, target: Path) -> tuple[bool, dict | None]:
    """(True, bound) when ``target`` holds the bound of hash ``key`` (a resumed campaign), else (False, None)."""
    try:
        saved = json.loads(target.read_text())
        if saved.get("hash") == key:
            return True, saved["bound"]
    except (OSError, ValueError, AttributeError, KeyError):
        pass
    return False, None


def _make_bound(sim, key: str, target: Path) -> dict | None:
    """The posterior bound along ``sim``'s truth (:func:`opnav.studies.campaign_runs.posterior_bound`), saved
    with its hash; None when the study has no truth start or the navigation takes consider parameters."""
    bound = posterior_bound(sim) if sim.start_truth is not None else None
    atomic_write_text(target, json.dumps({"hash": key, "bound": bound}, indent=2))
    return bound


def _bound_task(path: str, overrides: dict, seed: int, out: str, single_thread: bool = False) -> dict | None:
    """Worker task: the posterior Cramér-Rao bound along the campaign's truth (the runs share the truth, so
    the first seed's simulation stands for all), saved in ``out/BOUND_FILE`` and read back when it was made
    for the same run (:func:`_make_bound`). A campaign makes it inside its first seed's run
    (:func:`_runs_and_bound`); this simulates that seed again, for a campaign whose first run was finished."""
    if single_thread:
        _one_thread()
    from . import STUDIES

    key, target = _bound_file(path, overrides, seed, out)
    found, bound = _saved_bound(key, target)
    if found:
        return bound
    run = load_run_file(path, {**overrides, "seed": str(seed)})
    return _make_bound(STUDIES[run.study].simulate(run.settings, run.seed), key, target)


def _runs_and_bound(task: tuple, bound: tuple, single_thread: bool = False) -> tuple[list[dict], dict | None]:
    """Worker task: a task of runs (``_run_batch`` arguments) whose first seed is the bound's (``_bound_task``
    arguments), and the bound made from that seed's own simulation (it follows the truth, which the run
    simulates anyway: a second simulation of it was a third of a run's time). Returns (summaries, bound)."""
    key, target = _bound_file(*bound)
    found, made = _saved_bound(key, target)
    made = {"bound": made} if found else {}

    def simulated(k: int, sim) -> None:
        if k == 0 and not made:
            made["bound"] = _make_bound(sim, key, target)

    summaries = _run_batch(*task[:7], single_thread, simulated)
    if not made:  # its first run was finished before: the bound from a simulation of its own
        made["bound"] = _bound_task(*bound, single_thread)
    return summaries, made["bound"]


def _timed(function, *arguments):
    """Worker task: ``function(*arguments)`` and when and where it ran: (result, {"worker": process id,
    "start", "end": Unix time, s, "cpu_s": the process's CPU seconds in it})."""
    start, cpu = time.time(), time.process_time()
    result = function(*arguments)
    return result, {"worker": os.getpid(), "start": start, "end": time.time(), "cpu_s": time.process_time() - cpu}


def _finished_batch(task: tuple) -> list[dict] | None:
    """The summaries of a quick task whose runs are all finished (a resumed campaign), else None."""
    path, overrides, seeds, folders, filters, _, quick = task
    if not quick:
        return None
    runs = [load_run_file(path, {**overrides, "seed": str(seed)}) for seed in seeds]
    names = check_filters(filters or runs[0].filters, runs[0].path)
    done = [finished(Path(folder), quick_key(run, names)) for run, folder in zip(runs, folders)]
    return done if all(summary is not None for summary in done) else None


@dataclass(frozen=True)
class _Plan:
    """One campaign's runs, cut into worker tasks: ``tasks`` of ``_run_batch`` arguments (up to
    ``batch`` seeds each) and, for quick runs, ``bound``: the ``_bound_task`` arguments (else None)."""

    path: str
    overrides: dict
    out: Path
    seeds: list[int]
    folders: list[str]
    tasks: list[tuple]
    study: str
    mode: str
    bound: tuple | None


def _plan(path: str, runs: int, out: Path, overrides: dict, filters, mode: str | None, quick: bool,
          batch: int, first_seed: int = 0) -> _Plan:
    """The campaign's runs: seeds ``seed + first_seed + i`` for ``i < runs`` (``seed`` the run file's)."""
    base = load_run_file(path, overrides)  # validates everything before any work
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    run_mode = mode or base.mode
    check_filters(filters or base.filters, base.path)
    quick = quick and quick_runs_apply(base, run_mode)
    seeds = [base.seed + first_seed + i for i in range(runs)]
    folders = [str(out / f"run_{i:03d}") for i in range(runs)]
    tasks = [(str(path), overrides, seeds[i:i + batch], folders[i:i + batch], filters, mode, quick)
             for i in range(0, runs, batch)]
    bound = (str(path), overrides, seeds[0], str(out)) if quick else None
    return _Plan(str(path), overrides, out, seeds, folders, tasks, base.study, run_mode, bound)


def _progress_reporter(progress: bool, log: Callable[[str], None] | None) -> Callable[[str], None]:
    """Where a campaign's progress lines go: ``log`` (None: this module's logger at INFO); nowhere
    unless ``progress``."""
    if not progress:
        return lambda message: None
    return log if log is not None else (lambda message: _log.info("%s", message))


def _execute(plans: list[_Plan], *, workers: int, scheduler: str | None, report: Callable[[str], None],
             finish: Callable[[list[_Done]], object]):
    """Run the plans' tasks (in this process, on ``workers`` local processes or on ``scheduler``), then return
    ``finish(done)``, ``done`` per plan (:class:`_Done`). ``report`` gets a line after each task of runs.

    A plan's posterior bound is made inside the task of its first seed, from that run's simulation
    (:func:`_runs_and_bound`). On workers that task goes first (it is the longest), then the other runs; as
    soon as a plan's runs and bound are done its page figures go out, a task per filter and one for the RMS
    histogram (:func:`opnav.studies.report_campaign.filter_blocks_from_files`, ``rms_histogram``), so that
    they are drawn side by side at the end instead of one after the other in this process. Every task's
    worker, start, end and CPU time go into ``_Done.timeline``."""
    runs = [(k, i) for k, plan in enumerate(plans) for i in range(len(plan.tasks))]
    results: dict[tuple[int, int], list[dict]] = {}
    for k, i in runs:
        summaries = _finished_batch(plans[k].tasks[i])
        if summaries is not None:
            results[k, i] = summaries
    total = sum(len(plan.seeds) for plan in plans)
    done = sum(len(summaries) for summaries in results.values())
    if done:
        report(f"[campaign] {done}/{total} runs done")
    pending = [(k, i) for k, i in runs if (k, i) not in results]
    bounds: dict[int, dict | None] = {}
    aggregates: dict[int, dict] = {}
    drawn: dict[int, dict[str, list]] = {k: {} for k in range(len(plans))}
    histograms: dict[int, object] = {}
    # where the time goes: this process's start-up and planning before the first task (CPU seconds since the
    # process started), every task, and (``_write_campaign``) the page
    timeline: dict = {"tasks": [], "parent": {"worker": os.getpid(), "start": time.time(),
                                              "cpu_s": time.process_time()}}

    def summaries_of(k: int) -> list[dict] | None:
        """Plan ``k``'s summaries in seed order once all its runs are done, else None."""
        parts = [results.get((k, i)) for i in range(len(plans[k].tasks))]
        return None if any(part is None for part in parts) else [s for part in parts for s in part]

    def outcome() -> object:
        return finish([_Done(summaries_of(k), bounds.get(k), aggregates[k], drawn[k], histograms.get(k, DRAW_HERE),
                             timeline) for k in range(len(plans))])

    def with_bound(k: int, i: int) -> bool:
        """Whether task ``i`` of plan ``k`` makes the plan's bound (its first task, quick runs)."""
        return i == 0 and plans[k].bound is not None

    def ran(kind: str, what, timing: dict) -> None:
        timeline["tasks"].append({"task": kind, "what": what, **timing})

    if (scheduler is None and workers == 1) or not pending:
        # one local worker, or every run finished (the bound read back or made here)
        for k, i in pending:
            arguments = plans[k].tasks[i]
            if with_bound(k, i):
                (results[k, i], bounds[k]), timing = _timed(_runs_and_bound, arguments, plans[k].bound)
            else:
                results[k, i], timing = _timed(_run_batch, *arguments)
            ran("runs+bound" if with_bound(k, i) else "runs", arguments[2], timing)
            done += len(arguments[2])
            report(f"[campaign] {done}/{total} runs done")
        for k, plan in enumerate(plans):
            aggregates[k] = _campaign_aggregate(plan, summaries_of(k))
            if plan.bound is not None and k not in bounds:
                bounds[k], timing = _timed(_bound_task, *plan.bound)
                ran("bound", plan.bound[2], timing)
        return outcome()
    pool = _Pool(workers, scheduler)
    try:
        what: dict[object, tuple] = {}
        waiting: set = set()

        def submit(function, arguments: tuple, meaning: tuple) -> None:
            future = pool.submit(_timed, function, *arguments)
            what[future] = meaning
            waiting.add(future)

        def page_tasks(k: int) -> None:
            """Plan ``k``'s aggregate, and its page figures submitted (its runs and bound are done)."""
            aggregates[k] = _campaign_aggregate(plans[k], summaries_of(k))
            for call in figure_calls(aggregates[k], plans[k].folders, summaries_of(k)):
                submit(filter_blocks_from_files, call, ("figures", k, call[0]))
            record = _campaign_record(plans[k], _Done(summaries_of(k), bounds.get(k), aggregates[k], {}), 0.0)
            submit(rms_histogram, (record,), ("histogram", k, None))

        def ready(k: int) -> bool:
            return summaries_of(k) is not None and (plans[k].bound is None or k in bounds) and k not in aggregates

        # the tasks that make a bound first (the longest), then the other runs, in seed order
        for k, i in sorted(pending, key=lambda ki: not with_bound(*ki)):
            if with_bound(k, i):
                submit(_runs_and_bound, (plans[k].tasks[i], plans[k].bound, True), ("runs+bound", k, i))
            else:
                submit(_run_batch, (*plans[k].tasks[i], True), ("runs", k, i))
        for k, plan in enumerate(plans):
            if plan.bound is not None and (k, 0) not in pending:  # its first run finished before
                submit(_bound_task, (*plan.bound, True), ("bound", k, None))
            if ready(k):  # resumed with every run of this plan finished
                page_tasks(k)
        while waiting:
            finished_now, _ = pool.wait(waiting)
            for future in finished_now:
                waiting.discard(future)
                kind, k, detail = what.pop(future)
                value, timing = _result(future)
                if kind in ("runs", "runs+bound"):
                    if kind == "runs+bound":
                        value, bounds[k] = value
                    results[k, detail] = value
                    done += len(plans[k].tasks[detail][2])
                    report(f"[campaign] {done}/{total} runs done")
                    ran(kind, plans[k].tasks[detail][2], timing)
                elif kind == "bound":
                    bounds[k] = value
                    ran(kind, plans[k].bound[2], timing)
                elif kind == "histogram":
                    histograms[k] = value
                    ran(kind, k, timing)
                else:
                    drawn[k][detail] = value
                    ran(kind, detail, timing)
                if ready(k):
                    page_tasks(k)
        pool.close()  # its processes end while the pages are written
        return outcome()
    finally:
        pool.close(cancel=True)


def _result(future):
    """The future's result; a local worker process that ended without one (killed, out of memory) is one
    line, not a traceback."""
    from concurrent.futures.process import BrokenProcessPool

    try:
        return future.result()
    except BrokenProcessPool:
        raise OpnavError("a campaign worker process ended abruptly (killed, or out of memory); the runs it "
                         "finished are kept: run the same command again to resume") from None


class _Pool:
    """Where a campaign's tasks run: ``workers`` single-threaded local processes (a ``ProcessPoolExecutor``,
    forked from this one when that is safe: :func:`_fork_safe`), or the dask scheduler at ``scheduler``.

    Local processes take the tasks in the order they were submitted, each as soon as it is free. A forked
    process starts at once with this process's modules (a spawned one imports opnav again); a dask
    ``LocalCluster`` did the same work with ~0.25 s of CPU to import dask.distributed and 0.6 s of wall
    to start its scheduler and nannies before the first task (at load ~11), which a 4-run campaign on 2
    workers waits for."""

    def __init__(self, workers: int, scheduler: str | None) -> None:
        self.client = None
        self.executor = None
        self.order = 0
        if scheduler is not None:
            self.client = _client(scheduler)
        else:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            method = "fork" if _fork_safe() else "spawn"
            self.executor = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context(method))

    def submit(self, function, *arguments):
        if self.executor is not None:
            return self.executor.submit(function, *arguments)
        self.order += 1  # dask runs higher priorities first: the order of submission, as the local processes
        return self.client.submit(function, *arguments, pure=False, priority=-self.order)

    def wait(self, futures: set) -> tuple[set, set]:
        """(done, not done) once at least one of ``futures`` is done."""
        if self.executor is not None:
            from concurrent.futures import FIRST_COMPLETED, wait

            return wait(futures, return_when=FIRST_COMPLETED)
        from dask.distributed import wait

        done, pending = wait(list(futures), return_when="FIRST_COMPLETED")
        return set(done), set(pending)

    def close(self, cancel: bool = False) -> None:
        """Let the local processes end (without waiting for them unless ``cancel``: then queued tasks are
        dropped and they are waited for), or close the client of the scheduler."""
        if self.executor is not None:
            self.executor.shutdown(wait=cancel, cancel_futures=cancel)
        elif self.client is not None:
            self.client.close()
            self.client = None


@dataclass(frozen=True)
class _Done:
    """One plan's outcome: its runs' ``summaries`` in seed order, its posterior ``bound`` (None without),
    its ``aggregate`` (with the Monte Carlo NEES tests), the page figures ``drawn`` on the workers (per
    filter, :func:`opnav.studies.report_campaign.filter_blocks_from_files`; those missing are drawn when the
    page is written), its RMS ``histogram`` drawn on a worker (``DRAW_HERE``: not drawn yet) and the
    campaign's ``timeline``: ``tasks``, every task's kind, seeds or figure, worker process, start and end
    (Unix time) and CPU seconds; ``parent``, this process when the tasks started (its CPU seconds since it
    started: its start-up and planning)."""

    summaries: list[dict]
    bound: dict | None
    aggregate: dict
    drawn: dict[str, list]
    histogram: object = DRAW_HERE
    timeline: dict = dataclasses.field(default_factory=dict)


def _fork_safe() -> bool:
    """Whether worker processes may be forked from this one: numba has not started its thread pool here
    (a forked child would take the pool for started, without its threads, and its parallel kernels
    would wait for them forever). A campaign command has not run a kernel when it starts its workers."""
    import sys

    parallel = sys.modules.get("numba.np.ufunc.parallel")
    return parallel is None or getattr(parallel, "_is_initialized", True) is False


def _numeric_leaves(figures: dict):
    """(dotted key, value) of every finite number in a run's figures for one filter."""
    for key, value in flat_items(figures):
        if isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value):
            yield key, float(value)


def _stats(values) -> dict:
    values = np.asarray(values, dtype=float)
    return {"mean": float(values.mean()), "std": float(values.std(ddof=1)) if values.size > 1 else 0.0,
            "min": float(values.min()), "max": float(values.max())}


def _aggregate(summaries: list[dict]) -> dict:
    """Per filter: mean, std, min and max of every figure all its runs report (dotted keys for
    nested ones, e.g. ``final.position_sigma_km`` or S2's ``MPS (model 2).position_error_mean_km``),
    and the runs with consistency flags or unusable answers."""
    out: dict = {}
    names = sorted({name for s in summaries for name in s.get("filters", {})})
    for name in names:
        runs = [s["filters"][name] for s in summaries if name in s.get("filters", {})]
        leaves = [dict(_numeric_leaves(r)) for r in runs]
        common = [key for key in leaves[0] if all(key in leaf for leaf in leaves)]
        entry: dict = {"runs": len(runs)}
        entry.update({key: _stats([leaf[key] for leaf in leaves]) for key in common})
        if "final.position_sigma_km" in entry:
            entry["final_position_sigma_km_mean"] = entry["final.position_sigma_km"]["mean"]
        checks = [r.get("consistency") for r in runs if r.get("consistency")]
        entry["runs_with_flags"] = int(sum(bool(c["flags"]) for c in checks))
        entry["runs_unusable"] = int(sum(not c["usable"] for c in checks))
        out[name] = entry
    return out


#: Aggregate key of a filter's Monte Carlo NEES test, and the coverage of its band.
MONTE_CARLO_KEY = "monte_carlo_nees"
MONTE_CARLO_PROBABILITY = 0.95


def run_nees_arrays(folder: Path, name: str, summary: dict) -> tuple[np.ndarray, np.ndarray]:
    """Epochs (TDB s) and per-epoch NEES of filter ``name`` in one campaign run's ``folder``.

    A quick run's ``nees/<name>.npz`` (its hash must be the summary's), else the runner's
    ``filters/<name>.npz``. Raises :class:`~opnav.errors.InputError` naming the file and what
    to do when it is missing, unreadable or another run's.
    """
    quick = summary.get("quick")
    if quick:
        path = nees_path(folder, name)
        remedy = f"delete {Path(folder) / 'summary.json'} and resume to recompute the run"
    else:  # the runner checks this file's checksum on resume and filters again when it fails
        path = Path(folder) / "filters" / f"{name}.npz"
        remedy = "resume the campaign to filter the run again"
    if not path.is_file():
        raise InputError(f"{path} is missing ({remedy})")
    try:
        with np.load(path) as data:
            epochs, values = np.asarray(data["t_tdb_s"]), np.asarray(data["nees"])
            made_by = str(data["hash"]) if quick else None
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path} cannot be read: {exc} ({remedy})") from None
    if quick and made_by != quick.get("hash"):
        raise InputError(f"{path} was written by another run than {Path(folder) / 'summary.json'} ({remedy})")
    return epochs, values


def _monte_carlo_nees(plan: _Plan, summaries: list[dict]) -> dict[str, dict]:
    """Per filter, the Monte Carlo NEES test over the campaign's runs (module notes), or why not."""
    from . import STUDIES

    if not STUDIES[plan.study].generic_filters:
        return {}
    # seeds do not move the study window; should they ever, judge only epochs inside every run's
    start = max(float(s["window_start_tdb_s"]) for s in summaries)
    out = {}
    for name in sorted({name for s in summaries for name in s.get("filters", {})}):
        try:
            arrays = [run_nees_arrays(Path(folder), name, s) for folder, s in zip(plan.folders, summaries)
                      if name in s.get("filters", {})]
            test = ensemble_nees(arrays, NEES_STATES, start, MONTE_CARLO_PROBABILITY)
            out[name] = {"available": True, **test.to_dict(), "window_start_tdb_s": start}
        except InputError as exc:
            out[name] = {"available": False, "reason": str(exc)}
    return out


def monte_carlo_line(name: str, test: dict) -> str:
    """The campaign's one line on filter ``name``'s Monte Carlo NEES test (module notes)."""
    if not test.get("available"):
        return f"{name}: Monte Carlo NEES: not available ({test.get('reason', 'no reason recorded')})"
    low, high = test["band"]
    return (f"{name}: Monte Carlo NEES: mean over {test['runs']} runs at each of {test['epochs']} epochs of the "
            f"window: {test['mean']:.2f} ({100 * test['probability']:g} % band [{low:.2f}, {high:.2f}]); "
            f"share of epochs inside: {test['share_inside']:.2f}")


def _monte_carlo_cell(test: dict | None) -> str:
    """A sweep table's cell: the run-averaged NEES and the share of epochs inside its band."""
    if not test or not test.get("available"):
        return "n/a"
    return f"{test['mean']:.2f} ({test['share_inside']:.2f})"


def campaign_table(aggregate: dict) -> list[str]:
    """Markdown rows of a campaign's aggregate: the RMS table of S1 and S3, or one row per figure."""
    if aggregate and all("position_rms_km" in a for a in aggregate.values()):
        lines = ["| filter | position RMS (km) mean ± std [min, max] | velocity RMS (m/s) mean ± std | NEES mean | "
                 "final 1-sigma (km) | runs with flags |", "|---|---|---|---|---|---|"]
        for name, a in aggregate.items():
            p, v = a["position_rms_km"], a["velocity_rms_m_s"]
            lines.append(f"| {name} | {p['mean']:.3f} ± {p['std']:.3f} [{p['min']:.3f}, {p['max']:.3f}] | "
                         f"{v['mean']:.4f} ± {v['std']:.4f} | {a['nees_mean']['mean']:.2f} | "
                         f"{a.get('final_position_sigma_km_mean', float('nan')):.3f} | "
                         f"{a['runs_with_flags']}/{a['runs']} |")
        return lines
    lines = ["| filter | figure | mean ± std | [min, max] |", "|---|---|---|---|"]
    for name, a in aggregate.items():
        for key, value in a.items():
            if isinstance(value, dict) and key not in ("wall_s", MONTE_CARLO_KEY):
                lines.append(f"| {name} | {key} | {value['mean']:.6g} ± {value['std']:.3g} | "
                             f"[{value['min']:.6g}, {value['max']:.6g}] |")
    return lines


def run_campaign(path: str, *, runs: int, out: Path, overrides: dict | None = None, filters=None,
                 mode: str | None = None, workers: int = 1, scheduler: str | None = None,
                 progress: bool = False, quick: bool = True, batch: int = 1,
                 log: Callable[[str], None] | None = None, command: tuple[str, ...] | None = None) -> dict:
    """Run ``runs`` seeds of run file ``path`` into ``out`` (module notes); returns the campaign record.

    ``quick`` runs keep each run's figures and per-epoch NEES only when the study allows it
    (:mod:`opnav.studies.campaign_runs`); ``False`` runs each seed through the runner with all its files.
    ``batch``: seeds per worker task (1: each seed its own task, which spreads a campaign over any
    number of workers). ``progress``: a line (``[campaign] k/N runs done``) after each task, to
    ``log`` (None: this module's logger at INFO). ``command``: the command line (argv) for the page's
    provenance (None from Python).
    """
    _check_counts(runs, workers, batch)
    plan = _plan(path, runs, out, dict(overrides or {}), filters, mode, quick, batch)
    with folder_lock(plan.out):  # two campaigns into one folder would mix their runs
        tic = time.perf_counter()

        def finish(done: list[_Done]) -> dict:
            return _write_campaign(plan, done[0], time.perf_counter() - tic, command)

        return _execute([plan], workers=workers, scheduler=scheduler, report=_progress_reporter(progress, log),
                        finish=finish)


def _check_counts(runs: int, workers: int, batch: int) -> None:
    for name, value in (("--runs", runs), ("--workers", workers), ("--batch", batch)):
        if int(value) != value or value < 1:
            raise InputError(f"{name} must be a positive integer, got {value}")
    most = MAX_WORKERS_PER_CORE * (os.cpu_count() or 1)
    if workers > most:
        raise InputError(f"--workers {workers}: at most {most} local worker processes on this machine "
                         f"({MAX_WORKERS_PER_CORE} per core; use --scheduler for a cluster of machines)")


#: Local worker processes a campaign may start per core (more only wait for the cores and their memory).
MAX_WORKERS_PER_CORE = 4
#: Seconds a campaign waits for a ``--scheduler`` to answer.
SCHEDULER_TIMEOUT_S = 20.0


def check_scheduler_address(address: str) -> str:
    """``address`` as dask takes it (``tcp://HOST:PORT``; ``HOST:PORT`` gets ``tcp://``), or InputError
    saying what is accepted."""
    text = address.strip()
    if "://" not in text:
        text = f"tcp://{text}"
    protocol, _, rest = text.partition("://")
    host, colon, port = rest.rpartition(":")
    if protocol not in ("tcp", "tls") or not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"--scheduler {address!r}: expected HOST:PORT or tcp://HOST:PORT with a port in "
                         "1-65535 (the address `dask scheduler` prints)")
    return text


def _client(scheduler: str):
    """A dask ``Client`` of the scheduler at ``scheduler``, which must answer within :data:`SCHEDULER_TIMEOUT_S`
    (else InputError naming the address)."""
    from dask.distributed import Client

    address = check_scheduler_address(scheduler)
    try:
        return Client(address, timeout=SCHEDULER_TIMEOUT_S)
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(f"--scheduler {scheduler}: no dask scheduler answered there within "
                         f"{SCHEDULER_TIMEOUT_S:g} s ({type(exc).__name__}); start one with `dask scheduler` "
                         "and give the address it prints") from None


def _campaign_aggregate(plan: _Plan, summaries: list[dict]) -> dict:
    """The campaign's aggregate of ``summaries`` (:func:`_aggregate`) with each filter's Monte Carlo NEES test."""
    aggregate = _aggregate(summaries)
    for name, test in _monte_carlo_nees(plan, summaries).items():
        aggregate[name][MONTE_CARLO_KEY] = test
    return aggregate


def _campaign_record(plan: _Plan, done: _Done, wall_s: float) -> dict:
    """The campaign's record (``campaign.json``) of one plan's outcome ``done``; ``wall_s``: the runs' wall time."""
    summaries = done.summaries
    record = {
        "run_file": plan.path, "overrides": plan.overrides, "study": plan.study, "mode": plan.mode,
        "runs": [{"seed": seed, "folder": folder, "filters": s.get("filters", {}),
                  **({"replay": s["quick"]["replay"]} if "quick" in s else {})}
                 for seed, folder, s in zip(plan.seeds, plan.folders, summaries)],
        "aggregate": done.aggregate, "paper": summaries[0].get("paper", {}),
        "quick_runs": sum("quick" in s for s in summaries),
        "wall_s": wall_s,
    }
    if done.bound:  # the bound follows the truth, which no seed changes
        record["posterior_crb"] = done.bound
    return record


def _write_campaign(plan: _Plan, done: _Done, wall_s: float, command: tuple[str, ...] | None = None) -> dict:
    """``campaign.json``, ``campaign.md`` and ``campaign.html`` of one campaign (atomically; the page:
    :func:`opnav.studies.report_campaign.write_campaign_page`, with the figures ``done.drawn`` and
    ``done.histogram``); ``done.bound``: the posterior Cramér-Rao bound along the truth or None;
    ``command``: the command line (argv) for the provenance. ``wall_s``: the runs' wall time.
    ``campaign.json``'s ``timeline`` is ``done.timeline`` (:class:`_Done`) and the page's start and end (Unix
    time) and CPU seconds."""
    record = _campaign_record(plan, done, wall_s)
    page_start, page_cpu = time.time(), time.process_time()
    write_campaign_page(plan.out, record, plan.folders, done.summaries, command, done.drawn,
                        histogram=done.histogram)
    record["timeline"] = {**done.timeline, "page": {"worker": os.getpid(), "start": page_start, "end": time.time(),
                                                    "cpu_s": time.process_time() - page_cpu}}
    atomic_write_text(plan.out / "campaign.json", json.dumps(record, indent=2, default=float))
    return record


def parse_sweeps(pairs: list[str] | None) -> dict[str, list[str]]:
    """``["KEY=V1,V2", ...]`` -> ``{KEY: [V1, V2]}``; errors name the bad pair."""
    out: dict[str, list[str]] = {}
    for pair in pairs or []:
        key, sep, values = pair.partition("=")
        items = [v.strip() for v in values.split(",") if v.strip()]
        if not sep or not key.strip() or not items:
            raise InputError(f"--sweep expects KEY=V1,V2,..., got {pair!r}")
        if key.strip() in out:  # a second --sweep of one key replaced the first without a word
            raise InputError(f"--sweep {key.strip()} is given twice; give its values once: "
                             f"--sweep {key.strip()}={','.join(out[key.strip()] + items)}")
        out[key.strip()] = items
    return out


def run_sweep(path: str, *, sweeps: dict[str, list[str]], runs: int, out: Path, overrides: dict | None = None,
              filters=None, mode: str | None = None, workers: int = 1, scheduler: str | None = None,
              progress: bool = False, quick: bool = True, batch: int = 1,
              log: Callable[[str], None] | None = None, command: tuple[str, ...] | None = None) -> dict:
    """A campaign per point of the Cartesian product of ``sweeps`` (``DIR/KEY=V,KEY=V``), then one table.

    Every point's runs go to the same workers at once (one cluster for the sweep). Point ``k`` (in
    the order of the product) runs seeds ``seed + k * runs + i``: no two points share a seed.
    ``DIR/sweep.json`` lists each point's overrides and aggregate; ``DIR/sweep.md`` is one row per
    point and filter, with the Monte Carlo NEES test (the run-averaged NEES and the share of epochs
    inside its band), the study's published figure and the posterior Cramér-Rao bound beside ours.
    ``progress``, ``log`` and ``command`` as for :func:`run_campaign`.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with folder_lock(out):  # two sweeps into one folder would mix their campaigns
        return _run_sweep_in(path, sweeps=sweeps, runs=runs, out=out, overrides=overrides, filters=filters,
                             mode=mode, workers=workers, scheduler=scheduler, progress=progress, quick=quick,
                             batch=batch, log=log, command=command)


def _run_sweep_in(path: str, *, sweeps, runs, out: Path, overrides, filters, mode, workers, scheduler, progress,
                  quick, batch, log, command) -> dict:
    """:func:`run_sweep` once ``out`` is held."""
    import itertools

    _check_counts(runs, workers, batch)
    keys = list(sweeps)
    points = [dict(zip(keys, values)) for values in itertools.product(*(sweeps[k] for k in keys))]
    out = Path(out)
    # Each point its own seeds (point k: seed + k * runs + i): no common random numbers across the
    # table's rows, so two rows' figures are independent draws and their intervals can be compared.
    plans = [_plan(path, runs, out / ",".join(f"{k}={v}" for k, v in point.items()),
                   {**(overrides or {}), **point}, filters, mode, quick, batch, first_seed=k * runs)
             for k, point in enumerate(points)]
    tic = time.perf_counter()

    def finish(done: list[_Done]) -> tuple[list[dict], float]:
        wall = time.perf_counter() - tic
        rows = []
        for point, plan, outcome in zip(points, plans, done):
            record = _write_campaign(plan, outcome, wall, command)
            rows.append({"point": point, "aggregate": record["aggregate"], "paper": record["paper"],
                         "posterior_crb": record.get("posterior_crb")})
        return rows, wall

    rows, wall = _execute(plans, workers=workers, scheduler=scheduler, report=_progress_reporter(progress, log),
                          finish=finish)
    atomic_write_text(out / "sweep.json", json.dumps({"run_file": str(path), "runs": runs, "wall_s": wall,
                                                     "points": rows}, indent=2, default=float))
    lines = [f"# Sweep of {Path(path).name}: {runs} runs per point", "",
             "| " + " | ".join(keys) + " | filter | position RMS (km) mean ± std | velocity RMS (m/s) | NEES | "
             "Monte Carlo NEES (share of epochs in band) | final 1-sigma (km) | PCRB (km) | paper |",
             "|" + "---|" * (len(keys) + 8)]
    for row in rows:
        paper = row["paper"]
        shown = (f"{paper['position_rms_km']} km, {paper['velocity_rms_m_s']} m/s" if "position_rms_km" in paper
                 else "see summary")
        bound = f"{row['posterior_crb']['pcrb_position_km']:.3f}" if row["posterior_crb"] else "-"
        for name, a in row["aggregate"].items():
            if "position_rms_km" not in a:  # S2/S4 figures: the point's own table below
                continue
            p, v = a["position_rms_km"], a["velocity_rms_m_s"]
            lines.append("| " + " | ".join(row["point"][k] for k in keys) + f" | {name} | {p['mean']:.3f} ± "
                         f"{p['std']:.3f} | {v['mean']:.4f} ± {v['std']:.4f} | {a['nees_mean']['mean']:.2f} | "
                         f"{_monte_carlo_cell(a.get(MONTE_CARLO_KEY))} | "
                         f"{a['final_position_sigma_km_mean']:.3f} | {bound} | {shown} |")
    for row in rows:
        if not all("position_rms_km" in a for a in row["aggregate"].values()):
            lines += ["", "## " + ", ".join(f"{k} = {v}" for k, v in row["point"].items()), "",
                      *campaign_table(row["aggregate"])]
    atomic_write_text(out / "sweep.md", "\n".join(lines) + "\n")
    atomic_write_text(out / "sweep.html", markdown_page(f"Sweep {Path(path).name}", lines))
    return {"points": rows, "wall_s": wall}
