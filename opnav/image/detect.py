"""Source detection: background, threshold, connected components, rejection, de-blending.

Pixel convention: docs/conventions.md ((0, 0) is the centre of the first pixel,
x = column, y = row). Algorithm, step by step:

1. **Background and noise** (:func:`estimate_background`). The frame is cut
   into ``tile_px`` square tiles (of ``SAMPLED_TILE_PX`` or more, one pixel of
   each 2 x 2 block is read, cycling through the block's four positions); in
   each, values are sigma-clipped
   (``clip_sigma`` x robust sigma, iterated) and the median of the survivors
   is the level, their standard deviation divided by the standard deviation
   of a unit normal truncated at +-``clip_sigma`` is the noise. A tile whose
   sky is clipped (``CLIPPED_TILE_FRACTION`` of it on its lowest value: an
   8-bit camera whose offset puts the sky at ~1 ADU) or quantised in steps of
   more than twice its noise is measured instead by a censored fit of a normal
   distribution to the empirical distribution of its unclipped values (mean
   and sigma; :func:`_censored_fit`), and no noise is taken below the rounding
   noise of the frame's value step, q / sqrt(12). A 3x3 median
   filter over the tile grid removes tiles spoiled by a bright object, and
   both maps are bilinearly interpolated between tile centres to every pixel.
2. **Rejection of hot pixels and cosmic rays.** They are sharper than any PSF
   the optics can form. With P the background-subtracted value of a pixel and
   S_x, S_y the sums of its two horizontal and two vertical neighbours, a
   Gaussian PSF of sigma >= 0.5 px gives min(S_x, S_y) >= 0.46 P at any pixel
   of the star and any pixel phase, while a hot pixel has both sums near zero
   and every pixel of a track has the sum across the track near zero. Pixels
   more than ``threshold_sigma`` noise sigmas above the background with
   min(S_x, S_y) < ``min_neighbour_ratio`` P are set to the background and
   reported in ``Detections.rejected`` (pass them to the centroider as
   invalid). Saturated pixels are tested too, except those with a saturated left or right
   neighbour (a clipped star core is at least two pixels wide), so a hot pixel clipped at the
   top of an 8-bit stretch, or one bloomed into its column, is rejected.
   Two adjacent hot pixels (a few a frame in a detector with hundreds, and bloomed into a
   2 x 3 block when they fill their wells below the file's range) pass that test: each is the
   other's neighbour. So a pixel above ``PAIR_TEST_MIN_SNR`` noise sigmas is also tested with
   its brighter neighbour along x, and along y: the two pixels beyond that pair, O, hold at least
   0.096 P for a Gaussian PSF of sigma >= 0.5 px at any phase (the least when the star is
   centred on the pair's common edge), and a pixel with O < ``PAIR_OUTER_RATIO`` P is rejected.
   (Below that signal-to-noise ratio the noise of O would reject faint stars.) Saturated pixels
   and their neighbours are left to the rules above: a planet's bloom trail can be two columns wide.
3. **Matched filter and threshold.** The background-subtracted frame is
   smoothed with a Gaussian of ``smooth_sigma_px`` cut at ``FILTER_RADIUS_SIGMAS``
   (close to the optimal matched filter for a star, and it blunts JPEG block
   edges and single-pixel noise); a pixel is "on" where the smoothed value exceeds
   ``threshold_sigma`` times the smoothed noise
   (noise x sqrt(sum kernel^2)).
4. **Connected components** of the "on" pixels (8-connectivity), labelled by a
   union-find over them in the threshold's pass (:func:`_detection_components`).
5. **Peaks and de-blending.** Local maxima at least ``deblend_separation_px``
   apart of the background-subtracted frame (smoothed by ``deblend_smooth_px``,
   default none: the detection filter would merge pairs closer than about two
   of its widths) are candidate seeds. Inside one
   component a fainter peak is kept as a separate source only if the smoothed
   profile along the straight line to every brighter peak dips below it by
   more than ``deblend_contrast`` of its height and by 3 noise sigmas; kept
   pairs are flagged ``FLAG_BLENDED``. Components with saturated pixels are not
   split (a clipped core is flat). Components larger than
   ``max_point_area_px`` are extended bodies (flag ``FLAG_EXTENDED``): one seed
   at their flux-weighted centre, never split.
6. **Flags.** ``FLAG_SATURATED`` (a pixel at or above the saturation level),
   ``FLAG_EDGE`` (seed within ``edge_margin_px`` of the border),
   ``FLAG_INVALID`` (the component touches a pixel that was NaN in the file).

A constant (blank or black) frame and a frame more than
``max_saturated_fraction`` saturated raise :class:`opnav.errors.FrameError`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.special import ndtr

from ..compiled import kernel
from ..errors import FrameError, InputError

FLAG_SATURATED = 1
FLAG_EDGE = 2
FLAG_BLENDED = 4
FLAG_EXTENDED = 8
FLAG_INVALID = 16
#: Detection threshold multiplier for lossy (JPEG) frames. The measured noise of the filtered frame
#: (:func:`_detection_components`) already carries the blocks' correlation, while the square-root
#: stretch of a consumer camera's 8-bit frame flattens a star's core against the noise: measured on
#: the frames of ``benchmarks/starid_real.py`` (q50-q90, 6-11 degree fields), 0.8 (4 sigma) finds
#: 1.4 times the stars 1.0 finds, with 0-2 false sources a frame, fainter than the stars; a
#: false source costs the solver nothing but a place at the end of the list.
LOSSY_THRESHOLD_FACTOR = 0.8
#: Hot-pixel test of lossy frames (module step 2): JPEG at quality 50 spreads a hot pixel so that
#: min(S_x, S_y) reaches 0.2-0.75 of its peak, while a star of sigma >= 1 px keeps >= 1.0
#: (>= 1.2 after the square-root stretch of an 8-bit frame).
LOSSY_NEIGHBOUR_RATIO = 0.8
#: Half-width, px, of the ring of pixels around a rejected saturated spike of a
#: lossy frame also rejected.
LOSSY_HIT_HALO_PX = 3
#: Smallest per-pixel noise, ADU, assumed for a lossy frame (8-bit JPEG: quantisation and blocks).
LOSSY_NOISE_FLOOR_ADU = 1.0


@dataclass(frozen=True)
class DetectOptions:
    """Settings of :func:`detect` (see the module docstring for their roles)."""

    threshold_sigma: float = 5.0
    tile_px: int = 64
    clip_sigma: float = 3.0
    smooth_sigma_px: float = 1.0
    min_area_px: int = 1
    max_point_area_px: int = 400
    min_neighbour_ratio: float = 0.25
    deblend: bool = True
    deblend_separation_px: int = 1
    deblend_smooth_px: float = 0.0
    deblend_contrast: float = 0.1
    edge_margin_px: int = 3
    max_saturated_fraction: float = 0.5

    def __post_init__(self) -> None:
        positive = ("threshold_sigma", "tile_px", "clip_sigma", "smooth_sigma_px", "max_point_area_px",
                    "deblend_separation_px", "max_saturated_fraction")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"DetectOptions.{name} must be a positive number, got {value!r}")
        if self.tile_px < 8:
            raise InputError(f"DetectOptions.tile_px must be >= 8, got {self.tile_px}")
        for name in ("min_area_px", "deblend_smooth_px", "min_neighbour_ratio", "deblend_contrast", "edge_margin_px"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"DetectOptions.{name} must be >= 0, got {value!r}")


#: The valid mask of a frame without invalid pixels, for kernels that read a mask of the frame's shape only.
_ALL_VALID = np.ones((1, 1), bool)
#: The invalid mask of such a frame (:func:`_tile_band`).
_ALL_INVALID_FREE = np.zeros((1, 1), bool)

#: Two-pixel sharpness test (module docstring, step 2): the least signal-to-noise ratio tested and
#: the least ratio of the two pixels beyond a pair to the pixel (a third of a 0.5 px PSF's 0.096).
PAIR_TEST_MIN_SNR = 100.0
PAIR_OUTER_RATIO = 0.03


@dataclass(frozen=True)
class Background:
    """Background level and per-pixel noise (1 sigma) of a frame, in its units (ADU).

    Held as the values of its tiles; the (H, W) maps ``level`` and ``noise`` interpolate them
    bilinearly between tile centres (module step 1) and are made on first use. Detection
    interpolates the level inside its residual pass instead of keeping a full-frame map (8 MB at
    1 MP), and :meth:`window` gives both maps' values in a box.

    Attributes
    ----------
    level_tiles, noise_tiles : (TY, TX) float
        Level and noise of each tile, ADU.
    shape : (int, int)
        Frame shape (H, W), px.
    tile_px : int
        Tile side, px; tile (i, j)'s centre is at row ``(i + 0.5) tile_px - 0.5``, column
        ``(j + 0.5) tile_px - 0.5``, and the maps are flat beyond the outer centres.
    noise_floor : float
        Least noise, ADU: the noise map is ``max(interpolated noise, noise_floor)``.
    """

    level_tiles: np.ndarray
    noise_tiles: np.ndarray
    shape: tuple[int, int]
    tile_px: int
    noise_floor: float = 0.0

    @functools.cached_property
    def _weights(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(iy, wy, ix, wx): each row's and column's tile-centre interval and weight."""
        return _tile_weights(tuple(self.level_tiles.shape), (int(self.shape[0]), int(self.shape[1])),
                             int(self.tile_px))

    @functools.cached_property
    def _level_padded(self) -> np.ndarray:
        return _edge_padded(self.level_tiles)

    @functools.cached_property
    def _noise_padded(self) -> np.ndarray:
        return _edge_padded(self.noise_tiles)

    @functools.cached_property
    def level(self) -> np.ndarray:
        """Background level map (H, W), ADU."""
        return _bilinear(self.level_tiles, self.shape, self.tile_px)

    @functools.cached_property
    def noise(self) -> np.ndarray:
        """Noise map (H, W), ADU, 1 sigma."""
        noise = _bilinear(self.noise_tiles, self.shape, self.tile_px)
        return np.maximum(noise, self.noise_floor, out=noise) if self.noise_floor > 0 else noise

    def window(self, rows: slice, cols: slice) -> tuple[np.ndarray, np.ndarray]:
        """(level, noise) maps of the box ``[rows, cols]`` (slices, any step), ADU: the values of
        ``level[rows, cols]`` and ``noise[rows, cols]`` without making the full maps."""
        r = np.arange(self.shape[0])[rows]
        c = np.arange(self.shape[1])[cols]
        iy, wy, ix, wx = self._weights
        level = _interpolate(self._level_padded, iy[r], wy[r], ix[c], wx[c])
        noise = _interpolate(self._noise_padded, iy[r], wy[r], ix[c], wx[c])
        return level, (np.maximum(noise, self.noise_floor) if self.noise_floor > 0 else noise)

    def noise_window(self, rows: slice, cols: slice) -> np.ndarray:
        """The noise map of the box ``[rows, cols]`` (slices, any step), ADU: :meth:`window`'s second map
        alone."""
        r = np.arange(self.shape[0])[rows]
        c = np.arange(self.shape[1])[cols]
        iy, wy, ix, wx = self._weights
        noise = _interpolate(self._noise_padded, iy[r], wy[r], ix[c], wx[c])
        return np.maximum(noise, self.noise_floor) if self.noise_floor > 0 else noise

    def with_noise_floor(self, floor: float) -> Background:
        """The same background with the noise map raised to at least ``floor`` ADU."""
        return replace(self, noise_floor=max(self.noise_floor, float(floor)))

    def level_interpolation(self) -> tuple[np.ndarray, ...]:
        """(padded level grid, iy, wy, ix, wx) for a compiled pass that interpolates the level map
        row by row (:func:`_map_row`)."""
        return (self._level_padded, *self._weights)

    def noise_interpolation(self) -> tuple:
        """(padded noise grid, iy, wy, ix, wx, noise_floor) for a compiled pass that interpolates the
        noise map row by row (:func:`_noise_row`) instead of reading the (H, W) map."""
        return (self._noise_padded, *self._weights, float(self.noise_floor))

    def noise_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """``noise[rows, cols]`` (integer arrays of one shape), ADU, without making the map: the
        interpolation's arithmetic at those pixels alone."""
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        if self.noise_tiles.shape == (1, 1):
            values = np.full(rows.shape, float(self.noise_tiles[0, 0]))
        else:
            grid = self._noise_padded
            iy, wy, ix, wx = self._weights
            r, c = iy[rows], ix[cols]
            # _interpolate's order: along x at the two rows, then along y
            top = grid[r, c] * (1.0 - wx[cols]) + grid[r, c + 1] * wx[cols]
            bottom = grid[r + 1, c] * (1.0 - wx[cols]) + grid[r + 1, c + 1] * wx[cols]
            values = top * (1.0 - wy[rows]) + bottom * wy[rows]
        return np.maximum(values, self.noise_floor) if self.noise_floor > 0 else values


