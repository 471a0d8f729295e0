"""Frames on disk: FITS with a WCS header plus a truth JSON sidecar.

Header
------
The WCS maps pixels to the *apparent* (aberrated) RA/Dec of the frame epoch:

* ``CRPIX = (cx + 1, cy + 1)`` (principal point; FITS pixels are 1-based, docs/conventions.md),
  ``CRVAL`` = RA/Dec of the boresight, gnomonic projection (``RA---TAN``/``DEC--TAN``).
* ``CD = (180/pi) / f * [[X.E, Y.E], [X.N, Y.N]]`` where X, Y are the camera
  axes in ICRF, E and N the east and north unit vectors at the boresight and
  f the focal length in pixels. For a pinhole camera this TAN header is exact.
* With Brown distortion on, ``-SIP`` polynomials map a detector pixel offset
  (u, v) to the pinhole offset: they are fitted by least squares on a grid
  covering the detector to the camera's exact inverse distortion, the
  lowest order (3..9) whose largest residual is below ``SIP_TOLERANCE_PX`` is
  kept, the fitted linear part is folded into CD, and the inverse (AP, BP)
  polynomials are fitted the same way.

Other keywords: ``DATE-OBS`` (UTC, start of exposure), ``DATE-AVG`` (UTC,
mid-exposure), ``TDB_S`` (TDB s past J2000, mid-exposure, the truth epoch),
``EXPTIME`` (s), ``CAMERA``, ``OBS_X/Y/Z`` (km) and ``OBS_VX/VY/VZ`` (km/s) of the
observer relative to the SSB in ICRF, ``GAIN``, ``RDNOISE``, ``SATURATE``,
``OPNVFLAG`` (comma-separated frame flags).

Files: ``NAME.fits`` and ``NAME.truth.json`` side by side. Windowed frames
store each region of interest as an image extension with ``XORIGIN``/``YORIGIN``
(0-based full-frame pixel of the extension's first pixel) and its own WCS.
"""

from __future__ import annotations

import functools
import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..epochs import format_epoch, to_time
from ..errors import FrameError
from ..frames import unit_to_radec
from .truth import FrameTruth, truth_from_json, truth_to_json

#: Largest allowed difference between the SIP-distorted WCS and the camera model, px.
SIP_TOLERANCE_PX = 2.0e-3
_SIP_GRID = 41


@dataclass(frozen=True)
class Window:
    """A region of interest: ``image[0, 0]`` is full-frame pixel (``x0``, ``y0``)."""

    x0: int
    y0: int
    image: np.ndarray


@dataclass(frozen=True)
class StoredFrame:
    """A full frame read back from disk."""

    image: np.ndarray
    header: fits.Header
    truth: FrameTruth


@dataclass(frozen=True)
class StoredWindows:
    """A windowed frame read back from disk."""

    windows: tuple[Window, ...]
    header: fits.Header
    truth: FrameTruth


def _monomials(u: np.ndarray, v: np.ndarray, order: int, min_degree: int) -> tuple[list[tuple[int, int]], np.ndarray]:
    terms = [(p, q) for total in range(min_degree, order + 1) for p in range(total, -1, -1) for q in [total - p]]
    return terms, np.stack([u**p * v**q for p, q in terms], -1)


def _fit_poly(u: np.ndarray, v: np.ndarray, target: np.ndarray, order: int, min_degree: int, scale: float):
    terms, basis = _monomials(u / scale, v / scale, order, min_degree)
    coef, *_ = np.linalg.lstsq(basis, target, rcond=None)
    residual = basis @ coef - target
    factors = np.array([scale ** -(p + q) for p, q in terms])
    return terms, coef * factors[:, None], float(np.max(np.abs(residual)))


@functools.lru_cache(maxsize=16)
def sip_solution(camera: Camera) -> tuple[np.ndarray, dict[str, float], int]:
    """SIP fit for ``camera``: (linear 2x2 matrix folded into CD, SIP keywords, order).

    The keywords hold A/B (pixel -> pinhole) and AP/BP (inverse) coefficients.
    Raises ``FrameError`` if no order up to 9 reaches ``SIP_TOLERANCE_PX``.
    """
    xs = np.linspace(-0.5, camera.width_px - 0.5, _SIP_GRID)
    ys = np.linspace(-0.5, camera.height_px - 0.5, _SIP_GRID)
    gx, gy = np.meshgrid(xs, ys)
    u, v = gx.ravel() - camera.cx_px, gy.ravel() - camera.cy_px
    f = camera.focal_length_px
    xn, yn = camera._undistort(u / f, v / f)
    target = np.stack([xn * f, yn * f], -1)
    scale = max(camera.width_px, camera.height_px) / 2.0
    for order in range(3, 10):
        terms, coef, worst = _fit_poly(u, v, target, order, 1, scale)
        if worst < SIP_TOLERANCE_PX:
            break
    else:
        raise FrameError(f"camera {camera.camera_id!r}: SIP order 9 cannot represent the distortion to {SIP_TOLERANCE_PX} px (worst {worst:.3g} px)")
    linear = np.array([coef[terms.index((1, 0))], coef[terms.index((0, 1))]]).T
    inv_linear = np.linalg.inv(linear)
    keys: dict[str, float] = {"A_ORDER": order, "B_ORDER": order}
    for (p, q), c in zip(terms, coef):
        if p + q >= 2:
            ca, cb = inv_linear @ c
            keys[f"A_{p}_{q}"] = float(ca)
            keys[f"B_{p}_{q}"] = float(cb)
    # Inverse: SIP-linearised offsets U = u + A(u, v) -> detector offsets u.
    big_u = target @ inv_linear.T
    inv_order = min(order + 1, 9)
    inv_terms, inv_coef, _ = _fit_poly(big_u[:, 0], big_u[:, 1], np.stack([u, v], -1) - big_u, inv_order, 1, scale)
    keys["AP_ORDER"] = inv_order
    keys["BP_ORDER"] = inv_order
    for (p, q), c in zip(inv_terms, inv_coef):
        keys[f"AP_{p}_{q}"] = float(c[0])
        keys[f"BP_{p}_{q}"] = float(c[1])
    return linear, keys, order


