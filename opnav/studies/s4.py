"""S4: federated angle + stellar-Doppler navigation at Mars approach, with and without time registration.

Set-up (docs/studies.md#s4-mars-approach):

- window 2021-01-15 05:46:07 UTC to 2021-01-25 18:40:00 UTC (``duration_hours`` shortens it);
- trajectory (S4 gives none): a heliocentric Lambert arc from the Earth on
  2020-07-23 04:00 UTC (Tianwen-1's launch) to Mars on 2021-02-10 11:52 UTC (its
  arrival), two-body, evaluated at the window start, then propagated as truth with
  ``approach_model()`` (Sun + Earth + Mars + SRP);
- angle sensor every 60 s: geometric lines of sight probe->Sun and probe->Mars
  (light time on), 2" (1-sigma) per transverse axis, turned into the S4 eq. 1
  position pseudo-measurement by :func:`opnav.measurements.position_measurement`;
- velocity sensor every 600 s, 1 m/s: Doppler of the Sun, Canopus (HIP 30438)
  and Vega (HIP 91262) with the catalog space velocities (:mod:`opnav.catalog`);
- the angle data lead the velocity clock by ``lead_s``: an angle sample is taken at
  ``t - lead`` for fusion epoch ``t``;
- federated UKF (angle local + velocity local, beta = 0.5 each, fusion-reset) fused
  every 60 s on the velocity clock; initial error dr = [1000, 1000, 1000] km,
  dv = [100, 100, 100] m/s.

Three runs on the same data: exact (each record at its own time tag), registered
(three-point Lagrange extrapolation to the fusion epochs) and unregistered (the
latest angle sample used as if taken at the fusion epoch).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..catalog import load_catalog
from ..constants import ARCSEC_RAD, GM_KM3_S2
from ..dynamics import approach_model, propagate, two_body_model
from ..ephemeris import default_ephemeris
from ..epochs import parse_epoch
from ..errors import InputError
from ..filters.base import Estimate
from ..filters.federated import FederatedFilter, FederatedOptions, run_federated
from ..filters.noise import WhiteAcceleration
from ..filters.registration import hold_latest, register
from ..filters.ukf import UKFOptions, UnscentedKalmanFilter, force_model_transition
from ..light import light_time_vector
from ..measurements import ProbeMeasurementModel, position_measurement
from ..records import Measurement
from ..studies.trajectories import lambert
from .evaluation import EstimatedTrajectory, Evaluation

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


@dataclass(frozen=True)
class FederatedRun:
    """One federated UKF run over an S4 record set.

    Attributes
    ----------
    states : (M, 6) array
        Fused estimates ``[r km, v km/s]`` at the fusion epochs, ICRF, heliocentric.
    covariances : (M, 6, 6) array
        Their covariances, km^2, km^2/s, km^2/s^2.
    refused : int
        Records the local filters refused.
    wall_s : float
        Wall time of the run, s.
    """

    states: np.ndarray
    covariances: np.ndarray
    refused: int
    wall_s: float

    @property
    def sigma(self) -> np.ndarray:
        """1-sigmas of the fused estimates (M, 6), km and km/s."""
        return np.sqrt(np.diagonal(self.covariances, axis1=1, axis2=2))


def run(records, epochs, t0, x_start, P0, model, dynamics) -> FederatedRun:
    """Federated UKF (angle + velocity locals, beta 0.5 each, fusion-reset) over ``records``, fused at ``epochs``."""
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
    return FederatedRun(np.array([e.x for e in fused]), np.array([e.P for e in fused]), int(refused),
                        time.perf_counter() - start)


#: The study's kind for the runner (:mod:`opnav.studies.base`): evaluating (its own ``evaluate``); ``--mode images`` is refused.
KIND = "evaluating"
IMAGE_MODE = False
#: Settings only image mode reads: none.
IMAGE_SETTINGS: tuple[str, ...] = ()


@dataclass(frozen=True)
class Settings:
    """S4 run settings (``[settings]`` of the run file; each one a ``--set`` key).

    Attributes
    ----------
    duration_hours : float
        Arc length from the window start, h; 0 takes the whole S4 window (253 h).
    lead_s : float
        The angle data lead the velocity clock by this, s (S4's time-registration case).
    """

    duration_hours: float = 0.0
    lead_s: float = 30.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.duration_hours) and 0.0 <= self.duration_hours <= 253.0):
            raise InputError(f"duration_hours must be in [0, 253] (0: the whole window), got {self.duration_hours}")
        if not (np.isfinite(self.lead_s) and 0.0 <= self.lead_s < 600.0):
            raise InputError(f"lead_s must be in [0, 600), got {self.lead_s}")


@dataclass(frozen=True)
class S4Case:
    """Truth and records of one S4 run: fusion epochs, true states there, the three record sets, the start."""

    t0: float
    epochs: np.ndarray
    truth: np.ndarray
    cases: dict
    x_start: np.ndarray
    P0: np.ndarray
    model: ProbeMeasurementModel
    facts: dict


def build_case(settings: Settings, seed: int) -> S4Case:
    """Simulate S4's sensors along the approach arc (module notes)."""
    rng = np.random.default_rng(seed)
    eph = default_ephemeris()
    t0 = parse_epoch(START_UTC)
    t_end = parse_epoch(END_UTC) if settings.duration_hours == 0.0 else t0 + 3600.0 * settings.duration_hours
    x0 = initial_state(t0)
    dynamics = approach_model()
    epochs = t0 + 60.0 * np.arange(1, int((t_end - t0) // 60.0) + 1)
    if epochs.size < 20:
        raise InputError(f"duration_hours={settings.duration_hours} leaves {epochs.size} fusion epochs; need 20")
    velocity_epochs = epochs[9::10]
    angle_times = epochs - settings.lead_s
    all_times = np.concatenate([angle_times, epochs])
    order = np.argsort(all_times, kind="stable")
    truth = np.empty((all_times.size, 6))
    truth[order] = propagate(dynamics, t0, x0, all_times[order]).states
    truth_angle, truth_fusion = truth[: epochs.size], truth[epochs.size:]
    catalog = load_catalog()
    stars, star_rv = {}, {}
    for name, hip in STARS_HIP.items():
        row = np.flatnonzero(catalog.hip == hip)
        u = catalog.unit_vectors()[row[0]]
        stars[name] = (hip, u)
        star_rv[hip] = float(catalog.space_velocity_km_s(row)[0] @ u)
    model = ProbeMeasurementModel("sun", light_time=False, aberration=False, star_radial_velocity_km_s=star_rv)
    positions = angle_records(angle_times, truth_angle, rng)
    dopplers = doppler_records(velocity_epochs, truth_fusion[np.isin(epochs, velocity_epochs)], model, stars, rng)
    cases = {"exact": positions + dopplers, "registered": register(positions, epochs, causal=True) + dopplers,
             "unregistered": hold_latest(positions, epochs) + dopplers}
    facts = {"state_at_start_km_km_s": x0.tolist(),
             "distance_to_mars_start_km": float(np.linalg.norm(x0[:3] - eph.state("mars", t0, center="sun")[0])),
             "distance_to_mars_end_km": float(np.linalg.norm(truth_fusion[-1, :3]
                                                             - eph.state("mars", epochs[-1], center="sun")[0])),
             "star_radial_velocity_km_s": {str(k): v for k, v in star_rv.items()},
             "position_pseudo_measurement_sigma_km": float(np.median([np.sqrt(np.trace(r.covariance) / 3)
                                                                      for r in positions]))}
    P0 = np.diag([1000.0**2] * 3 + [0.1**2] * 3)
    x_start = x0 + np.array([1000.0, 1000.0, 1000.0, 0.1, 0.1, 0.1])
    return S4Case(t0, epochs, truth_fusion, cases, x_start, P0, model, facts)


def run_cases(case: S4Case) -> dict[str, FederatedRun]:
    """The three federated runs, by case name."""
    return {name: run(records, case.epochs, case.t0, case.x_start, case.P0, case.model, approach_model())
            for name, records in case.cases.items()}


#: How each case uses the angle records (the report's legend and the OEMs' comments).
CASE_DESCRIPTIONS = {
    "exact": "each angle record at its own time tag (reference)",
    "registered": "angle data brought to the fusion epochs by three-point Lagrange extrapolation",
    "unregistered": "the latest angle sample used as if taken at the fusion epoch",
}


def evaluate(settings: Settings, seed: int, log) -> Evaluation:
    """The run's figures (final errors of the exact, registered and unregistered federated runs), the
    arrays the report plots (errors and 1-sigmas at every fusion epoch) and the three estimated
    trajectories."""
    from ..filters.estimates import Track

    log(f"S4: simulating the approach arc (lead {settings.lead_s:g} s, seed {seed})")
    case = build_case(settings, seed)
    filters, arrays, trajectories = {}, {"t_tdb_s": case.epochs}, []
    for name, result in run_cases(case).items():
        log(f"federated UKF ({name}) done in {result.wall_s:.1f} s")
        sigma = result.sigma
        error = result.states - case.truth
        err, verr = error[-1, :3], error[-1, 3:]
        filters[name] = {"final_position_error_km": float(np.linalg.norm(err)),
                         "final_position_sigma_km": float(np.linalg.norm(sigma[-1, :3])),
                         "final_velocity_error_m_s": float(1e3 * np.linalg.norm(verr)),
                         "final_velocity_sigma_m_s": float(1e3 * np.linalg.norm(sigma[-1, 3:])),
                         "max_axis_error_in_sigma": float(np.max(np.abs(err) / sigma[-1, :3])),
                         "refused": result.refused, "records": len(case.cases[name]), "wall_s": result.wall_s}
        arrays[f"{name}_state"], arrays[f"{name}_error"], arrays[f"{name}_sigma"] = result.states, error, sigma
        trajectories.append(EstimatedTrajectory(name, "sun", Track(case.epochs, result.states, result.covariances),
                                                f"S4 federated UKF, {CASE_DESCRIPTIONS[name]}"))
    summary = {"filters": filters, "facts": case.facts,
               "paper": {"claim": "without registration the federated filter diverges; with it, it converges"}}
    return Evaluation(summary, arrays, tuple(trajectories))


def report_blocks(summary: dict, arrays) -> list:
    """The report's paragraphs, tables and figures (:func:`opnav.studies.report_s4.report_blocks`)."""
    from .report_s4 import report_blocks as blocks

    return blocks(summary, arrays)
