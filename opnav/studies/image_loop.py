"""S1 image mode on the one loop (:mod:`opnav.sim.loop`): the demo camera along the S1 arc, its frame
faults, the truth's moon ephemeris error.

Two ways through the loop, both with the demo camera tracking Phobos (:func:`opnav.sim.loop.scene_sensor`):

- :func:`stream_frames`, frames in memory: while the :class:`~opnav.image.tracking.Tracker` holds
  lock only the windows it will read are rendered (each window read out with the same detector
  model as a full frame) and measured at once, no FITS file per frame; every ``dump_every``-th
  frame is rendered in full and written with its truth (``frames/``) for inspection. The frames
  go in chunks of ``chunk_frames`` (a day at one a minute), each from its own acquisition, saved
  in ``stream/`` and read back by a re-run, in ``workers`` processes with the same records
  (:mod:`opnav.sim.chunks`). The renderer and the image stage read the Chebyshev cache of DE421
  (within 1 cm of it): the ephemeris calls of each frame's geometry would otherwise cost more
  than its pixels.
- :func:`frames_on_disk`: every frame written to ``frames/`` (FITS with truth, tagged with the
  seed and the scene's digest, so a re-run reuses the intact ones) and measured as read back,
  one stage over the whole arc; truth and frames from DE421 itself.

The moons of a frame become one ``radec_pair`` record with the cross-covariance of the attitude
they share (:func:`opnav.records.join_frame_radec`). Noise of frame ``k`` comes from
``default_rng([seed, k])`` and its image stage from ``default_rng([seed, 1, k])``, whatever the
arc (so one seed gives two arcs the same streams: :mod:`opnav.studies.s1`); a frame rendered in
windows draws its noise window by window, so its pixels differ from the full render's by the
noise draw only (same statistics, ``tests/render/test_render_io.py``).

:class:`FrameFaults` is S1's :class:`~opnav.sim.sensors.FrameHook`: the run's frame faults
(:class:`opnav.studies.faults.Faults`, each from a stream of its own: ``[seed, 92, k]`` frame
lost, ``[seed, 93]`` missing catalog stars, ``[seed, 94, k]`` a-priori attitude error, ``[seed, 95,
first frame of the chunk]`` uncatalogued point sources) and the moon ephemeris error of the
truth (``[seed, 96, k]`` white, ``[seed, 96]`` bias).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..constants import ARCSEC_RAD
from ..image.tracking import TrackingOptions
from ..sim.chunks import run_chunks
from ..sim.loop import scene_sensor
from ..sim.results import LoopResult
from ..sim.sensors import Arc, FrameHook, FrameTag, Loop, Sky, Storage
from ..sim.stages import FullFrame, Tracking


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


@dataclass(frozen=True)
class FrameFaults(FrameHook):
    """S1's frame faults and moon ephemeris error (module notes).

    Attributes
    ----------
    faults : dict
        The frame faults that are on (:attr:`opnav.studies.faults.Faults.on_frames`).
    moons : tuple of str
        Moons drawn away from the ephemeris the stage predicts with.
    moon_ephemeris_sigma_km : float
        Offset per axis, km (ICRF); 0 draws them at the ephemeris.
    moon_ephemeris_error : str
        ``"white"`` (a new draw per frame) or ``"bias"`` (one per run).
    """

    faults: dict = field(default_factory=dict)
    moons: tuple[str, ...] = ()
    moon_ephemeris_sigma_km: float = 0.0
    moon_ephemeris_error: str = "white"

    def lost(self, seed: int, k: int) -> str | None:
        if np.random.default_rng([seed, 92, k]).random() < self.faults.get("dropped_frame_fraction", 0.0):
            return "frame lost (faults.dropped_frame_fraction)"
        return None

    def prior(self, seed: int, sensor: int, k: int, R_icrf_cam: Rotation) -> Rotation:
        if not self.faults.get("prior_attitude_error_arcsec"):
            return R_icrf_cam
        axis = np.random.default_rng([seed, 94, k]).standard_normal(3)
        error = self.faults["prior_attitude_error_arcsec"]
        return R_icrf_cam * Rotation.from_rotvec(axis / np.linalg.norm(axis) * error * ARCSEC_RAD)

    def ephemeris(self, seed: int, k: int, ephemeris):
        """The moons offset by the truth's ephemeris error."""
        if self.moon_ephemeris_sigma_km <= 0.0:
            return ephemeris
        draw = [seed, 96] if self.moon_ephemeris_error == "bias" else [seed, 96, k]
        offsets = np.random.default_rng(draw).normal(0.0, self.moon_ephemeris_sigma_km, (len(self.moons), 3))
        return _OffsetEphemeris(ephemeris, dict(zip(self.moons, offsets)))

    def drawn(self, seed: int, sensor: int, spec, arc: Arc, catalog, ephemeris):
        """(render options, star catalog) the chunk's frames are rendered with, frame faults applied.

        The image stage keeps the true catalog and camera; only what is drawn changes. Missing
        stars are the same over the whole arc (one draw per run); uncatalogued point sources are
        fixed on the sky, spread over the cone the chunk's pointing covers.
        """
        from ..catalog import StarCatalog, synthetic_catalog
        from ..observer import Observer
        from ..sim.pointing import pointing_attitude

        faults = self.faults
        options = spec.render
        detector = options.detector
        if "cosmic_ray_factor" in faults or "hot_pixel_clusters" in faults:
            detector = replace(
                detector, cosmic_ray_rate_cm2_s=detector.cosmic_ray_rate_cm2_s * faults.get("cosmic_ray_factor", 1.0),
                hot_pixel_clusters=detector.hot_pixel_clusters + int(faults.get("hot_pixel_clusters", 0)))
        options = replace(options, detector=detector,
                          stray_light_e=options.stray_light_e + faults.get("stray_light_e", 0.0))
        drawn = catalog
        if faults.get("missing_star_fraction"):
            drawn = catalog.subset(np.random.default_rng([seed, 93]).random(len(catalog))
                                   >= faults["missing_star_fraction"])
        if faults.get("uncatalogued_stars"):
            camera = spec.camera
            samples = np.unique(np.linspace(0, len(arc) - 1, 48).astype(int))
            boresights = np.array([pointing_attitude(spec.pointing, Observer(float(arc.t_tdb_s[i]), arc.r_ssb_km[i],
                                                                             arc.v_ssb_km_s[i]),
                                                     ephemeris, options.corrections).apply([0.0, 0.0, 1.0])
                                   for i in samples])
            centre = boresights.mean(axis=0)
            centre /= np.linalg.norm(centre)
            cap = camera.half_diagonal_fov_rad + float(np.max(np.arccos(np.clip(boresights @ centre, -1.0, 1.0))))
            # about `uncatalogued_stars` in a frame: that density (per field of view) over the whole cap
            field_area = camera.width_px * camera.height_px * camera.pixel_scale_rad**2
            rng = np.random.default_rng([seed, 95, arc.first])
            count = rng.poisson(faults["uncatalogued_stars"] * 2.0 * np.pi * (1.0 - np.cos(cap)) / field_area)
            extra = synthetic_catalog(count, rng=rng, vmag_range=(8.0, 11.0), centre_icrf=centre, radius_rad=cap)
            # ids beyond HIP's and below Gaia's: no catalog star shares them
            extra = replace(extra, hip=np.zeros(count, np.int64), gaia_id=2**34 + np.arange(count, dtype=np.int64))
            drawn = StarCatalog(**{f.name: np.concatenate([getattr(drawn, f.name), getattr(extra, f.name)])
                                   for f in fields(drawn)})
        return options, drawn

    # a camera model with the wrong sign on x: the detector's readout is mirrored left to right

    def boxes(self, sensor: int, boxes: list, camera) -> list:
        if not self.faults.get("flipped_axis"):
            return boxes
        return [(camera.width_px - 1 - x1, y0, camera.width_px - 1 - x0, y1) for x0, y0, x1, y1 in boxes]

    def image(self, sensor: int, image: np.ndarray) -> np.ndarray:
        return image[:, ::-1].copy() if self.faults.get("flipped_axis") else image

    def windows(self, sensor: int, windows, camera):
        if not self.faults.get("flipped_axis"):
            return windows
        from ..render.frames_io import Window

        return [Window(camera.width_px - w.x0 - w.image.shape[1], w.y0, w.image[:, ::-1].copy()) for w in windows]


