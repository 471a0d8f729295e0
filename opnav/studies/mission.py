"""Any mission from its run file: truth -> simulated measurements -> filters (docs/mission.md).

The run file's ``[settings]`` describe the mission (each key a ``--set`` key; the defaults are the
translunar coast of ``samples/cislunar.toml``):

1. **Epochs.** The filters start at ``start``; a record set every ``step_s`` from ``start + step_s``
   to ``stop`` (in ``epoch_scale``).
2. **Truth**, the spacecraft's states relative to ``center`` (ICRF, km, km/s), by ``trajectory``:

   - ``"state"``: ``position_km``/``velocity_km_s`` at ``state_epoch`` propagated by DOP853
     (:func:`opnav.dynamics.states_at`, either side of its epoch) with the force model below;
   - ``"oem"``: a CCSDS OEM (``oem_file``, :func:`opnav.ccsds.read_oem`) interpolated as the OEM
     says (its ``INTERPOLATION``/``INTERPOLATION_DEGREE``): the arc is written to a scratch SPK
     (:func:`opnav.ephemeris.spk_writer.write_oem_spk`, SPICE types 13/9 are those interpolations)
     and read back, so ``opnav kernel --oem`` and this study read an OEM the same way;
   - ``"spk"``: body ``spk_body`` (NAIF id or name) of the SPICE ``kernels``.

3. **Bodies.** The truth's bodies (targets, the truth's third bodies) come from ``kernels`` when it
   is given (:class:`opnav.ephemeris.spice.SpiceEphemeris`, the shipped DE421 loaded under them),
   else from DE421, and the filters read the same: the kernels through a Chebyshev cache
   (:func:`filter_ephemeris`, :class:`opnav.ephemeris.spice.KernelCache`, within 1 cm; named by the
   force model, :attr:`opnav.dynamics.ForceModel.ephemeris`), else DE421's. So a body only the kernels
   hold (an asteroid's SPK) can be a target and a gravity body; the kernels must cover it over
   the filters' reach (:func:`_filter_reach`: whole days, 6 days beyond the arc each side).
4. **Force model** (the filters', and the ``"state"`` truth's): point masses of ``gravity``
   (``center`` the central one; DE421's GMs, :data:`opnav.constants.GM_KM3_S2`, else the kernels'
   ``BODYnnn_GM``, :func:`gm_km3_s2`), and solar
   radiation pressure when ``srp_area_to_mass_m2_kg > 0`` (conical shadows of the gravity bodies
   with a radius in :data:`opnav.constants.RADIUS_KM`).
5. **Measurements:** the apparent RA/Dec of each body of ``targets`` (its centre, a line of sight;
   light time and aberration as the renderer applies them, :func:`opnav.measurements.simulate_radec`)
   with ``noise_arcsec`` Gaussian noise on each angle (one value, or one per target); the targets'
   true positions are the ephemeris plus ``target_ephemeris_sigma_km`` white noise per axis, which
   the filters add to R.
6. **Filters** start from the truth plus a draw of P0 (``sigma_position_km``, ``sigma_velocity_m_s``
   per axis) and run with ``process_noise_km2_s3``; the RMS is taken over the last half of the arc.

Every file a setting names (``oem_file``, ``kernels``) is taken from the run file's folder when
relative (:data:`opnav.studies.settings.RUN_FILE_FOLDER`), and the SHA-256 of its bytes is part of
the run's identity (:attr:`Settings.inputs_sha256`), so a rewritten file is simulated again.

**Image mode** (``--mode images``, or ``mode = "images"`` in the run file's ``[scenario]``):
:func:`simulate_images` renders each target at each record epoch on the navigation camera, pointed
at it in turn (or, with ``attitude = "ck"``, oriented by a CK: docs/formats/ck.md), with a star tracker
for the attitude, and measures the body's centre
(:mod:`opnav.studies.mission_images`); the records carry the image stage's covariances, and are
checked against the truth (wrong-body records, achieved noise per target) in the run's facts. The
targets' shapes and reflectance come through :func:`mission_bodies`.
"""

from __future__ import annotations

import difflib
import functools
import hashlib
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import TIME_SCALES, CalendarText, check_zone
from ..constants import ARCSEC_RAD, DAY_S, GM_KM3_S2, RADIUS_KM
from ..epochs import describe_epoch, parse_epoch
from ..errors import InputError, OpnavError
from ..filters.options import NavigationConfig
from ..ephemeris.spk_writer import OEM_FRAMES
from ..records import Measurement, file_sha256
from .common import Simulation
from .mission_exposure import EXPOSURE_LAWS
from .settings import RUN_FILE_FOLDER

#: The study's kind for the runner (:mod:`opnav.studies.base`): simulating, measurement mode only.
KIND = "simulating"
#: ``--mode images`` (or ``[scenario] mode = "images"``) renders the targets and measures their centres
#: (:func:`simulate_images`, :mod:`opnav.studies.mission_images`).
IMAGE_MODE = True
IMAGE_SETTINGS: tuple[str, ...] = ("camera_fov_deg", "camera_px", "camera_aperture_mm", "camera_exposure_s",
                                   "camera_exposure_law", "camera_peak_fraction", "camera_exposure_limits_s",
                                   "tracker_fov_deg", "tracker_px", "tracker_vmag_limit", "tracker_boresight_body",
                                   "attitude", "ck_frame", "ck_tolerance_s")
#: Where the truth comes from (``trajectory``).
TRAJECTORIES = ("state", "oem", "spk")
#: Where image mode's navigation-camera attitude comes from (``attitude``): the pointing law or a CK.
ATTITUDES = ("pointing", "ck")
#: Reflectance models of a ``shape_target`` (:func:`opnav.shape.reflectance_weights`).
SHAPE_SHADINGS = ("lambert", "lommel-seeliger", "lunar-lambert")
#: Most epochs of a run (as S1: two million records would be about 1 GB in memory).
MAX_EPOCHS = 1_000_000
#: NAIF id of the spacecraft in the scratch SPK an OEM is read through.
_OEM_BODY = -999_001


def _ephemeris_bodies() -> tuple[str, ...]:
    """Bodies the filters' ephemeris (DE421, MAR080) holds: what ``targets`` may name."""
    from ..ephemeris import Ephemeris

    return Ephemeris.known_bodies()


