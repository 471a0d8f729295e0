"""The one loader of opnav's TOML files: scene, navigation and run files -> typed, frozen options.

Every file opnav reads as TOML goes through here, in four steps:

1. :func:`read_toml` parses the file; a missing file says which kind of file was expected
   (``run file not found: X``) and an unreadable one names the file.
2. :func:`build` makes a frozen dataclass from one table by the dataclass's type hints. Each key
   must be a field (an unknown key is refused with the nearest known one suggested, through
   :func:`difflib.get_close_matches`), each value is converted to its field's type by
   :func:`convert`, a field whose type is itself a dataclass is read from the sub-table of that
   name (recursively), and fields without a default must be given. The dataclass's
   ``__post_init__`` then checks the values; its :class:`~opnav.errors.InputError` comes back
   with the file and table in front.
3. ``--set KEY=VALUE`` overrides (:func:`parse_overrides`) are applied by :func:`build` to the
   table they change, their keys checked the same way (with a suggestion) and their text
   converted to the field's type.
4. Unit conversions (degrees to radians, calendar dates to TDB seconds) are left to the thin
   loader of each file (:func:`opnav.sim.scene.load_scene`,
   :func:`opnav.filters.options.load_navigation`, :func:`opnav.studies.settings.load_run_file`).

Types a field may have: ``bool``, ``int``, ``float`` (finite), ``str``, :data:`CalendarText`,
``dict`` (a table kept as it is), a tuple of one of those (``tuple[str, ...]`` or a fixed
length such as ``tuple[float, float, float]``), a union of those (``X | None``,
``float | tuple[float, float, float]``) or a dataclass (a sub-table). A field's
``metadata["accepts"]`` replaces the type's description in its error message.

The rules, the same in every file (scene, ``[navigation]``, run file; docs/formats/README.md):

- **Values are TOML's own.** A file writes numbers, booleans and arrays as TOML does: ``"1024"``
  is not a number, ``"false"`` not a boolean and ``"a, b"`` not an array (the message says how to
  write it). A whole number is accepted for a float and a float without fraction (``2.0``) for
  an integer. Only ``--set`` values are text (``text=True`` of :func:`convert`, the overrides of
  :func:`build`): ``"true"``/``"false"``/``"yes"``/``"no"``/``"1"``/``"0"``, numbers as text,
  arrays as comma-separated text, ``none`` for an optional value.
- **Enumerated names are case-insensitive.** A field whose ``metadata["choices"]`` names its
  accepted values (a tuple, or a function giving it, for lists known only to a higher layer),
  or a field named by the ``choices`` argument of :func:`build` (for classes the loader does not
  own), takes any case and is stored as the name is listed (``"EKF"`` -> ``"ekf"``,
  ``"ICRF"`` -> ``"icrf"``); anything else is refused with the list. In an array each item is
  a name (``tuple[str, ...]``), given once.
- **Dates** (:data:`CalendarText`) are text such as ``"2014-07-15T00:00:00"`` (a trailing ``Z``
  allowed) or an unquoted TOML date-time or date. A TOML date-time with ``Z`` or an offset
  (``2014-07-15T02:00:00+02:00``) is turned into the UTC text a quoted one would be
  (``"2014-07-15T00:00:00Z"``); :func:`check_zone` refuses such a date in a scale other than UTC.

- **Numbers stay computable.** A float is 0 or of magnitude :data:`FLOAT_RANGE` (1e-150 to
  1e150): its square and the product of two such values are finite and not lost to underflow
  (``noise_arcsec = 1e300`` overflowed and ``1e-300`` made every covariance singular). No
  quantity opnav takes, in its units (km, s, arcsec, ADU, probabilities), comes near the limits.

Every message is one line naming the file, the table and the key, and what is accepted.

This is a foundation module: it imports only :mod:`opnav.errors`, :mod:`opnav.files` and the standard library.
"""

from __future__ import annotations

import dataclasses
import datetime
import difflib
import math
import reprlib
import tomllib
import types
import typing
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from pathlib import Path

