"""The filters' names and option classes, light: only the standard library and :mod:`opnav.errors`.

What the command line (``opnav navigate --help``) and the ``[navigation]`` loader
(:mod:`opnav.filters.options`) need without importing a filter (numpy, scipy, filterpy):

- :data:`FILTERS`: the filter names ``[navigation] filter`` and ``--filter`` take;
- :class:`UKFOptions`: sigma-point parameters and gate of the unscented filters;
- :class:`ParticleOptions`: settings of the particle filters;
- :class:`BatchOptions`: iteration control of batch least squares;
- :class:`FederatedSetup` (with :data:`LOCAL_FILTERS` and :data:`MODES`): how the federated filter
  is set up.

The filter modules import their options from here and keep them importable under their own
names (``opnav.filters.ukf.UKFOptions``, ``opnav.filters.particle.ParticleOptions``,
``opnav.filters.batch.BatchOptions``, ``opnav.filters.federated.FederatedSetup``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..errors import InputError

#: The filters by name (``[navigation] filter``, ``opnav navigate --filter``).
FILTERS = ("ekf", "ukf", "sr-ukf", "pf", "upf", "mcmc-upf", "wls", "federated")
#: Modes of the federated filter: the locals restart from each fused estimate, or never hear from it.
MODES = ("fusion-reset", "no-reset")
#: Local filters a federated run may be built from.
LOCAL_FILTERS = ("ekf", "ukf", "sr-ukf")


@dataclass(frozen=True)
class UKFOptions:
    """Scaled-sigma-point parameters and gating of the unscented filters.

    Attributes
    ----------
    alpha : float
        Spread of the points, 0 < alpha <= 1. The default 1 puts them at
        ``sqrt(n + kappa)`` sigma with non-negative weights. Van der Merwe's
        1e-3 makes the weights ~1/(alpha^2 n) ~ 1e5, which multiplies every
        per-point error: a DOP853 propagation at rtol 1e-11 is off by ~2 m at
        1.5 au, and the S1 mean then jitters by tens to hundreds of km
        (``benchmarks/filters.py``).
    beta : float
        Prior-knowledge weight on the central point (2 is optimal for Gaussians).
    kappa : float
        Secondary scaling; ``n + kappa`` must be positive.
    gate_probability : float or None
        Reject a record whose NIS exceeds this chi-square quantile; ``None`` disables gating.
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0
    gate_probability: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.alpha) and 0.0 < self.alpha <= 1.0):
            raise InputError(f"UKFOptions.alpha must be in (0, 1], got {self.alpha}")
        if not (math.isfinite(self.beta) and self.beta >= 0.0):
            raise InputError(f"UKFOptions.beta must be >= 0, got {self.beta}")
        if not math.isfinite(self.kappa):
            raise InputError(f"UKFOptions.kappa must be finite, got {self.kappa}")
        if self.gate_probability is not None and not 0.0 < self.gate_probability < 1.0:
            raise InputError(f"UKFOptions.gate_probability must be in (0, 1), got {self.gate_probability}")


