"""False-match calibration of lost-in-space and tracking identification: how often a frame with
no true solution is "solved", against the ``p_false_max`` the solver was given.

Run: ``.venv/bin/python benchmarks/starid_false_match.py [--trials 1000] [--tracking-trials 3000]``

``opnav.image.starid.identify`` accepts a candidate when its false-match probability (module
step 6: the pattern's own fit times the chance that the other stars match by accident), times the
number of candidates offered, is at most ``p_false_max``. If that probability is honest, a frame
that holds no catalog pattern is accepted at a rate of at most ``p_false_max``. Two such nulls,
each through :func:`opnav.image.starid.solve_stars` as ``opnav solve --fov`` calls it (2 px
verification radius, +-10 % focal length) on the packaged catalog:

- *random*: 5-12 points uniform over the frame;
- *mirrored*: the 5-12 brightest catalog stars of a random pointing with one image axis
  flipped (a camera with a mirrored axis): their patterns have the true edge ratios, so only
  the attitude fit and the other stars can refuse them.

for the S1 1-degree camera (1024 x 1024, lattice-field index) and an 11.4-degree 1024 x 768
camera (density index). Each trial is solved at every ``p_false_max`` of ``--levels``; the
printed rate beside each level, with its 95 % upper bound (Clopper-Pearson), must not exceed it.

Tracking (:func:`opnav.image.starid.track` with a 1.5-degree 1024 x 768 camera) gets 3-10 points
uniform over the frame and an a-priori attitude at a random pointing: a false source field, or a
prior that is wrong. Two settings: ``benchmarks/starid.py``'s (catalog stars to V 11.5, prior
sigma 0.033 deg, 2 px match radius: few candidates a star, where the test credits the pair's
agreeing separation) and a crowded one (V 13, 0.1 deg, 4 px: many candidate pairs).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import beta

from opnav.camera import Camera
from opnav.catalog import load_catalog
from opnav.errors import NoSolutionError
from opnav.image.starid import CatalogTree, bearings, solve_stars, track
from opnav.image.starid_index import index_options_for_fov, load_or_build_index

CAMERAS = {"s1 1 deg": (Camera.from_fov(1.0, 1024, 1024), 1.0, 10.5),
           "wide 11.4 deg": (Camera.from_fov(11.4, 1024, 768), 11.4, 7.0)}


def random_points(camera: Camera, rng: np.random.Generator, **_) -> np.ndarray:
    return rng.uniform([0.0, 0.0], [camera.width_px - 1, camera.height_px - 1], (int(rng.integers(5, 13)), 2))


def mirrored_stars(camera: Camera, rng: np.random.Generator, *, catalog, vmag_limit: float) -> np.ndarray:
    """Brightest stars in view of a random pointing, x flipped; empty when fewer than 5."""
    truth = Rotation.random(random_state=int(rng.integers(2**31)))
    boresight = truth.apply([0.0, 0.0, 1.0])
    rows = catalog.cone(boresight, camera.half_diagonal_fov_rad, vmag_limit=vmag_limit)  # brightest first
    xy = camera.project(truth.inv().apply(catalog.unit_vectors()[rows]))
    xy = xy[camera.in_frame(xy)][: int(rng.integers(5, 13))]
    xy = xy + rng.normal(0.0, 0.05, xy.shape)
    xy[:, 0] = camera.width_px - 1 - xy[:, 0]
    return xy


def report(levels, accepted, trials: int) -> None:
    for level, count in zip(levels, accepted):
        upper = beta.ppf(0.95, count + 1, trials - count) if count < trials else 1.0
        verdict = "ok" if upper <= level or count / trials <= level else "EXCEEDS"
        print(f"  p_false_max {level:g}: accepted {count}/{trials} = {count / trials:.4f} "
              f"(95 % upper {upper:.4f}) {verdict}")


def tracking_nulls(catalog, rng: np.random.Generator, trials: int, levels) -> None:
    camera = Camera.from_fov(1.5, 1024, 768)
    for vmag_limit, prior_sigma_deg, radius_px in ((11.5, 0.1 / 3.0, 2.0), (13.0, 0.1, 4.0)):
        stars = CatalogTree.from_catalog(catalog, vmag_limit=vmag_limit)
        accepted = np.zeros(len(levels), int)
        started = time.perf_counter()
        for _ in range(trials):
            xy = random_points(camera, rng)[: int(rng.integers(3, 11))]
            prior = Rotation.random(random_state=int(rng.integers(2**31)))
            try:
                # the loosest level: a solution's p_false then says at which levels it passes
                found = track(bearings(xy, camera), stars, prior, camera, prior_sigma_rad=np.radians(prior_sigma_deg),
                              match_radius_px=radius_px, p_false_max=max(levels), rng=rng)
            except NoSolutionError:
                continue
            accepted += np.asarray(levels) >= found.p_false
        print(f"tracking 1.5 deg, random points, V <= {vmag_limit}, prior sigma {prior_sigma_deg:.3f} deg, "
              f"match radius {radius_px:g} px: {trials} frames, "
              f"{time.perf_counter() - started:.0f} s")
        report(levels, accepted, trials)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=1000, help="lost-in-space trials per camera and null")
    parser.add_argument("--tracking-trials", type=int, default=3000, help="tracking trials per setting (two settings; module docstring)")
    parser.add_argument("--levels", type=float, nargs="+", default=[0.1, 0.01, 0.001])
    parser.add_argument("--seed", type=int, default=20261125)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    catalog = load_catalog()
    if args.tracking_trials:
        tracking_nulls(catalog, rng, args.tracking_trials, args.levels)
    for name, (camera, fov_deg, vmag_limit) in CAMERAS.items() if args.trials else ():
        index = load_or_build_index(catalog, **index_options_for_fov(catalog, fov_deg, 0.1))
        for null in (random_points, mirrored_stars):
            accepted = np.zeros(len(args.levels), int)
            trials = 0
            started = time.perf_counter()
            while trials < args.trials:
                xy = null(camera, rng, catalog=catalog, vmag_limit=vmag_limit)
                if len(xy) < 5:
                    continue
                trials += 1
                cov = np.tile(np.eye(2) * 0.05**2, (len(xy), 1, 1))
                for k, level in enumerate(args.levels):
                    try:
                        solve_stars(xy, cov, camera.shape, index=index, fov_deg=fov_deg, fov_tolerance=0.1,
                                    p_false_max=level)
                    except NoSolutionError:
                        continue
                    accepted[k] += 1
            elapsed = time.perf_counter() - started
            print(f"{name}, {null.__name__.replace('_', ' ')}: {trials} frames, {elapsed:.0f} s")
            report(args.levels, accepted, trials)


if __name__ == "__main__":
    main()
