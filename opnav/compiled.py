"""The one numba configuration of opnav's compiled kernels (:func:`kernel`), and their warm-up (:func:`warm_up`).

Kernels are cached on disk (``cache=True``: the first run compiles, later runs
load) and use numpy's floating-point error model: a division by zero gives
inf/nan instead of raising, so no zero test guards every division in the inner
loops (the light-time kernel on 260 states: 17 us against 24 us with Python's
model, one run). Callers check their outputs for non-finite values.

Warm-up
-------
numba compiles a kernel on its first call with new argument types, and ``cache=True`` saves the
machine code in ``__pycache__`` next to the module (or ``NUMBA_CACHE_DIR``), keyed by the source
file's time stamp, the argument types and the CPU. On a fresh checkout the first run of the demo
spent 30 to 90 s (by how busy the machine was) compiling inside its first frame and first filter
record, where the progress bars turned it into ETAs of 18 min to 1.5 h. :data:`KERNEL_CALLS` lists
the kernels opnav's runs call from Python with the argument types they call them with, and what
needs each (:data:`USES`); :func:`pending` says, from numba's cache index and without compiling,
which of them have no machine code for this CPU yet, and :func:`warm_up` compiles those (in several
processes when asked: each writes numba's cache, and the kernels of one cache index file stay in one
process) before the run starts, so the run only loads them. A kernel called with types not listed,
or a kernel not listed, still compiles on its first call: ``tests/test_compiled_warmup.py`` checks
that the demo after a warm-up compiles nothing.
"""

from __future__ import annotations

import importlib
import logging
import math
import os
import pickle
import time
from dataclasses import dataclass
from typing import Callable, Iterable

from numba import njit
from numba.core import caching as _caching

_log = logging.getLogger(__name__)


def _tolerate_damaged_cache() -> None:
    """Read a damaged numba cache file as a missing one: the kernel compiles again and its cache is
    written anew. numba itself raises on a truncated or corrupted index or data file (``pickle data was
    truncated``), and a cache cut short by a full disk or a killed process would then stop every opnav
    command before it starts."""
    cache_file = _caching.IndexDataCacheFile
    if getattr(cache_file, "_opnav_tolerant", False):
        return
    load_index, load_data = cache_file._load_index, cache_file._load_data
    damage = (EOFError, ValueError, TypeError, AttributeError, ImportError, IndexError, KeyError,
              pickle.UnpicklingError)

    def _load_index(self):
        try:
            return load_index(self)
        except damage as exc:
            _log.warning("compiled-kernel cache %s is damaged (%s): compiling again", self._index_path, exc)
            return {}

    def _load_data(self, name):
        try:
            return load_data(self, name)
        except damage as exc:
            _log.warning("compiled-kernel cache %s is damaged (%s): compiling again", self._data_path(name), exc)
            raise OSError(f"damaged cache file {name}") from None  # numba reads an OSError here as a missing file

    cache_file._load_index, cache_file._load_data = _load_index, _load_data
    cache_file._opnav_tolerant = True


_tolerate_damaged_cache()


def kernel(function=None, *, parallel: bool = False, inline: bool = False):
    """``numba.njit`` with opnav's options; use as ``@kernel`` or ``@kernel(parallel=True)``."""
    decorate = njit(cache=True, error_model="numpy", parallel=parallel, inline="always" if inline else "never")
    return decorate if function is None else decorate(function)


def use_one_thread() -> None:
    """Run this process's parallel kernels on one thread: for a worker process that shares the
    cores with others (a kernel's thread pool waiting for busy cores made the lockstep UKF 10 to
    100 times slower with two workers on two cores)."""
    import numba

    numba.set_num_threads(1)


