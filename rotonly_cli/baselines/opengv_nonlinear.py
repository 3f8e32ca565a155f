"""OpenGV-style non-linear relative-pose refinement (``relative_pose::optimize_nonlinear``),
the paper's "Kneip Nonlin Opt". Reimplemented from algorithms.md §4; benchmark baseline only.

OpenGV frames: view 1 = our view i, view 2 = our view j; ``R12 = R_ijᵀ`` maps view-2 vectors
into frame 1 and ``t12 = −R_ijᵀ t_ij`` is the centre of camera 2 in frame 1.

* 6 parameters x = [t12 (3); cayley(R12) (3)] (‖t12‖ left free, as OpenGV does).
* Per correspondence: triangulate p in frame 1 with the mid-point method
  (OpenGV ``triangulation::triangulate2``) at the current pose, reproject to unit bearings
  r̂1 = p/‖p‖, r̂2 = R12ᵀ(p − t12)/‖·‖, residual (1 − f1·r̂1) + (1 − f2·r̂2): one scalar per point.
  We evaluate 1 − f·r̂ as ‖f − r̂‖²/2 (identical for unit vectors, without cancellation).
* Levenberg–Marquardt with a numerical Jacobian. OpenGV uses forward differences and
  ``ftol = xtol = 10·eps``, ``maxfev = 1000``; we use central differences (the residual is
  quadratic in the angular error, so forward differences stall at ~1e-8 rad even without
  noise) with the same tolerances and evaluation budget.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from rotonly_cli.baselines.kneip import cayley_to_rotation, unit_rows
from rotonly_cli.geometry import so3

_EPS = np.finfo(float).eps


@dataclass
class NonlinearResult:
    R_j_from_i: np.ndarray  # (3, 3)
    t_direction: np.ndarray  # (3,) unit t_ij
    initial_cost: float  # Σ residual² (OpenGV's objective)
    cost: float
    num_evaluations: int
    success: bool


def rotation_to_cayley(R: np.ndarray) -> np.ndarray:
    """Inverse of the Cayley map (valid for rotation angles < π)."""
    return so3.vee(R - R.T) / (1.0 + np.trace(R))


def triangulate_midpoint_frame1(R12: np.ndarray, t12: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    """Mid-point of the closest approach of rays λ f1 and t12 + μ R12 f2 (frame 1), (m, 3)."""
    g2 = f2 @ R12.T
    b0 = f1 @ t12
    b1 = g2 @ t12
    a00 = np.sum(f1 * f1, axis=1)
    a10 = np.sum(f1 * g2, axis=1)
    a11 = -np.sum(g2 * g2, axis=1)
    # normal equations of min ‖λ f1 − t12 − μ g2‖²: [a00, −a10; a10, a11] [λ; μ] = [b0; b1]
    det = a00 * a11 + a10 * a10
    det = np.where(np.abs(det) > 1e-300, det, 1e-300)
    lam = (a11 * b0 + a10 * b1) / det
    mu = (a00 * b1 - a10 * b0) / det
    return 0.5 * (lam[:, None] * f1 + t12 + mu[:, None] * g2)


def nonlinear_residuals(t12: np.ndarray, R12: np.ndarray, f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    p = triangulate_midpoint_frame1(R12, t12, f1, f2)
    r1 = p / np.linalg.norm(p, axis=1, keepdims=True)
    q = (p - t12) @ R12  # R12ᵀ (p − t12), rows
    r2 = q / np.linalg.norm(q, axis=1, keepdims=True)
    return 0.5 * (np.sum((f1 - r1) ** 2, axis=1) + np.sum((f2 - r2) ** 2, axis=1))


def optimize_nonlinear_twoview(R_init: np.ndarray, t_init: np.ndarray, x_i: np.ndarray, x_j: np.ndarray,
                               max_evaluations: int = 1000) -> NonlinearResult:
    """OpenGV-style 6-DoF refinement from a start pose (R_ij, t_ij) on matches (x_i, x_j)."""
    f1 = unit_rows(np.asarray(x_i, dtype=float))  # view 1 = i
    f2 = unit_rows(np.asarray(x_j, dtype=float))
    R12_0 = np.asarray(R_init, dtype=float).T
    t_init = np.asarray(t_init, dtype=float)
    t12_0 = -R12_0 @ (t_init / np.linalg.norm(t_init))
    x0 = np.concatenate([t12_0, rotation_to_cayley(R12_0)])

    def residuals(x: np.ndarray) -> np.ndarray:
        return nonlinear_residuals(x[:3], cayley_to_rotation(x[3:]), f1, f2)

    def jacobian(x: np.ndarray) -> np.ndarray:
        cols = []
        for k in range(6):
            h = np.sqrt(np.sqrt(_EPS)) * 1e-2 * max(1.0, abs(x[k]))  # ~1e-6: central-difference optimum
            d = np.zeros(6)
            d[k] = h
            cols.append((residuals(x + d) - residuals(x - d)) / (2 * h))
        return np.stack(cols, axis=1)

    r0 = residuals(x0)
    tol = 10 * _EPS
    sol = least_squares(residuals, x0, jac=jacobian, method="lm", ftol=tol, xtol=tol, gtol=tol,
                        max_nfev=max(1, max_evaluations // 13))  # 1 + 12 residual evaluations per step
    R12 = cayley_to_rotation(sol.x[3:])
    t12 = sol.x[:3]
    R = R12.T
    t = -R @ t12
    return NonlinearResult(R_j_from_i=R, t_direction=t / np.linalg.norm(t), initial_cost=float(r0 @ r0),
                           cost=2.0 * float(sol.cost), num_evaluations=int(sol.nfev) * 13,
                           success=bool(sol.status > 0))
