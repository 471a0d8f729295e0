"""Frame sequences along a trajectory, with a pointing law.

Steps per epoch: observer SSB state (from arrays or a
:class:`opnav.dynamics.Trajectory` moved to the SSB), attitude from the
pointing law, camera body rate by differencing the law over one second (so a
target-tracking camera smears the stars, not the target), render (full or
windowed), write ``frame_NNNNN.fits`` + ``.truth.json``.

Pointing laws (camera +z = boresight; +x toward celestial east, +y toward
celestial north at the boresight, then turned by ``roll_rad`` about +z):

* ``target``: boresight on the apparent direction of ``target`` (light time and
  aberration through :func:`opnav.light.apparent_direction`);
* ``earth``: the same with the Earth's centre (Earth-pointing satellite);
* ``inertial``: fixed boresight ``ra_rad``, ``dec_rad``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
import shutil
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from ..camera import Camera
from ..errors import InputError
from ..frames import radec_to_unit
from ..light import apparent_direction
from ..bodies import Body
from .frame import RenderOptions, render_frame, render_windows
from .frames_io import write_frame, write_windows
from ..observer import Corrections, Observer
from .scene import StarSource

_LAWS = ("target", "earth", "inertial")


@dataclass(frozen=True)
class PointingLaw:
    """How the camera is pointed (see module notes); angles rad."""

    law: str = "inertial"
    target: str | None = None
    ra_rad: float = 0.0
    dec_rad: float = 0.0
    roll_rad: float = 0.0

    def __post_init__(self) -> None:
        if self.law not in _LAWS:
            raise InputError(f"pointing law must be one of {', '.join(_LAWS)}, got {self.law!r}")
        if self.law == "target" and not self.target:
            raise InputError("pointing law 'target' needs a target name")
        for name in ("ra_rad", "dec_rad", "roll_rad"):
            if not math.isfinite(getattr(self, name)):
                raise InputError(f"pointing {name} must be finite")


def attitude_from_boresight(boresight_icrf: np.ndarray, roll_rad: float = 0.0) -> Rotation:
    """Camera -> ICRF rotation with +z on ``boresight_icrf``, +x east, +y north, then rolled about +z."""
    z = np.asarray(boresight_icrf, dtype=float)
    z = z / np.linalg.norm(z)
    ra = math.atan2(z[1], z[0])
    east = np.array([-math.sin(ra), math.cos(ra), 0.0])
    north = np.cross(z, east)
    base = Rotation.from_matrix(np.column_stack([east, north, z]))
    return base * Rotation.from_rotvec([0.0, 0.0, roll_rad])


def pointing_attitude(law: PointingLaw, observer: Observer, ephemeris, corrections: Corrections) -> Rotation:
    """Attitude (camera -> ICRF) of ``law`` at ``observer``'s epoch and state."""
    if law.law == "inertial":
        boresight = radec_to_unit(law.ra_rad, law.dec_rad)
    else:
        name = law.target if law.law == "target" else "earth"
        boresight = apparent_direction(
            lambda t: ephemeris.position(name, t), observer.t_tdb_s, observer.r_ssb_km, observer.v_ssb_km_s,
            light_time=corrections.light_time, aberration=corrections.aberration,
        )
    return attitude_from_boresight(boresight, law.roll_rad)


def body_rate(law: PointingLaw, observer: Observer, ephemeris, corrections: Corrections, *, dt_s: float = 1.0) -> np.ndarray:
    """Camera body rate (camera frame, rad/s) of ``law``, central difference over ``dt_s``."""
    if law.law == "inertial":
        return np.zeros(3)
    shifted = []
    for sign in (-0.5, 0.5):
        obs = Observer(observer.t_tdb_s + sign * dt_s, observer.r_ssb_km + sign * dt_s * observer.v_ssb_km_s, observer.v_ssb_km_s)
        shifted.append(pointing_attitude(law, obs, ephemeris, corrections))
    return (shifted[0].inv() * shifted[1]).as_rotvec() / dt_s


