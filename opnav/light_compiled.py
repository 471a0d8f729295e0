"""Compiled twin of :mod:`opnav.light` for filters: apparent directions of K states in one call.

A filter asks for the apparent direction of the same target from K states
(Monte Carlo runs, sigma points, particles) tens of thousands of times an arc.
The numpy path (:mod:`opnav.light` through
:class:`opnav.measurements.ProbeMeasurementModel`) spends ~0.2 ms a call in
per-operation overhead; this numba kernel does the same arithmetic in a few
microseconds, reading the centre and target states from the Chebyshev tables
of an :class:`~opnav.ephemeris.cache.EphemerisCache`
(:class:`~opnav.ephemeris.tables.ArcTables`).

For each state, exactly as ``ProbeMeasurementModel._direction`` does with :mod:`opnav.light`:

1. probe SSB state = centre's SSB state + ``x``;
2. light time by the fixed-point iteration of :func:`opnav.light.light_time_vector`
   (same tolerance; each state starts from the previous state's light time), then ``drho/dr = -(I - a rho_hat^T / (1 + rho_hat . a))``,
   ``a = v_T / c``;
3. unit vector and its Jacobian ``(I - u u^T) / |rho|``;
4. relativistic aberration (:func:`opnav.light.aberrate`) and its two
   Jacobians (:func:`opnav.light.aberration_jacobian`,
   :func:`opnav.light.aberration_velocity_jacobian`).

``tests/test_light_compiled.py`` checks every output against the numpy path.
Vectors: ICRF, km, km/s; epochs TDB seconds past J2000.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import get_num_threads, prange

from .compiled import kernel
from .constants import C_KM_S
from .ephemeris.tables import chebyshev_states
from .light import LIGHT_TIME_TOLERANCE_KM

_C = C_KM_S
#: Fewest states per parallel chunk. Measured on 2 cores: 13 states take 6 us serial and 8 us in two
#: chunks (the thread pool's cost), 260 states 61 us serial and 36 us in two chunks.
_CHUNK_STATES = 32


@kernel(inline=True)
def _matmul3(A, B, out):
    """out (3, 3) = A B without an allocation (numba's ``@`` goes through BLAS and the heap)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@kernel(inline=True)
def _aberration(u, v, want, u_app, J_u, J_v, work):
    """Apparent direction (3,) of unit ``u`` for observer velocity ``v`` (km/s) and, if ``want``,
    d u_app/d u (3, 3) and d u_app/d v (3, 3, per km/s); ``work`` (3, 3, 3) is scratch space."""
    b0, b1, b2_ = v[0] / _C, v[1] / _C, v[2] / _C
    g = math.sqrt(1.0 - (b0 * b0 + b1 * b1 + b2_ * b2_))
    udb = u[0] * b0 + u[1] * b1 + u[2] * b2_
    den = 1.0 + udb
    b = work[2, 0]
    num = work[2, 1]
    b[0], b[1], b[2] = b0, b1, b2_
    for c in range(3):
        num[c] = u[c] * g + b[c] + udb * b[c] / (1.0 + g)
    w_norm = math.sqrt(num[0] * num[0] + num[1] * num[1] + num[2] * num[2]) / den
    for c in range(3):
        u_app[c] = num[c] / den / w_norm
    if not want:
        return
    proj = work[0]
    d_w = work[1]
    for i in range(3):
        for j in range(3):
            proj[i, j] = ((1.0 if i == j else 0.0) - u_app[i] * u_app[j]) / w_norm
    # d/du: d_num = g I + b b^T / (1 + g)
    for i in range(3):
        for j in range(3):
            d_num = (g if i == j else 0.0) + b[i] * b[j] / (1.0 + g)
            d_w[i, j] = d_num / den - num[i] * b[j] / (den * den)
    _matmul3(proj, d_w, J_u)
    # d/dbeta: d_num = u d_g^T + I + (b u^T + udb I)/(1+g) - udb b d_g^T/(1+g)^2, d_g = -b/g
    for i in range(3):
        for j in range(3):
            d_g = -b[j] / g
            eye = 1.0 if i == j else 0.0
            d_num = u[i] * d_g + eye + (b[i] * u[j] + udb * eye) / (1.0 + g) - udb * b[i] * d_g / ((1.0 + g) ** 2)
            d_w[i, j] = (d_num / den - num[i] * u[j] / (den * den)) / _C
    _matmul3(proj, d_w, J_v)


@kernel(parallel=True)
def directions(chunks, t, X, center_ssb, coef, first, seg, count, light_time, aberration, want, tolerance_km,
               max_iterations, rho_out, u_out, du_dr_out, du_dv_out, drho_out, v_obs_out):
    """Apparent directions to a target from K states; outputs as ``ProbeMeasurementModel._direction``.

    ``coef`` etc. hold two tables: 0 = target relative to the SSB, 1 = the states' centre relative
    to the SSB (ignored when ``center_ssb``). Returns 0 on success, 1 if an epoch left the tables,
    2 if the light-time iteration did not converge. The states are split into ``chunks`` contiguous
    chunks run in parallel (the light-time warm start runs along each chunk).
    """
    K = X.shape[0]
    status = np.zeros(chunks, dtype=np.int64)
    for c in prange(chunks):
        status[c] = directions_range(K * c // chunks, K * (c + 1) // chunks, t, X, center_ssb, coef, first, seg,
                                     count, light_time, aberration, want, tolerance_km, max_iterations, rho_out,
                                     u_out, du_dr_out, du_dv_out, drho_out, v_obs_out)
    return status.max()


@kernel
def directions_range(k_first, k_end, t, X, center_ssb, coef, first, seg, count, light_time, aberration, want,
                     tolerance_km, max_iterations, rho_out, u_out, du_dr_out, du_dv_out, drho_out, v_obs_out):
    """:func:`directions` for states ``k_first`` to ``k_end - 1``, serially (and callable from other
    kernels: the compiled filter steps of :mod:`opnav.filters.compiled` use it)."""
    states = np.empty((coef.shape[0], 6))
    if not chebyshev_states(t, coef, first, seg, count, 6, states):
        return 1
    r_c = np.zeros(3)
    v_c = np.zeros(3)
    if not center_ssb:
        r_c[:] = states[1, :3]
        v_c[:] = states[1, 3:]
    r_target_now = states[0, :3].copy()
    work = np.empty((3, 3, 3))
    r_obs = np.empty(3)
    v_obs = np.empty(3)
    rho = np.empty(3)
    v_t = np.empty(3)
    u = np.empty(3)
    u_app = np.empty(3)
    J_u = np.zeros((3, 3))
    J_v = np.zeros((3, 3))
    d_rho = np.empty((3, 3))
    d_u = np.empty((3, 3))
    # neighbouring states (sigma points, runs) have nearly the same light time: starting each
    # iteration from the previous state's saves one or two ephemeris evaluations per state
    tau_start = 0.0
    target = (coef[:1], first[:1], seg[:1], count[:1])
    for k in range(k_first, k_end):
        for c in range(3):
            r_obs[c] = r_c[c] + X[k, c]
            v_obs[c] = v_c[c] + X[k, 3 + c]
        if light_time:
            tau = tau_start
            converged = False
            for _ in range(max_iterations):
                if not chebyshev_states(t - tau, target[0], target[1], target[2], target[3], 3, states):
                    return 1
                for c in range(3):
                    rho[c] = states[0, c] - r_obs[c]
                new_tau = math.sqrt(rho[0] ** 2 + rho[1] ** 2 + rho[2] ** 2) / _C
                done = abs(new_tau - tau) * _C < tolerance_km
                tau = new_tau
                if done:
                    converged = True
                    break
            if not converged:
                return 2
            tau_start = tau
            # the target's velocity enters the Jacobian only
            if not chebyshev_states(t - tau, target[0], target[1], target[2], target[3], 6 if want else 3, states):
                return 1
            for c in range(3):
                rho[c] = states[0, c] - r_obs[c]
            if want:
                for c in range(3):
                    v_t[c] = states[0, 3 + c]
                dist = math.sqrt(rho[0] ** 2 + rho[1] ** 2 + rho[2] ** 2)
                denom = 1.0 + (rho[0] * v_t[0] + rho[1] * v_t[1] + rho[2] * v_t[2]) / (dist * _C)
                for i in range(3):
                    for j in range(3):
                        d_rho[i, j] = -((1.0 if i == j else 0.0) - (v_t[i] / _C) * (rho[j] / dist) / denom)
        else:
            for c in range(3):
                rho[c] = r_target_now[c] - r_obs[c]
            for i in range(3):
                for j in range(3):
                    d_rho[i, j] = -1.0 if i == j else 0.0
        dist = math.sqrt(rho[0] ** 2 + rho[1] ** 2 + rho[2] ** 2)
        for c in range(3):
            u[c] = rho[c] / dist
        if aberration:
            _aberration(u, v_obs, want, u_app, J_u, J_v, work)
        else:
            u_app[:] = u
        for c in range(3):
            rho_out[k, c] = rho[c]
            u_out[k, c] = u_app[c]
            v_obs_out[k, c] = v_obs[c]
        if want:
            for i in range(3):
                for j in range(3):
                    d_u[i, j] = ((1.0 if i == j else 0.0) - u[i] * u[j]) / dist
            drho_out[k] = d_rho
            if aberration:
                _matmul3(d_u, d_rho, work[0])
                _matmul3(J_u, work[0], du_dr_out[k])
                du_dv_out[k] = J_v
            else:
                _matmul3(d_u, d_rho, du_dr_out[k])
                du_dv_out[k] = 0.0
    return 0


def compiled_directions(t_tdb_s: float, x: np.ndarray, tables, *, center_ssb: bool, light_time: bool,
                        aberration: bool, want_jacobian: bool):
    """Run :func:`directions` for K states ``x`` (K, >=6) at ``t_tdb_s``.

    ``tables`` is ``(coef, first, seg, count)`` of an :class:`~opnav.ephemeris.tables.ArcTables`
    whose entry 0 is the target and entry 1 the centre, both relative to the SSB.

    Returns
    -------
    status : int
        0 ok, 1 outside the tables, 2 light time did not converge.
    rho (K, 3) km, u_app (K, 3), du_app/dr (K, 3, 3) 1/km, du_app/dv (K, 3, 3) 1/(km/s),
    drho/dr (K, 3, 3), probe SSB velocity (K, 3) km/s (Jacobians zero-filled unless asked).
    """
    k = x.shape[0]
    rho, u_app, v_obs = np.empty((k, 3)), np.empty((k, 3)), np.empty((k, 3))
    if want_jacobian:
        du_dr, du_dv, d_rho = np.empty((k, 3, 3)), np.empty((k, 3, 3)), np.empty((k, 3, 3))
    else:
        du_dr = du_dv = d_rho = np.empty((1, 3, 3))
    # one chunk per thread, at least _CHUNK_STATES states each; one chunk runs without the thread pool
    chunks = max(1, min(k // _CHUNK_STATES, get_num_threads()))
    kernel = directions_range if chunks == 1 else functools.partial(directions, chunks)
    args = (float(t_tdb_s), np.ascontiguousarray(x[:, :6]), center_ssb, *tables, light_time, aberration,
            want_jacobian, LIGHT_TIME_TOLERANCE_KM, 10, rho, u_app, du_dr, du_dv, d_rho, v_obs)
    status = kernel(0, k, *args) if chunks == 1 else kernel(*args)
    return status, rho, u_app, du_dr, du_dv, d_rho, v_obs
