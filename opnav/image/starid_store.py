"""Pattern indexes on disk (:class:`opnav.image.starid_index.PatternIndex`): memory-mapped, verified once.

A 1-degree index holds 15 million patterns (700 MB). Read and hashed whole, it took a second or
more to load in every process; here it is opened in milliseconds and its pages are read as the
lookups touch them.

Layout (a directory, ``STORAGE_VERSION`` 1)
-------------------------------------------
``manifest.json``
    Index format version, options, catalog digest, the content checksum
    (:meth:`PatternIndex.checksum`, SHA-256 of options, digest and arrays), the checksum of the
    key directory and star zones, and the dtype, shape and byte size of each array file.
``<array>.npy``
    One uncompressed ``.npy`` per array (``STORED_ARRAYS``: the index's arrays, its key
    directory and its star zones), opened with ``numpy.load(mmap_mode="r")``.
``verified.json``
    Written after the checksums were computed from the files and matched the manifest (once,
    right after a build or a conversion): the checksum and each file's size, modification time
    and inode.

Integrity on load, cheap: the manifest parses and names this format; every file has the size
the manifest gives; every ``.npy`` header gives the manifest's dtype and shape. The checksums
are computed again only when ``verified.json`` is missing, names another checksum, or no longer
matches a file's size, time or inode (a file written, replaced or copied since) -- or when a
file's recorded time is not older than the marker itself (a write within the file system's
clock tick would leave the time unchanged; ``git``'s "racily clean" rule). Such a load verifies
and writes the marker again. Corruption that leaves a file's size, time and inode unchanged (a
failing disk) is not seen by a plain load; ``load_index_dir(path, verify=True)`` hashes every
byte.

A single ``.npz`` file (:func:`write_index_npz`) is the portable form: its checksum is verified
on every load, as it was for the cache before this layout.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import shutil
import zipfile
import zlib
from pathlib import Path

import numpy as np

from ..errors import CatalogError, InputError

log = logging.getLogger(__name__)

STORAGE_VERSION = 1
MANIFEST = "manifest.json"
VERIFIED = "verified.json"
#: Arrays of the index itself, in the order their bytes enter :meth:`PatternIndex.checksum`.
INDEX_ARRAYS = ("star_vectors", "star_vmag", "catalog_rows", "patterns", "keys", "ratios", "max_edge_rad")
#: The key directory and star zones (:class:`PatternIndex` ``key_directory``, ``star_zones``), stored so
#: a load need not scan the keys nor sort the stars.
DIRECTORY_ARRAYS = ("directory_keys", "directory_bounds", "zone_order", "zone_z")
STORED_ARRAYS = INDEX_ARRAYS + DIRECTORY_ARRAYS


def _directory_checksum(*arrays: np.ndarray) -> str:
    digest = hashlib.sha256()
    for name, array in zip(DIRECTORY_ARRAYS, arrays, strict=True):
        array = np.ascontiguousarray(array)
        digest.update(f"{name}:{array.dtype.str}:{array.shape}".encode())
        digest.update(memoryview(array).cast("B"))
    return digest.hexdigest()


def _stored_arrays(index) -> dict[str, np.ndarray]:
    arrays = {name: getattr(index, name) for name in INDEX_ARRAYS}
    arrays["directory_keys"], arrays["directory_bounds"] = index.key_directory
    arrays["zone_order"], arrays["zone_z"] = index.zones()
    return arrays


def write_index_dir(index, path: str | os.PathLike) -> None:
    """Write ``index`` as a directory at ``path`` (module docstring), verified once and marked.

    The files are written into a temporary directory beside ``path`` and renamed into place; an
    existing ``path`` is replaced.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    shutil.rmtree(temporary, ignore_errors=True)
    temporary.mkdir()
    try:
        arrays = _stored_arrays(index)
        files = {}
        for name, array in arrays.items():
            target = temporary / f"{name}.npy"
            np.save(target, np.ascontiguousarray(array), allow_pickle=False)
            files[name] = {"dtype": np.dtype(array.dtype).str, "shape": list(array.shape),
                           "bytes": target.stat().st_size}
        manifest = {
            "storage_version": STORAGE_VERSION,
            "format_version": _format_version(),
            "options": dataclasses.asdict(index.options),
            "catalog_digest": index.catalog_digest,
            "checksum": index.checksum(),
            "directory_checksum": _directory_checksum(*index.key_directory, *index.zones()),
            "arrays": files,
        }
        (temporary / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
        load_index_dir(temporary, verify=True)  # the checksums of the files as written, once
        _replace_dir(temporary, path)
    except BaseException:
        shutil.rmtree(temporary, ignore_errors=True)
        raise


def _replace_dir(source: Path, target: Path) -> None:
    """Rename ``source`` to ``target``, replacing a directory (or file) already there."""
    try:
        os.rename(source, target)
        return
    except OSError:
        if not target.exists():
            raise
    aside = target.with_name(f".{target.name}.{os.getpid()}.old")
    shutil.rmtree(aside, ignore_errors=True)
    os.rename(target, aside)
    os.rename(source, target)
    if aside.is_dir():
        shutil.rmtree(aside, ignore_errors=True)
    else:
        aside.unlink(missing_ok=True)


def _format_version() -> int:
    from .starid_index import FORMAT_VERSION

    return FORMAT_VERSION


def read_manifest(path: str | os.PathLike) -> dict:
    """The manifest of an index directory (a few hundred bytes read).

    Raises
    ------
    CatalogError
        Missing or unreadable manifest, or one of another storage or index format version.
    """
    path = Path(path)
    try:
        manifest = json.loads((path / MANIFEST).read_text())
        storage, version = int(manifest["storage_version"]), int(manifest["format_version"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CatalogError(f"cannot read pattern index {path}: {MANIFEST}: {exc}") from None
    if storage != STORAGE_VERSION or version != _format_version():
        raise CatalogError(f"pattern index {path}: storage {storage}, format {version}; expected storage "
                           f"{STORAGE_VERSION}, format {_format_version()}")
    return manifest


def _file_stats(path: Path) -> dict[str, list[int]]:
    stats = {}
    for name in (MANIFEST, *(f"{array}.npy" for array in STORED_ARRAYS)):
        st = os.stat(path / name)
        stats[name] = [st.st_size, st.st_mtime_ns, st.st_ino]
    return stats


def _marked_verified(path: Path, manifest: dict) -> bool:
    """Whether ``verified.json`` vouches for the files as they are now (module docstring)."""
    try:
        marker_path = path / VERIFIED
        marker = json.loads(marker_path.read_text())
        marked_at = os.stat(marker_path).st_mtime_ns
        recorded = marker["files"]
        if marker["checksum"] != manifest["checksum"] or recorded != _file_stats(path):
            return False
        return all(mtime < marked_at for _, mtime, _ in recorded.values())
    except (OSError, ValueError, KeyError, TypeError):
        return False


def _mark_verified(path: Path, manifest: dict) -> None:
    try:
        text = json.dumps({"checksum": manifest["checksum"], "files": _file_stats(path)}) + "\n"
        temporary = path / f".{VERIFIED}.{os.getpid()}"
        temporary.write_text(text)
        os.replace(temporary, path / VERIFIED)
    except OSError as exc:  # a read-only cache: verified again next time
        log.info("pattern index %s: cannot record its verification (%s)", path, exc)


def load_index_dir(path: str | os.PathLike, *, verify: bool = False):
    """Open an index directory written by :func:`write_index_dir`, its arrays memory-mapped.

    Parameters
    ----------
    path : str or Path
        The directory.
    verify : bool
        Hash every byte even when ``verified.json`` vouches for the files.

    Returns
    -------
    PatternIndex

    Raises
    ------
    CatalogError
        A missing or unreadable file, a file of another size, dtype or shape than the manifest
        gives, another format version, or content that does not match the checksums (corrupt).
    """
    from .starid_index import IndexOptions, PatternIndex

    path = Path(path)
    manifest = read_manifest(path)
    arrays = {}
    try:
        for name in STORED_ARRAYS:
            spec = manifest["arrays"][name]
            file = path / f"{name}.npy"
            size = file.stat().st_size
            if size != int(spec["bytes"]):
                raise CatalogError(f"pattern index {path} is corrupt: {file.name} has {size} bytes, "
                                   f"the manifest says {spec['bytes']}")
            try:
                array = np.load(file, mmap_mode="r", allow_pickle=False)
            except Exception as exc:  # noqa: BLE001 - a damaged .npy header raises SyntaxError, TokenError, ...
                raise CatalogError(f"pattern index {path} is corrupt: {file.name}: {type(exc).__name__}") from None
            if array.dtype.str != spec["dtype"] or list(array.shape) != list(spec["shape"]):
                raise CatalogError(f"pattern index {path} is corrupt: {file.name} holds {array.dtype.str} "
                                   f"{list(array.shape)}, the manifest says {spec['dtype']} {spec['shape']}")
            arrays[name] = array.view(np.ndarray)  # a plain array on the mapped pages
        index = PatternIndex(
            options=IndexOptions(**manifest["options"]),
            catalog_digest=str(manifest["catalog_digest"]),
            key_directory=(arrays.pop("directory_keys"), arrays.pop("directory_bounds")),
            star_zones=(arrays.pop("zone_order"), arrays.pop("zone_z")),
            **arrays,
        )
    except CatalogError:
        raise
    except (OSError, KeyError, ValueError, TypeError, InputError) as exc:
        raise CatalogError(f"cannot read pattern index {path}: {exc}") from None
    if verify or not _marked_verified(path, manifest):
        if index.checksum() != manifest["checksum"] or \
                _directory_checksum(*index.key_directory, *index.zones()) != manifest["directory_checksum"]:
            raise CatalogError(f"pattern index {path} is corrupt: its content does not match its checksum")
        _mark_verified(path, manifest)
        log.info("pattern index %s: checksums verified", path)
    return index


def write_index_npz(index, path: str | os.PathLike) -> None:
    """Write ``index`` to one uncompressed ``.npz`` file with its checksum (the portable form)."""
    np.savez(
        Path(path),
        format_version=np.array(_format_version()),
        options=np.array(json.dumps(dataclasses.asdict(index.options))),
        catalog_digest=np.array(index.catalog_digest),
        checksum=np.array(index.checksum()),
        **{name: getattr(index, name) for name in INDEX_ARRAYS},
    )


def read_npz_options(path: str | os.PathLike) -> tuple[int, dict, str]:
    """``(format version, options, catalog digest)`` of an ``.npz`` index, reading only those entries."""
    with np.load(Path(path)) as data:
        return int(data["format_version"]), json.loads(str(data["options"])), str(data["catalog_digest"])


def load_index_npz(path: str | os.PathLike):
    """Read an index written by :func:`write_index_npz` (or a cache file of earlier versions), checksum verified.

    Raises
    ------
    CatalogError
        Unreadable or truncated file, another format version, or content that does not match the
        stored checksum (a corrupt file).
    """
    from .starid_index import FORMAT_VERSION, IndexOptions, PatternIndex

    try:
        with np.load(Path(path)) as data:
            if int(data["format_version"]) != FORMAT_VERSION:
                raise CatalogError(f"pattern index {path}: format {int(data['format_version'])}, expected {FORMAT_VERSION}")
            index = PatternIndex(
                options=IndexOptions(**json.loads(str(data["options"]))),
                catalog_digest=str(data["catalog_digest"]),
                **{name: data[name] for name in INDEX_ARRAYS},
            )
            stored = str(data["checksum"])
    except (OSError, KeyError, ValueError, TypeError, EOFError, zipfile.BadZipFile, zlib.error, InputError) as exc:
        raise CatalogError(f"cannot read pattern index {path}: {exc}") from exc
    if index.checksum() != stored:
        raise CatalogError(f"pattern index {path} is corrupt: its content does not match its checksum")
    return index
