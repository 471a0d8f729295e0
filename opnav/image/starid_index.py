"""Pattern index for lost-in-space star identification (geometric hashing of 4-star patterns).

Algorithm (tetra3-style, Brown & Stubis 2017, with several field-of-view levels)
-----------------------------------------------------------------------------
1. Keep catalog stars brighter than ``vmag_limit``, sorted brightest first.
2. For each level field of view ``F`` (a geometric ladder from ``fov_min_deg`` to
   ``fov_max_deg``, step ``level_ratio``) a star is a *pattern star* when it is among the
   ``pattern_stars_per_fov`` brightest stars within ``F/2`` of itself. This keeps about that
   many pattern stars in every 4:3 frame of width ``F``, dense sky or sparse.
   *Verification stars* are chosen the same way with ``verification_stars_per_fov`` at
   ``fov_min_deg``; every star of the index is a verification star or a pattern star.
3. Patterns of a level, by ``selection``:

   ``"density"``: every set of 4 pattern stars whose 6 pairwise angles are all at most
   ``pattern_size_fraction * F``. The count grows as the cube of the stars within that
   distance, which is fine for wide fields but not for a 1-degree field, where nearly every
   catalog star is a pattern star (36 million patterns for the packaged catalog).

   ``"fields"``: lattice fields spread evenly over the sky: ``field_oversampling`` times as
   many centres (a Fibonacci lattice, equal-area) as disks of radius
   ``rho = pattern_size_fraction * F / 2`` needed to tile it. In each disk the
   ``pattern_stars_per_fov`` brightest stars form all their 4-subsets (all edges are then at
   most ``2 rho``, so a pattern fits in the frame's short side). A frame of width ``F`` covers
   several such disks whole or in large part, and the brightest stars of a disk are the ones
   a frame detects first, so some 4-set of the frame's brightest stars is in the index; the
   count is bounded by ``fields x C(pattern_stars_per_fov, 4)`` however deep the catalog.

   *Sparse level* (``sparse_spacing_fraction`` > 0): a frame with only 5-6 stars spread over the
   whole field holds no 4 of them within ``pattern_size_fraction`` of a level (a 0.05 s exposure
   of a 6-degree field at high galactic latitude), and its fainter stars are not among the
   ``pattern_stars_per_fov`` brightest of the larger levels, whose disks reach bright stars beyond
   the frame. So one more set of patterns is made from the stars that are the brightest within
   ``sparse_spacing_fraction * fov_max_deg`` of themselves (local brightness maxima: an even
   spread of about one star per disk of that radius, which is what such a frame shows) with every
   edge up to ``fov_max_deg``.

   The 6 angles of a pattern sorted ascending and divided by the largest give 5 ratios in
   (0, 1]; ``floor(ratio * pattern_bins)`` for each gives the hash key
   ``sum_k q_k * pattern_bins**k``.
4. Patterns are stored sorted by key, so a lookup is a ``numpy.searchsorted`` (vectorised over
   every probe key of a frame at once); the ratios and largest angle are kept for the exact check.

The index is immutable. :func:`load_or_build_index` caches it under ``$OPNAV_CACHE`` (default
``~/.cache/opnav``) as a directory of memory-mapped ``.npy`` files (:mod:`opnav.image.starid_store`:
opened in milliseconds, its SHA-256 checksums verified once after the build, then size, headers
and a marker checked on each load), keyed by a digest of the catalog content and the options, so
a changed catalog or option builds a new index and a corrupt or unreadable one is rebuilt; a
single ``.npz`` cache file of earlier versions is converted on first use. The index for a field
of view (:func:`index_options_for_fov`) and the indexes a search tries
(:func:`choose_indexes`) are chosen here too.

Observation epoch: :meth:`PatternIndex.at_epoch` moves the star directions to the frame's date
and observer, each star when the solver first reads it (a frame reads a few thousand of the
490,000 stars of a 1-degree index). Frames solved one after another in a process (``opnav solve
FRAMES...``) share the work: each star's direction is kept with the epoch and observer position it
was computed for, and computed again only when a frame reads it and the star would have moved by
more than ``EPOCH_REUSE_TOLERANCE_RAD`` since (a bound from its proper motion and parallax).
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import logging
import math
import os
import time
import weakref
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Callable, Protocol

import numpy as np
from scipy.spatial import cKDTree

from ..allocator import returning_freed_memory
from ..constants import AU_KM, JULIAN_YEAR_S
from ..errors import CatalogError, InputError
from ..files import default_cache_dir

log = logging.getLogger(__name__)

#: Version of the index content (arrays and their meaning); the cache key carries it.
FORMAT_VERSION = 3
SELECTIONS = ("density", "fields")
#: Arrays of an index, in the order their bytes enter its checksum.
_ARRAYS = ("star_vectors", "star_vmag", "catalog_rows", "patterns", "keys", "ratios", "max_edge_rad")
#: :meth:`PatternIndex.at_epoch` reuses a star's direction computed for another epoch or observer
#: position when its bound on the star's motion between them is below this, rad (20 micro-arcseconds,
#: a millionth of a 20"/px pixel).
EPOCH_REUSE_TOLERANCE_RAD = 1e-10
SKY_DEG2 = 4.0 * math.pi * math.degrees(1.0) ** 2


class StarSource(Protocol):
    """What the index needs from a star catalog (``opnav.catalog.StarCatalog`` satisfies it)."""

    vmag: np.ndarray

    def unit_vectors(self) -> np.ndarray: ...


@dataclass(frozen=True)
class IndexOptions:
    """Options of :func:`build_index` (see the module docstring for their meaning).

    Parameters
    ----------
    fov_min_deg, fov_max_deg : float
        Range of horizontal fields of view the index serves, deg.
    vmag_limit : float
        Faintest catalog magnitude used.
    pattern_stars_per_fov : int
        Pattern-star density: brightest stars kept within ``F/2`` of each star.
    verification_stars_per_fov : int
        Verification-star density at ``fov_min_deg``.
    pattern_bins : int
        Quantisation bins per edge ratio.
    pattern_size_fraction : float
        Largest pattern edge as a fraction of the level FOV (0.75 = short side of a 4:3 frame).
    level_ratio : float
        Ratio between successive level FOVs.
    selection : {"density", "fields"}
        How the patterns of a level are chosen (module docstring, step 3): every close 4-set of
        the level's pattern stars (``"density"``), or the 4-sets of the brightest stars of
        lattice fields spread evenly over the sky (``"fields"``, for narrow fields of view).
    field_oversampling : float
        ``"fields"`` only: lattice fields per field area (1 = the fields just tile the sky).
    sparse_spacing_fraction : float
        Sparse level (module docstring, step 3): stars that are the brightest within this fraction
        of ``fov_max_deg`` of themselves form every 4-set with edges up to ``fov_max_deg``;
        0 (the default) makes no sparse level.
    """

    fov_min_deg: float
    fov_max_deg: float
    vmag_limit: float
    pattern_stars_per_fov: int = 10
    verification_stars_per_fov: int = 30
    pattern_bins: int = 50
    pattern_size_fraction: float = 0.7
    level_ratio: float = 1.4
    selection: str = "density"
    field_oversampling: float = 3.0
    sparse_spacing_fraction: float = 0.0

    def __post_init__(self) -> None:
        if self.selection not in SELECTIONS:
            raise InputError(f"selection must be one of {', '.join(SELECTIONS)}, got {self.selection!r}")
        if not (math.isfinite(self.field_oversampling) and 0.5 <= self.field_oversampling <= 20.0):
            raise InputError(f"field_oversampling must be in [0.5, 20], got {self.field_oversampling!r}")
        if not (0.0 < self.fov_min_deg <= self.fov_max_deg < 120.0):
            raise InputError(f"need 0 < fov_min_deg <= fov_max_deg < 120, got {self.fov_min_deg}, {self.fov_max_deg}")
        if not math.isfinite(self.vmag_limit):
            raise InputError(f"vmag_limit must be finite, got {self.vmag_limit!r}")
        if not (4 <= self.pattern_stars_per_fov <= 40):
            raise InputError(f"pattern_stars_per_fov must be in [4, 40], got {self.pattern_stars_per_fov}")
        if self.verification_stars_per_fov < self.pattern_stars_per_fov:
            raise InputError("verification_stars_per_fov must be >= pattern_stars_per_fov")
        if not (4 <= self.pattern_bins <= 200):
            raise InputError(f"pattern_bins must be in [4, 200], got {self.pattern_bins}")
        if not (0.1 <= self.pattern_size_fraction <= 1.0):
            raise InputError(f"pattern_size_fraction must be in [0.1, 1], got {self.pattern_size_fraction}")
        if not (self.sparse_spacing_fraction == 0.0 or 0.05 <= self.sparse_spacing_fraction <= 0.5):
            raise InputError(f"sparse_spacing_fraction must be 0 or in [0.05, 0.5], got {self.sparse_spacing_fraction!r}")
        if not (self.level_ratio > 1.05):
            raise InputError(f"level_ratio must be > 1.05, got {self.level_ratio}")

    def level_fovs_rad(self) -> np.ndarray:
        """Field of view of each level, rad."""
        n = 1 + max(0, math.ceil(math.log(self.fov_max_deg / self.fov_min_deg) / math.log(self.level_ratio) - 1e-9))
        return np.radians(self.fov_min_deg * self.level_ratio ** np.arange(n))


def _chord(angle_rad: float | np.ndarray) -> float | np.ndarray:
    return 2.0 * np.sin(np.asarray(angle_rad) / 2.0)


def pair_angles(vectors: np.ndarray, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Angles (rad) between ``vectors[..., first, :]`` and ``vectors[..., second, :]`` (unit vectors).

    Uses ``2 asin(chord / 2)``, accurate for the small angles of narrow fields.
    """
    chord = np.linalg.norm(vectors[..., first, :] - vectors[..., second, :], axis=-1)
    return 2.0 * np.arcsin(np.minimum(chord / 2.0, 1.0))


