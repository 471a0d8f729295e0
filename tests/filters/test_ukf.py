"""Unscented filters: agreement with the Kalman filter and filterpy, square-root and
augmented forms, chi-square consistency, gating and bad input.

The toy problems here (constant-velocity and point-mass dynamics, position and
beacon RA/Dec measurements) are also used by the particle and federated tests.
"""

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints
from filterpy.kalman import UnscentedKalmanFilter as FilterpyUKF
from scipy import stats

from opnav.errors import InputError
from opnav.filters.base import Estimate
from opnav.filters.augmented_ukf import AugmentedUKF, additive_noise
from opnav.filters.sr_ukf import SquareRootUKF, cholupdate
from opnav.filters.ukf import (
    UKFOptions,
    UnscentedKalmanFilter,
    sigma_points,
    sigma_weights,
)
from opnav.records import Measurement

GM = 398_600.4418  # km^3/s^2, a point-mass Earth for the toy orbit


def cv_matrix(dt: float) -> np.ndarray:
    F = np.eye(6)
    F[:3, 3:] = dt * np.eye(3)
    return F


def cv_transition(t0, X, t1):
    return np.asarray(X) @ cv_matrix(t1 - t0).T


class FixedNoise:
    """Process noise with the same discrete Q for every step (the steps here are all 60 s)."""

    def __init__(self, Q):
        self.Q = np.asarray(Q, dtype=float)

    def discrete(self, dt_s, x):
        return self.Q


def gravity_transition(t0, X, t1, substeps=6):
    """Point-mass gravity, fixed-step RK4 (km, km/s); vectorised over rows of X."""

    def rhs(y):
        r = y[:, :3]
        a = -GM * r / np.linalg.norm(r, axis=1, keepdims=True) ** 3
        return np.hstack([y[:, 3:], a])

    y = np.atleast_2d(np.array(X, dtype=float))
    h = (t1 - t0) / substeps
    for _ in range(substeps):
        k1 = rhs(y)
        k2 = rhs(y + 0.5 * h * k1)
        k3 = rhs(y + 0.5 * h * k2)
        k4 = rhs(y + h * k3)
        y = y + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return y if np.ndim(X) == 2 else y[0]


class PositionModel:
    """Linear position measurement of the first three state entries (km)."""

    def predict(self, record, x):
        return np.asarray(x)[..., :3]

    def jacobian(self, record, x):
        return np.hstack([np.eye(3), np.zeros((3, np.size(x) - 3))])

    def residual(self, record, predicted):
        return record.value - predicted


class BeaconRadec:
    """RA/Dec (rad) of fixed beacons (``record.target``) seen from the state's position."""

    def __init__(self, beacons):
        self.beacons = {k: np.asarray(v, dtype=float) for k, v in beacons.items()}

    def predict(self, record, x):
        d = self.beacons[record.target] - np.asarray(x)[..., :3]
        return np.stack([np.arctan2(d[..., 1], d[..., 0]), np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))], -1)

    def jacobian(self, record, x):
        raise NotImplementedError("the unscented and particle filters never call it")

    def residual(self, record, predicted):
        d = record.value - predicted
        d[..., 0] = (d[..., 0] + np.pi) % (2 * np.pi) - np.pi
        return d


BEACONS = {"a": np.zeros(3), "b": np.array([0.0, 0.0, 9000.0])}
X0_ORBIT = np.array([7000.0, 1000.0, 500.0, -1.0, 7.3, 1.0])
P0_ORBIT = np.diag([4.0, 4.0, 4.0, 1e-6, 1e-6, 1e-6])
Q_ORBIT = np.diag([1e-4, 1e-4, 1e-4, 1e-8, 1e-8, 1e-8])
SIGMA_RADEC = 2e-4


def radec_record(t, z, target, sigma=SIGMA_RADEC):
    return Measurement(t, "radec", z, np.eye(2) * sigma**2, target=target)


