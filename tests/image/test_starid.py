"""Star identification: pattern index, lost-in-space, tracking, plate solving of synthetic frames."""

import io

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from opnav.camera import Camera
from opnav.catalog import load_catalog, synthetic_catalog
from opnav.errors import FrameError, InputError, NoSolutionError
from opnav.image.starid import CatalogTree, bearings, identify, solve_image, track
from opnav.image.starid_index import (
    PatternIndex,
    build_index,
    load_or_build_index,
    vmag_limit_for_density,
)

CAMERA = Camera.from_fov(20.0, 640, 480)
VMAG_LIMIT = 6.5


@pytest.fixture(scope="module")
def sky():
    return synthetic_catalog(8000, rng=np.random.default_rng(1), vmag_range=(1.0, 7.0))


@pytest.fixture(scope="module")
def index(sky):
    return build_index(sky, fov_min_deg=13.0, fov_max_deg=24.0, vmag_limit=VMAG_LIMIT)


def simulate_stars(camera, R_icrf_cam, catalog, rng, *, vmag_limit, px_sigma=0.3, mag_sigma=0.3, n_false=0):
    """Centroids (brightest first) of catalog stars in view plus false stars, and the true catalog rows (-1 false)."""
    v_cam = R_icrf_cam.inv().apply(np.array(catalog.unit_vectors()))
    xy = camera.project(v_cam)
    rows = np.flatnonzero(camera.in_frame(xy) & (v_cam[:, 2] > 0))
    mag = catalog.vmag[rows] + rng.normal(0.0, mag_sigma, len(rows))
    seen = mag <= vmag_limit
    rows, mag = rows[seen], mag[seen]
    xy = xy[rows] + rng.normal(0.0, px_sigma, (len(rows), 2))
    xy = np.vstack([xy, rng.uniform([0.0, 0.0], [camera.width_px - 1, camera.height_px - 1], (n_false, 2))])
    mag = np.r_[mag, rng.uniform(mag.min(initial=3.0), vmag_limit, n_false)]
    rows = np.r_[rows, -np.ones(n_false, int)]
    order = np.argsort(mag, kind="stable")
    return xy[order], rows[order]


def corner_error_px(camera, R_est, R_true):
    """Largest displacement (px) of the detector corners between two attitudes."""
    corners = np.array([[0.0, 0.0], [camera.width_px - 1, 0.0], [0.0, camera.height_px - 1], [camera.width_px - 1, camera.height_px - 1]])
    moved = camera.project(R_est.inv().apply(R_true.apply(camera.unproject(corners))))
    return float(np.max(np.linalg.norm(moved - corners, axis=1)))


def render_stars(camera, R_icrf_cam, catalog, rng, *, vmag_limit, psf="gauss", width_px=1.2, background_e=200.0,
                 read_noise_e=10.0, full_well_e=60000.0):
    """A frame (ADU, bias 100, gain 1) of catalog stars; the faintest (vmag_limit) has a peak ~12 sigma."""
    v_cam = R_icrf_cam.inv().apply(np.array(catalog.unit_vectors()))
    xy = camera.project(v_cam)
    rows = np.flatnonzero(camera.in_frame(xy, margin_px=-3.0) & (v_cam[:, 2] > 0) & (catalog.vmag <= vmag_limit + 0.5))
    flux = 3000.0 * 10.0 ** (-0.4 * (catalog.vmag[rows] - vmag_limit))
    signal = np.full(camera.shape, background_e)
    yy, xx = np.mgrid[-10:11, -10:11]
    for (x, y), f in zip(xy[rows], flux):
        cx, cy = round(x), round(y)
        r2 = (xx + cx - x) ** 2 + (yy + cy - y) ** 2
        if psf == "gauss":
            profile = np.exp(-0.5 * r2 / width_px**2)
        else:  # Moffat, beta = 2.5: broad wings like real optics
            profile = (1.0 + r2 / (1.6 * width_px) ** 2) ** -2.5
        stamp = f * profile / profile.sum()
        r0, c0 = cy - 10, cx - 10
        rs, cs = slice(max(r0, 0), min(r0 + 21, camera.height_px)), slice(max(c0, 0), min(c0 + 21, camera.width_px))
        signal[rs, cs] += stamp[rs.start - r0 : rs.stop - r0, cs.start - c0 : cs.stop - c0]
    electrons = rng.poisson(signal) + rng.normal(0.0, read_noise_e, signal.shape)
    return np.clip(electrons, 0.0, full_well_e) + 100.0


