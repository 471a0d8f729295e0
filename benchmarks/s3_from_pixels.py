"""S3 from pixels against S3 from measurements at the noise the image stage achieved.

For each seed, ``opnav run samples/s3_geo.toml --mode images`` (the star sensor and the UV
Earth sensor rendered and measured along the 24-hour GEO arc, :mod:`opnav.studies.s3_images`;
a run already in ``--out``/s<seed> is reused) and its measurement-level twins: the same epochs,
stars and record covariances, each value drawn from that covariance around the truth's
prediction (:mod:`twins`; ``--twin-draws`` a seed, averaged: over the last 12 h the error lies
along the weakly observed cross-track axis, so one twin cannot stand for the expectation).
Prints per seed and over the seeds: the image stage's angle and elevation error RMS against
the truth, the median 1-sigma it reported, their correlation and the mean chi-square per
degree of freedom; each filter's position RMS over the last 12 h from pixels and the mean over
that seed's twins, and their ratio; NEES (mean and share of epochs inside the 95 % band of
chi-square(6)); and the image-mode simulation's wall time.

Usage::

    .venv/bin/python benchmarks/s3_from_pixels.py --seeds 1,2,3 --filters ekf,ukf
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from opnav.constants import ARCSEC_RAD
from opnav.studies.runner import RunOptions, run_study, simulate_stage
from opnav.studies.settings import load_run_file
from twins import twin_means

ROOT = Path(__file__).resolve().parent.parent
RUN_FILE = ROOT / "samples" / "s3_geo.toml"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="1,2,3")
    parser.add_argument("--filters", default="ekf,ukf")
    parser.add_argument("--out", default="out/s3_pixels", help="folder of the image-mode runs (s<seed>), reused")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="run-file setting")
    parser.add_argument("--workers", type=int, default=None, help="processes of the image mode (default: one per core)")
    parser.add_argument("--twin-draws", type=int, default=10, help="measurement-level twins a seed (module docstring)")
    args = parser.parse_args(argv)
    logging.getLogger("opnav").setLevel(logging.ERROR)
    filters = tuple(args.filters.split(","))
    overrides = dict(item.split("=", 1) for item in args.set)
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        run = load_run_file(RUN_FILE, {**overrides, "seed": str(seed)})
        out = Path(args.out) / f"s{seed}"
        image = run_study(run, RunOptions(out=out, filters=filters, mode="images", progress=False, workers=args.workers))
        sim, key, _ = simulate_stage(run, out, lambda message: None, "images")
        rows.append((seed, image, twin_means(sim, key, seed, args.twin_draws, filters, out)))
    print("| seed | angle RMS / median 1-sigma (\") | elevation RMS / median 1-sigma (\") | correlation | "
          "chi2/dof | filter | RMS from pixels (km) | RMS from the twins, mean (km) | ratio | NEES mean (in 95 % band) "
          "pixels / twin | simulate (min) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    ratios: dict = {}
    for seed, image, measured in rows:
        errors = image["facts"]["measurement_errors"]
        for name in filters:
            pix, twin = image["filters"][name], measured[name]
            ratio = pix["position_rms_km"] / twin["position_rms_km"]
            ratios.setdefault(name, []).append((pix["position_rms_km"], twin["position_rms_km"], ratio,
                                                pix["nees_mean"], pix["nees_fraction_in_95"]))
            print(f"| {seed} | {errors['angle_rms_arcsec']:.3f} / {errors['angle_median_sigma_arcsec']:.3f} | "
                  f"{errors['elevation_rms_arcsec']:.3f} / {errors['elevation_median_sigma_arcsec']:.3f} | "
                  f"{errors['correlation_median']:.2f} | {errors['chi2_mean_per_dof']:.3f} | {name} | "
                  f"{pix['position_rms_km']:.4f} | {twin['position_rms_km']:.4f} | {ratio:.2f} | "
                  f"{pix['nees_mean']:.2f} ({pix['nees_fraction_in_95']:.1%}) / {twin['nees_mean']:.2f} "
                  f"({twin['nees_fraction_in_95']:.1%}) | {image['stages_wall_s'].get('simulate', float('nan')) / 60:.1f} |")
    print(f"\n(twins: {args.twin_draws} a seed; the twin column is the mean and sd over the seeds of each seed's twin mean)")
    print("\n| filter | seeds | RMS from pixels mean +- sd (km) | RMS from the twins mean +- sd (km) | ratio of means | "
          "NEES mean from pixels | share in 95 % band |")
    print("|---|---|---|---|---|---|---|")
    for name, values in ratios.items():
        values = np.array(values)
        spread = (lambda column: column.std(ddof=1) if len(column) > 1 else 0.0)
        print(f"| {name} | {len(values)} | {values[:, 0].mean():.4f} +- {spread(values[:, 0]):.4f} | "
              f"{values[:, 1].mean():.4f} +- {spread(values[:, 1]):.4f} | {values[:, 0].mean() / values[:, 1].mean():.2f} | "
              f"{values[:, 3].mean():.2f} | {values[:, 4].mean():.1%} |")
    print(f"\n(angles in arcsec: 1\" = {ARCSEC_RAD:.3e} rad; RMS over the last 12 h)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
