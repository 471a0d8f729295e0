"""Star catalog: load the default catalog or a file, move stars to an epoch, cone search.

The default catalog is package data, ``opnav/data/stars.npz`` (read through
:mod:`importlib.resources`, so an installed package has it; sources, licences
and build steps in ``opnav/data/stars.README.md``, built by the repository's
``catalogs/build_catalog.py``). It merges Hipparcos-2 (reference epoch J1991.25, with
parallax and proper motion) and Gaia DR3 stars to G = 10 that Hipparcos lacks
(reference epoch J2016.0, position only, ``has_pm`` False). Positions are ICRS
(= ICRF here) at each star's own reference epoch.

Apparent direction of a star, as seen by an observer at ``r_observer_ssb_km``
moving at ``v_observer_ssb_km_s`` at TDB epoch t, step by step:

1. Space motion. A star with a positive parallax p has barycentric position
   ``r(t) = d u0 + v dt`` with ``d = 1 au / p`` and space velocity
   ``v = d (mu_a p_hat + mu_d q_hat) + rv u0``: straight-line motion, which
   includes the radial-velocity (perspective acceleration) terms. A star
   without a parallax gets the linear tangent-plane motion
   ``u0 + (mu_a p_hat + mu_d q_hat) dt``.
2. Parallax: ``r(t) - r_observer`` for stars with a positive parallax; stars
   with parallax <= 0 are at infinity.
3. Stellar aberration from the observer's SSB velocity, by
   :func:`opnav.light.aberrate`.

Light time from the stars is not applied: catalogue positions are already
astrometric (as received at the SSB at the catalogue epoch).
"""

from __future__ import annotations

import hashlib
import importlib.resources
import json
import os
import zipfile
import zlib
from dataclasses import dataclass, fields
from functools import cached_property, lru_cache
from pathlib import Path
from stat import S_ISREG

import numpy as np

from .constants import AU_KM, JULIAN_YEAR_S
from .errors import CatalogError, InputError
from .files import default_cache_dir
from .frames import radec_to_unit, unit_to_radec
from .light import aberrate

#: Environment variable naming a catalog file to use instead of the default.
CATALOG_ENV = "OPNAV_CATALOG"
#: The default catalog: a resource of the ``opnav`` package (``opnav/data/stars.npz``).
DEFAULT_CATALOG_RESOURCE = ("data", "stars.npz")
#: Values of ``StarCatalog.source``.
SOURCE_SYNTHETIC = 0
SOURCE_HIPPARCOS = 1
SOURCE_GAIA = 2
FORMAT_VERSION = 1

_DTYPES = {
    "hip": np.int64,
    "gaia_id": np.int64,
    "ra_rad": np.float64,
    "dec_rad": np.float64,
    "epoch_tdb_s": np.float64,
    "pm_ra_cosdec_rad_yr": np.float64,
    "pm_dec_rad_yr": np.float64,
    "parallax_rad": np.float64,
    "rv_km_s": np.float64,
    "vmag": np.float32,
    "source": np.uint8,
    "has_pm": np.bool_,
}

#: Array kinds accepted for a column of each kind (integer columns: any integer type with values in range).
_CASTABLE_KINDS = {"i": "iu", "u": "iu", "f": "iuf", "b": "b"}


