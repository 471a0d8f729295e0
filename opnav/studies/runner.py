"""Run one study: simulate -> filters -> report, each stage saved under a content hash.

Stages and their files in the output folder:

``simulate``
    ``measurements.csv`` (+ ``.json``), ``truth.npz`` and ``simulation.json``: the
    records, the true states at the measurement epochs, the navigation set-up (in
    image mode also ``frames/``: the rendered frames the records were measured on);
    ``measurements.tdm`` and its sidecar ``measurements.tdm.cov.csv``: the RA/Dec records (a moon
    pair's cross-covariance in the sidecar) as a CCSDS TDM (:mod:`opnav.ccsds`), when any;
``filter <name>``
    ``filters/<name>.npz`` (errors, 1-sigmas, NEES, NIS), ``filters/<name>.oem`` (the
    estimates with their covariance as a CCSDS OEM) and ``filters/<name>.json``
    (figures of :func:`opnav.studies.common.filter_metrics`, consistency flags of
    :mod:`opnav.filters.monitor`, wall time);
``report``
    ``summary.json``, ``report.md``, ``report.html`` (:mod:`opnav.studies.report`).

``summary.json``'s ``stages_wall_s`` accounts for the whole command, one stage after another
(:class:`StageClock`): ``setup`` (from the start of the process when ``RunOptions.started``
says when that was: imports, reading the run file), ``simulate``, ``write measurements``
(CSV, JSON, TDM, truth, checksums), per filter ``filter <name>`` (the filter and its figures)
and ``write <name> estimates`` (npz, OEM, JSON, checksums), and ``report`` (figures,
Markdown, HTML). A stage loaded from an earlier run is named with `` (reused)`` and
counts the time it took to load it; what the stage cost when it was made stays in its own
record (``simulation.json``, ``filters/<name>.json``; a filter's ``wall_s``).

Every file is written atomically. Each stage's JSON holds the SHA-256 of what it
was made from (the run file's study, seed and settings, opnav's version and, for a
filter, the simulation's hash and the filter name); a re-run with the same inputs
loads the stage instead of recomputing it, so ``kill -9`` loses at most the stage
that was running, and a changed setting recomputes exactly what depends on it.

The runner is quiet: progress messages go to ``RunOptions.log`` (``opnav run`` prints them on
stderr), or to this module's logger at INFO when no callback is given; progress bars only when
``RunOptions.progress``. What a study offers is asked of its :class:`~opnav.studies.base.Study`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..errors import InputError
from ..filters.estimates import Track, save_npz, write_json, write_oem, write_records_tdm
from ..filters.monitor import check_history
from ..filters.navigate import navigate
from ..filters.options import NavigationConfig
from ..files import atomic_write_text, folder_lock
from ..records import file_sha256, read_csv, write_csv
from .base import Study
from .common import Simulation, filter_metrics, measurements_summary, track
from .faults import apply_faults, truth_at_tags
from .settings import MODES, RunFile, check_run_filters

_log = logging.getLogger(__name__)

#: Refused records listed by name in a filter's record and the report (all are counted).
MAX_LISTED = 1000


@dataclass(frozen=True)
class RunOptions:
    """How to run: output folder, filters (None: the run file's), mode (None: the run file's),
    ``progress``: progress bars (off by default), ``checked``: every filter's covariance checked
    after every record (:func:`opnav.filters.run.run_filter`), its worst conditioning in the
    filter's figures, ``workers``: processes image mode renders and measures in (None: one per
    core; the records do not depend on it), ``log``: where progress messages go (one line
    each, ``[run name] message``; None: this module's logger at INFO), and ``started``: the
    ``time.perf_counter()`` reading when the command started (``opnav run``: the process start),
    so that the ``setup`` stage counts the time before :func:`run_study` (None: from its call);
    ``command``: the command line that ran it (``sys.argv``), for the report's provenance (None: run
    from Python); ``report_frame``: the axes of the report's error plots, ``rtn`` (radial,
    along-track, cross-track of the true orbit about the centre body) or ``icrf``."""

    out: Path
    filters: tuple[str, ...] | None = None
    mode: str | None = None
    progress: bool = False
    checked: bool = False
    workers: int | None = None
    log: Callable[[str], None] | None = None
    started: float | None = None
    command: tuple[str, ...] | None = None
    report_frame: str = "rtn"


class StageClock:
    """Wall time of a command's stages, one after another: :meth:`lap` gives a stage every second since
    the previous lap (or since ``started``, a ``time.perf_counter()`` reading; None: now), so the
    stages add up to the command's wall time from ``started`` to the last lap."""

    def __init__(self, started: float | None = None) -> None:
        self._last = time.perf_counter() if started is None else float(started)
        self.walls: dict[str, float] = {}

    def lap(self, stage: str) -> float:
        """Close ``stage`` (added to its earlier laps, if any): its wall time since the previous lap, s."""
        now = time.perf_counter()
        wall = now - self._last
        self._last = now
        self.walls[stage] = self.walls.get(stage, 0.0) + wall
        return wall


