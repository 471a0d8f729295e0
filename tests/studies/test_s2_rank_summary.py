"""S2's numerical rank stated with its tolerance and spectrum beside the paper's rank (issue 40 item 4)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from opnav.observability import ObservabilityReport, numerical_rank
from opnav.studies.s2_observability import S2_COLUMN_SCALE, paper_rank_tolerance, rank_summary


def report(sigma) -> ObservabilityReport:
    sigma = np.sort(np.asarray(sigma, float))[::-1]
    return ObservabilityReport("SET", int(numerical_rank(np.diag(sigma), rtol=1e-9)[0]), sigma, 1.0, 1.0,
                               np.ones(6), S2_COLUMN_SCALE)


@settings(deadline=None, derandomize=True, max_examples=200)
@given(sigma=st.lists(st.floats(1e-12, 1.0), min_size=6, max_size=6, unique=True), paper_rank=st.integers(1, 6),
       where=st.floats(0.01, 0.99))
def test_a_tolerance_inside_the_stated_interval_gives_the_paper_rank(sigma, paper_rank, where):
    summary = rank_summary(report(sigma), 1e-9, paper_rank)
    low, high = summary["paper_rank_rtol"]
    assert 0.0 <= low < high <= 1.0
    rtol = low + where * (high - low)
    matrix = np.diag(np.sort(sigma)[::-1])
    assert numerical_rank(matrix, rtol=rtol)[0] == paper_rank
    # just outside the interval (by more than the rounding of sigma / sigma_max) the rank is another
    assert numerical_rank(matrix, rtol=high * (1.0 + 1e-12))[0] == paper_rank - 1
    if low > 0.0:
        assert numerical_rank(matrix, rtol=low * (1.0 - 1e-12))[0] == paper_rank + 1


def test_the_summary_states_rank_tolerance_units_and_spectrum():
    summary = rank_summary(report([5.3e-4, 4.3e-4, 2.7e-5, 2.2e-5, 8.2e-6, 4.2e-7]), 1e-9, 5)
    assert summary["rank"] == 6 and summary["rank_rtol"] == 1e-9 and summary["paper_rank"] == 5
    assert summary["column_units"] == ["km", "km", "km", "m/s", "m/s", "m/s"]
    assert summary["relative_singular_values"][0] == 1.0
    np.testing.assert_allclose(summary["paper_rank_rtol"], [4.2e-7 / 5.3e-4, 8.2e-6 / 5.3e-4])


def test_one_tolerance_for_a_whole_table_or_none():
    a = {"paper_rank_rtol": [1e-4, 1e-2]}
    b = {"paper_rank_rtol": [5e-3, 2e-2]}
    assert paper_rank_tolerance([a, b]) == [5e-3, 1e-2]
    assert paper_rank_tolerance([a, {"paper_rank_rtol": [2e-2, 3e-2]}]) is None
    assert paper_rank_tolerance([a, {"paper_rank_rtol": None}]) is None


@pytest.mark.slow
def test_s2_model_1_ranks_beside_the_paper():
    """On the hourly capture arc every set is of full rank at 1e-9; the paper's model-1 ranks (6, 5, 5, 5)
    need a tolerance each, and the stated intervals say whether one tolerance gives them all."""
    from opnav.studies.s2_observability import s2_observability
    from opnav.studies.trajectories import mars_capture_trajectory

    study = s2_observability(1, trajectory=mars_capture_trajectory(step_s=3600.0))
    summary = study.rank_summary()
    for name, figures in summary["sets"].items():
        assert figures["rank"] == 6 and figures["rank_rtol"] == 1e-9
        low, high = figures["paper_rank_rtol"]
        matrix = np.diag(figures["singular_values"])
        assert numerical_rank(matrix, rtol=0.5 * (low + high))[0] == figures["paper_rank"], name
    common = summary["paper_rank_rtol"]
    if common is not None:
        for figures in summary["sets"].values():
            assert numerical_rank(np.diag(figures["singular_values"]), rtol=0.5 * sum(common))[0] == \
                figures["paper_rank"]
