"""Centres of a mesh body: cross-correlation with the mesh's template on rendered frames (bias and
scatter against the truth, scatter against the reported covariance), and far out the photocentre moved
by the mesh's predicted offset."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "render"))
from render_helpers import sphere_at_phase  # noqa: E402

from opnav.camera import Camera  # noqa: E402
from opnav.errors import InputError, NoSolutionError  # noqa: E402
from opnav.image.centres import CentreOptions  # noqa: E402
from opnav.image.centroid import centroid  # noqa: E402
from opnav.image.correlate import DetectorNoise  # noqa: E402
from opnav.image.mesh_centre import (correlate_mesh_centre, find_point_source, measure_mesh_centre,  # noqa: E402
                                     mesh_pose, point_centre)
from opnav.render import Body, DetectorOptions, Observer, RenderOptions, render_frame  # noqa: E402
from opnav.render.detector import read_out  # noqa: E402
from opnav.shape import read_obj, shipped_shape  # noqa: E402

CLEAN = DetectorOptions(hot_pixel_fraction=0.0, cosmic_ray_rate_cm2_s=0.0)


def _pointing_at(direction):
    z = direction / np.linalg.norm(direction)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    return Rotation.from_matrix(np.column_stack([x, np.cross(z, x), z]))


def _scene(phase, distance_km, exposure_s):
    """The shipped body (spinning, lunar-Lambert) at ``phase`` from ``distance_km``, seen by a 256 px,
    2-degree camera moving at 13 km/s (aberration on), light time on; its noise-free frame."""
    mesh = read_obj(shipped_shape())
    body = Body("ball", mesh.half_extents_km(), 0.15, shading="lunar-lambert", shape=mesh, pole_ra_rad=0.4,
                pole_dec_rad=0.5, rotation_rate_rad_s=2e-4)
    camera = Camera.from_fov(2.0, 256, 256, exposure_s=exposure_s)
    ephem, r_obs = sphere_at_phase(phase, distance_km=distance_km)
    attitude = _pointing_at(ephem.positions["ball"] - r_obs) * Rotation.from_rotvec([3e-4, -2e-4, 0.2])
    observer = Observer(100.0, r_obs, np.array([5.0, 12.0, -3.0]))
    frame = render_frame(camera, attitude, observer, targets=[body], ephemeris=ephem,
                         options=RenderOptions(detector=DetectorOptions(noise_free=True)))
    return body, camera, ephem, attitude, observer, frame


@pytest.mark.parametrize("phase", [0.4, 1.3])
def test_mesh_correlation_centre_is_unbiased_and_its_covariance_holds(phase):
    """The body 27 px across (700 km), its peak ~2,000 e-, the prior 0.3 km off across the line of
    sight (~3 px): over 10 noise draws the centre's mean error lies within 4 sigma of the mean, and
    the errors normalised by each fit's covariance give a chi-square (20 dof) inside its 0.1-99.9 %
    interval."""
    body, camera, ephem, attitude, observer, frame = _scene(phase, 700.0, 5e-6)
    truth = frame.truth.target("ball").xy_cof_px
    prior = Observer(observer.t_tdb_s, observer.r_ssb_km + np.array([0.0, 0.2, -0.25]), observer.v_ssb_km_s)
    pose = mesh_pose(body, attitude, prior, ephem)
    assert np.hypot(*(camera.project(pose.r_cam_km) - truth)) > 2.0
    noise = DetectorNoise(camera.read_noise_e, camera.gain_e_per_adu, camera.bias_adu)
    rng = np.random.default_rng(38)
    errors, covs = [], []
    for _ in range(10):
        image = read_out(frame.signal_e, camera, options=CLEAN, rng=rng)
        fit = correlate_mesh_centre(image, camera, pose, psf_sigma_px=1.0, noise=noise)
        errors.append(fit.xy_px - truth)
        covs.append(fit.cov_xy_px2)
    errors, covs = np.array(errors), np.array(covs)
    mean_cov = covs.mean(0) / len(errors)
    bias = errors.mean(0)
    assert float(bias @ np.linalg.solve(mean_cov, bias)) < stats.chi2.ppf(0.99994, 2)  # 4 sigma in 2-D
    chi2 = sum(float(e @ np.linalg.solve(c, e)) for e, c in zip(errors, covs))
    assert stats.chi2.ppf(0.001, 2 * len(errors)) < chi2 < stats.chi2.ppf(0.999, 2 * len(errors))
    assert np.sqrt(np.max(np.linalg.eigvalsh(covs.mean(0)))) < 0.05  # a resolved body's centre to hundredths of a px


def _radec_within(record, truth, n_sigma=5.0):
    ra, dec = record.value
    sigma = np.sqrt(np.diag(record.covariance))
    return abs((ra - truth.ra_rad + np.pi) % (2 * np.pi) - np.pi) < n_sigma * sigma[0] and abs(dec - truth.dec_rad) < n_sigma * sigma[1]


def test_measure_mesh_centre_gives_the_radec_record_near_and_far():
    """Resolved (27 px): cross-correlation; far (0.9 px): the point source of the body's predicted
    brightness; each record's RA/Dec within 5 sigma of the truth's apparent direction; an empty frame
    far out is no record."""
    body, camera, ephem, attitude, observer, frame = _scene(0.8, 700.0, 5e-6)
    image = read_out(frame.signal_e, camera, options=CLEAN, rng=np.random.default_rng(3))
    noise = DetectorNoise(camera.read_noise_e, camera.gain_e_per_adu, camera.bias_adu)
    common = dict(R_icrf_cam=attitude, cov_att_rad2=np.eye(3) * 1e-14, observer=observer, ephemeris=ephem,
                  psf_sigma_px=1.0, noise=noise, t_tdb_s=observer.t_tdb_s)
    got = measure_mesh_centre(image, camera, body, **common)
    assert got.method == "correlation" and [r.kind for r in got.records] == ["radec"]
    assert _radec_within(got.records[0], frame.truth.target("ball"))
    with pytest.raises(InputError, match="no limb fit"):
        measure_mesh_centre(image, camera, body, options=CentreOptions(method="limb"), **common)

    body, camera, ephem, attitude, observer, frame = _scene(1.3, 3.0e4, 0.005)
    truth = frame.truth.target("ball")
    far = dict(common, observer=observer, ephemeris=ephem, R_icrf_cam=attitude, t_tdb_s=observer.t_tdb_s)
    got = measure_mesh_centre(read_out(frame.signal_e, camera, options=CLEAN, rng=np.random.default_rng(4)), camera,
                              body, **far)
    assert got.method == "point" and np.hypot(*(got.fit.xy_px - truth.xy_cof_px)) < 0.2
    assert _radec_within(got.records[0], truth)
    with pytest.raises(NoSolutionError, match="no point source"):
        measure_mesh_centre(read_out(frame.signal_e * 0.0, camera, options=CLEAN, rng=np.random.default_rng(5)),
                            camera, body, **far)


def test_the_point_source_search_takes_the_body_s_brightness_not_the_nearest_star():
    """A star 4x brighter than the far body 6 px from it, the prediction 60 % of the way to the star: the
    search takes the source of the body's predicted flux, not the nearer peak."""
    body, camera, ephem, attitude, observer, frame = _scene(1.3, 3.0e4, 0.005)
    truth = frame.truth.target("ball")
    signal = frame.signal_e.copy()
    yy, xx = np.mgrid[0:signal.shape[0], 0:signal.shape[1]]
    star = truth.xy_photocentre_px + np.array([4.8, -3.6])
    signal += 4.0 * truth.electrons / (2 * np.pi) * np.exp(-0.5 * ((xx - star[0]) ** 2 + (yy - star[1]) ** 2))
    image = read_out(signal, camera, options=CLEAN, rng=np.random.default_rng(6))
    noise = DetectorNoise(camera.read_noise_e, camera.gain_e_per_adu, camera.bias_adu)
    predicted = truth.xy_photocentre_px + 0.6 * (star - truth.xy_photocentre_px)
    xy, cov = find_point_source(image, camera, predicted, truth.electrons, noise=noise, psf_sigma_px=1.0)
    assert np.hypot(*(xy - truth.xy_photocentre_px)) < 5 * np.sqrt(np.max(np.linalg.eigvalsh(cov))) + 0.01


