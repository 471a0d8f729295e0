"""S2 from pixels: the capture arc's starlight angles measured on rendered frames (docs/studies.md#s2-mars-capture).

The spacecraft (:func:`body_attitude`) points its navigation camera (body +z) at Mars' apparent
direction and turns about it so that the Sun lies in the body's x-z half-plane (+x side); three
sensors are fixed on it, each mounted as the run file says (:func:`sensors`):

- the **star tracker** (boresight ``tracker_boresight_body``, ``tracker_fov_deg`` across
  ``tracker_px``): a full-frame acquisition, then tracking in windows
  (:class:`opnav.sim.stages.Tracking`): the body's attitude and its covariance. Its frames show the
  sky ``SKY_DEPTH_MAG`` fainter than its catalog, and it leaves out guide stars with a catalog
  neighbour ``NEIGHBOUR_DEPTH_MAG`` deep (as S3's star sensor): a neighbour's pull on a guide star
  lasts the hours the field takes to turn, and biased the attitude by 0.4" (1 sigma) for hours
  when every star was used (seed 2: the Mars directions' errors, time-correlated, put the MPS
  phase's NEES at 13);
- the **navigation camera** (``nav_fov_deg`` across ``nav_px``), in two exposures per epoch:
  Mars at ``mars_exposure_s`` (a disk that saturates any exposure that shows stars: measured with
  the star tracker's attitude through the mountings, :class:`opnav.sim.stages.Centre`, limb
  ellipsoid fit or cross-correlation by size and phase), and each moon at ``moon_exposure_s``
  with the camera slewed to it (the moon's frame shows stars enough for its own attitude:
  :class:`~opnav.sim.stages.FullFrame` with ``centre_finding = "by_size"``, a moon beside a
  saturated Mars fitted with Mars' pixels left out, or skipped with the reason);
- the **sun sensor** (:mod:`opnav.sim.sun_sensor`: ``sun_sensor_boresight_body``,
  ``sun_sensor_half_angle_deg``, ``sun_sensor_sigma_arcsec``), read through the star tracker's
  attitude of the same epoch.

Each measured direction (ICRF, apparent, with its covariance) becomes two starlight angles
(:func:`angle_pair`): against the two catalog stars whose angles' errors are the least correlated
(a direction has two degrees of freedom; the filters take the two angles as independent, the
residual correlation is reported). A moon's direction comes from its own frame's stars and its
angles are against stars of that frame (they hardly depend on the attitude: the stars fix it);
Mars' and the Sun's come through the star tracker's attitude (its error is in the records'
covariance) and their angles are against bright stars anywhere 20-150 deg away. The star directions are
aberrated with the true velocity (1 m/s changes them by 0.7 mas).

Epochs: every ``image_step_s`` on the switching run's grid (``step_s``) over both phases: Mars,
Phobos and Deimos before the SOI (MPD), Mars, Phobos and the Sun after it (MPS). Random streams
(:mod:`opnav.sim.loop`): tracker ``[seed, 61 | 63, k]``, Mars frames ``[seed, 62 | 64, k]``,
Phobos ``[seed, 65 | 66, k]``, Deimos ``[seed, 67 | 68, k]``, sun sensor ``[seed, 69, k]``.

The records are checked against the truth (:func:`wrong_body_count`, :func:`angle_errors`); the
measurement-mode twin (:func:`twin_records`) is the same records' epochs and stars with values
drawn about the truth at each body's achieved angle noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..constants import ARCSEC_RAD, DEG_RAD
from ..errors import InputError
from ..frames import pointing_with_sun_roll, radec_to_unit
from ..records import Measurement

#: Frames per chunk of the loop (:mod:`opnav.sim.chunks`): the unit of resumption.
CHUNK_FRAMES = 24
#: Stars a moon's angles may be formed against: catalog stars this bright ...
ANGLE_STAR_VMAG = 6.0
#: ... within this of its direction (the navigation camera's field), rad.
BODY_STAR_RADIUS_RAD = 6.0 * DEG_RAD
#: Mars and the Sun (measured through the star tracker's attitude; no star shows beside them): catalog
#: stars this bright, 20-150 deg away. Their directions' errors are far from round (the tracker's roll
#: error), so the pair whose angles' errors are uncorrelated needs stars at position angles within about a
#: degree of the error ellipse's axes: the whole sky offers them.
WIDE_STAR_VMAG = 5.0
#: Targets measured through the star tracker's attitude.
THROUGH_TRACKER = ("mars", "sun")
#: The tracker's frames show the sky this many magnitudes below its catalog limit ...
SKY_DEPTH_MAG = 1.0
#: ... and it leaves out guide stars with a catalog neighbour this deep (TrackingOptions).
NEIGHBOUR_DEPTH_MAG = 1.5
#: Frames written for inspection: every this many of a loop (the first only).
SAMPLE_FRAME_EVERY = 10**9
#: Smallest sine of the angle between two stars' angle gradients (their two angles must see two directions).
MIN_GRADIENT_SINE = 0.5


@dataclass(frozen=True)
class Sensors:
    """The S2 sensors and their mountings (sensor -> body rotations)."""

    tracker: Camera
    nav_mars: Camera
    nav_moon: Camera
    body_tracker: Rotation
    sun: object


def _mounting(boresight_body) -> Rotation:
    from ..sim.sun_sensor import mounting_from_boresight

    return mounting_from_boresight(boresight_body)


def sensors(settings) -> Sensors:
    """The star tracker, the navigation camera's two exposures and the sun sensor of ``settings``
    (:class:`opnav.studies.s2.Settings`)."""
    from ..sim.sun_sensor import sun_sensor

    nav = dict(aperture_mm=settings.nav_aperture_mm, read_noise_e=8.0)
    return Sensors(
        tracker=Camera.from_fov(settings.tracker_fov_deg, settings.tracker_px, settings.tracker_px, aperture_mm=20.0,
                                exposure_s=0.2, read_noise_e=8.0, camera_id="s2-star-tracker"),
        nav_mars=Camera.from_fov(settings.nav_fov_deg, settings.nav_px, settings.nav_px,
                                 exposure_s=settings.mars_exposure_s, camera_id="s2-nav-mars", **nav),
        nav_moon=Camera.from_fov(settings.nav_fov_deg, settings.nav_px, settings.nav_px,
                                 exposure_s=settings.moon_exposure_s, camera_id="s2-nav-moon", **nav),
        body_tracker=_mounting(settings.tracker_boresight_body),
        sun=sun_sensor(boresight_body=settings.sun_sensor_boresight_body,
                       half_angle_deg=settings.sun_sensor_half_angle_deg,
                       sigma_arcsec=settings.sun_sensor_sigma_arcsec, stream=(69,), name="sun sensor"))


def body_attitude(u_mars: np.ndarray, u_sun: np.ndarray) -> Rotation:
    """Body -> ICRF: +z on ``u_mars``, +x towards ``u_sun``'s part across it (ICRF unit vectors)."""
    return pointing_with_sun_roll(u_mars, u_sun,
                                  "S2 attitude: the Sun and Mars are in line; the body's roll is undefined")


