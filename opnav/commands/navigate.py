"""``opnav navigate``: run a navigation filter over a measurement file.

Reads measurement records (:func:`opnav.records.read_csv`) and the
``[navigation]`` section of a scenario file (:mod:`opnav.navconfig`), builds the
dynamics (:mod:`opnav.dynamics`), the measurement model
(:class:`opnav.measurements.ProbeMeasurementModel`) and the chosen filter, runs
it and writes, atomically, into ``--out``:

- ``estimates.csv``: epoch, state (km, km/s, ICRF, dynamics centre) and 1-sigmas (after each
  record; the smoothed trajectory for ``wls``; the fused estimates for ``federated``);
- ``covariances.csv``: epoch and the upper triangle of P (km^2, km^2/s, km^2/s^2 blocks);
- ``residuals.csv``: per record: kind, target, accepted, NIS, reason, residual (record units);
- ``summary.json``: counts, NIS statistics, final estimate, wall time.

The unscented, particle and federated filters live in modules of their own and are
imported only when asked for, so a missing one gives a clear error instead of
breaking the command.
"""

from __future__ import annotations

import argparse
import csv
import importlib
import io
import json
import time
from pathlib import Path

import numpy as np

from ..epochs import format_epoch
from ..errors import InputError
from ..filters.base import Estimate
from ..filters.noise import process_noise_from_config
from ..filters.run import FilterHistory, chi2_mean_bounds, run_filter
from ..navconfig import FILTERS, NavigationConfig, load_navigation
from ..records import atomic_write_text, read_csv

NAME = "navigate"
HELP = "run a navigation filter (EKF/UKF/PF/WLS/...) over a measurement CSV"

#: filter name -> (module, class) imported on demand.
LAZY_FILTERS = {
    "ukf": ("opnav.filters.ukf", "UnscentedKalmanFilter"),
    "sr-ukf": ("opnav.filters.ukf", "SquareRootUKF"),
    "pf": ("opnav.filters.particle", "ParticleFilter"),
    "upf": ("opnav.filters.particle", "UnscentedParticleFilter"),
    "mcmc-upf": ("opnav.filters.particle", "UnscentedParticleFilter"),
    "federated": ("opnav.filters.federated", "FederatedFilter"),
}
STATE_COLUMNS = ("x_km", "y_km", "z_km", "vx_km_s", "vy_km_s", "vz_km_s")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("measurements", help="measurement CSV (opnav.records format)")
    parser.add_argument("--scenario", required=True, help="scenario TOML with a [navigation] section")
    parser.add_argument("--filter", choices=FILTERS, default=None, help="filter (default: [navigation] filter)")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _lazy(name: str):
    module_name, attr = LAZY_FILTERS[name]
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise InputError(f"filter {name!r} is not available: cannot import {module_name} ({exc})") from None
    if not hasattr(module, attr):
        raise InputError(f"filter {name!r} is not available: {module_name} has no {attr}")
    return getattr(module, attr)


def build_filter(name: str, nav: NavigationConfig, model, force_model):
    """The sequential filter ``name`` configured from ``nav`` (not ``wls`` or ``federated``)."""
    from ..filters.ekf import EKFOptions, ExtendedKalmanFilter, force_model_propagator

    estimate = Estimate(nav.t0_tdb_s, nav.x0, nav.P0)
    noise = process_noise_from_config(nav.process_noise)
    if name == "ekf":
        return ExtendedKalmanFilter(estimate, propagator=force_model_propagator(force_model), model=model,
                                    process_noise=noise, options=EKFOptions(gate_probability=nav.gate_probability))
    factory = _lazy(name)
    from ..filters.ukf import UKFOptions, force_model_transition

    transition = force_model_transition(force_model)
    if name in ("ukf", "sr-ukf"):
        options = UKFOptions(**nav.ukf, gate_probability=nav.gate_probability)
        return factory(estimate, transition=transition, process_noise=noise, model=model, options=options)
    from ..filters.particle import ParticleOptions

    particle = dict(nav.particle)
    if name in ("upf", "mcmc-upf"):
        particle["mcmc_move"] = name == "mcmc-upf"
    options = ParticleOptions(**particle, gate_probability=nav.gate_probability)
    return factory(estimate, transition=transition, process_noise=noise, model=model,
                   rng=np.random.default_rng(nav.seed), options=options)


