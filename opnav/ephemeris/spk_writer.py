"""SPK files written with spiceypy: an arc of states (types 13 and 9) or a body's orbital elements (type 5).

An SPK makes any trajectory opnav or a user has (a propagated arc, a CCSDS OEM, a small body's
stated elements) into a kernel that :class:`opnav.ephemeris.spice.SpiceEphemeris`, and any SPICE
tool, reads.

- :func:`write_spk` writes states at epochs as one segment of type 13 (Hermite interpolation of
  positions and velocities over a window of ``(degree + 1) / 2`` states) or type 9 (Lagrange
  interpolation of positions and of velocities, each over ``degree + 1`` states). Between its
  states an SPK is as good as that interpolation; at the states it is exact.
- :func:`write_elements_spk` writes a body on a Keplerian orbit as type 5 (discrete states,
  two-body propagation between them): the conic's states every ``step_s`` (SPICE's ``conics``),
  which type 5 propagates exactly along the same conic, so the kernel is the stated orbit.

States are km and km/s about the NAIF body ``center``, axes of the SPICE frame ``frame``
(``J2000`` = ICRF, ``ECLIPJ2000`` the J2000 ecliptic); epochs TDB seconds past J2000. Files are
written whole into a temporary file beside the output and moved into place (an existing file is
replaced; nothing is left on an error).
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_write_bytes
from .spice import POOL_LOCK, KernelError, naif_code, spice_error_type, spice_message, spiceypy_module

#: SPK types :func:`write_spk` writes, by the interpolation they apply.
INTERPOLATIONS = {"hermite": 13, "lagrange": 9}

#: Largest interpolation degree of SPK types 9 and 13 (SPICE's MAXDEG).
MAX_DEGREE = 27

#: Frames an SPK segment may be written in (SPICE names).
FRAMES = ("J2000", "ECLIPJ2000")


def _check_arc(t_tdb_s, states) -> tuple[np.ndarray, np.ndarray]:
    try:
        t = np.array(t_tdb_s, dtype=float)
        x = np.array(states, dtype=float)
    except (TypeError, ValueError):
        raise InputError("t_tdb_s and states must be arrays of numbers") from None
    if t.ndim != 1 or x.shape != (t.size, 6):
        raise InputError(f"states must have shape (N, 6) matching t_tdb_s (N,), got {x.shape} and {t.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(x))):
        raise InputError("t_tdb_s and states must be finite")
    if np.any(np.diff(t) <= 0.0):
        raise InputError("t_tdb_s must increase strictly")
    return t, x


def _check_ids(body: int, center: int, frame: str) -> None:
    for name, value in (("body", body), ("center", center)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise InputError(f"{name} must be a NAIF id (an integer), got {value!r}")
    if int(body) == int(center):
        raise InputError(f"body and center must differ, both are NAIF {body}")
    if frame not in FRAMES:
        raise InputError(f"frame must be one of {', '.join(FRAMES)}, got {frame!r}")


def _write(path: str | Path, segment_writer, comment: str) -> Path:
    """Run ``segment_writer(handle)`` on a new SPK and move it to ``path`` (module notes)."""
    path = Path(path)
    sp = spiceypy_module()
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=f".{path.name}.") as folder:
        scratch = Path(folder) / "kernel.bsp"
        with POOL_LOCK:  # CSPICE's file table is process-wide too
            handle = None
            try:
                handle = sp.spkopn(str(scratch), "opnav SPK", 1024)
                if comment:
                    sp.dafac(handle, [line[:1000] for line in comment.splitlines() if line] or [" "])
                segment_writer(handle)
            except spice_error_type() as exc:
                raise KernelError(f"cannot write SPK {path}: {spice_message(exc)}") from None
            finally:
                if handle is not None:
                    sp.spkcls(handle)
        atomic_write_bytes(path, scratch.read_bytes())
    return path


def write_spk(path: str | Path, t_tdb_s, states, *, body: int, center: int, frame: str = "J2000",
              interpolation: str = "hermite", degree: int = 7, segment_id: str = "opnav arc",
              comment: str = "") -> Path:
    """Write an arc of states as one SPK segment (type 13 Hermite or type 9 Lagrange).

    Parameters
    ----------
    path : str or Path
        The SPK file (replaced if it exists).
    t_tdb_s : (N,) array
        Epochs, TDB seconds past J2000, strictly increasing.
    states : (N, 6) array
        ``[r km, v km/s]`` of ``body`` relative to ``center``, axes of ``frame``.
    body, center : int
        NAIF ids (a spacecraft's is negative, e.g. -77).
    frame : {"J2000", "ECLIPJ2000"}
        Axes of ``states``; J2000 is ICRF.
    interpolation : {"hermite", "lagrange"}
        Type 13 or type 9.
    degree : int
        Degree of the interpolating polynomials, 1..27 (odd for Hermite: a window of
        ``(degree + 1) / 2`` states); at most ``2 N - 1`` (Hermite) or ``N - 1`` (Lagrange).
    segment_id : str
        The segment's name (at most 40 characters).
    comment : str
        Lines written to the file's comment area.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    InputError
        Bad shapes or values, epochs that do not increase, a degree the type or the arc cannot take.
    """
    t, x = _check_arc(t_tdb_s, states)
    _check_ids(body, center, frame)
    if interpolation not in INTERPOLATIONS:
        raise InputError(f"interpolation must be one of {', '.join(INTERPOLATIONS)}, got {interpolation!r}")
    kind = INTERPOLATIONS[interpolation]
    window = (degree + 1) // 2 if kind == 13 else degree + 1
    if isinstance(degree, bool) or not isinstance(degree, (int, np.integer)) or not 1 <= degree <= MAX_DEGREE:
        raise InputError(f"degree must be an integer from 1 to {MAX_DEGREE}, got {degree!r}")
    if kind == 13 and degree % 2 == 0:
        raise InputError(f"a Hermite SPK (type 13) takes an odd degree, got {degree}")
    if t.size < window:
        raise InputError(f"a degree-{degree} {interpolation} SPK needs at least {window} states, got {t.size}")
    if len(segment_id) > 40:
        raise InputError(f"segment_id must be at most 40 characters, got {len(segment_id)}")
    sp = spiceypy_module()

    def segment(handle: int) -> None:
        writer = sp.spkw13 if kind == 13 else sp.spkw09
        writer(handle, int(body), int(center), frame, float(t[0]), float(t[-1]), segment_id, int(degree),
               t.size, np.ascontiguousarray(x), np.ascontiguousarray(t))

    return _write(path, segment, comment)


@dataclass(frozen=True)
class KeplerElements:
    """Osculating elements of a body on an elliptic orbit (internal units).

    Attributes
    ----------
    a_km : float
        Semi-major axis, km (> 0).
    e : float
        Eccentricity, 0 <= e < 1.
    i_rad, node_rad, argp_rad, mean_anomaly_rad : float
        Inclination, longitude of the ascending node, argument of periapsis and mean anomaly at
        ``epoch_tdb_s``, rad, in the axes of the SPK's frame.
    epoch_tdb_s : float
        Epoch of the elements, TDB seconds past J2000.
    gm_km3_s2 : float
        Gravitational parameter of the centre, km^3/s^2 (> 0).
    """

    a_km: float
    e: float
    i_rad: float
    node_rad: float
    argp_rad: float
    mean_anomaly_rad: float
    epoch_tdb_s: float
    gm_km3_s2: float

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            if not math.isfinite(getattr(self, name)):
                raise InputError(f"element {name} must be finite, got {getattr(self, name)!r}")
        if self.a_km <= 0.0:
            raise InputError(f"element a_km must be positive, got {self.a_km!r}")
        if not 0.0 <= self.e < 1.0:
            raise InputError(f"element e must be in [0, 1) (an elliptic orbit), got {self.e!r}")
        if self.gm_km3_s2 <= 0.0:
            raise InputError(f"element gm_km3_s2 must be positive, got {self.gm_km3_s2!r}")

    @property
    def period_s(self) -> float:
        """Orbital period, s."""
        return 2.0 * math.pi * math.sqrt(self.a_km**3 / self.gm_km3_s2)

    def states(self, t_tdb_s) -> np.ndarray:
        """``[r km, v km/s]`` (N, 6) on the conic at TDB epochs ``t_tdb_s`` (N,), axes of the elements
        (SPICE's ``conics``)."""
        sp = spiceypy_module()
        elts = [self.a_km * (1.0 - self.e), self.e, self.i_rad, self.node_rad, self.argp_rad,
                self.mean_anomaly_rad, self.epoch_tdb_s, self.gm_km3_s2]
        return np.array([sp.conics(elts, float(t)) for t in np.atleast_1d(t_tdb_s)], dtype=float)


def write_elements_spk(path: str | Path, elements: KeplerElements, *, body: int, center: int, start_tdb_s: float,
                       stop_tdb_s: float, frame: str = "J2000", step_s: float | None = None,
                       segment_id: str = "opnav elements", comment: str = "") -> Path:
    """Write a body on the Keplerian orbit ``elements`` from ``start_tdb_s`` to ``stop_tdb_s`` (SPK type 5).

    ``step_s`` (default a 16th of the period, at most the span) spaces the conic states written;
    type 5 propagates each along its conic, so any step reproduces the orbit (module notes).
    ``frame`` names the axes the elements are referred to (``ECLIPJ2000`` for heliocentric
    elements on the ecliptic). Returns ``path``; ``InputError`` for bad values.
    """
    _check_ids(body, center, frame)
    if not (math.isfinite(start_tdb_s) and math.isfinite(stop_tdb_s) and stop_tdb_s > start_tdb_s):
        raise InputError(f"stop_tdb_s must be after start_tdb_s, got {start_tdb_s!r} to {stop_tdb_s!r}")
    span = stop_tdb_s - start_tdb_s
    step = min(elements.period_s / 16.0, span) if step_s is None else float(step_s)
    if not (math.isfinite(step) and step > 0.0):
        raise InputError(f"step_s must be positive, got {step_s!r}")
    n = int(math.ceil(span / step)) + 1
    t = np.linspace(start_tdb_s, stop_tdb_s, max(n, 2))
    x = elements.states(t)
    sp = spiceypy_module()

    def segment(handle: int) -> None:
        sp.spkw05(handle, int(body), int(center), frame, float(t[0]), float(t[-1]), segment_id,
                  elements.gm_km3_s2, t.size, np.ascontiguousarray(x), np.ascontiguousarray(t))

    return _write(path, segment, comment)


#: CCSDS ``REF_FRAME`` names an OEM may use, and the SPICE frame of each. ICRF, GCRF and EME2000 are
#: all SPICE's J2000, as in opnav (EME2000's axes differ from ICRF's by the 23 mas frame bias).
OEM_FRAMES = {"ICRF": "J2000", "GCRF": "J2000", "EME2000": "J2000", "J2000": "J2000"}

#: An OEM without ``INTERPOLATION``: the SPK interpolates as a degree-7 Hermite (4 states a window).
OEM_DEFAULT_INTERPOLATION = ("hermite", 7)


def oem_interpolation(method: str, degree: int | None) -> tuple[str, int]:
    """The SPK interpolation ``(interpolation, degree)`` that applies an OEM's ``INTERPOLATION`` and
    ``INTERPOLATION_DEGREE``: HERMITE d is type 13 of degree d, LAGRANGE d type 9 of degree d,
    LINEAR type 9 of degree 1; none given, :data:`OEM_DEFAULT_INTERPOLATION`."""
    method = (method or "").strip().upper()
    if not method:
        return OEM_DEFAULT_INTERPOLATION
    if method == "LINEAR":
        return "lagrange", 1
    if method not in ("HERMITE", "LAGRANGE") or degree is None:
        raise InputError(f"OEM INTERPOLATION {method} with INTERPOLATION_DEGREE {degree}: opnav writes an SPK "
                         "for HERMITE or LAGRANGE with a degree, or LINEAR")
    if method == "HERMITE" and degree % 2 == 0:
        raise InputError(f"OEM INTERPOLATION HERMITE of even degree {degree}: an SPK (type 13) interpolates "
                         "Hermite polynomials of odd degree only")
    return method.lower(), int(degree)


def write_oem_spk(path: str | Path, oem, *, body: int | None = None, segment_id: str = "opnav OEM") -> Path:
    """Write the arc of an OEM (an :class:`opnav.ccsds.OemData`, as :func:`opnav.ccsds.read_oem` gives)
    as an SPK that interpolates as the OEM says (:func:`oem_interpolation`).

    ``body`` is the NAIF id written (default: the OEM's ``OBJECT_ID`` when it is an integer); the centre
    is the OEM's ``CENTER_NAME`` (an opnav or SPICE body name), the frame its ``REF_FRAME``
    (:data:`OEM_FRAMES`). ``InputError`` names what cannot be written.
    """
    if body is None:
        try:
            body = int(str(oem.object_id).strip())
        except ValueError:
            raise InputError(f"OEM OBJECT_ID {oem.object_id!r} is not a NAIF id; give the body's NAIF id "
                             "(e.g. -77 for a spacecraft)") from None
    frame = OEM_FRAMES.get(str(oem.ref_frame).strip().upper())
    if frame is None:
        raise InputError(f"OEM REF_FRAME {oem.ref_frame!r}: opnav writes an SPK from {', '.join(OEM_FRAMES)} only")
    try:
        center = naif_code(oem.center)
    except KernelError as exc:
        raise InputError(f"OEM CENTER_NAME: {exc}") from None
    interpolation, degree = oem_interpolation(oem.interpolation, oem.interpolation_degree)
    comment = f"From the CCSDS OEM of OBJECT_NAME {oem.object_name}, written by opnav."
    return write_spk(path, oem.t_tdb_s, oem.states, body=body, center=center, frame=frame,
                     interpolation=interpolation, degree=degree, segment_id=segment_id, comment=comment)


__all__ = ["FRAMES", "INTERPOLATIONS", "KeplerElements", "MAX_DEGREE", "OEM_FRAMES", "oem_interpolation",
           "write_elements_spk", "write_oem_spk", "write_spk"]