def stream_frames(scenario, epochs: np.ndarray, r_ssb_km: np.ndarray, v_ssb_km_s: np.ndarray, out: Path, *,
                  seed: int, options, tracking=None, moons: tuple[str, ...], dump_every: int = 0,
                  chunk_frames: int = 1440, key: str = "", workers: int = 1, faults=None,
                  moon_ephemeris_sigma_km: float = 0.0, moon_ephemeris_error: str = "white",
                  progress: bool = False) -> LoopResult:
    """Render and measure every epoch in memory, in chunks (module notes).

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
        The image stage's settings (its ``targets`` are the moons measured, and their true RA/Dec
        is kept for the measurement errors).
    tracking : opnav.image.tracking.TrackingOptions, optional
        Tracking settings (default: the defaults).
    moons : tuple of str
        Moons moved by the ephemeris error.
    dump_every : int
        Write every this-many-th frame as FITS (0: none).
    chunk_frames : int
        Frames per chunk (the unit of resumption and of work per process).
    key : str
        Content hash of the run; chunks made from another are recomputed.
    workers : int
        Processes the chunks run in (1: this one). The records do not depend on it.
    faults : opnav.studies.faults.Faults, optional
        Frame faults applied to the rendered frames (:class:`FrameFaults`).
    moon_ephemeris_sigma_km, moon_ephemeris_error : float, str
        The moons are drawn this far (km per axis, ICRF) from the ephemeris the image stage
        predicts with: a new draw per frame (``"white"``) or one per run (``"bias"``), as the
        measurement-mode truth of S1 has it. The image stage does not know the offset.
    progress : bool
        Show a progress bar (by frame; by finished chunk with several workers).
    """
    hook = FrameFaults(faults.on_frames if faults is not None else {}, tuple(moons), moon_ephemeris_sigma_km,
                       moon_ephemeris_error)
    sensor = scene_sensor(scenario, Tracking(options, tracking or TrackingOptions()))
    loop = Loop((sensor,), seed, Sky(scenario.catalog_path), Storage(Path(out) / "frames", dump_every), hook)
    return run_chunks(loop, Arc(epochs, r_ssb_km, v_ssb_km_s), folder=Path(out) / "stream",
                      key=f"{key}:{dump_every}:identified-only:joint-frames:{moon_ephemeris_sigma_km}:"
                          f"{moon_ephemeris_error}",
                      chunk_frames=chunk_frames, workers=workers, progress=progress)


