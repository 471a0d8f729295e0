"""Reading frames: formats, bit depths, colour, NaN, and damaged files."""

import numpy as np
import pytest
import tifffile
from astropy.io import fits
from PIL import Image

from opnav.errors import FrameError, InputError
from opnav.image.io import BAYER_PATTERNS, LUMA_WEIGHTS, demosaic_bayer, read_image


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


def _bayer(rgb, pattern):
    """The raw mosaic a sensor with ``pattern`` records of the colour frame ``rgb`` (H, W, 3)."""
    channel = np.array(["RGB".index(c) for c in pattern]).reshape(2, 2)
    rows, cols = np.indices(rgb.shape[:2])
    return np.take_along_axis(rgb, channel[rows % 2, cols % 2][..., None], axis=2)[..., 0]


@pytest.mark.parametrize("pattern", BAYER_PATTERNS)
def test_bayer_mosaic_of_a_flat_colour_gives_its_luminance(tmp_path, pattern):
    rgb = np.empty((30, 40, 3))
    rgb[...] = [1200.0, 3000.0, 700.0]
    tifffile.imwrite(tmp_path / "raw.tif", _bayer(rgb, pattern).astype(np.uint16))
    image, meta = read_image(tmp_path / "raw.tif", bayer=pattern.lower())
    assert meta.bayer == pattern and meta.channels == 1 and image.shape == (30, 40)
    np.testing.assert_allclose(image, LUMA_WEIGHTS @ [1200.0, 3000.0, 700.0], rtol=1e-12)


@pytest.mark.parametrize("pattern", BAYER_PATTERNS)
def test_demosaic_keeps_each_sample_and_interpolates_linear_ramps_exactly(pattern):
    # bilinear interpolation reproduces a linear ramp of each colour away from the border
    rows, cols = np.mgrid[:24, :32].astype(float)
    rgb = np.stack([10.0 + rows + 2.0 * cols, 50.0 + 3.0 * rows - cols, 7.0 + 0.5 * rows + 0.25 * cols], axis=-1)
    mosaic = _bayer(rgb, pattern)
    out = demosaic_bayer(mosaic, pattern)
    np.testing.assert_allclose(out[1:-1, 1:-1], rgb[1:-1, 1:-1], atol=1e-9)
    np.testing.assert_array_equal(_bayer(out, pattern), mosaic)


def test_bayer_star_centroid_stays_on_the_star(tmp_path):
    # a white star behind the filters: the luminance frame puts its centroid where the star is
    from scipy.special import ndtr

    from opnav.image.extract import extract_stars

    x0, y0, sigma = 20.3, 17.6, 1.3
    cols, rows = np.arange(48), np.arange(40)
    ex = ndtr((cols + 0.5 - x0) / sigma) - ndtr((cols - 0.5 - x0) / sigma)
    ey = ndtr((rows + 0.5 - y0) / sigma) - ndtr((rows - 0.5 - y0) / sigma)
    star = 4000.0 * np.outer(ey, ex)
    rgb = 100.0 + star[..., None] * np.array([0.5, 1.0, 0.7])
    noisy = np.random.default_rng(8).normal(_bayer(rgb, "GRBG"), 2.0)
    tifffile.imwrite(tmp_path / "star.tif", np.rint(noisy).astype(np.uint16))
    image, _ = read_image(tmp_path / "star.tif", bayer="GRBG")
    xy, cov = extract_stars(image)
    assert len(xy) == 1
    # within 4 sigmas of the reported covariance and 0.1 px
    error = xy[0] - [x0, y0]
    assert error @ np.linalg.solve(cov[0], error) < 16.0 and np.hypot(*error) < 0.1


def test_bayer_option_errors(tmp_path):
    Image.fromarray(np.zeros((10, 12, 3), np.uint8)).save(tmp_path / "rgb.png")
    with pytest.raises(FrameError, match="rgb.png"):
        read_image(tmp_path / "rgb.png", bayer="RGGB")
    with pytest.raises(InputError, match="RGBG"):
        read_image(tmp_path / "rgb.png", bayer="RGBG")
