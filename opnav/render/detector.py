"""Detector: expected electrons -> digital numbers (ADU), with every noise source.

Steps, in the order the charge sees them:

1. Dark current ``dark_current_e_s * exposure`` is added to the expected signal;
   hot pixels get ``hot_pixel_factor`` times the dark rate. They are a property
   of the detector, not of the frame: their positions come from a generator
   seeded with ``hot_pixel_seed``, so every frame (and every window) of one
   camera shows the same hot pixels.
2. Photon and dark shot noise: Poisson draw of the total expected charge.
3. Cosmic-ray hits: a Poisson number of events with mean
   ``rate * detector area * exposure``. The default rate, 5 events cm^-2 s^-1,
   is the galactic-cosmic-ray flux behind light shielding in interplanetary
   space near solar minimum (about 4 protons cm^-2 s^-1 plus heavier ions;
   e.g. the Hubble WFC3/ACS and Gaia in-flight rates of 1-6 cm^-2 s^-1).
   Each event crosses ``depletion_um`` of silicon at an isotropic random angle
   and leaves 80 e-/um along its path (a minimum-ionising particle), spread over
   the pixels its projected track crosses.
4. Saturation and blooming: charge above the full well of a pixel spills
   equally up and down its column into the next unsaturated pixels; charge that
   reaches the ends of the column is lost.
5. Read noise (Gaussian, electrons), gain (electrons per ADU), bias (ADU),
   rounding to integers and clipping to the ADC range ``[0, 2^bits - 1]``.

``noise_free=True`` returns the expected value ``(signal + dark) / gain + bias``
as floats (no Poisson, read noise, cosmic rays or quantisation; hot pixels and
saturation still apply), which tests use for exact photometry and astrometry.

:func:`read_out_windows` reads several detector windows (:class:`WindowLayout`) in one pass,
each with the statistics of a read-out of that window alone.

Variance of a flat frame of mean charge S (electrons) in ADU:
``(S + read_noise^2) / gain^2 + 1/12`` (the last term from rounding).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..camera import Camera
from ..compiled import kernel
from ..errors import InputError

#: Charge left by a minimum-ionising particle in silicon, electrons per micrometre.
MIP_ELECTRONS_PER_UM = 80.0


@dataclass(frozen=True)
class DetectorOptions:
    """Noise switches and rates for :func:`read_out`.

    Parameters
    ----------
    noise_free : bool
        Return the expected ADU (float) without random draws.
    cosmic_ray_rate_cm2_s : float
        Cosmic-ray events per cm^2 per second (default 5, deep space).
    depletion_um : float
        Sensitive silicon thickness crossed by a cosmic ray, micrometres.
    hot_pixel_fraction : float
        Fraction of pixels that are hot.
    hot_pixel_factor : float
        Dark-rate multiplier of a hot pixel.
    hot_pixel_seed : int
        Seed of the detector's (fixed) hot-pixel map.
    hot_pixel_clusters : int
        Clusters of 3 x 3 hot pixels (radiation damage) added to the map, from the same seed.
    blooming : bool
        Spill charge above the full well along columns (otherwise clip).
    """

    noise_free: bool = False
    cosmic_ray_rate_cm2_s: float = 5.0
    depletion_um: float = 10.0
    hot_pixel_fraction: float = 1.0e-5
    hot_pixel_factor: float = 1000.0
    hot_pixel_seed: int = 0
    hot_pixel_clusters: int = 0
    blooming: bool = True

    def __post_init__(self) -> None:
        for name in ("cosmic_ray_rate_cm2_s", "hot_pixel_fraction"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"detector {name} must be >= 0, got {value!r}")
        for name in ("depletion_um", "hot_pixel_factor"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"detector {name} must be positive, got {value!r}")
        if int(self.hot_pixel_clusters) != self.hot_pixel_clusters or self.hot_pixel_clusters < 0:
            raise InputError(f"detector hot_pixel_clusters must be an integer >= 0, got {self.hot_pixel_clusters!r}")
        if self.hot_pixel_fraction > 1:
            raise InputError(f"detector hot_pixel_fraction must be <= 1, got {self.hot_pixel_fraction!r}")


def adu_dtype(camera: Camera) -> type:
    """Smallest unsigned integer type holding the camera's ADC range."""
    return np.uint16 if camera.bit_depth <= 16 else np.uint32


