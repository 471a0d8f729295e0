"""``opnav navigate``: run a navigation filter over a measurement file.

Reads measurement records (:func:`opnav.records.read_csv`, or a CCSDS TDM through
:func:`opnav.ccsds.read_tdm`, with the covariances, exact epochs and moon pairs of its sidecar
``FILE.tdm.cov.csv`` when it is beside it) and the
``[navigation]`` section of a scenario file (:mod:`opnav.filters.options`), builds the
dynamics (:mod:`opnav.dynamics`), the measurement model
(:class:`opnav.measurements.ProbeMeasurementModel`) and the chosen filter, runs
it and writes, atomically, into ``--out``:

- ``estimates.csv``: epoch, state (km, km/s, ICRF, dynamics centre) and 1-sigmas (after each
  record; the smoothed trajectory for ``wls``; the fused estimates for ``federated``);
- ``covariances.csv``: epoch and the upper triangle of P (km^2, km^2/s, km^2/s^2 blocks);
- ``residuals.csv``: per record: kind, target, accepted, NIS, reason, residual (record units);
- ``estimates.oem``: the same estimates with their covariance as a CCSDS OEM (:mod:`opnav.ccsds`,
  the last estimate of each epoch; ``OBJECT_NAME`` the spacecraft: ``[scenario] spacecraft`` or
  ``name`` of the ``--scenario`` file, else its file name without ``.toml``), and
  ``measurements.tdm`` with ``measurements.tdm.cov.csv``: the RA/Dec records as a CCSDS TDM;
- ``summary.json``: counts, NIS statistics, final estimate, wall time and ``consistency``
  (:mod:`opnav.filters.monitor`: flags such as ``nis_out_of_band`` or ``particles_degenerate``
  and whether the final estimate is ``usable``).

It prints the records accepted, the final estimate (epoch UTC; position, km, and velocity, km/s,
ICRF, relative to the dynamics' centre) with its 1-sigmas, and the consistency flags.

``--scenario`` takes any TOML file with a ``[navigation]`` section (docs/formats/navigation.md):
the packaged ``opnav/data/demo.toml``, the scene files ``samples/s1_render.toml`` and
``samples/s3_render.toml``, and the run files ``samples/s1_jul_both_0.1.toml`` and
``samples/s3_geo.toml`` (their study's filter set-up, for the ``measurements.csv`` that
``opnav run`` writes). A file without one is refused naming the files that have one.

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
                                             "(.tdm or .xml; RADEC angles; its covariances and moon pairs "
                                             "from FILE.cov.csv beside it when there is one)")
    parser.add_argument("--tdm-sigma-arcsec", type=float, default=None,
                        help="1-sigma of each TDM angle, arcsec, for TDMs without opnav's covariance comment or "
                             "sidecar (those written by opnav have them)")
    parser.add_argument("--scenario", required=True,
                        help="TOML file with a [navigation] section (docs/formats/navigation.md): a scene file such "
                             "as opnav/data/demo.toml or samples/s1_render.toml, or a run file such as "
                             "samples/s1_jul_both_0.1.toml")
    parser.add_argument("--filter", choices=FILTERS, default=None, help="filter (default: [navigation] filter)")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--exact", action="store_true",
                        help="propagate with DOP853 and the exact ephemeris instead of the compiled fast path "
                             "(same answers to < 1%% of the filter sigma, ~20x slower); also [navigation] propagation")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def load_scenario(path: str):
    """The ``[navigation]`` of ``--scenario`` file ``path`` (:func:`opnav.filters.options.load_navigation`);
    ``InputError`` naming the nearest file when it does not exist, and the files that have a
    ``[navigation]`` section when it has none."""
    from ..config import describe_kind, read_toml
    from ..filters.options import load_navigation, navigation_files

    data = read_toml(path, kind="--scenario file")
    if not isinstance(data.get("navigation"), dict):
        why = ""
        head = data.get("scenario")
        study = head.get("study") if isinstance(head, dict) else None
        from ..studies import STUDIES

        if isinstance(study, str) and study in STUDIES and not STUDIES[study].generic_filters:
            why = f"; study {study} evaluates its own filters and writes no records to navigate"
        raise InputError(f"{path}: no [navigation] section (it is {describe_kind(data)}{why}); files with one: "
                         f"{', '.join(navigation_files())}; the section is documented in docs/formats/navigation.md")
    return load_navigation(path)


def spacecraft_name(path: str) -> str:
    """The spacecraft of ``--scenario`` file ``path`` for the OEM and TDM: its ``[scenario] spacecraft``,
    else its ``[scenario] name``, else the file's name without ``.toml``."""
    from ..config import read_toml

    head = read_toml(path, kind="--scenario file").get("scenario")
    head = head if isinstance(head, dict) else {}
    for key in ("spacecraft", "name"):
        value = head.get(key)
        if isinstance(value, str) and value.strip() and value == value.strip() and value.isprintable():
            return value
    return Path(path).stem