from .constants import TIME_SCALES  # noqa: F401 - the scales a file's scale keys take
from .errors import InputError
from .files import MAX_TEXT_BYTES, check_input_file

#: A calendar date field: TOML text such as ``"2014-07-15T00:00:00"`` or an unquoted TOML
#: date-time, kept as its text (the loader converts it with its scale, :func:`opnav.epochs.parse_epoch`);
#: a TOML date-time with ``Z`` or an offset becomes UTC text ending in ``Z``.
CalendarText = typing.NewType("CalendarText", str)


_REPR = reprlib.Repr()
_REPR.maxstring, _REPR.maxother, _REPR.maxlist = 60, 60, 8


#: Magnitudes a float setting may have besides 0 (module notes).
FLOAT_RANGE = (1e-150, 1e150)


@dataclass(frozen=True)
class Where:
    """A table of a file, named by the errors about its keys.

    Attributes
    ----------
    path : str
        The file (as the user gave it).
    table : str
        Dotted table name (``"settings"``, ``"navigation.ukf"``); ``""`` for the file's top level.
    """

    path: str
    table: str = ""

    def key(self, name: str) -> str:
        """``"file: [table] name"``: where the value of key ``name`` is."""
        return f"{self.path}: [{self.table}] {name}" if self.table else f"{self.path}: {name}"

    def sub(self, name: str) -> Where:
        """The sub-table ``name`` of this table."""
        return Where(self.path, f"{self.table}.{name}" if self.table else name)

    @property
    def place(self) -> str:
        """``"[table] of file"`` (or just the file at the top level)."""
        return f"[{self.table}] of {self.path}" if self.table else self.path


#: Each kind of TOML file: what marks it, the commands that take it and a sample of it.
FILE_KINDS = {
    "run file": ("[scenario] study", "opnav run and opnav montecarlo", "samples/s1_jul_both_0.1.toml"),
    "scene file": ("[camera], [epochs], [observer]", "opnav render and opnav navigate --scenario",
                   "samples/s1_render.toml"),
}
_SCENE_TABLES = ("camera", "epochs", "observer", "pointing", "targets", "psf", "detector", "render")
_RUN_TABLES = ("settings", "filters", "faults")


def toml_kind(data: dict) -> str | None:
    """Which kind of file (:data:`FILE_KINDS`) the parsed TOML ``data`` is: ``"run file"`` (a
    ``[scenario]`` naming a ``study``, or a ``[settings]``/``[filters]``/``[faults]`` table),
    ``"scene file"`` (a ``[camera]``, ``[epochs]``, ``[observer]`` ... table), or None."""
    head = data.get("scenario")
    if isinstance(head, dict) and "study" in head:
        return "run file"
    if any(name in data for name in _SCENE_TABLES):
        return "scene file"
    if any(name in data for name in _RUN_TABLES):
        return "run file"
    return None


def describe_kind(data: dict) -> str:
    """``"a run file of study s2"``, ``"a scene file"`` or ``"neither a run file nor a scene file"``."""
    kind = toml_kind(data)
    if kind == "run file":
        study = (data.get("scenario") or {}).get("study") if isinstance(data.get("scenario"), dict) else None
        return f"a run file of study {study}" if isinstance(study, str) else "a run file"
    return f"a {kind}" if kind else "neither a run file nor a scene file"


def refuse_other_kind(path: str | Path, data: dict, kind: str) -> None:
    """``InputError`` when ``data`` (the parsed file ``path``) is another kind of file than ``kind``
    (:data:`FILE_KINDS`): the message says what it is, which commands take it and what is needed."""
    actual = toml_kind(data)
    if actual is None or actual == kind or kind not in FILE_KINDS:
        return
    _, commands, _ = FILE_KINDS[actual]
    marks, _, sample = FILE_KINDS[kind]
    raise InputError(f"{path} is {describe_kind(data)} ({FILE_KINDS[actual][0]}), which {commands} take; "
                     f"a {kind} ({marks}) is needed here, e.g. {sample}")