#: The 6 edges of a 4-star pattern as (first, second) star positions.
EDGE_FIRST = np.array([0, 0, 0, 1, 1, 2])
EDGE_SECOND = np.array([1, 2, 3, 2, 3, 3])


def pattern_ratios(edges_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted-edge ratios (..., 5) and the largest edge (...,) of patterns with edges (..., 6)."""
    edges = np.sort(edges_rad, axis=-1)
    return edges[..., :5] / edges[..., 5:], edges[..., 5]


def pattern_keys(quantised: np.ndarray, bins: int) -> np.ndarray:
    """Hash keys (...,) int64 of quantised ratios (..., 5)."""
    return np.asarray(quantised, dtype=np.int64) @ (np.int64(bins) ** np.arange(5, dtype=np.int64))


def _brightest_nearby(vectors: np.ndarray, radius_rad: float, count: int) -> np.ndarray:
    """Mask of stars among the ``count`` brightest within ``radius_rad``; rows sorted brightest first."""
    pairs = cKDTree(vectors).query_pairs(float(_chord(radius_rad)), output_type="ndarray")
    brighter = np.bincount(pairs.max(axis=1), minlength=len(vectors)) if len(pairs) else np.zeros(len(vectors), int)
    return brighter < count


@lru_cache(maxsize=256)
def _triples(n: int) -> np.ndarray:
    return np.array(list(itertools.combinations(range(n), 3)), dtype=np.int32).reshape(-1, 3)


def _level_patterns(vectors: np.ndarray, max_edge_rad: float) -> np.ndarray:
    """All 4-sets (P, 4) of rows of ``vectors`` with every pairwise angle <= ``max_edge_rad``.

    Each set is listed once, from its first (brightest) row.
    """
    tree = cKDTree(vectors)
    chord = float(_chord(max_edge_rad))
    pairs = tree.query_pairs(chord, output_type="ndarray")
    if len(pairs) == 0:
        return np.empty((0, 4), np.int32)
    pairs = np.sort(pairs, axis=1)
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    starts = np.searchsorted(pairs[:, 0], np.arange(len(vectors) + 1))
    cos_max = math.cos(max_edge_rad)
    found = []
    for first in range(len(vectors)):
        later = pairs[starts[first] : starts[first + 1], 1]
        if len(later) < 3:
            continue
        close = (vectors[later] @ vectors[later].T) >= cos_max
        triples = _triples(len(later))
        ok = close[triples[:, 0], triples[:, 1]] & close[triples[:, 0], triples[:, 2]] & close[triples[:, 1], triples[:, 2]]
        chosen = later[triples[ok]]
        found.append(np.column_stack([np.full(len(chosen), first), chosen]))
    return np.concatenate(found).astype(np.int32) if found else np.empty((0, 4), np.int32)


def fibonacci_lattice(count: int) -> np.ndarray:
    """``count`` unit vectors (count, 3) spread evenly (equal area per point) over the sphere."""
    i = np.arange(count, dtype=float)
    z = 1.0 - (2.0 * i + 1.0) / count
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


@lru_cache(maxsize=64)
def _quads_brightest_first(n: int) -> np.ndarray:
    """All 4-subsets (C(n, 4), 4) of ``range(n)``, those of brighter (lower) rows first."""
    rows = [(*first, last) for last in range(3, n) for first in itertools.combinations(range(last), 3)]
    return np.array(rows, dtype=np.int64).reshape(-1, 4)


#: Most lattice fields one level of a ``"fields"`` index may have: 4.4 times the 340,000 of the
#: 1-degree camera's lowest level (its index is 700 MB). A 0.05-degree field asked for 140 million
#: and held 9 GB a minute into the build.
MAX_LATTICE_FIELDS = 1_500_000
#: The narrowest horizontal field of view, deg, whose index stays within ``MAX_LATTICE_FIELDS`` with
#: the default options (``field_oversampling`` 3, lowest level 0.75 x 0.9 of the field, whole-field
#: patterns: a level field of radius sqrt(4 x 3 / MAX_LATTICE_FIELDS) rad): 4 sqrt(3 / MAX_LATTICE_FIELDS) /
#: (0.75 x 0.9) rad = 0.48 deg, rounded up.
MIN_INDEX_FOV_DEG = 0.5


def _field_patterns(
    vectors: np.ndarray, tree: cKDTree, radius_rad: float, stars_per_field: int, oversampling: float,
    progress=None,
) -> np.ndarray:
    """4-sets (P, 4), rows sorted, of the brightest stars of lattice fields (module step 3, "fields").

    ``vectors`` rows are sorted brightest first, so the brightest stars of a field are its
    lowest rows.
    """
    count = max(12, int(math.ceil(oversampling * 4.0 * math.pi / (math.pi * radius_rad**2))))
    if count > MAX_LATTICE_FIELDS:
        raise InputError(f"a pattern index of {math.degrees(2.0 * radius_rad):.3g}-degree fields needs {count:,} lattice "
                         f"fields over the sky (gigabytes of patterns); at most {MAX_LATTICE_FIELDS:,}: fields of view "
                         f"from about {MIN_INDEX_FOV_DEG:g} deg")
    chord = float(_chord(radius_rad))
    lattice = fibonacci_lattice(count)
    found = []
    chunk = 100_000
    for lo in range(0, count, chunk):
        centres = lattice[lo : lo + chunk]
        members = tree.query_ball_point(centres, chord, return_sorted=False)
        lengths = np.fromiter((len(m) for m in members), dtype=np.int64, count=len(members))
        flat = np.fromiter(itertools.chain.from_iterable(members), dtype=np.int64, count=int(lengths.sum()))
        field_of = np.repeat(np.arange(len(members)), lengths)
        order = np.lexsort((flat, field_of))
        flat = flat[order]
        rank = np.arange(len(flat)) - np.repeat(np.cumsum(lengths) - lengths, lengths)
        kept = np.minimum(lengths, stars_per_field)
        flat = flat[rank < stars_per_field]
        starts = np.cumsum(kept) - kept
        for m in range(4, stars_per_field + 1):
            fields = np.flatnonzero(kept == m)
            if len(fields) == 0:
                continue
            stars = flat[starts[fields][:, None] + np.arange(m)[None, :]]
            quads = stars[:, _quads_brightest_first(m)].reshape(-1, 4)
            found.append(_unique_rows(quads.astype(np.int32)))
        if progress is not None:
            progress(min(lo + chunk, count), count)
    if not found:
        return np.empty((0, 4), np.int32)
    return _unique_rows(np.concatenate(found))


def _unique_rows(rows: np.ndarray) -> np.ndarray:
    """Distinct rows of an (N, 4) int32 array, in no particular order.

    Each row is read as two int64 words (a view, no copy), so one ``lexsort`` of two keys finds
    the duplicates: about half the peak memory of ``np.unique(axis=0)``, which holds the largest
    arrays of an index build.
    """
    words = np.ascontiguousarray(rows, dtype=np.int32).view(np.int64)
    words = words[np.lexsort((words[:, 1], words[:, 0]))]
    new = np.ones(len(words), bool)
    new[1:] = (words[1:, 0] != words[:-1, 0]) | (words[1:, 1] != words[:-1, 1])
    return words[new].view(np.int32).reshape(-1, 4)


class SortedChunks:
    """``points[order]`` (K, 3), each chunk of ``CHUNK`` rows gathered on first use.

    A band of the zones (:class:`StarZones`) is then read in order; its rows of a memory-mapped index
    are scattered over the index's directions (12 MB at 1 degree): a search read ~6,000 of them at
    random, 0.7 ms, three times a candidate. Gathering all of them at once cost ~30 ms, which a process
    solving one frame would pay for a few bands. The chunks are gathered into one buffer (allocated,
    not written, up front) that the compiled search reads (:mod:`opnav.image.starid_compiled`).
    """

    CHUNK = 4096

    def __init__(self, points: np.ndarray, order: np.ndarray) -> None:
        self._points, self._order = points, order
        #: ``points[order]`` (K, 3), the rows of the chunks ``gathered`` set.
        self.sorted = np.empty((len(order), 3))
        self.gathered = np.zeros(-(-len(order) // self.CHUNK), bool)

    def gather(self, lo: int, hi: int) -> None:
        """Gather the chunks of rows ``lo:hi`` not gathered yet."""
        if hi <= lo:
            return
        for k in range(lo // self.CHUNK, (hi - 1) // self.CHUNK + 1):
            if not self.gathered[k]:
                rows = np.asarray(self._order[k * self.CHUNK:(k + 1) * self.CHUNK])
                self.sorted[k * self.CHUNK:k * self.CHUNK + len(rows)] = \
                    np.asarray(self._points[rows], dtype=float).reshape(-1, 3)
                self.gathered[k] = True


class StarZones:
    """``query_ball_point`` over star directions by declination zones (the :attr:`PatternIndex.tree`).

    The stars are kept sorted by ``z`` (sine of the declination); the stars within chord ``r`` of
    ``x`` lie in the band ``|z - x_z| <= r``, found by two binary searches, and their distances pick
    them out. Unlike a ``cKDTree`` (0.13 s to build for the 490,000 stars of a 1-degree index) the
    order is stored with the index, so a process that solves one frame builds nothing. Directions
    moved from the sorted ones by at most ``max_shift`` (chord, :meth:`PatternIndex.at_epoch`) are
    searched in the same order with the band widened by it. Other ``cKDTree`` methods build one
    on first use.

    Parameters
    ----------
    points : ndarray, shape (K, 3)
        Unit vectors searched.
    order : ndarray, shape (K,)
        Rows of ``points`` sorted by the ``z`` of ``sorted_z`` (of these or of unmoved points).
    sorted_z : ndarray, shape (K,)
        That ``z``, ascending.
    max_shift : float
        Largest chord between ``points`` and the points ``sorted_z`` was taken from.
    unmoved : ndarray, shape (K, 3), optional
        Those points (when ``points`` moved from them): the band's stars beyond ``r + max_shift`` of
        them are left out before ``points`` is read.
    """

    def __init__(self, points: np.ndarray, order: np.ndarray, sorted_z: np.ndarray, max_shift: float = 0.0,
                 unmoved: np.ndarray | None = None, sorted_points: SortedChunks | None = None) -> None:
        self._points, self._order, self._sorted_z, self._max_shift = points, order, sorted_z, float(max_shift)
        self._unmoved = unmoved
        self._sorted_points = sorted_points
        self._tree: cKDTree | None = None


    @staticmethod
    def order_of(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(order, sorted_z)`` of unit vectors (K, 3)."""
        order = np.argsort(points[:, 2], kind="stable")
        return order, np.ascontiguousarray(points[order, 2])

    def ball_rows(self, x: np.ndarray, r: float) -> np.ndarray:
        """Rows (ascending, int64) of the points within chord ``r`` of the unit vector ``x`` (3,)."""
        x = np.ascontiguousarray(x, dtype=float)
        search = _compiled().search_kernel
        while True:
            status, rows, _, lo, hi, stale = search(x, float(r), *self.kernel_arguments())
            if not self.provide(status, lo, hi, stale):
                return rows

    def kernel_arguments(self) -> tuple[tuple, tuple]:
        """``(zones, directions)`` of the compiled search (:mod:`opnav.image.starid_compiled`): the sorted
        directions gathered so far, and the directions searched (an :meth:`PatternIndex.at_epoch` copy's
        epoch cache, checked as it is read)."""
        if self._sorted_points is None:
            self._sorted_points = SortedChunks(self._points if self._unmoved is None else self._unmoved, self._order)
        chunks = self._sorted_points
        zones = (self._sorted_z, self._order, chunks.sorted, chunks.gathered, chunks.CHUNK, self._max_shift)
        if isinstance(self._points, _EpochDirections):
            return zones, self._points.kernel_directions()
        return zones, (np.asarray(self._points, dtype=float), False, *_NO_EPOCH)

    def provide(self, status: int, lo: int, hi: int, stale: np.ndarray) -> bool:
        """Do what a compiled search's ``status`` asks (gather the sorted rows ``lo:hi``, or compute the
        ``stale`` rows' directions); False when it asks nothing."""
        if status == _compiled().NEED_BAND:
            self._sorted_points.gather(int(lo), int(hi))
            return True
        if status == _compiled().NEED_DIRECTIONS:
            self._points.compute(stale)
            return True
        return False

    def _ball(self, x: np.ndarray, r: float) -> list:
        return self.ball_rows(x, r).tolist()

    def query_ball_point(self, x, r, **kwargs):
        """Rows of the points within chord ``r`` of ``x`` (ascending), as ``cKDTree.query_ball_point``."""
        if kwargs:
            return self.__getattr__("query_ball_point")(x, r, **kwargs)
        x = np.asarray(x, dtype=float)
        if x.ndim == 1:
            return self._ball(x, float(r))
        radii = np.broadcast_to(np.asarray(r, dtype=float), x.shape[:-1])
        out = np.empty(x.shape[:-1], dtype=object)
        for k in np.ndindex(*x.shape[:-1]):
            out[k] = self._ball(x[k], float(radii[k]))
        return out

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        if self._tree is None:
            self._tree = cKDTree(self._points)
        return getattr(self._tree, name)


#: Tokens of :class:`_EpochDirections` readers (0: no reader).
_READER_TOKENS = itertools.count(1)
_NO_POSITION = np.zeros(3)
#: The ``directions`` of the compiled search after the values, for directions that are not an epoch's.
_NO_EPOCH = (np.zeros(0, np.int64), 0, np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0), 0.0, _NO_POSITION,
             False, 0.0, JULIAN_YEAR_S, AU_KM)


