"""Extended bodies: tri-axial ellipsoids and triangle meshes lit by the Sun, and the Earth's UV disk.

Rendering one body, step by step:

1. Light time: the astrometric vector observer -> body (body at the emission
   epoch ``t - tau``) from :func:`opnav.light.light_time_vector`; the centre of
   figure's apparent direction from :func:`opnav.light.apparent_direction` (the
   function the filters use). Orientation and the Sun direction are taken at
   ``t - tau``.
2. Orientation. Phobos and Deimos rotate synchronously: body x axis (longest)
   toward Mars, z (shortest) along the orbit normal ``r x v``. Mars and the
   Earth use their IAU pole (Mars: RA 317.681 deg, Dec 52.887 deg, Archinal
   et al. 2018; Earth: the ICRF pole, the ~0.4 deg precession since J2000 being
   invisible on a sphere-like body) with an arbitrary prime meridian, since an
   oblate spheroid looks the same at every longitude.
3. Rays: a square grid in gnomonic coordinates (a, b) around the astrometric
   direction ``l``; ray ``d = unit(l + a e1 + b e2)`` carries the solid angle
   ``da db / (1 + a^2 + b^2)^(3/2)``. The spacing is ``pixel / supersample``,
   never coarser than 1/48 of the body's diameter (so unresolved bodies still
   get an accurate photocentre) and never finer than 1/2000 of it (memory).
   These rays give the view's flux, magnitude and photocentre (the truth of an
   unresolved body and the image stage's predictions). A resolved sunlit body's
   *image* is not these rays binned to the nearest pixel (the grid is not the
   pixels': a 100 px disk's light landed up to 0.075 px off its centre) but
   :func:`body_pixels`: each pixel's own rays, finer where the limb or the
   terminator crosses it.
4. Each ray is intersected with the ellipsoid; at the hit point the outward
   normal gives ``mu = cos(emission)`` and ``mu0 = cos(incidence)``. Reflectance
   (I/F) for geometric albedo p:
   Lommel-Seeliger ``2 p mu0 / (mu0 + mu)`` (uniform disk of I/F = p at zero
   phase) or Lambert ``1.5 p mu0`` (Lambert albedo 3p/2).
   The ray's flux as a fraction of the Sun's flux at 1 au is
   ``(I/F) / pi * (1 au / r_sun_body)^2 * dOmega``; the sum gives the apparent
   magnitude through the Sun's V magnitude (:mod:`opnav.photometry`).
   There is no opposition surge and no mutual shadowing or occultation (S1:
   Mars never hides the moons in cruise).
5. Earth (UV Earth sensor): radiance ``L0`` (electrons/s per boresight pixel
   solid angle, detector-referred; UV sensors see the whole disk, day and
   night, so no Sun dependence) for rays whose closest approach to the centre
   lies below ``limb_altitude_km`` (default 40 km, the ozone-layer UV horizon),
   and ``L0 exp(-(h - h0) / H)`` above it, H = ``limb_scale_height_km``
   (default 8 km, the scale height of the upper stratosphere). A spherical UV
   body is not ray-cast: each pixel is integrated across the direction its
   angle from the centre changes in (:func:`_sphere_limb_samples`; exact for a
   radially symmetric radiance, where a ray grid binned to the nearest pixel
   aliases against the pixel grid), ``supersample`` unused; ``band_rad``
   limits it to an annulus (a limb rendered only where a limb fit reads it).
6. A body with a ``shape`` (a :class:`opnav.shape.Mesh`: an irregular body from a Wavefront OBJ)
   is ray-cast on its triangles instead (:mod:`opnav.shape`: the same ray grid and pixel rays,
   flat facets, self-shadowing, Lambert / Lommel-Seeliger / lunar-Lambert); its extent is the
   mesh's bounding radius. A ``rotation_rate_rad_s`` (or ``prime_meridian_rad``) turns a fixed-pole
   body about its pole: prime meridian ``W = prime_meridian_rad + rotation_rate_rad_s t`` from the
   node of its equator on the ICRF equator (the IAU convention).
7. Ray directions are aberrated with the observer's SSB velocity
   (:func:`opnav.light.aberrate`) and projected; their flux-weighted mean pixel
   position is the photocentre.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from .camera import Camera
from .compiled import kernel
from .constants import AU_KM, DEIMOS_RADII_KM, MARS_POLAR_RADIUS_KM, PHOBOS_RADII_KM, RADIUS_KM
from .errors import InputError
from .frames import radec_to_unit, unit, unit_to_radec
from .light import aberrate, light_time_vector
from .photometry import SUN_VMAG_1AU, electron_rate, reflected_magnitude
from .observer import Corrections, Observer
from .shape import Mesh, mesh_lit_rays, mesh_pixel_means, outside_band, reflectance_weights, subpixel_ray

_SHADINGS = ("lommel-seeliger", "lambert", "uv-limb", "lunar-lambert")
_ORIENTATIONS = ("synchronous", "pole")
_MIN_SAMPLES_ACROSS = 48
#: Memory guard: a very large disk (the Earth filling a wide-field sensor) gets at most this many rays across.
_MAX_SAMPLES_ACROSS = 2000
#: A spherical UV limb is sampled at most this far off the detector, px (its PSF's reach).
_OFFSCREEN_MARGIN_PX = 16
#: Points of the radiance average across a pixel of a spherical UV limb (0.02 px apart, an eighth of the
#: 8 km scale height seen from GEO).
_LIMB_QUADRATURE = 64


@dataclass(frozen=True)
class Body:
    """An extended target.

    Parameters
    ----------
    name : str
        Ephemeris name (``phobos``, ``deimos``, ``mars``, ``earth``, ...).
    radii_km : (a, b, c)
        Semi-axes along body x, y, z, km.
    geometric_albedo : float
        V-band geometric albedo (unused by ``uv-limb``).
    shading : {"lommel-seeliger", "lambert", "uv-limb", "lunar-lambert"}
    orientation : {"synchronous", "pole"}
        Synchronous moon (x toward the primary, z along the orbit normal) or a fixed pole.
    pole_ra_rad, pole_dec_rad : float
        Pole direction for ``orientation="pole"``, ICRF.
    primary : str
        Body the moon orbits (``synchronous`` only).
    uv_radiance_e_s_px : float
        Earth-disk radiance for ``uv-limb``, electrons/s per pixel at the boresight.
    limb_altitude_km, limb_scale_height_km : float
        Soft atmospheric limb of ``uv-limb`` (see module notes).
    shape : opnav.shape.Mesh, optional
        A triangle mesh (body axes, km, origin at the ephemeris point) rendered instead of the
        ellipsoid of ``radii_km`` (which then only sizes the image stage's predictions: give the
        mesh's half extents, :meth:`opnav.shape.Mesh.half_extents_km`). Not with ``uv-limb``.
    lunar_lambert_l : float
        ``L`` of the ``lunar-lambert`` shading (0: Lambert, 1: Lommel-Seeliger; mesh bodies only).
    rotation_rate_rad_s, prime_meridian_rad : float
        Spin about the pole (``orientation="pole"``): prime meridian angle at J2000 and its rate (module notes).
    """

    name: str
    radii_km: tuple[float, float, float]
    geometric_albedo: float = 0.07
    shading: str = "lommel-seeliger"
    orientation: str = "pole"
    pole_ra_rad: float = 0.0
    pole_dec_rad: float = math.pi / 2.0
    primary: str = "mars"
    uv_radiance_e_s_px: float = 2.0e4
    limb_altitude_km: float = 40.0
    limb_scale_height_km: float = 8.0
    shape: Mesh | None = None
    lunar_lambert_l: float = 0.5
    rotation_rate_rad_s: float = 0.0
    prime_meridian_rad: float = 0.0

    def __post_init__(self) -> None:
        radii = tuple(float(r) for r in self.radii_km)
        if len(radii) != 3 or not all(math.isfinite(r) and r > 0 for r in radii):
            raise InputError(f"body {self.name!r} radii_km must be three positive numbers, got {self.radii_km!r}")
        object.__setattr__(self, "radii_km", radii)
        if self.shading not in _SHADINGS:
            raise InputError(f"body {self.name!r} shading must be one of {', '.join(_SHADINGS)}, got {self.shading!r}")
        if self.orientation not in _ORIENTATIONS:
            raise InputError(f"body {self.name!r} orientation must be one of {', '.join(_ORIENTATIONS)}")
        if not (0.0 < self.geometric_albedo <= 1.5):
            raise InputError(f"body {self.name!r} geometric_albedo must be in (0, 1.5], got {self.geometric_albedo!r}")
        for name in ("uv_radiance_e_s_px", "limb_scale_height_km"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise InputError(f"body {self.name!r} {name} must be positive")
        if self.shape is not None and not isinstance(self.shape, Mesh):
            raise InputError(f"body {self.name!r} shape must be an opnav.shape.Mesh (opnav.shape.read_obj)")
        if self.shading == "uv-limb" and self.shape is not None:
            raise InputError(f"body {self.name!r}: a mesh shape takes lambert, lommel-seeliger or lunar-lambert shading")
        if self.shading == "lunar-lambert" and self.shape is None:
            raise InputError(f"body {self.name!r}: lunar-lambert shading is rendered on mesh shapes only")
        if not (0.0 <= self.lunar_lambert_l <= 1.0):
            raise InputError(f"body {self.name!r} lunar_lambert_l must be in [0, 1], got {self.lunar_lambert_l!r}")
        for name in ("rotation_rate_rad_s", "prime_meridian_rad"):
            if not math.isfinite(getattr(self, name)):
                raise InputError(f"body {self.name!r} {name} must be a finite number")

    @property
    def extent_km(self) -> float:
        """Largest distance of the body's surface from its centre, km (the mesh's bounding radius)."""
        return self.shape.bounding_radius_km if self.shape is not None else max(self.radii_km)


#: Default models. Phobos/Deimos albedo 0.07 (Thomas et al. 1996); Mars 0.17 (Mallama 2007).
BODIES = {
    "phobos": Body("phobos", PHOBOS_RADII_KM, 0.07, orientation="synchronous"),
    "deimos": Body("deimos", DEIMOS_RADII_KM, 0.07, orientation="synchronous"),
    "mars": Body(
        "mars",
        (RADIUS_KM["mars"], RADIUS_KM["mars"], MARS_POLAR_RADIUS_KM),
        0.17,
        shading="lambert",
        pole_ra_rad=math.radians(317.681),
        pole_dec_rad=math.radians(52.887),
    ),
    "earth": Body("earth", (RADIUS_KM["earth"],) * 3, shading="uv-limb"),
}


def body_model(name: str) -> Body:
    """The default :class:`Body` for ``name``; raise ``InputError`` listing the known ones."""
    key = str(name).strip().lower()
    if key not in BODIES:
        raise InputError(f"no body model for target {name!r}; known targets: {', '.join(sorted(BODIES))}")
    return BODIES[key]


@dataclass(frozen=True)
class BodyRays:
    """Sampled light of one body in one frame.

    ``xy_px`` (M, 2) projected ray positions at mid-exposure and ``electrons_s``
    (M,) their electron rates (only rays carrying light are kept).
    """

    xy_px: np.ndarray
    electrons_s: np.ndarray


@dataclass(frozen=True)
class BodyView:
    """Geometry and photometry of one body in one frame (the truth record's source).

    Pixel positions are at mid-exposure; angles rad; ``vmag`` is None for the UV Earth.
    """

    name: str
    xy_cof_px: np.ndarray
    xy_photocentre_px: np.ndarray
    direction_icrf: np.ndarray
    ra_rad: float
    dec_rad: float
    range_km: float
    phase_angle_rad: float
    angular_radius_rad: float
    vmag: float | None
    electrons_s: float
    rays: BodyRays


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``numpy.cross`` of two 3-vectors: the same products and differences, so the same numbers,
    without its ~10 us of axis handling (a frame's predicted views take a dozen)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def body_axes_icrf(body: Body, t_emit: float, ephemeris) -> np.ndarray:
    """Columns = body x, y, z axes in ICRF at the emission epoch (3, 3)."""
    if body.orientation == "synchronous":
        r, v = ephemeris.state(body.name, t_emit, center=body.primary)
        x = -unit(r)
        z = unit(cross3(r, v))
        return np.column_stack([x, cross3(z, x), z])
    axes = _pole_axes(body.pole_ra_rad, body.pole_dec_rad).copy()
    if body.rotation_rate_rad_s != 0.0 or body.prime_meridian_rad != 0.0:
        w = body.prime_meridian_rad + body.rotation_rate_rad_s * t_emit
        x, y = axes[:, 0].copy(), axes[:, 1].copy()
        axes[:, 0], axes[:, 1] = math.cos(w) * x + math.sin(w) * y, -math.sin(w) * x + math.cos(w) * y
    return axes


@functools.lru_cache(maxsize=16)
def _pole_axes(pole_ra_rad: float, pole_dec_rad: float) -> np.ndarray:
    """Axes of a fixed-pole body (:func:`body_axes_icrf`): they never change, so they are made once."""
    z = radec_to_unit(pole_ra_rad, pole_dec_rad)
    helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = unit(cross3(helper, z))
    return np.column_stack([x, cross3(z, x), z])


def reflectance(mu0: np.ndarray, mu: np.ndarray, shading: str, albedo: float) -> np.ndarray:
    """Radiance factor I/F for the incidence/emission cosines (both > 0)."""
    if shading == "lommel-seeliger":
        return 2.0 * albedo * mu0 / (mu0 + mu)
    return 1.5 * albedo * mu0


def _ellipsoid_hits(origin: np.ndarray, dirs: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray-ellipsoid intersection in the body frame: (hit mask, unit outward normals)."""
    o = origin / radii
    d = dirs / radii
    qa = np.sum(d * d, -1)
    qb = 2.0 * np.sum(o * d, -1)
    qc = np.dot(o, o) - 1.0
    disc = qb * qb - 4.0 * qa * qc
    hit = disc > 0.0
    t = (-qb - np.sqrt(np.where(hit, disc, 0.0))) / (2.0 * qa)
    hit &= t > 0.0
    point = origin + t[:, None] * dirs
    normal = point / radii**2
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return hit, normal


def view_body(
    body: Body,
    camera: Camera,
    R_icrf_cam: Rotation,
    observer: Observer,
    ephemeris,
    *,
    corrections: Corrections = Corrections(),
    supersample: int = 4,
    band_rad: tuple[float, float] | None = None,
    keep_rays: bool = True,
) -> BodyView:
    """Ray-cast ``body`` as seen by ``camera`` at ``observer``; see the module notes.

    Parameters
    ----------
    body : Body
    camera : Camera
    R_icrf_cam : Rotation
        Attitude at mid-exposure, camera -> ICRF.
    observer : Observer
        SSB state (ICRF, km, km/s) at mid-exposure.
    ephemeris : opnav.ephemeris.Ephemeris
    corrections : Corrections
        ``light_time`` and ``aberration`` switches.
    supersample : int
        Rays per pixel per axis for resolved bodies (a spherical UV body is integrated per pixel).
    band_rad : (inner, outer), optional
        Cast only the rays between these angles from the body's centre direction, rad (the rays
        of the full grid that fall there, so every pixel whose rays all lie inside the band gets
        the full view's light): a limb seen only where it is read. The geometry (centre,
        radius, photocentre of the rays cast) is computed as usual.
    keep_rays : bool
        False leaves the view's ``rays`` empty (they are still cast for the photocentre and the
        flux): an image stage's prediction needs only the centre, photocentre, radius and flux,
        and each reprojection of a view moves all its rays.
    """
    if band_rad is not None and not (0.0 <= band_rad[0] < band_rad[1]):
        raise InputError(f"band_rad must be (inner, outer) with 0 <= inner < outer, got {band_rad!r}")

    geo = _geometry(body, observer, ephemeris, corrections)
    r_rel, direction, range_km, phase = geo["r_rel"], geo["direction"], geo["range_km"], geo["phase"]
    r_sun_body, sun_from_body = geo["r_sun_body"], geo["sun_from_body"]
    extent_km = body.extent_km + (body.limb_altitude_km + 8.0 * body.limb_scale_height_km if body.shading == "uv-limb" else 0.0)
    if extent_km >= range_km:
        raise InputError(f"observer is inside or on target {body.name!r} (range {range_km:.1f} km)")
    angular_radius = math.asin(body.extent_km / range_km)

    spherical = body.radii_km[0] == body.radii_km[1] == body.radii_km[2]
    axes = geo["axes"]
    if body.shading == "uv-limb" and spherical:
        xy, rate = _sphere_limb_samples(body, camera, R_icrf_cam, observer, r_rel, math.asin(extent_km / range_km),
                                        band_rad, corrections.aberration)
        return _finish_view(body, camera, R_icrf_cam.inv(), direction, range_km, phase, angular_radius, None, xy, rate,
                            keep_rays)
    if body.shading != "uv-limb":
        rays_dir, solid_angle, i_over_f = _lit_rays(r_rel, math.asin(extent_km / range_km),
                                                    camera.pixel_scale_rad / supersample, band_rad, axes,
                                                    np.asarray(body.radii_km, float), sun_from_body, body.shading,
                                                    body.geometric_albedo, body)
        keep = i_over_f > 0.0
        flux_ratio = i_over_f / math.pi * (AU_KM / np.linalg.norm(r_sun_body)) ** 2 * solid_angle
        total = float(np.sum(flux_ratio))
        vmag = float(reflected_magnitude(total)) if total > 0 else None
        rate = flux_ratio / total * float(electron_rate(vmag, camera)) if vmag is not None else np.zeros_like(flux_ratio)
        apparent_rays = aberrate(rays_dir[keep], observer.v_ssb_km_s) if corrections.aberration else rays_dir[keep]
        R_cam_icrf = R_icrf_cam.inv()
        xy = camera.project(R_cam_icrf.apply(apparent_rays))
        return _finish_view(body, camera, R_cam_icrf, direction, range_km, phase, angular_radius, vmag, xy,
                            rate[keep], keep_rays)
    rays_dir, solid_angle = _ray_grid(r_rel, math.asin(extent_km / range_km), camera.pixel_scale_rad / supersample,
                                      band_rad)
    hit, _ = _ellipsoid_hits(axes.T @ (-r_rel), rays_dir @ axes, np.asarray(body.radii_km))
    # a non-spherical UV body: closest approach of each ray to the centre; rays that hit count as altitude <= 0
    closest = np.linalg.norm(np.cross(-r_rel, rays_dir), axis=-1)
    rate = _uv_rate(body, np.where(hit, -1.0, closest - body.radii_km[0]), solid_angle, camera)
    keep = rate > 1e-9 * body.uv_radiance_e_s_px
    vmag = None
    apparent_rays = aberrate(rays_dir[keep], observer.v_ssb_km_s) if corrections.aberration else rays_dir[keep]
    R_cam_icrf = R_icrf_cam.inv()
    xy = camera.project(R_cam_icrf.apply(apparent_rays))
    return _finish_view(body, camera, R_cam_icrf, direction, range_km, phase, angular_radius, vmag, xy, rate[keep],
                        keep_rays)


def _geometry(body: Body, observer: Observer, ephemeris, corrections: Corrections) -> dict:
    """Steps 1-2 of the module notes: ``r_rel`` (observer -> body at emission, ICRF, km),
    ``direction`` (apparent unit vector of the centre), ``range_km``, ``phase`` (rad),
    ``r_sun_body`` (Sun -> body at emission, km), ``sun_from_body`` (unit, body -> Sun) and ``axes``
    (body axes in ICRF, columns)."""

    def target_ssb(t):
        return ephemeris.position(body.name, t)

    t = observer.t_tdb_s
    if corrections.light_time:
        r_rel, tau = light_time_vector(target_ssb, t, observer.r_ssb_km)
    else:
        r_rel, tau = np.asarray(target_ssb(t), dtype=float).reshape(3) - observer.r_ssb_km, 0.0
    t_emit = t - float(tau)
    direction = r_rel / np.linalg.norm(r_rel)  # opnav.light.apparent_direction on the light-time solution made above
    if corrections.aberration:
        direction = aberrate(direction, observer.v_ssb_km_s)
    r_sun_body = np.asarray(ephemeris.position(body.name, t_emit), dtype=float) - np.asarray(ephemeris.position("sun", t_emit), dtype=float)
    sun_from_body = -unit(r_sun_body)
    # opnav.frames.angle_between with the cross product of cross3 (the same numbers)
    to_observer = -r_rel
    phase = float(np.arctan2(np.linalg.norm(cross3(sun_from_body, to_observer), axis=-1),
                             np.sum(sun_from_body * to_observer, axis=-1)))
    return dict(r_rel=r_rel, direction=direction, range_km=float(np.linalg.norm(r_rel)), phase=phase,
                r_sun_body=r_sun_body, sun_from_body=sun_from_body, axes=body_axes_icrf(body, t_emit, ephemeris))


def _uv_rate(body: Body, altitude_km: np.ndarray, solid_angle: np.ndarray, camera: Camera) -> np.ndarray:
    """Electron rates (e/s) of samples of a ``uv-limb`` body at these closest-approach altitudes (km)
    and solid angles (sr): flat below ``limb_altitude_km``, exponential above (module notes)."""
    radiance = body.uv_radiance_e_s_px * np.exp(-np.clip(altitude_km - body.limb_altitude_km, 0.0, None)
                                                / body.limb_scale_height_km)
    return radiance * solid_angle / camera.pixel_scale_rad**2


def _sphere_limb_samples(body: Body, camera: Camera, R_icrf_cam: Rotation, observer: Observer, r_rel: np.ndarray,
                         extent_rad: float, band_rad, aberration: bool):
    """Pixel-integrated light of a spherical ``uv-limb`` body: pixel centres (x, y) px (M, 2) and
    the electron rate of each whole pixel (M,).

    Its radiance depends only on a line of sight's angle theta from the centre (through the
    closest approach), so each pixel is integrated along the direction theta changes in: theta
    and its gradient come from the pixel's corners (unprojected, de-aberrated with the inverse
    Lorentz aberration, camera frame), the pixel's width across that direction is a trapezoid
    (a unit square seen along a slanted axis), and the radiance is averaged over it with
    ``_LIMB_QUADRATURE`` points. The limb's curvature across one pixel (its sag, under 0.002 px
    on the Earth from GEO) enters through the corners' mean theta. No ray grid meets the pixel
    grid, so nothing aliases: a grid of rays binned to the nearest pixel put the fitted limb
    centre of a nadir UV frame 0.23 px off and left its radius off by up to 0.005 px with the
    pixel phase (0.2 km of limb altitude); point samples at 2 x 2 a pixel still moved it by 0.1 km.
    Pixels farther than ``_OFFSCREEN_MARGIN_PX`` off the detector are not rendered.
    """
    v = observer.v_ssb_km_s
    centre_geo = unit(r_rel)
    range_km = float(np.linalg.norm(r_rel))
    R_cam_icrf = R_icrf_cam.inv()
    inner, outer = (0.0, extent_rad) if band_rad is None else (band_rad[0], min(band_rad[1], extent_rad))
    if inner >= outer:
        return np.zeros((0, 2)), np.zeros(0)
    # the pixels inside the outline (a circle of `outer` about the centre) and one beyond
    helper = np.array([0.0, 0.0, 1.0]) if abs(centre_geo[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = unit(cross3(helper, centre_geo))
    e2 = cross3(centre_geo, e1)
    azimuth = np.linspace(0.0, 2.0 * np.pi, 180, endpoint=False)
    outline = (math.cos(outer) * centre_geo + math.sin(outer) * (np.cos(azimuth)[:, None] * e1
                                                                 + np.sin(azimuth)[:, None] * e2))
    outline_cam = R_cam_icrf.apply(aberrate(outline, v) if aberration else outline)  # apparent
    margin = _OFFSCREEN_MARGIN_PX
    if np.all(outline_cam[:, 2] > 0.0):
        xy = camera.project(outline_cam)
        x0, y0 = np.floor(xy.min(0)).astype(int) - 1
        x1, y1 = np.ceil(xy.max(0)).astype(int) + 1
    else:  # the outline reaches behind the camera: the whole detector
        x0, y0, x1, y1 = -margin, -margin, camera.width_px - 1 + margin, camera.height_px - 1 + margin
    x0, y0 = max(x0, -margin), max(y0, -margin)
    x1, y1 = min(x1, camera.width_px - 1 + margin), min(y1, camera.height_px - 1 + margin)
    if x0 > x1 or y0 > y1:
        return np.zeros((0, 2)), np.zeros(0)
    # everything in the camera frame (aberration turns with the axes): no rotation of the pixels
    to_cam = R_cam_icrf.as_matrix()
    centre_cam = to_cam @ centre_geo
    v_cam = to_cam @ v
    cx, cy = np.meshgrid(np.arange(x0, x1 + 2) - 0.5, np.arange(y0, y1 + 2) - 0.5)
    corners = camera.unproject(np.column_stack([cx.ravel(), cy.ravel()]))
    if aberration:
        corners = aberrate(corners, -v_cam)  # geometric lines of sight
    theta = np.arccos(np.clip(corners @ centre_cam, -1.0, 1.0)).reshape(cx.shape)
    tl, tr, bl, br = theta[:-1, :-1], theta[:-1, 1:], theta[1:, :-1], theta[1:, 1:]
    mean = 0.25 * (tl + tr + bl + br)
    gx, gy = 0.5 * (tr + br - tl - bl), 0.5 * (bl + br - tl - tr)  # rad per px
    reach = 0.5 * (np.abs(gx) + np.abs(gy))  # theta's half-range over the pixel
    take = (mean + reach >= inner) & (mean - reach <= outer)
    rows, cols = np.nonzero(take)
    mean, gx, gy = mean[take], gx[take], gy[take]
    slope = np.hypot(gx, gy)
    # the unit square's width across the gradient: the trapezoid of two boxes |cos|, |sin| wide
    a, b = np.abs(gx) / np.maximum(slope, 1e-300), np.abs(gy) / np.maximum(slope, 1e-300)
    s = (np.arange(_LIMB_QUADRATURE) + 0.5) / _LIMB_QUADRATURE - 0.5  # fractions of the support
    support = (a + b)[:, None] * s[None, :]
    low, high = 0.5 * np.abs(a - b)[:, None], 0.5 * (a + b)[:, None]
    weight = np.where(np.abs(support) <= low, 1.0, np.clip((high - np.abs(support)) / np.maximum(high - low, 1e-12),
                                                          0.0, 1.0))
    weight /= weight.sum(axis=1, keepdims=True)
    angle = mean[:, None] + slope[:, None] * support
    inside = (angle >= inner) & (angle <= outer) & (angle < 0.5 * np.pi)
    altitude = range_km * np.sin(np.minimum(angle, 0.5 * np.pi)) - body.radii_km[0]
    centres = np.column_stack([cols + x0, rows + y0]).astype(float)
    z_cam = camera.unproject(centres)[:, 2]
    # pinhole solid angle of the pixel
    rate = _uv_rate(body, altitude, np.ones_like(altitude), camera)
    rate = np.sum(np.where(inside, rate, 0.0) * weight, axis=1) * z_cam**3 / camera.focal_length_px**2
    keep = rate > 0.0
    return centres[keep], rate[keep]


def _finish_view(body: Body, camera: Camera, R_cam_icrf: Rotation, direction: np.ndarray, range_km: float,
                 phase: float, angular_radius: float, vmag, xy: np.ndarray, rate: np.ndarray,
                 keep_rays: bool = True) -> BodyView:
    total_rate = float(np.sum(rate))
    xy_cof = camera.project(R_cam_icrf.apply(direction))
    photocentre = np.sum(xy * rate[:, None], 0) / total_rate if total_rate > 0 else np.full(2, np.nan)
    ra, dec = unit_to_radec(direction)
    return BodyView(
        name=body.name,
        xy_cof_px=xy_cof,
        xy_photocentre_px=photocentre,
        direction_icrf=direction,
        ra_rad=float(ra),
        dec_rad=float(dec),
        range_km=range_km,
        phase_angle_rad=phase,
        angular_radius_rad=angular_radius,
        vmag=vmag,
        electrons_s=total_rate,
        rays=BodyRays(xy_px=xy, electrons_s=rate) if keep_rays else BodyRays(np.zeros((0, 2)), np.zeros(0)),
    )


def reproject_view(view: BodyView, camera: Camera, R_icrf_cam: Rotation, new_camera: Camera,
                   new_R_icrf_cam: Rotation) -> BodyView:
    """``view`` (made with ``camera`` at attitude ``R_icrf_cam``) as ``new_camera`` at ``new_R_icrf_cam`` sees it.

    The body's apparent directions do not depend on the camera, so a new attitude or a crop
    of the detector (a camera whose principal point moved) only moves the pixels: each is
    unprojected with the old camera and attitude and projected with the new ones.
    """
    # the centre, the photocentre and the rays in one pass
    xy = np.concatenate([np.reshape(view.xy_cof_px, (1, 2)), np.reshape(view.xy_photocentre_px, (1, 2)),
                         np.reshape(view.rays.xy_px, (-1, 2))]).astype(float)
    # old camera frame -> new camera frame as one matrix (composing and applying scipy rotations
    # cost ~30 us a call, and the tracking stage reprojects eight views a frame)
    turn = new_R_icrf_cam.as_matrix().T @ R_icrf_cam.as_matrix()
    moved = new_camera.project(camera.unproject(xy) @ turn.T)
    return replace(view, xy_cof_px=moved[0], xy_photocentre_px=moved[1],
                   rays=BodyRays(xy_px=moved[2:], electrons_s=view.rays.electrons_s))


def _grid_geometry(r_rel: np.ndarray, half_angle_rad: float, spacing_rad: float):
    """The ray grid's axes (ICRF unit vectors: line of sight ``l``, ``e1``, ``e2``), gnomonic
    half-width, spacing and samples across (module notes, step 3)."""
    los = unit(r_rel)
    helper = np.array([0.0, 0.0, 1.0]) if abs(los[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = unit(cross3(helper, los))
    e2 = cross3(los, e1)
    half = math.tan(half_angle_rad) * 1.02
    step = max(min(spacing_rad, 2.0 * half / _MIN_SAMPLES_ACROSS), 2.0 * half / _MAX_SAMPLES_ACROSS)
    return los, e1, e2, half, step, int(math.ceil(2.0 * half / step))


def _ray_grid(r_rel: np.ndarray, half_angle_rad: float, spacing_rad: float,
              band_rad: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions (M, 3) and their solid angles (M,) covering a cone around ``r_rel`` (only
    the rays between ``band_rad`` angles from it, when given: the same rays as the full grid's)."""
    los, e1, e2, half, step, n = _grid_geometry(r_rel, half_angle_rad, spacing_rad)
    g = (np.arange(n) - (n - 1) / 2.0) * step
    g2 = g * g
    radius2 = g2[:, None] + g2[None, :]  # [row (b), column (a)]
    inside = radius2 <= half * half
    if band_rad is not None:
        inside &= (radius2 >= math.tan(band_rad[0]) ** 2) & (radius2 <= math.tan(min(band_rad[1], 1.5)) ** 2)
    rows, cols = np.nonzero(inside)
    a, b = g[cols], g[rows]
    rays = los + a[:, None] * e1 + b[:, None] * e2
    scale = 1.0 + radius2[rows, cols]
    return rays / np.sqrt(scale)[:, None], step * step / scale**1.5


def _lit_rays(r_rel: np.ndarray, half_angle_rad: float, spacing_rad: float, band_rad, axes: np.ndarray,
              radii_km: np.ndarray, sun_from_body: np.ndarray, shading: str, albedo: float, body: Body | None = None):
    """The rays of :func:`_ray_grid` (ICRF unit vectors (M, 3) and solid angles (M,)) and the I/F
    each carries from a sunlit ellipsoid (0 where it misses, faces away or lies in shadow); steps
    3-4 of the module notes in one compiled pass (the array version allocated ~20 temporaries
    of every ray and cost ~0.6 ms a view). A ``body`` with a mesh ``shape`` is cast on its mesh."""
    los, e1, e2, half, step, n = _grid_geometry(r_rel, half_angle_rad, spacing_rad)
    lo2, hi2 = (0.0, half * half) if band_rad is None else (math.tan(band_rad[0]) ** 2,
                                                            min(half * half, math.tan(min(band_rad[1], 1.5)) ** 2))
    if body is not None and body.shape is not None:
        return mesh_lit_rays(body.shape, (los, e1, e2, step, n, lo2, hi2), axes, -r_rel @ axes, sun_from_body @ axes,
                             weights=reflectance_weights(shading, body.lunar_lambert_l), albedo=albedo)
    return _lit_rays_kernel(los, e1, e2, step, n, lo2, hi2, np.ascontiguousarray(axes), -r_rel @ axes, radii_km,
                            np.asarray(sun_from_body, float), shading == "lambert", float(albedo))


@kernel
def _lit_rays_kernel(los, e1, e2, step, n, lo2, hi2, axes, origin_body, radii, sun, lambert,
                     albedo):  # pragma: no cover - compiled
    """Grid rays with lo2 <= a^2 + b^2 <= hi2 (row-major, as ``np.nonzero``), their solid angles and I/F."""
    rays = np.empty((n * n, 3))
    solid = np.empty(n * n)
    i_over_f = np.zeros(n * n)
    o0, o1, o2 = origin_body[0] / radii[0], origin_body[1] / radii[1], origin_body[2] / radii[2]
    qc = o0 * o0 + o1 * o1 + o2 * o2 - 1.0
    k = 0
    for row in range(n):
        b = (row - (n - 1) / 2.0) * step
        for col in range(n):
            a = (col - (n - 1) / 2.0) * step
            radius2 = b * b + a * a
            if not (lo2 <= radius2 <= hi2):
                continue
            scale = 1.0 + radius2
            root = math.sqrt(scale)
            r0 = (los[0] + a * e1[0] + b * e2[0]) / root
            r1 = (los[1] + a * e1[1] + b * e2[1]) / root
            r2 = (los[2] + a * e1[2] + b * e2[2]) / root
            rays[k, 0], rays[k, 1], rays[k, 2] = r0, r1, r2
            solid[k] = step * step / scale**1.5
            # the ray in body axes, scaled to the unit sphere: |o + t d|^2 = 1
            d0 = (r0 * axes[0, 0] + r1 * axes[1, 0] + r2 * axes[2, 0]) / radii[0]
            d1 = (r0 * axes[0, 1] + r1 * axes[1, 1] + r2 * axes[2, 1]) / radii[1]
            d2 = (r0 * axes[0, 2] + r1 * axes[1, 2] + r2 * axes[2, 2]) / radii[2]
            qa = d0 * d0 + d1 * d1 + d2 * d2
            qb = 2.0 * (o0 * d0 + o1 * d1 + o2 * d2)
            disc = qb * qb - 4.0 * qa * qc
            if disc > 0.0:
                t = (-qb - math.sqrt(disc)) / (2.0 * qa)
                if t > 0.0:
                    # outward normal at the hit (body axes, then ICRF): emission and incidence cosines
                    m0 = (origin_body[0] + t * d0 * radii[0]) / radii[0] ** 2
                    m1 = (origin_body[1] + t * d1 * radii[1]) / radii[1] ** 2
                    m2 = (origin_body[2] + t * d2 * radii[2]) / radii[2] ** 2
                    norm = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
                    n0 = (axes[0, 0] * m0 + axes[0, 1] * m1 + axes[0, 2] * m2) / norm
                    n1 = (axes[1, 0] * m0 + axes[1, 1] * m1 + axes[1, 2] * m2) / norm
                    n2 = (axes[2, 0] * m0 + axes[2, 1] * m1 + axes[2, 2] * m2) / norm
                    mu = -(r0 * n0 + r1 * n1 + r2 * n2)
                    mu0 = n0 * sun[0] + n1 * sun[1] + n2 * sun[2]
                    if mu > 0.0 and mu0 > 0.0:
                        i_over_f[k] = 1.5 * albedo * mu0 if lambert else 2.0 * albedo * mu0 / (mu0 + mu)
            k += 1
    return rays[:k].copy(), solid[:k].copy(), i_over_f[:k].copy()


#: Rays per pixel per axis on the pixels a lit body's limb or terminator crosses (and their
#: neighbours): the light stops there, and a regular sub-grid's coverage error of a pixel is about
#: 1/this of it; elsewhere the shading is smooth and ``supersample`` rays per axis integrate it.
EDGE_SUPERSAMPLE = 32
#: Exact rows per pixel on the pixels only the limb crosses (and their neighbours): each row's
#: stretch on the body solved for, its light integrated by Gauss-Legendre (``_pixel_by_rows``; 0:
#: the ``EDGE_SUPERSAMPLE`` grid there too).
EDGE_ROWS = 16
#: Rays per pixel per axis near the terminator alone (the shading's kink: Lambert's mu0 and
#: Lommel-Seeliger's I/F fall continuously to 0 there).
_TERMINATOR_SUPERSAMPLE = 8
#: A lit body at most this many pixels across is integrated on the edge grid everywhere.
_SMALL_BODY_PX = 12
#: Pixels around the ones the limb or terminator crosses that get the edge grid too (the shading
#: near a limb varies fast across a pixel: Lambert's mu0 ~ sqrt(distance) at zero phase).
_EDGE_DILATION_PX = 1


def body_pixels(
    body: Body,
    camera: Camera,
    R_icrf_cam: Rotation,
    observer: Observer,
    ephemeris,
    *,
    corrections: Corrections = Corrections(),
    supersample: int = 4,
    band_rad: tuple[float, float] | None = None,
    margin_px: int = 0,
) -> tuple[int, int, np.ndarray]:
    """Light of a sunlit ellipsoid integrated over each detector pixel (its rays aligned with the pixels).

    Parameters
    ----------
    body : Body
        Lambert or Lommel-Seeliger (not ``uv-limb``).
    camera, R_icrf_cam, observer, ephemeris, corrections
        As :func:`view_body` (attitude camera -> ICRF; observer SSB state, ICRF km and km/s).
    supersample : int
        Rays per pixel per axis where the shading is smooth; pixels the limb or terminator crosses
        and their neighbours get ``max(supersample, EDGE_SUPERSAMPLE)``, and so does every pixel of
        a body under ``_SMALL_BODY_PX`` across.
    band_rad : (inner, outer), optional
        Only rays between these angles from the body's centre direction (rad; :func:`view_body`).
    margin_px : int
        Pixels beyond the detector's edges that are still integrated (a PSF's reach).

    Returns
    -------
    x0, y0 : int
        Detector column and row of the first pixel of ``rate``.
    rate : (H, W) array
        Electrons per second in each pixel; zeros when the body is off the detector.

    Notes
    -----
    The rays are the pixel's own: each pixel's corners are unprojected (:meth:`Camera.unproject`,
    distortion included) and de-aberrated (apparent -> geometric lines of sight, inverse of
    :func:`opnav.light.aberrate`), and a pixel's ``s x s`` rays are the bilinear interpolation
    of its corners' gnomonic vectors at the sub-pixel centres (exact for a pinhole). Each ray is
    intersected with the ellipsoid and shaded as in :func:`view_body` (its I/F); the pixel's
    rate is the mean I/F times its solid angle (from its corners) times the flux of I/F = pi in
    electrons per second. No ray is binned to a pixel it does not belong to, so the light's
    centre is the body's to the sub-grid's coverage error: the ray grid of :func:`view_body`,
    binned to the nearest pixel, aliased with the pixels (a 100 px disk's light 0.07 px off its
    centre at 4 rays per pixel) and was capped at 2000 rays across. Memory is the patch's pixels,
    not its rays, so no body is too large.
    """
    if body.shading == "uv-limb":
        raise InputError(f"body_pixels renders sunlit bodies; {body.name!r} is uv-limb (view_body integrates it)")
    geo = _geometry(body, observer, ephemeris, corrections)
    r_rel, direction, range_km = geo["r_rel"], geo["direction"], geo["range_km"]
    R_cam_icrf = R_icrf_cam.inv()
    empty = (0, 0, np.zeros((0, 0)))
    # the pixels the outline can reach: a circle of the largest radius (plus 2 px) about the apparent centre
    reach = math.asin(body.extent_km / range_km) + 2.0 * camera.pixel_scale_rad
    helper = np.array([0.0, 0.0, 1.0]) if abs(direction[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = unit(cross3(helper, direction))
    e2 = cross3(direction, e1)
    azimuth = np.linspace(0.0, 2.0 * np.pi, 90, endpoint=False)
    outline = math.cos(reach) * direction + math.sin(reach) * (np.cos(azimuth)[:, None] * e1
                                                               + np.sin(azimuth)[:, None] * e2)
    outline_cam = R_cam_icrf.apply(outline)
    lo_x, lo_y = -margin_px, -margin_px
    hi_x, hi_y = camera.width_px - 1 + margin_px, camera.height_px - 1 + margin_px
    if np.all(outline_cam[:, 2] > 0.0):
        xy = camera.project(outline_cam)
        lo_x, lo_y = max(lo_x, int(math.floor(xy[:, 0].min())) - 1), max(lo_y, int(math.floor(xy[:, 1].min())) - 1)
        hi_x, hi_y = min(hi_x, int(math.ceil(xy[:, 0].max())) + 1), min(hi_y, int(math.ceil(xy[:, 1].max())) + 1)
    if lo_x > hi_x or lo_y > hi_y:
        return empty
    width, height = hi_x - lo_x + 1, hi_y - lo_y + 1
    cx, cy = np.meshgrid(np.arange(lo_x, hi_x + 2) - 0.5, np.arange(lo_y, hi_y + 2) - 0.5)
    corners = camera.unproject(np.column_stack([cx.ravel(), cy.ravel()]))
    if corrections.aberration:
        corners = aberrate(corners, -(R_cam_icrf.as_matrix() @ observer.v_ssb_km_s))  # geometric lines of sight
    corners = corners.reshape(height + 1, width + 1, 3)
    # solid angle of each pixel: its corners' quadrilateral on the unit sphere (diagonals' cross product)
    solid = 0.5 * np.linalg.norm(np.cross(corners[1:, 1:] - corners[:-1, :-1], corners[:-1, 1:] - corners[1:, :-1]),
                                 axis=-1)
    # gnomonic vectors about the boresight (bilinear interpolation of them is exact for a pinhole), body axes
    cam_to_body = geo["axes"].T @ R_icrf_cam.as_matrix()
    gnomonic = corners / corners[..., 2:3]
    size_px = 2.0 * math.asin(body.extent_km / range_km) / camera.pixel_scale_rad
    if body.shape is not None:
        mean_i_over_f = mesh_pixel_means(
            gnomonic @ cam_to_body.T, geo["axes"].T @ (-r_rel), body.shape, geo["axes"].T @ geo["sun_from_body"],
            weights=reflectance_weights(body.shading, body.lunar_lambert_l), albedo=body.geometric_albedo,
            supersample=supersample, size_px=size_px,
            band=None if band_rad is None else (geo["axes"].T @ unit(r_rel), band_rad))
        per_i_over_f = float(electron_rate(SUN_VMAG_1AU, camera)) / math.pi * (AU_KM / np.linalg.norm(geo["r_sun_body"])) ** 2
        return lo_x, lo_y, mean_i_over_f * solid * per_i_over_f
    mean_i_over_f = ellipsoid_pixel_means(
        gnomonic @ cam_to_body.T, geo["axes"].T @ (-r_rel), body.radii_km, geo["axes"].T @ geo["sun_from_body"],
        lambert=body.shading == "lambert", albedo=body.geometric_albedo, supersample=supersample, size_px=size_px,
        band=None if band_rad is None else (geo["axes"].T @ unit(r_rel), band_rad))
    per_i_over_f = float(electron_rate(SUN_VMAG_1AU, camera)) / math.pi * (AU_KM / np.linalg.norm(geo["r_sun_body"])) ** 2
    return lo_x, lo_y, mean_i_over_f * solid * per_i_over_f


def ellipsoid_pixel_means(gnomonic_body: np.ndarray, origin_body_km: np.ndarray, radii_km, sun_body: np.ndarray, *,
                          lambert: bool, albedo: float = 1.0, supersample: int, size_px: float,
                          wanted: np.ndarray | None = None, band=None) -> np.ndarray:
    """Mean I/F over each pixel of a box, on the pixels' own rays (:func:`body_pixels`' integral,
    shared with the image stage's model images so a model and a rendered frame differ only by pose).

    Parameters
    ----------
    gnomonic_body : (H + 1, W + 1, 3) array
        The box's pixel corners as camera-frame lines of sight scaled to unit boresight component
        (``v / v_z``; bilinear interpolation of them is exact for a pinhole), then turned into the
        body's axes. Corner ``[i, j]`` is the top-left corner of pixel ``[i, j]``.
    origin_body_km : (3,) array
        The camera's position in the body's axes, km (body centre at the origin).
    radii_km : (3,) array
        Semi-axes along the body's axes, km.
    sun_body : (3,) array
        Unit vector body -> Sun in the body's axes.
    lambert : bool
        Lambert (else Lommel-Seeliger) shading; ``albedo`` the geometric albedo (1: I/F per unit albedo).
    supersample : int
        Rays per pixel per axis where the shading is smooth; the pixels whose corners disagree
        (on or off the body, lit or not) and their neighbours get ``max(supersample,
        EDGE_SUPERSAMPLE)``, and so does every pixel when ``size_px`` (the body's apparent
        diameter) is at most ``_SMALL_BODY_PX``.
    wanted : (H, W) bool array, optional
        Integrate only these pixels (the others are 0).
    band : (los_body, (inner, outer)), optional
        Only rays between these angles (rad) from the unit vector ``los_body`` (body axes).
    """
    gnomonic_body = np.ascontiguousarray(gnomonic_body, dtype=float)
    h, w = gnomonic_body.shape[0] - 1, gnomonic_body.shape[1] - 1
    wanted = np.ones((h, w), bool) if wanted is None else np.ascontiguousarray(wanted, dtype=bool)
    if band is None:
        los, lo2, hi2 = np.array([0.0, 0.0, 0.0]), -1.0, math.inf
    else:
        los, (inner, outer) = np.asarray(band[0], float), band[1]
        lo2, hi2 = math.tan(inner) ** 2, math.tan(min(outer, 1.5)) ** 2
    return _pixel_light_kernel(gnomonic_body, np.asarray(origin_body_km, float), np.asarray(radii_km, float),
                               np.asarray(sun_body, float), los, bool(lambert), float(albedo), int(supersample),
                               max(int(supersample), EDGE_SUPERSAMPLE), EDGE_ROWS,
                               max(int(supersample), _TERMINATOR_SUPERSAMPLE), _EDGE_DILATION_PX,
                               bool(size_px <= _SMALL_BODY_PX), lo2, hi2, band is not None, wanted)


@kernel
def _pixel_light_kernel(gnomonic, origin, radii, sun, los, lambert, albedo, ss, edge_ss, edge_rows, term_ss, dilation,
                        small, lo2, hi2, banded, wanted):  # pragma: no cover - compiled
    """Mean I/F of each ``wanted`` pixel (H, W) from its corners' gnomonic vectors (H + 1, W + 1, 3; body
    axes): corners first classed (off the body, on it in shadow, lit), the pixels whose corners
    disagree and ``dilation`` around them integrated by ``edge_rows`` exact rows
    (:func:`_pixel_by_rows`) near the limb when no corner is in shadow (``edge_rows`` > 0, not
    ``small``, not ``banded``), else on ``edge_ss`` rays per axis near the limb (a cusp) and
    ``term_ss`` near the terminator alone; the rest on ``ss``; when
    ``banded``, rays outside ``lo2 <= tan^2(angle from los) <= hi2`` carry nothing."""
    hp, wp = gnomonic.shape[0], gnomonic.shape[1]
    h, w = hp - 1, wp - 1
    o0, o1, o2 = origin[0] / radii[0], origin[1] / radii[1], origin[2] / radii[2]
    qc = o0 * o0 + o1 * o1 + o2 * o2 - 1.0
    # the pixels whose class matters: the wanted ones and their neighbours (a band of a large body
    # needs the corners of its own pixels only, not of the whole box)
    need = np.zeros((h, w), np.bool_)
    for i in range(h):
        for j in range(w):
            if wanted[i, j]:
                for di in range(max(i - dilation, 0), min(i + dilation + 1, h)):
                    for dj in range(max(j - dilation, 0), min(j + dilation + 1, w)):
                        need[di, dj] = True
    state = np.full((hp, wp), -1, np.int8)  # 0 off the body, 1 on it in shadow, 2 on it and lit (-1: not needed)
    for i in range(h):
        for j in range(w):
            if not need[i, j]:
                continue
            for ci in range(i, i + 2):
                for cj in range(j, j + 2):
                    if state[ci, cj] < 0:
                        state[ci, cj] = _ray_state(gnomonic[ci, cj, 0], gnomonic[ci, cj, 1], gnomonic[ci, cj, 2],
                                                   origin, radii, sun, o0, o1, o2, qc)
    mixed = np.zeros((h, w), np.bool_)  # an edge (limb or terminator) crosses it or a neighbour
    limbish = np.zeros((h, w), np.bool_)  # the limb (the light's end) crosses it or a neighbour
    for i in range(h):
        for j in range(w):
            if not need[i, j]:
                continue
            s = state[i, j]
            if small or state[i, j + 1] != s or state[i + 1, j] != s or state[i + 1, j + 1] != s:
                off = (s == 0) + (state[i, j + 1] == 0) + (state[i + 1, j] == 0) + (state[i + 1, j + 1] == 0)
                for di in range(max(i - dilation, 0), min(i + dilation + 1, h)):
                    for dj in range(max(j - dilation, 0), min(j + dilation + 1, w)):
                        mixed[di, dj] = True
                        if small or 0 < off < 4:
                            limbish[di, dj] = True
    out = np.zeros((h, w))
    for i in range(h):
        for j in range(w):
            if not wanted[i, j] or (not mixed[i, j] and state[i, j] != 2):
                continue  # not asked for, or all four corners dark and no edge crosses it or a neighbour
            if limbish[i, j] and edge_rows > 0 and not small and not banded and _lit_or_off(state, i, j):
                # integrate across the limb exactly: along rows when it crosses the pixel's top and bottom
                # sides, along columns when it crosses its left and right sides (runs along the rows)
                sides = (state[i, j] != state[i + 1, j]) + (state[i, j + 1] != state[i + 1, j + 1])
                ends = (state[i, j] != state[i, j + 1]) + (state[i + 1, j] != state[i + 1, j + 1])
                out[i, j] = _pixel_by_rows(gnomonic, i, j, edge_rows, sides > ends, origin, radii, sun, o0, o1, o2,
                                           qc, lambert, albedo)
                continue
            # the terminator alone is a kink of the shading, not a step: a moderate grid integrates it
            n = edge_ss if limbish[i, j] else term_ss if mixed[i, j] else ss
            acc = 0.0
            for ky in range(n):
                v = (ky + 0.5) / n
                for kx in range(n):
                    u = (kx + 0.5) / n
                    d0, d1, d2 = subpixel_ray(gnomonic, i, j, u, v)
                    if banded and outside_band(d0, d1, d2, los, lo2, hi2):
                        continue
                    acc += _ray_i_over_f(d0, d1, d2, origin, radii, sun, o0, o1, o2, qc, lambert, albedo)
            out[i, j] = acc / (n * n)
    return out


@kernel
def _lit_or_off(state, i, j):  # pragma: no cover - compiled
    """No corner of pixel (i, j) lies on the body's shadowed side (state 1): only the limb crosses it."""
    return state[i, j] != 1 and state[i, j + 1] != 1 and state[i + 1, j] != 1 and state[i + 1, j + 1] != 1


#: Gauss-Legendre nodes and weights on [0, 1] (4 points): a row's lit stretch integrated exactly to degree 7.
_GL_NODES = np.array([0.0694318442029737, 0.3300094782075719, 0.6699905217924281, 0.9305681557970262])
_GL_WEIGHTS = np.array([0.1739274225687269, 0.3260725774312731, 0.3260725774312731, 0.1739274225687269])


@kernel
def _pixel_by_rows(gnomonic, i, j, rows, columns, origin, radii, sun, o0, o1, o2, qc, lambert,
                   albedo):  # pragma: no cover - compiled
    """Mean I/F of pixel (i, j) crossed by the limb: on each of ``rows`` sub-rows (sub-columns when
    ``columns``) the ray is linear in the fraction u along it (d = P + u Q, bilinear corners), so
    where it meets the ellipsoid is a quadratic's sign (its discriminant ``A u^2 + B u + C``); the
    stretches on the body are found exactly and the I/F integrated over each by 4-point
    Gauss-Legendre. A regular sub-grid quantises each row's stretch to 1/n of the pixel; this
    leaves the midpoint rule across the rows, exact for a straight limb that crosses them (hence
    columns for a limb along the rows)."""
    acc = 0.0
    # corners in the order (start of the first line, its end, start of the last line, its end)
    a00, a01 = gnomonic[i, j], (gnomonic[i + 1, j] if columns else gnomonic[i, j + 1])
    a10, a11 = (gnomonic[i, j + 1] if columns else gnomonic[i + 1, j]), gnomonic[i + 1, j + 1]
    for k in range(rows):
        v = (k + 0.5) / rows
        p0 = (1 - v) * a00[0] + v * a10[0]
        p1 = (1 - v) * a00[1] + v * a10[1]
        p2 = (1 - v) * a00[2] + v * a10[2]
        q0 = (1 - v) * a01[0] + v * a11[0] - p0
        q1 = (1 - v) * a01[1] + v * a11[1] - p1
        q2 = (1 - v) * a01[2] + v * a11[2] - p2
        # scaled to the unit sphere: |o + t s|^2 = 1 meets the ray when (o.s)^2 - |s|^2 qc > 0 (and o.s < 0)
        sp0, sp1, sp2 = p0 / radii[0], p1 / radii[1], p2 / radii[2]
        sq0, sq1, sq2 = q0 / radii[0], q1 / radii[1], q2 / radii[2]
        op = o0 * sp0 + o1 * sp1 + o2 * sp2
        oq = o0 * sq0 + o1 * sq1 + o2 * sq2
        pp = sp0 * sp0 + sp1 * sp1 + sp2 * sp2
        pq = sp0 * sq0 + sp1 * sq1 + sp2 * sq2
        qq = sq0 * sq0 + sq1 * sq1 + sq2 * sq2
        a = oq * oq - qq * qc
        b = 2.0 * (op * oq - pq * qc)
        c = op * op - pp * qc
        cuts = np.empty(4)
        cuts[0] = 0.0
        n_cuts = 1
        if abs(a) > 1e-12 * (abs(b) + abs(c)):
            disc = b * b - 4.0 * a * c
            if disc > 0.0:
                root = math.sqrt(disc)
                q = -0.5 * (b + root if b >= 0.0 else b - root)
                r1, r2 = q / a, (c / q if q != 0.0 else q / a)
                lo, hi = min(r1, r2), max(r1, r2)
                if 0.0 < lo < 1.0:
                    cuts[n_cuts] = lo
                    n_cuts += 1
                if 0.0 < hi < 1.0:
                    cuts[n_cuts] = hi
                    n_cuts += 1
        elif b != 0.0 and 0.0 < -c / b < 1.0:
            cuts[n_cuts] = -c / b
            n_cuts += 1
        cuts[n_cuts] = 1.0
        for m in range(n_cuts):
            u0, u1 = cuts[m], cuts[m + 1]
            mid = 0.5 * (u0 + u1)
            if a * mid * mid + b * mid + c <= 0.0 or op + mid * oq >= 0.0:
                continue  # this stretch misses the body
            part = 0.0
            for g in range(4):
                u = u0 + (u1 - u0) * _GL_NODES[g]
                part += _GL_WEIGHTS[g] * _ray_i_over_f(p0 + u * q0, p1 + u * q1, p2 + u * q2, origin, radii, sun,
                                                       o0, o1, o2, qc, lambert, albedo)
            acc += part * (u1 - u0)
    return acc / rows


@kernel
def _ray_state(d0, d1, d2, origin, radii, sun, o0, o1, o2, qc):  # pragma: no cover - compiled
    """0: the ray (body axes) misses the ellipsoid; 1: it hits where the Sun does not shine; 2: it hits lit."""
    value = _ray_i_over_f(d0, d1, d2, origin, radii, sun, o0, o1, o2, qc, True, 1.0)
    if value > 0.0:
        return 2
    s0, s1, s2 = d0 / radii[0], d1 / radii[1], d2 / radii[2]
    qa = s0 * s0 + s1 * s1 + s2 * s2
    qb = 2.0 * (o0 * s0 + o1 * s1 + o2 * s2)
    return 1 if qb * qb - 4.0 * qa * qc > 0.0 and qb < 0.0 else 0


@kernel
def _ray_i_over_f(d0, d1, d2, origin, radii, sun, o0, o1, o2, qc, lambert, albedo):  # pragma: no cover - compiled
    """I/F the ray ``d`` (body axes, any length) from ``origin`` (body axes, km) sees on the ellipsoid of
    ``radii``: :func:`reflectance` at the hit's incidence and emission cosines, 0 off the body or in shadow."""
    s0, s1, s2 = d0 / radii[0], d1 / radii[1], d2 / radii[2]
    qa = s0 * s0 + s1 * s1 + s2 * s2
    qb = 2.0 * (o0 * s0 + o1 * s1 + o2 * s2)
    disc = qb * qb - 4.0 * qa * qc
    if disc <= 0.0:
        return 0.0
    t = (-qb - math.sqrt(disc)) / (2.0 * qa)
    if t <= 0.0:
        return 0.0
    m0 = (origin[0] + t * d0) / radii[0] ** 2
    m1 = (origin[1] + t * d1) / radii[1] ** 2
    m2 = (origin[2] + t * d2) / radii[2] ** 2
    norm = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2) * math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    mu = -(d0 * m0 + d1 * m1 + d2 * m2) / norm
    mu0 = (m0 * sun[0] + m1 * sun[1] + m2 * sun[2]) / math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    if mu <= 0.0 or mu0 <= 0.0:
        return 0.0
    return 1.5 * albedo * mu0 if lambert else 2.0 * albedo * mu0 / (mu0 + mu)
