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

The estimate is the weighted mean and covariance of the particles.
Randomness only comes from the ``numpy.random.Generator`` passed in.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.special import logsumexp

from ..errors import CovarianceError, InputError
from ..records import Measurement
from .base import (
    Estimate,
    MeasurementModel,
    UpdateOutcome,
    check_covariance,
    check_estimate,
    chi2_gate,
    record_problem,
    rejected,
)
from .ekf import measurement_covariance
from .noise import ProcessNoise
from .ukf import (
    Transition,
    UKFOptions,
    discrete_noise,
    sigma_weights,
    ukf_predict,
    ukf_update,
)

log = logging.getLogger(__name__)


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


def log_likelihood(records: list[Measurement], model: MeasurementModel, X: np.ndarray) -> np.ndarray:
    """Sum over ``records`` of ``log p(z | x)`` for states X (K, n).

    Gaussian with ``R`` from :func:`opnav.filters.ekf.measurement_covariance` (the
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


class _ParticleBase:
    """Particles, weights, epoch bookkeeping and the update outcome common to SIR and UPF."""

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
        checked = check_estimate(estimate)
        P0, x0 = checked.P, checked.x
        self.transition = transition
        self.process_noise = process_noise
        self.model = model
        self.rng = rng
        self.options = options
        n_p = int(options.n_particles)
        self.t_tdb_s = float(estimate.t_tdb_s)
        self.particles = x0 + rng.standard_normal((n_p, x0.size)) @ np.linalg.cholesky(P0).T
        self.log_weights = np.full(n_p, -np.log(n_p))
        self.epoch_records: list[Measurement] = []
        self.last_epoch: EpochDiagnostics | None = None
        self._ess = float(n_p)

    @property
    def weights(self) -> np.ndarray:
        """Normalised weights (N,)."""
        return np.exp(self.log_weights)

    @property
    def estimate(self) -> Estimate:
        mean, cov = _weighted_moments(self.particles, self.weights)
        return Estimate(self.t_tdb_s, mean, 0.5 * (cov + cov.T))

    def _resample(self) -> np.ndarray | None:
        """Systematic resample if N_eff is low; returns the parent indices or ``None``."""
        ess = effective_sample_size(self.weights)
        self._ess = ess
        if ess >= self.options.resample_fraction * self.particles.shape[0]:
            return None
        index = systematic_resample(self.weights, self.rng)
        self.particles = self.particles[index]
        self.log_weights = np.full(index.size, -np.log(index.size))
        return index

    def _check_epoch(self, t_tdb_s: float) -> None:
        if not np.isfinite(t_tdb_s):
            raise InputError("predict epoch t_tdb_s is not finite")
        if t_tdb_s < self.t_tdb_s - 1e-9:
            raise InputError(f"cannot predict backwards: t_tdb_s={t_tdb_s:.3f} is before the filter epoch {self.t_tdb_s:.3f}")

    def _predictive(self, record: Measurement) -> tuple[np.ndarray, np.ndarray, float]:
        """Weighted innovation mean, its covariance (particle spread + R) and NIS for ``record``."""
        nu = self.model.residual(record, self.model.predict(record, self.particles))
        mean, cov = _weighted_moments(nu, self.weights)
        S = 0.5 * (cov + cov.T) + measurement_covariance(self.model, record, self.particles[0])
        return mean, S, float(mean @ np.linalg.solve(S, mean))

    def _gate(self, record: Measurement, residual: np.ndarray, S: np.ndarray, nis: float) -> UpdateOutcome | None:
        if self.options.gate_probability is None or chi2_gate(nis, record.size, self.options.gate_probability):
            return None
        reason = f"chi-square gate: NIS {nis:.3g} above the {self.options.gate_probability} quantile of chi2({record.size})"
        log.warning("rejected %s measurement at t=%.3f s (%s): %s", record.kind, record.t_tdb_s, record.sensor or "-", reason)
        return UpdateOutcome(self.estimate, residual, S, nis, False, reason)

    def _screen(self, record: Measurement) -> tuple[UpdateOutcome | None, tuple]:
        """Refuse a bad or gated record (outcome, ()), else predict to it: (None, (residual, S, NIS))."""
        reason = record_problem(record, self.t_tdb_s)
        if reason is not None:
            return rejected(self.estimate, record.size, reason, record), ()
        self.predict(record.t_tdb_s)
        residual, S, nis = self._predictive(record)
        return self._gate(record, residual, S, nis), (residual, S, nis)

    def _weigh(self, record: Measurement, residual: np.ndarray, S: np.ndarray, nis: float) -> UpdateOutcome:
        """Multiply the current weights by the likelihood of ``record`` and keep it for the epoch."""
        reason = self._normalise(self.log_weights + log_likelihood([record], self.model, self.particles))
        if reason is not None:
            return rejected(self.estimate, record.size, reason, record)
        self.epoch_records.append(record)
        return UpdateOutcome(self.estimate, residual, S, nis, True)

    def _normalise(self, log_weights: np.ndarray) -> str | None:
        total = logsumexp(log_weights)
        if not np.isfinite(total):
            return "every particle has zero likelihood"
        self.log_weights = log_weights - total
        return None


class ParticleFilter(_ParticleBase):
    """Bootstrap (SIR) particle filter with systematic resampling.

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
        self._check_epoch(t_tdb_s)
        if t_tdb_s > self.t_tdb_s:
            resampled = self._resample() is not None
            self.last_epoch = EpochDiagnostics(self.t_tdb_s, self._ess, resampled, np.zeros(0), np.zeros(0, bool))
            Q = discrete_noise(self.process_noise, self.t_tdb_s, t_tdb_s, self.particles[0])
            values, vectors = np.linalg.eigh(0.5 * (Q + Q.T))
            if np.any(values < -1e-12 * max(1.0, float(np.max(np.abs(values))))):
                raise CovarianceError("process noise Q is not positive semi-definite")
            root = vectors * np.sqrt(np.clip(values, 0.0, None))
            moved = np.asarray(self.transition(self.t_tdb_s, self.particles, t_tdb_s), dtype=float)
            self.particles = moved + self.rng.standard_normal(moved.shape) @ root.T
            self.t_tdb_s = float(t_tdb_s)
            self.epoch_records = []
        return self.estimate

    def update(self, record: Measurement) -> UpdateOutcome:
        """Weight the particles by the likelihood of ``record`` (predicting to its epoch first)."""
        refused, moments = self._screen(record)
        if refused is not None:
            return refused
        return self._weigh(record, *moments)


