"""Navigation filters sharing one interface (see :mod:`opnav.filters.base`).

The public names are exported here (``opnav.filters.__all__``), lazily: importing
``opnav.filters`` loads nothing until a name is used.

- configuration and running: :class:`NavigationConfig` (the ``[navigation]`` table,
  :func:`load_navigation`, :func:`navigation_from_dict`), :func:`build_filter` (a
  filter by name), :func:`measurement_model`, :func:`run_filter` ->
  :class:`FilterHistory`, :func:`run_federated_filter`;
- the state: :class:`Estimate`, :class:`UpdateOutcome`, and the protocols
  :class:`NavigationFilter` and :class:`MeasurementModel`;
- the filters: :class:`ExtendedKalmanFilter` (:class:`EKFOptions`),
  :class:`UnscentedKalmanFilter` (:class:`UKFOptions`), :class:`SquareRootUKF`,
  :class:`AugmentedUKF`, :class:`ParticleFilter` and :class:`UnscentedParticleFilter`
  (:class:`ParticleOptions`), :func:`batch_least_squares` (:class:`BatchOptions`,
  :class:`BatchResult`), :class:`FederatedFilter` (:class:`FederatedOptions`,
  :func:`fuse`) with time registration (:func:`register`), :class:`SwitchingFilter`;
- process noise: :class:`WhiteAcceleration`, :class:`StateNoiseCompensation`;
- consistency: :func:`nees`, :func:`ensemble_nees`, :func:`check_history`, and the
  posterior Cramér-Rao bound :func:`pcrb`.

Every form has a pure-function core and a thin class holding its models; the cores
stay in their modules:

- :mod:`~opnav.filters.ekf`: ``ekf_predict`` / ``ekf_update``;
- :mod:`~opnav.filters.ukf`: ``ukf_predict_estimate`` / ``ukf_update_estimate`` (and the array kernels
  ``ukf_predict`` / ``ukf_update``);
- :mod:`~opnav.filters.sr_ukf`: ``sr_ukf_predict`` / ``sr_ukf_update``;
- :mod:`~opnav.filters.augmented_ukf`: ``augmented_ukf_predict`` / ``augmented_ukf_update``;
- :mod:`~opnav.filters.particle`: ``sir_predict`` / ``sir_update`` and ``upf_predict`` / ``upf_update`` on a
  ``ParticleCloud``.
"""

from .. import lazy_exports

#: The public names of ``opnav.filters``, by the module that defines each (edit here when a module moves).
_EXPORTS: dict[str, tuple[str, ...]] = {
    "opnav.filters.options": ("NavigationConfig", "load_navigation", "navigation_from_dict"),
    "opnav.filters.factory": ("build_filter", "measurement_model", "run_federated_filter"),
    "opnav.filters.run": ("FilterHistory", "run_filter"),
    "opnav.consistency": ("ensemble_nees", "nees"),
    "opnav.filters.base": ("Estimate", "MeasurementModel", "NavigationFilter", "UpdateOutcome"),
    "opnav.filters.ekf": ("EKFOptions", "ExtendedKalmanFilter"),
    "opnav.filters.ukf": ("UKFOptions", "UnscentedKalmanFilter"),
    "opnav.filters.sr_ukf": ("SquareRootUKF",),
    "opnav.filters.augmented_ukf": ("AugmentedUKF",),
    "opnav.filters.particle": ("ParticleFilter", "ParticleOptions", "UnscentedParticleFilter"),
    "opnav.filters.batch": ("BatchOptions", "BatchResult", "batch_least_squares"),
    "opnav.filters.federated": ("FederatedFilter", "FederatedOptions", "fuse"),
    "opnav.filters.registration": ("register",),
    "opnav.filters.switching": ("SwitchingFilter",),
    "opnav.filters.noise": ("StateNoiseCompensation", "WhiteAcceleration"),
    "opnav.filters.monitor": ("check_history",),
    "opnav.filters.crb": ("pcrb",),
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
