"""Model images of an ellipsoid (:mod:`opnav.image.ellipsoid`): the pixels they integrate."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from centre_scene import camera_1mp, render_scene

from opnav.bodies import ellipsoid_pixel_means
from opnav.image.centres import body_pose
from opnav.image.ellipsoid import lit_mask, outline_box

DISTORTED = replace(camera_1mp(), k1=-0.2, k2=0.05, p1=1e-3)


@pytest.mark.parametrize("name, diameter, phase, distorted", [
    ("moon", 8, 0, False), ("mars", 40, 45, False), ("phobos", 10, 120, False), ("mars", 40, 90, False),
    ("phobos", 40, 150, True), ("moon", 60, 176, False), ("mars", 8, 165, True)])
def test_every_pixel_with_light_is_in_the_lit_mask(name, diameter, phase, distorted):
    """Every pixel of the box that the pixels' own rays (the renderer's integral, no mask) find light in
    lies in :func:`lit_mask`, from a full disk to a crescent thinner than a pixel (the 60 px Moon at
    176 deg: 0.07 px at its widest), on a pinhole and a distorted camera far off its centre; and past
    a quarter phase the mask leaves out at least a third of the outline's box (the night side)."""
    camera = DISTORTED if distorted else camera_1mp()
    offset = (400.3, -350.7) if distorted else (13.3, -7.6)
    scene = render_scene(name, diameter, phase, rng=None, noise=False, camera=camera, offset_px=offset)
    pose = body_pose(scene.body, scene.R_icrf_cam, scene.observer, scene.ephemeris)
    box = outline_box(camera, pose, 3.0)
    x0, y0, w, h = box
    cx, cy = np.meshgrid(np.arange(x0, x0 + w + 1) - 0.5, np.arange(y0, y0 + h + 1) - 0.5)
    corners = camera.unproject(np.column_stack([cx.ravel(), cy.ravel()])).reshape(h + 1, w + 1, 3)
    rot = pose.R_cam_body
    size_px = 2.0 * math.asin(float(np.max(pose.radii_km)) / float(np.linalg.norm(pose.r_cam_km))) \
        * camera.focal_length_px
    light = ellipsoid_pixel_means((corners / corners[..., 2:3]) @ rot, -pose.r_cam_km @ rot, pose.radii_km,
                                  pose.sun_cam @ rot, lambert=True, supersample=4, size_px=size_px)
    mask = lit_mask(camera, pose, box)
    assert np.count_nonzero(light) > 0
    assert not np.any((light > 0) & ~mask)
    if phase > 90:
        assert mask.mean() < 2.0 / 3.0
