"""Particle filters: SIR, unscented particle filter (UPF) and the MCMC-UPF of S3.

All three keep ``N`` weighted particles ``x_i`` (state units, frame/origin of
the transition; see :mod:`opnav.filters.base`) and share the interface of
:mod:`opnav.filters.base`. Per epoch ``t_k``:

SIR (bootstrap)
    1. ``x_i <- f(x_i) + w_i``, ``w_i ~ N(0, Q)`` (all particles in one transition call);
    2. every record at ``t_k`` multiplies the weights by its likelihood ``p(z | x_i)``.

UPF (van der Merwe, Doucet, de Freitas & Wan 2000)
    1. each particle's UKF starts from ``N(x_i, Q/2)`` (see
       :class:`UnscentedParticleFilter`); one unscented time update per
       particle (plus ``Q/2``) gives ``N(xbar_i, Pbar_i)`` and the propagated
       particle ``f(x_i)`` (its central sigma point). All particles' sigma
       points go through the transition in ONE call (``N (2n+1)`` states);
    2. the records at ``t_k`` update each Gaussian (batched unscented update),
       giving the proposal ``q_i = N(mu_i, Pq_i)``; a new particle is drawn from
       it and weighted by
       ``w_i ∝ w_i^{k-1} p(z_k | x_i) N(x_i; f(x_i^{k-1}), Q) / q_i(x_i)``.
       A second record at the same epoch refines the proposal and redraws, with
       the likelihood of all the epoch's records, so records may arrive one at a time;
    3. when the epoch is over (the next ``predict``), if
       ``N_eff = 1 / sum w^2 < resample_fraction * N`` the particles are
       resampled (systematic) and their weights reset to ``1/N``.

MCMC-UPF (S3; Gilks & Berzuini 2001 resample-move)
    After resampling, each particle makes one Metropolis–Hastings move with
    its parent's proposal ``q_j`` as an independence sampler targeting
    ``p(x | x_j^{k-1}, z_k) ∝ p(z_k | x) N(x; f(x_j^{k-1}), Q)``: a candidate
    ``x* ~ q_j`` is accepted with probability ``min(1, r(x*) / r(x))``,
    ``r = p(z_k | .) N(.; f, Q) / q_j(.)``. The move restores diversity lost to
    duplication without changing the target distribution.

The state of each filter is a frozen :class:`ParticleCloud` (epoch, particles,
log-weights, the records of the current epoch and, for the UPF, the per-particle
proposals of the epoch, :class:`Proposal`); its ``estimate`` is the weighted mean
and covariance of the particles. :func:`sample_cloud`, :func:`sir_predict`,
:func:`sir_update`, :func:`upf_predict` and :func:`upf_update` are the pure core;
:class:`ParticleFilter` and :class:`UnscentedParticleFilter` only hold the models,
the generator and the current cloud. Randomness only comes from the
``numpy.random.Generator`` passed in.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.special import logsumexp

from ..errors import InputError
from ..records import Measurement
from .base import (
    Estimate,
    MeasurementModel,
    UpdateOutcome,
    check_covariance,
    check_epoch,
    check_estimate,
    discrete_noise,
    gate_refusal,
    measurement_covariance,
    psd_sqrt,
    record_problem,
    rejected,
    screen_record,
)
from .noise import ProcessNoise
from .ukf import (
    SigmaWeights,
    Transition,
    UKFOptions,
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


@dataclass(frozen=True)
class ParticleOptions:
    """Settings of the particle filters.

    Attributes
    ----------
    n_particles : int
        Number of particles (150 in S3).
    resample_fraction : float
        Resample when ``N_eff < resample_fraction * n_particles`` (0 < f <= 1).
    mcmc_move : bool
        UPF only: Metropolis–Hastings move after each resampling (the S3 MCMC-UPF).
    ukf : UKFOptions
        UPF only: sigma-point parameters of the per-particle proposals.
    gate_probability : float or None
        Refuse a record whose predictive NIS exceeds this chi-square quantile.
    """

    n_particles: int = 150
    resample_fraction: float = 0.5
    mcmc_move: bool = True
    ukf: UKFOptions = field(default_factory=lambda: UKFOptions(alpha=1.0, kappa=0.0))
    gate_probability: float | None = None

    def __post_init__(self) -> None:
        if int(self.n_particles) != self.n_particles or self.n_particles < 2:
            raise InputError(f"ParticleOptions.n_particles must be an integer >= 2, got {self.n_particles}")
        if not 0.0 < self.resample_fraction <= 1.0:
            raise InputError(f"ParticleOptions.resample_fraction must be in (0, 1], got {self.resample_fraction}")
        if self.gate_probability is not None and not 0.0 < self.gate_probability < 1.0:
            raise InputError(f"ParticleOptions.gate_probability must be in (0, 1), got {self.gate_probability}")


@dataclass(frozen=True)
class EpochDiagnostics:
    """What happened when an epoch was closed.

    ``ess`` is N_eff before resampling; ``acceptance`` holds each particle's
    Metropolis–Hastings acceptance probability ``min(1, r*/r)`` (empty when no
    move was made) and ``accepted`` whether its candidate was taken.
    """

    t_tdb_s: float
    ess: float
    resampled: bool
    acceptance: np.ndarray
    accepted: np.ndarray


@dataclass(frozen=True)
class Proposal:
    """The UPF's per-particle proposals for the current epoch (arrays over the N particles).

    Attributes
    ----------
    log_w0 : (N,) array
        Normalised log-weights at the start of the epoch, before any of its records.
    f : (N, n) array
        Propagated previous particles ``f(x_i^{k-1})``: the means of the transition density.
    Q : (n, n) array
        Process noise over the step: the covariance of the transition density.
    mu : (N, n) array
        Proposal means, refined by each record of the epoch.
    P : (N, n, n) array
        Proposal covariances.
    """

    log_w0: np.ndarray
    f: np.ndarray
    Q: np.ndarray
    mu: np.ndarray
    P: np.ndarray


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
    proposal : Proposal or None
        UPF only: the proposals of this epoch; ``None`` for SIR and before the first transition.
    last_epoch : EpochDiagnostics or None
        What closing the previous epoch did; ``None`` before the first transition.
    """

    t_tdb_s: float
    particles: np.ndarray
    log_weights: np.ndarray
    records: tuple[Measurement, ...] = ()
    proposal: Proposal | None = None
    last_epoch: EpochDiagnostics | None = None

    @property
    def weights(self) -> np.ndarray:
        """Normalised weights (N,)."""
        return np.exp(self.log_weights)

    @property
    def estimate(self) -> Estimate:
        """Gaussian summary: the weighted mean and covariance of the particles."""
        mean, cov = _weighted_moments(self.particles, self.weights)
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


