"""The force models of the four studies (S1-S4) and a plain two-body model.

Every factory returns a :class:`~opnav.dynamics.forces.ForceModel`. Ephemeris
arguments default to the process-wide DE421 reader; a plain
:class:`~opnav.ephemeris.Ephemeris` passed in is wrapped in an
:class:`~opnav.ephemeris.cache.EphemerisCache` so that the integrator does not
call jplephem on every right-hand side.

GM values are DE421's (:data:`opnav.constants.GM_KM3_S2`; planets are their
systems), except the Earth's central term and geopotential in S3, which use
the JGM-3 reference of the S3 coefficient table.
"""

from __future__ import annotations

from typing import Callable

from ..constants import EARTH_GM_JGM3_KM3_S2, EARTH_RADIUS_JGM3_KM, GM_KM3_S2
from ..ephemeris import Ephemeris
from ..epochs import to_time
from ..errors import InputError
from .forces import (
    CentralGravity,
    ForceModel,
    ForceTerm,
    PositionSource,
    SolarRadiationPressure,
    ThirdBody,
)
from ..ephemeris.cache import EphemerisCache, default_cached_ephemeris
from .geopotential import Geopotential

#: S3 geopotential (docs/studies.md#s3-geo-satellite, unnormalised, JGM-3), with J_n = -C_n0.
S3_GEOPOTENTIAL = {
    "j2": 1082.627e-6,
    "j3": -2.532435e-6,
    "j4": -1.619331e-6,
    "c22": 1.574536e-6,
    "s22": -0.903868e-6,
    "c31": 2.192799e-6,
    "s31": 0.2680119e-6,
    "c33": 0.100559e-6,
    "s33": 0.197201e-6,
}

#: S1 perturbing bodies (Mercury..Saturn, with the Earth and the Moon separately).
CRUISE_BODIES = ("mercury", "venus", "earth", "moon", "mars", "jupiter", "saturn")


def _source(ephemeris: PositionSource | None) -> PositionSource:
    if ephemeris is None:
        return default_cached_ephemeris()
    if isinstance(ephemeris, Ephemeris):
        return EphemerisCache(ephemeris)
    return ephemeris


def _third_bodies(center: str, bodies: tuple[str, ...], source: PositionSource) -> list[ForceTerm]:
    return [ThirdBody(body, center, GM_KM3_S2[body], source) for body in bodies]


def _srp(area_to_mass_m2_kg: float, cr: float, center: str, source: PositionSource,
         shadow_bodies: tuple[str, ...]) -> list[ForceTerm]:
    # A zero area-to-mass ratio means "no SRP"; leaving the term out keeps the right-hand side cheap.
    if area_to_mass_m2_kg == 0.0:
        return []
    return [SolarRadiationPressure(area_to_mass_m2_kg, cr, center, source, shadow_bodies)]


def two_body_model(center: str, gm_km3_s2: float | None = None) -> ForceModel:
    """Point-mass gravity of ``center`` only (GM default from DE421)."""
    center = Ephemeris.check_body(center)
    if gm_km3_s2 is None:
        if center not in GM_KM3_S2:
            raise InputError(f"no GM known for {center!r}; pass gm_km3_s2")
        gm_km3_s2 = GM_KM3_S2[center]
    return ForceModel(center, (CentralGravity(gm_km3_s2),), f"two-body {center}")


def cruise_model(*, srp_area_to_mass_m2_kg: float = 0.0, cr: float = 1.3,
                 ephemeris: PositionSource | None = None, shadow_bodies: tuple[str, ...] = ()) -> ForceModel:
    """S1 Mars cruise: Sun central; Mercury..Saturn, Earth, Moon, Mars third bodies; SRP.

    Eclipses are off by default (``shadow_bodies=()``): the cruise never
    crosses a planet's shadow cone.
    """
    source = _source(ephemeris)
    terms = [CentralGravity(GM_KM3_S2["sun"]), *_third_bodies("sun", CRUISE_BODIES, source)]
    terms += _srp(srp_area_to_mass_m2_kg, cr, "sun", source, shadow_bodies)
    return ForceModel("sun", tuple(terms), "cruise")


