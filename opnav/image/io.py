"""Reading image frames: FITS, PNG, TIFF (8/16 bit) and JPEG, mono or RGB.

:func:`read_image` returns the pixel array as ``float64`` indexed ``[row, col]``
(docs/conventions.md) together with an :class:`ImageMeta` record. The steps:

1. Choose the reader from the file suffix: astropy for FITS (the first HDU with
   2-D data), tifffile for TIFF, Pillow for PNG and JPEG.
2. A truncated or corrupt file raises :class:`opnav.errors.FrameError` naming
   the file; astropy's "file may have been truncated" warning counts as corrupt.
3. Colour frames (RGB/RGBA) become luminance with the Rec. 709 weights
   (0.2126 R + 0.7152 G + 0.0722 B); ``meta.channels`` records the original
   channel count so callers can tell a converted frame from a mono one.
4. Non-finite pixels (NaN, inf) are recorded in ``meta.invalid`` and replaced
   by the median of the finite pixels, so that filters and connected
   components see no NaN; detection flags sources that touch them. A frame
   with no finite pixel raises ``FrameError``.
5. The saturation level comes from the FITS ``SATURATE`` (or ``DATAMAX``)
   keyword, else from the integer storage type (255, 65535, ...); it is
   ``None`` for float data without a keyword.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FrameError

log = logging.getLogger(__name__)

FITS_SUFFIXES = (".fits", ".fit", ".fts", ".fits.gz", ".fit.gz")
PNG_SUFFIXES = (".png",)
TIFF_SUFFIXES = (".tif", ".tiff")
JPEG_SUFFIXES = (".jpg", ".jpeg")

#: Rec. 709 / sRGB luminance weights.
LUMA_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])


@dataclass(frozen=True)
class ImageMeta:
    """What :func:`read_image` learned about a frame besides its pixels.

    Attributes
    ----------
    path : str
        The file read.
    file_format : str
        ``"fits"``, ``"png"``, ``"tiff"`` or ``"jpeg"``.
    header : astropy.io.fits.Header or None
        The FITS header of the image HDU (``None`` for other formats).
    channels : int
        Channel count in the file (1 for mono; 3 or 4 were converted to luminance).
    saturation_adu : float or None
        Pixel value at which the detector or storage saturates, ADU.
    invalid : (H, W) bool array or None
        Pixels that were NaN/inf in the file (replaced by the median), or ``None`` if none were.
    lossy : bool
        ``True`` for JPEG (block artefacts; detection should not trust single pixels).
    """

    path: str
    file_format: str
    header: object | None
    channels: int
    saturation_adu: float | None
    invalid: np.ndarray | None
    lossy: bool


def _suffix(path: Path) -> str:
    name = path.name.lower()
    for suffix in FITS_SUFFIXES + PNG_SUFFIXES + TIFF_SUFFIXES + JPEG_SUFFIXES:
        if name.endswith(suffix):
            return suffix
    return path.suffix.lower()


def _integer_saturation(dtype: np.dtype) -> float | None:
    if np.issubdtype(dtype, np.integer):
        return float(np.iinfo(dtype).max)
    return None


def _read_fits(path: Path) -> tuple[np.ndarray, object, float | None]:
    from astropy.io import fits

    try:
        with warnings.catch_warnings():
            # astropy only *warns* about a short file and pads the data; that is corruption here.
            warnings.simplefilter("error")
            with fits.open(path, memmap=False, lazy_load_hdus=False) as hdul:
                for hdu in hdul:
                    if hdu.data is not None and hdu.data.ndim in (2, 3):
                        raw = np.array(hdu.data)
                        header = hdu.header.copy()
                        break
                else:
                    raise FrameError(f"{path}: no 2-D image HDU in the FITS file")
    except FrameError:
        raise
    except Exception as exc:  # noqa: BLE001 - astropy raises OSError, ValueError, TypeError, warnings as errors
        raise FrameError(f"{path}: corrupt or truncated FITS file ({exc})") from None
    saturation = header.get("SATURATE", header.get("DATAMAX"))
    if saturation is None and header.get("BITPIX", -64) > 0:
        bits = int(header["BITPIX"])
        zero = float(header.get("BZERO", 0.0))
        scale = float(header.get("BSCALE", 1.0))
        top = 2.0 ** (bits - 1) - 1.0
        saturation = top * scale + zero
    if raw.ndim == 3:
        # FITS colour cubes are stored (channel, row, col).
        raw = np.moveaxis(raw, 0, -1)
    return raw, header, None if saturation is None else float(saturation)


def _read_tiff(path: Path) -> tuple[np.ndarray, float | None]:
    import tifffile

    try:
        raw = tifffile.imread(path)
    except Exception as exc:  # noqa: BLE001 - tifffile raises several types for damaged files
        raise FrameError(f"{path}: unreadable TIFF file ({exc})") from None
    return np.asarray(raw), _integer_saturation(np.asarray(raw).dtype)


def _read_pillow(path: Path) -> tuple[np.ndarray, float | None]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as img:
            img.load()
            if img.mode in ("P", "PA", "CMYK", "YCbCr", "LAB", "HSV"):
                img = img.convert("RGB")
            raw = np.asarray(img)
            mode = img.mode
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise FrameError(f"{path}: unreadable image file ({exc})") from None
    if mode.startswith("I;16"):
        saturation = 65535.0
    else:
        saturation = _integer_saturation(raw.dtype)
    return raw, saturation


def _to_luminance(raw: np.ndarray, path: Path) -> tuple[np.ndarray, int]:
    if raw.ndim == 2:
        return raw.astype(np.float64), 1
    if raw.ndim == 3 and raw.shape[-1] in (3, 4):
        # An alpha channel carries no light.
        return raw[..., :3].astype(np.float64) @ LUMA_WEIGHTS, int(raw.shape[-1])
    if raw.ndim == 3 and raw.shape[-1] == 1:
        return raw[..., 0].astype(np.float64), 1
    raise FrameError(f"{path}: unsupported image shape {raw.shape}; expected (rows, cols) or (rows, cols, 3|4)")


def read_image(path: str | Path) -> tuple[np.ndarray, ImageMeta]:
    """Read a frame from disk as a 2-D ``float64`` array plus metadata.

    Parameters
    ----------
    path : str or Path
        FITS (``.fits``, ``.fit``, ``.fts``, optionally ``.gz``), PNG, TIFF or JPEG file.

    Returns
    -------
    image : (H, W) float64 array
        Pixel values in ADU, indexed ``[row, col]``; colour converted to luminance,
        non-finite pixels replaced by the median of the finite ones.
    meta : ImageMeta
        Header, saturation level, channel count and the mask of replaced pixels.

    Raises
    ------
    FrameError
        Missing, corrupt or truncated file; unsupported format or shape; no finite pixel.
    """
    path = Path(path)
    if not path.is_file():
        raise FrameError(f"image file not found: {path}")
    suffix = _suffix(path)
    header = None
    if suffix in FITS_SUFFIXES:
        raw, header, saturation = _read_fits(path)
        file_format = "fits"
    elif suffix in TIFF_SUFFIXES:
        raw, saturation = _read_tiff(path)
        file_format = "tiff"
    elif suffix in PNG_SUFFIXES + JPEG_SUFFIXES:
        raw, saturation = _read_pillow(path)
        file_format = "png" if suffix in PNG_SUFFIXES else "jpeg"
    else:
        raise FrameError(f"{path}: unknown image format {suffix!r}; expected FITS, PNG, TIFF or JPEG")
    image, channels = _to_luminance(np.asarray(raw), path)
    if image.size == 0 or min(image.shape) < 3:
        raise FrameError(f"{path}: image is too small ({image.shape})")
    finite = np.isfinite(image)
    invalid = None
    if not finite.all():
        if not finite.any():
            raise FrameError(f"{path}: every pixel is NaN or infinite")
        invalid = ~finite
        image = np.where(finite, image, np.median(image[finite]))
        log.info("%s: %d non-finite pixels replaced by the median", path, int(invalid.sum()))
    meta = ImageMeta(
        path=str(path),
        file_format=file_format,
        header=header,
        channels=channels,
        saturation_adu=saturation,
        invalid=invalid,
        lossy=file_format == "jpeg",
    )
    return image, meta