@dataclass(frozen=True)
class ParticleOptions:
    """Settings of the particle filters (:mod:`opnav.filters.particle`).

    Attributes
    ----------
    n_particles : int or None
        Number of particles; None takes the filter's default,
        :data:`opnav.filters.particle.SIR_PARTICLES` for SIR and
        :data:`opnav.filters.particle.UPF_PARTICLES` (S3's 150) for the UPFs.
    resample_fraction : float
        Resample when ``N_eff < resample_fraction * n_particles`` (0 < f <= 1).
    mcmc_move : bool
        UPF only: Metropolis–Hastings move after each resampling (the S3 MCMC-UPF).
    ukf : UKFOptions
        UPF only: sigma-point parameters of the per-particle proposals.
    gate_probability : float or None
        Refuse a record whose predictive NIS exceeds this chi-square quantile.
    bandwidth_scale : float
        SIR: kernel width relative to Musso's optimal Gaussian bandwidth (notes of
        :mod:`opnav.filters.particle`), in [0, 1/h_opt); 0 turns regularisation off (the cloud
        can then collapse: for tests of that).
    component_fraction : float
        UPF: the share ``h^2`` of the cloud covariance each particle's Gaussian carries after a
        (re)start, in (0, 1); the means carry the rest (notes of :mod:`opnav.filters.particle`).
    correction_ess : float
        SIR: progressive correction keeps ``N_eff >= correction_ess * n_particles`` at every stage,
        in [0, 1); 0 applies each likelihood in one go.
    max_corrections : int
        SIR: most correction stages per record; the rest of the likelihood is then applied at
        once and the stage count shows it (:class:`opnav.filters.particle.EpochDiagnostics`).
    """

    n_particles: int | None = None
    resample_fraction: float = 0.5
    mcmc_move: bool = True
    ukf: UKFOptions = field(default_factory=lambda: UKFOptions(alpha=1.0, kappa=0.0))
    gate_probability: float | None = None
    bandwidth_scale: float = 1.0
    component_fraction: float = 0.8
    correction_ess: float = 0.5
    max_corrections: int = 100

    def __post_init__(self) -> None:
        if self.n_particles is not None and (int(self.n_particles) != self.n_particles or self.n_particles < 2):
            raise InputError(f"ParticleOptions.n_particles must be an integer >= 2, got {self.n_particles}")
        if not 0.0 < self.resample_fraction <= 1.0:
            raise InputError(f"ParticleOptions.resample_fraction must be in (0, 1], got {self.resample_fraction}")
        if self.gate_probability is not None and not 0.0 < self.gate_probability < 1.0:
            raise InputError(f"ParticleOptions.gate_probability must be in (0, 1), got {self.gate_probability}")
        if not (math.isfinite(self.bandwidth_scale) and self.bandwidth_scale >= 0.0):
            raise InputError(f"ParticleOptions.bandwidth_scale must be finite and >= 0, got {self.bandwidth_scale}")
        if not 0.0 < self.component_fraction < 1.0:
            raise InputError(f"ParticleOptions.component_fraction must be in (0, 1), got {self.component_fraction}")
        if not 0.0 <= self.correction_ess < 1.0:
            raise InputError(f"ParticleOptions.correction_ess must be in [0, 1), got {self.correction_ess}")
        if int(self.max_corrections) != self.max_corrections or self.max_corrections < 1:
            raise InputError(f"ParticleOptions.max_corrections must be an integer >= 1, got {self.max_corrections}")


@dataclass(frozen=True)
class BatchOptions:
    """Iteration control of :func:`opnav.filters.batch.batch_least_squares`.

    Attributes
    ----------
    max_iterations : int
    tolerance : float
        Converged when ``dx^T N dx`` (the step's squared size in its own sigmas) is below this.
    """

    max_iterations: int = 20
    tolerance: float = 1e-6

    def __post_init__(self) -> None:
        if self.max_iterations < 1:
            raise InputError(f"BatchOptions.max_iterations must be >= 1, got {self.max_iterations}")
        if not (math.isfinite(self.tolerance) and self.tolerance > 0.0):
            raise InputError(f"BatchOptions.tolerance must be positive, got {self.tolerance}")


@dataclass(frozen=True)
class FederatedSetup:
    """How :func:`opnav.filters.factory.run_federated_filter` sets the federated filter up
    (``[navigation.federated]``); the sharing factors and routes follow from the records' sensors.

    Attributes
    ----------
    local_filter : {"ekf", "ukf", "sr-ukf"}
        The filter of each sensor.
    mode : {"fusion-reset", "no-reset"}
    fusion_interval_s : float or None
        Fuse every this many seconds from the first record; None fuses at every record epoch.
    """

    local_filter: str = field(default="ekf", metadata={"choices": LOCAL_FILTERS})  # any case in a file
    mode: str = field(default="fusion-reset", metadata={"choices": MODES})
    fusion_interval_s: float | None = None

    def __post_init__(self) -> None:
        if self.local_filter not in LOCAL_FILTERS:
            raise InputError(f"FederatedSetup.local_filter must be one of {', '.join(LOCAL_FILTERS)}, "
                             f"got {self.local_filter!r}")
        if self.mode not in MODES:
            raise InputError(f"FederatedSetup.mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.fusion_interval_s is not None and not (math.isfinite(self.fusion_interval_s)
                                                       and self.fusion_interval_s > 0.0):
            raise InputError(f"FederatedSetup.fusion_interval_s must be positive, got {self.fusion_interval_s}")