#: Bodies with a GM (``center``, ``gravity``): DE421's, planets as their systems.
GRAVITY_BODIES = tuple(GM_KM3_S2)


@dataclass(frozen=True)
class Settings:
    """A mission's run settings (``[settings]`` of a run file with ``study = "mission"``; each a ``--set`` key).

    Attributes
    ----------
    start, stop : str
        First epoch of the arc (the filters' initial estimate) and last record epoch, calendar
        dates in ``epoch_scale``.
    epoch_scale : str
        ``utc``, ``tt``, ``tdb`` or ``tai``: the scale of ``start``, ``stop`` and ``state_epoch``.
    step_s : float
        Interval between record epochs, s.
    trajectory : str
        Where the truth comes from: ``state``, ``oem`` or ``spk`` (module notes).
    state_epoch : str
        ``trajectory = "state"``: epoch of ``position_km``/``velocity_km_s`` (before, inside or after the arc).
    position_km, velocity_km_s : 3 floats
        ``trajectory = "state"``: the spacecraft's state, ICRF, relative to ``center``, km and km/s.
    oem_file : str
        ``trajectory = "oem"``: a CCSDS OEM (KVN or XML) of the spacecraft, any centre DE421 holds,
        frame ICRF/GCRF/EME2000/J2000, covering ``start`` to ``stop``.
    spk_body : str
        ``trajectory = "spk"``: the spacecraft's NAIF id (``"-77"``) or name in ``kernels``.
    kernels : tuple of str
        SPICE kernels (SPK, PCK, text or meta-kernels; docs/formats/kernels.md), loaded over the
        shipped DE421: the spacecraft of ``spk_body`` and the truth's bodies.
    center : str
        Origin of every state and the central body of the force model.
    gravity : tuple of str
        Bodies whose point masses act (``center`` among them).
    srp_area_to_mass_m2_kg : float
        Solar radiation pressure: area over mass, m^2/kg (0: none).
    srp_cr : float
        Reflectivity coefficient of the SRP term.
    targets : tuple of str
        Bodies whose centre's apparent RA/Dec is measured at every epoch.
    noise_arcsec : float or tuple of float
        1-sigma of RA and of Dec, arcsec: one value for every target or one per target.
    target_ephemeris_sigma_km : float
        The targets' true positions are off the ephemeris by this, km per axis, a new draw per
        record (the filters add it to R).
    starlight_target : str
        A body with a radius in :data:`opnav.constants.RADIUS_KM` ("": no starlight records): at each
        epoch one ``starlight`` record (angle from each star of ``starlight_stars_radec_deg`` to the
        body's centre, and to its limb) per star clear of the body and of the angles' poles.
    starlight_stars_radec_deg : tuple of (float, float)
        The stars' ICRF right ascension and declination, deg (fixed directions; the records and the
        filters apply the spacecraft's aberration to them).
    starlight_star_sigma_arcsec, starlight_target_sigma_arcsec : float
        The star sensor's and the body sensor's 1-sigma, arcsec: the records' covariance is
        :func:`opnav.measurements.starlight_covariance` of the two (the angle carries both).
    camera_fov_deg, camera_px : float, int
        Image mode: the navigation camera's square field across, deg, and pixels across.
    camera_aperture_mm : float
        Image mode: its aperture diameter, mm.
    camera_exposure_s : float or tuple of float
        Image mode: its exposure for each target, s (one value for all, or one per target), with
        ``camera_exposure_law = "fixed"``.
    camera_exposure_law : str
        Image mode: ``fixed`` (``camera_exposure_s``) or ``peak``: each frame exposed so that the
        target's predicted brightest pixel reaches ``camera_peak_fraction`` of the full well, on the
        camera's settings between ``camera_exposure_limits_s`` [shortest, longest] (s), a factor 2
        apart (:mod:`opnav.studies.mission_exposure`).
    camera_peak_fraction : float
        The ``peak`` law's brightest pixel, a fraction of the full well.
    camera_exposure_limits_s : (float, float)
        The ``peak`` law's shortest and longest exposure, s.
    tracker_fov_deg, tracker_px : float, int
        Image mode: the star tracker's square field across, deg, and pixels across.
    tracker_vmag_limit : float
        Image mode: the faintest catalog star the tracker identifies (V mag).
    tracker_boresight_body : 3 floats
        Image mode: the tracker's boresight in the body frame (the navigation camera's: +z its
        boresight, +x towards the Sun's side), any length.
    attitude : str
        Image mode: ``pointing`` (the pointing law turns the camera to each target) or ``ck``: the
        camera's attitude at each epoch is ``ck_frame``'s from a CK among ``kernels``
        (:func:`opnav.studies.mission_images.ck_pointing`; docs/formats/ck.md).
    ck_frame : str
        ``attitude = "ck"``: the navigation camera's frame, an FK frame name (a camera frame fixed on the
        spacecraft's CK frame, or the CK frame itself), a frame id, or a CK id (``"-77000"``); its axes
        are the camera's (+z boresight, +x along columns, +y along rows).
    ck_tolerance_s : float
        ``attitude = "ck"``: outside the CK's interpolation intervals, a pointing record this near (s)
        answers (0: interpolated pointing only).
    shape_target : str
        Image mode: a target drawn and measured as a triangle mesh ("": none; docs/formats/shape.md).
    shape_file : str
        Its Wavefront OBJ (body axes, origin at the ephemeris point), relative to the run file, or
        ``"opnav:NAME"`` for a shape shipped in ``opnav/data`` (``"opnav:asteroid.obj"``).
    shape_scale_km : float
        Kilometres per unit of the OBJ file.
    shape_shading : str
        ``lambert``, ``lommel-seeliger`` or ``lunar-lambert``; ``shape_albedo`` its geometric albedo,
        ``shape_lunar_lambert_l`` the lunar-Lambert ``L``.
    shape_pole_radec_deg : (float, float)
        The body's pole, ICRF right ascension and declination, deg.
    shape_period_h, shape_prime_meridian_deg : float
        Its rotation period, h (0: it does not turn), and its prime meridian angle at J2000, deg
        (from the node of its equator on the ICRF equator, the IAU convention).
    sigma_position_km, sigma_velocity_m_s : float
        Initial error 1-sigma per axis, km and m/s.
    process_noise_km2_s3 : float
        Filters' white-acceleration density (0: none).
    inputs_sha256 : str
        Not a key: SHA-256 of the files ``oem_file`` and ``kernels`` name, set on load, so that the
        run's identity changes when a file does.
    """

    start: CalendarText = "2027-03-10T01:00:00"
    stop: CalendarText = "2027-03-14T00:00:00"
    epoch_scale: str = field(default="tdb", metadata={"choices": TIME_SCALES})
    step_s: float = 600.0
    trajectory: str = field(default="state", metadata={"choices": TRAJECTORIES})
    state_epoch: CalendarText = "2027-03-10T00:00:00"
    position_km: tuple[float, float, float] = (-2470.3367, -5343.9210, -2934.5907)
    velocity_km_s: tuple[float, float, float] = (10.099509, -3.919871, -1.363635)
    oem_file: str = ""
    spk_body: str = ""
    kernels: tuple[str, ...] = ()
    center: str = field(default="earth", metadata={"choices": GRAVITY_BODIES})
    gravity: tuple[str, ...] = ("earth", "moon", "sun")
    srp_area_to_mass_m2_kg: float = 0.0
    srp_cr: float = 1.3
    targets: tuple[str, ...] = ("moon", "earth")
    noise_arcsec: float | tuple[float, ...] = 3.0
    target_ephemeris_sigma_km: float = 0.0
    starlight_target: str = ""
    starlight_stars_radec_deg: tuple[tuple[float, float], ...] = ()
    starlight_star_sigma_arcsec: float = 1.0
    starlight_target_sigma_arcsec: float = 3.0
    camera_fov_deg: float = 20.0
    camera_px: int = 512
    camera_aperture_mm: float = 30.0
    camera_exposure_s: float | tuple[float, ...] = 1e-5
    camera_exposure_law: str = field(default="fixed", metadata={"choices": EXPOSURE_LAWS})
    camera_peak_fraction: float = 0.5
    camera_exposure_limits_s: tuple[float, float] = (1e-6, 1.0)
    tracker_fov_deg: float = 20.0
    tracker_px: int = 1024
    tracker_vmag_limit: float = 6.5
    tracker_boresight_body: tuple[float, float, float] = (-1.0, 0.0, 0.0)
    attitude: str = field(default="pointing", metadata={"choices": ATTITUDES})
    ck_frame: str = ""
    ck_tolerance_s: float = 0.0
    shape_target: str = ""
    shape_file: str = ""
    shape_scale_km: float = 1.0
    shape_shading: str = field(default="lommel-seeliger", metadata={"choices": SHAPE_SHADINGS})
    shape_albedo: float = 0.15
    shape_lunar_lambert_l: float = 0.5
    shape_pole_radec_deg: tuple[float, float] = (0.0, 90.0)
    shape_period_h: float = 0.0
    shape_prime_meridian_deg: float = 0.0
    sigma_position_km: float = 10.0
    sigma_velocity_m_s: float = 1.0
    process_noise_km2_s3: float = 0.0
    inputs_sha256: str = field(default="", init=False)

    def __post_init__(self) -> None:
        for name in ("start", "stop", "state_epoch"):
            check_zone(getattr(self, name), self.epoch_scale, name)
            _epoch(self, name)  # a date astropy cannot read is named here, not at the first use
        if not (np.isfinite(self.step_s) and self.step_s > 0.0):
            raise InputError(f"step_s must be positive, got {self.step_s!r}")
        span = _epoch(self, "stop") - _epoch(self, "start")
        if not span > 0.0:
            raise InputError(f"stop ({self.stop}) must be after start ({self.start})")
        if not 1 <= span / self.step_s <= MAX_EPOCHS:
            raise InputError(f"(stop - start) / step_s gives {span / self.step_s:.0f} record epochs; allowed 1 to "
                             f"{MAX_EPOCHS:,} (a longer step_s or a shorter arc)")
        self._check_bodies()
        if self.center not in self.gravity:
            raise InputError(f"gravity must include center {self.center!r} (its central point mass), got "
                             f"{list(self.gravity)}")
        if not self.targets and not self.starlight_target:
            raise InputError("targets must name at least one body (or starlight_target and its stars be given)")
        self._check_starlight()
        noise = np.atleast_1d(np.asarray(self.noise_arcsec, dtype=float))
        if noise.size not in (1, max(len(self.targets), 1)):
            raise InputError(f"noise_arcsec must be one value or one per target ({len(self.targets)}: "
                             f"{', '.join(self.targets)}), got {noise.size}")
        if not np.all(noise > 0.0):
            raise InputError(f"noise_arcsec must be positive, got {self.noise_arcsec!r}")
        self._check_cameras()
        for name in ("sigma_position_km", "sigma_velocity_m_s", "srp_cr", "starlight_star_sigma_arcsec",
                     "starlight_target_sigma_arcsec"):
            if not getattr(self, name) > 0.0:
                raise InputError(f"{name} must be positive, got {getattr(self, name)!r}")
        for name in ("srp_area_to_mass_m2_kg", "target_ephemeris_sigma_km", "process_noise_km2_s3"):
            if not getattr(self, name) >= 0.0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        self._check_shape()
        self._check_trajectory()
        self._check_coverage()
        self._check_attitude()

    def _check_cameras(self) -> None:
        """Image mode's sensors: positive sizes and fields under 90 deg, an exposure per target, a boresight."""
        for name in ("camera_fov_deg", "tracker_fov_deg"):
            if not 0.0 < getattr(self, name) < 90.0:
                raise InputError(f"{name} must be in (0, 90) deg, got {getattr(self, name)!r}")
        for name in ("camera_px", "tracker_px"):
            if not 16 <= getattr(self, name) <= 8192:
                raise InputError(f"{name} must be 16 to 8192 pixels, got {getattr(self, name)!r}")
        if not self.camera_aperture_mm > 0.0:
            raise InputError(f"camera_aperture_mm must be positive, got {self.camera_aperture_mm!r}")
        exposure = np.atleast_1d(np.asarray(self.camera_exposure_s, dtype=float))
        if exposure.size not in (1, max(len(self.targets), 1)) or not np.all(exposure > 0.0):
            raise InputError(f"camera_exposure_s must be one positive value or one per target ({len(self.targets)}: "
                             f"{', '.join(self.targets)}), got {self.camera_exposure_s!r}")
        if not 0.0 < self.camera_peak_fraction <= 1.0:
            raise InputError(f"camera_peak_fraction must be in (0, 1] (of the full well), got {self.camera_peak_fraction!r}")
        shortest, longest = self.camera_exposure_limits_s
        if not (np.isfinite(longest) and 0.0 < shortest <= longest):
            raise InputError(f"camera_exposure_limits_s must be [shortest, longest] with 0 < shortest <= longest, s, got "
                             f"{list(self.camera_exposure_limits_s)}")
        if not np.linalg.norm(self.tracker_boresight_body) > 0.0:
            raise InputError(f"tracker_boresight_body must be a non-zero vector [x, y, z], got "
                             f"{list(self.tracker_boresight_body)}")

    def _check_bodies(self) -> None:
        """``targets`` and ``gravity`` as lower-case names, each once; without ``kernels`` each a body
        DE421 holds (a gravity body one with a GM there); with kernels they are checked against the
        kernels (:meth:`_check_coverage`)."""
        for key, known in (("targets", _ephemeris_bodies()), ("gravity", GRAVITY_BODIES)):
            names = tuple(str(name).strip().lower() for name in getattr(self, key))
            repeated = sorted({name for name in names if names.count(name) > 1})
            if repeated:
                raise InputError(f"{key} lists {', '.join(map(repr, repeated))} more than once; give each name once")
            unknown = [name for name in names if name not in known]
            if unknown and not self.kernels:
                close = difflib.get_close_matches(unknown[0], known, n=1)
                guess = f" (did you mean {close[0]!r}?)" if close else ""
                raise InputError(f"{key} must be names from {', '.join(known)} (or bodies of the kernels, when "
                                 f"kernels are given), got {unknown[0]!r}{guess}")
            object.__setattr__(self, key, names)

    def _check_starlight(self) -> None:
        """Starlight needs a body with a radius the filters know and at least one star, each a direction."""
        if bool(self.starlight_target) != bool(self.starlight_stars_radec_deg):
            raise InputError("starlight_target and starlight_stars_radec_deg go together (a body and its stars), got "
                             f"{self.starlight_target!r} and {len(self.starlight_stars_radec_deg)} star(s)")
        if not self.starlight_target:
            return
        key = self.starlight_target.strip().lower()
        if key not in RADIUS_KM or key not in _ephemeris_bodies():
            raise InputError(f"starlight_target must be one of {', '.join(RADIUS_KM)} (a body with a radius for "
                             f"the elevation), got {self.starlight_target!r}")
        object.__setattr__(self, "starlight_target", key)
        for ra, dec in self.starlight_stars_radec_deg:
            if not -90.0 <= dec <= 90.0:
                raise InputError(f"starlight_stars_radec_deg: declination {dec} of star [{ra}, {dec}] must be in "
                                 "[-90, 90] deg")

    def _check_shape(self) -> None:
        """The shaped target: one of ``targets``, its OBJ file found and read (one line naming the file and
        line otherwise), its reflectance and spin in range."""
        if not self.shape_target and not self.shape_file:
            return
        if not (self.shape_target and self.shape_file):
            raise InputError(f"shape_target and shape_file go together (a target and its OBJ), got "
                             f"{self.shape_target!r} and {self.shape_file!r}")
        key = self.shape_target.strip().lower()
        if key not in self.targets:
            raise InputError(f"shape_target {self.shape_target!r} must be one of targets ({', '.join(self.targets)})")
        object.__setattr__(self, "shape_target", key)
        object.__setattr__(self, "shape_file", _resolve_shape(self.shape_file))
        if not (np.isfinite(self.shape_scale_km) and self.shape_scale_km > 0.0):
            raise InputError(f"shape_scale_km must be positive, got {self.shape_scale_km!r}")
        if not 0.0 < self.shape_albedo <= 1.5:
            raise InputError(f"shape_albedo must be in (0, 1.5], got {self.shape_albedo!r}")
        if not 0.0 <= self.shape_lunar_lambert_l <= 1.0:
            raise InputError(f"shape_lunar_lambert_l must be in [0, 1], got {self.shape_lunar_lambert_l!r}")
        ra, dec = self.shape_pole_radec_deg
        if not (np.isfinite(ra) and -90.0 <= dec <= 90.0):
            raise InputError(f"shape_pole_radec_deg must be [ra, dec] with dec in [-90, 90] deg, got "
                             f"{list(self.shape_pole_radec_deg)}")
        if not (np.isfinite(self.shape_period_h) and self.shape_period_h >= 0.0 and np.isfinite(self.shape_prime_meridian_deg)):
            raise InputError(f"shape_period_h must be >= 0 h (0: no spin) and shape_prime_meridian_deg finite, got "
                             f"{self.shape_period_h!r} and {self.shape_prime_meridian_deg!r}")
        shape_body(self)  # the OBJ read now: a bad file is one line here, not in a worker

    # --- the truth's sources -------------------------------------------------------------------
    def _check_trajectory(self) -> None:
        """Each trajectory's own keys given, the others' left out; files resolved and hashed."""
        needs = {"oem": ("oem_file",), "spk": ("spk_body", "kernels")}
        for name in needs.get(self.trajectory, ()):
            if not getattr(self, name):
                raise InputError(f"trajectory = {self.trajectory!r} needs {name}")
        if self.trajectory != "oem" and self.oem_file:
            raise InputError(f"oem_file is read only with trajectory = 'oem' (trajectory is {self.trajectory!r})")
        if self.trajectory != "spk" and self.spk_body:
            raise InputError(f"spk_body is read only with trajectory = 'spk' (trajectory is {self.trajectory!r})")
        if self.oem_file:
            object.__setattr__(self, "oem_file", _resolve(self.oem_file, "oem_file"))
        if self.kernels:
            object.__setattr__(self, "kernels", tuple(_resolve(name, "kernels") for name in self.kernels))
        files = [name for name in (self.oem_file, *self.kernels, self.shape_file) if name]
        # a digest of the files' digests (streamed: a planetary SPK is 100 MB and more)
        digests = "".join(str(file_sha256(name)) for name in files)
        object.__setattr__(self, "inputs_sha256", hashlib.sha256(digests.encode()).hexdigest() if files else "")

    def _check_coverage(self) -> None:
        """Every epoch (``state_epoch`` too) inside DE421, the OEM and the kernels, and the bodies in
        the kernels: a one-line error now rather than in a worker later."""
        from ..ephemeris.planets import default_planets

        planets = default_planets()
        epochs = {name: _epoch(self, name) for name in ("start", "stop", "state_epoch")}
        if self.trajectory != "state":
            del epochs["state_epoch"]
        for name, t in epochs.items():
            if not planets.start_tdb_s <= t <= planets.end_tdb_s:
                raise InputError(f"{name} {getattr(self, name)} is outside DE421, which the filters read: "
                                 f"{describe_epoch(planets.start_tdb_s)} to {describe_epoch(planets.end_tdb_s)}")
        if self.trajectory == "oem":
            oem = _read_oem(self.oem_file)
            first, last = float(oem.t_tdb_s[0]), float(oem.t_tdb_s[-1])
            if epochs["start"] < first or epochs["stop"] > last:
                arc = f"{describe_epoch(epochs['start'])} to {describe_epoch(epochs['stop'])}"
                raise InputError(f"oem_file {self.oem_file} covers {describe_epoch(first)} to {describe_epoch(last)}; "
                                 f"the arc runs from {arc}")
            if str(oem.ref_frame).strip().upper() not in OEM_FRAMES:
                raise InputError(f"oem_file {self.oem_file}: REF_FRAME {oem.ref_frame!r} is not an inertial frame "
                                 f"opnav reads ({', '.join(OEM_FRAMES)})")
            _oem_origin(oem, self)
        if self.kernels:
            from ..ephemeris.spice import KernelError

            eph = truth_ephemeris(self)
            try:
                for body in (*self.targets, *self.gravity):
                    eph.check_body(body)
                for body in self.gravity:
                    gm_km3_s2(self, body)
                reach = _filter_reach(epochs["start"], epochs["stop"])
                for body in {*self.targets, *self.gravity}:
                    try:
                        eph.state(body, np.array(reach), center="ssb")
                    except KernelError as exc:
                        raise KernelError(f"{exc}; the filters read the kernels' bodies from "
                                          f"{describe_epoch(reach[0])} to {describe_epoch(reach[1])} (whole days of "
                                          "Chebyshev series with margins)") from None
                if self.trajectory == "spk":
                    eph.check_body(self.spk_body)
                    eph.state(self.spk_body, np.array([epochs["start"], epochs["stop"]]), center=self.center)
            except KernelError as exc:
                raise InputError(f"kernels: {exc}") from None

    def _check_attitude(self) -> None:
        """``attitude = "ck"``: its keys and kernels given, and the CK answering at every record epoch (one
        line naming the kernels, the frame and the first epoch it cannot orient, now rather than in a run)."""
        if self.attitude not in ATTITUDES:
            raise InputError(f"attitude must be one of {', '.join(ATTITUDES)}, got {self.attitude!r}")
        if not (np.isfinite(self.ck_tolerance_s) and self.ck_tolerance_s >= 0.0):
            raise InputError(f"ck_tolerance_s must be >= 0 s, got {self.ck_tolerance_s!r}")
        if self.attitude != "ck":
            for name, unset in (("ck_frame", ""), ("ck_tolerance_s", 0.0)):
                if getattr(self, name) != unset:
                    raise InputError(f"{name} is read only with attitude = 'ck' (attitude is {self.attitude!r})")
            return
        for name in ("ck_frame", "kernels"):
            if not getattr(self, name):
                raise InputError(f"attitude = 'ck' needs {name} (the CK, its SCLK and the FK among kernels; "
                                 "docs/formats/ck.md)")
        from .mission_images import ck_pointing

        ck_pointing(self, record_epochs(self)[1])


