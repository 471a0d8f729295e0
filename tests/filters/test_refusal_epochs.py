"""A refused record never stamps an old state with a new time tag (issue 15, part 1)."""

import numpy as np
from test_ukf import BEACONS, P0_ORBIT, X0_ORBIT, BeaconRadec, FixedNoise, Q_ORBIT, gravity_transition

from opnav.filters.base import Estimate
from opnav.filters.ekf import ExtendedKalmanFilter
from opnav.filters.particle import ParticleOptions, UnscentedParticleFilter
from opnav.filters.run import run_filter
from opnav.filters.ukf import UnscentedKalmanFilter
from opnav.records import Measurement


def stm_propagator(t0, x, t1):
    eps = np.array([1e-3] * 3 + [1e-6] * 3)
    x1 = gravity_transition(t0, x, t1)
    cols = [(gravity_transition(t0, x + e, t1) - gravity_transition(t0, x - e, t1)) / (2 * e[i])
            for i, e in enumerate(np.diag(eps))]
    return x1, np.stack(cols, axis=-1)


def filters():
    start = Estimate(0.0, X0_ORBIT, P0_ORBIT)
    common = dict(process_noise=FixedNoise(Q_ORBIT), model=BeaconRadec(BEACONS))
    return {
        "ekf": ExtendedKalmanFilter(start, propagator=stm_propagator, **common),
        "ukf": UnscentedKalmanFilter(start, transition=gravity_transition, **common),
        "upf": UnscentedParticleFilter(start, transition=gravity_transition, rng=np.random.default_rng(0),
                                       options=ParticleOptions(n_particles=20), **common),
    }


def test_bad_noise_moves_the_filter_to_the_record_epoch():
    for name, filt in filters().items():
        record = Measurement(600.0, "radec", [0.1, 0.2], np.zeros((2, 2)), target="a")
        outcome = filt.update(record)
        assert not outcome.accepted, name
        assert outcome.estimate.t_tdb_s == 600.0, name
        np.testing.assert_allclose(outcome.estimate.x[:3], gravity_transition(0.0, X0_ORBIT, 600.0)[:3],
                                   rtol=0, atol=1.0, err_msg=name)


def test_a_record_in_the_past_keeps_the_filter_and_its_epoch():
    for name, filt in filters().items():
        filt.predict(1200.0)
        history = run_filter(filt, [Measurement(600.0, "radec", [0.1, 0.2], np.eye(2) * 1e-8, target="a")],
                             progress=False)
        assert not history.accepted[0], name
        assert history.epochs[0] == 1200.0, name