# ----------------------------------------------------------------------------- warm-up
#: What needs a kernel: ``images`` (frames rendered and measured: S1 and S3 image mode, the demo);
#: ``ekf`` and ``ukf``, the compiled single-run steps of :mod:`opnav.filters.compiled` (S1's RA/Dec
#: records, the demo); ``filters``, the general path: one state or a few propagated and measured
#: (S2, S3, the lockstep Monte Carlo, the square-root UKF, a record the single-run steps do not
#: take); ``sigma-points``, the unscented filters' points on the general path (Fortran-ordered;
#: S3, S4, the square-root UKF); ``particles``, the particle filters' clouds (the parallel kernels).
USES = ("images", "ekf", "ukf", "filters", "sigma-points", "particles")


@dataclass(frozen=True)
class KernelCall:
    """One compiled specialisation a run needs: kernel ``function`` of ``module`` called with the
    numba argument types ``signature`` (``f8[:, ::1]``: a C-ordered 2-D float64 array, ``f8[::1, :]``
    Fortran-ordered, ``f8[:, :]`` any layout; ``i8``, ``f8``, ``b1`` scalars), what needs it (``uses``)
    and the CPU seconds it took to compile (numba 0.68, 2-core machine; a kernel compiled after others
    that share its parts takes less)."""

    module: str
    function: str
    signature: str
    uses: tuple[str, ...]
    seconds: float

    @property
    def name(self) -> str:
        return f"{self.module}.{self.function}"

    def dispatcher(self):
        """The kernel (imports its module)."""
        return getattr(importlib.import_module(self.module), self.function)

    def argument_types(self) -> tuple:
        """The arguments' numba types, as numba types the arguments of a call from Python (the key of
        the call's entry in numba's cache)."""
        from numba.core import types

        parsed = eval(self.signature, {"__builtins__": {}}, dict(vars(types)))  # noqa: S307 - the table below
        return parsed if isinstance(parsed, tuple) else (parsed,)


_F = ("filters",)
_I = ("images",)
#: The serial propagation kernel's arguments after the states (K, 6): the STMs, the tableau, the
#: ephemeris tables and the force model (:meth:`opnav.dynamics.fast.FastPropagator.step`).
_INTEGRATE_REST = ("f8[:, :, ::1], b1, f8[:, ::1], f8[::1], f8[::1], f8[:, :, :, ::1], i8[::1], f8[::1], i8[::1], f8, "
                   "f8[::1], i8[::1], f8, i8, i8[::1], f8[::1], b1, f8[::1], f8[:, ::1], f8[:, ::1], f8[:, ::1], "
                   "f8[:, ::1], f8[::1]")
_TIMESCALE_REST = "f8[:, :, :, ::1], i8[::1], f8[::1], i8[::1], f8, f8[::1], i8[::1]"
_DIRECTIONS_REST = ("f8, f8[:, ::1], b1, f8[:, :, :, ::1], i8[::1], f8[::1], i8[::1], b1, b1, b1, f8, i8, f8[:, ::1], "
                    "f8[:, ::1], f8[:, :, ::1], f8[:, :, ::1], f8[:, :, ::1], f8[:, ::1]")

#: The compiled single-run steps' arguments: ephemeris tables (:class:`~opnav.ephemeris.tables.ArcTables`),
#: the force model's arrays and a record's value and covariance (read-only arrays).
_TABLES = "Tuple((f8[:, :, :, ::1], i8[::1], f8[::1], i8[::1]))"
_FORCE = ("Tuple((f8[:, ::1], f8[::1], f8[::1], f8, f8[::1], i8[::1], f8, i8, i8[::1], f8[::1], b1, f8[::1], "
          "f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[::1]))")
_RECORD = "Array(f8, 1, 'C', readonly=True), Array(f8, 2, 'C', readonly=True)"
_STEP_START = f"f8, f8, f8[::1], f8[:, ::1], f8[:, ::1], {_TABLES}, {_FORCE}, f8"
_STEP_END = f"{_RECORD}, b1, {_TABLES}, {_TABLES}, b1, b1, b1, f8, f8, f8"

