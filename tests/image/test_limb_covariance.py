"""The limb fit's covariance describes its own frame's noise: the scan lines' direction is not set by
the noise (zero phase), and a line read next to the detector's edge is modelled with the light the
PSF brings in from beyond it."""

import math

import numpy as np
from scipy.spatial.transform import Rotation

from centre_scene import camera_1mp, render_scene
from opnav.camera import Camera
from opnav.image.centres import body_pose
from opnav.image.correlate import DetectorNoise
from opnav.image.limb import fit_limb_ellipsoid, limb_offsets, scan_lines, usable_lines
from opnav.render.detector import DetectorOptions, read_out


def _noise(camera):
    return DetectorNoise(camera.read_noise_e, camera.gain_e_per_adu, camera.bias_adu)


def _major_axis_deg(cov):
    values, vectors = np.linalg.eigh(cov)
    v = vectors[:, np.argmax(values)]
    return math.degrees(math.atan2(v[1], v[0])) % 180.0


def test_at_zero_phase_the_lines_do_not_turn_with_the_frame_s_noise():
    """A full Mars 100 px across: the Sun is on the line of sight, so the image's illumination
    direction is the small angle between the Sun and the pose's line of sight. Set from each pass's
    own estimate it pointed along that estimate's error, and so did the covariance's long axis
    (along the lines): the error looked small against it (scatter/sigma 0.76 over 50 frames at
    300 px). From the given pose, the same prior on six noisy frames gives one covariance
    orientation, whatever each frame's noise."""
    scene = render_scene("mars", 100, 0, rng=None, noise=False)
    cam = scene.camera
    truth = body_pose(scene.body, scene.R_icrf_cam, scene.observer, scene.ephemeris)
    f = cam.focal_length_px
    prior = truth.at(Rotation.from_rotvec([0.7 / f, -0.5 / f, 0.0]).apply(truth.r_cam_km) * 1.004)
    angles = []
    for k in range(6):
        image = np.asarray(read_out(scene.signal_e, cam, options=DetectorOptions(), rng=np.random.default_rng([3, k])),
                           float)
        fit = fit_limb_ellipsoid(image, cam, prior, psf_sigma_px=scene.psf_sigma_px, noise=_noise(cam))
        angles.append(_major_axis_deg(fit.cov_xy_px2))
    eig = np.linalg.eigvalsh(fit.cov_xy_px2)
    assert eig[1] > 2.0 * eig[0]  # elongated: an orientation to compare
    spread = np.ptp(np.unwrap(np.radians(angles), period=np.pi))
    assert math.degrees(spread) < 1.0, angles


def test_lines_next_to_the_detector_edge_are_modelled_with_the_light_from_beyond_it():
    """Mars 330 px across on a 256 px detector, its lit limb leaving the frame at the top and bottom
    rows: on the noise-free frame at the true pose every line the fit may read, the ones a row from
    the edge included, finds the model's limb where the frame's is (within 0.005 px). A model tile
    cut at the detector's edge lacked the light the PSF spreads onto the edge pixels from the
    body's image beyond it: a line one row from the edge was 0.44 px off."""
    base = camera_1mp()
    cam = Camera(width_px=256, height_px=256, focal_length_mm=base.focal_length_mm,
                 pixel_pitch_um=base.pixel_pitch_um, exposure_s=1.0, read_noise_e=10.0, full_well_e=200000.0,
                 bit_depth=20)
    scene = render_scene("mars", 330, 30, rng=None, noise=False, camera=cam, offset_px=(-100.0, 0.0), clock_deg=0.0)
    pose = body_pose(scene.body, scene.R_icrf_cam, scene.observer, scene.ephemeris)
    scan = scan_lines(scene.camera, pose, psf_sigma_px=scene.psf_sigma_px)
    offsets = limb_offsets(scene.image, scan, _noise(scene.camera))
    use = usable_lines(scan) & offsets.ok
    samples = scan.start_xy[use, None, :] + (scan.a_pred_px[use, None, None] + scan.a_px[None, :, None]) * scan.dir_xy[0]
    edge_gap = np.minimum(samples[..., 1].min(1), scene.camera.height_px - 1 - samples[..., 1].max(1))
    assert use.sum() >= 40 and edge_gap.min() < 2.0  # lines within the PSF's reach of the edge are read
    assert np.max(np.abs(offsets.delta_px[use])) < 0.005, offsets.delta_px[use][np.argsort(edge_gap)[:5]]
