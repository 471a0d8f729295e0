"""Extended bodies: tri-axial ellipsoids lit by the Sun, and the Earth's UV disk.

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
   (default 8 km, the scale height of the upper stratosphere).
6. Ray directions are aberrated with the observer's SSB velocity
   (:func:`opnav.light.aberrate`) and projected; their flux-weighted mean pixel
   position is the photocentre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from .camera import Camera
from .constants import AU_KM, DEIMOS_RADII_KM, MARS_POLAR_RADIUS_KM, PHOBOS_RADII_KM, RADIUS_KM
from .errors import InputError
from .frames import angle_between, radec_to_unit, unit, unit_to_radec
from .light import aberrate, light_time_vector
from .photometry import electron_rate, reflected_magnitude
from .observer import Corrections, Observer

_SHADINGS = ("lommel-seeliger", "lambert", "uv-limb")
_ORIENTATIONS = ("synchronous", "pole")
_MIN_SAMPLES_ACROSS = 48
#: Memory guard: a very large disk (the Earth filling a wide-field sensor) gets at most this many rays across.
_MAX_SAMPLES_ACROSS = 2000


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
    shading : {"lommel-seeliger", "lambert", "uv-limb"}
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


def body_axes_icrf(body: Body, t_emit: float, ephemeris) -> np.ndarray:
    """Columns = body x, y, z axes in ICRF at the emission epoch (3, 3)."""
    if body.orientation == "synchronous":
        r, v = ephemeris.state(body.name, t_emit, center=body.primary)
        x = -unit(r)
        z = unit(np.cross(r, v))
        return np.column_stack([x, np.cross(z, x), z])
    z = radec_to_unit(body.pole_ra_rad, body.pole_dec_rad)
    helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = unit(np.cross(helper, z))
    return np.column_stack([x, np.cross(z, x), z])


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
        Rays per pixel per axis for resolved bodies.
    """
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
    range_km = float(np.linalg.norm(r_rel))
    r_sun_body = np.asarray(ephemeris.position(body.name, t_emit), dtype=float) - np.asarray(ephemeris.position("sun", t_emit), dtype=float)
    sun_from_body = -unit(r_sun_body)
    phase = float(angle_between(sun_from_body, -r_rel))
    extent_km = max(body.radii_km) + (body.limb_altitude_km + 8.0 * body.limb_scale_height_km if body.shading == "uv-limb" else 0.0)
    if extent_km >= range_km:
        raise InputError(f"observer is inside or on target {body.name!r} (range {range_km:.1f} km)")
    angular_radius = math.asin(max(body.radii_km) / range_km)

    rays_dir, solid_angle = _ray_grid(r_rel, math.asin(extent_km / range_km), camera.pixel_scale_rad / supersample)
    axes = body_axes_icrf(body, t_emit, ephemeris)
    origin_body = axes.T @ (-r_rel)
    dirs_body = rays_dir @ axes
    hit, normal_body = _ellipsoid_hits(origin_body, dirs_body, np.asarray(body.radii_km))

    if body.shading == "uv-limb":
        # Closest approach of each ray to the centre; rays that hit count as altitude <= 0.
        closest = np.linalg.norm(np.cross(-r_rel, rays_dir), axis=-1)
        altitude = np.where(hit, -1.0, closest - body.radii_km[0])
        radiance = body.uv_radiance_e_s_px * np.exp(-np.clip(altitude - body.limb_altitude_km, 0.0, None) / body.limb_scale_height_km)
        rate = radiance * solid_angle / camera.pixel_scale_rad**2
        keep = rate > 1e-9 * body.uv_radiance_e_s_px
        vmag = None
    else:
        normal = normal_body @ axes.T
        mu = -np.sum(rays_dir * normal, -1)
        mu0 = normal @ sun_from_body
        keep = hit & (mu > 0.0) & (mu0 > 0.0)
        i_over_f = np.zeros(rays_dir.shape[0])
        i_over_f[keep] = reflectance(mu0[keep], mu[keep], body.shading, body.geometric_albedo)
        flux_ratio = i_over_f / math.pi * (AU_KM / np.linalg.norm(r_sun_body)) ** 2 * solid_angle
        total = float(np.sum(flux_ratio))
        vmag = float(reflected_magnitude(total)) if total > 0 else None
        rate = flux_ratio / total * float(electron_rate(vmag, camera)) if vmag is not None else np.zeros_like(flux_ratio)
    apparent_rays = aberrate(rays_dir[keep], observer.v_ssb_km_s) if corrections.aberration else rays_dir[keep]
    R_cam_icrf = R_icrf_cam.inv()
    xy = camera.project(R_cam_icrf.apply(apparent_rays))
    rate = rate[keep]
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
        rays=BodyRays(xy_px=xy, electrons_s=rate),
    )


def reproject_view(view: BodyView, camera: Camera, R_icrf_cam: Rotation, new_camera: Camera,
                   new_R_icrf_cam: Rotation) -> BodyView:
    """``view`` (made with ``camera`` at attitude ``R_icrf_cam``) as ``new_camera`` at ``new_R_icrf_cam`` sees it.

    The body's apparent directions do not depend on the camera, so a new attitude or a crop
    of the detector (a camera whose principal point moved) only moves the pixels: each is
    unprojected with the old camera and attitude and projected with the new ones.
    """
    def move(xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=float)
        if not xy.size:
            return xy.copy()
        icrf = R_icrf_cam.apply(camera.unproject(xy.reshape(-1, 2)))
        return new_camera.project(new_R_icrf_cam.inv().apply(icrf)).reshape(xy.shape)

    return replace(view, xy_cof_px=move(view.xy_cof_px), xy_photocentre_px=move(view.xy_photocentre_px),
                   rays=BodyRays(xy_px=move(view.rays.xy_px), electrons_s=view.rays.electrons_s))


def _ray_grid(r_rel: np.ndarray, half_angle_rad: float, spacing_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions (M, 3) and their solid angles (M,) covering a cone around ``r_rel``."""
    los = unit(r_rel)
    helper = np.array([0.0, 0.0, 1.0]) if abs(los[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = unit(np.cross(helper, los))
    e2 = np.cross(los, e1)
    half = math.tan(half_angle_rad) * 1.02
    step = max(min(spacing_rad, 2.0 * half / _MIN_SAMPLES_ACROSS), 2.0 * half / _MAX_SAMPLES_ACROSS)
    n = int(math.ceil(2.0 * half / step))
    g = (np.arange(n) - (n - 1) / 2.0) * step
    a, b = np.meshgrid(g, g)
    a, b = a.ravel(), b.ravel()
    inside = a * a + b * b <= half * half
    a, b = a[inside], b[inside]
    rays = los + a[:, None] * e1 + b[:, None] * e2
    scale = 1.0 + a * a + b * b
    return rays / np.sqrt(scale)[:, None], step * step / scale**1.5
