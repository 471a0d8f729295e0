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


#: The study's kind for the runner (:mod:`opnav.studies.base`): evaluating (its own ``evaluate``); ``--mode images`` is refused.
KIND = "evaluating"
IMAGE_MODE = False
#: Settings only image mode reads: none.
IMAGE_SETTINGS: tuple[str, ...] = ()


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
    """

    sigma_arcsec: float = 1.0
    sigma_position_km: float = 100.0
    sigma_velocity_km_s: float = 1e-3
    arc_days: float = 2.0
    stop_before_periapsis_h: float = 2.0
    step_s: float = 600.0
    observability: bool = True

    def __post_init__(self) -> None:
        for name in ("sigma_arcsec", "sigma_position_km", "sigma_velocity_km_s", "arc_days", "step_s"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise InputError(f"{name} must be positive, got {value!r}")
        if not 0.0 <= self.stop_before_periapsis_h < 48.0:
            raise InputError(f"stop_before_periapsis_h must be in [0, 48), got {self.stop_before_periapsis_h}")
        if not 60.0 <= self.step_s <= 3600.0:
            raise InputError(f"step_s must be in [60, 3600], got {self.step_s}")


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


def report_blocks(summary: dict, arrays) -> list:
    """The report's paragraphs, tables and figures (:func:`opnav.studies.report_s2.report_blocks`)."""
    from .report_s2 import report_blocks as blocks

    return blocks(summary, arrays)
