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
    ephemeris_targets = ["phobos", "deimos"]   # distinct ephemeris bodies
    camera_error = "white"             # white: the records' covariances as they are (the camera exact, or its
                                       # covariance added to each record's by the image stage);
                                       # consider: the camera's parameter errors appended to the state as
                                       # consider parameters (EKF only, ephemeris_error = "white"), prior
                                       # covariance camera_file's [calibration], each record's Jacobian
                                       # from the image stage (opnav.measurements.CameraOffsetModel)
    camera_file = "calibrated.toml"    # camera_error = "consider": the camera file the records were
                                       # measured with (relative: from this file's folder)
    seed = 0                           # particle filters' generator
    propagation = "fast"               # fast: compiled fixed-step RK8 + cached ephemeris (opnav.dynamics.fast);
                                       # exact: DOP853 at rtol 1e-11 and the exact ephemeris (CLI: --exact)

    [navigation.process_noise]         # see opnav.filters.noise.process_noise_from_config
    model = "white"                    # white (q_km2_s3) | snc (q_ric_km2_s3) | none (no density)
    q_km2_s3 = 0.0

    [navigation.corrections]
    light_time = true
    aberration = true

    [navigation.ukf]                   # alpha, beta, kappa (opnav.filters.ukf.UKFOptions); the gate is
                                       # gate_probability above
    [navigation.particle]              # n_particles (default 2000 for pf, 150 for upf/mcmc-upf),
                                       # resample_fraction, bandwidth_scale, component_fraction,
                                       # correction_ess, max_corrections (opnav.filters.particle.ParticleOptions)
    [navigation.particle.ukf]          # the UPFs' sigma points: alpha, beta, kappa
    [navigation.batch]                 # max_iterations, tolerance (opnav.filters.batch.BatchOptions)
    [navigation.federated]             # local_filter (ekf | ukf | sr-ukf), mode (fusion-reset | no-reset),
                                       # fusion_interval_s (default: fuse at every record epoch)
                                       # (opnav.filters.federated.FederatedSetup)

