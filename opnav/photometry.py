"""Photometry: magnitudes -> photons at the aperture -> electrons per second.

Band and zero point (defaults, Johnson V):

* Vega-system zero point of Bessell, Castelli & Plez (1998, A&A 333, 231,
  Table A2): ``f_lambda(V = 0) = 363.1e-11 erg s^-1 cm^-2 A^-1`` at the
  effective wavelength 5448 A.
* Band width: the FWHM of Bessell's V passband, 840 A (Bessell 2005, ARA&A 43,
  293, Table 2).
* Photon energy ``h c / lambda_eff`` = 3.646e-12 erg, so a V = 0 source gives
  ``363.1e-11 / 3.646e-12 * 840 = 8.37e5 photons s^-1 cm^-2``
  = 8.37e9 photons s^-1 m^-2 over the band (the familiar "1000 photons/s/cm^2/A").

A source of magnitude m then gives
``electrons/s = 10^(-0.4 m) * F0 * (pi D^2 / 4) * throughput * QE``
with the camera's aperture diameter D, optical throughput and mean quantum
efficiency (:class:`opnav.camera.Camera`). The throughput and QE are band means,
so the colour of the source is ignored (a flat spectrum within the band).

Reflected light uses the Sun's V magnitude at 1 au, -26.74 (Willmer 2018, ApJS
236, 47, Table 3 gives -26.76; the classic value is kept for comparison with
Phobos/Deimos magnitudes in the literature).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .errors import InputError

_H_C_ERG_ANGSTROM = 6.62607015e-27 * 2.99792458e18

#: Apparent V magnitude of the Sun seen from 1 au.
SUN_VMAG_1AU = -26.74


@dataclass(frozen=True)
class Band:
    """A photometric band: Vega zero point and width.

    Parameters
    ----------
    name : str
    f_lambda_zero_erg_s_cm2_a : float
        Flux density of a magnitude-0 source at the effective wavelength, erg s^-1 cm^-2 A^-1.
    wavelength_eff_a : float
        Effective wavelength, angstrom.
    width_a : float
        Band FWHM, angstrom.
    """

    name: str = "Johnson V"
    f_lambda_zero_erg_s_cm2_a: float = 363.1e-11
    wavelength_eff_a: float = 5448.0
    width_a: float = 840.0

    def __post_init__(self) -> None:
        for field in ("f_lambda_zero_erg_s_cm2_a", "wavelength_eff_a", "width_a"):
            value = getattr(self, field)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"band {field} must be a positive finite number, got {value!r}")

    @property
    def photon_flux_zero_m2_s(self) -> float:
        """Photons s^-1 m^-2 over the band from a magnitude-0 source."""
        photon_energy_erg = _H_C_ERG_ANGSTROM / self.wavelength_eff_a
        return self.f_lambda_zero_erg_s_cm2_a / photon_energy_erg * self.width_a * 1.0e4


JOHNSON_V = Band()


def collecting_area_m2(camera: Camera) -> float:
    """Entrance-pupil area of ``camera``, m^2 (unobstructed circular aperture)."""
    return math.pi * (camera.aperture_mm * 1.0e-3) ** 2 / 4.0


def electron_rate(vmag: np.ndarray | float, camera: Camera, band: Band = JOHNSON_V) -> np.ndarray:
    """Electrons per second produced on the detector by sources of magnitude ``vmag``.

    Parameters
    ----------
    vmag : float or (N,) array
        Apparent magnitudes in ``band``.
    camera : Camera
        Supplies aperture, throughput and QE.
    band : Band
        Zero point and width (default Johnson V, Bessell et al. 1998).
    """
    vmag = np.asarray(vmag, dtype=float)
    if not np.all(np.isfinite(vmag)):
        raise InputError("magnitudes must be finite")
    rate_zero = band.photon_flux_zero_m2_s * collecting_area_m2(camera) * camera.throughput * camera.qe
    return rate_zero * 10.0 ** (-0.4 * vmag)


def magnitude_from_rate(electrons_s: np.ndarray | float, camera: Camera, band: Band = JOHNSON_V) -> np.ndarray:
    """Inverse of :func:`electron_rate`: electrons per second -> apparent magnitude."""
    rate = np.asarray(electrons_s, dtype=float)
    rate_zero = band.photon_flux_zero_m2_s * collecting_area_m2(camera) * camera.throughput * camera.qe
    with np.errstate(divide="ignore"):
        return -2.5 * np.log10(rate / rate_zero)


def reflected_magnitude(flux_ratio_to_sun_1au: np.ndarray | float) -> np.ndarray:
    """Magnitude of reflected sunlight whose flux is the given fraction of the Sun's at 1 au."""
    ratio = np.asarray(flux_ratio_to_sun_1au, dtype=float)
    with np.errstate(divide="ignore"):
        return SUN_VMAG_1AU - 2.5 * np.log10(ratio)
