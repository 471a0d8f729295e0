"""Frame -> time-tagged measurements: the image stage end to end.

For each frame (FITS with the opnav header, :mod:`opnav.render.frames_io`):

1. Read it (:func:`opnav.image.io.read_image`); the epoch, the a-priori attitude,
   a pinhole camera (unless a :class:`~opnav.camera.Camera` is given), the detector
   figures and the a-priori observer state come from the header
   (:mod:`opnav.image.header`), the saturation level from ``SATURATE``.
2. Detect (:func:`opnav.image.detect.detect`) and centroid every point source
   with the batched Gaussian fit (:func:`opnav.image.centroid.centroid`).
3. Predict each requested target's position from the a-priori state and
   attitude with the renderer's own geometry (:func:`opnav.bodies.view_body`,
   light time and aberration included), and take the nearest source within
   ``association_radius_px`` (a point-like moon) or the extended detection
   (a resolved planet).
4. Attitude: with a catalog, the remaining sources are identified in tracking
   mode (:func:`opnav.image.starid.track`) around the WCS attitude, giving
   ``R_icrf_cam`` with its covariance (refitted to the stars' apparent
   directions, :func:`_identify_attitude`; the match radius widens up to
   ``star_match_max_px`` for a camera model off by pixels at the corners, and the
   fit allows for the stars' scatter, :mod:`opnav.image.camera_scatter`); without a catalog, or when
   identification fails, the WCS attitude is used with ``prior_sigma_rad`` per
   axis in the records' covariance and the frame is flagged
   ``"attitude_prior"``.
5. Measurements (:class:`opnav.records.Measurement`):
   - moons: ``radec`` of the centre of figure, phase-corrected
     (:func:`opnav.image.targets.moon_direction`, flag ``FLAG_PHASE_CORRECTED``);
     a moon near its bright primary (module section below) is fitted locally;
   - resolved bodies: limb fit (:func:`opnav.image.targets.fit_limb`) ->
     ``los`` of the centre and, for every identified star, one ``starlight`` record
     (angle and elevation with their cross-covariance).
   Source flags map to record flags (saturated, edge, low SNR).

Moons next to a saturated primary
---------------------------------
When no clean point source is found near a moon's prediction, the local fit of
:mod:`opnav.image.moon_fit` searches around it with the primary's saturated, bloomed and
halo pixels left out; otherwise the frame is flagged ``no_<moon>`` (and ``<moon>_hidden``
when the prediction lies on those pixels), with the reason logged.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..constants import C_KM_S, RADIUS_KM
from ..errors import FrameError, InputError, NoSolutionError, OpnavError
from ..light import aberrate
from ..records import (
    ATTITUDE_COVARIANCE,
    ATTITUDE_JACOBIAN,
    FLAG_EDGE,
    FLAG_LOW_SNR,
    FLAG_PHASE_CORRECTED,
    FLAG_SATURATED,
    Measurement,
    join_frame_radec,
    write_csv,
)
from . import detect as detect_mod
from .centres import CentreOptions
from .centroid import CentroidResult, centroid, psf_like
from .header import camera_from_header, detector_keywords, header_epoch, header_observer, wcs_attitude
from .io import read_image
from .moon_fit import MoonContext, MoonHiddenError, local_moon_fit, moon_context
from .targets import fit_limb, limb_points, moon_direction, starlight_measurements

log = logging.getLogger(__name__)

FRAME_SUFFIXES = (".fits", ".fit", ".fts")
RESOLVED_BODIES = ("mars", "earth")
CENTRE_FINDING = ("by_name", "by_size")


@dataclass(frozen=True)
class PipelineOptions:
    """Settings of :func:`process_frame`.

    ``targets``: bodies to measure (``"phobos"``, ``"deimos"``, ``"mars"``, ``"earth"``);
    ``window_px``: centroid stamp side; ``prior_sigma_rad``: a-priori attitude error per
    axis; ``association_radius_px``: how far a moon may sit from its prediction;
    ``min_snr``: sources below are flagged ``FLAG_LOW_SNR``; ``phase_correction``: apply
    the moon phase correction; ``limb_altitude_km``/``limb_altitude_sigma_km``: visible-limb
    altitude of each body and its uncertainty for the starlight elevation (the renderer's UV
    Earth: 40 km + 8 km scale height -> 48 km, see :mod:`opnav.image.targets`);
    ``sensor``: written to every record; ``frame_gradient``: measure a background gradient
    across the frame (stray light) from the sources' local backgrounds and centroid without it
    when it is significant (:mod:`opnav.image.centroid`, "Frame-wide background gradient");
    ``centre_finding``: ``"by_name"`` (``RESOLVED_BODIES`` get the limb fit of
    :func:`limb_records`, the others the point-source path) or ``"by_size"`` (every sunlit body by
    :func:`opnav.image.centres.measure_body_centre`: limb ellipsoid fit or cross-correlation as its
    predicted size and phase say, a point-like one by the point-source path; the UV Earth keeps
    :func:`limb_records`; a target another body overlaps or nearly touches in the frame is not
    measured, its flags say why: :mod:`opnav.image.occultation`); ``centre_options``: the
    chooser's settings for ``"by_size"``; ``star_match_px``: star identification's match radius
    around the a-priori attitude, px; when no identification passes, it is doubled up to
    ``star_match_max_px`` (None: no widening; each try under the same false-match test): a camera
    model off by 0.2-0.5 % in focal length, a few pixels in principal point and distortion (an
    uncalibrated camera) puts the stars at the corner of a 1024-px detector 2-6 px from the
    pinhole's prediction; the attitude fit then allows for the stars' scatter
    (:mod:`opnav.image.camera_scatter`). Widening is for a camera the caller knows to be uncertain,
    not a default: with 3-4 stars an 8 px radius lets a bloom artefact stand in for a star hidden on
    Mars' trail (a frame of 3 August 2014 identified so was 5" off; ``tests/sim/test_image_loop.py``).
    """

    targets: tuple[str, ...] = ()
    detect: detect_mod.DetectOptions = field(default_factory=detect_mod.DetectOptions)
    window_px: int = 7
    prior_sigma_rad: float = math.radians(0.05)
    association_radius_px: float = 15.0
    min_snr: float = 10.0
    phase_correction: bool = True
    phase_sigma_fraction: float = 0.1
    limb_altitude_km: dict = field(default_factory=lambda: {"earth": 48.0})
    limb_altitude_sigma_km: dict = field(default_factory=lambda: {"earth": 1.0})
    vmag_limit: float | None = None
    sensor: str = "camera"
    min_psf_fraction: float = 0.5
    local_window_px: int = 9
    frame_gradient: bool = True
    centre_finding: str = "by_name"
    centre_options: CentreOptions = field(default_factory=CentreOptions)
    star_match_px: float = 2.0
    star_match_max_px: float | None = None

    def __post_init__(self) -> None:
        if self.centre_finding not in CENTRE_FINDING:
            raise InputError(f"PipelineOptions.centre_finding must be one of {', '.join(CENTRE_FINDING)}, "
                             f"got {self.centre_finding!r}")
        if self.window_px < 3 or self.window_px % 2 == 0:
            raise InputError(f"PipelineOptions.window_px must be odd and >= 3, got {self.window_px}")
        if not 0.0 < self.min_psf_fraction <= 1.0:
            raise InputError(f"PipelineOptions.min_psf_fraction must be in (0, 1], got {self.min_psf_fraction!r}")
        if self.local_window_px < 5 or self.local_window_px % 2 == 0:
            raise InputError(f"PipelineOptions.local_window_px must be odd and >= 5, got {self.local_window_px}")
        if self.star_match_max_px is not None and not self.star_match_max_px >= self.star_match_px:
            raise InputError(f"PipelineOptions.star_match_max_px ({self.star_match_max_px!r}) must be at least "
                             f"star_match_px ({self.star_match_px!r})")
        for name in ("prior_sigma_rad", "association_radius_px", "min_snr", "star_match_px"):
            if not getattr(self, name) > 0:
                raise InputError(f"PipelineOptions.{name} must be positive, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class FrameResult:
    """What one frame gave: ``records`` plus the intermediate products for inspection."""

    frame_id: str
    t_tdb_s: float
    records: tuple[Measurement, ...]
    sources: CentroidResult
    detections: detect_mod.Detections
    R_icrf_cam: Rotation
    cov_attitude_rad2: np.ndarray
    n_stars_matched: int
    flags: tuple[str, ...]
    #: The identified stars' per-axis scatter about the attitude beyond their centroid noise (the camera
    #: model's error) that the attitude fit allowed for, px (0: none; :mod:`opnav.image.camera_scatter`).
    star_scatter_px: float = 0.0


@dataclass(frozen=True)
class FrameInput:
    """One frame and what is known about it before measuring: the array-level input of
    :func:`measure_frame` (:func:`frame_input` builds it from a FITS file and its header).

    Attributes
    ----------
    image : (H, W) array
        Pixels, ADU, indexed ``[row, col]``; pixel centres at integer coordinates.
    camera : Camera
    t_tdb_s : float
        Mid-exposure epoch, TDB seconds past J2000.
    R_prior : Rotation
        A-priori attitude, camera -> ICRF.
    observer : Observer or None
        A-priori observer state (SSB, ICRF, km and km/s); needed to predict targets.
    read_noise_e, gain_e_per_adu, bias_adu, exposure_s : float
        Detector read noise (e-), gain (e-/ADU), bias (ADU), exposure (s).
    saturation_adu : float or None
    invalid : (H, W) bool array or None
        Pixels not to use (NaN in the file, outside a window).
    lossy : bool
        JPEG-like compression (detection should not trust single pixels).
    frame_id : str
    flags : tuple of str
        Flags the frame arrived with (``OPNVFLAG``).
    """

    image: np.ndarray
    camera: Camera
    t_tdb_s: float
    R_prior: Rotation
    observer: object | None
    read_noise_e: float
    gain_e_per_adu: float
    bias_adu: float
    exposure_s: float
    saturation_adu: float | None = None
    invalid: np.ndarray | None = None
    lossy: bool = False
    frame_id: str = "frame"
    flags: tuple[str, ...] = ()

    @classmethod
    def from_camera(cls, image: np.ndarray, camera: Camera, t_tdb_s: float, R_prior: Rotation, observer,
                    **rest) -> "FrameInput":
        """A frame whose detector figures (read noise, gain, bias, exposure) are the camera's own
        (an in-memory render); ``rest`` sets the other fields."""
        return cls(image=np.asarray(image, dtype=float), camera=camera, t_tdb_s=float(t_tdb_s), R_prior=R_prior,
                   observer=observer, read_noise_e=camera.read_noise_e, gain_e_per_adu=camera.gain_e_per_adu,
                   bias_adu=camera.bias_adu, exposure_s=camera.exposure_s, **rest)


def _record_flags(det_flags: int, snr: float, min_snr: float) -> int:
    flags = 0
    if det_flags & detect_mod.FLAG_SATURATED:
        flags |= FLAG_SATURATED
    if det_flags & detect_mod.FLAG_EDGE:
        flags |= FLAG_EDGE
    if not snr >= min_snr:
        flags |= FLAG_LOW_SNR
    return flags


def _identify_attitude(sources, usable, camera, catalog, R_prior, observer, options, rng):
    """Tracking-mode star ID, then Wahba on the stars' *apparent* directions.

    The catalog directions are astrometric; the frame shows stars displaced by stellar
    aberration (~20" at 25 km/s) and parallax. An attitude fitted to astrometric directions
    would absorb that shift and carry it into every target direction, so the final fit uses
    the apparent directions for the observer's state (the same corrections the renderer and
    the measurement models apply).

    The match radius starts at ``options.star_match_px`` and doubles, up to ``star_match_max_px``
    when one is given, while no identification passes (a camera model off by pixels at the corners); the attitude fit
    allows for the stars' scatter about it (:func:`opnav.image.camera_scatter.gated_attitude`).
    Returns ``(R_icrf_cam, covariance, star_rows, scatter_px)``.
    """
    from .camera_scatter import gated_attitude
    from .starid import CatalogTree, bearings, track

    rows = np.flatnonzero(usable)
    if rows.size < 3:  # as track() says, before a median of nothing
        raise NoSolutionError(f"tracking needs at least 3 stars, got {rows.size}")
    sigma_px = np.sqrt(sources.cov[rows][:, [0, 1], [0, 1]].mean(axis=1))
    b_cam = bearings(sources.xy[rows], camera)
    tree = CatalogTree.from_catalog(catalog, vmag_limit=options.vmag_limit)
    radius = options.star_match_px
    widest = options.star_match_px if options.star_match_max_px is None else options.star_match_max_px
    while True:
        try:
            ident = track(b_cam, tree, R_prior, camera, prior_sigma_rad=options.prior_sigma_rad,
                          match_radius_px=radius, sigma_rad=float(np.median(sigma_px)) * camera.pixel_scale_rad,
                          rng=rng)
            break
        except NoSolutionError:
            if radius >= widest:
                raise
            radius = min(2.0 * radius, widest)
    image_rows, cat_rows = ident.pairs[:, 0], ident.pairs[:, 1]
    v_icrf = astrometric = ident.v_icrf
    if observer is not None:
        state = dict(t_tdb_s=observer.t_tdb_s, r_observer_ssb_km=observer.r_ssb_km,
                     v_observer_ssb_km_s=observer.v_ssb_km_s)
        v_icrf = catalog.apparent_directions(cat_rows, **state)
        astrometric = catalog.apparent_directions(cat_rows, **state, aberration=False)
    # gated: an unresolved double or a star on a bright wing would otherwise bias the attitude
    fit = gated_attitude(b_cam[image_rows], v_icrf, sigma_px[image_rows], camera, min_stars=3)
    kept, solution = fit.kept, fit.solution
    if not kept.all():
        log.info("attitude fit dropped %d of %d matched stars as outliers", (~kept).sum(), kept.size)
    return solution.R_icrf_cam, solution.cov_rad2, (rows[image_rows][kept], v_icrf[kept], astrometric[kept],
                                                    catalog.star_id[cat_rows][kept]), fit.scatter_px


def frame_input(path: str | Path, camera: Camera | None = None) -> FrameInput:
    """Read a FITS frame with the opnav header into a :class:`FrameInput` (the header-to-camera step).

    The epoch is ``TDB_S`` (else ``DATE-AVG``/``DATE-OBS``), the a-priori attitude the WCS, the
    camera ``camera`` or a pinhole camera from the WCS, the detector ``RDNOISE``, ``GAIN``,
    ``BIASLVL``, ``EXPTIME`` (the camera's values when absent), the observer ``OBS_X`` ... ``OBS_VZ``.
    """
    path = Path(path)
    image, meta = read_image(path)
    header = meta.header
    if header is None:
        raise FrameError(f"{path}: the pipeline needs a FITS frame with an opnav header")
    t = header_epoch(header, str(path))
    R_prior, _, _ = wcs_attitude(header, str(path))
    if camera is None:
        camera = camera_from_header(header, image.shape, str(path))
    if image.shape != camera.shape:
        raise FrameError(f"{path}: image shape {image.shape} does not match the camera {camera.shape}")
    observer = header_observer(header, t, str(path)) if "OBS_X" in header else None
    return FrameInput(
        image=image, camera=camera, t_tdb_s=t, R_prior=R_prior, observer=observer,
        **detector_keywords(header, str(path), camera),
        saturation_adu=meta.saturation_adu, invalid=meta.invalid, lossy=meta.lossy, frame_id=path.stem,
        flags=tuple(f for f in str(header.get("OPNVFLAG", "")).split(",") if f),
    )


def process_frame(
    path: str | Path,
    *,
    camera: Camera | None = None,
    catalog=None,
    ephemeris=None,
    options: PipelineOptions = PipelineOptions(),
    rng: np.random.Generator | int | None = None,
    camera_covariance=None,
    camera_error: str = "white",
) -> FrameResult:
    """Turn one frame into measurement records (module docstring): :func:`frame_input` then :func:`measure_frame`.

    Parameters
    ----------
    path : str or Path
        FITS frame with the opnav header (epoch, WCS, detector, observer state).
    camera : Camera, optional
        Camera model (with distortion); default a pinhole camera from the WCS.
    catalog : opnav.catalog.StarCatalog, optional
        Enables star identification and the attitude fit.
    ephemeris : opnav.ephemeris.Ephemeris, optional
        Needed when ``options.targets`` is not empty.
    options : PipelineOptions
    rng : Generator, int or None
        For the star-ID hypothesis subset and RANSAC.
    camera_covariance : opnav.camera.CameraCovariance, optional
        The ``camera`` file's calibration covariance: each moon record's covariance gets what it adds
        relative to the frame's identified stars (:func:`opnav.image.camera_noise.frame_with_camera_covariance`;
        a frame without a star-identified attitude is left as it is). Needs ``catalog``.
    camera_error : str
        ``"white"`` (that share added to each record's covariance) or ``"consider"`` (each record keeps its
        Jacobian by the camera's parameters instead, for an EKF holding their errors as consider
        parameters); with ``camera_covariance`` only.

    Returns
    -------
    FrameResult
    """
    frame = frame_input(path, camera)
    result = measure_frame(frame, catalog=catalog, ephemeris=ephemeris, options=options, rng=rng, source=str(path))
    if camera_covariance is None or "attitude_prior" in result.flags:
        return result
    from .camera_noise import frame_with_camera_covariance

    return frame_with_camera_covariance(result, frame.camera, camera_covariance, catalog=catalog,
                                        observer=frame.observer, vmag_limit=options.vmag_limit,
                                        camera_error=camera_error)


@dataclass(frozen=True)
class _Sources:
    """Detections and centroids of a frame (or of a crop of it)."""

    det: detect_mod.Detections
    sources: CentroidResult
    ok: np.ndarray
    invalid: np.ndarray | None


def measure_sources(frame: FrameInput, options: PipelineOptions, near: tuple[np.ndarray, float] | None = None,
                    gradient_adu_px: tuple[float, float] | None = None) -> _Sources:
    """Background, detection and Gaussian-fit centroids of every point source (only of those within
    ``near = (xy, radius_px)`` when given: a crop around one target needs no others). A frame-wide
    background gradient is measured from the sources (``PipelineOptions.frame_gradient``) unless
    ``gradient_adu_px`` gives it (a crop, from the frame's stars)."""
    det = detect_mod.detect(frame.image, options=options.detect, saturation_adu=frame.saturation_adu,
                            invalid=frame.invalid, lossy=frame.lossy)
    if near is not None:
        keep = np.hypot(*(det.xy - np.asarray(near[0], float)).T) <= near[1]
        det = replace(det, xy=det.xy[keep], peak=det.peak[keep], flux=det.flux[keep], area=det.area[keep],
                      flags=det.flags[keep], label=det.label[keep], snr=det.snr[keep])
    invalid = det.rejected if frame.invalid is None else (det.rejected | frame.invalid)
    point = (det.flags & detect_mod.FLAG_EXTENDED) == 0
    sources = centroid(
        frame.image, det.xy, window=options.window_px, read_noise_e=frame.read_noise_e,
        gain_e_per_adu=frame.gain_e_per_adu, bias_adu=frame.bias_adu,
        saturation_adu=frame.saturation_adu, invalid=invalid,
        frame_gradient=options.frame_gradient and gradient_adu_px is None, gradient_adu_px=gradient_adu_px,
    )
    # a fit that is not a PSF (a cosmic-ray track through the stamp) is neither a star nor a moon
    return _Sources(det, sources, sources.ok & point & psf_like(sources), invalid)


def _target_views(frame: FrameInput, ephemeris, options: PipelineOptions, source: str) -> dict:
    """Each target's body model and predicted view from the a-priori attitude and observer."""
    if not options.targets:
        return {}
    if ephemeris is None:
        raise InputError("process_frame: targets need an ephemeris")
    if frame.observer is None:
        raise FrameError(f"{source}: header lacks the observer state (OBS_X...); needed to predict targets")
    from ..bodies import body_model, view_body

    return {name: (body_model(name), view_body(body_model(name), frame.camera, frame.R_prior, frame.observer, ephemeris,
                                               supersample=1, keep_rays=False))
            for name in options.targets}


def claim_moons(views: dict, found: _Sources, options: PipelineOptions) -> np.ndarray:
    """Sources nearest each point-like target's prediction (within the association radius)."""
    claimed = np.zeros(len(found.det), bool)
    for name, (_, view) in views.items():
        if name in RESOLVED_BODIES:
            continue
        dist = np.hypot(*(found.sources.xy - view.xy_photocentre_px).T)
        dist[~found.ok | claimed] = np.inf
        if dist.size and np.min(dist) < options.association_radius_px:
            claimed[int(np.argmin(dist))] = True
    return claimed


def target_records(frame: FrameInput, views: dict, found: _Sources, claimed: np.ndarray, R_icrf_cam: Rotation,
                   cov_att: np.ndarray, star_rows, ephemeris, options: PipelineOptions, rng, source: str,
                   flags: list[str], psf_sigma_px: float | None = None, primary_view=None) -> list[Measurement]:
    """Records of every target (moons: RA/Dec; resolved bodies: limb and starlight); misses go to ``flags``.

    ``psf_sigma_px``: the stars' PSF width when known from elsewhere (a crop has too few stars);
    ``primary_view``: the moons' primary as this frame sees it, when already predicted.
    """
    moons = [name for name in views if name not in RESOLVED_BODIES]
    moon_ctx = moon_context(frame, found, views, moons, ephemeris, psf_sigma_px, primary_view) if moons else None
    records: list[Measurement] = []
    blocked = _occultations(frame, views, R_icrf_cam, ephemeris, options) if options.centre_finding == "by_size" else {}
    for name, (body, view) in views.items():
        if name in blocked:
            # never fitted: another body's light or outline is in what its fit would read
            log.info("%s: no measurement of %s (%s)", source, name, ", ".join(blocked[name]))
            flags += [f"no_{name}", *blocked[name]]
            continue
        try:
            if options.centre_finding == "by_size" and body.shading != "uv-limb":
                centre = _centre_by_size(frame, body, found, R_icrf_cam, cov_att, ephemeris, options, psf_sigma_px)
                if centre is not None:
                    records += centre
                    continue
                records += _moon_records(name, body, view, found.sources, found.det, claimed, frame.camera, R_icrf_cam,
                                         cov_att, ephemeris, frame.t_tdb_s, frame.frame_id, options, moon_ctx)
            elif name in RESOLVED_BODIES:
                records += limb_records(name, body, frame.image, frame.camera, view.xy_cof_px,
                                        view.angular_radius_rad * frame.camera.focal_length_px, R_icrf_cam, cov_att,
                                        star_rows, frame.t_tdb_s, frame.frame_id, options, rng,
                                        v_observer_km_s=None if frame.observer is None else frame.observer.v_ssb_km_s)
            else:
                records += _moon_records(name, body, view, found.sources, found.det, claimed, frame.camera, R_icrf_cam,
                                         cov_att, ephemeris, frame.t_tdb_s, frame.frame_id, options, moon_ctx)
        except (NoSolutionError, FrameError) as exc:
            log.info("%s: no measurement of %s (%s)", source, name, exc)
            flags.append(f"no_{name}")
            if isinstance(exc, MoonHiddenError):
                flags.append(f"{name}_hidden")
    return records


def measure_frame(
    frame: FrameInput,
    *,
    catalog=None,
    ephemeris=None,
    options: PipelineOptions = PipelineOptions(),
    rng: np.random.Generator | int | None = None,
    source: str | None = None,
) -> FrameResult:
    """The image stage on one frame in memory (module docstring, steps 2-5): full-frame detection,
    centroids, star identification around ``frame.R_prior``, attitude, target records.

    ``source`` names the frame in errors and logs (default ``frame.frame_id``).
    """
    rng = np.random.default_rng(rng)
    source = source or frame.frame_id
    flags = list(frame.flags)
    found = measure_sources(frame, options)
    views = _target_views(frame, ephemeris, options, source)
    claimed = claim_moons(views, found, options)
    R_icrf_cam, cov_att, matched, star_rows = frame.R_prior, np.eye(3) * options.prior_sigma_rad**2, 0, None
    scatter_px = 0.0
    if catalog is not None:
        usable = found.ok & ~claimed & ((found.det.flags & (detect_mod.FLAG_SATURATED | detect_mod.FLAG_BLENDED)) == 0)
        try:
            R_icrf_cam, cov_att, star_rows, scatter_px = _identify_attitude(
                found.sources, usable, frame.camera, catalog, frame.R_prior, frame.observer, options, rng)
            matched = len(star_rows[0])
        except (NoSolutionError, InputError) as exc:
            log.warning("%s: star identification failed (%s); using the a-priori attitude", source, exc)
            flags.append("attitude_prior")
    else:
        flags.append("attitude_prior")
    records = target_records(frame, views, found, claimed, R_icrf_cam, cov_att, star_rows, ephemeris, options, rng,
                             source, flags)
    return FrameResult(frame.frame_id, frame.t_tdb_s, tuple(records), found.sources, found.det, R_icrf_cam, cov_att,
                       matched, tuple(flags), scatter_px)


def _occultations(frame: FrameInput, views: dict, R_icrf_cam: Rotation, ephemeris,
                  options: PipelineOptions) -> dict[str, list[str]]:
    """Flags (``phobos_transits_mars``, ``mars_occulted_by_phobos``, ``phobos_in_glare_of_mars``) of each
    target another body overlaps or comes within ``centre_options.glare_margin_px`` of
    (:func:`opnav.image.occultation.frame_conflicts`), among the targets and their primaries (a
    moon's primary is in its frame whether or not it is measured)."""
    from ..bodies import body_model
    from .occultation import frame_conflicts

    bodies = {name: body for name, (body, _) in views.items()}
    for body in list(bodies.values()):
        if body.orientation == "synchronous" and body.primary not in bodies:
            bodies[body.primary] = body_model(body.primary)
    found: dict[str, list[str]] = {}
    for conflict in frame_conflicts(frame.camera, list(bodies.values()), R_icrf_cam, frame.observer, ephemeris,
                                    margin_px=options.centre_options.glare_margin_px):
        if conflict.name in views:
            found.setdefault(conflict.name, []).append(conflict.flag)
    return found


def _centre_by_size(frame: FrameInput, body, found: _Sources, R_icrf_cam: Rotation, cov_att: np.ndarray, ephemeris,
                    options: PipelineOptions, psf_sigma_px: float | None) -> list[Measurement] | None:
    """Records of a sunlit body by :func:`opnav.image.centres.measure_body_centre`, or None when it is
    point-like (the point-source path measures it). The model's PSF is ``psf_sigma_px`` or the
    median Gaussian width of the frame's clean stars."""
    from .centres import apparent_diameter_px, body_pose, choose_method, measure_body_centre
    from .correlate import DetectorNoise

    pose = body_pose(body, frame.R_prior, frame.observer, ephemeris)
    if choose_method(apparent_diameter_px(frame.camera, pose), pose.phase_rad, options=options.centre_options) == "point":
        return None
    if psf_sigma_px is None:
        stars = found.ok & ((found.det.flags & (detect_mod.FLAG_SATURATED | detect_mod.FLAG_BLENDED)) == 0)
        stars &= found.sources.snr > 20.0
        if stars.sum() < 3:
            raise NoSolutionError(f"{body.name}: too few clean stars ({int(stars.sum())}) to know the PSF its model needs")
        psf_sigma_px = float(np.median(found.sources.sigma_px[stars]))
    got = measure_body_centre(frame.image, frame.camera, body, R_icrf_cam=R_icrf_cam, cov_att_rad2=cov_att,
                              observer=frame.observer, ephemeris=ephemeris, psf_sigma_px=psf_sigma_px,
                              noise=DetectorNoise(frame.read_noise_e, frame.gain_e_per_adu, frame.bias_adu),
                              t_tdb_s=frame.t_tdb_s, sensor=options.sensor, frame_id=frame.frame_id,
                              options=options.centre_options, prior_R_icrf_cam=frame.R_prior)
    return list(got.records)


def _moon_records(name, body, view, sources, det, claimed, camera, R_icrf_cam, cov_att, ephemeris, t, frame_id, options,
                  ctx: MoonContext | None = None):
    from ..bodies import body_axes_icrf

    dist = np.hypot(*(sources.xy - view.xy_photocentre_px).T)
    dist[~claimed] = np.inf
    # another target's claimed source must not stand in for this one
    found = bool(dist.size) and dist.min() < options.association_radius_px
    i = int(np.argmin(dist)) if found else -1
    if found and ctx is not None:
        # a centroid stamp touching blocked pixels would fit Mars' halo or bloom as background
        c = np.rint(sources.xy[i]).astype(int)
        half = options.window_px // 2
        stamp = ctx.blocked[max(c[1] - half, 0):c[1] + half + 1, max(c[0] - half, 0):c[0] + half + 1]
        found = not stamp.any()
    local = None
    if ctx is not None and not (found and dist[i] < 1.0):
        # The nearest clean source may be a star while the moon itself sits in the primary's
        # component with no seed of its own: the local search competes, and the nearer one wins.
        try:
            local = local_moon_fit(name, view, camera, ctx, options)
        except NoSolutionError:
            if not found:
                raise
        if local is not None and found and dist[i] <= float(np.hypot(*(local.xy - view.xy_photocentre_px))):
            local = None
    if local is None and found:
        xy, cov_xy = sources.xy[i], sources.cov[i]
        flags = _record_flags(int(det.flags[i]), float(sources.snr[i]), options.min_snr)
        extra = {}
    elif ctx is None:
        raise NoSolutionError(f"no source within {options.association_radius_px} px of the predicted {name}")
    else:
        fit = local
        xy, cov_xy = fit.xy, fit.cov
        flags = _record_flags(0, fit.snr, options.min_snr)
        extra = {"fit": "psf_plane_masked", "psf_fraction": round(fit.psf_fraction, 3)}
    kwargs = {}
    if options.phase_correction and body.shading in ("lommel-seeliger", "lambert"):
        t_emit = t - view.range_km / C_KM_S
        r_sun_body = ephemeris.position(name, t_emit) - ephemeris.position("sun", t_emit)
        kwargs = {
            "radii_km": body.radii_km, "R_icrf_body": Rotation.from_matrix(body_axes_icrf(body, t_emit, ephemeris)),
            "sun_icrf": -np.asarray(r_sun_body, float) / np.linalg.norm(r_sun_body), "range_km": view.range_km,
            "law": body.shading, "phase_sigma_fraction": options.phase_sigma_fraction,
        }
        flags |= FLAG_PHASE_CORRECTED
    moon = moon_direction(xy, cov_xy, camera, R_icrf_cam, cov_att, **kwargs)
    return [Measurement(
        t_tdb_s=t, kind="radec", value=[moon.ra_rad, moon.dec_rad], covariance=moon.cov_rad2, target=name,
        sensor=options.sensor, frame_id=frame_id, flags=flags,
        extra={"xy_px": np.asarray(xy).tolist(), "xy_cof_px": moon.xy_cof_px.tolist(),
               ATTITUDE_JACOBIAN: moon.attitude_jacobian, ATTITUDE_COVARIANCE: np.asarray(cov_att, float), **extra},
    )]


def limb_records(name: str, body, image: np.ndarray, camera: Camera, centre_xy: np.ndarray, radius_px: float,
                 R_icrf_cam: Rotation, cov_att: np.ndarray, star_rows, t: float, frame_id: str,
                 options: PipelineOptions, rng, radial_half_width_px: float | None = None,
                 v_observer_km_s: np.ndarray | None = None) -> list[Measurement]:
    """Records of a resolved body from its limb: the ``los`` of its centre (ICRF unit vector) and one
    ``starlight`` record (angle and elevation, rad) per star of ``star_rows`` (None: no star): rows,
    apparent ICRF unit vectors (what the frame shows: the angle is measured against them),
    astrometric ones (proper motion and parallax, no aberration: what the record carries, as the
    measurement model aberrates it with the filter's velocity) and catalog ids.

    The limb is searched around ``centre_xy`` (px) at ``radius_px`` (within ``radial_half_width_px``
    of it, :func:`opnav.image.targets.limb_points`); ``R_icrf_cam`` (camera -> ICRF) with ``cov_att``
    (camera-frame small rotation, rad^2) is the attitude of ``camera``. With the observer's SSB
    velocity ``v_observer_km_s`` (ICRF, km/s) the limb is fitted as the geometric cone and its
    axis aberrated (:func:`opnav.image.targets.fit_limb`): the apparent centre and the geometric
    radius the measurement models use. Raises ``NoSolutionError`` when no limb is fitted.
    """
    pts = limb_points(image, centre_xy, radius_px, radial_half_width_px=radial_half_width_px)
    velocity_cam = None if v_observer_km_s is None else R_icrf_cam.inv().apply(v_observer_km_s)
    fit = fit_limb(pts, camera, rng=rng, velocity_cam_km_s=velocity_cam)
    rot = R_icrf_cam.as_matrix()
    c_icrf = rot @ fit.centre_cam
    if v_observer_km_s is not None:
        c_icrf = aberrate(c_icrf, v_observer_km_s)
    tangent_icrf = fit.tangent_cam @ rot.T
    cross = np.array([[0.0, -fit.centre_cam[2], fit.centre_cam[1]], [fit.centre_cam[2], 0.0, -fit.centre_cam[0]],
                      [-fit.centre_cam[1], fit.centre_cam[0], 0.0]])
    j_att = rot @ (-cross)
    cov_los = tangent_icrf.T @ fit.cov[:2, :2] @ tangent_icrf + j_att @ cov_att @ j_att.T
    # a unit vector has no variance along itself; keep the record's covariance positive definite
    cov_los = cov_los + np.outer(c_icrf, c_icrf) * max(float(np.trace(cov_los)), 1e-30) * 1e-6
    records = [Measurement(t_tdb_s=t, kind="los", value=c_icrf, covariance=cov_los, target=name,
                           sensor=options.sensor, frame_id=frame_id)]
    if star_rows is not None:
        radius_km = max(body.radii_km) if name != "earth" else RADIUS_KM["earth"]
        altitude = float(options.limb_altitude_km.get(name, 0.0))
        altitude_sigma = float(options.limb_altitude_sigma_km.get(name, 0.0))
        for _, star_icrf, star_astrometric, star_id in zip(*star_rows):
            sl = starlight_measurements(fit, R_icrf_cam, cov_att, star_icrf, body_radius_km=radius_km, limb_altitude_km=altitude,
                                        limb_altitude_sigma_km=altitude_sigma, v_observer_km_s=v_observer_km_s)
            # one vector record: angle and elevation share the limb-centre and attitude errors
            records.append(Measurement(t_tdb_s=t, kind="starlight", value=[sl.angle_rad, sl.elevation_rad],
                                       covariance=sl.covariance, target=name, sensor=options.sensor,
                                       star_id=int(star_id), star_unit_icrf=star_astrometric, frame_id=frame_id))
    return records


def frame_paths(frames_dir: str | Path) -> list[Path]:
    """FITS frames in ``frames_dir``, sorted by name; ``InputError`` if none."""
    frames_dir = Path(frames_dir)
    if not frames_dir.is_dir():
        raise InputError(f"frames directory not found: {frames_dir}")
    paths = sorted(p for p in frames_dir.iterdir() if p.name.lower().endswith(FRAME_SUFFIXES))
    if not paths:
        raise InputError(f"no FITS frames in {frames_dir}")
    return paths


def process_directory(
    frames_dir: str | Path,
    out_csv: str | Path,
    *,
    camera: Camera | None = None,
    catalog=None,
    ephemeris=None,
    options: PipelineOptions = PipelineOptions(),
    rng: np.random.Generator | int | None = None,
    progress: bool = False,
    camera_covariance=None,
    camera_error: str = "white",
) -> list[FrameResult]:
    """Process every frame of a directory and write all records to ``out_csv`` (+ ``.json``).

    A frame that cannot be used (corrupt, blank, saturated) is logged and listed in the
    metadata file under ``skipped``; the others still produce records. Two moons measured in one
    frame are written as one ``radec_pair`` record with the cross-covariance of the attitude they
    share (:func:`opnav.records.join_frame_radec`), which a filter reading the file then keeps.
    ``camera_covariance`` and ``camera_error`` go to :func:`process_frame`.
    """
    from tqdm import tqdm

    rng = np.random.default_rng(rng)
    results, skipped = [], {}
    for path in tqdm(frame_paths(frames_dir), desc="frames", unit="frame", disable=not progress):
        try:
            results.append(process_frame(path, camera=camera, catalog=catalog, ephemeris=ephemeris, options=options,
                                         rng=rng, camera_covariance=camera_covariance, camera_error=camera_error))
        except OpnavError as exc:
            log.warning("skipping %s: %s", path, exc)
            skipped[path.name] = str(exc)
    records = join_frame_radec([rec for res in results for rec in res.records])
    write_csv(out_csv, records, metadata={
        "frames": len(results), "skipped": skipped, "targets": list(options.targets), "sensor": options.sensor,
        "frame_flags": {res.frame_id: list(res.flags) for res in results if res.flags},
        # how the camera's calibration covariance reached the moon records (none: the camera taken as exact)
        "camera_error": None if camera_covariance is None else camera_error,
    })
    return results
