"""SPKs written by opnav through spiceypy: a propagated arc (type 13), the same arc handed over as a
CCSDS OEM, and a small body from stated orbital elements (type 5), each read back through
:class:`opnav.ephemeris.spice.SpiceEphemeris` against an independent truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import CubicHermiteSpline

from opnav.ccsds import read_oem, write_oem
from opnav.constants import GM_KM3_S2
from opnav.dynamics import get_model, propagate, two_body_model
from opnav.errors import InputError
from opnav.ephemeris.planets import default_kernel_path
from opnav.ephemeris.spice import SpiceEphemeris
from opnav.ephemeris.spk_writer import KeplerElements, oem_interpolation, write_elements_spk, write_oem_spk, write_spk
from opnav.frames import ecliptic_to_icrf

pytest.importorskip("spiceypy")

#: The S1 cruise state of the demo scene (heliocentric, ICRF), at 2014-07-15.
T0 = 458_654_467.0
X0 = np.array([24306991.2893, 132523850.2219, 58427884.5328, -32.455391, 3.658828, 3.362343])
SPAN_S = 20 * 86_400.0
PROBE = -999


@pytest.fixture(scope="module")
def arc():
    """The cruise force model's arc every 10 min for 20 days (DOP853), and the model."""
    model = get_model("cruise")
    t = T0 + np.arange(0.0, SPAN_S + 1.0, 600.0)
    return model, propagate(model, T0, X0, t, rtol=1e-13, atol_km=1e-9)  # smooth to far below a millimetre


def test_an_spk_of_a_propagated_arc_is_the_arc_to_a_metre(tmp_path, arc):
    model, trajectory = arc
    nodes = trajectory.t_tdb_s[::6]  # an hour apart
    write_spk(tmp_path / "probe.bsp", nodes, trajectory.states[::6], body=PROBE, center=10)
    eph = SpiceEphemeris([default_kernel_path(), tmp_path / "probe.bsp"])
    # every 10-minute state, five of every six between the SPK's nodes
    r, v = eph.state(PROBE, trajectory.t_tdb_s, center="sun")
    error_m = np.linalg.norm(r - trajectory.states[:, :3], axis=1) * 1e3
    assert error_m.max() < 1.0
    assert np.linalg.norm(v - trajectory.states[:, 3:], axis=1).max() < 1e-6  # 1 mm/s
    # at the nodes the kernel holds the states themselves
    r_nodes, _ = eph.state(PROBE, nodes, center="sun")
    np.testing.assert_allclose(r_nodes, trajectory.states[::6, :3], rtol=0, atol=1e-6)
    print(f"type-13 SPK (degree 7, 1 h nodes) against the 10-min arc: {error_m.max() * 1e3:.3f} mm")


def _fourth_derivative_km_s4(model, trajectory) -> float:
    """The norm of the per-axis largest |d^4 r_i / dt^4| along the arc (each axis's remainder has its own
    intermediate epoch): the second difference of the model's acceleration."""
    acc = np.array([model.acceleration(t, x[None, :3], x[None, 3:])[0]
                    for t, x in zip(trajectory.t_tdb_s, trajectory.states)])
    step = trajectory.t_tdb_s[1] - trajectory.t_tdb_s[0]
    return float(np.linalg.norm(np.abs(acc[2:] - 2.0 * acc[1:-1] + acc[:-2]).max(axis=0)) / step**2)


@pytest.mark.parametrize("spacing_s", [3_600.0, 86_400.0])
def test_an_oem_of_the_arc_gives_the_arc_to_its_interpolation_accuracy(tmp_path, arc, spacing_s):
    model, trajectory = arc
    every = int(spacing_s / 600.0)
    t_oem, x_oem = trajectory.t_tdb_s[::every], trajectory.states[::every]
    write_oem(tmp_path / "probe.oem", t_oem, x_oem, object_name="probe", object_id=str(PROBE), center="SUN")
    oem = read_oem(tmp_path / "probe.oem")
    assert (oem.interpolation, oem.interpolation_degree) == ("HERMITE", 3)  # what opnav's OEMs recommend
    write_oem_spk(tmp_path / "probe.bsp", oem)
    eph = SpiceEphemeris([default_kernel_path(), tmp_path / "probe.bsp"])
    r, _ = eph.state(PROBE, trajectory.t_tdb_s, center="sun")
    # the SPK is the OEM's own interpolation: cubic Hermite between neighbouring states
    hermite = CubicHermiteSpline(oem.t_tdb_s, oem.states[:, :3], oem.states[:, 3:])(trajectory.t_tdb_s)
    np.testing.assert_allclose(r, hermite, rtol=0, atol=1e-6)
    # and so it meets the arc within cubic Hermite's remainder, h^4 / 384 max |r''''|
    # plus what the file's epochs (text to the microsecond, read back as float seconds) move the states by
    error_km = np.linalg.norm(r - trajectory.states[:, :3], axis=1).max()
    remainder_km = spacing_s**4 / 384.0 * _fourth_derivative_km_s4(model, trajectory)
    epochs_km = np.abs(oem.t_tdb_s - t_oem).max() * np.linalg.norm(x_oem[:, 3:], axis=1).max()
    assert error_km <= remainder_km + epochs_km + 1e-6
    print(f"OEM every {spacing_s:.0f} s, HERMITE 3: truth from its SPK within {error_km * 1e3:.4f} m of the arc "
          f"(cubic Hermite remainder {remainder_km * 1e3:.4f} m, epoch rounding {epochs_km * 1e3:.4f} m)")


