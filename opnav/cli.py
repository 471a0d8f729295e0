"""The ``opnav`` command.

Each sub-command lives in its own module under :mod:`opnav.commands` and
exposes ``NAME``, ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``, and
``OUT = "file"`` when its ``--out`` names a file rather than a folder. ``NAME``,
``HELP`` and ``OUT`` are string literals at the top of the module, before its first
function: :func:`commands` reads them from the module's source without importing it,
so ``opnav --help`` and ``opnav --version`` import no command module and
``opnav COMMAND ...`` imports that command's module only. A command module imports
only light modules at its top (heavy imports go inside ``add_arguments`` and ``run``).
Errors raised on purpose (:class:`opnav.errors.OpnavError`) become a one-line
message on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import ast
import gc
import importlib
import importlib.util
import logging
import os
import pkgutil
import re
import sys
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Iterable

from . import __version__
from . import commands as _commands_package
from .errors import InputError, OpnavError

#: Where a command module's header (its docstring, imports and constants) ends.
_HEADER_END = re.compile(r"^(?:def |class |@)", re.M)


@dataclass(frozen=True)
class Command:
    """A sub-command: its name, help line, module (dotted path) and what its ``--out`` names
    (``folder`` or ``file``), as the module's ``NAME``, ``HELP`` and ``OUT`` say."""

    name: str
    help: str
    module: str
    out: str = "folder"


def _constants(module: str) -> dict:
    """``NAME``, ``HELP`` and ``OUT`` of command module ``module``, read from its source's header
    (empty when the source cannot be read or does not assign them as literals there)."""
    spec = importlib.util.find_spec(module)
    try:
        source = Path(spec.origin).read_text(encoding="utf-8")
    except (AttributeError, TypeError, OSError):
        return {}
    end = _HEADER_END.search(source)
    try:
        tree = ast.parse(source[: end.start()] if end else source)
    except SyntaxError:
        return {}
    found = {}
    for node in tree.body:
        if (isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name)
                and node.targets[0].id in ("NAME", "HELP", "OUT")):
            try:
                found[node.targets[0].id] = ast.literal_eval(node.value)
            except ValueError:
                continue
    return found


@lru_cache(maxsize=1)
def commands() -> tuple[Command, ...]:
    """The sub-commands, by name (the modules of :mod:`opnav.commands` not starting with ``_``)."""
    table = []
    for info in sorted(pkgutil.iter_modules(_commands_package.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = f"{_commands_package.__name__}.{info.name}"
        found = _constants(module)
        if not {"NAME", "HELP"} <= set(found):  # not literals in the header: ask the module itself
            loaded = importlib.import_module(module)
            found = {"NAME": loaded.NAME, "HELP": loaded.HELP, "OUT": getattr(loaded, "OUT", "folder")}
        table.append(Command(found["NAME"], found["HELP"], module, found.get("OUT", "folder")))
    return tuple(table)


def check_out(path: str, kind: str) -> None:
    """Refuse an ``--out`` that cannot be written before any work: a file where a folder is
    needed or the reverse, or a place without write permission."""
    target = Path(path)
    if target.exists() and not (target.is_dir() or target.is_file()):  # a device, FIFO or socket: never replaced
        raise InputError(f"--out {target} is not a regular file or folder (a device, FIFO or socket); give a {kind}")
    if kind == "folder" and target.exists() and not target.is_dir():
        raise InputError(f"--out {target} is a file; give a folder")
    if kind == "file" and target.is_dir():
        raise InputError(f"--out {target} is a folder; give a file name")
    base = target if kind == "folder" else target.parent
    existing = next((p for p in (base, *base.parents) if p.exists()), Path("."))
    if not existing.is_dir():
        raise InputError(f"--out {target}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(f"--out {target}: no permission to write in {existing}")


def build_parser(load: Iterable[str] | None = None) -> argparse.ArgumentParser:
    """The ``opnav`` parser; the sub-commands named in ``load`` (None: all) get their options, which
    imports their modules. The others are listed with their help line only."""
    names = {command.name for command in commands()} if load is None else set(load)
    parser = argparse.ArgumentParser(
        prog="opnav",
        description="Image-in-the-loop optical navigation: render frames, process them into "
        "measurements, navigate with EKF/UKF/particle/batch/federated filters.",
    )
    parser.add_argument("--version", action="version", version=f"opnav {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress at INFO level")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command in commands():
        subparser = sub.add_parser(command.name, help=command.help, description=command.help)
        if command.name in names:
            module = importlib.import_module(command.module)
            module.add_arguments(subparser)
            subparser.set_defaults(run=module.run, out_kind=command.out)
    return parser


def command_named(argv: list[str]) -> str | None:
    """The sub-command ``argv`` runs: its first word that is not an option (the top-level options
    take no value), if that is a command's name."""
    known = {command.name for command in commands()}
    for token in argv:
        if token == "--":
            return None
        if not token.startswith("-"):
            return token if token in known else None
    return None


@contextmanager
def collector_paused():
    """``with collector_paused():`` the cyclic garbage collector pauses (and afterwards is as it was).

    A command's start-up (its module, numpy, scipy, astropy, numba...) creates some 190,000 objects
    that live as long as the process; the collector's passes over them while they are being made
    cost 0.12 s of the 0.74 s of CPU the imports of ``opnav solve`` take (0.61 s paused; load ~16,
    one run of each, repeated 4 times). Nothing made there is garbage worth collecting early.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    name = command_named(argv)
    with collector_paused():
        parser = build_parser(load=() if name is None else (name,))
        args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if getattr(args, "run", None) is None:
        parser.print_help()
        return 0
    from .allocator import keep_freed_memory

    keep_freed_memory()  # frame after frame, the image stage's arrays reuse the last frame's pages
    try:
        if getattr(args, "out", None) is not None:
            if not str(args.out).strip():
                raise InputError(f"--out must name a {args.out_kind}, got an empty name")
            check_out(args.out, args.out_kind)
        return int(args.run(args) or 0)
    except OpnavError as exc:
        print(f"opnav {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except (FileExistsError, NotADirectoryError, IsADirectoryError, PermissionError) as exc:
        # an output path that names a file where a folder is needed (or the reverse), or no rights
        print(f"opnav {args.command}: error: {exc.strerror}: {exc.filename}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"opnav {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # the reader went away (``opnav solve ... | head``): stop quietly, as other Unix tools do, and keep
        # Python from complaining again when it flushes stdout at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except OSError as exc:
        # the system refused a read or write (a full disk, a name too long, a folder removed under the
        # run, a read-only place): one line; files already written stay (every output is atomic)
        where = f": {exc.filename}" if exc.filename else ""
        print(f"opnav {args.command}: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