@dataclass(frozen=True, eq=False)
class StarCatalog:
    """Star catalog as parallel arrays, one entry per star (all read-only).

    Parameters
    ----------
    hip : (N,) int64
        Hipparcos number, 0 if none.
    gaia_id : (N,) int64
        Gaia DR3 source_id, 0 if none.
    ra_rad, dec_rad : (N,) float64
        ICRS right ascension and declination at the reference epoch, rad.
    epoch_tdb_s : (N,) float64
        Reference epoch of each star, TDB s past J2000 (J1991.25 for Hipparcos,
        J2016.0 for Gaia).
    pm_ra_cosdec_rad_yr, pm_dec_rad_yr : (N,) float64
        Proper motion (RA component includes cos dec), rad per Julian year.
    parallax_rad : (N,) float64
        Parallax, rad; <= 0 means unknown (star treated at infinity).
    rv_km_s : (N,) float64
        Radial velocity, km/s; 0 when unknown.
    vmag : (N,) float32
        Johnson V magnitude.
    source : (N,) uint8
        ``SOURCE_HIPPARCOS``, ``SOURCE_GAIA`` or ``SOURCE_SYNTHETIC``.
    has_pm : (N,) bool
        False where the proper motion is unknown (stored as 0).
    """

    hip: np.ndarray
    gaia_id: np.ndarray
    ra_rad: np.ndarray
    dec_rad: np.ndarray
    epoch_tdb_s: np.ndarray
    pm_ra_cosdec_rad_yr: np.ndarray
    pm_dec_rad_yr: np.ndarray
    parallax_rad: np.ndarray
    rv_km_s: np.ndarray
    vmag: np.ndarray
    source: np.ndarray
    has_pm: np.ndarray

    def __post_init__(self) -> None:
        size = None
        for name, dtype in _DTYPES.items():
            values = np.asarray(getattr(self, name))
            if values.ndim != 1:
                raise InputError(f"StarCatalog.{name} must be 1-D, got shape {values.shape}")
            size = values.size if size is None else size
            if values.size != size:
                raise InputError(f"StarCatalog.{name} has {values.size} entries, expected {size}")
            # float -> int would truncate, complex -> float drop a part, text or int -> bool invent flags
            if values.dtype.kind not in _CASTABLE_KINDS[np.dtype(dtype).kind]:
                raise InputError(f"StarCatalog.{name} has {values.dtype} values; expected {np.dtype(dtype).name}")
            if np.issubdtype(dtype, np.integer) and values.size:
                info = np.iinfo(dtype)
                if values.min() < info.min or values.max() > info.max:
                    raise InputError(f"StarCatalog.{name} has values outside the {np.dtype(dtype).name} range")
            with np.errstate(over="ignore"):  # float64 -> float32 (vmag) overflow is caught as non-finite below
                converted = values.astype(dtype, copy=False)
            if converted.dtype.kind == "f" and not np.all(np.isfinite(converted)):
                raise InputError(f"StarCatalog.{name} contains NaN or infinite values")
            # A view marked read-only: shared (cached) catalogs cannot be altered by a caller.
            view = converted.view()
            view.flags.writeable = False
            object.__setattr__(self, name, view)
        if not np.all(np.isin(self.source, (SOURCE_SYNTHETIC, SOURCE_HIPPARCOS, SOURCE_GAIA))):
            raise InputError(f"StarCatalog.source must be {SOURCE_SYNTHETIC} (synthetic), {SOURCE_HIPPARCOS} "
                             f"(Hipparcos) or {SOURCE_GAIA} (Gaia)")

    def __len__(self) -> int:
        return int(self.hip.size)

    def subset(self, index: np.ndarray) -> StarCatalog:
        """A new catalog of the stars selected by ``index`` (integer indices or boolean mask)."""
        index = np.asarray(index)
        return StarCatalog(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    @cached_property
    def star_id(self) -> np.ndarray:
        """(N,) int64 unique star id: the HIP number, else the Gaia DR3 source_id.

        The two ranges cannot collide: HIP numbers are <= 120416 and Gaia
        source_ids are >= 2^35 (they start with a HEALPix index times 2^35).
        """
        ids = np.where(self.hip > 0, self.hip, self.gaia_id)
        ids.flags.writeable = False
        return ids

    def unit_vectors(self) -> np.ndarray:
        """(N, 3) unit vectors, ICRF, at each star's reference epoch (computed once, read-only)."""
        return self._unit_vectors

    @cached_property
    def _unit_vectors(self) -> np.ndarray:
        vectors = radec_to_unit(self.ra_rad, self.dec_rad)
        vectors.flags.writeable = False
        return vectors

    @cached_property
    def _tree(self):
        from scipy.spatial import cKDTree  # a cone search's, not every catalog user's (opnav solve)

        return cKDTree(self._unit_vectors)

    def cone(self, center_icrf: np.ndarray, radius_rad: float, *, vmag_limit: float | None = None) -> np.ndarray:
        """Indices of the stars within ``radius_rad`` of a direction, brightest first.

        Parameters
        ----------
        center_icrf : (3,) array
            Cone axis, ICRF, any non-zero length.
        radius_rad : float
            Cone half-angle, rad, in (0, pi].
        vmag_limit : float, optional
            Keep only stars with ``vmag <= vmag_limit``.

        Returns
        -------
        (M,) int64 array
            Indices into this catalog, sorted by V magnitude (ties by index).

        Notes
        -----
        Positions are those at each star's reference epoch; a star with a large
        proper motion (Barnard's star: 10.3"/yr) can have moved by minutes of
        arc since, so pad the radius when the cone edge matters. The search
        uses a k-d tree on unit vectors (built on first use) with the chord
        radius ``2 sin(radius/2)``.
        """
        center = _vector3(center_icrf, "center_icrf")
        norm = np.linalg.norm(center)
        if norm == 0.0:
            raise InputError("center_icrf must be a non-zero vector")
        radius_rad = float(radius_rad)
        if not 0.0 < radius_rad <= np.pi:
            raise InputError(f"radius_rad must be in (0, pi], got {radius_rad}")
        if vmag_limit is not None and not np.isfinite(vmag_limit):
            raise InputError(f"vmag_limit must be finite, got {vmag_limit}")
        index = np.asarray(
            self._tree.query_ball_point(center / norm, 2.0 * np.sin(0.5 * radius_rad)), dtype=np.int64
        )
        if vmag_limit is not None:
            index = index[self.vmag[index] <= vmag_limit]
        return index[np.lexsort((index, self.vmag[index]))]

    def apparent_directions(
        self,
        index: np.ndarray | None = None,
        *,
        t_tdb_s: float,
        r_observer_ssb_km: np.ndarray,
        v_observer_ssb_km_s: np.ndarray,
        proper_motion: bool = True,
        parallax: bool = True,
        aberration: bool = True,
    ) -> np.ndarray:
        """Apparent directions of stars seen by an observer (module docstring, steps 1-3).

        Parameters
        ----------
        index : (M,) int array or (N,) bool mask, optional
            Stars to compute; all stars if omitted.
        t_tdb_s : float
            Observation epoch, TDB s past J2000.
        r_observer_ssb_km : (3,) array
            Observer position relative to the SSB, ICRF, km.
        v_observer_ssb_km_s : (3,) array
            Observer velocity relative to the SSB, ICRF, km/s.
        proper_motion, parallax, aberration : bool
            Apply each correction (all on by default). ``proper_motion`` covers
            the whole space motion, radial velocity included.

        Returns
        -------
        (M, 3) array
            Apparent unit vectors from the observer, ICRF.
        """
        t_tdb_s = float(t_tdb_s)
        if not np.isfinite(t_tdb_s):
            raise InputError(f"t_tdb_s must be finite, got {t_tdb_s}")
        r_observer = _vector3(r_observer_ssb_km, "r_observer_ssb_km")
        v_observer = _vector3(v_observer_ssb_km_s, "v_observer_ssb_km_s")
        rows = self._rows(index)
        u0 = self._unit_vectors[rows]
        direction = u0.copy()
        dt_s = t_tdb_s - self.epoch_tdb_s[rows]
        if proper_motion:
            direction += self._tangential_rate_rad_yr(rows) * (dt_s / JULIAN_YEAR_S)[:, None]
        parallax_rad = self.parallax_rad[rows]
        near = parallax_rad > 0.0
        if np.any(near):
            distance_km = AU_KM / parallax_rad[near]
            # Here direction[near] is u0 + w dt, so scaling by d gives d u0 + (tangential velocity) dt.
            position_km = direction[near] * distance_km[:, None]
            if proper_motion:
                position_km += (self.rv_km_s[rows][near] * dt_s[near])[:, None] * u0[near]
            if parallax:
                position_km -= r_observer
            direction[near] = position_km
        direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
        if aberration:
            direction = aberrate(direction, v_observer)
        return direction

    def space_velocity_km_s(self, index: np.ndarray | None = None) -> np.ndarray:
        """(M, 3) star velocity relative to the SSB, ICRF, km/s, at the reference epoch.

        ``v = (1 au / parallax) (mu_a p_hat + mu_d q_hat) + rv u0``, with unknown
        radial velocities taken as 0.

        Raises
        ------
        CatalogError
            If a selected star has no positive parallax (its velocity is unknown).
        """
        rows = np.arange(len(self)) if index is None else np.arange(len(self))[np.asarray(index)]
        parallax_rad = self.parallax_rad[rows]
        unknown = parallax_rad <= 0.0
        if np.any(unknown):
            raise CatalogError(
                f"{int(unknown.sum())} selected star(s) have no positive parallax, so no space velocity "
                f"(star_id {self.star_id[rows][unknown][:5].tolist()}...)"
            )
        distance_km = AU_KM / parallax_rad
        tangential = self._tangential_rate_rad_yr(rows) * (distance_km / JULIAN_YEAR_S)[:, None]
        return tangential + self.rv_km_s[rows][:, None] * self._unit_vectors[rows]

    def _rows(self, index: np.ndarray | None) -> np.ndarray:
        """The rows an index array or mask selects (all for None); integer rows as given, without the
        catalog-long ``arange`` a mask needs (opnav solve computes a few stars at a time)."""
        if index is None:
            return np.arange(len(self))
        index = np.asarray(index)
        return index if index.dtype.kind in "iu" else np.arange(len(self))[index]

    def _tangential_rate_rad_yr(self, rows: np.ndarray) -> np.ndarray:
        """(M, 3) ``mu_a p_hat + mu_d q_hat``, rad/yr, ICRF (p_hat east, q_hat north)."""
        ra = self.ra_rad[rows]
        dec = self.dec_rad[rows]
        sin_ra, cos_ra = np.sin(ra), np.cos(ra)
        sin_dec, cos_dec = np.sin(dec), np.cos(dec)
        mu_a = self.pm_ra_cosdec_rad_yr[rows]
        mu_d = self.pm_dec_rad_yr[rows]
        return np.stack(
            [-mu_a * sin_ra - mu_d * sin_dec * cos_ra, mu_a * cos_ra - mu_d * sin_dec * sin_ra, mu_d * cos_dec],
            axis=-1,
        )


def _vector3(value: np.ndarray, name: str) -> np.ndarray:
    vector = np.asarray(value, dtype=float)
    if vector.shape != (3,):
        raise InputError(f"{name} must have shape (3,), got {vector.shape}")
    if not np.all(np.isfinite(vector)):
        raise InputError(f"{name} contains NaN or infinite values: {vector}")
    return vector


def load_catalog(path: str | Path | None = None) -> StarCatalog:
    """Load the star catalog file (read once per file version, then shared).

    Parameters
    ----------
    path : str or Path, optional
        Catalog file. Default: ``$OPNAV_CATALOG`` if set (and not empty), else
        the catalog shipped with the package (``opnav/data/stars.npz``).

    Raises
    ------
    CatalogError
        If the file is missing, unreadable, of another format version, or lacks a column.
    """
    if path is None:
        path = os.environ.get(CATALOG_ENV) or None
    if path is not None:
        return _load_file(Path(path).expanduser().resolve(),
                          f"set {CATALOG_ENV} or pass another path (the package ships a default catalog)")
    resource = importlib.resources.files("opnav").joinpath(*DEFAULT_CATALOG_RESOURCE)
    # as_file gives a real file even for a zipped package (a temporary copy, read whole before it goes)
    with importlib.resources.as_file(resource) as default_path:
        return _load_file(Path(default_path).resolve(),
                          f"the installed package lacks its default catalog; reinstall opnav, rebuild it "
                          f"with `make catalog` in a checkout, or set {CATALOG_ENV}")


def default_catalog_path() -> Path:
    """Path of the catalog shipped with the package (``opnav/data/stars.npz``).

    Valid for an ordinary (unzipped) installation or a checkout; :func:`load_catalog`
    also handles a zipped package.
    """
    return Path(str(importlib.resources.files("opnav").joinpath(*DEFAULT_CATALOG_RESOURCE)))


def _load_file(path: Path, hint: str) -> StarCatalog:
    try:
        stat = path.stat()
    except OSError:
        raise CatalogError(f"star catalog {path} not found; {hint}") from None
    if not S_ISREG(stat.st_mode):  # a folder fails to open, a FIFO never ends its read
        raise CatalogError(f"star catalog {path} is not a regular file (a folder, FIFO or device); {hint}")
    return _load_cached(path, stat.st_mtime_ns, stat.st_size)


def save_catalog(catalog: StarCatalog, path: str | Path) -> Path:
    """Write ``catalog`` as an opnav catalog file (``.npz``, format :data:`FORMAT_VERSION`) that
    :func:`load_catalog` reads, atomically; e.g. a catalog extended with stars of one's own."""
    from .files import atomic_output

    path = Path(path).expanduser()
    with atomic_output(path) as handle:
        np.savez_compressed(handle, format_version=np.int64(FORMAT_VERSION),
                            **{name: np.asarray(getattr(catalog, name), dtype) for name, dtype in _DTYPES.items()})
    return path


@lru_cache(maxsize=4)
def _load_cached(path: Path, mtime_ns: int, size: int) -> StarCatalog:
    unpacked = _unpacked_folder(path, mtime_ns, size)
    catalog = _read_unpacked(unpacked) if unpacked is not None else None
    if catalog is None:
        catalog = _read_npz(path)
        if unpacked is not None:
            _write_unpacked(catalog, unpacked, path)
    return catalog


def _read_npz(path: Path) -> StarCatalog:
    with path.open("rb") as handle:
        magic = handle.read(4)
    if magic != b"PK\x03\x04":  # every .npz is a zip archive; numpy would call other bytes "pickled data"
        raise CatalogError(f"star catalog {path} is not an opnav catalog (.npz zip archive): it starts with "
                           f"{magic!r}; build one with `make catalog`")
    try:
        with np.load(path, allow_pickle=False) as data:
            version = data["format_version"] if "format_version" in data.files else None
            # an integer scalar, compared as such (int() of an array or of text would raise or mislead)
            if version is None or version.shape != () or version.dtype.kind not in "iu" or version != FORMAT_VERSION:
                shown = None if version is None else version.tolist() if version.size <= 3 else f"{version.shape} array"
                raise CatalogError(f"star catalog {path} has format version {shown!r}, expected {FORMAT_VERSION}")
            missing = [name for name in _DTYPES if name not in data.files]
            if missing:
                raise CatalogError(f"star catalog {path} lacks column(s) {', '.join(missing)}")
            columns = {name: data[name] for name in _DTYPES}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError, RuntimeError) as exc:
        # zipfile raises zlib.error for damaged compressed members, NotImplementedError for an unknown
        # compression method or zip version, RuntimeError for an encrypted member
        raise CatalogError(f"star catalog {path} is unreadable: {' '.join(str(exc).split())}") from None
    try:
        catalog = StarCatalog(**columns)
    except InputError as exc:
        raise CatalogError(f"star catalog {path} is corrupt: {exc}") from None
    if not len(catalog):
        raise CatalogError(f"star catalog {path} has no stars; build one with `make catalog`")
    return catalog


