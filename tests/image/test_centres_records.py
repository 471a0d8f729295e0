"""The records of a resolved body's centre: the ``target_vector`` model's analytic Jacobian against
central differences, its CSV round trip, and the centre's records from a fit."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from opnav.camera import Camera
from opnav.ephemeris import Ephemeris, default_planets
from opnav.epochs import parse_epoch
from opnav.errors import InputError
from opnav.measurements import ProbeMeasurementModel, radec_partials
from opnav.records import Measurement, read_csv, write_csv
from opnav.image.centres import centre_records

T0 = parse_epoch("2014-07-15T00:00:00", scale="tdb")


class CircularPhobos:
    """Phobos on a circular, slightly inclined orbit (enough for Jacobian checks)."""

    def state(self, name, t):
        t = np.asarray(t, dtype=float)
        n, a = 2.0 * np.pi / 27_554.0, 9_377.0
        c, s = np.cos(n * t), np.sin(n * t)
        return (np.stack([a * c, a * s, 0.1 * a * s], axis=-1),
                np.stack([-a * n * s, a * n * c, 0.1 * a * n * c], axis=-1))


EPH = Ephemeris(default_planets(), CircularPhobos())
# 1 km and 1e-3 km/s: truncation ~(h / range)^2, far below the tolerance
STEPS = np.array([1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])


def _numeric(f, x):
    cols = []
    for i, h in enumerate(STEPS):
        dx = np.zeros_like(x)
        dx[i] = h
        cols.append((f(x + dx) - f(x - dx)) / (2.0 * h))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("target, offset_km", [("mars", (-4.0e4, 2.5e4, 1.0e4)), ("phobos", (-2.0e4, 1.0e4, 3.0e3))])
@pytest.mark.parametrize("light_time, aberration", [(True, True), (False, False), (True, False)])
def test_target_vector_jacobian_matches_central_differences(target, offset_km, light_time, aberration):
    r_mars, v_mars = EPH.state("mars", T0, center="sun")
    x = np.concatenate([r_mars + np.array(offset_km), v_mars + np.array([1.5, -2.0, 0.4])])
    record = Measurement(T0, "target_vector", [0.0, 0.0, 0.0], np.eye(3), target=target)
    model = ProbeMeasurementModel("sun", ephemeris=EPH, light_time=light_time, aberration=aberration)
    analytic = model.jacobian(record, x)
    numeric = _numeric(lambda s: model.predict(record, s), x)
    for block in (slice(0, 3), slice(3, 6)):
        scale = max(np.abs(numeric[:, block]).max(), 1e-12)
        np.testing.assert_allclose(analytic[:, block], numeric[:, block], rtol=0, atol=1e-6 * scale)
    # d(vector)/d(probe position) is -I plus light-time and aberration terms of order v/c
    np.testing.assert_allclose(analytic[:, :3], -np.eye(3), atol=2e-4)


def test_target_vector_is_range_times_the_radec_direction():
    r_mars, v_mars = EPH.state("mars", T0, center="sun")
    x = np.concatenate([r_mars + np.array([-4.0e4, 2.5e4, 1.0e4]), v_mars])
    model = ProbeMeasurementModel("sun", ephemeris=EPH)
    vector = model.predict(Measurement(T0, "target_vector", np.zeros(3), np.eye(3), target="mars"), x)
    ra, dec = model.predict(Measurement(T0, "radec", [0.0, 0.0], np.eye(2), target="mars"), x)
    u = np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
    np.testing.assert_allclose(vector / np.linalg.norm(vector), u, atol=1e-12)
    assert 4.0e4 < np.linalg.norm(vector) < 5.0e4  # |(-4, 2.5, 1) 1e4 km| = 4.8e4 km


def test_target_vector_csv_round_trip(tmp_path):
    cov = np.array([[4.0, 1.0, 0.0], [1.0, 9.0, 2.0], [0.0, 2.0, 25.0]])
    rec = Measurement(T0, "target_vector", [1.0e4, -2.0e4, 3.0e3], cov, target="mars", sensor="navcam",
                      frame_id="f001")
    write_csv(tmp_path / "m.csv", [rec])
    (back,) = read_csv(tmp_path / "m.csv")
    assert back.kind == "target_vector" and back.target == "mars"
    np.testing.assert_array_equal(back.value, rec.value)
    np.testing.assert_array_equal(back.covariance, rec.covariance)


def test_target_vector_in_another_unit_is_refused(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("t_tdb_s,kind,unit,sensor,target,star_id,star_x,star_y,star_z,frame_id,flags,value,covariance\n"
                    "0.0,target_vector,m,cam,mars,0,nan,nan,nan,,0,1 2 3,1 0 0 0 1 0 0 0 1\n")
    with pytest.raises(InputError, match="target_vector"):
        read_csv(path)


def _camera():
    return Camera(width_px=1024, height_px=1024, focal_length_mm=100.0, pixel_pitch_um=10.0)


def test_centre_records_radec_covariance_is_the_vector_covariance_projected():
    cam = _camera()
    R = Rotation.from_euler("xyz", [0.3, -0.2, 1.1])
    r_cam = np.array([120.0, -80.0, 4.0e4])
    cov_cam = np.diag([4.0, 9.0, 400.0])
    cov_att = np.eye(3) * (1e-5) ** 2
    radec, vector = centre_records(t_tdb_s=T0, target="mars", sensor="navcam", frame_id="f", camera=cam,
                                   R_icrf_cam=R, cov_att_rad2=cov_att, r_cam_km=r_cam, cov_cam_km2=cov_cam,
                                   method="limb")
    np.testing.assert_allclose(vector.value, R.apply(r_cam), rtol=1e-12)
    j = radec_partials(vector.value)
    np.testing.assert_allclose(radec.covariance, j @ vector.covariance @ j.T, rtol=1e-9)
    # the attitude error adds range * sigma_att across the line of sight
    extra = vector.covariance - R.as_matrix() @ cov_cam @ R.as_matrix().T
    u = vector.value / np.linalg.norm(vector.value)
    assert abs(u @ extra @ u) < 1e-6 * np.trace(extra)
    assert np.trace(extra) == pytest.approx(2.0 * (np.linalg.norm(r_cam) * 1e-5) ** 2, rel=1e-9)


def test_centre_records_from_a_pixel_give_radec_only():
    cam = _camera()
    R = Rotation.from_euler("y", 90.0, degrees=True)  # boresight +z -> ICRF +x
    (rec,) = centre_records(t_tdb_s=T0, target="phobos", sensor="navcam", frame_id="f", camera=cam,
                            R_icrf_cam=R, cov_att_rad2=np.zeros((3, 3)), xy_px=np.array([511.5, 511.5]),
                            cov_xy_px2=np.eye(2) * 0.01)
    assert rec.kind == "radec"
    # the principal point looks along ICRF +x: RA 0, Dec 0; a 0.1 px sigma is 0.1 / f rad in each
    np.testing.assert_allclose(rec.value, [0.0, 0.0], atol=1e-12)
    assert math.sqrt(rec.covariance[0, 0]) == pytest.approx(0.1 / cam.focal_length_px, rel=1e-5)
    assert math.sqrt(rec.covariance[1, 1]) == pytest.approx(0.1 / cam.focal_length_px, rel=1e-5)
    with pytest.raises(InputError, match="xy_px or r_cam_km"):
        centre_records(t_tdb_s=T0, target="x", sensor="s", frame_id="f", camera=cam, R_icrf_cam=R,
                       cov_att_rad2=np.zeros((3, 3)))
