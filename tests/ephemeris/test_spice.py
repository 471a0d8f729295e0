"""SPICE kernels as opnav's ephemeris: the same states as jplephem's DE421, kernels that do not leak
between instances, meta-kernels, PCK radii and frames, and opnav's light time and aberration
through kernels held against CSPICE's own ``CN+S``."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from opnav.constants import C_KM_S
from opnav.ephemeris import default_ephemeris
from opnav.ephemeris.planets import default_kernel_path
from opnav.ephemeris.spice import SpiceEphemeris, naif_code, pool_string
from opnav.ephemeris.spk_writer import write_spk
from opnav.light import apparent_direction

spiceypy = pytest.importorskip("spiceypy")

MAS_RAD = np.pi / (180.0 * 3600.0e3)
DE421 = default_kernel_path()
#: Epochs across the S1 cruise and a year later (TDB s past J2000).
EPOCHS = 4.6e8 + np.array([0.0, 37.3, 200.1, 401.7]) * 86_400.0


@pytest.fixture(scope="module")
def de421():
    return SpiceEphemeris([DE421])


def _angle_mas(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)) / MAS_RAD


def test_de421_through_spice_equals_jplephem(de421):
    # Two readers of one kernel: CSPICE and jplephem evaluate the same Chebyshev series.
    t = np.linspace(EPOCHS[0], EPOCHS[-1], 2_001)
    for body, center in (("mars", "ssb"), ("earth", "sun"), ("moon", "earth"), ("jupiter", "mars"), ("venus", "sun")):
        r, v = de421.state(body, t, center=center)
        r_ref, v_ref = default_ephemeris().state(body, t, center=center)
        assert r.shape == (t.size, 3)
        # float64 epochs near 4.6e8 s are 6e-8 s apart: 25 km/s x 6e-8 s = 1.5 mm of rounding
        np.testing.assert_allclose(r, r_ref, rtol=0, atol=1e-5)
        np.testing.assert_allclose(v, v_ref, rtol=0, atol=1e-11)
    r0, v0 = de421.state("mars", float(t[3]), center="sun")
    assert r0.shape == (3,) and v0.shape == (3,)
    np.testing.assert_allclose(r0, de421.state("mars", t[3:4], center="sun")[0][0], rtol=0, atol=0)


def test_bodies_by_opnav_name_naif_id_or_spice_name(de421):
    t = EPOCHS[:2]
    by_name = de421.position("earth_barycenter", t)
    np.testing.assert_array_equal(de421.position(3, t), by_name)
    np.testing.assert_array_equal(de421.position("3", t), by_name)
    np.testing.assert_array_equal(de421.position("EARTH BARYCENTER", t), by_name)
    # opnav's "jupiter" is the system barycentre (DE421 has no planet centre), not SPICE's JUPITER (599)
    assert de421.naif_id("jupiter") == 5 and naif_code("jupiter") == 5
    assert naif_code("Solar System Barycenter") == 0 and naif_code("eros") == 2000433
    assert {"sun", "earth", "moon", "mars", "ssb", "jupiter"} <= set(de421.known_bodies())
    assert de421.check_body("MARS") == "mars"


def _cruise_arc(t0: float, n: int = 200, step_s: float = 600.0):
    """A heliocentric arc on a straight line with DE421's Sun under it: enough to write an SPK."""
    t = t0 + step_s * np.arange(n)
    r0, v0 = np.array([2.4e7, 1.3e8, 5.8e7]), np.array([-32.4, 3.6, 3.3])
    states = np.hstack([r0 + (t - t0)[:, None] * v0, np.tile(v0, (n, 1))])
    return t, states


