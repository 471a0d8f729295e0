"""Light time and stellar aberration: one implementation for renderer and filters.

The renderer and the measurement models both call these functions, so a filter
whose state equals the truth sees zero-mean residuals. Each correction can be
switched off (``light_time=False``, ``aberration=False``) to study its effect.

Conventions: observer states are barycentric (origin SSB), ICRF, km and km/s;
epochs TDB seconds past J2000.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .constants import C_KM_S
from .errors import ConvergenceError, InputError

#: Light-time iteration stops when the light path changes by less than this (km).
LIGHT_TIME_TOLERANCE_KM = 1.0e-4


def aberrate(direction: np.ndarray, v_observer_km_s: np.ndarray) -> np.ndarray:
    """Apply relativistic stellar aberration for an observer moving at ``v_observer_km_s``.

    Parameters
    ----------
    direction : (..., 3) array
        Geometric (astrometric) unit vector(s) from the observer to the source, ICRF.
    v_observer_km_s : (3,) or (..., 3) array
        Observer velocity relative to the SSB, ICRF, km/s.

    Returns
    -------
    (..., 3) array
        Apparent unit vector(s), ICRF.

    Notes
    -----
    With beta = v/c and gamma = 1/sqrt(1 - beta^2) (Kaplan et al. 1989, NOVAS):
    ``u' = (u / gamma + beta + (u.beta) beta / (1 + 1/gamma)) / (1 + u.beta)``.
    The result is renormalised to remove rounding.
    """
    u = np.asarray(direction, dtype=float)
    beta = np.asarray(v_observer_km_s, dtype=float) / C_KM_S
    beta_sq = np.sum(beta * beta, axis=-1, keepdims=True)
    if np.any(beta_sq >= 1.0):
        raise InputError("observer speed must be below the speed of light")
    inv_gamma = np.sqrt(1.0 - beta_sq)
    u_dot_beta = np.sum(u * beta, axis=-1, keepdims=True)
    apparent = (u * inv_gamma + beta + u_dot_beta * beta / (1.0 + inv_gamma)) / (1.0 + u_dot_beta)
    return apparent / np.linalg.norm(apparent, axis=-1, keepdims=True)


def aberration_jacobian(direction: np.ndarray, v_observer_km_s: np.ndarray) -> np.ndarray:
    """d(apparent)/d(direction) of :func:`aberrate`, holding velocity fixed, shape (..., 3, 3).

    The derivative is taken with respect to :func:`aberrate`'s input as given (a
    unit vector in practice). To differentiate with respect to a relative
    position r, chain with the normalisation Jacobian ``(I - u u^T) / |r|``.
    """
    u = np.asarray(direction, dtype=float)
    beta = np.broadcast_to(np.asarray(v_observer_km_s, dtype=float) / C_KM_S, u.shape)
    inv_gamma = np.sqrt(1.0 - np.sum(beta * beta, axis=-1))[..., None, None]
    eye = np.eye(3)
    # numerator n(u) = u/gamma + beta + (u.beta) beta/(1+1/gamma); denominator d = 1 + u.beta
    d_num = eye * inv_gamma + np.einsum("...i,...j->...ij", beta, beta) / (1.0 + inv_gamma)
    num = u * inv_gamma[..., 0] + beta + np.sum(u * beta, -1, keepdims=True) * beta / (1.0 + inv_gamma[..., 0])
    den = 1.0 + np.sum(u * beta, -1)[..., None]
    w = num / den
    d_w = d_num / den[..., None] - np.einsum("...i,...j->...ij", num, beta) / (den[..., None] ** 2)
    w_norm = np.linalg.norm(w, axis=-1)[..., None, None]
    w_hat = w / w_norm[..., 0]
    d_norm = (eye - np.einsum("...i,...j->...ij", w_hat, w_hat)) / w_norm
    return d_norm @ d_w


def light_time_vector(
    target_ssb: Callable[[np.ndarray], np.ndarray],
    t_obs: float | np.ndarray,
    r_observer_ssb_km: np.ndarray,
    *,
    tolerance_km: float = LIGHT_TIME_TOLERANCE_KM,
    max_iterations: int = 10,
) -> tuple[np.ndarray, np.ndarray]:
    """Solve the light-time equation: where was the target when the light left it?

    Parameters
    ----------
    target_ssb : callable
        ``target_ssb(t)`` -> (N, 3) SSB-relative ICRF position (km) of the target at
        TDB epochs ``t`` (N,).
    t_obs : float or (N,) array
        Reception epochs, TDB seconds past J2000.
    r_observer_ssb_km : (3,) or (N, 3) array
        Observer position at reception, SSB-relative ICRF, km.

    Returns
    -------
    r_observer_target_km : (N, 3) or (3,) array
        Astrometric vector from observer (at ``t_obs``) to target (at ``t_obs - tau``), ICRF km.
    tau_s : (N,) or scalar
        One-way light time, s.

    Notes
    -----
    Fixed-point iteration tau_{k+1} = |r_T(t - tau_k) - r_O(t)| / c, which
    contracts by |v_T|/c (< 1e-4) per step; it stops when the light path
    changes by less than ``tolerance_km`` (default 0.1 m, so < 1 m as required).
    """
    scalar = np.ndim(t_obs) == 0
    t = np.atleast_1d(np.asarray(t_obs, dtype=float))
    r_obs = np.broadcast_to(np.asarray(r_observer_ssb_km, dtype=float), t.shape + (3,))
    tau = np.zeros_like(t)
    for _ in range(max_iterations):
        r_rel = np.asarray(target_ssb(t - tau)).reshape(t.shape + (3,)) - r_obs
        new_tau = np.linalg.norm(r_rel, axis=-1) / C_KM_S
        if np.all(np.abs(new_tau - tau) * C_KM_S < tolerance_km):
            tau = new_tau
            break
        tau = new_tau
    else:
        raise ConvergenceError(f"light-time iteration did not converge in {max_iterations} steps")
    r_rel = np.asarray(target_ssb(t - tau)).reshape(t.shape + (3,)) - r_obs
    return (r_rel[0], tau[0]) if scalar else (r_rel, tau)


def apparent_direction(
    target_ssb: Callable[[np.ndarray], np.ndarray],
    t_obs: float | np.ndarray,
    r_observer_ssb_km: np.ndarray,
    v_observer_ssb_km_s: np.ndarray,
    *,
    light_time: bool = True,
    aberration: bool = True,
) -> np.ndarray:
    """Apparent unit vector from observer to a solar-system target, ICRF.

    Parameters
    ----------
    target_ssb : callable
        ``target_ssb(t)`` -> SSB-relative ICRF target position (km) at TDB epochs t (N,).
    t_obs : float or (N,)
        Reception epochs, TDB seconds past J2000.
    r_observer_ssb_km, v_observer_ssb_km_s : (3,) or (N, 3)
        Observer position (km) and velocity (km/s) relative to the SSB, ICRF.
    light_time, aberration : bool
        Apply each correction (both on by default).
    """
    if light_time:
        r_rel, _ = light_time_vector(target_ssb, t_obs, r_observer_ssb_km)
    else:
        t = np.atleast_1d(np.asarray(t_obs, dtype=float))
        r_rel = np.asarray(target_ssb(t)).reshape(t.shape + (3,)) - np.asarray(r_observer_ssb_km, dtype=float)
        if np.ndim(t_obs) == 0:
            r_rel = r_rel[0]
    direction = r_rel / np.linalg.norm(r_rel, axis=-1, keepdims=True)
    if aberration:
        direction = aberrate(direction, v_observer_ssb_km_s)
    return direction


def _outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...j->...ij", a, b)


def aberration_velocity_jacobian(direction: np.ndarray, v_observer_km_s: np.ndarray) -> np.ndarray:
    """d(apparent)/d(v_observer_km_s) of :func:`aberrate`, holding direction fixed, shape (..., 3, 3).

    Units 1/(km/s). Differentiates the exact relativistic formula of
    :func:`aberrate` (not its first-order form) with respect to beta = v/c.
    """
    u = np.asarray(direction, dtype=float)
    beta = np.asarray(v_observer_km_s, dtype=float) / C_KM_S
    u, beta = np.broadcast_arrays(u, beta)
    eye = np.eye(3)
    g = np.sqrt(1.0 - np.sum(beta * beta, -1))[..., None]  # 1/gamma
    u_dot_beta = np.sum(u * beta, -1)[..., None]
    d_g = -beta / g  # d(1/gamma)/d beta
    num = u * g + beta + u_dot_beta * beta / (1.0 + g)
    den = 1.0 + u_dot_beta
    d_num = (
        _outer(u, d_g)
        + eye
        + (_outer(beta, u) + u_dot_beta[..., None] * eye) / (1.0 + g)[..., None]
        - u_dot_beta[..., None] * _outer(beta, d_g) / ((1.0 + g) ** 2)[..., None]
    )
    w = num / den
    d_w = d_num / den[..., None] - _outer(num, u) / (den**2)[..., None]
    w_norm = np.linalg.norm(w, axis=-1)[..., None, None]
    w_hat = w / w_norm[..., 0]
    return ((eye - _outer(w_hat, w_hat)) / w_norm) @ d_w / C_KM_S