def to_jpeg(image, quality=85):
    """Square-root stretch to 8 bits and a JPEG round trip, as a consumer camera would save it."""
    level = np.median(image)
    noise = 1.4826 * np.median(np.abs(image - level))
    stretched = np.clip((image - level + 3.0 * noise) / (60.0 * noise), 0.0, 1.0) ** 0.5
    buffer = io.BytesIO()
    Image.fromarray((255.0 * stretched).astype(np.uint8)).save(buffer, format="JPEG", quality=quality)
    return np.asarray(Image.open(io.BytesIO(buffer.getvalue())), dtype=float)


# ---- lost in space -------------------------------------------------------------------------


def test_identify_random_attitudes_with_false_stars(sky, index):
    rng = np.random.default_rng(7)
    correct = wrong = 0
    for _ in range(60):
        truth = Rotation.random(random_state=rng.integers(2**31))
        xy, rows = simulate_stars(CAMERA, truth, sky, rng, vmag_limit=VMAG_LIMIT, n_false=int(rng.integers(0, 6)))
        try:
            found = identify(bearings(xy, CAMERA), index)
        except NoSolutionError:
            continue
        if corner_error_px(CAMERA, found.R_icrf_cam, truth) < 2.0:
            correct += 1
            assert np.mean(rows[found.pairs[:, 0]] == found.pairs[:, 1]) > 0.9
        else:
            wrong += 1
    assert wrong == 0
    assert correct >= 58


def test_identify_covariance_is_consistent(sky, index):
    """NEES of the lost-in-space attitude (given the true bearing noise) is inside the 95% chi2 band."""
    rng = np.random.default_rng(8)
    px_sigma = 0.3
    nees = []
    while len(nees) < 40:
        truth = Rotation.random(random_state=rng.integers(2**31))
        xy, _ = simulate_stars(CAMERA, truth, sky, rng, vmag_limit=VMAG_LIMIT, px_sigma=px_sigma, mag_sigma=0.0)
        try:
            found = identify(bearings(xy, CAMERA), index, sigma_rad=px_sigma / CAMERA.focal_length_px)
        except NoSolutionError:
            continue
        error = (found.R_icrf_cam.inv() * truth).as_rotvec()
        nees.append(error @ np.linalg.solve(found.cov_rad2, error))
    low, high = chi2.ppf([0.025, 0.975], 3 * len(nees)) / len(nees)
    assert low < np.mean(nees) < high


def test_identify_fits_an_unknown_focal_length(sky, index):
    rng = np.random.default_rng(9)
    truth = Rotation.random(random_state=10)
    xy, _ = simulate_stars(CAMERA, truth, sky, rng, vmag_limit=VMAG_LIMIT, n_false=2)
    assumed = CAMERA.replace(focal_length_mm=CAMERA.focal_length_mm * 1.08)
    found = identify(bearings(xy, assumed), index, fov_tolerance=0.1)
    assert abs(found.focal_scale - 1.0 / 1.08) < 1e-3
    assert corner_error_px(CAMERA, found.R_icrf_cam, truth) < 2.0
    with pytest.raises(NoSolutionError):
        identify(bearings(xy, assumed), index, fov_tolerance=0.0)


def test_random_points_are_never_identified(index):
    rng = np.random.default_rng(11)
    for _ in range(20):
        xy = rng.uniform([0.0, 0.0], [639.0, 479.0], (30, 2))
        with pytest.raises(NoSolutionError):
            identify(bearings(xy, CAMERA), index, fov_tolerance=0.1)


def test_too_few_stars_and_bad_bearings(index):
    with pytest.raises(NoSolutionError, match="at least 4"):
        identify(bearings(np.array([[10.0, 10.0], [300.0, 200.0], [500.0, 400.0]]), CAMERA), index)
    with pytest.raises(InputError, match="shape"):
        identify(np.ones((5, 2)), index)
    with pytest.raises(InputError, match="NaN"):
        bearings(np.array([[np.nan, 1.0]]), CAMERA)
    with pytest.raises(InputError, match="fov_tolerance"):
        identify(bearings(np.ones((5, 2)), CAMERA), index, fov_tolerance=2.0)


