"""Monte Carlo campaigns of a run file: N seeds through the runner, on dask.distributed, aggregated.

Run ``i`` is the run file with seed ``seed + i`` (recorded, so ``opnav run RUNFILE --seed S``
replays it alone) written by :func:`opnav.studies.runner.run_study` into ``DIR/run_NNN``.
Each run's stages are saved atomically under their content hashes, so an interrupted campaign
resumes: finished runs are read back, unfinished ones continue from their last stage.

Studies whose runs share one record layout (S1) go ``batch`` seeds at a time in lockstep
(:mod:`opnav.studies.lockstep_campaign`: one vectorised pass of each filter, the same
figures as the seed's replay; each run keeps its ``summary.json``, its per-epoch NEES and the
command that replays it, which writes its measurement files, OEM and report); other runs go one per task.
Tasks go to a dask.distributed ``LocalCluster`` of ``workers`` single-threaded processes (forked
from this one when that is safe: :func:`_local_cluster`), or to an existing scheduler (``dask scheduler`` and ``dask worker ADDRESS`` on other machines
sharing the output folder); with ``workers = 1`` and no scheduler they run in this process.

On workers, a lockstep batch is cut where its work divides without changing a number
(:func:`_submit_lockstep`): its seeds are simulated in one task per worker, each filter runs
over the whole batch in a task of its own, and a last task writes the summaries. A lockstep
pass costs about the same for 8 runs as for 4 (measured: 23 CPU s for the S1 EKF over 30
days either way; its time goes to the steps, not the runs), so cutting the batch into smaller
ones would gain little; and the batches stay those of one worker, so the figures are the same
on any number of workers (a lockstep filter takes the measurement noise at the first run of
its batch: other batches move a run's figures by 1e-6 or so). The default ``--batch 10`` put
a campaign of 8 S1 seeds in one task, and the second of 2 workers had nothing to do; now the
EKF and the UKF run side by side.

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
``nees/<name>.npz`` (lockstep runs, :mod:`opnav.studies.lockstep_campaign`); when one is missing or
unreadable the entry is ``{"available": false, "reason": ...}`` and the line says why.
Studies with their own evaluation (S2, S4) have no per-epoch NEES and no such entry.
"""

from __future__ import annotations

import json
import logging
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..consistency import ensemble_nees
from ..errors import InputError
from ..records import atomic_write_text
from .common import NEES_STATES
from .report import flat_items, markdown_page
from .lockstep_campaign import (SimulatedBatch, filter_batch, finished, join_batches, lockstep_filters, lockstep_key,
                                lockstep_ready, nees_path, run_lockstep, simulate_batch, write_batch)
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
               lockstep: bool, single_thread: bool = False) -> list[dict]:
    """Worker task: seeds of the run file, quietly, in lockstep when ``lockstep`` and their records allow
    (:mod:`opnav.studies.lockstep_campaign`), else one by one through the runner; returns their summaries.

    ``single_thread``: the compiled kernels run on one thread (:func:`opnav.compiled.use_one_thread`;
    a dask worker shares the machine with the other workers).
    """
    if single_thread:
        _one_thread()
    runs = [load_run_file(path, {**overrides, "seed": str(seed)}) for seed in seeds]
    if lockstep:
        names = check_filters(filters or runs[0].filters, runs[0].path)
        done = [finished(Path(folder), lockstep_key(run, names)) for run, folder in zip(runs, folders)]
        if all(summary is not None for summary in done):
            return done
        replay = [replay_command(path, overrides, seed, filters, mode) for seed in seeds]
        summaries = run_lockstep(runs, [Path(f) for f in folders], names, replay)
        if summaries is not None:
            return summaries
    return [run_study(run, RunOptions(out=Path(folder), filters=filters, mode=mode, workers=1))
            for run, folder in zip(runs, folders)]


def _one_thread() -> None:
    """The compiled kernels on one thread (:func:`opnav.compiled.use_one_thread`): a dask worker shares
    the machine with the other workers."""
    from ..compiled import use_one_thread

    use_one_thread()


def _lockstep_runs(path: str, overrides: dict, seeds: list[int], filters) -> tuple[list, tuple[str, ...]]:
    """The run files of ``seeds`` and the filter names of a lockstep batch."""
    runs = [load_run_file(path, {**overrides, "seed": str(seed)}) for seed in seeds]
    return runs, check_filters(filters or runs[0].filters, runs[0].path)


