"""Image files to lost-in-space plate solutions, one after another in a process (``opnav solve FRAMES...``).

For each frame (:meth:`PlateSolver.solve_file`):

1. The pixels (:func:`opnav.image.io.read_image`) and, from a FITS header (:mod:`opnav.image.header`,
   the one place that reads it), the mid-exposure epoch, the observer's position and velocity
   (``OBS_X`` ... ``OBS_VZ``) and the celestial TAN WCS. Options given to the solver (a date, a
   velocity) take precedence over the header's.
2. The field-of-view guess (``hint``): the one given (``"fov"``), else the WCS's (``"wcs"``: its
   pixel scale gives the field of view, and the index is the one of that field of view snapped to
   a grid, :func:`opnav.image.starid_index.snap_fov_deg`, so the frames of a camera share it; its
   pointing is not used to search, only compared with the answer, ``hint_offset_rad``), else none (``"none"``: the default range, then the narrow
   indexes already cached). :func:`opnav.image.starid_index.choose_indexes` names the indexes.
3. Each index is loaded once per solver (memory-mapped) and moved to the frame's epoch
   (:meth:`opnav.image.starid_index.PatternIndex.at_epoch`); the frame is extracted and solved in
   each index in turn until one gives a verified solution
   (:func:`opnav.image.starid.solve_with_deeper_extraction`): ``method = "lost_in_space"``.
4. A frame with a WCS that no index solves (lost in space needs a star beyond the 4 of a
   pattern: a sparse frame may have none) is tracked from the WCS pointing
   (:func:`opnav.image.starid.track`, prior ``WCS_PRIOR_SIGMA_FRACTION`` of the field of view a
   side, stars at the catalog epoch): ``method = "tracking"``. Its false-match test counts the
   chance hypotheses within that gate; a WCS farther off than the gate gives no solution.

A header keyword that cannot be read for the epoch, velocity or WCS is logged as a warning and
left out (the frame is still solved, with the catalog's epoch or without the hint). A header with
the detector's noise model (``RDNOISE`` e-, ``GAIN`` e-/ADU and ``BIASLVL`` ADU, all three, as
opnav's rendered frames carry) has its stars centroided with it (:func:`opnav.image.extract.extract_stars`);
otherwise, or when one of them is not a usable number (a warning), the noise is fitted from the frame.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace

import numpy as np

from ..camera import Camera
from ..errors import CatalogError, FrameError, InputError, NoSolutionError
from .header import WcsHint, has_epoch, header_epoch, header_vector, wcs_hint
from .io import read_image
from .sources import header_number
from .starid import PlateSolution, solve_stars, solve_with_deeper_extraction
from .starid_index import MIN_INDEX_FOV_DEG, IndexChoice, PatternIndex, choose_indexes, snap_fov_deg

log = logging.getLogger(__name__)

HINTS = ("fov", "wcs", "none")
#: Per-axis 1-sigma error of a WCS attitude when a frame is tracked from it, as a fraction of the
#: horizontal field of view (the gate, 4.3 sigma, then reaches a fifth of the field).
WCS_PRIOR_SIGMA_FRACTION = 0.05


class NoPlateSolution(NoSolutionError):
    """No index gave a verified solution for a frame; ``searched`` holds the FOV ranges searched
    ((low, high) deg) and ``hint`` how the FOV was guessed (``HINTS``)."""

    def __init__(self, message: str, searched: tuple, hint: str) -> None:
        super().__init__(message)
        self.searched = searched
        self.hint = hint


@dataclass(frozen=True)
class SolveOptions:
    """What :class:`PlateSolver` is told beyond the frames.

    Attributes
    ----------
    fov_deg : float, optional
        Horizontal field-of-view guess, deg, for every frame (default: each frame's WCS, else a search).
    fov_tolerance : float
        Relative uncertainty of the guess (0.1 = +-10 %).
    bayer : str, optional
        The files are raw Bayer mosaics of this pattern (:data:`opnav.image.io.BAYER_PATTERNS`).
    epoch_tdb_s : float, optional
        Date of every frame, TDB s past J2000 (default: each FITS header's).
    velocity_km_s : ndarray, shape (3,), optional
        Observer velocity relative to the solar-system barycentre, ICRF, km/s (default: each FITS
        header's ``OBS_VX/VY/VZ``); with it the pointing reported is the apparent one.
    use_wcs : bool
        Read a frame's WCS: the field-of-view guess when ``fov_deg`` is not given, the pointing a frame
        no index solves is tracked from (module docstring); False ignores it.
    camera : Camera, optional
        The frames' camera (a camera file, e.g. from ``opnav calibrate``): its focal length (within
        ``fov_tolerance``), principal point and distortion turn the stars' pixels into bearings, and
        its field of view is the guess (instead of ``fov_deg``, the WCS's or a search).
    """

    fov_deg: float | None = None
    fov_tolerance: float = 0.1
    bayer: str | None = None
    epoch_tdb_s: float | None = None
    velocity_km_s: np.ndarray | None = None
    use_wcs: bool = True
    camera: Camera | None = None

    def __post_init__(self) -> None:
        if self.fov_deg is not None and not (MIN_INDEX_FOV_DEG <= self.fov_deg < 120.0):
            raise InputError(f"fov_deg (--fov) must be in [{MIN_INDEX_FOV_DEG:g}, 120) deg (a narrower field's pattern "
                             f"index would take gigabytes), got {self.fov_deg}")
        if not (0.0 < self.fov_tolerance <= 0.5):
            raise InputError(f"fov_tolerance (--fov-tolerance) must be in (0, 0.5], got {self.fov_tolerance}")
        if self.epoch_tdb_s is not None and not math.isfinite(self.epoch_tdb_s):
            raise InputError(f"epoch_tdb_s (--epoch) must be finite, got {self.epoch_tdb_s}")
        if self.velocity_km_s is not None:
            velocity = np.asarray(self.velocity_km_s, dtype=float)
            if velocity.shape != (3,) or not np.all(np.isfinite(velocity)) or np.linalg.norm(velocity) >= 299792.458:
                raise InputError(f"velocity_km_s (--velocity) must be finite and below the speed of light, got {self.velocity_km_s}")
            object.__setattr__(self, "velocity_km_s", velocity)


@dataclass(frozen=True)
class FrameSolution:
    """A solved frame (:meth:`PlateSolver.solve_file`).

    Attributes
    ----------
    path : str
    solution : PlateSolution
        Geometric attitude, fitted camera, stars and times.
    v_observer_km_s : ndarray or None
        Observer velocity (ICRF, km/s) the apparent pointing uses; None: geometric pointing.
    epoch_tdb_s : float or None
        Date the catalog stars were moved to, TDB s past J2000; None: the catalog's epoch.
    hint : str
        How the field of view was guessed: ``"fov"``, ``"wcs"`` or ``"none"``.
    wcs : WcsHint or None
        The frame's WCS, when it has one.
    searched : tuple of (float, float)
        Horizontal FOV ranges searched, deg.
    total_s : float
        Wall-clock time of the frame, s (the first frame's includes loading the indexes).
    method : str
        ``"lost_in_space"`` (a pattern index), or ``"tracking"`` from the WCS pointing (module step 4).
    """

    path: str
    solution: PlateSolution
    v_observer_km_s: np.ndarray | None
    epoch_tdb_s: float | None
    hint: str
    wcs: WcsHint | None
    searched: tuple
    total_s: float
    method: str = "lost_in_space"

    @property
    def pointing(self) -> str:
        """``"apparent"`` with an observer velocity, else ``"geometric"`` (:class:`PlateSolution`)."""
        return "geometric" if self.v_observer_km_s is None else "apparent"

    def attitude(self):
        """Camera -> ICRF attitude, apparent with the observer velocity (:meth:`PlateSolution.attitude`)."""
        return self.solution.attitude(self.v_observer_km_s)

    def center_icrf(self) -> np.ndarray:
        """ICRF unit direction of the image centre (the pointing reported)."""
        camera = self.solution.camera
        return self.attitude().apply(camera.unproject(np.array([(camera.width_px - 1) / 2.0,
                                                                 (camera.height_px - 1) / 2.0])))

    def hint_offset_rad(self) -> float | None:
        """Angle between the solved image centre and the WCS's, rad; None without a WCS."""
        if self.wcs is None:
            return None
        return float(np.arccos(np.clip(self.center_icrf() @ self.wcs.center_icrf(), -1.0, 1.0)))


class PlateSolver:
    """Solves frames one after another, each index loaded once (module docstring).

    Parameters
    ----------
    catalog : opnav.catalog.StarCatalog
        The star catalog the indexes are built from.
    options : SolveOptions
    cache_dir : str or Path, optional
        Pattern-index cache (default ``$OPNAV_CACHE`` or ``~/.cache/opnav``).
    progress : callable, optional
        ``progress(stage, done, total)`` while an index is built.
    """

    def __init__(self, catalog, options: SolveOptions = SolveOptions(), *, cache_dir=None, progress=None) -> None:
        self.catalog = catalog
        self.options = options
        self.cache_dir = cache_dir
        self.progress = progress
        self._indexes: dict[IndexChoice, PatternIndex | CatalogError] = {}
        self._choices: dict[float | None, tuple[IndexChoice, ...]] = {}

    def _index(self, choice: IndexChoice) -> PatternIndex:
        if choice not in self._indexes:
            try:
                self._indexes[choice] = choice.load(self.catalog, self.cache_dir, self.progress)
            except CatalogError as exc:
                self._indexes[choice] = exc
        found = self._indexes[choice]
        if isinstance(found, CatalogError):
            raise found
        return found

    def _choose(self, fov_deg: float | None) -> tuple[IndexChoice, ...]:
        if fov_deg not in self._choices:
            self._choices[fov_deg] = choose_indexes(self.catalog, fov_deg=fov_deg,
                                                    fov_tolerance=self.options.fov_tolerance, cache_dir=self.cache_dir)
        return self._choices[fov_deg]

    def _header_hints(self, path: str, header, shape) -> tuple[float | None, np.ndarray | None, np.ndarray | None,
                                                                WcsHint | None]:
        """``(epoch, position, velocity, wcs)`` from the options and the header (warnings for unreadable keywords)."""
        options = self.options

        def lenient(read):
            try:
                return read()
            except FrameError as exc:
                log.warning("%s; left out", exc)
                return None

        epoch = options.epoch_tdb_s
        if epoch is None and has_epoch(header):
            epoch = lenient(lambda: header_epoch(header, path))
        velocity = options.velocity_km_s
        if velocity is None:
            velocity = lenient(lambda: header_vector(header, ("OBS_VX", "OBS_VY", "OBS_VZ"), path))
            if velocity is not None and np.linalg.norm(velocity) >= 299792.458:
                log.warning("%s: OBS_VX/VY/VZ is not below the speed of light; left out", path)
                velocity = None
        position = None
        if epoch is not None:
            position = lenient(lambda: header_vector(header, ("OBS_X", "OBS_Y", "OBS_Z"), path))
        wcs = lenient(lambda: wcs_hint(header, shape, path)) if header is not None and options.use_wcs else None
        return epoch, position, velocity, wcs

    def solve_file(self, path) -> FrameSolution:
        """Solve one image file (module docstring).

        Raises
        ------
        FrameError, InputError
            The file cannot be read or used (:func:`opnav.image.io.read_image`, detection).
        NoPlateSolution
            No index gave a verified solution (or none could be loaded).
        """
        started = time.perf_counter()
        path = str(path)
        options = self.options
        image, meta = read_image(path, bayer=options.bayer)
        epoch, position, velocity, wcs = self._header_hints(path, meta.header, image.shape)
        if options.camera is not None:
            camera_fov_deg = math.degrees(options.camera.fov_x_rad)
            fov_deg, index_fov_deg, hint = camera_fov_deg, camera_fov_deg, "fov"
        elif options.fov_deg is not None:
            fov_deg, index_fov_deg, hint = options.fov_deg, options.fov_deg, "fov"
        elif options.use_wcs and wcs is not None and wcs.fov_deg >= MIN_INDEX_FOV_DEG:
            fov_deg, index_fov_deg, hint = wcs.fov_deg, snap_fov_deg(wcs.fov_deg), "wcs"
        elif options.use_wcs and wcs is not None:
            # a field narrower than any index (or a WCS that says so): searched as without a guess, and a
            # frame no index solves is still tracked from the WCS pointing
            log.warning("%s: the WCS gives a %.3g deg field of view, narrower than the %g deg opnav indexes; "
                        "its field of view left out", path, wcs.fov_deg, MIN_INDEX_FOV_DEG)
            fov_deg, index_fov_deg, hint = None, None, "none"
        else:
            fov_deg, index_fov_deg, hint = None, None, "none"
        choices = self._choose(index_fov_deg)
        searched: list[tuple[float, float]] = []
        failures: list[str] = []
        moved: dict[int, PatternIndex | None] = {}

        def solve_in_each_index(xy: np.ndarray, cov: np.ndarray) -> PlateSolution:
            for k, choice in enumerate(choices):
                low, high = choice.fov_low_deg, choice.fov_high_deg
                if fov_deg is not None:
                    low, high = fov_deg * (1.0 - options.fov_tolerance), fov_deg * (1.0 + options.fov_tolerance)
                if k not in moved:
                    moved[k] = None
                    try:
                        index = self._index(choice)
                    except CatalogError as exc:
                        failures.append(f"{low:.4g}-{high:.4g} deg: {exc}")
                        continue
                    searched.append((low, high))
                    if epoch is not None:
                        index = index.at_epoch(self.catalog, t_tdb_s=float(epoch), r_observer_ssb_km=position)
                    moved[k] = index
                if moved[k] is None:
                    continue
                try:
                    if options.camera is not None:  # its distortion and principal point, its focal length the guess
                        return solve_stars(xy, cov, image.shape, index=moved[k], camera=options.camera,
                                           fov_tolerance=options.fov_tolerance)
                    if fov_deg is not None:
                        return solve_stars(xy, cov, image.shape, index=moved[k], fov_deg=fov_deg,
                                           fov_tolerance=options.fov_tolerance)
                    return solve_stars(xy, cov, image.shape, index=moved[k], fov_range_deg=(low, high),
                                       fov_tolerance=options.fov_tolerance)
                except NoSolutionError as exc:
                    failures.append(f"{low:.4g}-{high:.4g} deg: {exc}")
            raise NoSolutionError(failures[-1] if failures else "no pattern index could be loaded")

        extracted: dict[str, np.ndarray] = {}
        searching_s = [0.0]

        def remember(xy: np.ndarray, cov: np.ndarray) -> PlateSolution:
            extracted["xy"], extracted["cov"] = xy, cov
            search_started = time.perf_counter()
            try:
                return solve_in_each_index(xy, cov)
            finally:
                searching_s[0] += time.perf_counter() - search_started

        method = "lost_in_space"
        lost_started = time.perf_counter()
        try:
            solution = solve_with_deeper_extraction(image, remember, saturation_adu=meta.saturation_adu,
                                                    invalid=meta.invalid, lossy=meta.lossy,
                                                    noise=_header_noise(meta.header, path))
            # the solve time is the whole search: loading the indexes and moving their stars to the
            # frame's epoch included, not the pattern search alone
            solution = replace(solution, solve_s=searching_s[0])
        except NoSolutionError as exc:
            ranges = ", ".join(f"{low:.4g}-{high:.4g}" for low, high in searched)
            why = f"searched horizontal FOV {ranges} deg; {exc}"
            if wcs is None or "xy" not in extracted:
                raise NoPlateSolution(why, tuple(searched), hint) from None
            try:
                solution = self._track(extracted["xy"], extracted["cov"], wcs, choices,
                                       time.perf_counter() - lost_started - searching_s[0], searching_s[0])
            except (NoSolutionError, CatalogError) as tracked:
                raise NoPlateSolution(f"{why}; tracked from the WCS pointing: {tracked}", tuple(searched), hint) from None
            method = "tracking"
        return FrameSolution(path, solution, velocity, epoch, hint, wcs, tuple(searched), time.perf_counter() - started,
                             method)

    def _track(self, xy: np.ndarray, cov: np.ndarray, wcs: WcsHint, choices: tuple[IndexChoice, ...],
               extract_s: float, searched_s: float) -> PlateSolution:
        """Module step 4: the stars ``xy`` tracked from the WCS attitude, as a :class:`PlateSolution` (its
        ``solve_s`` holds the lost-in-space search that failed and the tracking)."""
        from .starid import CatalogTree, bearings, track

        started = time.perf_counter()
        camera = wcs.camera if self.options.camera is None else self.options.camera
        vmag_limit = dict(choices[0].options).get("vmag_limit") if choices else None
        if len(xy) < 3:  # as track() needs; the median of no source's noise was NaN
            raise NoSolutionError(f"tracking needs at least 3 stars, {len(xy)} extracted")
        sigma_px = float(np.median(np.sqrt(0.5 * np.trace(cov, axis1=1, axis2=2))))
        ident = track(bearings(xy, camera), CatalogTree.from_catalog(self.catalog, vmag_limit=vmag_limit),
                      wcs.R_icrf_cam, camera, prior_sigma_rad=WCS_PRIOR_SIGMA_FRACTION * camera.fov_x_rad,
                      sigma_rad=sigma_px * camera.pixel_scale_rad, rng=0)
        return PlateSolution(ident, camera, xy, extract_s, searched_s + time.perf_counter() - started)


def _header_noise(header, path: str) -> dict | None:
    """The detector's noise model of a FITS header as keyword arguments of
    :func:`opnav.image.extract.extract_stars` (``RDNOISE``, ``GAIN``, ``BIASLVL``), or None when one of
    them is absent or unusable (a warning names it): the noise is then fitted from the frame."""
    if header is None or not all(key in header for key in ("RDNOISE", "GAIN", "BIASLVL")):
        return None
    try:
        read_noise, gain, bias = (header_number(header, key, path) for key in ("RDNOISE", "GAIN", "BIASLVL"))
    except InputError as exc:
        log.warning("%s; the noise model fitted from the frame instead", exc)
        return None
    if read_noise < 0 or gain <= 0:
        log.warning("%s: RDNOISE %r and GAIN %r are not a noise model (RDNOISE >= 0, GAIN > 0); the noise model "
                    "fitted from the frame instead", path, read_noise, gain)
        return None
    return {"read_noise_e": read_noise, "gain_e_per_adu": gain, "bias_adu": bias}
