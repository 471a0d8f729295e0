"""Reading image frames: FITS, PNG, TIFF (8/16 bit) and JPEG, mono or RGB.

:func:`read_image` returns the pixel array as ``float64`` indexed ``[row, col]``
(docs/conventions.md) together with an :class:`ImageMeta` record. The steps:

1. Choose the reader from the file suffix: for FITS (the first HDU with 2-D data)
   :mod:`opnav.image.fits_simple` for a plain file (the same pixels and values,
   without importing astropy), astropy for any other; tifffile for TIFF, Pillow for
   PNG and JPEG.
2. A truncated or corrupt file raises :class:`opnav.errors.FrameError` naming
   the file; astropy's "file may have been truncated" warning counts as corrupt.
3. Colour frames (RGB/RGBA) become luminance with the Rec. 709 weights
   (0.2126 R + 0.7152 G + 0.0722 B); ``meta.channels`` records the original
   channel count so callers can tell a converted frame from a mono one.
   A raw Bayer mosaic (a 2-D frame whose pixels sit behind a 2 x 2 colour filter pattern,
   ``bayer="RGGB"`` and the like) is demosaiced bilinearly (:func:`demosaic_bayer`: each
   channel's missing sites are the mean of its nearest sites of that colour, its own sites
   kept) and then weighted the same way; ``meta.bayer`` names the pattern.
4. Non-finite pixels (NaN, inf) are recorded in ``meta.invalid`` and replaced
   by the median of the finite pixels, so that filters and connected
   components see no NaN; detection flags sources that touch them. A frame
   with no finite pixel raises ``FrameError``.
5. The saturation level comes from the FITS ``SATURATE`` (or ``DATAMAX``)
   keyword, else from the integer storage type (255, 65535, ...); it is
   ``None`` for float data without a keyword.

A frame of more than :data:`MAX_FRAME_PIXELS` pixels is refused in every format before its
pixels are read (FITS: from the header's ``NAXISn``).
"""

from __future__ import annotations

import gzip
import logging
import math
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FrameError, InputError

log = logging.getLogger(__name__)

FITS_SUFFIXES = (".fits", ".fit", ".fts", ".fits.gz", ".fit.gz")
PNG_SUFFIXES = (".png",)
TIFF_SUFFIXES = (".tif", ".tiff")
JPEG_SUFFIXES = (".jpg", ".jpeg")

#: Rec. 709 / sRGB luminance weights.
LUMA_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])
#: Most pixels a frame may declare: Pillow's decompression-bomb limit (2 x Image.MAX_IMAGE_PIXELS),
#: applied to TIFF pages as well.
MAX_FRAME_PIXELS = 178_956_970
#: Largest pixel magnitude read as a value, ADU (far beyond any detector; squares stay finite).
MAX_ABS_ADU = 1e30
#: FITS headers and data come in blocks of 2880 bytes, 36 cards of 80 characters.
FITS_BLOCK = 2880
FITS_CARD = 80
#: Most axes a FITS HDU may declare (the FITS standard: NAXIS is 0 to 999).
FITS_MAX_NAXIS = 999
#: 2 x 2 colour filter patterns of a raw Bayer mosaic, named row by row from the first pixel.
BAYER_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")


@dataclass(frozen=True)
class ImageMeta:
    """What :func:`read_image` learned about a frame besides its pixels.

    Attributes
    ----------
    path : str
        The file read.
    file_format : str
        ``"fits"``, ``"png"``, ``"tiff"`` or ``"jpeg"``.
    header : astropy.io.fits.Header, opnav.image.fits_simple.PlainHeader or None
        The FITS header of the image HDU, keyword -> value (``None`` for other formats).
    channels : int
        Channel count in the file (1 for mono; 3 or 4 were converted to luminance).
    saturation_adu : float or None
        Pixel value at which the detector or storage saturates, ADU.
    invalid : (H, W) bool array or None
        Pixels that were NaN/inf in the file (replaced by the median), or ``None`` if none were.
    lossy : bool
        ``True`` for JPEG (block artefacts; detection should not trust single pixels).
    bayer : str or None
        Colour filter pattern of a raw mosaic that was demosaiced to luminance (``BAYER_PATTERNS``).
    """

    path: str
    file_format: str
    header: object | None
    channels: int
    saturation_adu: float | None
    invalid: np.ndarray | None
    lossy: bool
    bayer: str | None = None


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


