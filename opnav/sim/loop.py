"""The render -> measure loop: a list of sensors along an arc, frame by frame, to records.

The one loop for every use: ``opnav render`` (frames written, no image stage), ``opnav demo`` and
S1 image mode (the demo camera tracking Phobos; frames on disk or in memory), S3 image mode (a
star sensor and a UV Earth-limb sensor on one Earth-pointing body), S2 image mode (a star tracker
and a navigation camera exposed for Mars on one body; the camera slewed to each moon). For each
frame ``k`` of the :class:`~opnav.sim.sensors.Arc` (``k`` counts from the arc's start, whatever
the chunk):

1. The study's :class:`~opnav.sim.sensors.FrameHook` may declare the frame lost (no sensor sees it).
2. The observer's true state (SSB, ICRF) and each sensor's true attitude: its own pointing law
   (:mod:`opnav.sim.pointing`, with the body rate that smears the stars) or the body's attitude
   times the sensor's mounting. The hook may give the image stage another a-priori attitude.
3. Render, in memory or to disk (:class:`~opnav.sim.sensors.Storage`): in full; in the windows a tracking stage
   will read while it holds lock; or, for a limb stage, in the annulus where another sensor's
   attitude solution predicts the limb (:mod:`opnav.sim.stages`); a centre stage's frame in full,
   measured with another sensor's attitude solution (a frame exposed for a bright body shows no stars). The hook may change what is
   drawn (detector, catalog, ephemeris) and the readout (a mirrored camera).
4. Measure with the sensor's stage; a frame whose stage fails, or gives no star-identified
   attitude, gives no records and is listed with its reason. Sensors run in list order, so a
   limb sensor uses its reference sensor's solution of the same frame.

Random streams
--------------
Every draw of frame ``k`` comes from a generator of its own, so a frame does not depend on which
others were run in the same call, chunk or process:

==========================  ==================================================
render noise of sensor s    ``default_rng([seed, *s.streams.render, k])``
its image stage             ``default_rng([seed, *s.streams.measure, k])``
the study's hook            its own streams (S1's frame faults: ``[seed, 92..96, ...]``)
==========================  ==================================================

The default :class:`~opnav.sim.sensors.Streams` (``render = ()``, ``measure = (1,)``: ``[seed, k]`` and
``[seed, 1, k]``) are the demo camera's, so ``opnav render``, ``opnav demo`` and S1 image mode
draw the same noise for the same scene, seed and frame. S3's star sensor uses ``(31,)`` and
``(33,)``, its Earth sensor ``(32,)`` and ``(34,)``.

Frames on disk
--------------
With ``Storage.every == 1`` each frame is a FITS file with its truth sidecar in
``Storage.folder`` and the stage measures it as read back (what a ground pipeline sees); with a
:class:`~opnav.sim.sensors.FrameTag` a file already there is reused when it reads back intact and carries the tag's
seed and digest and the frame's epoch, and is rendered again otherwise (the reason is kept).
With ``every = N > 1`` every N-th frame is rendered in full and written for inspection while
the stage measures it in memory; with 0 nothing is written.

Results are a frozen :class:`~opnav.sim.results.LoopResult`; :mod:`opnav.sim.chunks` runs the loop in resumable
chunks and worker processes, :mod:`opnav.sim.checks` compares the records with the truth.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from ..bodies import body_model
from ..camera import Camera
from ..errors import InputError, NoSolutionError, OpnavError
from ..image.pipeline import FrameInput, frame_input, limb_records, measure_frame
from ..image.tracking import Tracker, paste_windows, windows_frame
from ..observer import Observer
from ..records import join_frame_radec
from ..render.frame import RenderOptions, render_frame, render_windows
from ..render.frames_io import read_frame, saturation_level_adu, write_frame, write_windows
from .checks import misidentified_stars
from .pointing import body_rate, pointing_attitude
from .results import COUNTS, FrameTargets, LoopResult, Miss
from .sensors import Arc, FrameHook, FrameTag, Loop, Sensor, Sky, Storage, Streams, loop_sources, scene_sensor
from .stages import IDENTIFIABLE_STARS, Centre, FullFrame, Limb, Tracking, identifiable, limb_window, predicted_limb

#: Most frames one loop writes (a month at one a minute is 43,200).
MAX_FRAMES = 1_000_000


def digest_card(digest: str) -> tuple[str, str]:
    """The ``DEMOHASH`` card's (value, comment): the comment only where the 80-character card has room for it
    (a run's digest grows with the files it names, and astropy warns on every frame whose comment it cuts)."""
    comment = "opnav demo scenario digest"
    return digest, comment if len("DEMOHASH= ") + max(len(digest) + 2, 20) + len(" / ") + len(comment) <= 80 else ""


def check_frame_budget(count: int, camera: Camera, out_dir: str | Path) -> None:
    """Refuse ``count`` frames of ``camera`` into ``out_dir`` above :data:`MAX_FRAMES` or the free disk.

    Checked before any work, so a step of a millisecond over a day (86 million frames) ends in
    one line instead of hours of propagation and a full disk.
    """
    if count > MAX_FRAMES:
        raise InputError(f"{count:,} frames requested; at most {MAX_FRAMES:,} per render (raise the step or "
                         "shorten the span)")
    frame_bytes = camera.width_px * camera.height_px * 2 + 20_000  # 16-bit FITS + truth JSON
    out = Path(out_dir)
    probe = next((p for p in (out, *out.parents) if p.exists()), Path("."))
    free = shutil.disk_usage(probe).free
    if count * frame_bytes > free:
        raise InputError(f"{count:,} frames of {camera.width_px} x {camera.height_px} px need about "
                         f"{count * frame_bytes / 1e9:.1f} GB; {free / 1e9:.1f} GB free under {probe}")


def frames_folder(storage: Storage) -> Path | None:
    """Create ``storage.folder`` when frames are written; ``InputError`` when it cannot be a folder."""
    if not storage.every:
        return None
    folder = Path(storage.folder)
    for path in (folder, *folder.parents):
        if path.exists() and not path.is_dir():
            raise InputError(f"{folder}: {path} exists and is not a directory")
        if path.exists():
            break
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{folder}: cannot create the frames folder ({exc.strerror})") from None
    return folder


def render_limb(camera: Camera, R_icrf_cam: Rotation, observer: Observer, *, body: str, ephemeris,
                options: RenderOptions, box: tuple[int, int, int, int], band_rad: tuple[float, float],
                rng: np.random.Generator | None = None) -> np.ndarray:
    """``body`` rendered only in ``box`` and only its rays within ``band_rad`` of its centre
    (:func:`opnav.sim.stages.limb_window`): a full-size image (ADU), zero elsewhere."""
    window = render_windows(camera, R_icrf_cam, observer, targets=(body,), ephemeris=ephemeris, options=options,
                            rng=rng, boxes=[box], body_bands={body: band_rad})
    return paste_windows(window.windows, camera.shape)[0]


def _reuse_problem(path: Path, t_tdb_s: float, tag: FrameTag, shape: tuple[int, int]):
    """Why the frame at ``path`` cannot be reused (None if it can), and its truth."""
    if not path.exists():
        return "missing", None
    try:
        stored = read_frame(path)
    except OpnavError as exc:
        return str(exc), None
    header = stored.header
    if header.get("DEMOHASH") != tag.digest:
        return "rendered from another version of the scene", None
    if header.get("DEMOSEED") != tag.seed:
        return f"rendered with seed {header.get('DEMOSEED')}, not {tag.seed}", None
    if stored.image.shape != shape or abs(stored.truth.t_tdb_s - t_tdb_s) > 1e-6:
        return "epoch or image size differs from the scene", None
    return None, stored.truth


@dataclass(frozen=True)
class _Outcome:
    """A sensor's measurement of one frame, for the sensors after it."""

    result: object
    tracked: object


class _Tally:
    """What the frames of one call gave so far (becomes the :class:`LoopResult`)."""

    def __init__(self, targets: tuple[str, ...]) -> None:
        self.records: list = []
        self.skipped: dict = {}
        self.missed: list = []
        self.targets = targets
        self.truths: dict = {}
        self.paths: list = []
        self.rerendered: dict = {}
        self.attitudes: dict = {}
        self.counts = dict.fromkeys(COUNTS, 0)

    def skip(self, frame_id: str, reason: str) -> None:
        self.skipped.setdefault(frame_id, reason)

    def result(self, events: list) -> LoopResult:
        return LoopResult(tuple(self.records), self.skipped, tuple(self.missed), self.targets, tuple(events),
                          self.truths, tuple(self.paths), rerendered=self.rerendered, attitudes=self.attitudes,
                          **self.counts)


class _SensorRun:
    """One sensor over one call of :func:`run_frames`: its tracker, drawn catalog and options."""

    def __init__(self, index: int, loop: Loop, arc: Arc, catalog, ephemeris, stage_ephemeris, hook: FrameHook,
                 folder: Path | None) -> None:
        self.index, self.loop, self.arc, self.hook, self.folder = index, loop, arc, hook, folder
        self.sensor = sensor = loop.sensors[index]
        self.catalog, self.ephemeris, self.stage_ephemeris = catalog, ephemeris, stage_ephemeris
        self.options, self.drawn_catalog = hook.drawn(loop.seed, index, sensor, arc, catalog if sensor.stars else None,
                                                      ephemeris)
        stage = sensor.stage
        self.tracker = (Tracker(catalog, stage_ephemeris, stage.options, stage.tracking)
                        if isinstance(stage, Tracking) else None)
        self.saturation = saturation_level_adu(sensor.camera)
        self.label = f"{sensor.name}: " if sensor.name else ""
        self.unidentified = 0  # frames in a row no star identification gave an attitude, before any lock
        if isinstance(stage, (Limb, Centre)):
            # this camera -> the reference camera, through the body
            self.turn = loop.sensors[stage.reference].mounting.inv() * sensor.mounting
        self.names = (tuple(stage.options.targets) if isinstance(stage, (FullFrame, Tracking))
                      else (stage.body,) if isinstance(stage, Centre) else ())

    def path(self, frame_id: str) -> Path:
        return self.folder / (f"{frame_id}.fits" if self.index == 0 else f"{frame_id}_{self.index}.fits")

    def attitude(self, offset: int, observer: Observer):
        """True attitude (camera -> ICRF) and body rate (camera frame, rad/s; None: not turning)."""
        sensor = self.sensor
        if sensor.pointing is not None:
            corrections = sensor.render.corrections
            return (pointing_attitude(sensor.pointing, observer, self.ephemeris, corrections),
                    body_rate(sensor.pointing, observer, self.ephemeris, corrections))
        return self.arc.R_icrf_body[offset] * sensor.mounting, None

    def draw(self, k: int, omega) -> dict:
        """Keyword arguments of the renderer for frame ``k``."""
        seed = self.loop.seed
        kwargs = dict(catalog=self.drawn_catalog, targets=self.sensor.targets,
                      ephemeris=self.hook.ephemeris(seed, k, self.ephemeris), options=self.options,
                      rng=self.sensor.streams.rng(seed, "render", k))
        if omega is not None:
            kwargs["omega_cam_rad_s"] = omega
        return kwargs

    def frame(self, k: int, offset: int, frame_id: str, observer: Observer, outcomes: list, tally: _Tally):
        if isinstance(self.sensor.stage, Limb):
            return self._limb(k, offset, frame_id, observer, outcomes, tally)
        if isinstance(self.sensor.stage, Centre):
            return self._centre(k, offset, frame_id, observer, outcomes, tally)
        return self._image(k, offset, frame_id, observer, tally)

    # ---- full frames and windows --------------------------------------------------------------

    def _image(self, k, offset, frame_id, observer, tally):
        hook, storage, stage = self.hook, self.loop.storage, self.sensor.stage
        attitude, omega = self.attitude(offset, observer)
        prior = hook.prior(self.loop.seed, self.index, k, attitude)
        try:
            if storage.every == 1:
                path = self.path(frame_id)
                truth = self._file(k, path, attitude, omega, observer, tally)
                frame = None
                if stage is not None:
                    # the stage measures with the camera it assumes (None: the one the header describes)
                    frame = frame_input(path, self.sensor.measure_camera)
                    image = hook.image(self.index, frame.image)
                    if image is not frame.image:
                        frame = replace(frame, image=image)
                    if prior is not attitude:  # else the attitude the file's header carries
                        frame = replace(frame, R_prior=prior)
                source = str(path)
            else:
                frame, truth = self._memory(k, frame_id, attitude, omega, prior, observer, tally)
                source = None
        except OpnavError as exc:
            tally.skip(frame_id, self.label + str(exc))
            return None
        if stage is None:
            self._keep_truth(frame_id, truth, tally)
            return None
        return self.measure(frame, truth, k, frame_id, source, tally)

    def _keep_truth(self, frame_id: str, truth, tally: _Tally) -> None:
        tally.truths[frame_id] = FrameTargets({target.name: (target.ra_rad, target.dec_rad) for target in truth.targets
                                               if target.name in (self.names or self.sensor.targets)})

    def measure(self, frame: FrameInput, truth, k: int, frame_id: str, source: str | None, tally: _Tally):
        """The stage on frame ``k`` (``truth``: its :class:`~opnav.render.truth.FrameTruth`): its records,
        misses and tracked stars into ``tally``; the outcome for later sensors (None: no records)."""
        stage = self.sensor.stage
        self._keep_truth(frame_id, truth, tally)
        try:
            result, tracked = self._measure(frame, k, source)
        except OpnavError as exc:
            tally.skip(frame_id, self.label + str(exc))
            return None
        if tracked is not None:  # checked against the truth: not a star the stage used
            used, wrong = misidentified_stars(tracked, truth.stars)
            tally.counts["stars_used"] += used
            tally.counts["stars_misidentified"] += wrong
        if self.tracker is not None and self.unidentified >= 0:
            # until the first lock; later failures are losses of lock, counted as events
            if self.tracker.locked:
                self.unidentified = -1
            elif identifiable(frame, result, self.catalog, self.stage_ephemeris, stage.options, stage.tracking):
                self.unidentified += 1  # stars enough, yet no match: a sparse field or the glare of Mars does not count
            if self.unidentified >= stage.max_unidentified_frames:
                first = f"{self.loop.frame_prefix}_{0 if self.arc is None else self.arc.first:05d}"
                raise NoSolutionError(
                    f"{frame_id}: star identification gave no attitude on {self.unidentified} frames with at least "
                    f"{IDENTIFIABLE_STARS} catalog stars predicted and as many sources detected, from the start of "
                    f"the chunk at {first}: the frames do not match the catalog around the "
                    "a-priori attitude (a camera model with mirrored or rotated axes or a wrong scale, an a-priori "
                    "attitude far off, or more false sources than stars?); stopping instead of navigating on the "
                    "a-priori attitude")
        if "attitude_prior" in result.flags:
            # no star-identified attitude (too few stars, or none matched): records on the a-priori
            # attitude would carry its 0.05-degree sigma, nothing for navigation at 0.03"
            tally.skip(frame_id, f"{self.label}no star-identified attitude ({result.n_stars_matched} stars matched); "
                                 "no records")
            return None
        # the star-identified attitude, for sensors read outside the loop (a sun sensor on the same body)
        tally.attitudes[f"{frame_id}:{self.index}"] = (result.R_icrf_cam.as_quat().tolist(),
                                                       np.asarray(result.cov_attitude_rad2, float).tolist())
        # the moons of one frame share its attitude error: one record with their cross-covariance
        tally.records.extend(join_frame_radec(list(result.records)))
        for name in self.names:
            if f"no_{name}" in result.flags:
                tally.missed.append(Miss(frame_id, name, f"{name}_hidden" in result.flags))
        return _Outcome(result, tracked)

    def _file(self, k, path, attitude, omega, observer, tally):
        """Frame ``k`` as a file at ``path``: reused when its tag matches, else rendered and written; its truth."""
        sensor, tag = self.sensor, self.loop.storage.tag
        if tag is not None:
            problem, truth = _reuse_problem(path, observer.t_tdb_s, tag, sensor.camera.shape)
            if problem is None:
                tally.counts["frames_reused"] += 1
                tally.counts["frames_full"] += 1
                tally.paths.append(path)
                return truth
            if problem != "missing":
                tally.rerendered[path.name] = problem
        if sensor.window_half_px is not None:
            rendered = render_windows(sensor.camera, attitude, observer, window_half_px=sensor.window_half_px,
                                      **self.draw(k, omega))
            write_windows(path, rendered.windows, sensor.camera, rendered.truth)
            tally.counts["frames_windowed"] += 1
        else:
            rendered = render_frame(sensor.camera, attitude, observer, **self.draw(k, omega))
            header = rendered.header
            if tag is not None:
                header = header.copy()
                header["DEMOSEED"] = (tag.seed, "opnav demo noise seed")
                header["DEMOHASH"] = digest_card(tag.digest)
            write_frame(path, rendered.image, header, rendered.truth)
            tally.counts["frames_full"] += 1
        tally.paths.append(path)
        return rendered.truth

    def _memory(self, k, frame_id, attitude, omega, prior, observer, tally):
        """Frame ``k`` rendered in memory (in full, in the tracker's windows or around every source): (frame, truth)."""
        sensor, hook, index = self.sensor, self.hook, self.index
        # rendered with the true camera, measured (and its windows predicted) with the one the stage assumes
        camera, assumed, t = sensor.camera, sensor.assumed_camera, observer.t_tdb_s
        write = self.loop.storage.writes(k)
        boxes = None
        if self.tracker is not None and not write:
            boxes = self.tracker.read_boxes(assumed, t, observer, prior)
        if boxes is None and sensor.window_half_px is None:
            rendered = render_frame(camera, attitude, observer, **self.draw(k, omega))
            if write:
                path, _ = write_frame(self.path(frame_id), rendered.image, rendered.header, rendered.truth)
                tally.paths.append(path)
            frame = FrameInput.from_camera(hook.image(index, rendered.image), assumed, t, prior, observer,
                                           saturation_adu=self.saturation, frame_id=frame_id,
                                           flags=rendered.truth.flags)
            tally.counts["frames_full"] += 1
            return frame, rendered.truth
        if boxes is not None:  # the windows the stage reads are where the readout puts them
            boxes = hook.boxes(index, boxes, camera)
            rendered = render_windows(camera, attitude, observer, boxes=boxes, **self.draw(k, omega))
        else:
            rendered = render_windows(camera, attitude, observer, window_half_px=sensor.window_half_px,
                                      **self.draw(k, omega))
            if write:
                path, _ = write_windows(self.path(frame_id), rendered.windows, camera, rendered.truth)
                tally.paths.append(path)
        frame = windows_frame(hook.windows(index, rendered.windows, camera), camera=assumed, t_tdb_s=t, R_prior=prior,
                              observer=observer, saturation_adu=self.saturation, frame_id=frame_id)
        tally.counts["frames_windowed"] += 1
        return frame, rendered.truth

    def _measure(self, frame: FrameInput, k: int, source: str | None):
        """(FrameResult, TrackedFrame or None) of the stage on ``frame``, from frame ``k``'s stream."""
        rng = self.sensor.streams.rng(self.loop.seed, "measure", k)
        if self.tracker is None:
            return measure_frame(frame, catalog=self.catalog, ephemeris=self.stage_ephemeris,
                                 options=self.sensor.stage.options, rng=rng, source=source), None
        result = self.tracker.step(frame, rng=rng)
        tracked, self.tracker.last_tracked = self.tracker.last_tracked, None
        return result, tracked

    # ---- a limb in the annulus another sensor's attitude predicts -------------------------------

    def _limb(self, k, offset, frame_id, observer, outcomes, tally):
        sensor, stage, seed = self.sensor, self.sensor.stage, self.loop.seed
        camera, t = sensor.camera, observer.t_tdb_s
        reference = outcomes[stage.reference]
        if reference is None:  # its frame gave nothing (the reason is listed)
            return None
        row = int(stage.stars[k])
        if row < 0:
            tally.skip(frame_id, f"no navigation star in the {self.loop.sensors[stage.reference].name or 'reference'}"
                                 "'s field")
            return None
        star_id = int(self.catalog.star_id[row])
        tracked = reference.tracked
        if tracked is not None:
            # the angle is the catalog star's against the limb through the attitude the whole field
            # gives; the star itself need not be a guide star (a neighbour or the field edge)
            tally.counts["navigation_star_not_tracked"] += star_id not in set(
                tracked.predicted.star_id[tracked.used].tolist())
        # this sensor's attitude: the reference's solution through the mountings; its covariance
        # (camera-frame small rotation) turns with the frame
        R_solved = reference.result.R_icrf_cam * self.turn
        turn = self.turn.inv().as_matrix()
        cov = turn @ reference.result.cov_attitude_rad2 @ turn.T
        centre, radius_px, rho = predicted_limb(camera, R_solved, observer, self.stage_ephemeris, stage.altitude_km,
                                                stage.body)
        band, box = limb_window(camera, centre, radius_px, rho, stage.reach_px)
        R_true = self.arc.R_icrf_body[offset] * sensor.mounting
        try:
            image = render_limb(camera, R_true, observer, body=stage.body,
                                ephemeris=self.hook.ephemeris(seed, k, self.ephemeris), options=self.options, box=box,
                                band_rad=band, rng=sensor.streams.rng(seed, "render", k))
            state = dict(t_tdb_s=t, r_observer_ssb_km=observer.r_ssb_km, v_observer_ssb_km_s=observer.v_ssb_km_s)
            astrometric = self.catalog.apparent_directions([row], **state, aberration=False)
            apparent = self.catalog.apparent_directions([row], **state)
            measured = limb_records(stage.body, body_model(stage.body), image, camera, centre, radius_px, R_solved, cov,
                                    ([row], apparent, astrometric, [star_id]), t, frame_id, stage.options,
                                    sensor.streams.rng(seed, "measure", k), radial_half_width_px=stage.band_px,
                                    v_observer_km_s=observer.v_ssb_km_s)
        except OpnavError as exc:
            tally.skip(frame_id, self.label + str(exc))
            return None
        tally.records.extend(r for r in measured if r.kind in stage.kinds)
        return _Outcome(None, None)

    # ---- a resolved body's centre with another sensor's attitude --------------------------------

    def _centre(self, k, offset, frame_id, observer, outcomes, tally):
        from ..image.centres import measure_body_centre
        from ..image.correlate import DetectorNoise
        from ..image.mesh_centre import measure_mesh_centre

        sensor, stage = self.sensor, self.sensor.stage
        reference = outcomes[stage.reference]
        if reference is None or reference.result is None:  # its frame gave nothing (the reason is listed)
            return None
        # this sensor's attitude: the reference's solution through the mountings; its covariance
        # (camera-frame small rotation) turns with the frame
        R_solved = reference.result.R_icrf_cam * self.turn
        turn = self.turn.inv().as_matrix()
        cov = turn @ reference.result.cov_attitude_rad2 @ turn.T
        R_true = self.arc.R_icrf_body[offset] * sensor.mounting
        camera, assumed = sensor.camera, sensor.assumed_camera
        try:
            rendered = render_frame(camera, R_true, observer, **self.draw(k, None))
            tally.counts["frames_full"] += 1
            self._keep_truth(frame_id, rendered.truth, tally)
            if self.loop.storage.writes(k):  # for inspection; measured in memory
                path, _ = write_frame(self.path(frame_id), rendered.image, rendered.header, rendered.truth)
                tally.paths.append(path)
            model = stage.model or body_model(stage.body)
            # a mesh body's centre by correlation with its own rendered template (or its centroid when
            # point-like); an ellipsoid's by limb fit or correlation, chosen by size and phase
            measure = measure_mesh_centre if model.shape is not None else measure_body_centre
            got = measure(
                self.hook.image(self.index, rendered.image), assumed, model,
                R_icrf_cam=R_solved,
                cov_att_rad2=cov, observer=observer, ephemeris=self.stage_ephemeris, psf_sigma_px=stage.psf_sigma_px,
                noise=DetectorNoise(assumed.read_noise_e, assumed.gain_e_per_adu, assumed.bias_adu),
                t_tdb_s=observer.t_tdb_s, sensor=stage.sensor, frame_id=frame_id, options=stage.centre_options)
        except (OpnavError, np.linalg.LinAlgError) as exc:
            # a fit whose least squares does not converge is one frame lost, not the run: its reason is listed
            reason = str(exc) if isinstance(exc, OpnavError) else f"{stage.body} centre fit failed numerically ({exc})"
            tally.skip(frame_id, self.label + reason)
            tally.missed.append(Miss(frame_id, stage.body, False))
            return None
        tally.records.extend(r for r in got.records if r.kind in stage.kinds)
        return _Outcome(None, None)


def run_frames(loop: Loop, arc: Arc, *, catalog=None, ephemeris=None, stage_ephemeris=None,
               on_frame: Callable[[], None] | None = None) -> LoopResult:
    """Render and measure every frame of ``arc`` with ``loop``'s sensors (module notes).

    Parameters
    ----------
    loop : Loop
    arc : Arc
    catalog, ephemeris, stage_ephemeris : optional
        The star catalog and the truth's and the stage's ephemerides; default those of
        ``loop.sky`` (:func:`loop_sources`).
    on_frame : callable, optional
        Called once per frame (a progress bar).

    Returns
    -------
    LoopResult

    Raises
    ------
    NoSolutionError
        When a tracking stage's frames keep failing star identification that should solve them
        (:class:`opnav.sim.stages.Tracking` ``max_unidentified_frames``).
    """
    if ephemeris is None:
        needs_catalog = any(s.stars or s.stage is not None for s in loop.sensors)
        loaded, ephemeris, loaded_stage = loop_sources(loop.sky, catalog=needs_catalog and catalog is None)
        catalog = catalog if catalog is not None else loaded
        stage_ephemeris = stage_ephemeris or loaded_stage
    stage_ephemeris = stage_ephemeris or ephemeris
    if any(s.mounting is not None for s in loop.sensors) and arc.R_icrf_body is None:
        raise InputError("sensors mounted on the body need the body's attitude along the arc (Arc.R_icrf_body)")
    hook = loop.hook or FrameHook()
    folder = frames_folder(loop.storage)
    runs = [_SensorRun(index, loop, arc, catalog, ephemeris, stage_ephemeris, hook, folder)
            for index in range(len(loop.sensors))]
    tally = _Tally(tuple(name for run in runs for name in run.names))
    for offset in range(len(arc)):
        k = arc.first + offset
        frame_id = f"{loop.frame_prefix}_{k:05d}"
        if on_frame is not None:
            on_frame()
        lost = hook.lost(loop.seed, k)
        if lost:
            tally.skip(frame_id, lost)
            tally.counts["frames_dropped"] += 1
            continue
        observer = Observer(float(arc.t_tdb_s[offset]), arc.r_ssb_km[offset], arc.v_ssb_km_s[offset])
        outcomes: list = []
        for run in runs:
            outcomes.append(run.frame(k, offset, frame_id, observer, outcomes, tally))
    return tally.result([event for run in runs if run.tracker is not None for event in run.tracker.events])


def stored_truth(path: str | Path):
    """The :class:`~opnav.render.truth.FrameTruth` in the sidecar of the frame file at ``path``."""
    import json

    from ..errors import FrameError
    from ..render.truth import truth_from_json

    path = Path(path)
    sidecar = path.with_name(path.stem + ".truth.json")
    try:
        data = json.loads(sidecar.read_text())
    except (OSError, ValueError) as exc:
        raise FrameError(f"{sidecar}: unreadable truth sidecar ({exc})") from None
    return truth_from_json(data, source=str(sidecar))


def measure_files(paths, stage: FullFrame | Tracking, *, seed: int, streams: Streams = Streams(), catalog=None,
                  ephemeris=None, on_frame: Callable[[], None] | None = None) -> LoopResult:
    """``stage`` on frames already on disk (FITS with the opnav header and a truth sidecar), in order, as
    :func:`run_frames` measures the frames it writes: frame ``k`` is ``paths[k]``, its stage draws
    from ``streams`` (``[seed, 1, k]`` by default) and its id is the file's stem.

    ``catalog`` default the packaged one; ``ephemeris`` (the stage's) default DE421.
    """
    from .pointing import PointingLaw

    paths = [Path(path) for path in paths]
    if catalog is None or ephemeris is None:
        stars, _, exact = loop_sources(Sky(ephemeris="exact"), catalog=catalog is None)
        catalog = catalog if catalog is not None else stars
        ephemeris = ephemeris if ephemeris is not None else exact
    if not paths:
        return LoopResult(targets=tuple(stage.options.targets))
    camera = frame_input(paths[0]).camera  # the files' own camera (the stage reads it from each header)
    loop = Loop((Sensor(camera, stage, pointing=PointingLaw(), streams=streams),), seed)
    run = _SensorRun(0, loop, None, catalog, ephemeris, ephemeris, FrameHook(), None)
    tally = _Tally(run.names)
    for k, path in enumerate(paths):
        if on_frame is not None:
            on_frame()
        try:
            frame, truth = frame_input(path), stored_truth(path)
        except OpnavError as exc:
            tally.skip(path.stem, str(exc))
            continue
        tally.counts["frames_full"] += 1
        tally.paths.append(path)
        run.measure(frame, truth, k, path.stem, str(path), tally)
    return tally.result(run.tracker.events if run.tracker is not None else [])


@dataclass(frozen=True)
class RenderedFrames:
    """Frames on disk: ``paths`` and ``truths`` (:class:`opnav.render.truth.FrameTruth`) per epoch;
    ``reused`` counts frames kept from an earlier run; ``rerendered`` maps a frame name to why its
    old file was not reused."""

    paths: tuple[Path, ...]
    truths: tuple
    reused: int
    rerendered: dict


def render_frames(scene, t_tdb_s: np.ndarray, r_ssb_km: np.ndarray, v_ssb_km_s: np.ndarray, frames_dir, *,
                  seed: int, digest: str | None = None, catalog=None, ephemeris=None,
                  progress: bool = False) -> RenderedFrames:
    """Render and write ``frames_dir/frame_NNNNN.fits`` (+ truth JSON) for every epoch: the loop with
    ``scene``'s camera and no image stage (what ``opnav render`` does).

    Parameters
    ----------
    scene : opnav.sim.scene.Scene
        Camera, pointing law, targets, render options, stars (windowed when ``scene.windowed``).
    t_tdb_s : (M,) array
        Mid-exposure epochs, TDB seconds past J2000.
    r_ssb_km, v_ssb_km_s : (M, 3) arrays
        Observer position (km) and velocity (km/s) relative to the SSB, ICRF.
    frames_dir : path
    seed : int
        Frame ``k`` draws its noise from ``default_rng([seed, k])`` (module notes).
    digest : str, optional
        Tags every frame (with ``seed``); frames already there with the same tag and epoch are reused.
    catalog, ephemeris : optional
        Star catalog and ephemeris (default: ``scene.catalog_path``'s catalog when the scene draws
        stars, and DE421).
    progress : bool
        Show a progress bar.
    """
    sensor = scene_sensor(scene)
    storage = Storage(Path(frames_dir), 1, None if digest is None else FrameTag(seed, digest))
    loop = Loop((sensor,), seed, Sky(scene.catalog_path, ephemeris="exact"), storage)
    if ephemeris is None or (catalog is None and scene.stars):
        stars, exact, _ = loop_sources(loop.sky, catalog=scene.stars and catalog is None)
        catalog = catalog if catalog is not None else stars
        ephemeris = ephemeris if ephemeris is not None else exact
    arc = Arc(t_tdb_s, r_ssb_km, v_ssb_km_s)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(arc), desc="render", unit="frame")
    try:
        result = run_frames(loop, arc, catalog=catalog if scene.stars else None, ephemeris=ephemeris,
                            on_frame=None if bar is None else (lambda: bar.update(1)))
    finally:
        if bar is not None:
            bar.close()
    truths = tuple(stored_truth(path) for path in result.paths)
    return RenderedFrames(result.paths, truths, result.frames_reused, result.rerendered)


