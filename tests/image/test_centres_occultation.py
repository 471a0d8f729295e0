"""Bodies in front of bodies: overlapping or nearly touching outlines are predicted, with the
nearer and farther body told apart."""

import numpy as np
import pytest

from opnav.camera import Camera
from opnav.errors import InputError
from opnav.image.ellipsoid import EllipsoidPose
from opnav.image.occultation import conflicts

CAMERA = Camera(width_px=1024, height_px=1024, focal_length_mm=20.0, pixel_pitch_um=10.0)  # 2000 px focal length
F = CAMERA.focal_length_px


def _pose(radii, r_cam):
    return EllipsoidPose(radii_km=np.asarray(radii, float), R_cam_body=np.eye(3), r_cam_km=np.asarray(r_cam, float),
                         sun_cam=np.array([1.0, 0.0, -1.0]))


MARS = _pose((3396.2, 3396.2, 3376.2), (0.0, 0.0, 60000.0))  # 113 px in radius at the principal point
MARS_RADIUS_PX = 3396.2 / 60000.0 * F


def _phobos_at(gap_px: float, range_km: float = 9000.0):
    """Phobos (13 x 11 x 9 km, ~3 px across at 9000 km) along +x, its near edge ``gap_px`` beyond Mars'
    limb (negative: over the disk)."""
    x_px = MARS_RADIUS_PX + gap_px + 13.0 / range_km * F
    return _pose((13.0, 11.4, 9.1), (x_px / F * range_km, 0.0, range_km))


def test_phobos_across_mars_occults_it_and_transits():
    found = {c.flag for c in conflicts(CAMERA, {"mars": MARS, "phobos": _phobos_at(-20.0)})}
    assert found == {"mars_occulted_by_phobos", "phobos_transits_mars"}


def test_phobos_behind_mars_is_occulted_by_it():
    hidden = _phobos_at(-20.0, range_km=90000.0)
    found = {c.flag for c in conflicts(CAMERA, {"mars": MARS, "phobos": hidden})}
    assert found == {"phobos_occulted_by_mars", "mars_transits_phobos"}


@pytest.mark.parametrize("gap_px, expected", [(5.0, {"phobos_in_glare_of_mars", "mars_in_glare_of_phobos"}),
                                              (30.0, set())])
def test_a_moon_near_the_limb_is_in_its_glare_and_one_far_off_is_not(gap_px, expected):
    found = {c.flag for c in conflicts(CAMERA, {"mars": MARS, "phobos": _phobos_at(gap_px)}, margin_px=10.0)}
    assert found == expected


def test_margin_must_not_be_negative():
    with pytest.raises(InputError, match="margin_px"):
        conflicts(CAMERA, {"mars": MARS}, margin_px=-1.0)
