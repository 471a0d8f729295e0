"""opnav.files: durable atomic outputs with the umask's permissions; inputs refused when they are not
regular files of a sane size."""

import os
import stat
from pathlib import Path

import pytest

from opnav.errors import InputError
from opnav.files import atomic_output, atomic_write_text, check_input_file

DEMO = Path(__file__).resolve().parent.parent / "opnav" / "data" / "demo.toml"


def test_an_output_gets_the_umask_permissions_and_replaces_the_old_file_whole(tmp_path):
    target = tmp_path / "sub" / "result.json"
    old = os.umask(0o027)
    try:
        atomic_write_text(target, "first")
    finally:
        os.umask(old)
    assert target.read_text() == "first"
    assert stat.S_IMODE(target.stat().st_mode) == 0o640  # 0666 less umask 027, not mkstemp's 0600
    with pytest.raises(RuntimeError):
        with atomic_output(target) as handle:
            handle.write(b"half of a second version")
            raise RuntimeError("the writer fails midway")
    assert target.read_text() == "first"  # untouched, and no temporary file left beside it
    assert sorted(p.name for p in target.parent.iterdir()) == ["result.json"]


def test_outputs_replace_regular_files_only(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="not a regular file"):
        atomic_write_text(fifo, "x")
    assert stat.S_ISFIFO(fifo.stat().st_mode)


def test_inputs_that_would_hang_or_exhaust_memory_are_refused_in_one_line(tmp_path):
    fifo = tmp_path / "run.toml"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="not a regular file"):
        check_input_file(fifo, "run file")
    with pytest.raises(InputError, match="not a regular file"):
        check_input_file("/dev/zero", "run file")
    with pytest.raises(InputError, match="is a folder"):
        check_input_file(tmp_path, "run file")
    with pytest.raises(InputError, match="not found"):
        check_input_file(tmp_path / "missing.toml", "run file")
    big = tmp_path / "big.toml"
    big.write_bytes(b"#" * 2000)
    with pytest.raises(InputError, match="too large for a run file"):
        check_input_file(big, "run file", max_bytes=1000)
    assert check_input_file(big, "run file", max_bytes=2000) == big


def test_the_commands_refuse_a_fifo_or_a_device_as_a_run_or_measurement_file(tmp_path, capsys):
    from opnav.cli import main

    fifo = tmp_path / "run.toml"
    os.mkfifo(fifo)
    assert main(["run", str(fifo), "--out", str(tmp_path / "out")]) == 2
    assert "not a regular file" in capsys.readouterr().err
    assert main(["run", "/dev/zero", "--out", str(tmp_path / "out")]) == 2
    assert "not a regular file" in capsys.readouterr().err
    assert main(["navigate", "/dev/zero", "--scenario", str(DEMO), "--out", str(tmp_path / "n")]) == 2
    assert "not a regular file" in capsys.readouterr().err


def test_an_output_folder_is_held_by_one_process_at_a_time(tmp_path):
    import subprocess
    import sys
    import time

    from opnav.files import LOCK_NAME, folder_lock

    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom opnav.files import folder_lock\n"
                               f"with folder_lock({str(tmp_path)!r}):\n    print('held', flush=True)\n"
                               "    time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(InputError, match=rf"being written by another opnav command \(process {holder.pid}\)"):
            with folder_lock(tmp_path):
                pass
    finally:
        holder.kill()
        holder.wait()
    time.sleep(0.05)
    with folder_lock(tmp_path) as held:  # the kernel let go when the holder died
        assert (held / LOCK_NAME).read_text() == str(os.getpid())


_KILLED_WRITER = r"""
import os, signal, sys
import opnav.files as files

def killed_at_rename(src, dst):  # the bytes are written and fsynced; the process dies before the rename
    os.kill(os.getpid(), signal.SIGKILL)

files.os.replace = killed_at_rename
files.atomic_write_text(sys.argv[1], "second version, complete " * 1000)
"""


@pytest.mark.parametrize("had_old", [True, False])
def test_a_writer_killed_between_write_and_rename_leaves_no_empty_or_partial_output(tmp_path, had_old):
    """SIGKILL after the temporary file is written and synced, before ``os.replace``: the output name
    holds the old file whole (or nothing, if there was none), never an empty or half-written one; what
    is left is only the hidden ``.NAME.*.tmp`` beside it, which no reader of NAME opens."""
    import signal
    import subprocess
    import sys

    target = tmp_path / "summary.json"
    if had_old:
        target.write_text("first")
    child = subprocess.run([sys.executable, "-c", _KILLED_WRITER, str(target)], capture_output=True)
    assert child.returncode == -signal.SIGKILL
    if had_old:
        assert target.read_text() == "first"
    else:
        assert not target.exists()
    leftovers = [p.name for p in tmp_path.iterdir() if p.name != "summary.json"]
    assert all(name.startswith(".summary.json.") and name.endswith(".tmp") for name in leftovers), leftovers
