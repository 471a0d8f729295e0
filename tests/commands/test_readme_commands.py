"""Every `opnav` command line in the README's code blocks runs as written (slow: full study runs)."""

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```\n(.*?)```", text, flags=re.S)
    commands = []
    for block in blocks:
        joined = block.replace("\\\n", " ")
        for line in joined.splitlines():
            line = line.strip()
            if line.startswith((".venv/bin/opnav ", "opnav ")) and "demo" not in line:
                commands.append(line)
    return commands


def test_the_readme_has_commands():
    assert any(" run samples/" in c for c in readme_commands())


@pytest.mark.slow
@pytest.mark.parametrize("command", readme_commands())
def test_readme_command_runs_as_written(command):
    args = shlex.split(command)
    args = [sys.executable, "-m", "opnav.cli"] + args[1:]
    result = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=3600)
    assert result.returncode == 0, result.stderr[-2000:]
