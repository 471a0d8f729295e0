"""The FITS header of a frame to what the image stage and the plate solver need: the one place that reads it.

Epoch (:func:`header_epoch`), mid-exposure, TDB s past J2000, the first of:

1. ``TDB_S`` (opnav's own, TDB s past J2000, mid-exposure);
2. ``DATE-AVG`` (mid-exposure);
3. ``DATE-OBS`` + ``EXPTIME / 2``: ``DATE-OBS`` is the *start* of the exposure (FITS 4.0,
   section 9.4.1, and what :mod:`opnav.render.frames_io` writes), so half the exposure is added
   (nothing without ``EXPTIME``).

Dates are in the scale ``TIMESYS`` names (UTC when absent, the FITS default; UTC, TT, TDB or
TAI). The a-priori attitude (camera -> ICRF) and a pinhole camera come from the TAN WCS
(:func:`wcs_attitude`, :func:`wcs_hint`: ``CDi_j``, else ``PCi_j`` x ``CDELTi`` or ``CROTA2``,
with ``CRVAL``/``CRPIX``; SIP terms, if any, are left out: the hint is the linear part); detector
gain, read noise, bias and exposure from ``GAIN``, ``RDNOISE``, ``BIASLVL``, ``EXPTIME``
(:func:`detector_keywords`; absent, they are :data:`DETECTOR_DEFAULTS`: the
:class:`~opnav.camera.Camera` defaults, so a frame without ``BIASLVL`` has the 100 ADU bias of a
default camera, and 1 s of exposure); the a-priori observer state (ICRF, solar-system
barycentre, km and km/s) from ``OBS_X`` ... ``OBS_VZ``. Headers written by
:mod:`opnav.render.frames_io` carry all of them.

The keywords are read from the header cards themselves (no ``astropy.wcs``), so a header of
any FITS reader that maps keywords to values (``astropy.io.fits.Header``, a dict) is accepted.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..errors import FrameError, InputError
from ..frames import radec_to_unit

#: ``TIMESYS`` values read, as :func:`opnav.epochs.parse_epoch` scales.
TIME_SCALES = {"UTC": "utc", "TT": "tt", "TDB": "tdb", "TAI": "tai"}

_CAMERA_DEFAULTS = {f.name: f.default for f in dataclasses.fields(Camera)}
#: What a frame without the detector keyword is taken to have: the :class:`~opnav.camera.Camera`
#: defaults (what ``opnav render`` writes for a ``[camera]`` that does not set them), and an
#: exposure of 1 s (``EXPTIME = 0`` is taken as absent).
DETECTOR_DEFAULTS = {
    "GAIN": _CAMERA_DEFAULTS["gain_e_per_adu"],
    "RDNOISE": _CAMERA_DEFAULTS["read_noise_e"],
    "BIASLVL": _CAMERA_DEFAULTS["bias_adu"],
    "EXPTIME": 1.0,
}


def _number(header, key: str, path: str, default: float | None = None) -> float | None:
    """The finite number of ``key`` (``default`` when absent); FrameError naming the file when it is not one."""
    if key not in header:
        return default
    value = header[key]
    try:
        if isinstance(value, bool):
            raise TypeError
        number = float(value)
    except (TypeError, ValueError):
        raise FrameError(f"{path}: header keyword {key} = {value!r} is not a number") from None
    if not math.isfinite(number):
        raise FrameError(f"{path}: header keyword {key} = {value!r} is not a finite number")
    return number


def time_scale(header, path: str) -> str:
    """The :func:`opnav.epochs.parse_epoch` scale of the header's dates: ``TIMESYS``, UTC when absent."""
    name = str(header.get("TIMESYS", "UTC")).strip().upper() or "UTC"
    if name not in TIME_SCALES:
        raise FrameError(f"{path}: TIMESYS = {name!r} is not supported; expected one of {', '.join(TIME_SCALES)}")
    return TIME_SCALES[name]


def _date(header, key: str, path: str) -> float:
    from ..epochs import parse_epoch  # astropy.time, only for headers that need it

    try:
        return float(parse_epoch(str(header[key]).strip(), time_scale(header, path)))
    except InputError as exc:
        raise FrameError(f"{path}: header keyword {key}: {exc}") from None


def has_epoch(header) -> bool:
    """Whether the header carries an epoch keyword (``TDB_S``, ``DATE-AVG`` or ``DATE-OBS``)."""
    return header is not None and any(key in header for key in ("TDB_S", "DATE-AVG", "DATE-OBS"))


