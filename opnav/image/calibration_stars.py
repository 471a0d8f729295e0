"""A frame's identified stars for camera calibration (:mod:`opnav.image.calibration`), from its file.

For each frame (:func:`frame_stars`):

1. The lost-in-space plate solution (:class:`opnav.image.plate_solve.PlateSolver`, the path of
   ``opnav solve``: pattern index, or the WCS pointing when no index solves) gives the attitude
   and a handful of matched stars; or (``identify="wcs"``) the FITS header's WCS pointing does,
   the catalog stars it predicts matched within 2.5 times the match radius.
2. Up to ``max_stars`` point sources are extracted with their centroid covariances
   (:func:`opnav.image.extract.extract_sources`): a calibration wants every star it can get, far
   more than the 40 a lost-in-space solve needs.
3. The catalog stars in view are moved to the frame's epoch (proper motion) and aberrated with the
   observer's velocity when the header (or ``--epoch``/``--velocity``) gives them
   (:meth:`opnav.catalog.StarCatalog.apparent_directions`): aberration alone changes the apparent
   scale of a field by up to ``|v| / c`` (1e-4 at 30 km/s), far above what a calibration resolves.
   With the observer's position (a FITS header's ``OBS_X/Y/Z``) and the epoch, parallax too: 1.5 AU
   from the Sun it moves a typical V 11 star (5 mas) by 0.0075", 0.002 px of a 1-degree camera,
   and a near one (0.1") by 0.04 px.
4. The solve's matches refine the attitude, focal length and ``k1`` of the starting camera
   (:func:`opnav.image.attitude.refine_camera`), so the catalog stars' predicted pixels fall within
   a pixel or so of their images across the field even when the starting camera is off by
   pixels at the corners.
5. Each predicted star is matched to the nearest source within ``match_radius_px``, both ways
   (the source's nearest prediction is that star), and only when no other catalog star is
   predicted within twice the radius of the source (no ambiguous pair). Only the ``2 N + 10``
   brightest catalog stars in view take part (N sources extracted): a catalog to V 14.5 has a star
   within a few pixels of every bright one on a wide field, far below what the frame shows. A wrong
   match left is rejected by the calibration's robust fit. The same test keeps out stars with a
   neighbour of comparable brightness within twice the radius.
6. The matched stars' centroids are made honest and the unreliable ones left out
   (:mod:`opnav.image.calibration_centroids`): with the detector's noise in the header (``GAIN``,
   ``RDNOISE``, ``BIASLVL``) they are fitted again with it (the extraction fits its noise model
   from the frame's stamps, which saturated and blended stars throw off: on six rendered 12-degree
   frames a background variance 9 to 18,000 times the true 26 ADU^2 and a gain of 0.16 to 2.2
   e-/ADU against 1, the stars' chi-square per dof 0.13 to 3.5 frame by frame), stars touching
   saturation are left out, and so is a star whose catalog neighbours (to the catalog's full depth)
   are predicted to pull its centroid by more than ``max_blend_sigma`` of its sigma. A frame
   without the noise keywords (PNG, JPEG) gets a noise model estimated from the stars' stamps
   (:func:`opnav.image.calibration_centroids.frame_noise`) and the same treatment; with too few
   stars for that (under 8) it keeps the extraction's centroids and leaves out instead a star with
   a catalog neighbour within ``neighbour_radius_px`` of its predicted place and at most
   ``neighbour_depth_mag`` fainter: the neighbour's light pulls its centroid the same way in every
   frame the pair is seen in, a bias no number of frames averages down. A star centred within
   ``EDGE_MARGIN_PX`` of the detector's edge is left out too: the edge cuts its light off on one side,
   which pulls its centroid inward (and a star just beyond the edge, its wing on the detector, was
   fitted outside it, where the calibration refused the whole set as frames of another camera).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..camera import Camera
from ..errors import InputError, NoSolutionError
from .attitude import refine_camera
from .calibration import FrameStars
from .calibration_centroids import MAX_BLEND_SIGMA, calibration_centroids
from .extract import extract_sources
from .io import read_image
from .plate_solve import PlateSolver

#: Default match radius of a predicted catalog star, px.
MATCH_RADIUS_PX = 3.0
#: A star centred closer than this to the detector's edge is left out (module step 6), px: a Gaussian PSF of
#: sigma 1 px loses 0.1 % of its light beyond 3 sigma, the detection's own edge margin
#: (:attr:`opnav.image.detect.DetectOptions.edge_margin_px`).
EDGE_MARGIN_PX = 3.0
#: Default reach of a neighbour's light on a star's centroid, px (module step 6, a frame without a
#: noise model): the 7-px centroid
#: stamp's half side and 4 widths of a 1-px PSF beyond it (the 1-degree demo camera's, and the
#: typical well-sampled star camera's).
NEIGHBOUR_RADIUS_PX = 7.0
#: Default depth of a neighbour that counts, magnitudes fainter than the star (module step 6): at 3 mag
#: (6 % of the flux) a neighbour 3 px away pulls a 1-px PSF's centroid by about 0.02 px, the centroid
#: noise of a typical calibration star. On the rendered 20-degree frames of tests/commands (catalog to
#: V 14.5) it leaves 118 of 204 stars, the fit's gate then rejects 2 instead of 24 and chi-square per
#: dof falls from 0.97 to 0.60 (their 0.01 px floor had absorbed the blends); 5 mag would leave 69.
NEIGHBOUR_DEPTH_MAG = 3.0


@dataclass(frozen=True)
class IdentifiedFrame:
    """One frame's stars for calibration (:func:`frame_stars`).

    Attributes
    ----------
    stars : FrameStars
        Matched centroids (with covariances) and apparent catalog directions.
    shape : (int, int)
        Frame shape (rows, columns).
    camera_id : str or None
        The FITS ``CAMERA`` keyword, when there is one.
    method : str
        How the attitude was found: ``"lost_in_space"`` or ``"tracking"`` (the plate solver), or
        ``"wcs"`` (the header's WCS pointing, ``identify="wcs"``).
    solved_matches : int
        Stars the first identification matched (step 1), before the deeper matching.
    solved_camera : Camera
        The plate solution's camera (a pinhole at the detector centre with the solved focal length),
        or the camera the WCS identification started from.
    """

    stars: FrameStars
    shape: tuple[int, int]
    camera_id: str | None
    method: str
    solved_matches: int
    solved_camera: Camera


def _directions(catalog, rows: np.ndarray, solved, position_km: np.ndarray | None = None) -> np.ndarray:
    """Apparent ICRF unit directions of catalog ``rows`` at the frame's epoch (module step 3); with the
    observer's SSB position (ICRF, km) and the epoch, parallax too."""
    epoch = solved.epoch_tdb_s
    velocity = solved.v_observer_km_s
    if epoch is None and velocity is None:
        return np.asarray(catalog.unit_vectors())[rows]
    zero = np.zeros(3)
    parallax = epoch is not None and position_km is not None
    return catalog.apparent_directions(
        rows, t_tdb_s=float(epoch) if epoch is not None else 0.0,
        r_observer_ssb_km=position_km if parallax else zero,
        v_observer_ssb_km_s=velocity if velocity is not None else zero, proper_motion=epoch is not None,
        parallax=parallax, aberration=velocity is not None)


def _brightest(rows: np.ndarray, n_sources: int) -> np.ndarray:
    """The first ``2 n + 10`` of ``rows`` (catalog stars in view, brightest first): only stars the frame can
    show take part in the match, so the many faint catalog stars far below detection do not make every
    bright star ambiguous (module step 5)."""
    return rows[: 2 * n_sources + 10]


def match_predicted(xy_sources: np.ndarray, xy_predicted: np.ndarray, radius_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``(sources, predicted)`` of the unambiguous mutual nearest pairs within ``radius_px`` (module step 5)."""
    if len(xy_sources) == 0 or len(xy_predicted) < 1:
        return np.zeros(0, int), np.zeros(0, int)
    k = min(2, len(xy_predicted))
    dist, near = cKDTree(xy_predicted).query(xy_sources, k=k)
    dist, near = dist.reshape(len(xy_sources), k), near.reshape(len(xy_sources), k)
    _, back = cKDTree(xy_sources).query(xy_predicted[near[:, 0]])
    mutual = back == np.arange(len(xy_sources))
    clear = dist[:, 1] > 2.0 * radius_px if k == 2 else np.ones(len(xy_sources), bool)
    keep = (dist[:, 0] <= radius_px) & mutual & clear
    return np.flatnonzero(keep), near[keep, 0]


#: Catalog neighbours of a matched star are looked for this far from it, px: the blend test
#: (:mod:`opnav.image.calibration_centroids`) keeps those within the stamp's half-diagonal and 5 PSF
#: widths (25 px: a PSF sigma up to 4 px).
NEIGHBOUR_SEARCH_PX = 25.0


def _neighbours(stars: np.ndarray, xy: np.ndarray, vmag: np.ndarray, radius_px: float) -> list[np.ndarray]:
    """Each of ``stars``' (rows of ``xy``/``vmag``) catalog neighbours within ``radius_px``: (M, 3) arrays of
    the offset from the star (x, y, px) and the magnitude difference (neighbour less star)."""
    front = np.flatnonzero(np.all(np.isfinite(xy), axis=1))
    if len(stars) == 0 or len(front) == 0:
        return [np.zeros((0, 3)) for _ in stars]
    near = cKDTree(xy[front]).query_ball_point(xy[stars], radius_px)
    out = []
    for i, others in zip(stars, near):
        j = front[np.asarray(others, int)]
        j = j[j != i]
        out.append(np.c_[xy[j] - xy[i], vmag[j] - vmag[i]])
    return out


def _has_neighbour(stars: np.ndarray, xy: np.ndarray, vmag: np.ndarray, radius_px: float, depth_mag: float) -> np.ndarray:
    """Whether each of ``stars`` (rows of ``xy``/``vmag``: every catalog star near the field, predicted
    pixels) has another within ``radius_px`` at most ``depth_mag`` fainter than it (module step 6)."""
    front = np.flatnonzero(np.all(np.isfinite(xy), axis=1))
    near = cKDTree(xy[front]).query_ball_point(xy[stars], radius_px)
    return np.array([any(front[j] != i and vmag[front[j]] <= vmag[i] + depth_mag for j in others)
                     for i, others in zip(stars, near)], dtype=bool)


#: How a frame's stars are first identified: the plate solver (lost in space, or tracking from the
#: WCS when no pattern solves), or from the FITS WCS pointing alone.
IDENTIFY = ("solve", "wcs")


@dataclass(frozen=True)
class _Seen:
    """When and how fast the frame was taken (what :func:`_directions` needs), from a header."""

    epoch_tdb_s: float | None
    v_observer_km_s: np.ndarray | None


def _header_position(header, path: str) -> np.ndarray | None:
    """The observer's SSB position of a FITS header (``OBS_X/Y/Z``, ICRF, km); None without one."""
    from .header import header_vector

    return header_vector(header, ("OBS_X", "OBS_Y", "OBS_Z"), path) if header is not None else None


def _wcs_start(path: str, image: np.ndarray, meta, camera: Camera | None, catalog, sources, radius_px: float,
               options, position: np.ndarray | None):
    """``(camera, attitude, seen, matched xy, matched directions)`` from the frame's WCS pointing: the
    catalog stars predicted with ``camera`` (default the WCS's pinhole) and matched within
    ``radius_px`` (module step 1 without a plate solve)."""
    from .header import has_epoch, header_epoch, header_vector, wcs_hint

    header = meta.header
    hint = wcs_hint(header, image.shape, path) if header is not None else None
    if hint is None:
        raise NoSolutionError(f"{path}: no celestial TAN WCS in the header to identify the stars from; "
                              f"use --identify solve")
    # the solver's options (--epoch, --velocity) take precedence over the header, as for the plate solve
    epoch = options.epoch_tdb_s if options.epoch_tdb_s is not None else (
        header_epoch(header, path) if has_epoch(header) else None)
    velocity = options.velocity_km_s if options.velocity_km_s is not None else header_vector(
        header, ("OBS_VX", "OBS_VY", "OBS_VZ"), path)
    seen = _Seen(epoch, velocity)
    start = camera if camera is not None else hint.camera
    rows = catalog.cone(hint.R_icrf_cam.apply([0.0, 0.0, 1.0]), min(math.pi, start.half_diagonal_fov_rad * 1.05 + 1e-3))
    v_icrf = _directions(catalog, rows, seen, position)
    v_cam = hint.R_icrf_cam.inv().apply(v_icrf)
    xy = start.project(v_cam)
    inside = _brightest(np.flatnonzero((v_cam[:, 2] > 0) & start.in_frame(xy, margin_px=-radius_px)), len(sources))
    src, pred = match_predicted(sources.xy, xy[inside], radius_px)
    if len(src) < 4:
        raise NoSolutionError(f"{path}: only {len(src)} extracted sources within {radius_px:g} px of the catalog "
                              f"stars the WCS pointing predicts; calibration needs at least 4 a frame")
    return start, hint.R_icrf_cam, seen, sources.xy[src], v_icrf[inside[pred]]


def frame_stars(
    path,
    solver: PlateSolver,
    camera: Camera | None = None,
    *,
    max_stars: int = 200,
    match_radius_px: float = MATCH_RADIUS_PX,
    identify: str = "solve",
    neighbour_radius_px: float = NEIGHBOUR_RADIUS_PX,
    neighbour_depth_mag: float | None = NEIGHBOUR_DEPTH_MAG,
    max_blend_sigma: float = MAX_BLEND_SIGMA,
) -> IdentifiedFrame:
    """Identify the stars of one image file for calibration (module docstring).

    Parameters
    ----------
    path : str or Path
        FITS, PNG, TIFF or JPEG frame.
    solver : PlateSolver
        Lost-in-space solver (its catalog is the one matched against).
    camera : Camera, optional
        Starting camera (distortion included) the catalog stars are predicted with; default the
        plate solution's (or the WCS's) pinhole camera.
    max_stars : int
        Point sources extracted (largest flux first).
    match_radius_px : float
        Largest distance of a source from its predicted star, px.
    identify : str
        ``"solve"``: module step 1 (the plate solver); ``"wcs"``: the FITS WCS pointing instead, the
        catalog stars it predicts with ``camera`` matched within 2.5 ``match_radius_px`` (no pattern
        index: a narrow camera's takes a minute and gigabytes to build).
    neighbour_radius_px : float
        A matched star with a catalog neighbour within this of its predicted place, px ...
    neighbour_depth_mag : float or None
        ... and at most this many magnitudes fainter is left out (module step 6, a frame with too few
        stars for a noise model); None keeps every star.
    max_blend_sigma : float
        A star whose catalog neighbours are predicted to pull
        its centroid by more than this many of its sigmas is left out (module step 6).

    Raises
    ------
    FrameError, InputError
        Unreadable or unusable frame; a camera of another size than the frame.
    NoSolutionError
        No plate solution (or no WCS), or fewer than 4 stars matched.
    """
    path = str(path)
    if not (math.isfinite(match_radius_px) and match_radius_px > 0):
        raise InputError(f"match radius must be a positive number of px, got {match_radius_px!r}")
    if not (math.isfinite(neighbour_radius_px) and neighbour_radius_px > 0):
        raise InputError(f"neighbour radius must be a positive number of px, got {neighbour_radius_px!r}")
    if neighbour_depth_mag is not None and not (math.isfinite(neighbour_depth_mag) and neighbour_depth_mag >= 0):
        raise InputError(f"neighbour depth must be a number of magnitudes >= 0, got {neighbour_depth_mag!r}")
    if not (math.isfinite(max_blend_sigma) and max_blend_sigma > 0):
        raise InputError(f"largest blend pull must be a positive number of sigmas, got {max_blend_sigma!r}")
    if identify not in IDENTIFY:
        raise InputError(f"--identify must be one of {', '.join(IDENTIFY)}, got {identify!r}")
    catalog = solver.catalog
    image, meta = read_image(path, bayer=solver.options.bayer)
    if camera is not None and camera.shape != image.shape:
        raise InputError(f"{path}: a {image.shape[1]} x {image.shape[0]} px frame; the camera given is "
                         f"{camera.width_px} x {camera.height_px} px (--camera)")
    sources = extract_sources(image, max_stars=max_stars, saturation_adu=meta.saturation_adu, invalid=meta.invalid,
                              lossy=meta.lossy)
    position = _header_position(meta.header, path)
    if identify == "wcs":
        start, attitude, seen, xy_matched, v_matched = _wcs_start(path, image, meta, camera, catalog, sources,
                                                                  2.5 * match_radius_px, solver.options, position)
        method, solved_camera = "wcs", start
    else:
        solved = solver.solve_file(path)
        start = camera if camera is not None else solved.solution.camera
        ident = solved.solution.identification
        attitude, seen = solved.attitude(), solved
        xy_matched = solved.solution.xy[ident.pairs[:, 0]]
        v_matched = _directions(catalog, ident.pairs[:, 1], solved, position)
        method, solved_camera = solved.method, solved.solution.camera
    refined = refine_camera(xy_matched, v_matched, start, attitude, fit_k1=len(xy_matched) >= 6)
    predictor = refined.camera
    boresight = refined.R_icrf_cam.apply([0.0, 0.0, 1.0])
    rows = catalog.cone(boresight, min(math.pi, predictor.half_diagonal_fov_rad * 1.05 + 1e-3))
    v_icrf = _directions(catalog, rows, seen, position)
    v_cam = refined.R_icrf_cam.inv().apply(v_icrf)
    xy_predicted = predictor.project(v_cam)
    inside = _brightest(np.flatnonzero((v_cam[:, 2] > 0) & predictor.in_frame(xy_predicted, margin_px=-match_radius_px)),
                        len(sources))
    src, pred = match_predicted(sources.xy, xy_predicted[inside], match_radius_px)
    ahead = np.where((v_cam[:, 2] > 0)[:, None], xy_predicted, np.nan)  # a star behind the camera projects anywhere
    vmag = np.asarray(catalog.vmag)[rows]
    centroids = calibration_centroids(image, meta, sources.xy[src], sources.cov[src],
                                      neighbours=_neighbours(inside[pred], ahead, vmag, NEIGHBOUR_SEARCH_PX),
                                      max_blend_sigma=max_blend_sigma, frame=path)
    keep = centroids.keep & predictor.in_frame(centroids.xy, margin_px=EDGE_MARGIN_PX)
    if not centroids.refitted and neighbour_depth_mag is not None and len(src):
        keep = keep & ~_has_neighbour(inside[pred], ahead, vmag, neighbour_radius_px, neighbour_depth_mag)
    src, pred = src[keep], pred[keep]
    if len(src) < 4:
        raise NoSolutionError(f"{path}: only {len(src)} extracted sources match catalog stars within "
                              f"{match_radius_px:g} px, unsaturated and clear of neighbours; calibration needs "
                              f"at least 4 a frame")
    stars = FrameStars(centroids.xy[keep], centroids.cov[keep], v_icrf[inside[pred]], refined.R_icrf_cam, name=path)
    header = meta.header
    camera_id = str(header["CAMERA"]).strip() if header is not None and "CAMERA" in header else None
    return IdentifiedFrame(stars, image.shape, camera_id, method, len(xy_matched), solved_camera)
