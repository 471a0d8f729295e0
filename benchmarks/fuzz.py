"""Fuzz the readers and a few commands with mutated inputs; print the tally of outcomes.

Run: ``.venv/bin/python benchmarks/fuzz.py [--inputs 100000] [--seconds 600] [--seed 0] [--out out/fuzz]``

Targets (each input is written to a scratch file and read in this process):

- ``fits``, ``png``, ``tiff``, ``jpeg``: :func:`opnav.image.io.read_image` on frames built with
  odd shapes (1x1, 0-size, 1-D, 3-D colour and cubes, 4-D), storage types (8/16/32/64-bit,
  float, complex, bool), contents (NaN, inf, huge, constant), header keywords of the wrong
  type, then in half the cases byte-mutated behind the format's magic (PNG chunks get their
  CRC recomputed so the damage reaches the decoder; FITS header cards get wrong values);
- ``scenario``, ``navigation``, ``runfile``: :func:`opnav.sim.scene.load_scene`,
  :func:`opnav.filters.options.load_navigation`, :func:`opnav.studies.settings.load_run_file`
  on the sample files with one or two values replaced (a string, a bool, a negative, NaN,
  a huge number, an empty array, a nested table, a date), keys deleted, renamed or added,
  tables replaced by scalars, deep nesting, or the text byte-mutated; run files also get
  ``--set`` overrides;
- ``csv``: :func:`opnav.records.read_csv` on a short measurement file (every kind) with cells
  replaced per column (text, NaN, inf, empty, huge, wrong count of values), columns or rows
  dropped, duplicated or swapped, or the bytes mutated;
- ``catalog``: :func:`opnav.catalog.load_catalog` on a 20-star ``.npz`` (plain and compressed)
  with columns of the wrong type, shape or length, NaN, a bad format version, or bytes mutated;
- ``cli-centroid``, ``cli-solve``, ``cli-navigate``: :func:`opnav.cli.main` on mutated frames
  and measurement files, at a lower rate (they are slower).

The classes of issue 40 (each target belongs to one class; the table at the end is per class):

- *inconsistent headers* (``headers``, ``cli-headers``): a small frame with an opnav header whose
  epoch, WCS, detector or observer keywords are given text, NaN-like, extreme or shifted values
  (a date a day or a century off, a WCS degrees off, no WCS), through
  :func:`opnav.image.pipeline.frame_input`, :func:`~opnav.image.header.wcs_hint` and
  ``opnav centroid``/``opnav solve``;
- *extreme values* (``extreme --set``): every numeric setting of every study's sample run file
  set to 1e300, 1e-300, -1, 0, nan, inf, -inf, 1e308 or 5e-324 through
  :func:`opnav.studies.settings.load_run_file` (where values enter);
- *special files* (``special files``): a FIFO, ``/dev/zero``, ``/dev/null``, a folder, a dangling
  symlink or a symlink to one of them as every file argument of every reader and of
  ``opnav centroid``/``solve``/``navigate``/``run``/``process --camera``;
- *environment* (``environment``): ``OPNAV_CACHE`` in a place that cannot be written (under a
  file, under ``/proc``, a dangling symlink), ``--out`` in such a place or in a folder removed
  before the run, and stdout closed by its reader (``BrokenPipeError``: exit 141, nothing on
  stderr); an output a command reports as written must exist (else *lost*).

Outcomes (the table's columns: clear error, correct, unclear, traceback, hang, wrong, lost).
A reader input is *accepted* (correct) when it returns a result that passes a validity check
(finite 2-D frame of at least 3x3, finite initial state, ...), an *opnav error* when it raises
a subclass of :class:`opnav.errors.OpnavError`, and a *finding* otherwise: any other exception,
an invalid result, a ``RuntimeWarning`` raised inside opnav (made an error, as in the test
configuration) or a hang (per-input ``SIGALRM`` timeout: ``--timeout`` for a reader,
``--command-timeout`` for a command, which may build a pattern index for a new field of view). A command is accepted with exit
status 0, 1 (``solve``: no solution), 2 with one line on stderr, or 3; a traceback or another
status is a finding. Each finding type is listed with its first message, the deepest opnav
frame, the last frame, and a reproducer saved under ``--out``. Exit status 0 when nothing was
found, 1 otherwise.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import math
import os
import random
import re
import shutil
import signal
import struct
import sys
import tempfile
import time
import traceback
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomli_w

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "samples"
DEMO = ROOT / "opnav" / "data" / "demo.toml"


#: A log line in the CLI's format (opnav.cli: "%(levelname)s %(name)s: %(message)s").
LOG_LINE = re.compile(r"^(DEBUG|INFO|WARNING) [\w.]+: ")


def stderr_lines(text: str) -> list[str]:
    """The lines of a command's stderr that are not its log notes, ``warning:`` notes or progress bars
    (a bar rewrites its line with carriage returns: what is left after the last one counts)."""
    lines = [ln.rsplit("\r", 1)[-1] for ln in text.splitlines()]
    return [ln for ln in lines if ln.strip() and not ln.startswith("warning:") and not LOG_LINE.match(ln)]


class Hang(BaseException):
    """Raised by the SIGALRM handler when one input runs past the per-input timeout.

    A ``BaseException``: readers that turn every ``Exception`` of a library into their own error
    (``except Exception``) must not swallow it and report a hang as a corrupt file."""


class InvalidResult(Exception):
    """A reader returned a result that fails the validity check (a silent bad value), or a command
    exited 0 (or with another status) where it should have refused: the table's *wrong*."""


class Unclear(Exception):
    """A command refused (exit 2) but not in one line of its own: the table's *unclear*."""


class TracebackPrinted(Exception):
    """A command printed a traceback on stderr (whatever its exit status)."""


class Lost(Exception):
    """A command said it wrote an output that is not there: the table's *lost*."""


#: The table's finding columns, by the exception a finding raised (anything else is a traceback).
FINDING_KINDS = {"Hang": "hang", "InvalidResult": "wrong", "Unclear": "unclear", "Lost": "lost"}


def _alarm(signum, frame):  # noqa: ARG001 - signal handler signature
    raise Hang("input ran past the per-input timeout")


# --------------------------------------------------------------------------------------------
# Value pools and byte mutations
# --------------------------------------------------------------------------------------------

def _toml_pool() -> list:
    import datetime as dt

    return [
        "text", "", " ", "nan", "inf", "-inf", "-1", "1e999", "true", "none", "∞", "\x00", "x" * 2000,
        True, False, 0, -1, -7, 1, 3, 2**63 - 1, -(2**63), 10**30, 0.0, -0.0, -1.5, 1e-320, 1e308, -1e308,
        float("nan"), float("inf"), float("-inf"), [], [1], [1, 2], ["a", "b"], [[1, 2, 3]], [1.0, "a", True],
        [float("nan")] * 3, [1e308] * 3, {}, {"x": 1}, {"nested": {"deep": [1]}}, [{"a": 1}],
        dt.date(2014, 7, 15), dt.datetime(2014, 7, 15, 0, 0), dt.time(12, 0), dt.datetime(1, 1, 1),
    ]


TOML_POOL = _toml_pool()
CSV_POOL = [
    "abc", "nan", "NaN", "inf", "-inf", "", " ", "1e400", "-1e400", "1e-400", "9" * 5000, "0", "-0", "-1", "1",
    "3", "1 2", "1 2 3", "1 2 3 4", "1 2 3 4 5 6 7 8 9 10", "0x10", "1_000", "١٢", "1e5", "1.5", "2.5e10",
    "\x00", "\"", "'", "radec", "los", "starlight", "position", "rad", "deg", "arcsec", "km", "km/s", "1",
    "nan nan", "inf 0 0 inf", "1e308 1e308 1e308 1e308", "-1 0 0 -1", "0 0 0 0", "1 2 3 4 5 6 7 8 9",
]
INTERESTING_BYTES = (0x00, 0x01, 0x7F, 0x80, 0xFF, 0x20, 0x0A, 0x0D, 0x2C, 0x22, 0x3D, 0x5B, 0x5D)
INTERESTING_WORDS = (0, 1, 0x7F, 0x80, 0xFF, 0x7FFF, 0x8000, 0xFFFF, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF)


