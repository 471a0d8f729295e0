"""Filter speed: EKF vs UKF vs SR-UKF on the S1 arc, and the MCMC-UPF step cost on S3.

S1 part (SCENARIOS.md S1): truth from the S1 Table 1 state propagated with
``cruise_model()`` to 2014-07-01 TDB; one Deimos RA/Dec per minute with 0.1"
noise (light time and aberration on, as the renderer), 5000 km / 5 m/s initial
error. The 30-day arc has 43,200 updates; on this shared machine a
representative first fraction (``--updates``, default 600 = 10 h) is timed for
each filter on the same records and the full-arc time is extrapolated
linearly (per-update cost does not depend on the arc position: a 60 s
propagation and one measurement-model call). The final position error and
1-sigma are printed so that a fast but wrong filter would show.

S3 part (SCENARIOS.md S3): GEO orbit (RAAN 260 deg, true anomaly 0.702295 deg,
period 86164.09 s) from 2001-01-01 00:00 UTC with ``geo_model()``; every 10 s
one starlight angle (star sensor 5" 3-sigma combined with the UV Earth sensor
20" 3-sigma) and one starlight elevation; the MCMC-UPF with 150 particles
(all 150 x 13 sigma points in one propagate call per step). ``--upf-steps``
steps are timed and the per-step cost printed.

Usage::

    .venv/bin/python benchmarks/filters.py --updates 600 --upf-steps 20
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from opnav.constants import ARCSEC_RAD, EARTH_GM_JGM3_KM3_S2
from opnav.dynamics import cruise_model, geo_model, propagate
from opnav.epochs import parse_epoch
from opnav.filters.base import Estimate
from opnav.filters.ekf import ExtendedKalmanFilter, force_model_propagator
from opnav.filters.noise import WhiteAcceleration
from opnav.filters.particle import ParticleOptions, UnscentedParticleFilter
from opnav.filters.ukf import (
    SquareRootUKF,
    UnscentedKalmanFilter,
    force_model_transition,
)
from opnav.frames import radec_to_unit
from opnav.measurements import ProbeMeasurementModel, simulate_radec
from opnav.records import Measurement

S1_EPOCH_TT = "2013-12-12T12:00:00"
S1_STATE0 = np.array([24_306_991.2893, 132_523_850.2219, 58_427_884.5328, -32.455391, 3.658828, 3.362343])
FULL_ARC_UPDATES = 43_200


def s1_records(updates: int, rng: np.random.Generator):
    """Arc start, true initial state, true final state and Deimos RA/Dec records (0.1")."""
    model = ProbeMeasurementModel("sun")
    t_epoch = parse_epoch(S1_EPOCH_TT, scale="tt")
    t_start = parse_epoch("2014-07-01T00:00:00", scale="tdb")
    epochs = t_start + 60.0 * np.arange(1, updates + 1)
    states = propagate(cruise_model(), t_epoch, S1_STATE0, np.concatenate([[t_start], epochs])).states
    sigma = 0.1 * ARCSEC_RAD
    values = simulate_radec(model, "deimos", epochs, states[1:], sigma_rad=sigma, rng=rng)
    records = [Measurement(t, "radec", v, sigma**2 * np.eye(2), target="deimos", sensor="camera")
               for t, v in zip(epochs, values)]
    return t_start, states[0], states[-1], records, model


def time_filter(name, filt, records, truth_final):
    start = time.perf_counter()
    for rec in records:
        filt.update(rec)
    wall = time.perf_counter() - start
    err = np.linalg.norm(filt.estimate.x[:3] - truth_final[:3])
    sigma = np.sqrt(np.trace(filt.estimate.P[:3, :3]))
    full = wall / len(records) * FULL_ARC_UPDATES
    print(f"  {name:7s} {wall:8.2f} s for {len(records)} updates = {1e3 * wall / len(records):7.2f} ms/update"
          f" -> 30-day arc ~{full / 60:7.1f} min; final |dr| {err:8.1f} km (1-sigma {sigma:8.1f} km)")
    return wall


def s1_part(updates: int, rng: np.random.Generator) -> None:
    print(f"S1 (Deimos RA/Dec, 1/min, 0.1\"), first {updates} of {FULL_ARC_UPDATES} updates, extrapolated linearly:")
    t0, x_true, x_final, records, model = s1_records(updates, rng)
    sig_r, sig_v = 5000.0 / np.sqrt(3.0), 0.005 / np.sqrt(3.0)
    P0 = np.diag([sig_r**2] * 3 + [sig_v**2] * 3)
    x0 = x_true + np.sqrt(np.diag(P0)) * rng.standard_normal(6)
    dynamics = cruise_model()
    noise = WhiteAcceleration(1e-22)
    start = Estimate(t0, x0, P0)
    transition = force_model_transition(dynamics)
    # warm-up (ephemeris caches, first-call imports) so that no filter pays it inside its timing
    for warm in (ExtendedKalmanFilter(start, propagator=force_model_propagator(dynamics), model=model, process_noise=noise),
                 UnscentedKalmanFilter(start, transition=transition, process_noise=noise, model=model)):
        for rec in records[:5]:
            warm.update(rec)
    ekf = ExtendedKalmanFilter(start, propagator=force_model_propagator(dynamics), model=model, process_noise=noise)
    ukf = UnscentedKalmanFilter(start, transition=transition, process_noise=noise, model=model)
    srukf = SquareRootUKF(start, transition=transition, process_noise=noise, model=model)
    walls = {name: time_filter(name, f, records, x_final) for name, f in (("EKF", ekf), ("UKF", ukf), ("SR-UKF", srukf))}
    print(f"  UKF/EKF wall-time ratio {walls['UKF'] / walls['EKF']:.2f} (paper 12x; goal <= 1.5x);"
          f" SR-UKF/EKF {walls['SR-UKF'] / walls['EKF']:.2f}")


def geo_state(t0: float) -> np.ndarray:
    """S3 circular equatorial GEO state, Earth-centred ICRF km and km/s."""
    period = 86_164.09
    a = (EARTH_GM_JGM3_KM3_S2 * (period / (2 * np.pi)) ** 2) ** (1 / 3)
    u = np.deg2rad(260.0 + 0.702295)
    speed = np.sqrt(EARTH_GM_JGM3_KM3_S2 / a)
    return np.array([a * np.cos(u), a * np.sin(u), 0.0, -speed * np.sin(u), speed * np.cos(u), 0.0])


def s3_part(steps: int, rng: np.random.Generator) -> None:
    print(f"S3 (GEO, starlight angle + elevation every 10 s), MCMC-UPF with 150 particles, {steps} steps:")
    t0 = parse_epoch("2001-01-01T00:00:00", scale="utc")
    dynamics = geo_model()
    epochs = t0 + 10.0 * np.arange(1, steps + 1)
    truth = propagate(dynamics, t0, geo_state(t0), epochs).states
    model = ProbeMeasurementModel("earth", light_time=False, aberration=False)
    # star sensor 5" and Earth sensor 20" (3-sigma each) combine on the measured angle
    sigma = np.hypot(5.0, 20.0) / 3.0 * ARCSEC_RAD
    star = radec_to_unit(np.deg2rad(30.0), np.deg2rad(10.0))
    records = []
    for t, x in zip(epochs, truth):
        for kind in ("starlight_angle", "starlight_elevation"):
            rec = Measurement(t, kind, [0.0], [[sigma**2]], target="earth", star_unit_icrf=star, sensor="s3")
            value = model.predict(rec, x) + sigma * rng.standard_normal(1)
            records.append(Measurement(t, kind, value, [[sigma**2]], target="earth", star_unit_icrf=star, sensor="s3"))
    P0 = np.diag([10.0**2] * 3 + [0.001**2] * 3)
    x0 = geo_state(t0) + np.sqrt(np.diag(P0)) * rng.standard_normal(6)
    upf = UnscentedParticleFilter(Estimate(t0, x0, P0), transition=force_model_transition(dynamics),
                                  process_noise=WhiteAcceleration(1e-12), model=model, rng=rng,
                                  options=ParticleOptions(n_particles=150, mcmc_move=True))
    start = time.perf_counter()
    resampled = 0
    for i, rec in enumerate(records):
        upf.update(rec)
        if i % 2 == 1 and i + 1 < len(records):
            upf.predict(records[i + 1].t_tdb_s)
            resampled += bool(upf.last_epoch and upf.last_epoch.resampled)
    wall = time.perf_counter() - start
    print(f"  {wall:.2f} s for {steps} steps = {wall / steps:.3f} s/step (150 particles x 13 sigma points per"
          f" propagate call); 24 h arc (8640 steps) ~{wall / steps * 8640 / 3600:.1f} h;"
          f" resampled at {resampled} of {steps - 1} epochs")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--updates", type=int, default=600, help="S1 updates timed per filter")
    parser.add_argument("--upf-steps", type=int, default=20, help="S3 MCMC-UPF steps timed")
    parser.add_argument("--seed", type=int, default=2014)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    s1_part(args.updates, rng)
    s3_part(args.upf_steps, rng)


if __name__ == "__main__":
    main()
