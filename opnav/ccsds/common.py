"""What the CCSDS messages of :mod:`opnav.ccsds` share: a file read through ccsds-ndm into its object
model (every failure one :class:`~opnav.errors.InputError` naming the file), a message written (KVN
with the data lines in ccsds-ndm's layout, NDM/XML through its serializer; atomically), epochs as TDB
text with microseconds, and the checks of keyword values and numbers.
"""

from __future__ import annotations

import math
import re
import warnings
from collections.abc import Sequence
from datetime import datetime, timezone
from enum import Enum
from functools import lru_cache
from pathlib import Path

import numpy as np
from ccsds_ndm.mapping import NDMFileFormats
from ccsds_ndm.ndm_io import NdmIo
from xsdata.exceptions import ConverterWarning

from ..epochs import format_epoch, parse_epoch
from ..errors import InputError
from ..files import MAX_TEXT_BYTES, atomic_write_text, check_input_file


#: Decimal digits of the seconds in written epochs. Microseconds, not more: Python's
#: ``datetime.strptime('%f')`` and many other readers stop at six digits.
EPOCH_DIGITS = 6

EPOCH_RESOLUTION_S = 10.0 ** -EPOCH_DIGITS

_WRITTEN_EPOCH = re.compile(r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}\.\d+")

_DAY_OF_YEAR_EPOCH = re.compile(r"\s*(-?\d{4})-(\d{3})T(.*)")

#: TIME_SYSTEM values read (as opnav.epochs scales); anything else is refused.
_TIME_SCALES = {"TDB": "tdb", "TT": "tt", "UTC": "utc", "TAI": "tai"}

_XML_SCHEMA = {
    "OEM": "https://sanaregistry.org/r/ndmxml_unqualified/ndmxml-2.0.0-master-2.0.xsd",
    "TDM": "https://sanaregistry.org/r/ndmxml_unqualified/ndmxml-4.0.0-master-4.0.xsd",
}

#: Width of a KVN keyword column (``KEY<blanks> = value``), as ccsds-ndm writes it.
KEY_WIDTH = 24


def is_xml(path: Path) -> bool:
    """Whether ``path`` names NDM/XML (else KVN)."""
    return path.name.lower().endswith(".xml")


def write_kvn(path: Path, message, data: list[str]) -> None:
    """Write a KVN message whose segments were built without data rows, segment ``k``'s rows (``data[k]``,
    text as ccsds-ndm's writer lays them out) where that writer puts them: an OEM's after the blank line
    that follows ``META_STOP``, a TDM's after ``DATA_START``.

    ccsds-ndm writes every other line (header, metadata, markers); building 86,400 state vectors,
    covariance blocks or observations as its objects, only to have them written one field at a time,
    took most of a 30-day run's output time. ``tests/test_ccsds_golden.py`` pins the bytes.
    """
    from ccsds_ndm.kvn_tokenizer import SectionMarkerLine
    from ccsds_ndm.kvn_writer import write_kvn_lines

    marker, offset = ("DATA_START", 0) if type(message).__name__ == "Tdm" else ("META_STOP", 1)
    out: list[str] = []
    insert_at, k = -1, 0
    tdm = marker == "DATA_START"
    for i, line in enumerate(write_kvn_lines(message)):
        if tdm and out and out[-1] == "META_STOP" and not line.to_str().strip():
            # ccsds-ndm puts a blank line between META_STOP and DATA_START, where ccsds-ndm-py stops
            # with 'Expected DATA'; the standard allows the layout without it, which both read
            continue
        out.append(line.to_str())
        if isinstance(line, SectionMarkerLine) and line.key == marker:
            insert_at = i + offset
        if i == insert_at:
            out.append(data[k])
            k += 1
    if k != len(data):
        raise RuntimeError(f"ccsds-ndm laid out {k} data sections for {len(data)} segments")
    text = "\n".join(out)
    atomic_write_text(path, text if text.endswith("\n") else text + "\n")


def write_message(path: Path, message, kind: str) -> None:
    if is_xml(path):
        text = NdmIo().to_string(message, NDMFileFormats.XML, no_namespace_schema_location=_XML_SCHEMA[kind])
    else:
        text = NdmIo().to_string(message, NDMFileFormats.KVN)
    atomic_write_text(path, text if text.endswith("\n") else text + "\n")


#: KVN block markers that must come in pairs, in order (a file cut short ends inside one).
KVN_BLOCKS = ("META", "DATA", "COVARIANCE")


