"""opnav: image-in-the-loop optical navigation for spacecraft.

Conventions (units, frames, time, pixels, attitude) are stated once in
``docs/conventions.md``; every public function names the frame, origin and
units of the vectors it takes and returns.
"""

__version__ = "0.1.0"
