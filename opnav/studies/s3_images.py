"""S3 from pixels: the star sensor and the UV Earth sensor rendered along the GEO arc and measured in memory.

The spacecraft is Earth-pointing and 3-axis stabilised (:func:`body_attitude`: body z to the
Earth's centre, x ahead along the track, y = z x x). Two sensors are fixed on it
(:func:`sensors`):

- the **star sensor**, boresight where the measurement mode's schedule puts it
  (``boresight_from_nadir_deg``, ``boresight_out_of_plane_deg``), a field of
  2 ``fov_half_deg`` across ``star_sensor_px`` pixels, catalog stars to ``star_vmag_limit``;
- the **UV Earth sensor**, boresight at nadir, ``earth_sensor_fov_deg`` across
  ``earth_sensor_px`` pixels (the renderer's UV Earth: a flat disk with a soft ozone-layer limb).

Each epoch (``step_s``; noise of epoch ``k`` from ``default_rng([seed, 31 or 32, k])``):

1. **Star sensor.** Rendered only in the windows the tracker reads
   (:meth:`opnav.image.tracking.Tracker.read_boxes`, :func:`opnav.render.render_windows`), in
   full at acquisition, and measured by the tracking image stage: an attitude and its
   covariance from the gated Wahba fit of the tracked stars. The frames show stars
   ``SKY_DEPTH_MAG`` fainter than the stage's catalog, so the tracker leaves out guide stars
   with a catalog neighbour (``TrackingOptions.neighbour_depth_mag``): their pull on a guide
   star's centroid lasts its whole crossing of the field (an hour) and the filters would
   average it as if it were white noise.
2. **Earth sensor.** Its attitude is the star sensor's solution times the mounting; from it
   and the a-priori observer state the limb is predicted (centre and the visible limb's radius,
   ``PipelineOptions.limb_altitude_km`` above the surface), and the frame is rendered only in
   the annulus the limb fit reads: the Earth's rays within ``limb_band_px`` (plus the PSF) of
   the predicted limb, one window around it (:func:`opnav.bodies.view_body` ``band_rad``).
   The limb is fitted within ``limb_band_px`` of its prediction
   (:func:`opnav.image.targets.limb_points`, :func:`~opnav.image.targets.fit_limb`).
3. **Record.** The starlight angle and elevation of the scheduled navigation star
   (:func:`opnav.studies.s3.star_schedule`) against the fitted limb
   (:func:`opnav.image.pipeline.limb_records`): one ``starlight`` record whose covariance
   carries the limb fit, the attitude (mapped from the star sensor to the Earth sensor) and the
   limb-altitude model.

An epoch gives no record when the star sensor has no star-identified attitude or the limb fit
fails; each is listed with its reason (``frames_skipped``). The navigation star need not be
one of the guide stars (the angle is its catalog direction against the Earth, through the
attitude the whole field gives); the epochs where it was not are counted. The frames show real light (light time,
stellar and planetary aberration, proper motion, parallax), so the filters' model applies
light time and aberration (``navigation.light_time``/``aberration`` true), where the
measurement mode's truth and model are both the study's geometric one.

The arc goes in chunks of ``chunk_epochs`` (:func:`opnav.studies.image_loop.run_chunks`):
each starts with an acquisition, is written atomically when done and read back by a re-run,
and chunks run in ``workers`` processes with the same records.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..constants import ARCSEC_RAD, DEG_RAD
from ..errors import InputError, OpnavError

#: Epochs per chunk: four hours at the study's 10 s.
CHUNK_EPOCHS = 1440
#: The star sensor's frames show the sky this many magnitudes below the stage's catalog limit ...
SKY_DEPTH_MAG = 1.0
#: ... and the tracker leaves out guide stars with a catalog neighbour this deep (TrackingOptions).
NEIGHBOUR_DEPTH_MAG = 1.5
#: Extra pixels of the Earth's light drawn beyond the limb fit's reach (the prediction rests on the
#: solved attitude and the calibrated limb: the drawn limb is within a small part of a pixel of it).
_BAND_SLACK_PX = 1.5


@dataclass(frozen=True)
class Sensors:
    """The two S3 sensors and their mountings (camera -> body rotations)."""

    star_camera: Camera
    earth_camera: Camera
    body_star: Rotation
    body_earth: Rotation

    @property
    def star_to_earth(self) -> Rotation:
        """Earth-sensor frame -> star-sensor frame."""
        return self.body_star.inv() * self.body_earth


def sensors(settings) -> Sensors:
    """The star sensor and UV Earth sensor of ``settings`` (:class:`opnav.studies.s3.Settings`)."""
    angle = settings.boresight_from_nadir_deg * DEG_RAD
    tilt = settings.boresight_out_of_plane_deg * DEG_RAD
    # body axes: x along the track, y = z x x, z to the Earth; the orbit normal r x v is -y
    boresight = np.cos(tilt) * np.array([np.sin(angle), 0.0, np.cos(angle)]) - np.sin(tilt) * np.array([0.0, 1.0, 0.0])
    ref = np.array([0.0, 1.0, 0.0]) if abs(boresight[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = ref - (ref @ boresight) * boresight
    x /= np.linalg.norm(x)
    body_star = Rotation.from_matrix(np.column_stack([x, np.cross(boresight, x), boresight]))
    star_camera = Camera.from_fov(2.0 * settings.fov_half_deg, settings.star_sensor_px, settings.star_sensor_px,
                                  aperture_mm=settings.star_sensor_aperture_mm,
                                  exposure_s=settings.star_sensor_exposure_s, camera_id="s3-star-sensor")
    earth_camera = Camera.from_fov(settings.earth_sensor_fov_deg, settings.earth_sensor_px, settings.earth_sensor_px,
                                   camera_id="s3-uv-earth-sensor")
    return Sensors(star_camera, earth_camera, body_star, Rotation.identity())


def body_attitude(state: np.ndarray) -> Rotation:
    """Earth-pointing body frame -> ICRF for an Earth-centred ICRF state [r km, v km/s] (module notes)."""
    r = np.asarray(state[:3], float)
    v = np.asarray(state[3:6], float)
    z = -r / np.linalg.norm(r)
    x = v - (v @ z) * z
    x /= np.linalg.norm(x)
    return Rotation.from_matrix(np.column_stack([x, np.cross(z, x), z]))


def predicted_limb(camera: Camera, R_icrf_cam: Rotation, observer, ephemeris, limb_altitude_km: float
                   ) -> tuple[np.ndarray, float, float]:
    """Where ``camera`` at attitude ``R_icrf_cam`` sees the Earth: centre (x, y) px, the visible
    limb's radius px (``limb_altitude_km`` above the surface) and its angular radius, rad.

    The centre's apparent direction (light time and aberration) from the a-priori ``observer``
    (SSB, ICRF, km and km/s), through ``ephemeris``.
    """
    from ..constants import RADIUS_KM
    from ..light import apparent_direction

    direction = apparent_direction(lambda t: ephemeris.position("earth", t), observer.t_tdb_s, observer.r_ssb_km,
                                   observer.v_ssb_km_s)
    distance = float(np.linalg.norm(ephemeris.position("earth", observer.t_tdb_s) - observer.r_ssb_km))
    rho = float(np.arcsin((RADIUS_KM["earth"] + limb_altitude_km) / distance))
    centre = camera.project(R_icrf_cam.inv().apply(direction))
    # one limb point projected: the radius in pixels (the disk is round to 0.1 % near the boresight)
    edge = camera.project(R_icrf_cam.inv().apply(Rotation.from_rotvec(rho * _perpendicular(direction)).apply(direction)))
    return centre, float(np.hypot(*(edge - centre))), rho


def _perpendicular(u: np.ndarray) -> np.ndarray:
    ref = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    w = np.cross(u, ref)
    return w / np.linalg.norm(w)


@dataclass(frozen=True)
class _Chunk:
    """One chunk's epochs and everything its worker needs (picklable)."""

    settings: object
    seed: int
    first: int
    epochs: np.ndarray
    states: np.ndarray
    stars: np.ndarray
    stem: Path
    key: str
    limb_altitude_km: float


