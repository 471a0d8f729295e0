"""The embedded demo scenario end to end: render -> image -> navigate -> report.

Steps of :func:`run_demo`:

1. Load ``opnav/data/demo.toml`` (package data, through :mod:`importlib.resources`): an
   S1-like Mars cruise in July 2014 (:mod:`opnav.scenario` sections plus ``[navigation]``).
2. Render one full frame per epoch into ``OUT/frames`` (FITS + truth JSON). Each frame draws
   its noise from its own generator seeded with ``(seed, frame index)``, so a frame does not
   depend on which others were rendered in the same run. A frame already on disk is reused
   when it reads back intact (FITS checksums, truth sidecar) and carries this run's epoch,
   seed and scenario digest; anything else is rendered again, with the reason reported.
3. Process every frame with the image pipeline (:func:`opnav.image.pipeline.process_frame`:
   star ID and attitude from the frame, Phobos/Deimos centroids -> RA/Dec with covariance);
   a frame the pipeline cannot use is skipped with its reason. Records go to
   ``OUT/measurements.csv`` (:func:`opnav.records.write_csv`).
4. Compare every RA/Dec record with the apparent direction in the frame's truth sidecar:
   ``chi2 = d^T C^-1 d`` is chi-square(2) when the reported covariance ``C`` is right.
5. Run the scenario's sequential filter over the records and compare its estimates with the
   truth trajectory (the ``[observer]`` state propagated with its force model): final error
   against the filter's sigmas, and ``NEES = e^T P^-1 e`` (chi-square(6) when consistent).
6. Write ``OUT/summary.json`` and ``OUT/position_error.png`` atomically.
"""

from __future__ import annotations

import hashlib
import importlib.resources
import json
import logging
import math
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats
from tqdm import tqdm

from .errors import InputError, OpnavError
from .measurements import wrap_angle
from .records import Measurement, atomic_write_text, write_csv

log = logging.getLogger(__name__)

DEMO_RESOURCE = "demo.toml"
MOONS = ("phobos", "deimos")
ARCSEC_PER_RAD = 180.0 / math.pi * 3600.0
#: Probability of the chi-square intervals quoted in the summary.
BOUND_PROBABILITY = 0.99


