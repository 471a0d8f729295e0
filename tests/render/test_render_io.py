"""FITS + truth JSON round trip, corrupt files, windowed frames."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from opnav.camera import Camera
from opnav.errors import FrameError
from opnav.render.truth import TargetTruth
from opnav.render import (
    DetectorOptions, Observer, RenderOptions, read_frame, read_windows, render_frame, render_windows,
    write_frame, write_windows,
)

OBSERVER = Observer(4.0e8, np.array([-1.0e8, 1.1e8, 4.0e7]), np.array([-20.0, -15.0, -6.0]))
ATTITUDE = Rotation.from_euler("zyx", [0.3, 0.9, -0.2])


def test_fits_and_truth_round_trip(tmp_path, star_catalog):
    camera = Camera.from_fov(8.0, 256, 200, k1=-0.05, camera_id="nac-test")
    result = render_frame(camera, ATTITUDE, OBSERVER, catalog=star_catalog, rng=np.random.default_rng(3))
    fits_path, json_path = write_frame(tmp_path / "f0001.fits", result.image, result.header, result.truth)
    stored = read_frame(fits_path)
    np.testing.assert_array_equal(stored.image, result.image)
    assert stored.header["CAMERA"] == "nac-test" and stored.header["CTYPE1"] == "RA---TAN-SIP"
    assert stored.header["CRPIX1"] == pytest.approx(camera.cx_px + 1.0)
    assert stored.header["OBS_VY"] == pytest.approx(-15.0) and stored.header["TDB_S"] == pytest.approx(4.0e8)
    np.testing.assert_array_equal(stored.truth.stars.star_id, result.truth.stars.star_id)
    np.testing.assert_allclose(stored.truth.stars.xy_px, result.truth.stars.xy_px, rtol=0, atol=1e-12)
    np.testing.assert_allclose(stored.truth.R_icrf_cam.as_quat(), ATTITUDE.as_quat(), atol=1e-15)
    assert json_path.name == "f0001.truth.json"


def test_a_target_without_a_pixel_is_written_with_null_pixels_and_read_back_as_nan(tmp_path, star_catalog):
    # JSON has no NaN: a truth whose target has no pixel (NaN: behind the camera, or no lit light for a
    # photocentre) made json.dumps refuse the whole sidecar.
    camera = Camera.from_fov(8.0, 128, 128)
    result = render_frame(camera, ATTITUDE, OBSERVER, catalog=star_catalog, rng=np.random.default_rng(3))
    dark = TargetTruth(name="ball", xy_cof_px=np.array([np.nan, np.nan]), xy_photocentre_px=np.array([40.5, np.nan]),
                       ra_rad=0.25, dec_rad=-0.5, range_km=1.0e6, phase_angle_rad=3.0, vmag=None, electrons=0.0,
                       angular_radius_rad=1e-4, resolved=False)
    truth = dataclasses.replace(result.truth, targets=(dark,))
    _, json_path = write_frame(tmp_path / "dark.fits", result.image, result.header, truth)
    assert '"x_cof_px": null' in json_path.read_text()
    stored = read_frame(tmp_path / "dark.fits").truth.target("ball")
    np.testing.assert_array_equal(stored.xy_cof_px, dark.xy_cof_px)
    np.testing.assert_array_equal(stored.xy_photocentre_px, dark.xy_photocentre_px)
    assert stored.range_km == dark.range_km and stored.ra_rad == pytest.approx(dark.ra_rad, abs=1e-15)


def test_truncated_or_corrupt_fits_raises_frame_error(tmp_path, star_catalog):
    camera = Camera.from_fov(8.0, 64, 64)
    result = render_frame(camera, ATTITUDE, OBSERVER, catalog=star_catalog, rng=np.random.default_rng(4))
    path, _ = write_frame(tmp_path / "a.fits", result.image, result.header, result.truth)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(FrameError, match="a.fits"):
        read_frame(path)
    path.write_bytes(b"SIMPLE  = nonsense" + bytes(3000))
    with pytest.raises(FrameError):
        read_frame(path)
    flipped = bytearray(data)
    flipped[-100] ^= 0xFF  # one corrupted pixel byte: the checksum catches it
    path.write_bytes(bytes(flipped))
    with pytest.raises(FrameError):
        read_frame(path)
    with pytest.raises(FrameError, match="not found"):
        read_frame(tmp_path / "missing.fits")


def test_windowed_frame_equals_full_frame_inside_windows(tmp_path, star_catalog):
    camera = Camera.from_fov(8.0, 300, 240)
    options = RenderOptions(detector=DetectorOptions(noise_free=True), vmag_limit=7.0)
    full = render_frame(camera, ATTITUDE, OBSERVER, catalog=star_catalog, options=options)
    windowed = render_windows(camera, ATTITUDE, OBSERVER, catalog=star_catalog, options=options, window_half_px=8)
    assert len(windowed.windows) > 0
    for w in windowed.windows:
        h, wd = w.image.shape
        np.testing.assert_allclose(w.image, full.image[w.y0 : w.y0 + h, w.x0 : w.x0 + wd], rtol=1e-12, atol=1e-9)
    covered = sum(w.image.size for w in windowed.windows)
    assert covered < 0.5 * camera.width_px * camera.height_px
    path, _ = write_windows(tmp_path / "w.fits", windowed.windows, camera, windowed.truth)
    stored = read_windows(path)
    assert [(w.x0, w.y0) for w in stored.windows] == [(w.x0, w.y0) for w in windowed.windows]
    with pytest.raises(FrameError, match="read_windows"):
        read_frame(path)