def test_index_round_trip_and_cache(sky, index, tmp_path):
    path = tmp_path / "index.npz"
    index.save(path)
    loaded = PatternIndex.load(path)
    assert loaded.options == index.options and loaded.catalog_digest == index.catalog_digest
    np.testing.assert_array_equal(loaded.keys, index.keys)
    np.testing.assert_array_equal(loaded.patterns, index.patterns)
    options = {"fov_min_deg": 18.0, "fov_max_deg": 22.0, "vmag_limit": 6.0}
    first = load_or_build_index(sky, cache_dir=tmp_path, **options)
    again = load_or_build_index(sky, cache_dir=tmp_path, **options)
    np.testing.assert_array_equal(first.keys, again.keys)
    assert len(list(tmp_path.glob("starid-*"))) == 1
    load_or_build_index(sky.subset(np.arange(len(sky) - 1)), cache_dir=tmp_path, **options)
    load_or_build_index(sky, cache_dir=tmp_path, **{**options, "vmag_limit": 6.2})
    assert len(list(tmp_path.glob("starid-*"))) == 3
    # a cache entry is a directory of memory-mapped arrays: the same index, loaded without a copy
    (entry,) = [path for path in tmp_path.glob("starid-*") if PatternIndex.load(path).checksum() == first.checksum()]
    assert entry.is_dir()
    mapped = PatternIndex.load(entry)
    assert isinstance(mapped.patterns.base, np.memmap) or isinstance(mapped.patterns.base.base, np.memmap)
    assert mapped.checksum() == first.checksum()


def test_vmag_limit_gives_the_requested_density(sky):
    limit = vmag_limit_for_density(sky.vmag, 20.0, stars_per_fov=40.0)
    per_field = np.sum(sky.vmag <= limit) * 20.0**2 / (4.0 * np.pi * np.degrees(1.0) ** 2)
    assert abs(per_field - 40.0) < 0.1
    # A catalog too shallow for the request gives all its stars.
    assert vmag_limit_for_density(sky.vmag, 1.0) == sky.vmag.max()


def test_index_options_are_validated(sky):
    with pytest.raises(InputError, match="fov_min_deg"):
        build_index(sky, fov_min_deg=20.0, fov_max_deg=10.0, vmag_limit=6.0)
    with pytest.raises(InputError, match="pattern_bins"):
        build_index(sky, fov_min_deg=10.0, fov_max_deg=12.0, vmag_limit=6.0, pattern_bins=1)


# ---- tracking ------------------------------------------------------------------------------


def test_track_narrow_field_with_prior_off_by_a_tenth_of_a_degree():
    rng = np.random.default_rng(12)
    deep = synthetic_catalog(150_000, rng=rng, vmag_range=(4.0, 10.0))
    stars = CatalogTree.from_catalog(deep)
    camera = Camera.from_fov(1.5, 1024, 768)
    attempted = correct = 0
    for _ in range(40):
        truth = Rotation.random(random_state=rng.integers(2**31))
        xy, rows = simulate_stars(camera, truth, deep, rng, vmag_limit=10.0, mag_sigma=0.3, n_false=int(rng.integers(0, 2)))
        if np.sum(rows >= 0) < 3:
            continue
        axis = rng.normal(size=3)
        prior = truth * Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(0.1) * rng.uniform())
        attempted += 1
        found = track(bearings(xy, camera), stars, prior, camera, prior_sigma_rad=np.radians(0.1) / 3, rng=rng)
        correct += corner_error_px(camera, found.R_icrf_cam, truth) < 2.0
    assert attempted >= 20
    assert correct == attempted


def test_chance_of_an_agreeing_pair_separation_bounds_the_simulated_rate():
    # two stars uniform in disks of radius G (the prior gates) a separation d apart: the chance that
    # their separation is within +-2 r of d, simulated, against the tracking test's q = c r / G
    from opnav.image.starid import PAIR_SEPARATION_CHANCE

    rng = np.random.default_rng(31)
    n, gate, radius = 400_000, 1.0, 0.02

    def disk():
        r, t = gate * np.sqrt(rng.random(n)), rng.uniform(0.0, 2.0 * np.pi, n)
        return np.column_stack([r * np.cos(t), r * np.sin(t)])

    rates = []
    for d in (0.3, 0.5, 0.7, 1.0, 2.0, 5.0):
        separation = np.hypot(*(disk() - disk() - [d, 0.0]).T)
        rates.append(np.mean(np.abs(separation - d) <= 2.0 * radius))
    q = PAIR_SEPARATION_CHANCE * radius / gate
    assert max(rates) <= q  # the bound holds for every separation, overlapping gates included
    assert rates[-1] >= 0.75 * q  # and is within 1.25x of the far-pair rate (not vacuous)


