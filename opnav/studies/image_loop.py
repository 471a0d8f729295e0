"""Image-in-the-loop in memory: truth -> (windowed) render -> tracking image stage -> records, chunk by chunk.

For each epoch the frame is rendered along the truth (:func:`opnav.render.render_frame`
or, while the :class:`~opnav.image.tracking.Tracker` holds lock, only the windows it will
read: :meth:`~opnav.image.tracking.Tracker.read_boxes` and :func:`opnav.render.render_windows`,
each window read out with the same detector model as a full frame) and measured at once
from memory: no FITS file per frame. The two moons of a frame become one ``radec_pair`` record
with the cross-covariance of the attitude they share (:func:`opnav.records.join_frame_radec`).
Every ``dump_every``-th frame is rendered in full and written as FITS with its truth
(``frames/``) for inspection.

The frames go in chunks of ``chunk_frames`` (a day at one a minute). Each chunk starts
from lost-in-space acquisition on its first frame, as a camera switched on, and depends on
nothing before it, so chunks run in ``workers`` processes side by side and give the same
records in any number of them. Each chunk's records (``stream/chunk_NNNNN.records.csv``)
and its book-keeping (``chunk_NNNNN.done.json``: tracking events, frames skipped, moons
missed, the moons' true RA/Dec per frame) are written atomically when the chunk ends, the
JSON last, with the records' checksum; a re-run reads the finished chunks (same content hash,
records intact), so an interrupted run loses at most the chunks under way and a damaged chunk
is made again.

The renderer and the image stage read the scenario's star catalog
(:func:`opnav.catalog.load_catalog`) and the Chebyshev cache of DE421
(:func:`opnav.ephemeris.cache.default_cached_ephemeris`, within 1 cm of it): the ephemeris
calls of each frame's geometry would otherwise cost more than its pixels.

Noise of frame ``k`` comes from ``default_rng([seed, k])``, whatever the arc (so one seed gives
two arcs the same streams: :mod:`opnav.studies.s1`); a frame rendered in windows
draws its noise window by window, so its pixels differ from the full render's by the
noise draw only (same statistics, ``tests/render/test_render_io.py``).
"""

from __future__ import annotations

import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from ..constants import ARCSEC_RAD
from ..errors import InputError, NoSolutionError, OpnavError
from ..records import Measurement, atomic_write_text, file_sha256, join_frame_radec, read_csv, write_csv

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
class _MoonTruth:
    ra_rad: float
    dec_rad: float


@dataclass(frozen=True)
class _FrameTruth:
    """The part of a frame's truth the measurement errors need (``target(name)``)."""

    moons: dict

    def target(self, name: str) -> _MoonTruth:
        ra, dec = self.moons[name]
        return _MoonTruth(ra, dec)


@dataclass
class StreamResult:
    """What the loop gave over the whole arc."""

    records: list[Measurement] = field(default_factory=list)
    skipped: dict = field(default_factory=dict)
    missed: dict = field(default_factory=dict)
    events: list = field(default_factory=list)
    truths: dict = field(default_factory=dict)
    dumped: list = field(default_factory=list)
    frames_windowed: int = 0
    frames_full: int = 0
    frames_dropped: int = 0
    stars_used: int = 0
    stars_misidentified: int = 0
    chunks_reused: int = 0


@dataclass(frozen=True)
class _Chunk:
    """Everything one chunk needs, picklable for a worker process."""

    scenario: object
    first: int
    epochs: np.ndarray
    r_ssb_km: np.ndarray
    v_ssb_km_s: np.ndarray
    stem: Path
    frames_dir: Path
    key: str
    seed: int
    options: object
    tracking: object
    moons: tuple
    dump_every: int
    faults: object = None
    moon_ephemeris_sigma_km: float = 0.0
    moon_ephemeris_error: str = "white"


