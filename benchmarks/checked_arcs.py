"""Long-run numerical health: 30-day, 1-minute S1 arcs with every covariance checked.

Runs ``opnav run samples/s1_jul_both_0.1.toml --checked`` (EKF, UKF, SR-UKF; 86,400 RA/Dec
records) and prints, per filter: records checked, the largest relative asymmetry of P,
the smallest eigenvalue ratio of the diagonally scaled P over the arc, position RMS, NEES,
consistency flags and wall time. A covariance that is not finite, symmetric and positive
definite after any record stops the run with the record named.

Usage::

    .venv/bin/python benchmarks/checked_arcs.py [--days 30] [--filters ekf,ukf,sr-ukf]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from opnav.studies.runner import RunOptions, run_study
from opnav.studies.settings import load_run_file

ROOT = Path(__file__).resolve().parent.parent


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runfile", default=str(ROOT / "samples" / "s1_jul_both_0.1.toml"))
    parser.add_argument("--days", type=float, default=30.0)
    parser.add_argument("--filters", default="ekf,ukf,sr-ukf")
    args = parser.parse_args(argv)
    run = load_run_file(args.runfile, {"duration_days": str(args.days)})
    with tempfile.TemporaryDirectory() as out:
        summary = run_study(run, RunOptions(out=Path(out), filters=tuple(args.filters.split(",")), progress=False,
                                            checked=True))
    print(f"{run.name}: {summary['measurements']['records']} records over {args.days:g} days, every covariance checked")
    for name, figures in summary["filters"].items():
        health = figures["covariance_health"]
        print(f"{name:7s} checked {health['records_checked']} records: max asymmetry {health['max_asymmetry']:.2g}, "
              f"min scaled eigenvalue ratio {health['min_scaled_eigenvalue_ratio']:.3g}; position RMS "
              f"{figures['position_rms_km']:.3f} km, NEES {figures['nees_mean']:.2f}, flags "
              f"{figures['consistency']['flags'] or 'none'}, {figures['wall_s']:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
