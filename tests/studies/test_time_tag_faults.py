"""Time-tag faults: a clock offset or jitter moves the tags, never silently the answer."""

import json
from pathlib import Path

import numpy as np

from opnav.cli import main
from opnav.dynamics import cruise_model, propagate
from opnav.studies.faults import truth_at_tags
from opnav.studies.s1 import S1_EPOCH_TT, S1_STATE0
from opnav.epochs import parse_epoch

S1 = str(Path(__file__).resolve().parents[2] / "samples" / "s1_jul_both_0.1.toml")


def test_truth_at_tags_matches_the_propagated_truth():
    t0 = parse_epoch("2014-07-01T00:00:00", scale="tdb")
    grid = t0 + 60.0 * np.arange(30)
    tags = grid[5:20] + 17.3
    start = parse_epoch(S1_EPOCH_TT, scale="tt")
    on_grid = propagate(cruise_model(), start, S1_STATE0, grid).states
    at_tags = propagate(cruise_model(), start, S1_STATE0, tags).states
    interpolated = truth_at_tags(grid, on_grid, tags)
    assert np.max(np.abs(interpolated[:, :3] - at_tags[:, :3])) < 1e-3  # km
    assert np.max(np.abs(interpolated[:, 3:] - at_tags[:, 3:])) < 1e-7  # km/s


def test_a_clock_offset_is_caught_by_the_consistency_checks(tmp_path, capsys):
    out = tmp_path / "offset"
    code = main(["run", S1, "--set", "duration_days=1", "--filters", "ekf", "--set", "faults.clock_offset_s=30",
                 "--out", str(out), "--no-progress"])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["facts"]["faults"]["time_tag_error_s"]["mean"] == 30.0
    flags = summary["filters"]["ekf"]["consistency"]["flags"]
    assert code == 3 and "nis_out_of_band" in flags


def test_jitter_below_the_noise_keeps_the_filter_consistent(tmp_path):
    out = tmp_path / "jitter"
    assert main(["run", S1, "--set", "duration_days=1", "--filters", "ekf", "--set", "faults.time_jitter_s=0.5",
                 "--out", str(out), "--no-progress"]) == 0
    figures = json.loads((out / "summary.json").read_text())["filters"]["ekf"]
    assert figures["consistency"]["usable"] and figures["refused_count"] == 0


def test_bad_time_faults_are_refused(tmp_path, capsys):
    assert main(["run", S1, "--set", "faults.time_jitter_s=-1", "--out", str(tmp_path), "--no-progress"]) == 2
    assert "faults.time_jitter_s must be >= 0" in capsys.readouterr().err
