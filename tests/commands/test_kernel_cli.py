"""``opnav kernel``: an SPK from an OEM, from a scene's propagated observer and from an elements file,
each read back through :class:`opnav.ephemeris.spice.SpiceEphemeris` against its source; bad inputs
end in one line and exit status 2."""

from __future__ import annotations

import numpy as np
import pytest

from opnav.ccsds import read_oem, write_oem
from opnav.cli import main
from opnav.ephemeris.planets import default_kernel_path
from opnav.ephemeris.spice import SpiceEphemeris
from opnav.epochs import parse_epoch
from opnav.frames import ecliptic_to_icrf
from opnav.sim.scene import load_scene

pytest.importorskip("spiceypy")

#: The demo's cruise state (opnav/data/demo.toml): heliocentric ICRF at 2013-12-12T12:00 TT.
SCENE = """
[epochs]
start = "2014-07-15T00:00:00"
stop = "2014-07-16T00:00:00"
scale = "tdb"
step_s = 3600.0

[observer]
epoch = "2013-12-12T12:00:00"
epoch_scale = "tt"
position_km = [24306991.2893, 132523850.2219, 58427884.5328]
velocity_km_s = [-32.455391, 3.658828, 3.362343]
center = "sun"
dynamics = "cruise"

[camera]
width_px = 64
height_px = 64
focal_length_mm = 100.0
pixel_pitch_um = 10.0
"""

ELEMENTS = """
[body]
naif_id = 2099999
center = "sun"

[elements]
epoch = "2027-01-01T00:00:00"
epoch_scale = "tdb"
frame = "ecliptic"
a_km = 3.9e8
e = 0.18
i_deg = 10.6
node_deg = 80.3
argp_deg = 73.6
mean_anomaly_deg = 20.0

[span]
start = "2026-01-01T00:00:00"
stop = "2032-01-01T00:00:00"
scale = "tdb"
"""


