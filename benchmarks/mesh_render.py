"""Mesh bodies: render and centre-finding time of the shipped small body (opnav/data/asteroid.obj, 5,120
triangles) beside an ellipsoid of its half extents, at a few apparent sizes; and the correlation
centre's error on noise-free frames at a few phases.

Run: .venv/bin/python benchmarks/mesh_render.py   (the first call of each kernel compiles or loads it:
a warm-up render runs first; times are medians of 3 and depend on the machine's load, printed beside them)
"""

from __future__ import annotations

import math
import os
import time

import numpy as np
from scipy.spatial.transform import Rotation

from opnav.bodies import Body
from opnav.camera import Camera
from opnav.image.correlate import DetectorNoise
from opnav.image.mesh_centre import correlate_mesh_centre, mesh_pose
from opnav.observer import Corrections, Observer
from opnav.render import DetectorOptions, RenderOptions, render_frame
from opnav.shape import read_obj, shipped_shape

NOISE_FREE = RenderOptions(detector=DetectorOptions(noise_free=True), corrections=Corrections())


class _Static:
    """The Sun at the SSB, the body at 1.25 au on +x."""

    def __init__(self):
        self.body = np.array([1.25 * 1.495978707e8, 0.0, 0.0])

    def position(self, name, t, *, center="ssb"):
        return self.body.copy() if name == "ball" else np.zeros(3)

    def state(self, name, t, *, center="ssb"):
        return self.position(name, t), np.zeros(3)


def _scene(phase_rad: float, range_km: float):
    eph = _Static()
    to_observer = np.array([-math.cos(phase_rad), math.sin(phase_rad), 0.0])
    r_obs = eph.body + range_km * to_observer
    z = -to_observer
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    attitude = Rotation.from_matrix(np.column_stack([x, np.cross(z, x), z])) * Rotation.from_rotvec([1e-4, -2e-4, 0.3])
    return eph, Observer(0.0, r_obs, np.array([3.0, 20.0, -1.0])), attitude


def _median_time(fn, repeats=3):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times)), out


def main() -> None:
    mesh = read_obj(shipped_shape())
    camera = Camera.from_fov(2.0, 1024, 1024, exposure_s=2e-6)
    shaped = Body("ball", mesh.half_extents_km(), 0.15, shading="lunar-lambert", shape=mesh, pole_ra_rad=0.4,
                  pole_dec_rad=0.5)
    plain = Body("ball", mesh.half_extents_km(), 0.15, shading="lommel-seeliger", pole_ra_rad=0.4, pole_dec_rad=0.5)
    eph, observer, attitude = _scene(0.8, 3000.0)
    render_frame(camera, attitude, observer, targets=[shaped], ephemeris=eph, options=NOISE_FREE)  # warm-up
    print(f"load average {os.getloadavg()[0]:.2f}; camera 1024 px, 2 deg; phase 0.8 rad")
    print(f"{'range km':>10} {'diameter px':>12} {'mesh s':>8} {'ellipsoid s':>12} {'ratio':>6}")
    for range_km in (1.0e5, 2.0e4, 5.0e3, 2.0e3, 1.0e3):
        eph, observer, attitude = _scene(0.8, range_km)
        diameter = 2.0 * mesh.bounding_radius_km / range_km / camera.pixel_scale_rad
        t_mesh, _ = _median_time(lambda: render_frame(camera, attitude, observer, targets=[shaped], ephemeris=eph,
                                                      options=NOISE_FREE))
        t_plain, _ = _median_time(lambda: render_frame(camera, attitude, observer, targets=[plain], ephemeris=eph,
                                                       options=NOISE_FREE))
        print(f"{range_km:10.0f} {diameter:12.1f} {t_mesh:8.3f} {t_plain:12.3f} {t_mesh / t_plain:6.1f}")
    print("correlation centre on noise-free frames (prior 0.5 km off at 2,000 km), error px:")
    noise = DetectorNoise(camera.read_noise_e, camera.gain_e_per_adu, camera.bias_adu)
    for phase in (0.2, 0.8, 1.4, 2.0):
        eph, observer, attitude = _scene(phase, 2000.0)
        frame = render_frame(camera, attitude, observer, targets=[shaped], ephemeris=eph, options=NOISE_FREE)
        prior = Observer(0.0, observer.r_ssb_km + np.array([0.0, 0.3, -0.4]), observer.v_ssb_km_s)
        image = frame.signal_e / camera.gain_e_per_adu + camera.bias_adu
        t_fit, fit = _median_time(lambda: correlate_mesh_centre(image, camera, mesh_pose(shaped, attitude, prior, eph),
                                                                psf_sigma_px=1.0, noise=noise), repeats=1)
        error = fit.xy_px - frame.truth.target("ball").xy_cof_px
        print(f"  phase {phase:.1f} rad: error ({error[0]:+.4f}, {error[1]:+.4f}) px, reported sigma "
              f"{math.sqrt(fit.cov_xy_px2[0, 0]):.4f} px, {t_fit:.2f} s")


if __name__ == "__main__":
    main()
