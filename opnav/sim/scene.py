"""Scenario files: TOML -> frozen, validated dataclasses (``load_scene``).

Sections known so far (later issues add navigation sections to ``SECTIONS``);
units are named in every key and converted here, once:

``[scenario]`` name, seed · ``[epochs]`` start, stop (calendar strings), scale,
step_s · ``[observer]`` either ``epoch`` + ``epoch_scale`` + ``position_km`` +
``velocity_km_s`` + ``frame`` (icrf | ecliptic) + ``center`` + ``dynamics``
(a key of ``opnav.dynamics.MODELS``), or ``body`` + ``offset_km`` (fixed ICRF
offset from an ephemeris body, moving with it) · ``[camera]`` every
:class:`opnav.camera.Camera` field · ``[pointing]`` law (target | earth |
inertial), target, ra_deg, dec_deg, roll_deg · ``[targets]`` names ·
``[psf]`` :class:`opnav.render.PSF` fields · ``[detector]``
:class:`opnav.render.DetectorOptions` fields · ``[corrections]`` light_time,
aberration, parallax, proper_motion · ``[catalog]`` stars (false: draw no
stars, e.g. a UV Earth sensor), path (optional), vmag_limit ·
``[render]`` windowed, window_half_px, supersample, sun_keepout_margin_deg, sun_policy.

Unknown sections or keys raise :class:`opnav.errors.InputError` naming the file
and listing what is known.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..epochs import parse_epoch
from ..errors import InputError, OpnavError
from ..frames import ecliptic_to_icrf
from ..bodies import body_model
from ..render.detector import DetectorOptions
from ..render.frame import RenderOptions
from ..render.psf import PSF
from ..observer import Corrections
from .pointing import PointingLaw
from ..tomlio import convert, read_toml

SECTIONS = ("scenario", "epochs", "observer", "camera", "pointing", "targets", "psf", "detector", "corrections", "catalog", "render", "navigation")  # [navigation] is read by opnav.filters.options


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


def _build(cls, values: dict, section: str, path: str):
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise InputError(f"{path}: unknown key(s) {unknown} in [{section}]; known: {sorted(known)}")
    hints = typing.get_type_hints(cls)
    values = {key: convert(value, hints[key], f"{path}: [{section}] {key}") for key, value in values.items()}
    try:
        return cls(**values)
    except TypeError as exc:
        raise InputError(f"{path}: bad [{section}] ({exc})") from None


def _get(section: dict, key: str, kind, default, table: str, path: str):
    """``section[key]`` as ``kind`` (``default`` when absent); a wrong type names the file and key."""
    return convert(section.get(key, default), kind, f"{path}: [{table}] {key}")


def _pop_section(data: dict, name: str, path: str) -> dict:
    section = data.get(name, {})
    if not isinstance(section, dict):
        raise InputError(f"{path}: [{name}] must be a table")
    return dict(section)


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scenario TOML file; ``InputError`` naming the file on any problem."""
    path = Path(path)
    data = read_toml(path)
    source = str(path)
    unknown = sorted(set(data) - set(SECTIONS))
    if unknown:
        raise InputError(f"{source}: unknown section(s) {unknown}; known sections: {', '.join(SECTIONS)}")
    try:
        return _scenario(data, source)
    except OpnavError as exc:
        if source in str(exc):
            raise
        raise type(exc)(f"{source}: {exc}") from None


def _scenario(data: dict, source: str) -> Scene:
    head = _pop_section(data, "scenario", source)
    epochs = _pop_section(data, "epochs", source)
    scale = epochs.get("scale", "utc")
    try:
        start = parse_epoch(epochs["start"], scale)
        stop = parse_epoch(epochs.get("stop", epochs["start"]), scale)
    except KeyError:
        raise InputError("[epochs] needs start (and optionally stop, step_s, scale)") from None
    t = epochs_between(start, stop, _get(epochs, "step_s", float, 60.0, "epochs", source))

    obs = _pop_section(data, "observer", source)
    if "epoch" in obs:
        obs["epoch_tdb_s"] = parse_epoch(obs.pop("epoch"), obs.pop("epoch_scale", "utc"))
    frame = obs.pop("frame", "icrf")
    if frame not in ("icrf", "ecliptic"):
        raise InputError(f"[observer] frame must be icrf or ecliptic, got {frame!r}")
    for key in ("position_km", "velocity_km_s", "offset_km"):
        if key in obs:
            vector = np.asarray(convert(obs[key], tuple[float, ...], f"{source}: [observer] {key}"))
            if vector.shape != (3,):
                raise InputError(f"{source}: [observer] {key} must be 3 numbers, got {obs[key]!r}")
            obs[key] = tuple(ecliptic_to_icrf(vector) if frame == "ecliptic" else vector)
    observer = _build(ObserverSpec, obs, "observer", source)

    camera = _build(Camera, _pop_section(data, "camera", source), "camera", source)
    pointing = _pop_section(data, "pointing", source)
    for key in ("ra", "dec", "roll"):
        if f"{key}_deg" in pointing:
            pointing[f"{key}_rad"] = math.radians(_get(pointing, f"{key}_deg", float, 0.0, "pointing", source))
            del pointing[f"{key}_deg"]
    pointing_law = _build(PointingLaw, pointing, "pointing", source)
    targets = _get(_pop_section(data, "targets", source), "names", tuple[str, ...], (), "targets", source)
    for name in targets:
        body_model(name)
    catalog = _pop_section(data, "catalog", source)
    render = _pop_section(data, "render", source)
    options = RenderOptions(
        psf=_build(PSF, _pop_section(data, "psf", source), "psf", source),
        detector=_build(DetectorOptions, _pop_section(data, "detector", source), "detector", source),
        corrections=_build(Corrections, _pop_section(data, "corrections", source), "corrections", source),
        vmag_limit=_get(catalog, "vmag_limit", float | None, None, "catalog", source),
        sun_keepout_margin_rad=math.radians(_get(render, "sun_keepout_margin_deg", float, 10.0, "render", source)),
        sun_policy=_get(render, "sun_policy", str, "flag", "render", source),
        supersample=_get(render, "supersample", int, 4, "render", source),
    )
    return Scene(
        name=_get(head, "name", str, Path(source).stem, "scenario", source),
        seed=_get(head, "seed", int, 0, "scenario", source),
        t_tdb_s=t,
        observer=observer,
        camera=camera,
        pointing=pointing_law,
        targets=targets,
        options=options,
        catalog_path=_get(catalog, "path", str | None, None, "catalog", source),
        stars=_get(catalog, "stars", bool, True, "catalog", source),
        windowed=_get(render, "windowed", bool, False, "render", source),
        window_half_px=_get(render, "window_half_px", int, 12, "render", source),
        source=source,
    )


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
