"""Compiled single-run EKF and UKF steps for the common case: RA/Dec records, fast propagation, white ephemeris error.

The pure cores -- :func:`opnav.filters.ekf.ekf_predict` / :func:`~opnav.filters.ekf.ekf_update` and
:func:`opnav.filters.ukf.ukf_predict_estimate` / :func:`~opnav.filters.ukf.ukf_update_estimate` --
stay the reference and the general path: every record kind, augmented states, consider
parameters, refusals with their reasons. On S1's 86,400 RA/Dec records they spend most of their
time in numpy's per-call overhead (some fifty operations on 2x2 to 6x6 arrays a record). Here
one numba call does one record's predict and update with the same formulas:

:func:`ekf_radec_step`
    the record screen of :meth:`opnav.records.Measurement.problem`; propagation of the state and
    its STM (:func:`opnav.dynamics.fast.propagate_states`, the arithmetic of
    :meth:`~opnav.dynamics.fast.FastPropagator.step`), ``P = Phi P Phi^T + Q``, symmetrised and
    checked; the apparent direction to each target and its partials
    (:func:`opnav.light_compiled.directions_range`, as
    :class:`~opnav.measurements.ProbeMeasurementModel` computes them); RA/Dec, the wrapped
    innovation, ``R`` = record covariance + the white target-ephemeris term of
    :meth:`~opnav.measurements.ProbeMeasurementModel.noise_covariance`; the Joseph-form update of
    :func:`opnav.filters.ekf.joseph_update`; the chi-square gate; the posterior check.
:func:`ukf_radec_step`
    the same screen; sigma points of ``P``'s Cholesky factor propagated together (no STM), their
    moments about the central point plus ``Q`` (:func:`opnav.filters.ukf.ukf_predict`); points
    redrawn, measured and the update of :func:`opnav.filters.ukf.innovate`; gate and check.

What they cover: ``radec`` and ``radec_pair`` records, 6-element states ``[r km, v km/s]`` (ICRF,
relative to the dynamics' centre), a :class:`~opnav.dynamics.fast.FastPropagator` (the default
propagation, not ``exact``) and a :class:`~opnav.measurements.ProbeMeasurementModel` reading an
:class:`~opnav.ephemeris.cache.EphemerisCache` (the white ephemeris-error model). A kernel that
does not end in a plain accepted update -- a record with bad values, a step the propagator
refuses, a covariance that is not positive definite, a record outside the gate -- returns a
nonzero status and changes nothing; the filter then takes the record through the general path,
which refuses it with its logged reason or raises as it always did.

Cost on S1 (86,400 records, process CPU time, 2-core machine): ~15 us a record for the EKF and
~20 us for the UKF (13 sigma points propagated together and measured), against ~150 us for
either on the general path (``benchmarks/filters.py`` times the runner's stage).

Rounding: the formulas are the pure cores', evaluated in loops instead of BLAS/LAPACK calls (and
Cholesky solves instead of LU; libm's arctan2 instead of numpy's vectorised one, which differ in
the last bit for one call in fourteen), so the results agree with them to rounding, not to the bit:
one step to ~1e-13 relative (``tests/test_filter_compiled.py`` states each bound). S1's figures
are sensitive to rounding anywhere in the arc (its along-track axis is weakly observable): one
last-bit change of one of its 172,800 angles moves the EKF's position RMS by 8e-7 and its final
error by 3e-5 relative; the compiled steps move them by 1.4e-6 and 8e-5 (UKF: 1.8e-5, 4e-4).

numba caches each kernel keyed by its own file's text: after changing a kernel these call
(:func:`opnav.dynamics.fast.propagate_states`, :func:`opnav.light_compiled.directions_range`,
:func:`opnav.ephemeris.tables.chebyshev_states`), delete this module's cache
(``opnav/filters/__pycache__/compiled.*.nbi`` and ``.nbc``) or it keeps the old code.
Epochs are TDB seconds past J2000.
"""

from __future__ import annotations

import math

import numpy as np

from ..compiled import kernel
from ..dynamics.fast import propagate_states
from ..ephemeris.cache import EphemerisCache
from ..ephemeris.tables import chebyshev_states
from ..light import LIGHT_TIME_TOLERANCE_KM
from ..light_compiled import directions_range
from ..records import Measurement, pair_targets
from .base import Estimate, UpdateOutcome, chi2_quantile, discrete_noise
from .noise import WhiteAcceleration

