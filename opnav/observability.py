"""Observability analysis (S2): PWCS stripped observability matrix, Fisher information, condition number.

Three views of how well a measurement set pins down the state along an arc,
each computed from linearised segments ``(F_j, H_j)``:

1. **PWCS / stripped observability matrix** (Goshen-Meskin & Bar-Itzhack 1992).
   Segment j has the piecewise-constant system ``x_{k+1} = F_j x_k``, ``z = H_j x``
   with ``F_j = I + dT A_j`` (``A_j = df/dx``) and ``H_j = dh/dx``. Its local
   observability matrix is ``Q_j = [H_j; H_j F_j; ...; H_j F_j^(n-1)]`` and the
   stripped observability matrix ``Q_s = [Q_1; Q_2; ...; Q_r]``. Q_s replaces the
   total observability matrix when ``null(Q_j) ⊂ null(F_j)`` for every segment,
   which holds here because each F_j is invertible (a small step from I). We
   report its numerical rank and singular values.
2. **Fisher information** ``F_x = sum_i H_i^T R_i^-1 H_i`` with ``H_i`` mapped to
   the initial epoch by the state transition matrix (``H_i Phi(t_i, t_0)``); its
   inverse is the Cramér–Rao bound on the initial state, computed from the SVD of
   the whitened stacked rows (:func:`information_inverse_diagonal`) so that weak
   directions survive and blind ones get an infinite bound. The *degree of
   observability* used here is ``eta = n / tr(F_x^-1)``: larger is better,
   equivalent to the paper's "smaller tr(F^-1) is better". (The S2 print of the
   definition is garbled; this is the reading consistent with its text.)
3. **Condition number** ``kappa(M)`` of ``M = O^T O`` with
   ``O = [H_0; H_1 Phi_1; H_2 Phi_2; ...]`` (the same mapped rows, unweighted).

:mod:`opnav.studies.s2_observability` evaluates the three figures for several
measurement sets along one propagated arc, and for the S2 sets on the capture
arc of :mod:`opnav.studies.trajectories`.

Numerical rank uses the tolerance ``max(sigma) * max(shape) * eps * rank_rtol_scale``;
the SVD is computed on a column-scaled matrix (position km, velocity km/s mixed
units would otherwise make "rank" depend on units), and the scaling is stated in
the result so that tables are comparable.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError


@dataclass(frozen=True)
class ObservabilityReport:
    """Observability figures for one measurement set along one arc.

    Attributes
    ----------
    name : str
        Label of the measurement set (e.g. ``"MPD"``).
    rank : int
        Numerical rank of the stripped observability matrix (state dimension n is full).
    singular_values : (n,) array
        Singular values of the (column-scaled) stripped observability matrix, descending.
    eta : float
        Degree of observability n / tr(F_x^-1) (F_x in scaled units).
    condition_number : float
        kappa(O^T O) (2-norm), in scaled units.
    crb_sigma : (n,) array
        sqrt(diag(F_x^-1)) in physical units (km, km/s): the Cramér–Rao 1-sigma of the
        initial state.
    column_scale : (n,) array
        Units used for the columns: state component i is measured in ``column_scale[i]``
        (physical) units before the SVD, FIM trace and condition number.
    """

    name: str
    rank: int
    singular_values: np.ndarray
    eta: float
    condition_number: float
    crb_sigma: np.ndarray
    column_scale: np.ndarray

    @property
    def max_singular_value(self) -> float:
        return float(self.singular_values[0])


def numerical_rank(matrix: np.ndarray, *, rtol: float | None = None) -> tuple[int, np.ndarray]:
    """Rank and singular values; rank counts sigma > rtol * sigma_max (default max(shape)*eps)."""
    sigma = np.linalg.svd(np.asarray(matrix, dtype=float), compute_uv=False)
    if rtol is None:
        rtol = max(np.shape(matrix)) * np.finfo(float).eps
    if sigma.size == 0 or sigma[0] == 0.0:
        return 0, sigma
    return int(np.sum(sigma > rtol * sigma[0])), sigma


def local_observability_matrix(F: np.ndarray, H: np.ndarray) -> np.ndarray:
    """``[H; H F; ...; H F^(n-1)]`` for one piecewise-constant segment, shape (n*m, n)."""
    F = np.asarray(F, dtype=float)
    H = np.atleast_2d(np.asarray(H, dtype=float))
    n = F.shape[0]
    if F.shape != (n, n) or H.shape[1] != n:
        raise InputError(f"F must be (n, n) and H (m, n); got {F.shape} and {H.shape}")
    blocks = [H]
    for _ in range(n - 1):
        blocks.append(blocks[-1] @ F)
    return np.vstack(blocks)


def stripped_observability_matrix(segments: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Stack the local observability matrices of PWCS segments ``[(F_j, H_j), ...]``."""
    if not segments:
        raise InputError("need at least one (F, H) segment")
    return np.vstack([local_observability_matrix(F, H) for F, H in segments])


def fisher_information(mapped_rows: list[np.ndarray], covariances: list[np.ndarray]) -> np.ndarray:
    """``sum_i H_i^T R_i^-1 H_i`` for measurement Jacobians already mapped to the reference epoch."""
    if len(mapped_rows) != len(covariances) or not mapped_rows:
        raise InputError("need matching, non-empty lists of Jacobians and covariances")
    n = np.atleast_2d(mapped_rows[0]).shape[1]
    info = np.zeros((n, n))
    for H, R in zip(mapped_rows, covariances):
        H = np.atleast_2d(H)
        info += H.T @ np.linalg.solve(np.atleast_2d(R), H)
    return 0.5 * (info + info.T)


