"""Centroids of a frame's identified stars whose covariances hold, for camera calibration.

A calibration weighs hundreds of stars by their centroid covariances and judges the fit by its
chi-square, so every star's covariance has to be its real error, bright and faint alike. Three
things break that; :func:`calibration_centroids` handles each for the stars a frame matched
(:mod:`opnav.image.calibration_stars`):

1. **The noise model.** With the detector's gain, read noise and bias in the header (``GAIN``
   e-/ADU, ``RDNOISE`` e-, ``BIASLVL`` ADU: opnav's FITS frames and many cameras'), the stars are
   fitted again (:func:`opnav.image.centroid.centroid`, same 7-px stamps) with that noise model,
   whose covariance is then the Cramer-Rao bound of the star (on rendered 12-degree frames the
   scatter over 20 noise draws of one frame is 0.98-1.08 of the reported sigma from 60,000 e- to
   700 e-, and the sigma 1.00-1.05 of the bound). A frame without them (PNG, JPEG, a bare FITS)
   gets a noise model estimated from the stars' stamps (:func:`frame_noise`): the background
   level and sigma from the low side of the pooled rings around the stars (faint stars' light only
   raises pixels), and the gain that makes the median chi-square per dof of the brighter half of
   the unblended stars' fits its expected value (a median: a cosmic-ray hit among them does not
   move it; the blends are found with a first model from all the stars). On two rendered
   20-degree frames with the keywords removed: gain 1.03 and 1.15 against 1. The extraction's own fitted noise model pools every stamp by least squares, which
   saturated stars and blends throw off (9 to 18,000 times the true background variance on six
   rendered 12-degree frames).
2. **Saturation.** A star with a pixel of its stamp at the saturation level is left out: its
   centroid comes from the wings and the charge bled along its column, pulled by tenths of a pixel
   (44 sigma on rendered frames) in ways no covariance of the fit says. A calibration has stars to spare.
3. **Blends.** Each star's fit is predicted on a noise-free copy of its stamp holding its catalog
   neighbours (:func:`blend_bias`: every catalog star whose PSF reaches the stamp, its flux scaled
   from the star's fitted flux by the catalog magnitudes) and fitted by the same estimator; a star
   whose predicted pull exceeds ``max_blend_sigma`` of its own centroid sigma is left out. The pull
   is a bias, the same in every frame the pair is seen in, so no number of frames averages it down;
   a fixed magnitude or distance cut cannot say when it matters, since a bright star's sigma is
   a tenth of a faint one's. (The fits' own chi-square is no test here: on a wide field every stamp
   holds catalog stars too faint to pull a centroid but not too faint to fail
   :func:`opnav.image.centroid.psf_like`, which on rendered 20-degree frames refused 40 % of the
   stars; a cosmic-ray hit is an outlier the calibration's robust fit rejects.)

Pixel coordinates follow docs/conventions.md (x column, y row, (0, 0) the first pixel's centre).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from .centroid import centroid
from .sources import header_number

#: Stamp side of the calibration fits, px (the extraction's, :mod:`opnav.image.extract`).
STAMP_PX = 7
#: Default largest predicted blend pull a kept star may have, in its own centroid sigmas (module step 3):
#: a pull of 0.3 sigma adds at most 0.09 to a star's chi-square per axis, and the catalog magnitudes
#: (not in the camera's band) may be off by a magnitude, a factor 2.5 in the pull.
MAX_BLEND_SIGMA = 0.3
#: A neighbour's Gaussian PSF reaches the stamp from this many PSF sigmas beyond its edge.
_REACH_SIGMAS = 5.0


@dataclass(frozen=True)
class DetectorNoise:
    """A frame's detector noise model from its header (module step 1).

    Attributes
    ----------
    read_noise_e : float
        RMS read noise per pixel, electrons.
    gain_e_per_adu : float
        Electrons per ADU.
    bias_adu : float
        Electronic offset, ADU.
    """

    read_noise_e: float
    gain_e_per_adu: float
    bias_adu: float


def header_noise(header, frame: str) -> DetectorNoise | None:
    """The noise model of ``GAIN``, ``RDNOISE`` and ``BIASLVL`` (0 when absent) of a FITS header; None
    without a positive ``GAIN`` and a non-negative ``RDNOISE``.

    Raises
    ------
    InputError
        A keyword present that is not a finite number (names ``frame`` and the keyword).
    """
    if header is None:
        return None
    gain = header_number(header, "GAIN", frame)
    read_noise = header_number(header, "RDNOISE", frame)
    if gain is None or read_noise is None or gain <= 0.0 or read_noise < 0.0:
        return None
    bias = header_number(header, "BIASLVL", frame)
    return DetectorNoise(read_noise, gain, 0.0 if bias is None else bias)


#: Fewest stars a noise model is estimated from (:func:`frame_noise`).
MIN_NOISE_STARS = 8
#: Range of the estimated gain, e-/ADU (:func:`frame_noise`): at its top the stars' shot noise is nil.
_GAIN_RANGE = (1e-3, 1e4)


def frame_noise(image: np.ndarray, xy: np.ndarray, usable: np.ndarray) -> DetectorNoise | None:
    """A noise model estimated from stars' stamps, for a frame whose header does not give it (module step 1).

    Background level and sigma from the low side of the pooled one-pixel rings around the stars,
    5 PSF widths out (beyond their own wings) and at least just outside the ``STAMP_PX`` stamp: sigma the distance of the 2.3rd percentile (-2 sigma) from the 15.9th
    (-1 sigma), the level one sigma above the latter (ADU; a read noise and a bias that hold the
    background's own shot noise); the catalog neighbours' light is the blend test's (module step 3). Gain: bisection (in its logarithm, over ``_GAIN_RANGE``)
    for the gain at which the median chi-square per dof of the brighter half of the ``usable``
    stars' fits equals the median of chi-square(dof) / dof; the fits' chi-square falls as the gain
    rises (less shot noise). Returns None with fewer than ``MIN_NOISE_STARS`` usable stars or a
    ring without spread (a clipped or synthetic frame).
    """
    stars = xy[usable]
    if len(stars) < MIN_NOISE_STARS:
        return None
    # a first fit (background noise alone, from the frame's robust spread) for the PSF width and the fluxes
    spread0 = 1.482602218505602 * float(np.median(np.abs(image - np.median(image))))
    probe = centroid(image, stars, window=STAMP_PX, read_noise_e=max(spread0, 1e-9) * _GAIN_RANGE[1],
                     gain_e_per_adu=_GAIN_RANGE[1], bias_adu=float(np.median(image)))
    width = probe.sigma_px[probe.ok]
    if len(width) == 0:
        return None
    # rings beyond the stars' own wings: 5 PSF widths out, at least just outside the stamp
    half = max(STAMP_PX // 2 + 1, int(math.ceil(5.0 * float(np.median(width)))))
    side = np.arange(-half, half + 1)
    ring = (np.abs(side)[:, None] == half) | (np.abs(side)[None, :] == half)
    rows = np.clip(np.rint(stars[:, 1]).astype(int)[:, None, None] + side[:, None], 0, image.shape[0] - 1)
    cols = np.clip(np.rint(stars[:, 0]).astype(int)[:, None, None] + side[None, :], 0, image.shape[1] - 1)
    values = image[rows, cols][:, ring].ravel()
    # the low side of the rings' distribution: light of stars too faint to detect (on a wide field they
    # are in every ring) only raises pixels, so the median and the spread above it are not the detector's
    low, mid = np.percentile(values, [100.0 * ndtr(-2.0), 100.0 * ndtr(-1.0)])
    spread = float(mid - low)
    level = float(mid) + spread
    if not spread > 0.0:
        return None
    # the brighter half carries the shot noise that sets the gain
    bright = stars[np.argsort(-np.nan_to_num(probe.flux, nan=-np.inf))[: max(MIN_NOISE_STARS, len(stars) // 2)]]

    def excess(log_gain: float) -> float:
        gain = math.exp(log_gain)
        fit = centroid(image, bright, window=STAMP_PX, read_noise_e=spread * gain, gain_e_per_adu=gain,
                       bias_adu=level)
        ok = fit.ok & np.isfinite(fit.chi2) & (fit.dof > 0)
        if not ok.any():
            return math.nan
        dof = fit.dof[ok]
        # median of chi-square(k) / k, Wilson-Hilferty: (1 - 2 / (9 k))^3
        return float(np.median(fit.chi2[ok] / dof) - np.median((1.0 - 2.0 / (9.0 * dof)) ** 3))

    lo, hi = math.log(_GAIN_RANGE[0]), math.log(_GAIN_RANGE[1])
    if not excess(hi) > 0.0:  # the background's variance alone explains the fits: no shot noise to see
        gain = _GAIN_RANGE[1]
    elif excess(lo) > 0.0:  # even the most shot noise does not: keep the most (the widest covariances)
        gain = _GAIN_RANGE[0]
    else:
        for _ in range(20):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if excess(mid) > 0.0 else (mid, hi)  # too much chi-square: a lower gain
        gain = math.exp(0.5 * (lo + hi))
    return DetectorNoise(spread * gain, gain, level)


@dataclass(frozen=True)
class CalibrationCentroids:
    """What :func:`calibration_centroids` gives, row for row with the seeds passed in.

    Attributes
    ----------
    xy : (N, 2) array
        Centroids, px (NaN where the fit failed).
    cov : (N, 2, 2) array
        Their covariances, px^2.
    keep : (N,) bool array
        The stars a calibration should use (module steps 1-3).
    saturated, failed, blended : (N,) bool arrays
        Why a star is left out (a star may have several reasons): a pixel at saturation, the fit
        failed, a predicted blend pull above ``max_blend_sigma``.
    blend_bias_px : (N, 2) array
        Predicted pull of the catalog neighbours on each centroid, px (module step 3).
    noise : DetectorNoise or None
        The noise model the stars were fitted again with (module step 1); None: the extraction's
        centroids were kept (too few stars to estimate one).
    noise_source : str
        ``"header"``, ``"frame"`` (:func:`frame_noise`) or ``"none"``.
    """

    xy: np.ndarray
    cov: np.ndarray
    keep: np.ndarray
    saturated: np.ndarray
    failed: np.ndarray
    blended: np.ndarray
    blend_bias_px: np.ndarray
    noise: DetectorNoise | None
    noise_source: str

    @property
    def refitted(self) -> bool:
        """The stars were fitted again with a noise model (module step 1)."""
        return self.noise is not None


def _saturated(image: np.ndarray, xy: np.ndarray, level: float | None) -> np.ndarray:
    """Whether any pixel of each star's ``STAMP_PX`` stamp reaches ``level`` (module step 2)."""
    if level is None or len(xy) == 0:
        return np.zeros(len(xy), bool)
    half = STAMP_PX // 2
    offsets = np.arange(-half, half + 1)
    cols = np.clip(np.rint(xy[:, 0]).astype(int)[:, None] + offsets, 0, image.shape[1] - 1)
    rows = np.clip(np.rint(xy[:, 1]).astype(int)[:, None] + offsets, 0, image.shape[0] - 1)
    return np.any(image[rows[:, :, None], cols[:, None, :]] >= level, axis=(1, 2))


def _gaussian_stamps(centres: np.ndarray, flux: np.ndarray, sigma_px: float, size: int) -> np.ndarray:
    """(N, size, size) pixel-integrated circular Gaussians of ``flux`` at ``centres`` (tile pixels, x y)."""
    edges = np.arange(size + 1) - 0.5
    scale = 1.0 / sigma_px
    fx = np.diff(ndtr((edges[None, :] - centres[:, 0, None]) * scale), axis=1)
    fy = np.diff(ndtr((edges[None, :] - centres[:, 1, None]) * scale), axis=1)
    return flux[:, None, None] * fy[:, :, None] * fx[:, None, :]


def blend_bias(xy: np.ndarray, flux_adu: np.ndarray, background_adu: np.ndarray, neighbours: list[np.ndarray],
               psf_sigma_px: float, noise: DetectorNoise) -> np.ndarray:
    """Predicted pull of neighbours on each star's centroid, px (module step 3).

    Each star and its neighbours are drawn noise-free (pixel-integrated Gaussians of the frame's
    PSF width) on a tile of their own, the star at its own pixel phase, and fitted by
    :func:`opnav.image.centroid.centroid` with ``noise``'s weights; the same tile without the
    neighbours is fitted too, and the difference of the two fits is the pull (whatever the
    estimator does on a lone star cancels).

    Parameters
    ----------
    xy : (N, 2) array
        The stars' centroids, px.
    flux_adu : (N,) array
        Their fitted fluxes above the background, ADU.
    background_adu : (N,) array
        Their local backgrounds, ADU (the tile's level, which sets the weights).
    neighbours : list of N (M_n, 3) arrays
        Each star's neighbours: offset from the star (x, y, px) and flux, ADU.
    psf_sigma_px : float
        Gaussian PSF sigma, px.
    noise : DetectorNoise
        The weights' noise model.

    Returns
    -------
    (N, 2) array
        Fit with neighbours less fit without, px; 0 for a star without neighbours.
    """
    n = len(xy)
    bias = np.zeros((n, 2))
    crowded = np.flatnonzero([len(m) > 0 for m in neighbours])
    if len(crowded) == 0:
        return bias
    half = STAMP_PX // 2 + int(math.ceil(_REACH_SIGMAS * psf_sigma_px)) + 1
    size = 2 * half + 1
    phase = xy[crowded] - np.rint(xy[crowded])
    centre = half + phase  # each star at its own pixel phase in the middle of its tile
    tiles = _gaussian_stamps(centre, flux_adu[crowded], psf_sigma_px, size)
    lone = tiles.copy()
    for k, i in enumerate(crowded):
        others = neighbours[i]
        tiles[k] += _gaussian_stamps(centre[k] + others[:, :2], others[:, 2], psf_sigma_px, size).sum(axis=0)
    # tiles side by side in one canvas (with and without the neighbours), one batched fit
    count = 2 * len(crowded)
    stack = np.concatenate([tiles, lone]) + background_adu[np.r_[crowded, crowded], None, None]
    canvas = stack.transpose(1, 0, 2).reshape(size, count * size)
    shift = np.c_[np.arange(count) * size, np.zeros(count)]
    fit = centroid(canvas, np.tile(centre, (2, 1)) + shift, window=STAMP_PX, read_noise_e=noise.read_noise_e,
                   gain_e_per_adu=noise.gain_e_per_adu, bias_adu=noise.bias_adu)
    in_tile = fit.xy - shift
    pulled, alone = in_tile[: len(crowded)], in_tile[len(crowded):]
    # a fit the neighbour wrecks (no convergence) is a pull as large as the stamp
    bias[crowded] = np.where(np.isfinite(pulled - alone), pulled - alone, float(STAMP_PX))
    return bias


def calibration_centroids(image: np.ndarray, meta, xy: np.ndarray, cov: np.ndarray, *, neighbours: list[np.ndarray],
                          max_blend_sigma: float = MAX_BLEND_SIGMA, frame: str = "") -> CalibrationCentroids:
    """The matched stars' centroids with honest covariances, and which of them to calibrate with (module docstring).

    Parameters
    ----------
    image : (H, W) array
        The frame, ADU.
    meta : opnav.image.io.ImageMeta
        Its header (noise keywords), saturation level and invalid pixels.
    xy, cov : (N, 2) and (N, 2, 2) arrays
        The extraction's centroids (px) and covariances (px^2) of the matched stars.
    neighbours : list of N (M_n, 3) arrays
        Each star's catalog neighbours whose PSF may reach its stamp (those farther than the
        stamp's half-diagonal and 5 PSF widths are ignored): offset from the star's predicted
        pixel (x, y, px) and the magnitude difference (neighbour less star).
    max_blend_sigma : float
        Largest predicted blend pull kept, in the star's centroid sigmas (module step 3).
    frame : str
        The frame's name in errors.
    """
    xy = np.asarray(xy, float)
    seeds = xy
    level = meta.saturation_adu
    saturated = _saturated(image, xy, level)
    noise, source = header_noise(meta.header, frame), "header"
    if noise is None:
        source = "frame"
        noise = frame_noise(image, xy, ~saturated & np.all(np.isfinite(xy), axis=1))
        if noise is not None:
            # the gain again from the stars the first model finds clear of blends: a blend's fit has
            # chi-square to spare whatever the gain, and on a wide field most stars have one
            _, _, failed, _, blended = _refit(image, meta, seeds, saturated, neighbours, noise, max_blend_sigma)
            noise = frame_noise(image, seeds, ~(saturated | failed | blended)) or noise
    if noise is None or len(xy) == 0:
        failed = ~np.all(np.isfinite(xy), axis=1)
        return CalibrationCentroids(xy, cov, ~(saturated | failed), saturated, failed, np.zeros(len(xy), bool),
                                    np.zeros((len(xy), 2)), None, "none" if noise is None else source)
    xy, cov, failed, bias, blended = _refit(image, meta, seeds, saturated, neighbours, noise, max_blend_sigma)
    keep = ~(saturated | failed | blended)
    return CalibrationCentroids(xy, cov, keep, saturated, failed, blended, bias, noise, source)


def _refit(image, meta, xy, saturated, neighbours, noise: DetectorNoise, max_blend_sigma: float):
    """``(xy, cov, failed, blend pull, blended)`` of the stars fitted with ``noise`` (module steps 1 and 3)."""
    fit = centroid(image, xy, window=STAMP_PX, read_noise_e=noise.read_noise_e, gain_e_per_adu=noise.gain_e_per_adu,
                   bias_adu=noise.bias_adu, saturation_adu=meta.saturation_adu, invalid=meta.invalid)
    xy, cov, failed = fit.xy, fit.cov, ~fit.ok
    bias = np.zeros((len(xy), 2))
    blended = np.zeros(len(xy), bool)
    width = fit.sigma_px[fit.ok & ~saturated]
    if len(width) == 0:
        return xy, cov, failed, bias, blended
    psf_sigma = float(np.median(width))
    # a neighbour's light reaches the stamp's corner from _REACH_SIGMAS PSF widths beyond it
    reach = (STAMP_PX // 2) * math.sqrt(2.0) + _REACH_SIGMAS * psf_sigma
    offsets = []
    for i, m in enumerate(neighbours):
        m = m[np.hypot(m[:, 0], m[:, 1]) <= reach] if len(m) else np.zeros((0, 3))
        offsets.append(np.c_[m[:, :2], fit.flux[i] * 10.0 ** (-0.4 * m[:, 2])])
    rows = np.flatnonzero(~failed)
    bias[rows] = blend_bias(xy[rows], fit.flux[rows], fit.background[rows], [offsets[i] for i in rows], psf_sigma,
                            noise)
    sigma = np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], axis=1))
    with np.errstate(invalid="ignore"):
        blended = np.any(np.abs(bias) > max_blend_sigma * sigma, axis=1)
    return xy, cov, failed, bias, blended