def image_epochs(trajectory, settings) -> tuple[np.ndarray, np.ndarray]:
    """Image epochs of phase 1 and phase 2 (TDB s): every ``image_step_s`` of the switching run's epochs."""
    from .s2_observability import s2_arc_epochs

    every = int(round(settings.image_step_s / settings.step_s))
    stop = 3600.0 * settings.stop_before_periapsis_h
    one = s2_arc_epochs(trajectory, 1, arc_days=settings.arc_days, stop_before_periapsis_s=stop)
    two = s2_arc_epochs(trajectory, 2, arc_days=settings.arc_days, stop_before_periapsis_s=stop)
    two = two[two > trajectory.t_soi_tdb_s]
    return one[::every], two[::every]


def _tangent_basis(u: np.ndarray) -> np.ndarray:
    """(3, 2): east and north unit vectors at the unit vector ``u``."""
    east = np.array([-u[1], u[0], 0.0])
    east /= np.linalg.norm(east)
    return np.column_stack([east, np.cross(u, east)])


def tangent_covariance(record: Measurement) -> tuple[np.ndarray, np.ndarray]:
    """(unit vector, 2 x 2 covariance in its east-north tangent plane, rad^2) of a ``radec`` or ``los`` record."""
    if record.kind == "radec":
        ra, dec = record.value
        u = radec_to_unit(ra, dec)
        scale = np.diag([np.cos(dec), 1.0])
        return u, scale @ record.covariance @ scale
    if record.kind == "los":
        u = np.asarray(record.value, float) / np.linalg.norm(record.value)
        basis = _tangent_basis(u)
        return u, basis.T @ record.covariance @ basis
    raise InputError(f"S2 angles are formed from radec or los records, got {record.kind!r}")