def _filter_reach(t_start: float, t_stop: float) -> tuple[float, float]:
    """First and last epoch (TDB s) the filters' cache of the kernels reads for an arc: whole days
    (:class:`opnav.ephemeris.cache.EphemerisCache` segments) over the arc, a day before ``t_start`` (the
    light time's reach) and the compiled tables' margin (:data:`opnav.ephemeris.tables.MARGIN_S`) each side."""
    from ..ephemeris.tables import MARGIN_S

    first = np.floor((t_start - DAY_S - MARGIN_S) / DAY_S) * DAY_S
    return float(first), float((np.floor((t_stop + MARGIN_S) / DAY_S) + 1.0) * DAY_S)


def _epoch(settings: Settings, name: str) -> float:
    """Setting ``name`` (a calendar date in ``epoch_scale``) as TDB s past J2000."""
    text = str(getattr(settings, name))
    try:
        return float(parse_epoch(text, scale=settings.epoch_scale))
    except InputError as exc:
        raise InputError(f"{name}: {exc}") from None


def _resolve(name: str, key: str) -> str:
    """``name`` as an absolute path (relative to the run file's folder, else the working directory),
    refused in one line unless it is a readable regular file."""
    path = Path(name).expanduser()
    if not path.is_absolute():
        path = (RUN_FILE_FOLDER.get() or Path.cwd()) / path
    if not path.is_file():
        raise InputError(f"{key}: {name!r} is not a file ({path})")
    return str(path)