def stream_frames(scenario, epochs: np.ndarray, r_ssb_km: np.ndarray, v_ssb_km_s: np.ndarray, out: Path, *,
                  seed: int, options, tracking=None, moons: tuple[str, ...], dump_every: int = 0,
                  chunk_frames: int = 1440, key: str = "", workers: int = 1, faults=None,
                  moon_ephemeris_sigma_km: float = 0.0, moon_ephemeris_error: str = "white",
                  progress: bool = True) -> StreamResult:
    """Render and measure every epoch in memory (module docstring).

    Parameters
    ----------
    scenario : opnav.sim.scene.Scene
        Camera, pointing law, targets, render options, star catalog path.
    epochs : (M,) array
        Mid-exposure epochs, TDB s past J2000.
    r_ssb_km, v_ssb_km_s : (M, 3) arrays
        True observer states (SSB, ICRF, km and km/s).
    out : Path
        Run folder (``stream/`` chunks, ``frames/`` dumps).
    seed : int
    options : opnav.image.pipeline.PipelineOptions
        The image stage's settings (its ``targets`` are the moons measured).
    tracking : opnav.image.tracking.TrackingOptions, optional
        Tracking settings (default: the defaults).
    moons : tuple of str
        Moons whose true RA/Dec is kept for the measurement errors.
    dump_every : int
        Write every this-many-th frame as FITS (0: none).
    chunk_frames : int
        Frames per chunk (the unit of resumption and of work per process).
    key : str
        Content hash of the run; chunks made from another are recomputed.
    workers : int
        Processes the chunks run in (1: this one). The records do not depend on it.
    faults : opnav.studies.faults.Faults, optional
        Frame faults (``Faults.on_frames``) applied to the rendered frames (:func:`_faulted_render`).
    moon_ephemeris_sigma_km, moon_ephemeris_error : float, str
        The moons are drawn this far (km per axis, ICRF) from the ephemeris the image stage
        predicts with: a new draw per frame (``"white"``) or one per run (``"bias"``), as the
        measurement-mode truth of S1 has it. The image stage does not know the offset.
    progress : bool
        Show a progress bar (by frame; by finished chunk with several workers).
    """
    from ..image.tracking import TrackingOptions

    if int(workers) != workers or workers < 1:
        raise InputError(f"workers must be a positive integer, got {workers!r}")
    if int(chunk_frames) != chunk_frames or chunk_frames < 1:
        raise InputError(f"chunk_frames must be a positive integer, got {chunk_frames!r}")
    folder = Path(out) / "stream"
    chunks = [_Chunk(scenario, start, epochs[start:start + chunk_frames], r_ssb_km[start:start + chunk_frames],
                     v_ssb_km_s[start:start + chunk_frames], folder / f"chunk_{start // chunk_frames:05d}",
                     Path(out) / "frames",
                     f"{key}:{start}:{min(start + chunk_frames, len(epochs))}:{dump_every}:identified-only:joint-frames:"
                     f"{moon_ephemeris_sigma_km}:{moon_ephemeris_error}",
                     seed, options, tracking or TrackingOptions(), tuple(moons), dump_every, faults,
                     moon_ephemeris_sigma_km, moon_ephemeris_error)
              for start in range(0, len(epochs), chunk_frames)]
    result = StreamResult(missed={name: [] for name in moons})
    finished, result.chunks_reused = run_chunks(chunks, _run_chunk, workers=workers, progress=progress)
    for records, book in finished:
        _merge(result, records, book)
    return result


def run_chunks(chunks: list, work, *, workers: int, progress: bool, unit: str = "frame") -> tuple[list, int]:
    """``work(chunk, bar)`` -> (records, book) of every chunk, in order, and how many were read back.

    A chunk (anything with ``stem``, ``key`` and ``epochs``) whose files :func:`load_chunk` finds
    intact is read back; the others run here (``workers`` 1) or in ``workers`` spawned processes
    (``work`` a module-level function, each chunk picklable). ``work`` writes its chunk with
    :func:`save_chunk`. The progress bar counts epochs.
    """
    done: dict[int, tuple] = {}
    for index, chunk in enumerate(chunks):
        finished = load_chunk(chunk.stem, chunk.key)
        if finished is not None:
            done[index] = finished
    reused = len(done)
    todo = [index for index in range(len(chunks)) if index not in done]
    bar = tqdm(total=sum(len(chunk.epochs) for chunk in chunks), desc=f"{unit}s", unit=unit, disable=not progress)
    bar.update(sum(len(chunks[index].epochs) for index in done))
    workers = min(int(workers), len(todo))
    if workers <= 1:
        for index in todo:
            done[index] = work(chunks[index], bar)
    else:
        # spawned, not forked: the parent may hold numba's thread pool, which a fork would copy broken
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_worker_init) as pool:
            futures = {pool.submit(work, chunks[index]): index for index in todo}
            for future in as_completed(futures):
                done[futures[future]] = future.result()
                bar.update(len(chunks[futures[future]].epochs))
    bar.close()
    return [done[index] for index in range(len(chunks))], reused


