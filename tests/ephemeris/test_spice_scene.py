"""Scene files with ``[kernels]``: the observer's truth from a spacecraft SPK, frames drawn with the
kernels' ephemeris (a later kernel moves Mars, and the frames see it move), bad kernels refused on
load in one line, and scenes without ``[kernels]`` on the default ephemeris as before."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from opnav.cli import main
from opnav.constants import C_KM_S
from opnav.dynamics import get_model, propagate
from opnav.ephemeris import default_ephemeris
from opnav.ephemeris.planets import default_kernel_path
from opnav.ephemeris.spice import SpiceEphemeris
from opnav.ephemeris.spk_writer import write_spk
from opnav.epochs import parse_epoch
from opnav.errors import InputError
from opnav.light import light_time_vector
from opnav.sim.scene import load_scene

pytest.importorskip("spiceypy")

#: The demo's cruise state (opnav/data/demo.toml [observer]): heliocentric ICRF at 2013-12-12T12:00 TT.
STATE_EPOCH = ("2013-12-12T12:00:00", "tt")
STATE = np.array([24306991.2893, 132523850.2219, 58427884.5328, -32.455391, 3.658828, 3.362343])
PROBE = -999

SCENE = """
[epochs]
start = "2014-07-15T06:00:00"
stop = "2014-07-15T06:30:00"
scale = "tdb"
step_s = 1800

[observer]
body = "{body}"

[camera]
width_px = 256
height_px = 256
focal_length_mm = 200.0
pixel_pitch_um = 10.0

[pointing]
law = "target"
target = "mars"

[targets]
names = ["mars"]

[catalog]
stars = false

[detector]
noise_free = true
"""


@pytest.fixture(scope="module")
def probe(tmp_path_factory):
    """A folder with the probe's SPK (type 13, 10-min nodes over a day of the S1 cruise) and the arc."""
    folder = tmp_path_factory.mktemp("kernels")
    t = parse_epoch("2014-07-15T00:00:00", "tdb") + np.arange(0.0, 86_400.0 + 1.0, 600.0)
    trajectory = propagate(get_model("cruise"), parse_epoch(*STATE_EPOCH), STATE, t, rtol=1e-13, atol_km=1e-9)
    write_spk(folder / "probe.bsp", t, trajectory.states, body=PROBE, center=10)
    return folder, trajectory


def _scene(folder: Path, kernels: str, body: str = str(PROBE), name: str = "scene.toml") -> Path:
    path = folder / name
    path.write_text(SCENE.format(body=body) + kernels)
    return path


def test_truth_from_a_spk_is_the_propagated_arc(probe):
    folder, trajectory = probe
    scene = load_scene(_scene(folder, '[kernels]\nfiles = ["probe.bsp"]\n'))
    assert scene.kernels == (str(default_kernel_path()), str(folder / "probe.bsp"))
    # between the SPK's nodes too: 5-minute offsets
    t = trajectory.t_tdb_s[:-1] + 300.0
    reference = propagate(get_model("cruise"), parse_epoch(*STATE_EPOCH), STATE, t, rtol=1e-13, atol_km=1e-9)
    truth = scene.truth(t, "sun")
    error_m = np.linalg.norm(truth[:, :3] - reference.states[:, :3], axis=1) * 1e3
    assert error_m.max() < 1.0
    print(f"scene truth from the probe SPK against the propagated arc: {error_m.max() * 1e3:.3f} mm")


def test_a_scene_without_kernels_keeps_the_default_ephemeris(probe):
    folder, _ = probe
    scene = load_scene(_scene(folder, "", body="mars", name="plain.toml"))
    assert scene.kernels == () and scene.ephemeris() is default_ephemeris()
    demo = load_scene(Path(__file__).resolve().parents[2] / "opnav" / "data" / "demo.toml")
    assert demo.kernels == () and demo.ephemeris() is default_ephemeris()


def test_observer_and_pointing_bodies_are_checked_against_the_kernels(probe):
    folder, _ = probe
    with pytest.raises(InputError, match=r"\[observer\] body must be one of .*'-998'"):
        load_scene(_scene(folder, '[kernels]\nfiles = ["probe.bsp"]\n', body="-998"))
    # without DE421 under the probe's SPK there is no Mars to point at or draw
    with pytest.raises(InputError, match=r"\[pointing\] target must be one of -999, ssb, got 'mars'"):
        load_scene(_scene(folder, '[kernels]\nfiles = ["probe.bsp"]\nde421 = false\n'))
    # a body opnav can draw but the kernels do not hold
    text = SCENE.format(body=PROBE).replace('names = ["mars"]', 'names = ["mars", "phobos"]')
    (folder / "phobos.toml").write_text(text + '[kernels]\nfiles = ["probe.bsp"]\n')
    with pytest.raises(InputError, match=r"phobos.toml: \[targets\] names: body 'phobos' \(NAIF 401\) is in no SPK"):
        load_scene(folder / "phobos.toml")


