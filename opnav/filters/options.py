"""The ``[navigation]`` section of a scenario file: initial state, dynamics, noise, filter options.

Schema (units in every key; converted here, once)::

    [navigation]
    epoch = "2014-07-01T00:00:00"      # initial-estimate epoch
    epoch_scale = "tdb"                # utc | tt | tdb | tai (default utc)
    dynamics = "cruise"                # a key of opnav.dynamics.MODELS; its centre is the state origin
    position_km = [x, y, z]            # initial estimate, ICRF, relative to the model's centre
    velocity_km_s = [vx, vy, vz]
    sigma_position_km = 2886.75        # 1-sigma per axis (one number or three)
    sigma_velocity_km_s = 0.00289
    filter = "ekf"                     # default when the CLI gives none
    gate_probability = 0.999999        # chi-square gate; 0 turns it off
    target_position_sigma_km = 1.0     # target ephemeris error, km per axis (1-sigma)
    ephemeris_error = "white"          # white: that error added to R at every record (independent draws);
                                       # estimate | consider: one constant offset per body of
                                       # ephemeris_targets, appended to the state (3 km each) and
                                       # estimated, or held as consider parameters (EKF only)
    ephemeris_targets = ["phobos", "deimos"]
    seed = 0                           # particle filters' generator
    propagation = "fast"               # fast: compiled fixed-step RK8 + cached ephemeris (opnav.dynamics.fast);
                                       # exact: DOP853 at rtol 1e-11 and the exact ephemeris (CLI: --exact)

    [navigation.process_noise]         # see opnav.filters.noise.process_noise_from_config
    model = "white"
    q_km2_s3 = 0.0

    [navigation.corrections]
    light_time = true
    aberration = true

    [navigation.ukf]                   # alpha, beta, kappa (opnav.filters.ukf.UKFOptions)
    [navigation.particle]              # n_particles (default 2000 for pf, 150 for upf/mcmc-upf),
                                       # resample_fraction, bandwidth_scale, component_fraction,
                                       # correction_ess, max_corrections (opnav.filters.particle.ParticleOptions)
    [navigation.batch]                 # max_iterations, tolerance (opnav.filters.batch.BatchOptions)
    [navigation.federated]             # local_filter (ekf | ukf | sr-ukf), mode (fusion-reset | no-reset),
                                       # fusion_interval_s (default: fuse at every record epoch)

Unknown keys raise :class:`opnav.errors.InputError` naming the file and the key.
"""

from __future__ import annotations

import reprlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..epochs import parse_epoch
from ..errors import InputError
from ..tomlio import read_toml

FILTERS = ("ekf", "ukf", "sr-ukf", "pf", "upf", "mcmc-upf", "wls", "federated")
_KEYS = {
    "epoch", "epoch_scale", "dynamics", "position_km", "velocity_km_s", "sigma_position_km", "sigma_velocity_km_s",
    "filter", "gate_probability", "target_position_sigma_km", "seed", "process_noise", "corrections", "ukf",
    "particle", "batch", "federated", "propagation", "ephemeris_error", "ephemeris_targets",
}
EPHEMERIS_ERROR = ("white", "estimate", "consider")
PROPAGATION = ("fast", "exact")


