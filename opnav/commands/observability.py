"""``opnav observability``: S2 observability table (model 1 or 2) for the built capture arc.

The study is :func:`opnav.studies.s2_observability.s2_observability`, its figures
:func:`opnav.studies.report.observability_figures`; this module parses arguments and prints.
"""

from __future__ import annotations

import argparse
import json

NAME = "observability"
HELP = "S2 observability of starlight-angle sets on the Mars capture arc (PWCS rank, FIM eta, kappa, CRB)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", type=int, choices=(1, 2), required=True,
                        help="1: heliocentric, before the SOI crossing; 2: Mars-centred, inside the SOI")
    parser.add_argument("--sigma-arcsec", type=float, default=1.0, help="1-sigma of each starlight angle (default 1)")
    parser.add_argument("--step-s", type=float, default=3600.0, help="measurement / PWCS step, s (default 3600)")
    parser.add_argument("--arc-days", type=float, default=2.0,
                        help="model 1: arc length before the SOI crossing, days (default 2)")
    parser.add_argument("--stop-before-periapsis-s", type=float, default=7200.0,
                        help="model 2: end of the arc before periapsis, s (default 7200)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of the table")


def run(args: argparse.Namespace) -> int:
    from ..epochs import format_epoch
    from ..errors import InputError
    from ..observability import format_table
    from ..studies.report import observability_figures, observability_paper_columns
    from ..studies.s2_observability import s2_observability
    from ..studies.trajectories import mars_capture_trajectory

    if not args.sigma_arcsec > 0.0:
        raise InputError(f"--sigma-arcsec must be positive, got {args.sigma_arcsec!r}")
    trajectory = mars_capture_trajectory(step_s=args.step_s)
    study = s2_observability(args.model, trajectory=trajectory, sigma_arcsec=args.sigma_arcsec,
                             arc_days=args.arc_days, stop_before_periapsis_s=args.stop_before_periapsis_s)
    figures = observability_figures(study)
    if args.json:
        print(json.dumps(figures, indent=2))
        return 0
    print(f"S2 model {args.model}: {figures['epochs']} epochs {format_epoch(float(study.t_tdb_s[0]), 'tdb')} .. "
          f"{format_epoch(float(study.t_tdb_s[-1]), 'tdb')} TDB, sigma {study.sigma_arcsec:g}\" per angle, "
          f"stars HIP {', '.join(map(str, study.star_hip))}; figures in km and m/s, CRB at the arc start")
    print(format_table(list(study.reports), paper=observability_paper_columns(args.model)))
    for vis in figures["visibility"]:
        print(f"  {vis['target']:<7} occulted by Mars at {vis['occulted_epochs']} epochs, "
              f"eclipsed at {vis['eclipsed_epochs']}, min Sun separation "
              f"{vis['min_sun_separation_deg']:.1f} deg")
    return 0
