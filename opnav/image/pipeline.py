"""Frame -> time-tagged measurements: the image stage end to end.

For each frame (FITS with the opnav header, :mod:`opnav.render.frames_io`):

1. Read it (:func:`opnav.image.io.read_image`); the epoch is ``TDB_S`` (else
   ``DATE-AVG`` in UTC); the a-priori attitude and a pinhole camera come from
   the WCS unless a :class:`~opnav.camera.Camera` is given; detector gain, read
   noise, bias and saturation from ``GAIN``, ``RDNOISE``, ``BIASLVL``,
   ``SATURATE``; the a-priori observer state from ``OBS_X`` ... ``OBS_VZ``.
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
   directions, :func:`_identify_attitude`); without a catalog, or when
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
A saturated Mars bleeds charge up and down its columns (blooming) and its PSF halo
spreads a few PSF widths beyond the limb; both join a nearby moon to Mars' connected
component, so :func:`~opnav.image.detect.detect` gives it no point seed, and a moon in a
bloomed column is physically lost. When no clean point source is found near the
prediction, :func:`_local_moon_fit` searches ``association_radius_px`` around it for a
PSF-shaped local maximum of the frame with the *blocked* pixels left out:

- pixels within 5 read-noise sigmas of saturation (read noise is added after the
  clipping, so half of a bloomed column reads just below ``SATURATE``), grown by one
  pixel along the column (the partly filled end of a bloom run);
- the primary's disk and halo: pixels closer to its centre than ``R + sigma_psf z``,
  where ``z`` makes the halo of a uniform disk of the predicted surface brightness
  ``S`` (e-/px) fall to one read-noise sigma, ``S Q(z) = read_noise``, plus
  ``HALO_MARGIN_PX`` for the error of the predicted disk centre.

Each candidate is fitted with a Gaussian PSF of the stars' width over a plane
(:func:`opnav.image.targets.fit_point_source`) and kept only if at least
``min_psf_fraction`` of its PSF lies on usable pixels (judged at the predicted position when
the fit is within a pixel of it: a gate on the fitted centre is a selection on the noise that
keeps the fits pushed away from the primary and drops those pushed toward it, a bias of ~0.3
sigma radial from Mars on the kept records near the gate) and the fit's chi-square is
acceptable (p >= 0.001; the covariance is scaled by the reduced chi-square above 1).
Pixels the detector rejected as cosmic-ray hits or hot pixels seed no candidate, but the fit
takes back those its model explains (``suspect``): a rejection test that fails on bright noise
more often than on faint, as it can on the primary's slope, would otherwise take upward
fluctuations away from one side of the moon (``tests/image/test_fit_suspect_pixels.py``). In
the S1 July arc this changes 20 of 41,600 records: such rejections inside the fit are rare.
Otherwise no record is written: the frame is flagged ``no_<moon>`` and, when the
prediction lies on blocked pixels, ``<moon>_hidden``, with the reason logged.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from astropy.wcs import WCS
from scipy import ndimage
from scipy.spatial.transform import Rotation
from scipy.special import ndtri

from ..camera import Camera
from ..constants import C_KM_S, RADIUS_KM
from ..epochs import parse_epoch
from ..errors import FrameError, InputError, NoSolutionError, OpnavError
from ..frames import radec_to_unit
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
from .centroid import CentroidResult, centroid, chi2_sf, psf_like
from .io import read_image
from .targets import fit_limb, fit_point_source, limb_points, moon_direction, psf_fraction, starlight_measurements

log = logging.getLogger(__name__)

FRAME_SUFFIXES = (".fits", ".fit", ".fts")
RESOLVED_BODIES = ("mars", "earth")
#: Margin added to the primary's masked disk + halo for the error of its predicted position, px.
HALO_MARGIN_PX = 2.0


class MoonHiddenError(NoSolutionError):
    """The moon's predicted position lies on saturated, bloomed or halo pixels of its primary."""


