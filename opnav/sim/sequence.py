"""Frame sequences along a trajectory, with a pointing law (:mod:`opnav.sim.pointing`).

Steps per epoch: observer SSB state, attitude from the pointing law, camera body rate by
differencing the law over one second (so a target-tracking camera smears the stars, not the
target), render (full or windowed), write ``frame_NNNNN.fits`` + ``.truth.json``.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Sequence

import numpy as np
from tqdm import tqdm

from ..camera import Camera
from ..errors import InputError
from ..bodies import Body
from ..render.frame import RenderOptions, render_frame, render_windows
from ..render.frames_io import write_frame, write_windows
from ..observer import Observer
from .pointing import PointingLaw, body_rate, pointing_attitude
from ..render.scene import StarSource

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
