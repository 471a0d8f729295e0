"""Point sources of a whole frame for lost-in-space star identification (:mod:`opnav.image.starid`).

:func:`extract_sources` detects (:func:`opnav.image.detect.detect`), fits each point source
(Gaussian fit, moment centroid when a faint star's fit fails) and orders them most reliable
first (detection signal-to-noise ratio); stars that a saturated planet's halo or bloom trail
joined to its extended component are looked for as PSF peaks inside it. Pixel coordinates
follow :mod:`opnav.image` (x = column, y = row, origin at the centre of the first pixel).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..compiled import kernel
from .centroid import MAX_WINDOW, centroid, psf_like
from .detect import FLAG_EXTENDED, FLAG_INVALID, FLAG_SATURATED, DetectOptions, detect, saturation_plateau

_DEFAULT_DETECT = DetectOptions()
#: Centroid stamp side of :func:`extract_stars`, px.
_STAMP_PX = 7


@dataclass(frozen=True)
class ExtractedStars:
    """Point sources of a frame (:func:`extract_sources`), most reliable first.

    Attributes
    ----------
    xy : ndarray, shape (N, 2)
        Centroids, px (docs/conventions.md).
    cov : ndarray, shape (N, 2, 2)
        Their covariances, px^2.
    flux : ndarray, shape (N,)
        Centroid (fitted or moment) flux above the local background, ADU.
    snr : ndarray, shape (N,)
        Detection signal-to-noise ratio (:attr:`opnav.image.detect.Detections.snr`): the
        detection-filtered frame at the source over its measured filtered noise. Rows are sorted
        by it, highest first.
    """

    xy: np.ndarray
    cov: np.ndarray
    flux: np.ndarray
    snr: np.ndarray

    def __len__(self) -> int:
        return len(self.xy)


def extract_stars(
    image: np.ndarray,
    *,
    max_stars: int = 40,
    saturation_adu: float | None = None,
    invalid: np.ndarray | None = None,
    lossy: bool = False,
    detect_options: DetectOptions = _DEFAULT_DETECT,
    read_noise_e: float | None = None,
    gain_e_per_adu: float | None = None,
    bias_adu: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Centroids (N, 2) px and covariances (N, 2, 2) px^2 of :func:`extract_sources`, highest SNR first."""
    found = extract_sources(image, max_stars=max_stars, saturation_adu=saturation_adu, invalid=invalid, lossy=lossy,
                            detect_options=detect_options, read_noise_e=read_noise_e, gain_e_per_adu=gain_e_per_adu,
                            bias_adu=bias_adu)
    return found.xy, found.cov