def simulate_scene(scene, *, count: int | None = None, seed: int | None = None,
                   targets: tuple[str, ...] | None = None, catalog=None, ephemeris=None) -> LoopResult:
    """Render the first ``count`` frames of ``scene`` and measure each with the full-frame image stage.

    The shortest way from a scene file to records: the scene's camera, pointing law, targets and
    render options, its epochs and observer (:func:`opnav.sim.scene.observer_states`), one sensor
    in memory with the default :class:`~opnav.sim.sensors.Streams` (so frame ``k`` has the noise
    ``opnav render`` and ``opnav demo`` give it for the same scene and seed).

    Parameters
    ----------
    scene : opnav.sim.scene.Scene
    count : int, optional
        Frames from the scene's first epoch (default: every epoch of the scene).
    seed : int, optional
        Seed of every stream (default: the scene's).
    targets : tuple of str, optional
        Bodies the image stage measures (default: the scene's targets except the resolved
        bodies the stage does not measure as point sources, :data:`opnav.image.pipeline.RESOLVED_BODIES`).
    catalog, ephemeris : optional
        Star catalog and ephemeris (default: the scene's catalog or the packaged one, DE421).

    Returns
    -------
    LoopResult
        ``records`` (RA/Dec of the targets, ICRF, with covariances), ``skipped``, ``truths`` per frame.
    """
    from ..image.pipeline import RESOLVED_BODIES, PipelineOptions
    from .scene import observer_states

    t = scene.t_tdb_s if count is None else scene.t_tdb_s[:count]
    if t.size == 0:
        raise InputError(f"count must be at least 1 (the scene has {scene.t_tdb_s.size} epochs), got {count!r}")
    sky = Sky(scene.catalog_path, ephemeris="exact")
    stars, exact, _ = loop_sources(sky, catalog=catalog is None and scene.stars)
    catalog = catalog if catalog is not None else stars
    ephemeris = ephemeris if ephemeris is not None else exact
    names = tuple(targets) if targets is not None else tuple(n for n in scene.targets if n not in RESOLVED_BODIES)
    stage = FullFrame(PipelineOptions(targets=names, vmag_limit=scene.options.vmag_limit))
    loop = Loop((scene_sensor(scene, stage),), scene.seed if seed is None else int(seed), sky)
    r, v = observer_states(scene, t, ephemeris)
    return run_frames(loop, Arc(t, r, v), catalog=catalog, ephemeris=ephemeris)
