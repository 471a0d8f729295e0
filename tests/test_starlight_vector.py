"""The vector ``starlight`` record: model, Jacobian, files, and why its cross-covariance matters (S3)."""

import numpy as np
import pytest
from scipy import stats
from test_fast_propagation import geo_state
from test_measurements import numeric_jacobian

from opnav.constants import ARCSEC_RAD
from opnav.dynamics import geo_model, propagate
from opnav.ephemeris.cache import default_cached_ephemeris
from opnav.epochs import parse_epoch
from opnav.errors import InputError
from opnav.filters.base import Estimate
from opnav.filters.ekf import ExtendedKalmanFilter, force_model_propagator
from opnav.filters.noise import WhiteAcceleration
from opnav.filters.run import nees, run_filter
from opnav.frames import radec_to_unit
from opnav.measurements import ProbeMeasurementModel, simulate_starlight, starlight_covariance
from opnav.records import Measurement, read_csv, write_csv

T0 = parse_epoch("2001-01-01T00:00:00", scale="utc")
STAR = radec_to_unit(np.deg2rad(30.0), np.deg2rad(10.0))
SIGMA_STAR, SIGMA_EARTH = 5.0 / 3.0 * ARCSEC_RAD, 20.0 / 3.0 * ARCSEC_RAD  # S3: 5" and 20" (3 sigma)
MODEL = ProbeMeasurementModel("earth", light_time=False, aberration=False)


def test_vector_record_is_the_two_scalars_with_their_jacobians():
    x = geo_state()
    cov = starlight_covariance(SIGMA_STAR, SIGMA_EARTH)
    vector = Measurement(T0, "starlight", [0.0, 0.0], cov, target="earth", star_unit_icrf=STAR)
    angle = Measurement(T0, "starlight_angle", [0.0], cov[:1, :1], target="earth", star_unit_icrf=STAR)
    elevation = Measurement(T0, "starlight_elevation", [0.0], cov[1:, 1:], target="earth", star_unit_icrf=STAR)
    np.testing.assert_array_equal(MODEL.predict(vector, x), np.concatenate([MODEL.predict(angle, x),
                                                                             MODEL.predict(elevation, x)]))
    jac = MODEL.jacobian(vector, x)
    steps = np.array([1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])
    numeric = numeric_jacobian(lambda s: MODEL.predict(vector, s), x, steps)
    np.testing.assert_allclose(jac, numeric, rtol=1e-6, atol=1e-6 * np.abs(jac).max())


def test_covariance_and_files_carry_the_correlation(tmp_path):
    cov = starlight_covariance(SIGMA_STAR, SIGMA_EARTH)
    # the angle's error is shared by the elevation, which adds the apparent-radius error
    assert cov[0, 1] == cov[0, 0] and cov[1, 1] == pytest.approx(cov[0, 0] + SIGMA_EARTH**2)
    records = simulate_starlight(MODEL, "earth", T0 + np.array([10.0, 20.0]), np.stack([geo_state()] * 2), STAR,
                                 sigma_star_rad=SIGMA_STAR, sigma_target_rad=SIGMA_EARTH,
                                 rng=np.random.default_rng(0))
    write_csv(tmp_path / "s3.csv", records)
    back = read_csv(tmp_path / "s3.csv")
    for a, b in zip(records, back):
        assert b.kind == "starlight"
        np.testing.assert_array_equal(a.value, b.value)
        np.testing.assert_array_equal(a.covariance, b.covariance)
    with pytest.raises(InputError, match="sensor sigmas"):
        starlight_covariance(SIGMA_STAR, 0.0)


@pytest.fixture(scope="module")
def s3_runs():
    """S3's first hour (one star, 10 s) for 8 seeds, each filtered from vector and from scalar records."""
    dynamics = geo_model(epoch_tdb_s=T0)
    epochs = T0 + 10.0 * np.arange(1, 361)
    truth = propagate(dynamics, T0, geo_state(), epochs).states
    model = ProbeMeasurementModel("earth", light_time=False, aberration=False, ephemeris=default_cached_ephemeris())
    P0 = np.diag([10.0**2] * 3 + [0.001**2] * 3)
    out = {True: [], False: []}
    for seed in range(8):
        for vector in (True, False):
            rng = np.random.default_rng(seed)
            records = simulate_starlight(MODEL, "earth", epochs, truth, STAR, sigma_star_rad=SIGMA_STAR,
                                         sigma_target_rad=SIGMA_EARTH, rng=rng, vector=vector)
            x0 = geo_state() + np.sqrt(np.diag(P0)) * rng.standard_normal(6)
            ekf = ExtendedKalmanFilter(Estimate(T0, x0, P0), propagator=force_model_propagator(dynamics), model=model,
                                       process_noise=WhiteAcceleration(1e-12))
            history = run_filter(ekf, records, progress=False)
            out[vector].append((history, truth[-1], model.jacobian(records[-1], truth[-1])))
    return out


def test_vector_records_are_consistent(s3_runs):
    runs = s3_runs[True]
    nis = np.concatenate([h.nis for h, _, _ in runs])
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], 2 * nis.size) / nis.size
    assert lo < nis.mean() < hi
    final = [nees(h.states[-1:], h.covariances[-1:], truth[None])[0] for h, truth, _ in runs]
    lo, hi = stats.chi2.ppf([0.005, 0.995], 6 * len(runs)) / len(runs)
    assert lo < np.mean(final) < hi


def test_scalar_records_count_the_shared_error_twice():
    """One epoch from a broad prior: the scalar pair (same marginal variances, no cross term) claims
    the angle's information twice over, ``1/a + 1/(a + e)`` along the angle gradient where the pair
    holds ``1/a``, and under-weights the elevation's own range information (``1/(a + e)`` for ``1/e``).
    Over S3's first hour (the fixture above) the two errors cancel in the 6-state NEES, which is
    why this is shown on the information itself."""
    x = geo_state()
    cov = starlight_covariance(SIGMA_STAR, SIGMA_EARTH)
    a, e = cov[0, 0], cov[1, 1] - cov[0, 0]
    vector = Measurement(T0, "starlight", MODEL.predict(Measurement(T0, "starlight", [0, 0], cov, target="earth",
                                                                     star_unit_icrf=STAR), x), cov,
                         target="earth", star_unit_icrf=STAR)
    H = MODEL.jacobian(vector, x)[:, :3]
    info_vector = H.T @ np.linalg.inv(cov) @ H
    info_scalar = np.outer(H[0], H[0]) / cov[0, 0] + np.outer(H[1], H[1]) / cov[1, 1]
    h = H[0] / np.linalg.norm(H[0])
    g = (H[1] - H[0]) / np.linalg.norm(H[1] - H[0])  # the apparent radius' gradient: range
    ratio_h = (h @ info_scalar @ h) / (h @ info_vector @ h)
    assert ratio_h == pytest.approx(1.0 + a / (a + e), rel=0.02)  # 1.52: over-confident
    ratio_g = (g @ info_scalar @ g) / (g @ info_vector @ g)
    assert ratio_g < 0.6  # e / (a + e) = 0.48 of the range information is used
