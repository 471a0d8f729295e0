"""Fitted Chebyshev segments of an ephemeris kept on disk between processes (:class:`SegmentStore`).

An :class:`~opnav.ephemeris.cache.EphemerisCache` fits each segment on its first use (the exact
ephemeris at the segment's Chebyshev nodes, then a least-squares fit): a 30-day S1 run fits about
2,200 segments, 0.7 s of CPU, in every process that runs it (each ``opnav run``, each worker of
``opnav montecarlo``). A store keeps the fitted coefficients in files, so a later process reads
them instead: the same floats in the same memory order, so every result is the same to the bit.

Files
-----
``FOLDER/<hash>.npz``, one per (source, body, centre, segment length, degree), ``hash`` the
SHA-256 of ``key``, the text that names them (:func:`pair_key`). Arrays: ``key`` (that text),
``index`` (S,) int64, the segment numbers (segment ``i`` starts at ``i * L`` TDB s past J2000),
``coefficients`` (S, D + 1, 6) float64, position (km) and velocity (km/s) ICRF per segment, and
``checksum``, the SHA-256 of ``index`` and ``coefficients``' bytes.

A file is used only when (:meth:`SegmentStore.load`):

1. it reads, its ``key`` is the one asked for and its ``checksum`` is its arrays';
2. its shapes are right and every coefficient is finite;
3. its first, middle and last segments, evaluated at a point between the nodes, agree with the exact
   source within :data:`CHECK_POSITION_KM` and :data:`CHECK_VELOCITY_KM_S` (ten times the fit's own
   error: a file of another source or another model fails here).

Otherwise it is ignored; the segments are fitted again and the file replaced at the next save.
Writes (:meth:`SegmentStore.save`) are atomic (a temporary file renamed over the old one) and keep
the segments the file already holds, so processes that save at once lose nothing but, at worst,
the segments of one of them, fitted again later.

Sources the store can name (:func:`source_identity`): :class:`opnav.ephemeris.Ephemeris` over an
SPK file (DE421 by default) and the mean-element moons or a moon SPK; the identity is the files'
SHA-256 and the moons' elements. Any other source is not stored.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import logging
import os
import zipfile
from pathlib import Path

import numpy as np

_log = logging.getLogger(__name__)

#: Bumped when the fit or the file changes: older files then no longer match any key.
FORMAT = 1
#: Largest difference from the exact source a stored segment may show at its check point (the fit: < 1 cm).
CHECK_POSITION_KM = 1e-4
CHECK_VELOCITY_KM_S = 1e-8
#: Where in a segment the check evaluates (x in [-1, 1]; between the nodes of any degree).
_CHECK_X = 0.3141592653589793


@functools.lru_cache(maxsize=16)
def _file_sha256(path: str, size: int, mtime_ns: int) -> str:
    """SHA-256 of a file (cached per path, size and modification time: DE421 is 17 MB)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def file_sha256(path: Path) -> str:
    stat = os.stat(path)
    return _file_sha256(str(path), stat.st_size, stat.st_mtime_ns)


def source_identity(ephemeris) -> str | None:
    """A text naming what ``ephemeris`` computes (module notes), or None when the store cannot name it."""
    from . import Ephemeris
    from .moons import MeanElementMoons, SpkMoons
    from .planets import PlanetEphemeris

    if type(ephemeris) is not Ephemeris or type(ephemeris.planets) is not PlanetEphemeris:
        return None
    moons = ephemeris.moons
    if type(moons) is MeanElementMoons:
        moon_text = "elements " + repr(sorted(moons.elements.items()))
    elif type(moons) is SpkMoons:
        moon_text = "spk " + file_sha256(Path(moons.path))
    else:
        return None
    try:
        planets = file_sha256(ephemeris.planets.path)
    except OSError:
        return None
    return f"planets spk {planets}; moons {moon_text}"


def pair_key(source: str, body: str, center: str, length_s: float, degree: int) -> str:
    """The text that names one file of the store (module notes)."""
    return json.dumps({"format": FORMAT, "source": source, "body": body, "center": center,
                       "segment_s": float(length_s), "degree": int(degree)}, sort_keys=True)


def _checksum(index: np.ndarray, coefficients: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(index).tobytes() + np.ascontiguousarray(coefficients).tobytes()).hexdigest()