@dataclass(frozen=True)
class _MoonContext:
    """What the local moon fit needs from the frame (module section "Moons next to a saturated primary")."""

    image: np.ndarray
    background: np.ndarray
    noise: np.ndarray
    blocked: np.ndarray
    invalid: np.ndarray
    rejected: np.ndarray
    psf_sigma_px: float | None
    read_noise_e: float
    gain: float
    bias_adu: float
    exposure_s: float
    primary: object | None


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
    when it is significant (:mod:`opnav.image.centroid`, "Frame-wide background gradient").
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

    def __post_init__(self) -> None:
        if self.window_px < 3 or self.window_px % 2 == 0:
            raise InputError(f"PipelineOptions.window_px must be odd and >= 3, got {self.window_px}")
        if not 0.0 < self.min_psf_fraction <= 1.0:
            raise InputError(f"PipelineOptions.min_psf_fraction must be in (0, 1], got {self.min_psf_fraction!r}")
        if self.local_window_px < 5 or self.local_window_px % 2 == 0:
            raise InputError(f"PipelineOptions.local_window_px must be odd and >= 5, got {self.local_window_px}")
        for name in ("prior_sigma_rad", "association_radius_px", "min_snr"):
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


def header_epoch(header, path: str) -> float:
    """Mid-exposure epoch (TDB s past J2000) from ``TDB_S`` or ``DATE-AVG``/``DATE-OBS``+``EXPTIME``."""
    if "TDB_S" in header:
        return float(header["TDB_S"])
    if "DATE-AVG" in header:
        return float(parse_epoch(str(header["DATE-AVG"]), header.get("TIMESYS", "utc").lower()))
    if "DATE-OBS" in header:
        start = float(parse_epoch(str(header["DATE-OBS"]), header.get("TIMESYS", "utc").lower()))
        return start + 0.5 * float(header.get("EXPTIME", 0.0))
    raise FrameError(f"{path}: no epoch in the header (TDB_S, DATE-AVG or DATE-OBS)")


def wcs_attitude(header, path: str) -> tuple[Rotation, float, tuple[float, float]]:
    """A-priori attitude (camera -> ICRF), focal length (px) and principal point from a TAN WCS.

    At the reference pixel the TAN projection's tangent plane holds the camera's x and y axes:
    column j of CD gives d(east, north)/d(pixel j) in degrees.
    """
    try:
        wcs = WCS(header, relax=True, naxis=2)
        cd = wcs.wcs.cd if wcs.wcs.has_cd() else wcs.wcs.get_pc() * wcs.wcs.cdelt[:, None]
        ra0, dec0 = (math.radians(v) for v in wcs.wcs.crval)
        crpix = wcs.wcs.crpix
    except Exception as exc:  # noqa: BLE001 - astropy raises several types for bad WCS keywords
        raise FrameError(f"{path}: no usable WCS in the header ({exc})") from None
    if not np.all(np.isfinite(cd)) or abs(np.linalg.det(cd)) == 0.0:
        raise FrameError(f"{path}: the WCS has no valid CD matrix")
    east = np.array([-math.sin(ra0), math.cos(ra0), 0.0])
    north = np.array([-math.sin(dec0) * math.cos(ra0), -math.sin(dec0) * math.sin(ra0), math.cos(dec0)])
    boresight = radec_to_unit(ra0, dec0)
    axis_x = cd[0, 0] * east + cd[1, 0] * north
    axis_y = cd[0, 1] * east + cd[1, 1] * north
    scale_rad = math.radians(math.sqrt(abs(np.linalg.det(cd))))
    u, _, vt = np.linalg.svd(np.column_stack([axis_x / np.linalg.norm(axis_x), axis_y / np.linalg.norm(axis_y), boresight]))
    matrix = u @ vt
    if np.linalg.det(matrix) < 0:
        raise FrameError(f"{path}: the WCS is mirrored; the camera frame must be right-handed")
    return Rotation.from_matrix(matrix), 1.0 / scale_rad, (float(crpix[0] - 1.0), float(crpix[1] - 1.0))