def frames_on_disk(scenario, epochs: np.ndarray, r_ssb_km: np.ndarray, v_ssb_km_s: np.ndarray, out: Path, *,
                   seed: int, digest: str, options, tracking: bool = True, progress: bool = False,
                   tracking_options=None) -> LoopResult:
    """Render (or reuse) ``out/frames/frame_NNNNN.fits`` for every epoch and measure each as read back
    (module notes): one stage over the arc, full-frame (``tracking`` False) or tracking.

    Parameters
    ----------
    scenario : opnav.sim.scene.Scene
    epochs : (M,) array
        Mid-exposure epochs, TDB seconds past J2000.
    r_ssb_km, v_ssb_km_s : (M, 3) arrays
        Observer position (km) and velocity (km/s) relative to the SSB, ICRF.
    out : Path
        Run folder.
    seed : int
        Frame ``k`` draws its noise from ``default_rng([seed, k])``.
    digest : str
        Scene digest written to (and checked in) every header, with the seed.
    options : opnav.image.pipeline.PipelineOptions
    tracking : bool
        Tracking stage (predicting through the Chebyshev cache, as in memory) or full-frame stage.
    progress : bool
    tracking_options : opnav.image.tracking.TrackingOptions, optional
        The tracking stage's settings (default: the defaults).
    """
    stage = Tracking(options, tracking_options or TrackingOptions()) if tracking else FullFrame(options)
    sky = Sky(scenario.catalog_path, ephemeris="exact", stage_ephemeris="cached" if tracking else "exact")
    loop = Loop((scene_sensor(scenario, stage),), seed, sky, Storage(Path(out) / "frames", 1, FrameTag(seed, digest)))
    return run_chunks(loop, Arc(epochs, r_ssb_km, v_ssb_km_s), folder=None, chunk_frames=max(len(epochs), 1),
                      progress=progress)
