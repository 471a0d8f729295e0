"""The one numba configuration of opnav's compiled kernels (:func:`kernel`).

Kernels are cached on disk (``cache=True``: the first run compiles, later runs
load) and use numpy's floating-point error model: a division by zero gives
inf/nan instead of raising, so no zero test guards every division in the inner
loops (the light-time kernel on 260 states: 17 us against 24 us with Python's
model, one run). Callers check their outputs for non-finite values.
"""

from __future__ import annotations

from numba import njit


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
