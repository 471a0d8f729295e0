"""Monte Carlo campaigns of a run file: N seeds through the runner, on dask.distributed, aggregated.

Run ``i`` is the run file with seed ``seed + i`` (recorded, so ``opnav run RUNFILE --seed S``
replays it alone) written by :func:`opnav.scenarios.runner.run_study` into ``DIR/run_NNN``.
Each run's stages are saved atomically under their content hashes, so an interrupted campaign
resumes: finished runs are read back, unfinished ones continue from their last stage.

Runs go to a dask.distributed ``LocalCluster`` of ``workers`` single-threaded processes, or
to an existing scheduler (``dask scheduler`` and ``dask worker ADDRESS`` on other machines
sharing the output folder); with ``workers = 1`` and no scheduler they run in this process.

``DIR/campaign.json`` holds ``{"runs": [...], "aggregate": {...}}``: per run its seed and each
filter's figures; per filter the mean, standard deviation, minimum and maximum of the position
and velocity RMS, the mean NEES, the mean final 1-sigma, and the count of runs with consistency
flags. ``DIR/campaign.md`` shows the aggregate beside the study's published figures.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..records import atomic_write_text
from .runner import RunOptions, run_study
from .settings import load_run_file


def _one_run(path: str, overrides: dict, seed: int, out: str, filters, mode: str) -> dict:
    """Worker task: one seed of the run file, quietly; returns its summary."""
    run = load_run_file(path, {**overrides, "seed": str(seed)})
    return run_study(run, RunOptions(out=Path(out), filters=filters, mode=mode, progress=False))


def _aggregate(summaries: list[dict]) -> dict:
    out: dict = {}
    names = sorted({name for s in summaries for name in s.get("filters", {})})
    for name in names:
        runs = [s["filters"][name] for s in summaries if name in s.get("filters", {})]
        if not runs or "position_rms_km" not in runs[0]:
            continue
        entry = {"runs": len(runs)}
        for key in ("position_rms_km", "velocity_rms_m_s", "nees_mean"):
            values = np.array([r[key] for r in runs], dtype=float)
            entry[key] = {"mean": float(values.mean()), "std": float(values.std(ddof=1)) if values.size > 1 else 0.0,
                          "min": float(values.min()), "max": float(values.max())}
        entry["final_position_sigma_km_mean"] = float(np.mean([r["final"]["position_sigma_km"] for r in runs]))
        entry["runs_with_flags"] = int(sum(bool(r["consistency"]["flags"]) for r in runs))
        entry["runs_unusable"] = int(sum(not r["consistency"]["usable"] for r in runs))
        out[name] = entry
    return out


def run_campaign(path: str, *, runs: int, out: Path, overrides: dict | None = None, filters=None,
                 mode: str = "measurements", workers: int = 1, scheduler: str | None = None,
                 progress: bool = True) -> dict:
    """Run ``runs`` seeds of run file ``path`` into ``out`` (module notes); returns the campaign record."""
    if int(runs) != runs or runs < 1:
        raise InputError(f"--runs must be a positive integer, got {runs}")
    if int(workers) != workers or workers < 1:
        raise InputError(f"--workers must be a positive integer, got {workers}")
    overrides = dict(overrides or {})
    base = load_run_file(path, overrides)  # validates everything before any work
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    seeds = [base.seed + i for i in range(runs)]
    folders = [str(out / f"run_{i:03d}") for i in range(runs)]
    args = [(str(path), overrides, seed, folder, filters, mode) for seed, folder in zip(seeds, folders)]
    tic = time.perf_counter()
    if scheduler is None and workers == 1:
        summaries = []
        for i, task in enumerate(args):
            if progress:
                print(f"[campaign] run {i + 1}/{runs} (seed {task[2]})", file=sys.stderr, flush=True)
            summaries.append(_one_run(*task))
    else:
        from dask.distributed import Client, LocalCluster, as_completed

        # the scheduler's INFO chatter (every worker and connection) would bury the progress lines
        if not logging.getLogger("opnav").isEnabledFor(logging.INFO):
            logging.getLogger("distributed").setLevel(logging.WARNING)

        cluster = None if scheduler else LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                                      dashboard_address=None, silence_logs=logging.WARNING)
        with Client(scheduler or cluster) as client:
            futures = [client.submit(_one_run, *task, pure=False) for task in args]
            for done, _ in enumerate(as_completed(futures), start=1):
                if progress:
                    print(f"[campaign] {done}/{runs} runs done", file=sys.stderr, flush=True)
            summaries = client.gather(futures)
        if cluster is not None:
            cluster.close()
    record = {
        "run_file": str(path), "overrides": overrides, "study": base.study, "mode": mode,
        "runs": [{"seed": seed, "folder": folder, "filters": s.get("filters", {})}
                 for seed, folder, s in zip(seeds, folders, summaries)],
        "aggregate": _aggregate(summaries), "paper": summaries[0].get("paper", {}),
        "wall_s": time.perf_counter() - tic,
    }
    atomic_write_text(out / "campaign.json", json.dumps(record, indent=2, default=float))
    lines = [f"# Campaign: {Path(path).name}, {runs} runs (seeds {seeds[0]}..{seeds[-1]})", "",
             f"Overrides: {overrides or 'none'}. Paper: `{record['paper']}`", "",
             "| filter | position RMS (km) mean ± std [min, max] | velocity RMS (m/s) mean ± std | NEES mean | "
             "final 1-sigma (km) | runs with flags |", "|---|---|---|---|---|---|"]
    for name, a in record["aggregate"].items():
        p, v = a["position_rms_km"], a["velocity_rms_m_s"]
        lines.append(f"| {name} | {p['mean']:.3f} ± {p['std']:.3f} [{p['min']:.3f}, {p['max']:.3f}] | "
                     f"{v['mean']:.4f} ± {v['std']:.4f} | {a['nees_mean']['mean']:.2f} | "
                     f"{a['final_position_sigma_km_mean']:.3f} | {a['runs_with_flags']}/{a['runs']} |")
    atomic_write_text(out / "campaign.md", "\n".join(lines) + "\n")
    return record



def parse_sweeps(pairs: list[str] | None) -> dict[str, list[str]]:
    """``["KEY=V1,V2", ...]`` -> ``{KEY: [V1, V2]}``; errors name the bad pair."""
    out: dict[str, list[str]] = {}
    for pair in pairs or []:
        key, sep, values = pair.partition("=")
        items = [v.strip() for v in values.split(",") if v.strip()]
        if not sep or not key.strip() or not items:
            raise InputError(f"--sweep expects KEY=V1,V2,..., got {pair!r}")
        out[key.strip()] = items
    return out


def run_sweep(path: str, *, sweeps: dict[str, list[str]], runs: int, out: Path, overrides: dict | None = None,
              **options) -> dict:
    """A campaign per point of the Cartesian product of ``sweeps`` (``DIR/KEY=V,KEY=V``), then one table.

    ``DIR/sweep.json`` lists each point's overrides and aggregate; ``DIR/sweep.md`` is one row per
    point and filter, with the study's published figure for that point beside ours.
    """
    import itertools

    keys = list(sweeps)
    points = [dict(zip(keys, values)) for values in itertools.product(*(sweeps[k] for k in keys))]
    out = Path(out)
    for point in points:  # validate every point before any work
        load_run_file(path, {**(overrides or {}), **point})
    rows = []
    for point in points:
        folder = out / ",".join(f"{k}={v}" for k, v in point.items())
        record = run_campaign(path, runs=runs, out=folder, overrides={**(overrides or {}), **point}, **options)
        rows.append({"point": point, "aggregate": record["aggregate"], "paper": record["paper"]})
    atomic_write_text(out / "sweep.json", json.dumps({"run_file": str(path), "runs": runs, "points": rows},
                                                     indent=2, default=float))
    lines = [f"# Sweep of {Path(path).name}: {runs} runs per point", "",
             "| " + " | ".join(keys) + " | filter | position RMS (km) mean ± std | velocity RMS (m/s) | NEES | "
             "final 1-sigma (km) | paper |", "|" + "---|" * (len(keys) + 6)]
    for row in rows:
        paper = row["paper"]
        shown = (f"{paper['position_rms_km']} km, {paper['velocity_rms_m_s']} m/s" if "position_rms_km" in paper
                 else "see summary")
        for name, a in row["aggregate"].items():
            p, v = a["position_rms_km"], a["velocity_rms_m_s"]
            lines.append("| " + " | ".join(row["point"][k] for k in keys) + f" | {name} | {p['mean']:.3f} ± "
                         f"{p['std']:.3f} | {v['mean']:.4f} ± {v['std']:.4f} | {a['nees_mean']['mean']:.2f} | "
                         f"{a['final_position_sigma_km_mean']:.3f} | {shown} |")
    atomic_write_text(out / "sweep.md", "\n".join(lines) + "\n")
    return {"points": rows}
