"""Tracking against the full-frame image stage over the S1 July arc, on the same frames.

The demo's S1 camera (1 degree, 1024 x 1024, Phobos-tracking, both moons and Mars, catalog
stars to V 11) over the 30-day July arc: ``--blocks`` runs of ``--block-frames`` consecutive
frames one minute apart, the runs spread evenly over the arc (the default, 30 runs of 144
frames, takes every tenth frame of the 43,200 in 2.4-hour runs: every geometry of the arc,
and runs long enough for tracking to hold its lock). Each frame is rendered whole in memory
(:func:`opnav.render.render_frame`, noise from ``default_rng([seed, block, k])``) and measured
twice: by the full-frame stage (:func:`opnav.image.pipeline.measure_frame`) and by a tracker
that starts each run with a full-frame acquisition (:class:`opnav.image.tracking.Tracker`,
as ``opnav run --mode images``). Printed, per moon and stage: records, RA/Dec error RMS
against the frames' truth, the tracking / full-frame RMS ratio, the mean chi-square/2 of the
records against their own covariance with its standard error (1 when the covariance is
right); misidentified stars in the tracked frames (centroid more than 1 px from where the
truth put that catalog star, :func:`opnav.sim.checks.misidentified_stars`);
acquisitions and losses of lock.

Usage::

    .venv/bin/python benchmarks/tracking_vs_full.py --blocks 30 --block-frames 144 --workers 2
"""

from __future__ import annotations

import argparse
import logging
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

from opnav.sim.checks import radec_errors
from opnav.sim.scene import observer_states
from opnav.studies.s1 import MOONS, load_demo

ARC_DAYS = 30.0
STEP_S = 60.0


