"""``opnav propagate``: JSON schema, S1 Mars ranges, frames, and one-line errors with exit 2."""

from __future__ import annotations

import json

import numpy as np
import pytest

from opnav.cli import main
from opnav.frames import icrf_to_ecliptic

STATE = ["24306991.2893", "132523850.2219", "58427884.5328", "-32.455391", "3.658828", "3.362343"]
DATES = ["2014-05-01T00:00:00", "2014-06-01T00:00:00", "2014-07-01T00:00:00", "2014-08-01T00:00:00",
         "2014-09-01T00:00:00"]


def _args(state=STATE, frame="icrf", at=DATES, extra=()):
    return ["propagate", "--epoch", "2013-12-12T12:00:00", "--scale", "tt", "--state", *state, "--frame", frame,
            "--center", "sun", "--model", "cruise", "--at", *at, "--relative-to", "mars", *extra]


def test_json_output_schema_and_mars_range(capsys):
    assert main(_args(extra=["--json"])) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [row["epoch"][:10] for row in rows] == [d[:10] for d in DATES]
    for row in rows:
        assert set(row) == {"epoch", "r_km", "v_km_s", "range_km"}
        assert len(row["r_km"]) == 3 and len(row["v_km_s"]) == 3
        assert row["range_km"] == pytest.approx(np.linalg.norm(row["r_km"]), rel=1e-12)
    ranges_mkm = np.array([row["range_km"] for row in rows]) / 1e6
    np.testing.assert_allclose(ranges_mkm, [49.0, 33.0, 23.0, 15.0, 7.0], rtol=0, atol=1.5)


def test_ecliptic_input_gives_same_range_and_ecliptic_output(capsys):
    r = icrf_to_ecliptic(np.array([float(s) for s in STATE[:3]]))
    v = icrf_to_ecliptic(np.array([float(s) for s in STATE[3:]]))
    main(_args(extra=["--json"], at=DATES[:1]))
    icrf_row = json.loads(capsys.readouterr().out)[0]
    main(_args(state=[repr(float(c)) for c in np.r_[r, v]], frame="ecliptic", at=DATES[:1], extra=["--json"]))
    ecliptic_row = json.loads(capsys.readouterr().out)[0]
    assert ecliptic_row["range_km"] == pytest.approx(icrf_row["range_km"], abs=1e-3)
    np.testing.assert_allclose(ecliptic_row["r_km"], icrf_to_ecliptic(np.array(icrf_row["r_km"])), atol=1e-3)


def test_dates_before_and_after_epoch_and_table_output(capsys):
    at = ["2014-01-01T00:00:00", "2013-12-01T00:00:00"]
    assert main(_args(at=at, extra=["--json"])) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [row["epoch"][:10] for row in rows] == ["2014-01-01", "2013-12-01"]
    assert main(_args(at=at)) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].startswith("model cruise") and "range_km" in table[1] and len(table) == 4


@pytest.mark.parametrize(
    "args, message",
    [
        (_args(extra=["--model", "warp"]), "unknown force model"),
        (_args(extra=["--relative-to", "vulcan"]), "vulcan"),
        (_args(at=["2014-13-45"]), "cannot parse epoch"),
        (_args(state=STATE[:5] + ["nan"]), "NaN"),
        (_args(state=STATE[:5] + ["fast"]), "six numbers"),
        (_args(frame="galactic"), "--frame"),
        (_args(extra=["--scale", "gps"]), "time scale"),
        (_args(at=["2200-01-01T00:00:00"]), "coverage"),
    ],
)
def test_bad_input_exits_2_with_one_line(capsys, args, message):
    assert main(args) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert message in err
