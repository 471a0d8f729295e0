"""Point-spread functions rendered as small stamps, vectorised over sources.

Only a square stamp around each source is evaluated, never the full frame per
star. Two shapes are offered:

* ``gaussian`` (default): the exact pixel integral of a circular Gaussian of
  standard deviation ``sigma_px``. Pixel (i, j) spans [i - 1/2, i + 1/2] in each
  axis (pixel centres at integers, docs/conventions.md), so the fraction of the
  flux falling in column i from a source at x is
  ``(erf((i + 1/2 - x) / (sqrt(2) sigma)) - erf((i - 1/2 - x) / (sqrt(2) sigma))) / 2``;
  the stamp is the outer product of the row and column fractions.
* ``airy``: the diffraction pattern of a clear circular aperture,
  ``I(v) = (2 J1(v) / v)^2`` with ``v = 3.8317 r / r0`` (r0 the first dark ring,
  ``1.22 lambda f / D`` in pixels), optionally convolved with a uniform defocus
  disk of radius ``defocus_px``. It is sampled on ``subsample x subsample``
  points per pixel and normalised with the analytic total power
  ``4 pi / k^2`` (k = 3.8317 / r0), so the flux beyond the stamp is lost, as on
  a real detector, rather than folded back in.

Linear smear: a source that moves during the exposure is drawn as the mean of
``K`` copies along its path (positions supplied per source, at the mid-points
of K equal time slices; see :func:`opnav.render.scene.smear_path_px`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import erf, j1

from ..errors import InputError

_AIRY_FIRST_ZERO = 3.831705970207512
PSF_KINDS = ("gaussian", "airy")


@dataclass(frozen=True)
class PSF:
    """Point-spread function options.

    Parameters
    ----------
    kind : {"gaussian", "airy"}
        Pixel-integrated Gaussian (exact erf integrals) or Airy pattern (sub-sampled).
    sigma_px : float
        Gaussian standard deviation, pixels.
    airy_first_zero_px : float
        Radius of the first Airy dark ring, ``1.22 lambda f / D``, pixels.
    defocus_px : float
        Radius of a uniform defocus blur disk convolved with the Airy pattern, pixels (0 = none).
    subsample : int
        Samples per pixel per axis for the Airy option.
    radius_px : int or None
        Stamp half-width, pixels; default ``ceil(6 sigma) + 1`` (Gaussian) or
        ``ceil(6 r0 + defocus) + 1`` (Airy).
    """

    kind: str = "gaussian"
    sigma_px: float = 1.0
    airy_first_zero_px: float = 1.5
    defocus_px: float = 0.0
    subsample: int = 5
    radius_px: int | None = None

    def __post_init__(self) -> None:
        if self.kind not in PSF_KINDS:
            raise InputError(f"psf kind must be one of {', '.join(PSF_KINDS)}, got {self.kind!r}")
        for name in ("sigma_px", "airy_first_zero_px"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"psf {name} must be a positive finite number, got {value!r}")
        if not (math.isfinite(self.defocus_px) and self.defocus_px >= 0):
            raise InputError(f"psf defocus_px must be >= 0, got {self.defocus_px!r}")
        if not (isinstance(self.subsample, int) and self.subsample >= 1):
            raise InputError(f"psf subsample must be a positive integer, got {self.subsample!r}")
        if self.radius_px is not None and not (isinstance(self.radius_px, int) and self.radius_px >= 1):
            raise InputError(f"psf radius_px must be a positive integer, got {self.radius_px!r}")

    @property
    def half_width_px(self) -> int:
        """Stamp half-width actually used, pixels."""
        if self.radius_px is not None:
            return self.radius_px
        if self.kind == "gaussian":
            return int(math.ceil(6.0 * self.sigma_px)) + 1
        return int(math.ceil(6.0 * self.airy_first_zero_px + self.defocus_px)) + 1

    @property
    def sigma_equivalent_px(self) -> float:
        """Standard deviation of the Gaussian with the same FWHM, pixels (for image-stage priors)."""
        if self.kind == "gaussian":
            return self.sigma_px
        # Airy FWHM = 1.029 lambda/D = 0.8436 r0; a defocus disk of radius a has sigma a/2.
        sigma_airy = 0.8436 * self.airy_first_zero_px / 2.3548
        return math.hypot(sigma_airy, self.defocus_px / 2.0)


@dataclass(frozen=True)
class Stamps:
    """Rendered stamps: ``values[n]`` covers rows ``y0[n]..y0[n]+Sy-1``, columns ``x0[n]..x0[n]+Sx-1``.

    ``values`` is (N, Sy, Sx) in the unit of the flux passed in (usually electrons).
    """

    x0: np.ndarray
    y0: np.ndarray
    values: np.ndarray


def _gaussian_fractions(edges: np.ndarray, centre: np.ndarray, sigma: float) -> np.ndarray:
    """Fraction of a 1-D Gaussian centred at ``centre`` falling between consecutive ``edges``
    (last axis, ascending); ``centre`` broadcasts against ``edges``. One erf per edge: the
    upper edge of a pixel is the lower edge of the next."""
    scale = 1.0 / (math.sqrt(2.0) * sigma)
    return 0.5 * np.diff(erf((edges - centre) * scale), axis=-1)


def _airy_density(dx: np.ndarray, dy: np.ndarray, first_zero_px: float) -> np.ndarray:
    """Airy intensity per unit pixel area, integrating to 1 over the plane."""
    k = _AIRY_FIRST_ZERO / first_zero_px
    v = k * np.hypot(dx, dy)
    with np.errstate(invalid="ignore", divide="ignore"):
        pattern = np.where(v > 1e-8, (2.0 * j1(v) / np.where(v > 1e-8, v, 1.0)) ** 2, 1.0)
    return pattern * k * k / (4.0 * math.pi)


def _defocus_offsets(radius_px: float, subsample: int) -> np.ndarray:
    """Sample points (M, 2) filling a uniform disk of ``radius_px`` (equal weights)."""
    if radius_px == 0.0:
        return np.zeros((1, 2))
    n = max(3, int(math.ceil(2.0 * radius_px * subsample)))
    grid = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    gx, gy = np.meshgrid(grid, grid)
    inside = gx * gx + gy * gy <= 1.0
    return radius_px * np.stack([gx[inside], gy[inside]], -1)


def render_stamps(xy_px: np.ndarray, flux: np.ndarray, psf: PSF, *, path_px: np.ndarray | None = None) -> Stamps:
    """Render one PSF stamp per source.

    Parameters
    ----------
    xy_px : (N, 2) array
        Source positions (x = column, y = row), pixels, conventions of docs/conventions.md.
        Ignored for the shape when ``path_px`` is given, but sets the stamp origin.
    flux : (N,) array
        Total flux of each source (any unit, typically electrons).
    psf : PSF
    path_px : (N, K, 2) array, optional
        Positions along each source's path during the exposure (equal time steps);
        the stamp is the mean PSF over the path (linear smear).

    Returns
    -------
    Stamps
        Stamps sized to hold the PSF plus the path extent.
    """
    xy_px = np.asarray(xy_px, dtype=float).reshape(-1, 2)
    flux = np.asarray(flux, dtype=float).reshape(-1)
    if path_px is None:
        path = xy_px[:, None, :]
    else:
        path = np.asarray(path_px, dtype=float)
        if path.ndim != 3 or path.shape[0] != xy_px.shape[0] or path.shape[2] != 2:
            raise InputError(f"path_px must have shape (N, K, 2) with N = {xy_px.shape[0]}, got {path.shape}")
    extent = np.max(np.abs(path - xy_px[:, None, :]), axis=(0, 1)) if path.size else np.zeros(2)
    half = psf.half_width_px + int(math.ceil(float(np.max(extent, initial=0.0))))
    size = 2 * half + 1
    centre = np.round(xy_px).astype(int)
    x0 = centre[:, 0] - half
    y0 = centre[:, 1] - half
    offsets = np.arange(size, dtype=float)
    # Pixel coordinates relative to each stamp origin; path positions follow the same shift.
    rel = path - np.stack([x0, y0], -1)[:, None, :].astype(float)
    if psf.kind == "gaussian":
        # (N, K, axis, size): fraction of each path position's flux in each column (x) and row (y)
        fractions = _gaussian_fractions(np.arange(size + 1) - 0.5, rel[..., None], psf.sigma_px)
        fx, fy = fractions[:, :, 0], fractions[:, :, 1]
        # Mean over the path of the outer products fy fx. (A batched matmul is ~8x faster but sums
        # in another order: the rounding it changes, amplified by the FFT of a bright resolved
        # body's patch, moved noise-free pixels by 1e-8 of their value.)
        values = np.einsum("nky,nkx->nyx", fy, fx) / path.shape[1]
    else:
        values = _airy_stamps(rel, offsets, psf)
    return Stamps(x0=x0, y0=y0, values=values * flux[:, None, None])


def _airy_stamps(rel: np.ndarray, offsets: np.ndarray, psf: PSF) -> np.ndarray:
    n_src, n_path = rel.shape[:2]
    size = offsets.size
    sub = (np.arange(psf.subsample) + 0.5) / psf.subsample - 0.5
    # Sub-sample positions in stamp coordinates, one row/column of sub-pixels per pixel.
    fine = (offsets[:, None] + sub[None, :]).reshape(-1)
    disk = _defocus_offsets(psf.defocus_px, psf.subsample)
    values = np.zeros((n_src, size, size))
    for point in disk:
        for k in range(n_path):
            cx = rel[:, k, 0] + point[0]
            cy = rel[:, k, 1] + point[1]
            dens = _airy_density(fine[None, None, :] - cx[:, None, None], fine[None, :, None] - cy[:, None, None], psf.airy_first_zero_px)
            values += dens.reshape(n_src, size, psf.subsample, size, psf.subsample).mean(axis=(2, 4))
    return values / (len(disk) * n_path)


def add_stamps(image: np.ndarray, stamps: Stamps, *, origin_xy: tuple[int, int] = (0, 0)) -> None:
    """Add stamps into ``image`` in place, clipping at its edges.

    ``origin_xy`` is the full-frame pixel (x, y) of ``image[0, 0]`` (non-zero for windows).
    """
    n, size_y, size_x = stamps.values.shape
    if n == 0:
        return
    rows, cols = image.shape
    yy = stamps.y0[:, None, None] - origin_xy[1] + np.arange(size_y)[None, :, None]
    xx = stamps.x0[:, None, None] - origin_xy[0] + np.arange(size_x)[None, None, :]
    yy, xx = np.broadcast_arrays(yy, xx)
    keep = (yy >= 0) & (yy < rows) & (xx >= 0) & (xx < cols)
    flat = yy[keep] * cols + xx[keep]
    image += np.bincount(flat, weights=stamps.values[keep], minlength=rows * cols).reshape(rows, cols)
