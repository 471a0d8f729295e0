"""The point sources of one frame: detected, then centroided with the detector's noise model.

:func:`frame_sources` reads a frame (:func:`opnav.image.io.read_image`), detects its sources
(:func:`opnav.image.detect.detect`) and centroids each (:func:`opnav.image.centroid.centroid`)
with the gain, read noise and bias of an opnav FITS header (``GAIN``, ``RDNOISE``, ``BIASLVL``;
other frames are fitted with the noise estimated from the frame). It is what ``opnav centroid``
prints. Pixel coordinates follow :mod:`opnav.image` (x = column, y = row, (0, 0) the centre of
the first pixel).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from .centroid import CentroidResult, centroid
from .detect import DetectOptions, Detections, detect
from .io import ImageMeta, read_image


@dataclass(frozen=True)
class FrameSources:
    """The sources of one frame (:func:`frame_sources`).

    Attributes
    ----------
    detections : Detections
        What detection found, brightest first; ``flags`` is its bit mask (:mod:`opnav.image.detect`),
        ``n_rejected`` the hot-pixel and cosmic-ray hits it refused.
    centroids : CentroidResult
        One fit per detection, same order (``ok`` false where the fit failed).
    """

    detections: Detections
    centroids: CentroidResult

    def rows(self) -> list[dict]:
        """One dict per source whose fit succeeded, brightest first: ``x``, ``y`` (px), ``flux`` (ADU
        above the background), ``snr``, ``sigma_x``, ``sigma_y`` (px, from the fit covariance) and
        ``flags`` (the detection bit mask); plain floats and ints, ready for JSON."""
        res, det = self.centroids, self.detections
        return [
            {
                "x": float(res.xy[i, 0]), "y": float(res.xy[i, 1]), "flux": float(res.flux[i]),
                "snr": float(res.snr[i]), "sigma_x": float(np.sqrt(res.cov[i, 0, 0])),
                "sigma_y": float(np.sqrt(res.cov[i, 1, 1])), "flags": int(det.flags[i]),
            }
            for i in np.flatnonzero(res.ok)
        ]


def header_number(header, key: str, frame: str) -> float | None:
    """FITS header keyword ``key`` as a finite number, ``None`` when absent.

    Raises
    ------
    InputError
        When the value is not a finite number (a boolean is not one); the message names ``frame``
        and the keyword.
    """
    if key not in header:
        return None
    value = header[key]
    try:
        if isinstance(value, bool):
            raise ValueError
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{frame}: FITS keyword {key} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise InputError(f"{frame}: FITS keyword {key} must be finite, got {value!r}")
    return number


def image_sources(image: np.ndarray, meta: ImageMeta, *, method: str = "gauss", window: int = 7,
                  threshold_sigma: float = 5.0, frame: str | None = None) -> FrameSources:
    """Detect and centroid the point sources of a frame read by :func:`opnav.image.io.read_image`.

    Parameters
    ----------
    image : (H, W) array
        Pixel values, ADU.
    meta : ImageMeta
        Its saturation level, invalid pixels, lossy flag and FITS header (gain ``GAIN`` e-/ADU,
        read noise ``RDNOISE`` e-, bias ``BIASLVL`` ADU, each optional; the read noise is used only
        with the bias, else the background's variance is fitted from the frame).
    method : str
        Centroid estimator (:data:`opnav.image.centroid.METHODS`).
    window : int
        Odd stamp side, px.
    threshold_sigma : float
        Detection threshold, sigma.
    frame : str, optional
        The frame's name in errors (default ``meta.path``).

    Raises
    ------
    InputError
        A header keyword that is not a finite number; bad ``method``, ``window`` or threshold.
    """
    frame = meta.path if frame is None else frame
    det = detect(image, options=DetectOptions(threshold_sigma=threshold_sigma), saturation_adu=meta.saturation_adu,
                 invalid=meta.invalid, lossy=meta.lossy)
    header = meta.header if meta.header is not None else {}
    read_noise = header_number(header, "RDNOISE", frame)
    gain = header_number(header, "GAIN", frame)
    bias = header_number(header, "BIASLVL", frame)
    invalid = det.rejected if meta.invalid is None else det.rejected | meta.invalid
    if bias is None:
        # Without BIASLVL the pixels' zero is unknown: a known read noise would count every ADU above 0
        # (the bias included) as shot noise. The background's variance is then fitted from the frame
        # (its level is the floor), with the header's gain for the stars' own shot noise.
        read_noise = None
    res = centroid(
        image, det.xy, method=method, window=window, read_noise_e=read_noise,
        gain_e_per_adu=gain, bias_adu=0.0 if bias is None else bias,
        saturation_adu=meta.saturation_adu, invalid=invalid,
    )
    return FrameSources(det, res)


def frame_sources(path: str | Path, *, method: str = "gauss", window: int = 7,
                  threshold_sigma: float = 5.0) -> FrameSources:
    """Read the frame at ``path`` (FITS, PNG, TIFF, JPEG) and detect and centroid its point sources
    (:func:`image_sources`; errors name the frame as ``str(path)``).

    Raises
    ------
    FrameError
        A frame that cannot be read (:func:`opnav.image.io.read_image`).
    InputError
        As :func:`image_sources`.
    """
    image, meta = read_image(path)
    return image_sources(image, meta, method=method, window=window, threshold_sigma=threshold_sigma,
                         frame=str(path))
