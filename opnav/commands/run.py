"""``opnav run``: run a study from its run file (truth -> measurements -> filters -> report).

The run file (``samples/s1_jul_both_0.1.toml``, ``samples/s3_geo.toml``) names the study,
the seed, the study's settings and the filters (:mod:`opnav.studies.settings`). Outputs
in ``--out``: ``measurements.csv``, ``truth.npz``, ``filters/<name>.json|npz``,
``summary.json``, ``report.md``, ``report.html`` (:mod:`opnav.studies.runner`). A re-run
with the same inputs reuses the finished stages, so an interrupted run resumes.
``summary.json``'s ``stages_wall_s`` times the whole command from the start of the process
(``setup``: the interpreter, the imports, the run file), stage after stage; with progress on,
a last line on stderr lists them.

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
    parser.add_argument("--report-frame", choices=("rtn", "icrf"), default="rtn",
                        help="axes of the report's error plots: rtn (radial, along-track, cross-track of the true "
                             "orbit about the centre body; default) or icrf")
    parser.add_argument("--no-progress", action="store_true", help="hide progress messages and bars")


def own_process(args: argparse.Namespace) -> bool:
    """Whether this process is this command (its arguments are the process's), not ``main`` called in a
    longer process (a test, a notebook)."""
    return args.runfile in sys.argv[1:] and args.out in sys.argv[1:]


def command_started(args: argparse.Namespace) -> float:
    """When this command started, as a ``time.perf_counter()`` reading, for the run's ``setup`` stage: the
    start of the process when the process is this command (the interpreter's start and the imports
    count), else now."""
    import time

    now = time.perf_counter()
    started = process_started() if own_process(args) else None
    return now if started is None else min(started, now)


def process_started() -> float | None:
    """When this process started, as a ``time.perf_counter()`` reading (Linux: its start time in
    ``/proc/self/stat`` against the boot clock, to 10 ms); None where that cannot be read."""
    import os
    import time

    try:
        with open("/proc/self/stat", encoding="ascii") as handle:
            fields = handle.read().rsplit(")", 1)[1].split()
        # fields[0] is the state, field 3 of proc(5); the start time, field 22, is in clock ticks after boot
        age = time.clock_gettime(time.CLOCK_BOOTTIME) - int(fields[19]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        return None
    return time.perf_counter() - age if age >= 0.0 else None


def log_to_stderr(message: str) -> None:
    """A progress message on its own line on stderr (the runner's ``RunOptions.log``)."""
    print(message, file=sys.stderr, flush=True)


def filter_names(text: str | None) -> tuple[str, ...] | None:
    """``--filters a,b`` as ``("a", "b")``; None when the option was not given (the run file's filters).
    An option that names no filter (``--filters ''``) is refused rather than read as not given."""
    if text is None:
        return None
    names = tuple(name.strip() for name in text.split(",") if name.strip())
    if not names:
        raise InputError(f"--filters {text!r} names no filter; give a comma-separated list (e.g. ekf,ukf) "
                         "or leave the option out for the run file's filters")
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise InputError(f"--filters {text!r} lists {', '.join(repeated)} more than once; give each filter once")
    return names


def run(args: argparse.Namespace) -> int:
    started = command_started(args)
    from ..studies.runner import RunOptions, run_study
    from ..studies.flags import check_run_flags
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
    filters = filter_names(args.filters)
    # options the study would ignore are refused before any work (opnav.studies.flags)
    filters = check_run_flags(run_file, filters=filters, mode=args.mode, checked=args.checked, workers=args.workers)
    # kernels not in numba's cache compile here, announced, not inside a progress bar's first step
    compile_for_run(run_uses(run_file, filters, args.mode), show=not args.no_progress, workers=args.workers)
    summary = run_study(run_file, RunOptions(out=args.out, filters=filters, mode=args.mode,
                                             progress=not args.no_progress, checked=args.checked,
                                             workers=args.workers, log=None if args.no_progress else log_to_stderr,
                                             started=started, report_frame=args.report_frame,
                                             # the provenance's command line: this process's, when it is the command
                                             command=tuple(sys.argv) if own_process(args) else None))
    if not args.no_progress:
        log_to_stderr(stage_line(summary["stages_wall_s"]))
    status = print_summary(summary, args.out)
    if own_process(args):
        import gc

        # the process ends here: its exit then skips the collector's sweeps over every object left
        # (half a second of an S1 run, after the last stage was timed)
        gc.freeze()
    return status


def stage_line(walls: dict[str, float]) -> str:
    """One line of a run's stage walls (``summary.json`` ``stages_wall_s``) and their sum."""
    return ("stages: " + ", ".join(f"{name} {wall:.1f} s" for name, wall in walls.items())
            + f"; total {sum(walls.values()):.1f} s")


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
