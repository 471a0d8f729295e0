"""``opnav navigate``: run a navigation filter over a measurement file.

Reads measurement records (:func:`opnav.records.read_csv`, or a CCSDS TDM through
:func:`opnav.ccsds.read_tdm`) and the
``[navigation]`` section of a scenario file (:mod:`opnav.filters.options`), builds the
dynamics (:mod:`opnav.dynamics`), the measurement model
(:class:`opnav.measurements.ProbeMeasurementModel`) and the chosen filter, runs
it and writes, atomically, into ``--out``:

- ``estimates.csv``: epoch, state (km, km/s, ICRF, dynamics centre) and 1-sigmas (after each
  record; the smoothed trajectory for ``wls``; the fused estimates for ``federated``);
- ``covariances.csv``: epoch and the upper triangle of P (km^2, km^2/s, km^2/s^2 blocks);
- ``residuals.csv``: per record: kind, target, accepted, NIS, reason, residual (record units);
- ``estimates.oem``: the same estimates with their covariance as a CCSDS OEM (:mod:`opnav.ccsds`,
  the last estimate of each epoch), and ``measurements.tdm``: the RA/Dec records as a CCSDS TDM;
- ``summary.json``: counts, NIS statistics, final estimate, wall time and ``consistency``
  (:mod:`opnav.filters.monitor`: flags such as ``nis_out_of_band`` or ``particles_degenerate``
  and whether the final estimate is ``usable``).

Exit status: 0 when the final estimate is usable (flags are printed as warnings),
3 when it is not (most records refused, NIS out of its band at the end, or a
degenerate particle cloud at the end); the outputs are written either way.

The work is :func:`opnav.filters.navigate.navigate` (any filter by name) and
:func:`opnav.filters.estimates.write_navigation_outputs`; this module parses arguments and prints.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from ..errors import InputError

NAME = "navigate"
HELP = "run a navigation filter (EKF/UKF/PF/WLS/...) over a measurement CSV"
#: Exit status when the run finished but its final estimate is not to be used.
EXIT_UNUSABLE = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..filters.option_types import FILTERS

    parser.add_argument("measurements", help="measurement CSV (opnav.records format) or CCSDS TDM "
                                             "(.tdm or .xml; RADEC angles)")
    parser.add_argument("--tdm-sigma-arcsec", type=float, default=None,
                        help="1-sigma of each TDM angle, arcsec, for TDMs that do not carry opnav's covariance "
                             "comments (those written by opnav do)")
    parser.add_argument("--scenario", required=True, help="scenario TOML with a [navigation] section")
    parser.add_argument("--filter", choices=FILTERS, default=None, help="filter (default: [navigation] filter)")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--exact", action="store_true",
                        help="propagate with DOP853 and the exact ephemeris instead of the compiled fast path "
                             "(same answers to < 1%% of the filter sigma, ~20x slower); also [navigation] propagation")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def run(args: argparse.Namespace) -> int:
    from ..constants import ARCSEC_RAD
    from ..filters.estimates import write_navigation_outputs
    from ..filters.navigate import navigate, navigation_summary, read_measurements
    from ..filters.options import load_navigation

    nav = load_navigation(args.scenario)
    sigma = args.tdm_sigma_arcsec
    if sigma is not None and not (math.isfinite(sigma) and sigma > 0.0):
        raise InputError(f"--tdm-sigma-arcsec must be a positive number, got {sigma!r}")
    records = read_measurements(args.measurements, tdm_sigma_rad=None if sigma is None else sigma * ARCSEC_RAD)
    result = navigate(records, nav, filter_name=args.filter, exact=args.exact, progress=not args.no_progress,
                      source=str(args.scenario))
    summary = navigation_summary(result, records, measurements=str(args.measurements), scenario=str(args.scenario))
    out = Path(args.out)
    write_navigation_outputs(out, result.track, result.history, records, summary)
    name = result.filter
    print(f"{name}: {summary['accepted']}/{summary['records']} records accepted; outputs in {out}")
    consistency = summary.get("consistency")
    if consistency is None:
        return 0
    for message in consistency["messages"]:
        print(f"warning: {name}: {message}", file=sys.stderr)
    if not consistency["usable"]:
        print(f"error: {name}: the final estimate is not usable ({', '.join(consistency['flags'])}); "
              f"see {out / 'summary.json'}", file=sys.stderr)
        return EXIT_UNUSABLE
    return 0
