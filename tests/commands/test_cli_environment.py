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