Every key and value is checked on load, by the rules of :mod:`opnav.config` (TOML values only:
``"false"`` is not false; enumerated names such as ``filter``, ``dynamics`` or the bodies of
``ephemeris_targets`` in any case, stored as listed; a date with ``Z`` only in UTC): an unknown
key, a value of the wrong type, a name that is not one of those accepted, a process-noise density
its model does not use or a value its options class refuses raises :class:`opnav.errors.InputError`
naming the file, the table and the key (an unknown key with the nearest known one suggested).
"""

from __future__ import annotations

import reprlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import TIME_SCALES, CalendarText, Where, build, check_zone, read_toml
from ..epochs import parse_epoch
from ..errors import InputError
from .noise import PROCESS_NOISE_MODELS, process_noise_from_config
from .option_types import FILTERS, BatchOptions, FederatedSetup, ParticleOptions, UKFOptions

EPHEMERIS_ERROR = ("white", "estimate", "consider")
CAMERA_ERROR = ("white", "consider")
PROPAGATION = ("fast", "exact")


def force_models() -> tuple[str, ...]:
    """The force models by name (``[navigation] dynamics``): the keys of :data:`opnav.dynamics.MODELS`."""
    from ..dynamics import MODELS

    return tuple(MODELS)


def ephemeris_bodies() -> tuple[str, ...]:
    """The bodies the ephemeris answers for (``[navigation] ephemeris_targets``)."""
    from ..ephemeris import Ephemeris

    return Ephemeris.known_bodies()


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
    camera_error : str
        How filters treat the error of the camera the records were measured with: ``white`` (as the
        records' covariances have it) or ``consider`` (its parameters' errors appended to the state,
        after the first six, as consider parameters of the EKF: :class:`opnav.measurements.CameraOffsetModel`).
    camera_parameters : tuple of str
        ``consider``: the camera's calibrated parameters (:data:`opnav.camera.CALIBRATION_PARAMETERS`).
    camera_covariance : (P, P) array or None
        ``consider``: their covariance (the camera file's ``[calibration]``; ``f``, ``cx``, ``cy`` px,
        Brown coefficients dimensionless), the consider states' prior.
    process_noise : dict
        The ``[navigation.process_noise]`` table (:func:`opnav.filters.noise.process_noise_from_config`).
    ukf : UKFOptions
        Sigma-point parameters of the UKF and SR-UKF (their gate is :attr:`gate_probability`).
    particle : ParticleOptions
        Settings of the particle filters (gate and MCMC move set from :attr:`gate_probability`
        and the filter's name).
    batch : BatchOptions
        Iteration control of batch least squares (``wls``).
    federated : FederatedSetup
        Local filter, mode and fusion interval of the federated filter.

    A table (mapping) given for ``ukf``, ``particle``, ``batch`` or ``federated`` (e.g. read back
    from JSON) is built into its options class, its keys and values checked.
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
    camera_error: str = "white"
    camera_parameters: tuple[str, ...] = ()
    camera_covariance: np.ndarray | None = None
    process_noise: dict = field(default_factory=lambda: {"model": "none"})
    ukf: UKFOptions = field(default_factory=UKFOptions)
    particle: ParticleOptions = field(default_factory=ParticleOptions)
    batch: BatchOptions = field(default_factory=BatchOptions)
    federated: FederatedSetup = field(default_factory=FederatedSetup)

    def __post_init__(self) -> None:
        for name, kind in (("ukf", UKFOptions), ("particle", ParticleOptions), ("batch", BatchOptions),
                           ("federated", FederatedSetup)):
            value = getattr(self, name)
            if isinstance(value, Mapping):
                object.__setattr__(self, name, build(kind, value, Where("NavigationConfig", f"navigation.{name}")))
            elif not isinstance(value, kind):
                raise InputError(f"[navigation] {name} must be a {kind.__name__} or a table, got {reprlib.repr(value)}")
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
        self._check_camera()

    def _check_camera(self) -> None:
        # a table read back from JSON gives lists: the names a tuple, the covariance an array
        object.__setattr__(self, "camera_parameters", tuple(self.camera_parameters))
        if self.camera_covariance is not None:
            object.__setattr__(self, "camera_covariance", np.asarray(self.camera_covariance, dtype=float))
        if self.camera_error not in CAMERA_ERROR:
            raise InputError(f"[navigation] camera_error must be one of {', '.join(CAMERA_ERROR)}, "
                             f"got {self.camera_error!r}")
        if self.camera_error == "white":
            return
        if self.filter != "ekf":
            raise InputError("[navigation] camera_error = 'consider' works with filter = 'ekf' only "
                             f"(got {self.filter!r})")
        if self.ephemeris_error != "white":
            raise InputError("[navigation] camera_error = 'consider' works with ephemeris_error = 'white' only "
                             f"(got {self.ephemeris_error!r})")
        names, cov = self.camera_parameters, self.camera_covariance
        if not names or cov is None or cov.shape != (len(names), len(names)):
            raise InputError("[navigation] camera_error = 'consider' needs the camera's calibrated parameters and "
                             "their covariance (camera_file: a camera file with a [calibration] table, from opnav "
                             "calibrate)")
        if not (np.all(np.isfinite(cov)) and np.allclose(cov, cov.T, rtol=1e-9, atol=0.0)
                and np.linalg.eigvalsh(cov).min() > 0.0):
            raise InputError("[navigation] camera_error = 'consider': the camera's [calibration] covariance must be "
                             "finite, symmetric and positive definite")
        object.__setattr__(self, "camera_covariance", 0.5 * (cov + cov.T))

    @property
    def augmented(self) -> tuple[np.ndarray, np.ndarray]:
        """Initial state and covariance with the ephemeris offsets appended (zero, sigma^2 per axis), or the
        camera's parameter errors (zero, the calibration's covariance)."""
        if self.camera_error == "consider":
            block = self.camera_covariance
        elif self.ephemeris_error != "white":
            block = self.target_position_sigma_km**2 * np.eye(3 * len(self.ephemeris_targets))
        else:
            return self.x0, self.P0
        extra = len(block)
        x0 = np.concatenate([self.x0, np.zeros(extra)])
        P0 = np.zeros((6 + extra, 6 + extra))
        P0[:6, :6] = self.P0
        P0[6:, 6:] = block
        return x0, P0


@dataclass(frozen=True)
class NavigationCorrections:
    """``[navigation.corrections]``: the apparent-direction corrections the filters' models apply."""

    light_time: bool = True
    aberration: bool = True