_KERNELS = None


def _compiled():
    """:mod:`opnav.image.starid_compiled`, imported on first use (numba is not needed to read an index)."""
    global _KERNELS
    if _KERNELS is None:
        from . import starid_compiled

        _KERNELS = starid_compiled
    return _KERNELS


class _DirectionCache:
    """The latest computed direction of each index star (ICRF unit vector) with the epoch (TDB s past
    J2000; NaN: never computed) and observer position (km, ICRF, from the barycentre) it is for."""

    def __init__(self, count: int) -> None:
        self.values = np.empty((count, 3))
        self.t_tdb_s = np.full(count, np.nan)
        self.r_observer_km = np.zeros((count, 3))
        self.writes = 0  # batches of rows computed so far (a reader's checks stand until another writes)
        # the reader (_EpochDirections token) that last found each row's value good for its epoch
        self.checked_by = np.zeros(count, np.int64)


class _StarMotion:
    """Per-star bounds on how fast the index stars of one catalog move, and their computed directions
    (one cache with parallax, one without)."""

    def __init__(self, catalog, rows: np.ndarray) -> None:
        self.catalog = weakref.ref(catalog)
        self.pm_rad_yr = np.hypot(catalog.pm_ra_cosdec_rad_yr[rows], catalog.pm_dec_rad_yr[rows])
        self.parallax_rad = np.maximum(catalog.parallax_rad[rows], 0.0)
        epochs = getattr(catalog, "epoch_tdb_s", None)
        self.epoch_tdb_s = None if epochs is None else np.asarray(epochs)[rows]
        self.caches = {with_parallax: _DirectionCache(len(rows)) for with_parallax in (False, True)}
        # extremes for catalog_epoch_bound, once per catalog rather than over every star a frame
        self._extremes = None if epochs is None or not len(rows) else (
            float(np.max(self.pm_rad_yr)), float(np.min(self.epoch_tdb_s)), float(np.max(self.epoch_tdb_s)),
            float(np.max(self.parallax_rad)))

    def catalog_epoch_bound(self, t_tdb_s: float, r_observer_km: np.ndarray | None) -> float:
        """Bound (rad, and so on the chord) on every star's shift between its catalog direction (its
        catalog epoch, seen from the barycentre) and its direction at ``t_tdb_s`` from ``r_observer_km``:
        the terms of :func:`opnav.image.starid_compiled.read_rows_kernel`'s bound with the largest proper
        motion, time and parallax of the stars."""
        if self._extremes is None:
            return 0.0
        pm_max, first_epoch, last_epoch, parallax_max = self._extremes
        years = max(abs(t_tdb_s - first_epoch), abs(t_tdb_s - last_epoch)) / JULIAN_YEAR_S
        bound = pm_max * years
        if r_observer_km is not None:
            bound += parallax_max * math.sqrt(float(r_observer_km.dot(r_observer_km))) / AU_KM  # numpy's norm
        return 2.0 * bound