# ----------------------------------------------------------------------------- the unpacked copy
#: Format of the unpacked copy (its folder name changes with it).
UNPACKED_VERSION = 1
#: The file whose presence says an unpacked copy is whole (written last).
_UNPACKED_DONE = "complete.json"
#: Catalog files at least this large get an unpacked copy: unpacking the default catalog (13 MB of
#: ``.npz``, 489,000 stars) took 0.1 s of every process that loaded it; a small one unpacks in no time.
UNPACK_MIN_BYTES = 4_000_000


def _cache_root() -> Path | None:
    """Where opnav caches derived files (:func:`opnav.files.default_cache_dir`); None without an absolute
    folder (the catalog is then read from its file, not copied)."""
    try:
        return default_cache_dir()
    except InputError:
        return None


def _unpacked_folder(path: Path, mtime_ns: int, size: int) -> Path | None:
    """The folder of the unpacked copy of catalog file ``path`` as it is now (its path, time stamp and size
    name it: a changed file gets a new copy), or None when there is no cache folder."""
    root = _cache_root()
    if root is None or size < UNPACK_MIN_BYTES:
        return None
    key = json.dumps({"catalog": str(path), "mtime_ns": mtime_ns, "size": size, "format": UNPACKED_VERSION})
    return root / f"catalog-{hashlib.sha256(key.encode()).hexdigest()[:20]}"