def wcs_header(camera: Camera, R_icrf_cam: Rotation, *, origin_xy: tuple[int, int] = (0, 0)) -> fits.Header:
    """WCS keywords mapping pixels of ``camera`` to apparent RA/Dec (see module notes).

    ``origin_xy`` shifts CRPIX for a window whose first pixel is full-frame (x0, y0).
    """
    boresight = R_icrf_cam.apply([0.0, 0.0, 1.0])
    ra0, dec0 = (float(a) for a in unit_to_radec(boresight))
    east = np.array([-math.sin(ra0), math.cos(ra0), 0.0])
    north = np.array([-math.sin(dec0) * math.cos(ra0), -math.sin(dec0) * math.sin(ra0), math.cos(dec0)])
    axis_x = R_icrf_cam.apply([1.0, 0.0, 0.0])
    axis_y = R_icrf_cam.apply([0.0, 1.0, 0.0])
    cd = math.degrees(1.0) / camera.focal_length_px * np.array(
        [[axis_x @ east, axis_y @ east], [axis_x @ north, axis_y @ north]]
    )
    header = fits.Header()
    header["WCSAXES"] = 2
    header["CRPIX1"] = camera.cx_px + 1.0 - origin_xy[0]
    header["CRPIX2"] = camera.cy_px + 1.0 - origin_xy[1]
    header["CRVAL1"] = math.degrees(ra0)
    header["CRVAL2"] = math.degrees(dec0)
    header["CUNIT1"] = "deg"
    header["CUNIT2"] = "deg"
    header["RADESYS"] = "ICRS"
    header["LONPOLE"] = 180.0
    if camera.has_distortion:
        linear, sip_keys, _ = sip_solution(camera)
        cd = cd @ linear
        header["CTYPE1"] = "RA---TAN-SIP"
        header["CTYPE2"] = "DEC--TAN-SIP"
    else:
        header["CTYPE1"] = "RA---TAN"
        header["CTYPE2"] = "DEC--TAN"
    for i in range(2):
        for j in range(2):
            header[f"CD{i + 1}_{j + 1}"] = float(cd[i, j])
    if camera.has_distortion:
        for key, value in sip_keys.items():
            header[key] = value
    return header


def frame_header(camera: Camera, truth: FrameTruth, *, origin_xy: tuple[int, int] = (0, 0)) -> fits.Header:
    """Full header (WCS + epoch, exposure, observer state, detector) for a frame."""
    header = wcs_header(camera, truth.R_icrf_cam, origin_xy=origin_xy)
    t_mid = truth.t_tdb_s
    header["DATE-OBS"] = (format_epoch(t_mid - 0.5 * truth.exposure_s, "utc", 6), "UTC, start of exposure")
    header["DATE-AVG"] = (format_epoch(t_mid, "utc", 6), "UTC, mid-exposure")
    header["MJD-OBS"] = (float(to_time(t_mid - 0.5 * truth.exposure_s).utc.mjd), "UTC MJD, start of exposure")
    header["MJD-AVG"] = (float(to_time(t_mid).utc.mjd), "UTC MJD, mid-exposure")
    header["TIMESYS"] = "UTC"
    header["TDB_S"] = (t_mid, "TDB s past J2000, mid-exposure")
    header["EXPTIME"] = (truth.exposure_s, "s")
    header["CAMERA"] = truth.camera_id
    for axis, r, v in zip("XYZ", truth.r_observer_ssb_km, truth.v_observer_ssb_km_s):
        header[f"OBS_{axis}"] = (float(r), "km, observer wrt SSB, ICRF")
        header[f"OBS_V{axis}"] = (float(v), "km/s, observer wrt SSB, ICRF")
    header["GAIN"] = (camera.gain_e_per_adu, "e-/ADU")
    header["RDNOISE"] = (camera.read_noise_e, "e- RMS")
    header["BIASLVL"] = (camera.bias_adu, "ADU")
    header["SATURATE"] = (saturation_level_adu(camera), "ADU, lowest reading of a saturated pixel")
    header["OPNVFLAG"] = (",".join(truth.flags), "frame flags")
    return header