def _resolve_shape(name: str) -> str:
    """``shape_file`` as an absolute path: ``"opnav:NAME"`` a shape shipped in ``opnav/data``, else :func:`_resolve`."""
    from ..shape import shipped_shape

    if name.startswith("opnav:"):
        path = shipped_shape(name[len("opnav:"):])
        if not path.is_file():
            raise InputError(f"shape_file: opnav ships no shape {name[len('opnav:'):]!r} (it has 'asteroid.obj')")
        return str(path)
    return _resolve(name, "shape_file")


def shape_body(settings: Settings):
    """The :class:`opnav.bodies.Body` of ``shape_target``: its mesh (:func:`opnav.shape.load_obj`, read once
    per file a process), reflectance and spin as the keys say; its ``radii_km`` the mesh's half extents."""
    from ..bodies import Body
    from ..shape import load_obj

    try:
        mesh = load_obj(settings.shape_file, scale_km=settings.shape_scale_km)
    except InputError as exc:
        raise InputError(f"shape_file: {exc}") from None
    ra, dec = np.radians(settings.shape_pole_radec_deg)
    rate = 2.0 * np.pi / (settings.shape_period_h * 3600.0) if settings.shape_period_h > 0.0 else 0.0
    return Body(settings.shape_target, mesh.half_extents_km(), settings.shape_albedo, shading=settings.shape_shading,
                pole_ra_rad=float(ra), pole_dec_rad=float(dec), shape=mesh,
                lunar_lambert_l=settings.shape_lunar_lambert_l, rotation_rate_rad_s=float(rate),
                prime_meridian_rad=float(np.radians(settings.shape_prime_meridian_deg)))


