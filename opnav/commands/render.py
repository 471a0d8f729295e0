"""``opnav render``: render a scenario's frames (FITS + truth JSON) into a directory.

Frames go through the one render loop (:func:`opnav.sim.loop.render_frames`): frame ``k`` draws its
noise from ``default_rng([seed, k])``, so a scene and seed give the same frames as ``opnav demo``'s.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np

from ..config import TIME_SCALES, check_zone
from ..errors import InputError

NAME = "render"
HELP = "render synthetic frames (FITS + truth JSON) for a scenario file"

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", help="scenario TOML file")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--start", help="first epoch (calendar, in --scale: UTC unless given; not the "
                        "scenario's [epochs] scale)")
    parser.add_argument("--stop", help="last epoch (calendar, in --scale)")
    parser.add_argument("--step", type=float, help="step between frames, s")
    parser.add_argument("--scale", default=None, type=str.lower, choices=TIME_SCALES,
                        help="time scale of --start/--stop: utc, tt, tdb or tai (default: utc, whatever the "
                             "scenario's [epochs] scale)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def run(args: argparse.Namespace) -> int:
    from ..catalog import load_catalog
    from ..sim.loop import check_frame_budget, render_frames
    from ..sim.scene import epochs_between, load_scene, observer_states

    scenario = load_scene(args.scenario)
    t = scenario.t_tdb_s
    if args.step is not None and not (np.isfinite(args.step) and args.step > 0.0):
        raise InputError(f"--step must be a positive number of seconds, got {args.step!r}")
    if args.scale is not None and not (args.start or args.stop):
        raise InputError("--scale is the scale of --start/--stop; give one of them with it")
    if args.start or args.stop or args.step:
        scale = args.scale or "utc"
        start = _epoch(args.start, scale, "--start") if args.start else float(t[0])
        stop = _epoch(args.stop, scale, "--stop") if args.stop else (start if args.start else float(t[-1]))
        step = args.step if args.step else (float(t[1] - t[0]) if len(t) > 1 else 60.0)
        t = epochs_between(start, stop, step)
    check_frame_budget(len(t), scenario.camera, args.out)
    ephemeris = scenario.ephemeris()  # [kernels] when the scene has them, else DE421
    catalog = load_catalog(scenario.catalog_path) if scenario.stars else None
    r, v = observer_states(scenario, t, ephemeris)
    # frame k's noise from default_rng([seed, k]), as the demo's frames (opnav.sim.loop)
    frames = render_frames(scenario, t, r, v, args.out, seed=scenario.seed, catalog=catalog, ephemeris=ephemeris,
                           progress=not args.no_progress)
    print(f"wrote {len(frames.paths)} frame(s) to {args.out}")
    return 0


def _epoch(text: str, scale: str, option: str) -> float:
    """``text`` of ``option`` in ``scale``, TDB s past J2000; a bad date names the option."""
    from ..epochs import parse_epoch

    check_zone(text, scale, option)
    try:
        return parse_epoch(text, scale)
    except InputError as exc:
        raise InputError(f"{option}: {exc}") from None
