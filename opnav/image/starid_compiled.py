"""Compiled kernels of lost-in-space star identification (:func:`opnav.image.starid.identify`).

The arithmetic of a frame's search is small (a few hundred pattern probes, a candidate's 4 stars and
the twenty-odd index stars in its field) but was spread over ~150 numpy calls a candidate, whose
overhead (a few microseconds each) was most of a solve's time. These kernels do the same arithmetic
in the same order, so that they take the same decisions:

- :func:`lookup_kernel`: module steps 2-3, every probe key of a block of image patterns looked up in
  the sorted index and the catalog patterns within the ratio and scale tolerances kept;
- :func:`verify_kernel`: steps 4-5 and the closeness of step 6 for one candidate: the star
  correspondence, the pattern's angle and residual tests, the refits on the matched stars (focal
  scale included) and the last match, with the index stars of the field searched by declination
  zones (:func:`_search`, as :meth:`opnav.image.starid_index.StarZones.ball_rows`). What only Python
  can do, gather a band of the memory-mapped directions and compute stars' directions for the frame's
  epoch, the kernel asks for (a ``NEED_`` status) and goes on from where it stopped.
"""

from __future__ import annotations

import math

import numpy as np

from ..compiled import kernel

#: Statuses of :func:`verify_kernel` and :func:`search_kernel`: the candidate fails; the candidate passed
#: steps 4-5 (the search is done); the sorted directions of the zones' rows ``lo:hi`` must be gathered
#: first (:class:`opnav.image.starid_index.SortedChunks`); the directions of the rows returned must be
#: computed for the epoch first (:class:`opnav.image.starid_index._EpochDirections`). After either of the
#: last two the call is made again, from the stage returned.
REJECT, DONE, NEED_BAND, NEED_DIRECTIONS = 0, 2, 3, 4

#: The 24 orders of a pattern's 4 catalog stars (``itertools.permutations(range(4))`` order).
PERMUTATIONS = np.array([[a, b, c, d] for a in range(4) for b in range(4) for c in range(4) for d in range(4)
                         if len({a, b, c, d}) == 4], dtype=np.int64)


@kernel(inline=True)
def _probe_bins(ratios, s, max_error, bins, low, high):  # pragma: no cover - compiled
    """The lower and upper bins probed of each ratio of image pattern ``s`` (into ``low`` and ``high``)."""
    for k in range(5):
        low[k] = int(min(max(math.floor((ratios[s, k] - max_error) * bins), 0.0), bins - 1.0))
        high[k] = int(min(max(math.floor((ratios[s, k] + max_error) * bins), 0.0), bins - 1.0))


@kernel(inline=True)
def _probe_key(bits, low, high, powers):  # pragma: no cover - compiled
    """The key of the bins ``high`` where ``bits`` is set, ``low`` elsewhere; -1 when a bit is set where
    the two bins are one (the key with that bit clear already)."""
    key = 0
    for k in range(5):
        if (bits >> k) & 1:
            if high[k] == low[k]:
                return -1
            key += high[k] * powers[k]
        else:
            key += low[k] * powers[k]
    return key


@kernel(inline=True)
def _slot(unique_keys, bounds, key):  # pragma: no cover - compiled
    """The slot of ``key`` among the index's distinct keys, -1 when it has none."""
    if key < 0:
        return -1
    slot = min(np.searchsorted(unique_keys, key), unique_keys.shape[0] - 1)
    return slot if unique_keys[slot] == key else -1


@kernel(inline=True)
def _scan(s, slots, ratios, largest, bounds, index_ratios, max_edge, max_error, allowed_log_scale,
          out_subset, out_pattern, out_scale, out_error, count):  # pragma: no cover - compiled
    """The patterns of the slots of image pattern ``s`` within the ratio and scale tolerances, appended at
    ``count`` (the new count returned)."""
    for slot in slots:
        if slot < 0:
            continue
        for p in range(bounds[slot], bounds[slot + 1]):
            error = 0.0
            for k in range(5):
                error = max(error, abs(np.float64(index_ratios[p, k]) - ratios[s, k]))
            ratio = largest[s] / np.float64(max_edge[p])
            if error <= max_error and abs(math.log(ratio)) <= allowed_log_scale:
                out_subset[count] = s
                out_pattern[count] = p
                out_scale[count] = ratio
                out_error[count] = error
                count += 1
    return count


