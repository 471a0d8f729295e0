"""Files opnav writes and reads: durable atomic outputs, and inputs that are what they claim to be.

Outputs: every file goes to a temporary file beside its target, is flushed to the disk
(``fsync``), renamed into place and the rename made durable (``fsync`` of the folder), so a
crash or a power loss leaves either the old file or the new one, never an empty or partial
one. The file gets the permissions an ordinary ``open`` would give it (``0666`` less the
process's umask), not the ``0600`` of a temporary file: results on a shared machine stay
readable by those the user's umask admits.

Inputs: :func:`check_input_file` refuses, in one line naming the file, what would hang or
exhaust memory when read: a missing path, a folder, a FIFO or device (``/dev/zero``), a file
larger than the kind of file can be.
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from pathlib import Path
from typing import BinaryIO, Iterator

from .errors import InputError


def _umask() -> int:
    """The process's umask: from ``/proc/self/status`` where Linux gives it, so no other thread ever sees
    a changed umask; else by setting it and setting it back at once."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (where the system allows a folder to be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some file systems refuse fsync on a folder; the rename stands
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_output(path: str | Path) -> Iterator[BinaryIO]:
    """A binary handle whose bytes become ``path`` when the block ends without an exception (module
    notes); the folder is created. On an exception nothing is left behind and ``path`` is untouched.

    Raises
    ------
    InputError
        ``path`` exists and is not a regular file (a folder, a device, a FIFO): outputs replace
        regular files only.
    """
    path = Path(path)
    if path.exists() and not path.is_file():
        raise InputError(f"{path} exists and is not a regular file; opnav writes its outputs into regular files only")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_folder(path.parent)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` durably and atomically (:func:`atomic_output`)."""
    with atomic_output(path) as handle:
        handle.write(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8, newlines as given) to ``path`` durably and atomically (:func:`atomic_output`)."""
    atomic_write_bytes(path, text.encode("utf-8"))


#: Largest input files opnav reads whole, by kind (bytes): far above any real file of the kind,
#: far below what would exhaust memory.
MAX_TEXT_BYTES = {"toml": 16 * 2**20, "table": 4 * 2**30}


def check_input_file(path: str | Path, what: str, max_bytes: int | None = None) -> Path:
    """``path`` as a regular file of at most ``max_bytes``; else ``InputError`` naming it and ``what`` it
    should be (a missing path, a folder, a FIFO, socket or device, a file too large).

    Parameters
    ----------
    path : str or Path
    what : str
        What the file should be, for the message (``"run file"``, ``"measurement file"``).
    max_bytes : int, optional
        Largest size accepted.
    """
    path = Path(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        raise InputError(f"{what} not found: {path}") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    if stat.S_ISDIR(info.st_mode):
        raise InputError(f"{path} is a folder; give a {what}")
    if not stat.S_ISREG(info.st_mode):
        raise InputError(f"{path} is not a regular file (a FIFO, socket or device); give a {what}")
    if max_bytes is not None and info.st_size > max_bytes:
        raise InputError(f"{path}: {info.st_size:,} bytes is too large for a {what} (at most {max_bytes:,})")
    return path


#: The lock file an output folder holds while a command writes it.
LOCK_NAME = ".opnav.lock"


@contextlib.contextmanager
def folder_lock(folder: str | Path, option: str = "--out") -> Iterator[Path]:
    """Hold ``folder`` (created) for this process while the block runs: a second opnav process that asks
    for it gets InputError at once instead of mixing its files with this one's. The lock is the
    kernel's (``fcntl.flock`` on ``folder/.opnav.lock``), so it ends with the process however it ends.

    Raises
    ------
    InputError
        Another process holds ``folder`` (its pid is named when it wrote it).
    """
    import fcntl

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o666 & ~_umask())
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
            who = f" (process {holder})" if holder.isdigit() else ""
            raise InputError(f"{option} {folder} is being written by another opnav command{who}; wait for it "
                             "to end or give another folder") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield folder
    finally:
        os.close(fd)


def default_cache_dir() -> Path:
    """The folder of opnav's cached derived files (pattern indexes, the catalog's unpacked copy):
    ``$OPNAV_CACHE`` if set and not empty (an empty one is unset, as ``$OPNAV_CATALOG``), else
    ``$XDG_CACHE_HOME/opnav`` when that is an absolute path, else ``~/.cache/opnav``.

    Raises
    ------
    InputError
        None of them gives an absolute folder (``HOME`` empty or relative: the index, hundreds of MB,
        would land in the working or root folder).
    """
    value = os.environ.get("OPNAV_CACHE") or None
    if value is not None:
        return Path(value).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME") or ""
    if os.path.isabs(xdg):
        return Path(xdg) / "opnav"
    # os.path.expanduser turns an empty HOME into "/" (the index landed in /.cache); an unset one reads the
    # password database
    home = os.environ["HOME"] if "HOME" in os.environ else os.path.expanduser("~")
    if not os.path.isabs(home):
        raise InputError(f"no folder for opnav's cache (pattern indexes, the catalog's copy): HOME is {os.environ.get('HOME', '')!r}; set "
                         "OPNAV_CACHE to a writable folder (or give --cache-dir)")
    return Path(home) / ".cache" / "opnav"
