"""S4 from pixels: Mars' line of sight from a navigation camera's frames, the Sun's from a sun sensor.

The spacecraft points its navigation camera at Mars (:func:`body_attitudes`: body +z on Mars'
apparent centre, +x toward the Sun's side, +y = z x x). Three sensors are fixed on it
(:func:`instruments`, every one stated in the run file's settings, :class:`opnav.studies.s4.Settings`):

- the **navigation camera**, boresight on +z: ``camera_fov_deg`` across ``camera_px`` pixels,
  exposed for Mars (``camera_aperture_mm``, ``camera_exposure_s``: its disk below saturation, so too
  few stars show for an attitude), Mars, Phobos and Deimos drawn resolved and phased with the stars;
- the **star tracker**, boresight turned ``tracker_from_camera_deg`` from the camera's about body
  +x (180: looking away from Mars, so its weak roll axis is the camera's boresight and barely moves
  Mars' direction), tracking catalog stars to ``tracker_vmag_limit``;
- the **sun sensor** (:mod:`opnav.sim.sun_sensor`), boresight ``sun_sensor_from_camera_deg`` from the
  camera's toward +x, ``sun_sensor_half_angle_deg`` field, ``sun_sensor_sigma_arcsec`` noise and an
  optional bias the filters are not told.

Every ``image_step_s`` (an angle sample, ``lead_s`` before its fusion epoch; frame ``k``'s draws:
tracker render ``[seed, 51, k]`` and stage ``[seed, 53, k]``, camera ``[seed, 52, k]`` and
``[seed, 54, k]``, sun sensor ``[seed, 55, k]``):

1. **Star tracker** (:class:`opnav.sim.stages.Tracking`): full-frame acquisition, then windows; a
   star-identified attitude with its covariance, or no sample (the reason is listed).
2. **Navigation camera** (:class:`opnav.sim.stages.Centre`): its attitude is the tracker's solution
   through the mountings; Mars' centre is measured by :func:`opnav.image.centres.measure_body_centre`,
   the method chosen by apparent size and phase (a limb fit at 33-56 px, never by name), with the
   camera's calibrated PSF: an apparent ``radec`` record whose covariance carries the fit and the
   tracker's attitude error.
3. **Sun sensor** (:func:`opnav.sim.sun_sensor.read_sun`): the Sun's apparent direction taken to ICRF
   with the tracker's solution, its covariance the sensor's noise and that attitude error.
4. **Eq. 1**: both lines of sight are made geometric by removing the aberration of the velocity the
   spacecraft knows: the velocity sensor's own solution (:func:`doppler_velocity`: the three Doppler
   records of the nearest velocity epoch, 1 m/s each; through the three directions' geometry about
   12 m/s RMS, 8 mas of aberration, a new error every 600 s: the summary's
   ``velocity_for_aberration_error_m_s``), carried to the sample by the a-priori trajectory. (The a-priori velocity alone is 173 m/s off: 0.12" of
   aberration in both lines of sight, the same for days, which at the Sun's 1.5 AU moves the
   position by 130 km.) :func:`opnav.measurements.position_measurement` turns them into the
   position pseudo-measurement with the covariance of the two (taken as independent: the
   attitude error they share is a fraction of the sun sensor's 2").

The same three federated runs as measurement mode then use these records (:func:`opnav.studies.s4.evaluate_case`).
The summary's ``image_mode`` states what the frames gave against the truth: the achieved noise of
each line of sight per axis (what measurement mode should be run with to compare, at the same
cadence: ``--set angle_step_s=<image_step_s> sun_sigma_arcsec=... mars_sigma_arcsec=...``), the
mean chi-square of the reported covariances, the methods used and the wrong-body check: every Mars
record within 5 sigma of the true centre and on the true disk.

The frames are rendered and measured by the one loop (:mod:`opnav.sim.loop`) in chunks of
``CHUNK_FRAMES`` (:mod:`opnav.sim.chunks`: resumable under ``out/stream``, in ``workers`` processes).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..constants import ARCSEC_RAD, DEG_RAD
from ..errors import InputError
from ..frames import radec_to_unit
from ..light import aberrate
from ..measurements import position_measurement
from ..records import Measurement
from ..sim.sun_sensor import SunSensor, geometric_los, mounting_from_boresight, read_sun, sun_sensor
from .evaluation import Evaluation

#: Frames per chunk: a day at the default 600 s.
CHUNK_FRAMES = 144
#: A Mars record further than this many sigma from the true centre counts as the wrong body.
WRONG_BODY_SIGMA = 5.0
#: Most frames one run renders (two per sample: tracker and camera).
MAX_SAMPLES = 20_000
#: Streams of the three sensors (module notes).
TRACKER_STREAMS, CAMERA_STREAMS, SUN_STREAM = ((51,), (53,)), ((52,), (54,)), (55,)
#: Names of the sensors in records and reasons.
CAMERA_SENSOR, TRACKER_SENSOR = "s4 camera", "s4 star tracker"


@dataclass(frozen=True)
class Instruments:
    """The three S4 sensors of image mode (module notes): cameras, and mountings (sensor -> body)."""

    camera: object
    tracker: object
    body_camera: Rotation
    body_tracker: Rotation
    sun: SunSensor


def instruments(settings) -> Instruments:
    """The navigation camera, star tracker and sun sensor of ``settings`` (:class:`opnav.studies.s4.Settings`)."""
    from ..camera import Camera

    camera = Camera.from_fov(settings.camera_fov_deg, settings.camera_px, settings.camera_px,
                             aperture_mm=settings.camera_aperture_mm, exposure_s=settings.camera_exposure_s,
                             camera_id="s4-navigation-camera")
    tracker = Camera.from_fov(settings.tracker_fov_deg, settings.tracker_px, settings.tracker_px,
                              aperture_mm=settings.tracker_aperture_mm, exposure_s=settings.tracker_exposure_s,
                              camera_id="s4-star-tracker")
    b = settings.tracker_from_camera_deg * DEG_RAD
    a = settings.sun_sensor_from_camera_deg * DEG_RAD
    sun = sun_sensor(boresight_body=[math.sin(a), 0.0, math.cos(a)], half_angle_deg=settings.sun_sensor_half_angle_deg,
                     sigma_arcsec=settings.sun_sensor_sigma_arcsec, bias_arcsec=tuple(settings.sun_sensor_bias_arcsec),
                     stream=SUN_STREAM)
    return Instruments(camera, tracker, Rotation.identity(),
                       mounting_from_boresight([0.0, -math.sin(b), math.cos(b)]), sun)


def body_attitudes(times: np.ndarray, r_ssb_km: np.ndarray, v_ssb_km_s: np.ndarray, ephemeris) -> Rotation:
    """Body -> ICRF at ``times`` (M,) TDB s for SSB states (M, 3) km, km/s (module notes): +z on Mars'
    apparent centre, +x toward the Sun's apparent direction, perpendicular to +z."""
    from ..light import apparent_direction

    z = apparent_direction(lambda t: ephemeris.position("mars", t), times, r_ssb_km, v_ssb_km_s)
    sun = apparent_direction(lambda t: ephemeris.position("sun", t), times, r_ssb_km, v_ssb_km_s)
    x = sun - np.sum(sun * z, axis=1, keepdims=True) * z
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return Rotation.from_matrix(np.stack([x, np.cross(z, x), z], axis=2))


