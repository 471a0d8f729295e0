"""Monte Carlo campaigns of a run file: N seeds through the runner, on local processes or dask, aggregated.

Run ``i`` is the run file with seed ``seed + i`` (recorded, so ``opnav run RUNFILE --seed S``
replays it alone) written by :func:`opnav.studies.runner.run_study` into ``DIR/run_NNN``.
Each run's stages are saved atomically under their content hashes, so an interrupted campaign
resumes: finished runs are read back, unfinished ones continue from their last stage.

Runs of studies that simulate records in measurement mode (S1, S3) go as quick runs
(:mod:`opnav.studies.campaign_runs`: the runner's own simulation, filters and figures, so the
same numbers as each seed's replay, keeping only ``summary.json`` and the per-epoch NEES);
the posterior Cramér-Rao bound along the truth (``DIR/posterior_bound.json``) is made from the first
seed's own simulation (the runs share the truth).
Other runs (image mode, faults, S2/S4, ``quick=False``) go through the runner with all their files.
Tasks of ``batch`` seeds (default 1) go to ``workers`` single-threaded local processes forked from this
one (:class:`opnav.studies.campaign_workers.LocalWorkers`), or to an existing dask.distributed scheduler
(``dask scheduler`` and ``dask worker ADDRESS`` on other machines sharing the output folder); with
``workers = 1`` and no scheduler they run in this process (:mod:`opnav.studies.campaign_tasks`). On local
workers each task goes to the worker free first; the worker of the first seed keeps its simulation and
makes the bound from it once the runs are handed out, while another draws the page's figures (a task per
filter, and one for the RMS histogram once the bound is known), so that the end of the campaign is shared
too (:func:`_run_on_workers`). A run does not depend on the other runs of its task, so the figures are the
same on any number of workers and with any batch. ``campaign.json``'s ``timeline`` says where and when
each task ran.

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
import importlib
import json
import logging
import os
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..consistency import ensemble_nees
from ..errors import InputError
from ..files import atomic_write_text, folder_lock
from .common import NEES_STATES
from .report import flat_items, markdown_page
from .campaign_runs import nees_path, quick_runs_apply
from .campaign_tasks import (KEPT, NOT_KEPT, bound_from_kept, bound_task, filter_part, finished_batch,
                             join_filter_parts, run_batch, runs_and_bound, runs_keeping_simulation, task_filters,
                             timed)
from .campaign_workers import LocalWorkers, SchedulerWorkers
from .report_campaign import (DRAW_HERE, FILTER_PARTS, figure_calls, filter_part_from_files, rms_histogram,
                              write_campaign_page)
from .settings import check_run_filters, load_run_file

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Plan:
    """One campaign's runs, cut into worker tasks: ``tasks`` of :func:`opnav.studies.campaign_tasks.run_batch`
    arguments (up to ``batch`` seeds each) and, for quick runs, ``bound``: the
    :func:`opnav.studies.campaign_tasks.bound_task` arguments (else None)."""

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
    check_run_filters(base, filters or base.filters)
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


class _Book:
    """What a campaign's tasks have given so far (:func:`_execute`): per plan its runs' summaries
    (``results[k, i]`` per task), its bound, aggregate, page figures and histogram, and the
    ``timeline``; ``report`` gets a line after each task of runs."""

    def __init__(self, plans: list[_Plan], report: Callable[[str], None]) -> None:
        self.plans, self.report = plans, report
        self.results: dict[tuple[int, int], list[dict]] = {}
        tasks = [(k, i) for k, plan in enumerate(plans) for i in range(len(plan.tasks))]
        for k, i in tasks:
            summaries = finished_batch(plans[k].tasks[i])
            if summaries is not None:
                self.results[k, i] = summaries
        self.total = sum(len(plan.seeds) for plan in plans)
        self.done = sum(len(summaries) for summaries in self.results.values())
        if self.done:
            report(f"[campaign] {self.done}/{self.total} runs done")
        # the tasks that make a bound first (the longest), then the other runs, in seed order
        self.pending = sorted(((k, i) for k, i in tasks if (k, i) not in self.results),
                              key=lambda ki: not self.with_bound(*ki))
        self.bounds: dict[int, dict | None] = {}
        self.aggregates: dict[int, dict] = {}
        self.drawn: dict[int, dict[str, list]] = {k: {} for k in range(len(plans))}
        self.parts: dict[tuple[int, str], dict[str, list]] = {}
        self.histograms: dict[int, object] = {}
        # where the time goes: this process's start-up and planning before the first task (CPU seconds since
        # the process started), every task, and (``_write_campaign``) the page
        self.timeline: dict = {"tasks": [], "parent": {"worker": os.getpid(), "start": time.time(),
                                                       "cpu_s": time.process_time()}}

    def with_bound(self, k: int, i: int) -> bool:
        """Whether task ``i`` of plan ``k`` makes the plan's bound (its first task, quick runs)."""
        return i == 0 and self.plans[k].bound is not None

    def summaries_of(self, k: int) -> list[dict] | None:
        """Plan ``k``'s summaries in seed order once all its runs are done, else None."""
        parts = [self.results.get((k, i)) for i in range(len(self.plans[k].tasks))]
        return None if any(part is None for part in parts) else [s for part in parts for s in part]

    def ran(self, kind: str, what, timing: dict) -> None:
        self.timeline["tasks"].append({"task": kind, "what": what, **timing})

    def figure_done(self, k: int, name: str, part: str, blocks: list, timing: dict) -> None:
        """Part ``part`` of filter ``name``'s page blocks drawn; the filter's blocks once all its parts are."""
        self.parts.setdefault((k, name), {})[part] = blocks
        if len(self.parts[k, name]) == len(FILTER_PARTS):
            self.drawn[k][name] = [block for p in FILTER_PARTS for block in self.parts[k, name][p]]
        self.ran("figures", [name, part], timing)

    def runs_done(self, k: int, i: int, summaries: list[dict], kind: str, timing: dict | None) -> None:
        self.results[k, i] = summaries
        self.done += len(self.plans[k].tasks[i][2])
        self.report(f"[campaign] {self.done}/{self.total} runs done")
        if timing is not None:  # (a run whose filters ran apart has their parts in the timeline)
            self.ran(kind, self.plans[k].tasks[i][2], timing)

    def splits(self, k: int, i: int) -> bool:
        """Whether task ``i`` of plan ``k`` can run its filters apart (:func:`_run_on_workers`): one seed, a
        quick run, not the bound's, two filters or more."""
        task = self.plans[k].tasks[i]
        return len(task[2]) == 1 and task[6] and not self.with_bound(k, i) and len(task_filters(task)) > 1

    def page_tasks(self, k: int) -> list[tuple]:
        """Plan ``k``'s page tasks that can start now and have not: (function, arguments, meaning). The
        filters' figures once its runs are done (with its aggregate, which they follow), the RMS histogram
        once its bound is known too."""
        summaries = self.summaries_of(k)
        if summaries is None:
            return []
        tasks = []
        if k not in self.aggregates:
            self.aggregates[k] = _campaign_aggregate(self.plans[k], summaries)
            # a figure a task, the longer (the error ensembles) first, so that the workers end together
            calls = figure_calls(self.aggregates[k], self.plans[k].folders, summaries)
            tasks += [(filter_part_from_files, (*call, part), ("figures", k, (call[0], part)))
                      for part in FILTER_PARTS for call in calls]
        if k not in self.histograms and (self.plans[k].bound is None or k in self.bounds):
            self.histograms[k] = None  # sent
            record = _campaign_record(self.plans[k], _Done(summaries, self.bounds.get(k), self.aggregates[k], {}), 0.0)
            tasks.append((rms_histogram, (record,), ("histogram", k, None)))
        return tasks

    def outcome(self) -> list[_Done]:
        return [_Done(self.summaries_of(k), self.bounds.get(k), self.aggregates[k], self.drawn[k],
                      self.histograms.get(k, DRAW_HERE), self.timeline) for k in range(len(self.plans))]