def _worker_init() -> None:
    """A chunk worker runs compiled kernels on one thread (the processes already fill the cores) and
    keeps freed memory for the next frame (:func:`opnav.allocator.keep_freed_memory`)."""
    from ..allocator import keep_freed_memory
    from ..compiled import use_one_thread

    use_one_thread()
    keep_freed_memory()


_LOADED: dict = {}


def loop_sources(catalog_path):
    """(catalog, ephemeris) of the loop, loaded once per process."""
    if catalog_path not in _LOADED:
        from ..catalog import load_catalog
        from ..ephemeris.cache import default_cached_ephemeris

        _LOADED[catalog_path] = (load_catalog(catalog_path), default_cached_ephemeris())
    return _LOADED[catalog_path]


def _run_chunk(chunk: _Chunk, bar=None) -> tuple[list[Measurement], dict]:
    """Render and measure one chunk from a fresh tracker; write its files; (records, book)."""
    from ..demo import quiet_moon_misses
    from ..image.pipeline import FrameInput
    from ..image.tracking import Tracker, windows_frame
    from ..observer import Observer
    from ..render.frame import render_frame, render_windows
    from ..render.frames_io import Window, saturation_level_adu, write_frame
    from ..sim.pointing import body_rate, pointing_attitude

    scenario, moons = chunk.scenario, chunk.moons
    catalog, ephemeris = loop_sources(scenario.catalog_path)
    tracker = Tracker(catalog, ephemeris, chunk.options, chunk.tracking)
    camera = scenario.camera
    corrections = scenario.options.corrections
    saturation = saturation_level_adu(camera)
    faults = chunk.faults.on_frames if chunk.faults is not None else {}
    render_options, render_catalog = _faulted_render(scenario, catalog, ephemeris, chunk, faults)
    records, book = [], {"events": [], "skipped": {}, "missed": {name: [] for name in moons}, "truth": {},
                         "dumped": [], "windowed": 0, "full": 0, "dropped": 0, "stars_used": 0,
                         "stars_misidentified": 0}
    render = dict(catalog=render_catalog, targets=scenario.targets, options=render_options)
    unidentified = 0  # frames in a row no star identification gave an attitude, before any lock
    with quiet_moon_misses():
        for offset in range(len(chunk.epochs)):
            k = chunk.first + offset
            frame_id = f"frame_{k:05d}"
            if bar is not None:
                bar.update(1)
            if np.random.default_rng([chunk.seed, 92, k]).random() < faults.get("dropped_frame_fraction", 0.0):
                book["skipped"][frame_id] = "frame lost (faults.dropped_frame_fraction)"
                book["dropped"] += 1
                continue
            observer = Observer(float(chunk.epochs[offset]), chunk.r_ssb_km[offset], chunk.v_ssb_km_s[offset])
            attitude = pointing_attitude(scenario.pointing, observer, ephemeris, corrections)
            omega = body_rate(scenario.pointing, observer, ephemeris, corrections)
            prior = attitude
            if faults.get("prior_attitude_error_arcsec"):
                axis = np.random.default_rng([chunk.seed, 94, k]).standard_normal(3)
                prior = attitude * Rotation.from_rotvec(axis / np.linalg.norm(axis) * faults["prior_attitude_error_arcsec"]
                                                        * ARCSEC_RAD)
            rng = np.random.default_rng([chunk.seed, k])
            render["ephemeris"] = _drawn_ephemeris(ephemeris, chunk, k)
            dump = chunk.dump_every > 0 and k % chunk.dump_every == 0
            boxes = None if dump else tracker.read_boxes(camera, observer.t_tdb_s, observer, prior)
            flipped = bool(faults.get("flipped_axis"))
            render.update(omega_cam_rad_s=omega, rng=rng)
            try:
                if boxes is None:
                    rendered = render_frame(camera, attitude, observer, **render)
                    if dump:
                        path, _ = write_frame(chunk.frames_dir / f"{frame_id}.fits", rendered.image, rendered.header,
                                              rendered.truth)
                        book["dumped"].append(str(path))
                    image = rendered.image[:, ::-1].copy() if flipped else rendered.image
                    frame = FrameInput.from_camera(image, camera, observer.t_tdb_s, prior, observer,
                                                   saturation_adu=saturation, frame_id=frame_id,
                                                   flags=rendered.truth.flags)
                    book["full"] += 1
                else:
                    if flipped:  # the windows the stage reads are where the mirrored camera put them
                        boxes = [(camera.width_px - 1 - x1, y0, camera.width_px - 1 - x0, y1) for x0, y0, x1, y1 in boxes]
                    rendered = render_windows(camera, attitude, observer, boxes=boxes, **render)
                    windows = rendered.windows
                    if flipped:
                        windows = [Window(camera.width_px - w.x0 - w.image.shape[1], w.y0, w.image[:, ::-1].copy())
                                   for w in windows]
                    frame = windows_frame(windows, camera=camera, t_tdb_s=observer.t_tdb_s, R_prior=prior,
                                          observer=observer, saturation_adu=saturation, frame_id=frame_id)
                    book["windowed"] += 1
                book["truth"][frame_id] = {t.name: [t.ra_rad, t.dec_rad] for t in rendered.truth.targets
                                           if t.name in moons}
                measured = tracker.step(frame, rng=np.random.default_rng([chunk.seed, 1, k]))
                if tracker.last_tracked is not None:  # checked against the truth: not a star the stage used
                    used, wrong = misidentified_stars(tracker.last_tracked, rendered.truth.stars)
                    book["stars_used"] += used
                    book["stars_misidentified"] += wrong
                    tracker.last_tracked = None
            except OpnavError as exc:
                book["skipped"][frame_id] = str(exc)
                continue
            if unidentified >= 0:  # until the first lock; later failures are losses of lock, counted as events
                if tracker.locked:
                    unidentified = -1
                elif _identifiable(frame, measured, catalog, ephemeris, chunk.options, chunk.tracking):
                    unidentified += 1  # stars enough, yet no match: a sparse field or the glare of Mars does not count
            if unidentified >= MAX_UNIDENTIFIED_FRAMES:
                raise NoSolutionError(
                    f"{frame_id}: star identification gave no attitude on {unidentified} frames with at least "
                    f"{IDENTIFIABLE_STARS} catalog stars predicted and as many sources detected, from the start of "
                    f"the chunk at frame_{chunk.first:05d}: the frames do not match the catalog around the "
                    "a-priori attitude (a camera model with mirrored or rotated axes or a wrong scale, an a-priori "
                    "attitude far off, or more false sources than stars?); stopping instead of navigating on the "
                    "a-priori attitude")
            if "attitude_prior" in measured.flags:
                # no star-identified attitude (too few stars, or none matched): records on the a-priori
                # attitude would carry its 0.05-degree sigma, nothing for navigation at 0.03"
                book["skipped"][frame_id] = (f"no star-identified attitude ({measured.n_stars_matched} stars "
                                             "matched); no records")
                continue
            # the moons of one frame share its attitude error: one record with their cross-covariance
            records.extend(join_frame_radec([r for r in measured.records if r.kind == "radec"]))
            for name in moons:
                if f"no_{name}" in measured.flags:
                    book["missed"][name].append({"frame": frame_id,
                                                 "hidden_by_primary": f"{name}_hidden" in measured.flags})
    book["events"] = tracker.events
    save_chunk(chunk.stem, chunk.key, records, book)
    return records, book