#: Lost-in-space verification (opnav.image.starid_compiled): the candidate's arguments, the index's star zones,
#: and its star directions at a frame's epoch (the epoch cache, checked as read) or at the catalog's (read-only).
_STARID_VERIFY = "f8[:, ::1], i8[::1], i8[::1], i8, f8, b1, f8, f8[:, ::1], f8[:, ::1], i8[::1], i8[::1], f8[:, ::1]"
_STARID_ZONES = "Tuple((Array(f8, 1, 'C', readonly=True), Array(i8, 1, 'C', readonly=True), f8[:, ::1], b1[::1], i8, f8))"
_STARID_DIRECTIONS_REST = "i8[::1], i8, f8[::1], f8[:, ::1], f8[::1], f8[::1], f8, f8[::1], b1, f8, f8, f8"
_STARID_EPOCH = f"Tuple((f8[:, ::1], b1, {_STARID_DIRECTIONS_REST}))"
_STARID_PLAIN = f"Tuple((Array(f8, 2, 'C', readonly=True), b1, {_STARID_DIRECTIONS_REST}))"

#: The kernels opnav's runs call from Python, with the types they are called with (recorded from
#: ``opnav demo``, ``opnav run`` of S1 with each filter, S2, S3 in both modes and S4, and
#: ``opnav montecarlo``, with numba's compile events; kernels only called from other kernels are
#: compiled inside them).
KERNEL_CALLS: tuple[KernelCall, ...] = (
    # render
    KernelCall("opnav.bodies", "_lit_rays_kernel",
               "f8[::1], f8[::1], f8[::1], f8, i8, f8, f8, f8[:, ::1], f8[::1], f8[::1], f8[::1], b1, f8", _I, 1.5),
    KernelCall("opnav.bodies", "_pixel_light_kernel",
               "f8[:, :, ::1], f8[::1], f8[::1], f8[::1], f8[::1], b1, f8, i8, i8, i8, i8, i8, b1, f8, f8, b1, b1[:, ::1]", _I, 1.3),
    KernelCall("opnav.render.detector", "_bloom_kernel", "f8[:, ::1], f8", _I, 0.7),
    KernelCall("opnav.render.frame", "_merge_kernel", "i8[:, ::1]", _I, 0.6),
    # image stage
    KernelCall("opnav.image.centroid", "_gauss_kernel",
               "f8[:, :, ::1], b1[:, :, ::1], i8[:, ::1], i8[:, ::1], f8[:, ::1], f8[::1], f8, b1, f8, b1, f8, b1, "
               "i8, f8", _I, 12.0),
    KernelCall("opnav.image.centroid", "_cut_stamps", "f8[:, ::1], b1[:, ::1], b1, i8[:, ::1], i8[:, ::1], f8", _I, 0.6),
    KernelCall("opnav.image.centroid", "_cut_stamps",  # a view into a frame (a tracking window)
               "f8[:, :], b1[:, ::1], b1, i8[:, ::1], i8[:, ::1], f8", _I, 0.2),
    KernelCall("opnav.image.detect", "_clipped_tiles", "f8[:, ::1], f8, f8", _I, 1.7),
    KernelCall("opnav.image.detect", "_count_groups", "b1[:, ::1], i8[::1], i8[::1]", _I, 0.4),
    KernelCall("opnav.image.detect", "_deblend_kernel", "f4[:, ::1], i8[:, ::1], f8, f8", _I, 0.4),
    KernelCall("opnav.image.detect", "_interpolate", "f8[:, ::1], i8[::1], f8[::1], i8[::1], f8[::1]", _I, 0.2),
    KernelCall("opnav.image.detect", "_local_maxima", "f4[:, ::1], i8[::1], i8[::1], i8", _I, 0.4),
    KernelCall("opnav.image.detect", "_residual",
               "f8[:, ::1], b1[:, ::1], b1, f8[:, ::1], i8[::1], f8[::1], i8[::1], f8[::1]", _I, 0.5),
    KernelCall("opnav.image.detect", "_residual",  # a tracking window (a view into the frame)
               "f8[:, :], b1[:, ::1], b1, f8[:, ::1], i8[::1], f8[::1], i8[::1], f8[::1]", _I, 0.3),
    KernelCall("opnav.image.detect", "_sharp_kernel",
               "f4[:, ::1], f8[:, ::1], i8[::1], f8[::1], i8[::1], f8[::1], f8, b1[:, ::1], f8, f8, f8, f8", _I, 0.8),
    KernelCall("opnav.image.detect", "_subpixel_kernel", "f4[:, ::1], i8[::1], i8[::1]", _I, 0.3),
    KernelCall("opnav.image.detect", "_five_tap_kernel", "f4[:, ::1], f4, f4, f4", _I, 0.3),
    KernelCall("opnav.image.targets", "_photocentre_moment", "f8[:, ::1], f8[::1], f8[::1], i8, b1", _I, 0.3),
    KernelCall("opnav.image.targets", "_ray_profiles", "f8[:, ::1], f8[::1], f8[:, ::1], f8[::1]", _I, 0.3),
    # lost-in-space star identification (opnav solve; the index's arrays are read-only): a frame with a date
    # (its index stars at that epoch) and one without
    KernelCall("opnav.image.starid_compiled", "lookup_kernel",
               "f8[:, ::1], f8[::1], Array(i8, 1, 'C', readonly=True), Array(i8, 1, 'C', readonly=True), "
               "Array(f4, 2, 'C', readonly=True), Array(f4, 1, 'C', readonly=True), f8, f8, i8, b1, f8", _I, 1.5),
    KernelCall("opnav.image.starid_compiled", "verify_kernel", f"{_STARID_VERIFY}, {_STARID_ZONES}, {_STARID_EPOCH}",
               _I, 9.0),
    KernelCall("opnav.image.starid_compiled", "verify_kernel", f"{_STARID_VERIFY}, {_STARID_ZONES}, {_STARID_PLAIN}",
               _I, 9.0),
    KernelCall("opnav.image.starid_compiled", "read_rows_kernel", f"i8[::1], b1, {_STARID_EPOCH}", _I, 0.5),
    KernelCall("opnav.image.starid_compiled", "rotation_quaternion", "f8[:, ::1]", _I, 0.1),
    KernelCall("opnav.image.starid_compiled", "rigid_kernel", "f8[:, ::1], i8[:, ::1], f8[:, :, ::1], f8[::1], f8",
               _I, 0.5),
    KernelCall("opnav.image.attitude", "_information", "f8[:, ::1], f8[::1]", _I, 0.2),
    # navigation: the compiled single-run EKF and UKF steps (S1's RA/Dec records)
    KernelCall("opnav.filters.compiled", "ekf_radec_step", f"{_STEP_START}, {_STEP_END}", ("ekf",), 29.0),
    KernelCall("opnav.filters.compiled", "ukf_radec_step", f"{_STEP_START}, f8, f8[::1], f8[::1], f8, {_STEP_END}",
               ("ukf",), 24.0),
    # navigation, the general path: propagation (C-ordered states; the unscented filters' points are
    # Fortran-ordered), apparent directions, and the square-root UKF's rank-one update
    KernelCall("opnav.dynamics.fast", "_integrate_serial", "f8, f8, i8, f8[:, ::1], " + _INTEGRATE_REST, _F, 12.0),
    KernelCall("opnav.dynamics.fast", "_timescale", "f8, f8[:, ::1], " + _TIMESCALE_REST, ("filters", "particles"),
               0.5),
    KernelCall("opnav.light_compiled", "directions_range", "i8, i8, " + _DIRECTIONS_REST, _F, 4.0),
    KernelCall("opnav.dynamics.fast", "_integrate_serial", "f8, f8, i8, f8[::1, :], " + _INTEGRATE_REST,
               ("sigma-points",), 12.0),
    KernelCall("opnav.dynamics.fast", "_timescale", "f8, f8[::1, :], " + _TIMESCALE_REST, ("sigma-points",), 0.5),
    KernelCall("opnav.filters.sr_ukf", "_cholupdate", "f8[::1, :], f8[::1], f8", ("sigma-points",), 0.1),
    # navigation: the particle filters' clouds
    KernelCall("opnav.dynamics.fast", "_integrate_parallel", "f8, f8, i8, f8[:, ::1], " + _INTEGRATE_REST,
               ("particles",), 13.0),
    KernelCall("opnav.light_compiled", "directions", "i8, " + _DIRECTIONS_REST, ("particles",), 8.0),
    # image stage: the background's tile-grid median and the saturation plateau's medians
    KernelCall("opnav.image.detect", "_median_3x3", "f8[:, ::1]", _I, 0.3),
    KernelCall("opnav.image.detect", "_exact_median", "f8[::1]", _I, 5.7),
    KernelCall("opnav.image.detect", "_frame_scan", "f8[:, ::1], b1[:, ::1], f8, i8, b1[:, ::1], i8, f8[:, :, ::1]",
               _I, 1.2),
    KernelCall("opnav.image.detect", "_frame_scan",  # a tracking window (a view into the frame)
               "f8[:, :], b1[:, ::1], f8, i8, b1[:, ::1], i8, f8[:, :, ::1]", _I, 0.8),
    KernelCall("opnav.image.detect", "_uint16_rows", "f8[:, ::1]", _I, 0.3),
    KernelCall("opnav.image.detect", "_components_kernel",
               "f4[:, ::1], f8[:, ::1], i8[::1], f8[::1], i8[::1], f8[::1], f8, f8, f8, b1[:, ::1], b1, i8, b1[:, ::1], "
               "f4[:, ::1]", _I, 5.5),
    KernelCall("opnav.image.detect", "_component_weights", "f4[:, :], i4[:, :], i8", _I, 0.3),
    KernelCall("opnav.image.extract", "_embedded_peaks",
               "f8[:, :], i4[:, :], b1[::1], b1, f8, f8[:, ::1], f8[:, ::1]", _I, 2.3),
)