@kernel(inline=True)
def _patterns_of(slots, bounds):  # pragma: no cover - compiled
    total = 0
    for i in range(slots.shape[0]):
        for j in range(slots.shape[1]):
            if slots[i, j] >= 0:
                total += bounds[slots[i, j] + 1] - bounds[slots[i, j]]
    return total


@kernel
def lookup_kernel(ratios, largest, unique_keys, bounds, index_ratios, max_edge, max_error, allowed_log_scale,
                  bins, first_only, slack):  # pragma: no cover - compiled
    """Catalog patterns within tolerance of image patterns (:func:`opnav.image.starid._lookup`), or with
    ``first_only`` a part of them that holds the one of least ratio error (module step 4).

    With ``first_only`` the keys looked up are each image pattern's own key (each ratio in its own bin),
    and then, for the least ratio error ``e`` of their patterns, the probe keys that differ from it only
    in ratios within ``e + slack`` of their own bin's edge towards the other bin probed: a pattern of
    any other key differs from its image pattern by more than ``e`` in a ratio (``slack`` covers the
    stored ratios' float32 rounding), so the pattern of least error, ties broken alike, is among those
    returned.

    Parameters
    ----------
    ratios : ndarray, shape (S, 5)
        Sorted edge ratios of the image patterns.
    largest : ndarray, shape (S,)
        Their largest edges, rad.
    unique_keys, bounds : ndarray, shape (U,) and (U + 1,) int64
        The index's distinct keys and where each one's patterns start
        (:attr:`opnav.image.starid_index.PatternIndex.key_directory`).
    index_ratios : ndarray, shape (P, 5) float32
    max_edge : ndarray, shape (P,) float32
        The index's pattern ratios and largest edges, rad.
    max_error : float
        Largest ratio difference kept.
    allowed_log_scale : float
        Largest ``|log(image edge / catalog edge)|`` kept.
    bins : int
        Ratio bins of the index's keys.
    first_only : bool
        Look up only what the candidate of least ratio error needs.
    slack : float
        See ``first_only``.

    Returns
    -------
    subset_of, pattern_of : ndarray, shape (C,) int64
        Image pattern and index pattern of each candidate (in probe order).
    scale : ndarray, shape (C,)
        Image largest edge over the catalog pattern's.
    ratio_error : ndarray, shape (C,)
        Largest ratio difference.
    complete : bool
        False when ``first_only`` could not settle the first candidate (no pattern in the own keys, or
        an own bin not among those probed): the full lookup is needed.
    """
    n = ratios.shape[0]
    low = np.empty((n, 5), np.int64)
    high = np.empty((n, 5), np.int64)
    powers = np.empty(5, np.int64)
    powers[0] = 1
    for k in range(1, 5):
        powers[k] = powers[k - 1] * bins
    for s in range(n):
        _probe_bins(ratios, s, max_error, bins, low[s], high[s])
    # first the keys' slots (-1: no such key) and how many patterns they hold, so that the candidates'
    # arrays are allocated once (growing them in the loop made it 6x slower)
    slots = np.full((n, 32), -1, np.int64)
    own_bits = np.zeros(n, np.int64)
    for s in range(n):
        if first_only:
            for k in range(5):
                own = int(min(max(math.floor(ratios[s, k] * bins), 0.0), bins - 1.0))
                if own == high[s, k] and own != low[s, k]:
                    own_bits[s] |= 1 << k
                elif own != low[s, k]:  # a bin between the two probed
                    return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0), np.empty(0), False
            slots[s, own_bits[s]] = _slot(unique_keys, bounds, _probe_key(own_bits[s], low[s], high[s], powers))
        else:
            for bits in range(32):
                slots[s, bits] = _slot(unique_keys, bounds, _probe_key(bits, low[s], high[s], powers))
    patterns = _patterns_of(slots, bounds)
    subset_of = np.empty(patterns, np.int64)
    pattern_of = np.empty(patterns, np.int64)
    scale = np.empty(patterns)
    ratio_error = np.empty(patterns)
    count = 0
    for s in range(n):
        count = _scan(s, slots[s], ratios, largest, bounds, index_ratios, max_edge, max_error, allowed_log_scale,
                      subset_of, pattern_of, scale, ratio_error, count)
    if not first_only:
        return subset_of[:count], pattern_of[:count], scale[:count], ratio_error[:count], True
    if count == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0), np.empty(0), False
    least = ratio_error[:count].min() + slack
    # the other keys that can hold a pattern of error <= least: they differ from the own key only in
    # ratios that close to their own bin's edge towards the other bin probed
    others = np.full((n, 32), -1, np.int64)
    for s in range(n):
        near = 0
        for k in range(5):
            if low[s, k] != high[s, k]:
                if own_bits[s] >> k & 1:
                    edge_distance = ratios[s, k] - high[s, k] / bins
                else:
                    edge_distance = high[s, k] / bins - ratios[s, k]
                if edge_distance <= least:
                    near |= 1 << k
        for bits in range(32):
            if bits != own_bits[s] and (bits ^ own_bits[s]) & ~near == 0:
                others[s, bits] = _slot(unique_keys, bounds, _probe_key(bits, low[s], high[s], powers))
    more = _patterns_of(others, bounds)
    all_subset = np.empty(count + more, np.int64)
    all_pattern = np.empty(count + more, np.int64)
    all_scale = np.empty(count + more)
    all_error = np.empty(count + more)
    all_subset[:count] = subset_of[:count]
    all_pattern[:count] = pattern_of[:count]
    all_scale[:count] = scale[:count]
    all_error[:count] = ratio_error[:count]
    for s in range(n):
        count = _scan(s, others[s], ratios, largest, bounds, index_ratios, max_edge, max_error, allowed_log_scale,
                      all_subset, all_pattern, all_scale, all_error, count)
    return all_subset[:count], all_pattern[:count], all_scale[:count], all_error[:count], True


