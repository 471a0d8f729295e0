"""Particle filters: regularised SIR, unscented particle filter (UPF) and the MCMC-UPF of S3.

All three keep ``N`` weighted particles ``x_i`` (state units, frame/origin of
the transition; see :mod:`opnav.filters.base`) and share the interface of
:mod:`opnav.filters.base`.

Why regularisation. Spacecraft dynamics are nearly deterministic (the process
noise ``Q`` of S3 moves a particle by metres a step) while one record can be far
narrower than the cloud (S1 starts with 5000 km of prior and sees each moon to a
few km). A plain bootstrap filter then puts all the weight on one particle at
the first record, resampling duplicates it, ``Q`` cannot spread the copies
again, and the cloud's covariance collapses to zero while the filter goes on
reporting it (4,800 km off with a 1-sigma of 0.016 km on the demo, before this
module was rewritten). The cure in the literature, used here:

- **Kernel regularisation with shrinkage** (Musso, Oudjane & Le Gland 2001,
  "Improving regularised particle filters", in Doucet et al., *Sequential Monte
  Carlo Methods in Practice*; Liu & West 2001, same book): the weighted cloud
  stands for the density ``sum_i w_i N(x; a x_i + (1 - a) xbar, h^2 Sigma)``,
  with ``xbar, Sigma`` the cloud's weighted mean and covariance, Musso's optimal
  Gaussian bandwidth ``h = A N^(-1/(n+4))``, ``A = (4/(n+2))^(1/(n+4))``
  (times ``ParticleOptions.bandwidth_scale``), and ``a = sqrt(1 - h^2)``, so the
  density keeps the cloud's mean and covariance exactly. Drawing from it
  replaces duplicates by distinct particles without inflating the spread.
- **Progressive correction** (Oudjane & Musso 2000; Musso et al. 2001, sec. 12.5)
  for SIR: a record's likelihood ``L`` is applied as ``L^l1, L^l2, ...``
  (``sum l = 1``), each exponent the largest that keeps ``N_eff >=
  correction_ess * N``, with a regularised resample between the stages, so
  the cloud contracts onto a narrow likelihood instead of collapsing onto one
  particle.

Per epoch ``t_k``:

SIR (regularised bootstrap)
    1. close the previous epoch: if ``N_eff < resample_fraction * N`` resample
       (systematic) and draw each particle from its parent's kernel;
    2. ``x_i <- f(x_i) + w_i``, ``w_i ~ N(0, Q)`` (all particles in one transition call);
    3. each record at ``t_k`` reweights by its likelihood, progressively.

UPF: each particle carries a UKF (S3: "each particle carries a UKF")
    The particle is the Gaussian ``N(m_i, C_i)``, the cloud their mixture
    (the Gaussian-sum particle filter of Kotecha & Djuric 2003, with the
    sigma-point components of van der Merwe & Wan 2003):

    1. close the previous epoch: if ``N_eff < resample_fraction * N``, resample
       the components (systematic), draw one point from each parent (for the
       MCMC-UPF a Metropolis–Hastings step, below) and make the points new
       components ``N(a x + (1 - a) xbar, f Sigma)``, ``f = component_fraction``,
       ``a = sqrt(1 - f)``, which keeps the mixture's mean ``xbar`` and
       covariance ``Sigma`` (the same shrinkage as above, with ``h^2 = f``);
    2. one unscented time update per component, all ``N (2n+1)`` sigma points
       through the transition in ONE call, plus ``Q``;
    3. each record updates every component (batched unscented update) and
       multiplies its weight by the component's predictive likelihood
       ``N(nu_i; 0, S_i)``.

    Why not the sampling UPF of van der Merwe, Doucet, de Freitas & Wan (2000),
    which draws a new point from each particle's UKF proposal every epoch and
    weighs it by ``p(z | x) p(x | x_prev) / q(x)``: with near-deterministic
    dynamics ``p(x | x_prev)`` is ``Q`` wide, so either the proposal is as
    narrow and the cloud cannot move (opnav's earlier form: 31-40 km off on S3
    with a 1-sigma of 0.01 km), or it is wider and the weights collapse (N_eff
    2-20 of 150). Even with regularised proposals, each epoch's fresh draws add
    Monte Carlo error ``Sigma / N`` to the mean while the posterior keeps
    shrinking: measured on S3 with 150 particles, NEES ~10^6 after 2000 steps.
    The Gaussian-sum form adds Monte Carlo error only when it resamples (a
    handful of times an arc: N_eff falls as the components disagree, not every
    epoch). ``component_fraction`` 0.8 keeps N_eff high with 150 particles on
    S3 (measured: 3 resamples in 2000 steps against 15 with Musso's
    bandwidth, ``f`` = 0.32, whose mixture was too tight, NEES 12). The UPF's
    ``Q`` may be singular (it is a covariance added to each component, not a density).

MCMC-UPF (S3; Gilks & Berzuini 2001 resample-move)
    The point drawn from a resampled parent ``j`` is a Metropolis–Hastings
    step from the parent's mean ``m_j`` towards the component's exact
    posterior ``p(z_k | x) N(x; xbar_j, Pbar_j)`` (``xbar_j, Pbar_j``: its
    prior at the epoch), with the UKF posterior ``N(m_j, C_j)`` as
    independence proposal: the candidate ``x* ~ N(m_j, C_j)`` is taken with
    probability ``min(1, r(x*) / r(m_j))``, ``r = p(z_k | .) N(.; xbar_j, Pbar_j)
    / N(.; m_j, C_j)``, which corrects the UKF's Gaussian approximation where
    the measurement is nonlinear over the component.

Honesty. Every cloud carries its ``N_eff``; :class:`EpochDiagnostics` records it
with the number of correction stages, and :mod:`opnav.filters.monitor` turns a
history into consistency flags (a collapsed cloud, NIS out of its band).

The state of each filter is a frozen :class:`ParticleCloud` (epoch, particles,
log-weights, the records of the current epoch and, for the UPF, the component
covariances and their priors at the epoch, :class:`ComponentPriors`); its
``estimate`` is the weighted mean and covariance of the particles (of the
mixture, for the UPF). :func:`sample_cloud`, :func:`sample_mixture`,
:func:`sir_predict`, :func:`sir_update`, :func:`upf_predict` and
:func:`upf_update` are the pure core;
:class:`ParticleFilter` and :class:`UnscentedParticleFilter` only hold the models,
the generator and the current cloud. Randomness only comes from the
``numpy.random.Generator`` passed in.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.special import logsumexp

from ..errors import InputError
from ..records import Measurement
from .base import (
    Estimate,
    MeasurementModel,
    UpdateOutcome,
    check_epoch,
    check_estimate,
    discrete_noise,
    gate_refusal,
    measurement_covariance,
    psd_sqrt,
    refuse_unusable,
    rejected,
    screen_record,
)
from .noise import ProcessNoise
from .option_types import ParticleOptions
from .ukf import (
    SigmaWeights,
    Transition,
    sigma_weights,
    ukf_predict,
    ukf_update,
)


def systematic_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices of a systematic resample of normalised ``weights`` (N,), one uniform draw from ``rng``.

    Same algorithm as ``filterpy.monte_carlo.systematic_resample`` (positions
    ``(u + arange(N)) / N`` against the cumulative weights) but without
    filterpy's global ``np.random``.
    """
    weights = np.asarray(weights, dtype=float)
    n = weights.size
    positions = (rng.random() + np.arange(n)) / n
    index = np.searchsorted(np.cumsum(weights), positions, side="right")
    # the cumulative sum can end a rounding error below 1
    return np.minimum(index, n - 1)


