"""`opnav montecarlo`: seeds recorded, aggregate of the runs, resume, dask workers."""

import json
from pathlib import Path

import numpy as np
import pytest

from opnav.cli import main

ROOT = Path(__file__).resolve().parents[2]


def _figures(filters: dict) -> dict:
    """Every finite numeric figure of a summary's filters, by dotted key (wall times left out)."""
    from opnav.studies.report import flat_items

    return {f"{name}.{key}": value for name, figures in filters.items() for key, value in flat_items(figures)
            if isinstance(value, (int, float)) and not isinstance(value, bool) and "wall_s" not in key}


S1 = str(ROOT / "samples" / "s1_jul_both_0.1.toml")
SHORT = ["--set", "duration_days=0.2", "--filters", "ekf,ukf", "--no-progress"]


def test_quick_campaign_runs_equal_their_replays_and_resume(tmp_path):
    """S1 seeds as quick runs: each run's figures and per-epoch NEES are its replay's with ``opnav run
    --seed``, to the last bit (the same simulation, filters and figures), the Monte Carlo NEES test is
    taken over them, the posterior Cramér-Rao bound is recorded, and a second call reuses
    the results (and says so when a run's NEES file is lost)."""
    out = tmp_path / "camp"
    args = ["montecarlo", S1, "--runs", "3", "--out", str(out), "--batch", "2", *SHORT]
    assert main(args) == 0
    record = json.loads((out / "campaign.json").read_text())
    assert [r["seed"] for r in record["runs"]] == [2014, 2015, 2016] and record["quick_runs"] == 3
    rms = [r["filters"]["ekf"]["position_rms_km"] for r in record["runs"]]
    aggregate = record["aggregate"]["ekf"]["position_rms_km"]
    assert aggregate["mean"] == np.mean(rms) and aggregate["min"] == min(rms)
    assert record["posterior_crb"]["pcrb_position_km"] > 0.0  # its value: tests/filters/test_ekf.py
    for index, seed in ((1, 2015), (2, 2016)):  # one run of each task
        single = tmp_path / f"single{seed}"
        assert main(["run", S1, "--seed", str(seed), "--out", str(single), *SHORT]) == 0
        replay = _figures(json.loads((single / "summary.json").read_text())["filters"])
        assert _figures(record["runs"][index]["filters"]) == replay
        assert f"--seed {seed}" in record["runs"][index]["replay"]
        for name in ("ekf", "ukf"):  # the quick run's per-epoch NEES is its replay's
            quick_nees = np.load(out / f"run_{index:03d}" / "nees" / f"{name}.npz")
            replay_nees = np.load(single / "filters" / f"{name}.npz")
            np.testing.assert_array_equal(quick_nees["t_tdb_s"], replay_nees["t_tdb_s"])
            np.testing.assert_array_equal(quick_nees["nees"], replay_nees["nees"])
    for name in ("ekf", "ukf"):
        _check_monte_carlo_nees(out, record, name, [out / f"run_{i:03d}" / "nees" / f"{name}.npz" for i in range(3)])
    summary = out / "run_001" / "summary.json"
    before = summary.stat().st_mtime_ns
    assert main(args) == 0
    assert summary.stat().st_mtime_ns == before
    resumed = json.loads((out / "campaign.json").read_text())
    assert resumed["aggregate"]["ekf"]["monte_carlo_nees"] == record["aggregate"]["ekf"]["monte_carlo_nees"]
    # a resumed campaign whose run lost its NEES file says so instead of failing
    (out / "run_001" / "nees" / "ekf.npz").write_bytes(b"not an npz")
    (out / "run_002" / "nees" / "ukf.npz").unlink()
    assert main(args) == 0
    broken = json.loads((out / "campaign.json").read_text())["aggregate"]
    assert not broken["ekf"]["monte_carlo_nees"]["available"]
    assert "run_001/nees/ekf.npz cannot be read" in broken["ekf"]["monte_carlo_nees"]["reason"]
    assert "run_002/nees/ukf.npz is missing" in broken["ukf"]["monte_carlo_nees"]["reason"]
    assert f"not available: {broken['ekf']['monte_carlo_nees']['reason']}" in (out / "campaign.md").read_text()


