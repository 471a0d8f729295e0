"""S2 observability along the capture arc: the paper's ordering, units, and the CLI."""

import json

import numpy as np
import pytest

from opnav.cli import main
from opnav.constants import ARCSEC_RAD
from opnav.errors import InputError
from opnav.observability import analyse, information_inverse_diagonal
from opnav.studies.s2_observability import S2_COLUMN_SCALE, S2_SETS, s2_arc_epochs, s2_observability
from opnav.studies.trajectories import mars_capture_trajectory


@pytest.fixture(scope="module")
def capture():
    # A 2-hour grid and a 1-day model-1 arc keep the module to a few seconds.
    return mars_capture_trajectory(step_s=7200.0, days_before_soi=1.0)


@pytest.fixture(scope="module")
def tables(capture):
    return {model: {rep.name: rep for rep in s2_observability(model, trajectory=capture, arc_days=1.0).reports}
            for model in (1, 2)}


def _crb_position_km(report) -> float:
    return float(np.linalg.norm(report.crb_sigma[:3]))


@pytest.mark.parametrize("model, best", [(1, "MPD"), (2, "MPS")])
def test_richest_set_is_best(tables, model, best):
    # Adding a body adds positive semi-definite information, so the richest set (the paper's best)
    # has the largest eta and the smallest CRB; a broken FIM inverse violates this (the old
    # pseudo-inverse gave a lone Mars a 2 km CRB against 69 km for MPD).
    reports = tables[model]
    assert set(reports) == set(S2_SETS[model])
    for name, rep in reports.items():
        if name != best:
            assert reports[best].eta >= rep.eta, name
            assert _crb_position_km(reports[best]) <= _crb_position_km(rep), name


def test_mars_sun_set_is_near_singular(tables):
    # S2: MS is (nearly) unobservable: the Sun direction moves by |dr| / 1.5 au only.
    reports = tables[2]
    assert reports["MS"].condition_number > 30.0 * reports["MPS"].condition_number
    assert _crb_position_km(reports["MS"]) > 5.0 * _crb_position_km(reports["MPS"])
    assert all(rep.rank == 6 for rep in reports.values()), "full rank expected: weak, not blind, directions"


def test_crb_scales_with_the_angle_noise(capture):
    one = s2_observability(2, trajectory=capture, sigma_arcsec=1.0)
    three = s2_observability(2, trajectory=capture, sigma_arcsec=3.0)
    for a, b in zip(one.reports, three.reports):
        np.testing.assert_allclose(b.crb_sigma, 3.0 * a.crb_sigma, rtol=1e-9)
        np.testing.assert_allclose(b.eta, a.eta / 9.0, rtol=1e-9)
        assert b.rank == a.rank


def _random_rows(rng, column_sizes):
    basis = np.linalg.qr(rng.standard_normal((6, 6)))[0]
    return [rng.standard_normal((3, 6)) @ np.diag(column_sizes) @ basis for _ in range(20)]


def test_crb_does_not_depend_on_state_units():
    # Weakly observable 6-state problem, cond(F) ~ 1e14 as on the S2 arcs: the physical CRB must not
    # change with the units in which the columns are taken.
    rows = _random_rows(np.random.default_rng(20140922), [1.0, 1.0, 1.0, 1e3, 1e3, 1e-4])
    covs = [np.eye(3) * ARCSEC_RAD**2] * len(rows)
    segments = [(np.eye(6), rows[0])]
    km = analyse("km", segments, rows, covs)
    scaled = analyse("scaled", segments, rows, covs, column_scale=S2_COLUMN_SCALE)
    np.testing.assert_allclose(scaled.crb_sigma, km.crb_sigma, rtol=1e-6)


def test_crb_matches_the_inverse_fisher_matrix_when_well_conditioned():
    # cond(F) ~ 1e8 leaves the explicit inverse accurate to ~1e-8: an independent reference.
    rows = _random_rows(np.random.default_rng(7), [1.0, 1.0, 1.0, 1e2, 1e2, 1e-2])
    covs = [np.eye(3) * ARCSEC_RAD**2] * len(rows)
    report = analyse("x", [(np.eye(6), rows[0])], rows, covs)
    info = sum(H.T @ np.linalg.solve(R, H) for H, R in zip(rows, covs))
    np.testing.assert_allclose(report.crb_sigma**2, np.diag(np.linalg.inv(info)), rtol=1e-6)
    np.testing.assert_allclose(report.eta, 6.0 / np.trace(np.linalg.inv(info)), rtol=1e-6)


def test_unobservable_state_gets_infinite_crb():
    rows = [np.array([[1.0, 0.0]]), np.array([[2.0, 0.0]])]
    variance = information_inverse_diagonal(rows, [np.eye(1)] * 2)
    np.testing.assert_allclose(variance[0], 1.0 / 5.0)
    assert np.isinf(variance[1])
    assert analyse("blind", [(np.eye(2), rows[0])], rows, [np.eye(1)] * 2).eta == 0.0


def test_arc_epochs_follow_the_model_switch(capture):
    one = s2_arc_epochs(capture, 1, arc_days=1.0)
    two = s2_arc_epochs(capture, 2, stop_before_periapsis_s=7200.0)
    assert one[-1] == capture.t_soi_tdb_s == two[0]
    assert two[-1] <= capture.t_periapsis_tdb_s - 7200.0
    with pytest.raises(InputError, match="model must be 1 or 2"):
        s2_arc_epochs(capture, 3)


def test_cli_prints_json_and_rejects_bad_sigma(capsys):
    assert main(["observability", "--model", "2", "--step-s", "7200", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [s["name"] for s in out["sets"]] == list(S2_SETS[2])
    assert out["sigma_arcsec"] == 1.0 and out["stars_hip"] == [7588, 97649, 80763]
    assert main(["observability", "--model", "1", "--sigma-arcsec", "-1"]) == 2
    assert "--sigma-arcsec" in capsys.readouterr().err


@pytest.mark.parametrize("model", [1, 2])
def test_crb_over_the_arc_falls_to_the_whole_arc_bound(capture, model):
    # information only adds up: the bound from the first k epochs can only fall as k grows, and with
    # every epoch it is the whole arc's bound (the tables' CRB); before a set sees the position it is inf
    study = s2_observability(model, trajectory=capture, arc_days=1.0)
    assert len(study.crb_position_km) == len(study.reports)
    for report, curve in zip(study.reports, study.crb_position_km):
        assert curve.shape == study.t_tdb_s.shape
        finite = curve[np.isfinite(curve)]
        assert finite.size and np.all(np.diff(finite) <= 1e-9 * finite[:-1])
        assert np.all(np.isfinite(curve[np.argmax(np.isfinite(curve)):]))
        np.testing.assert_allclose(curve[-1], np.linalg.norm(report.crb_sigma[:3]), rtol=1e-6)
