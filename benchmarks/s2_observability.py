"""S2 observability: our Tables 1 and 2 beside the paper's, unit dependence, single bodies, visibility.

Run: ``.venv/bin/python benchmarks/s2_observability.py [--step-s 3600] [--sigma-arcsec 1]``.

Prints, for the capture arc of :func:`opnav.studies.trajectories.mars_capture_trajectory`:

1. Tables 1 (model 1, the last 2 days before the SOI crossing) and 2 (model 2, SOI
   crossing to 2 h before periapsis) in km and m/s, with the CRB 1-sigma of the
   arc-start state, beside the paper's rank / max singular value / eta / kappa;
2. the same sets with the state in SI-like uniform units (km, km/s; m, m/s gives
   the same kappa and rank), where the velocity columns dwarf the position ones;
3. single bodies (M, P, D, S) to show where the information comes from;
4. visibility of Phobos, Deimos and the Sun on a 5-minute grid from the SOI
   crossing to periapsis (occultation by Mars, eclipse, Sun separation).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from opnav.catalog import load_catalog
from opnav.constants import ARCSEC_RAD
from opnav.dynamics import capture_model_1, capture_model_2
from opnav.epochs import format_epoch
from opnav.measurements import ProbeMeasurementModel
from opnav.observability import format_table
from opnav.studies.report import observability_paper_columns
from opnav.studies.s2_observability import (
    S2_COLUMN_SCALE,
    S2_SETS,
    S2_STARS_HIP,
    s2_arc_epochs,
    s2_observability,
    starlight_angle_observability,
)
from opnav.studies.trajectories import body_visibility, mars_capture_trajectory


def _intervals(hours: np.ndarray, mask: np.ndarray) -> str:
    if not np.any(mask):
        return "never"
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(int), 0]))
    spans = [f"{hours[a]:+.2f}..{hours[b - 1]:+.2f} h" for a, b in zip(edges[::2], edges[1::2])]
    return ", ".join(spans)


def _extra_sets(trajectory, model: int, sigma_arcsec: float, scale: np.ndarray, sets: dict) -> list:
    t = s2_arc_epochs(trajectory, model)
    rows = np.isin(trajectory.t_tdb_s, t)
    center, force_model = ("sun", capture_model_1()) if model == 1 else ("mars", capture_model_2())
    states = trajectory.states_sun if model == 1 else trajectory.states_mars
    catalog = load_catalog()
    index = [int(np.flatnonzero(catalog.hip == hip)[0]) for hip in S2_STARS_HIP]
    visible = {body: body_visibility(t, trajectory.states_mars[rows, :3], body).visible
               for body in {b for bodies in sets.values() for b in bodies}}
    return starlight_angle_observability(
        sets, force_model=force_model, measurement_model=ProbeMeasurementModel(center), t_tdb_s=t,
        state0=states[rows][0], star_units_icrf=catalog.unit_vectors()[index], sigma_rad=sigma_arcsec * ARCSEC_RAD,
        visible=visible, column_scale=scale)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--step-s", type=float, default=3600.0, help="measurement / PWCS step, s (default 3600)")
    parser.add_argument("--sigma-arcsec", type=float, default=1.0, help="1-sigma per starlight angle (default 1)")
    args = parser.parse_args()

    start = time.perf_counter()
    trajectory = mars_capture_trajectory(step_s=args.step_s)
    print(f"capture arc built in {time.perf_counter() - start:.1f} s: |v_inf| = "
          f"{np.linalg.norm(trajectory.v_inf_km_s):.3f} km/s, SOI crossing "
          f"{format_epoch(trajectory.t_soi_tdb_s, 'tdb')} TDB, periapsis "
          f"{format_epoch(trajectory.t_periapsis_tdb_s, 'tdb')} TDB "
          f"(altitude {np.linalg.norm(trajectory.states_mars[-1, :3]) - 3396.19:.1f} km)")

    for model in (1, 2):
        start = time.perf_counter()
        study = s2_observability(model, trajectory=trajectory, sigma_arcsec=args.sigma_arcsec)
        elapsed = time.perf_counter() - start
        print(f"\nTable {model} (model {model}): {study.t_tdb_s.size} epochs "
              f"{format_epoch(float(study.t_tdb_s[0]), 'tdb')} .. {format_epoch(float(study.t_tdb_s[-1]), 'tdb')} TDB, "
              f"{args.sigma_arcsec:g}\" per angle, state in km and m/s, CRB at the arc start ({elapsed:.1f} s)")
        print(format_table(list(study.reports), paper=observability_paper_columns(model)))
        for rep in study.reports:
            print(f"  {rep.name:<4} CRB per axis: position [{', '.join(f'{v:.3g}' for v in rep.crb_sigma[:3])}] km, "
                  f"velocity [{', '.join(f'{v * 1e3:.3g}' for v in rep.crb_sigma[3:])}] m/s; "
                  f"sigma_min/sigma_max of Q_s = {rep.singular_values[-1] / rep.singular_values[0]:.2e}")

        print(f"\n  model {model} with the state in uniform units (km, km/s; kappa and rank as in m, m/s):")
        uniform = _extra_sets(trajectory, model, args.sigma_arcsec, np.ones(6), dict(S2_SETS[model]))
        print("  " + format_table(uniform).replace("\n", "\n  "))
        print(f"\n  model {model} single bodies (km, m/s):")
        singles = {"M": ("mars",), "P": ("phobos",), "D": ("deimos",), "S": ("sun",)}
        print("  " + format_table(_extra_sets(trajectory, model, args.sigma_arcsec, S2_COLUMN_SCALE, singles))
              .replace("\n", "\n  "))

    fine = mars_capture_trajectory(step_s=300.0)
    inside = fine.inside_soi
    t = fine.t_tdb_s[inside]
    hours = (t - fine.t_periapsis_tdb_s) / 3600.0
    print("\nVisibility from the SOI crossing to periapsis (5-minute grid; hours relative to periapsis):")
    for body in ("mars", "phobos", "deimos", "sun"):
        vis = body_visibility(t, fine.states_mars[inside, :3], body)
        closest = np.argmin(vis.mars_separation_rad / vis.mars_angular_radius_rad)
        print(f"  {body:<7} occulted: {_intervals(hours, vis.occulted)}; "
              f"eclipsed: {_intervals(hours, vis.eclipsed)}; closest to Mars' limb {vis.mars_separation_rad[closest] / vis.mars_angular_radius_rad[closest]:.2f} "
              f"Mars radii at {hours[closest]:+.2f} h; min Sun separation {np.degrees(vis.sun_separation_rad.min()):.1f} deg")

if __name__ == "__main__":
    main()