@dataclass(frozen=True)
class NavigationConfig:
    """Validated ``[navigation]`` section (internal units: TDB s, km, km/s).

    Attributes
    ----------
    t0_tdb_s : float
        Epoch of the initial estimate, TDB seconds past J2000.
    dynamics : str
        Force-model name (:data:`opnav.dynamics.MODELS`); its centre is the state origin.
    x0 : (6,) array
        Initial estimate [r km, v km/s], ICRF.
    P0 : (6, 6) array
        Initial covariance (diagonal from the sigmas).
    filter : str
        One of :data:`FILTERS`.
    gate_probability : float or None
    target_position_sigma_km : float
    light_time, aberration : bool
    seed : int
    exact : bool
        Filters propagate with DOP853 and read the exact ephemeris (``propagation = "exact"``)
        instead of the compiled fast path (the default; same answers to < 1 % of sigma).
    ephemeris_error : str
        How filters treat the targets' ephemeris error: ``white`` (added to R), ``estimate``
        or ``consider`` (one constant offset per :attr:`ephemeris_targets` body in the state,
        :class:`opnav.measurements.TargetOffsetModel`).
    ephemeris_targets : tuple of str
    process_noise, ukf, particle, batch, federated : dict
        Raw option tables, validated by the classes they configure.
    """

    t0_tdb_s: float
    dynamics: str
    x0: np.ndarray
    P0: np.ndarray
    filter: str = "ekf"
    gate_probability: float | None = 1.0 - 1e-6
    target_position_sigma_km: float = 0.0
    light_time: bool = True
    aberration: bool = True
    seed: int = 0
    exact: bool = False
    ephemeris_error: str = "white"
    ephemeris_targets: tuple[str, ...] = ()
    process_noise: dict = field(default_factory=lambda: {"model": "none"})
    ukf: dict = field(default_factory=dict)
    particle: dict = field(default_factory=dict)
    batch: dict = field(default_factory=dict)
    federated: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.filter not in FILTERS:
            raise InputError(f"[navigation] filter must be one of {', '.join(FILTERS)}, got {self.filter!r}")
        if np.shape(self.x0) != (6,) or not np.all(np.isfinite(self.x0)):
            raise InputError("[navigation] position_km and velocity_km_s must be 3 finite numbers each")
        if self.gate_probability is not None and not 0.0 < self.gate_probability < 1.0:
            raise InputError(f"[navigation] gate_probability must be in (0, 1) or 0 (off), got {self.gate_probability}")
        if not (np.isfinite(self.target_position_sigma_km) and self.target_position_sigma_km >= 0.0):
            raise InputError(f"[navigation] target_position_sigma_km must be >= 0, got {self.target_position_sigma_km}")
        if self.ephemeris_error not in EPHEMERIS_ERROR:
            raise InputError(f"[navigation] ephemeris_error must be one of {', '.join(EPHEMERIS_ERROR)}, "
                             f"got {self.ephemeris_error!r}")
        if self.ephemeris_error != "white":
            if not self.ephemeris_targets:
                raise InputError(f"[navigation] ephemeris_error = {self.ephemeris_error!r} needs ephemeris_targets")
            if not self.target_position_sigma_km > 0.0:
                raise InputError(f"[navigation] ephemeris_error = {self.ephemeris_error!r} needs "
                                 "target_position_sigma_km > 0 (the offsets' a-priori sigma)")
            if self.ephemeris_error == "consider" and self.filter != "ekf":
                raise InputError("[navigation] ephemeris_error = 'consider' works with filter = 'ekf' only "
                                 f"(got {self.filter!r}); use 'estimate'")

    @property
    def augmented(self) -> tuple[np.ndarray, np.ndarray]:
        """Initial state and covariance with the ephemeris offsets appended (zero, sigma^2 per axis)."""
        if self.ephemeris_error == "white":
            return self.x0, self.P0
        extra = 3 * len(self.ephemeris_targets)
        x0 = np.concatenate([self.x0, np.zeros(extra)])
        P0 = np.zeros((6 + extra, 6 + extra))
        P0[:6, :6] = self.P0
        P0[6:, 6:] = self.target_position_sigma_km**2 * np.eye(extra)
        return x0, P0

def _typed(section: dict, key: str, kind, default, source: str, table: str = "navigation"):
    """``section[key]`` as ``kind`` (bool, int or float), ``default`` when absent; a value of another
    TOML type (``"false"``, ``"big"``, ``1.5`` for an integer) is an error naming the file and key."""
    value = section.get(key, default)
    ok = (isinstance(value, bool) if kind is bool else
          isinstance(value, int) and not isinstance(value, bool) if kind is int else
          isinstance(value, (int, float)) and not isinstance(value, bool))
    if not ok:
        raise InputError(f"{source}: [{table}] {key} must be {'true or false' if kind is bool else kind.__name__}, "
                         f"got {value!r}")
    return kind(value)