def trajectory_to_ssb(trajectory, ephemeris) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t (M,), r_ssb_km (M, 3), v_ssb_km_s (M, 3)) from an ``opnav.dynamics.Trajectory``."""
    states = np.asarray(trajectory.states, dtype=float)
    if states.ndim != 2 or states.shape[1] != 6:
        raise InputError(f"trajectory states must have shape (M, 6), got {states.shape}")
    t = np.asarray(trajectory.t_tdb_s, dtype=float)
    r_c, v_c = ephemeris.state(trajectory.center, t) if trajectory.center != "ssb" else (0.0, 0.0)
    return t, states[:, :3] + r_c, states[:, 3:] + v_c


#: Most frames one render call writes (a month at one a minute is 43,200).
MAX_FRAMES = 1_000_000


def check_frame_budget(count: int, camera: Camera, out_dir: str | Path) -> None:
    """Refuse ``count`` frames of ``camera`` into ``out_dir`` above :data:`MAX_FRAMES` or the free disk.

    Checked before any work, so a step of a millisecond over a day (86 million frames) ends in
    one line instead of hours of propagation and a full disk.
    """
    if count > MAX_FRAMES:
        raise InputError(f"{count:,} frames requested; at most {MAX_FRAMES:,} per render (raise the step or "
                         "shorten the span)")
    frame_bytes = camera.width_px * camera.height_px * 2 + 20_000  # 16-bit FITS + truth JSON
    out = Path(out_dir)
    probe = next((p for p in (out, *out.parents) if p.exists()), Path("."))
    free = shutil.disk_usage(probe).free
    if count * frame_bytes > free:
        raise InputError(f"{count:,} frames of {camera.width_px} x {camera.height_px} px need about "
                         f"{count * frame_bytes / 1e9:.1f} GB; {free / 1e9:.1f} GB free under {probe}")


def render_sequence(
    camera: Camera,
    t_tdb_s: np.ndarray,
    r_ssb_km: np.ndarray,
    v_ssb_km_s: np.ndarray,
    *,
    out_dir: str | Path,
    pointing: PointingLaw,
    catalog: StarSource | None,
    targets: Sequence[str | Body],
    ephemeris,
    options: RenderOptions,
    rng: np.random.Generator,
    windowed: bool = False,
    window_half_px: int = 12,
    progress: bool = True,
) -> list[Path]:
    """Render and write one frame per epoch; return the FITS paths.

    Parameters
    ----------
    camera : Camera
    t_tdb_s : (M,) array
        Mid-exposure epochs, TDB seconds past J2000.
    r_ssb_km, v_ssb_km_s : (M, 3) arrays
        Observer states relative to the SSB, ICRF.
    out_dir : path
    pointing : PointingLaw
    catalog, targets, ephemeris, options, rng
        As for :func:`opnav.render.render_frame`.
    windowed : bool
        Render only regions of interest (:func:`opnav.render.render_windows`).
    progress : bool
        Show a tqdm progress bar.
    """
    t = np.atleast_1d(np.asarray(t_tdb_s, dtype=float))
    r = np.asarray(r_ssb_km, dtype=float).reshape(-1, 3)
    v = np.asarray(v_ssb_km_s, dtype=float).reshape(-1, 3)
    if not (len(t) == len(r) == len(v)):
        raise InputError(f"t_tdb_s, r_ssb_km and v_ssb_km_s disagree in length: {len(t)}, {len(r)}, {len(v)}")
    check_frame_budget(len(t), camera, out_dir)
    out = Path(out_dir)
    paths = []
    for k in tqdm(range(len(t)), desc="render", unit="frame", disable=not progress):
        observer = Observer(t[k], r[k], v[k])
        attitude = pointing_attitude(pointing, observer, ephemeris, options.corrections)
        omega = body_rate(pointing, observer, ephemeris, options.corrections)
        kwargs = dict(catalog=catalog, targets=targets, ephemeris=ephemeris, options=options, omega_cam_rad_s=omega, rng=rng)
        path = out / f"frame_{k:05d}.fits"
        if windowed:
            result = render_windows(camera, attitude, observer, window_half_px=window_half_px, **kwargs)
            write_windows(path, result.windows, camera, result.truth)
        else:
            result = render_frame(camera, attitude, observer, **kwargs)
            write_frame(path, result.image, result.header, result.truth)
        paths.append(path)
    return paths
