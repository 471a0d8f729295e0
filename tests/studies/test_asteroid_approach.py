"""The asteroid-approach sample's inputs: its SPK is the one `opnav kernel` writes from its elements file,
and the spacecraft's stated state makes the approach the sample's comments say."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from opnav.cli import main
from opnav.ephemeris.planets import default_kernel_path
from opnav.ephemeris.spice import SpiceEphemeris

SAMPLES = Path(__file__).resolve().parents[2] / "samples"


def test_the_shipped_spk_is_what_opnav_kernel_writes_from_the_elements(tmp_path):
    """`opnav kernel --elements samples/asteroid_elements.toml` (the command the sample states) writes an
    SPK whose states equal the shipped asteroid.bsp's to < 1 m over the span, and the body's orbit
    is the stated one (a = 1.25 au: its vis-viva speed)."""
    out = tmp_path / "asteroid.bsp"
    assert main(["kernel", "--elements", str(SAMPLES / "asteroid_elements.toml"), "--out", str(out)]) == 0
    shipped = SpiceEphemeris([default_kernel_path(), SAMPLES / "asteroid.bsp", SAMPLES / "asteroid.tpc"])
    fresh = SpiceEphemeris([default_kernel_path(), out, SAMPLES / "asteroid.tpc"])
    t = np.linspace(shipped.coverage[2999038][0][1][0, 0], shipped.coverage[2999038][0][1][0, 1], 97)
    r_shipped, v_shipped = shipped.state("opnav38", t, center="sun")
    r_fresh, _ = fresh.state("opnav38", t, center="sun")
    assert np.max(np.linalg.norm(r_shipped - r_fresh, axis=1)) < 1e-3
    a_km, gm_sun = 1.87e8, 1.32712440041e11
    r, v = np.linalg.norm(r_shipped, axis=1), np.linalg.norm(v_shipped, axis=1)
    np.testing.assert_allclose(v**2, gm_sun * (2.0 / r - 1.0 / a_km), rtol=1e-6)


def test_the_sample_approaches_from_a_million_km_to_a_thousand():
    from opnav.studies import mission
    from opnav.studies.settings import load_run_file

    run = load_run_file(SAMPLES / "asteroid_approach.toml")
    settings = run.settings
    t = np.array([mission._epoch(settings, "start"), mission._epoch(settings, "stop")])
    states = mission.truth_states(settings, t)
    eph = mission.truth_ephemeris(settings)
    body = eph.state("opnav38", t, center="sun")[0]
    ranges = np.linalg.norm(states[:, :3] - body, axis=1)
    assert ranges[0] == pytest.approx(1.0e6, rel=0.05)
    assert ranges[1] == pytest.approx(1000.0, rel=1e-3)
    # seen at ~45 deg phase at the end (sunward side)
    to_sun, to_craft = -body[1] / np.linalg.norm(body[1]), (states[1, :3] - body[1]) / ranges[1]
    assert np.degrees(np.arccos(to_sun @ to_craft)) == pytest.approx(45.0, abs=1.0)