def angle_pair(record: Measurement, stars_icrf: np.ndarray, stars_apparent: np.ndarray,
               star_ids: np.ndarray) -> tuple[list[Measurement], float]:
    """Two ``starlight_angle`` records of ``record``'s direction and the correlation of their errors.

    ``stars_icrf`` (S, 3) are the candidates' astrometric directions (what the records carry; the
    model aberrates them), ``stars_apparent`` (S, 3) what the observer sees (the angle is measured
    against them). The pair kept is the one whose angle errors, through the direction's covariance,
    are the least correlated among pairs whose gradients are at least ``asin(MIN_GRADIENT_SINE)``
    apart. Raises ``InputError`` with fewer than two usable stars.
    """
    u, cov = tangent_covariance(record)
    basis = _tangent_basis(u)
    theta = np.arccos(np.clip(stars_apparent @ u, -1.0, 1.0))
    # d theta / d u in the tangent plane: away from the star
    grads = -(stars_apparent @ basis) / np.sin(theta)[:, None]
    variance = np.einsum("si,ij,sj->s", grads, cov, grads)
    norms = np.linalg.norm(grads, axis=1)
    sine = np.abs(np.outer(grads[:, 0], grads[:, 1]) - np.outer(grads[:, 1], grads[:, 0])) / np.outer(norms, norms)
    rho = np.abs(grads @ cov @ grads.T) / np.sqrt(np.outer(variance, variance))
    rho[np.tril_indices(len(theta))] = np.inf  # each pair once, never a star with itself
    rho[sine < MIN_GRADIENT_SINE] = np.inf
    pair = None
    if len(theta) >= 2 and np.isfinite(rho).any():
        pair = np.unravel_index(int(np.argmin(rho)), rho.shape)
        best = float(rho[pair])
    if pair is None:
        raise InputError(f"{record.target} at {record.t_tdb_s}: fewer than two stars to form starlight angles against")
    out = [Measurement(record.t_tdb_s, "starlight_angle", [float(theta[i])], [[float(variance[i])]],
                       target=record.target, sensor=record.sensor, frame_id=record.frame_id,
                       star_id=int(star_ids[i]), star_unit_icrf=stars_icrf[i]) for i in pair]
    return out, float(best)


def _candidates(catalog, u: np.ndarray, *, wide: bool) -> np.ndarray:
    """Catalog rows of the stars an angle to direction ``u`` may use (module constants)."""
    units = catalog.unit_vectors()
    cos = units @ u
    if wide:
        keep = (catalog.vmag <= WIDE_STAR_VMAG) & (cos < np.cos(20.0 * DEG_RAD)) & (cos > np.cos(150.0 * DEG_RAD))
    else:
        keep = (catalog.vmag <= ANGLE_STAR_VMAG) & (cos > np.cos(BODY_STAR_RADIUS_RAD)) & (cos < np.cos(0.2 * DEG_RAD))
    return np.flatnonzero(keep)