def study_of(run: RunFile) -> Study:
    """The :class:`~opnav.studies.base.Study` a run file names."""
    from . import STUDIES

    return STUDIES[run.study]


def digest(payload: dict) -> str:
    """SHA-256 of a JSON-able ``payload`` (sorted keys), hex."""
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()


def _stage_done(path: Path, key: str) -> dict | None:
    """The stage record at ``path`` if it exists and was made from ``key``."""
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return record if record.get("hash") == key else None


def navigation_json(nav: NavigationConfig) -> dict:
    out = asdict(nav)
    out["x0"], out["P0"] = nav.x0.tolist(), nav.P0.tolist()
    out["ephemeris_targets"] = list(nav.ephemeris_targets)
    out["camera_parameters"] = list(nav.camera_parameters)
    out["camera_covariance"] = None if nav.camera_covariance is None else nav.camera_covariance.tolist()
    return out


def _navigation_from_json(data: dict) -> NavigationConfig:
    data = dict(data)
    data["x0"], data["P0"] = np.array(data["x0"]), np.array(data["P0"])
    data["ephemeris_targets"] = tuple(data["ephemeris_targets"])
    return NavigationConfig(**data)


def simulation_key(run: RunFile, mode: str = "measurements") -> str:
    """The hash that marks a saved simulation as this run's (:func:`simulate_stage`)."""
    return digest({"run": run.describe(mode), "opnav": __version__, "stage": "simulate", "mode": mode})


def load_simulation(run: RunFile, out: Path, log=lambda message: None,
                    mode: str = "measurements") -> tuple[Simulation, str, float] | None:
    """The simulation saved in ``out`` for this run and mode, as :func:`simulate_stage` returns it,
    or None when there is none, it belongs to another run, or its files fail their checksums."""
    key = simulation_key(run, mode)
    record = _stage_done(out / "simulation.json", key)
    if record is None:
        return None
    if not _files_intact(out, record):
        log("simulate: the saved measurements or truth do not match their checksums; simulating again")
        return None
    try:
        truth = np.load(out / "truth.npz")
        records = read_csv(out / "measurements.csv")
    except (OSError, ValueError, InputError):
        return None
    log(f"simulate: reusing {out / 'measurements.csv'} ({len(records)} records)")
    sim = Simulation(record["center"], truth["epochs"], truth["truth"], records,
                     _navigation_from_json(record["navigation"]), study_of(run).dynamics(run.settings),
                     float(record["window_start_tdb_s"]), record["paper"], record["facts"])
    return sim, key, float(record["wall_s"])


def simulate_stage(run: RunFile, out: Path, log, mode: str = "measurements",
                   progress: bool = False, workers: int | None = None,
                   clock: StageClock | None = None) -> tuple[Simulation, str, float]:
    """Load the simulation if its files match the run, else simulate and save it: (sim, hash, wall_s).

    ``mode`` ``images`` renders frames and measures them (the study's ``simulate_images``, in
    ``workers`` processes; None: one per core). ``clock`` gets the laps ``simulate`` and ``write
    measurements`` (``simulate (reused)`` when the saved one is loaded).
    """
    clock = clock or StageClock()
    study = study_of(run)
    if mode == "images" and not study.image_mode:
        raise InputError(f"{run.path}: image mode is not available for study {run.study!r} "
                         "(S1 and S3 have it; measurement mode adds the study's noise directly)")
    frame_faults = run.faults.on_frames if run.faults is not None else {}
    if frame_faults and mode != "images":
        raise InputError(f"{run.path}: faults {sorted(frame_faults)} act on rendered frames; run with --mode images")
    saved = load_simulation(run, out, log, mode)
    if saved is not None:
        clock.lap("simulate (reused)")
        return saved
    key = simulation_key(run, mode)
    log(f"simulate: {run.study} truth and measurements (seed {run.seed}, {mode})")
    begin = time.perf_counter()
    if mode == "images":
        sim = study.simulate_images(run.settings, run.seed, out, progress=progress,
                                    workers=workers or os.cpu_count() or 1, faults=run.faults)
    else:
        sim = study.simulate(run.settings, run.seed)
    if run.faults is not None and run.faults.active:
        records, done = apply_faults(sim.records, run.faults, run.seed)
        sim = replace(sim, records=records, facts={**sim.facts, "faults": done})
        if run.faults.retags:  # errors are taken at the epochs the filters believe
            tags = np.unique([r.t_tdb_s for r in records])
            sim = replace(sim, epochs=tags, truth=truth_at_tags(sim.epochs, sim.truth, tags))
    wall = time.perf_counter() - begin
    clock.lap("simulate")
    write_csv(out / "measurements.csv", sim.records, {"study": run.study, "seed": run.seed})
    write_records_tdm(out / "measurements.tdm", sim.records, spacecraft=run.spacecraft)
    save_npz(out / "truth.npz", epochs=sim.epochs, truth=sim.truth)
    atomic_write_text(out / "simulation.json", json.dumps({
        "hash": key, "run": run.describe(mode), "center": sim.center, "navigation": navigation_json(sim.navigation),
        "window_start_tdb_s": sim.window_start_tdb_s, "paper": sim.paper, "facts": sim.facts, "wall_s": wall,
        "files": {name: file_sha256(out / name) for name in ("measurements.csv", "truth.npz")},
    }, indent=2, default=str))
    clock.lap("write measurements")
    return sim, key, wall