#: Kernel outcomes: 0 is an accepted update; every other one sends the record to the general path.
ACCEPTED, RECORD_UNUSABLE, PROPAGATION_FAILED, PRIOR_NOT_PD, GEOMETRY_FAILED, INNOVATION_NOT_PD, OUTSIDE_GATE, \
    POSTERIOR_NOT_PD = range(8)
#: Record kinds the kernels take.
RADEC_KINDS = ("radec", "radec_pair")
#: A record covariance counts as positive definite here only with every Cholesky pivot above this
#: fraction of its diagonal entry; a closer call goes to :meth:`~opnav.records.Measurement.problem`.
_RECORD_PIVOT_MARGIN = 1e-10
#: Light-time iterations before giving up (as :func:`opnav.light_compiled.compiled_directions`).
_LIGHT_TIME_ITERATIONS = 10
_TWO_PI = 2.0 * math.pi


# ----------------------------------------------------------------------------- small kernels
@kernel(inline=True)
def _cholesky(A, L, margin):
    """Lower Cholesky factor of the symmetric ``A`` (m, m) into ``L``; False unless every pivot is
    positive, finite and above ``margin`` times its diagonal entry (LAPACK's test for ``margin`` 0)."""
    m = A.shape[0]
    for j in range(m):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > 0.0 and s > margin * A[j, j] and s < np.inf):
            return False
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j):
            L[i, j] = 0.0
        for i in range(j + 1, m):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
    return True


@kernel(inline=True)
def _solve_lower(L, B):
    """``B <- L^-1 B`` in place, ``L`` (m, m) lower triangular, ``B`` (m, k)."""
    m = L.shape[0]
    for c in range(B.shape[1]):
        for i in range(m):
            s = B[i, c]
            for k in range(i):
                s -= L[i, k] * B[k, c]
            B[i, c] = s / L[i, i]


@kernel(inline=True)
def _solve_upper_transposed(L, B):
    """``B <- L^-T B`` in place, ``L`` (m, m) lower triangular, ``B`` (m, k)."""
    m = L.shape[0]
    for c in range(B.shape[1]):
        for i in range(m - 1, -1, -1):
            s = B[i, c]
            for k in range(i + 1, m):
                s -= L[k, i] * B[k, c]
            B[i, c] = s / L[i, i]


@kernel(inline=True)
def _all_finite(a):
    for v in a.ravel():
        if not math.isfinite(v):
            return False
    return True


@kernel(inline=True)
def _symmetrize(A):
    """``A <- (A + A^T) / 2`` in place."""
    m = A.shape[0]
    for i in range(m):
        for j in range(i + 1, m):
            s = 0.5 * (A[i, j] + A[j, i])
            A[i, j] = s
            A[j, i] = s
        A[i, i] = 0.5 * (A[i, i] + A[i, i])


@kernel(inline=True)
def _record_usable(value, cov, work):
    """:meth:`opnav.records.Measurement.problem` is None: finite value and covariance, the covariance
    symmetric to 1e-9 (``numpy.allclose(C, C.T, rtol=1e-9, atol=0)``) and positive definite with a
    margin (a closer call is left to ``problem``); ``work`` is (m, m) scratch."""
    m = value.shape[0]
    if not (_all_finite(value) and _all_finite(cov)):
        return False
    for i in range(m):
        for j in range(m):
            if not abs(cov[i, j] - cov[j, i]) <= 1e-9 * abs(cov[j, i]):
                return False
    return _cholesky(cov, work, _RECORD_PIVOT_MARGIN)


@kernel(inline=True)
def _mod_two_pi(a):
    """``numpy.mod(a, 2 pi)`` (fmod, then the divisor's sign)."""
    mod = np.fmod(a, _TWO_PI)
    if mod != 0.0:
        if mod < 0.0:
            mod += _TWO_PI
    else:
        mod = 0.0
    return mod


@kernel(inline=True)
def _wrap(a):
    """:func:`opnav.measurements.wrap_angle`: ``a`` (rad) to (-pi, pi]."""
    wrapped = _mod_two_pi(a + math.pi) - math.pi
    return math.pi if wrapped == -math.pi else wrapped


