"""``opnav montecarlo``: N seeds of a run file on dask.distributed, aggregated (:mod:`opnav.studies.campaign`).

Each run goes to ``--out/run_NNN`` (its seed is recorded in ``campaign.json``; ``opnav run
RUNFILE --seed S`` replays it alone); an interrupted campaign resumes from the finished stages.
``--workers K`` runs the tasks on K single-threaded local processes (forked from this one);
``--scheduler ADDRESS`` sends them to an existing dask.distributed cluster (start it with ``dask
scheduler`` and ``dask worker ADDRESS`` on machines that share the output folder). Measurement-mode runs of S1 and S3 are quick runs (the same figures
as each seed's replay, only ``summary.json`` and the per-epoch NEES per run; the posterior
Cramér-Rao bound once per campaign); ``--full-runs`` runs each seed through the full runner.
``--batch`` seeds go in one worker task (default 1). Prints per filter the Monte Carlo NEES test of the campaign
(:mod:`opnav.studies.campaign`). Exit status 3 when any run's final estimate is not usable.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys

NAME = "montecarlo"
HELP = "run N seeds of a run file (dask.distributed) and aggregate them into campaign.json/.md (resumable)"
#: Exit status when a run's final estimate is not usable (the campaign is still written).
EXIT_UNUSABLE = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    if "numpy" not in sys.modules:
        # this process is the command, numpy not loaded yet: a run's matrices are 6 x 6 and its longest
        # products a few columns wide, and OpenBLAS's idle threads spin on the other core, which the second
        # worker needs (an S1 run: 3.6 % more CPU, 9.50 against 9.16 s for two 5-day runs at load ~13, the
        # same figures to the last bit; the workers are forked from here with it); a value the user set stands
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    parser.add_argument("runfile", help="run file (as for opnav run)")
    parser.add_argument("--runs", type=int, required=True, help="number of seeds (run file seed, +1, +2, ...)")
    parser.add_argument("--out", required=True, help="campaign folder (run_NNN/ per run, campaign.json, campaign.md)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a [settings] value")
    parser.add_argument("--sweep", action="append", default=[], metavar="KEY=V1,V2,...",
                        help="run a campaign at every combination of these [settings] values (repeatable); "
                             "DIR/sweep.md tables them beside the paper")
    parser.add_argument("--filters", default=None, help="comma-separated filters (default: the run file's)")
    parser.add_argument("--mode", choices=("measurements", "images"), default=None,
                        help="default: the run file's [scenario] mode, else measurements")
    parser.add_argument("--workers", type=int, default=1, help="local worker processes (default 1: in this process)")
    parser.add_argument("--scheduler", default=None, help="address of a running dask scheduler")
    parser.add_argument("--batch", type=int, default=1,
                        help="seeds per worker task (default 1: each seed its own task; a run's figures do not "
                             "depend on it)")
    parser.add_argument("--full-runs", action="store_true",
                        help="run every seed through the full runner (measurement files, OEM, report per run), "
                             "not as a quick run (summary.json and per-epoch NEES)")
    parser.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from ..studies.campaign import (MONTE_CARLO_KEY, campaign_table, monte_carlo_line, parse_sweeps, run_campaign,
                                      run_sweep)
    from ..studies.settings import parse_overrides
    from .run import filter_names, log_to_stderr, own_process

    if not logging.getLogger("opnav").isEnabledFor(logging.INFO):
        # a dask scheduler's INFO chatter (every worker and connection) would bury the progress lines;
        # distributed sets its loggers' levels from its configuration when it is imported (in the
        # campaign, and in each worker process, which inherits the environment)
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
        logging.getLogger("distributed").setLevel(logging.WARNING)
    filters = filter_names(args.filters)
    sweeps = parse_sweeps(args.sweep)
    if sweeps:
        run_sweep(args.runfile, sweeps=sweeps, runs=args.runs, out=args.out, overrides=parse_overrides(args.set),
                  filters=filters, mode=args.mode, workers=args.workers, scheduler=args.scheduler,
                  progress=not args.no_progress, quick=not args.full_runs, batch=args.batch, log=log_to_stderr,
                  command=tuple(sys.argv) if own_process(args) else None)
        print(f"sweep in {args.out} (sweep.json, sweep.md; one campaign folder per point)")
        return 0
    record = run_campaign(args.runfile, runs=args.runs, out=args.out, overrides=parse_overrides(args.set),
                          filters=filters, mode=args.mode, workers=args.workers, scheduler=args.scheduler,
                          progress=not args.no_progress, quick=not args.full_runs, batch=args.batch,
                          log=log_to_stderr, command=tuple(sys.argv) if own_process(args) else None)
    for name, a in record["aggregate"].items():
        if "position_rms_km" not in a:
            continue
        p = a["position_rms_km"]
        print(f"{name:9s} position RMS {p['mean']:.3f} +- {p['std']:.3f} km over {a['runs']} runs "
              f"[{p['min']:.3f}, {p['max']:.3f}], NEES {a['nees_mean']['mean']:.2f}, "
              f"runs with flags {a['runs_with_flags']}")
    if not all("position_rms_km" in a for a in record["aggregate"].values()):
        print("\n".join(campaign_table(record["aggregate"])))
    for name, a in record["aggregate"].items():
        if MONTE_CARLO_KEY in a:
            print(monte_carlo_line(name, a[MONTE_CARLO_KEY]))
    print(f"campaign in {args.out} (campaign.json, campaign.md) after {record['wall_s']:.1f} s")
    unusable = {name: a["runs_unusable"] for name, a in record["aggregate"].items() if a["runs_unusable"]}
    if unusable:
        print("error: some runs' final estimates are not usable (their consistency flags in run_NNN/summary.json): "
              + ", ".join(f"{name} {count}/{record['aggregate'][name]['runs']}" for name, count in unusable.items()),
              file=sys.stderr)
        return EXIT_UNUSABLE
    return 0
