"""Observability along a trajectory: starlight-angle measurement sets and the S2 study.

Uses the linear-algebra core of :mod:`opnav.observability` (PWCS stripped
observability matrix, Fisher information, condition number) with the force
model partials of :mod:`opnav.dynamics` and the measurement Jacobians of
:mod:`opnav.measurements`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..catalog import load_catalog
from ..constants import ARCSEC_RAD, DAY_S
from ..dynamics import ForceModel, capture_model_1, capture_model_2, propagate
from ..errors import InputError
from ..filters.base import MeasurementModel
from ..measurements import ProbeMeasurementModel
from ..observability import ObservabilityReport, analyse, information_inverse_diagonal
from ..records import Measurement
from .trajectories import BodyVisibility, CaptureTrajectory, body_visibility, mars_capture_trajectory


# --------------------------------------------------------------------------- along a trajectory


@dataclass(frozen=True)
class SetRows:
    """One measurement set's information along an arc, as the observability figures take it.

    Attributes
    ----------
    name : str
        The set's name.
    epochs : (K,) int array
        Indices into the arc's epochs at which a body of the set is visible (one row block each).
    segments : tuple of (F (6, 6), H (m, 6))
        PWCS segments at those epochs (:func:`opnav.observability.analyse`).
    mapped : tuple of (m, 6) arrays
        ``H_i Phi(t_i, t_0)``: the rows mapped to the arc's first epoch.
    covariances : tuple of (m, m) arrays
        Their noise covariances, rad^2.
    """

    name: str
    epochs: np.ndarray
    segments: tuple
    mapped: tuple
    covariances: tuple


def starlight_angle_rows(
    sets: Mapping[str, Sequence[str]],
    *,
    force_model: ForceModel,
    measurement_model: MeasurementModel,
    t_tdb_s: np.ndarray,
    state0: np.ndarray,
    star_units_icrf: np.ndarray,
    sigma_rad: float,
    visible: Mapping[str, np.ndarray] | None = None,
) -> list[SetRows]:
    """The PWCS segments and mapped Jacobians of several starlight-angle sets along one arc
    (parameters and method: :func:`starlight_angle_observability`), one :class:`SetRows` per set."""
    t = np.asarray(t_tdb_s, dtype=float)
    if t.ndim != 1 or t.size < 2 or np.any(np.diff(t) <= 0.0):
        raise InputError("t_tdb_s must hold at least two increasing epochs")
    stars = np.atleast_2d(np.asarray(star_units_icrf, dtype=float))
    if stars.ndim != 2 or stars.shape[1] != 3 or stars.shape[0] == 0:
        raise InputError(f"star_units_icrf must have shape (S, 3), got {np.shape(star_units_icrf)}")
    if not (np.isfinite(sigma_rad) and sigma_rad > 0.0):
        raise InputError(f"sigma_rad must be positive, got {sigma_rad!r}")
    if not sets:
        raise InputError("need at least one measurement set")
    visible = dict(visible or {})
    for target, mask in visible.items():
        if np.shape(mask) != t.shape:
            raise InputError(f"visible[{target!r}] must have shape {t.shape}, got {np.shape(mask)}")

    arc = propagate(force_model, t[0], state0, t, stm=True)
    targets = sorted({body for bodies in sets.values() for body in bodies})
    cov = np.array([[sigma_rad**2]])
    rows = {body: np.empty((t.size, stars.shape[0], 6)) for body in targets}
    for i, (epoch, x) in enumerate(zip(t, arc.states)):
        for body in targets:
            for j, star in enumerate(stars):
                # A planned measurement: the Jacobian needs geometry only, so the value is NaN, not a fake reading.
                record = Measurement(epoch, "starlight_angle", [np.nan], cov, target=body, star_unit_icrf=star)
                rows[body][i, j] = measurement_model.jacobian(record, x)[0, :6]
    steps = np.diff(t)
    steps = np.append(steps, steps[-1])
    transitions = []
    for epoch, x, dt in zip(t, arc.states, steps):
        da_dr, da_dv = force_model.partials(epoch, x[:3], x[3:])
        a_matrix = np.block([[np.zeros((3, 3)), np.eye(3)], [da_dr, da_dv]])
        transitions.append(np.eye(6) + dt * a_matrix)

    out = []
    for name, bodies in sets.items():
        segments, mapped, covariances, used = [], [], [], []
        for i in range(t.size):
            seen = [body for body in bodies if visible.get(body, np.ones(t.size, bool))[i]]
            if not seen:
                continue
            H = np.vstack([rows[body][i] for body in seen])
            segments.append((transitions[i], H))
            mapped.append(H @ arc.stm[i])
            covariances.append(sigma_rad**2 * np.eye(H.shape[0]))
            used.append(i)
        if not segments:
            raise InputError(f"measurement set {name!r} has no visible target at any epoch")
        out.append(SetRows(name, np.array(used), tuple(segments), tuple(mapped), tuple(covariances)))
    return out


def starlight_angle_observability(
    sets: Mapping[str, Sequence[str]],
    *,
    force_model: ForceModel,
    measurement_model: MeasurementModel,
    t_tdb_s: np.ndarray,
    state0: np.ndarray,
    star_units_icrf: np.ndarray,
    sigma_rad: float,
    visible: Mapping[str, np.ndarray] | None = None,
    column_scale: np.ndarray | None = None,
    rank_rtol: float = 1e-9,
) -> list[ObservabilityReport]:
    """All three figures for several starlight-angle measurement sets along one arc.

    Parameters
    ----------
    sets : mapping of str to sequence of str
        Set name -> target bodies (e.g. ``{"MPD": ("mars", "phobos", "deimos")}``). Every
        target is measured against every star at every epoch.
    force_model : ForceModel
        Dynamics of the arc; the state is relative to ``force_model.center``.
    measurement_model : MeasurementModel
        Gives ``jacobian(record, x)`` for ``starlight_angle`` records in the same state
        (e.g. :class:`opnav.measurements.ProbeMeasurementModel` with the same centre).
    t_tdb_s : (M,) array
        Measurement epochs, increasing, TDB s past J2000; the first is the reference
        epoch of the Fisher information (the CRB is that of ``state0``).
    state0 : (6,) array
        ``[r (km), v (km/s)]`` at ``t_tdb_s[0]``, ICRF, relative to ``force_model.center``.
    star_units_icrf : (S, 3) array
        Catalog unit vectors of the stars, ICRF.
    sigma_rad : float
        1-sigma noise of one starlight angle, rad (independent angles).
    visible : mapping of str to (M,) bool arrays, optional
        Per target, the epochs at which it can be measured (e.g. not behind Mars);
        targets missing from the mapping are always visible.
    column_scale, rank_rtol
        Passed to :func:`analyse`.

    Returns
    -------
    list of ObservabilityReport, in the order of ``sets``.

    Notes
    -----
    The arc is propagated once with the STM, ``Phi_i = Phi(t_i, t_0)``. At epoch i,
    ``H_i`` stacks the visible targets' rows ``d theta / d x`` (one per star) and
    ``A_i = [[0, I], [da/dr, da/dv]]`` comes from ``force_model.partials``; the PWCS
    segment is ``(F_i = I + dT_i A_i, H_i)`` with ``dT_i`` the step to the next epoch
    (the last epoch reuses the previous step), and the Fisher rows are ``H_i Phi_i``.
    Epochs where no target of a set is visible contribute nothing to that set.
    """
    rows = starlight_angle_rows(sets, force_model=force_model, measurement_model=measurement_model, t_tdb_s=t_tdb_s,
                                state0=state0, star_units_icrf=star_units_icrf, sigma_rad=sigma_rad, visible=visible)
    return [analyse(r.name, list(r.segments), list(r.mapped), list(r.covariances), column_scale=column_scale,
                    rank_rtol=rank_rtol) for r in rows]


def position_crb_over_arc(rows: SetRows, epochs: int, *, column_scale: np.ndarray | None = None) -> np.ndarray:
    """Position Cramer-Rao bound at the arc's first epoch from the measurements up to each epoch.

    Parameters
    ----------
    rows : SetRows
        One set's information along the arc (:func:`starlight_angle_rows`).
    epochs : int
        Epochs of the arc (M).
    column_scale : (6,) array, optional
        State units of the inversion (:func:`opnav.observability.analyse`); the bound does not
        depend on them, the conditioning of the inversion does.

    Returns
    -------
    (M,) array
        RSS of the three position 1-sigmas, km; inf until the set's rows make the position observable.

    Notes
    -----
    The information of the first k epochs is the sum of their rows' ``H^T R^-1 H``, so the bound can
    only fall as epochs are added: the curve shows how fast each set pins the state down.
    """
    scale = np.ones(6) if column_scale is None else np.asarray(column_scale, dtype=float)
    scaled = [np.atleast_2d(H) * scale[None, :] for H in rows.mapped]
    out = np.full(int(epochs), np.inf)
    for k, epoch in enumerate(rows.epochs):
        variance = information_inverse_diagonal(scaled[:k + 1], list(rows.covariances[:k + 1]))[:3] * scale[:3] ** 2
        out[epoch:] = np.sqrt(np.sum(variance))
    return out


# --------------------------------------------------------------------------- S2 study

#: S2 measurement sets (docs/studies.md#s2-mars-capture): model 1 outside Mars' sphere of influence, model 2 inside.
S2_SETS: dict[int, dict[str, tuple[str, ...]]] = {
    1: {"MPD": ("mars", "phobos", "deimos"), "MP": ("mars", "phobos"), "MD": ("mars", "deimos"),
        "PD": ("phobos", "deimos")},
    2: {"MPS": ("mars", "phobos", "sun"), "MP2": ("mars", "phobos"), "MS": ("mars", "sun"), "PS": ("phobos", "sun")},
}
#: S2 Tables 1-2 as printed: rank, max singular value, eta, kappa (units and scaling unstated).
S2_PAPER_TABLES: dict[int, dict[str, tuple]] = {
    1: {"MPD": (6, 0.024417, 8.30767e-16, 1.25989e14), "MP": (5, 0.019817, 3.2509e-15, 1.0528e17),
        "MD": (5, 0.019979, 1.5983e-15, 1.6543e17), "PD": (5, 0.020012, 6.4148e-15, 2.0611e17)},
    2: {"MPS": (5, 0.014036, 4.3622e-21, 9.8418e15), "MP2": (5, 0.014036, 4.8726e-12, 7.5473e16),
        "MS": (4, 0.001024, 1.3652e-15, 3.4336e17), "PS": (4, 0.014036, 7.3571e-18, 1.7294e17)},
}
#: The three navigation stars (Hipparcos numbers): Achernar, Altair, Antares. Chosen on the S2 arc for
#: 53-144 deg separations from Mars and the Sun and evenly spread position angles around both.
S2_STARS_HIP = (7588, 97649, 80763)
#: State units for the SVD, eta and kappa: 1 km for position, 1 m/s for velocity.
S2_COLUMN_SCALE = np.array([1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])


@dataclass(frozen=True)
class S2Study:
    """Observability tables of one S2 model along the capture arc.

    Attributes
    ----------
    model : int
        1 (heliocentric, outside the SOI) or 2 (Mars-centred, inside).
    reports : tuple of ObservabilityReport
        One per measurement set, in the order of :data:`S2_SETS`.
    t_tdb_s : (M,) array
        Measurement epochs (the first is the CRB reference epoch), TDB s past J2000.
    visibility : tuple of BodyVisibility
        Per target of the model's sets, over ``t_tdb_s``.
    sigma_arcsec : float
        1-sigma of one starlight angle, arcsec.
    star_hip : tuple of int
        Hipparcos numbers of the stars.
    crb_position_km : tuple of (M,) arrays
        Per report, the position CRB at ``t_tdb_s[0]`` from the measurements up to each epoch
        (:func:`position_crb_over_arc`), km.
    rank_rtol : float
        The numerical rank's tolerance: singular values above ``rank_rtol`` times the largest count
        (state in :data:`S2_COLUMN_SCALE` units, km and m/s).
    """

    model: int
    reports: tuple[ObservabilityReport, ...]
    t_tdb_s: np.ndarray
    visibility: tuple[BodyVisibility, ...]
    sigma_arcsec: float
    star_hip: tuple[int, ...]
    crb_position_km: tuple[np.ndarray, ...] = ()
    rank_rtol: float = 1e-9

    def rank_summary(self) -> dict:
        """Per set, the numerical rank with its tolerance and the singular-value spectrum beside the
        paper's rank (:func:`rank_summary`), and the tolerances that would give every paper rank of
        the model at once (:func:`paper_rank_tolerance`)."""
        paper = S2_PAPER_TABLES[self.model]
        sets = {rep.name: rank_summary(rep, self.rank_rtol, paper[rep.name][0] if rep.name in paper else None)
                for rep in self.reports}
        return {"sets": sets, "paper_rank_rtol": paper_rank_tolerance(list(sets.values()))}


def rank_summary(report: ObservabilityReport, rank_rtol: float, paper_rank: int | None) -> dict:
    """The numerical rank of one set with the tolerance used, the spectrum, and the paper's rank beside.

    Parameters
    ----------
    report : ObservabilityReport
        One set's figures (singular values in the report's column units).
    rank_rtol : float
        The tolerance the rank used: singular values above ``rank_rtol`` times the largest count.
    paper_rank : int or None
        The paper's rank of the set (:data:`S2_PAPER_TABLES`).

    Returns
    -------
    dict
        ``rank``, ``rank_rtol``, ``singular_values`` (descending, in the column units ``column_units``),
        ``relative_singular_values`` (each over the largest), ``paper_rank`` and
        ``paper_rank_rtol``: the interval ``[low, high)`` of tolerances that give the paper's rank
        (``low`` the first left out relative value, ``high`` the last kept; ``None`` without one).

    Notes
    -----
    A rank is a count of singular values above a threshold, and the threshold is a choice: the
    spectrum and the interval let a reader see what tolerance a printed rank implies (the paper
    states none), and whether one tolerance gives all of a table's ranks.
    """
    sigma = np.asarray(report.singular_values, dtype=float)
    relative = sigma / sigma[0] if sigma.size and sigma[0] > 0.0 else np.zeros_like(sigma)
    interval = None
    if paper_rank is not None and 0 < paper_rank <= sigma.size:
        interval = [float(relative[paper_rank]) if paper_rank < sigma.size else 0.0, float(relative[paper_rank - 1])]
    units = ["km" if scale == 1.0 else f"{scale:g} km" for scale in report.column_scale[:3]] + \
            ["m/s" if scale == 1e-3 else f"{scale:g} km/s" for scale in report.column_scale[3:]]
    return {"rank": int(report.rank), "rank_rtol": float(rank_rtol), "singular_values": [float(v) for v in sigma],
            "relative_singular_values": [float(v) for v in relative], "column_units": units,
            "paper_rank": paper_rank, "paper_rank_rtol": interval}


def paper_rank_tolerance(summaries: Sequence[dict]) -> list[float] | None:
    """The tolerances ``[low, high)`` that give every set of ``summaries`` (:func:`rank_summary`) its
    paper rank at once; None when no single tolerance does (or a set has no paper rank)."""
    intervals = [s["paper_rank_rtol"] for s in summaries]
    if not intervals or any(i is None for i in intervals):
        return None
    low, high = max(i[0] for i in intervals), min(i[1] for i in intervals)
    return [low, high] if low < high else None


def s2_arc_epochs(trajectory: CaptureTrajectory, model: int, *, arc_days: float = 2.0,
                  stop_before_periapsis_s: float = 7200.0) -> np.ndarray:
    """Grid epochs of the S2 arc of ``model``: the last ``arc_days`` before the SOI crossing (model 1),
    or from the crossing to ``stop_before_periapsis_s`` before periapsis (model 2)."""
    t = trajectory.t_tdb_s
    if model == 1:
        held = (trajectory.t_soi_tdb_s - t[0]) / DAY_S
        if not (np.isfinite(arc_days) and 0.0 < arc_days <= held + 1e-9):
            raise InputError(f"arc_days must be in (0, {held:.6g}]: the trajectory holds {held:.6g} days before "
                             f"the SOI crossing, got {arc_days!r}")
        keep = (t >= trajectory.t_soi_tdb_s - arc_days * DAY_S) & (t <= trajectory.t_soi_tdb_s)
    elif model == 2:
        held = trajectory.t_periapsis_tdb_s - trajectory.t_soi_tdb_s
        if not (np.isfinite(stop_before_periapsis_s) and 0.0 <= stop_before_periapsis_s < held):
            raise InputError(f"stop_before_periapsis_s must be in [0, {held:.6g}) s (SOI crossing to periapsis), "
                             f"got {stop_before_periapsis_s!r}")
        keep = (t >= trajectory.t_soi_tdb_s) & (t <= trajectory.t_periapsis_tdb_s - stop_before_periapsis_s)
    else:
        raise InputError(f"S2 model must be 1 or 2, got {model!r}")
    if np.count_nonzero(keep) < 2:
        raise InputError(f"the model-{model} arc holds fewer than two trajectory epochs; use a finer step_s")
    return t[keep]


def s2_observability(model: int, *, trajectory: CaptureTrajectory | None = None, sigma_arcsec: float = 1.0,
                     arc_days: float = 2.0, stop_before_periapsis_s: float = 7200.0,
                     drop_hidden: bool = True, rank_rtol: float = 1e-9) -> S2Study:
    """S2 Tables 1 (model 1) or 2 (model 2) for our capture arc.

    Parameters
    ----------
    model : int
        1 or 2.
    trajectory : CaptureTrajectory, optional
        Default :func:`opnav.studies.trajectories.mars_capture_trajectory` with a 1 h grid.
    sigma_arcsec : float
        1-sigma of each starlight angle, arcsec (the paper gives none; default 1").
    arc_days, stop_before_periapsis_s
        Arc limits, see :func:`s2_arc_epochs`.
    drop_hidden : bool
        Leave out measurements of bodies occulted by Mars or eclipsed in its shadow.
    rank_rtol : float
        See :func:`analyse`.

    Notes
    -----
    Every body of a set is measured against each of the three :data:`S2_STARS_HIP`
    stars at every grid epoch of the arc, with light time and aberration (the
    :class:`opnav.measurements.ProbeMeasurementModel` defaults). Model 1 uses the
    heliocentric state and ``capture_model_1``; model 2 the Mars-centred state and
    ``capture_model_2``. Figures use :data:`S2_COLUMN_SCALE` (km, m/s).
    """
    if not (np.isfinite(sigma_arcsec) and sigma_arcsec > 0.0):
        raise InputError(f"sigma_arcsec must be positive, got {sigma_arcsec!r}")
    if trajectory is None:
        trajectory = mars_capture_trajectory()
    t = s2_arc_epochs(trajectory, model, arc_days=arc_days, stop_before_periapsis_s=stop_before_periapsis_s)
    rows = np.isin(trajectory.t_tdb_s, t)
    center, force_model = ("sun", capture_model_1()) if model == 1 else ("mars", capture_model_2())
    states = trajectory.states_sun if model == 1 else trajectory.states_mars
    sets = S2_SETS[model]
    targets = sorted({body for bodies in sets.values() for body in bodies})
    visibility = tuple(body_visibility(t, trajectory.states_mars[rows, :3], body) for body in targets)
    catalog = load_catalog()
    index = [int(np.flatnonzero(catalog.hip == hip)[0]) for hip in S2_STARS_HIP]
    set_rows = starlight_angle_rows(
        sets, force_model=force_model, measurement_model=ProbeMeasurementModel(center),
        t_tdb_s=t, state0=states[rows][0], star_units_icrf=catalog.unit_vectors()[index],
        sigma_rad=sigma_arcsec * ARCSEC_RAD,
        visible={v.target: v.visible for v in visibility} if drop_hidden else None)
    reports = tuple(analyse(r.name, list(r.segments), list(r.mapped), list(r.covariances),
                            column_scale=S2_COLUMN_SCALE, rank_rtol=rank_rtol) for r in set_rows)
    crb = tuple(position_crb_over_arc(r, t.size, column_scale=S2_COLUMN_SCALE) for r in set_rows)
    return S2Study(model, reports, t, visibility, float(sigma_arcsec), S2_STARS_HIP, crb, float(rank_rtol))


# --------------------------------------------------------------------------- S2 switching run

@dataclass(frozen=True)
class S2SwitchingRun:
    """One EKF run over the S2 capture arc that switches model and measurement set at the SOI.

    Attributes
    ----------
    t_tdb_s : (M,) array
        Epochs of the estimates (after each epoch's records), TDB s past J2000.
    states : (M, 6) array
        The estimates ``[r km, v km/s]``, ICRF, about the Sun in phase 1 and about Mars in phase 2
        (``inside_soi``).
    errors : (M, 6) array
        Estimate minus truth, km and km/s (each phase in its own origin).
    covariances : (M, 6, 6) array
        The estimates' covariances, km^2, km^2/s, km^2/s^2.
    inside_soi : (M,) bool
        Epochs of phase 2 (Mars-centred model, MPS).
    accepted_fraction : float
        Share of the records the filters accepted.
    switch : Switch
        The hand-over at the SOI (estimate before and after the change of origin).
    accepted : (R,) bool array
        Per record, in the order given to :func:`s2_switching_filter`, whether the filter took it
        (False: refused, e.g. by the chi-square gate).
    """

    t_tdb_s: np.ndarray
    states: np.ndarray
    errors: np.ndarray
    covariances: np.ndarray
    inside_soi: np.ndarray
    accepted_fraction: float
    switch: object
    accepted: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))


def s2_switching_run(seed: int, *, trajectory: CaptureTrajectory | None = None, sets: tuple[str, str] = ("MPD", "MPS"),
                     sigma_arcsec: float = 1.0, arc_days: float = 2.0, stop_before_periapsis_s: float = 7200.0,
                     sigma_position_km: float = 100.0, sigma_velocity_km_s: float = 1e-3) -> S2SwitchingRun:
    """Simulate S2's starlight angles along the capture arc and run the switching EKF (model 1 -> 2 at the SOI).

    Parameters
    ----------
    seed : int
        Generator of the initial error and the measurement noise.
    trajectory : CaptureTrajectory, optional
        Default :func:`opnav.studies.trajectories.mars_capture_trajectory` with a 10-minute grid.
    sets : (str, str)
        Measurement sets of model 1 and model 2 (:data:`S2_SETS`), default the paper's best, MPD -> MPS.
    sigma_arcsec : float
        1-sigma of each starlight angle (S2 gives none; 1").
    arc_days, stop_before_periapsis_s
        Phase 1 covers the last ``arc_days`` before the SOI crossing, phase 2 the crossing to
        ``stop_before_periapsis_s`` before periapsis (:func:`s2_arc_epochs`).
    sigma_position_km, sigma_velocity_km_s : float
        Initial 1-sigma per axis (S2 gives none); the initial error is drawn from it.

    Notes
    -----
    Each body of the phase's set is measured against the three :data:`S2_STARS_HIP` stars at
    every grid epoch where it is visible (not occulted by Mars nor in its shadow); truth
    measurements come from the exact ephemeris and model, the filters run on the fast path
    (compiled propagation and light time over the Chebyshev cache) with a token process
    noise (1e-18 km^2/s^3; the truth and filter dynamics are the same models).
    """
    if trajectory is None:
        trajectory = mars_capture_trajectory(step_s=600.0)
    rng = np.random.default_rng(seed)
    sigma = sigma_arcsec * ARCSEC_RAD
    catalog = load_catalog()
    stars = catalog.unit_vectors()[[int(np.flatnonzero(catalog.hip == hip)[0]) for hip in S2_STARS_HIP]]
    records = []
    phase_epochs = []
    for model, set_name in zip((1, 2), sets):
        t = s2_arc_epochs(trajectory, model, arc_days=arc_days, stop_before_periapsis_s=stop_before_periapsis_s)
        if model == 2:
            t = t[t > trajectory.t_soi_tdb_s]  # the crossing epoch itself closes phase 1
        phase_epochs.append(t)
        rows = np.isin(trajectory.t_tdb_s, t)
        center = "sun" if model == 1 else "mars"
        states = (trajectory.states_sun if model == 1 else trajectory.states_mars)[rows]
        truth_model = ProbeMeasurementModel(center)
        for body in S2_SETS[model][set_name]:
            visible = body_visibility(t, trajectory.states_mars[rows, :3], body).visible
            for star in stars:
                for epoch, state in zip(t[visible], states[visible]):
                    template = Measurement(epoch, "starlight_angle", [0.0], [[sigma**2]], target=body,
                                           star_unit_icrf=star, sensor=f"phase{model}")
                    value = truth_model.predict(template, state) + sigma * rng.standard_normal(1)
                    records.append(Measurement(epoch, "starlight_angle", value, [[sigma**2]], target=body,
                                               star_unit_icrf=star, sensor=f"phase{model}"))
    t0 = phase_epochs[0][0]
    truth0 = trajectory.state_at(t0, "sun")
    P0 = np.diag([sigma_position_km**2] * 3 + [sigma_velocity_km_s**2] * 3)
    x0 = truth0 + np.sqrt(np.diag(P0)) * rng.standard_normal(6)
    return s2_switching_filter(records, trajectory=trajectory, x0_sun=x0, P0=P0, t0_tdb_s=t0)


def s2_switching_filter(records: Sequence[Measurement], *, trajectory: CaptureTrajectory, x0_sun: np.ndarray,
                        P0: np.ndarray, t0_tdb_s: float) -> S2SwitchingRun:
    """The switching EKF (model 1 about the Sun, model 2 about Mars from the SOI crossing) on ``records``.

    Parameters
    ----------
    records : sequence of Measurement
        Starlight angles (or any record kind :class:`opnav.measurements.ProbeMeasurementModel` takes)
        at epochs of ``trajectory``'s grid: simulated (:func:`s2_switching_run`) or measured from
        frames (:mod:`opnav.studies.s2_images`).
    trajectory : CaptureTrajectory
        The truth the errors are taken against.
    x0_sun : (6,) array
        Initial estimate ``[r km, v km/s]`` at ``t0_tdb_s``, ICRF, relative to the Sun.
    P0 : (6, 6) array
        Its covariance, km^2, km^2/s, km^2/s^2 (also the model-2 phase's placeholder until the hand-over).
    t0_tdb_s : float
        Epoch of the initial estimate, TDB s past J2000.

    Returns
    -------
    S2SwitchingRun
        One estimate per epoch that has records (after them).
    """
    from ..ephemeris.cache import default_cached_ephemeris
    from ..filters.base import Estimate
    from ..filters.ekf import ExtendedKalmanFilter, force_model_propagator
    from ..filters.noise import WhiteAcceleration
    from ..filters.switching import Phase, SwitchingFilter

    if not records:
        raise InputError("the switching filter needs at least one record")
    cache = default_cached_ephemeris()
    noise = WhiteAcceleration(1e-18)
    phases = []
    for start, center, force_model in ((-np.inf, "sun", capture_model_1()),
                                       (trajectory.t_soi_tdb_s, "mars", capture_model_2())):
        estimate = Estimate(t0_tdb_s, x0_sun, P0) if center == "sun" else Estimate(t0_tdb_s, np.zeros(6), P0)
        phases.append(Phase(start, center, ExtendedKalmanFilter(
            estimate, propagator=force_model_propagator(force_model),
            model=ProbeMeasurementModel(center, ephemeris=cache), process_noise=noise)))
    switching = SwitchingFilter(phases)
    order = sorted(range(len(records)), key=lambda i: records[i].t_tdb_s)
    states, errors, covariances = [], [], []
    taken = np.zeros(len(records), bool)
    by_epoch = {}
    for i in order:
        taken[i] = switching.update(records[i]).accepted
        by_epoch[records[i].t_tdb_s] = (switching.estimate, switching.center)
    kept = sorted(by_epoch)
    for t in kept:
        estimate, center = by_epoch[t]
        truth = trajectory.state_at(t, center)
        states.append(estimate.x[:6])
        errors.append(estimate.x[:6] - truth)
        covariances.append(estimate.P[:6, :6])
    kept = np.array(kept)
    return S2SwitchingRun(kept, np.array(states), np.array(errors), np.array(covariances),
                          kept > trajectory.t_soi_tdb_s,
                          float(taken.mean()), switching.switches[0] if switching.switches else None, taken)