def _files_intact(folder: Path, record: dict) -> bool:
    """Whether every file a stage record lists (``files``: name -> SHA-256) still has its checksum."""
    files = record.get("files")
    return isinstance(files, dict) and bool(files) and all(
        file_sha256(folder / name) == checksum for name, checksum in files.items())


def filter_stage(name: str, sim: Simulation, sim_key: str, out: Path, progress: bool, log,
                 checked: bool = False, clock: StageClock | None = None, spacecraft: str = "opnav") -> dict:
    """Run filter ``name`` over the simulation unless its saved result matches: the stage record.

    ``spacecraft`` is the OEM's ``OBJECT_NAME`` (the run file's :attr:`RunFile.spacecraft`).

    ``clock`` gets the laps ``filter <name>`` (the filter and its figures) and ``write <name>
    estimates`` (``filter <name> (reused)`` when the saved result is loaded).
    """
    clock = clock or StageClock()
    identity = {"simulation": sim_key, "filter": name, "opnav": __version__, "stage": "filter"}
    if checked:  # unchecked runs keep their old hashes
        identity["checked"] = True
    key = digest(identity)
    path = out / "filters" / f"{name}.json"
    record = _stage_done(path, key)
    if record is not None and _files_intact(out / "filters", record):
        log(f"filter {name}: reusing {path}")
        clock.lap(f"filter {name} (reused)")
        return record
    if record is not None:
        log(f"filter {name}: the saved estimates do not match their checksums; filtering again")
    log(f"filter {name}: {len(sim.records)} records")
    result = navigate(sim.records, sim.navigation, filter_name=name, force_model=sim.force_model, center=sim.center,
                      progress=progress, checked=checked)
    history, wall = result.history, result.wall_s
    metrics = filter_metrics(history, sim)
    arrays = track(history, sim)
    consistency = check_history(history, final_nees=float(arrays["nees"][-1]))
    refused = [{"t_tdb_s": float(r.t_tdb_s), "kind": r.kind, "target": r.target, "reason": reason}
               for r, ok, reason in zip(sorted(sim.records, key=lambda r: r.t_tdb_s), history.accepted, history.reasons)
               if not ok]
    clock.lap(f"filter {name}")
    save_npz(out / "filters" / f"{name}.npz", **arrays)
    write_oem(out / "filters" / f"{name}.oem", Track.from_history(history), center=sim.center,
              object_name=spacecraft, comment=f"opnav run {sim_key[:12]}, filter {name}: estimates after each record")
    record = {"hash": key, "filter": name, "wall_s": wall, **metrics, "consistency": consistency.to_dict(),
              "refused": refused[:MAX_LISTED], "refused_count": len(refused),
              "files": {f"{name}.npz": file_sha256(out / "filters" / f"{name}.npz")}}
    if history.health is not None:
        record["covariance_health"] = history.health
    write_json(path, record)
    clock.lap(f"write {name} estimates")
    return record


