"""S4 from pixels over several seeds, beside measurement mode at the noise the pixels achieved.

For each seed (the run file's seed + 0, 1, ...), the same command a user runs::

    opnav run samples/s4_approach.toml --mode images --seed S --out OUT/images_seed_S

(the navigation camera's frames of Mars, the star tracker and the sun sensor every ``image_step_s``,
:mod:`opnav.studies.s4_images`). The achieved line-of-sight noise per axis (Mars and the Sun, against
the true geometric lines of sight) is pooled over the seeds, and measurement mode is run on the same
seeds at the same cadence and that noise::

    opnav run samples/s4_approach.toml --seed S --out OUT/measurements_seed_S \\
        --set angle_step_s=<image_step_s> --set sun_sigma_arcsec=<Sun> --set mars_sigma_arcsec=<Mars>

Printed: the achieved noise, per seed the three runs' final errors (both modes), then the
acceptance lines of issue 37 item 4:

- registered vs unregistered: converges vs diverges (final worst axis within / beyond 3 sigma) on every seed;
- the registered filter's final position error, mean over the seeds, within 1.5x of measurement mode's;
- NEES: the Monte Carlo NEES test (:func:`opnav.consistency.ensemble_nees`, 6 dof, 95 % band) over the
  second half of the arc, per run and mode;
- wrong-body records over every from-pixels run (each Mars record within 5 sigma of the truth and on its disk).

Runs already finished in ``--out`` are reused (the runner's stages).

Usage::

    .venv/bin/python benchmarks/s4_from_pixels.py --seeds 5 --out out/benchmarks/s4_from_pixels
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from opnav.consistency import ensemble_nees

ROOT = Path(__file__).resolve().parents[1]
RUN_FILE = ROOT / "samples" / "s4_approach.toml"
CASES = ("exact", "registered", "unregistered")


def opnav_run(out: Path, seed: int, sets: list[str], *, images: bool, workers: int) -> dict:
    """``opnav run`` of the S4 run file into ``out`` (reused when done); its summary."""
    command = [str(Path(sys.executable).parent / "opnav"), "run", str(RUN_FILE), "--out", str(out), "--seed", str(seed),
               "--no-progress"]
    if images:
        command += ["--mode", "images", "--workers", str(workers)]
    for item in sets:
        command += ["--set", item]
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    print(f"  {'images' if images else 'measurements'} seed {seed}: {time.perf_counter() - start:.0f} s", flush=True)
    return json.loads((out / "summary.json").read_text())


def pooled(summaries: list[dict], body: str) -> float:
    """RMS per axis (arcsec) of ``body``'s line-of-sight errors over every image-mode run."""
    figures = [s["image_mode"]["achieved_noise"][body] for s in summaries]
    count = sum(f["count"] for f in figures)
    return float(np.sqrt(sum(f["count"] * f["rms_per_axis_arcsec"] ** 2 for f in figures) / count))