class _EpochDirections:
    """The star directions of an :meth:`PatternIndex.at_epoch` copy, each computed when first read.

    Read by numpy keys (``directions[rows]``, as the solver and :class:`StarZones` do; a copy is
    returned) or whole by ``numpy.asarray`` (a checksum, a pickle, a k-d tree). A star's direction is
    taken from the catalog's cache when its motion since the epoch and position it was computed for is
    within ``EPOCH_REUSE_TOLERANCE_RAD``, else computed (``compute(rows)``) and cached.
    """

    def __init__(self, motion: _StarMotion, t_tdb_s: float, r_observer_km: np.ndarray | None, compute) -> None:
        self._motion, self._t, self._r, self._compute = motion, t_tdb_s, r_observer_km, compute
        self._cache = motion.caches[r_observer_km is not None]
        self.shape = self._cache.values.shape
        self.ndim = 2
        self.dtype = self._cache.values.dtype
        # rows checked (or computed) for this epoch since the cache's last write by another reader are
        # marked with this reader's token in the cache (a new token forgets them all): the solver reads
        # the 4 stars of each candidate pattern, many small reads a frame
        self._token = next(_READER_TOKENS)
        self._writes_seen = self._cache.writes

    def __len__(self) -> int:
        return self.shape[0]

    def kernel_directions(self) -> tuple:
        """The ``directions`` of the compiled reads and searches (:mod:`opnav.image.starid_compiled`)."""
        cache, motion = self._cache, self._motion
        if cache.writes != self._writes_seen:  # another epoch computed stars since: check again
            self._token = next(_READER_TOKENS)
            self._writes_seen = cache.writes
        return (cache.values, True, cache.checked_by, self._token, cache.t_tdb_s, cache.r_observer_km,
                motion.pm_rad_yr, motion.parallax_rad, self._t, _NO_POSITION if self._r is None else self._r,
                self._r is not None, EPOCH_REUSE_TOLERANCE_RAD, JULIAN_YEAR_S, AU_KM)

    def compute(self, rows: np.ndarray) -> None:
        """Compute the directions of ``rows`` for this epoch into the cache (checked for it)."""
        cache = self._cache
        cache.values[rows] = self._compute(rows)
        cache.t_tdb_s[rows] = self._t
        cache.r_observer_km[rows] = 0.0 if self._r is None else self._r
        cache.writes += 1
        cache.checked_by[rows] = self._token
        self._writes_seen = cache.writes

    def _read(self, rows: np.ndarray, gather: bool) -> np.ndarray:
        """The directions of ``rows`` (1-D integers, negative from the end) when ``gather`` (a copy), each
        checked against this epoch first and computed again when stale."""
        rows = np.asarray(rows, dtype=np.int64)
        values, stale = _compiled().read_rows_kernel(rows, gather, self.kernel_directions())
        if len(stale):
            self.compute(stale)
            if gather:
                values = self._cache.values[rows]
        return values

    def __getitem__(self, key) -> np.ndarray:
        if type(key) is np.ndarray and key.dtype.kind in "iu":  # the solver's reads: rows (a copy)
            if key.ndim == 1:
                return self._read(key, True)
            self._read(np.ravel(key), False)
            return self._cache.values[key]
        first = key[0] if isinstance(key, tuple) else key
        if isinstance(first, np.ndarray) and first.dtype.kind in "iu":
            rows = first  # negative rows as numpy reads them
        else:
            rows = np.arange(self.shape[0])[first]  # the rows any other numpy key reads
        self._read(np.ravel(rows), False)
        return np.array(self._cache.values[key])  # a copy: a later epoch may compute these stars again

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        return self[np.arange(self.shape[0])].astype(dtype or self.dtype, copy=False)

    def setflags(self, write: bool) -> None:
        """Read-only already (reads return copies); for :class:`PatternIndex`'s ``__post_init__``."""

    def __reduce__(self):
        return (np.array, (np.asarray(self),))