@dataclass(frozen=True)
class ProcessNoiseTable:
    """``[navigation.process_noise]`` as written (:func:`opnav.filters.noise.process_noise_from_config` reads it).

    Attributes
    ----------
    model : str
        ``white`` (needs ``q_km2_s3``), ``snc`` (needs ``q_ric_km2_s3``) or ``none``.
    q_km2_s3 : float or None
        White-acceleration spectral density per axis, km^2/s^3.
    q_ric_km2_s3 : 3 floats or None
        Radial, in-track and cross-track densities, km^2/s^3.
    """

    model: str = field(default="white", metadata={"choices": PROCESS_NOISE_MODELS})
    q_km2_s3: float | None = None
    q_ric_km2_s3: tuple[float, float, float] | None = None


_SIGMAS = "one positive number or three, each with a finite non-zero square (about 1e-160 to 1e154)"


@dataclass(frozen=True)
class NavigationFile:
    """The ``[navigation]`` table as written (the module notes give each key); read by
    :func:`opnav.config.build`, turned into a :class:`NavigationConfig` by :func:`navigation_from_dict`."""

    epoch: CalendarText
    dynamics: str = field(metadata={"choices": force_models})
    position_km: tuple[float, float, float]
    velocity_km_s: tuple[float, float, float]
    sigma_position_km: float | tuple[float, float, float] = field(metadata={"accepts": _SIGMAS})
    sigma_velocity_km_s: float | tuple[float, float, float] = field(metadata={"accepts": _SIGMAS})
    epoch_scale: str = field(default="utc", metadata={"choices": TIME_SCALES})
    filter: str = field(default="ekf", metadata={"choices": FILTERS})
    gate_probability: float = 1.0 - 1e-6
    target_position_sigma_km: float = 0.0
    seed: int = 0
    propagation: str = field(default="fast", metadata={"choices": PROPAGATION})
    ephemeris_error: str = field(default="white", metadata={"choices": EPHEMERIS_ERROR})
    ephemeris_targets: tuple[str, ...] = field(default=("phobos", "deimos"), metadata={"choices": ephemeris_bodies})
    camera_error: str = field(default="white", metadata={"choices": CAMERA_ERROR})
    camera_file: str = ""
    process_noise: ProcessNoiseTable | None = None
    corrections: NavigationCorrections = field(default_factory=NavigationCorrections)
    ukf: UKFOptions = field(default_factory=UKFOptions)
    particle: ParticleOptions = field(default_factory=ParticleOptions)
    batch: BatchOptions = field(default_factory=BatchOptions)
    federated: FederatedSetup = field(default_factory=FederatedSetup)


#: Option fields the ``[navigation]`` keys set, not the sub-tables, and where their value comes from
#: (the message when a sub-table writes one): the gate is ``gate_probability`` and the MCMC move
#: follows the filter's name (``upf`` or ``mcmc-upf``).
_GATE = "the gate of every filter is [navigation] gate_probability"
SET_BY_NAVIGATION = {
    UKFOptions: {"gate_probability": _GATE},
    ParticleOptions: {"gate_probability": _GATE,
                      "mcmc_move": "the MCMC move follows [navigation] filter (on for mcmc-upf, off for upf)"},
}


def _sigmas(value, name: str) -> np.ndarray:
    numbers = np.array(value if isinstance(value, tuple) else (value,) * 3)
    # a sigma whose square under- or overflows would give a zero or infinite variance in P0
    if not all(v > 0.0 and 0.0 < v * v < np.inf for v in numbers):
        raise InputError(f"[navigation] {name} must be {_SIGMAS}, got {reprlib.repr(value)}")
    return numbers