def nees_test(folders: list[Path], case: str):
    """Monte Carlo NEES over the second half of the arc of ``case`` in the runs' ``evaluation.npz``."""
    runs = []
    for folder in folders:
        arrays = np.load(folder / "evaluation.npz")
        runs.append((arrays["t_tdb_s"], arrays[f"{case}_nees"]))
    t = runs[0][0]
    return ensemble_nees(runs, 6, float(t[t.size // 2]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--first-seed", type=int, default=2021)
    parser.add_argument("--hours", type=float, default=0.0, help="duration_hours (0: the whole 253 h window)")
    parser.add_argument("--workers", type=int, default=1, help="processes each image-mode run renders in")
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "benchmarks" / "s4_from_pixels")
    args = parser.parse_args()
    seeds = [args.first_seed + i for i in range(args.seeds)]
    base = [f"duration_hours={args.hours:g}"]
    print(f"S4 from pixels, seeds {seeds}, duration_hours={args.hours:g}:", flush=True)
    images = [opnav_run(args.out / f"images_seed_{s}", s, base, images=True, workers=args.workers) for s in seeds]
    step = images[0]["image_mode"]["image_step_s"]
    mars, sun = pooled(images, "mars"), pooled(images, "sun")
    sets = base + [f"angle_step_s={step:g}", f"sun_sigma_arcsec={sun:.4f}", f"mars_sigma_arcsec={mars:.4f}"]
    measured = [opnav_run(args.out / f"measurements_seed_{s}", s, sets, images=False, workers=1) for s in seeds]

    print(f"\nachieved line-of-sight noise per axis over {len(seeds)} runs (against the true geometric lines of sight):")
    for body, value in (("Mars (camera + star tracker)", mars), ("Sun (sun sensor + star tracker)", sun)):
        key = "mars" if body.startswith("Mars") else "sun"
        chi2 = np.mean([s["image_mode"]["achieved_noise"][key]["chi2_per_dof"] for s in images])
        print(f"  {body:32s} {value:.3f}\"  (mean chi-square/dof of the reported covariances {chi2:.2f})")
    print(f"measurement mode at that noise: --set angle_step_s={step:g} sun_sigma_arcsec={sun:.4f} "
          f"mars_sigma_arcsec={mars:.4f}")
    print("\nfinal position error km (worst axis / sigma): images | measurements")
    for seed, a, b in zip(seeds, images, measured):
        cells = [f"{c[:5]} {a['filters'][c]['final_position_error_km']:8.1f} ({a['filters'][c]['max_axis_error_in_sigma']:5.2f})"
                 f" | {b['filters'][c]['final_position_error_km']:8.1f} ({b['filters'][c]['max_axis_error_in_sigma']:5.2f})"
                 for c in CASES]
        print(f"  seed {seed}: " + "   ".join(cells))

    converges = [s["filters"]["registered"]["max_axis_error_in_sigma"] <= 3.0 for s in images]
    diverges = [s["filters"]["unregistered"]["max_axis_error_in_sigma"] > 3.0 for s in images]
    reg_img = float(np.mean([s["filters"]["registered"]["final_position_error_km"] for s in images]))
    reg_meas = float(np.mean([s["filters"]["registered"]["final_position_error_km"] for s in measured]))
    wrong = sum(s["image_mode"]["wrong_body"]["count"] for s in images)
    checked = sum(s["image_mode"]["wrong_body"]["checked"] for s in images)
    print("\nacceptance (issue 37 item 4):")
    print(f"  registered converges on {sum(converges)}/{len(seeds)} seeds, unregistered diverges on "
          f"{sum(diverges)}/{len(seeds)} (final worst axis within / beyond 3 sigma): "
          f"{'holds' if all(converges) and all(diverges) else 'DOES NOT HOLD'}")
    ratio = reg_img / reg_meas
    print(f"  registered final position error, mean of {len(seeds)}: {reg_img:.1f} km from pixels, {reg_meas:.1f} km in "
          f"measurement mode at the achieved noise: ratio {ratio:.2f} (<= 1.5: {'holds' if ratio <= 1.5 else 'DOES NOT HOLD'})")
    for label, runs in (("from pixels", images), ("measurements", measured)):
        folders = [args.out / f"{'images' if runs is images else 'measurements'}_seed_{s}" for s in seeds]
        for case in CASES:
            test = nees_test(folders, case)
            inside = test.band[0] <= test.mean <= test.band[1]
            print(f"  NEES {label:12s} {case:12s} mean {test.mean:7.2f} over {test.epochs} epochs, 95 % band of the "
                  f"{test.runs}-run mean [{test.band[0]:.2f}, {test.band[1]:.2f}]: {'in band' if inside else 'OUT OF BAND'}"
                  f" ({test.share_inside:.0%} of epochs inside)")
    print(f"  wrong-body Mars records over every from-pixels run: {wrong} of {checked} checked "
          f"({'holds' if wrong == 0 else 'DOES NOT HOLD'})")


if __name__ == "__main__":
    main()
