"""opnav.allocator: the process keeps freed memory for the next frame."""

import resource
import sys

import numpy as np
import pytest

from opnav.allocator import keep_freed_memory


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
