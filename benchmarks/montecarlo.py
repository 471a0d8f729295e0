"""Campaign throughput: runs per minute of an S1 Monte Carlo on 1 and on 2 dask workers.

Each worker count gets a fresh ``LocalCluster`` (started before the clock) and a fresh
output folder; the campaign is :func:`opnav.studies.campaign.run_campaign` pointed at the
cluster's scheduler, so both counts pay the same task overhead. The figures printed: runs,
wall time, runs per minute, the 2-worker speed-up, and whether both campaigns gave the same
aggregate (they must: the seeds, not the workers, decide every number).

Usage::

    .venv/bin/python benchmarks/montecarlo.py --runs 100
    .venv/bin/python benchmarks/montecarlo.py --runs 20 --days 5     # a quick look
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

from dask.distributed import LocalCluster

from opnav.studies.campaign import run_campaign

ROOT = Path(__file__).resolve().parent.parent


def campaign(workers: int, out: Path, args: argparse.Namespace) -> tuple[float, dict]:
    """Wall time and aggregate of one campaign on a new LocalCluster of ``workers`` processes."""
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.WARNING) as cluster:
        tic = time.perf_counter()
        record = run_campaign(str(args.runfile), runs=args.runs, out=out, filters=tuple(args.filters.split(",")),
                              overrides={"duration_days": str(args.days)}, scheduler=cluster.scheduler_address,
                              progress=False, lockstep=not args.no_lockstep, batch=args.batch)
        wall = time.perf_counter() - tic
    return wall, record["aggregate"]


def without_walls(aggregate: dict) -> dict:
    return {name: {k: v for k, v in figures.items() if "wall_s" not in k} for name, figures in aggregate.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runfile", default=ROOT / "samples" / "s1_jul_both_0.1.toml")
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--days", type=float, default=30.0, help="arc length (S1: 30)")
    parser.add_argument("--filters", default="ekf")
    parser.add_argument("--batch", type=int, default=10, help="seeds per lockstep task")
    parser.add_argument("--no-lockstep", action="store_true")
    args = parser.parse_args(argv)
    walls, aggregates = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for workers in (1, 2):
            walls[workers], aggregates[workers] = campaign(workers, Path(tmp) / f"w{workers}", args)
            rate = args.runs / walls[workers] * 60.0
            rms = aggregates[workers][args.filters.split(",")[0]]["position_rms_km"]
            print(f"{workers} worker(s): {args.runs} runs of {args.days:g} days in {walls[workers]:.1f} s = "
                  f"{rate:.2f} runs/min (position RMS {rms['mean']:.3f} +- {rms['std']:.3f} km)", flush=True)
    print(f"speed-up 2 workers / 1 worker: {walls[1] / walls[2]:.2f}x")
    same = without_walls(aggregates[1]) == without_walls(aggregates[2])
    print(f"aggregates identical on 1 and 2 workers: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
