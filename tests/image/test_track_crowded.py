"""Tracking in a crowded prior gate: more candidate pairs than hypotheses scored."""

import math

import numpy as np
from scipy.spatial.transform import Rotation

from opnav.camera import Camera
from opnav.catalog import synthetic_catalog
from opnav.image.starid import CatalogTree, bearings, track

# the narrow-angle camera of tests/image/test_moons_near_mars.py (3.5"/px) on 320 px, and the
# pipeline's default prior (0.05 deg a axis: a 4.3-sigma gate of 220 px, most of the frame)
CAMERA = Camera.from_fov(320 * 3.5 / 3600.0, 320, 320)
PRIOR_SIGMA_RAD = math.radians(0.05)


def _field(rng):
    """A true attitude, 400 catalog stars (V 6-11) in a 0.25-degree cap around its boresight, and the
    centroids (px, brightest first, 0.02 px noise: stars at SNR of hundreds) of those in the frame."""
    truth = Rotation.random(random_state=rng.integers(2**31))
    boresight = truth.apply([0.0, 0.0, 1.0])
    catalog = synthetic_catalog(400, rng=rng, vmag_range=(6.0, 11.0), centre_icrf=boresight,
                                radius_rad=math.radians(0.25))
    v_cam = truth.inv().apply(np.array(catalog.unit_vectors()))
    xy = CAMERA.project(v_cam)
    rows = np.flatnonzero(CAMERA.in_frame(xy) & (v_cam[:, 2] > 0))
    rows = rows[np.argsort(catalog.vmag[rows], kind="stable")]
    return truth, catalog, rows, xy[rows] + rng.normal(0.0, 0.02, (len(rows), 2))


def _corner_shift_px(R_est, R_true):
    """Largest displacement (px) of the detector's corners between two attitudes (the roll about a
    narrow field's boresight is weakly held and moves the corners least)."""
    corners = np.array([[0.0, 0.0], [319.0, 0.0], [0.0, 319.0], [319.0, 319.0]])
    moved = CAMERA.project(R_est.inv().apply(R_true.apply(CAMERA.unproject(corners))))
    return float(np.max(np.linalg.norm(moved - corners, axis=1)))


def test_track_finds_the_true_pairs_among_many_more_hypotheses_than_it_scores():
    # 18,000-23,000 hypotheses from the 6 brightest stars, 15 of them true; 400 scored. A random
    # draw of 400 holds none of the 15 in ~3 frames of 4 (9 of these 10 failed with it); the true
    # pairs' separations agree to the centroids' noise (hundredths of a pixel), so the best-agreeing
    # half holds them.
    rng = np.random.default_rng(41)
    for _ in range(10):
        truth, catalog, rows, xy = _field(rng)
        prior = truth * Rotation.from_rotvec(rng.normal(0.0, PRIOR_SIGMA_RAD / 5, 3))
        found = track(bearings(xy, CAMERA), CatalogTree.from_catalog(catalog), prior, CAMERA,
                      prior_sigma_rad=PRIOR_SIGMA_RAD, max_hypotheses=400, rng=rng)
        assert _corner_shift_px(found.R_icrf_cam, truth) < 0.05  # a single centroid's noise is 0.02 px
        matched = found.pairs[:, 1] == rows[found.pairs[:, 0]]
        assert matched.all() and len(found.pairs) >= 0.95 * len(rows)
