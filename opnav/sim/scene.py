"""Scene files: TOML -> a frozen, validated :class:`Scene` (``load_scene``).

:class:`SceneFile` is the file as written, one field per section (:data:`SECTIONS`); it is read
by :func:`opnav.config.build` from the dataclasses' type hints (values may also be written as
text, as ``--set`` gives them). Units are named in every key and converted here, once:

``[scenario]`` name, seed (>= 0) · ``[epochs]`` start, stop (calendar strings), scale,
step_s · ``[observer]`` either ``epoch`` + ``epoch_scale`` + ``position_km`` +
``velocity_km_s`` + ``frame`` (icrf | ecliptic) + ``center`` (the model's centre) +
``dynamics`` (a key of ``opnav.dynamics.MODELS``), or ``body`` + ``offset_km`` (fixed ICRF
offset from an ephemeris body, moving with it) · ``[camera]`` every
:class:`opnav.camera.Camera` field · ``[pointing]`` law (target | earth |
inertial), target (an ephemeris body), ra_deg, dec_deg, roll_deg · ``[targets]`` names ·
``[psf]`` :class:`opnav.render.PSF` fields · ``[detector]``
:class:`opnav.render.DetectorOptions` fields · ``[corrections]`` light_time,
aberration, parallax, proper_motion · ``[catalog]`` stars (false: draw no
stars, e.g. a UV Earth sensor), path (optional; an existing file, a relative path taken from
the scene file's folder), vmag_limit · ``[render]`` windowed, window_half_px (>= 1),
supersample, sun_keepout_margin_deg, sun_policy · ``[measurement]`` camera_file (optional; a camera
file, docs/formats/camera.md, the image stage measures with: a nominal or calibrated model of the
``[camera]`` the frames are rendered with; a relative path taken from the scene file's folder) ·
``[kernels]`` files (SPICE kernels or meta-kernels, relative paths from the scene file's folder), de421
(the shipped DE421 loaded under them): with files, every body's state comes from the kernels
(:meth:`Scene.ephemeris`, :class:`opnav.ephemeris.spice.SpiceEphemeris`), and ``[observer] body`` /
``center`` and ``[pointing] target`` may name any body their SPKs hold (a name or a NAIF id).

``[navigation]`` is read by :func:`opnav.filters.options.load_navigation`.

Everything is checked on load, by the rules of :mod:`opnav.config` (TOML values only, enumerated
names in any case, dates with ``Z`` only in UTC): unknown sections or keys raise
:class:`opnav.errors.InputError` naming the file and the table, suggesting the nearest known key
and listing them all; a bad value names the file, table and key and lists what is accepted.
"""

from __future__ import annotations

import contextvars
import dataclasses
import functools
import math
import reprlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..config import TIME_SCALES, CalendarText, Where, build, check_zone, read_toml
from ..epochs import parse_epoch
from ..errors import InputError, OpnavError
from ..frames import ecliptic_to_icrf
from ..bodies import BODIES, body_model
from ..render.detector import DetectorOptions
from ..render.frame import SUN_POLICIES, RenderOptions
from ..render.psf import PSF, PSF_KINDS
from ..observer import Corrections
from .pointing import POINTING_LAWS, PointingLaw


@dataclass(frozen=True)
class ObserverSpec:
    """Observer: a propagated initial state, or a fixed offset from an ephemeris body (km, km/s, ICRF)."""

    epoch_tdb_s: float | None = None
    position_km: tuple[float, float, float] | None = None
    velocity_km_s: tuple[float, float, float] | None = None
    center: str = "sun"
    dynamics: str | None = None
    body: str | None = None
    offset_km: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        propagated = self.position_km is not None
        if propagated == (self.body is not None):
            raise InputError("[observer] needs either position_km/velocity_km_s/epoch/dynamics or body/offset_km")
        if propagated:
            if self.velocity_km_s is None or self.epoch_tdb_s is None or self.dynamics is None:
                raise InputError("[observer] with position_km also needs velocity_km_s, epoch and dynamics")
            values = list(self.position_km) + list(self.velocity_km_s)
            if len(values) != 6 or not all(math.isfinite(v) for v in values):
                raise InputError(f"[observer] position_km/velocity_km_s must be 3 finite numbers each, got {values}")
        if not all(math.isfinite(v) for v in self.offset_km):
            raise InputError("[observer] offset_km must be finite")