def stream_s3(settings, seed: int, epochs: np.ndarray, states: np.ndarray, stars: np.ndarray, out: Path, *, key: str,
              limb_altitude_km: float, workers: int = 1, progress: bool = True) -> tuple[list, dict]:
    """Render and measure every epoch (module notes): (starlight records, book-keeping merged over chunks).

    ``states``: true Earth-centred ICRF states (N, 6) km, km/s at ``epochs`` (TDB s); ``stars``:
    catalog row of the navigation star per epoch (-1: none); ``limb_altitude_km``: the Earth
    sensor's visible-limb altitude (:func:`calibrate_limb_altitude`).
    """
    from .image_loop import run_chunks

    folder = Path(out) / "stream"
    chunks = [_Chunk(settings, seed, start, epochs[start:start + CHUNK_EPOCHS], states[start:start + CHUNK_EPOCHS],
                     stars[start:start + CHUNK_EPOCHS], folder / f"s3_chunk_{start // CHUNK_EPOCHS:05d}",
                     f"{key}:{start}:{min(start + CHUNK_EPOCHS, len(epochs))}:{limb_altitude_km!r}", limb_altitude_km)
              for start in range(0, len(epochs), CHUNK_EPOCHS)]
    finished, reused = run_chunks(chunks, _run_chunk, workers=workers, progress=progress, unit="epoch")
    records, book = [], {"skipped": {}, "events": [], "windowed": 0, "full": 0, "stars_used": 0,
                         "stars_misidentified": 0, "navigation_star_not_tracked": 0, "chunks_reused": reused}
    for chunk_records, chunk_book in finished:
        records += chunk_records
        book["skipped"].update(chunk_book["skipped"])
        book["events"] += chunk_book["events"]
        for name in ("windowed", "full", "stars_used", "stars_misidentified", "navigation_star_not_tracked"):
            book[name] += chunk_book[name]
    return records, book


