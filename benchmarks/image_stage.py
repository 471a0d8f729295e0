"""Image stage speed on the demo's frames: milliseconds per 1024 x 1024 frame, and where they go.

Renders ``--frames`` frames of the embedded demo scenario (S1 July 2014, 1-degree camera,
Phobos, Deimos and Mars against catalog stars) into a temporary folder, then runs the full
image stage (:func:`opnav.studies.s1.process_frames`: background, detection, centroids, star ID,
attitude, moon measurements) over them twice and prints the second pass's time per frame,
with the share of background estimation and detection (cProfile of the same pass).

Usage::

    .venv/bin/python benchmarks/image_stage.py --frames 20
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import tempfile
import time
from pathlib import Path

from opnav.catalog import load_catalog
from opnav.sim.loop import render_frames
from opnav.ephemeris import default_ephemeris
from opnav.sim.scene import observer_states
from opnav.studies.s1 import load_demo, process_frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=20)
    args = parser.parse_args()
    scenario, _, digest = load_demo()
    t = scenario.t_tdb_s[: args.frames]
    ephemeris = default_ephemeris()
    catalog = load_catalog(scenario.catalog_path)
    with tempfile.TemporaryDirectory() as folder:
        r, v = observer_states(scenario, t, ephemeris)
        begin = time.perf_counter()
        frames = render_frames(scenario, t, r, v, Path(folder), seed=1, digest=digest, catalog=catalog,
                               ephemeris=ephemeris, progress=False)
        render_ms = 1e3 * (time.perf_counter() - begin) / len(t)
        kwargs = dict(catalog=catalog, ephemeris=ephemeris, vmag_limit=scenario.options.vmag_limit, seed=1,
                      progress=False)
        process_frames(frames.paths, **kwargs)  # warm: catalog tree, ephemeris segments
        begin = time.perf_counter()
        process_frames(frames.paths, **kwargs)
        process_ms = 1e3 * (time.perf_counter() - begin) / len(t)
        profile = cProfile.Profile()
        profile.runcall(process_frames, frames.paths, **kwargs)
    stats = pstats.Stats(profile)
    total = stats.total_tt

    def share(name: str) -> float:
        return 100.0 * max((v[3] for k, v in stats.stats.items() if k[2] == name), default=0.0) / total

    print(f"{len(t)} demo frames (1024 x 1024): render {render_ms:.0f} ms/frame, image stage {process_ms:.0f} ms/frame "
          f"(background {share('estimate_background'):.0f} %, detection in all {share('detect'):.0f} %, "
          f"centroids {share('centroid'):.0f} %)")


if __name__ == "__main__":
    main()