def save_chunk(stem: Path, key: str, records: list[Measurement], book: dict) -> None:
    """Write a finished chunk: its records (``<stem>.records.csv``), then its book-keeping with the
    records' checksum and ``key`` (``<stem>.done.json``, atomically, last: the mark of a finished chunk)."""
    book["hash"] = key
    write_csv(stem.with_suffix(".records.csv"), records, {"chunk": stem.name})
    book["records_sha256"] = file_sha256(stem.with_suffix(".records.csv"))
    atomic_write_text(stem.with_suffix(".done.json"), json.dumps(book, default=float))


@dataclass(frozen=True)
class _OffsetEphemeris:
    """``base`` with the moons moved by fixed offsets (km, ICRF): what the renderer draws when the
    image stage's ephemeris is wrong by them."""

    base: object
    offsets_km: dict

    def state(self, body: str, t, *, center: str = "ssb"):
        r, v = self.base.state(body, t, center=center)
        shift = self.offsets_km.get(body, 0.0) - self.offsets_km.get(center, 0.0)
        return r + shift, v

    def position(self, body: str, t, *, center: str = "ssb"):
        return self.state(body, t, center=center)[0]


def _drawn_ephemeris(ephemeris, chunk: _Chunk, k: int):
    """The ephemeris frame ``k`` is rendered with: the moons offset by the chunk's ephemeris error."""
    if chunk.moon_ephemeris_sigma_km <= 0.0:
        return ephemeris
    draw = [chunk.seed, 96] if chunk.moon_ephemeris_error == "bias" else [chunk.seed, 96, k]
    offsets = np.random.default_rng(draw).normal(0.0, chunk.moon_ephemeris_sigma_km, (len(chunk.moons), 3))
    return _OffsetEphemeris(ephemeris, dict(zip(chunk.moons, offsets)))