def extract_sources(
    image: np.ndarray,
    *,
    max_stars: int = 40,
    saturation_adu: float | None = None,
    invalid: np.ndarray | None = None,
    lossy: bool = False,
    detect_options: DetectOptions = _DEFAULT_DETECT,
    read_noise_e: float | None = None,
    gain_e_per_adu: float | None = None,
    bias_adu: float = 0.0,
) -> ExtractedStars:
    """Point sources of a frame, ordered by detection signal-to-noise ratio, highest first.

    Extended sources and sources touching invalid pixels are left out; the ``max_stars``
    detections of largest flux are centroided (a JPEG frame can hold over a hundred sharp
    compression remnants of hot pixels, of high peak SNR but small flux, that would crowd faint
    stars out of the list). Ordering by SNR rather than by flux puts
    the sources least likely to be noise, compression artefacts or the wide, low-significance
    fits of a noise bump first, so that lost-in-space patterns (:func:`identify`, which works
    down the list) start from reliable stars. ``lossy`` (a JPEG frame) makes detection ignore
    compression ringing; pixels detection rejects as hot or cosmic-ray hits are kept out of the
    centroids. A detector that clips below ``saturation_adu``
    (:func:`opnav.image.detect.saturation_plateau`) has its clipped pixels kept out of the fit
    too. A source whose Gaussian fit fails is centroided by iteratively weighted moments with the
    frame's fitted PSF width, unless its stamp lost pixels; a source without a finite, positive
    covariance is left out.

    The detector's noise model, when known (an opnav FITS header's ``RDNOISE``, ``GAIN`` and
    ``BIASLVL``, as :func:`opnav.image.sources.image_sources` reads them), sets the pixel variances
    of every fit: ``read_noise_e`` (electrons), ``gain_e_per_adu`` (electrons per ADU) and
    ``bias_adu`` (ADU) are passed to :func:`opnav.image.centroid.centroid`. Without them the
    frame's background variance and gain are fitted from its clean stamps.

    Returns
    -------
    ExtractedStars
    """
    found = detect(image, options=detect_options, saturation_adu=saturation_adu, invalid=invalid, lossy=lossy)
    point = np.flatnonzero((found.flags & (FLAG_EXTENDED | FLAG_INVALID)) == 0)[:max_stars]
    excluded = found.rejected if invalid is None else (found.rejected | invalid)
    # A detector that clips below the file's range (full well < 65535 ADU) leaves flat-topped
    # stars and hot-pixel clusters; their clipped pixels stay out of the PSF fit.
    plateau = saturation_plateau(image, found.background, brightest=found.brightest)
    clip = saturation_adu if plateau is None else min(plateau, math.inf if saturation_adu is None else saturation_adu)
    seeds, snr = found.xy[point], found.snr[point]
    noise = {"read_noise_e": read_noise_e, "gain_e_per_adu": gain_e_per_adu, "bias_adu": bias_adu}
    result = centroid(image, seeds, window=_STAMP_PX, saturation_adu=clip, invalid=excluded, **noise)
    xy, cov, flux = result.xy, result.cov, result.flux
    good = _usable_centroids(result)
    wide = np.zeros(len(seeds), bool)
    if clip is not None and math.isfinite(clip):
        # a clipped core wider than the stamp's wings allow: fitted again over a stamp that holds them
        # (clipped at the file's top or at a full well below it: the seed's 3 x 3 pixels reach the clip)
        saturated = np.flatnonzero(((found.flags[point] & FLAG_SATURATED) != 0) | _reaches(image, seeds, clip))
        if len(saturated):
            xy, cov, flux = xy.copy(), cov.copy(), flux.copy()
        plateaus = set()
        for k in saturated:
            refit = _wide_core_centroid(image, seeds[k], clip, excluded, noise)
            if refit is not None:
                wide[k] = True
                centre, xy[k], cov[k], flux[k], good[k] = refit
                # de-blending can split a flat top it did not know was clipped (a full well below the
                # file's range): its seeds find the same plateau, kept once (the first, highest SNR)
                good[k] &= centre not in plateaus
                plateaus.add(centre)
    if 0 < good.sum() < len(seeds):
        # A faint star's Gaussian fit can wander off in a noisy or compressed stamp (a third of
        # the 5-7 sigma stars of a JPEG frame): its position then comes from the iteratively
        # weighted centroid with the frame's fitted PSF width, which needs no convergence of a
        # 5-parameter fit. Not where the stamp lost pixels (a hot pixel's or a track's rejected
        # halo, a NaN): a moment centroid of the rest of a star is pulled away from it.
        failed = np.array([k for k in np.flatnonzero(~good & ~wide) if not _stamp_lost_pixels(excluded, seeds[k])],
                          int)
        width = float(np.median(result.sigma_px[good]))
        if len(failed):
            rescue = centroid(image, seeds[failed], method="iwc", window=_STAMP_PX, psf_sigma_px=width,
                              saturation_adu=clip, invalid=excluded, **noise)
            xy, cov, flux = xy.copy(), cov.copy(), flux.copy()
            xy[failed], cov[failed], flux[failed] = rescue.xy, rescue.cov, rescue.flux
            good[failed] = _usable_centroids(rescue) & (rescue.flux > 0.0)
    embedded = _embedded_point_sources(image, found, clip, max_stars - len(point))
    if len(embedded):
        extra = centroid(image, embedded, window=_STAMP_PX, saturation_adu=clip, invalid=excluded, **noise)
        # a peak on a planet's halo or bloom trail counts only as a PSF-shaped fit (not a limb,
        # an edge or a noise spike of the halo)
        xy, cov, flux = np.concatenate([xy, extra.xy]), np.concatenate([cov, extra.cov]), np.concatenate([flux, extra.flux])
        good = np.concatenate([good, _usable_centroids(extra) & psf_like(extra) & (extra.snr >= 10.0)])
        snr = np.concatenate([snr, extra.snr])
    ok = np.flatnonzero(good)
    ok = ok[np.argsort(-snr[ok], kind="stable")]
    return ExtractedStars(xy=xy[ok], cov=cov[ok], flux=flux[ok], snr=snr[ok])


