"""Robust losses ρ(s) of a squared residual norm s, shared by TRRM and GRRM (Ceres' convention:
ρ(s) ≈ s near 0), and the second-order terms GRRM's Hessian uses."""

from __future__ import annotations

import numpy as np

from rotonly_cli.options import RobustLoss  # noqa: F401 (re-exported)


def robust_curvature(sq_norm: np.ndarray, loss: str, scale: float) -> np.ndarray:
    """β = -2 s ρ''(s) / ρ'(s), clamped to [0, 1]: with it, ρ'(I - β v̂v̂ᵀ) is the exact
    Hessian of ρ(‖V‖²) w.r.t. V (up to the factor 2), kept positive semi-definite.

    Without it (plain IRLS weights ρ') LM converges only linearly under a robust loss
    (measured ratio ~0.5 per iteration); this is Triggs et al.'s correction
    ("Bundle adjustment — a modern synthesis", §4.3), which Ceres applies only for ρ'' > 0.
    Here ρ'' < 0 (Cauchy, Huber) and the clamp β ≤ 1 drops only the radial curvature of
    observations beyond the loss scale, so the damped system stays positive definite.
    """
    if loss == "none":
        return np.zeros_like(sq_norm)
    u = sq_norm / (scale * scale)
    if loss == "huber":
        return (u > 1.0).astype(float)
    if loss == "geman_mcclure":
        return np.minimum(4.0 * u / (1.0 + u), 1.0)
    return np.minimum(2.0 * u / (1.0 + u), 1.0)  # cauchy


def radial_excess(sq_norm: np.ndarray, loss: str, scale: float) -> np.ndarray:
    """(β - 1)₊ of the unclamped β = -2 s ρ''(s) / ρ'(s) (see robust_curvature): Cauchy's
    β = 2u / (1 + u) exceeds 1 beyond the loss scale (u > 1), Geman-McClure's 4u / (1 + u)
    beyond u = 1/3; Huber's is at most 1."""
    if loss not in ("cauchy", "geman_mcclure"):
        return np.zeros_like(sq_norm)
    u = sq_norm / (scale * scale)
    factor = 4.0 if loss == "geman_mcclure" else 2.0
    return np.maximum(factor * u / (1.0 + u) - 1.0, 0.0)


def robust_rho(sq_norm: np.ndarray, loss: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """ρ(s) and ρ'(s) of a squared norm s (Ceres' convention: ρ(s) ≈ s near 0)."""
    if loss == "none":
        return sq_norm, np.ones_like(sq_norm)
    c2 = scale * scale
    if loss == "huber":
        small = sq_norm <= c2
        root = np.sqrt(sq_norm)
        rho = np.where(small, sq_norm, 2.0 * scale * root - c2)
        drho = np.where(small, 1.0, scale / np.where(small, 1.0, root))
        return rho, drho
    if loss == "geman_mcclure":
        inv = c2 / (c2 + sq_norm)
        return sq_norm * inv, inv * inv
    rho = c2 * np.log1p(sq_norm / c2)  # cauchy
    drho = 1.0 / (1.0 + sq_norm / c2)
    return rho, drho
