"""A mission's filters read the bodies from the same kernels as the truth: a body that exists only in
a kernel (a moonlet written to an SPK, its GM in a text PCK) is a target and a gravity body."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from opnav.constants import ARCSEC_RAD
from opnav.dynamics import ThirdBody
from opnav.errors import InputError
from opnav.filters.factory import measurement_model
from opnav.filters.navigate import navigate
from opnav.measurements import ProbeMeasurementModel
from opnav.studies import mission

MOONLET = 2_099_999
GM_MOONLET = 600.0  # km^3/s^2: an eighth of the Moon's, enough to bend the coast by km in a day
PCK = f"""KPL/PCK
\\begindata
NAIF_BODY_NAME += ( 'MOONLET' )
NAIF_BODY_CODE += ( {MOONLET} )
BODY{MOONLET}_GM = ( {GM_MOONLET} )
\\begintext
"""


@pytest.fixture(scope="module")
def kernels(tmp_path_factory) -> tuple[str, str]:
    """An SPK of a moonlet on a circular geocentric orbit (150,000 km, in the ICRF x-y plane) from 8 days
    before the sample's start to 8 days after, and the text PCK naming it and giving its GM."""
    from opnav.ephemeris.spk_writer import write_spk

    folder = tmp_path_factory.mktemp("mission_kernels")
    t_start, _ = mission.record_epochs(mission.Settings())
    # the filters read the kernels' bodies in whole days of Chebyshev series, 6 days beyond the arc
    t = t_start - 8 * 86_400.0 + np.arange(0.0, 16 * 86_400.0, 600.0)
    radius, gm_earth = 150_000.0, 398_600.435
    n = np.sqrt(gm_earth / radius**3)
    phase = n * (t - t[0])
    states = np.column_stack([radius * np.cos(phase), radius * np.sin(phase), np.zeros_like(t),
                              -radius * n * np.sin(phase), radius * n * np.cos(phase), np.zeros_like(t)])
    spk = write_spk(folder / "moonlet.bsp", t, states, body=MOONLET, center=399)
    pck = folder / "moonlet.tpc"
    pck.write_text(PCK)
    return str(spk), str(pck)


def _settings(kernels, **changes) -> mission.Settings:
    keys = dict(stop="2027-03-11T00:00:00", kernels=kernels, targets=("moonlet", "moon"),
                gravity=("earth", "moon", "sun", "moonlet"))
    return mission.Settings(**{**keys, **changes})


def test_the_filters_measure_and_feel_a_body_only_the_kernels_hold(kernels):
    settings = _settings(kernels)
    model = mission.dynamics(settings)
    moonlet = [term for term in model.terms if isinstance(term, ThirdBody) and term.body == "moonlet"]
    assert len(moonlet) == 1 and moonlet[0].gm_km3_s2 == GM_MOONLET
    assert model.ephemeris is mission.filter_ephemeris(settings) and model.ephemeris is not None
    sim = mission.simulate(settings, seed=5)
    assert {r.target for r in sim.records} == {"moonlet", "moon"}
    # the filters' model of a record at the true state is the truth's own prediction (the noise-free
    # record): the kernels' bodies through the Chebyshev cache (< 1 cm) and the same light time and aberration
    filters = measurement_model(sim.navigation, sim.center, ephemeris=model.ephemeris)
    exact = ProbeMeasurementModel(settings.center, ephemeris=mission.truth_ephemeris(settings))
    worst = 0.0
    for record, state in zip(sim.records[::37], sim.truth[[list(sim.epochs).index(r.t_tdb_s)
                                                          for r in sim.records[::37]]]):
        worst = max(worst, float(np.max(np.abs(filters.predict(record, state) - exact.predict(record, state)))))
    # the cache's 1 cm at the moonlet's 150,000 km at least: 1.4e-5 arcsec
    assert worst < 1e-4 * ARCSEC_RAD, f"filters' model vs the truth's: {worst / ARCSEC_RAD:.2e} arcsec"
    # and the filter, run over the day, ends inside its covariance (NEES against chi-square(6), 99.9 %)
    result = navigate(sim.records, sim.navigation, filter_name="ekf", force_model=model, center=sim.center)
    x = result.history.states[-1]
    P = result.history.covariances[-1]
    error = x - sim.truth[-1]
    assert result.history.accepted.all()
    assert error @ np.linalg.solve(P, error) < stats.chi2.ppf(0.999, 6)


def test_the_moonlet_bends_the_truth_so_its_gravity_is_read(kernels):
    """The moonlet's GM from the PCK moves the coast (the truth's force model has it): without it in
    ``gravity`` the day ends elsewhere by more than the filters' knowledge."""
    with_moonlet = mission.truth_states(_settings(kernels), np.array([mission._epoch(_settings(kernels), "stop")]))
    without = mission.truth_states(_settings(kernels, gravity=("earth", "moon", "sun")),
                                   np.array([mission._epoch(_settings(kernels), "stop")]))
    assert np.linalg.norm(with_moonlet[0, :3] - without[0, :3]) > 1.0


def test_a_body_without_gm_or_outside_the_kernels_is_one_line(kernels, tmp_path):
    spk, _ = kernels
    with pytest.raises(InputError, match=r"kernels: .*do not cover 'moonlet'.*the filters read the kernels' bodies "
                                         r"from 2027-03-08T12:00:00 TDB"):
        _settings(kernels, start="2027-03-15T00:00:00", stop="2027-03-15T12:00:00",
                  state_epoch="2027-03-15T00:00:00")
    with pytest.raises(InputError, match=r"gravity: .*no GM \(BODY2099999_GM\)"):
        mission.Settings(kernels=(spk,), targets=("moon",), gravity=("earth", "moon", "sun", "2099999"))
    with pytest.raises(InputError, match=r"kernels: body 'ceres'.*in no SPK"):
        mission.Settings(kernels=kernels, targets=("ceres",))
    with pytest.raises(InputError, match=r"targets must be names from .*got 'moonlet'"):
        mission.Settings(targets=("moonlet",))


def test_without_kernels_the_filters_read_de421_as_before():
    model = mission.dynamics(mission.Settings())
    assert model.ephemeris is None and mission.filter_ephemeris(mission.Settings()) is None
    assert replace(mission.Settings(), targets=("Moon", "EARTH")).targets == ("moon", "earth")