def angles_of(records, catalog, observers: dict) -> tuple[list[Measurement], list[float]]:
    """Starlight angles (:func:`angle_pair`) of every ``radec`` and ``los`` record; ``observers`` maps an
    epoch (TDB s) to the observer's (SSB position km, velocity km/s), ICRF."""
    angles, correlations = [], []
    for record in records:
        if record.kind not in ("radec", "los"):
            continue
        u, _ = tangent_covariance(record)
        rows = _candidates(catalog, u, wide=record.target in THROUGH_TRACKER)
        r, v = observers[record.t_tdb_s]
        state = dict(t_tdb_s=record.t_tdb_s, r_observer_ssb_km=r, v_observer_ssb_km_s=v)
        pair, rho = angle_pair(record, catalog.apparent_directions(rows, **state, aberration=False),
                               catalog.apparent_directions(rows, **state), catalog.star_id[rows])
        angles += pair
        correlations.append(rho)
    return angles, correlations


@dataclass(frozen=True)
class Measured:
    """What the frames gave: the angle records, each direction record, the loops' results, the
    sun sensor's refusals and the angle pairs' residual correlations."""

    angles: tuple
    directions: tuple
    loops: dict
    sun_skipped: dict
    correlations: tuple


def measure_arc(settings, seed: int, trajectory, out: Path, *, progress: bool = False, workers: int = 1) -> Measured:
    """Render and measure the image epochs of both phases (module notes)."""
    from ..catalog import load_catalog
    from ..image.pipeline import PipelineOptions
    from ..light import apparent_direction
    from ..render.frame import RenderOptions
    from ..sim.chunks import run_chunks
    from ..sim.pointing import PointingLaw
    from ..sim.sensors import Arc, Loop, Sensor, Sky, Storage, Streams, loop_sources
    from ..image.tracking import TrackingOptions
    from ..sim.stages import Centre, FullFrame, Tracking
    from ..sim.sun_sensor import read_sun

    kit = sensors(settings)
    _, ephemeris, _ = loop_sources(Sky(), catalog=False)
    one, two = image_epochs(trajectory, settings)
    epochs = np.concatenate([one, two])
    rows = np.searchsorted(trajectory.t_tdb_s, epochs)
    r_mars, v_mars = ephemeris.state("mars", epochs)
    r_ssb = r_mars + trajectory.states_mars[rows, :3]
    v_ssb = v_mars + trajectory.states_mars[rows, 3:]
    attitudes = []
    for t, r, v in zip(epochs, r_ssb, v_ssb):
        u_mars = apparent_direction(lambda e: ephemeris.position("mars", e), t, r, v)
        u_sun = apparent_direction(lambda e: ephemeris.position("sun", e), t, r, v)
        attitudes.append(body_attitude(u_mars, u_sun))
    body = Rotation.concatenate(attitudes)
    psf = RenderOptions().psf
    moon_render = RenderOptions(vmag_limit=settings.nav_vmag_limit + 1.0, supersample=2, sun_keepout_margin_rad=0.0)
    tracker = Sensor(kit.tracker, Tracking(PipelineOptions(vmag_limit=settings.tracker_vmag_limit, sensor="tracker"),
                                           TrackingOptions(neighbour_depth_mag=NEIGHBOUR_DEPTH_MAG)),
                     mounting=kit.body_tracker, name="star tracker", streams=Streams((61,), (63,)),
                     render=RenderOptions(vmag_limit=settings.tracker_vmag_limit + SKY_DEPTH_MAG,
                                          sun_keepout_margin_rad=0.0))
    mars = Sensor(kit.nav_mars, Centre("mars", 0, psf.sigma_px, sensor="nav"), mounting=Rotation.identity(),
                  targets=("mars", "phobos", "deimos"), stars=False, name="navigation camera (Mars)",
                  streams=Streams((62,), (64,)), render=RenderOptions(supersample=2, sun_keepout_margin_rad=0.0))
    key = repr((settings, seed))
    # the first frame of each loop is written for the report (SAMPLE_FRAME_EVERY: no other)
    storage = Storage(Path(out) / "frames", SAMPLE_FRAME_EVERY)
    results = {"mars": run_chunks(Loop((tracker, mars), seed, Sky(), storage, frame_prefix="mars"), Arc(epochs, r_ssb, v_ssb, body),
                                  folder=Path(out) / "stream_mars", key=key + repr((SKY_DEPTH_MAG, NEIGHBOUR_DEPTH_MAG)), chunk_frames=CHUNK_FRAMES, workers=workers,
                                  progress=progress, unit="epoch", name="s2_mars")}
    for moon, stream, span in (("phobos", (65,), slice(None)), ("deimos", (67,), slice(0, len(one)))):
        stage = FullFrame(PipelineOptions(targets=(moon,), vmag_limit=settings.nav_vmag_limit, centre_finding="by_size",
                                          sensor="nav"))
        sensor = Sensor(kit.nav_moon, stage, pointing=PointingLaw(law="target", target=moon),
                        targets=("mars", "phobos", "deimos"), name=f"navigation camera ({moon})",
                        streams=Streams(stream, (stream[0] + 1,)), render=moon_render)
        arc = Arc(epochs[span], r_ssb[span], v_ssb[span])
        results[moon] = run_chunks(Loop((sensor,), seed, Sky(), storage, frame_prefix=moon), arc,
                                   folder=Path(out) / f"stream_{moon}", key=key, chunk_frames=CHUNK_FRAMES,
                                   workers=workers, progress=progress, unit="epoch", name=f"s2_{moon}")
    directions = [r for result in results.values() for r in result.records if r.kind == "radec"]
    # the Sun after the SOI, read through the star tracker's attitude of the same epoch
    sun_skipped = {}
    for k in range(len(one), len(epochs)):
        frame_id = f"mars_{k:05d}"
        solved = results["mars"].attitudes.get(f"{frame_id}:0")
        if solved is None:
            sun_skipped[frame_id] = "sun sensor: no star-tracker attitude at this epoch"
            continue
        turn = kit.body_tracker.as_matrix()
        R_est = Rotation.from_quat(solved[0]) * kit.body_tracker.inv()
        cov_body = turn @ np.asarray(solved[1]) @ turn.T
        reading = read_sun(kit.sun, epochs[k], r_ssb[k], v_ssb[k], body[k], rng=kit.sun.rng(seed, k),
                           ephemeris=ephemeris, R_icrf_body_est=R_est, cov_att_body_rad2=cov_body, frame_id=frame_id)
        if reading.record is None:
            sun_skipped[frame_id] = reading.reason
        else:
            directions.append(reading.record)
    keep = {t: "MPD" for t in one} | {t: "MPS" for t in two}
    sets = {"MPD": ("mars", "phobos", "deimos"), "MPS": ("mars", "phobos", "sun")}
    directions = [r for r in directions if r.target in sets[keep[r.t_tdb_s]]]
    observers = {float(t): (r, v) for t, r, v in zip(epochs, r_ssb, v_ssb)}
    angles, correlations = angles_of(directions, load_catalog(), observers)
    return Measured(tuple(angles), tuple(directions), results, sun_skipped, tuple(correlations))


