"""The campaign's posterior Cramér-Rao bound (opnav.studies.campaign_runs.posterior_bound, the filter's own
steps held on the truth) against an independent computation: with no process noise the bound at t_k is
Phi_k (P0^-1 + sum_i Phi_i^T H_i^T R_i^-1 H_i Phi_i)^-1 Phi_k^T over the records up to t_k, with Phi from
central differences of the truth's DOP853 propagator, H from central differences of the measurement
model and R from the record's noise plus the moon's ephemeris error carried by minus H's position block."""

import numpy as np
import pytest

from opnav.dynamics import propagate
from opnav.filters.factory import measurement_model
from opnav.studies import STUDIES
from opnav.studies.campaign_runs import posterior_bound
from opnav.studies.settings import load_run_file


def _central(function, x: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """d function / d x by central differences, (m, n) or (N, m, n) for a function returning (m,) or (N, m)."""
    columns = []
    for i, step in enumerate(steps):
        dx = np.zeros_like(x)
        dx[i] = step
        columns.append((function(x + dx) - function(x - dx)) / (2.0 * step))
    return np.stack(columns, axis=-1)


@pytest.mark.parametrize("targets", ["phobos", "both"])
def test_posterior_bound_equals_the_batch_information_of_the_initial_state(targets):
    run = load_run_file("samples/s1_jul_both_0.1.toml", {"duration_days": "0.1", "targets": targets, "seed": "5"})
    sim = STUDIES["s1"].simulate(run.settings, run.seed)
    nav = sim.navigation
    t0, epochs = nav.t0_tdb_s, sim.epochs
    steps = np.array([1.0] * 3 + [1e-6] * 3)  # km, km/s
    phi = _central(lambda x0: propagate(sim.force_model, t0, x0, epochs).states, sim.start_truth, steps)
    model = measurement_model(nav, sim.center)
    information = np.linalg.inv(nav.P0)
    sigma_moon = nav.target_position_sigma_km
    index = np.searchsorted(epochs, [record.t_tdb_s for record in sim.records])
    trace = np.empty(epochs.size)
    done = 0
    for k in range(epochs.size):
        while done < len(sim.records) and index[done] == k:
            record = sim.records[done]
            H = _central(lambda x: model.predict(record, x), sim.truth[k], steps)
            carried = -H[:, :3]  # the angles move with the moon as against the probe
            R = record.covariance + sigma_moon**2 * carried @ carried.T
            mapped = H @ phi[k]
            information += mapped.T @ np.linalg.solve(R, mapped)
            done += 1
        bound = phi[k] @ np.linalg.inv(information) @ phi[k].T
        trace[k] = np.trace(bound[:3, :3])
    window = epochs >= sim.window_start_tdb_s
    independent = np.sqrt(np.mean(trace[window]))
    assert independent < 0.6 * np.sqrt(np.trace(nav.P0[:3, :3]))  # the records have shrunk it (one weak axis left)
    assert posterior_bound(sim)["pcrb_position_km"] == pytest.approx(independent, rel=5e-5)
