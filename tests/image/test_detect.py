"""Detection: completeness, position of seeds, rejection of hot pixels and tracks, flags, bad frames."""

import math

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.special import ndtr

from opnav.errors import FrameError, InputError
from opnav.image.detect import (
    FLAG_BLENDED,
    FLAG_EXTENDED,
    FLAG_INVALID,
    FLAG_SATURATED,
    DetectOptions,
    detect,
    estimate_background,
)

BACKGROUND = 100.0
READ_NOISE = 5.0


def _stars(shape, xy, flux, sigma=1.0):
    img = np.zeros(shape)
    cols, rows = np.arange(shape[1]), np.arange(shape[0])
    for (x, y), f in zip(xy, np.broadcast_to(flux, (len(xy),))):
        ex = ndtr((cols + 0.5 - x) / sigma) - ndtr((cols - 0.5 - x) / sigma)
        ey = ndtr((rows + 0.5 - y) / sigma) - ndtr((rows - 0.5 - y) / sigma)
        img += f * np.outer(ey, ex)
    return img


def _noisy(rng, expected):
    return rng.poisson(expected + BACKGROUND) + rng.normal(0.0, READ_NOISE, expected.shape)


def _field(rng, n=50, shape=(256, 256)):
    xy = rng.uniform(12, shape[0] - 12, (n, 2))
    # keep stars apart so each is one source
    tree = cKDTree(xy)
    close = {j for i, j in tree.query_pairs(6.0)}
    xy = np.delete(xy, sorted(close), axis=0)
    flux = 10 ** rng.uniform(3.0, 4.5, len(xy))
    return xy, flux


def test_finds_every_star_and_rejects_hot_pixels_and_tracks():
    rng = np.random.default_rng(1)
    xy, flux = _field(rng)
    img = _noisy(rng, _stars((256, 256), xy, flux))
    hot = rng.integers(5, 250, (8, 2))
    img[hot[:, 1], hot[:, 0]] += 4000.0
    img[200, 30:42] += 3000.0  # cosmic-ray track, one pixel wide
    det = detect(img)
    dist, idx = cKDTree(xy).query(det.xy)
    assert np.all(dist < 0.5), "every detection is a real star, within 0.5 px"
    assert len(set(idx)) == len(xy), "every star found once"
    assert det.n_rejected >= 9
    assert np.all(np.diff(det.flux) <= 0), "brightest first"


def test_background_and_noise_estimates():
    rng = np.random.default_rng(2)
    xy, flux = _field(rng)
    img = _noisy(rng, _stars((256, 256), xy, flux) + 0.05 * np.arange(256)[None, :])
    bg = estimate_background(img, tile_px=32)
    expected_level = BACKGROUND + 0.05 * np.arange(256)[None, :]
    sigma = np.sqrt(expected_level + READ_NOISE**2)
    # tile medians of 1024 pixels: standard error ~ 1.25 sigma / 32 ~ 0.4 ADU; allow a 1 ADU gradient residual
    assert np.median(np.abs(bg.level - expected_level)) < 1.0
    assert np.median(np.abs(bg.noise / sigma - 1.0)) < 0.05


def test_noise_only_frame_has_no_false_detections():
    rng = np.random.default_rng(3)
    det = detect(_noisy(rng, np.zeros((256, 256))))
    # 5-sigma threshold on the matched-filtered frame: ~1e-7 per independent sample
    assert len(det) == 0


def test_close_pair_is_deblended_and_flagged():
    rng = np.random.default_rng(4)
    xy = np.array([[30.0, 30.0], [33.0, 30.5]])
    img = _noisy(rng, _stars((64, 64), xy, [20000.0, 15000.0]))
    det = detect(img)
    assert len(det) == 2
    dist, idx = cKDTree(xy).query(det.xy)
    assert set(idx) == {0, 1} and np.all(dist < 0.5)
    assert np.all(det.flags & FLAG_BLENDED)


def test_isolated_star_is_not_split_by_noise():
    rng = np.random.default_rng(5)
    img = _noisy(rng, _stars((64, 64), np.array([[31.3, 30.7]]), [1e5], sigma=2.0))
    det = detect(img)
    assert len(det) == 1
    assert not det.flags[0] & FLAG_BLENDED


def test_saturated_star_is_flagged():
    rng = np.random.default_rng(6)
    img = _noisy(rng, _stars((64, 64), np.array([[20.0, 20.0], [45.0, 40.0]]), [3e5, 5e3]))
    img = np.minimum(img, 10000.0)
    det = detect(img, saturation_adu=10000.0)
    flags = det.flags[np.argsort(det.xy[:, 0])]
    assert flags[0] & FLAG_SATURATED and not flags[1] & FLAG_SATURATED


def test_extended_body_is_one_flagged_source():
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[:128, :128]
    disk = 500.0 * ((xx - 64.2) ** 2 + (yy - 60.7) ** 2 < 20.0**2)
    det = detect(_noisy(rng, disk))
    extended = det.flags & FLAG_EXTENDED > 0
    assert extended.sum() == 1
    np.testing.assert_allclose(det.xy[extended][0], [64.2, 60.7], atol=0.1)


def test_invalid_pixels_flag_their_source():
    rng = np.random.default_rng(8)
    img = _noisy(rng, _stars((64, 64), np.array([[20.0, 20.0], [45.0, 40.0]]), [2e4, 2e4]))
    invalid = np.zeros(img.shape, bool)
    invalid[20, 21] = True
    img[invalid] = np.median(img)
    det = detect(img, invalid=invalid)
    near = np.hypot(*(det.xy - [20.0, 20.0]).T) < 1.0
    assert near.sum() == 1 and det.flags[near][0] & FLAG_INVALID
    assert not np.any(det.flags[~near] & FLAG_INVALID)


