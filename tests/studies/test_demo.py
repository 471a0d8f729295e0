"""``opnav demo``: the embedded demo run file through the study runner, on its first few frames."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from scipy import stats

from opnav.cli import main
from opnav.render.frames_io import read_frame

FRAMES = 5


def _demo(out, *extra) -> int:
    return main(["demo", "--out", str(out), "--frames", str(FRAMES), "--no-progress", *extra])


def _summary(out) -> dict:
    return json.loads((out / "summary.json").read_text())


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "run"
    assert _demo(out) == 0
    return out


def test_demo_measurements_match_truth_within_reported_sigma(first_run):
    summary = _summary(first_run)
    facts = summary["facts"]
    assert summary["mode"] == "images" and facts["frames"] == FRAMES and not facts["frames_skipped"]
    errors = facts["measurement_errors"]
    assert "deimos" in errors
    # every record's d^T C^-1 d against the truth sidecar is chi-square(2); their sum over n
    # records is chi-square(2n) when the pipeline's covariance is right (records of one frame
    # share the attitude error, a small part of C, so they are nearly independent)
    n = sum(m["count"] for m in errors.values())
    total = sum(m["chi2_mean"] * m["count"] for m in errors.values())
    assert stats.chi2.ppf(0.0005, 2 * n) < total < stats.chi2.ppf(0.9995, 2 * n)
    for m in errors.values():
        assert m["chi2_mean"] * m["count"] < stats.chi2.ppf(0.9995, 2 * m["count"])
        # a tenth of the 3.5"/px pixel: the centroid really located the moon
        assert max(m["rms_arcsec"]) < 0.35


def test_demo_final_estimate_inside_filter_three_sigma(first_run):
    ekf = _summary(first_run)["filters"]["ekf"]
    assert ekf["accepted"] >= FRAMES
    final = ekf["final"]
    assert final["position_error_km"] < 3.0 * final["position_sigma_km"]
    assert final["velocity_error_m_s"] < 3.0 * final["velocity_sigma_m_s"]
    # the moons' directions shrank the 5000 km start
    assert final["position_sigma_km"] < 0.7 * 5000.0
    assert ekf["consistency"]["usable"]
    for name in ("report.html", "filters/ekf.oem", "measurements.tdm", "figures/sample_frame.png"):
        assert (first_run / name).exists()


def test_demo_second_run_reuses_every_stage(first_run, tmp_path):
    out = tmp_path / "again"
    shutil.copytree(first_run, out)
    stage = out / "filters" / "ekf.json"
    before = stage.stat().st_mtime_ns
    assert _demo(out) == 0
    assert stage.stat().st_mtime_ns == before
    assert _summary(out)["filters"]["ekf"]["final"] == _summary(first_run)["filters"]["ekf"]["final"]


def test_demo_rerenders_corrupt_frame_identically(first_run, tmp_path):
    out = tmp_path / "corrupt"
    shutil.copytree(first_run, out)
    (out / "simulation.json").unlink()  # the measurements must be made again, from the frames
    path = out / "frames" / "frame_00002.fits"
    original = read_frame(path).image
    path.write_bytes(path.read_bytes()[:5000])
    assert _demo(out) == 0
    facts = _summary(out)["facts"]
    assert facts["frames_reused"] == FRAMES - 1
    assert "corrupt" in facts["frames_rerendered"]["frame_00002.fits"]
    # the frame's own noise generator (seed, index) makes the re-rendered frame the same frame
    np.testing.assert_array_equal(read_frame(path).image, original)
    assert _summary(out)["filters"]["ekf"]["final"] == _summary(first_run)["filters"]["ekf"]["final"]


def test_demo_other_seed_renders_new_frames(first_run, tmp_path):
    out = tmp_path / "seed"
    shutil.copytree(first_run, out)
    assert main(["demo", "--out", str(out), "--frames", "2", "--seed", "99", "--no-progress"]) == 0
    summary = _summary(out)
    assert summary["run"]["seed"] == 99 and summary["facts"]["frames_reused"] == 0
    assert "seed" in summary["facts"]["frames_rerendered"]["frame_00000.fits"]


@pytest.mark.parametrize("args, message", [(["--frames", "0"], "--frames"), (["--seed", "-1"], "--seed")])
def test_demo_bad_options_give_clear_errors(tmp_path, capsys, args, message):
    assert main(["demo", "--out", str(tmp_path / "x"), "--no-progress", *args]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_demo_out_is_a_file(tmp_path, capsys):
    target = tmp_path / "file.txt"
    target.write_text("not a directory")
    assert main(["demo", "--out", str(target), "--frames", "2", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "is a file; give a folder" in err and str(target) in err and len(err.strip().splitlines()) == 1
