"""Narrow-field lost-in-space (lattice-field index), index checksum, geometric vs apparent pointing."""

import itertools
import logging
import math
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_starid import corner_error_px, simulate_stars

from opnav.camera import Camera
from opnav.catalog import synthetic_catalog
from opnav.errors import CatalogError, InputError, NoSolutionError
from opnav.image.starid import _candidates, _lookup, _subsets_brightest_first, bearings, solve_stars
from opnav.image.starid_index import (
    EDGE_FIRST,
    EDGE_SECOND,
    IndexOptions,
    PatternIndex,
    build_index,
    fibonacci_lattice,
    load_or_build_index,
    pair_angles,
    pattern_ratios,
)
from opnav.light import aberrate

#: A 2-degree camera; the synthetic sky holds ~10 stars (V <= 9) in its 2 x 1.5 deg field.
CAMERA = Camera.from_fov(2.0, 1024, 768)
ARCSEC = math.radians(1.0 / 3600.0)


@pytest.fixture(scope="module")
def sky():
    # 3.3 stars per square degree to V 9, magnitudes uniform in 6-9.5
    return synthetic_catalog(140_000, rng=np.random.default_rng(11), vmag_range=(6.0, 9.5))


@pytest.fixture(scope="module")
def index(sky):
    return build_index(sky, fov_min_deg=1.4, fov_max_deg=2.2, vmag_limit=9.5, selection="fields",
                       pattern_stars_per_fov=8)


def xy_cov(xy):
    return xy, np.tile(np.eye(2) * 0.3**2, (len(xy), 1, 1))


def test_lattice_is_even():
    points = fibonacci_lattice(4000)
    assert np.allclose(np.linalg.norm(points, axis=1), 1.0)
    # equal-area: each octant holds an eighth of the points
    octant = (points[:, 0] > 0) * 4 + (points[:, 1] > 0) * 2 + (points[:, 2] > 0)
    assert np.all(np.abs(np.bincount(octant, minlength=8) - 500) < 25)


def test_field_index_size_is_bounded(sky, index):
    # each lattice field contributes at most C(8, 4) = 70 patterns whatever the catalog depth
    fields = sum(3.0 * 4.0 / (0.35 * fov) ** 2 for fov in index.options.level_fovs_rad())
    assert 0 < len(index.patterns) <= 70 * fields
    assert index.options.selection == "fields"
    assert np.all(index.max_edge_rad <= 0.7 * index.options.level_fovs_rad()[-1] + 1e-6)


def test_narrow_field_random_attitudes_with_few_stars(sky, index):
    rng = np.random.default_rng(12)
    scored = solved = 0
    for _ in range(60):
        truth = Rotation.random(random_state=rng.integers(2**31))
        xy, rows = simulate_stars(CAMERA, truth, sky, rng, vmag_limit=9.0, n_false=int(rng.integers(0, 2)))
        if np.sum(rows >= 0) < 6:
            continue
        scored += 1
        try:
            solution = solve_stars(*xy_cov(xy), CAMERA.shape, index=index, fov_deg=2.1, fov_tolerance=0.1)
        except NoSolutionError:
            continue
        # never a wrong attitude: every accepted one is within 2 px at the corners
        assert corner_error_px(CAMERA, solution.attitude(), truth) < 2.0
        solved += 1
    assert scored >= 30
    assert solved >= 0.95 * scored


def test_random_points_are_never_identified(index):
    rng = np.random.default_rng(13)
    for _ in range(30):
        xy = rng.uniform([0, 0], [CAMERA.width_px - 1, CAMERA.height_px - 1], (int(rng.integers(6, 15)), 2))
        with pytest.raises(NoSolutionError):
            solve_stars(*xy_cov(xy), CAMERA.shape, index=index, fov_deg=2.0, fov_tolerance=0.1)


