"""CCSDS files a run writes, as other readers see them (issue 36 item 3): the spacecraft named in
the OEMs and the TDM, INTERPOLATION in the OEMs, TDMs the ``ccsds-ndm`` parser reads with the same
numbers, a ``radec_pair``'s cross-covariance kept beside the TDM, and the demo's TDM navigating to the
CSV's estimate. ``benchmarks/ccsds_readers.py`` adds the second independent reader (``ccsds-ndm-py``)."""

from __future__ import annotations

import pytest

from opnav.errors import InputError
from opnav.studies.settings import load_run_file

RUN = """[scenario]
study = "s1"
name = "cruise"
{extra}
[settings]
month = "jul"
"""


def test_the_spacecraft_is_the_run_files_or_its_name(tmp_path):
    named = tmp_path / "named.toml"
    named.write_text(RUN.format(extra='spacecraft = "MAVEN"'))
    plain = tmp_path / "plain.toml"
    plain.write_text(RUN.format(extra=""))
    run = load_run_file(named)
    assert run.spacecraft == "MAVEN" and run.describe()["spacecraft"] == "MAVEN"
    default = load_run_file(plain)
    # the default leaves the run's identity (its stage hashes) as it was
    assert default.spacecraft == "cruise" and "spacecraft" not in default.describe()


@pytest.mark.parametrize("value", ['" MAVEN"', '""', '"MA\\nVEN"'])
def test_a_spacecraft_name_a_ccsds_file_cannot_hold_is_refused(tmp_path, value):
    path = tmp_path / "bad.toml"
    path.write_text(RUN.format(extra=f"spacecraft = {value}"))
    with pytest.raises(InputError) as caught:
        load_run_file(path)
    message = str(caught.value)
    assert str(path) in message and "[scenario] spacecraft" in message and "\n" not in message


# ---- the demo's records: a TDM and its sidecar navigate as the CSV does

import importlib.resources  # noqa: E402
import json  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from opnav.cli import main  # noqa: E402
from opnav.records import split_radec_pairs, write_csv  # noqa: E402

DEMO_SCENARIO = Path(__file__).resolve().parents[1] / "opnav" / "data" / "demo.toml"


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    """The demo run's simulate stage (S1 from pixels, its run file) over its first 16 hourly frames:
    measurements.csv, measurements.tdm and its sidecar as ``opnav run`` writes them."""
    from opnav.studies.runner import simulate_stage

    path = Path(str(importlib.resources.files("opnav").joinpath("data", "demo_run.toml")))
    run = load_run_file(path, {"duration_days": str(16 * 3600.0 / 86400.0)})
    out = tmp_path_factory.mktemp("demo16")
    sim, _, _ = simulate_stage(run, out, lambda message: None, "images", workers=1)
    return out, sim, run


def _navigate(measurements: Path, out: Path) -> dict:
    assert main(["navigate", str(measurements), "--scenario", str(DEMO_SCENARIO), "--out", str(out),
                 "--no-progress"]) == 0
    return json.loads((out / "summary.json").read_text())


def test_the_demo_tdm_navigates_to_the_csv_estimate(demo_run, tmp_path, capsys):
    """The frames that hold both moons give radec_pair records (their shared attitude error as a
    cross-covariance); the TDM holds each moon's direction and the sidecar the pair, so navigating the
    TDM takes the same records and lands on the CSV's estimate to 1e-6 of its sigma. Without the
    pairs taken as independent directions (what the TDM alone held) the estimate moves."""
    out, sim, run = demo_run
    pairs = sum(rec.kind == "radec_pair" for rec in sim.records)
    assert pairs >= 3 and len(sim.records) > pairs  # both kinds are in the test
    csv_run = _navigate(out / "measurements.csv", tmp_path / "csv")
    tdm_run = _navigate(out / "measurements.tdm", tmp_path / "tdm")
    assert tdm_run["records"] == csv_run["records"] == len(sim.records)
    sigma = np.array(csv_run["final"]["sigma"])
    moved = np.abs(np.array(tdm_run["final"]["state"]) - csv_run["final"]["state"]) / sigma
    assert moved.max() < 1e-6, moved
    np.testing.assert_allclose(tdm_run["final"]["sigma"], sigma, rtol=1e-6)

    # what the TDM alone held before the sidecar: each pair as two independent directions
    write_csv(tmp_path / "split.csv", split_radec_pairs(list(sim.records)))
    split = _navigate(tmp_path / "split.csv", tmp_path / "split")
    assert split["records"] == len(sim.records) + pairs
    lost = np.abs(np.array(split["final"]["state"]) - csv_run["final"]["state"]) / sigma
    assert lost.max() > 1e3 * moved.max(), (lost, moved)
    capsys.readouterr()


