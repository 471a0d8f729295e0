"""Checked runs: every covariance finite, symmetric and positive definite, or a stop naming the record."""

import numpy as np
import pytest

from opnav.errors import CovarianceError
from opnav.filters.base import Estimate, UpdateOutcome
from opnav.filters.run import covariance_health, run_filter
from opnav.records import Measurement


class _Drifting:
    """A stand-in filter whose covariance loses a dimension at its third record."""

    def __init__(self):
        self.estimate = Estimate(0.0, np.zeros(2), np.eye(2))
        self.count = 0

    def update(self, record):
        self.count += 1
        P = np.eye(2) if self.count < 3 else np.array([[1.0, 1.0], [1.0, 1.0 - 1e-3]])
        self.estimate = Estimate(record.t_tdb_s, np.zeros(2), P)
        return UpdateOutcome(self.estimate, np.zeros(1), np.eye(1), 0.5, True, "")


def _records(n):
    return [Measurement(float(t), "position", [1.0, 0.0, 0.0], np.eye(3), target="x") for t in range(1, n + 1)]


def test_a_checked_run_stops_at_the_first_bad_covariance_and_names_the_record():
    with pytest.raises(CovarianceError, match=r"after record 2 \(position at t = 3.000 s TDB\).*not positive definite"):
        run_filter(_Drifting(), _records(5), progress=False, checked=True)
    # unchecked, the same run goes through (the filters' own checks are the only guard)
    assert len(run_filter(_Drifting(), _records(5), progress=False)) == 5


def test_health_of_good_and_bad_covariances():
    asymmetry, ratio = covariance_health(np.diag([4.0, 1e-6]))
    assert asymmetry == 0.0 and ratio == pytest.approx(1.0)  # scaled by its diagonal: no bad conditioning
    _, ratio = covariance_health(np.array([[1.0, 0.999], [0.999, 1.0]]))
    assert ratio == pytest.approx(0.001 / 1.999)
    with pytest.raises(CovarianceError, match="not symmetric"):
        covariance_health(np.array([[1.0, 0.1], [0.2, 1.0]]))
    with pytest.raises(CovarianceError, match="NaN"):
        covariance_health(np.array([[np.nan, 0.0], [0.0, 1.0]]))


def test_opnav_run_checked_reports_the_worst_conditioning(tmp_path):
    import json
    from pathlib import Path

    from opnav.cli import main

    runfile = Path(__file__).resolve().parents[2] / "samples" / "s3_geo.toml"
    assert main(["run", str(runfile), "--set", "duration_hours=0.5", "--filters", "ekf,ukf,sr-ukf", "--checked",
                 "--out", str(tmp_path), "--no-progress"]) == 0
    filters = json.loads((tmp_path / "summary.json").read_text())["filters"]
    for name in ("ekf", "ukf", "sr-ukf"):
        health = filters[name]["covariance_health"]
        assert health["records_checked"] == 180 and health["max_asymmetry"] <= 1e-9
        assert 0.0 < health["min_scaled_eigenvalue_ratio"] <= 1.0