@kernel(inline=True)
def _radec(u, out, slot):
    """RA in [0, 2 pi) and Dec (rad) of the vector ``u`` (3,) into ``out[slot]``, ``out[slot + 1]``
    (:func:`opnav.frames.unit_to_radec`)."""
    ra = _mod_two_pi(math.atan2(u[1], u[0]))
    if ra >= _TWO_PI:
        ra -= _TWO_PI
    out[slot] = ra
    out[slot + 1] = math.atan2(u[2], math.hypot(u[0], u[1]))


@kernel(inline=True)
def _radec_rows(u, du_dr, du_dv, H, slot):
    """Rows ``slot``, ``slot + 1`` of ``H`` (m, 6): d(ra, dec)/d[r, v] = radec_partials(u) [du/dr, du/dv]
    (:func:`opnav.measurements.radec_partials`)."""
    x, y, z = u[0], u[1], u[2]
    rxy2 = x * x + y * y
    rxy = math.sqrt(rxy2)
    r2 = rxy2 + z * z
    d_ra = (-y / rxy2, x / rxy2, 0.0)
    d_dec = (-x * z / (r2 * rxy), -y * z / (r2 * rxy), rxy / r2)
    for c in range(3):
        H[slot, c] = d_ra[0] * du_dr[0, c] + d_ra[1] * du_dr[1, c] + d_ra[2] * du_dr[2, c]
        H[slot, 3 + c] = d_ra[0] * du_dv[0, c] + d_ra[1] * du_dv[1, c] + d_ra[2] * du_dv[2, c]
        H[slot + 1, c] = d_dec[0] * du_dr[0, c] + d_dec[1] * du_dr[1, c] + d_dec[2] * du_dr[2, c]
        H[slot + 1, 3 + c] = d_dec[0] * du_dv[0, c] + d_dec[1] * du_dv[1, c] + d_dec[2] * du_dv[2, c]


@kernel(inline=True)
def _add_ephemeris_noise(t, x, tables, center_ssb, sigma_km, R, slot):
    """``R[slot:slot+2, slot:slot+2] += diag(s^2 / (u_x^2 + u_y^2), s^2)``, ``s = sigma_km / |rho|``: the
    white target-ephemeris term of :meth:`opnav.measurements.ProbeMeasurementModel.noise_covariance`
    at the geometric ``rho`` = target(t) - (centre(t) + r); False if ``t`` leaves the tables."""
    coef, first, seg, count = tables
    states = np.empty((coef.shape[0], 6))
    if not chebyshev_states(t, coef, first, seg, count, 3, states):
        return False
    rho = np.empty(3)
    for c in range(3):
        r_obs = x[c] if center_ssb else states[1, c] + x[c]
        rho[c] = states[0, c] - r_obs
    dist = math.sqrt(rho[0] * rho[0] + rho[1] * rho[1] + rho[2] * rho[2])
    u0, u1 = rho[0] / dist, rho[1] / dist
    angle_var = (sigma_km / dist) ** 2
    R[slot, slot] += angle_var / (u0 * u0 + u1 * u1)
    R[slot + 1, slot + 1] += angle_var
    return True


@kernel(inline=True)
def _measurement_noise(t, x, cov, pair, tables_a, tables_b, center_ssb, sigma_km, R):
    """``R`` (m, m) = record covariance + the ephemeris term of each target at state ``x``."""
    R[:, :] = cov
    if sigma_km == 0.0:
        return True
    if not _add_ephemeris_noise(t, x, tables_a, center_ssb, sigma_km, R, 0):
        return False
    if pair and not _add_ephemeris_noise(t, x, tables_b, center_ssb, sigma_km, R, 2):
        return False
    return True


