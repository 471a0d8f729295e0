"""A reader of plain FITS files without astropy: the frames opnav and most cameras write.

Importing ``astropy.io.fits`` costs a process ~0.2-0.3 s of CPU (``astropy.units`` with it), a
quarter of a one-frame ``opnav solve``. :func:`read_plain_fits` reads the common kind of FITS file
itself and returns exactly what :func:`opnav.image.io.read_image`'s astropy path returns (the same
pixel values and type, the same keyword values); any file outside that kind gives ``None`` and goes
to astropy, which reads it (or refuses it) as before. The kind, checked in full before any pixel
is used:

1. Every HDU a primary array or an ``IMAGE`` extension (``PCOUNT = 0``, ``GCOUNT = 1``), its
   mandatory keywords in the standard's order (FITS 4.0, section 4.4.1), the file exactly as long as
   its headers and padded data say (astropy warns about a short or padded-out file).
2. Every card printable ASCII in the fixed or free format of the standard (section 4.2): a keyword
   of ``A-Z 0-9 _ -``, ``= `` and a string (``''`` for a quote), ``T``/``F``, an integer or a real
   (``E`` or ``D`` exponent), then spaces or a ``/`` comment; ``COMMENT``, ``HISTORY`` and blank
   keywords as commentary. ``CONTINUE``, ``HIERARCH``, complex and undefined values, lower-case
   exponents or keywords: astropy's.
3. Pixels stored as ``BITPIX`` 8, 16, 32, 64, -32 or -64 with no scaling (``BZERO = 0`` and
   ``BSCALE = 1``, or absent) or the unsigned offsets astropy reads as ``uint16``/``uint32``/``uint64``
   (``BZERO = 2**15``, ``2**31``, ``2**63`` with ``BSCALE = 1``), and no ``BLANK``: astropy scales other
   values to float and rewrites the header's ``BITPIX``, ``BZERO`` and ``BSCALE``.

A keyword that appears twice is astropy's too. The header is a :class:`PlainHeader`: keyword -> value
(``str``, ``bool``, ``int`` or ``float``, as astropy gives them), case-insensitive, read-only.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

#: FITS headers and data come in blocks of 2880 bytes, 36 cards of 80 characters.
BLOCK = 2880
CARD = 80
#: Big-endian pixel types of ``BITPIX``.
_PIXELS = {8: "u1", 16: ">i2", 32: ">i4", 64: ">i8", -32: ">f4", -64: ">f8"}
#: ``BZERO`` with ``BSCALE = 1`` that astropy reads as unsigned integers, by ``BITPIX``.
_UNSIGNED = {16: (2**15, np.uint16), 32: (2**31, np.uint32), 64: (2**63, np.uint64)}
_COMMENTARY = ("COMMENT", "HISTORY", "")
_KEYWORD = re.compile(rb"[A-Z0-9_-]*")
_PRINTABLE = re.compile(rb"[ -~]*")
#: A value after ``= `` (FITS 4.0 section 4.2 in its fixed and free formats), then an optional comment.
_VALUE = re.compile(
    rb" *(?:'(?P<string>(?:[ -&(-~]|'')*?) *'"
    rb"|(?P<logical>[TF])"
    rb"|(?P<real>[+-]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[DE][+-]?[0-9]+)?))"
    rb" *(?:/[ -~]*)?")


class PlainHeader:
    """A FITS header's keywords and values (module docstring), read like ``astropy.io.fits.Header``:
    ``key in header``, ``header[key]``, ``header.get(key, default)``, ``len``, iteration over keywords."""

    def __init__(self, values: dict[str, object], commentary: dict[str, tuple[str, ...]]) -> None:
        self._values = dict(values)
        self._values.update(commentary)

    def __contains__(self, key) -> bool:
        return isinstance(key, str) and key.upper() in self._values

    def __getitem__(self, key: str):
        return self._values[key.upper()]

    def get(self, key: str, default=None):
        return self._values.get(key.upper(), default) if isinstance(key, str) else default

    def __iter__(self):
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def keys(self):
        return self._values.keys()

    def items(self):
        return self._values.items()

    def copy(self) -> PlainHeader:
        return PlainHeader(self._values, {})

    def __repr__(self) -> str:
        return f"PlainHeader({self._values!r})"


def _value(field: bytes):
    """The value of a card's field after ``= ``, or ``None`` when it is not of the plain kind."""
    match = _VALUE.fullmatch(field)
    if match is None:
        return None
    if match.group("string") is not None:
        return match.group("string").decode("ascii").replace("''", "'")
    if match.group("logical") is not None:
        return match.group("logical") == b"T"
    text = match.group("real").decode("ascii")
    if any(mark in text for mark in ".ED"):
        return float(text.replace("D", "E"))
    return int(text)


