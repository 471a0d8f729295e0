"""``opnav navigate``: run a navigation filter over a measurement file.

Reads measurement records (:func:`opnav.records.read_csv`, or a CCSDS TDM through
:func:`opnav.ccsds.read_tdm`) and the
``[navigation]`` section of a scenario file (:mod:`opnav.filters.options`), builds the
dynamics (:mod:`opnav.dynamics`), the measurement model
(:class:`opnav.measurements.ProbeMeasurementModel`) and the chosen filter, runs
it and writes, atomically, into ``--out``:

- ``estimates.csv``: epoch, state (km, km/s, ICRF, dynamics centre) and 1-sigmas (after each
  record; the smoothed trajectory for ``wls``; the fused estimates for ``federated``);
- ``covariances.csv``: epoch and the upper triangle of P (km^2, km^2/s, km^2/s^2 blocks);
- ``residuals.csv``: per record: kind, target, accepted, NIS, reason, residual (record units);
- ``estimates.oem``: the same estimates with their covariance as a CCSDS OEM (:mod:`opnav.ccsds`,
  the last estimate of each epoch), and ``measurements.tdm``: the RA/Dec records as a CCSDS TDM;
- ``summary.json``: counts, NIS statistics, final estimate, wall time and ``consistency``
  (:mod:`opnav.filters.monitor`: flags such as ``nis_out_of_band`` or ``particles_degenerate``
  and whether the final estimate is ``usable``).

Exit status: 0 when the final estimate is usable (flags are printed as warnings),
3 when it is not (most records refused, NIS out of its band at the end, or a
degenerate particle cloud at the end); the outputs are written either way.

The filters are built by :mod:`opnav.filters.factory` (which imports each one
only when it is asked for); this module parses arguments, reads and writes files
and prints.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import json
import sys
import time
from pathlib import Path

import numpy as np

from ..ccsds import read_tdm, tdm_ready, write_estimates_oem, write_tdm
from ..constants import ARCSEC_RAD
from ..epochs import format_epoch
from ..errors import InputError
from ..filters.base import Estimate
from ..filters.factory import build_filter, measurement_model, run_federated_filter
from ..filters.monitor import check_history
from ..filters.run import FilterHistory, chi2_mean_bounds, run_filter
from ..filters.options import FILTERS, load_navigation
from ..records import atomic_write_text, read_csv

NAME = "navigate"
HELP = "run a navigation filter (EKF/UKF/PF/WLS/...) over a measurement CSV"
#: Exit status when the run finished but its final estimate is not to be used.
EXIT_UNUSABLE = 3

STATE_COLUMNS = ("x_km", "y_km", "z_km", "vx_km_s", "vy_km_s", "vz_km_s")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("measurements", help="measurement CSV (opnav.records format) or CCSDS TDM "
                                             "(.tdm or .xml; RADEC angles)")
    parser.add_argument("--tdm-sigma-arcsec", type=float, default=None,
                        help="1-sigma of each TDM angle, arcsec, for TDMs that do not carry opnav's covariance "
                             "comments (those written by opnav do)")
    parser.add_argument("--scenario", required=True, help="scenario TOML with a [navigation] section")
    parser.add_argument("--filter", choices=FILTERS, default=None, help="filter (default: [navigation] filter)")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--exact", action="store_true",
                        help="propagate with DOP853 and the exact ephemeris instead of the compiled fast path "
                             "(same answers to < 1%% of the filter sigma, ~20x slower); also [navigation] propagation")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


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
    write_estimates_oem(out / "estimates.oem", epochs, states, covariances, center=summary["center"],
                        object_name=summary["filter"], comment=f"opnav navigate, filter {summary['filter']}")
    radec = tdm_ready(records)
    if radec:
        write_tdm(out / "measurements.tdm", radec)
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2))


def read_measurements(path: str, tdm_sigma_arcsec: float | None = None) -> list:
    """Records of a measurement CSV, or of a CCSDS TDM (by suffix ``.tdm``/``.xml`` or its first keyword)."""
    source = Path(path)
    if tdm_sigma_arcsec is not None and not (np.isfinite(tdm_sigma_arcsec) and tdm_sigma_arcsec > 0.0):
        raise InputError(f"--tdm-sigma-arcsec must be a positive number, got {tdm_sigma_arcsec!r}")
    head = b""
    if source.is_file():
        with source.open("rb") as handle:
            head = handle.read(64).lstrip()
    if source.suffix.lower() in (".tdm", ".xml") or head.startswith(b"CCSDS_TDM_VERS"):
        sigma = None if tdm_sigma_arcsec is None else tdm_sigma_arcsec * ARCSEC_RAD
        return read_tdm(source, sigma_rad=sigma)
    return read_csv(source)


def run(args: argparse.Namespace) -> int:
    from ..dynamics import get_model
    nav = load_navigation(args.scenario)
    if args.exact:
        nav = dataclasses.replace(nav, exact=True)
    name = args.filter or nav.filter
    if name in ("wls", "federated") and nav.ephemeris_error != "white":
        raise InputError(f"{args.scenario}: filter {name!r} takes ephemeris_error = 'white' only, "
                         f"not {nav.ephemeris_error!r}")
    records = read_measurements(args.measurements, args.tdm_sigma_arcsec)
    if not records:
        raise InputError(f"{args.measurements}: no measurement records")
    force_model = get_model(nav.dynamics)
    model = measurement_model(nav, force_model.center)
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
    consistency = None if name == "wls" else check_history(history)
    if consistency is not None:
        summary["consistency"] = consistency.to_dict()
    write_outputs(out, track, history, records, summary)
    print(f"{name}: {summary['accepted']}/{summary['records']} records accepted; outputs in {out}")
    if consistency is None:
        return 0
    for message in consistency.messages:
        print(f"warning: {name}: {message}", file=sys.stderr)
    if not consistency.usable:
        print(f"error: {name}: the final estimate is not usable ({', '.join(consistency.flags)}); "
              f"see {out / 'summary.json'}", file=sys.stderr)
        return EXIT_UNUSABLE
    return 0
