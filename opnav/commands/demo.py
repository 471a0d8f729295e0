"""``opnav demo``: run the embedded default scenario end to end (:mod:`opnav.demo`).

Example::

    opnav demo --out out/demo --frames 20 --seed 7

renders the S1-like Mars-cruise frames into ``OUT/frames`` (reusing valid frames of an
earlier run), processes them into Phobos/Deimos RA/Dec records, runs the EKF and prints
measurement errors against truth, the final state error against the filter's sigmas and
NEES; ``OUT/summary.json`` and ``OUT/position_error.png`` hold the same figures.
"""

from __future__ import annotations

import argparse

NAME = "demo"
HELP = "run the embedded default scenario end to end (render -> image -> navigate -> report)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="out/demo",
                        help="output directory (default: out/demo): frames/, measurements.csv, summary.json, "
                             "position_error.png; valid frames already there are reused")
    parser.add_argument("--frames", type=int, default=None,
                        help="use only the first N frame epochs of the scenario (default: all 60, one an hour)")
    parser.add_argument("--seed", type=int, default=None,
                        help="random seed of the frames' noise and the image stage (default: the scenario's)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bars")


def run(args: argparse.Namespace) -> int:
    from ..demo import DemoOptions, format_report, run_demo

    summary = run_demo(DemoOptions(out_dir=args.out, frames=args.frames, seed=args.seed, progress=not args.no_progress))
    print(format_report(summary))
    return 0