def mutate_bytes(r: random.Random, data: bytes, keep: int = 0, rounds: int | None = None) -> bytes:
    """``data`` with 1-4 random byte edits after the first ``keep`` bytes (the format's magic)."""
    buf = bytearray(data)
    for _ in range(rounds or r.randint(1, 4)):
        n = len(buf)
        if n <= keep:
            buf += bytes(r.randrange(256) for _ in range(r.randint(1, 8)))
            continue
        pos = r.randrange(keep, n)
        op = r.randrange(9)
        if op == 0:
            buf[pos] ^= 1 << r.randrange(8)
        elif op == 1:
            buf[pos] = r.randrange(256)
        elif op == 2:
            buf[pos] = r.choice(INTERESTING_BYTES)
        elif op == 3:
            buf[pos:pos] = bytes(r.randrange(256) for _ in range(r.randint(1, 16)))
        elif op == 4:
            del buf[pos:pos + r.randint(1, 64)]
        elif op == 5:
            del buf[r.randint(keep, n):]
        elif op == 6:
            start = r.randrange(keep, n)
            buf[pos:pos] = buf[start:start + r.randint(1, 128)]
        elif op == 7:
            fmt = r.choice(("<I", ">I", "<H", ">H"))
            word = r.choice(INTERESTING_WORDS) & (0xFFFF if fmt.endswith("H") else 0xFFFFFFFF)
            buf[pos:pos + struct.calcsize(fmt)] = struct.pack(fmt, word)
        else:
            text = str(r.choice(("nan", "-1", "0", "1e999", "99999999999", "'", "[", "{", "\n", ",")))
            buf[pos:pos + r.randint(0, 4)] = text.encode()
    return bytes(buf)


# --------------------------------------------------------------------------------------------
# Frames
# --------------------------------------------------------------------------------------------

SHAPES_2D = [(16, 16), (1, 1), (2, 2), (3, 3), (1, 64), (64, 1), (2, 40), (5, 17), (32, 24), (64, 64)]
SHAPES_ODD = [(0, 0), (0, 16), (16,), (3, 16, 16), (4, 8, 8), (2, 8, 8), (1, 8, 8), (5, 8, 8),
              (16, 16, 3), (16, 16, 4), (16, 16, 2), (2, 2, 4, 4), (1, 1, 1)]
INT_DTYPES = (np.uint8, np.int8, np.uint16, np.int16, np.uint32, np.int32, np.int64)
FLOAT_DTYPES = (np.float32, np.float64)