@dataclass(frozen=True)
class PatternIndex:
    """Immutable lost-in-space pattern index (build with :func:`build_index`).

    Attributes
    ----------
    options : IndexOptions
    catalog_digest : str
        SHA-256 of the catalog directions and magnitudes the index was built from.
    star_vectors : ndarray, shape (K, 3)
        Unit directions (ICRF, catalog epoch, or an observation epoch after :meth:`at_epoch`) of the
        index stars, brightest first.
    star_vmag : ndarray, shape (K,)
    catalog_rows : ndarray, shape (K,)
        Row of each index star in the catalog given to :func:`build_index`.
    patterns : ndarray, shape (P, 4)
        Index-star rows of each pattern, sorted by ``keys``.
    keys : ndarray, shape (P,) int64
        Sorted hash keys.
    ratios : ndarray, shape (P, 5)
        Sorted edge ratios of each pattern.
    max_edge_rad : ndarray, shape (P,)
        Largest edge of each pattern, rad.
    key_directory : tuple of ndarray, optional
        ``(unique_keys, bounds)``: the distinct ``keys`` and where each one's rows start, with
        ``len(keys)`` appended; derived from ``keys`` when not given (and carried by copies).
    star_zones : tuple of ndarray, optional
        ``(order, sorted_z)`` of the catalog-epoch ``star_vectors`` (:class:`StarZones`); derived on
        first use when not given (and carried by copies).

    The arrays may be memory-mapped (:meth:`load` of a cache directory).
    """

    options: IndexOptions
    catalog_digest: str
    star_vectors: np.ndarray
    star_vmag: np.ndarray
    catalog_rows: np.ndarray
    patterns: np.ndarray
    keys: np.ndarray
    ratios: np.ndarray
    max_edge_rad: np.ndarray
    key_directory: tuple[np.ndarray, np.ndarray] | None = dataclasses.field(default=None, repr=False, compare=False)
    star_zones: tuple[np.ndarray, np.ndarray] | None = dataclasses.field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in _ARRAYS:
            getattr(self, name).setflags(write=False)
        if len(self.patterns) == 0:
            raise CatalogError("pattern index holds no patterns: the catalog is too sparse for these options")
        if self.key_directory is None:
            # A lookup then searches the distinct keys once (17x fewer in the 1-degree index)
            # instead of the whole table twice, for each key's start and end.
            starts = np.flatnonzero(np.concatenate([[True], self.keys[1:] != self.keys[:-1]]))
            bounds = np.append(starts, len(self.keys)).astype(np.int64)
            object.__setattr__(self, "key_directory", (self.keys[starts], bounds))
        for array in self.key_directory:
            array.setflags(write=False)

    def __getstate__(self) -> dict:
        """Pickle the fields only: the search structures and epoch caches are derived again on use."""
        return {name: getattr(self, name) for name in _FIELDS}

    @property
    def tree(self) -> StarZones:
        """Searches ``star_vectors`` by ``query_ball_point`` (:class:`StarZones`; an :meth:`at_epoch`
        copy searches its moved directions in its source's order)."""
        tree = self.__dict__.get("_tree")
        if tree is None:
            tree = StarZones(self.star_vectors, *self.zones())
            object.__setattr__(self, "_tree", tree)
        return tree

    def zones(self) -> tuple[np.ndarray, np.ndarray]:
        """``star_zones``, derived from ``star_vectors`` on first use."""
        if self.star_zones is None:
            zones = StarZones.order_of(self.star_vectors)
            for array in zones:
                array.setflags(write=False)
            object.__setattr__(self, "star_zones", zones)
        return self.star_zones

    def at_epoch(self, catalog, *, t_tdb_s: float, r_observer_ssb_km: np.ndarray | None = None) -> PatternIndex:
        """The index with its star directions moved to an observation epoch (patterns unchanged).

        The index holds catalog-epoch directions (Hipparcos stars at 1991.25): a star of proper
        motion ``mu`` is ``mu * (t - epoch)`` from them at ``t`` (200 mas/yr over 33 years is 6.6",
        2 px of a 3.5"/px camera), enough to push the one star that would confirm a sparse
        frame's match beyond the verification radius. The copy's directions are
        ``catalog.apparent_directions`` of the index stars at ``t_tdb_s`` without aberration (the
        solution stays geometric, :class:`opnav.image.starid.PlateSolution`), with parallax from
        ``r_observer_ssb_km`` when given. Pattern keys and ratios stay those of the catalog epoch
        (recomputing them means rebuilding the index): a star that moved by ``s`` changes a ratio
        by about ``s / edge``, within the ratio tolerance (0.008) for the few arcseconds of real
        stars over decades but for the fastest stars on the short edges of a narrow field; the
        verification, which decides, uses the moved directions.

        The directions are computed as they are read (module docstring), and calls with one
        :class:`opnav.catalog.StarCatalog` share them: a star's direction computed for another epoch
        or position is reused while its motion since then is within ``EPOCH_REUSE_TOLERANCE_RAD``.
        Every direction read is within that tolerance of a computation from scratch; the zone
        search's band is widened by a bound on every star's shift since its catalog epoch.

        Parameters
        ----------
        catalog : opnav.catalog.StarCatalog
            The catalog the index was built from (checked against ``catalog_digest``).
        t_tdb_s : float
            Observation epoch, TDB s past J2000.
        r_observer_ssb_km : ndarray, shape (3,), optional
            Observer position relative to the solar-system barycentre, ICRF, km.

        Returns
        -------
        PatternIndex
            For solving; its :meth:`checksum` differs from the cached index's.

        Raises
        ------
        CatalogError
            ``catalog`` is not the one the index was built from.
        """
        if catalog_digest(catalog) != self.catalog_digest:
            raise CatalogError("at_epoch needs the catalog the index was built from (catalog digest differs)")
        t_tdb_s = float(t_tdb_s)
        if not math.isfinite(t_tdb_s):
            raise InputError(f"t_tdb_s must be finite, got {t_tdb_s}")
        r = None
        if r_observer_ssb_km is not None:
            r = np.array(r_observer_ssb_km, dtype=float).reshape(-1)
            if r.shape != (3,) or not np.all(np.isfinite(r)):
                raise InputError(f"r_observer_ssb_km must be a finite (3,) vector in km, got {r_observer_ssb_km!r}")

        def apparent(rows: np.ndarray) -> np.ndarray:
            return catalog.apparent_directions(
                rows, t_tdb_s=t_tdb_s, r_observer_ssb_km=np.zeros(3) if r is None else r,
                v_observer_ssb_km_s=np.zeros(3), parallax=r is not None, aberration=False)

        motion = self._motion(catalog)
        if motion is None or motion.epoch_tdb_s is None:
            moved = np.ascontiguousarray(apparent(self.catalog_rows), dtype=float)
            return self._moved(moved, float(np.max(np.linalg.norm(moved - self._zone_source()[0], axis=1))))
        directions = _EpochDirections(motion, t_tdb_s, r, lambda rows: apparent(self.catalog_rows[rows]))
        return self._moved(directions, motion.catalog_epoch_bound(t_tdb_s, r))

    def _motion(self, catalog) -> _StarMotion | None:
        """The motion bounds of this index's stars in ``catalog`` (kept for the last catalog object);
        None for a star source without proper motions and parallaxes."""
        motion = self.__dict__.get("_star_motion")
        if motion is not None and motion.catalog() is catalog:
            return motion
        if not all(hasattr(catalog, name) for name in ("pm_ra_cosdec_rad_yr", "pm_dec_rad_yr", "parallax_rad")):
            return None
        try:
            motion = _StarMotion(catalog, self.catalog_rows)
        except TypeError:  # no weak reference to this catalog object
            return None
        object.__setattr__(self, "_star_motion", motion)
        return motion

    def _zone_source(self) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """The directions the zones searched by :attr:`tree` were sorted from, and those zones (a moved
        copy searches its source's)."""
        return self.__dict__.get("_zone_source_of_copy") or (self.star_vectors, self.zones())

    def _moved(self, vectors: np.ndarray, max_shift: float) -> PatternIndex:
        """A copy with ``vectors``, at most ``max_shift`` (chord) from :meth:`_zone_source`'s directions."""
        source = self._zone_source()
        # the fields of this index with the new directions: dataclasses.replace would check every array again
        # (~50 us a frame), and only the directions are new (read-only: reads return copies, or set below)
        moved = object.__new__(PatternIndex)
        for name in _FIELDS:
            object.__setattr__(moved, name, getattr(self, name))
        object.__setattr__(moved, "star_vectors", vectors)
        object.__setattr__(moved, "star_zones", None)
        vectors.setflags(write=False)
        sorted_points = self.__dict__.get("_zone_sorted_points")
        if sorted_points is None:  # one for the source and every copy of it, filled as bands are searched
            sorted_points = SortedChunks(source[0], source[1][0])
            object.__setattr__(self, "_zone_sorted_points", sorted_points)
        object.__setattr__(moved, "_zone_sorted_points", sorted_points)
        object.__setattr__(moved, "_tree", StarZones(vectors, *source[1], max_shift, unmoved=source[0],
                                                     sorted_points=sorted_points))
        object.__setattr__(moved, "_zone_source_of_copy", source)
        return moved

    def checksum(self) -> str:
        """SHA-256 hex digest of the options, catalog digest and every array (dtype, shape, bytes)."""
        digest = hashlib.sha256()
        digest.update(json.dumps(dataclasses.asdict(self.options), sort_keys=True).encode())
        digest.update(self.catalog_digest.encode())
        for name in _ARRAYS:
            array = np.ascontiguousarray(getattr(self, name))
            digest.update(f"{name}:{array.dtype.str}:{array.shape}".encode())
            digest.update(memoryview(array).cast("B"))
        return digest.hexdigest()

    def save(self, path: str | os.PathLike) -> None:
        """Write the index: a path ending in ``.npz`` gets one portable file (checksum verified on every
        load), any other a directory of memory-mapped arrays (:mod:`opnav.image.starid_store`)."""
        from . import starid_store

        if str(path).endswith(".npz"):
            starid_store.write_index_npz(self, path)
        else:
            starid_store.write_index_dir(self, path)

    @classmethod
    def load(cls, path: str | os.PathLike, *, verify: bool = False) -> PatternIndex:
        """Read an index written by :meth:`save` (a directory, memory-mapped, or an ``.npz`` file).

        Parameters
        ----------
        path : str or Path
        verify : bool
            For a directory: hash every byte even when its verification marker vouches for it
            (an ``.npz`` file is always verified).

        Raises
        ------
        CatalogError
            Unreadable or truncated files, another format version, or content that does not
            match the stored checksum (a corrupt index).
        """
        from . import starid_store

        if Path(path).is_dir():
            return starid_store.load_index_dir(path, verify=verify)
        return starid_store.load_index_npz(path)