def _resample(cloud: ParticleCloud, *, fraction: float, rng: np.random.Generator
              ) -> tuple[ParticleCloud, float, np.ndarray | None]:
    """Systematic resample if ``N_eff < fraction * N``: (cloud, N_eff before, parent indices or ``None``)."""
    ess = effective_sample_size(cloud.weights)
    if ess >= fraction * cloud.particles.shape[0]:
        return cloud, ess, None
    index = systematic_resample(cloud.weights, rng)
    resampled = replace(cloud, particles=cloud.particles[index], log_weights=np.full(index.size, -np.log(index.size)))
    return resampled, ess, index


def _normalised(log_weights: np.ndarray) -> np.ndarray | None:
    """``log_weights`` normalised to ``logsumexp = 0``, or ``None`` if every weight is zero."""
    total = logsumexp(log_weights)
    if not np.isfinite(total):
        return None
    return log_weights - total


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
           nis: float) -> tuple[ParticleCloud, UpdateOutcome]:
    """Multiply the weights by the likelihood of ``record`` and keep it among the epoch's records."""
    log_weights = _normalised(cloud.log_weights + log_likelihood([record], model, cloud.particles))
    if log_weights is None:
        return cloud, rejected(cloud.estimate, record.size, "every particle has zero likelihood", record)
    weighed = replace(cloud, log_weights=log_weights, records=cloud.records + (record,))
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
    """Close the cloud's epoch (resample if N_eff is low), then move every particle to ``t_tdb_s``.

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
        ``resample_fraction`` is used.
    rng : numpy.random.Generator
        One uniform if resampling, then ``N n`` normals.

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
    closed, ess, parents = _resample(cloud, fraction=options.resample_fraction, rng=rng)
    diagnostics = EpochDiagnostics(cloud.t_tdb_s, ess, parents is not None, np.zeros(0), np.zeros(0, bool))
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
) -> tuple[ParticleCloud, UpdateOutcome]:
    """Weight the particles by the likelihood of ``record`` (at the cloud's epoch).

    Parameters
    ----------
    cloud : ParticleCloud
        At ``record.t_tdb_s`` (predict first).
    record : Measurement
    model : MeasurementModel
        Vectorised measurement model; the likelihood is Gaussian with ``R`` of
        :func:`opnav.filters.base.measurement_covariance`.
    options : ParticleOptions
        ``gate_probability`` is used.

    Returns
    -------
    cloud : ParticleCloud
        Reweighted, or the input when the record is refused.
    outcome : UpdateOutcome
        Cloud estimate, predictive innovation mean (m,) and covariance (particle spread + R),
        NIS, accepted flag and reason. Refused: bad values, another epoch, the chi-square gate,
        or zero likelihood for every particle.
    """
    refusal, predictive = _screen(cloud, record, model, options.gate_probability)
    if refusal is not None:
        return cloud, refusal
    return _weigh(cloud, record, model, *predictive)


def _log_ratio(X: np.ndarray, records: tuple[Measurement, ...], model: MeasurementModel, f: np.ndarray, Q: np.ndarray,
               mu: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``log[p(z_k | x_i) N(x_i; f_i, Q) / N(x_i; mu_i, P_i)]`` for particles X (N, n) of one epoch."""
    return log_likelihood(records, model, X) + log_gaussian(X, f, Q) - log_gaussian(X, mu, P)


def _close_epoch(cloud: ParticleCloud, *, model: MeasurementModel, options: ParticleOptions,
                 rng: np.random.Generator) -> ParticleCloud:
    """Resample if N_eff is low and, for the MCMC-UPF, move each resampled particle once (same epoch)."""
    closed, ess, parents = _resample(cloud, fraction=options.resample_fraction, rng=rng)
    acceptance = np.zeros(0)
    accepted = np.zeros(0, dtype=bool)
    particles = closed.particles
    e = cloud.proposal
    if parents is not None and options.mcmc_move and e is not None and cloud.records:
        f, mu, P = e.f[parents], e.mu[parents], e.P[parents]
        candidates = mu + np.einsum("kij,kj->ki", np.linalg.cholesky(P), rng.standard_normal(mu.shape))
        log_alpha = (_log_ratio(candidates, cloud.records, model, f, e.Q, mu, P)
                     - _log_ratio(particles, cloud.records, model, f, e.Q, mu, P))
        acceptance = np.exp(np.minimum(log_alpha, 0.0))
        accepted = rng.random(parents.size) < acceptance
        particles = np.where(accepted[:, None], candidates, particles)
    diagnostics = EpochDiagnostics(cloud.t_tdb_s, ess, parents is not None, acceptance, accepted)
    return replace(closed, particles=particles, last_epoch=diagnostics)


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
    """Close the cloud's epoch (resample, MCMC move), then run each particle's unscented time update.

    Until a record arrives, the particles are draws from the transition prior ``N(f(x_i), Q)``.

    Parameters
    ----------
    cloud : ParticleCloud
    t_tdb_s : float
        Target epoch, TDB seconds past J2000; at the cloud's epoch the cloud is returned unchanged.
    transition : Transition
        All ``N (2n+1)`` sigma points in one call.
    process_noise : ProcessNoise or None
        :mod:`opnav.filters.noise` model, evaluated at the cloud's mean; must be positive definite
        (it is a density in the weights).
    model : MeasurementModel
        For the likelihood of the closed epoch's records in the MCMC move.
    options : ParticleOptions
        ``resample_fraction`` and ``mcmc_move``.
    weights : SigmaWeights
        ``sigma_weights(n, options.ukf)``.
    rng : numpy.random.Generator

    Returns
    -------
    ParticleCloud
        At ``t_tdb_s`` with this epoch's :class:`Proposal` and no records yet.

    Raises
    ------
    InputError
        If ``t_tdb_s`` is not finite or lies before the cloud's epoch.
    CovarianceError
        If the process noise is not positive definite.
    """
    check_epoch(cloud.t_tdb_s, t_tdb_s)
    if not t_tdb_s > cloud.t_tdb_s:
        return cloud
    closed = _close_epoch(cloud, model=model, options=options, rng=rng)
    Q = check_covariance(discrete_noise(process_noise, closed.t_tdb_s, t_tdb_s, closed.estimate.x), "process noise Q")
    n_p = closed.particles.shape[0]
    # the proposal must match p(x_k | x_i^{k-1}, z_k), whose prior part N(f(x_i), Q) is narrow:
    # each particle's UKF restarts from the point x_i with half of Q before the
    # transition and half after (F ~ I over a step), so Pbar_i ~ Q
    xbar, Pbar, central = ukf_predict(closed.particles, np.broadcast_to(0.5 * Q, (n_p,) + Q.shape), closed.t_tdb_s,
                                      t_tdb_s, transition=transition, Q=0.5 * Q, weights=weights)
    particles = central + rng.standard_normal(central.shape) @ np.linalg.cholesky(Q).T
    return ParticleCloud(float(t_tdb_s), particles, closed.log_weights,
                         proposal=Proposal(closed.log_weights, central, Q, xbar, Pbar), last_epoch=closed.last_epoch)


def upf_update(
    cloud: ParticleCloud,
    record: Measurement,
    *,
    model: MeasurementModel,
    options: ParticleOptions,
    weights: SigmaWeights,
    rng: np.random.Generator,
) -> tuple[ParticleCloud, UpdateOutcome]:
    """Refine every particle's proposal with ``record`` (at the cloud's epoch), redraw and reweight.

    Parameters
    ----------
    cloud : ParticleCloud
        At ``record.t_tdb_s`` (predict first). Without a proposal (no transition yet) the
        particles are only reweighted, as in :func:`sir_update`.
    record : Measurement
    model : MeasurementModel
        Vectorised measurement model.
    options : ParticleOptions
        ``gate_probability`` is used.
    weights : SigmaWeights
        ``sigma_weights(n, options.ukf)``.
    rng : numpy.random.Generator
        ``N n`` normals for the draws.

    Returns
    -------
    cloud : ParticleCloud
        Redrawn and reweighted, or the input when the record is refused.
    outcome : UpdateOutcome
        As for :func:`sir_update`; also refused when a particle's innovation or proposal
        covariance is not positive definite.
    """
    refusal, predictive = _screen(cloud, record, model, options.gate_probability)
    if refusal is not None:
        return cloud, refusal
    e = cloud.proposal
    if e is None:
        # no transition into this epoch (update at the initial epoch): weight the prior draws
        return _weigh(cloud, record, model, *predictive)
    try:
        post = ukf_update(e.mu, e.P, record, model=model, weights=weights)
    except np.linalg.LinAlgError:
        return cloud, rejected(cloud.estimate, record.size, "a particle's innovation covariance is not positive definite",
                               record)
    try:
        chol = np.linalg.cholesky(post.P)
    except np.linalg.LinAlgError:
        return cloud, rejected(cloud.estimate, record.size, "a particle's proposal covariance is not positive definite",
                               record)
    draws = post.x + np.einsum("kij,kj->ki", chol, rng.standard_normal(post.x.shape))
    records = cloud.records + (record,)
    log_weights = _normalised(e.log_w0 + _log_ratio(draws, records, model, e.f, e.Q, post.x, post.P))
    if log_weights is None:
        return cloud, rejected(cloud.estimate, record.size, "every particle has zero likelihood", record)
    redrawn = ParticleCloud(cloud.t_tdb_s, draws, log_weights, records, replace(e, mu=post.x, P=post.P),
                            cloud.last_epoch)
    return redrawn, UpdateOutcome(redrawn.estimate, *predictive, True)


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
        self.cloud = sample_cloud(estimate, n_particles=int(options.n_particles), rng=rng)

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
    """Bootstrap (SIR) particle filter with systematic resampling; holds the models and a :class:`ParticleCloud`.

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
        reason = record_problem(record, self.cloud.t_tdb_s)
        if reason is not None:
            return rejected(self.cloud.estimate, record.size, reason, record)
        self.predict(record.t_tdb_s)
        self.cloud, outcome = sir_update(self.cloud, record, model=self.model, options=self.options)
        return outcome


class UnscentedParticleFilter(_ParticleFilterBase):
    """Unscented particle filter; with ``options.mcmc_move`` the MCMC-UPF of S3.

    Holds the models, the generator and a :class:`ParticleCloud`; the work is done by
    :func:`upf_predict` and :func:`upf_update`. Parameters are those of
    :class:`ParticleFilter`; ``process_noise`` must be positive definite (it is a
    density in the weights).

    Notes
    -----
    The proposal must approximate the *conditional* ``p(x_k | x_i^{k-1}, z_k)``,
    whose prior part ``N(f(x_i), Q)`` is as narrow as the process noise. Van der
    Merwe et al. carry each particle's UKF covariance forward; that covariance
    grows to the width of the whole posterior while the transition density
    stays ``Q`` wide, which leaves a handful of particles with all the weight
    (N_eff of 2-20 out of 150 on ``tests/test_particle.py``'s orbit). Here each
    particle's UKF restarts every epoch from the point ``x_i`` with ``Q/2``
    before the transition and ``Q/2`` after it, so that ``Pbar_i ~ Q`` for
    steps over which ``F ~ I``; the sigma points still carry the dynamics'
    curvature into the proposal.
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

    def predict(self, t_tdb_s: float) -> Estimate:
        """Close the epoch (resample and move), then run each particle's unscented time update."""
        self.cloud = upf_predict(self.cloud, t_tdb_s, transition=self.transition, process_noise=self.process_noise,
                                 model=self.model, options=self.options, weights=self.weights_ukf, rng=self.rng)
        return self.cloud.estimate

    def update(self, record: Measurement) -> UpdateOutcome:
        """Refine every particle's proposal with ``record``, redraw and reweight (see module notes)."""
        reason = record_problem(record, self.cloud.t_tdb_s)
        if reason is not None:
            return rejected(self.cloud.estimate, record.size, reason, record)
        self.predict(record.t_tdb_s)
        self.cloud, outcome = upf_update(self.cloud, record, model=self.model, options=self.options,
                                         weights=self.weights_ukf, rng=self.rng)
        return outcome
