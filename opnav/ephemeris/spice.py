"""An ephemeris over SPICE kernels (SPK, PCK, text kernels, meta-kernels), read with spiceypy.

:class:`SpiceEphemeris` answers as :class:`opnav.ephemeris.Ephemeris` does: ``state(body, t,
center=...)`` gives position (km) and velocity (km/s), ICRF (SPICE's ``J2000``, DE4xx's frame),
at TDB seconds past J2000, scalar or (N,) epochs (spiceypy's vectorised ``spkgeo_v``: one C loop
for all epochs). Light time and aberration are not SPICE's: the renderer and the filters apply
opnav's own (:mod:`opnav.light`) to these geometric states, the same code as through DE421.

Kernel pool discipline, step by step
------------------------------------
CSPICE keeps one kernel pool per process, so two sets of kernels cannot be loaded side by side.

1. A :class:`KernelSet` holds its files in load order (a meta-kernel expanded into its files) and a
   token of its own.
2. Every query runs inside :meth:`KernelSet.loaded`, under a process-wide lock: when the pool
   holds another set's files (the pool remembers the token of the set it loaded and the number of
   files), it is cleared (``kclear``) and this set's files are loaded (``furnsh``) in order; later
   files take priority, as in SPICE.
3. So instances never see each other's kernels, a test's kernels never leak into the next test,
   and code that calls spiceypy itself does so inside ``with kernels.loaded():``.

A worker process gets the set by pickling its file names and loads them on first use.

Errors
------
Every kernel problem ends in one :class:`KernelError` line naming the kernel and the body, frame or
epoch: a missing file, a file of the wrong type (a text file named ``.bsp``, a file with no SPICE
ID word), a body the kernels do not cover at an epoch, a frame they do not define, a constant (radii)
they lack. CSPICE's own multi-line message never reaches the user.

Body names
----------
opnav's names keep their meaning (:data:`opnav.ephemeris.planets.NAIF_ID`: ``jupiter`` is the
Jupiter system barycentre, 5, as in DE421; ``phobos`` 401, ``deimos`` 402); any other name goes
through SPICE's name table (built-in names and ``NAIF_BODY_NAME`` of loaded text kernels), and a
NAIF id may be given as an integer or as its text (``"-77"``).
"""

from __future__ import annotations

import contextlib
import itertools
import re
import threading
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from ..epochs import describe_epoch
from ..errors import EphemerisError, InputError
from .cache import EphemerisCache
from .moons import MOON_NAIF_ID
from .planets import NAIF_ID


class KernelError(InputError, EphemerisError):
    """A SPICE kernel is missing, of the wrong type, or cannot answer (body, frame, epoch)."""


#: File suffixes NAIF's conventions give each kernel type: (architecture, type) as ``getfat`` reads them.
SUFFIX_TYPES = {
    ".bsp": ("DAF", "SPK"), ".bpc": ("DAF", "PCK"), ".bc": ("DAF", "CK"), ".bds": ("DAS", "DSK"),
    ".tpc": ("KPL", "PCK"), ".tm": ("KPL", "MK"), ".tls": ("KPL", "LSK"), ".tf": ("KPL", "FK"),
    ".ti": ("KPL", "IK"), ".tsc": ("KPL", "SCLK"),
}

#: The frame of every state opnav asks SPICE for: ICRF, which SPICE calls J2000.
ICRF = "J2000"

POOL_LOCK = threading.RLock()
_POOL = {"owner": None, "count": -1}  # the token of the set the pool holds, and its ktotal("ALL")
_TOKENS = itertools.count()
_OPNAV_IDS = {**NAIF_ID, **MOON_NAIF_ID}
_OPNAV_NAMES = {naif: name for name, naif in _OPNAV_IDS.items()}


def spiceypy_module():
    """spiceypy, imported on first use (``opnav --help`` never loads CSPICE)."""
    import spiceypy

    return spiceypy


def _cyice():
    import spiceypy.cyice

    return spiceypy.cyice


