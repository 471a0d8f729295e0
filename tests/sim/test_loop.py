"""The one render -> measure loop: same scene and seed, same noise, whichever command renders it."""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from scipy.spatial.transform import Rotation

from opnav.cli import main
from opnav.ephemeris.cache import default_cached_ephemeris
from opnav.errors import InputError
from opnav.render.frames_io import read_frame
from opnav.sim.chunks import load_chunk, save_chunk
from opnav.sim.loop import digest_card, run_frames, scene_sensor
from opnav.sim.results import FrameTargets, LoopResult, Miss
from opnav.sim.sensors import Arc, Loop, Sensor, Storage, Streams
from opnav.sim.scene import ObserverSpec, load_scene, observer_states
from opnav.studies.s1 import load_demo

SAMPLES = Path(__file__).resolve().parents[2] / "samples"


def test_opnav_render_and_the_demo_draw_the_same_noise_for_the_same_scene_and_seed(tmp_path):
    # samples/s1_render.toml is the demo's camera; at the demo's seed and its first two epochs
    # (hourly from 15 July 2014 01:00 TDB) `opnav render` must write the demo's frames
    text = (SAMPLES / "s1_render.toml").read_text()
    text = text.replace("seed = 41", "seed = 2014").replace('scale = "utc"\nstart = "2014-07-15T00:00:00"\n'
                                                             'stop = "2014-07-15T00:10:00"\nstep_s = 300.0',
                                                             'scale = "tdb"\nstart = "2014-07-15T01:00:00"\n'
                                                             'stop = "2014-07-15T02:00:00"\nstep_s = 3600.0')
    assert "seed = 2014" in text and "step_s = 3600.0" in text
    scene = tmp_path / "scene.toml"
    scene.write_text(text)
    assert main(["render", str(scene), "--out", str(tmp_path / "render"), "--no-progress"]) == 0
    assert main(["demo", "--out", str(tmp_path / "demo"), "--frames", "2", "--no-progress"]) == 0
    for k in range(2):
        rendered = read_frame(tmp_path / "render" / f"frame_{k:05d}.fits")
        demo = read_frame(tmp_path / "demo" / "frames" / f"frame_{k:05d}.fits")
        assert rendered.truth.t_tdb_s == demo.truth.t_tdb_s
        np.testing.assert_array_equal(rendered.image, demo.image)
    first = read_frame(tmp_path / "render" / "frame_00000.fits").image
    assert np.std(first - np.median(first)) > 0.0  # noisy frames, not two noise-free ones


@pytest.fixture(scope="module")
def demo_arc():
    scene, _, _ = load_demo()
    t = scene.t_tdb_s[24:28]
    r, v = observer_states(replace(scene, t_tdb_s=t), t, default_cached_ephemeris())
    return scene, Arc(t, r, v)


def test_a_frame_draws_the_same_noise_whatever_else_the_call_renders(demo_arc, tmp_path):
    scene, arc = demo_arc
    loop = Loop((scene_sensor(scene),), 7, storage=Storage(tmp_path / "all", 1))
    whole = run_frames(loop, arc)
    part = run_frames(replace(loop, storage=Storage(tmp_path / "part", 1)), arc.part(2, 4))
    assert [p.name for p in part.paths] == ["frame_00002.fits", "frame_00003.fits"]
    for k in (2, 3):
        np.testing.assert_array_equal(read_frame(whole.paths[k]).image, read_frame(part.paths[k - 2]).image)
    # another render stream for the same sensor draws other noise
    other = run_frames(Loop((replace(scene_sensor(scene), streams=Streams(render=(5,))),), 7,
                            storage=Storage(tmp_path / "other", 1)), arc.part(2, 3))
    assert not np.array_equal(read_frame(other.paths[0]).image, read_frame(whole.paths[2]).image)
    assert whole.frames_full == 4 and whole.truths["frame_00002"].target("phobos").ra_rad == \
        read_frame(whole.paths[2]).truth.target("phobos").ra_rad


