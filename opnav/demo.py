"""Frames of the demo camera along an S1 arc and their measurement by the image stage.

What S1's image mode (:func:`opnav.studies.s1.simulate_images`, and so ``opnav demo``,
which runs ``opnav/data/demo_run.toml``) is made of:

- :func:`load_demo`: the camera, detector, PSF, pointing and catalog of ``opnav/data/demo.toml``
  (package data: an S1-like Mars cruise in July 2014 with a 1-degree camera tracking Phobos).
- :func:`render_frames`: one full frame per epoch into ``OUT/frames`` (FITS + truth JSON). Each
  frame draws its noise from its own generator seeded with ``(seed, frame index)``, so a frame
  does not depend on which others were rendered in the same run. A frame already on disk is
  reused when it reads back intact (FITS checksums, truth sidecar) and carries this run's
  epoch, seed and scenario digest; anything else is rendered again, with the reason reported.
- :func:`process_frames`: the image pipeline on every frame (star ID and attitude from the
  frame, Phobos/Deimos centroids -> RA/Dec with covariance); a frame the pipeline cannot use
  is skipped with its reason.
- :func:`radec_errors`: every RA/Dec record against the apparent direction in its frame's
  truth sidecar: ``chi2 = d^T C^-1 d`` is chi-square(2) when the reported covariance is right.
"""

from __future__ import annotations

import hashlib
import importlib.resources
import contextlib
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .errors import InputError, OpnavError
from .measurements import wrap_angle
from .records import Measurement, pair_targets, split_radec_pairs

log = logging.getLogger(__name__)

DEMO_RESOURCE = "demo.toml"
MOONS = ("phobos", "deimos")
ARCSEC_PER_RAD = 180.0 / math.pi * 3600.0


@dataclass(frozen=True)
class RenderedFrames:
    """Frames on disk: ``paths`` and ``truths`` per epoch; ``reused`` counts frames kept from
    an earlier run; ``rerendered`` maps a frame name to why its old file was not reused."""

    paths: tuple[Path, ...]
    truths: tuple  # opnav.render.truth.FrameTruth per path
    reused: int
    rerendered: dict


def demo_text() -> str:
    """The embedded scenario file's text."""
    return importlib.resources.files("opnav").joinpath("data", DEMO_RESOURCE).read_text()


def load_demo():
    """The embedded scenario and its navigation section: ``(Scene, NavigationConfig, digest)``.

    ``digest`` (16 hex digits of SHA-256 of the file) marks rendered frames, so frames from
    another version of the scenario are never reused.
    """
    from .filters.options import load_navigation
    from .sim.scene import load_scene

    resource = importlib.resources.files("opnav").joinpath("data", DEMO_RESOURCE)
    with importlib.resources.as_file(resource) as path:
        scenario = load_scene(path)
        nav = load_navigation(path)
    return scenario, nav, hashlib.sha256(demo_text().encode()).hexdigest()[:16]


def prepare_out_dir(out_dir: Path) -> Path:
    """Create ``out_dir/frames``; ``InputError`` when ``out_dir`` (or that folder) is not a directory."""
    for folder in (out_dir, out_dir / "frames"):
        if folder.exists() and not folder.is_dir():
            raise InputError(f"--out {out_dir}: {folder} exists and is not a directory")
    try:
        (out_dir / "frames").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out {out_dir}: cannot create the output directory ({exc.strerror})") from None
    return out_dir / "frames"


def _reuse_problem(path: Path, t_tdb_s: float, seed: int, digest: str, shape: tuple[int, int]) -> tuple[str | None, object]:
    """Why the frame at ``path`` cannot be reused (None if it can), and its truth."""
    from .render.frames_io import read_frame

    if not path.exists():
        return "missing", None
    try:
        stored = read_frame(path)
    except OpnavError as exc:
        return str(exc), None
    header = stored.header
    if header.get("DEMOHASH") != digest:
        return "rendered from another version of the demo scenario", None
    if header.get("DEMOSEED") != seed:
        return f"rendered with seed {header.get('DEMOSEED')}, not {seed}", None
    if stored.image.shape != shape or abs(stored.truth.t_tdb_s - t_tdb_s) > 1e-6:
        return "epoch or image size differs from the scenario", None
    return None, stored.truth


def render_frames(scenario, t_tdb_s: np.ndarray, r_ssb_km: np.ndarray, v_ssb_km_s: np.ndarray, frames_dir: Path, *,
                  seed: int, digest: str, catalog, ephemeris, progress: bool = True) -> RenderedFrames:
    """Render (or reuse) ``frames_dir/frame_NNNNN.fits`` for every epoch.

    Parameters
    ----------
    scenario : opnav.sim.scene.Scene
    t_tdb_s : (M,) array
        Mid-exposure epochs, TDB seconds past J2000.
    r_ssb_km, v_ssb_km_s : (M, 3) arrays
        Observer position (km) and velocity (km/s) relative to the SSB, ICRF.
    frames_dir : Path
    seed : int
        Frame ``k`` draws its noise from ``default_rng([seed, k])``.
    digest : str
        Scene digest written to (and checked in) every header.
    catalog, ephemeris
        As for :func:`opnav.render.render_frame`.
    """
    from .render.frame import render_frame
    from .render.frames_io import write_frame
    from .observer import Observer
    from .sim.pointing import body_rate, pointing_attitude

    paths, truths, rerendered, reused = [], [], {}, 0
    for k in tqdm(range(len(t_tdb_s)), desc="render", unit="frame", disable=not progress):
        path = frames_dir / f"frame_{k:05d}.fits"
        problem, truth = _reuse_problem(path, float(t_tdb_s[k]), seed, digest, scenario.camera.shape)
        if problem is None:
            reused += 1
        else:
            if problem != "missing":
                rerendered[path.name] = problem
            observer = Observer(float(t_tdb_s[k]), r_ssb_km[k], v_ssb_km_s[k])
            corrections = scenario.options.corrections
            result = render_frame(
                scenario.camera, pointing_attitude(scenario.pointing, observer, ephemeris, corrections), observer,
                catalog=catalog, targets=scenario.targets, ephemeris=ephemeris, options=scenario.options,
                omega_cam_rad_s=body_rate(scenario.pointing, observer, ephemeris, corrections),
                rng=np.random.default_rng([seed, k]),
            )
            header = result.header.copy()
            header["DEMOSEED"] = (seed, "opnav demo noise seed")
            header["DEMOHASH"] = (digest, "opnav demo scenario digest")
            write_frame(path, result.image, header, result.truth)
            truth = result.truth
        paths.append(path)
        truths.append(truth)
    return RenderedFrames(tuple(paths), tuple(truths), reused, rerendered)


