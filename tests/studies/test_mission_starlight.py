"""Starlight angles in a mission: the angle from fixed stars to a body's centre and limb, with the two
sensors' correlated noise; a star behind the body is left out; the filters stay inside 3 sigma."""

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from opnav.errors import InputError
from opnav.filters.navigate import navigate
from opnav.frames import unit_to_radec
from opnav.measurements import ProbeMeasurementModel
from opnav.studies import mission

#: Sirius, Vega, Arcturus and Polaris (ICRF RA/Dec, deg) against the Earth, over the first 12 hours.
STARS = ((101.287, -16.716), (279.234, 38.784), (213.915, 19.182), (37.95, 89.26))
BASE = mission.Settings(stop="2027-03-10T13:00:00", targets=(), starlight_target="earth",
                        starlight_stars_radec_deg=STARS)


@pytest.fixture(scope="module")
def sim():
    return mission.simulate(BASE, seed=11)


def test_the_records_scatter_as_their_covariance_says(sim):
    model = ProbeMeasurementModel("earth")
    truth = dict(zip(sim.epochs, sim.truth))
    chi2 = []
    for record in sim.records:
        assert record.kind == "starlight" and record.target == "earth"
        d = record.value - model.predict(record, truth[record.t_tdb_s])
        chi2.append(d @ np.linalg.solve(record.covariance, d))
    assert len(chi2) == len(STARS) * sim.epochs.size
    low, high = stats.chi2.ppf([0.005, 0.995], 2 * len(chi2)) / len(chi2)  # the mean of chi-square(2) values
    assert low < np.mean(chi2) < high


def test_the_filters_nees_over_ten_seeds_is_in_band():
    """The final NEES of 10 seeded EKF runs: each below chi-square(6)'s 99.9 % point, their mean inside
    the 99 % band of the mean of 10 chi-square(6) values (one run's errors can sit at 2.5 sigma)."""
    final = []
    for seed in range(10):
        sim = mission.simulate(BASE, seed=seed)
        history = navigate(sim.records, sim.navigation, filter_name="ekf", force_model=sim.force_model,
                           center=sim.center).history
        error = history.states[-1, :6] - sim.truth[-1]
        final.append(error @ np.linalg.solve(history.covariances[-1, :6, :6], error))
    assert max(final) < stats.chi2.ppf(0.999, 6)
    low, high = stats.chi2.ppf([0.005, 0.995], 6 * len(final)) / len(final)
    assert low < np.mean(final) < high


def test_a_star_behind_the_body_gives_no_record():
    t_start, epochs = mission.record_epochs(BASE)
    truth = mission.truth_states(BASE, epochs)
    earth = -truth[0, :3] / np.linalg.norm(truth[0, :3])  # the Earth's centre seen at the first epoch
    ra, dec = np.degrees(unit_to_radec(earth))
    settings = replace(BASE, starlight_stars_radec_deg=((float(ra), float(dec)), STARS[0]))
    sim = mission.simulate(settings, seed=11)
    hidden = sim.facts["starlight_records_left_out"][f"[{float(ra):g}, {float(dec):g}]"]
    assert 0 < hidden < epochs.size  # behind the disk at first, out of it as the disk shrinks and moves
    stars = {tuple(np.round(r.star_unit_icrf, 12)) for r in sim.records if r.t_tdb_s == epochs[0]}
    assert len(stars) == 1  # only Sirius at the first epoch


@pytest.mark.parametrize("changes, words", [
    ({"starlight_target": "phobos"}, "starlight_target must be one of"),
    ({"starlight_stars_radec_deg": ()}, "go together"),
    ({"starlight_stars_radec_deg": ((10.0, 95.0),)}, "declination 95.0"),
    ({"starlight_target": "", "starlight_stars_radec_deg": ()}, "targets must name at least one body"),
])
def test_bad_starlight_settings_are_named(changes, words):
    with pytest.raises(InputError, match=words):
        replace(BASE, **changes)