def check_file_exists(path: str | Path, kind: str) -> Path:
    """``path`` if it is a file; else ``InputError``: ``"<kind> not found: <path>"`` with the nearest
    ``*.toml`` of its folder suggested (:func:`difflib.get_close_matches`), or the folder's TOML files
    listed when none is near, or that the folder does not exist."""
    path = Path(path)
    if path.is_file():
        return path
    if path.is_dir():
        raise InputError(f"{path} is a folder; give a {kind}")
    if path.exists():  # a FIFO, socket or device: reading it could hang or never end
        raise InputError(f"{path} is not a regular file (a FIFO, socket or device); give a {kind}")
    folder = path.parent
    if not folder.is_dir():
        raise InputError(f"{kind} not found: {path} (no folder {folder})")
    names = sorted(p.name for p in folder.glob("*.toml") if p.is_file())
    close = difflib.get_close_matches(path.name, names, n=1, cutoff=0.6)
    if close:
        raise InputError(f"{kind} not found: {path} (did you mean {folder / close[0]}?)")
    listed = f"the TOML files there: {', '.join(names)}" if names else "no TOML file there"
    raise InputError(f"{kind} not found: {path} ({listed})")


def read_toml(path: str | Path, *, kind: str) -> dict:
    """Parse TOML file ``path``.

    Parameters
    ----------
    path : str or Path
    kind : str
        What the file is, for the messages: ``"scene file"``, ``"navigation file"``, ``"run file"``.

    Raises
    ------
    InputError
        ``"<kind> not found: <path>"`` for a missing file, with the nearest ``*.toml`` of its folder
        suggested (:func:`check_file_exists`); a message naming the file for one that cannot be read
        or is not TOML; a file of another kind (:func:`refuse_other_kind`).
    """
    path = check_input_file(check_file_exists(path, kind), kind, MAX_TEXT_BYTES["toml"])
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{kind} not found: {path}") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputError(f"{path}: not a readable TOML file ({exc})") from None
    except RecursionError:
        # tomllib recurses once per level of nested arrays or inline tables; a few hundred exhaust the stack
        raise InputError(f"{path}: not a readable TOML file (arrays or inline tables nested too deeply; "
                         f"a {kind} needs at most a few levels)") from None
    refuse_other_kind(path, data, kind)
    return data


def parse_overrides(pairs: list[str] | None) -> dict[str, str]:
    """``["KEY=VALUE", ...]`` (the ``--set`` options) -> ``{KEY: VALUE}``; a pair without ``=`` is an error naming it."""
    out = {}
    for pair in pairs or []:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise InputError(f"--set expects KEY=VALUE, got {pair!r}")
        out[key.strip()] = value.strip()
    return out


class _Refused(Exception):
    """A value that is not of the type asked for (turned into an InputError by :func:`convert`)."""


def convert(value, kind, where: str, *, text: bool = True, accepts: str | None = None, choices=None):
    """``value`` (a TOML value, or the text of a ``--set`` override) as type ``kind``.

    Parameters
    ----------
    value
        The value as read.
    kind
        A type of the module notes (not a dataclass: :func:`build` reads those).
    where : str
        Start of the message, the file, table and key (:meth:`Where.key`).
    text : bool
        Also accept text for numbers, booleans, arrays and ``none`` (``--set`` values); a file's
        values are TOML's own (``text=False``).
    accepts : str, optional
        What the message says is accepted, instead of the type's description.
    choices : tuple of str, or a function returning one, optional
        The accepted names of a string (or of each string of an array), matched in any case and
        returned as listed.

    Raises
    ------
    InputError
        ``"<where> must be <what is accepted>, got <value>"``; a non-finite float is refused too. A
        file's text that would be a number, boolean or array as ``--set`` text says how to write it.
    """
    try:
        result = _convert(value, kind, text)
    except _Refused:
        raise InputError(f"{where} must be {accepts or _describe(kind)}{_hint(value, kind, text)}, "
                         f"got {_REPR.repr(value)}") from None
    return result if choices is None else _choose(result, choices, where)


