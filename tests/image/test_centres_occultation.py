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


def _mars_and_phobos(lateral_mars_radii: float, rng):
    """A rendered 100 px Mars at 40 deg phase with Phobos 9378 km in front of it toward the camera,
    ``lateral_mars_radii`` Mars radii off the line of sight across it (0.3: over the disk; 3: beside it)."""
    import math

    from centre_scene import BODIES, FixedEphemeris, camera_1mp
    from scipy.spatial.transform import Rotation

    from opnav.constants import AU_KM
    from opnav.observer import Observer
    from opnav.render.detector import DetectorOptions
    from opnav.render.frame import RenderOptions, render_frame
    from opnav.render.psf import PSF

    camera = camera_1mp(exposure_s=1.5e-4)  # the disk's brightest pixel near 20,000 e-
    mars, phobos = BODIES["mars"], BODIES["phobos"]
    r_mars = np.array([1.5 * AU_KM, 0.0, 0.0])
    dist = mars.radii_km[0] / math.sin(50.0 / camera.focal_length_px)
    phase = math.radians(40.0)
    w = np.array([-math.cos(phase), math.sin(phase), 0.0])  # Mars -> observer
    r_obs = r_mars + dist * w
    across = np.cross(w, [0.0, 0.0, 1.0])
    r_phobos = r_mars + 9378.0 * w + lateral_mars_radii * mars.radii_km[0] * across
    eph = FixedEphemeris({"sun": np.zeros(3), "mars": r_mars, "phobos": r_phobos},
                         {"phobos": 2.14 * np.array([0.0, 0.0, 1.0]), "mars": np.zeros(3)})
    z = -w
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    R = Rotation.from_matrix(np.column_stack([x, np.cross(z, x), z]))
    observer = Observer(0.0, r_obs, np.zeros(3))
    options = RenderOptions(psf=PSF(sigma_px=1.2), detector=DetectorOptions(), sun_keepout_margin_rad=0.0)
    frame = render_frame(camera, R, observer, targets=[mars, phobos], ephemeris=eph, options=options, rng=rng)
    return frame, camera, R, observer, eph


@pytest.mark.parametrize("lateral, blocked", [(0.3, True), (3.0, False)])
def test_phobos_across_a_rendered_mars_is_skipped_with_its_reason_never_fitted(lateral, blocked):
    """The image stage (``centre_finding="by_size"``) on a frame where Phobos crosses Mars' disk gives
    no record of either body and says why in the frame's flags; with Phobos well beside the disk
    Mars is measured as usual (and its flags name no conflict)."""
    from opnav.image.pipeline import FrameInput, PipelineOptions, measure_sources, target_records, _target_views

    frame, camera, R, observer, eph = _mars_and_phobos(lateral, np.random.default_rng(7))
    assert {t.name for t in frame.truth.targets} == {"mars", "phobos"}
    image = FrameInput.from_camera(np.asarray(frame.image, float), camera, 0.0, R, observer)
    options = PipelineOptions(targets=("mars", "phobos"), centre_finding="by_size", prior_sigma_rad=1e-9)
    views = _target_views(image, eph, options, "test")
    found = measure_sources(image, options)
    flags: list[str] = []
    records = target_records(image, views, found, np.zeros(len(found.det), bool), R, np.eye(3) * 1e-18, None, eph,
                             options, None, "test", flags, psf_sigma_px=1.2)
    mars_records = [r for r in records if r.target == "mars"]
    if blocked:
        assert not records
        assert {"no_mars", "no_phobos", "mars_occulted_by_phobos", "phobos_transits_mars"} <= set(flags)
    else:
        assert not any("occulted" in f or "transits" in f or "glare" in f for f in flags)
        assert {r.kind for r in mars_records} == {"radec", "target_vector"}
        truth = frame.truth.target("mars").xy_cof_px
        vector = next(r for r in mars_records if r.kind == "target_vector")
        xy = camera.project(R.inv().apply(np.array(vector.value, float)))
        assert np.hypot(*(xy - truth)) < 0.1
