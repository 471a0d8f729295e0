"""`opnav run`: the study runner on the shipped run files, resuming after kill -9, bad run files."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
from scipy import stats

from opnav.cli import main

ROOT = Path(__file__).resolve().parents[2]
S1 = str(ROOT / "samples" / "s1_jul_both_0.1.toml")
S3 = str(ROOT / "samples" / "s3_geo.toml")


def without_walls(value):
    """The summary with every wall time removed (the only figures a resumed run may change)."""
    if isinstance(value, dict):
        return {k: without_walls(v) for k, v in value.items() if "wall" not in k}
    if isinstance(value, list):
        return [without_walls(v) for v in value]
    return value


def test_s1_short_arc_writes_the_summary_and_ekf_and_ukf_agree(tmp_path):
    out = tmp_path / "s1"
    assert main(["run", S1, "--out", str(out), "--set", "duration_days=0.5", "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["run"]["settings"]["duration_days"] == 0.5
    assert summary["measurements"]["records"] == 2 * 720 and summary["measurements"]["kinds"] == ["radec"]
    ekf, ukf = summary["filters"]["ekf"], summary["filters"]["ukf"]
    for figures in (ekf, ukf):
        for key in ("position_rms_km", "velocity_rms_m_s", "converged_after_s", "nees_mean", "wall_s"):
            assert key in figures
        assert figures["accepted"] == figures["records"] == 1440
    assert abs(ekf["position_rms_km"] - ukf["position_rms_km"]) < 0.1 * ekf["position_rms_km"]
    final = ekf["final"]
    assert final["position_error_km"] < 3.0 * final["position_sigma_km"]
    for name in ("report.md", "report.html", "figures/ekf_errors.png", "filters/ukf.npz", "measurements.csv"):
        assert (out / name).exists()
    assert "data:image/png;base64," in (out / "report.html").read_text()
    # CCSDS: the EKF's estimates as an OEM (its last state is the summary's final error), the records as a TDM
    from opnav.ccsds import read_oem, read_tdm

    oem = read_oem(out / "filters" / "ekf.oem")
    truth = np.load(out / "truth.npz")
    assert np.linalg.norm(oem.states[-1, :3] - truth["truth"][-1, :3]) == pytest.approx(final["position_error_km"])
    assert len(read_tdm(out / "measurements.tdm")) == 1440


def test_s3_short_arc_with_the_star_schedule(tmp_path):
    out = tmp_path / "s3"
    assert main(["run", S3, "--out", str(out), "--set", "duration_hours=1", "--filters", "ekf", "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["measurements"]["kinds"] == ["starlight"] and summary["measurements"]["records"] == 360
    assert summary["facts"]["stars_used"] and summary["facts"]["epochs_without_star"] == 0
    data = np.load(out / "filters" / "ekf.npz")
    assert data["nees"][-1] < stats.chi2.ppf(0.999, 6)


def test_damaged_saved_stages_are_detected_by_checksum_and_made_again(tmp_path, capsys):
    out = tmp_path / "s1"
    args = ["run", S1, "--out", str(out), "--set", "duration_days=0.2", "--filters", "ekf"]
    assert main(args + ["--no-progress"]) == 0
    first = json.loads((out / "summary.json").read_text())
    # a measurement file cut short and a filter file with one byte changed: both still parse
    text = (out / "measurements.csv").read_text().splitlines(keepends=True)
    (out / "measurements.csv").write_text("".join(text[: len(text) // 2]))
    npz = bytearray((out / "filters" / "ekf.npz").read_bytes())
    npz[-200] ^= 0xFF
    (out / "filters" / "ekf.npz").write_bytes(bytes(npz))
    capsys.readouterr()
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "do not match their checksums; simulating again" in err
    assert "filter ekf: the saved estimates do not match their checksums; filtering again" in err
    assert without_walls(json.loads((out / "summary.json").read_text())) == without_walls(first)
    # undamaged, everything is reused
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "simulate: reusing" in err and "filter ekf: reusing" in err


def test_kill_9_then_the_same_command_gives_the_same_summary(tmp_path, uninterrupted):
    """kill -9 once the EKF's estimates are saved (the UKF and the report still to come): the same
    command resumes from the saved stages to the uninterrupted run's summary."""
    command = KILL_COMMAND
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    broken = tmp_path / "broken"
    proc = subprocess.Popen(command + ["--out", str(broken)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while not (broken / "filters" / "ekf.json").exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (broken / "summary.json").exists()
    resumed = [c for c in command if c != "--no-progress"]
    again = subprocess.run(resumed + ["--out", str(broken)], check=True, env=env, capture_output=True, text=True)
    assert "simulate: reusing" in again.stderr and "filter ekf: reusing" in again.stderr
    assert without_walls(json.loads((broken / "summary.json").read_text())) == uninterrupted.summary


@pytest.mark.parametrize("args,message", [
    (["--set", "monht=jul"], "unknown setting(s) ['monht']"),
    (["--set", "noise_arcsec=big"], "noise_arcsec"),
    (["--set", "month=dec"], "month must be one of"),
    (["--set", "duration_days"], "KEY=VALUE"),
    (["--filters", "kalman"], "filters must be some of"),
    (["--seed", "-1"], "--seed"),
])
def test_bad_settings_are_one_clear_line(tmp_path, capsys, args, message):
    assert main(["run", S1, "--out", str(tmp_path / "x")] + args) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


@pytest.mark.parametrize("command", ["run", "montecarlo"])
def test_consider_settings_with_a_filter_other_than_the_ekf_are_refused_before_any_work(tmp_path, capsys, command):
    # the filter stage refused it too, but after the simulation and the EKF had run (a 30-day image run's minutes)
    out = tmp_path / "x"
    args = [command, S1, "--out", str(out), "--set", "ephemeris_model=consider", "--filters", "ekf,ukf", "--no-progress"]
    assert main(args + (["--runs", "2"] if command == "montecarlo" else [])) == 2
    err = capsys.readouterr().err
    assert "ephemeris_model = 'consider' works with filter 'ekf' only, not ukf" in err and err.count("\n") == 1
    assert not any(out.rglob("*.csv")) and not any(out.rglob("*.npz"))


def test_bad_run_files_name_the_file(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('[scenario]\nstudy = "s9"\n')
    assert main(["run", str(bad), "--out", str(tmp_path / "x")]) == 2
    assert "bad.toml" in capsys.readouterr().err
    bad.write_text('[scenario]\nstudy = "s1"\n[extra]\nx = 1\n')
    assert main(["run", str(bad), "--out", str(tmp_path / "x")]) == 2
    assert "unknown table(s) ['extra']" in capsys.readouterr().err
    bad.write_text('[scenario]\nstudy = "s1"\n[settings]\nduration_days = "long"\n')
    assert main(["run", str(bad), "--out", str(tmp_path / "x")]) == 2
    assert "duration_days" in capsys.readouterr().err


def test_s2_switching_run_from_its_run_file(tmp_path):
    out = tmp_path / "s2"
    args = ["run", str(ROOT / "samples" / "s2_capture.toml"), "--out", str(out), "--no-progress",
            "--set", "arc_days=0.5", "--set", "stop_before_periapsis_h=36", "--set", "observability=false"]
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    run = summary["filters"]["ekf-switching"]
    assert run["accepted_fraction"] == 1.0 and run["switch_tdb_s"] == summary["facts"]["soi_crossing_tdb_s"]
    for phase in ("MPD (model 1)", "MPS (model 2)"):
        assert run[phase]["nees_mean"] < stats.chi2.ppf(0.999, 6)
    assert (out / "report.html").exists()


def test_s4_registration_run_from_its_run_file(tmp_path):
    out = tmp_path / "s4"
    args = ["run", str(ROOT / "samples" / "s4_approach.toml"), "--out", str(out), "--no-progress",
            "--set", "duration_hours=24"]
    assert main(args) == 0
    filters = json.loads((out / "summary.json").read_text())["filters"]
    # with the angle data leading by 30 s, holding the latest sample puts the fused error many sigma off;
    # registering it (or using each record at its own time) stays inside 3 sigma
    assert filters["unregistered"]["max_axis_error_in_sigma"] > 5.0
    for name in ("exact", "registered"):
        assert filters[name]["max_axis_error_in_sigma"] < 3.0 and filters[name]["refused"] == 0


def test_s1_image_mode_from_pixels(tmp_path):
    """Six hours of frames every 15 minutes through the renderer and the image stage: the EKF ends
    inside its 3-sigma and the report carries the overlaid sample frame."""
    out = tmp_path / "img"
    args = ["run", S1, "--out", str(out), "--mode", "images", "--filters", "ekf", "--no-progress",
            "--set", "duration_days=0.25", "--set", "step_s=900"]
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mode"] == "images" and summary["facts"]["frames"] == 24
    assert summary["measurements"]["targets"] == ["deimos", "phobos"]
    data = np.load(out / "filters" / "ekf.npz")
    assert data["nees"][-1] < stats.chi2.ppf(0.997, 6)
    assert (out / "figures" / "sample_frame.png").exists()


def test_injected_outliers_are_each_refused_and_named(tmp_path, capsys):
    """faults.outlier_fraction: every 100-sigma record is refused by the gate and listed with its
    reason; the answer is the fault-free run's to a small part of its sigma."""
    clean, faulty = tmp_path / "clean", tmp_path / "faulty"
    common = ["--set", "duration_days=0.3", "--filters", "ekf", "--no-progress"]
    assert main(["run", S1, "--out", str(clean), *common]) == 0
    assert main(["run", S1, "--out", str(faulty), *common, "--set", "faults.outlier_fraction=0.02"]) == 0
    summary = json.loads((faulty / "summary.json").read_text())
    injected = summary["facts"]["faults"]["outliers_at"]
    ekf = summary["filters"]["ekf"]
    assert len(injected) == summary["facts"]["faults"]["outliers"] == ekf["refused_count"] > 5
    assert {(r["t_tdb_s"], r["target"]) for r in ekf["refused"]} == {(r["t_tdb_s"], r["target"]) for r in injected}
    assert all("chi-square gate" in r["reason"] for r in ekf["refused"])
    assert "records refused" in (faulty / "report.md").read_text()
    base = json.loads((clean / "summary.json").read_text())["filters"]["ekf"]["final"]
    assert abs(ekf["final"]["position_error_km"] - base["position_error_km"]) < 0.2 * base["position_sigma_km"]
    # dropped records are gone, and a fault that is not known is one clear line
    dropped = tmp_path / "dropped"
    assert main(["run", S1, "--out", str(dropped), *common, "--set", "faults.dropped_fraction=0.25"]) == 0
    summary = json.loads((dropped / "summary.json").read_text())
    assert summary["measurements"]["records"] == 2 * 432 - summary["facts"]["faults"]["records_dropped"]
    capsys.readouterr()
    assert main(["run", S1, "--out", str(tmp_path / "bad"), "--set", "faults.solar_flare=1"]) == 2
    assert "unknown fault(s) ['solar_flare']" in capsys.readouterr().err


# ---- kill -9, SIGTERM and SIGINT at random points (issue 15: twenty kill series behind -m slow)
KILL_COMMAND = [sys.executable, "-m", "opnav.cli", "run", S1, "--set", "duration_days=0.5", "--filters", "ekf,ukf",
                "--no-progress"]


class Uninterrupted(NamedTuple):
    summary: dict  # without wall times
    wall_s: float  # the command's wall time, measured around its process
    out: Path


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> Uninterrupted:
    """KILL_COMMAND run once to its end in its own process, shared by the kill tests (its summary, and
    its wall time: the span the random interruptions are drawn over) and the stage-wall test (the
    same command: its stages against its wall time)."""
    whole = tmp_path_factory.mktemp("whole")
    tic = time.perf_counter()
    subprocess.run(KILL_COMMAND + ["--out", str(whole)], check=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
                   capture_output=True)
    wall = time.perf_counter() - tic
    return Uninterrupted(without_walls(json.loads((whole / "summary.json").read_text())), wall, whole)


def _kill_and_resume(tmp_path: Path, uninterrupted, kills: int, seed: int) -> None:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    reference, duration = uninterrupted.summary, uninterrupted.wall_s
    rng = np.random.default_rng(seed)
    for k in range(kills):
        out = tmp_path / f"killed{k}"
        # one to three interruptions (SIGKILL, SIGTERM or SIGINT) at random points of a run, each
        # time resuming the same folder
        for delay in rng.uniform(0.05, duration, size=int(rng.integers(1, 4))):
            how = [signal.SIGKILL, signal.SIGTERM, signal.SIGINT][int(rng.integers(3))]
            proc = subprocess.Popen(KILL_COMMAND + ["--out", str(out)], env=env, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL)
            try:
                proc.wait(timeout=delay)
            except subprocess.TimeoutExpired:
                proc.send_signal(how)
                proc.wait()
        finished = subprocess.run(KILL_COMMAND + ["--out", str(out)], env=env, capture_output=True, text=True)
        assert finished.returncode == 0, f"kill series {k}: the resumed run failed:\n{finished.stderr[-3000:]}"
        assert without_walls(json.loads((out / "summary.json").read_text())) == reference, f"kill series {k}"


def test_one_kill_series_resumes_to_the_uninterrupted_summary(tmp_path, uninterrupted):
    """Fast sibling of the three and twenty kill series below: one series (the three-series test's
    first: its one to three interruptions at the same random points)."""
    _kill_and_resume(tmp_path, uninterrupted, kills=1, seed=1)


@pytest.mark.slow
def test_three_kill_series_resume_to_the_uninterrupted_summary(tmp_path, uninterrupted):
    _kill_and_resume(tmp_path, uninterrupted, kills=3, seed=1)


@pytest.mark.slow
def test_twenty_kill_series_resume_to_the_uninterrupted_summary(tmp_path, uninterrupted):
    _kill_and_resume(tmp_path, uninterrupted, kills=20, seed=2)


def test_studies_declare_what_they_offer_through_the_protocol(capsys):
    """The runner asks the Study protocol, not the study module: simulating studies (S1, S3) take the
    generic filter stages (and render frames); evaluating ones (S2, S4) print their own figures."""
    from opnav.commands.run import print_summary
    from opnav.studies import STUDIES
    from opnav.studies.base import Study

    flags = {name: (study.generic_filters, study.image_mode) for name, study in STUDIES.items()}
    assert {name: generic for name, (generic, _) in flags.items()} == {"s1": True, "s2": False, "s3": True, "s4": False,
                                                                       "mission": True}
    assert flags["s1"][1] and flags["s3"][1] and flags["s4"][1]  # S4 from pixels (issue 37 item 4)
    assert all(isinstance(study, Study) and study.name == name for name, study in STUDIES.items())
    assert "image_stage" in STUDIES["s1"].image_settings and "image_step_s" in STUDIES["s4"].image_settings
    summary = {"run": {"study": "s4"}, "filters": {"exact": {"refused": 0, "final_position_error_km": 1.5}}}
    assert print_summary(summary, "OUT") == 0
    out = capsys.readouterr().out
    assert out.splitlines()[1].split()[:3] == ["exact", "1.500", "km"] and "{" not in out  # a table, not JSON


# ---- issue 35: the stages of summary.json account for the whole command
STAGES = ["setup", "simulate", "write measurements", "filter ekf", "write ekf estimates", "filter ukf",
          "write ukf estimates", "report"]


def test_stage_walls_add_up_to_the_command_wall(uninterrupted):
    """``opnav run`` in its own process: ``stages_wall_s`` names every stage, in order, from the start
    of the process (interpreter and imports in ``setup``) to the report, and their sum is the
    command's wall time within 5 % (all but the interpreter's exit; a resumed run names its loaded
    stages). The first run is the kill tests' uninterrupted one (KILL_COMMAND is this command); the
    second resumes its folder."""
    out = uninterrupted.out

    def check(stages: list[str], wall: float) -> None:
        walls = json.loads((out / "summary.json").read_text())["stages_wall_s"]
        assert list(walls) == stages and all(value >= 0.0 for value in walls.values())
        assert wall - max(0.05 * wall, 0.5) < sum(walls.values()) <= wall, (walls, wall)
        assert walls["setup"] > 0.05  # the interpreter's start and the imports are counted

    check(STAGES, uninterrupted.wall_s)
    tic = time.perf_counter()
    subprocess.run(KILL_COMMAND + ["--out", str(out)], check=True, capture_output=True)
    check(["setup", "simulate (reused)", "filter ekf (reused)", "filter ukf (reused)", "report"],
          time.perf_counter() - tic)


def test_stage_walls_of_a_run_inside_a_longer_process_start_at_the_call(tmp_path):
    """``main(["run", ...])`` called inside this (pytest) process: ``setup`` starts at the call, not at
    the start of the process."""
    tic = time.perf_counter()
    assert main(["run", S1, "--out", str(tmp_path / "s1"), "--set", "duration_days=0.2", "--filters", "ekf",
                 "--no-progress"]) == 0
    wall = time.perf_counter() - tic
    walls = json.loads((tmp_path / "s1" / "summary.json").read_text())["stages_wall_s"]
    assert list(walls) == ["setup", "simulate", "write measurements", "filter ekf", "write ekf estimates", "report"]
    assert sum(walls.values()) <= wall


def test_stage_clock_gives_every_second_to_one_stage():
    from opnav.studies.runner import StageClock

    start = time.perf_counter()
    clock = StageClock(start - 1.0)  # the command began a second before the clock was made
    time.sleep(0.01)
    clock.lap("setup")
    time.sleep(0.02)
    clock.lap("simulate")
    clock.lap("simulate")  # a stage that comes back adds up
    total = time.perf_counter() - (start - 1.0)
    assert list(clock.walls) == ["setup", "simulate"] and clock.walls["setup"] >= 1.01
    assert clock.walls["simulate"] >= 0.02 and sum(clock.walls.values()) == pytest.approx(total, abs=1e-3)


# ---- issue 36: opnav run without traps (file kinds, options a study ignores, one filter list, tables)
def test_a_missing_run_file_suggests_the_nearest_and_a_scene_file_says_what_it_is(tmp_path, capsys):
    samples = ROOT / "samples"
    assert main(["run", str(samples / "s1_jul_both.toml"), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert f"run file not found: {samples / 's1_jul_both.toml'} (did you mean {samples / 's1_jul_both_0.1.toml'}?)" in err
    assert main(["run", str(samples / "s1_render.toml"), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "s1_render.toml is a scene file" in err and "opnav render" in err
    assert "a run file ([scenario] study) is needed here" in err


def test_studies_refuse_the_options_and_tables_they_would_ignore(tmp_path):
    from opnav.errors import InputError
    from opnav.studies.flags import check_run_flags
    from opnav.studies.settings import load_run_file

    s2 = load_run_file(ROOT / "samples" / "s2_capture.toml")
    s4 = load_run_file(ROOT / "samples" / "s4_approach.toml")
    s1 = load_run_file(S1)
    mission = load_run_file(ROOT / "samples" / "cislunar.toml")
    for run, options, named in [(s2, {"filters": ("ukf",)}, "--filters"), (s4, {"checked": True}, "--checked"),
                                (s1, {"workers": 2}, "--workers"), (s2, {"workers": 2}, "--workers"),
                                (mission, {"mode": "measurements", "workers": 2}, "--workers")]:
        with pytest.raises(InputError, match=f"study {run.study}") as info:
            check_run_flags(run, **options)
        assert named in str(info.value) and "\n" not in str(info.value)
    assert check_run_flags(s1, filters=("ekf", "wls")) == ("ekf", "wls")
    with pytest.raises(InputError, match="--checked verifies the covariance after every record, which wls"):
        check_run_flags(s1, filters=("ekf", "wls"), checked=True)
    with pytest.raises(InputError, match="ephemeris_model is 'estimate'"):
        check_run_flags(load_run_file(S1, {"ephemeris_model": "estimate"}), filters=("wls",))
    assert check_run_flags(s1, mode="images", workers=2) is None and check_run_flags(s2) is None
    assert check_run_flags(s4, mode="images", workers=2) is None  # S4 from pixels (issue 37 item 4)
    assert check_run_flags(s2, mode="images", workers=2) is None  # S2 from pixels (issue 37 item 3)
    assert check_run_flags(mission, workers=2) is None  # the sample's own mode is images (issue 38)
    with pytest.raises(InputError, match=r"study s1 runs the filters ekf, ukf, sr-ukf, pf, upf, mcmc-upf, wls, not "
                                         r"federated \(federated: it fuses one local filter per sensor"):
        check_run_flags(s1, filters=("federated",))
    # a [filters] table or a fault in an S2 run file would be ignored: refused on load
    text = (ROOT / "samples" / "s2_capture.toml").read_text()
    (tmp_path / "s2.toml").write_text(text + '\n[filters]\nnames = ["ukf"]\n')
    with pytest.raises(InputError, match=r"study s2 evaluates its own filters .* does not use \[filters\]"):
        load_run_file(tmp_path / "s2.toml")
    with pytest.raises(InputError, match=r"does not use --set faults.outlier_fraction"):
        load_run_file(ROOT / "samples" / "s2_capture.toml", {"faults.outlier_fraction": "0.01"})


def test_run_takes_the_one_filter_list_wls_included(tmp_path, capsys):
    """`opnav run` and `opnav navigate` take the same names (opnav.filters.option_types.FILTERS): batch
    least squares runs in a study; the federated filter is refused with the reason."""
    out = tmp_path / "wls"
    assert main(["run", S1, "--out", str(out), "--set", "duration_days=0.2", "--filters", "wls", "--no-progress"]) == 0
    wls = json.loads((out / "summary.json").read_text())["filters"]["wls"]
    assert wls["final"]["position_error_km"] < 3.0 * wls["final"]["position_sigma_km"]
    capsys.readouterr()
    assert main(["run", S1, "--out", str(out), "--filters", "federated"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not federated" in err and "one local filter per sensor" in err


def test_evaluating_studies_print_a_table_beside_the_paper(capsys):
    from opnav.studies import STUDIES

    phase = {"nees_mean": 5.5, "position_error_mean_km": 14.13, "position_error_var_km2": 117.2,
             "velocity_error_mean_km_s": 2e-4, "velocity_error_var": 1e-8, "sigma_position_km_at_end": 9.93}
    s2 = {"run": {"study": "s2"}, "paper": {"table3": {"MPD": (5.0314, 6.7987, 0.0093, 0.0054)}},
          "filters": {"ekf-switching": {"accepted_fraction": 1.0, "wall_s": 1.0, "MPD (model 1)": phase,
                                        "switch_tdb_s": 0.0}}}
    lines = STUDIES["s2"].summary_lines(s2)
    row = next(line for line in lines if "MPD (model 1)" in line).split()
    assert row[3:5] == ["14.130", "km"] and row[5:7] == ["117.20", "km^2"] and row[7:9] == ["0.2000", "m/s"]
    assert row[9:12] == ["5.50", "9.930", "km"] and row[-7:] == ["5.0314", "km", "/", "6.7987", "km^2", "9.3", "m/s"]
    s4 = {"run": {"study": "s4"}, "paper": {"claim": "without registration it diverges"},
          "filters": {"registered": {"final_position_error_km": 27.8, "final_position_sigma_km": 116.1,
                                     "final_velocity_error_m_s": 0.06, "final_velocity_sigma_m_s": 0.2,
                                     "max_axis_error_in_sigma": 0.31, "refused": 0, "records": 1870}}}
    lines = STUDIES["s4"].summary_lines(s4)
    assert lines[0].split()[:4] == ["filter", "final", "position", "error"]
    assert lines[1].split() == ["registered", "27.800", "km", "116.100", "km", "0.0600", "m/s", "0.2000", "m/s",
                                "0.31", "0/1870"]
    assert lines[2] == "paper: without registration it diverges"
    assert not any("{" in line for line in lines)