@dataclass(frozen=True)
class Scene:
    """A validated scenario (renderer sections)."""

    name: str
    seed: int
    t_tdb_s: np.ndarray
    observer: ObserverSpec
    camera: Camera
    pointing: PointingLaw
    targets: tuple[str, ...]
    options: RenderOptions
    catalog_path: str | None = None
    stars: bool = True
    windowed: bool = False
    window_half_px: int = 12
    source: str = field(default="", compare=False)
    #: The camera the image stage assumes (``[measurement] camera_file``); None: ``camera``, the truth.
    measure_camera: Camera | None = None
    #: SPICE kernels in load order (``[kernels]``, absolute paths); empty: the default ephemeris (DE421).
    kernels: tuple[str, ...] = ()

    def ephemeris(self):
        """The ephemeris of this scene: its kernels' (:class:`opnav.ephemeris.spice.SpiceEphemeris`, shared
        by the scenes of the same kernels) or, without ``[kernels]``, the default (DE421 and the MAR080
        moons)."""
        if self.kernels:
            return kernel_ephemeris(self.kernels)
        from ..ephemeris import default_ephemeris

        return default_ephemeris()

    def truth(self, t_tdb_s, center: str = "sun", *, ephemeris=None) -> np.ndarray:
        """The observer's true states ``[r km, v km/s]`` (M, 6), ICRF, relative to ``center`` (an
        ephemeris body, or ``"ssb"``) at ``t_tdb_s`` (M,), TDB seconds past J2000.

        The states of :func:`observer_states` (through ``ephemeris``, default :meth:`ephemeris`) less the
        centre's.
        """
        if ephemeris is None:
            ephemeris = self.ephemeris()
        t = np.atleast_1d(np.asarray(t_tdb_s, dtype=float))
        r, v = observer_states(self, t, ephemeris)
        if center != "ssb":
            r_center, v_center = ephemeris.state(center, t)
            r, v = r - r_center, v - v_center
        return np.hstack([r, v])


def demo_scene_path() -> Path:
    """The packaged demo scene file (``opnav/data/demo.toml``): the 1-degree camera tracking Phobos
    along the S1 cruise from 15 July 2014, Phobos, Deimos and Mars in view, and a ``[navigation]``
    section (:func:`opnav.filters.options.load_navigation`) for the filters."""
    import importlib.resources

    return Path(str(importlib.resources.files("opnav").joinpath("data", "demo.toml")))


#: Most epochs a span may give (a year at 10 s is 3.2 million).
MAX_EPOCHS = 10_000_000


def epochs_between(start_tdb_s: float, stop_tdb_s: float, step_s: float) -> np.ndarray:
    """Epochs from start to stop inclusive (within 1 us) every ``step_s``."""
    if not (math.isfinite(step_s) and step_s >= 1e-6):
        raise InputError(f"epoch step_s must be positive (at least 1e-6 s), got {step_s!r}")
    if stop_tdb_s < start_tdb_s:
        raise InputError("epoch stop is before start")
    span = (stop_tdb_s - start_tdb_s + 1e-6) / step_s
    if not span < MAX_EPOCHS:
        raise InputError(f"epochs every {step_s:g} s from start to stop give {int(span) + 1:,} epochs; "
                         f"at most {MAX_EPOCHS:,}")
    n = int(math.floor(span)) + 1
    return start_tdb_s + step_s * np.arange(n)


#: Axes the ``[observer]`` vectors may be written in.
FRAMES = ("icrf", "ecliptic")


#: The kernels' ephemeris of the scene file being read (None: the default ephemeris), for :func:`ephemeris_bodies`.
_KERNEL_EPHEMERIS: contextvars.ContextVar = contextvars.ContextVar("scene_kernel_ephemeris", default=None)


def ephemeris_bodies() -> tuple[str, ...]:
    """The bodies the ephemeris answers for (``[observer] center``/``body``, ``[pointing] target``): the
    default ephemeris's, or, while a scene file with ``[kernels]`` is read, those the kernels' SPKs hold,
    by name and by NAIF id."""
    kernels = _KERNEL_EPHEMERIS.get()
    if kernels is not None:
        return tuple(dict.fromkeys(kernels.known_bodies() + tuple(str(naif) for naif in sorted(kernels.coverage))))
    from ..ephemeris import Ephemeris

    return Ephemeris.known_bodies()


