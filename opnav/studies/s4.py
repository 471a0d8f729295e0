"""S4: federated angle + stellar-Doppler navigation at Mars approach, with and without time registration.

Set-up (docs/studies.md#s4-mars-approach):

- window 2021-01-15 05:46:07 UTC to 2021-01-25 18:40:00 UTC (``duration_hours`` shortens it);
- trajectory (S4 gives none): a heliocentric Lambert arc from the Earth on
  2020-07-23 04:00 UTC (Tianwen-1's launch) to Mars on 2021-02-10 11:52 UTC (its
  arrival), two-body, evaluated at the window start, then propagated as truth with
  ``approach_model()`` (Sun + Earth + Mars + SRP);
- angle sensor every 60 s (``angle_step_s``): geometric lines of sight probe->Sun and probe->Mars
  (light time on), 2" (1-sigma, ``sun_sigma_arcsec`` and ``mars_sigma_arcsec``) per transverse
  axis, turned into the S4 eq. 1 position pseudo-measurement by
  :func:`opnav.measurements.position_measurement`;
- velocity sensor every 600 s, 1 m/s: Doppler of the Sun, Canopus (HIP 30438)
  and Vega (HIP 91262) with the catalog space velocities (:mod:`opnav.catalog`);
- the angle data lead the velocity clock by ``lead_s``: an angle sample is taken at
  ``t - lead`` for fusion epoch ``t`` (every ``angle_step_s / 60``-th fusion epoch gets one);
- federated UKF (angle local + velocity local, beta = 0.5 each, fusion-reset) fused
  every 60 s on the velocity clock; initial error dr = [1000, 1000, 1000] km,
  dv = [100, 100, 100] m/s.

Three runs on the same data: exact (each record at its own time tag), registered
(three-point Lagrange extrapolation to the fusion epochs that follow each angle sample) and
unregistered (the latest angle sample used as if taken at the fusion epoch).

``--mode images`` (:mod:`opnav.studies.s4_images`) takes the lines of sight from rendered frames of
Mars and a sun-sensor model instead, every ``image_step_s``; the rest is this module's.
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


def geometric_lines(times: np.ndarray, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """True geometric (light time, no aberration) unit lines of sight probe -> Sun and probe -> Mars
    (M, 3) each, ICRF, at ``times`` (M,) TDB s for heliocentric ICRF states ``states`` (M, 6) km, km/s."""
    eph = default_ephemeris()
    r_probe_ssb = states[:, :3] + eph.state("sun", times, center="ssb")[0]
    to_sun, _ = light_time_vector(lambda t: eph.state("sun", t, center="ssb")[0], times, r_probe_ssb)
    to_mars, _ = light_time_vector(lambda t: eph.state("mars", t, center="ssb")[0], times, r_probe_ssb)
    return (to_sun / np.linalg.norm(to_sun, axis=1, keepdims=True),
            to_mars / np.linalg.norm(to_mars, axis=1, keepdims=True))


def line_covariance(u: np.ndarray, sigma_rad: float) -> np.ndarray:
    """Covariance (3, 3) of a unit line of sight ``u`` with ``sigma_rad`` per transverse axis (rank 2)."""
    return sigma_rad**2 * (np.eye(3) - np.outer(u, u))


def angle_records(times: np.ndarray, states: np.ndarray, rng: np.random.Generator, *,
                  sun_sigma_rad: float = ANGLE_SIGMA_RAD, mars_sigma_rad: float = ANGLE_SIGMA_RAD) -> list[Measurement]:
    """Eq. 1 position pseudo-measurements from noisy geometric lines of sight to the Sun and Mars
    (``sun_sigma_rad`` and ``mars_sigma_rad`` per transverse axis), at ``times`` (M,) TDB s for the
    heliocentric ICRF states ``states`` (M, 6) km, km/s."""
    out = []
    for t, d_s, d_m in zip(times, *geometric_lines(times, states)):
        l_ps = transverse_noise(d_s, sun_sigma_rad, rng)
        l_pm = transverse_noise(d_m, mars_sigma_rad, rng)
        out.append(position_measurement(t, l_ps, line_covariance(l_ps, sun_sigma_rad), l_pm,
                                        line_covariance(l_pm, mars_sigma_rad), sensor="angle"))
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


#: The study's kind for the runner (:mod:`opnav.studies.base`): evaluating (its own ``evaluate``), with an
#: image mode (``evaluate_images``, :mod:`opnav.studies.s4_images`).
KIND = "evaluating"
IMAGE_MODE = True
#: Settings only image mode reads (:mod:`opnav.studies.s4_images`).
IMAGE_SETTINGS: tuple[str, ...] = (
    "image_step_s", "camera_fov_deg", "camera_px", "camera_aperture_mm", "camera_exposure_s", "camera_psf_sigma_px",
    "tracker_fov_deg", "tracker_px", "tracker_aperture_mm", "tracker_exposure_s", "tracker_vmag_limit",
    "tracker_from_camera_deg", "sun_sensor_from_camera_deg", "sun_sensor_half_angle_deg", "sun_sensor_sigma_arcsec",
    "sun_sensor_bias_arcsec")
#: Fusion (velocity-clock) step, s.
FUSION_STEP_S = 60.0


@dataclass(frozen=True)
class Settings:
    """S4 run settings (``[settings]`` of the run file; each one a ``--set`` key).

    Attributes
    ----------
    duration_hours : float
        Arc length from the window start, h; 0 takes the whole S4 window (253 h).
    lead_s : float
        The angle data lead the velocity clock by this, s (S4's time-registration case).
    angle_step_s : float
        Measurement mode: one angle sample every this, s (S4: 60; a multiple of the 60 s fusion step).
    sun_sigma_arcsec, mars_sigma_arcsec : float
        Measurement mode: noise of the Sun's and Mars' lines of sight, 1-sigma per transverse axis,
        arcsec (S4: 2 each).
    image_step_s : float
        Image mode: one camera frame, star-tracker frame and sun-sensor reading (one angle sample)
        every this, s (a multiple of 60; 600 by default: 1,518 frames over the window).
    camera_fov_deg, camera_px, camera_aperture_mm, camera_exposure_s, camera_psf_sigma_px : float, int, ...
        Image mode: the navigation camera, boresight on Mars: field across ``camera_px`` square
        pixels (1 deg over 512 px, 7"/px: Mars 33-56 px across), aperture, exposure (20 mm and 0.01 s
        keep Mars' brightest pixel near 40 % of full well) and the PSF's Gaussian sigma, px (also the
        centre finder's model: the camera's calibrated PSF).
    tracker_fov_deg, tracker_px, tracker_aperture_mm, tracker_exposure_s, tracker_vmag_limit : ...
        Image mode: the star tracker (field across ``tracker_px`` square pixels, aperture, exposure,
        faintest catalog star it tracks, V).
    tracker_from_camera_deg : float
        Image mode: the tracker's boresight is the camera's turned by this about the body's x axis,
        deg (180: looking away from Mars; its roll then turns the camera about its own boresight).
    sun_sensor_from_camera_deg : float
        Image mode: the sun sensor's boresight is the camera's turned by this toward the body's +x
        axis (the Sun's side), deg (the Sun is 124-120 deg from Mars over the window).
    sun_sensor_half_angle_deg, sun_sensor_sigma_arcsec : float
        Image mode: the sun sensor's field half-angle, deg, and its noise, 1-sigma per transverse
        axis, arcsec (:mod:`opnav.sim.sun_sensor`).
    sun_sensor_bias_arcsec : (float, float)
        Image mode: the sun sensor's bias along its two axes, arcsec (the filters are not told).
    """

    duration_hours: float = 0.0
    lead_s: float = 30.0
    angle_step_s: float = 60.0
    sun_sigma_arcsec: float = 2.0
    mars_sigma_arcsec: float = 2.0
    image_step_s: float = 600.0
    camera_fov_deg: float = 1.0
    camera_px: int = 512
    camera_aperture_mm: float = 20.0
    camera_exposure_s: float = 0.01
    camera_psf_sigma_px: float = 1.0
    tracker_fov_deg: float = 20.0
    tracker_px: int = 1024
    tracker_aperture_mm: float = 25.0
    tracker_exposure_s: float = 0.2
    tracker_vmag_limit: float = 6.0
    tracker_from_camera_deg: float = 180.0
    sun_sensor_from_camera_deg: float = 122.0
    sun_sensor_half_angle_deg: float = 30.0
    sun_sensor_sigma_arcsec: float = 2.0
    sun_sensor_bias_arcsec: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.duration_hours) and 0.0 <= self.duration_hours <= 253.0):
            raise InputError(f"duration_hours must be in [0, 253] (0: the whole window), got {self.duration_hours}")
        if not (np.isfinite(self.lead_s) and 0.0 <= self.lead_s < 600.0):
            raise InputError(f"lead_s must be in [0, 600), got {self.lead_s}")
        for name in ("angle_step_s", "image_step_s"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= FUSION_STEP_S and value % FUSION_STEP_S == 0.0):
                raise InputError(f"{name} must be a positive multiple of the {FUSION_STEP_S:g} s fusion step, "
                                 f"got {value}")
        positive = ("sun_sigma_arcsec", "mars_sigma_arcsec", "camera_fov_deg", "camera_aperture_mm",
                    "camera_exposure_s", "camera_psf_sigma_px", "tracker_fov_deg", "tracker_aperture_mm",
                    "tracker_exposure_s", "sun_sensor_half_angle_deg", "sun_sensor_sigma_arcsec")
        for name in positive:
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise InputError(f"{name} must be a positive number, got {value}")
        for name in ("camera_px", "tracker_px"):
            if not 32 <= getattr(self, name) <= 8192:
                raise InputError(f"{name} must be 32 to 8192 pixels, got {getattr(self, name)}")
        if not (self.camera_fov_deg < 30.0 and self.tracker_fov_deg < 60.0):
            raise InputError(f"camera_fov_deg must be below 30 and tracker_fov_deg below 60 (a pinhole field), got "
                             f"{self.camera_fov_deg} and {self.tracker_fov_deg}")
        if len(self.sun_sensor_bias_arcsec) != 2 or not np.all(np.isfinite(self.sun_sensor_bias_arcsec)):
            raise InputError(f"sun_sensor_bias_arcsec must be two finite numbers [x, y], got "
                             f"{self.sun_sensor_bias_arcsec!r}")


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


@dataclass(frozen=True)
class Clocks:
    """The S4 clocks: ``t0`` (window start), fusion ``epochs`` (every 60 s, TDB s), the fusion epochs
    ``angle_epochs`` that receive an angle sample and the samples' own ``angle_times`` (``lead_s``
    earlier), and ``velocity_epochs`` (every 600 s)."""

    t0: float
    epochs: np.ndarray
    angle_epochs: np.ndarray
    angle_times: np.ndarray
    velocity_epochs: np.ndarray


def clocks(settings: Settings, angle_step_s: float) -> Clocks:
    """The S4 clocks of ``settings`` with one angle sample every ``angle_step_s``."""
    t0 = parse_epoch(START_UTC)
    t_end = parse_epoch(END_UTC) if settings.duration_hours == 0.0 else t0 + 3600.0 * settings.duration_hours
    epochs = t0 + FUSION_STEP_S * np.arange(1, int((t_end - t0) // FUSION_STEP_S) + 1)
    every = int(round(angle_step_s / FUSION_STEP_S))
    angle_epochs = epochs[every - 1::every]
    if angle_epochs.size < 20:
        raise InputError(f"duration_hours={settings.duration_hours} leaves {angle_epochs.size} angle samples (one "
                         f"every {angle_step_s:g} s); need 20")
    return Clocks(t0, epochs, angle_epochs, angle_epochs - settings.lead_s, epochs[9::10])


def true_states(t0: float, x0: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The truth (heliocentric ICRF ``[r km, v km/s]``, (M, 6)) at ``times`` (M,) TDB s, any order."""
    order = np.argsort(times, kind="stable")
    states = np.empty((times.size, 6))
    states[order] = propagate(approach_model(), t0, x0, times[order]).states
    return states


def sensor_model() -> tuple[ProbeMeasurementModel, dict]:
    """The filters' measurement model (Doppler of the Sun, Canopus and Vega with their catalog radial
    velocities) and the stars (name -> (HIP, ICRF unit vector))."""
    catalog = load_catalog()
    stars, star_rv = {}, {}
    for name, hip in STARS_HIP.items():
        row = np.flatnonzero(catalog.hip == hip)
        u = catalog.unit_vectors()[row[0]]
        stars[name] = (hip, u)
        star_rv[hip] = float(catalog.space_velocity_km_s(row)[0] @ u)
    return ProbeMeasurementModel("sun", light_time=False, aberration=False, star_radial_velocity_km_s=star_rv), stars


def velocity_sensor(clock: Clocks, truth_fusion: np.ndarray, rng: np.random.Generator) -> list[Measurement]:
    """The velocity sensor's Doppler records (module notes) at ``clock.velocity_epochs`` from the truth at
    the fusion epochs ``truth_fusion`` (M, 6), noise from ``rng``."""
    model, stars = sensor_model()
    on_velocity_clock = np.isin(clock.epochs, clock.velocity_epochs)
    return doppler_records(clock.velocity_epochs, truth_fusion[on_velocity_clock], model, stars, rng)


def assemble_case(clock: Clocks, x0: np.ndarray, truth_fusion: np.ndarray, positions: list[Measurement],
                  rng: np.random.Generator, facts: dict, dopplers: list[Measurement] | None = None) -> S4Case:
    """The S4 case from the angle records ``positions`` (eq. 1 records at ``clock.angle_times``) and the
    truth at the fusion epochs ``truth_fusion`` (M, 6): the Doppler records (``dopplers``, else made
    from ``rng`` by :func:`velocity_sensor`), the three record sets and the filters' start (module notes)."""
    eph = default_ephemeris()
    model, _ = sensor_model()
    if dopplers is None:
        dopplers = velocity_sensor(clock, truth_fusion, rng)
    cases = {"exact": positions + dopplers,
             "registered": register(positions, clock.angle_epochs, causal=True) + dopplers,
             "unregistered": hold_latest(positions, clock.angle_epochs) + dopplers}
    facts = {"state_at_start_km_km_s": x0.tolist(),
             "distance_to_mars_start_km": float(np.linalg.norm(x0[:3] - eph.state("mars", clock.t0, center="sun")[0])),
             "distance_to_mars_end_km": float(np.linalg.norm(truth_fusion[-1, :3]
                                                             - eph.state("mars", clock.epochs[-1], center="sun")[0])),
             "star_radial_velocity_km_s": {str(hip): rv for hip, rv in model.star_radial_velocity_km_s.items()},
             "position_pseudo_measurement_sigma_km": float(np.median([np.sqrt(np.trace(r.covariance) / 3)
                                                                      for r in positions])),
             "angle_samples": len(positions), **facts}
    P0 = np.diag([1000.0**2] * 3 + [0.1**2] * 3)
    x_start = x0 + np.array([1000.0, 1000.0, 1000.0, 0.1, 0.1, 0.1])
    return S4Case(clock.t0, clock.epochs, truth_fusion, cases, x_start, P0, model, facts)


def build_case(settings: Settings, seed: int) -> S4Case:
    """Simulate S4's sensors along the approach arc (module notes)."""
    rng = np.random.default_rng(seed)
    clock = clocks(settings, settings.angle_step_s)
    x0 = initial_state(clock.t0)
    truth = true_states(clock.t0, x0, np.concatenate([clock.angle_times, clock.epochs]))
    truth_angle, truth_fusion = truth[:clock.angle_times.size], truth[clock.angle_times.size:]
    positions = angle_records(clock.angle_times, truth_angle, rng, sun_sigma_rad=settings.sun_sigma_arcsec * ARCSEC_RAD,
                              mars_sigma_rad=settings.mars_sigma_arcsec * ARCSEC_RAD)
    return assemble_case(clock, x0, truth_fusion, positions, rng, {})


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
    log(f"S4: simulating the approach arc (lead {settings.lead_s:g} s, seed {seed})")
    return evaluate_case(build_case(settings, seed), log, {})


def evaluate_case(case: S4Case, log, extra: dict, arrays: dict | None = None) -> Evaluation:
    """:func:`evaluate`'s figures, arrays and trajectories of ``case``, ``extra`` merged into the
    summary and ``arrays`` into the arrays (image mode's own). Per run the NEES (position and
    velocity, 6 dof) at every fusion epoch is kept (``<case>_nees``) and its mean over the second
    half of the arc reported."""
    from ..consistency import nees
    from ..filters.estimates import Track

    filters, arrays, trajectories = {}, {"t_tdb_s": case.epochs, **(arrays or {})}, []
    half = case.epochs.size // 2
    for name, result in run_cases(case).items():
        log(f"federated UKF ({name}) done in {result.wall_s:.1f} s")
        sigma = result.sigma
        error = result.states - case.truth
        err, verr = error[-1, :3], error[-1, 3:]
        values = nees(result.states, result.covariances, case.truth)
        filters[name] = {"final_position_error_km": float(np.linalg.norm(err)),
                         "final_position_sigma_km": float(np.linalg.norm(sigma[-1, :3])),
                         "final_velocity_error_m_s": float(1e3 * np.linalg.norm(verr)),
                         "final_velocity_sigma_m_s": float(1e3 * np.linalg.norm(sigma[-1, 3:])),
                         "max_axis_error_in_sigma": float(np.max(np.abs(err) / sigma[-1, :3])),
                         "nees_mean_second_half": float(np.mean(values[half:])),
                         "refused": result.refused, "records": len(case.cases[name]), "wall_s": result.wall_s}
        arrays[f"{name}_state"], arrays[f"{name}_error"], arrays[f"{name}_sigma"] = result.states, error, sigma
        arrays[f"{name}_nees"] = values
        trajectories.append(EstimatedTrajectory(name, "sun", Track(case.epochs, result.states, result.covariances),
                                                f"S4 federated UKF, {CASE_DESCRIPTIONS[name]}"))
    summary = {"filters": filters, "facts": case.facts, **extra,
               "paper": {"claim": "without registration the federated filter diverges; with it, it converges"}}
    return Evaluation(summary, arrays, tuple(trajectories))


def evaluate_images(settings: Settings, seed: int, log, out, *, progress: bool = False, workers: int = 1) -> Evaluation:
    """Image mode (:func:`opnav.studies.s4_images.evaluate_images`)."""
    from .s4_images import evaluate_images as from_pixels

    return from_pixels(settings, seed, log, out, progress=progress, workers=workers)


def report_blocks(summary: dict, arrays) -> list:
    """The report's paragraphs, tables and figures (:func:`opnav.studies.report_s4.report_blocks`)."""
    from .report_s4 import report_blocks as blocks

    return blocks(summary, arrays)