def _read_oem(path: str):
    from ..ccsds import read_oem

    return read_oem(path)


def truth_ephemeris(settings: Settings):
    """The truth's bodies: the ``kernels`` over the shipped DE421
    (:class:`opnav.ephemeris.spice.SpiceEphemeris`, one per set of files as they are on disk), or DE421."""
    if not settings.kernels:
        from ..ephemeris import default_ephemeris

        return default_ephemeris()
    from ..ephemeris.planets import default_kernel_path
    from ..sim.scene import kernel_ephemeris

    return kernel_ephemeris((str(default_kernel_path()), *settings.kernels))


def filter_ephemeris(settings: Settings):
    """What the filters read the bodies from (module notes): the Chebyshev cache of the truth's
    ``kernels`` (:class:`opnav.ephemeris.spice.KernelCache`, one per set of files as they are on disk),
    else None (opnav's DE421 through its process-wide cache)."""
    return _kernel_cache(truth_ephemeris(settings)) if settings.kernels else None


@functools.lru_cache(maxsize=8)
def _kernel_cache(truth):
    """One :class:`~opnav.ephemeris.spice.KernelCache` per truth ephemeris (itself one per set of files)."""
    from ..ephemeris.spice import KernelCache

    return KernelCache(truth)


def gm_km3_s2(settings: Settings, body: str) -> float:
    """``body``'s gravitational parameter, km^3/s^2: DE421's (:data:`opnav.constants.GM_KM3_S2`), else the
    kernels' (``BODYnnn_GM`` of a text PCK among ``kernels``)."""
    if body in GM_KM3_S2:
        return GM_KM3_S2[body]
    from ..ephemeris.spice import KernelError

    try:
        return truth_ephemeris(settings).gm_km3_s2(body)
    except KernelError as exc:
        raise InputError(f"gravity: {exc}") from None