def _header(data: bytes, start: int) -> tuple[dict, dict, int] | None:
    """``(values, commentary, end)`` of the header starting at byte ``start`` (``end``: where its data
    begins), or None when a card is not of the plain kind or the header has no ``END``."""
    values: dict[str, object] = {}
    commentary: dict[str, list[str]] = {}
    position = start
    while position + BLOCK <= len(data):
        block = data[position:position + BLOCK]
        position += BLOCK
        if _PRINTABLE.fullmatch(block) is None:
            return None
        for offset in range(0, BLOCK, CARD):
            card = block[offset:offset + CARD]
            keyword = card[:8].rstrip(b" ")
            if keyword == b"END":
                if card[8:].strip(b" ") or block[offset + CARD:].strip(b" "):
                    return None  # astropy reads cards after END, or warns about them
                return values, {k: tuple(v) for k, v in commentary.items()}, position
            if _KEYWORD.fullmatch(keyword) is None or b" " in keyword:
                return None
            name = keyword.decode("ascii")
            if name in _COMMENTARY:
                commentary.setdefault(name, []).append(card[8:].decode("ascii").rstrip())
                continue
            if card[8:10] != b"= " or name in ("CONTINUE", "HIERARCH"):
                return None
            value = _value(card[10:])
            if value is None:
                return None
            if name in values:
                return None  # astropy reads a repeated keyword its own way (and a repeated NAXISn as the data's)
            values[name] = value
    return None


def _mandatory(values: dict) -> tuple[tuple[int, ...], int] | None:
    """``(axes as NAXIS1..n, BITPIX)`` of a header with the standard's mandatory keywords, or None."""
    bitpix, naxis = values.get("BITPIX"), values.get("NAXIS")
    if type(bitpix) is not int or bitpix not in _PIXELS or type(naxis) is not int or not 0 <= naxis <= 999:
        return None
    axes = tuple(values.get(f"NAXIS{k}") for k in range(1, naxis + 1))
    if any(type(size) is not int or size < 0 for size in axes):
        return None
    return axes, bitpix


def _keyword_order(data: bytes, start: int) -> list[str]:
    """The keywords of the header at ``start`` in their order (commentary cards left out)."""
    names = []
    position = start
    while True:
        for offset in range(position, position + BLOCK, CARD):
            name = data[offset:offset + 8].rstrip(b" ").decode("ascii")
            if name == "END":
                return names
            if name not in _COMMENTARY:
                names.append(name)
        position += BLOCK


def read_plain_fits(path: Path) -> tuple[np.ndarray, PlainHeader] | None:
    """The first 2-D or 3-D image of a plain FITS file (module docstring) and its HDU's header, as the
    astropy path of :func:`opnav.image.io.read_image` gives them; None for a file of another kind.

    Parameters
    ----------
    path : Path
        An uncompressed FITS file.

    Returns
    -------
    (pixels, header) or None
        The pixels indexed ``[row, col]`` (or ``[channel, row, col]``: FITS axis order reversed), in
        astropy's type for the file's ``BITPIX``, ``BZERO`` and ``BSCALE``; the header's keywords.
    """
    data = path.read_bytes()
    start, found = 0, None
    while start < len(data):
        parsed = _header(data, start)
        if parsed is None:
            return None
        values, commentary, end = parsed
        names = _keyword_order(data, start)
        first = "SIMPLE" if start == 0 else "XTENSION"
        if start == 0 and values.get("SIMPLE") is not True:
            return None
        if start > 0 and (values.get("XTENSION") != "IMAGE" or values.get("PCOUNT", 0) != 0
                          or values.get("GCOUNT", 1) != 1):
            return None
        shape = _mandatory(values)
        if shape is None:
            return None
        axes, bitpix = shape
        expected = [first, "BITPIX", "NAXIS", *(f"NAXIS{k}" for k in range(1, len(axes) + 1))]
        if start > 0:
            expected += ["PCOUNT", "GCOUNT"]
        if names[:len(expected)] != expected or "BLANK" in values or values.get("GROUPS") is not None:
            return None
        size = abs(bitpix) // 8 * int(np.prod(axes, dtype=object)) if axes else 0
        padded = -(-size // BLOCK) * BLOCK
        if end + padded > len(data):
            return None  # short: astropy warns, read_image refuses
        if found is None and len(axes) in (2, 3) and size:
            pixels = _pixels(data, end, axes, bitpix, values)
            if pixels is None:
                return None
            found = (pixels, PlainHeader(values, commentary))
        start = end + padded
    return found


def _pixels(data: bytes, start: int, axes: tuple[int, ...], bitpix: int, values: dict) -> np.ndarray | None:
    """The pixels of an HDU, unscaled or read as astropy's unsigned type; None for other scalings."""
    zero, scale = values.get("BZERO", 0), values.get("BSCALE", 1)
    if type(zero) not in (int, float) or type(scale) not in (int, float) or scale != 1:
        return None
    count = int(np.prod(axes))
    pixels = np.frombuffer(data, dtype=_PIXELS[bitpix], count=count, offset=start).reshape(axes[::-1])
    if zero == 0:
        return pixels.copy()
    if bitpix in _UNSIGNED and zero == _UNSIGNED[bitpix][0]:
        unsigned = _UNSIGNED[bitpix][1]
        # the stored signed value plus 2**(bits - 1) is its sign bit flipped: astropy's unsigned reading
        return pixels.astype(pixels.dtype.newbyteorder("=")).view(unsigned) ^ unsigned(zero)
    return None