def _check_monte_carlo_nees(out: Path, record: dict, name: str, files: list[Path]) -> None:
    """The campaign's Monte Carlo NEES entry and line against a computation from the runs' files."""
    test = record["aggregate"][name]["monte_carlo_nees"]
    saved = [np.load(path) for path in files]  # S1 runs share their epochs
    window = np.round(saved[0]["t_tdb_s"]) >= test["window_start_tdb_s"]
    per_epoch = np.mean([run["nees"][window] for run in saved], axis=0)
    assert test["available"] and test["runs"] == len(files) and test["epochs"] == window.sum() > 0
    assert test["mean"] == pytest.approx(per_epoch.mean(), rel=1e-12)
    assert 0.0 <= test["share_inside"] <= 1.0
    # the campaign page's table row of the test: filter, runs, epochs, mean, band
    low, high = test["band"]
    assert f"| {name} | {len(files)} | {test['epochs']} | {test['mean']:.2f} | {low:.2f} to {high:.2f} |" in \
        (out / "campaign.md").read_text()


def test_campaign_of_full_runs_replays_exactly_and_resumes_by_stage(tmp_path):
    out = tmp_path / "camp"
    args = ["montecarlo", S1, "--runs", "2", "--out", str(out), "--full-runs", *SHORT]
    assert main(args) == 0
    record = json.loads((out / "campaign.json").read_text())
    assert record["quick_runs"] == 0
    single = tmp_path / "single"
    assert main(["run", S1, "--seed", "2015", "--out", str(single), *SHORT]) == 0
    replay = json.loads((single / "summary.json").read_text())["filters"]["ekf"]["position_rms_km"]
    assert replay == record["runs"][1]["filters"]["ekf"]["position_rms_km"]
    stage = out / "run_001" / "filters" / "ekf.json"
    before = stage.stat().st_mtime_ns
    assert main(args) == 0
    assert stage.stat().st_mtime_ns == before
    assert "| ekf |" in (out / "campaign.md").read_text()
    record = json.loads((out / "campaign.json").read_text())
    _check_monte_carlo_nees(out, record, "ekf", [out / f"run_{i:03d}" / "filters" / "ekf.npz" for i in range(2)])


def _aggregate_without_walls(path: Path) -> dict:
    record = json.loads((path / "campaign.json").read_text())
    return {name: {k: v for k, v in figures.items() if "wall_s" not in k}
            for name, figures in record["aggregate"].items()}


