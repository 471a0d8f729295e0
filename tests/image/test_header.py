"""FITS header -> epoch, WCS attitude and camera (opnav.image.header, the one place that reads them)."""

import math

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS
from scipy.spatial.transform import Rotation

from opnav.camera import Camera
from opnav.epochs import parse_epoch
from opnav.errors import FrameError
from opnav.image.header import (DETECTOR_DEFAULTS, camera_from_header, detector_keywords, has_epoch, header_epoch,
                                header_vector, wcs_attitude, wcs_hint)
from opnav.render.frames_io import frame_header, wcs_header
from opnav.render.truth import FrameTruth

MICROSECOND = 1e-6
CAMERA = Camera.from_fov(1.0, 1024, 768)
ATTITUDE = Rotation.from_euler("zyx", [40.0, -25.0, 110.0], degrees=True)


def _truth(t_mid: float, exposure_s: float) -> FrameTruth:
    return FrameTruth(t_tdb_s=t_mid, exposure_s=exposure_s, camera_id="nac", R_icrf_cam=ATTITUDE,
                      r_observer_ssb_km=np.array([1e8, 2e7, -3e6]), v_observer_ssb_km_s=np.array([20.0, -8.0, 4.0]),
                      omega_cam_rad_s=np.zeros(3), stars=None, targets=())


def test_opnav_headers_give_the_mid_exposure_epoch_from_every_keyword():
    # frames_io writes DATE-OBS at the start of the exposure, DATE-AVG and TDB_S at its middle
    t_mid = 4.586e8 + 0.25
    header = frame_header(CAMERA, _truth(t_mid, exposure_s=30.0))
    assert header_epoch(header, "f.fits") == t_mid
    del header["TDB_S"]
    assert abs(header_epoch(header, "f.fits") - t_mid) < MICROSECOND
    del header["DATE-AVG"]
    assert abs(header_epoch(header, "f.fits") - t_mid) < MICROSECOND  # DATE-OBS + EXPTIME / 2
    del header["EXPTIME"]
    assert abs(header_epoch(header, "f.fits") - (t_mid - 15.0)) < MICROSECOND
    del header["DATE-OBS"]
    assert not has_epoch(header)
    with pytest.raises(FrameError, match="f.fits: no epoch"):
        header_epoch(header, "f.fits")


def test_timesys_names_the_scale_of_the_dates_utc_by_default():
    text = "2014-07-15T00:58:52.316"
    utc = parse_epoch(text, "utc")
    for timesys, expected in ((None, utc), ("UTC", utc), ("TT", utc - 67.184), ("tai", utc - 35.0),
                              ("TDB", parse_epoch(text, "tdb"))):
        header = fits.Header({"DATE-OBS": text})
        if timesys is not None:
            header["TIMESYS"] = timesys
        assert abs(header_epoch(header, "f.fits") - expected) < MICROSECOND
    header = fits.Header({"DATE-OBS": text, "TIMESYS": "GPS"})
    with pytest.raises(FrameError, match="f.fits: TIMESYS"):
        header_epoch(header, "f.fits")


@pytest.mark.parametrize("keyword, value, message", [
    ("DATE-OBS", "2014-13-45T00:00:00", "DATE-OBS"),
    ("DATE-AVG", "yesterday", "DATE-AVG"),
    ("TDB_S", "nan", "TDB_S"),
    ("TDB_S", "soon", "TDB_S"),
])
def test_an_unreadable_epoch_keyword_is_one_line_naming_file_and_keyword(keyword, value, message):
    header = fits.Header({keyword: value})
    with pytest.raises(FrameError, match=f"f.fits: .*{message}") as caught:
        header_epoch(header, "f.fits")
    assert "\n" not in str(caught.value)
    with pytest.raises(FrameError, match="EXPTIME"):
        header_epoch(fits.Header({"DATE-OBS": "2014-07-15T00:00:00", "EXPTIME": -1.0}), "f.fits")


def test_observer_vectors_are_read_when_all_three_keywords_are_there():
    header = frame_header(CAMERA, _truth(4.5e8, 1.0))
    np.testing.assert_array_equal(header_vector(header, ("OBS_VX", "OBS_VY", "OBS_VZ"), "f"), [20.0, -8.0, 4.0])
    del header["OBS_VZ"]
    assert header_vector(header, ("OBS_VX", "OBS_VY", "OBS_VZ"), "f") is None
    header["OBS_VZ"] = "fast"
    with pytest.raises(FrameError, match="OBS_VZ"):
        header_vector(header, ("OBS_VX", "OBS_VY", "OBS_VZ"), "f")


def _astropy_cd(header) -> np.ndarray:
    """The CD matrix as the image stage read it through astropy.wcs before this module read the keywords."""
    wcs = WCS(header, relax=True, naxis=2)
    return wcs.wcs.cd if wcs.wcs.has_cd() else wcs.wcs.get_pc() * wcs.wcs.cdelt[:, None]


def test_the_wcs_gives_the_rendered_attitude_camera_and_field_of_view():
    header = wcs_header(CAMERA, ATTITUDE)
    rotation, f_px, (cx, cy) = wcs_attitude(header, "f.fits")
    assert math.degrees((rotation.inv() * ATTITUDE).magnitude()) * 3600.0 < 1e-6
    assert f_px == pytest.approx(CAMERA.focal_length_px, rel=1e-12)
    assert (cx, cy) == (CAMERA.cx_px, CAMERA.cy_px)
    hint = wcs_hint(header, CAMERA.shape, "f.fits")
    assert hint.fov_deg == pytest.approx(1.0, rel=1e-12)
    assert np.linalg.norm(hint.center_icrf() - ATTITUDE.apply([0.0, 0.0, 1.0])) < 1e-12
    # SIP keywords (a distorted camera): the hint is the linear part, CTYPE still TAN
    distorted = wcs_header(CAMERA.replace(k1=-0.02), ATTITUDE)
    assert distorted["CTYPE1"] == "RA---TAN-SIP"
    assert wcs_hint(distorted, CAMERA.shape, "f.fits").fov_deg == pytest.approx(1.0, rel=0.01)
    # as read from a file (astropy.wcs parses the card text, the header in memory keeps every digit)
    written = fits.Header.fromstring(distorted.tostring())
    from opnav.image.header import _linear_wcs

    np.testing.assert_allclose(_linear_wcs(written, "f.fits")[0], _astropy_cd(written), rtol=0.0, atol=0.0)


