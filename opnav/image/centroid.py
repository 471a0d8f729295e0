"""Sub-pixel centroiding of point sources, with a covariance per source.

Pixel convention: docs/conventions.md ((0, 0) is the centre of the first pixel,
x = column, y = row). Three methods, chosen with ``method``:

``"cog"``
    Thresholded centre of gravity: background (median of the stamp border)
    subtracted, pixels more than 3 background sigmas above it averaged with
    their values as weights, re-centred twice.
``"iwc"``
    Iteratively weighted centroid: a Gaussian window of the PSF width follows
    the centroid; each step is scaled by (1 + s^2/s_w^2), the exact fixed-point
    gain for a Gaussian PSF of sigma s under a Gaussian window of sigma s_w,
    so it converges in a few steps without the windowed-centroid shrinkage.
``"gauss"`` (default)
    Least-squares fit of a pixel-integrated Gaussian
    ``m = F E_x E_y + B`` with
    ``E_x(i) = Phi((i + 1/2 - x0)/s) - Phi((i - 1/2 - x0)/s)`` (exact pixel
    integrals; Phi the normal CDF), parameters (x0, y0, F, B) plus the width s
    unless ``psf_sigma_px`` is given. All stamps are stacked and solved at
    once: a Levenberg–Marquardt step per source from the batched normal
    equations (N, P, P), compiled (:func:`_gauss`; :func:`_gauss_reference`
    is the same fit as array operations, which the tests compare it with).
    The weights are 1/var with
    ``var = read_noise^2/gain^2 + (m - bias)/gain`` (ADU^2) taken from the
    current model, which makes the fixed point the maximum-likelihood
    estimate under the shifted-Poisson noise model below. Without
    ``read_noise_e`` the background variance is measured on the stamp border.

Frame-wide background gradient (``frame_gradient=True``). A constant background per
stamp is biased by a gradient across it (stray light, a ramp): the fit leans the source
toward the brighter side by about ``8 pi s^4 g / F`` px for a gradient g (electrons per px
per px), flux F and width s, the same in every frame, so it does not average down. Fitting
a plane in every stamp removes it at a cost in precision (the plane's tilt and the centre
share the odd part of the stamp). A gradient over the whole frame is measured far better
from the sources' local backgrounds, hundreds of pixels apart: after the first fit a plane
``B_i = b + g_x x_i + g_y y_i`` is fitted to them with their variances (5-sigma clipping);
when its slope is significant (chi-square, 2 dof, false alarm ``GRADIENT_FALSE_ALARM``) and
the plane explains them, ``g . (pixel - stamp centre)`` is subtracted from every stamp and
the sources are fitted again. Without a significant gradient nothing changes.
``gradient_adu_px`` subtracts a gradient known from elsewhere (a crop from the frame's
stars).

Covariance. For the fit it is the inverse of J^T W J at the solution (the
observed Fisher information). When ``read_noise_e`` is not given, a first fit
gives residuals from which the frame's background variance and, if unknown,
its gain are fitted (all sources share them), and the fit is repeated with
that noise model.
For the moment methods the pixel variances are propagated linearly.

Cramér–Rao bound (:func:`centroid_crb`). With the expected electrons per pixel
mu_k(theta) = F E_x E_y + b and independent Poisson photon noise plus Gaussian
read noise sigma_r, the count d_k + sigma_r^2 is approximated as Poisson with
mean mu_k + sigma_r^2 (the "shifted Poisson" model of Snyder et al. 1993,
J. Opt. Soc. Am. A 10, 1014, exact in its first two moments). Its Fisher
information is

    I_ij = sum_k (d mu_k/d theta_i)(d mu_k/d theta_j) / (mu_k + sigma_r^2)

over the pixels of the stamp, and any unbiased estimator has
cov(x0, y0) >= [I^-1]_{xy block}. The nuisance parameters (F, b and, when it
is fitted, s) are in theta, so the bound is the one for an estimator that does
not know them. The benchmark (``benchmarks/centroid.py``) compares the fit's
RMS error with this bound evaluated at each trial's true position.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.special import chdtr, chdtrc, chdtri, ndtr

from ..compiled import kernel
from ..errors import InputError

METHODS = ("gauss", "iwc", "cog")
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


@dataclass(frozen=True)
class CentroidResult:
    """Centroids aligned row for row with the seeds passed in.

    Attributes
    ----------
    xy : (N, 2) float
        Centroid (x = column, y = row), px; NaN where ``ok`` is False.
    cov : (N, 2, 2) float
        Covariance of ``xy``, px^2; NaN where ``ok`` is False.
    flux : (N,) float
        Background-subtracted flux, ADU.
    snr : (N,) float
        Flux over its 1-sigma uncertainty.
    ok : (N,) bool
        The estimate converged inside its stamp.
    sigma_px : (N,) float
        Fitted (or given) Gaussian width, px; NaN for the moment methods.
    background : (N,) float
        Local background level, ADU (at the stamp centre after any gradient was subtracted).
    method : str
        The method used.
    gradient_adu_px : (2,) float
        Background gradient subtracted from the stamps before the fit, ADU per px along x and
        y; zero when none was (module docstring, "Frame-wide background gradient").
    chi2, dof : (N,) float or None
        ``"gauss"``: weighted residual sum of squares of each fit under its noise model and its
        degrees of freedom (usable pixels less parameters); a PSF fit far above chi-square(dof)
        did not fit a PSF (a cosmic-ray track through the stamp, a blend). NaN for the moment
        methods.
    noise_var_adu2 : float
        Background variance per pixel of the noise model the fit used, ADU^2: read noise over the
        gain squared when both are given, the frame's fitted one (module docstring,
        "Covariance"), or the median of the stamp borders' variances when it could not be fitted.
        NaN with no sources.
    noise_gain_e_per_adu : float or None
        Gain of that noise model (given or fitted), electrons per ADU; None without a shot-noise term.
    """

    xy: np.ndarray
    cov: np.ndarray
    flux: np.ndarray
    snr: np.ndarray
    ok: np.ndarray
    sigma_px: np.ndarray
    background: np.ndarray
    method: str
    gradient_adu_px: tuple[float, float] = (0.0, 0.0)
    chi2: np.ndarray | None = None
    dof: np.ndarray | None = None
    noise_var_adu2: float = math.nan
    noise_gain_e_per_adu: float | None = None

    def __len__(self) -> int:
        return len(self.xy)


# ---- pixel-integrated Gaussian model ---------------------------------------------------------

def _edges(coord: np.ndarray, centre: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, ...]:
    """Integrals over each pixel along one axis and their derivatives by centre and width.

    ``coord`` (N, w) pixel centres, ``centre`` and ``sigma`` (N,). Returns E, dE/dc, dE/ds, each (N, w).
    """
    s = sigma[:, None]
    # Pixel i spans boundaries i and i + 1, so each boundary's CDF and density are computed once.
    t = (np.concatenate([coord, coord[:, -1:] + 1.0], axis=1) - 0.5 - centre[:, None]) / s
    pdf = np.exp(-0.5 * t * t) * _INV_SQRT_2PI
    cdf = ndtr(t)
    tpdf = t * pdf
    return cdf[:, 1:] - cdf[:, :-1], -(pdf[:, 1:] - pdf[:, :-1]) / s, -(tpdf[:, 1:] - tpdf[:, :-1]) / s


def _model(theta: np.ndarray, u: np.ndarray, v: np.ndarray, sigma: np.ndarray | None) -> np.ndarray:
    s = theta[:, 4] if sigma is None else sigma
    ex = _edges(u, theta[:, 0], s)[0]
    ey = _edges(v, theta[:, 1], s)[0]
    return theta[:, 2, None, None] * ey[:, :, None] * ex[:, None, :] + theta[:, 3, None, None]


def _model_jacobian(
    theta: np.ndarray, u: np.ndarray, v: np.ndarray, sigma: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """Model (N, w, w) and Jacobian (N, P, w, w) by (x0, y0, F, B[, s])."""
    s = theta[:, 4] if sigma is None else sigma
    ex, dex_dc, dex_ds = _edges(u, theta[:, 0], s)
    ey, dey_dc, dey_ds = _edges(v, theta[:, 1], s)
    flux = theta[:, 2, None, None]
    n_par = 4 if sigma is not None else 5
    jac = np.empty((len(theta), n_par) + (v.shape[1], u.shape[1]))
    np.multiply(ey[:, :, None], dex_dc[:, None, :], out=jac[:, 0])
    jac[:, 0] *= flux
    np.multiply(dey_dc[:, :, None], ex[:, None, :], out=jac[:, 1])
    jac[:, 1] *= flux
    np.multiply(ey[:, :, None], ex[:, None, :], out=jac[:, 2])
    jac[:, 3] = 1.0
    if sigma is None:
        np.multiply(dey_ds[:, :, None], ex[:, None, :], out=jac[:, 4])
        jac[:, 4] += ey[:, :, None] * dex_ds[:, None, :]
        jac[:, 4] *= flux
    return flux * jac[:, 2] + theta[:, 3, None, None], jac


# Each Jacobian column is a sum of outer products (row vector of y) x (column vector of x) drawn
# from the bases Y = [E_y, dE_y/dy0, dE_y/ds, 1] and X = [E_x, dE_x/dx0, dE_x/ds, 1]; entries
# (a, b) below select Y[a] x X[b]. Columns: x0, y0, F, B, s (x0, y0 and s also carry a factor F).
_TERMS = (((0, 1),), ((1, 0),), ((0, 0),), ((3, 3),), ((2, 0), (0, 2)))
_SCALED_BY_FLUX = (True, True, False, False, True)


def _pair_table(used: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unordered pairs of the basis vectors ``used`` (products are symmetric) and their index."""
    pairs = [(a, c) for i, a in enumerate(used) for c in used[i:]]
    index = np.full((4, 4), -1)
    for k, (a, c) in enumerate(pairs):
        index[a, c] = index[c, a] = k
    return np.array([a for a, _ in pairs]), np.array([c for _, c in pairs]), index