def camera_sensor(settings, stage):
    """The navigation camera (module notes) as a loop sensor measuring with ``stage`` (None: render only)."""
    from ..render.frame import RenderOptions
    from ..render.psf import PSF
    from ..sim.sensors import Sensor, Streams

    kit = instruments(settings)
    return Sensor(kit.camera, stage, mounting=kit.body_camera, targets=("mars", "phobos", "deimos"),
                  name="navigation camera", streams=Streams(*CAMERA_STREAMS),
                  # the camera is blinded only by the Sun in its own field
                  render=RenderOptions(psf=PSF(sigma_px=settings.camera_psf_sigma_px), supersample=2,
                                       sun_keepout_margin_rad=0.0))


def stream_frames(settings, seed: int, arc, out: Path, *, key: str, workers: int, progress: bool):
    """The tracker and camera frames of ``arc`` (:class:`opnav.sim.sensors.Arc` with the body's
    attitudes) rendered and measured (module notes, steps 1-2): the loop's
    :class:`~opnav.sim.results.LoopResult`."""
    from ..image.pipeline import PipelineOptions
    from ..image.tracking import TrackingOptions
    from ..render.frame import RenderOptions
    from ..sim.chunks import run_chunks
    from ..sim.sensors import Loop, Sensor, Sky, Streams
    from ..sim.stages import Centre, Tracking

    kit = instruments(settings)
    tracker = Sensor(kit.tracker, Tracking(PipelineOptions(vmag_limit=settings.tracker_vmag_limit, sensor=TRACKER_SENSOR),
                                           TrackingOptions(neighbour_depth_mag=1.5)),
                     mounting=kit.body_tracker, name="star tracker", streams=Streams(*TRACKER_STREAMS),
                     # the sky a magnitude below what the tracker uses; only the Sun in its own field blinds it
                     render=RenderOptions(vmag_limit=settings.tracker_vmag_limit + 1.0, sun_keepout_margin_rad=0.0))
    camera = camera_sensor(settings, Centre("mars", 0, settings.camera_psf_sigma_px, sensor=CAMERA_SENSOR))
    loop = Loop((tracker, camera), seed, Sky(), frame_prefix="sample")
    return run_chunks(loop, arc, folder=Path(out) / "stream", key=key, chunk_frames=CHUNK_FRAMES, workers=workers,
                      progress=progress, unit="frame", name="s4_chunk")


