"""Fixtures of the renderer tests."""

from __future__ import annotations

import numpy as np
import pytest

from opnav.catalog import synthetic_catalog


@pytest.fixture(scope="session")
def star_catalog():
    return synthetic_catalog(60_000, rng=np.random.default_rng(20240611), vmag_range=(4.0, 9.0))