def test_two_kernel_sets_never_see_each_other(tmp_path, de421):
    t, states = _cruise_arc(EPOCHS[0])
    write_spk(tmp_path / "probe.bsp", t, states, body=-999, center=10)
    both = SpiceEphemeris([DE421, tmp_path / "probe.bsp"])
    alone = SpiceEphemeris([tmp_path / "probe.bsp"])
    for _ in range(2):  # alternate: each query reloads the pool with its own set
        r, _ = both.state(-999, t[5], center="sun")
        np.testing.assert_allclose(r, states[5, :3], rtol=0, atol=1e-6)
        with pytest.raises(ValueError, match="-999"):
            de421.state(-999, t[5])
        with pytest.raises(ValueError, match="do not cover 'mars'"):
            alone.state("mars", t[5])
    assert "-999" in both.known_bodies() and "-999" not in de421.known_bodies()
    # code that calls spiceypy itself does so inside the set's context
    with both.kernels.loaded():
        assert spiceypy.ktotal("SPK") == 2
    with de421.kernels.loaded():
        assert spiceypy.ktotal("SPK") == 1


def test_an_ephemeris_pickles_by_its_kernel_names(de421):
    copy = pickle.loads(pickle.dumps(de421))
    np.testing.assert_array_equal(copy.position("mars", EPOCHS), de421.position("mars", EPOCHS))
    assert copy.kernels.files == de421.kernels.files


def test_a_meta_kernel_is_read_with_symbols_and_paths_from_its_folder(tmp_path, monkeypatch):
    t, states = _cruise_arc(EPOCHS[0])
    (tmp_path / "spk").mkdir()
    write_spk(tmp_path / "spk" / "probe.bsp", t, states, body=-999, center=10)
    (tmp_path / "mission.tm").write_text(
        "KPL/MK\n\\begindata\n"
        "PATH_SYMBOLS = ( 'SPK' )\n"
        "PATH_VALUES  = ( 'spk' )\n"
        f"KERNELS_TO_LOAD = ( {pool_string(DE421)},\n '$SPK/pro+'\n 'be.bsp' )\n\\begintext\n"
    )
    monkeypatch.chdir(tmp_path / "spk")  # not the meta-kernel's folder: paths are taken from its folder
    eph = SpiceEphemeris([tmp_path / "mission.tm"])
    assert [p.name for p in eph.kernels.files] == ["de421.bsp", "probe.bsp"]
    r, _ = eph.state(-999, t[7], center="sun")
    np.testing.assert_allclose(r, states[7, :3], rtol=0, atol=1e-6)


PCK = """KPL/PCK
\\begindata
BODY499_RADII     = ( 3396.19 3396.19 3376.20 )
BODY499_POLE_RA   = ( 317.68143 -0.1061 0. )
BODY499_POLE_DEC  = ( 52.88650 -0.0609 0. )
BODY499_PM        = ( 176.630 350.89198226 0. )
\\begintext
"""


def test_radii_and_orientation_from_a_text_pck(tmp_path):
    (tmp_path / "mars.tpc").write_text(PCK)
    eph = SpiceEphemeris([DE421, tmp_path / "mars.tpc"])
    np.testing.assert_array_equal(eph.radii_km("mars"), [3396.19, 3396.19, 3376.20])
    R = eph.body_rotation("mars", EPOCHS)
    assert R.shape == (len(EPOCHS), 3, 3)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    # the body frame's +z is the pole the PCK states (RA, Dec at T Julian centuries past J2000)
    centuries = EPOCHS / (86_400.0 * 36_525.0)
    ra, dec = np.radians(317.68143 - 0.1061 * centuries), np.radians(52.88650 - 0.0609 * centuries)
    pole = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=-1)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R, pole), np.tile([0.0, 0.0, 1.0], (len(EPOCHS), 1)),
                               atol=1e-12)
    # the prime meridian turns 350.89198226 deg a day: R(t + 1 day) R(t)^T is that turn of the axes
    # about +z (the pole moves 3e-6 deg in a day)
    R0, R1 = eph.body_rotation("mars", EPOCHS[0]), eph.body_rotation("mars", EPOCHS[0] + 86_400.0)
    turn = R1 @ R0.T
    assert np.degrees(np.arctan2(turn[0, 1], turn[0, 0])) % 360.0 == pytest.approx(350.89198226, abs=1e-4)