def _hint(value, kind, text: bool) -> str:
    """How to write a file's text value that ``--set`` would have read as ``kind``."""
    if text or not isinstance(value, str):
        return ""
    try:
        as_text = _convert(value, kind, True)
    except _Refused:
        return ""
    if as_text is None:
        return " (leave the key out for none)"
    if isinstance(as_text, tuple):
        return " (written as a TOML array, [a, b, ...])"
    return " (written without quotes)"


def _choose(value, choices, where: str):
    """``value`` (a string, or a tuple of them) with each name as ``choices`` lists it, matched in any case."""
    names = tuple(choices() if callable(choices) else choices)
    lookup = {name.lower(): name for name in names}

    def one(item):
        if not isinstance(item, str):
            return item
        key = item.strip().lower()
        if key in lookup:
            return lookup[key]
        close = difflib.get_close_matches(key, list(lookup), n=1)
        guess = f" (did you mean {lookup[close[0]]!r}?)" if close else ""
        what = "names from" if isinstance(value, tuple) else "one of"
        raise InputError(f"{where} must be {what} {', '.join(names)}, got {_REPR.repr(item)}{guess}")

    if not isinstance(value, tuple):
        return one(value)
    chosen = tuple(one(item) for item in value)
    repeated = sorted({name for name in chosen if chosen.count(name) > 1})
    if repeated:  # a body listed twice was drawn twice (twice its light); a filter twice would run twice
        raise InputError(f"{where} lists {', '.join(map(repr, repeated))} more than once; give each name once")
    return chosen


def _utc_text(moment: datetime.datetime) -> str:
    """A TOML date-time with ``Z`` or an offset as the UTC text a quoted one would be (``...Z``)."""
    utc = moment.astimezone(datetime.timezone.utc).replace(tzinfo=None)
    return utc.isoformat() + "Z"


def check_zone(text: str, scale: str, where: str) -> None:
    """Refuse a date written in UTC (a trailing ``Z``, or a TOML offset turned into one) read in another scale.

    Raises
    ------
    InputError
        ``"<where> '2014-07-15T00:00:00Z' is a UTC date (Z or an offset) but its scale is 'tt'; ..."``.
    """
    if isinstance(text, str) and text.strip().upper().endswith("Z") and str(scale).strip().lower() != "utc":
        raise InputError(f"{where} {text!r} is a UTC date (Z or an offset) but its scale is {scale!r}; "
                         f"drop the Z or set the scale to utc")


def _convert(value, kind, text: bool):
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin in (typing.Union, types.UnionType):
        if value is None or (text and isinstance(value, str) and value.strip().lower() in ("none", "")):
            if type(None) in args:
                return None
        for option in (a for a in args if a is not type(None)):
            try:
                return _convert(value, option, text)
            except _Refused:
                pass
        raise _Refused
    if kind is bool:
        if isinstance(value, bool):
            return value
        if text and isinstance(value, (str, int)):
            answer = {"true": True, "1": True, "yes": True, "false": False, "0": False, "no": False}
            lowered = str(value).strip().lower()
            if lowered in answer:
                return answer[lowered]
        raise _Refused
    if kind is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        try:
            if isinstance(value, float) and value.is_integer():  # 2.0 for an integer, in a file too
                return int(value)
            if text and isinstance(value, str):
                return int(value)
        except (ValueError, OverflowError):
            pass
        raise _Refused
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float, str)) or (isinstance(value, str) and not text):
            raise _Refused
        try:
            number = float(value)
        except (ValueError, OverflowError):  # TOML integers have no size limit
            raise _Refused from None
        if not math.isfinite(number) or not (number == 0.0 or FLOAT_RANGE[0] <= abs(number) <= FLOAT_RANGE[1]):
            raise _Refused
        return number
    if kind is str:
        if not isinstance(value, str):
            raise _Refused
        return value
    if kind is CalendarText:
        if isinstance(value, datetime.datetime) and value.tzinfo is not None:
            return _utc_text(value)
        if isinstance(value, (str, datetime.date, datetime.time)):  # datetime.datetime is a date
            return str(value)
        raise _Refused
    if kind is dict:
        if not isinstance(value, Mapping):
            raise _Refused
        return dict(value)
    if origin is tuple:
        items = value.split(",") if text and isinstance(value, str) else value
        if not isinstance(items, (list, tuple)):
            raise _Refused
        if text:
            items = [item.strip() if isinstance(item, str) else item for item in items]
            items = [item for item in items if item != ""]
        variable = len(args) == 2 and args[1] is Ellipsis
        if not variable and len(items) != len(args):
            raise _Refused
        inner = [args[0]] * len(items) if variable else args
        return tuple(_convert(item, k, text) for item, k in zip(items, inner))
    raise TypeError(f"opnav.config cannot read fields of type {kind!r}")  # a programming error


