"""The search for stars inside extended detections (:func:`opnav.image.extract._embedded_point_sources`):
its compiled pass over the components' box finds the peaks its definition, as full-box filters, finds."""

import math

import cv2
import numpy as np
import pytest
from scipy import ndimage
from scipy.special import ndtr

from opnav.image.detect import FLAG_EXTENDED, detect
from opnav.image.extract import _embedded_point_sources, extended_box


def _by_filters(image, found, clip, count):
    """The definition over the whole box: 7 x 7 clipped dilation, 9 x 9 erosion, 9-px running median,
    5 x 5 maximum and 9 x 9 MAD of scipy.ndimage / OpenCV, edges repeated."""
    extended, box = extended_box(found, image.shape)  # the box is the search's, shared
    if count <= 0 or extended.size == 0:
        return np.zeros((0, 2))
    r0, c0 = box[0].start, box[1].start
    candidates = np.isin(found.labels[box], extended)
    if clip is not None and math.isfinite(clip):
        clipped = (image[box] >= clip).astype(np.uint8)
        candidates &= cv2.dilate(clipped, np.ones((7, 7), np.uint8), borderType=cv2.BORDER_CONSTANT,
                                 borderValue=0) == 0
    background_level, background_noise = found.background.window(*box)
    level = image[box] - background_level
    candidates &= level - ndimage.minimum_filter(level, size=9, mode="nearest") > 8.0 * background_noise
    sharp = level - ndimage.median_filter(level, size=9, mode="nearest")
    local = np.maximum(1.4826 * ndimage.median_filter(np.abs(sharp), size=9, mode="nearest"), background_noise)
    peak = (candidates & (sharp == ndimage.maximum_filter(sharp, size=5, mode="nearest"))
            & (sharp > 8.0 * background_noise) & (sharp > 8.0 * local))
    rows, cols = np.nonzero(peak)
    order = np.argsort(-(sharp / local)[rows, cols], kind="stable")[:count]
    return np.column_stack([cols[order] + c0, rows[order] + r0]).astype(float)


def _pixel_gaussian(coord, centre, sigma=1.0):
    return ndtr((coord + 0.5 - centre) / sigma) - ndtr((coord - 0.5 - centre) / sigma)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_compiled_search_finds_what_the_filters_find(seed):
    # a clipped bloom column in a scattered-light halo (a box touching the frame's top and bottom edges),
    # a round saturated body apart from it, stars on both halos and one beside the frame's edge
    rng = np.random.default_rng(seed)
    shape = (192, 160)
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    edge = np.maximum(np.abs(cols - 60.0) - 5.0, 0.0)
    disc = np.maximum(np.hypot(rows - 140.0, cols - 125.0) - 9.0, 0.0)
    frame = 100.0 + 1e6 * np.exp(-0.5 * edge**2) + 300.0 * np.exp(-edge / 10.0) + 5e5 * np.exp(-0.5 * disc**2)
    frame += 250.0 * np.exp(-disc / 8.0)
    for _ in range(12):
        x = rng.choice([rng.uniform(66.0, 85.0), rng.uniform(35.0, 54.0), rng.uniform(105.0, 150.0)])
        y = rng.uniform(1.0, shape[0] - 2.0)
        frame += rng.uniform(2e3, 5e4) * np.outer(_pixel_gaussian(rows[:, 0], y), _pixel_gaussian(cols[0], x))
    saturation = 30000.0
    image = np.minimum(rng.poisson(frame) + rng.normal(0.0, 5.0, shape), saturation)
    found = detect(image, saturation_adu=saturation)
    assert (found.flags & FLAG_EXTENDED).any()
    total = 0
    for clip in (saturation, None):
        for count in (3, 40):
            expected = _by_filters(image, found, clip, count)
            np.testing.assert_array_equal(_embedded_point_sources(image, found, clip, count), expected)
            total += len(expected)
    assert total > 0  # peaks were found, not only agreed on


@pytest.mark.parametrize("seed", [4, 5, 6, 7])
def test_the_compiled_tests_are_the_filters_on_random_boxes(seed):
    # every test at its edges: clipped pixels scattered at 2-5 px from candidates, many peaks of every
    # height against a low noise, labels that leave holes in the extended components, and a box whose
    # pixels and rows are views into a larger frame
    from opnav.image.extract import _embedded_peaks

    rng = np.random.default_rng(seed)
    frame = rng.normal(0.0, 1.0, (150, 170)) + 30.0 * (rng.random((150, 170)) < 0.06) * rng.random((150, 170))
    labels = rng.integers(0, 4, (150, 170)).astype(np.int32)
    box = (slice(3, 141), slice(5, 163))
    image, label_box = frame[box], labels[box]
    is_extended = np.array([False, True, False, True])
    background_level = rng.normal(0.0, 0.1, image.shape)
    background_noise = rng.uniform(0.05, 0.6, image.shape)
    clip = float(np.quantile(image, 0.97))
    for clipping in (True, False):
        rows, cols, strength = _embedded_peaks(image, label_box, is_extended, clipping,
                                               clip if clipping else math.inf, background_level, background_noise)
        level = image - background_level
        candidates = is_extended[label_box]
        if clipping:
            near = ndimage.maximum_filter((image >= clip).astype(np.uint8), size=7, mode="constant", cval=0)
            candidates &= near == 0
        candidates &= level - ndimage.minimum_filter(level, size=9, mode="nearest") > 8.0 * background_noise
        sharp = level - ndimage.median_filter(level, size=9, mode="nearest")
        local = np.maximum(1.4826 * ndimage.median_filter(np.abs(sharp), size=9, mode="nearest"),
                           background_noise)
        peak = (candidates & (sharp == ndimage.maximum_filter(sharp, size=5, mode="nearest"))
                & (sharp > 8.0 * background_noise) & (sharp > 8.0 * local))
        expected_rows, expected_cols = np.nonzero(peak)
        assert len(expected_rows) >= 3
        np.testing.assert_array_equal(rows, expected_rows)
        np.testing.assert_array_equal(cols, expected_cols)
        np.testing.assert_array_equal(strength, (sharp / local)[expected_rows, expected_cols])