class SegmentStore:
    """Fitted segments in ``folder`` (module notes).

    Parameters
    ----------
    folder : Path
        Where the files are (created on the first save).
    """

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)

    def path(self, key: str) -> Path:
        return self.folder / f"{hashlib.sha256(key.encode()).hexdigest()[:32]}.npz"

    def _read(self, key: str, degree: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(index, coefficients) of the file of ``key`` when it reads and is whole (checks 1-2), else None."""
        path = self.path(key)
        try:
            with np.load(path, allow_pickle=False) as data:
                stored_key, checksum = str(data["key"]), str(data["checksum"])
                index, coefficients = np.asarray(data["index"]), np.asarray(data["coefficients"])
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            _log.debug("ephemeris segments %s unreadable (%s): fitted again", path, exc)
            return None
        whole = (stored_key == key and index.ndim == 1 and index.dtype == np.int64
                 and coefficients.dtype == np.float64 and coefficients.shape == (index.size, degree + 1, 6)
                 and checksum == _checksum(index, coefficients) and bool(np.all(np.isfinite(coefficients))))
        if not whole:
            _log.debug("ephemeris segments %s damaged or of another key: fitted again", path)
            return None
        return index, coefficients

    def load(self, key: str, degree: int, length_s: float, exact) -> dict[int, np.ndarray]:
        """The segments stored under ``key`` (segment number -> (D + 1, 6) coefficients), each checked
        (module notes) against ``exact(t)``, the source's (N, 6) states at epochs ``t`` (N,); empty when
        the file is missing or fails a check."""
        found = self._read(key, degree)
        if found is None or found[0].size == 0:
            return {}
        index, coefficients = found
        picks = np.unique([0, index.size // 2, index.size - 1])
        t = (index[picks] + 0.5 * (_CHECK_X + 1.0)) * length_s
        orders = np.arange(degree + 1)
        series = np.einsum("nk,nkj->nj", np.cos(orders * np.arccos(_CHECK_X))[None, :].repeat(picks.size, 0),
                           coefficients[picks])
        try:
            truth = np.asarray(exact(t), dtype=float)
        except Exception as exc:  # noqa: BLE001 - the source cannot reach them: fit them when asked
            _log.debug("ephemeris segments %s not checked (%s): fitted again", self.path(key), exc)
            return {}
        if (np.abs(series[:, :3] - truth[:, :3]).max() > CHECK_POSITION_KM
                or np.abs(series[:, 3:] - truth[:, 3:]).max() > CHECK_VELOCITY_KM_S):
            _log.debug("ephemeris segments %s disagree with their source: fitted again", self.path(key))
            return {}
        # each segment an array of its own in C order, as a fresh fit is kept (EphemerisCache): a product
        # with another memory order may round differently
        return {int(i): np.array(c, order="C") for i, c in zip(index, coefficients)}

    def save(self, key: str, degree: int, segments: dict[int, np.ndarray]) -> None:
        """Add ``segments`` (segment number -> coefficients) to the file of ``key`` (atomically, keeping the
        segments it holds); nothing when the folder cannot be written (a cache, not a result)."""
        from ..errors import InputError
        from ..files import atomic_write_bytes

        merged: dict[int, np.ndarray] = {}
        found = self._read(key, degree)
        if found is not None:
            merged.update(zip(found[0].tolist(), found[1]))
        merged.update(segments)
        index = np.array(sorted(merged), dtype=np.int64)
        coefficients = np.stack([merged[i] for i in index.tolist()]).astype(np.float64)
        buffer = io.BytesIO()
        np.savez(buffer, key=np.str_(key), index=index, coefficients=coefficients,
                 checksum=np.str_(_checksum(index, coefficients)))
        try:
            atomic_write_bytes(self.path(key), buffer.getvalue())
        except (OSError, InputError) as exc:
            _log.debug("ephemeris segments not saved in %s (%s)", self.folder, exc)


def default_store() -> SegmentStore | None:
    """The store in opnav's cache folder (:func:`opnav.files.default_cache_dir`, ``ephemeris/``); None when
    there is no cache folder."""
    from ..errors import InputError
    from ..files import default_cache_dir

    try:
        return SegmentStore(default_cache_dir() / "ephemeris")
    except InputError:
        return None