def test_pc_cdelt_and_crota2_forms_give_the_cd_matrix_astropy_gives():
    header = wcs_header(CAMERA, ATTITUDE)
    cd = np.array([[header[f"CD{i}_{j}"] for j in (1, 2)] for i in (1, 2)])
    reference = wcs_attitude(header, "f")[0]
    # PC x CDELT
    pc_form = header.copy()
    for i in (1, 2):
        for j in (1, 2):
            del pc_form[f"CD{i}_{j}"]
    scale = math.sqrt(abs(np.linalg.det(cd)))
    pc_form["CDELT1"], pc_form["CDELT2"] = -scale, scale
    for i in (1, 2):
        for j in (1, 2):
            pc_form[f"PC{i}_{j}"] = cd[i - 1, j - 1] / (-scale if i == 1 else scale)
    np.testing.assert_allclose(wcs_attitude(pc_form, "f")[0].as_matrix(), reference.as_matrix(), atol=1e-12)
    # CROTA2 (the AIPS convention)
    rota = header.copy()
    for i in (1, 2):
        for j in (1, 2):
            del rota[f"CD{i}_{j}"]
    rota["CDELT1"], rota["CDELT2"], rota["CROTA2"] = -scale, scale, 30.0
    from opnav.image.header import _linear_wcs

    rota = fits.Header.fromstring(rota.tostring())
    np.testing.assert_allclose(_linear_wcs(rota, "f")[0], _astropy_cd(rota), rtol=1e-12, atol=1e-18)


def test_no_tan_wcs_gives_no_hint_and_a_broken_one_an_error():
    assert wcs_hint(fits.Header(), CAMERA.shape, "f.fits") is None
    assert wcs_hint(None, CAMERA.shape, "f.fits") is None
    header = wcs_header(CAMERA, ATTITUDE)
    header["CTYPE1"], header["CTYPE2"] = "GLON-CAR", "GLAT-CAR"
    assert wcs_hint(header, CAMERA.shape, "f.fits") is None
    header = wcs_header(CAMERA, ATTITUDE)
    header["CD1_1"] = header["CD1_2"] = 0.0
    with pytest.raises(FrameError, match="f.fits: the WCS has no valid CD matrix"):
        wcs_hint(header, CAMERA.shape, "f.fits")
    header = wcs_header(CAMERA, ATTITUDE)
    header["CD1_1"] = "wide"
    with pytest.raises(FrameError, match="f.fits: header keyword CD1_1"):
        wcs_hint(header, CAMERA.shape, "f.fits")


def test_a_frame_without_detector_keywords_gets_the_default_camera_s_values():
    # opnav render writes BIASLVL = [camera] bias_adu (100 ADU by default): a frame without the keyword
    # is taken to have that default, not 0 (issue 40)
    header = frame_header(CAMERA, _truth(4.5e8, 2.0))
    assert camera_from_header(header, CAMERA.shape, "f.fits").bias_adu == CAMERA.bias_adu == 100.0
    for key in ("GAIN", "RDNOISE", "BIASLVL", "EXPTIME"):
        del header[key]
    camera = camera_from_header(header, CAMERA.shape, "f.fits")
    default = Camera(width_px=8, height_px=8, focal_length_mm=10.0, pixel_pitch_um=10.0)
    assert (camera.gain_e_per_adu, camera.read_noise_e, camera.bias_adu) == (
        default.gain_e_per_adu, default.read_noise_e, default.bias_adu)
    assert camera.exposure_s == DETECTOR_DEFAULTS["EXPTIME"] == 1.0
    # with a camera given, an absent keyword takes the camera's value (EXPTIME = 0 is absent too)
    header["EXPTIME"] = 0.0
    given = CAMERA.replace(bias_adu=250.0, exposure_s=3.0)
    assert detector_keywords(header, "f.fits", given) == {"read_noise_e": 5.0, "gain_e_per_adu": 1.0,
                                                          "bias_adu": 250.0, "exposure_s": 3.0}


@pytest.mark.parametrize("keyword, value, message", [
    ("GAIN", "high", "is not a number"),
    ("GAIN", 0.0, "must be positive"),
    ("RDNOISE", float("nan"), "is not a finite number"),
    ("RDNOISE", -2.0, "must not be negative"),
    ("BIASLVL", True, "is not a number"),
    ("EXPTIME", "1s", "is not a number"),
    ("EXPTIME", -1.0, "must not be negative"),
])
def test_a_bad_detector_keyword_is_a_frame_error_naming_file_and_keyword(keyword, value, message):
    header = dict(frame_header(CAMERA, _truth(4.5e8, 2.0)))  # any mapping is a header (astropy refuses nan)
    header[keyword] = value
    with pytest.raises(FrameError, match=rf"^f.fits: header keyword {keyword} = .* {message}") as caught:
        camera_from_header(header, CAMERA.shape, "f.fits")
    assert "\n" not in str(caught.value)
    with pytest.raises(FrameError, match=rf"^f.fits: header keyword {keyword}"):
        detector_keywords(header, "f.fits", CAMERA)
