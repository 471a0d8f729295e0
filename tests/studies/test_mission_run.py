"""`opnav run` and `opnav montecarlo` on samples/cislunar.toml (a day of it): the filters' errors stay
inside their 3-sigma of the truth, a re-run resumes, a campaign run is its replay."""

import json
from pathlib import Path

import numpy as np
from scipy import stats

from opnav.cli import main

SAMPLE = str(Path(__file__).resolve().parents[2] / "samples" / "cislunar.toml")
# the first day of the coast in measurement mode (the sample's own is images): 144 epochs
DAY = ["--set", "stop=2027-03-01T01:00:00", "--set", "step_s=600", "--mode", "measurements", "--no-progress"]


def test_a_day_of_the_coast_is_inside_three_sigma_and_resumes(tmp_path):
    out = tmp_path / "cislunar"
    assert main(["run", SAMPLE, "--out", str(out), *DAY]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["run"]["study"] == "mission"
    assert summary["measurements"]["records"] == 2 * 144 and summary["measurements"]["targets"] == ["earth", "moon"]
    truth = np.load(out / "truth.npz")
    for name in ("ekf", "ukf"):
        figures = summary["filters"][name]
        assert figures["accepted"] == figures["records"] == 288 and not figures["consistency"]["flags"]
        saved = np.load(out / "filters" / f"{name}.npz")
        ratio = np.abs(saved["error"]) / saved["sigma"]  # (epochs, 6): position and velocity per axis
        # a consistent filter has 99.73 % of its errors inside 3 sigma; successive epochs are correlated,
        # so one run's share strays, but not below 95 %
        assert np.mean(ratio < 3.0) > 0.95, f"{name}: {np.mean(ratio < 3.0):.3f} inside 3 sigma"
        assert np.all(ratio[-1] < 3.0), f"{name}: final error / sigma {ratio[-1]}"
        # the final NEES against chi-square(6) at 99.9 %
        assert saved["nees"][-1] < stats.chi2.ppf(0.999, 6)
        assert np.array_equal(saved["t_tdb_s"], truth["epochs"])
    page = (out / "report.html").read_text()
    assert "cislunar (MISSION, seed 2027" in page and "data:image/png;base64," in page
    before = (out / "filters" / "ekf.npz").stat().st_mtime_ns
    assert main(["run", SAMPLE, "--out", str(out), *DAY]) == 0  # resumes: every stage reused
    walls = json.loads((out / "summary.json").read_text())["stages_wall_s"]
    assert "simulate (reused)" in walls and "filter ekf (reused)" in walls and "filter ukf (reused)" in walls
    assert (out / "filters" / "ekf.npz").stat().st_mtime_ns == before


def test_a_campaign_run_is_its_replay(tmp_path):
    out = tmp_path / "campaign"
    assert main(["montecarlo", SAMPLE, "--runs", "2", "--out", str(out), "--filters", "ekf", *DAY]) == 0
    record = json.loads((out / "campaign.json").read_text())
    assert [run["seed"] for run in record["runs"]] == [2027, 2028]
    assert record["aggregate"]["ekf"]["monte_carlo_nees"]["available"]
    single = tmp_path / "replay"
    assert main(["run", SAMPLE, "--seed", "2028", "--out", str(single), "--filters", "ekf", *DAY]) == 0
    replay = json.loads((single / "summary.json").read_text())["filters"]["ekf"]
    assert record["runs"][1]["filters"]["ekf"]["position_rms_km"] == replay["position_rms_km"]
