"""`opnav navigate`: end to end on a short simulated S1-like arc; outputs, consistency, errors."""

import csv
import json
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from opnav.cli import main
from opnav.commands import navigate
from opnav.constants import ARCSEC_RAD
from opnav.dynamics import cruise_model, propagate
from opnav.epochs import format_epoch, parse_epoch
from opnav.filters import factory
from opnav.filters.estimates import STATE_COLUMNS
from opnav.measurements import ProbeMeasurementModel, simulate_radec
from opnav.records import Measurement, read_csv, write_csv

T0 = parse_epoch("2014-07-10T00:00:00", scale="tdb")
SIGMA = 1.0 * ARCSEC_RAD
P0_SIG_KM, P0_SIG_KM_S = 300.0, 3e-4


@pytest.fixture(scope="module")
def arc(tmp_path_factory):
    """Truth on the S1 trajectory, 2 h of Mars and Deimos RA/Dec every 10 min, one NaN record."""
    tmp = tmp_path_factory.mktemp("nav")
    t_s1 = parse_epoch("2013-12-12T12:00:00", scale="tt")
    s1 = np.array([24_306_991.2893, 132_523_850.2219, 58_427_884.5328, -32.455391, 3.658828, 3.362343])
    epochs = T0 + 600.0 * np.arange(1, 13)
    truth = propagate(cruise_model(), t_s1, s1, np.concatenate([[T0], epochs])).states
    rng = np.random.default_rng(5)
    model = ProbeMeasurementModel("sun")
    records = []
    for target in ("mars", "deimos"):
        values = simulate_radec(model, target, epochs, truth[1:], sigma_rad=SIGMA, rng=rng)
        records += [Measurement(t, "radec", v, np.eye(2) * SIGMA**2, target=target, sensor=f"nac-{target}")
                    for t, v in zip(epochs, values)]
    records.append(Measurement(epochs[3], "radec", [np.nan, 0.1], np.eye(2) * SIGMA**2, target="mars", sensor="nac-mars"))
    write_csv(tmp / "meas.csv", records)
    x0 = truth[0] + rng.normal(size=6) * np.array([P0_SIG_KM] * 3 + [P0_SIG_KM_S] * 3)
    scenario = f"""
[navigation]
epoch = "{format_epoch(T0, 'tdb', precision=6)}"
epoch_scale = "tdb"
dynamics = "cruise"
position_km = {list(map(float, x0[:3]))}
velocity_km_s = {list(map(float, x0[3:]))}
sigma_position_km = {P0_SIG_KM}
sigma_velocity_km_s = {P0_SIG_KM_S}
filter = "ekf"

[navigation.process_noise]
model = "none"
"""
    (tmp / "scenario.toml").write_text(scenario)
    return tmp, epochs, truth


@pytest.mark.parametrize("name", ["ekf", "wls", "ukf", "federated", "pf", "mcmc-upf"])
def test_navigate_writes_outputs_and_final_error_is_consistent(arc, name, capsys):
    tmp, epochs, truth = arc
    out = tmp / f"out_{name}"
    code = main(["navigate", str(tmp / "meas.csv"), "--scenario", str(tmp / "scenario.toml"), "--filter", name,
                 "--out", str(out), "--no-progress"])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["records"] == 25 and summary["rejected"] == 1
    assert any("NaN" in reason or "bad record" in reason for reason in summary["rejection_reasons"])
    with open(out / "estimates.csv") as handle:
        rows = list(csv.DictReader(handle))
    # one row per record, or per fusion epoch (12) for the federated filter (two locals: one per sensor)
    assert len(rows) == (12 if name == "federated" else 25)
    final = np.array([float(rows[-1][c]) for c in STATE_COLUMNS])
    with open(out / "covariances.csv") as handle:
        last = list(csv.DictReader(handle))[-1]
    P = np.zeros((6, 6))
    for i in range(6):
        for j in range(i, 6):
            P[i, j] = P[j, i] = float(last[f"p{i}{j}"])
    err = final - truth[-1]
    # one draw of chi2(6): 99.9% bound
    assert err @ np.linalg.solve(P, err) < stats.chi2.ppf(0.999, 6)
    with open(out / "residuals.csv") as handle:
        residual_rows = list(csv.DictReader(handle))
    assert sum(r["accepted"] == "0" for r in residual_rows) == 1
    if name != "wls":
        assert summary["consistency"]["usable"] and summary["consistency"]["flags"] == []