def process_frames(paths, *, catalog, ephemeris, vmag_limit: float | None, seed: int, progress: bool = True,
                   tracker=None):
    """Image pipeline over ``paths``: ``(records, skipped {name: reason}, moon misses {name: [frame]})``.

    Each frame goes through the full-frame stage, or, with ``tracker``
    (:class:`opnav.image.tracking.Tracker`, its options are used), through tracking mode after
    acquisition; the tracker keeps its acquisitions and losses of lock in ``tracker.events``.
    """
    from .image.pipeline import PipelineOptions, frame_input, process_frame

    options = PipelineOptions(targets=MOONS, vmag_limit=vmag_limit) if tracker is None else tracker.options
    records, skipped, missed = [], {}, {name: [] for name in MOONS}
    with quiet_moon_misses():
        for k, path in enumerate(tqdm(paths, desc="process", unit="frame", disable=not progress)):
            try:
                rng = np.random.default_rng([seed, 1, k])
                if tracker is None:
                    result = process_frame(path, catalog=catalog, ephemeris=ephemeris, options=options, rng=rng)
                else:
                    result = tracker.step(frame_input(path), rng=rng)
            except OpnavError as exc:
                skipped[path.name] = str(exc)
                continue
            records.extend(result.records)
            for name in MOONS:
                if f"no_{name}" in result.flags:
                    hidden = f"{name}_hidden" in result.flags
                    missed[name].append({"frame": path.stem, "hidden_by_primary": hidden})
    return records, skipped, missed


@contextlib.contextmanager
def quiet_moon_misses():
    """Silence the image stage's per-frame warnings (unless INFO logging is on): a moon lost in
    Mars' glare is counted in the report, and one warning per frame would bury everything else."""
    loggers = [logging.getLogger(name) for name in ("opnav.image.pipeline", "opnav.image.tracking")]
    levels = [log.level for log in loggers]
    for log in loggers:
        if not log.isEnabledFor(logging.INFO):
            log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for log, level in zip(loggers, levels):
            log.setLevel(level)


def pair_chi2(records: list[Measurement], truths: dict) -> np.ndarray:
    """``d^T C^-1 d`` of each ``radec_pair`` record of ``records`` against its frame's truth (``truths``
    as in :func:`radec_errors`): chi-square(4) when the pair's covariance, cross terms included, is right."""
    out = []
    for record in (r for r in records if r.kind == "radec_pair"):
        truth = [truths[record.frame_id].target(name) for name in pair_targets(record)]
        d = record.value - np.array([value for t in truth for value in (t.ra_rad, t.dec_rad)])
        d[[0, 2]] = wrap_angle(d[[0, 2]])
        out.append(float(d @ np.linalg.solve(record.covariance, d)))
    return np.array(out)


def radec_errors(records: list[Measurement], truths: dict) -> dict:
    """Per-target RA/Dec errors of ``records`` against the frames' truth.

    ``truths`` maps a record's ``frame_id`` to its :class:`opnav.render.truth.FrameTruth`.
    Errors are ``[dRA cos(dec), dDec]`` (rad, tangent plane); their covariance is the record's
    covariance mapped the same way. Returns, per target: ``count``, ``rms_arcsec`` (2,),
    ``mean_abs_arcsec`` (2,), ``median_sigma_arcsec`` (2,), ``chi2`` (each record's
    ``d^T C^-1 d``, chi-square(2) when ``C`` is right). A ``radec_pair`` counts as its two records.
    """
    records = split_radec_pairs(records)  # a frame's pair counts as its two moons' records
    out = {}
    for name in sorted({r.target for r in records if r.kind == "radec"}):
        errors, sigmas, chi2 = [], [], []
        for record in (r for r in records if r.kind == "radec" and r.target == name):
            target = truths[record.frame_id].target(name)
            scale = np.diag([math.cos(target.dec_rad), 1.0])
            d = scale @ np.array([wrap_angle(record.value[0] - target.ra_rad), record.value[1] - target.dec_rad])
            cov = scale @ record.covariance @ scale
            errors.append(d)
            sigmas.append(np.sqrt(np.diag(cov)))
            chi2.append(float(d @ np.linalg.solve(cov, d)))
        errors, sigmas = np.array(errors), np.array(sigmas)
        out[name] = {
            "count": len(chi2),
            "rms_arcsec": (np.sqrt(np.mean(errors**2, axis=0)) * ARCSEC_PER_RAD).tolist(),
            "mean_arcsec": (np.mean(errors, axis=0) * ARCSEC_PER_RAD).tolist(),
            "median_sigma_arcsec": (np.median(sigmas, axis=0) * ARCSEC_PER_RAD).tolist(),
            "chi2": chi2,
        }
    return out