def simulate_orbit(rng, steps, dt=60.0, x0=X0_ORBIT, P0=P0_ORBIT, Q=Q_ORBIT):
    """Truth states and beacon RA/Dec records for the toy orbit (truth perturbed by Q)."""
    model = BeaconRadec(BEACONS)
    x = x0 + np.linalg.cholesky(P0) @ rng.standard_normal(6)
    truth, records = [], []
    for k in range(1, steps + 1):
        x = gravity_transition(0.0, x, dt) + np.linalg.cholesky(Q) @ rng.standard_normal(6)
        truth.append(x)
        for target in BEACONS:
            rec = radec_record(k * dt, 0.0 * np.ones(2), target)
            z = model.predict(rec, x) + SIGMA_RADEC * rng.standard_normal(2)
            records.append(radec_record(k * dt, z, target))
    return np.array(truth), records


def assert_gaussians_close(x, P, x_ref, P_ref, tol):
    """Means within ``tol`` sigma and covariances within ``tol`` after normalising by the reference sigmas."""
    scale = np.sqrt(np.diag(P_ref))
    np.testing.assert_allclose(x / scale, x_ref / scale, rtol=0, atol=tol)
    np.testing.assert_allclose(P / np.outer(scale, scale), P_ref / np.outer(scale, scale), rtol=0, atol=tol)


# With small alpha the points sit alpha*sqrt(n) sigma from the mean, so forming
# them from a state of size |x| costs eps*|x|/(alpha*sqrt(n)*sigma) relative
# precision, amplified by weights ~1/(alpha^2 n): eps*|x|/(alpha^2 n sigma) is
# 2e-9 sigma per step for the linear case below and 1e-7 sigma for the RA/Dec
# innovations (|z| ~ 1 rad, sigma ~ 3e-4 rad) at alpha = 1e-3. Agreement to
# 1e-9 is checked where that rounding floor is below it; alpha = 1e-3 gets 1e-6.
ALPHA_TOLERANCES = [(1.0, 1e-9), (0.1, 1e-9), (1e-3, 1e-6)]


def test_sigma_points_match_filterpy():
    rng = np.random.default_rng(1)
    A = rng.standard_normal((6, 6))
    P = A @ A.T + 6 * np.eye(6)
    x = rng.standard_normal(6)
    options = UKFOptions(alpha=0.5, beta=2.0, kappa=1.0)
    ref = MerweScaledSigmaPoints(6, 0.5, 2.0, 1.0)
    w = sigma_weights(6, options)
    np.testing.assert_allclose(w.Wm, ref.Wm, rtol=1e-14, atol=0)
    np.testing.assert_allclose(w.Wc, ref.Wc, rtol=1e-14, atol=0)
    for n, alpha, beta, kappa in ((6, 1e-3, 2.0, 0.0), (7, 1.0, 0.0, 3.0 - 7), (3, 0.3, 2.0, 2.0)):
        ref_n, w_n = MerweScaledSigmaPoints(n, alpha, beta, kappa), sigma_weights(n, UKFOptions(alpha=alpha, beta=beta, kappa=kappa))
        np.testing.assert_allclose(w_n.Wm, ref_n.Wm, rtol=1e-12, atol=0)
        np.testing.assert_allclose(w_n.Wc, ref_n.Wc, rtol=1e-12, atol=0)
    np.testing.assert_allclose(sigma_points(x, np.linalg.cholesky(P), w.gamma), ref.sigma_points(x, P), rtol=0, atol=1e-12)
    batch = sigma_points(np.stack([x, 2 * x]), np.linalg.cholesky(np.stack([P, P])), w.gamma)
    np.testing.assert_allclose(batch[1], ref.sigma_points(2 * x, P), atol=1e-12)


def test_cholupdate_update_and_downdate():
    rng = np.random.default_rng(2)
    A = rng.standard_normal((5, 5))
    P = A @ A.T + np.eye(5)
    v = 0.3 * rng.standard_normal(5)
    L = np.linalg.cholesky(P)
    up = cholupdate(L, v, 1.0)
    np.testing.assert_allclose(up @ up.T, P + np.outer(v, v), rtol=1e-12, atol=1e-12)
    down = cholupdate(up, v, -1.0)
    np.testing.assert_allclose(down @ down.T, P, rtol=1e-11, atol=1e-11)


