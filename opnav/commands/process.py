"""``opnav process``: turn a directory of frames into time-tagged measurements.

Example::

    opnav process out/frames --targets phobos deimos --out measurements.csv

reads every FITS frame (opnav header: epoch, WCS, detector, observer state), identifies the stars
around the WCS attitude, measures the targets and writes the records as CSV plus a ``.json``
metadata file (:func:`opnav.records.write_csv`). Frames that cannot be used are listed there
under ``skipped``. A tqdm progress bar shows the frames done. The work is
:func:`opnav.image.directory.process_folder`; this module parses arguments and prints.
"""

from __future__ import annotations

import argparse
import math

from ..errors import InputError

NAME = "process"
OUT = "file"
HELP = "process a directory of FITS frames into measurement records (CSV + JSON)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("frames_dir", help="directory of FITS frames written by `opnav render`")
    parser.add_argument("--out", default="measurements.csv", help="output CSV (default measurements.csv)")
    parser.add_argument("--targets", nargs="*", default=[], help="bodies to measure: phobos deimos mars earth")
    parser.add_argument("--catalog", default=None, help="star catalog file (default: the packaged catalog)")
    parser.add_argument("--no-catalog", action="store_true", help="skip star identification; use the WCS attitude")
    parser.add_argument("--prior-sigma-deg", type=float, default=0.05, help="a-priori attitude error per axis, deg")
    parser.add_argument("--seed", type=int, default=0, help="random seed (star-ID hypotheses, RANSAC)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from ..image.directory import process_folder
    from ..image.pipeline import PipelineOptions

    if not args.prior_sigma_deg > 0:
        raise InputError(f"--prior-sigma-deg must be positive, got {args.prior_sigma_deg}")
    options = PipelineOptions(targets=tuple(args.targets), prior_sigma_rad=math.radians(args.prior_sigma_deg))
    results = process_folder(args.frames_dir, args.out, identify_stars=not args.no_catalog, catalog=args.catalog,
                             options=options, rng=args.seed, progress=not args.no_progress)
    n_records = sum(len(r.records) for r in results)
    print(f"{len(results)} frames -> {n_records} records in {args.out}")
    return 0