def kernel_ephemeris(files: tuple[str, ...]):
    """The :class:`opnav.ephemeris.spice.SpiceEphemeris` of kernel ``files`` (in load order): one per set
    of files as they are on disk (a file rewritten, e.g. by ``opnav kernel``, gives a new one)."""
    stamps = []
    for name in files:
        try:
            info = Path(name).stat()
            stamps.append((info.st_mtime_ns, info.st_size))
        except (OSError, ValueError):  # missing, a name too long, a NUL byte: SpiceEphemeris names it
            stamps.append(None)
    return _kernel_ephemeris(tuple(files), tuple(stamps))


@functools.lru_cache(maxsize=8)
def _kernel_ephemeris(files: tuple[str, ...], stamps: tuple) -> object:
    del stamps  # part of the cache key only
    from ..ephemeris.spice import SpiceEphemeris

    return SpiceEphemeris(files)


def force_models() -> tuple[str, ...]:
    """The force models by name (``[observer] dynamics``): the keys of :data:`opnav.dynamics.MODELS`."""
    from ..dynamics import MODELS

    return tuple(MODELS)


def target_bodies() -> tuple[str, ...]:
    """The bodies a scene can draw (``[targets] names``): :data:`opnav.bodies.BODIES`."""
    return tuple(sorted(BODIES))


@dataclass(frozen=True)
class ScenarioTable:
    """``[scenario]``: the scene's name (default: the file's stem) and the seed of its random draws."""

    name: str | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if self.seed < 0:  # numpy's generators take non-negative seeds only
            raise InputError(f"[scenario] seed must be a non-negative integer, got {self.seed}")


@dataclass(frozen=True)
class EpochsTable:
    """``[epochs]``: frame epochs from ``start`` to ``stop`` (default: ``start``) every ``step_s``, dates in ``scale``."""

    start: CalendarText | None = None
    stop: CalendarText | None = None
    scale: str = field(default="utc", metadata={"choices": TIME_SCALES})
    step_s: float = 60.0


@dataclass(frozen=True)
class ObserverTable:
    """``[observer]`` as written: dates and, with ``frame = "ecliptic"``, ecliptic vectors (see :class:`ObserverSpec`)."""

    epoch: CalendarText | None = None
    epoch_scale: str = field(default="utc", metadata={"choices": TIME_SCALES})
    frame: str = field(default="icrf", metadata={"choices": FRAMES})
    position_km: tuple[float, float, float] | None = None
    velocity_km_s: tuple[float, float, float] | None = None
    center: str = field(default="sun", metadata={"choices": ephemeris_bodies})
    dynamics: str | None = field(default=None, metadata={"choices": force_models})
    body: str | None = field(default=None, metadata={"choices": ephemeris_bodies})
    offset_km: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class PointingTable:
    """``[pointing]`` as written, angles in degrees (:class:`opnav.sim.pointing.PointingLaw`)."""

    law: str = field(default="inertial", metadata={"choices": POINTING_LAWS})
    target: str | None = field(default=None, metadata={"choices": ephemeris_bodies})
    ra_deg: float = 0.0
    dec_deg: float = 0.0
    roll_deg: float = 0.0


@dataclass(frozen=True)
class TargetsTable:
    """``[targets]``: the bodies drawn and measured."""

    names: tuple[str, ...] = field(default=(), metadata={"choices": target_bodies})


@dataclass(frozen=True)
class CatalogTable:
    """``[catalog]``: stars drawn or not, the catalog file (default: the packaged one; a relative path is
    taken from the scene file's folder by :func:`load_scene`), the faintest magnitude."""

    stars: bool = True
    path: str | None = None
    vmag_limit: float | None = None


@dataclass(frozen=True)
class RenderTable:
    """``[render]``: windows or full frames, supersampling and the Sun keep-out (degrees)."""

    windowed: bool = False
    window_half_px: int = 12
    supersample: int = 4
    sun_keepout_margin_deg: float = 10.0
    sun_policy: str = field(default="flag", metadata={"choices": SUN_POLICIES})

    def __post_init__(self) -> None:
        if self.window_half_px < 1:
            raise InputError(f"[render] window_half_px must be a positive integer, got {self.window_half_px}")


@dataclass(frozen=True)
class MeasurementTable:
    """``[measurement]``: the camera file the image stage measures with (default: ``[camera]`` itself,
    a perfectly known camera); a relative path is taken from the scene file's folder."""

    camera_file: str | None = None


@dataclass(frozen=True)
class KernelsTable:
    """``[kernels]``: SPICE kernels or meta-kernels in load order (later files take priority; a relative
    path is taken from the scene file's folder) and whether the shipped DE421 is loaded under them."""

    files: tuple[str, ...] = ()
    de421: bool = True