#: :func:`catalog_digest` of the catalog objects seen (read-only ``StarCatalog`` arrays: the digest
#: of one object never changes).
_DIGESTS: "weakref.WeakKeyDictionary[object, str]" = weakref.WeakKeyDictionary()


#: The :class:`PatternIndex` fields.
_FIELDS = tuple(field.name for field in dataclasses.fields(PatternIndex))


def catalog_digest(catalog: StarSource) -> str:
    """SHA-256 hex digest of a catalog's unit vectors and magnitudes (kept per ``StarCatalog`` object)."""
    kept = isinstance(catalog, _star_catalog_class())
    if kept and catalog in _DIGESTS:
        return _DIGESTS[catalog]
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(catalog.unit_vectors(), dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(catalog.vmag, dtype=np.float64).tobytes())
    text = digest.hexdigest()
    if kept:
        _DIGESTS[catalog] = text
    return text


_STAR_CATALOG = None


def _star_catalog_class() -> type:
    """``opnav.catalog.StarCatalog``, imported on first use (an import statement in a function called once a
    frame cost ~20 us)."""
    global _STAR_CATALOG
    if _STAR_CATALOG is None:
        from ..catalog import StarCatalog

        _STAR_CATALOG = StarCatalog
    return _STAR_CATALOG


def build_index(
    catalog: StarSource,
    *,
    fov_min_deg: float,
    fov_max_deg: float,
    vmag_limit: float,
    pattern_stars_per_fov: int = 10,
    verification_stars_per_fov: int = 30,
    pattern_bins: int = 50,
    pattern_size_fraction: float = 0.7,
    level_ratio: float = 1.4,
    selection: str = "density",
    field_oversampling: float = 3.0,
    sparse_spacing_fraction: float = 0.0,
    progress: Callable[[str, int, int], None] | None = None,
) -> PatternIndex:
    """Build a lost-in-space pattern index from a star catalog (module docstring, steps 1-4).

    Parameters
    ----------
    catalog : StarSource
        Anything with ``unit_vectors()`` (N, 3) ICRF and ``vmag`` (N,), e.g.
        ``opnav.catalog.StarCatalog``.
    fov_min_deg, fov_max_deg, vmag_limit, pattern_stars_per_fov, verification_stars_per_fov,
    pattern_bins, pattern_size_fraction, level_ratio, selection, field_oversampling, sparse_spacing_fraction
        See :class:`IndexOptions`.
    progress : callable, optional
        Called as ``progress(stage, done, total)`` while the levels are built.

    Returns
    -------
    PatternIndex

    Raises
    ------
    InputError
        Bad options.
    CatalogError
        The catalog has no usable stars or yields no patterns.
    """
    options = IndexOptions(
        fov_min_deg=fov_min_deg,
        fov_max_deg=fov_max_deg,
        vmag_limit=vmag_limit,
        pattern_stars_per_fov=pattern_stars_per_fov,
        verification_stars_per_fov=verification_stars_per_fov,
        pattern_bins=pattern_bins,
        pattern_size_fraction=pattern_size_fraction,
        level_ratio=level_ratio,
        selection=selection,
        field_oversampling=field_oversampling,
        sparse_spacing_fraction=sparse_spacing_fraction,
    )
    vectors = np.asarray(catalog.unit_vectors(), dtype=float)
    vmag = np.asarray(catalog.vmag, dtype=float)
    if vectors.ndim != 2 or vectors.shape[1] != 3 or len(vmag) != len(vectors):
        raise CatalogError(f"catalog unit_vectors() {vectors.shape} and vmag {vmag.shape} do not match")
    usable = np.flatnonzero(np.isfinite(vmag) & (vmag <= vmag_limit) & np.all(np.isfinite(vectors), axis=1))
    if len(usable) < 4:
        raise CatalogError(f"catalog has {len(usable)} stars brighter than vmag {vmag_limit}; need at least 4")
    rows = usable[np.argsort(vmag[usable], kind="stable")]
    candidates = vectors[rows]

    levels = options.level_fovs_rad()
    keep = _brightest_nearby(candidates, levels[0] / 2.0, verification_stars_per_fov)
    all_patterns = []
    if sparse_spacing_fraction > 0.0:
        fov_max = math.radians(fov_max_deg)
        sparse = np.flatnonzero(_brightest_nearby(candidates, sparse_spacing_fraction * fov_max, 1))
        keep[sparse] = True
        sparse_local = sparse[_level_patterns(candidates[sparse], fov_max)]
        log.info("index sparse level: %d stars, %d patterns", len(sparse), len(sparse_local))
    if selection == "fields":
        tree = cKDTree(candidates)
        for k, fov in enumerate(levels):
            def report(done: int, total: int, k: int = k) -> None:
                if progress is not None:
                    progress(f"level {k + 1}/{len(levels)} ({math.degrees(fov):.2f} deg) fields", done, total)

            local = _field_patterns(candidates, tree, 0.5 * pattern_size_fraction * fov, pattern_stars_per_fov,
                                    field_oversampling, report)
            all_patterns.append(local)
            keep[np.unique(local)] = True
            log.info("index level %.2f deg: %d patterns", math.degrees(fov), len(local))
        index_of_candidate = (np.cumsum(keep) - 1).astype(np.int32)
        all_patterns = [index_of_candidate[local] for local in all_patterns]
    else:
        level_members = []
        for fov in levels:
            members = np.flatnonzero(_brightest_nearby(candidates, fov / 2.0, pattern_stars_per_fov))
            keep[members] = True
            level_members.append(members)
        index_of_candidate = (np.cumsum(keep) - 1).astype(np.int32)
        for k, (fov, members) in enumerate(zip(levels, level_members)):
            local = _level_patterns(candidates[members], pattern_size_fraction * fov)
            all_patterns.append(index_of_candidate[members[local]])
            log.info("index level %.2f deg: %d pattern stars, %d patterns", math.degrees(fov), len(members), len(local))
            if progress is not None:
                progress("levels", k + 1, len(levels))
    if sparse_spacing_fraction > 0.0:
        all_patterns.append(index_of_candidate[sparse_local])
    star_vectors = candidates[keep]
    patterns = np.concatenate(all_patterns)
    del all_patterns
    patterns.sort(axis=1)
    patterns = _unique_rows(patterns)
    if len(patterns) == 0:
        raise CatalogError(f"catalog yields no 4-star patterns for fov {fov_min_deg}-{fov_max_deg} deg, vmag <= {vmag_limit}")
    ratios = np.empty((len(patterns), 5), np.float32)
    max_edge = np.empty(len(patterns), np.float32)
    keys = np.empty(len(patterns), np.int64)
    for lo in range(0, len(patterns), 1_000_000):
        block = slice(lo, lo + 1_000_000)
        block_ratios, block_edge = pattern_ratios(pair_angles(star_vectors[patterns[block]], EDGE_FIRST, EDGE_SECOND))
        ratios[block], max_edge[block] = block_ratios, block_edge
        keys[block] = pattern_keys(np.minimum(np.floor(block_ratios * pattern_bins), pattern_bins - 1), pattern_bins)
    order = np.argsort(keys, kind="stable")
    # one array reordered at a time: each old copy is freed before the next is made
    patterns = patterns[order]
    keys = keys[order]
    ratios = ratios[order]
    max_edge = max_edge[order]
    return PatternIndex(
        options=options,
        catalog_digest=catalog_digest(catalog),
        star_vectors=star_vectors,
        star_vmag=vmag[rows][keep],
        catalog_rows=rows[keep].astype(np.int64),
        patterns=patterns,
        keys=keys,
        ratios=ratios,
        max_edge_rad=max_edge,
    )


