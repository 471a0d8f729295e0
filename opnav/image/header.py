"""The FITS header of a frame to what the image stage needs (:mod:`opnav.image.pipeline`, step 1).

The epoch is ``TDB_S`` (else ``DATE-AVG``/``DATE-OBS`` with ``TIMESYS``, UTC by default); the
a-priori attitude (camera -> ICRF) and a pinhole camera come from the TAN WCS; detector gain,
read noise, bias and exposure from ``GAIN``, ``RDNOISE``, ``BIASLVL``, ``EXPTIME``; the
a-priori observer state (ICRF, solar-system barycentre, km and km/s) from ``OBS_X`` ...
``OBS_VZ``. Headers written by :mod:`opnav.render.frames_io` carry all of them.
"""

from __future__ import annotations

import math

import numpy as np
from astropy.wcs import WCS
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..epochs import parse_epoch
from ..errors import FrameError
from ..frames import radec_to_unit


def header_epoch(header, path: str) -> float:
    """Mid-exposure epoch (TDB s past J2000) from ``TDB_S`` or ``DATE-AVG``/``DATE-OBS``+``EXPTIME``."""
    if "TDB_S" in header:
        return float(header["TDB_S"])
    if "DATE-AVG" in header:
        return float(parse_epoch(str(header["DATE-AVG"]), header.get("TIMESYS", "utc").lower()))
    if "DATE-OBS" in header:
        start = float(parse_epoch(str(header["DATE-OBS"]), header.get("TIMESYS", "utc").lower()))
        return start + 0.5 * float(header.get("EXPTIME", 0.0))
    raise FrameError(f"{path}: no epoch in the header (TDB_S, DATE-AVG or DATE-OBS)")


def wcs_attitude(header, path: str) -> tuple[Rotation, float, tuple[float, float]]:
    """A-priori attitude (camera -> ICRF), focal length (px) and principal point from a TAN WCS.

    At the reference pixel the TAN projection's tangent plane holds the camera's x and y axes:
    column j of CD gives d(east, north)/d(pixel j) in degrees.
    """
    try:
        wcs = WCS(header, relax=True, naxis=2)
        cd = wcs.wcs.cd if wcs.wcs.has_cd() else wcs.wcs.get_pc() * wcs.wcs.cdelt[:, None]
        ra0, dec0 = (math.radians(v) for v in wcs.wcs.crval)
        crpix = wcs.wcs.crpix
    except Exception as exc:  # noqa: BLE001 - astropy raises several types for bad WCS keywords
        raise FrameError(f"{path}: no usable WCS in the header ({exc})") from None
    if not np.all(np.isfinite(cd)) or abs(np.linalg.det(cd)) == 0.0:
        raise FrameError(f"{path}: the WCS has no valid CD matrix")
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


def camera_from_header(header, shape: tuple[int, int], path: str) -> Camera:
    """A pinhole camera matching the WCS (distortion-free) and the detector keywords."""
    _, f_px, (cx, cy) = wcs_attitude(header, path)
    pitch_um = 10.0
    return Camera(
        width_px=shape[1], height_px=shape[0], focal_length_mm=f_px * pitch_um / 1000.0, pixel_pitch_um=pitch_um,
        cx_px=cx, cy_px=cy, gain_e_per_adu=float(header.get("GAIN", 1.0)),
        read_noise_e=float(header.get("RDNOISE", 5.0)), bias_adu=float(header.get("BIASLVL", 0.0)),
        exposure_s=float(header.get("EXPTIME", 1.0)) or 1.0, camera_id=str(header.get("CAMERA", "opnav-cam")),
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
