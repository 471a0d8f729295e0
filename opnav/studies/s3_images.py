"""S3 from pixels: the star sensor and the UV Earth sensor rendered along the GEO arc and measured in memory.

The spacecraft is Earth-pointing and 3-axis stabilised (:func:`body_attitude`: body z to the
Earth's centre, x ahead along the track, y = z x x). Two sensors are fixed on it
(:func:`sensors`):

- the **star sensor**, boresight where the measurement mode's schedule puts it
  (``boresight_from_nadir_deg``, ``boresight_out_of_plane_deg``), a field of
  2 ``fov_half_deg`` across ``star_sensor_px`` pixels, catalog stars to ``star_vmag_limit``;
- the **UV Earth sensor**, boresight at nadir, ``earth_sensor_fov_deg`` across
  ``earth_sensor_px`` pixels (the renderer's UV Earth: a flat disk with a soft ozone-layer limb).

Each epoch (``step_s``; noise of epoch ``k`` from ``default_rng([seed, 31 or 32, k])``, the stages'
draws from ``[seed, 33 or 34, k]``):

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

Both sensors go through the one render -> measure loop (:mod:`opnav.sim.loop`): the star sensor
with a :class:`~opnav.sim.stages.Tracking` stage, the Earth sensor with a
:class:`~opnav.sim.stages.Limb` stage that follows the star sensor's solution through the
mountings. The arc goes in chunks of ``CHUNK_EPOCHS`` (:mod:`opnav.sim.chunks`): each starts with
an acquisition, is written atomically when done and read back by a re-run, and chunks run in
``workers`` processes with the same records.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..constants import DEG_RAD

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
    from ..constants import RADIUS_KM
    from ..image.targets import fit_limb, limb_points
    from ..sim.loop import render_limb
    from ..sim.stages import limb_window, predicted_limb

    altitudes = []
    for roll in np.linspace(0.0, np.pi / 2, rolls, endpoint=False):
        R = body_attitude(state) * kit.body_earth * Rotation.from_rotvec([0.0, 0.0, roll])
        centre, radius_px, rho = predicted_limb(camera, R, observer, ephemeris, guess)
        band, box = limb_window(camera, centre, radius_px, rho, _limb_reach_px(settings))
        image = render_limb(camera, R, observer, body="earth", ephemeris=ephemeris, options=options, box=box,
                            band_rad=band, rng=rng)
        fit = fit_limb(limb_points(image, centre, radius_px, radial_half_width_px=settings.limb_band_px), camera,
                       rng=len(altitudes), velocity_cam_km_s=R.inv().apply(observer.v_ssb_km_s))
        altitudes.append(distance * np.sin(fit.radius_rad) - RADIUS_KM["earth"])
    return altitudes


def stream_s3(settings, seed: int, epochs: np.ndarray, states: np.ndarray, stars: np.ndarray, out: Path, *, key: str,
              limb_altitude_km: float, workers: int = 1, progress: bool = False):
    """Render and measure every epoch (module notes): the loop's result (:class:`opnav.sim.results.LoopResult`:
    the starlight records, epochs skipped and why, tracking events, counts).

    ``states``: true Earth-centred ICRF states (N, 6) km, km/s at ``epochs`` (TDB s); ``stars``:
    catalog row of the navigation star per epoch (-1: none); ``limb_altitude_km``: the Earth
    sensor's visible-limb altitude (:func:`calibrate_limb_altitude`).
    """
    from ..image.tracking import TrackingOptions
    from ..render.frame import RenderOptions
    from ..sim.chunks import run_chunks
    from ..sim.sensors import Arc, Loop, Sensor, Sky, Streams, loop_sources
    from ..sim.stages import Limb, Tracking

    kit = sensors(settings)
    options = stage_options(settings, limb_altitude_km)
    star_sensor = Sensor(kit.star_camera, Tracking(options, TrackingOptions(neighbour_depth_mag=NEIGHBOUR_DEPTH_MAG)),
                         mounting=kit.body_star, name="star sensor", streams=Streams((31,), (33,)),
                         # a sensor is blinded only by the Sun inside its own field
                         render=RenderOptions(vmag_limit=settings.star_vmag_limit + SKY_DEPTH_MAG,
                                              sun_keepout_margin_rad=0.0))
    earth_sensor = Sensor(kit.earth_camera, Limb(options, 0, np.asarray(stars, int), settings.limb_band_px,
                                                 _limb_reach_px(settings), limb_altitude_km),
                          mounting=kit.body_earth, targets=("earth",), render=_earth_render_options(), stars=False,
                          name="Earth sensor", streams=Streams((32,), (34,)))
    loop = Loop((star_sensor, earth_sensor), seed, Sky(), frame_prefix="epoch")
    _, ephemeris, _ = loop_sources(loop.sky, catalog=False)
    r_ssb, v_ssb = np.empty((len(epochs), 3)), np.empty((len(epochs), 3))
    for k, t in enumerate(epochs):  # the Earth's SSB state, one epoch at a time, as the renderer asks for it
        r_earth, v_earth = ephemeris.state("earth", float(t))
        r_ssb[k], v_ssb[k] = r_earth + states[k, :3], v_earth + states[k, 3:]
    arc = Arc(epochs, r_ssb, v_ssb, Rotation.concatenate([body_attitude(state) for state in states]))
    return run_chunks(loop, arc, folder=Path(out) / "stream", key=f"{key}:{limb_altitude_km!r}",
                      chunk_frames=CHUNK_EPOCHS, workers=workers, progress=progress, unit="epoch", name="s3_chunk")
