"""S1 Monte Carlo: EKF on Phobos/Deimos RA/Dec during the Mars cruise (S1 Table 2 set-up).

Set-up (the study: docs/studies.md#s1-mars-cruise; its numbers restated here):
- truth: S1 Table 1 state (TT 2013-12-12 12:00, heliocentric ICRF) propagated with
  ``opnav.dynamics.cruise_model()`` (Sun + Mercury..Saturn, Earth, Moon) to the arc;
- arc: 30 days from the 1st of ``--month`` 2014, one RA/Dec per target per minute;
- measurements simulated at measurement level: truth apparent RA/Dec through
  ``opnav.light`` (light time + aberration, as the renderer) + Gaussian noise of
  ``--noise-arcsec`` on RA and on Dec; the truth moons sit at the filter's
  ephemeris plus a constant offset drawn per run and moon, 1 km (1-sigma) per axis;
- filter: EKF with the same cruise model, STM from the variational equations, no
  process noise by default (truth and filter dynamics are identical), moon ephemeris
  error 1 km added to R; initial error drawn from P0 with 5000 km / 5 m/s RMS
  (per axis 5000/sqrt(3) km and 5/sqrt(3) m/s);
- figures: position/velocity RMS over the last 15 days (mean and spread over runs),
  the filter's own 1-sigma, the posterior Cramér-Rao bound along the truth, mean NEES
  and NIS with their 95% chi-square bounds, wall time.

The runs advance in lockstep (one integration and one measurement-model call per step
for all runs of a chunk, ``--chunk-size``); chunks run in a process pool (``--workers``).
Each run's result is written atomically to ``--out/run_XXX.npz`` when its chunk ends and
skipped when present, so an interrupted campaign resumes from the last finished chunk. ``summary.json`` is written atomically at the end.

Usage::

    .venv/bin/python benchmarks/s1_filters.py --runs 50 --month jul --targets both --noise-arcsec 0.1
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from opnav.consistency import chi2_mean_bounds, nees
from opnav.constants import ARCSEC_RAD
from opnav.dynamics import cruise_model, propagate
from opnav.epochs import parse_epoch
from opnav.filters.ekf import EKFOptions, force_model_batch_propagator
from opnav.filters.noise import WhiteAcceleration
from opnav.filters.lockstep import run_ekf_lockstep
from opnav.ephemeris.cache import default_cached_ephemeris
from opnav.measurements import ProbeMeasurementModel, TargetOffsetModel, simulate_radec
from opnav.records import Measurement, atomic_write_text
from opnav.studies.s1 import MONTHS, S1_EPOCH_TT, S1_STATE0, TARGETS
from opnav.studies.s1 import PAPER as S1_PAPER

INITIAL_SIGMA_KM = 5000.0 / np.sqrt(3.0)
INITIAL_SIGMA_KM_S = 0.005 / np.sqrt(3.0)
MOON_EPHEMERIS_SIGMA_KM = 1.0
KEEP_EVERY = 10


def truth_arc(month: str, days: float, step_s: float) -> tuple[float, np.ndarray, np.ndarray]:
    """Arc start (TDB s), measurement epochs (N,), true states at start and epochs (N+1, 6)."""
    t_epoch = parse_epoch(S1_EPOCH_TT, scale="tt")
    t_start = parse_epoch(MONTHS[month] + "T00:00:00", scale="tdb")
    epochs = t_start + step_s * np.arange(1, int(round(days * 86_400.0 / step_s)) + 1)
    traj = propagate(cruise_model(), t_epoch, S1_STATE0, np.concatenate([[t_start], epochs]))
    return t_start, epochs, traj.states


def run_chunk(run_ids: list[int], config: dict) -> list[int]:
    """Run the EKFs of ``run_ids`` in lockstep and write one result file per run."""
    out = Path(config["out"])
    t_start, epochs, truth = truth_arc(config["month"], config["days"], config["step_s"])
    targets = TARGETS[config["targets"]]
    sigma = config["noise_arcsec"] * ARCSEC_RAD
    truth_model = ProbeMeasurementModel("sun")
    # the filter reads the ephemeris through the Chebyshev cache (compiled light time) unless --exact
    ephemeris = None if config["exact"] else default_cached_ephemeris()
    handling = config["ephemeris_model"]
    P0 = np.diag([INITIAL_SIGMA_KM**2] * 3 + [INITIAL_SIGMA_KM_S**2] * 3)
    options = EKFOptions()
    if handling == "white":
        model = ProbeMeasurementModel("sun", target_position_sigma_km=MOON_EPHEMERIS_SIGMA_KM, ephemeris=ephemeris)
    else:
        # each moon's offset is a state (estimated) or a consider parameter, 1 km a priori per axis
        model = TargetOffsetModel(ProbeMeasurementModel("sun", ephemeris=ephemeris), targets)
        P0 = np.diag(np.concatenate([np.diag(P0), np.full(3 * len(targets), MOON_EPHEMERIS_SIGMA_KM**2)]))
        if handling == "consider":
            options = EKFOptions(consider=tuple(range(6, model.size)))
    x0 = np.zeros((len(run_ids), P0.shape[0]))
    values = np.empty((len(targets), epochs.size, len(run_ids), 2))
    for k, run in enumerate(run_ids):
        rng = np.random.default_rng([config["seed"], run])
        x0[k, :6] = truth[0] + rng.multivariate_normal(np.zeros(6), P0[:6, :6])
        for j, target in enumerate(targets):
            shape = (3,) if config["ephemeris_error"] == "bias" else (epochs.size, 3)
            offset = rng.normal(0.0, MOON_EPHEMERIS_SIGMA_KM, shape)
            values[j, :, k] = simulate_radec(truth_model, target, epochs, truth[1:], sigma_rad=sigma, rng=rng,
                                             target_offset_km=offset)
    templates = [Measurement(epochs[0], "radec", [0.0, 0.0], np.eye(2) * sigma**2, target=t, sensor="nac")
                 for t in targets]
    q = config["q_km2_s3"]
    tic = time.perf_counter()
    # the bound rides along the true trajectory with zero offsets (their value barely moves H)
    truth_n = np.hstack([truth, np.zeros((truth.shape[0], P0.shape[0] - 6))])
    hist = run_ekf_lockstep(t_start, x0, P0, epochs, templates, values,
                            propagator=force_model_batch_propagator(cruise_model(), exact=config["exact"]), model=model,
                            process_noise=WhiteAcceleration(q) if q > 0 else None,
                            options=options, truth=truth_n, keep_every=KEEP_EVERY, progress=config["progress"])
    wall = time.perf_counter() - tic
    kept_truth = truth[1:][KEEP_EVERY - 1::KEEP_EVERY]
    if kept_truth.shape[0] != hist.epochs.size:
        kept_truth = np.vstack([kept_truth, truth[-1]])
    for k, run in enumerate(run_ids):
        err = hist.states[:, k, :6] - kept_truth
        arrays = dict(
            epochs=hist.epochs, pos_err_km=err[:, :3], vel_err_km_s=err[:, 3:6],
            sigma_pos_km=np.sqrt(np.trace(hist.covariances[:, k, :3, :3], axis1=1, axis2=2)),
            sigma_vel_km_s=np.sqrt(np.trace(hist.covariances[:, k, 3:6, 3:6], axis1=1, axis2=2)),
            nees=nees(hist.states[:, k, :6], hist.covariances[:, k, :6, :6], kept_truth),
            nis=hist.nis[:, :, k], accepted=hist.accepted[:, :, k],
            pcrb_pos_km=np.sqrt(np.trace(hist.pcrb[:, :3, :3], axis1=1, axis2=2)),
            pcrb_vel_km_s=np.sqrt(np.trace(hist.pcrb[:, 3:6, 3:6], axis1=1, axis2=2)),
            wall_s=np.array(wall / len(run_ids)),
        )
        fd, tmp = tempfile.mkstemp(dir=out, prefix=f".run_{run:03d}.", suffix=".npz")
        os.close(fd)
        np.savez(tmp, **arrays)
        os.replace(tmp, out / f"run_{run:03d}.npz")
    return run_ids


def rms(a: np.ndarray, axis=None) -> np.ndarray:
    return np.sqrt(np.mean(a * a, axis=axis))


def summarise(out: Path, runs: int, config: dict, wall_s: float) -> dict:
    results = [np.load(out / f"run_{run:03d}.npz") for run in range(runs)]
    epochs = results[0]["epochs"]
    last = epochs >= epochs[-1] - 15 * 86_400.0 + 1.0
    pos_err = np.stack([np.linalg.norm(r["pos_err_km"][last], axis=1) for r in results])
    pos_rms = rms(pos_err, axis=1)
    vel_rms = np.array([rms(np.linalg.norm(r["vel_err_km_s"][last], axis=1)) for r in results]) * 1e3
    sigma_pos = np.array([rms(r["sigma_pos_km"][last]) for r in results])
    sigma_vel = np.array([rms(r["sigma_vel_km_s"][last]) for r in results]) * 1e3
    pcrb_pos = float(rms(results[0]["pcrb_pos_km"][last]))
    pcrb_vel = float(rms(results[0]["pcrb_vel_km_s"][last])) * 1e3
    nees_runs = np.stack([r["nees"] for r in results])  # (R, M)
    nees_mean_t = nees_runs.mean(axis=0)
    lo, hi = chi2_mean_bounds(6, runs, 0.95)
    nis_all = np.stack([r["nis"] for r in results])  # (R, N, T)
    accepted = np.stack([r["accepted"] for r in results])
    nis_ok = nis_all[accepted]
    nis_lo, nis_hi = chi2_mean_bounds(2, nis_ok.size, 0.95)
    nis_mean_t = np.nanmean(np.where(accepted, nis_all, np.nan), axis=(0, 2))
    nis_t_lo, nis_t_hi = chi2_mean_bounds(2, runs * nis_all.shape[2], 0.95)
    paper = S1_PAPER.get((config["noise_arcsec"], config["month"]), {}).get(config["targets"])
    summary = {
        "scenario": "S1", "month": config["month"], "targets": config["targets"], "noise_arcsec": config["noise_arcsec"],
        "days": config["days"], "step_s": config["step_s"], "runs": runs, "seed": config["seed"],
        "q_km2_s3": config["q_km2_s3"], "ephemeris_error": config["ephemeris_error"],
        "ephemeris_model": config["ephemeris_model"],
        "position_rms_last15d_km": {"mean": float(pos_rms.mean()), "std": float(pos_rms.std(ddof=1)) if runs > 1 else 0.0,
                                    "pooled": float(rms(pos_err))},
        "velocity_rms_last15d_m_s": {"mean": float(vel_rms.mean()), "std": float(vel_rms.std(ddof=1)) if runs > 1 else 0.0},
        "filter_1sigma_last15d": {"position_km": float(sigma_pos.mean()), "velocity_m_s": float(sigma_vel.mean())},
        "pcrb_1sigma_last15d": {"position_km": pcrb_pos, "velocity_m_s": pcrb_vel},
        "paper_table": {"position_km": paper[0], "velocity_m_s": paper[1]} if paper else None,
        "nees": {
            "mean_over_arc": float(nees_mean_t.mean()), "mean_last15d": float(nees_mean_t[last].mean()),
            "bounds95_per_epoch": [lo, hi],
            "fraction_epochs_inside": float(np.mean((nees_mean_t > lo) & (nees_mean_t < hi))),
            "fraction_epochs_inside_last15d": float(np.mean((nees_mean_t[last] > lo) & (nees_mean_t[last] < hi))),
        },
        "nis": {
            "mean": float(nis_ok.mean()), "bounds95_all": [nis_lo, nis_hi],
            "fraction_epochs_inside": float(np.mean((nis_mean_t > nis_t_lo) & (nis_mean_t < nis_t_hi))),
            "bounds95_per_epoch": [nis_t_lo, nis_t_hi],
            "rejected": int((~accepted).sum()), "updates": int(accepted.size),
        },
        "wall_s": wall_s, "lockstep_wall_s_per_run": float(np.mean([float(r["wall_s"]) for r in results])),
    }
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2))
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=50)
    parser.add_argument("--month", choices=sorted(MONTHS), default="jul")
    parser.add_argument("--targets", choices=sorted(TARGETS), default="both")
    parser.add_argument("--noise-arcsec", type=float, default=0.1)
    parser.add_argument("--days", type=float, default=30.0, help="arc length (S1: 30)")
    parser.add_argument("--step-s", type=float, default=60.0, help="measurement interval (S1: 60)")
    parser.add_argument("--q-km2-s3", type=float, default=0.0, help="filter white-acceleration density")
    parser.add_argument("--ephemeris-error", choices=("white", "bias"), default="white",
                        help="truth moon offsets: new draw per measurement (what the filter assumes) "
                             "or one constant offset per run and moon")
    parser.add_argument("--ephemeris-model", choices=("white", "estimate", "consider"), default="white",
                        help="how the filter treats the moon-ephemeris error: white noise added to R, "
                             "one offset per moon estimated as states, or held as consider parameters")
    parser.add_argument("--seed", type=int, default=2014)
    parser.add_argument("--workers", type=int, default=1, help="dask.distributed local worker processes (the machine is shared)")
    parser.add_argument("--chunk-size", type=int, default=25,
                        help="runs advanced in lockstep per task; results are saved per finished chunk")
    parser.add_argument("--out", default=None,
                        help="result folder (default out/benchmarks/s1_<month>_<targets>_<noise>_<days>_<error>)")
    parser.add_argument("--exact", action="store_true", help="filters on DOP853 and the exact ephemeris")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    name = (f"s1_{args.month}_{args.targets}_{args.noise_arcsec:g}as_{args.days:g}d_{args.ephemeris_error}"
            + ("" if args.ephemeris_model == "white" else f"_{args.ephemeris_model}"))
    out = Path(args.out or Path(__file__).resolve().parent.parent / "out" / "benchmarks" / name)
    out.mkdir(parents=True, exist_ok=True)
    config = {"out": str(out), "month": args.month, "targets": args.targets, "noise_arcsec": args.noise_arcsec,
              "days": args.days, "step_s": args.step_s, "q_km2_s3": args.q_km2_s3, "seed": args.seed,
              "ephemeris_error": args.ephemeris_error, "ephemeris_model": args.ephemeris_model,
              "progress": not args.no_progress, "exact": args.exact}
    config_file = out / "config.json"
    same = {"progress": True, "out": ""}  # keys that may differ between a run and its resumption
    if config_file.exists() and json.loads(config_file.read_text()) | same != config | same:
        parser.error(f"{out} holds results of another configuration; use --out")
    atomic_write_text(config_file, json.dumps(config, indent=2))
    todo = [run for run in range(args.runs) if not (out / f"run_{run:03d}.npz").exists()]
    tic = time.perf_counter()
    if todo:
        chunks = [todo[i:i + args.chunk_size] for i in range(0, len(todo), args.chunk_size)]
        if args.workers == 1:
            for chunk in chunks:
                run_chunk(chunk, config)
        else:
            # dask.distributed: one local process per worker, one single-threaded task per chunk;
            # each task writes its own results, so an interrupted campaign resumes from them.
            from dask.distributed import Client, LocalCluster

            with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                              dashboard_address=None) as cluster, Client(cluster) as client:
                client.gather(client.map(run_chunk, chunks, [config] * len(chunks), pure=False))
    summary = summarise(out, args.runs, config, time.perf_counter() - tic)
    print(json.dumps(summary, indent=2))
    p, v = summary["position_rms_last15d_km"], summary["velocity_rms_last15d_m_s"]
    print(f"\nS1 {args.month} {args.targets} {args.noise_arcsec}\" ({args.runs} runs, {args.days:g} d): "
          f"position RMS {p['mean']:.3f} +- {p['std']:.3f} km, velocity RMS {v['mean']:.4f} +- {v['std']:.4f} m/s; "
          f"filter 1-sigma {summary['filter_1sigma_last15d']['position_km']:.3f} km; "
          f"PCRB {summary['pcrb_1sigma_last15d']['position_km']:.3f} km; paper {summary['paper_table']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