def _describe(kind, plural: bool = False) -> str:
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(a, plural) for a in args if a is not type(None))
    if origin is tuple:
        variable = len(args) == 2 and args[1] is Ellipsis
        return f"an array of {'' if variable else f'{len(args)} '}{_describe(args[0], plural=True)}"
    names = {bool: ("true or false", "true/false values"), int: ("int (a whole number)", "whole numbers"),
             float: (f"float (a finite number: 0 or of magnitude {FLOAT_RANGE[0]:g} to {FLOAT_RANGE[1]:g})",
                     f"finite numbers (0 or of magnitude {FLOAT_RANGE[0]:g} to {FLOAT_RANGE[1]:g})"), str: ("a string", "strings"),
             CalendarText: ("a calendar date such as '2014-07-15T00:00:00'", "calendar dates"),
             dict: ("a table", "tables")}
    if kind in names:
        return names[kind][plural]
    return getattr(kind, "__name__", str(kind))


def check_keys(keys: Collection[str], known: Collection[str], where: Where, *, noun: str = "key",
               by: str = "") -> None:
    """Refuse the ``keys`` that are not ``known``, suggesting the nearest known one of each.

    Parameters
    ----------
    keys, known : collections of str
    where : Where
        The table the keys are in.
    noun : str
        What a key is called in the message (``"key"``, ``"setting"``, ``"table"``, ``"section"``).
    by : str
        Where the keys came from when not the file itself (``"--set"``).

    Raises
    ------
    InputError
        e.g. ``"unknown setting(s) ['duraton_days'] in [settings] of s1.toml; did you mean 'duration_days'?"``;
        the message ends with the list of known keys.
    """
    unknown = sorted(set(keys) - set(known), key=str)
    if not unknown:
        return
    known = list(known)
    close = {key: difflib.get_close_matches(str(key), known, n=1) for key in unknown}
    source = f"given by {by} for {where.place}" if by else f"in {where.place}"
    message = f"unknown {noun}(s) {_REPR.repr(unknown)} {source}"
    guesses = [(key, match[0]) for key, match in close.items() if match]
    if len(unknown) == 1 and guesses:
        message += f"; did you mean {guesses[0][1]!r}?"
    elif guesses:
        message += "; did you mean " + ", ".join(f"{match!r} for {_REPR.repr(key)}" for key, match in guesses) + "?"
    raise InputError(f"{message} (known {noun}s: {', '.join(known) or 'none'})")