@kernel(inline=True)
def _angle(a, b):  # pragma: no cover - compiled
    """Angle between unit vectors ``a`` and ``b`` (3,), rad, as ``2 asin(chord / 2)``."""
    chord = math.sqrt((a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2 + (a[2] - b[2]) ** 2)
    return 2.0 * math.asin(min(chord / 2.0, 1.0))


@kernel(inline=True)
def _rescale(b, focal_scale):  # pragma: no cover - compiled
    """Bearings (N, 3) as seen with focal length ``f_assumed * focal_scale`` (tangent plane / scale)."""
    out = np.empty_like(b)
    for i in range(b.shape[0]):
        x = b[i, 0] / b[i, 2] / focal_scale
        y = b[i, 1] / b[i, 2] / focal_scale
        norm = math.sqrt(x * x + y * y + 1.0)
        out[i, 0] = x / norm
        out[i, 1] = y / norm
        out[i, 2] = 1.0 / norm
    return out


@kernel(inline=True)
def _wahba(b, v):  # pragma: no cover - compiled
    """Rotation matrix ``R`` (camera -> ICRF) minimising ``sum |v_i - R b_i|^2`` (equal weights), by the
    SVD method (:func:`opnav.image.attitude.wahba_matrix`)."""
    profile = np.zeros((3, 3))
    for n in range(b.shape[0]):
        for i in range(3):
            for j in range(3):
                profile[i, j] += v[n, i] * b[n, j]
    u, _, vt = np.linalg.svd(profile)
    d = np.linalg.det(u) * np.linalg.det(vt)
    u[:, 2] *= d
    return u @ vt


@kernel(inline=True)
def _predicted(v, matrix):  # pragma: no cover - compiled
    """ICRF directions (K, 3) in the camera frame, ``v @ matrix``."""
    out = np.empty((v.shape[0], 3))
    for k in range(v.shape[0]):
        for j in range(3):
            out[k, j] = v[k, 0] * matrix[0, j] + v[k, 1] * matrix[1, j] + v[k, 2] * matrix[2, j]
    return out


@kernel(inline=True)
def _match(b, c, radius, rows_b, rows_c):  # pragma: no cover - compiled
    """Rows of ``b`` (ascending, into ``rows_b``) and of ``c`` (into ``rows_c``) of the nearest pairs within
    ``radius``, each row used at most once (:func:`opnav.image.starid._match_one_to_one`); their count."""
    if c.shape[0] == 0:
        return 0
    n = b.shape[0]
    nearest = np.empty(n, np.int64)
    best = np.empty(n)
    for i in range(n):
        top = -np.inf
        at = 0
        for k in range(c.shape[0]):
            cosine = b[i, 0] * c[k, 0] + b[i, 1] * c[k, 1] + b[i, 2] * c[k, 2]
            if cosine > top:
                top = cosine
                at = k
        nearest[i] = at
        best[i] = top
    limit = math.cos(radius)
    winner = np.full(c.shape[0], -1, np.int64)
    for i in range(n):  # a catalog star goes to its closest image star, the first of equals
        if best[i] >= limit:
            w = winner[nearest[i]]
            if w < 0 or best[i] > best[w]:
                winner[nearest[i]] = i
    count = 0
    for i in range(n):
        if best[i] >= limit and winner[nearest[i]] == i:
            rows_b[count] = i
            rows_c[count] = nearest[i]
            count += 1
    return count


@kernel(inline=True)
def _pattern_edges(v):  # pragma: no cover - compiled
    """The 6 sorted edges of a 4-star pattern (4, 3), rad (:data:`opnav.image.starid_index.EDGE_FIRST` order)."""
    edges = np.empty(6)
    k = 0
    for i in range(4):
        for j in range(i + 1, 4):
            edges[k] = _angle(v[i], v[j])
            k += 1
    return np.sort(edges)


@kernel
def verify_kernel(b, subset, pattern, stage, focal_scale, free_scale, radius, matrix, v_pattern, rows_image,
                  rows_index, v_matched, zones, directions):  # pragma: no cover - compiled
    """Steps 4-5 of one candidate (:func:`opnav.image.starid._verify_candidate`), from ``stage`` on.

    Stages: -1, the catalog pattern's directions read (into ``v_pattern``) and the star correspondence
    (the order of them whose angle matrix best fits the image's), the angle test, the 4-star attitude
    (into ``matrix``) and its residual test; 0-2, the refits: the index stars within the bearings' cone
    of the boresight ``matrix[:, 2]`` matched one-to-one within ``radius``, the attitude (and the focal
    scale when ``free_scale``) fitted to the matches; 3, the last match. The index stars are searched
    (:func:`_search`) over the cone widened by ``0.05 cone + 4 radius``, again only when a refit's cone
    leaves them (the refits move the boresight and the cone by about the match radius).

    Parameters
    ----------
    b : ndarray, shape (N, 3)
        Image bearings, camera frame, at the assumed focal length.
    subset : ndarray, shape (4,) int64
        Rows of ``b`` of the image pattern.
    pattern : ndarray, shape (4,) int64
        Index rows of the catalog pattern's stars.
    stage : int
        Stage to start from (-1 for a new candidate; the stage returned after a ``NEED_`` status).
    focal_scale : float
        ``f_true / f_assumed`` so far.
    free_scale : bool
        Re-fit the focal scale at each refit.
    radius : float
        Match radius, rad.
    matrix : ndarray, shape (3, 3)
        The attitude (camera -> ICRF), updated in place.
    v_pattern : ndarray, shape (4, 3)
        Set to the pattern stars' ICRF directions in the order matched to ``subset``.
    rows_image, rows_index : ndarray, shape (N,) int64
    v_matched : ndarray, shape (N, 3)
        Filled with the matched rows of ``b`` (ascending), index rows and ICRF directions (``DONE``).
    zones, directions : tuple
        The index's star search (module section "the index's star directions").

    Returns
    -------
    status : int
        ``REJECT``, ``DONE``, ``NEED_BAND`` or ``NEED_DIRECTIONS`` (module constants).
    stage : int
        The stage to go on from after a ``NEED_`` status.
    focal_scale : float
    cone : float
        The cone of the bearings (their largest angle from the optical axis plus ``radius``), rad, of the
        last refit's stars (``DONE``).
    matched : int
        Matches of the last match (``DONE``).
    nearby : int
        Index stars within the last refit's cone.
    closeness : float
        The larger of the pattern's largest edge-ratio difference and its largest residual over its
        largest edge (module step 6).
    lo, hi, stale
        What a ``NEED_`` status needs (:func:`_search`).
    """
    values = directions[0]
    no_rows = np.empty(0, np.int64)
    b_scaled = _rescale(b, focal_scale)
    cone = 0.0
    if stage == -1:
        stale = np.empty(4, np.int64)
        n_stale = 0
        for i in range(4):
            if not _fresh(pattern[i], directions):
                stale[n_stale] = pattern[i]
                n_stale += 1
        if n_stale:
            return NEED_DIRECTIONS, stage, focal_scale, cone, 0, 0, 0.0, 0, 0, stale[:n_stale]
        for i in range(4):
            v_pattern[i] = values[pattern[i]]
        image = np.empty((4, 4))
        catalog = np.empty((4, 4))
        image_sum = 0.0
        catalog_sum = 0.0
        for i in range(4):
            for j in range(4):
                image[i, j] = _angle(b[subset[i]], b[subset[j]])
                catalog[i, j] = _angle(v_pattern[i], v_pattern[j])
                image_sum += image[i, j]
                catalog_sum += catalog[i, j]
        factor = catalog_sum / image_sum
        best, order = np.inf, 0
        for p in range(PERMUTATIONS.shape[0]):
            cost = 0.0
            for i in range(4):
                for j in range(4):
                    cost += abs(catalog[PERMUTATIONS[p, i], PERMUTATIONS[p, j]] - image[i, j] * factor)
            if cost < best:
                best, order = cost, p
        original = v_pattern.copy()
        for i in range(4):
            v_pattern[i] = original[PERMUTATIONS[order, i]]
        b_pattern = np.empty((4, 3))
        for i in range(4):
            b_pattern[i] = b_scaled[subset[i]]
        # A rotation keeps angles, so residuals all within the radius need every pair's angles to agree
        # within twice it: most false candidates end here, before the attitude fit.
        for i in range(4):
            for j in range(4):
                if abs(_angle(b_pattern[i], b_pattern[j]) - _angle(v_pattern[i], v_pattern[j])) > 2.0 * radius:
                    return REJECT, stage, focal_scale, cone, 0, 0, 0.0, 0, 0, no_rows
        matrix[:, :] = _wahba(b_pattern, v_pattern)
        predicted = _predicted(v_pattern, matrix)
        for i in range(4):
            if _angle(b_pattern[i], predicted[i]) > radius:
                return REJECT, stage, focal_scale, cone, 0, 0, 0.0, 0, 0, no_rows
        stage = 0
    n = b.shape[0]
    searched = False
    axis = np.empty(3)
    reach = 0.0
    wide_rows = no_rows
    wide = np.empty((0, 3))
    near_rows = np.empty(0, np.int64)
    near = np.empty((0, 3))
    rows_star = np.empty(n, np.int64)
    matched = 0
    while stage <= 3:
        if stage < 3:
            cone = 0.0
            for i in range(n):
                cone = max(cone, math.acos(min(max(b_scaled[i, 2], -1.0), 1.0)))
            cone += radius
            inside = False
            if searched:  # the cone must lie within the stars searched, else search again
                cosine = matrix[0, 2] * axis[0] + matrix[1, 2] * axis[1] + matrix[2, 2] * axis[2]
                inside = math.acos(min(1.0, cosine)) + cone <= reach
            if not inside:
                axis = matrix[:, 2].copy()
                reach = cone + 0.05 * cone + 4.0 * radius
                status, wide_rows, wide, lo, hi, stale = _search(axis, 2.0 * math.sin(reach / 2.0), zones, directions)
                if status != DONE:
                    return status, stage, focal_scale, cone, 0, 0, 0.0, lo, hi, stale
                searched = True
            chord = 2.0 * math.sin(cone / 2.0)
            near_rows = np.empty(wide.shape[0], np.int64)
            count = 0
            for k in range(wide.shape[0]):
                dx = wide[k, 0] - matrix[0, 2]
                dy = wide[k, 1] - matrix[1, 2]
                dz = wide[k, 2] - matrix[2, 2]
                if dx * dx + dy * dy + dz * dz <= chord * chord:
                    near_rows[count] = k
                    count += 1
            near = np.empty((count, 3))
            for k in range(count):
                near[k] = wide[near_rows[k]]
        matched = _match(b_scaled, _predicted(near, matrix), radius, rows_image, rows_star)
        if stage == 3:
            break
        if matched < 4:
            return REJECT, stage, focal_scale, cone, matched, near.shape[0], 0.0, 0, 0, no_rows
        b_matched = np.empty((matched, 3))
        v_fit = np.empty((matched, 3))
        for m in range(matched):
            b_matched[m] = b_scaled[rows_image[m]]
            v_fit[m] = near[rows_star[m]]
        matrix[:, :] = _wahba(b_matched, v_fit)
        if free_scale:
            # least-squares s with tangent(b) / s = tangent(c) over the matched rows
            c_matched = _predicted(v_fit, matrix)
            uu = 0.0
            ut = 0.0
            for m in range(matched):
                ux = b_matched[m, 0] / b_matched[m, 2]
                uy = b_matched[m, 1] / b_matched[m, 2]
                uu += ux * ux + uy * uy
                ut += ux * (c_matched[m, 0] / c_matched[m, 2]) + uy * (c_matched[m, 1] / c_matched[m, 2])
            focal_scale *= uu / ut
            b_scaled = _rescale(b, focal_scale)
        stage += 1
    if matched < 5:  # nothing beyond the pattern confirms it
        return REJECT, stage, focal_scale, cone, matched, near.shape[0], 0.0, 0, 0, no_rows
    for m in range(matched):
        rows_index[m] = wide_rows[near_rows[rows_star[m]]]
        v_matched[m] = near[rows_star[m]]
    b_pattern = np.empty((4, 3))
    for i in range(4):
        b_pattern[i] = b_scaled[subset[i]]
    image_edges = _pattern_edges(b_pattern)
    catalog_edges = _pattern_edges(v_pattern)
    closeness = 0.0
    for k in range(5):
        closeness = max(closeness, abs(image_edges[k] / image_edges[5] - catalog_edges[k] / catalog_edges[5]))
    predicted = _predicted(v_pattern, matrix)
    for i in range(4):
        closeness = max(closeness, _angle(b_pattern[i], predicted[i]) / image_edges[5])
    return DONE, stage, focal_scale, cone, matched, near.shape[0], closeness, 0, 0, no_rows


@kernel
def rigid_kernel(b, subsets, catalog, scale, radius):  # pragma: no cover - compiled
    """Which candidates can pass :func:`verify_kernel`'s angle test (:func:`opnav.image.starid._rigid_candidates`):
    the least, over the 24 orders of the catalog stars (``catalog``, (C, 4, 3) ICRF), of the largest
    difference between the image pattern's angles (bearings ``b`` rows ``subsets`` (C, 4) at focal
    scales ``scale``) and the catalog pattern's is within twice ``radius`` (a hair's margin for rounding)."""
    count = subsets.shape[0]
    out = np.empty(count, np.bool_)
    image = np.empty((4, 3))
    image_angles = np.empty((4, 4))
    catalog_angles = np.empty((4, 4))
    for c in range(count):
        for i in range(4):
            row = subsets[c, i]
            x = b[row, 0] / b[row, 2] / scale[c]
            y = b[row, 1] / b[row, 2] / scale[c]
            norm = math.sqrt(x * x + y * y + 1.0)
            image[i, 0] = x / norm
            image[i, 1] = y / norm
            image[i, 2] = 1.0 / norm
        for i in range(4):
            for j in range(4):
                image_angles[i, j] = _angle(image[i], image[j])
                catalog_angles[i, j] = _angle(catalog[c, i], catalog[c, j])
        least = np.inf
        for p in range(PERMUTATIONS.shape[0]):
            worst = 0.0
            for i in range(4):
                for j in range(4):
                    worst = max(worst, abs(catalog_angles[PERMUTATIONS[p, i], PERMUTATIONS[p, j]] - image_angles[i, j]))
            least = min(least, worst)
        out[c] = least <= 2.0 * radius * (1.0 + 1e-9)
    return out


@kernel
def rotation_quaternion(matrix):  # pragma: no cover - compiled
    """The quaternion (x, y, z, w), not normalised, of a rotation matrix (3, 3): the branch of the
    largest of its diagonal and trace, as ``scipy.spatial.transform.Rotation.from_matrix`` takes it, so
    that ``Rotation.from_quat`` of it (which normalises) is that rotation to the bit, in a fifth of the
    time (27 us)."""
    q = np.empty(4)
    trace = matrix[0, 0] + matrix[1, 1] + matrix[2, 2]
    choice, top = 0, matrix[0, 0]
    if matrix[1, 1] > top:
        choice, top = 1, matrix[1, 1]
    if matrix[2, 2] > top:
        choice, top = 2, matrix[2, 2]
    if trace > top:
        choice = 3
    if choice == 3:
        q[0] = matrix[2, 1] - matrix[1, 2]
        q[1] = matrix[0, 2] - matrix[2, 0]
        q[2] = matrix[1, 0] - matrix[0, 1]
        q[3] = 1.0 + trace
    else:
        i = choice
        j = (i + 1) % 3
        k = (j + 1) % 3
        q[i] = 1.0 - trace + 2.0 * matrix[i, i]
        q[j] = matrix[j, i] + matrix[i, j]
        q[k] = matrix[k, i] + matrix[i, k]
        q[3] = matrix[k, j] - matrix[j, k]
    return q

# ----------------------------------------------------------------------------- the index's star directions
# ``zones`` = (sorted_z, order, sorted_points, gathered, chunk, max_shift) of a
# :class:`opnav.image.starid_index.StarZones`: the ``z`` of its unmoved directions ascending, their rows,
# those directions in that order (rows of chunks not yet ``gathered`` unset) and the largest chord from
# them to the directions searched. ``directions`` = (values, epoch, checked_by, token, t0_tdb_s, r0_km,
# pm_rad_yr, parallax_rad, t_tdb_s, r_km, with_parallax, tolerance_rad, year_s, au_km): the directions
# searched (ICRF unit vectors), and when ``epoch`` the cache of an at_epoch copy's reader (``token``)
# whose rows are checked for its epoch as they are read (:func:`_fresh`).


@kernel(inline=True)
def _fresh(row, directions):  # pragma: no cover - compiled
    """Whether the cached direction of ``row`` is good for the reader's epoch (marked checked if so).

    A star's direction ``n = unit(u0 + w dt)`` changes by at most ``|w| |dt|`` (``w`` the proper
    motion, perpendicular to ``u0``) between the epoch ``t0`` it was computed for and ``t``, and with
    parallax ``n = unit(D (u0 + w dt) - r)`` by at most ``|dr| / D = parallax |dr| / AU`` for a move
    ``dr`` of the observer, to first order; twice that bound covers the higher orders (``|r| / D <
    1e-5``, radial velocity). A row is computed again when the bound exceeds ``tolerance_rad`` or is
    NaN (never computed: ``t0`` NaN).
    """
    (_, epoch, checked_by, token, t0_tdb_s, r0_km, pm_rad_yr, parallax_rad, t_tdb_s, r_km, with_parallax,
     tolerance_rad, year_s, au_km) = directions
    if not epoch or checked_by[row] == token:
        return True
    bound = pm_rad_yr[row] * (abs(t_tdb_s - t0_tdb_s[row]) / year_s)
    if with_parallax:
        dx = r_km[0] - r0_km[row, 0]
        dy = r_km[1] - r0_km[row, 1]
        dz = r_km[2] - r0_km[row, 2]
        bound += parallax_rad[row] * (math.sqrt(dx * dx + dy * dy + dz * dz) / au_km)
    if 2.0 * bound <= tolerance_rad:
        checked_by[row] = token
        return True
    return False


@kernel(inline=True)
def _search(x, r, zones, directions):  # pragma: no cover - compiled
    """The stars within chord ``r`` of the unit vector ``x`` (:meth:`opnav.image.starid_index.StarZones.ball_rows`).

    Returns ``(status, rows, vectors, lo, hi, stale)``: ``DONE`` with their rows (ascending) and
    directions (ICRF); ``NEED_BAND`` with the zones' rows ``lo:hi`` to gather; ``NEED_DIRECTIONS`` with the
    ``stale`` rows to compute.
    """
    sorted_z, order, sorted_points, gathered, chunk, max_shift = zones
    values = directions[0]
    reach = r + max_shift + 1e-12
    lo = np.searchsorted(sorted_z, x[2] - reach)
    hi = np.searchsorted(sorted_z, x[2] + reach)
    no_rows = np.empty(0, np.int64)
    if hi > lo:
        for c in range(lo // chunk, (hi - 1) // chunk + 1):
            if not gathered[c]:
                return NEED_BAND, no_rows, np.empty((0, 3)), lo, hi, no_rows
    # the band is a ring around the sky: the sorted (unmoved) directions, read in order, keep the stars
    # within reach of x, and only those few (moved) directions are read (computed, at_epoch)
    near = np.empty(hi - lo, np.int64)
    stale = np.empty(hi - lo, np.int64)
    count = 0
    n_stale = 0
    for k in range(lo, hi):
        dx = sorted_points[k, 0] - x[0]
        dy = sorted_points[k, 1] - x[1]
        dz = sorted_points[k, 2] - x[2]
        if dx * dx + dy * dy + dz * dz <= reach * reach:
            row = order[k]
            if _fresh(row, directions):
                near[count] = row
                count += 1
            else:
                stale[n_stale] = row
                n_stale += 1
    if n_stale:
        return NEED_DIRECTIONS, no_rows, np.empty((0, 3)), lo, hi, stale[:n_stale]
    rows = np.empty(count, np.int64)
    kept = 0
    for k in range(count):
        row = near[k]
        dx = values[row, 0] - x[0]
        dy = values[row, 1] - x[1]
        dz = values[row, 2] - x[2]
        if dx * dx + dy * dy + dz * dz <= r * r:
            rows[kept] = row
            kept += 1
    rows = np.sort(rows[:kept])
    vectors = np.empty((kept, 3))
    for k in range(kept):
        vectors[k, 0] = values[rows[k], 0]
        vectors[k, 1] = values[rows[k], 1]
        vectors[k, 2] = values[rows[k], 2]
    return DONE, rows, vectors, lo, hi, no_rows


@kernel
def search_kernel(x, r, zones, directions):  # pragma: no cover - compiled
    """:func:`_search` (its statuses and results)."""
    return _search(x, r, zones, directions)


@kernel
def read_rows_kernel(rows, gather, directions):  # pragma: no cover - compiled
    """The cached directions of ``rows`` (negative rows counted from the end) when ``gather`` (else an
    empty array), and the rows (in order) whose direction must be computed again for the reader's
    epoch (:func:`_fresh`; the others are marked checked)."""
    values = directions[0]
    count = values.shape[0]
    stale = np.empty(rows.shape[0], np.int64)
    gathered = np.empty((rows.shape[0] if gather else 0, 3))
    n_stale = 0
    for k in range(rows.shape[0]):
        row = rows[k] % count
        if gather:
            gathered[k, 0] = values[row, 0]
            gathered[k, 1] = values[row, 1]
            gathered[k, 2] = values[row, 2]
        if not _fresh(row, directions):
            stale[n_stale] = row
            n_stale += 1
    return gathered, stale[:n_stale]