def doppler_velocity(model, records: list[Measurement], x_prior: np.ndarray) -> np.ndarray:
    """The heliocentric ICRF velocity (3,), km/s, that the velocity sensor's ``records`` of one epoch
    (three ``radial_velocity`` records, :func:`opnav.studies.s4.doppler_records`) give through the filters'
    ``model``, at the position of ``x_prior`` (6,): the radial velocities are linear in the velocity,
    so one Gauss-Newton step from ``x_prior`` solves them."""
    H = np.vstack([model.jacobian(r, x_prior)[:, 3:] for r in records])
    dz = np.concatenate([np.asarray(r.value) - model.predict(r, x_prior) for r in records])
    return x_prior[3:] + np.linalg.solve(H, dz)


def tangent_errors(u: np.ndarray, u_true: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, float]:
    """Error of a unit vector ``u`` against ``u_true`` (both (3,), ICRF) along two axes perpendicular to
    ``u_true`` (rad, (2,)), and its chi-square under ``cov`` (3, 3) projected on those axes."""
    a = np.cross(u_true, [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    basis = np.stack([a, np.cross(u_true, a)])
    e = basis @ (u - u_true)
    return e, float(e @ np.linalg.solve(basis @ cov @ basis.T, e))


def radec_line(record: Measurement) -> tuple[np.ndarray, np.ndarray]:
    """Unit line of sight (3,) and its covariance (3, 3) of a ``radec`` record, ICRF."""
    ra, dec = record.value
    jac = np.array([[-math.sin(ra) * math.cos(dec), -math.cos(ra) * math.sin(dec)],
                    [math.cos(ra) * math.cos(dec), -math.sin(ra) * math.sin(dec)],
                    [0.0, math.cos(dec)]])
    return radec_to_unit(ra, dec), jac @ record.covariance @ jac.T


def _noise_figures(errors: list, chi2: list) -> dict:
    """RMS per axis (arcsec), the mean error's size (arcsec) and the mean chi-square per dof of ``errors`` (N, 2) rad."""
    e = np.asarray(errors).reshape(-1, 2)
    return {"count": int(e.shape[0]), "rms_per_axis_arcsec": float(np.sqrt(np.mean(e**2)) / ARCSEC_RAD),
            "mean_arcsec": (np.mean(e, axis=0) / ARCSEC_RAD).tolist() if e.size else [],
            "chi2_per_dof": float(np.mean(chi2) / 2.0) if chi2 else float("nan")}


def evaluate_images(settings, seed: int, log, out, *, progress: bool = False, workers: int = 1) -> Evaluation:
    """S4 from pixels (module notes): the three federated runs on eq. 1 records from the camera's
    frames and the sun sensor, with the frames' figures against the truth in ``image_mode``."""
    from .. import __version__
    from ..bodies import body_model
    from ..ephemeris.cache import default_cached_ephemeris
    from ..sim.checks import radec_errors
    from ..sim.sensors import Arc
    from .runner import digest
    from .s4 import (assemble_case, clocks, evaluate_case, geometric_lines, initial_state, sensor_model, true_states,
                     velocity_sensor)

    clock = clocks(settings, settings.image_step_s)
    if clock.angle_times.size > MAX_SAMPLES:
        raise InputError(f"image mode renders two frames per sample: {clock.angle_times.size} samples asked, at most "
                         f"{MAX_SAMPLES}; raise image_step_s or shorten duration_hours")
    ephemeris = default_cached_ephemeris()
    x0 = initial_state(clock.t0)
    times = clock.angle_times
    truth = true_states(clock.t0, x0, np.concatenate([times, clock.epochs]))
    truth_angle, truth_fusion = truth[:times.size], truth[times.size:]
    r_sun, v_sun = ephemeris.state("sun", times)
    r_ssb, v_ssb = truth_angle[:, :3] + r_sun, truth_angle[:, 3:] + v_sun
    R_body = body_attitudes(times, r_ssb, v_ssb, ephemeris)
    log(f"S4 from pixels: {times.size} samples every {settings.image_step_s:g} s (star tracker, navigation camera, "
        f"sun sensor), seed {seed}")
    key = digest({"settings": asdict(settings), "seed": seed, "opnav": __version__, "stage": "s4-images"})
    arc = Arc(times, r_ssb, v_ssb, R_body)
    loop = stream_frames(settings, seed, arc, Path(out), key=key, workers=workers, progress=progress)
    kit = instruments(settings)
    # the velocity the aberration is removed with: the velocity sensor's solution at the nearest velocity
    # epoch, carried to the sample along the a-priori trajectory (module notes, step 4)
    dopplers = velocity_sensor(clock, truth_fusion, np.random.default_rng([seed, 56]))
    x_start = x0 + np.array([1000.0, 1000.0, 1000.0, 0.1, 0.1, 0.1])
    prior = true_states(clock.t0, x_start, np.concatenate([times, clock.velocity_epochs]))
    prior_sample, prior_velocity = prior[:times.size], prior[times.size:]
    model, _ = sensor_model()
    by_epoch = {}
    for record in dopplers:
        by_epoch.setdefault(record.t_tdb_s, []).append(record)
    v_doppler = np.array([doppler_velocity(model, by_epoch[t], x) for t, x in zip(clock.velocity_epochs, prior_velocity)])
    nearest = np.abs(times[:, None] - clock.velocity_epochs[None, :]).argmin(axis=1)
    v_known = v_doppler[nearest] + prior_sample[:, 3:] - prior_velocity[nearest, 3:] + v_sun
    true_sun, true_mars = geometric_lines(times, truth_angle)
    mars = {r.frame_id: r for r in loop.records if r.kind == "radec" and r.target == "mars"}
    positions, skipped = [], dict(loop.skipped)
    sun_err, sun_chi2, mars_err, mars_chi2, sun_readings = [], [], [], [], 0
    for k, t in enumerate(times):
        frame_id = f"sample_{k:05d}"
        solved = loop.attitudes.get(f"{frame_id}:0")
        if solved is None or frame_id not in mars:
            skipped.setdefault(frame_id, "no Mars record")
            continue
        # the tracker's solution carried to the body, its covariance turned into body axes
        R_tracker, cov_tracker = Rotation.from_quat(solved[0]), np.asarray(solved[1], float)
        turn = kit.body_tracker.as_matrix()
        reading = read_sun(kit.sun, t, r_ssb[k], v_ssb[k], R_body[k], rng=kit.sun.rng(seed, k), ephemeris=ephemeris,
                           R_icrf_body_est=R_tracker * kit.body_tracker.inv(),
                           cov_att_body_rad2=turn @ cov_tracker @ turn.T, frame_id=frame_id)
        if reading.record is None:
            skipped[frame_id] = reading.reason
            continue
        sun_readings += 1
        l_ps = geometric_los(reading.record, v_known[k])
        cov_ps = reading.record.covariance
        u_mars, cov_pm = radec_line(mars[frame_id])
        l_pm = aberrate(u_mars, -v_known[k])
        for u, cov, u_true, errs, chis in ((l_ps, cov_ps, true_sun[k], sun_err, sun_chi2),
                                           (l_pm, cov_pm, true_mars[k], mars_err, mars_chi2)):
            e, chi = tangent_errors(u, u_true, cov)
            errs.append(e)
            chis.append(chi)
        positions.append(position_measurement(t, l_ps, cov_ps, l_pm, cov_pm, ephemeris=ephemeris, sensor="angle"))
    if len(positions) < 20:
        raise InputError(f"{out}: only {len(positions)} of {times.size} samples gave both lines of sight (first "
                         f"reasons: {list(skipped.values())[:3]})")
    distance = np.linalg.norm(ephemeris.position("mars", times) - r_ssb, axis=1)
    radius_km = max(body_model("mars").radii_km)
    radius = {f"sample_{k:05d}": math.asin(radius_km / d) for k, d in enumerate(distance)}
    wrong = wrong_body_check(list(mars.values()), loop.truths, radius)
    apparent = radec_errors(list(mars.values()), loop.truths).get("mars", {})
    image = {
        "samples": int(times.size), "image_step_s": settings.image_step_s, "position_records": len(positions),
        "mars_records": len(mars), "sun_readings": sun_readings, "samples_skipped": len(skipped),
        "skipped_reasons": _reason_counts(skipped),
        "achieved_noise": {"sun": _noise_figures(sun_err, sun_chi2), "mars": _noise_figures(mars_err, mars_chi2)},
        "mars_apparent_vs_frame_truth": {key: apparent[key] for key in ("count", "rms_arcsec", "mean_arcsec",
                                                                       "median_sigma_arcsec") if key in apparent},
        "mars_methods": _method_counts(list(mars.values())),
        "wrong_body": wrong,
        "tracking": {"stars_used": loop.stars_used, "stars_misidentified": loop.stars_misidentified,
                     "events": len(loop.events)},
        "chunks_reused": loop.chunks_reused,
    }
    achieved = image["achieved_noise"]
    log(f"achieved line-of-sight noise per axis: Mars {achieved['mars']['rms_per_axis_arcsec']:.3f}\", Sun "
        f"{achieved['sun']['rms_per_axis_arcsec']:.3f}\"; wrong-body records {wrong['count']}")
    velocity_error = v_known - v_sun - truth_angle[:, 3:]
    image["velocity_for_aberration_error_m_s"] = float(1e3 * np.sqrt(np.mean(np.sum(velocity_error**2, axis=1))))
    case = assemble_case(clock, x0, truth_fusion, positions, np.random.default_rng([seed, 56]), {}, dopplers=dopplers)
    sample = sample_frame(settings, seed, loop, mars, arc, Path(out))
    arrays = {"sample_t_tdb_s": times,
              "sun_error_arcsec": np.asarray(sun_err).reshape(-1, 2) / ARCSEC_RAD,
              "mars_error_arcsec": np.asarray(mars_err).reshape(-1, 2) / ARCSEC_RAD,
              "position_t_tdb_s": np.array([p.t_tdb_s for p in positions]), **sample}
    return evaluate_case(case, log, {"image_mode": image}, arrays)


def wrong_body_check(records: list[Measurement], truths: dict, radius_rad: dict) -> dict:
    """Mars records against their frames' true Mars (module notes): each must lie within
    :data:`WRONG_BODY_SIGMA` sigma of the true apparent centre (``truths``: frame id ->
    :class:`~opnav.sim.results.FrameTargets`) and inside the true disk (``radius_rad``: frame id ->
    Mars' true angular radius, rad). ``count`` of those that do not, their first frame ids, and the
    largest error in sigma and in disk radii."""
    worst_sigma, worst_radius, bad = 0.0, 0.0, []
    for record in records:
        target = truths[record.frame_id].target("mars")
        u, cov = radec_line(record)
        e, chi = tangent_errors(u, radec_to_unit(target.ra_rad, target.dec_rad), cov)
        sigmas, radii = math.sqrt(chi), float(np.linalg.norm(e)) / radius_rad[record.frame_id]
        worst_sigma, worst_radius = max(worst_sigma, sigmas), max(worst_radius, radii)
        if sigmas > WRONG_BODY_SIGMA or radii > 1.0:
            bad.append(record.frame_id)
    return {"count": len(bad), "frames": bad[:20], "checked": len(records), "worst_sigma": worst_sigma,
            "worst_disk_radii": worst_radius, "threshold_sigma": WRONG_BODY_SIGMA}


def _reason_counts(skipped: dict) -> dict:
    """How many samples each reason took (reasons with their numbers cut, to group them)."""
    counts: dict = {}
    for reason in skipped.values():
        head = str(reason).split(" (")[0]
        counts[head] = counts.get(head, 0) + 1
    return dict(sorted(counts.items(), key=lambda item: -item[1]))


def _method_counts(records: list[Measurement]) -> dict:
    counts: dict = {}
    for record in records:
        method = record.extra.get("method", "unknown")
        counts[method] = counts.get(method, 0) + 1
    return counts


def sample_frame(settings, seed: int, loop, mars: dict, arc, out: Path) -> dict:
    """The first measured camera frame drawn again by the loop from its own stream (the same pixels the
    stage measured; written to ``out/sample_frame``), cut around Mars, with the fitted and true
    centres in its pixels: the report's sample."""
    from ..render.frames_io import read_frame
    from ..sim.loop import run_frames
    from ..sim.sensors import Loop, Sky, Storage

    if not mars:
        return {}
    frame_id = min(mars)
    k = int(frame_id.split("_")[1])
    drawn = run_frames(Loop((camera_sensor(settings, None),), seed, Sky(), Storage(Path(out) / "sample_frame", 1),
                            frame_prefix="sample"), arc.part(k, k + 1))
    image = read_frame(drawn.paths[0]).image
    kit = instruments(settings)
    R_cam = arc.R_icrf_body[k] * kit.body_camera
    u_fit, _ = radec_line(mars[frame_id])
    target = loop.truths[frame_id].target("mars")
    # the fitted centre drawn through the true attitude: its offset from the truth is the whole error
    fit_xy = kit.camera.project(R_cam.inv().apply(u_fit))
    true_xy = kit.camera.project(R_cam.inv().apply(radec_to_unit(target.ra_rad, target.dec_rad)))
    half = int(min(kit.camera.width_px // 2, 60))
    x0, y0 = (int(np.clip(round(true_xy[0]) - half, 0, kit.camera.width_px - 2 * half)),
              int(np.clip(round(true_xy[1]) - half, 0, kit.camera.height_px - 2 * half)))
    return {"sample_image_adu": image[y0:y0 + 2 * half, x0:x0 + 2 * half],
            "sample_fit_xy_px": fit_xy - [x0, y0], "sample_true_xy_px": true_xy - [x0, y0],
            "sample_index": np.array(k)}
