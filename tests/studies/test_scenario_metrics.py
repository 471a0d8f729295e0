"""Figures the runner takes from a filter run (opnav.studies.common)."""

import numpy as np

from opnav.studies.common import rtn_axes


def test_rtn_axes_are_radial_transverse_normal():
    rng = np.random.default_rng(4)
    states = np.hstack([rng.normal(0.0, 7000.0, (20, 3)), rng.normal(0.0, 7.0, (20, 3))])
    axes = rtn_axes(states)
    np.testing.assert_allclose(axes @ axes.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (20, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(axes), 1.0)
    r = np.einsum("nij,nj->ni", axes, states[:, :3])
    v = np.einsum("nij,nj->ni", axes, states[:, 3:])
    np.testing.assert_allclose(r[:, 1:], 0.0, atol=1e-9)  # position along radial only
    np.testing.assert_allclose(v[:, 2], 0.0, atol=1e-12)  # velocity in the orbit plane
    assert np.all(r[:, 0] > 0.0) and np.all(v[:, 1] > 0.0)  # outward, prograde