def dynamics(settings: Settings, ephemeris=None):
    """The force model (module notes): point masses of ``gravity`` about ``center``, SRP when asked.

    ``ephemeris`` gives the third bodies' positions; default the filters' (:func:`filter_ephemeris`:
    a Chebyshev cache, which the compiled propagator reads), which the model also names as the one
    its filters measure the bodies in (:attr:`opnav.dynamics.ForceModel.ephemeris`).
    """
    from ..dynamics import CentralGravity, ForceModel, SolarRadiationPressure, ThirdBody
    from ..ephemeris.cache import default_cached_ephemeris

    filters = filter_ephemeris(settings)
    source = ephemeris if ephemeris is not None else filters if filters is not None else default_cached_ephemeris()
    others = [body for body in settings.gravity if body != settings.center]
    terms = [CentralGravity(GM_KM3_S2[settings.center]),
             *(ThirdBody(body, settings.center, gm_km3_s2(settings, body), source) for body in others)]
    name = f"mission: {settings.center}" + "".join(f" + {body}" for body in others)
    if settings.srp_area_to_mass_m2_kg > 0.0:
        shadows = tuple(body for body in settings.gravity if body in RADIUS_KM and body != "sun")
        terms.append(SolarRadiationPressure(settings.srp_area_to_mass_m2_kg, settings.srp_cr, settings.center,
                                            source, shadows))
        name += " + SRP"
    return ForceModel(settings.center, tuple(terms), name, ephemeris=filters)


def truth_states(settings: Settings, t_tdb_s: np.ndarray) -> np.ndarray:
    """The spacecraft's true states ``[r km, v km/s]`` (N, 6), ICRF, relative to ``center``, at
    ``t_tdb_s`` (TDB s past J2000), from ``trajectory`` (module notes)."""
    t = np.asarray(t_tdb_s, dtype=float)
    eph = truth_ephemeris(settings)
    if settings.trajectory == "state":
        from ..dynamics import states_at

        state0 = np.r_[settings.position_km, settings.velocity_km_s]
        model = dynamics(settings, eph if settings.kernels else None)
        return states_at(model, _epoch(settings, "state_epoch"), state0, t, ephemeris=eph)
    if settings.trajectory == "spk":
        from ..ephemeris.spice import KernelError

        try:
            r, v = eph.state(settings.spk_body, t, center=settings.center)
        except KernelError as exc:
            raise InputError(f"kernels: {exc}") from None
        return np.hstack([r, v])
    return _oem_states(settings, t, eph)


def _oem_states(settings: Settings, t: np.ndarray, eph) -> np.ndarray:
    """The OEM's arc at ``t``, interpolated as the OEM says, moved to ``center``."""
    from ..ephemeris.spice import SpiceEphemeris
    from ..ephemeris.spk_writer import write_oem_spk

    oem = _read_oem(settings.oem_file)
    with tempfile.TemporaryDirectory(prefix="opnav-oem-") as scratch:
        spk = write_oem_spk(Path(scratch) / "oem.bsp", oem, body=_OEM_BODY)
        arc = SpiceEphemeris([spk])
        # the SPK holds the arc relative to the OEM's own centre; asked there, no other body is needed
        r, v = arc.state(_OEM_BODY, t, center=arc.naif_id(oem.center))
    origin = _oem_origin(oem, settings)
    if origin is None:
        return np.hstack([r, v])
    r_c, v_c = eph.state(origin, t, center=settings.center)
    return np.hstack([r + r_c, v + v_c])


def _oem_origin(oem, settings: Settings) -> str | int | None:
    """The OEM's ``CENTER_NAME`` as a body the truth's ephemeris holds (None: ``center`` itself), or one
    line naming the file."""
    from ..ephemeris.moons import MOON_NAIF_ID
    from ..ephemeris.planets import NAIF_ID
    from ..ephemeris.spice import naif_code

    try:
        naif = naif_code(oem.center)
    except OpnavError as exc:
        raise InputError(f"oem_file {settings.oem_file}: CENTER_NAME {oem.center!r}: {exc}") from None
    if naif == naif_code(settings.center):
        return None
    if settings.kernels:
        try:
            truth_ephemeris(settings).check_body(naif)
            return naif
        except OpnavError:
            pass
    else:
        names = {code: name for name, code in {**NAIF_ID, **MOON_NAIF_ID}.items()}
        if naif in names:
            return names[naif]
    raise InputError(f"oem_file {settings.oem_file}: CENTER_NAME {oem.center!r} (NAIF {naif}) is not a body of "
                     f"{'the kernels' if settings.kernels else 'DE421'}, so its states cannot be moved to "
                     f"center {settings.center!r}")