def stage_options(settings, limb_altitude_km: float = 48.0):
    """The image stage's settings: the star sensor's catalog stars to ``star_vmag_limit``, the Earth
    sensor's visible limb at ``limb_altitude_km`` with ``settings.limb_altitude_sigma_km``."""
    from ..image.pipeline import PipelineOptions

    return PipelineOptions(vmag_limit=settings.star_vmag_limit, sensor="s3",
                           limb_altitude_km={"earth": limb_altitude_km},
                           limb_altitude_sigma_km={"earth": settings.limb_altitude_sigma_km})


def _earth_render_options():
    # a sensor is blinded only by the Sun inside its own field
    from ..render.frame import RenderOptions

    return RenderOptions(supersample=2, sun_keepout_margin_rad=0.0)


def _limb_reach_px(settings) -> float:
    """How far from the predicted limb the Earth is rendered, px: what the fit reads plus the PSF."""
    from ..image.targets import limb_read_width_px

    return limb_read_width_px(settings.limb_band_px) + _earth_render_options().psf.half_width_px + _BAND_SLACK_PX


def _limb_window(camera: Camera, centre: np.ndarray, radius_px: float, rho: float, reach_px: float):
    """(band_rad, box) of the annulus the limb fit reads: the Earth's rays within ``reach_px`` of the
    limb predicted at ``centre`` (px) with radius ``radius_px`` (``rho`` rad), and the box around it."""
    scale = camera.focal_length_px
    band = (max(rho - reach_px / scale, 0.0), rho + reach_px / scale)
    half = radius_px + reach_px
    box = (int(np.floor(centre[0] - half)), int(np.floor(centre[1] - half)),
           int(np.ceil(centre[0] + half)), int(np.ceil(centre[1] + half)))
    return band, box


