"""One S1 row against its posterior Cramér-Rao bound: the EKF, and the EKF restarted from its own answer.

The S1 table (``make reproduce-s1``, ``benchmarks/results.py``) holds each row's RMS over seeds
against the bound with a bootstrap interval. A row above the bound may be the EKF losing
information (it linearises the first records about an initial estimate 5000 km off) or one of the
rows a 95 % interval misses by chance. This script tells them apart on the same seeds: per seed it
runs the EKF as a campaign run does (``position_rms_km`` over the window, the campaign's figure to
the last bit), then runs it again over the same records from the first pass's final estimate
propagated back to the arc's start (a batch initialisation; P0 unchanged, so the second pass's prior
is centred on the data's own answer: a double count that weighs ``(PCRB / prior sigma)^2`` of the
weakest direction's information, about 1 % in May with Phobos, 0.02 % in July with both moons). When the first
pass lost information to linearisation, the second, linearised about an estimate a bound's width
from the truth, gets it back and its RMS falls; when the row was off by chance, both passes give
the same errors (paired: the ratio of the two passes' mean squares has no seed-to-seed spread of
the bound's own).

    python benchmarks/s1_bound_check.py --month may --targets phobos --noise-arcsec 0.1 --runs 50 --first-seed 2014 --ukf

``--first-seed``: a sweep's point ``k`` (in the order of ``make reproduce-s1``'s product: month,
targets, noise) runs seeds ``2014 + 50 k`` onwards; seeds from ``2014 + 24 * 50 = 3214`` on belong to
no point of the sweep (a fresh replication of a row). Prints one line per seed and, for both passes,
the RMS over seeds, the bound and the ratio with its 95 % interval, and writes them to
``OUT/month=M,targets=T,noise_arcsec=N,seeds=FIRST-LAST.json`` (``--out``, default ``out/reproduce/s1_bound_check``),
where ``benchmarks/results.py`` finds them for the README's S1 table.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from opnav.dynamics import propagate
from opnav.errors import InputError
from opnav.files import atomic_write_text
from opnav.filters.navigate import navigate
from opnav.studies import STUDIES
from opnav.studies.bound_ratio import rms_over_bound
from opnav.studies.campaign_runs import posterior_bound
from opnav.studies.common import filter_metrics
from opnav.studies.settings import load_run_file

RUN_FILE = "samples/s1_jul_both_0.1.toml"


def passes(sim, *, ukf: bool = False) -> dict[str, dict]:
    """Window position RMS (km, ``position_rms_km``) and mean NEES over the window and the arc
    (``nees_mean``, ``nees_mean_arc``) over ``sim`` of the EKF (``ekf``), of the EKF restarted from
    its final estimate propagated back to the arc's start (``restarted``, module notes) and, with
    ``ukf``, of the UKF from the run's own start (``ukf``)."""
    nav = sim.navigation

    def figures(name: str, start) -> tuple[dict, object]:
        result = navigate(sim.records, start, filter_name=name, force_model=sim.force_model, center=sim.center)
        metrics = filter_metrics(result.history, sim)
        return {key: metrics[key] for key in ("position_rms_km", "nees_mean", "nees_mean_arc")}, result.history

    out = {}
    out["ekf"], history = figures("ekf", nav)
    back = propagate(sim.force_model, float(history.epochs[-1]), np.asarray(history.states[-1][:6]),
                     np.array([nav.t0_tdb_s])).states[0]
    out["restarted"], _ = figures("ekf", replace(nav, x0=back))
    if ukf:
        out["ukf"], _ = figures("ukf", nav)
    return out


NAMES = {"ekf": "EKF", "restarted": "EKF restarted from its back-propagated answer", "ukf": "UKF"}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--month", default="may")
    parser.add_argument("--targets", default="phobos")
    parser.add_argument("--noise-arcsec", default="0.1")
    parser.add_argument("--runs", type=int, default=50)
    parser.add_argument("--first-seed", type=int, default=2014)
    parser.add_argument("--ukf", action="store_true", help="run the UKF on the same records too")
    parser.add_argument("--out", default="out/reproduce/s1_bound_check", help="folder of the JSON record")
    args = parser.parse_args()
    if args.runs < 3:
        print("--runs: at least 3 seeds (the ratio's interval needs them)", file=sys.stderr)
        return 2
    overrides = {"month": args.month, "targets": args.targets, "noise_arcsec": args.noise_arcsec}
    try:
        runs = [load_run_file(RUN_FILE, {**overrides, "seed": str(args.first_seed + i)}) for i in range(args.runs)]
    except InputError as error:
        print(f"{RUN_FILE}: {error}", file=sys.stderr)
        return 2
    study = STUDIES["s1"]
    tic = time.perf_counter()
    bound = posterior_bound(study.simulate(runs[0].settings, runs[0].seed))["pcrb_position_km"]
    print(f"{overrides}: PCRB {bound:.2f} km ({time.perf_counter() - tic:.0f} s)", flush=True)
    figures: dict[str, list[float]] = {}
    nees: dict[str, list[list[float]]] = {}
    for run in runs:
        tic = time.perf_counter()
        seed_figures = passes(study.simulate(run.settings, run.seed), ukf=args.ukf)
        for name, value in seed_figures.items():
            figures.setdefault(name, []).append(value["position_rms_km"])
            nees.setdefault(name, []).append([value["nees_mean"], value["nees_mean_arc"]])
        print(f"seed {run.seed}: " + ", ".join(f"{name} {value['position_rms_km']:.2f} km, NEES {value['nees_mean']:.2f}"
                                              for name, value in seed_figures.items())
              + f" ({time.perf_counter() - tic:.0f} s)", flush=True)
    record = {"point": overrides, "seeds": [run.seed for run in runs], "pcrb_position_km": bound, "rms_km": figures,
              "nees_window_arc": nees}
    for name, values in figures.items():
        ratio = rms_over_bound(values, bound)
        record[name] = {**asdict(ratio), "verdict": ratio.verdict}
        print(f"{NAMES[name]}: RMS over {ratio.seeds} seeds {ratio.rms_km:.2f} km, PCRB {bound:.2f} km, "
              f"ratio {ratio.ratio:.3f} [{ratio.low:.3f}, {ratio.high:.3f}] ({ratio.verdict})")
    squares = {name: np.sum(np.square(values)) for name, values in figures.items()}
    record["restarted_over_ekf_mean_square"] = float(squares["restarted"] / squares["ekf"])
    print(f"restarted / EKF, mean square over the seeds: {record['restarted_over_ekf_mean_square']:.4f}")
    if "ukf" in squares:
        record["ukf_over_ekf_mean_square"] = float(squares["ukf"] / squares["ekf"])
        print(f"UKF / EKF, mean square over the seeds: {record['ukf_over_ekf_mean_square']:.4f}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = ",".join(f"{k}={v}" for k, v in overrides.items())
    path = out / f"{name},seeds={runs[0].seed}-{runs[-1].seed}.json"
    atomic_write_text(path, json.dumps(record, indent=2))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