def test_a_loop_result_survives_its_chunk_files(tmp_path):
    result = LoopResult(skipped={"frame_00003": "why"}, missed=(Miss("frame_00001", "phobos", True),),
                        targets=("phobos", "deimos"), events=({"frame": "frame_00000", "event": "acquired"},),
                        truths={"frame_00001": FrameTargets({"phobos": (1.25, -0.5)})},
                        paths=(tmp_path / "frame_00000.fits",), frames_full=1, frames_windowed=3, stars_used=12)
    save_chunk(tmp_path / "chunk_00000", "key", result)
    back = load_chunk(tmp_path / "chunk_00000", "key")
    assert back == result
    assert back.missed_counts() == {"phobos": 1, "deimos": 0}
    assert load_chunk(tmp_path / "chunk_00000", "another key") is None


def test_sensors_and_loops_are_checked(demo_arc):
    scene, arc = demo_arc
    with pytest.raises(InputError, match="pointing law or a mounting"):
        Sensor(scene.camera)
    with pytest.raises(InputError, match="folder"):
        Storage(every=1)
    with pytest.raises(InputError, match="at least one sensor"):
        Loop((), 1)
    mounted = Sensor(scene.camera, mounting=Rotation.identity())
    with pytest.raises(InputError, match="R_icrf_body"):
        run_frames(Loop((mounted,), 1), arc)


def test_scene_truth_is_the_observer_about_its_centre():
    from opnav.ephemeris import default_ephemeris

    ephemeris = default_ephemeris()
    s3 = load_scene(SAMPLES / "s3_render.toml")  # GEO, propagated about the Earth from the first epoch
    t = s3.t_tdb_s[:3]
    about_earth = s3.truth(t, "earth", ephemeris=ephemeris)
    assert about_earth.shape == (3, 6)
    np.testing.assert_allclose(about_earth[0], [*s3.observer.position_km, *s3.observer.velocity_km_s], rtol=0.0,
                               atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(about_earth[:, :3], axis=1), 42_164.17, atol=0.1)
    parked = replace(s3, observer=ObserverSpec(body="mars", offset_km=(1000.0, -20.0, 3.0)))  # fixed off Mars
    np.testing.assert_allclose(parked.truth(t, "mars", ephemeris=ephemeris),
                               np.tile([1000.0, -20.0, 3.0, 0.0, 0.0, 0.0], (3, 1)), rtol=0.0, atol=1e-6)
    s1 = load_scene(SAMPLES / "s1_render.toml")  # a propagated heliocentric observer
    r, v = observer_states(s1, s1.t_tdb_s, ephemeris)
    np.testing.assert_array_equal(s1.truth(s1.t_tdb_s, "ssb", ephemeris=ephemeris), np.hstack([r, v]))
    r_sun, v_sun = ephemeris.state("sun", s1.t_tdb_s)
    np.testing.assert_array_equal(s1.truth(s1.t_tdb_s, ephemeris=ephemeris), np.hstack([r - r_sun, v - v_sun]))
    # about the Sun the S1 observer is the study's 1 AU-class cruise orbit at 20-30 km/s
    assert 1.0e8 < np.linalg.norm(s1.truth(s1.t_tdb_s[:1])[0, :3]) < 3.0e8


@pytest.mark.parametrize("digest", ["6745a1fac13e5bf2-s1-jul", "6745a1fac13e5bf2-s1-jul-f271f52baaf488a0", "d" * 90])
def test_the_scenario_digest_card_is_written_without_a_warning_and_read_back_whole(tmp_path, digest):
    # a run naming camera files has a longer digest: astropy cut its comment and warned on every frame written
    header = fits.Header()
    header["DEMOHASH"] = digest_card(digest)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fits.PrimaryHDU(np.zeros((2, 2), np.int16), header=header).writeto(tmp_path / "f.fits")
    assert fits.getheader(tmp_path / "f.fits")["DEMOHASH"] == digest
