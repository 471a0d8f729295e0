"""S1: Mars cruise, RA/Dec of Phobos and Deimos (docs/studies.md#s1-mars-cruise; Tables 2 and 3).

Truth: S1 Table 1 state (TT 2013-12-12 12:00, heliocentric ICRF) propagated with
``opnav.dynamics.cruise_model()`` (DOP853) to the arc. Every ``step_s`` each
target of ``targets`` gives one apparent RA/Dec (light time and aberration, as
the renderer) with ``noise_arcsec`` Gaussian noise on each angle; the true moons
sit at the filters' ephemeris plus an offset of ``moon_ephemeris_sigma_km`` per
axis, drawn per measurement (``ephemeris_error = "white"``, what the paper's
filter assumes) or once per run and moon (``"bias"``, what an ephemeris error
is). The filters start from the truth plus a draw of P0 (5000 km, 5 m/s RMS) and
propagate with the same cruise model; the RMS is taken over the last 15 days
(the last half of a shorter arc).

The random streams depend on the seed and the record or frame index, not on the month:
runs of one seed in two months draw the same random numbers (common random numbers, which
make a month-to-month comparison paired). In measurement mode the draws are the same values;
from pixels each frame's noise comes from the same stream, and the per-record errors of July
and August of one seed correlate by about 0.3 (Phobos) and 0.14 (Deimos). Runs meant to be
independent across months take different seeds.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..constants import ARCSEC_RAD, DAY_S
from ..dynamics import cruise_model, propagate
from ..epochs import parse_epoch
from ..errors import InputError
from ..measurements import ProbeMeasurementModel, simulate_radec
from ..filters.options import NavigationConfig
from ..records import Measurement, join_frame_radec, split_radec_pairs
from .common import Simulation, tracking_facts

#: S1 Table 1: epoch (TT) and heliocentric ICRF state, km and km/s.
S1_EPOCH_TT = "2013-12-12T12:00:00"
S1_STATE0 = np.array([24_306_991.2893, 132_523_850.2219, 58_427_884.5328, -32.455391, 3.658828, 3.362343])
#: Settings only image mode reads (left out of measurement-mode run identities and hashes).
IMAGE_SETTINGS = ("image_stage", "dump_every", "true_camera_file", "camera_file", "camera_covariance",
                  "camera_error", "star_match_max_px")
#: Image mode: most frames with every frame written to disk (``dump_every = 1``), and kept in memory.
MAX_FRAMES_ON_DISK = 5000
MAX_STREAMED_FRAMES = 100_000
#: The moons image mode measures, and the embedded scene its camera comes from (package data).
MOONS = ("phobos", "deimos")
DEMO_RESOURCE = "demo.toml"
MONTHS = {"may": "2014-05-01", "jun": "2014-06-01", "jul": "2014-07-01", "aug": "2014-08-01"}
TARGETS = {"phobos": ("phobos",), "deimos": ("deimos",), "both": ("phobos", "deimos")}
#: S1 Tables 2 (0.1") and 3 (1"): position RMS (km), velocity RMS (m/s) over the last 15 days.
PAPER = {
    (0.1, "may"): {"phobos": (391.544, 0.067), "deimos": (143.680, 0.027), "both": (75.775, 0.018)},
    (0.1, "jun"): {"phobos": (124.819, 0.029), "deimos": (105.979, 0.018), "both": (76.529, 0.011)},
    (0.1, "jul"): {"phobos": (32.444, 0.013), "deimos": (13.808, 0.003), "both": (8.737, 0.003)},
    (0.1, "aug"): {"phobos": (26.166, 0.012), "deimos": (12.526, 0.004), "both": (7.641, 0.007)},
    (1.0, "may"): {"phobos": (3218.16, 0.564), "deimos": (1623.12, 0.304), "both": (1129.14, 0.228)},
    (1.0, "jun"): {"phobos": (1135.26, 0.270), "deimos": (703.78, 0.111), "both": (457.62, 0.082)},
    (1.0, "jul"): {"phobos": (440.82, 0.156), "deimos": (116.66, 0.024), "both": (72.92, 0.034)},
    (1.0, "aug"): {"phobos": (282.67, 0.101), "deimos": (123.88, 0.043), "both": (75.50, 0.069)},
}


#: The study's kind for the runner (:mod:`opnav.studies.base`): simulating (``simulate`` feeds the generic filter stages); ``--mode images`` renders and measures frames (``simulate_images``).
KIND = "simulating"
IMAGE_MODE = True


@dataclass(frozen=True)
class Settings:
    """S1 run settings (``[settings]`` of the run file; each one a ``--set`` key).

    Attributes
    ----------
    month : str
        ``may``, ``jun``, ``jul`` or ``aug`` 2014 (S1's four cases).
    day : int
        Day of the month the arc starts, 00:00 TDB (S1: 1; the demo starts on the 15th).
    targets : str
        ``phobos``, ``deimos`` or ``both``.
    noise_arcsec : float
        1-sigma of RA and of Dec, arcsec (S1: 0.1 or 1).
    noise_arcsec_phobos, noise_arcsec_deimos : float
        That moon's 1-sigma instead of ``noise_arcsec`` (0: ``noise_arcsec``), e.g. to compare an
        image-mode run with measurements at the noise its image stage achieved on each moon.
    duration_days : float
        Arc length, days (S1: 30).
    step_s : float
        Measurement interval, s (S1: 60).
    moon_ephemeris_sigma_km : float
        Moon ephemeris error, km per axis (S1: 1).
    ephemeris_error : str
        ``white`` (a new offset per measurement) or ``bias`` (one per run and moon) in the truth.
    ephemeris_model : str
        How the filters treat it: ``white`` (added to R), ``estimate`` or ``consider`` (offsets as states).
    sigma_position_km, sigma_velocity_m_s : float
        Initial error RMS (3-D), km and m/s (S1: 5000 and 5).
    process_noise_km2_s3 : float
        Filters' white-acceleration density (0: none; truth and filter dynamics are the same).
    image_stage : str
        Image mode only: ``tracking`` (full-frame acquisition, then stars and moons measured in
        windows around their predictions, :mod:`opnav.image.tracking`) or ``full-frame`` (every
        frame detected and identified from scratch).
    dump_every : int
        Image mode only: 1 writes every frame to ``frames/`` as FITS and measures it from there;
        0 keeps every frame in memory (only the tracked windows are rendered while tracking);
        N > 1 keeps them in memory and writes every N-th one in full for inspection.
    true_camera_file : str
        Image mode only: a camera file (docs/formats/camera.md) the frames are rendered with, e.g. the
        demo camera with distortion ("": the demo camera).
    camera_file : str
        Image mode only: a camera file the image stage measures with, e.g. one ``opnav calibrate``
        fitted ("": the demo camera, the nominal model).
    camera_covariance : bool
        Image mode with ``image_stage = "tracking"`` only: add the covariance of ``camera_file``'s
        ``[calibration]`` to each moon record's, as it moves the moon relative to the frame's stars
        (:mod:`opnav.image.camera_noise`; default false: the camera is taken as exact).
    camera_error : str
        With ``camera_covariance``: how that covariance enters. ``white`` adds it to each moon
        record's covariance (independent at every record); ``consider`` keeps each record's Jacobian
        by the camera's parameters and runs the EKF with their errors as consider parameters, one
        error shared by the whole arc (``[navigation] camera_error``; EKF only).
    star_match_max_px : float
        Image mode only: when star identification finds no match within 2 px of the a-priori
        attitude, the radius is doubled up to this (px; 0: never widened, the default). For a
        camera file known only nominally (an uncalibrated camera: stars up to several px from its
        model at the corners); :class:`opnav.image.pipeline.PipelineOptions`.
    """

    month: str = "jul"
    day: int = 1
    targets: str = "both"
    noise_arcsec: float = 0.1
    noise_arcsec_phobos: float = 0.0
    noise_arcsec_deimos: float = 0.0
    duration_days: float = 30.0
    step_s: float = 60.0
    moon_ephemeris_sigma_km: float = 1.0
    ephemeris_error: str = "white"
    ephemeris_model: str = "white"
    sigma_position_km: float = 5000.0
    sigma_velocity_m_s: float = 5.0
    process_noise_km2_s3: float = 0.0
    image_stage: str = "tracking"
    dump_every: int = 1
    true_camera_file: str = ""
    camera_file: str = ""
    camera_covariance: bool = False
    camera_error: str = "white"
    star_match_max_px: float = 0.0

    def __post_init__(self) -> None:
        for name in ("true_camera_file", "camera_file"):
            value = getattr(self, name)
            if value and not Path(value).expanduser().is_file():
                raise InputError(f"{name} must be a camera file (docs/formats/camera.md), got {value!r}: no such file")
        if self.dump_every < 0:
            raise InputError(f"dump_every must be >= 0 (0: no frame on disk), got {self.dump_every!r}")
        if not (self.star_match_max_px == 0.0 or 2.0 <= self.star_match_max_px <= 64.0):
            raise InputError(f"star_match_max_px must be 0 (no widening) or from 2 to 64 px, got {self.star_match_max_px!r}")
        if self.image_stage not in ("tracking", "full-frame"):
            raise InputError(f"image_stage must be 'tracking' or 'full-frame', got {self.image_stage!r}")
        if self.camera_covariance and not (self.camera_file and self.image_stage == "tracking"):
            raise InputError("camera_covariance = true needs camera_file (a camera file with a [calibration] table, "
                             "from opnav calibrate) and image_stage = 'tracking'")
        if self.camera_error not in ("white", "consider"):
            raise InputError(f"camera_error must be 'white' or 'consider', got {self.camera_error!r}")
        if self.camera_error == "consider" and not self.camera_covariance:
            raise InputError("camera_error = 'consider' needs camera_covariance = true (and camera_file with a "
                             "[calibration] table)")
        if self.camera_error == "consider" and self.ephemeris_model != "white":
            raise InputError("camera_error = 'consider' works with ephemeris_model = 'white' only, "
                             f"got {self.ephemeris_model!r}")
        if self.month not in MONTHS:
            raise InputError(f"month must be one of {sorted(MONTHS)}, got {self.month!r}")
        if not 1 <= self.day <= 28:
            raise InputError(f"day must be from 1 to 28, got {self.day!r}")
        if self.targets not in TARGETS:
            raise InputError(f"targets must be one of {sorted(TARGETS)}, got {self.targets!r}")
        for name in ("noise_arcsec", "duration_days", "step_s", "sigma_position_km", "sigma_velocity_m_s"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise InputError(f"{name} must be positive, got {value!r}")
        # a million epochs are two million records in memory (about 1 GB) and minutes of filtering; 57 days at
        # a 1-s step (4.9 million) ran for an hour before it could say anything
        if not 2 <= self.duration_days * DAY_S / self.step_s <= 1_000_000:
            raise InputError(f"duration_days / step_s gives {self.duration_days * DAY_S / self.step_s:.0f} epochs; "
                             "allowed 2 to 1,000,000 (a longer step_s or a shorter arc)")
        if self.duration_days > 60.0:
            raise InputError(f"duration_days must be at most 60 (the S1 arcs are 30 days), got {self.duration_days}")
        for name in ("noise_arcsec_phobos", "noise_arcsec_deimos"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0.0):
                raise InputError(f"{name} must be >= 0 (0: noise_arcsec), got {value!r}")
        if not (np.isfinite(self.moon_ephemeris_sigma_km) and self.moon_ephemeris_sigma_km >= 0.0):
            raise InputError(f"moon_ephemeris_sigma_km must be >= 0, got {self.moon_ephemeris_sigma_km!r}")
        if self.ephemeris_error not in ("white", "bias"):
            raise InputError(f"ephemeris_error must be 'white' or 'bias', got {self.ephemeris_error!r}")
        if self.ephemeris_model not in ("white", "estimate", "consider"):
            raise InputError(f"ephemeris_model must be white, estimate or consider, got {self.ephemeris_model!r}")
        if not (np.isfinite(self.process_noise_km2_s3) and self.process_noise_km2_s3 >= 0.0):
            raise InputError(f"process_noise_km2_s3 must be >= 0, got {self.process_noise_km2_s3!r}")


def arc_start(settings: Settings) -> float:
    """Start of the arc, TDB s past J2000: ``day`` of ``month`` 2014 at 00:00 TDB."""
    return parse_epoch(MONTHS[settings.month] + "T00:00:00", scale="tdb") + (settings.day - 1) * DAY_S


def dynamics(settings: Settings):
    """The truth's and the filters' force model (Sun + planets, Moon; no SRP)."""
    return cruise_model()


def simulate(settings: Settings, seed: int) -> Simulation:
    """Truth, records and filter start of one S1 run (module notes)."""
    rng = np.random.default_rng([seed, 1])
    t_start = arc_start(settings)
    count = int(round(settings.duration_days * DAY_S / settings.step_s))
    epochs = t_start + settings.step_s * np.arange(1, count + 1)
    truth = propagate(cruise_model(), parse_epoch(S1_EPOCH_TT, scale="tt"), S1_STATE0,
                      np.concatenate([[t_start], epochs])).states
    exact = ProbeMeasurementModel("sun")
    targets = TARGETS[settings.targets]
    records = []
    for target in targets:
        sigma = (getattr(settings, f"noise_arcsec_{target}") or settings.noise_arcsec) * ARCSEC_RAD
        shape = (3,) if settings.ephemeris_error == "bias" else (epochs.size, 3)
        offset = rng.normal(0.0, settings.moon_ephemeris_sigma_km, shape)
        values = simulate_radec(exact, target, epochs, truth[1:], sigma_rad=sigma, rng=rng, target_offset_km=offset)
        records += [Measurement(t, "radec", v, sigma**2 * np.eye(2), target=target, sensor="nac")
                    for t, v in zip(epochs, values)]
    records.sort(key=lambda r: r.t_tdb_s)  # stable: both moons of an epoch in target order
    sig_r = settings.sigma_position_km / np.sqrt(3.0)
    sig_v = 1e-3 * settings.sigma_velocity_m_s / np.sqrt(3.0)
    P0 = np.diag([sig_r**2] * 3 + [sig_v**2] * 3)
    x0 = truth[0] + np.sqrt(np.diag(P0)) * rng.standard_normal(6)
    q = settings.process_noise_km2_s3
    nav = NavigationConfig(
        t0_tdb_s=t_start, dynamics="cruise", x0=x0, P0=P0,
        target_position_sigma_km=settings.moon_ephemeris_sigma_km,
        ephemeris_error=settings.ephemeris_model, ephemeris_targets=targets, seed=seed,
        process_noise={"model": "white", "q_km2_s3": q} if q > 0 else {"model": "none"},
    )
    window = max(epochs[-1] - 15.0 * DAY_S, t_start + 0.5 * (epochs[-1] - t_start))
    position, velocity = PAPER[(1.0 if settings.noise_arcsec >= 0.5 else 0.1, settings.month)][settings.targets]
    paper = {"position_rms_km": position, "velocity_rms_m_s": velocity,
             "note": "S1 Tables 2/3, the row of this month, targets and noise (0.1\" or 1\", nearest)"}
    return Simulation("sun", epochs, truth[1:], records, nav, dynamics(settings), float(window), paper,
                      {"window": "last 15 days (last half of a shorter arc)"}, start_truth=truth[0])


def load_demo():
    """The embedded demo scene (``opnav/data/demo.toml``) and its navigation section: ``(Scene,
    NavigationConfig, digest)``; S1 image mode's camera, detector, PSF, pointing and catalog.

    ``digest`` (16 hex digits of SHA-256 of the file) marks rendered frames, so frames from
    another version of the scene are never reused.
    """
    import hashlib
    import importlib.resources

    from ..filters.options import load_navigation
    from ..sim.scene import load_scene

    resource = importlib.resources.files("opnav").joinpath("data", DEMO_RESOURCE)
    with importlib.resources.as_file(resource) as path:
        scene = load_scene(path)
        nav = load_navigation(path)
    return scene, nav, hashlib.sha256(resource.read_text().encode()).hexdigest()[:16]


def process_frames(paths, *, catalog, ephemeris, vmag_limit: float | None, seed: int, progress: bool = False):
    """The full-frame image stage on demo frames already on disk, Phobos and Deimos to ``vmag_limit``
    stars, frame ``k`` from ``[seed, 1, k]`` (:func:`opnav.sim.loop.measure_files`): the loop's result."""
    from ..image.pipeline import PipelineOptions
    from ..sim.loop import measure_files
    from ..sim.stages import FullFrame

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(paths), desc="process", unit="frame")
    try:
        return measure_files(paths, FullFrame(PipelineOptions(targets=MOONS, vmag_limit=vmag_limit)), seed=seed,
                             catalog=catalog, ephemeris=ephemeris,
                             on_frame=None if bar is None else (lambda: bar.update(1)))
    finally:
        if bar is not None:
            bar.close()