def final_lines(summary: dict) -> list[str]:
    """The final estimate of a ``summary.json`` (:func:`opnav.filters.navigate.navigation_summary`):
    epoch, position (km) and velocity (km/s) relative to the centre, ICRF, with their 1-sigmas, and the
    consistency flags."""
    final = summary["final"]
    state, sigma = final["state"], final["sigma"]
    lines = [f"final estimate at {final['epoch_utc']} UTC (ICRF, relative to {summary['center']}):",
             "  position " + " ".join(f"{v:17.3f}" for v in state[:3]) + " km    1-sigma "
             + " ".join(f"{v:10.4g}" for v in sigma[:3]) + " km",
             "  velocity " + " ".join(f"{v:17.9f}" for v in state[3:6]) + " km/s  1-sigma "
             + " ".join(f"{v:10.4g}" for v in sigma[3:6]) + " km/s"]
    consistency = summary.get("consistency")
    if consistency is None:
        lines.append(f"consistency: not checked for {summary['filter']} (a batch solution has no per-record NIS)")
    else:
        nis = summary.get("nis")
        band = (f"; NIS mean {nis['mean']:.2f} for {nis['mean_dof']} dof (95 % band {nis['bounds95_for_mean'][0]:.2f}"
                f" to {nis['bounds95_for_mean'][1]:.2f})") if nis else ""
        lines.append(f"consistency: {'usable' if consistency['usable'] else 'NOT USABLE'}; flags: "
                     f"{', '.join(consistency['flags']) or 'none'}{band}")
    return lines


def run(args: argparse.Namespace) -> int:
    from ..constants import ARCSEC_RAD
    from ..files import folder_lock
    from ..filters.estimates import write_navigation_outputs
    from ..filters.navigate import navigate, navigation_summary, read_measurements

    nav = load_scenario(args.scenario)
    sigma = args.tdm_sigma_arcsec
    if sigma is not None and not (math.isfinite(sigma) and sigma > 0.0):
        raise InputError(f"--tdm-sigma-arcsec must be a positive number, got {sigma!r}")
    records = read_measurements(args.measurements, tdm_sigma_rad=None if sigma is None else sigma * ARCSEC_RAD)
    result = navigate(records, nav, filter_name=args.filter, exact=args.exact, progress=not args.no_progress,
                      source=str(args.scenario))
    summary = navigation_summary(result, records, measurements=str(args.measurements), scenario=str(args.scenario))
    out = Path(args.out)
    with folder_lock(out):  # another command writing the same folder would mix its files with these
        write_navigation_outputs(out, result.track, result.history, records, summary,
                                 spacecraft=spacecraft_name(args.scenario))
    name = result.filter
    print(f"{name}: {summary['accepted']}/{summary['records']} records accepted ({summary['rejected']} refused)")
    for line in final_lines(summary):
        print(line)
    print(f"outputs in {out} (estimates.csv, covariances.csv, residuals.csv, estimates.oem, summary.json)")
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
