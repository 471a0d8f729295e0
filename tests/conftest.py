"""Test-suite set-up shared by every folder.

The tests mirror the package (``tests/sim``, ``tests/filters``, ``tests/studies`` ...). A few test
modules reuse another module's models and helpers (``from test_ukf import ...``, ``from
test_measurements import numeric_jacobian``); the folders holding those modules are put on
``sys.path`` here so such an import works whichever folder the importing test lives in.
"""

import os
import sys
from pathlib import Path

# OpenBLAS on one thread in each test process and the processes the tests start (set before numpy
# loads: no plugin imports it earlier). ``make test`` already runs one pytest-xdist worker per core;
# each worker's idle OpenBLAS threads spun on the core the other worker needed: the brown1 calibration
# test took 14.7 s CPU with them and 3.5 s without at load ~10, same result (``opnav montecarlo`` and
# ``opnav solve`` do the same for their workers). A test that sets the variable itself still can.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

_TESTS = Path(__file__).resolve().parent
for _folder in (_TESTS, _TESTS / "filters", _TESTS / "image"):
    if str(_folder) not in sys.path:
        sys.path.insert(0, str(_folder))


# ---- what renders or builds once per session (issue 35 item 5: tests in minutes)
import pytest  # noqa: E402


@pytest.fixture(scope="session")
def s1_demo_frames(tmp_path_factory):
    """Twelve S1 demo frames a minute apart from 16 July (the demo's Phobos-tracking 1-degree camera;
    both moons clear of Mars' glare), seed 3, rendered once for the tracking tests
    (``tests/image/test_tracking.py``, the first six in ``test_tracking_fast.py``): the frames, the
    catalog, the ephemeris and the image stage's options."""
    from dataclasses import replace

    import numpy as np

    from opnav.catalog import load_catalog
    from opnav.ephemeris import default_ephemeris
    from opnav.image.pipeline import PipelineOptions
    from opnav.sim.loop import render_frames
    from opnav.sim.scene import observer_states
    from opnav.studies.s1 import MOONS, load_demo

    scenario, _, digest = load_demo()
    ephemeris = default_ephemeris()
    catalog = load_catalog(scenario.catalog_path)
    t = scenario.t_tdb_s[0] + 86_400.0 + 60.0 * np.arange(12)
    r, v = observer_states(replace(scenario, t_tdb_s=t), t, ephemeris)
    frames = render_frames(replace(scenario, t_tdb_s=t), t, r, v, tmp_path_factory.mktemp("s1_demo_frames"), seed=3,
                           digest=digest, catalog=catalog, ephemeris=ephemeris, progress=False)
    options = PipelineOptions(targets=MOONS, vmag_limit=scenario.options.vmag_limit)
    return frames, catalog, ephemeris, options
