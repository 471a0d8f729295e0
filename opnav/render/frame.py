"""Render one frame (full or windowed) in memory: scene -> electrons -> ADU + truth + header.

Steps:

1. Sun keep-out: if the Sun's apparent direction is within the camera's
   half-diagonal field plus ``sun_keepout_margin_rad`` of the boresight, nothing
   is drawn, the frame carries the flag ``"sun_keepout"`` (header ``OPNVFLAG``,
   truth ``flags``) and holds only the detector's dark/bias/noise; with
   ``sun_policy="raise"`` a ``FrameError`` is raised instead.
2. Stars (:mod:`opnav.render.scene`): magnitude -> electrons
   (:mod:`opnav.photometry`), one PSF stamp each (:mod:`opnav.render.psf`).
3. Targets (:mod:`opnav.bodies`): an unresolved body (largest angular
   diameter below one pixel) is one PSF stamp at its photocentre; one under :data:`SMALL_BODY_PX`
   across a PSF stamp per ray of its view (each at its own place); a larger sunlit one is its
   light integrated over each pixel on rays aligned with the pixels
   (:func:`opnav.bodies.body_pixels`), a UV limb its per-pixel samples, convolved with the PSF.
4. Smear: with a camera body rate ``omega_cam_rad_s`` every source is drawn
   along its path over the exposure (the truth position is mid-exposure).
5. Detector read-out (:mod:`opnav.render.detector`), header and truth
   (:mod:`opnav.render.frames_io`, :mod:`opnav.render.truth`).

The windowed variant renders only regions of interest around the predicted
stars and targets, and reads out only those pixels, for long sequences.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from astropy.io import fits
from scipy.signal import fftconvolve
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..compiled import kernel
from ..errors import FrameError, InputError
from ..frames import angle_between
from ..bodies import Body, BodyView, body_model, body_pixels, view_body
from .detector import DetectorOptions, WindowLayout, read_out, read_out_windows
from .frames_io import Window, frame_header
from ..photometry import electron_rate
from .psf import PSF, Stamps, add_stamps, render_stamps
from ..observer import Corrections, Observer
from .scene import StarSource, boresight_icrf, smear_path_px, stars_in_view, sun_direction
from .truth import FrameTruth, StarTruth, TargetTruth

SUN_POLICIES = ("flag", "raise")
#: A resolved body under this many pixels across is drawn ray by ray (each ray's light a PSF stamp at its own
#: place); larger ones as their pixels' integrated light convolved with the PSF (:func:`_body_patch`), whose
#: placement of each pixel's light at the pixel's centre costs under ~0.01 px of the photocentre from 3 px up.
SMALL_BODY_PX = 3.0


@dataclass(frozen=True)
class RenderOptions:
    """How to render a frame.

    Parameters
    ----------
    psf : PSF
    detector : DetectorOptions
    corrections : Corrections
        Light time, aberration, parallax, proper motion switches.
    vmag_limit : float or None
        Faintest star drawn (None: every star the catalog returns).
    sun_keepout_margin_rad : float
        Keep-out cone half-angle beyond the camera's half-diagonal field, rad.
    sun_policy : {"flag", "raise"}
        What to do when the Sun is inside the keep-out cone.
    supersample : int
        Rays per pixel per axis for resolved bodies where their shading is smooth (the pixels a
        sunlit body's limb or terminator crosses get :data:`opnav.bodies.EDGE_SUPERSAMPLE`).
    smear_steps : int
        Attitude samples across the exposure when the camera turns.
    stray_light_e : float
        Scattered light from outside the field: a ramp across the detector's columns from 0 at
        the first to this many electrons per pixel per exposure at the last (0: none).
    """

    psf: PSF = field(default_factory=PSF)
    detector: DetectorOptions = field(default_factory=DetectorOptions)
    corrections: Corrections = field(default_factory=Corrections)
    vmag_limit: float | None = None
    sun_keepout_margin_rad: float = math.radians(10.0)
    sun_policy: str = "flag"
    supersample: int = 4
    smear_steps: int = 9
    stray_light_e: float = 0.0

    def __post_init__(self) -> None:
        if self.sun_policy not in SUN_POLICIES:
            raise InputError(f"sun_policy must be one of {', '.join(SUN_POLICIES)}, got {self.sun_policy!r}")
        if not (math.isfinite(self.sun_keepout_margin_rad) and self.sun_keepout_margin_rad >= 0):
            raise InputError(f"sun_keepout_margin_rad must be >= 0, got {self.sun_keepout_margin_rad!r}")
        if self.vmag_limit is not None and not math.isfinite(self.vmag_limit):
            raise InputError(f"vmag_limit must be finite, got {self.vmag_limit!r}")
        if not (isinstance(self.supersample, int) and self.supersample >= 1):
            raise InputError(f"supersample must be a positive integer, got {self.supersample!r}")
        if not (isinstance(self.smear_steps, int) and self.smear_steps >= 2):
            raise InputError(f"smear_steps must be an integer >= 2, got {self.smear_steps!r}")
        if not (math.isfinite(self.stray_light_e) and self.stray_light_e >= 0):
            raise InputError(f"stray_light_e must be >= 0, got {self.stray_light_e!r}")


def _add_stray_light(signal: np.ndarray, camera: Camera, options: RenderOptions,
                     layout: WindowLayout | None = None) -> None:
    """Add the stray-light ramp of ``options`` to ``signal`` (electrons per pixel) in place:
    the full frame (rows, cols), or the flat pixel array of ``layout``'s windows."""
    if options.stray_light_e > 0:
        columns = np.arange(camera.width_px) if layout is None else layout.columns()
        signal += options.stray_light_e * columns / max(camera.width_px - 1, 1)


def _add_stamps_to_windows(signal: np.ndarray, sources: Sequence[Stamps], layout: WindowLayout) -> None:
    """Add the stamps of every source into ``signal``, the flat pixel array of ``layout``, in place.

    Only the (stamp, window) pairs whose boxes overlap are visited, and all of them in one
    ``bincount``, so the cost grows with the pixels drawn rather than with windows x stamps.
    Windows do not overlap, so each stamp pixel lands in at most one window.
    """
    index, weight = [], []
    for stamps in sources:
        index_s, weight_s = _stamp_pixels_in_windows(stamps, layout)
        index.append(index_s)
        weight.append(weight_s)
    if index:
        signal += np.bincount(np.concatenate(index), weights=np.concatenate(weight), minlength=signal.size)


def _stamp_pixels_in_windows(stamps: Stamps, layout: WindowLayout) -> tuple[np.ndarray, np.ndarray]:
    """(flat index into ``layout``'s pixel array, value) of every stamp pixel inside a window."""
    n, size_y, size_x = stamps.values.shape
    x0, y0 = stamps.x0[:, None], stamps.y0[:, None]
    overlap = ((x0 <= layout.x0 + layout.cols - 1) & (x0 + size_x > layout.x0)
               & (y0 <= layout.y0 + layout.rows - 1) & (y0 + size_y > layout.y0))
    stamp, window = np.nonzero(overlap)  # stamp-major: within a window, stamps add in their order
    rows = (stamps.y0[stamp] - layout.y0[window])[:, None] + np.arange(size_y)  # window-local, (pairs, size_y)
    cols = (stamps.x0[stamp] - layout.x0[window])[:, None] + np.arange(size_x)  # (pairs, size_x)
    keep = (((rows >= 0) & (rows < layout.rows[window, None]))[:, :, None]
            & ((cols >= 0) & (cols < layout.cols[window, None]))[:, None, :])
    index = layout.start[window, None, None] + rows[:, :, None] * layout.cols[window, None, None] + cols[:, None, :]
    return index[keep], stamps.values[stamp][keep]


@dataclass(frozen=True)
class RenderResult:
    """A rendered full frame.

    ``image``: (rows, cols) ADU, float64 when noise-free else unsigned integers;
    ``signal_e``: expected photo-electrons per pixel (no dark, no noise);
    ``truth``: :class:`FrameTruth`; ``header``: FITS header with WCS.
    """

    image: np.ndarray
    signal_e: np.ndarray
    truth: FrameTruth
    header: fits.Header

    @property
    def flags(self) -> tuple[str, ...]:
        return self.truth.flags


@dataclass(frozen=True)
class WindowedResult:
    """A frame rendered only in regions of interest (``windows`` in ADU)."""

    windows: tuple[Window, ...]
    truth: FrameTruth
    camera: Camera

    @property
    def header(self) -> fits.Header:
        """FITS header with WCS of the whole frame (made on demand: a streamed frame never needs it)."""
        return frame_header(self.camera, self.truth)


@dataclass(frozen=True)
class _Scene:
    sources: tuple[Stamps, ...]
    truth: FrameTruth


def _resolve_bodies(targets: Sequence[str | Body]) -> list[Body]:
    return [t if isinstance(t, Body) else body_model(t) for t in targets]


def _body_patch(view: BodyView, camera: Camera, psf: PSF, exposure_s: float, path_offsets: np.ndarray | None,
                pixels: tuple[int, int, np.ndarray] | None = None) -> Stamps | None:
    """Resolved body: its light per pixel (``pixels`` = (x0, y0, e-/s), a sunlit body's from
    :func:`opnav.bodies.body_pixels`; else the view's rays binned into pixels: a UV limb's are
    already one per pixel), convolved with the PSF (and smear) kernel; None when no light lands."""
    if pixels is None:
        # Column and row as 1-D arrays: numpy reduces an (M, 2) array along its short axis
        # ~10x slower than two contiguous vectors (thousands of rays a body).
        x, y = view.rays.xy_px.T
        ok = np.isfinite(x) & np.isfinite(y)
        col, row, rate = np.rint(x[ok]).astype(int), np.rint(y[ok]).astype(int), view.rays.electrons_s[ok]
        x0, y0 = col.min(), row.min()
        width, height = col.max() - x0 + 1, row.max() - y0 + 1
        binned = np.bincount((row - y0) * width + (col - x0), weights=rate * exposure_s,
                             minlength=width * height).reshape(height, width)
    else:
        x0, y0, rate = pixels
        if not rate.size:
            return None
        binned = rate * exposure_s
    kernel_path = None if path_offsets is None else path_offsets[None]
    kernel = render_stamps(np.zeros((1, 2)), np.ones(1), psf, path_px=kernel_path)
    k_half = -int(kernel.x0[0])
    patch = fftconvolve(binned, kernel.values[0], mode="full")
    np.clip(patch, 0.0, None, out=patch)  # FFT round-off leaves tiny negatives
    return Stamps(x0=np.array([x0 - k_half]), y0=np.array([y0 - k_half]), values=patch[None])


def _build_scene(
    camera: Camera,
    R_icrf_cam: Rotation,
    observer: Observer,
    catalog: StarSource | None,
    bodies: list[Body],
    ephemeris,
    options: RenderOptions,
    omega_cam_rad_s: np.ndarray,
    bands: dict | None = None,
) -> _Scene:
    flags: list[str] = []
    turning = bool(np.any(omega_cam_rad_s != 0.0))
    if ephemeris is not None:
        sun = sun_direction(observer, ephemeris, options.corrections)
        keepout = camera.half_diagonal_fov_rad + options.sun_keepout_margin_rad
        if float(angle_between(sun, boresight_icrf(R_icrf_cam))) < keepout:
            if options.sun_policy == "raise":
                raise FrameError(
                    f"camera {camera.camera_id!r}: the Sun is {math.degrees(float(angle_between(sun, boresight_icrf(R_icrf_cam)))):.2f} deg "
                    f"from the boresight, inside the {math.degrees(keepout):.2f} deg keep-out cone"
                )
            flags.append("sun_keepout")
    elif bodies:
        raise InputError("an ephemeris is required to render targets")
    sources: list[Stamps] = []
    margin = options.psf.half_width_px
    empty_stars = StarTruth(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros((0, 3)))
    star_truth, target_truth = empty_stars, []
    if "sun_keepout" not in flags:
        if catalog is not None:
            stars = stars_in_view(
                catalog, camera, R_icrf_cam, observer,
                corrections=options.corrections, vmag_limit=options.vmag_limit, margin_px=margin,
            )
            electrons = electron_rate(stars.vmag, camera) * camera.exposure_s
            path = None
            if turning and len(stars.star_id):
                path = smear_path_px(stars.direction_icrf, camera, R_icrf_cam, omega_cam_rad_s, n_steps=options.smear_steps)
            if len(stars.star_id):
                sources.append(render_stamps(stars.xy_px, electrons, options.psf, path_px=path))
            star_truth = StarTruth(stars.star_id, stars.xy_px, electrons, stars.vmag, stars.direction_icrf)
        for body in bodies:
            view = view_body(body, camera, R_icrf_cam, observer, ephemeris, corrections=options.corrections,
                             supersample=options.supersample, band_rad=(bands or {}).get(body.name))
            if not np.all(np.isfinite(view.xy_cof_px)):
                flags.append(f"{body.name}_behind_camera")
                continue
            path_offsets = None
            if turning:
                path_offsets = smear_path_px(view.direction_icrf, camera, R_icrf_cam, omega_cam_rad_s, n_steps=options.smear_steps)[0] - view.xy_cof_px
            diameter_px = 2.0 * view.angular_radius_rad / camera.pixel_scale_rad
            resolved = diameter_px >= 1.0
            electrons = view.electrons_s * camera.exposure_s
            reaches = camera.in_frame(view.rays.xy_px, margin_px=-margin) if view.rays.xy_px.size else np.zeros(0, bool)
            if not np.any(reaches):
                flags.append(f"{body.name}_out_of_view")
            elif resolved and diameter_px < SMALL_BODY_PX and body.shading != "uv-limb":
                # A body a few pixels across: each ray's light through the PSF at its own place. Its pixel
                # means through the PSF as if each pixel's light sat at the pixel's centre (below) lose where
                # the light lies inside its pixel: 0.09-0.11 px off the photocentre at 1-2 px across.
                lit = np.isfinite(view.rays.xy_px).all(axis=1) & (view.rays.electrons_s > 0)
                xy = view.rays.xy_px[lit]
                path = None if path_offsets is None else xy[:, None, :] + path_offsets[None, :, :]
                sources.append(render_stamps(xy, view.rays.electrons_s[lit] * camera.exposure_s, options.psf,
                                             path_px=path))
            elif resolved:
                pixels = None
                if body.shading != "uv-limb":  # its rays aligned with the pixels (module notes of opnav.bodies)
                    pixels = body_pixels(body, camera, R_icrf_cam, observer, ephemeris,
                                         corrections=options.corrections, supersample=options.supersample,
                                         band_rad=(bands or {}).get(body.name), margin_px=margin)
                patch = _body_patch(view, camera, options.psf, camera.exposure_s, path_offsets, pixels)
                if patch is not None:
                    sources.append(patch)
            elif electrons > 0:
                path = None if path_offsets is None else (view.xy_photocentre_px + path_offsets)[None]
                sources.append(render_stamps(view.xy_photocentre_px[None], np.array([electrons]), options.psf, path_px=path))
            target_truth.append(
                TargetTruth(
                    name=body.name,
                    xy_cof_px=view.xy_cof_px,
                    xy_photocentre_px=view.xy_photocentre_px,
                    ra_rad=view.ra_rad,
                    dec_rad=view.dec_rad,
                    range_km=view.range_km,
                    phase_angle_rad=view.phase_angle_rad,
                    vmag=view.vmag,
                    electrons=electrons,
                    angular_radius_rad=view.angular_radius_rad,
                    resolved=resolved,
                )
            )
    truth = FrameTruth(
        t_tdb_s=observer.t_tdb_s,
        exposure_s=camera.exposure_s,
        camera_id=camera.camera_id,
        R_icrf_cam=R_icrf_cam,
        r_observer_ssb_km=observer.r_ssb_km,
        v_observer_ssb_km_s=observer.v_ssb_km_s,
        omega_cam_rad_s=omega_cam_rad_s,
        stars=star_truth,
        targets=tuple(target_truth),
        flags=tuple(flags),
    )
    return _Scene(sources=tuple(sources), truth=truth)


def _check_inputs(R_icrf_cam: Rotation, omega_cam_rad_s, rng, options: RenderOptions) -> np.ndarray:
    if not isinstance(R_icrf_cam, Rotation) or R_icrf_cam.single is False:
        raise InputError("R_icrf_cam must be a single scipy Rotation (camera -> ICRF)")
    if not np.all(np.isfinite(R_icrf_cam.as_quat())):
        raise InputError("R_icrf_cam contains NaN")
    omega = np.asarray(omega_cam_rad_s, dtype=float)
    if omega.shape != (3,) or not np.all(np.isfinite(omega)):
        raise InputError(f"omega_cam_rad_s must be a finite (3,) vector, got {omega_cam_rad_s!r}")
    if rng is None and not options.detector.noise_free:
        raise InputError("rng (numpy.random.Generator) is required unless options.detector.noise_free")
    return omega


def render_frame(
    camera: Camera,
    R_icrf_cam: Rotation,
    observer: Observer,
    *,
    catalog: StarSource | None = None,
    targets: Sequence[str | Body] = (),
    ephemeris=None,
    options: RenderOptions = RenderOptions(),
    omega_cam_rad_s: np.ndarray = (0.0, 0.0, 0.0),
    rng: np.random.Generator | None = None,
) -> RenderResult:
    """Render a full frame in memory.

    Parameters
    ----------
    camera : Camera
        Optics, detector and exposure.
    R_icrf_cam : Rotation
        Mid-exposure attitude, camera frame -> ICRF.
    observer : Observer
        Mid-exposure epoch and SSB state (ICRF, km, km/s).
    catalog : StarSource, optional
        Star catalog (:class:`opnav.catalog.StarCatalog`); None draws no stars.
    targets : sequence of str or Body
        Extended targets (``"phobos"``, ``"deimos"``, ``"mars"``, ``"earth"`` or custom :class:`Body`).
    ephemeris : opnav.ephemeris.Ephemeris, optional
        Needed for targets and for the Sun keep-out test (skipped without it).
    options : RenderOptions
    omega_cam_rad_s : (3,) array
        Camera body rate (camera frame, rad/s) for smear.
    rng : numpy.random.Generator
        Detector noise; required unless ``options.detector.noise_free``.

    Returns
    -------
    RenderResult
    """
    omega = _check_inputs(R_icrf_cam, omega_cam_rad_s, rng, options)
    scene = _build_scene(camera, R_icrf_cam, observer, catalog, _resolve_bodies(targets), ephemeris, options, omega)
    signal = np.zeros(camera.shape)
    for stamps in scene.sources:
        add_stamps(signal, stamps)
    _add_stray_light(signal, camera, options)
    image = read_out(signal, camera, options=options.detector, rng=rng)
    return RenderResult(image=image, signal_e=signal, truth=scene.truth, header=frame_header(camera, scene.truth))


def roi_boxes(truth: FrameTruth, camera: Camera, *, half_px: int) -> list[tuple[int, int, int, int]]:
    """Square boxes (x0, y0, x1, y1), inclusive, clipped to the detector, around every
    star and target of ``truth`` (targets grow by their angular radius); overlapping
    boxes are merged."""
    centres = [truth.stars.xy_px]
    halves = [np.full(len(truth.stars), float(half_px))]
    for target in truth.targets:
        centres.append(target.xy_cof_px[None])
        halves.append(np.array([half_px + target.angular_radius_rad / camera.pixel_scale_rad * 1.2]))
    xy = np.concatenate(centres).reshape(-1, 2)
    half = np.concatenate(halves)[:, None]
    boxes = np.concatenate([np.floor(xy - half), np.ceil(xy + half)], axis=1).astype(np.int64)
    return _merge_boxes(boxes, camera)


def merge_boxes(boxes, camera: Camera) -> list[tuple[int, int, int, int]]:
    """Boxes (x0, y0, x1, y1), inclusive full-frame pixels, clipped to the detector, touching or
    overlapping ones merged; ``InputError`` for a box that is not four finite numbers."""
    try:
        values = np.array(list(boxes), dtype=float).reshape(-1, 4) if len(boxes) else np.zeros((0, 4))
    except (TypeError, ValueError):
        values = np.full((1, 4), np.nan)
    if values.shape[0] != len(boxes) or not np.all(np.isfinite(values)):
        raise InputError(f"boxes must be (x0, y0, x1, y1) of finite pixel numbers, got {boxes!r}")
    return _merge_boxes(np.trunc(values).astype(np.int64), camera)


def _merge_boxes(boxes: np.ndarray, camera: Camera) -> list[tuple[int, int, int, int]]:
    """:func:`merge_boxes` of an (N, 4) integer array."""
    low = np.maximum(boxes[:, :2], 0)
    high = np.minimum(boxes[:, 2:], [camera.width_px - 1, camera.height_px - 1])
    boxes = np.concatenate([low, high], axis=1)[np.all(low <= high, axis=1)]
    return [tuple(box) for box in _merge_kernel(boxes).tolist()]


@kernel
def _merge_kernel(boxes):  # pragma: no cover - compiled
    """Merge touching boxes (N, 4) into their bounding box until no two touch.

    A merged box takes the place of the earlier of the two. The result is the finest grouping
    in which no two boxes touch, whatever the merge order (two touching boxes must end in one
    group), in the order of each group's first box. Compiled: tens of boxes a frame, pairs
    compared in a double loop.
    """
    boxes = boxes.copy()
    alive = np.ones(boxes.shape[0], np.bool_)
    merged = True
    while merged:
        merged = False
        for i in range(boxes.shape[0]):
            for j in range(i + 1, boxes.shape[0]):
                if not (alive[i] and alive[j]):
                    continue
                if (boxes[i, 0] <= boxes[j, 2] + 1 and boxes[j, 0] <= boxes[i, 2] + 1
                        and boxes[i, 1] <= boxes[j, 3] + 1 and boxes[j, 1] <= boxes[i, 3] + 1):
                    boxes[i, 0] = min(boxes[i, 0], boxes[j, 0])
                    boxes[i, 1] = min(boxes[i, 1], boxes[j, 1])
                    boxes[i, 2] = max(boxes[i, 2], boxes[j, 2])
                    boxes[i, 3] = max(boxes[i, 3], boxes[j, 3])
                    alive[j] = False
                    merged = True
    return boxes[alive]


def render_windows(
    camera: Camera,
    R_icrf_cam: Rotation,
    observer: Observer,
    *,
    catalog: StarSource | None = None,
    targets: Sequence[str | Body] = (),
    ephemeris=None,
    options: RenderOptions = RenderOptions(),
    omega_cam_rad_s: np.ndarray = (0.0, 0.0, 0.0),
    rng: np.random.Generator | None = None,
    window_half_px: int = 12,
    boxes=None,
    body_bands: dict | None = None,
) -> WindowedResult:
    """Render only regions of interest: around the true stars and targets, or ``boxes``.

    Same parameters as :func:`render_frame`, plus ``window_half_px``: half-width of the
    square window around each source (targets add their apparent radius), and ``boxes``:
    the windows to render instead, ``(x0, y0, x1, y1)`` inclusive (e.g. where an image
    stage will read; clipped to the detector, overlapping ones merged), and ``body_bands``:
    ``{body name: (inner, outer)}``, the angles from a resolved body's centre direction (rad)
    between which its light is drawn (:func:`opnav.bodies.view_body` ``band_rad``; pixels more
    than the PSF's half-width inside that band are those of a full render, the rest are
    not: a limb rendered only where a limb fit reads it). Each window is read
    out as on its own (noise, dark, hot pixels and cosmic rays of its pixels only, blooming
    along its columns; :func:`~opnav.render.detector.read_out_windows` reads all of them in
    one pass), so its pixel statistics are those of the same region of a full frame.
    """
    omega = _check_inputs(R_icrf_cam, omega_cam_rad_s, rng, options)
    if not (isinstance(window_half_px, int) and window_half_px >= 1):
        raise InputError(f"window_half_px must be a positive integer, got {window_half_px!r}")
    scene = _build_scene(camera, R_icrf_cam, observer, catalog, _resolve_bodies(targets), ephemeris, options, omega,
                         body_bands)
    regions = (roi_boxes(scene.truth, camera, half_px=window_half_px) if boxes is None
               else merge_boxes(boxes, camera))
    # All windows in one flat array: stamps pasted and read out once for the frame, not once a window.
    layout = WindowLayout.from_boxes(regions)
    signal = np.zeros(layout.size)
    _add_stamps_to_windows(signal, scene.sources, layout)
    _add_stray_light(signal, camera, options, layout)
    image = read_out_windows(signal, layout, camera, options=options.detector, rng=rng)
    windows = tuple(Window(x0=x0, y0=y0, image=pixels) for (x0, y0, _, _), pixels in zip(regions, layout.views(image)))
    return WindowedResult(windows=windows, truth=scene.truth, camera=camera)
