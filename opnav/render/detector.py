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

Variance of a flat frame of mean charge S (electrons) in ADU:
``(S + read_noise^2) / gain^2 + 1/12`` (the last term from rounding).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
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


def dark_map(shape: tuple[int, int], camera: Camera, options: DetectorOptions, origin_xy: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Dark rate per pixel (electrons/s) of the window at ``origin_xy`` with ``shape``, hot pixels included."""
    dark = np.full(shape, camera.dark_current_e_s, dtype=float)
    rows, cols = hot_pixels(camera, options)
    rows, cols = rows - origin_xy[1], cols - origin_xy[0]
    inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
    dark[rows[inside], cols[inside]] *= options.hot_pixel_factor
    return dark


def cosmic_rays(shape: tuple[int, int], camera: Camera, options: DetectorOptions, rng: np.random.Generator) -> np.ndarray:
    """Charge (electrons) deposited by cosmic rays during one exposure, image of ``shape``."""
    charge = np.zeros(shape)
    area_cm2 = shape[0] * shape[1] * (camera.pixel_pitch_um * 1.0e-4) ** 2
    n_events = rng.poisson(options.cosmic_ray_rate_cm2_s * area_cm2 * camera.exposure_s)
    if n_events == 0:
        return charge
    start = rng.uniform([0.0, 0.0], [shape[1], shape[0]], size=(n_events, 2)) - 0.5
    # Isotropic flux through a plane: cos(theta) distributed as sqrt(uniform).
    cos_theta = np.sqrt(rng.uniform(1e-6, 1.0, n_events))
    tan_theta = np.sqrt(1.0 - cos_theta**2) / cos_theta
    length_px = np.minimum(options.depletion_um * tan_theta / camera.pixel_pitch_um, max(shape))
    azimuth = rng.uniform(0.0, 2.0 * np.pi, n_events)
    path_um = options.depletion_um / cos_theta
    total_e = MIP_ELECTRONS_PER_UM * path_um
    for p0, length, phi, electrons in zip(start, length_px, azimuth, total_e):
        n_steps = int(math.ceil(length * 2.0)) + 1
        s = np.linspace(0.0, length, n_steps)
        cols = np.rint(p0[0] + s * math.cos(phi)).astype(int)
        rows = np.rint(p0[1] + s * math.sin(phi)).astype(int)
        keep = (cols >= 0) & (cols < shape[1]) & (rows >= 0) & (rows < shape[0])
        np.add.at(charge, (rows[keep], cols[keep]), electrons / n_steps)
    return charge


def bloom(charge: np.ndarray, full_well_e: float) -> np.ndarray:
    """Spill charge above ``full_well_e`` up and down each column (half each way).

    Returns a new array; every pixel ends at or below the full well and charge
    is conserved except what runs off the column ends.

    Notes
    -----
    Each contiguous run of saturated pixels in a column is flattened to the full
    well and its total excess is split in two; each half fills the free room
    (full well minus charge) of the pixels beyond that end of the run, nearest
    first, found with a cumulative sum.
    """
    out = np.array(charge, dtype=float)
    for col in np.nonzero(np.any(out > full_well_e, axis=0))[0]:
        column = out[:, col]
        saturated = np.concatenate([[False], column > full_well_e, [False]])
        edges = np.flatnonzero(np.diff(saturated.astype(np.int8)))
        for first, stop in zip(edges[::2], edges[1::2]):
            excess = float(np.sum(column[first:stop]) - full_well_e * (stop - first))
            if excess <= 0.0:
                continue
            column[first:stop] = full_well_e
            _spill(column, np.arange(first - 1, -1, -1), excess / 2.0, full_well_e)
            _spill(column, np.arange(stop, column.size), excess / 2.0, full_well_e)
        out[:, col] = column
    return out


def _spill(column: np.ndarray, order: np.ndarray, amount: float, full_well_e: float) -> None:
    """Pour ``amount`` electrons into ``column[order]`` nearest first, up to the full well."""
    if order.size == 0:
        return
    room = np.clip(full_well_e - column[order], 0.0, None)
    filled = np.cumsum(room)
    n_full = int(np.searchsorted(filled, amount))
    column[order[:n_full]] += room[:n_full]
    if n_full < order.size:
        column[order[n_full]] += amount - (filled[n_full - 1] if n_full > 0 else 0.0)


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
    if not np.all(np.isfinite(signal_e)) or np.any(signal_e < 0):
        raise InputError("signal image must be finite and non-negative")
    if options.noise_free:
        charge = signal_e + dark_map(signal_e.shape, camera, options, origin_xy) * camera.exposure_s
        charge = bloom(charge, camera.full_well_e) if options.blooming else np.minimum(charge, camera.full_well_e)
        return charge / camera.gain_e_per_adu + camera.bias_adu
    if rng is None:
        raise InputError("a numpy.random.Generator (rng) is required unless noise_free=True")
    dark = dark_map(signal_e.shape, camera, options, origin_xy)
    charge = rng.poisson(signal_e + dark * camera.exposure_s).astype(float)
    if options.cosmic_ray_rate_cm2_s > 0:
        # A stream of their own (spawning draws nothing from rng), so the rate changes only the
        # hits: the same seed gives the same photon and read noise with or without a storm.
        charge += cosmic_rays(signal_e.shape, camera, options, rng.spawn(1)[0])
    charge = bloom(charge, camera.full_well_e) if options.blooming else np.minimum(charge, camera.full_well_e)
    if camera.read_noise_e > 0:
        charge += rng.normal(0.0, camera.read_noise_e, signal_e.shape)
    adu = np.rint(charge / camera.gain_e_per_adu + camera.bias_adu)
    return np.clip(adu, 0, 2**camera.bit_depth - 1).astype(adu_dtype(camera))


def flat_variance_adu2(signal_e: float, camera: Camera) -> float:
    """Model variance (ADU^2) of one pixel of a flat frame with ``signal_e`` mean photo-electrons.

    Shot noise of signal plus dark, read noise, and the 1/12 ADU^2 of rounding
    (no hot pixels or cosmic rays).
    """
    charge = signal_e + camera.dark_current_e_s * camera.exposure_s
    return (charge + camera.read_noise_e**2) / camera.gain_e_per_adu**2 + 1.0 / 12.0
