"""Image-in-the-loop in memory: truth -> (windowed) render -> tracking image stage -> records, chunk by chunk.

For each epoch the frame is rendered along the truth (:func:`opnav.render.render_frame`
or, while the :class:`~opnav.image.tracking.Tracker` holds lock, only the windows it will
read: :meth:`~opnav.image.tracking.Tracker.read_boxes` and :func:`opnav.render.render_windows`,
each window read out with the same detector model as a full frame) and measured at once
from memory: no FITS file per frame. Every ``dump_every``-th frame is rendered in full and
written as FITS with its truth (``frames/``) for inspection.

The frames go in chunks of ``chunk_frames`` (a day at one a minute). Each chunk starts
from lost-in-space acquisition on its first frame, as a camera switched on, and depends on
nothing before it, so chunks run in ``workers`` processes side by side and give the same
records in any number of them. Each chunk's records (``stream/chunk_NNNNN.records.csv``)
and its book-keeping (``chunk_NNNNN.done.json``: tracking events, frames skipped, moons
missed, the moons' true RA/Dec per frame) are written atomically when the chunk ends, the
JSON last; a re-run reads the finished chunks (same content hash), so an interrupted run
loses at most the chunks under way.

The renderer and the image stage read the scenario's star catalog
(:func:`opnav.catalog.load_catalog`) and the Chebyshev cache of DE421
(:func:`opnav.ephemeris.cache.default_cached_ephemeris`, within 1 cm of it): the ephemeris
calls of each frame's geometry would otherwise cost more than its pixels.

Noise of frame ``k`` comes from ``default_rng([seed, k])``; a frame rendered in windows
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
from tqdm import tqdm

from ..errors import InputError, OpnavError
from ..records import Measurement, atomic_write_text, read_csv, write_csv


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


def stream_frames(scenario, epochs: np.ndarray, r_ssb_km: np.ndarray, v_ssb_km_s: np.ndarray, out: Path, *,
                  seed: int, options, tracking=None, moons: tuple[str, ...], dump_every: int = 0,
                  chunk_frames: int = 1440, key: str = "", workers: int = 1, progress: bool = True) -> StreamResult:
    """Render and measure every epoch in memory (module docstring).

    Parameters
    ----------
    scenario : opnav.scenario.Scenario
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
                     Path(out) / "frames", f"{key}:{start}:{min(start + chunk_frames, len(epochs))}:{dump_every}:own-acquisition",
                     seed, options, tracking or TrackingOptions(), tuple(moons), dump_every)
              for start in range(0, len(epochs), chunk_frames)]
    result = StreamResult(missed={name: [] for name in moons})
    done: dict[int, tuple] = {}
    for index, chunk in enumerate(chunks):
        finished = _load_chunk(chunk.stem, chunk.key)
        if finished is not None:
            done[index] = finished
            result.chunks_reused += 1
    todo = [index for index in range(len(chunks)) if index not in done]
    bar = tqdm(total=len(epochs), desc="frames", unit="frame", disable=not progress)
    bar.update(sum(len(chunks[index].epochs) for index in done))
    workers = min(int(workers), len(todo))
    if workers <= 1:
        for index in todo:
            done[index] = _run_chunk(chunks[index], bar)
    else:
        # spawned, not forked: the parent may hold numba's thread pool, which a fork would copy broken
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_worker_init) as pool:
            futures = {pool.submit(_run_chunk, chunks[index]): index for index in todo}
            for future in as_completed(futures):
                done[futures[future]] = future.result()
                bar.update(len(chunks[futures[future]].epochs))
    bar.close()
    for index in range(len(chunks)):
        _merge(result, *done[index])
    return result


def _worker_init() -> None:
    """A chunk worker runs compiled kernels on one thread: the processes already fill the cores."""
    import numba

    numba.set_num_threads(1)


_LOADED: dict = {}


def _sources(catalog_path):
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
    from ..render.frames_io import saturation_level_adu, write_frame
    from ..render.sequence import body_rate, pointing_attitude

    scenario, moons = chunk.scenario, chunk.moons
    catalog, ephemeris = _sources(scenario.catalog_path)
    tracker = Tracker(catalog, ephemeris, chunk.options, chunk.tracking)
    camera = scenario.camera
    corrections = scenario.options.corrections
    saturation = saturation_level_adu(camera)
    records, book = [], {"events": [], "skipped": {}, "missed": {name: [] for name in moons}, "truth": {},
                         "dumped": [], "windowed": 0, "full": 0}
    with quiet_moon_misses():
        for offset in range(len(chunk.epochs)):
            k = chunk.first + offset
            frame_id = f"frame_{k:05d}"
            observer = Observer(float(chunk.epochs[offset]), chunk.r_ssb_km[offset], chunk.v_ssb_km_s[offset])
            attitude = pointing_attitude(scenario.pointing, observer, ephemeris, corrections)
            omega = body_rate(scenario.pointing, observer, ephemeris, corrections)
            rng = np.random.default_rng([chunk.seed, k])
            dump = chunk.dump_every > 0 and k % chunk.dump_every == 0
            boxes = None if dump else tracker.read_boxes(camera, observer.t_tdb_s, observer, attitude)
            try:
                if boxes is None:
                    rendered = render_frame(camera, attitude, observer, catalog=catalog, targets=scenario.targets,
                                            ephemeris=ephemeris, options=scenario.options, omega_cam_rad_s=omega,
                                            rng=rng)
                    if dump:
                        path, _ = write_frame(chunk.frames_dir / f"{frame_id}.fits", rendered.image, rendered.header,
                                              rendered.truth)
                        book["dumped"].append(str(path))
                    frame = FrameInput.from_camera(rendered.image, camera, observer.t_tdb_s, attitude, observer,
                                                   saturation_adu=saturation, frame_id=frame_id,
                                                   flags=rendered.truth.flags)
                    book["full"] += 1
                else:
                    rendered = render_windows(camera, attitude, observer, catalog=catalog, targets=scenario.targets,
                                              ephemeris=ephemeris, options=scenario.options, omega_cam_rad_s=omega,
                                              rng=rng, boxes=boxes)
                    frame = windows_frame(rendered.windows, camera=camera, t_tdb_s=observer.t_tdb_s, R_prior=attitude,
                                          observer=observer, saturation_adu=saturation, frame_id=frame_id)
                    book["windowed"] += 1
                book["truth"][frame_id] = {t.name: [t.ra_rad, t.dec_rad] for t in rendered.truth.targets
                                           if t.name in moons}
                measured = tracker.step(frame, rng=np.random.default_rng([chunk.seed, 1, k]))
            except OpnavError as exc:
                book["skipped"][frame_id] = str(exc)
            else:
                records.extend(r for r in measured.records if r.kind == "radec")
                for name in moons:
                    if f"no_{name}" in measured.flags:
                        book["missed"][name].append({"frame": frame_id,
                                                     "hidden_by_primary": f"{name}_hidden" in measured.flags})
            if bar is not None:
                bar.update(1)
    book["events"] = tracker.events
    book["hash"] = chunk.key
    write_csv(chunk.stem.with_suffix(".records.csv"), records, {"chunk": chunk.stem.name})
    atomic_write_text(chunk.stem.with_suffix(".done.json"), json.dumps(book, default=float))
    return records, book


def _load_chunk(stem: Path, key: str):
    """(records, book) of a finished chunk made from ``key``, else None."""
    try:
        book = json.loads(stem.with_suffix(".done.json").read_text())
        if book.get("hash") != key:
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