@pytest.mark.parametrize("files, message", [
    ('["gone.bsp"]', "[kernels] files: kernel {folder}/gone.bsp not found"),
    ('["notes.bsp"]', "[kernels] files: kernel {folder}/notes.bsp is a text kernel (KPL/?), but a .bsp file must be "
                      "DAF/SPK"),
    ('["."]', "[kernels] files: kernel {folder} is not a file"),
    ('["a\\u0000b.bsp"]', "[kernels] files: kernel '{folder}/a\\x00b.bsp' not found"),
])
def test_bad_kernels_are_one_line_naming_the_scene_and_the_kernel(probe, files, message):
    folder, _ = probe
    (folder / "notes.bsp").write_text("\\begindata\nX = 1\n")
    with pytest.raises(InputError) as excinfo:
        load_scene(_scene(folder, f"[kernels]\nfiles = {files}\n", name="bad.toml"))
    assert str(excinfo.value) == f"{folder / 'bad.toml'}: " + message.format(folder=folder)


def test_opnav_render_draws_with_the_kernels_ephemeris(probe, tmp_path, capsys):
    folder, _ = probe
    t = parse_epoch("2014-07-15T00:00:00", "tdb") + np.arange(0.0, 86_400.0 + 1.0, 600.0)
    # a later kernel moves Mars 3,000 km off its DE421 place (Mars barycentre -> Mars)
    offset_km = np.array([3000.0, -1000.0, 500.0])
    r, v = default_ephemeris().state("mars", t, center="mars_barycenter")
    write_spk(folder / "moved_mars.bsp", t, np.hstack([r + offset_km, v]), body=499, center=4)
    truths = {}
    for name, files in (("de421", '["probe.bsp"]'), ("moved", '["probe.bsp", "moved_mars.bsp"]')):
        scene = _scene(folder, f"[kernels]\nfiles = {files}\n", name=f"{name}.toml")
        assert main(["render", str(scene), "--out", str(tmp_path / name), "--no-progress"]) == 0
        truths[name] = json.loads((tmp_path / name / "frame_00000.truth.json").read_text())
    capsys.readouterr()
    before, after = (truths[k]["targets"][0] for k in ("de421", "moved"))
    # the same observer (from the probe's SPK in both), Mars where each set of kernels puts it
    assert truths["de421"]["r_observer_ssb_km"] == truths["moved"]["r_observer_ssb_km"]
    eph = SpiceEphemeris([default_kernel_path(), folder / "probe.bsp"])
    t0 = truths["de421"]["t_tdb_s"]
    # the line of sight to where Mars was when the light left it (DE421's Mars)
    line_of_sight, _ = light_time_vector(lambda t: eph.position("mars", t), t0, eph.position(PROBE, t0))
    v_mars = eph.state("mars", t0)[1]  # barycentric: a change of light time moves Mars along it
    u = line_of_sight / np.linalg.norm(line_of_sight)
    # the range moves as |L + offset| - |L|, and by what Mars travels in the light time that adds (the
    # frames draw Mars where it was when the light left it)
    moved_km = np.linalg.norm(line_of_sight + offset_km) - np.linalg.norm(line_of_sight)
    light_time_km = abs(moved_km) / C_KM_S * np.linalg.norm(v_mars)
    assert after["range_km"] - before["range_km"] == pytest.approx(moved_km, abs=light_time_km + 0.01)

    def unit(target):
        ra, dec = np.radians(target["ra_deg"]), np.radians(target["dec_deg"])
        return np.array([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)])

    turn_rad = np.arccos(np.clip(unit(before) @ unit(after), -1.0, 1.0))
    across_km = np.linalg.norm(offset_km - (offset_km @ u) * u)
    assert turn_rad == pytest.approx(across_km / before["range_km"], rel=1e-3)


def test_a_kernel_rewritten_in_place_is_read_again(tmp_path):
    t = parse_epoch("2014-07-15T00:00:00", "tdb") + 600.0 * np.arange(20)
    states = np.hstack([np.tile([1.4e8, 2.0e7, 1.0e7], (t.size, 1)), np.zeros((t.size, 3))])
    write_spk(tmp_path / "probe.bsp", t, states, body=PROBE, center=10)
    path = _scene(tmp_path, '[kernels]\nfiles = ["probe.bsp"]\n')
    first = load_scene(path).truth(t[:3], "sun")
    write_spk(tmp_path / "probe.bsp", t, states + [1000.0, 0, 0, 0, 0, 0], body=PROBE, center=10)
    second = load_scene(path).truth(t[:3], "sun")
    np.testing.assert_allclose(second[:, 0] - first[:, 0], 1000.0, rtol=0, atol=1e-6)