#: A clipped core whose plateau is wider than this along x or y leaves the ``_STAMP_PX`` stamp fewer
#: than two rings of unclipped wing pixels, px: it is fitted over a stamp that holds ``_WING_PX`` rings.
_NARROW_CORE_PX = _STAMP_PX - 4
_WING_PX = 3
#: Widest plateau searched for around a saturated seed, px (beyond it a clipped body, not a star).
_WIDEST_CORE_PX = MAX_WINDOW - 2 * _WING_PX
#: Iterations of the wide core's fit (30 left a third of the 7-px plateaus of 8-bit frames unconverged).
_WIDE_CORE_ITER = 200


def _reaches(image: np.ndarray, seeds: np.ndarray, clip: float) -> np.ndarray:
    """Whether the 3 x 3 pixels around each seed (x, y px) hold one at or above ``clip``, (N,) bool."""
    height, width = image.shape
    if len(seeds) == 0 or min(height, width) < 3:
        return np.zeros(len(seeds), bool)
    col = np.clip(np.rint(seeds[:, 0]).astype(int), 1, width - 2)
    row = np.clip(np.rint(seeds[:, 1]).astype(int), 1, height - 2)
    offsets = np.arange(-1, 2)
    values = image[row[:, None, None] + offsets[None, :, None], col[:, None, None] + offsets[None, None, :]]
    return values.reshape(len(seeds), -1).max(axis=1) >= clip


def _wide_core_centroid(image: np.ndarray, seed_xy: np.ndarray, clip: float, excluded: np.ndarray, noise: dict):
    """``(plateau centre (x, y), xy, cov, flux, ok)`` of a saturated star whose clipped plateau is wider
    than ``_NARROW_CORE_PX``, or None for a narrower one (the ``_STAMP_PX`` fit holds its wings).
    ``noise`` holds the keyword arguments of the detector's noise model for
    :func:`opnav.image.centroid.centroid`.

    The plateau is the 8-connected set of pixels at or above ``clip`` nearest the seed (the seed of
    a flat top can be any of its pixels). Its pixels carry no shape, only its outline does: the
    Gaussian fit of :func:`opnav.image.centroid.centroid` over a stamp centred on the plateau
    (the mean of its pixels) and ``_WING_PX`` pixels wider than it on each side, clipped pixels
    left out, reads the star's position from the wings around the plateau. Its covariance is the
    fit's times the fit's reduced chi-square when above 1 (the wings of a real PSF are not a
    Gaussian's, and the fit then says so in its residuals). A fit that fails or lands more than a
    pixel from the plateau's centre gives that centre with a pixel's variance, 1/12 px^2, per axis.
    """
    height, width = image.shape
    col, row = int(np.clip(np.rint(seed_xy[0]), 0, width - 1)), int(np.clip(np.rint(seed_xy[1]), 0, height - 1))
    half = _STAMP_PX
    while True:
        r0, r1, c0, c1 = max(row - half, 0), min(row + half + 1, height), max(col - half, 0), min(col + half + 1, width)
        clipped = (np.asarray(image[r0:r1, c0:c1]) >= clip).view(np.uint8)
        if not clipped.any():
            return None
        labels = cv2.connectedComponents(clipped, connectivity=8)[1]
        rows, cols = np.nonzero(labels)
        nearest = np.argmin((rows + r0 - row) ** 2 + (cols + c0 - col) ** 2)
        rows, cols = np.nonzero(labels == labels[rows[nearest], cols[nearest]])
        touches = ((rows.min() == 0 and r0 > 0) or (cols.min() == 0 and c0 > 0)
                   or (rows.max() == r1 - r0 - 1 and r1 < height) or (cols.max() == c1 - c0 - 1 and c1 < width))
        if not touches or 2 * half + 1 > _WIDEST_CORE_PX:
            break
        half *= 2
    extent = max(rows.max() - rows.min(), cols.max() - cols.min()) + 1
    if extent <= _NARROW_CORE_PX or touches:
        return None
    centre = np.array([cols.mean() + c0, rows.mean() + r0])
    side = min(int(extent) + 2 * _WING_PX + (int(extent) + 1) % 2, MAX_WINDOW)
    # the fit starts from the clipped stamp's flux, far below the star's: it needs more steps than a stamp
    fit = centroid(image, centre[None], window=side, saturation_adu=clip, invalid=excluded, max_iter=_WIDE_CORE_ITER,
                   **noise)
    key = (float(centre[0]), float(centre[1]))
    if _usable_centroids(fit)[0] and np.hypot(*(fit.xy[0] - centre)) < 1.0:
        reduced_chi2 = float(fit.chi2[0] / fit.dof[0]) if fit.dof[0] > 0 else 1.0
        return key, fit.xy[0], fit.cov[0] * max(reduced_chi2, 1.0), fit.flux[0], True
    return key, centre, np.eye(2) / 12.0, float(np.nan_to_num(fit.flux[0])), True