def test_track_credits_the_hypothesis_pair_in_a_sparse_gate():
    # 3 catalog stars and a false one, the prior gate holding a star or two a bearing: the two
    # hypothesis stars' agreeing separation is itself unlikely by chance, so the third match suffices
    from opnav.image.starid import _chance_hypotheses

    rng = np.random.default_rng(14)
    deep = synthetic_catalog(150_000, rng=rng, vmag_range=(4.0, 10.0))
    stars = CatalogTree.from_catalog(deep)
    camera = Camera.from_fov(1.5, 1024, 768)
    prior_sigma = np.radians(0.1) / 3
    tried = 0
    for _ in range(200):
        truth = Rotation.random(random_state=rng.integers(2**31))
        xy, rows = simulate_stars(camera, truth, deep, rng, vmag_limit=10.0, px_sigma=0.1)
        if len(xy) < 3:
            continue
        xy = np.vstack([rng.uniform([0, 0], [1023, 767], (1, 2)), xy[:3]])  # a false source first
        b = bearings(xy, camera)
        found = track(b, stars, truth, camera, prior_sigma_rad=prior_sigma, p_false_max=0.5, rng=rng)
        assert corner_error_px(camera, found.R_icrf_cam, truth) < 2.0
        assert len(found.pairs) == 3
        radius, gate = 2.0 * camera.pixel_scale_rad, 4.3 * prior_sigma + 2.0 * camera.pixel_scale_rad
        c_prior = truth.inv().apply(stars.vectors)
        in_gate = (b @ c_prior.T) >= np.cos(gate)
        expected = _chance_hypotheses(in_gate, radius, gate)
        p_single = np.mean(in_gate.sum(axis=1)) * (1 - np.cos(radius)) / (1 - np.cos(gate))
        tail = 1.0 - (1.0 - p_single) ** 2  # P[Binomial(2, p) >= 1]: 4 stars counted, 2 fixed, 1 more matched
        np.testing.assert_allclose(found.p_false, expected * tail, rtol=1e-9)
        tried += 1
        if tried == 5:
            break
    assert tried == 5


def test_track_refuses_a_prior_far_off():
    rng = np.random.default_rng(13)
    deep = synthetic_catalog(150_000, rng=rng, vmag_range=(4.0, 10.0))
    stars = CatalogTree.from_catalog(deep)
    camera = Camera.from_fov(1.5, 1024, 768)
    for _ in range(10):
        truth = Rotation.random(random_state=rng.integers(2**31))
        xy, _ = simulate_stars(camera, truth, deep, rng, vmag_limit=10.0)
        prior = truth * Rotation.from_rotvec([np.radians(2.0), 0.0, 0.0])
        with pytest.raises(NoSolutionError):
            track(bearings(xy, camera), stars, prior, camera, prior_sigma_rad=np.radians(0.1) / 3, rng=rng)


# ---- frames --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "psf, hot_pixels, blob, jpeg, fov_error",
    [
        ("gauss", False, False, False, 0.0),
        ("moffat", True, True, False, 0.07),
        ("moffat", True, False, True, -0.08),
    ],
)
def test_solve_degraded_frames(sky, index, psf, hot_pixels, blob, jpeg, fov_error):
    rng = np.random.default_rng(14)
    truth = Rotation.random(random_state=15)
    image = render_stars(CAMERA, truth, sky, rng, vmag_limit=VMAG_LIMIT, psf=psf)
    if hot_pixels:
        image[rng.integers(0, 480, 40), rng.integers(0, 640, 40)] = 60000.0
    if blob:  # an extended bright object (a planet or a reflection), 25 px across
        yy, xx = np.mgrid[0:480, 0:640]
        image += 20000.0 * np.exp(-0.5 * ((xx - 200.0) ** 2 + (yy - 300.0) ** 2) / 12.0**2)
    if jpeg:
        image = to_jpeg(image)
    solved = solve_image(image, index=index, fov_deg=20.0 * (1.0 + fov_error), fov_tolerance=0.1)
    assert corner_error_px(CAMERA, solved.identification.R_icrf_cam, truth) < 2.0
    assert abs(np.degrees(solved.camera.fov_x_rad) - 20.0) < 0.05


def test_solve_without_any_fov_guess(sky, index):
    rng = np.random.default_rng(16)
    truth = Rotation.random(random_state=17)
    image = render_stars(CAMERA, truth, sky, rng, vmag_limit=VMAG_LIMIT)
    solved = solve_image(image, index=index)
    assert corner_error_px(CAMERA, solved.identification.R_icrf_cam, truth) < 2.0


