"""Filter speed on full-length arcs: S1 30 days at 1 min (EKF, UKF, SR-UKF, lockstep) and S3 24 h at 10 s.

S1 part (docs/studies.md#s1-mars-cruise): truth from the S1 Table 1 state propagated with
``cruise_model()`` (DOP853) to 2014-07-01 TDB; Phobos and Deimos RA/Dec alternating,
one record a minute (43,200 updates in 30 days), 0.1" noise, light time and
aberration on as in the renderer; 5000 km / 5 m/s initial error. Every filter runs
the whole arc (nothing is extrapolated) on the default fast path (compiled
propagator, cached ephemeris, compiled light time); the final position error and
the filter's 1-sigma are printed so that a fast but wrong filter would show. The
lockstep EKF and UKF run ``--runs`` Monte Carlo runs together on the same arc.
The propagation cost of one 60-s step with the STM is printed beside DOP853's
(scipy, rtol 1e-11, one call per step as the exact filter path does) timed in the
same run.

S3 part (docs/studies.md#s3-geo-satellite): GEO orbit (RAAN 260 deg, true anomaly 0.702295 deg,
period 86164.09 s) from 2001-01-01 00:00 UTC with ``geo_model()``; every 10 s one
starlight angle and one starlight elevation (star sensor 5" and UV Earth sensor
20", 3-sigma, combined); the EKF over the whole 24 h (8,640 steps) and the
MCMC-UPF with 150 particles over ``--upf-steps`` steps (the whole day by default).

Usage::

    .venv/bin/python benchmarks/filters.py            # everything, full length
    .venv/bin/python benchmarks/filters.py --runs 20 --upf-steps 8640
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from opnav.constants import ARCSEC_RAD
from opnav.dynamics import cruise_model, geo_model, propagate
from opnav.dynamics.fast import FastPropagator
from opnav.ephemeris.cache import default_cached_ephemeris
from opnav.epochs import parse_epoch
from opnav.filters.base import Estimate
from opnav.filters.ekf import ExtendedKalmanFilter, force_model_batch_propagator, force_model_propagator
from opnav.filters.lockstep import run_ekf_lockstep, run_ukf_lockstep
from opnav.filters.noise import WhiteAcceleration
from opnav.filters.particle import ParticleOptions, UnscentedParticleFilter
from opnav.filters.sr_ukf import SquareRootUKF
from opnav.filters.ukf import UnscentedKalmanFilter, force_model_transition
from opnav.frames import radec_to_unit
from opnav.measurements import ProbeMeasurementModel, simulate_radec
from opnav.records import Measurement
from opnav.studies.s1 import S1_EPOCH_TT, S1_STATE0
from opnav.studies.s3 import geo_state as s3_geo_state

SIGMA_S1 = 0.1 * ARCSEC_RAD
TARGETS = ("phobos", "deimos")


def s1_arc(updates: int, runs: int, rng: np.random.Generator):
    """Arc start, truth (N+1, 6), epochs (N,), per-run values (2, N/2, K, 2) of alternating Phobos/Deimos."""
    exact = ProbeMeasurementModel("sun")
    t_epoch = parse_epoch(S1_EPOCH_TT, scale="tt")
    t_start = parse_epoch("2014-07-01T00:00:00", scale="tdb")
    epochs = t_start + 60.0 * np.arange(1, updates + 1)
    truth = propagate(cruise_model(), t_epoch, S1_STATE0, np.concatenate([[t_start], epochs])).states
    values = np.empty((updates, runs, 2))
    for j, target in enumerate(TARGETS):
        rows = slice(j, None, 2)
        for k in range(runs):
            values[rows, k] = simulate_radec(exact, target, epochs[rows], truth[1:][rows], sigma_rad=SIGMA_S1, rng=rng)
    return t_start, truth, epochs, values


def s1_records(epochs: np.ndarray, values: np.ndarray) -> list[Measurement]:
    return [Measurement(t, "radec", v, SIGMA_S1**2 * np.eye(2), target=TARGETS[i % 2], sensor="camera")
            for i, (t, v) in enumerate(zip(epochs, values))]


def report(name: str, wall: float, updates: int, x: np.ndarray, P: np.ndarray, truth: np.ndarray) -> None:
    err = np.linalg.norm(x[:3] - truth[:3])
    sigma = np.sqrt(np.trace(P[:3, :3]))
    print(f"  {name:8s} {wall:8.2f} s for {updates} updates = {1e6 * wall / updates:7.1f} us/update;"
          f" final |dr| {err:7.2f} km (1-sigma {sigma:7.2f} km)")


def propagation_cost(model, x0: np.ndarray, t0: float, steps: int = 2000) -> None:
    fast = FastPropagator(model)
    fast.step(t0, x0, t0 + 60.0)
    start = time.perf_counter()
    x = x0
    for i in range(steps):
        x, _ = fast.step(t0 + 60.0 * i, x, t0 + 60.0 * (i + 1))
    fast_us = 1e6 * (time.perf_counter() - start) / steps
    start = time.perf_counter()
    x = x0
    for i in range(steps // 10):
        x = propagate(model, t0 + 60.0 * i, x, [t0 + 60.0 * (i + 1)], stm=True).states[-1]
    exact_us = 1e6 * (time.perf_counter() - start) / (steps // 10)
    print(f"  propagation of one 60-s step with the 6x6 STM: fast {fast_us:.1f} us, DOP853 {exact_us:.1f} us"
          f" (ratio {exact_us / fast_us:.0f}x; heyoka measured 130-150 us on this machine type)")


def s1_part(updates: int, runs: int, rng: np.random.Generator) -> None:
    print(f"S1 July, Phobos + Deimos RA/Dec alternating, 1/min, 0.1\": {updates} updates, full arc")
    t0, truth, epochs, values = s1_arc(updates, max(runs, 1), rng)
    dynamics = cruise_model()
    model = ProbeMeasurementModel("sun", ephemeris=default_cached_ephemeris())
    noise = WhiteAcceleration(1e-22)
    P0 = np.diag([(5000.0 / np.sqrt(3.0)) ** 2] * 3 + [(0.005 / np.sqrt(3.0)) ** 2] * 3)
    x0 = truth[0] + np.sqrt(np.diag(P0)) * rng.standard_normal((max(runs, 1), 6))
    propagation_cost(dynamics, truth[0], t0)
    records = s1_records(epochs, values[:, 0])
    transition = force_model_transition(dynamics)
    start = Estimate(t0, x0[0], P0)
    filters = {
        "EKF": lambda: ExtendedKalmanFilter(start, propagator=force_model_propagator(dynamics), model=model,
                                            process_noise=noise),
        "UKF": lambda: UnscentedKalmanFilter(start, transition=transition, process_noise=noise, model=model),
        "SR-UKF": lambda: SquareRootUKF(start, transition=transition, process_noise=noise, model=model),
    }
    for build in filters.values():  # warm-up: compiled kernels loaded, ephemeris segments fitted
        warm = build()
        for rec in records[:5]:
            warm.update(rec)
    walls = {}
    for name, build in filters.items():
        filt = build()
        begin = time.perf_counter()
        for rec in records:
            filt.update(rec)
        walls[name] = time.perf_counter() - begin
        report(name, walls[name], len(records), filt.estimate.x, filt.estimate.P, truth[-1])
    print(f"  UKF/EKF wall-time ratio {walls['UKF'] / walls['EKF']:.2f} (goal <= 1.2; paper 12x);"
          f" SR-UKF/EKF {walls['SR-UKF'] / walls['EKF']:.2f} (goal <= 1.5)")
    if runs < 1:
        return
    # lockstep: runs share epochs; records alternate between the two targets, so each target is one
    # template observed at every other epoch -- done as two interleaved templates with NaN (refused) gaps
    templates = [Measurement(t0, "radec", np.zeros(2), SIGMA_S1**2 * np.eye(2), target=t) for t in TARGETS]
    per_template = np.full((2, updates, runs, 2), np.nan)
    for j in range(2):
        per_template[j, j::2] = values[j::2]
    common = dict(process_noise=noise, progress=False)
    begin = time.perf_counter()
    ekf = run_ekf_lockstep(t0, x0, P0, epochs, templates, per_template,
                           propagator=force_model_batch_propagator(dynamics), model=model, keep_every=updates,
                           **common)
    wall_ekf = time.perf_counter() - begin
    begin = time.perf_counter()
    ukf = run_ukf_lockstep(t0, x0, P0, epochs, templates, per_template, transition=transition, model=model,
                           keep_every=updates, **common)
    wall_ukf = time.perf_counter() - begin
    for name, hist, wall in (("EKF", ekf, wall_ekf), ("UKF", ukf, wall_ukf)):
        err = np.linalg.norm(hist.states[-1, :, :3] - truth[-1, :3], axis=1)
        sigma = np.sqrt(np.trace(hist.covariances[-1, :, :3, :3], axis1=1, axis2=2))
        print(f"  lockstep {name}: {runs} runs in {wall:7.2f} s = {wall / runs:5.2f} s per run"
              f" (goal <= {1 if name == 'EKF' else 2} s); final |dr| mean {err.mean():7.2f} km,"
              f" 1-sigma mean {sigma.mean():7.2f} km")


def geo_state(t0: float) -> np.ndarray:
    """S3 circular equatorial GEO state at ``t0`` (the study's start), Earth-centred ICRF km and km/s."""
    return s3_geo_state()


def s3_part(upf_steps: int, rng: np.random.Generator) -> None:
    steps = 8640
    print(f"S3 GEO, starlight angle + elevation every 10 s, {steps} steps (24 h):")
    t0 = parse_epoch("2001-01-01T00:00:00", scale="utc")
    dynamics = geo_model(epoch_tdb_s=t0)
    epochs = t0 + 10.0 * np.arange(1, steps + 1)
    truth = propagate(dynamics, t0, geo_state(t0), epochs).states
    exact = ProbeMeasurementModel("earth", light_time=False, aberration=False)
    model = ProbeMeasurementModel("earth", light_time=False, aberration=False, ephemeris=default_cached_ephemeris())
    sigma = np.hypot(5.0, 20.0) / 3.0 * ARCSEC_RAD
    star = radec_to_unit(np.deg2rad(30.0), np.deg2rad(10.0))
    records = []
    for t, x in zip(epochs, truth):
        for kind in ("starlight_angle", "starlight_elevation"):
            rec = Measurement(t, kind, [0.0], [[sigma**2]], target="earth", star_unit_icrf=star, sensor="s3")
            value = exact.predict(rec, x) + sigma * rng.standard_normal(1)
            records.append(Measurement(t, kind, value, [[sigma**2]], target="earth", star_unit_icrf=star, sensor="s3"))
    P0 = np.diag([10.0**2] * 3 + [0.001**2] * 3)
    x0 = geo_state(t0) + np.sqrt(np.diag(P0)) * rng.standard_normal(6)
    noise = WhiteAcceleration(1e-12)
    warm = ExtendedKalmanFilter(Estimate(t0, x0, P0), propagator=force_model_propagator(dynamics), model=model,
                                process_noise=noise)
    for rec in records[:4]:
        warm.update(rec)
    ekf = ExtendedKalmanFilter(Estimate(t0, x0, P0), propagator=force_model_propagator(dynamics), model=model,
                               process_noise=noise)
    begin = time.perf_counter()
    for rec in records:
        ekf.update(rec)
    wall = time.perf_counter() - begin
    print(f"  EKF      {wall:8.2f} s for {steps} steps ({len(records)} scalar records; goal <= 3 s);"
          f" final |dr| {np.linalg.norm(ekf.estimate.x[:3] - truth[-1, :3]):.3f} km"
          f" (1-sigma {np.sqrt(np.trace(ekf.estimate.P[:3, :3])):.3f} km)")
    upf = UnscentedParticleFilter(Estimate(t0, x0, P0), transition=force_model_transition(dynamics),
                                  process_noise=noise, model=model, rng=rng,
                                  options=ParticleOptions(n_particles=150, mcmc_move=True))
    used = records[: 2 * upf_steps]
    begin = time.perf_counter()
    for rec in used:
        upf.update(rec)
    wall = time.perf_counter() - begin
    print(f"  MCMC-UPF {wall:8.2f} s for {upf_steps} steps, 150 particles = {1e3 * wall / upf_steps:.1f} ms/step"
          f" (goal <= 120 s for 8640 steps); final |dr| {np.linalg.norm(upf.estimate.x[:3] - truth[upf_steps - 1, :3]):.3f} km"
          f" (1-sigma {np.sqrt(np.trace(upf.estimate.P[:3, :3])):.3f} km)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--updates", type=int, default=43_200, help="S1 updates (43,200 = 30 days at 1/min)")
    parser.add_argument("--runs", type=int, default=20, help="S1 lockstep Monte Carlo runs (0: skip)")
    parser.add_argument("--upf-steps", type=int, default=8640, help="S3 MCMC-UPF steps (8640 = 24 h)")
    parser.add_argument("--seed", type=int, default=2014)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    s1_part(args.updates, args.runs, rng)
    s3_part(args.upf_steps, rng)


if __name__ == "__main__":
    main()
