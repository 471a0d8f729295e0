"""Faults injected into a run's measurement records, by name in the run file's ``[faults]`` table
or with ``opnav run --set faults.NAME=VALUE``.

Each fault acts on the records a study simulated (measurement or image mode), after the
simulation and before the filters, drawn from its own generator (the run's seed and a fixed
stream), so the same run file and seed give the same faults. What was done is counted in the
summary's ``facts.faults``, and the records each filter refused are listed with their reasons in
``filters/<name>.json`` and the report: a fault either shows up there or in the consistency
flags, never silently in the answer.

Time-tag faults (``clock_offset_s``, ``time_jitter_s``) move each record's epoch tag and leave
its value as measured at the true time, which is what a wrong clock does; the run then takes the
truth at the tags (:func:`truth_at_tags`), so its errors are those of the estimates at the epochs
the filter believes.

Frame faults (image mode only, :mod:`opnav.studies.image_loop`) act on the rendered frames
before the image stage sees them: frames lost, a cosmic-ray storm, clusters of hot pixels, a
stray-light ramp, point sources the catalog lacks, catalog stars missing from the sky, a wrong
a-priori attitude, a camera whose x axis is mirrored. Each frame the image stage refuses is
listed with its reason (``facts.frames_skipped``, the tracking events); a run whose frames can
never be identified against the catalog stops with an error instead of navigating on them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..config import Where, build
from ..errors import InputError
from ..records import Measurement


@dataclass(frozen=True)
class Faults:
    """Record faults (all off by default).

    Attributes
    ----------
    outlier_fraction : float
        Share of records whose value is moved by ``outlier_sigma`` standard deviations of their
        own covariance, in a random direction (a false match, a cosmic ray on a centroid).
    outlier_sigma : float
        Size of an outlier, in sigmas (default 100).
    dropped_fraction : float
        Share of records removed (lost frames or telemetry).
    clock_offset_s : float
        Added to every record's epoch tag, s (a clock offset).
    time_jitter_s : float
        1-sigma of a Gaussian error added to the epoch tag, one draw per measurement epoch (the
        records of one frame share it), s.
    dropped_frame_fraction : float
        Image mode: share of frames lost before the image stage (the tracker carries its
        attitude across the gap).
    cosmic_ray_factor : float
        Image mode: the detector's cosmic-ray rate times this (a solar particle event: 10 or more).
    hot_pixel_clusters : int
        Image mode: clusters of 3 x 3 hot pixels added to the detector's hot-pixel map
        (radiation damage; fixed on the detector like single hot pixels).
    stray_light_e : float
        Image mode: a ramp of scattered light across the detector's columns, from 0 at the
        first to this many electrons per pixel at the last (a bright body outside the field).
    uncatalogued_stars : int
        Image mode: point sources fixed on the sky that are not in the star catalog (an
        asteroid, a planet or a star the catalog lacks), about this many in the field of each
        frame, V 8 to 11.
    missing_star_fraction : float
        Image mode: share of the catalog's stars not drawn in the frames (a catalog entry with
        no star in the sky).
    prior_attitude_error_arcsec : float
        Image mode: error of the a-priori attitude the image stage is given (a random rotation
        of this size per frame); the tracker's carried attitude is not affected.
    flipped_axis : bool
        Image mode: every frame mirrored left to right (a camera model with the wrong sign on x).
    """

    outlier_fraction: float = 0.0
    outlier_sigma: float = 100.0
    dropped_fraction: float = 0.0
    clock_offset_s: float = 0.0
    time_jitter_s: float = 0.0
    dropped_frame_fraction: float = 0.0
    cosmic_ray_factor: float = 1.0
    hot_pixel_clusters: int = 0
    stray_light_e: float = 0.0
    uncatalogued_stars: int = 0
    missing_star_fraction: float = 0.0
    prior_attitude_error_arcsec: float = 0.0
    flipped_axis: bool = False

    def __post_init__(self) -> None:
        for name in ("outlier_fraction", "dropped_fraction", "dropped_frame_fraction", "missing_star_fraction"):
            value = getattr(self, name)
            if not (np.isfinite(value) and 0.0 <= value < 1.0):
                raise InputError(f"faults.{name} must be in [0, 1), got {value!r}")
        if not (np.isfinite(self.outlier_sigma) and self.outlier_sigma > 0.0):
            raise InputError(f"faults.outlier_sigma must be positive, got {self.outlier_sigma!r}")
        if not np.isfinite(self.clock_offset_s):
            raise InputError(f"faults.clock_offset_s must be finite, got {self.clock_offset_s!r}")
        if not (np.isfinite(self.time_jitter_s) and self.time_jitter_s >= 0.0):
            raise InputError(f"faults.time_jitter_s must be >= 0, got {self.time_jitter_s!r}")
        for name in ("cosmic_ray_factor", "stray_light_e", "prior_attitude_error_arcsec"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0.0):
                raise InputError(f"faults.{name} must be >= 0, got {value!r}")
        for name in ("hot_pixel_clusters", "uncatalogued_stars"):
            value = getattr(self, name)
            if not 0 <= value <= 100_000:
                raise InputError(f"faults.{name} must be from 0 to 100000, got {value!r}")

    #: The faults that act on rendered frames (image mode).
    FRAME_FAULTS = ("dropped_frame_fraction", "cosmic_ray_factor", "hot_pixel_clusters", "stray_light_e",
                    "uncatalogued_stars", "missing_star_fraction", "prior_attitude_error_arcsec", "flipped_axis")

    @property
    def on_frames(self) -> dict:
        """The frame faults that are on, by name (empty: frames as rendered)."""
        default = Faults()
        return {name: getattr(self, name) for name in self.FRAME_FAULTS if getattr(self, name) != getattr(default, name)}

    @property
    def retags(self) -> bool:
        """Whether the faults move epoch tags."""
        return self.clock_offset_s != 0.0 or self.time_jitter_s > 0.0

    @property
    def active(self) -> bool:
        return self != Faults()


def apply_faults(records: list[Measurement], faults: Faults, seed: int) -> tuple[list[Measurement], dict]:
    """``records`` with ``faults`` applied (time order kept), and what was done."""
    if not faults.active:
        return records, {}
    rng = np.random.default_rng([seed, 77])
    count = len(records)
    keep = rng.random(count) >= faults.dropped_fraction
    outlier = (rng.random(count) < faults.outlier_fraction) & keep
    epochs = np.unique([r.t_tdb_s for r in records])
    shift = faults.clock_offset_s + faults.time_jitter_s * np.random.default_rng([seed, 78]).standard_normal(epochs.size)
    out = []
    for i, record in enumerate(records):
        if not keep[i]:
            continue
        value = np.array(record.value, dtype=float)
        if outlier[i]:
            direction = rng.standard_normal(record.size)
            direction /= np.linalg.norm(direction)
            # along a unit direction in the whitened space: exactly outlier_sigma sigmas
            value = value + faults.outlier_sigma * np.linalg.cholesky(record.covariance) @ direction
        tag = record.t_tdb_s + float(shift[np.searchsorted(epochs, record.t_tdb_s)]) if faults.retags else record.t_tdb_s
        out.append(replace(record, value=value, t_tdb_s=tag))
    out.sort(key=lambda r: r.t_tdb_s)
    facts = {"records_dropped": int(np.sum(~keep)), "outliers": int(np.sum(outlier)),
             "outliers_at": [{"t_tdb_s": records[i].t_tdb_s, "kind": records[i].kind, "target": records[i].target}
                             for i in np.flatnonzero(outlier)][:1000]}
    if faults.retags:
        facts["time_tag_error_s"] = {"mean": float(shift.mean()), "rms": float(np.sqrt(np.mean(shift**2))),
                                     "max_abs": float(np.max(np.abs(shift)))}
    return out, facts


def truth_at_tags(epochs: np.ndarray, truth: np.ndarray, tags: np.ndarray) -> np.ndarray:
    """True states ``[r km, v km/s]`` (M, 6) at ``tags`` (TDB s) from states (N, 6) at ``epochs``,
    in the same frame and about the same origin as ``truth`` (the study's centre, ICRF).

    Cubic Hermite in position with the velocity as its derivative (the velocity is that
    spline's derivative): for the studies' steps (10-60 s) far below a kilometre-level error.
    Tags up to one step outside the arc are extrapolated; further out is an error.
    """
    from scipy.interpolate import CubicHermiteSpline

    epochs = np.asarray(epochs, dtype=float)
    tags = np.asarray(tags, dtype=float)
    step = float(np.min(np.diff(epochs))) if epochs.size > 1 else 0.0
    if epochs.size < 2 or tags.min() < epochs[0] - step or tags.max() > epochs[-1] + step:
        raise InputError("faulted time tags fall more than one step outside the simulated arc; "
                         "use a clock offset or jitter smaller than the measurement step")
    spline = CubicHermiteSpline(epochs, truth[:, :3], truth[:, 3:6])
    return np.hstack([spline(tags), spline.derivative()(tags)])


def faults_from_values(table: dict, source: str, overrides: dict[str, str] | None = None) -> Faults:
    """A :class:`Faults` from the ``[faults]`` table of run file ``source`` and the ``faults.NAME``
    overrides (``--set``), each key checked (:func:`opnav.config.build`)."""
    return build(Faults, table, Where(source, "faults"), text=True, noun="fault", overrides=overrides,
                 set_prefix="faults.")
