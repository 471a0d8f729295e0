"""Process-noise models: white acceleration and state-noise compensation (SNC).

Both model the unmodelled acceleration (SRP mismodelling, outgassing, attitude
thruster leaks, truncated gravity) as continuous white noise ``w(t)`` entering
the velocity: ``d/dt [r, v] = f(r, v) + [0; I] w`` with
``E[w(t) w(s)^T] = Q_c delta(t - s)``. Over a step ``dt`` short against the
orbital period, ``Phi(dt) ~ [[I, dt I], [0, I]]`` and the discrete covariance is
the closed form (Tapley, Schutz & Born 2004, Statistical Orbit Determination,
Sec. 4.9, eq. 4.9.50; Bar-Shalom, Li & Kirubarajan 2001, Sec. 6.2.2):

    Q(dt) = [[Q_c dt^3/3, Q_c dt^2/2],
             [Q_c dt^2/2, Q_c dt    ]]

:class:`WhiteAcceleration` takes one spectral density ``q`` per axis
(``Q_c = q I``, ICRF). :class:`StateNoiseCompensation` takes separate densities
along the radial, in-track (transverse) and cross-track axes of the current
state (RIC frame of the orbit about the filter's central body) and rotates
``Q_c`` into ICRF, which matters when mismodelling is mostly along-track (drag,
thrust) or radial (SRP).

Tuning guidance
---------------
- Units: ``q`` is km^2/s^3. An acceleration error of 1-sigma ``sigma_a`` (km/s^2)
  that stays correlated for ``tau`` seconds corresponds to ``q ~ sigma_a^2 tau``;
  after time ``T`` it grows a position error ~ sqrt(q T^3 / 3).
- Start from the largest unmodelled acceleration: a 10% SRP error on a probe
  with A/m = 0.01 m^2/kg at 1.5 au is ~2e-11 km/s^2; with tau ~ 1 day this gives
  q ~ 4e-17 km^2/s^3.
- Check with NIS/NEES (:mod:`opnav.filters.run`): a NIS mean above its chi-square
  bound means q is too small (or the measurement noise is); a NEES mean well
  below its bound means q is larger than needed and the filter is pessimistic.
- Use ``q = 0`` only when the filter's dynamics equal the truth's (simulation);
  otherwise the covariance collapses and the filter stops learning.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..errors import InputError


class ProcessNoise(Protocol):
    """Discrete process noise for a step ``dt_s`` from state ``x`` (6,): (6, 6), km and km/s."""

    def discrete(self, dt_s: float, x: np.ndarray) -> np.ndarray: ...


def white_acceleration_q(dt_s: float, q_c: np.ndarray) -> np.ndarray:
    """Closed-form discrete Q (6, 6) for white acceleration with spectral density ``q_c`` (3, 3) km^2/s^3.

    ``dt_s`` is the step length (s, sign ignored: noise accumulates either way).
    """
    dt = abs(float(dt_s))
    q_c = np.asarray(q_c, dtype=float)
    Q = np.empty((6, 6))
    Q[:3, :3] = q_c * (dt**3 / 3.0)
    Q[:3, 3:] = Q[3:, :3] = q_c * (dt**2 / 2.0)
    Q[3:, 3:] = q_c * dt
    return Q


def _check_density(name: str, value: np.ndarray) -> None:
    if not np.all(np.isfinite(value)) or np.any(value < 0.0):
        raise InputError(f"{name} must be finite and >= 0 (km^2/s^3), got {value!r}")


@dataclass(frozen=True)
class WhiteAcceleration:
    """Isotropic white acceleration noise, spectral density ``q_km2_s3`` per ICRF axis."""

    q_km2_s3: float

    def __post_init__(self) -> None:
        _check_density("q_km2_s3", np.asarray(self.q_km2_s3, dtype=float))

    def discrete(self, dt_s: float, x: np.ndarray | None = None) -> np.ndarray:
        """Q(dt) (6, 6), ICRF, km and km/s; ``x`` is not used (isotropic)."""
        return white_acceleration_q(dt_s, self.q_km2_s3 * np.eye(3))


def ric_rotation(x: np.ndarray) -> np.ndarray:
    """R_icrf_ric (3, 3): columns are the radial, in-track, cross-track unit vectors of ``x`` (6,).

    ``x`` is [r km, v km/s], ICRF, relative to the central body.
    """
    r = np.asarray(x[:3], dtype=float)
    v = np.asarray(x[3:6], dtype=float)
    h = np.cross(r, v)
    r_norm, h_norm = np.linalg.norm(r), np.linalg.norm(h)
    if r_norm == 0.0 or h_norm == 0.0:
        raise InputError("RIC frame undefined: state has zero position or zero angular momentum")
    radial = r / r_norm
    cross = h / h_norm
    return np.column_stack([radial, np.cross(cross, radial), cross])


@dataclass(frozen=True)
class StateNoiseCompensation:
    """SNC: white acceleration with spectral densities along radial, in-track, cross-track.

    Attributes
    ----------
    q_ric_km2_s3 : tuple of 3 floats
        Spectral densities (km^2/s^3) along the radial, in-track and cross-track axes
        of the state at the start of each step.
    """

    q_ric_km2_s3: tuple[float, float, float]

    def __post_init__(self) -> None:
        q = np.asarray(self.q_ric_km2_s3, dtype=float)
        if q.shape != (3,):
            raise InputError(f"q_ric_km2_s3 needs 3 values (radial, in-track, cross-track), got {q.shape}")
        _check_density("q_ric_km2_s3", q)

    def discrete(self, dt_s: float, x: np.ndarray) -> np.ndarray:
        """Q(dt) (6, 6), ICRF, km and km/s, with the RIC axes of ``x`` (6,) at the step start."""
        rot = ric_rotation(x)
        q_c = rot @ np.diag(self.q_ric_km2_s3) @ rot.T
        return white_acceleration_q(dt_s, 0.5 * (q_c + q_c.T))


#: ``[navigation.process_noise] model`` and the density each one needs (none for ``none``).
PROCESS_NOISE_MODELS = ("white", "snc", "none")
_DENSITY = {"white": "q_km2_s3", "snc": "q_ric_km2_s3", "none": None}
_KEYS = ("model", "q_km2_s3", "q_ric_km2_s3")


def process_noise_from_config(config: dict) -> ProcessNoise | None:
    """Build a process-noise model from a ``[navigation.process_noise]`` table.

    ``{"model": "white", "q_km2_s3": 1e-17}`` or
    ``{"model": "snc", "q_ric_km2_s3": [qr, qi, qc]}``; ``{"model": "none"}`` gives ``None``.
    ``model`` defaults to ``white`` and is read in any case.

    Raises
    ------
    InputError
        An unknown model or key, a missing density, or a density the model does not use (named:
        ``q_km2_s3`` with ``snc`` or ``none``, ``q_ric_km2_s3`` with ``white`` or ``none``), so a
        table never carries a number that silently does nothing.
    """
    unknown = sorted(str(key) for key in config if key not in _KEYS)
    if unknown:
        raise InputError(f"unknown process_noise key(s) {unknown}; known: {', '.join(_KEYS)}")
    model = str(config.get("model", "white")).strip().lower()
    if model not in _DENSITY:
        raise InputError(f"unknown process_noise model {config.get('model')!r}; expected white, snc or none")
    needed = _DENSITY[model]
    unused = [key for key in ("q_km2_s3", "q_ric_km2_s3") if key in config and key != needed]
    if unused:
        uses = f"uses {needed} only" if needed else "uses no density"
        raise InputError(f"{unused[0]} is not used by process_noise model {model!r}, which {uses}; "
                         f"remove it or change the model")
    if model == "none":
        return None
    if needed not in config:
        if model == "white":
            raise InputError("process_noise model 'white' needs q_km2_s3")
        raise InputError("process_noise model 'snc' needs q_ric_km2_s3 = [radial, in-track, cross-track]")
    if model == "white":
        return WhiteAcceleration(float(config["q_km2_s3"]))
    return StateNoiseCompensation(tuple(float(v) for v in config["q_ric_km2_s3"]))
