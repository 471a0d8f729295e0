"""A mission from pixels: its targets' centres measured on rendered frames (docs/mission.md#image-mode).

The spacecraft carries two sensors on one body, mounted as the run file's ``[settings]`` say:

- the **navigation camera** (``camera_fov_deg`` across ``camera_px``, ``camera_aperture_mm``, each frame's
  exposure by ``camera_exposure_law``: :mod:`opnav.studies.mission_exposure`) is the body frame: its
  boresight is body +z, its +x body +x; the frames of one exposure setting run as one loop;
- the **star tracker** (``tracker_fov_deg`` across ``tracker_px``, catalog to ``tracker_vmag_limit``) looks
  along ``tracker_boresight_body`` (:func:`opnav.sim.sun_sensor.mounting_from_boresight`).

**Pointing law** (:func:`body_attitude`): at each record epoch the body turns the camera to each target
in turn: boresight on the target's apparent centre (light time and aberration, as the renderer has
them), roll such that the Sun lies in the camera's x-z half-plane on the +x side (so the tracker,
mounted away from +x, looks away from the Sun). The turn between two targets is not simulated: each
target has its own loop of frames, one per epoch, with its own tracker (a full-frame acquisition, then
tracking in windows, :class:`opnav.sim.stages.Tracking`; guide stars with a catalog neighbour
``NEIGHBOUR_DEPTH_MAG`` deep left out, as S2's and S3's trackers).

**Attitude from a CK** (``attitude = "ck"``, :func:`ck_pointing`): the navigation camera's attitude at
each epoch is that of ``ck_frame`` read from the CK among ``kernels`` (:func:`opnav.ephemeris.ck.ck_attitude`:
a CK frame, or a camera frame an FK mounts on one; its axes are the camera's), the same for every
target; a target is imaged at the epochs its whole disk lies on the camera's detector (:func:`in_view`),
and each target keeps its own loop of frames.

**Measurement** (:class:`opnav.sim.stages.Centre`): the navigation frame shows the resolved, phased
body (its :class:`~opnav.bodies.Body` from :func:`opnav.studies.mission.mission_bodies`) and the
other targets against stars; the body's centre is found by :func:`opnav.image.centres.measure_body_centre`
(limb ellipsoid fit or cross-correlation, chosen by size and phase) with the tracker's attitude turned
through the mountings; the record is the centre's apparent RA/Dec with the covariance the stage gives
(the fit's and the tracker's attitude covariance). A target whose disk's angular radius exceeds
:data:`FILL_LIMIT` of the camera's half field (the Earth in the first hours of a lunar transfer), or
that is point-like (fewer than a few pixels across), is not measured at that epoch: the reason is
listed. Both sensors' frames draw every target, so a body across the tracker's field costs that
epoch's attitude (listed).

**Checks** (:func:`check_records`): every record against the truth's apparent directions of every
target: a record nearer another target's centre than its own is a wrong-body record; one whose error's
chi-square (2 dof, its own covariance) exceeds :data:`GROSS_CHI2` a gross error; per target the
achieved noise (RMS of the RA cos(Dec) and Dec errors), the median reported sigma and the mean
chi-square per axis.

Random streams (:mod:`opnav.sim.loop`): target ``i`` of ``targets``: tracker ``[seed, 70 + 4 i, k]``
(render) and ``[seed, 71 + 4 i, k]`` (stage), camera ``[seed, 72 + 4 i, k]`` and ``[seed, 73 + 4 i, k]``.
Vectors: ICRF; observer states relative to the SSB, km and km/s; epochs TDB seconds past J2000.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..constants import ARCSEC_RAD
from ..epochs import describe_epoch
from ..errors import InputError
from ..frames import pointing_with_sun_roll

#: Frames per chunk of the loop (:mod:`opnav.sim.chunks`): the unit of resumption and of work per process.
CHUNK_FRAMES = 24
#: A target is imaged while its disk's angular radius is below this fraction of the camera's half field.
FILL_LIMIT = 0.8
#: The tracker's frames show the sky this many magnitudes below its catalog limit ...
SKY_DEPTH_MAG = 1.0
#: ... and it leaves out guide stars with a catalog neighbour this deep (TrackingOptions).
NEIGHBOUR_DEPTH_MAG = 1.5
#: A record whose error's chi-square (2 dof) exceeds this is a gross error: the 1 - 1e-6 quantile.
GROSS_CHI2 = 27.63
#: First stream of target 0 (module notes).
STREAM_BASE = 70


@dataclass(frozen=True)
class Kit:
    """The mission's sensors: the star tracker, the navigation camera per target (its exposure), and
    the tracker's mounting (tracker -> body rotation; the body frame is the camera's)."""

    tracker: Camera
    cameras: dict
    body_tracker: Rotation


def navigation_camera(settings, target: str, exposure_s: float) -> Camera:
    """The navigation camera of ``settings`` exposed for ``exposure_s`` (s) on ``target``."""
    return Camera.from_fov(settings.camera_fov_deg, settings.camera_px, settings.camera_px,
                           aperture_mm=settings.camera_aperture_mm, exposure_s=exposure_s, read_noise_e=8.0,
                           camera_id=f"mission-navcam-{target}")


def sensors(settings) -> Kit:
    """The star tracker and the navigation camera of ``settings`` (:class:`opnav.studies.mission.Settings`;
    the cameras with the targets' ``camera_exposure_s``)."""
    from ..sim.sun_sensor import mounting_from_boresight
    from .mission import target_exposure_s

    exposure = target_exposure_s(settings)
    cameras = {target: navigation_camera(settings, target, exposure[target]) for target in settings.targets}
    tracker = Camera.from_fov(settings.tracker_fov_deg, settings.tracker_px, settings.tracker_px, aperture_mm=20.0,
                              exposure_s=0.2, read_noise_e=8.0, camera_id="mission-star-tracker")
    return Kit(tracker, cameras, mounting_from_boresight(settings.tracker_boresight_body))


def body_attitude(u_target: np.ndarray, u_sun: np.ndarray) -> Rotation:
    """Body (= camera) -> ICRF: +z on ``u_target``, +x towards ``u_sun``'s part across it (ICRF unit vectors).

    Raises ``InputError`` when the target and the Sun are in line (the roll is undefined)."""
    return pointing_with_sun_roll(u_target, u_sun,
                                  "mission pointing: a target and the Sun are in line; the camera's roll is undefined")


def pointing(target: str, epochs: np.ndarray, r_ssb: np.ndarray, v_ssb: np.ndarray, ephemeris) -> tuple[Rotation, np.ndarray]:
    """(body attitudes (M), the target's distance at each epoch, km) of the pointing law for ``target``."""
    from ..light import apparent_direction

    u, distance = target_directions(target, epochs, r_ssb, v_ssb, ephemeris)
    attitudes = [body_attitude(u_k, apparent_direction(lambda e: ephemeris.position("sun", e), t, r, v))
                 for u_k, t, r, v in zip(u, epochs, r_ssb, v_ssb)]
    return Rotation.concatenate(attitudes), distance


def target_directions(target: str, epochs: np.ndarray, r_ssb: np.ndarray, v_ssb: np.ndarray,
                      ephemeris) -> tuple[np.ndarray, np.ndarray]:
    """(apparent unit directions of ``target``'s centre (M, 3), ICRF, light time and aberration as the
    renderer has them; its geometric distance (M,), km) from the observer states ``r_ssb``, ``v_ssb``."""
    from ..light import apparent_direction

    u, distance = np.zeros((len(epochs), 3)), np.zeros(len(epochs))
    for i, (t, r, v) in enumerate(zip(epochs, r_ssb, v_ssb)):
        u[i] = apparent_direction(lambda e: ephemeris.position(target, e), t, r, v)
        distance[i] = float(np.linalg.norm(ephemeris.position(target, t) - r))
    return u, distance


def ck_pointing(settings, epochs: np.ndarray) -> Rotation:
    """The navigation camera's attitudes (camera -> ICRF, M) at ``epochs`` (TDB s) from the CK: ``ck_frame``
    of the kernels over DE421 (:func:`opnav.ephemeris.ck.ck_attitude`, ``ck_tolerance_s``)."""
    from ..ephemeris.ck import ck_attitude
    from ..ephemeris.spice import KernelError
    from .mission import truth_ephemeris

    try:
        return ck_attitude(truth_ephemeris(settings).kernels, settings.ck_frame, np.asarray(epochs, dtype=float),
                           tolerance_s=settings.ck_tolerance_s)
    except KernelError as exc:
        raise InputError(f"ck_frame: {exc}") from None


def in_view(camera: Camera, R_icrf_cam: Rotation, u_icrf: np.ndarray, radius_rad: np.ndarray) -> np.ndarray:
    """(M,) bool: the disk of angular radius ``radius_rad`` about each direction ``u_icrf`` (M, 3) lies on
    ``camera``'s detector at attitudes ``R_icrf_cam`` (M), with 2 px to spare for the PSF."""
    xy = camera.project(R_icrf_cam.inv().apply(u_icrf))  # NaN behind the camera: not in view
    return camera.in_frame(xy, margin_px=np.asarray(radius_rad, dtype=float) / camera.pixel_scale_rad + 2.0)


@dataclass(frozen=True)
class Measured:
    """What the frames gave: the records (time order), each target's loop result (frame ``<target>_<k>``
    is its ``k``-th imaged epoch), the epochs at which a target was not imaged ("<target> at <epoch>"
    -> reason), and each target's navigation-camera exposure at its imaged epochs (s)."""

    records: tuple
    loops: dict
    not_imaged: dict
    exposures: dict


def exposure_runs(exposures: np.ndarray) -> list[tuple[int, int]]:
    """``(first, stop)`` of each run of equal consecutive ``exposures``, in order."""
    cuts = np.flatnonzero(np.diff(exposures) != 0.0) + 1
    edges = [0, *cuts.tolist(), len(exposures)]
    return list(zip(edges[:-1], edges[1:]))


def measure(settings, seed: int, epochs: np.ndarray, r_ssb: np.ndarray, v_ssb: np.ndarray, out: Path, *,
            key: str, progress: bool = False, workers: int = 1) -> Measured:
    """Render and measure every target at every epoch (module notes); ``r_ssb``, ``v_ssb`` (M, 3) the true
    observer states (SSB, ICRF, km and km/s) at ``epochs`` (TDB s past J2000)."""
    from ..image.pipeline import PipelineOptions
    from ..image.tracking import TrackingOptions
    from ..render.frame import RenderOptions
    from ..sim.chunks import run_chunks
    from ..sim.results import LoopResult
    from ..sim.sensors import Arc, Loop, Sensor, Sky, Storage, Streams, loop_sources
    from ..sim.stages import Centre, Tracking
    from .mission import mission_bodies
    from .mission_exposure import frame_exposures

    kit = sensors(settings)
    bodies = mission_bodies(settings)
    drawn = tuple(bodies.values())
    sky = Sky(kernels=tuple(settings.kernels))
    _, ephemeris, _ = loop_sources(sky, catalog=False)
    psf = RenderOptions().psf
    # no frame written: a target behind a camera leaves NaN pixels in the frame's truth sidecar, which JSON refuses
    storage = Storage()
    tracker_stage = Tracking(PipelineOptions(vmag_limit=settings.tracker_vmag_limit, sensor="tracker"),
                             TrackingOptions(neighbour_depth_mag=NEIGHBOUR_DEPTH_MAG))
    records, loops, not_imaged, exposures = [], {}, {}, {}
    from_ck = ck_pointing(settings, epochs) if settings.attitude == "ck" else None
    for i, target in enumerate(settings.targets):
        camera = kit.cameras[target]
        if from_ck is None:
            body, distance = pointing(target, epochs, r_ssb, v_ssb, ephemeris)
        else:
            body = from_ck
            u, distance = target_directions(target, epochs, r_ssb, v_ssb, ephemeris)
        model = bodies[target]
        half_field = 0.5 * min(camera.width_px, camera.height_px) * camera.pixel_scale_rad
        angular = np.arcsin(np.clip(max(model.radii_km) / distance, 0.0, 1.0))
        fits = angular < FILL_LIMIT * half_field
        for k in np.flatnonzero(~fits):
            not_imaged[f"{target} at {describe_epoch(epochs[k])}"] = (
                f"fills the frame (angular radius {np.degrees(angular[k]):.1f} deg; imaged below {FILL_LIMIT:g} "
                "of the half field)")
        if from_ck is not None:
            seen = in_view(camera, body, u, angular)
            for k in np.flatnonzero(fits & ~seen):
                not_imaged[f"{target} at {describe_epoch(epochs[k])}"] = (
                    f"off the navigation camera's detector at the CK's attitude ({settings.ck_frame}; imaged when "
                    "its whole disk is on it)")
            fits &= seen
        rows = np.flatnonzero(fits)
        if rows.size == 0:
            continue
        base = STREAM_BASE + 4 * i
        tracker = Sensor(kit.tracker, tracker_stage, mounting=kit.body_tracker, targets=drawn, name="star tracker",
                         streams=Streams((base,), (base + 1,)),
                         render=RenderOptions(vmag_limit=settings.tracker_vmag_limit + SKY_DEPTH_MAG,
                                              sun_keepout_margin_rad=0.0))
        arc = Arc(epochs[rows], r_ssb[rows], v_ssb[rows], body[rows])
        exposure = frame_exposures(settings, target, model, camera, arc.R_icrf_body, arc.t_tdb_s, arc.r_ssb_km,
                                   arc.v_ssb_km_s, ephemeris, psf.sigma_px)
        exposures[target] = exposure
        jobs = []
        # one loop per run of frames at one exposure (the camera is the sensor's); frame k of a target's
        # loop is its k-th imaged epoch whatever the run, so its random streams do not depend on the runs
        for first, stop in exposure_runs(exposure):
            navcam = Sensor(navigation_camera(settings, target, float(exposure[first])),
                            Centre(target, 0, psf.sigma_px, sensor="navcam", model=model),
                            mounting=Rotation.identity(), targets=drawn, name=f"navigation camera ({target})",
                            streams=Streams((base + 2,), (base + 3,)),
                            render=RenderOptions(supersample=2, sun_keepout_margin_rad=0.0))
            jobs.append(dict(loop=Loop((tracker, navcam), seed, sky, storage, frame_prefix=target),
                             arc=arc.part(first, stop), folder=Path(out) / f"stream_{target}",
                             key=f"{key}:{target}:{exposure[first]!r}", chunk_frames=CHUNK_FRAMES, unit="epoch",
                             name=f"mission_{target}" if first == 0 else f"mission_{target}_from{first:05d}"))
        if len(jobs) == 1:
            result = run_chunks(**jobs[0], workers=workers, progress=progress)
        else:
            parts = _run_parts(jobs, workers, progress)
            result = LoopResult.combine(parts, chunks_reused=sum(p.chunks_reused for p in parts))
        loops[target] = result
        records += [r for r in result.records if r.kind == "radec"]
    records.sort(key=lambda r: r.t_tdb_s)  # stable: an epoch's targets in the order listed
    return Measured(tuple(records), loops, not_imaged, exposures)


def _run_parts(jobs: list[dict], workers: int, progress: bool) -> list:
    """:func:`opnav.sim.chunks.run_chunks` of each job (its keyword arguments), in order: in this process
    with one worker (a progress bar per job when asked), else the jobs spread over ``workers`` spawned
    processes without one (a run of a few frames at one exposure is one chunk, which run_chunks alone
    would not spread)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from ..sim.chunks import run_chunks

    if workers <= 1:
        return [run_chunks(**job, progress=progress) for job in jobs]
    # spawned, not forked, as run_chunks' own workers: the parent may hold numba's thread pool
    with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=multiprocessing.get_context("spawn"),
                             initializer=_part_worker) as pool:
        return list(pool.map(_run_job, jobs))


def _run_job(job: dict):
    from ..sim.chunks import run_chunks

    return run_chunks(**job)


def _part_worker() -> None:
    """A part's process runs compiled kernels on one thread (the processes fill the cores)."""
    from ..allocator import keep_freed_memory
    from ..compiled import use_one_thread

    use_one_thread()
    keep_freed_memory()


def check_records(records, epochs: np.ndarray, truth: np.ndarray, model, targets: tuple[str, ...]) -> dict:
    """Per target: records, wrong-body records (nearer another target's true apparent centre than their
    own's), gross errors (chi-square above :data:`GROSS_CHI2`), the largest error (arcsec), the achieved
    noise (RMS of the RA cos(Dec) and Dec errors, arcsec), the median reported sigma (arcsec) and the
    mean chi-square per axis. ``truth`` (M, 6) the true states at ``epochs`` relative to ``model.center``
    (``model``: a :class:`~opnav.measurements.ProbeMeasurementModel` on the truth's ephemeris)."""
    from dataclasses import replace

    from ..frames import angle_between, radec_to_unit

    row = {float(t): i for i, t in enumerate(epochs)}
    out: dict = {}
    errors: dict = {target: [] for target in targets}
    for record in records:
        state = truth[row[float(record.t_tdb_s)]]
        u = radec_to_unit(*record.value)
        miss = {}
        for other in targets:
            predicted = model.predict(replace(record, target=other), state)
            miss[other] = float(angle_between(u, radec_to_unit(*predicted)))
        truth_value = model.predict(record, state)
        d = np.array([np.angle(np.exp(1j * (record.value[0] - truth_value[0]))), record.value[1] - truth_value[1]])
        chi2 = float(d @ np.linalg.solve(record.covariance, d))
        entry = out.setdefault(record.target, {"records": 0, "wrong_body": 0, "gross_errors": 0,
                                               "max_error_arcsec": 0.0})
        entry["records"] += 1
        entry["wrong_body"] += int(min(miss, key=miss.get) != record.target)
        entry["gross_errors"] += int(chi2 > GROSS_CHI2)
        entry["max_error_arcsec"] = max(entry["max_error_arcsec"], miss[record.target] / ARCSEC_RAD)
        cos_dec = np.cos(truth_value[1])
        errors[record.target].append((d[0] * cos_dec, d[1], np.sqrt(record.covariance[0, 0]) * cos_dec,
                                      np.sqrt(record.covariance[1, 1]), chi2))
    for target, rows in errors.items():
        if not rows:
            continue
        e = np.array(rows)
        out[target].update({
            "rms_ra_cos_dec_arcsec": float(np.sqrt(np.mean(e[:, 0] ** 2)) / ARCSEC_RAD),
            "rms_dec_arcsec": float(np.sqrt(np.mean(e[:, 1] ** 2)) / ARCSEC_RAD),
            "achieved_noise_arcsec": float(np.sqrt(np.mean(e[:, :2] ** 2)) / ARCSEC_RAD),
            "median_sigma_arcsec": float(np.median(e[:, 2:4]) / ARCSEC_RAD),
            "chi2_per_axis": float(np.mean(e[:, 4]) / 2.0)})
    return out


__all__ = ["CHUNK_FRAMES", "FILL_LIMIT", "GROSS_CHI2", "Kit", "Measured", "body_attitude", "check_records",
           "ck_pointing", "exposure_runs", "in_view", "measure", "navigation_camera", "pointing", "sensors",
           "target_directions"]