def header_epoch(header, path: str) -> float:
    """Mid-exposure epoch, TDB s past J2000 (module docstring: ``TDB_S``, ``DATE-AVG``, ``DATE-OBS`` + ``EXPTIME/2``).

    Raises
    ------
    FrameError
        No epoch keyword, or one (or ``TIMESYS``, ``EXPTIME``) that cannot be read; the message
        names the file and the keyword.
    """
    if "TDB_S" in header:
        return _number(header, "TDB_S", path)
    if "DATE-AVG" in header:
        return _date(header, "DATE-AVG", path)
    if "DATE-OBS" in header:
        exposure = _number(header, "EXPTIME", path, 0.0)
        if exposure < 0.0:
            raise FrameError(f"{path}: header keyword EXPTIME = {exposure!r} is negative")
        return _date(header, "DATE-OBS", path) + 0.5 * exposure
    raise FrameError(f"{path}: no epoch in the header (TDB_S, DATE-AVG or DATE-OBS)")


def header_vector(header, keys: tuple[str, str, str], path: str) -> np.ndarray | None:
    """The three finite numbers of ``keys`` (e.g. ``OBS_VX/VY/VZ``); None when the header lacks any of them.

    Raises
    ------
    FrameError
        A keyword present but not a finite number.
    """
    if header is None or not all(key in header for key in keys):
        return None
    return np.array([_number(header, key, path) for key in keys])


def _linear_wcs(header, path: str) -> tuple[np.ndarray, float, float, np.ndarray]:
    """``(CD (2, 2) deg/px, CRVAL1, CRVAL2 deg, CRPIX (2,) 1-based)`` of the header's celestial WCS."""
    if any(f"CD{i}_{j}" in header for i in (1, 2) for j in (1, 2)):
        cd = np.array([[_number(header, f"CD{i}_{j}", path, 0.0) for j in (1, 2)] for i in (1, 2)])
    else:
        cdelt = np.array([_number(header, f"CDELT{i}", path, 1.0) for i in (1, 2)])
        if any(f"PC{i}_{j}" in header for i in (1, 2) for j in (1, 2)) or "CROTA2" not in header:
            pc = np.array([[_number(header, f"PC{i}_{j}", path, float(i == j)) for j in (1, 2)] for i in (1, 2)])
        else:  # the AIPS convention (FITS WCS paper II, eq. 185): a rotation by CROTA2
            rho = math.radians(_number(header, "CROTA2", path))
            pc = np.array([[math.cos(rho), -math.sin(rho) * cdelt[1] / cdelt[0]],
                           [math.sin(rho) * cdelt[0] / cdelt[1], math.cos(rho)]])
        cd = pc * cdelt[:, None]
    crval = (_number(header, "CRVAL1", path, 0.0), _number(header, "CRVAL2", path, 0.0))
    crpix = np.array([_number(header, "CRPIX1", path, 0.0), _number(header, "CRPIX2", path, 0.0)])
    return cd, crval[0], crval[1], crpix


def wcs_attitude(header, path: str) -> tuple[Rotation, float, tuple[float, float]]:
    """A-priori attitude (camera -> ICRF), focal length (px) and principal point (px, 0-based) from a TAN WCS.

    At the reference pixel the TAN projection's tangent plane holds the camera's x and y axes:
    column j of CD gives d(east, north)/d(pixel j) in degrees.

    Raises
    ------
    FrameError
        No valid CD matrix (absent, singular, not finite) or a mirrored one.
    """
    cd, ra0_deg, dec0_deg, crpix = _linear_wcs(header, path)
    if not np.all(np.isfinite(cd)) or abs(np.linalg.det(cd)) == 0.0:
        raise FrameError(f"{path}: the WCS has no valid CD matrix")
    ra0, dec0 = math.radians(ra0_deg), math.radians(dec0_deg)
    east = np.array([-math.sin(ra0), math.cos(ra0), 0.0])
    north = np.array([-math.sin(dec0) * math.cos(ra0), -math.sin(dec0) * math.sin(ra0), math.cos(dec0)])
    boresight = radec_to_unit(ra0, dec0)
    axis_x = cd[0, 0] * east + cd[1, 0] * north
    axis_y = cd[0, 1] * east + cd[1, 1] * north
    scale_rad = math.radians(math.sqrt(abs(np.linalg.det(cd))))
    u, _, vt = np.linalg.svd(np.column_stack([axis_x / np.linalg.norm(axis_x), axis_y / np.linalg.norm(axis_y), boresight]))
    matrix = u @ vt
    if np.linalg.det(matrix) < 0:
        raise FrameError(f"{path}: the WCS is mirrored; the camera frame must be right-handed")
    return Rotation.from_matrix(matrix), 1.0 / scale_rad, (float(crpix[0] - 1.0), float(crpix[1] - 1.0))


@dataclass(frozen=True)
class WcsHint:
    """What a frame's celestial TAN WCS says before any solve (:func:`wcs_hint`).

    Attributes
    ----------
    fov_deg : float
        Horizontal field of view of the WCS's pinhole camera, deg.
    R_icrf_cam : Rotation
        Camera -> ICRF attitude of the WCS.
    camera : Camera
        The WCS's pinhole camera (focal length and principal point; distortion-free).
    """

    fov_deg: float
    R_icrf_cam: Rotation
    camera: Camera

    def center_icrf(self) -> np.ndarray:
        """ICRF unit direction of the image centre, as the WCS places it."""
        camera = self.camera
        return self.R_icrf_cam.apply(camera.unproject(np.array([(camera.width_px - 1) / 2.0, (camera.height_px - 1) / 2.0])))


