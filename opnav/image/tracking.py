"""Tracking mode of the image stage: measure only where the stars and targets are predicted.

A star tracker or OpNav camera that knows its attitude does not search the whole frame:
from the a-priori attitude (the previous solution carried forward with the body rate,
:class:`Tracker`) and the camera model it predicts where each catalog star and each target
must appear and reads small windows there.

:func:`track_frame` on one frame (:class:`opnav.image.pipeline.FrameInput`):

1. **Stars.** Catalog stars in the field (``PipelineOptions.vmag_limit``) at their apparent
   directions for the observer (proper motion, parallax, aberration: what the frame shows)
   are projected with ``frame.R_prior``; stars near the frame edge or near a target's
   predicted disk are left out. In a box of ``search_px`` around each prediction the
   brightest pixel seeds the same Gaussian-fit centroid as the full-frame stage
   (:func:`opnav.image.centroid.centroid`, CRB covariance). A star counts as found only if
   its centroid converged, has SNR >= ``PipelineOptions.min_snr``, lies within
   ``search_px`` of its prediction and has the PSF's width (``width_tolerance``: a star
   blended with a hot-pixel cluster is wider or narrower than the optics make a star);
   otherwise it is reported missing by catalog id and never matched to anything else.
2. **Attitude.** The found stars go into the same gated Wahba fit as the full-frame stage
   (:func:`opnav.image.camera_scatter.gated_attitude`) on their apparent directions: when the
   residuals scatter far beyond the centroid noise (a camera model off by a fraction of a pixel or
   more across the field), that scatter is added to every star's sigma. While the last solution
   showed such a scatter, the next frame's search box and jump gate widen by ``SCATTER_REACH``
   times it (a star at the field corner sits that far from where the camera model puts it).
3. **Loss of lock** (the frame gives no records; :class:`Tracker` re-acquires on the next
   frame with the full-frame stage): fewer than ``min_stars`` found, the gate dropping more
   than ``max_dropped_fraction`` of them, or the solution differing from the prior by more
   than ``max_jump_px`` (the rotation's displacement at the field corner).
4. **Targets.** Each moon is measured in a crop around its prediction (from the new
   attitude) with the full-frame stage's own detection, association, local fit beside a
   bright primary and phase correction (the crop is a camera whose principal point moved),
   so the records are those of :func:`opnav.image.pipeline.measure_frame`. With
   ``TrackingOptions.camera_covariance`` each record's covariance gains what the camera's
   uncertainty adds relative to the stars the attitude used (:mod:`opnav.image.camera_noise`).

Pixel coordinates: x = column, y = row, pixel centres at integers (docs/conventions.md).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from ..bodies import reproject_view
from ..camera import CameraCovariance
from ..errors import InputError, OpnavError
from ..records import Measurement
from .camera_noise import check_camera_error, frame_with_camera_covariance, with_camera_covariance
from .camera_scatter import gated_attitude
from .centroid import CentroidResult, centroid, psf_like
from .pipeline import (
    RESOLVED_BODIES,
    FrameInput,
    FrameResult,
    PipelineOptions,
    claim_moons,
    measure_frame,
    measure_sources,
    target_records,
)
from .starid import bearings

log = logging.getLogger(__name__)

#: While the last solution's stars scattered about it beyond their noise (a camera model off across
#: the field), the search box and the jump gate widen by this many times that per-axis scatter: the
#: error of a radial model (focal length, distortion) at the field corner is 2-3 times its RMS over
#: the field, and a star there sits that far from its prediction frame after frame.
SCATTER_REACH = 3.0


@dataclass(frozen=True)
class TrackingOptions:
    """Settings of :func:`track_frame` and :class:`Tracker`.

    Attributes
    ----------
    search_px : float
        A star's centroid must lie within this of its prediction, px (the a-priori attitude's
        error at the star).
    min_stars : int
        Fewer found stars is a loss of lock.
    max_dropped_fraction : float
        The attitude gate dropping more than this share of the found stars is a loss of lock.
    max_jump_px : float
        The solution may differ from the prior by at most this displacement at the field
        corner, px; beyond it is a loss of lock.
    edge_margin_px : float
        Stars predicted closer than this to the frame edge are not tracked.
    target_clearance_px : float
        Stars predicted within this of a target's disk are not tracked (its light would bias them).
    crop_half_px : int
        Half side of the crop in which each moon is measured (at least the association radius
        plus the local-fit window; 32 makes the crop one 64-px background tile).
    max_carry_s : float
        :class:`Tracker` carries the last solution forward at most this long, s; a frame taken
        later is tracked around its own a-priori attitude (the spacecraft's, in its header).
    width_tolerance : float
        A found star's fitted Gaussian width may differ from the frame's PSF width (the median
        of the found stars') by this fraction plus ``width_sigmas`` times the width's own
        relative uncertainty, 1 / (sqrt(2) SNR); otherwise it is not a clean star (a star
        blended with a hot-pixel cluster, a cosmic ray or a neighbour, or a defect that the
        optics did not blur) and is reported missing.
    width_sigmas : float
        See ``width_tolerance``.
    star_exclusion_px : float
        A source in a moon's crop within this of a catalog star's predicted position is that
        star, never the moon.
    moon_search_px : float
        A moon is searched for and must be measured within this of its prediction from the
        solved attitude (which the stars of the same frame fix to a small fraction of a pixel);
        anything farther (a limb feature of its primary, a passing moon) is not that moon, and
        the moon is reported missing.
    neighbour_depth_mag : float or None
        Guide-star selection: a star with another catalog star down to
        ``PipelineOptions.vmag_limit`` plus this many magnitudes within ``neighbour_radius_px``
        is not tracked (the neighbour's light pulls its centroid the same way for as long as the
        pair crosses the field: on the S3 star sensor, stars to V 6.5 beside V 6 guide stars
        moved the attitude by 0.15-0.23" for 40 minutes). None tracks every star (a frame that
        shows no star fainter than the stage's catalog, as the S1 camera's).
    neighbour_radius_px : float
        See ``neighbour_depth_mag`` (the centroid stamp's half side plus the PSF's reach).
    camera_covariance : opnav.camera.CameraCovariance or None
        The covariance of the camera the frames are measured with (a camera file's
        ``[calibration]``): when given, each moon record's covariance gains what it adds to the
        moon's direction relative to the frame's stars (:mod:`opnav.image.camera_noise`), on
        tracked and acquired frames alike. None: the camera is taken as exact.
    camera_error : str
        With ``camera_covariance``: ``white`` adds that term to each moon record's covariance;
        ``consider`` keeps the record's Jacobian by the camera's parameters instead (for a filter
        holding them as consider parameters, ``[navigation] camera_error``).
    """

    search_px: float = 3.0
    min_stars: int = 3
    max_dropped_fraction: float = 0.5
    max_jump_px: float = 3.0
    edge_margin_px: float = 6.0
    target_clearance_px: float = 12.0
    crop_half_px: int = 32
    max_carry_s: float = 600.0
    width_tolerance: float = 0.05
    width_sigmas: float = 5.0
    star_exclusion_px: float = 2.0
    moon_search_px: float = 3.0
    neighbour_depth_mag: float | None = None
    neighbour_radius_px: float = 7.0
    camera_covariance: CameraCovariance | None = field(default=None, compare=False)
    camera_error: str = "white"

    def __post_init__(self) -> None:
        check_camera_error(self.camera_error)
        for name in ("search_px", "max_jump_px", "edge_margin_px", "target_clearance_px", "max_carry_s",
                     "width_tolerance", "width_sigmas", "star_exclusion_px", "moon_search_px", "neighbour_radius_px"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise InputError(f"TrackingOptions.{name} must be positive, got {value!r}")
        if int(self.min_stars) != self.min_stars or self.min_stars < 2:
            raise InputError(f"TrackingOptions.min_stars must be an integer >= 2, got {self.min_stars!r}")
        if not 0.0 <= self.max_dropped_fraction < 1.0:
            raise InputError(f"TrackingOptions.max_dropped_fraction must be in [0, 1), got {self.max_dropped_fraction!r}")
        if self.neighbour_depth_mag is not None and not (math.isfinite(self.neighbour_depth_mag)
                                                         and self.neighbour_depth_mag > 0.0):
            raise InputError(f"TrackingOptions.neighbour_depth_mag must be positive or None, got {self.neighbour_depth_mag!r}")
        if int(self.crop_half_px) != self.crop_half_px or self.crop_half_px < 8:
            raise InputError(f"TrackingOptions.crop_half_px must be an integer >= 8, got {self.crop_half_px!r}")


@dataclass(frozen=True)
class StarPrediction:
    """Catalog stars predicted in a frame.

    Attributes
    ----------
    rows : (N,) int array
        Catalog rows.
    star_id : (N,) int array
    xy_px : (N, 2) array
        Predicted pixel positions.
    apparent_icrf : (N, 3) array
        Apparent unit directions (ICRF) for the frame's observer.
    """

    rows: np.ndarray
    star_id: np.ndarray
    xy_px: np.ndarray
    apparent_icrf: np.ndarray


@dataclass(frozen=True)
class TrackedFrame:
    """What tracking gave on one frame.

    Attributes
    ----------
    result : FrameResult or None
        Records, attitude and its covariance (as the full-frame stage gives them, with
        ``sources`` the tracked stars' centroids and no ``detections``); None when lock was lost.
    predicted : StarPrediction
    centroids : CentroidResult
        Row for row with ``predicted``.
    found : (N,) bool array
        Stars measured where predicted.
    used : (N,) bool array
        Stars the attitude fit kept.
    lost : str
        Why lock was lost ("" while tracking).
    scatter_px : float
        The camera model's per-axis scatter the attitude fit allowed for, px (0: none;
        :func:`opnav.image.camera_scatter.gated_attitude`).
    """

    result: FrameResult | None
    predicted: StarPrediction
    centroids: CentroidResult
    found: np.ndarray
    used: np.ndarray
    lost: str = ""
    scatter_px: float = 0.0

    @property
    def missing_star_ids(self) -> np.ndarray:
        """Catalog ids of the stars not found where predicted."""
        return self.predicted.star_id[~self.found]


def predict_stars(frame: FrameInput, catalog, views: dict, options: PipelineOptions,
                  tracking: TrackingOptions) -> StarPrediction:
    """Catalog stars at their apparent directions projected with ``frame.R_prior`` (module step 1)."""
    return predict_stars_at(frame.camera, frame.t_tdb_s, frame.observer, frame.R_prior, catalog, views, options, tracking)


def predict_stars_at(camera, t_tdb_s: float, observer, R: Rotation, catalog, views: dict, options: PipelineOptions,
                     tracking: TrackingOptions) -> StarPrediction:
    """:func:`predict_stars` for ``camera`` at attitude ``R`` (camera -> ICRF), epoch ``t_tdb_s`` and ``observer``."""
    boresight = R.apply([0.0, 0.0, 1.0])
    rows = np.asarray(catalog.cone(boresight, camera.half_diagonal_fov_rad * 1.05, vmag_limit=options.vmag_limit))
    if observer is not None and rows.size:
        directions = catalog.apparent_directions(rows, t_tdb_s=t_tdb_s, r_observer_ssb_km=observer.r_ssb_km,
                                                 v_observer_ssb_km_s=observer.v_ssb_km_s)
    else:
        directions = np.asarray(catalog.unit_vectors(), float)[rows]
    xy = camera.project(R.inv().apply(directions)) if rows.size else np.zeros((0, 2))
    keep = camera.in_frame(xy, margin_px=tracking.edge_margin_px) if rows.size else np.zeros(0, bool)
    for _, view in views.values():  # a star on a target's disk or glow is not a clean star
        radius = view.angular_radius_rad * camera.focal_length_px
        keep &= np.hypot(*(xy - view.xy_cof_px).T) > radius + tracking.target_clearance_px
    if tracking.neighbour_depth_mag is not None and keep.any():
        keep &= ~_has_neighbour(camera, t_tdb_s, observer, R, catalog, options, tracking, boresight, xy)
    rows = rows[keep]
    return StarPrediction(rows, np.asarray(catalog.star_id)[rows], xy[keep], directions[keep])


def _has_neighbour(camera, t_tdb_s: float, observer, R: Rotation, catalog, options: PipelineOptions,
                   tracking: TrackingOptions, boresight: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Whether each star at pixel ``xy`` has another catalog star down to ``neighbour_depth_mag``
    below the stage's limit within ``neighbour_radius_px`` (:class:`TrackingOptions`)."""
    from scipy.spatial import cKDTree

    limit = (np.inf if options.vmag_limit is None else options.vmag_limit) + tracking.neighbour_depth_mag
    deep = np.asarray(catalog.cone(boresight, camera.half_diagonal_fov_rad * 1.05, vmag_limit=limit))
    if observer is not None:
        directions = catalog.apparent_directions(deep, t_tdb_s=t_tdb_s, r_observer_ssb_km=observer.r_ssb_km,
                                                 v_observer_ssb_km_s=observer.v_ssb_km_s)
    else:
        directions = np.asarray(catalog.unit_vectors(), float)[deep]
    # every star finds itself (distance 0): a neighbour makes two
    counts = cKDTree(camera.project(R.inv().apply(directions))).query_ball_point(xy, tracking.neighbour_radius_px,
                                                                                return_length=True)
    return np.asarray(counts) > 1


def _catalog_stars_px(camera, t_tdb_s: float, observer, R: Rotation, catalog, options: PipelineOptions) -> np.ndarray:
    """Pixel positions (N, 2) of the catalog stars (to ``options.vmag_limit``) that ``camera`` at
    attitude ``R`` sees, at their apparent directions for ``observer``."""
    boresight = R.apply(camera.unproject(np.array([(camera.width_px - 1) / 2.0, (camera.height_px - 1) / 2.0])))
    rows = np.asarray(catalog.cone(boresight, camera.half_diagonal_fov_rad * 1.2, vmag_limit=options.vmag_limit))
    if not rows.size:
        return np.zeros((0, 2))
    directions = catalog.apparent_directions(rows, t_tdb_s=t_tdb_s, r_observer_ssb_km=observer.r_ssb_km,
                                             v_observer_ssb_km_s=observer.v_ssb_km_s)
    xy = camera.project(R.inv().apply(directions))
    return xy[camera.in_frame(xy, margin_px=-3.0)]


def views_with_primaries(camera, R: Rotation, observer, ephemeris, names) -> dict:
    """Body model and predicted view of each target and of the moons' primary (module step 1)."""
    from ..bodies import body_model, view_body

    models = {name: body_model(name) for name in names}
    for body in list(models.values()):
        if body.primary and body.primary not in models:  # a bright primary's disk and glow keep stars away too
            models[body.primary] = body_model(body.primary)
    return {name: (body, view_body(body, camera, R, observer, ephemeris, supersample=1, keep_rays=False))
            for name, body in models.items()}


def read_boxes(camera, t_tdb_s: float, observer, R_prior: Rotation, *, catalog, ephemeris=None,
               options: PipelineOptions = PipelineOptions(), tracking: TrackingOptions = TrackingOptions()):
    """The pixels :func:`track_frame` reads at attitude ``R_prior``: boxes ``(x0, y0, x1, y1)``, inclusive.

    One box around each star it will look for (search box plus the centroid stamp) and one
    around each moon's crop (2 px wider: the crop follows the solved attitude), so a frame
    rendered only in these windows (:func:`opnav.render.render_windows` with ``boxes``) gives
    the tracking stage every pixel it uses.
    """
    return _read_boxes(camera, t_tdb_s, observer, R_prior, catalog, ephemeris, options, tracking)[0]


def _read_boxes(camera, t_tdb_s, observer, R_prior, catalog, ephemeris, options, tracking):
    """(boxes, views) of :func:`read_boxes`."""
    views = views_with_primaries(camera, R_prior, observer, ephemeris, options.targets) if options.targets else {}
    stars = predict_stars_at(camera, t_tdb_s, observer, R_prior, catalog, views, options, tracking)
    half = int(math.ceil(tracking.search_px)) + options.window_px // 2 + 1
    boxes = [(int(x) - half, int(y) - half, int(x) + half, int(y) + half) for x, y in np.rint(stars.xy_px)]
    for name in options.targets:
        x, y = np.rint(views[name][1].xy_photocentre_px)
        if np.isfinite(x) and np.isfinite(y):
            h = tracking.crop_half_px + 2
            boxes.append((int(x) - h, int(y) - h, int(x) + h, int(y) + h))
    return boxes, views


def windows_frame(windows, *, camera, t_tdb_s: float, R_prior: Rotation, observer, saturation_adu: float | None,
                  frame_id: str = "frame") -> FrameInput:
    """A :class:`~opnav.image.pipeline.FrameInput` from windows read out of a frame (objects with
    ``x0``, ``y0`` and ``image`` in ADU): pixels outside every window are marked invalid."""
    image, invalid = paste_windows(windows, camera.shape)
    return FrameInput.from_camera(image, camera, t_tdb_s, R_prior, observer, saturation_adu=saturation_adu,
                                  invalid=invalid, frame_id=frame_id)


def paste_windows(windows, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """A frame of ``shape`` (rows, cols) from windows (``x0``, ``y0``, ``image`` in ADU): the image, zero
    outside every window, and the mask of those pixels (True: not read)."""
    image = np.zeros(shape)
    invalid = np.ones(shape, bool)
    for window in windows:
        rows, cols = window.image.shape
        image[window.y0:window.y0 + rows, window.x0:window.x0 + cols] = window.image
        invalid[window.y0:window.y0 + rows, window.x0:window.x0 + cols] = False
    return image, invalid


def _brightest_near(image: np.ndarray, xy: np.ndarray, half: int) -> np.ndarray:
    """Pixel (x, y) of the brightest pixel in the box of half side ``half`` around each ``xy``."""
    if not len(xy):
        return np.zeros((0, 2))
    offsets = np.arange(-half, half + 1)
    centre = np.rint(xy).astype(int)
    shape = (len(xy), offsets.size, offsets.size)
    cols = np.broadcast_to(np.clip(centre[:, 0, None, None] + offsets[None, None, :], 0, image.shape[1] - 1), shape)
    rows = np.broadcast_to(np.clip(centre[:, 1, None, None] + offsets[None, :, None], 0, image.shape[0] - 1), shape)
    best = np.argmax(image[rows, cols].reshape(len(xy), -1), axis=1)
    pick = np.arange(len(xy))
    return np.column_stack([cols.reshape(len(xy), -1)[pick, best], rows.reshape(len(xy), -1)[pick, best]]).astype(float)


def _jump_px(R_solution: Rotation, R_prior: Rotation, camera) -> float:
    """Displacement at the field corner of the rotation from the prior to the solution, px."""
    delta = (R_prior.inv() * R_solution).as_rotvec()
    corner = math.hypot(camera.width_px, camera.height_px) / 2.0
    return float(math.hypot(*delta[:2]) * camera.focal_length_px + abs(delta[2]) * corner)


def _crop(frame: FrameInput, xy: np.ndarray, half: int) -> FrameInput | None:
    """The part of ``frame`` within ``half`` px of ``xy`` as a frame of its own (principal point moved)."""
    h, w = frame.image.shape
    c0, r0 = int(round(xy[0])) - half, int(round(xy[1])) - half
    # 2 * half pixels a side: one background tile of the full-frame stage's 64 px for the default half
    c1, r1 = min(c0 + 2 * half, w), min(r0 + 2 * half, h)
    c0, r0 = max(c0, 0), max(r0, 0)
    if c1 - c0 < 8 or r1 - r0 < 8:
        return None
    camera = frame.camera.replace(width_px=c1 - c0, height_px=r1 - r0, cx_px=frame.camera.cx_px - c0,
                                  cy_px=frame.camera.cy_px - r0)
    invalid = None if frame.invalid is None else frame.invalid[r0:r1, c0:c1]
    return replace(frame, image=frame.image[r0:r1, c0:c1], camera=camera, invalid=invalid)


def track_frame(
    frame: FrameInput,
    *,
    catalog,
    ephemeris=None,
    options: PipelineOptions = PipelineOptions(),
    tracking: TrackingOptions = TrackingOptions(),
    rng: np.random.Generator | int | None = None,
    views: dict | None = None,
) -> TrackedFrame:
    """Measure ``frame`` in tracking mode around ``frame.R_prior`` (module docstring).

    Parameters
    ----------
    frame : FrameInput
        The frame; ``R_prior`` is the a-priori attitude (camera -> ICRF), ``observer`` the
        a-priori observer state (needed for the stars' apparent directions and the targets).
    catalog : opnav.catalog.StarCatalog
    ephemeris : opnav.ephemeris.Ephemeris, optional
        Needed when ``options.targets`` is not empty.
    options : PipelineOptions
        The full-frame stage's settings (targets, centroid window, SNR floor, magnitude limit).
    tracking : TrackingOptions
    rng : Generator, int or None
    views : dict, optional
        The targets' (and primaries') predicted views at ``frame.R_prior`` when already made
        (:meth:`Tracker.read_boxes` made them to plan the windows).

    Returns
    -------
    TrackedFrame
        ``lost`` says why when lock was lost (``result`` is then None).
    """
    rng = np.random.default_rng(rng)
    camera = frame.camera
    resolved = [name for name in options.targets if name in RESOLVED_BODIES]
    if resolved:
        raise InputError(f"tracking mode measures point-like moons; {resolved} need the full-frame stage")
    if options.targets and views is None:
        if ephemeris is None:
            raise InputError("track_frame: targets need an ephemeris")
        if frame.observer is None:
            raise InputError(f"{frame.frame_id}: no observer state; needed to predict targets")
        views = views_with_primaries(camera, frame.R_prior, frame.observer, ephemeris, options.targets)
    views = views or {}
    predicted = predict_stars(frame, catalog, views, options, tracking)
    seeds = _brightest_near(frame.image, predicted.xy_px, int(math.ceil(tracking.search_px)))
    sources = centroid(frame.image, seeds, window=options.window_px, read_noise_e=frame.read_noise_e,
                       gain_e_per_adu=frame.gain_e_per_adu, bias_adu=frame.bias_adu,
                       saturation_adu=frame.saturation_adu, invalid=frame.invalid,
                       frame_gradient=options.frame_gradient)
    with np.errstate(invalid="ignore", divide="ignore"):  # failed fits carry snr 0; found is already False there
        found = (sources.ok & psf_like(sources) & (sources.snr >= options.min_snr)
                 & (np.hypot(*(sources.xy - predicted.xy_px).T) <= tracking.search_px))
        if found.sum() >= 3:  # a PSF width to compare with
            deviation = np.abs(sources.sigma_px / np.median(sources.sigma_px[found]) - 1.0)
            found &= deviation <= tracking.width_tolerance + tracking.width_sigmas / (math.sqrt(2.0) * sources.snr)
    used = np.zeros(len(found), bool)
    scatter = 0.0

    def lost(reason: str) -> TrackedFrame:
        log.info("%s: tracking lost lock (%s)", frame.frame_id, reason)
        return TrackedFrame(None, predicted, sources, found, used, reason, scatter)

    count = int(found.sum())
    if count < tracking.min_stars:
        return lost(f"{count} of {len(found)} predicted stars found where predicted (at least {tracking.min_stars} needed)")
    rows = np.flatnonzero(found)
    fit = gated_attitude(bearings(sources.xy[rows], camera), predicted.apparent_icrf[rows],
                         np.sqrt(sources.cov[rows][:, [0, 1], [0, 1]].mean(axis=1)), camera,
                         min_stars=tracking.min_stars, max_dropped_fraction=tracking.max_dropped_fraction)
    solution, kept, fit_sigma_px, scatter = fit.solution, fit.kept, fit.sigma_px, fit.scatter_px
    used[rows[kept]] = True
    dropped = 1.0 - kept.mean()
    if dropped > tracking.max_dropped_fraction:
        return lost(f"the attitude gate dropped {dropped:.0%} of the {count} found stars")
    jump = _jump_px(solution.R_icrf_cam, frame.R_prior, camera)
    if jump > tracking.max_jump_px:
        return lost(f"the attitude moved {jump:.1f} px from its prior (gate {tracking.max_jump_px:g} px)")
    R, cov_att = solution.R_icrf_cam, solution.cov_rad2
    flags = list(frame.flags)
    records: list[Measurement] = []
    moon_options = replace(options, association_radius_px=min(options.association_radius_px, tracking.moon_search_px))
    sharp = used & np.isfinite(sources.sigma_px)
    psf_sigma = float(np.median(sources.sigma_px[sharp])) if sharp.sum() >= 3 else None
    for name in options.targets:
        body, view = views[name]
        # the bodies' directions do not change with the attitude: only their pixels move
        view = reproject_view(view, camera, frame.R_prior, camera, R)
        crop = _crop(replace(frame, R_prior=R), view.xy_photocentre_px, tracking.crop_half_px)
        if crop is None:
            flags.append(f"no_{name}")
            continue
        crop_view = reproject_view(view, camera, R, crop.camera, R)
        primary = None
        if body.primary in views:
            primary = reproject_view(views[body.primary][1], camera, frame.R_prior, crop.camera, R)
        try:
            # only sources that could be the moon: the association radius around its prediction
            # the stars, spread over the frame, measure its background gradient; the crop cannot
            found_crop = measure_sources(crop, moon_options, near=(crop_view.xy_photocentre_px,
                                                                   moon_options.association_radius_px),
                                         gradient_adu_px=sources.gradient_adu_px)
        except OpnavError as exc:
            log.info("%s: no measurement of %s (%s)", frame.frame_id, name, exc)
            flags.append(f"no_{name}")
            continue
        # a catalog star where the stage predicts one is never taken for the moon (a star passing
        # a moon hidden by its primary would otherwise be claimed)
        stars_xy = _catalog_stars_px(crop.camera, frame.t_tdb_s, frame.observer, R, catalog, options)
        if len(stars_xy) and len(found_crop.det):
            gap = np.min(np.hypot(*(found_crop.sources.xy[:, None, :] - stars_xy[None, :, :]).transpose(2, 0, 1)),
                         axis=1)
            with np.errstate(invalid="ignore"):
                found_crop = replace(found_crop, ok=found_crop.ok & ~(gap <= tracking.star_exclusion_px))
        # nor is another moon passing by: a source goes to the target predicted nearest to it
        others = [reproject_view(views[other][1], camera, frame.R_prior, crop.camera, R).xy_photocentre_px
                  for other in options.targets if other != name]
        if others and len(found_crop.det):
            own = np.hypot(*(found_crop.sources.xy - crop_view.xy_photocentre_px).T)
            nearest_other = np.min([np.hypot(*(found_crop.sources.xy - xy).T) for xy in others], axis=0)
            with np.errstate(invalid="ignore"):
                found_crop = replace(found_crop, ok=found_crop.ok & ~(nearest_other < own))
        crop_views = {name: (body, crop_view)}
        claimed = claim_moons(crop_views, found_crop, moon_options)
        measured = target_records(crop, crop_views, found_crop, claimed, R, cov_att, None, ephemeris, moon_options,
                                  rng, frame.frame_id, flags, psf_sigma_px=psf_sigma, primary_view=primary)
        if tracking.camera_covariance is not None:  # the crop's pixels are offset from the frame's
            measured = with_camera_covariance(
                measured, camera=camera, calibration=tracking.camera_covariance, star_xy=sources.xy[used],
                R_icrf_cam=R, star_weights=fit_sigma_px[kept] ** -2,
                xy_offset_px=(camera.cx_px - crop.camera.cx_px, camera.cy_px - crop.camera.cy_px),
                camera_error=tracking.camera_error)
        for record in measured:
            offset = np.hypot(*(np.asarray(record.extra["xy_px"]) - crop_view.xy_photocentre_px))
            if offset <= tracking.moon_search_px:
                records.append(record)
            else:
                log.info("%s: %s measured %.1f px from its prediction; not taken", frame.frame_id, name, offset)
                flags.append(f"no_{name}")
    result = FrameResult(frame.frame_id, frame.t_tdb_s, tuple(records), sources, None, R, cov_att, int(used.sum()),
                         tuple(flags), star_scatter_px=scatter)
    return TrackedFrame(result, predicted, sources, found, used, scatter_px=scatter)



@dataclass
class Tracker:
    """Frame-to-frame tracking with acquisition and re-acquisition (module docstring).

    Call :meth:`step` with each frame in time order. The first frame, and the first after a
    loss of lock, is measured by the full-frame stage (:func:`opnav.image.pipeline.measure_frame`,
    star identification around the frame's own prior); while locked, a frame is tracked around
    the last solution carried forward with the rate of the last two solutions (camera frame),
    or, more than ``TrackingOptions.max_carry_s`` after the last solution, around the frame's
    own a-priori attitude. Every acquisition and loss of lock is kept in ``events``;
    ``last_tracked`` is the last tracked frame's :class:`TrackedFrame` (stars predicted,
    found and used), for inspection.
    """

    catalog: object
    ephemeris: object = None
    options: PipelineOptions = field(default_factory=PipelineOptions)
    tracking: TrackingOptions = field(default_factory=TrackingOptions)
    events: list = field(default_factory=list)
    last_tracked: TrackedFrame | None = None
    _last: list = field(default_factory=list)
    _planned: tuple | None = None
    _scatter_px: float = 0.0

    def _tracking_now(self) -> TrackingOptions:
        """The tracking settings for the next frame: the search box and jump gate widened by the last
        solution's camera-model scatter (module step 2)."""
        if self._scatter_px == 0.0:
            return self.tracking
        reach = SCATTER_REACH * self._scatter_px
        return replace(self.tracking, search_px=math.hypot(self.tracking.search_px, reach),
                       max_jump_px=math.hypot(self.tracking.max_jump_px, reach))

    @property
    def locked(self) -> bool:
        """Whether the next frame is tracked (a solution since the last acquisition or loss)."""
        return bool(self._last)

    def prior(self, t_tdb_s: float) -> Rotation | None:
        """The last solution carried forward to ``t_tdb_s`` (camera -> ICRF), or None when unlocked
        or when the last solution is more than ``max_carry_s`` old."""
        if not self._last or abs(t_tdb_s - self._last[-1][0]) > self.tracking.max_carry_s:
            return None
        t1, R1 = self._last[-1]
        if len(self._last) < 2:
            return R1
        t0, R0 = self._last[-2]
        rate = (R0.inv() * R1).as_rotvec() / (t1 - t0)  # camera frame, rad/s
        return R1 * Rotation.from_rotvec(rate * (t_tdb_s - t1))

    def read_boxes(self, camera, t_tdb_s: float, observer, R_apriori: Rotation):
        """The windows :meth:`step` will read in a frame at ``t_tdb_s`` whose own a-priori attitude
        is ``R_apriori`` (:func:`read_boxes`), or None when the frame will be acquired full-frame."""
        if not self.locked:
            return None
        prior = self.prior(t_tdb_s)
        R = R_apriori if prior is None else prior
        boxes, views = _read_boxes(camera, t_tdb_s, observer, R, self.catalog, self.ephemeris, self.options,
                                   self._tracking_now())
        self._planned = (t_tdb_s, R.as_quat().tobytes(), views)  # step() reuses the predictions
        return boxes

    def step(self, frame: FrameInput, rng=None) -> FrameResult:
        """Measure one frame: tracking when locked, else full-frame acquisition.

        When acquisition finds no attitude either, the full-frame result (records with the
        frame's prior attitude and ``prior_sigma_rad``, flag ``attitude_prior``) is returned and
        the next frame tries acquisition again.
        """
        if self.locked:
            prior = self.prior(frame.t_tdb_s)
            carried = frame if prior is None else replace(frame, R_prior=prior)
            planned = self._planned
            views = (planned[2] if planned is not None and planned[0] == frame.t_tdb_s
                     and planned[1] == carried.R_prior.as_quat().tobytes() else None)
            self._planned = None
            tracked = track_frame(carried, catalog=self.catalog, ephemeris=self.ephemeris, options=self.options,
                                  tracking=self._tracking_now(), rng=rng, views=views)
            self.last_tracked = tracked
            if tracked.result is not None:
                self._remember(frame.t_tdb_s, tracked.result.R_icrf_cam, tracked.scatter_px)
                return tracked.result
            self.events.append({"frame": frame.frame_id, "t_tdb_s": frame.t_tdb_s, "event": "lost", "reason": tracked.lost})
            self._last.clear()
        result = measure_frame(frame, catalog=self.catalog, ephemeris=self.ephemeris, options=self.options, rng=rng)
        if self.tracking.camera_covariance is not None and "attitude_prior" not in result.flags:
            result = frame_with_camera_covariance(result, frame.camera, self.tracking.camera_covariance,
                                                  catalog=self.catalog, observer=frame.observer,
                                                  vmag_limit=self.options.vmag_limit,
                                                  camera_error=self.tracking.camera_error)
        if "attitude_prior" in result.flags:
            # as the full-frame stage: the records carry the prior's attitude sigma; no lock yet
            self.events.append({"frame": frame.frame_id, "t_tdb_s": frame.t_tdb_s, "event": "acquisition failed"})
            return result
        self.events.append({"frame": frame.frame_id, "t_tdb_s": frame.t_tdb_s, "event": "acquired",
                            "stars": result.n_stars_matched})
        self._remember(frame.t_tdb_s, result.R_icrf_cam, result.star_scatter_px)
        return result

    def _remember(self, t_tdb_s: float, R: Rotation, scatter_px: float) -> None:
        self._scatter_px = float(scatter_px)
        # a solution after a gap starts a new rate estimate
        if self._last and abs(t_tdb_s - self._last[-1][0]) > self.tracking.max_carry_s:
            self._last.clear()
        self._last = (self._last + [(t_tdb_s, R)])[-2:]