def _identifiable(frame, result, catalog, ephemeris, options, tracking) -> bool:
    """Whether star identification should have solved ``frame`` (its full-frame ``result`` has none):
    at least :data:`IDENTIFIABLE_STARS` catalog stars predicted from its a-priori attitude clear of
    the targets, the edges and saturated pixels, and as many point sources detected.

    Saturated pixels count because near Mars its bloom trail runs across the field: a star
    predicted on it is not in the frame, and a frame with three measurable stars (August,
    day 3, Phobos behind Mars) otherwise counted as one identification had failed on, and
    stopped the run after an hour of them."""
    from ..image.detect import FLAG_EXTENDED
    from ..image.tracking import _predict_stars, _views_with_primaries

    if result.detections is None or frame.observer is None:
        return False
    points = int(np.sum((result.detections.flags & FLAG_EXTENDED) == 0))
    if points < IDENTIFIABLE_STARS:
        return False
    views = (_views_with_primaries(frame.camera, frame.R_prior, frame.observer, ephemeris, options.targets)
             if options.targets else {})
    predicted = _predict_stars(frame.camera, frame.t_tdb_s, frame.observer, frame.R_prior, catalog, views, options,
                               tracking)
    if frame.saturation_adu is None:
        return len(predicted.rows) >= IDENTIFIABLE_STARS
    c = SATURATION_CLEARANCE_PX
    clear = [not np.any(frame.image[max(y - c, 0):y + c + 1, max(x - c, 0):x + c + 1] >= frame.saturation_adu)
             for x, y in np.rint(predicted.xy_px).astype(int)]
    return sum(clear) >= IDENTIFIABLE_STARS


def misidentified_stars(tracked, stars) -> tuple[int, int]:
    """(stars the tracked frame's attitude used, those whose centroid is more than 1 px from where the
    rendered truth put that catalog star, or that the truth does not have)."""
    where = dict(zip(stars.star_id.tolist(), stars.xy_px))
    rows = np.flatnonzero(tracked.used)
    wrong = sum(int(tracked.predicted.star_id[i]) not in where
                or float(np.hypot(*(tracked.centroids.xy[i] - where[int(tracked.predicted.star_id[i])]))) > 1.0
                for i in rows)
    return len(rows), wrong


