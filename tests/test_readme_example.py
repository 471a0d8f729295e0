"""The README's Python example runs as printed and its answer is consistent with the truth."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import numpy as np
from scipy.stats import chi2

README = Path(__file__).resolve().parents[1] / "README.md"


def _example() -> str:
    text = README.read_text()
    section = text[text.index("### Example"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_the_example_is_short():
    lines = [line for line in _example().splitlines() if line.strip()]
    assert len(lines) <= 12, f"the README's Python example has {len(lines)} lines"


def test_the_example_runs_and_its_estimate_is_inside_its_own_covariance(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the example needs nothing from the checkout
    namespace: dict = {}
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(_example(), "README example", "exec"), namespace)
    assert re.fullmatch(r"\d+ records, position error \d+ km -> \d+ km\n", printed.getvalue())
    frames, run, truth = namespace["frames"], namespace["run"], namespace["truth"]
    assert len(frames.records) >= 5 and run.filter == "ekf"
    assert np.all(run.history.accepted)
    # the final position error against the filter's own covariance: chi-square(3) when consistent
    d = run.track.states[-1, :3] - truth[-1, :3]
    P = run.track.covariances[-1, :3, :3]
    assert d @ np.linalg.solve(P, d) < chi2.ppf(0.9999, 3)