# With a known width the dE/ds basis vectors never enter: 6 pairs instead of 10.
_PAIR_TABLES = {True: _pair_table((0, 1, 2, 3)), False: _pair_table((0, 1, 3))}


def _normal_equations(theta, u, v, sigma, stamps, usable, noise, rows):
    """Weighted normal equations J^T W J, J^T W r of the fit, without forming the Jacobian.

    With the separable structure above, every entry of J^T W J is
    sum_ij W_ij (Y_a Y_c)(i) (X_b X_d)(j): one batched product (Y Y)^T W (X X) gives them all,
    which reads W once instead of once per Jacobian column pair.
    """
    n = len(u)
    s = theta[:, 4] if sigma is None else sigma
    ex, dex_dc, dex_ds = _edges(u, theta[:, 0], s)
    ey, dey_dc, dey_ds = _edges(v, theta[:, 1], s)
    flux = theta[:, 2]
    model = flux[:, None, None] * ey[:, :, None] * ex[:, None, :] + theta[:, 3, None, None]
    weight = usable / noise.variance(model, theta[:, 3], rows)
    resid = stamps - model
    ones = np.ones_like(ex)
    basis_x = np.stack([ex, dex_dc, dex_ds, ones], axis=1)
    basis_y = np.stack([ey, dey_dc, dey_ds, ones], axis=1)
    first, second, pair_index = _PAIR_TABLES[sigma is None]
    pairs_x = basis_x[:, first] * basis_x[:, second]
    pairs_y = basis_y[:, first] * basis_y[:, second]
    table = (pairs_y @ weight) @ pairs_x.transpose(0, 2, 1)
    projected = (basis_y @ (weight * resid)) @ basis_x.transpose(0, 2, 1)
    n_par = 5 if sigma is None else 4
    scale = [flux if _SCALED_BY_FLUX[p] else 1.0 for p in range(n_par)]
    normal = np.empty((n, n_par, n_par))
    grad = np.empty((n, n_par))
    for p in range(n_par):
        grad[:, p] = scale[p] * sum(projected[:, a, b] for a, b in _TERMS[p])
        for q in range(p, n_par):
            total = sum(table[:, pair_index[a, c], pair_index[b, d]] for a, b in _TERMS[p] for c, d in _TERMS[q])
            normal[:, p, q] = normal[:, q, p] = scale[p] * scale[q] * total
    return normal, grad, resid, weight


#: Largest centroid stamp side, px: a point source with a PSF sigma up to ~8 px.
MAX_WINDOW = 51


