"""Numerical propagation of one or many states, with the state transition matrix.

Algorithm
---------
1. Stack K initial states (and, for ``stm=True``, K identity matrices) into one
   vector and integrate it with ``scipy.integrate.solve_ivp(method="DOP853")``:
   one call, one step sequence, a right-hand side vectorised over the K states.
2. The variational equations ``dPhi/dt = A(t) Phi`` use the force model's
   analytic partials, ``A = [[0, I], [da/dr, da/dv]]``.
3. Tolerances are per state. scipy's error norm is the RMS over all
   components, so a batch of K states (each carrying 6 or 42 components) would
   let one state's error hide among the others; ``rtol`` and ``atol`` are
   therefore divided by ``sqrt(n_components / 6)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

from ..ephemeris import Ephemeris, default_ephemeris
from ..errors import ConvergenceError, InputError
from .forces import ForceModel

#: Absolute tolerance of velocities per km of position tolerance, 1/s. Small enough that velocities
#: are held by ``rtol``: with 1e-3 /s a 7000 x 39700 km orbit drifted 13 m along track in 10
#: revolutions (energy error near apoapsis, where |v| is small); with 1e-6 /s, 0.4 m.
_VELOCITY_ATOL_PER_KM = 1e-6


@dataclass(frozen=True)
class Trajectory:
    """States (and optionally STMs) at requested epochs.

    Attributes
    ----------
    t_tdb_s : (M,) array
        TDB seconds past J2000.
    states : (M, 6) or (M, K, 6) array
        ``[r (km), v (km/s)]``, ICRF, relative to ``center``; (M, K, 6) when a
        batch of K initial states was propagated.
    stm : (M, 6, 6) or (M, K, 6, 6) array or None
        ``d state(t) / d state(t0)`` (``None`` unless requested).
    center : str
        Origin of the states.
    """

    t_tdb_s: np.ndarray
    states: np.ndarray
    stm: np.ndarray | None
    center: str


def _check_inputs(t0_tdb_s: float, state0: np.ndarray, t_tdb_s) -> tuple[float, np.ndarray, np.ndarray]:
    t0 = float(t0_tdb_s)
    if not np.isfinite(t0):
        raise InputError(f"t0_tdb_s must be finite, got {t0_tdb_s!r}")
    x0 = np.array(state0, dtype=float)
    if x0.shape[-1:] != (6,) or x0.ndim not in (1, 2) or x0.size == 0:
        raise InputError(f"state0 must have shape (6,) or (K, 6), got {x0.shape}")
    if not np.all(np.isfinite(x0)):
        raise InputError("state0 contains NaN or infinity")
    t = np.atleast_1d(np.array(t_tdb_s, dtype=float))
    if t.ndim != 1 or t.size == 0:
        raise InputError(f"t_tdb_s must be a scalar or a non-empty 1-D array, got shape {np.shape(t_tdb_s)}")
    if not np.all(np.isfinite(t)):
        raise InputError("t_tdb_s contains NaN or infinity")
    steps = np.diff(np.concatenate([[t0], t]))
    if not (np.all(steps >= 0.0) or np.all(steps <= 0.0)):
        raise InputError("t_tdb_s must be sorted in the direction of travel from t0 (all later or all earlier)")
    return t0, x0, t


def _first_step(model: ForceModel, t0: float, states0: np.ndarray, span_s: float, max_step_s: float) -> float | None:
    """A safe first step: 1% of the shortest dynamical time ``sqrt(|r| / |a|)`` of the batch, capped by the span.

    scipy's own guess is orders of magnitude smaller for these smooth problems, so a
    1-minute call would spend most of its evaluations growing the step (x10 per step).
    A too-long first step is merely rejected and shortened by the error control.
    """
    if span_s == 0.0:
        return None
    acc = model.acceleration(t0, states0[:, :3], states0[:, 3:])
    with np.errstate(divide="ignore"):
        scale_s = np.sqrt(np.linalg.norm(states0[:, :3], axis=1) / np.linalg.norm(acc, axis=1))
    return float(min(span_s, max_step_s, 0.01 * np.min(scale_s)))


def propagate(model: ForceModel, t0_tdb_s: float, state0: np.ndarray, t_tdb_s, *, stm: bool = False,
              rtol: float = 1e-11, atol_km: float = 1e-6, max_step_s: float = np.inf) -> Trajectory:
    """Propagate state(s) with ``model`` from ``t0_tdb_s`` to the epochs ``t_tdb_s``.

    Parameters
    ----------
    model : ForceModel
        Dynamics; states are relative to ``model.center``.
    t0_tdb_s : float
        Epoch of ``state0``, TDB seconds past J2000.
    state0 : (6,) or (K, 6) array
        ``[r (km), v (km/s)]``, ICRF, relative to ``model.center``. Not modified.
    t_tdb_s : float or (M,) array
        Output epochs, all after (or all before) ``t0_tdb_s``, sorted in that
        direction; ``t0_tdb_s`` itself may be included. A scalar gives M = 1.
    stm : bool
        Also integrate the variational equations and return the STM.
    rtol : float
        Relative tolerance per state.
    atol_km : float
        Absolute position tolerance, km (velocities: ``atol_km * 1e-6`` km/s;
        STM entries: ``rtol`` in their own units).
    max_step_s : float
        Largest step, s.

    Returns
    -------
    Trajectory

    Raises
    ------
    InputError
        For malformed or non-finite inputs or unsorted epochs.
    ConvergenceError
        If the integrator fails.
    """
    t0, x0, t_out = _check_inputs(t0_tdb_s, state0, t_tdb_s)
    if not (rtol > 0.0 and atol_km > 0.0):
        raise InputError(f"rtol and atol_km must be positive, got {rtol!r}, {atol_km!r}")
    if not max_step_s > 0.0:
        raise InputError(f"max_step_s must be positive, got {max_step_s!r}")
    batch = x0.ndim == 2
    states0 = np.atleast_2d(x0)
    k = len(states0)
    n_state = 6 * k
    per_state = 42 if stm else 6
    shrink = np.sqrt(per_state / 6.0 * k)

    atol_state = np.tile(np.r_[np.full(3, atol_km), np.full(3, atol_km * _VELOCITY_ATOL_PER_KM)], k)
    y0 = states0.ravel()
    if stm:
        y0 = np.concatenate([y0, np.tile(np.eye(6).ravel(), k)])
        atol = np.concatenate([atol_state, np.full(36 * k, rtol)])
    else:
        atol = atol_state

    def rhs(t: float, y: np.ndarray) -> np.ndarray:
        x = y[:n_state].reshape(k, 6)
        r, v = x[:, :3], x[:, 3:]
        acc = model.acceleration(t, r, v)
        dx = np.concatenate([v, acc], axis=1).ravel()
        if not stm:
            return dx
        da_dr, da_dv = model.partials(t, r, v)
        phi = y[n_state:].reshape(k, 6, 6)
        dphi = np.empty_like(phi)
        dphi[:, :3] = phi[:, 3:]
        dphi[:, 3:] = da_dr @ phi[:, :3] + da_dv @ phi[:, 3:]
        return np.concatenate([dx, dphi.ravel()])

    t_end = t_out[-1]
    # One evaluation at the far end makes an epoch outside the ephemeris fail before integrating.
    model.acceleration(t_end, states0[:, :3], states0[:, 3:])
    first_step = _first_step(model, t0, states0, abs(t_end - t0), max_step_s)
    if t_end == t0:
        ys = np.repeat(y0[:, None], len(t_out), axis=1)
    else:
        # an epoch asked for twice is integrated to once: solve_ivp wants t_eval strictly monotonic
        # (S4 with lead_s = 0 asks for each fusion epoch as an angle epoch too)
        distinct = np.r_[True, np.diff(t_out) != 0.0]
        solution = solve_ivp(rhs, (t0, t_end), y0, method="DOP853", t_eval=t_out[distinct], rtol=rtol / shrink,
                             atol=atol / shrink, max_step=max_step_s, first_step=first_step)
        if not solution.success:
            raise ConvergenceError(f"DOP853 failed propagating model {model.name!r} to {t_end:.3f} s: "
                                   f"{solution.message}")
        ys = solution.y[:, np.cumsum(distinct) - 1]
    m = len(t_out)
    states = ys[:n_state].T.reshape(m, k, 6)
    phis = ys[n_state:].T.reshape(m, k, 6, 6) if stm else None
    if not batch:
        states = states[:, 0]
        phis = phis[:, 0] if stm else None
    return Trajectory(t_out, states, phis, model.center)


def change_center(states: np.ndarray, t_tdb_s, from_center: str, to_center: str,
                  ephemeris: Ephemeris | None = None) -> np.ndarray:
    """Shift the origin of ICRF states from ``from_center`` to ``to_center``.

    Parameters
    ----------
    states : (6,), (M, 6) or (M, K, 6) array
        ``[r (km), v (km/s)]``, ICRF, relative to ``from_center``.
    t_tdb_s : float or (M,) array
        Epoch(s) of the states (one per leading row), TDB seconds past J2000.
    from_center, to_center : str
        Ephemeris body names.
    ephemeris : Ephemeris, optional
        Default :func:`opnav.ephemeris.default_ephemeris`.

    Returns
    -------
    Array of the shape of ``states``, relative to ``to_center``. The input is not modified.
    """
    ephemeris = ephemeris if ephemeris is not None else default_ephemeris()
    from_key = Ephemeris.check_body(from_center)
    to_key = Ephemeris.check_body(to_center)
    x = np.array(states, dtype=float)
    if x.shape[-1:] != (6,) or x.ndim > 3:
        raise InputError(f"states must have shape (6,), (M, 6) or (M, K, 6), got {x.shape}")
    t = np.asarray(t_tdb_s, dtype=float)
    if from_key == to_key:
        return x
    if x.ndim == 1 and t.ndim != 0:
        raise InputError("a single state (6,) needs a scalar epoch")
    if x.ndim > 1 and t.ndim == 1 and len(t) != len(x):
        raise InputError(f"{len(t)} epochs for {len(x)} rows of states")
    r, v = ephemeris.state(from_key, t, center=to_key)
    shift = np.concatenate([r, v], axis=-1)
    if x.ndim == 3:
        shift = shift[..., None, :] if shift.ndim == 2 else shift
    return x + shift


def states_at(model: ForceModel, t0_tdb_s: float, state0: np.ndarray, t_tdb_s, *, center: str | None = None,
              output_center: str | None = None, ephemeris: Ephemeris | None = None) -> np.ndarray:
    """One state propagated with ``model`` to epochs in any order, before and after its own, with a change of origin.

    The state is moved from ``center`` to the model's centre, propagated backward to the
    epochs before ``t0_tdb_s`` and forward to the others (:func:`propagate`, two calls at most),
    and moved to ``output_center`` (:func:`change_center`).

    Parameters
    ----------
    model : ForceModel
        Dynamics.
    t0_tdb_s : float
        Epoch of ``state0``, TDB seconds past J2000.
    state0 : (6,) array
        ``[r (km), v (km/s)]``, ICRF, relative to ``center``.
    t_tdb_s : (M,) array
        Output epochs, TDB seconds past J2000, in any order; ``t0_tdb_s`` may be among them.
    center : str, optional
        Origin of ``state0`` (an ephemeris body); default ``model.center``.
    output_center : str, optional
        Origin of the output; default ``center``.
    ephemeris : Ephemeris, optional
        For the changes of origin; default :func:`opnav.ephemeris.default_ephemeris`.

    Returns
    -------
    (M, 6) array
        ``[r (km), v (km/s)]``, ICRF, relative to ``output_center``, row ``i`` at ``t_tdb_s[i]``.

    Raises
    ------
    InputError
        For malformed or non-finite inputs or an unknown body.
    ConvergenceError
        If the integrator fails.
    """
    center = model.center if center is None else center
    output_center = center if output_center is None else output_center
    t0 = float(t0_tdb_s)
    epochs = np.atleast_1d(np.array(t_tdb_s, dtype=float))
    if epochs.ndim != 1:
        raise InputError(f"t_tdb_s must be a scalar or a 1-D array, got shape {np.shape(t_tdb_s)}")
    state_model = change_center(state0, t0, center, model.center, ephemeris)
    order = np.argsort(epochs)
    before, after = order[epochs[order] < t0][::-1], order[epochs[order] >= t0]
    states = np.empty((len(epochs), 6))
    for indices in (before, after):
        if len(indices):
            states[indices] = propagate(model, t0, state_model, epochs[indices]).states
    return change_center(states, epochs, model.center, output_center, ephemeris)