# ----------------------------------------------------------------------------- the EKF step
@kernel
def ekf_radec_step(t0, t, x, P, Q, prop_tables, force, step_fraction, value, cov, pair, tables_a, tables_b,
                   center_ssb, light_time, aberration, sigma_km, gate_nis, tolerance_km):
    """One EKF record: predict from ``t0`` to the record epoch ``t`` (if later) and update.

    Parameters
    ----------
    t0, t : float
        Filter and record epochs, TDB s past J2000.
    x : (6,) array  P : (6, 6) array  Q : (6, 6) array
        Prior state (km, km/s, ICRF, relative to the dynamics' centre), its covariance and the process
        noise over ``[t0, t]`` (zero when ``t == t0``).
    prop_tables, force, step_fraction
        :meth:`FastPropagator.tables` over ``[t0, t]``, :meth:`FastPropagator.kernel_force`, and the
        propagator's step fraction.
    value : (m,) array  cov : (m, m) array
        The record's RA/Dec (``m = 2``) or RA/Dec pair (``m = 4``), rad, and its covariance, rad^2.
    pair : bool
        ``radec_pair`` (second target read from ``tables_b``).
    tables_a, tables_b
        :meth:`ProbeMeasurementModel.direction_tables` of the (first, second) target at ``t``.
    center_ssb, light_time, aberration, sigma_km
        The measurement model's centre being the SSB, its switches and ``target_position_sigma_km``.
    gate_nis : float
        Chi-square quantile the NIS must not exceed (``inf``: no gate).
    tolerance_km : float
        Light-time convergence tolerance (:data:`opnav.light.LIGHT_TIME_TOLERANCE_KM`).

    Returns
    -------
    status : int
        :data:`ACCEPTED` or why the general path must take the record.
    x_post (6,), P_post (6, 6), nu (m,), S (m, m), nis : posterior, innovation, its covariance, NIS.
    """
    n = 6
    m = value.shape[0]
    x_post = np.empty(n)
    P_post = np.empty((n, n))
    nu = np.empty(m)
    S = np.empty((m, m))
    L = np.empty((m, m))
    nis = np.nan
    if not _record_usable(value, cov, L):
        return RECORD_UNUSABLE, x_post, P_post, nu, S, nis
    # flags and counts for the shared kernels as run-time values: a literal (True, 0) would compile
    # them once more, typed for that literal, instead of reusing what the general path compiled
    yes, first_state, iterations = m > 0, m - m, m - m + _LIGHT_TIME_ITERATIONS
    # predict: x = f(x), P = Phi P Phi^T + Q, symmetrised and checked (ekf_predict, check_covariance)
    X = np.empty((1, n))
    X[0, :] = x[:n]
    Pp = np.empty((n, n))
    if t > t0:
        Phi = np.zeros((1, n, n))
        for i in range(n):
            Phi[0, i, i] = 1.0
        if propagate_states(t0, t, X, Phi, yes, step_fraction, prop_tables, force) != 0:
            return PROPAGATION_FAILED, x_post, P_post, nu, S, nis
        phi = Phi[0]
        work = np.empty((n, n))
        for i in range(n):
            for j in range(n):
                s = 0.0
                for k in range(n):
                    s += phi[i, k] * P[k, j]
                work[i, j] = s
        for i in range(n):
            for j in range(n):
                s = 0.0
                for k in range(n):
                    s += work[i, k] * phi[j, k]
                Pp[i, j] = s + Q[i, j]
        _symmetrize(Pp)
        if not _all_finite(Pp) or not _cholesky(Pp, np.empty((n, n)), 0.0):
            return PRIOR_NOT_PD, x_post, P_post, nu, S, nis
    else:
        Pp[:, :] = P
    # measurement: RA/Dec of each target and the Jacobian
    h = np.empty(m)
    H = np.zeros((m, n))
    rho, u, v_obs = np.empty((1, 3)), np.empty((1, 3)), np.empty((1, 3))
    du_dr, du_dv, drho = np.empty((1, 3, 3)), np.empty((1, 3, 3)), np.empty((1, 3, 3))
    for j in range(2 if pair else 1):
        coef, first, seg, count = tables_a if j == 0 else tables_b
        if directions_range(first_state, X.shape[0], t, X, center_ssb, coef, first, seg, count, light_time, aberration,
                            yes, tolerance_km, iterations, rho, u, du_dr, du_dv, drho, v_obs) != 0:
            return GEOMETRY_FAILED, x_post, P_post, nu, S, nis
        _radec(u[0], h, 2 * j)
        _radec_rows(u[0], du_dr[0], du_dv[0], H, 2 * j)
    for i in range(m):
        nu[i] = value[i] - h[i]
    nu[0] = _wrap(nu[0])
    if pair:
        nu[2] = _wrap(nu[2])
    R = np.empty((m, m))
    if not _measurement_noise(t, X[0], cov, pair, tables_a, tables_b, center_ssb, sigma_km, R):
        return GEOMETRY_FAILED, x_post, P_post, nu, S, nis
    # Joseph-form update (joseph_update): S = H P H^T + R, K = P H^T S^-1 through S's Cholesky factor
    HP = np.empty((m, n))
    for i in range(m):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += H[i, k] * Pp[k, j]
            HP[i, j] = s
    for i in range(m):
        for j in range(m):
            s = 0.0
            for k in range(n):
                s += HP[i, k] * H[j, k]
            S[i, j] = s + R[i, j]
    _symmetrize(S)
    if not _all_finite(nu) or not _cholesky(S, L, 0.0):
        return INNOVATION_NOT_PD, x_post, P_post, nu, S, nis
    white = np.empty((m, 1))
    white[:, 0] = nu
    _solve_lower(L, white)
    nis = 0.0
    for i in range(m):
        nis += white[i, 0] * white[i, 0]
    if not nis <= gate_nis:
        return OUTSIDE_GATE, x_post, P_post, nu, S, nis
    KT = HP.copy()  # becomes K^T = S^-1 H P
    _solve_lower(L, KT)
    _solve_upper_transposed(L, KT)
    a = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(m):
                s += KT[k, i] * H[k, j]
            a[i, j] = (1.0 if i == j else 0.0) - s
    aP = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += a[i, k] * Pp[k, j]
            aP[i, j] = s
    KR = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for k in range(m):
                s += KT[k, i] * R[k, j]
            KR[i, j] = s
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += aP[i, k] * a[j, k]
            r = 0.0
            for k in range(m):
                r += KR[i, k] * KT[k, j]
            P_post[i, j] = s + r
    _symmetrize(P_post)
    for i in range(n):
        s = 0.0
        for k in range(m):
            s += KT[k, i] * nu[k]
        x_post[i] = X[0, i] + s
    if not _all_finite(P_post) or not _cholesky(P_post, np.empty((n, n)), 0.0):
        return POSTERIOR_NOT_PD, x_post, P_post, nu, S, nis
    return ACCEPTED, x_post, P_post, nu, S, nis