def run_federated_filter(nav: NavigationConfig, records, model, force_model):
    """Federated filter with one local filter per ``record.sensor`` and equal sharing factors.

    Returns the fused (epochs, states, covariances) and a per-record :class:`FilterHistory`.
    """
    federated = _lazy("federated")
    from ..filters.federated import FederatedOptions, run_federated

    options = dict(nav.federated)
    unknown = sorted(set(options) - {"local_filter", "mode", "fusion_interval_s"})
    if unknown:
        raise InputError(f"unknown key(s) {unknown} in [navigation.federated]")
    local = str(options.get("local_filter", "ekf"))
    if local not in ("ekf", "ukf", "sr-ukf"):
        raise InputError(f"[navigation.federated] local_filter must be ekf, ukf or sr-ukf, got {local!r}")
    sensors = sorted({r.sensor for r in records})
    fed = federated({s: build_filter(local, nav, model, force_model) for s in sensors},
                    initial=Estimate(nav.t0_tdb_s, nav.x0, nav.P0),
                    options=FederatedOptions(betas={s: 1.0 / len(sensors) for s in sensors}, routes={s: s for s in sensors},
                                             mode=str(options.get("mode", "fusion-reset"))))
    epochs = np.unique([r.t_tdb_s for r in records])
    if "fusion_interval_s" in options:
        step = float(options["fusion_interval_s"])
        if not step > 0.0:
            raise InputError(f"[navigation.federated] fusion_interval_s must be positive, got {step}")
        epochs = np.arange(epochs[0], epochs[-1] + step, step)
    fused, outcomes = run_federated(fed, records, epochs)
    ordered = sorted(records, key=lambda r: r.t_tdb_s)
    m_max = max(r.size for r in ordered)
    residuals = np.full((len(ordered), m_max), np.nan)
    for i, (r, o) in enumerate(zip(ordered, outcomes)):
        residuals[i, : r.size] = o.residual
    history = FilterHistory(
        epochs=np.array([r.t_tdb_s for r in ordered]), states=np.stack([o.estimate.x for o in outcomes]),
        covariances=np.stack([o.estimate.P for o in outcomes]), residuals=residuals,
        nis=np.array([o.nis for o in outcomes]), dof=np.array([r.size for r in ordered]),
        accepted=np.array([o.accepted for o in outcomes]), reasons=tuple(o.reason for o in outcomes),
        kinds=tuple(r.kind for r in ordered), targets=tuple(r.target for r in ordered),
    )
    fused_track = (np.array([e.t_tdb_s for e in fused]), np.stack([e.x for e in fused]), np.stack([e.P for e in fused]))
    return fused_track, history


def _history_from_batch(result) -> FilterHistory:
    n = len(result.epochs)
    return FilterHistory(
        epochs=result.epochs, states=result.states, covariances=result.covariances, residuals=result.residuals,
        nis=np.full(n, np.nan), dof=np.sum(np.isfinite(result.residuals), axis=1), accepted=result.used,
        reasons=tuple("" if used else "left out (bad record)" for used in result.used),
        kinds=("",) * n, targets=("",) * n,
    )


