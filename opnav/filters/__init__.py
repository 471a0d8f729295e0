"""Navigation filters sharing one interface (see :mod:`opnav.filters.base`).

Every form has a pure-function core and a thin class holding its models:

- :mod:`~opnav.filters.ekf`: ``ekf_predict`` / ``ekf_update``, :class:`~opnav.filters.ekf.ExtendedKalmanFilter`;
- :mod:`~opnav.filters.ukf`: ``ukf_predict_estimate`` / ``ukf_update_estimate`` (and the array kernels
  ``ukf_predict`` / ``ukf_update``), :class:`~opnav.filters.ukf.UnscentedKalmanFilter`;
- :mod:`~opnav.filters.sr_ukf`: ``sr_ukf_predict`` / ``sr_ukf_update``, :class:`~opnav.filters.sr_ukf.SquareRootUKF`;
- :mod:`~opnav.filters.augmented_ukf`: ``augmented_ukf_predict`` / ``augmented_ukf_update``,
  :class:`~opnav.filters.augmented_ukf.AugmentedUKF`;
- :mod:`~opnav.filters.particle`: ``sir_predict`` / ``sir_update`` and ``upf_predict`` / ``upf_update`` on a
  :class:`~opnav.filters.particle.ParticleCloud`, :class:`~opnav.filters.particle.ParticleFilter` and
  :class:`~opnav.filters.particle.UnscentedParticleFilter`;
- :mod:`~opnav.filters.batch`: ``batch_least_squares``.

:mod:`~opnav.filters.federated` fuses local filters, :mod:`~opnav.filters.factory` builds any of them from a
``[navigation]`` configuration, and :mod:`~opnav.filters.run` runs one over a record set.
"""
