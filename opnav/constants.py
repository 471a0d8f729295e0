"""Physical constants in opnav's internal units (km, km/s, s, rad).

Sources
-------
- GM values: JPL DE421 header constants (Folkner, Williams & Boggs 2008,
  IPN Progress Report 42-178), converted from au^3/day^2 with au = 149597870.7 km.
- Earth geopotential reference (GM, radius): JGM-3 (Tapley et al. 1996), as used by S3.
- Mars radii: IAU WGCCRE 2015 (Archinal et al. 2018).
- Phobos/Deimos tri-axial radii: half the diameters quoted in S1 (Thomas 1989).
- c and au: IAU 2012 Resolution B2 (exact).
- Solar radiation pressure at 1 au: 4.56e-6 N/m^2 (S3, Montenbruck & Gill 2000 Sec. 3.4).
- Obliquity of the J2000 ecliptic: 84381.448 arcsec (IAU 1976; the value JPL uses for
  its "J2000 ecliptic" frame).
"""

import numpy as np

C_KM_S = 299_792.458
AU_KM = 149_597_870.7
DAY_S = 86_400.0
JULIAN_YEAR_S = 365.25 * DAY_S
ARCSEC_RAD = np.pi / (180.0 * 3600.0)
DEG_RAD = np.pi / 180.0

#: Gravitational parameters, km^3/s^2 (DE421). Planet values are for the planet
#: system (planet + moons), which is what a distant probe feels.
GM_KM3_S2 = {
    "sun": 132_712_440_040.944,
    "mercury": 22_032.090,
    "venus": 324_858.592,
    "earth": 398_600.436,
    "moon": 4_902.800,
    "mars": 42_828.375,
    "jupiter": 126_712_764.8,
    "saturn": 37_940_585.2,
    "uranus": 5_794_548.6,
    "neptune": 6_836_535.0,
}

#: Equatorial radii, km.
RADIUS_KM = {
    "sun": 695_700.0,
    "earth": 6_378.1363,
    "moon": 1_737.4,
    "mars": 3_396.19,
}
MARS_POLAR_RADIUS_KM = 3_376.20

#: Tri-axial radii (a >= b >= c), km.
PHOBOS_RADII_KM = (13.4, 11.2, 9.2)
DEIMOS_RADII_KM = (7.5, 6.1, 5.2)

#: Earth geopotential reference of S3 (JGM-3).
EARTH_GM_JGM3_KM3_S2 = 398_600.4415
EARTH_RADIUS_JGM3_KM = 6_378.1363
#: Earth rotation rate, rad/s (IERS, mean).
EARTH_ROTATION_RAD_S = 7.292_115_146_706_979e-5

#: Solar radiation pressure at 1 au, N/m^2.
SOLAR_PRESSURE_1AU_N_M2 = 4.56e-6

OBLIQUITY_J2000_RAD = 84_381.448 * ARCSEC_RAD

#: Time scales a file, header or option may name (those :func:`opnav.epochs.parse_epoch` converts).
TIME_SCALES = ("utc", "tt", "tdb", "tai")