def camera_from_header(header, shape: tuple[int, int], path: str) -> Camera:
    """A pinhole camera matching the WCS (distortion-free) and the detector keywords."""
    _, f_px, (cx, cy) = wcs_attitude(header, path)
    pitch_um = 10.0
    return Camera(
        width_px=shape[1], height_px=shape[0], focal_length_mm=f_px * pitch_um / 1000.0, pixel_pitch_um=pitch_um,
        cx_px=cx, cy_px=cy, gain_e_per_adu=float(header.get("GAIN", 1.0)),
        read_noise_e=float(header.get("RDNOISE", 5.0)), bias_adu=float(header.get("BIASLVL", 0.0)),
        exposure_s=float(header.get("EXPTIME", 1.0)) or 1.0, camera_id=str(header.get("CAMERA", "opnav-cam")),
    )


def _observer(header, t: float, path: str):
    from ..observer import Observer

    try:
        r = np.array([float(header[f"OBS_{a}"]) for a in "XYZ"])
        v = np.array([float(header[f"OBS_V{a}"]) for a in "XYZ"])
    except (KeyError, ValueError) as exc:
        raise FrameError(f"{path}: bad observer state in the header ({exc})") from None
    return Observer(t, r, v)


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
    """
    from .attitude import wahba_gated
    from .starid import CatalogTree, bearings, track

    rows = np.flatnonzero(usable)
    if rows.size < 3:  # as track() says, before a median of nothing
        raise NoSolutionError(f"tracking needs at least 3 stars, got {rows.size}")
    sigma_px = np.sqrt(sources.cov[rows][:, [0, 1], [0, 1]].mean(axis=1))
    b_cam = bearings(sources.xy[rows], camera)
    ident = track(
        b_cam, CatalogTree.from_catalog(catalog, vmag_limit=options.vmag_limit), R_prior, camera,
        prior_sigma_rad=options.prior_sigma_rad, sigma_rad=float(np.median(sigma_px)) * camera.pixel_scale_rad, rng=rng,
    )
    image_rows, cat_rows = ident.pairs[:, 0], ident.pairs[:, 1]
    v_icrf = astrometric = ident.v_icrf
    if observer is not None:
        state = dict(t_tdb_s=observer.t_tdb_s, r_observer_ssb_km=observer.r_ssb_km,
                     v_observer_ssb_km_s=observer.v_ssb_km_s)
        v_icrf = catalog.apparent_directions(cat_rows, **state)
        astrometric = catalog.apparent_directions(cat_rows, **state, aberration=False)
    # gated: an unresolved double or a star on a bright wing would otherwise bias the attitude
    solution, kept = wahba_gated(b_cam[image_rows], v_icrf, sigma_rad=sigma_px[image_rows] * camera.pixel_scale_rad)
    if not kept.all():
        log.info("attitude fit dropped %d of %d matched stars as outliers", (~kept).sum(), kept.size)
    return solution.R_icrf_cam, solution.cov_rad2, (rows[image_rows][kept], v_icrf[kept], astrometric[kept],
                                                    catalog.star_id[cat_rows][kept])


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
    observer = _observer(header, t, str(path)) if "OBS_X" in header else None
    return FrameInput(
        image=image, camera=camera, t_tdb_s=t, R_prior=R_prior, observer=observer,
        read_noise_e=float(header.get("RDNOISE", camera.read_noise_e)),
        gain_e_per_adu=float(header.get("GAIN", camera.gain_e_per_adu)),
        bias_adu=float(header.get("BIASLVL", camera.bias_adu)),
        exposure_s=float(header.get("EXPTIME", camera.exposure_s)) or camera.exposure_s,
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

    Returns
    -------
    FrameResult
    """
    frame = frame_input(path, camera)
    return measure_frame(frame, catalog=catalog, ephemeris=ephemeris, options=options, rng=rng, source=str(path))


@dataclass(frozen=True)
class _Sources:
    """Detections and centroids of a frame (or of a crop of it)."""

    det: detect_mod.Detections
    sources: CentroidResult
    ok: np.ndarray
    invalid: np.ndarray | None


