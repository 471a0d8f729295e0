"""Directions and frames: unit vectors, RA/Dec, ICRF <-> J2000 ecliptic.

All inertial vectors are ICRF (= J2000 equatorial, DE421's frame) unless a name
says otherwise. Angles are radians. Rotations between frames are named
``R_to_from`` so that ``v_to = R_to_from @ v_from``.
"""

from __future__ import annotations

import numpy as np

from .constants import OBLIQUITY_J2000_RAD
from .errors import InputError


def radec_to_unit(ra: np.ndarray | float, dec: np.ndarray | float) -> np.ndarray:
    """Right ascension and declination (rad) -> unit vector(s), shape (..., 3), same frame."""
    ra = np.asarray(ra, dtype=float)
    dec = np.asarray(dec, dtype=float)
    cos_dec = np.cos(dec)
    return np.stack([cos_dec * np.cos(ra), cos_dec * np.sin(ra), np.sin(dec)], axis=-1)


def unit_to_radec(vector: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vector(s) (..., 3), any length -> (ra in [0, 2pi), dec in [-pi/2, pi/2]) rad.

    Uses atan2 forms, accurate at the poles and for vectors of any length.
    """
    vector = np.asarray(vector, dtype=float)
    x, y, z = vector[..., 0], vector[..., 1], vector[..., 2]
    ra = np.mod(np.arctan2(y, x), 2.0 * np.pi)
    # mod of a tiny negative angle rounds up to exactly 2 pi; keep the range half-open
    ra = ra - 2.0 * np.pi * (ra >= 2.0 * np.pi)
    dec = np.arctan2(z, np.hypot(x, y))
    return ra, dec


def unit(vector: np.ndarray) -> np.ndarray:
    """Normalise vector(s) along the last axis; raise on a zero or non-finite vector."""
    vector = np.asarray(vector, dtype=float)
    norm = np.linalg.norm(vector, axis=-1, keepdims=True)
    if not np.all(np.isfinite(norm)) or np.any(norm == 0.0):
        raise InputError("cannot normalise a zero-length or non-finite vector")
    return vector / norm


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad) between vectors along the last axis; accurate near 0 and pi."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.arctan2(cross, np.sum(a * b, axis=-1))


def _rotation_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])


#: ICRF (J2000 equatorial) -> J2000 mean ecliptic, obliquity 84381.448".
R_ECLIPTIC_ICRF = _rotation_x(OBLIQUITY_J2000_RAD)
R_ICRF_ECLIPTIC = R_ECLIPTIC_ICRF.T


def icrf_to_ecliptic(vector: np.ndarray) -> np.ndarray:
    """ICRF vector(s) (..., 3) -> J2000 ecliptic, same origin and units."""
    return np.asarray(vector, dtype=float) @ R_ECLIPTIC_ICRF.T


def ecliptic_to_icrf(vector: np.ndarray) -> np.ndarray:
    """J2000 ecliptic vector(s) (..., 3) -> ICRF, same origin and units."""
    return np.asarray(vector, dtype=float) @ R_ICRF_ECLIPTIC.T


def pointing_with_sun_roll(u_target: np.ndarray, u_sun: np.ndarray, in_line: str):
    """The attitude (body -> ICRF) whose +z is on ``u_target`` and whose +x points to ``u_sun``'s part across
    it (both ICRF unit vectors, any origin): a camera on the target with the Sun on one side.

    Raises ``InputError(in_line)`` when the target and the Sun are in line (the roll is undefined).
    Returns a ``scipy.spatial.transform.Rotation`` (imported here: this module is on every command's start-up).
    """
    from scipy.spatial.transform import Rotation

    z = np.asarray(u_target, float) / np.linalg.norm(u_target)
    x = np.asarray(u_sun, float) - (np.asarray(u_sun, float) @ z) * z
    if np.linalg.norm(x) < 1e-6:
        raise InputError(in_line)
    x /= np.linalg.norm(x)
    return Rotation.from_matrix(np.column_stack([x, np.cross(z, x), z]))
