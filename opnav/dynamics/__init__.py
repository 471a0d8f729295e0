"""Dynamics: force terms and models (S1-S4), DOP853 propagation with the STM
(:func:`propagate`; :func:`states_at`: one state to dates on both sides of its epoch, any origin).

States are ``[r (km), v (km/s)]`` in ICRF relative to a model's central body;
epochs are TDB seconds past J2000 (``docs/conventions.md``).
"""

from .forces import (
    CentralGravity,
    ForceModel,
    ForceTerm,
    SolarRadiationPressure,
    ThirdBody,
    shadow_factor,
)
from ..ephemeris.cache import EphemerisCache, default_cached_ephemeris
from .geopotential import Geopotential, earth_rotation_angle
from .models import (
    MODELS,
    S3_GEOPOTENTIAL,
    approach_model,
    capture_model_1,
    capture_model_2,
    cruise_model,
    geo_model,
    get_model,
    two_body_model,
)
from .propagate import Trajectory, change_center, propagate, states_at

__all__ = [
    "CentralGravity", "EphemerisCache", "ForceModel", "ForceTerm", "Geopotential", "MODELS", "S3_GEOPOTENTIAL",
    "SolarRadiationPressure", "ThirdBody", "Trajectory", "approach_model", "capture_model_1", "capture_model_2",
    "change_center", "cruise_model", "default_cached_ephemeris", "earth_rotation_angle", "geo_model", "get_model",
    "propagate", "shadow_factor", "states_at", "two_body_model",
]