# ----------------------------------------------------------------------------- the UKF step
@kernel(inline=True)
def _sigma_points(x, L, gamma, points):
    """``points`` (2n+1, n) = [x, x + gamma L[:, i], x - gamma L[:, i]] (:func:`opnav.filters.ukf.sigma_points`)."""
    n = x.shape[0]
    for c in range(n):
        points[0, c] = x[c]
    for i in range(n):
        for c in range(n):
            spread = gamma * L[c, i]
            points[1 + i, c] = x[c] + spread
            points[1 + n + i, c] = x[c] - spread


@kernel(inline=True)
def _spread(points, Wm, offsets, shift):
    """Offsets (2L, k) of ``points`` (2L+1, k) from the central one and the weighted shift (k,) of
    the mean from it (:func:`opnav.filters.ukf.sigma_moments`)."""
    k = points.shape[1]
    for c in range(k):
        shift[c] = 0.0
    for i in range(offsets.shape[0]):
        for c in range(k):
            d = points[1 + i, c] - points[0, c]
            offsets[i, c] = d
            shift[c] += Wm[1 + i] * d


@kernel(inline=True)
def _cross(a_off, a_shift, b_off, b_shift, Wc, c_shift, out):
    """``out`` (j, k) = sum_i Wc_i A_i B_i^T + (sum Wc - 2) a b^T (:func:`opnav.filters.ukf.cross_covariance`)."""
    for p in range(a_off.shape[1]):
        for q in range(b_off.shape[1]):
            s = 0.0
            for i in range(a_off.shape[0]):
                s += Wc[1 + i] * a_off[i, p] * b_off[i, q]
            out[p, q] = s + c_shift * (a_shift[p] * b_shift[q])


