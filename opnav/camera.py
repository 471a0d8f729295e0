"""Camera model: pinhole projection with Brown distortion, plus detector parameters.

Conventions (docs/conventions.md): camera frame +z along the boresight, +x along
increasing column, +y along increasing row. Pixel (0, 0) is the *centre* of the
first pixel; x is the column, y the row. Attitude is a
``scipy.spatial.transform.Rotation`` taking camera-frame vectors to ICRF
(``R_icrf_cam``).

Projection of a camera-frame direction (X, Y, Z), Z > 0::

    x_n, y_n = X/Z, Y/Z                                  (normalised image plane)
    r^2      = x_n^2 + y_n^2
    radial   = 1 + k1 r^2 + k2 r^4 + k3 r^6
    x_d      = x_n radial + 2 p1 x_n y_n + p2 (r^2 + 2 x_n^2)
    y_d      = y_n radial + p1 (r^2 + 2 y_n^2) + 2 p2 x_n y_n
    x, y     = cx + f x_d, cy + f y_d                    (f in pixels)

This is the Brown–Conrady model in OpenCV's parameter order. The inverse uses
Newton iterations on the 2x2 distortion Jacobian, converged far below 1e-6 px.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError


#: Narrowest field of view accepted, arcsec across the longer side (narrow-angle OpNav cameras: ~1000").
MIN_FIELD_ARCSEC = 10.0


@dataclass(frozen=True)
class Camera:
    """A frame camera: optics, distortion and detector electronics.

    Parameters
    ----------
    width_px, height_px : int
        Detector size (columns, rows).
    focal_length_mm : float
        Effective focal length.
    pixel_pitch_um : float
        Pixel size (square pixels).
    cx_px, cy_px : float, optional
        Principal point in pixels; default the detector centre ((w-1)/2, (h-1)/2).
    k1, k2, k3, p1, p2 : float
        Brown radial (k) and tangential (p) coefficients on the normalised plane. Default 0.
    aperture_mm : float
        Entrance-pupil diameter (default 50 mm).
    throughput : float
        Optical transmission, 0..1 (default 0.8).
    qe : float
        Mean quantum efficiency over the band, 0..1 (default 0.6).
    gain_e_per_adu : float
        Electrons per ADU (default 1.0).
    read_noise_e : float
        RMS read noise per pixel, electrons (default 5).
    dark_current_e_s : float
        Dark current per pixel, electrons/s (default 1).
    full_well_e : float
        Full-well capacity, electrons (default 60000).
    bit_depth : int
        ADC bits (default 16).
    bias_adu : float
        Offset added by the ADC, ADU (default 100).
    exposure_s : float
        Exposure time, s (default 0.5).
    camera_id : str
        Name written to FITS headers and truth files.
    """

    width_px: int
    height_px: int
    focal_length_mm: float
    pixel_pitch_um: float
    cx_px: float | None = None
    cy_px: float | None = None
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    aperture_mm: float = 50.0
    throughput: float = 0.8
    qe: float = 0.6
    gain_e_per_adu: float = 1.0
    read_noise_e: float = 5.0
    dark_current_e_s: float = 1.0
    full_well_e: float = 60_000.0
    bit_depth: int = 16
    bias_adu: float = 100.0
    exposure_s: float = 0.5
    camera_id: str = "opnav-cam"

    def __post_init__(self) -> None:
        if self.cx_px is None:
            object.__setattr__(self, "cx_px", (self.width_px - 1) / 2.0)
        if self.cy_px is None:
            object.__setattr__(self, "cy_px", (self.height_px - 1) / 2.0)
        positive = {
            "width_px": self.width_px,
            "height_px": self.height_px,
            "focal_length_mm": self.focal_length_mm,
            "pixel_pitch_um": self.pixel_pitch_um,
            "aperture_mm": self.aperture_mm,
            "gain_e_per_adu": self.gain_e_per_adu,
            "full_well_e": self.full_well_e,
            "bit_depth": self.bit_depth,
            "exposure_s": self.exposure_s,
        }
        for name, value in positive.items():
            if not (isinstance(value, (int, float, np.number)) and math.isfinite(value) and value > 0):
                raise InputError(f"camera {name} must be a positive finite number, got {value!r}")
        for name in ("throughput", "qe"):
            value = getattr(self, name)
            if not (0.0 < value <= 1.0):
                raise InputError(f"camera {name} must be in (0, 1], got {value!r}")
        for name in ("read_noise_e", "dark_current_e_s", "bias_adu", "k1", "k2", "k3", "p1", "p2", "cx_px", "cy_px"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise InputError(f"camera {name} must be finite, got {value!r}")
        if self.read_noise_e < 0 or self.dark_current_e_s < 0:
            raise InputError("camera read_noise_e and dark_current_e_s must be >= 0")
        field_arcsec = math.degrees(2.0 * math.atan(0.5 * max(self.width_px, self.height_px) * self.pixel_pitch_um
                                                    / (1000.0 * self.focal_length_mm))) * 3600.0
        if field_arcsec < MIN_FIELD_ARCSEC:
            # a sub-arcsecond field turns every resolved body into billions of pixels of ray tracing
            raise InputError(f"camera focal_length_mm {self.focal_length_mm!r} with pixel_pitch_um "
                             f"{self.pixel_pitch_um!r} gives a {field_arcsec:.3g}\" field of view; "
                             f"at least {MIN_FIELD_ARCSEC:g}\" is accepted")

    # ---- derived quantities -------------------------------------------------
    @property
    def focal_length_px(self) -> float:
        """Focal length in pixels."""
        return self.focal_length_mm * 1000.0 / self.pixel_pitch_um

    @property
    def shape(self) -> tuple[int, int]:
        """Image array shape (rows, columns)."""
        return (self.height_px, self.width_px)

    @property
    def has_distortion(self) -> bool:
        return any(getattr(self, k) != 0.0 for k in ("k1", "k2", "k3", "p1", "p2"))

    @property
    def fov_x_rad(self) -> float:
        """Full field of view across the columns (pinhole, centre to edges), rad."""
        return 2.0 * math.atan(self.width_px / 2.0 / self.focal_length_px)

    @property
    def fov_y_rad(self) -> float:
        """Full field of view across the rows, rad."""
        return 2.0 * math.atan(self.height_px / 2.0 / self.focal_length_px)

    @property
    def half_diagonal_fov_rad(self) -> float:
        """Angle from the boresight to a detector corner (pinhole), rad."""
        return math.atan(math.hypot(self.width_px, self.height_px) / 2.0 / self.focal_length_px)

    @property
    def pixel_scale_rad(self) -> float:
        """Angular size of one pixel at the boresight, rad."""
        return 1.0 / self.focal_length_px

    @classmethod
    def from_fov(cls, fov_x_deg: float, width_px: int, height_px: int, *, pixel_pitch_um: float = 5.5, **kwargs) -> "Camera":
        """A camera with the given horizontal field of view (deg) across ``width_px`` columns."""
        if not (0.0 < fov_x_deg < 180.0):
            raise InputError(f"field of view must be in (0, 180) deg, got {fov_x_deg!r}")
        f_px = width_px / 2.0 / math.tan(math.radians(fov_x_deg) / 2.0)
        return cls(width_px, height_px, f_px * pixel_pitch_um / 1000.0, pixel_pitch_um, **kwargs)

    def replace(self, **changes) -> "Camera":
        """A copy with fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    # ---- geometry -----------------------------------------------------------
    def _distort(self, xn: np.ndarray, yn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xd = xn * radial + 2.0 * self.p1 * xn * yn + self.p2 * (r2 + 2.0 * xn * xn)
        yd = yn * radial + self.p1 * (r2 + 2.0 * yn * yn) + 2.0 * self.p2 * xn * yn
        return xd, yd

    def _distortion_jacobian(self, xn: np.ndarray, yn: np.ndarray) -> np.ndarray:
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        d_radial_d_r2 = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2)
        dxd_dx = radial + 2.0 * xn * xn * d_radial_d_r2 + 2.0 * self.p1 * yn + 6.0 * self.p2 * xn
        dxd_dy = 2.0 * xn * yn * d_radial_d_r2 + 2.0 * self.p1 * xn + 2.0 * self.p2 * yn
        dyd_dx = 2.0 * xn * yn * d_radial_d_r2 + 2.0 * self.p1 * xn + 2.0 * self.p2 * yn
        dyd_dy = radial + 2.0 * yn * yn * d_radial_d_r2 + 6.0 * self.p1 * yn + 2.0 * self.p2 * xn
        return np.stack([np.stack([dxd_dx, dxd_dy], -1), np.stack([dyd_dx, dyd_dy], -1)], -2)

    def _undistort(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xn, yn = xd.copy(), yd.copy()
        if not self.has_distortion:
            return xn, yn
        for _ in range(20):
            fx, fy = self._distort(xn, yn)
            jac = self._distortion_jacobian(xn, yn)
            residual = np.stack([fx - xd, fy - yd], -1)
            step = np.linalg.solve(jac, residual[..., None])[..., 0]
            xn = xn - step[..., 0]
            yn = yn - step[..., 1]
            if np.all(np.abs(step) < 1e-15):
                break
        return xn, yn

    def project(self, direction_cam: np.ndarray) -> np.ndarray:
        """Camera-frame direction(s) (..., 3) -> pixel (x, y) (..., 2).

        Directions with Z <= 0 (behind the camera) give NaN pixels.
        """
        d = np.asarray(direction_cam, dtype=float)
        z = d[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = np.where(z > 0, d[..., 0] / z, np.nan)
            yn = np.where(z > 0, d[..., 1] / z, np.nan)
        xd, yd = self._distort(xn, yn)
        f = self.focal_length_px
        return np.stack([self.cx_px + f * xd, self.cy_px + f * yd], -1)

    def unproject(self, xy: np.ndarray) -> np.ndarray:
        """Pixel (x, y) (..., 2) -> unit direction(s) in the camera frame (..., 3)."""
        xy = np.asarray(xy, dtype=float)
        f = self.focal_length_px
        xn, yn = self._undistort((xy[..., 0] - self.cx_px) / f, (xy[..., 1] - self.cy_px) / f)
        d = np.stack([xn, yn, np.ones_like(xn)], -1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def projection_jacobian(self, direction_cam: np.ndarray) -> np.ndarray:
        """d(x, y)/d(X, Y, Z) of :meth:`project`, shape (..., 2, 3), pixels per unit."""
        d = np.asarray(direction_cam, dtype=float)
        z = d[..., 2]
        xn, yn = d[..., 0] / z, d[..., 1] / z
        d_norm = np.zeros(d.shape[:-1] + (2, 3))
        d_norm[..., 0, 0] = 1.0 / z
        d_norm[..., 0, 2] = -xn / z
        d_norm[..., 1, 1] = 1.0 / z
        d_norm[..., 1, 2] = -yn / z
        return self.focal_length_px * self._distortion_jacobian(xn, yn) @ d_norm

    def in_frame(self, xy: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Boolean mask: pixel positions (..., 2) lie on the detector, ``margin_px`` from the edges."""
        xy = np.asarray(xy, dtype=float)
        x, y = xy[..., 0], xy[..., 1]
        lo = -0.5 + margin_px
        with np.errstate(invalid="ignore"):
            return (x >= lo) & (y >= lo) & (x <= self.width_px - 0.5 - margin_px) & (y <= self.height_px - 0.5 - margin_px)


# ---- camera files (docs/formats/camera.md) ------------------------------------
#: The tables a camera file may hold.
CAMERA_FILE_TABLES = ("camera", "calibration")
#: Parameters a ``[calibration]`` table may list (:mod:`opnav.image.calibration`): ``f``, ``cx``, ``cy`` in px.
CALIBRATION_PARAMETERS = ("f", "cx", "cy", "k1", "k2", "k3", "p1", "p2")


@dataclass(frozen=True)
class CameraCovariance:
    """What a calibration knows of a camera's parameters (a camera file's ``[calibration]`` table).

    Attributes
    ----------
    names : tuple of str
        Fitted parameters (:data:`CALIBRATION_PARAMETERS`): ``f`` focal length, ``cx``, ``cy``
        principal point, all px; Brown ``k1 k2 k3 p1 p2`` dimensionless.
    covariance : ndarray, shape (P, P)
        Their covariance (units of the parameters squared).
    summary : dict
        The table's other keys as written (model, frames, stars, chi-square per dof, RMS, date).
    """

    names: tuple[str, ...]
    covariance: np.ndarray
    summary: dict

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))


@dataclass(frozen=True)
class CameraFile:
    """A camera file read (:func:`read_camera_file`): the camera and, when calibrated, its covariance."""

    camera: Camera
    calibration: CameraCovariance | None = None


def _calibration_table(table, path: str) -> CameraCovariance:
    where = f"{path}: [calibration]"
    if not isinstance(table, dict):
        raise InputError(f"{where} must be a table")
    names = table.get("parameters")
    if not (isinstance(names, list) and names and all(isinstance(n, str) for n in names)):
        raise InputError(f"{where} parameters must be a non-empty array of names from {', '.join(CALIBRATION_PARAMETERS)}")
    unknown = [n for n in names if n not in CALIBRATION_PARAMETERS]
    if unknown or len(set(names)) != len(names):
        raise InputError(f"{where} parameters {names!r}: each once, from {', '.join(CALIBRATION_PARAMETERS)}")
    sigma, corr = table.get("sigma"), table.get("correlation")
    try:
        sigma = np.array(sigma, dtype=float)
        corr = np.array(corr, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{where} sigma must be an array of numbers and correlation an array of arrays") from None
    p = len(names)
    if sigma.shape != (p,) or not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise InputError(f"{where} sigma must hold {p} positive numbers, one a parameter")
    if (corr.shape != (p, p) or not np.all(np.isfinite(corr)) or not np.allclose(corr, corr.T, atol=1e-9)
            or not np.allclose(np.diag(corr), 1.0, atol=1e-9) or np.linalg.eigvalsh(corr).min() < -1e-9):
        raise InputError(f"{where} correlation must be a symmetric {p} x {p} correlation matrix (unit diagonal, "
                         f"positive semi-definite)")
    summary = {k: v for k, v in table.items() if k not in ("parameters", "sigma", "correlation")}
    return CameraCovariance(tuple(names), corr * np.outer(sigma, sigma), summary)


def read_camera_file(path) -> CameraFile:
    """Read a camera file (docs/formats/camera.md): ``[camera]`` (every :class:`Camera` field) and an
    optional ``[calibration]`` (what ``opnav calibrate`` fitted, with sigmas and correlations).

    Raises
    ------
    InputError
        Missing or unreadable file, an unknown table or key, a bad value; one line naming the file,
        table and key.
    """
    from .config import Where, build, read_toml

    data = read_toml(path, kind="camera file")
    unknown = [name for name in data if name not in CAMERA_FILE_TABLES]
    if unknown:
        raise InputError(f"{path}: a camera file holds [camera] and optionally [calibration]; unknown "
                         f"{', '.join(f'[{n}]' for n in unknown)}")
    if "camera" not in data:
        raise InputError(f"{path}: a camera file needs a [camera] table (docs/formats/camera.md)")
    camera = build(Camera, data["camera"], Where(str(path), "camera"))
    calibration = _calibration_table(data["calibration"], str(path)) if "calibration" in data else None
    return CameraFile(camera, calibration)


def write_camera_file(path, camera: Camera, calibration: CameraCovariance | None = None, *, comment: str = "") -> None:
    """Write ``camera`` (and its calibration) as a camera file that :func:`read_camera_file` reads back exactly.

    The file is written atomically (a temporary file renamed), its folder created. Numbers are written with Python's shortest round-trip representation, so reading the file gives
    the same floats.
    """
    import tomli_w

    table = {f.name: getattr(camera, f.name) for f in dataclasses.fields(camera)}
    table = {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in table.items()}
    data = {"camera": table}
    if calibration is not None:
        sigma = calibration.sigma
        corr = calibration.covariance / np.outer(sigma, sigma)
        np.fill_diagonal(corr, 1.0)  # exactly, not to the last bit of the division
        data["calibration"] = {**calibration.summary, "parameters": list(calibration.names),
                               "sigma": [float(s) for s in sigma],
                               "correlation": [[float(c) for c in row] for row in corr]}
    from .records import atomic_write_text

    head = "".join(f"# {line}\n" for line in comment.splitlines())
    atomic_write_text(path, head + tomli_w.dumps(data))
