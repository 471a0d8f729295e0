"""Build the filters named in a ``[navigation]`` configuration (:mod:`opnav.filters.options`).

:func:`build_filter` makes one sequential filter (``ekf``, ``ukf``, ``sr-ukf``,
``pf``, ``upf``, ``mcmc-upf``) from the configuration's initial estimate,
process noise, gate and per-filter options; :func:`run_federated_filter` sets
up and runs the federated filter (one local filter per sensor). Batch least
squares (``wls``) needs no set-up beyond :func:`opnav.filters.batch.batch_least_squares`.

All but the EKF live in modules of their own and are imported only when asked
for (:data:`LAZY_FILTERS`), so a missing one gives a clear :class:`InputError`
instead of breaking every filter.
"""

from __future__ import annotations

import importlib
from dataclasses import replace

import numpy as np

from ..errors import InputError
from .options import NavigationConfig
from ..records import Measurement
from .base import Estimate, MeasurementModel, NavigationFilter
from .ekf import EKFOptions, ExtendedKalmanFilter, force_model_propagator
from .noise import process_noise_from_config
from .run import FilterHistory

#: filter name -> (module, class) imported on demand.
LAZY_FILTERS = {
    "ukf": ("opnav.filters.ukf", "UnscentedKalmanFilter"),
    "sr-ukf": ("opnav.filters.sr_ukf", "SquareRootUKF"),
    "pf": ("opnav.filters.particle", "ParticleFilter"),
    "upf": ("opnav.filters.particle", "UnscentedParticleFilter"),
    "mcmc-upf": ("opnav.filters.particle", "UnscentedParticleFilter"),
    "federated": ("opnav.filters.federated", "FederatedFilter"),
}


def _lazy(name: str):
    """The class of filter ``name`` from :data:`LAZY_FILTERS`; :class:`InputError` if it cannot be imported."""
    module_name, attr = LAZY_FILTERS[name]
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise InputError(f"filter {name!r} is not available: cannot import {module_name} ({exc})") from None
    if not hasattr(module, attr):
        raise InputError(f"filter {name!r} is not available: {module_name} has no {attr}")
    return getattr(module, attr)


def measurement_model(nav: NavigationConfig, center: str, *, ephemeris=None):
    """The :class:`~opnav.measurements.ProbeMeasurementModel` a filter of ``nav`` uses for states about ``center``.

    The fast path (default) reads the ephemeris through a Chebyshev cache, which also switches light
    time and aberration to their compiled twins; ``nav.exact`` reads the cache's source directly.
    The cache is ``ephemeris`` when given (an :class:`~opnav.ephemeris.cache.EphemerisCache`, e.g.
    a mission's kernels, :class:`opnav.ephemeris.spice.KernelCache`; :attr:`opnav.dynamics.ForceModel.ephemeris`
    is the one a force model names), else the process-wide one of DE421 and the moon model. With
    ``nav.ephemeris_error`` ``estimate`` or ``consider`` the model is a
    :class:`~opnav.measurements.TargetOffsetModel` over the augmented state; with ``nav.camera_error``
    ``consider`` a :class:`~opnav.measurements.CameraOffsetModel` over the state augmented with the
    camera's parameter errors.
    """
    from ..ephemeris import default_ephemeris
    from ..ephemeris.cache import default_cached_ephemeris
    from ..measurements import ProbeMeasurementModel

    if ephemeris is None:
        source = default_ephemeris() if nav.exact else default_cached_ephemeris()
    else:
        source = ephemeris.ephemeris if nav.exact else ephemeris
    white = nav.ephemeris_error == "white"
    model = ProbeMeasurementModel(center, light_time=nav.light_time, aberration=nav.aberration,
                                  target_position_sigma_km=nav.target_position_sigma_km if white else 0.0,
                                  ephemeris=source)
    if nav.camera_error == "consider":
        from ..measurements import CameraOffsetModel

        return CameraOffsetModel(model, nav.camera_parameters)
    if white:
        return model
    from ..measurements import TargetOffsetModel

    return TargetOffsetModel(model, nav.ephemeris_targets)


