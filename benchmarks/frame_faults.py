"""Faults in S1 image mode, one at a time: what the image stage and the filter make of each.

Each case runs ``opnav run samples/s1_jul_both_0.1.toml --mode images`` on a short arc
(``--days``, from 16 July 2014, frames in memory) with one fault of
:class:`opnav.studies.faults.Faults` on, as a user would, in a subprocess with a time bound,
and prints one markdown row:

- outcome: ``ran`` (exit 0 or 3: the run finished and wrote its summary), ``clear error`` (exit
  2 with one ``opnav run: error:`` line), ``traceback`` or ``hang`` (the time bound);
- frames not measured by the image stage (lost, refused, no star-identified attitude), losses
  of lock;
- moon records made, and the wrong ones among them: error against the frame's truth beyond the
  1 - 1e-6 quantile of chi-square(2) under the record's own covariance (the injected 100-sigma
  outliers are wrong records by design);
- wrong records the EKF accepted (not refused by its gate);
- the EKF's final position error over its own 1-sigma, and the run's consistency flags.

A case is a **silent wrong answer** when the run finished without a consistency flag while
its EKF accepted a wrong record or ended more than 3 sigma from the truth.

Usage::

    .venv/bin/python benchmarks/frame_faults.py --days 0.5 --jobs 2
"""

from __future__ import annotations

import argparse
import glob
import json
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from scipy.stats import chi2

ROOT = Path(__file__).resolve().parent.parent
RUN_FILE = ROOT / "samples" / "s1_jul_both_0.1.toml"
CASES = [
    ("clean", {}),
    ("frames lost 5%", {"dropped_frame_fraction": "0.05"}),
    ("cosmic-ray storm x10", {"cosmic_ray_factor": "10"}),
    ("cosmic-ray storm x100", {"cosmic_ray_factor": "100"}),
    ("hot-pixel clusters 200", {"hot_pixel_clusters": "200"}),
    ("hot-pixel clusters 2000", {"hot_pixel_clusters": "2000"}),
    ("stray-light ramp 3000 e", {"stray_light_e": "3000"}),
    ("stray-light ramp 30000 e", {"stray_light_e": "30000"}),
    ("uncatalogued point sources 5/frame", {"uncatalogued_stars": "5"}),
    ("uncatalogued point sources 30/frame", {"uncatalogued_stars": "30"}),
    ("catalog stars missing 20%", {"missing_star_fraction": "0.2"}),
    ("catalog stars missing 60%", {"missing_star_fraction": "0.6"}),
    ("a-priori attitude off 120\"", {"prior_attitude_error_arcsec": "120"}),
    ("a-priori attitude off 1200\"", {"prior_attitude_error_arcsec": "1200"}),
    ("camera x axis flipped", {"flipped_axis": "true"}),
    ("record outliers 0.5% at 100 sigma", {"outlier_fraction": "0.005"}),
    ("clock offset 30 s", {"clock_offset_s": "30"}),
]
WRONG_CHI2 = chi2.ppf(1.0 - 1e-6, 2)


def run_case(name: str, faults: dict, out: Path, days: float, timeout_s: float) -> dict:
    folder = out / name.replace(" ", "_").replace("%", "pct").replace('"', "as").replace("/", "_per_")
    shutil.rmtree(folder, ignore_errors=True)
    command = [str(Path(sys.executable).parent / "opnav"), "run", str(RUN_FILE), "--mode", "images", "--set", "day=16",
               "--set", f"duration_days={days}", "--set", "dump_every=0", "--filters", "ekf", "--workers", "1",
               "--no-progress", "--out", str(folder)]
    for key, value in faults.items():
        command += ["--set", f"faults.{key}={value}"]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"case": name, "outcome": "hang"}
    if "Traceback" in done.stderr:
        return {"case": name, "outcome": "traceback", "detail": done.stderr.strip().splitlines()[-1]}
    if done.returncode not in (0, 3):
        return {"case": name, "outcome": "clear error", "detail": done.stderr.strip().splitlines()[-1][:160]}
    return {"case": name, "outcome": "ran", **_figures(folder)}


def _figures(folder: Path) -> dict:
    from opnav.records import read_csv

    summary = json.loads((folder / "summary.json").read_text())
    facts = summary["facts"]
    truth = {}
    for path in sorted(glob.glob(str(folder / "stream" / "chunk_*.done.json"))):
        truth.update(json.loads(Path(path).read_text())["truth"])
    ekf = summary["filters"]["ekf"]
    refused = {(round(r["t_tdb_s"], 3), r["target"]) for r in json.loads((folder / "filters" / "ekf.json").read_text())
               .get("refused", [])}
    wrong = accepted_wrong = 0
    records = read_csv(folder / "measurements.csv")
    for record in records:
        if record.frame_id not in truth or record.target not in truth[record.frame_id]:
            continue
        error = np.asarray(record.value) - np.asarray(truth[record.frame_id][record.target])
        if float(error @ np.linalg.solve(record.covariance, error)) > WRONG_CHI2:
            wrong += 1
            accepted_wrong += (round(record.t_tdb_s, 3), record.target) not in refused
    tracking = facts.get("tracking", {})
    final = ekf["final"]
    flags = ekf["consistency"]["flags"]
    ratio = final["position_error_km"] / final["position_sigma_km"]
    return {"frames": facts["frames"], "not_measured": len(facts.get("frames_skipped", {})),
            "losses": tracking.get("losses_of_lock", 0), "records": len(records),
            "wrong": wrong, "accepted_wrong": accepted_wrong, "final_sigmas": ratio, "flags": flags,
            "silent_wrong": not flags and (accepted_wrong > 0 or ratio > 3.0)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--days", type=float, default=0.5, help="arc length per case, days (frames a minute apart)")
    parser.add_argument("--jobs", type=int, default=2, help="cases run side by side")
    parser.add_argument("--timeout-s", type=float, default=1800.0, help="a case running longer counts as a hang")
    parser.add_argument("--out", default="out/frame_faults")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with ThreadPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(lambda case: run_case(*case, out, args.days, args.timeout_s), CASES))
    print(f"S1 July both moons from pixels, {args.days:g} day(s) from 16 July, one fault per case, EKF\n")
    print("| case | outcome | frames not measured | losses of lock | records | wrong records | wrong accepted "
          "by the EKF | final error / 1-sigma | flags | silent wrong answer |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        if row["outcome"] != "ran":
            print(f"| {row['case']} | {row['outcome']}: {row.get('detail', '')} | | | | | | | | no |")
            continue
        print(f"| {row['case']} | ran | {row['not_measured']} of {row['frames']} | {row['losses']} | {row['records']} | "
              f"{row['wrong']} | {row['accepted_wrong']} | {row['final_sigmas']:.2f} | {', '.join(row['flags']) or '-'} | "
              f"{'YES' if row['silent_wrong'] else 'no'} |")
    bad = [row["case"] for row in rows if row["outcome"] in ("traceback", "hang") or row.get("silent_wrong")]
    print(f"\n{len(rows)} cases; tracebacks, hangs and silent wrong answers: {len(bad)} {bad if bad else ''}")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