def _one_line(exc: BaseException) -> str:
    """``exc``'s message on one line (astropy's validation reports span several)."""
    return " ".join(str(exc).split())


def _check_fits_sizes(path: Path) -> None:
    """Refuse a FITS file whose header declares more than 999 axes or a negative size, before astropy reads it.

    astropy makes one header look-up per declared axis before it checks the count, so a damaged
    ``NAXIS = 99999999999`` card keeps ``fits.open`` busy for hours instead of failing, and a
    negative ``NAXISn`` makes it read the same HDU again and again. The
    headers are walked HDU by HDU (each data part skipped by its declared size); the walk stops
    quietly at anything it cannot follow and leaves that damage to astropy's own checks.
    """
    opener = gzip.open if path.name.lower().endswith(".gz") else open
    try:
        with opener(path, "rb") as handle:
            while True:
                values: dict[bytes, bytes] = {}
                ended = False
                while not ended:
                    block = handle.read(FITS_BLOCK)
                    if len(block) < FITS_BLOCK:
                        return
                    for start in range(0, FITS_BLOCK, FITS_CARD):
                        card = block[start:start + FITS_CARD]
                        if card[:8].rstrip() == b"END":
                            ended = True
                            break
                        if card[8:10] == b"= ":
                            values.setdefault(card[:8].rstrip(), card[10:].split(b"/", 1)[0].strip())
                try:
                    naxis = int(values.get(b"NAXIS", b"0"))
                except ValueError:
                    return
                if not 0 <= naxis <= FITS_MAX_NAXIS:
                    raise FrameError(f"{path}: FITS header declares NAXIS = {naxis}; the FITS standard allows "
                                     f"0 to {FITS_MAX_NAXIS} axes")
                for key in (b"BITPIX", b"PCOUNT", b"GCOUNT", *(b"NAXIS%d" % axis for axis in range(1, naxis + 1))):
                    text = values.get(key, b"0")
                    # astropy multiplies the sizes: NAXIS1 = 999999999 times NAXIS2 = 'abc' builds a 3 GB string
                    if text[:1] == b"'" or text in (b"T", b"F"):
                        raise FrameError(f"{path}: FITS header declares {key.decode()} = "
                                         f"{text.decode('ascii', 'replace')}; expected an integer")
                try:
                    axes = [int(values[b"NAXIS%d" % axis]) for axis in range(1, naxis + 1)]
                    bits = abs(int(values[b"BITPIX"]))
                    pcount = int(values.get(b"PCOUNT", b"0"))
                    gcount = int(values.get(b"GCOUNT", b"1"))
                except (KeyError, ValueError):
                    return
                if min(axes + [pcount, gcount], default=0) < 0:
                    # a negative size sends astropy back to the same header, HDU after HDU, forever
                    raise FrameError(f"{path}: FITS header declares a negative size (NAXISn = {axes}, PCOUNT = "
                                     f"{pcount}, GCOUNT = {gcount}); sizes are >= 0")
                if values.get(b"GROUPS") == b"T" and axes and axes[0] == 0:
                    axes = axes[1:]  # random groups: NAXIS1 = 0 is not a data axis
                image = b"XTENSION" not in values or values[b"XTENSION"].strip(b"' ") == b"IMAGE"
                if image and naxis >= 2 and math.prod(axes) > MAX_FRAME_PIXELS:
                    # a 20000 x 20000 frame is 3.2 GB as float64 before detection's copies: the bound of
                    # PNG, JPEG and TIFF frames, before anything is read
                    raise FrameError(f"{path}: FITS image of {' x '.join(map(str, axes))} pixels; at most "
                                     f"{MAX_FRAME_PIXELS:,} pixels a frame")
                size = bits // 8 * gcount * (pcount + math.prod(axes)) if naxis else 0
                handle.seek(-(-size // FITS_BLOCK) * FITS_BLOCK, 1)
    except FrameError:
        raise
    except (OSError, EOFError, ValueError, OverflowError, zlib.error):
        return  # unreadable or not gzip: astropy reports it


def _fits_number(header, key: str, path: Path) -> float | None:
    """Header keyword ``key`` as a finite float, ``None`` when absent; another value is a ``FrameError``."""
    try:
        value = header.get(key)
    except Exception as exc:  # noqa: BLE001 - astropy parses a card on first use: VerifyError, ValueError
        raise FrameError(f"{path}: unparsable FITS keyword {key} ({_one_line(exc)})") from None
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(value):
        raise FrameError(f"{path}: FITS keyword {key} = {value!r}; expected a finite number")
    return float(value)


def _read_fits(path: Path) -> tuple[np.ndarray, object, float | None]:
    _check_fits_sizes(path)
    plain = None
    if not path.name.lower().endswith(".gz"):
        from .fits_simple import read_plain_fits  # astropy's import costs more than most frames' reading

        try:
            plain = read_plain_fits(path)
        except OSError:
            plain = None  # astropy's read names the problem
    raw, header = plain if plain is not None else _read_fits_astropy(path)
    # A keyword of the wrong type (SATURATE = 'abc') must not become a saturation level, nor a traceback.
    saturation = _fits_number(header, "SATURATE", path)
    if saturation is None:
        saturation = _fits_number(header, "DATAMAX", path)
    bitpix = _fits_number(header, "BITPIX", path)
    if saturation is None and bitpix is not None and bitpix > 0:
        zero = _fits_number(header, "BZERO", path)
        scale = _fits_number(header, "BSCALE", path)
        top = 2.0 ** (int(bitpix) - 1) - 1.0
        saturation = top * (1.0 if scale is None else scale) + (0.0 if zero is None else zero)
    if raw.ndim == 3:
        # FITS colour cubes are stored (channel, row, col).
        raw = np.moveaxis(raw, 0, -1)
    return raw, header, saturation


def _read_fits_astropy(path: Path) -> tuple[np.ndarray, object]:
    """The first 2-D or 3-D image HDU's pixels and a copy of its header, read by astropy."""
    from astropy.io import fits

    try:
        with warnings.catch_warnings():
            # astropy only *warns* about a short file and pads the data; that is corruption here.
            warnings.simplefilter("error")
            # our own handle: astropy leaves the one it opens unclosed when the file fails to parse
            with open(path, "rb") as handle, fits.open(handle, memmap=False, lazy_load_hdus=False) as hdul:
                for hdu in hdul:
                    if hdu.data is not None and hdu.data.ndim in (2, 3):
                        return np.array(hdu.data), hdu.header.copy()
                raise FrameError(f"{path}: no 2-D image HDU in the FITS file")
    except FrameError:
        raise
    except Exception as exc:  # noqa: BLE001 - astropy raises OSError, ValueError, TypeError, warnings as errors
        raise FrameError(f"{path}: corrupt or truncated FITS file ({_one_line(exc)})") from None


class _LogNotes(logging.Handler):
    """Collects a library logger's complaints, to name them in the error instead of printing them."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(" ".join(record.getMessage().split()))


def _read_tiff(path: Path) -> tuple[np.ndarray, float | None]:
    import tifffile

    # tifffile logs what it finds wrong (to stderr via the CLI's logging set-up) and carries on;
    # its notes go into the FrameError instead, so a command's error stays one line
    logger = logging.getLogger("tifffile")
    notes = _LogNotes()
    logger.addHandler(notes)
    propagate, logger.propagate = logger.propagate, False
    try:
        with tifffile.TiffFile(path) as tif:
            # Index the page chain first: len() follows it with tifffile's check for an IFD that points
            # back to an earlier one, where building the series straight away can loop forever on such a file.
            if not len(tif.pages):
                raise FrameError(f"{path}: TIFF file without an image")
            for page in tif.series[0].pages if tif.series else ():
                # a damaged header may declare billions of pixels (a 281-byte file: 16 x 16.7 M); the
                # same bound as Pillow's for PNG and JPEG, before anything is allocated
                if math.prod(page.shape) > MAX_FRAME_PIXELS:
                    raise FrameError(f"{path}: TIFF page {page.shape} declares more than {MAX_FRAME_PIXELS:,} "
                                     "pixels; not a frame opnav reads")
                chunked = getattr(page, "chunked", None)
                # tifffile visits every declared strip or tile, present or not: a damaged ImageLength
                # declaring millions of strips beside the one stored costs minutes, then gives zeros
                if chunked is not None and math.prod(chunked) != len(page.dataoffsets):
                    raise FrameError(f"{path}: corrupt TIFF file (its {page.shape} page declares "
                                     f"{math.prod(chunked):,} strips or tiles, and {len(page.dataoffsets):,} "
                                     "are stored)")
            raw = tif.asarray()
    except FrameError:
        raise
    except Exception as exc:  # noqa: BLE001 - tifffile raises several types for damaged files
        detail = "; ".join([_one_line(exc)] + notes.messages[:1])
        raise FrameError(f"{path}: unreadable TIFF file ({detail})") from None
    finally:
        logger.removeHandler(notes)
        logger.propagate = propagate
    return np.asarray(raw), _integer_saturation(np.asarray(raw).dtype)


#: PNG Adam7 interlace passes: (first column, first row, column step, row step).
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))
#: Samples per pixel of each PNG colour type (grey, RGB, palette, grey + alpha, RGBA).
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}


def _png_missing_rows(path: Path) -> str | None:
    """Why the IDAT data of PNG ``path`` cannot fill its declared size, or ``None`` when it can.

    Pillow stops at the end of the compressed stream and leaves the rows it did not get at 0,
    without an error: a PNG whose header declares more rows than its data holds would otherwise
    be read as a frame with a black band. Called after Pillow read the file, so the chunks are sound.
    """
    data = path.read_bytes()
    pos, idat, header = 8, [], None
    while pos + 8 <= len(data):
        length = int.from_bytes(data[pos:pos + 4], "big")
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + length]
        if kind == b"IHDR" and len(body) >= 13:
            header = body
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
        pos += 12 + length
    if header is None:
        return None
    width, height = int.from_bytes(header[0:4], "big"), int.from_bytes(header[4:8], "big")
    depth, colour, interlace = header[8], header[9], header[12]
    bits = _PNG_CHANNELS.get(colour, 1) * depth
    passes = _ADAM7 if interlace else ((0, 0, 1, 1),)
    expected = 0
    for x0, y0, dx, dy in passes:
        cols, rows = (width - x0 + dx - 1) // dx, (height - y0 + dy - 1) // dy
        if cols > 0 and rows > 0:
            expected += rows * (1 + (cols * bits + 7) // 8)  # one filter byte per row
    try:
        got = len(zlib.decompressobj().decompress(b"".join(idat), expected))
    except zlib.error as exc:
        return f"damaged image data ({exc})"
    if got < expected:
        return f"its image data fills {got:,} of the {expected:,} bytes its {width} x {height} header declares"
    return None


def _read_pillow(path: Path) -> tuple[np.ndarray, float | None]:
    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():
            # Pillow warns (on stderr) about frames of 90-180 million pixels and still reads them; a frame
            # that large is read like any other, and one larger is refused below
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as img:
                # Before decoding: a few hundred bytes can declare a frame of hundreds of millions of
                # pixels, which Pillow would allocate and fill (seconds) before the data runs out.
                problem = _png_missing_rows(path) if img.format == "PNG" else None
                if not problem:
                    img.load()
                    if img.mode in ("P", "PA", "CMYK", "YCbCr", "LAB", "HSV"):
                        img = img.convert("RGB")
                    raw = np.asarray(img)
                    mode = img.mode
    except Image.DecompressionBombError:
        # a damaged or hostile header may declare billions of pixels; Pillow refuses to allocate them
        raise FrameError(f"{path}: image header declares more than {MAX_FRAME_PIXELS:,} pixels; "
                         "not a frame opnav reads") from None
    except MemoryError:
        # a header declaring more pixels than this machine can allocate (a short PNG is refused before)
        raise FrameError(f"{path}: image header declares a frame too large to hold in memory here") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise FrameError(f"{path}: unreadable image file ({_one_line(exc)})") from None
    if problem:
        raise FrameError(f"{path}: truncated PNG file: {problem}")
    if mode.startswith("I;16"):
        saturation = 65535.0
    else:
        saturation = _integer_saturation(raw.dtype)
    return raw, saturation


def _to_luminance(raw: np.ndarray, path: Path) -> tuple[np.ndarray, int]:
    if raw.dtype.kind not in "biuf":
        # complex (TIFF allows it) would lose its imaginary part in the cast; text or records are not pixels
        raise FrameError(f"{path}: pixels of type {raw.dtype}; expected integer or real (float) pixels")
    # Signalling NaNs in a float file raise the "invalid" flag when cast (they become quiet NaNs), and
    # channels of +inf and -inf (or sums past the float range) give a non-finite luminance: read_image
    # marks all of them invalid, like the file's own NaN pixels.
    with np.errstate(invalid="ignore", over="ignore"):
        if raw.ndim == 2:
            return raw.astype(np.float64), 1
        if raw.ndim == 3 and raw.shape[-1] in (3, 4):
            # An alpha channel carries no light.
            return raw[..., :3].astype(np.float64) @ LUMA_WEIGHTS, int(raw.shape[-1])
        if raw.ndim == 3 and raw.shape[-1] == 1:
            return raw[..., 0].astype(np.float64), 1
    raise FrameError(f"{path}: unsupported image shape {raw.shape}; expected (rows, cols) or (rows, cols, 3|4)")


#: Bilinear demosaicing kernels: green sites form a checkerboard (its 4 edge neighbours), red and
#: blue a one-in-four lattice (2 edge or 4 corner neighbours). Normalised convolution divides by
#: the same kernel applied to the channel's site mask, so a site keeps its own value.
_GREEN_KERNEL = np.array([[0.0, 1.0, 0.0], [1.0, 4.0, 1.0], [0.0, 1.0, 0.0]])
_RED_BLUE_KERNEL = np.array([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]])


def demosaic_bayer(mosaic: np.ndarray, pattern: str) -> np.ndarray:
    """Bilinear demosaic of a raw Bayer mosaic into an RGB frame.

    Parameters
    ----------
    mosaic : (H, W) array
        Raw frame, one colour sample per pixel, indexed ``[row, col]``.
    pattern : str
        The filter colours of the 2 x 2 cell at the first pixel, row by row (``BAYER_PATTERNS``:
        ``"RGGB"`` has red at (0, 0), green at (0, 1) and (1, 0), blue at (1, 1)).

    Returns
    -------
    (H, W, 3) float64 array
        Red, green and blue at every pixel: the pixel's own sample for its colour, the mean of
        the nearest samples of each other colour (normalised convolution, edges reflected).

    Raises
    ------
    InputError
        Unknown pattern or a mosaic that is not 2-D.
    """
    name = str(pattern).upper()
    if name not in BAYER_PATTERNS:
        raise InputError(f"unknown Bayer pattern {pattern!r}; expected one of {', '.join(BAYER_PATTERNS)}")
    mosaic = np.asarray(mosaic, dtype=np.float64)
    if mosaic.ndim != 2:
        raise InputError(f"a Bayer mosaic is one 2-D frame, got shape {mosaic.shape}")
    import cv2  # for raw mosaics only: a process reading mono frames does not load OpenCV here

    rgb = np.empty(mosaic.shape + (3,))
    cell = np.array(list(name)).reshape(2, 2)
    for channel, colour in enumerate("RGB"):
        sites = np.zeros(mosaic.shape)
        for dr, dc in zip(*np.nonzero(cell == colour)):
            sites[dr::2, dc::2] = 1.0
        kernel = _GREEN_KERNEL if colour == "G" else _RED_BLUE_KERNEL
        total = cv2.filter2D(mosaic * sites, cv2.CV_64F, kernel, borderType=cv2.BORDER_REFLECT_101)
        weight = cv2.filter2D(sites, cv2.CV_64F, kernel, borderType=cv2.BORDER_REFLECT_101)
        rgb[..., channel] = total / weight
    return rgb


def read_image(path: str | Path, *, bayer: str | None = None) -> tuple[np.ndarray, ImageMeta]:
    """Read a frame from disk as a 2-D ``float64`` array plus metadata.

    Parameters
    ----------
    path : str or Path
        FITS (``.fits``, ``.fit``, ``.fts``, optionally ``.gz``), PNG, TIFF or JPEG file.
    bayer : str, optional
        The file is a raw Bayer mosaic with this 2 x 2 pattern (``BAYER_PATTERNS``, e.g.
        ``"RGGB"``): it is demosaiced (:func:`demosaic_bayer`) and weighted to luminance.

    Returns
    -------
    image : (H, W) float64 array
        Pixel values in ADU, indexed ``[row, col]``; colour converted to luminance,
        non-finite pixels and pixels beyond +-``MAX_ABS_ADU`` replaced by the median of the others
        (and marked in ``meta.invalid``).
    meta : ImageMeta
        Header, saturation level, channel count and the mask of replaced pixels.

    Raises
    ------
    FrameError
        Missing, corrupt or truncated file; unsupported format or shape; no usable pixel; a
        ``bayer`` frame that is not one 2-D mosaic.
    InputError
        Unknown ``bayer`` pattern.
    """
    if bayer is not None and str(bayer).upper() not in BAYER_PATTERNS:
        raise InputError(f"unknown Bayer pattern {bayer!r}; expected one of {', '.join(BAYER_PATTERNS)}")
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
    raw = np.asarray(raw)
    if bayer is not None:
        if raw.ndim == 3 and raw.shape[-1] == 1:
            raw = raw[..., 0]
        if raw.ndim != 2:
            raise FrameError(f"{path}: a Bayer mosaic ({bayer}) is one 2-D frame, got shape {raw.shape}")
        if raw.dtype.kind not in "biuf":
            raise FrameError(f"{path}: pixels of type {raw.dtype}; expected integer or real (float) pixels")
        if min(raw.shape) < 3:
            raise FrameError(f"{path}: image is too small ({raw.shape})")
        # Non-finite samples would spread to their neighbours' colours: they are marked (below) first.
        with np.errstate(invalid="ignore", over="ignore"):
            samples = raw.astype(np.float64)
            bad = ~np.isfinite(samples) | (np.abs(samples) > MAX_ABS_ADU)
            if bad.all():
                raise FrameError(f"{path}: every pixel is NaN, infinite or beyond +-{MAX_ABS_ADU:g} ADU")
            samples[bad] = np.median(samples[~bad])
            raw = demosaic_bayer(samples, bayer)
            if bad.any():
                raw[bad] = np.nan
    image, channels = _to_luminance(raw, path)
    if bayer is not None:
        channels = 1  # the file holds one sample per pixel
    if image.size == 0 or min(image.shape) < 3:
        raise FrameError(f"{path}: image is too small ({image.shape})")
    # a value beyond MAX_ABS_ADU (e.g. BSCALE = 1e300) is no detector's count and would overflow the
    # background and centroid arithmetic: it is a bad pixel like a NaN
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(image) & (np.abs(image) <= MAX_ABS_ADU)
    invalid = None
    if not finite.all():
        if not finite.any():
            raise FrameError(f"{path}: every pixel is NaN, infinite or beyond +-{MAX_ABS_ADU:g} ADU")
        invalid = ~finite
        image = np.where(finite, image, np.median(image[finite]))
        log.info("%s: %d non-finite or out-of-range pixels replaced by the median", path, int(invalid.sum()))
    meta = ImageMeta(
        path=str(path),
        file_format=file_format,
        header=header,
        channels=channels,
        saturation_adu=saturation,
        invalid=invalid,
        lossy=file_format == "jpeg",
        bayer=None if bayer is None else str(bayer).upper(),
    )
    return image, meta