def _embedded_point_sources(image: np.ndarray, found, clip: float | None, count: int) -> np.ndarray:
    """Point-like peaks inside extended detections: seeds (M, 2), px, strongest first, at most ``count``.

    A star beside a saturated planet joins the planet's halo or bloom trail in one extended
    component and is lost with it (a sparse 1-degree field beside Mars then has too few stars
    for lost-in-space). Inside those components the frame less its 9-px running median (which
    follows a halo, not a PSF of ~1 px) peaks at such stars: a peak counts when it is the
    maximum of its 5 x 5 square and stands 8 local noise sigmas (the running MAD of that
    difference over 9 x 9: the halo's own shot noise) above it, and not within 3 px of clipped
    pixels. The caller keeps a peak only when its PSF fit passes the chi-square test
    (:func:`opnav.image.centroid.psf_like`).

    The running statistics are those of ``scipy.ndimage`` filters over the components' bounding
    box with its edge pixels repeated (``mode="nearest"``), evaluated only where a peak can be
    (the component's pixels away from clipped ones) and where those tests read them, in one compiled
    pass over the box (:func:`_embedded_peaks`). A bloom trail's box is a full column of the frame,
    mostly clipped: the filters over all of it took 70 ms of a 1 MP demo frame's 85 ms extraction.
    """
    extended, box = extended_box(found, image.shape)
    if count <= 0 or extended.size == 0:
        return np.zeros((0, 2))
    r0, c0 = box[0].start, box[1].start
    is_extended = np.zeros(len(found.boxes), bool)
    is_extended[extended] = True
    background_level, background_noise = found.background.window(*box)
    clipping = clip is not None and math.isfinite(clip)
    rows, cols, strength = _embedded_peaks(np.asarray(image[box], dtype=float), found.labels[box], is_extended,
                                           clipping, float(clip) if clipping else math.inf, background_level,
                                           background_noise)
    order = np.argsort(-strength, kind="stable")[:count]
    return np.column_stack([cols[order] + c0, rows[order] + r0]).astype(float)


def extended_box(found, shape: tuple[int, int]) -> tuple[np.ndarray, tuple[slice, slice]]:
    """The labels of ``found``'s extended components and the box (rows, columns) that holds them with 4 px
    around, within a frame of ``shape``, from detection's statistics: the label image is read only inside it
    (an empty box when there is no extended component)."""
    extended = np.unique(found.label[(found.flags & FLAG_EXTENDED) != 0])
    if extended.size == 0:
        return extended, (slice(0, 0), slice(0, 0))
    left, top, width, height = found.boxes[extended].T
    r0, r1 = max(int(top.min()) - 4, 0), min(int((top + height).max()) + 4, shape[0])
    c0, c1 = max(int(left.min()) - 4, 0), min(int((left + width).max()) + 4, shape[1])
    return extended, (slice(r0, r1), slice(c0, c1))


