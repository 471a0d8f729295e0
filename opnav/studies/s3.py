"""S3: GEO satellite, star sensor + UV Earth sensor, starlight angle and elevation (docs/studies.md#s3-geo-satellite; Table 4).

Truth: the study's orbit (period 86164.09 s, e = 0, i = 0, RAAN 260 deg, true
anomaly 0.702295 deg, Earth-centred J2000) propagated with
``opnav.dynamics.geo_model`` (JGM-3 two-body, J2..J4, C/S22, C/S31, C/S33, Sun,
Moon, SRP; DOP853) from 2001-01-01 00:00 UTC.

Star schedule (the study says only "one navigation star always in view;
Earth-pointing, 3-axis stabilised"): the star sensor's boresight is fixed in the
Earth-pointing frame at ``boresight_from_nadir_deg`` from nadir in the orbit
plane, ahead along the track (90 deg: along the velocity, where the starlight
angle is most sensitive to the position); it turns with the orbit, once a day.
At each epoch the sensor follows its current star while it stays within
``fov_half_deg`` of the boresight and otherwise takes the brightest catalog star
(V <= ``vmag_limit``) there. The schedule is reported (stars used, epochs without one).

Measurements every ``step_s``: one ``starlight`` record per epoch, angle and
elevation of the current star, or the two scalar records with ``vector = false``.
Their noise (``noise_model``): the study writes eq. 4 with white noises v_alpha and
v_beta and gives the star sensor 5" and the UV Earth sensor 20" (3-sigma); read as it
stands ("paper", the default), the angle carries the star sensor's error and the elevation
the Earth sensor's, independently. The angle is measured between the star and the Earth's
centre, so a physical angle also carries the Earth sensor's centre error and the elevation
repeats it ("sensors": the correlated covariance of
:func:`opnav.measurements.starlight_covariance`, what an image stage delivers). Over the
24 h the "sensors" noise leaves the EKF a 1-sigma of ~0.28 km at the end (its RMS over the
last 12 h 0.27 km over 5 seeds) against ~0.07 km with the paper's, 1-sigma and RMS
agreeing in both: the difference is information, not filter quality.
The filters start from the truth plus a draw of P0 and the RMS is taken over the
last 12 h.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..catalog import load_catalog
from ..constants import ARCSEC_RAD, DEG_RAD, EARTH_GM_JGM3_KM3_S2
from ..dynamics import geo_model, propagate
from ..epochs import parse_epoch
from ..errors import InputError
from ..measurements import ProbeMeasurementModel, simulate_starlight
from ..filters.options import NavigationConfig
from .common import Simulation, tracking_facts

START_UTC = "2001-01-01T00:00:00"
NOISE_MODELS = ("paper", "sensors")
#: S3 Table 4: converged error ranges, position (km), velocity (m/s).
PAPER = {"ekf": {"position_km": (-2.0, 2.0), "velocity_m_s": (-2.5, 2.5)},
         "ukf": {"position_km": (-1.2, 1.0), "velocity_m_s": (-4.0, 2.0)},
         "mcmc-upf": {"position_km": (-0.1, 0.25), "velocity_m_s": (-2.0, 2.0)}}


#: The study's kind for the runner (:mod:`opnav.studies.base`): simulating (``simulate`` feeds the generic filter stages); ``--mode images`` renders and measures frames (``simulate_images``).
KIND = "simulating"
IMAGE_MODE = True
#: Settings only image mode reads: none (its frames follow the measurement-mode settings).
IMAGE_SETTINGS: tuple[str, ...] = ()


@dataclass(frozen=True)
class Settings:
    """S3 run settings (``[settings]`` of the run file; each one a ``--set`` key).

    Attributes
    ----------
    duration_hours : float
        Arc length, h (S3: 24).
    step_s : float
        Measurement interval, s (S3: 10).
    star_sensor_arcsec_3sigma, earth_sensor_arcsec_3sigma : float
        Sensor accuracies, arcsec, 3-sigma (S3: 5 and 20).
    vector : bool
        One ``starlight`` record (angle and elevation with their cross-covariance) per epoch;
        false gives the two scalar records with the diagonal only.
    noise_model : {"paper", "sensors"}
        ``"paper"``: eq. 4 as the study sets it up, independent white noises on the angle (the
        star sensor's 5") and on the elevation (the UV Earth sensor's 20"). ``"sensors"``: what
        the two sensors give (:func:`opnav.measurements.starlight_covariance`): the angle also
        carries the Earth-centre error and the elevation repeats it, so both are ~20" and
        correlated; the position error is about 4x larger (module notes).
    boresight_from_nadir_deg : float
        Star-sensor boresight from nadir, in the orbit plane, ahead along the track, deg.
    boresight_out_of_plane_deg : float
        Tilt of the boresight out of the orbit plane, toward the orbit normal, deg (module notes).
    fov_half_deg : float
        Star-sensor half field of view, deg.
    vmag_limit : float
        Faintest navigation star, V.
    sigma_position_km, sigma_velocity_m_s : float
        Initial 1-sigma per axis, km and m/s.
    process_noise_km2_s3 : float
        Filters' white-acceleration density, km^2/s^3 (default 0: the truth has none and the
        fast propagator stays within 1 m of it over the day; 1e-12 makes the EKF's NEES 3 and
        its RMS 0.78 km on seed 1, measured).
    particles : int
        Particles of the particle filters (S3: 150).
    star_sensor_px, star_sensor_aperture_mm, star_sensor_exposure_s : int, float, float
        Image mode: the star sensor's detector side (its field is 2 ``fov_half_deg`` across),
        aperture and exposure (25 mm and 0.2 s: a V 6 star gives ~1,600 electrons, SNR ~35).
    star_vmag_limit : float
        Image mode: faintest catalog star the star sensor tracks, V (drawn to 0.5 fainter).
    earth_sensor_fov_deg, earth_sensor_px : float, int
        Image mode: the UV Earth sensor's field (deg, the Earth is 17.4 deg across from GEO)
        and detector side.
    limb_band_px : float
        Image mode: the limb is searched, and rendered, within this of its prediction, px
        (:mod:`opnav.studies.s3_images`).
    limb_altitude_sigma_km : float
        Image mode: 1-sigma of the Earth sensor's calibrated visible-limb altitude, km
        (:func:`opnav.studies.s3_images.calibrate_limb_altitude`: ~47.59 km for the default
        sensor, the same within 0.001 km over the arc's geometries and roll angles, with a standard
        error of ~0.003 km from its 200 noisy frames). It enters every record's elevation variance
        as white noise, though an error of the calibration is a bias all records share (the filters
        average it down: their NEES grows with it).
    """

    duration_hours: float = 24.0
    step_s: float = 10.0
    star_sensor_arcsec_3sigma: float = 5.0
    earth_sensor_arcsec_3sigma: float = 20.0
    vector: bool = True
    noise_model: str = "paper"
    boresight_from_nadir_deg: float = 90.0
    boresight_out_of_plane_deg: float = 0.0
    fov_half_deg: float = 10.0
    vmag_limit: float = 5.0
    sigma_position_km: float = 10.0
    sigma_velocity_m_s: float = 1.0
    process_noise_km2_s3: float = 0.0
    particles: int = 150
    star_sensor_px: int = 1024
    star_sensor_aperture_mm: float = 25.0
    star_sensor_exposure_s: float = 0.2
    star_vmag_limit: float = 6.0
    earth_sensor_fov_deg: float = 30.0
    earth_sensor_px: int = 512
    limb_band_px: float = 5.0
    limb_altitude_sigma_km: float = 0.01

    def __post_init__(self) -> None:
        for name in ("duration_hours", "step_s", "star_sensor_arcsec_3sigma", "earth_sensor_arcsec_3sigma",
                     "fov_half_deg", "sigma_position_km", "sigma_velocity_m_s"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise InputError(f"{name} must be positive, got {value!r}")
        if not 2 <= self.duration_hours * 3600.0 / self.step_s <= 2_000_000:
            raise InputError(f"duration_hours / step_s gives {self.duration_hours * 3600.0 / self.step_s:.0f} epochs; "
                             "allowed 2 to 2,000,000")
        if not 0.0 < self.boresight_from_nadir_deg < 180.0:
            raise InputError(f"boresight_from_nadir_deg must be in (0, 180), got {self.boresight_from_nadir_deg}")
        if not -90.0 <= self.boresight_out_of_plane_deg <= 90.0:
            raise InputError(f"boresight_out_of_plane_deg must be in [-90, 90], got {self.boresight_out_of_plane_deg}")
        if self.fov_half_deg >= 60.0:
            raise InputError(f"fov_half_deg must be below 60, got {self.fov_half_deg}")
        if not (np.isfinite(self.process_noise_km2_s3) and self.process_noise_km2_s3 >= 0.0):
            raise InputError(f"process_noise_km2_s3 must be >= 0, got {self.process_noise_km2_s3!r}")
        if self.noise_model not in NOISE_MODELS:
            raise InputError(f"noise_model must be one of {', '.join(NOISE_MODELS)}, got {self.noise_model!r}")
        if self.particles < 2:
            raise InputError(f"particles must be >= 2, got {self.particles}")
        for name in ("star_sensor_px", "earth_sensor_px"):
            if not 64 <= getattr(self, name) <= 8192:
                raise InputError(f"{name} must be 64 to 8192 pixels, got {getattr(self, name)!r}")
        for name in ("star_sensor_aperture_mm", "star_sensor_exposure_s", "limb_band_px", "limb_altitude_sigma_km"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise InputError(f"{name} must be positive, got {value!r}")
        if not np.isfinite(self.star_vmag_limit):
            raise InputError(f"star_vmag_limit must be finite, got {self.star_vmag_limit!r}")
        if not 20.0 <= self.earth_sensor_fov_deg < 90.0:
            raise InputError(f"earth_sensor_fov_deg must be in [20, 90) (the Earth is 17.4 deg across from GEO), "
                             f"got {self.earth_sensor_fov_deg!r}")


def geo_state() -> np.ndarray:
    """The S3 orbit at the start: circular equatorial GEO, Earth-centred ICRF km and km/s."""
    period = 86_164.09
    a = (EARTH_GM_JGM3_KM3_S2 * (period / (2.0 * np.pi)) ** 2) ** (1.0 / 3.0)
    u = (260.0 + 0.702295) * DEG_RAD
    speed = np.sqrt(EARTH_GM_JGM3_KM3_S2 / a)
    return np.array([a * np.cos(u), a * np.sin(u), 0.0, -speed * np.sin(u), speed * np.cos(u), 0.0])


def earth_sensor_view(t_tdb_s: float, ephemeris, rng: np.random.Generator, *, sun_spread_rad: float = 1.2,
                      pointing_error_rad: float = 0.03):
    """A GEO observer on the sunlit side and a UV Earth sensor attitude looking at the Earth.

    The observer sits on the 42,164 km equatorial circle at a longitude within
    ``sun_spread_rad`` of the Sun's (the Sun behind the sensor, a lit disk), moving eastward at
    3.07 km/s; the sensor's boresight points at the Earth's centre, off by up to
    ``pointing_error_rad`` per axis, with a random roll.

    Returns
    -------
    observer : opnav.observer.Observer
        Barycentric ICRF position (km) and velocity (km/s) at ``t_tdb_s``.
    attitude : scipy.spatial.transform.Rotation
        Camera -> ICRF.
    """
    from scipy.spatial.transform import Rotation

    from ..observer import Observer

    r_earth, v_earth = ephemeris.state("earth", t_tdb_s)
    sun = ephemeris.position("sun", t_tdb_s) - r_earth
    lon = np.arctan2(sun[1], sun[0]) + rng.uniform(-sun_spread_rad, sun_spread_rad)
    rel = 42_164.0 * np.array([np.cos(lon), np.sin(lon), 0.0])
    observer = Observer(t_tdb_s, r_earth + rel, v_earth + 3.07 * np.array([-np.sin(lon), np.cos(lon), 0.0]))
    z = -rel / np.linalg.norm(rel)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    attitude = Rotation.from_matrix(np.column_stack([x, np.cross(z, x), z])) * Rotation.from_rotvec(
        np.r_[rng.uniform(-pointing_error_rad, pointing_error_rad, 2), rng.uniform(-np.pi, np.pi)])
    return observer, attitude


def star_schedule(states: np.ndarray, settings: Settings) -> tuple[np.ndarray, np.ndarray]:
    """Star followed at each epoch: catalog index (N,) (-1: none in view) and unit vectors (N, 3), ICRF."""
    catalog = load_catalog()
    bright = np.flatnonzero(catalog.vmag <= settings.vmag_limit)
    if bright.size == 0:
        raise InputError(f"no catalog star brighter than V {settings.vmag_limit}")
    units = catalog.unit_vectors()[bright]
    order = np.argsort(catalog.vmag[bright])  # brightest first
    r_hat = states[:, :3] / np.linalg.norm(states[:, :3], axis=1, keepdims=True)
    along = states[:, 3:] - np.sum(states[:, 3:] * r_hat, axis=1, keepdims=True) * r_hat
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    angle = settings.boresight_from_nadir_deg * DEG_RAD
    in_plane = -np.cos(angle) * r_hat + np.sin(angle) * along
    normal = np.cross(r_hat, along)
    tilt = settings.boresight_out_of_plane_deg * DEG_RAD
    boresight = np.cos(tilt) * in_plane + np.sin(tilt) * normal
    cos_fov = np.cos(settings.fov_half_deg * DEG_RAD)
    chosen = np.full(len(states), -1)
    current = -1
    for k, b in enumerate(boresight):
        if current < 0 or units[current] @ b < cos_fov:
            inside = order[units[order] @ b >= cos_fov]
            current = int(inside[0]) if inside.size else -1
        chosen[k] = current
    index = np.where(chosen >= 0, bright[np.maximum(chosen, 0)], -1)
    return index, np.where(chosen[:, None] >= 0, units[np.maximum(chosen, 0)], np.nan)


def dynamics(settings: Settings):
    """The truth's and the filters' force model (S3's GEO model, Earth rotation for 2001-01-01)."""
    return geo_model(epoch_tdb_s=parse_epoch(START_UTC, scale="utc"))


def simulate(settings: Settings, seed: int) -> Simulation:
    """Truth, star schedule, records and filter start of one S3 run (module notes)."""
    rng = np.random.default_rng([seed, 3])
    t0 = parse_epoch(START_UTC, scale="utc")
    count = int(round(settings.duration_hours * 3600.0 / settings.step_s))
    epochs = t0 + settings.step_s * np.arange(1, count + 1)
    force_model = dynamics(settings)
    truth = propagate(force_model, t0, geo_state(), epochs).states
    stars, units = star_schedule(truth, settings)
    exact = ProbeMeasurementModel("earth", light_time=False, aberration=False)
    records = []
    sigma_star = settings.star_sensor_arcsec_3sigma / 3.0 * ARCSEC_RAD
    sigma_earth = settings.earth_sensor_arcsec_3sigma / 3.0 * ARCSEC_RAD
    catalog = load_catalog()
    ids = catalog.star_id
    covariance = np.diag([sigma_star**2, sigma_earth**2]) if settings.noise_model == "paper" else None
    for star in np.unique(stars[stars >= 0]):
        rows = stars == star
        batch = simulate_starlight(exact, "earth", epochs[rows], truth[rows], units[rows][0],
                                   sigma_star_rad=sigma_star, sigma_target_rad=sigma_earth, rng=rng,
                                   vector=settings.vector, sensor="s3", covariance=covariance)
        records += [replace(r, star_id=int(ids[star])) for r in batch]
    records.sort(key=lambda r: r.t_tdb_s)
    P0 = np.diag([settings.sigma_position_km**2] * 3 + [(1e-3 * settings.sigma_velocity_m_s) ** 2] * 3)
    x0 = geo_state() + np.sqrt(np.diag(P0)) * rng.standard_normal(6)
    q = settings.process_noise_km2_s3
    nav = NavigationConfig(
        t0_tdb_s=t0, dynamics="geo", x0=x0, P0=P0, light_time=False, aberration=False, seed=seed,
        process_noise={"model": "white", "q_km2_s3": q} if q > 0 else {"model": "none"},
        particle={"n_particles": settings.particles},
    )
    used = np.unique(stars[stars >= 0])
    facts = {"stars_used": [int(ids[s]) for s in used], "epochs_without_star": int(np.sum(stars < 0)),
             "window": "last 12 h (last half of a shorter arc)"}
    window = max(epochs[-1] - 12 * 3600.0, t0 + 0.5 * (epochs[-1] - t0))
    return Simulation("earth", epochs, truth, records, nav, force_model, float(window),
                      {"table4": PAPER, "note": "S3 Table 4: converged error ranges per axis"}, facts)


#: Epochs image mode renders at most (two frames each).
MAX_IMAGE_EPOCHS = 100_000


def simulate_images(settings: Settings, seed: int, out, *, progress: bool = False, workers: int = 1,
                    faults=None) -> Simulation:
    """S3 from pixels (:mod:`opnav.studies.s3_images`): the truth, star schedule and filter start of
    :func:`simulate`, the records measured on the star sensor's and UV Earth sensor's frames.

    The filters' model applies light time and aberration (the frames have them). ``facts`` gains
    the records' errors against the truth (``measurement_errors``: angle and elevation RMS, the
    median 1-sigma the stage reported and the mean chi-square/2), the epochs without a record
    and why, the star sensor's acquisitions and losses of lock, and the tracked stars checked
    against the truth.
    """
    from dataclasses import asdict

    from .. import __version__
    from ..ephemeris.cache import default_cached_ephemeris
    from ..sim.checks import starlight_errors
    from .runner import digest as content_hash
    from .s3_images import calibrate_limb_altitude, stream_s3

    if faults is not None and faults.on_frames:
        raise InputError(f"frame faults {sorted(faults.on_frames)} are not available for S3 image mode")
    sim = simulate(settings, seed)
    if sim.epochs.size > MAX_IMAGE_EPOCHS:
        raise InputError(f"image mode renders two frames per epoch: {sim.epochs.size} epochs asked, at most "
                         f"{MAX_IMAGE_EPOCHS}; raise step_s or shorten duration_hours")
    stars, _ = star_schedule(sim.truth, settings)
    ephemeris = default_cached_ephemeris()
    altitude, spread = calibrate_limb_altitude(settings, sim.truth[0], float(sim.epochs[0]), ephemeris)
    if spread > settings.limb_altitude_sigma_km:
        raise InputError(f"the Earth sensor's limb calibration has a standard error of {spread:.4f} km, above "
                         f"limb_altitude_sigma_km = {settings.limb_altitude_sigma_km} km; raise it")
    key = content_hash({"settings": asdict(settings), "seed": seed, "opnav": __version__, "stage": "s3-images"})
    loop = stream_s3(settings, seed, sim.epochs, sim.truth, stars, Path(out), key=key, workers=workers,
                     limb_altitude_km=altitude, progress=progress)
    if not loop.records:
        raise InputError(f"{out}: no starlight record measured in {sim.epochs.size} epochs "
                         f"(first reasons: {list(loop.skipped.values())[:3]})")
    records = sorted(loop.records, key=lambda r: r.t_tdb_s)
    navigation = replace(sim.navigation, light_time=True, aberration=True)
    truth_model = ProbeMeasurementModel("earth", ephemeris=ephemeris)
    facts = {**sim.facts, "measurement_errors": starlight_errors(records, sim.epochs, sim.truth, truth_model),
             "epochs": int(sim.epochs.size), "epochs_without_record": len(loop.skipped),
             "frames_skipped": loop.skipped, "frames_windowed": loop.frames_windowed, "frames_full": loop.frames_full,
             "chunks_reused": loop.chunks_reused,
             "limb_altitude_km": {"calibrated": altitude, "standard_error": spread,
                                  "sigma": settings.limb_altitude_sigma_km},
             "tracking": tracking_facts(list(loop.events)),
             "tracked_stars": {"used": loop.stars_used, "misidentified": loop.stars_misidentified},
             "navigation_star_not_tracked": loop.navigation_star_not_tracked}
    return replace(sim, records=records, navigation=navigation, facts=facts)
