"""Observer state at mid-exposure and the physical corrections applied to what it sees.

Shared by the renderer (what a camera at the observer records) and the image stage (what it
predicts there); neither imports the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError


@dataclass(frozen=True)
class Corrections:
    """Which physical corrections the renderer applies (each can be switched off to study it)."""

    light_time: bool = True
    aberration: bool = True
    parallax: bool = True
    proper_motion: bool = True


@dataclass(frozen=True)
class Observer:
    """Observer state at mid-exposure.

    Parameters
    ----------
    t_tdb_s : float
        Mid-exposure epoch, TDB seconds past J2000.
    r_ssb_km : (3,) array
        Position relative to the SSB, ICRF, km.
    v_ssb_km_s : (3,) array
        Velocity relative to the SSB, ICRF, km/s.
    """

    t_tdb_s: float
    r_ssb_km: np.ndarray
    v_ssb_km_s: np.ndarray

    def __post_init__(self) -> None:
        r = np.asarray(self.r_ssb_km, dtype=float)
        v = np.asarray(self.v_ssb_km_s, dtype=float)
        if r.shape != (3,) or v.shape != (3,):
            raise InputError(f"observer r_ssb_km and v_ssb_km_s must have shape (3,), got {r.shape} and {v.shape}")
        if not (math.isfinite(self.t_tdb_s) and np.all(np.isfinite(r)) and np.all(np.isfinite(v))):
            raise InputError("observer state is not finite (NaN or inf in t_tdb_s, r_ssb_km or v_ssb_km_s)")
        object.__setattr__(self, "r_ssb_km", r)
        object.__setattr__(self, "v_ssb_km_s", v)
        object.__setattr__(self, "t_tdb_s", float(self.t_tdb_s))