def test_oem_interpolations_map_to_spk_types():
    assert oem_interpolation("HERMITE", 5) == ("hermite", 5)
    assert oem_interpolation("LAGRANGE", 8) == ("lagrange", 8)
    assert oem_interpolation("LINEAR", 1) == ("lagrange", 1)
    assert oem_interpolation("", None) == ("hermite", 7)
    with pytest.raises(InputError, match="odd degree only"):
        oem_interpolation("HERMITE", 4)


def test_a_lagrange_spk_interpolates_as_its_degree_says(tmp_path, arc):
    # degree-1 Lagrange (an OEM's LINEAR) is the straight line between neighbouring states
    _, trajectory = arc
    t, x = trajectory.t_tdb_s[::36], trajectory.states[::36]
    write_spk(tmp_path / "linear.bsp", t, x, body=PROBE, center=10, interpolation="lagrange", degree=1)
    eph = SpiceEphemeris([tmp_path / "linear.bsp"])
    mid = 0.5 * (t[:-1] + t[1:])
    np.testing.assert_allclose(eph.position(PROBE, mid, center=10), 0.5 * (x[:-1, :3] + x[1:, :3]), rtol=0, atol=1e-6)


def test_an_elements_spk_is_the_two_body_orbit(tmp_path):
    # a main-belt asteroid's elements on the J2000 ecliptic, heliocentric
    elements = KeplerElements(a_km=3.9e8, e=0.18, i_rad=np.radians(10.6), node_rad=np.radians(80.3),
                              argp_rad=np.radians(73.6), mean_anomaly_rad=np.radians(20.0), epoch_tdb_s=T0,
                              gm_km3_s2=GM_KM3_S2["sun"])
    start, stop = T0 - 200 * 86_400.0, T0 + 200 * 86_400.0
    write_elements_spk(tmp_path / "asteroid.bsp", elements, body=2_099_999, center=10, start_tdb_s=start,
                       stop_tdb_s=stop, frame="ECLIPJ2000")
    eph = SpiceEphemeris([tmp_path / "asteroid.bsp"])
    t = np.linspace(T0, stop, 97)
    r, v = eph.state(2_099_999, t, center="sun")  # ICRF: SPICE turns the ecliptic segment
    # an independent truth: opnav's two-body DOP853 from the elements' state at their epoch
    x0 = elements.states(T0)[0]
    x0_icrf = np.concatenate([ecliptic_to_icrf(x0[:3]), ecliptic_to_icrf(x0[3:])])
    truth = propagate(two_body_model("sun"), T0, x0_icrf, t, rtol=1e-13, atol_km=1e-9).states
    assert np.linalg.norm(r - truth[:, :3], axis=1).max() < 1e-3  # 1 m over 200 days
    assert np.linalg.norm(v - truth[:, 3:], axis=1).max() < 1e-9
    # backwards from the epoch too, and the radius stays on the ellipse
    r_back = eph.position(2_099_999, np.linspace(start, T0, 50), center="sun")
    radius = np.linalg.norm(r_back, axis=1)
    assert radius.min() >= elements.a_km * (1 - elements.e) * (1 - 1e-12)
    assert radius.max() <= elements.a_km * (1 + elements.e) * (1 + 1e-12)


def test_spk_writing_refuses_what_it_cannot_write(tmp_path, arc):
    _, trajectory = arc
    t, x = trajectory.t_tdb_s[:10], trajectory.states[:10]
    with pytest.raises(InputError, match="odd degree"):
        write_spk(tmp_path / "a.bsp", t, x, body=PROBE, center=10, degree=6)
    with pytest.raises(InputError, match="needs at least 12 states, got 10"):
        write_spk(tmp_path / "a.bsp", t, x, body=PROBE, center=10, interpolation="lagrange", degree=11)
    with pytest.raises(InputError, match="increase strictly"):
        write_spk(tmp_path / "a.bsp", t[::-1], x, body=PROBE, center=10)
    with pytest.raises(InputError, match="body and center must differ"):
        write_spk(tmp_path / "a.bsp", t, x, body=10, center=10)
    with pytest.raises(InputError, match="frame must be one of J2000, ECLIPJ2000"):
        write_spk(tmp_path / "a.bsp", t, x, body=PROBE, center=10, frame="IAU_MARS")
    assert not (tmp_path / "a.bsp").exists()
    with pytest.raises(InputError, match=r"element e must be in \[0, 1\)"):
        KeplerElements(1e8, 1.2, 0, 0, 0, 0, 0, 1e11)