def test_navigate_exits_3_when_the_answer_is_unusable(arc, tmp_path, capsys):
    """Records 30 sigma off in RA: the gate refuses most of them; outputs are written, exit 3."""
    tmp, _, _ = arc
    shifted = [replace(r, value=r.value + np.array([30 * SIGMA, 0.0])) for r in read_csv(tmp / "meas.csv")]
    write_csv(tmp_path / "biased.csv", shifted)
    scenario = (tmp / "scenario.toml").read_text().replace('filter = "ekf"', 'filter = "ekf"\ngate_probability = 0.999')
    (tmp_path / "gated.toml").write_text(scenario)
    code = main(["navigate", str(tmp_path / "biased.csv"), "--scenario", str(tmp_path / "gated.toml"),
                 "--out", str(tmp_path / "out"), "--no-progress"])
    assert code == navigate.EXIT_UNUSABLE
    err = capsys.readouterr().err
    assert "not usable" in err and "refused" in err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["consistency"]["usable"] is False and "refused" in summary["consistency"]["flags"]


def test_navigate_errors_are_one_line_exit_2(arc, tmp_path, capsys, monkeypatch):
    tmp, _, _ = arc
    (tmp_path / "empty.toml").write_text("[scenario]\nname = 'x'\n")
    assert main(["navigate", str(tmp / "meas.csv"), "--scenario", str(tmp_path / "empty.toml"), "--out", str(tmp_path)]) == 2
    assert "no [navigation] section" in capsys.readouterr().err
    (tmp_path / "bad.toml").write_text((tmp / "scenario.toml").read_text().replace('filter = "ekf"', 'filtr = "ekf"'))
    assert main(["navigate", str(tmp / "meas.csv"), "--scenario", str(tmp_path / "bad.toml"), "--out", str(tmp_path)]) == 2
    assert "unknown key(s) ['filtr']" in capsys.readouterr().err
    monkeypatch.setitem(factory.LAZY_FILTERS, "federated", ("opnav.filters.no_such_module", "X"))
    assert main(["navigate", str(tmp / "meas.csv"), "--scenario", str(tmp / "scenario.toml"), "--filter", "federated",
                 "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "filter 'federated' is not available" in err and err.count("\n") == 1
    assert main(["navigate", str(tmp_path / "missing.csv"), "--scenario", str(tmp / "scenario.toml"), "--out", str(tmp_path)]) == 2
    assert "measurement file not found" in capsys.readouterr().err


def test_out_naming_an_existing_file_is_one_clear_line(arc, tmp_path, capsys):
    tmp, _, _ = arc
    existing = tmp_path / "a_file"
    existing.write_text("not a folder")
    code = main(["navigate", str(tmp / "meas.csv"), "--scenario", str(tmp / "scenario.toml"), "--out", str(existing),
                 "--no-progress"])
    assert code == 2
    err = capsys.readouterr().err
    assert str(existing) in err and err.count("\n") == 1 and "Traceback" not in err
    assert existing.read_text() == "not a folder"


def test_ccsds_outputs_and_a_tdm_as_input_give_the_same_estimates(arc, capsys):
    """navigate writes the estimates as an OEM and the RA/Dec records as a TDM; reading that TDM
    back gives the CSV run's estimates (the NaN record, refused either way, is not in the TDM)."""
    from opnav.ccsds import read_oem, read_tdm

    tmp, epochs, truth = arc
    first, second = tmp / "ccsds_csv", tmp / "ccsds_tdm"
    assert main(["navigate", str(tmp / "meas.csv"), "--scenario", str(tmp / "scenario.toml"), "--out", str(first),
                 "--no-progress"]) == 0
    oem = read_oem(first / "estimates.oem")
    with open(first / "estimates.csv") as handle:
        rows = list(csv.DictReader(handle))
    np.testing.assert_array_equal(oem.states[-1], [float(rows[-1][c]) for c in STATE_COLUMNS])
    assert oem.center == "SUN" and oem.covariances.shape == (oem.t_tdb_s.size, 6, 6)
    assert np.all(np.abs(oem.t_tdb_s - epochs) < 1e-6)  # the last estimate of each of the 12 epochs
    assert len(read_tdm(first / "measurements.tdm")) == 24
    assert main(["navigate", str(first / "measurements.tdm"), "--scenario", str(tmp / "scenario.toml"),
                 "--out", str(second), "--no-progress"]) == 0
    again = read_oem(second / "estimates.oem")
    np.testing.assert_allclose(again.states, oem.states, rtol=1e-12)  # TDM epochs to the microsecond
    np.testing.assert_allclose(again.covariances, oem.covariances, rtol=1e-9)


# ---- issue 36: navigate prints its answer, and every sample a user can navigate with has a [navigation]
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SAMPLES = ROOT / "samples"


def test_navigate_prints_the_final_state_its_sigma_and_the_flags(arc, tmp_path, capsys):
    """Not only "24/25 records accepted": the final epoch, position and velocity relative to the centre
    with their 1-sigmas, and the consistency flags, the numbers of summary.json."""
    tmp, _, _ = arc
    out = tmp_path / "out"
    assert main(["navigate", str(tmp / "meas.csv"), "--scenario", str(tmp / "scenario.toml"), "--out", str(out),
                 "--no-progress"]) == 0
    lines = capsys.readouterr().out.splitlines()
    final = json.loads((out / "summary.json").read_text())["final"]
    assert lines[0] == "ekf: 24/25 records accepted (1 refused)"
    assert lines[1] == f"final estimate at {final['epoch_utc']} UTC (ICRF, relative to sun):"
    position, velocity = lines[2].split(), lines[3].split()
    assert position[0] == "position" and position[4] == "km" and position[5] == "1-sigma"
    np.testing.assert_allclose([float(v) for v in position[1:4]], final["state"][:3], atol=1e-3)
    np.testing.assert_allclose([float(v) for v in position[6:9]], final["sigma"][:3], rtol=1e-3)
    assert velocity[0] == "velocity" and velocity[4] == "km/s"
    np.testing.assert_allclose([float(v) for v in velocity[1:4]], final["state"][3:], atol=1e-9)
    np.testing.assert_allclose([float(v) for v in velocity[6:9]], final["sigma"][3:], rtol=1e-3)
    assert lines[4].startswith("consistency: usable; flags: none; NIS mean")
    # wls has no NIS: the line says so instead of inventing flags
    assert main(["navigate", str(tmp / "meas.csv"), "--scenario", str(tmp / "scenario.toml"), "--filter", "wls",
                 "--out", str(tmp_path / "wls"), "--no-progress"]) == 0
    assert "consistency: not checked for wls" in capsys.readouterr().out


def test_a_scenario_without_navigation_names_the_files_that_have_one(tmp_path, capsys):
    assert main(["navigate", str(tmp_path / "m.csv"), "--scenario", str(SAMPLES / "s2_capture.toml"),
                 "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no [navigation] section" in err and "study s2 evaluates its own filters" in err
    for name in ("demo.toml", "s1_render.toml", "s3_render.toml", "s1_jul_both_0.1.toml", "s3_geo.toml"):
        assert name in err
    assert "s4_approach.toml" not in err and "docs/formats/navigation.md" in err
    assert main(["navigate", str(tmp_path / "m.csv"), "--scenario", str(SAMPLES / "s1_rendr.toml"),
                 "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"--scenario file not found: {SAMPLES / 's1_rendr.toml'} (did you mean {SAMPLES / 's1_render.toml'}?)" in err


@pytest.mark.parametrize("name", ["s1_jul_both_0.1", "s3_geo"])
def test_a_run_files_navigation_is_its_studys_filter_set_up(name):
    """The [navigation] of a sample run file is what the study sets its filters up with for the file as
    written (the prior drawn with its seed, dynamics, noise, corrections)."""
    import dataclasses

    from opnav.filters.options import load_navigation
    from opnav.studies import STUDIES
    from opnav.studies.settings import load_run_file

    path = SAMPLES / f"{name}.toml"
    run = load_run_file(path)
    study = STUDIES[run.study].simulate(run.settings, run.seed).navigation
    loaded = load_navigation(path)
    for field in dataclasses.fields(loaded):
        mine, theirs = getattr(loaded, field.name), getattr(study, field.name)
        assert np.array_equal(mine, theirs) if isinstance(mine, np.ndarray) else mine == theirs, field.name


@pytest.mark.parametrize("name, center", [("s1_render", "sun"), ("s3_render", "earth")])
def test_a_scene_files_navigation_starts_one_sigma_from_its_truth(name, center):
    from opnav.filters.options import load_navigation
    from opnav.sim.scene import load_scene

    nav = load_navigation(SAMPLES / f"{name}.toml")
    scene = load_scene(SAMPLES / f"{name}.toml")
    assert nav.t0_tdb_s == scene.t_tdb_s[0]
    error = nav.x0 - scene.truth(nav.t0_tdb_s, center=center)[0]
    np.testing.assert_allclose(np.abs(error), np.sqrt(np.diag(nav.P0)), rtol=0.01)


@pytest.mark.parametrize("name, setting", [("s1_jul_both_0.1", "duration_days=0.5"), ("s3_geo", "duration_hours=1")])
def test_navigate_with_a_samples_navigation_on_the_records_of_its_run(name, setting, tmp_path, capsys):
    run_out = tmp_path / "run"
    assert main(["run", str(SAMPLES / f"{name}.toml"), "--out", str(run_out), "--set", setting, "--filters", "ekf",
                 "--no-progress"]) == 0
    out = tmp_path / "nav"
    assert main(["navigate", str(run_out / "measurements.csv"), "--scenario", str(SAMPLES / f"{name}.toml"),
                 "--out", str(out), "--no-progress"]) == 0
    truth = np.load(run_out / "truth.npz")["truth"][-1]
    final = json.loads((out / "summary.json").read_text())["final"]
    error = np.array(final["state"]) - truth
    assert np.all(np.abs(error) < 4.0 * np.array(final["sigma"])), (error, final["sigma"])