def measure_block(block: int, blocks: int, frames: int, seed: int) -> dict:
    """Render ``frames`` frames of run ``block`` and measure each with both stages: their records,
    truths and the tracker's star checks."""
    from opnav.catalog import load_catalog
    from opnav.ephemeris import default_ephemeris
    from opnav.ephemeris.cache import default_cached_ephemeris
    from opnav.errors import OpnavError
    from opnav.image.pipeline import FrameInput, PipelineOptions, measure_frame
    from opnav.image.tracking import Tracker
    from opnav.observer import Observer
    from opnav.render.frame import render_frame
    from opnav.render.frames_io import saturation_level_adu
    from opnav.sim.pointing import body_rate, pointing_attitude
    from opnav.sim.checks import misidentified_stars

    logging.getLogger("opnav").setLevel(logging.ERROR)
    scenario, _, _ = load_demo()
    ephemeris, cached = default_ephemeris(), default_cached_ephemeris()
    catalog = load_catalog(scenario.catalog_path)
    start = scenario.t_tdb_s[0] + block * (ARC_DAYS * 86_400.0 - frames * STEP_S) / max(blocks - 1, 1)
    t = start + STEP_S * np.arange(frames)
    r, v = observer_states(replace(scenario, t_tdb_s=t), t, ephemeris)
    options = PipelineOptions(targets=MOONS, vmag_limit=scenario.options.vmag_limit)
    tracker = Tracker(catalog, cached, options)
    camera, corrections = scenario.camera, scenario.options.corrections
    out = {"full": [], "tracking": [], "truths": {}, "used": 0, "wrong": 0, "errors": {"full": 0, "tracking": 0},
           "full_s": 0.0, "tracking_s": 0.0}
    for k in range(frames):
        observer = Observer(float(t[k]), r[k], v[k])
        attitude = pointing_attitude(scenario.pointing, observer, ephemeris, corrections)
        rendered = render_frame(camera, attitude, observer, catalog=catalog, targets=scenario.targets,
                                ephemeris=ephemeris, options=scenario.options,
                                omega_cam_rad_s=body_rate(scenario.pointing, observer, ephemeris, corrections),
                                rng=np.random.default_rng([seed, block, k]))
        frame_id = f"b{block:03d}_f{k:04d}"
        out["truths"][frame_id] = rendered.truth
        frame = FrameInput.from_camera(rendered.image, camera, observer.t_tdb_s, attitude, observer,
                                       saturation_adu=saturation_level_adu(camera), frame_id=frame_id,
                                       flags=rendered.truth.flags)
        for stage in ("full", "tracking"):
            tic = time.perf_counter()
            try:
                if stage == "full":
                    result = measure_frame(frame, catalog=catalog, ephemeris=cached, options=options, rng=k)
                else:
                    result = tracker.step(frame, rng=k)
            except OpnavError:
                out["errors"][stage] += 1
                continue
            finally:
                out[f"{stage}_s"] += time.perf_counter() - tic
            if "attitude_prior" not in result.flags:
                out[stage].extend(rec for rec in result.records if rec.kind == "radec")
        if tracker.last_tracked is not None:
            used, wrong = misidentified_stars(tracker.last_tracked, rendered.truth.stars)
            out["used"], out["wrong"] = out["used"] + used, out["wrong"] + wrong
            tracker.last_tracked = None
    kinds = [event["event"] for event in tracker.events]
    out["acquired"], out["lost"] = kinds.count("acquired"), kinds.count("lost")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--blocks", type=int, default=30, help="runs of consecutive frames spread over the arc")
    parser.add_argument("--block-frames", type=int, default=144, help="frames a run, one minute apart")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args(argv)
    if args.blocks < 1 or args.block_frames < 2 or args.block_frames * STEP_S * args.blocks > ARC_DAYS * 86_400.0:
        parser.error("need blocks >= 1 and block-frames >= 2, and the runs must fit in the 30-day arc")
    tic = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        parts = list(pool.map(measure_block, range(args.blocks), [args.blocks] * args.blocks,
                              [args.block_frames] * args.blocks, [args.seed] * args.blocks))
    wall = time.perf_counter() - tic
    truths = {key: truth for part in parts for key, truth in part["truths"].items()}
    frames = args.blocks * args.block_frames
    print(f"{frames} frames ({args.blocks} runs of {args.block_frames}, one minute apart, over the 30-day July "
          f"arc), {wall / 60:.1f} min in {args.workers} processes")
    print(f"stage time a frame: full-frame {1e3 * sum(p['full_s'] for p in parts) / frames:.1f} ms, tracking "
          f"{1e3 * sum(p['tracking_s'] for p in parts) / frames:.1f} ms; frames refused: full-frame "
          f"{sum(p['errors']['full'] for p in parts)}, tracking {sum(p['errors']['tracking'] for p in parts)}")
    print(f"tracking: {sum(p['acquired'] for p in parts)} acquisitions, {sum(p['lost'] for p in parts)} losses of "
          f"lock; {sum(p['used'] for p in parts)} star uses in tracked frames, {sum(p['wrong'] for p in parts)} "
          "misidentified")
    errors = {stage: radec_errors([rec for part in parts for rec in part[stage]], truths)
              for stage in ("full", "tracking")}
    print("\n| moon | stage | records | RMS RA cos(dec) / Dec (\") | tracking / full-frame RMS | chi2/2 mean +- se |")
    print("|---|---|---|---|---|---|")
    for moon in MOONS:
        for stage in ("full", "tracking"):
            if moon not in errors[stage]:
                print(f"| {moon} | {stage} | 0 | | | |")
                continue
            e = errors[stage][moon]
            half = np.asarray(e["chi2"]) / 2.0
            ratio = ""
            if stage == "tracking" and moon in errors["full"]:
                r = np.asarray(e["rms_arcsec"]) / np.asarray(errors["full"][moon]["rms_arcsec"])
                ratio = f"{r[0]:.3f} / {r[1]:.3f}"
            print(f"| {moon} | {stage} | {e['count']} | {e['rms_arcsec'][0]:.4f} / {e['rms_arcsec'][1]:.4f} | {ratio} | "
                  f"{half.mean():.3f} +- {half.std(ddof=1) / np.sqrt(len(half)):.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
