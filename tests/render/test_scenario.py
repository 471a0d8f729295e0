"""Scenario files: the samples load, bad files give clear errors, the CLI writes frames."""

from __future__ import annotations

import math
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
    path.write_text((SAMPLES / "s3_render.toml").read_text().replace("0.0]\nvelocity", "nan]\nvelocity"))
    assert main(["render", str(path), "--out", str(tmp_path / "out")]) == 2
    assert "position_km" in capsys.readouterr().err


def test_cli_unknown_catalog_is_a_clear_error(tmp_path, capsys):
    path = tmp_path / "cat.toml"
    text = (SAMPLES / "s3_render.toml").read_text().replace("stars = false", 'path = "/nonexistent/stars.npz"')
    path.write_text(text)
    assert main(["render", str(path), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    assert "nonexistent/stars.npz" in capsys.readouterr().err
