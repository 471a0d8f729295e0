"""Particle filters against the EKF/UKF: consistency and cost per particle count, S3 and S1.

S3 (GEO, starlight angle + elevation of one star every 10 s, the set-up of
``benchmarks/filters.py``): 24 h, ``--seeds`` seeds; for each filter the mean NEES over
the last 12 h (time-averaged per seed, then over seeds, beside the 95 % band of the mean of
``seeds`` chi-square(6) values, a band for independent seeds), the position RMS over the
last 12 h, the accepted records, the smallest N_eff and the wall time per run.

S1 (Mars cruise, July, Phobos and Deimos RA/Dec alternating at 1/min, 0.1"): ``--s1-hours``
of the arc from the 5000 km prior, where the particle filters' difficulty is (the prior is
3 orders of magnitude wider than one record); same figures over the whole window.

Usage::

    .venv/bin/python benchmarks/particles.py                      # S3 5 seeds x 24 h, S1 3 seeds x 12 h
    .venv/bin/python benchmarks/particles.py --steps 2000 --seeds 2 --filters ekf,mcmc-upf:150
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from filters import S1_EPOCH_TT, S1_STATE0, SIGMA_S1, TARGETS, geo_state
from scipy import stats

from opnav.consistency import nees
from opnav.constants import ARCSEC_RAD
from opnav.dynamics import cruise_model, geo_model, propagate
from opnav.ephemeris.cache import default_cached_ephemeris
from opnav.epochs import parse_epoch
from opnav.filters.base import Estimate
from opnav.filters.ekf import ExtendedKalmanFilter, force_model_propagator
from opnav.filters.noise import WhiteAcceleration
from opnav.filters.particle import ParticleFilter, ParticleOptions, UnscentedParticleFilter
from opnav.filters.run import run_filter
from opnav.filters.ukf import UnscentedKalmanFilter, force_model_transition
from opnav.frames import radec_to_unit
from opnav.measurements import ProbeMeasurementModel, simulate_radec
from opnav.records import Measurement


def s3_case(seed: int, steps: int):
    """Truth, records and the filters' start for one S3 seed (Earth-centred ICRF, km, km/s)."""
    rng = np.random.default_rng(seed)
    t0 = parse_epoch("2001-01-01T00:00:00", scale="utc")
    dynamics = geo_model(epoch_tdb_s=t0)
    epochs = t0 + 10.0 * np.arange(1, steps + 1)
    truth = propagate(dynamics, t0, geo_state(t0), epochs).states
    exact = ProbeMeasurementModel("earth", light_time=False, aberration=False)
    sigma = np.hypot(5.0, 20.0) / 3.0 * ARCSEC_RAD
    star = radec_to_unit(np.deg2rad(30.0), np.deg2rad(10.0))
    records = []
    for t, x in zip(epochs, truth):
        for kind in ("starlight_angle", "starlight_elevation"):
            template = Measurement(t, kind, [0.0], [[sigma**2]], target="earth", star_unit_icrf=star)
            value = exact.predict(template, x) + sigma * rng.standard_normal(1)
            records.append(Measurement(t, kind, value, [[sigma**2]], target="earth", star_unit_icrf=star))
    P0 = np.diag([10.0**2] * 3 + [0.001**2] * 3)
    x0 = geo_state(t0) + np.sqrt(np.diag(P0)) * rng.standard_normal(6)
    model = ProbeMeasurementModel("earth", light_time=False, aberration=False, ephemeris=default_cached_ephemeris())
    return dict(dynamics=dynamics, model=model, records=records, truth=truth, epochs=epochs,
                start=Estimate(t0, x0, P0), noise=WhiteAcceleration(1e-12), rng=rng)


def s1_case(seed: int, hours: float):
    """Truth, records and start for the first ``hours`` of the S1 July arc (heliocentric ICRF)."""
    rng = np.random.default_rng(seed)
    dynamics = cruise_model()
    t0 = parse_epoch("2014-07-01T00:00:00", scale="utc")
    updates = int(hours * 60)
    epochs = t0 + 60.0 * np.arange(1, updates + 1)
    truth = propagate(dynamics, parse_epoch(S1_EPOCH_TT, scale="tt"), S1_STATE0, np.concatenate([[t0], epochs])).states
    exact = ProbeMeasurementModel("sun")
    records = []
    for j, target in enumerate(TARGETS):
        picked = np.arange(j, updates, 2)
        values = simulate_radec(exact, target, epochs[picked], truth[1 + picked], sigma_rad=SIGMA_S1, rng=rng)
        records += [Measurement(t, "radec", v, SIGMA_S1**2 * np.eye(2), target=target)
                    for t, v in zip(epochs[picked], values)]
    P0 = np.diag([(5000.0 / np.sqrt(3.0)) ** 2] * 3 + [(0.005 / np.sqrt(3.0)) ** 2] * 3)
    x0 = truth[0] + np.sqrt(np.diag(P0)) * rng.standard_normal(6)
    model = ProbeMeasurementModel("sun", ephemeris=default_cached_ephemeris())
    return dict(dynamics=dynamics, model=model, records=records, truth=truth[1:], epochs=epochs,
                start=Estimate(t0, x0, P0), noise=WhiteAcceleration(1e-22), rng=rng)