@dataclass(frozen=True)
class Detections:
    """Sources found by :func:`detect`, brightest first.

    Attributes
    ----------
    xy : (N, 2) float
        Seed positions (x = column, y = row), px; good to ~0.2 px, refine with
        :func:`opnav.image.centroid.centroid`.
    peak : (N,) float
        Background-subtracted peak pixel value, ADU.
    flux : (N,) float
        Background-subtracted sum over the component, ADU (shared by blended seeds).
    area : (N,) int
        Component area above threshold, px.
    flags : (N,) int
        Bit mask of ``FLAG_*``.
    label : (N,) int
        Component label of each seed in ``labels``.
    labels : (H, W) int32
        Component map (0 = background).
    background : Background
        The background model used.
    rejected : (H, W) bool
        Pixels rejected as hot pixels or cosmic-ray hits.
    n_rejected : int
        Connected groups of rejected pixels (hits).
    snr : (N,) float
        Detection signal-to-noise ratio of each seed: the detection-filtered frame (module
        step 3) at the seed's pixel over its filtered noise, the measured correlation included;
        the quantity the threshold ``threshold_sigma`` is applied to.
    boxes : (M, 4) int32 or None
        Bounding box of each component of ``labels`` (row ``k`` for label ``k``; row 0 the
        background), in OpenCV's layout: left column, top row, width, height, px; None when
        nothing was detected.
    brightest : (3,) float or None
        The frame's three largest pixel values (every pixel, invalid ones included), largest
        first, ADU; NaN when the frame holds a NaN (:func:`saturation_plateau` reads its flat top
        from them without a pass over the frame).
    """

    xy: np.ndarray
    peak: np.ndarray
    flux: np.ndarray
    area: np.ndarray
    flags: np.ndarray
    label: np.ndarray
    labels: np.ndarray
    background: Background
    rejected: np.ndarray
    n_rejected: int
    snr: np.ndarray
    boxes: np.ndarray | None = None
    brightest: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.xy)