#: The particle filters (their clouds propagate and measure with the parallel kernels).
_PARTICLE_FILTERS = ("pf", "upf", "mcmc-upf")
#: The filters with a compiled single-run step (:mod:`opnav.filters.compiled`).
_COMPILED_STEPS = ("ekf", "ukf")


def uses_of(filters: Iterable[str] = (), *, images: bool = False, compiled_steps: bool = True) -> frozenset[str]:
    """The :data:`USES` of a run with these filters (names as ``opnav run --filters`` takes them),
    rendering and measuring frames when ``images``; ``compiled_steps``: its EKF and UKF take the
    compiled single-run steps (RA/Dec records with the white ephemeris error: S1), else the general path."""
    uses = {"images"} if images else set()
    for name in filters:
        if name in _COMPILED_STEPS and compiled_steps:
            uses.add(name)
        elif name in _PARTICLE_FILTERS:
            uses.add("particles")
        else:
            uses.add("filters")
            if "ukf" in name:
                uses.add("sigma-points")
    return frozenset(uses)


def kernel_calls(uses: Iterable[str] | None = None) -> tuple[KernelCall, ...]:
    """The entries of :data:`KERNEL_CALLS` needed by any of ``uses`` (None: all of them)."""
    if uses is None:
        return KERNEL_CALLS
    uses = set(uses)
    unknown = uses - set(USES)
    if unknown:
        raise ValueError(f"unknown kernel uses {sorted(unknown)}; known: {', '.join(USES)}")
    return tuple(call for call in KERNEL_CALLS if uses.intersection(call.uses))