@pytest.mark.parametrize("alpha,tol", ALPHA_TOLERANCES)
@pytest.mark.parametrize("filter_class", [UnscentedKalmanFilter, SquareRootUKF])
def test_linear_gaussian_reproduces_kalman_filter(filter_class, alpha, tol):
    """On a linear-Gaussian problem the unscented transform is exact: UKF == KF."""
    rng = np.random.default_rng(3)
    dt = 60.0
    Q = np.diag([1e-3, 1e-3, 1e-3, 1e-7, 1e-7, 1e-7])
    R = np.diag([0.5, 0.8, 0.3])
    x0 = np.array([100.0, -50.0, 20.0, 0.1, 0.2, -0.05])
    P0 = np.diag([25.0, 25.0, 25.0, 1e-4, 1e-4, 1e-4])
    ukf = filter_class(Estimate(0.0, x0, P0), transition=cv_transition, process_noise=FixedNoise(Q),
                       model=PositionModel(), options=UKFOptions(alpha=alpha))
    kf = KalmanFilter(dim_x=6, dim_z=3)
    kf.x, kf.P, kf.F, kf.Q, kf.R = x0.copy(), P0.copy(), cv_matrix(dt), Q.copy(), R.copy()
    kf.H = np.hstack([np.eye(3), np.zeros((3, 3))])
    x_own, P_own = x0.copy(), P0.copy()
    H = kf.H
    for k in range(1, 40):
        z = rng.standard_normal(3) * 2 + x0[:3]
        out = ukf.update(Measurement(k * dt, "position", z, R))
        kf.predict()
        kf.update(z)
        # textbook KF written out, independent of filterpy
        F = cv_matrix(dt)
        x_own, P_own = F @ x_own, F @ P_own @ F.T + Q
        S = H @ P_own @ H.T + R
        K = P_own @ H.T @ np.linalg.inv(S)
        x_own, P_own = x_own + K @ (z - H @ x_own), (np.eye(6) - K @ H) @ P_own
        assert out.accepted
        assert_gaussians_close(out.estimate.x, out.estimate.P, kf.x.ravel(), kf.P, tol)
        assert_gaussians_close(out.estimate.x, out.estimate.P, x_own, P_own, tol)
        assert_gaussians_close(out.residual, out.residual_cov, out.residual, kf.S, tol)


def _filterpy_orbit_ukf(options, Q, R):
    points = MerweScaledSigmaPoints(6, options.alpha, options.beta, options.kappa)
    model = BeaconRadec(BEACONS)
    rec = radec_record(0.0, np.zeros(2), "a")
    fx = lambda x, dt: gravity_transition(0.0, x, dt)
    hx = lambda x: model.predict(rec, x)
    ref = FilterpyUKF(dim_x=6, dim_z=2, dt=60.0, hx=hx, fx=fx, points=points)
    ref.x, ref.P, ref.Q, ref.R = X0_ORBIT.copy(), P0_ORBIT.copy(), Q.copy(), R.copy()
    return ref