def _finite(value) -> float | None:
    """``value`` as a finite float if it is a TOML number (not a bool), else ``None``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        number = float(value)
    except OverflowError:  # TOML integers have no size limit
        return None
    return number if np.isfinite(number) else None


def _vector3(section: dict, key: str, source: str) -> np.ndarray:
    """``section[key]`` as 3 finite numbers; text, booleans and nested arrays are errors naming the key."""
    value = section[key]
    numbers = [_finite(v) for v in value] if isinstance(value, list) else []
    if len(numbers) != 3 or None in numbers:
        raise InputError(f"{source}: [navigation] {key} must be an array of 3 finite numbers, got {reprlib.repr(value)}")
    return np.array(numbers)


def _sigmas(value, name: str, source: str) -> np.ndarray:
    numbers = [_finite(v) for v in value] if isinstance(value, list) else [_finite(value)] * 3
    # a sigma whose square under- or overflows would give a zero or infinite variance in P0
    if len(numbers) != 3 or None in numbers or not all(v > 0.0 and 0.0 < v * v < np.inf for v in numbers):
        raise InputError(f"{source}: [navigation] {name} must be one positive number or three, each with a "
                         f"finite non-zero square (about 1e-160 to 1e154), got {reprlib.repr(value)}")
    return np.array(numbers)


def _table(section: dict, key: str, default: dict, source: str) -> dict:
    """Sub-table ``[navigation.key]`` (``default`` when absent); a value of another type is an error."""
    value = section.get(key, default)
    if not isinstance(value, dict):
        raise InputError(f"{source}: [navigation] {key} must be a table ([navigation.{key}]), "
                         f"got {reprlib.repr(value)}")
    return dict(value)


def _text(section: dict, key: str, default: str, source: str, lower: bool = True) -> str:
    """``section[key]`` as text, lower-cased if ``lower`` (``default`` when absent); a number or array is an
    error naming the key (``str()`` would turn ``filter = 1`` into a name)."""
    value = section.get(key, default)
    if not isinstance(value, str):
        raise InputError(f"{source}: [navigation] {key} must be a string, got {reprlib.repr(value)}")
    return value.lower() if lower else value


def navigation_from_dict(section: dict, source: str = "<navigation>") -> NavigationConfig:
    """Build a :class:`NavigationConfig` from a parsed ``[navigation]`` table; errors name ``source``."""
    unknown = sorted(set(section) - _KEYS)
    if unknown:
        raise InputError(f"{source}: unknown key(s) {unknown} in [navigation]; known: {sorted(_KEYS)}")
    for key in ("epoch", "dynamics", "position_km", "velocity_km_s", "sigma_position_km", "sigma_velocity_km_s"):
        if key not in section:
            raise InputError(f"{source}: [navigation] needs {key}")
    scale = _text(section, "epoch_scale", "utc", source)
    try:
        # str(): a TOML date-time (epoch = 2014-07-15T00:00:00, unquoted) is calendar text too
        t0 = parse_epoch(str(section["epoch"]), scale)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{source}: bad [navigation] initial state ({exc})") from None
    x0 = np.concatenate([_vector3(section, "position_km", source), _vector3(section, "velocity_km_s", source)])
    sig = np.concatenate([_sigmas(section["sigma_position_km"], "sigma_position_km", source),
                          _sigmas(section["sigma_velocity_km_s"], "sigma_velocity_km_s", source)])
    corrections = _table(section, "corrections", {}, source)
    unknown = sorted(set(corrections) - {"light_time", "aberration"})
    if unknown:
        raise InputError(f"{source}: unknown key(s) {unknown} in [navigation.corrections]")
    gate = _typed(section, "gate_probability", float, 1.0 - 1e-6, source)
    propagation = _text(section, "propagation", "fast", source)
    if propagation not in PROPAGATION:
        raise InputError(f"{source}: [navigation] propagation must be one of {', '.join(PROPAGATION)}, "
                         f"got {section['propagation']!r}")
    seed = _typed(section, "seed", int, 0, source)
    if seed < 0:  # numpy's generators take non-negative seeds only
        raise InputError(f"{source}: [navigation] seed must be a non-negative integer, got {seed}")
    targets = section.get("ephemeris_targets", ["phobos", "deimos"])
    # a bare string would otherwise become a tuple of its letters
    if not (isinstance(targets, list) and all(isinstance(t, str) and t.strip() for t in targets)):
        raise InputError(f"{source}: [navigation] ephemeris_targets must be an array of body names, "
                         f"got {reprlib.repr(targets)}")
    try:
        return NavigationConfig(
            t0_tdb_s=t0, dynamics=_text(section, "dynamics", "", source, lower=False), x0=x0, P0=np.diag(sig**2),
            filter=_text(section, "filter", "ekf", source),
            gate_probability=None if gate == 0.0 else gate,
            target_position_sigma_km=_typed(section, "target_position_sigma_km", float, 0.0, source),
            light_time=_typed(corrections, "light_time", bool, True, source, "navigation.corrections"),
            aberration=_typed(corrections, "aberration", bool, True, source, "navigation.corrections"),
            seed=seed, exact=propagation == "exact",
            ephemeris_error=_text(section, "ephemeris_error", "white", source),
            ephemeris_targets=tuple(t.lower() for t in targets),
            process_noise=_table(section, "process_noise", {"model": "none"}, source),
            ukf=_table(section, "ukf", {}, source), particle=_table(section, "particle", {}, source),
            batch=_table(section, "batch", {}, source), federated=_table(section, "federated", {}, source),
        )
    except InputError as exc:
        raise InputError(f"{source}: {exc}") from None


def load_navigation(path: str | Path) -> NavigationConfig:
    """Read the ``[navigation]`` section of scenario TOML ``path`` (other sections are ignored here)."""
    path = Path(path)
    data = read_toml(path)
    if "navigation" not in data or not isinstance(data["navigation"], dict):
        raise InputError(f"{path}: no [navigation] section")
    return navigation_from_dict(data["navigation"], str(path))