def test_killed_campaign_resumes_to_the_same_aggregate(tmp_path):
    """kill -9 once the first runs are written, run the same command again: the aggregate equals an
    uninterrupted campaign's."""
    import os
    import signal
    import subprocess
    import sys
    import time

    command = [sys.executable, "-m", "opnav.cli", "montecarlo", S1, "--runs", "4", "--batch", "1",
               "--set", "duration_days=0.5", "--filters", "ekf", "--no-progress"]
    killed = tmp_path / "killed"
    process = subprocess.Popen(command + ["--out", str(killed)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not (killed / "run_001" / "summary.json").exists() and process.poll() is None:
        assert time.monotonic() < deadline, "the campaign wrote no run in 120 s"
        time.sleep(0.05)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    assert not (killed / "campaign.json").exists(), "the campaign finished before it could be killed"
    subprocess.run(command + ["--out", str(killed)], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    whole = tmp_path / "whole"
    subprocess.run(command + ["--out", str(whole)], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    assert _aggregate_without_walls(killed) == _aggregate_without_walls(whole)


def test_campaign_on_a_scheduler_started_by_hand_matches_the_local_one(tmp_path):
    """``dask scheduler`` and ``dask worker`` started from the command line, then ``--scheduler``:
    the same aggregate as the campaign run in this process."""
    import subprocess
    import sys
    import time

    dask = Path(sys.executable).parent / "dask"
    info = tmp_path / "scheduler.json"
    scheduler = subprocess.Popen([str(dask), "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                  "--scheduler-file", str(info)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    worker = None
    try:
        deadline = time.monotonic() + 60
        while not info.exists():
            assert time.monotonic() < deadline and scheduler.poll() is None, "dask scheduler did not start"
            time.sleep(0.1)
        time.sleep(0.2)  # the file is written whole, but give the scheduler a moment to listen
        address = json.loads(info.read_text())["address"]
        worker = subprocess.Popen([str(dask), "worker", address, "--nthreads", "1", "--no-dashboard"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=str(ROOT))
        common = ["montecarlo", S1, "--runs", "3", "--batch", "2", "--set", "duration_days=0.2", "--filters", "ekf",
                  "--no-progress"]
        assert main(common + ["--out", str(tmp_path / "remote"), "--scheduler", address]) == 0
        assert main(common + ["--out", str(tmp_path / "local")]) == 0
    finally:
        for process in (worker, scheduler):
            if process is not None:
                process.terminate()
                process.wait(timeout=30)
    assert _aggregate_without_walls(tmp_path / "remote") == _aggregate_without_walls(tmp_path / "local")


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
    # no common random numbers across rows: each point's run has a seed of its own
    seeds = [json.loads(p.read_text())["runs"][0]["seed"] for p in sorted(out.glob("*/campaign.json"))]
    assert len(seeds) == 4 and len(set(seeds)) == 4
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
    assert "| unregistered | max axis error in sigma |" in (out / "campaign.md").read_text()
    page = (out / "campaign.html").read_text()
    assert page.startswith("<!DOCTYPE html>") and "<td>unregistered</td>" in page


# ---- issue 35: work for every worker; a seed's figures are its own, whatever its batch or the workers
def test_workers_are_forked_only_before_numba_starts_its_threads():
    import subprocess
    import sys

    probe = ("from opnav.studies.campaign_workers import fork_safe\nimport numba, numpy as np\nbefore = fork_safe()\n"
             "@numba.njit(parallel=True)\ndef f(x):\n    return np.sum(x * 2.0)\nf(np.ones(100))\n"
             "print(before, fork_safe())")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert result.stdout.split() == ["True", "False"]


def test_a_campaign_is_cut_into_tasks_of_batch_seeds_and_one_bound():
    """8 S1 seeds at the default --batch: a task per seed (any worker takes any), and the posterior bound
    a task of its own; --batch 3: tasks of 3, 3 and 2 seeds."""
    from opnav.studies import campaign

    plan = campaign._plan(S1, 8, ROOT / "unused", {"duration_days": "0.2"}, ("ekf", "ukf"), None, True, 1)
    assert [task[2] for task in plan.tasks] == [[2014 + k] for k in range(8)] and all(t[6] for t in plan.tasks)
    assert plan.bound == (S1, {"duration_days": "0.2"}, 2014, str(ROOT / "unused"))
    plan = campaign._plan(S1, 8, ROOT / "unused", {}, ("ekf",), None, True, 3)
    assert [len(task[2]) for task in plan.tasks] == [3, 3, 2]
    plan = campaign._plan(S1, 2, ROOT / "unused", {}, ("ekf",), "images", True, 1)
    assert not any(task[6] for task in plan.tasks) and plan.bound is None  # image mode: full runs


def test_a_campaign_on_two_workers_gives_the_figures_of_one(tmp_path):
    """The same S1 seeds in this process and on 2 dask workers (a command of its own, whose workers are
    forked from it): every run's figures and per-epoch NEES are the same, to
    the last bit."""
    import subprocess
    import sys

    import socket

    common = ["montecarlo", S1, "--runs", "3", *SHORT]
    assert main(common + ["--out", str(tmp_path / "one")]) == 0
    # dask's default HTTP port taken (here, or by another cluster on the machine): the command stays quiet
    with socket.socket() as taken:
        try:
            taken.bind(("127.0.0.1", 8787))
            taken.listen()
        except OSError:
            pass  # already taken by someone else
        two = subprocess.run([sys.executable, "-m", "opnav.cli", *common, "--out", str(tmp_path / "two"),
                              "--workers", "2"], check=True, capture_output=True, text=True)
    assert "already in use" not in two.stderr and "Warning" not in two.stderr
    one, two = (_seed_figures(tmp_path / name) for name in ("one", "two"))
    assert one == two and len(one) == 3
    for k in range(3):
        for name in ("ekf", "ukf"):
            a, b = (np.load(tmp_path / side / f"run_{k:03d}" / "nees" / f"{name}.npz") for side in ("one", "two"))
            np.testing.assert_array_equal(a["nees"], b["nees"])
    assert _aggregate_without_walls(tmp_path / "one") == _aggregate_without_walls(tmp_path / "two")
    # the page: its figures drawn on the workers (beside the bound) say what those drawn here say
    one_page, two_page = ((tmp_path / side / "campaign.md").read_text().split("## Provenance")[0]
                          for side in ("one", "two"))
    assert one_page == two_page and "campaign_ukf_errors" in two_page


def _seed_figures(out: Path) -> dict:
    record = json.loads((out / "campaign.json").read_text())
    return {run["seed"]: _figures(run["filters"]) for run in record["runs"]}


def test_batching_does_not_change_a_seeds_figures(tmp_path):
    """The same 3 seeds in tasks of 3 and of 1 give each seed the same figures to the last bit."""
    figures = {}
    for batch in (3, 1):
        out = tmp_path / f"batch{batch}"
        assert main(["montecarlo", S1, "--runs", "3", "--batch", str(batch), "--out", str(out), *SHORT]) == 0
        figures[batch] = _seed_figures(out)
    assert figures[1] == figures[3] and len(figures[1]) == 3


def test_the_bound_made_inside_the_first_run_is_the_bound_of_its_own_simulation(tmp_path):
    """The posterior bound is made from the first seed's simulation inside its run (no second simulation):
    it equals the bound of a simulation of its own, to the last bit; a campaign whose first run was finished
    before (resumed) makes it from a simulation of its own; campaign.json says where every task ran."""
    import os

    from opnav.studies import campaign_tasks

    out = tmp_path / "c"
    assert main(["montecarlo", S1, "--runs", "2", *SHORT, "--out", str(out)]) == 0
    record = json.loads((out / "campaign.json").read_text())
    inside = record["posterior_crb"]
    (out / campaign_tasks.BOUND_FILE).unlink()
    alone = campaign_tasks.bound_task(S1, {"duration_days": "0.2"}, 2014, str(out))
    assert alone == inside and inside["pcrb_position_km"] > 0.0
    timeline = record["timeline"]
    assert [(task["task"], task["what"]) for task in timeline["tasks"]] == [("runs+bound", [2014]), ("runs", [2015])]
    for task in timeline["tasks"]:
        assert task["worker"] == timeline["parent"]["worker"] and task["start"] <= task["end"] and task["cpu_s"] > 0.0
    assert timeline["parent"]["start"] <= timeline["tasks"][0]["start"] <= timeline["page"]["start"]
    # on 2 local workers: the first seed's worker keeps its simulation and makes the bound from it after the
    # runs (a task of its own, on that worker), beside the figures: the same bound to the last bit
    two = tmp_path / "two"
    assert main(["montecarlo", S1, "--runs", "2", *SHORT, "--out", str(two), "--workers", "2"]) == 0
    record = json.loads((two / "campaign.json").read_text())
    assert record["posterior_crb"] == inside
    tasks = {task["task"]: task for task in record["timeline"]["tasks"]}
    assert sorted(task["task"] for task in record["timeline"]["tasks"]) == [
        "bound", "figures", "figures", "figures", "figures", "histogram", "runs", "runs"]
    assert sorted(task["what"] for task in record["timeline"]["tasks"] if task["task"] == "figures") == [
        ["ekf", "errors"], ["ekf", "nees"], ["ukf", "errors"], ["ukf", "nees"]]
    first = next(task for task in record["timeline"]["tasks"] if task["what"] == [2014])
    assert tasks["bound"]["worker"] == first["worker"] and tasks["bound"]["start"] >= first["end"]
    assert tasks["histogram"]["start"] >= tasks["bound"]["end"]
    # resumed with the first run finished: the bound is made again from a simulation of its own, on a worker
    (out / campaign_tasks.BOUND_FILE).unlink()
    os.remove(out / "run_001" / "summary.json")
    assert main(["montecarlo", S1, "--runs", "2", *SHORT, "--out", str(out), "--workers", "2"]) == 0
    again = json.loads((out / "campaign.json").read_text())
    assert again["posterior_crb"] == inside
    kinds = sorted(task["task"] for task in again["timeline"]["tasks"])
    # one run left for 2 workers: its filters apart, each a task simulating the run: the figures of the run
    assert kinds == ["bound", "figures", "figures", "figures", "figures", "histogram", "part", "part"]
    split = [task for task in again["timeline"]["tasks"] if task["task"] == "part"]
    assert sorted(task["what"] for task in split) == [[2015, "ekf"], [2015, "ukf"]]
    assert _figures(again["runs"][1]["filters"]) == _figures(record["runs"][1]["filters"])
    assert list(again["runs"][1]["filters"]) == ["ekf", "ukf"]
    assert {task["worker"] for task in again["timeline"]["tasks"]} != {again["timeline"]["parent"]["worker"]}


_DYING_WORKER = """
import functools, os, sys
from opnav.studies import campaign, campaign_tasks
original = campaign_tasks.run_batch

@functools.wraps(original)  # pickled by name: the forked workers find this one in the module
def dies(path, overrides, seeds, *rest):
    if seeds == [2015]:
        os._exit(9)
    return original(path, overrides, seeds, *rest)

campaign_tasks.run_batch = campaign.run_batch = dies
from opnav.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_worker_that_dies_is_one_line_and_the_campaign_resumes(tmp_path):
    """A local worker process that ends during its run (as a kill or the out-of-memory killer ends it): the
    command says so in one line (exit 2), and the same command then finishes the campaign. (A command of its
    own: its workers are forked from it, with the run that ends its worker.)"""
    import subprocess
    import sys

    out = tmp_path / "killed"
    command = ["montecarlo", S1, "--runs", "2", *SHORT, "--out", str(out), "--workers", "2"]
    died = subprocess.run([sys.executable, "-c", _DYING_WORKER, *command], capture_output=True, text=True)
    assert died.returncode == 2, died.stderr
    error = died.stderr.strip().splitlines()
    assert len(error) == 1 and "worker process ended abruptly" in error[0]
    assert main(command) == 0
    assert len(json.loads((out / "campaign.json").read_text())["runs"]) == 2
