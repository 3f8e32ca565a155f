"""Two-view bundle adjustment baseline (points + relative pose), for the benchmarks.

Model (rotonly conventions): view i is the reference (R_i = I, c_i = 0), points P_k are held
in the camera-i frame, view j sees Q_k = R_ij P_k + t_ij (eq:two-view_imaging_equation with
depths made explicit). Residuals are the classical reprojection errors in normalized
coordinates of both views (eq. of "Under the influence of noise observations, the
reprojection residual of BA ..."), 4 m of them. Gauge: ||t_ij|| = 1.

Parameters: w (3) with R_ij = exp([w]x) R_0, s (2) with t = (t_0 + B s)/||t_0 + B s|| (B a
basis of t_0's tangent plane), and the 3 m point coordinates. The Jacobian is exact
(the left Jacobian of SO(3) for w) and sparse (each residual pair touches 5 + 3 columns),
solved by scipy ``least_squares`` (trust-region reflective, sparse LSMR).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from rotonly_cli.geometry import so3


@dataclass
class TwoViewBAResult:
    R_j_from_i: np.ndarray  # (3, 3)
    t_direction: np.ndarray  # (3,) unit
    points_in_i: np.ndarray  # (m, 3)
    initial_cost: float  # 0.5 * sum of squared normalized residuals
    cost: float
    num_evaluations: int
    success: bool


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """J_l(w) with d/dw exp([w]x) v = -[exp([w]x) v]x J_l(w) ... (applied to the rotated point)."""
    theta = float(np.linalg.norm(w))
    K = so3.hat(w)
    if theta < 1e-8:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    return (np.eye(3) + (1.0 - np.cos(theta)) / theta**2 * K
            + (theta - np.sin(theta)) / theta**3 * (K @ K))


def _tangent_basis(t: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis of the plane orthogonal to unit ``t``."""
    helper = np.eye(3)[np.argmin(np.abs(t))]
    b1 = np.cross(t, helper)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, np.cross(t, b1)])


def triangulate_midpoint(R_j_from_i: np.ndarray, t_j_from_i: np.ndarray, x_i: np.ndarray, x_j: np.ndarray,
                         fallback_depth: float = 100.0) -> np.ndarray:
    """Points in frame i from z_j x_j = z_i R x_i + t in least squares (2x2 system per match).

    Depths that are not finite or not positive (no parallax, e.g. pure rotation) are replaced by
    the median of the good ones (or ``fallback_depth``), so BA starts from a valid point set.
    """
    xi = np.column_stack([x_i[:, :2], np.ones(len(x_i))])
    xj = np.column_stack([x_j[:, :2], np.ones(len(x_j))])
    a = xi @ R_j_from_i.T  # R x_i
    b = xj
    # minimise || z_i a - z_j b + t ||: normal equations [a.a, -a.b; -a.b, b.b] [z_i, z_j] = [-a.t, b.t]
    aa, bb, ab = np.sum(a * a, 1), np.sum(b * b, 1), np.sum(a * b, 1)
    at, bt = a @ t_j_from_i, b @ t_j_from_i
    det = aa * bb - ab * ab
    ok = det > 1e-12 * aa * bb
    safe = np.where(ok, det, 1.0)
    z_i = (-at * bb + ab * bt) / safe
    z_j = (aa * bt - ab * at) / safe
    good = ok & (z_i > 0) & (z_j > 0) & np.isfinite(z_i)
    fill = float(np.median(z_i[good])) if np.any(good) else fallback_depth
    z_i = np.where(good, z_i, fill)
    return xi * z_i[:, None]


def _project_jac(Q: np.ndarray) -> np.ndarray:
    """(m, 2, 3) derivative of (Q_x/Q_z, Q_y/Q_z) with respect to Q."""
    inv_z = 1.0 / Q[:, 2]
    J = np.zeros((len(Q), 2, 3))
    J[:, 0, 0] = inv_z
    J[:, 1, 1] = inv_z
    J[:, 0, 2] = -Q[:, 0] * inv_z**2
    J[:, 1, 2] = -Q[:, 1] * inv_z**2
    return J