@kernel
def _embedded_peaks(image, labels, is_extended, clipping, clip, background_level, background_noise
                    ):  # pragma: no cover - compiled
    """(rows, columns, strength) of :func:`_embedded_point_sources`' peaks in its box, in raster order.

    ``image``, ``labels``, ``background_level`` and ``background_noise`` are the box's. A pixel is a
    candidate where ``is_extended[label]``, no pixel at or above ``clip`` lies within 3 px (when
    ``clipping``; the 7 x 7 square, none beyond the box) and its level (image less background
    level) stands 8 ``background_noise`` above the least level of its 9 x 9 square (edge pixels
    repeated, as ``cv2.erode`` with ``BORDER_REPLICATE``). ``sharp`` (level less its running 9-px
    median, :func:`_running_median`) is made only where the tests read it: within 2 px of a candidate
    (its 5 x 5 maximum, :func:`_running_max`) and within 4 px of one that passes (the running MAD).
    One pass over the box for the candidates: as full-box masks, filters and index lists (a bloom
    trail's box is a full column of the frame) they were 0.7 ms of a 1 MP demo frame's extraction."""
    height, width = image.shape
    level = np.empty((height, width))
    for r in range(height):
        for c in range(width):
            level[r, c] = image[r, c] - background_level[r, c]
    # within 3 px of a clipped pixel: running counts of clipped pixels over 7 columns, then over 7 rows
    near = np.zeros((height, width), np.bool_)
    if clipping:
        along = np.zeros((height, width), np.int64)
        for r in range(height):
            count = 0
            for c in range(min(3, width)):
                count += image[r, c] >= clip
            for c in range(width):
                if c + 3 < width:
                    count += image[r, c + 3] >= clip
                if c - 4 >= 0:
                    count -= image[r, c - 4] >= clip
                along[r, c] = count
        counts = np.zeros(width, np.int64)
        for r in range(min(3, height)):
            counts += along[r]
        for r in range(height):
            if r + 3 < height:
                counts += along[r + 3]
            if r - 4 >= 0:
                counts -= along[r - 4]
            for c in range(width):
                near[r, c] = counts[c] > 0
    # the candidates: a pixel of an extended component away from clipped ones whose level stands 8 sigmas
    # above the least of its 9 x 9 square (edges repeated: the clipped square's own pixels)
    n = 0
    for r in range(height):
        for c in range(width):
            n += is_extended[labels[r, c]] and not near[r, c]
    cand_r = np.empty(n, np.int64)
    cand_c = np.empty(n, np.int64)
    n = 0
    for r in range(height):
        for c in range(width):
            if not is_extended[labels[r, c]] or near[r, c]:
                continue
            low = level[r, c]
            for k in range(max(r - 4, 0), min(r + 5, height)):
                for j in range(max(c - 4, 0), min(c + 5, width)):
                    low = min(low, level[k, j])
            if level[r, c] - low > 8.0 * background_noise[r, c]:
                cand_r[n] = r
                cand_c[n] = c
                n += 1
    cand_r, cand_c = cand_r[:n], cand_c[:n]
    sharp = np.full((height, width), np.nan)
    _fill_sharp(sharp, level, cand_r, cand_c, 2)
    highest = _running_max(sharp, cand_r, cand_c, 2)
    keep = np.zeros(n, np.bool_)
    for k in range(n):
        value = sharp[cand_r[k], cand_c[k]]
        keep[k] = value == highest[k] and value > 8.0 * background_noise[cand_r[k], cand_c[k]]
    peak_r, peak_c = cand_r[keep], cand_c[keep]
    _fill_sharp(sharp, level, peak_r, peak_c, 4)
    deviation = _running_median(np.abs(sharp), peak_r, peak_c, 4)
    found = np.zeros(peak_r.size, np.bool_)
    strength = np.empty(peak_r.size)
    for k in range(peak_r.size):
        r, c = peak_r[k], peak_c[k]
        local = max(_MAD_TO_SIGMA * deviation[k], background_noise[r, c])
        found[k] = sharp[r, c] > 8.0 * local
        strength[k] = sharp[r, c] / local
    return peak_r[found], peak_c[found], strength[found]


