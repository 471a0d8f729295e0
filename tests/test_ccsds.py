"""CCSDS OEM and TDM files (opnav.ccsds): round trips in KVN and XML, foreign TDMs, refusals."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from ccsds_ndm.mapping import NDMFileFormats
from ccsds_ndm.models import ndmxml4
from ccsds_ndm.ndm_io import NdmIo

from opnav.ccsds import OemData, read_oem, read_tdm, write_oem, write_tdm
from opnav.errors import InputError
from opnav.frames import angle_between, radec_to_unit
from opnav.records import Measurement

MICROSECOND = 1e-6
MAS = np.radians(1.0 / 3.6e6)


def ephemeris(n: int = 20, seed: int = 7) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Epochs (TDB s past J2000, not on whole microseconds), Mars-centred ICRF states, SPD covariances."""
    rng = np.random.default_rng(seed)
    t = 4.5e8 + np.cumsum(rng.uniform(30.0, 90.0, n))
    position = rng.normal(size=(n, 3))
    position *= rng.uniform(3600.0, 10_000.0, (n, 1)) / np.linalg.norm(position, axis=1, keepdims=True)
    velocity = rng.normal(scale=2.0, size=(n, 3))
    scale = np.array([1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])  # km, km/s
    a = rng.normal(size=(n, 6, 6))
    cov = scale[:, None] * (a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(6)) * scale[None, :]
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    return t, np.hstack([position, velocity]), cov