def _finished_batch(task: tuple) -> list[dict] | None:
    """The summaries of a lockstep task whose runs are all finished (a resumed campaign), else None."""
    path, overrides, seeds, folders, filters, _, lockstep = task
    if not lockstep:
        return None
    runs, names = _lockstep_runs(path, overrides, seeds, filters)
    done = [finished(Path(folder), lockstep_key(run, names)) for run, folder in zip(runs, folders)]
    return done if all(summary is not None for summary in done) else None


def _simulate_task(path: str, overrides: dict, seeds: list[int]) -> SimulatedBatch:
    """Worker task: some seeds of a lockstep batch simulated (:func:`~opnav.studies.lockstep_campaign.simulate_batch`)."""
    _one_thread()
    return simulate_batch([load_run_file(path, {**overrides, "seed": str(seed)}) for seed in seeds])


def _filter_task(path: str, overrides: dict, seeds: list[int], folders: list[str], filters, name: str,
                 *parts: SimulatedBatch) -> dict | None:
    """Worker task: filter ``name`` over a whole lockstep batch simulated in ``parts``; None when its
    records do not fit lockstep (:func:`~opnav.studies.lockstep_campaign.filter_batch`)."""
    _one_thread()
    runs, names = _lockstep_runs(path, overrides, seeds, filters)
    batch = join_batches(list(parts))
    if not lockstep_ready(batch, names):
        return None
    return filter_batch(name, batch, runs, [Path(folder) for folder in folders], names)


def _write_task(path: str, overrides: dict, seeds: list[int], folders: list[str], filters, mode: str | None,
                n_parts: int, *parts_and_results) -> list[dict]:
    """Worker task: the summaries of a lockstep batch from its simulation ``parts`` and each filter's
    result (in filter order); a batch whose records do not fit lockstep goes through the runner."""
    _one_thread()
    parts, results = list(parts_and_results[:n_parts]), list(parts_and_results[n_parts:])
    if any(result is None for result in results):
        return _run_batch(path, overrides, seeds, folders, filters, mode, False)
    runs, names = _lockstep_runs(path, overrides, seeds, filters)
    replay = [replay_command(path, overrides, seed, filters, mode) for seed in seeds]
    return write_batch(runs, [Path(folder) for folder in folders], names, join_batches(parts),
                       dict(zip(names, results)), replay)