@kernel(inline=True)
def _fill_sharp(sharp, level, rows, cols, half):  # pragma: no cover - compiled
    """``sharp = level - running 9-px median of level`` (:func:`_running_median`) at the pixels within
    ``half`` of a listed one (``rows``, ``cols``; the square, inside the array) where it is NaN (not made yet)."""
    height, width = level.shape
    wanted = np.zeros((height, width), np.bool_)
    todo_r = np.empty(rows.size * (2 * half + 1) ** 2, np.int64)
    todo_c = np.empty(todo_r.size, np.int64)
    m = 0
    for k in range(rows.size):
        for r in range(max(rows[k] - half, 0), min(rows[k] + half + 1, height)):
            for c in range(max(cols[k] - half, 0), min(cols[k] + half + 1, width)):
                if np.isnan(sharp[r, c]) and not wanted[r, c]:
                    wanted[r, c] = True
                    todo_r[m], todo_c[m] = r, c
                    m += 1
    medians = _running_median(level, todo_r[:m], todo_c[:m], 4)
    for k in range(m):
        sharp[todo_r[k], todo_c[k]] = level[todo_r[k], todo_c[k]] - medians[k]


#: MAD of a normal distribution times this is its standard deviation.
_MAD_TO_SIGMA = 1.4826


@kernel
def _running_max(values, rows, cols, half):  # pragma: no cover - compiled
    """Maximum of the ``(2 half + 1)^2`` square of ``values`` around each pixel ``(rows[k], cols[k])``,
    indices beyond the array clipped to its edge: ``scipy.ndimage.maximum_filter(values, size=2 half + 1,
    mode="nearest")`` at those pixels."""
    height, width = values.shape
    out = np.empty(rows.size)
    for k in range(rows.size):
        highest = -np.inf
        for dr in range(-half, half + 1):
            r = min(max(rows[k] + dr, 0), height - 1)
            for dc in range(-half, half + 1):
                highest = max(highest, values[r, min(max(cols[k] + dc, 0), width - 1)])
        out[k] = highest
    return out


@kernel
def _running_median(values, rows, cols, half):  # pragma: no cover - compiled
    """Median of the ``(2 half + 1)^2`` square of ``values`` around each pixel ``(rows[k], cols[k])``,
    indices beyond the array clipped to its edge: ``scipy.ndimage.median_filter(values, size=2 half + 1,
    mode="nearest")`` at those pixels (an odd count: the median is one of the values, found by
    Hoare's selection in place of numpy's partition, 1 us a pixel for 81 values)."""
    height, width = values.shape
    side = 2 * half + 1
    n = side * side
    middle = n // 2
    window = np.empty(n)
    out = np.empty(rows.size)
    for k in range(rows.size):
        m = 0
        for dr in range(-half, half + 1):
            r = min(max(rows[k] + dr, 0), height - 1)
            for dc in range(-half, half + 1):
                window[m] = values[r, min(max(cols[k] + dc, 0), width - 1)]
                m += 1
        low, high = 0, n - 1
        while low < high:
            pivot = window[middle]
            i, j = low, high
            while i <= j:
                while window[i] < pivot:
                    i += 1
                while pivot < window[j]:
                    j -= 1
                if i <= j:
                    window[i], window[j] = window[j], window[i]
                    i += 1
                    j -= 1
            if j < middle:
                low = i
            if middle < i:
                high = j
        out[k] = window[middle]
    return out


def _stamp_lost_pixels(excluded: np.ndarray, seed_xy: np.ndarray) -> bool:
    """Whether the ``_STAMP_PX`` square centred on the pixel nearest ``seed_xy`` (x, y px) holds an excluded pixel."""
    half = _STAMP_PX // 2
    col, row = np.clip(np.rint(seed_xy), 0, [excluded.shape[1] - 1, excluded.shape[0] - 1]).astype(int)
    return bool(excluded[max(row - half, 0):row + half + 1, max(col - half, 0):col + half + 1].any())


def _usable_centroids(result) -> np.ndarray:
    """Rows of a :class:`opnav.image.centroid.CentroidResult` with a finite, positive covariance."""
    variances = np.diagonal(result.cov, axis1=1, axis2=2)
    return result.ok & np.all(np.isfinite(result.cov), axis=(1, 2)) & np.all(variances > 0.0, axis=1)
