"""Star-identification benchmark: lost in space (11.4 deg camera) and tracking (narrow cameras).

Run: ``.venv/bin/python benchmarks/starid.py [--trials 1000] [--rendered 100] [--tracking 500]``

Three parts, every random draw from one seeded generator:

1. Lost in space, centroid level: ``--trials`` random attitudes of an 11.4 deg, 1024 x 768
   camera. Catalog stars in view with (V + 0.3 mag noise) <= 7.0 are "detected", centroids get
   0.3 px Gaussian noise, 0-5 false stars are added at random positions with magnitudes drawn
   between the brightest star and the limit, then the list is sorted by noisy magnitude.
2. Lost in space, rendered: ``--rendered`` frames from ``opnav.render.render_frame`` (shot,
   read and dark noise, hot pixels, cosmic rays; catalog magnitudes with 0.3 mag noise, 0-5
   false stars drawn as extra catalog entries), extracted with ``opnav.image.detect`` and
   ``opnav.image.centroid``, then identified. Extraction time is reported separately.
3. Tracking: ``--tracking`` random attitudes each for 1.5 deg and 1.0 deg, 1024 x 768 cameras,
   the full catalog (to V 10.5 detected), the a-priori attitude off by a random rotation of
   uniform magnitude in [0, 0.1] deg, 0-2 false stars; scored when >= 3 catalog stars are in view.

A solution is *correct* when every matched star is the true catalog star (or within a pixel of
it: double stars), or when the four detector corners projected with the solved and the true
attitude agree within 2 px (a false star may fall on a faint catalog star without harming the
attitude); an accepted solution that is not correct is *wrong*.
Solve times are wall-clock and thread CPU time of ``identify``/``track`` alone (the machine is
shared, so CPU time is the fairer figure).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time

import numpy as np
from scipy.spatial.transform import Rotation

from opnav.allocator import keep_freed_memory
from opnav.camera import Camera
from opnav.catalog import StarCatalog, load_catalog, synthetic_catalog
from opnav.errors import NoSolutionError
from opnav.frames import unit_to_radec
from opnav.image.extract import extract_stars
from opnav.image.starid import CatalogTree, bearings, identify, track
from opnav.image.starid_index import load_or_build_index, vmag_limit_for_density
from opnav.render.frame import RenderOptions, render_frame
from opnav.observer import Observer

FOV_DEG = 11.4
DETECT_VMAG = 7.0


def corner_error_px(camera: Camera, R_est: Rotation, R_true: Rotation) -> float:
    corners = np.array([[0.0, 0.0], [camera.width_px - 1, 0.0], [0.0, camera.height_px - 1], [camera.width_px - 1, camera.height_px - 1]])
    moved = camera.project(R_est.inv().apply(R_true.apply(camera.unproject(corners))))
    return float(np.max(np.linalg.norm(moved - corners, axis=1)))


def stars_in_view(camera, R_true, stars, rng, *, vmag_limit, n_false, px_sigma=0.3, mag_sigma=0.3):
    """Noisy centroids, brightest (noisy magnitude) first, with false stars, and their catalog rows (-1: false).

    The cone search uses the k-d tree: a matrix product over the whole catalog would wake
    OpenBLAS worker threads whose spinning then slows the timed solve on a shared machine.
    """
    radius = camera.half_diagonal_fov_rad + 0.01
    near = np.asarray(stars.tree.query_ball_point(R_true.apply([0.0, 0.0, 1.0]), 2.0 * math.sin(radius / 2.0)), dtype=int)
    v_cam = R_true.inv().apply(stars.vectors[near])
    xy = camera.project(v_cam)
    seen = camera.in_frame(xy)
    mag = stars.vmag[near][seen] + rng.normal(0.0, mag_sigma, seen.sum())
    detected = mag <= vmag_limit
    xy, mag, rows = xy[seen][detected], mag[detected], stars.rows[near][seen][detected]
    xy = np.vstack([xy + rng.normal(0.0, px_sigma, xy.shape),
                    rng.uniform([0.0, 0.0], [camera.width_px - 1, camera.height_px - 1], (n_false, 2))])
    mag = np.r_[mag, rng.uniform(mag.min(initial=3.0), vmag_limit, n_false)]
    rows = np.r_[rows, -np.ones(n_false, int)]
    order = np.argsort(mag, kind="stable")
    return xy[order], rows[order]


def score(found, camera, truth, rows, catalog) -> tuple[bool, bool]:
    """(correct, every match true). A match is true when the matched catalog star lies within
    one pixel of the true one (components of a double star closer than a pixel are one image).
    Correct: every match true, or the attitude agrees with the truth within 2 px at the detector
    corners (a false star may land on a faint catalog star without harming the attitude)."""
    vectors = catalog.unit_vectors()
    image_rows, catalog_rows = found.pairs[:, 0], found.pairs[:, 1]
    real = rows[image_rows] >= 0
    cosines = np.sum(vectors[catalog_rows[real]] * vectors[rows[image_rows][real]], axis=1)
    all_true = bool(np.all(real) and np.all(cosines >= math.cos(camera.pixel_scale_rad)))
    return all_true or corner_error_px(camera, found.R_icrf_cam, truth) < 2.0, all_true


def timed(function, *args, **kwargs):
    wall, cpu = time.perf_counter(), time.thread_time()
    try:
        result = function(*args, **kwargs)
    except NoSolutionError:
        result = None
    return result, time.perf_counter() - wall, time.thread_time() - cpu


def lost_in_space(catalog, index, rng, trials):
    camera = Camera.from_fov(FOV_DEG, 1024, 768)
    stars = CatalogTree.from_catalog(catalog, vmag_limit=DETECT_VMAG + 1.5)
    correct = wrong = some_false = 0
    walls, cpus = [], []
    for _ in range(trials):
        truth = Rotation.random(random_state=rng.integers(2**31))
        xy, rows = stars_in_view(camera, truth, stars, rng, vmag_limit=DETECT_VMAG, n_false=int(rng.integers(0, 6)))
        found, wall, cpu = timed(identify, bearings(xy, camera), index)
        walls.append(wall)
        cpus.append(cpu)
        if found is not None:
            good, all_true = score(found, camera, truth, rows, catalog)
            correct += good
            wrong += not good
            some_false += not all_true
    print(f"[1] lost in space, centroids: {trials} attitudes, {FOV_DEG} deg 1024x768, V<={DETECT_VMAG} + 0.3 mag noise, "
          f"0.3 px, 0-5 false stars")
    print(f"    correct {correct}/{trials} = {100.0 * correct / trials:.2f} %, wrong accepted {wrong}, "
          f"no solution {trials - correct - wrong}; accepted with a false star among the matches {some_false}")
    print(f"    solve time median {1e3 * np.median(walls):.2f} ms wall / {1e3 * np.median(cpus):.2f} ms CPU, "
          f"95th percentile {1e3 * np.percentile(walls, 95):.2f} ms wall / {1e3 * np.percentile(cpus, 95):.2f} ms CPU")


def _with_false_stars(catalog: StarCatalog, boresight: np.ndarray, radius_rad: float, rng, n_false: int) -> StarCatalog:
    """Catalog stars near ``boresight`` with 0.3 mag noise plus ``n_false`` random stars in the cone."""
    near = catalog.subset(catalog.cone(boresight, radius_rad, vmag_limit=DETECT_VMAG + 1.5))
    extra = synthetic_catalog(n_false, rng=rng, vmag_range=(4.0, DETECT_VMAG))
    # Place the false stars uniformly in the cone around the boresight.
    cos_theta = rng.uniform(math.cos(radius_rad), 1.0, n_false)
    phi = rng.uniform(0.0, 2.0 * math.pi, n_false)
    local = np.column_stack([np.sqrt(1 - cos_theta**2) * np.cos(phi), np.sqrt(1 - cos_theta**2) * np.sin(phi), cos_theta])
    to_icrf, _ = Rotation.align_vectors([boresight], [[0.0, 0.0, 1.0]])
    ra, dec = unit_to_radec(to_icrf.apply(local))
    extra = dataclasses.replace(extra, ra_rad=ra, dec_rad=dec)
    merged = {f.name: np.concatenate([getattr(near, f.name), getattr(extra, f.name)]) for f in dataclasses.fields(StarCatalog)}
    merged["vmag"] = merged["vmag"] + np.r_[rng.normal(0.0, 0.3, len(near)), np.zeros(n_false)]
    return StarCatalog(**merged)


def rendered(catalog, index, rng, frames):
    camera = Camera.from_fov(FOV_DEG, 1024, 768)
    observer = Observer(0.0, np.array([1.496e8, 0.0, 0.0]), np.zeros(3))
    options = RenderOptions(vmag_limit=DETECT_VMAG + 1.5)
    correct = wrong = 0
    extract_times, walls, cpus = [], [], []
    for _ in range(frames):
        truth = Rotation.random(random_state=rng.integers(2**31))
        scene = _with_false_stars(catalog, truth.apply([0.0, 0.0, 1.0]), camera.half_diagonal_fov_rad + 0.02, rng,
                                  int(rng.integers(0, 6)))
        image = render_frame(camera, truth, observer, catalog=scene, options=options, rng=rng).image
        started = time.perf_counter()
        xy, _ = extract_stars(image, saturation_adu=float(2**camera.bit_depth - 1))
        extract_times.append(time.perf_counter() - started)
        found, wall, cpu = timed(identify, bearings(xy, camera), index) if len(xy) >= 4 else (None, 0.0, 0.0)
        walls.append(wall)
        cpus.append(cpu)
        if found is not None:
            good = corner_error_px(camera, found.R_icrf_cam, truth) < 2.0
            correct += good
            wrong += not good
    print(f"[2] lost in space, rendered frames (opnav.render): {frames} frames, 0.3 mag noise, 0-5 false stars")
    print(f"    correct {correct}/{frames} = {100.0 * correct / frames:.2f} %, wrong accepted {wrong}")
    print(f"    extraction (detect + centroid, <= 40 stars) median {1e3 * np.median(extract_times):.1f} ms wall; "
          f"solve median {1e3 * np.median(walls):.2f} ms wall / {1e3 * np.median(cpus):.2f} ms CPU")


def tracking(catalog, rng, trials, fov_deg, vmag_limit):
    camera = Camera.from_fov(fov_deg, 1024, 768)
    stars = CatalogTree.from_catalog(catalog, vmag_limit=vmag_limit + 1.0)
    scored = correct = wrong = some_false = 0
    walls, cpus = [], []
    for _ in range(trials):
        truth = Rotation.random(random_state=rng.integers(2**31))
        xy, rows = stars_in_view(camera, truth, stars, rng, vmag_limit=vmag_limit, n_false=int(rng.integers(0, 3)))
        if np.sum(rows >= 0) < 3:
            continue
        axis = rng.normal(size=3)
        prior = truth * Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.radians(0.1) * rng.uniform())
        found, wall, cpu = timed(track, bearings(xy, camera), stars, prior, camera,
                                 prior_sigma_rad=math.radians(0.1) / 3.0, rng=rng)
        scored += 1
        walls.append(wall)
        cpus.append(cpu)
        if found is not None:
            good, all_true = score(found, camera, truth, rows, catalog)
            correct += good
            wrong += not good
            some_false += not all_true
    print(f"[3] tracking, {fov_deg} deg 1024x768, V<={vmag_limit}, prior off by U(0, 0.1) deg, 0-2 false stars: "
          f"{scored} of {trials} attitudes with >= 3 stars")
    print(f"    correct {correct}/{scored} = {100.0 * correct / max(scored, 1):.2f} %, wrong accepted {wrong}, "
          f"with a false star among the matches {some_false}; "
          f"median {1e3 * np.median(walls):.2f} ms wall / {1e3 * np.median(cpus):.2f} ms CPU")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=1000)
    parser.add_argument("--rendered", type=int, default=100)
    parser.add_argument("--tracking", type=int, default=500)
    parser.add_argument("--seed", type=int, default=20240605)
    args = parser.parse_args()
    keep_freed_memory()  # as the opnav command does: the extraction times are the command's
    rng = np.random.default_rng(args.seed)
    catalog = load_catalog()
    fov_min = 0.6 * FOV_DEG
    started = time.perf_counter()
    index = load_or_build_index(catalog, fov_min_deg=fov_min, fov_max_deg=1.15 * FOV_DEG,
                                vmag_limit=vmag_limit_for_density(catalog.vmag, fov_min))
    print(f"index: {len(index.patterns)} patterns, {len(index.star_vectors)} stars, V <= {index.options.vmag_limit:.2f}, "
          f"levels {np.round(np.degrees(index.options.level_fovs_rad()), 2).tolist()} deg, "
          f"load/build {time.perf_counter() - started:.1f} s")
    if args.trials:
        lost_in_space(catalog, index, rng, args.trials)
    if args.rendered:
        rendered(catalog, index, rng, args.rendered)
    for fov_deg, vmag_limit in ((1.5, 10.5), (1.0, 10.5)):
        if args.tracking:
            tracking(catalog, rng, args.tracking, fov_deg, vmag_limit)


if __name__ == "__main__":
    main()
