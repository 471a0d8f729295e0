"""S4: federated angle + stellar-Doppler navigation at Mars approach, with and without time registration.

Set-up (SCENARIOS.md S4):
- window 2021-01-15 05:46:07 UTC to 2021-01-25 18:40:00 UTC;
- trajectory (stated here, S4 gives none): a heliocentric Lambert arc from the
  Earth on 2020-07-23 04:00 UTC (Tianwen-1's launch) to Mars on 2021-02-10
  11:52 UTC (its arrival), two-body, evaluated at the window start; that state
  is then propagated as truth with ``approach_model()`` (Sun + Earth + Mars + SRP);
  the script prints the state and the distance to Mars;
- angle sensor every 60 s: geometric lines of sight probe->Sun and probe->Mars
  (light time on), 2" (1-sigma) per transverse axis, turned into the S4 eq. 1
  position pseudo-measurement by :func:`opnav.measurements.position_measurement`;
- velocity sensor every 600 s, 1 m/s: Doppler of the Sun, Canopus (HIP 30438)
  and Vega (HIP 91262) with the catalog space velocities (``opnav.catalog``);
- the angle data lead the velocity clock by ``--lead-s`` (default 30 s): an
  angle sample is taken at ``t - lead`` for fusion epoch ``t``;
- federated UKF (angle local + velocity local, beta = 0.5 each, fusion-reset)
  fused every 60 s on the velocity clock; initial error dr = [1000, 1000, 1000] km,
  dv = [100, 100, 100] m/s.
Three runs on the same data: exact (each record at its own time tag), registered
(three-point Lagrange extrapolation to the fusion epochs) and unregistered (the
latest angle sample used as if taken at the fusion epoch). A plot of the
position error of each with the registered run's 3-sigma is saved.

Usage::

    .venv/bin/python benchmarks/s4_registration.py --hours 252 --out out/benchmarks/s4_registration.png
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from opnav.catalog import load_catalog  # noqa: E402
from opnav.constants import ARCSEC_RAD, GM_KM3_S2  # noqa: E402
from opnav.dynamics import approach_model, propagate, two_body_model  # noqa: E402
from opnav.ephemeris import default_ephemeris  # noqa: E402
from opnav.epochs import parse_epoch  # noqa: E402
from opnav.filters.base import Estimate  # noqa: E402
from opnav.filters.federated import FederatedFilter, FederatedOptions, run_federated  # noqa: E402
from opnav.filters.noise import WhiteAcceleration  # noqa: E402
from opnav.filters.registration import hold_latest, register  # noqa: E402
from opnav.filters.ukf import UKFOptions, UnscentedKalmanFilter, force_model_transition  # noqa: E402
from opnav.light import light_time_vector  # noqa: E402
from opnav.measurements import ProbeMeasurementModel, position_measurement  # noqa: E402
from opnav.records import Measurement  # noqa: E402
from opnav.trajectories import lambert  # noqa: E402

START_UTC, END_UTC = "2021-01-15T05:46:07", "2021-01-25T18:40:00"
LAUNCH_UTC, ARRIVAL_UTC = "2020-07-23T04:00:00", "2021-02-10T11:52:00"
STARS_HIP = {"canopus": 30438, "vega": 91262}
ANGLE_SIGMA_RAD = 2.0 * ARCSEC_RAD
DOPPLER_SIGMA_KM_S = 1e-3


def initial_state(t_start: float) -> np.ndarray:
    """Heliocentric ICRF state (km, km/s) at ``t_start`` on the Earth -> Mars Lambert arc."""
    eph = default_ephemeris()
    t_dep, t_arr = parse_epoch(LAUNCH_UTC), parse_epoch(ARRIVAL_UTC)
    r_earth = eph.state("earth", t_dep, center="sun")[0]
    r_mars = eph.state("mars", t_arr, center="sun")[0]
    pole = np.cross(r_earth, eph.state("earth", t_dep, center="sun")[1])
    v_dep, _ = lambert(r_earth, r_mars, t_arr - t_dep, mu_km3_s2=GM_KM3_S2["sun"], pole=pole)
    return propagate(two_body_model("sun"), t_dep, np.concatenate([r_earth, v_dep]), t_start).states[-1]


def transverse_noise(u: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Unit vector ``u`` perturbed by ``sigma`` rad along two axes perpendicular to it."""
    a = np.cross(u, [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(u, a)
    noisy = u + sigma * (rng.standard_normal() * a + rng.standard_normal() * b)
    return noisy / np.linalg.norm(noisy)


def angle_records(times: np.ndarray, states: np.ndarray, rng: np.random.Generator) -> list[Measurement]:
    """Eq. 1 position pseudo-measurements from noisy geometric lines of sight to the Sun and Mars."""
    eph = default_ephemeris()
    r_sun_ssb = eph.state("sun", times, center="ssb")[0]
    r_probe_ssb = states[:, :3] + r_sun_ssb
    out = []
    cov_line = lambda u: ANGLE_SIGMA_RAD**2 * (np.eye(3) - np.outer(u, u))
    to_sun, _ = light_time_vector(lambda t: eph.state("sun", t, center="ssb")[0], times, r_probe_ssb)
    to_mars, _ = light_time_vector(lambda t: eph.state("mars", t, center="ssb")[0], times, r_probe_ssb)
    for t, d_s, d_m in zip(times, to_sun, to_mars):
        l_ps = transverse_noise(d_s / np.linalg.norm(d_s), ANGLE_SIGMA_RAD, rng)
        l_pm = transverse_noise(d_m / np.linalg.norm(d_m), ANGLE_SIGMA_RAD, rng)
        out.append(position_measurement(t, l_ps, cov_line(l_ps), l_pm, cov_line(l_pm), sensor="angle"))
    return out


def doppler_records(times, states, model, stars, rng) -> list[Measurement]:
    """Sun and star radial velocities (km/s, 1 m/s noise) at the velocity-sensor epochs."""
    out = []
    for t, x in zip(times, states):
        sources = [(0, "sun", -x[:3] / np.linalg.norm(x[:3]))] + [(hip, name, u) for name, (hip, u) in stars.items()]
        for star_id, target, direction in sources:
            template = Measurement(t, "radial_velocity", [0.0], [[DOPPLER_SIGMA_KM_S**2]], target=target,
                                   sensor="velocity", star_id=star_id, star_unit_icrf=direction)
            value = model.predict(template, x) + DOPPLER_SIGMA_KM_S * rng.standard_normal(1)
            out.append(Measurement(t, "radial_velocity", value, [[DOPPLER_SIGMA_KM_S**2]], target=target,
                                   sensor="velocity", star_id=star_id, star_unit_icrf=direction))
    return out


def run(name, records, epochs, t0, x_start, P0, model, dynamics):
    transition = force_model_transition(dynamics)
    noise = WhiteAcceleration(1e-20)
    locals_ = {k: UnscentedKalmanFilter(Estimate(t0, x_start, P0), transition=transition, process_noise=noise,
                                        model=model, options=UKFOptions(alpha=1e-3))
               for k in ("angle", "velocity")}
    federated = FederatedFilter(locals_, initial=Estimate(t0, x_start, P0),
                                options=FederatedOptions(betas={"angle": 0.5, "velocity": 0.5},
                                                         routes={"angle": "angle", "velocity": "velocity"}))
    start = time.perf_counter()
    fused, outcomes = run_federated(federated, records, epochs)
    refused = sum(not o.accepted for o in outcomes)
    print(f"  {name:12s} {len(records):6d} records, {refused} refused, {time.perf_counter() - start:6.1f} s")
    return np.array([e.x for e in fused]), np.array([np.sqrt(np.diag(e.P)) for e in fused])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--hours", type=float, default=None, help="arc length (default: the whole window)")
    parser.add_argument("--lead-s", type=float, default=30.0, help="angle data lead the velocity clock by this")
    parser.add_argument("--seed", type=int, default=2021)
    parser.add_argument("--out", type=Path, default=Path("out/benchmarks/s4_registration.png"))
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    eph = default_ephemeris()

    t0 = parse_epoch(START_UTC)
    t_end = parse_epoch(END_UTC) if args.hours is None else t0 + 3600.0 * args.hours
    x0 = initial_state(t0)
    print(f"S4 trajectory at {START_UTC} UTC (heliocentric ICRF): r = {np.array2string(x0[:3], precision=1)} km,"
          f" v = {np.array2string(x0[3:], precision=6)} km/s")
    dynamics = approach_model()
    epochs = t0 + 60.0 * np.arange(1, int((t_end - t0) // 60.0) + 1)
    velocity_epochs = epochs[9::10]
    angle_times = epochs - args.lead_s
    all_times = np.concatenate([angle_times, epochs])
    order = np.argsort(all_times, kind="stable")
    truth = np.empty((all_times.size, 6))
    truth[order] = propagate(dynamics, t0, x0, all_times[order]).states
    truth_angle, truth_fusion = truth[: epochs.size], truth[epochs.size :]
    for label, t, x in (("start", t0, x0), ("end", epochs[-1], truth_fusion[-1])):
        d = np.linalg.norm(x[:3] - eph.state("mars", t, center="sun")[0])
        print(f"  distance to Mars at {label}: {d / 1e6:.2f} million km")

    catalog = load_catalog()
    stars = {}
    star_rv = {}
    for name, hip in STARS_HIP.items():
        row = np.flatnonzero(catalog.hip == hip)
        u = catalog.unit_vectors()[row[0]]
        stars[name] = (hip, u)
        star_rv[hip] = float(catalog.space_velocity_km_s(row)[0] @ u)
    print(f"  star radial velocities from the catalog: {', '.join(f'HIP {k}: {v:+.2f} km/s' for k, v in star_rv.items())}")
    model = ProbeMeasurementModel("sun", light_time=False, aberration=False, star_radial_velocity_km_s=star_rv)

    positions = angle_records(angle_times, truth_angle, rng)
    in_velocity = np.isin(epochs, velocity_epochs)
    dopplers = doppler_records(velocity_epochs, truth_fusion[in_velocity], model, stars, rng)
    sigma_pos = np.median([np.sqrt(np.trace(r.covariance) / 3) for r in positions])
    print(f"  eq. 1 position pseudo-measurement: median 1-sigma {sigma_pos:.0f} km per axis;"
          f" lead {args.lead_s:.0f} s x |v| {np.linalg.norm(x0[3:]):.1f} km/s = {args.lead_s * np.linalg.norm(x0[3:]):.0f} km")

    P0 = np.diag([1000.0**2] * 3 + [0.1**2] * 3)
    x_start = x0 + np.array([1000.0, 1000.0, 1000.0, 0.1, 0.1, 0.1])
    cases = {
        "exact": positions + dopplers,
        "registered": register(positions, epochs, causal=True) + dopplers,
        "unregistered": hold_latest(positions, epochs) + dopplers,
    }
    results = {name: run(name, recs, epochs, t0, x_start, P0, model, dynamics) for name, recs in cases.items()}

    days = (epochs - t0) / 86_400.0
    fig, ax = plt.subplots(figsize=(9, 5))
    print("final errors (fused estimate at the last epoch):")
    for name, (x, sigma) in results.items():
        err = x[:, :3] - truth_fusion[:, :3]
        verr = x[:, 3:] - truth_fusion[:, 3:]
        ax.semilogy(days, np.linalg.norm(err, axis=1), label=f"{name}: |dr|")
        print(f"  {name:12s} |dr| {np.linalg.norm(err[-1]):9.1f} km  (1-sigma {np.linalg.norm(sigma[-1, :3]):8.1f} km),"
              f" |dv| {1e3 * np.linalg.norm(verr[-1]):7.3f} m/s (1-sigma {1e3 * np.linalg.norm(sigma[-1, 3:]):6.3f} m/s),"
              f" max |dr_i|/sigma_i {np.max(np.abs(err[-1]) / sigma[-1, :3]):5.2f}")
    sigma_reg = results["registered"][1]
    ax.semilogy(days, 3.0 * np.linalg.norm(sigma_reg[:, :3], axis=1), "k--", label="registered: 3-sigma")
    ax.set_xlabel(f"days since {START_UTC} UTC")
    ax.set_ylabel("position error, km")
    ax.set_title(f"S4 federated angle + Doppler navigation, angle data lead by {args.lead_s:.0f} s")
    ax.legend()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=120, bbox_inches="tight")
    print(f"plot saved to {args.out}")


if __name__ == "__main__":
    main()