def hot_pixels(camera: Camera, options: DetectorOptions) -> tuple[np.ndarray, np.ndarray]:
    """Full-detector (rows, cols) of the hot pixels, fixed by ``options.hot_pixel_seed``."""
    n_pixels = camera.width_px * camera.height_px
    n_hot = int(round(options.hot_pixel_fraction * n_pixels))
    rng = np.random.default_rng(options.hot_pixel_seed)
    flat = rng.integers(0, n_pixels, n_hot)
    rows, cols = np.divmod(flat, camera.width_px)
    if options.hot_pixel_clusters:
        # drawn after the single pixels, so adding clusters leaves those where they were
        centres = rng.integers(0, n_pixels, int(options.hot_pixel_clusters))
        c_rows, c_cols = np.divmod(centres, camera.width_px)
        d_rows, d_cols = np.divmod(np.arange(9), 3)
        c_rows = np.clip(c_rows[:, None] + d_rows - 1, 0, camera.height_px - 1).ravel()
        c_cols = np.clip(c_cols[:, None] + d_cols - 1, 0, camera.width_px - 1).ravel()
        rows, cols = np.concatenate([rows, c_rows]), np.concatenate([cols, c_cols])
    return rows, cols


@dataclass(frozen=True)
class WindowLayout:
    """Detector windows whose pixels are stored one after another in one flat array.

    Window ``k`` covers full-frame rows ``y0[k] .. y0[k] + rows[k] - 1`` and columns
    ``x0[k] .. x0[k] + cols[k] - 1`` (pixels, 0-based) and occupies
    ``flat[start[k]:start[k + 1]]``, row-major. Windows must not overlap (a full-frame pixel
    is read out once). One read-out over the flat array serves every window at once.
    """

    x0: np.ndarray
    y0: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    start: np.ndarray  # (windows + 1,): the last entry is the number of pixels

    @classmethod
    def from_boxes(cls, boxes: Sequence[tuple[int, int, int, int]]) -> WindowLayout:
        """Layout of boxes ``(x0, y0, x1, y1)``, inclusive full-frame pixels, in their order."""
        box = np.array(boxes, dtype=np.int64).reshape(-1, 4)
        rows, cols = box[:, 3] - box[:, 1] + 1, box[:, 2] - box[:, 0] + 1
        start = np.concatenate([[0], np.cumsum(rows * cols)])
        return cls(x0=box[:, 0], y0=box[:, 1], rows=rows, cols=cols, start=start)

    @property
    def size(self) -> int:
        """Pixels of all windows."""
        return int(self.start[-1])

    def views(self, flat: np.ndarray) -> list[np.ndarray]:
        """The (rows, cols) window views into ``flat``, in layout order (no copies)."""
        return [flat[a:b].reshape(r, c) for a, b, r, c in
                zip(self.start[:-1].tolist(), self.start[1:].tolist(), self.rows.tolist(), self.cols.tolist())]

    def columns(self) -> np.ndarray:
        """Full-frame column of every pixel of the flat array."""
        window = np.repeat(np.arange(self.x0.size), self.rows * self.cols)
        local = np.arange(self.size) - self.start[window]
        return self.x0[window] + local % self.cols[window]

    def flat_index(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Flat-array index of each full-frame pixel (``rows``, ``cols``) inside a window; the
        pixels outside every window are dropped."""
        r = rows[:, None] - self.y0[None]
        c = cols[:, None] - self.x0[None]
        pixel, window = np.nonzero((r >= 0) & (r < self.rows) & (c >= 0) & (c < self.cols))
        return self.start[window] + r[pixel, window] * self.cols[window] + c[pixel, window]


def _dark_rate(layout: WindowLayout, camera: Camera, options: DetectorOptions) -> np.ndarray:
    """Dark rate (electrons/s) of every pixel of ``layout``'s flat array, hot pixels included."""
    dark = np.full(layout.size, camera.dark_current_e_s, dtype=float)
    # A pixel listed twice (a cluster over a single hot pixel) is hot once: fancy-index
    # assignment applies the factor once per distinct index.
    dark[layout.flat_index(*hot_pixels(camera, options))] *= options.hot_pixel_factor
    return dark


#: Cosmic-ray tracks per pixel in one exposure above which a frame is refused (:func:`_add_cosmic_rays`).
MAX_COSMIC_RAYS_PER_PIXEL = 10.0


def _add_cosmic_rays(charge: np.ndarray, layout: WindowLayout, camera: Camera, options: DetectorOptions,
                     rng: np.random.Generator) -> None:
    """Add the charge (electrons) cosmic rays deposit during one exposure to ``charge``, the flat
    array of ``layout``; each window is hit as a detector of its own area (tracks start inside it
    and are cut at its edges)."""
    pitch_cm = camera.pixel_pitch_um * 1.0e-4
    area_cm2 = (layout.rows * layout.cols) * pitch_cm**2
    expected = options.cosmic_ray_rate_cm2_s * area_cm2 * camera.exposure_s
    # Beyond ~MAX_COSMIC_RAYS_PER_PIXEL tracks a pixel the frame is cosmic-ray charge and nothing else, and the
    # track list alone would outgrow any memory (an exposure of 1e9 s asks for ~50 TiB): refused, not drawn.
    per_pixel = float(np.max(expected / (layout.rows * layout.cols), initial=0.0))  # no window: nothing to hit
    if per_pixel > MAX_COSMIC_RAYS_PER_PIXEL:
        limit_s = camera.exposure_s * MAX_COSMIC_RAYS_PER_PIXEL / per_pixel
        raise InputError(f"camera exposure_s = {camera.exposure_s:g} s: at a cosmic-ray rate of "
                         f"{options.cosmic_ray_rate_cm2_s:g} /cm^2/s every pixel would be crossed ~{per_pixel:.3g} times "
                         f"in one exposure; use an exposure below {limit_s:.3g} s or cosmic_ray_rate_cm2_s = 0")
    n_events = rng.poisson(expected)
    total = int(n_events.sum())
    if total == 0:
        return
    window = np.repeat(np.arange(n_events.size), n_events)
    rows, cols = layout.rows[window], layout.cols[window]
    start = rng.uniform(0.0, np.stack([cols, rows], -1).astype(float)) - 0.5
    # Isotropic flux through a plane: cos(theta) distributed as sqrt(uniform).
    cos_theta = np.sqrt(rng.uniform(1e-6, 1.0, total))
    tan_theta = np.sqrt(1.0 - cos_theta**2) / cos_theta
    length_px = np.minimum(options.depletion_um * tan_theta / camera.pixel_pitch_um, np.maximum(rows, cols))
    azimuth = rng.uniform(0.0, 2.0 * np.pi, total)
    total_e = MIP_ELECTRONS_PER_UM * (options.depletion_um / cos_theta)  # 80 e-/um along the slant path
    # Each track sampled every half pixel or less (n points from its start to its end, as
    # np.linspace), the event's charge shared equally among the points: all events at once.
    n_steps = np.ceil(2.0 * length_px).astype(np.int64) + 1
    event = np.repeat(np.arange(total), n_steps)
    step = np.arange(event.size) - (np.cumsum(n_steps) - n_steps)[event]  # 0 .. n - 1 along each track
    along = step * (length_px / np.maximum(n_steps - 1, 1))[event]
    c = np.rint(start[event, 0] + along * np.cos(azimuth)[event]).astype(np.int64)
    r = np.rint(start[event, 1] + along * np.sin(azimuth)[event]).astype(np.int64)
    keep = (c >= 0) & (c < cols[event]) & (r >= 0) & (r < rows[event])
    event = event[keep]
    np.add.at(charge, layout.start[window[event]] + r[keep] * cols[event] + c[keep], (total_e / n_steps)[event])


def bloom(charge: np.ndarray, full_well_e: float) -> np.ndarray:
    """Spill charge above ``full_well_e`` up and down each column (half each way).

    Returns a new array; every pixel ends at or below the full well and charge
    is conserved except what runs off the column ends.

    Notes
    -----
    Each contiguous run of saturated pixels in a column is flattened to the full
    well and its total excess is split in two; each half fills the free room
    (full well minus charge) of the pixels beyond that end of the run, nearest
    first. The runs are those of the column as it came in (pixels poured into
    never start a run), processed top to bottom. Compiled: a bright body saturates
    tens of columns, each a short sequential fill.
    """
    out = np.array(charge, dtype=float)
    if out.ndim != 2:
        raise InputError(f"charge image must be 2-D, got shape {out.shape}")
    _bloom_kernel(out, float(full_well_e))
    return out


@kernel
def _bloom_kernel(out, full_well):  # pragma: no cover - compiled
    """:func:`bloom` in place on the 2-D float array ``out``."""
    rows, cols = out.shape
    saturated = np.empty(rows, np.bool_)
    for col in range(cols):
        for row in range(rows):
            saturated[row] = out[row, col] > full_well
        row = 0
        while row < rows:
            if not saturated[row]:
                row += 1
                continue
            first = row
            total = 0.0
            while row < rows and saturated[row]:
                total += out[row, col]
                row += 1
            excess = total - full_well * (row - first)
            if excess <= 0.0:
                continue
            for k in range(first, row):
                out[k, col] = full_well
            _spill(out, col, first - 1, -1, excess / 2.0, full_well)
            _spill(out, col, row, 1, excess / 2.0, full_well)


@kernel
def _spill(out, col, start, step, amount, full_well):  # pragma: no cover - compiled
    """Pour ``amount`` electrons into column ``col`` from row ``start`` on in steps of ``step``,
    nearest first, each pixel up to the full well; what passes the column's end is lost."""
    rows = out.shape[0]
    poured = 0.0
    row = start
    while 0 <= row < rows:
        room = max(full_well - out[row, col], 0.0)
        if poured + room >= amount:
            out[row, col] += amount - poured
            return
        out[row, col] += room
        poured += room
        row += step


def read_out(
    signal_e: np.ndarray,
    camera: Camera,
    *,
    options: DetectorOptions = DetectorOptions(),
    rng: np.random.Generator | None = None,
    origin_xy: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """Turn an expected-signal image (electrons, no dark) into ADU.

    Parameters
    ----------
    signal_e : (rows, cols) array
        Expected photo-electrons per pixel over the exposure.
    camera : Camera
        Dark current, full well, read noise, gain, bias, bit depth and exposure.
    options : DetectorOptions
    rng : numpy.random.Generator
        Required unless ``options.noise_free``.
    origin_xy : (int, int)
        Full-frame pixel (x, y) of ``signal_e[0, 0]`` when reading out a window.

    Returns
    -------
    (rows, cols) array
        float64 expected ADU when noise-free, else unsigned integers (see :func:`adu_dtype`).
    """
    signal_e = np.asarray(signal_e, dtype=float)
    if signal_e.ndim != 2:
        raise InputError(f"signal image must be 2-D, got shape {signal_e.shape}")
    rows, cols = signal_e.shape
    layout = WindowLayout.from_boxes([(origin_xy[0], origin_xy[1], origin_xy[0] + cols - 1, origin_xy[1] + rows - 1)])
    return read_out_windows(signal_e.ravel(), layout, camera, options=options, rng=rng).reshape(rows, cols)


def read_out_windows(
    signal_e: np.ndarray,
    layout: WindowLayout,
    camera: Camera,
    *,
    options: DetectorOptions = DetectorOptions(),
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Read out every window of ``layout`` at once: each as :func:`read_out` would on its own.

    Dark, hot pixels, shot noise, read noise and quantisation are per pixel, so one draw over
    all windows' pixels has the statistics of one draw per window; cosmic rays hit each window
    as a detector of its area and blooming runs along each window's columns (charge spilling
    past a window's top or bottom row is lost), as in a read-out of that window alone.

    Parameters
    ----------
    signal_e : (layout.size,) array
        Expected photo-electrons per pixel over the exposure, windows one after another
        (:class:`WindowLayout`).
    layout : WindowLayout
    camera, options, rng
        As :func:`read_out`.

    Returns
    -------
    (layout.size,) array
        float64 expected ADU when noise-free, else unsigned integers (see :func:`adu_dtype`).
    """
    signal_e = np.asarray(signal_e, dtype=float)
    if signal_e.shape != (layout.size,):
        raise InputError(f"signal must be flat with the layout's {layout.size} pixels, got shape {signal_e.shape}")
    if not np.all(np.isfinite(signal_e)) or np.any(signal_e < 0):
        raise InputError("signal image must be finite and non-negative")
    expected = signal_e + _dark_rate(layout, camera, options) * camera.exposure_s
    if options.noise_free:
        _saturate(expected, layout, camera.full_well_e, options.blooming)
        return expected / camera.gain_e_per_adu + camera.bias_adu
    if rng is None:
        raise InputError("a numpy.random.Generator (rng) is required unless noise_free=True")
    charge = rng.poisson(expected).astype(float)
    if options.cosmic_ray_rate_cm2_s > 0:
        # A stream of their own (spawning draws nothing from rng), so the rate changes only the
        # hits: the same seed gives the same photon and read noise with or without a storm.
        _add_cosmic_rays(charge, layout, camera, options, rng.spawn(1)[0])
    _saturate(charge, layout, camera.full_well_e, options.blooming)
    if camera.read_noise_e > 0:
        charge += rng.normal(0.0, camera.read_noise_e, charge.size)
    adu = np.rint(charge / camera.gain_e_per_adu + camera.bias_adu)
    return np.clip(adu, 0, 2**camera.bit_depth - 1).astype(adu_dtype(camera))


def _saturate(charge: np.ndarray, layout: WindowLayout, full_well_e: float, blooming: bool) -> None:
    """Bloom (or clip) ``charge``, the flat array of ``layout``, to the full well in place."""
    if not blooming:
        np.minimum(charge, full_well_e, out=charge)
        return
    if layout.size == 0:
        return
    # Blooming leaves a window without a pixel above the full well as it is: only the others
    # (bright sources) are visited, each on its own (charge runs off its top and bottom rows).
    full = np.maximum.reduceat(charge, layout.start[:-1]) > full_well_e
    for k in np.flatnonzero(full):
        _bloom_kernel(charge[layout.start[k]:layout.start[k + 1]].reshape(layout.rows[k], layout.cols[k]),
                      float(full_well_e))


def flat_variance_adu2(signal_e: float, camera: Camera) -> float:
    """Model variance (ADU^2) of one pixel of a flat frame with ``signal_e`` mean photo-electrons.

    Shot noise of signal plus dark, read noise, and the 1/12 ADU^2 of rounding
    (no hot pixels or cosmic rays).
    """
    charge = signal_e + camera.dark_current_e_s * camera.exposure_s
    return (charge + camera.read_noise_e**2) / camera.gain_e_per_adu**2 + 1.0 / 12.0