def record_epochs(settings: Settings) -> tuple[float, np.ndarray]:
    """``(start, record epochs)``, TDB s past J2000: every ``step_s`` after ``start`` up to ``stop``."""
    t_start, t_stop = _epoch(settings, "start"), _epoch(settings, "stop")
    count = int(np.floor((t_stop - t_start) / settings.step_s + 1e-9))
    return t_start, t_start + settings.step_s * np.arange(1, count + 1)


def target_exposure_s(settings: Settings) -> dict[str, float]:
    """Each target's exposure of the navigation camera (image mode), s."""
    exposure = np.broadcast_to(np.atleast_1d(np.asarray(settings.camera_exposure_s, dtype=float)),
                               (len(settings.targets),))
    return {target: float(value) for target, value in zip(settings.targets, exposure)}


#: Visible-light models of targets :data:`opnav.bodies.BODIES` has none for (the Moon) or only another
#: band's (the Earth's there is S3's UV limb): spheres of the IAU mean radius
#: (:data:`opnav.constants.RADIUS_KM`) with V-band geometric albedos (Moon 0.12, Earth 0.367: Cox,
#: Allen's Astrophysical Quantities, 4th ed., table 12.2), Lommel-Seeliger for the regolith, Lambert for
#: the Earth's clouds and oceans, poles from the IAU WGCCRE 2015 report.
VISIBLE_BODIES = {
    "moon": dict(geometric_albedo=0.12, shading="lommel-seeliger", pole_ra_rad=np.radians(269.9949),
                 pole_dec_rad=np.radians(66.5392)),
    "earth": dict(geometric_albedo=0.367, shading="lambert", pole_ra_rad=0.0, pole_dec_rad=np.radians(90.0)),
}


def mission_bodies(settings: Settings) -> dict:
    """Each target's :class:`opnav.bodies.Body` (what image mode renders and its centre finder assumes):
    ``shape_target``'s mesh (:func:`shape_body`), :data:`VISIBLE_BODIES` for the Moon and the Earth, else
    :func:`opnav.bodies.body_model` (Mars, Phobos, Deimos); ``InputError`` naming a target with none."""
    from ..bodies import Body, body_model

    models = {}
    for target in settings.targets:
        if target == settings.shape_target:  # a mesh of its own (shape_file): drawn and measured on its triangles
            models[target] = shape_body(settings)
            continue
        if target in VISIBLE_BODIES:
            models[target] = Body(target, (RADIUS_KM[target],) * 3, **VISIBLE_BODIES[target])
            continue
        try:
            models[target] = body_model(target)
        except InputError:
            raise InputError(f"targets: image mode has no shape or reflectance for {target!r} (it has the Moon, the "
                             "Earth, opnav.bodies' bodies and a shape_target's mesh); give it shape_target and "
                             "shape_file, or measure it in measurement mode") from None
    return models


def target_noise_arcsec(settings: Settings) -> dict[str, float]:
    """Each target's 1-sigma on RA and on Dec, arcsec."""
    noise = np.broadcast_to(np.atleast_1d(np.asarray(settings.noise_arcsec, dtype=float)), (len(settings.targets),))
    return {target: float(value) for target, value in zip(settings.targets, noise)}


def simulate(settings: Settings, seed: int) -> Simulation:
    """Truth, records and filter start of one mission run (module notes)."""
    from ..measurements import ProbeMeasurementModel, simulate_radec

    rng = np.random.default_rng([seed, 1])
    t_start, epochs = record_epochs(settings)
    truth = truth_states(settings, np.concatenate([[t_start], epochs]))
    exact = ProbeMeasurementModel(settings.center, ephemeris=truth_ephemeris(settings))
    noise = target_noise_arcsec(settings)
    records, ranges = [], {}
    for target in settings.targets:
        sigma = noise[target] * ARCSEC_RAD
        offset = (rng.normal(0.0, settings.target_ephemeris_sigma_km, (epochs.size, 3))
                  if settings.target_ephemeris_sigma_km > 0.0 else None)
        values = simulate_radec(exact, target, epochs, truth[1:], sigma_rad=sigma, rng=rng, target_offset_km=offset)
        records += [Measurement(t, "radec", v, sigma**2 * np.eye(2), target=target, sensor="navcam")
                    for t, v in zip(epochs, values)]
        r_target = exact.ephemeris.position(target, epochs, center=settings.center)
        distance = np.linalg.norm(r_target - truth[1:, :3], axis=1)
        ranges[target] = {"min_km": float(distance.min()), "max_km": float(distance.max())}
    starlight = _starlight_records(settings, exact, epochs, truth[1:], rng) if settings.starlight_target else None
    if starlight is not None:
        records += starlight[0]
    records.sort(key=lambda r: r.t_tdb_s)  # stable: the targets of an epoch in the order listed, then the stars
    sig_r, sig_v = settings.sigma_position_km, 1e-3 * settings.sigma_velocity_m_s
    P0 = np.diag([sig_r**2] * 3 + [sig_v**2] * 3)
    x0 = truth[0] + np.sqrt(np.diag(P0)) * rng.standard_normal(6)
    q = settings.process_noise_km2_s3
    nav = NavigationConfig(t0_tdb_s=t_start, dynamics="mission", x0=x0, P0=P0,
                           target_position_sigma_km=settings.target_ephemeris_sigma_km, seed=seed,
                           process_noise={"model": "white", "q_km2_s3": q} if q > 0 else {"model": "none"})
    window = t_start + 0.5 * (epochs[-1] - t_start)
    model = dynamics(settings)
    facts = {"window": "last half of the arc", "trajectory": settings.trajectory, "force_model": model.name,
             "truth_bodies": "kernels over DE421" if settings.kernels else "DE421",
             "filter_bodies": "kernels over DE421 (Chebyshev cache)" if settings.kernels else "DE421",
             "noise_arcsec": noise, "target_range_km": ranges, "arc_days": float((epochs[-1] - t_start) / DAY_S)}
    if starlight is not None:
        facts["starlight_records_left_out"] = starlight[1]
    return Simulation(settings.center, epochs, truth[1:], records, nav, model, float(window), {}, facts,
                      start_truth=truth[0])