def is_cached(call: KernelCall) -> bool:
    """Whether numba's on-disk cache holds machine code of ``call`` for this CPU and the kernel's
    current source (read from the kernel's cache index; nothing is compiled or loaded). False also
    when the cache cannot be read, or when the kernel is not a cached numba kernel (``NUMBA_DISABLE_JIT``:
    then there is nothing to compile either, see :func:`pending`)."""
    try:
        dispatcher = call.dispatcher()
        cache = dispatcher._cache
        index_file = cache._cache_file
        key = cache._index_key(call.argument_types(), dispatcher.targetctx.codegen())
        data = index_file._load_index().get(key)
        return data is not None and os.path.exists(index_file._data_path(data))
    except Exception:  # noqa: BLE001 - numba internals moved, or an unreadable cache: count it as not cached
        return False


def _compilable(call: KernelCall) -> bool:
    """Whether ``call``'s kernel is a numba dispatcher (not a plain function under ``NUMBA_DISABLE_JIT``).
    A module that fails to import counts as compilable, so that :func:`warm_up` reports it."""
    try:
        return hasattr(call.dispatcher(), "compile")
    except Exception:  # noqa: BLE001 - reported by warm_up
        return True


def pending(uses: Iterable[str] | None = None) -> tuple[KernelCall, ...]:
    """The kernel calls of ``uses`` (None: all) with no machine code in numba's cache for this CPU:
    what :func:`warm_up` would compile, found without compiling (it imports the kernels' modules)."""
    return tuple(call for call in kernel_calls(uses) if _compilable(call) and not is_cached(call))


