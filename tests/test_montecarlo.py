"""`opnav montecarlo`: seeds recorded, aggregate of the runs, resume, dask workers."""

import json
from pathlib import Path

import numpy as np
import pytest

from opnav.cli import main

ROOT = Path(__file__).resolve().parent.parent


def test_campaign_records_seeds_aggregates_and_resumes(tmp_path):
    out = tmp_path / "camp"
    args = ["montecarlo", str(ROOT / "samples" / "s1_jul_both_0.1.toml"), "--runs", "2", "--out", str(out),
            "--set", "duration_days=0.2", "--filters", "ekf", "--no-progress"]
    assert main(args) == 0
    record = json.loads((out / "campaign.json").read_text())
    assert [r["seed"] for r in record["runs"]] == [2014, 2015]
    rms = [r["filters"]["ekf"]["position_rms_km"] for r in record["runs"]]
    aggregate = record["aggregate"]["ekf"]["position_rms_km"]
    assert aggregate["mean"] == np.mean(rms) and aggregate["min"] == min(rms)
    # each run replays alone with opnav run --seed
    single = tmp_path / "single"
    assert main(["run", str(ROOT / "samples" / "s1_jul_both_0.1.toml"), "--seed", "2015", "--out", str(single),
                 "--set", "duration_days=0.2", "--filters", "ekf", "--no-progress"]) == 0
    replay = json.loads((single / "summary.json").read_text())["filters"]["ekf"]["position_rms_km"]
    assert replay == rms[1]
    # a second call reuses the finished stages
    stage = out / "run_001" / "filters" / "ekf.json"
    before = stage.stat().st_mtime_ns
    assert main(args) == 0
    assert stage.stat().st_mtime_ns == before
    assert "| ekf |" in (out / "campaign.md").read_text()


def test_campaign_on_local_dask_workers(tmp_path):
    out = tmp_path / "dask"
    assert main(["montecarlo", str(ROOT / "samples" / "s3_geo.toml"), "--runs", "2", "--out", str(out),
                 "--set", "duration_hours=0.5", "--filters", "ekf", "--workers", "2", "--no-progress"]) == 0
    record = json.loads((out / "campaign.json").read_text())
    assert len(record["runs"]) == 2 and record["aggregate"]["ekf"]["runs"] == 2


def test_bad_campaign_arguments(tmp_path, capsys):
    assert main(["montecarlo", str(ROOT / "samples" / "s3_geo.toml"), "--runs", "0", "--out", str(tmp_path)]) == 2
    assert "--runs must be a positive integer" in capsys.readouterr().err


def test_sweep_tables_every_point_beside_the_paper(tmp_path):
    out = tmp_path / "sweep"
    assert main(["montecarlo", str(ROOT / "samples" / "s1_jul_both_0.1.toml"), "--runs", "1", "--out", str(out),
                 "--set", "duration_days=0.1", "--filters", "ekf", "--sweep", "targets=phobos,deimos",
                 "--sweep", "noise_arcsec=0.1,1", "--no-progress"]) == 0
    table = (out / "sweep.md").read_text()
    # S1 Table 2/3 July rows: Phobos 32.444 km (0.1"), 440.82 km (1"); Deimos 13.808, 116.66
    for figure in ("32.444 km", "440.82 km", "13.808 km", "116.66 km"):
        assert figure in table
    assert len(json.loads((out / "sweep.json").read_text())["points"]) == 4
    assert main(["montecarlo", str(ROOT / "samples" / "s1_jul_both_0.1.toml"), "--runs", "1", "--out", str(out),
                 "--sweep", "month=dec"]) == 2


def test_unusable_runs_make_the_campaign_exit_3(tmp_path, capsys):
    """SIR with 20 particles on the S1 prior: its cloud degenerates; the campaign says so."""
    out = tmp_path / "pf"
    code = main(["montecarlo", str(ROOT / "samples" / "s3_geo.toml"), "--runs", "1", "--out", str(out),
                 "--set", "duration_hours=0.2", "--set", "particles=20", "--filters", "pf", "--no-progress"])
    record = json.loads((out / "campaign.json").read_text())
    assert record["aggregate"]["pf"]["runs_unusable"] == 1
    assert code == 3 and "not usable" in capsys.readouterr().err


def test_s4_campaign_tables_every_figure_with_html(tmp_path):
    """Studies whose figures are not an RMS (S4: final errors with and without registration) are
    aggregated figure by figure: the mean equals the runs' mean."""
    out = tmp_path / "s4"
    assert main(["montecarlo", str(ROOT / "samples" / "s4_approach.toml"), "--runs", "2", "--out", str(out),
                 "--set", "duration_hours=6", "--no-progress"]) == 0
    record = json.loads((out / "campaign.json").read_text())
    errors = [r["filters"]["registered"]["final_position_error_km"] for r in record["runs"]]
    assert record["aggregate"]["registered"]["final_position_error_km"]["mean"] == pytest.approx(np.mean(errors))
    assert "| unregistered | max_axis_error_in_sigma |" in (out / "campaign.md").read_text()
    page = (out / "campaign.html").read_text()
    assert page.startswith("<!DOCTYPE html>") and "<td>unregistered</td>" in page