def _csv(rows: list[list], header: list[str]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue()


def write_outputs(out: Path, track: tuple[np.ndarray, np.ndarray, np.ndarray], history: FilterHistory, records,
                  summary: dict) -> None:
    """Write estimates and covariances of ``track`` (epochs, states, covariances), the per-record
    residuals of ``history`` (CSV) and summary.json, atomically, into ``out``."""
    epochs, states, covariances = track
    epochs_utc = format_epoch(epochs, "utc")
    sig = np.sqrt(np.diagonal(covariances, axis1=1, axis2=2))
    est_rows = [[repr(float(t)), utc, *map(repr, map(float, x[:6])), *map(repr, map(float, s[:6]))]
                for t, utc, x, s in zip(epochs, epochs_utc, states, sig)]
    atomic_write_text(out / "estimates.csv", _csv(
        est_rows, ["t_tdb_s", "epoch_utc", *STATE_COLUMNS, *(f"sigma_{c}" for c in STATE_COLUMNS)]))
    iu = np.triu_indices(states.shape[1])
    cov_rows = [[repr(float(t)), *map(repr, map(float, P[iu]))] for t, P in zip(epochs, covariances)]
    atomic_write_text(out / "covariances.csv", _csv(cov_rows, ["t_tdb_s", *(f"p{i}{j}" for i, j in zip(*iu))]))
    ordered = sorted(records, key=lambda r: r.t_tdb_s)
    res_rows = [[repr(r.t_tdb_s), r.kind, r.target, r.sensor, int(ok), repr(float(nis)), reason,
                 " ".join(repr(float(v)) for v in res[: r.size])]
                for r, ok, nis, reason, res in zip(ordered, history.accepted, history.nis, history.reasons, history.residuals)]
    atomic_write_text(out / "residuals.csv", _csv(
        res_rows, ["t_tdb_s", "kind", "target", "sensor", "accepted", "nis", "reason", "residual"]))
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2))


def run(args: argparse.Namespace) -> int:
    from ..dynamics import get_model
    from ..measurements import ProbeMeasurementModel

    nav = load_navigation(args.scenario)
    name = args.filter or nav.filter
    records = read_csv(args.measurements)
    if not records:
        raise InputError(f"{args.measurements}: no measurement records")
    force_model = get_model(nav.dynamics)
    model = ProbeMeasurementModel(force_model.center, light_time=nav.light_time, aberration=nav.aberration,
                                  target_position_sigma_km=nav.target_position_sigma_km)
    out = Path(args.out)
    tic = time.perf_counter()
    if name == "wls":
        from ..filters.batch import BatchOptions, batch_least_squares, force_model_trajectory

        result = batch_least_squares(records, Estimate(nav.t0_tdb_s, nav.x0, nav.P0),
                                     propagator=force_model_trajectory(force_model), model=model,
                                     options=BatchOptions(**nav.batch))
        history = _history_from_batch(result)
        track = (history.epochs, history.states, history.covariances)
        extra = {"iterations": result.iterations, "cost": result.cost}
    elif name == "federated":
        track, history = run_federated_filter(nav, records, model, force_model)
        extra = {"fusions": int(track[0].size)}
    else:
        history = run_filter(build_filter(name, nav, model, force_model), records, progress=not args.no_progress)
        track = (history.epochs, history.states, history.covariances)
        extra = {}
    wall = time.perf_counter() - tic
    accepted = history.accepted
    nis = history.nis[accepted & np.isfinite(history.nis)]
    summary = {
        "filter": name, "dynamics": nav.dynamics, "center": force_model.center,
        "measurements": str(args.measurements), "scenario": str(args.scenario),
        "records": len(records), "accepted": int(accepted.sum()), "rejected": int((~accepted).sum()),
        "rejection_reasons": sorted({r for r in history.reasons if r}),
        "final": {"t_tdb_s": float(track[0][-1]), "epoch_utc": format_epoch(float(track[0][-1]), "utc"),
                  "state": track[1][-1, :6].tolist(), "state_units": "km, km/s (ICRF)",
                  "sigma": np.sqrt(np.diag(track[2][-1])[:6]).tolist()},
        "wall_s": wall, **extra,
    }
    if nis.size:
        dof = int(round(np.mean(history.dof[accepted & np.isfinite(history.nis)])))
        summary["nis"] = {"mean": float(nis.mean()), "mean_dof": dof,
                          "bounds95_for_mean": list(chi2_mean_bounds(dof, nis.size, 0.95))}
    write_outputs(out, track, history, records, summary)
    print(f"{name}: {summary['accepted']}/{summary['records']} records accepted; outputs in {out}")
    return 0
