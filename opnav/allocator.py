"""Process-wide memory allocator setting for frame processing: :func:`keep_freed_memory`.

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

_log = logging.getLogger(__name__)
# mallopt parameters of glibc's malloc.h
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_MAX = -4
#: Freed memory kept at the top of the heap before it is returned to the system, bytes.
KEEP_BYTES = 512 << 20
_applied = False


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
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # mallopt returns 1 on success; musl has no mallopt (AttributeError above)
    done = all(mallopt(param, value) == 1 for param, value in
               ((_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, KEEP_BYTES), (_M_TOP_PAD, 64 << 20)))
    if not done:
        _log.debug("mallopt refused a setting: the allocator keeps its defaults")
    _applied = done
    return done
