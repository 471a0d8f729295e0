"""Centre and range of a resolved ellipsoidal body from its lit limb.

Steps (:func:`fit_limb_ellipsoid`), given the body's predicted pose (:class:`EllipsoidPose`: shape,
orientation, position and Sun direction in the camera frame):

1. Scan lines (:func:`scan_lines`). The Sun's direction projected at the body's centre (of the
   given pose: the same in every pass) gives the image's illumination direction ``s``; lines parallel to ``s``, ``line_spacing_px`` apart across the
   outline, each cross the outline twice. Going along ``s`` the lit limb is the *far* crossing and
   is always a fall of brightness; the terminator is always a rise (dark side to lit side), so a line
   is read only in a window around its predicted far crossing, and a line whose window reaches the
   dark side in the model image (the terminator or a cusp nearby, :func:`usable_lines`) is not
   used: the terminator is never taken for the limb. Lines 3 px apart (more than 2 sqrt 2) never share a pixel through the bilinear
   samples, so their errors are independent.
2. Per-line offsets (:func:`limb_offsets`). The model image of the body at the predicted pose
   (:func:`opnav.image.ellipsoid.render_ellipsoid`: same shading, PSF and pixel integral as the
   renderer) is sampled along each line; the frame's samples are fitted as ``gain * model(a - delta)
   + background`` by Gauss-Newton, generalised least squares with the samples' covariance (shot and
   read noise of the pixels through the bilinear weights, so neighbouring samples' shared pixels are
   counted). ``delta`` moves the model's exact limb crossing to the observed one: the edge's shape
   (a Lambert disk's limb darkening, the PSF) is in the model, so no edge detector's bias is.
3. Outline fit (:func:`fit_outline`). The closed-form horizon solution
   (:func:`opnav.image.ellipsoid.horizon_position`, Christian 2021) of the limb points gives the
   body's position, range included; Gauss-Newton then minimises the weighted distances along the
   lines between the observed crossings and those of the outline at ``r`` (the exact line-conic
   crossing, :func:`opnav.image.ellipsoid.line_crossings`; Jacobian by central differences).
   A line the outline at an iterate no longer crosses is left out (a grazing line after a long
   step). Lines beyond ``outlier_sigma`` of the fit are dropped (the worst half of them a round, so a
   first fit pulled by a few bad lines does not take good ones with it) and the fit repeated.
   Covariance: ``(J^T W J)^-1``, scaled by the reduced chi-square of the residuals when that is
   beyond the 95 % point of chi-square for their dof (the data say the noise is larger than the
   pixels' model: a shape or photometry the model lacks).
4. Later passes render the model at the previous fit's pose and fit again, until a pass moves the
   outline by no more than ``converged_px`` (the model's shift ``delta`` is then a small
   correction). They fit the lines' shifts not to the outline's crossings but to their *response*
   to a small move of the body (:attr:`LineOffsets.response`: the model image moved and scaled as
   the body's image would be, through each line's own estimator): a line's fitted shift of a
   profile along it is not its crossing's move where the edge curves across its window or the
   shading changes along the limb (a grazing line's shift is then half its crossing's or less), and
   a fit to the crossings carried up to 40 % of the previous pass's error into the next, noise
   included, so the centre scattered up to 1.4x its sigma. The prior is first improved: a small body (few lines, no room
   for long windows) is placed by cross-correlation with its model (shift and scale,
   :mod:`opnav.image.correlate`); a large one gets a first pass with windows widened for the
   prior's range error that reads only lines within 60 deg of the limb's normal (a prediction a
   few pixels off moves a grazing line's crossing far along it), each line's shift started from
   the best of a 0.5 px grid across the widening (Gauss-Newton from no shift does not reach an edge
   several px away: the model's slope is flat there).

Distortion: each line is straight in detector pixels; its start and direction are mapped to ideal
coordinates locally (a line a few pixels long is straight to well below 1e-3 px there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage
from scipy.stats import chi2 as chi2_dist

from ..camera import Camera
from ..errors import InputError, NoSolutionError
from .correlate import CorrelationOptions, DetectorNoise, correlate_centre
from .ellipsoid import (
    EllipsoidPose,
    horizon_cone,
    horizon_cones,
    horizon_position,
    ideal_xy,
    line_crossings,
    outline_points,
    render_ellipsoid,
    shape_matrix,
)


#: Neighbouring scan lines that share one model image (its box and spline): a large body's lit limb
#: in boxes a few tens of pixels across instead of one the size of the body (800 px across: the
#: model's unprojection, PSF and spline over 0.7 megapixels were 3/4 of a pass).
_TILE_LINES = 12


@dataclass(frozen=True)
class LimbOptions:
    """Settings of :func:`fit_limb_ellipsoid` (module docstring).

    ``line_spacing_px``: distance between scan lines (>= 2 sqrt 2 keeps their pixels apart), widened
    so that at most ``max_lines`` cross the outline (a large body's limb has more than enough);
    ``window_half_px``: half length of each line's window around its predicted crossing (None:
    3 PSF sigmas + 3 px); ``sample_step_px``: spacing of the samples along a line;
    ``min_lines``: fewest usable lines for a fit; ``min_edge_fraction``: a line's model edge must
    fall by at least this fraction of the strongest line's (cusps are dark); ``max_dip_fraction``:
    a line whose model dips by more than this fraction of its peak inside the limb (the
    terminator in the window) is dropped (:func:`usable_lines`); ``outlier_sigma``: normalised
    residual beyond which a line is dropped; ``passes``: most model renders (each after the first
    at the previous fit's pose); ``converged_px``: a pass after the first that moves the outline
    (centre shift plus radius change) by no more than this ends the fit; ``supersample``: rays per pixel per axis of the model
    where its shading is smooth (None: 2; the pixels the limb or the terminator crosses get
    :data:`opnav.bodies.EDGE_SUPERSAMPLE`); ``prior_range_fraction``: the prior's range error the first
    pass allows for (its windows widened by this fraction of the apparent radius);
    ``correlate_below_px``: a body smaller than this (apparent diameter, px) is first placed by
    cross-correlation (:mod:`opnav.image.correlate`, shift and scale), so the limb passes start
    within a small fraction of a pixel (a small body has few lines and no room for a wide window).
    """

    line_spacing_px: float = 3.0
    max_lines: int = 64
    window_half_px: float | None = None
    sample_step_px: float = 1.0
    min_lines: int = 5
    min_edge_fraction: float = 0.2
    max_dip_fraction: float = 0.5
    outlier_sigma: float = 4.0
    passes: int = 4
    converged_px: float = 0.02
    supersample: int | None = None
    prior_range_fraction: float = 0.02
    correlate_below_px: float = 150.0

    def __post_init__(self) -> None:
        if not self.line_spacing_px >= 2.0 * math.sqrt(2.0):
            raise InputError(f"LimbOptions.line_spacing_px must be >= 2.83 px, got {self.line_spacing_px!r}")
        if self.window_half_px is not None and not self.window_half_px >= 2.0:
            raise InputError(f"LimbOptions.window_half_px must be >= 2 px, got {self.window_half_px!r}")
        if not 0.1 <= self.sample_step_px <= 1.0:
            raise InputError(f"LimbOptions.sample_step_px must be in [0.1, 1] px, got {self.sample_step_px!r}")
        if self.min_lines < 4 or self.passes < 1 or (self.supersample is not None and self.supersample < 1):
            raise InputError("LimbOptions: min_lines >= 4, passes >= 1 and supersample >= 1 are required")
        if not (0.0 <= self.prior_range_fraction < 0.5 and self.correlate_below_px >= 0.0):
            raise InputError("LimbOptions: prior_range_fraction must be in [0, 0.5) and correlate_below_px >= 0")
        if not (math.isfinite(self.converged_px) and self.converged_px > 0.0):
            raise InputError(f"LimbOptions.converged_px must be positive, got {self.converged_px!r}")
        if not self.outlier_sigma > 2.0:
            raise InputError(f"LimbOptions.outlier_sigma must be > 2, got {self.outlier_sigma!r}")


@dataclass(frozen=True)
class ScanLines:
    """Scan lines of one pose (step 1): detector-pixel starts (L, 2) and unit direction ``dir_xy``
    (toward the Sun), the predicted crossing ``a_pred_px`` (L,) of each, the sample offsets
    ``a_px`` (M,) around it, the model image's samples ``model`` (L, M) and their derivative
    ``model_slope`` (L, M) along the line; ``ideal_start`` (L, 2), ``ideal_dir`` (L, 2) and
    ``ideal_per_px`` (L,) map each line to ideal coordinates; ``incidence`` (L,) the cosine between
    the line and the outline's normal at the crossing (small: the line grazes the limb);
    ``tiles``: the model images the lines were sampled from, ``(box, image, cubic spline
    coefficients)`` each over ``box = (x0, y0, width, height)`` (``_TILE_LINES`` neighbouring lines
    a tile: a large body's limb in small boxes, not one box the size of the body), ``line_tile``
    (L,) the tile of each line."""

    pose: EllipsoidPose
    start_xy: np.ndarray
    dir_xy: np.ndarray
    a_pred_px: np.ndarray
    a_px: np.ndarray
    model: np.ndarray
    ideal_start: np.ndarray
    ideal_dir: np.ndarray
    ideal_per_px: np.ndarray
    incidence: np.ndarray
    tiles: tuple
    line_tile: np.ndarray
    centre_xy: np.ndarray
    centre_jac: np.ndarray


@dataclass(frozen=True)
class LineOffsets:
    """Per-line result of step 2: ``delta_px`` (L,) along the line, its ``sigma_px`` (L,), the
    fitted ``gain`` (L,), ``ok`` (L,) bool and ``response`` (L, 3): d delta / d r, px per km
    (camera frame), the shift each line's fit reports when the body moves from the scan's pose by a
    small ``dr`` (its image moved and scaled: the edge's curvature and the shading across the
    window included, which a shift of the profile along the line leaves out)."""

    delta_px: np.ndarray
    sigma_px: np.ndarray
    gain: np.ndarray
    ok: np.ndarray
    response: np.ndarray


@dataclass(frozen=True)
class LimbCentre:
    """A limb fit's result.

    Attributes
    ----------
    r_cam_km : (3,) array
        Camera -> body centre, camera frame, km (apparent: as the frame shows it).
    cov_cam_km2 : (3, 3) array
        Its covariance, km^2.
    xy_px : (2,) array
        Detector pixel of the centre's direction.
    cov_xy_px2 : (2, 2) array
    initial_r_cam_km : (3,) array
        The closed-form horizon solution of the last pass (before Gauss-Newton).
    points_xy : (N, 2) array
        Observed limb points of the last pass (detector px), ``inliers`` (N,) those fitted.
    chi2 : float
        Weighted residual sum of the inliers; ``dof`` its degrees of freedom.
    """

    r_cam_km: np.ndarray
    cov_cam_km2: np.ndarray
    xy_px: np.ndarray
    cov_xy_px2: np.ndarray
    initial_r_cam_km: np.ndarray
    points_xy: np.ndarray
    inliers: np.ndarray
    chi2: float
    dof: int

    @property
    def range_km(self) -> float:
        return float(np.linalg.norm(self.r_cam_km))

    @property
    def sigma_range_km(self) -> float:
        u = self.r_cam_km / self.range_km
        return float(math.sqrt(u @ self.cov_cam_km2 @ u))


def illumination_direction(camera: Camera, pose: EllipsoidPose) -> np.ndarray:
    """Unit image direction (detector px) of the Sun as seen at the body's centre; +x when the Sun is
    along the line of sight (zero or 180 deg phase: any direction sees the lit limb)."""
    r = pose.r_cam_km
    c = camera.project(r)
    step = 1e-3 * float(np.linalg.norm(r))
    d = camera.project(r + step * pose.sun_cam) - c
    n = float(np.hypot(*d))
    if not np.isfinite(n) or n < 1e-9 * camera.focal_length_px:
        return np.array([1.0, 0.0])
    return d / n


def _bilinear(image: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear samples of ``image`` at ``xy`` (..., 2), their 4 pixel indices and weights (..., 4)."""
    h, w = image.shape
    x, y = xy[..., 0], xy[..., 1]
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = np.clip(x - x0, 0.0, 1.0), np.clip(y - y0, 0.0, 1.0)
    idx = np.stack([y0 * w + x0, y0 * w + x0 + 1, (y0 + 1) * w + x0, (y0 + 1) * w + x0 + 1], -1)
    wts = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
    return np.sum(image.ravel()[idx] * wts, -1), idx, wts


def scan_lines(camera: Camera, pose: EllipsoidPose, *, psf_sigma_px: float,
               options: LimbOptions = LimbOptions(), widen_px: float = 0.0,
               direction: np.ndarray | None = None) -> ScanLines:
    """Lines, windows and model samples for ``pose`` (module docstring, step 1); ``widen_px``
    lengthens each window at both ends; ``direction``: the lines' unit direction (detector px,
    toward the Sun; None: :func:`illumination_direction` at ``pose``)."""
    if not psf_sigma_px > 0:
        raise InputError(f"psf_sigma_px must be positive, got {psf_sigma_px!r}")
    half = (options.window_half_px if options.window_half_px is not None else 3.0 * psf_sigma_px + 3.0) + widen_px
    s = illumination_direction(camera, pose) if direction is None else np.asarray(direction, float)
    t = np.array([-s[1], s[0]])
    centre = camera.project(pose.r_cam_km)
    # the lines span the outline's width across them (its part on the detector, when any: a body
    # larger than the field), not its bounding box's, which is up to sqrt 2 wider when they run
    # diagonally and widened the spacing that holds them to max_lines
    outline = outline_points(camera, pose, spacing_px=2.0)
    on_detector = ((outline[:, 0] >= 0) & (outline[:, 0] <= camera.width_px - 1) & (outline[:, 1] >= 0)
                   & (outline[:, 1] <= camera.height_px - 1))
    across = ((outline[on_detector] if on_detector.sum() >= 2 else outline) - centre) @ t
    spacing = max(options.line_spacing_px, float(across.max() - across.min()) / options.max_lines)
    first = math.ceil(across.min() / spacing)
    offsets = np.arange(first, across.max() / spacing + 1) * spacing
    start = centre[None, :] + offsets[:, None] * t[None, :]
    f = camera.focal_length_px
    ends = ideal_xy(camera, np.concatenate([start - 0.5 * s, start + 0.5 * s]))
    n = len(start)
    ideal_start = 0.5 * (ends[:n] + ends[n:])
    chord = ends[n:] - ends[:n]
    per_px = np.hypot(*chord.T)
    ideal_dir = chord / per_px[:, None]
    cone = horizon_cone(pose)
    a_pred = line_crossings(cone, f, ideal_start, ideal_dir) / per_px
    keep = np.isfinite(a_pred)
    start, ideal_start, ideal_dir, per_px, a_pred = (v[keep] for v in (start, ideal_start, ideal_dir, per_px, a_pred))
    hit = ideal_start + (a_pred * per_px)[:, None] * ideal_dir
    normal = (np.concatenate([hit, np.full((len(hit), 1), f)], 1) @ cone.T)[:, :2]
    incidence = np.abs(np.sum(normal * ideal_dir, 1)) / np.maximum(np.hypot(*normal.T), 1e-300)
    if len(start) < options.min_lines:
        raise NoSolutionError(f"the outline spans only {len(start)} scan lines (need {options.min_lines})")
    a = np.arange(-half, half + 1e-9, options.sample_step_px)
    xy = start[:, None, :] + (a_pred[:, None, None] + a[None, :, None]) * s[None, None, :]
    # only lines whose whole window is on the detector (a body larger than the field has its limb
    # across the edge: the lines beyond it read nothing)
    on = np.all((xy[..., 0] >= 0) & (xy[..., 0] <= camera.width_px - 1) & (xy[..., 1] >= 0)
                & (xy[..., 1] <= camera.height_px - 1), 1)
    if on.sum() < options.min_lines:
        raise NoSolutionError(f"only {int(on.sum())} of the {len(on)} scan lines across the outline have their "
                              f"window on the detector (need {options.min_lines}): the lit limb is off the frame")
    start, ideal_start, ideal_dir, per_px, a_pred, incidence, xy = (
        v[on] for v in (start, ideal_start, ideal_dir, per_px, a_pred, incidence, xy))
    margin = half + 4.0 * psf_sigma_px + 3.0
    ss = options.supersample if options.supersample is not None else 2
    model = np.empty(xy.shape[:2])
    tiles = []
    line_tile = np.repeat(np.arange(math.ceil(len(start) / _TILE_LINES)), _TILE_LINES)[:len(start)]
    for k in range(int(line_tile[-1]) + 1):
        rows = line_tile == k
        part = xy[rows]
        # not clipped to the detector: its edge pixels hold light the PSF spreads from the body's
        # image beyond it (a model tile cut at the edge put a line one row from it 0.44 px off)
        x0 = int(math.floor(part[..., 0].min() - margin))
        y0 = int(math.floor(part[..., 1].min() - margin))
        x1 = int(math.ceil(part[..., 0].max() + margin))
        y1 = int(math.ceil(part[..., 1].max() + margin))
        tbox = (x0, y0, x1 - x0 + 1, y1 - y0 + 1)
        # ray-cast only what the windows read, with a PSF's reach around them
        band = np.zeros((tbox[3], tbox[2]), np.uint8)
        ends = np.round((part[:, [0, -1], :] - np.array([x0, y0], float)) * 16).astype(np.int32)
        cv2.polylines(band, [np.ascontiguousarray(e) for e in ends], False, 1,
                      thickness=int(2 * math.ceil(4.0 * psf_sigma_px + 3.0)) + 1, lineType=cv2.LINE_8, shift=4)
        template = render_ellipsoid(camera, pose, tbox, psf_sigma_px=psf_sigma_px, supersample=ss,
                                    pixels=band.astype(bool))
        model[rows] = _bilinear(template, part - np.array([x0, y0], float))[0]
        tiles.append((tbox, template, ndimage.spline_filter(template, order=3, mode="constant")))
    return ScanLines(pose=pose, start_xy=start, dir_xy=np.broadcast_to(s, start.shape).copy(), a_pred_px=a_pred,
                     a_px=a, model=model, ideal_start=ideal_start, ideal_dir=ideal_dir, ideal_per_px=per_px,
                     incidence=incidence, tiles=tuple(tiles), line_tile=line_tile, centre_xy=centre,
                     centre_jac=camera.projection_jacobian(pose.r_cam_km))


def limb_offsets(image: np.ndarray, scan: ScanLines, noise: DetectorNoise, *, iterations: int = 10,
                 search_px: float = 0.0) -> LineOffsets:
    """Per-line shift of the model's limb to the frame's (module docstring, step 2); ``search_px``:
    each line's Gauss-Newton starts from the best of the shifts within this many px (0.5 px apart;
    0: from no shift), for windows widened for a prior's range error.

    The frame's samples are fixed bilinear combinations of its pixels; the model applies the same
    combinations to the model image moved by ``delta`` along the line (cubic spline of the model
    image, which its PSF makes smooth), so the bilinear interpolation's own smoothing, which is
    not the same at every sub-pixel phase, is in both.
    """
    image = np.asarray(image, float)
    s = scan.dir_xy[0]
    base = scan.start_xy[:, None, :] + (scan.a_pred_px[:, None, None] + scan.a_px[None, :, None]) * s
    obs, idx, wts = _bilinear(image, base)
    var = np.zeros(image.size)
    var[idx] = noise.variance_adu2(image.ravel()[idx])
    # covariance of the samples: shared pixels of the bilinear footprints (L, M, M)
    same = idx[:, :, None, :, None] == idx[:, None, :, None, :]
    cov = np.einsum("lia,ljb,lijab->lij", wts * var[idx], wts, same.astype(float))
    m = obs.shape[1]
    cov += np.eye(m) * 1e-12 * np.trace(cov, axis1=1, axis2=2)[:, None, None] / m
    chol = np.linalg.cholesky(cov)
    width = image.shape[1]
    # the footprint pixels (rows, cols), in each line's model tile's coordinates
    corner = np.array([box[:2] for box, _, _ in scan.tiles], float)[scan.line_tile]
    pix_r = idx // width - corner[:, 1, None, None]
    pix_c = idx % width - corner[:, 0, None, None]
    # a small move dr of the body moves its image by J_c dr and scales it about its centre by
    # -r.dr / |r|^2 (the apparent size goes as 1 / range): the displacement under each footprint pixel
    r = scan.pose.r_cam_km
    offset = np.stack([idx % width, idx // width], -1) - scan.centre_xy  # (L, M, 4, 2) px from the centre

    def motion(dr):
        return scan.centre_jac @ dr - offset * (float(r @ dr) / float(r @ r))

    def model_at(delta, moved=0.0, rows=None):
        # lines ``rows`` (all: None) of the model moved by delta along the line and by ``moved``
        # ((L, M, 4, 2) px) under each pixel
        rows = np.arange(n_lines) if rows is None else rows
        rr = pix_r[rows] - delta[rows, None, None] * s[1] - (moved[rows][..., 1] if np.ndim(moved) else 0.0)
        cc = pix_c[rows] - delta[rows, None, None] * s[0] - (moved[rows][..., 0] if np.ndim(moved) else 0.0)
        values = np.empty(rr.shape)
        tile = scan.line_tile[rows]
        for k in np.unique(tile):
            sel = tile == k
            values[sel] = ndimage.map_coordinates(scan.tiles[k][2], [rr[sel].ravel(), cc[sel].ravel()], order=3,
                                                  mode="constant", prefilter=False).reshape(rr[sel].shape)
        return np.sum(values * wts[rows], -1)

    n_lines = len(obs)
    limit = float(scan.a_px[-1]) - 2.0
    delta = np.zeros(n_lines)
    if search_px > 0.0:
        # a limb several px from its prediction is beyond Gauss-Newton's reach from no shift (the
        # model's slope there is flat: its steps run to the window's end): start each line from its
        # best shift on a grid, the gain and background solved for each by least squares
        best = np.full(n_lines, np.inf)
        reach = min(search_px, limit - 0.5)
        for shift in np.arange(-math.floor(reach / 0.5) * 0.5, reach + 1e-9, 0.5):
            trial = np.full(n_lines, shift)
            mod = model_at(trial)
            mc = mod - mod.mean(1, keepdims=True)
            oc = obs - obs.mean(1, keepdims=True)
            g = np.sum(mc * oc, 1) / np.maximum(np.sum(mc * mc, 1), 1e-300)
            cost = np.where(g > 0, np.sum((oc - g[:, None] * mc) ** 2, 1), np.inf)
            better = cost < best
            best[better], delta[better] = cost[better], shift
    model = model_at(delta)
    gain = np.sum(model * obs, 1) / np.maximum(np.sum(model * model, 1), 1e-300)
    back = np.zeros(n_lines)
    h = 0.05
    wslope = np.empty_like(obs)
    wj = np.empty(obs.shape + (3,))
    normal = np.empty((n_lines, 3, 3))
    # each line iterates until its own step is below 1e-4 px: a grazing line whose shift and gain
    # trade off can swing for all the iterations, and made every line's model be evaluated again
    # (37 model evaluations of all 64 lines of an 800 px limb instead of ~16)
    refresh = np.ones(n_lines, bool)
    active = np.ones(n_lines, bool)
    for _ in range(iterations):
        a = np.flatnonzero(active)
        fresh = a[refresh[a]]
        if fresh.size:
            # the model's slope along the line, again only after a step of more than 0.05 px: near the
            # answer it hardly changes, and Gauss-Newton with it still lands on the exact residual's minimum
            slope = (model_at(delta + h, rows=fresh) - model_at(delta - h, rows=fresh)) / (2.0 * h)
            wslope[fresh] = np.linalg.solve(chol[fresh], slope[..., None])[..., 0]
        model = model_at(delta, rows=a)
        resid = obs[a] - (gain[a, None] * model + back[a, None])
        wm = np.linalg.solve(chol[a], np.stack([model, np.ones_like(model), resid], -1))
        wj[a] = np.stack([gain[a, None] * wslope[a], wm[..., 0], wm[..., 1]], -1)  # d/d(delta, gain, back)
        normal[a] = np.einsum("lmi,lmj->lij", wj[a], wj[a])
        rhs = np.einsum("lmi,lm->li", wj[a], wm[..., 2])
        try:
            step = np.linalg.solve(normal[a], rhs[..., None])[..., 0]
        except np.linalg.LinAlgError:
            with np.errstate(invalid="ignore"):
                step = np.einsum("lij,lj->li", np.linalg.pinv(normal[a]), rhs)
        delta[a] = np.clip(delta[a] + step[:, 0], -limit, limit)
        gain[a] += step[:, 1]
        back[a] += step[:, 2]
        moved = np.abs(step[:, 0])
        refresh[a] = moved > 0.05
        active[a] = moved >= 1e-4
        if not active.any():
            break
    try:
        cov_p = np.linalg.inv(normal)
    except np.linalg.LinAlgError:
        with np.errstate(invalid="ignore"):
            cov_p = np.linalg.pinv(normal)
    sigma = np.sqrt(np.abs(cov_p[:, 0, 0]))
    # the response of delta to a small move of the body: each footprint pixel's model value changes
    # by the move's displacement there, and the line's estimator (the Gauss-Newton gain of the
    # converged fit) turns the samples' change into a change of delta
    gain_row = np.einsum("lij,lmj->lim", cov_p, wj)[:, 0]  # (L, M): d delta / d(whitened sample)
    response = np.empty((n_lines, 3))
    step_km = 0.05 / float(np.linalg.norm(scan.centre_jac[:, :2], axis=0).max())  # ~0.05 px
    for j in range(3):
        move = motion(step_km * np.eye(3)[j])
        d_samples = gain[:, None] * (model_at(delta, move) - model_at(delta, -move)) / (2.0 * step_km)
        response[:, j] = np.sum(gain_row * np.linalg.solve(chol, d_samples[..., None])[..., 0], 1)
    # a line whose samples reach past the detector's edge reads clipped pixels, not the body: not used
    # (a body larger than the field, its limb across the edge)
    rows_px, cols_px = image.shape
    inside = np.all((base[..., 0] >= 0) & (base[..., 0] <= cols_px - 1) & (base[..., 1] >= 0)
                    & (base[..., 1] <= rows_px - 1), 1)
    ok = (np.isfinite(delta) & np.isfinite(sigma) & (sigma > 0) & (gain > 0) & (np.abs(delta) < limit)
          & np.all(np.isfinite(response), 1) & inside)
    return LineOffsets(delta_px=delta, sigma_px=sigma, gain=gain, ok=ok, response=response)


def usable_lines(scan: ScanLines, options: LimbOptions = LimbOptions()) -> np.ndarray:
    """Lines whose model window holds a clear limb fall with no dark stretch inside it (the
    terminator, a cusp): between the window's inner end and the model's peak the model never drops
    below ``1 - max_dip_fraction`` of the peak (a Lommel-Seeliger disk brightens toward the limb,
    which is allowed; a terminator starts from the dark side, which is not)."""
    diff = np.diff(scan.model, axis=1)
    fall = np.max(-diff, axis=1)
    strong = fall >= options.min_edge_fraction * np.max(fall)
    peak_at = np.argmax(scan.model, axis=1)
    inner = np.arange(scan.model.shape[1])[None, :] <= peak_at[:, None]
    low = np.min(np.where(inner, scan.model, np.inf), axis=1)
    peak = scan.model[np.arange(len(peak_at)), peak_at]
    return strong & (peak > 0) & (low >= (1.0 - options.max_dip_fraction) * peak)


def _line_residuals(scan: ScanLines, rows: np.ndarray, a_obs: np.ndarray, pose: EllipsoidPose,
                    focal_px: float, r_stack: np.ndarray) -> np.ndarray:
    """Observed minus modelled crossing (detector px) of lines ``rows`` for body positions (K, 3)."""
    cones = horizon_cones(shape_matrix(pose), r_stack)  # (K, 3, 3)
    a_model = line_crossings(cones[:, None], focal_px, scan.ideal_start[rows][None], scan.ideal_dir[rows][None])
    return a_obs[None, :] - a_model / scan.ideal_per_px[rows][None]


def fit_outline(scan: ScanLines, offsets: LineOffsets, camera: Camera, *,
                options: LimbOptions = LimbOptions(), usable: np.ndarray | None = None,
                linear: bool = False) -> LimbCentre:
    """Closed-form horizon solution then Gauss-Newton on the lines' crossings (module docstring, step 3).

    ``linear``: instead of the crossings of the outline, the lines' shifts as their fits respond to
    a small move of the body from the scan's pose (``offsets.response``): exact to first order in
    the move, where the outline's crossings leave out the edge's curvature and the shading across a
    line's window (a grazing line's shift is then up to half its crossing's); for a final pass whose
    pose is within a fraction of a pixel.
    """
    keep = offsets.ok & (usable if usable is not None else usable_lines(scan, options))
    rows = np.flatnonzero(keep)
    if rows.size < options.min_lines:
        raise NoSolutionError(f"only {rows.size} usable limb lines (need {options.min_lines})")
    a_obs = scan.a_pred_px + offsets.delta_px
    points = scan.start_xy + a_obs[:, None] * scan.dir_xy
    f = camera.focal_length_px
    r0 = horizon_position(scan.pose, camera.unproject(points[rows]))
    p = scan.pose.r_cam_km

    def residuals(sel, stack):
        if linear:
            return offsets.delta_px[sel][None, :] - (stack - p) @ offsets.response[sel].T
        return _line_residuals(scan, sel, a_obs[sel], scan.pose, f, stack)

    r = p.copy() if linear else r0.copy()
    inl = np.ones(rows.size, bool)
    w = 1.0 / offsets.sigma_px[rows]
    for _ in range(10):
        for _ in range(10):
            sel = rows[inl]
            h = 1e-7 * float(np.linalg.norm(r))
            stack = np.vstack([r, r + h * np.eye(3), r - h * np.eye(3)])
            res = residuals(sel, stack)
            if _drop_missed(res, inl, options):
                continue
            jac = -(res[1:4] - res[4:7]).T / (2.0 * h)  # d(model crossing)/dr, (n, 3)
            wr, wj = res[0] * w[inl], jac * w[inl, None]
            step, *_ = np.linalg.lstsq(wj, wr, rcond=None)
            r = r + step
            if np.max(np.abs(step)) < 1e-9 * float(np.linalg.norm(r)):
                break
        norm_res = np.abs(residuals(rows, r[None])[0] * w)
        # drop the lines beyond the gate (all of them at once when they are few, else the worst
        # half of them: a badly placed first fit makes good lines look bad) and fit again
        beyond = inl & (norm_res > options.outlier_sigma)
        if not beyond.any() or inl.sum() - 1 < options.min_lines:
            break
        cut = np.sort(norm_res[beyond])[::-1][:max(1, int(beyond.sum()) // 2) if beyond.sum() > 3 else None]
        drop = beyond & (norm_res >= cut[-1])
        if inl.sum() - drop.sum() < options.min_lines:
            break
        inl &= ~drop
    h = 1e-7 * float(np.linalg.norm(r))
    stack = np.vstack([r, r + h * np.eye(3), r - h * np.eye(3)])
    res = residuals(rows[inl], stack)
    if _drop_missed(res, inl, options):
        res = residuals(rows[inl], stack)
    sel = rows[inl]
    jac = -(res[1:4] - res[4:7]).T / (2.0 * h) * w[inl, None]
    chi2 = float(np.sum((res[0] * w[inl]) ** 2))
    dof = int(sel.size - 3)
    # the residuals scale the covariance only when they say the noise model is short (beyond the 95 %
    # point of chi-square for their dof: a shape or a photometry the model lacks); below it their
    # reduced chi-square is the noise's own scatter, and scaling by it would overstate sigma
    k = chi2 / max(dof, 1)
    try:
        cov = np.linalg.inv(jac.T @ jac) * (k if dof > 0 and chi2 > chi2_dist.ppf(0.95, dof) else 1.0)
    except np.linalg.LinAlgError:
        raise NoSolutionError(f"limb fit: the {sel.size} lines kept do not fix the body's position "
                              "(singular normal matrix)") from None
    j_px = camera.projection_jacobian(r)
    inliers = np.zeros(len(points), bool)
    inliers[sel] = True
    return LimbCentre(r_cam_km=r, cov_cam_km2=0.5 * (cov + cov.T), xy_px=camera.project(r),
                      cov_xy_px2=j_px @ cov @ j_px.T, initial_r_cam_km=r0, points_xy=points[rows],
                      inliers=inliers[rows], chi2=chi2, dof=dof)


def _drop_missed(res: np.ndarray, inl: np.ndarray, options: LimbOptions) -> bool:
    """Take out of ``inl`` (in place) the lines whose residuals ``res`` (K, n: one column per inlier)
    are not finite: the outline at a Gauss-Newton iterate no longer crosses them (a line grazing it
    near its tangent point, after a long step from a prior a few per cent off in range); True when
    any were. Too few left is a NoSolutionError."""
    missed = ~np.all(np.isfinite(res), 0)
    if not missed.any():
        return False
    if inl.sum() - missed.sum() < options.min_lines:
        raise NoSolutionError(f"limb fit: the fitted outline crosses only {int(inl.sum() - missed.sum())} of the "
                              f"lines (need {options.min_lines})")
    inl[np.flatnonzero(inl)[missed]] = False
    return True


def fit_limb_ellipsoid(image: np.ndarray, camera: Camera, pose: EllipsoidPose, *, psf_sigma_px: float,
                       noise: DetectorNoise, options: LimbOptions = LimbOptions()) -> LimbCentre:
    """The body's position in the camera frame from its lit limb (module docstring, steps 1-4).

    Parameters
    ----------
    image : (H, W) array
        Frame, ADU, ``[row, col]``.
    camera : Camera
    pose : EllipsoidPose
        Predicted pose (shape, orientation, position, Sun direction; camera frame, km).
    psf_sigma_px : float
        The camera's Gaussian PSF sigma, px (e.g. measured on the frame's stars).
    noise : DetectorNoise
    options : LimbOptions

    Returns
    -------
    LimbCentre

    Raises
    ------
    NoSolutionError
        Too few usable lines, or a fit that leaves the lines.
    """
    if np.shape(image) != camera.shape:
        raise InputError(f"image shape {np.shape(image)} does not match the camera {camera.shape}")
    fit = None
    # the lines' direction from the given pose, the same in every pass: near zero phase the Sun's
    # direction in the image is the small angle between it and the line of sight, which a pass's
    # own estimate would set (the lines then turned toward that estimate's error, and the centre's
    # covariance, long along the lines, turned toward the error: its scatter/sigma 0.76 at 0 deg)
    direction = illumination_direction(camera, pose)
    radius_px = float(np.max(pose.radii_km) / np.linalg.norm(pose.r_cam_km)) * camera.focal_length_px
    widen = options.prior_range_fraction * radius_px
    if 2.0 * radius_px < options.correlate_below_px:
        # only a starting centre and range: the covariance's template-error term (two more renders) is not needed
        cc = correlate_centre(image, camera, pose, psf_sigma_px=psf_sigma_px, noise=noise,
                              options=CorrelationOptions(supersample=options.supersample, template_error=False))
        pose = pose.at(camera.unproject(cc.xy_px) * float(np.linalg.norm(pose.r_cam_km)) / cc.scale)
        widen = 0.0
    for n in range(options.passes):
        scan = scan_lines(camera, pose, psf_sigma_px=psf_sigma_px, options=options, widen_px=widen if n == 0 else 0.0,
                          direction=direction)
        offsets = limb_offsets(image, scan, noise, search_px=widen if n == 0 else 0.0)
        usable = usable_lines(scan, options) & offsets.ok
        if n == 0 and options.passes > 1 and widen > 0.0:
            # a prediction a few px off moves a grazing line's crossing far along it: the first
            # pass reads only lines within 60 deg of the limb's normal
            steep = usable & (scan.incidence > 0.5)
            usable = steep if steep.sum() >= options.min_lines else usable
        fit = fit_outline(scan, offsets, camera, options=options, usable=usable, linear=n > 0)
        pose = pose.at(fit.r_cam_km)
        if n > 0 and _image_move_px(scan, fit.r_cam_km - scan.pose.r_cam_km, radius_px) <= options.converged_px:
            break
    return fit


def _image_move_px(scan: ScanLines, dr_km: np.ndarray, radius_px: float) -> float:
    """How far (px) a move ``dr_km`` (camera frame) of the body from ``scan``'s pose moves its outline:
    its centre's shift plus its radius' change."""
    r = scan.pose.r_cam_km
    return float(np.hypot(*(scan.centre_jac @ dr_km)) + radius_px * abs(float(r @ dr_km)) / float(r @ r))
