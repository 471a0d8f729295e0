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

The index is immutable. :meth:`PatternIndex.save` / :meth:`PatternIndex.load` use ``.npz``
with a SHA-256 checksum of the arrays, verified on load; :func:`load_or_build_index` caches it
under ``$OPNAV_CACHE`` (default ``~/.cache/opnav``), keyed by a digest of the catalog content
and the options, so a changed catalog or option builds a new index, and a file that fails its
checksum (or cannot be read) is rebuilt.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import logging
import math
import os
import sys
import time
import zipfile
import zlib
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Callable, Protocol

import numpy as np
from scipy.spatial import cKDTree

from ..allocator import returning_freed_memory
from ..errors import CatalogError, InputError

log = logging.getLogger(__name__)

FORMAT_VERSION = 3
SELECTIONS = ("density", "fields")
#: Arrays of a saved index, in the order their bytes enter its checksum.
_ARRAYS = ("star_vectors", "star_vmag", "catalog_rows", "patterns", "keys", "ratios", "max_edge_rad")
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


def _field_patterns(
    vectors: np.ndarray, tree: cKDTree, radius_rad: float, stars_per_field: int, oversampling: float,
    progress=None,
) -> np.ndarray:
    """4-sets (P, 4), rows sorted, of the brightest stars of lattice fields (module step 3, "fields").

    ``vectors`` rows are sorted brightest first, so the brightest stars of a field are its
    lowest rows.
    """
    count = max(12, int(math.ceil(oversampling * 4.0 * math.pi / (math.pi * radius_rad**2))))
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
    tree: cKDTree = field(init=False, repr=False, compare=False)
    key_directory: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("star_vectors", "star_vmag", "catalog_rows", "patterns", "keys", "ratios", "max_edge_rad"):
            getattr(self, name).setflags(write=False)
        if len(self.patterns) == 0:
            raise CatalogError("pattern index holds no patterns: the catalog is too sparse for these options")
        object.__setattr__(self, "tree", cKDTree(self.star_vectors))
        if self.key_directory is None:
            # A lookup then searches the distinct keys once (17x fewer in the 1-degree index)
            # instead of the whole table twice, for each key's start and end.
            starts = np.flatnonzero(np.concatenate([[True], self.keys[1:] != self.keys[:-1]]))
            bounds = np.append(starts, len(self.keys)).astype(np.int64)
            object.__setattr__(self, "key_directory", (self.keys[starts], bounds))
        for array in self.key_directory:
            array.setflags(write=False)

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
        moved = catalog.apparent_directions(
            self.catalog_rows, t_tdb_s=t_tdb_s,
            r_observer_ssb_km=np.zeros(3) if r_observer_ssb_km is None else r_observer_ssb_km,
            v_observer_ssb_km_s=np.zeros(3), parallax=r_observer_ssb_km is not None, aberration=False)
        return dataclasses.replace(self, star_vectors=np.ascontiguousarray(moved, dtype=float))

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
        """Write the index to an ``.npz`` file at ``path``, with its :meth:`checksum`."""
        np.savez(
            Path(path),
            format_version=np.array(FORMAT_VERSION),
            options=np.array(json.dumps(dataclasses.asdict(self.options))),
            catalog_digest=np.array(self.catalog_digest),
            checksum=np.array(self.checksum()),
            **{name: getattr(self, name) for name in _ARRAYS},
        )

    @classmethod
    def load(cls, path: str | os.PathLike) -> PatternIndex:
        """Read an index written by :meth:`save`.

        Raises
        ------
        CatalogError
            Unreadable or truncated file, another format version, or content that does not
            match the stored checksum (a corrupt file).
        """
        try:
            with np.load(Path(path)) as data:
                if int(data["format_version"]) != FORMAT_VERSION:
                    raise CatalogError(f"pattern index {path}: format {int(data['format_version'])}, expected {FORMAT_VERSION}")
                index = cls(
                    options=IndexOptions(**json.loads(str(data["options"]))),
                    catalog_digest=str(data["catalog_digest"]),
                    **{name: data[name] for name in _ARRAYS},
                )
                stored = str(data["checksum"])
        except (OSError, KeyError, ValueError, TypeError, EOFError, zipfile.BadZipFile, zlib.error, InputError) as exc:
            raise CatalogError(f"cannot read pattern index {path}: {exc}") from exc
        if index.checksum() != stored:
            raise CatalogError(f"pattern index {path} is corrupt: its content does not match its checksum")
        return index


def catalog_digest(catalog: StarSource) -> str:
    """SHA-256 hex digest of a catalog's unit vectors and magnitudes."""
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(catalog.unit_vectors(), dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(catalog.vmag, dtype=np.float64).tobytes())
    return digest.hexdigest()


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


def default_cache_dir() -> Path:
    """``$OPNAV_CACHE`` if set, else ``~/.cache/opnav``."""
    return Path(os.environ.get("OPNAV_CACHE", Path.home() / ".cache" / "opnav"))


def index_cache_path(catalog: StarSource, options: IndexOptions, cache_dir: str | os.PathLike | None = None) -> Path:
    """Cache file of the index for ``catalog`` and ``options`` (see :func:`load_or_build_index`)."""
    text = json.dumps({"format": FORMAT_VERSION, "catalog": catalog_digest(catalog), **dataclasses.asdict(options)},
                      sort_keys=True)
    directory = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    return directory / f"starid-{hashlib.sha256(text.encode()).hexdigest()[:20]}.npz"


def stderr_progress(stage: str, done: int, total: int) -> None:
    """A ``progress`` callback for :func:`build_index` writing one updating line to stderr."""
    end = "\n" if done >= total else ""
    print(f"\r  building pattern index: {stage} {100.0 * done / max(total, 1):5.1f} %", end=end, file=sys.stderr, flush=True)


def load_or_build_index(
    catalog: StarSource,
    *,
    cache_dir: str | os.PathLike | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    **options,
) -> PatternIndex:
    """The index for ``catalog`` and ``options`` (keywords of :func:`build_index`), cached on disk.

    The file name carries a digest of the catalog content and the options; a missing,
    unreadable or corrupt (checksum) file is rebuilt. Writes go through a temporary file and an
    atomic rename. ``progress`` is passed to :func:`build_index` when a build is needed.
    """
    resolved = IndexOptions(**options)
    path = index_cache_path(catalog, resolved, cache_dir)
    if path.exists():
        try:
            return PatternIndex.load(path)
        except CatalogError as exc:
            log.warning("rebuilding pattern index: %s", exc)
    started = time.perf_counter()
    with returning_freed_memory():  # the build's freed arrays must not stay on the heap
        index = build_index(catalog, progress=progress, **dataclasses.asdict(resolved))
    log.info("pattern index built in %.1f s: %d patterns -> %s", time.perf_counter() - started, len(index.patterns), path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.{os.getpid()}.npz")
    index.save(temporary)
    os.replace(temporary, path)
    return index