def test_apparent_and_geometric_pointing(sky, index):
    """Stars drawn at their aberrated directions: the apparent boresight is the true one, the
    geometric one is off by the aberration of the boresight (|v|/c sin angle, up to 22" here).
    (Roll about the boresight of a 2-degree field is known only to a few arcsec: not compared.)"""
    rng = np.random.default_rng(14)
    velocity = np.array([0.0, 29.8, 12.9])  # km/s, ICRF: Earth-like orbital speed
    done = 0
    for _ in range(40):
        truth = Rotation.random(random_state=rng.integers(2**31))
        v_cam = truth.inv().apply(aberrate(sky.unit_vectors(), velocity))
        xy = CAMERA.project(v_cam)
        rows = np.flatnonzero(CAMERA.in_frame(xy) & (v_cam[:, 2] > 0) & (sky.vmag <= 9.0))
        if len(rows) < 8:
            continue
        rows = rows[np.argsort(sky.vmag[rows])]
        solution = solve_stars(*xy_cov(xy[rows] + rng.normal(0.0, 0.02, (len(rows), 2))), CAMERA.shape,
                               index=index, fov_deg=2.0, fov_tolerance=0.1)
        boresight = truth.apply([0.0, 0.0, 1.0])
        expected = np.linalg.norm(velocity) / 299792.458 * np.linalg.norm(np.cross(boresight, velocity / np.linalg.norm(velocity)))
        apparent = math.acos(np.clip(solution.attitude(velocity).apply([0, 0, 1]) @ boresight, -1, 1))
        geometric_offset = math.acos(np.clip(solution.attitude().apply([0, 0, 1]) @ boresight, -1, 1))
        assert solution.pointing == "geometric"
        assert apparent < 0.3 * ARCSEC
        assert expected > 3.0 * ARCSEC
        assert abs(geometric_offset - expected) < 0.3 * ARCSEC
        done += 1
        if done == 5:
            break
    assert done == 5
    with pytest.raises(InputError):
        solution.attitude(np.array([1.0, 2.0]))


