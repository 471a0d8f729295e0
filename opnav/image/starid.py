"""Star identification: lost-in-space (pattern hashing) and tracking (a-priori attitude).

Lost in space, :func:`identify` (index from :mod:`opnav.image.starid_index`)
------------------------------------------------------------------------------
1. Take the first ``pattern_checking_stars`` bearings (rows are ordered most reliable first:
   :func:`opnav.image.extract.extract_stars` sorts by detection signal-to-noise ratio, so the search starts from
   stars and not from faint false detections) and every 4-subset of them, ordered so that
   subsets of earlier stars come first (all subsets of the first 4, then those adding the 5th, ...).
2. For each subset compute its 5 sorted edge ratios; the probe keys are every bin
   combination within ``pattern_max_error`` of them (at most 2 bins per ratio, 32 keys).
   The keys of a block of subsets (step 4) are looked up at once, each by a binary search of the index's
   distinct keys (:func:`opnav.image.starid_compiled.lookup_kernel`).
3. Keep catalog patterns whose ratios agree within ``pattern_max_error`` and whose largest
   edge agrees with the image's within the allowed focal-length range ``fov_tolerance``.
4. For each surviving candidate, best ratio fit first within each block of subsets (those of the
   first ``FIRST_BLOCK_STARS`` stars, then those adding each later star): find the star correspondence (the
   permutation of the 4 catalog stars whose angle matrix best fits the image's; a mirror
   pattern fails step 5), scale the bearings' tangent-plane coordinates by the focal-length
   ratio ``focal_scale = f_true / f_assumed`` and solve Wahba's problem. A block's best fit is
   found first from each image pattern's own key and the few keys that could hold a better fit
   (:func:`_best_fit_of_own_keys`); when it is accepted with the Bonferroni count of step 6 taken
   as ``max_candidates``, the block's other keys are not read.
5. Verification: predict every index star in the field from that attitude, match bearings
   within ``match_radius_rad`` one-to-one, re-solve with all matches (and re-fit the focal
   scale when it is free) and match again. Steps 4-5 of a candidate, the search of the field's index
   stars included, are one compiled kernel (:func:`opnav.image.starid_compiled.verify_kernel`).
6. False-match test, the product of two independent chances under the hypothesis that the
   candidate is false:

   - *the pattern's own fit.* A false candidate is a catalog pattern whose sorted edge ratios
     happen to lie within ``pattern_max_error`` (``e``) of the image's. Catalog patterns are
     spread smoothly over ratio space at that scale, and the ratios of a 4-star pattern in a
     narrow field have 4 degrees of freedom (8 tangent-plane coordinates less a similarity), so
     the largest ratio difference ``d`` of a false candidate has ``P[d <= t] = (t / e)^4``. A
     true pattern fits to its centroid noise, ``d`` ~ 1e-4 where ``e`` is 8e-3: this is what
     keeps the test strict with few stars. The ratios are recomputed with the fitted focal
     scale and the catalog stars at their epoch.
   - *the other stars:* ``n`` image stars down to the last matched row, ``m`` matches, and
     ``p`` the chance that one image star falls by accident within the match radius of one of
     the ``n_cat`` index stars predicted in the field (area ratio). The 4 pattern stars match
     by construction, so ``P[X >= m - 4]`` for ``X ~ Binomial(n - 4, p)``; at least one star
     beyond the pattern must match (``m >= 5``).

   Accept the first candidate with ``K * p_false <= p_false_max``, ``K`` the number of
   candidates found by the lookups made so far (a Bonferroni bound on the chance that any of
   them matched by accident); otherwise raise :class:`opnav.errors.NoSolutionError`.

Tracking, :func:`track`
-----------------------
Catalog stars are predicted from the a-priori attitude. Each image star's candidates are the
stars within ``gate_sigma * prior_sigma_rad`` of its prior direction. Hypotheses are pairs of
image stars matched to pairs of candidates with the same angular separation (the
rotation-invariant); each gives a TRIAD attitude, and the one with most inliers wins (all
hypotheses are scored at once; when there are more than ``max_hypotheses``, half of them are
those whose separations agree best and half a random draw of the rest from ``rng``). The winner
is refined and tested as in step 6, with ``p`` the chance of a coincidence within the prior
gate instead of the whole field and the 2 hypothesis stars (instead of 4) matching by
construction. The tail is multiplied by the expected number of chance hypotheses (a union bound
over every pair of candidates the hypothesis stars offer): ``E = sum_{i<j} N_i N_j q`` with
``N_i`` the candidates of hypothesis star ``i`` and ``q`` the chance that two stars placed at
random in their gates (radius ``G``) have the image pair's separation to within twice the match
radius ``r``. For ``r << G``, ``q = (64 / 3 pi^2) r / G`` (the separation difference is the
difference of two projections of uniform disks, of density ``16 / (3 pi^2 G)`` at zero); gates
that overlap raise it by up to 1.21x (Monte Carlo over the pair's separation), so ``q = 1.25
(64 / 3 pi^2) r / G``, at most 1. A sparse prior gate (``E < 1``) credits the pair's agreement;
a crowded one (many candidate pairs) is stricter than the tail alone. The solution must also
lie within the prior's 3-D gate (the chi-square tail probability of ``gate_sigma`` in 2-D).
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import time
import weakref
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from scipy.special import bdtrc, chdtrc, chdtri

from ..camera import Camera
from ..errors import CatalogError, InputError, NoSolutionError
from .attitude import shuster_covariance, wahba_rotation
from .detect import DetectOptions
from .extract import extract_stars
from .starid_compiled import REJECT, lookup_kernel, rigid_kernel, rotation_quaternion, verify_kernel
from .starid_index import (
    EDGE_FIRST,
    EDGE_SECOND,
    PatternIndex,
    StarSource,
    pair_angles,
    pattern_ratios,
)

log = logging.getLogger(__name__)

#: Default verification match radius of :func:`solve_stars`, px, and in centroid sigmas (the larger wins).
MATCH_RADIUS_PX = 2.0
MATCH_RADIUS_SIGMAS = 4.0


@dataclass(frozen=True)
class Identification:
    """Matched stars and the attitude they give.

    Attributes
    ----------
    pairs : ndarray, shape (M, 2) int
        ``(bearing row, catalog row)`` of each matched star; catalog rows index the catalog the
        index (or :func:`track`) was given.
    v_icrf : ndarray, shape (M, 3)
        Catalog unit directions of the matched stars, ICRF.
    p_false : float
        Probability that a random attitude would match as many stars (module step 6).
    R_icrf_cam : Rotation
        Camera frame -> ICRF.
    cov_rad2 : ndarray, shape (3, 3)
        Covariance of the camera-frame small rotation vector, rad^2
        (:func:`opnav.image.attitude.shuster_covariance`).
    focal_scale : float
        Fitted ``f_true / f_assumed`` (1 when the focal length was held fixed).
    residuals_rad : ndarray, shape (M,)
        Angle between each matched bearing (after focal scaling) and its predicted direction, rad.
    sigma_rad : float
        Per-axis bearing noise used for the covariance (given or estimated from the residuals), rad.
    n_candidates : int
        Pattern candidates (or tracking hypotheses) examined.
    """

    pairs: np.ndarray
    v_icrf: np.ndarray
    p_false: float
    R_icrf_cam: Rotation
    cov_rad2: np.ndarray
    focal_scale: float
    residuals_rad: np.ndarray
    sigma_rad: float
    n_candidates: int


def bearings(xy: np.ndarray, camera: Camera) -> np.ndarray:
    """Pixel positions (N, 2) -> unit directions (N, 3) in the camera frame (docs/conventions.md).

    Raises
    ------
    InputError
        Wrong shape or non-finite positions.
    """
    xy = np.asarray(xy, dtype=float)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise InputError(f"xy must have shape (N, 2), got {xy.shape}")
    if not np.all(np.isfinite(xy)):
        raise InputError("xy contains NaN or infinite pixel positions")
    return camera.unproject(xy)


def _as_bearings(value: np.ndarray) -> np.ndarray:
    b = np.asarray(value, dtype=float)
    if b.ndim != 2 or b.shape[1] != 3:
        raise InputError(f"bearings must have shape (N, 3), got {b.shape}")
    if not np.all(np.isfinite(b)):
        raise InputError("bearings contain NaN or infinite values")
    if np.any(b[:, 2] <= 0.0):
        raise InputError("bearings must point into the camera's hemisphere (z > 0)")
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def _rescale(b_cam: np.ndarray, focal_scale: float) -> np.ndarray:
    """Bearings as seen with focal length ``f_assumed * focal_scale`` (tangent plane / scale)."""
    tangent = b_cam[:, :2] / b_cam[:, 2:] / focal_scale
    d = np.column_stack([tangent, np.ones(len(b_cam))])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return 2.0 * np.arcsin(np.minimum(np.linalg.norm(a - b, axis=-1) / 2.0, 1.0))


@lru_cache(maxsize=64)
def _subsets_brightest_first(n: int) -> np.ndarray:
    rows = [(*first, last) for last in range(3, n) for first in itertools.combinations(range(last), 3)]
    return np.array(rows, dtype=np.int64).reshape(-1, 4)


def _match_one_to_one(b_cam: np.ndarray, c_cam: np.ndarray, radius_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows (image, catalog) of nearest pairs within ``radius_rad``, each row used at most once."""
    if len(c_cam) == 0:
        return np.empty(0, int), np.empty(0, int)
    cosines = b_cam @ c_cam.T
    nearest = np.argmax(cosines, axis=1)
    best = cosines[np.arange(len(b_cam)), nearest]
    close = np.flatnonzero(best >= math.cos(radius_rad))
    close = close[np.argsort(-best[close], kind="stable")]
    _, first = np.unique(nearest[close], return_index=True)
    kept = np.sort(close[first])
    return kept, nearest[kept]