def saturation_level_adu(camera: Camera) -> float:
    """Lowest ADU a saturated pixel can read, for the FITS ``SATURATE`` keyword.

    Charge is clipped at the full well *before* read noise is added, so a full
    pixel reads ``full_well / gain + bias`` give or take the read noise: half of
    them fall below that level. ``SATURATE`` is therefore set 5 read-noise sigmas
    lower, unless the ADC clips first (its ceiling is then exact).
    """
    adc_max = float(2**camera.bit_depth - 1)
    full = camera.full_well_e / camera.gain_e_per_adu + camera.bias_adu
    if full >= adc_max:
        return adc_max
    return full - 5.0 * camera.read_noise_e / camera.gain_e_per_adu


def _truth_path(path: Path) -> Path:
    name = path.name
    for suffix in (".fits", ".fit", ".fts"):
        if name.endswith(suffix):
            name = name[: -len(suffix)]
    return path.with_name(name + ".truth.json")


def _write_truth(path: Path, truth: FrameTruth) -> Path:
    truth_path = _truth_path(path)
    truth_path.write_text(json.dumps(truth_to_json(truth), indent=1, allow_nan=False))
    return truth_path


def write_frame(path: str | Path, image: np.ndarray, header: fits.Header, truth: FrameTruth) -> tuple[Path, Path]:
    """Write ``image`` with ``header`` to ``path`` (FITS, with checksums) and the truth sidecar.

    Returns the FITS and JSON paths.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fits.PrimaryHDU(np.asarray(image), header=header).writeto(path, overwrite=True, checksum=True)
    return path, _write_truth(path, truth)


def write_windows(path: str | Path, windows: tuple[Window, ...], camera: Camera, truth: FrameTruth) -> tuple[Path, Path]:
    """Write a windowed frame: an empty primary HDU plus one image extension per window."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    primary = fits.PrimaryHDU(header=frame_header(camera, truth))
    primary.header["NWINDOWS"] = len(windows)
    hdus = [primary]
    for window in windows:
        header = frame_header(camera, truth, origin_xy=(window.x0, window.y0))
        header["XORIGIN"] = (window.x0, "full-frame column of first pixel (0-based)")
        header["YORIGIN"] = (window.y0, "full-frame row of first pixel (0-based)")
        hdus.append(fits.ImageHDU(np.asarray(window.image), header=header))
    fits.HDUList(hdus).writeto(path, overwrite=True, checksum=True)
    return path, _write_truth(path, truth)


def _open_checked(path: Path) -> list[tuple[fits.Header, np.ndarray | None]]:
    if not path.is_file():
        raise FrameError(f"frame file not found: {path}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with fits.open(path, checksum=True, memmap=False) as hdul:
                hdul.verify("exception")
                return [(hdu.header.copy(), None if hdu.data is None else np.array(hdu.data)) for hdu in hdul]
    except Exception as exc:  # astropy raises OSError, ValueError, VerifyError and warnings alike
        raise FrameError(f"{path}: unreadable or corrupt FITS ({type(exc).__name__}: {exc})") from None


def _read_truth(path: Path) -> FrameTruth:
    truth_path = _truth_path(path)
    if not truth_path.is_file():
        raise FrameError(f"truth sidecar not found: {truth_path}")
    try:
        data = json.loads(truth_path.read_text())
    except (OSError, ValueError) as exc:
        raise FrameError(f"{truth_path}: unreadable truth JSON ({exc})") from None
    return truth_from_json(data, source=str(truth_path))


def read_frame(path: str | Path) -> StoredFrame:
    """Read a full frame and its truth; ``FrameError`` for a missing, truncated or corrupt file."""
    path = Path(path)
    hdus = _open_checked(path)
    header, image = hdus[0]
    if image is None or image.ndim != 2:
        raise FrameError(f"{path}: primary HDU holds no 2-D image (windowed file? use read_windows)")
    return StoredFrame(image=image, header=header, truth=_read_truth(path))


def read_windows(path: str | Path) -> StoredWindows:
    """Read a windowed frame written by :func:`write_windows`."""
    path = Path(path)
    hdus = _open_checked(path)
    if "NWINDOWS" not in hdus[0][0] or len(hdus) - 1 != hdus[0][0]["NWINDOWS"]:
        raise FrameError(f"{path}: not a windowed opnav frame (NWINDOWS missing or wrong)")
    windows = tuple(Window(int(h["XORIGIN"]), int(h["YORIGIN"]), data) for h, data in hdus[1:])
    return StoredWindows(windows=windows, header=hdus[0][0], truth=_read_truth(path))


def header_wcs(header: fits.Header) -> WCS:
    """astropy ``WCS`` of a frame header (SIP included when present)."""
    return WCS(header, relax=True)