def test_corrupt_index_is_detected_and_rebuilt(sky, tmp_path):
    options = dict(fov_min_deg=8.0, fov_max_deg=12.0, vmag_limit=7.0, selection="fields")
    first = load_or_build_index(sky, cache_dir=tmp_path, **options)
    # the index is memory-mapped: the files are changed in place below (the cache itself never
    # does: it writes new files and renames them), so keep what it held
    first_checksum, first_patterns = first.checksum(), np.array(first.patterns)
    del first
    (path,) = tmp_path.glob("starid-*")
    # same arrays but one pattern changed, stored checksum kept: the checksum catches it
    patterns = np.load(path / "patterns.npy")
    patterns[0, 0] += 1
    np.save(path / "patterns.npy", patterns)
    with pytest.raises(CatalogError, match="checksum"):
        PatternIndex.load(path)
    assert np.array_equal(load_or_build_index(sky, cache_dir=tmp_path, **options).patterns, first_patterns)
    assert PatternIndex.load(path).checksum() == first_checksum
    # a flipped byte anywhere in a file: unreadable or failing the checksum, never silently used
    for name in ("patterns.npy", "keys.npy", "star_vectors.npy", "directory_keys.npy", "zone_order.npy",
                 "manifest.json"):
        assert PatternIndex.load(path).checksum() == first_checksum
        for offset in (10, None):  # in the .npy header, then in the data
            raw = bytearray((path / name).read_bytes())
            raw[len(raw) // 2 if offset is None else offset] ^= 0xFF
            (path / name).write_bytes(bytes(raw))
            with pytest.raises(CatalogError):
                PatternIndex.load(path)
            raw[len(raw) // 2 if offset is None else offset] ^= 0xFF
            (path / name).write_bytes(bytes(raw))
    # a truncated file, a missing one
    raw = (path / "ratios.npy").read_bytes()
    (path / "ratios.npy").write_bytes(raw[:-8])
    with pytest.raises(CatalogError, match="bytes"):
        PatternIndex.load(path)
    (path / "ratios.npy").unlink()
    with pytest.raises(CatalogError):
        PatternIndex.load(path)
    assert np.array_equal(load_or_build_index(sky, cache_dir=tmp_path, **options).patterns, first_patterns)


def test_an_index_is_verified_once_then_opened_without_hashing(sky, tmp_path, monkeypatch):
    """The checksums are computed when the index is written (and after any file changed), not on every load."""
    options = dict(fov_min_deg=8.0, fov_max_deg=12.0, vmag_limit=7.0, selection="fields")
    built = load_or_build_index(sky, cache_dir=tmp_path, **options)
    built_checksum = built.checksum()
    (path,) = tmp_path.glob("starid-*")
    time.sleep(0.05)
    PatternIndex.load(path)  # verifies again only if the build's marker was written within the clock tick
    hashed = []
    real = PatternIndex.checksum
    monkeypatch.setattr(PatternIndex, "checksum", lambda self: hashed.append(1) or real(self))
    for _ in range(3):
        assert np.array_equal(load_or_build_index(sky, cache_dir=tmp_path, **options).patterns, built.patterns)
    assert hashed == []
    assert PatternIndex.load(path, verify=True).checksum() == built_checksum
    assert len(hashed) == 2
    # a copy of the directory (other inodes) is verified once, then trusted
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(path, copy)
    hashed.clear()
    PatternIndex.load(copy)
    assert len(hashed) == 1
    time.sleep(0.05)
    PatternIndex.load(copy)
    PatternIndex.load(copy)
    assert len(hashed) <= 2


def test_an_earlier_npz_cache_file_is_converted_once(sky, tmp_path, caplog):
    options = dict(fov_min_deg=8.0, fov_max_deg=12.0, vmag_limit=7.0, selection="fields")
    built = load_or_build_index(sky, cache_dir=tmp_path, **options)
    (path,) = tmp_path.glob("starid-*")
    # what earlier versions left in the cache: one .npz file of the same name
    import shutil

    shutil.rmtree(path)
    built.save(path.with_name(path.name + ".npz"))
    assert cached_entry_count(tmp_path) == 1
    with caplog.at_level(logging.INFO, logger="opnav.image.starid_index"):
        converted = load_or_build_index(sky, cache_dir=tmp_path, **options)
    assert "converted" in caplog.text
    assert converted.checksum() == built.checksum()
    assert path.is_dir() and not path.with_name(path.name + ".npz").exists()
    # a corrupt earlier file is rebuilt, not converted
    shutil.rmtree(path)
    built.save(path.with_name(path.name + ".npz"))
    raw = bytearray(path.with_name(path.name + ".npz").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    path.with_name(path.name + ".npz").write_bytes(bytes(raw))
    assert load_or_build_index(sky, cache_dir=tmp_path, **options).checksum() == built.checksum()
    assert cached_entry_count(tmp_path) == 1


def cached_entry_count(directory) -> int:
    return len(list(directory.glob("starid-*")))


def test_field_options_are_validated():
    with pytest.raises(InputError):
        IndexOptions(fov_min_deg=1.0, fov_max_deg=2.0, vmag_limit=9.0, selection="random")
    with pytest.raises(InputError):
        IndexOptions(fov_min_deg=1.0, fov_max_deg=2.0, vmag_limit=9.0, field_oversampling=0.0)


class _Directions:
    """A star source of given directions and magnitudes (a sky at another epoch)."""

    def __init__(self, vectors, vmag):
        self._vectors, self.vmag = vectors, vmag

    def unit_vectors(self):
        return self._vectors


def test_index_at_the_observation_epoch_follows_proper_motion(sky, index):
    """Stars moving 0.4"/yr observed 30 years after the catalog epoch are 12" (1.7 px of this 7"/px
    camera) from their catalog directions, most of the 2 px verification radius: against the index
    moved to the epoch the matched stars' residuals are the centroids' (0.3 px) and (nearly) every
    star is confirmed; against the catalog-epoch index they are several times larger and a quarter
    of the stars are lost. Never a wrong star either way."""
    import dataclasses

    from opnav.image.starid import _angles

    rng = np.random.default_rng(21)
    year_s = 365.25 * 86400.0
    heading = rng.uniform(0.0, 2.0 * math.pi, len(sky))
    mu = 0.4 * ARCSEC
    moving = dataclasses.replace(sky, pm_ra_cosdec_rad_yr=mu * np.cos(heading), pm_dec_rad_yr=mu * np.sin(heading),
                                 has_pm=np.ones(len(sky), bool))
    t_tdb_s = float(sky.epoch_tdb_s[0]) + 30.0 * year_s
    np.testing.assert_allclose(index.at_epoch(moving, t_tdb_s=float(sky.epoch_tdb_s[0])).star_vectors,
                               index.star_vectors, rtol=0.0, atol=1e-15)
    moved = index.at_epoch(moving, t_tdb_s=t_tdb_s)
    np.testing.assert_allclose(_angles(index.star_vectors, moved.star_vectors), 30.0 * mu, rtol=1e-6)
    assert moved.patterns is index.patterns and moved.keys is index.keys
    with pytest.raises(CatalogError, match="catalog digest"):
        index.at_epoch(synthetic_catalog(100, rng=rng), t_tdb_s=t_tdb_s)

    sky_then = _Directions(moving.apparent_directions(t_tdb_s=t_tdb_s, r_observer_ssb_km=np.zeros(3),
                                                      v_observer_ssb_km_s=np.zeros(3), parallax=False,
                                                      aberration=False), sky.vmag)
    scored = 0
    solved = {"epoch": 0, "catalog": 0}
    residual_px = {"epoch": [], "catalog": []}
    matched = {"epoch": [], "catalog": []}
    for _ in range(40):
        truth = Rotation.random(random_state=rng.integers(2**31))
        xy, rows = simulate_stars(CAMERA, truth, sky_then, rng, vmag_limit=9.0)
        if np.sum(rows >= 0) < 6:
            continue
        scored += 1
        for name, used in (("epoch", moved), ("catalog", index)):
            try:
                solution = solve_stars(*xy_cov(xy), CAMERA.shape, index=used, fov_deg=2.1, fov_tolerance=0.1)
            except NoSolutionError:
                continue
            ident = solution.identification
            assert np.array_equal(rows[ident.pairs[:, 0]], ident.pairs[:, 1]), "never a wrong star"
            solved[name] += 1
            residual_px[name] += list(ident.residuals_rad * solution.camera.focal_length_px)
            matched[name].append(len(ident.pairs) / np.sum(rows >= 0))
    assert scored >= 20
    # (pattern ratios stay those of the catalog epoch, 12" moves short edges' ratios by up to ~0.02:
    # a few frames lose their patterns either way; measured 31 and 26 of 33)
    assert solved["epoch"] >= 0.9 * scored and solved["epoch"] >= solved["catalog"]
    # residuals of 2-D Gaussian centroid errors of 0.3 px: median 0.3 sqrt(2 ln 2) = 0.35 px
    assert np.median(residual_px["epoch"]) < 0.45
    assert np.median(residual_px["catalog"]) > 2.0 * np.median(residual_px["epoch"])
    assert np.mean(matched["epoch"]) > np.mean(matched["catalog"])


def test_false_candidates_fit_their_ratios_as_the_false_match_test_assumes(index):
    """Module step 6 credits a pattern's own fit with P[d <= t] = (t / e)^4 for a false candidate,
    d its largest edge-ratio difference and e ``pattern_max_error``. Random points hold no catalog
    pattern, so every candidate the lookup offers them is false: their d must follow that law."""
    rng = np.random.default_rng(15)
    subsets = _subsets_brightest_first(10)
    max_error = 0.008
    found = []
    for _ in range(150):
        b = bearings(rng.uniform([0, 0], [CAMERA.width_px - 1, CAMERA.height_px - 1], (10, 2)), CAMERA)
        ratios, largest = pattern_ratios(pair_angles(b[subsets], EDGE_FIRST, EDGE_SECOND))
        subset_of, pattern_of, _ = _lookup(ratios, largest, index, max_error, math.log1p(0.1) + 3 * max_error)
        found.append(np.max(np.abs(index.ratios[pattern_of] - ratios[subset_of]), axis=1) / max_error)
    d = np.concatenate(found)
    assert len(d) > 5000
    for t in (0.5, 0.25):
        # the law may be conservative (fewer close fits), never optimistic beyond sampling noise
        expected = t**4
        assert np.mean(d <= t) <= expected + 4.0 * math.sqrt(expected / len(d))
    assert np.mean(d <= 0.5) > 0.5 * 0.5**4  # and not so conservative that it says nothing


def test_lookup_finds_exactly_what_a_scan_of_every_pattern_finds(index):
    """The keyed lookup (distinct-key directory, column-wise ratio check) returns the candidates,
    in the order, that comparing each image pattern with every catalog pattern gives."""
    rng = np.random.default_rng(17)
    subsets = _subsets_brightest_first(6)
    max_error, allowed = 0.008, math.log1p(0.1) + 3 * 0.008
    catalog_ratios = index.ratios.astype(float)
    total = 0
    for trial in range(8):
        if trial % 2:
            # image patterns that are catalog patterns, with noise: candidates near the tolerance
            picked = rng.integers(0, len(index.patterns), len(subsets))
            ratios = catalog_ratios[picked] + rng.normal(0.0, 0.004, (len(subsets), 5))
            largest = index.max_edge_rad[picked] * np.exp(rng.normal(0.0, 0.05, len(subsets)))
        else:
            b = bearings(rng.uniform([0, 0], [CAMERA.width_px - 1, CAMERA.height_px - 1], (6, 2)), CAMERA)
            ratios, largest = pattern_ratios(pair_angles(b[subsets], EDGE_FIRST, EDGE_SECOND))
        expected = []  # (subset, ratio error, pattern, scale) of every pattern within the tolerances
        for row in range(len(subsets)):
            near = np.flatnonzero(np.abs(catalog_ratios[:, 0] - ratios[row, 0]) <= max_error)
            error = np.max(np.abs(catalog_ratios[near] - ratios[row]), axis=1)
            scale = largest[row] / index.max_edge_rad[near].astype(float)
            keep = (error <= max_error) & (np.abs(np.log(scale)) <= allowed)
            expected += list(zip([row] * int(keep.sum()), error[keep], near[keep], scale[keep]))
        expected.sort(key=lambda e: (e[1], e[0], e[2]))  # smallest ratio error first, then subset, then pattern
        subset_of, pattern_of, scale = _lookup(ratios, largest, index, max_error, allowed)
        assert np.array_equal(subset_of, [e[0] for e in expected])
        assert np.array_equal(pattern_of, [e[2] for e in expected])
        assert np.array_equal(scale, [e[3] for e in expected])
        total += len(subset_of)
    assert total > 100


def test_the_first_only_lookup_finds_the_full_lookups_first_candidate(index):
    """identify's first block starts from a lookup of each image pattern's own key and the keys that could
    hold a closer fit (module step 4): when it says it is complete, its first candidate is the full
    lookup's first and everything it returns is among the full lookup's candidates. Image patterns that
    are catalog patterns with centroid-like noise (fits of 1e-5 to 1e-3), some moved onto their bins'
    edges, and random ones."""
    rng = np.random.default_rng(18)
    subsets = _subsets_brightest_first(6)
    max_error, allowed = 0.008, math.log1p(0.1) + 3 * 0.008
    bins = index.options.pattern_bins
    catalog_ratios = index.ratios.astype(float)
    complete = 0
    for trial in range(300):
        if trial % 3:
            picked = rng.integers(0, len(index.patterns), len(subsets))
            ratios = catalog_ratios[picked] + rng.normal(0.0, 10.0 ** rng.uniform(-5, -3), (len(subsets), 5))
            if trial % 3 == 2:  # a ratio a hair from its bin's edge, on either side
                row, k = rng.integers(len(subsets)), rng.integers(5)
                ratios[row, k] = np.round(ratios[row, k] * bins) / bins + rng.normal(0.0, 1e-5)
            largest = index.max_edge_rad[picked].astype(float)
        else:
            b = bearings(rng.uniform([0, 0], [CAMERA.width_px - 1, CAMERA.height_px - 1], (6, 2)), CAMERA)
            ratios, largest = pattern_ratios(pair_angles(b[subsets], EDGE_FIRST, EDGE_SECOND))
        full = _candidates(ratios, largest, index, max_error, allowed, False)
        first = _candidates(ratios, largest, index, max_error, allowed, True)
        if not first[3]:
            continue
        complete += 1
        assert (first[0][0], first[1][0]) == (full[0][0], full[1][0])
        assert set(zip(first[0], first[1])) <= set(zip(full[0], full[1]))
    assert complete > 150


def test_five_stars_suffice_and_their_mirror_image_never_does(sky, index):
    """Four pattern stars and one confirming star identify a narrow field when the centroids are
    good (the pattern's own fit carries the evidence, module step 6); the same stars seen through
    a camera with a flipped axis have the true edge ratios but must never give an attitude."""
    rng = np.random.default_rng(16)
    index_row = {int(row): k for k, row in enumerate(index.catalog_rows)}
    patterns = set(map(tuple, np.sort(index.patterns, axis=1).tolist()))
    scored = solved = 0
    while scored < 30:
        truth = Rotation.random(random_state=rng.integers(2**31))
        xy, rows = simulate_stars(CAMERA, truth, sky, rng, vmag_limit=9.0, px_sigma=0.05, mag_sigma=0.0)
        xy, rows = xy[:5], rows[:5]
        in_index = sorted(index_row[r] for r in rows.tolist() if r in index_row)
        if len(xy) < 5 or not any(quad in patterns for quad in itertools.combinations(in_index, 4)):
            continue  # no pattern of these stars in the index: nothing to identify them by
        scored += 1
        cov = np.tile(np.eye(2) * 0.05**2, (5, 1, 1))
        try:
            solution = solve_stars(xy, cov, CAMERA.shape, index=index, fov_deg=2.0, fov_tolerance=0.1)
        except NoSolutionError:
            pass
        else:
            assert corner_error_px(CAMERA, solution.attitude(), truth) < 2.0
            solved += 1
        mirrored = np.column_stack([CAMERA.width_px - 1 - xy[:, 0], xy[:, 1]])
        with pytest.raises(NoSolutionError):
            solve_stars(mirrored, cov, CAMERA.shape, index=index, fov_deg=2.0, fov_tolerance=0.1)
    assert solved >= 0.95 * scored


def test_solve_offers_only_narrow_indexes_built_with_this_versions_options(sky, tmp_path):
    from opnav.image.starid_index import NARROW_PATTERN_SIZE_FRACTION, NARROW_STARS_PER_FIELD, cached_narrow_indexes

    # small indexes (wide levels, bright stars): only the options that name an index as narrow matter here
    common = dict(cache_dir=tmp_path, fov_min_deg=8.0, fov_max_deg=10.0, vmag_limit=6.8,
                  pattern_stars_per_fov=NARROW_STARS_PER_FIELD)
    load_or_build_index(sky, selection="fields", pattern_size_fraction=0.7, **common)  # an earlier version's
    load_or_build_index(sky, selection="density", pattern_size_fraction=NARROW_PATTERN_SIZE_FRACTION, **common)
    assert cached_narrow_indexes(sky, tmp_path) == []
    current = load_or_build_index(sky, selection="fields", pattern_size_fraction=NARROW_PATTERN_SIZE_FRACTION,
                                  **common)
    ((low, high, path),) = cached_narrow_indexes(sky, tmp_path)
    assert PatternIndex.load(path).options == current.options
    assert high == pytest.approx(10.0)
