"""Force terms: partials vs central differences, geopotential vs an independent potential, SRP, shadow."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.time import Time

from opnav.constants import AU_KM, EARTH_GM_JGM3_KM3_S2, EARTH_RADIUS_JGM3_KM, GM_KM3_S2, RADIUS_KM
from opnav.dynamics import (
    CentralGravity,
    EphemerisCache,
    ForceModel,
    Geopotential,
    S3_GEOPOTENTIAL,
    SolarRadiationPressure,
    ThirdBody,
    default_cached_ephemeris,
    earth_rotation_angle,
    shadow_factor,
)
from opnav.epochs import J2000_JD, parse_epoch
from opnav.ephemeris import default_ephemeris
from opnav.errors import EphemerisError, InputError

T_S1 = parse_epoch("2013-12-12T12:00:00", "tt")
T_S3 = parse_epoch("2001-01-01T00:00:00", "utc")


def _states_around(center_km: np.ndarray, radius_km: float, rng: np.random.Generator, k: int = 3) -> np.ndarray:
    directions = rng.normal(size=(k, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return center_km + radius_km * directions


def _central_jacobian(f, r: np.ndarray, h: float) -> np.ndarray:
    """d f / d r by central differences, (K, 3, 3); f maps (K, 3) -> (K, 3)."""
    jac = np.empty((len(r), 3, 3))
    for j in range(3):
        step = np.zeros(3)
        step[j] = h
        jac[:, :, j] = (f(r + step) - f(r - step)) / (2.0 * h)
    return jac


def _term_cases():
    rng = np.random.default_rng(7)
    ephem = default_cached_ephemeris()
    r_moon = ephem.position("moon", T_S3, center="earth")
    r_jup = ephem.position("jupiter", T_S1, center="sun")
    r_sun = ephem.position("sun", T_S3, center="earth")
    u_sun = r_sun / np.linalg.norm(r_sun)
    geo = Geopotential(EARTH_GM_JGM3_KM3_S2, EARTH_RADIUS_JGM3_KM, **S3_GEOPOTENTIAL)
    return [
        ("central", CentralGravity(GM_KM3_S2["sun"]), T_S1, _states_around(np.zeros(3), 1.5e8, rng), 1.5e8),
        # Probe 20 000 km from the Moon, so the direct term's curvature matters.
        ("third-moon", ThirdBody("moon", "earth", GM_KM3_S2["moon"]), T_S3, _states_around(r_moon, 2.0e4, rng), 2.0e4),
        ("third-jupiter", ThirdBody("jupiter", "sun", GM_KM3_S2["jupiter"]), T_S1,
         _states_around(r_jup, 5.0e6, rng), 5.0e6),
        ("srp-helio", SolarRadiationPressure(0.02, 1.3, "sun", shadow_bodies=()), T_S1,
         _states_around(np.zeros(3), 1.5e8, rng), 1.5e8),
        # Sunlit GEO positions (the shadow factor is 1, so the partial is exact).
        ("srp-geo", SolarRadiationPressure(0.02, 1.5, "earth"), T_S3,
         _states_around(42164.0 * u_sun, 5000.0, rng), 4.2e4),
        ("geopotential", geo, T_S3, _states_around(np.zeros(3), 7000.0, rng), 7000.0),
        ("geopotential-geo", geo, T_S3, _states_around(np.zeros(3), 42164.0, rng), 42164.0),
    ]


@pytest.mark.parametrize("name, term, t, r, scale_km", _term_cases(), ids=[c[0] for c in _term_cases()])
def test_partials_match_central_differences(name, term, t, r, scale_km):
    v = np.tile([1.0, -2.0, 0.5], (len(r), 1))
    da_dr, da_dv = term.partials(t, r, v)
    # Step 1e-4 of the length scale: truncation ~1e-8, rounding ~1e-12 relative.
    h = 1e-4 * scale_km
    numeric = _central_jacobian(lambda rr: term.acceleration(t, rr, v), r, h)
    for k in range(len(r)):
        scale = np.abs(numeric[k]).max()
        np.testing.assert_allclose(da_dr[k], numeric[k], rtol=0, atol=1e-6 * scale)
    np.testing.assert_array_equal(da_dv, 0.0)
    # A conservative force has a symmetric gradient.
    if name.startswith(("central", "third", "geopotential")):
        np.testing.assert_allclose(da_dr, np.swapaxes(da_dr, 1, 2), rtol=0, atol=1e-12 * np.abs(da_dr).max())


# --- geopotential against an independently written potential ------------------------------------

# d^m P_n / du^m (unnormalised Legendre), and Re/Im of (x + i y)^m as real polynomials.
_LEGENDRE_DERIVATIVE = {
    (2, 0): lambda u: (3 * u**2 - 1) / 2,
    (2, 2): lambda u: 3 + 0 * u,
    (3, 0): lambda u: (5 * u**3 - 3 * u) / 2,
    (3, 1): lambda u: (15 * u**2 - 3) / 2,
    (3, 3): lambda u: 15 + 0 * u,
    (4, 0): lambda u: (35 * u**4 - 30 * u**2 + 3) / 8,
}
_COS_POLY = {0: lambda x, y: 1 + 0 * x, 1: lambda x, y: x, 2: lambda x, y: x**2 - y**2, 3: lambda x, y: x**3 - 3 * x * y**2}
_SIN_POLY = {0: lambda x, y: 0 * x, 1: lambda x, y: y, 2: lambda x, y: 2 * x * y, 3: lambda x, y: 3 * x**2 * y - y**3}


def _potential(r_bf, n, m, c, s, gm, radius):
    """GM/r (R/r)^n P_nm(sin phi)(C cos m lambda + S sin m lambda), analytic in x, y, z (complex-step safe).

    Uses cos^m(phi) cos(m lambda) = Re((x + i y)^m) / r^m.
    """
    x, y, z = r_bf
    r = np.sqrt(x * x + y * y + z * z)
    angular = c * _COS_POLY[m](x, y) + s * _SIN_POLY[m](x, y)
    return gm / r * (radius / r) ** n * _LEGENDRE_DERIVATIVE[(n, m)](z / r) * angular / r**m


def _complex_step_gradient(f, r, h=1e-30):
    grad = np.empty(3)
    for i in range(3):
        rc = r.astype(complex)
        rc[i] += 1j * h
        grad[i] = f(rc).imag / h
    return grad


_TERMS = [  # (keyword, value) -> (n, m, C, S)
    ({"j2": S3_GEOPOTENTIAL["j2"]}, (2, 0, -S3_GEOPOTENTIAL["j2"], 0.0)),
    ({"j3": S3_GEOPOTENTIAL["j3"]}, (3, 0, -S3_GEOPOTENTIAL["j3"], 0.0)),
    ({"j4": S3_GEOPOTENTIAL["j4"]}, (4, 0, -S3_GEOPOTENTIAL["j4"], 0.0)),
    ({"c22": S3_GEOPOTENTIAL["c22"], "s22": S3_GEOPOTENTIAL["s22"]}, (2, 2, S3_GEOPOTENTIAL["c22"], S3_GEOPOTENTIAL["s22"])),
    ({"c31": S3_GEOPOTENTIAL["c31"], "s31": S3_GEOPOTENTIAL["s31"]}, (3, 1, S3_GEOPOTENTIAL["c31"], S3_GEOPOTENTIAL["s31"])),
    ({"c33": S3_GEOPOTENTIAL["c33"], "s33": S3_GEOPOTENTIAL["s33"]}, (3, 3, S3_GEOPOTENTIAL["c33"], S3_GEOPOTENTIAL["s33"])),
]


@pytest.mark.parametrize("kwargs, nmcs", _TERMS, ids=["J2", "J3", "J4", "C22S22", "C31S31", "C33S33"])
def test_geopotential_term_matches_potential_gradient(kwargs, nmcs):
    n, m, c, s = nmcs
    gm, radius = EARTH_GM_JGM3_KM3_S2, EARTH_RADIUS_JGM3_KM
    term = Geopotential(gm, radius, **kwargs)
    rng = np.random.default_rng(11)
    r_icrf = _states_around(np.zeros(3), 1.0, rng, k=6) * rng.uniform(6800.0, 45000.0, size=(6, 1))
    a_icrf = term.acceleration(T_S3, r_icrf, np.zeros_like(r_icrf))
    R_bf_icrf = term.rotation(T_S3)
    for r, a in zip(r_icrf, a_icrf):
        # The complex step gives the gradient to rounding: no step-size trade-off.
        grad_bf = _complex_step_gradient(lambda rb: _potential(rb, n, m, c, s, gm, radius), R_bf_icrf @ r)
        assert np.linalg.norm(R_bf_icrf @ a - grad_bf) <= 1e-10 * np.linalg.norm(grad_bf)


def test_j2_equatorial_magnitude():
    # Closed form on the equator: |a_J2| = 1.5 J2 GM R^2 / r^4, pointing inward.
    term = Geopotential(EARTH_GM_JGM3_KM3_S2, EARTH_RADIUS_JGM3_KM, j2=S3_GEOPOTENTIAL["j2"])
    r = np.array([[42164.0, 0.0, 0.0]])
    a = term.acceleration(T_S3, r, np.zeros((1, 3)))[0]
    expected = 1.5 * S3_GEOPOTENTIAL["j2"] * EARTH_GM_JGM3_KM3_S2 * EARTH_RADIUS_JGM3_KM**2 / 42164.0**4
    np.testing.assert_allclose(a, [-expected, 0.0, 0.0], rtol=1e-12, atol=1e-14 * expected)


def test_earth_rotation_angle_matches_erfa():
    offset_s = 64.184
    for days in (0.0, 366.25, 5000.3, -1234.9):
        t_tdb_s = days * 86_400.0 + offset_s
        expected = Time(J2000_JD, days, format="jd", scale="ut1").earth_rotation_angle(0.0).rad
        got = earth_rotation_angle(t_tdb_s, offset_s)
        assert abs(np.angle(np.exp(1j * (got - expected)))) < 1e-9


# --- SRP and shadow ---------------------------------------------------------------------------------


def test_srp_at_one_au_is_pressure_times_area_over_mass():
    srp = SolarRadiationPressure(0.02, 1.3, "sun", shadow_bodies=())
    r = np.array([[AU_KM, 0.0, 0.0], [0.0, 0.0, -2.0 * AU_KM]])
    a = srp.acceleration(T_S1, r, np.zeros((2, 3)))
    magnitude = 4.56e-6 * 1.3 * 0.02 * 1e-3  # N/m^2 * m^2/kg -> m/s^2 -> km/s^2
    np.testing.assert_allclose(a, [[magnitude, 0, 0], [0, 0, -magnitude / 4]], rtol=1e-12, atol=1e-25)


def _visible_fraction_by_grid(r_sun_probe, r_body_probe, body_radius, n=801):
    """Fraction of sampled directions on the solar disk that miss the occulting body (n x n grid)."""
    to_sun = -r_sun_probe / np.linalg.norm(r_sun_probe)
    to_body = -r_body_probe / np.linalg.norm(r_body_probe)
    a = np.arcsin(RADIUS_KM["sun"] / np.linalg.norm(r_sun_probe))
    cos_b = np.cos(np.arcsin(body_radius / np.linalg.norm(r_body_probe)))
    e1 = np.cross(to_sun, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(to_sun, e1)
    u = np.linspace(-np.tan(a), np.tan(a), n)
    uu, vv = np.meshgrid(u, u)
    directions = to_sun + uu[..., None] * e1 + vv[..., None] * e2
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    on_sun = directions @ to_sun >= np.cos(a)
    covered = directions @ to_body >= cos_b
    return 1.0 - np.count_nonzero(on_sun & covered) / np.count_nonzero(on_sun)


def test_shadow_factor_conical_geometry():
    r_sun_earth = np.array([AU_KM, 0.0, 0.0])  # Earth relative to the Sun
    radius = RADIUS_KM["earth"]
    # Umbra right behind the Earth, full sun on the day side.
    behind = np.array([[42164.0, 0.0, 0.0]])
    assert shadow_factor(r_sun_earth + behind, behind, radius)[0] == 0.0
    assert shadow_factor(r_sun_earth - behind, -behind, radius)[0] == 1.0
    # Penumbra: compare with a brute-force disk-overlap count.
    penumbra_half_width = 42164.0 * (RADIUS_KM["sun"] / AU_KM)
    for lateral in (radius - 0.6 * penumbra_half_width, radius, radius + 0.6 * penumbra_half_width):
        r_body = np.array([[42164.0, lateral, 0.0]])
        got = shadow_factor(r_sun_earth + r_body, r_body, radius)[0]
        expected = _visible_fraction_by_grid(r_sun_earth + r_body[0], r_body[0], radius)
        assert 0.0 < got < 1.0
        assert abs(got - expected) < 3e-3
    # Annular eclipse: a small body close to the Sun line but far from the probe.
    r_body = np.array([[1.0e7, 0.0, 0.0]])
    expected = 1.0 - (np.arcsin(radius / 1.0e7) / np.arcsin(RADIUS_KM["sun"] / (AU_KM + 1.0e7))) ** 2
    np.testing.assert_allclose(shadow_factor(r_sun_earth + r_body, r_body, radius), [expected], rtol=1e-12)


def test_srp_is_zero_in_earth_umbra():
    srp = SolarRadiationPressure(0.02, 1.5, "earth")
    r_sun = default_cached_ephemeris().position("sun", T_S3, center="earth")
    r = -42164.0 * r_sun / np.linalg.norm(r_sun)
    np.testing.assert_array_equal(srp.acceleration(T_S3, r[None, :], np.zeros((1, 3))), 0.0)


# --- ephemeris cache, model assembly, validation --------------------------------------------------


def test_ephemeris_cache_matches_direct_ephemeris():
    direct = default_ephemeris()
    cache = EphemerisCache(direct)
    t = T_S1 + np.random.default_rng(3).uniform(0.0, 300 * 86_400.0, 60)
    for body, center in [("moon", "earth"), ("sun", "earth"), ("mars", "sun"), ("earth", "mars"), ("saturn", "sun")]:
        assert np.abs(cache.position(body, t, center=center) - direct.position(body, t, center=center)).max() < 1e-5


def test_force_model_sums_terms_and_accepts_single_state():
    terms = (CentralGravity(GM_KM3_S2["sun"]), ThirdBody("mars", "sun", GM_KM3_S2["mars"]))
    model = ForceModel("sun", terms, "test")
    r = np.array([[1.4e8, 2.0e7, 1.0e6]])
    v = np.zeros((1, 3))
    expected = terms[0].acceleration(T_S1, r, v) + terms[1].acceleration(T_S1, r, v)
    np.testing.assert_allclose(model.acceleration(T_S1, r, v), expected, rtol=1e-14)
    np.testing.assert_allclose(model.acceleration(T_S1, r[0], v[0]), expected[0], rtol=1e-14)
    assert model.partials(T_S1, r[0], v[0])[0].shape == (3, 3)


def test_fused_third_bodies_equal_the_sum_of_single_terms():
    # ForceModel evaluates ThirdBody terms sharing an ephemeris together; it must equal their sum.
    bodies = ("venus", "earth", "moon", "mars", "jupiter")
    terms = tuple(ThirdBody(b, "sun", GM_KM3_S2[b]) for b in bodies)
    model = ForceModel("sun", terms, "fused")
    r = _states_around(np.zeros(3), 1.5e8, np.random.default_rng(5), k=4)
    v = np.zeros_like(r)
    np.testing.assert_allclose(model.acceleration(T_S1, r, v), sum(t.acceleration(T_S1, r, v) for t in terms),
                               rtol=1e-13, atol=0)
    np.testing.assert_allclose(model.partials(T_S1, r, v)[0], sum(t.partials(T_S1, r, v)[0] for t in terms),
                               rtol=1e-12, atol=0)


@pytest.mark.parametrize(
    "build, error, match",
    [
        (lambda: CentralGravity(-1.0), InputError, "gm_km3_s2"),
        (lambda: CentralGravity(float("nan")), InputError, "gm_km3_s2"),
        (lambda: ThirdBody("vulcan", "sun", 1.0), EphemerisError, "vulcan"),
        (lambda: ThirdBody("sun", "sun", 1.0), InputError, "central body"),
        (lambda: SolarRadiationPressure(-0.1, 1.3, "sun"), InputError, "area_to_mass"),
        (lambda: SolarRadiationPressure(0.1, 7.0, "sun"), InputError, "cr"),
        (lambda: SolarRadiationPressure(0.1, 1.3, "sun", shadow_bodies=("jupiter",)), InputError, "shadow body"),
        (lambda: Geopotential(398600.0, 6378.0, j2=float("inf")), InputError, "j2"),
        (lambda: ForceModel("sun", (), "empty"), InputError, "at least one term"),
        (lambda: ForceModel("mars", (ThirdBody("earth", "sun", 1.0),), "mixed"), InputError, "centred"),
    ],
)
def test_bad_parameters_raise_named_errors(build, error, match):
    with pytest.raises(error, match=match):
        build()