# filterpy sums raw weighted points (central weight 1 - 1/alpha^2): with
# |x|/sigma ~ 5000 its own rounding exceeds 1e-9 sigma below alpha ~ 0.5.
@pytest.mark.parametrize("options", [UKFOptions(alpha=0.5), UKFOptions(alpha=0.8, beta=2.0, kappa=0.5)])
def test_nonlinear_agrees_with_filterpy_ukf(options):
    rng = np.random.default_rng(4)
    truth, records = simulate_orbit(rng, 25)
    records = [r for r in records if r.target == "a"]
    R = np.eye(2) * SIGMA_RADEC**2
    ukf = UnscentedKalmanFilter(Estimate(0.0, X0_ORBIT, P0_ORBIT), transition=gravity_transition,
                                process_noise=FixedNoise(Q_ORBIT), model=BeaconRadec(BEACONS), options=options)
    ref = _filterpy_orbit_ukf(options, Q_ORBIT, R)
    for rec in records:
        out = ukf.update(rec)
        ref.predict()
        ref.update(rec.value)
        assert_gaussians_close(out.estimate.x, out.estimate.P, ref.x, ref.P, 1e-9)
        np.testing.assert_allclose(out.residual / SIGMA_RADEC, ref.y / SIGMA_RADEC, rtol=0, atol=1e-9)
        assert_gaussians_close(out.residual, out.residual_cov, ref.y, ref.S, 1e-9)


def rounding_floor(alpha, x, P):
    """Sigma-normalised rounding of one unscented step: eps |x| / (alpha^2 n sigma)."""
    ratio = np.max(np.abs(x) / np.sqrt(np.diag(P)))
    return np.finfo(float).eps * ratio / (alpha**2 * x.size)


@pytest.mark.parametrize("alpha", [1.0, 0.1, 1e-3])
def test_square_root_ukf_equals_ukf(alpha):
    rng = np.random.default_rng(5)
    _, records = simulate_orbit(rng, 40)
    kwargs = dict(transition=gravity_transition, process_noise=FixedNoise(Q_ORBIT),
                  model=BeaconRadec(BEACONS), options=UKFOptions(alpha=alpha))
    ukf = UnscentedKalmanFilter(Estimate(0.0, X0_ORBIT, P0_ORBIT), **kwargs)
    srukf = SquareRootUKF(Estimate(0.0, X0_ORBIT, P0_ORBIT), **kwargs)
    for rec in records:
        a, b = ukf.update(rec), srukf.update(rec)
        # the two forms draw points from different (equal to rounding) square roots; the gap
        # random-walks at the floor: sqrt(2n) points x sqrt(80 updates) ~ 30, with a margin of 3
        tol = max(1e-9, 100 * rounding_floor(alpha, a.estimate.x, a.estimate.P))
        assert_gaussians_close(b.estimate.x, b.estimate.P, a.estimate.x, a.estimate.P, tol)
        assert np.sqrt(b.nis) == pytest.approx(np.sqrt(a.nis), abs=tol)


def test_augmented_ukf_is_exact_on_linear_problem():
    """Linear dynamics and measurement: the joint [x, w, v] transform is exact, so it equals the KF."""
    rng = np.random.default_rng(6)
    Q = np.diag([1e-3, 1e-3, 1e-3, 1e-7, 1e-7, 1e-7])
    R = np.diag([0.5, 0.8, 0.3])
    x0 = np.array([100.0, -50.0, 20.0, 0.1, 0.2, -0.05])
    P0 = np.diag([25.0, 25.0, 25.0, 1e-4, 1e-4, 1e-4])
    common = dict(process_noise=FixedNoise(Q), model=PositionModel(), options=UKFOptions(alpha=0.5))
    aug = AugmentedUKF(Estimate(0.0, x0, P0), transition=additive_noise(cv_transition), **common)
    ukf = UnscentedKalmanFilter(Estimate(0.0, x0, P0), transition=cv_transition, **common)
    for k in range(1, 30):
        rec = Measurement(60.0 * k, "position", x0[:3] + rng.standard_normal(3), R)
        predicted, reference = aug.predict(rec.t_tdb_s), ukf.predict(rec.t_tdb_s)
        assert_gaussians_close(predicted.x, predicted.P, reference.x, reference.P, 1e-9)
        a, b = aug.update(rec), ukf.update(rec)
        assert_gaussians_close(a.estimate.x, a.estimate.P, b.estimate.x, b.estimate.P, 1e-9)


