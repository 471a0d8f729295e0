"""Measurement-level twins of an image-mode run (shared by the from-pixels benchmarks).

A twin keeps a run's records (epochs, targets, stars, covariances) and replaces each value by
one drawn from the record's own covariance around the truth's prediction: what the filters
would get from a perfect image stage that reports its noise honestly. Over the judged window
a run's position error lies mostly along one weakly observed axis, so its RMS is close to a
single draw of a quantity with one or two degrees of freedom (one S3 seed's twins span 0.006
to 0.031 km, one S1 seed's 9.7 to 15.5 km): the measurement-level expectation is the mean over
several twins, not one.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from opnav.ephemeris.cache import default_cached_ephemeris
from opnav.measurements import ProbeMeasurementModel
from opnav.records import split_radec_pairs
from opnav.studies.runner import filter_stage


def twin_records(sim, seed: int, draw: int = 0) -> list:
    """The records of ``sim`` with values drawn around the truth's prediction from the covariance the
    filters use for them (stream ``draw`` of ``seed``): the record's own, plus the white target-
    ephemeris error the navigation set-up models (S1: the moons 1 km off per frame, 0.01-0.03",
    which the frames show and the filters add to each record)."""
    nav = sim.navigation
    sigma_km = nav.target_position_sigma_km if nav.ephemeris_error == "white" else 0.0
    model = ProbeMeasurementModel(sim.center, ephemeris=default_cached_ephemeris(), target_position_sigma_km=sigma_km)
    rng = np.random.default_rng([seed, 303] + ([draw] if draw else []))
    index = np.searchsorted(sim.epochs, [r.t_tdb_s for r in sim.records])
    return [replace(r, value=model.predict(r, sim.truth[i])
                    + np.linalg.cholesky(model.noise_covariance(r, sim.truth[i])) @ rng.standard_normal(r.size))
            for r, i in zip(sim.records, index)]


def twin_means(sim, key: str, seed: int, draws: int, filters, out) -> dict:
    """Each filter's position RMS, NEES mean and share of epochs in the NEES band, averaged over
    ``draws`` twins of ``sim`` (filter runs kept under ``out``/twin<k>, reused by ``key``)."""
    runs: dict = {name: [] for name in filters}
    for draw in range(draws):
        twin = replace(sim, records=twin_records(sim, seed, draw))
        tag = "twin" + (f"{draw}" if draw else "")
        for name in filters:
            runs[name].append(filter_stage(name, twin, f"{key}:{tag}:ephemeris-noise", out / tag, False,
                                                           lambda message: None))
    return {name: {field: float(np.mean([run[field] for run in done]))
                   for field in ("position_rms_km", "nees_mean", "nees_fraction_in_95")}
            for name, done in runs.items()}


def measured_where_imaged(measured, imaged) -> tuple:
    """The measurement-mode simulation ``measured`` with only the records of a moon at an epoch
    where the image-mode simulation ``imaged`` of the same run measured that moon (each of a
    ``radec_pair``'s two counts): the papers' constant noise, the camera's availability (a moon
    behind Mars, on its disk or in its halo gives no record). Returns (simulation, share of the
    measurement-mode records kept per moon)."""
    seen = {(round(r.t_tdb_s), r.target) for r in split_radec_pairs(imaged.records)}
    kept = [r for r in measured.records if (round(r.t_tdb_s), r.target) in seen]
    share = {}
    for target in sorted({r.target for r in measured.records}):
        total = sum(r.target == target for r in measured.records)
        share[target] = sum(r.target == target for r in kept) / total
    return replace(measured, records=kept), share