def test_bad_frames_give_an_error_never_an_attitude(sky, index):
    rng = np.random.default_rng(18)
    with pytest.raises(FrameError):
        solve_image(np.zeros((480, 640)), index=index, fov_deg=20.0)
    with pytest.raises(FrameError):
        solve_image(np.full((480, 640), 65535.0), index=index, fov_deg=20.0, saturation_adu=65535.0)
    with pytest.raises(FrameError):
        solve_image(np.full((480, 640), np.nan), index=index, fov_deg=20.0)
    with pytest.raises(NoSolutionError):  # noise only
        solve_image(100.0 + rng.normal(0.0, 10.0, (480, 640)), index=index, fov_deg=20.0)
    pointing = Rotation.random(random_state=19)
    _, in_view = simulate_stars(CAMERA, pointing, sky, rng, vmag_limit=VMAG_LIMIT)
    few = render_stars(CAMERA, pointing, sky.subset(in_view[:2]), rng, vmag_limit=VMAG_LIMIT)
    with pytest.raises(NoSolutionError, match="only 2"):
        solve_image(few, index=index, fov_deg=20.0)
    with pytest.raises(InputError, match="2-D"):
        solve_image(np.zeros((480, 640, 3)), index=index, fov_deg=20.0)


def test_catalog_tree_is_built_once_per_catalog_and_limit():
    catalog = load_catalog()
    first = CatalogTree.from_catalog(catalog, vmag_limit=9.0)
    assert CatalogTree.from_catalog(catalog, vmag_limit=9.0) is first
    other = CatalogTree.from_catalog(catalog, vmag_limit=8.0)
    assert other is not first and other.vmag.max() <= 8.0 < first.vmag.max()


def test_extraction_keeps_honest_covariances_beside_a_clipped_hot_pixel_block():
    """A detector whose full well (18 000 ADU) is below its 16-bit file's range: a bloomed hot-pixel
    pair is a flat 2 x 6 block no PSF fits. The stars' centroids and covariances must not suffer
    from it (the frame's noise was fitted with it and every sigma came out 10-30 px)."""
    from scipy.spatial import cKDTree
    from scipy.special import ndtr

    from opnav.image.extract import extract_stars

    rng = np.random.default_rng(31)
    shape = (300, 400)
    xy = rng.uniform(15, [shape[1] - 15, shape[0] - 15], (25, 2))
    close = {j for i, j in cKDTree(xy).query_pairs(10.0)}
    xy = np.delete(xy, sorted(close), axis=0)
    flux = 10 ** rng.uniform(2.5, 3.5, len(xy))
    cols, rows = np.arange(shape[1]), np.arange(shape[0])
    signal = np.full(shape, 2.0)
    for (x, y), f in zip(xy, flux):
        ex = ndtr((cols + 0.5 - x) / 1.2) - ndtr((cols - 0.5 - x) / 1.2)
        ey = ndtr((rows + 0.5 - y) / 1.2) - ndtr((rows - 0.5 - y) / 1.2)
        signal += f * np.outer(ey, ex)
    signal[140:146, 200:202] = 1e6  # the hot pair, clipped at the full well below
    signal[[139, 146], 200:202] = 4000.0  # the ends of its bloom
    electrons = np.minimum(rng.poisson(signal), 18000.0) + rng.normal(0.0, 8.0, shape)
    found, cov = extract_stars(100.0 + electrons, saturation_adu=65535.0)
    dist, idx = cKDTree(xy).query(found)
    stars = dist < 2.0
    assert stars.sum() == len(xy), "every star extracted"
    error = found[stars] - xy[idx[stars]]
    z2 = np.einsum("ni,nij,nj->n", error, np.linalg.inv(cov[stars]), error)
    # reported covariances match the errors: chi^2 of 2 dof per star, and none inflated
    assert z2.sum() < chi2.ppf(0.999, 2 * stars.sum()) and z2.sum() > chi2.ppf(0.001, 2 * stars.sum())
    assert np.median(np.sqrt(np.trace(cov[stars], axis1=1, axis2=2) / 2.0)) < 0.3


