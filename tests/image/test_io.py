"""Reading frames: formats, bit depths, colour, NaN, and damaged files."""

import numpy as np
import pytest
import tifffile
from astropy.io import fits
from PIL import Image

from opnav.errors import FrameError
from opnav.image.io import LUMA_WEIGHTS, read_image


def _pattern(dtype=np.uint16, top=60000):
    rows, cols = np.mgrid[:40, :50]
    return ((rows * 50 + cols) * top // 2000).astype(dtype)


def test_fits_float_and_header(tmp_path):
    data = _pattern().astype(np.float32)
    header = fits.Header({"EXPTIME": 0.5, "SATURATE": 50000.0})
    path = tmp_path / "frame.fits"
    fits.PrimaryHDU(data, header=header).writeto(path)
    image, meta = read_image(path)
    assert image.dtype == np.float64 and image.shape == (40, 50)
    np.testing.assert_array_equal(image, data)
    assert meta.file_format == "fits" and meta.header["EXPTIME"] == 0.5
    assert meta.saturation_adu == 50000.0 and meta.invalid is None and meta.channels == 1


def test_fits_unsigned_16_bit_saturation(tmp_path):
    data = _pattern()
    path = tmp_path / "frame.fits"
    fits.PrimaryHDU(data).writeto(path)  # stored as int16 with BZERO = 32768
    image, meta = read_image(path)
    np.testing.assert_array_equal(image, data)
    assert meta.saturation_adu == 65535.0


def test_truncated_fits_names_the_file(tmp_path):
    path = tmp_path / "cut.fits"
    fits.PrimaryHDU(np.ones((200, 200), np.float32)).writeto(path)
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(FrameError, match="cut.fits"):
        read_image(path)


def test_garbage_and_missing_files(tmp_path):
    bad = tmp_path / "noise.fits"
    bad.write_bytes(b"this is not a FITS file" * 200)
    with pytest.raises(FrameError, match="noise.fits"):
        read_image(bad)
    with pytest.raises(FrameError, match="not found"):
        read_image(tmp_path / "absent.png")
    other = tmp_path / "frame.xyz"
    other.write_bytes(b"0")
    with pytest.raises(FrameError, match="unknown image format"):
        read_image(other)
    png = tmp_path / "broken.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)
    with pytest.raises(FrameError, match="broken.png"):
        read_image(png)


@pytest.mark.parametrize("dtype, top, saturation", [(np.uint8, 250, 255.0), (np.uint16, 60000, 65535.0)])
def test_png_and_tiff_bit_depths(tmp_path, dtype, top, saturation):
    data = _pattern(dtype, top)
    Image.fromarray(data).save(tmp_path / "a.png")
    tifffile.imwrite(tmp_path / "a.tif", data)
    for name in ("a.png", "a.tif"):
        image, meta = read_image(tmp_path / name)
        np.testing.assert_array_equal(image, data)
        assert meta.saturation_adu == saturation and meta.channels == 1


def test_rgb_png_becomes_luminance(tmp_path):
    rgb = np.zeros((30, 40, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200, 100, 50
    Image.fromarray(rgb).save(tmp_path / "c.png")
    image, meta = read_image(tmp_path / "c.png")
    assert meta.channels == 3 and image.shape == (30, 40)
    np.testing.assert_allclose(image, LUMA_WEIGHTS @ [200, 100, 50])


def test_jpeg_is_marked_lossy(tmp_path):
    Image.fromarray(_pattern(np.uint8, 250)).save(tmp_path / "d.jpg", quality=90)
    image, meta = read_image(tmp_path / "d.jpg")
    assert meta.lossy and meta.file_format == "jpeg"
    assert np.abs(image - _pattern(np.uint8, 250)).mean() < 3.0


def test_nan_pixels_are_masked_and_replaced(tmp_path):
    data = _pattern().astype(np.float32)
    data[5, 7] = np.nan
    data[10, :3] = np.inf
    path = tmp_path / "nan.fits"
    fits.PrimaryHDU(data).writeto(path)
    image, meta = read_image(path)
    assert np.isfinite(image).all()
    assert meta.invalid.sum() == 4 and meta.invalid[5, 7] and meta.invalid[10, 2]
    assert image[5, 7] == np.median(data[np.isfinite(data)])


def test_all_nan_frame_raises(tmp_path):
    path = tmp_path / "allnan.fits"
    fits.PrimaryHDU(np.full((20, 20), np.nan, np.float32)).writeto(path)
    with pytest.raises(FrameError, match="NaN"):
        read_image(path)