@kernel
def ukf_radec_step(t0, t, x, P, Q, prop_tables, force, step_fraction, gamma, Wm, Wc, c_shift, value, cov, pair,
                   tables_a, tables_b, center_ssb, light_time, aberration, sigma_km, gate_nis, tolerance_km):
    """One additive-noise UKF record: unscented predict from ``t0`` to ``t`` (if later) and update.

    Parameters as :func:`ekf_radec_step`, plus the sigma-point scale ``gamma``, the weights
    ``Wm``, ``Wc`` (2n+1,) and ``c_shift = sum(Wc) - 2`` (:class:`opnav.filters.ukf.SigmaWeights`).

    Returns
    -------
    status : int
    x_post (6,), P_post (6, 6), nu (m,) mean innovation, S (m, m), nis.
    """
    n = 6
    m = value.shape[0]
    n_points = Wm.shape[0]
    x_post = np.empty(n)
    P_post = np.empty((n, n))
    nu_mean = np.empty(m)
    S = np.empty((m, m))
    Ls = np.empty((m, m))
    nis = np.nan
    if not _record_usable(value, cov, Ls):
        return RECORD_UNUSABLE, x_post, P_post, nu_mean, S, nis
    no, first_state, iterations = m < 0, m - m, m - m + _LIGHT_TIME_ITERATIONS  # run-time values (ekf_radec_step)
    L = np.empty((n, n))
    points = np.empty((n_points, n))
    x_off = np.empty((n_points - 1, n))
    x_shift = np.empty(n)
    mean = np.empty(n)
    Pp = np.empty((n, n))
    # predict (ukf_predict): all points through the propagator at once, moments about the central one
    if t > t0:
        if not _cholesky(P, L, 0.0):
            return PRIOR_NOT_PD, x_post, P_post, nu_mean, S, nis
        _sigma_points(x, L, gamma, points)
        if propagate_states(t0, t, points, np.empty((1, 6, 6)), no, step_fraction, prop_tables, force) != 0:
            return PROPAGATION_FAILED, x_post, P_post, nu_mean, S, nis
        _spread(points, Wm, x_off, x_shift)
        for c in range(n):
            mean[c] = points[0, c] + x_shift[c]
        _cross(x_off, x_shift, x_off, x_shift, Wc, c_shift, Pp)
        for i in range(n):
            for j in range(n):
                Pp[i, j] += Q[i, j]
        _symmetrize(Pp)
    else:
        mean[:] = x
        Pp[:, :] = P
    # update (ukf_update, innovate): points redrawn from the prediction and measured
    R = np.empty((m, m))
    if not _measurement_noise(t, mean, cov, pair, tables_a, tables_b, center_ssb, sigma_km, R):
        return GEOMETRY_FAILED, x_post, P_post, nu_mean, S, nis
    if not _cholesky(Pp, L, 0.0):
        return PRIOR_NOT_PD, x_post, P_post, nu_mean, S, nis
    _sigma_points(mean, L, gamma, points)
    if not _all_finite(points):
        return PRIOR_NOT_PD, x_post, P_post, nu_mean, S, nis
    predicted = np.empty((n_points, m))
    rho, u, v_obs = np.empty((n_points, 3)), np.empty((n_points, 3)), np.empty((n_points, 3))
    unused = np.empty((1, 3, 3))
    for j in range(2 if pair else 1):
        coef, first, seg, count = tables_a if j == 0 else tables_b
        if directions_range(first_state, n_points, t, points, center_ssb, coef, first, seg, count, light_time,
                            aberration, no, tolerance_km, iterations, rho, u, unused, unused, unused, v_obs) != 0:
            return GEOMETRY_FAILED, x_post, P_post, nu_mean, S, nis
        for i in range(n_points):
            _radec(u[i], predicted[i], 2 * j)
    nu = np.empty((n_points, m))
    for i in range(n_points):
        for c in range(m):
            nu[i, c] = value[c] - predicted[i, c]
        nu[i, 0] = _wrap(nu[i, 0])
        if pair:
            nu[i, 2] = _wrap(nu[i, 2])
    nu_off = np.empty((n_points - 1, m))
    nu_shift = np.empty(m)
    _spread(nu, Wm, nu_off, nu_shift)
    for c in range(m):
        nu_mean[c] = nu[0, c] + nu_shift[c]
    _spread(points, Wm, x_off, x_shift)
    _cross(nu_off, nu_shift, nu_off, nu_shift, Wc, c_shift, S)
    for i in range(m):
        for j in range(m):
            S[i, j] += R[i, j]
    _symmetrize(S)
    Pxz = np.empty((n, m))
    _cross(x_off, x_shift, nu_off, nu_shift, Wc, c_shift, Pxz)
    if not _all_finite(nu_mean) or not _cholesky(S, Ls, 0.0):
        return INNOVATION_NOT_PD, x_post, P_post, nu_mean, S, nis
    # [K^T | S^-1 nu] = S^-1 [Pxz^T | nu] (Pxz as innovate defines it: minus the cross-covariance above)
    solved = np.empty((m, n + 1))
    for i in range(m):
        for c in range(n):
            solved[i, c] = -Pxz[c, i]
        solved[i, n] = nu_mean[i]
    _solve_lower(Ls, solved)
    _solve_upper_transposed(Ls, solved)
    nis = 0.0
    for i in range(m):
        nis += nu_mean[i] * solved[i, n]
    if not nis <= gate_nis:
        return OUTSIDE_GATE, x_post, P_post, nu_mean, S, nis
    for c in range(n):
        s = 0.0
        for k in range(m):
            s += solved[k, c] * nu_mean[k]
        x_post[c] = mean[c] + s
    KS = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for k in range(m):
                s += solved[k, i] * S[k, j]
            KS[i, j] = s
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(m):
                s += KS[i, k] * solved[k, j]
            P_post[i, j] = Pp[i, j] - s
    _symmetrize(P_post)
    if not _all_finite(P_post) or not _cholesky(P_post, L, 0.0):
        return POSTERIOR_NOT_PD, x_post, P_post, nu_mean, S, nis
    return ACCEPTED, x_post, P_post, nu_mean, S, nis