def simulate_images(settings: Settings, seed: int, out, *, progress: bool = False, workers: int = 1,
                    faults=None) -> Simulation:
    """S1 from pixels: render a frame every ``step_s`` with the demo's 1-degree camera, measure the
    moons with the image stage, and set up the filters as :func:`simulate` does.

    The frames follow the S1 trajectory with the demo's camera, detector, PSF and Phobos-tracking
    pointing (the catalog stars and Mars are in the frames); the records come from the image
    stage (``image_stage``: tracking after a full-frame acquisition, or full-frame on every frame),
    through the one render -> measure loop (:mod:`opnav.sim.loop`, :mod:`opnav.studies.image_loop`).
    With ``dump_every = 1`` every frame is written to ``out/frames`` (FITS with truth) and measured
    as read back (frames already there from the same scenario and seed are reused:
    :func:`opnav.studies.image_loop.frames_on_disk`). Otherwise the frames stay in memory
    (:func:`opnav.studies.image_loop.stream_frames`: while tracking, only the windows the stage
    reads are rendered; every ``dump_every``-th frame is written for inspection; the arc goes in
    chunks of a day, each from its own acquisition and saved, so an interrupted run resumes;
    ``workers`` processes run the days side by side with the same records; ``faults``: the run's
    frame faults, :class:`opnav.studies.faults.Faults`). The moons are rendered at the ephemeris
    the filters use; in memory they are moved by the moon ephemeris error of :func:`simulate`
    (``moon_ephemeris_sigma_km``, ``ephemeris_error``: the frames show the moons where the truth
    has them, the stage predicts them from the ephemeris, and the filters treat the error as in
    measurement mode), while frames written to disk (``dump_every = 1``) show them at the
    ephemeris itself, so their filters' R is conservative. A frame without a star-identified
    attitude gives no records (``facts.frames_skipped``).
    """
    from dataclasses import asdict, replace

    from .. import __version__
    from ..ephemeris import default_ephemeris
    from ..consistency import chi2_mean_bounds
    from ..image.pipeline import PipelineOptions
    from ..sim.checks import pair_chi2, radec_errors
    from ..sim.scene import observer_states
    from .image_loop import frames_on_disk, stream_frames
    from .runner import digest as content_hash

    if settings.targets != "both":
        raise InputError("image mode measures both moons in the demo camera's frames; use targets = 'both'")
    streaming = settings.dump_every != 1
    if streaming and settings.image_stage != "tracking":
        raise InputError("dump_every other than 1 (frames in memory) needs image_stage = 'tracking'")
    frame_faults = faults.on_frames if faults is not None else {}
    if frame_faults and not streaming:
        raise InputError(f"frame faults {sorted(frame_faults)} act on frames rendered in memory; set dump_every "
                         "to 0 or to N > 1")
    base, _, digest = load_demo()
    true_camera, measure_camera, camera_digest = s1_cameras(settings, base.camera)
    t_start = arc_start(settings)
    count = int(round(settings.duration_days * DAY_S / settings.step_s))
    limit = MAX_STREAMED_FRAMES if streaming else MAX_FRAMES_ON_DISK
    if count > limit:
        where = "in memory" if streaming else "with every frame on disk (dump_every = 0 keeps them in memory)"
        raise InputError(f"image mode renders one frame per epoch: {count} frames asked, at most {limit} {where}; "
                         "raise step_s or shorten duration_days")
    epochs = t_start + settings.step_s * np.arange(1, count + 1)
    # rendered with the true camera, measured with the one the stage assumes (None: the same)
    scenario = replace(base, t_tdb_s=epochs, seed=seed, camera=true_camera, measure_camera=measure_camera)
    out = Path(out)
    r, v = observer_states(scenario, epochs, default_ephemeris())
    options = PipelineOptions(targets=MOONS, vmag_limit=scenario.options.vmag_limit,
                              star_match_max_px=settings.star_match_max_px or None)
    tracking = s1_tracking_options(settings)
    if streaming:
        identity = asdict(settings)
        if settings.camera_error == "white":  # runs from before the setting keep their saved chunks
            del identity["camera_error"]
        key = content_hash({"settings": identity, "seed": seed, "opnav": __version__, "demo": digest,
                            **({"frame_faults": frame_faults} if frame_faults else {}),
                            **({"cameras": camera_digest} if camera_digest else {})})
        loop = stream_frames(scenario, epochs, r, v, out, seed=seed, options=options, tracking=tracking, moons=MOONS,
                             dump_every=settings.dump_every, key=key, workers=workers, faults=faults,
                             moon_ephemeris_sigma_km=settings.moon_ephemeris_sigma_km,
                             moon_ephemeris_error=settings.ephemeris_error, progress=progress)
        frames_facts = {"frames_on_disk": len(loop.paths), "chunks_reused": loop.chunks_reused}
    else:
        loop = frames_on_disk(scenario, epochs, r, v, out, seed=seed,
                              digest=digest + f"-s1-{settings.month}" + (f"-{camera_digest}" if camera_digest else ""),
                              options=options, tracking=settings.image_stage == "tracking", progress=progress,
                              tracking_options=tracking)
        frames_facts = {"frames_reused": loop.frames_reused, "frames_rerendered": loop.rerendered}
    frames_facts = {"frames": count, "frames_windowed": loop.frames_windowed, "frames_full": loop.frames_full,
                    **frames_facts, "frames_dropped": loop.frames_dropped}
    if settings.image_stage == "tracking":
        frames_facts["tracked_stars"] = {"used": loop.stars_used, "misidentified": loop.stars_misidentified}
    # the moons of one frame share its attitude error: one radec_pair with their cross-covariance
    records = sorted(join_frame_radec([rec for rec in loop.records if rec.kind in ("radec", "radec_pair")]),
                     key=lambda rec: rec.t_tdb_s)
    if not records:
        raise InputError(f"{out}: no moon measured in {count} frames")
    per_moon = split_radec_pairs(records)
    # truth, filter start and window as in measurement mode; the records are the frames' instead
    sim = simulate(replace(settings, ephemeris_error="white"), seed)
    if settings.camera_error == "consider":  # the records carry their camera Jacobians: the EKF holds the errors
        calibration = tracking.camera_covariance
        sim = replace(sim, navigation=replace(sim.navigation, camera_error="consider",
                                              camera_parameters=calibration.names,
                                              camera_covariance=calibration.covariance))
    facts = dict(sim.facts)
    errors = radec_errors(records, loop.truths)
    for entry in errors.values():  # each record's d^T C^-1 d against the frame's truth: chi-square(2)
        chi2 = entry.pop("chi2")
        entry.update(chi2_mean=float(np.mean(chi2)), chi2_max=float(np.max(chi2)),
                     chi2_mean_interval_99=list(chi2_mean_bounds(2, len(chi2), 0.99)))
    pairs = pair_chi2(records, loop.truths)
    if pairs.size:  # the frames' pairs against the truth with their cross-covariance: chi-square(4)
        facts["measurement_pairs"] = {"count": int(pairs.size), "chi2_mean": float(np.mean(pairs)),
                                      "chi2_mean_interval_99": list(chi2_mean_bounds(4, pairs.size, 0.99))}
    facts.update({**frames_facts, "frames_skipped": loop.skipped, "measurement_errors": errors,
                  "image_stage": settings.image_stage, "moon_not_measured": loop.missed_counts()})
    sample = _sample_frame(list(loop.paths), per_moon)
    if sample is not None:
        facts["sample_frame"] = str(sample)
    if settings.image_stage == "tracking":
        facts["tracking"] = tracking_facts(list(loop.events))
    return replace(sim, records=records, facts=facts)


