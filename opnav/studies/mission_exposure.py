"""The navigation camera's exposure at each frame of a mission in image mode (docs/mission.md#exposure).

``camera_exposure_law`` of the run file's ``[settings]`` (:class:`opnav.studies.mission.Settings`):

- ``"fixed"``: every frame of a target is exposed for its ``camera_exposure_s``;
- ``"peak"``: each frame is exposed so that the target's brightest pixel reaches about
  ``camera_peak_fraction`` of the detector's full well, the way an approach camera's exposure is
  planned from the predicted scene. Far out an asteroid is a point source whose light falls as the
  range squared; near, a resolved disk whose brightness per pixel no longer depends on range: one
  exposure cannot cover 10^6 km to 1,000 km.

**The peak law.** At each record epoch the target is drawn as the renderer draws it
(:func:`opnav.bodies.view_body`: the rays of its shape and reflectance at the true geometry, through
the pointing law's attitude): its rays' electron rates binned to sub-pixels, blurred by the
renderer's Gaussian PSF and summed over each pixel give the brightest pixel's rate ``peak`` (e-/s). The
wanted exposure is ``camera_peak_fraction * full_well / peak``; the camera has the exposure settings
``shortest * EXPOSURE_STEP**n`` up to ``longest`` (``camera_exposure_limits_s``), and the frame gets
the longest setting at or below the wanted one: the brightest pixel lands between
``camera_peak_fraction / EXPOSURE_STEP`` and ``camera_peak_fraction`` of the full well, unless the
limits stop it (a body too faint for ``longest``, or one too bright for ``shortest``, which then
saturates). The prediction is the truth's (the pointing law's is too): a flight planner predicts
from its estimate, and a centre fit does not need the peak to be exact.

The stars are not what the navigation camera is exposed for: the attitude comes from the star
tracker either way.
"""

from __future__ import annotations

import numpy as np

#: The camera's exposure settings are this factor apart (``shortest * EXPOSURE_STEP**n``).
EXPOSURE_STEP = 2.0
#: Laws of ``camera_exposure_law``.
EXPOSURE_LAWS = ("fixed", "peak")


def exposure_ladder(shortest_s: float, longest_s: float) -> np.ndarray:
    """The camera's exposure settings, s: ``shortest_s * EXPOSURE_STEP**n`` up to ``longest_s``."""
    count = int(np.floor(np.log(longest_s / shortest_s) / np.log(EXPOSURE_STEP) + 1e-9)) + 1
    return shortest_s * EXPOSURE_STEP ** np.arange(count)


def ladder_exposure(wanted_s: np.ndarray, shortest_s: float, longest_s: float) -> np.ndarray:
    """The longest setting of :func:`exposure_ladder` at or below each ``wanted_s`` (s); ``shortest_s``
    where even that is longer."""
    ladder = exposure_ladder(shortest_s, longest_s)
    wanted = np.asarray(wanted_s, dtype=float)
    index = np.searchsorted(ladder, wanted * (1.0 + 1e-12), side="right") - 1
    return ladder[np.clip(index, 0, ladder.size - 1)]


#: Sub-pixels per pixel and axis on which :func:`peak_rate_e_s` bins the rays before the PSF.
SUBPIXELS = 5


def peak_rate_e_s(body, camera, R_icrf_cam, observer, ephemeris, psf_sigma_px: float, *, supersample: int = 2) -> float:
    """The brightest pixel's electron rate (e-/s) of ``body`` (:class:`opnav.bodies.Body`) on ``camera``
    at attitude ``R_icrf_cam`` (camera -> ICRF) from ``observer`` (:class:`opnav.observer.Observer`: SSB,
    ICRF, km, km/s, TDB s): the body's rays (:func:`opnav.bodies.view_body`) binned to :data:`SUBPIXELS`
    sub-pixels, blurred by the Gaussian PSF of ``psf_sigma_px`` and summed over each pixel (a point
    source's light split between pixels by where it falls, as the renderer splits it). 0 when no lit ray
    falls on the detector."""
    from scipy.ndimage import convolve1d

    from ..bodies import view_body

    view = view_body(body, camera, R_icrf_cam, observer, ephemeris, supersample=supersample)
    xy, rate = view.rays.xy_px, view.rays.electrons_s
    inside = (np.all(np.isfinite(xy), axis=1) & (xy[:, 0] > -0.5) & (xy[:, 1] > -0.5)
              & (xy[:, 0] < camera.width_px - 0.5) & (xy[:, 1] < camera.height_px - 0.5) & (rate > 0.0))
    if not np.any(inside):
        return 0.0
    n = SUBPIXELS
    reach = int(np.ceil(6.0 * psf_sigma_px))  # whole pixels of margin for the PSF's wings
    # sub-pixel cells aligned with the pixels (pixel k spans [k - 0.5, k + 0.5])
    cell = np.floor((xy[inside] + 0.5) * n).astype(int)
    lo = (cell.min(axis=0) // n - reach) * n
    shape = ((cell.max(axis=0) // n + reach + 1) * n) - lo
    fine = np.zeros((shape[1], shape[0]))
    np.add.at(fine, (cell[:, 1] - lo[1], cell[:, 0] - lo[0]), rate[inside])
    offsets = np.arange(-reach * n, reach * n + 1) / n
    kernel = np.exp(-0.5 * (offsets / psf_sigma_px) ** 2)
    kernel /= kernel.sum()
    blurred = convolve1d(convolve1d(fine, kernel, axis=0, mode="constant"), kernel, axis=1, mode="constant")
    pixels = blurred.reshape(shape[1] // n, n, shape[0] // n, n).sum(axis=(1, 3))
    return float(pixels.max())


def frame_exposures(settings, target: str, body, camera, attitudes, epochs: np.ndarray, r_ssb: np.ndarray,
                    v_ssb: np.ndarray, ephemeris, psf_sigma_px: float) -> np.ndarray:
    """Each frame's exposure of ``target``'s navigation camera (s), by ``settings.camera_exposure_law``
    (module notes); ``attitudes`` (M) the pointing law's body (= camera) -> ICRF, ``r_ssb``, ``v_ssb`` (M, 3)
    the observer's SSB states (ICRF, km, km/s) at ``epochs`` (TDB s past J2000)."""
    from ..observer import Observer
    from .mission import target_exposure_s

    if settings.camera_exposure_law == "fixed":
        return np.full(len(epochs), target_exposure_s(settings)[target])
    shortest, longest = settings.camera_exposure_limits_s
    peak = np.array([peak_rate_e_s(body, camera, attitudes[i], Observer(float(t), r_ssb[i], v_ssb[i]), ephemeris,
                                   psf_sigma_px) for i, t in enumerate(epochs)])
    with np.errstate(divide="ignore"):
        wanted = np.where(peak > 0.0, settings.camera_peak_fraction * camera.full_well_e / peak, np.inf)
    return ladder_exposure(wanted, shortest, longest)


__all__ = ["EXPOSURE_LAWS", "EXPOSURE_STEP", "SUBPIXELS", "exposure_ladder", "frame_exposures", "ladder_exposure", "peak_rate_e_s"]
