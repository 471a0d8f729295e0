"""Scenario files: the samples load, bad files give clear errors, the CLI writes frames."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from opnav.cli import main
from opnav.errors import InputError
from opnav.sim.scene import load_scene

SAMPLES = Path(__file__).resolve().parents[2] / "samples"


def test_sample_scenarios_load_with_converted_units():
    s1 = load_scene(SAMPLES / "s1_render.toml")
    assert s1.camera.camera_id == "s1-nac" and s1.pointing.target == "phobos"
    assert math.degrees(s1.camera.fov_x_rad) == pytest.approx(1.0, abs=0.01)
    assert np.allclose(np.diff(s1.t_tdb_s), 300.0)
    assert s1.observer.position_km[0] == pytest.approx(24_306_991.2893)
    s3 = load_scene(SAMPLES / "s3_render.toml")
    assert s3.targets == ("earth",) and not s3.stars
    assert np.linalg.norm(s3.observer.position_km) == pytest.approx(42_164.17, abs=0.01)


def test_bad_scenarios_name_the_problem(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text('[scenario]\nname = "x"\n[navigaton]\nfilter = "ekf"\n')  # misspelt section
    with pytest.raises(InputError, match="known sections"):
        load_scene(path)
    text = (SAMPLES / "s3_render.toml").read_text()
    path.write_text(text.replace("exposure_s = 0.05", "exposure_s = -1.0"))
    with pytest.raises(InputError, match="exposure_s"):
        load_scene(path)
    path.write_text(text.replace('names = ["earth"]', 'names = ["vulcan"]'))
    with pytest.raises(InputError, match="vulcan"):
        load_scene(path)
    path.write_text(text.replace("[camera]", "[camera]\nzoom = 3"))
    with pytest.raises(InputError, match="zoom"):
        load_scene(path)


def test_cli_render_reports_errors_with_exit_status_2(tmp_path, capsys):
    path = tmp_path / "nan.toml"
    path.write_text((SAMPLES / "s3_render.toml").read_text().replace("0.0]\nvelocity", "nan]\nvelocity", 1))
    assert main(["render", str(path), "--out", str(tmp_path / "out")]) == 2
    assert "position_km" in capsys.readouterr().err


def test_cli_unknown_catalog_is_a_clear_error(tmp_path, capsys):
    path = tmp_path / "cat.toml"
    text = (SAMPLES / "s3_render.toml").read_text().replace("stars = false", 'path = "/nonexistent/stars.npz"')
    path.write_text(text)
    assert main(["render", str(path), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    assert "nonexistent/stars.npz" in capsys.readouterr().err


def test_a_relative_catalog_path_is_taken_from_the_scene_file_s_folder(tmp_path, monkeypatch):
    folder = tmp_path / "scenes"
    folder.mkdir()
    (folder / "stars.npz").write_bytes(b"")  # only its presence is checked on load
    text = (SAMPLES / "s1_render.toml").read_text().replace("vmag_limit = 11.0", 'vmag_limit = 11.0\npath = "stars.npz"')
    (folder / "scene.toml").write_text(text)
    monkeypatch.chdir(tmp_path)  # not the scene's folder: the old reading would have looked in tmp_path
    assert load_scene(folder / "scene.toml").catalog_path == str(folder / "stars.npz")
    assert load_scene(Path("scenes") / "scene.toml").catalog_path == str(Path("scenes") / "stars.npz")
    absolute = text.replace('path = "stars.npz"', f'path = "{folder / "stars.npz"}"')
    (tmp_path / "elsewhere.toml").write_text(absolute)
    assert load_scene(tmp_path / "elsewhere.toml").catalog_path == str(folder / "stars.npz")
    (tmp_path / "stars.npz").write_bytes(b"")  # a catalog in the working directory is not the scene's
    (folder / "stars.npz").unlink()
    with pytest.raises(InputError, match=r"\[catalog\] path must be an existing catalog file"):
        load_scene(folder / "scene.toml")
    # no sample or packaged scene relied on the old reading (from the working directory)
    for path in [*SAMPLES.glob("*.toml"), *(SAMPLES.parent / "opnav" / "data").glob("*.toml")]:
        assert "path" not in tomllib.loads(path.read_text()).get("catalog", {}), path


def test_enumerated_scene_names_take_any_case_and_are_stored_as_documented(tmp_path):
    text = ((SAMPLES / "s1_render.toml").read_text()
            .replace('scale = "utc"', 'scale = "UTC"').replace('epoch_scale = "tt"', 'epoch_scale = "TT"')
            .replace('frame = "icrf"', 'frame = "ICRF"').replace('center = "sun"', 'center = "Sun"')
            .replace('dynamics = "cruise"', 'dynamics = "CRUISE"').replace('law = "target"', 'law = "Target"')
            .replace('target = "phobos"', 'target = "Phobos"').replace('kind = "gaussian"', 'kind = "Gaussian"')
            .replace('names = ["phobos", "deimos", "mars"]', 'names = ["PHOBOS", "Deimos", "mars"]')
            .replace("windowed = false", 'windowed = false\nsun_policy = "RAISE"'))
    path = tmp_path / "case.toml"
    path.write_text(text)
    scene, reference = load_scene(path), load_scene(SAMPLES / "s1_render.toml")
    assert scene.observer == reference.observer and scene.pointing == reference.pointing
    assert scene.targets == reference.targets and scene.options.psf == reference.options.psf
    assert np.array_equal(scene.t_tdb_s, reference.t_tdb_s) and scene.options.sun_policy == "raise"


def test_the_scene_s_lists_of_names_are_those_their_classes_accept():
    from opnav.render.frame import RenderOptions
    from opnav.render.psf import PSF
    from opnav.sim.pointing import PointingLaw
    from opnav.sim.scene import POINTING_LAWS, PSF_KINDS, SUN_POLICIES

    for kind in PSF_KINDS:
        PSF(kind=kind)
    for law in POINTING_LAWS:
        PointingLaw(law=law, target="mars")
    for policy in SUN_POLICIES:
        RenderOptions(sun_policy=policy)
    for refused in (lambda: PSF(kind="moffat"), lambda: PointingLaw(law="sun"), lambda: RenderOptions(sun_policy="x")):
        with pytest.raises(InputError):
            refused()
