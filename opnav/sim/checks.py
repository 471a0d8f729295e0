"""Records against the truth of the frames they were measured on.

- :func:`radec_errors`: every RA/Dec record against the apparent direction its frame's truth
  gives the target: ``chi2 = d^T C^-1 d`` is chi-square(2) when the reported covariance is right;
- :func:`pair_chi2`: each ``radec_pair`` (two moons of one frame with the cross-covariance of the
  attitude they share) against the truth: chi-square(4);
- :func:`starlight_errors`: starlight records against a measurement model's prediction at the
  true state: angle and elevation errors and chi-square per degree of freedom;
- :func:`misidentified_stars`: the stars a tracked frame's attitude used, checked against where
  the rendered truth put them.

``truths`` maps a record's ``frame_id`` to anything with ``target(name)`` giving ``ra_rad`` and
``dec_rad`` (ICRF, rad): a :class:`opnav.render.truth.FrameTruth` or the loop's
:class:`opnav.sim.loop.FrameTargets`.
"""

from __future__ import annotations

import math

import numpy as np

from ..constants import ARCSEC_RAD
from ..errors import InputError
from ..measurements import wrap_angle
from ..records import Measurement, pair_targets, split_radec_pairs

ARCSEC_PER_RAD = 180.0 / math.pi * 3600.0


def pair_chi2(records: list[Measurement], truths: dict) -> np.ndarray:
    """``d^T C^-1 d`` of each ``radec_pair`` record of ``records`` against its frame's truth (``truths``
    as in :func:`radec_errors`): chi-square(4) when the pair's covariance, cross terms included, is right."""
    out = []
    for record in (r for r in records if r.kind == "radec_pair"):
        truth = [truths[record.frame_id].target(name) for name in pair_targets(record)]
        d = record.value - np.array([value for t in truth for value in (t.ra_rad, t.dec_rad)])
        d[[0, 2]] = wrap_angle(d[[0, 2]])
        out.append(float(d @ np.linalg.solve(record.covariance, d)))
    return np.array(out)


def radec_errors(records: list[Measurement], truths: dict) -> dict:
    """Per-target RA/Dec errors of ``records`` against the frames' truth.

    ``truths`` maps a record's ``frame_id`` to its frame's truth (module notes).
    Errors are ``[dRA cos(dec), dDec]`` (rad, tangent plane); their covariance is the record's
    covariance mapped the same way. Returns, per target: ``count``, ``rms_arcsec`` (2,),
    ``mean_arcsec`` (2,) (signed), ``median_sigma_arcsec`` (2,), ``chi2`` (each record's
    ``d^T C^-1 d``, chi-square(2) when ``C`` is right). A ``radec_pair`` counts as its two records.
    """
    records = split_radec_pairs(records)  # a frame's pair counts as its two moons' records
    out = {}
    for name in sorted({r.target for r in records if r.kind == "radec"}):
        errors, sigmas, chi2 = [], [], []
        for record in (r for r in records if r.kind == "radec" and r.target == name):
            target = truths[record.frame_id].target(name)
            scale = np.diag([math.cos(target.dec_rad), 1.0])
            d = scale @ np.array([wrap_angle(record.value[0] - target.ra_rad), record.value[1] - target.dec_rad])
            cov = scale @ record.covariance @ scale
            errors.append(d)
            sigmas.append(np.sqrt(np.diag(cov)))
            chi2.append(float(d @ np.linalg.solve(cov, d)))
        errors, sigmas = np.array(errors), np.array(sigmas)
        out[name] = {
            "count": len(chi2),
            "rms_arcsec": (np.sqrt(np.mean(errors**2, axis=0)) * ARCSEC_PER_RAD).tolist(),
            "mean_arcsec": (np.mean(errors, axis=0) * ARCSEC_PER_RAD).tolist(),
            "median_sigma_arcsec": (np.median(sigmas, axis=0) * ARCSEC_PER_RAD).tolist(),
            "chi2": chi2,
        }
    return out


def starlight_errors(records: list, epochs: np.ndarray, truth: np.ndarray, model) -> dict:
    """Each record's error against the truth's prediction (``model.predict(record, state)`` at the true
    state of ``truth`` (N, 6) at ``epochs`` (N,), TDB s): angle and elevation errors and median
    1-sigma (arcsec), and the mean of d^T C^-1 d over its 2 degrees of freedom (1 when the
    covariances are right)."""
    index = np.searchsorted(epochs, [r.t_tdb_s for r in records])
    if not len(records):
        raise InputError("no starlight records to compare with the truth")
    errors = np.array([r.value - model.predict(r, truth[i]) for r, i in zip(records, index)])
    sigmas = np.array([np.sqrt(np.diag(r.covariance)) for r in records])
    chi2 = np.array([e @ np.linalg.solve(r.covariance, e) for e, r in zip(errors, records)])
    return {
        "records": len(records),
        "angle_rms_arcsec": float(np.sqrt(np.mean(errors[:, 0] ** 2)) / ARCSEC_RAD),
        "elevation_rms_arcsec": float(np.sqrt(np.mean(errors[:, 1] ** 2)) / ARCSEC_RAD),
        "angle_mean_arcsec": float(np.mean(errors[:, 0]) / ARCSEC_RAD),
        "elevation_mean_arcsec": float(np.mean(errors[:, 1]) / ARCSEC_RAD),
        "angle_median_sigma_arcsec": float(np.median(sigmas[:, 0]) / ARCSEC_RAD),
        "elevation_median_sigma_arcsec": float(np.median(sigmas[:, 1]) / ARCSEC_RAD),
        "correlation_median": float(np.median([r.covariance[0, 1] / np.sqrt(r.covariance[0, 0] * r.covariance[1, 1])
                                               for r in records])),
        "chi2_mean_per_dof": float(np.mean(chi2) / 2.0),
    }


def misidentified_stars(tracked, stars) -> tuple[int, int]:
    """(stars the tracked frame's attitude used, those whose centroid is more than 1 px from where the
    rendered truth put that catalog star, or that the truth does not have).

    ``tracked``: :class:`opnav.image.tracking.TrackedFrame`; ``stars``: the frame's
    :class:`opnav.render.truth.StarTruth` (``star_id``, ``xy_px``).
    """
    where = dict(zip(stars.star_id.tolist(), stars.xy_px))
    rows = np.flatnonzero(tracked.used)
    wrong = sum(int(tracked.predicted.star_id[i]) not in where
                or float(np.hypot(*(tracked.centroids.xy[i] - where[int(tracked.predicted.star_id[i])]))) > 1.0
                for i in rows)
    return len(rows), wrong