def _faulted_render(scenario, catalog, ephemeris, chunk: _Chunk, faults: dict):
    """(render options, star catalog) the chunk's frames are rendered with, frame faults applied.

    The image stage keeps the true catalog and camera; only what is drawn changes. Missing
    stars are the same over the whole arc (one draw per run); uncatalogued point sources are
    fixed on the sky, spread over the cone the chunk's pointing covers.
    """
    from dataclasses import fields, replace

    from ..catalog import StarCatalog, synthetic_catalog
    from ..observer import Observer
    from ..sim.pointing import pointing_attitude

    options = scenario.options
    detector = options.detector
    if "cosmic_ray_factor" in faults or "hot_pixel_clusters" in faults:
        detector = replace(detector, cosmic_ray_rate_cm2_s=detector.cosmic_ray_rate_cm2_s * faults.get("cosmic_ray_factor", 1.0),
                           hot_pixel_clusters=detector.hot_pixel_clusters + int(faults.get("hot_pixel_clusters", 0)))
    options = replace(options, detector=detector, stray_light_e=options.stray_light_e + faults.get("stray_light_e", 0.0))
    drawn = catalog
    if faults.get("missing_star_fraction"):
        drawn = catalog.subset(np.random.default_rng([chunk.seed, 93]).random(len(catalog))
                               >= faults["missing_star_fraction"])
    if faults.get("uncatalogued_stars"):
        camera = scenario.camera
        samples = np.unique(np.linspace(0, len(chunk.epochs) - 1, 48).astype(int))
        boresights = np.array([pointing_attitude(scenario.pointing, Observer(float(chunk.epochs[i]), chunk.r_ssb_km[i],
                                                                             chunk.v_ssb_km_s[i]),
                                                 ephemeris, options.corrections).apply([0.0, 0.0, 1.0])
                               for i in samples])
        centre = boresights.mean(axis=0)
        centre /= np.linalg.norm(centre)
        field = camera.half_diagonal_fov_rad
        cap = field + float(np.max(np.arccos(np.clip(boresights @ centre, -1.0, 1.0))))
        # about `uncatalogued_stars` in a frame: that density (per field of view) over the whole cap
        field_area = camera.width_px * camera.height_px * camera.pixel_scale_rad**2
        rng = np.random.default_rng([chunk.seed, 95, chunk.first])
        count = rng.poisson(faults["uncatalogued_stars"] * 2.0 * np.pi * (1.0 - np.cos(cap)) / field_area)
        extra = synthetic_catalog(count, rng=rng, vmag_range=(8.0, 11.0), centre_icrf=centre, radius_rad=cap)
        # ids beyond HIP's and below Gaia's: no catalog star shares them
        extra = replace(extra, hip=np.zeros(count, np.int64), gaia_id=2**34 + np.arange(count, dtype=np.int64))
        drawn = StarCatalog(**{f.name: np.concatenate([getattr(drawn, f.name), getattr(extra, f.name)])
                               for f in fields(drawn)})
    return options, drawn


def load_chunk(stem: Path, key: str):
    """(records, book) of a finished chunk made from ``key`` whose records still have their checksum, else None."""
    try:
        book = json.loads(stem.with_suffix(".done.json").read_text())
        if book.get("hash") != key or book.get("records_sha256") != file_sha256(stem.with_suffix(".records.csv")):
            return None
        return read_csv(stem.with_suffix(".records.csv")), book
    except (OSError, ValueError, OpnavError):
        return None


def _merge(result: StreamResult, records: list[Measurement], book: dict) -> None:
    result.records.extend(records)
    result.skipped.update(book["skipped"])
    for name, misses in book["missed"].items():
        result.missed.setdefault(name, []).extend(misses)
    result.events.extend(book["events"])
    result.truths.update({frame: _FrameTruth(moons) for frame, moons in book["truth"].items()})
    result.dumped.extend(Path(p) for p in book["dumped"])
    result.frames_windowed += book["windowed"]
    result.frames_full += book["full"]
    result.frames_dropped += book["dropped"]
    result.stars_used += book["stars_used"]
    result.stars_misidentified += book["stars_misidentified"]
