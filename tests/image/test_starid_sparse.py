"""Frames with few stars: the sparse level of a pattern index, and the deeper second extraction."""

import dataclasses
import itertools
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_starid import corner_error_px, simulate_stars

from opnav.camera import Camera
from opnav.catalog import load_catalog
from opnav.image.starid_index import SPARSE_SPACING_FRACTION
from opnav.errors import InputError, NoSolutionError
from opnav.image.starid import SPARSE_FRAME_STARS, solve_stars, solve_with_deeper_extraction
from opnav.image.starid_index import IndexOptions, build_index

#: The 6.1 x 4.6 deg camera of ``benchmarks/starid_real.py`` (1392 x 1040 px, 15.8"/px).
CAMERA = Camera(1392, 1040, 6.45e-3 / math.radians(15.8 / 3600.0), 6.45)
#: A frame of that benchmark (seed 101) the levels could not solve: its 9 stars to V 7.35 hold no
#: 4 within a level's pattern size whose stars are all pattern stars of that level.
ATTITUDE = Rotation.from_quat([0.58985969, 0.79556622, 0.08407854, -0.10986688])
VISIBLE_VMAG = 7.35
#: The options ``opnav solve --fov 6.1`` gives this camera, without and with the sparse level.
LEVELS = dict(fov_min_deg=0.6 * 0.9 * 6.1, fov_max_deg=1.1 * 6.1, vmag_limit=9.21)
SPARSE = SPARSE_SPACING_FRACTION


@pytest.fixture(scope="module")
def sky():
    # The real sky within 15 deg of the frame: star selection looks at most 4.5 deg (half the
    # largest level) around a star, so the frame's stars are chosen as in a whole-sky index.
    catalog = load_catalog()
    return catalog.subset(catalog.cone(ATTITUDE.apply([0.0, 0.0, 1.0]), math.radians(15.0), vmag_limit=9.21))


@pytest.fixture(scope="module")
def frame(sky):
    xy, rows = simulate_stars(CAMERA, ATTITUDE, sky, np.random.default_rng(1), vmag_limit=VISIBLE_VMAG, mag_sigma=0.0)
    return xy, np.tile(np.eye(2) * 0.3**2, (len(xy), 1, 1)), rows


def frame_patterns(index, rows):
    """How many 4-sets of the frame's catalog rows are index patterns."""
    patterns = set(map(tuple, np.sort(index.patterns, axis=1).tolist()))
    index_row = {int(c): i for i, c in enumerate(index.catalog_rows)}
    return sum(tuple(sorted(index_row.get(int(r), -1) for r in quad)) in patterns for quad in itertools.combinations(rows, 4))


def test_sparse_level_solves_a_real_frame_the_levels_miss(sky, frame):
    xy, cov, rows = frame
    assert len(rows) == 9 and np.all(rows >= 0)
    levels = build_index(sky, **LEVELS)
    assert frame_patterns(levels, rows) == 0
    with pytest.raises(NoSolutionError):
        solve_stars(xy, cov, CAMERA.shape, index=levels, fov_deg=6.1)
    sparse = build_index(sky, **LEVELS, sparse_spacing_fraction=SPARSE)
    assert frame_patterns(sparse, rows) >= 1
    solution = solve_stars(xy, cov, CAMERA.shape, index=sparse, fov_deg=6.1)
    matched = solution.identification.pairs
    assert len(matched) == 9
    assert np.array_equal(rows[matched[:, 0]], matched[:, 1])
    assert corner_error_px(CAMERA, solution.identification.R_icrf_cam, ATTITUDE) < 1.0


def test_sparse_patterns_are_local_maxima_up_to_the_largest_fov(sky):
    levels = build_index(sky, **LEVELS)
    sparse = build_index(sky, **LEVELS, sparse_spacing_fraction=SPARSE)
    old = set(map(tuple, levels.catalog_rows[levels.patterns].tolist()))
    new = np.array([p for p in sparse.catalog_rows[sparse.patterns].tolist() if tuple(p) not in old])
    assert len(new) > 0
    vectors, vmag = sky.unit_vectors(), sky.vmag
    spacing = SPARSE * math.radians(LEVELS["fov_max_deg"])
    for row in np.unique(new):
        near = sky.cone(vectors[row], spacing, vmag_limit=LEVELS["vmag_limit"])
        assert vmag[row] <= vmag[near].min()
    edges = np.arccos(np.clip(np.einsum("pik,pjk->pij", vectors[new], vectors[new]), -1.0, 1.0))
    assert edges.max() <= math.radians(LEVELS["fov_max_deg"]) + 1e-9


@pytest.mark.parametrize("fraction", [-0.1, 0.01, 0.6, math.nan])
def test_sparse_spacing_is_validated(fraction):
    with pytest.raises(InputError, match="sparse_spacing_fraction"):
        IndexOptions(**LEVELS, sparse_spacing_fraction=fraction)


def faint_frame(rng, bright, faint):
    """A 400 x 400 frame (ADU, sky 100, noise 5) with ``bright`` stars of peak SNR 60 and ``faint`` ones at the detection threshold."""
    rows, cols = np.mgrid[0:400, 0:400].astype(float)
    image = 100.0 + rng.normal(0.0, 5.0, rows.shape)
    for k, peak in enumerate([300.0] * bright + [8.0] * faint):
        x, y = 40.0 + (k % 6) * 60.0 + 0.3, 60.0 + (k // 6) * 90.0 + 0.6
        image += peak * np.exp(-((cols - x) ** 2 + (rows - y) ** 2) / (2.0 * 1.2**2))
    return image


def test_a_frame_of_few_stars_is_extracted_again_deeper():
    image = faint_frame(np.random.default_rng(4), bright=4, faint=6)
    offered = []

    def solve(xy, cov):
        offered.append(len(xy))
        if len(xy) < 6:
            raise NoSolutionError("too few stars")
        return SimpleSolution()

    solution = solve_with_deeper_extraction(image, solve)
    assert len(offered) == 2 and offered[0] < 6 <= offered[1]
    assert solution.extract_s > 0.0

    offered.clear()
    with pytest.raises(NoSolutionError, match="too few stars; extracted again down to 4 sigma: too few stars"):
        solve_with_deeper_extraction(image, lambda xy, cov: solve(xy[:3], cov[:3]))


def test_a_frame_of_many_stars_is_not_extracted_again():
    image = faint_frame(np.random.default_rng(4), bright=SPARSE_FRAME_STARS, faint=6)
    offered = []

    def never(xy, cov):
        offered.append(len(xy))
        raise NoSolutionError("no")

    with pytest.raises(NoSolutionError, match="^no$"):
        solve_with_deeper_extraction(image, never)
    assert offered == [SPARSE_FRAME_STARS]


@dataclasses.dataclass(frozen=True)
class SimpleSolution:
    extract_s: float = 0.0
