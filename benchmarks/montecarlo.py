"""Campaign throughput: runs per minute of ``opnav montecarlo`` on 1 and on 2 workers, default batch.

Each case is the command itself in a fresh process (``opnav montecarlo RUNFILE --runs N
--workers W --filters ekf,ukf``, default ``--batch``, a fresh output folder), timed from the
start of the process to its end, so what is compared is what a user waits for: start-up,
the worker processes of ``--workers 2`` and what they load included. Printed per
case: runs, wall time, runs per minute, the campaign's own wall (``campaign.json``), the CPU
time of the command and its workers, and the load average before and after (the machine may be shared: a core busy with another job caps
the 2-worker speed-up below 2), and the wall expected on an idle machine from the campaign's
timeline (``campaign.json``: the command's CPU seconds before its first task, each worker's tasks
in their order at their CPU seconds, page figures after the last run, the page); ``--timeline``
prints the timeline itself. Then the speed-up of 2 workers over 1 for each run count (measured,
and expected from the CPU seconds), and the largest relative difference between the two
campaigns' per-run figures.

Those figures must not differ: a run's figures are its seed's. Quick runs
(:mod:`opnav.studies.campaign_runs`) are the runner's own simulation and filters, one seed per
task by default, and the posterior bound (from the first seed's simulation, which its worker
keeps) a task of its own after the runs, so the 2 workers share the seeds and the numbers are
those of one worker.

Usage::

    .venv/bin/python benchmarks/montecarlo.py                       # --runs 4 and 8, the 30-day arc
    .venv/bin/python benchmarks/montecarlo.py --runs 4 --days 5     # a shorter arc (say so when quoting it)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def load() -> str:
    """The 1-, 5- and 15-minute load averages, as ``uptime`` prints them."""
    return ", ".join(f"{value:.2f}" for value in os.getloadavg())


def campaign(runs: int, workers: int, out: Path, args: argparse.Namespace) -> dict:
    """One ``opnav montecarlo`` command in its own process: its wall and CPU time (its workers' included)
    and what it wrote."""
    command = [sys.executable, "-m", "opnav.cli", "montecarlo", str(args.runfile), "--runs", str(runs),
               "--workers", str(workers), "--filters", args.filters, "--out", str(out), "--no-progress"]
    if args.days is not None:
        command += ["--set", f"duration_days={args.days:g}"]
    env = dict(os.environ)
    if args.one_thread and workers == 1:
        env["NUMBA_NUM_THREADS"] = "1"  # the work of one worker (a worker process runs its kernels on one thread)
    before = load()
    used = resource.getrusage(resource.RUSAGE_CHILDREN)
    tic, started = time.perf_counter(), time.time()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, cwd=ROOT, env=env)
    wall, ended = time.perf_counter() - tic, time.time()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    record = json.loads((out / "campaign.json").read_text())
    return {"runs": runs, "workers": workers, "wall_s": wall, "campaign_wall_s": record["wall_s"],
            "cpu_s": after.ru_utime + after.ru_stime - used.ru_utime - used.ru_stime,
            "runs_per_min": 60.0 * runs / wall, "load_before": before, "load_after": load(),
            "figures": [run["filters"] for run in record["runs"]],
            "expected_wall_s": expected_wall_s(record["timeline"]),
            "timeline": timeline_lines(record["timeline"], started, ended)}


def expected_wall_s(timeline: dict) -> float:
    """The campaign's wall on an idle machine, from its CPU seconds: the command's start-up and planning
    (its CPU before the first task), each worker's tasks one after the other in the order they ran, a
    filter's page figures not before the last run is done (they need them all), the RMS histogram not
    before the bound is made too, then the page."""
    tasks = sorted(timeline["tasks"], key=lambda task: task["start"])
    clock: dict[int, float] = {}
    start = timeline["parent"]["cpu_s"]
    runs_done = bound_done = start
    for task in tasks:
        begin = clock.get(task["worker"], start)
        if task["task"] == "figures":
            begin = max(begin, runs_done)
        elif task["task"] == "histogram":
            begin = max(begin, runs_done, bound_done)
        end = clock[task["worker"]] = begin + task["cpu_s"]
        if task["task"] in ("runs", "runs+bound", "part"):
            runs_done = max(runs_done, end)
        if task["task"] in ("runs+bound", "bound"):
            bound_done = max(bound_done, end)
    return max(clock.values(), default=start) + timeline["page"]["cpu_s"]


def timeline_lines(timeline: dict, started: float, ended: float) -> list[str]:
    """The campaign's timeline, s from the command's start: its start-up and planning, each task (worker,
    start, end, CPU), the page, the exit; and per worker its busy and idle seconds between the first task
    and the last."""
    parent = timeline["parent"]
    lines = [f"    command start-up and planning: 0.00-{parent['start'] - started:.2f} s wall, {parent['cpu_s']:.2f} s CPU"]
    workers: dict[int, list] = {}
    for task in sorted(timeline["tasks"], key=lambda task: task["start"]):
        workers.setdefault(task["worker"], []).append(task)
        lines.append(f"    worker {task['worker']}: {task['start'] - started:6.2f}-{task['end'] - started:6.2f} s "
                     f"({task['end'] - task['start']:5.2f} s wall, {task['cpu_s']:5.2f} s CPU) {task['task']} "
                     f"{task['what']}")
    page = timeline["page"]
    lines.append(f"    page: {page['start'] - started:.2f}-{page['end'] - started:.2f} s ({page['cpu_s']:.2f} s CPU); "
                 f"exit {ended - page['end']:.2f} s")
    first = min(task["start"] for task in timeline["tasks"])
    last = max(task["end"] for task in timeline["tasks"])
    for worker, done in workers.items():
        busy = sum(task["end"] - task["start"] for task in done)
        lines.append(f"    worker {worker}: busy {busy:.2f} s, idle {last - first - busy:.2f} s of the tasks' "
                     f"{last - first:.2f} s")
    return lines


def numbers(value, prefix: str = ""):
    """(dotted key, number) of every number in nested figures, wall times left out."""
    if isinstance(value, dict):
        for key, item in value.items():
            if "wall" not in key:
                yield from numbers(item, f"{prefix}.{key}" if prefix else key)
    elif isinstance(value, list):
        for index, item in enumerate(value):
            yield from numbers(item, f"{prefix}[{index}]")
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        yield prefix, float(value)


def largest_difference(first: list[dict], second: list[dict]) -> tuple[float, str]:
    """The largest relative difference between two campaigns' per-run figures, and where."""
    worst, where = 0.0, "none"
    for k, (a, b) in enumerate(zip(first, second)):
        other = dict(numbers(b))
        for key, value in numbers(a):
            if key in other and math.isfinite(value) and math.isfinite(other[key]):
                diff = abs(value - other[key]) / max(abs(value), abs(other[key]), 1e-300)
                if diff > worst:
                    worst, where = diff, f"run {k} {key}"
    return worst, where


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runfile", default=ROOT / "samples" / "s1_jul_both_0.1.toml")
    parser.add_argument("--runs", type=int, nargs="+", default=[4, 8], help="run counts (each >= 4 for the target)")
    parser.add_argument("--days", type=float, default=None, help="arc length (default: the run file's, S1 30 days)")
    parser.add_argument("--filters", default="ekf,ukf")
    parser.add_argument("--one-thread", action="store_true",
                        help="run the 1-worker campaign's kernels on one thread (NUMBA_NUM_THREADS=1), as each of "
                             "the 2 workers does: the same work on one core against two (a busy machine makes an "
                             "in-process campaign's thread pool wait for cores)")
    parser.add_argument("--timeline", action="store_true",
                        help="print each campaign's timeline (campaign.json: start-up, every task's worker, start, "
                             "end and CPU seconds, the page, the exit; each worker's busy and idle time)")
    args = parser.parse_args(argv)
    arc = "the run file's arc" if args.days is None else f"{args.days:g}-day arc"
    threads = "; 1 worker on one thread" if args.one_thread else ""
    print(f"opnav montecarlo {Path(args.runfile).name} --filters {args.filters}, {arc}, default --batch{threads}; "
          f"{os.cpu_count()} cores", flush=True)
    ratios, differences, expected = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for runs in args.runs:
            cases = {}
            for workers in (1, 2):
                case = cases[workers] = campaign(runs, workers, Path(tmp) / f"r{runs}w{workers}", args)
                print(f"--runs {runs} --workers {workers}: {case['wall_s']:.1f} s (campaign {case['campaign_wall_s']:.1f} s, "
                      f"CPU {case['cpu_s']:.1f} s) = {case['runs_per_min']:.2f} runs/min; load average before "
                      f"{case['load_before']}, after {case['load_after']}; expected on an idle machine from its "
                      f"CPU seconds {case['expected_wall_s']:.1f} s", flush=True)
                if args.timeline:
                    print("\n".join(case["timeline"]), flush=True)
            ratio = cases[2]["runs_per_min"] / cases[1]["runs_per_min"]
            ratios.append(ratio)
            expected.append(cases[1]["expected_wall_s"] / cases[2]["expected_wall_s"])
            diff, where = largest_difference(cases[1]["figures"], cases[2]["figures"])
            differences.append(diff)
            print(f"--runs {runs}: 2 workers / 1 worker = {ratio:.2f}x runs/min; largest relative difference of a "
                  f"run's figures between them: {diff:.2g} ({where})", flush=True)
    print(f"speed-up 2 workers / 1 worker: {', '.join(f'{r:.2f}x' for r in ratios)} (target >= 1.8x); expected "
          f"on an idle machine from the campaigns' CPU seconds: {', '.join(f'{r:.2f}x' for r in expected)}")
    return 0 if max(differences) == 0.0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