def _stamp_grid(xy: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integer stamp centres (N, 2) and the column/row coordinates (N, w) of each stamp."""
    centre = np.rint(xy).astype(np.int64)
    offs = np.arange(window) - window // 2
    return centre, centre[:, 0, None] + offs, centre[:, 1, None] + offs


def centroid_crb(
    xy: np.ndarray,
    flux_e: np.ndarray | float,
    psf_sigma_px: np.ndarray | float,
    *,
    background_e: float,
    read_noise_e: float,
    window: int = 7,
    fit_width: bool = True,
) -> np.ndarray:
    """Cramér–Rao bound on the centroid covariance of a pixel-integrated Gaussian.

    Parameters
    ----------
    xy : (N, 2) array
        True source positions, px (docs/conventions.md).
    flux_e : float or (N,)
        Total source signal, electrons.
    psf_sigma_px : float or (N,)
        Gaussian PSF sigma, px.
    background_e : float
        Background (sky + dark) per pixel, electrons.
    read_noise_e : float
        RMS read noise per pixel, electrons.
    window : int
        Side of the square stamp the estimator uses, px (centred on the nearest pixel).
    fit_width : bool
        Treat the width as an unknown nuisance parameter (as ``centroid`` does
        without ``psf_sigma_px``).

    Returns
    -------
    (N, 2, 2) array
        Lower bound on cov(x, y), px^2 (module docstring, "Cramér–Rao bound").
    """
    xy = np.atleast_2d(np.asarray(xy, dtype=float))
    n = len(xy)
    flux = np.broadcast_to(np.asarray(flux_e, dtype=float), (n,))
    sigma = np.broadcast_to(np.asarray(psf_sigma_px, dtype=float), (n,))
    if np.any(flux <= 0) or np.any(sigma <= 0) or background_e < 0 or read_noise_e < 0:
        raise InputError("centroid_crb needs flux_e > 0, psf_sigma_px > 0, background_e >= 0, read_noise_e >= 0")
    _, u, v = _stamp_grid(xy, window)
    theta = np.column_stack([xy, flux, np.full(n, background_e), sigma])
    mu, jac = _model_jacobian(theta, u, v, None if fit_width else sigma)
    jac = jac.reshape(n, jac.shape[1], -1)
    weight = 1.0 / (mu.reshape(n, -1) + read_noise_e**2)
    fisher = np.einsum("npk,nk,nqk->npq", jac, weight, jac)
    return np.linalg.inv(fisher)[:, :2, :2]


# ---- stamps and noise --------------------------------------------------------------------

@kernel
def _cut_stamps(image, bad, has_bad, u, v, saturation):  # pragma: no cover - compiled
    """Stamps (N, w, w) at columns ``u`` and rows ``v`` (N, w) of ``image``, 0 where not usable, and their
    usable-pixel mask: on the frame, not ``bad`` (read only when ``has_bad``), finite and below
    ``saturation``. One pass over the stamps' pixels: the fancy-indexed gathers, masks and
    ``numpy.where`` it replaces were half of a 10-star frame's centroiding."""
    n, side = u.shape
    height, width = image.shape
    stamps = np.zeros((n, side, side))
    usable = np.zeros((n, side, side), np.bool_)
    for k in range(n):
        for i in range(side):
            r = v[k, i]
            if r < 0 or r >= height:
                continue
            for j in range(side):
                c = u[k, j]
                if c < 0 or c >= width or (has_bad and bad[r, c]):
                    continue
                value = image[r, c]
                if np.isfinite(value) and value < saturation:
                    stamps[k, i, j] = value
                    usable[k, i, j] = True
    return stamps, usable


_NO_BAD = np.zeros((1, 1), np.bool_)


def _median(values: np.ndarray) -> float:
    """``numpy.median`` of ``values``; a constant array's (a known or fitted noise model's per-stamp
    variances) without its sort and partition (~0.1 ms a call)."""
    if len(values) and np.all(values == values[0]):
        return float(values[0])
    return float(np.median(values))


def _border_stats(stamps: np.ndarray, usable: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median and robust sigma of each stamp's outermost ring of usable pixels."""
    ring = np.zeros(stamps.shape[1:], bool)
    ring[[0, -1], :] = True
    ring[:, [0, -1]] = True
    vals = np.where(usable & ring, stamps, np.nan)[:, ring]
    if not np.isnan(vals).any():
        med = np.median(vals, axis=1)
        return med, np.median(np.abs(vals - med[:, None]), axis=1) * 1.482602218505602
    with warnings.catch_warnings():
        # A stamp wholly off the frame has no border; its NaN statistics mark it as failed.
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(vals, axis=1)
        mad = np.nanmedian(np.abs(vals - med[:, None]), axis=1) * 1.482602218505602
    return med, mad


@dataclass(frozen=True)
class _Noise:
    read_var_adu2: np.ndarray  # (N,) variance floor per stamp, ADU^2
    gain: float | None
    bias_adu: float
    known_scale: bool

    def variance(self, model: np.ndarray, background: np.ndarray, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        """Pixel variances (ADU^2) of stamps ``rows`` given their model (or data) and background."""
        floor_var = self.read_var_adu2[rows][:, None, None]
        if self.gain is None:
            return np.broadcast_to(floor_var, model.shape)
        floor = self.bias_adu if self.known_scale else background[:, None, None]
        return floor_var + np.clip(model - floor, 0.0, None) / self.gain


def _noise_model(stamps, usable, read_noise_e, gain, bias_adu) -> _Noise:
    if read_noise_e is not None and gain is not None:
        return _Noise(np.full(len(stamps), (read_noise_e / gain) ** 2), gain, bias_adu, True)
    # Unknown read noise: the border scatter holds read noise and the sky's shot noise together,
    # so only the source's own shot noise (model above the local background) is added to it.
    _, border_sigma = _border_stats(stamps, usable)
    good = np.isfinite(border_sigma) & (border_sigma > 0)
    fill = np.median(border_sigma[good]) if good.any() else 1.0
    return _Noise(np.where(good, border_sigma, fill) ** 2, gain, bias_adu, False)


#: Tail probability beyond which a pooled pixel's squared residual, or a stamp's chi-square, is not
#: the frame's noise (a cosmic-ray hit, a blend's neighbour, a bloom edge) in the noise-model fit.
NOISE_FIT_TAIL = 1e-4
NOISE_FIT_PIXEL_TAIL = 1e-4
#: Fewest clean stamps (every pixel usable, fit converged) the frame's noise model is fitted from.
NOISE_FIT_MIN_STAMPS = 3
#: Median of chi-square(1): the median squared residual over the pixel variance.
_CHI2_1_MEDIAN = 0.454936423119572
_NOISE_FIT_BINS = 16


def _with_fitted_noise(noise: _Noise, stamps, usable, u, v, xy, flux, background, sigma, ok, fit_width) -> _Noise:
    """The noise model with background variance (and gain, if unknown) fitted from first-pass residuals.

    Every source shares one gain and (nearly) one background noise, so the squared residuals r^2,
    pooled over the stamps, follow E[r^2] = a + b (m - B): the intercept a is the background
    variance and b = 1/gain, with m - B spread and scaled as the fit spreads and absorbs each
    pixel's noise (comment below).

    Only stamps with every pixel usable (no clipped core, no rejected or off-frame pixel) whose
    fit converged are pooled, and the fit is robust: saturated stars, bloom edges, blends and
    cosmic-ray hits leave residuals orders of magnitude above the noise, and a plain least-squares
    line through them put the background variance of rendered frames at 10 to 18,000 times its
    true value. The start is a line through the medians of r^2 (over chi-square(1)'s median) in
    bins of equal count along m - B; then, until the kept set settles, pixels whose r^2 exceeds
    the chi-square(1) quantile at ``NOISE_FIT_TAIL`` and whole stamps whose chi-square exceeds
    chi-square(dof)'s are left out and a, b refitted with weights 1/var^2 (the variance of r^2 is
    2 var^2), the truncated mean corrected for the cut. Fewer than ``NOISE_FIT_MIN_STAMPS`` clean
    stamps, or a fit that does not give a positive variance, leave ``noise`` as it was; a slope
    not above zero leaves the gain unknown (no shot term).
    """
    clean = ok & usable.all(axis=(1, 2))
    if clean.sum() < NOISE_FIT_MIN_STAMPS:
        return noise
    rows = np.flatnonzero(clean)
    theta = np.column_stack([xy, flux, background, sigma])[rows]
    n = len(rows)
    model, jac = _model_jacobian(theta, u[rows], v[rows], None if fit_width else sigma[rows])
    jac = jac.reshape(n, jac.shape[1], -1)
    resid = stamps[rows].reshape(n, -1) - model.reshape(n, -1)
    excess = np.clip(model - background[rows, None, None], 0.0, None).reshape(n, -1)
    # The fit absorbs part of the noise and spreads the rest: with the first pass's weights W and
    # the hat matrix H = J (J^T W J)^-1 J^T W, the residuals are (I - H) times the noise, so
    # E[r_k^2] = sum_j (I - H)_kj^2 var_j = a A_k + b D_k with A_k = sum_j (I - H)_kj^2 and
    # D_k = sum_j (I - H)_kj^2 (m_j - B). A core pixel's shot noise reaches the border's residuals
    # through the fitted background; the diagonal alone ((1 - h_k) var_k) put the fitted
    # background variance 4-9 % high on a frame of exact Gaussian stars.
    weight = 1.0 / noise.variance(model, theta[:, 3], rows).reshape(n, -1)
    weighted = jac * weight[:, None, :]
    normal = weighted @ jac.transpose(0, 2, 1)
    try:
        inverse = np.linalg.inv(normal)
    except np.linalg.LinAlgError:
        inverse = np.linalg.pinv(normal)
    spread = jac.transpose(0, 2, 1) @ (inverse @ weighted)
    spread *= -1.0
    spread[:, np.arange(spread.shape[1]), np.arange(spread.shape[1])] += 1.0
    spread **= 2
    absorbed = np.clip(spread.sum(axis=2), 0.05, None)
    # r^2 / A = a + b D / A: the line of the start and of the robust fit below
    resid2 = resid**2 / absorbed
    excess = (spread @ excess[:, :, None])[:, :, 0] / absorbed
    if not (np.all(np.isfinite(resid2)) and np.all(np.isfinite(excess))):
        finite = np.isfinite(resid2).all(axis=1) & np.isfinite(excess).all(axis=1)
        resid2, excess = resid2[finite], excess[finite]
        if len(resid2) < NOISE_FIT_MIN_STAMPS:
            return noise
    known_slope = None if noise.gain is None else 1.0 / noise.gain
    intercept, slope = _binned_median_line(resid2.ravel(), excess.ravel(), known_slope)
    pixel_cut = float(chdtri(1, NOISE_FIT_PIXEL_TAIL))
    # E[r^2 | r^2 < cut var] = var P(chi2_3 < cut) / P(chi2_1 < cut)
    truncation = float(chdtr(3, pixel_cut) / chdtr(1, pixel_cut))
    # r^2 / (1 - h) has the pixel's full variance: a clean stamp's sum is chi-square(pixels)
    dof = resid2.shape[1]
    keep = None
    for _ in range(20):
        if not (np.isfinite(intercept) and intercept > 0):
            return noise
        var = intercept + max(slope, 0.0) * excess
        z = resid2 / var
        stamp_ok = chi2_sf(z.sum(axis=1), dof) >= NOISE_FIT_TAIL
        new_keep = (z <= pixel_cut) & stamp_ok[:, None]
        if keep is not None and np.array_equal(new_keep, keep):
            break
        keep = new_keep
        if stamp_ok.sum() < NOISE_FIT_MIN_STAMPS:
            return noise
        w = np.where(keep, 1.0 / var**2, 0.0)
        target = resid2 / truncation
        if known_slope is None:
            sw, swe, swee = w.sum(), (w * excess).sum(), (w * excess**2).sum()
            swr, swer = (w * target).sum(), (w * excess * target).sum()
            det = sw * swee - swe * swe
            if det > 1e-12 * sw * swee:
                slope = (sw * swer - swe * swr) / det
                intercept = (swr - slope * swe) / sw
            if slope <= 0.0:
                slope = 0.0
                intercept = swr / sw
        else:
            slope = known_slope
            intercept = (w * (target - slope * excess)).sum() / w.sum()
    if not (np.isfinite(intercept) and intercept > 0 and np.isfinite(slope)):
        return noise
    gain = None if slope <= 0.0 else 1.0 / slope
    return _Noise(np.full(len(stamps), intercept), gain, noise.bias_adu, False)


def _binned_median_line(resid2, excess, known_slope) -> tuple[float, float]:
    """Robust start of :func:`_with_fitted_noise`: intercept and slope of the variance line through the
    medians of ``resid2`` (each over chi-square(1)'s median) in ``_NOISE_FIT_BINS`` bins of equal count
    along ``excess``, weighted by count over the squared variance; ``known_slope`` fixes the slope."""
    order = np.argsort(excess, kind="stable")
    n_bins = min(_NOISE_FIT_BINS, max(len(order) // 20, 1))
    # equal bins; the few pixels of largest excess beyond n_bins * size are left to the robust fit
    order = order[:len(order) // n_bins * n_bins].reshape(n_bins, -1)
    level = np.median(resid2[order], axis=1) / _CHI2_1_MEDIAN
    centre = excess[order].mean(axis=1)
    count = np.full(n_bins, float(order.shape[1]))
    if known_slope is not None:
        return float(np.median(level - known_slope * centre)), known_slope
    intercept, slope = float(level[0]), 0.0
    for _ in range(3):
        w = count / np.maximum(intercept + slope * centre, 1e-300) ** 2
        sw, swe, swee = w.sum(), (w * centre).sum(), (w * centre**2).sum()
        swr, swer = (w * level).sum(), (w * centre * level).sum()
        det = sw * swee - swe * swe
        slope = max(float((sw * swer - swe * swr) / det), 0.0) if det > 1e-12 * sw * swee else 0.0
        intercept = float((swr - slope * swe) / sw)
        if not (np.isfinite(intercept) and intercept > 0):
            return float(level[0]), 0.0
    return intercept, slope


# ---- estimators --------------------------------------------------------------------------

def _weighted_centre(weighted: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    total = weighted.sum(axis=(1, 2))
    with np.errstate(all="ignore"):
        xy = np.stack([(weighted * u[:, None, :]).sum(axis=(1, 2)), (weighted * v[:, :, None]).sum(axis=(1, 2))], -1)
        return xy / total[:, None], total


def _diagonal_cov(var, weight, u, v, centre, total, scale=1.0) -> np.ndarray:
    """Linear propagation of pixel variances through a weighted mean position."""
    cov = np.zeros((len(centre), 2, 2))
    with np.errstate(all="ignore"):
        cov[:, 0, 0] = scale * (var * (weight * (u[:, None, :] - centre[:, 0, None, None])) ** 2).sum(axis=(1, 2)) / total**2
        cov[:, 1, 1] = scale * (var * (weight * (v[:, :, None] - centre[:, 1, None, None])) ** 2).sum(axis=(1, 2)) / total**2
    return cov


def _cog(stamps, usable, u, v, noise: _Noise, threshold_sigma=3.0):
    background, border_sigma = _border_stats(stamps, usable)
    usable = usable & (stamps > background[:, None, None] + threshold_sigma * border_sigma[:, None, None])
    signal = np.where(usable, stamps - background[:, None, None], 0.0)
    xy, total = _weighted_centre(signal, u, v)
    var = noise.variance(stamps, background) * usable
    cov = _diagonal_cov(var, 1.0, u, v, xy, total)
    with np.errstate(all="ignore"):
        snr = total / np.sqrt(var.sum(axis=(1, 2)))
    return xy, cov, total, snr, np.full(len(xy), np.nan), background


def _iwc(stamps, usable, u, v, noise: _Noise, xy0, psf_sigma_px):
    background, _ = _border_stats(stamps, usable)
    s = 1.0 if psf_sigma_px is None else psf_sigma_px
    sw = s  # a window matched to the PSF maximises the centroid's signal-to-noise ratio
    gain = 1.0 + s * s / (sw * sw)

    def window(xy):
        return np.exp(-0.5 * ((u[:, None, :] - xy[:, 0, None, None]) ** 2 + (v[:, :, None] - xy[:, 1, None, None]) ** 2) / sw**2)

    signal = np.where(usable, stamps - background[:, None, None], 0.0)
    xy = xy0.copy()
    for _ in range(50):
        wc, total = _weighted_centre(window(xy) * signal, u, v)
        step = gain * (wc - xy)
        xy = xy + step
        if np.all(~np.isfinite(step) | (np.abs(step) < 1e-7)):
            break
    var = noise.variance(stamps, background) * usable
    cov = _diagonal_cov(var, window(xy), u, v, wc, total, gain**2)
    flux = signal.sum(axis=(1, 2))
    with np.errstate(all="ignore"):
        snr = flux / np.sqrt(var.sum(axis=(1, 2)))
    return xy, cov, flux, snr, np.full(len(xy), float(s)), background


def _gauss_start(stamps, usable, u, v, xy0, psf_sigma_px):
    """Starting parameters (x0, y0, F, B[, s]) from the stamp's border and moments."""
    background, _ = _border_stats(stamps, usable)
    background = np.where(np.isfinite(background), background, 0.0)
    signal = np.where(usable, stamps - background[:, None, None], 0.0)
    flux0 = np.maximum(signal.sum(axis=(1, 2)), 1e-6)
    # The centre of gravity of the positive signal is a closer start than the seed.
    pos = np.clip(signal, 0, None)
    centre, total = _weighted_centre(pos, u, v)
    start = np.where(np.isfinite(centre) & (np.abs(centre - xy0) < 1.5), centre, xy0)
    if psf_sigma_px is not None:
        return np.column_stack([start, flux0, background])
    # Width from the second moment of the positive signal, less pixelisation (1/12 px^2).
    total = np.maximum(total, 1e-12)
    m2 = (pos * ((u[:, None, :] - centre[:, 0, None, None]) ** 2 + (v[:, :, None] - centre[:, 1, None, None]) ** 2)).sum(axis=(1, 2)) / total
    s0 = np.clip(np.sqrt(np.clip(m2 / 2.0 - 1.0 / 12.0, 0.04, None)), 0.3, stamps.shape[1] / 4.0)
    return np.column_stack([start, flux0, background, s0])


class _GaussFit(NamedTuple):
    """Per-source results of :func:`_gauss` (N rows each)."""

    xy: np.ndarray  # (N, 2) px
    cov: np.ndarray  # (N, 2, 2) px^2
    flux: np.ndarray  # ADU
    snr: np.ndarray
    sigma_px: np.ndarray
    background: np.ndarray  # ADU
    ok: np.ndarray
    background_var: np.ndarray  # ADU^2
    chi2: np.ndarray
    dof: np.ndarray


def _gauss_reference(stamps, usable, u, v, noise: _Noise, xy0, psf_sigma_px, max_iter, tol_px) -> _GaussFit:
    """Batched Levenberg–Marquardt fit; one model + Jacobian evaluation per iteration.

    A step is judged at the next evaluation: if chi-square rose, the source goes back to its
    last accepted point and re-solves its stored normal equations with more damping. Only
    sources not yet converged are evaluated.

    The array-level reference of :func:`_gauss` (the compiled fit the stage runs, one source at a
    time): tests check that both give the same numbers.
    """
    n = len(stamps)
    theta = _gauss_start(stamps, usable, u, v, xy0, psf_sigma_px)
    sigma = None if psf_sigma_px is None else np.full(n, float(psf_sigma_px))
    n_par = theta.shape[1]
    data = stamps.reshape(n, -1)
    width_cap = stamps.shape[1]

    def evaluate(rows, th):
        normal, grad, resid, weight = _normal_equations(
            th, u[rows], v[rows], None if sigma is None else sigma[rows],
            stamps[rows], usable[rows], noise, rows,
        )
        return normal, grad, resid.reshape(len(rows), -1), weight.reshape(len(rows), -1)

    accepted = theta.copy()
    normal_acc = np.zeros((n, n_par, n_par))
    grad_acc = np.zeros((n, n_par))
    chi2_acc = np.full(n, np.inf)
    weight_acc = np.ones_like(data)
    lam = np.full(n, 1e-3)
    converged = np.zeros(n, bool)
    eye = np.eye(n_par)
    for _ in range(max_iter):
        rows = np.flatnonzero(~converged)
        if len(rows) == 0:
            break
        normal, grad, resid, weight = evaluate(rows, theta[rows])
        # Judge the step with the weights it was computed with, so both chi-squares are the same function.
        better = np.sum(weight_acc[rows] * resid**2, axis=1) <= chi2_acc[rows]
        good = rows[better]
        accepted[good] = theta[good]
        normal_acc[good], grad_acc[good] = normal[better], grad[better]
        weight_acc[good] = weight[better]
        chi2_acc[good] = np.sum(weight[better] * resid[better] ** 2, axis=1)
        lam[good] = np.maximum(lam[good] * 0.1, 1e-9)
        bad = rows[~better]
        lam[bad] = np.minimum(lam[bad] * 10.0, 1e9)
        damped = normal_acc[rows] + lam[rows, None, None] * (normal_acc[rows] * eye)
        try:
            step = np.linalg.solve(damped, grad_acc[rows][..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = np.stack([np.linalg.lstsq(d, g, rcond=None)[0] for d, g in zip(damped, grad_acc[rows])])
        step = np.where(np.isfinite(step), step, 0.0)
        # A step below tol_px from a freshly accepted point is deep in the quadratic regime (the
        # error left after it is ~tol^2): take it without another evaluation.
        done = better & (np.max(np.abs(step[:, :2]), axis=1) < tol_px)
        theta[rows] = accepted[rows] + step
        if sigma is None:
            theta[rows, 4] = np.clip(theta[rows, 4], 0.1, width_cap)
        accepted[rows[done]] = theta[rows[done]]
        converged[rows[done]] = True
    theta = accepted
    cov_full = np.full_like(normal_acc, np.nan)
    finite = np.all(np.isfinite(normal_acc), axis=(1, 2)) & (chi2_acc < np.inf)
    try:
        cov_full[finite] = np.linalg.inv(normal_acc[finite])
    except np.linalg.LinAlgError:
        with np.errstate(all="ignore"):
            cov_full[finite] = np.linalg.pinv(normal_acc[finite])
    return _fit_result(theta, cov_full, chi2_acc, converged, stamps, usable, xy0, psf_sigma_px)


def _gauss(stamps, usable, u, v, noise: _Noise, xy0, psf_sigma_px, max_iter, tol_px) -> _GaussFit:
    """The fit of :func:`_gauss_reference` compiled (:func:`_gauss_kernel`): the same start, the same
    Levenberg–Marquardt steps, acceptance and convergence test, the same covariance. The array
    version costs dozens of small numpy operations an iteration (~0.7 ms for the stars of an S1
    frame, 3-5 ms with 40 stars); the kernel evaluates each source pixel by pixel and only while
    it has not converged."""
    has_gain = noise.gain is not None
    fixed = psf_sigma_px is not None
    theta, cov_full, chi2_acc, converged = _gauss_kernel(
        np.ascontiguousarray(stamps, dtype=float), np.ascontiguousarray(usable, dtype=np.bool_),
        np.ascontiguousarray(u, dtype=np.int64), np.ascontiguousarray(v, dtype=np.int64),
        np.ascontiguousarray(xy0, dtype=float), np.ascontiguousarray(noise.read_var_adu2, dtype=float),
        float(noise.gain) if has_gain else 1.0, has_gain, float(noise.bias_adu), bool(noise.known_scale),
        float(psf_sigma_px) if fixed else 1.0, fixed, int(max_iter), float(tol_px))
    return _fit_result(theta, cov_full, chi2_acc, converged, stamps, usable, xy0, psf_sigma_px)


def _fit_result(theta, cov_full, chi2_acc, converged, stamps, usable, xy0, psf_sigma_px) -> _GaussFit:
    """The fit's outputs from its final parameters (N, 4 or 5) and their covariance: a source is
    ``ok`` when converged, inside its stamp, with positive flux, a finite covariance and a width
    between 0.15 px and half the stamp."""
    n = len(stamps)
    fitted_sigma = np.full(n, float(psf_sigma_px)) if psf_sigma_px is not None else theta[:, 4]
    half = stamps.shape[1] / 2.0
    inside = np.all(np.abs(theta[:, :2] - np.rint(xy0)) < half - 0.5, axis=1)
    ok = converged & inside & (theta[:, 2] > 0) & np.all(np.isfinite(cov_full[:, :3, :3]), axis=(1, 2))
    ok &= (fitted_sigma > 0.15) & (fitted_sigma < half)
    with np.errstate(all="ignore"):
        snr = theta[:, 2] / np.sqrt(cov_full[:, 2, 2])
    dof = usable.reshape(n, -1).sum(axis=1) - theta.shape[1]
    return _GaussFit(theta[:, :2], cov_full[:, :2, :2], theta[:, 2], snr, fitted_sigma, theta[:, 3], ok,
                     cov_full[:, 3, 3], chi2_acc, dof)


@kernel
def _clip_nan(x, lo, hi):  # pragma: no cover - compiled
    """``numpy.clip`` of a scalar: NaN stays NaN."""
    if x < lo:
        return lo
    if x > hi:
        return hi
    return x


@kernel
def _ndtr(a):  # pragma: no cover - compiled
    """Standard normal CDF, as ``scipy.special.ndtr`` computes it (erf near 0, erfc in the tails)."""
    x = a * 0.7071067811865476
    z = abs(x)
    if z < 0.7071067811865476:
        return 0.5 + 0.5 * math.erf(x)
    y = 0.5 * math.erfc(z)
    return 1.0 - y if x > 0.0 else y


@kernel
def _edges_one(coord, centre, sigma, e, de_dc, de_ds):  # pragma: no cover - compiled
    """:func:`_edges` of one stamp axis: fills E, dE/dc, dE/ds (w,) from the pixel centres ``coord`` (w,)."""
    w = coord.size
    prev_cdf = prev_pdf = prev_tpdf = 0.0
    for b in range(w + 1):
        edge = (coord[b] if b < w else coord[w - 1] + 1.0) - 0.5
        t = (edge - centre) / sigma
        pdf = math.exp(-0.5 * t * t) * _INV_SQRT_2PI
        cdf = _ndtr(t)
        tpdf = t * pdf
        if b > 0:
            e[b - 1] = cdf - prev_cdf
            de_dc[b - 1] = -(pdf - prev_pdf) / sigma
            de_ds[b - 1] = -(tpdf - prev_tpdf) / sigma
        prev_cdf, prev_pdf, prev_tpdf = cdf, pdf, tpdf


@kernel
def _start_one(stamp, usable, u, v, xy0, fixed, theta):  # pragma: no cover - compiled
    """:func:`_gauss_start` of one stamp into ``theta``: background from the border ring's median,
    centre of gravity of the positive signal (when within 1.5 px of the seed), flux and, when the
    width is fitted, the width from the second moment."""
    w = stamp.shape[0]
    ring = np.empty(4 * w)
    count = 0
    for i in range(w):
        for j in range(w):
            if (i == 0 or i == w - 1 or j == 0 or j == w - 1) and usable[i, j]:
                ring[count] = stamp[i, j]
                count += 1
    background = np.median(ring[:count]) if count else np.nan
    if not np.isfinite(background):
        background = 0.0
    total_signal = total = sum_x = sum_y = 0.0
    for i in range(w):
        for j in range(w):
            signal = stamp[i, j] - background if usable[i, j] else 0.0
            total_signal += signal
            positive = _clip_nan(signal, 0.0, np.inf)
            total += positive
            sum_x += positive * u[j]
            sum_y += positive * v[i]
    cx, cy = sum_x / total, sum_y / total
    theta[0] = cx if np.isfinite(cx) and abs(cx - xy0[0]) < 1.5 else xy0[0]
    theta[1] = cy if np.isfinite(cy) and abs(cy - xy0[1]) < 1.5 else xy0[1]
    theta[2] = max(total_signal, 1e-6)
    theta[3] = background
    if fixed:
        return
    m2 = 0.0
    for i in range(w):
        for j in range(w):
            signal = stamp[i, j] - background if usable[i, j] else 0.0
            m2 += _clip_nan(signal, 0.0, np.inf) * ((u[j] - cx) ** 2 + (v[i] - cy) ** 2)
    m2 /= max(total, 1e-12)
    theta[4] = _clip_nan(math.sqrt(_clip_nan(m2 / 2.0 - 1.0 / 12.0, 0.04, np.inf)), 0.3, w / 4.0)


@kernel
def _normal_one(theta, stamp, usable, u, v, read_var, gain, has_gain, bias, known_scale, sigma, fixed,
                edges, normal, grad, weight, resid):  # pragma: no cover - compiled
    """Normal equations J^T W J (``normal``), J^T W r (``grad``), weights and residuals (w, w) of one
    stamp at ``theta`` (the quantities of :func:`_normal_equations`, pixel by pixel; the sums in
    scalars, which the compiler keeps in registers)."""
    w = stamp.shape[0]
    s = sigma if fixed else theta[4]
    ex, dex_dc, dex_ds = edges[0], edges[1], edges[2]
    ey, dey_dc, dey_ds = edges[3], edges[4], edges[5]
    _edges_one(u, theta[0], s, ex, dex_dc, dex_ds)
    _edges_one(v, theta[1], s, ey, dey_dc, dey_ds)
    flux, background = theta[2], theta[3]
    floor = bias if known_scale else background
    n00 = n10 = n11 = n20 = n21 = n22 = n30 = n31 = n32 = n33 = 0.0
    n40 = n41 = n42 = n43 = n44 = 0.0
    g0 = g1 = g2 = g3 = g4 = 0.0
    j4 = 0.0
    for i in range(w):
        for j in range(w):
            model = flux * ey[i] * ex[j] + background
            var = read_var + _clip_nan(model - floor, 0.0, np.inf) / gain if has_gain else read_var
            wt = (1.0 if usable[i, j] else 0.0) / var
            r = stamp[i, j] - model
            weight[i, j] = wt
            resid[i, j] = r
            # Jacobian by x0, y0, F, B (1) and s
            j0 = flux * ey[i] * dex_dc[j]
            j1 = flux * dey_dc[i] * ex[j]
            j2 = ey[i] * ex[j]
            wr = wt * r
            g0 += wr * j0
            g1 += wr * j1
            g2 += wr * j2
            g3 += wr
            w0, w1, w2 = wt * j0, wt * j1, wt * j2
            n00 += w0 * j0
            n10 += w1 * j0
            n11 += w1 * j1
            n20 += w2 * j0
            n21 += w2 * j1
            n22 += w2 * j2
            n30 += w0
            n31 += w1
            n32 += w2
            n33 += wt
            if not fixed:
                j4 = flux * (dey_ds[i] * ex[j] + ey[i] * dex_ds[j])
                g4 += wr * j4
                w4 = wt * j4
                n40 += w4 * j0
                n41 += w4 * j1
                n42 += w4 * j2
                n43 += w4
                n44 += w4 * j4
    normal[0, 0] = n00
    normal[1, 0] = normal[0, 1] = n10
    normal[1, 1] = n11
    normal[2, 0] = normal[0, 2] = n20
    normal[2, 1] = normal[1, 2] = n21
    normal[2, 2] = n22
    normal[3, 0] = normal[0, 3] = n30
    normal[3, 1] = normal[1, 3] = n31
    normal[3, 2] = normal[2, 3] = n32
    normal[3, 3] = n33
    grad[0], grad[1], grad[2], grad[3] = g0, g1, g2, g3
    if not fixed:
        normal[4, 0] = normal[0, 4] = n40
        normal[4, 1] = normal[1, 4] = n41
        normal[4, 2] = normal[2, 4] = n42
        normal[4, 3] = normal[3, 4] = n43
        normal[4, 4] = n44
        grad[4] = g4


@kernel
def _solve_all(damped, grad, rows, singular):  # pragma: no cover - compiled
    """Steps (len(rows), P) solving ``damped[k] step = grad[k]`` for ``k`` in ``rows``, as the batched
    fit solves them: ``numpy.linalg.solve`` for all, or, when any matrix of the batch is singular
    (``singular``: known to be; else the batch solve raises), the least-squares solution
    (``lstsq``, rcond eps * P) for all."""
    n_par = grad.shape[1]
    step = np.empty((rows.size, n_par))
    if not singular:
        try:
            for r in range(rows.size):
                step[r] = np.linalg.solve(damped[rows[r]], grad[rows[r]])
            return step
        except Exception:  # numba raises LinAlgError for a singular matrix
            pass
    for r in range(rows.size):
        step[r] = np.linalg.lstsq(damped[rows[r]], grad[rows[r]], rcond=np.finfo(np.float64).eps * n_par)[0]
    return step


@kernel
def _invert_all(normal, rows):  # pragma: no cover - compiled
    """Inverses of ``normal[k]`` for ``k`` in ``rows`` as the batched fit takes them: ``numpy.linalg.inv``
    for all, or, when any is singular, the pseudo-inverse of all."""
    out = np.empty((rows.size,) + normal.shape[1:])
    try:
        for r in range(rows.size):
            out[r] = np.linalg.inv(normal[rows[r]])
    except Exception:
        for r in range(rows.size):
            out[r] = np.linalg.pinv(normal[rows[r]])
    return out


@kernel
def _gauss_kernel(stamps, usable, u, v, xy0, read_var, gain, has_gain, bias, known_scale, sigma, fixed, max_iter,
                  tol_px):  # pragma: no cover - compiled
    """Levenberg–Marquardt fit of every stamp (:func:`_gauss`): parameters (N, P), covariance (N, P, P)
    (NaN where the normal matrix is not finite or no step was accepted), chi-square (inf when no
    step was accepted) and convergence flags.

    The sources advance in lockstep, as in the batched fit, because one singular matrix switches
    the whole iteration's solve to least squares there (and one singular normal matrix the final
    inversion to the pseudo-inverse): each source's numbers then do not depend on how it is
    computed, only on its batch, as before. A source whose first evaluation is not finite is
    never accepted: its normal matrix stays zero, so its step is zero and every later evaluation
    would repeat the first; it is not evaluated again, but stays in the batch (unconverged, its
    zero matrix singular) as in the batched fit."""
    n, w = stamps.shape[0], stamps.shape[1]
    n_par = 4 if fixed else 5
    uf, vf = u.astype(np.float64), v.astype(np.float64)
    theta = np.empty((n, n_par))
    for k in range(n):
        _start_one(stamps[k], usable[k], uf[k], vf[k], xy0[k], fixed, theta[k])
    accepted = theta.copy()
    normal_acc = np.zeros((n, n_par, n_par))
    grad_acc = np.zeros((n, n_par))
    chi2_acc = np.full(n, np.inf)
    weight_acc = np.ones((n, w, w))
    lam = np.full(n, 1e-3)
    converged = np.zeros(n, np.bool_)
    better = np.zeros(n, np.bool_)
    frozen = np.zeros(n, np.bool_)
    damped = np.empty((n, n_par, n_par))
    edges = np.empty((6, w))
    normal, grad = np.empty((n_par, n_par)), np.empty(n_par)
    weight, resid = np.empty((w, w)), np.empty((w, w))
    for _ in range(max_iter):
        rows = np.flatnonzero(~converged & ~frozen)
        if rows.size == 0:
            break
        for k in rows:
            _normal_one(theta[k], stamps[k], usable[k], uf[k], vf[k], read_var[k], gain, has_gain, bias, known_scale,
                        sigma, fixed, edges, normal, grad, weight, resid)
            # judge the step with the weights it was computed with, so both chi-squares are the same function
            trial = 0.0
            for i in range(w):
                for j in range(w):
                    trial += weight_acc[k, i, j] * resid[i, j] ** 2
            better[k] = trial <= chi2_acc[k]
            if better[k]:
                accepted[k] = theta[k]
                normal_acc[k] = normal
                grad_acc[k] = grad
                weight_acc[k] = weight
                total = 0.0
                for i in range(w):
                    for j in range(w):
                        total += weight[i, j] * resid[i, j] ** 2
                chi2_acc[k] = total
                lam[k] = max(lam[k] * 0.1, 1e-9)
            else:
                lam[k] = min(lam[k] * 10.0, 1e9)
                frozen[k] = chi2_acc[k] == np.inf  # never accepted (see the docstring)
            for p in range(n_par):
                for q in range(n_par):
                    # normal + lam (normal * I), as the array version forms it (inf * 0 is NaN there too)
                    damped[k, p, q] = normal_acc[k, p, q] + lam[k] * (normal_acc[k, p, q] * (1.0 if p == q else 0.0))
        rows = rows[~frozen[rows]]
        step = _solve_all(damped, grad_acc, rows, frozen.any())
        for r in range(rows.size):
            k = rows[r]
            for p in range(n_par):
                theta[k, p] = accepted[k, p] + (step[r, p] if np.isfinite(step[r, p]) else 0.0)
            if not fixed:
                theta[k, 4] = _clip_nan(theta[k, 4], 0.1, float(w))
            # a step below tol_px from a freshly accepted point is deep in the quadratic regime (the
            # error left after it is ~tol^2): take it without another evaluation
            if better[k] and max(abs(step[r, 0]) if np.isfinite(step[r, 0]) else 0.0,
                                 abs(step[r, 1]) if np.isfinite(step[r, 1]) else 0.0) < tol_px:
                accepted[k] = theta[k]
                converged[k] = True
    cov = np.full((n, n_par, n_par), np.nan)
    finite = np.zeros(n, np.bool_)
    for k in range(n):
        finite[k] = chi2_acc[k] < np.inf and np.all(np.isfinite(normal_acc[k]))
    rows = np.flatnonzero(finite)
    cov[rows] = _invert_all(normal_acc, rows)
    return accepted, cov, chi2_acc, converged


def chi2_sf(x, dof):
    """``scipy.stats.chi2.sf(x, dof)``: the same numbers (``scipy.special.chdtrc`` inside the
    distribution's support, with its argument checks: 1 at x <= 0, 0 at x = inf, NaN for NaN x
    or dof <= 0) without the distribution object's ~70 us a call, which the image stage pays
    several times a frame.

    Returns
    -------
    float or ndarray
        Broadcast shape of ``x`` and ``dof``; a NumPy scalar for scalar arguments.
    """
    x, dof = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(dof, dtype=float))
    with np.errstate(invalid="ignore"):
        inside = (x > 0.0) & (x < np.inf)
        out = np.where(inside, chdtrc(dof, np.where(inside, x, 1.0)), np.where(x > 0.0, 0.0, 1.0))
        out = np.where((dof > 0.0) & ~np.isnan(x), out, np.nan)
    return out[()]


#: A Gaussian fit whose chi-square exceeds chi-square(dof) at this probability did not fit a PSF.
PSF_FIT_FALSE_ALARM = 1e-6


def psf_like(result: CentroidResult, false_alarm: float = PSF_FIT_FALSE_ALARM) -> np.ndarray:
    """Rows of ``result`` whose fit is consistent with a point source under the noise model.

    A cosmic-ray track through a star's or a moon's stamp, a blend or a bloom edge leaves a fit
    whose weighted residuals are far beyond chi-square(dof): its centroid is pulled by the
    intruder, often by several sigmas, with a covariance that does not say so. Measured on
    S1 frames, the fits' p-values are uniform (5.8 % below 0.05) and those below 1e-6 are
    tracks and stars on Mars' bloom. Moment centroids (no chi-square) pass.

    Returns
    -------
    (N,) bool
    """
    if result.chi2 is None:
        return np.ones(len(result), bool)
    with np.errstate(invalid="ignore"):
        return ~(chi2_sf(result.chi2, np.maximum(result.dof, 1.0)) < false_alarm)


#: False-alarm probability of the frame-wide gradient test (module docstring).
GRADIENT_FALSE_ALARM = 1e-3
#: Fewest sources with a background to measure a frame-wide gradient from.
GRADIENT_MIN_SOURCES = 4


def background_gradient(
    xy: np.ndarray,
    background: np.ndarray,
    background_var: np.ndarray,
    *,
    false_alarm: float = GRADIENT_FALSE_ALARM,
    clip_sigma: float = 5.0,
) -> np.ndarray | None:
    """Frame-wide background gradient from the sources' local backgrounds, or None.

    Parameters
    ----------
    xy : (N, 2) array
        Where each background was measured (its stamp's centre pixel), px (docs/conventions.md).
    background, background_var : (N,) arrays
        Each source's fitted local background, ADU, and its variance, ADU^2.
    false_alarm : float
        The slope is returned only when a zero slope is rejected at this probability
        (chi-square, 2 dof) and a plane fits the backgrounds at it.
    clip_sigma : float
        Backgrounds further than this from the plane (in their own sigmas: a source on a
        planet's halo) are left out, iteratively.

    Returns
    -------
    (2,) array or None
        Gradient, ADU per px along x and y; None with fewer than ``GRADIENT_MIN_SOURCES`` usable
        backgrounds, an insignificant slope or backgrounds a plane does not explain.
    """
    xy = np.asarray(xy, float)
    background = np.asarray(background, float)
    background_var = np.asarray(background_var, float)
    keep = np.isfinite(background) & np.isfinite(background_var) & (background_var > 0) & np.isfinite(xy).all(axis=1)
    if keep.sum() < GRADIENT_MIN_SOURCES:
        return None
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = 1.0 / np.sqrt(background_var)
    # Centred coordinates keep the normal equations well conditioned on a large frame.
    design = np.column_stack([np.ones(len(xy)), xy - xy[keep].mean(axis=0)])
    for _ in range(5):
        solution, *_ = np.linalg.lstsq(design[keep] * scale[keep, None], background[keep] * scale[keep], rcond=None)
        with np.errstate(invalid="ignore"):
            z = np.abs(background - design @ solution) * scale
            clipped = keep & (z <= clip_sigma)
        if clipped.sum() < GRADIENT_MIN_SOURCES:
            return None
        if np.array_equal(clipped, keep):
            break
        keep = clipped
    dof = int(keep.sum()) - 3
    if dof > 0 and chi2_sf(float(np.sum(z[keep] ** 2)), dof) < false_alarm:
        return None
    weighted = design[keep] * scale[keep, None]
    slope_cov = np.linalg.inv(weighted.T @ weighted)[1:, 1:]
    slope = solution[1:]
    if chi2_sf(float(slope @ np.linalg.solve(slope_cov, slope)), 2) >= false_alarm:
        return None
    return slope


def _minus_gradient(stamps, usable, u, v, gradient) -> np.ndarray:
    """Stamps less ``gradient . (pixel - stamp centre)``; the constant stays in the fitted background."""
    centre_u = u[:, u.shape[1] // 2, None]
    centre_v = v[:, v.shape[1] // 2, None]
    ramp = gradient[0] * (u - centre_u)[:, None, :] + gradient[1] * (v - centre_v)[:, :, None]
    return np.where(usable, stamps - ramp, 0.0)


def centroid(
    image: np.ndarray,
    seeds: np.ndarray,
    *,
    method: str = "gauss",
    window: int = 7,
    psf_sigma_px: float | None = None,
    read_noise_e: float | None = None,
    gain_e_per_adu: float | None = None,
    bias_adu: float = 0.0,
    saturation_adu: float | None = None,
    invalid: np.ndarray | None = None,
    max_iter: int = 30,
    tol_px: float = 1e-4,
    frame_gradient: bool = False,
    gradient_adu_px: tuple[float, float] | np.ndarray | None = None,
) -> CentroidResult:
    """Refine seed positions to sub-pixel centroids with covariances.

    Parameters
    ----------
    image : (H, W) array
        Frame, ADU, indexed ``[row, col]``.
    seeds : (N, 2) array
        Starting positions (x, y), px, within ~1 px of the source (e.g. ``Detections.xy``).
    method : {"gauss", "iwc", "cog"}
        Estimator (module docstring).
    window : int
        Odd stamp side, px; about 6 PSF sigmas + 1 keeps the wings.
    psf_sigma_px : float, optional
        Known Gaussian PSF sigma, px. ``gauss`` then fixes the width; ``iwc`` sizes its window
        with it (default 1 px).
    read_noise_e, gain_e_per_adu : float, optional
        Detector read noise (electrons) and gain (electrons per ADU). With both, pixel variances
        are ``read_noise^2/gain^2 + (value - bias)/gain``. Without the read noise, the "gauss"
        method fits once with the stamp-border variance (plus shot noise if the gain is known),
        then fits the frame's background variance (and gain, if unknown) from the pooled
        residuals of all sources and fits again. The moment methods use the border variance
        plus shot noise (border variance alone without the gain).
    bias_adu : float
        Electronic offset of the frame, ADU (used with ``read_noise_e`` and ``gain_e_per_adu``).
    saturation_adu : float, optional
        Pixels at or above this value are left out of the fit (a clipped core carries no shape).
    invalid : (H, W) bool array, optional
        Pixels to leave out (``ImageMeta.invalid``).
    max_iter : int
        Iteration limit of the fit.
    tol_px : float
        Convergence threshold on the position step, px.
    frame_gradient : bool
        ``"gauss"`` only: measure a frame-wide background gradient from the sources' local
        backgrounds and, when it is significant, fit again without it (module docstring).
    gradient_adu_px : (2,) array, optional
        A known background gradient, ADU per px along x and y, subtracted from every stamp
        before the fit (e.g. the one a frame's stars gave, for a crop around a target).

    Returns
    -------
    CentroidResult
        Rows aligned with ``seeds``; failed seeds have ``ok`` False and NaN position.

    Raises
    ------
    InputError
        Unknown method, even or too small window, seeds not (N, 2), bad noise parameters.
    """
    image = np.asarray(image, dtype=float)
    seeds = np.asarray(seeds, dtype=float)
    if method not in METHODS:
        raise InputError(f"unknown centroid method {method!r}; expected one of {', '.join(METHODS)}")
    if not isinstance(window, (int, np.integer)) or not 3 <= window <= MAX_WINDOW or window % 2 == 0:
        raise InputError(f"centroid window must be an odd integer from 3 to {MAX_WINDOW} px (a point-source "
                         f"stamp), got {window!r}")
    if seeds.ndim != 2 or seeds.shape[1] != 2:
        raise InputError(f"seeds must have shape (N, 2), got {seeds.shape}")
    if image.ndim != 2:
        raise InputError(f"image must be 2-D, got shape {image.shape}")
    if invalid is not None and np.shape(invalid) != image.shape:
        raise InputError(f"centroid invalid mask has shape {np.shape(invalid)}, the image {image.shape}")
    for name, value in (("read_noise_e", read_noise_e), ("gain_e_per_adu", gain_e_per_adu), ("psf_sigma_px", psf_sigma_px)):
        if value is not None and not (math.isfinite(value) and value >= 0 and (name == "read_noise_e" or value > 0)):
            raise InputError(f"centroid {name} must be a positive finite number, got {value!r}")
    n = len(seeds)
    finite_seed = np.all(np.isfinite(seeds), axis=1)
    if gradient_adu_px is not None:
        gradient_adu_px = np.asarray(gradient_adu_px, float)
        if gradient_adu_px.shape != (2,) or not np.all(np.isfinite(gradient_adu_px)):
            raise InputError(f"centroid gradient_adu_px must be two finite numbers, got {gradient_adu_px!r}")
    if n == 0:
        empty = np.zeros(0)
        return CentroidResult(np.zeros((0, 2)), np.zeros((0, 2, 2)), empty, empty, np.zeros(0, bool), empty, empty, method)
    start = np.where(finite_seed[:, None], seeds, 0.0)
    _, u, v = _stamp_grid(start, window)
    # Only the stamps are inspected, so the cost does not grow with the frame size.
    bad = _NO_BAD if invalid is None else np.ascontiguousarray(invalid, dtype=np.bool_)
    stamps, usable = _cut_stamps(image, bad, invalid is not None, u, v,
                                 math.inf if saturation_adu is None else float(saturation_adu))
    gradient = np.zeros(2)
    if gradient_adu_px is not None and np.any(gradient_adu_px != 0.0):
        gradient = gradient_adu_px
        stamps = _minus_gradient(stamps, usable, u, v, gradient)
    noise = _noise_model(stamps, usable, read_noise_e, gain_e_per_adu, bias_adu)
    if method == "cog":
        xy, cov, flux, snr, sig, bg = _cog(stamps, usable, u, v, noise)
        ok = np.isfinite(xy).all(axis=1) & (flux > 0)
    elif method == "iwc":
        xy, cov, flux, snr, sig, bg = _iwc(stamps, usable, u, v, noise, start, psf_sigma_px)
        ok = np.isfinite(xy).all(axis=1) & (flux > 0)
    else:
        fit = _gauss(stamps, usable, u, v, noise, start, psf_sigma_px, max_iter, tol_px)
        if read_noise_e is None and fit.ok.any():
            noise = _with_fitted_noise(noise, stamps, usable, u, v, fit.xy, fit.flux, fit.background, fit.sigma_px,
                                       fit.ok, psf_sigma_px is None)
            fit = _gauss(stamps, usable, u, v, noise, np.where(fit.ok[:, None], fit.xy, start), psf_sigma_px, max_iter,
                         tol_px)
        if frame_gradient and fit.ok.sum() >= GRADIENT_MIN_SOURCES:
            ok = fit.ok
            # each background is the level at its stamp's centre pixel
            centres = np.column_stack([u[:, window // 2], v[:, window // 2]])
            measured = background_gradient(centres[ok], fit.background[ok], fit.background_var[ok])
            if measured is not None:
                gradient = gradient + measured
                stamps = _minus_gradient(stamps, usable, u, v, measured)
                fit = _gauss(stamps, usable, u, v, noise, np.where(ok[:, None], fit.xy, start), psf_sigma_px, max_iter,
                             tol_px)
        xy, cov, flux, snr, sig, bg, ok, _, fit_chi2, fit_dof = fit
    if method != "gauss":
        fit_chi2 = fit_dof = np.full(n, np.nan)
        ok &= np.all(np.abs(xy - np.rint(start)) < window / 2.0 - 0.5, axis=1)
    ok &= finite_seed & (usable.sum(axis=(1, 2)) > (5 if method == "gauss" else 1))
    ok &= np.all(np.isfinite(cov), axis=(1, 2))
    xy = np.where(ok[:, None], xy, np.nan)
    cov = np.where(ok[:, None, None], cov, np.nan)
    return CentroidResult(xy=xy, cov=cov, flux=flux, snr=snr, ok=ok, sigma_px=sig, background=bg, method=method,
                          gradient_adu_px=(float(gradient[0]), float(gradient[1])), chi2=fit_chi2,
                          dof=np.asarray(fit_dof, float), noise_var_adu2=_median(noise.read_var_adu2),
                          noise_gain_e_per_adu=None if noise.gain is None else float(noise.gain))
