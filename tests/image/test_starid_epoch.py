"""PatternIndex.at_epoch frame after frame (directions reused within a tolerance) and its star search by zones."""

import dataclasses
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from opnav.catalog import load_catalog
from opnav.constants import JULIAN_YEAR_S
from opnav.errors import InputError
from opnav.image.starid_index import EPOCH_REUSE_TOLERANCE_RAD, build_index

HOUR_S = 3600.0
T0 = 4.586e8  # July 2014, TDB s past J2000


@pytest.fixture(scope="module")
def sky():
    # the real stars (proper motions and parallaxes) within 12 deg of a direction
    catalog = load_catalog()
    return catalog.subset(catalog.cone(np.array([0.3, -0.8, 0.5]), math.radians(12.0), vmag_limit=10.0))


@pytest.fixture(scope="module")
def index(sky):
    return build_index(sky, fov_min_deg=4.0, fov_max_deg=6.0, vmag_limit=10.0)


def _exact(sky, index, t, r):
    return sky.apparent_directions(index.catalog_rows, t_tdb_s=t, r_observer_ssb_km=np.zeros(3) if r is None else r,
                                   v_observer_ssb_km_s=np.zeros(3), parallax=r is not None, aberration=False)


def _angles(a, b):
    return 2.0 * np.arcsin(np.minimum(np.linalg.norm(a - b, axis=1) / 2.0, 1.0))


def test_directions_reused_from_an_earlier_frame_are_within_the_tolerance_of_a_fresh_computation(sky, index):
    """Hourly frames along a 30 km/s arc, then a jump of decades and back: every direction is within
    EPOCH_REUSE_TOLERANCE_RAD of the catalog's own computation, and an unchanged epoch gives it exactly."""
    r0, v = np.array([-7.2e7, -1.8e8, -7.9e7]), np.array([20.0, -8.0, -4.6])
    epochs = [T0 + k * HOUR_S for k in range(0, 80, 7)] + [T0 + 30.0 * JULIAN_YEAR_S, T0 + 2.0 * HOUR_S]
    for with_parallax in (True, False):
        for t in epochs:
            r = r0 + v * (t - T0) if with_parallax else None
            moved = index.at_epoch(sky, t_tdb_s=t, r_observer_ssb_km=r)
            assert np.max(_angles(moved.star_vectors, _exact(sky, index, t, r))) <= EPOCH_REUSE_TOLERANCE_RAD
            assert moved.patterns is index.patterns and moved.keys is index.keys
        again = index.at_epoch(sky, t_tdb_s=epochs[-1], r_observer_ssb_km=r)
        np.testing.assert_array_equal(again.star_vectors, moved.star_vectors)
    # another catalog object of the same directions (the digest matches) moves by its own proper motions
    faster = dataclasses.replace(sky, pm_ra_cosdec_rad_yr=3.0 * sky.pm_ra_cosdec_rad_yr)
    t = T0 + 5.0 * HOUR_S
    moved = index.at_epoch(faster, t_tdb_s=t)
    assert np.max(_angles(moved.star_vectors, _exact(faster, index, t, None))) <= EPOCH_REUSE_TOLERANCE_RAD
    assert np.max(_angles(moved.star_vectors, _exact(sky, index, t, None))) > 1e3 * EPOCH_REUSE_TOLERANCE_RAD


def test_the_zone_search_finds_what_a_kd_tree_finds(sky, index):
    rng = np.random.default_rng(5)
    moved = index.at_epoch(sky, t_tdb_s=T0 - 60.0 * JULIAN_YEAR_S)  # stars far (up to arcminutes) from the sorted ones
    for searched in (index, moved):
        tree = cKDTree(searched.star_vectors)
        centres = sky.unit_vectors()[rng.integers(len(sky), size=40)] + rng.normal(scale=0.02, size=(40, 3))
        centres /= np.linalg.norm(centres, axis=1, keepdims=True)
        for centre, radius in zip(centres, rng.uniform(1e-4, 0.1, 40)):
            found = searched.tree.query_ball_point(centre, radius)
            assert found == sorted(tree.query_ball_point(centre, radius))
        many = searched.tree.query_ball_point(centres[:3], 0.05)
        assert [sorted(rows) for rows in many] == [sorted(rows) for rows in tree.query_ball_point(centres[:3], 0.05)]
    # a method the zones do not offer is a kd-tree's
    assert moved.tree.query(moved.star_vectors[:2])[1].tolist() == [0, 1]