def vmag_limit_for_density(vmag: np.ndarray, fov_min_deg: float, *, stars_per_fov: float = 50.0) -> float:
    """Magnitude limit that leaves ``stars_per_fov`` stars in a ``fov_min_deg`` square field, on sky average.

    A deeper catalog only slows the index build (the per-field thinning caps the star count);
    a shallower one leaves sparse fields without patterns.
    """
    if not (fov_min_deg > 0.0 and stars_per_fov > 0.0):
        raise InputError(f"fov_min_deg and stars_per_fov must be positive, got {fov_min_deg}, {stars_per_fov}")
    ordered = np.sort(np.asarray(vmag, dtype=float))
    if len(ordered) == 0:
        raise CatalogError("catalog is empty")
    wanted = int(SKY_DEG2 * stars_per_fov / fov_min_deg**2)
    return float(ordered[min(wanted, len(ordered) - 1)])


def index_cache_path(catalog: StarSource, options: IndexOptions, cache_dir: str | os.PathLike | None = None) -> Path:
    """Cache directory of the index for ``catalog`` and ``options`` (see :func:`load_or_build_index`)."""
    text = json.dumps({"format": FORMAT_VERSION, "catalog": catalog_digest(catalog), **dataclasses.asdict(options)},
                      sort_keys=True)
    directory = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    return directory / f"starid-{hashlib.sha256(text.encode()).hexdigest()[:20]}"


def _legacy_cache_file(path: Path) -> Path:
    """The single-file ``.npz`` cache entry earlier versions wrote for the directory ``path``."""
    return path.with_name(path.name + ".npz")


def _check_cache_folder(folder: Path, given: bool) -> None:
    """Refuse a cache folder that cannot be created or written, before a build of seconds to minutes
    whose save would then fail (``OPNAV_CACHE`` under a file, in a read-only place, ...)."""
    import tempfile

    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-test-"):
            pass
    except OSError as exc:
        source = ("--cache-dir" if given else "OPNAV_CACHE" if os.environ.get("OPNAV_CACHE")
                  else "the pattern-index cache folder (from XDG_CACHE_HOME or HOME)")
        raise InputError(f"{source} {folder} cannot be written ({exc.strerror or exc}); give a writable folder "
                         "(OPNAV_CACHE or --cache-dir)") from None


def load_or_build_index(
    catalog: StarSource,
    *,
    cache_dir: str | os.PathLike | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    **options,
) -> PatternIndex:
    """The index for ``catalog`` and ``options`` (keywords of :func:`build_index`), cached on disk.

    The cache entry (:func:`index_cache_path`, a directory of memory-mapped arrays,
    :mod:`opnav.image.starid_store`) carries a digest of the catalog content and the options in
    its name. A missing, unreadable or corrupt entry is rebuilt; a ``.npz`` file left by an
    earlier version is read once (checksum verified), written in the current layout and removed.
    Writes go through a temporary directory and a rename. ``progress`` is passed to
    :func:`build_index` when a build is needed.
    """
    resolved = IndexOptions(**options)
    path = index_cache_path(catalog, resolved, cache_dir)
    if path.exists():
        try:
            return PatternIndex.load(path)
        except CatalogError as exc:
            log.warning("rebuilding pattern index: %s", exc)
    legacy = _legacy_cache_file(path)
    if legacy.is_file():
        try:
            index = PatternIndex.load(legacy)
        except CatalogError as exc:
            log.warning("rebuilding pattern index: %s", exc)
        else:
            started = time.perf_counter()
            index.save(path)
            legacy.unlink(missing_ok=True)
            log.info("pattern index %s converted to memory-mapped arrays in %s (%.1f s)", legacy.name, path.name,
                     time.perf_counter() - started)
            return PatternIndex.load(path)
    _check_cache_folder(path.parent, cache_dir is not None)
    started = time.perf_counter()
    with returning_freed_memory():  # the build's freed arrays must not stay on the heap
        index = build_index(catalog, progress=progress, **dataclasses.asdict(resolved))
    log.info("pattern index built in %.1f s: %d patterns -> %s", time.perf_counter() - started, len(index.patterns), path)
    index.save(path)
    legacy.unlink(missing_ok=True)
    return PatternIndex.load(path)


# --- which index for which field of view --------------------------------------------------------

#: Without a field-of-view guess, the index covers horizontal fields of view in this range, deg.
DEFAULT_FOV_RANGE_DEG = (10.0, 45.0)
#: The smallest index level is this fraction of the smallest FOV searched: a frame then holds
#: patterns of a denser level too, which makes sparse or cluttered fields solvable.
LEVEL_MARGIN = 0.6
#: Below this horizontal FOV, deg, the index is built from lattice fields (``selection="fields"``).
NARROW_FOV_DEG = 4.0
#: Smallest level of a narrow index as a fraction of the smallest FOV searched.
NARROW_LEVEL_MARGIN = 0.75
#: Brightest stars of each lattice field that form patterns in a narrow index.
NARROW_STARS_PER_FIELD = 8
#: Lattice-field diameter of a narrow index as a fraction of each level's FOV. A field as wide
#: as the level's frame holds the frame's brightest stars even when they sit near its edges
#: (0.7 left 19 of the 60 ``make demo`` frames with no 4 of their stars in one field).
NARROW_PATTERN_SIZE_FRACTION = 1.0
#: Sparse level of an index for a given field of view wider than ``NARROW_FOV_DEG`` (:class:`IndexOptions`):
#: local brightness maxima about this fraction of the largest FOV apart form patterns as large as
#: the frame. 0.18 (1.2 deg for a 6.1 deg field) held a pattern of 2 in 3 of the 6.1 x 4.6 deg
#: frames of 5-9 stars that the levels miss, for 45 % more patterns; 0.16 (1.07 deg) also holds
#: the frames whose fainter stars have a brighter neighbour just beyond the frame's edge (2 of
#: 100 JPEG q70 frames of ``benchmarks/starid_real.py``'s 6.1-degree camera), for 56 % more again
#: (10.7 million patterns for that camera).
SPARSE_SPACING_FRACTION = 0.16