def spice_error_type():
    """spiceypy's base exception class (every CSPICE error and spiceypy's not-found errors)."""
    from spiceypy.utils.exceptions import SpiceyError

    return SpiceyError


def spice_message(exc: BaseException) -> str:
    """CSPICE's short error name and the first sentence of its long message, on one line."""
    short = getattr(exc, "short", "") or type(exc).__name__
    long = " ".join(str(getattr(exc, "long", "") or "").split())
    first = re.split(r"(?<=\.)\s", long, maxsplit=1)[0] if long else ""
    return f"{short}: {first}" if first else short


def kernel_type(path: Path) -> tuple[str, str]:
    """``(architecture, type)`` of a kernel file from its ID word (``("DAF", "SPK")``, ``("KPL", "MK")``),
    checked against its suffix; ``KernelError`` for a missing file or a mismatch.

    A text file without an ID word is accepted as a text kernel only if it has a ``\\begindata``
    marker (old text kernels lack the ID word); anything else is not a SPICE kernel.
    """
    try:
        found, exists = path.is_file(), path.exists()
    except (OSError, ValueError):  # a name too long, a NUL byte
        found = exists = False
    if not found:
        text = str(path)
        name = f"{text[:80]}...{text[-40:]}" if len(text) > 200 else repr(text) if "\0" in text else text
        raise KernelError(f"kernel {name} is not a file" if exists else f"kernel {name} not found")
    try:
        arch, kind = spiceypy_module().getfat(str(path))
    except spice_error_type() as exc:
        raise KernelError(f"kernel {path} cannot be read: {spice_message(exc)}") from None
    if arch == "?":
        try:
            text = path.read_bytes()[:1_000_000]
        except OSError as exc:
            raise KernelError(f"kernel {path} cannot be read: {exc.strerror}") from None
        if b"\\begindata" not in text:
            raise KernelError(f"kernel {path} is not a SPICE kernel: it has no ID word (DAF/SPK, KPL/PCK, KPL/MK, ...)"
                              " and no \\begindata")
        arch, kind = "KPL", "?"
    if arch == "DAF":
        _check_daf_length(path)
    expected = SUFFIX_TYPES.get(path.suffix.lower())
    if expected is not None and (arch, kind) != expected and not (arch == expected[0] == "KPL" and kind == "?"):
        what = "a text kernel" if arch == "KPL" else f"a {arch}/{kind} file"
        raise KernelError(f"kernel {path} is {what} ({arch}/{kind}), but a {path.suffix} file must be "
                          f"{expected[0]}/{expected[1]}")
    return arch, kind


def _check_daf_length(path: Path) -> None:
    """Refuse a binary kernel cut short: its file record's first free address must lie within the file
    (CSPICE loads a truncated DAF and fails only when a state falls in the missing part)."""
    sp = spiceypy_module()
    with POOL_LOCK:
        try:
            handle = sp.dafopr(str(path))
            try:
                free = sp.dafrfr(handle)[5]
            finally:
                sp.dafcls(handle)
        except spice_error_type() as exc:
            raise KernelError(f"kernel {path} cannot be read: {spice_message(exc)}") from None
    needed, size = (int(free) - 1) * 8, path.stat().st_size
    if size < needed:
        raise KernelError(f"kernel {path} is cut short: its records run to byte {needed:,}, the file has {size:,}")


def expand_kernels(paths: Sequence[str | Path]) -> tuple[Path, ...]:
    """The kernel files of ``paths`` in load order, each meta-kernel replaced by the files it lists.

    A meta-kernel's ``KERNELS_TO_LOAD`` may use ``PATH_SYMBOLS``/``PATH_VALUES`` (``$SYMBOL``) and
    ``+`` continuation; a relative path in it is taken from the meta-kernel's folder (SPICE itself
    takes it from the working directory, which would make a scene depend on where it is run).
    """
    return tuple(path for path, _ in _typed_kernels(paths, ()))