def check_kvn_blocks(path: Path, text: str) -> None:
    """Refuse a KVN message cut short or spliced: every ``<BLOCK>_START`` of :data:`KVN_BLOCKS` closed by
    its ``<BLOCK>_STOP`` before the next block opens (a TDM cut inside a META block was read as half its
    records, an OEM cut inside a COVARIANCE block without any covariance, both without a word)."""
    markers = {f"{block}_{end}": (block, end) for block in KVN_BLOCKS for end in ("START", "STOP")}
    open_block, opened_at = None, 0
    for number, line in enumerate(text.splitlines(), start=1):
        word = line.strip().split(" ", 1)[0]
        if word not in markers:
            continue
        block, end = markers[word]
        if end == "START":
            if open_block is not None:
                raise InputError(f"{path}: line {number}: {word} inside the {open_block} block opened at line "
                                 f"{opened_at} (a file cut short or spliced)")
            open_block, opened_at = block, number
        elif open_block != block:
            raise InputError(f"{path}: line {number}: {word} without its {block}_START")
        else:
            open_block = None
    if open_block is not None:
        raise InputError(f"{path}: the file ends inside the {open_block} block opened at line {opened_at} "
                         f"(no {open_block}_STOP: a file cut short?)")


def load_message(path: Path, kind: str, *, kvn_data: list | None = None):
    """Parse ``path`` with ccsds-ndm; every failure becomes a one-line InputError naming the file.

    With ``kvn_data`` (a list) and a KVN TDM, the observation lines of each segment are taken out of
    the text before ccsds-ndm parses it and appended to ``kvn_data`` as ``[(line number, line), ...]``
    per segment (:func:`opnav.ccsds.tdm._kvn_observations` reads them): ccsds-ndm builds each observation through
    ``typing.get_type_hints``, about 1 ms a line, 6 minutes for a 30-day S1 TDM.
    """
    check_input_file(path, f"CCSDS {kind} file", MAX_TEXT_BYTES["table"])
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text {kind} file (bytes that are not UTF-8)") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the {kind} file ({exc.strerror or exc})") from None
    if not text.strip():
        raise InputError(f"{path}: empty file, expected a CCSDS {kind}")
    if not text.lstrip().startswith("<"):
        check_kvn_blocks(path, text)
    if kvn_data is not None and not text.lstrip().startswith("<"):
        text = _strip_kvn_data(text, kvn_data)
    try:
        with warnings.catch_warnings():
            # xsdata keeps a number it cannot parse as text and only warns; make that an error
            warnings.simplefilter("error", ConverterWarning)
            message = NdmIo().from_string(text)
    except Exception as exc:  # noqa: BLE001 - ValueError, KeyError, lxml and xsdata errors all mean "malformed"
        raise InputError(f"{path}: not a readable CCSDS {kind} ({one_line(exc)})") from None
    found = str(getattr(message, "id", "") or "")
    if found != f"CCSDS_{kind}_VERS":
        name = found.removeprefix("CCSDS_").removesuffix("_VERS") or type(message).__name__
        raise InputError(f"{path}: a CCSDS {name} message, not a{'n' if kind[0] in 'AEIOU' else ''} {kind}")
    return message


def _strip_kvn_data(text: str, data: list) -> str:
    """``text`` without the lines between each ``DATA_START`` and ``DATA_STOP`` other than blanks and
    ``COMMENT`` lines; those lines, with their line numbers, appended to ``data``, one list a segment."""
    kept, inside = [], False
    for number, line in enumerate(text.splitlines(), start=1):
        word = line.strip()
        if word == "DATA_STOP":
            inside = False
        elif inside and word and not word.startswith("COMMENT"):
            data[-1].append((number, word))
            continue
        elif word == "DATA_START":
            inside = True
            data.append([])
        kept.append(line)
    return "\n".join(kept) + "\n"


def message_segments(message, path: Path, kind: str) -> list:
    segments = getattr(getattr(message, "body", None), "segment", None)
    if not isinstance(segments, list) or not segments:
        raise InputError(f"{path}: the {kind} has no segment")
    return segments


def required_field(obj, name: str, where: str):
    value = getattr(obj, name, None)
    if value is None:
        raise InputError(f"{where}: {name} is missing")
    return value


def time_scale(meta, where: str) -> str:
    system = enum_text(getattr(meta, "time_system", None))
    if system not in _TIME_SCALES:
        raise InputError(f"{where}: TIME_SYSTEM {system or '(missing)'} is not supported; "
                         f"expected one of {', '.join(_TIME_SCALES)}")
    return _TIME_SCALES[system]


def enum_text(value) -> str:
    if isinstance(value, Enum):
        value = value.value
    return "" if value is None else str(value).strip().upper()


