"""``opnav observability``: S2 observability table (model 1 or 2) for the built capture arc."""

from __future__ import annotations

import argparse
import json

import numpy as np

from ..epochs import format_epoch
from ..errors import InputError
from ..observability import format_table
from ..studies.s2_observability import S2_PAPER_TABLES, S2Study, s2_observability
from ..studies.trajectories import mars_capture_trajectory

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


def study_to_dict(study: S2Study) -> dict:
    """JSON-ready figures of a study (lengths km, velocities m/s, angles deg)."""
    return {
        "model": study.model,
        "sigma_arcsec": study.sigma_arcsec,
        "stars_hip": list(study.star_hip),
        "arc_start_tdb": format_epoch(float(study.t_tdb_s[0]), "tdb"),
        "arc_end_tdb": format_epoch(float(study.t_tdb_s[-1]), "tdb"),
        "epochs": int(study.t_tdb_s.size),
        "sets": [
            {
                "name": rep.name,
                "rank": rep.rank,
                "singular_values": rep.singular_values.tolist(),
                "eta": rep.eta,
                "condition_number": rep.condition_number,
                "crb_position_km": rep.crb_sigma[:3].tolist(),
                "crb_velocity_m_s": (rep.crb_sigma[3:6] * 1e3).tolist(),
                "column_scale_km_km_s": rep.column_scale.tolist(),
                "paper": list(S2_PAPER_TABLES[study.model].get(rep.name, ())),
            }
            for rep in study.reports
        ],
        "visibility": [
            {
                "target": vis.target,
                "occulted_epochs": int(np.count_nonzero(vis.occulted)),
                "eclipsed_epochs": int(np.count_nonzero(vis.eclipsed)),
                "min_sun_separation_deg": float(np.degrees(vis.sun_separation_rad.min())),
            }
            for vis in study.visibility
        ],
    }


def paper_columns(model: int) -> dict[str, tuple[str, ...]]:
    """The paper's Table 1 or 2 entries as short strings for :func:`opnav.observability.format_table`."""
    return {name: tuple(f"{value:.5g}" for value in row) for name, row in S2_PAPER_TABLES[model].items()}


def run(args: argparse.Namespace) -> int:
    if not args.sigma_arcsec > 0.0:
        raise InputError(f"--sigma-arcsec must be positive, got {args.sigma_arcsec!r}")
    trajectory = mars_capture_trajectory(step_s=args.step_s)
    study = s2_observability(args.model, trajectory=trajectory, sigma_arcsec=args.sigma_arcsec,
                             arc_days=args.arc_days, stop_before_periapsis_s=args.stop_before_periapsis_s)
    if args.json:
        print(json.dumps(study_to_dict(study), indent=2))
        return 0
    print(f"S2 model {args.model}: {study.t_tdb_s.size} epochs {format_epoch(float(study.t_tdb_s[0]), 'tdb')} .. "
          f"{format_epoch(float(study.t_tdb_s[-1]), 'tdb')} TDB, sigma {study.sigma_arcsec:g}\" per angle, "
          f"stars HIP {', '.join(map(str, study.star_hip))}; figures in km and m/s, CRB at the arc start")
    print(format_table(list(study.reports), paper=paper_columns(args.model)))
    for vis in study.visibility:
        print(f"  {vis.target:<7} occulted by Mars at {np.count_nonzero(vis.occulted)} epochs, "
              f"eclipsed at {np.count_nonzero(vis.eclipsed)}, min Sun separation "
              f"{np.degrees(vis.sun_separation_rad.min()):.1f} deg")
    return 0