def _axis_weights(n: int, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pos = np.arange(n, dtype=float)
    if len(centres) == 1:
        return np.zeros(n, dtype=int), np.zeros(n)
    idx = np.clip(np.searchsorted(centres, pos) - 1, 0, len(centres) - 2)
    w = np.clip((pos - centres[idx]) / (centres[idx + 1] - centres[idx]), 0.0, 1.0)
    return idx, w


def _bilinear(grid: np.ndarray, shape: tuple[int, int], tile: int) -> np.ndarray:
    """The tile grid interpolated to every pixel, tile centres at ``(i + 0.5) * tile - 0.5``, flat beyond
    the outer centres."""
    if grid.shape == (1, 1):
        # one tile (a crop around a target): every weight is 0, the map is the tile's value (the
        # interpolation's g (1 - 0) + g 0 exactly), without the padding and the kernel's passes
        return np.full(shape, float(grid[0, 0]))
    return _interpolate(_edge_padded(grid), *_tile_weights(grid.shape, shape, tile))


def _edge_padded(grid: np.ndarray) -> np.ndarray:
    """``numpy.pad(grid, ((0, 1), (0, 1)), mode="edge")`` as float, without its ~90 us of set-up (a
    tracking crop's background is a 1 x 1 grid)."""
    rows, cols = grid.shape
    out = np.empty((rows + 1, cols + 1))
    out[:rows, :cols] = grid
    out[rows, :cols] = grid[-1]
    out[:, cols] = out[:, cols - 1]
    return out


@functools.lru_cache(maxsize=8)
def _tile_weights(grid_shape: tuple[int, int], shape: tuple[int, int], tile: int) -> tuple[np.ndarray, ...]:
    """(iy, wy, ix, wx) of :func:`_interpolate` for a (TY, TX) grid of ``tile``-px tiles over a frame of ``shape``,
    kept for the next frame of that shape (making them was ~0.03 ms of every 1 MP frame): shared, never
    written to (not made read-only: the compiled passes are typed for writable arrays)."""
    iy, wy = _axis_weights(shape[0], (np.arange(grid_shape[0]) + 0.5) * tile - 0.5)
    ix, wx = _axis_weights(shape[1], (np.arange(grid_shape[1]) + 0.5) * tile - 0.5)
    return iy, wy, ix, wx


@kernel
def _interpolate(grid, iy, wy, ix, wx):  # pragma: no cover - compiled
    """``columns = grid[:, ix] (1 - wx) + grid[:, ix + 1] wx``, then the same along y, pixel by pixel."""
    along_x = _along_x(grid, ix, wx)
    out = np.empty((iy.size, ix.size))
    for r in range(iy.size):
        _map_row(along_x, iy, wy, r, out[r])
    return out


@kernel(inline=True)
def _along_x(grid, ix, wx):  # pragma: no cover - compiled
    """The padded tile grid interpolated along x to every column, (TY + 1, W): the first step of
    :func:`_interpolate`, made once per pass (the rows then interpolate along y in loops that
    vectorise; gathering the tiles column by column in every row was a third of a pass)."""
    out = np.empty((grid.shape[0], ix.size))
    for i in range(grid.shape[0]):
        for c in range(ix.size):
            out[i, c] = grid[i, ix[c]] * (1.0 - wx[c]) + grid[i, ix[c] + 1] * wx[c]
    return out


@kernel(inline=True)
def _map_row(along_x, iy, wy, r, out):  # pragma: no cover - compiled
    """Row ``r`` of a background map into ``out`` (W,), with :func:`_interpolate`'s arithmetic, from the
    grid interpolated along x (:func:`_along_x`)."""
    low, below = 1.0 - wy[r], wy[r]
    first, second = along_x[iy[r]], along_x[iy[r] + 1]
    for c in range(out.size):
        out[c] = first[c] * low + second[c] * below


@kernel(inline=True)
def _noise_row(along_x, iy, wy, floor, r, out):  # pragma: no cover - compiled
    """Row ``r`` of :attr:`Background.noise` into ``out`` (W,): :func:`_map_row`, then the floor."""
    _map_row(along_x, iy, wy, r, out)
    if floor > 0.0:
        for c in range(out.size):
            out[c] = max(out[c], floor)


@kernel
def _residual(image, valid, any_invalid, level_grid, iy, wy, ix, wx):  # pragma: no cover - compiled
    """``image - Background.level`` in single precision (the difference taken in double), 0 at pixels
    not ``valid`` (read only when ``any_invalid``)."""
    rows, cols = image.shape
    out = np.empty((rows, cols), np.float32)
    along_x, level = _along_x(level_grid, ix, wx), np.empty(cols)
    for r in range(rows):
        _map_row(along_x, iy, wy, r, level)
        for c in range(cols):
            out[r, c] = image[r, c] - level[c]
        if any_invalid:
            for c in range(cols):
                if not valid[r, c]:
                    out[r, c] = 0.0
    return out


@functools.lru_cache(maxsize=16)
def _truncated_sd(clip_sigma: float) -> float:
    """Standard deviation of a unit normal truncated at +-``clip_sigma``: the closed form
    ``1 - 2 c phi(c) / (2 Phi(c) - 1)`` of its variance: ``scipy.stats.truncnorm.var`` within one unit
    in the last place (the same bits at the default 3), without importing ``scipy.stats``, a quarter
    of a second at start-up."""
    c = float(clip_sigma)
    density = math.exp(-0.5 * c * c) / math.sqrt(2.0 * math.pi)
    return math.sqrt(1.0 - 2.0 * c * density / (2.0 * ndtr(c) - 1.0))


def estimate_background(
    image: np.ndarray, *, tile_px: int = 64, clip_sigma: float = 3.0, invalid: np.ndarray | None = None
) -> Background:
    """Sigma-clipped, tiled, interpolated background level and noise.

    Parameters
    ----------
    image : (H, W) array
        Frame, ADU.
    tile_px : int
        Tile side, px (clipped to the frame size).
    clip_sigma : float
        Clipping threshold in robust sigmas.
    invalid : (H, W) bool array, optional
        Pixels to ignore.

    Returns
    -------
    Background
        Level and 1-sigma noise maps, (H, W), ADU.
    """
    image = np.asarray(image, dtype=float)
    if invalid is not None and np.shape(invalid) != image.shape:
        raise InputError(f"invalid mask has shape {np.shape(invalid)}, the frame {image.shape}")
    invalid = np.zeros((1, 1), bool) if invalid is None else np.ascontiguousarray(invalid, dtype=bool)
    tile, bands = _tile_bands(image.shape, tile_px)
    for row in range(bands.shape[0]):
        _tile_band(image, invalid, tile, row, bands[row])
    return _background_of_bands(bands, image.shape, tile, clip_sigma)


def _tile_bands(shape: tuple[int, int], tile_px: int) -> tuple[int, np.ndarray]:
    """(tile side px, uninitialised (TY, TX, values a tile) buffer) of :func:`estimate_background`'s tiles
    over a frame of ``shape``, for :func:`_tile_band`. One row of tiles at a time, in one buffer: no
    full-frame copy. A tile of ``SAMPLED_TILE_PX`` or more gives one pixel of each 2 x 2 block: the sort
    was 60 % of the estimate."""
    h, w = shape
    tile = int(min(tile_px, h, w))
    side = tile // 2 if tile >= SAMPLED_TILE_PX else tile
    return tile, np.empty((-(-h // tile), -(-w // tile), side * side))


def _background_of_bands(bands: np.ndarray, shape: tuple[int, int], tile: int, clip_sigma: float) -> Background:
    """:func:`estimate_background` from its tiles' values (:func:`_tile_bands`, filled by :func:`_tile_band`)."""
    h, w = shape
    ty, tx, size = bands.shape
    # each tile's values sorted once (NaNs last); the clipping then only moves the ends of the kept run.
    # One sort and one pass for every tile (a call of each per row of tiles cost more than the work at 1 MP)
    bands = bands.reshape(ty * tx, size)
    _sort_rows(bands)
    level, noise, step = (values.reshape(ty, tx) for values in
                          _clipped_tiles(bands, float(clip_sigma), _truncated_sd(clip_sigma)))
    if np.isnan(level).all():
        raise FrameError("no valid pixels to estimate the background from")
    quantum = _quantum(level, step)
    # a tile whose noise could not be measured (too few distinct values) takes the others' median, or
    # the rounding noise when none could be
    if np.isnan(noise).all():
        noise[:] = quantum / math.sqrt(12.0)
    for grid in (level, noise):
        empty = np.isnan(grid)
        if empty.any():
            grid[empty] = np.nanmedian(grid)
    if level.size > 1:  # the median of one tile's 3 x 3 neighbourhood (edges replicated) is the tile itself
        level, noise = _median_3x3(level), _median_3x3(noise)
    # values quantised in steps of q carry at least their rounding noise, q / sqrt(12): the floor keeps a
    # flat (clipped or quantised) sky from a zero noise, and every threshold and ratio from dividing by it
    return Background(level_tiles=level, noise_tiles=noise, shape=(h, w), tile_px=tile,
                      noise_floor=quantum / math.sqrt(12.0))


def _sort_rows(values: np.ndarray) -> None:
    """``values.sort(axis=-1)`` of a C-ordered (N, M) float array, in place (NaNs last): the rows of whole
    numbers from 0 to 65535 (an 8- or 16-bit detector's values, the tile samples of most frames) sorted as
    uint16, whose vectorised sort takes a quarter of the float sort's time (0.5 ms of a 1 MP frame's
    background), the other rows as they are. The same values in the same order (-0.0 is no uint16: its row
    is sorted as floats)."""
    keys, whole = _uint16_rows(values)
    if whole.all():
        keys.sort(axis=-1)
        values[...] = keys
        return
    rest = values[~whole]
    rest.sort(axis=-1)
    values[~whole] = rest
    if whole.any():
        keys = keys[whole]
        keys.sort(axis=-1)
        values[whole] = keys


@kernel
def _uint16_rows(values):  # pragma: no cover - compiled
    """(keys, whole): ``values`` (N, M) as uint16 and whether each row's values are all whole numbers from 0
    to 65535 other than -0.0 (the keys of the other rows are not their values)."""
    rows, size = values.shape
    keys = np.empty((rows, size), np.uint16)
    whole = np.empty(rows, np.bool_)
    for r in range(rows):
        bad = 0
        for k in range(size):
            value = values[r, k]
            # NaN fails every comparison; 1 / -0.0 is -inf
            ok = ((value >= 0.0) & (value <= 65535.0) & (value == np.floor(value))
                  & ((value != 0.0) | (1.0 / value > 0.0)))
            bad += ~ok
            keys[r, k] = np.uint16(value) if ok else 0
        whole[r] = bad == 0
    return keys, whole


def _quantum(level: np.ndarray, step: np.ndarray) -> float:
    """The frame's value step, ADU: the least of the tiles' steps (:func:`_step_at_median`: 1 for
    integers, the scale of a scaled integer file, about 0 for floating-point data); for a frame whose
    tiles are each constant, the least gap between tile levels."""
    finite = step[np.isfinite(step)]
    if finite.size:
        return float(finite.min())
    levels = np.unique(level[np.isfinite(level)])
    return float(np.diff(levels).min()) if levels.size > 1 else 1.0


@kernel
def _median_3x3(grid):  # pragma: no cover - compiled
    """``scipy.ndimage.median_filter(grid, size=3, mode="nearest")`` of a tile grid without NaN (a few
    hundred values): each tile's 3 x 3 neighbourhood, edges replicated, ordered by insertion, its 5th
    value (the median of 9; numpy's partition of the padded grid's windows cost 0.1 ms a grid)."""
    rows, cols = grid.shape
    out = np.empty((rows, cols))
    window = np.empty(9)
    for i in range(rows):
        for j in range(cols):
            n = 0
            for di in range(-1, 2):
                r = min(max(i + di, 0), rows - 1)
                for dj in range(-1, 2):
                    value = grid[r, min(max(j + dj, 0), cols - 1)]
                    k = n
                    while k > 0 and window[k - 1] > value:
                        window[k] = window[k - 1]
                        k -= 1
                    window[k] = value
                    n += 1
            out[i, j] = window[4]
    return out


#: Tiles of at least this side are sampled (module step 1): a quarter of a 64-px tile, 1,024 values,
#: measures its noise to ~2 % (the 3 x 3 median over tiles and the interpolation smooth it further).
SAMPLED_TILE_PX = 32


@kernel
def _tile_band(image, invalid, tile, row, out):  # pragma: no cover - compiled
    """The pixels of the tiles of tile row ``row`` into ``out`` (TX, tile^2), one tile a row, in
    row-major order within the tile; NaN beyond the frame and where ``invalid`` (ignored when 1 x 1).

    With ``out`` of (TX, (tile // 2)^2), one pixel of each 2 x 2 block of the tile instead: in block
    (i, j) the pixel at row ``2 i + (i + j) % 2``, column ``2 j + i % 2``, so the four positions of a
    block (a Bayer mosaic's four colours, a detector's even and odd read-out columns) are sampled alike.
    """
    h, w = image.shape
    masked = invalid.shape[0] == h and invalid.shape[1] == w
    if out.shape[1] != tile * tile:
        half = tile // 2
        for i in range(half):
            for j in range(out.shape[0]):
                k = i * half
                for b in range(half):
                    r = row * tile + 2 * i + ((i + b) & 1)
                    c = j * tile + 2 * b + (i & 1)
                    if r >= h or c >= w or (masked and invalid[r, c]):
                        out[j, k] = np.nan
                    else:
                        out[j, k] = image[r, c]
                    k += 1
        return
    # frame rows outer: each is read once, in order (tiles outer read 64 rows apart: 3x slower at 5 MP)
    for i in range(tile):
        r = row * tile + i
        for j in range(out.shape[0]):
            k = i * tile
            for c in range(j * tile, (j + 1) * tile):
                if r >= h or c >= w or (masked and invalid[r, c]):
                    out[j, k] = np.nan
                else:
                    out[j, k] = image[r, c]
                k += 1


#: Clipping rounds of :func:`estimate_background` (each drops what lies beyond clip_sigma robust sigmas).
_CLIP_ROUNDS = 6
#: MAD of a normal distribution times this is its standard deviation.
_MAD_TO_SIGMA = 1.482602218505602


@kernel
def _sorted_median(values, lo, hi):  # pragma: no cover - compiled
    """Median of the sorted run ``values[lo:hi]`` (hi > lo)."""
    n = hi - lo
    return 0.5 * (values[lo + (n - 1) // 2] + values[lo + n // 2])


@kernel
def _deviation_median(values, lo, hi, centre):  # pragma: no cover - compiled
    """Median of |values[lo:hi] - centre| for a sorted run.

    The deviations below ``centre`` (read leftwards) and from it upwards (read rightwards) are two
    ascending runs; each order statistic of their union is found by bisecting how many of it come
    from the left run, in O(log n) instead of merging half the tile.
    """
    n = hi - lo
    right = lo + np.searchsorted(values[lo:hi], centre)
    n_left, n_right = right - lo, hi - right
    result = 0.0
    for k in ((n - 1) // 2, n // 2):
        # take i deviations from the left run and k + 1 - i from the right run
        low_i, high_i = max(0, k + 1 - n_right), min(k + 1, n_left)
        while low_i < high_i:
            i = (low_i + high_i) // 2
            if abs(values[right - 1 - i] - centre) < abs(values[right + k - i] - centre):
                low_i = i + 1
            else:
                high_i = i
        i = low_i
        deviation = -np.inf
        if i > 0:
            deviation = abs(values[right - i] - centre)
        if k - i >= 0:
            deviation = max(deviation, abs(values[right + k - i] - centre))
        result += 0.5 * deviation
    return result


#: A tile whose lowest value holds at least this fraction of its pixels, and at least this many, is
#: clipped there: a Gaussian sky quantised in steps of up to its sigma puts ~1 % or less of a tile's
#: ~1,000 sampled pixels on its lowest value (up to 13 of the 128 of a frame's edge tile, measured).
CLIPPED_TILE_FRACTION = 0.02
CLIPPED_TILE_PIXELS = 20
#: Fewest values of a tile measured by the censored fit (a frame's corner tile can hold a dozen: it
#: keeps the clipped estimate, which the 3 x 3 median over tiles and the noise floor then bound).
_FIT_MIN_PIXELS = 64
#: The censored fit (:func:`_censored_fit`) reads the empirical distribution between these fractions:
#: the upper tail holds the tile's stars.
_FIT_LOW, _FIT_HIGH = 0.002, 0.9


@kernel
def _clipped_tiles(ordered, clip_sigma, truncated_sd):  # pragma: no cover - compiled
    """(level, noise, step) of each row of sorted tile values (NaNs last): median and clipped standard
    deviation after the sigma clipping of :func:`estimate_background`, or the censored fit's mean and
    sigma (:func:`_censored_fit`) for a tile clipped at its lowest value or quantised in steps of
    more than twice its noise; the least gap between two distinct values; NaN for an empty tile (and
    a NaN step for a constant one)."""
    tiles, size = ordered.shape
    level = np.full(tiles, np.nan)
    noise = np.full(tiles, np.nan)
    step = np.full(tiles, np.nan)
    for t in range(tiles):
        row = ordered[t]
        # the NaNs are sorted last: bisect for the first
        hi, top = 0, size
        while hi < top:
            middle = (hi + top) // 2
            if np.isnan(row[middle]):
                top = middle
            else:
                hi = middle + 1
        lo = 0
        if hi == 0:
            continue
        valid = hi
        gap = _step_at_median(row, valid)
        if np.isfinite(gap):
            step[t] = gap
        for _ in range(_CLIP_ROUNDS):
            med = _sorted_median(row, lo, hi)
            limit = clip_sigma * max(_deviation_median(row, lo, hi, med) * _MAD_TO_SIGMA, 1e-12)
            new_lo, new_hi = lo, hi
            while new_lo < new_hi and abs(row[new_lo] - med) > limit:
                new_lo += 1
            while new_hi > new_lo and abs(row[new_hi - 1] - med) > limit:
                new_hi -= 1
            if new_lo == lo and new_hi == hi:
                break
            lo, hi = new_lo, new_hi
            if hi == lo:
                break
        count = hi - lo
        if count == 0:
            continue
        level[t] = _sorted_median(row, lo, hi)
        if count > 1:
            noise[t] = np.sqrt(_spread(row, lo, hi, level[t]) / (count - 1)) / truncated_sd
        # a sky clipped at the bottom (an ADC offset too low); a tile clipped at the top is a saturated
        # body, measured by clipping like any tile spoiled by a bright object
        lowest = np.searchsorted(row[:valid], row[0], side="right")
        clipped = max(CLIPPED_TILE_FRACTION * valid, CLIPPED_TILE_PIXELS) <= lowest < valid
        # a sky quantised in steps of more than twice its noise (most values on one or two steps):
        # the clipped standard deviation collapses with the MAD
        if (clipped or not noise[t] >= 0.5 * gap) and valid >= _FIT_MIN_PIXELS:
            mu, sigma = _censored_fit(row, valid)
            if np.isfinite(sigma):
                level[t], noise[t] = mu, sigma
            elif clipped:
                noise[t] = np.nan  # too few distinct values to measure: the caller fills the tile
    return level, noise, step


@kernel(inline=True)
def _spread(row, lo, hi, centre):  # pragma: no cover - compiled
    """Sum of squared deviations of ``row[lo:hi]`` from their mean, in one pass: the sums of ``v - centre``
    and of its square (``centre`` a value inside the run, the median, keeps them well conditioned; for
    whole-number values both sums are exact), in 4 running sums each (one running sum made the loop wait on
    each addition: 80 % of the tiles' clipping time)."""
    n = hi - lo
    s0 = s1 = s2 = s3 = q0 = q1 = q2 = q3 = 0.0
    whole = lo + n - n % 4
    for k in range(lo, whole, 4):
        d0, d1, d2, d3 = row[k] - centre, row[k + 1] - centre, row[k + 2] - centre, row[k + 3] - centre
        s0 += d0
        s1 += d1
        s2 += d2
        s3 += d3
        q0 += d0 * d0
        q1 += d1 * d1
        q2 += d2 * d2
        q3 += d3 * d3
    total, total_sq = (s0 + s1) + (s2 + s3), (q0 + q1) + (q2 + q3)
    for k in range(whole, hi):
        d = row[k] - centre
        total += d
        total_sq += d * d
    return max(total_sq - total * total / n, 0.0)


@kernel
def _step_at_median(row, n):  # pragma: no cover - compiled
    """The lesser gap between the median's value of the sorted ``row[:n]`` and the distinct values
    on either side of it (inf when there is none): the value step of quantised data (1 for
    integers: the values around the median are the densest), near 0 for floating-point data; by
    bisection, not a pass over the tile."""
    middle = row[(n - 1) // 2]
    above = np.searchsorted(row[:n], middle, side="right")
    below = np.searchsorted(row[:n], middle, side="left") - 1
    gap = np.inf
    if above < n:
        gap = row[above] - middle
    if below >= 0:
        gap = min(gap, middle - row[below])
    return gap


@kernel
def _censored_fit(row, n):  # pragma: no cover - compiled
    """Mean and sigma of a normal distribution from the sorted values ``row[:n]``, read only through
    their empirical distribution between the fractions ``_FIT_LOW`` and ``_FIT_HIGH``.

    A detector clips its sky at zero (or its ADC's top) and rounds it to whole ADU: below the clip
    every value is the clip, and a value v stands for every true value that rounds to it. But the
    fraction F of values at or below v is still the normal distribution's at the boundary between v
    and the next value (the midpoint), whatever was clipped below: so probit(F) against the boundary
    is a line of slope 1 / sigma and intercept -mean / sigma, fitted by weighted least squares (the
    weight of a point the inverse variance of its probit, ``n phi(z)^2 / (F (1 - F))``). Stars and
    hot pixels sit in the upper tail the fit leaves out. NaN when fewer than two boundaries fall
    between those fractions.
    """
    sw = swx = swy = swxx = swxy = 0.0
    points = 0
    k = 0
    while k < n - 1:
        j = k
        while j + 1 < n and row[j + 1] == row[k]:
            j += 1
        if j + 1 >= n:
            break
        fraction = (j + 1) / n
        if fraction > _FIT_HIGH:
            break
        if fraction >= _FIT_LOW:
            z = _probit(fraction)
            boundary = 0.5 * (row[j] + row[j + 1])
            weight = n * math.exp(-z * z) / (2.0 * math.pi) / (fraction * (1.0 - fraction))
            sw += weight
            swx += weight * z
            swy += weight * boundary
            swxx += weight * z * z
            swxy += weight * z * boundary
            points += 1
        k = j + 1
    if points < 2:
        return np.nan, np.nan
    spread = sw * swxx - swx * swx
    if not spread > 0.0:
        return np.nan, np.nan
    sigma = (sw * swxy - swx * swy) / spread
    mean = (swy - sigma * swx) / sw
    if not sigma > 0.0:
        return np.nan, np.nan
    return mean, sigma


@kernel
def _probit(p):  # pragma: no cover - compiled
    """Inverse of the standard normal distribution function for 0 < p < 1 (P. J. Acklam's rational
    approximation, relative error < 1.2e-9, with one Newton step on ``math.erfc``)."""
    low = 0.02425
    if p < low:
        q = math.sqrt(-2.0 * math.log(p))
        x = ((((((-7.784894002430293e-03 * q - 3.223964580411365e-01) * q - 2.400758277161838e+00) * q
                - 2.549732539343734e+00) * q + 4.374664141464968e+00) * q + 2.938163982698783e+00)
             / ((((7.784695709041462e-03 * q + 3.224671290700398e-01) * q + 2.445134137142996e+00) * q
                 + 3.754408661907416e+00) * q + 1.0))
    elif p <= 1.0 - low:
        q = p - 0.5
        r = q * q
        x = ((((((-3.969683028665376e+01 * r + 2.209460984245205e+02) * r - 2.759285104469687e+02) * r
                + 1.383577518672690e+02) * r - 3.066479806614716e+01) * r + 2.506628277459239e+00) * q
             / (((((-5.447609879822406e+01 * r + 1.615858368580409e+02) * r - 1.556989798598866e+02) * r
                  + 6.680131188771972e+01) * r - 1.328068155288572e+01) * r + 1.0))
    else:
        q = math.sqrt(-2.0 * math.log(1.0 - p))
        x = -((((((-7.784894002430293e-03 * q - 3.223964580411365e-01) * q - 2.400758277161838e+00) * q
                 - 2.549732539343734e+00) * q + 4.374664141464968e+00) * q + 2.938163982698783e+00)
              / ((((7.784695709041462e-03 * q + 3.224671290700398e-01) * q + 2.445134137142996e+00) * q
                  + 3.754408661907416e+00) * q + 1.0))
    error = 0.5 * math.erfc(-x / math.sqrt(2.0)) - p
    return x - error * math.sqrt(2.0 * math.pi) * math.exp(0.5 * x * x)


#: The detection filter's Gaussian is cut this many of its sigmas from its centre (module step 3). For a
#: pixelated Gaussian PSF of sigma 0.5-3 px, the 1-px filter cut at 2 sigmas (5 x 5 px) gives 99.3-100 % of
#: the signal-to-noise ratio of one cut at 4 sigmas (9 x 9 px), at any pixel phase: the threshold is set
#: from the filter's own noise gain, and the wings carry almost no signal. With OpenCV the 5-tap filter took
#: half the time of the 9-tap one (0.44 against 0.84 ms on 1 MP, one thread); it is compiled now
#: (:func:`_smoothed`).
FILTER_RADIUS_SIGMAS = 2.0


def _gaussian_kernel(sigma: float) -> np.ndarray:
    """The normalised 1-D Gaussian of ``sigma`` px over ``2 ceil(FILTER_RADIUS_SIGMAS sigma) + 1`` taps."""
    half = max(1, math.ceil(FILTER_RADIUS_SIGMAS * sigma))
    return cv2.getGaussianKernel(2 * half + 1, sigma, cv2.CV_64F)[:, 0]


def _smoothed(resid: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``resid`` (H, W) convolved with the symmetric 1-D ``kernel`` (odd length) along both axes, edges
    reflected (``cv2.BORDER_REFLECT``: ``dcb|abcd|cba``), in single precision. The 5-tap filter (the
    detection filter of 1 px, :data:`FILTER_RADIUS_SIGMAS`) is compiled (:func:`_five_tap_kernel`: 0.19
    against OpenCV's 0.40 ms on 1 MP, equal to it within a few units in the last place, the sums taken
    in another order); other lengths go to OpenCV's ``sepFilter2D``."""
    resid = np.ascontiguousarray(resid, dtype=np.float32)
    kernel = np.asarray(kernel, np.float32)
    if len(kernel) == 5:
        return _five_tap_kernel(resid, kernel[2], kernel[3], kernel[4])
    return cv2.sepFilter2D(resid, cv2.CV_32F, kernel, kernel, borderType=cv2.BORDER_REFLECT)


@kernel(inline=True)
def _reflected(i, n):  # pragma: no cover - compiled
    """Index ``i`` reflected into ``[0, n)`` as ``cv2.BORDER_REFLECT`` does (repeatedly, for a line shorter
    than the kernel)."""
    while i < 0 or i >= n:
        i = -i - 1 if i < 0 else 2 * n - i - 1
    return i


@kernel
def _five_tap_kernel(image, centre, near, far):  # pragma: no cover - compiled
    """:func:`_smoothed` with the taps ``far, near, centre, near, far``: each row filtered along x into a
    ring of the last 5 rows, each output row summed from the ring along y as soon as its rows are in it
    (the frame read once and written once); each sum one expression, so that the loops vectorise."""
    rows, cols = image.shape
    out = np.empty((rows, cols), np.float32)
    ring = np.empty((5, cols), np.float32)
    for ahead in range(rows + 2):
        if ahead < rows:
            source, filtered = image[ahead], ring[ahead % 5]
            for c in range(2, cols - 2):
                filtered[c] = centre * source[c] + near * (source[c - 1] + source[c + 1]) + far * (
                    source[c - 2] + source[c + 2])
            for c in range(min(2, cols)):
                filtered[c] = _edge_sum(source, c, cols, centre, near, far)
            for c in range(max(cols - 2, min(2, cols)), cols):
                filtered[c] = _edge_sum(source, c, cols, centre, near, far)
        r = ahead - 2
        if r < 0:
            continue
        row, middle = out[r], ring[r % 5]
        up1, down1 = ring[_reflected(r - 1, rows) % 5], ring[_reflected(r + 1, rows) % 5]
        up2, down2 = ring[_reflected(r - 2, rows) % 5], ring[_reflected(r + 2, rows) % 5]
        for c in range(cols):
            row[c] = centre * middle[c] + near * (up1[c] + down1[c]) + far * (up2[c] + down2[c])
    return out


@kernel(inline=True)
def _edge_sum(source, c, cols, centre, near, far):  # pragma: no cover - compiled
    """:func:`_five_tap_kernel`'s sum along x at column ``c`` within 2 px of an edge (reflected)."""
    return centre * source[c] + near * (source[_reflected(c - 1, cols)] + source[_reflected(c + 1, cols)]) + far * (
        source[_reflected(c - 2, cols)] + source[_reflected(c + 2, cols)])


def _subpixel_peak(smooth: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Seeds (x, y) px: each peak pixel moved to the vertex of the parabola through it and its two
    neighbours along x and along y (at most half a pixel; none where the profile is not curved down)."""
    return _subpixel_kernel(np.ascontiguousarray(smooth, dtype=np.float32), np.asarray(rows, np.int64),
                            np.asarray(cols, np.int64))


@kernel
def _subpixel_kernel(smooth, rows, cols):  # pragma: no cover - compiled
    """:func:`_subpixel_peak` peak by peak (a dozen array operations on a few peaks cost ~20 us)."""
    h, w = smooth.shape
    out = np.empty((rows.size, 2))
    for k in range(rows.size):
        r = min(max(rows[k], 1), h - 2)
        c = min(max(cols[k], 1), w - 2)
        for axis in range(2):
            # in double precision (a single-precision frame's differences would round; numba's float() of a
            # float32 stays single)
            if axis == 0:
                lo, mid, hi = np.float64(smooth[r, c - 1]), np.float64(smooth[r, c]), np.float64(smooth[r, c + 1])
            else:
                lo, mid, hi = np.float64(smooth[r - 1, c]), np.float64(smooth[r, c]), np.float64(smooth[r + 1, c])
            curvature = lo - 2.0 * mid + hi
            step = 0.5 * (lo - hi) / curvature if curvature < 0 else 0.0
            out[k, axis] = (cols[k] if axis == 0 else rows[k]) + min(max(step, -0.5), 0.5)
    return out


def _keep_deblended(smooth: np.ndarray, peaks_rc: np.ndarray, noise_s: float, contrast: float) -> np.ndarray:
    """Which peaks of one component (sorted brightest first) are separate sources: a fainter peak is
    kept when the profile of ``smooth`` along the straight line to every brighter kept peak (sampled
    4 times a pixel, bilinear) dips below it by more than ``contrast`` of its height and by 3 ``noise_s``."""
    return _deblend_kernel(np.ascontiguousarray(smooth, dtype=np.float32), np.asarray(peaks_rc, np.int64),
                           float(noise_s), float(contrast))


@kernel
def _bilinear_at(values, y, x):  # pragma: no cover - compiled
    """``scipy.ndimage.map_coordinates(values, [[y], [x]], order=1)`` of a point inside the frame, with
    its weights and sum in scipy's order (a neighbour beyond the last row or column has weight 0)."""
    rows, cols = values.shape
    y0, x0 = int(math.floor(y)), int(math.floor(x))
    wy0 = 1.0 - (y - y0)
    wx0 = 1.0 - (x - x0)
    wy1, wx1 = 1.0 - wy0, 1.0 - wx0
    y1, x1 = min(y0 + 1, rows - 1), min(x0 + 1, cols - 1)
    total = 0.0
    total += values[y0, x0] * wy0 * wx0
    total += values[y0, x1] * wy0 * wx1
    total += values[y1, x0] * wy1 * wx0
    total += values[y1, x1] * wy1 * wx1
    return total


@kernel
def _deblend_kernel(smooth, peaks_rc, noise_s, contrast):  # pragma: no cover - compiled
    """:func:`_keep_deblended` (a dozen array operations and a ``map_coordinates`` call per peak pair
    cost ~1.5 ms a component on a JPEG frame's star cores)."""
    n = peaks_rc.shape[0]
    keep = np.zeros(n, np.bool_)
    keep[0] = True
    for j in range(1, n):
        rj, cj = peaks_rc[j, 0], peaks_rc[j, 1]
        height = smooth[rj, cj]
        longest = 0.0
        for k in range(j):
            if keep[k]:
                longest = max(longest, math.hypot(peaks_rc[k, 0] - rj, peaks_rc[k, 1] - cj))
        n_samples = int(math.ceil(longest)) * 4 + 2
        step = 1.0 / (n_samples - 1)  # numpy.linspace(0, 1, n_samples): i * step, the last exactly 1
        separate = True
        for k in range(j):
            if not keep[k]:
                continue
            dr, dc = peaks_rc[k, 0] - rj, peaks_rc[k, 1] - cj
            saddle = np.inf
            for i in range(n_samples):
                t = 1.0 if i == n_samples - 1 else i * step
                saddle = min(saddle, _bilinear_at(smooth, rj + t * dr, cj + t * dc))
            dip = height - saddle
            if not (dip > contrast * height and dip > 3.0 * noise_s):
                separate = False
                break
        keep[j] = separate
    return keep


#: At most this fraction of a frame's pixels is rejected as hot pixels or cosmic-ray hits (module step
#: 2): a detector with 10^-4 hot pixels and a long exposure's hits flag ~10^-4; a noise model that does
#: not fit the frame (a clipped or quantised sky) can make the test flag a fifth of it.
MAX_REJECTED_FRACTION = 0.005


def _sharp_pixels(resid: np.ndarray, background: Background, saturated: np.ndarray, options: DetectOptions
                  ) -> np.ndarray:
    """Pixels sharper than any PSF: hot pixels and cosmic-ray hits (module docstring, step 2), at most
    ``MAX_REJECTED_FRACTION`` of the frame: beyond it only the most significant (residual over noise)."""
    return _sharp_hits(resid, background, saturated, options)[0]


def _sharp_hits(resid: np.ndarray, background: Background, saturated: np.ndarray, options: DetectOptions
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(:func:`_sharp_pixels` mask, its rows, its columns in row-major order); ``resid`` float32, the
    noise map ``background.noise`` interpolated row by row inside the pass."""
    resid = np.ascontiguousarray(resid, dtype=np.float32)
    hits, rows, cols = _sharp_kernel(resid, *background.noise_interpolation(),
                                     np.ascontiguousarray(saturated, dtype=bool), float(options.threshold_sigma),
                                     float(options.min_neighbour_ratio), PAIR_TEST_MIN_SNR, PAIR_OUTER_RATIO)
    cap = int(MAX_REJECTED_FRACTION * hits.size)
    if len(rows) > cap:
        significance = resid[rows, cols] / np.maximum(background.noise_at(rows, cols), 1e-300)
        drop = np.sort(np.argsort(-significance, kind="stable")[cap:])
        hits[rows[drop], cols[drop]] = False
        kept = np.ones(len(rows), bool)
        kept[drop] = False
        rows, cols = rows[kept], cols[kept]
    return hits, rows, cols


@kernel
def _count_groups(mask, rows, cols):  # pragma: no cover - compiled
    """Number of 8-connected groups of the set pixels of ``mask`` (all of them listed in ``rows``,
    ``cols``): ``cv2.connectedComponents(mask)[0] - 1``, flooding from the listed pixels instead of
    reading the frame."""
    height, width = mask.shape
    seen = np.zeros(rows.size, np.bool_)
    index = {}
    for k in range(rows.size):
        index[rows[k] * width + cols[k]] = k
    stack = np.empty(rows.size, np.int64)
    groups = 0
    for start in range(rows.size):
        if seen[start]:
            continue
        groups += 1
        seen[start] = True
        stack[0] = start
        top = 1
        while top > 0:
            top -= 1
            k = stack[top]
            for dr in range(-1, 2):
                r = rows[k] + dr
                if r < 0 or r >= height:
                    continue
                for dc in range(-1, 2):
                    c = cols[k] + dc
                    if c < 0 or c >= width or not mask[r, c]:
                        continue
                    j = index[r * width + c]
                    if not seen[j]:
                        seen[j] = True
                        stack[top] = j
                        top += 1
    return groups


@kernel(inline=True)
def _beyond_pair(resid, r, c, dr, dc):  # pragma: no cover - compiled
    """Sum of the two values beyond the pair of ``resid[r, c]`` and its brighter neighbour along the axis
    (dr, dc) ((0, 1): x, (1, 0): y); NaN at an edge. By index, not through a row or column view (a
    view's reference counting cost more than the test)."""
    n = resid.shape[1] if dc else resid.shape[0]
    k = c if dc else r
    left = resid[r - dr, c - dc] if k > 0 else -np.inf
    right = resid[r + dr, c + dc] if k < n - 1 else -np.inf
    if right >= left:
        return resid[r - dr, c - dc] + resid[r + 2 * dr, c + 2 * dc] if k > 0 and k < n - 2 else np.nan
    return resid[r - 2 * dr, c - 2 * dc] + resid[r + dr, c + dc] if k > 1 and k < n - 1 else np.nan


@kernel
def _touches_saturated(saturated, r, c):  # pragma: no cover - compiled
    """Whether pixel (r, c) or one of its 4 neighbours is saturated."""
    rows, cols = saturated.shape
    return (saturated[r, c] or (r > 0 and saturated[r - 1, c]) or (r < rows - 1 and saturated[r + 1, c])
            or (c > 0 and saturated[r, c - 1]) or (c < cols - 1 and saturated[r, c + 1]))


@kernel
def _sharp_kernel(resid, noise_grid, iy, wy, ix, wx, floor, saturated, threshold_sigma, ratio, pair_min_snr,
                  pair_ratio):  # pragma: no cover - compiled
    """(mask, rows, columns) of the significant pixels whose lesser neighbour pair (x or y, zero beyond
    the edge) is below ``ratio`` of them, except a clipped core (a saturated pixel with a saturated x neighbour: a hot pixel, or
    one bloomed into its column, is one pixel wide); and pixels above ``pair_min_snr`` sigmas with
    less than ``pair_ratio`` of them beyond their pair along x or y (module docstring, step 2). The
    noise map is interpolated row by row (:func:`_noise_row` of ``Background.noise_interpolation``)."""
    rows, cols = resid.shape
    out = np.zeros((rows, cols), np.bool_)
    along_x, noise = _along_x(noise_grid, ix, wx), np.empty(cols)
    marks, marked = _row_marks(cols)
    per_row = np.zeros(rows, np.int64)
    for r in range(rows):
        _noise_row(along_x, iy, wy, floor, r, noise)
        # the row's significant pixels marked in a loop that vectorises (a test and a branch at every
        # pixel were most of the pass), then tested; no array grows inside this loop (that made every
        # pixel of it cost 20 ns)
        if not _marked_row(resid[r], noise, saturated[r], threshold_sigma, marks):
            continue
        found = 0
        for word in range(marked.size):  # the marks 8 at a time
            if marked[word] == 0:
                continue
            for c in range(8 * word, 8 * word + 8):
                if marks[c] and _sharp_test(resid, saturated, r, c, noise[c], threshold_sigma, ratio, pair_min_snr,
                                            pair_ratio):
                    out[r, c] = True
                    found += 1
        per_row[r] = found
    # the set pixels' rows and columns in row-major order (a few hundred a frame)
    found_r = np.empty(per_row.sum(), np.int64)
    found_c = np.empty(per_row.sum(), np.int64)
    k = 0
    for r in range(rows):
        if per_row[r]:
            for c in range(cols):
                if out[r, c]:
                    found_r[k] = r
                    found_c[k] = c
                    k += 1
    return out, found_r, found_c


@kernel(inline=True)
def _row_marks(cols):  # pragma: no cover - compiled
    """(marks, words): a zeroed uint8 array of a row's ``cols`` marks (0 or 1) padded to a multiple of 8,
    and the same memory as uint64 words, for loops that skip 8 unmarked pixels at a time."""
    marks = np.zeros(8 * ((cols + 7) // 8), np.uint8)
    return marks, marks.view(np.uint64)


@kernel
def _marked_row(values, noise, saturated, threshold_sigma, marks):  # pragma: no cover - compiled
    """``marks[c] = values[c] > threshold_sigma * noise[c]`` along a row, except at a clipped core's pixels
    (``saturated`` with a saturated x neighbour: :func:`_sharp_test` keeps them whatever their
    neighbours); whether any is set. A kernel of its own, called rather than inlined, so that this
    loop is compiled, and vectorised, alone. (A planet's bloom trail is ~20 clipped pixels in every
    row: tested one by one, they were three quarters of the pass.)"""
    n = values.size
    count = 0
    for c in range(1, n - 1):  # the two end columns below: this loop then vectorises
        mark = (values[c] > threshold_sigma * noise[c]) & ~(saturated[c] & (saturated[c - 1] | saturated[c + 1]))
        marks[c] = mark
        count += mark
    for c in (0, n - 1):
        neighbour = (c > 0 and saturated[c - 1]) or (c < n - 1 and saturated[c + 1])
        mark = values[c] > threshold_sigma * noise[c] and not (saturated[c] and neighbour)
        marks[c] = mark
        count += mark
    return count > 0


@kernel(inline=True)
def _sharp_test(resid, saturated, r, c, noise, threshold_sigma, ratio, pair_min_snr,
                pair_ratio):  # pragma: no cover - compiled
    """:func:`_sharp_kernel`'s tests of pixel (r, c), above ``threshold_sigma`` times its ``noise``:
    whether it is a hot pixel or a cosmic-ray hit."""
    rows, cols = resid.shape
    value = resid[r, c]
    pair_x = (resid[r, c - 1] if c > 0 else 0.0) + (resid[r, c + 1] if c < cols - 1 else 0.0)
    pair_y = (resid[r - 1, c] if r > 0 else 0.0) + (resid[r + 1, c] if r < rows - 1 else 0.0)
    if not min(pair_x, pair_y) < ratio * value:
        if value > pair_min_snr * noise and not _touches_saturated(saturated, r, c):
            beyond_x = _beyond_pair(resid, r, c, 0, 1)
            beyond_y = _beyond_pair(resid, r, c, 1, 0)
            # NaN at an edge compares False: untested, kept
            return beyond_x < pair_ratio * value or beyond_y < pair_ratio * value
        return False
    # a clipped core (a saturated pixel with a saturated x neighbour) is not sharp
    return not (saturated[r, c] and ((c > 0 and saturated[r, c - 1]) or (c < cols - 1 and saturated[r, c + 1])))


@kernel(inline=True)
def _with_room(buffer, used, more):  # pragma: no cover - compiled
    """``buffer`` with room for ``more`` items after its first ``used`` (at least doubled when full)."""
    if used + more <= buffer.size:
        return buffer
    bigger = np.empty(max(2 * buffer.size, used + more), buffer.dtype)
    bigger[:used] = buffer[:used]
    return bigger


def _detection_components(smooth: np.ndarray, background: Background, gain: float, valid: np.ndarray | None,
                          threshold_sigma: float, saturated: np.ndarray, resid: np.ndarray) -> tuple:
    """Threshold, connected components and their statistics of the detection-filtered frame (module steps 3
    and 4) in one pass over it: ``(correlation, n_comp, labels, on_rows, on_cols, on_labels, stats,
    saturated, invalid, flux)``.

    ``correlation`` is the measured over predicted noise of the filtered frame. The prediction
    assumes independent pixels. Compression (JPEG blocks), demosaicing and resampling correlate
    neighbouring pixels, so the filtered noise is larger than predicted (while the per-pixel noise
    the background step measures is smaller): the robust sigma of ``smooth / (max(noise, 1e-12)
    gain)`` over a sample of the pixels (stars are a tiny fraction) corrects it, ``valid`` pixels
    only (None: all). Never below 1: a frame is not assumed quieter than its pixel noise says. The
    sample is every :func:`_correlation_step`-th pixel of each axis.

    A pixel is "on" where ``smooth > threshold_sigma * (max(noise, 1e-12) * gain * correlation)``;
    ``labels`` (H, W) int32 numbers the 8-connected components of the on pixels 1..n_comp-1 in the
    raster order of their first pixels (0: off), the partition ``cv2.connectedComponents`` gives;
    ``on_rows``, ``on_cols`` list the on pixels in row-major order (the later steps read only them),
    ``on_labels`` their labels. ``stats`` (n_comp, 5) int32 holds each component's box and area in OpenCV's layout
    (``CC_STAT_LEFT``, ``TOP``, ``WIDTH``, ``HEIGHT``, ``AREA``; row 0, the background, zero); per
    component 1..n_comp-1, whether a pixel is ``saturated``, whether one is not ``valid``, and the sum
    of ``resid`` over its pixels in pixel order (the sums ``numpy.bincount`` gives).
    """
    any_invalid = valid is not None
    valid = np.ones((1, 1), bool) if valid is None else np.ascontiguousarray(valid, dtype=bool)
    correlation, n_comp, labels, rows, cols, on_label, stats, any_saturated, has_invalid, flux = _components_kernel(
        smooth, *background.noise_interpolation(), float(gain), float(threshold_sigma), valid, any_invalid,
        _correlation_step(smooth.shape), np.ascontiguousarray(saturated, dtype=bool),
        np.ascontiguousarray(resid, dtype=np.float32))
    return float(correlation), int(n_comp), labels, rows, cols, on_label, stats, any_saturated, has_invalid, flux


#: :func:`_detection_components` samples about this many pixels (at most 4 times as many on frames
#: below 0.26 MP): the robust sigma of 16,384 values is good to ~1 % (1.17 / sqrt(n)), half the ~2 %
#: of the background noise it multiplies (a tile's 1,024 sampled values). 65,536 values (0.5 %) cost
#: 0.2 ms more a 1 MP frame (the sample's two medians and its gathering) for a threshold steadier
#: by 0.04 sigma at 5 sigmas.
_CORRELATION_SAMPLE = 16384


def _correlation_step(shape: tuple[int, int]) -> int:
    """The sampling step along each axis of the correlation sample (:func:`_detection_components`): every
    4th pixel up to 0.26 MP (512 x 512 px), beyond it the odd step that keeps about ``_CORRELATION_SAMPLE``
    pixels (odd, so that the sample runs through every position of a JPEG frame's 8 x 8 blocks: every 9th
    pixel of a 1 MP frame, every 19th of a 5 MP frame)."""
    step = max(4, math.ceil(math.sqrt(shape[0] * shape[1] / _CORRELATION_SAMPLE)))
    return step if step == 4 or step % 2 else step + 1


@kernel
def _components_kernel(smooth, noise_grid, iy, wy, ix, wx, floor, gain, threshold_sigma, valid, any_invalid,
                       step, saturated, resid):  # pragma: no cover - compiled
    """:func:`_detection_components`. One pass over ``smooth`` (the noise rows interpolated,
    :func:`_noise_row`) gathers the correlation sample and the candidates above the threshold at a
    correlation of 1 (the least it can be: the on pixels are among them); the correlation then
    keeps the on pixels among the candidates, and a union-find over their runs along the rows, in
    raster order, labels them (a run's neighbours read in the label image: the pixels above it and its
    two upper corners); the components are numbered in the raster order of their first pixels."""
    rows, cols = smooth.shape
    sample = np.empty(((rows + step - 1) // step) * ((cols + step - 1) // step))
    along_x, noise = _along_x(noise_grid, ix, wx), np.empty(cols)
    n_sample = 0
    n_cand = 0
    cand_r = np.empty(1024, np.int64)
    cand_c = np.empty(1024, np.int64)
    cand_n = np.empty(1024)
    marks, marked = _row_marks(cols)
    for r in range(rows):
        _noise_row(along_x, iy, wy, floor, r, noise)
        if r % step == 0:
            for c in range(0, cols, step):
                if not any_invalid or valid[r, c]:
                    sample[n_sample] = smooth[r, c] / (max(noise[c], 1e-12) * gain)
                    n_sample += 1
        # marked and counted first, in a loop of its own that vectorises (the appends inside it made
        # every pixel cost 40 times as much); then gathered from the marks 8 at a time (a planet's bloom
        # trail puts candidates in every row: a pixel-by-pixel scan of each row was a quarter of the pass)
        values = smooth[r]
        count = 0
        for c in range(cols):
            mark = values[c] > threshold_sigma * (max(noise[c], 1e-12) * gain * 1.0)
            marks[c] = mark
            count += mark
        if count == 0:
            continue
        cand_r = _with_room(cand_r, n_cand, count)
        cand_c = _with_room(cand_c, n_cand, count)
        cand_n = _with_room(cand_n, n_cand, count)
        for word in range(marked.size):
            if marked[word] == 0:
                continue
            for c in range(8 * word, 8 * word + 8):
                if marks[c]:
                    cand_r[n_cand] = r
                    cand_c[n_cand] = c
                    cand_n[n_cand] = noise[c]
                    n_cand += 1
    correlation = 1.0
    if n_sample >= 100:
        values = sample[:n_sample]
        centre = _exact_median(values)
        correlation = max(1.0, _MAD_TO_SIGMA * _exact_median(np.abs(values - centre)))
    on_r = np.empty(n_cand, np.int64)
    on_c = np.empty(n_cand, np.int64)
    n_on = 0
    for k in range(n_cand):
        r, c = cand_r[k], cand_c[k]
        if smooth[r, c] > threshold_sigma * (max(cand_n[k], 1e-12) * gain * correlation):
            on_r[n_on] = r
            on_c[n_on] = c
            n_on += 1
    on_r, on_c = on_r[:n_on], on_c[:n_on]
    labels = np.zeros((rows, cols), np.int32)
    parent = np.empty(n_on + 1, np.int64)
    provisional = 0
    k = 0
    while k < n_on:
        # a run of on pixels along the row: one label, joined to the labels above it and its two corners
        # (read once a run of equal labels: a bloom trail's ~25-px runs in every row made a union a pixel)
        r, end = on_r[k], k + 1
        while end < n_on and on_r[end] == r and on_c[end] == on_c[end - 1] + 1:
            end += 1
        label = 0
        if r > 0:
            above = 0
            for cc in range(max(on_c[k] - 1, 0), min(on_c[end - 1] + 2, cols)):
                if labels[r - 1, cc] != above:
                    above = labels[r - 1, cc]
                    label = _joined(parent, above, label)
        if label == 0:
            provisional += 1
            parent[provisional] = provisional
            label = provisional
        for j in range(k, end):
            labels[r, on_c[j]] = label
        k = end
    # final labels: the roots numbered in order (their first pixels' raster order)
    final = np.zeros(provisional + 1, np.int32)
    n_comp = 1
    for k in range(1, provisional + 1):
        root = _root(parent, k)
        if root == k:
            final[k] = n_comp
            n_comp += 1
        else:
            final[k] = final[root]
    # the final labels written, and each component's box, area, saturated and invalid pixels and flux
    # summed, in one pass over the on pixels (in pixel order)
    left = np.full(n_comp, cols, np.int32)
    top = np.full(n_comp, rows, np.int32)
    right = np.full(n_comp, -1, np.int32)
    bottom = np.full(n_comp, -1, np.int32)
    area = np.zeros(n_comp, np.int32)
    any_saturated = np.zeros(n_comp - 1, np.bool_)
    has_invalid = np.zeros(n_comp - 1, np.bool_)
    flux = np.zeros(n_comp - 1)
    on_label = np.empty(n_on, np.int32)
    for i in range(n_on):
        r, c = on_r[i], on_c[i]
        k = final[labels[r, c]]
        labels[r, c] = k
        on_label[i] = k
        area[k] += 1
        left[k] = min(left[k], c)
        right[k] = max(right[k], c)
        top[k] = min(top[k], r)
        bottom[k] = max(bottom[k], r)
        any_saturated[k - 1] |= saturated[r, c]
        if any_invalid:
            has_invalid[k - 1] |= not valid[r, c]
        flux[k - 1] += resid[r, c]
    stats = np.zeros((n_comp, 5), np.int32)
    for k in range(1, n_comp):
        stats[k, 0] = left[k]
        stats[k, 1] = top[k]
        stats[k, 2] = right[k] - left[k] + 1
        stats[k, 3] = bottom[k] - top[k] + 1
        stats[k, 4] = area[k]
    return correlation, n_comp, labels, on_r, on_c, on_label, stats, any_saturated, has_invalid, flux


#: :func:`_exact_median` brackets the median between the values this many binomial sigmas of rank either
#: side of it in a sorted subsample of ``_MEDIAN_SUBSAMPLE`` values.
_MEDIAN_BRACKET_SIGMAS = 5.0
_MEDIAN_SUBSAMPLE = 1024
#: The subsample's positions: ``floor(n frac(k _GOLDEN))`` (a Weyl sequence, the golden ratio's fraction).
_GOLDEN = 0.6180339887498949


@kernel
def _median_bracket(values, first, half):  # pragma: no cover - compiled
    """(low, high): the values ``_MEDIAN_BRACKET_SIGMAS`` binomial sigmas of rank either side of ranks
    ``first`` and ``half`` of the ``n = values.size`` values (0-based) in a sorted subsample of
    ``_MEDIAN_SUBSAMPLE`` of them (-inf, inf beyond its ends), n >= ``_MEDIAN_SUBSAMPLE``.

    The subsample's positions spread over the array with no period (a Weyl sequence): the correlation
    sample is rows of a frame, and every ``n // _MEDIAN_SUBSAMPLE``-th value of 256-value rows read the
    same 4 columns of every 16th row, whose median was not the frame's (the bracket missed on the demo
    frames with a planet's bloom trail, and the full median of the fallback ran twice a frame)."""
    n = values.size
    m = _MEDIAN_SUBSAMPLE
    sub = np.empty(m)
    for k in range(m):
        sub[k] = values[min(int(((k * _GOLDEN) % 1.0) * n), n - 1)]
    sub.sort()
    margin = int(_MEDIAN_BRACKET_SIGMAS * math.sqrt(0.25 * m)) + 2
    low_rank, high_rank = int(first / n * m) - margin, int(half / n * m) + margin
    low = sub[low_rank] if low_rank >= 0 else -np.inf
    high = sub[high_rank] if high_rank < m else np.inf
    return low, high


@kernel
def _exact_median(values):  # pragma: no cover - compiled
    """``np.median(values)`` of a 1-D array, the same number, in a fraction of the time on 65,536 values
    (numba's selection was half of :func:`_components_kernel`).

    The median is one or two order statistics, found without ordering the array: a sorted subsample
    brackets them (:func:`_median_bracket`); one pass counts the values below
    the bracket and gathers those in it (~16 %), and a partition of those finds them. When the bracket
    misses either rank (its chance is ~1e-6; ties cannot cause it) or a value is NaN, numba's ``np.median``
    of the whole array gives the answer, so the result is always that median's (numpy's for values
    without NaN: for an even count the mean of the two middle values, (a + b) / 2)."""
    n = values.size
    if n < 4 * _MEDIAN_SUBSAMPLE:
        return np.median(values)
    half = n >> 1
    first = half - 1 if n % 2 == 0 else half
    low, high = _median_bracket(values, first, half)
    # branch-free loops (they vectorise; a branch per value, taken at random, cost 8 times as much)
    below = 0
    nans = 0
    for k in range(n):
        below += values[k] < low
        nans += values[k] != values[k]
    inside = np.empty(n + 1)
    count = 0
    for k in range(n):
        value = values[k]
        inside[count] = value
        count += (value >= low) & (value <= high)
    if nans or not (below <= first and half < below + count):
        return np.median(values)
    part = np.partition(inside[:count], first - below)
    a = part[first - below]
    if n % 2 == 1:
        return a
    b = np.inf
    for k in range(first - below + 1, count):
        b = min(b, part[k])
    return (a + b) / 2


@kernel(inline=True)
def _joined(parent, neighbour, label):  # pragma: no cover - compiled
    """The label of a pixel so far (0: none yet) once it meets a neighbour labelled ``neighbour`` (0:
    off): the two trees of the union-find ``parent`` joined under the smaller root (the earlier first
    pixel)."""
    if neighbour == 0:
        return label
    root = _root(parent, neighbour)
    if label == 0 or root == label:
        return root
    low, high = min(root, label), max(root, label)
    parent[high] = low
    return low


@kernel(inline=True)
def _root(parent, k):  # pragma: no cover - compiled
    """Root of ``k`` in the union-find forest ``parent``, the path to it compressed."""
    root = k
    while parent[root] != root:
        root = parent[root]
    while parent[k] != root:
        following = parent[k]
        parent[k] = root
        k = following
    return root


def _extended_centres(resid: np.ndarray, labels: np.ndarray, stats: np.ndarray, components: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Centre of mass (x, y) px of the positive residual and peak residual of each extended component,
    each computed inside the component's bounding box (a few, but large: the full-frame labelled
    statistics of ndimage sort the whole label image for each)."""
    xy = np.zeros((len(components), 2))
    peak = np.zeros(len(components))
    for i, k in enumerate(components):
        x0, y0 = stats[k, cv2.CC_STAT_LEFT], stats[k, cv2.CC_STAT_TOP]
        box = (slice(y0, y0 + stats[k, cv2.CC_STAT_HEIGHT]), slice(x0, x0 + stats[k, cv2.CC_STAT_WIDTH]))
        weights, peak[i] = _component_weights(resid[box], labels[box], k)
        rows, cols = np.arange(weights.shape[0])[:, None], np.arange(weights.shape[1])[None, :]  # the products as
        # with np.indices, without its two index arrays of the box; numpy's sums (pairwise, in its order)
        total = weights.sum()
        xy[i] = (x0 + (weights * cols).sum() / total, y0 + (weights * rows).sum() / total) if total > 0 else np.nan
    return xy, peak


@kernel
def _component_weights(resid, labels, k):  # pragma: no cover - compiled
    """(weights, peak) of component ``k`` in a box: ``where(labels == k, clip(resid, 0, None), 0)`` in double
    precision and the largest ``resid`` of its pixels (-inf without one), in one pass (numpy's masks,
    copies and clips of a bloom trail's full-column box were half of :func:`_extended_centres`)."""
    rows, cols = resid.shape
    weights = np.zeros((rows, cols))
    peak = -np.inf
    for r in range(rows):
        for c in range(cols):
            if labels[r, c] == k:
                value = np.float64(resid[r, c])
                weights[r, c] = value if value >= 0.0 else 0.0
                peak = max(peak, value)
    return weights, peak


@kernel
def _local_maxima(values, on_rows, on_cols, half):  # pragma: no cover - compiled
    """Rows and columns, in the order listed, of the listed (on) pixels no pixel of whose square of
    half-width ``half`` exceeds (indices beyond the frame clipped to its edge): where ``values``
    equals its maximum filter, tested only at those pixels (a few thousand, not the frame)."""
    rows, cols = values.shape
    out_r = np.empty(on_rows.size, np.int64)
    out_c = np.empty(on_rows.size, np.int64)
    k = 0
    for i in range(on_rows.size):
        r, c = on_rows[i], on_cols[i]
        value = values[r, c]
        peak = True
        for dr in range(-half, half + 1):
            rr = min(max(r + dr, 0), rows - 1)
            for dc in range(-half, half + 1):
                if values[rr, min(max(c + dc, 0), cols - 1)] > value:
                    peak = False
                    break
            if not peak:
                break
        if peak:
            out_r[k] = r
            out_c[k] = c
            k += 1
    return out_r[:k], out_c[:k]


def detect(
    image: np.ndarray,
    *,
    options: DetectOptions = DetectOptions(),
    saturation_adu: float | None = None,
    invalid: np.ndarray | None = None,
    lossy: bool = False,
) -> Detections:
    """Find point sources (and flag extended bodies) in a frame.

    Parameters
    ----------
    image : (H, W) array
        Frame in ADU, indexed ``[row, col]`` (:func:`opnav.image.io.read_image`).
    options : DetectOptions
        Thresholds and tests (module docstring).
    saturation_adu : float, optional
        Saturation level; pixels at or above it flag their source ``FLAG_SATURATED``.
    invalid : (H, W) bool array, optional
        Pixels that were NaN/inf in the file (``ImageMeta.invalid``).
    lossy : bool
        The frame went through lossy compression (``ImageMeta.lossy``, JPEG). Its block
        artefacts are correlated over 8 x 8 pixels and the compression smooths the noise the
        background step measures: the measured noise of the filtered frame sets the threshold
        (as for every frame, :func:`_detection_components`), times ``LOSSY_THRESHOLD_FACTOR``
        (the stretch of an 8-bit frame flattens star cores); a pixel is a hot pixel below
        ``LOSSY_NEIGHBOUR_RATIO`` (the compression spreads it) and the pixels within
        ``LOSSY_HIT_HALO_PX`` of it (its ringing) go with it; de-blending works on the
        detection-filtered frame and needs a dip of at least 30% and of 3 measured filtered-noise
        sigmas (a noise bump in the wing of a star is not a second source).

    Returns
    -------
    Detections
        Seeds (px), brightest first; an empty result when nothing passes.

    Raises
    ------
    FrameError
        Blank (constant) frame, or more than ``max_saturated_fraction`` of the pixels saturated.
    """
    image = np.asarray(image, dtype=float)
    if image.ndim != 2:
        raise FrameError(f"detect needs a 2-D image, got shape {image.shape}")
    if lossy:
        options = replace(options, threshold_sigma=LOSSY_THRESHOLD_FACTOR * options.threshold_sigma,
                          deblend_contrast=max(options.deblend_contrast, 0.3),
                          deblend_smooth_px=max(options.deblend_smooth_px, options.smooth_sigma_px),
                          min_neighbour_ratio=max(options.min_neighbour_ratio, LOSSY_NEIGHBOUR_RATIO))
    if invalid is not None and np.shape(invalid) != image.shape:
        raise InputError(f"invalid mask has shape {np.shape(invalid)}, the frame {image.shape}")
    valid = _ALL_VALID if invalid is None else ~np.asarray(invalid, bool)
    # one pass over the frame: finite and varied valid pixels, the saturated ones, the brightest values,
    # and the background's tile samples
    tile, bands = _tile_bands(image.shape, options.tile_px)
    masked = _ALL_INVALID_FREE if invalid is None else ~valid
    finite, varied, saturated_px, n_saturated, brightest = _frame_scan(
        image, valid, math.inf if saturation_adu is None else float(saturation_adu), _BRIGHTEST, masked, tile, bands)
    if not finite:
        raise FrameError("image contains NaN or infinite pixels not marked invalid; read it with read_image")
    if not varied:
        raise FrameError("frame is blank: every valid pixel has the same value")
    if n_saturated / saturated_px.size > options.max_saturated_fraction:
        raise FrameError(f"frame is {100 * n_saturated / saturated_px.size:.0f}% saturated "
                         f"(> {100 * options.max_saturated_fraction:.0f}%)")

    bg = _background_of_bands(bands, image.shape, tile, options.clip_sigma)
    if lossy:
        # A compressed sky can come out flat over whole blocks (zero measured noise) while block
        # edges and ringing of a few ADU remain: never trust a noise below the floor.
        bg = bg.with_noise_floor(LOSSY_NOISE_FLOOR_ADU)
    level_grid, iy, wy, ix, wx = bg.level_interpolation()
    # the residual in single precision (the filter below takes it so); the noise map is never made:
    # each pass interpolates its rows (a full-frame map and its copies were ~40 % of the extraction)
    resid = _residual(image, valid, invalid is not None, level_grid, iy, wy, ix, wx)
    hits, hit_rows, hit_cols = _sharp_hits(resid, bg, saturated_px, options)
    if lossy and saturated_px[hit_rows, hit_cols].any():
        # Compression rings around a strong spike: its neighbours belong to it, not to a source.
        strong = hits & saturated_px
        size = 2 * LOSSY_HIT_HALO_PX + 1
        hits |= cv2.dilate(strong.astype(np.uint8), np.ones((size, size), np.uint8)).astype(bool)
        hit_rows, hit_cols = np.nonzero(hits)
    # the hits' pixels by index (a few hundred): a boolean mask over the frame reads all of it
    resid[hit_rows, hit_cols] = 0.0
    saturated_px[hit_rows, hit_cols] = False
    if invalid is not None and not valid.all():
        # A hole in a star would split it in two at de-blending: fill holes from their neighbours.
        from scipy import ndimage  # only frames with invalid pixels: no start-up cost for the others

        resid = np.where(valid, resid, ndimage.grey_dilation(np.where(valid, resid, -np.inf), size=3))
        resid[~np.isfinite(resid)] = 0.0
    n_rejected = int(_count_groups(hits, hit_rows.astype(np.int64), hit_cols.astype(np.int64)))
    kernel = _gaussian_kernel(options.smooth_sigma_px)
    # the detection filter in single precision: a float64 filter took 5 times as long (OpenCV's, 6.1 against
    # 1.1 ms on 1 MP, the conversion included), and the threshold it feeds is at 5 sigmas, not at 1e-7 of
    # a value
    smooth = _smoothed(resid, kernel)
    # filtered noise max(noise, 1e-12) * gain * correlation: the correlation from a sample of pixels, the
    # threshold and the labelling in one pass over the frame (no full-frame map of the filtered noise is
    # kept; OpenCV's labelling read the frame again, and the statistics and peaks read every row that
    # held an on pixel: all of them beside a planet's bloom trail)
    gain = float(np.sum(kernel**2))
    # (with each component's statistics and sums over its pixels, in pixel order: ndimage's labelled
    # statistics sort the label image)
    correlation, n_comp, labels, on_r, on_c, on_label, stats, comp_sat, comp_invalid, comp_flux = _detection_components(
        smooth, bg, gain, None if invalid is None else valid, float(options.threshold_sigma), saturated_px, resid)
    empty = Detections(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, int), np.zeros(0, int),
                       np.zeros(0, int), labels, bg, hits, n_rejected, np.zeros(0), brightest=brightest)
    if n_comp <= 1:
        return empty
    index = np.arange(1, n_comp)
    area = stats[1:, cv2.CC_STAT_AREA]
    usable = area >= options.min_area_px
    extended = area > options.max_point_area_px

    # Candidate peaks: local maxima inside usable point-like components, found on a lightly smoothed
    # frame: the detection filter would merge pairs closer than ~2 of its own widths.
    # (single precision, as the detection filter and the residual)
    if options.deblend_smooth_px == options.smooth_sigma_px:
        fine, fine_gain = smooth, float(np.sum(kernel**2))  # the same filter: reuse it
    elif options.deblend_smooth_px > 0:
        fine_kernel = _gaussian_kernel(options.deblend_smooth_px).astype(np.float32)
        fine = _smoothed(resid, fine_kernel)
        fine_gain = float(np.sum(fine_kernel.astype(float)**2))
    else:
        fine, fine_gain = resid, 1.0
    # "on" pixels equal to the maximum of their (2 separation + 1)^2 square (edge pixels replicated),
    # in row-major order
    # (tested only in usable point-like components: a planet's thousands of pixels give it no seeds)
    point_ok = np.zeros(n_comp, bool)
    point_ok[1:] = usable & ~extended
    in_point = point_ok[on_label]
    cand_r, cand_c = _local_maxima(fine, on_r[in_point], on_c[in_point], int(options.deblend_separation_px))
    cand_label = labels[cand_r, cand_c]
    order = np.lexsort((-fine[cand_r, cand_c], cand_label))
    cand_r, cand_c, cand_label = cand_r[order], cand_c[order], cand_label[order]
    first = np.ones(len(cand_label), bool)  # (np.r_ and np.nan_to_num below cost ~40 us a call)
    first[1:] = cand_label[1:] != cand_label[:-1]
    keep = first.copy()
    blended = np.zeros(len(cand_r), bool)
    if options.deblend:
        starts = np.flatnonzero(first)
        ends = np.append(starts[1:], len(cand_r))
        for s, e in zip(starts, ends):
            # A clipped (saturated) core is flat and rings in lossy files: never split it.
            if e - s > 1 and not comp_sat[cand_label[s] - 1]:
                rc = np.stack([cand_r[s:e], cand_c[s:e]], -1)
                noise_f = max(float(bg.noise_at(rc[:1, 0], rc[:1, 1])[0]), 1e-12) * fine_gain
                if lossy:
                    # compressed pixels are correlated: the dip must beat the measured filtered noise
                    noise_f *= correlation
                k = _keep_deblended(fine, rc, noise_f, options.deblend_contrast)
                keep[s:e] = k
                if k.sum() > 1:
                    blended[s:e] = True
    cand_r, cand_c, cand_label, blended = cand_r[keep], cand_c[keep], cand_label[keep], blended[keep]
    xy_point = _subpixel_peak(fine, cand_r, cand_c)
    peak_point = np.array([resid[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2].max() for r, c in zip(cand_r, cand_c)],
                          float)

    ext_index = index[usable & extended]
    xy_ext, peak_ext = _extended_centres(resid, labels, stats, ext_index)

    xy = np.concatenate([xy_point, xy_ext])
    label = np.concatenate([cand_label, ext_index]).astype(int)
    peak = np.concatenate([peak_point, np.asarray(peak_ext, float)])
    flags = np.zeros(len(xy), int)
    flags[: len(cand_r)] |= np.where(blended, FLAG_BLENDED, 0)
    flags[len(cand_r):] |= FLAG_EXTENDED
    flags |= np.where(comp_sat[label - 1], FLAG_SATURATED, 0)
    flags |= np.where(comp_invalid[label - 1], FLAG_INVALID, 0)
    m = options.edge_margin_px
    h, w = image.shape
    near_edge = (xy[:, 0] < m) | (xy[:, 1] < m) | (xy[:, 0] > w - 1 - m) | (xy[:, 1] > h - 1 - m)
    flags |= np.where(near_edge, FLAG_EDGE, 0)
    flux = comp_flux[label - 1]
    # an extended component's NaN centre read at 0 (infinities are clipped to the edge)
    ext_x, ext_y = np.where(np.isnan(xy_ext), 0.0, xy_ext).T
    at_r = np.clip(np.rint(np.concatenate([cand_r, ext_y])), 0, h - 1).astype(int)
    at_c = np.clip(np.rint(np.concatenate([cand_c, ext_x])), 0, w - 1).astype(int)
    snr = smooth[at_r, at_c] / (np.maximum(bg.noise_at(at_r, at_c), 1e-12) * gain * correlation)
    order = np.lexsort((-peak, -flux))
    return Detections(
        xy=xy[order], peak=peak[order], flux=flux[order], area=area[label - 1][order].astype(int),
        flags=flags[order], label=label[order], labels=labels, background=bg, rejected=hits, n_rejected=n_rejected,
        snr=snr[order], boxes=stats[:, :4], brightest=brightest,
    )


#: Pixel values :func:`_frame_scan` keeps (:attr:`Detections.brightest`): :func:`saturation_plateau`'s
#: default ``min_pixels``.
_BRIGHTEST = 3


@kernel
def _frame_scan(image, valid, saturation, count, invalid, tile, bands):  # pragma: no cover - compiled
    """(every valid pixel finite, not all valid pixels equal, saturated mask (H, W) (valid pixels at or
    above ``saturation``), its count, the ``count`` largest values of every pixel, largest first (NaN
    when a pixel is NaN, as ``numpy.max``)) in one pass. ``valid`` is read when it has the frame's
    shape (a (1, 1) array: every pixel valid). No valid pixel: (True, False, ...).

    ``bands`` (:func:`_tile_bands`) is filled with the background's tile samples (:func:`_tile_band`,
    ``invalid`` its mask) as each row of ``tile``-px tiles is scanned, while its rows are in the cache
    (read again after the scan, the frame's sampled pixels cost 3 times as much)."""
    rows, cols = image.shape
    masked = valid.shape[0] == rows and valid.shape[1] == cols
    saturated = np.empty((rows, cols), np.bool_)
    top = np.full(count, -np.inf)
    first = np.nan
    found = False
    for r in range(rows):
        for c in range(cols):
            if not masked or valid[r, c]:
                first = image[r, c]
                found = True
                break
        if found:
            break
    finite = 0
    differ = 0
    n_saturated = 0
    for r in range(rows):
        # one simple loop a quantity over the row (8 KB at 1 MP, in cache): they vectorise, a loop
        # doing all of them did not (3.5 times as long)
        row, out = image[r], saturated[r]
        count_row = 0
        for c in range(cols):
            count_row += np.isfinite(row[c])
        finite += count_row
        count_row = 0
        if masked:
            ok = valid[r]
            for c in range(cols):
                count_row += ok[c] & (row[c] != first)
            for c in range(cols):
                out[c] = ok[c] & (row[c] >= saturation)
        else:
            for c in range(cols):
                count_row += row[c] != first
            for c in range(cols):
                out[c] = row[c] >= saturation
        differ += count_row
        count_row = 0
        for c in range(cols):
            count_row += out[c]
        n_saturated += count_row
        least = top[count - 1]
        count_row = 0
        for c in range(cols):
            count_row += row[c] > least
        if count_row:
            for c in range(cols):
                value = row[c]
                if value > top[count - 1]:
                    k = count - 1
                    while k > 0 and top[k - 1] < value:
                        top[k] = top[k - 1]
                        k -= 1
                    top[k] = value
        if (r + 1) % tile == 0 or r == rows - 1:
            _tile_band(image, invalid, tile, r // tile, bands[r // tile])
    valid_finite = True
    if finite < rows * cols:
        # a non-finite pixel somewhere (rare): whether a valid one is, and NaN brightest values for a NaN
        for r in range(rows):
            for c in range(cols):
                value = image[r, c]
                if np.isnan(value):
                    top[:] = np.nan
                if not np.isfinite(value) and (not masked or valid[r, c]):
                    valid_finite = False
    return valid_finite, differ > 0, saturated, n_saturated, top


def saturation_plateau(
    image: np.ndarray, background: Background, *, flat_sigma: float = 5.0, min_pixels: int = 3,
    min_height_sigma: float = 50.0, brightest: np.ndarray | None = None,
) -> float | None:
    """Level at which a frame's detector clips, found from the flat top its brightest pixels share.

    A detector clips at its full well (or its ADC's range), often far below the top of the file's
    storage type (a 16-bit file of a camera whose full well is 18 000 e- at 1 e-/ADU). The
    clipped cores of saturated stars and hot pixels are then flat at that level, a shape no
    point-spread function has, and a PSF fit that uses them both misplaces the star and (fitting
    the frame's noise from the pooled residuals) inflates every source's covariance.

    Parameters
    ----------
    image : (H, W) array
        Frame, ADU.
    background : Background
        Its background (:func:`estimate_background` or ``Detections.background``).
    flat_sigma : float
        Pixels within this many median background sigmas of the frame's maximum are on the plateau
        (a clipped level carries only the read noise, less than the sky's).
    min_pixels : int
        Pixels needed on the plateau: a clipped core is several pixels wide, a single peak is not.
    min_height_sigma : float
        The maximum must be this many background sigmas above the median background level: an
        unclipped Gaussian core has ``min_pixels`` pixels within ``flat_sigma`` sigmas of its peak
        only when the peak is below ~17 sigmas (sigma_psf 1.2 px: the nearest pixels are at 70 %).
    brightest : ndarray, optional
        The frame's largest pixel values, largest first (:attr:`Detections.brightest`): with at least
        ``min_pixels`` of them the frame is not read again (its maximum is the first, and
        ``min_pixels`` pixels reach a level when the ``min_pixels``-th largest does).

    Returns
    -------
    float or None
        The clipping level, ADU (pixels at or above it are clipped), or None when the frame shows
        no plateau.
    """
    known = brightest is not None and len(brightest) >= min_pixels >= 1
    if not known:
        image = np.asarray(image, dtype=float)
    top = float(brightest[0]) if known else float(np.max(image))
    # every value of the maps lies between their tiles' least and largest (the noise floor included), up
    # to the rounding of the interpolation: bounds that settle the tests below without a median when they
    # can (a frame without a flat top, or whose top is far above every tile's level)
    if known and float(brightest[min_pixels - 1]) < top - flat_sigma * _rounded_up(
            max(float(np.max(background.noise_tiles)), background.noise_floor)):
        return None  # below the lowest level the plateau can have
    # Medians of the maps at 4 x 4 points a tile (every 16th row and column of 64-px tiles): the maps are
    # bilinear between tile centres, so the sample holds each tile's value as the full map does (the
    # full map's median cost ~15 ms on 1 MP, every 4th pixel's 0.25 ms); by bracketing where the sample is
    # large (:func:`_exact_median`, numpy's number)
    sample_step = slice(None, None, max(1, background.tile_px // 4))
    # (the level's sample only when the tiles' bounds leave the test open: a saturated frame's top is far
    # above every tile's level)
    noise = float(_exact_median(background.noise_window(sample_step, sample_step).ravel()))
    if not (noise > 0.0):
        return None
    if top - _rounded_up(float(np.max(background.level_tiles))) < min_height_sigma * noise:
        level_sample = background.window(sample_step, sample_step)[0]
        if top - float(_exact_median(level_sample.ravel())) < min_height_sigma * noise:
            return None
    level = top - flat_sigma * noise
    if known:
        return level if float(brightest[min_pixels - 1]) >= level else None
    return level if int(np.count_nonzero(image >= level)) >= min_pixels else None


def _rounded_up(value: float) -> float:
    """``value`` raised by a billionth of its size: above any bilinear interpolation of values up to it (whose
    weights, summing to 1, round by a few units in the last place)."""
    return value + 1e-9 * abs(value)