def _read_unpacked(folder: Path) -> StarCatalog | None:
    """The catalog of an unpacked copy, its columns and unit vectors memory-mapped; None when the copy is
    missing, incomplete or does not read as one (then the ``.npz`` is read and the copy written anew).

    The copy is trusted as far as its sizes, ``.npy`` headers and the catalog's own checks
    (:class:`StarCatalog`) go: it is opnav's own file, written whole or not at all."""
    try:
        if not (folder / _UNPACKED_DONE).is_file():
            return None
        columns = {name: np.asarray(np.load(folder / f"{name}.npy", mmap_mode="r", allow_pickle=False))
                   for name in (*_DTYPES, "unit_vectors")}
        vectors = columns.pop("unit_vectors")
        if any(columns[name].dtype != np.dtype(dtype) for name, dtype in _DTYPES.items()) \
                or vectors.shape != (len(columns["hip"]), 3) or vectors.dtype != np.float64:
            return None
        catalog = StarCatalog(**columns)
    except (OSError, ValueError, InputError):
        return None
    vectors.flags.writeable = False
    catalog.__dict__["_unit_vectors"] = vectors  # the cached_property's value, computed when the copy was written
    return catalog


def _write_unpacked(catalog: StarCatalog, folder: Path, source: Path) -> None:
    """Write the unpacked copy of ``catalog``, read from ``source`` (its columns and unit vectors as ``.npy``
    files, then the file that says it is whole), and remove the copies of earlier versions of ``source`` and
    of catalog files that no longer exist; a cache that cannot be written is left alone (the ``.npz`` is
    read next time)."""
    import shutil

    from .files import atomic_output

    for done in folder.parent.glob(f"catalog-*/{_UNPACKED_DONE}"):
        try:
            of = json.loads(done.read_text()).get("catalog")
            # an earlier version of this file, or a file that is gone (a removed checkout): no process reads
            # it again (one still reading it keeps its mapping)
            if done.parent != folder and (of == str(source) or not Path(of).exists()):
                shutil.rmtree(done.parent, ignore_errors=True)
        except (OSError, ValueError, AttributeError, TypeError):
            continue
    try:
        folder.mkdir(parents=True, exist_ok=True)
        arrays = {name: getattr(catalog, name) for name in _DTYPES}
        arrays["unit_vectors"] = catalog.unit_vectors()
        for name, values in arrays.items():
            with atomic_output(folder / f"{name}.npy") as handle:
                np.save(handle, np.ascontiguousarray(values), allow_pickle=False)
        with atomic_output(folder / _UNPACKED_DONE) as handle:
            handle.write(json.dumps({"catalog": str(source), "stars": len(catalog), "format": UNPACKED_VERSION}).encode())
    except (OSError, InputError):
        return