def _groups(calls: Iterable[KernelCall]) -> list[list[KernelCall]]:
    """``calls`` grouped by the cache index file their kernel writes (one per Python function: the
    serial and parallel propagation kernels share one), costliest group first."""
    groups: dict[tuple, list[KernelCall]] = {}
    for call in calls:
        try:
            function = call.dispatcher().py_func
            key = (call.module, function.__qualname__, function.__code__.co_firstlineno)
        except Exception:  # noqa: BLE001 - a broken entry goes alone and is reported as failed
            key = (call.module, call.function)
        groups.setdefault(key, []).append(call)
    return sorted(groups.values(), key=lambda group: -sum(call.seconds for call in group))


#: Seconds a compiling process takes to start and import numba and the kernels' modules.
_PROCESS_START_S = 3.0


def _schedule(groups: list[list[KernelCall]], workers: int) -> tuple[float, int]:
    """(expected wall seconds, processes) of compiling ``groups`` in at most ``workers`` processes:
    the longest-first schedule over the number of processes that finishes first (one process, this
    one, when starting more does not pay)."""
    best = (0.0, 1)
    for count in range(1, max(1, min(int(workers), len(groups))) + 1):
        loads = [0.0] * count
        for group in groups:
            loads[loads.index(min(loads))] += sum(call.seconds for call in group)
        wall = max(loads) + (_PROCESS_START_S if count > 1 else 0.0)
        if count == 1 or wall < best[0]:
            best = (wall, count)
    return best


def estimate_s(calls: Iterable[KernelCall], workers: int = 1, *, busy: bool = False) -> float:
    """Expected wall time of :func:`warm_up` compiling ``calls`` with up to ``workers`` processes, from the
    compile times of :data:`KERNEL_CALLS` (an idle machine), or with ``busy`` times :func:`slowdown`."""
    wall, processes = _schedule(_groups(calls), workers)
    return wall * slowdown(processes) if busy else wall


def cores() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def slowdown(processes: int = 1) -> float:
    """How much slower than on an idle machine ``processes`` new CPU-bound processes run now: the other
    runnable processes (the 1-minute load average less this one) and them, over the cores; at least 1
    (measured on 2 cores with others' jobs running: the demo's 21 kernels, 32 s on an idle machine by
    :func:`estimate_s`, took 92 s at a load of 4 to 6, estimated 85 s, and 116 s at 6 to 7, estimated 135 s)."""
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # pragma: no cover - no load average
        return 1.0
    return max(1.0, (max(0.0, load - 1.0) + processes) / cores())