def build_filter(name: str, nav: NavigationConfig, model: MeasurementModel, force_model) -> NavigationFilter:
    """The sequential filter ``name`` configured from ``nav``.

    Parameters
    ----------
    name : str
        ``ekf``, ``ukf``, ``sr-ukf``, ``pf``, ``upf`` or ``mcmc-upf`` (not ``wls`` or ``federated``).
    nav : NavigationConfig
        Initial estimate (``t0_tdb_s``, ``x0``, ``P0``, augmented with the ephemeris offsets
        when ``ephemeris_error`` is not ``white``, with the camera's parameter errors when
        ``camera_error`` is ``consider``), process noise, gate probability,
        ``[navigation.ukf]`` / ``[navigation.particle]`` options, the particle filters' seed and
        ``exact`` (DOP853 instead of the compiled fast propagator).
    model : MeasurementModel
        e.g. :class:`opnav.measurements.ProbeMeasurementModel` for the force model's centre.
    force_model
        :mod:`opnav.dynamics` force model the filter propagates with.

    Returns
    -------
    NavigationFilter
        A new filter at ``nav.t0_tdb_s``; the particle filters draw from
        ``numpy.random.default_rng(nav.seed)``.

    Raises
    ------
    InputError
        If the filter's module cannot be imported or an option is invalid.
    """
    if nav.ephemeris_error != "white" and name not in ("ekf", "ukf", "sr-ukf", "pf", "upf", "mcmc-upf"):
        raise InputError(f"filter {name!r} does not take ephemeris_error = {nav.ephemeris_error!r}; use 'white'")
    if nav.ephemeris_error == "consider" and name != "ekf":
        raise InputError(f"ephemeris_error = 'consider' works with the EKF only, not {name!r}; use 'estimate'")
    if nav.camera_error == "consider" and name != "ekf":
        raise InputError(f"camera_error = 'consider' works with the EKF only, not {name!r}")
    estimate = Estimate(nav.t0_tdb_s, *nav.augmented)
    noise = process_noise_from_config(nav.process_noise)
    if name == "ekf":
        held = "consider" in (nav.ephemeris_error, nav.camera_error)
        consider = tuple(range(6, estimate.x.size)) if held else ()
        return ExtendedKalmanFilter(estimate, propagator=force_model_propagator(force_model, exact=nav.exact), model=model,
                                    process_noise=noise,
                                    options=EKFOptions(gate_probability=nav.gate_probability, consider=consider))
    factory = _lazy(name)
    from .ukf import force_model_transition

    transition = force_model_transition(force_model, exact=nav.exact)
    if name in ("ukf", "sr-ukf"):
        options = replace(nav.ukf, gate_probability=nav.gate_probability)
        return factory(estimate, transition=transition, process_noise=noise, model=model, options=options)
    options = replace(nav.particle, gate_probability=nav.gate_probability)
    if name in ("upf", "mcmc-upf"):
        options = replace(options, mcmc_move=name == "mcmc-upf")
    return factory(estimate, transition=transition, process_noise=noise, model=model,
                   rng=np.random.default_rng(nav.seed), options=options)


def run_federated_filter(
    nav: NavigationConfig, records: list[Measurement], model: MeasurementModel, force_model
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], FilterHistory]:
    """Run the federated filter with one local filter per ``record.sensor`` and equal sharing factors.

    Parameters
    ----------
    nav : NavigationConfig
        As for :func:`build_filter`; ``nav.federated`` (:class:`~opnav.filters.federated.FederatedSetup`)
        gives the local filter (default ``ekf``), the mode (default ``fusion-reset``) and the
        fusion interval (default: fuse at every record epoch).
    records : list of Measurement
        All sensors' records; ``record.sensor`` routes each to its local filter.
    model : MeasurementModel
    force_model
        :mod:`opnav.dynamics` force model of the local filters.

    Returns
    -------
    fused : tuple of (M,), (M, n), (M, n, n) arrays
        Fusion epochs (TDB s past J2000), fused states and covariances.
    history : FilterHistory
        Per record (in epoch order), the outcome of its local filter.

    Raises
    ------
    InputError
        If the federated filter's module cannot be imported (the ``[navigation.federated]``
        options were checked when ``nav`` was loaded).
    """
    federated = _lazy("federated")
    from .federated import FederatedOptions, run_federated

    setup = nav.federated
    sensors = sorted({r.sensor for r in records})
    fed = federated({s: build_filter(setup.local_filter, nav, model, force_model) for s in sensors},
                    initial=Estimate(nav.t0_tdb_s, nav.x0, nav.P0),
                    options=FederatedOptions(betas={s: 1.0 / len(sensors) for s in sensors}, routes={s: s for s in sensors},
                                             mode=setup.mode))
    epochs = np.unique([r.t_tdb_s for r in records])
    if setup.fusion_interval_s is not None:
        step = setup.fusion_interval_s
        epochs = np.arange(epochs[0], epochs[-1] + step, step)
    fused, outcomes = run_federated(fed, records, epochs)
    ordered = sorted(records, key=lambda r: r.t_tdb_s)
    m_max = max(r.size for r in ordered)
    residuals = np.full((len(ordered), m_max), np.nan)
    for i, (r, o) in enumerate(zip(ordered, outcomes)):
        residuals[i, : r.size] = o.residual
    history = FilterHistory(
        epochs=np.array([r.t_tdb_s for r in ordered]), states=np.stack([o.estimate.x for o in outcomes]),
        covariances=np.stack([o.estimate.P for o in outcomes]), residuals=residuals,
        nis=np.array([o.nis for o in outcomes]), dof=np.array([r.size for r in ordered]),
        accepted=np.array([o.accepted for o in outcomes]), reasons=tuple(o.reason for o in outcomes),
        kinds=tuple(r.kind for r in ordered), targets=tuple(r.target for r in ordered),
    )
    fused_track = (np.array([e.t_tdb_s for e in fused]), np.stack([e.x for e in fused]), np.stack([e.P for e in fused]))
    return fused_track, history
