"""``opnav demo``: the embedded demo run (``opnav/data/demo_run.toml``) through the study runner.

Example::

    opnav demo --out out/demo --frames 20 --seed 7

is ``opnav run opnav/data/demo_run.toml --out out/demo`` with the arc cut to the first
``--frames`` hourly frames and the seed replaced: S1 from pixels from 15 July 2014 (frames
rendered into ``OUT/frames``, the image stage's Phobos/Deimos RA/Dec in
``OUT/measurements.csv`` and ``.tdm``, the EKF, ``OUT/summary.json`` and ``OUT/report.html``
with a sample frame). The summary's ``facts.measurement_errors`` compares every RA/Dec with the
frame's truth. A re-run reuses the finished stages and the frames on disk. The first run on a
machine compiles the numba kernels first, saying so (:func:`opnav.commands.compile.compile_for_run`).
"""

from __future__ import annotations

import argparse
import importlib.resources

from ..constants import DAY_S
from ..errors import InputError

NAME = "demo"
HELP = "run the embedded demo (S1 from pixels: render -> image stage -> EKF -> report)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="out/demo",
                        help="output folder (default: out/demo); finished stages and valid frames there are reused")
    parser.add_argument("--frames", type=int, default=None,
                        help="use only the first N hourly frames, N >= 2 (default: all 60)")
    parser.add_argument("--seed", type=int, default=None,
                        help="seed of the frames' noise, the image stage and the filter start (default: the run file's)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bars")


def run(args: argparse.Namespace) -> int:
    from ..studies.runner import RunOptions, run_study
    from ..studies.settings import load_run_file
    from .compile import compile_for_run, run_uses
    from .run import print_summary

    overrides = {}
    if args.frames is not None and args.frames < 2:
        raise InputError(f"--frames must be at least 2, got {args.frames}")
    if args.seed is not None:
        if args.seed < 0:
            raise InputError(f"--seed must be a non-negative integer, got {args.seed}")
        overrides["seed"] = str(args.seed)
    resource = importlib.resources.files("opnav").joinpath("data", "demo_run.toml")
    with importlib.resources.as_file(resource) as path:
        run_file = load_run_file(path, overrides)
        if args.frames is not None:  # the arc of the first N frames at the run file's own step
            overrides["duration_days"] = str(args.frames * run_file.settings.step_s / DAY_S)
            run_file = load_run_file(path, overrides)
    # on a first run, the kernels compile here, announced, and not inside the first frame's progress bar
    compile_for_run(run_uses(run_file), show=not args.no_progress)
    summary = run_study(run_file, RunOptions(out=args.out, progress=not args.no_progress))
    for name, errors in summary["facts"].get("measurement_errors", {}).items():
        print(f"{name:9s} {errors['count']} RA/Dec records: error RMS {errors['rms_arcsec'][0]:.3f}\" / "
              f"{errors['rms_arcsec'][1]:.3f}\" (RA cos dec / Dec), reported 1-sigma "
              f"{errors['median_sigma_arcsec'][0]:.3f}\" / {errors['median_sigma_arcsec'][1]:.3f}\", "
              f"mean chi2/2 {errors['chi2_mean'] / 2:.2f}")
    pairs = summary["facts"].get("measurement_pairs")
    if pairs:
        print(f"both moons in one frame: {pairs['count']} pair records (their shared attitude error as a "
              f"cross-covariance), mean chi2/4 {pairs['chi2_mean'] / 4:.2f}")
    return print_summary(summary, args.out)
