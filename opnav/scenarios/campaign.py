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
flags. ``DIR/campaign.md`` (and ``campaign.html``) shows the aggregate beside the study's published figures.
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
from .report import flat_items, markdown_page
from .runner import RunOptions, run_study
from .settings import load_run_file


def _one_run(path: str, overrides: dict, seed: int, out: str, filters, mode: str) -> dict:
    """Worker task: one seed of the run file, quietly; returns its summary."""
    run = load_run_file(path, {**overrides, "seed": str(seed)})
    return run_study(run, RunOptions(out=Path(out), filters=filters, mode=mode, progress=False))


def _numeric_leaves(figures: dict):
    """(dotted key, value) of every finite number in a run's figures for one filter."""
    for key, value in flat_items(figures):
        if isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value):
            yield key, float(value)


def _stats(values) -> dict:
    values = np.asarray(values, dtype=float)
    return {"mean": float(values.mean()), "std": float(values.std(ddof=1)) if values.size > 1 else 0.0,
            "min": float(values.min()), "max": float(values.max())}


def _aggregate(summaries: list[dict]) -> dict:
    """Per filter: mean, std, min and max of every figure all its runs report (dotted keys for
    nested ones, e.g. ``final.position_sigma_km`` or S2's ``MPS (model 2).position_error_mean_km``),
    and the runs with consistency flags or unusable answers."""
    out: dict = {}
    names = sorted({name for s in summaries for name in s.get("filters", {})})
    for name in names:
        runs = [s["filters"][name] for s in summaries if name in s.get("filters", {})]
        leaves = [dict(_numeric_leaves(r)) for r in runs]
        common = [key for key in leaves[0] if all(key in leaf for leaf in leaves)]
        entry: dict = {"runs": len(runs)}
        entry.update({key: _stats([leaf[key] for leaf in leaves]) for key in common})
        if "final.position_sigma_km" in entry:
            entry["final_position_sigma_km_mean"] = entry["final.position_sigma_km"]["mean"]
        checks = [r.get("consistency") for r in runs if r.get("consistency")]
        entry["runs_with_flags"] = int(sum(bool(c["flags"]) for c in checks))
        entry["runs_unusable"] = int(sum(not c["usable"] for c in checks))
        out[name] = entry
    return out


def campaign_table(aggregate: dict) -> list[str]:
    """Markdown rows of a campaign's aggregate: the RMS table of S1 and S3, or one row per figure."""
    if aggregate and all("position_rms_km" in a for a in aggregate.values()):
        lines = ["| filter | position RMS (km) mean ± std [min, max] | velocity RMS (m/s) mean ± std | NEES mean | "
                 "final 1-sigma (km) | runs with flags |", "|---|---|---|---|---|---|"]
        for name, a in aggregate.items():
            p, v = a["position_rms_km"], a["velocity_rms_m_s"]
            lines.append(f"| {name} | {p['mean']:.3f} ± {p['std']:.3f} [{p['min']:.3f}, {p['max']:.3f}] | "
                         f"{v['mean']:.4f} ± {v['std']:.4f} | {a['nees_mean']['mean']:.2f} | "
                         f"{a.get('final_position_sigma_km_mean', float('nan')):.3f} | "
                         f"{a['runs_with_flags']}/{a['runs']} |")
        return lines
    lines = ["| filter | figure | mean ± std | [min, max] |", "|---|---|---|---|"]
    for name, a in aggregate.items():
        for key, value in a.items():
            if isinstance(value, dict) and key != "wall_s":
                lines.append(f"| {name} | {key} | {value['mean']:.6g} ± {value['std']:.3g} | "
                             f"[{value['min']:.6g}, {value['max']:.6g}] |")
    return lines


def run_campaign(path: str, *, runs: int, out: Path, overrides: dict | None = None, filters=None,
                 mode: str | None = None, workers: int = 1, scheduler: str | None = None,
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
        "run_file": str(path), "overrides": overrides, "study": base.study, "mode": mode or base.mode,
        "runs": [{"seed": seed, "folder": folder, "filters": s.get("filters", {})}
                 for seed, folder, s in zip(seeds, folders, summaries)],
        "aggregate": _aggregate(summaries), "paper": summaries[0].get("paper", {}),
        "wall_s": time.perf_counter() - tic,
    }
    atomic_write_text(out / "campaign.json", json.dumps(record, indent=2, default=float))
    lines = [f"# Campaign: {Path(path).name}, {runs} runs (seeds {seeds[0]}..{seeds[-1]})", "",
             f"Overrides: {overrides or 'none'}. Paper: `{record['paper']}`", "", *campaign_table(record["aggregate"])]
    atomic_write_text(out / "campaign.md", "\n".join(lines) + "\n")
    atomic_write_text(out / "campaign.html", markdown_page(f"Campaign {Path(path).name}", lines))
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
            if "position_rms_km" not in a:  # S2/S4 figures: the point's own table below
                continue
            p, v = a["position_rms_km"], a["velocity_rms_m_s"]
            lines.append("| " + " | ".join(row["point"][k] for k in keys) + f" | {name} | {p['mean']:.3f} ± "
                         f"{p['std']:.3f} | {v['mean']:.4f} ± {v['std']:.4f} | {a['nees_mean']['mean']:.2f} | "
                         f"{a['final_position_sigma_km_mean']:.3f} | {shown} |")
    for row in rows:
        if not all("position_rms_km" in a for a in row["aggregate"].values()):
            lines += ["", "## " + ", ".join(f"{k} = {v}" for k, v in row["point"].items()), "",
                      *campaign_table(row["aggregate"])]
    atomic_write_text(out / "sweep.md", "\n".join(lines) + "\n")
    atomic_write_text(out / "sweep.html", markdown_page(f"Sweep {Path(path).name}", lines))
    return {"points": rows}