def test_the_run_names_its_spacecraft_in_the_tdm_and_oem(demo_run, tmp_path):
    from opnav.ccsds import read_oem
    from ccsds_ndm.ndm_io import NdmIo

    out, sim, run = demo_run
    tdm = NdmIo().from_path(out / "measurements.tdm")
    assert {segment.metadata.participant_1 for segment in tdm.body.segment} == {run.spacecraft} == {"demo"}
    _navigate(out / "measurements.tdm", tmp_path / "nav")
    oem = read_oem(tmp_path / "nav" / "estimates.oem")
    # opnav navigate names the spacecraft of its --scenario file ([scenario] name of demo.toml or its stem)
    assert oem.object_name == oem.object_id and oem.object_name not in ("ekf", "opnav")
    assert (oem.interpolation, oem.interpolation_degree) == ("HERMITE", 3)


# ---- what ccsds-ndm (an independent parser) reads in opnav's files

import math  # noqa: E402

from ccsds_ndm.ndm_io import NdmIo  # noqa: E402

from opnav.ccsds import read_oem, read_tdm, tdm_sidecar, write_oem, write_tdm  # noqa: E402
from opnav.records import Measurement  # noqa: E402


def pair_records(n: int = 6, seed: int = 5) -> list[Measurement]:
    """Frames alternating between both moons (a radec_pair with a cross-covariance) and Phobos alone,
    each record with a covariance of its own (as the image stage gives them)."""
    rng = np.random.default_rng(seed)
    records = []
    for k in range(n):
        t = 4.586e8 + 3600.0 * k + 0.25  # off a whole second
        a = rng.normal(size=(4, 4)) * 1e-7
        cov = a @ a.T + 1e-14 * np.eye(4)
        value = [rng.uniform(0, 2 * np.pi), rng.uniform(-1.2, 1.2), rng.uniform(0, 2 * np.pi), rng.uniform(-1.2, 1.2)]
        if k % 2:
            records.append(Measurement(t, "radec", value[:2], cov[:2, :2], target="phobos", sensor="nac",
                                       frame_id=f"frame_{k}", flags=8))
        else:
            records.append(Measurement(t, "radec_pair", value, cov, target="phobos+deimos", sensor="nac",
                                       frame_id=f"frame_{k}", flags=8 | 16))
    return records


@pytest.mark.parametrize("name", ["pairs.tdm", "pairs.xml"])
def test_a_radec_pair_keeps_its_cross_covariance_through_the_tdm_and_its_sidecar(tmp_path, name):
    records = pair_records()
    path = tmp_path / name
    assert write_tdm(path, records, participant="MAVEN") == len(records)
    assert tdm_sidecar(path) == tmp_path / f"{name}.cov.csv" and tdm_sidecar(path).is_file()

    # an independent parser sees one segment per moon and every direction of every record
    tdm = NdmIo().from_path(path)
    by_target = {}
    for segment in tdm.body.segment:
        meta = segment.metadata
        assert (meta.participant_1, meta.path, meta.angle_type.value) == ("MAVEN", "2,1", "RADEC")
        by_target[meta.participant_2] = [(obs.epoch, obs.angle_1.value if obs.angle_1 else obs.angle_2.value)
                                         for obs in segment.data.observation]
    assert sorted(by_target) == ["DEIMOS", "PHOBOS"]
    assert len(by_target["PHOBOS"]) == 2 * len(records) and len(by_target["DEIMOS"]) == len(records)
    first_deimos = records[0].value[2:]
    assert by_target["DEIMOS"][0][1] == pytest.approx(math.degrees(first_deimos[0]), abs=1e-12)
    assert by_target["DEIMOS"][1][1] == pytest.approx(math.degrees(first_deimos[1]), abs=1e-12)

    back = read_tdm(path)
    assert [rec.kind for rec in back] == [rec.kind for rec in records]
    for got, want in zip(back, records):
        assert (got.t_tdb_s, got.target, got.sensor, got.frame_id, got.flags) == (
            want.t_tdb_s, want.target, want.sensor, want.frame_id, want.flags)
        np.testing.assert_array_equal(got.covariance, want.covariance)  # the cross-covariance included
        np.testing.assert_allclose(got.value, want.value, rtol=1e-14, atol=1e-15)


def test_a_sidecar_of_another_tdm_is_refused_naming_it(tmp_path):
    records = pair_records()
    write_tdm(tmp_path / "a.tdm", records)
    write_tdm(tmp_path / "b.tdm", records[:-1])
    tdm_sidecar(tmp_path / "b.tdm").replace(tdm_sidecar(tmp_path / "a.tdm"))
    with pytest.raises(InputError) as caught:
        read_tdm(tmp_path / "a.tdm")
    message = str(caught.value)
    assert str(tdm_sidecar(tmp_path / "a.tdm")) in message and "another TDM" in message and "\n" not in message
    write_tdm(tmp_path / "c.tdm", records)
    sidecar = tdm_sidecar(tmp_path / "c.tdm")
    sidecar.write_text(sidecar.read_text().replace(" ", " x", 1))
    with pytest.raises(InputError, match=r"c\.tdm\.cov\.csv: line 2: covariance_rad2 must be 16 finite numbers"):
        read_tdm(tmp_path / "c.tdm")