def _submit_lockstep(client, task: tuple, workers: int):
    """A lockstep task as tasks of the cluster: its seeds simulated in up to ``workers`` parts, each
    filter over the whole batch, then the summaries (module notes); the future of the summaries."""
    path, overrides, seeds, folders, filters, mode, _ = task
    names = _lockstep_runs(path, overrides, seeds[:1], filters)[1]
    count = max(1, min(workers, len(seeds)))
    edges = [len(seeds) * k // count for k in range(count + 1)]
    parts = [client.submit(_simulate_task, path, overrides, seeds[a:b], pure=False)
             for a, b in zip(edges[:-1], edges[1:])]
    results = [client.submit(_filter_task, path, overrides, seeds, folders, filters, name, *parts, pure=False)
               for name in names]
    return client.submit(_write_task, path, overrides, seeds, folders, filters, mode, len(parts), *parts, *results,
                         pure=False)


@dataclass(frozen=True)
class _Plan:
    """One campaign's runs, cut into worker tasks."""

    path: str
    overrides: dict
    out: Path
    seeds: list[int]
    folders: list[str]
    tasks: list[tuple]
    study: str
    mode: str


def _plan(path: str, runs: int, out: Path, overrides: dict, filters, mode: str | None, lockstep: bool,
          batch: int) -> _Plan:
    base = load_run_file(path, overrides)  # validates everything before any work
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    run_mode = mode or base.mode
    names = check_filters(filters or base.filters, base.path)
    together = lockstep and lockstep_filters(base, names, run_mode)
    size = batch if together else 1
    seeds = [base.seed + i for i in range(runs)]
    folders = [str(out / f"run_{i:03d}") for i in range(runs)]
    tasks = [(str(path), overrides, seeds[i:i + size], folders[i:i + size], filters, mode, together)
             for i in range(0, runs, size)]
    return _Plan(str(path), overrides, out, seeds, folders, tasks, base.study, run_mode)


def _progress_reporter(progress: bool, log: Callable[[str], None] | None) -> Callable[[str], None]:
    """Where a campaign's progress lines go: ``log`` (None: this module's logger at INFO); nowhere
    unless ``progress``."""
    if not progress:
        return lambda message: None
    return log if log is not None else (lambda message: _log.info("%s", message))


def _execute(tasks: list[tuple], *, workers: int, scheduler: str | None,
             report: Callable[[str], None]) -> list[list[dict]]:
    """Run the tasks (in this process, on a LocalCluster or on ``scheduler``): their results in order;
    ``report`` gets a line after each task."""
    total = sum(len(task[2]) for task in tasks)
    if scheduler is None and workers == 1:
        results, done = [], 0
        for task in tasks:
            results.append(_run_batch(*task))
            done += len(task[2])
            report(f"[campaign] {done}/{total} runs done")
        return results
    from dask.distributed import Client, as_completed

    results: list = [_finished_batch(task) for task in tasks]  # finished lockstep batches are read back
    done = sum(len(task[2]) for task, result in zip(tasks, results) if result is not None)
    if done:
        report(f"[campaign] {done}/{total} runs done")
    if done == total:
        return results
    cluster = None if scheduler else _local_cluster(workers)
    try:
        with Client(scheduler or cluster) as client:
            count = len(client.scheduler_info().get("workers", {})) or workers
            futures = {k: (_submit_lockstep(client, task, count) if task[6] else
                           client.submit(_run_batch, *task, True, pure=False))
                       for k, (task, result) in enumerate(zip(tasks, results)) if result is None}
            index = {future.key: k for k, future in futures.items()}
            for future in as_completed(list(futures.values())):
                k = index[future.key]
                results[k] = future.result()
                done += len(tasks[k][2])
                report(f"[campaign] {done}/{total} runs done")
            return results
    finally:
        if cluster is not None:
            cluster.close()


def _local_cluster(workers: int):
    """A ``LocalCluster`` of ``workers`` single-threaded worker processes, forked from this one when that is
    safe (:func:`_fork_safe`): a forked worker has this process's modules and starts at once, where a
    spawned one starts an interpreter and imports opnav again (seconds each, and as long again to stop)."""
    import dask
    from dask.distributed import LocalCluster

    method = "fork" if _fork_safe() else "spawn"
    with dask.config.set({"distributed.worker.multiprocessing-method": method}):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                            silence_logs=logging.WARNING)


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

    A lockstep run's ``nees/<name>.npz`` (its hash must be the summary's), else the runner's
    ``filters/<name>.npz``. Raises :class:`~opnav.errors.InputError` naming the file and what
    to do when it is missing, unreadable or another run's.
    """
    lockstep = summary.get("lockstep")
    if lockstep:
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
            made_by = str(data["hash"]) if lockstep else None
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path} cannot be read: {exc} ({remedy})") from None
    if lockstep and made_by != lockstep.get("hash"):
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
                 progress: bool = False, lockstep: bool = True, batch: int = 10,
                 log: Callable[[str], None] | None = None) -> dict:
    """Run ``runs`` seeds of run file ``path`` into ``out`` (module notes); returns the campaign record.

    ``lockstep`` runs up to ``batch`` seeds per worker task together when the study and
    filters allow it (:mod:`opnav.studies.lockstep_campaign`); ``False`` runs each seed on its own.
    ``progress``: a line (``[campaign] k/N runs done``) after each task, to ``log`` (None: this
    module's logger at INFO).
    """
    _check_counts(runs, workers, batch)
    plan = _plan(path, runs, out, dict(overrides or {}), filters, mode, lockstep, batch)
    tic = time.perf_counter()
    results = _execute(plan.tasks, workers=workers, scheduler=scheduler, report=_progress_reporter(progress, log))
    return _write_campaign(plan, [s for batch_result in results for s in batch_result], time.perf_counter() - tic)


def _check_counts(runs: int, workers: int, batch: int) -> None:
    for name, value in (("--runs", runs), ("--workers", workers), ("--batch", batch)):
        if int(value) != value or value < 1:
            raise InputError(f"{name} must be a positive integer, got {value}")


def _write_campaign(plan: _Plan, summaries: list[dict], wall_s: float) -> dict:
    """``campaign.json``, ``campaign.md`` and ``campaign.html`` of one campaign (atomically)."""
    bounds = [s["lockstep"]["bound"] for s in summaries if "bound" in s.get("lockstep", {})]
    aggregate = _aggregate(summaries)
    tests = _monte_carlo_nees(plan, summaries)
    for name, test in tests.items():
        aggregate[name][MONTE_CARLO_KEY] = test
    record = {
        "run_file": plan.path, "overrides": plan.overrides, "study": plan.study, "mode": plan.mode,
        "runs": [{"seed": seed, "folder": folder, "filters": s.get("filters", {}),
                  **({"replay": s["lockstep"]["replay"]} if "lockstep" in s else {})}
                 for seed, folder, s in zip(plan.seeds, plan.folders, summaries)],
        "aggregate": aggregate, "paper": summaries[0].get("paper", {}),
        "lockstep_runs": sum("lockstep" in s for s in summaries),
        "wall_s": wall_s,
    }
    if bounds:  # the bound follows the truth, which no seed changes: the first run's stands for all
        record["posterior_crb"] = bounds[0]
    atomic_write_text(plan.out / "campaign.json", json.dumps(record, indent=2, default=float))
    seeds = plan.seeds
    lines = [f"# Campaign: {Path(plan.path).name}, {len(seeds)} runs (seeds {seeds[0]}..{seeds[-1]})", "",
             f"Overrides: {plan.overrides or 'none'}. Paper: `{record['paper']}`", "",
             *campaign_table(record["aggregate"])]
    if tests:
        lines += ["", f"Monte Carlo NEES test: the NEES ({NEES_STATES} states) averaged over the runs at each epoch "
                      f"of the study window they share, against the band of the mean of that many chi-square("
                      f"{NEES_STATES}) values; a consistent filter has about {100 * MONTE_CARLO_PROBABILITY:g} % of "
                      "the epochs inside."]
        for name, test in tests.items():
            lines += ["", monte_carlo_line(name, test)]
    if bounds:
        lines += ["", f"Posterior Cramér-Rao bound along the truth (1-sigma, RMS over the study window): "
                      f"{bounds[0]['pcrb_position_km']:.4g} km, {bounds[0]['pcrb_velocity_m_s']:.4g} m/s."]
    atomic_write_text(plan.out / "campaign.md", "\n".join(lines) + "\n")
    atomic_write_text(plan.out / "campaign.html", markdown_page(f"Campaign {Path(plan.path).name}", lines))
    return record


def parse_sweeps(pairs: list[str] | None) -> dict[str, list[str]]:
    """``["KEY=V1,V2", ...]`` -> ``{KEY: [V1, V2]}``; errors name the bad pair."""
    out: dict[str, list[str]] = {}
    for pair in pairs or []:
        key, sep, values = pair.partition("=")
        items = [v.strip() for v in values.split(",") if v.strip()]
        if not sep or not key.strip() or not items:
            raise InputError(f"--sweep expects KEY=V1,V2,..., got {pair!r}")
        out[key.strip()] = items
    return out


def run_sweep(path: str, *, sweeps: dict[str, list[str]], runs: int, out: Path, overrides: dict | None = None,
              filters=None, mode: str | None = None, workers: int = 1, scheduler: str | None = None,
              progress: bool = False, lockstep: bool = True, batch: int = 10,
              log: Callable[[str], None] | None = None) -> dict:
    """A campaign per point of the Cartesian product of ``sweeps`` (``DIR/KEY=V,KEY=V``), then one table.

    Every point's runs go to the same workers at once (one cluster for the sweep).
    ``DIR/sweep.json`` lists each point's overrides and aggregate; ``DIR/sweep.md`` is one row per
    point and filter, with the Monte Carlo NEES test (the run-averaged NEES and the share of epochs
    inside its band), the study's published figure and the posterior Cramér-Rao bound beside ours.
    ``progress`` and ``log`` as for :func:`run_campaign`.
    """
    import itertools

    _check_counts(runs, workers, batch)
    keys = list(sweeps)
    points = [dict(zip(keys, values)) for values in itertools.product(*(sweeps[k] for k in keys))]
    out = Path(out)
    plans = [_plan(path, runs, out / ",".join(f"{k}={v}" for k, v in point.items()),
                   {**(overrides or {}), **point}, filters, mode, lockstep, batch) for point in points]
    tic = time.perf_counter()
    results = _execute([task for plan in plans for task in plan.tasks], workers=workers, scheduler=scheduler,
                       report=_progress_reporter(progress, log))
    wall = time.perf_counter() - tic
    rows, first = [], 0
    for point, plan in zip(points, plans):
        batches = results[first:first + len(plan.tasks)]
        first += len(plan.tasks)
        record = _write_campaign(plan, [s for b in batches for s in b], wall)
        rows.append({"point": point, "aggregate": record["aggregate"], "paper": record["paper"],
                     "posterior_crb": record.get("posterior_crb")})
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