def has_celestial_tan_wcs(header) -> bool:
    """Whether ``CTYPE1/2`` name a celestial TAN projection (``RA---TAN``/``DEC--TAN``, ``-SIP`` allowed)."""
    if header is None:
        return False
    ctype1, ctype2 = (str(header.get(f"CTYPE{i}", "")).strip().upper() for i in (1, 2))
    return ctype1.startswith("RA--") and ctype2.startswith("DEC-") and ctype1[4:8] == "-TAN" and ctype2[4:8] == "-TAN"


def wcs_hint(header, shape: tuple[int, int], path: str) -> WcsHint | None:
    """The field of view and pointing of a frame's celestial TAN WCS; None without one.

    Parameters
    ----------
    header : mapping or None
        FITS header (``CTYPE1/2`` must be ``RA---TAN``/``DEC--TAN``, optionally ``-SIP``).
    shape : (int, int)
        Frame shape (rows, columns).
    path : str
        The file, for messages.

    Raises
    ------
    FrameError
        A TAN WCS whose keywords cannot be read or give no valid, right-handed CD matrix.
    """
    if not has_celestial_tan_wcs(header):
        return None
    rotation, f_px, (cx, cy) = wcs_attitude(header, path)
    camera = Camera(width_px=shape[1], height_px=shape[0], focal_length_mm=f_px * 10.0 / 1000.0, pixel_pitch_um=10.0,
                    cx_px=cx, cy_px=cy)
    fov_deg = math.degrees(camera.fov_x_rad)
    if not (0.0 < fov_deg < 120.0):
        raise FrameError(f"{path}: the WCS gives a {fov_deg:.4g} deg field of view; expected (0, 120) deg")
    return WcsHint(fov_deg, rotation, camera)


def detector_keywords(header, path: str, camera: Camera | None = None) -> dict[str, float]:
    """The detector of a frame: ``read_noise_e``, ``gain_e_per_adu``, ``bias_adu``, ``exposure_s``
    from ``RDNOISE``, ``GAIN``, ``BIASLVL``, ``EXPTIME``.

    A keyword absent (or ``EXPTIME = 0``) takes ``camera``'s value, or :data:`DETECTOR_DEFAULTS`
    without a camera.

    Raises
    ------
    FrameError
        A keyword that is not a finite number, a ``GAIN`` not positive, a ``RDNOISE`` or
        ``EXPTIME`` negative; the message names the file and the keyword.
    """
    fallback = DETECTOR_DEFAULTS if camera is None else {
        "GAIN": camera.gain_e_per_adu, "RDNOISE": camera.read_noise_e, "BIASLVL": camera.bias_adu,
        "EXPTIME": camera.exposure_s}
    values = {key: _number(header, key, path, fallback[key]) for key in ("RDNOISE", "GAIN", "BIASLVL", "EXPTIME")}
    if not values["GAIN"] > 0.0:
        raise FrameError(f"{path}: header keyword GAIN = {header['GAIN']!r} must be positive (e-/ADU)")
    for key in ("RDNOISE", "EXPTIME"):
        if values[key] < 0.0:
            raise FrameError(f"{path}: header keyword {key} = {header[key]!r} must not be negative")
    return {"read_noise_e": values["RDNOISE"], "gain_e_per_adu": values["GAIN"], "bias_adu": values["BIASLVL"],
            "exposure_s": values["EXPTIME"] or fallback["EXPTIME"]}


def camera_from_header(header, shape: tuple[int, int], path: str) -> Camera:
    """A pinhole camera matching the WCS (distortion-free) and the detector keywords (:func:`detector_keywords`)."""
    _, f_px, (cx, cy) = wcs_attitude(header, path)
    pitch_um = 10.0
    return Camera(
        width_px=shape[1], height_px=shape[0], focal_length_mm=f_px * pitch_um / 1000.0, pixel_pitch_um=pitch_um,
        cx_px=cx, cy_px=cy, **detector_keywords(header, path), camera_id=str(header.get("CAMERA", "opnav-cam")),
    )


def header_observer(header, t: float, path: str):
    """The observer state of ``OBS_X`` ... ``OBS_VZ`` (ICRF, solar-system barycentre, km, km/s) at
    ``t`` (TDB s past J2000), as an :class:`opnav.observer.Observer`."""
    from ..observer import Observer

    try:
        r = np.array([float(header[f"OBS_{a}"]) for a in "XYZ"])
        v = np.array([float(header[f"OBS_V{a}"]) for a in "XYZ"])
    except (KeyError, ValueError) as exc:
        raise FrameError(f"{path}: bad observer state in the header ({exc})") from None
    return Observer(t, r, v)