def test_an_index_and_its_moved_copy_pickle(sky, index):
    import pickle

    moved = index.at_epoch(sky, t_tdb_s=T0 + 40.0 * JULIAN_YEAR_S)
    for original in (index, moved):
        copy = pickle.loads(pickle.dumps(original))
        assert copy.checksum() == original.checksum()
        centre = original.star_vectors[7]
        assert copy.tree.query_ball_point(centre, 0.03) == original.tree.query_ball_point(centre, 0.03)


class _CountingCatalog:
    """``sky`` that counts the star directions computed (apparent_directions rows)."""

    def __init__(self, sky):
        self.sky, self.computed = sky, 0

    def __getattr__(self, name):
        return getattr(self.sky, name)

    def apparent_directions(self, rows, **kwargs):
        self.computed += len(rows)
        return self.sky.apparent_directions(rows, **kwargs)


def test_a_first_epoch_computes_the_directions_read_each_as_the_full_computation(sky, index):
    # opnav solve of one frame reads a few thousand of a 1-degree index's 490,000 stars: at_epoch from
    # scratch computes those it is asked for, each the value of the full computation, and the rest on asarray
    fresh = dataclasses.replace(index)  # no epoch computed yet
    counting = _CountingCatalog(sky)
    t, r = T0 + 25.0 * JULIAN_YEAR_S, np.array([-7.2e7, -1.8e8, -7.9e7])
    moved = fresh.at_epoch(counting, t_tdb_s=t, r_observer_ssb_km=r)
    assert counting.computed <= 1  # the row that checks the epoch and position
    exact = _exact(sky, fresh, t, r)
    rows = np.random.default_rng(2).integers(len(exact), size=60)
    np.testing.assert_array_equal(moved.star_vectors[rows], exact[rows])
    np.testing.assert_array_equal(moved.star_vectors[:3], exact[:3])
    assert counting.computed <= 1 + 60 + 3
    np.testing.assert_array_equal(np.asarray(moved.star_vectors), exact)
    # the zones' band covers every star's move: what a k-d tree of the moved directions finds
    centre = exact[7]
    assert moved.tree.query_ball_point(centre, 0.03) == sorted(cKDTree(exact).query_ball_point(centre, 0.03))
    with pytest.raises(InputError, match="t_tdb_s must be finite"):
        dataclasses.replace(index).at_epoch(sky, t_tdb_s=math.nan)


def test_two_epochs_read_in_turn_each_get_their_own_directions(sky, index):
    # the directions are cached per star with the epoch they were computed for: a copy at another epoch
    # that computes a star again must not hand its direction to the first copy
    fresh = dataclasses.replace(index)
    early, late = T0, T0 + 40.0 * JULIAN_YEAR_S
    a, b = fresh.at_epoch(sky, t_tdb_s=early), fresh.at_epoch(sky, t_tdb_s=late)
    exact_a, exact_b = _exact(sky, fresh, early, None), _exact(sky, fresh, late, None)
    rows = np.random.default_rng(4).integers(len(exact_a), size=(5, 30))
    for chunk in rows:
        for moved, exact in ((a, exact_a), (b, exact_b), (a, exact_a)):
            assert np.max(_angles(moved.star_vectors[chunk], exact[chunk])) <= EPOCH_REUSE_TOLERANCE_RAD
    assert np.max(_angles(np.asarray(a.star_vectors), exact_a)) <= EPOCH_REUSE_TOLERANCE_RAD
    assert np.max(_angles(np.asarray(b.star_vectors), exact_b)) <= EPOCH_REUSE_TOLERANCE_RAD
    assert np.max(_angles(exact_a, exact_b)) > 1e3 * EPOCH_REUSE_TOLERANCE_RAD  # the epochs differ