#: A direction record whose error's chi-square (2 dof, its own covariance) exceeds this is a gross error.
GROSS_CHI2 = 27.63  # the 1 - 1e-6 quantile of chi-square(2)


def wrong_body_count(directions, trajectory) -> dict:
    """Per target, the direction records nearer another body's true apparent centre than their own's
    (Mars, Phobos, Deimos; from the trajectory's true state), those with a gross error (the right body
    fitted badly: chi-square above :data:`GROSS_CHI2`), and the largest error, arcsec."""
    from ..ephemeris import default_ephemeris
    from ..light import apparent_direction

    ephemeris = default_ephemeris()
    bodies = ("mars", "phobos", "deimos")
    out: dict = {}
    for record in directions:
        if record.target == "sun":
            continue
        u, _ = tangent_covariance(record)
        row = int(np.searchsorted(trajectory.t_tdb_s, record.t_tdb_s))
        r_mars, v_mars = ephemeris.state("mars", record.t_tdb_s)
        r, v = r_mars + trajectory.states_mars[row, :3], v_mars + trajectory.states_mars[row, 3:]
        miss = {b: float(np.arccos(np.clip(u @ apparent_direction(lambda e, b=b: ephemeris.position(b, e),
                                                                  record.t_tdb_s, r, v), -1.0, 1.0)))
                for b in bodies}
        entry = out.setdefault(record.target, {"records": 0, "wrong_body": 0, "gross_errors": 0,
                                               "max_error_arcsec": 0.0})
        entry["records"] += 1
        u_cov = tangent_covariance(record)[1]
        truth = apparent_direction(lambda e: ephemeris.position(record.target, e), record.t_tdb_s, r, v)
        d = _tangent_basis(u).T @ (truth - u)
        entry["gross_errors"] += int(d @ np.linalg.solve(u_cov, d) > GROSS_CHI2)
        entry["wrong_body"] += int(min(miss, key=miss.get) != record.target)
        entry["max_error_arcsec"] = max(entry["max_error_arcsec"], miss[record.target] / ARCSEC_RAD)
    return out


