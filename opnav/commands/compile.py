"""``opnav compile``: compile opnav's numba kernels for this machine now.

Example::

    opnav compile                      # every kernel opnav's runs call
    opnav compile --uses images,filters --workers 2

A kernel is compiled on its first call and cached next to its module (numba's ``__pycache__``, or
``NUMBA_CACHE_DIR``); later processes load it. ``opnav run`` and ``opnav demo`` compile what
they need before their progress bars start (:func:`compile_for_run`), with one line saying so;
this command does it ahead of time, e.g. in an image build or after ``pip install``, for all of
them (:mod:`opnav.compiled`: :data:`~opnav.compiled.KERNEL_CALLS`, :func:`~opnav.compiled.warm_up`).
"""

from __future__ import annotations

import argparse
import sys
from typing import Iterable

from ..errors import InputError

NAME = "compile"
HELP = "compile opnav's numba kernels for this machine now (runs otherwise compile them on first use)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--uses", default="all",
                        help="comma-separated: images, ekf, ukf, filters, sigma-points, particles, or all "
                             "(default: all)")
    parser.add_argument("--workers", type=int, default=None,
                        help="processes to compile in (default: one per core)")


def run_uses(run_file, filters: Iterable[str] | None = None, mode: str | None = None) -> frozenset[str]:
    """The kernel uses (:data:`opnav.compiled.USES`) of running ``run_file`` (a
    :class:`~opnav.studies.settings.RunFile`) with ``filters`` and ``mode`` (None: the run file's)."""
    from ..compiled import uses_of
    from ..studies import STUDIES

    if not STUDIES[run_file.study].generic_filters:  # S2, S4: their own propagation, general-path kernels
        return uses_of(("ukf",), compiled_steps=False)
    # S1's RA/Dec records with the white ephemeris error go through the compiled single-run steps, and
    # a mission's without starlight records (its ephemeris error is white)
    steps = (run_file.study == "s1" and getattr(run_file.settings, "ephemeris_error", "white") == "white") or (
        run_file.study == "mission" and not run_file.settings.starlight_target)
    return uses_of(tuple(filters or run_file.filters), images=(mode or run_file.mode) == "images",
                   compiled_steps=steps)


def compile_for_run(uses: Iterable[str], *, show: bool, workers: int | None = None) -> None:
    """Compile the kernels of ``uses`` (:func:`run_uses`) that numba's cache does not hold
    (:func:`opnav.compiled.warm_up`, in ``workers`` processes; None: one per core) before a run
    starts, so that no progress bar's estimate includes compile time. With ``show``, one line on
    stderr before (how many, about how long) and one after. Nothing when all are cached."""
    from ..compiled import cores, pending, warm_up

    todo = pending(uses)
    if not todo:
        return
    workers = cores() if workers is None else max(1, workers)
    if show:
        print(f"compiling opnav's numba kernels for this machine: {len(todo)} for this run, {_about(todo, workers)} "
              "(first run only; later runs load them from numba's cache)...", file=sys.stderr, flush=True)
    result = warm_up(uses, workers=workers)
    if show:
        print(f"compiled {_done(result)}", file=sys.stderr, flush=True)


def _about(calls, workers: int) -> str:
    """``about N s``, for a machine as busy as this one is now."""
    from ..compiled import estimate_s, rounded_s

    idle, now = estimate_s(calls, workers), estimate_s(calls, workers, busy=True)
    return f"about {rounded_s(now)} s" + (" on this busy machine" if now > 1.3 * idle else "")


def _done(result) -> str:
    """``N kernels in S s`` (and the failures, which compile, or fail, on first use instead)."""
    text = f"{len(result.compiled)} kernels in {result.wall_s:.0f} s"
    if result.failed:
        text += f"; {len(result.failed)} did not compile ({result.failed[0][0].name}: {result.failed[0][1]})"
    return text


def run(args: argparse.Namespace) -> int:
    from ..compiled import USES, cores, kernel_calls, pending, warm_up

    names = [name.strip() for name in args.uses.split(",") if name.strip()]
    if not names:
        raise InputError("--uses names nothing; give some of " + ", ".join(USES) + " or all")
    uses = None if names == ["all"] else names
    unknown = sorted(set(names) - set(USES)) if uses is not None else []
    if unknown:
        raise InputError(f"--uses: unknown {', '.join(unknown)}; give some of {', '.join(USES)} or all")
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be >= 1, got {args.workers}")
    workers = cores() if args.workers is None else args.workers
    todo = pending(uses)
    total = len(kernel_calls(uses))
    if not todo:
        print(f"all {total} kernels are in numba's cache already")
        return 0
    print(f"compiling {len(todo)} of {total} kernels in up to {workers} processes, {_about(todo, workers)}...",
          flush=True)
    result = warm_up(uses, workers=workers,
                     progress=lambda call, seconds, error: print(
                         f"  {call.name}: {'failed: ' + error if error else f'{seconds:.1f} s'}", flush=True))
    print(f"compiled {_done(result)}; {len(result.cached)} were cached")
    return 1 if result.failed else 0