def analyse(
    name: str,
    segments: list[tuple[np.ndarray, np.ndarray]],
    mapped_rows: list[np.ndarray],
    covariances: list[np.ndarray],
    *,
    column_scale: np.ndarray | None = None,
    rank_rtol: float = 1e-9,
) -> ObservabilityReport:
    """All three observability figures for one measurement set.

    Parameters
    ----------
    name : str
        Label of the set.
    segments : list of (F_j (n,n), H_j (m,n))
        PWCS segments (discrete transition over the segment step, measurement Jacobian).
    mapped_rows : list of (m, n)
        Measurement Jacobians mapped to the reference epoch, ``H_i Phi(t_i, t_0)``.
    covariances : list of (m, m)
        Measurement noise covariances matching ``mapped_rows``.
    column_scale : (n,) array, optional
        Physical size of one unit per state component (default: ones). For a
        position/velocity state a natural choice is (1 km, ..., 1e-3 km/s, ...).
    rank_rtol : float
        Relative singular-value threshold for the numerical rank (default 1e-9, well
        above the double-precision floor, so that near-singular directions count as
        unobservable — the S2 paper's "rank-deficient" sets).
    """
    if not segments:
        raise InputError("need at least one (F, H) segment")
    n = np.asarray(segments[0][0]).shape[0]
    scale = np.ones(n) if column_scale is None else np.asarray(column_scale, dtype=float)
    if scale.shape != (n,) or np.any(scale <= 0):
        raise InputError(f"column_scale must be {n} positive numbers")
    scaled_segments = [
        (np.asarray(F) * scale[None, :] / scale[:, None], np.atleast_2d(H) * scale[None, :])
        for F, H in segments
    ]
    rank, sigma = numerical_rank(stripped_observability_matrix(scaled_segments), rtol=rank_rtol)
    scaled_rows = [np.atleast_2d(H) * scale[None, :] for H in mapped_rows]
    variance = information_inverse_diagonal(scaled_rows, covariances)
    eta = float(n / np.sum(variance))
    O = np.vstack(scaled_rows)
    # cond(O)^2 equals cond(O^T O) in the 2-norm without squaring O's rounding errors first.
    condition = float(np.linalg.cond(O) ** 2)
    crb_sigma = np.sqrt(variance) * scale
    return ObservabilityReport(name, rank, sigma, eta, condition, crb_sigma, scale)


def information_inverse_diagonal(mapped_rows: list[np.ndarray], covariances: list[np.ndarray]) -> np.ndarray:
    """``diag(F_x^-1)`` for ``F_x = sum_i H_i^T R_i^-1 H_i``, computed without forming F_x.

    The rows are whitened (``L_i^-1 H_i`` with ``R_i = L_i L_i^T``) and stacked into W,
    so ``F_x = W^T W`` and ``F_x^-1 = V S^-2 V^T`` from the SVD ``W = U S V^T``: the
    condition number met is cond(W), the square root of cond(F_x), which keeps weakly
    observable directions (cond(F_x) ~ 1e15 on the S2 arcs) accurate. Directions with
    ``s_j <= max(shape) * eps * s_max`` carry no information: every component with
    weight on them gets an infinite variance (a pseudo-inverse would report zero).
    """
    if len(mapped_rows) != len(covariances) or not mapped_rows:
        raise InputError("need matching, non-empty lists of Jacobians and covariances")
    whitened = np.vstack([
        np.linalg.solve(np.linalg.cholesky(np.atleast_2d(R)), np.atleast_2d(H))
        for H, R in zip(mapped_rows, covariances)
    ])
    _, s, vt = np.linalg.svd(whitened, full_matrices=True)
    s_full = np.zeros(whitened.shape[1])
    s_full[: s.size] = s
    observed = s_full > max(whitened.shape) * np.finfo(float).eps * s_full[0]
    variance = (vt[observed].T ** 2) @ (1.0 / s_full[observed] ** 2)
    blind = np.any(np.abs(vt[~observed]) > np.sqrt(np.finfo(float).eps), axis=0)
    return np.where(blind, np.inf, variance)


def format_table(reports: list[ObservabilityReport], *, paper: dict[str, tuple] | None = None) -> str:
    """Plain-text table like S2 Tables 1-2, optionally with the paper's figures beside ours."""
    header = f"{'set':<6} {'rank':>4} {'max sv':>11} {'eta':>11} {'kappa':>11} {'CRB pos km':>11} {'CRB vel m/s':>11}"
    if paper:
        header += "   paper: rank / max sv / eta / kappa"
    lines = [header, "-" * len(header)]
    for rep in reports:
        pos = float(np.linalg.norm(rep.crb_sigma[:3]))
        vel = float(np.linalg.norm(rep.crb_sigma[3:6])) * 1e3 if rep.crb_sigma.size >= 6 else float("nan")
        line = (
            f"{rep.name:<6} {rep.rank:>4d} {rep.max_singular_value:>11.4e} {rep.eta:>11.4e} "
            f"{rep.condition_number:>11.4e} {pos:>11.4g} {vel:>11.4g}"
        )
        if paper and rep.name in paper:
            line += "   " + " / ".join(str(v) for v in paper[rep.name])
        lines.append(line)
    return "\n".join(lines)
