"""opnav.image.fits_simple against astropy: whatever the plain reader reads, astropy reads the same."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from opnav.errors import FrameError
from opnav.image.fits_simple import read_plain_fits
from opnav.image.io import _read_fits_astropy, read_image


def _astropy(path: Path):
    """astropy's (pixels, header as a dict) of the file, or None when read_image's astropy path refuses it."""
    try:
        raw, header = _read_fits_astropy(path)
    except FrameError:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        values = {key: header[key] for key in header if key not in ("COMMENT", "HISTORY", "")}
    return raw, values


def _same(plain, reference) -> None:
    raw, header = plain
    assert reference is not None, "astropy refuses a file the plain reader read"
    ref_raw, ref_header = reference
    assert raw.dtype == ref_raw.dtype and raw.shape == ref_raw.shape
    assert np.array_equal(raw, ref_raw, equal_nan=True)
    values = {key: value for key, value in header.items() if key not in ("COMMENT", "HISTORY", "")}
    assert values == ref_header
    assert all(type(values[key]) is type(ref_header[key]) for key in values)


def _write(path: Path, data: np.ndarray, cards: dict | None = None, extension: bool = False) -> Path:
    header = fits.Header(cards or {})
    hdus = [fits.PrimaryHDU(), fits.ImageHDU(data, header=header)] if extension else \
        [fits.PrimaryHDU(data, header=header)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fits.HDUList(hdus).writeto(path, overwrite=True)
    return path


CARDS = {"DATE-OBS": "2014-07-15T00:58:52.316274", "EXPTIME": 1.5, "GAIN": 2, "FLAG": True, "NOTE": "it''s ok",
         "BIG": 12345678901234567890, "TINY": 1.5e-300, "EMPTY": "", "COMMENT": "a comment", "HISTORY": "made here"}


@pytest.mark.parametrize("dtype", ["u1", ">i2", ">i4", ">i8", ">f4", ">f8", "uint16", "uint32", "uint64", "int8"])
@pytest.mark.parametrize("extension", [False, True])
def test_written_frames_read_as_astropy_reads_them(tmp_path, dtype, extension):
    rng = np.random.default_rng(3)
    data = rng.integers(0, 200, (7, 9)).astype(dtype) if np.dtype(dtype).kind in "iu" else \
        rng.normal(0.0, 1e3, (7, 9)).astype(dtype)
    if np.dtype(dtype).kind == "f":
        data[2, 3] = np.nan
    path = _write(tmp_path / "f.fits", data, CARDS, extension)
    plain = read_plain_fits(path)
    if dtype == "int8":  # stored as BITPIX 8 with BZERO = -128: astropy rewrites the header, the plain reader declines
        assert plain is None
        return
    assert plain is not None
    _same(plain, _astropy(path))


def test_colour_cube_and_first_image_hdu(tmp_path):
    cube = np.arange(3 * 5 * 6, dtype=">i2").reshape(3, 5, 6)
    _same(read_plain_fits(_write(tmp_path / "c.fits", cube)), _astropy(tmp_path / "c.fits"))
    line = fits.ImageHDU(np.arange(10, dtype=">i2"))  # a 1-D HDU before the image is skipped, as astropy does
    fits.HDUList([fits.PrimaryHDU(), line, fits.ImageHDU(np.ones((4, 4), ">f4"))]).writeto(tmp_path / "m.fits")
    _same(read_plain_fits(tmp_path / "m.fits"), _astropy(tmp_path / "m.fits"))


def test_demo_frame_reads_as_astropy_reads_it(tmp_path):
    from opnav.render.frames_io import write_frame  # noqa: F401 - the writer of the demo's frames

    demo = Path("/tmp/hD/demo/frames/frame_00000.fits")
    path = demo if demo.is_file() else _write(tmp_path / "d.fits", np.zeros((64, 64), np.uint16), CARDS)
    _same(read_plain_fits(path), _astropy(path))


def _mutations(data: bytes, rng: np.random.Generator, count: int):
    """Damaged copies of a file: bytes changed in its header, a card replaced, cut short, padded out."""
    header_end = data.index(b"END" + b" " * 77) + 80
    for _ in range(count):
        damaged = bytearray(data)
        kind = rng.integers(0, 7)
        if kind == 0:
            for _ in range(int(rng.integers(1, 4))):
                damaged[int(rng.integers(0, header_end))] = int(rng.integers(0, 256))
        elif kind == 1:
            position = int(rng.integers(0, header_end // 80)) * 80
            damaged[position:position + 80] = rng.choice(_CARD_VARIANTS).ljust(80)[:80]
        elif kind == 2:
            damaged = damaged[:int(rng.integers(0, len(damaged)))]
        elif kind == 3:
            damaged += bytes(int(rng.integers(1, 6000)))
        elif kind == 4:
            position = int(rng.integers(0, header_end // 80)) * 80
            value = bytes(rng.choice(list(b" 0123456789+-.EDTF'/()&abcXYZ"), int(rng.integers(1, 25))))
            damaged[position + 10:position + 10 + len(value)] = value
        else:  # a card added before END (the block has room): a variant, or a keyword of random value
            card = rng.choice(_CARD_VARIANTS) if kind == 5 else b"ADDED   = " + _random_value(rng)
            damaged[header_end - 80:header_end + 80] = card.ljust(80)[:80] + b"END".ljust(80)
        yield bytes(damaged)


def _random_value(rng: np.random.Generator) -> bytes:
    """A card value of a random form: a real in any notation, an integer, a string, a logical, or noise."""
    form = int(rng.integers(0, 5))
    if form == 0:
        text = rng.choice(["%r", "%.3e", "%.17g", "%.0f", "%+.5E", "%.1f"]) % float(rng.normal() * 10.0 ** rng.integers(-320, 320))
        text = text.replace("e", rng.choice(["E", "D", "e"])).replace("inf", "1E999")
    elif form == 1:
        text = str(int(rng.integers(-10**12, 10**12))).rjust(int(rng.integers(1, 21)))
    elif form == 2:
        text = "'" + "".join(rng.choice(list(" abc'XYZ-/&"), int(rng.integers(0, 12)))) + "'"
    elif form == 3:
        text = rng.choice(["T", "F", " T", "t"])
    else:
        text = "".join(rng.choice(list(" 0123456789+-.EDTF'/()"), int(rng.integers(1, 12))))
    return (text + rng.choice(["", " / a comment", "/x", "   "])).encode()


_CARD_VARIANTS = [b"CONTINUE  'more'", b"HIERARCH ESO DET = 3", b"LOWER   = 1.5e3", b"CPLX    = (1.0, 2.0)",
                  b"UNDEF   =", b"BLANK   = -32768", b"BZERO   = 10", b"BSCALE  = 2.0", b"NAXIS   = 3",
                  b"NAXIS1  = -4", b"BITPIX  = 12", b"XTENSION= 'BINTABLE'", b"END", b"SIMPLE  = F",
                  b"DUP     = 'one'", b"EXPTIME = 1.5D2", b"GAIN    = .5", b"GAIN    = 5.", b"GAIN    = +7",
                  b"STR     = 'a''b' / c", b"STR     = 'unterminated", b"KEY     = 1 2", b"key     = 1",
                  b"COMMENT   anything at all", b"        blank keyword", b"DATE-OBS= '2014-07-15T00:58:52'"]


@pytest.mark.filterwarnings("ignore")
def test_damaged_files_are_read_as_astropy_reads_them_or_left_to_it(tmp_path):
    # the property the fast path rests on: a file it reads, astropy reads with the same pixels and values;
    # every other file (None) goes to astropy, which reads or refuses it as before
    rng = np.random.default_rng(11)
    sources = [
        _write(tmp_path / "a.fits", rng.integers(0, 60000, (6, 5)).astype(np.uint16), CARDS),
        _write(tmp_path / "b.fits", rng.normal(size=(4, 7)).astype(">f4"), {"EXPTIME": 2.0}, extension=True),
    ]
    read, declined = 0, 0
    for source in sources:
        for k, damaged in enumerate(_mutations(source.read_bytes(), rng, 600)):
            path = tmp_path / f"m{k}.fits"
            path.write_bytes(damaged)
            plain = read_plain_fits(path)
            if plain is None:
                declined += 1
                continue
            read += 1
            _same(plain, _astropy(path))
    assert read > 150 and declined > 150  # both sides of the property were exercised


def test_read_image_gives_the_same_frame_either_way(tmp_path, monkeypatch):
    from opnav.image import fits_simple

    data = np.random.default_rng(5).integers(0, 65535, (16, 12)).astype(np.uint16)
    path = _write(tmp_path / "f.fits", data, {**CARDS, "SATURATE": 50000.0})
    image, meta = read_image(path)
    monkeypatch.setattr(fits_simple, "read_plain_fits", lambda _: None)
    image_astropy, meta_astropy = read_image(path)
    assert np.array_equal(image, image_astropy) and image.dtype == image_astropy.dtype
    assert meta.saturation_adu == meta_astropy.saturation_adu == 50000.0
    assert type(meta.header).__name__ == "PlainHeader" and isinstance(meta_astropy.header, fits.Header)
    assert meta.header["date-obs"] == meta_astropy.header["DATE-OBS"] and "GAIN" in meta.header


def test_a_plain_frame_is_read_without_importing_astropy(tmp_path):
    import subprocess
    import sys

    path = _write(tmp_path / "f.fits", np.ones((8, 8), np.uint16), CARDS)
    script = (f"import sys; from opnav.image.io import read_image; image, meta = read_image({str(path)!r}); "
              "print(meta.header['EXPTIME'], 'astropy' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["1.5", "False"]


def test_gzip_frames_still_go_to_astropy(tmp_path):
    import gzip

    path = _write(tmp_path / "f.fits", np.ones((8, 8), np.uint16), CARDS)
    packed = tmp_path / "f.fits.gz"
    packed.write_bytes(gzip.compress(path.read_bytes()))
    image, meta = read_image(packed)
    assert isinstance(meta.header, fits.Header) and image.shape == (8, 8)