def _execute(plans: list[_Plan], *, workers: int, scheduler: str | None, report: Callable[[str], None],
             finish: Callable[[list[_Done]], object]):
    """Run the plans' tasks (in this process, on ``workers`` local processes or on ``scheduler``), then return
    ``finish(done)``, ``done`` per plan (:class:`_Done`). ``report`` gets a line after each task of runs.

    In this process a plan's posterior bound is made inside the task of its first seed, from that run's
    simulation (:func:`opnav.studies.campaign_tasks.runs_and_bound`), and the page is drawn at the end. On
    workers (:func:`_run_on_workers`) the runs go first, then the page's figures (a task per figure,
    :func:`opnav.studies.report_campaign.filter_part_from_files`, and one for the RMS histogram,
    ``rms_histogram``) as soon as a plan's runs are done, so that they are drawn side by side. Every
    task's worker, start, end and CPU time go into ``_Done.timeline``."""
    book = _Book(plans, report)
    if (scheduler is None and workers == 1) or not book.pending:
        # one local worker, or every run finished (the bound read back or made here)
        for k, i in book.pending:
            arguments = plans[k].tasks[i]
            if book.with_bound(k, i):
                (summaries, book.bounds[k]), timing = timed(runs_and_bound, arguments, plans[k].bound)
            else:
                summaries, timing = timed(run_batch, *arguments)
            book.runs_done(k, i, summaries, "runs+bound" if book.with_bound(k, i) else "runs", timing)
        for k, plan in enumerate(plans):
            book.aggregates[k] = _campaign_aggregate(plan, book.summaries_of(k))
            if plan.bound is not None and k not in book.bounds:
                book.bounds[k], timing = timed(bound_task, *plan.bound)
                book.ran("bound", plan.bound[2], timing)
        return finish(book.outcome())
    if scheduler is None:
        # the page's drawing library loaded once here, before the workers fork, rather than by each worker
        # in the campaign's last seconds, where they draw its figures (0.23 s of CPU each)
        importlib.import_module("matplotlib.figure")
        # the command's start-up and planning in the timeline end when the workers start
        book.timeline["parent"].update(start=time.time(), cpu_s=time.process_time())
    pool = LocalWorkers(workers) if scheduler is None else SchedulerWorkers(scheduler)
    try:
        _run_on_workers(book, pool, keeps=scheduler is None)
        pool.close()  # its processes end while the pages are written
        return finish(book.outcome())
    finally:
        pool.close(cancel=True)


