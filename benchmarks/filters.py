"""Filter speed: S1's runner filter stage (EKF, UKF, SR-UKF), the EKF update against filterpy's, lockstep, S3.

S1 runner stage (docs/studies.md#s1-mars-cruise): the records, initial estimate and force model of
``samples/s1_jul_both_0.1.toml`` made by the study's own simulation (Phobos and Deimos RA/Dec
every minute for 30 days, 0.1", 86,400 records, moon ephemeris error 1 km white), then each filter
run through :func:`opnav.filters.navigate.navigate` exactly as ``opnav run`` calls it
(:func:`opnav.studies.runner.filter_stage`): per-record cost, the wall-time ratios, and the
figures the runner reports (position RMS over the last 15 days, final error and 1-sigma), so a
fast but wrong filter would show. Warm-up first (compiled kernels loaded, ephemeris segments
fitted), on the first 50 records.

EKF update against filterpy: one S1 record at mid-arc and the EKF's prior at its epoch; opnav's
single-run update as the filters take it (``ExtendedKalmanFilter.update``: the compiled step with
light time, aberration, the Jacobian, R with the ephemeris term, the Joseph update, the gate and the
covariance check) timed beside filterpy's ``ExtendedKalmanFilter.update`` given the same ``H``,
``h(x)``, ``R`` and the wrapped residual (the Joseph update alone, no model), and beside opnav's pure
core ``ekf_update`` (the general path); the posteriors are compared.

Lockstep: ``--runs`` Monte Carlo runs of the EKF and UKF together on an S1 arc (Phobos and Deimos
alternating, one record a minute, 5000 km / 5 m/s initial error; ``run_ekf_lockstep``,
``run_ukf_lockstep``). The propagation cost of one 60-s step with the STM is printed beside DOP853's
(scipy, rtol 1e-11, one call per step as the exact filter path does) timed in the same run.

S3 part (docs/studies.md#s3-geo-satellite): GEO orbit (RAAN 260 deg, true anomaly 0.702295 deg,
period 86164.09 s) from 2001-01-01 00:00 UTC with ``geo_model()``; every 10 s one
starlight angle and one starlight elevation (star sensor 5" and UV Earth sensor
20", 3-sigma, combined); the EKF over the whole 24 h (8,640 steps) and the
MCMC-UPF with 150 particles over ``--upf-steps`` steps (the whole day by default).

Timings share the machine with whatever else runs: compare the ratios printed within one run.

Usage::

    .venv/bin/python benchmarks/filters.py            # everything, full length
    .venv/bin/python benchmarks/filters.py --days 5 --runs 0 --upf-steps 500
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
from opnav.filters.ekf import ExtendedKalmanFilter, ekf_update, force_model_batch_propagator, force_model_propagator
from opnav.filters.factory import build_filter, measurement_model
from opnav.filters.lockstep import run_ekf_lockstep, run_ukf_lockstep
from opnav.filters.navigate import navigate
from opnav.filters.noise import WhiteAcceleration
from opnav.filters.particle import ParticleOptions, UnscentedParticleFilter
from opnav.filters.ukf import force_model_transition
from opnav.frames import radec_to_unit
from opnav.measurements import ProbeMeasurementModel, simulate_radec
from opnav.records import Measurement
from opnav.studies.common import filter_metrics
from opnav.studies.runner import study_of
from opnav.studies.s1 import S1_EPOCH_TT, S1_STATE0
from opnav.studies.s3 import geo_state as s3_geo_state
from opnav.studies.settings import load_run_file

SIGMA_S1 = 0.1 * ARCSEC_RAD
TARGETS = ("phobos", "deimos")
RUN_FILE = "samples/s1_jul_both_0.1.toml"


def runner_stage(run_file: str, days: float | None, filters: tuple[str, ...]):
    """The S1 run's simulation and each filter's stage through ``navigate``; returns (sim, EKF history)."""
    run = load_run_file(run_file, {"duration_days": str(days)} if days else None)
    begin = time.perf_counter()
    sim = study_of(run).simulate(run.settings, run.seed)
    print(f"S1 runner filter stage: {run.path} (seed {run.seed}), {len(sim.records)} records"
          f" (simulated in {time.perf_counter() - begin:.1f} s)")
    common = dict(force_model=sim.force_model, center=sim.center)
    for name in filters:  # warm-up: compiled kernels loaded, ephemeris segments fitted
        navigate(sim.records[:50], sim.navigation, filter_name=name, **common)
    walls, ekf_history = {}, None
    for name in filters:
        cpu = time.process_time()
        result = navigate(sim.records, sim.navigation, filter_name=name, **common)
        cpu = time.process_time() - cpu
        walls[name] = result.wall_s
        figures = filter_metrics(result.history, sim)
        final = figures["final"]
        print(f"  {name:7s} {result.wall_s:7.2f} s = {1e6 * result.wall_s / len(sim.records):6.1f} us/record"
              f" (process CPU {1e6 * cpu / len(sim.records):6.1f} us/record); position RMS"
              f" {figures['position_rms_km']:.4f} km, final |dr| {final['position_error_km']:.3f} km"
              f" (1-sigma {final['position_sigma_km']:.3f} km), accepted {figures['accepted']}/{figures['records']}")
        if name == "ekf":
            ekf_history = result.history
    if "ekf" in walls:
        ratios = ", ".join(f"{n.upper()}/EKF {walls[n] / walls['ekf']:.2f}" for n in walls if n != "ekf")
        print(f"  EKF stage goal <= 10 s for 86,400 records (~110 us/record); {ratios} (UKF goal <= 1.2)")
    return sim, ekf_history


def update_against_filterpy(sim, history, repeats: int = 20_000) -> None:
    """opnav's single-run EKF update against filterpy's for one mid-arc S1 record (module notes)."""
    from filterpy.kalman import ExtendedKalmanFilter as FilterpyEKF

    nav = sim.navigation
    model = measurement_model(nav, sim.center)
    ordered = sorted(sim.records, key=lambda r: r.t_tdb_s)
    i = len(ordered) // 2
    record = ordered[i]
    ekf = build_filter("ekf", nav, model, sim.force_model)
    ekf.reset(Estimate(float(history.epochs[i - 1]), history.states[i - 1], history.covariances[i - 1]))
    prior = ekf.predict(record.t_tdb_s)  # at the record's epoch: the update alone is timed
    h, H = model.predict_and_jacobians(record, prior.x[None])
    h, H = h[0], H[0]
    R = model.noise_covariance(record, prior.x)

    def residual(z, hx):
        return model.residual(record, hx.ravel()).reshape(-1, 1)

    def filterpy_at_prior():
        fp = FilterpyEKF(dim_x=6, dim_z=record.size)
        fp.x, fp.P = prior.x.reshape(6, 1).copy(), prior.P.copy()
        return fp

    z, column = record.value.reshape(-1, 1), h.reshape(-1, 1)
    fp = filterpy_at_prior()
    fp.update(z, HJacobian=lambda x: H, Hx=lambda x: column, R=R, residual=residual)
    mine = ekf.update(record)
    general = ekf_update(prior, record, model=model, options=ekf.options)
    sigma = np.sqrt(np.diag(fp.P))
    print(f"EKF update, one S1 record at mid-arc (m = {record.size}, n = 6), prior at the record epoch:")
    print(f"  posteriors: opnav vs filterpy |dx|/sigma {np.max(np.abs(mine.estimate.x - fp.x.ravel()) / sigma):.1e},"
          f" |dP|/(sigma sigma) {np.max(np.abs(mine.estimate.P - fp.P) / np.outer(sigma, sigma)):.1e};"
          f" opnav compiled vs pure core |dP|/(sigma sigma)"
          f" {np.max(np.abs(mine.estimate.P - general.estimate.P) / np.outer(sigma, sigma)):.1e}")
    fp = filterpy_at_prior()
    begin = time.perf_counter()
    for _ in range(repeats):
        fp.update(z, HJacobian=lambda x: H, Hx=lambda x: column, R=R, residual=residual)
    filterpy_us = 1e6 * (time.perf_counter() - begin) / repeats
    ekf.reset(prior)
    begin = time.perf_counter()
    for _ in range(repeats):  # the record folded in again and again: one update each, at one epoch
        ekf.update(record)
    opnav_us = 1e6 * (time.perf_counter() - begin) / repeats
    begin = time.perf_counter()
    for _ in range(repeats // 10):
        ekf_update(prior, record, model=model, options=ekf.options)
    core_us = 1e6 * (time.perf_counter() - begin) / (repeats // 10)
    print(f"  opnav ExtendedKalmanFilter.update {opnav_us:6.1f} us (model, light time, aberration, R, Joseph, gate,"
          f" check); filterpy ExtendedKalmanFilter.update {filterpy_us:6.1f} us (Joseph update given H, h, R):"
          f" opnav/filterpy {opnav_us / filterpy_us:.2f} (goal <= 1.5); opnav pure core ekf_update {core_us:6.1f} us")


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


def lockstep_part(updates: int, runs: int, rng: np.random.Generator) -> None:
    print(f"S1 lockstep, Phobos + Deimos RA/Dec alternating, 1/min, 0.1\": {updates} updates, {runs} runs")
    t0, truth, epochs, values = s1_arc(updates, runs, rng)
    dynamics = cruise_model()
    model = ProbeMeasurementModel("sun", ephemeris=default_cached_ephemeris())
    noise = WhiteAcceleration(1e-22)
    P0 = np.diag([(5000.0 / np.sqrt(3.0)) ** 2] * 3 + [(0.005 / np.sqrt(3.0)) ** 2] * 3)
    x0 = truth[0] + np.sqrt(np.diag(P0)) * rng.standard_normal((runs, 6))
    propagation_cost(dynamics, truth[0], t0)
    transition = force_model_transition(dynamics)
    # runs share epochs; records alternate between the two targets, so each target is one
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
    parser.add_argument("--run-file", default=RUN_FILE, help="S1 run file of the runner stage")
    parser.add_argument("--days", type=float, default=None, help="S1 arc length (default: the run file's 30 days)")
    parser.add_argument("--filters", default="ekf,ukf,sr-ukf", help="filters of the runner stage")
    parser.add_argument("--updates", type=int, default=43_200, help="lockstep updates (43,200 = 30 days at 1/min)")
    parser.add_argument("--runs", type=int, default=20, help="S1 lockstep Monte Carlo runs (0: skip)")
    parser.add_argument("--upf-steps", type=int, default=8640, help="S3 MCMC-UPF steps (8640 = 24 h; 0: skip S3)")
    parser.add_argument("--seed", type=int, default=2014)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    filters = tuple(name.strip() for name in args.filters.split(",") if name.strip())
    sim, ekf_history = runner_stage(args.run_file, args.days, filters)
    if ekf_history is not None:
        update_against_filterpy(sim, ekf_history)
    if args.runs > 0:
        lockstep_part(args.updates, args.runs, rng)
    if args.upf_steps > 0:
        s3_part(args.upf_steps, rng)


if __name__ == "__main__":
    main()
