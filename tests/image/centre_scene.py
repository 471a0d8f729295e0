"""Frames of one resolved body at a chosen apparent size and phase, rendered by opnav's renderer
(:func:`opnav.render.frame.render_frame`) against a fixed ephemeris: shared by
``tests/image/test_centres*.py`` and ``benchmarks/centre_finding.py``.

The Sun is at the SSB origin, the body 1.5 au from it on +x; the observer sits at the range that
gives the wanted apparent diameter, in the direction that gives the wanted phase angle, and the
camera looks at the body with it placed ``offset_px`` from the principal point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from opnav.bodies import Body
from opnav.camera import Camera
from opnav.constants import AU_KM, MARS_POLAR_RADIUS_KM, PHOBOS_RADII_KM, RADIUS_KM
from opnav.observer import Observer
from opnav.render.detector import DetectorOptions
from opnav.render.frame import RenderOptions, render_frame
from opnav.render.psf import PSF

BODIES = {
    "mars": Body("mars", (RADIUS_KM["mars"], RADIUS_KM["mars"], MARS_POLAR_RADIUS_KM), 0.17, shading="lambert",
                 pole_ra_rad=math.radians(317.681), pole_dec_rad=math.radians(52.887)),
    # the Moon as an ellipsoid (the IAU 2015 mean radii about 1737.4 km; a 2 km flattening)
    "moon": Body("moon", (1738.1, 1737.4, 1736.0), 0.12, shading="lommel-seeliger",
                 pole_ra_rad=math.radians(269.99), pole_dec_rad=math.radians(66.54)),
    "phobos": Body("phobos", PHOBOS_RADII_KM, 0.07, orientation="synchronous"),
}


class FixedEphemeris:
    """Bodies at fixed SSB positions (km, ICRF) with fixed velocities (km/s): what view_body asks."""

    def __init__(self, positions: dict, velocities: dict | None = None):
        self.positions = {k: np.asarray(v, float) for k, v in positions.items()}
        self.velocities = {k: np.asarray(v, float) for k, v in (velocities or {}).items()}

    def state(self, body, t, center="ssb"):
        t = np.asarray(t, float)
        r = self.positions[body] - (self.positions[center] if center != "ssb" else 0.0)
        v = self.velocities.get(body, np.zeros(3)) - (self.velocities.get(center, np.zeros(3)) if center != "ssb" else 0.0)
        shape = t.shape + (3,)
        return np.broadcast_to(r, shape).copy(), np.broadcast_to(v, shape).copy()

    def position(self, body, t, center="ssb"):
        return self.state(body, t, center)[0]


@dataclass(frozen=True)
class Scene:
    image: np.ndarray
    signal_e: np.ndarray
    camera: Camera
    body: Body
    R_icrf_cam: Rotation
    observer: Observer
    ephemeris: FixedEphemeris
    xy_true_px: np.ndarray
    range_true_km: float
    psf_sigma_px: float


def camera_1mp(exposure_s: float = 1.0) -> Camera:
    """1024 x 1024 px, 20 arcsec/px (a 5.7 deg field)."""
    pitch_um = 10.0
    focal_mm = pitch_um * 1e-3 / math.radians(20.0 / 3600.0)
    return Camera(width_px=1024, height_px=1024, focal_length_mm=focal_mm, pixel_pitch_um=pitch_um,
                  exposure_s=exposure_s, read_noise_e=10.0, full_well_e=200000.0, bit_depth=20)


def render_scene(name: str, diameter_px: float, phase_deg: float, *, rng, offset_px=(13.3, -7.6),
                 psf_sigma_px: float = 1.2, peak_e: float = 20000.0, velocity_km_s: float = 0.0,
                 clock_deg: float = 30.0, noise: bool = True, camera: Camera | None = None,
                 supersample: int = 4) -> Scene:
    """A frame of body ``name`` (``BODIES``) ``diameter_px`` across (its largest axis) at phase
    ``phase_deg``, the Sun's direction turned ``clock_deg`` about the line of sight; the exposure
    set so the brightest pixel holds about ``peak_e`` electrons; ``velocity_km_s`` of the observer
    (aberration) across the line of sight. ``supersample``: the renderer's rays per pixel per axis
    where the shading is smooth (:func:`opnav.bodies.body_pixels`)."""
    body = BODIES[name]
    camera = camera or camera_1mp()
    f = camera.focal_length_px
    dist = max(body.radii_km) / math.sin(diameter_px / (2.0 * f))
    r_body = np.array([1.5 * AU_KM, 0.0, 0.0])
    to_sun = -r_body / np.linalg.norm(r_body)
    # observer direction from the body: phase angle away from the Sun, turned by clock about it
    ref = np.array([0.0, 0.0, 1.0])
    perp = np.cross(to_sun, ref)
    perp /= np.linalg.norm(perp)
    perp = Rotation.from_rotvec(to_sun * math.radians(clock_deg)).apply(perp)
    phase = math.radians(phase_deg)
    w = math.cos(phase) * to_sun + math.sin(phase) * perp
    r_obs = r_body + dist * w
    positions = {"sun": np.zeros(3), name: r_body}
    velocities = {}
    if name == "phobos":  # synchronous: Mars 9378 km along -x of Phobos, orbit normal +z
        positions["mars"] = r_body + np.array([0.0, 9378.0, 0.0])
        velocities = {"phobos": np.array([2.14, 0.0, 0.0]), "mars": np.zeros(3)}
    eph = FixedEphemeris(positions, velocities)
    v_obs = velocity_km_s * np.cross(w, np.array([0.0, 1.0, 0.0]))
    observer = Observer(0.0, r_obs, v_obs)
    boresight = -w
    # point the camera so the body lands offset_px from the principal point
    up = np.cross(boresight, np.array([0.0, 0.0, 1.0]))
    up /= np.linalg.norm(up)
    side = np.cross(boresight, up)
    R0 = Rotation.from_matrix(np.column_stack([up, side, boresight]))  # camera -> ICRF
    tilt = Rotation.from_rotvec([-offset_px[1] / f, offset_px[0] / f, 0.0])
    R_icrf_cam = R0 * tilt.inv()
    options = RenderOptions(psf=PSF(sigma_px=psf_sigma_px), detector=DetectorOptions(noise_free=True),
                            sun_keepout_margin_rad=0.0)
    probe = render_frame(camera, R_icrf_cam, observer, targets=[body], ephemeris=eph, options=options)
    exposure = camera.exposure_s * peak_e / max(float(probe.signal_e.max()), 1e-9)
    camera = replace(camera, exposure_s=exposure)
    options = RenderOptions(psf=PSF(sigma_px=psf_sigma_px), detector=DetectorOptions(noise_free=not noise),
                            sun_keepout_margin_rad=0.0, supersample=supersample)
    out = render_frame(camera, R_icrf_cam, observer, targets=[body], ephemeris=eph, options=options,
                       rng=rng if noise else None)
    truth = out.truth.target(name)
    return Scene(image=np.asarray(out.image, float), signal_e=np.asarray(out.signal_e, float), camera=camera, body=body, R_icrf_cam=R_icrf_cam,
                 observer=observer, ephemeris=eph, xy_true_px=np.asarray(truth.xy_cof_px, float),
                 range_true_km=float(truth.range_km), psf_sigma_px=psf_sigma_px)