def s1_cameras(settings: Settings, demo_camera):
    """``(true camera, camera the stage assumes or None, digest)`` of image mode: ``true_camera_file``
    (default the demo camera) renders, ``camera_file`` (default the demo camera, the nominal model)
    measures; ``digest`` (16 hex digits of the files' SHA-256, "" without them) marks the frames and
    chunks so that those of other cameras are never reused."""
    import hashlib

    from ..camera import read_camera_file

    if not (settings.true_camera_file or settings.camera_file):
        return demo_camera, None, ""
    true = read_camera_file(settings.true_camera_file).camera if settings.true_camera_file else demo_camera
    assumed = read_camera_file(settings.camera_file).camera if settings.camera_file else demo_camera
    if assumed.shape != true.shape:
        raise InputError(f"camera_file {settings.camera_file!r} is {assumed.width_px} x {assumed.height_px} px; the "
                         f"frames' camera {true.width_px} x {true.height_px} px")
    text = "".join(Path(p).read_text() for p in (settings.true_camera_file, settings.camera_file) if p)
    return true, assumed, hashlib.sha256(text.encode()).hexdigest()[:16]


def s1_tracking_options(settings: Settings):
    """The tracking stage's settings: the defaults, with ``camera_file``'s calibration covariance and
    ``camera_error`` when ``camera_covariance`` is set (None: the defaults)."""
    if not settings.camera_covariance:
        return None
    from ..camera import read_camera_file
    from ..image.tracking import TrackingOptions

    calibration = read_camera_file(settings.camera_file).calibration
    if calibration is None:
        raise InputError(f"camera_covariance = true: camera_file {settings.camera_file!r} has no [calibration] table "
                         "(docs/formats/camera.md); write one with opnav calibrate")
    return TrackingOptions(camera_covariance=calibration, camera_error=settings.camera_error)


def _sample_frame(paths, records):
    """The middle frame on disk among those where both moons were measured (any frame if none was;
    None when no frame is on disk)."""
    if not paths:
        return None
    counts: dict = {}
    for record in records:
        counts[record.frame_id] = counts.get(record.frame_id, 0) + 1
    per_path = np.array([counts.get(Path(path).stem, 0) for path in paths])
    best = np.flatnonzero(per_path == per_path.max())
    return paths[int(best[best.size // 2])]
