"""S2 model switching: one EKF over the Mars capture arc, model 1 + MPD outside the SOI, model 2 + MPS inside.

For ``--seeds`` seeds (initial error and measurement noise): the share of records accepted,
the NEES over the second half of each phase (mean over seeds beside the 95 % band of the mean
of ``seeds`` chi-square(6) values), and the position and velocity error after convergence
(second half of each phase: mean and variance of the error magnitudes over epochs and seeds),
beside S2 Table 3 for MPD (model 1) and MPS (model 2). The paper gives neither the initial
error nor the angle noise; they are ``--sigma-position-km``, ``--sigma-velocity-km-s`` and
``--sigma-arcsec`` here. See :func:`opnav.studies.s2_observability.s2_switching_run`.

Usage::

    .venv/bin/python benchmarks/s2_switching.py --seeds 10
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import stats

from opnav.studies.s2_observability import s2_switching_run
from opnav.studies.trajectories import mars_capture_trajectory

#: S2 Table 3: position error mean (km) / variance (km^2), velocity mean (km/s) / variance.
S2_TABLE3 = {"MPD": (5.0314, 6.7987, 0.0093, 0.0054), "MPS": (14.5518, 16.2534, 0.0045, 0.0023)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--sigma-arcsec", type=float, default=1.0)
    parser.add_argument("--sigma-position-km", type=float, default=100.0)
    parser.add_argument("--sigma-velocity-km-s", type=float, default=1e-3)
    args = parser.parse_args()
    trajectory = mars_capture_trajectory(step_s=600.0)
    runs, walls = [], []
    for seed in range(args.seeds):
        begin = time.perf_counter()
        runs.append(s2_switching_run(seed, trajectory=trajectory, sigma_arcsec=args.sigma_arcsec,
                                     sigma_position_km=args.sigma_position_km,
                                     sigma_velocity_km_s=args.sigma_velocity_km_s))
        walls.append(time.perf_counter() - begin)
    band = stats.chi2.ppf([0.025, 0.975], 6 * args.seeds) / args.seeds
    print(f"S2 switching EKF, MPD -> MPS at the SOI, {args.seeds} seeds, {args.sigma_arcsec:g}\" angles, "
          f"{np.mean(walls):.1f} s/run; accepted {np.mean([r.accepted_fraction for r in runs]):.2%} of the records")
    for name, inside in (("MPD", False), ("MPS", True)):
        nees_means, pos, vel, sig = [], [], [], []
        for r in runs:
            idx = np.flatnonzero(r.inside_soi == inside)
            half = idx[idx.size // 2:]
            e, P = r.errors[half], r.covariances[half]
            nees_means.append(np.mean([x @ np.linalg.solve(c, x) for x, c in zip(e, P)]))
            pos.append(np.linalg.norm(e[:, :3], axis=1))
            vel.append(np.linalg.norm(e[:, 3:], axis=1))
            sig.append(np.sqrt(np.trace(P[-1, :3, :3])))
        pos, vel = np.concatenate(pos), np.concatenate(vel)
        paper = S2_TABLE3[name]
        verdict = "in band" if band[0] <= np.mean(nees_means) <= band[1] else "OUT of band"
        print(f"  {name}: NEES {np.mean(nees_means):5.2f} ({verdict} [{band[0]:.2f}, {band[1]:.2f}]); "
              f"position error {pos.mean():8.3f} km (var {pos.var():8.3f}; paper {paper[0]} / {paper[1]}), "
              f"velocity {vel.mean():.5f} km/s (var {vel.var():.2e}; paper {paper[2]} / {paper[3]}); "
              f"filter 1-sigma at the phase end {np.mean(sig):.3f} km")
    switch = runs[0].switch
    print(f"  switch at TDB {switch.t_tdb_s:.1f} s: sun -> mars origin, covariance carried over unchanged")


if __name__ == "__main__":
    main()