def navigation_from_dict(section: dict, source: str = "<navigation>") -> NavigationConfig:
    """Build a :class:`NavigationConfig` from a parsed ``[navigation]`` table; errors name ``source``.

    Values must be TOML's own (``"false"`` is not false, ``"1.5"`` not a number); the table's
    keys and types are those of :class:`NavigationFile`, its option sub-tables those of
    :class:`~opnav.filters.ukf.UKFOptions`, :class:`~opnav.filters.particle.ParticleOptions`,
    :class:`~opnav.filters.batch.BatchOptions` and :class:`~opnav.filters.federated.FederatedSetup`
    (less :data:`SET_BY_NAVIGATION`), so a bad option fails here, not when a filter is built.
    """
    where = Where(source, "navigation")
    table = build(NavigationFile, section, where, exclude=SET_BY_NAVIGATION)
    try:
        check_zone(table.epoch, table.epoch_scale, "[navigation] epoch")
        t0 = parse_epoch(table.epoch, table.epoch_scale)
    except InputError as exc:
        raise InputError(f"{source}: bad [navigation] initial state ({exc})") from None
    if table.seed < 0:  # numpy's generators take non-negative seeds only
        raise InputError(f"{source}: [navigation] seed must be a non-negative integer, got {table.seed}")
    if len(set(table.ephemeris_targets)) != len(table.ephemeris_targets):
        raise InputError(f"{source}: [navigation] ephemeris_targets must name each body once, "
                         f"got {reprlib.repr(list(table.ephemeris_targets))}")
    noise = {"model": "none"}
    if table.process_noise is not None:
        noise = {}  # the keys as written, their values typed
        for key in section["process_noise"]:
            value = getattr(table.process_noise, key)
            noise[key] = list(value) if isinstance(value, tuple) else value
        try:
            process_noise_from_config(noise)  # an unknown model or a missing density fails on load too
        except InputError as exc:
            raise InputError(f"{source}: [navigation.process_noise] {exc}") from None
    names, covariance = _camera_calibration(table, source)
    try:
        sig = np.concatenate([_sigmas(table.sigma_position_km, "sigma_position_km"),
                              _sigmas(table.sigma_velocity_km_s, "sigma_velocity_km_s")])
        gate = table.gate_probability
        return NavigationConfig(
            t0_tdb_s=t0, dynamics=table.dynamics, x0=np.array(table.position_km + table.velocity_km_s),
            P0=np.diag(sig**2), filter=table.filter, gate_probability=None if gate == 0.0 else gate,
            target_position_sigma_km=table.target_position_sigma_km,
            light_time=table.corrections.light_time, aberration=table.corrections.aberration,
            seed=table.seed, exact=table.propagation == "exact", ephemeris_error=table.ephemeris_error,
            ephemeris_targets=table.ephemeris_targets, camera_error=table.camera_error, camera_parameters=names,
            camera_covariance=covariance, process_noise=noise, ukf=table.ukf, particle=table.particle,
            batch=table.batch, federated=table.federated,
        )
    except InputError as exc:
        raise InputError(f"{source}: {exc}") from None


def _camera_calibration(table: NavigationFile, source: str) -> tuple[tuple[str, ...], np.ndarray | None]:
    """``camera_file``'s ``[calibration]`` names and covariance for ``camera_error = "consider"`` (a relative
    path from the folder of ``source``, when that is a file); ``((), None)`` for ``white``."""
    if table.camera_error == "white":
        if table.camera_file:
            raise InputError(f"{source}: [navigation] camera_file is read with camera_error = 'consider' only; "
                             "drop it or set camera_error")
        return (), None
    if not table.camera_file:
        raise InputError(f"{source}: [navigation] camera_error = 'consider' needs camera_file (the camera file the "
                         "records were measured with, with a [calibration] table from opnav calibrate)")
    from ..camera import read_camera_file

    path = Path(table.camera_file).expanduser()
    if not path.is_absolute() and Path(source).is_file():
        path = Path(source).parent / path
    calibration = read_camera_file(path).calibration
    if calibration is None:
        raise InputError(f"{source}: [navigation] camera_error = 'consider': camera_file {path} has no [calibration] "
                         "table (docs/formats/camera.md); write one with opnav calibrate")
    return calibration.names, calibration.covariance


def load_navigation(path: str | Path) -> NavigationConfig:
    """Read the ``[navigation]`` section of scene file ``path`` (other sections are ignored here)."""
    path = Path(path)
    data = read_toml(path, kind="navigation file")
    if "navigation" not in data or not isinstance(data["navigation"], dict):
        raise InputError(f"{path}: no [navigation] section")
    return navigation_from_dict(data["navigation"], str(path))


def navigation_files() -> list[str]:
    """The TOML files shipped with a ``[navigation]`` section: the packaged demo scene and, in a
    checkout, those of ``samples/`` (paths relative to the working folder when under it)."""
    import importlib.resources
    import os

    def shown(path: Path) -> str:
        relative = os.path.relpath(path)
        return relative if not relative.startswith("..") else str(path)

    demo = Path(str(importlib.resources.files("opnav").joinpath("data", "demo.toml")))  # the demo scene
    found = [shown(demo)]
    samples = demo.parent.parent.parent / "samples"
    for path in sorted(samples.glob("*.toml")) if samples.is_dir() else ():
        try:
            if isinstance(read_toml(path, kind="TOML file").get("navigation"), dict):
                found.append(shown(path))
        except InputError:
            continue
    return found