def test_extraction_orders_sources_by_detection_snr_not_flux():
    """Under a sky whose brightness (and noise) changes across the frame, a star of more flux on the
    bright sky is less reliable than a fainter one on the dark sky: the list starts from the one of
    higher signal-to-noise ratio, and ``extract_stars`` returns the rows of ``extract_sources``."""
    from scipy.special import ndtr

    from opnav.image.extract import extract_sources, extract_stars

    rng = np.random.default_rng(32)
    shape = (200, 400)
    xy = np.array([[100.0, 60.0], [300.0, 60.0], [100.0, 140.0], [300.0, 140.0]])
    flux = np.array([6000.0, 2500.0, 4000.0, 1500.0])  # left two on the bright sky, right two on the dark
    cols, rows = np.arange(shape[1]), np.arange(shape[0])
    signal = np.where(cols < 200, 4000.0, 25.0)[None, :] * np.ones(shape)
    for (x, y), f in zip(xy, flux):
        ex = ndtr((cols + 0.5 - x) / 1.2) - ndtr((cols - 0.5 - x) / 1.2)
        ey = ndtr((rows + 0.5 - y) / 1.2) - ndtr((rows - 0.5 - y) / 1.2)
        signal += f * np.outer(ey, ex)
    image = rng.poisson(signal) + rng.normal(0.0, 5.0, shape)
    found = extract_sources(image)
    assert len(found) == 4
    assert np.all(np.diff(found.snr) <= 0), "highest SNR first"
    nearest = np.argmin(np.linalg.norm(found.xy[:, None] - xy[None], axis=2), axis=1)
    np.testing.assert_array_equal(nearest, [1, 3, 0, 2])  # the dark-sky stars first, though fainter
    assert np.all(np.diff(found.flux[[0, 2]]) > 0), "not flux order"
    xy_only, cov_only = extract_stars(image)
    np.testing.assert_array_equal(xy_only, found.xy)
    np.testing.assert_array_equal(cov_only, found.cov)


def test_a_star_on_a_bloom_trail_halo_is_extracted():
    # a saturated planet's bloom trail and its halo make one extended detection; a star beside
    # it joins that component and would be lost with it (S1 frames beside Mars)
    from scipy.special import ndtr

    from opnav.image.extract import extract_sources

    rng = np.random.default_rng(5)
    shape = (256, 256)
    cols = np.arange(shape[1], dtype=float)
    rows = np.arange(shape[0], dtype=float)
    # a clipped column 16 px wide (its edges blurred by the PSF) in a broad scattered-light halo
    # that joins the star to it above the detection threshold
    edge = np.maximum(np.abs(cols - 128.0) - 8.0, 0.0)
    halo = 1e6 * np.exp(-0.5 * edge**2) + 400.0 * np.exp(-edge / 12.0)
    expected = 100.0 + np.tile(halo, (shape[0], 1))
    star = np.array([145.3, 80.6])

    def pixel_gaussian(coord, centre):
        return ndtr((coord + 0.5 - centre) / 1.0) - ndtr((coord - 0.5 - centre) / 1.0)

    with_star = expected + 60000.0 * np.outer(pixel_gaussian(rows, star[1]), pixel_gaussian(cols, star[0]))
    saturation = 30000.0
    for frame, has_star in ((with_star, True), (expected, False)):
        image = np.minimum(rng.poisson(frame) + rng.normal(0.0, 5.0, shape), saturation)
        found = extract_sources(image, saturation_adu=saturation)
        near = np.hypot(*(found.xy - star).T) < 0.2 if len(found.xy) else np.zeros(0, bool)
        assert near.any() == has_star
        # nothing on the trail's edges passes for a star
        assert np.all((np.abs(found.xy[:, 0] - 128.0) > 20.0) | near)


def test_running_statistics_equal_scipy_filters_at_the_pixels_asked():
    # _embedded_point_sources evaluates the 9-px running median and 5-px running maximum only where
    # its tests read them: at those pixels the values must be scipy.ndimage's (edges repeated), ties
    # and the array's edges included
    from scipy import ndimage

    from opnav.image.extract import _running_max, _running_median

    rng = np.random.default_rng(11)
    values = rng.normal(0.0, 1.0, (40, 23))
    values[::3] = np.round(values[::3])  # ties
    rows, cols = np.nonzero(rng.random(values.shape) < 0.4)
    for half in (2, 4):
        median = ndimage.median_filter(values, size=2 * half + 1, mode="nearest")
        assert np.array_equal(_running_median(values, rows, cols, half), median[rows, cols])
        maximum = ndimage.maximum_filter(values, size=2 * half + 1, mode="nearest")
        assert np.array_equal(_running_max(values, rows, cols, half), maximum[rows, cols])