def calibrate_limb_altitude(settings, state: np.ndarray, t_tdb_s: float, ephemeris, rolls: int = 4,
                            noisy_frames: int = 200) -> tuple[float, float]:
    """The Earth sensor's visible-limb altitude, km, and its standard error, km.

    The limb the stage fits is where the blurred UV horizon's brightness falls fastest: above the
    renderer's equivalent sharp edge (40 km plus one 8 km scale height, 48 km) by the PSF, pixel and
    profile-smoothing blur on a curved limb (about sigma^2 / 2R inwards: 0.36 km at a 1-px PSF).
    As a mission calibrates its horizon sensor, this renders noise-free frames of the sensor
    model at the arc's start (``state``: Earth-centred ICRF km, km/s at ``t_tdb_s``), turned
    ``rolls`` times about the boresight, fits them as the stage does and takes the mean altitude
    of the fitted limb; twice, the second time searching around the first answer as the stage
    will (the limb points' sampling grid moves the fitted radius by ~0.005 km). Then
    ``noisy_frames`` frames with detector noise, at rolls spread over a quarter turn, searched
    around that answer: their mean altitude and its standard error are returned (noise moves
    the fitted limb by ~0.01 km: the steepest fall of a profile with an exponential tail on one
    side is found slightly inwards). Any error left is a bias every record shares.
    """
    from ..light import light_time_vector
    from ..observer import Observer
    from ..render.detector import DetectorOptions

    kit = sensors(settings)
    camera = kit.earth_camera
    options = replace(_earth_render_options(), detector=DetectorOptions(noise_free=True, hot_pixel_fraction=0.0))
    r_earth, v_earth = ephemeris.state("earth", t_tdb_s)
    observer = Observer(t_tdb_s, r_earth + state[:3], v_earth + state[3:])
    # the frames show the Earth where it was when the light left it: its distance then
    rel, _ = light_time_vector(lambda t: ephemeris.position("earth", t), t_tdb_s, observer.r_ssb_km)
    distance = float(np.linalg.norm(rel))
    guess = 48.0
    for _ in range(2):  # the second pass searches where the stage will: around the calibrated limb
        guess = float(np.mean(_fitted_limb_altitudes(settings, camera, kit, state, observer, ephemeris, options,
                                                     distance, guess, rolls)))
    altitudes = _fitted_limb_altitudes(settings, camera, kit, state, observer, ephemeris, _earth_render_options(),
                                       distance, guess, noisy_frames, rng=np.random.default_rng(20011))
    return float(np.mean(altitudes)), float(np.std(altitudes) / np.sqrt(len(altitudes)))


def _fitted_limb_altitudes(settings, camera, kit, state, observer, ephemeris, options, distance, guess, rolls,
                           rng=None):
    """Altitudes (km) of the limbs fitted on Earth-sensor frames (noise from ``rng``, None: the
    options' noise-free detector) turned ``rolls`` times about the boresight over a quarter turn,
    each searched around the limb predicted at altitude ``guess``."""
    from ..bodies import body_model
    from ..constants import RADIUS_KM
    from ..image.targets import fit_limb, limb_points
    from ..render.frame import render_windows

    altitudes = []
    for roll in np.linspace(0.0, np.pi / 2, rolls, endpoint=False):
        R = body_attitude(state) * kit.body_earth * Rotation.from_rotvec([0.0, 0.0, roll])
        centre, radius_px, rho = predicted_limb(camera, R, observer, ephemeris, guess)
        band, box = _limb_window(camera, centre, radius_px, rho, _limb_reach_px(settings))
        window = render_windows(camera, R, observer, targets=(body_model("earth"),), ephemeris=ephemeris,
                                options=options, boxes=[box], body_bands={"earth": band}, rng=rng)
        image = _paste(window.windows, camera)
        fit = fit_limb(limb_points(image, centre, radius_px, radial_half_width_px=settings.limb_band_px), camera,
                       rng=len(altitudes), velocity_cam_km_s=R.inv().apply(observer.v_ssb_km_s))
        altitudes.append(distance * np.sin(fit.radius_rad) - RADIUS_KM["earth"])
    return altitudes