def _run_on_workers(book: _Book, pool, keeps: bool) -> None:
    """The pending tasks of ``book`` on ``pool`` (:mod:`opnav.studies.campaign_workers`), each sent to a
    free worker: a standalone bound (a plan whose first run was finished before), else the next run, else
    a page task that can start.

    ``keeps`` (local workers, each addressed): the worker of a plan's first run keeps that seed's
    simulation (:func:`opnav.studies.campaign_tasks.runs_keeping_simulation`) and makes the bound from it
    once no run is left to hand out (or before it starts another plan's first run, so that it keeps one
    simulation at most), while the other workers draw the page's figures; 4 runs on 2 workers: each worker
    2 runs, then one the bound, the other the filters' figures. And when the runs do not share out evenly
    (5 runs on 2 workers), the last run's filters go to different workers, each simulating the run
    (:func:`opnav.studies.campaign_tasks.filter_part`; the same simulation, so the same figures): a
    simulation more, instead of one worker running a whole run alone while the other waits for it.
    Without (a dask scheduler places the tasks itself) the bound is made inside the first run's task
    (:func:`opnav.studies.campaign_tasks.runs_and_bound`)."""
    plans = book.plans
    queue = [("runs", k, i) for k, i in book.pending]
    if keeps and len(queue) % pool.count and book.splits(*queue[-1][1:]):
        k, i = queue.pop()[1:]
        queue += [("part", k, i, name) for name in task_filters(plans[k].tasks[i])]
    parts: dict[tuple[int, int], dict[str, dict]] = {}
    for k, plan in enumerate(plans):
        if plan.bound is not None and (k, 0) not in book.pending:  # its first run finished before
            queue.insert(0, ("bound", k, None))
    ready = [task for k in range(len(plans)) for task in book.page_tasks(k)]  # resumed with its runs finished
    holders: dict[object, int] = {}  # worker -> the plan whose first simulation it keeps
    running: dict[object, tuple] = {}

    def next_task(worker) -> tuple | None:
        k = holders.get(worker)
        if k is not None and not (queue and queue[0][0] in ("runs", "part") and not book.with_bound(*queue[0][1:3])):
            del holders[worker]
            return bound_from_kept, (*plans[k].bound, True), ("bound", k, None)
        if queue:
            kind, k, i, *name = queue.pop(0)
            if kind == "bound":
                return bound_task, (*plans[k].bound, True), ("bound", k, None)
            if kind == "part":
                return filter_part, (plans[k].tasks[i], name[0], True), ("part", k, (i, name[0]))
            if book.with_bound(k, i):
                function = runs_keeping_simulation if keeps else runs_and_bound
                return function, (plans[k].tasks[i], plans[k].bound, True), ("runs+bound", k, i)
            return run_batch, (*plans[k].tasks[i], True), ("runs", k, i)
        return ready.pop(0) if ready else None

    while True:
        sent = True
        while sent:
            sent = False
            for worker in pool.free():
                task = next_task(worker)
                if task is not None:
                    function, arguments, meaning = task
                    running[pool.send(worker, timed, function, *arguments)] = (worker, meaning)
                    sent = True
        if not running:
            return
        for ticket, (value, timing) in pool.wait():
            worker, (kind, k, detail) = running.pop(ticket)
            if kind == "runs+bound":
                value, bound = value
                if bound == KEPT:
                    holders[worker] = k
                    kind = "runs"
                elif bound == NOT_KEPT:
                    queue.insert(0, ("bound", k, None))
                    kind = "runs"
                else:
                    book.bounds[k] = bound["bound"] if keeps else bound
                book.runs_done(k, detail, value, kind, timing)
            elif kind == "runs":
                book.runs_done(k, detail, value, kind, timing)
            elif kind == "part":
                i, name = detail
                parts.setdefault((k, i), {})[name] = value
                book.ran(kind, [*plans[k].tasks[i][2], name], timing)
                if len(parts[k, i]) == len(task_filters(plans[k].tasks[i])):
                    book.runs_done(k, i, join_filter_parts(plans[k].tasks[i], parts.pop((k, i))), kind, None)
            elif kind == "bound":
                book.bounds[k] = value
                book.ran(kind, plans[k].bound[2], timing)
            elif kind == "histogram":
                book.histograms[k] = value
                book.ran(kind, k, timing)
            else:
                book.figure_done(k, *detail, value, timing)
            ready.extend(book.page_tasks(k))


@dataclass(frozen=True)
class _Done:
    """One plan's outcome: its runs' ``summaries`` in seed order, its posterior ``bound`` (None without),
    its ``aggregate`` (with the Monte Carlo NEES tests), the page figures ``drawn`` on the workers (per
    filter, :func:`opnav.studies.report_campaign.filter_blocks`; those missing are drawn when the
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
