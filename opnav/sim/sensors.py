"""What the render -> measure loop (:mod:`opnav.sim.loop`) runs: its sensors, the arc, the frames on disk,
where the catalog and ephemerides come from, and the study's hook.

- :class:`Sensor`: a camera, how it is pointed (its own :class:`~opnav.sim.pointing.PointingLaw`, or a
  mounting on a body whose attitude the :class:`Arc` gives), what is drawn, its image stage
  (:mod:`opnav.sim.stages`) and its random :class:`Streams`;
- :class:`Arc`: epochs and true observer states (and the body's attitude), a chunk of it with
  :meth:`Arc.part`;
- :class:`Storage` and :class:`FrameTag`: frames on disk, and the tag that lets a re-run reuse them;
- :class:`Sky` and :func:`loop_sources`: the star catalog and ephemerides by name, loaded once per process;
- :class:`FrameHook`: what a study changes (frame faults, the truth's ephemeris error);
- :class:`Loop`: all of it with the seed of every stream.

Vectors: ICRF; observer states relative to the SSB, km and km/s; epochs TDB seconds past J2000.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..errors import InputError
from ..render.frame import RenderOptions
from .pointing import PointingLaw
from .stages import Centre, FullFrame, Limb, Tracking


@dataclass(frozen=True)
class Streams:
    """Random streams of a sensor (module notes): frame ``k``'s render noise from
    ``default_rng([seed, *render, k])``, its image stage from ``default_rng([seed, *measure, k])``."""

    render: tuple[int, ...] = ()
    measure: tuple[int, ...] = (1,)

    def rng(self, seed: int, purpose: str, k: int) -> np.random.Generator:
        """Frame ``k``'s generator for ``purpose`` (``"render"`` or ``"measure"``)."""
        return np.random.default_rng([seed, *getattr(self, purpose), k])


@dataclass(frozen=True, eq=False)
class Sensor:
    """A camera, how it is pointed and how its frames are measured.

    Attributes
    ----------
    camera : Camera
        The true camera: the frames are rendered with it.
    stage : FullFrame, Tracking, Limb, Centre or None
        The image stage (:mod:`opnav.sim.stages`); None renders only.
    pointing : PointingLaw, optional
        The camera's own guidance law (attitude and body rate). Exactly one of ``pointing`` and
        ``mounting``.
    mounting : Rotation, optional
        Camera -> body rotation of a camera fixed on the body; its attitude is
        ``Arc.R_icrf_body[k] * mounting`` and it does not turn during the exposure.
    targets : tuple of str
        Bodies drawn.
    render : RenderOptions
        PSF, detector, corrections and magnitude limit of the frames.
    stars : bool
        Draw catalog stars (False: a UV Earth sensor).
    window_half_px : int, optional
        Render only windows of this half side around the stars and targets (no stage only).
    name : str
        Prefixes the reasons its frames are skipped ("star sensor: ...") when set.
    streams : Streams
    measure_camera : Camera, optional
        The camera the image stage assumes (a nominal or calibrated model, e.g. from a camera file):
        it turns the frames' pixels into directions and predicts the windows. None: ``camera``, the
        truth (a perfectly known camera). Same detector size as ``camera``.
    """

    camera: Camera
    stage: FullFrame | Tracking | Limb | Centre | None = None
    pointing: PointingLaw | None = None
    mounting: Rotation | None = None
    targets: tuple[str, ...] = ()
    render: RenderOptions = field(default_factory=RenderOptions)
    stars: bool = True
    window_half_px: int | None = None
    name: str = ""
    streams: Streams = field(default_factory=Streams)
    measure_camera: Camera | None = None

    def __post_init__(self) -> None:
        if self.measure_camera is not None and self.measure_camera.shape != self.camera.shape:
            raise InputError(f"the camera the stage assumes is {self.measure_camera.width_px} x "
                             f"{self.measure_camera.height_px} px; the frames' camera {self.camera.width_px} x "
                             f"{self.camera.height_px} px")
        if (self.pointing is None) == (self.mounting is None):
            raise InputError("a sensor needs either a pointing law or a mounting on the body")
        if isinstance(self.stage, (Limb, Centre)) and self.mounting is None:
            raise InputError("a limb or centre sensor follows its reference sensor through the mountings: give it one")
        if self.window_half_px is not None and self.stage is not None:
            raise InputError("window_half_px is for sensors that only render; a stage chooses its own windows")

    @property
    def assumed_camera(self) -> Camera:
        """The camera the image stage measures with: ``measure_camera``, else the true ``camera``."""
        return self.camera if self.measure_camera is None else self.measure_camera


