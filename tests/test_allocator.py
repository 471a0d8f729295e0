"""opnav.allocator: the process keeps freed memory for the next frame."""

import resource
import sys

import numpy as np
import pytest

from opnav.allocator import keep_freed_memory, returning_freed_memory


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_frames_are_reused_without_page_faults():
    assert keep_freed_memory() is True
    assert keep_freed_memory() is True  # once is enough; again changes nothing
    # 40 MB (a 5 MP float frame): above the largest threshold glibc's defaults ever serve from the
    # heap (32 MB), so by default each one is mapped afresh and faulted in again
    for _ in range(3):  # the heap grows to the working set once
        np.full((5_000_000,), 1.0).sum()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(10):
        np.full((5_000_000,), 1.0).sum()
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    assert faults < 1_000  # by default 5,000-10,000 (huge pages take some of them)


def _resident_bytes() -> int:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * resource.getpagesize()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_one_off_work_returns_its_freed_memory_and_the_setting_comes_back():
    assert keep_freed_memory() is True
    with returning_freed_memory():
        block = np.ones(40_000_000)  # 320 MB, touched
        with_block = _resident_bytes()
        del block
        after = _resident_bytes()
    assert with_block - after > 300e6  # kept on the heap it would stay resident
    # the frames' setting is back: 40 MB blocks are reused without faulting
    for _ in range(3):
        np.full((5_000_000,), 1.0).sum()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(10):
        np.full((5_000_000,), 1.0).sum()
    assert resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before < 1_000