def _typed_kernels(paths: Sequence[str | Path], within: tuple[Path, ...]) -> list[tuple[Path, tuple[str, str]]]:
    """``(file, (architecture, type))`` of :func:`expand_kernels`; ``within``: the meta-kernels being read."""
    found = []
    for given in paths:
        path = Path(given).expanduser()
        kind = kernel_type(path)
        if kind == ("KPL", "MK"):
            if path.resolve() in within:
                raise KernelError(f"meta-kernel {path} lists itself (through {', '.join(p.name for p in within)})")
            found.extend(_typed_kernels(_meta_kernel_files(path), within + (path.resolve(),)))
        else:
            found.append((path.resolve(), kind))
    return found


#: The longest string a text kernel's data may hold; SPICE cuts a longer one short without a word (a
#: path cut to its first 80 characters then reads as a missing file).
POOL_STRING_MAX = 80


def pool_string(text: str) -> str:
    """``text`` as a text kernel's string value: quoted (a quote doubled), split with ``+`` continuation into
    pieces SPICE keeps whole (:data:`POOL_STRING_MAX`), one a line, for writing a meta-kernel's long paths."""
    pieces, piece = [], ""
    for char in str(text):
        quoted = char.replace("'", "''")
        if len(piece) + len(quoted) > POOL_STRING_MAX - 1:  # room for the piece's '+'
            pieces.append(piece)
            piece = ""
        piece += quoted
    pieces.append(piece)
    return "\n".join([f"'{p}+'" for p in pieces[:-1]] + [f"'{pieces[-1]}'"])


