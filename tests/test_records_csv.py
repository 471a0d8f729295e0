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