@dataclass(frozen=True)
class DemoOptions:
    """Settings of :func:`run_demo`.

    ``out_dir``: output directory; ``frames``: use only the first ``frames`` epochs of the
    scenario (None: all); ``seed``: overrides the scenario seed (None: keep it);
    ``progress``: tqdm bars on stderr.
    """

    out_dir: Path
    frames: int | None = None
    seed: int | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "out_dir", Path(self.out_dir))
        if self.frames is not None and self.frames < 1:
            raise InputError(f"--frames must be at least 1, got {self.frames}")
        if self.seed is not None and self.seed < 0:
            raise InputError(f"--seed must be a non-negative integer, got {self.seed}")


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
    """The embedded scenario and its navigation section: ``(Scenario, NavigationConfig, digest)``.

    ``digest`` (16 hex digits of SHA-256 of the file) marks rendered frames, so frames from
    another version of the scenario are never reused.
    """
    from .navconfig import load_navigation
    from .scenario import load_scenario

    resource = importlib.resources.files("opnav").joinpath("data", DEMO_RESOURCE)
    with importlib.resources.as_file(resource) as path:
        scenario = load_scenario(path)
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
    scenario : opnav.scenario.Scenario
    t_tdb_s : (M,) array
        Mid-exposure epochs, TDB seconds past J2000.
    r_ssb_km, v_ssb_km_s : (M, 3) arrays
        Observer position (km) and velocity (km/s) relative to the SSB, ICRF.
    frames_dir : Path
    seed : int
        Frame ``k`` draws its noise from ``default_rng([seed, k])``.
    digest : str
        Scenario digest written to (and checked in) every header.
    catalog, ephemeris
        As for :func:`opnav.render.render_frame`.
    """
    from .render.frame import render_frame
    from .render.frames_io import write_frame
    from .render.scene import Observer
    from .render.sequence import body_rate, pointing_attitude

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


def process_frames(paths, *, catalog, ephemeris, vmag_limit: float | None, seed: int, progress: bool = True):
    """Image pipeline over ``paths``: ``(records, skipped {name: reason}, moon misses {name: [frame]})``."""
    from .image.pipeline import PipelineOptions, process_frame

    options = PipelineOptions(targets=MOONS, vmag_limit=vmag_limit)
    records, skipped, missed = [], {}, {name: [] for name in MOONS}
    pipeline_log = logging.getLogger("opnav.image.pipeline")
    level = pipeline_log.level
    if not pipeline_log.isEnabledFor(logging.INFO):
        # a moon lost in Mars' glare is counted in the report; one warning per frame would bury it
        pipeline_log.setLevel(logging.ERROR)
    try:
        for k, path in enumerate(tqdm(paths, desc="process", unit="frame", disable=not progress)):
            try:
                result = process_frame(path, catalog=catalog, ephemeris=ephemeris, options=options,
                                       rng=np.random.default_rng([seed, 1, k]))
            except OpnavError as exc:
                skipped[path.name] = str(exc)
                continue
            records.extend(result.records)
            for name in MOONS:
                if f"no_{name}" in result.flags:
                    hidden = f"{name}_hidden" in result.flags
                    missed[name].append({"frame": path.stem, "hidden_by_primary": hidden})
    finally:
        pipeline_log.setLevel(level)
    return records, skipped, missed


def radec_errors(records: list[Measurement], truths: dict) -> dict:
    """Per-target RA/Dec errors of ``records`` against the frames' truth.

    ``truths`` maps a record's ``frame_id`` to its :class:`opnav.render.truth.FrameTruth`.
    Errors are ``[dRA cos(dec), dDec]`` (rad, tangent plane); their covariance is the record's
    covariance mapped the same way. Returns, per target: ``count``, ``rms_arcsec`` (2,),
    ``mean_abs_arcsec`` (2,), ``median_sigma_arcsec`` (2,), ``chi2`` (each record's
    ``d^T C^-1 d``, chi-square(2) when ``C`` is right).
    """
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


def chi2_interval(dof: int, probability: float = BOUND_PROBABILITY) -> list[float]:
    """Two-sided ``probability`` interval of one chi-square(``dof``) value."""
    tail = 0.5 * (1.0 - probability)
    return [float(stats.chi2.ppf(tail, dof)), float(stats.chi2.ppf(1.0 - tail, dof))]


def navigate(nav, records: list[Measurement], *, progress: bool = True):
    """Run the ``[navigation]`` filter (a sequential one) over ``records``; ``(history, centre)``."""
    from .dynamics import get_model
    from .filters.factory import build_filter, measurement_model
    from .filters.run import run_filter

    if nav.filter in ("wls", "federated"):
        raise InputError(f"[navigation] filter {nav.filter!r}: the demo runs a sequential filter (ekf, ukf, ...)")
    force_model = get_model(nav.dynamics)
    model = measurement_model(nav, force_model.center)
    return run_filter(build_filter(nav.filter, nav, model, force_model), records, progress=progress), force_model.center


def truth_states(scenario, t_tdb_s: np.ndarray, center: str, ephemeris) -> np.ndarray:
    """True probe states (M, 6) [km, km/s], ICRF, relative to ``center``, at ``t_tdb_s`` (M,)."""
    from .scenario import observer_states

    r, v = observer_states(scenario, t_tdb_s, ephemeris)
    if center != "ssb":
        r_c, v_c = ephemeris.state(center, np.asarray(t_tdb_s, dtype=float))
        r, v = r - r_c, v - v_c
    return np.hstack([r, v])


def write_plot(path: Path, hours: np.ndarray, errors_km: np.ndarray, sigmas_km: np.ndarray, title: str) -> None:
    """Position error per axis (km) and the filter's +-3 sigma against time, as a PNG written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, sharex=True, figsize=(7.0, 7.0))
    for i, (ax, label) in enumerate(zip(axes, ("x", "y", "z"))):
        ax.fill_between(hours, -3.0 * sigmas_km[:, i], 3.0 * sigmas_km[:, i], color="0.85", label="filter 3-sigma")
        ax.plot(hours, errors_km[:, i], "C0.-", ms=3, label="estimate - truth")
        ax.axhline(0.0, color="0.5", lw=0.5)
        ax.set_ylabel(f"{label} error (km)")
        # linear well inside the smallest sigma, logarithmic beyond: keeps the 5000 km start and the end readable
        ax.set_yscale("symlog", linthresh=max(0.1 * float(np.min(sigmas_km[:, i])), 1e-3))
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title(title, fontsize=9)
    axes[-1].set_xlabel("hours since the first frame")
    fig.tight_layout()
    fd, tmp = tempfile.mkstemp(prefix=".position_error.", suffix=".png", dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=110)
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        if os.path.exists(tmp):
            os.unlink(tmp)


