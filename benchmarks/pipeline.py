"""Image stage at mission scale: tracking mode against the full-frame stage on the same S1 frames.

Frames: the demo's S1 camera (1 degree, 1024 x 1024, Phobos-tracking, both moons and Mars,
catalog stars to V 11) rendered one a minute from ``--start-day`` of July 2014, written as
FITS once (``--out``, reused when present). Printed, for the same frames:

- full-frame render and windowed render (:func:`opnav.render.render_windows`, the windows
  around every source, in memory, through the cached ephemeris as the in-memory loop renders)
  in frames/s;
- full-frame stage (:func:`opnav.image.pipeline.measure_frame`) and tracking stage
  (:class:`opnav.image.tracking.Tracker`) in frames/s, both from frames already in memory;
- each moon's RA/Dec error RMS against the frames' truth for both stages, their ratio and
  the mean chi-square/2 of the records (1 when the reported covariance is right);
- misidentified stars: tracked stars used by the attitude whose centroid is more than 1 px
  from where the truth put that catalog star (must be 0), and the acquisitions and losses
  of lock;
- the whole in-memory loop (:mod:`opnav.studies.image_loop`: windowed render, tracking,
  records) in frames/s and the time it implies for a 30-day arc at one frame a minute, in one
  process and in ``--workers`` processes;
- full-frame extraction (background, detection and Gaussian-fit centroids, the full-frame
  stage's first step) on the 1024 x 1024 frames and on a 5-megapixel frame of the same sky
  (2592 x 1944 px, same pixel scale), ms a frame;
- the Earth-limb fit (:func:`opnav.image.targets.limb_points` and
  :func:`~opnav.image.targets.fit_limb`) on S3 UV Earth-sensor frames from GEO (30 degrees,
  512 x 512, rendered with :mod:`opnav.render`): ms a frame and the fitted centre's error
  against the frame's truth, px.

Usage::

    .venv/bin/python benchmarks/pipeline.py --frames 200
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from opnav.allocator import keep_freed_memory
from opnav.catalog import load_catalog
from opnav.ephemeris import default_ephemeris
from opnav.ephemeris.cache import default_cached_ephemeris
from opnav.image.pipeline import PipelineOptions, frame_input, measure_frame
from opnav.image.tracking import Tracker
from opnav.observer import Observer
from opnav.render.frame import render_windows
from opnav.sim.checks import misidentified_stars, radec_errors
from opnav.sim.loop import render_frames
from opnav.sim.pointing import body_rate, pointing_attitude
from opnav.sim.scene import observer_states
from opnav.studies.s1 import MOONS, load_demo


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--step-s", type=float, default=60.0)
    parser.add_argument("--start-day", type=float, default=1.0, help="days after the demo's first epoch (15 July)")
    parser.add_argument("--limb-frames", type=int, default=4, help="UV Earth frames of the limb-fit timing")
    parser.add_argument("--loop-frames", type=int, default=1440, help="frames of the in-memory loop runs")
    parser.add_argument("--workers", type=int, default=2, help="processes of the second in-memory loop run")
    parser.add_argument("--field-stars", type=int, default=0,
                        help="add synthetic catalog stars (V 9-11) around the arc's pointing so a frame holds about "
                             "this many (the catalog has 5-7 in the demo's 1-degree field); renderer and image stage "
                             "both use the extended catalog")
    parser.add_argument("--out", default=None, help="frames folder, reused when present (default "
                                                    "out/bench_pipeline, with _stars<N> for --field-stars)")
    parser.add_argument("--malloc-defaults", action="store_true",
                        help="leave the C allocator's defaults (the opnav command keeps freed memory: "
                             "opnav.allocator.keep_freed_memory)")
    args = parser.parse_args(argv)
    if not args.malloc_defaults:
        keep_freed_memory()
    logging.getLogger("opnav").setLevel(logging.ERROR)
    scenario, _, digest = load_demo()
    if args.out is None:
        args.out = "out/bench_pipeline" + (f"_stars{args.field_stars}" if args.field_stars else "")
    if args.field_stars:
        scenario = dense_field(scenario, args.field_stars, args.start_day, Path(args.out))
        digest += f"-stars{args.field_stars}"
    ephemeris = default_ephemeris()
    cached = default_cached_ephemeris()
    catalog = load_catalog(scenario.catalog_path)
    t = scenario.t_tdb_s[0] + args.start_day * 86_400.0 + args.step_s * np.arange(args.frames)
    scene = replace(scenario, t_tdb_s=t)
    r, v = observer_states(scene, t, ephemeris)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tic = time.perf_counter()
    frames = render_frames(scene, t, r, v, out, seed=7, digest=digest, catalog=catalog, ephemeris=ephemeris,
                           progress=False)
    render_s = time.perf_counter() - tic
    print(f"{args.frames} frames, {args.step_s:g} s apart ({frames.reused} reused from {out})")
    if frames.reused < args.frames:
        print(f"full-frame render + FITS write: {args.frames / render_s:.1f} frames/s")
    count = min(args.frames, 100)
    tic = 0.0
    for k in range(-1, count):  # frame -1 loads the compiled kernels before the clock starts
        if k == 0:
            tic = time.perf_counter()
        observer = Observer(float(t[max(k, 0)]), r[max(k, 0)], v[max(k, 0)])
        corrections = scenario.options.corrections
        render_windows(scenario.camera, pointing_attitude(scenario.pointing, observer, cached, corrections),
                       observer, catalog=catalog, targets=scenario.targets, ephemeris=cached, options=scenario.options,
                       omega_cam_rad_s=body_rate(scenario.pointing, observer, cached, corrections),
                       rng=np.random.default_rng(max(k, 0)))
    print(f"windowed render in memory: {count / (time.perf_counter() - tic):.1f} frames/s ({count} frames)")

    options = PipelineOptions(targets=MOONS, vmag_limit=scenario.options.vmag_limit)
    inputs = [frame_input(path) for path in frames.paths]
    truths = {path.stem: truth for path, truth in zip(frames.paths, frames.truths)}
    tic = time.perf_counter()
    full = [measure_frame(f, catalog=catalog, ephemeris=ephemeris, options=options, rng=k) for k, f in enumerate(inputs)]
    full_s = time.perf_counter() - tic
    tracker = Tracker(catalog, cached, options)  # as S1 image mode: the stage predicts through the cache
    tracked, checks, wrong, used = [], [], 0, 0
    tic = time.perf_counter()
    for k, frame in enumerate(inputs):
        tracked.append(tracker.step(frame, rng=k))
        checks.append(tracker.last_tracked)  # None after a full-frame acquisition
        tracker.last_tracked = None
    track_s = time.perf_counter() - tic
    for check, truth in zip(checks, frames.truths):
        if check is None or check.result is None:
            continue
        count, misidentified = misidentified_stars(check, truth.stars)
        used, wrong = used + count, wrong + misidentified
    print(f"full-frame stage: {args.frames / full_s:.2f} frames/s; tracking stage: {args.frames / track_s:.2f} frames/s "
          f"({full_s / track_s:.1f}x)")
    kinds = [e["event"] for e in tracker.events]
    print(f"tracking: {kinds.count('acquired')} acquisition(s), {kinds.count('lost')} loss(es) of lock; "
          f"{used} star uses ({used / max(sum(c is not None for c in checks), 1):.1f} a tracked frame), "
          f"{wrong} misidentified")
    errors = {name: radec_errors([r for res in results for r in res.records], truths)
              for name, results in (("full-frame", full), ("tracking", tracked))}
    for moon in MOONS:
        row = []
        for stage, table in errors.items():
            if moon in table:
                e = table[moon]
                row.append(f"{stage} {e['count']} records, RMS {e['rms_arcsec'][0]:.4f}\" / {e['rms_arcsec'][1]:.4f}\", "
                           f"chi2/2 {np.mean(e['chi2']) / 2:.2f}")
        if all(moon in table for table in errors.values()):
            ratio = np.array(errors["tracking"][moon]["rms_arcsec"]) / np.array(errors["full-frame"][moon]["rms_arcsec"])
            row.append(f"tracking / full-frame RMS {ratio[0]:.3f} / {ratio[1]:.3f}")
        print(f"{moon}: " + "; ".join(row))

    # the whole loop in memory, as `opnav run --mode images` with dump_every = 0: windowed render
    # (cached ephemeris) -> tracking stage -> records, chunks saved
    import tempfile

    from opnav.studies.image_loop import stream_frames

    t = scenario.t_tdb_s[0] + args.start_day * 86_400.0 + args.step_s * np.arange(args.loop_frames)
    r, v = observer_states(scene, t, ephemeris)
    for workers in (1, args.workers):
        with tempfile.TemporaryDirectory() as folder:
            tic = time.perf_counter()
            stream = stream_frames(replace(scenario, t_tdb_s=t), t, r, v, Path(folder), seed=7, options=options,
                                   moons=MOONS, progress=False, workers=workers,
                                   chunk_frames=-(-args.loop_frames // args.workers))
            loop_s = time.perf_counter() - tic
        print(f"in-memory loop, {workers} process(es), {args.loop_frames} frames in {args.workers} chunks "
              f"({stream.frames_windowed} windowed, {stream.frames_full} full, process start-up included): "
              f"{args.loop_frames / loop_s:.1f} frames/s; 43,200 frames (30 days a minute apart) would take "
              f"{43_200 / (args.loop_frames / loop_s) / 60:.1f} min")
    extraction(inputs, scene, r[0], v[0], catalog, ephemeris, options)
    limb_fit(args.limb_frames, ephemeris)
    return 0


def dense_field(scenario, count: int, start_day: float, out: Path):
    """``scenario`` with a catalog extended by synthetic stars so a frame holds about ``count`` (written
    to ``out/catalog.npz``)."""
    from opnav.catalog import save_catalog, synthetic_catalog

    ephemeris = default_ephemeris()
    catalog = load_catalog(scenario.catalog_path)
    t = np.array([scenario.t_tdb_s[0] + start_day * 86_400.0])
    r, v = observer_states(replace(scenario, t_tdb_s=t), t, ephemeris)
    boresight = pointing_attitude(scenario.pointing, Observer(float(t[0]), r[0], v[0]), ephemeris,
                                  scenario.options.corrections).apply([0.0, 0.0, 1.0])
    camera = scenario.camera
    cap = 3.0 * camera.half_diagonal_fov_rad  # the pointing drifts by less over a day
    field = camera.width_px * camera.height_px * camera.pixel_scale_rad**2
    extra = synthetic_catalog(int(count * 2.0 * np.pi * (1.0 - np.cos(cap)) / field), rng=np.random.default_rng(40),
                              vmag_range=(9.0, 11.0), centre_icrf=boresight, radius_rad=cap)
    extra = replace(extra, hip=np.zeros(len(extra), np.int64), gaia_id=2**34 + np.arange(len(extra), dtype=np.int64))
    from dataclasses import fields

    dense = type(catalog)(**{f.name: np.concatenate([getattr(catalog, f.name), getattr(extra, f.name)])
                             for f in fields(catalog)})
    return replace(scenario, catalog_path=str(save_catalog(dense, out / "catalog.npz")))


def extraction(inputs, scenario, r_km, v_km_s, catalog, ephemeris, options) -> None:
    """Time background + detection + centroids on 1 MP frames and on a 5 MP frame (module docstring)."""
    from opnav.image.pipeline import FrameInput
    from opnav.image.pipeline import measure_sources as _measure_sources
    from opnav.render import render_frame
    from opnav.render.frames_io import saturation_level_adu

    _measure_sources(inputs[0], options)  # compiled kernels loaded before the clock starts
    tic = time.perf_counter()
    found = [len(_measure_sources(frame, options).det) for frame in inputs]
    one_s = (time.perf_counter() - tic) / len(inputs)
    camera = scenario.camera.replace(width_px=2592, height_px=1944, cx_px=1295.5, cy_px=971.5)
    observer = Observer(float(scenario.t_tdb_s[0]), r_km, v_km_s)
    attitude = pointing_attitude(scenario.pointing, observer, ephemeris, scenario.options.corrections)
    big = render_frame(camera, attitude, observer, catalog=catalog, targets=scenario.targets, ephemeris=ephemeris,
                       options=scenario.options, rng=np.random.default_rng(5))
    frame = FrameInput.from_camera(big.image, camera, observer.t_tdb_s, attitude, observer,
                                   saturation_adu=saturation_level_adu(camera))
    _measure_sources(frame, options)
    tic = time.perf_counter()
    for _ in range(3):
        sources = _measure_sources(frame, options)
    five_s = (time.perf_counter() - tic) / 3
    print(f"full-frame extraction (background, detection, centroids): 1024 x 1024 {1e3 * one_s:.1f} ms a frame "
          f"({np.mean(found):.0f} sources); 2592 x 1944 {1e3 * five_s:.1f} ms ({len(sources.det)} sources)")


def limb_fit(count: int, ephemeris) -> None:
    """Time the limb fit on ``count`` UV Earth frames from GEO (module docstring)."""
    from opnav.camera import Camera
    from opnav.epochs import parse_epoch
    from opnav.image.targets import fit_limb, limb_points
    from opnav.render import RenderOptions, render_frame
    from opnav.studies.s3 import earth_sensor_view

    rng = np.random.default_rng(30)
    camera = Camera.from_fov(30.0, 512, 512)
    t = float(parse_epoch("2001-01-01T06:00:00", "utc"))
    frames = []
    for _ in range(count):
        observer, attitude = earth_sensor_view(t, ephemeris, rng)
        rendered = render_frame(camera, attitude, observer, targets=("earth",), ephemeris=ephemeris, rng=rng,
                                options=RenderOptions(supersample=2))
        truth = rendered.truth.target("earth")
        frames.append((rendered.image.astype(float), truth.xy_cof_px, truth.xy_cof_px + rng.uniform(-3, 3, 2),
                       truth.angular_radius_rad * camera.focal_length_px))
    limb_points(frames[0][0], frames[0][2], frames[0][3])  # compiled kernels loaded before the clock starts
    errors = []
    tic = time.perf_counter()
    for k, (image, centre, guess, radius) in enumerate(frames):
        fit = fit_limb(limb_points(image, guess, radius), camera, rng=k)
        errors.append(np.hypot(*(camera.project(fit.centre_cam) - centre)))
    limb_s = (time.perf_counter() - tic) / count
    print(f"Earth-limb fit (S3 UV sensor, 512 x 512): {1e3 * limb_s:.1f} ms a frame ({count} frames); centre error "
          f"{min(errors):.4f}-{max(errors):.4f} px")


if __name__ == "__main__":
    raise SystemExit(main())