def index_options_for_fov(catalog: StarSource, fov_deg: float, fov_tolerance: float) -> dict:
    """Keywords of :func:`load_or_build_index` for a horizontal FOV guess ``fov_deg`` +- ``fov_tolerance``.

    Fields narrower than ``NARROW_FOV_DEG`` get a ``"fields"`` index (patterns from the brightest
    stars of lattice fields, bounded in size however deep the catalog; module docstring, step 3)
    with levels from ``NARROW_LEVEL_MARGIN`` of the smallest FOV; wider ones a ``"density"`` index
    from ``LEVEL_MARGIN`` of it, with a sparse level (``SPARSE_SPACING_FRACTION``).
    """
    low, high = fov_deg * (1.0 - fov_tolerance), fov_deg * (1.0 + fov_tolerance)
    if fov_deg < NARROW_FOV_DEG:
        fov_min = NARROW_LEVEL_MARGIN * low
        return dict(fov_min_deg=fov_min, fov_max_deg=high, vmag_limit=vmag_limit_for_density(catalog.vmag, fov_min),
                    selection="fields", pattern_stars_per_fov=NARROW_STARS_PER_FIELD,
                    pattern_size_fraction=NARROW_PATTERN_SIZE_FRACTION)
    fov_min = LEVEL_MARGIN * low
    return dict(fov_min_deg=fov_min, fov_max_deg=high, vmag_limit=vmag_limit_for_density(catalog.vmag, fov_min),
                sparse_spacing_fraction=SPARSE_SPACING_FRACTION)


#: Field-of-view guesses taken from a frame (its WCS) are snapped to this many steps per decade
#: (:func:`snap_fov_deg`), so the frames of one camera share one index.
FOV_STEPS_PER_DECADE = 100


def snap_fov_deg(fov_deg: float) -> float:
    """``fov_deg`` on a geometric grid of ``FOV_STEPS_PER_DECADE`` steps a decade (within 1.2 %), rounded to 6 digits.

    The index options depend on the field of view, so every WCS's slightly different pixel scale
    would otherwise build (30-50 s) and cache (700 MB at 1 degree) an index of its own. The frame
    is still solved with its own field of view (the index serves +- the tolerance around the
    snapped one, 10 % by default, and the levels reach a quarter below it): 0.99996 deg gives the
    index of ``--fov 1``.
    """
    if not (math.isfinite(fov_deg) and fov_deg > 0.0):
        raise InputError(f"fov_deg must be positive, got {fov_deg!r}")
    step = round(math.log10(fov_deg) * FOV_STEPS_PER_DECADE)
    return float(f"{10.0 ** (step / FOV_STEPS_PER_DECADE):.6g}")


def _cache_entry_options(path: Path) -> tuple[dict, str]:
    """``(options, catalog digest)`` of a cache entry (directory or earlier ``.npz``), its small parts only."""
    from . import starid_store

    if path.is_dir():
        manifest = starid_store.read_manifest(path)
        return manifest["options"], str(manifest["catalog_digest"])
    version, options, digest = starid_store.read_npz_options(path)
    if version != FORMAT_VERSION:
        raise CatalogError(f"pattern index {path}: format {version}, expected {FORMAT_VERSION}")
    return options, digest


def cached_narrow_indexes(catalog: StarSource, cache_dir: str | os.PathLike | None = None) -> list[tuple[float, float, str]]:
    """``(fov low, fov high, path)`` of the narrow (``"fields"``) indexes cached for ``catalog``, narrowest first.

    Only indexes built with this version's narrow options (``NARROW_STARS_PER_FIELD``,
    ``NARROW_PATTERN_SIZE_FRACTION``) are offered: one left in the cache by an earlier version
    covers fewer frames and would only cost a failed search before the current one. Only each
    entry's manifest (or an earlier ``.npz`` file's small entries) is read here; an entry that
    cannot be read is skipped (it is rebuilt when its FOV is asked for).
    """
    directory = default_cache_dir() if cache_dir is None else Path(cache_dir)
    digest = catalog_digest(catalog)
    current = {"selection": "fields", "pattern_stars_per_fov": NARROW_STARS_PER_FIELD,
               "pattern_size_fraction": NARROW_PATTERN_SIZE_FRACTION}
    found = {}
    for path in sorted(directory.glob("starid-*")):
        if path.name.endswith(".npz") and path.with_suffix("").is_dir():
            continue  # converted already
        try:
            options, entry_digest = _cache_entry_options(path)
        except Exception:  # noqa: BLE001 - any unreadable cache entry is simply not offered
            continue
        if entry_digest != digest or any(options.get(key) != value for key, value in current.items()):
            continue
        found[path.name.removesuffix(".npz")] = (options["fov_min_deg"] / NARROW_LEVEL_MARGIN, options["fov_max_deg"],
                                                 str(path))
    return sorted(found.values())


@dataclass(frozen=True)
class IndexChoice:
    """One index a lost-in-space search tries (:func:`choose_indexes`).

    Attributes
    ----------
    fov_low_deg, fov_high_deg : float
        Horizontal fields of view it serves (the range searched with it), deg.
    options : dict or None
        Keywords of :func:`load_or_build_index` (an index built when not cached), or None for
        ``path``.
    path : str or None
        A cached index offered as it is (a narrow one built by an earlier search).
    """

    fov_low_deg: float
    fov_high_deg: float
    options: tuple = ()
    path: str | None = None

    def load(self, catalog: StarSource, cache_dir=None, progress=None) -> PatternIndex:
        """The index, built and cached when needed (:func:`load_or_build_index`)."""
        if self.path is not None:
            return load_or_convert(Path(self.path))
        return load_or_build_index(catalog, cache_dir=cache_dir, progress=progress, **dict(self.options))


def load_or_convert(path: Path) -> PatternIndex:
    """A cached index by its path; an earlier version's ``.npz`` entry is converted (and removed) first."""
    if path.is_file() and path.name.endswith(".npz"):
        target = path.with_name(path.name.removesuffix(".npz"))
        if target.is_dir():
            return PatternIndex.load(target)
        index = PatternIndex.load(path)
        index.save(target)
        path.unlink(missing_ok=True)
        log.info("pattern index %s converted to memory-mapped arrays in %s", path.name, target.name)
        return PatternIndex.load(target)
    return PatternIndex.load(path)


def choose_indexes(catalog: StarSource, *, fov_deg: float | None = None, fov_tolerance: float = 0.1,
                   cache_dir: str | os.PathLike | None = None) -> tuple[IndexChoice, ...]:
    """The indexes a lost-in-space search of a frame tries, in order.

    Parameters
    ----------
    catalog : StarSource
    fov_deg : float, optional
        Horizontal field-of-view guess, deg: one index for ``fov_deg`` +- ``fov_tolerance``
        (:func:`index_options_for_fov`). Without it, the ``DEFAULT_FOV_RANGE_DEG`` index, then every
        narrow index already cached for the catalog (:func:`cached_narrow_indexes`).
    fov_tolerance : float
        Relative uncertainty of ``fov_deg``.
    cache_dir : str or Path, optional
        Index cache (default :func:`default_cache_dir`).

    Returns
    -------
    tuple of IndexChoice
    """
    if fov_deg is not None:
        options = index_options_for_fov(catalog, fov_deg, fov_tolerance)
        return (IndexChoice(fov_deg * (1.0 - fov_tolerance), fov_deg * (1.0 + fov_tolerance), tuple(options.items())),)
    low, high = DEFAULT_FOV_RANGE_DEG
    options = dict(fov_min_deg=low, fov_max_deg=high, vmag_limit=vmag_limit_for_density(catalog.vmag, low))
    choices = [IndexChoice(low, high, tuple(options.items()))]
    choices += [IndexChoice(low_n, high_n, path=path) for low_n, high_n, path in cached_narrow_indexes(catalog, cache_dir)]
    return tuple(choices)