def _final_report(history, truth: np.ndarray) -> dict:
    from .filters.run import nees

    err = history.states[-1] - truth[-1]
    sig = np.sqrt(np.diag(history.covariances[-1]))
    values = nees(history.states[-1:], history.covariances[-1:], truth[-1:])
    pos = nees(history.states[-1:, :3], history.covariances[-1:, :3, :3], truth[-1:, :3])
    return {
        "t_tdb_s": float(history.epochs[-1]),
        "position_error_km": err[:3].tolist(), "position_sigma_km": sig[:3].tolist(),
        "position_error_norm_km": float(np.linalg.norm(err[:3])),
        "velocity_error_m_s": (err[3:6] * 1e3).tolist(), "velocity_sigma_m_s": (sig[3:6] * 1e3).tolist(),
        "velocity_error_norm_m_s": float(np.linalg.norm(err[3:6]) * 1e3),
        "inside_3sigma": bool(np.all(np.abs(err[:6]) <= 3.0 * sig[:6])),
        "nees": float(values[0]), "nees_dof": 6, "nees_interval": chi2_interval(6),
        "position_nees": float(pos[0]), "position_nees_interval": chi2_interval(3),
    }


def run_demo(options: DemoOptions) -> dict:
    """Run the demo (module docstring) and return the summary written to ``summary.json``."""
    from .catalog import load_catalog
    from .ephemeris import default_ephemeris
    from .filters.run import chi2_mean_bounds
    from .scenario import observer_states

    tic = time.perf_counter()
    frames_dir = prepare_out_dir(options.out_dir)
    scenario, nav, digest = load_demo()
    seed = scenario.seed if options.seed is None else options.seed
    t = scenario.t_tdb_s if options.frames is None else scenario.t_tdb_s[: options.frames]
    ephemeris = default_ephemeris()
    catalog = load_catalog(scenario.catalog_path)
    walls = {}

    r, v = observer_states(scenario, t, ephemeris)
    frames = render_frames(scenario, t, r, v, frames_dir, seed=seed, digest=digest, catalog=catalog,
                           ephemeris=ephemeris, progress=options.progress)
    walls["render"] = time.perf_counter() - tic

    records, skipped, missed = process_frames(frames.paths, catalog=catalog, ephemeris=ephemeris,
                                              vmag_limit=scenario.options.vmag_limit, seed=seed, progress=options.progress)
    write_csv(options.out_dir / "measurements.csv", records, metadata={"frames": len(frames.paths) - len(skipped),
                                                                        "skipped": skipped, "targets": list(MOONS)})
    walls["process"] = time.perf_counter() - tic - walls["render"]
    if not records:
        raise InputError(f"{frames_dir}: no usable Phobos/Deimos measurement in {len(frames.paths)} frame(s)")

    truths = {path.stem: truth for path, truth in zip(frames.paths, frames.truths)}
    measured = radec_errors(records, truths)
    for entry in measured.values():
        chi2 = entry.pop("chi2")
        entry["chi2_mean"] = float(np.mean(chi2))
        entry["chi2_mean_interval"] = list(chi2_mean_bounds(2, len(chi2), BOUND_PROBABILITY))
        entry["chi2_max"] = float(np.max(chi2))

    mark = time.perf_counter()
    history, center = navigate(nav, records, progress=options.progress)
    walls["navigate"] = time.perf_counter() - mark
    # propagate() wants strictly increasing epochs; records share frame epochs
    epochs, index = np.unique(np.concatenate([[nav.t0_tdb_s], history.epochs]), return_inverse=True)
    truth = truth_states(scenario, epochs, center, ephemeris)[index]
    initial_error = nav.x0 - truth[0]
    truth = truth[1:]
    nis = history.nis[history.accepted & np.isfinite(history.nis)]

    hours = (history.epochs - t[0]) / 3600.0
    sig_pos = np.sqrt(np.diagonal(history.covariances, axis1=1, axis2=2)[:, :3])
    write_plot(options.out_dir / "position_error.png", hours, history.states[:, :3] - truth[:, :3], sig_pos,
               f"opnav demo: {nav.filter.upper()} on Phobos/Deimos RA/Dec, {len(frames.paths)} frames, seed {seed}")
    walls["total"] = time.perf_counter() - tic

    summary = {
        "scenario": scenario.name, "seed": seed, "filter": nav.filter, "center": center,
        "frames": {"requested": len(frames.paths), "rendered": len(frames.paths) - frames.reused, "reused": frames.reused,
                   "rerendered": frames.rerendered, "processed": len(frames.paths) - len(skipped), "skipped": skipped,
                   "moon_not_measured": missed},
        "records": {"total": len(records), "accepted": int(history.accepted.sum()),
                    "rejected": int((~history.accepted).sum()),
                    "rejection_reasons": sorted({reason for reason in history.reasons if reason})},
        "measurement_errors": measured,
        "nis": {"mean": float(np.mean(nis)) if nis.size else None, "count": int(nis.size),
                "mean_interval": list(chi2_mean_bounds(2, nis.size, BOUND_PROBABILITY)) if nis.size else None},
        "initial": {"position_error_km": initial_error[:3].tolist(), "velocity_error_m_s": (initial_error[3:6] * 1e3).tolist(),
                    "position_sigma_km": np.sqrt(np.diag(nav.P0)[:3]).tolist()},
        "final": _final_report(history, truth),
        "interval_probability": BOUND_PROBABILITY,
        "wall_s": walls,
        "outputs": {"frames": str(frames_dir), "measurements": "measurements.csv", "plot": "position_error.png"},
    }
    atomic_write_text(options.out_dir / "summary.json", json.dumps(summary, indent=2, allow_nan=False))
    return summary