def angle_errors(angles, trajectory) -> dict:
    """Per target, the angle records' errors against the truth's prediction (light time and aberration,
    the exact ephemeris): count, RMS, mean and median reported sigma (arcsec), chi-square per record."""
    from ..measurements import ProbeMeasurementModel

    model = ProbeMeasurementModel("sun")
    out = {}
    for name in sorted({a.target for a in angles}):
        mine = [a for a in angles if a.target == name]
        errors = np.array([a.value[0] - model.predict(a, trajectory.state_at(a.t_tdb_s, "sun"))[0] for a in mine])
        sigmas = np.sqrt([a.covariance[0, 0] for a in mine])
        out[name] = {"count": len(mine), "rms_arcsec": float(np.sqrt(np.mean(errors**2)) / ARCSEC_RAD),
                     "mean_arcsec": float(np.mean(errors) / ARCSEC_RAD),
                     "median_sigma_arcsec": float(np.median(sigmas) / ARCSEC_RAD),
                     "chi2_mean": float(np.mean((errors / sigmas) ** 2))}
    return out


def twin_records(angles, trajectory, sigma_rad: dict, rng: np.random.Generator) -> list[Measurement]:
    """The measurement-mode twin: each angle record's epoch, target and star with the truth's value plus
    Gaussian noise of its target's ``sigma_rad`` (the achieved noise), and that variance."""
    from ..measurements import ProbeMeasurementModel

    model = ProbeMeasurementModel("sun")
    out = []
    for a in angles:
        sigma = sigma_rad[a.target]
        value = model.predict(a, trajectory.state_at(a.t_tdb_s, "sun"))[0] + sigma * rng.standard_normal()
        out.append(Measurement(a.t_tdb_s, "starlight_angle", [value], [[sigma**2]], target=a.target,
                               sensor="twin", star_id=a.star_id, star_unit_icrf=a.star_unit_icrf))
    return out


def sample_frame(path: Path, body: str, record: Measurement | None, half_px: int = 60) -> dict:
    """A written frame around ``body`` for the report: the crop (ADU), the body's true centre and the
    measured one (``record``'s direction through the frame's true attitude; NaN without a record), px
    in the crop, and the title. ``path``: a frame the loop wrote with its truth sidecar."""
    from ..image.header import camera_from_header, wcs_attitude
    from ..render.frames_io import read_frame

    stored = read_frame(path)
    camera = camera_from_header(stored.header, stored.image.shape, str(path))
    R_icrf_cam, _, _ = wcs_attitude(stored.header, str(path))
    target = stored.truth.target(body)
    true_xy = camera.project(R_icrf_cam.inv().apply(radec_to_unit(target.ra_rad, target.dec_rad)))
    measured = np.full(2, np.nan) if record is None else camera.project(
        R_icrf_cam.inv().apply(tangent_covariance(record)[0]))
    x0 = int(np.clip(round(true_xy[0]) - half_px, 0, camera.width_px - 2 * half_px - 1))
    y0 = int(np.clip(round(true_xy[1]) - half_px, 0, camera.height_px - 2 * half_px - 1))
    crop = stored.image[y0:y0 + 2 * half_px + 1, x0:x0 + 2 * half_px + 1]
    return {"image": np.asarray(crop, float), "true_xy": true_xy - [x0, y0], "measured_xy": measured - [x0, y0],
            "title": f"{target.name}: {path.name}" + (f" ({record.extra.get('method', 'point')})" if record else "")}
