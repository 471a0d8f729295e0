"""The image stages a sensor of the loop (:mod:`opnav.sim.loop`) measures its frames with, and the
predictions they need before a frame is rendered.

- :class:`FullFrame`: every frame detected, identified and measured from scratch
  (:func:`opnav.image.pipeline.measure_frame`);
- :class:`Tracking`: a full-frame acquisition, then stars and targets measured in windows around
  their predictions (:class:`opnav.image.tracking.Tracker`); the loop renders only those windows
  while the tracker holds lock. A run whose frames star identification should solve but does
  not (:func:`identifiable`) stops after ``max_unidentified_frames`` of them: the frames do not
  match the catalog through the camera model;
- :class:`Limb`: a body's limb fitted in the annulus where another sensor's attitude solution
  predicts it (:func:`predicted_limb`, :func:`limb_window`), and the starlight angle and elevation
  of the frame's navigation star against it (:func:`opnav.image.pipeline.limb_records`);
- :class:`Centre`: a resolved body's centre (:func:`opnav.image.centres.measure_body_centre`: limb
  ellipsoid fit or cross-correlation by size and phase) with another sensor's attitude solution,
  for a frame exposed for the body, in which no star shows (S2's Mars frames).

Vectors: ICRF; observer states relative to the SSB, km and km/s; pixels x = column, y = row,
pixel centres at integers (docs/conventions.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ..bodies import Body
from ..camera import Camera
from ..errors import InputError
from ..image.centres import CentreOptions
from ..image.pipeline import PipelineOptions
from ..image.tracking import TrackingOptions

#: Frames that should have been identified (enough catalog stars predicted and point sources
#: detected) but were not, from a chunk's start before any lock, that stop the run.
MAX_UNIDENTIFIED_FRAMES = 60
#: Catalog stars predicted clear of targets, edges and saturated pixels, and point sources
#: detected, that make a frame one star identification should solve.
IDENTIFIABLE_STARS = 4
#: A predicted star within this many px of a saturated pixel (a planet's disk or bloom trail)
#: cannot be measured, so it does not count towards :data:`IDENTIFIABLE_STARS`.
SATURATION_CLEARANCE_PX = 3


@dataclass(frozen=True)
class FullFrame:
    """Every frame measured from scratch with ``options`` (targets, magnitude limit, ...)."""

    options: PipelineOptions = field(default_factory=PipelineOptions)


@dataclass(frozen=True)
class Tracking:
    """Full-frame acquisition, then tracking (module notes).

    Attributes
    ----------
    options : PipelineOptions
        The image stage's settings (its ``targets`` are the bodies measured).
    tracking : TrackingOptions
    max_unidentified_frames : int
        Frames star identification should have solved (:func:`identifiable`) and did not, before
        the first lock of a chunk, that stop the run with ``NoSolutionError``.
    """

    options: PipelineOptions = field(default_factory=PipelineOptions)
    tracking: TrackingOptions = field(default_factory=TrackingOptions)
    max_unidentified_frames: int = MAX_UNIDENTIFIED_FRAMES

    def __post_init__(self) -> None:
        if int(self.max_unidentified_frames) != self.max_unidentified_frames or self.max_unidentified_frames < 1:
            raise InputError("max_unidentified_frames must be a positive integer, got "
                             f"{self.max_unidentified_frames!r}")


@dataclass(frozen=True, eq=False)
class Limb:
    """A body's limb and the navigation star's starlight angle and elevation against it.

    The sensor's attitude is sensor ``reference``'s solution on the same frame turned through the
    two mountings (both sensors fixed on one body); its frame is rendered only in the annulus the
    limb fit reads around the limb that attitude predicts.

    Attributes
    ----------
    options : PipelineOptions
        ``limb_altitude_km`` / ``limb_altitude_sigma_km`` of ``body`` and the records' ``sensor``.
    reference : int
        Index of the sensor (in the loop's sensor list, before this one) whose attitude is used.
    stars : (N,) int array
        Catalog row of the navigation star at each frame index of the arc (-1: none, no record).
    band_px : float
        The limb is searched within this of its prediction, px.
    reach_px : float
        The body is rendered within this of the predicted limb, px (the band, the PSF and slack).
    altitude_km : float
        Altitude of the visible limb above the body's radius, km (where the limb is predicted).
    body : str
    kinds : tuple of str
        Record kinds kept (``limb_records`` also gives the centre's ``los``).
    """

    options: PipelineOptions
    reference: int
    stars: np.ndarray
    band_px: float
    reach_px: float
    altitude_km: float
    body: str = "earth"
    kinds: tuple[str, ...] = ("starlight",)

    def __post_init__(self) -> None:
        for name in ("band_px", "reach_px"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) > 0.0):
                raise InputError(f"Limb.{name} must be positive, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class Centre:
    """A resolved body's centre measured with the attitude of another sensor on the same body.

    The frame is exposed for the body (its stars are too faint to identify); its attitude is sensor
    ``reference``'s solution on the same frame index turned through the two mountings, with that
    solution's covariance; the centre is found by :func:`opnav.image.centres.measure_body_centre`
    with the camera's known PSF width. Records: the centre's ``radec`` (and, from a limb fit, the
    ``target_vector``) whose covariance carries the reference's attitude error.

    Attributes
    ----------
    body : str
        The body measured (the frame shows the sensor's ``targets``).
    reference : int
        Index of the sensor (in the loop's sensor list, before this one) whose attitude is used.
    psf_sigma_px : float
        The camera's PSF width (Gaussian sigma, px): the body model's blur.
    sensor : str
        The records' ``sensor``.
    centre_options : CentreOptions
        The method chooser's settings.
    kinds : tuple of str
        Record kinds kept.
    model : Body, optional
        The body's shape and reflectance the fit assumes (None: :func:`opnav.bodies.body_model` of ``body``).
    """

    body: str
    reference: int
    psf_sigma_px: float
    sensor: str = "camera"
    centre_options: CentreOptions = field(default_factory=CentreOptions)
    kinds: tuple[str, ...] = ("radec",)
    model: Body | None = None

    def __post_init__(self) -> None:
        if not (np.isfinite(self.psf_sigma_px) and self.psf_sigma_px > 0.0):
            raise InputError(f"Centre.psf_sigma_px must be positive, got {self.psf_sigma_px!r}")


def predicted_limb(camera: Camera, R_icrf_cam: Rotation, observer, ephemeris, limb_altitude_km: float,
                   body: str = "earth") -> tuple[np.ndarray, float, float]:
    """Where ``camera`` at attitude ``R_icrf_cam`` (camera -> ICRF) sees ``body``: centre (x, y) px,
    the visible limb's radius px (``limb_altitude_km`` above the surface) and its angular radius, rad.

    The centre's apparent direction (light time and aberration) from the a-priori ``observer``
    (SSB, ICRF, km and km/s), through ``ephemeris``.
    """
    from ..constants import RADIUS_KM
    from ..light import apparent_direction

    direction = apparent_direction(lambda t: ephemeris.position(body, t), observer.t_tdb_s, observer.r_ssb_km,
                                   observer.v_ssb_km_s)
    distance = float(np.linalg.norm(ephemeris.position(body, observer.t_tdb_s) - observer.r_ssb_km))
    rho = float(np.arcsin((RADIUS_KM[body] + limb_altitude_km) / distance))
    centre = camera.project(R_icrf_cam.inv().apply(direction))
    # one limb point projected: the radius in pixels (the disk is round to 0.1 % near the boresight)
    edge_icrf = Rotation.from_rotvec(rho * _perpendicular(direction)).apply(direction)
    edge = camera.project(R_icrf_cam.inv().apply(edge_icrf))
    return centre, float(np.hypot(*(edge - centre))), rho


def _perpendicular(u: np.ndarray) -> np.ndarray:
    ref = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    w = np.cross(u, ref)
    return w / np.linalg.norm(w)


def limb_window(camera: Camera, centre: np.ndarray, radius_px: float, rho: float, reach_px: float):
    """(band_rad, box) of the annulus the limb fit reads: the body's rays within ``reach_px`` of the
    limb predicted at ``centre`` (px) with radius ``radius_px`` (``rho`` rad), and the box
    ``(x0, y0, x1, y1)`` (inclusive) around it."""
    scale = camera.focal_length_px
    band = (max(rho - reach_px / scale, 0.0), rho + reach_px / scale)
    half = radius_px + reach_px
    box = (int(np.floor(centre[0] - half)), int(np.floor(centre[1] - half)),
           int(np.ceil(centre[0] + half)), int(np.ceil(centre[1] + half)))
    return band, box


def identifiable(frame, result, catalog, ephemeris, options: PipelineOptions, tracking: TrackingOptions) -> bool:
    """Whether star identification should have solved ``frame`` (its full-frame ``result`` has none):
    at least :data:`IDENTIFIABLE_STARS` catalog stars predicted from its a-priori attitude clear of
    the targets, the edges and saturated pixels, and as many point sources detected.

    Saturated pixels count because near Mars its bloom trail runs across the field: a star
    predicted on it is not in the frame, and a frame with three measurable stars (August,
    day 3, Phobos behind Mars) otherwise counted as one identification had failed on, and
    stopped the run after an hour of them."""
    from ..image.detect import FLAG_EXTENDED
    from ..image.tracking import predict_stars_at, views_with_primaries

    if result.detections is None or frame.observer is None:
        return False
    points = int(np.sum((result.detections.flags & FLAG_EXTENDED) == 0))
    if points < IDENTIFIABLE_STARS:
        return False
    views = (views_with_primaries(frame.camera, frame.R_prior, frame.observer, ephemeris, options.targets)
             if options.targets else {})
    predicted = predict_stars_at(frame.camera, frame.t_tdb_s, frame.observer, frame.R_prior, catalog, views, options,
                                 tracking)
    if frame.saturation_adu is None:
        return len(predicted.rows) >= IDENTIFIABLE_STARS
    c = SATURATION_CLEARANCE_PX
    clear = [not np.any(frame.image[max(y - c, 0):y + c + 1, max(x - c, 0):x + c + 1] >= frame.saturation_adu)
             for x, y in np.rint(predicted.xy_px).astype(int)]
    return sum(clear) >= IDENTIFIABLE_STARS
