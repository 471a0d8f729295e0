"""The renderer: physically modelled synthetic frames with truth (opnav issue 3).

:func:`render_frame` returns a frozen :class:`RenderResult` (image, expected
electrons, truth, FITS header) in memory; :func:`write_frame`/:func:`read_frame`
store it as FITS + truth JSON. See the module docstrings of ``psf``,
``detector`` and ``frames_io`` here and of :mod:`opnav.photometry`, :mod:`opnav.bodies` and
:mod:`opnav.observer` (shared with the image stage) for the models.
"""

from ..bodies import BODIES, Body, body_model
from ..observer import Corrections, Observer
from ..photometry import JOHNSON_V, Band, electron_rate
from .detector import DetectorOptions, read_out
from .frame import RenderOptions, RenderResult, WindowedResult, render_frame, render_windows
from .frames_io import StoredFrame, StoredWindows, Window, read_frame, read_windows, write_frame, write_windows
from .psf import PSF
from .truth import FrameTruth, StarTruth, TargetTruth

__all__ = [
    "BODIES", "Band", "Body", "Corrections", "DetectorOptions", "FrameTruth", "JOHNSON_V", "Observer", "PSF",
    "RenderOptions", "RenderResult", "StarTruth", "StoredFrame", "StoredWindows", "TargetTruth", "Window",
    "WindowedResult", "body_model", "electron_rate", "read_frame", "read_out", "read_windows", "render_frame",
    "render_windows", "write_frame", "write_windows",
]
