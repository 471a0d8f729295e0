"""The ``opnav`` command.

Each sub-command lives in its own module under :mod:`opnav.commands` and
exposes ``NAME``, ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``, and
``OUT = "file"`` when its ``--out`` names a file rather than a folder.
Errors raised on purpose (:class:`opnav.errors.OpnavError`) become a one-line
message on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import pkgutil
import sys
from pathlib import Path

from . import __version__, commands
from .allocator import keep_freed_memory
from .errors import InputError, OpnavError


def _command_modules():
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if not info.name.startswith("_"):
            yield importlib.import_module(f"{commands.__name__}.{info.name}")


def check_out(path: str, kind: str) -> None:
    """Refuse an ``--out`` that cannot be written before any work: a file where a folder is
    needed or the reverse, or a place without write permission."""
    target = Path(path)
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="opnav",
        description="Image-in-the-loop optical navigation: render frames, process them into "
        "measurements, navigate with EKF/UKF/particle/batch/federated filters.",
    )
    parser.add_argument("--version", action="version", version=f"opnav {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress at INFO level")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in _command_modules():
        command = sub.add_parser(module.NAME, help=module.HELP, description=module.HELP)
        module.add_arguments(command)
        command.set_defaults(run=module.run, out_kind=getattr(module, "OUT", "folder"))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if getattr(args, "run", None) is None:
        parser.print_help()
        return 0
    keep_freed_memory()  # frame after frame, the image stage's arrays reuse the last frame's pages
    try:
        if getattr(args, "out", None):
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


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
