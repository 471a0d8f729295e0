"""Image-in-the-loop in memory: truth -> (windowed) render -> tracking image stage -> records, chunk by chunk.

For each epoch the frame is rendered along the truth (:func:`opnav.render.render_frame`
or, while the :class:`~opnav.image.tracking.Tracker` holds lock, only the windows it will
read: :meth:`~opnav.image.tracking.Tracker.read_boxes` and :func:`opnav.render.render_windows`,
each window read out with the same detector model as a full frame) and measured at once
from memory: no FITS file per frame. Every ``dump_every``-th frame is rendered in full and
written as FITS with its truth (``frames/``) for inspection.

The frames go in chunks of ``chunk_frames``; each chunk's records
(``stream/chunk_NNNNN.records.csv``) and its book-keeping (``chunk_NNNNN.done.json``:
tracking events, frames skipped, moons missed, the moons' true RA/Dec per frame, the
tracker's state) are written atomically when the chunk ends, the JSON last. A re-run
reads the finished chunks (same content hash) and continues with the tracker's saved
state, so an interrupted run loses at most one chunk.

Noise of frame ``k`` comes from ``default_rng([seed, k])``; a frame rendered in windows
draws its noise window by window, so its pixels differ from the full render's by the
noise draw only (same statistics, ``tests/render/test_render_io.py``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..errors import OpnavError
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


def stream_frames(scenario, epochs: np.ndarray, r_ssb_km: np.ndarray, v_ssb_km_s: np.ndarray, out: Path, *,
                  seed: int, catalog, ephemeris, tracker, moons: tuple[str, ...], dump_every: int = 0,
                  chunk_frames: int = 1440, key: str = "", progress: bool = True) -> StreamResult:
    """Render and measure every epoch in memory (module docstring).

    Parameters
    ----------
    scenario : opnav.scenario.Scenario
        Camera, pointing law, targets, render options.
    epochs : (M,) array
        Mid-exposure epochs, TDB s past J2000.
    r_ssb_km, v_ssb_km_s : (M, 3) arrays
        True observer states (SSB, ICRF).
    out : Path
        Run folder (``stream/`` chunks, ``frames/`` dumps).
    seed : int
    catalog, ephemeris
        Star catalog and ephemeris of both the renderer and the image stage.
    tracker : opnav.image.tracking.Tracker
        The image stage (its options name the moons measured).
    moons : tuple of str
        Moons whose true RA/Dec is kept for the measurement errors.
    dump_every : int
        Write every this-many-th frame as FITS (0: none).
    chunk_frames : int
        Frames per chunk (the unit of resumption).
    key : str
        Content hash of the run; chunks made from another are recomputed.
    """
    from ..demo import quiet_moon_misses

    with quiet_moon_misses():
        return _stream(scenario, epochs, r_ssb_km, v_ssb_km_s, out, seed=seed, catalog=catalog, ephemeris=ephemeris,
                       tracker=tracker, moons=moons, dump_every=dump_every, chunk_frames=chunk_frames, key=key,
                       progress=progress)


def _stream(scenario, epochs, r_ssb_km, v_ssb_km_s, out, *, seed, catalog, ephemeris, tracker, moons, dump_every,
            chunk_frames, key, progress) -> StreamResult:
    from ..observer import Observer
    from ..render.frame import render_frame, render_windows
    from ..render.frames_io import saturation_level_adu, write_frame
    from ..render.sequence import body_rate, pointing_attitude
    from ..image.pipeline import FrameInput
    from ..image.tracking import windows_frame

    folder = Path(out) / "stream"
    frames_dir = Path(out) / "frames"
    camera = scenario.camera
    corrections = scenario.options.corrections
    saturation = saturation_level_adu(camera)
    result = StreamResult(missed={name: [] for name in moons})
    count = len(epochs)
    bar = tqdm(total=count, desc="frames", unit="frame", disable=not progress)
    for start in range(0, count, chunk_frames):
        stop = min(start + chunk_frames, count)
        stem = folder / f"chunk_{start // chunk_frames:05d}"
        chunk_key = f"{key}:{start}:{stop}:{dump_every}"
        done = _load_chunk(stem, chunk_key)
        if done is not None:
            _merge(result, *done)
            tracker.restore(done[1]["tracker"])
            result.chunks_reused += 1
            bar.update(stop - start)
            continue
        records, book = [], {"events": [], "skipped": {}, "missed": {name: [] for name in moons}, "truth": {},
                             "dumped": [], "windowed": 0, "full": 0}
        events_before = len(tracker.events)
        for k in range(start, stop):
            frame_id = f"frame_{k:05d}"
            observer = Observer(float(epochs[k]), r_ssb_km[k], v_ssb_km_s[k])
            attitude = pointing_attitude(scenario.pointing, observer, ephemeris, corrections)
            omega = body_rate(scenario.pointing, observer, ephemeris, corrections)
            rng = np.random.default_rng([seed, k])
            dump = dump_every > 0 and k % dump_every == 0
            boxes = None if dump else tracker.read_boxes(camera, observer.t_tdb_s, observer, attitude)
            try:
                if boxes is None:
                    rendered = render_frame(camera, attitude, observer, catalog=catalog, targets=scenario.targets,
                                            ephemeris=ephemeris, options=scenario.options, omega_cam_rad_s=omega, rng=rng)
                    if dump:
                        path, _ = write_frame(frames_dir / f"{frame_id}.fits", rendered.image, rendered.header,
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
                truth = rendered.truth
                book["truth"][frame_id] = {t.name: [t.ra_rad, t.dec_rad] for t in truth.targets if t.name in moons}
                measured = tracker.step(frame, rng=np.random.default_rng([seed, 1, k]))
            except OpnavError as exc:
                book["skipped"][frame_id] = str(exc)
                bar.update(1)
                continue
            records.extend(r for r in measured.records if r.kind == "radec")
            for name in moons:
                if f"no_{name}" in measured.flags:
                    book["missed"][name].append({"frame": frame_id, "hidden_by_primary": f"{name}_hidden" in measured.flags})
            bar.update(1)
        book["events"] = tracker.events[events_before:]
        book["tracker"] = tracker.state()
        book["hash"] = chunk_key
        write_csv(stem.with_suffix(".records.csv"), records, {"chunk": stem.name})
        atomic_write_text(stem.with_suffix(".done.json"), json.dumps(book, default=float))
        _merge(result, records, book)
    bar.close()
    return result


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