def test_records_sharing_one_covariance_carry_it_in_the_tdm_itself(tmp_path):
    """Measurement mode gives each target one covariance: the segment's COMMENT holds it, so the TDM
    alone reads back exactly; the blank line ccsds-ndm-py cannot read is not before DATA_START."""
    cov = np.array([[2.0e-12, 1.0e-14], [1.0e-14, 3.0e-12]])
    records = [Measurement(4.5e8 + 10.0 * k, "radec", [0.1 * k, 0.2], cov, target=("phobos", "deimos")[k % 2])
               for k in range(8)]
    path = tmp_path / "same.tdm"
    write_tdm(path, records)
    text = path.read_text()
    assert "META_STOP\nDATA_START" in text and "META_STOP\n\n" not in text
    tdm_sidecar(path).unlink()
    back = read_tdm(path)
    assert len(back) == len(records)
    for got in back:
        np.testing.assert_array_equal(got.covariance, cov)


# ---- OEMs: the object, and the interpolation they recommend

@pytest.mark.parametrize("name", ["arc.oem", "arc.xml"])
def test_oems_carry_the_object_and_the_interpolation_every_reader_sees(tmp_path, name):
    t = 4.5e8 + 3600.0 * np.arange(5)
    states = np.tile([1.5e8, 2.0e7, 1.0e6, -3.0, 29.0, 0.5], (5, 1))
    write_oem(tmp_path / name, t, states, object_name="demo", object_id="demo")
    oem = NdmIo().from_path(tmp_path / name)
    meta = oem.body.segment[0].metadata
    assert (meta.object_name, meta.object_id, meta.interpolation, meta.interpolation_degree) == (
        "demo", "demo", "HERMITE", 3)
    back = read_oem(tmp_path / name)
    assert (back.object_name, back.interpolation, back.interpolation_degree) == ("demo", "HERMITE", 3)
    write_oem(tmp_path / f"none_{name}", t, states, interpolation=None)
    assert NdmIo().from_path(tmp_path / f"none_{name}").body.segment[0].metadata.interpolation is None
    with pytest.raises(InputError, match="interpolation must be"):
        write_oem(tmp_path / f"bad_{name}", t, states, interpolation=("SPLINE", 3))


def test_the_recommended_interpolation_holds_the_trajectory_between_the_runs_epochs(tmp_path):
    """Cubic Hermite (the OEM's INTERPOLATION = HERMITE, degree 3) between S1's hourly states of a
    heliocentric orbit (1 au, circular) reproduces the orbit at the half-hours to better than 1 m, far
    inside any filter sigma (hundreds of km)."""
    from scipy.interpolate import CubicHermiteSpline

    from opnav.constants import AU_KM, GM_KM3_S2

    n = math.sqrt(GM_KM3_S2["sun"] / AU_KM ** 3)

    def orbit(t):
        angle = n * (t - 4.5e8)
        return np.column_stack([AU_KM * np.cos(angle), AU_KM * np.sin(angle), 0.0 * angle,
                                -AU_KM * n * np.sin(angle), AU_KM * n * np.cos(angle), 0.0 * angle])

    t = 4.5e8 + 3600.0 * np.arange(25)
    write_oem(tmp_path / "orbit.oem", t, orbit(t))
    oem = read_oem(tmp_path / "orbit.oem")
    assert (oem.interpolation, oem.interpolation_degree) == ("HERMITE", 3)
    spline = CubicHermiteSpline(oem.t_tdb_s, oem.states[:, :3], oem.states[:, 3:])
    middle = t[:-1] + 1800.0
    assert np.max(np.linalg.norm(spline(middle) - orbit(middle)[:, :3], axis=1)) < 1e-3  # km


@pytest.mark.parametrize("line, message", [
    ("ANGLE_1                  = 2014-07-15T01:00:00.000000  12.5x", r"ANGLE_1 at 2014-07-15T01:00:00\.000000 \(line \d+\) is not a finite number"),
    ("ANGLE_9                  = 2014-07-15T01:00:00.000000  12.5", r"line \d+: not a TDM observation"),
    ("ANGLE_1 2014-07-15T01:00:00.000000", r"line \d+: not a TDM observation"),
])
def test_a_broken_observation_line_is_refused_naming_its_line(tmp_path, line, message):
    """KVN observation lines are read by opnav (ccsds-ndm parses the header and metadata): a line that is
    not ``KEYWORD = EPOCH VALUE`` with a TDM keyword and a number is refused, naming the file and line."""
    path = tmp_path / "obs.tdm"
    write_tdm(path, pair_records()[:2])
    tdm_sidecar(path).unlink()
    text = path.read_text().replace("DATA_START\n", f"DATA_START\n{line}\n", 1)
    path.write_text(text)
    with pytest.raises(InputError, match=rf"obs\.tdm: .*{message}"):
        read_tdm(path, sigma_rad=1e-6)
