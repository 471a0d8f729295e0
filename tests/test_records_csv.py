"""Measurement CSV: the unit column is honoured; duplicated rows are refused, not counted twice."""

import numpy as np
import pytest
from test_ukf import BEACONS, P0_ORBIT, X0_ORBIT, BeaconRadec, FixedNoise, Q_ORBIT, gravity_transition

from opnav.errors import InputError
from opnav.filters.base import Estimate
from opnav.filters.run import run_filter
from opnav.filters.ukf import UnscentedKalmanFilter
from opnav.records import Measurement, read_csv, write_csv


def test_angles_in_degrees_or_arcseconds_are_converted(tmp_path):
    record = Measurement(10.0, "radec", [0.5, -0.2], np.diag([1e-10, 2e-10]), target="mars")
    write_csv(tmp_path / "m.csv", [record])
    text = (tmp_path / "m.csv").read_text()
    deg = np.degrees(record.value)
    rows = text.splitlines()
    fields = rows[1].split(",")
    fields[2] = "deg"
    fields[-2] = " ".join(repr(float(v)) for v in deg)
    fields[-1] = " ".join(repr(float(v)) for v in (record.covariance * np.degrees(1.0) ** 2).ravel())
    (tmp_path / "deg.csv").write_text("\n".join([rows[0], ",".join(fields)]) + "\n")
    back = read_csv(tmp_path / "deg.csv")[0]
    np.testing.assert_allclose(back.value, record.value, rtol=1e-14)
    np.testing.assert_allclose(back.covariance, record.covariance, rtol=1e-12)
    fields[2] = "km"
    (tmp_path / "bad.csv").write_text("\n".join([rows[0], ",".join(fields)]) + "\n")
    with pytest.raises(InputError, match=r"bad.csv:2: .*unit 'km' for a radec record"):
        read_csv(tmp_path / "bad.csv")


def test_a_duplicated_record_is_refused_not_counted_twice():
    model = BeaconRadec(BEACONS)
    truth = gravity_transition(0.0, X0_ORBIT, 60.0)
    record = Measurement(60.0, "radec", model.predict(Measurement(60.0, "radec", [0, 0], np.eye(2), target="a"), truth),
                         np.eye(2) * 4e-8, target="a")

    def ukf():
        return UnscentedKalmanFilter(Estimate(0.0, X0_ORBIT, P0_ORBIT), transition=gravity_transition,
                                     process_noise=FixedNoise(Q_ORBIT), model=model)

    once = run_filter(ukf(), [record], progress=False)
    twice = run_filter(ukf(), [record, record], progress=False)
    assert twice.accepted.tolist() == [True, False] and "duplicate" in twice.reasons[1]
    np.testing.assert_array_equal(twice.covariances[-1], once.covariances[-1])


def test_written_rows_are_each_numbers_repr_and_read_back_exactly(tmp_path):
    """write_csv formats a covariance shared by many records once: each row is still every number's
    shortest repr (-0.0 kept apart from 0.0), names with commas are quoted, and a read gives back
    the same records."""
    import csv

    shared = np.diag([2.35e-13, 2.35e-13])
    signed = np.array([[1e-12, -0.0], [-0.0, 1e-12]])
    records = [Measurement(4.5e8 + k, "radec", [0.1 * k + 1e-17, -0.3], shared, target="phobos", sensor="nac")
               for k in range(5)]
    records += [Measurement(4.5e8 + 7, "radec", [1.0, 0.5], signed, target="deimos, the outer", frame_id="f7"),
                Measurement(4.5e8 + 7, "radec", [1.0, 0.5], np.diag([1e-12, 1e-12]), target="deimos"),
                Measurement(4.5e8 + 9, "starlight", [0.2, 0.1], np.diag([1e-10, 1e-10]), target="mars", star_id=7,
                            star_unit_icrf=np.array([0.6, 0.8, 0.0]), flags=3)]
    write_csv(tmp_path / "m.csv", records)
    with open(tmp_path / "m.csv", newline="") as handle:
        rows = list(csv.reader(handle))[1:]
    for rec, row in zip(records, rows):
        star = rec.star_unit_icrf if rec.star_unit_icrf is not None else [np.nan] * 3
        assert row[0] == repr(rec.t_tdb_s) and row[4] == rec.target
        assert row[6:9] == [repr(float(v)) for v in star]
        assert row[11] == " ".join(repr(float(v)) for v in rec.value)
        assert row[12] == " ".join(repr(float(v)) for v in rec.covariance.ravel())
    assert rows[5][12].split()[1] == "-0.0" and rows[6][12].split()[1] == "0.0"
    back = read_csv(tmp_path / "m.csv")
    assert len(back) == len(records)
    for got, rec in zip(back, records):
        assert (got.t_tdb_s, got.kind, got.target, got.sensor, got.star_id, got.frame_id, got.flags) == (
            rec.t_tdb_s, rec.kind, rec.target, rec.sensor, rec.star_id, rec.frame_id, rec.flags)
        assert got.value.tobytes() == rec.value.tobytes() and got.covariance.tobytes() == rec.covariance.tobytes()
        assert (got.star_unit_icrf is None) == (rec.star_unit_icrf is None)