def effective_sample_size(weights: np.ndarray) -> float:
    """``N_eff = 1 / sum w_i^2`` of normalised weights."""
    weights = np.asarray(weights, dtype=float)
    return float(1.0 / np.sum(weights**2))


def log_gaussian(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Log density of ``N(mean, cov)`` at ``x``; ``x``, ``mean`` (..., n), ``cov`` (n, n) or (..., n, n)."""
    L = np.linalg.cholesky(cov)
    diff = np.asarray(x, dtype=float) - mean
    if L.ndim == 2:
        y = np.linalg.solve(L, diff.reshape(-1, diff.shape[-1]).T).T.reshape(diff.shape)
        log_det = np.sum(np.log(np.diag(L)))
    else:
        y = np.linalg.solve(L, diff[..., None])[..., 0]
        log_det = np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
    n = diff.shape[-1]
    return -0.5 * np.sum(y * y, axis=-1) - log_det - 0.5 * n * np.log(2.0 * np.pi)


def log_likelihood(records: Sequence[Measurement], model: MeasurementModel, X: np.ndarray) -> np.ndarray:
    """Sum over ``records`` of ``log p(z | x)`` for states X (K, n).

    Gaussian with ``R`` from :func:`opnav.filters.base.measurement_covariance` (the
    model's ``noise_covariance`` at the first state, else the record's covariance).
    """
    total = np.zeros(X.shape[0])
    for record in records:
        nu = model.residual(record, model.predict(record, X))
        total += log_gaussian(nu, np.zeros(record.size), measurement_covariance(model, record, X[0]))
    return total


def _weighted_moments(X: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean = w @ X
    d = X - mean
    return mean, (d * w[:, None]).T @ d


#: SIR's default particle count. Measured on the demo's 89 records (5000 km prior, 0.03-0.05"
#: moons): 150 particles end 3.5 sigma off with half the EKF's sigma, 1000 inside 1 sigma,
#: 5000 within 15 km of the EKF with its sigma.
SIR_PARTICLES = 2000
#: The UPFs' default (S3's 150): each particle carries a UKF, so few are needed.
UPF_PARTICLES = 150


def kernel_bandwidth(n_particles: int, n_state: int) -> float:
    """Musso et al.'s optimal Gaussian-kernel bandwidth ``h = (4/(n+2))^(1/(n+4)) N^(-1/(n+4))``.

    Optimal (mean integrated squared error) for a Gaussian density; 0.566 for 150 particles
    of a 6-state.
    """
    return (4.0 / (n_state + 2)) ** (1.0 / (n_state + 4)) * n_particles ** (-1.0 / (n_state + 4))


def shrinkage_kernel(particles: np.ndarray, weights: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Centres ``a x_i + (1 - a) xbar`` (N, n) and covariance ``h^2 Sigma`` (n, n) of the regularised density;
    units, frame and origin those of the particles (N, n).

    ``xbar``/``Sigma`` are the weighted mean and covariance of the particles, ``h`` is
    ``scale`` times :func:`kernel_bandwidth` and ``a = sqrt(1 - h^2)``, so the mixture
    ``sum_i w_i N(centre_i, h^2 Sigma)`` has the cloud's mean and covariance (Liu & West 2001).

    Raises
    ------
    InputError
        If the scaled bandwidth reaches 1 (the shrinkage would reverse the cloud).
    """
    n_p, n = particles.shape
    h = scale * kernel_bandwidth(n_p, n)
    if h >= 1.0:
        raise InputError(f"ParticleOptions.bandwidth_scale={scale} gives a kernel bandwidth {h:.3f} >= 1 for "
                         f"{n_p} particles; use a smaller scale")
    mean, cov = _weighted_moments(particles, weights)
    a = np.sqrt(1.0 - h * h)
    return a * particles + (1.0 - a) * mean, (h * h) * 0.5 * (cov + cov.T)


@dataclass(frozen=True)
class EpochDiagnostics:
    """What happened when an epoch was closed.

    ``ess`` is N_eff before resampling; ``acceptance`` holds each particle's
    Metropolis–Hastings acceptance probability ``min(1, r*/r)`` (empty when no
    move was made) and ``accepted`` whether its candidate was taken;
    ``corrections`` counts the progressive-correction stages the epoch's
    records needed beyond the first (SIR; 0 when each likelihood went in at once).
    """

    t_tdb_s: float
    ess: float
    resampled: bool
    acceptance: np.ndarray
    accepted: np.ndarray
    corrections: int = 0


@dataclass(frozen=True)
class ComponentPriors:
    """UPF: each particle's prior component ``N(mean_i, cov_i)`` at the current epoch (before its records).

    The Metropolis–Hastings move of the MCMC-UPF targets ``p(z_k | x) N(x; mean_j, cov_j)``.
    """

    mean: np.ndarray
    cov: np.ndarray


@dataclass(frozen=True)
class ParticleCloud:
    """Weighted particles at an epoch: the state of the particle filters.

    Attributes
    ----------
    t_tdb_s : float
        TDB seconds past J2000.
    particles : (N, n) array
        States (units, frame and origin of the transition).
    log_weights : (N,) array
        Normalised log-weights (``logsumexp(log_weights) = 0``).
    records : tuple of Measurement
        The records at ``t_tdb_s`` already weighed in (their joint likelihood enters the UPF
        weights and the MCMC move).
    covariances : (N, n, n) array or None
        UPF only: each particle's UKF covariance (the particle is the Gaussian
        ``N(particles_i, covariances_i)``); ``None`` for SIR's point particles.
    priors : ComponentPriors or None
        UPF only: the components' priors at this epoch; ``None`` for SIR and before the first transition.
    last_epoch : EpochDiagnostics or None
        What closing the previous epoch did; ``None`` before the first transition.
    corrections : int
        Progressive-correction stages beyond the first taken by this epoch's records so far.
    """

    t_tdb_s: float
    particles: np.ndarray
    log_weights: np.ndarray
    records: tuple[Measurement, ...] = ()
    covariances: np.ndarray | None = None
    priors: ComponentPriors | None = None
    last_epoch: EpochDiagnostics | None = None
    corrections: int = 0

    @property
    def weights(self) -> np.ndarray:
        """Normalised weights (N,)."""
        return np.exp(self.log_weights)

    @property
    def ess(self) -> float:
        """Effective sample size ``1 / sum w^2`` of the current weights."""
        return effective_sample_size(self.weights)

    @property
    def estimate(self) -> Estimate:
        """Gaussian summary: the weighted mean and covariance of the particles (of the mixture, for the UPF)."""
        w = self.weights
        mean, cov = _weighted_moments(self.particles, w)
        if self.covariances is not None:
            cov = cov + np.einsum("k,kij->ij", w, self.covariances)
        return Estimate(self.t_tdb_s, mean, 0.5 * (cov + cov.T))


def sample_cloud(estimate: Estimate, *, n_particles: int, rng: np.random.Generator) -> ParticleCloud:
    """``n_particles`` equally weighted draws from ``N(estimate.x, estimate.P)`` at the estimate's epoch.

    Raises
    ------
    InputError, CovarianceError
        If ``estimate`` is not a finite state with a finite SPD covariance of matching size.
    """
    checked = check_estimate(estimate)
    particles = checked.x + rng.standard_normal((n_particles, checked.x.size)) @ np.linalg.cholesky(checked.P).T
    return ParticleCloud(checked.t_tdb_s, particles, np.full(n_particles, -np.log(n_particles)))


def sample_mixture(estimate: Estimate, *, n_particles: int, fraction: float, rng: np.random.Generator
                   ) -> ParticleCloud:
    """UPF start: ``n_particles`` equally weighted Gaussians whose mixture has the estimate's mean and covariance.

    Draws ``x_i ~ N(x, P)`` and makes them the components ``N(a x_i + (1 - a) x, f P)``,
    ``f = fraction``, ``a = sqrt(1 - f)`` (the shrinkage kernel of Liu & West 2001 with ``h^2 = f``).

    Raises
    ------
    InputError, CovarianceError
        If ``estimate`` is not a finite state with a finite SPD covariance.
    """
    cloud = sample_cloud(estimate, n_particles=n_particles, rng=rng)
    a = np.sqrt(1.0 - fraction)
    centres = a * cloud.particles + (1.0 - a) * estimate.x
    P = check_estimate(estimate).P
    return replace(cloud, particles=centres, covariances=np.repeat((fraction * P)[None], n_particles, axis=0))


def _regularised_resample(particles: np.ndarray, log_weights: np.ndarray, *, scale: float,
                          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Systematic resample, then each copy drawn from its parent's shrinkage kernel: (particles, parents).

    With ``scale`` 0 the copies stay duplicates (plain resampling).
    """
    weights = np.exp(log_weights)
    parents = systematic_resample(weights, rng)
    if scale == 0.0:
        return particles[parents], parents
    centres, kernel = shrinkage_kernel(particles, weights, scale)
    root = psd_sqrt(kernel, "particle cloud covariance")
    return centres[parents] + rng.standard_normal(particles.shape) @ root.T, parents


def _resample(cloud: ParticleCloud, *, options: ParticleOptions, rng: np.random.Generator, regularise: bool
              ) -> tuple[ParticleCloud, float, np.ndarray | None]:
    """Resample if ``N_eff < resample_fraction * N``: (cloud, N_eff before, parent indices or ``None``).

    ``regularise`` draws each copy from its parent's kernel (SIR); the UPF regularises every
    epoch in its time update instead.
    """
    ess = cloud.ess
    n_p = cloud.particles.shape[0]
    if ess >= options.resample_fraction * n_p:
        return cloud, ess, None
    scale = options.bandwidth_scale if regularise else 0.0
    particles, parents = _regularised_resample(cloud.particles, cloud.log_weights, scale=scale, rng=rng)
    return replace(cloud, particles=particles, log_weights=np.full(n_p, -np.log(n_p))), ess, parents


def _normalised(log_weights: np.ndarray) -> np.ndarray | None:
    """``log_weights`` normalised to ``logsumexp = 0``, or ``None`` if every weight is zero."""
    total = logsumexp(log_weights)
    if not np.isfinite(total):
        return None
    return log_weights - total


def _ess_of(log_weights: np.ndarray) -> float:
    return effective_sample_size(np.exp(log_weights - logsumexp(log_weights)))


def _largest_exponent(log_weights: np.ndarray, log_lik: np.ndarray, remaining: float, target: float) -> float:
    """Largest ``l`` in (0, remaining] with ``N_eff(w L^l) >= target`` (bisection; N_eff falls with ``l``)."""
    if _ess_of(log_weights + remaining * log_lik) >= target:
        return remaining
    lo, hi = 0.0, remaining
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if _ess_of(log_weights + mid * log_lik) >= target:
            lo = mid
        else:
            hi = mid
    # progress is guaranteed: right after a resample N_eff(l -> 0) = N > target
    return max(lo, 1e-6 * remaining)


def _predictive(cloud: ParticleCloud, record: Measurement, model: MeasurementModel
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted innovation mean (m,), its covariance (particle spread + R) and NIS for ``record``."""
    nu = model.residual(record, model.predict(record, cloud.particles))
    mean, cov = _weighted_moments(nu, cloud.weights)
    S = 0.5 * (cov + cov.T) + measurement_covariance(model, record, cloud.particles[0])
    return mean, S, float(mean @ np.linalg.solve(S, mean))


def _screen(cloud: ParticleCloud, record: Measurement, model: MeasurementModel, gate_probability: float | None
            ) -> tuple[UpdateOutcome | None, tuple[np.ndarray, np.ndarray, float] | None]:
    """Refuse a bad, mistimed or gated record: (refusal or ``None``, predictive (residual, S, NIS) once formed)."""
    prior = cloud.estimate
    refusal = screen_record(prior, record)
    if refusal is not None:
        return refusal, None
    residual, S, nis = _predictive(cloud, record, model)
    return gate_refusal(prior, record, residual=residual, residual_cov=S, nis=nis,
                        probability=gate_probability), (residual, S, nis)


def _weigh(cloud: ParticleCloud, record: Measurement, model: MeasurementModel, residual: np.ndarray, S: np.ndarray,
           nis: float, *, options: ParticleOptions, rng: np.random.Generator) -> tuple[ParticleCloud, UpdateOutcome]:
    """Apply the likelihood of ``record`` by progressive correction and keep it among the epoch's records.

    Stages: reweight by ``L^l`` with the largest ``l`` keeping ``N_eff >= correction_ess * N``,
    then (if some likelihood is left) a regularised resample; the likelihood is re-evaluated
    at the moved particles.
    """
    particles, log_weights = cloud.particles, cloud.log_weights
    n_p = particles.shape[0]
    target = options.correction_ess * n_p
    remaining, stages = 1.0, 0
    while True:
        log_lik = log_likelihood([record], model, particles)
        if not np.any(np.isfinite(log_lik) & np.isfinite(log_weights)):
            return cloud, rejected(cloud.estimate, record.size, "every particle has zero likelihood", record)
        last_stage = target == 0.0 or stages >= options.max_corrections
        step = remaining if last_stage else _largest_exponent(log_weights, log_lik, remaining, target)
        log_weights = _normalised(log_weights + step * log_lik)
        if log_weights is None:
            return cloud, rejected(cloud.estimate, record.size, "every particle has zero likelihood", record)
        remaining -= step
        if remaining <= 1e-12:
            break
        stages += 1
        particles, _ = _regularised_resample(particles, log_weights, scale=options.bandwidth_scale, rng=rng)
        log_weights = np.full(n_p, -np.log(n_p))
    weighed = replace(cloud, particles=particles, log_weights=log_weights, records=cloud.records + (record,),
                      corrections=cloud.corrections + stages)
    return weighed, UpdateOutcome(weighed.estimate, residual, S, nis, True)


def sir_predict(
    cloud: ParticleCloud,
    t_tdb_s: float,
    *,
    transition: Transition,
    process_noise: ProcessNoise | None,
    options: ParticleOptions,
    rng: np.random.Generator,
) -> ParticleCloud:
    """Close the cloud's epoch (regularised resample if N_eff is low), then move every particle to ``t_tdb_s``.

    Parameters
    ----------
    cloud : ParticleCloud
    t_tdb_s : float
        Target epoch, TDB seconds past J2000; at the cloud's epoch the cloud is returned unchanged.
    transition : Transition
        ``f(t0, X (N, n), t1)``; all particles in one call.
    process_noise : ProcessNoise or None
        :mod:`opnav.filters.noise` model for the first six states, evaluated at the first
        particle; ``w_i ~ N(0, Q)`` is added after the transition.
    options : ParticleOptions
        ``resample_fraction`` and ``bandwidth_scale`` are used.
    rng : numpy.random.Generator
        One uniform and ``N n`` normals if resampling, then ``N n`` normals.

    Returns
    -------
    ParticleCloud
        At ``t_tdb_s``, with no records yet and ``last_epoch`` describing the closed epoch.

    Raises
    ------
    InputError
        If ``t_tdb_s`` is not finite or lies before the cloud's epoch.
    CovarianceError
        If the process noise is not positive semi-definite.
    """
    check_epoch(cloud.t_tdb_s, t_tdb_s)
    if not t_tdb_s > cloud.t_tdb_s:
        return cloud
    closed, ess, parents = _resample(cloud, options=options, rng=rng, regularise=True)
    diagnostics = EpochDiagnostics(cloud.t_tdb_s, ess, parents is not None, np.zeros(0), np.zeros(0, bool),
                                   cloud.corrections)
    root = psd_sqrt(discrete_noise(process_noise, cloud.t_tdb_s, t_tdb_s, closed.particles[0]), "process noise Q")
    moved = np.asarray(transition(cloud.t_tdb_s, closed.particles, t_tdb_s), dtype=float)
    particles = moved + rng.standard_normal(moved.shape) @ root.T
    return ParticleCloud(float(t_tdb_s), particles, closed.log_weights, last_epoch=diagnostics)


def sir_update(
    cloud: ParticleCloud,
    record: Measurement,
    *,
    model: MeasurementModel,
    options: ParticleOptions,
    rng: np.random.Generator,
) -> tuple[ParticleCloud, UpdateOutcome]:
    """Weight the particles by the likelihood of ``record`` (at the cloud's epoch), progressively.

    Parameters
    ----------
    cloud : ParticleCloud
        At ``record.t_tdb_s`` (predict first).
    record : Measurement
    model : MeasurementModel
        Vectorised measurement model; the likelihood is Gaussian with ``R`` of
        :func:`opnav.filters.base.measurement_covariance`.
    options : ParticleOptions
        ``gate_probability``, ``correction_ess``, ``max_corrections`` and ``bandwidth_scale``.
    rng : numpy.random.Generator
        For the resamples between correction stages.

    Returns
    -------
    cloud : ParticleCloud
        Reweighted (and, after correction stages, moved), or the input when the record is refused.
    outcome : UpdateOutcome
        Cloud estimate, predictive innovation mean (m,) and covariance (particle spread + R),
        NIS, accepted flag and reason. Refused: bad values, another epoch, the chi-square gate,
        or zero likelihood for every particle.
    """
    refusal, predictive = _screen(cloud, record, model, options.gate_probability)
    if refusal is not None:
        return cloud, refusal
    return _weigh(cloud, record, model, *predictive, options=options, rng=rng)


def _component_log_target(X: np.ndarray, records: tuple[Measurement, ...], model: MeasurementModel,
                          priors: ComponentPriors) -> np.ndarray:
    """``log[p(z_k | x_i) N(x_i; mean_i, cov_i)]`` (unnormalised component posterior) of X (N, n)."""
    return log_likelihood(records, model, X) + log_gaussian(X, priors.mean, priors.cov)


def _close_upf_epoch(cloud: ParticleCloud, *, model: MeasurementModel, options: ParticleOptions,
                     rng: np.random.Generator) -> ParticleCloud:
    """If N_eff is low: resample the components, draw a point from each parent, regularise.

    The point is a draw from the parent's UKF posterior ``N(m_j, C_j)``; for the MCMC-UPF it is
    a Metropolis–Hastings step from ``m_j`` towards the parent's exact posterior
    ``p(z_k | x) N(x; prior_j)`` with ``N(m_j, C_j)`` as independence proposal (Gilks &
    Berzuini 2001), which corrects the UKF's Gaussian approximation. The points then become
    the components ``N(a x + (1 - a) xbar, f Sigma)``, ``f = component_fraction``,
    ``a = sqrt(1 - f)``, ``xbar`` and ``Sigma`` being the mixture's moments before
    resampling, so the mixture keeps them.
    """
    ess = cloud.ess
    n_p = cloud.particles.shape[0]
    empty = np.zeros(0), np.zeros(0, dtype=bool)
    if ess >= options.resample_fraction * n_p:
        return replace(cloud, last_epoch=EpochDiagnostics(cloud.t_tdb_s, ess, False, *empty))
    before = cloud.estimate
    parents = systematic_resample(cloud.weights, rng)
    mean, cov = cloud.particles[parents], cloud.covariances[parents]
    draws = mean + np.einsum("kij,kj->ki", np.linalg.cholesky(cov), rng.standard_normal(mean.shape))
    acceptance, accepted = empty
    if options.mcmc_move and cloud.priors is not None and cloud.records:
        priors = ComponentPriors(cloud.priors.mean[parents], cloud.priors.cov[parents])

        def log_ratio(X):
            return _component_log_target(X, cloud.records, model, priors) - log_gaussian(X, mean, cov)

        log_alpha = log_ratio(draws) - log_ratio(mean)
        acceptance = np.exp(np.minimum(log_alpha, 0.0))
        accepted = rng.random(n_p) < acceptance
        draws = np.where(accepted[:, None], draws, mean)
    fraction = options.component_fraction
    a = np.sqrt(1.0 - fraction)
    centres = a * draws + (1.0 - a) * before.x
    diagnostics = EpochDiagnostics(cloud.t_tdb_s, ess, True, acceptance, accepted)
    return replace(cloud, particles=centres, covariances=np.repeat((fraction * before.P)[None], n_p, axis=0),
                   log_weights=np.full(n_p, -np.log(n_p)), last_epoch=diagnostics)


def upf_predict(
    cloud: ParticleCloud,
    t_tdb_s: float,
    *,
    transition: Transition,
    process_noise: ProcessNoise | None,
    model: MeasurementModel,
    options: ParticleOptions,
    weights: SigmaWeights,
    rng: np.random.Generator,
) -> ParticleCloud:
    """Close the cloud's epoch (resample, MCMC move, regularise), then run every particle's unscented time update.

    Parameters
    ----------
    cloud : ParticleCloud
        With component covariances (:func:`sample_mixture`).
    t_tdb_s : float
        Target epoch, TDB seconds past J2000; at the cloud's epoch the cloud is returned unchanged.
    transition : Transition
        All ``N (2n+1)`` sigma points in one call.
    process_noise : ProcessNoise or None
        :mod:`opnav.filters.noise` model, evaluated at the cloud's mean.
    model : MeasurementModel
        For the likelihood of the closed epoch's records in the MCMC move.
    options : ParticleOptions
        ``resample_fraction``, ``mcmc_move`` and ``bandwidth_scale``.
    weights : SigmaWeights
        ``sigma_weights(n, options.ukf)``.
    rng : numpy.random.Generator
        One uniform, ``N n`` normals and (MCMC) ``N`` uniforms when resampling.

    Returns
    -------
    ParticleCloud
        At ``t_tdb_s``, the components' priors recorded, no records yet.

    Raises
    ------
    InputError
        If ``t_tdb_s`` is not finite or lies before the cloud's epoch.
    CovarianceError
        If the process noise is not positive semi-definite.
    """
    check_epoch(cloud.t_tdb_s, t_tdb_s)
    if not t_tdb_s > cloud.t_tdb_s:
        return cloud
    closed = _close_upf_epoch(cloud, model=model, options=options, rng=rng)
    Q = discrete_noise(process_noise, closed.t_tdb_s, t_tdb_s, closed.estimate.x)
    psd_sqrt(Q, "process noise Q")  # raises for an indefinite Q
    xbar, Pbar, _ = ukf_predict(closed.particles, closed.covariances, closed.t_tdb_s, t_tdb_s, transition=transition,
                                Q=Q, weights=weights)
    return ParticleCloud(float(t_tdb_s), xbar, closed.log_weights, covariances=Pbar, priors=ComponentPriors(xbar, Pbar),
                         last_epoch=closed.last_epoch)


def upf_update(
    cloud: ParticleCloud,
    record: Measurement,
    *,
    model: MeasurementModel,
    options: ParticleOptions,
    weights: SigmaWeights,
) -> tuple[ParticleCloud, UpdateOutcome]:
    """Update every particle's UKF with ``record`` (at the cloud's epoch) and reweight by its predictive likelihood.

    Parameters
    ----------
    cloud : ParticleCloud
        At ``record.t_tdb_s`` (predict first), with component covariances.
    record : Measurement
    model : MeasurementModel
        Vectorised measurement model.
    options : ParticleOptions
        ``gate_probability`` is used.
    weights : SigmaWeights
        ``sigma_weights(n, options.ukf)``.

    Returns
    -------
    cloud : ParticleCloud
        Updated components and weights ``w_i ∝ w_i N(nu_i; 0, S_i)``, or the input when the record
        is refused.
    outcome : UpdateOutcome
        Mixture estimate, the mixture's innovation mean (m,) and covariance
        ``sum w_i (S_i + (nu_i - nu)(nu_i - nu)^T)``, NIS, accepted flag and reason. Refused:
        bad values, another epoch, the chi-square gate, a non-positive-definite innovation
        covariance, or zero likelihood for every particle.
    """
    prior = cloud.estimate
    refusal = screen_record(prior, record)
    if refusal is not None:
        return cloud, refusal
    try:
        post = ukf_update(cloud.particles, cloud.covariances, record, model=model, weights=weights)
    except np.linalg.LinAlgError:
        return cloud, rejected(prior, record.size, "a particle's innovation covariance is not positive definite",
                               record)
    w = cloud.weights
    residual, spread = _weighted_moments(post.residual, w)
    S = np.einsum("k,kij->ij", w, post.S) + spread
    S = 0.5 * (S + S.T)
    nis = float(residual @ np.linalg.solve(S, residual))
    refusal = gate_refusal(prior, record, residual=residual, residual_cov=S, nis=nis,
                           probability=options.gate_probability)
    if refusal is not None:
        return cloud, refusal
    log_weights = _normalised(cloud.log_weights + log_gaussian(post.residual, np.zeros(record.size), post.S))
    if log_weights is None:
        return cloud, rejected(prior, record.size, "every particle has zero likelihood", record)
    updated = replace(cloud, particles=post.x, covariances=post.P, log_weights=log_weights,
                      records=cloud.records + (record,))
    return updated, UpdateOutcome(updated.estimate, residual, S, nis, True)


class _ParticleFilterBase:
    """Models, generator and current cloud common to :class:`ParticleFilter` and :class:`UnscentedParticleFilter`."""

    def __init__(
        self,
        estimate: Estimate,
        *,
        transition: Transition,
        process_noise: ProcessNoise | None,
        model: MeasurementModel,
        rng: np.random.Generator,
        options: ParticleOptions,
    ) -> None:
        if not isinstance(rng, np.random.Generator):
            raise InputError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        self.transition = transition
        self.process_noise = process_noise
        self.model = model
        self.rng = rng
        self.options = options
        self.cloud = self._start(estimate)

    def _start(self, estimate: Estimate) -> ParticleCloud:
        return sample_cloud(estimate, n_particles=int(self.options.n_particles or SIR_PARTICLES), rng=self.rng)

    @property
    def estimate(self) -> Estimate:
        return self.cloud.estimate

    @property
    def weights(self) -> np.ndarray:
        """Normalised weights (N,)."""
        return self.cloud.weights

    @property
    def last_epoch(self) -> EpochDiagnostics | None:
        """What closing the previous epoch did (``None`` before the first prediction)."""
        return self.cloud.last_epoch


class ParticleFilter(_ParticleFilterBase):
    """Regularised bootstrap (SIR) particle filter with progressive correction; holds the models and a
    :class:`ParticleCloud` (module notes).

    Parameters
    ----------
    estimate : Estimate
        Initial mean and covariance; particles are drawn from it.
    transition : Transition
        ``f(t0, X (N, n), t1)``; all particles in one call.
    process_noise : ProcessNoise or None
        :mod:`opnav.filters.noise` model (``discrete(dt_s, x)``) for the first six
        states, evaluated at the first particle (SIR) or at the mean (UPF).
    model : MeasurementModel
    rng : numpy.random.Generator
    options : ParticleOptions
        ``mcmc_move`` and ``ukf`` are not used by SIR.
    """

    def predict(self, t_tdb_s: float) -> Estimate:
        """Close the current epoch (resample if N_eff is low), then move every particle to ``t_tdb_s``."""
        self.cloud = sir_predict(self.cloud, t_tdb_s, transition=self.transition, process_noise=self.process_noise,
                                 options=self.options, rng=self.rng)
        return self.cloud.estimate

    def update(self, record: Measurement) -> UpdateOutcome:
        """Weight the particles by the likelihood of ``record`` (predicting to its epoch first)."""
        refusal = refuse_unusable(record, self.cloud.estimate, self.predict)
        if refusal is not None:
            return refusal
        self.predict(record.t_tdb_s)
        self.cloud, outcome = sir_update(self.cloud, record, model=self.model, options=self.options, rng=self.rng)
        return outcome


class UnscentedParticleFilter(_ParticleFilterBase):
    """Unscented particle filter; with ``options.mcmc_move`` the MCMC-UPF of S3.

    Holds the models, the generator and a :class:`ParticleCloud`; the work is done by
    :func:`upf_predict` and :func:`upf_update`. Parameters are those of
    :class:`ParticleFilter`; ``process_noise`` must be positive definite (it is a
    density in the weights).

    Notes
    -----
    Each particle stands for its regularisation kernel and goes through its own
    unscented time and measurement updates; the module notes say why the kernel,
    not ``Q`` alone nor the particle's accumulated UKF covariance, is the width
    to carry.
    """

    def __init__(
        self,
        estimate: Estimate,
        *,
        transition: Transition,
        process_noise: ProcessNoise | None,
        model: MeasurementModel,
        rng: np.random.Generator,
        options: ParticleOptions = ParticleOptions(),
    ) -> None:
        super().__init__(estimate, transition=transition, process_noise=process_noise, model=model, rng=rng,
                         options=options)
        self.weights_ukf = sigma_weights(self.cloud.particles.shape[1], options.ukf)

    def _start(self, estimate: Estimate) -> ParticleCloud:
        return sample_mixture(estimate, n_particles=int(self.options.n_particles or UPF_PARTICLES),
                              fraction=self.options.component_fraction, rng=self.rng)

    def predict(self, t_tdb_s: float) -> Estimate:
        """Close the epoch (resample and move), then run each particle's unscented time update."""
        self.cloud = upf_predict(self.cloud, t_tdb_s, transition=self.transition, process_noise=self.process_noise,
                                 model=self.model, options=self.options, weights=self.weights_ukf, rng=self.rng)
        return self.cloud.estimate

    def update(self, record: Measurement) -> UpdateOutcome:
        """Update every particle's UKF with ``record`` and reweight (see module notes)."""
        refusal = refuse_unusable(record, self.cloud.estimate, self.predict)
        if refusal is not None:
            return refusal
        self.predict(record.t_tdb_s)
        self.cloud, outcome = upf_update(self.cloud, record, model=self.model, options=self.options,
                                         weights=self.weights_ukf)
        return outcome
