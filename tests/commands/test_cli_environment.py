"""The environment refuses: an empty --out, a name the file system refuses, stdout on a full device --
each one line on stderr and exit 2, never a traceback."""

import subprocess
import sys
from pathlib import Path

from opnav.cli import main

ROOT = Path(__file__).resolve().parents[2]
S3 = str(ROOT / "samples" / "s3_geo.toml")


def test_an_empty_out_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["run", S3, "--out", ""]) == 2
    assert "--out must name a folder, got an empty name" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []  # nothing written into the working folder


def test_a_name_the_file_system_refuses_is_one_line(tmp_path, capsys):
    out = tmp_path / ("x" * 300)  # longer than a file name may be (255 bytes)
    assert main(["run", S3, "--set", "duration_hours=0.1", "--filters", "ekf", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "File name too long" in err and "Traceback" not in err


def test_stdout_on_a_full_device_is_one_line_on_stderr(tmp_path):
    with open("/dev/full", "w") as full:
        result = subprocess.run([sys.executable, "-m", "opnav.cli", "run", S3, "--set", "duration_hours=0.1",
                                 "--filters", "ekf", "--out", str(tmp_path / "out")],
                                stdout=full, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    assert result.returncode == 2, result.stderr
    assert "No space left on device" in result.stderr and "Traceback" not in result.stderr
    assert (tmp_path / "out" / "summary.json").is_file()  # what was written stays


def test_a_filter_list_that_names_no_filter_is_refused(tmp_path, capsys):
    for command in (["run", S3], ["montecarlo", S3, "--runs", "2"]):
        assert main([*command, "--filters", " , ", "--out", str(tmp_path / "x")]) == 2
        assert "names no filter" in capsys.readouterr().err


def test_campaign_workers_and_scheduler_addresses_are_checked(tmp_path, capsys):
    import os

    too_many = 4 * (os.cpu_count() or 1) + 1
    assert main(["montecarlo", S3, "--runs", "2", "--workers", str(too_many), "--out", str(tmp_path / "w")]) == 2
    assert f"--workers {too_many}: at most" in capsys.readouterr().err
    for address in ("not an address", "tcp://127.0.0.1:99999999", "udp://127.0.0.1:8786"):
        assert main(["montecarlo", S3, "--runs", "2", "--scheduler", address, "--out", str(tmp_path / "s")]) == 2
        assert "expected HOST:PORT" in capsys.readouterr().err


def test_a_negative_seed_is_refused_however_it_is_given(tmp_path, capsys):
    for command in (["run", S3, "--set", "seed=-1"], ["montecarlo", S3, "--runs", "2", "--set", "seed=-5"],
                    ["run", S3, "--seed", "-1"]):
        assert main([*command, "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err
        assert "seed must be" in err and "Traceback" not in err, err


def test_an_out_that_names_a_device_or_fifo_is_refused_and_left_alone(tmp_path, capsys):
    import os
    import stat

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    for target in (str(fifo), "/dev/null"):
        assert main(["run", S3, "--out", target]) == 2
        assert "not a regular file or folder" in capsys.readouterr().err
    assert stat.S_ISFIFO(fifo.stat().st_mode) and stat.S_ISCHR(os.stat("/dev/null").st_mode)


def test_a_folder_another_opnav_command_is_writing_is_refused(tmp_path, capsys):
    """Two runs of different seeds into one --out both exited 0 and left one seed's summary beside the
    other's measurements: the second is refused while the first holds the folder."""
    holder = subprocess.Popen([sys.executable, "-c", "import time\nfrom opnav.files import folder_lock\n"
                               f"with folder_lock({str(tmp_path / 'out')!r}):\n    print('held', flush=True)\n"
                               "    time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        for command in (["run", S3, "--set", "duration_hours=0.1"],
                        ["montecarlo", S3, "--runs", "2", "--set", "duration_hours=0.1"]):
            assert main([*command, "--filters", "ekf", "--out", str(tmp_path / "out")]) == 2
            assert "being written by another opnav command" in capsys.readouterr().err
    finally:
        holder.kill()
        holder.wait()
    assert not (tmp_path / "out" / "summary.json").exists()


def test_a_sweep_key_given_twice_is_refused(tmp_path, capsys):
    assert main(["montecarlo", S3, "--runs", "1", "--sweep", "duration_hours=0.1", "--sweep", "duration_hours=0.2",
                 "--out", str(tmp_path / "s")]) == 2
    assert "--sweep duration_hours is given twice; give its values once: --sweep duration_hours=0.1,0.2" in \
        capsys.readouterr().err


def test_an_arc_of_millions_of_epochs_is_refused_before_any_work(tmp_path, capsys):
    s1 = str(ROOT / "samples" / "s1_jul_both_0.1.toml")
    assert main(["run", s1, "--set", "duration_days=57", "--set", "step_s=1", "--out", str(tmp_path / "x")]) == 2
    assert "gives 4924800 epochs; allowed 2 to 1,000,000" in capsys.readouterr().err


def test_a_filter_given_twice_is_refused(tmp_path, capsys):
    assert main(["run", S3, "--filters", "ekf,ukf,ekf", "--out", str(tmp_path / "x")]) == 2
    assert "lists ekf more than once; give each filter once" in capsys.readouterr().err