def _measure_sources(frame: FrameInput, options: PipelineOptions, near: tuple[np.ndarray, float] | None = None,
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


def _claim_moons(views: dict, found: _Sources, options: PipelineOptions) -> np.ndarray:
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


def _target_records(frame: FrameInput, views: dict, found: _Sources, claimed: np.ndarray, R_icrf_cam: Rotation,
                    cov_att: np.ndarray, star_rows, ephemeris, options: PipelineOptions, rng, source: str,
                    flags: list[str], psf_sigma_px: float | None = None, primary_view=None) -> list[Measurement]:
    """Records of every target (moons: RA/Dec; resolved bodies: limb and starlight); misses go to ``flags``.

    ``psf_sigma_px``: the stars' PSF width when known from elsewhere (a crop has too few stars);
    ``primary_view``: the moons' primary as this frame sees it, when already predicted.
    """
    moon_ctx = None
    if any(name not in RESOLVED_BODIES for name in views):
        moon_ctx = _moon_context(frame, found, views, ephemeris, psf_sigma_px, primary_view)
    records: list[Measurement] = []
    for name, (body, view) in views.items():
        try:
            if name in RESOLVED_BODIES:
                records += limb_records(name, body, frame.image, frame.camera, view.xy_cof_px,
                                        view.angular_radius_rad * frame.camera.focal_length_px, R_icrf_cam, cov_att,
                                        star_rows, frame.t_tdb_s, frame.frame_id, options, rng,
                                        v_observer_km_s=None if frame.observer is None else frame.observer.v_ssb_km_s)
            else:
                records += _moon_records(name, body, view, found.sources, found.det, claimed, frame.camera, R_icrf_cam,
                                         cov_att, ephemeris, frame.t_tdb_s, frame.frame_id, options, moon_ctx)
        except (NoSolutionError, FrameError) as exc:
            log.warning("%s: no measurement of %s (%s)", source, name, exc)
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
    found = _measure_sources(frame, options)
    views = _target_views(frame, ephemeris, options, source)
    claimed = _claim_moons(views, found, options)
    R_icrf_cam, cov_att, matched, star_rows = frame.R_prior, np.eye(3) * options.prior_sigma_rad**2, 0, None
    if catalog is not None:
        usable = found.ok & ~claimed & ((found.det.flags & (detect_mod.FLAG_SATURATED | detect_mod.FLAG_BLENDED)) == 0)
        try:
            R_icrf_cam, cov_att, star_rows = _identify_attitude(found.sources, usable, frame.camera, catalog, frame.R_prior,
                                                                frame.observer, options, rng)
            matched = len(star_rows[0])
        except (NoSolutionError, InputError) as exc:
            log.warning("%s: star identification failed (%s); using the a-priori attitude", source, exc)
            flags.append("attitude_prior")
    else:
        flags.append("attitude_prior")
    records = _target_records(frame, views, found, claimed, R_icrf_cam, cov_att, star_rows, ephemeris, options, rng,
                              source, flags)
    return FrameResult(frame.frame_id, frame.t_tdb_s, tuple(records), found.sources, found.det, R_icrf_cam, cov_att,
                       matched, tuple(flags))


def _moon_context(frame: FrameInput, found: _Sources, views: dict, ephemeris,
                  psf_sigma_px: float | None = None, primary_view=None) -> _MoonContext:
    """Blocked pixels, the stars' PSF width and the moons' primary for :func:`_local_moon_fit`."""
    from ..bodies import body_model, view_body

    image, det, sources = frame.image, found.det, found.sources
    blocked = np.zeros(image.shape, bool)
    if frame.saturation_adu is not None:
        near_full = image >= frame.saturation_adu - 5.0 * frame.read_noise_e / frame.gain_e_per_adu
        blocked |= ndimage.binary_dilation(near_full, structure=np.ones((3, 1), bool))
    stars = found.ok & ((det.flags & (detect_mod.FLAG_SATURATED | detect_mod.FLAG_BLENDED | detect_mod.FLAG_EDGE)) == 0)
    stars &= sources.snr > 20.0
    psf_sigma = psf_sigma_px
    if psf_sigma is None and stars.sum() >= 3:
        psf_sigma = float(np.median(sources.sigma_px[stars]))
    primaries = {body.primary for name, (body, _) in views.items() if name not in RESOLVED_BODIES}
    primary = primary_view
    if primary is None and len(primaries) == 1:
        name = primaries.pop()
        primary = views[name][1] if name in views else view_body(body_model(name), frame.camera, frame.R_prior,
                                                                 frame.observer, ephemeris, supersample=1,
                                                                 keep_rays=False)
    invalid = frame.invalid
    return _MoonContext(image=image, background=det.background.level, noise=det.background.noise, blocked=blocked,
                        invalid=np.zeros(image.shape, bool) if invalid is None else np.asarray(invalid, bool),
                        rejected=np.asarray(det.rejected, bool),
                        psf_sigma_px=psf_sigma, read_noise_e=frame.read_noise_e, gain=frame.gain_e_per_adu,
                        bias_adu=frame.bias_adu, exposure_s=frame.exposure_s, primary=primary)


def _halo_mask(ctx: _MoonContext, camera, shape_rc: tuple[slice, slice]) -> np.ndarray:
    """Pixels of ``image[shape_rc]`` on the primary's predicted disk or halo (module docstring)."""
    rows, cols = shape_rc
    yy, xx = np.mgrid[rows, cols]
    if ctx.primary is None:
        return np.zeros(yy.shape, bool)
    radius = ctx.primary.angular_radius_rad * camera.focal_length_px
    if radius < 1.0:
        return np.zeros(yy.shape, bool)
    surface_e = ctx.primary.electrons_s * ctx.exposure_s / (math.pi * radius**2)
    sigma = ctx.psf_sigma_px if ctx.psf_sigma_px is not None else 1.0
    # -ndtri(q) is scipy.stats.norm.isf(q) for q in (0, 1), without its ~70 us a call
    z = float(-ndtri(max(ctx.read_noise_e, 1.0) / surface_e)) if surface_e > max(ctx.read_noise_e, 1.0) else 0.0
    centre = ctx.primary.xy_cof_px
    return np.hypot(xx - centre[0], yy - centre[1]) < radius + sigma * max(z, 0.0) + HALO_MARGIN_PX


def _local_moon_fit(name, view, camera, ctx: _MoonContext, options):
    """Search around the prediction for the moon with blocked pixels left out (module docstring).

    Returns the accepted :class:`~opnav.image.targets.PointFit`; raises ``MoonHiddenError`` when
    the prediction is on blocked pixels and nothing usable is found, ``NoSolutionError`` otherwise.
    """
    if ctx.psf_sigma_px is None:
        raise NoSolutionError(f"no point source near the predicted {name} and too few stars to know the PSF")
    h, w = ctx.image.shape
    pred = np.asarray(view.xy_photocentre_px, float)
    r = options.association_radius_px
    half = options.local_window_px // 2
    r0, r1 = max(int(pred[1] - r) - half, 0), min(int(pred[1] + r) + half + 2, h)
    c0, c1 = max(int(pred[0] - r) - half, 0), min(int(pred[0] + r) + half + 2, w)
    box = (slice(r0, r1), slice(c0, c1))
    fittable = ~(ctx.blocked[box] | ctx.invalid[box] | _halo_mask(ctx, camera, box))
    # cosmic-ray hits and hot pixels seed no peak; the fit judges them itself (``suspect``)
    usable = fittable & ~ctx.rejected[box]
    pi, pj = int(round(pred[1])) - r0, int(round(pred[0])) - c0
    hidden = not (0 <= pi < fittable.shape[0] and 0 <= pj < fittable.shape[1] and fittable[pi, pj])
    resid = np.where(usable, ctx.image[box] - ctx.background[box], 0.0)
    # Normalised convolution: the matched filter over the usable pixels only.
    weight = ndimage.gaussian_filter(usable.astype(float), ctx.psf_sigma_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth = ndimage.gaussian_filter(resid, ctx.psf_sigma_px) / weight
    kernel_norm = 1.0 / (4.0 * math.pi * ctx.psf_sigma_px**2)  # sum of k^2 for a unit Gaussian kernel
    threshold = options.detect.threshold_sigma * ctx.noise[box] * math.sqrt(kernel_norm)
    yy, xx = np.mgrid[box]
    peaks = usable & (weight > 0.3) & (smooth > threshold) & (np.hypot(xx - pred[0], yy - pred[1]) < r)
    peaks &= smooth == ndimage.maximum_filter(np.where(usable, smooth, -np.inf), size=3)
    rows, cols = np.nonzero(peaks)
    order = np.argsort(-smooth[rows, cols])[:5]
    reason = "no PSF-shaped source on its usable pixels"
    best, best_dist = None, np.inf
    full_usable = ~(ctx.blocked | ctx.invalid)
    full_usable[box] &= fittable
    # Enough of the PSF on usable pixels is judged at the prediction, which the moon's own noise
    # does not move: a gate on the fitted centre would keep the fits the noise pushed off the
    # blocked pixels and drop those it pushed onto them, biasing the kept ones away from the primary.
    predicted_fraction = psf_fraction(full_usable, pred, ctx.psf_sigma_px, options.local_window_px)
    for i, j in zip(rows[order], cols[order]):
        xy0 = np.array([xx[i, j], yy[i, j]], float)
        try:
            fit = fit_point_source(ctx.image, xy0, usable=full_usable, psf_sigma_px=ctx.psf_sigma_px,
                                   read_noise_e=ctx.read_noise_e, gain_e_per_adu=ctx.gain, bias_adu=ctx.bias_adu,
                                   window=options.local_window_px, suspect=ctx.rejected)
        except NoSolutionError as exc:
            reason = str(exc)
            continue
        # the prediction stands for the moon when the fit lands within a pixel of it (the usual
        # case: the fit's noise is hundredths of a pixel); a fit farther off is judged where it is
        fraction = predicted_fraction if np.hypot(*(fit.xy - pred)) <= 1.0 else fit.psf_fraction
        if fraction < options.min_psf_fraction:
            reason = f"only {100 * fraction:.0f}% of its PSF on usable pixels"
            continue
        if chi2_sf(fit.chi2, fit.dof) < 1e-3:
            reason = f"PSF + plane fit rejected (chi2 {fit.chi2:.0f} for {fit.dof} dof)"
            continue
        if fit.snr < options.detect.threshold_sigma or np.hypot(*(fit.xy - xy0)) > 1.5:
            reason = "fit drifted from its peak or too faint"
            continue
        dist = float(np.hypot(*(fit.xy - pred)))
        if dist < min(best_dist, r):
            best, best_dist = fit, dist
    if best is not None:
        return best
    where = f"within {r} px of the predicted {name}"
    if hidden:
        raise MoonHiddenError(f"{name} predicted on saturated, bloomed or halo pixels; nothing measurable {where} ({reason})")
    raise NoSolutionError(f"no usable source {where} ({reason})")


def _moon_records(name, body, view, sources, det, claimed, camera, R_icrf_cam, cov_att, ephemeris, t, frame_id, options,
                  ctx: _MoonContext | None = None):
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
            local = _local_moon_fit(name, view, camera, ctx, options)
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
    progress: bool = True,
) -> list[FrameResult]:
    """Process every frame of a directory and write all records to ``out_csv`` (+ ``.json``).

    A frame that cannot be used (corrupt, blank, saturated) is logged and listed in the
    metadata file under ``skipped``; the others still produce records. Two moons measured in one
    frame are written as one ``radec_pair`` record with the cross-covariance of the attitude they
    share (:func:`opnav.records.join_frame_radec`), which a filter reading the file then keeps.
    """
    from tqdm import tqdm

    rng = np.random.default_rng(rng)
    results, skipped = [], {}
    for path in tqdm(frame_paths(frames_dir), desc="frames", unit="frame", disable=not progress):
        try:
            results.append(process_frame(path, camera=camera, catalog=catalog, ephemeris=ephemeris, options=options, rng=rng))
        except OpnavError as exc:
            log.warning("skipping %s: %s", path, exc)
            skipped[path.name] = str(exc)
    records = join_frame_radec([rec for res in results for rec in res.records])
    write_csv(out_csv, records, metadata={
        "frames": len(results), "skipped": skipped, "targets": list(options.targets), "sensor": options.sensor,
        "frame_flags": {res.frame_id: list(res.flags) for res in results if res.flags},
    })
    return results