@dataclass(frozen=True)
class WarmUp:
    """What :func:`warm_up` did: the calls it compiled (with their compile seconds), those already
    in numba's cache (not loaded: a run loads them on first use), those that failed to compile
    (with the error; they compile, or fail, on first use instead), its wall time and processes."""

    compiled: tuple[tuple[KernelCall, float], ...]
    cached: tuple[KernelCall, ...]
    failed: tuple[tuple[KernelCall, str], ...]
    wall_s: float
    workers: int


def _compile_one(call: KernelCall) -> tuple[float, str | None]:
    """Compile ``call`` in this process (numba saves it in its cache): (seconds, error or None)."""
    begin = time.perf_counter()
    try:
        call.dispatcher().compile(call.argument_types())
    except Exception as exc:  # noqa: BLE001 - any failure is reported, never raised
        return time.perf_counter() - begin, f"{type(exc).__name__}: {str(exc).strip().splitlines()[0][:300]}"
    return time.perf_counter() - begin, None


def _compile_group(calls: list[KernelCall]) -> list[tuple[float, str | None]]:
    """A worker process's task: compile a group of calls (:func:`_groups`)."""
    return [_compile_one(call) for call in calls]


def warm_up(uses: Iterable[str] | None = None, *, workers: int = 1,
            progress: Callable[[KernelCall, float, str | None], None] | None = None) -> WarmUp:
    """Compile the kernel calls of ``uses`` (None: all of :data:`KERNEL_CALLS`) that numba's cache
    does not hold yet, so that a run loads them instead of compiling them on its first frame or record.

    Parameters
    ----------
    uses : iterable of str or None
        Which calls (:data:`USES`, e.g. :func:`uses_of`); None: all.
    workers : int
        Processes to compile in at most (1: this one, which then holds the compiled kernels). Kernels
        of one cache index file compile in one process; no more processes are started than pay for
        their start (:func:`estimate_s`).
    progress : callable or None
        Called as ``progress(call, seconds, error)`` after each call compiled (or failed). Quiet by default.

    Returns
    -------
    WarmUp
        What was compiled, found cached or failed, and the wall time.
    """
    if int(workers) != workers or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    begin = time.perf_counter()
    todo = pending(uses)
    cached = tuple(call for call in kernel_calls(uses) if call not in todo)
    groups = _groups(todo)
    workers = _schedule(groups, workers)[1]
    done: dict[KernelCall, tuple[float, str | None]] = {}

    def finished(call: KernelCall, outcome: tuple[float, str | None]) -> None:
        done[call] = outcome
        if progress is not None:
            progress(call, *outcome)

    if workers > 1:
        _compile_in_processes(groups, workers, finished)
    for group in groups:  # in this process: all of them, or those a broken pool left
        for call in group:
            if call not in done:
                finished(call, _compile_one(call))
    compiled = tuple((call, done[call][0]) for call in todo if done[call][1] is None)
    failed = tuple((call, done[call][1]) for call in todo if done[call][1] is not None)
    return WarmUp(compiled, cached, failed, time.perf_counter() - begin, workers)


def _compile_in_processes(groups: list[list[KernelCall]], workers: int, finished) -> None:
    """Compile ``groups`` in ``workers`` spawned processes, costliest first; a pool that cannot start or
    breaks leaves its groups to the caller."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    try:
        # spawned, not forked: this process may hold numba's thread pool, which a fork would copy broken
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(_compile_group, group): group for group in groups}
            for future in as_completed(futures):
                for call, outcome in zip(futures[future], future.result()):
                    finished(call, outcome)
    except Exception:  # noqa: BLE001 - no processes (or a pool that broke): the caller compiles what is left
        return


def rounded_s(seconds: float) -> int:
    """``seconds`` rounded up to a multiple of 5 (at least 5), for a message."""
    return max(5, 5 * math.ceil(seconds / 5.0))