def test_bad_frames_raise_clear_errors():
    with pytest.raises(FrameError, match="blank"):
        detect(np.zeros((64, 64)))
    with pytest.raises(FrameError, match="saturated"):
        detect(np.full((64, 64), 65535.0) - np.eye(64), saturation_adu=65535.0 - 1.0)
    img = np.random.default_rng(9).normal(100.0, 5.0, (64, 64))
    img[3, 3] = np.nan
    with pytest.raises(FrameError, match="NaN"):
        detect(img)
    with pytest.raises(FrameError, match="2-D"):
        detect(np.zeros((4, 4, 3)))


def test_options_are_validated():
    with pytest.raises(InputError, match="threshold_sigma"):
        DetectOptions(threshold_sigma=0.0)
    with pytest.raises(InputError, match="tile_px"):
        DetectOptions(tile_px=4)


def test_robust_to_moffat_psf_and_jpeg_artefacts(tmp_path):
    from PIL import Image

    from opnav.image.io import read_image

    rng = np.random.default_rng(10)
    xy, flux = _field(rng, n=30)
    yy, xx = np.mgrid[:256, :256]
    expected = np.zeros((256, 256))
    for (x, y), f in zip(xy, flux):
        # Moffat beta = 2.5, alpha = 2 px: broad wings no Gaussian has
        profile = (1 + ((xx - x) ** 2 + (yy - y) ** 2) / 4.0) ** -2.5
        expected += f * profile / profile.sum()
    img = np.clip(_noisy(rng, expected) * 0.3, 0, 255).astype(np.uint8)
    Image.fromarray(img).save(tmp_path / "m.jpg", quality=85)
    image, meta = read_image(tmp_path / "m.jpg")
    det = detect(image, saturation_adu=meta.saturation_adu, lossy=meta.lossy)
    dist, idx = cKDTree(xy).query(det.xy)
    assert np.all(dist < 1.0), "no spurious sources from JPEG blocks or Moffat wings"
    bright = flux > 3000
    assert bright[np.unique(idx)].sum() == bright.sum(), "every bright star found"