def capture_model_1(*, ephemeris: PositionSource | None = None) -> ForceModel:
    """S2 model 1 (outside Mars' sphere of influence): Sun central + Mars + Earth."""
    source = _source(ephemeris)
    terms = [CentralGravity(GM_KM3_S2["sun"]), *_third_bodies("sun", ("mars", "earth"), source)]
    return ForceModel("sun", tuple(terms), "capture1")


def capture_model_2(*, ephemeris: PositionSource | None = None) -> ForceModel:
    """S2 model 2 (inside Mars' sphere of influence): Mars central + Sun + Earth."""
    source = _source(ephemeris)
    terms = [CentralGravity(GM_KM3_S2["mars"]), *_third_bodies("mars", ("sun", "earth"), source)]
    return ForceModel("mars", tuple(terms), "capture2")


def tdb_minus_ut1_s(t_tdb_s: float) -> float:
    """TDB - UT1 (s) at an epoch with UT1 ~ UTC (leap seconds from astropy/ERFA)."""
    time = to_time(t_tdb_s)
    return float((time.tdb.jd1 - time.utc.jd1) * 86_400.0 + (time.tdb.jd2 - time.utc.jd2) * 86_400.0)


def geo_model(*, area_to_mass_m2_kg: float = 0.02, cr: float = 1.5, ephemeris: PositionSource | None = None,
              epoch_tdb_s: float | None = None, shadow_bodies: tuple[str, ...] = ("earth",)) -> ForceModel:
    """S3 GEO: Earth two-body (JGM-3 GM) + J2..J4, C/S22, C/S31, C/S33 + Sun + Moon + SRP.

    ``epoch_tdb_s`` sets TDB - UT1 for the Earth rotation angle (UT1 ~ UTC at
    that epoch); default 64.184 s, right for 1999-2005 (S3 is 2001-01-01).
    """
    source = _source(ephemeris)
    offset = 64.184 if epoch_tdb_s is None else tdb_minus_ut1_s(epoch_tdb_s)
    geopotential = Geopotential(EARTH_GM_JGM3_KM3_S2, EARTH_RADIUS_JGM3_KM, **S3_GEOPOTENTIAL, tdb_minus_ut1_s=offset)
    terms = [CentralGravity(EARTH_GM_JGM3_KM3_S2), geopotential, *_third_bodies("earth", ("sun", "moon"), source)]
    terms += _srp(area_to_mass_m2_kg, cr, "earth", source, shadow_bodies)
    return ForceModel("earth", tuple(terms), "geo")


def approach_model(*, srp_area_to_mass_m2_kg: float = 0.01, cr: float = 1.3,
                   ephemeris: PositionSource | None = None, shadow_bodies: tuple[str, ...] = ()) -> ForceModel:
    """S4 Mars approach: Sun central + Earth + Mars third bodies + SRP (integrated in ICRF)."""
    source = _source(ephemeris)
    terms = [CentralGravity(GM_KM3_S2["sun"]), *_third_bodies("sun", ("earth", "mars"), source)]
    terms += _srp(srp_area_to_mass_m2_kg, cr, "sun", source, shadow_bodies)
    return ForceModel("sun", tuple(terms), "approach")


#: Model name -> factory (keyword arguments only).
MODELS: dict[str, Callable[..., ForceModel]] = {
    "cruise": cruise_model,
    "capture1": capture_model_1,
    "capture2": capture_model_2,
    "geo": geo_model,
    "approach": approach_model,
}


def get_model(name: str, **options) -> ForceModel:
    """Build the model called ``name`` (a key of :data:`MODELS`); raise ``InputError`` otherwise."""
    key = str(name).strip().lower()
    if key not in MODELS:
        raise InputError(f"unknown force model {name!r}; known: {', '.join(MODELS)}")
    return MODELS[key](**options)


__all__ = ["MODELS", "S3_GEOPOTENTIAL", "CRUISE_BODIES", "approach_model", "capture_model_1", "capture_model_2",
           "cruise_model", "geo_model", "get_model", "tdb_minus_ut1_s", "two_body_model"]