def build(cls, table: Mapping, where: Where, *, text: bool = False, noun: str = "key",
          overrides: Mapping[str, str] | None = None, set_prefix: str = "",
          exclude: Mapping[type, Collection[str] | Mapping[str, str]] | None = None,
          choices: Mapping[type, Mapping[str, object]] | None = None):
    """An instance of frozen dataclass ``cls`` from TOML table ``table``, by ``cls``'s type hints.

    Parameters
    ----------
    cls : dataclass type
    table : mapping
        The table as parsed: TOML values (or values already of the field's type), never text for
        numbers, booleans or arrays (module notes).
    where : Where
        The file and table, for the messages.
    text : bool
        Ignored: a file's values are TOML's own in every file (module notes); only ``overrides``
        are text. Kept so that callers written when files could hold text still run.
    noun : str
        What a key of this table is called in messages (``"setting"``, ``"fault"``).
    overrides : mapping of str to str, optional
        ``--set`` values (text) replacing or adding keys of this table.
    set_prefix : str
        How the user wrote the overrides' keys before the field name (``"faults."``), for messages.
    exclude : mapping of dataclass type to field names, optional
        Fields of those classes (here or in sub-tables) that a file may not set: the program sets
        them. Given as a mapping of field name to where the value comes from instead, a key
        written is refused with that reason (e.g. the gate of ``[navigation.ukf]``: "the gate is
        [navigation] gate_probability"); otherwise it is an unknown key.
    choices : mapping of dataclass type to {field name: names}, optional
        Enumerated fields of classes the loader does not own (module notes), as a field's
        ``metadata["choices"]`` would give them.

    Returns
    -------
    cls instance

    Raises
    ------
    InputError
        For an unknown key (with a suggestion), a missing key, a value of the wrong type or a value
        ``cls`` refuses; every message names ``where``'s file and table and the key.
    """
    del text  # file values are TOML's own (module notes)
    if not isinstance(table, Mapping):
        raise InputError(f"{where.path}: [{where.table}] must be a table, got {_REPR.repr(table)}")
    excluded = (exclude or {}).get(cls, ())
    reasons = dict(excluded) if isinstance(excluded, Mapping) else {}
    for name in [*table, *(overrides or {})]:
        if name in reasons:
            raise InputError(f"{where.key(name)} cannot be set here: {reasons[name]}")
    skip = set(excluded)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init and f.name not in skip}
    check_keys(table, fields, where, noun=noun)
    check_keys(overrides or {}, fields, where, noun=noun, by="--set")
    hints = typing.get_type_hints(cls)
    named = (choices or {}).get(cls, {})
    rules = (exclude, choices)
    values = {name: _field(value, hints[name], fields[name], where, False, rules, named.get(name))
              for name, value in table.items()}
    for name, value in (overrides or {}).items():
        values[name] = _field(value, hints[name], fields[name], where, True, rules, named.get(name),
                              at=f"{where.path}: --set {set_prefix}{name}")
    missing = []
    for name, f in fields.items():
        if name in values or f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING:
            continue
        if _dataclass_in(hints[name]) is not None:  # an absent sub-table is an empty one
            values[name] = _field({}, hints[name], f, where, False, rules, None)
        else:
            missing.append(name)
    if missing:
        raise InputError(f"{where.path}: [{where.table}] needs {', '.join(missing)}" if where.table
                         else f"{where.path}: needs {', '.join(missing)}")
    try:
        return cls(**values)
    except InputError as exc:
        raise InputError(_located(str(exc), where)) from None
    except TypeError as exc:
        raise InputError(f"{where.path}: bad [{where.table}] ({exc})") from None


def _dataclass_in(kind):
    """The dataclass of a field typed ``D`` or ``D | None``, else None."""
    if typing.get_origin(kind) in (typing.Union, types.UnionType):
        found = [a for a in typing.get_args(kind) if dataclasses.is_dataclass(a)]
        return found[0] if found else None
    return kind if dataclasses.is_dataclass(kind) else None


def _field(value, kind, f: dataclasses.Field, where: Where, text: bool, rules, named, at: str | None = None):
    """One field's value: a sub-table built, anything else converted (``rules``: build's exclude and choices)."""
    sub = _dataclass_in(kind)
    if sub is not None:
        if isinstance(value, sub) or (value is None and typing.get_origin(kind) is not None):
            return value
        if not isinstance(value, Mapping):
            raise InputError(f"{at or where.key(f.name)} must be a table ([{where.sub(f.name).table}]), "
                             f"got {_REPR.repr(value)}")
        return build(sub, value, where.sub(f.name), exclude=rules[0], choices=rules[1])
    return convert(value, kind, at or where.key(f.name), text=text, accepts=f.metadata.get("accepts"),
                   choices=f.metadata.get("choices", named))


def _located(message: str, where: Where) -> str:
    """``message`` (from a dataclass's checks) with the file and table in front, unless it has them."""
    if where.path in message:
        return message
    if not where.table:
        return f"{where.path}: {message}"
    if message.startswith(f"[{where.table}]"):
        return f"{where.path}: {message}"
    return f"{where.path}: [{where.table}] {message}"