def _p_false(rows_matched: np.ndarray, p_single: float, n_fixed: int) -> float:
    """``P[X >= m - k]`` for ``X ~ Binomial(n - k, p)``, ``k = n_fixed`` (module step 6).

    ``n`` counts the image stars down to the last matched row: later (fainter, less significant) stars are
    beyond the catalog depth in a deep frame and say nothing about the match.
    """
    m = len(rows_matched)
    if m <= n_fixed:
        return 1.0
    n = int(np.max(rows_matched)) + 1
    return float(bdtrc(m - n_fixed - 1, n - n_fixed, min(p_single, 1.0)))


def _scored_hypotheses(disagreement_rad: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Rows (sorted) of the ``count`` tracking hypotheses scored out of more (module: Tracking).

    Half are those whose catalog pair's separation agrees best with the image pair's: a true pair
    disagrees by its two centroids' noise (hundredths of a pixel), a chance pair uniformly over the
    +-2 r tolerance. A random draw of 4,000 of them all lost the 15 true pairs of a crowded frame
    (320 px at 3.5"/px with the pipeline's 0.05-degree prior: ~200 catalog stars in each star's
    220 px gate, 18,231 hypotheses) in 0.78^15 = 2.4 % of draws, and star ID failed. The other
    half is drawn at random from the rest, so a camera whose model misstates separations by more
    than its noise still has a chance at its true pairs.
    """
    order = np.argsort(disagreement_rad, kind="stable")
    best = count - count // 2
    drawn = rng.choice(order[best:], count // 2, replace=False)
    return np.sort(np.concatenate([order[:best], drawn]))


#: Chance that two stars at random in their prior gates (radius G) have a given separation to
#: within +-2 r, over r / G (module: Tracking): 64 / (3 pi^2) for gates far apart, times 1.25 for
#: the most that overlapping gates raise it.
PAIR_SEPARATION_CHANCE = 1.25 * 64.0 / (3.0 * math.pi**2)


def _chance_hypotheses(in_gate: np.ndarray, radius_rad: float, gate_rad: float) -> float:
    """Expected number of tracking hypotheses formed by chance (module: Tracking): the pairs of
    candidates of the hypothesis stars (rows of ``in_gate``) times the chance of an agreeing separation."""
    counts = np.sum(in_gate, axis=1).astype(float)
    pairs = 0.5 * (counts.sum() ** 2 - np.sum(counts**2))
    return float(pairs * min(1.0, PAIR_SEPARATION_CHANCE * radius_rad / gate_rad))


def _sigma(residuals_rad: np.ndarray, sigma_rad: float | None) -> float:
    if sigma_rad is not None:
        return float(sigma_rad)
    # Each residual has two tangent components; the attitude absorbs three degrees of freedom.
    return float(max(np.sqrt(np.sum(residuals_rad**2) / max(2 * len(residuals_rad) - 3, 1)), 1e-9))


def _finish(
    b_cam: np.ndarray,
    rows_image: np.ndarray,
    v_icrf: np.ndarray,
    catalog_rows: np.ndarray,
    rotation: Rotation,
    p_false: float,
    focal_scale: float,
    sigma_rad: float | None,
    n_candidates: int,
) -> Identification:
    # v @ R is R^-1 v (camera frame), as rotation.inv().apply(v) gives it at a third of the cost
    residuals = _angles(b_cam[rows_image], v_icrf @ rotation.as_matrix())
    sigma = _sigma(residuals, sigma_rad)
    return Identification(
        pairs=np.column_stack([rows_image, catalog_rows]).astype(np.int64),
        v_icrf=v_icrf,
        p_false=p_false,
        R_icrf_cam=rotation,
        cov_rad2=shuster_covariance(b_cam[rows_image], np.full(len(rows_image), sigma)),
        focal_scale=focal_scale,
        residuals_rad=residuals,
        sigma_rad=sigma,
        n_candidates=n_candidates,
    )


def _check_common(p_false_max: float, sigma_rad: float | None) -> None:
    if not (0.0 < p_false_max < 1.0):
        raise InputError(f"p_false_max must be in (0, 1), got {p_false_max!r}")
    if sigma_rad is not None and not (math.isfinite(sigma_rad) and sigma_rad > 0.0):
        raise InputError(f"sigma_rad must be positive, got {sigma_rad!r}")


#: Stars whose 4-subsets form the first block of lookups (:func:`identify`, module step 4).
FIRST_BLOCK_STARS = 6


def _lookup(
    ratios: np.ndarray, largest: np.ndarray, index: PatternIndex, max_error: float, allowed_log_scale: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidates (subset row, pattern row, focal scale) for image patterns, smallest ratio error first
    (then subset, then pattern row; steps 2-3, :func:`opnav.image.starid_compiled.lookup_kernel`)."""
    return _candidates(ratios, largest, index, max_error, allowed_log_scale, False)[:3]


#: Stored pattern ratios are float32, their keys of the float64 ratios: a stored ratio may lie this far
#: beyond its key's bin (float32's half-ulp of a ratio <= 1 is 6e-8).
_STORED_RATIO_SLACK = 1e-6


def _candidates(ratios: np.ndarray, largest: np.ndarray, index: PatternIndex, max_error: float,
                allowed_log_scale: float, first_only: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """:func:`opnav.image.starid_compiled.lookup_kernel`'s candidates (subset row, pattern row, focal scale),
    smallest ratio error first, and whether they settle the first candidate (``complete``)."""
    unique_keys, bounds = index.key_directory
    subset_of, pattern_of, scale, ratio_error, complete = lookup_kernel(
        np.ascontiguousarray(ratios, dtype=float), np.ascontiguousarray(largest, dtype=float), np.asarray(unique_keys),
        np.asarray(bounds), np.asarray(index.ratios), np.asarray(index.max_edge_rad), float(max_error),
        float(allowed_log_scale), int(index.options.pattern_bins), first_only, _STORED_RATIO_SLACK)
    # best fit first: a true pattern fits to its centroid noise (~1e-4 of the tolerance's 8e-3), so it
    # is verified before the chance fits of the block (31-133 of them a demo frame in subset order)
    order = np.lexsort((pattern_of, subset_of, ratio_error))
    return subset_of[order], pattern_of[order], scale[order], complete


def identify(
    bearings: np.ndarray,
    index: PatternIndex,
    *,
    fov_tolerance: float = 0.0,
    pattern_checking_stars: int = 16,
    pattern_max_error: float = 0.008,
    match_radius_rad: float | None = None,
    p_false_max: float = 1e-5,
    sigma_rad: float | None = None,
    max_candidates: int = 500,
) -> Identification:
    """Lost-in-space identification of star bearings (module steps 1-6).

    Parameters
    ----------
    bearings : ndarray, shape (N, 3)
        Unit directions of image stars in the camera frame, **most reliable first** (highest
        signal-to-noise ratio, as :func:`opnav.image.extract.extract_stars` orders them, or brightest), computed with an
        assumed focal length (:func:`bearings`).
    index : PatternIndex
        From :func:`opnav.image.starid_index.build_index`.
    fov_tolerance : float
        Allowed relative error of the assumed focal length (0 = known; 0.1 = +-10 %).
    pattern_checking_stars : int
        Leading bearings used to form 4-star patterns.
    pattern_max_error : float
        Largest edge-ratio difference accepted between image and catalog patterns.
    match_radius_rad : float, optional
        Verification match radius, rad; default 0.5 % of the angular diagonal spanned by the bearings.
    p_false_max : float
        Accept a solution only if its false-match probability is at most this.
    sigma_rad : float, optional
        Per-axis bearing noise for the covariance, rad; default estimated from the residuals.
    max_candidates : int
        Give up after verifying this many pattern candidates.

    Returns
    -------
    Identification

    Raises
    ------
    NoSolutionError
        Fewer than 4 bearings, or no candidate passes verification.
    InputError
        Bad bearings or options.
    """
    b = _as_bearings(bearings)
    _check_common(p_false_max, sigma_rad)
    if not (0.0 <= fov_tolerance <= 0.5):
        raise InputError(f"fov_tolerance must be in [0, 0.5], got {fov_tolerance!r}")
    if not (4 <= pattern_checking_stars <= 30):
        raise InputError(f"pattern_checking_stars must be in [4, 30], got {pattern_checking_stars!r}")
    if not (0.0 < pattern_max_error < 0.1):
        raise InputError(f"pattern_max_error must be in (0, 0.1), got {pattern_max_error!r}")
    if len(b) < 4:
        raise NoSolutionError(f"lost-in-space identification needs at least 4 stars, got {len(b)}")
    if match_radius_rad is None:
        radius = 0.01 * float(np.max(np.arccos(np.clip(b[:, 2], -1.0, 1.0))))  # of the half extent
    else:
        radius = float(match_radius_rad)
    if not (radius > 0.0):
        raise InputError(f"match_radius_rad must be positive, got {match_radius_rad!r}")

    subsets = _subsets_brightest_first(min(len(b), pattern_checking_stars))
    allowed = math.log1p(fov_tolerance) + 3.0 * pattern_max_error
    # Subsets of the first FIRST_BLOCK_STARS first, then those adding each later star: a typical frame
    # is solved from the first block, so later lookups are only paid when needed (each match a
    # lookup gathers is a read of the memory-mapped index: the 70 subsets of 8 stars gathered ~30,000,
    # 1-2 ms a frame, to verify the first candidate)
    bounds = [0] + [math.comb(last, 4) for last in range(FIRST_BLOCK_STARS, len(b) + 1)
                    if math.comb(last, 4) <= len(subsets)]
    bounds = sorted(set(bounds + [len(subsets)]))
    verify = dict(free_scale=fov_tolerance > 0.0, radius=radius, pattern_max_error=pattern_max_error)
    accept = dict(p_false_max=p_false_max, fov_tolerance=fov_tolerance, sigma_rad=sigma_rad)
    tried = 0
    for lo, hi in itertools.pairwise(bounds):
        ratios, largest = pattern_ratios(pair_angles(b[subsets[lo:hi]], EDGE_FIRST, EDGE_SECOND))
        best_fit = _UNVERIFIED
        if tried < max_candidates:
            found, best_fit = _best_fit_of_own_keys(b, subsets[lo:hi], ratios, largest, index, pattern_max_error,
                                                    allowed, max_candidates, tried, verify, accept)
            if found is not None:
                return found
        subset_of, pattern_of, scale = _lookup(ratios, largest, index, pattern_max_error, allowed)
        looked_up = tried
        rigid = None
        for candidate in range(len(subset_of)):
            if tried == max_candidates:
                break
            tried += 1
            if candidate == 1:  # the best fit (most often the true pattern) failed: screen the rest at once
                rest = slice(1, 1 + max_candidates - tried + 1)
                rigid = np.ones(len(subset_of), bool)
                rigid[rest] = _rigid_candidates(b, subsets[lo + subset_of[rest]], index.patterns[pattern_of[rest]],
                                                index, scale[rest] if fov_tolerance > 0.0 else None, radius)
            if rigid is not None and not rigid[candidate]:
                continue  # its pattern's angles disagree: _verify_candidate's first test would reject it
            if candidate == 0 and best_fit is not _UNVERIFIED:
                solution = best_fit  # this candidate, verified by _best_fit_of_own_keys
            else:
                solution = _verify_candidate(b, subsets[lo + subset_of[candidate]],
                                             index.patterns[pattern_of[candidate]], index,
                                             focal_scale=float(scale[candidate]) if fov_tolerance > 0.0 else 1.0,
                                             **verify)
            found = _accepted(b, index, solution, min(looked_up + len(subset_of), max_candidates), tried, **accept)
            if found is not None:
                return found
        if tried == max_candidates:
            break
    raise NoSolutionError(
        f"no star pattern passed verification ({tried} candidates from {len(b)} stars, "
        f"p_false_max {p_false_max:g})"
    )


def _accepted(b: np.ndarray, index: PatternIndex, solution: tuple | None, offered: int, tried: int, *,
              p_false_max: float, fov_tolerance: float, sigma_rad: float | None) -> Identification | None:
    """The identification of a verified candidate (:func:`_verify_candidate`'s ``solution``) when it passes
    the false-match test (module step 6) among ``offered`` candidates and its focal scale is within the
    tolerance, else None."""
    if solution is None:
        return None
    rows_image, rows_index, v_matched, matrix, focal_scale, p_false = solution
    # Bonferroni: every candidate the lookups have offered is a chance for a false match.
    if p_false * offered <= p_false_max and abs(math.log(focal_scale)) <= math.log1p(fov_tolerance) + 1e-3:
        rotation = Rotation.from_quat(rotation_quaternion(matrix))
        return _finish(_rescale(b, focal_scale), rows_image, v_matched, index.catalog_rows[rows_index], rotation,
                       p_false, focal_scale, sigma_rad, tried)
    return None


#: :func:`_best_fit_of_own_keys` could not tell the block's first candidate.
_UNVERIFIED = object()


def _best_fit_of_own_keys(b: np.ndarray, subsets: np.ndarray, ratios: np.ndarray, largest: np.ndarray,
                          index: PatternIndex, max_error: float, allowed: float, max_candidates: int, tried: int,
                          verify: dict, accept: dict) -> tuple[Identification | None, object]:
    """A block's search (module step 4) settled by its first candidate, found without the block's full
    lookup: ``(identification or None, the first candidate's verification or _UNVERIFIED)``.

    The full lookup's first candidate is the catalog pattern of least ratio error over every probe key of
    the block (image patterns ``subsets``, their ``ratios`` and ``largest`` edges). It is found from each
    image pattern's own key (each ratio in its own bin) and the few other keys that could hold a pattern
    fitting as well (:func:`opnav.image.starid_compiled.lookup_kernel` with ``first_only``: a pattern of
    any other key differs from its image pattern by more than the best fit's error in a ratio) and
    verified as the full search would verify it first (after ``tried`` candidates). Accepted with the
    Bonferroni count taken as ``max_candidates`` (the full search's is at most that), it is the full
    search's answer; otherwise the full search runs and takes this verification for its first candidate.
    A typical frame's lookup then reads ~17 keys instead of ~240 (0.16 ms after an extraction, most of
    it reads of the memory-mapped index).
    """
    subset_of, pattern_of, scale, complete = _candidates(ratios, largest, index, max_error, allowed, True)
    if not complete:
        return None, _UNVERIFIED
    solution = _verify_candidate(b, subsets[subset_of[0]], index.patterns[pattern_of[0]], index,
                                 focal_scale=float(scale[0]) if verify["free_scale"] else 1.0, **verify)
    return _accepted(b, index, solution, max_candidates, tried + 1, **accept), solution


def _rigid_candidates(b: np.ndarray, subsets: np.ndarray, patterns: np.ndarray, index: PatternIndex,
                      scale: np.ndarray | None, radius: float) -> np.ndarray:
    """Which candidates (image subset rows (C, 4), index patterns (C, 4), focal scales or None for 1)
    can pass the first test of :func:`_verify_candidate`, all at once: the least, over the 24 orders
    of the catalog stars, of the largest difference between the image pattern's and the catalog
    pattern's angles is within twice ``radius`` (a hair's margin for rounding). A candidate that
    :func:`_verify_candidate` would keep past that test is never screened out (its order is one of
    the 24); a block of a frame whose brightest sources include a hot pixel or a planet's ghost offers
    ~100 false ones (:func:`opnav.image.starid_compiled.rigid_kernel`, the same angles as the verification's)."""
    count = len(subsets)
    if count == 0:
        return np.zeros(0, bool)
    catalog = np.asarray(index.star_vectors[patterns.ravel()], dtype=float).reshape(count, 4, 3)
    return rigid_kernel(b, np.ascontiguousarray(subsets, dtype=np.int64), catalog,
                        np.ones(count) if scale is None else np.ascontiguousarray(scale, dtype=float), radius)


def _verify_candidate(
    b: np.ndarray,
    subset: np.ndarray,
    pattern: np.ndarray,
    index: PatternIndex,
    *,
    focal_scale: float,
    free_scale: bool,
    radius: float,
    pattern_max_error: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, float] | None:
    """Steps 4-6 for one candidate: (image rows, index rows, their ICRF directions, attitude matrix camera ->
    ICRF, focal scale, p_false) or None.

    The arithmetic and the search of the field's index stars are
    :func:`opnav.image.starid_compiled.verify_kernel`'s; what it asks for (sorted directions gathered,
    stars' directions computed for the frame's epoch) is done here and the kernel called again.
    """
    zones = index.tree
    pattern = np.asarray(pattern, dtype=np.int64)
    v_pattern, matrix = np.empty((4, 3)), np.empty((3, 3))
    rows_image, rows_index, v_matched = np.empty(len(b), np.int64), np.empty(len(b), np.int64), np.empty((len(b), 3))
    stage = -1
    while True:
        status, stage, focal_scale, cone, matched, nearby, closeness, lo, hi, stale = verify_kernel(
            b, subset, pattern, stage, focal_scale, free_scale, radius, matrix, v_pattern, rows_image, rows_index,
            v_matched, *zones.kernel_arguments())
        if not zones.provide(status, lo, hi, stale):
            break
    if status == REJECT:
        return None
    rows_image = rows_image[:matched].copy()
    p_single = nearby * (1.0 - math.cos(radius)) / (1.0 - math.cos(cone))
    # the pattern's own fit (module step 6): a false candidate's closeness d has P[d <= t] = (t / e)^4
    p_false = _p_false(rows_image, p_single, 4) * min(closeness / pattern_max_error, 1.0) ** 4
    return rows_image, rows_index[:matched].copy(), v_matched[:matched].copy(), matrix, focal_scale, p_false


#: CatalogTree per catalog object (weakly held) and magnitude limit.
_TREES: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


@dataclass(frozen=True)
class CatalogTree:
    """Catalog directions with a KD-tree, for repeated cone searches in :func:`track`.

    Build with :meth:`from_catalog`; ``rows`` are row numbers in that catalog.
    """

    vectors: np.ndarray
    vmag: np.ndarray
    rows: np.ndarray
    tree: cKDTree

    @classmethod
    def from_catalog(cls, catalog: StarSource, *, vmag_limit: float | None = None) -> CatalogTree:
        """Keep stars brighter than ``vmag_limit`` (all if None) with finite directions.

        Built once per catalog object and limit and then reused: a tracking step takes a few
        milliseconds, building the tree over the 489k-star catalog ~200 ms, and a frame sequence
        asks for the same tree at every frame.
        """
        try:
            cache = _TREES.setdefault(catalog, {})
        except TypeError:  # a catalog that cannot be weakly referenced is not cached
            cache = {}
        key = None if vmag_limit is None else float(vmag_limit)
        if key not in cache:
            cache[key] = cls._build(catalog, key)
        return cache[key]

    @classmethod
    def _build(cls, catalog: StarSource, vmag_limit: float | None) -> CatalogTree:
        vectors = np.asarray(catalog.unit_vectors(), dtype=float)
        vmag = np.asarray(catalog.vmag, dtype=float)
        usable = np.all(np.isfinite(vectors), axis=1)
        if vmag_limit is not None:
            usable &= vmag <= vmag_limit
        rows = np.flatnonzero(usable)
        if len(rows) < 3:
            raise CatalogError(f"catalog has {len(rows)} usable stars (vmag_limit {vmag_limit}); tracking needs at least 3")
        return cls(vectors=vectors[rows], vmag=vmag[rows], rows=rows, tree=cKDTree(vectors[rows]))


def _triad(b1: np.ndarray, b2: np.ndarray, v1: np.ndarray, v2: np.ndarray) -> np.ndarray:
    """TRIAD rotation matrices (H, 3, 3), camera -> ICRF, anchored on the first pair."""

    def frame(first: np.ndarray, second: np.ndarray) -> np.ndarray:
        normal = np.cross(first, second)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        return np.stack([first, normal, np.cross(first, normal)], axis=-1)

    return frame(v1, v2) @ np.swapaxes(frame(b1, b2), -1, -2)


def track(
    bearings: np.ndarray,
    catalog: CatalogTree,
    R_icrf_cam_prior: Rotation,
    camera: Camera,
    *,
    prior_sigma_rad: float,
    match_radius_px: float = 2.0,
    gate_sigma: float = 4.3,
    hypothesis_stars: int = 6,
    max_hypotheses: int = 4000,
    p_false_max: float = 1e-3,
    sigma_rad: float | None = None,
    rng: np.random.Generator | int | None = None,
) -> Identification:
    """Identify stars near their positions predicted from an a-priori attitude (module: Tracking).

    Parameters
    ----------
    bearings : ndarray, shape (N, 3)
        Camera-frame unit directions of image stars, brightest first.
    catalog : CatalogTree
        Catalog stars to match (:meth:`CatalogTree.from_catalog`); ``pairs`` index the rows
        of the catalog it was built from.
    R_icrf_cam_prior : Rotation
        A-priori attitude, camera -> ICRF.
    camera : Camera
        Sets the field of view and the pixel scale of ``match_radius_px``.
    prior_sigma_rad : float
        Per-axis 1-sigma error of the prior attitude, rad.
    match_radius_px : float
        Match radius, px (converted with the boresight pixel scale).
    gate_sigma : float
        Candidate gate in prior sigmas (4.3 holds 99.99 % of a 2-D Gaussian displacement).
    hypothesis_stars : int
        Brightest bearings used to form pair hypotheses.
    max_hypotheses : int
        Hypotheses scored at most; beyond that, half the best-agreeing and half drawn from ``rng``.
    p_false_max : float
        Accept only if the false-match probability (within the prior gate) is at most this.
        The default is looser than :func:`identify`'s because the prior already excludes
        nearly every attitude.
    sigma_rad : float, optional
        Per-axis bearing noise for the covariance, rad; default estimated from the residuals.
    rng : numpy.random.Generator or int or None
        Source of the hypothesis subset.

    Returns
    -------
    Identification
        ``focal_scale`` is 1 (the camera model is taken as known).

    Raises
    ------
    NoSolutionError
        Fewer than 3 stars, or fewer than 3 matches passing the false-match test.
    InputError
        Bad arguments.
    """
    b = _as_bearings(bearings)
    _check_common(p_false_max, sigma_rad)
    if not (math.isfinite(prior_sigma_rad) and prior_sigma_rad > 0.0):
        raise InputError(f"prior_sigma_rad must be positive, got {prior_sigma_rad!r}")
    if not (match_radius_px > 0.0 and gate_sigma > 0.0 and hypothesis_stars >= 2 and max_hypotheses >= 1):
        raise InputError("match_radius_px, gate_sigma, hypothesis_stars (>= 2) and max_hypotheses must be positive")
    if len(b) < 3:
        raise NoSolutionError(f"tracking needs at least 3 stars, got {len(b)}")
    rng = np.random.default_rng(rng)
    radius = match_radius_px * camera.pixel_scale_rad
    gate = gate_sigma * prior_sigma_rad + radius

    boresight = R_icrf_cam_prior.apply([0.0, 0.0, 1.0])
    cone = camera.half_diagonal_fov_rad + gate
    near = np.sort(np.asarray(catalog.tree.query_ball_point(boresight, 2.0 * math.sin(cone / 2.0)), dtype=int))
    rows_catalog = catalog.rows[near]
    v_near = catalog.vectors[near]
    c_prior = R_icrf_cam_prior.inv().apply(v_near) if len(v_near) else np.empty((0, 3))
    in_gate = (b @ c_prior.T) >= math.cos(gate)

    hypotheses, disagreement = [], []
    for i, j in itertools.combinations(range(min(len(b), hypothesis_stars)), 2):
        a, c = np.nonzero(in_gate[i][:, None] & in_gate[j][None, :])
        offset = np.abs(_angles(v_near[a], v_near[c]) - _angles(b[i], b[j]))
        same_separation = (offset <= 2.0 * radius) & (a != c)
        a, c = a[same_separation], c[same_separation]
        hypotheses.append(np.column_stack([np.full(len(a), i), np.full(len(a), j), a, c]))
        disagreement.append(offset[same_separation])
    hypotheses = np.concatenate(hypotheses) if hypotheses else np.empty((0, 4), int)
    if len(hypotheses) == 0:
        raise NoSolutionError("tracking: no pair of stars matches a catalog pair within the prior gate")
    if len(hypotheses) > max_hypotheses:
        hypotheses = hypotheses[_scored_hypotheses(np.concatenate(disagreement), max_hypotheses, rng)]

    matrices = _triad(b[hypotheses[:, 0]], b[hypotheses[:, 1]], v_near[hypotheses[:, 2]], v_near[hypotheses[:, 3]])
    inliers = np.empty(len(hypotheses), int)
    for lo in range(0, len(hypotheses), 256):
        # c_cam[h, k] = R_h^T v_k; cosines[h, n, k] = b_n . c_cam[h, k]
        c_cam = np.einsum("hji,kj->hki", matrices[lo : lo + 256], v_near)
        cosines = np.einsum("ni,hki->hnk", b, c_cam)
        inliers[lo : lo + 256] = np.sum(cosines.max(axis=2) >= math.cos(radius), axis=1)
    rotation = Rotation.from_matrix(matrices[int(np.argmax(inliers))])

    for _ in range(2):
        rows_image, rows_near = _match_one_to_one(b, rotation.inv().apply(v_near), radius)
        if len(rows_image) < 3:
            raise NoSolutionError(f"tracking: only {len(rows_image)} stars match the best hypothesis")
        rotation = wahba_rotation(b[rows_image], v_near[rows_near], np.ones(len(rows_image)))
    rows_image, rows_near = _match_one_to_one(b, rotation.inv().apply(v_near), radius)
    p_single = float(np.mean(np.sum(in_gate, axis=1))) * (1.0 - math.cos(radius)) / (1.0 - math.cos(gate))
    # a bound: above 1 where the gates offer many candidate pairs, reported as 1
    p_false = min(1.0, _chance_hypotheses(in_gate[:hypothesis_stars], radius, gate) * _p_false(rows_image, p_single, 2))
    if len(rows_image) < 3 or p_false > p_false_max:
        raise NoSolutionError(f"tracking: {len(rows_image)} matches, p_false {p_false:.2g} > {p_false_max:g}")
    # The answer must agree with the prior it was searched under (3-D, same tail as the gate).
    departure_sigma = (R_icrf_cam_prior.inv() * rotation).magnitude() / prior_sigma_rad
    if departure_sigma > math.sqrt(chdtri(3, chdtrc(2, gate_sigma**2))):  # the chi-square(2) gate as a chi-square(3) radius
        raise NoSolutionError(f"tracking: solution is {departure_sigma:.1f} prior sigmas from the a-priori attitude")
    return _finish(b, rows_image, v_near[rows_near], rows_catalog[rows_near], rotation, p_false, 1.0, sigma_rad, len(hypotheses))


@dataclass(frozen=True)
class PlateSolution:
    """Result of :func:`solve_image`.

    Attributes
    ----------
    identification : Identification
        Rows of ``pairs`` index ``xy``. Its ``R_icrf_cam`` is the **geometric** attitude: it maps
        the bearings onto the catalog's astrometric ICRF directions (catalog epoch, no stellar
        aberration). A camera moving at ``v`` sees every star displaced by aberration (up to
        ``|v| / c``, 20" at 30 km/s) towards ``v``; the attitude that maps bearings onto these
        *apparent* directions (the one a rendered frame's WCS and truth carry) is
        :meth:`attitude` with the observer velocity.
    camera : Camera
        The camera used, with the focal length scaled by the fitted ``focal_scale``.
    xy : ndarray, shape (N, 2)
        Centroids of the extracted stars, highest detection SNR first (:func:`opnav.image.extract.extract_stars`), px.
    extract_s, solve_s : float
        Wall-clock time of extraction (detect + centroid) and of identification, s.
    """

    identification: Identification
    camera: Camera
    xy: np.ndarray
    extract_s: float
    solve_s: float

    #: What ``identification.R_icrf_cam`` means (see the class docstring).
    pointing = "geometric"

    def attitude(self, v_observer_km_s: np.ndarray | None = None) -> Rotation:
        """Camera -> ICRF attitude: geometric without a velocity, apparent (aberrated) with one.

        Parameters
        ----------
        v_observer_km_s : ndarray, shape (3,), optional
            Observer velocity relative to the solar-system barycentre, ICRF, km/s. The matched
            catalog directions are aberrated with it (:func:`opnav.light.aberrate`) and the
            attitude re-fitted to the same bearings (Wahba, equal weights).

        Returns
        -------
        Rotation
            Camera frame -> ICRF.

        Raises
        ------
        InputError
            ``v_observer_km_s`` not a finite (3,) vector below the speed of light.
        """
        ident = self.identification
        if v_observer_km_s is None:
            return ident.R_icrf_cam
        v = np.asarray(v_observer_km_s, dtype=float)
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise InputError(f"v_observer_km_s must be a finite (3,) vector in km/s, got {v_observer_km_s!r}")
        from ..light import aberrate

        b_cam = self.camera.unproject(self.xy[ident.pairs[:, 0]])
        return wahba_rotation(b_cam, aberrate(ident.v_icrf, v), np.ones(len(b_cam)))


#: A frame that fails lost-in-space with fewer extracted stars than this is extracted again
#: with detection down to ``DEEP_THRESHOLD_SIGMA`` (:func:`solve_with_deeper_extraction`).
SPARSE_FRAME_STARS = 12
DEEP_THRESHOLD_SIGMA = 4.0


def solve_with_deeper_extraction(
    image: np.ndarray,
    solve: Callable[[np.ndarray, np.ndarray], PlateSolution],
    *,
    saturation_adu: float | None = None,
    invalid: np.ndarray | None = None,
    lossy: bool = False,
    max_stars: int = 40,
    noise: dict | None = None,
) -> PlateSolution:
    """Extract and solve a frame; a frame of few stars that does not solve is extracted deeper and solved again.

    A star at the detection threshold (5 sigma) is found about half the time, so a frame of 5-6
    stars often loses the one that would confirm its pattern. When ``solve`` fails on fewer than
    ``SPARSE_FRAME_STARS`` stars, the frame is extracted again with detection down to
    ``DEEP_THRESHOLD_SIGMA`` and solved once more. The few noise peaks a megapixel frame gains at
    4 sigma come last in the signal-to-noise order; the false-match test counts every star down
    to the last one matched and every candidate the search offered, so they weaken no solution.
    The second search is a second chance for a false match: for the frames that need it the
    bound on a wrong answer is twice ``p_false_max``.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Frame, ADU, indexed ``[row, col]``.
    solve : callable
        ``solve(xy, cov)`` of extracted stars (most reliable first, px and px^2): a
        :class:`PlateSolution`, or :class:`opnav.errors.NoSolutionError`.
    saturation_adu, invalid, lossy, max_stars
        Passed to :func:`opnav.image.extract.extract_stars`.
    noise : dict, optional
        The detector's noise model, ``read_noise_e``, ``gain_e_per_adu`` and ``bias_adu``, passed to
        :func:`opnav.image.extract.extract_stars` (None: fitted from the frame).

    Returns
    -------
    PlateSolution
        With ``extract_s`` the time of the extractions made.

    Raises
    ------
    NoSolutionError
        Neither extraction gave a solution (the message names both).
    """
    started = time.perf_counter()
    noise = {} if noise is None else noise
    xy, cov = extract_stars(image, max_stars=max_stars, saturation_adu=saturation_adu, invalid=invalid, lossy=lossy,
                            **noise)
    extract_s = time.perf_counter() - started
    try:
        return dataclasses.replace(solve(xy, cov), extract_s=extract_s)
    except NoSolutionError as exc:
        if len(xy) >= SPARSE_FRAME_STARS:
            raise
        first = exc
    started = time.perf_counter()
    deep = DetectOptions(threshold_sigma=DEEP_THRESHOLD_SIGMA)
    xy_deep, cov_deep = extract_stars(image, max_stars=max_stars, saturation_adu=saturation_adu, invalid=invalid,
                                      lossy=lossy, detect_options=deep, **noise)
    extract_s += time.perf_counter() - started
    if len(xy_deep) <= len(xy):
        raise first
    try:
        return dataclasses.replace(solve(xy_deep, cov_deep), extract_s=extract_s)
    except NoSolutionError as exc:
        raise NoSolutionError(f"{first}; extracted again down to {DEEP_THRESHOLD_SIGMA:g} sigma: {exc}") from None


def solve_image(
    image: np.ndarray,
    *,
    index: PatternIndex,
    camera: Camera | None = None,
    fov_deg: float | None = None,
    fov_tolerance: float = 0.1,
    saturation_adu: float | None = None,
    invalid: np.ndarray | None = None,
    lossy: bool = False,
    max_stars: int = 40,
    p_false_max: float = 1e-5,
) -> PlateSolution:
    """Lost-in-space plate solve of a frame: extract -> bearings -> :func:`identify`.

    A frame of few stars that does not solve is extracted again, deeper
    (:func:`solve_with_deeper_extraction`).

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Frame, ADU, indexed ``[row, col]`` (:func:`opnav.image.io.read_image`).
    index : PatternIndex
        Pattern index covering the frame's field of view.
    camera : Camera, optional
        Camera model (distortion, principal point); its focal length is the guess.
    fov_deg : float, optional
        Horizontal field of view guess, deg, for a pinhole camera centred on the frame (used
        when ``camera`` is None). With neither, guesses step through the index's FOV range.
    fov_tolerance : float
        Relative uncertainty of the focal length (or FOV) guess; 0 holds it fixed.
    saturation_adu, invalid, lossy
        Passed to detection and centroiding (``ImageMeta`` fields).
    max_stars : int
        Point sources centroided (those of largest detection flux).
    p_false_max : float
        See :func:`identify`.

    Returns
    -------
    PlateSolution

    Raises
    ------
    FrameError
        Blank, saturated or otherwise unusable frame (from :func:`opnav.image.detect.detect`).
    NoSolutionError
        Fewer than 4 stars, or no solution passes verification.
    """
    image = np.asarray(image, dtype=float)
    if image.ndim != 2:
        raise InputError(f"solve_image needs a 2-D frame, got shape {image.shape}")
    if camera is not None and camera.shape != image.shape:
        raise InputError(f"camera shape {camera.shape} does not match the frame {image.shape}")
    _fov_guesses(image.shape, index, camera, fov_deg, fov_tolerance)  # bad options fail before extraction

    def solve(xy: np.ndarray, cov: np.ndarray) -> PlateSolution:
        return solve_stars(xy, cov, image.shape, index=index, camera=camera, fov_deg=fov_deg,
                           fov_tolerance=fov_tolerance, p_false_max=p_false_max)

    return solve_with_deeper_extraction(image, solve, saturation_adu=saturation_adu, invalid=invalid, lossy=lossy,
                                        max_stars=max_stars)


def _median(values: np.ndarray) -> float:
    """``numpy.median`` of a 1-D array, the same number, without its general machinery (~15 us a frame)."""
    ordered = np.sort(values)
    if not len(ordered) or math.isnan(ordered[-1]):
        return math.nan
    half = len(ordered) // 2
    return float(ordered[half]) if len(ordered) % 2 else float((ordered[half - 1] + ordered[half]) / 2.0)


def _fov_guesses(shape: tuple[int, int], index: PatternIndex, camera: Camera | None, fov_deg: float | None,
                 fov_tolerance: float, fov_range_deg: tuple[float, float] | None = None) -> list[Camera]:
    """Cameras whose focal lengths, each +-``fov_tolerance``, cover the search (see :func:`solve_image`)."""
    height, width = shape
    if not (0.0 <= fov_tolerance <= 0.5):
        raise InputError(f"fov_tolerance must be in [0, 0.5], got {fov_tolerance!r}")
    if camera is not None:
        return [camera]
    if fov_deg is not None:
        if not (0.0 < fov_deg < 120.0):
            raise InputError(f"fov_deg must be in (0, 120), got {fov_deg!r}")
        return [_camera_of_fov(float(fov_deg), width, height)]
    if fov_tolerance == 0.0:
        raise InputError("without camera or fov_deg the FOV must be searched: fov_tolerance must be > 0")
    step = (1.0 + fov_tolerance) / (1.0 - fov_tolerance)
    low, high = (index.options.fov_min_deg, index.options.fov_max_deg) if fov_range_deg is None else fov_range_deg
    if not (0.0 < low <= high < 120.0):
        raise InputError(f"fov_range_deg must satisfy 0 < low <= high < 120, got {fov_range_deg!r}")
    count = 1 + math.ceil(math.log(high / low) / math.log(step) - 1e-9)
    return [_camera_of_fov(low * (1.0 + fov_tolerance) * step**k, width, height) for k in range(count)]


@lru_cache(maxsize=256)
def _camera_of_fov(fov_deg: float, width: int, height: int) -> Camera:
    """``Camera.from_fov``, kept: the frames of a camera ask for the same guesses (~25 us each)."""
    return Camera.from_fov(fov_deg, width, height)


def solve_stars(
    xy: np.ndarray,
    cov: np.ndarray,
    shape: tuple[int, int],
    *,
    index: PatternIndex,
    camera: Camera | None = None,
    fov_deg: float | None = None,
    fov_tolerance: float = 0.1,
    p_false_max: float = 1e-5,
    match_radius_px: float | None = None,
    fov_range_deg: tuple[float, float] | None = None,
) -> PlateSolution:
    """Lost-in-space plate solve of extracted stars (:func:`solve_image` after extraction).

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        Star centroids, px, **most reliable first** (:func:`opnav.image.extract.extract_stars`: highest detection SNR).
    cov : ndarray, shape (N, 2, 2)
        Their covariances, px^2.
    shape : (int, int)
        Frame shape (rows, columns).
    index, camera, fov_deg, fov_tolerance, p_false_max
        As for :func:`solve_image`.
    match_radius_px : float, optional
        Verification match radius, px; default the larger of ``MATCH_RADIUS_PX`` and
        ``MATCH_RADIUS_SIGMAS`` times the median centroid sigma. It sets the false-match
        probability of each extra matched star (module step 6): a radius fitted to the centroids
        rather than to the field (1 %, the :func:`identify` default) makes each confirming star
        count for more.
    fov_range_deg : (float, float), optional
        Horizontal FOV range searched when neither ``camera`` nor ``fov_deg`` is given, deg;
        default the index's ``fov_min_deg`` to ``fov_max_deg``.

    Returns
    -------
    PlateSolution
        ``extract_s`` is 0; ``solve_s`` the time spent here.
    """
    started = time.perf_counter()
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    cov = np.asarray(cov, dtype=float).reshape(-1, 2, 2)
    if len(cov) != len(xy):
        raise InputError(f"xy ({len(xy)}) and cov ({len(cov)}) must have one row per star")
    if camera is not None and camera.shape != tuple(shape):
        raise InputError(f"camera shape {camera.shape} does not match the frame {tuple(shape)}")
    guesses = _fov_guesses(tuple(shape), index, camera, fov_deg, fov_tolerance, fov_range_deg)
    if len(xy) < 4:
        raise NoSolutionError(f"only {len(xy)} point sources found in the frame; lost-in-space needs at least 4")
    sigma_px = _median(np.sqrt(0.5 * np.trace(cov, axis1=1, axis2=2)))
    if match_radius_px is None:
        match_radius_px = max(MATCH_RADIUS_PX, MATCH_RADIUS_SIGMAS * sigma_px)
    if not (math.isfinite(match_radius_px) and match_radius_px > 0.0):
        raise InputError(f"match_radius_px must be positive, got {match_radius_px!r}")
    failures = []
    for guess in guesses:
        try:
            found = identify(bearings(xy, guess), index, fov_tolerance=fov_tolerance, p_false_max=p_false_max,
                             sigma_rad=max(sigma_px / guess.focal_length_px, 1e-9),
                             match_radius_rad=match_radius_px / guess.focal_length_px)
        except NoSolutionError as exc:
            failures.append(str(exc))
            continue
        fitted = guess.replace(focal_length_mm=guess.focal_length_mm * found.focal_scale)
        return PlateSolution(found, fitted, xy, 0.0, time.perf_counter() - started)
    raise NoSolutionError(f"{len(xy)} stars extracted but no solution passed verification: {failures[-1]}")
