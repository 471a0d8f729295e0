"""S2: Mars capture, starlight angles, model switching at the sphere of influence (docs/studies.md#s2-mars-capture; Tables 1-3).

The capture arc is :func:`opnav.studies.trajectories.mars_capture_trajectory` (MAVEN's launch
and arrival dates, a Lambert arc seeding a 380 km periapsis hyperbola at 75 deg,
integrated with S2's model 1 outside Mars' sphere of influence and model 2 inside;
its module docstring states every step). Two evaluations:

- **observability** (Tables 1-2): :func:`opnav.studies.s2_observability.s2_observability`
  for model 1 (MPD, MP, MD, PD) and model 2 (MPS, MP2, MS, PS) on an hourly grid;
- **switching filter** (Table 3 for the paper's best sets): one EKF run over the arc,
  model 1 with MPD until the SOI crossing, then model 2 with MPS
  (:func:`opnav.studies.s2_observability.s2_switching_run`): NEES and the error after
  convergence (second half of each phase).

S2 gives neither the angle noise nor the initial error; they are settings.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..consistency import nees
from ..errors import InputError
from .evaluation import EstimatedTrajectory, Evaluation

#: S2 Table 3: position error mean (km) / variance (km^2), velocity mean (km/s) / variance.
TABLE3 = {"MPD": (5.0314, 6.7987, 0.0093, 0.0054), "MPS": (14.5518, 16.2534, 0.0045, 0.0023)}


#: The study's kind for the runner (:mod:`opnav.studies.base`): evaluating (its own ``evaluate``); ``--mode images``
#: measures the angles on rendered frames (:func:`evaluate_images`, :mod:`opnav.studies.s2_images`).
KIND = "evaluating"
IMAGE_MODE = True
#: Settings only image mode reads.
IMAGE_SETTINGS: tuple[str, ...] = (
    "image_step_s", "nav_fov_deg", "nav_px", "nav_aperture_mm", "nav_vmag_limit", "mars_exposure_s",
    "moon_exposure_s", "tracker_fov_deg", "tracker_px", "tracker_vmag_limit", "tracker_boresight_body",
    "sun_sensor_boresight_body", "sun_sensor_half_angle_deg", "sun_sensor_sigma_arcsec")


@dataclass(frozen=True)
class Settings:
    """S2 run settings (``[settings]`` of the run file; each one a ``--set`` key).

    Attributes
    ----------
    sigma_arcsec : float
        1-sigma of each starlight angle, arcsec (S2 gives none).
    sigma_position_km, sigma_velocity_km_s : float
        Initial 1-sigma per axis of the switching filter (S2 gives none).
    arc_days : float
        Phase 1: the last ``arc_days`` before the SOI crossing, days.
    stop_before_periapsis_h : float
        Phase 2 ends this long before periapsis, h.
    step_s : float
        Measurement grid of the switching run, s.
    observability : bool
        Also compute Tables 1-2 (hourly grid; about a minute).
    image_step_s : float
        Image mode: frames every this many seconds, a multiple of ``step_s``.
    nav_fov_deg, nav_px, nav_aperture_mm, nav_vmag_limit : float, int, float, float
        Image mode: the navigation camera's field across ``nav_px`` square pixels, its aperture and
        the faintest catalog star its moon frames identify.
    mars_exposure_s, moon_exposure_s : float
        Image mode: the navigation camera's exposure for Mars (short: the disk unsaturated, no star
        shows) and for a moon (stars enough for the frame's own attitude).
    tracker_fov_deg, tracker_px, tracker_vmag_limit : float, int, float
        Image mode: the star tracker's field, pixels and faintest catalog star.
    tracker_boresight_body, sun_sensor_boresight_body : (3,) float
        Image mode: the star tracker's and sun sensor's boresights in the body frame (body +z is the
        navigation camera's boresight, on Mars; the Sun is on the body's +x side of the x-z plane).
        The tracker's default, -z, puts its weak roll axis on the camera's boresight.
    sun_sensor_half_angle_deg, sun_sensor_sigma_arcsec : float
        Image mode: the sun sensor's field half-angle and noise per axis (:mod:`opnav.sim.sun_sensor`).
    """

    sigma_arcsec: float = 1.0
    sigma_position_km: float = 100.0
    sigma_velocity_km_s: float = 1e-3
    arc_days: float = 2.0
    stop_before_periapsis_h: float = 2.0
    step_s: float = 600.0
    observability: bool = True
    image_step_s: float = 3600.0
    nav_fov_deg: float = 10.0
    nav_px: int = 1024
    nav_aperture_mm: float = 30.0
    nav_vmag_limit: float = 8.0
    mars_exposure_s: float = 1e-4
    moon_exposure_s: float = 0.5
    tracker_fov_deg: float = 20.0
    tracker_px: int = 1024
    tracker_vmag_limit: float = 6.5
    tracker_boresight_body: tuple[float, float, float] = (0.0, 0.0, -1.0)
    sun_sensor_boresight_body: tuple[float, float, float] = (1.0, 0.0, 0.0)
    sun_sensor_half_angle_deg: float = 60.0
    sun_sensor_sigma_arcsec: float = 30.0

    def __post_init__(self) -> None:
        for name in ("sigma_arcsec", "sigma_position_km", "sigma_velocity_km_s", "arc_days", "step_s"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise InputError(f"{name} must be positive, got {value!r}")
        if not 0.0 <= self.stop_before_periapsis_h < 48.0:
            raise InputError(f"stop_before_periapsis_h must be in [0, 48), got {self.stop_before_periapsis_h}")
        if not 60.0 <= self.step_s <= 3600.0:
            raise InputError(f"step_s must be in [60, 3600], got {self.step_s}")
        for name in ("image_step_s", "nav_fov_deg", "nav_aperture_mm", "mars_exposure_s", "moon_exposure_s",
                     "tracker_fov_deg", "sun_sensor_half_angle_deg", "sun_sensor_sigma_arcsec"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise InputError(f"{name} must be positive, got {value!r}")
        ratio = self.image_step_s / self.step_s
        if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
            raise InputError(f"image_step_s must be a whole multiple of step_s ({self.step_s:g} s), "
                             f"got {self.image_step_s!r}")
        if not (self.nav_fov_deg < 60.0 and self.tracker_fov_deg < 60.0):
            raise InputError(f"nav_fov_deg and tracker_fov_deg must be below 60 deg, got {self.nav_fov_deg!r} "
                             f"and {self.tracker_fov_deg!r}")
        for name in ("nav_px", "tracker_px"):
            if not 64 <= getattr(self, name) <= 8192:
                raise InputError(f"{name} must be in [64, 8192] pixels, got {getattr(self, name)!r}")
        for name in ("tracker_boresight_body", "sun_sensor_boresight_body"):
            value = np.asarray(getattr(self, name), float)
            if value.shape != (3,) or not np.all(np.isfinite(value)) or not np.linalg.norm(value) > 0.0:
                raise InputError(f"{name} must be a non-zero body-frame vector [x, y, z], got {getattr(self, name)!r}")


def _phase_figures(run, inside: bool) -> dict:
    idx = np.flatnonzero(run.inside_soi == inside)
    half = idx[idx.size // 2:]
    err, cov = run.errors[half], run.covariances[half]
    values = np.array([e @ np.linalg.solve(c, e) for e, c in zip(err, cov)])
    pos = np.linalg.norm(err[:, :3], axis=1)
    vel = np.linalg.norm(err[:, 3:], axis=1)
    return {"nees_mean": float(values.mean()), "position_error_mean_km": float(pos.mean()),
            "position_error_var_km2": float(pos.var()), "velocity_error_mean_km_s": float(vel.mean()),
            "velocity_error_var": float(vel.var()), "sigma_position_km_at_end": float(np.sqrt(np.trace(cov[-1, :3, :3])))}


def evaluate(settings: Settings, seed: int, log) -> Evaluation:
    """Observability tables and one switching-filter run (module notes): the summary's figures, the
    arrays the report plots and the switching EKF's estimates (one trajectory per phase and origin)."""
    from ..filters.estimates import Track
    from ..studies.s2_observability import S2_PAPER_TABLES, s2_observability, s2_switching_run
    from ..studies.trajectories import mars_capture_trajectory

    out: dict = {"paper": {"table1_2": {str(k): v for k, v in S2_PAPER_TABLES.items()}, "table3": TABLE3}}
    arrays: dict[str, np.ndarray] = {}
    if settings.observability:
        log("observability: Tables 1-2 on an hourly grid")
        hourly = mars_capture_trajectory(step_s=3600.0)
        out["observability"] = {}
        for model in (1, 2):
            study = s2_observability(model, trajectory=hourly, sigma_arcsec=settings.sigma_arcsec)
            out["observability"][f"model{model}"] = {
                rep.name: {"rank": int(rep.rank), "max_singular_value": float(rep.singular_values[0]),
                           "eta": float(rep.eta), "crb_sigma_position_km": [float(v) for v in rep.crb_sigma[:3]],
                           "condition_number": float(rep.condition_number)} for rep in study.reports}
            arrays[f"model{model}_t_tdb_s"] = study.t_tdb_s
            arrays[f"model{model}_sets"] = np.array([rep.name for rep in study.reports])
            arrays[f"model{model}_singular_values"] = np.array([rep.singular_values for rep in study.reports])
            arrays[f"model{model}_crb_position_km"] = np.array(study.crb_position_km)
    log(f"switching EKF: MPD -> MPS at the SOI (seed {seed})")
    trajectory = mars_capture_trajectory(step_s=settings.step_s)
    begin = time.perf_counter()
    run = s2_switching_run(seed, trajectory=trajectory, sigma_arcsec=settings.sigma_arcsec,
                           arc_days=settings.arc_days, stop_before_periapsis_s=3600.0 * settings.stop_before_periapsis_h,
                           sigma_position_km=settings.sigma_position_km,
                           sigma_velocity_km_s=settings.sigma_velocity_km_s)
    wall = time.perf_counter() - begin
    out["filters"] = {"ekf-switching": {
        "accepted_fraction": run.accepted_fraction, "wall_s": wall,
        "MPD (model 1)": _phase_figures(run, False), "MPS (model 2)": _phase_figures(run, True),
        "switch_tdb_s": float(run.switch.t_tdb_s) if run.switch else None}}
    out["facts"] = {"soi_crossing_tdb_s": float(trajectory.t_soi_tdb_s),
                    "periapsis_tdb_s": float(trajectory.t_periapsis_tdb_s),
                    "v_inf_km_s": float(np.linalg.norm(trajectory.v_inf_km_s))}
    arrays.update({"switching_t_tdb_s": run.t_tdb_s, "switching_state": run.states, "switching_error": run.errors,
                   "switching_sigma": np.sqrt(np.diagonal(run.covariances, axis1=1, axis2=2)),
                   "switching_nees": nees(run.states, run.covariances, run.states - run.errors),
                   "switching_inside_soi": run.inside_soi})
    trajectories = tuple(
        EstimatedTrajectory(name, center, Track(run.t_tdb_s[keep], run.states[keep], run.covariances[keep]),
                            f"S2 switching EKF, {label}")
        for name, center, label, keep in (
            ("ekf-switching-model1", "sun", "phase 1: model 1 (heliocentric), MPD, until the SOI crossing",
             ~run.inside_soi),
            ("ekf-switching-model2", "mars", "phase 2: model 2 (Mars-centred), MPS, after the SOI crossing",
             run.inside_soi))
        if np.any(keep))
    return Evaluation(out, arrays, trajectories)


def evaluate_images(settings: Settings, seed: int, log, out, *, progress: bool = False, workers: int = 1) -> Evaluation:
    """S2 from pixels (:mod:`opnav.studies.s2_images`): the starlight angles measured on rendered frames,
    the switching EKF on them, and beside it the measurement-mode twin: the same epochs and stars with
    each body's achieved angle noise drawn about the truth, from the same initial estimate."""
    from pathlib import Path

    from ..constants import ARCSEC_RAD
    from ..filters.estimates import Track
    from ..errors import OpnavError
    from .s2_images import angle_errors, measure_arc, sample_frame, twin_records, wrong_body_count
    from .s2_observability import s2_switching_filter
    from .trajectories import mars_capture_trajectory

    trajectory = mars_capture_trajectory(step_s=settings.step_s)
    log(f"S2 from pixels: star tracker, navigation camera and sun sensor every {settings.image_step_s:g} s "
        f"(seed {seed})")
    measured = measure_arc(settings, seed, trajectory, Path(out), progress=progress, workers=workers)
    if not measured.angles:
        raise InputError("S2 from pixels: no frame gave a starlight angle (see the skipped frames)")
    t0 = min(a.t_tdb_s for a in measured.angles)
    P0 = np.diag([settings.sigma_position_km**2] * 3 + [settings.sigma_velocity_km_s**2] * 3)
    x0 = trajectory.state_at(t0, "sun") + np.sqrt(np.diag(P0)) * np.random.default_rng([seed, 70]).standard_normal(6)
    log("switching EKF on the measured angles, then on the measurement-mode twin at the achieved noise")
    begin = time.perf_counter()
    pixels = s2_switching_filter(list(measured.angles), trajectory=trajectory, x0_sun=x0, P0=P0, t0_tdb_s=t0)
    runs = {"ekf-switching from pixels": (pixels, time.perf_counter() - begin)}
    # the achieved noise is that of the angles the filter took: its gate refuses a gross error (a moon
    # fitted on Mars' glare), which the twin's white noise would otherwise carry as an arcminute sigma
    taken = [a for a, ok in zip(measured.angles, pixels.accepted) if ok]
    errors = angle_errors(taken, trajectory)
    refused = [a for a, ok in zip(measured.angles, pixels.accepted) if not ok]
    sigma = {name: figures["rms_arcsec"] * ARCSEC_RAD for name, figures in errors.items()}
    twin = twin_records(taken, trajectory, sigma, np.random.default_rng([seed, 71]))
    begin = time.perf_counter()
    runs["ekf-switching measurement mode at the achieved noise"] = (
        s2_switching_filter(twin, trajectory=trajectory, x0_sun=x0, P0=P0, t0_tdb_s=t0), time.perf_counter() - begin)
    out_summary: dict = {"paper": {"table3": TABLE3}, "filters": {}}
    arrays: dict[str, np.ndarray] = {}
    for (name, (run, wall)), prefix in zip(runs.items(), ("switching", "twin")):
        out_summary["filters"][name] = {
            "accepted_fraction": run.accepted_fraction, "wall_s": wall,
            "MPD (model 1)": _phase_figures(run, False), "MPS (model 2)": _phase_figures(run, True),
            "switch_tdb_s": float(run.switch.t_tdb_s) if run.switch else None}
        arrays.update({f"{prefix}_t_tdb_s": run.t_tdb_s, f"{prefix}_state": run.states, f"{prefix}_error": run.errors,
                       f"{prefix}_sigma": np.sqrt(np.diagonal(run.covariances, axis1=1, axis2=2)),
                       f"{prefix}_nees": nees(run.states, run.covariances, run.states - run.errors),
                       f"{prefix}_inside_soi": run.inside_soi})
    loops = measured.loops
    out_summary["images"] = {
        "achieved_angle_noise": errors,
        "refused_by_the_filter": angle_errors(refused, trajectory) if refused else {},
        "wrong_body": wrong_body_count(measured.directions, trajectory),
        "angle_pair_correlation_max": float(max(measured.correlations)),
        "frames": {name: {"rendered": result.frames_full, "skipped": len(result.skipped),
                          "missed": len(result.missed), "records": sum(r.kind == "radec" for r in result.records)}
                   for name, result in loops.items()},
        "missed": {f"{m.frame_id} {m.target}": "hidden by Mars' glare" if m.hidden_by_primary else "not found"
                   for result in loops.values() for m in result.missed},
        "skipped": {**{k: v for result in loops.values() for k, v in result.skipped.items()}, **measured.sun_skipped},
        "sun_sensor_records": sum(d.target == "sun" for d in measured.directions),
        "tracker_stars_used": loops["mars"].stars_used, "tracker_stars_misidentified": loops["mars"].stars_misidentified}
    out_summary["facts"] = {"soi_crossing_tdb_s": float(trajectory.t_soi_tdb_s),
                            "periapsis_tdb_s": float(trajectory.t_periapsis_tdb_s),
                            "v_inf_km_s": float(np.linalg.norm(trajectory.v_inf_km_s))}
    arrays["angle_t_tdb_s"] = np.array([a.t_tdb_s for a in measured.angles])
    arrays["angle_target"] = np.array([a.target for a in measured.angles])
    for body, path in (("mars", "mars_00000_1.fits"), ("phobos", "phobos_00000.fits")):
        record = next((d for d in measured.directions if d.frame_id == f"{body}_00000" and d.target == body), None)
        try:
            sample = sample_frame(Path(out) / "frames" / path, body, record)
        except OpnavError as exc:  # a frame the first run wrote, removed since: the page shows none
            log(f"no sample frame of {body}: {exc}")
            continue
        arrays.update({f"sample_{body}_{key}": np.asarray(value) for key, value in sample.items()})
    run = runs["ekf-switching from pixels"][0]
    trajectories = tuple(
        EstimatedTrajectory(name, center, Track(run.t_tdb_s[keep], run.states[keep], run.covariances[keep]),
                            f"S2 switching EKF from pixels, {label}")
        for name, center, label, keep in (
            ("ekf-switching-model1", "sun", "phase 1: model 1 (heliocentric), MPD", ~run.inside_soi),
            ("ekf-switching-model2", "mars", "phase 2: model 2 (Mars-centred), MPS", run.inside_soi))
        if np.any(keep))
    return Evaluation(out_summary, arrays, trajectories)


def report_blocks(summary: dict, arrays) -> list:
    """The report's paragraphs, tables and figures (:func:`opnav.studies.report_s2.report_blocks`)."""
    from .report_s2 import report_blocks as blocks

    return blocks(summary, arrays)