def radec_records(seed: int = 3) -> list[Measurement]:
    rng = np.random.default_rng(seed)
    covs = [np.array([[1e-10, 2e-12], [2e-12, 4e-10]]), np.diag([2.5e-9, 2.5e-9])]
    records = []
    for k in range(16):
        target = ("phobos", "deimos")[k % 2]
        sensor = ("nac", "wac")[(k // 2) % 2]
        records.append(Measurement(4.5e8 + 61.0 * k + rng.uniform(0, 1), "radec",
                                   [rng.uniform(0.0, 2.0 * np.pi), rng.uniform(-1.5, 1.5)],
                                   covs[(k // 4) % 2], target=target, sensor=sensor))
    return records


def key(rec: Measurement) -> tuple:
    return round(rec.t_tdb_s, 3), rec.target, rec.sensor


# --- OEM ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("name, first", [("arc.oem", "CCSDS_OEM_VERS"), ("arc.xml", "<?xml")])
def test_oem_round_trip_keeps_states_covariances_and_names(tmp_path, name, first):
    t, states, cov = ephemeris()
    path = tmp_path / name
    write_oem(path, t, states, cov, object_name="MAVEN", object_id="2013-063A", center="MARS",
              comment="opnav test arc\nsecond line")
    text = path.read_text()
    assert text.startswith(first) and "TDB" in text
    assert not list(tmp_path.glob(".*tmp")), "the temporary file must be renamed away"
    back = read_oem(path)
    assert isinstance(back, OemData)
    assert np.max(np.abs(back.t_tdb_s - t)) <= MICROSECOND
    np.testing.assert_allclose(back.states, states, rtol=1e-14, atol=0.0)
    np.testing.assert_allclose(back.covariances, cov, rtol=1e-14, atol=0.0)
    np.testing.assert_array_equal(back.covariances, np.swapaxes(back.covariances, 1, 2))
    assert (back.center, back.ref_frame, back.object_name, back.object_id) == ("MARS", "ICRF", "MAVEN", "2013-063A")
    with pytest.raises(ValueError):
        back.states[0, 0] = 1.0  # read-only, like Measurement arrays


def test_oem_without_covariance(tmp_path):
    t, states, _ = ephemeris(5)
    write_oem(tmp_path / "arc.oem.txt", t, states)
    assert "COVARIANCE_START" not in (tmp_path / "arc.oem.txt").read_text()
    back = read_oem(tmp_path / "arc.oem.txt")
    assert back.covariances is None
    np.testing.assert_allclose(back.states, states, rtol=1e-14, atol=0.0)


def test_oem_in_utc_is_converted_and_an_unknown_time_system_refused(tmp_path):
    t, states, _ = ephemeris(3)
    write_oem(tmp_path / "arc.oem", t, states)
    text = (tmp_path / "arc.oem").read_text()
    (tmp_path / "utc.oem").write_text(text.replace("= TDB", "= UTC"))
    # the same calendar text read as UTC is TDB - UTC = 32.184 s + 35 leap seconds (+- 2 ms) later in 2014
    np.testing.assert_allclose(read_oem(tmp_path / "utc.oem").t_tdb_s - t, 67.184, atol=3e-3)
    (tmp_path / "gps.oem").write_text(text.replace("= TDB", "= GPS"))
    with pytest.raises(InputError, match=r"gps\.oem.*TIME_SYSTEM GPS is not supported"):
        read_oem(tmp_path / "gps.oem")


def test_oem_3_kvn_is_read(tmp_path):
    t, states, cov = ephemeris(4)
    write_oem(tmp_path / "arc.oem", t, states, cov)
    text = (tmp_path / "arc.oem").read_text().replace("CCSDS_OEM_VERS           = 2.0", "CCSDS_OEM_VERS = 3.0")
    (tmp_path / "v3.oem").write_text(text)
    back = read_oem(tmp_path / "v3.oem")
    np.testing.assert_allclose(back.states, states, rtol=1e-14, atol=0.0)
    np.testing.assert_allclose(back.covariances, cov, rtol=1e-14, atol=0.0)


def test_oem_segments_are_joined_and_an_overlap_refused(tmp_path, caplog):
    t, states, cov = ephemeris(6)
    write_oem(tmp_path / "a.oem", t[:3], states[:3], cov[:3])
    write_oem(tmp_path / "b.oem", t[3:], states[3:])
    write_oem(tmp_path / "c.oem", t[2:], states[2:])
    first = (tmp_path / "a.oem").read_text()
    for name, other in (("ab.oem", "b.oem"), ("ac.oem", "c.oem")):
        text = (tmp_path / other).read_text()
        (tmp_path / name).write_text(first + text[text.index("META_START"):])
    with caplog.at_level(logging.WARNING, logger="opnav.ccsds"):
        back = read_oem(tmp_path / "ab.oem")
    assert "3 of 6 epochs have no covariance block" in caplog.text
    np.testing.assert_allclose(back.states, states, rtol=1e-14, atol=0.0)
    np.testing.assert_allclose(back.covariances[:3], cov[:3], rtol=1e-14, atol=0.0)
    assert np.all(np.isnan(back.covariances[3:]))
    with pytest.raises(InputError, match=r"ac\.oem: OEM epochs do not increase"):
        read_oem(tmp_path / "ac.oem")


def test_oem_epochs_day_of_year_read_and_a_bad_date_refused(tmp_path):
    t, states, _ = ephemeris(3)
    write_oem(tmp_path / "arc.oem", t, states)
    text = (tmp_path / "arc.oem").read_text()
    calendar = next(line for line in text.splitlines() if line.startswith("STOP_TIME")).split("=")[1].strip()
    assert calendar.startswith("2014-04-05T")  # day 95 of 2014; the last state and STOP_TIME
    (tmp_path / "doy.oem").write_text(text.replace(calendar, calendar.replace("2014-04-05T", "2014-095T")))
    np.testing.assert_array_equal(read_oem(tmp_path / "doy.oem").t_tdb_s, read_oem(tmp_path / "arc.oem").t_tdb_s)
    (tmp_path / "bad.oem").write_text(text.replace(calendar, calendar.replace("-04-", "-13-")))
    with pytest.raises(InputError, match=r"bad\.oem: OEM segment 1: cannot read epoch '2014-13-05"):
        read_oem(tmp_path / "bad.oem")


# --- TDM ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["angles.tdm", "angles.xml"])
def test_tdm_round_trip_keeps_angles_covariance_target_and_sensor(tmp_path, name):
    records = radec_records()
    others = [Measurement(4.5e8, "position", [1.0, 2.0, 3.0], np.eye(3), target="mars"),
              Measurement(4.5e8 + 1.0, "los", [1.0, 0.0, 0.0], 1e-10 * np.eye(3), target="phobos")]
    path = tmp_path / name
    assert write_tdm(path, records + others, participant="MAVEN") == len(records)

    tdm = NdmIo().from_path(path)  # what another reader sees
    assert tdm.version == "2.0" and len(tdm.body.segment) == 4  # 2 targets x 2 sensors
    for segment in tdm.body.segment:
        meta = segment.metadata
        assert (meta.time_system, meta.participant_1, meta.path) == ("TDB", "MAVEN", "2,1")
        assert meta.participant_2 in ("PHOBOS", "DEIMOS")
        assert (meta.angle_type.value, meta.reference_frame.value, meta.mode.value) == ("RADEC", "ICRF", "SEQUENTIAL")
        assert all(0.0 <= obs.angle_1.value < 360.0 for obs in segment.data.observation if obs.angle_1)
        # each segment's records alternate between two covariances: no one covariance comment for them
        assert not any("covariance_rad2" in line for line in meta.comment)

    back = read_tdm(path)  # with its sidecar: the records as written, in their order, epochs exact
    assert len(back) == len(records)
    for got, want in zip(back, records):
        assert (got.kind, got.target, got.sensor, got.t_tdb_s) == ("radec", want.target, want.sensor, want.t_tdb_s)
        np.testing.assert_allclose(got.value, want.value, rtol=1e-12, atol=0.0)
        np.testing.assert_array_equal(got.covariance, want.covariance)

    (tmp_path / f"{name}.cov.csv").unlink()  # the TDM alone: angles, but no covariance to read
    with pytest.raises(InputError, match=rf"{name}: TDM segment 1: the TDM carries no 'opnav covariance_rad2'.*"
                                         rf"{name}\.cov\.csv"):
        read_tdm(path)
    alone = read_tdm(path, sigma_rad=1e-5)
    assert [rec.t_tdb_s for rec in alone] == sorted(rec.t_tdb_s for rec in alone)
    for got, want in zip(sorted(alone, key=key), sorted(records, key=key)):
        assert abs(got.t_tdb_s - want.t_tdb_s) <= MICROSECOND
        np.testing.assert_allclose(got.value, want.value, rtol=1e-12, atol=0.0)


def foreign_tdm(path, frame: str = "ICRF", angle_type: str = "RADEC", time_system: str = "UTC"):
    """A TDM as another tool writes it: no opnav comments, a MAG line, observer first (standard E-16)."""
    meta = ndmxml4.TdmMetadata(time_system=time_system, participant_1="TFRM", participant_2="TRACK_001",
                               mode=ndmxml4.ModeType.SEQUENTIAL, path="2,1",
                               angle_type=ndmxml4.AngleTypeType(angle_type),
                               reference_frame=ndmxml4.RefFrameType(frame))
    epochs = ["2012-10-29T17:46:39.02", "2012-10-29T17:47:39.02"]
    obs = []
    for epoch, (ra, dec) in zip(epochs, [(332.2298750, -16.3028389), (332.5, 85.0)]):
        obs += [ndmxml4.TrackingDataObservationType(epoch=epoch, angle_1=ndmxml4.AngleType(value=ra)),
                ndmxml4.TrackingDataObservationType(epoch=epoch, angle_2=ndmxml4.AngleType(value=dec)),
                ndmxml4.TrackingDataObservationType(epoch=epoch, mag=12.1)]
    tdm = ndmxml4.Tdm(header=ndmxml4.TdmHeader(creation_date="2012-10-30T20:00:00", originator="ESA"),
                      body=ndmxml4.TdmBody(segment=[ndmxml4.TdmSegment(
                          metadata=meta, data=ndmxml4.TdmData(observation=obs))]))
    path.write_text(NdmIo().to_string(tdm, NDMFileFormats.KVN))
    return np.radians([[332.2298750, -16.3028389], [332.5, 85.0]])


def test_tdm_without_opnav_covariance_needs_sigma(tmp_path, caplog):
    values = foreign_tdm(tmp_path / "esa.tdm")
    with pytest.raises(InputError, match=r"esa\.tdm.*no 'opnav covariance_rad2'.*sigma_rad"):
        read_tdm(tmp_path / "esa.tdm")
    with caplog.at_level(logging.WARNING, logger="opnav.ccsds"):
        back = read_tdm(tmp_path / "esa.tdm", sigma_rad=1e-5)
    assert "2 observations" in caplog.text and "MAG: 2" in caplog.text
    assert [rec.target for rec in back] == ["track_001", "track_001"]  # where PATH 2,1 starts
    np.testing.assert_allclose([rec.value for rec in back], values, rtol=1e-14)
    for rec in back:
        np.testing.assert_array_equal(rec.covariance, 1e-5 ** 2 * np.eye(2))
    assert back[1].t_tdb_s - back[0].t_tdb_s == pytest.approx(60.0, abs=MICROSECOND)


def test_eme2000_angles_are_rotated_to_icrf_by_the_frame_bias(tmp_path):
    values = foreign_tdm(tmp_path / "eme.tdm", frame="EME2000")
    back = read_tdm(tmp_path / "eme.tdm", sigma_rad=1e-5)
    shift = angle_between(radec_to_unit(*np.array([rec.value for rec in back]).T), radec_to_unit(*values.T))
    assert np.all(shift > 1.0 * MAS) and np.all(shift < 25.0 * MAS)


@pytest.mark.parametrize("change, message", [
    ({"angle_type": "AZEL"}, "ANGLE_TYPE AZEL is not supported"),
    ({"frame": "TOD"}, "REFERENCE_FRAME TOD is not supported"),
    ({"time_system": "GPS"}, "TIME_SYSTEM GPS is not supported"),
])
def test_tdm_with_unsupported_metadata_is_refused(tmp_path, change, message):
    foreign_tdm(tmp_path / "odd.tdm", **change)
    with pytest.raises(InputError, match=rf"odd\.tdm.*{message}"):
        read_tdm(tmp_path / "odd.tdm", sigma_rad=1e-5)


def test_write_tdm_refuses_no_radec_and_unusable_records(tmp_path):
    position = Measurement(0.0, "position", [1.0, 2.0, 3.0], np.eye(3))
    with pytest.raises(InputError, match="none of the 1 records is of kind radec"):
        write_tdm(tmp_path / "none.tdm", [position])
    bad = Measurement(0.0, "radec", [0.1, np.nan], np.eye(2) * 1e-10, target="phobos")
    with pytest.raises(InputError, match="NaN"):
        write_tdm(tmp_path / "nan.tdm", [bad])
    assert not (tmp_path / "none.tdm").exists() and not (tmp_path / "nan.tdm").exists()


# --- files that are not what they claim ---------------------------------------------------------


@pytest.mark.parametrize("reader", [read_oem, read_tdm])
@pytest.mark.parametrize("content", ["random", "empty", "missing", "truncated xml", "plain text"])
def test_unreadable_files_raise_input_error_naming_the_file(tmp_path, reader, content):
    path = tmp_path / f"bad-{content.replace(' ', '_')}.dat"
    if content == "random":
        path.write_bytes(np.random.default_rng(0).bytes(4096))
    elif content == "empty":
        path.write_text("")
    elif content == "truncated xml":
        t, states, _ = ephemeris(2)
        write_oem(tmp_path / "ok.xml", t, states)
        path.write_text((tmp_path / "ok.xml").read_text()[:300])
    elif content == "plain text":
        path.write_text("hello, this is not a CCSDS message\n")
    with pytest.raises(InputError) as info:
        reader(path)
    message = str(info.value)
    assert str(path) in message and "\n" not in message


@pytest.mark.parametrize("name", ["arc.oem", "arc.xml"])
def test_a_letter_in_a_number_is_refused(tmp_path, name):
    t, states, cov = ephemeris(3)
    write_oem(tmp_path / name, t, states, cov)
    text = (tmp_path / name).read_text()
    number = repr(float(states[1, 2]))
    assert text.count(number) == 1
    (tmp_path / name).write_text(text.replace(number, number[:3] + "x" + number[3:]))
    with pytest.raises(InputError, match=rf"{name}"):
        read_oem(tmp_path / name)


def test_a_tdm_is_not_an_oem(tmp_path):
    write_tdm(tmp_path / "angles.tdm", radec_records()[:2])
    with pytest.raises(InputError, match=r"angles\.tdm: a CCSDS TDM message, not an OEM"):
        read_oem(tmp_path / "angles.tdm")


# --- write_oem input checks ---------------------------------------------------------------------


def _nan_state(t, x, c):
    x = x.copy()
    x[4, 1] = np.nan
    return t, x, c


def _decreasing(t, x, c):
    t = t.copy()
    t[6] = t[5] - 1.0
    return t, x, c


def _asymmetric(t, x, c):
    c = c.copy()
    c[2, 0, 4] += 1e-3 * np.sqrt(c[2, 0, 0] * c[2, 4, 4])
    return t, x, c


@pytest.mark.parametrize("spoil, message", [
    (_nan_state, r"states\[4\] contains NaN"),
    (lambda t, x, c: (t, x[:, :5], c), r"states must have shape \(20, 6\)"),
    (lambda t, x, c: (t[:, None], x, c), r"t_tdb_s must have shape \(N,\)"),
    (lambda t, x, c: (t, x[:-1], c), r"states must have shape \(20, 6\)"),
    (lambda t, x, c: (t, x, c[:, :3, :3]), r"covariances must have shape \(20, 6, 6\)"),
    (_decreasing, r"t_tdb_s must increase strictly; t_tdb_s\[6\]"),
    (lambda t, x, c: (np.r_[t[:1], t[:1] + 2e-7, t[2:]], x, c), r"less than 1 us apart"),
    (_asymmetric, r"covariances\[2\] is not symmetric"),
])
def test_write_oem_refuses_bad_input(tmp_path, spoil, message):
    t, states, cov = spoil(*ephemeris())
    with pytest.raises(InputError, match=message):
        write_oem(tmp_path / "bad.oem", t, states, cov)
    assert not (tmp_path / "bad.oem").exists()


def test_write_oem_refuses_a_name_that_would_break_the_file(tmp_path):
    t, states, _ = ephemeris(2)
    with pytest.raises(InputError, match="center"):
        write_oem(tmp_path / "bad.oem", t, states, center="MARS\nREF_FRAME = GCRF")


def test_a_file_cut_inside_a_block_is_refused_never_read_in_part(tmp_path):
    """Every cut of a golden OEM (with covariances) and TDM at a line end: a cut inside a META, DATA or
    COVARIANCE block is refused naming the block; any other cut reads whole blocks only (a cut OEM never
    loses its covariances without a word)."""
    from pathlib import Path

    from opnav.ccsds import read_oem, read_tdm
    from opnav.errors import InputError

    golden = Path(__file__).resolve().parent / "golden" / "ccsds"
    for name, reader in (("arc_cov.oem", read_oem), ("radec.tdm", read_tdm)):
        source = golden / name
        lines = source.read_text().splitlines(keepends=True)
        inside, refused = [], 0
        depth = None
        for line in lines:
            word = line.strip().split(" ", 1)[0]
            if word.endswith("_START"):
                depth = word
            elif word.endswith("_STOP"):
                depth = None
            inside.append(depth is not None)
        for k in range(1, len(lines)):
            cut = tmp_path / f"cut_{k}{source.suffix}"
            cut.write_text("".join(lines[:k]))
            sidecar = source.with_name(source.name + ".cov.csv")
            if sidecar.exists():
                (tmp_path / f"{cut.name}.cov.csv").write_text(sidecar.read_text())
            if inside[k - 1]:
                with pytest.raises(InputError, match="ends inside the"):
                    reader(cut)
                refused += 1
            elif name.endswith(".oem") and any(line.startswith("COVARIANCE_STOP") for line in lines[:k]):
                try:
                    data = reader(cut)
                except InputError:
                    continue  # e.g. no data line yet
                assert data.covariances is not None
        assert refused > 0