def test_a_far_mesh_body_s_centre_is_its_centroid_moved_by_the_mesh_offset():
    """0.9 px across (3e4 km) at 1.3 rad: the centroid of its light is its photocentre, ~0.1 px off
    the centre of figure toward the Sun; moved by the mesh view's predicted offset (prior 2 km off)
    the centre lands on the truth within the centroid's covariance over 20 draws (chi-square, 40 dof;
    ``phase_sigma_fraction`` 0: the model here is the truth's, so its allowance for albedo marks is
    left out of the check), where the centroid alone misses it by the offset; the default allowance
    adds (0.1 x offset)^2 to each axis."""
    body, camera, ephem, attitude, observer, frame = _scene(1.3, 3.0e4, 0.005)
    truth = frame.truth.target("ball")
    prior = Observer(observer.t_tdb_s, observer.r_ssb_km + np.array([0.0, 2.0, -1.0]), observer.v_ssb_km_s)
    rng = np.random.default_rng(5)
    chi2, raw = 0.0, []
    for _ in range(20):
        image = read_out(frame.signal_e, camera, options=CLEAN, rng=rng)
        got = centroid(image, truth.xy_photocentre_px[None] + rng.normal(0, 0.3, (1, 2)), read_noise_e=camera.read_noise_e,
                       gain_e_per_adu=camera.gain_e_per_adu, bias_adu=camera.bias_adu, window=9)
        assert got.ok[0]
        centre = point_centre(got.xy[0], got.cov[0], camera, body, R_icrf_cam=attitude, observer=prior,
                              ephemeris=ephem, phase_sigma_fraction=0.0)
        error = centre.xy_px - truth.xy_cof_px
        chi2 += float(error @ np.linalg.solve(centre.cov_xy_px2, error))
        raw.append(got.xy[0] - truth.xy_cof_px)
    offset = truth.xy_cof_px - truth.xy_photocentre_px
    assert np.hypot(*offset) > 0.05
    assert stats.chi2.ppf(0.001, 40) < chi2 < stats.chi2.ppf(0.999, 40)
    assert np.hypot(*np.mean(raw, 0)) > 0.7 * np.hypot(*offset)  # without the offset the centre is biased
    allowed = point_centre(got.xy[0], got.cov[0], camera, body, R_icrf_cam=attitude, observer=prior, ephemeris=ephem)
    np.testing.assert_allclose(allowed.cov_xy_px2 - got.cov[0], np.eye(2) * (0.1 * np.hypot(*allowed.offset_px)) ** 2)