def _paste(windows, camera: Camera) -> np.ndarray:
    """A full-size image (ADU) with ``windows`` in place, zero elsewhere."""
    from ..image.tracking import paste_windows

    return paste_windows(windows, camera.shape)[0]


def _run_chunk(chunk: _Chunk, bar=None) -> tuple[list, dict]:
    """Render and measure one chunk from a fresh tracker; write its files; (records, book)."""
    from ..bodies import body_model
    from ..image.pipeline import FrameInput, limb_records
    from ..image.tracking import Tracker, TrackingOptions, windows_frame
    from ..observer import Observer
    from ..render.frame import RenderOptions, render_frame, render_windows
    from ..render.frames_io import saturation_level_adu
    from .image_loop import loop_sources, misidentified_stars, save_chunk

    settings = chunk.settings
    catalog, ephemeris = loop_sources(None)
    kit = sensors(settings)
    options = stage_options(settings, chunk.limb_altitude_km)
    tracker = Tracker(catalog, ephemeris, options, TrackingOptions(neighbour_depth_mag=NEIGHBOUR_DEPTH_MAG))
    # a sensor is blinded only by the Sun inside its own field
    star_render = RenderOptions(vmag_limit=settings.star_vmag_limit + SKY_DEPTH_MAG, sun_keepout_margin_rad=0.0)
    earth_render = _earth_render_options()
    star_saturation = saturation_level_adu(kit.star_camera)
    earth = body_model("earth")
    reach = _limb_reach_px(settings)
    records, book = [], {"skipped": {}, "windowed": 0, "full": 0, "stars_used": 0, "stars_misidentified": 0,
                         "navigation_star_not_tracked": 0}
    for offset, t in enumerate(chunk.epochs):
        k = chunk.first + offset
        frame_id = f"epoch_{k:05d}"
        if bar is not None:
            bar.update(1)
        t = float(t)
        r_earth, v_earth = ephemeris.state("earth", t)
        observer = Observer(t, r_earth + chunk.states[offset, :3], v_earth + chunk.states[offset, 3:])
        R_body = body_attitude(chunk.states[offset])
        R_star = R_body * kit.body_star
        try:
            boxes = tracker.read_boxes(kit.star_camera, t, observer, R_star)
            rng = np.random.default_rng([chunk.seed, 31, k])
            if boxes is None:
                rendered = render_frame(kit.star_camera, R_star, observer, catalog=catalog, ephemeris=ephemeris,
                                        options=star_render, rng=rng)
                frame = FrameInput.from_camera(rendered.image, kit.star_camera, t, R_star, observer,
                                               saturation_adu=star_saturation, frame_id=frame_id)
                book["full"] += 1
            else:
                rendered = render_windows(kit.star_camera, R_star, observer, catalog=catalog, ephemeris=ephemeris,
                                          options=star_render, rng=rng, boxes=boxes)
                frame = windows_frame(rendered.windows, camera=kit.star_camera, t_tdb_s=t, R_prior=R_star,
                                      observer=observer, saturation_adu=star_saturation, frame_id=frame_id)
                book["windowed"] += 1
            result = tracker.step(frame, rng=np.random.default_rng([chunk.seed, 33, k]))
        except OpnavError as exc:
            book["skipped"][frame_id] = f"star sensor: {exc}"
            continue
        tracked, tracker.last_tracked = tracker.last_tracked, None
        if "attitude_prior" in result.flags:
            book["skipped"][frame_id] = f"star sensor: no star-identified attitude ({result.n_stars_matched} stars matched)"
            continue
        row = int(chunk.stars[offset])
        if row < 0:
            book["skipped"][frame_id] = "no navigation star in the star sensor's field"
            continue
        star_id = int(catalog.star_id[row])
        if tracked is not None:
            used, wrong = misidentified_stars(tracked, rendered.truth.stars)
            book["stars_used"] += used
            book["stars_misidentified"] += wrong
            # the angle is the catalog star's against the Earth through the attitude the whole field
            # gives; the star itself need not be a guide star (a neighbour or the field edge)
            book["navigation_star_not_tracked"] += star_id not in set(tracked.predicted.star_id[tracked.used].tolist())
        # the Earth sensor's attitude: the star sensor's solution through the mounting; its covariance
        # (camera-frame small rotation) turns with the frame
        R_earth_solved = result.R_icrf_cam * kit.star_to_earth
        turn = kit.star_to_earth.inv().as_matrix()
        cov_earth = turn @ result.cov_attitude_rad2 @ turn.T
        centre, radius_px, rho = predicted_limb(kit.earth_camera, R_earth_solved, observer, ephemeris,
                                                chunk.limb_altitude_km)
        band, box = _limb_window(kit.earth_camera, centre, radius_px, rho, reach)
        try:
            limb = render_windows(kit.earth_camera, R_body * kit.body_earth, observer, targets=(earth,),
                                  ephemeris=ephemeris, options=earth_render,
                                  rng=np.random.default_rng([chunk.seed, 32, k]), boxes=[box],
                                  body_bands={"earth": band})
            image = _paste(limb.windows, kit.earth_camera)
            star_astrometric = catalog.apparent_directions([row], t_tdb_s=t, r_observer_ssb_km=observer.r_ssb_km,
                                                           v_observer_ssb_km_s=observer.v_ssb_km_s, aberration=False)
            star_apparent = catalog.apparent_directions([row], t_tdb_s=t, r_observer_ssb_km=observer.r_ssb_km,
                                                        v_observer_ssb_km_s=observer.v_ssb_km_s)
            measured = limb_records("earth", earth, image, kit.earth_camera, centre, radius_px, R_earth_solved,
                                    cov_earth, ([row], star_apparent, star_astrometric, [star_id]), t, frame_id,
                                    options, np.random.default_rng([chunk.seed, 34, k]),
                                    radial_half_width_px=settings.limb_band_px, v_observer_km_s=observer.v_ssb_km_s)
        except OpnavError as exc:
            book["skipped"][frame_id] = f"Earth sensor: {exc}"
            continue
        records += [r for r in measured if r.kind == "starlight"]
    book["events"] = tracker.events
    save_chunk(chunk.stem, chunk.key, records, book)
    return records, book