class UnscentedParticleFilter(_ParticleBase):
    """Unscented particle filter; with ``options.mcmc_move`` the MCMC-UPF of S3.

    Parameters are those of :class:`ParticleFilter`; ``process_noise`` must be
    positive definite (it is a density in the weights).

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
        self.weights_ukf = sigma_weights(self.particles.shape[1], options.ukf)
        self._epoch: dict[str, np.ndarray] | None = None

    def predict(self, t_tdb_s: float) -> Estimate:
        """Close the epoch (resample and move), then run each particle's unscented time update.

        Until a record arrives, the particles are draws from the transition
        prior ``N(f(x_i), Q)``.
        """
        self._check_epoch(t_tdb_s)
        if t_tdb_s > self.t_tdb_s:
            self._close_epoch()
            Q = check_covariance(discrete_noise(self.process_noise, self.t_tdb_s, t_tdb_s, self.estimate.x),
                                 "process noise Q")
            n_p = self.particles.shape[0]
            # the proposal must match p(x_k | x_i^{k-1}, z_k), whose prior part N(f(x_i), Q) is narrow:
            # each particle's UKF restarts from the point x_i with half of Q before the
            # transition and half after (F ~ I over a step), so Pbar_i ~ Q
            xbar, Pbar, central = ukf_predict(self.particles, np.broadcast_to(0.5 * Q, (n_p,) + Q.shape), self.t_tdb_s,
                                              t_tdb_s, transition=self.transition, Q=0.5 * Q,
                                              weights=self.weights_ukf)
            self._epoch = {"log_w0": self.log_weights.copy(), "f": central, "Q": Q, "mu": xbar, "P": Pbar}
            self.particles = central + self.rng.standard_normal(central.shape) @ np.linalg.cholesky(Q).T
            self.t_tdb_s = float(t_tdb_s)
            self.epoch_records = []
        return self.estimate

    def _log_ratio(self, X: np.ndarray) -> np.ndarray:
        """``log[p(z_k | x_i) N(x_i; f_i, Q) / q_i(x_i)]`` for particles X (N, n) of the current epoch."""
        e = self._epoch
        return (log_likelihood(self.epoch_records, self.model, X) + log_gaussian(X, e["f"], e["Q"])
                - log_gaussian(X, e["mu"], e["P"]))

    def _close_epoch(self) -> None:
        parents = self._resample()
        acceptance = np.zeros(0)
        accepted = np.zeros(0, dtype=bool)
        if parents is not None:
            if self.options.mcmc_move and self._epoch is not None and self.epoch_records:
                e = self._epoch
                for key in ("f", "mu", "P"):
                    e[key] = e[key][parents]
                candidates = e["mu"] + np.einsum("kij,kj->ki", np.linalg.cholesky(e["P"]), self.rng.standard_normal(e["mu"].shape))
                log_alpha = self._log_ratio(candidates) - self._log_ratio(self.particles)
                acceptance = np.exp(np.minimum(log_alpha, 0.0))
                accepted = self.rng.random(parents.size) < acceptance
                self.particles = np.where(accepted[:, None], candidates, self.particles)
        self.last_epoch = EpochDiagnostics(self.t_tdb_s, self._ess, parents is not None, acceptance, accepted)

    def update(self, record: Measurement) -> UpdateOutcome:
        """Refine every particle's proposal with ``record``, redraw and reweight (see module notes)."""
        refused, moments = self._screen(record)
        if refused is not None:
            return refused
        residual, S, nis = moments
        if self._epoch is None:
            # no transition into this epoch (update at the initial epoch): weight the prior draws
            return self._weigh(record, residual, S, nis)
        e = self._epoch
        try:
            post = ukf_update(e["mu"], e["P"], record, model=self.model, weights=self.weights_ukf)
        except np.linalg.LinAlgError:
            return rejected(self.estimate, record.size, "a particle's innovation covariance is not positive definite", record)
        try:
            chol = np.linalg.cholesky(post.P)
        except np.linalg.LinAlgError:
            return rejected(self.estimate, record.size, "a particle's proposal covariance is not positive definite", record)
        draws = post.x + np.einsum("kij,kj->ki", chol, self.rng.standard_normal(post.x.shape))
        records = self.epoch_records + [record]
        log_ratio = (log_likelihood(records, self.model, draws) + log_gaussian(draws, e["f"], e["Q"])
                     - log_gaussian(draws, post.x, post.P))
        reason = self._normalise(e["log_w0"] + log_ratio)
        if reason is not None:
            return rejected(self.estimate, record.size, reason, record)
        self.epoch_records = records
        e["mu"], e["P"] = post.x, post.P
        self.particles = draws
        return UpdateOutcome(self.estimate, residual, S, nis, True)
