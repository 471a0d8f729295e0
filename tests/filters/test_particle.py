"""Particle filters: resampling against filterpy, weights and N_eff, MH move, chi-square consistency."""

import numpy as np
import pytest
from filterpy.monte_carlo import resampling
from scipy import stats
from test_ukf import (
    BEACONS,
    P0_ORBIT,
    X0_ORBIT,
    BeaconRadec,
    FixedNoise,
    gravity_transition,
    nees,
    simulate_orbit,
)

from dataclasses import replace

from opnav.errors import InputError
from opnav.filters.base import Estimate
from opnav.filters.monitor import MonitorOptions, check_history
from opnav.filters.particle import (
    ParticleFilter,
    ParticleOptions,
    UnscentedParticleFilter,
    _close_upf_epoch,
    effective_sample_size,
    log_gaussian,
    sample_mixture,
    systematic_resample,
)
from opnav.filters.run import run_filter

# Process noise comparable to one record's information (the mechanics tests below).
Q_PF = np.diag([0.04, 0.04, 0.04, 1e-6, 1e-6, 1e-6])


def make_filter(kind, rng, n_particles, q=Q_PF, P0=P0_ORBIT, **options):
    common = dict(transition=gravity_transition, process_noise=FixedNoise(q), model=BeaconRadec(BEACONS),
                  rng=rng)
    if kind == "sir":
        return ParticleFilter(Estimate(0.0, X0_ORBIT, P0), options=ParticleOptions(n_particles=n_particles, **options),
                              **common)
    return UnscentedParticleFilter(Estimate(0.0, X0_ORBIT, P0),
                                   options=ParticleOptions(n_particles=n_particles, mcmc_move=kind == "mcmc-upf", **options),
                                   **common)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_systematic_resample_matches_filterpy_on_same_uniform(seed, monkeypatch):
    weights = np.random.default_rng(100 + seed).dirichlet(np.full(60, 0.3))
    u = np.random.default_rng(seed).random()
    monkeypatch.setattr(resampling, "random", lambda: u)
    expected = resampling.systematic_resample(weights)
    np.testing.assert_array_equal(systematic_resample(weights, np.random.default_rng(seed)), expected)


def test_systematic_resample_counts_are_within_one_of_n_w():
    rng = np.random.default_rng(3)
    weights = rng.dirichlet(np.ones(200))
    counts = np.bincount(systematic_resample(weights, rng), minlength=200)
    assert counts.sum() == 200
    assert np.all(np.abs(counts - 200 * weights) < 1.0 + 1e-12)


def test_effective_sample_size_limits():
    assert effective_sample_size(np.full(50, 1 / 50)) == pytest.approx(50.0)
    assert effective_sample_size(np.eye(1, 50)[0]) == pytest.approx(1.0)


def test_log_gaussian_matches_scipy():
    rng = np.random.default_rng(4)
    A = rng.standard_normal((4, 4))
    P = A @ A.T + np.eye(4)
    x = rng.standard_normal((7, 4))
    m = rng.standard_normal(4)
    np.testing.assert_allclose(log_gaussian(x, m, P), stats.multivariate_normal(m, P).logpdf(x), rtol=1e-12)
    batch = log_gaussian(x, np.broadcast_to(m, x.shape), np.broadcast_to(P, (7, 4, 4)))
    np.testing.assert_allclose(batch, stats.multivariate_normal(m, P).logpdf(x), rtol=1e-12)


# Near-deterministic dynamics, as in navigation: the process noise moves a state by metres a step
# while the prior is kilometres wide; the plain bootstrap and the sampling UPF collapse here.
Q_SMALL = np.diag([1e-6, 1e-6, 1e-6, 1e-10, 1e-10, 1e-10])


@pytest.mark.parametrize("kind,n_particles", [("sir", None), ("upf", None), ("mcmc-upf", None)])
def test_mean_nees_inside_chi_square_interval_with_near_deterministic_dynamics(kind, n_particles):
    """Final-epoch NEES over 20 seeded runs against chi2(6 runs)/runs, default particle counts
    (SIR 2000, the UPFs 150); every record accepted, the clouds never degenerate."""
    rng = np.random.default_rng(20)
    values = []
    for _ in range(20):
        truth, records = simulate_orbit(rng, 15, Q=Q_SMALL)
        pf = make_filter(kind, rng, n_particles, q=Q_SMALL)
        for rec in records:
            assert pf.update(rec).accepted
            assert pf.cloud.ess > 10.0
        values.append(nees(pf.estimate.x - truth[-1], pf.estimate.P))
    lo, hi = stats.chi2.ppf([0.005, 0.995], 6 * 20) / 20
    assert lo < np.mean(values) < hi, values


def test_unregularised_bootstrap_collapses_and_the_monitor_says_so():
    """A 100 km prior against ~2 km records: with regularisation and progressive correction off,
    150 SIR particles put all the weight on one or two at the first record; the history's N_eff
    shows it and the run is flagged unusable. The regularised filter passes the same records."""
    rng = np.random.default_rng(21)
    wide = np.diag([100.0**2] * 3 + [1e-6] * 3)
    truth, records = simulate_orbit(rng, 15, P0=wide, Q=Q_SMALL)
    collapsed = make_filter("sir", rng, 150, q=Q_SMALL, P0=wide, bandwidth_scale=0.0, correction_ess=0.0)
    history = run_filter(collapsed, records, progress=False)
    report = check_history(history, options=MonitorOptions(window=10))
    assert "particles_degenerate" in report.flags and report.min_ess < 3.0 and not report.usable
    regularised = make_filter("sir", np.random.default_rng(22), 150, q=Q_SMALL, P0=wide)
    history = run_filter(regularised, records, progress=False)
    report = check_history(history, options=MonitorOptions(window=10))
    assert report.usable and not report.flags, report.messages
    assert nees(regularised.estimate.x - truth[-1], regularised.estimate.P) < stats.chi2.ppf(0.999, 6)


