"""Fast propagation for filters: fixed-step Runge-Kutta of K states and their STMs, compiled.

DOP853 with error control (:func:`opnav.dynamics.propagate`) stays the truth
generator and the ``exact`` option. A filter, though, propagates thousands of
short intervals (60 s in S1, 10 s in S3) and pays scipy's per-call set-up and
a Python right-hand side on every one: 2-4 ms a step. This module compiles a
:class:`~opnav.dynamics.forces.ForceModel` into arrays and integrates with
numba-compiled kernels instead.

Algorithm
---------
1. **Compile the model.** Each term of the model becomes numbers: the central
   GM; for each third body its GM and a table index; the solar radiation
   pressure scale, the Sun's table and the occulting spheres; the geopotential's
   Cunningham tables (:attr:`opnav.dynamics.geopotential.Geopotential.evaluation_tables`).
   Unknown term types are refused (use the exact propagator for them).
2. **Per-arc ephemeris.** The positions of the bodies relative to the model's
   centre come from dense Chebyshev tables of an
   :class:`~opnav.ephemeris.cache.EphemerisCache` over the arc, extended
   automatically when a request leaves it, and are evaluated inside the kernel
   (Chebyshev recurrence) once per stage epoch for all K states.
3. **Integrate.** The 8th-order, 12-stage Runge-Kutta formula of
   Dormand & Prince (the one inside DOP853; Hairer, Norsett & Wanner 1993,
   sec. II.10) with a fixed step, applied to ``[r, v]`` and the variational
   equations ``dPhi/dt = [[0, I], [da/dr, 0]] Phi`` of each state. Every
   supported term has ``da/dv = 0``. States without STMs (a UKF's sigma points) go
   through one loop with the states in columns, each operation done for all of them
   in a row so that it compiles to vector instructions: the same operations in the
   same order as one state at a time, so the same bits (13 sigma points of S1 cost
   ~1.3x one state instead of ~7x).
4. **Choose the step.** Each interval is cut into ``ceil(|dt| / h_max)`` equal
   steps with ``h_max = step_fraction * T``, ``T`` the shortest dynamical
   time ``sqrt(d^3 / GM)`` of any state to the central body or a third body at
   the interval start. The local error of an 8th-order step scales as
   ``(h/T)^9``: with the default 0.05 it is ~1e-12 of the orbit per step, and
   S1's 60-s steps (``T`` ~ 1e7 s) or S3's 10-s steps (``T`` ~ 1.4e4 s) take one
   step per interval. ``tests/test_fast_propagation.py`` checks the result
   against DOP853 at rtol 1e-12.

Compiled callers (the single-run filter steps of :mod:`opnav.filters.compiled`) propagate with
:func:`propagate_states`, which chooses the steps and does the arithmetic of
:meth:`FastPropagator.step` inside their own kernel.

Measured choice (``benchmarks/filters.py`` prints it): this path costs tens of
microseconds per 60-s step with the STM, below a Taylor integrator (heyoka,
0.13-0.15 ms measured on this machine) and without an LLVM compile of every
force model at start-up; numba's compiled kernels are cached on disk.

Vectors: states ``[r (km), v (km/s)]`` ICRF relative to ``model.center``;
epochs TDB seconds past J2000.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import prange
from scipy.integrate._ivp import dop853_coefficients as _dop853

from ..compiled import kernel
from ..constants import RADIUS_KM
from ..ephemeris import Ephemeris
from ..ephemeris.cache import EphemerisCache
from ..ephemeris.tables import ArcTables, chebyshev_states
from ..errors import InputError
from .forces import CentralGravity, ForceModel, SolarRadiationPressure, ThirdBody
from .geopotential import LEGENDRE_ROW_A, LEGENDRE_ROW_B, DOUBLE_FACTORIAL, LEGENDRE_SIZE, Geopotential
from .propagate import Trajectory

#: The 8th-order DOP853 tableau (stages 1-12; scipy keeps the dense-output stages after them).
_STAGES = _dop853.N_STAGES
_A = np.ascontiguousarray(_dop853.A[:_STAGES, :_STAGES], dtype=float)
_B = np.ascontiguousarray(_dop853.B, dtype=float)
_C = np.ascontiguousarray(_dop853.C[:_STAGES], dtype=float)
_ROW_A_TABLE = np.zeros((LEGENDRE_SIZE, LEGENDRE_SIZE))
_ROW_B_TABLE = np.zeros((LEGENDRE_SIZE, LEGENDRE_SIZE))
for _n in range(LEGENDRE_SIZE):
    _ROW_A_TABLE[_n, :_n] = LEGENDRE_ROW_A[_n]
    _ROW_B_TABLE[_n, :_n] = LEGENDRE_ROW_B[_n]
_DF = DOUBLE_FACTORIAL[:LEGENDRE_SIZE].copy()
_SUN_RADIUS_KM = RADIUS_KM["sun"]


# ----------------------------------------------------------------------------- kernels
@kernel(inline=True)
def _add_point_mass(d0, d1, d2, gm, sign, a, dadr, want):
    """a += sign*gm*d/|d|^3 (d = body - probe) and its r-gradient (d depends on r with sign -1)."""
    dist2 = d0 * d0 + d1 * d1 + d2 * d2
    dist = math.sqrt(dist2)
    inv3 = gm / (dist2 * dist)
    a[0] += sign * inv3 * d0
    a[1] += sign * inv3 * d1
    a[2] += sign * inv3 * d2
    if want:
        inv5 = 3.0 * inv3 / dist2
        d = (d0, d1, d2)
        for i in range(3):
            for j in range(3):
                dadr[i, j] += sign * (inv5 * d[i] * d[j] - (inv3 if i == j else 0.0))


@kernel(inline=True)
def _shadow(s, rb, radius):
    """Visible fraction of the solar disk past a sphere (conical model, forces.shadow_factor)."""
    dist_s = math.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
    dist_b = math.sqrt(rb[0] * rb[0] + rb[1] * rb[1] + rb[2] * rb[2])
    a = math.asin(min(1.0, max(0.0, _SUN_RADIUS_KM / dist_s)))
    b = math.asin(min(1.0, max(0.0, radius / dist_b)))
    cos_c = (s[0] * rb[0] + s[1] * rb[1] + s[2] * rb[2]) / (dist_s * dist_b)
    c = math.acos(min(1.0, max(-1.0, cos_c)))
    if c <= b - a:
        return 0.0
    if c <= a - b:
        return 1.0 - (b / a) ** 2
    if c < a + b:
        x = (c * c + a * a - b * b) / (2.0 * c)
        y = math.sqrt(max(a * a - x * x, 0.0))
        area = (a * a * math.acos(min(1.0, max(-1.0, x / a))) + b * b * math.acos(min(1.0, max(-1.0, (c - x) / b)))
                - c * y)
        return 1.0 - area / (math.pi * a * a)
    return 1.0


@kernel(inline=True)
def _add_geopotential(t, r, gm_r2, gm_r3, radius, ut1_offset, grad, hess, row_a, row_b, dfact, a, dadr, want):
    """Geopotential acceleration and Hessian (geopotential.Geopotential, ERA-only Earth rotation)."""
    days = (t - ut1_offset) / 86_400.0
    whole = math.floor(days)
    turns = 0.7790572732640 + 0.00273781191135448 * days + (days - whole)
    era = 2.0 * math.pi * (turns - math.floor(turns))
    cr, sr = math.cos(era), math.sin(era)
    x = cr * r[0] + sr * r[1]
    y = -sr * r[0] + cr * r[1]
    z = r[2]
    size = row_a.shape[0]
    r2 = x * x + y * y + z * z
    rho = radius * radius / r2
    z0 = z * radius / r2
    Z = np.zeros((size, size), dtype=np.complex128)
    xy0 = complex(x, y) * (radius / r2)
    power = complex(1.0, 0.0)
    base = radius / math.sqrt(r2)
    for m in range(size):
        Z[m, m] = dfact[m] * power * base
        power *= xy0
    Z[1, 0] = z0 * Z[0, 0]
    for n in range(2, size):
        for m in range(n):
            Z[n, m] = row_a[n, m] * z0 * Z[n - 1, m] - row_b[n, m] * rho * Z[n - 2, m]
    half = size * size
    g = np.zeros(3)
    h = np.zeros(9)
    for n in range(size):
        for m in range(size):
            v = Z[n, m].real
            w = Z[n, m].imag
            if v == 0.0 and w == 0.0:
                continue
            iv = n * size + m
            iw = half + iv
            for c in range(3):
                g[c] += v * grad[iv, c] + w * grad[iw, c]
            if want:
                for c in range(9):
                    h[c] += v * hess[iv, c] + w * hess[iw, c]
    # back to ICRF: a = R^T a_bf with R = [[c, s, 0], [-s, c, 0], [0, 0, 1]]
    a[0] += gm_r2 * (cr * g[0] - sr * g[1])
    a[1] += gm_r2 * (sr * g[0] + cr * g[1])
    a[2] += gm_r2 * g[2]
    if want:
        R = np.array([[cr, sr, 0.0], [-sr, cr, 0.0], [0.0, 0.0, 1.0]])
        for i in range(3):
            for j in range(3):
                total = 0.0
                for p in range(3):
                    for q in range(3):
                        total += R[p, i] * h[3 * p + q] * R[q, j]
                dadr[i, j] += gm_r3 * total


@kernel(inline=True)
def _indirect_acceleration(pos, tb_gm, tb_idx, out):
    """Acceleration (3,) km/s^2 of the centre towards the third bodies at pos (NT, 3), negated: the
    indirect term, the same for every state at one epoch."""
    out[:] = 0.0
    for b in range(tb_gm.shape[0]):
        j = tb_idx[b]
        p2 = pos[j, 0] ** 2 + pos[j, 1] ** 2 + pos[j, 2] ** 2
        k = tb_gm[b] / (p2 * math.sqrt(p2))
        for c in range(3):
            out[c] -= k * pos[j, c]


@kernel(inline=True)
def _acceleration(t, r, pos, indirect, gm_central, tb_gm, tb_idx, srp_scale, srp_sun, sh_idx, sh_radius,
                  geo_on, geo_f, geo_grad, geo_hess, row_a, row_b, dfact, a, dadr, want):
    """Total acceleration (3,) km/s^2 and da/dr (3, 3) 1/s^2 of a state at r (3,) km; pos (NT, 3) body
    positions, ``indirect`` (3,) their :func:`_indirect_acceleration`."""
    a[:] = indirect
    if want:
        dadr[:, :] = 0.0
    _add_point_mass(-r[0], -r[1], -r[2], gm_central, 1.0, a, dadr, want)
    for b in range(tb_gm.shape[0]):
        j = tb_idx[b]
        d0, d1, d2 = pos[j, 0] - r[0], pos[j, 1] - r[1], pos[j, 2] - r[2]
        _add_point_mass(d0, d1, d2, tb_gm[b], 1.0, a, dadr, want)
    _add_srp_and_geopotential(t, r, pos, srp_scale, srp_sun, sh_idx, sh_radius, geo_on, geo_f, geo_grad, geo_hess,
                              row_a, row_b, dfact, a, dadr, want)


@kernel(inline=True)
def _add_srp_and_geopotential(t, r, pos, srp_scale, srp_sun, sh_idx, sh_radius, geo_on, geo_f, geo_grad, geo_hess,
                              row_a, row_b, dfact, a, dadr, want):
    """The terms of :func:`_acceleration` after the point masses (radiation pressure, geopotential)."""
    if srp_scale > 0.0:
        s = np.empty(3)
        for c in range(3):
            s[c] = r[c] - (pos[srp_sun, c] if srp_sun >= 0 else 0.0)
        nu = 1.0
        rb = np.empty(3)
        for h in range(sh_idx.shape[0]):
            for c in range(3):
                rb[c] = r[c] - (pos[sh_idx[h], c] if sh_idx[h] >= 0 else 0.0)
            nu *= _shadow(s, rb, sh_radius[h])
        if nu > 0.0:
            # +k s/|s|^3 is a point mass of "GM" -k at the Sun: d = -s
            _add_point_mass(-s[0], -s[1], -s[2], srp_scale * nu, -1.0, a, dadr, want)
    if geo_on:
        _add_geopotential(t, r, geo_f[0], geo_f[1], geo_f[2], geo_f[3], geo_grad, geo_hess, row_a, row_b, dfact,
                          a, dadr, want)


@kernel
def _timescale(t, X, coef, first, seg, count, gm_central, tb_gm, tb_idx):
    """Shortest sqrt(d^3/GM) of the K states to the centre and every third body at t, s."""
    pos = np.empty((coef.shape[0], 6))
    if not chebyshev_states(t, coef, first, seg, count, 3, pos):
        return -1.0
    shortest = np.inf
    for k in range(X.shape[0]):
        d2 = X[k, 0] ** 2 + X[k, 1] ** 2 + X[k, 2] ** 2
        shortest = min(shortest, math.sqrt(d2 * math.sqrt(d2) / gm_central))
        for b in range(tb_gm.shape[0]):
            j = tb_idx[b]
            d2 = (pos[j, 0] - X[k, 0]) ** 2 + (pos[j, 1] - X[k, 1]) ** 2 + (pos[j, 2] - X[k, 2]) ** 2
            shortest = min(shortest, math.sqrt(d2 * math.sqrt(d2) / tb_gm[b]))
    return shortest


@kernel
def _stage_positions(t0, t1, n_steps, C, coef, first, seg, count, tb_gm, tb_idx):
    """Body positions (n_steps, n_stages, NT, 6; first 3 columns) and indirect accelerations
    (n_steps, n_stages, 3) at every stage epoch; empty arrays if a table ends."""
    n_stages = C.shape[0]
    h = (t1 - t0) / n_steps
    out = np.empty((n_steps, n_stages, coef.shape[0], 6))
    indirect = np.empty((n_steps, n_stages, 3))
    for step in range(n_steps):
        for i in range(n_stages):
            if not chebyshev_states(t0 + step * h + C[i] * h, coef, first, seg, count, 3, out[step, i]):
                return np.empty((0, n_stages, coef.shape[0], 6)), indirect
            _indirect_acceleration(out[step, i], tb_gm, tb_idx, indirect[step, i])
    return out, indirect


@kernel(inline=True)
def _integrate_one(k, t0, h, positions, indirect, X, Phi, with_stm, A, B, C, gm_central, tb_gm, tb_idx, srp_scale, srp_sun,
                   sh_idx, sh_radius, geo_on, geo_f, geo_grad, geo_hess, row_a, row_b, dfact):
    """Fixed-step RK of state k (and its STM) through the precomputed stage positions; in place."""
    n_steps, n_stages = positions.shape[0], positions.shape[1]
    kx = np.empty((n_stages, 6))
    kphi = np.empty((n_stages, 6, 6))
    y = np.empty(6)
    phi = np.empty((6, 6))
    a = np.empty(3)
    dadr = np.empty((3, 3))
    for step in range(n_steps):
        ts = t0 + step * h
        for i in range(n_stages):
            for c in range(6):
                total = X[k, c]
                for j in range(i):
                    total += h * A[i, j] * kx[j, c]
                y[c] = total
            if with_stm:
                for p in range(6):
                    for q in range(6):
                        total = Phi[k, p, q]
                        for j in range(i):
                            total += h * A[i, j] * kphi[j, p, q]
                        phi[p, q] = total
            _acceleration(ts + C[i] * h, y[:3], positions[step, i], indirect[step, i], gm_central, tb_gm, tb_idx,
                          srp_scale, srp_sun, sh_idx, sh_radius, geo_on, geo_f, geo_grad, geo_hess, row_a, row_b,
                          dfact, a, dadr, with_stm)
            for c in range(3):
                kx[i, c] = y[3 + c]
                kx[i, 3 + c] = a[c]
            if with_stm:
                for q in range(6):
                    for p in range(3):
                        kphi[i, p, q] = phi[3 + p, q]
                        kphi[i, 3 + p, q] = dadr[p, 0] * phi[0, q] + dadr[p, 1] * phi[1, q] + dadr[p, 2] * phi[2, q]
        for c in range(6):
            total = 0.0
            for i in range(n_stages):
                total += B[i] * kx[i, c]
            X[k, c] += h * total
        if with_stm:
            for p in range(6):
                for q in range(6):
                    total = 0.0
                    for i in range(n_stages):
                        total += B[i] * kphi[i, p, q]
                    Phi[k, p, q] += h * total


@kernel(inline=True)
def _integrate_points(t0, h, positions, indirect, X, A, B, C, gm_central, tb_gm, tb_idx, srp_scale, srp_sun, sh_idx,
                      sh_radius, geo_on, geo_f, geo_grad, geo_hess, row_a, row_b, dfact):
    """:func:`_integrate_one` of every state k of X (K, 6), without STMs, in place: the same operations in
    the same order, but each one done for all K states in a row (states in columns), which the
    compiler turns into vector instructions -- the sigma points of a UKF step go through together."""
    n_steps, n_stages = positions.shape[0], positions.shape[1]
    K = X.shape[0]
    start = np.empty((6, K))
    y = np.empty((6, K))
    kx = np.empty((n_stages, 6, K))
    total = np.empty(K)
    extra = geo_on or srp_scale > 0.0
    a = np.empty(3)
    r = np.empty(3)
    dadr = np.empty((3, 3))
    for k in range(K):
        for c in range(6):
            start[c, k] = X[k, c]
    for step in range(n_steps):
        ts = t0 + step * h
        for i in range(n_stages):
            for c in range(6):
                row = y[c]
                row[:] = start[c]
                for j in range(i):
                    hA = h * A[i, j]
                    stage = kx[j, c]
                    for k in range(K):
                        row[k] += hA * stage[k]
            # kx[i] = [v, a]; a = indirect + centre + third bodies (+ SRP, geopotential), as _acceleration adds them
            for c in range(3):
                kx[i, c, :] = y[3 + c]
            ax, ay, az = kx[i, 3], kx[i, 4], kx[i, 5]
            pos = positions[step, i]
            ind = indirect[step, i]
            for k in range(K):
                e0, e1, e2 = -y[0, k], -y[1, k], -y[2, k]
                dist2 = e0 * e0 + e1 * e1 + e2 * e2
                inv3 = gm_central / (dist2 * math.sqrt(dist2))
                ax[k] = ind[0] + 1.0 * inv3 * e0
                ay[k] = ind[1] + 1.0 * inv3 * e1
                az[k] = ind[2] + 1.0 * inv3 * e2
            for b in range(tb_gm.shape[0]):
                j = tb_idx[b]
                px, py, pz = pos[j, 0], pos[j, 1], pos[j, 2]
                gm = tb_gm[b]
                for k in range(K):
                    e0, e1, e2 = px - y[0, k], py - y[1, k], pz - y[2, k]
                    dist2 = e0 * e0 + e1 * e1 + e2 * e2
                    inv3 = gm / (dist2 * math.sqrt(dist2))
                    ax[k] += 1.0 * inv3 * e0
                    ay[k] += 1.0 * inv3 * e1
                    az[k] += 1.0 * inv3 * e2
            if extra:
                for k in range(K):
                    for c in range(3):
                        r[c] = y[c, k]
                    a[0], a[1], a[2] = ax[k], ay[k], az[k]
                    _add_srp_and_geopotential(ts + C[i] * h, r, pos, srp_scale, srp_sun, sh_idx, sh_radius, geo_on,
                                              geo_f, geo_grad, geo_hess, row_a, row_b, dfact, a, dadr, False)
                    ax[k], ay[k], az[k] = a[0], a[1], a[2]
        for c in range(6):
            total[:] = 0.0
            for i in range(n_stages):
                weight = B[i]
                stage = kx[i, c]
                for k in range(K):
                    total[k] += weight * stage[k]
            for k in range(K):
                start[c, k] += h * total[k]
    for k in range(K):
        for c in range(6):
            X[k, c] = start[c, k]


def _make_integrate(parallel: bool):
    loop = prange if parallel else range

    def integrate(t0, t1, n_steps, X, Phi, with_stm, A, B, C, coef, first, seg, count, gm_central, tb_gm, tb_idx,
                  srp_scale, srp_sun, sh_idx, sh_radius, geo_on, geo_f, geo_grad, geo_hess, row_a, row_b, dfact):
        positions, indirect = _stage_positions(t0, t1, n_steps, C, coef, first, seg, count, tb_gm, tb_idx)
        if positions.shape[0] == 0:
            return False
        h = (t1 - t0) / n_steps
        if not (parallel or with_stm):  # the same numbers, all states at once
            _integrate_points(t0, h, positions, indirect, X, A, B, C, gm_central, tb_gm, tb_idx, srp_scale, srp_sun,
                              sh_idx, sh_radius, geo_on, geo_f, geo_grad, geo_hess, row_a, row_b, dfact)
            return True
        for k in loop(X.shape[0]):
            _integrate_one(k, t0, h, positions, indirect, X, Phi, with_stm, A, B, C, gm_central, tb_gm, tb_idx,
                           srp_scale, srp_sun, sh_idx, sh_radius, geo_on, geo_f, geo_grad, geo_hess, row_a, row_b,
                           dfact)
        return True

    integrate.__doc__ = ("Fixed-step RK of K states (K, 6) and STMs (K, 6, 6) from t0 to t1 in n_steps, in place; "
                         "False if the ephemeris tables do not cover a stage epoch.")
    return kernel(integrate, parallel=parallel)


#: Batches below this many states run serially. The thread pool pays on a quiet machine (2 cores,
#: S1 cruise, 60-s step: 2x for 13-21 states, 3-7x for 260) but on a loaded one its threads wait
#: for busy cores (measured with two other jobs running: the one-state S3 EKF 30x slower, the
#: 13-sigma-point S1 UKF 5x slower than its EKF); sigma points of one filter stay serial,
#: lockstep Monte Carlo runs and particle clouds go parallel.
PARALLEL_FROM = 32
_integrate_serial = _make_integrate(parallel=False)
_integrate_parallel = _make_integrate(parallel=True)

#: :func:`propagate_states` outcomes other than 0 (done).
OUTSIDE_TABLES, AT_A_CENTRE, NOT_FINITE = 1, 2, 3


@kernel
def propagate_states(t0, t1, X, Phi, with_stm, step_fraction, tables, force):
    """:meth:`FastPropagator.step` inside a compiled kernel: K states (K, 6) and, if ``with_stm``, their
    STMs (K, 6, 6; identity on entry) from ``t0`` to ``t1`` (TDB s past J2000), serially and in place.

    ``tables`` is ``FastPropagator.tables(t0, t1)`` and ``force`` is :meth:`FastPropagator.kernel_force`;
    the steps are chosen, and the arithmetic done, exactly as :meth:`FastPropagator.step` does
    (``tests/test_fast_propagation.py`` checks the two agree to the last bit). Returns 0, or
    :data:`OUTSIDE_TABLES`, :data:`AT_A_CENTRE` (a state at a body's centre) or :data:`NOT_FINITE`.
    """
    (A, B, C, gm_central, tb_gm, tb_idx, srp_scale, srp_sun, sh_idx, sh_radius, geo_on, geo_f, geo_grad, geo_hess,
     row_a, row_b, dfact) = force
    coef, first, seg, count = tables
    dt = t1 - t0
    if dt == 0.0:
        return 0
    scale = _timescale(t0, X, coef, first, seg, count, gm_central, tb_gm, tb_idx)
    if scale == -1.0:
        return OUTSIDE_TABLES
    if not scale > 0.0:
        return AT_A_CENTRE
    n_steps = max(1, math.ceil(abs(dt) / (step_fraction * scale)))
    positions, indirect = _stage_positions(t0, t1, n_steps, C, coef, first, seg, count, tb_gm, tb_idx)
    if positions.shape[0] == 0:
        return OUTSIDE_TABLES
    h = (t1 - t0) / n_steps
    if with_stm:
        for k in range(X.shape[0]):
            _integrate_one(k, t0, h, positions, indirect, X, Phi, with_stm, A, B, C, gm_central, tb_gm, tb_idx,
                           srp_scale, srp_sun, sh_idx, sh_radius, geo_on, geo_f, geo_grad, geo_hess, row_a, row_b,
                           dfact)
    else:
        _integrate_points(t0, h, positions, indirect, X, A, B, C, gm_central, tb_gm, tb_idx, srp_scale, srp_sun, sh_idx,
                          sh_radius, geo_on, geo_f, geo_grad, geo_hess, row_a, row_b, dfact)
    for k in range(X.shape[0]):
        for c in range(6):
            if not math.isfinite(X[k, c]):
                return NOT_FINITE
    return 0


# ----------------------------------------------------------------------------- model compilation
def _cache_of(source) -> EphemerisCache:
    if isinstance(source, EphemerisCache):
        return source
    if isinstance(source, Ephemeris):
        return EphemerisCache(source)
    raise InputError(f"fast propagation needs an Ephemeris or EphemerisCache as position source, got "
                     f"{type(source).__name__}; use the exact (DOP853) propagator")


@dataclass(frozen=True)
class _Compiled:
    gm_central: float
    tb_gm: np.ndarray
    tb_idx: np.ndarray
    srp_scale: float
    srp_sun: int
    sh_idx: np.ndarray
    sh_radius: np.ndarray
    geo_on: bool
    geo_f: np.ndarray
    geo_grad: np.ndarray
    geo_hess: np.ndarray
    bodies: tuple[tuple[str, EphemerisCache], ...]


def _compile(model: ForceModel) -> _Compiled:
    center = model.center
    bodies: list[tuple[str, EphemerisCache]] = []

    def index(body: str, source) -> int:
        cache = _cache_of(source)
        for i, (name, other) in enumerate(bodies):
            if name == body and other is cache:
                return i
        bodies.append((body, cache))
        return len(bodies) - 1

    gm_central = 0.0
    tb_gm, tb_idx, sh_idx, sh_radius = [], [], [], []
    srp_scale, srp_sun = 0.0, -1
    geo = None
    for term in model.terms:
        kind = type(term)
        if kind is CentralGravity:
            gm_central += term.gm_km3_s2
        elif kind is ThirdBody:
            tb_gm.append(term.gm_km3_s2)
            tb_idx.append(index(term.body, term.ephemeris))
        elif kind is SolarRadiationPressure:
            if srp_scale > 0.0:
                raise InputError(f"force model {model.name!r}: fast propagation supports one SRP term")
            srp_scale = term._scale_km3_s2
            srp_sun = -1 if center == "sun" else index("sun", term.ephemeris)
            for body in term.shadow_bodies:
                sh_idx.append(-1 if body == center else index(body, term.ephemeris))
                sh_radius.append(RADIUS_KM[body])
        elif kind is Geopotential:
            if geo is not None:
                raise InputError(f"force model {model.name!r}: fast propagation supports one geopotential")
            geo = term
        else:
            raise InputError(f"force model {model.name!r}: term {kind.__name__} has no compiled form; "
                             "use the exact (DOP853) propagator")
    if gm_central <= 0.0:
        raise InputError(f"force model {model.name!r} has no central gravity term; fast propagation needs one")
    if geo is not None:
        grad, hess = geo.evaluation_tables
        geo_f = np.array([geo.gm_km3_s2 / geo.radius_km**2, geo.gm_km3_s2 / geo.radius_km**3, geo.radius_km,
                          geo.tdb_minus_ut1_s])
    else:
        grad, hess, geo_f = np.zeros((1, 3)), np.zeros((1, 9)), np.zeros(4)
    return _Compiled(gm_central, np.array(tb_gm, dtype=float), np.array(tb_idx, dtype=np.int64), float(srp_scale),
                     int(srp_sun), np.array(sh_idx, dtype=np.int64), np.array(sh_radius, dtype=float),
                     geo is not None, geo_f, np.ascontiguousarray(grad), np.ascontiguousarray(hess), tuple(bodies))


class FastPropagator:
    """Fixed-step, compiled propagation of K states (and STMs) under a :class:`ForceModel`.

    Parameters
    ----------
    model : ForceModel
        Dynamics; states are relative to ``model.center``. Supported terms:
        :class:`CentralGravity`, :class:`ThirdBody`, :class:`SolarRadiationPressure`,
        :class:`Geopotential` (every model of :mod:`opnav.dynamics.models`).
    step_fraction : float
        Largest step as a fraction of the shortest dynamical time (module docstring), in (0, 0.5].

    Raises
    ------
    InputError
        For a term without a compiled form or a bad ``step_fraction``.
    """

    def __init__(self, model: ForceModel, *, step_fraction: float = 0.05):
        if not (np.isfinite(step_fraction) and 0.0 < step_fraction <= 0.5):
            raise InputError(f"step_fraction must lie in (0, 0.5], got {step_fraction!r}")
        self.model = model
        self.center = model.center
        self.step_fraction = float(step_fraction)
        self._compiled = _compile(model)
        self._tables = ArcTables([(body, model.center, cache) for body, cache in self._compiled.bodies])

    def _steps(self, t0: float, X: np.ndarray, dt: float, tables) -> int:
        c = self._compiled
        coef, first, seg, count = tables
        scale = _timescale(t0, X, coef, first, seg, count, c.gm_central, c.tb_gm, c.tb_idx)
        if not scale > 0.0:
            raise InputError(f"fast propagation: a state is at a body's centre at t={t0:.3f} s")
        return max(1, math.ceil(abs(dt) / (self.step_fraction * scale)))

    def tables(self, t0_tdb_s: float, t1_tdb_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Chebyshev tables ``(coef, first, seg, count)`` of the model's bodies relative to its centre
        covering [t0, t1] (either order; TDB s past J2000), for :func:`propagate_states`."""
        return self._tables.cover(min(t0_tdb_s, t1_tdb_s), max(t0_tdb_s, t1_tdb_s))

    def kernel_force(self) -> tuple:
        """The compiled force model (with the Runge-Kutta tableau and the geopotential's recurrence
        tables) as the one tuple :func:`propagate_states` takes."""
        c = self._compiled
        return (_A, _B, _C, c.gm_central, c.tb_gm, c.tb_idx, c.srp_scale, c.srp_sun, c.sh_idx, c.sh_radius, c.geo_on,
                c.geo_f, c.geo_grad, c.geo_hess, _ROW_A_TABLE, _ROW_B_TABLE, _DF)

    def acceleration(self, t_tdb_s: float, r_km: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The compiled right-hand side: acceleration (K, 3) km/s^2 and da/dr (K, 3, 3) 1/s^2, ICRF,
        of positions ``r_km`` (K, 3) relative to ``model.center`` (equals ``model.acceleration`` /
        ``model.partials``; exposed to test that)."""
        r = np.atleast_2d(np.asarray(r_km, dtype=float))
        coef, first, seg, count = self._tables.cover(t_tdb_s, t_tdb_s)
        positions = np.empty((coef.shape[0], 6))
        chebyshev_states(float(t_tdb_s), coef, first, seg, count, 3, positions)
        c = self._compiled
        indirect = np.empty(3)
        _indirect_acceleration(positions, c.tb_gm, c.tb_idx, indirect)
        acc, grad = np.empty((len(r), 3)), np.empty((len(r), 3, 3))
        for k in range(len(r)):
            _acceleration(float(t_tdb_s), r[k].copy(), positions, indirect, c.gm_central, c.tb_gm, c.tb_idx, c.srp_scale,
                          c.srp_sun, c.sh_idx, c.sh_radius, c.geo_on, c.geo_f, c.geo_grad, c.geo_hess, _ROW_A_TABLE,
                          _ROW_B_TABLE, _DF, acc[k], grad[k], True)
        return acc, grad

    def step(self, t0_tdb_s: float, states: np.ndarray, t1_tdb_s: float, *, stm: bool = True
             ) -> tuple[np.ndarray, np.ndarray | None]:
        """Propagate states from ``t0_tdb_s`` to ``t1_tdb_s`` (either direction).

        Parameters
        ----------
        t0_tdb_s, t1_tdb_s : float
            TDB seconds past J2000.
        states : (6,) or (K, 6) array
            ``[r km, v km/s]``, ICRF, relative to ``model.center``. Not modified.
        stm : bool
            Also return ``d state(t1) / d state(t0)``.

        Returns
        -------
        states : (6,) or (K, 6) array at ``t1_tdb_s``
        stm : (6, 6) or (K, 6, 6) array, or None
        """
        X = np.array(states, dtype=float)
        single = X.ndim == 1
        X = np.atleast_2d(X)
        if X.ndim != 2 or X.shape[1] != 6:
            raise InputError(f"states must have shape (6,) or (K, 6), got {np.shape(states)}")
        if not (np.isfinite(t0_tdb_s) and np.isfinite(t1_tdb_s)):
            raise InputError(f"epochs must be finite, got {t0_tdb_s!r} -> {t1_tdb_s!r}")
        if not np.isfinite(X).all():
            raise InputError("states contain NaN or infinity")
        Phi = np.repeat(np.eye(6)[None], len(X), axis=0) if stm else np.empty((1, 6, 6))
        dt = float(t1_tdb_s) - float(t0_tdb_s)
        if dt != 0.0:
            tables = self._tables.cover(min(t0_tdb_s, t1_tdb_s), max(t0_tdb_s, t1_tdb_s))
            coef, first, seg, count = tables
            c = self._compiled
            integrate = _integrate_serial if len(X) < PARALLEL_FROM else _integrate_parallel
            ok = integrate(float(t0_tdb_s), float(t1_tdb_s), self._steps(t0_tdb_s, X, dt, tables), X, Phi, stm, _A,
                            _B, _C, coef, first, seg, count, c.gm_central, c.tb_gm, c.tb_idx, c.srp_scale, c.srp_sun,
                            c.sh_idx, c.sh_radius, c.geo_on, c.geo_f, c.geo_grad, c.geo_hess, _ROW_A_TABLE,
                            _ROW_B_TABLE, _DF)
            if not ok:  # pragma: no cover - cover() guarantees the span
                raise InputError(f"fast propagation left its ephemeris tables ({t0_tdb_s} -> {t1_tdb_s})")
            if not np.isfinite(X).all():
                raise InputError(f"fast propagation of model {self.model.name!r} produced NaN "
                                 f"({t0_tdb_s:.3f} -> {t1_tdb_s:.3f} s)")
        if single:
            return X[0], (Phi[0] if stm else None)
        return X, (Phi if stm else None)

    def trajectory(self, t0_tdb_s: float, state0: np.ndarray, t_tdb_s, *, stm: bool = False) -> Trajectory:
        """Chain :meth:`step` through the epochs ``t_tdb_s`` (like :func:`opnav.dynamics.propagate`).

        The STM returned at each epoch is relative to ``t0_tdb_s`` (products of the step STMs).
        """
        t_out = np.atleast_1d(np.asarray(t_tdb_s, dtype=float))
        x = np.array(state0, dtype=float)
        batch = x.ndim == 2
        X = np.atleast_2d(x)
        states = np.empty((len(t_out),) + X.shape)
        phis = np.empty((len(t_out), len(X), 6, 6)) if stm else None
        total = np.repeat(np.eye(6)[None], len(X), axis=0)
        t_prev = float(t0_tdb_s)
        for i, t in enumerate(t_out):
            X, phi = self.step(t_prev, X, float(t), stm=stm)
            states[i] = X
            if stm:
                total = phi @ total
                phis[i] = total
            t_prev = float(t)
        if not batch:
            states = states[:, 0]
            phis = phis[:, 0] if stm else None
        return Trajectory(t_out, states, phis, self.center)


def fast_propagator(model: ForceModel, **options) -> FastPropagator:
    """A :class:`FastPropagator` for ``model`` (``options`` as its constructor)."""
    return FastPropagator(model, **options)


__all__ = ["FastPropagator", "fast_propagator", "propagate_states"]