def _check_string_lengths(path: Path) -> None:
    """One line naming the meta-kernel and the string when a quoted value in its data sections is longer
    than :data:`POOL_STRING_MAX` (SPICE's ``+`` continuation splits a long path over several strings)."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise KernelError(f"meta-kernel {path} cannot be read: {exc.strerror or exc}") from None
    data = False
    for number, line in enumerate(text.splitlines(), 1):
        marker = line.strip().lower()
        if marker in ("\\begindata", "\\begintext"):
            data = marker == "\\begindata"
            continue
        for value in re.findall(r"'((?:[^']|'')*)'", line) if data else ():
            if len(value) > POOL_STRING_MAX:
                raise KernelError(f"meta-kernel {path}, line {number}: a string of {len(value)} characters "
                                  f"({value[:40]}...); SPICE keeps {POOL_STRING_MAX}: split it with '+' continuation "
                                  "('first part+' 'rest')")


def _meta_kernel_files(path: Path) -> list[Path]:
    """The files a meta-kernel lists, symbols substituted, relative paths from its folder."""
    _check_string_lengths(path)
    sp = spiceypy_module()
    with POOL_LOCK:
        _clear_pool()
        try:
            sp.ldpool(str(path))
            values = {}
            for name in ("KERNELS_TO_LOAD", "PATH_SYMBOLS", "PATH_VALUES"):
                values[name] = _pool_strings(name)
        except spice_error_type() as exc:
            raise KernelError(f"meta-kernel {path} cannot be read: {spice_message(exc)}") from None
        finally:
            _clear_pool()
    symbols, targets = values["PATH_SYMBOLS"], values["PATH_VALUES"]
    if len(symbols) != len(targets):
        raise KernelError(f"meta-kernel {path}: PATH_SYMBOLS has {len(symbols)} names, PATH_VALUES {len(targets)}")
    if not values["KERNELS_TO_LOAD"]:
        raise KernelError(f"meta-kernel {path} lists no KERNELS_TO_LOAD")
    files = []
    for text in values["KERNELS_TO_LOAD"]:
        for symbol, value in zip(symbols, targets):
            text = text.replace(f"${symbol}", value)
        if "$" in text:
            raise KernelError(f"meta-kernel {path}: {text!r} uses a symbol not in PATH_SYMBOLS")
        given = Path(text).expanduser()
        files.append(given if given.is_absolute() else path.parent / given)
    return files


def _pool_strings(name: str) -> list[str]:
    """The strings of kernel-pool variable ``name``, ``+`` continuations joined (empty if absent)."""
    sp = spiceypy_module()
    with sp.no_found_check():
        count, _, found = sp.dtpool(name)
        if not found:
            return []
        pieces, _ = sp.gcpool(name, 0, count)
    out, pending = [], ""
    for piece in pieces:
        piece = piece.rstrip()
        if piece.endswith("+"):
            pending += piece[:-1]
        else:
            out.append(pending + piece)
            pending = ""
    if pending:
        out.append(pending)
    return out


def _clear_pool() -> None:
    spiceypy_module().kclear()
    _POOL["owner"], _POOL["count"] = None, -1


def naif_code(body: str | int) -> int:
    """NAIF id of ``body`` without kernels of its own: an id (int or text), an opnav name
    (:data:`opnav.ephemeris.planets.NAIF_ID`, ``phobos``, ``deimos``) or a name built into SPICE
    (``"SOLAR SYSTEM BARYCENTER"``, ``"EROS"``); ``KernelError`` for any other name."""
    if isinstance(body, (int, np.integer)) and not isinstance(body, bool):
        return int(body)
    text = str(body).strip()
    key = text.lower().replace(" ", "_")
    if re.fullmatch(r"[+-]?\d+", text):
        return int(text)
    if key in _OPNAV_IDS:
        return _OPNAV_IDS[key]
    sp = spiceypy_module()
    with POOL_LOCK, sp.no_found_check():
        code, found = sp.bodn2c(text.replace("_", " "))
    if not found:
        raise KernelError(f"unknown body {body!r}: not a NAIF id, an opnav name ({', '.join(sorted(_OPNAV_IDS))}) "
                          "or a name built into SPICE")
    return int(code)


class KernelSet:
    """SPICE kernels loaded together, in order (later files take priority).

    Parameters
    ----------
    paths : sequence of str or Path
        Kernel files and meta-kernels (expanded by :func:`expand_kernels`).

    Raises
    ------
    KernelError
        A missing file, a file of the wrong type, a meta-kernel that cannot be read.
    """

    def __init__(self, paths: Sequence[str | Path]):
        if isinstance(paths, (str, Path)):
            paths = [paths]
        self.sources = tuple(str(p) for p in paths)
        if not self.sources:
            raise KernelError("no kernels given")
        typed = _typed_kernels(self.sources, ())
        #: The kernel files in load order (meta-kernels expanded), absolute.
        self.files = tuple(path for path, _ in typed)
        #: ``(architecture, type)`` of each file, as its ID word says (``("DAF", "SPK")``).
        self.types = dict(typed)
        self._token = next(_TOKENS)

    def __getstate__(self) -> dict:
        return {"sources": self.sources}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["sources"])

    def names(self) -> str:
        """The files' names, for messages."""
        return ", ".join(path.name for path in self.files)

    def of_type(self, kind: str) -> tuple[Path, ...]:
        """The files whose ID word names ``kind`` (``"SPK"``, ``"PCK"``, ...)."""
        return tuple(path for path in self.files if self.types[path][1] == kind)

    @contextlib.contextmanager
    def loaded(self) -> Iterator[None]:
        """Hold the process's kernel pool with exactly this set's files loaded (a context)."""
        sp = spiceypy_module()
        with POOL_LOCK:
            if _POOL["owner"] != self._token or sp.ktotal("ALL") != _POOL["count"]:
                _clear_pool()
                for path in self.files:
                    try:
                        sp.furnsh(str(path))
                    except spice_error_type() as exc:
                        _clear_pool()
                        raise KernelError(f"kernel {path} cannot be loaded: {spice_message(exc)}") from None
                _POOL["owner"], _POOL["count"] = self._token, sp.ktotal("ALL")
            yield