def bundle_adjust_twoview(R_init: np.ndarray, t_init: np.ndarray, x_i: np.ndarray, x_j: np.ndarray,
                          points_init: np.ndarray | None = None, max_evaluations: int = 50,
                          tolerance: float = 1e-12, max_inner_iterations: int = 300) -> TwoViewBAResult:
    """Minimise the two-view reprojection error over (R_ij, unit t_ij, points).

    The LSMR sub-problem tolerances are tightened to 1e-12 (scipy's 1e-6 default makes
    the trust-region steps so inexact that a regular scene needs 100+ evaluations instead
    of about 6); ``max_inner_iterations`` bounds LSMR on degenerate scenes (Holoplane,
    pure rotation) where the normal equations are singular.
    """
    x_i = np.asarray(x_i, dtype=float)[:, :2]
    x_j = np.asarray(x_j, dtype=float)[:, :2]
    m = len(x_i)
    R0 = np.asarray(R_init, dtype=float)
    t0 = np.asarray(t_init, dtype=float)
    t0 = t0 / np.linalg.norm(t0)
    B = _tangent_basis(t0)
    P0 = triangulate_midpoint(R0, t0, x_i, x_j) if points_init is None else np.asarray(points_init, float)

    def unpack(params: np.ndarray):
        w, s, P = params[:3], params[3:5], params[5:].reshape(m, 3)
        raw_t = t0 + B @ s
        return so3.exp(w) @ R0, raw_t, P

    def residuals(params: np.ndarray) -> np.ndarray:
        R, raw_t, P = unpack(params)
        t = raw_t / np.linalg.norm(raw_t)
        Q = P @ R.T + t
        r_i = P[:, :2] / P[:, 2:3] - x_i
        r_j = Q[:, :2] / Q[:, 2:3] - x_j
        return np.concatenate([r_i.ravel(), r_j.ravel()])

    # sparsity pattern: rows 0..2m-1 view i (point block only), 2m..4m-1 view j (5 pose + point)
    k = np.arange(m)
    rows_i = np.repeat(np.arange(2 * m), 3)
    cols_i = (5 + 3 * np.repeat(k, 2)[:, None] + np.arange(3)).ravel()
    rows_j = np.repeat(2 * m + np.arange(2 * m), 8)
    cols_j = np.concatenate([np.broadcast_to(np.arange(5), (2 * m, 5)),
                             5 + 3 * np.repeat(k, 2)[:, None] + np.arange(3)], axis=1).ravel()
    rows = np.concatenate([rows_i, rows_j])
    cols = np.concatenate([cols_i, cols_j])
    shape = (4 * m, 5 + 3 * m)

    def jacobian(params: np.ndarray) -> sp.csr_matrix:
        R, raw_t, P = unpack(params)
        norm_t = np.linalg.norm(raw_t)
        t = raw_t / norm_t
        RP = P @ R.T
        Q = RP + t
        Ji = _project_jac(P)  # (m, 2, 3)
        Jj = _project_jac(Q)
        # d(RP)/dw = -[RP]x J_l(w); dt/ds = (I - t t^T)/||raw_t|| B; dQ/dP = R
        dQ_dw = -so3.hat(RP) @ _left_jacobian(params[:3])  # (m, 3, 3)
        dt_ds = (np.eye(3) - np.outer(t, t)) / norm_t @ B  # (3, 2)
        block_pose = np.concatenate([Jj @ dQ_dw, Jj @ dt_ds], axis=2)  # (m, 2, 5)
        block_point_j = Jj @ R  # (m, 2, 3)
        vals_i = Ji.reshape(-1)
        vals_j = np.concatenate([block_pose, block_point_j], axis=2).reshape(-1)
        return sp.csr_matrix((np.concatenate([vals_i, vals_j]), (rows, cols)), shape=shape)

    params0 = np.concatenate([np.zeros(5), P0.ravel()])
    r0 = residuals(params0)
    sol = least_squares(residuals, params0, jac=jacobian, method="trf", tr_solver="lsmr", x_scale="jac",
                        tr_options=dict(atol=1e-12, btol=1e-12, maxiter=max_inner_iterations),
                        ftol=tolerance, xtol=tolerance, gtol=tolerance, max_nfev=max_evaluations)
    R, raw_t, P = unpack(sol.x)
    return TwoViewBAResult(R_j_from_i=R, t_direction=raw_t / np.linalg.norm(raw_t), points_in_i=P,
                           initial_cost=0.5 * float(r0 @ r0), cost=float(sol.cost),
                           num_evaluations=int(sol.nfev), success=bool(sol.status > 0))