def format_report(summary: dict) -> str:
    """The short text report printed by ``opnav demo``."""
    f = summary["frames"]
    head = (f"opnav demo ({summary['scenario']}, seed {summary['seed']}): {f['requested']} frames: "
            f"{f['rendered']} rendered, {f['reused']} reused, {f['processed']} processed, {len(f['skipped'])} skipped")
    lines = [head]
    for name, reason in {**f["rerendered"], **f["skipped"]}.items():
        action = "rendered again" if name in f["rerendered"] else "skipped"
        lines.append(f"  {name}: {action}: {reason}")
    for name, frames in f["moon_not_measured"].items():
        if frames:
            hidden = sum(item["hidden_by_primary"] for item in frames)
            lines.append(f"  {name} not measured in {len(frames)} frame(s): {hidden} on Mars' saturated, bloomed "
                         f"or halo pixels, {len(frames) - hidden} with no acceptable source near its prediction")
    lines.append("measurement error vs truth (RA cos(dec), Dec), arcsec:")
    for name, m in summary["measurement_errors"].items():
        lo, hi = m["chi2_mean_interval"]
        lines.append(f"  {name:7s} n={m['count']:3d}  rms {m['rms_arcsec'][0]:.3f} {m['rms_arcsec'][1]:.3f}  "
                     f"reported sigma {m['median_sigma_arcsec'][0]:.3f} {m['median_sigma_arcsec'][1]:.3f}  "
                     f"mean chi2(2) {m['chi2_mean']:.2f} (99% interval {lo:.2f}-{hi:.2f})")
    rec, nis = summary["records"], summary["nis"]
    lines.append(f"{summary['filter'].upper()}: {rec['accepted']}/{rec['total']} records accepted"
                 + (f", mean NIS {nis['mean']:.2f} (99% interval {nis['mean_interval'][0]:.2f}-{nis['mean_interval'][1]:.2f})"
                    if nis["mean"] is not None else ""))
    init, fin = summary["initial"], summary["final"]
    lines.append(f"  initial error {np.linalg.norm(init['position_error_km']):.1f} km, "
                 f"{np.linalg.norm(init['velocity_error_m_s']):.3f} m/s")
    lines.append("  final position error (km) " + " ".join(f"{e:+.2f}" for e in fin["position_error_km"])
                 + "  sigma " + " ".join(f"{s:.2f}" for s in fin["position_sigma_km"]))
    lines.append("  final velocity error (m/s) " + " ".join(f"{e:+.4f}" for e in fin["velocity_error_m_s"])
                 + "  sigma " + " ".join(f"{s:.4f}" for s in fin["velocity_sigma_m_s"]))
    lo, hi = fin["nees_interval"]
    lines.append(f"  inside 3-sigma: {'yes' if fin['inside_3sigma'] else 'NO'};  final NEES {fin['nees']:.2f} "
                 f"(chi2(6) 99% interval {lo:.2f}-{hi:.2f})")
    lines.append(f"wall time {summary['wall_s']['total']:.1f} s; summary.json and position_error.png in "
                 f"{Path(summary['outputs']['frames']).parent}")
    return "\n".join(lines)


__all__ = ["DemoOptions", "RenderedFrames", "chi2_interval", "demo_text", "format_report", "load_demo", "navigate",
           "prepare_out_dir", "process_frames", "radec_errors", "render_frames", "run_demo", "truth_states", "write_plot"]