class SpiceEphemeris:
    """Body states from SPICE kernels, with the interface of :class:`opnav.ephemeris.Ephemeris`.

    Parameters
    ----------
    kernels : KernelSet or sequence of str or Path
        SPK, PCK and text kernels or meta-kernels, in load order.

    Examples
    --------
    >>> from opnav.ephemeris.planets import default_kernel_path
    >>> eph = SpiceEphemeris([default_kernel_path()])
    >>> r, v = eph.state("mars", 0.0, center="sun")
    >>> 2.0e8 < float((r @ r) ** 0.5) < 2.5e8
    True
    """

    def __init__(self, kernels: KernelSet | Sequence[str | Path]):
        self.kernels = kernels if isinstance(kernels, KernelSet) else KernelSet(kernels)
        if not self.kernels.of_type("SPK"):
            raise KernelError(f"kernels {self.kernels.names()} hold no SPK (a binary DAF/SPK file): no body states")
        self._ids: dict[str, int] = {}
        sp = spiceypy_module()
        coverage: dict[int, list[tuple[Path, np.ndarray]]] = {}
        with self.kernels.loaded():
            for path in self.kernels.of_type("SPK"):
                for naif in sp.spkobj(str(path)):
                    window = sp.spkcov(str(path), int(naif))
                    intervals = np.asarray([sp.wnfetd(window, k) for k in range(sp.wncard(window))], dtype=float)
                    coverage.setdefault(int(naif), []).append((path, intervals.reshape(-1, 2)))
        #: NAIF id -> [(SPK file, (K, 2) covered intervals, TDB s past J2000)].
        self.coverage = coverage

    def __repr__(self) -> str:
        return f"SpiceEphemeris([{self.kernels.names()}])"

    # --- names -------------------------------------------------------------------------------
    def naif_id(self, body: str | int) -> int:
        """NAIF id of ``body``: a NAIF id (int or text), an opnav name, or a SPICE name."""
        if isinstance(body, (int, np.integer)):
            return int(body)
        text = str(body).strip()
        if text in self._ids:
            return self._ids[text]
        key = text.lower().replace(" ", "_")
        if re.fullmatch(r"[+-]?\d+", text):
            naif = int(text)
        elif key in _OPNAV_IDS:
            naif = _OPNAV_IDS[key]
        else:
            sp = spiceypy_module()
            with self.kernels.loaded(), sp.no_found_check():
                code, found = sp.bodn2c(text.replace("_", " "))
            if not found:
                raise KernelError(f"unknown body {body!r}: not an opnav name, a NAIF id or a name SPICE knows "
                                  f"(kernels {self.kernels.names()}); bodies the SPKs hold: "
                                  f"{', '.join(self.known_bodies())}")
            naif = int(code)
        self._ids[text] = naif
        return naif

    def body_name(self, naif: int) -> str:
        """A name for NAIF id ``naif``: opnav's, else SPICE's in lower case, else the id as text."""
        if naif in _OPNAV_NAMES:
            return _OPNAV_NAMES[naif]
        sp = spiceypy_module()
        with self.kernels.loaded(), sp.no_found_check():
            name, found = sp.bodc2n(int(naif))
        return name.lower().replace(" ", "_") if found else str(naif)

    def known_bodies(self) -> tuple[str, ...]:
        """The bodies the kernels' SPKs hold, by name (or NAIF id), sorted; ``ssb`` included."""
        return tuple(sorted({"ssb"} | {self.body_name(naif) for naif in self.coverage}))

    def check_body(self, name: str | int) -> str:
        """``name`` as these kernels know it (lower case), or ``KernelError`` listing the bodies they hold."""
        naif = self.naif_id(name)
        if naif != 0 and naif not in self.coverage:
            raise KernelError(f"body {name!r} (NAIF {naif}) is in no SPK of kernels {self.kernels.names()}; "
                              f"they hold {', '.join(self.known_bodies())}")
        return str(name).strip().lower()

    # --- states ------------------------------------------------------------------------------
    def state(self, body: str | int, t: float | np.ndarray, *, center: str | int = "ssb"
              ) -> tuple[np.ndarray, np.ndarray]:
        """Geometric position (km) and velocity (km/s) of ``body`` relative to ``center``, ICRF.

        Parameters
        ----------
        body, center : str or int
            Names or NAIF ids (module notes); ``center`` default the solar-system barycentre.
        t : float or (N,) array
            TDB seconds past J2000.

        Returns
        -------
        r_center_body_km, v_center_body_km_s : (3,) or (N, 3) arrays
            ICRF; no light time or aberration (:mod:`opnav.light` applies them).

        Raises
        ------
        KernelError
            An unknown body, or an epoch the kernels do not cover for it (the message names the
            kernels, the body and the first such epoch).
        """
        t_arr = np.atleast_1d(np.asarray(t, dtype=float))
        if t_arr.ndim != 1:
            raise KernelError(f"epochs t must be a scalar or 1-D array, got shape {np.shape(t)}")
        if not np.all(np.isfinite(t_arr)):
            raise KernelError("epoch t is NaN or infinite")
        target, origin = self.naif_id(body), self.naif_id(center)
        with self.kernels.loaded():
            try:
                states, _ = _cyice().spkgeo_v(target, np.array(t_arr, order="C"), ICRF, origin)
            except spice_error_type() as exc:
                raise self._state_error(exc, body, center, target, origin, t_arr) from None
        states = np.asarray(states, dtype=float).reshape(-1, 6)
        r, v = states[:, :3], states[:, 3:]
        if np.ndim(t) == 0:
            return r[0], v[0]
        return r, v

    def position(self, body: str | int, t: float | np.ndarray, *, center: str | int = "ssb") -> np.ndarray:
        """Position (km, ICRF) of ``body`` relative to ``center``; see :meth:`state`."""
        return self.state(body, t, center=center)[0]

    def _state_error(self, exc, body, center, target: int, origin: int, t: np.ndarray) -> KernelError:
        """The one line for a failed ``spkgeo_v``: the first epoch that fails and what the kernels cover."""
        if getattr(exc, "short", "") != "SPICE(SPKINSUFFDATA)":
            return KernelError(f"kernels {self.kernels.names()}: state of {body!r} relative to {center!r}: "
                               f"{spice_message(exc)}")
        sp = spiceypy_module()
        bad = float(t[0])
        for epoch in t:  # the error path only: find the first epoch SPICE cannot answer
            try:
                sp.spkgeo(target, float(epoch), ICRF, origin)
            except spice_error_type():
                bad = float(epoch)
                break
        held = []
        for naif, name in ((target, body), (origin, center)):
            if naif == 0:
                continue
            spans = [f"{path.name} {describe_epoch(a)} to {describe_epoch(b)}"
                     for path, intervals in self.coverage.get(naif, []) for a, b in intervals]
            held.append(f"{name!r} (NAIF {naif}): " + ("; ".join(spans) if spans else "in no SPK"))
        return KernelError(f"kernels {self.kernels.names()} do not cover {body!r} relative to {center!r} at "
                           f"{describe_epoch(bad)}; coverage of {', '.join(held) or 'the chain to the SSB'}")

    # --- constants and frames ----------------------------------------------------------------
    def radii_km(self, body: str | int) -> np.ndarray:
        """Tri-axial radii (a, b, c), km, of ``body`` from a text PCK (``BODYnnn_RADII``)."""
        naif = self.naif_id(body)
        sp = spiceypy_module()
        with self.kernels.loaded():
            if not sp.bodfnd(naif, "RADII"):
                pcks = ", ".join(p.name for p in self.kernels.of_type("PCK")) or "none loaded"
                raise KernelError(f"kernels {self.kernels.names()} give no radii (BODY{naif}_RADII) for {body!r}; "
                                  f"PCKs: {pcks}")
            try:
                return np.asarray(sp.bodvcd(naif, "RADII", 3)[1], dtype=float)
            except spice_error_type() as exc:
                raise KernelError(f"kernels {self.kernels.names()}: radii of {body!r}: {spice_message(exc)}") from None

    def gm_km3_s2(self, body: str | int) -> float:
        """Gravitational parameter of ``body``, km^3/s^2, from a text PCK (``BODYnnn_GM``)."""
        naif = self.naif_id(body)
        sp = spiceypy_module()
        with self.kernels.loaded():
            if not sp.bodfnd(naif, "GM"):
                pcks = ", ".join(p.name for p in self.kernels.of_type("PCK")) or "none loaded"
                raise KernelError(f"kernels {self.kernels.names()} give no GM (BODY{naif}_GM) for {body!r}; "
                                  f"PCKs: {pcks}")
            try:
                return float(sp.bodvcd(naif, "GM", 1)[1][0])
            except spice_error_type() as exc:
                raise KernelError(f"kernels {self.kernels.names()}: GM of {body!r}: {spice_message(exc)}") from None

    def rotation(self, frame: str, t: float | np.ndarray) -> np.ndarray:
        """``R_frame_icrf``: the matrix turning ICRF vectors into ``frame`` at TDB epochs ``t``.

        ``frame`` is a SPICE frame name (``IAU_MARS`` from a text PCK, ``MOON_PA`` from an FK and
        binary PCK, ...). Shape (3, 3) for a scalar ``t``, (N, 3, 3) for (N,).
        """
        t_arr = np.atleast_1d(np.asarray(t, dtype=float))
        with self.kernels.loaded():
            try:
                matrices = _cyice().pxform_v(ICRF, str(frame), np.array(t_arr, order="C"))
            except spice_error_type() as exc:
                if getattr(exc, "short", "") == "SPICE(UNKNOWNFRAME)":
                    message = f"frame {frame!r} is not defined by kernels {self.kernels.names()}"
                else:
                    message = (f"kernels {self.kernels.names()} cannot orient frame {frame!r} near "
                               f"{describe_epoch(t_arr[0])}: {spice_message(exc)}")
                raise KernelError(message) from None
        matrices = np.asarray(matrices, dtype=float).reshape(-1, 3, 3)
        return matrices[0] if np.ndim(t) == 0 else matrices

    def body_rotation(self, body: str | int, t: float | np.ndarray) -> np.ndarray:
        """``R_body_icrf`` of ``body``'s PCK frame (``IAU_<NAME>``, or the frame ``OBJECT_<NAME>_FRAME`` names);
        see :meth:`rotation`."""
        naif = self.naif_id(body)
        sp = spiceypy_module()
        with self.kernels.loaded(), sp.no_found_check():
            _, name, found = sp.cidfrm(naif)
        if not found:
            raise KernelError(f"kernels {self.kernels.names()} define no body-fixed frame for {body!r} "
                              f"(NAIF {naif})")
        return self.rotation(name, t)


class KernelCache(EphemerisCache):
    """A Chebyshev cache (:class:`opnav.ephemeris.cache.EphemerisCache`, within 1 cm of its source)
    over a :class:`SpiceEphemeris`, for any body the kernels hold: what the filters, the fast
    propagator and the image stage read when a mission gives kernels (:mod:`opnav.studies.mission`).

    Parameters
    ----------
    ephemeris : SpiceEphemeris
    """

    def __init__(self, ephemeris: SpiceEphemeris, **options):
        super().__init__(ephemeris, **options)

    def body_key(self, name) -> str:
        """``name`` as the kernels know it (:meth:`SpiceEphemeris.check_body`)."""
        return self.ephemeris.check_body(name)


__all__ = ["ICRF", "POOL_LOCK", "POOL_STRING_MAX", "KernelError", "KernelSet", "SpiceEphemeris", "KernelCache", "expand_kernels", "kernel_type",
           "naif_code", "pool_string", "spice_error_type", "spice_message", "spiceypy_module"]
