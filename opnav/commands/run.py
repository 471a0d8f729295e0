"""``opnav run``: run a study from its run file (truth -> measurements -> filters -> report).

The run file (``samples/s1_jul_both_0.1.toml``, ``samples/s3_geo.toml``) names the study,
the seed, the study's settings and the filters (:mod:`opnav.studies.settings`). Outputs
in ``--out``: ``measurements.csv``, ``truth.npz``, ``filters/<name>.json|npz``,
``summary.json``, ``report.md``, ``report.html`` (:mod:`opnav.studies.runner`). A re-run
with the same inputs reuses the finished stages, so an interrupted run resumes.

Exit status: 0, or 3 when a filter's final estimate is not usable (its consistency flags,
:mod:`opnav.filters.monitor`), with every output written.
"""

from __future__ import annotations

import argparse
import sys

from ..errors import InputError

NAME = "run"
HELP = "run a study from its run file: truth, measurements, filters, report (resumable)"
EXIT_UNUSABLE = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("runfile", help="run file (TOML with [scenario] study, [settings], [filters])")
    parser.add_argument("--out", required=True, help="output folder (created; finished stages in it are reused)")
    parser.add_argument("--mode", choices=("measurements", "images"), default=None,
                        help="measurements: the study's noise added to the true values (the papers' set-up); "
                             "images: rendered frames through the image stage (default: the run file's "
                             "[scenario] mode, else measurements)")
    parser.add_argument("--filters", default=None,
                        help="comma-separated filters (ekf, ukf, sr-ukf, pf, upf, mcmc-upf); default: the run file's")
    parser.add_argument("--seed", type=int, default=None, help="seed (default: the run file's)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a [settings] value, e.g. --set duration_days=1, or inject a fault, "
                             "e.g. --set faults.outlier_fraction=0.01 (opnav/studies/faults.py; repeatable)")
    parser.add_argument("--checked", action="store_true",
                        help="check every filter's covariance after every record (finite, symmetric, positive "
                             "definite; stop naming the record otherwise) and report its worst conditioning")
    parser.add_argument("--workers", type=int, default=None,
                        help="processes image mode renders and measures in, a day of frames each (default: one per "
                             "core; the records are the same for any number)")
    parser.add_argument("--no-progress", action="store_true", help="hide progress messages and bars")


def log_to_stderr(message: str) -> None:
    """A progress message on its own line on stderr (the runner's ``RunOptions.log``)."""
    print(message, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    from ..studies.runner import RunOptions, run_study
    from ..studies.settings import load_run_file, parse_overrides
    from .compile import compile_for_run, run_uses

    overrides = parse_overrides(args.set)
    if args.seed is not None:
        if args.seed < 0:
            raise InputError(f"--seed must be >= 0, got {args.seed}")
        overrides["seed"] = str(args.seed)
    run_file = load_run_file(args.runfile, overrides)
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be >= 1, got {args.workers}")
    filters = None if args.filters is None else tuple(f.strip() for f in args.filters.split(",") if f.strip())
    # kernels not in numba's cache compile here, announced, not inside a progress bar's first step
    compile_for_run(run_uses(run_file, filters, args.mode), show=not args.no_progress, workers=args.workers)
    summary = run_study(run_file, RunOptions(out=args.out, filters=filters, mode=args.mode,
                                             progress=not args.no_progress, checked=args.checked,
                                             workers=args.workers, log=None if args.no_progress else log_to_stderr))
    return print_summary(summary, args.out)


def print_summary(summary: dict, out) -> int:
    """Print a run's figures (the study's summary lines; warnings on stderr); the exit status."""
    from ..studies import STUDIES

    for line in STUDIES[summary["run"]["study"]].summary_lines(summary):
        print(line)
    unusable = []
    for name, figures in summary["filters"].items():
        consistency = figures.get("consistency")
        if consistency is None:
            continue
        for message in consistency["messages"]:
            print(f"warning: {name}: {message}", file=sys.stderr)
        if not consistency["usable"]:
            unusable.append(name)
    print(f"outputs in {out} (summary.json, report.html)")
    if unusable:
        print(f"error: the final estimate of {', '.join(unusable)} is not usable; see summary.json", file=sys.stderr)
        return EXIT_UNUSABLE
    return 0