@dataclass(frozen=True)
class SceneFile:
    """A scene file as written: one field per section (read by :func:`opnav.config.build`)."""

    scenario: ScenarioTable
    epochs: EpochsTable
    observer: ObserverTable
    camera: Camera
    pointing: PointingTable
    targets: TargetsTable
    psf: PSF
    detector: DetectorOptions
    corrections: Corrections
    catalog: CatalogTable
    render: RenderTable
    measurement: MeasurementTable
    kernels: KernelsTable
    navigation: dict = field(default_factory=dict)  # read by opnav.filters.options.load_navigation


SECTIONS = tuple(f.name for f in dataclasses.fields(SceneFile))
#: Enumerated keys of the sections whose classes live elsewhere (:func:`opnav.config.build`'s ``choices``).
CHOICES = {PSF: {"kind": PSF_KINDS}}


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file; ``InputError`` naming the file on any problem."""
    path = Path(path)
    source = str(path)
    table = read_toml(path, kind="scene file")
    kernels = _kernel_files(table.get("kernels", {}), source)
    # the body keys are checked against the kernels' bodies while the file is built
    context = _KERNEL_EPHEMERIS.set(_scene_kernels(kernels, source) if kernels else None)
    try:
        data = build(SceneFile, table, Where(source), noun="section", choices=CHOICES)
    finally:
        _KERNEL_EPHEMERIS.reset(context)
    try:
        return _scene(data, source, kernels)
    except OpnavError as exc:
        if source in str(exc):
            raise
        raise type(exc)(f"{source}: {exc}") from None


def _kernel_files(table, source: str) -> tuple[str, ...]:
    """``[kernels]`` as absolute paths in load order (the shipped DE421 first when ``de421``); empty
    without ``files``."""
    kernels = build(KernelsTable, table, Where(source, "kernels"))
    if not kernels.files:
        return ()
    files = []
    for given in kernels.files:
        try:
            path = Path(given).expanduser()
        except RuntimeError:  # ~user of no such user
            path = Path(given)
        files.append(str(path if path.is_absolute() else Path(source).parent / path))
    if kernels.de421:
        from ..ephemeris.planets import default_kernel_path

        files.insert(0, str(default_kernel_path()))
    return tuple(files)


def _scene_kernels(files: tuple[str, ...], source: str):
    """The kernels' ephemeris, or ``InputError`` naming the scene file, ``[kernels]`` and the kernel."""
    from ..ephemeris.spice import KernelError

    try:
        return kernel_ephemeris(files)
    except KernelError as exc:
        raise KernelError(f"{source}: [kernels] files: {exc}") from None


def _scene(data: SceneFile, source: str, kernels: tuple[str, ...] = ()) -> Scene:
    """The :class:`Scene` of a read file: dates to TDB seconds, degrees to radians, ecliptic to ICRF,
    the catalog path from the scene file's folder; the checks that span keys."""
    epochs = data.epochs
    if epochs.start is None:
        raise InputError("[epochs] needs start (and optionally stop, step_s, scale)")
    check_zone(epochs.start, epochs.scale, "[epochs] start")
    check_zone(epochs.stop, epochs.scale, "[epochs] stop")
    t = epochs_between(parse_epoch(epochs.start, epochs.scale),
                       parse_epoch(epochs.stop or epochs.start, epochs.scale), epochs.step_s)
    obs = data.observer
    check_zone(obs.epoch, obs.epoch_scale, "[observer] epoch")
    if obs.dynamics is not None and obs.body is None:
        model_center = _model_center(obs.dynamics)
        if model_center is not None and model_center != obs.center:
            raise InputError(f"[observer] center must be {model_center!r}, the centre of dynamics "
                             f"{obs.dynamics!r}, got {obs.center!r}")

    def icrf(vector):
        if vector is None or obs.frame == "icrf":
            return vector
        return tuple(float(v) for v in ecliptic_to_icrf(np.asarray(vector)))

    observer = ObserverSpec(
        epoch_tdb_s=None if obs.epoch is None else parse_epoch(obs.epoch, obs.epoch_scale),
        position_km=icrf(obs.position_km), velocity_km_s=icrf(obs.velocity_km_s), center=obs.center,
        dynamics=obs.dynamics, body=obs.body, offset_km=icrf(obs.offset_km),
    )
    pointing = data.pointing
    pointing_law = PointingLaw(law=pointing.law, target=pointing.target, ra_rad=math.radians(pointing.ra_deg),
                               dec_rad=math.radians(pointing.dec_deg), roll_rad=math.radians(pointing.roll_deg))
    for name in data.targets.names:
        body_model(name)
    if kernels:  # a body drawn must be in the kernels too (its shape is still opnav's)
        for name in data.targets.names:
            try:
                kernel_ephemeris(kernels).check_body(name)
            except InputError as exc:
                raise InputError(f"[targets] names: {exc}") from None
    catalog, render = data.catalog, data.render
    options = RenderOptions(
        psf=data.psf, detector=data.detector, corrections=data.corrections, vmag_limit=catalog.vmag_limit,
        sun_keepout_margin_rad=math.radians(render.sun_keepout_margin_deg), sun_policy=render.sun_policy,
        supersample=render.supersample,
    )
    return Scene(
        name=data.scenario.name if data.scenario.name is not None else Path(source).stem,
        seed=data.scenario.seed,
        t_tdb_s=t,
        observer=observer,
        camera=data.camera,
        pointing=pointing_law,
        targets=data.targets.names,
        options=options,
        catalog_path=_catalog_path(catalog.path, source),
        stars=catalog.stars,
        windowed=render.windowed,
        window_half_px=render.window_half_px,
        source=source,
        measure_camera=_measure_camera(data.measurement.camera_file, source, data.camera),
        kernels=kernels,
    )


