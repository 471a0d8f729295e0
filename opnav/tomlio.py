"""Reading scenario TOML files with errors that name the file."""

from __future__ import annotations

import math
import tomllib
import types
import typing
from pathlib import Path

from .errors import InputError


def read_toml(path: str | Path) -> dict:
    """Parse TOML file ``path``; a missing or unreadable file raises ``InputError`` naming it."""
    path = Path(path)
    try:
        return tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"scenario file not found: {path}") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputError(f"{path}: not a readable TOML file ({exc})") from None
    except RecursionError:
        # tomllib recurses once per level of nested arrays or inline tables; a few hundred exhaust the stack
        raise InputError(f"{path}: not a readable TOML file (arrays or inline tables nested too deeply; "
                         "scenario files need at most a few levels)") from None


def convert(value, kind, where: str):
    """``value`` (a TOML value, or the text of a ``--set`` override) as type ``kind``.

    ``kind`` is bool, int, float, str, ``X | None`` or a tuple of one of those; text is
    accepted for numbers and booleans (``"true"``/``"false"``/``"1"``/``"0"``/``"yes"``/``"no"``),
    never a non-finite float. Any other value raises :class:`InputError` starting with ``where``
    (the file and key), so a string where a number belongs never reaches arithmetic.
    """
    origin = typing.get_origin(kind)
    args = typing.get_args(kind)
    try:
        if origin in (typing.Union, types.UnionType) and type(None) in args:
            if value is None or (isinstance(value, str) and value.strip().lower() in ("none", "")):
                return None
            (inner,) = [a for a in args if a is not type(None)]
            return convert(value, inner, where)
        if kind is bool:
            if isinstance(value, bool):
                return value
            text = str(value).strip().lower()
            if text in ("true", "1", "yes"):
                return True
            if text in ("false", "0", "no"):
                return False
            raise ValueError(f"expected true or false, got {value!r}")
        if kind is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError(f"expected an integer, got {value!r}")
            return int(value)
        if kind is float:
            if isinstance(value, bool) or not isinstance(value, (int, float, str)):
                raise ValueError(f"expected a number, got {value!r}")
            number = float(value)
            if not math.isfinite(number):
                raise ValueError(f"expected a finite number, got {value!r}")
            return number
        if kind is str:
            if not isinstance(value, str):
                raise ValueError(f"expected a string, got {value!r}")
            return value
        if origin is tuple:
            items = value.split(",") if isinstance(value, str) else value
            if not isinstance(items, (list, tuple)):
                raise ValueError(f"expected a list, got {value!r}")
            inner = args[0] if args else str
            items = [item.strip() if isinstance(item, str) else item for item in items]
            return tuple(convert(item, inner, where) for item in items if item != "")
    except InputError:
        raise
    except (TypeError, ValueError, OverflowError) as exc:
        raise InputError(f"{where}: {exc}") from None
    raise InputError(f"{where}: unsupported type {kind!r}")