def build(spec: str, case: dict):
    """``ekf``, ``ukf``, ``pf:N``, ``upf:N`` or ``mcmc-upf:N`` on ``case``'s models."""
    name, _, count = spec.partition(":")
    common = dict(process_noise=case["noise"], model=case["model"])
    if name == "ekf":
        return ExtendedKalmanFilter(case["start"], propagator=force_model_propagator(case["dynamics"]), **common)
    transition = force_model_transition(case["dynamics"])
    if name == "ukf":
        return UnscentedKalmanFilter(case["start"], transition=transition, **common)
    options = ParticleOptions(n_particles=int(count) if count else None, mcmc_move=name == "mcmc-upf")
    kind = ParticleFilter if name == "pf" else UnscentedParticleFilter
    return kind(case["start"], transition=transition, rng=case["rng"], options=options, **common)


def evaluate(spec: str, case: dict, window: slice) -> dict:
    filt = build(spec, case)
    begin = time.perf_counter()
    history = run_filter(filt, case["records"], progress=False)
    wall = time.perf_counter() - begin
    # the last record of each epoch carries the epoch's posterior
    last = np.r_[history.epochs[1:] != history.epochs[:-1], True]
    index = np.searchsorted(case["epochs"], history.epochs[last])
    truth = case["truth"][index]
    values = nees(history.states[last], history.covariances[last], truth)[window]
    err = np.linalg.norm(history.states[last][window, :3] - truth[window, :3], axis=1)
    return {"nees": float(values.mean()), "rms_km": float(np.sqrt(np.mean(err**2))),
            "accepted": float(history.accepted.mean()), "wall_s": wall,
            "min_ess": float(np.nanmin(history.ess)) if history.ess is not None else np.nan}


def campaign(title: str, make_case, seeds: int, specs: list[str], window: slice) -> None:
    print(title)
    band = stats.chi2.ppf([0.025, 0.975], 6 * seeds) / seeds
    results = {spec: [] for spec in specs}
    for seed in range(seeds):
        case = make_case(seed)
        for spec in specs:
            results[spec].append(evaluate(spec, case, window))
    ekf_rms = np.mean([r["rms_km"] for r in results["ekf"]]) if "ekf" in results else np.nan
    for spec, runs in results.items():
        mean = {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}
        spread = np.std([r["rms_km"] for r in runs])
        verdict = "in band" if band[0] <= mean["nees"] <= band[1] else "OUT of band"
        print(f"  {spec:13s} NEES {mean['nees']:9.2f} ({verdict} [{band[0]:.2f}, {band[1]:.2f}])"
              f"  RMS {mean['rms_km']:8.3f} +- {spread:6.3f} km ({mean['rms_km'] / ekf_rms:5.2f} x EKF)"
              f"  accepted {mean['accepted']:6.1%}  min N_eff {mean['min_ess']:7.1f}  {mean['wall_s']:7.1f} s/run")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=5, help="S3 seeds (the acceptance asks 5)")
    parser.add_argument("--steps", type=int, default=8640, help="S3 steps of 10 s (8640 = 24 h)")
    parser.add_argument("--filters", default="ekf,ukf,pf:150,pf:2000,upf:150,mcmc-upf:50,mcmc-upf:150",
                        help="comma-separated: ekf, ukf, pf:N, upf:N, mcmc-upf:N")
    parser.add_argument("--s1-seeds", type=int, default=3, help="S1 seeds (0: skip S1)")
    parser.add_argument("--s1-hours", type=float, default=12.0, help="S1 window from the 5000 km prior")
    parser.add_argument("--s1-filters", default="ekf,pf:2000,pf:10000,upf:150,mcmc-upf:150")
    args = parser.parse_args()
    specs = args.filters.split(",")
    if "ekf" not in specs:
        specs.insert(0, "ekf")
    half = slice(args.steps // 2, None)
    campaign(f"S3 GEO, {args.steps} steps of 10 s, {args.seeds} seeds; NEES and RMS over the second half:",
             lambda seed: s3_case(seed, args.steps), args.seeds, specs, half)
    if args.s1_seeds > 0:
        s1_specs = args.s1_filters.split(",")
        if "ekf" not in s1_specs:
            s1_specs.insert(0, "ekf")
        campaign(f"S1 July both 0.1\", first {args.s1_hours:g} h from the 5000 km prior, {args.s1_seeds} seeds; "
                 "NEES and RMS over the window:", lambda seed: s1_case(seed, args.s1_hours), args.s1_seeds, s1_specs,
                 slice(None))


if __name__ == "__main__":
    main()
