"""Renderer speed and the S1 moon magnitudes: prints figures for the issue note.

Run: .venv/bin/python benchmarks/render.py
"""

from __future__ import annotations

import math
import time

import numpy as np
from scipy.spatial.transform import Rotation

from opnav.camera import Camera
from opnav.catalog import synthetic_catalog
from opnav.render import Observer, RenderOptions, render_frame, render_windows

FOV_DEG = 5.0
STARS_IN_FIELD = 100


def _timed(fn, repeats=3):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times)), out


def main() -> None:
    rng = np.random.default_rng(1)
    n_sky = int(STARS_IN_FIELD * 4 * math.pi / math.radians(FOV_DEG) ** 2)
    catalog = synthetic_catalog(n_sky, rng=rng, vmag_range=(4.0, 10.0))
    observer = Observer(4.5e8, np.array([1.2e8, 8.0e7, 3.0e7]), np.array([-15.0, 20.0, 8.0]))
    attitude = Rotation.from_euler("zyx", [0.4, 0.3, 0.1])
    options = RenderOptions()
    for size in (1024, 2048):
        camera = Camera.from_fov(FOV_DEG, size, size)
        seconds, result = _timed(lambda: render_frame(camera, attitude, observer, catalog=catalog, options=options, rng=rng))
        print(f"full frame {size}x{size}: {len(result.truth.stars)} stars, noise on: {seconds * 1e3:.0f} ms")
        w_seconds, windowed = _timed(lambda: render_windows(camera, attitude, observer, catalog=catalog, options=options, rng=rng))
        pixels = sum(w.image.size for w in windowed.windows)
        print(f"  windowed: {len(windowed.windows)} windows, {pixels / size**2:.1%} of the pixels: "
              f"{w_seconds * 1e3:.0f} ms, speed-up {seconds / w_seconds:.1f}x")
    sparse = synthetic_catalog(n_sky // 10, rng=rng, vmag_range=(4.0, 10.0))
    camera = Camera.from_fov(FOV_DEG, 2048, 2048)
    seconds, result = _timed(lambda: render_frame(camera, attitude, observer, catalog=sparse, options=options, rng=rng))
    w_seconds, windowed = _timed(lambda: render_windows(camera, attitude, observer, catalog=sparse, options=options, rng=rng))
    print(f"sparse 2048x2048 ({len(result.truth.stars)} stars): full {seconds * 1e3:.0f} ms, "
          f"windowed {w_seconds * 1e3:.0f} ms, speed-up {seconds / w_seconds:.1f}x")
    s1_moon_magnitudes()


def s1_moon_magnitudes() -> None:
    """Phobos/Deimos as seen by the S1 probe (samples/s1_render.toml trajectory), first of each month."""
    from pathlib import Path

    from opnav.ephemeris import default_ephemeris
    from opnav.epochs import parse_epoch
    from opnav.render import body_model
    from opnav.bodies import view_body
    from opnav.sim.pointing import PointingLaw, pointing_attitude
    from opnav.sim.scene import load_scene, observer_states

    scenario = load_scene(Path(__file__).resolve().parents[1] / "samples" / "s1_render.toml")
    ephemeris = default_ephemeris()
    dates = ["2014-05-01", "2014-06-01", "2014-07-01", "2014-08-01"]
    t = np.array([parse_epoch(f"{d}T00:00:00", "utc") for d in dates])
    r, v = observer_states(scenario, t, ephemeris)
    for date, tk, rk, vk in zip(dates, t, r, v):
        observer = Observer(tk, rk, vk)
        attitude = pointing_attitude(PointingLaw("target", "phobos"), observer, ephemeris, scenario.options.corrections)
        views = [view_body(body_model(n), scenario.camera, attitude, observer, ephemeris) for n in ("phobos", "deimos")]
        offsets = [np.linalg.norm(w.xy_photocentre_px - w.xy_cof_px) * scenario.camera.pixel_scale_rad * w.range_km for w in views]
        print(f"S1 {date}: range {views[0].range_km / 1e6:.1f}e6 km, phase {math.degrees(views[0].phase_angle_rad):.1f} deg, "
              f"V(Phobos) {views[0].vmag:.2f}, V(Deimos) {views[1].vmag:.2f}, "
              f"photocentre offset {offsets[0]:.2f} / {offsets[1]:.2f} km")


if __name__ == "__main__":
    main()