def test_an_oem_becomes_an_spk_holding_its_states(tmp_path, capsys):
    t = parse_epoch("2014-07-15T00:00:00", "tdb") + 600.0 * np.arange(50)
    r0, v0 = np.array([1.1e8, -9.0e7, 2.0e7]), np.array([12.0, 25.0, -3.0])
    states = np.hstack([r0 + (t - t[0])[:, None] * v0, np.tile(v0, (t.size, 1))])
    write_oem(tmp_path / "probe.oem", t, states, object_name="probe", object_id="probe", center="SUN")
    assert main(["kernel", "--oem", str(tmp_path / "probe.oem"), "--body", "-77", "--out",
                 str(tmp_path / "probe.bsp")]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith(f"wrote {tmp_path / 'probe.bsp'}: NAIF -77 relative to NAIF 10, 2014-07-15T00:00:00 TDB")
    assert "(type 13, Hermite of degree 3, 50 states)" in printed
    eph = SpiceEphemeris([tmp_path / "probe.bsp"])
    t = read_oem(tmp_path / "probe.oem").t_tdb_s  # the epochs as the file keeps them (microseconds)
    r, v = eph.state(-77, t, center=10)
    np.testing.assert_allclose(r, states[:, :3], rtol=0, atol=1e-6)
    np.testing.assert_allclose(v, states[:, 3:], rtol=0, atol=1e-12)
    # a straight line is a cubic: Hermite reproduces it between the states too (to the file's epochs,
    # kept to the microsecond: 0.5 us x 28 km/s = 1.4e-5 km)
    np.testing.assert_allclose(eph.position(-77, t[:-1] + 300.0, center=10), states[:-1, :3] + 300.0 * v0,
                               rtol=0, atol=1.4e-5)


def test_a_scene_observer_becomes_an_spk_equal_to_its_truth(tmp_path, capsys):
    (tmp_path / "cruise.toml").write_text(SCENE)
    assert main(["kernel", "--scene", str(tmp_path / "cruise.toml"), "--body", "-77", "--step", "600",
                 "--out", str(tmp_path / "probe.bsp")]) == 0
    assert "(type 13, Hermite of degree 7, 145 states)" in capsys.readouterr().out
    scene = load_scene(tmp_path / "cruise.toml")
    t = scene.t_tdb_s[0] + np.linspace(0.0, 86_400.0, 97)  # every 15 min, between the SPK's states
    truth = scene.truth(t, "sun")
    eph = SpiceEphemeris([default_kernel_path(), tmp_path / "probe.bsp"])
    r, _ = eph.state(-77, t, center="sun")
    assert np.linalg.norm(r - truth[:, :3], axis=1).max() < 1e-3  # < 1 m


def test_an_elements_file_becomes_a_closed_orbit(tmp_path, capsys):
    (tmp_path / "asteroid.toml").write_text(ELEMENTS)
    assert main(["kernel", "--elements", str(tmp_path / "asteroid.toml"), "--out",
                 str(tmp_path / "asteroid.bsp")]) == 0
    assert "(type 5, two-body, ECLIPJ2000)" in capsys.readouterr().out
    eph = SpiceEphemeris([tmp_path / "asteroid.bsp"])
    epoch = parse_epoch("2027-01-01T00:00:00", "tdb")
    r, v = eph.state(2099999, epoch, center="sun")
    # at the epoch: the periapsis distance a (1 - e) lies where the elements put it
    a, e = 3.9e8, 0.18
    i, node, argp, m = np.radians([10.6, 80.3, 73.6, 20.0])
    period = 2 * np.pi * np.sqrt(a**3 / 132_712_440_040.944)
    ecc = m
    for _ in range(50):  # Kepler's equation by fixed point (e < 1)
        ecc = m + e * np.sin(ecc)
    r_pf = a * np.array([np.cos(ecc) - e, np.sqrt(1 - e**2) * np.sin(ecc), 0.0])

    def rz(x):
        return np.array([[np.cos(x), -np.sin(x), 0], [np.sin(x), np.cos(x), 0], [0, 0, 1]])

    def rx(x):
        return np.array([[1, 0, 0], [0, np.cos(x), -np.sin(x)], [0, np.sin(x), np.cos(x)]])

    r_ecliptic = rz(node) @ rx(i) @ rz(argp) @ r_pf
    np.testing.assert_allclose(r, ecliptic_to_icrf(r_ecliptic), rtol=1e-12, atol=1e-3)
    # one period later it is back
    r_later, v_later = eph.state(2099999, epoch + period, center="sun")
    np.testing.assert_allclose(r_later, r, rtol=0, atol=1e-3)
    np.testing.assert_allclose(v_later, v, rtol=0, atol=1e-9)


@pytest.mark.parametrize("args, message", [
    (["--scene", "{d}/cruise.toml"], "opnav kernel: error: --scene needs --body, the NAIF id"),
    (["--elements", "{d}/asteroid.toml", "--body", "-5"], "--body is not taken with --elements"),
    (["--elements", "{d}/bad.toml"], "{d}/bad.toml: [elements] e must be in [0, 1) (an elliptic orbit), got 1.3"),
    (["--elements", "{d}/typo.toml"], "unknown key(s) ['ecc'] in [elements] of {d}/typo.toml"),
    (["--oem", "{d}/probe.oem"], "OEM OBJECT_ID 'probe' is not a NAIF id"),
    (["--scene", "{d}/cruise.toml", "--body", "-7", "--degree", "4"], "a Hermite SPK (type 13) takes an odd degree"),
])
def test_bad_inputs_end_in_one_line(tmp_path, capsys, args, message):
    (tmp_path / "cruise.toml").write_text(SCENE)
    (tmp_path / "asteroid.toml").write_text(ELEMENTS)
    (tmp_path / "bad.toml").write_text(ELEMENTS.replace("e = 0.18", "e = 1.3"))
    (tmp_path / "typo.toml").write_text(ELEMENTS.replace("e = 0.18", "ecc = 0.18"))
    t = parse_epoch("2014-07-15T00:00:00", "tdb") + 600.0 * np.arange(4)
    write_oem(tmp_path / "probe.oem", t, np.tile([1e8, 0, 0, 0, 30.0, 0], (4, 1)), object_name="probe",
              object_id="probe", center="SUN")
    argv = ["kernel", *[a.format(d=tmp_path) for a in args], "--out", str(tmp_path / "out.bsp")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message.format(d=tmp_path) in err
    assert not (tmp_path / "out.bsp").exists()


def test_a_scene_whose_state_epoch_is_inside_its_epochs_is_written_both_ways(tmp_path, capsys):
    from opnav.dynamics import get_model, propagate

    model = get_model("cruise")
    start = parse_epoch("2013-12-12T12:00:00", "tt")
    x0 = np.array([24306991.2893, 132523850.2219, 58427884.5328, -32.455391, 3.658828, 3.362343])
    middle = parse_epoch("2014-07-15T12:00:00", "tdb")
    x_mid = propagate(model, start, x0, middle).states[0]
    text = (SCENE.replace('epoch = "2013-12-12T12:00:00"\nepoch_scale = "tt"',
                          'epoch = "2014-07-15T12:00:00"\nepoch_scale = "tdb"')
            .replace("[24306991.2893, 132523850.2219, 58427884.5328]", repr([float(v) for v in x_mid[:3]]))
            .replace("[-32.455391, 3.658828, 3.362343]", repr([float(v) for v in x_mid[3:]])))
    (tmp_path / "middle.toml").write_text(text)
    assert main(["kernel", "--scene", str(tmp_path / "middle.toml"), "--body", "-77", "--step", "600",
                 "--out", str(tmp_path / "probe.bsp")]) == 0
    capsys.readouterr()
    eph = SpiceEphemeris([default_kernel_path(), tmp_path / "probe.bsp"])
    for t in (middle - np.linspace(0.0, 43_000.0, 11), middle + np.linspace(0.0, 43_000.0, 11)):
        truth = propagate(model, middle, x_mid, t).states
        assert np.linalg.norm(eph.position(-77, t, center="sun") - truth[:, :3], axis=1).max() < 1e-3