def _measure_camera(path: str | None, source: str, camera: Camera) -> Camera | None:
    """``[measurement] camera_file`` read (a relative path from the scene file's folder), the same detector
    size as ``[camera]``; None without one."""
    if path is None:
        return None
    from ..camera import read_camera_file

    given = Path(path).expanduser()
    resolved = given if given.is_absolute() else Path(source).parent / given
    assumed = read_camera_file(resolved).camera
    if assumed.shape != camera.shape:
        raise InputError(f"[measurement] camera_file {resolved} is a {assumed.width_px} x {assumed.height_px} px "
                         f"camera; [camera] is {camera.width_px} x {camera.height_px} px")
    return assumed


def _model_center(name: str) -> str | None:
    """The centre of force model ``name``, without reading an ephemeris (None if it cannot be told)."""
    from ..dynamics import get_model

    class _Unread:  # a position source the model stores but, built and not run, never asks
        pass

    try:
        return get_model(name, ephemeris=_Unread()).center
    except TypeError:  # a model factory without an ephemeris argument: checked when it is built
        return None


def _catalog_path(path: str | None, source: str) -> str | None:
    """``[catalog] path`` as an existing file; a relative path is taken from the scene file's folder."""
    if path is None:
        return None
    try:
        given = Path(path).expanduser()
    except RuntimeError:  # ~user of no such user
        given = Path(path)
    resolved = given if given.is_absolute() else Path(source).parent / given
    try:
        found = resolved.is_file()
    except (OSError, ValueError):  # a name too long, a NUL byte
        found = False
    if not found:
        where = "" if given.is_absolute() else " (a relative path is taken from the scene file's folder)"
        raise InputError(f"[catalog] path must be an existing catalog file{where}, got {reprlib.repr(path)}: "
                         f"no file {reprlib.repr(str(resolved))}")
    return str(resolved)


def observer_states(scenario: Scene, t_tdb_s: np.ndarray, ephemeris) -> tuple[np.ndarray, np.ndarray]:
    """Observer SSB positions (km) and velocities (km/s), ICRF, at ``t_tdb_s`` (M,)."""
    spec = scenario.observer
    t = np.atleast_1d(np.asarray(t_tdb_s, dtype=float))
    if spec.body is not None:
        r, v = ephemeris.state(spec.body, t)
        return np.asarray(r) + np.asarray(spec.offset_km), np.asarray(v)
    from ..dynamics import get_model, propagate
    from .pointing import trajectory_to_ssb

    model = get_model(spec.dynamics)
    if getattr(model, "center", spec.center) != spec.center:
        raise InputError(f"[observer] center {spec.center!r} differs from dynamics model {spec.dynamics!r} center {model.center!r}")
    state0 = np.concatenate([spec.position_km, spec.velocity_km_s])
    trajectory = propagate(model, spec.epoch_tdb_s, state0, t)
    _, r, v = trajectory_to_ssb(trajectory, ephemeris)
    return r, v
