"""The focal length of a rotating camera (a panorama): with a rotation only between two views
of one camera, x_j ~ K R K⁻¹ x_i, so at the true focal length the bearings of every pair are
one rotation apart (the paper's PR case, eq:PureRotationReprojBearingError) and at any other
they are not (Hartley, "Self-calibration from multiple views with a rotating camera", ECCV
1994). The focal length minimises the pairs' pure-rotation residuals: a one-dimensional search.

Input: per pair, the matched keypoints as undistorted pixel offsets from the principal point.
Pure math (arrays in, arrays out)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rotonly_cli.geometry import kernels
from rotonly_cli.geometry import pairwise as pg


@dataclass
class RotatingCameraFit:
    focal_px: float  #: the minimiser
    residual_px: np.ndarray  #: per pair, the median pure-rotation residual at it (pixels)
    interior: bool  #: whether the minimiser lies inside the searched range (not at a bound)


def pure_rotation_residuals_px(u_i: Sequence[np.ndarray], u_j: Sequence[np.ndarray], focal_px: float) -> np.ndarray:
    """Per pair, the median over its matches of ‖x̂_j − R* x̂_i‖ · f (pixels): the bearings at
    ``focal_px`` against the best pure rotation R* (robust orthogonal Procrustes)."""
    batch = pg.pack_edges([np.asarray(u, dtype=float) / focal_px for u in u_i],
                          [np.asarray(u, dtype=float) / focal_px for u in u_j])
    table = kernels.MatchTable.from_batch(batch)
    R = kernels.best_pure_rotation(table, robust_iterations=2)  # as the PR/B/I test fits it
    return np.sqrt(kernels.segment_median(kernels.rotated_bearing_sq(R, table), table.offsets)) * focal_px


def rotating_camera_focal(u_i: Sequence[np.ndarray], u_j: Sequence[np.ndarray], focal_guess_px: float,
                          min_scale: float = 0.25, max_scale: float = 4.0, grid: int = 41) -> RotatingCameraFit:
    """The focal length in [min_scale, max_scale] x ``focal_guess_px`` that minimises the sum
    over the pairs of their squared median pure-rotation residuals (pixels): the best of a
    log-spaced grid, then a bounded scalar search between its neighbours."""
    from scipy.optimize import minimize_scalar

    def cost(log_f: float) -> float:
        return float(np.sum(pure_rotation_residuals_px(u_i, u_j, float(np.exp(log_f))) ** 2))

    logs = np.log(focal_guess_px) + np.linspace(np.log(min_scale), np.log(max_scale), grid)
    costs = np.array([cost(v) for v in logs])
    best = int(np.argmin(costs))
    lo, hi = logs[max(best - 1, 0)], logs[min(best + 1, grid - 1)]
    found = minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": 1e-6})
    log_f = float(found.x) if found.fun <= costs[best] else float(logs[best])
    focal = float(np.exp(log_f))
    return RotatingCameraFit(focal, pure_rotation_residuals_px(u_i, u_j, focal), 0 < best < grid - 1)
