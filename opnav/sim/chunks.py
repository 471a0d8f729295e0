"""The loop (:func:`opnav.sim.loop.run_frames`) in chunks: resumable, and in worker processes.

The arc goes in chunks of ``chunk_frames``. Each chunk starts its sensors afresh (a tracker
acquires lost-in-space on the chunk's first frame, as a camera switched on) and depends on
nothing before it, so chunks run in ``workers`` processes side by side and give the same results
in any number of them (every random stream is the frame's own, :mod:`opnav.sim.loop`).

With a ``folder``, each chunk's records (``<stem>.records.csv``) and the rest of its result
(``<stem>.done.json``: skipped frames, misses, tracking events, true target directions, counts)
are written atomically when the chunk ends, the JSON last, with the records' checksum and the
chunk's key; a re-run reads the finished chunks back (same key, records intact), so an interrupted
run loses at most the chunks under way and a damaged chunk is made again.
"""

from __future__ import annotations

import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError, OpnavError
from ..files import atomic_write_text
from ..records import file_sha256, read_csv, write_csv
from .loop import run_frames
from .results import LoopResult, result_from_json, result_to_json
from .sensors import Arc, Loop

#: Written into every chunk's key: chunks of another layout of ``done.json`` are made again.
CHUNK_FORMAT = "sim-loop-1"


@dataclass(frozen=True, eq=False)
class Chunk:
    """One chunk: the loop, its part of the arc, its files' stem (None: not saved) and its key."""

    loop: Loop
    arc: Arc
    stem: Path | None
    key: str


def run_chunks(loop: Loop, arc: Arc, *, folder: str | Path | None, key: str = "", chunk_frames: int = 1440,
               workers: int = 1, progress: bool = False, unit: str = "frame", name: str = "chunk") -> LoopResult:
    """Run ``loop`` over ``arc`` in chunks (module notes).

    Parameters
    ----------
    loop : Loop
    arc : Arc
    folder : path or None
        Where finished chunks are saved as ``<name>_NNNNN.*`` and read back from (None: not saved).
    key : str
        Content hash of the run; chunks saved from another are made again.
    chunk_frames : int
        Frames per chunk (the unit of resumption and of work per process).
    workers : int
        Processes the chunks run in (1: this one). The results do not depend on it.
    progress : bool
        Show a progress bar (by frame; by finished chunk with several workers).
    unit : str
        The progress bar's unit.
    name : str
        Stem of the chunk files.

    Returns
    -------
    LoopResult
        The chunks' results joined in order; ``chunks_reused`` counts those read back.
    """
    if int(workers) != workers or workers < 1:
        raise InputError(f"workers must be a positive integer, got {workers!r}")
    if int(chunk_frames) != chunk_frames or chunk_frames < 1:
        raise InputError(f"chunk_frames must be a positive integer, got {chunk_frames!r}")
    chunk_frames = int(chunk_frames)
    chunks = [Chunk(loop, arc.part(start, start + chunk_frames),
                    None if folder is None else Path(folder) / f"{name}_{start // chunk_frames:05d}",
                    f"{key}:{start}:{min(start + chunk_frames, len(arc))}:{CHUNK_FORMAT}")
              for start in range(0, len(arc), chunk_frames)]
    done: dict[int, LoopResult] = {}
    for index, chunk in enumerate(chunks):
        if chunk.stem is not None:
            finished = load_chunk(chunk.stem, chunk.key)
            if finished is not None:
                done[index] = finished
    reused = len(done)
    todo = [index for index in range(len(chunks)) if index not in done]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(arc), desc=f"{unit}s", unit=unit)
        bar.update(sum(len(chunks[index].arc) for index in done))
    try:
        workers = min(int(workers), len(todo))
        if workers <= 1:
            for index in todo:
                done[index] = _work(chunks[index], None if bar is None else (lambda: bar.update(1)))
        else:
            # spawned, not forked: the parent may hold numba's thread pool, which a fork would copy broken
            with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                     initializer=_worker_init) as pool:
                futures = {pool.submit(_work, chunks[index]): index for index in todo}
                for future in as_completed(futures):
                    done[futures[future]] = future.result()
                    if bar is not None:
                        bar.update(len(chunks[futures[future]].arc))
    finally:
        if bar is not None:
            bar.close()
    return LoopResult.combine([done[index] for index in range(len(chunks))], chunks_reused=reused)


def _work(chunk: Chunk, on_frame=None) -> LoopResult:
    """Run one chunk and save it (when it has a stem)."""
    result = run_frames(chunk.loop, chunk.arc, on_frame=on_frame)
    if chunk.stem is not None:
        save_chunk(chunk.stem, chunk.key, result)
    return result


def _worker_init() -> None:
    """A chunk worker runs compiled kernels on one thread (the processes already fill the cores) and
    keeps freed memory for the next frame (:func:`opnav.allocator.keep_freed_memory`)."""
    from ..allocator import keep_freed_memory
    from ..compiled import use_one_thread

    use_one_thread()
    keep_freed_memory()


def save_chunk(stem: Path, key: str, result: LoopResult) -> None:
    """Write a finished chunk: its records (``<stem>.records.csv``), then the rest of its result with the
    records' checksum and ``key`` (``<stem>.done.json``, atomically, last: the mark of a finished chunk)."""
    stem = Path(stem)
    write_csv(stem.with_suffix(".records.csv"), list(result.records), {"chunk": stem.name})
    done = {**result_to_json(result), "hash": key, "records_sha256": file_sha256(stem.with_suffix(".records.csv"))}
    atomic_write_text(stem.with_suffix(".done.json"), json.dumps(done, default=float))


def load_chunk(stem: Path, key: str) -> LoopResult | None:
    """The result of a finished chunk made from ``key`` whose records still have their checksum, else None."""
    stem = Path(stem)
    try:
        done = json.loads(stem.with_suffix(".done.json").read_text())
        if done.get("hash") != key or done.get("records_sha256") != file_sha256(stem.with_suffix(".records.csv")):
            return None
        return result_from_json(done, read_csv(stem.with_suffix(".records.csv")))
    except (OSError, ValueError, KeyError, TypeError, OpnavError):
        return None