def scene_sensor(scene, stage: FullFrame | Tracking | None = None) -> Sensor:
    """The camera of ``scene`` (:class:`opnav.sim.scene.Scene`) as a sensor with ``stage``: its pointing
    law, targets, render options and stars (windowed when the scene says so and there is no stage), and
    the camera its stage assumes (``scene.measure_camera``)."""
    return Sensor(scene.camera, stage, pointing=scene.pointing, targets=tuple(scene.targets), render=scene.options,
                  stars=scene.stars, window_half_px=scene.window_half_px if scene.windowed and stage is None else None,
                  measure_camera=scene.measure_camera)


@dataclass(frozen=True, eq=False)
class Arc:
    """The frames' epochs and true observer states.

    Attributes
    ----------
    t_tdb_s : (M,) array
        Mid-exposure epochs, TDB seconds past J2000.
    r_ssb_km, v_ssb_km_s : (M, 3) arrays
        Observer position (km) and velocity (km/s) relative to the SSB, ICRF.
    R_icrf_body : Rotation of length M, optional
        Body -> ICRF attitude per frame (for sensors with a mounting).
    first : int
        Index of the first frame in the whole arc (a chunk's offset).
    """

    t_tdb_s: np.ndarray
    r_ssb_km: np.ndarray
    v_ssb_km_s: np.ndarray
    R_icrf_body: Rotation | None = None
    first: int = 0

    def __post_init__(self) -> None:
        t = np.atleast_1d(np.asarray(self.t_tdb_s, dtype=float))
        r = np.asarray(self.r_ssb_km, dtype=float).reshape(-1, 3)
        v = np.asarray(self.v_ssb_km_s, dtype=float).reshape(-1, 3)
        if not (len(t) == len(r) == len(v)) or (self.R_icrf_body is not None and len(self.R_icrf_body) != len(t)):
            raise InputError(f"arc: epochs, positions, velocities and body attitudes disagree in length "
                             f"({len(t)}, {len(r)}, {len(v)})")
        object.__setattr__(self, "t_tdb_s", t)
        object.__setattr__(self, "r_ssb_km", r)
        object.__setattr__(self, "v_ssb_km_s", v)

    def __len__(self) -> int:
        return int(self.t_tdb_s.size)

    def part(self, start: int, stop: int) -> "Arc":
        """Frames ``start`` to ``stop`` (exclusive) of this arc, indices kept."""
        body = None if self.R_icrf_body is None else self.R_icrf_body[start:stop]
        return Arc(self.t_tdb_s[start:stop], self.r_ssb_km[start:stop], self.v_ssb_km_s[start:stop], body,
                   self.first + start)


@dataclass(frozen=True)
class FrameTag:
    """Marks frames on disk (FITS keys ``DEMOSEED``, ``DEMOHASH``) so a re-run reuses only its own."""

    seed: int
    digest: str


@dataclass(frozen=True)
class Storage:
    """Frames on disk (module notes): ``every`` 0 none, 1 all (measured from the files), N > 1 every
    N-th for inspection; into ``folder`` as ``<frame id>.fits`` (sensor i > 0: ``<frame id>_<i>.fits``)."""

    folder: Path | None = None
    every: int = 0
    tag: FrameTag | None = None

    def __post_init__(self) -> None:
        if int(self.every) != self.every or self.every < 0:
            raise InputError(f"frames are written every N >= 0 frames, got {self.every!r}")
        if self.every and self.folder is None:
            raise InputError("frames written to disk need a folder")

    def writes(self, k: int) -> bool:
        return self.every > 0 and k % self.every == 0


@dataclass(frozen=True)
class Sky:
    """Where the loop's star catalog and ephemerides come from, by name, so each worker process loads
    them once (:func:`loop_sources`): ``catalog_path`` (None: the packaged catalog), ``ephemeris``
    for the truth (pointing and render) and ``stage_ephemeris`` for the image stage's predictions
    (None: the same), each ``"cached"`` (the Chebyshev cache of DE421, within 1 cm of it) or ``"exact"``;
    with ``kernels`` (SPICE files, absolute paths, loaded over DE421) both read the kernels' bodies
    instead (:class:`opnav.ephemeris.spice.SpiceEphemeris`, cached: :class:`~opnav.ephemeris.spice.KernelCache`)."""

    catalog_path: str | None = None
    ephemeris: str = "cached"
    stage_ephemeris: str | None = None
    kernels: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name in (self.ephemeris, self.stage_ephemeris or self.ephemeris):
            if name not in ("cached", "exact"):
                raise InputError(f"ephemeris must be 'cached' or 'exact', got {name!r}")


