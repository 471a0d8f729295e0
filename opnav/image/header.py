"""The FITS header of a frame to what the image stage and the plate solver need: the one place that reads it.

Epoch (:func:`header_epoch`), mid-exposure, TDB s past J2000, the first of:

1. ``TDB_S`` (opnav's own, TDB s past J2000, mid-exposure);
2. ``DATE-AVG`` (mid-exposure);
3. ``DATE-OBS`` + ``EXPTIME / 2``: ``DATE-OBS`` is the *start* of the exposure (FITS 4.0,
   section 9.4.1, and what :mod:`opnav.render.frames_io` writes), so half the exposure is added
   (nothing without ``EXPTIME``).

Dates are in the scale ``TIMESYS`` names (UTC when absent, the FITS default; UTC, TT, TDB or
TAI). The header must agree with itself and with the sky: every epoch keyword present (``TDB_S``,
``DATE-AVG``, ``MJD-AVG``, ``DATE-OBS`` or ``MJD-OBS`` + ``EXPTIME / 2``) within
:data:`EPOCH_AGREEMENT_S` + ``EXPTIME / 2`` of the one used (a writer that stamps the middle of the
exposure as ``DATE-OBS`` still agrees), and the epoch inside :data:`EPOCH_SPAN_TDB_S`; a header that
does not is refused with a :class:`~opnav.errors.FrameError` naming the file and the keywords. The
a-priori attitude (camera -> ICRF) and a pinhole camera come from the TAN WCS
(:func:`wcs_attitude`, :func:`wcs_hint`: ``CDi_j``, else ``PCi_j`` x ``CDELTi`` or ``CROTA2``,
with ``CRVAL``/``CRPIX``; SIP terms, if any, are left out: the hint is the linear part; a frame
without ``CTYPE1/2 = 'RA---TAN'/'DEC--TAN'``, ``CRVAL1/2`` and a scale has no a-priori attitude, and
:func:`wcs_attitude` says so instead of reading absent keywords as 0 and 1 deg/px); detector
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
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..constants import C_KM_S
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


#: The epochs a frame may carry, TDB s past J2000: from 1957-10-04 (Sputnik 1: no spacecraft frame is
#: older) to 2100-01-01 (the catalog's Hipparcos J1991.25 and Gaia J2016.0 positions carried more than
#: ~85 years; DE421, the default ephemeris, ends in 2053 and refuses later dates itself).
EPOCH_SPAN_TDB_S = (-1_332_115_200.0, 3_155_716_800.0)
#: How far the header's epoch keywords may disagree beyond half the exposure, s (a writer rounding
#: ``DATE-OBS`` to the second agrees; a date one day off does not).
EPOCH_AGREEMENT_S = 1.0


def _date(header, key: str, path: str) -> float:
    from ..epochs import parse_epoch  # astropy.time only for a date its fast exact path does not read

    try:
        with warnings.catch_warnings():
            # ERFA's "dubious year" for a date outside its leap-second table: the span check refuses those
            warnings.simplefilter("ignore")
            return float(parse_epoch(str(header[key]).strip(), time_scale(header, path)))
    except InputError as exc:
        raise FrameError(f"{path}: header keyword {key}: {exc}") from None


def _mjd(header, key: str, path: str) -> float:
    """``key`` (a modified Julian date in the ``TIMESYS`` scale) as TDB s past J2000."""
    from ..epochs import mjd_tdb_seconds  # astropy's Time(mjd, format="mjd"), without astropy where exact

    mjd = _number(header, key, path)
    # far outside the span: refused before astropy's calendar, which warns about "dubious years" there
    if not -30_000.0 < mjd < 150_000.0:
        raise FrameError(f"{path}: header keyword {key} = {mjd!r} is not a modified Julian date of a spacecraft frame "
                         f"(1957 to 2100: MJD 36115 to 88069)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # ERFA's "dubious year" for dates past the leap-second table
        return mjd_tdb_seconds(mjd, time_scale(header, path))


def _epoch_candidates(header, path: str) -> list[tuple[str, float]]:
    """The epoch :func:`header_epoch` uses (the first of ``TDB_S``, ``DATE-AVG``, ``DATE-OBS`` +
    ``EXPTIME / 2``) followed by every other the header states (``MJD-AVG``, ``MJD-OBS`` too), as
    (keywords, TDB s past J2000). Without ``EXPTIME`` a start (``DATE-OBS``, ``MJD-OBS``) and a
    middle of the exposure cannot be compared, so only those of the used one's kind follow it."""
    exposure = _number(header, "EXPTIME", path, 0.0)
    if exposure < 0.0:
        raise FrameError(f"{path}: header keyword EXPTIME = {exposure!r} is negative")
    mids, starts = [], []
    if "TDB_S" in header:
        mids.append(("TDB_S", _number(header, "TDB_S", path)))
    if "DATE-AVG" in header:
        mids.append(("DATE-AVG", _date(header, "DATE-AVG", path)))
    if "DATE-OBS" in header:
        starts.append(("DATE-OBS + EXPTIME/2", _date(header, "DATE-OBS", path) + 0.5 * exposure))
    if "MJD-AVG" in header:
        mids.append(("MJD-AVG", _mjd(header, "MJD-AVG", path)))
    if "MJD-OBS" in header:
        starts.append(("MJD-OBS + EXPTIME/2", _mjd(header, "MJD-OBS", path) + 0.5 * exposure))
    used_mid = bool(mids) and mids[0][0] != "MJD-AVG"
    if "EXPTIME" in header:
        return mids + starts if used_mid else starts + mids
    return mids if used_mid else starts


