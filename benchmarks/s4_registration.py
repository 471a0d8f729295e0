"""S4: federated angle + stellar-Doppler navigation at Mars approach, with and without time registration.

Set-up (docs/studies.md#s4-mars-approach):
- window 2021-01-15 05:46:07 UTC to 2021-01-25 18:40:00 UTC;
- trajectory (stated here, S4 gives none): a heliocentric Lambert arc from the
  Earth on 2020-07-23 04:00 UTC (Tianwen-1's launch) to Mars on 2021-02-10
  11:52 UTC (its arrival), two-body, evaluated at the window start; that state
  is then propagated as truth with ``approach_model()`` (Sun + Earth + Mars + SRP);
  the script prints the state and the distance to Mars;
- angle sensor every 60 s: geometric lines of sight probe->Sun and probe->Mars
  (light time on), 2" (1-sigma) per transverse axis, turned into the S4 eq. 1
  position pseudo-measurement by :func:`opnav.measurements.position_measurement`;
- velocity sensor every 600 s, 1 m/s: Doppler of the Sun, Canopus (HIP 30438)
  and Vega (HIP 91262) with the catalog space velocities (``opnav.catalog``);
- the angle data lead the velocity clock by ``--lead-s`` (default 30 s): an
  angle sample is taken at ``t - lead`` for fusion epoch ``t``;
- federated UKF (angle local + velocity local, beta = 0.5 each, fusion-reset)
  fused every 60 s on the velocity clock; initial error dr = [1000, 1000, 1000] km,
  dv = [100, 100, 100] m/s.
Three runs on the same data: exact (each record at its own time tag), registered
(three-point Lagrange extrapolation to the fusion epochs) and unregistered (the
latest angle sample used as if taken at the fusion epoch). A plot of the
position error of each with the registered run's 3-sigma is saved.

Usage::

    .venv/bin/python benchmarks/s4_registration.py --hours 252 --out out/benchmarks/s4_registration.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from opnav.studies.s4 import START_UTC, Settings, build_case, run_cases  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--hours", type=float, default=None, help="arc length (default: the whole window)")
    parser.add_argument("--lead-s", type=float, default=30.0, help="angle data lead the velocity clock by this")
    parser.add_argument("--seed", type=int, default=2021)
    parser.add_argument("--out", type=Path, default=Path("out/benchmarks/s4_registration.png"))
    args = parser.parse_args()
    case = build_case(Settings(duration_hours=args.hours or 0.0, lead_s=args.lead_s), args.seed)
    facts = case.facts
    x0 = np.array(facts["state_at_start_km_km_s"])
    print(f"S4 trajectory at {START_UTC} UTC (heliocentric ICRF): r = {np.array2string(x0[:3], precision=1)} km,"
          f" v = {np.array2string(x0[3:], precision=6)} km/s")
    print(f"  distance to Mars at start: {facts['distance_to_mars_start_km'] / 1e6:.2f} million km, at end: "
          f"{facts['distance_to_mars_end_km'] / 1e6:.2f} million km")
    print("  star radial velocities from the catalog: "
          + ", ".join(f"HIP {k}: {v:+.2f} km/s" for k, v in facts["star_radial_velocity_km_s"].items()))
    print(f"  eq. 1 position pseudo-measurement: median 1-sigma {facts['position_pseudo_measurement_sigma_km']:.0f} km"
          f" per axis; lead {args.lead_s:.0f} s x |v| {np.linalg.norm(x0[3:]):.1f} km/s = "
          f"{args.lead_s * np.linalg.norm(x0[3:]):.0f} km")
    results = run_cases(case)
    days = (case.epochs - case.t0) / 86_400.0
    fig, ax = plt.subplots(figsize=(9, 5))
    print("final errors (fused estimate at the last epoch):")
    for name, result in results.items():
        x, sigma, refused, wall = result.states, result.sigma, result.refused, result.wall_s
        err = x[:, :3] - case.truth[:, :3]
        verr = x[:, 3:] - case.truth[:, 3:]
        ax.semilogy(days, np.linalg.norm(err, axis=1), label=f"{name}: |dr|")
        print(f"  {name:12s} {len(case.cases[name]):6d} records, {refused} refused, {wall:6.1f} s; "
              f"|dr| {np.linalg.norm(err[-1]):9.1f} km  (1-sigma {np.linalg.norm(sigma[-1, :3]):8.1f} km),"
              f" |dv| {1e3 * np.linalg.norm(verr[-1]):7.3f} m/s (1-sigma {1e3 * np.linalg.norm(sigma[-1, 3:]):6.3f} m/s),"
              f" max |dr_i|/sigma_i {np.max(np.abs(err[-1]) / sigma[-1, :3]):5.2f}")
    sigma_reg = results["registered"].sigma
    ax.semilogy(days, 3.0 * np.linalg.norm(sigma_reg[:, :3], axis=1), "k--", label="registered: 3-sigma")
    ax.set_xlabel(f"days since {START_UTC} UTC")
    ax.set_ylabel("position error, km")
    ax.set_title(f"S4 federated angle + Doppler navigation, angle data lead by {args.lead_s:.0f} s")
    ax.legend()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=120, bbox_inches="tight")
    print(f"plot saved to {args.out}")


if __name__ == "__main__":
    main()