# ----------------------------------------------------------------------------- the filters' side
class RadecSteps:
    """The compiled steps for one filter's propagator and measurement model (see :func:`radec_steps`).

    :meth:`ekf` and :meth:`ukf` take a prior :class:`~opnav.filters.base.Estimate` and a record and
    return the accepted :class:`~opnav.filters.base.UpdateOutcome` (what the filter's ``update``
    returns for it), or None when the general path must take the record (another kind, or a
    kernel status other than :data:`ACCEPTED`); they change nothing in either case.
    """

    def __init__(self, propagator, model):
        self.propagator = propagator
        self.model = model
        self.force = propagator.kernel_force()
        self._zero = np.zeros((6, 6))
        self._noise = (None, None, None)
        self._gates: dict[tuple[float | None, int], float] = {}
        self._targets: dict[str, tuple[str, ...]] = {}
        self._weights = (None, 0.0)  # the last SigmaWeights and their sum(Wc) - 2

    def _inputs(self, estimate: Estimate, record: Measurement, process_noise):
        """The epochs, process noise, tables and model switches of a kernel call, or None."""
        if record.kind not in RADEC_KINDS or estimate.x.shape != (6,):
            return None
        t0, t = estimate.t_tdb_s, record.t_tdb_s
        if not t >= t0 - 1e-9:  # in the filter's past: the general path refuses it
            return None
        names = self._targets.get(record.target)
        if names is None:
            names = tuple(name.strip().lower() for name in pair_targets(record)) if record.kind == "radec_pair" \
                else (record.target.strip().lower(),)
            self._targets[record.target] = names
        if not all(names):
            return None
        tables = [self.model.direction_tables(name, t) for name in names]
        if tables[0] is None:
            return None
        later = t > t0
        Q = self._process_noise(process_noise, t0, t, estimate.x) if later else self._zero
        prop_tables = self.propagator.tables(t0, t if later else t0)
        model = self.model
        return (t0, t, Q, prop_tables, tables[0], tables[-1], model.center == "ssb", model.light_time,
                model.aberration, model.target_position_sigma_km)

    def _process_noise(self, process_noise, t0: float, t: float, x: np.ndarray) -> np.ndarray:
        """``discrete_noise`` over [t0, t] at ``x``; white acceleration's, a function of the step alone, is
        kept for the last step length."""
        if process_noise is None:
            return self._zero
        if type(process_noise) is WhiteAcceleration:
            dt = t - t0
            last, model, Q = self._noise
            if last != dt or model is not process_noise:
                Q = discrete_noise(process_noise, t0, t, x)
                self._noise = (dt, process_noise, Q)
            return Q
        return discrete_noise(process_noise, t0, t, x)

    def _gate(self, probability: float | None, size: int) -> float:
        key = (probability, size)
        gate = self._gates.get(key)
        if gate is None:
            gate = self._gates[key] = np.inf if probability is None else chi2_quantile(probability, size)
        return gate

    def ekf(self, estimate: Estimate, record: Measurement, *, process_noise,
            gate_probability: float | None) -> UpdateOutcome | None:
        """:meth:`opnav.filters.ekf.ExtendedKalmanFilter.update` of ``record`` from ``estimate``, compiled."""
        inputs = self._inputs(estimate, record, process_noise)
        if inputs is None:
            return None
        t0, t, Q, prop_tables, tables_a, tables_b, center_ssb, light_time, aberration, sigma = inputs
        status, x, P, nu, S, nis = ekf_radec_step(
            t0, t, estimate.x, estimate.P, Q, prop_tables, self.force, self.propagator.step_fraction, record.value,
            record.covariance, record.kind == "radec_pair", tables_a, tables_b, center_ssb, light_time, aberration,
            sigma, self._gate(gate_probability, record.size), LIGHT_TIME_TOLERANCE_KM)
        if status != ACCEPTED:
            return None
        return UpdateOutcome(Estimate(t if t > t0 else t0, x, P), nu, S, nis, True)

    def ukf(self, estimate: Estimate, record: Measurement, *, process_noise, weights,
            gate_probability: float | None) -> UpdateOutcome | None:
        """:meth:`opnav.filters.ukf.UnscentedKalmanFilter.update` of ``record`` from ``estimate``, compiled;
        ``weights`` is the filter's :class:`~opnav.filters.ukf.SigmaWeights`."""
        inputs = self._inputs(estimate, record, process_noise)
        if inputs is None or weights.n != 6:
            return None
        t0, t, Q, prop_tables, tables_a, tables_b, center_ssb, light_time, aberration, sigma = inputs
        if self._weights[0] is not weights:
            self._weights = (weights, float(np.sum(weights.Wc)) - 2.0)
        status, x, P, nu, S, nis = ukf_radec_step(
            t0, t, estimate.x, estimate.P, Q, prop_tables, self.force, self.propagator.step_fraction, weights.gamma,
            weights.Wm, weights.Wc, self._weights[1], record.value, record.covariance,
            record.kind == "radec_pair", tables_a, tables_b, center_ssb, light_time, aberration, sigma,
            self._gate(gate_probability, record.size), LIGHT_TIME_TOLERANCE_KM)
        if status != ACCEPTED:
            return None
        return UpdateOutcome(Estimate(t, x, P), nu, S, nis, True)