class FrameHook:
    """What a study changes in the loop (frame faults, the truth's ephemeris error); this base class
    changes nothing. ``seed`` is the loop's, so a hook draws from streams of its own; ``sensor`` is the
    sensor's index in the loop. A hook must be picklable to run in worker processes."""

    def drawn(self, seed: int, sensor: int, spec: Sensor, arc: Arc, catalog, ephemeris) -> tuple[RenderOptions, object]:
        """(render options, star catalog) the sensor's frames are drawn with over ``arc`` (once per chunk)."""
        return spec.render, catalog

    def lost(self, seed: int, k: int) -> str | None:
        """Why frame ``k`` never reaches the image stage, or None."""
        return None

    def ephemeris(self, seed: int, k: int, ephemeris):
        """The ephemeris frame ``k`` is drawn with (the stage keeps the loop's)."""
        return ephemeris

    def prior(self, seed: int, sensor: int, k: int, R_icrf_cam: Rotation) -> Rotation:
        """The a-priori attitude (camera -> ICRF) the stage is given for the true ``R_icrf_cam``."""
        return R_icrf_cam

    def boxes(self, sensor: int, boxes: list, camera: Camera) -> list:
        """Where on the detector the windows the stage asks for are read out."""
        return boxes

    def image(self, sensor: int, image: np.ndarray) -> np.ndarray:
        """A full frame (ADU) as the stage receives it."""
        return image

    def windows(self, sensor: int, windows, camera: Camera):
        """Windows read out at :meth:`boxes` as the stage receives them."""
        return windows


@dataclass(frozen=True, eq=False)
class Loop:
    """What the loop does on every frame: ``sensors`` (in measuring order), the ``seed`` of every
    stream, where the catalog and ephemerides come from, the frames on disk, the study's hook, and
    the frame ids (``<frame_prefix>_<k:05d>``)."""

    sensors: tuple[Sensor, ...]
    seed: int
    sky: Sky = field(default_factory=Sky)
    storage: Storage = field(default_factory=Storage)
    hook: FrameHook | None = None
    frame_prefix: str = "frame"

    def __post_init__(self) -> None:
        object.__setattr__(self, "sensors", tuple(self.sensors))
        if not self.sensors:
            raise InputError("the loop needs at least one sensor")
        for index, sensor in enumerate(self.sensors):
            if isinstance(sensor.stage, (Limb, Centre)) and not (
                    0 <= sensor.stage.reference < index and self.sensors[sensor.stage.reference].mounting is not None):
                raise InputError(f"sensor {index}: its limb or centre stage's reference must be a sensor before it, mounted on "
                                 "the same body")
            if self.storage.tag is not None and sensor.window_half_px is not None:
                raise InputError("tagged frames for reuse are full frames; a windowed sensor cannot have them")


_SOURCES: dict = {}


def loop_sources(sky: Sky, *, catalog: bool = True):
    """(catalog or None, truth ephemeris, stage ephemeris) of ``sky``, loaded once per process."""
    from ..catalog import load_catalog

    def ephemeris(name: str):
        if sky.kernels:
            from ..ephemeris.planets import default_kernel_path
            from ..ephemeris.spice import KernelCache
            from .scene import kernel_ephemeris

            exact = kernel_ephemeris((str(default_kernel_path()), *sky.kernels))  # one per set of files
            key = (name, id(exact))
            if key not in _SOURCES:
                _SOURCES[key] = exact if name == "exact" else KernelCache(exact)
            return _SOURCES[key]
        if name not in _SOURCES:
            if name == "exact":
                from ..ephemeris import default_ephemeris

                _SOURCES[name] = default_ephemeris()
            else:
                from ..ephemeris.cache import default_cached_ephemeris

                _SOURCES[name] = default_cached_ephemeris()
        return _SOURCES[name]

    stars = load_catalog(sky.catalog_path) if catalog else None
    return stars, ephemeris(sky.ephemeris), ephemeris(sky.stage_ephemeris or sky.ephemeris)
