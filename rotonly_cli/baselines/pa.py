"""Two-view pose-only adjustment (PA, Cai et al. TPAMI 2023) as restated in the paper,
eq:PA1 to eq:PAtotal2. Benchmark baseline only (algorithms.md §5).

For an edge (i, j), with u_k = R_ij X_ik and θ_k = u_k × X_jk (z = 1 coordinates):

    Y^j_k = ‖X_jk × t‖ u_k + ‖θ_k‖ t                    (eq:PA1, view j)
    R_ij Y^i_k = ‖u_k × t‖ X_jk − ‖θ_k‖ t                 (eq:PA1 for the edge (j, i), view i)
    V^PA_k = [X̃_ik − Y^i/Y^i_(3);  X̃_jk − Y^j/Y^j_(3)]    (eq:PA3, eq:PA4, image-plane form)

and f_PA = Σ_k ‖V^PA_k‖² (eq:PAtotal1) is minimised over (R_ij, t_ij): the 3-D points are
eliminated through the analytic depths, leaving 5 DoF since ‖t‖ is a gauge. Parameters: the
Cayley vector c with R = cay(c) R_start and s ∈ R² with t = (t₀ + B s)/‖t₀ + B s‖ (B a basis
of t₀'s tangent plane). Levenberg–Marquardt (scipy MINPACK ``lm``) with an exact Jacobian by
the complex step (every operation below is complex-analytic: norms as sqrt(Σ v²), the Cayley
map is rational), vectorised over matches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from rotonly_cli.baselines.kneip import cayley_to_rotation
from rotonly_cli.baselines.twoview_ba import _tangent_basis

_COMPLEX_STEP = 1e-30


@dataclass
class PAResult:
    R_j_from_i: np.ndarray  # (3, 3)
    t_direction: np.ndarray  # (3,) unit t_ij
    initial_cost: float  # f_PA (sum of squared normalized-coordinate residuals)
    cost: float
    num_evaluations: int
    success: bool


def _norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.sum(v * v, axis=-1))  # analytic (complex-step safe), unlike np.abs / np.linalg.norm


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def pa_residuals(R_j_from_i: np.ndarray, t: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """V^PA (m, 4) = [view-i residual (2), view-j residual (2)] of eq:PA4 in normalized coordinates."""
    X_i = np.column_stack([x_i[:, :2], np.ones(len(x_i))])
    X_j = np.column_stack([x_j[:, :2], np.ones(len(x_j))])
    u = X_i @ R_j_from_i.T
    theta_norm = _norm(_cross(u, X_j))
    t_row = np.broadcast_to(t, u.shape)
    Y_j = _norm(_cross(X_j, t_row))[:, None] * u + theta_norm[:, None] * t
    Y_i = (_norm(_cross(u, t_row))[:, None] * X_j - theta_norm[:, None] * t) @ R_j_from_i  # R_ijᵀ (...)
    r_j = X_j[:, :2] - Y_j[:, :2] / Y_j[:, 2:3]
    r_i = X_i[:, :2] - Y_i[:, :2] / Y_i[:, 2:3]
    return np.concatenate([r_i, r_j], axis=1)


def pose_adjust_twoview(R_init: np.ndarray, t_init: np.ndarray, x_i: np.ndarray, x_j: np.ndarray,
                        max_evaluations: int = 100, tolerance: float = 1e-14) -> PAResult:
    """Minimise f_PA (eq:PAtotal2) over (R_ij, unit t_ij) from a start pose."""
    x_i = np.asarray(x_i, dtype=float)[:, :2]
    x_j = np.asarray(x_j, dtype=float)[:, :2]
    R0 = np.asarray(R_init, dtype=float)
    t0 = np.asarray(t_init, dtype=float)
    t0 = t0 / np.linalg.norm(t0)
    B = _tangent_basis(t0)

    def unpack(p: np.ndarray):
        raw_t = t0 + B @ p[3:5]
        return cayley_to_rotation(p[:3]) @ R0, raw_t / _norm(raw_t)

    def residuals(p: np.ndarray) -> np.ndarray:
        R, t = unpack(p)
        return pa_residuals(R, t, x_i, x_j).ravel()

    def jacobian(p: np.ndarray) -> np.ndarray:
        cols = []
        for k in range(5):
            pc = p.astype(complex)
            pc[k] += 1j * _COMPLEX_STEP
            cols.append(residuals(pc).imag / _COMPLEX_STEP)
        return np.stack(cols, axis=1)

    p0 = np.zeros(5)
    r0 = residuals(p0)
    sol = least_squares(residuals, p0, jac=jacobian, method="lm", ftol=tolerance, xtol=tolerance, gtol=tolerance,
                        max_nfev=max_evaluations, x_scale="jac")
    R, t = unpack(sol.x)
    return PAResult(R_j_from_i=R, t_direction=t, initial_cost=float(r0 @ r0), cost=2.0 * float(sol.cost),
                    num_evaluations=int(sol.nfev), success=bool(sol.status > 0))