def radec_steps(propagator, model) -> RadecSteps | None:
    """The compiled steps for a filter propagating with ``propagator`` and measuring with ``model``,
    or None when they do not fit (propagator not a :class:`~opnav.dynamics.fast.FastPropagator`,
    model not exactly a :class:`~opnav.measurements.ProbeMeasurementModel` on an
    :class:`~opnav.ephemeris.cache.EphemerisCache`)."""
    from ..dynamics.fast import FastPropagator
    from ..measurements import ProbeMeasurementModel

    if not isinstance(propagator, FastPropagator) or type(model) is not ProbeMeasurementModel:
        return None
    if not isinstance(model.ephemeris, EphemerisCache):
        return None
    return RadecSteps(propagator, model)


def filter_steps(owner, base: type, propagator, model) -> RadecSteps | None:
    """The :class:`RadecSteps` of filter ``owner``'s current ``propagator`` and ``model``, cached on
    ``owner`` until either changes; None when ``owner``'s class replaces ``base``'s ``_predict`` or
    ``_update`` (the square-root UKF, for one), whose steps the kernels do not do."""
    models = getattr(owner, "_steps_models", (None, None))
    if models[0] is not propagator or models[1] is not model:
        plain = type(owner)._predict is base._predict and type(owner)._update is base._update
        fast = getattr(propagator, "fast_propagator", None)
        owner._steps = radec_steps(fast, model) if plain else None
        owner._steps_models = (propagator, model)
    return owner._steps