def _numpy_background(image, tile, clip_sigma, invalid):
    """The slow path of estimate_background: numpy's nanmedian and nanstd over NaN-padded tiles."""
    import warnings

    from scipy import ndimage
    from scipy.stats import truncnorm

    h, w = image.shape
    ty, tx = -(-h // tile), -(-w // tile)
    padded = np.full((ty * tile, tx * tile), np.nan)
    padded[:h, :w] = image
    if invalid is not None:
        padded[:h, :w][invalid] = np.nan
    values = padded.reshape(ty, tile, tx, tile).swapaxes(1, 2)
    if tile >= 32:  # one pixel of each 2 x 2 block, cycling through its four positions
        i, b = np.meshgrid(np.arange(tile // 2), np.arange(tile // 2), indexing="ij")
        values = values[:, :, 2 * i + ((i + b) & 1), 2 * b + (i & 1)]
    values = values.reshape(ty, tx, -1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for _ in range(6):
            med = np.nanmedian(values, axis=-1)[..., None]
            mad = np.nanmedian(np.abs(values - med), axis=-1)[..., None] * 1.482602218505602
            clipped = np.where(np.abs(values - med) <= clip_sigma * np.maximum(mad, 1e-12), values, np.nan)
            if np.array_equal(np.isnan(clipped), np.isnan(values)):
                break
            values = clipped
        level = np.nanmedian(values, axis=-1)
        count = np.sum(~np.isnan(values), axis=-1)
        noise = np.where(count > 1, np.nanstd(values, axis=-1, ddof=1), np.nan) / np.sqrt(
            truncnorm.var(-clip_sigma, clip_sigma))
    for grid in (level, noise):
        grid[np.isnan(grid)] = np.nanmedian(grid)
    level = ndimage.median_filter(level, size=3, mode="nearest")
    noise = ndimage.median_filter(noise, size=3, mode="nearest")
    centres_y, centres_x = (np.arange(ty) + 0.5) * tile - 0.5, (np.arange(tx) + 0.5) * tile - 0.5
    rows = np.array([np.interp(np.arange(h), centres_y, level[:, j]) for j in range(tx)]).T
    level_map = np.array([np.interp(np.arange(w), centres_x, row) for row in rows])
    rows = np.array([np.interp(np.arange(h), centres_y, noise[:, j]) for j in range(tx)]).T
    noise_map = np.array([np.interp(np.arange(w), centres_x, row) for row in rows])
    return level_map, noise_map


def test_compiled_background_equals_the_numpy_path():
    # sigma clipping on each tile's sorted values (only the ends of the kept run move) gives numpy's
    # nanmedian/nanstd clipping to rounding: frames with invalid pixels, an all-invalid tile, ties,
    # a bright blob, a frame smaller than a tile
    rng = np.random.default_rng(9)
    cases = []
    image = rng.normal(100.0, 5.0, (300, 517))
    invalid = rng.random(image.shape) < 0.05
    invalid[:70, :70] = True
    cases.append((image, invalid, 64))
    blob = rng.poisson(50.0, (128, 128)).astype(float)
    blob[60:70, 60:70] += 1e4
    cases.append((blob, None, 64))
    cases.append((np.round(rng.normal(10.0, 1.0, (200, 200))), None, 64))
    cases.append((rng.normal(0.0, 1.0, (40, 50)), None, 64))
    cases.append((rng.normal(100.0, 5.0, (64, 64)), None, 64))  # one tile: a tracking crop
    for image, invalid, tile in cases:
        got = estimate_background(image, tile_px=tile, invalid=invalid)
        level, noise = _numpy_background(image, min(tile, *image.shape), 3.0, invalid)
        np.testing.assert_allclose(got.level, level, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(got.noise, noise, rtol=1e-12, atol=0.0)


def test_background_windows_and_residual_pass_equal_the_full_maps():
    # the maps are made on first use; a box of them, the level interpolated inside detection's
    # residual pass and a noise floor give the full maps' values exactly
    from opnav.image.detect import _residual

    rng = np.random.default_rng(21)
    for shape, tile in (((300, 517), 64), ((128, 128), 64), ((40, 50), 64), ((256, 192), 32)):
        image = rng.normal(100.0, 5.0, shape) + np.linspace(0.0, 40.0, shape[1])
        background = estimate_background(image, tile_px=tile)
        level, noise = background.level, background.noise
        assert level.shape == noise.shape == shape
        for rows, cols in ((slice(None), slice(None)), (slice(None, None, 4), slice(None, None, 4)),
                           (slice(7, 61), slice(shape[1] - 30, None)), (slice(3, 4), slice(0, 1))):
            box_level, box_noise = background.window(rows, cols)
            np.testing.assert_array_equal(box_level, level[rows, cols])
            np.testing.assert_array_equal(box_noise, noise[rows, cols])
        valid = rng.random(shape) > 0.1
        grid, iy, wy, ix, wx = background.level_interpolation()
        # the residual is single precision, the difference taken in double
        np.testing.assert_array_equal(_residual(image, valid, False, grid, iy, wy, ix, wx),
                                      (image - level).astype(np.float32))
        np.testing.assert_array_equal(_residual(image, valid, True, grid, iy, wy, ix, wx),
                                      np.where(valid, image - level, 0.0).astype(np.float32))
        floored = background.with_noise_floor(float(np.median(noise)))
        np.testing.assert_array_equal(floored.noise, np.maximum(noise, np.median(noise)))
        np.testing.assert_array_equal(floored.window(slice(2, 9), slice(5, 40))[1], floored.noise[2:9, 5:40])
        # the noise at pixels, and row by row inside the passes, without the map
        r, c = rng.integers(0, shape[0], 500), rng.integers(0, shape[1], 500)
        for model in (background, floored):
            np.testing.assert_array_equal(model.noise_at(r, c), model.noise[r, c])
        np.testing.assert_array_equal(floored.level, level)


def test_compiled_deblending_equals_the_map_coordinates_profiles():
    from scipy import ndimage

    from opnav.image.detect import _keep_deblended

    def reference(smooth, peaks_rc, noise_s, contrast):  # the replaced numpy/scipy version
        heights = smooth[peaks_rc[:, 0], peaks_rc[:, 1]]
        keep = np.zeros(len(peaks_rc), dtype=bool)
        keep[0] = True
        for j in range(1, len(peaks_rc)):
            kept = np.flatnonzero(keep[:j])
            n_samples = int(np.ceil(np.max(np.hypot(*(peaks_rc[kept] - peaks_rc[j]).T)))) * 4 + 2
            t = np.linspace(0.0, 1.0, n_samples)
            line = peaks_rc[j][None, None, :] + t[None, :, None] * (peaks_rc[kept] - peaks_rc[j])[:, None, :]
            profile = ndimage.map_coordinates(smooth, [line[..., 0].ravel(), line[..., 1].ravel()], order=1)
            dip = heights[j] - profile.reshape(len(kept), n_samples).min(axis=1)
            keep[j] = bool(np.all((dip > contrast * heights[j]) & (dip > 3.0 * noise_s)))
        return keep

    rng = np.random.default_rng(5)
    rows, cols = np.mgrid[0:40, 0:50]
    decided = 0
    for _ in range(60):
        n = int(rng.integers(2, 7))
        centres = rng.uniform([2, 2], [38, 48], (n, 2))
        smooth = sum(rng.uniform(20, 200) * np.exp(-((rows - y) ** 2 + (cols - x) ** 2) / (2 * rng.uniform(0.8, 2.5) ** 2))
                     for y, x in centres) + rng.normal(0.0, 1.0, rows.shape)
        smooth = smooth.astype(np.float32).astype(float)  # detection's filtered frame is single precision
        peaks = np.rint(centres).astype(np.int64)
        peaks[rng.integers(n)] = [39, 49]  # a peak on the last row and column
        peaks = peaks[np.argsort(-smooth[peaks[:, 0], peaks[:, 1]], kind="stable")]
        for contrast in (0.1, 0.3):
            expected = reference(smooth, peaks, 2.0, contrast)
            np.testing.assert_array_equal(_keep_deblended(smooth, peaks, 2.0, contrast), expected)
            decided += int(expected[1:].sum()) > 0 and not expected.all()
    assert decided > 5  # cases with peaks both kept and merged


def test_background_refuses_an_invalid_mask_of_another_shape():
    image = np.random.default_rng(2).normal(100.0, 5.0, (64, 80))
    with pytest.raises(InputError, match="shape"):
        estimate_background(image, invalid=np.zeros((64, 79), bool))
    for mask in (np.zeros((64, 79), bool), np.zeros(64 * 80, bool)):  # detection names it before reading the frame
        with pytest.raises(InputError, match="shape"):
            detect(image, invalid=mask)


def test_background_leaves_the_frame_unchanged():
    # tiles are copied into a buffer before sorting, never sorted in place
    rng = np.random.default_rng(13)
    for shape in ((128, 64), (64, 192), (128, 128), (64, 64), (100, 70)):
        image = rng.normal(100.0, 5.0, shape)
        kept = image.copy()
        estimate_background(image, tile_px=64)
        np.testing.assert_array_equal(image, kept)


def test_deviation_median_equals_the_merge_of_both_sides():
    # the bisection over the two ascending runs of deviations gives what merging them outwards gives
    from opnav.image.detect import _deviation_median

    def merged(values, lo, hi, centre):
        below = centre - values[lo:hi][values[lo:hi] < centre][::-1]
        above = values[lo:hi][values[lo:hi] >= centre] - centre
        deviations = np.sort(np.concatenate([below, above]))
        n = hi - lo
        return 0.5 * (deviations[(n - 1) // 2] + deviations[n // 2])

    rng = np.random.default_rng(14)
    for trial in range(3000):
        n = int(rng.integers(1, 60))
        if trial % 2:
            values = np.sort(rng.integers(0, int(rng.integers(1, 12)), n).astype(float))  # ties, as 8-bit frames
        else:
            values = np.sort(rng.normal(size=n))
        lo = int(rng.integers(0, n))
        hi = int(rng.integers(lo + 1, n + 1))
        centre = float(rng.choice([np.median(values[lo:hi]), values[lo] - 1.0, values[hi - 1] + 1.0, rng.normal()]))
        assert _deviation_median(values, lo, hi, centre) == merged(values, lo, hi, centre)

def test_compiled_local_maxima_equal_the_maximum_filter():
    # the seeds: "on" pixels equal to the maximum of their square (edges replicated), row-major, with ties
    from scipy import ndimage

    from opnav.image.detect import _local_maxima

    rng = np.random.default_rng(10)
    for half in (1, 2, 4):
        values = np.round(rng.normal(size=(97, 131)), 1)  # rounded: many ties
        on = rng.random(values.shape) < 0.3
        on[0, :] = on[:, -1] = True  # the edges
        values = values.astype(np.float32)  # detection's frames are single precision
        expected = np.nonzero((values == ndimage.maximum_filter(values, size=2 * half + 1, mode="nearest")) & on)
        rows, cols = _local_maxima(values, *np.nonzero(on), half)
        np.testing.assert_array_equal(rows, expected[0])
        np.testing.assert_array_equal(cols, expected[1])


def test_compiled_component_statistics_equal_opencv_and_bincount():
    # each component's box and area (OpenCV's statistics), and its saturated and invalid pixels and flux (numpy's
    # bincount over the label image), as the threshold's pass sums them
    import cv2

    from opnav.image.detect import _detection_components

    rng = np.random.default_rng(12)
    gain = 0.08
    for fraction in (0.02, 0.3, 0.6):
        shape = (150, 210)
        background = _random_background(rng, shape, floor=0.3)
        spikes = np.where(rng.random(shape) < fraction, 50.0, rng.normal(0.0, 1.0, shape))
        smooth = (np.maximum(background.noise, 1e-12) * gain * spikes).astype(np.float32)
        saturated = rng.random(shape) < 0.05
        valid = rng.random(shape) > 0.05
        resid = rng.normal(size=shape).astype(np.float32)
        for mask in (valid, None):
            correlation, n, labels, rows, cols, on_labels, got, sat, invalid, flux = _detection_components(
                smooth, background, gain, mask, 5.0, saturated, resid)
            on = smooth > 5.0 * (np.maximum(background.noise, 1e-12) * gain * correlation)
            n_cv, labels_cv, stats, _ = cv2.connectedComponentsWithStats(on.astype(np.uint8), connectivity=8,
                                                                        ltype=cv2.CV_32S)
            assert n == n_cv > 2
            np.testing.assert_array_equal(on_labels, labels[rows, cols])
            # OpenCV numbers its components in its own order: each of ours is the OpenCV one at its first pixel
            inside = np.flatnonzero(labels)
            first = np.unique(labels.ravel()[inside], return_index=True)[1]
            np.testing.assert_array_equal(got[1:], stats[labels_cv.ravel()[inside][first]])
            flat = labels.ravel()[inside]
            np.testing.assert_array_equal(sat,
                                          np.bincount(flat, weights=saturated.ravel()[inside], minlength=n)[1:] > 0)
            np.testing.assert_array_equal(flux, np.bincount(flat, weights=resid.ravel()[inside], minlength=n)[1:])
            if mask is None:
                assert not invalid.any()  # without invalid pixels the mask is not read
            else:
                np.testing.assert_array_equal(
                    invalid, np.bincount(flat, weights=~valid.ravel()[inside], minlength=n)[1:] > 0)


def test_threshold_labels_are_opencv_components_in_raster_order():
    # the union-find labelling of the threshold's pass: OpenCV's 8-connected partition, numbered in the
    # raster order of each component's first pixel, and the on pixels listed row-major
    import cv2

    from opnav.image.detect import _detection_components

    rng = np.random.default_rng(17)
    gain = 0.08
    for k, fraction in enumerate((0.0, 0.01, 0.1, 0.3, 0.5, 0.7)):
        shape = (90 + 7 * k, 120 - 5 * k)
        background = _random_background(rng, shape, floor=0.3)
        noise_s = np.maximum(background.noise, 1e-12) * gain
        # smooth in units of the filtered noise: a fraction of pixels well above a 5-sigma threshold,
        # spirals and U shapes of on pixels from the random field, the edges included
        spikes = np.where(rng.random(shape) < fraction, 50.0, rng.normal(0.0, 1.0, shape))
        smooth = (noise_s * spikes).astype(np.float32)
        none = np.zeros(shape, bool)
        correlation, n, labels, rows, cols = _detection_components(
            smooth, background, gain, None, 5.0, none, np.zeros(shape, np.float32))[:5]
        on = smooth > 5.0 * (np.maximum(background.noise, 1e-12) * gain * correlation)
        np.testing.assert_array_equal(rows, np.nonzero(on)[0])
        np.testing.assert_array_equal(cols, np.nonzero(on)[1])
        n_cv, labels_cv = cv2.connectedComponents(on.astype(np.uint8), connectivity=8, ltype=cv2.CV_32S)
        assert n == n_cv
        # the same partition: each OpenCV label maps to one of ours and back
        pairs = np.unique(np.stack([labels.ravel(), labels_cv.ravel()]), axis=1)
        assert pairs.shape[1] == n and np.array_equal(pairs[0], np.arange(n))
        first = np.unique(labels[on], return_index=True)[1]
        assert np.all(np.diff(first) > 0)  # numbered in the raster order of their first pixels


def test_one_tile_background_map_is_the_interpolations():
    # a frame of one tile (a tracking crop) skips the interpolation: the same map exactly
    from opnav.image.detect import _axis_weights, _bilinear, _interpolate

    for value in (103.25, -2.5e-3, 0.0):
        grid = np.array([[value]])
        iy, wy = _axis_weights(64, np.array([31.5]))
        ix, wx = _axis_weights(50, np.array([31.5]))
        np.testing.assert_array_equal(_bilinear(grid, (64, 50), 64),
                                      _interpolate(np.pad(grid, ((0, 1), (0, 1)), mode="edge"), iy, wy, ix, wx))


def test_compiled_subpixel_peaks_equal_the_numpy_expression():
    from opnav.image.detect import _subpixel_peak

    def reference(smooth, rows, cols):  # the replaced array version
        h, w = smooth.shape
        r, c = np.clip(rows, 1, h - 2), np.clip(cols, 1, w - 2)
        out = []
        for lo, mid, hi in ((smooth[r, c - 1], smooth[r, c], smooth[r, c + 1]),
                            (smooth[r - 1, c], smooth[r, c], smooth[r + 1, c])):
            curvature = lo - 2.0 * mid + hi
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.where(curvature < 0, 0.5 * (lo - hi) / curvature, 0.0)
            out.append(np.clip(step, -0.5, 0.5))
        return np.stack([cols + out[0], rows + out[1]], -1)

    rng = np.random.default_rng(15)
    smooth = np.round(rng.normal(size=(40, 50)), 1).astype(np.float32).astype(float)  # ties: flat profiles
    rows, cols = rng.integers(0, 40, 300), rng.integers(0, 50, 300)
    rows[:4], cols[:4] = [0, 39, 5, 0], [0, 49, 0, 20]  # the edges
    np.testing.assert_array_equal(_subpixel_peak(smooth, rows, cols), reference(smooth, rows, cols))
    assert _subpixel_peak(smooth, rows[:0], cols[:0]).shape == (0, 2)


def _random_background(rng, shape, tile=16, floor=0.0):
    """A background whose noise tiles vary (zeros among them: the 1e-12 floor of the passes)."""
    from opnav.image.detect import Background

    grid = (-(-shape[0] // tile), -(-shape[1] // tile))
    noise = rng.uniform(0.0, 2.0, grid)
    noise[0, 0] = 0.0
    return Background(level_tiles=np.zeros(grid), noise_tiles=noise, shape=tuple(shape), tile_px=tile,
                      noise_floor=floor)


def _correlation_factor(smooth, background, gain, valid):
    from opnav.image.detect import _detection_components

    return _detection_components(smooth, background, gain, valid, 5.0, np.zeros(smooth.shape, bool),
                                 np.zeros(smooth.shape, np.float32))[0]


def test_compiled_correlation_factor_equals_the_numpy_expression():
    from opnav.image.detect import _correlation_step

    def reference(smooth, noise_s, valid):  # the replaced array version
        sample = (smooth / noise_s)[valid]
        if sample.size < 100:
            return 1.0
        centre = np.median(sample)
        return max(1.0, float(1.482602218505602 * np.median(np.abs(sample - centre))))

    rng = np.random.default_rng(16)
    gain = 0.08
    for k in range(200):
        h, w = rng.integers(8, 60, 2)
        smooth = rng.normal(0.0, rng.uniform(0.5, 3.0), (4 * h + k % 4, 4 * w + k % 3)).astype(np.float32)
        if k % 3 == 0:
            smooth = np.round(smooth, 1)  # ties
        background = _random_background(rng, smooth.shape, floor=0.3 if k % 5 == 0 else 0.0)
        noise_s = np.maximum(background.noise, 1e-12) * gain
        valid = rng.random(smooth.shape) < rng.uniform(0.3, 1.0)
        # every 4th pixel of each axis, as detect() samples the frame
        expected = reference(smooth[::4, ::4], noise_s[::4, ::4], valid[::4, ::4])
        assert _correlation_factor(smooth, background, gain, valid) == expected
        everything = reference(smooth[::4, ::4], noise_s[::4, ::4], np.ones(valid[::4, ::4].shape, bool))
        assert _correlation_factor(smooth, background, gain, None) == everything
    # beyond 0.26 MP an odd step keeps ~16,384 pixels: every 5th of a 640 x 480 frame, every 9th at 1 MP and of a
    # 1100 x 1100 frame, every 19th at 5 MP
    assert tuple(_correlation_step(shape) for shape in ((512, 512), (480, 640), (1024, 1024), (1100, 1100),
                                                        (2240, 2240))) == (4, 5, 9, 9, 19)
    smooth = rng.normal(0.0, 1.3, (1100, 1100)).astype(np.float32)
    background = _random_background(rng, smooth.shape, tile=64)
    noise_s = np.maximum(background.noise, 1e-12) * gain
    valid = rng.random(smooth.shape) < 0.9
    assert _correlation_factor(smooth, background, gain, valid) == reference(smooth[::9, ::9], noise_s[::9, ::9],
                                                                             valid[::9, ::9])


def test_compiled_threshold_equals_the_numpy_expression():
    from opnav.image.detect import _detection_components

    rng = np.random.default_rng(13)
    smooth = rng.normal(size=(80, 90)).astype(np.float32)
    gain = 0.07957747154594767
    for floor in (0.0, 0.2):
        background = _random_background(rng, smooth.shape, floor=floor)
        for scale in (1.0, 1.37, 3.0):  # correlations of 1 and above (the candidates at 1 are a superset)
            data = (smooth * scale).astype(np.float32)
            correlation, _, labels, rows, cols = _detection_components(
                data, background, gain, None, 4.0, np.zeros(data.shape, bool), np.zeros(data.shape, np.float32))[:5]
            expected = data > 4.0 * (np.maximum(background.noise, 1e-12) * gain * correlation)
            np.testing.assert_array_equal(labels > 0, expected)
            np.testing.assert_array_equal(np.stack([rows, cols]), np.nonzero(expected))


def test_detection_snr_is_the_matched_filter_snr():
    # A Gaussian star of sigma 1 px (1 + 1/12 px^2 once integrated over pixels) and flux F over white
    # noise n, filtered by the detection Gaussian of sigma 1 px: the filtered peak is
    # F / (2 pi (1 + 1/12 + 1)) and its noise n / (2 sqrt(pi)), so SNR = F / (sqrt(pi) (2 + 1/12) n),
    # 96 % of the ideal matched filter's F / (2 sqrt(pi) n). The filtered value carries unit noise in
    # these units (4 sigma allowed) and the measured noise and correlation a few % (6 % allowed).
    rng = np.random.default_rng(14)
    xy = np.array([[40.0, 40.0], [120.0, 40.0], [40.0, 120.0], [120.0, 120.0], [200.0, 200.0]])
    flux = np.array([300.0, 600.0, 1200.0, 2400.0, 4800.0])
    for noise in (3.0, 12.0):
        det = detect(BACKGROUND + _stars((256, 256), xy, flux) + rng.normal(0.0, noise, (256, 256)))
        dist, idx = cKDTree(xy).query(det.xy)
        assert np.all(dist < 1.0) and len(det) == len(xy)
        expected = flux[idx] / (np.sqrt(np.pi) * (2.0 + 1.0 / 12.0) * noise)
        assert np.all(np.abs(det.snr - expected) < 4.0 + 0.06 * expected), (det.snr, expected)
        assert np.all(det.snr > DetectOptions().threshold_sigma)


def test_extended_centres_equal_the_labelled_statistics():
    import cv2
    from scipy import ndimage

    from opnav.image.detect import _extended_centres

    rng = np.random.default_rng(11)
    resid = rng.normal(size=(120, 160))
    mask = np.zeros(resid.shape, np.uint8)
    mask[10:40, 20:70] = 1
    mask[60:110, 100:150] = 1
    resid[mask.astype(bool)] += 5.0
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8, ltype=cv2.CV_32S)
    components = np.arange(1, n)
    xy, peak = _extended_centres(resid, labels, stats, components)
    expected = np.array(ndimage.center_of_mass(np.clip(resid, 0, None), labels, components))[:, ::-1]
    np.testing.assert_allclose(xy, expected, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(peak, ndimage.maximum(resid, labels, components))


def test_detection_filter_equals_opencv_separable_filter():
    # the compiled 5-tap filter against OpenCV's sepFilter2D with reflected edges, on frames smaller than
    # the kernel too (edges reflected more than once); other lengths are OpenCV's own
    from opnav.image.detect import FILTER_RADIUS_SIGMAS, _gaussian_kernel, _smoothed

    rng = np.random.default_rng(31)
    assert len(_gaussian_kernel(1.0)) == 2 * math.ceil(FILTER_RADIUS_SIGMAS) + 1 == 5
    for shape in ((1, 1), (1, 6), (2, 3), (4, 4), (5, 9), (17, 3), (64, 97), (300, 211)):
        for sigma in (0.6, 1.0, 1.7):
            image = (rng.normal(0.0, 10.0, shape) + rng.uniform(-50.0, 50.0)).astype(np.float32)
            kernel = _gaussian_kernel(sigma).astype(np.float32)
            expected = cv2.sepFilter2D(image, cv2.CV_32F, kernel, kernel, borderType=cv2.BORDER_REFLECT)
            got = _smoothed(image, kernel)
            assert got.dtype == np.float32 and got.shape == shape
            np.testing.assert_allclose(got, expected, rtol=0, atol=4e-7 * float(np.abs(image).max()))
    # a view of a larger frame is filtered as its own copy
    frame = rng.normal(0.0, 1.0, (50, 60)).astype(np.float32)
    kernel = _gaussian_kernel(1.0).astype(np.float32)
    np.testing.assert_array_equal(_smoothed(frame[5:40, 7:51], kernel), _smoothed(frame[5:40, 7:51].copy(), kernel))


def test_compiled_sharp_pixel_test_equals_the_numpy_path():
    from opnav.image.detect import _sharp_pixels

    rng = np.random.default_rng(10)
    options = DetectOptions()
    for _ in range(5):
        resid = rng.normal(0.0, 1.0, (120, 160))
        resid[rng.random(resid.shape) < 0.002] += 40.0  # well below MAX_REJECTED_FRACTION (the cap has its own test)
        background = _random_background(rng, resid.shape, floor=0.5)
        noise = background.noise
        resid = resid.astype(np.float32).astype(float)  # detection's residual is single precision
        saturated = rng.random(resid.shape) < 0.02
        padded = np.pad(resid, 1)
        pair = np.minimum(padded[1:-1, :-2] + padded[1:-1, 2:], padded[:-2, 1:-1] + padded[2:, 1:-1])
        sat = np.pad(saturated, 1)
        wide_core = saturated & (sat[1:-1, :-2] | sat[1:-1, 2:])
        expected = (resid > options.threshold_sigma * noise) & (pair < options.min_neighbour_ratio * resid) & ~wide_core
        np.testing.assert_array_equal(_sharp_pixels(resid, background, saturated, options), expected)


def test_saturation_plateau_finds_a_full_well_below_the_file_range():
    from opnav.image.detect import saturation_plateau

    rng = np.random.default_rng(21)
    xy, flux = _field(rng, n=20)
    img = _noisy(rng, _stars((256, 256), xy, flux))
    bg = estimate_background(img)
    assert saturation_plateau(img, bg) is None, "unclipped stars have no flat top"
    # a detector clipping at 18 000 ADU in a 16-bit file: a bright star's core is flat there
    bright = img + _stars((256, 256), [(128.3, 60.7)], 4e6, sigma=1.2)
    at_well = bright >= 18000.0
    clipped = np.where(at_well, 18000.0 + rng.normal(0.0, READ_NOISE, bright.shape), bright)
    level = saturation_plateau(clipped, estimate_background(clipped))
    assert level is not None
    assert np.all(clipped[at_well] >= level), "every clipped pixel is on the plateau"
    assert np.all(clipped[~at_well] < level), "no unclipped pixel is"
    # detect's brightest values give the same answers without reading the frame again
    for frame in (img, clipped, np.round(clipped)):
        found = detect(frame)
        np.testing.assert_array_equal(found.brightest, np.sort(frame.ravel())[::-1][:3])
        background = estimate_background(frame)
        for min_pixels in (1, 3):
            assert (saturation_plateau(frame, background, min_pixels=min_pixels, brightest=found.brightest)
                    == saturation_plateau(frame, background, min_pixels=min_pixels))



def _plateau_by_medians(image, background, *, flat_sigma=5.0, min_pixels=3, min_height_sigma=50.0):
    """saturation_plateau's definition, with numpy's medians of the maps at 4 x 4 points a tile (every 16th
    row and column of 64-px tiles)."""
    step = background.tile_px // 4
    level_map, noise_map = background.level[::step, ::step], background.noise[::step, ::step]
    noise, top = float(np.median(noise_map)), float(np.max(image))
    if not noise > 0.0 or top - float(np.median(level_map)) < min_height_sigma * noise:
        return None
    level = top - flat_sigma * noise
    return level if np.count_nonzero(image >= level) >= min_pixels else None


def test_saturation_plateau_is_its_definition_at_the_edges_of_its_tests():
    # the bounds that skip its medians decide as the medians do: clip levels from 40 to 60 background
    # sigmas above the sky (the height test's edge at 50) and peaks just beyond the flat band (5 sigmas)
    from opnav.image.detect import saturation_plateau

    rng = np.random.default_rng(23)
    xy, flux = _field(rng, n=20)
    base = _noisy(rng, _stars((256, 256), xy, flux)) + np.linspace(0.0, 30.0, 256)[None, :]  # a sloped sky
    background = estimate_background(base)  # one background for every frame: the edges are then exact
    sky, sigma = float(np.median(background.level[::16, ::16])), float(np.median(background.noise[::16, ::16]))
    frames = [base]
    for height in (40.0, 49.99, 50.01, 60.0):
        clip = sky + height * sigma
        frames.append(np.minimum(base, clip))  # flat at the clip
        single = np.minimum(base, clip - 10.0 * sigma)
        single[40, 40], single[41, 40], single[200, 100] = clip, clip - 4.99 * sigma, clip - 5.01 * sigma
        frames.append(single)
    decided = 0
    for frame in frames:
        brightest = np.sort(frame.ravel())[::-1][:3]
        for min_pixels in (1, 2, 3):
            expected = _plateau_by_medians(frame, background, min_pixels=min_pixels)
            decided += expected is not None
            assert saturation_plateau(frame, background, min_pixels=min_pixels) == expected
            assert saturation_plateau(frame, background, min_pixels=min_pixels, brightest=brightest) == expected
    assert 0 < decided < 3 * len(frames)  # both answers occur

def test_frame_scan_equals_the_numpy_expressions():
    # finite and varied valid pixels, the saturated mask and count, the three largest values (NaN with a NaN),
    # and the background's tile samples, as estimate_background takes them (full and sampled tiles)
    from opnav.image.detect import _frame_scan, _tile_band, _tile_bands

    rng = np.random.default_rng(22)
    for trial in range(40):
        shape = tuple(rng.integers(1, 40 if trial % 4 else 90, 2))
        image = np.round(rng.normal(100.0, 3.0, shape))  # ties among the brightest
        valid = rng.random(shape) > 0.2
        if trial % 5 == 1:
            image[tuple(rng.integers(0, s) for s in shape)] = rng.choice([np.nan, np.inf, -np.inf])
        if trial % 7 == 2:
            image[:] = 42.0  # blank
        masked = trial % 2 == 0
        mask = valid if masked else np.ones((1, 1), bool)
        inside = image[valid] if masked else image.ravel()
        saturation = float(np.percentile(image[np.isfinite(image)], 90)) if trial % 3 else np.inf
        invalid = ~valid if masked else np.zeros((1, 1), bool)
        tile, bands = _tile_bands(shape, (8, 32)[trial % 3 == 0])
        finite, varied, saturated, count, top = _frame_scan(image, mask, saturation, 3, invalid, tile, bands)
        expected_bands = np.empty_like(bands)
        for row in range(bands.shape[0]):
            _tile_band(image, invalid, tile, row, expected_bands[row])
        np.testing.assert_array_equal(bands, expected_bands)
        assert finite == bool(np.all(np.isfinite(inside)))
        assert varied == bool(inside.size and np.any(inside != inside[0]))
        expected = (image >= saturation) & (valid if masked else True)
        np.testing.assert_array_equal(saturated, expected)
        assert count == expected.sum()
        if np.isnan(image).any():
            assert np.isnan(top).all()
        else:
            np.testing.assert_array_equal(top[:min(3, image.size)], np.sort(image.ravel())[::-1][:3])


def test_lossy_frame_finds_faint_stars_without_block_artefacts():
    """An 8-bit square-root-stretched JPEG (quality 70): the stars a 16-bit frame shows at a
    matched-filter SNR of 8 or more are found, and nothing that is not a star."""
    import io

    from PIL import Image

    rng = np.random.default_rng(22)
    shape, sigma_psf, noise_e = (384, 512), 1.2, 8.0
    xy = rng.uniform(12, [shape[1] - 12, shape[0] - 12], (60, 2))
    close = {j for i, j in cKDTree(xy).query_pairs(8.0)}
    xy = np.delete(xy, sorted(close), axis=0)
    snr = rng.uniform(5.0, 25.0, len(xy))  # matched-filter SNR: F / (noise sqrt(4 pi s^2))
    flux = snr * noise_e * np.sqrt(4.0 * np.pi * sigma_psf**2)
    frame = 100.0 + _stars(shape, xy, flux, sigma=sigma_psf) + rng.normal(0.0, noise_e, shape)
    stretched = np.clip((frame - 100.0 + 3.0 * noise_e) / (60.0 * noise_e), 0.0, 1.0) ** 0.5
    buffer = io.BytesIO()
    Image.fromarray(np.rint(255.0 * stretched).astype(np.uint8)).save(buffer, format="JPEG", quality=70)
    image = np.asarray(Image.open(io.BytesIO(buffer.getvalue())), dtype=float)
    det = detect(image, saturation_adu=255.0, lossy=True)
    dist, idx = cKDTree(xy).query(det.xy)
    assert np.all(dist < 1.0), "every source is a star"
    found = np.zeros(len(xy), bool)
    found[idx] = True
    assert found[snr >= 8.0].all(), "every star of matched-filter SNR >= 8 found"


def test_adjacent_hot_pixels_are_rejected_and_the_sharpest_stars_kept():
    """Two hot pixels side by side pass the one-pixel test (each is the other's neighbour); the
    two-pixel test rejects them, bloomed into their columns or not, and keeps bright stars of the
    sharpest PSF the detector allows (sigma 0.5 px) at every pixel phase, the hardest being a star
    centred on the edge between two pixels."""
    rng = np.random.default_rng(21)
    shape = (200, 200)
    phases = [(0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5), (0.25, 0.4)]
    stars = np.array([[30.0 + 35.0 * k + dx, 40.0 + dy] for k, (dx, dy) in enumerate(phases)])
    img = _noisy(rng, _stars(shape, stars, 60000.0, sigma=0.5))
    img[120, 50:52] += 18000.0  # a hot pair
    img[119:122, 100:102] += np.array([[8600.0], [18000.0], [8600.0]])  # a hot pair bloomed into its columns
    img[150, 150:152] += [18000.0, 9000.0]
    det = detect(img)
    dist, _ = cKDTree(stars).query(det.xy)
    assert len(det.xy) == len(stars) and np.all(dist < 0.5)
    assert det.rejected[120, 50:52].all() and det.rejected[119:122, 100:102].all() and det.rejected[150, 150:152].all()


def test_truncated_normal_spread_is_scipys():
    """The closed-form spread of a clipped unit normal equals scipy's truncnorm (within 1 ulp)."""
    from scipy.stats import truncnorm

    from opnav.image.detect import _truncated_sd

    for clip in np.linspace(1.5, 6.0, 91):
        assert _truncated_sd(float(clip)) == pytest.approx(math.sqrt(truncnorm.var(-clip, clip)), rel=1e-15, abs=0)
    assert _truncated_sd(3.0) == math.sqrt(truncnorm.var(-3.0, 3.0))


@pytest.mark.parametrize("shape", [(1, 5), (2, 2), (7, 11), (16, 16)])
def test_tile_grid_median_is_scipys(shape):
    # the background's 3 x 3 median over the tile grid (compiled) is scipy.ndimage's with edges repeated
    from scipy import ndimage

    from opnav.image.detect import _median_3x3

    grid = np.round(np.random.default_rng(3).normal(100.0, 2.0, shape), 1)  # rounded: ties
    assert np.array_equal(_median_3x3(grid), ndimage.median_filter(grid, size=3, mode="nearest"))


def test_noise_window_is_the_noise_map_of_the_box():
    """Background.noise_window against the full noise map (and window's noise) on a sloped sky with a
    noise floor, for frames of one shape in turn (their tile weights are shared)."""
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[:200, :300]
    for slope in (0.0, 0.05):
        img = rng.normal(100.0 + slope * xx, 3.0 + slope * 10 * yy / 200)
        bg = estimate_background(img, tile_px=32).with_noise_floor(3.5)
        rows, cols = slice(1, None, 4), slice(None, None, 3)
        np.testing.assert_array_equal(bg.noise_window(rows, cols), bg.noise[rows, cols])
        np.testing.assert_array_equal(bg.noise_window(rows, cols), bg.window(rows, cols)[1])
        assert bg.noise[rows, cols].min() >= 3.5