def _evaluate_study(run: RunFile, out: Path, log, clock: StageClock, command: tuple[str, ...] | None = None,
                    mode: str = "measurements", progress: bool = False, workers: int | None = None) -> dict:
    """Studies with their own evaluation (S2, S4), one stage: ``evaluation.json`` (the figures),
    ``evaluation.npz`` (what the report plots) and one OEM per estimated trajectory
    (``filters/<name>.oem``), all checksummed in ``evaluation.json`` so a re-run reuses them only when
    intact; then ``summary.json`` and the report (the study's ``report_blocks``; ``command``, the
    command line's argv, goes into its provenance)."""
    from .report_page import provenance, write_page

    study = study_of(run)
    spacecraft = run.spacecraft
    identity = {"run": run.describe(mode), "opnav": __version__, "stage": "evaluate", "object_name": spacecraft}
    if mode != "measurements":  # measurement-mode runs keep their hashes
        identity["mode"] = mode
    key = digest(identity)
    record = _stage_done(out / "evaluation.json", key)
    if record is not None and not _files_intact(out, record):
        log("evaluate: the saved arrays or estimates do not match their checksums; evaluating again")
        record = None
    clock.lap("setup")
    if record is None:
        begin = time.perf_counter()
        if mode == "images":
            result = study.evaluate_images(run.settings, run.seed, log, out, progress=progress,
                                           workers=1 if workers is None else workers)
        else:
            result = study.evaluate(run.settings, run.seed, log)
        wall = time.perf_counter() - begin
        save_npz(out / "evaluation.npz", **result.arrays)
        files = ["evaluation.npz"]
        for trajectory in result.trajectories:
            name = f"filters/{trajectory.name}.oem"
            (out / "filters").mkdir(exist_ok=True)
            write_oem(out / name, trajectory.track, center=trajectory.center, object_name=spacecraft,
                      comment=f"opnav run {key[:12]}: {trajectory.description or trajectory.name}")
            files.append(name)
        record = {"hash": key, **result.summary, "wall_s": wall,
                  "estimates": {t.name: {"file": f"filters/{t.name}.oem", "center": t.center}
                                for t in result.trajectories},
                  "files": {name: file_sha256(out / name) for name in files}}
        write_json(out / "evaluation.json", record)
        clock.lap("evaluate")
    else:
        log(f"evaluate: reusing {out / 'evaluation.json'}")
        clock.lap("evaluate (reused)")
    summary = {"run": run.describe(mode), "mode": mode, "opnav": __version__,
               **{k: v for k, v in record.items() if k not in ("hash", "wall_s", "files")}}
    with np.load(out / "evaluation.npz") as saved:
        arrays = {name: saved[name] for name in saved.files}
    write_page(out, f"{run.name} ({run.study.upper()}, seed {run.seed})", study.report_blocks(summary, arrays),
               provenance(command, run.path if Path(run.path).is_file() else None))
    clock.lap("report")
    summary["stages_wall_s"] = clock.walls
    write_json(out / "summary.json", summary)
    log(f"done: {out / 'summary.json'}, {out / 'report.html'}")
    return summary


def run_study(run: RunFile, options: RunOptions) -> dict:
    """Run ``run`` into ``options.out`` (module notes); returns the summary written to ``summary.json``.

    Raises
    ------
    InputError
        Bad options, or another opnav process writing ``options.out`` (:func:`opnav.files.folder_lock`).
    """
    from .report import REPORT_FRAMES

    mode = run.mode if options.mode is None else options.mode
    if mode not in MODES:
        raise InputError(f"--mode must be one of {', '.join(MODES)}, got {mode!r}")
    if options.report_frame not in REPORT_FRAMES:
        raise InputError(f"--report-frame must be one of {', '.join(REPORT_FRAMES)}, got {options.report_frame!r}")
    out = Path(options.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a folder")
    # one process writes a run folder at a time: two runs into one folder would mix their stages' files
    with folder_lock(out):
        return _run_study_in(run, options, mode, out)


def _run_study_in(run: RunFile, options: RunOptions, mode: str, out: Path) -> dict:
    """:func:`run_study` once ``out`` is held."""
    from .report import write_report
    from .report_page import provenance

    def log(message: str) -> None:
        line = f"[{run.name}] {message}"
        if options.log is None:
            _log.info("%s", line)
        else:
            options.log(line)

    clock = StageClock(options.started)
    if not study_of(run).generic_filters:
        if mode == "images" and not study_of(run).image_mode:
            raise InputError(f"{run.path}: image mode is not available for study {run.study!r} "
                             f"({run.study.upper()} computes its tables from the trajectory)")
        return _evaluate_study(run, out, log, clock, options.command, mode, options.progress, options.workers)
    names = check_run_filters(run, options.filters or run.filters)
    clock.lap("setup")

    sim, sim_key, _ = simulate_stage(run, out, log, mode, options.progress, options.workers, clock)
    filters = {name: filter_stage(name, sim, sim_key, out, options.progress, log, options.checked, clock,
                                  spacecraft=run.spacecraft)
               for name in names}
    summary = {
        "run": run.describe(mode), "mode": mode, "opnav": __version__,
        "measurements": measurements_summary(sim),
        "window_start_tdb_s": sim.window_start_tdb_s, "paper": sim.paper, "facts": sim.facts,
        "filters": {name: {k: v for k, v in record.items() if k not in ("hash", "files")}
                    for name, record in filters.items()},
    }
    # the provenance (with its date) goes in the report only: summary.json stays the run's figures
    write_report(out, summary, frame=options.report_frame, prov=provenance(options.command, run.path))
    clock.lap("report")
    summary["stages_wall_s"] = clock.walls
    write_json(out / "summary.json", summary)
    log(f"done: {out / 'summary.json'}, {out / 'report.html'}")
    return summary
