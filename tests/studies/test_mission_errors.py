"""A mission run file that is wrong ends `opnav run` in one line naming the key and what is accepted
(exit 2): a misspelt key, an unknown body, epochs outside DE421, the OEM or the kernels."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from opnav.cli import main
from opnav.errors import InputError
from opnav.studies import mission
from opnav.studies.settings import load_run_file

SAMPLE = Path(__file__).resolve().parents[2] / "samples" / "cislunar.toml"
HEAD = '[scenario]\nstudy = "mission"\n\n[settings]\n'


@pytest.fixture(scope="module")
def short_arc(tmp_path_factory):
    """An SPK and an OEM of the sample's first 6 hours (the arc runs 4 days)."""
    from opnav.ccsds import write_oem
    from opnav.ephemeris.spk_writer import write_spk

    folder = tmp_path_factory.mktemp("mission_errors")
    settings = mission.Settings()
    t_start, _ = mission.record_epochs(settings)
    nodes = t_start + np.arange(0.0, 6 * 3600.0 + 1.0, 600.0)
    arc = mission.truth_states(settings, nodes)
    write_spk(folder / "probe.bsp", nodes, arc, body=-77, center=399)
    write_oem(folder / "probe.oem", nodes, arc, center="EARTH")
    return folder


def _run(folder: Path, settings: str, capsys, *extra: str) -> tuple[int, str]:
    path = folder / "run.toml"
    path.write_text(HEAD + settings)
    code = main(["run", str(path), "--out", str(folder / "out"), "--no-progress", *extra])
    return code, capsys.readouterr().err.strip()


@pytest.mark.parametrize("settings, words", [
    ("noise_arcsecs = 3.0\n", ["noise_arcsecs", "did you mean 'noise_arcsec'"]),
    ('targets = ["vulcan"]\n', ["targets", "vulcan", "moon"]),
    ('gravity = ["earth", "phobos"]\n', ["gravity", "phobos", "sun"]),
    ('gravity = ["moon", "sun"]\n', ["gravity must include center 'earth'"]),
    ("noise_arcsec = [1.0, 2.0, 3.0]\n", ["noise_arcsec", "one per target", "moon, earth"]),
    ('start = "2070-01-01T00:00:00"\nstop = "2070-01-02T00:00:00"\n', ["start 2070-01-01T00:00:00", "outside DE421"]),
    ('stop = "2027-03-09T00:00:00"\n', ["stop", "must be after start"]),
    ('start = "2027-03-10T01:00:00Z"\n', ["start", "UTC date", "tdb"]),
    ('state_epoch = "2027-02-30T00:00:00"\n', ["state_epoch", "cannot parse"]),
    ('trajectory = "spk"\n', ["trajectory = 'spk' needs spk_body"]),
    ('trajectory = "oem"\n', ["trajectory = 'oem' needs oem_file"]),
    ('oem_file = "probe.oem"\n', ["oem_file is read only with trajectory = 'oem'"]),
    ('trajectory = "oem"\noem_file = "nothere.oem"\n', ["oem_file", "nothere.oem", "not a file"]),
    ('trajectory = "spk"\nspk_body = "-77"\nkernels = ["nothere.bsp"]\n', ["kernels", "nothere.bsp", "not a file"]),
])
def test_a_bad_setting_is_one_line(short_arc, capsys, settings, words):
    code, err = _run(short_arc, settings, capsys)
    assert code == 2
    assert "\n" not in err and "Traceback" not in err and err.startswith("opnav run: error:"), err
    for word in words:
        assert word in err, f"{word!r} not in {err!r}"


def test_an_arc_outside_the_oem_names_the_file_and_both_spans(short_arc, capsys):
    code, err = _run(short_arc, 'trajectory = "oem"\noem_file = "probe.oem"\n', capsys)
    assert code == 2 and "\n" not in err
    assert "probe.oem covers 2027-03-10T01:00:00 TDB" in err and "to 2027-03-10T07:00:00 TDB" in err
    assert "the arc runs from 2027-03-10T01:00:00 TDB" in err and "to 2027-03-14T00:00:00 TDB" in err


def test_an_arc_outside_the_kernels_names_the_kernel_the_body_and_the_epoch(short_arc, capsys):
    code, err = _run(short_arc, 'trajectory = "spk"\nspk_body = "-77"\nkernels = ["probe.bsp"]\n', capsys)
    assert code == 2 and "\n" not in err and "SPICE(" not in err
    assert "kernels: kernels de421.bsp, probe.bsp do not cover '-77'" in err
    assert "at 2027-03-14T00:00:00 TDB" in err and "probe.bsp 2027-03-10T01:00:00 TDB" in err


def test_a_body_the_kernels_lack_is_named(short_arc, capsys):
    code, err = _run(short_arc, 'trajectory = "spk"\nspk_body = "-78"\nkernels = ["probe.bsp"]\n'
                                'stop = "2027-03-10T06:00:00"\n', capsys)
    assert code == 2 and "\n" not in err
    assert "'-78' (NAIF -78) is in no SPK" in err and "probe.bsp" in err


def test_inside_the_kernels_it_runs_and_set_changes_a_setting(short_arc, capsys):
    code, err = _run(short_arc, 'trajectory = "spk"\nspk_body = "-77"\nkernels = ["probe.bsp"]\n'
                                'stop = "2027-03-10T06:00:00"\n', capsys, "--filters", "ekf",
                     "--set", "targets=moon", "--set", "noise_arcsec=2")
    assert code == 0, err
    run = load_run_file(short_arc / "run.toml", {"targets": "moon", "noise_arcsec": "2"})
    assert run.settings.targets == ("moon",) and run.settings.noise_arcsec == 2.0
    assert (short_arc / "out" / "report.html").is_file()


NUMERIC = [f.name for f in dataclasses.fields(mission.Settings) if f.init and f.type in ("float", "int")]


@pytest.mark.parametrize("key", NUMERIC)
@pytest.mark.parametrize("value", ["nan", "inf", "1e300", "1e-300", "-1", "0"])
def test_extreme_numbers_are_refused_in_one_line_or_usable(key, value):
    try:
        run = load_run_file(SAMPLE, {key: value})
    except InputError as exc:
        assert "\n" not in str(exc) and key in str(exc), str(exc)
        return
    number = getattr(run.settings, key)
    assert math.isfinite(number) and (number == 0.0 or 0.0 < number * number < math.inf)