def pixel_array(r: random.Random, rng: np.random.Generator, shape, dtype) -> np.ndarray:
    """Pixels of ``shape`` and ``dtype``: noise, a star, constant, NaN/inf-filled or extreme values."""
    kind = r.choice(("noise", "noise", "star", "zeros", "nan", "some_nan", "inf", "huge", "tiny", "ramp"))
    size = int(np.prod(shape)) if len(shape) else 1
    info = np.iinfo(dtype) if np.issubdtype(dtype, np.integer) else None
    if kind == "noise":
        values = rng.normal(100.0, 5.0, size)
    elif kind == "star":
        values = rng.normal(100.0, 3.0, size)
        if size:
            values[size // 2] += 5000.0
    elif kind == "zeros":
        values = np.zeros(size)
    elif kind == "ramp":
        values = np.arange(size, dtype=float)
    elif kind == "huge":
        values = np.full(size, info.max if info else 1e308 * r.choice((1, -1)))
    elif kind == "tiny":
        values = np.full(size, info.min if info else 5e-324)
    else:
        values = rng.normal(100.0, 5.0, size)
        if info is None and size:
            bad = {"nan": np.nan, "inf": np.inf}.get(kind, np.nan)
            if kind == "some_nan":
                values[rng.random(size) < 0.3] = r.choice((np.nan, np.inf, -np.inf))
            else:
                values[:] = bad
    if info is not None:
        values = np.clip(np.nan_to_num(values), info.min, info.max)
    return values.astype(dtype).reshape(shape)


def fits_frame(r: random.Random, rng: np.random.Generator) -> bytes:
    from astropy.io import fits

    shape = r.choice(SHAPES_2D if r.random() < 0.6 else SHAPES_ODD)
    dtype = r.choice(INT_DTYPES[2:] + FLOAT_DTYPES + (np.uint8,))
    data = pixel_array(r, rng, shape, dtype)
    layout = r.choice(("primary", "primary", "extension", "table_then_image", "table_only", "empty"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if layout == "primary":
            hdus = [fits.PrimaryHDU(data)]
        elif layout == "extension":
            hdus = [fits.PrimaryHDU(), fits.ImageHDU(data)]
        elif layout == "table_then_image":
            table = fits.BinTableHDU.from_columns([fits.Column(name="a", format="E", array=np.arange(3.0))])
            hdus = [fits.PrimaryHDU(), table, fits.ImageHDU(data)]
        elif layout == "table_only":
            hdus = [fits.PrimaryHDU(), fits.BinTableHDU.from_columns([fits.Column(name="a", format="E",
                                                                                 array=np.arange(3.0))])]
        else:
            hdus = [fits.PrimaryHDU()]
        header = hdus[-1].header
        for key in r.sample(("SATURATE", "DATAMAX", "GAIN", "RDNOISE", "BIASLVL", "BZERO", "BSCALE"), r.randint(0, 3)):
            header[key] = r.choice((60000, 255.0, -1, 0, 1e300, "abc", "", True, False, 3))
        buf = io.BytesIO()
        fits.HDUList(hdus).writeto(buf, output_verify="silentfix")
    raw = buf.getvalue()
    if r.random() < 0.5:
        raw = fits_card_mutation(r, raw) if r.random() < 0.5 else mutate_bytes(r, raw, keep=10)
    return raw


FITS_KEYS = (b"BITPIX", b"NAXIS ", b"NAXIS1", b"NAXIS2", b"NAXIS3", b"BZERO ", b"BSCALE", b"SATURATE",
             b"DATAMAX", b"GAIN  ", b"EXTEND", b"GCOUNT", b"PCOUNT", b"XTENSION", b"SIMPLE")
FITS_VALUES = (b"8", b"16", b"32", b"64", b"-32", b"-64", b"7", b"0", b"-1", b"1", b"3", b"4", b"999999999",
               b"99999999999999999999", b"1E400", b"NAN", b"'abc'", b"T", b"F", b"''", b"1.5")


def fits_card_mutation(r: random.Random, raw: bytes) -> bytes:
    """A header card of ``raw`` given a wrong value (BITPIX 7, NAXIS1 huge, BZERO 'abc', ...)."""
    buf = bytearray(raw)
    cards = [i for i in range(0, min(len(buf), 2880 * 4), 80) if bytes(buf[i:i + 8]).startswith(FITS_KEYS)]
    for _ in range(r.randint(1, 2)):
        if not cards:
            break
        at = r.choice(cards)
        if bytes(buf[at:at + 6]) == b"SIMPLE" and r.random() < 0.8:
            continue  # keep the magic most of the time so the damage reaches the parser
        value = r.choice(FITS_VALUES)
        buf[at + 10:at + 30] = value.rjust(20)[:20]
    return bytes(buf)


def _png_chunks(raw: bytes) -> list[tuple[int, int]]:
    """(offset, length) of each chunk of a PNG byte string (stops at damage)."""
    chunks, pos = [], 8
    while pos + 12 <= len(raw):
        (length,) = struct.unpack(">I", raw[pos:pos + 4])
        if pos + 12 + length > len(raw):
            break
        chunks.append((pos, length))
        pos += 12 + length
    return chunks


def png_chunk_mutation(r: random.Random, raw: bytes) -> bytes:
    """Damage inside one PNG chunk with its CRC recomputed, so the decoder (not the CRC check) sees it;
    or an IHDR with a huge, zero or odd size, bit depth and colour type."""
    chunks = _png_chunks(raw)
    if not chunks:
        return mutate_bytes(r, raw, keep=8)
    buf = bytearray(raw)
    pos, length = chunks[0] if r.random() < 0.5 else r.choice(chunks)
    body = bytearray(buf[pos + 4:pos + 8 + length])  # type + data
    if body[:4] == b"IHDR" and r.random() < 0.7:
        width, height = r.choice(((0, 16), (16, 0), (1, 1), (2**31 - 1, 1), (100_000, 100_000), (30_000, 30_000),
                                  (16, 16), (65535, 65535), (1, 2**20)))
        body[4:12] = struct.pack(">II", width, height)
        if r.random() < 0.5:
            body[12] = r.choice((1, 2, 4, 8, 16, 3, 0, 32))
            body[13] = r.choice((0, 2, 3, 4, 6, 1, 7))
    else:
        body[4:] = mutate_bytes(r, bytes(body[4:]), rounds=r.randint(1, 3)) if len(body) > 4 else body[4:]
    new = struct.pack(">I", len(body) - 4) + bytes(body) + struct.pack(">I", zlib.crc32(bytes(body)) & 0xFFFFFFFF)
    buf[pos:pos + 12 + length] = new
    return bytes(buf)


def pillow_frame(r: random.Random, rng: np.random.Generator, fmt: str) -> bytes:
    from PIL import Image

    height, width = r.choice(SHAPES_2D)
    modes = ("L", "LA", "RGB", "RGBA", "P", "I;16", "1") if fmt == "png" else ("L", "RGB", "CMYK")
    mode = r.choice(modes)
    if mode in ("I;16",):
        img = Image.fromarray(pixel_array(r, rng, (height, width), np.uint16))
    elif mode == "I":
        img = Image.fromarray(pixel_array(r, rng, (height, width), np.int32))
    else:
        channels = {"L": 1, "P": 1, "1": 1, "LA": 2, "RGB": 3, "RGBA": 4, "CMYK": 4}[mode]
        base = pixel_array(r, rng, (height, width, channels) if channels > 1 else (height, width), np.uint8)
        img = Image.fromarray(base, {"P": "L", "1": "L"}.get(mode, mode) if channels == 1 else mode)
        if mode in ("P", "1"):
            img = img.convert(mode)
    buf = io.BytesIO()
    kwargs = {"quality": r.choice((1, 50, 95))} if fmt == "jpeg" else {}
    img.save(buf, format=fmt.upper(), **kwargs)
    raw = buf.getvalue()
    if r.random() < 0.5:
        if fmt == "png" and r.random() < 0.6:
            raw = png_chunk_mutation(r, raw)
        else:
            raw = mutate_bytes(r, raw, keep=8 if fmt == "png" else 2)
    return raw


def tiff_frame(r: random.Random, rng: np.random.Generator) -> bytes:
    import tifffile

    dtype = r.choice(INT_DTYPES + FLOAT_DTYPES + (np.float16, np.complex64, np.bool_))
    shape = r.choice(SHAPES_2D if r.random() < 0.6 else [s for s in SHAPES_ODD if 0 not in s])
    data = pixel_array(r, rng, shape, dtype if dtype not in (np.complex64, np.bool_) else np.float32)
    data = data.astype(dtype) if dtype is not np.bool_ else data > 100
    buf = io.BytesIO()
    kwargs = {}
    if len(shape) == 3 and shape[-1] in (3, 4) and dtype == np.uint8 and r.random() < 0.7:
        kwargs["photometric"] = "rgb"
    elif len(shape) >= 3:
        kwargs["photometric"] = "minisblack"
    if r.random() < 0.3:
        kwargs["compression"] = "zlib"
    try:
        tifffile.imwrite(buf, data, **kwargs)
    except Exception:  # noqa: BLE001 - tifffile refuses some combinations; write the plain array instead
        buf = io.BytesIO()
        tifffile.imwrite(buf, np.asarray(data, dtype=np.uint16) if data.dtype.kind == "c" else data)
    raw = buf.getvalue()
    if r.random() < 0.5:
        raw = mutate_bytes(r, raw, keep=4)
    return raw


def frame_input(r: random.Random, rng: np.random.Generator, fmt: str) -> bytes:
    if fmt == "fits":
        return fits_frame(r, rng)
    if fmt == "tiff":
        return tiff_frame(r, rng)
    return pillow_frame(r, rng, fmt)


# --------------------------------------------------------------------------------------------
# TOML, CSV and catalog mutations
# --------------------------------------------------------------------------------------------

def pool_value(r: random.Random):
    """A fresh copy of a :data:`TOML_POOL` value (a shared list put in a document and then edited there
    would change the pool, and in the end contain itself)."""
    import copy

    return copy.deepcopy(r.choice(TOML_POOL))


def _leaves(node, path=()):
    """Every (path, value) of a parsed TOML document, tables and array items included."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, value in items:
        yield path + (key,), value
        yield from _leaves(value, path + (key,))


def _parent(doc, path):
    for key in path[:-1]:
        doc = doc[key]
    return doc


def mutate_toml_doc(r: random.Random, doc: dict, extra_keys: tuple[str, ...] = ()) -> dict:
    """``doc`` with 1-2 structural edits: a value replaced (pool or scaled), a key deleted, renamed
    or added, a table made a scalar or an array of tables."""
    import copy

    doc = copy.deepcopy(doc)
    for _ in range(r.choice((1, 1, 1, 2))):
        leaves = list(_leaves(doc))
        if not leaves:
            doc[r.choice(("navigation", "scenario", "x"))] = pool_value(r)
            continue
        path, value = r.choice(leaves)
        parent = _parent(doc, path)
        key = path[-1]
        op = r.random()
        if op < 0.6:
            if isinstance(value, (int, float)) and not isinstance(value, bool) and r.random() < 0.3:
                parent[key] = value * r.choice((-1, 0, 1e300, -1e300, 1e-300, 10**20, float("nan")))
            else:
                parent[key] = pool_value(r)
        elif op < 0.7 and isinstance(parent, dict):
            del parent[key]
        elif op < 0.78 and isinstance(parent, dict):
            parent[str(key) + r.choice(("_x", "s", ""))[:2] + "z"] = parent.pop(key)
        elif op < 0.86 and isinstance(parent, dict):
            parent[r.choice(extra_keys or ("unknown",)) if r.random() < 0.5 else "bogus_key"] = pool_value(r)
        elif op < 0.93 and isinstance(value, dict):
            parent[key] = r.choice(([value, value], "table", 1, [], True))
        elif isinstance(parent, list):
            parent.append(pool_value(r))
        else:
            parent[key] = pool_value(r)
    return doc


def toml_input(r: random.Random, seeds: list[tuple[dict, str]], extra_keys: tuple[str, ...] = ()) -> bytes:
    doc, text = r.choice(seeds)
    op = r.random()
    if op < 0.7:
        try:
            return tomli_w.dumps(mutate_toml_doc(r, doc, extra_keys)).encode()
        except (TypeError, ValueError):
            return text.encode()
    if op < 0.8:
        # deep nesting: the TOML parser recurses once per level
        depth = r.choice((10, 100, 400, 1000, 3000))
        inner = r.choice((("[" * depth, "]" * depth), ("{a=" * depth + "1", "}" * depth)))
        lines = text.splitlines()
        where = r.randrange(len(lines))
        head, sep, _ = lines[where].partition("=")
        lines[where] = f"{head}= {inner[0]}{inner[1]}" if sep else lines[where]
        return "\n".join(lines).encode()
    if op < 0.9:
        lines = text.splitlines()
        where = r.randrange(len(lines))
        edit = r.randrange(4)
        if edit == 0:
            lines.insert(where, lines[r.randrange(len(lines))])  # duplicate key or table
        elif edit == 1:
            del lines[where]
        elif edit == 2:
            lines[where] = lines[where].replace("=", r.choice(("==", "= =", "")), 1)
        else:
            lines.insert(where, r.choice(("[navigation]", "[[navigation]]", "[settings]", "[scenario]", "x = 1",
                                          "[camera.sub]", "a.b.c = 1", "\ufeff", "\x00")))
        return "\n".join(lines).encode()
    data = text.encode()
    if r.random() < 0.1:
        return data[:r.randrange(len(data))] + r.choice((b"\xff\xfe", b"\xc3", b"\x80\x80"))
    return mutate_bytes(r, data)


def csv_input(r: random.Random, seed_rows: list[list[str]]) -> bytes:
    import csv

    rows = [list(row) for row in seed_rows]
    header = rows[0]
    for _ in range(r.choice((1, 1, 2, 3))):
        if not rows:
            break
        op = r.random()
        if op < 0.55:
            row = r.randrange(1, len(rows)) if len(rows) > 1 and r.random() < 0.95 else 0
            if rows[row]:
                col = r.randrange(len(rows[row]))
                cell = rows[row][col]
                if header[col:col + 1] in (["value"], ["covariance"]) and r.random() < 0.5 and cell.strip():
                    numbers = cell.split()
                    numbers = (numbers + numbers[:1] if r.random() < 0.5 else numbers[:-1]) if r.random() < 0.5 \
                        else [r.choice(("nan", "inf", "-inf", "1e400", "0", "-1", "x")) if r.random() < 0.5 else v
                              for v in numbers]
                    rows[row][col] = " ".join(numbers)
                else:
                    rows[row][col] = r.choice(CSV_POOL)
        elif op < 0.65:
            row = r.randrange(len(rows))
            if rows[row]:
                del rows[row][r.randrange(len(rows[row]))]
        elif op < 0.72:
            rows[r.randrange(len(rows))].append(r.choice(CSV_POOL))
        elif op < 0.8:
            col = r.randrange(len(header))
            for row in rows:
                if col < len(row):
                    del row[col]
        elif op < 0.86:
            rows.insert(r.randrange(1, len(rows) + 1), list(r.choice(rows)))
        elif op < 0.9 and len(rows) > 1:
            del rows[r.randrange(len(rows))]
        elif op < 0.94:
            a, b = r.randrange(len(header)), r.randrange(len(header))
            for row in rows:
                if max(a, b) < len(row):
                    row[a], row[b] = row[b], row[a]
        else:
            rows = rows[:1] if r.random() < 0.5 else []
    buf = io.StringIO()
    csv.writer(buf).writerows(rows)
    data = buf.getvalue().encode()
    if r.random() < 0.25:
        data = mutate_bytes(r, data)
    return data


def catalog_columns(n: int = 20) -> dict[str, np.ndarray]:
    from opnav.catalog import synthetic_catalog

    stars = synthetic_catalog(n, rng=np.random.default_rng(11))
    columns = {name: np.array(getattr(stars, name)) for name in stars.__dataclass_fields__}
    columns["parallax_rad"] = np.full(n, 1e-7)
    return {"format_version": np.array(1), **columns}


def catalog_input(r: random.Random, columns: dict[str, np.ndarray]) -> bytes:
    columns = dict(columns)
    if r.random() < 0.6:
        for _ in range(r.randint(1, 2)):
            name = r.choice(list(columns))
            column = columns[name]
            n = max(column.size, 1)
            op = r.randrange(13)
            if op == 0:
                del columns[name]
            elif op == 1:
                columns[name] = column.astype(r.choice((np.int8, np.int32, np.float16, np.float32, np.float64,
                                                        np.uint64, np.bool_, np.complex128, "U3", "S2")))
            elif op == 2:
                columns[name] = np.resize(column, (2, n // 2 or 1))
            elif op == 3:
                columns[name] = np.atleast_1d(column)[: r.randint(0, n - 1)]
            elif op == 4:
                columns[name] = np.full(n, r.choice((np.nan, np.inf, -np.inf, 1e300, -1e300, 2.0**70)))
            elif op == 5:
                columns[name] = np.array(r.choice((2, 0, -1, 1.5, "1", 10**12)))
            elif op == 6:
                columns[name] = np.arange(3)
            elif op == 7:
                columns[name] = np.array([])
            elif op == 8:
                columns["extra_column"] = np.arange(n)
            elif op == 9:
                columns[name] = np.full(n, r.choice((-1, 300, 2**40, 2**63 - 1)), dtype=np.int64)
            elif op == 10:
                columns[name] = np.array(5)
            elif op == 11:
                columns = {k: v[:0] if v.ndim else v for k, v in columns.items()}
            else:
                columns[name] = np.array([[1, 2], [3, 4]])
    buf = io.BytesIO()
    (np.savez_compressed if r.random() < 0.4 else np.savez)(buf, **columns)
    raw = buf.getvalue()
    if r.random() < 0.4:
        raw = mutate_bytes(r, raw, keep=4 if r.random() < 0.9 else 0)
    return raw


# --------------------------------------------------------------------------------------------
# Validity checks of returned results (an accepted input must give a usable value)
# --------------------------------------------------------------------------------------------

def check_frame(result) -> None:
    image, meta = result
    if not (isinstance(image, np.ndarray) and image.ndim == 2 and image.dtype == np.float64 and min(image.shape) >= 3):
        raise InvalidResult(f"frame of shape {np.shape(image)} dtype {getattr(image, 'dtype', None)}")
    if not np.all(np.isfinite(image)):
        raise InvalidResult("frame has non-finite pixels after reading")
    if meta.saturation_adu is not None and not math.isfinite(meta.saturation_adu):
        raise InvalidResult(f"saturation level {meta.saturation_adu}")
    if meta.invalid is not None and meta.invalid.shape != image.shape:
        raise InvalidResult("invalid-pixel mask does not match the frame")


def check_navigation(nav) -> None:
    if not (np.all(np.isfinite(nav.x0)) and np.all(np.isfinite(nav.P0)) and np.all(np.diag(nav.P0) > 0)):
        raise InvalidResult("initial state or covariance not finite and positive")
    if not isinstance(nav.seed, int) or nav.seed < 0:
        raise InvalidResult(f"seed {nav.seed!r}")
    from opnav.filters.batch import BatchOptions
    from opnav.filters.federated import FederatedSetup
    from opnav.filters.particle import ParticleOptions
    from opnav.filters.ukf import UKFOptions

    for name, kind in (("process_noise", dict), ("ukf", UKFOptions), ("particle", ParticleOptions),
                       ("batch", BatchOptions), ("federated", FederatedSetup)):
        if not isinstance(getattr(nav, name), kind):
            raise InvalidResult(f"{name} is not a {kind.__name__}")
    if not all(isinstance(t, str) and t for t in nav.ephemeris_targets):
        raise InvalidResult(f"ephemeris_targets {nav.ephemeris_targets!r}")


def check_records(records) -> None:
    from opnav.records import KIND_SIZE, Measurement

    for rec in records:
        if not isinstance(rec, Measurement) or rec.value.shape != (KIND_SIZE[rec.kind],):
            raise InvalidResult(f"record {rec!r}")
        if not math.isfinite(rec.t_tdb_s):
            raise InvalidResult("record epoch not finite")
        if rec.star_unit_icrf is not None and rec.problem() is None:
            star = rec.star_unit_icrf
            if not (np.all(np.isfinite(star)) and np.linalg.norm(star) > 0.0):
                raise InvalidResult(f"star direction {star} passed as usable")


def check_catalog(catalog) -> None:
    for name in ("ra_rad", "dec_rad", "epoch_tdb_s", "parallax_rad", "vmag"):
        if not np.all(np.isfinite(getattr(catalog, name))):
            raise InvalidResult(f"catalog column {name} not finite")
    if not np.all(np.isin(catalog.source, (0, 1, 2))):
        raise InvalidResult(f"catalog source values {np.unique(catalog.source)[:5]}")


def check_none(result) -> None:  # noqa: ARG001 - the reader's own types are its validity check
    return None


# --------------------------------------------------------------------------------------------
# Targets
# --------------------------------------------------------------------------------------------

@dataclass
class Target:
    """One reader or command under fuzz: how to make an input and how to run it."""

    name: str
    suffix: str
    weight: float
    make: object  # (random.Random, np.random.Generator) -> bytes
    run: object  # (Path) -> result (reader) or (exit status, stderr text) (command)
    check: object = check_none
    command: bool = False
    accept_status: tuple[int, ...] = (0, 2, 3)
    argv: object = None  # (Path) -> list[str], for the report
    state: dict = field(default_factory=dict)  # what make() chose beside the bytes: --set pairs, frame suffix
    klass: str = "readers"  # the class of the table (module docstring)
    make_path: object = None  # (random.Random, work folder) -> (Path, description bytes): a prepared path instead


@dataclass
class Finding:
    key: tuple
    count: int = 0
    message: str = ""
    reproducer: str = ""
    opnav_frame: str = ""
    last_frame: str = ""


@dataclass
class Tally:
    inputs: int = 0
    accepted: int = 0
    opnav_errors: int = 0
    findings: int = 0
    seconds: float = 0.0
    kinds: dict = field(default_factory=dict)


class ClosedPipe(io.TextIOBase):
    """A stdout whose reader went away: every write raises ``BrokenPipeError`` (``opnav ... | head``).

    ``fileno`` is a descriptor of ``/dev/null`` of its own, so the CLI's clean-up (``dup2`` onto it)
    touches nothing of the fuzzer's."""

    def __init__(self) -> None:
        super().__init__()
        self.fd = os.open(os.devnull, os.O_WRONLY)

    def write(self, text: str) -> int:
        raise BrokenPipeError(32, "Broken pipe")

    def fileno(self) -> int:
        return self.fd

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self.fd)
        super().close()


def run_command(argv: list[str], stdout=None) -> tuple[int, str]:
    """``opnav ARGV`` in this process: (exit status, stderr text), with what a user would see on stderr.

    Logging is switched back on and the root logger emptied so that ``main``'s ``basicConfig`` writes
    to the captured stderr (library log lines count towards the one-line rule); warnings print there
    too, with their default filters.
    """
    import logging

    from opnav.cli import main

    out, err = stdout if stdout is not None else io.StringIO(), io.StringIO()
    root = logging.getLogger()
    saved = root.handlers[:]
    root.handlers.clear()
    logging.disable(logging.NOTSET)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings():
            # the interpreter's own defaults: shown once per place, the developer categories hidden
            warnings.resetwarnings()
            warnings.simplefilter("default")
            for category in (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning):
                warnings.filterwarnings("ignore", category=category)
            status = main(argv)
    finally:
        root.handlers[:] = saved
        logging.disable(logging.CRITICAL)
    return status, err.getvalue()


def build_targets(work: Path) -> list[Target]:
    import csv

    from opnav.catalog import _load_cached, load_catalog
    from opnav.config import read_toml
    from opnav.image.io import read_image
    from opnav.filters.options import load_navigation
    from opnav.records import Measurement, read_csv, write_csv
    from opnav.sim.scene import SECTIONS, load_scene
    from opnav.studies import STUDIES
    from opnav.studies.settings import load_run_file

    def seeds(*paths: Path) -> list[tuple[dict, str]]:
        return [(read_toml(p, kind="seed file"), p.read_text()) for p in paths]

    nav_full = (
        'epoch = "2001-01-01T00:01:04.183921"\nepoch_scale = "tdb"\ndynamics = "geo"\n'
        "position_km = [-6816.1459303320435, -41604.77191263884, 3.9302753778435973]\n"
        "velocity_km_s = [3.0346193993817434, -0.49714475721971957, 0.0014231953064783522]\n"
        "sigma_position_km = [10.0, 10.0, 10.0]\nsigma_velocity_km_s = 0.001\nfilter = \"ekf\"\n"
        "gate_probability = 0.999999\ntarget_position_sigma_km = 1.0\nseed = 3\npropagation = \"fast\"\n"
        'ephemeris_error = "white"\nephemeris_targets = ["earth"]\n'
    )
    nav_text = ("[navigation]\n" + nav_full + "\n[navigation.process_noise]\nmodel = \"white\"\nq_km2_s3 = 0.0\n"
                "\n[navigation.corrections]\nlight_time = true\naberration = true\n"
                "\n[navigation.ukf]\nalpha = 0.001\n\n[navigation.particle]\nn_particles = 100\n"
                "\n[navigation.batch]\nmax_iterations = 5\n\n[navigation.federated]\nlocal_filter = \"ekf\"\n")
    nav_geo = work / "nav_geo.toml"
    nav_geo.write_text(nav_text)
    nav_seeds = seeds(DEMO, nav_geo)
    scenario_seeds = seeds(SAMPLES / "s1_render.toml", SAMPLES / "s3_render.toml", DEMO)
    run_seeds = seeds(*(SAMPLES / f for f in ("s1_jul_both_0.1.toml", "s3_geo.toml", "s2_capture.toml",
                                               "s4_approach.toml")))
    settings_keys = tuple(sorted({f for m in STUDIES.values() for f in m.Settings.__dataclass_fields__}))

    star = np.array([0.9809671218417076, -0.18554085828126138, 0.057254657224100974])
    t0 = 31579274.183921367
    records = [
        Measurement(t0, "starlight", [1.5961371563518711, 1.444290369520823],
                    [[1.11e-09, 1.11e-09], [1.11e-09, 2.15e-09]], target="earth", sensor="s3", star_id=114971,
                    star_unit_icrf=star),
        Measurement(t0 + 10, "starlight_angle", [1.5968], [[1.1e-9]], target="earth", sensor="s3", star_id=114971,
                    star_unit_icrf=star),
        Measurement(t0 + 10, "starlight_elevation", [1.4449], [[2.1e-9]], target="earth", sensor="s3",
                    star_id=114971, star_unit_icrf=star),
        Measurement(t0 + 20, "radec", [0.5, -0.2], np.diag([1e-10, 2e-10]), target="mars", frame_id="f0001", flags=8),
        Measurement(t0 + 30, "los", [0.6, 0.8, 0.0], np.eye(3) * 1e-10, target="sun"),
        Measurement(t0 + 40, "position", [-6816.0, -41604.0, 3.9], np.eye(3) * 100.0, target="earth"),
        Measurement(t0 + 50, "radial_velocity", [12.5], [[1e-6]], target="sun", star_unit_icrf=star),
    ]
    seed_csv = work / "seed.csv"
    write_csv(seed_csv, records)
    with seed_csv.open(newline="") as handle:
        csv_rows = list(csv.reader(handle))
    # the navigate command gets a short, consistent S3 file: starlight records only
    nav_rows = [csv_rows[0]] + [csv_rows[1]] + [
        [repr(t0 + 10.0 * k)] + csv_rows[1][1:] for k in range(1, 4)]
    columns = catalog_columns()
    # solve gets 300 stars in a 20-degree cap: enough 4-star patterns for a 10-degree field, a quick index
    from opnav.catalog import synthetic_catalog

    cap = synthetic_catalog(300, rng=np.random.default_rng(3), vmag_range=(2.0, 7.0),
                            centre_icrf=np.array([1.0, 0.0, 0.0]), radius_rad=np.radians(20.0))
    tiny_catalog = work / "solve_catalog.npz"
    np.savez(tiny_catalog, format_version=np.array(1), **{n: getattr(cap, n) for n in cap.__dataclass_fields__})
    cache = work / "index_cache"

    def frame(fmt):
        return lambda r, rng: frame_input(r, rng, fmt)

    def load_catalog_fresh(path: Path):
        # the loader caches by (path, mtime, size): a rewrite within one clock tick must not hit the cache
        _load_cached.cache_clear()
        return load_catalog(path)

    def run_file(path: Path):
        return load_run_file(path, None)

    def run_file_overrides(r: random.Random):
        pairs = {}
        for _ in range(r.randint(0, 2)):
            value = r.choice(TOML_POOL + ["0", "-5", "1e9", "nan", "ekf,ukf", ",", "true"])
            key = r.choice(settings_keys + ("seed", "bogus"))
            pairs[key] = value if isinstance(value, str) else str(value)
        return pairs

    targets = [
        Target("fits", ".fits", 11, frame("fits"), read_image, check_frame),
        Target("png", ".png", 9, frame("png"), read_image, check_frame),
        Target("tiff", ".tif", 9, frame("tiff"), read_image, check_frame),
        Target("jpeg", ".jpg", 7, frame("jpeg"), read_image, check_frame),
        Target("scenario", ".toml", 12, lambda r, rng: toml_input(r, scenario_seeds, SECTIONS), load_scene),
        Target("navigation", ".toml", 12, lambda r, rng: toml_input(r, nav_seeds, ("ukf", "seed", "filter")),
               load_navigation, check_navigation),
        Target("runfile", ".toml", 10, lambda r, rng: toml_input(r, run_seeds, settings_keys), run_file),
        Target("csv", ".csv", 14, lambda r, rng: csv_input(r, csv_rows), read_csv, check_records),
        Target("catalog", ".npz", 8, lambda r, rng: catalog_input(r, columns), load_catalog_fresh, check_catalog),
    ]
    # run files with --set overrides: the overrides are drawn from the input's own generator
    override_state: dict = {}

    def make_run_with_overrides(r, rng):
        override_state["pairs"] = run_file_overrides(r)
        return toml_input(r, run_seeds, settings_keys) if r.random() < 0.5 else r.choice(run_seeds)[1].encode()

    targets.append(Target("runfile --set", ".toml", 3, make_run_with_overrides,
                          lambda path: load_run_file(path, override_state.get("pairs"))))
    # commands, at a lower rate
    centroid_argv = lambda path: ["centroid", str(path), "--json"]  # noqa: E731
    solve_argv = lambda path: ["solve", str(path), "--fov", "10", "--catalog", str(tiny_catalog),  # noqa: E731
                               "--cache-dir", str(cache), "--json"]
    navigate_argv = lambda path: ["navigate", str(path), "--scenario", str(nav_geo),  # noqa: E731
                                  "--out", str(work / "nav_out"), "--no-progress"]

    def any_frame(r, rng):
        fmt = r.choice(("fits", "fits", "png", "tiff", "jpeg"))
        override_state["suffix"] = {"fits": ".fits", "png": ".png", "tiff": ".tif", "jpeg": ".jpg"}[fmt]
        return frame_input(r, rng, fmt)

    targets += [
        Target("cli-centroid", ".fits", 1.2, any_frame, lambda p: run_command(centroid_argv(p)), command=True,
               argv=centroid_argv, klass="commands"),
        Target("cli-solve", ".fits", 0.3, any_frame, lambda p: run_command(solve_argv(p)), command=True,
               accept_status=(0, 1, 2, 3), argv=solve_argv, klass="commands"),
        Target("cli-navigate", ".csv", 0.4, lambda r, rng: csv_input(r, nav_rows),
               lambda p: run_command(navigate_argv(p)), command=True, argv=navigate_argv, klass="commands"),
    ]
    for target in targets:
        target.state = override_state
    targets += issue40_targets(work, tiny_catalog, cache, nav_geo, nav_rows, run_seeds)
    return targets


# --------------------------------------------------------------------------------------------
# The classes of issue 40: inconsistent headers, extreme values, special files, environment
# --------------------------------------------------------------------------------------------

#: Header keywords a lying frame gets wrong, and what it says instead.
HEADER_KEYS = ("TDB_S", "DATE-OBS", "DATE-AVG", "MJD-OBS", "MJD-AVG", "EXPTIME", "TIMESYS", "CTYPE1", "CTYPE2",
               "CRVAL1", "CRVAL2", "CRPIX1", "CRPIX2", "CD1_1", "CD1_2", "CD2_1", "CD2_2", "CDELT1", "CDELT2",
               "CROTA2", "PC1_1", "GAIN", "RDNOISE", "BIASLVL", "SATURATE", "OBS_X", "OBS_Y", "OBS_Z", "OBS_VX",
               "OBS_VY", "OBS_VZ")
HEADER_VALUES = ("abc", "", "nan", "inf", "NaN", True, False, 0, -1, 1, 0.0, -0.0, 1e300, -1e300, 1e-300, 5e-324,
                 1e308, 2**62, "1900-01-01T00:00:00", "2200-01-01T00:00:00", "0000-01-01T00:00:00",
                 "2014-07-16T00:00:00", "2014-07-15", "RA---TAN", "DEC--TAN", "RA---SIN", "GLON-TAN", "GPS", "TDB",
                 -3.155e9, 1e12, 90.0, 95.0, -90.0, 360.0, 1e-12, 4e5)
DATE_SHIFTS_S = (86_400.0, -86_400.0, 3.156e9, -3.156e9, 1.0, 30.0)


def header_frame(r: random.Random, rng: np.random.Generator, base_headers: list) -> bytes:
    """A 40 x 48 frame with an opnav header (epoch, WCS, detector, observer) and 1-3 lies in it."""
    from astropy.io import fits
    from astropy.time import Time, TimeDelta

    header = r.choice(base_headers).copy()
    data = rng.normal(100.0, 5.0, (40, 48))
    for _ in range(r.randint(2, 5)):
        data[r.randrange(40), r.randrange(48)] += r.choice((500.0, 3000.0, 20000.0))
    for _ in range(r.randint(1, 3)):
        op = r.random()
        if op < 0.45:
            header[r.choice(HEADER_KEYS)] = r.choice(HEADER_VALUES)
        elif op < 0.6:
            for key in r.sample(HEADER_KEYS, r.randint(1, 6)):
                header.remove(key, ignore_missing=True)
        elif op < 0.7:  # no WCS at all
            for key in HEADER_KEYS[7:21]:
                header.remove(key, ignore_missing=True)
        elif op < 0.85:  # a date a day or a century off: one keyword, or all of them consistently
            shift = r.choice(DATE_SHIFTS_S)
            keys = [k for k in ("TDB_S", "DATE-OBS", "DATE-AVG", "MJD-OBS", "MJD-AVG") if k in header]
            for key in keys if r.random() < 0.5 else keys[:1] + r.sample(keys, min(len(keys), 1)):
                try:
                    if key.startswith("DATE"):
                        header[key] = (Time(str(header[key])) + TimeDelta(shift, format="sec")).isot
                    else:
                        header[key] = float(header[key]) + (shift / 86_400.0 if key.startswith("MJD") else shift)
                except (ValueError, TypeError):
                    pass  # an earlier lie already made it unreadable
        else:  # the WCS pointing degrees off (the a-priori attitude disagrees with the stars)
            key = r.choice(("CRVAL1", "CRVAL2"))
            with contextlib.suppress(ValueError, TypeError, KeyError):
                header[key] = float(header[key]) + r.choice((5.0, -5.0, 0.5, 90.0, 180.0))
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fits.PrimaryHDU(data.astype(np.float32), header).writeto(buf, output_verify="silentfix")
    return buf.getvalue()


def check_frame_input(frame) -> None:
    """An accepted header gave a usable frame: a finite epoch in the span, a rotation, a camera, a detector."""
    from opnav.image.header import EPOCH_SPAN_TDB_S

    if not EPOCH_SPAN_TDB_S[0] <= frame.t_tdb_s <= EPOCH_SPAN_TDB_S[1]:
        raise InvalidResult(f"epoch {frame.t_tdb_s!r} accepted")
    matrix = frame.R_prior.as_matrix()
    if not (np.all(np.isfinite(matrix)) and np.allclose(matrix @ matrix.T, np.eye(3), atol=1e-9)):
        raise InvalidResult("a-priori attitude is not a rotation")
    camera = frame.camera
    if not (math.isfinite(camera.focal_length_px) and 0.0 < math.degrees(camera.fov_x_rad) < 120.0):
        raise InvalidResult(f"camera of {camera.focal_length_px!r} px focal length accepted")
    values = (frame.read_noise_e, frame.gain_e_per_adu, frame.bias_adu, frame.exposure_s)
    if not (all(math.isfinite(v) for v in values) and frame.gain_e_per_adu > 0 and frame.exposure_s > 0):
        raise InvalidResult(f"detector {values} accepted")
    if frame.observer is not None:
        state = np.concatenate([frame.observer.r_ssb_km, frame.observer.v_ssb_km_s])
        if not (np.all(np.isfinite(state)) and np.linalg.norm(frame.observer.v_ssb_km_s) < 3000.0):
            raise InvalidResult(f"observer state {state} accepted")


#: --set values of the extreme-values class, for every numeric setting.
EXTREMES = ("1e300", "-1e300", "1e-300", "-1e-300", "5e-324", "1e308", "-1", "0", "-0", "nan", "inf", "-inf", "1e30",
            "1e-30", "2e9", "9223372036854775808")


def check_run_file(run) -> None:
    """Every number of an accepted run file's settings is finite (an infinite or NaN setting is wrong)."""
    import dataclasses

    for name, value in vars(run.settings).items() if not dataclasses.is_dataclass(run.settings) else \
            ((f.name, getattr(run.settings, f.name)) for f in dataclasses.fields(run.settings)):
        numbers = np.ravel(np.asarray(value, dtype=object)) if isinstance(value, (tuple, list)) else [value]
        for number in numbers:
            if isinstance(number, (int, float)) and not isinstance(number, bool) and not math.isfinite(number):
                raise InvalidResult(f"setting {name} = {value!r} accepted")


def issue40_targets(work: Path, tiny_catalog: Path, cache: Path, nav_geo: Path, nav_rows, run_seeds) -> list[Target]:
    """The targets of the four classes of issue 40 (module docstring)."""
    import csv
    import dataclasses

    from astropy.io import fits
    from scipy.spatial.transform import Rotation

    from opnav.camera import Camera, read_camera_file
    from opnav.catalog import _load_cached, load_catalog
    from opnav.filters.options import load_navigation
    from opnav.image.io import read_image
    from opnav.image.pipeline import frame_input as pipeline_frame_input
    from opnav.records import read_csv
    from opnav.render.frames_io import frame_header
    from opnav.render.truth import FrameTruth
    from opnav.sim.scene import load_scene
    from opnav.studies import STUDIES
    from opnav.studies.settings import load_run_file

    state: dict = {}
    # headers: three opnav headers (two cameras, short and long exposures) to lie in
    base_headers = []
    for k, (fov, exposure) in enumerate(((10.0, 1.0), (1.0, 30.0), (20.0, 0.05))):
        truth = FrameTruth(t_tdb_s=4.586e8 + 1000.0 * k, exposure_s=exposure, camera_id="fuzz",
                           R_icrf_cam=Rotation.from_euler("zyx", [10.0 * k, 5.0, 3.0], degrees=True),
                           r_observer_ssb_km=np.array([1e8, 2e7, -3e6]), v_observer_ssb_km_s=np.array([20.0, -8.0, 4.0]),
                           omega_cam_rad_s=np.zeros(3), stars=None, targets=())
        base_headers.append(frame_header(Camera.from_fov(fov, 48, 40), truth))

    def make_header(r, rng):
        return header_frame(r, rng, base_headers)

    def header_solve_argv(path):
        return ["solve", str(path), "--catalog", str(tiny_catalog), "--cache-dir", str(cache), "--json"]

    def header_command(path):
        argv = ["centroid", str(path), "--json"] if state.get("cmd") == "centroid" else header_solve_argv(path)
        return run_command(argv)

    def make_header_command(r, rng):
        state["cmd"] = r.choice(("centroid", "solve"))
        return make_header(r, rng)

    # extreme values: every numeric setting of every study
    run_paths = []
    for k, (doc, text) in enumerate(run_seeds):
        path = work / f"extreme_{k}.toml"
        path.write_text(text)
        study = STUDIES[doc["scenario"]["study"]]
        numeric = [f.name for f in dataclasses.fields(study.Settings)
                   if str(f.type).split("|")[0].strip() in ("float", "int")
                   or isinstance(getattr(study.Settings(), f.name, None), (int, float))
                   and not isinstance(getattr(study.Settings(), f.name, None), bool)]
        run_paths.append((path, numeric))

    def make_extreme(r, work_):  # noqa: ARG001
        path, numeric = r.choice(run_paths)
        pairs = {key: r.choice(EXTREMES) for key in r.sample(numeric, min(len(numeric), r.choice((1, 1, 2))))}
        if r.random() < 0.15:
            pairs["seed"] = r.choice(("-1", "-5", "1e300", "nan", "2**64", "18446744073709551616"))
        state["pairs"] = pairs
        return path, f"{path.name} --set {pairs}".encode()

    # special files: made once, named with every suffix a reader chooses by
    special = work / "special"
    special.mkdir()
    (special / "afile").write_text("x")
    (special / "folder.d").mkdir()
    kinds = {}
    for suffix in (".fits", ".png", ".toml", ".csv", ".npz", ".tif"):
        fifo = special / f"fifo{suffix}"
        os.mkfifo(fifo)
        folder = special / f"folder{suffix}"
        folder.mkdir()
        links = {"fifo": fifo, "folder": folder, "zero": Path("/dev/zero"), "null": Path("/dev/null"),
                 "dangling": special / "nowhere" / "x", "urandom": Path("/dev/urandom")}
        for kind, target in links.items():
            link = special / f"link_{kind}{suffix}"
            link.symlink_to(target)
            kinds[(kind + " symlink", suffix)] = link
        kinds[("fifo", suffix)] = fifo
        kinds[("folder", suffix)] = folder
    kinds[("dev zero", "")] = Path("/dev/zero")
    kinds[("dev null", "")] = Path("/dev/null")
    kinds[("folder", "")] = special / "folder.d"

    good_frame = work / "good.fits"
    noise = np.random.default_rng(5).normal(100.0, 5.0, (64, 64))
    noise[30, 30] += 5000.0
    fits.PrimaryHDU(noise.astype(np.float32)).writeto(good_frame)
    good_csv = work / "good.csv"
    with good_csv.open("w", newline="") as handle:
        csv.writer(handle).writerows(nav_rows)

    def catalog_fresh(path):
        _load_cached.cache_clear()
        return load_catalog(path)

    readers = {".fits": read_image, ".png": read_image, ".tif": read_image, ".toml": None, ".csv": read_csv,
               ".npz": catalog_fresh}
    toml_readers = (load_scene, load_navigation, lambda p: load_run_file(p, None), read_camera_file)
    special_commands = (
        lambda p: ["centroid", str(p)],
        lambda p: ["solve", str(p), "--fov", "10", "--catalog", str(tiny_catalog), "--cache-dir", str(cache)],
        lambda p: ["solve", str(good_frame), "--fov", "10", "--catalog", str(p), "--cache-dir", str(cache)],
        lambda p: ["navigate", str(p), "--scenario", str(nav_geo), "--out", str(work / "special_out"), "--no-progress"],
        lambda p: ["navigate", str(good_csv), "--scenario", str(p), "--out", str(work / "special_out"),
                   "--no-progress"],
        lambda p: ["run", str(p), "--out", str(work / "special_run")],
        lambda p: ["process", str(p), "--out", str(work / "special.csv"), "--no-progress"],
        lambda p: ["centroid", str(good_frame), "--camera", str(p)],
    )

    def make_special(r, work_):  # noqa: ARG001
        (kind, suffix), path = r.choice(sorted(kinds.items(), key=lambda item: (item[0][0], item[0][1])))
        if r.random() < 0.5:
            state["special"] = ("reader", r.choice(toml_readers) if suffix == ".toml" or readers.get(suffix) is None
                                else readers[suffix])
        else:
            state["special"] = ("command", r.choice(special_commands))
        return path, f"{kind} {path}".encode()

    def run_special(path):
        from opnav.errors import OpnavError

        how, what = state["special"]
        if how == "reader":
            try:
                what(path)
            except OpnavError as exc:
                return 2, f"error: {exc}"
            # a reader that returns for a special file read something that is no file of opnav's
            raise InvalidResult(f"{path} accepted by {getattr(what, '__name__', what)}")
        status, err = run_command(what(path))
        if status == 0:
            raise InvalidResult(f"exit 0 for {' '.join(what(path))}")
        return status, err

    # environment
    afile = special / "afile"
    bad_places = {
        "under a file": lambda: afile / "sub",
        "under /proc": lambda: Path("/proc/opnav-fuzz/sub"),
        "dangling symlink": lambda: special / "link_dangling.csv",
        "name too long": lambda: work / ("x" * 300),
    }

    def removed_folder():
        folder = Path(tempfile.mkdtemp(dir=work))
        folder.rmdir()
        return folder / "out"

    def make_environment(r, work_):  # noqa: ARG001
        case = r.choice(("cache", "out", "out", "stdout", "cwd"))
        place_name = r.choice(sorted(bad_places) + ["removed folder"])
        place = removed_folder() if place_name == "removed folder" else bad_places[place_name]()
        state["env"] = (case, place, r.choice(("centroid", "navigate", "solve")))
        return place, f"{case}: {place_name} {place}".encode()

    def run_environment(place):
        case, place, command = state["env"]
        nav_out = work / "env_nav"
        if case == "cache":
            saved = os.environ.get("OPNAV_CACHE")
            os.environ["OPNAV_CACHE"] = str(place)
            try:
                return run_command(["solve", str(good_frame), "--fov", "10", "--catalog", str(tiny_catalog)])
            finally:
                os.environ.pop("OPNAV_CACHE") if saved is None else os.environ.__setitem__("OPNAV_CACHE", saved)
        if case == "out":
            argv = (["navigate", str(good_csv), "--scenario", str(nav_geo), "--out", str(place), "--no-progress"]
                    if command != "solve" else ["process", str(special / "folder.d"), "--out", str(place),
                                                "--targets", "phobos", "--no-progress"])
            status, err = run_command(argv)
            if status == 0 and not (place / "summary.json").is_file() and not Path(place).is_file():
                raise Lost(f"exit 0 but nothing at {place}")
            return status, err
        if case == "stdout":
            pipe = ClosedPipe()
            try:
                argv = (["centroid", str(good_frame), "--json"] if command == "centroid" else
                        ["navigate", str(good_csv), "--scenario", str(nav_geo), "--out", str(nav_out), "--no-progress"])
                status, err = run_command(argv, stdout=pipe)
            finally:
                pipe.close()
            if status not in (0, 141) or stderr_lines(err):
                raise (Unclear if status == 2 else InvalidResult)(f"closed stdout: exit {status}: {err.strip()[-200:]}")
            return 0, ""
        # cwd: the working folder removed under the command, relative names
        here = os.getcwd()
        folder = Path(tempfile.mkdtemp(dir=work))
        shutil.copy(good_frame, folder / "frame.fits")
        os.chdir(folder)
        shutil.rmtree(folder)
        try:
            return run_command(["centroid", "frame.fits"] if command != "navigate" else
                               ["navigate", "m.csv", "--scenario", str(nav_geo), "--out", "out", "--no-progress"])
        finally:
            os.chdir(here)

    targets = [
        Target("headers", ".fits", 8, make_header, pipeline_frame_input, check_frame_input, klass="inconsistent headers"),
        Target("cli-headers", ".fits", 1.5, make_header_command, header_command, command=True,
               accept_status=(0, 1, 2), argv=header_solve_argv, klass="inconsistent headers"),
        Target("extreme --set", ".toml", 8, None, lambda path: load_run_file(path, state.get("pairs")), check_run_file,
               klass="extreme values", make_path=make_extreme),
        Target("special files", "", 3, None, run_special, command=True, accept_status=(2,), klass="special files",
               make_path=make_special),
        Target("environment", "", 1.5, None, run_environment, command=True, accept_status=(0, 1, 2, 3),
               klass="environment", make_path=make_environment),
    ]
    for target in targets:
        target.state = state
    return targets


# --------------------------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------------------------

def frames_of(exc: BaseException) -> tuple[str, str]:
    """(deepest frame inside opnav, last frame) of ``exc``'s traceback, as ``file:line in func``."""
    tb = traceback.extract_tb(exc.__traceback__)
    if not tb:
        return "", ""

    def fmt(fr):
        name = fr.filename
        with contextlib.suppress(ValueError):
            name = str(Path(name).resolve().relative_to(ROOT))
        return f"{name}:{fr.lineno} in {fr.name}"

    inside = [fr for fr in tb if "/opnav/" in fr.filename and "benchmarks" not in fr.filename]
    return (fmt(inside[-1]) if inside else ""), fmt(tb[-1])


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def fuzz_worker(job: dict) -> dict:
    """Run one worker's share of the inputs (its own generator, scratch folder and reproducer names)."""
    import logging

    from opnav.errors import OpnavError

    # quiet: each reader logs what it repaired, and the CLI would set up logging to stderr
    logging.disable(logging.CRITICAL)
    worker = job["worker"]
    findings_dir = Path(job["findings_dir"])
    work = Path(tempfile.mkdtemp(prefix=f"opnav-fuzz-{worker}-"))
    r = random.Random(job["seed"] * 1000 + worker)
    rng = np.random.default_rng([job["seed"], worker])
    targets = build_targets(work)
    if job["only"]:
        targets = [t for t in targets if t.name in job["only"]]
    weights = [t.weight for t in targets]
    tallies = {t.name: Tally() for t in targets}
    findings: dict[tuple, Finding] = {}
    signal.signal(signal.SIGALRM, _alarm)
    # warm-up, not counted: the first call of a command imports its modules (seconds for some), which
    # the per-input timeout would report as a hang
    warm = random.Random(0)
    for target in targets:
        with warnings.catch_warnings(), contextlib.suppress(Exception):
            warnings.simplefilter("ignore")
            if target.make_path is not None:
                target.run(target.make_path(warm, work)[0])
            else:
                target.run(_write(work / f"warm{target.suffix}", target.make(warm, np.random.default_rng(0))))
        target.state.pop("suffix", None)
    done = 0
    try:
        while done < job["inputs"] and time.time() < job["deadline"]:
            target = r.choices(targets, weights)[0]
            tally = tallies[target.name]
            tick = time.perf_counter()
            if target.make_path is not None:
                path, data = target.make_path(r, work)
                suffix = path.suffix
            else:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    data = target.make(r, rng)
                suffix = target.state.pop("suffix", target.suffix) if target.command else target.suffix
                path = work / f"input{suffix}"
                path.write_bytes(data)
            failure: BaseException | None = None
            stderr_text = ""
            status = None
            signal.setitimer(signal.ITIMER_REAL, job["command_timeout"] if target.command else job["timeout"])
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    # as in the test configuration (pyproject.toml): a RuntimeWarning inside opnav is a failure
                    warnings.filterwarnings("error", category=RuntimeWarning, module=r"opnav\.")
                    result = target.run(path)
                    if target.command:
                        status, stderr_text = result
                    else:
                        target.check(result)
            except OpnavError as exc:
                if target.command:
                    failure = exc  # main() turns these into exit status 2; one escaping it is a finding
                else:
                    tally.opnav_errors += 1
            except (Exception, RecursionError, MemoryError, Hang) as exc:  # noqa: BLE001 - every other outcome is a finding
                failure = exc
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            if target.command and failure is None:
                # the error is one line; the run's own log lines and "warning:" notes before it are not errors
                lines = stderr_lines(stderr_text)
                if "Traceback" in stderr_text:
                    failure = TracebackPrinted(stderr_text.strip()[-300:])
                elif status not in target.accept_status:
                    failure = InvalidResult(f"exit status {status}: {stderr_text.strip()[-300:]}")
                elif status == 2 and len(lines) != 1:
                    failure = Unclear(f"exit 2 with {len(lines)} stderr lines: {stderr_text.strip()[-300:]}")
                elif status == 2:
                    tally.opnav_errors += 1
                else:
                    tally.accepted += 1
            if failure is not None:
                tally.findings += 1
                kind = FINDING_KINDS.get(type(failure).__name__, "traceback")
                tally.kinds[kind] = tally.kinds.get(kind, 0) + 1
                opnav_frame, last_frame = frames_of(failure)
                key = (target.name, type(failure).__name__, opnav_frame or last_frame)
                finding = findings.get(key)
                if finding is None:
                    index = len(findings) + 1
                    name = f"w{worker}-{index:03d}-{target.name.replace(' ', '_')}-{type(failure).__name__}{suffix}"
                    repro = findings_dir / name
                    repro.write_bytes(data)
                    note = [f"target: {target.name}", f"exception: {type(failure).__name__}: {failure}"]
                    if target.argv:
                        note.append(f"argv: opnav {' '.join(target.argv(repro))}")
                    if target.name in ("runfile --set", "extreme --set"):
                        note.append(f"overrides: {target.state.get('pairs')}")
                    if target.make_path is not None:
                        note.append(f"case: {data.decode(errors='replace')} {target.state.get('special') or ''}"
                                    f"{target.state.get('env') or ''}")
                    note.append("".join(traceback.format_exception(failure)))
                    repro.with_name(repro.name + ".txt").write_text("\n".join(note))
                    finding = findings[key] = Finding(key, message=str(failure).replace("\n", " ")[:160],
                                                      reproducer=str(repro), opnav_frame=opnav_frame,
                                                      last_frame=last_frame)
                finding.count += 1
            tally.inputs += 1
            tally.seconds += time.perf_counter() - tick
            done += 1
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        shutil.rmtree(work, ignore_errors=True)
    for target in targets:
        tally = tallies[target.name]
        if not target.command:
            tally.accepted = tally.inputs - tally.opnav_errors - tally.findings
    return {"names": [t.name for t in targets], "classes": {t.name: t.klass for t in targets}, "tallies": tallies,
            "findings": findings, "done": done}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", type=int, default=100_000, help="mutated inputs in all (default 100000)")
    parser.add_argument("--seconds", type=float, default=600.0, help="time bound, s (default 600)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--out", default="out/fuzz", help="folder for reproducers (default out/fuzz)")
    parser.add_argument("--timeout", type=float, default=5.0, help="per-input timeout of a reader, s (default 5)")
    parser.add_argument("--command-timeout", type=float, default=60.0,
                        help="per-input timeout of a command, s (default 60: a command may build a pattern index "
                             "for a field of view it has not met, bounded work of seconds to tens of seconds)")
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                        help="worker processes, each with its own share of the inputs (default 2)")
    parser.add_argument("--only", default=None, help="comma-separated target names (default: all)")
    args = parser.parse_args(argv)
    if args.inputs < 1 or not args.seconds > 0 or not args.timeout > 0 or not args.command_timeout > 0 \
            or args.workers < 1:
        parser.error("--inputs, --seconds, --timeout, --command-timeout and --workers must be positive")
    findings_dir = Path(args.out) / "findings"
    if findings_dir.exists():
        shutil.rmtree(findings_dir)
    findings_dir.mkdir(parents=True)
    started = time.perf_counter()
    deadline = time.time() + args.seconds
    shares = [args.inputs // args.workers + (k < args.inputs % args.workers) for k in range(args.workers)]
    jobs = [{"worker": k, "seed": args.seed, "inputs": shares[k], "deadline": deadline, "timeout": args.timeout,
             "command_timeout": args.command_timeout,
             "findings_dir": str(findings_dir), "only": set(args.only.split(",")) if args.only else None}
            for k in range(args.workers) if shares[k]]
    if args.workers == 1:
        results = [fuzz_worker(jobs[0])]
    else:
        import multiprocessing

        # fork: the workers inherit the imported modules (no re-import per worker)
        with multiprocessing.get_context("fork").Pool(len(jobs)) as pool:
            results = pool.map(fuzz_worker, jobs)
    names = results[0]["names"]
    classes = results[0]["classes"]
    if not names:
        parser.error("--only names none of the targets")
    tallies = {name: Tally() for name in names}
    findings: dict[tuple, Finding] = {}
    for result in results:
        for name, t in result["tallies"].items():
            total = tallies[name]
            total.inputs += t.inputs
            total.accepted += t.accepted
            total.opnav_errors += t.opnav_errors
            total.findings += t.findings
            total.seconds += t.seconds
            for kind, n in t.kinds.items():
                total.kinds[kind] = total.kinds.get(kind, 0) + n
        for key, f in result["findings"].items():
            if key in findings:
                findings[key].count += f.count
            else:
                findings[key] = f
    done = sum(result["done"] for result in results)
    print_tally(names, tallies, findings, done, time.perf_counter() - started, args)
    print_classes(names, classes, tallies)
    return 1 if findings else 0


def print_tally(names, tallies, findings, done, elapsed, args) -> None:
    print(f"fuzz: {done:,} inputs in {elapsed:.1f} s ({done / elapsed:,.0f} inputs/s) on {args.workers} worker(s), "
          f"seed {args.seed}, per-input timeout {args.timeout:g} s (a command {args.command_timeout:g} s)")
    print(f"{'reader':<15} {'inputs':>8} {'accepted':>9} {'opnav err':>10} {'findings':>9} {'ms/input':>9}")
    total = Tally()
    for name in names:
        t = tallies[name]
        print(f"{name:<15} {t.inputs:>8,} {t.accepted:>9,} {t.opnav_errors:>10,} {t.findings:>9,} "
              f"{1e3 * t.seconds / max(t.inputs, 1):>9.2f}")
        total.inputs += t.inputs
        total.accepted += t.accepted
        total.opnav_errors += t.opnav_errors
        total.findings += t.findings
    print(f"{'total':<15} {total.inputs:>8,} {total.accepted:>9,} {total.opnav_errors:>10,} {total.findings:>9,}")
    if not findings:
        print("no findings")
        if done < args.inputs:
            print(f"time bound reached after {done:,} of {args.inputs:,} inputs")
        return
    print(f"\n{len(findings)} finding type(s):")
    for f in sorted(findings.values(), key=lambda f: (f.key[0], -f.count)):
        reader, kind, _ = f.key
        print(f"- {reader}: {kind} x{f.count}: {f.message}")
        print(f"    at {f.opnav_frame or '-'} (last frame {f.last_frame or '-'})")
        print(f"    reproducer {f.reproducer}")
    if done < args.inputs:
        print(f"time bound reached after {done:,} of {args.inputs:,} inputs")


def print_classes(names, classes, tallies) -> None:
    """The table of issue 40, per class: cases, clear error, correct, unclear, traceback, hang, wrong, lost."""
    columns = ("unclear", "traceback", "hang", "wrong", "lost")
    print(f"\n{'class':<22} {'cases':>8} {'clear error':>12} {'correct':>8} " + " ".join(f"{c:>9}" for c in columns))
    order = list(dict.fromkeys(classes[name] for name in names))
    for klass in order + ["all"]:
        members = [tallies[n] for n in names if klass in ("all", classes[n])]
        kinds = {c: sum(t.kinds.get(c, 0) for t in members) for c in columns}
        print(f"{klass:<22} {sum(t.inputs for t in members):>8,} {sum(t.opnav_errors for t in members):>12,} "
              f"{sum(t.accepted for t in members):>8,} " + " ".join(f"{kinds[c]:>9,}" for c in columns))


if __name__ == "__main__":
    sys.exit(main())
