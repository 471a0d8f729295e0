"""Test-suite set-up shared by every folder.

The tests mirror the package (``tests/sim``, ``tests/filters``, ``tests/studies`` ...). A few test
modules reuse another module's models and helpers (``from test_ukf import ...``, ``from
test_measurements import numeric_jacobian``); the folders holding those modules are put on
``sys.path`` here so such an import works whichever folder the importing test lives in.
"""

import sys
from pathlib import Path

_TESTS = Path(__file__).resolve().parent
for _folder in (_TESTS, _TESTS / "filters", _TESTS / "image"):
    if str(_folder) not in sys.path:
        sys.path.insert(0, str(_folder))