#: A star within this of the starlight body's limb or of the angle's other pole (180 deg) gives no
#: record: behind the body or at the limb it is not seen, and at the poles the angle's derivative
#: (1 / sin of the angle) blows up.
STARLIGHT_CLEARANCE_RAD = np.radians(1.0)


def _starlight_records(settings: Settings, model, epochs: np.ndarray, truth: np.ndarray,
                       rng: np.random.Generator) -> tuple[list[Measurement], dict[str, int]]:
    """``starlight`` records of every star of ``starlight_stars_radec_deg`` against ``starlight_target``
    (:func:`opnav.measurements.simulate_starlight`), and per star the epochs left out (:data:`STARLIGHT_CLEARANCE_RAD`)."""
    from ..frames import angle_between, radec_to_unit
    from ..measurements import simulate_starlight

    target = settings.starlight_target
    sigma_star = settings.starlight_star_sigma_arcsec * ARCSEC_RAD
    sigma_target = settings.starlight_target_sigma_arcsec * ARCSEC_RAD
    rho = model.ephemeris.position(target, epochs, center=settings.center) - truth[:, :3]
    distance = np.linalg.norm(rho, axis=1)
    if np.any(distance <= RADIUS_KM[target]):
        inside = describe_epoch(epochs[np.argmin(distance)])
        raise InputError(f"starlight_target {target}: the spacecraft is inside it at {inside}")
    limb = np.arcsin(RADIUS_KM[target] / distance)
    records, left_out = [], {}
    for ra, dec in settings.starlight_stars_radec_deg:
        star = radec_to_unit(np.radians(ra), np.radians(dec))
        theta = angle_between(np.broadcast_to(star, rho.shape), rho)
        seen = (theta > limb + STARLIGHT_CLEARANCE_RAD) & (theta < np.pi - STARLIGHT_CLEARANCE_RAD)
        left_out[f"[{ra:g}, {dec:g}]"] = int(np.count_nonzero(~seen))
        if np.any(seen):
            records += simulate_starlight(model, target, epochs[seen], truth[seen], star, sigma_star_rad=sigma_star,
                                          sigma_target_rad=sigma_target, rng=rng, sensor="navcam")
    return records, left_out


def simulate_images(settings: Settings, seed: int, out, *, progress: bool = False, workers: int = 1,
                    faults=None) -> Simulation:
    """A mission from pixels (:mod:`opnav.studies.mission_images`): the truth, epochs and filter start of
    :func:`simulate`, the targets' RA/Dec records measured on rendered frames with the covariances the
    image stage gives.

    ``facts`` gains ``images``: per target the records checked against the truth (wrong-body records,
    gross errors, achieved noise, median reported sigma, chi-square per axis:
    :func:`~opnav.studies.mission_images.check_records`), the epochs a target was not imaged, the frames
    the stage skipped and why, the trackers' acquisitions and losses of lock, their guide stars
    checked against the truth, and the navigation camera's exposures per target (shortest, longest,
    settings used: :mod:`opnav.studies.mission_exposure`).
    """
    from dataclasses import asdict, replace

    from .. import __version__
    from ..measurements import ProbeMeasurementModel
    from .common import tracking_facts
    from .mission_images import check_records, measure
    from .runner import digest

    if faults is not None and faults.on_frames:
        raise InputError(f"frame faults {sorted(faults.on_frames)} are not available for the mission's image mode")
    if settings.starlight_target:
        raise InputError("starlight_target: starlight records are measurement mode's; image mode measures the "
                         "targets' centres (leave starlight_target out, or run --mode measurements)")
    if settings.target_ephemeris_sigma_km > 0.0:
        raise InputError("target_ephemeris_sigma_km is measurement mode's; image mode draws the targets at the "
                         "ephemeris (set it to 0, or run --mode measurements)")
    sim = simulate(settings, seed)
    eph = truth_ephemeris(settings)
    r_c, v_c = eph.state(settings.center, sim.epochs, center="ssb")
    key = digest({"settings": asdict(settings), "seed": seed, "opnav": __version__, "stage": "mission-images"})
    measured = measure(settings, seed, sim.epochs, sim.truth[:, :3] + r_c, sim.truth[:, 3:] + v_c, Path(out),
                       key=key, progress=progress, workers=workers)
    if not measured.records:
        reasons = [*measured.not_imaged.values(), *(r for loop in measured.loops.values() for r in loop.skipped.values())]
        raise InputError(f"{out}: no target measured in {sim.epochs.size} epochs (first reasons: {reasons[:3]})")
    model = ProbeMeasurementModel(settings.center, ephemeris=eph)
    checks = check_records(measured.records, sim.epochs, sim.truth, model, settings.targets)
    loops = measured.loops.values()
    images = {
        "records": checks,
        "wrong_body": sum(entry["wrong_body"] for entry in checks.values()),
        "gross_errors": sum(entry["gross_errors"] for entry in checks.values()),
        "not_imaged": len(measured.not_imaged), "not_imaged_first": dict(list(measured.not_imaged.items())[:5]),
        "frames_skipped": sum(len(loop.skipped) for loop in loops),
        "frames_skipped_first": {k: v for loop in loops for k, v in list(loop.skipped.items())[:3]},
        "frames_full": sum(loop.frames_full for loop in loops),
        "frames_windowed": sum(loop.frames_windowed for loop in loops),
        "chunks_reused": sum(loop.chunks_reused for loop in loops),
        "tracking": {target: tracking_facts(list(loop.events)) for target, loop in measured.loops.items()},
        "tracked_stars": {"used": sum(loop.stars_used for loop in loops),
                          "misidentified": sum(loop.stars_misidentified for loop in loops)},
        "attitude": settings.attitude,
        "exposure_law": settings.camera_exposure_law,
        "exposures_s": {target: {"shortest": float(e.min()), "longest": float(e.max()),
                                 "settings_used": int(np.unique(e).size)}
                        for target, e in measured.exposures.items()},
    }
    facts = {key: value for key, value in sim.facts.items() if key != "noise_arcsec"}
    facts["images"] = images
    return replace(sim, records=list(measured.records), facts=facts)