def starlight_errors(records: list, epochs: np.ndarray, truth: np.ndarray, model) -> dict:
    """Each record's error against the truth's prediction (``model`` at the true state): angle and
    elevation errors and median 1-sigma (arcsec), and the mean of d^T C^-1 d over its 2 degrees of freedom
    (1 when the covariances are right)."""
    index = np.searchsorted(epochs, [r.t_tdb_s for r in records])
    if not len(records):
        raise InputError("no starlight records to compare with the truth")
    errors = np.array([r.value - model.predict(r, truth[i]) for r, i in zip(records, index)])
    sigmas = np.array([np.sqrt(np.diag(r.covariance)) for r in records])
    chi2 = np.array([e @ np.linalg.solve(r.covariance, e) for e, r in zip(errors, records)])
    return {
        "records": len(records),
        "angle_rms_arcsec": float(np.sqrt(np.mean(errors[:, 0] ** 2)) / ARCSEC_RAD),
        "elevation_rms_arcsec": float(np.sqrt(np.mean(errors[:, 1] ** 2)) / ARCSEC_RAD),
        "angle_mean_arcsec": float(np.mean(errors[:, 0]) / ARCSEC_RAD),
        "elevation_mean_arcsec": float(np.mean(errors[:, 1]) / ARCSEC_RAD),
        "angle_median_sigma_arcsec": float(np.median(sigmas[:, 0]) / ARCSEC_RAD),
        "elevation_median_sigma_arcsec": float(np.median(sigmas[:, 1]) / ARCSEC_RAD),
        "correlation_median": float(np.median([r.covariance[0, 1] / np.sqrt(r.covariance[0, 0] * r.covariance[1, 1])
                                               for r in records])),
        "chi2_mean_per_dof": float(np.mean(chi2) / 2.0),
    }
