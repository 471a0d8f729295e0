"""Observability core on systems whose answer is known in closed form."""

import numpy as np
import pytest

from opnav.errors import InputError
from opnav.observability import analyse, local_observability_matrix, numerical_rank


def _constant_velocity(dt: float) -> np.ndarray:
    return np.array([[1.0, dt], [0.0, 1.0]])


def test_position_measurement_makes_constant_velocity_observable():
    F = _constant_velocity(10.0)
    H = np.array([[1.0, 0.0]])
    rank, _ = numerical_rank(local_observability_matrix(F, H))
    assert rank == 2


def test_velocity_measurement_leaves_position_unobservable():
    F = _constant_velocity(10.0)
    H = np.array([[0.0, 1.0]])
    rank, _ = numerical_rank(local_observability_matrix(F, H))
    assert rank == 1


def test_fisher_information_gives_least_squares_covariance():
    # Position measured at t = 0, 1, ..., 9 with sigma 2: the CRB of (x0, v0) is the
    # covariance of the straight-line least-squares fit, (A^T A)^-1 sigma^2.
    times = np.arange(10.0)
    sigma = 2.0
    rows = [np.array([[1.0, t]]) for t in times]
    covs = [np.array([[sigma**2]])] * len(times)
    segments = [(_constant_velocity(1.0), np.array([[1.0, 0.0]]))]
    rep = analyse("line", segments, rows, covs)
    A = np.column_stack([np.ones_like(times), times])
    expected = np.sqrt(np.diag(np.linalg.inv(A.T @ A))) * sigma
    np.testing.assert_allclose(rep.crb_sigma, expected, rtol=1e-12)
    np.testing.assert_allclose(rep.eta, 2.0 / np.sum(expected**2), rtol=1e-12)
    assert rep.rank == 2


def test_more_measurements_raise_eta():
    times = np.linspace(0.0, 5.0, 6)
    segments = [(_constant_velocity(1.0), np.array([[1.0, 0.0]]))]
    few = analyse("few", segments, [np.array([[1.0, t]]) for t in times[:2]], [np.eye(1)] * 2)
    many = analyse("many", segments, [np.array([[1.0, t]]) for t in times], [np.eye(1)] * 6)
    assert many.eta > few.eta


@pytest.mark.parametrize("spread", [1e-1, 1e-2, 1e-3])
def test_nearly_collinear_rows_are_ill_conditioned(spread):
    # Two measurements whose Jacobian rows differ by `spread`: kappa(O^T O) ~ 4/spread^2,
    # the "near-collinear bodies" failure of S2's MS and PS sets.
    segments = [(np.eye(2), np.array([[1.0, 0.0]]))]
    rows = [np.array([[1.0, 0.0]]), np.array([[1.0, spread]])]
    rep = analyse("pair", segments, rows, [np.eye(1)] * 2)
    assert 2.0 / spread**2 < rep.condition_number < 8.0 / spread**2


def test_bad_shapes_raise():
    with pytest.raises(InputError, match="F must be"):
        local_observability_matrix(np.eye(3), np.ones((1, 2)))
    with pytest.raises(InputError, match="at least one"):
        analyse("x", [], [], [])