def text_value(value, what: str, required: bool = True) -> str:
    if not isinstance(value, str) or (required and not value.strip()):
        raise InputError(f"{what} is missing or not text")
    return value.strip()


def epoch_text(value, what: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"{what}: EPOCH is missing")
    return value.strip()


def number_of(item, what: str) -> float:
    """The float of a model value (a ``value``/``units`` wrapper or a bare float)."""
    if item is None:
        raise InputError(f"{what} is missing")
    value = getattr(item, "value", item)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{what} is not a finite number: {value!r}")
    return float(value)


def parse_epochs(texts: list[str], scale: str, where: str) -> np.ndarray:
    # astropy reads day-of-year dates as 'YYYY:DDD:hh:mm:ss', the CCSDS form is 'YYYY-DDDThh:mm:ss'
    cleaned = [_DAY_OF_YEAR_EPOCH.sub(r"\1:\2:\3", text) for text in texts]
    try:
        return np.atleast_1d(np.asarray(parse_epoch(cleaned, scale), dtype=float))
    except InputError:
        pass
    # one by one: astropy wants one form for a whole list (a file may mix calendar and
    # day-of-year dates), and a message should name the one bad date, not the list
    out = np.empty(len(texts))
    for k, (text, clean) in enumerate(zip(texts, cleaned)):
        try:
            out[k] = parse_epoch(clean, scale)
        except InputError:
            raise InputError(f"{where}: cannot read epoch {text!r} as a {scale.upper()} date") from None
    return out


def format_epochs(t: np.ndarray, what: str) -> list[str]:
    texts = [str(text) for text in format_epoch(np.atleast_1d(np.asarray(t, dtype=float)), "tdb",
                                                 precision=EPOCH_DIGITS)]
    for k, text in enumerate(texts):
        if not _WRITTEN_EPOCH.fullmatch(text):
            raise InputError(f"{what}[{k}] = {t[k]!r} s is outside the years 0000-9999 a CCSDS date can hold")
    repeated = [k for k in range(1, len(texts)) if texts[k] == texts[k - 1]]
    if repeated:
        k = repeated[0]
        raise InputError(f"{what}[{k - 1}] and [{k}] are less than 1 us apart ({texts[k]} TDB); "
                         "the file keeps microseconds")
    return texts


def format_shared_epochs(t: np.ndarray, what: str) -> list[str]:
    """Epoch texts of ``t`` (TDB, microseconds), repeated epochs allowed (records of one frame share one)."""
    if t.size == 0:
        return []
    unique, inverse = np.unique(t, return_inverse=True)
    texts = [str(text) for text in format_epoch(unique, "tdb", precision=EPOCH_DIGITS)]
    for k, text in enumerate(texts):
        if not _WRITTEN_EPOCH.fullmatch(text):
            raise InputError(f"{what} {unique[k]!r} s is outside the years 0000-9999 a CCSDS date can hold")
    return [texts[k] for k in inverse.ravel().tolist()]


@lru_cache(maxsize=1024)
def is_keyword_value(value: str) -> bool:
    """Whether :func:`keyword_value` accepts ``value`` (cached: a TDM names a few targets and sensors
    in every record)."""
    try:
        keyword_value("value", value)
    except InputError:
        return False
    return True


def keyword_value(name: str, value) -> str:
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"{name} must be a non-empty string, got {value!r}")
    if any(ord(c) < 32 or ord(c) == 127 for c in value) or value != value.strip():
        raise InputError(f"{name} {value!r} has line breaks, control characters or surrounding blanks; "
                         "a CCSDS keyword value cannot keep them")
    return value


def comment_lines(comment: str | Sequence[str] | None) -> list[str]:
    if comment is None:
        return []
    lines = comment.splitlines() if isinstance(comment, str) else list(comment)
    out = []
    for line in lines:
        if not isinstance(line, str) or "\n" in line or "\r" in line:
            raise InputError(f"comment lines must be strings without line breaks, got {line!r}")
        out.append(line.strip())
    return out


def creation_time_utc() -> str:
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S")


def first_true(mask: np.ndarray) -> int:
    return int(np.argmax(mask))


def one_line(exc: BaseException) -> str:
    # xsdata puts the offending text on a second line; keep it, on one line
    text = "; ".join(line.strip() for line in str(exc).strip().splitlines() if line.strip()) or type(exc).__name__
    return text if len(text) <= 160 else text[:157] + "..."


def percent_escaped(text: str) -> str:
    """``text`` for a ``%`` format string (its ``%`` doubled)."""
    return text.replace("%", "%%")
