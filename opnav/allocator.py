"""Process-wide memory allocator setting for frame processing: :func:`keep_freed_memory`, and
:func:`returning_freed_memory` for one-off work of large peak inside such a process.

Each frame the image stage allocates and frees a few dozen full-frame arrays (8 MB each at
1 MP in float64). glibc's ``malloc`` serves blocks above its mmap threshold (128 kB to 32 MB)
with fresh ``mmap`` pages and returns them to the system on ``free``; the next frame then
faults every page in again. On the 2-core machines opnav is benchmarked on a page fault costs
~4.5 us, 6,000-8,000 of them a 1 MP frame: 25-35 ms of a 60-90 ms extraction
(``benchmarks/starid_real.py``). Kept, the freed pages serve the next frame with no fault.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys
from collections.abc import Iterator
from contextlib import contextmanager

_log = logging.getLogger(__name__)
# mallopt parameters of glibc's malloc.h
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_MAX = -4
#: Freed memory kept at the top of the heap before it is returned to the system, bytes.
KEEP_BYTES = 512 << 20
_KEEP = ((_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, KEEP_BYTES), (_M_TOP_PAD, 64 << 20))
# glibc's documented defaults (mallopt(3)); the mmap threshold itself stays at its 128 kB start
# once any of these is set
_RETURN = ((_M_MMAP_MAX, 65536), (_M_TRIM_THRESHOLD, 128 << 10), (_M_TOP_PAD, 128 << 10))
_applied = False
_mallopt = None


def keep_freed_memory() -> bool:
    """Make this process's ``malloc`` keep freed memory for reuse instead of unmapping it.

    Every block comes from the heap (no ``mmap`` for large blocks) and up to ``KEEP_BYTES`` of
    free memory at its top stays mapped. The process's resident size then stays at its peak
    (plus at most ``KEEP_BYTES``) instead of shrinking between frames. Called by the ``opnav``
    command, by the image-loop workers and by the image benchmarks; a program that calls the
    image stage in a loop can call it once at start.

    Returns
    -------
    bool
        Whether the setting was applied: False (and nothing changed) where the C library is not
        glibc (macOS, Windows, musl).
    """
    global _applied
    if _applied:
        return True
    mallopt = _libc_mallopt()
    if mallopt is None:
        return False
    # mallopt returns 1 on success
    done = all(mallopt(param, value) == 1 for param, value in _KEEP)
    if not done:
        _log.debug("mallopt refused a setting: the allocator keeps its defaults")
    _applied = done
    return done


@contextmanager
def returning_freed_memory() -> Iterator[None]:
    """Within the block, large blocks are mapped on their own and go back to the system when freed.

    For one-off work of large peak in a process that keeps freed memory (:func:`keep_freed_memory`):
    a pattern-index build allocates and frees arrays of hundreds of MB whose holes, all on the
    heap, cannot be returned (the 1-degree index peaks at 2.2 GB resident that way, 1.85 GB with
    glibc's defaults). The setting is back on after the block, also on an exception; where it
    is not on, the block changes nothing.
    """
    if not _applied:
        yield
        return
    mallopt = _libc_mallopt()
    for param, value in _RETURN:
        mallopt(param, value)
    try:
        yield
    finally:
        for param, value in _KEEP:
            mallopt(param, value)


def _libc_mallopt():
    """glibc's ``mallopt`` through ctypes, or None where there is none (macOS, Windows, musl)."""
    global _mallopt
    if _mallopt is None and sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            _mallopt = libc.mallopt
        except (OSError, AttributeError):
            return None
        _mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
        _mallopt.restype = ctypes.c_int
    return _mallopt