GEOMETRIES = {  # observer = centre body + offset (km) moving at the centre's velocity + dv (km/s)
    "cruise": ("sun", [2.4e7, 1.3e8, 5.8e7], [-32.4, 3.6, 3.3]),
    "mars_orbit": ("mars", [3000.0, -2500.0, 1200.0], [1.2, 2.9, -1.1]),
    "low_earth_orbit": ("earth", [6800.0, 0.0, 0.0], [0.0, 7.5, 0.4]),
}


@pytest.mark.parametrize("geometry", GEOMETRIES)
def test_light_time_and_aberration_through_kernels_equal_spice_cn_s(de421, geometry):
    center, offset, dv = GEOMETRIES[geometry]
    r_center, v_center = de421.state(center, EPOCHS)
    r_obs, v_obs = r_center + np.asarray(offset), v_center + np.asarray(dv)
    worst = 0.0
    for body in ("mars", "earth", "moon", "jupiter", "sun", "venus"):
        if body == center:
            continue
        target = lambda t: de421.position(body, t)  # noqa: E731 - opnav's renderer asks the same way
        apparent = apparent_direction(target, EPOCHS, r_obs, v_obs)
        astrometric = apparent_direction(target, EPOCHS, r_obs, v_obs, aberration=False)
        naif = str(de421.naif_id(body))
        with de421.kernels.loaded():
            spice = {corr: np.array([spiceypy.spkcvo(naif, float(t), "J2000", "OBSERVER", corr, np.r_[r, v], float(t),
                                                     "SSB", "J2000")[0][:3]
                                     for t, r, v in zip(EPOCHS, r_obs, v_obs)]) for corr in ("CN", "CN+S")}
        spice = {corr: s / np.linalg.norm(s, axis=1, keepdims=True) for corr, s in spice.items()}
        # light time alone: the same converged Newtonian solution
        assert np.all(_angle_mas(astrometric, spice["CN"]) < 0.005)
        residual = _angle_mas(apparent, spice["CN+S"])
        assert np.all(residual < 1.0), (body, residual)
        # what remains is SPICE's first-order stellar aberration (it turns the direction by
        # asin(beta sin theta)); opnav's relativistic formula differs by (beta^2 / 4) sin 2 theta
        beta = np.linalg.norm(v_obs, axis=1) / C_KM_S
        theta = np.arccos(np.sum(spice["CN"] * v_obs, axis=1) / np.linalg.norm(v_obs, axis=1))
        second_order = beta**2 / 4.0 * np.abs(np.sin(2.0 * theta)) / MAS_RAD
        np.testing.assert_allclose(residual, second_order, rtol=0, atol=0.005)
        worst = max(worst, float(residual.max()))
    print(f"{geometry}: opnav vs SPICE CN+S, largest difference {worst:.3f} mas")


def test_an_spk_observer_sees_what_spkezr_cn_s_gives(tmp_path, de421):
    # the observer itself from a written SPK: SPICE's spkezr with CN+S against opnav's light code
    t, states = _cruise_arc(EPOCHS[0], n=400)
    write_spk(tmp_path / "probe.bsp", t, states, body=-999, center=10)
    eph = SpiceEphemeris([DE421, tmp_path / "probe.bsp"])
    epochs = t[10:390:47] + 123.4
    r_obs, v_obs = eph.state(-999, epochs)
    for body in ("mars", "earth", "jupiter"):
        apparent = apparent_direction(lambda tt: eph.position(body, tt), epochs, r_obs, v_obs)
        with eph.kernels.loaded():
            s = np.array([spiceypy.spkezr(str(eph.naif_id(body)), float(e), "J2000", "CN+S", "-999")[0][:3]
                          for e in epochs])
        assert np.all(_angle_mas(apparent, s / np.linalg.norm(s, axis=1, keepdims=True)) < 1.0)
