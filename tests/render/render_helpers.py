"""Helpers of the renderer tests: a static toy solar system for analytic geometry."""

from __future__ import annotations

import numpy as np

from opnav.constants import AU_KM


class StaticEphemeris:
    """Sun at the SSB and bodies at fixed ICRF positions (km): analytic geometry for tests."""

    def __init__(self, positions_km: dict[str, np.ndarray]):
        self.positions = {"sun": np.zeros(3), **{k: np.asarray(v, float) for k, v in positions_km.items()}}

    def state(self, body, t, *, center="ssb"):
        r = self.positions[body] - self.positions.get(center, np.zeros(3))
        if np.ndim(t):
            r = np.broadcast_to(r, (np.size(t), 3)).copy()
        return r, np.zeros_like(r)

    def position(self, body, t, *, center="ssb"):
        return self.state(body, t, center=center)[0]


def sphere_at_phase(phase_rad: float, distance_km: float = 1.0e6, r_helio_km: float = AU_KM):
    """Static ephemeris with body 'ball' at 1 au on +x and an observer seeing it at ``phase_rad``."""
    body = np.array([r_helio_km, 0.0, 0.0])
    # Observer direction from the body, rotated from the Sun direction (-x) by the phase angle.
    to_observer = np.array([-np.cos(phase_rad), np.sin(phase_rad), 0.0])
    return StaticEphemeris({"ball": body}), body + distance_km * to_observer