def test_augmented_ukf_close_to_additive_on_nonlinear_problem():
    rng = np.random.default_rng(7)
    truth, records = simulate_orbit(rng, 40)
    common = dict(process_noise=FixedNoise(Q_ORBIT), model=BeaconRadec(BEACONS), options=UKFOptions(alpha=1e-3))
    aug = AugmentedUKF(Estimate(0.0, X0_ORBIT, P0_ORBIT), transition=additive_noise(gravity_transition), **common)
    ukf = UnscentedKalmanFilter(Estimate(0.0, X0_ORBIT, P0_ORBIT), transition=gravity_transition, **common)
    for rec in records:
        a, b = aug.update(rec), ukf.update(rec)
        sigma = np.sqrt(np.diag(b.estimate.P))
        # differences are higher-order moments of a nearly linear problem: far below one sigma
        assert np.all(np.abs(a.estimate.x - b.estimate.x) < 1e-3 * sigma)
        np.testing.assert_allclose(np.sqrt(np.diag(a.estimate.P)), sigma, rtol=1e-3)


def nees(error, P):
    return float(error @ np.linalg.solve(P, error))


def test_ukf_mean_nees_inside_chi_square_interval():
    """Final-epoch NEES over independent seeded runs ~ chi2(6 N)/N."""
    runs, steps = 40, 30
    rng = np.random.default_rng(8)
    values = []
    for _ in range(runs):
        truth, records = simulate_orbit(rng, steps)
        ukf = UnscentedKalmanFilter(Estimate(0.0, X0_ORBIT, P0_ORBIT), transition=gravity_transition,
                                    process_noise=FixedNoise(Q_ORBIT), model=BeaconRadec(BEACONS))
        for rec in records:
            assert ukf.update(rec).accepted
        values.append(nees(ukf.estimate.x - truth[-1], ukf.estimate.P))
    lo, hi = stats.chi2.ppf([0.005, 0.995], 6 * runs) / runs
    assert lo < np.mean(values) < hi


def test_chi_square_gate_rejects_outlier_and_keeps_prior():
    rng = np.random.default_rng(9)
    _, records = simulate_orbit(rng, 5)
    common = dict(transition=gravity_transition, process_noise=FixedNoise(Q_ORBIT), model=BeaconRadec(BEACONS))
    gated = UnscentedKalmanFilter(Estimate(0.0, X0_ORBIT, P0_ORBIT), options=UKFOptions(gate_probability=0.999), **common)
    for rec in records[:-1]:
        assert gated.update(rec).accepted
    last = records[-1]
    outlier = radec_record(last.t_tdb_s, last.value + np.array([100 * SIGMA_RADEC, 0.0]), last.target)
    out = gated.update(outlier)
    assert not out.accepted and "chi-square" in out.reason
    assert out.nis > stats.chi2.ppf(0.999, 2)
    assert out.estimate.x == pytest.approx(gated.estimate.x)


def test_bad_input_is_refused_with_clear_errors():
    with pytest.raises(InputError, match="alpha"):
        UKFOptions(alpha=0.0)
    with pytest.raises(InputError, match="gate_probability"):
        UKFOptions(gate_probability=1.5)
    with pytest.raises(InputError, match="kappa"):
        sigma_weights(3, UKFOptions(kappa=-5.0))
    ukf = UnscentedKalmanFilter(Estimate(100.0, X0_ORBIT, P0_ORBIT), transition=gravity_transition,
                                process_noise=FixedNoise(Q_ORBIT), model=BeaconRadec(BEACONS))
    with pytest.raises(InputError, match="backwards"):
        ukf.predict(0.0)
    late = ukf.update(radec_record(50.0, np.zeros(2), "a"))
    assert not late.accepted and "backwards" in late.reason
    nan = ukf.update(radec_record(200.0, np.array([np.nan, 0.0]), "a"))
    assert not nan.accepted and "NaN" in nan.reason
    with pytest.raises(Exception, match="estimate.P"):
        UnscentedKalmanFilter(Estimate(0.0, X0_ORBIT, -P0_ORBIT), transition=gravity_transition,
                              process_noise=FixedNoise(Q_ORBIT), model=BeaconRadec(BEACONS))