def synthetic_catalog(
    n: int,
    *,
    rng: np.random.Generator,
    vmag_range: tuple[float, float] = (2.0, 8.0),
    epoch_tdb_s: float = 0.0,
    centre_icrf: np.ndarray | None = None,
    radius_rad: float | None = None,
) -> StarCatalog:
    """A catalog of ``n`` stars uniform on the sphere, for tests of other modules.

    With ``centre_icrf`` (unit vector, ICRF) and ``radius_rad`` the stars are
    uniform over that spherical cap instead (a dense field for a narrow camera).
    Magnitudes are uniform in ``vmag_range``; proper motions, parallaxes and
    radial velocities are zero (``has_pm`` True: the motion is known to be
    zero), every star has reference epoch ``epoch_tdb_s`` (TDB s past J2000)
    and ``hip = 1..n`` so ``star_id`` is unique.
    """
    if not isinstance(rng, np.random.Generator):
        raise InputError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    if int(n) != n or n < 0:
        raise InputError(f"n must be a non-negative integer, got {n}")
    low, high = (float(v) for v in vmag_range)
    if not low <= high:
        raise InputError(f"vmag_range must be (low, high) with low <= high, got {vmag_range}")
    n = int(n)
    if (centre_icrf is None) != (radius_rad is None):
        raise InputError("give both centre_icrf and radius_rad for a cap, or neither")
    if centre_icrf is None:
        ra, dec = unit_to_radec(rng.normal(size=(n, 3)))
    else:
        centre = np.asarray(centre_icrf, dtype=float)
        if centre.shape != (3,) or not np.all(np.isfinite(centre)) or not 0.0 < radius_rad <= np.pi:
            raise InputError("centre_icrf must be a finite (3,) vector and radius_rad in (0, pi]")
        centre = centre / np.linalg.norm(centre)
        # uniform in solid angle: cos of the offset uniform in [cos r, 1]
        cos_r = 1.0 - rng.uniform(0.0, 1.0, n) * (1.0 - np.cos(radius_rad))
        phi = rng.uniform(0.0, 2.0 * np.pi, n)
        helper = np.array([0.0, 0.0, 1.0]) if abs(centre[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        e1 = np.cross(centre, helper)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(centre, e1)
        sin_r = np.sqrt(1.0 - cos_r**2)
        ra, dec = unit_to_radec(cos_r[:, None] * centre
                                + sin_r[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2))
    zeros = np.zeros(n)
    return StarCatalog(
        hip=np.arange(1, n + 1),
        gaia_id=np.zeros(n, np.int64),
        ra_rad=ra,
        dec_rad=dec,
        epoch_tdb_s=np.full(n, float(epoch_tdb_s)),
        pm_ra_cosdec_rad_yr=zeros,
        pm_dec_rad_yr=zeros,
        parallax_rad=zeros,
        rv_km_s=zeros,
        vmag=rng.uniform(low, high, n),
        source=np.full(n, SOURCE_SYNTHETIC, np.uint8),
        has_pm=np.ones(n, bool),
    )