def test_sample_mixture_keeps_the_estimate_moments():
    estimate = Estimate(0.0, X0_ORBIT, P0_ORBIT)
    cloud = sample_mixture(estimate, n_particles=40_000, fraction=0.8, rng=np.random.default_rng(22))
    np.testing.assert_allclose(cloud.covariances[0], 0.8 * P0_ORBIT)
    got = cloud.estimate
    sigma = np.sqrt(np.diag(P0_ORBIT))
    # sample mean within 5 standard errors; covariance to a few percent (40,000 draws)
    assert np.all(np.abs(got.x - X0_ORBIT) < 5 * sigma / np.sqrt(40_000))
    np.testing.assert_allclose(np.sqrt(np.diag(got.P)), sigma, rtol=0.02)


def test_upf_resampling_keeps_the_mixture_moments():
    """Closing an epoch with resampling replaces the components but not the mixture's mean and covariance."""
    rng = np.random.default_rng(23)
    n_p = 40_000
    start = sample_mixture(Estimate(0.0, X0_ORBIT, P0_ORBIT), n_particles=n_p, fraction=0.5, rng=rng)
    log_w = np.log(rng.dirichlet(np.full(n_p, 2.0)))
    cloud = replace(start, log_weights=log_w - np.log(np.exp(log_w).sum()))
    before = cloud.estimate
    options = ParticleOptions(n_particles=n_p, resample_fraction=1.0, mcmc_move=False, component_fraction=0.8)
    closed = _close_upf_epoch(cloud, model=BeaconRadec(BEACONS), options=options, rng=rng)
    assert closed.last_epoch.resampled
    after = closed.estimate
    sigma = np.sqrt(np.diag(before.P))
    assert np.all(np.abs(after.x - before.x) < 5 * sigma / np.sqrt(closed.last_epoch.ess))
    np.testing.assert_allclose(np.sqrt(np.diag(after.P)), sigma, rtol=0.03)


def test_mcmc_upf_weights_neff_and_move():
    rng = np.random.default_rng(30)
    _, records = simulate_orbit(rng, 8, Q=Q_PF)
    pf = make_filter("mcmc-upf", rng, 150, resample_fraction=0.9)
    moves = 0
    for i, rec in enumerate(records):
        out = pf.update(rec)
        assert out.accepted
        assert pf.weights.sum() == pytest.approx(1.0, abs=1e-12)
        assert np.all(pf.weights >= 0.0)
        if i % 2 == 1:  # both records of the epoch are in: closing it decides on resampling
            ess = effective_sample_size(pf.weights)
            weights_before = pf.weights.copy()
            pf.predict(rec.t_tdb_s + 60.0)
            diag = pf.last_epoch
            assert diag.ess == pytest.approx(ess)
            assert diag.resampled == (ess < 0.9 * 150)
            if diag.resampled:
                np.testing.assert_allclose(pf.weights, 1 / 150)
                assert diag.acceptance.shape == (150,)
                assert np.all((diag.acceptance > 0.0) & (diag.acceptance <= 1.0))
                # a candidate whose acceptance probability is 1 is always taken
                assert np.all(diag.accepted[diag.acceptance == 1.0])
                moves += int(diag.accepted.sum())
            else:
                np.testing.assert_allclose(pf.weights, weights_before)
    assert moves > 0


def test_no_resampling_when_neff_stays_high():
    rng = np.random.default_rng(31)
    _, records = simulate_orbit(rng, 2, Q=Q_PF)
    pf = make_filter("upf", rng, 50, resample_fraction=1e-6)
    for rec in records:
        pf.update(rec)
    pf.predict(records[-1].t_tdb_s + 60.0)
    assert not pf.last_epoch.resampled
    assert pf.last_epoch.acceptance.size == 0


def test_same_seed_same_run():
    outs = []
    for _ in range(2):
        rng = np.random.default_rng(40)
        _, records = simulate_orbit(rng, 3, Q=Q_PF)
        pf = make_filter("mcmc-upf", rng, 40)
        for rec in records:
            pf.update(rec)
        outs.append(pf.estimate.x)
    np.testing.assert_array_equal(outs[0], outs[1])


def test_bad_input():
    with pytest.raises(InputError, match="n_particles"):
        ParticleOptions(n_particles=1)
    with pytest.raises(InputError, match="resample_fraction"):
        ParticleOptions(resample_fraction=0.0)
    with pytest.raises(InputError, match="rng"):
        ParticleFilter(Estimate(0.0, X0_ORBIT, P0_ORBIT), transition=gravity_transition,
                       process_noise=FixedNoise(Q_PF), model=BeaconRadec(BEACONS), rng=np.random.RandomState(0),
                       options=ParticleOptions())
    pf = make_filter("upf", np.random.default_rng(0), 20)
    pf.predict(60.0)
    with pytest.raises(InputError, match="backwards"):
        pf.predict(0.0)