def _agree(candidates: list[tuple[str, float]], path: str, tolerance: float) -> None:
    """Refuse epoch keywords that disagree with the first by more than ``tolerance`` s."""
    key, t = candidates[0]
    for other, t_other in candidates[1:]:
        if not abs(t_other - t) <= tolerance:
            raise FrameError(f"{path}: header keywords {key} and {other} disagree by {t_other - t:.6g} s "
                             f"(at most {tolerance:.6g} s: {EPOCH_AGREEMENT_S:g} s + EXPTIME/2); "
                             "correct or delete the wrong one")


def has_epoch(header) -> bool:
    """Whether the header carries an epoch keyword (``TDB_S``, ``DATE-AVG`` or ``DATE-OBS``)."""
    return header is not None and any(key in header for key in ("TDB_S", "DATE-AVG", "DATE-OBS"))


def header_epoch(header, path: str) -> float:
    """Mid-exposure epoch, TDB s past J2000 (module docstring: ``TDB_S``, ``DATE-AVG``, ``DATE-OBS`` + ``EXPTIME/2``).

    Raises
    ------
    FrameError
        No epoch keyword, or one (or ``TIMESYS``, ``EXPTIME``, ``MJD-AVG``, ``MJD-OBS``) that cannot
        be read; an epoch outside :data:`EPOCH_SPAN_TDB_S`; two epoch keywords that disagree by more
        than :data:`EPOCH_AGREEMENT_S` + ``EXPTIME / 2``. The message names the file and the keywords.
    """
    from ..epochs import describe_epoch

    if not has_epoch(header):
        raise FrameError(f"{path}: no epoch in the header (TDB_S, DATE-AVG or DATE-OBS)")
    candidates = _epoch_candidates(header, path)
    key, t = candidates[0]
    if not EPOCH_SPAN_TDB_S[0] <= t <= EPOCH_SPAN_TDB_S[1]:
        raise FrameError(f"{path}: header keyword {key.split(' ')[0]} gives {describe_epoch(t)}; a frame's epoch is "
                         "from 1957-10-04 (the first spacecraft) to 2100-01-01 (the star catalog's reach)")
    _agree(candidates, path, EPOCH_AGREEMENT_S + 0.5 * _number(header, "EXPTIME", path, 0.0))
    return t


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
    """``(CD (2, 2) deg/px, CRVAL1, CRVAL2 deg, CRPIX (2,) 1-based)`` of the header's celestial WCS.

    A header without a celestial TAN ``CTYPE1/2``, ``CRVAL1/2`` or a scale (``CDi_j`` or
    ``CDELT1/2``) is refused: read as 0 and 1 deg/px, the absent keywords made a field of view of a
    thousand degrees, whose star catalogue filled tens of gigabytes.
    """
    if not has_celestial_tan_wcs(header):
        got = ", ".join(f"CTYPE{i} = {header[f'CTYPE{i}']!r}" for i in (1, 2) if f"CTYPE{i}" in header) or "none"
        raise FrameError(f"{path}: no celestial TAN WCS in the header (CTYPE1/CTYPE2 = 'RA---TAN'/'DEC--TAN', "
                         f"'-SIP' allowed; got {got}); the a-priori attitude comes from it")
    has_cd = any(f"CD{i}_{j}" in header for i in (1, 2) for j in (1, 2))
    missing = [key for key in ("CRVAL1", "CRVAL2", "CRPIX1", "CRPIX2") + (() if has_cd else ("CDELT1", "CDELT2"))
               if key not in header]
    if missing:
        raise FrameError(f"{path}: the header's WCS lacks {', '.join(missing)} (a TAN WCS needs CRVAL1/2, CRPIX1/2 "
                         "and CDi_j or CDELT1/2)")
    if not -90.0 <= _number(header, "CRVAL2", path) <= 90.0:
        raise FrameError(f"{path}: header keyword CRVAL2 = {header['CRVAL2']!r} is not a declination "
                         "(-90 to 90 deg)")
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
    # no pixel spans more than 180 deg; bounded, the products below stay finite
    if not np.all(np.abs(cd) <= 180.0) or abs(np.linalg.det(cd)) == 0.0:
        raise FrameError(f"{path}: the WCS has no valid CD matrix (CDi_j, or PCi_j x CDELTi: finite, at most "
                         "180 deg a pixel, not singular)")
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
    """A pinhole camera matching the WCS (distortion-free) and the detector keywords (:func:`detector_keywords`).

    Raises
    ------
    FrameError
        No usable TAN WCS (:func:`wcs_attitude`), a WCS whose field of view is not in (0, 120) deg,
        or a detector keyword that cannot be read.
    """
    _, f_px, (cx, cy) = wcs_attitude(header, path)
    pitch_um = 10.0
    fov_deg = math.degrees(2.0 * math.atan(0.5 * shape[1] / f_px))
    if not (0.0 < fov_deg < 120.0):
        raise FrameError(f"{path}: the WCS gives a {fov_deg:.4g} deg field of view; expected (0, 120) deg")
    return Camera(
        width_px=shape[1], height_px=shape[0], focal_length_mm=f_px * pitch_um / 1000.0, pixel_pitch_um=pitch_um,
        cx_px=cx, cy_px=cy, **detector_keywords(header, path), camera_id=str(header.get("CAMERA", "opnav-cam")),
    )


#: Farthest observer a header may place, km from the solar-system barycentre: 670 AU, four times
#: Voyager 1's distance in 2026 (a larger one is a wrong header, and its squares near overflow).
MAX_OBSERVER_DISTANCE_KM = 1e11


def _magnitude(vector: np.ndarray) -> float:
    """The length of ``vector`` without overflowing its squares (math.hypot scales)."""
    return math.hypot(*vector)


def header_observer(header, t: float, path: str):
    """The observer state of ``OBS_X`` ... ``OBS_VZ`` (ICRF, solar-system barycentre, km, km/s) at
    ``t`` (TDB s past J2000), as an :class:`opnav.observer.Observer`."""
    from ..observer import Observer

    r = header_vector(header, ("OBS_X", "OBS_Y", "OBS_Z"), path)
    v = header_vector(header, ("OBS_VX", "OBS_VY", "OBS_VZ"), path)
    if r is None or v is None:
        raise FrameError(f"{path}: the header's observer state needs all of OBS_X, OBS_Y, OBS_Z, OBS_VX, OBS_VY, OBS_VZ")
    if not np.all(np.abs(v) < 0.01 * C_KM_S) or not np.linalg.norm(v) < 0.01 * C_KM_S:
        # the fastest spacecraft (Parker Solar Probe) reach ~190 km/s: 3000 km/s is a wrong header, not a flight
        raise FrameError(f"{path}: header keywords OBS_VX/VY/VZ give {_magnitude(v):.6g} km/s; a spacecraft "
                         f"moves below {0.01 * C_KM_S:.0f} km/s (1 % of the speed of light)")
    if not np.all(np.abs(r) < MAX_OBSERVER_DISTANCE_KM) or not np.linalg.norm(r) < MAX_OBSERVER_DISTANCE_KM:
        raise FrameError(f"{path}: header keywords OBS_X/Y/Z put the observer {_magnitude(r):.6g} km from the "
                         f"solar-system barycentre; at most {MAX_OBSERVER_DISTANCE_KM:.0e} km")
    return Observer(t, r, v)
